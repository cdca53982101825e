#![doc = include_str!("../README.md")]
#![cfg_attr(not(feature = "std"), no_std)]

pub mod actor;
pub mod frame;
pub mod obs;
pub mod safety;
pub mod separation;
pub mod wire;

pub use skyherd_model::Task;
