//! Building mission commands and matching their COMMAND_ACKs: pure, time passed in.

use mavlink::dialects::common::{
    COMMAND_ACK_DATA, COMMAND_LONG_DATA, HEARTBEAT_DATA, MavAutopilot, MavCmd, MavFrame,
    MavMessage, MavModeFlag, MavResult, MavState, MavType, PositionTargetTypemask,
    SET_POSITION_TARGET_LOCAL_NED_DATA,
};

pub use crate::flavour::FlightMode;

/// SET_POSITION_TARGET_LOCAL_NED type_mask that keeps only the velocity (ignores position,
/// acceleration, yaw and yaw rate): bits 0-2, 6-8, 10, 11.
pub const VELOCITY_ONLY_TYPE_MASK: u16 = 0x0DC7;

/// A COMMAND_LONG to one system/component.
pub fn command_long(
    target_system: u8,
    target_component: u8,
    command: MavCmd,
    params: [f32; 7],
) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: params[0],
        param2: params[1],
        param3: params[2],
        param4: params[3],
        param5: params[4],
        param6: params[5],
        param7: params[6],
        command,
        target_system,
        target_component,
        confirmation: 0,
    })
}

/// MAV_CMD_COMPONENT_ARM_DISARM (param1 = 1 arm, 0 disarm).
pub fn arm_disarm(target_system: u8, target_component: u8, arm: bool) -> MavMessage {
    let p1 = if arm { 1.0 } else { 0.0 };
    command_long(
        target_system,
        target_component,
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [p1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    )
}

/// MAV_CMD_DO_SET_MODE: param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 = custom (main)
/// mode, param3 = PX4 sub mode.
pub fn set_mode(target_system: u8, target_component: u8, mode: FlightMode) -> MavMessage {
    let (p2, p3) = match mode {
        FlightMode::Px4 { main, sub } => (f32::from(main), f32::from(sub)),
        FlightMode::ArduPilot(m) | FlightMode::Other(m) => (m as f32, 0.0),
    };
    command_long(
        target_system,
        target_component,
        MavCmd::MAV_CMD_DO_SET_MODE,
        [1.0, p2, p3, 0.0, 0.0, 0.0, 0.0],
    )
}

/// MAV_CMD_NAV_LAND as a COMMAND_LONG: land where the vehicle is. Param 1 (abort altitude)
/// and 2 (precision landing) 0: the autopilot's defaults; 4-7 NaN: current heading, here (PX4
/// and ArduPilot switch to their LAND mode and ignore a position they are not given).
pub fn land(target_system: u8, target_component: u8) -> MavMessage {
    command_long(
        target_system,
        target_component,
        MavCmd::MAV_CMD_NAV_LAND,
        [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, f32::NAN],
    )
}

/// MAV_CMD_SET_MESSAGE_INTERVAL: send message `message_id` every `interval_us` µs on the link
/// the command came in on (ArduPilot streams LOCAL_POSITION_NED only when asked).
pub fn message_interval(
    target_system: u8,
    target_component: u8,
    message_id: u32,
    interval_us: f32,
) -> MavMessage {
    command_long(
        target_system,
        target_component,
        MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        [message_id as f32, interval_us, 0.0, 0.0, 0.0, 0.0, 0.0],
    )
}

/// A velocity-only setpoint in MAV_FRAME_LOCAL_NED (m/s, north-east-down).
pub fn velocity_setpoint_ned(
    target_system: u8,
    target_component: u8,
    time_boot_ms: u32,
    velocity_ned: [f32; 3],
) -> MavMessage {
    MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
        time_boot_ms,
        x: 0.0,
        y: 0.0,
        z: 0.0,
        vx: velocity_ned[0],
        vy: velocity_ned[1],
        vz: velocity_ned[2],
        afx: 0.0,
        afy: 0.0,
        afz: 0.0,
        yaw: 0.0,
        yaw_rate: 0.0,
        type_mask: PositionTargetTypemask::from_bits_truncate(VELOCITY_ONLY_TYPE_MASK),
        target_system,
        target_component,
        coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
    })
}

/// The ground station's 1 Hz heartbeat.
pub fn gcs_heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_GCS,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

/// How a command ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommandOutcome {
    /// COMMAND_ACK with a result (ACCEPTED or a refusal).
    Acked(MavResult),
    /// No COMMAND_ACK before the deadline.
    TimedOut,
}

/// A finished command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandResult {
    /// The vehicle.
    pub system_id: u8,
    /// The command.
    pub command: MavCmd,
    /// Its outcome.
    pub outcome: CommandOutcome,
}

#[derive(Debug, Clone, Copy)]
struct Pending {
    system_id: u8,
    command: MavCmd,
    deadline: f64,
}

/// Commands in flight, matched to COMMAND_ACKs by (system, command).
#[derive(Debug, Clone, Default)]
pub struct PendingCommands {
    pending: Vec<Pending>,
}

