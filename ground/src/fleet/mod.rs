//! MAVLink 2 fleet links: the ground station's side (system id 255).
//!
//! Pure parts, usable without a socket:
//! * [`skyherd_link::codec`]: framing, signing and parsing with counted drops.
//! * [`vehicle`]: per-vehicle state (mode, armed, LOCAL_POSITION_NED, battery, link quality).
//! * [`skyherd_link::command`]: arm/disarm, set mode, velocity setpoints, COMMAND_ACK matching.
//!
//! The shell, [`GroundLink`], owns one transport (UDP, TCP or serial, opened from the same
//! address strings as `mavlink::connect`: `udpin:`, `udpout:`, `tcpout:`, `serial:`), sends
//! the 1 Hz heartbeat, folds every received frame into the [`Fleet`], matches ACKs, and logs
//! every frame in and out to an optional `.tlog`. Time is the caller's: every call takes
//! `now` in seconds (a simulated clock in lockstep SITL, or wall time in a daemon).
//!
//! ```no_run
//! use skyherd_ground::fleet::{GroundLink, LinkConfig};
//! use std::time::Duration;
//!
//! let mut link = GroundLink::open("udpin:0.0.0.0:14550", LinkConfig::default()).unwrap();
//! let mut now = 0.0;
//! loop {
//!     link.tick(now).unwrap(); // heartbeat when due, expire commands
//!     link.poll(now, Duration::from_millis(100)).unwrap();
//!     for v in link.fleet().iter() {
//!         println!("{} armed={} at {:?}", v.system_id, v.armed, v.position_sim());
//!     }
//!     now += 0.1;
//! }
//! ```

pub mod vehicle;

use std::collections::BTreeMap;
use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs, UdpSocket};
use std::str::FromStr;
use std::time::{Duration, Instant};

use mavlink::dialects::common::{MavMessage, MavResult};
use thiserror::Error;

use skyherd_link::command;
use skyherd_link::{
    Codec, CodecStats, CommandOutcome, CommandResult, Frame, GROUND_COMPONENT_ID, GROUND_SYSTEM_ID,
    PendingCommands, Signing,
};
pub use vehicle::{Fleet, LinkQuality, VehicleState};

use crate::tlog::TlogWriter;

/// Where a link goes, in `mavlink::connect` syntax.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Address {
    /// `udpin:host:port`: bind and answer whoever sends to us.
    UdpIn(SocketAddr),
    /// `udpout:host:port`: bind an ephemeral port and send to this peer.
    UdpOut(SocketAddr),
    /// `tcpout:host:port`: connect to a TCP server.
    TcpOut(SocketAddr),
    /// `serial:path:baud`: a serial port.
    Serial {
        /// Device path, e.g. `/dev/ttyAMA0`.
        path: String,
        /// Baud rate.
        baud: u32,
    },
}

