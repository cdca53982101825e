//! The daemon's thin I/O shell: MAVLink links, signing checks, heartbeats, clocks.
//!
//! Two links, each a [`mavlink`] connection read by its own thread that only forwards what it
//! reads over a channel; the daemon thread owns the [`DaemonCore`] and does all the deciding:
//!
//! * **autopilot** (`udpout:127.0.0.1:14540`, `udpin:0.0.0.0:14540`, `serial:/dev/ttyTHS1:921600`,
//!   `tcpout:…`): HEARTBEAT and LOCAL_POSITION_NED in; SET_POSITION_TARGET_LOCAL_NED
//!   (frame LOCAL_NED, type_mask [`VELOCITY_ONLY_TYPE_MASK`](skyherd_link::VELOCITY_ONLY_TYPE_MASK)), COMMAND_LONG and our HEARTBEAT
//!   out. Unsigned.
//! * **ground** (`udpin:0.0.0.0:14600`, …): TUNNEL frames (payload type 0) carrying the uplink
//!   chunks in. With a signing key every frame must carry a valid MAVLink 2 signature; unsigned
//!   and wrongly signed frames are dropped and counted ([`UplinkGate`]). Our HEARTBEAT out,
//!   signed with the same key, and a STATUSTEXT whenever the core's status changes (so the
//!   ground sees holds and their reasons).
//!
//! Clocks ([`ClockMode`]): wall clock (ticks at `--rate-hz`), or lockstep with a simulator, where
//! the daemon's time is the autopilot's `time_boot_ms` and every LOCAL_POSITION_NED triggers one
//! control tick, answered at least with a HEARTBEAT to the autopilot (the simulator waits for
//! that answer), so the loop runs as fast as the simulator feeds it.

use std::fmt;
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::thread;
use std::time::{Duration, Instant};

use log::{debug, info, warn};
use mavlink::dialects::common::{
    HEARTBEAT_DATA, MavAutopilot, MavCmd, MavMessage, MavModeFlag, MavResult, MavSeverity,
    MavState, MavTunnelPayloadType, MavType, STATUSTEXT_DATA,
};
use mavlink::error::MessageReadError;
use mavlink::{
    Connectable, MAVLinkMessageRaw, MAVLinkV2MessageRaw, MavConnection, MavHeader, MavlinkReader,
    Message, SigningData, UdpConfig, UdpMode,
};

use crate::control::{AutopilotCommand, DaemonCore, Millis, OnboardPolicy, Setpoint, Status};

use skyherd_link::AUTOPILOT_COMPONENT_ID;
/// Our MAVLink component id: `MAV_COMP_ID_ONBOARD_COMPUTER`.
pub use skyherd_link::DAEMON_COMPONENT_ID as COMPONENT_ID;
use skyherd_link::command::{command_long, land, message_interval, velocity_setpoint_ned};
use skyherd_link::replay::{ReplayGuard, ReplayStateError, SignatureError, SigningTime};
use skyherd_link::signing::{SigningKey, signing_data};
/// The LOCAL_POSITION_NED interval the daemon asks for, µs: 10 Hz, the actor's control rate.
pub const POSITION_INTERVAL_US: f32 = 100_000.0;
/// MAVLink message id of LOCAL_POSITION_NED.
const LOCAL_POSITION_NED_ID: u32 = 32;
/// No position for this long (wall time): ask for the stream again.
const POSITION_SILENCE: Duration = Duration::from_millis(1500);

/// HEARTBEAT period, ms of the daemon's clock.
pub const HEARTBEAT_PERIOD: Duration = Duration::from_millis(1000);
/// Slowest control rate accepted, Hz: PX4 leaves OFFBOARD when setpoints come slower than 2 Hz.
pub const MIN_RATE_HZ: f32 = 2.0;
/// Length of a MAVLink 2 signing key.
pub use skyherd_link::signing::KEY_LEN;

type Link = mavlink::Connection<MavMessage>;

/// Where the daemon's time comes from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ClockMode {
    /// Wall clock; one control tick every `1 / rate_hz` seconds.
    Wall {
        /// Control rate, Hz (>= 10 for PX4 OFFBOARD).
        rate_hz: f32,
    },
    /// The autopilot's `time_boot_ms`; one control tick per LOCAL_POSITION_NED. The ground's
    /// snapshots are expected on the same simulated clock: a tick waits for the snapshot of
    /// its instant, briefly (`LOCKSTEP_SNAPSHOT_WAIT`) or, once snapshots keep pace and the
    /// autopilot waits for this daemon, patiently (`LOCKSTEP_SNAPSHOT_PATIENCE`).
    Simulator {
        /// The simulator steps the autopilot only after this daemon's answer (a mock in
        /// lockstep). `false` for an autopilot on its own clock (a real ArduCopter SITL),
        /// whose positions may run ahead of the snapshots: it is never waited on long.
        lockstep: bool,
    },
}

/// How to reach the autopilot and the ground.
#[derive(Clone, Debug)]
pub struct LinkOptions {
    /// Autopilot address, `mavlink::connect` syntax (`udpout:host:port`, `udpin:host:port`,
    /// `serial:/dev/tty…:baud`, `tcpout:host:port`).
    pub autopilot: String,
    /// Ground address, same syntax.
    pub ground: String,
    /// MAVLink 2 signing key for the ground link; `None` accepts unsigned uplink (tests only).
    pub signing_key: Option<[u8; KEY_LEN]>,
    /// MAVLink 2 signing key for the autopilot link: every frame to the autopilot is signed
    /// and unsigned or wrongly signed frames from it are dropped, so that a configured
    /// autopilot (PX4 and ArduPilot verify signed links) refuses commands from anyone else.
    /// `None`: unsigned, as a serial cable inside the airframe usually is.
    pub autopilot_key: Option<[u8; KEY_LEN]>,
    /// Where the uplink's replay state (per-stream signing timestamps) is kept across restarts:
    /// read at start, written at most once a second while it changes and when the daemon
    /// stops. `None`: kept in memory only (a restart then refuses only frames over a minute
    /// old).
    pub replay_state: Option<std::path::PathBuf>,
    /// Clock source.
    pub clock: ClockMode,
}

/// What can go wrong in the shell.
#[derive(Debug)]
pub enum IoError {
    /// A link could not be opened.
    Connect {
        /// Which link (`autopilot` or `ground`).
        link: &'static str,
        /// The address given.
        address: String,
        /// Why.
        source: io::Error,
    },
    /// The replay state file cannot be read or is not one.
    ReplayState {
        /// The file.
        path: String,
        /// Why.
        why: String,
    },
    /// The control rate is below [`MIN_RATE_HZ`] (or not a number).
    BadRate(f32),
    /// Both reader threads stopped.
    LinksClosed,
}

impl fmt::Display for IoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            IoError::Connect {
                link,
                address,
                source,
            } => write!(f, "cannot open the {link} link {address:?}: {source}"),
            IoError::ReplayState { path, why } => {
                write!(f, "replay state file {path}: {why}")
            }
            IoError::BadRate(hz) => {
                write!(
                    f,
                    "control rate must be at least {MIN_RATE_HZ} Hz, got {hz}"
                )
            }
            IoError::LinksClosed => f.write_str("both MAVLink links closed"),
        }
    }
}

impl std::error::Error for IoError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            IoError::Connect { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// Why an uplink frame was dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UplinkRejection {
    /// Signing is required and the frame carries no signature (or is MAVLink 1).
    Unsigned,
    /// The signature does not match the key.
    BadSignature,
    /// A validly signed frame replayed: not newer than its stream's last, or a new stream
    /// over a minute old.
    Replayed,
    /// A timestamp over a minute ahead of this computer's clock.
    FromTheFuture,
    /// The payload does not parse as a `common` message (bad enum value, unknown id).
    Malformed,
}