impl PendingCommands {
    /// Remember a command sent at `now` (s) that must be acknowledged within `timeout` (s).
    /// A second identical command replaces the first (its ACK answers both).
    pub fn start(&mut self, system_id: u8, command: MavCmd, now: f64, timeout: f64) {
        self.pending
            .retain(|p| !(p.system_id == system_id && p.command == command));
        self.pending.push(Pending {
            system_id,
            command,
            deadline: now + timeout,
        });
    }

    /// Match an ACK from `system_id` for the requester `(own_system, own_component)`; None if
    /// nothing was waiting for it, or if its target fields name another requester (PX4 and
    /// ArduPilot fill them: on a link shared with the onboard daemon, the daemon's mode change
    /// is not ours). Zero target fields (an autopilot without the MAVLink 2 extension) match.
    pub fn on_ack(
        &mut self,
        system_id: u8,
        ack: &COMMAND_ACK_DATA,
        own: (u8, u8),
    ) -> Option<CommandResult> {
        if ack.result == MavResult::MAV_RESULT_IN_PROGRESS {
            return None;
        }
        let addressed = (ack.target_system, ack.target_component);
        if addressed != (0, 0) && addressed != own {
            return None;
        }
        let index = self
            .pending
            .iter()
            .position(|p| p.system_id == system_id && p.command == ack.command)?;
        let p = self.pending.swap_remove(index);
        Some(CommandResult {
            system_id,
            command: p.command,
            outcome: CommandOutcome::Acked(ack.result),
        })
    }

    /// Commands whose deadline has passed at `now`, removed.
    pub fn expire(&mut self, now: f64) -> Vec<CommandResult> {
        let mut out = Vec::new();
        self.pending.retain(|p| {
            if now > p.deadline {
                out.push(CommandResult {
                    system_id: p.system_id,
                    command: p.command,
                    outcome: CommandOutcome::TimedOut,
                });
                false
            } else {
                true
            }
        });
        out
    }

    /// Whether a command is still waiting.
    pub fn is_pending(&self, system_id: u8, command: MavCmd) -> bool {
        self.pending
            .iter()
            .any(|p| p.system_id == system_id && p.command == command)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn px4_and_ardupilot_mode_numbers() {
        assert_eq!(FlightMode::PX4_OFFBOARD.custom_mode(), 6 << 16);
        assert_eq!(FlightMode::ARDUPILOT_GUIDED.custom_mode(), 4);
        let MavMessage::COMMAND_LONG(c) = set_mode(1, 1, FlightMode::PX4_OFFBOARD) else {
            unreachable!()
        };
        assert_eq!(
            (c.param1, c.param2, c.command),
            (1.0, 6.0, MavCmd::MAV_CMD_DO_SET_MODE)
        );
        assert_eq!(
            FlightMode::from_heartbeat(MavAutopilot::MAV_AUTOPILOT_PX4, 6 << 16),
            FlightMode::PX4_OFFBOARD
        );
    }

    #[test]
    fn land_is_a_command_long_nav_land_for_the_autopilot() {
        let MavMessage::COMMAND_LONG(c) = land(3, 1) else {
            unreachable!()
        };
        assert_eq!(
            (c.command, c.target_system, c.target_component),
            (MavCmd::MAV_CMD_NAV_LAND, 3, 1)
        );
        assert!(c.param5.is_nan() && c.param6.is_nan(), "here, not at 0, 0");
    }

    #[test]
    fn setpoint_is_velocity_only_local_ned() {
        let MavMessage::SET_POSITION_TARGET_LOCAL_NED(s) =
            velocity_setpoint_ned(2, 1, 5, [1.0, -2.0, 0.5])
        else {
            unreachable!()
        };
        assert_eq!(s.type_mask.bits(), VELOCITY_ONLY_TYPE_MASK);
        assert_eq!(s.coordinate_frame, MavFrame::MAV_FRAME_LOCAL_NED);
        assert_eq!([s.vx, s.vy, s.vz], [1.0, -2.0, 0.5]);
    }

    #[test]
    fn acks_match_and_deadlines_expire() {
        let mut p = PendingCommands::default();
        p.start(3, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 1.0);
        p.start(4, MavCmd::MAV_CMD_DO_SET_MODE, 0.0, 1.0);
        let ack = COMMAND_ACK_DATA {
            command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            result: MavResult::MAV_RESULT_ACCEPTED,
            ..Default::default()
        };
        let us = (255, 190);
        assert_eq!(p.on_ack(4, &ack, us), None); // wrong system
        // Addressed to the drone's companion computer: its ACK, not ours.
        let theirs = COMMAND_ACK_DATA {
            target_system: 3,
            target_component: 191,
            ..ack.clone()
        };
        assert_eq!(p.on_ack(3, &theirs, us), None);
        assert!(p.is_pending(3, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM));
        assert_eq!(
            p.on_ack(3, &ack, us).map(|r| r.outcome),
            Some(CommandOutcome::Acked(MavResult::MAV_RESULT_ACCEPTED))
        );
        assert!(p.expire(0.5).is_empty());
        let expired = p.expire(1.5);
        assert_eq!(expired.len(), 1);
        assert_eq!(expired[0].outcome, CommandOutcome::TimedOut);
        assert!(!p.is_pending(4, MavCmd::MAV_CMD_DO_SET_MODE));
    }
}
