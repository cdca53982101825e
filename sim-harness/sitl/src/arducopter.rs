//! A real ArduCopter SITL (ArduPilot's own flight code and physics, GPLv3, kept outside this
//! repository) as one of the mission's drones.
//!
//! The process is started with its two MAVLink ports as UDP clients on loopback and no
//! listening TCP port:
//! * SERIAL0 sends to the onboard daemon (`skyherd-onboard --autopilot udpin:...`), which flies
//!   it exactly as it would fly a flight controller on a serial cable;
//! * SERIAL1 sends to this harness ([`ArduCopter::poll`]), which asks it for LOCAL_POSITION_NED
//!   on that port, follows its clock (`time_boot_ms`: ArduCopter's simulation runs free at
//!   `--speedup` times the wall clock, not in lockstep) and its position, moves that herder in
//!   the flock's world accordingly, and relays its telemetry to the ground station, signed
//!   with the fleet key like every fleet frame: the telemetry radio of the real system.
//!
//! Frames: ArduCopter's LOCAL_NED has its origin where it booted (its home), the drone's spawn
//! point; the world is in the simulator frame. The relay and the world place that origin at
//! the spawn point; the daemon is told the same with `--local-origin`.
//!
//! Where the binary is: `SKYHERD_ARDUCOPTER` (the binary, or a folder with `arducopter` and
//! `params/copter.parm`), else `../shared/ardupilot-sitl/` beside the checkout, else
//! `.arducopter/` in it (what `scripts/build-arducopter.sh` builds from the pinned source).

use std::collections::VecDeque;
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use mavlink::dialects::common::{MavAutopilot, MavMessage};
use skyherd_link::command::message_interval;
use skyherd_link::{Codec, Frame, Signing};
use thiserror::Error;

use crate::autopilot::Home;
use crate::launch::{Guard, spawn};

/// ArduCopter GUIDED's mode number.
pub const GUIDED: u32 = 4;
/// The position interval the harness asks for on SERIAL1, µs (20 Hz: finer than a 0.1 s
/// tick, so the world interpolates between two reports).
const POSITION_INTERVAL_US: f32 = 50_000.0;
/// Reports kept for interpolation.
const KEEP_REPORTS: usize = 64;
/// MAVLink identity of the harness on SERIAL1 (a telemetry radio's own ids, as SiK radios
/// use 51/68).
const HARNESS_SYSTEM_ID: u8 = 51;
const HARNESS_COMPONENT_ID: u8 = 68;

/// Why a real ArduCopter could not be used.
#[derive(Debug, Error)]
pub enum ArduCopterError {
    /// No binary where it was looked for.
    #[error(
        "no ArduCopter SITL found (tried {tried}); set SKYHERD_ARDUCOPTER, or run scripts/build-arducopter.sh"
    )]
    NotFound {
        /// The places tried, for the message.
        tried: String,
    },
    /// Starting it or talking to it failed.
    #[error("ArduCopter: {0}")]
    Io(#[from] io::Error),
}

/// The binary and its default parameters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ArduCopterBundle {
    /// The `arducopter` SITL executable.
    pub binary: PathBuf,
    /// `params/copter.parm`: the defaults ArduPilot's `sim_vehicle.py` loads for a quad.
    pub defaults: PathBuf,
}

impl ArduCopterBundle {
    /// Finds the bundle for the checkout at `repo_root`; see the [module docs](self).
    pub fn locate(repo_root: &Path) -> Result<Self, ArduCopterError> {
        Self::locate_from(std::env::var_os("SKYHERD_ARDUCOPTER"), repo_root)
    }

