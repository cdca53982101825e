//! skyherd onboard core.
#![cfg_attr(not(feature = "std"), no_std)]

pub use skyherd_model::Task;