/// Counts of the ground link's traffic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct UplinkCounters {
    /// Frames that passed the gate.
    pub accepted: u64,
    /// Dropped: no signature while one is required.
    pub unsigned: u64,
    /// Dropped: wrong signature.
    pub bad_signature: u64,
    /// Dropped: replayed (old timestamp on its stream, or a new stream over a minute old).
    pub replayed: u64,
    /// Dropped: timestamp too far in the future.
    pub from_the_future: u64,
    /// Dropped: payload does not parse.
    pub malformed: u64,
    /// TUNNEL frames for another system, ignored.
    pub not_for_us: u64,
    /// TUNNEL chunks handed to the core.
    pub tunnel_chunks: u64,
    /// Dropped unchecked: the sender had already had [`REJECTS_PER_SENDER`] frames refused
    /// this second.
    pub rate_limited: u64,
}

/// Refused frames a sender may cost the daemon a second (a signature check each) before the
/// rest of its frames that second are dropped unchecked. Counted only on refusals, so the
/// ground, whose frames pass, is never limited however fast a simulation drives it.
pub const REJECTS_PER_SENDER: u32 = 100;
/// Senders tracked at once; past this, new senders share one budget.
const TRACKED_SENDERS: usize = 256;

/// Per-sender budget of refused frames, renewed every second. Pure: the caller passes the
/// time in.
#[derive(Debug, Default)]
pub struct RejectBudget {
    window_start: Option<Instant>,
    refused: std::collections::HashMap<Option<SocketAddr>, u32>,
}

impl RejectBudget {
    fn key(&self, from: Option<SocketAddr>) -> Option<SocketAddr> {
        if from.is_some()
            && !self.refused.contains_key(&from)
            && self.refused.len() >= TRACKED_SENDERS
        {
            None
        } else {
            from
        }
    }

    fn roll(&mut self, now: Instant) {
        match self.window_start {
            Some(start) if now.duration_since(start) < Duration::from_secs(1) => {}
            _ => {
                self.window_start = Some(now);
                self.refused.clear();
            }
        }
    }

    /// Whether a frame from `from` at `now` should still be checked.
    pub fn allows(&mut self, from: Option<SocketAddr>, now: Instant) -> bool {
        self.roll(now);
        let key = self.key(from);
        self.refused.get(&key).copied().unwrap_or(0) < REJECTS_PER_SENDER
    }

    /// A frame from `from` was refused.
    pub fn refused(&mut self, from: Option<SocketAddr>, now: Instant) {
        self.roll(now);
        let key = self.key(from);
        *self.refused.entry(key).or_insert(0) += 1;
    }
}

/// Checks ground frames: signature and replay state first, then that the payload parses.
/// Pure: the signing clock comes in with each frame.
pub struct UplinkGate {
    signing: Option<(SigningKey, SigningData, ReplayGuard)>,
    counters: UplinkCounters,
}

impl UplinkGate {
    /// A gate requiring signatures made with `key` (replay state fresh at `now`), or
    /// accepting everything without one.
    pub fn new(key: Option<[u8; KEY_LEN]>, now: SigningTime) -> Self {
        Self::with_replay_state(key, ReplayGuard::new(now))
    }

    /// A gate whose replay state was read back from a file.
    pub fn with_replay_state(key: Option<[u8; KEY_LEN]>, guard: ReplayGuard) -> Self {
        UplinkGate {
            signing: key.map(|k| (SigningKey(k), signing_data(&SigningKey(k), 0), guard)),
            counters: UplinkCounters::default(),
        }
    }

    /// What the gate has counted.
    pub fn counters(&self) -> UplinkCounters {
        self.counters
    }

    /// The replay state, when signing.
    pub fn replay_state(&self) -> Option<&ReplayGuard> {
        self.signing.as_ref().map(|(_, _, guard)| guard)
    }

    /// The replay state, to mark it saved.
    fn replay_state_mut(&mut self) -> Option<&mut ReplayGuard> {
        self.signing.as_mut().map(|(_, _, guard)| guard)
    }

    /// Checks one raw frame at signing time `now` and parses it.
    pub fn accept(
        &mut self,
        raw: &MAVLinkMessageRaw,
        now: SigningTime,
    ) -> Result<(MavHeader, MavMessage), UplinkRejection> {
        let verdict = self.check(raw, now);
        match verdict {
            Ok(_) => self.counters.accepted += 1,
            Err(UplinkRejection::Unsigned) => self.counters.unsigned += 1,
            Err(UplinkRejection::BadSignature) => self.counters.bad_signature += 1,
            Err(UplinkRejection::Replayed) => self.counters.replayed += 1,
            Err(UplinkRejection::FromTheFuture) => self.counters.from_the_future += 1,
            Err(UplinkRejection::Malformed) => self.counters.malformed += 1,
        }
        verdict
    }

    fn check(
        &mut self,
        raw: &MAVLinkMessageRaw,
        now: SigningTime,
    ) -> Result<(MavHeader, MavMessage), UplinkRejection> {
        // Parse first (pure, no state): a frame that does not parse must not move the replay
        // state either.
        let message = MavMessage::parse(raw.version(), raw.message_id(), raw.payload())
            .map_err(|_| UplinkRejection::Malformed)?;
        if let Some((key, _, guard)) = &mut self.signing {
            let MAVLinkMessageRaw::V2(v2) = raw else {
                return Err(UplinkRejection::Unsigned);
            };
            guard.verify(key, v2, now).map_err(|e| match e {
                SignatureError::Unsigned => UplinkRejection::Unsigned,
                SignatureError::WrongSignature => UplinkRejection::BadSignature,
                SignatureError::Replayed { .. } | SignatureError::TooOld { .. } => {
                    UplinkRejection::Replayed
                }
                SignatureError::FromTheFuture { .. } => UplinkRejection::FromTheFuture,
            })?;
        }
        let header = MavHeader {
            system_id: raw.system_id(),
            component_id: raw.component_id(),
            sequence: raw.sequence(),
        };
        Ok((header, message))
    }

    /// Signs `message` for the ground if a key is set; plain MAVLink 2 otherwise.
    fn seal(&self, header: MavHeader, message: &MavMessage) -> MAVLinkV2MessageRaw {
        let mut raw = MAVLinkV2MessageRaw::new();
        match &self.signing {
            Some((_, signer, _)) => {
                raw.serialize_message_for_signing(header, message);
                signer.sign_message(&mut raw);
            }
            None => raw.serialize_message(header, message),
        }
        raw
    }
}

/// Reads the replay state file at `path`: a missing file is a fresh state at `now` (the first
/// start), anything else that is not a state file is an error naming it.
///
/// # Errors
/// [`IoError::ReplayState`] when the file exists but cannot be read or parsed.
pub fn load_replay_state(path: &std::path::Path, now: SigningTime) -> Result<ReplayGuard, IoError> {
    use std::io::Read;
    let bad = |why: String| IoError::ReplayState {
        path: path.display().to_string(),
        why,
    };
    let file = match std::fs::File::open(path) {
        Ok(file) => file,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(ReplayGuard::new(now)),
        Err(e) => return Err(bad(e.to_string())),
    };
    let mut bytes = Vec::new();
    // A state file of MAX_STREAMS entries is under 50 kB.
    file.take(1 << 20)
        .read_to_end(&mut bytes)
        .map_err(|e| bad(e.to_string()))?;
    let guard =
        ReplayGuard::from_bytes(&bytes).map_err(|e: ReplayStateError| bad(e.to_string()))?;
    info!(
        "replay state read from {}: {} signing streams remembered",
        path.display(),
        guard.stream_count()
    );
    Ok(guard)
}

/// Writes the replay state to `path` whole: a temporary file beside it, then a rename, so that
/// a crash mid-write leaves the previous state.
#[cfg(test)]
fn save_replay_state(path: &std::path::Path, guard: &ReplayGuard) -> io::Result<()> {
    write_state_file(path, &guard.to_bytes())
}

