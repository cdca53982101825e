#![doc = include_str!("../README.md")]
//!
//! # The API in brief
//!
//! * [`control`] takes explicit state and time (ground uplink, autopilot telemetry, the daemon's
//!   clock in milliseconds) and returns decisions: velocity setpoints in NED, autopilot commands,
//!   and a [`control::Status`] saying what it does and why. No sockets, no clock.
//! * [`io`] owns the sockets: MAVLink to the autopilot and to the ground station, signing
//!   checks, heartbeats, and the two clocks (wall clock, or the simulator's `time_boot_ms` in
//!   lockstep mode).
//! * [`selftest`] exercises the core without sockets; `skyherd-onboard self-test` runs it.
//!
//! Frames: the core works in the simulator frame (x east, y north, z up, metres, m/s) and
//! converts only at its edges through [`skyherd_onboard::frame`]; everything sent to or read from the
//! autopilot is MAVLink `LOCAL_NED`.
//!
//! # One daemon per drone
//! As a process (what a SITL orchestrator launches, one per simulated drone):
//!
//! ```text
//! skyherd-onboard run --model models/herd.skym --system-id 2 --herder-index 1 \
//!     --autopilot udpout:127.0.0.1:14541 --ground udpin:127.0.0.1:14602 --key uplink.key \
//!     --flavour px4 --sim-clock
//! ```
//!
//! or embedded, in a thread of a test or a simulator:
//!
//! ```no_run
//! use skyherd_onboard::actor::Actor;
//! use skyherd_daemon::control::{CoreConfig, DaemonCore};
//! use skyherd_link::Flavour;
//! use skyherd_daemon::io::{ClockMode, Daemon, LinkOptions};
//!
//! let model = std::fs::read("models/herd.skym").unwrap();
//! let actor = Actor::from_bytes(&model).unwrap();
//! // System id 2, herder 1 in the ground's snapshots, a PX4.
//! let core = DaemonCore::new(CoreConfig::new(2, 1, Flavour::Px4), actor);
//! let options = LinkOptions {
//!     autopilot: "udpout:127.0.0.1:14541".into(),
//!     ground: "udpin:127.0.0.1:0".into(), // port 0: pick one, read it back below
//!     signing_key: Some([0x42; 32]),
//!     autopilot_key: None,  // or the key the autopilot verifies
//!     replay_state: None,   // or a file, so that a restart keeps refusing old frames
//!     clock: ClockMode::Simulator { lockstep: true },
//! };
//! let mut daemon = Daemon::connect(&options, core).unwrap();
//! println!("uplink to {}", daemon.ground_address().unwrap());
//! let stop = daemon.stop_flag(); // set it from another thread to end run()
//! daemon.run().unwrap();
//! println!("{:?} {:?}", daemon.counters(), daemon.core().counters());
//! # drop(stop);
//! ```

pub mod control;
pub mod io;
pub mod log_queue;
pub mod selftest;

#[cfg(test)]
mod loopback_tests;
