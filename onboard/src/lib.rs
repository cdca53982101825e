//! skyherd onboard core.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod frame;
pub mod obs;

pub use skyherd_model::Task;