/// `bytes` to `path` through a temporary file and a rename, so that a crash mid-write leaves
/// the old state, never half of the new.
fn write_state_file(path: &std::path::Path, bytes: &[u8]) -> io::Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

/// Writes the replay state file on a thread of its own. On the control thread the write
/// stalled the setpoint stream: under writeback pressure (a large build writing gigabytes)
/// the kernel throttles every writer, and one 32-byte write and rename took 680 ms, near
/// PX4's 1 s setpoint-loss timeout; two daemons stalled together lost OFFBOARD mid-mission.
/// Only the newest state matters, so states queued behind a slow write are skipped.
struct StateWriter {
    sender: Sender<Vec<u8>>,
    thread: Option<thread::JoinHandle<()>>,
}

impl StateWriter {
    fn spawn(path: std::path::PathBuf) -> Self {
        let (sender, receiver) = mpsc::channel::<Vec<u8>>();
        let body = move || {
            while let Ok(mut bytes) = receiver.recv() {
                while let Ok(newer) = receiver.try_recv() {
                    bytes = newer;
                }
                if let Err(e) = write_state_file(&path, &bytes) {
                    warn!("cannot write the replay state {}: {e}", path.display());
                }
            }
        };
        let thread = thread::Builder::new()
            .name("replay-state-writer".into())
            .spawn(body)
            .map_err(|e| warn!("cannot start the replay state writer: {e}"))
            .ok();
        Self { sender, thread }
    }

    /// Queues `bytes` for writing; returns at once.
    fn save(&self, bytes: Vec<u8>) {
        // A writer thread that could not start leaves nothing to send to: the state in
        // memory still guards this run.
        let _ = self.sender.send(bytes);
    }

    /// Writes what is queued and ends the thread.
    fn finish(self) {
        let Self { sender, thread } = self;
        drop(sender);
        if let Some(thread) = thread {
            let _ = thread.join();
        }
    }
}

/// The daemon's time in lockstep mode, from the autopilot's `time_boot_ms`, kept monotonic
/// across an autopilot reboot (its clock restarting from zero).
#[derive(Clone, Copy, Debug, Default)]
pub struct BootClock {
    offset_ms: u64,
    last_raw: Option<u32>,
}

impl BootClock {
    /// The daemon time for a `time_boot_ms` just received.
    ///
    /// ```
    /// use skyherd_daemon::{control::Millis, io::BootClock};
    /// let mut clock = BootClock::default();
    /// assert_eq!(clock.update(5000), Millis(5000));
    /// assert_eq!(clock.update(9000), Millis(9000));
    /// // A datagram overtaken on the way: time does not go back.
    /// assert_eq!(clock.update(8950), Millis(9000));
    /// // The autopilot rebooted: time goes on from where it was.
    /// assert_eq!(clock.update(100), Millis(9100));
    /// ```
    pub fn update(&mut self, time_boot_ms: u32) -> Millis {
        if let Some(last) = self.last_raw
            && time_boot_ms < last
        {
            // A small step back is reordering on the link; a big one is a reboot.
            if last - time_boot_ms <= 1000 {
                return Millis(self.offset_ms + u64::from(last));
            }
            info!("autopilot clock restarted ({last} ms -> {time_boot_ms} ms)");
            self.offset_ms += u64::from(last);
        }
        self.last_raw = Some(time_boot_ms);
        Millis(self.offset_ms + u64::from(time_boot_ms))
    }
}

/// Counts of the autopilot link's traffic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AutopilotCounters {
    /// Messages from our autopilot that were used.
    pub received: u64,
    /// Messages from other systems, ignored.
    pub other_systems: u64,
    /// Frames that did not parse (unknown message, bad enum value).
    pub malformed: u64,
    /// Setpoints sent.
    pub setpoints_sent: u64,
    /// Commands sent.
    pub commands_sent: u64,
    /// Commands the autopilot refused (COMMAND_ACK other than accepted / in progress).
    pub commands_refused: u64,
    /// COMMAND_ACKs addressed to another requester (a ground station on a shared link).
    pub others_acks: u64,
    /// SET_MESSAGE_INTERVAL requests for LOCAL_POSITION_NED (sent while none arrives).
    pub stream_requests: u64,
}

/// Everything the shell has counted, for logs and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ShellCounters {
    /// Ground link.
    pub uplink: UplinkCounters,
    /// Autopilot link.
    pub autopilot: AutopilotCounters,
    /// Heartbeats sent (to both links).
    pub heartbeats_sent: u64,
    /// STATUSTEXT messages sent to the ground (one per status change).
    pub status_texts_sent: u64,
}

enum Event {
    Autopilot(MavHeader, Box<MavMessage>),
    AutopilotMalformed,
    /// A frame from the ground link, with the datagram's sender where the link is UDP.
    Ground(Box<MAVLinkMessageRaw>, Option<SocketAddr>),
    GroundMalformed,
}

/// The ground link. UDP is read datagram by datagram here, not through the `mavlink` crate's
/// connection, whose `udpin` mode answers whoever sent the last datagram, however it was
/// signed: one junk byte redirected the daemon's signed heartbeats to its sender. Here the
/// daemon answers only the address of the last frame that passed the uplink gate.
enum GroundLink {
    Udp {
        socket: UdpSocket,
        /// `udpout`: the socket is connected to the ground's address.
        connected: bool,
    },
    /// Serial, TCP: one peer by construction.
    Other(Arc<Link>),
}

/// The ground reader's buffer: eight of the largest MAVLink 2 frames (12 header and CRC
/// bytes, 255 payload, 13 signature: 280 bytes each) in one datagram; more is cut off.
const MAX_DATAGRAM: usize = 280 * 8;

/// A running daemon: both links open, the core inside.
pub struct Daemon<P> {
    core: DaemonCore<P>,
    autopilot: Arc<Link>,
    ground: GroundLink,
    /// Where the last authenticated ground frame came from: the only address answered.
    ground_peer: Option<SocketAddr>,
    /// Refused frames per sender this second.
    rejects: RejectBudget,
    /// Writes the replay state file off the control thread (`None`: no file).
    state_writer: Option<StateWriter>,
    ground_local: Option<SocketAddr>,
    autopilot_local: Option<SocketAddr>,
    events: Receiver<Event>,
    gate: UplinkGate,
    clock: ClockMode,
    boot_clock: BootClock,
    counters: ShellCounters,
    ground_sequence: u8,
    stop: Arc<AtomicBool>,
    /// When the last LOCAL_POSITION_NED arrived, and when it was last asked for (wall time:
    /// the request's retry is the shell's business, not the core's).
    position_heard_at: Option<Instant>,
    positions_requested_at: Option<Instant>,
    /// Lockstep: the last tick's snapshot came in time, so the next is waited for patiently.
    snapshots_keep_pace: bool,
}

/// Work on the control thread that takes longer than this (wall time) is logged: the
/// setpoint stream must not pause near PX4's setpoint-loss timeout (`COM_OF_LOSS_T`, 1 s).
const SLOW_WORK_WARNING: Duration = Duration::from_millis(200);

/// A gap between two autopilot positions this long (wall time) is logged.
const POSITION_GAP_WARNING: Duration = Duration::from_millis(500);

/// Logs `what` when it took longer than [`SLOW_WORK_WARNING`] since `started`.
fn warn_if_slow(what: &str, started: Instant) {
    let took = started.elapsed();
    if took >= SLOW_WORK_WARNING {
        warn!(
            "control thread: {what} took {} ms of wall time",
            took.as_millis()
        );
    }
}

/// How long reader threads block before looking at the stop flag.
const READ_TIMEOUT: Duration = Duration::from_millis(100);

