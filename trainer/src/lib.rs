//! skyherd-trainer: MTDDPG for skyherd.
#![forbid(unsafe_op_in_unsafe_fn)]

pub mod checkpoint;
pub mod config;
pub mod ddpg;
pub mod eval;
pub mod export;
pub mod network;
pub mod nn;
pub mod policy;
pub mod replay;
pub mod report;
pub mod rollout;
pub mod train;
