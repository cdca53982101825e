//! The uplink: world snapshots and mission commands for the drones, as MAVLink TUNNEL frames.
//!
//! Each [`Uplink`] message is postcard-encoded by `skyherd_onboard::wire`, split into chunks that
//! fit a TUNNEL payload (128 bytes) and wrapped in `TUNNEL` messages with payload type 0
//! (`MAV_TUNNEL_PAYLOAD_TYPE_UNKNOWN`: rust-mavlink rejects unknown payload-type values). The
//! drone's reassembler tolerates lost and reordered chunks; a message with a lost chunk is
//! simply superseded by the next one.
//!
//! The snapshot is built here from what the ground knows: the drones' own telemetry (converted
//! from NED by the link) and the tracker's confirmed targets, all in the simulator frame.
//!
//! ```
//! use skyherd_ground::uplink::{SnapshotInputs, UplinkEncoder};
//! use skyherd_onboard::Task;
//!
//! let mut uplink = UplinkEncoder::new();
//! let inputs = SnapshotInputs {
//!     task: Task::Driving,
//!     herders: &[[1.0, 1.0, 2.0], [2.0, 1.0, 2.0]],
//!     targets: &[[3.0, 3.0], [3.5, 3.2]],
//!     goal: [8.0, 8.0],
//!     goal_radius: 1.5,
//!     area: [10.0, 10.0, 3.0],
//!     max_speed: 1.0,
//!     timestamp_ms: 1_000,
//! };
//! let frames = uplink.snapshot(&inputs, 0).unwrap();
//! assert!(!frames.is_empty());
//! ```

use mavlink::dialects::common::{MavMessage, MavTunnelPayloadType, TUNNEL_DATA};
use skyherd_onboard::Task;
use skyherd_onboard::wire::{
    self, MAX_HERDERS, MAX_MESSAGE, MAX_TARGETS, MissionAction, MissionCommand, Uplink, WireError,
    WorldSnapshot,
};
use thiserror::Error;

/// Why an uplink message could not be built.
#[derive(Debug, Error, PartialEq)]
pub enum UplinkError {
    /// More herders than a snapshot holds.
    #[error("{0} herders exceed the snapshot's capacity of {MAX_HERDERS}")]
    TooManyHerders(usize),
    /// Encoding or chunking failed.
    #[error("uplink encoding failed: {0:?}")]
    Wire(WireError),
}

/// What a world snapshot is made of; simulator frame, metres, m/s.
#[derive(Clone, Copy, Debug)]
pub struct SnapshotInputs<'a> {
    /// The task being flown.
    pub task: Task,
    /// Every herder's position `[x, y, z]` (z up), in herder-index order (system id - 1).
    pub herders: &'a [[f32; 3]],
    /// Tracked target positions `[x, y]`; beyond [`MAX_TARGETS`] the rest are left out.
    pub targets: &'a [[f32; 2]],
    /// Goal centre.
    pub goal: [f32; 2],
    /// Goal radius.
    pub goal_radius: f32,
    /// Arena `[width, depth, ceiling]` from the origin.
    pub area: [f32; 3],
    /// Herders' speed limit.
    pub max_speed: f32,
    /// Ground clock, milliseconds.
    pub timestamp_ms: u64,
}

/// Numbers snapshots, commands and chunked messages, and turns them into TUNNEL frames.
pub struct UplinkEncoder {
    snapshot_sequence: u32,
    command_sequence: u32,
    message_id: u16,
    last_command: Option<MissionCommand>,
    buffer: Box<[u8; MAX_MESSAGE]>,
}

impl Default for UplinkEncoder {
    fn default() -> Self {
        Self::new()
    }
}

impl std::fmt::Debug for UplinkEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UplinkEncoder")
            .field("snapshot_sequence", &self.snapshot_sequence)
            .field("command_sequence", &self.command_sequence)
            .finish()
    }
}