/// Why a link failed.
#[derive(Debug, Error)]
pub enum LinkError {
    /// The address string is not `udpin:`, `udpout:`, `tcpout:` or `serial:` followed by a
    /// valid address.
    #[error(
        "bad link address {0:?}: expected udpin:HOST:PORT, udpout:HOST:PORT, tcpout:HOST:PORT or serial:PATH:BAUD"
    )]
    BadAddress(String),
    /// Socket or port I/O failed.
    #[error("link I/O error: {0}")]
    Io(#[from] io::Error),
    /// Opening the serial port failed.
    #[error("serial port error: {0}")]
    Serial(String),
    /// No peer address is known yet to send to (udpin before any vehicle spoke).
    #[error("no peer known for system {0}")]
    NoPeer(u8),
    /// [`GroundLink::run_command`] was given something other than a COMMAND_LONG.
    #[error("expected a COMMAND_LONG, got {0}")]
    NotACommand(&'static str),
    /// A blocking command got no COMMAND_ACK in time.
    #[error("command {command} to system {system_id} not acknowledged within {timeout:?}")]
    CommandTimeout {
        /// Vehicle.
        system_id: u8,
        /// Command name.
        command: String,
        /// How long we waited.
        timeout: Duration,
    },
}

impl FromStr for Address {
    type Err = LinkError;

    fn from_str(s: &str) -> Result<Self, LinkError> {
        let bad = || LinkError::BadAddress(s.to_string());
        let (kind, rest) = s.split_once(':').ok_or_else(bad)?;
        let socket = || -> Result<SocketAddr, LinkError> {
            rest.to_socket_addrs()
                .map_err(|_| bad())?
                .next()
                .ok_or_else(bad)
        };
        match kind {
            "udpin" => Ok(Self::UdpIn(socket()?)),
            "udpout" => Ok(Self::UdpOut(socket()?)),
            "tcpout" => Ok(Self::TcpOut(socket()?)),
            "serial" => {
                let (path, baud) = rest.rsplit_once(':').ok_or_else(bad)?;
                let baud = baud.parse().map_err(|_| bad())?;
                if path.is_empty() {
                    return Err(bad());
                }
                Ok(Self::Serial {
                    path: path.to_string(),
                    baud,
                })
            }
            _ => Err(bad()),
        }
    }
}

/// Options of a [`GroundLink`].
#[derive(Debug, Clone)]
pub struct LinkConfig {
    /// Our system id (255 for the ground station).
    pub system_id: u8,
    /// Our component id.
    pub component_id: u8,
    /// MAVLink 2 signing; None = unsigned.
    pub signing: Option<Signing>,
    /// Heartbeat period (s).
    pub heartbeat_period: f64,
    /// How long a command waits for its COMMAND_ACK (s, caller's clock).
    pub command_timeout: f64,
    /// Unix time (us) that `now = 0` maps to in the `.tlog`.
    pub tlog_epoch_us: u64,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            system_id: GROUND_SYSTEM_ID,
            component_id: GROUND_COMPONENT_ID,
            signing: None,
            heartbeat_period: 1.0,
            command_timeout: 1.5,
            tlog_epoch_us: unix_now_us(),
        }
    }
}

/// Wall-clock microseconds since the Unix epoch (0 if the clock is before 1970).
pub(crate) fn unix_now_us() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}

enum Transport {
    Udp {
        socket: UdpSocket,
        /// udpout's fixed peer.
        fixed_peer: Option<SocketAddr>,
        /// Where each system last spoke from (udpin answers there).
        peers: BTreeMap<u8, SocketAddr>,
    },
    Tcp(TcpStream),
    Serial(Box<dyn serialport::SerialPort>),
}

/// The ground station's end of one MAVLink link; see the [module docs](self).
pub struct GroundLink {
    transport: Transport,
    codec: Codec,
    config: LinkConfig,
    fleet: Fleet,
    commands: PendingCommands,
    results: Vec<CommandResult>,
    next_heartbeat: f64,
    last_now: f64,
    tlog: Option<TlogWriter<Box<dyn Write + Send>>>,
    buffer: Vec<u8>,
    frames: Vec<Frame>,
}

impl std::fmt::Debug for GroundLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GroundLink")
            .field("codec", &self.codec)
            .field("vehicles", &self.fleet.len())
            .finish()
    }
}

/// The receive buffer a listening link asks for, bytes. A fleet link hears every vehicle and
/// the sensor: a simulator's scan of 256 targets is 257 datagrams at once, which overflow
/// Linux's default 208 KiB (a datagram costs about 768 bytes of buffer however small), and a
/// lost end-of-scan stalls the lockstep. The kernel grants at most `net.core.rmem_max`.
const RECEIVE_BUFFER_BYTES: libc::c_int = 4 << 20;