/// Lockstep: longest wall-time wait for the snapshot of a position's instant while snapshots
/// are not coming (before the mission, an uplink cut). Keep it well under the simulator's
/// short wait for the answer (`SitlConfig::lockstep_timeout`, 50 ms): before the mission
/// every tick waits this long, and an answer later than the simulator waits would land in the
/// next tick.
pub(crate) const LOCKSTEP_SNAPSHOT_WAIT: Duration = Duration::from_millis(20);

/// Lockstep: longest wall-time wait for the snapshot of a position's instant while snapshots
/// keep pace (the last one came in time) and the daemon flies on them: a loaded machine can delay the ground's process or
/// this reader thread past [`LOCKSTEP_SNAPSHOT_WAIT`], and a tick flown on the previous
/// snapshot would make the mission differ from run to run. Under the simulator's patience
/// (`SitlConfig::lockstep_patience`, 400 ms) for a daemon that kept pace.
pub(crate) const LOCKSTEP_SNAPSHOT_PATIENCE: Duration = Duration::from_millis(250);

/// Whether a snapshot stamped `snapshot_ms` (the ground's clock) is older than the position
/// of `now` (the autopilot's clock), both simulated time in lockstep. A millisecond of slack
/// absorbs their different rounding. No snapshot at all is behind too: the ground's first one
/// (and the mission command it sends just before) may be on its way.
pub(crate) fn snapshot_is_behind(snapshot_ms: Option<u64>, now: Millis) -> bool {
    snapshot_ms.is_none_or(|ms| ms + 1 < now.0)
}

/// Binds a `udpin:`/`udpout:` address (an `udpout` socket connected to its peer), with the
/// read timeout set: the socket, whether it is connected, and its local address. `None` for
/// any other kind of address.
fn bind_udp(
    link: &'static str,
    address: &str,
) -> Option<Result<(UdpSocket, bool, SocketAddr), IoError>> {
    let err = |source| IoError::Connect {
        link,
        address: address.to_string(),
        source,
    };
    let bind = |target: &str, connected: bool| {
        let socket = if connected {
            let socket = UdpSocket::bind("0.0.0.0:0").map_err(err)?;
            socket.connect(target).map_err(err)?;
            socket
        } else {
            UdpSocket::bind(target).map_err(err)?
        };
        socket.set_read_timeout(Some(READ_TIMEOUT)).map_err(err)?;
        let local = socket.local_addr().map_err(err)?;
        Ok((socket, connected, local))
    };
    if let Some(target) = address.strip_prefix("udpin:") {
        Some(bind(target, false))
    } else {
        address
            .strip_prefix("udpout:")
            .map(|target| bind(target, true))
    }
}

/// Opens a link. UDP addresses are bound here (rather than inside `mavlink::connect`) so that
/// the bound address is known (`udpin:127.0.0.1:0` picks a free port) and reads time out.
fn open_link(link: &'static str, address: &str) -> Result<(Link, Option<SocketAddr>), IoError> {
    let err = |source| IoError::Connect {
        link,
        address: address.to_string(),
        source,
    };
    match bind_udp(link, address) {
        Some(bound) => {
            let (socket, connected, local) = bound?;
            let mode = if connected {
                UdpMode::Udpout
            } else {
                UdpMode::Udpin
            };
            let link = UdpConfig::from_socket(socket, mode)
                .map_err(err)?
                .connect::<MavMessage>()
                .map_err(err)?;
            Ok((link, Some(local)))
        }
        None => {
            let link = mavlink::connect::<MavMessage>(address).map_err(err)?;
            Ok((link, None))
        }
    }
}

/// Opens the ground link: UDP as a plain socket read by [`spawn_datagram_reader`], anything
/// else through the `mavlink` crate.
fn open_ground(address: &str) -> Result<(GroundLink, Option<SocketAddr>), IoError> {
    match bind_udp("ground", address) {
        Some(bound) => {
            let (socket, connected, local) = bound?;
            Ok((GroundLink::Udp { socket, connected }, Some(local)))
        }
        None => {
            let (link, local) = open_link("ground", address)?;
            Ok((GroundLink::Other(Arc::new(link)), local))
        }
    }
}

/// Reads the ground's UDP socket until `stop`: every frame of every datagram, with its sender.
/// Empty and junk datagrams are counted as malformed at once (no sleeping on them).
fn spawn_datagram_reader(socket: UdpSocket, events: Sender<Event>, stop: Arc<AtomicBool>) {
    let body = move || {
        let mut buffer = vec![0u8; MAX_DATAGRAM];
        while !stop.load(Ordering::Relaxed) {
            let (len, from) = match socket.recv_from(&mut buffer) {
                Ok(got) => got,
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) =>
                {
                    continue;
                }
                Err(e) => {
                    // Refused (an ICMP error from an earlier send) or a real fault: the next
                    // datagram may be fine; a short pause keeps a broken socket from spinning.
                    debug!("ground: read error: {e}");
                    thread::sleep(Duration::from_millis(5));
                    continue;
                }
            };
            let mut reader = MavlinkReader::new(&buffer[..len]);
            let mut frames = 0;
            while let Ok(raw) = reader.read_any_raw_message::<MavMessage>() {
                frames += 1;
                if events
                    .send(Event::Ground(Box::new(raw), Some(from)))
                    .is_err()
                {
                    return;
                }
            }
            if frames == 0 && events.send(Event::GroundMalformed).is_err() {
                return;
            }
        }
    };
    if let Err(e) = thread::Builder::new()
        .name("ground-reader".into())
        .spawn(body)
    {
        warn!("cannot start the ground reader: {e}");
    }
}

/// Reads one link until `stop`; `raw` selects unparsed frames (the ground link, whose
/// signatures are checked by the daemon thread so that rejections can be counted).
fn spawn_reader(
    name: &'static str,
    link: Arc<Link>,
    raw: bool,
    events: Sender<Event>,
    stop: Arc<AtomicBool>,
) {
    let body = move || {
        while !stop.load(Ordering::Relaxed) {
            let event = if raw {
                match link.recv_raw() {
                    Ok(frame) => Ok(Event::Ground(Box::new(frame), None)),
                    Err(e) => Err(e),
                }
            } else {
                match link.recv() {
                    Ok((header, message)) => Ok(Event::Autopilot(header, Box::new(message))),
                    Err(e) => Err(e),
                }
            };
            let event = match event {
                Ok(event) => event,
                Err(MessageReadError::Parse(e)) => {
                    debug!("{name}: dropped a frame: {e}");
                    if raw {
                        Event::GroundMalformed
                    } else {
                        Event::AutopilotMalformed
                    }
                }
                Err(MessageReadError::Io(e)) => {
                    match e.kind() {
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut => {}
                        // An empty or truncated datagram is the sender's problem, not the
                        // link's: drop it at once. Sleeping on it let a flood of zero-byte
                        // datagrams slow the reader to 50 frames a second.
                        io::ErrorKind::UnexpectedEof | io::ErrorKind::InvalidData => {
                            debug!("{name}: dropped an empty or short datagram: {e}");
                            if raw {
                                if events.send(Event::GroundMalformed).is_err() {
                                    return;
                                }
                            } else if events.send(Event::AutopilotMalformed).is_err() {
                                return;
                            }
                        }
                        // Refused (nobody listening yet on a UDP peer), serial hiccup: wait a
                        // little and keep reading.
                        _ => {
                            debug!("{name}: read error: {e}");
                            thread::sleep(Duration::from_millis(20));
                        }
                    }
                    continue;
                }
            };
            if events.send(event).is_err() {
                return;
            }
        }
    };
    // A reader that cannot start leaves the daemon deaf on that link, which the core reports
    // as a hold; the spawn error itself is logged.
    if let Err(e) = thread::Builder::new()
        .name(format!("{name}-reader"))
        .spawn(body)
    {
        warn!("cannot start the {name} reader: {e}");
    }
}