impl UplinkEncoder {
    /// A fresh encoder; sequences start at 1.
    pub fn new() -> Self {
        Self {
            snapshot_sequence: 0,
            command_sequence: 0,
            message_id: 0,
            last_command: None,
            buffer: Box::new([0; MAX_MESSAGE]),
        }
    }

    /// TUNNEL frames carrying a world snapshot, addressed to `target_system` (0 = everyone).
    pub fn snapshot(
        &mut self,
        inputs: &SnapshotInputs<'_>,
        target_system: u8,
    ) -> Result<Vec<MavMessage>, UplinkError> {
        if inputs.herders.len() > MAX_HERDERS {
            return Err(UplinkError::TooManyHerders(inputs.herders.len()));
        }
        self.snapshot_sequence = self.snapshot_sequence.wrapping_add(1);
        let mut snapshot = WorldSnapshot::empty(inputs.task, inputs.area);
        snapshot.sequence = self.snapshot_sequence;
        snapshot.timestamp_ms = inputs.timestamp_ms;
        for &h in inputs.herders {
            // Capacity was checked above.
            let _ = snapshot.herders.push(h);
        }
        for &t in inputs.targets.iter().take(MAX_TARGETS) {
            let _ = snapshot.targets.push(t);
        }
        snapshot.goal = inputs.goal;
        snapshot.goal_radius = inputs.goal_radius;
        snapshot.max_speed = inputs.max_speed;
        self.frames(&Uplink::Snapshot(snapshot), target_system)
    }

    /// TUNNEL frames carrying a mission command, addressed to `target_system` (0 = everyone).
    pub fn command(
        &mut self,
        task: Task,
        goal: [f32; 2],
        goal_radius: f32,
        action: MissionAction,
        target_system: u8,
    ) -> Result<Vec<MavMessage>, UplinkError> {
        self.command_sequence = self.command_sequence.wrapping_add(1);
        let command = MissionCommand {
            sequence: self.command_sequence,
            task,
            goal,
            goal_radius,
            action,
        };
        self.last_command = Some(command);
        self.frames(&Uplink::Command(command), target_system)
    }

    /// The last command again, same sequence number (a drone acts on it once) but a new chunk
    /// message id: the drone's reassembler drops chunks of messages older than the newest it has
    /// seen, and snapshots have been sent since. `None` before any command.
    pub fn repeat_command(
        &mut self,
        target_system: u8,
    ) -> Option<Result<Vec<MavMessage>, UplinkError>> {
        let command = self.last_command?;
        Some(self.frames(&Uplink::Command(command), target_system))
    }

