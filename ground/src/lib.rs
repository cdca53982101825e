//! skyherd-ground: the ground station's library.
//!
//! * [`fleet`]: the fleet link (UDP, TCP, serial) over `skyherd_link`'s codec and signing,
//!   per-vehicle state, mission commands with COMMAND_ACK matching.
//! * [`tlog`]: `.tlog` writer (pymavlink's format) with an injectable clock.
//! * [`tracking`]: multi-target tracker over anonymous detections (constant-velocity Kalman
//!   filters, grid gating, clustered assignment, M-of-N birth, death by misses).
//!
//! Frames: the tracker works in the simulator frame (x east, y north, metres); MAVLink
//! positions are LOCAL_NED and are converted only through `skyherd_onboard::frame`.
pub mod detections;
pub mod fleet;
pub mod mission;
pub mod tlog;
pub mod tracking;
pub mod uplink;
