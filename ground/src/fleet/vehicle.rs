//! Per-vehicle state folded from received frames: pure, time passed in (seconds on the
//! caller's clock).

use std::collections::BTreeMap;

use mavlink::MavHeader;
use mavlink::dialects::common::{MavAutopilot, MavMessage, MavModeFlag, MavState, MavType};

use skyherd_link::FlightMode;

/// Link quality of one vehicle, from MAVLink sequence numbers and arrival times.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LinkQuality {
    /// Frames received from this system (all components).
    pub received: u64,
    /// Frames inferred lost from gaps in each component's sequence numbers.
    pub lost: u64,
    /// When the last frame arrived (s, caller's clock).
    pub last_heard: f64,
    last_sequence: BTreeMap<u8, u8>,
}

impl LinkQuality {
    /// Fraction of frames lost, 0 when nothing has been received.
    pub fn loss_ratio(&self) -> f64 {
        let total = self.received + self.lost;
        if total == 0 {
            0.0
        } else {
            self.lost as f64 / total as f64
        }
    }

    /// Seconds since the last frame.
    pub fn age(&self, now: f64) -> f64 {
        now - self.last_heard
    }

    fn on_frame(&mut self, component: u8, sequence: u8, now: f64) {
        self.received += 1;
        self.last_heard = now;
        if let Some(last) = self.last_sequence.insert(component, sequence) {
            let gap = sequence.wrapping_sub(last.wrapping_add(1));
            // A "gap" over half the range is a reordered or duplicated frame, or a restart:
            // not a loss.
            if gap < 128 {
                self.lost += u64::from(gap);
            }
        }
    }
}

/// What the ground station knows about one vehicle. Positions: MAVLink LOCAL_NED, metres.
#[derive(Debug, Clone, PartialEq)]
pub struct VehicleState {
    /// MAVLink system id.
    pub system_id: u8,
    /// Component id of its autopilot (the one that sent the heartbeat).
    pub autopilot_component: u8,
    /// Autopilot flavour from the heartbeat.
    pub autopilot: MavAutopilot,
    /// Vehicle type from the heartbeat.
    pub mav_type: MavType,
    /// `base_mode` bits from the heartbeat.
    pub base_mode: MavModeFlag,
    /// `custom_mode` from the heartbeat (PX4: main mode << 16 | sub mode << 24).
    pub custom_mode: u32,
    /// Armed flag from the heartbeat.
    pub armed: bool,
    /// System status from the heartbeat.
    pub system_status: MavState,
    /// Last LOCAL_POSITION_NED position (m, NED).
    pub position_ned: Option<[f32; 3]>,
    /// Last LOCAL_POSITION_NED velocity (m/s, NED).
    pub velocity_ned: Option<[f32; 3]>,
    /// `time_boot_ms` of that position.
    pub position_time_boot_ms: u32,
    /// SYS_STATUS battery remaining, percent (None: not reported or -1).
    pub battery_remaining_pct: Option<i8>,
    /// SYS_STATUS battery voltage (V).
    pub battery_voltage: Option<f32>,
    /// When the last heartbeat arrived (s, caller's clock).
    pub last_heartbeat: f64,
    /// Sequence-gap and age statistics.
    pub link: LinkQuality,
}

impl VehicleState {
    fn new(system_id: u8, component: u8) -> Self {
        Self {
            system_id,
            autopilot_component: component,
            autopilot: MavAutopilot::MAV_AUTOPILOT_GENERIC,
            mav_type: MavType::MAV_TYPE_GENERIC,
            base_mode: MavModeFlag::empty(),
            custom_mode: 0,
            armed: false,
            system_status: MavState::MAV_STATE_UNINIT,
            position_ned: None,
            velocity_ned: None,
            position_time_boot_ms: 0,
            battery_remaining_pct: None,
            battery_voltage: None,
            last_heartbeat: f64::NEG_INFINITY,
            link: LinkQuality::default(),
        }
    }

    /// Position in the simulator frame (x east, y north, z up; m).
    pub fn position_sim(&self) -> Option<[f32; 3]> {
        self.position_ned.map(skyherd_onboard::frame::ned_to_sim)
    }

    /// The flight mode named by the last heartbeat.
    pub fn flight_mode(&self) -> FlightMode {
        FlightMode::from_heartbeat(self.autopilot, self.custom_mode)
    }
}

/// All vehicles heard on a link, by system id.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Fleet {
    vehicles: BTreeMap<u8, VehicleState>,
}