    fn frames(
        &mut self,
        message: &Uplink,
        target_system: u8,
    ) -> Result<Vec<MavMessage>, UplinkError> {
        self.message_id = self.message_id.wrapping_add(1);
        let bytes =
            wire::encode_uplink(message, &mut self.buffer[..]).map_err(UplinkError::Wire)?;
        let chunks = wire::chunks(self.message_id, bytes).map_err(UplinkError::Wire)?;
        Ok(chunks
            .map(|chunk| {
                let data = chunk.as_bytes();
                let mut payload = [0u8; 128];
                payload[..data.len()].copy_from_slice(data);
                MavMessage::TUNNEL(TUNNEL_DATA {
                    payload_type: MavTunnelPayloadType::MAV_TUNNEL_PAYLOAD_TYPE_UNKNOWN,
                    target_system,
                    target_component: 0,
                    payload_length: data.len() as u8,
                    payload,
                })
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_onboard::wire::{Reassembler, decode_uplink};

    fn reassemble(frames: &[MavMessage]) -> Option<Uplink> {
        let mut reassembler = Reassembler::new();
        let mut done = None;
        for frame in frames {
            let MavMessage::TUNNEL(t) = frame else {
                panic!("not a tunnel frame")
            };
            if let Some(bytes) = reassembler
                .push(&t.payload[..usize::from(t.payload_length)])
                .expect("valid chunk")
            {
                done = Some(decode_uplink(bytes).expect("decodes"));
            }
        }
        done
    }

    #[test]
    fn a_large_snapshot_survives_chunking_in_any_order() {
        let targets: Vec<[f32; 2]> = (0..1024)
            .map(|i| [i as f32 * 0.4, 250.0 - i as f32 * 0.1])
            .collect();
        let herders = [[10.0, 10.0, 2.0]; 4];
        let inputs = SnapshotInputs {
            task: Task::Collecting,
            herders: &herders,
            targets: &targets,
            goal: [400.0, 400.0],
            goal_radius: 45.0,
            area: [500.0, 500.0, 10.0],
            max_speed: 5.0,
            timestamp_ms: 42,
        };
        let mut uplink = UplinkEncoder::new();
        let mut frames = uplink.snapshot(&inputs, 3).unwrap();
        assert!(frames.len() > 60, "1024 targets need many chunks");
        frames.reverse();
        let Some(Uplink::Snapshot(s)) = reassemble(&frames) else {
            panic!("no snapshot")
        };
        assert_eq!(s.targets.len(), 1024);
        assert_eq!(s.targets[1023], targets[1023]);
        assert_eq!(s.task, Task::Collecting);
        assert_eq!(s.sequence, 1);
        for frame in &frames {
            let MavMessage::TUNNEL(t) = frame else {
                unreachable!()
            };
            assert_eq!(t.target_system, 3);
        }
    }

    #[test]
    fn commands_are_numbered() {
        let mut uplink = UplinkEncoder::new();
        for expected in 1..=3 {
            let frames = uplink
                .command(Task::Driving, [1.0, 2.0], 3.0, MissionAction::Start, 0)
                .unwrap();
            let Some(Uplink::Command(c)) = reassemble(&frames) else {
                panic!("no command")
            };
            assert_eq!(c.sequence, expected);
            assert_eq!(c.action, MissionAction::Start);
        }
    }

    #[test]
    fn a_repeated_command_survives_snapshots_sent_in_between() {
        let mut uplink = UplinkEncoder::new();
        assert!(uplink.repeat_command(0).is_none());
        let first = uplink
            .command(Task::Driving, [1.0, 2.0], 3.0, MissionAction::Start, 0)
            .unwrap();
        let inputs = SnapshotInputs {
            task: Task::Driving,
            herders: &[[0.0; 3]],
            targets: &[[1.0, 1.0]],
            goal: [1.0, 2.0],
            goal_radius: 3.0,
            area: [10.0, 10.0, 3.0],
            max_speed: 1.0,
            timestamp_ms: 0,
        };
        let snapshot = uplink.snapshot(&inputs, 0).unwrap();
        let again = uplink.repeat_command(0).unwrap().unwrap();
        // A drone that missed the first command hears the snapshot, then the repeat.
        let mut reassembler = Reassembler::new();
        let mut got = Vec::new();
        for frame in snapshot.iter().chain(&again) {
            let MavMessage::TUNNEL(t) = frame else {
                unreachable!()
            };
            if let Ok(Some(bytes)) = reassembler.push(&t.payload[..usize::from(t.payload_length)]) {
                got.push(decode_uplink(bytes).unwrap());
            }
        }
        let Some(Uplink::Command(c)) = got.last() else {
            panic!("the repeat was dropped: {got:?}")
        };
        assert_eq!(c.sequence, 1, "same command, same sequence");
        assert_ne!(first, again, "new chunk message id");
    }

    #[test]
    fn too_many_herders_is_an_error() {
        let herders = vec![[0.0; 3]; MAX_HERDERS + 1];
        let inputs = SnapshotInputs {
            task: Task::Driving,
            herders: &herders,
            targets: &[],
            goal: [1.0, 1.0],
            goal_radius: 1.0,
            area: [10.0, 10.0, 3.0],
            max_speed: 1.0,
            timestamp_ms: 0,
        };
        assert_eq!(
            UplinkEncoder::new().snapshot(&inputs, 0).unwrap_err(),
            UplinkError::TooManyHerders(MAX_HERDERS + 1)
        );
    }
}
