//! skyherd-trainer: MTDDPG for skyherd.
#![forbid(unsafe_op_in_unsafe_fn)]

pub mod network;
pub mod nn;