impl Fleet {
    /// Fold one received frame into the fleet state. `own_system_id` (the ground station)
    /// and ground-control heartbeats are ignored. Returns true when the frame announced a
    /// vehicle not seen before.
    pub fn on_frame(
        &mut self,
        header: &MavHeader,
        message: &MavMessage,
        now: f64,
        own_system_id: u8,
    ) -> bool {
        let Ok(system_id) = u8::try_from(header.system_id) else {
            return false;
        };
        if system_id == own_system_id {
            return false;
        }
        let mut discovered = false;
        if let MavMessage::HEARTBEAT(hb) = message {
            // Only an autopilot's heartbeat defines a vehicle: not a GCS, not a companion
            // computer or camera on the same system id.
            let is_vehicle = hb.mavtype != MavType::MAV_TYPE_GCS
                && hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID;
            if is_vehicle {
                let v = self.vehicles.entry(system_id).or_insert_with(|| {
                    discovered = true;
                    VehicleState::new(system_id, header.component_id)
                });
                v.autopilot_component = header.component_id;
                v.autopilot = hb.autopilot;
                v.mav_type = hb.mavtype;
                v.base_mode = hb.base_mode;
                v.custom_mode = hb.custom_mode;
                v.armed = hb
                    .base_mode
                    .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
                v.system_status = hb.system_status;
                v.last_heartbeat = now;
            }
        }
        let Some(v) = self.vehicles.get_mut(&system_id) else {
            return discovered;
        };
        v.link.on_frame(header.component_id, header.sequence, now);
        match message {
            MavMessage::LOCAL_POSITION_NED(p) => {
                v.position_ned = Some([p.x, p.y, p.z]);
                v.velocity_ned = Some([p.vx, p.vy, p.vz]);
                v.position_time_boot_ms = p.time_boot_ms;
            }
            MavMessage::SYS_STATUS(s) => {
                v.battery_remaining_pct = (s.battery_remaining >= 0).then_some(s.battery_remaining);
                v.battery_voltage = (s.voltage_battery != u16::MAX)
                    .then_some(f32::from(s.voltage_battery) / 1000.0);
            }
            _ => {}
        }
        discovered
    }

    /// One vehicle.
    pub fn get(&self, system_id: u8) -> Option<&VehicleState> {
        self.vehicles.get(&system_id)
    }

    /// All vehicles, by ascending system id.
    pub fn iter(&self) -> impl Iterator<Item = &VehicleState> + '_ {
        self.vehicles.values()
    }

    /// Number of vehicles known.
    pub fn len(&self) -> usize {
        self.vehicles.len()
    }

    /// No vehicle known yet.
    pub fn is_empty(&self) -> bool {
        self.vehicles.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA};

    fn header(system_id: u32, sequence: u8) -> MavHeader {
        MavHeader {
            system_id,
            component_id: 1,
            sequence,
        }
    }

    fn heartbeat(armed: bool, autopilot: MavAutopilot, custom_mode: u32) -> MavMessage {
        let mut base_mode = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        if armed {
            base_mode |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot,
            base_mode,
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        })
    }

    #[test]
    fn heartbeat_defines_vehicle_and_mode() {
        let mut fleet = Fleet::default();
        assert!(fleet.on_frame(
            &header(3, 0),
            &heartbeat(true, MavAutopilot::MAV_AUTOPILOT_PX4, 6 << 16),
            1.0,
            255
        ));
        let v = fleet.get(3).unwrap();
        assert!(v.armed);
        assert_eq!(v.flight_mode(), FlightMode::PX4_OFFBOARD);
        // Our own frames and a GCS heartbeat do not create vehicles.
        assert!(!fleet.on_frame(
            &header(255, 0),
            &heartbeat(false, MavAutopilot::MAV_AUTOPILOT_PX4, 0),
            1.0,
            255
        ));
        assert_eq!(fleet.len(), 1);
    }

    #[test]
    fn position_in_both_frames_and_sequence_gaps() {
        let mut fleet = Fleet::default();
        fleet.on_frame(
            &header(3, 10),
            &heartbeat(false, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA, 4),
            0.0,
            255,
        );
        let pos = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: 100,
            x: 20.0,
            y: 10.0,
            z: -2.0,
            vx: 1.0,
            vy: 0.0,
            vz: 0.0,
        });
        fleet.on_frame(&header(3, 13), &pos, 0.5, 255); // 11 and 12 lost
        let v = fleet.get(3).unwrap();
        assert_eq!(v.position_sim(), Some([10.0, 20.0, 2.0]));
        assert_eq!(v.flight_mode(), FlightMode::ARDUPILOT_GUIDED);
        assert_eq!((v.link.received, v.link.lost), (2, 2));
        assert!((v.link.loss_ratio() - 0.5).abs() < 1e-12);
        assert!((v.link.age(1.5) - 1.0).abs() < 1e-12);
    }
}