/// Asks for [`RECEIVE_BUFFER_BYTES`] of receive buffer; best effort (a smaller grant, or a
/// refusal, leaves the link as it was).
#[cfg(unix)]
fn enlarge_receive_buffer(socket: &UdpSocket) {
    use std::os::fd::AsRawFd;
    let size = RECEIVE_BUFFER_BYTES;
    // SAFETY: setsockopt(2) on a socket this process owns, with a pointer to a c_int that
    // outlives the call and its exact size; it writes no memory of ours.
    #[allow(unsafe_code)]
    let _ = unsafe {
        libc::setsockopt(
            socket.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&raw const size).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
}

#[cfg(not(unix))]
fn enlarge_receive_buffer(_socket: &UdpSocket) {}

impl GroundLink {
    /// Open a link from an address string (`udpin:0.0.0.0:14550`, `udpout:127.0.0.1:14551`,
    /// `tcpout:127.0.0.1:5760`, `serial:/dev/ttyUSB0:921600`).
    ///
    /// # Errors
    /// [`LinkError::BadAddress`], or the I/O error of opening it.
    pub fn open(address: &str, config: LinkConfig) -> Result<Self, LinkError> {
        let transport = match address.parse::<Address>()? {
            Address::UdpIn(addr) => {
                let socket = UdpSocket::bind(addr)?;
                enlarge_receive_buffer(&socket);
                Transport::Udp {
                    socket,
                    fixed_peer: None,
                    peers: BTreeMap::new(),
                }
            }
            Address::UdpOut(addr) => {
                let bind: SocketAddr = if addr.is_ipv4() {
                    ([0, 0, 0, 0], 0).into()
                } else {
                    (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
                };
                Transport::Udp {
                    socket: UdpSocket::bind(bind)?,
                    fixed_peer: Some(addr),
                    peers: BTreeMap::new(),
                }
            }
            Address::TcpOut(addr) => {
                let stream = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
                stream.set_nodelay(true)?;
                Transport::Tcp(stream)
            }
            Address::Serial { path, baud } => Transport::Serial(
                serialport::new(&path, baud)
                    .timeout(Duration::from_millis(10))
                    .open()
                    .map_err(|e| LinkError::Serial(format!("{path}: {e}")))?,
            ),
        };
        Ok(Self::with_transport(transport, config))
    }

    /// A link over an already bound UDP socket (e.g. an ephemeral port in tests), sending to
    /// `peer` until vehicles are heard.
    pub fn from_udp_socket(
        socket: UdpSocket,
        peer: Option<SocketAddr>,
        config: LinkConfig,
    ) -> Self {
        Self::with_transport(
            Transport::Udp {
                socket,
                fixed_peer: peer,
                peers: BTreeMap::new(),
            },
            config,
        )
    }

    fn with_transport(transport: Transport, config: LinkConfig) -> Self {
        Self {
            transport,
            codec: Codec::new(
                config.system_id,
                config.component_id,
                config.signing.clone(),
            ),
            config,
            fleet: Fleet::default(),
            commands: PendingCommands::default(),
            results: Vec::new(),
            next_heartbeat: f64::NEG_INFINITY,
            last_now: 0.0,
            tlog: None,
            buffer: vec![0u8; 65_536],
            frames: Vec::new(),
        }
    }

    /// Log every frame sent and received from now on to `out` in `.tlog` format.
    pub fn log_to(&mut self, out: Box<dyn Write + Send>) {
        self.tlog = Some(TlogWriter::new(out));
    }

    /// Flush the `.tlog`, if any.
    ///
    /// # Errors
    /// The writer's I/O error.
    pub fn flush_log(&mut self) -> io::Result<()> {
        self.tlog.as_mut().map_or(Ok(()), TlogWriter::flush)
    }

    /// The local address of a UDP link (None for TCP/serial).
    pub fn local_addr(&self) -> Option<SocketAddr> {
        match &self.transport {
            Transport::Udp { socket, .. } => socket.local_addr().ok(),
            _ => None,
        }
    }

    /// Vehicles heard so far.
    pub fn fleet(&self) -> &Fleet {
        &self.fleet
    }

    /// Frames accepted and dropped, by reason.
    pub fn stats(&self) -> &CodecStats {
        self.codec.stats()
    }

    /// Send the heartbeat when due and time out unanswered commands. Call at >= 1 Hz.
    ///
    /// # Errors
    /// I/O errors of the transport.
    pub fn tick(&mut self, now: f64) -> Result<(), LinkError> {
        self.last_now = now;
        if now >= self.next_heartbeat {
            self.next_heartbeat = now + self.config.heartbeat_period;
            self.broadcast(&command::gcs_heartbeat())?;
        }
        let expired = self.commands.expire(now);
        self.results.extend(expired);
        Ok(())
    }

    /// Receive for up to `wait` (wall time; zero = only what is already there), fold every
    /// frame into the fleet and match ACKs. Returns the frames received, for the caller's
    /// own use (TUNNEL uplink traffic and the like).
    ///
    /// # Errors
    /// I/O errors of the transport other than a timeout.
    pub fn poll(&mut self, now: f64, wait: Duration) -> Result<Vec<Frame>, LinkError> {
        self.last_now = now;
        let mut first = true;
        loop {
            let got = self.receive_once(if first { wait } else { Duration::ZERO })?;
            first = false;
            if !got {
                break;
            }
        }
        let frames = std::mem::take(&mut self.frames);
        let stamp = self.tlog_time(now);
        for frame in &frames {
            if let Some(tlog) = &mut self.tlog {
                tlog.write_frame(stamp, &frame.raw)?;
            }
            self.fleet
                .on_frame(&frame.header, &frame.message, now, self.config.system_id);
            if let (MavMessage::COMMAND_ACK(ack), Ok(system_id)) =
                (&frame.message, u8::try_from(frame.header.system_id))
                && let Some(result) = self.commands.on_ack(
                    system_id,
                    ack,
                    (self.config.system_id, self.config.component_id),
                )
            {
                self.results.push(result);
            }
        }
        Ok(frames)
    }

    /// One read from the transport; false when nothing arrived in time.
    fn receive_once(&mut self, wait: Duration) -> Result<bool, LinkError> {
        let timeout = (!wait.is_zero()).then_some(wait);
        let result = match &mut self.transport {
            Transport::Udp { socket, peers, .. } => {
                socket.set_nonblocking(timeout.is_none())?;
                socket.set_read_timeout(timeout)?;
                match socket.recv_from(&mut self.buffer) {
                    Ok((n, from)) => {
                        let before = self.frames.len();
                        self.codec.decode(&self.buffer[..n], &mut self.frames);
                        // Learn where each system speaks from, to answer it there.
                        for f in &self.frames[before..] {
                            if let Ok(id) = u8::try_from(f.header.system_id) {
                                peers.insert(id, from);
                            }
                        }
                        Ok(true)
                    }
                    Err(e) => Err(e),
                }
            }
            Transport::Tcp(stream) => {
                stream.set_nonblocking(timeout.is_none())?;
                stream.set_read_timeout(timeout)?;
                match stream.read(&mut self.buffer) {
                    Ok(0) => Err(io::Error::new(
                        io::ErrorKind::ConnectionAborted,
                        "TCP peer closed the link",
                    )),
                    Ok(n) => {
                        self.codec
                            .decode_stream(&self.buffer[..n], &mut self.frames);
                        Ok(true)
                    }
                    Err(e) => Err(e),
                }
            }
            Transport::Serial(port) => {
                port.set_timeout(wait.max(Duration::from_millis(1)))
                    .map_err(|e| LinkError::Serial(e.to_string()))?;
                match port.read(&mut self.buffer) {
                    Ok(n) => {
                        self.codec
                            .decode_stream(&self.buffer[..n], &mut self.frames);
                        Ok(n > 0)
                    }
                    Err(e) => Err(e),
                }
            }
        };
        match result {
            Ok(got) => Ok(got),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                Ok(false)
            }
            // A previous datagram to a closed port (ICMP unreachable): not fatal for UDP.
            Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => Ok(true),
            Err(e) => Err(e.into()),
        }
    }

    /// Send one message to one vehicle.
    ///
    /// # Errors
    /// [`LinkError::NoPeer`] on udpin before the vehicle spoke; I/O errors.
    pub fn send_to(&mut self, system_id: u8, message: &MavMessage) -> Result<(), LinkError> {
        let bytes = self.codec.encode(message);
        self.log_sent(&bytes)?;
        match &mut self.transport {
            Transport::Udp {
                socket,
                fixed_peer,
                peers,
            } => {
                let peer = peers
                    .get(&system_id)
                    .copied()
                    .or(*fixed_peer)
                    .ok_or(LinkError::NoPeer(system_id))?;
                send_udp(socket, &bytes, peer)
            }
            Transport::Tcp(stream) => Ok(stream.write_all(&bytes)?),
            Transport::Serial(port) => Ok(port.write_all(&bytes)?),
        }
    }

    /// Send one message to every known peer (heartbeats, broadcasts).
    ///
    /// # Errors
    /// I/O errors of the transport.
    pub fn broadcast(&mut self, message: &MavMessage) -> Result<(), LinkError> {
        let bytes = self.codec.encode(message);
        self.log_sent(&bytes)?;
        match &mut self.transport {
            Transport::Udp {
                socket,
                fixed_peer,
                peers,
            } => {
                let mut targets: Vec<SocketAddr> = peers.values().copied().collect();
                targets.extend(*fixed_peer);
                targets.sort();
                targets.dedup();
                for peer in targets {
                    send_udp(socket, &bytes, peer)?;
                }
                Ok(())
            }
            Transport::Tcp(stream) => Ok(stream.write_all(&bytes)?),
            Transport::Serial(port) => Ok(port.write_all(&bytes)?),
        }
    }

    /// Send a COMMAND_LONG (from [`command`]) and start waiting for its ACK; the outcome
    /// comes out of [`Self::take_command_results`] after a later [`Self::poll`] or
    /// [`Self::tick`].
    ///
    /// # Errors
    /// As [`Self::send_to`].
    pub fn send_command(
        &mut self,
        system_id: u8,
        message: &MavMessage,
        now: f64,
    ) -> Result<(), LinkError> {
        if let MavMessage::COMMAND_LONG(c) = message {
            self.commands
                .start(system_id, c.command, now, self.config.command_timeout);
        }
        self.send_to(system_id, message)
    }

    /// Finished commands (acknowledged or timed out) since the last call.
    pub fn take_command_results(&mut self) -> Vec<CommandResult> {
        std::mem::take(&mut self.results)
    }

    /// Send a command and wait (wall clock, up to `timeout`) for its ACK, polling the link
    /// meanwhile. For processes whose peers run on their own (not lockstep).
    ///
    /// # Errors
    /// [`LinkError::CommandTimeout`], or I/O errors.
    pub fn run_command(
        &mut self,
        system_id: u8,
        message: &MavMessage,
        timeout: Duration,
    ) -> Result<MavResult, LinkError> {
        let MavMessage::COMMAND_LONG(c) = message else {
            return Err(LinkError::NotACommand(mavlink::Message::message_name(
                message,
            )));
        };
        let command = c.command;
        let start = Instant::now();
        let base = self.last_now;
        self.commands
            .start(system_id, command, base, timeout.as_secs_f64() + 1.0);
        self.send_to(system_id, message)?;
        while start.elapsed() < timeout {
            let now = base + start.elapsed().as_secs_f64();
            self.poll(now, Duration::from_millis(10))?;
            let results = std::mem::take(&mut self.results);
            let mut answer = None;
            for r in results {
                if r.system_id == system_id && r.command == command {
                    if let CommandOutcome::Acked(result) = r.outcome {
                        answer = Some(result);
                    }
                } else {
                    self.results.push(r);
                }
            }
            if let Some(result) = answer {
                return Ok(result);
            }
        }
        Err(LinkError::CommandTimeout {
            system_id,
            command: format!("{command:?}"),
            timeout,
        })
    }

    fn tlog_time(&self, now: f64) -> u64 {
        self.config
            .tlog_epoch_us
            .saturating_add((now.max(0.0) * 1e6) as u64)
    }

    fn log_sent(&mut self, bytes: &[u8]) -> io::Result<()> {
        let t = self.tlog_time(self.last_now);
        if let Some(tlog) = &mut self.tlog {
            tlog.write_frame(t, bytes)?;
        }
        Ok(())
    }
}

fn send_udp(socket: &UdpSocket, bytes: &[u8], peer: SocketAddr) -> Result<(), LinkError> {
    match socket.send_to(bytes, peer) {
        Ok(_) => Ok(()),
        // An unreachable peer must not take the ground station down; the link-quality age
        // shows it.
        Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => Ok(()),
        Err(e) => Err(e.into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_link::FlightMode;

    #[test]
    fn address_strings() {
        assert_eq!(
            "udpin:127.0.0.1:14550".parse::<Address>().unwrap(),
            Address::UdpIn(([127, 0, 0, 1], 14550).into())
        );
        assert_eq!(
            "serial:/dev/ttyUSB0:921600".parse::<Address>().unwrap(),
            Address::Serial {
                path: "/dev/ttyUSB0".into(),
                baud: 921_600
            }
        );
        for bad in [
            "udp:1.2.3.4:5",
            "udpin:nonsense",
            "serial::9600",
            "serial:/dev/x:fast",
            "",
        ] {
            assert!(
                matches!(bad.parse::<Address>(), Err(LinkError::BadAddress(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn tcp_link_exchanges_frames() {
        use std::net::TcpListener;
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let peer = std::thread::spawn(move || {
            let (mut stream, _) = listener.accept().unwrap();
            let mut codec = Codec::new(9, 1, None);
            let hb = mavlink::dialects::common::MavMessage::HEARTBEAT(
                mavlink::dialects::common::HEARTBEAT_DATA {
                    custom_mode: 4,
                    mavtype: mavlink::dialects::common::MavType::MAV_TYPE_QUADROTOR,
                    autopilot: mavlink::dialects::common::MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                    base_mode: mavlink::dialects::common::MavModeFlag::empty(),
                    system_status: mavlink::dialects::common::MavState::MAV_STATE_STANDBY,
                    mavlink_version: 3,
                },
            );
            let bytes = codec.encode(&hb);
            // Split the frame across two writes: the stream decoder must join them.
            stream.write_all(&bytes[..5]).unwrap();
            stream.flush().unwrap();
            std::thread::sleep(Duration::from_millis(20));
            stream.write_all(&bytes[5..]).unwrap();
            let mut buf = [0u8; 64];
            stream
                .set_read_timeout(Some(Duration::from_secs(2)))
                .unwrap();
            let n = stream.read(&mut buf).unwrap();
            n > 0
        });
        let mut link = GroundLink::open(&format!("tcpout:{addr}"), LinkConfig::default()).unwrap();
        let start = Instant::now();
        while link.fleet().get(9).is_none() && start.elapsed() < Duration::from_secs(3) {
            link.poll(0.0, Duration::from_millis(50)).unwrap();
        }
        assert_eq!(
            link.fleet().get(9).map(|v| v.flight_mode()),
            Some(FlightMode::ARDUPILOT_GUIDED)
        );
        link.tick(0.0).unwrap(); // heartbeat back over TCP
        assert!(peer.join().unwrap());
    }
}
