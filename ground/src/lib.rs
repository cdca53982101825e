#![doc = include_str!("../README.md")]
//!
//! # The API in brief
//!
//! * [`fleet`]: the fleet link (UDP, TCP, serial) over `skyherd_link`'s codec and signing,
//!   per-vehicle state, mission commands with COMMAND_ACK matching.
//! * [`station`]: the mission loop as a pure core ([`station::GroundStation`]: scans,
//!   telemetry and time in, frames to send out); the `skyherd-ground` binary only moves bytes.
//! * [`mission`]: when to start, complete or abort; [`uplink`]: snapshots and commands as
//!   TUNNEL frames; [`detections`]: the sensor's scans.
//! * [`tlog`]: `.tlog` writer (pymavlink's format) with an injectable clock; [`spool`]: the
//!   binary's log files written on a thread of their own, so a stalled disk never stalls the loop.
//! * [`tracking`]: multi-target tracker over anonymous detections (constant-velocity Kalman
//!   filters, grid gating, clustered assignment, M-of-N birth, death by misses).
//!
//! Frames: the tracker works in the simulator frame (x east, y north, metres); MAVLink
//! positions are LOCAL_NED and are converted only through `skyherd_onboard::frame`.
pub mod detections;
pub mod fleet;
pub mod mission;
pub mod spool;
pub mod station;
pub mod tlog;
pub mod tracking;
pub mod uplink;