impl<P: OnboardPolicy> Daemon<P> {
    /// Opens both links and starts their reader threads.
    pub fn connect(options: &LinkOptions, core: DaemonCore<P>) -> Result<Self, IoError> {
        if let ClockMode::Wall { rate_hz } = options.clock {
            // PX4 drops out of OFFBOARD below 2 Hz of setpoints.
            if !(rate_hz.is_finite() && rate_hz >= MIN_RATE_HZ) {
                return Err(IoError::BadRate(rate_hz));
            }
            if rate_hz < 10.0 {
                warn!("control rate {rate_hz} Hz is below the 10 Hz the actor was designed for");
            }
        }
        let now = SigningTime::now();
        let guard = match &options.replay_state {
            Some(path) => load_replay_state(path, now)?,
            None => ReplayGuard::new(now),
        };
        let (mut autopilot, autopilot_local) = open_link("autopilot", &options.autopilot)?;
        if let Some(key) = options.autopilot_key {
            // Link id 1: the autopilot link's own signing stream, apart from the uplink's 0.
            autopilot.setup_signing(Some(skyherd_link::signing::signing_config(
                &SigningKey(key),
                1,
            )));
        }
        let (ground, ground_local) = open_ground(&options.ground)?;
        let autopilot = Arc::new(autopilot);
        let stop = Arc::new(AtomicBool::new(false));
        let (tx, rx) = mpsc::channel();
        spawn_reader(
            "autopilot",
            autopilot.clone(),
            false,
            tx.clone(),
            stop.clone(),
        );
        match &ground {
            GroundLink::Udp { socket, .. } => {
                let reader = socket.try_clone().map_err(|source| IoError::Connect {
                    link: "ground",
                    address: options.ground.clone(),
                    source,
                })?;
                spawn_datagram_reader(reader, tx, stop.clone());
            }
            GroundLink::Other(link) => spawn_reader("ground", link.clone(), true, tx, stop.clone()),
        }
        if options.signing_key.is_none() {
            warn!("no signing key: uplink frames are accepted unauthenticated");
        }
        info!(
            "links open: autopilot {} ({}), ground {} ({})",
            options.autopilot,
            autopilot_local.map_or("-".into(), |a| a.to_string()),
            options.ground,
            ground_local.map_or("-".into(), |a| a.to_string()),
        );
        Ok(Daemon {
            core,
            autopilot,
            ground,
            ground_peer: None,
            rejects: RejectBudget::default(),
            state_writer: options.replay_state.clone().map(StateWriter::spawn),
            ground_local,
            autopilot_local,
            events: rx,
            gate: UplinkGate::with_replay_state(options.signing_key, guard),
            clock: options.clock,
            boot_clock: BootClock::default(),
            counters: ShellCounters::default(),
            ground_sequence: 0,
            position_heard_at: None,
            snapshots_keep_pace: false,
            positions_requested_at: None,
            stop,
        })
    }

    /// The local address of the ground link, if it is UDP.
    pub fn ground_address(&self) -> Option<SocketAddr> {
        self.ground_local
    }

    /// The local address of the autopilot link, if it is UDP.
    pub fn autopilot_address(&self) -> Option<SocketAddr> {
        self.autopilot_local
    }

    /// A flag that ends [`run`](Self::run) when set (from a signal handler or a test).
    pub fn stop_flag(&self) -> Arc<AtomicBool> {
        self.stop.clone()
    }

    /// The core, for status and counters.
    pub fn core(&self) -> &DaemonCore<P> {
        &self.core
    }

    /// What the shell has counted.
    pub fn counters(&self) -> ShellCounters {
        ShellCounters {
            uplink: self.gate.counters(),
            ..self.counters
        }
    }

