#![doc = include_str!("../README.md")]
//!
//! # The API in brief
//!
//! Software-in-the-loop pieces: mock autopilots speaking MAVLink 2 over UDP, a target
//! detection sensor, and link fault injection. Everything is driven by an explicit simulated
//! clock (lockstep): whoever owns the loop steps the world, then each node with the same
//! `now`.
//!
//! * [`autopilot`]: the pure [`MockAutopilot`] state machine (PX4 / ArduPilot rules, see
//!   `docs/autopilots.md`).
//! * [`arducopter`]: a real ArduCopter SITL as one of a mission's drones, its clock and
//!   position followed.
//! * [`node`]: [`AutopilotNode`], its UDP shell (one socket per drone, optional signing and
//!   faults).
//! * [`sensor`]: [`DetectionSensor`], noisy anonymous detections from true positions.
//! * [`faults`]: [`FaultPlan`] (seeded loss, latency, cuts) and [`FaultyUdp`].
//!
//! Frames: autopilots speak MAVLink LOCAL_NED; the world is in the simulator frame; they meet
//! only in `skyherd_onboard::frame::{sim_to_ned, ned_to_sim}`.
//!
//! ```
//! use skyherd_sitl::{AutopilotConfig, AutopilotNode, MockAutopilot, NodeOptions};
//! use skyherd_onboard::frame::sim_to_ned;
//!
//! let start = sim_to_ned([10.0_f64, 20.0, 2.0]); // 10 m east, 20 m north, 2 m up
//! // Already flying (armed, holding); `MockAutopilot::new` starts one on the ground.
//! let autopilot = MockAutopilot::new_flying(AutopilotConfig::px4(1), start, 0.0);
//! let mut node = AutopilotNode::bind("127.0.0.1:0".parse().unwrap(), autopilot,
//!     NodeOptions::default()).unwrap();
//! let mut now = 0.0;
//! for _ in 0..10 {
//!     let velocity_ned = node.step(now).unwrap(); // hold: nobody has commanded it
//!     assert_eq!(velocity_ned, [0.0; 3]);
//!     now += 0.1;
//! }
//! assert_eq!(node.autopilot().position_ned(), start);
//! ```

pub mod arducopter;
pub mod autopilot;
pub mod console;
pub mod faults;
pub mod launch;
pub mod mission;
pub mod node;
pub mod sensor;

pub use autopilot::{AutopilotConfig, MockAutopilot, Rejections, Tick};
pub use faults::{DelayLine, FaultConfig, FaultPlan, FaultStats, FaultyUdp, Verdict};
pub use node::{AutopilotNode, NodeOptions};
pub use sensor::{DetectionSensor, SensorConfig, SensorError};

#[cfg(test)]
mod loopback_tests;
#[cfg(test)]
mod pymavlink_tests;
