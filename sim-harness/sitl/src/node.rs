//! The socket shell around one [`MockAutopilot`]: its own UDP socket, MAVLink 2 codec
//! (optionally signed), and optional link faults in both directions. Driven by the caller's
//! simulated clock: one [`AutopilotNode::step`] per simulation step.

use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use skyherd_link::{Codec, CodecStats, Frame, Signing};

use super::autopilot::MockAutopilot;
use super::faults::{DelayLine, FaultConfig, FaultPlan, FaultStats, FaultyUdp, Verdict};

/// Options of a node.
#[derive(Debug, Clone, Default)]
pub struct NodeOptions {
    /// MAVLink 2 signing (frames without a valid signature are then dropped and counted).
    pub signing: Option<Signing>,
    /// Faults applied to traffic in both directions.
    pub faults: FaultConfig,
    /// Seed of the fault decisions.
    pub seed: u64,
    /// Peers that get telemetry from the start (the ground station, the onboard daemon).
    pub peers: Vec<SocketAddr>,
}

/// One simulated drone's autopilot on the network.
#[derive(Debug)]
pub struct AutopilotNode {
    out: FaultyUdp,
    inbound_plan: FaultPlan,
    inbound: DelayLine,
    codec: Codec,
    autopilot: MockAutopilot,
    peers: Vec<SocketAddr>,
    buffer: Vec<u8>,
    frames: Vec<Frame>,
}

impl AutopilotNode {
    /// Bind `bind` (e.g. `127.0.0.1:0` for an ephemeral port) for `autopilot`.
    ///
    /// # Errors
    /// The bind error.
    pub fn bind(
        bind: SocketAddr,
        autopilot: MockAutopilot,
        options: NodeOptions,
    ) -> io::Result<Self> {
        let socket = UdpSocket::bind(bind)?;
        socket.set_nonblocking(true)?;
        let config = autopilot.config();
        let codec = Codec::new(config.system_id, config.component_id, options.signing);
        Ok(Self {
            out: FaultyUdp::new(socket, FaultPlan::new(options.faults.clone(), options.seed)),
            inbound_plan: FaultPlan::new(options.faults, options.seed ^ 0x9E37_79B9_7F4A_7C15),
            inbound: DelayLine::default(),
            codec,
            autopilot,
            peers: options.peers,
            buffer: vec![0u8; 2048],
            frames: Vec::new(),
        })
    }

    /// The node's UDP address.
    ///
    /// # Errors
    /// The socket's error.
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.out.socket().local_addr()
    }

    /// Send telemetry to `peer` too.
    pub fn add_peer(&mut self, peer: SocketAddr) {
        if !self.peers.contains(&peer) {
            self.peers.push(peer);
        }
    }

    /// The autopilot state machine.
    pub fn autopilot(&self) -> &MockAutopilot {
        &self.autopilot
    }

    /// Mutable access, e.g. to feed the world's true state in with `set_state`.
    pub fn autopilot_mut(&mut self) -> &mut MockAutopilot {
        &mut self.autopilot
    }

    /// Frames accepted and dropped by the codec.
    pub fn codec_stats(&self) -> &CodecStats {
        self.codec.stats()
    }

    /// What the injected faults did to outgoing and incoming traffic.
    pub fn fault_stats(&self) -> (FaultStats, FaultStats) {
        (*self.out.stats(), *self.inbound_plan.stats())
    }

    /// One step at `now` (s): receive, answer, tick the autopilot, send due telemetry.
    /// Returns the velocity the vehicle flies (m/s, NED).
    ///
    /// # Errors
    /// Socket errors other than "nothing to read" or an unreachable peer.
    pub fn step(&mut self, now: f64) -> io::Result<[f64; 3]> {
        let velocity = self.receive_and_fly(now)?;
        self.send_telemetry(now)?;
        Ok(velocity)
    }

    /// The first half of [`step`](Self::step): receive, answer commands and fly to `now`,
    /// without reporting. Returns the velocity the vehicle flies (m/s, NED).
    ///
    /// # Errors
    /// Socket errors other than "nothing to read" or an unreachable peer.
    pub fn receive_and_fly(&mut self, now: f64) -> io::Result<[f64; 3]> {
        self.receive(now)?;
        let velocity = self.autopilot.fly(now);
        self.out.flush(now)?;
        Ok(velocity)
    }

    /// The second half of [`step`](Self::step): send the telemetry due at `now` from the
    /// autopilot's current state (after a simulator's `set_state`) to every peer.
    ///
    /// # Errors
    /// Socket errors other than an unreachable peer.
    pub fn send_telemetry(&mut self, now: f64) -> io::Result<()> {
        for message in self.autopilot.telemetry(now) {
            let bytes = self.codec.encode(&message);
            for peer in self.peers.clone() {
                self.out.send_to(&bytes, peer, now)?;
            }
        }
        self.out.flush(now)
    }

    /// Receives what arrived, lets due datagrams through the fault plan and answers commands.
    fn receive(&mut self, now: f64) -> io::Result<()> {
        loop {
            match self.out.socket().recv_from(&mut self.buffer) {
                Ok((n, from)) => {
                    if let Verdict::DeliverAt(at) = self.inbound_plan.decide(now) {
                        self.inbound.push(at, from, self.buffer[..n].to_vec());
                    }
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => continue,
                Err(e) => return Err(e),
            }
        }
        for (from, datagram) in self.inbound.due(now) {
            self.frames.clear();
            self.codec.decode(&datagram, &mut self.frames);
            if !self.frames.is_empty() {
                self.add_peer(from);
            }
            for frame in std::mem::take(&mut self.frames) {
                for reply in self.autopilot.handle(&frame.header, &frame.message, now) {
                    let bytes = self.codec.encode(&reply);
                    self.out.send_to(&bytes, from, now)?;
                }
            }
        }
        Ok(())
    }

    /// Run on a thread against the wall clock at `rate_hz` until `stop` is set (for peers
    /// that are separate processes, e.g. a pymavlink ground station). Returns the node.
    pub fn spawn_realtime(
        mut self,
        rate_hz: f64,
        stop: Arc<AtomicBool>,
    ) -> JoinHandle<io::Result<Self>> {
        std::thread::spawn(move || {
            let start = Instant::now();
            let period = Duration::from_secs_f64(1.0 / rate_hz);
            while !stop.load(Ordering::Relaxed) {
                self.step(start.elapsed().as_secs_f64())?;
                std::thread::sleep(period);
            }
            Ok(self)
        })
    }
}
