//! skyherd-ground: the ground station's library.
//!
//! * [`tracking`]: multi-target tracker over anonymous detections (constant-velocity Kalman
//!   filters, grid gating, clustered assignment, M-of-N birth, death by misses).
pub mod tracking;