    /// [`locate`](Self::locate) with `SKYHERD_ARDUCOPTER`'s value given.
    fn locate_from(
        env: Option<std::ffi::OsString>,
        repo_root: &Path,
    ) -> Result<Self, ArduCopterError> {
        let mut candidates = Vec::new();
        if let Some(env) = env {
            let path = PathBuf::from(env);
            if path.is_file() {
                let folder = path.parent().map(Path::to_path_buf).unwrap_or_default();
                candidates.push((path, folder));
            } else {
                candidates.push((path.join("arducopter"), path));
            }
        }
        for folder in [
            repo_root.join("../shared/ardupilot-sitl"),
            repo_root.join(".arducopter"),
        ] {
            candidates.push((folder.join("arducopter"), folder));
        }
        let mut tried = Vec::new();
        for (binary, folder) in candidates {
            let defaults = folder.join("params/copter.parm");
            if binary.is_file() && defaults.is_file() {
                return Ok(Self { binary, defaults });
            }
            tried.push(binary.display().to_string());
        }
        Err(ArduCopterError::NotFound {
            tried: tried.join(", "),
        })
    }
}

/// How to start one instance.
#[derive(Debug, Clone)]
pub struct ArduCopterOptions {
    /// MAVLink system id (`--sysid`).
    pub system_id: u8,
    /// Simulation speed over the wall clock (`--speedup`).
    pub speedup: f64,
    /// Where SERIAL0 sends: the onboard daemon's `udpin` address.
    pub serial0: SocketAddr,
    /// Where home (the boot point) is on the Earth.
    pub home: Home,
    /// Where its home lies in the world, simulator frame (x east, y north), metres.
    pub origin_world: [f64; 2],
    /// ArduCopter's console output goes here.
    pub log: Option<PathBuf>,
}

/// One running ArduCopter SITL; see the [module docs](self). Dropping it ends the process and
/// removes its working folder.
#[derive(Debug)]
pub struct ArduCopter {
    _process: Guard,
    workdir: PathBuf,
    serial1: UdpSocket,
    /// ArduCopter's SERIAL1 socket: where requests go (known from its first datagram).
    peer: Option<SocketAddr>,
    codec: Codec,
    relay: Option<(Codec, SocketAddr)>,
    system_id: u8,
    origin_world: [f64; 2],
    armed: bool,
    custom_mode: u32,
    heartbeats: u64,
    /// (time s, position NED m, velocity NED m/s), oldest first.
    reports: VecDeque<(f64, [f64; 3], [f64; 3])>,
    position_heard_at: Option<Instant>,
    requested_at: Option<Instant>,
    buffer: Vec<u8>,
    frames: Vec<Frame>,
}

impl ArduCopter {
    /// Starts an instance; `relay`: forward its telemetry to this ground address, signed so.
    pub fn start(
        bundle: &ArduCopterBundle,
        options: &ArduCopterOptions,
        relay: Option<(Option<Signing>, SocketAddr)>,
    ) -> Result<Self, ArduCopterError> {
        let serial1 = UdpSocket::bind("127.0.0.1:0")?;
        serial1.set_nonblocking(true)?;
        let serial1_addr = serial1.local_addr()?;
        let instance = free_instance()?;
        let workdir = std::env::temp_dir().join(format!(
            "skyherd-arducopter-{}-{instance}",
            std::process::id()
        ));
        std::fs::create_dir_all(&workdir)?;
        let home = options.home;
        let mut command = Command::new(&bundle.binary);
        command
            .current_dir(&workdir)
            .args(["--model", "+", "--speedup"])
            .arg(options.speedup.to_string())
            .arg("--defaults")
            .arg(&bundle.defaults)
            .arg(format!("-I{instance}"))
            .arg("--home")
            .arg(format!(
                "{},{},{},0",
                home.latitude_deg, home.longitude_deg, home.altitude_amsl_m
            ))
            .arg("--wipe")
            .arg("--sysid")
            .arg(options.system_id.to_string())
            // No dataflash logs (1.4 MB a flight), nothing listening on TCP.
            .args(["--param", "LOG_BACKEND_TYPE=0"])
            .arg("--serial0")
            .arg(format!("udpclient:{}", options.serial0))
            .arg("--serial1")
            .arg(format!("udpclient:{serial1_addr}"))
            .args(["--serial2", "none"])
            .stdin(Stdio::null());
        match &options.log {
            Some(path) => {
                let log = std::fs::File::create(path)?;
                command.stdout(log.try_clone()?).stderr(log);
            }
            None => {
                command.stdout(Stdio::null()).stderr(Stdio::null());
            }
        }
        // ArduCopter also exits on its own when its parent (this process) dies.
        let process = spawn(command)?;
        let relay =
            relay.map(|(signing, ground)| (Codec::new(options.system_id, 1, signing), ground));
        Ok(Self {
            _process: process,
            workdir,
            serial1,
            peer: None,
            codec: Codec::new(HARNESS_SYSTEM_ID, HARNESS_COMPONENT_ID, None),
            relay,
            system_id: options.system_id,
            origin_world: options.origin_world,
            armed: false,
            custom_mode: 0,
            heartbeats: 0,
            reports: VecDeque::with_capacity(KEEP_REPORTS),
            position_heard_at: None,
            requested_at: None,
            buffer: vec![0u8; 4096],
            frames: Vec::new(),
        })
    }