    /// Runs until the stop flag is set.
    pub fn run(&mut self) -> Result<(), IoError> {
        let started = Instant::now();
        let wall_now = || Millis(started.elapsed().as_millis() as u64);
        let mut now = Millis(0);
        let mut next_tick = Millis(0);
        let mut next_heartbeat = Millis(0);
        // The first accepted frames are saved at once, then at most once a second: a daemon
        // killed (SIGKILL) a moment into a fast lockstep mission still leaves its state.
        let mut last_state_save: Option<Instant> = None;
        while !self.stop.load(Ordering::Relaxed) {
            if last_state_save.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
                let writing = Instant::now();
                if self.save_replay_state() {
                    last_state_save = Some(Instant::now());
                    warn_if_slow("writing the replay state", writing);
                }
            }
            let wait = match self.clock {
                ClockMode::Wall { .. } => next_tick.since(wall_now()).min(READ_TIMEOUT),
                ClockMode::Simulator { .. } => READ_TIMEOUT,
            };
            let event = match self.events.recv_timeout(wait) {
                Ok(event) => Some(event),
                Err(RecvTimeoutError::Timeout) => None,
                // The readers also end when asked to stop; only otherwise is it a failure.
                Err(RecvTimeoutError::Disconnected) if self.stop.load(Ordering::Relaxed) => break,
                Err(RecvTimeoutError::Disconnected) => return Err(IoError::LinksClosed),
            };
            if let ClockMode::Wall { rate_hz } = self.clock {
                now = wall_now();
                if let Some(event) = event {
                    self.handle(now, event);
                }
                if now >= next_tick {
                    self.tick(now);
                    let period = (1000.0 / rate_hz).max(1.0) as u64;
                    // Keep the cadence; after a stall, start afresh rather than burst.
                    next_tick = Millis(next_tick.0 + period);
                    if next_tick <= now {
                        next_tick = Millis(now.0 + period);
                    }
                }
            } else if let Some(event) = event {
                // Lockstep: time moves only with the autopilot's clock.
                let position_time = match &event {
                    Event::Autopilot(header, message) if self.is_our_autopilot(header) => {
                        match message.as_ref() {
                            MavMessage::LOCAL_POSITION_NED(p) => {
                                Some(self.boot_clock.update(p.time_boot_ms))
                            }
                            _ => None,
                        }
                    }
                    _ => None,
                };
                if let Some(t) = position_time {
                    now = now.max(t);
                }
                let handling = Instant::now();
                self.handle(now, event);
                warn_if_slow("handling a message", handling);
                if position_time.is_some() {
                    self.await_snapshot_of(now);
                    let ticking = Instant::now();
                    self.tick(now);
                    warn_if_slow("the control tick", ticking);
                    // Ends the lockstep answer to every position, whatever the tick decided
                    // (sent after its setpoint and command, on the same link): the simulator
                    // waits for it before the next step, so even the pre-flight (idle,
                    // arming: no setpoints yet) does not race the wall clock.
                    self.send_autopilot_heartbeat();
                }
            }
            if now >= next_heartbeat {
                match self.clock {
                    ClockMode::Wall { .. } => self.send_heartbeats(),
                    // Until the first position the autopilot needs one to learn where we
                    // are; from then on it gets one with every tick's answer, and only then:
                    // the simulator takes it for the end of that answer.
                    ClockMode::Simulator { .. } if self.core.own_position().is_none() => {
                        self.send_heartbeats();
                    }
                    ClockMode::Simulator { .. } => self.send_ground_heartbeat(),
                }
                next_heartbeat = now.after(HEARTBEAT_PERIOD);
            }
        }
        let _ = self.save_replay_state();
        // The last state is on disk before the daemon says it stops.
        if let Some(writer) = self.state_writer.take() {
            writer.finish();
        }
        info!(
            "stopping; counters: {:?}; core: {:?}",
            self.counters(),
            self.core.counters()
        );
        Ok(())
    }

    /// Lockstep only. The simulator's ground station stamps its snapshots on the simulated
    /// clock and sends the snapshot of an instant before the autopilots report that instant's
    /// positions, but the two links have two reader threads, so the snapshot can reach this
    /// thread just after the position. Wait (at most [`LOCKSTEP_SNAPSHOT_WAIT`] of wall time,
    /// handling whatever arrives) until the newest snapshot is of `now`, so that which one the
    /// actor sees (and whether the mission command sent just before it has arrived) does not
    /// depend on thread scheduling. When none comes (no mission yet, an uplink cut), the tick
    /// goes on with what there is after the wait.
    fn await_snapshot_of(&mut self, now: Millis) {
        let lockstep = matches!(self.clock, ClockMode::Simulator { lockstep: true });
        let wait = if self.snapshots_keep_pace && lockstep && self.core.steers_on_snapshots() {
            LOCKSTEP_SNAPSHOT_PATIENCE
        } else {
            LOCKSTEP_SNAPSHOT_WAIT
        };
        let deadline = Instant::now() + wait;
        self.snapshots_keep_pace = false;
        while snapshot_is_behind(self.core.snapshot_timestamp_ms(), now) {
            let Some(left) = deadline.checked_duration_since(Instant::now()) else {
                return;
            };
            match self.events.recv_timeout(left) {
                Ok(event) => self.handle(now, event),
                Err(_) => return,
            }
        }
        self.core.heard_snapshot_at(now);
        self.snapshots_keep_pace = true;
    }

    /// Hands the replay state to the writer thread when it changed (a failed write is logged
    /// there: flying on beats stopping, and the state in memory still guards this run).
    /// Returns whether it handed one over.
    fn save_replay_state(&mut self) -> bool {
        let Some(writer) = &self.state_writer else {
            return false;
        };
        let Some(guard) = self.gate.replay_state() else {
            return false;
        };
        if !guard.is_dirty() {
            return false;
        }
        writer.save(guard.to_bytes());
        if let Some(guard) = self.gate.replay_state_mut() {
            guard.mark_saved();
        }
        true
    }

    fn is_our_autopilot(&self, header: &MavHeader) -> bool {
        header.system_id == u32::from(self.core.config().system_id)
    }

    fn handle(&mut self, now: Millis, event: Event) {
        match event {
            Event::Autopilot(header, message) => self.handle_autopilot(now, header, *message),
            Event::AutopilotMalformed => self.counters.autopilot.malformed += 1,
            Event::GroundMalformed => self.gate.counters.malformed += 1,
            Event::Ground(raw, from) => self.handle_ground(now, &raw, from),
        }
    }

    fn handle_autopilot(&mut self, now: Millis, header: MavHeader, message: MavMessage) {
        if !self.is_our_autopilot(&header) {
            self.counters.autopilot.other_systems += 1;
            return;
        }
        match message {
            MavMessage::HEARTBEAT(hb) => {
                // Other components of the same vehicle (camera, gimbal, this computer) send
                // heartbeats too, with autopilot INVALID; only the autopilot's carry its mode.
                if hb.autopilot == MavAutopilot::MAV_AUTOPILOT_INVALID {
                    return;
                }
                self.counters.autopilot.received += 1;
                self.core
                    .on_heartbeat(now, hb.base_mode.bits(), hb.custom_mode);
                self.request_positions_if_silent();
            }
            MavMessage::LOCAL_POSITION_NED(p) => {
                // A silence the autopilot's setpoint-loss failsafe (PX4: 1 s) could notice.
                if let Some(gap) = self.position_heard_at.map(|t| t.elapsed())
                    && gap >= POSITION_GAP_WARNING
                    && self.core.own_position().is_some()
                {
                    warn!(
                        "autopilot position after {} ms without one",
                        gap.as_millis()
                    );
                }
                self.position_heard_at = Some(Instant::now());
                self.counters.autopilot.received += 1;
                self.core.on_local_position(now, [p.x, p.y, p.z]);
            }
            MavMessage::COMMAND_ACK(ack) => {
                self.counters.autopilot.received += 1;
                // An autopilot that fills the ACK's target fields (MAVLink 2 extensions; PX4
                // and ArduPilot do) says whose command it answers: a ground station's mode
                // change on a shared link is not ours. Zero: an older sender, taken as ours.
                let ours = (ack.target_system == 0 && ack.target_component == 0)
                    || (ack.target_system == self.core.config().system_id
                        && ack.target_component == COMPONENT_ID);
                if !ours {
                    self.counters.autopilot.others_acks += 1;
                    return;
                }
                match ack.result {
                    MavResult::MAV_RESULT_ACCEPTED => {
                        info!("autopilot accepted {:?}", ack.command);
                        // We only ever arm, switch to our control mode, take off and land.
                        let command = match ack.command {
                            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => Some(AutopilotCommand::Arm),
                            MavCmd::MAV_CMD_NAV_LAND => Some(AutopilotCommand::Land),
                            MavCmd::MAV_CMD_NAV_TAKEOFF => Some(AutopilotCommand::Takeoff {
                                altitude_m: self.core.config().takeoff_altitude,
                            }),
                            MavCmd::MAV_CMD_DO_SET_MODE => Some(AutopilotCommand::SetMode {
                                custom_main_mode: self.core.config().flavour.control_mode(),
                            }),
                            _ => None,
                        };
                        if let Some(command) = command {
                            self.core.on_command_accepted(now, command);
                        }
                    }
                    MavResult::MAV_RESULT_IN_PROGRESS => {
                        info!("autopilot working on {:?}", ack.command);
                    }
                    result => {
                        self.counters.autopilot.commands_refused += 1;
                        warn!("autopilot refused {:?}: {result:?}", ack.command);
                    }
                }
            }
            _ => {}
        }
    }

    fn handle_ground(&mut self, now: Millis, raw: &MAVLinkMessageRaw, from: Option<SocketAddr>) {
        let wall = Instant::now();
        if !self.rejects.allows(from, wall) {
            self.gate.counters.rate_limited += 1;
            return;
        }
        let (header, message) = match self.gate.accept(raw, SigningTime::now()) {
            Ok(accepted) => {
                // Only an authenticated frame tells where the ground is.
                if from.is_some() {
                    self.ground_peer = from;
                }
                accepted
            }
            Err(why) => {
                self.rejects.refused(from, wall);
                debug!(
                    "uplink frame from system {} dropped: {why:?}",
                    raw.system_id()
                );
                return;
            }
        };
        let MavMessage::TUNNEL(tunnel) = message else {
            return;
        };
        let system_id = self.core.config().system_id;
        if tunnel.target_system != 0 && tunnel.target_system != system_id {
            self.gate.counters.not_for_us += 1;
            return;
        }
        if tunnel.payload_type != MavTunnelPayloadType::MAV_TUNNEL_PAYLOAD_TYPE_UNKNOWN {
            self.gate.counters.malformed += 1;
            return;
        }
        let len = usize::from(tunnel.payload_length).min(tunnel.payload.len());
        if usize::from(tunnel.payload_length) > tunnel.payload.len() {
            self.gate.counters.malformed += 1;
            return;
        }
        self.gate.counters.tunnel_chunks += 1;
        debug!(
            "uplink chunk of {len} bytes from system {}",
            header.system_id
        );
        if let Err(e) = self.core.on_tunnel_payload(now, &tunnel.payload[..len]) {
            debug!("uplink chunk from system {} dropped: {e}", header.system_id);
        }
    }

    fn tick(&mut self, now: Millis) {
        let previous = self.core.status();
        let decision = self.core.tick(now);
        if !decision.status.same_kind(&previous) {
            self.send_status_text(decision.status);
        }
        if let Some(setpoint) = decision.setpoint {
            self.send_setpoint(now, setpoint);
        }
        if let Some(command) = decision.command {
            self.send_command(command);
        }
    }

    fn header(&self) -> MavHeader {
        MavHeader {
            system_id: u32::from(self.core.config().system_id),
            component_id: COMPONENT_ID,
            sequence: 0,
        }
    }

    fn send_autopilot(&mut self, message: &MavMessage) {
        if let Err(e) = self.autopilot.send(&self.header(), message) {
            debug!("autopilot send failed: {e}");
        }
    }

    fn send_setpoint(&mut self, now: Millis, setpoint: Setpoint) {
        let message = velocity_setpoint_ned(
            self.core.config().system_id,
            AUTOPILOT_COMPONENT_ID,
            now.0 as u32,
            setpoint.velocity_ned,
        );
        self.send_autopilot(&message);
        self.counters.autopilot.setpoints_sent += 1;
    }

    /// ArduPilot sends LOCAL_POSITION_NED only to a link that asked for it (and only once its
    /// EKF has an origin); PX4 streams it anyway and accepts the request. So while none
    /// arrives, every autopilot HEARTBEAT asks for it at [`POSITION_INTERVAL_US`], at most
    /// once a second of wall time (a request ArduCopter acknowledges before its first
    /// heartbeat can be lost, so it is repeated rather than trusted).
    fn request_positions_if_silent(&mut self) {
        let silent = self
            .position_heard_at
            .is_none_or(|t| t.elapsed() > POSITION_SILENCE);
        let due = self
            .positions_requested_at
            .is_none_or(|t| t.elapsed() >= Duration::from_secs(1));
        if !(silent && due) {
            return;
        }
        self.positions_requested_at = Some(Instant::now());
        let system_id = self.core.config().system_id;
        debug!("asking the autopilot for LOCAL_POSITION_NED every {POSITION_INTERVAL_US} us");
        let message = message_interval(
            system_id,
            AUTOPILOT_COMPONENT_ID,
            LOCAL_POSITION_NED_ID,
            POSITION_INTERVAL_US,
        );
        self.send_autopilot(&message);
        self.counters.autopilot.stream_requests += 1;
    }

    fn send_command(&mut self, command: AutopilotCommand) {
        let system_id = self.core.config().system_id;
        let (command_id, param1, param2) = match command {
            AutopilotCommand::Land => {
                warn!("sending MAV_CMD_NAV_LAND");
                self.send_autopilot(&land(system_id, AUTOPILOT_COMPONENT_ID));
                self.counters.autopilot.commands_sent += 1;
                return;
            }
            AutopilotCommand::Takeoff { altitude_m } => {
                info!("sending MAV_CMD_NAV_TAKEOFF to {altitude_m} m");
                let message = command_long(
                    system_id,
                    AUTOPILOT_COMPONENT_ID,
                    MavCmd::MAV_CMD_NAV_TAKEOFF,
                    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, altitude_m],
                );
                self.send_autopilot(&message);
                self.counters.autopilot.commands_sent += 1;
                return;
            }
            AutopilotCommand::Arm => (MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            AutopilotCommand::SetMode { custom_main_mode } => (
                MavCmd::MAV_CMD_DO_SET_MODE,
                // MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                1.0,
                f32::from(custom_main_mode),
            ),
        };
        info!("sending {command_id:?} ({param1}, {param2})");
        let message = command_long(
            system_id,
            AUTOPILOT_COMPONENT_ID,
            command_id,
            [param1, param2, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        self.send_autopilot(&message);
        self.counters.autopilot.commands_sent += 1;
    }

    fn send_to_ground(&mut self, message: &MavMessage) {
        let mut header = self.header();
        header.sequence = self.ground_sequence;
        self.ground_sequence = self.ground_sequence.wrapping_add(1);
        let sealed = self.gate.seal(header, message);
        let sent = match &self.ground {
            GroundLink::Udp {
                socket,
                connected: true,
            } => socket.send(sealed.raw_bytes()).map(|_| ()),
            GroundLink::Udp { socket, .. } => match self.ground_peer {
                Some(peer) => socket.send_to(sealed.raw_bytes(), peer).map(|_| ()),
                // Nobody has proved to be the ground yet: say nothing.
                None => Ok(()),
            },
            GroundLink::Other(link) => link
                .send_raw(&MAVLinkMessageRaw::V2(sealed))
                .map(|_| ())
                .map_err(|e| io::Error::other(e.to_string())),
        };
        if let Err(e) = sent {
            debug!("ground send failed: {e}");
        }
    }

    fn send_status_text(&mut self, status: Status) {
        let severity = if status.is_warning() {
            MavSeverity::MAV_SEVERITY_WARNING
        } else {
            MavSeverity::MAV_SEVERITY_INFO
        };
        // STATUSTEXT holds 50 bytes; longer texts are cut.
        let text = format!("skyherd: {status}");
        let message = MavMessage::STATUSTEXT(STATUSTEXT_DATA {
            severity,
            text: text.as_str().into(),
            ..Default::default()
        });
        self.send_to_ground(&message);
        self.counters.status_texts_sent += 1;
    }

    fn send_heartbeats(&mut self) {
        let message = heartbeat();
        self.send_autopilot(&message);
        self.send_to_ground(&message);
        self.counters.heartbeats_sent += 1;
    }

    fn send_autopilot_heartbeat(&mut self) {
        self.send_autopilot(&heartbeat());
        self.counters.heartbeats_sent += 1;
    }

    fn send_ground_heartbeat(&mut self) {
        self.send_to_ground(&heartbeat());
        self.counters.heartbeats_sent += 1;
    }
}

/// Our HEARTBEAT: an onboard controller, active.
fn heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

impl<P> Drop for Daemon<P> {
    fn drop(&mut self) {
        // Reader threads see the flag within one read timeout and exit.
        self.stop.store(true, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::TUNNEL_DATA;

    const KEY: [u8; KEY_LEN] = [9; KEY_LEN];

    fn tunnel() -> MavMessage {
        MavMessage::TUNNEL(TUNNEL_DATA {
            payload_type: MavTunnelPayloadType::MAV_TUNNEL_PAYLOAD_TYPE_UNKNOWN,
            target_system: 1,
            target_component: COMPONENT_ID,
            payload_length: 3,
            payload: [7; 128],
        })
    }

    fn header() -> MavHeader {
        MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: 0,
        }
    }

    /// What a ground station with `key` puts on the wire.
    fn signed_by(key: [u8; KEY_LEN]) -> MAVLinkMessageRaw {
        MAVLinkMessageRaw::V2(UplinkGate::new(Some(key), now()).seal(header(), &tunnel()))
    }

    fn now() -> SigningTime {
        SigningTime::now()
    }

    #[test]
    fn the_gate_takes_only_frames_signed_with_its_key() {
        let mut gate = UplinkGate::new(Some(KEY), now());
        let (h, m) = gate.accept(&signed_by(KEY), now()).unwrap();
        assert_eq!((h.system_id, m), (255, tunnel()));
        assert_eq!(
            gate.accept(&signed_by([8; KEY_LEN]), now()).err(),
            Some(UplinkRejection::BadSignature)
        );
        assert_eq!(
            gate.accept(
                &MAVLinkMessageRaw::V2(UplinkGate::new(None, now()).seal(header(), &tunnel())),
                now()
            )
            .err(),
            Some(UplinkRejection::Unsigned)
        );
        let c = gate.counters();
        assert_eq!((c.accepted, c.bad_signature, c.unsigned), (1, 1, 1));
    }

    #[test]
    fn the_state_writer_leaves_the_newest_state_on_disk_when_it_finishes() {
        let dir = std::env::temp_dir().join(format!("skyherd-state-writer-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("scratch folder");
        let path = dir.join("uplink.replay");
        let writer = StateWriter::spawn(path.clone());
        for bytes in [b"first".to_vec(), b"second".to_vec(), b"newest".to_vec()] {
            writer.save(bytes);
        }
        writer.finish();
        assert_eq!(std::fs::read(&path).expect("written"), b"newest");
        // No temporary file is left beside it.
        assert!(!path.with_extension("tmp").exists());
        // A folder that cannot be written is logged by the writer, not a panic or a stall.
        let writer = StateWriter::spawn(dir.join("missing").join("uplink.replay"));
        writer.save(b"lost".to_vec());
        writer.finish();
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_replayed_frame_is_refused() {
        let mut gate = UplinkGate::new(Some(KEY), now());
        let frame = signed_by(KEY);
        assert!(gate.accept(&frame, now()).is_ok());
        assert_eq!(
            gate.accept(&frame, now()).err(),
            Some(UplinkRejection::Replayed)
        );
    }

    #[test]
    fn a_sender_that_keeps_failing_is_dropped_unchecked_and_the_ground_never_is() {
        let attacker: SocketAddr = "127.0.0.1:4000".parse().expect("addr");
        let ground: SocketAddr = "127.0.0.1:5000".parse().expect("addr");
        let t0 = Instant::now();
        let mut budget = RejectBudget::default();
        let mut checked = 0;
        for _ in 0..300 {
            if budget.allows(Some(attacker), t0) {
                checked += 1;
                budget.refused(Some(attacker), t0);
            }
        }
        assert_eq!(checked, REJECTS_PER_SENDER);
        // Frames that pass are never counted: the ground is checked however many it sends.
        assert!((0..10_000).all(|_| budget.allows(Some(ground), t0)));
        // A second later the budget is renewed.
        assert!(budget.allows(Some(attacker), t0 + Duration::from_millis(1001)));
        // Past the tracked senders, new ones share one budget rather than growing the map.
        let mut crowd = RejectBudget::default();
        for port in 0..(TRACKED_SENDERS as u16 + 50) {
            let from = Some(SocketAddr::from(([127, 0, 0, 1], 10_000 + port)));
            crowd.refused(from, t0);
        }
        assert!(crowd.refused.len() <= TRACKED_SENDERS + 1);
    }

    #[test]
    fn a_frame_dated_a_year_ahead_is_refused() {
        let mut gate = UplinkGate::new(Some(KEY), now());
        let mut raw = MAVLinkV2MessageRaw::new();
        raw.serialize_message_for_signing(header(), &tunnel());
        let year = now().plus_seconds(365.0 * 86_400.0);
        skyherd_link::replay::sign(&SigningKey(KEY), 0, year, &mut raw);
        assert_eq!(
            gate.accept(&MAVLinkMessageRaw::V2(raw), now()).err(),
            Some(UplinkRejection::FromTheFuture)
        );
        assert_eq!(gate.counters().from_the_future, 1);
    }

    #[test]
    fn a_restarted_daemon_refuses_a_frame_it_took_before_the_restart() {
        let dir = std::env::temp_dir().join(format!("skyherd-replay-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("uplink.replay");
        let _ = std::fs::remove_file(&path);
        let start = signed_by(KEY);
        let mut gate = UplinkGate::with_replay_state(
            Some(KEY),
            load_replay_state(&path, now()).expect("a missing file is a fresh state"),
        );
        assert!(gate.accept(&start, now()).is_ok());
        save_replay_state(&path, gate.replay_state().expect("signing")).expect("saved");
        // A restart: the state comes back from the file, and the Start is refused although
        // it is seconds old (inside the one-minute window for new streams).
        let mut restarted = UplinkGate::with_replay_state(
            Some(KEY),
            load_replay_state(&path, now()).expect("read"),
        );
        assert_eq!(
            restarted.accept(&start, now()).err(),
            Some(UplinkRejection::Replayed)
        );
        assert!(restarted.accept(&signed_by(KEY), now()).is_ok());
        // Without the file it would have been taken.
        let mut forgetful = UplinkGate::new(Some(KEY), now());
        assert!(forgetful.accept(&start, now()).is_ok());
        // A file that is not a replay state is an error naming it.
        std::fs::write(&path, b"not a state").expect("write");
        let err = load_replay_state(&path, now())
            .expect_err("refused")
            .to_string();
        assert!(err.contains("uplink.replay"), "{err}");
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn every_empty_datagram_is_counted_as_malformed_and_the_next_frame_still_arrives() {
        // The reader once slept 20 ms on each empty datagram without counting it: a flood of
        // them slowed the uplink to 50 frames a second, unseen.
        let (link, local) = open_ground("udpin:127.0.0.1:0").expect("a loopback link");
        let local = local.expect("a UDP link has an address");
        let (events, heard) = mpsc::channel();
        let stop = Arc::new(AtomicBool::new(false));
        let GroundLink::Udp { socket, .. } = link else {
            panic!("udpin is a UDP link");
        };
        spawn_datagram_reader(socket, events, stop.clone());
        let attacker = UdpSocket::bind("127.0.0.1:0").expect("socket");
        for _ in 0..100 {
            attacker.send_to(&[], local).expect("send");
        }
        let MAVLinkMessageRaw::V2(frame) = signed_by(KEY) else {
            panic!("the gate seals MAVLink 2");
        };
        attacker.send_to(frame.raw_bytes(), local).expect("send");
        let mut malformed = 0;
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match heard.recv_timeout(left) {
                Ok(Event::GroundMalformed) => malformed += 1,
                Ok(Event::Ground(raw, from)) => {
                    assert_eq!(from, Some(attacker.local_addr().expect("addr")));
                    let MAVLinkMessageRaw::V2(raw) = *raw else {
                        panic!("a MAVLink 2 frame was sent");
                    };
                    assert_eq!(raw.raw_bytes(), frame.raw_bytes());
                    break;
                }
                Ok(_) => {}
                Err(e) => panic!("the frame after the flood never came ({malformed} counted): {e}"),
            }
        }
        stop.store(true, Ordering::Relaxed);
        assert_eq!(malformed, 100, "each empty datagram counted once");
    }

    #[test]
    fn an_unknown_tunnel_payload_type_is_malformed_not_a_panic() {
        let mut gate = UplinkGate::new(None, now());
        let mut raw = gate.seal(header(), &tunnel());
        // payload_type is the payload's first field (u16): 7 is no MAV_TUNNEL_PAYLOAD_TYPE.
        const V2_HEADER_LEN: usize = 10;
        raw.as_mut_slice()[V2_HEADER_LEN] = 7;
        assert_eq!(
            gate.accept(&MAVLinkMessageRaw::V2(raw), now()).err(),
            Some(UplinkRejection::Malformed)
        );
        assert_eq!(gate.counters().malformed, 1);
    }

    #[test]
    fn random_frames_are_dropped_and_counted_never_a_panic() {
        let mut seed = 0x2545_F491_4F6C_DD1D_u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for key in [None, Some(KEY)] {
            let mut gate = UplinkGate::new(key, now());
            for _ in 0..20_000 {
                let mut bytes = [0u8; mavlink::consts::MAX_FRAME_SIZE];
                for b in bytes.iter_mut() {
                    *b = next() as u8;
                }
                bytes[0] = mavlink::MAV_STX_V2;
                let raw = MAVLinkMessageRaw::V2(MAVLinkV2MessageRaw::from_bytes_unparsed(bytes));
                let _ = gate.accept(&raw, now());
            }
            let c = gate.counters();
            assert_eq!(
                c.accepted
                    + c.unsigned
                    + c.bad_signature
                    + c.replayed
                    + c.from_the_future
                    + c.malformed,
                20_000
            );
            if key.is_some() {
                assert_eq!(c.accepted, 0, "{c:?}");
            }
        }
    }

    #[test]
    fn lockstep_waits_for_a_snapshot_older_than_the_position_or_none() {
        assert!(snapshot_is_behind(None, Millis(5000)));
        assert!(snapshot_is_behind(Some(4900), Millis(5000)));
        // The ground rounds, the autopilot truncates: 0.3 s is 300 vs 299 ms.
        assert!(!snapshot_is_behind(Some(300), Millis(299)));
        assert!(!snapshot_is_behind(Some(299), Millis(300)));
        assert!(!snapshot_is_behind(Some(5100), Millis(5000)));
    }
}
