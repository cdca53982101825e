//! skyherd onboard core: what one drone needs to decide, as pure, allocation-free functions.
//!
//! * [`obs`]: world snapshot -> fixed-size feature vector (the only copy of the encoder).
//! * [`actor`]: the int8 multi-task actor over a decoded model file.
//! * [`safety`]: speed and altitude clamp, geofence, stale and non-finite data -> hold.
//! * [`wire`]: the uplink messages (world snapshot, mission command) in postcard, chunked into
//!   MAVLink TUNNEL payloads, and their loss- and reorder-tolerant reassembly.
//! * [`frame`]: simulator frame (z up) <-> MAVLink LOCAL_NED.
//!
//! `#![no_std]` without alloc; logging through `log`. Features (additive):
//! * `std`: `std::error::Error` impls and the model crate's host tools. The companion-computer
//!   daemon that flies this core is the `skyherd-daemon` crate.
//!
//! One decision, from bytes on the wire to a safe velocity:
//!
//! ```
//! # #[cfg(feature = "std")] {
//! use skyherd_model::{quantize, ActorShape, FloatActor, ModelMeta, Task};
//! use skyherd_onboard::{actor::Actor, obs, safety};
//!
//! // A model from seeded, untrained weights (a trained one would come from the trainer).
//! let shape = ActorShape { features: obs::FEATURES, hidden: 32, shared_layers: 2 };
//! let meta = ModelMeta { encoder_version: obs::ENCODER_VERSION, max_speed: 5.0 };
//! let calibration = [[0.5_f32; obs::FEATURES]];
//! let calibration = calibration.iter().map(|f| (Task::Driving, &f[..]));
//! let bytes = quantize(&FloatActor::random(shape, 1), meta, calibration).unwrap();
//! let actor = Actor::from_bytes(&bytes).unwrap();
//!
//! let herders = [[100.0_f32, 100.0, 2.0], [140.0, 90.0, 2.0]];
//! let targets = [[120.0_f32, 120.0], [125.0, 118.0], [118.0, 125.0]];
//! let input = obs::ObsInput {
//!     own_index: 0, herders: &herders, targets: &targets, goal: [300.0, 300.0],
//!     goal_radius: 45.0, area: [500.0, 500.0, 10.0], max_speed: 5.0,
//! };
//! let mut features = [0.0; obs::FEATURES];
//! let frame = obs::encode(&input, &mut features).unwrap();
//! let velocity = frame.action_to_world(actor.infer(Task::Driving, &features));
//!
//! let limits = safety::Limits::arena([500.0, 500.0, 10.0], 5.0);
//! let decision = safety::check(&limits, &safety::Situation {
//!     position: herders[0], velocity, snapshot_age_s: 0.1, snapshot_finite: true,
//! });
//! assert!(!decision.hold && decision.speed() <= 5.0 + 1e-4);
//! # }
//! ```
#![cfg_attr(not(feature = "std"), no_std)]

pub mod actor;
pub mod frame;
pub mod obs;
pub mod safety;
pub mod wire;

pub use skyherd_model::Task;