    /// Reads what SERIAL1 sent, relays it, and asks for positions while none come.
    ///
    /// # Errors
    /// Socket errors other than "nothing to read".
    pub fn poll(&mut self) -> io::Result<()> {
        loop {
            match self.serial1.recv_from(&mut self.buffer) {
                Ok((n, from)) => {
                    self.peer = Some(from);
                    self.frames.clear();
                    self.codec.decode(&self.buffer[..n], &mut self.frames);
                    for frame in std::mem::take(&mut self.frames) {
                        self.on_frame(&frame)?;
                    }
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => continue,
                Err(e) => return Err(e),
            }
        }
        self.request_positions()
    }

    fn on_frame(&mut self, frame: &Frame) -> io::Result<()> {
        if frame.header.system_id != u32::from(self.system_id) || frame.header.component_id != 1 {
            return Ok(());
        }
        let relayed = match &frame.message {
            MavMessage::HEARTBEAT(hb) if hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID => {
                self.heartbeats += 1;
                self.armed = hb
                    .base_mode
                    .contains(mavlink::dialects::common::MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
                self.custom_mode = hb.custom_mode;
                Some(frame.message.clone())
            }
            MavMessage::LOCAL_POSITION_NED(p) => {
                self.position_heard_at = Some(Instant::now());
                let t = f64::from(p.time_boot_ms) / 1000.0;
                let ned = [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
                let v = [f64::from(p.vx), f64::from(p.vy), f64::from(p.vz)];
                if ned.iter().chain(&v).all(|c| c.is_finite())
                    && self.reports.back().is_none_or(|(last, _, _)| t > *last)
                {
                    if self.reports.len() == KEEP_REPORTS {
                        self.reports.pop_front();
                    }
                    self.reports.push_back((t, ned, v));
                }
                // The ground tracks in the world frame: home sits at the spawn point.
                let mut world = p.clone();
                world.x += self.origin_world[1] as f32;
                world.y += self.origin_world[0] as f32;
                Some(MavMessage::LOCAL_POSITION_NED(world))
            }
            MavMessage::SYS_STATUS(_) | MavMessage::STATUSTEXT(_) => Some(frame.message.clone()),
            _ => None,
        };
        if let (Some(message), Some((codec, ground))) = (relayed, self.relay.as_mut()) {
            let bytes = codec.encode(&message);
            match self.serial1.send_to(&bytes, *ground) {
                Ok(_) => {}
                Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    /// ArduCopter streams LOCAL_POSITION_NED only to a port that asked (and only once its EKF
    /// has an origin, about 42 s of simulated time after boot); a request before its first
    /// heartbeat can be acknowledged and lost. So: after a heartbeat, while none come, ask
    /// once a second.
    fn request_positions(&mut self) -> io::Result<()> {
        let Some(peer) = self.peer else {
            return Ok(());
        };
        let silent = self
            .position_heard_at
            .is_none_or(|t| t.elapsed() > Duration::from_millis(1500));
        let due = self
            .requested_at
            .is_none_or(|t| t.elapsed() >= Duration::from_secs(1));
        if self.heartbeats == 0 || !silent || !due {
            return Ok(());
        }
        self.requested_at = Some(Instant::now());
        let request = message_interval(self.system_id, 1, 32, POSITION_INTERVAL_US);
        let bytes = self.codec.encode(&request);
        match self.serial1.send_to(&bytes, peer) {
            Ok(_) => Ok(()),
            Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => Ok(()),
            Err(e) => Err(e),
        }
    }

    /// System id.
    pub fn system_id(&self) -> u8 {
        self.system_id
    }
    /// Armed, as its last heartbeat said.
    pub fn armed(&self) -> bool {
        self.armed
    }
    /// In GUIDED, as its last heartbeat said.
    pub fn guided(&self) -> bool {
        self.custom_mode == GUIDED
    }
    /// Its simulated time as of the newest position report, s.
    pub fn time_s(&self) -> Option<f64> {
        self.reports.back().map(|(t, _, _)| *t)
    }

    /// Position and velocity (NED, from home) at its simulated time `t`, interpolated between
    /// the two reports around it; the newest when `t` is later, `None` before any report.
    pub fn state_at(&self, t: f64) -> Option<([f64; 3], [f64; 3])> {
        let after = self.reports.iter().position(|(time, _, _)| *time >= t);
        match after {
            Some(0) => self.reports.front().map(|(_, p, v)| (*p, *v)),
            Some(i) => {
                let (t0, p0, v0) = self.reports[i - 1];
                let (t1, p1, v1) = self.reports[i];
                let w = ((t - t0) / (t1 - t0)).clamp(0.0, 1.0);
                let lerp = |a: [f64; 3], b: [f64; 3]| {
                    [
                        a[0] + (b[0] - a[0]) * w,
                        a[1] + (b[1] - a[1]) * w,
                        a[2] + (b[2] - a[2]) * w,
                    ]
                };
                Some((lerp(p0, p1), lerp(v0, v1)))
            }
            None => self.reports.back().map(|(_, p, v)| (*p, *v)),
        }
    }

    /// The world position (simulator frame, m) of a NED position from its home.
    pub fn to_world(&self, ned: [f64; 3]) -> [f64; 3] {
        [
            self.origin_world[0] + ned[1],
            self.origin_world[1] + ned[0],
            -ned[2],
        ]
    }
}

impl Drop for ArduCopter {
    fn drop(&mut self) {
        // The process goes with its guard (dropped after this); its folder with it.
        let _ = std::fs::remove_dir_all(&self.workdir);
    }
}

/// An instance number whose RC-input port (UDP 5501 + 10 K, the one socket ArduCopter still
/// binds with its serial ports as clients) is free now.
fn free_instance() -> io::Result<u16> {
    for instance in 1..200u16 {
        let port = 5501 + 10 * instance;
        if UdpSocket::bind(("0.0.0.0", port)).is_ok() {
            return Ok(instance);
        }
    }
    Err(io::Error::new(
        io::ErrorKind::AddrInUse,
        "no free ArduCopter instance number (UDP 5511-7491 all taken)",
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_bundle_says_where_it_looked() {
        let empty = std::env::temp_dir().join(format!("skyherd-no-ac-{}", std::process::id()));
        std::fs::create_dir_all(&empty).unwrap();
        let missing = empty.join("no-such-arducopter");
        let err =
            ArduCopterBundle::locate_from(Some(missing.into()), &empty.join("repo")).unwrap_err();
        let text = err.to_string();
        assert!(text.contains("no-such-arducopter/arducopter"), "{text}");
        assert!(text.contains("ardupilot-sitl/arducopter"), "{text}");
        assert!(text.contains("scripts/build-arducopter.sh"), "{text}");
        let _ = std::fs::remove_dir_all(&empty);
    }
}
