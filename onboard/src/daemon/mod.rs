//! The companion-computer daemon (feature `std`): a pure decision core and a thin I/O shell.
//!
//! * [`core`] takes explicit state and time (ground uplink, autopilot telemetry, the daemon's
//!   clock in milliseconds) and returns decisions: velocity setpoints in NED, autopilot commands,
//!   and a [`core::Status`] saying what it does and why. No sockets, no clock.
//! * [`io`] owns the sockets: MAVLink to the autopilot and to the ground station, signing
//!   checks, heartbeats, and the two clocks (wall clock, or the simulator's `time_boot_ms` in
//!   lockstep mode).
//! * [`selftest`] exercises the core without sockets; `skyherd-onboard self-test` runs it.
//!
//! Frames: the core works in the simulator frame (x east, y north, z up, metres, m/s) and
//! converts only at its edges through [`crate::frame`]; everything sent to or read from the
//! autopilot is MAVLink `LOCAL_NED`.

pub mod core;
pub mod io;
pub mod selftest;

#[cfg(test)]
mod loopback_tests;
