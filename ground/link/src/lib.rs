#![doc = include_str!("../README.md")]
//!
//! # The API in brief
//!
//! The ground station (`skyherd-ground`), the companion-computer daemon (`skyherd-daemon`)
//! and the mock autopilots (`skyherd-sitl`) all frame, sign and command through this crate,
//! so they cannot drift apart in how they count bytes, which mode numbers they send or which
//! setpoint fields they ignore. Pure: no sockets, no clock (signing timestamps come from the
//! `mavlink` crate's wall clock, as the signing specification asks).
//!
//! * [`codec`]: framing, signing and parsing over raw bytes, with counted drops.
//! * [`command`]: COMMAND_LONG builders (arm, set mode), velocity setpoints, heartbeats,
//!   COMMAND_ACK matching.
//! * [`flavour`]: PX4 and ArduPilot: flight-mode numbering ([`FlightMode`]) and the
//!   autopilot families ([`Flavour`]).
//! * [`signing`]: 32-byte keys, key files (generated from OS randomness, created 0600,
//!   refused when open to others) and the one signing set-up.
//! * [`replay`]: signature checks with per-stream replay state that can be persisted, a
//!   bound on timestamps from the future, and the caller's clock passed in.
//!
//! Frame: setpoints are MAVLink `LOCAL_NED` (x north, y east, z down), metres and m/s.
//!
//! ```
//! use skyherd_link::command::velocity_setpoint_ned;
//! use skyherd_link::{Codec, Flavour, VELOCITY_ONLY_TYPE_MASK};
//!
//! let mut ground = Codec::new(255, 190, None);
//! let bytes = ground.encode(&velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]));
//! let mut drone = Codec::new(1, 1, None);
//! let mut frames = Vec::new();
//! drone.decode(&bytes, &mut frames);
//! assert_eq!(frames.len(), 1);
//! assert_eq!(frames[0].header.system_id, 255);
//! assert_eq!(Flavour::Px4.external_mode().custom_mode(), 6 << 16);
//! assert_eq!(VELOCITY_ONLY_TYPE_MASK, 0x0DC7);
//! ```

pub mod codec;
pub mod command;
pub mod flavour;
pub mod replay;
pub mod signing;

pub use codec::{Codec, CodecStats, Frame};
pub use command::{CommandOutcome, CommandResult, PendingCommands, VELOCITY_ONLY_TYPE_MASK};
pub use flavour::{Flavour, FlightMode};
pub use signing::{KeyFileError, Signing, SigningKey};

/// MAVLink system id of the ground station.
pub const GROUND_SYSTEM_ID: u8 = 255;
/// MAVLink component id of a ground control station (MAV_COMP_ID_MISSIONPLANNER).
pub const GROUND_COMPONENT_ID: u8 = 190;
/// MAVLink component id of the companion-computer daemon (MAV_COMP_ID_ONBOARD_COMPUTER).
pub const DAEMON_COMPONENT_ID: u8 = 191;
/// MAVLink component id of an autopilot (MAV_COMP_ID_AUTOPILOT1).
pub const AUTOPILOT_COMPONENT_ID: u8 = 1;
