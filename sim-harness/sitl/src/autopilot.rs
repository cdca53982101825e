//! A mock autopilot as a pure state machine: messages and time in, replies, telemetry and a
//! velocity command out. No socket, no clock.
//!
//! Frame: MAVLink LOCAL_NED (x north, y east, z down), metres and m/s; convert to the
//! simulator frame only with `skyherd_onboard::frame`.
//!
//! Rules modelled (the PX4 and ArduPilot behaviour `ARCHITECTURE.md` lists):
//! * PX4: OFFBOARD (custom_mode 6 << 16) is accepted only after velocity setpoints have
//!   streamed at > 2 Hz for 1 s; in OFFBOARD, setpoints lost for > 1 s trigger the failsafe:
//!   the mode drops to AUTO.LOITER (hold) and the vehicle stops.
//! * ArduPilot: GUIDED (4) is accepted at any time; a velocity setpoint older than 3 s is
//!   dropped and the vehicle stops (still GUIDED).
//! * Both: `MAV_CMD_NAV_LAND` (COMMAND_LONG) while armed switches to the LAND mode (PX4
//!   AUTO.LAND, ArduPilot LAND): the vehicle descends where it is at [`LAND_SPEED`], ignores
//!   velocity setpoints, and disarms itself on touchdown (height [`TOUCHDOWN_M`] or less above
//!   the floor, NED z = 0, where the simulator's world stops a descent). Disarmed, it is
//!   DENIED.
//! * Setpoints must be SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED with type_mask
//!   0x0DC7 (velocity only); anything else is rejected and counted by reason.

use mavlink::MavHeader;
use mavlink::dialects::common::{
    COMMAND_ACK_DATA, COMMAND_LONG_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA, MavCmd, MavFrame,
    MavMessage, MavModeFlag, MavResult, MavState, MavSysStatusSensor, MavType,
    SET_POSITION_TARGET_LOCAL_NED_DATA, SYS_STATUS_DATA,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use skyherd_link::Flavour;
use skyherd_link::{DAEMON_COMPONENT_ID, FlightMode, VELOCITY_ONLY_TYPE_MASK};
use skyherd_onboard::frame::{ned_to_sim, sim_to_ned};
use skyherd_sim::dynamics::{DynamicsLimits, Multicopter, Wind, WindConfig};

/// Configuration of one mock autopilot. Units: seconds, metres, m/s, percent.
#[derive(Debug, Clone, PartialEq)]
pub struct AutopilotConfig {
    /// MAVLink system id of this vehicle.
    pub system_id: u8,
    /// Autopilot component id (1 = MAV_COMP_ID_AUTOPILOT1).
    pub component_id: u8,
    /// PX4 (default) or ArduPilot behaviour.
    pub flavour: Flavour,
    /// LOCAL_POSITION_NED rate (Hz), >= 10.
    pub position_rate_hz: f64,
    /// HEARTBEAT and SYS_STATUS period (s).
    pub status_period: f64,
    /// Speed limit applied to setpoints (m/s).
    pub max_speed: f64,
    /// Battery drain while armed and hovering (% per s).
    pub hover_drain_pct_per_s: f64,
    /// Extra drain per m/s of speed (% per s per m/s).
    pub speed_drain_pct_per_s: f64,
    /// How the vehicle follows its setpoint: `None` flies it at once (the first-order model
    /// every earlier number was measured with); `Some` through the multicopter model of
    /// `skyherd_sim::dynamics`, in `wind`.
    pub dynamics: Option<Motion>,
}

/// The vehicle's motion model and its air.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// Acceleration, jerk and speed limits, lag.
    pub limits: DynamicsLimits,
    /// The wind it flies in.
    pub wind: WindConfig,
    /// Seed of the wind's gusts (one stream per vehicle).
    pub wind_seed: u64,
}

/// Sub-step of the motion model, s: the lockstep tick (0.1 s) is too coarse for a 0.3 s lag.
const MOTION_STEP_S: f64 = 0.01;

impl AutopilotConfig {
    /// A PX4 quadrotor with system id `system_id` and the defaults below.
    pub fn px4(system_id: u8) -> Self {
        Self {
            system_id,
            component_id: 1,
            flavour: Flavour::Px4,
            position_rate_hz: 20.0,
            status_period: 1.0,
            max_speed: 5.0,
            hover_drain_pct_per_s: 0.05,
            speed_drain_pct_per_s: 0.01,
            dynamics: None,
        }
    }

    /// The same, as ArduPilot.
    pub fn ardupilot(system_id: u8) -> Self {
        Self {
            flavour: Flavour::ArduPilot,
            ..Self::px4(system_id)
        }
    }
}

/// PX4 accepts OFFBOARD only after setpoints streamed this long (s)...
pub const PX4_STREAM_BEFORE_OFFBOARD: f64 = 1.0;
/// ...with no gap longer than this (s): i.e. faster than 2 Hz.
pub const PX4_MAX_STREAM_GAP: f64 = 0.5;
/// PX4 offboard loss failsafe (s).
pub const PX4_SETPOINT_LOSS_TIMEOUT: f64 = 1.0;
/// ArduPilot GUIDED velocity command timeout (s).
pub const ARDUPILOT_VELOCITY_TIMEOUT: f64 = 3.0;
/// Descent rate in the LAND mode (m/s): PX4's `MPC_LAND_SPEED` default, used for both
/// flavours (ArduCopter's `LAND_SPEED` is 0.5 m/s near the ground, 0.7 m/s would not change
/// any conclusion a room-height landing draws).
pub const LAND_SPEED: f64 = 0.7;
/// Height above the floor (m) at which a landing vehicle counts as on the ground and disarms.
pub const TOUCHDOWN_M: f64 = 0.01;

/// Setpoints and commands refused, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Rejections {
    /// Setpoint not in MAV_FRAME_LOCAL_NED.
    pub wrong_frame: u64,
    /// Setpoint type_mask other than 0x0DC7.
    pub wrong_type_mask: u64,
    /// Setpoint velocity NaN or infinite.
    pub non_finite: u64,
    /// Setpoints and commands addressed to another system.
    pub not_for_us: u64,
    /// Setpoints received while not in OFFBOARD/GUIDED (PX4 still counts them as stream).
    pub outside_external_mode: u64,
    /// Commands answered with a refusal (DENIED, TEMPORARILY_REJECTED, UNSUPPORTED).
    pub commands_refused: u64,
}

/// What [`MockAutopilot::tick`] says the vehicle should do, and what to send.
#[derive(Debug, Clone, PartialEq)]
pub struct Tick {
    /// Velocity the vehicle flies now (m/s, NED); zero when holding.
    pub velocity_ned: [f64; 3],
    /// Telemetry due now (HEARTBEAT, SYS_STATUS, LOCAL_POSITION_NED).
    pub telemetry: Vec<MavMessage>,
}

/// The autopilot; see the [module docs](self).
#[derive(Debug, Clone)]
pub struct MockAutopilot {
    config: AutopilotConfig,
    boot_time: f64,
    armed: bool,
    mode: FlightMode,
    position_ned: [f64; 3],
    velocity_ned: [f64; 3],
    setpoint: [f64; 3],
    last_setpoint: Option<f64>,
    companion_heartbeat_at: Option<f64>,
    stream_start: Option<f64>,
    failsafe_events: u64,
    /// When (s) the last landing began (`MAV_CMD_NAV_LAND` accepted).
    landing_since: Option<f64>,
    /// When (s) a landing ended in touchdown and the vehicle disarmed itself.
    touchdown_at: Option<f64>,
    battery_pct: f64,
    last_tick: Option<f64>,
    next_status: f64,
    next_position: f64,
    rejections: Rejections,
    /// The motion model's state, its wind and the wind's random stream (with `dynamics`).
    motion: Option<(Multicopter, Wind, ChaCha8Rng)>,
}

impl MockAutopilot {
    /// A disarmed autopilot booted at `now` (s), at `position_ned` (m), holding.
    pub fn new(config: AutopilotConfig, position_ned: [f64; 3], now: f64) -> Self {
        let mode = config.flavour.hold_mode();
        let motion = config.dynamics.map(|m| {
            let mut rng = ChaCha8Rng::seed_from_u64(m.wind_seed);
            let wind = Wind::new(&m.wind, &mut rng);
            (
                Multicopter::hovering_at(ned_to_sim(position_ned)),
                wind,
                rng,
            )
        });
        Self {
            config,
            boot_time: now,
            armed: false,
            mode,
            position_ned,
            velocity_ned: [0.0; 3],
            setpoint: [0.0; 3],
            last_setpoint: None,
            companion_heartbeat_at: None,
            stream_start: None,
            failsafe_events: 0,
            landing_since: None,
            touchdown_at: None,
            battery_pct: 100.0,
            last_tick: None,
            next_status: now,
            next_position: now,
            rejections: Rejections::default(),
            motion,
        }
    }

    /// When (s) the last HEARTBEAT arrived from this vehicle's companion computer (its own
    /// system id, component [`DAEMON_COMPONENT_ID`]). In lockstep the onboard daemon
    /// ends its answer to every position with one (after any setpoint and command, on the same
    /// link), so a lockstep loop waits for it.
    pub fn companion_heartbeat_at(&self) -> Option<f64> {
        self.companion_heartbeat_at
    }

    /// Configuration.
    pub fn config(&self) -> &AutopilotConfig {
        &self.config
    }
    /// Armed?
    pub fn armed(&self) -> bool {
        self.armed
    }
    /// Current flight mode.
    pub fn mode(&self) -> FlightMode {
        self.mode
    }
    /// Position (m, NED).
    pub fn position_ned(&self) -> [f64; 3] {
        self.position_ned
    }
    /// Velocity being flown (m/s, NED).
    pub fn velocity_ned(&self) -> [f64; 3] {
        self.velocity_ned
    }
    /// Battery remaining (%).
    pub fn battery_pct(&self) -> f64 {
        self.battery_pct
    }
    /// How often the setpoint-loss failsafe fired.
    pub fn failsafe_events(&self) -> u64 {
        self.failsafe_events
    }
    /// Refusals by reason.
    pub fn rejections(&self) -> &Rejections {
        &self.rejections
    }
    /// Armed and in the LAND mode: descending under its own control.
    pub fn landing(&self) -> bool {
        self.armed && self.mode == self.config.flavour.land_mode()
    }
    /// When (s) the last landing began: the first accepted `MAV_CMD_NAV_LAND` of it.
    pub fn landing_since(&self) -> Option<f64> {
        self.landing_since
    }
    /// When (s) the last landing touched down (the vehicle disarmed itself then).
    pub fn touchdown_at(&self) -> Option<f64> {
        self.touchdown_at
    }

    /// Overwrite the true state (the simulator's world owns the vehicle's motion when it is
    /// stepped; positions m NED, velocity m/s NED).
    pub fn set_state(&mut self, position_ned: [f64; 3], velocity_ned: [f64; 3]) {
        self.position_ned = position_ned;
        self.velocity_ned = velocity_ned;
        if let Some((drone, _, _)) = self.motion.as_mut() {
            drone.position = ned_to_sim(position_ned);
            drone.velocity = ned_to_sim(velocity_ned);
        }
    }

    /// Handle one received message at `now`; returns the replies (COMMAND_ACKs).
    pub fn handle(
        &mut self,
        header: &MavHeader,
        message: &MavMessage,
        now: f64,
    ) -> Vec<MavMessage> {
        if header.system_id == u32::from(self.config.system_id)
            && header.component_id == DAEMON_COMPONENT_ID
            && matches!(message, MavMessage::HEARTBEAT(_))
        {
            self.companion_heartbeat_at = Some(now);
        }
        match message {
            MavMessage::COMMAND_LONG(c) => self.on_command(c, now).into_iter().collect(),
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(s) => {
                self.on_setpoint(s, now);
                Vec::new()
            }
            _ => Vec::new(),
        }
    }

    fn on_setpoint(&mut self, s: &SET_POSITION_TARGET_LOCAL_NED_DATA, now: f64) {
        if s.target_system != self.config.system_id {
            self.rejections.not_for_us += 1;
            return;
        }
        if s.coordinate_frame != MavFrame::MAV_FRAME_LOCAL_NED {
            self.rejections.wrong_frame += 1;
            return;
        }
        if s.type_mask.bits() != VELOCITY_ONLY_TYPE_MASK {
            self.rejections.wrong_type_mask += 1;
            return;
        }
        let v = [f64::from(s.vx), f64::from(s.vy), f64::from(s.vz)];
        if v.iter().any(|c| !c.is_finite()) {
            self.rejections.non_finite += 1;
            return;
        }
        let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let scale = if speed > self.config.max_speed {
            self.config.max_speed / speed
        } else {
            1.0
        };
        self.setpoint = [v[0] * scale, v[1] * scale, v[2] * scale];
        // A gap longer than PX4_MAX_STREAM_GAP restarts the stream.
        match self.last_setpoint {
            Some(last) if now - last <= PX4_MAX_STREAM_GAP => {}
            _ => self.stream_start = Some(now),
        }
        self.last_setpoint = Some(now);
        if self.mode != self.config.flavour.external_mode() {
            self.rejections.outside_external_mode += 1;
        }
    }

    fn streaming_long_enough(&self, now: f64) -> bool {
        match (self.stream_start, self.last_setpoint) {
            (Some(start), Some(last)) => {
                now - start >= PX4_STREAM_BEFORE_OFFBOARD && now - last <= PX4_MAX_STREAM_GAP
            }
            _ => false,
        }
    }

    fn on_command(&mut self, c: &COMMAND_LONG_DATA, now: f64) -> Option<MavMessage> {
        // Broadcast (0) or addressed to us; anything else is another vehicle's.
        if c.target_system != self.config.system_id && c.target_system != 0 {
            self.rejections.not_for_us += 1;
            return None;
        }
        let result = match c.command {
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => {
                if c.param1 == 1.0 {
                    self.armed = true;
                    MavResult::MAV_RESULT_ACCEPTED
                } else if c.param1 == 0.0 {
                    self.armed = false;
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_DO_SET_MODE => self.on_set_mode(c, now),
            // Land where it is; a vehicle on the ground (disarmed) has nothing to land.
            MavCmd::MAV_CMD_NAV_LAND if self.armed => {
                if !self.landing() {
                    self.landing_since = Some(now);
                    self.touchdown_at = None;
                }
                self.mode = self.config.flavour.land_mode();
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_NAV_LAND => MavResult::MAV_RESULT_DENIED,
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        };
        if result != MavResult::MAV_RESULT_ACCEPTED {
            self.rejections.commands_refused += 1;
        }
        Some(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command: c.command,
            result,
        }))
    }

    fn on_set_mode(&mut self, c: &COMMAND_LONG_DATA, now: f64) -> MavResult {
        if c.param1 as u32 & MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits() as u32 == 0 {
            return MavResult::MAV_RESULT_DENIED;
        }
        if !(c.param2.is_finite() && c.param2 >= 0.0 && c.param3.is_finite() && c.param3 >= 0.0) {
            return MavResult::MAV_RESULT_DENIED;
        }
        let requested = match self.config.flavour {
            Flavour::Px4 => {
                let (main, sub) = (c.param2 as u32, c.param3 as u32);
                // PX4 main modes 1 (MANUAL) ..= 8 (STABILIZED).
                if !(1..=8).contains(&main) || sub > 10 {
                    return MavResult::MAV_RESULT_DENIED;
                }
                FlightMode::Px4 {
                    main: main as u8,
                    sub: sub as u8,
                }
            }
            Flavour::ArduPilot => {
                let mode = c.param2 as u32;
                if mode > 30 {
                    return MavResult::MAV_RESULT_DENIED;
                }
                FlightMode::ArduPilot(mode)
            }
        };
        if self.config.flavour == Flavour::Px4
            && requested == FlightMode::PX4_OFFBOARD
            && !self.streaming_long_enough(now)
        {
            // PX4 refuses OFFBOARD without a live setpoint stream.
            return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
        }
        self.mode = requested;
        MavResult::MAV_RESULT_ACCEPTED
    }

    /// Advance to `now`: apply failsafes, integrate the vehicle's own kinematics (first
    /// order: it flies the commanded velocity), drain the battery, and emit due telemetry.
    /// The same as [`fly`](Self::fly) then [`telemetry`](Self::telemetry).
    pub fn tick(&mut self, now: f64) -> Tick {
        let velocity_ned = self.fly(now);
        Tick {
            velocity_ned,
            telemetry: self.telemetry(now),
        }
    }

    /// Advance to `now` without reporting: failsafes, kinematics, battery. Returns the velocity
    /// the vehicle flies (m/s, NED; zero when holding). A lockstep simulator calls this, moves
    /// the world, feeds the true state back with [`set_state`](Self::set_state) and only then
    /// asks for [`telemetry`](Self::telemetry), so the reported position is the one after the
    /// move, as a real autopilot reports its latest estimate.
    pub fn fly(&mut self, now: f64) -> [f64; 3] {
        let external = self.mode == self.config.flavour.external_mode();
        let since_setpoint = self.last_setpoint.map_or(f64::INFINITY, |t| now - t);
        if external
            && self.config.flavour == Flavour::Px4
            && since_setpoint > PX4_SETPOINT_LOSS_TIMEOUT
        {
            self.mode = self.config.flavour.hold_mode();
            self.failsafe_events += 1;
        }
        // Touchdown: the landing is over, the vehicle disarms itself (PX4's land detector).
        if self.landing() && self.position_ned[2] >= -TOUCHDOWN_M {
            self.armed = false;
            self.touchdown_at = Some(now);
        }
        let fly = self.armed
            && self.mode == self.config.flavour.external_mode()
            && since_setpoint <= ARDUPILOT_VELOCITY_TIMEOUT;
        let command = if self.landing() {
            // Straight down (NED z positive), whatever the setpoints say.
            [0.0, 0.0, LAND_SPEED]
        } else if fly {
            self.setpoint
        } else {
            [0.0; 3]
        };
        let dt = self.last_tick.map_or(0.0, |last| (now - last).max(0.0));
        // What the vehicle flies: the command at once, or where the motion model has got to.
        let flown = match (self.motion.as_mut(), self.config.dynamics) {
            (Some((drone, wind, rng)), Some(m)) if dt > 0.0 => {
                let target = ned_to_sim(command);
                let steps = (dt / MOTION_STEP_S).ceil().max(1.0) as usize;
                let h = dt / steps as f64;
                let start = drone.position;
                for _ in 0..steps {
                    let air = wind.step(&m.wind, h, rng);
                    drone.step(target, air, &m.limits, h);
                }
                // The mean velocity over the tick, so that velocity * dt is where it went.
                let p = drone.position;
                sim_to_ned([
                    (p[0] - start[0]) / dt,
                    (p[1] - start[1]) / dt,
                    (p[2] - start[2]) / dt,
                ])
            }
            (Some(_), Some(_)) => [0.0; 3],
            _ => command,
        };
        if dt > 0.0 {
            for (p, v) in self.position_ned.iter_mut().zip(flown) {
                *p += v * dt;
            }
            if self.landing() {
                // The floor (NED z = 0) stops a descent, as the simulator's world does.
                self.position_ned[2] = self.position_ned[2].min(0.0);
            }
            if self.armed {
                let speed = (flown[0].powi(2) + flown[1].powi(2) + flown[2].powi(2)).sqrt();
                let drain =
                    self.config.hover_drain_pct_per_s + self.config.speed_drain_pct_per_s * speed;
                self.battery_pct = (self.battery_pct - drain * dt).max(0.0);
            }
        }
        self.velocity_ned = flown;
        self.last_tick = Some(now);
        flown
    }

    /// Restart the telemetry schedule at `now`: everything falls due then, and the periodic
    /// messages follow from there. A lockstep simulator calls this when simulated time starts,
    /// so the heartbeat phase does not depend on how long a wall-clock pre-roll took.
    pub fn restart_telemetry(&mut self, now: f64) {
        self.next_status = now;
        self.next_position = now;
    }

    /// The telemetry due at `now` (HEARTBEAT and SYS_STATUS every status period,
    /// LOCAL_POSITION_NED at the position rate), from the current state.
    pub fn telemetry(&mut self, now: f64) -> Vec<MavMessage> {
        let mut telemetry = Vec::new();
        if now >= self.next_status {
            self.next_status = now + self.config.status_period;
            telemetry.push(self.heartbeat());
            telemetry.push(self.sys_status());
        }
        if now >= self.next_position {
            self.next_position = now + 1.0 / self.config.position_rate_hz;
            telemetry.push(self.local_position(now));
        }
        telemetry
    }

    fn heartbeat(&self) -> MavMessage {
        let mut base_mode = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        if self.armed {
            base_mode |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        if self.mode == self.config.flavour.external_mode() {
            base_mode |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED;
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: self.mode.custom_mode(),
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot: self.config.flavour.mav_autopilot(),
            base_mode,
            system_status: if self.armed {
                MavState::MAV_STATE_ACTIVE
            } else {
                MavState::MAV_STATE_STANDBY
            },
            mavlink_version: 3,
        })
    }

    fn sys_status(&self) -> MavMessage {
        // A 4S pack: 16.8 V full, 14.0 V empty, linear in between.
        let volts = 14.0 + 2.8 * self.battery_pct / 100.0;
        let sensors = MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_GYRO
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_ACCEL;
        MavMessage::SYS_STATUS(SYS_STATUS_DATA {
            onboard_control_sensors_present: sensors,
            onboard_control_sensors_enabled: sensors,
            onboard_control_sensors_health: sensors,
            load: 200,
            voltage_battery: (volts * 1000.0) as u16,
            current_battery: if self.armed { 1500 } else { 50 },
            drop_rate_comm: 0,
            errors_comm: 0,
            errors_count1: 0,
            errors_count2: 0,
            errors_count3: 0,
            errors_count4: 0,
            battery_remaining: self.battery_pct.round() as i8,
        })
    }

    fn local_position(&self, now: f64) -> MavMessage {
        let p = self.position_ned;
        let v = self.velocity_ned;
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: ((now - self.boot_time).max(0.0) * 1000.0) as u32,
            x: p[0] as f32,
            y: p[1] as f32,
            z: p[2] as f32,
            vx: v[0] as f32,
            vy: v[1] as f32,
            vz: v[2] as f32,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{MavFrame, PositionTargetTypemask};
    use skyherd_link::command::{arm_disarm, land, set_mode, velocity_setpoint_ned};

    const H: MavHeader = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 0,
    };

    fn ack(replies: &[MavMessage]) -> MavResult {
        match replies {
            [MavMessage::COMMAND_ACK(a)] => a.result,
            other => panic!("expected one ACK, got {other:?}"),
        }
    }

    #[test]
    fn px4_offboard_needs_a_stream_then_fails_safe_on_loss() {
        let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
        assert_eq!(
            ack(&ap.handle(&H, &arm_disarm(1, 1, true), 0.0)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        let offboard = set_mode(1, 1, FlightMode::PX4_OFFBOARD);
        assert_eq!(
            ack(&ap.handle(&H, &offboard, 0.0)),
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
        );
        // 0.9 s of 10 Hz setpoints: not yet.
        let sp = velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]);
        let mut t = 0.0;
        while t < 0.85 {
            ap.handle(&H, &sp, t);
            ap.tick(t);
            t += 0.1;
        }
        assert_eq!(
            ack(&ap.handle(&H, &offboard, t)),
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
        );
        while t < 1.25 {
            ap.handle(&H, &sp, t);
            ap.tick(t);
            t += 0.1;
        }
        assert_eq!(
            ack(&ap.handle(&H, &offboard, t)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        let start = ap.position_ned()[0];
        for _ in 0..10 {
            ap.handle(&H, &sp, t);
            ap.tick(t);
            t += 0.1;
        }
        assert!(
            (ap.position_ned()[0] - start - 0.9).abs() < 0.15,
            "{:?}",
            ap.position_ned()
        );
        // Stop streaming: still OFFBOARD 0.95 s after the last setpoint, hold after 1 s.
        let last_setpoint = t - 0.1;
        ap.tick(last_setpoint + 0.95);
        assert_eq!(ap.mode(), FlightMode::PX4_OFFBOARD);
        ap.tick(last_setpoint + 1.05);
        assert_eq!(ap.mode(), FlightMode::PX4_HOLD);
        assert_eq!(ap.failsafe_events(), 1);
        assert_eq!(ap.tick(last_setpoint + 1.15).velocity_ned, [0.0; 3]);
    }

    #[test]
    fn ardupilot_guided_and_velocity_timeout() {
        let mut ap = MockAutopilot::new(AutopilotConfig::ardupilot(2), [0.0; 3], 0.0);
        ap.handle(&H, &arm_disarm(2, 1, true), 0.0);
        let guided = set_mode(2, 1, FlightMode::ARDUPILOT_GUIDED);
        assert_eq!(
            ack(&ap.handle(&H, &guided, 0.0)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        ap.handle(&H, &velocity_setpoint_ned(2, 1, 0, [0.0, 2.0, 0.0]), 0.0);
        assert_eq!(ap.tick(2.9).velocity_ned, [0.0, 2.0, 0.0]);
        assert_eq!(ap.tick(3.1).velocity_ned, [0.0; 3]);
        assert_eq!(ap.mode(), FlightMode::ARDUPILOT_GUIDED);
    }

    /// A PX4 autopilot armed and flying OFFBOARD at `height` m (NED z = -height), at t = 2 s.
    fn offboard_at(height: f64) -> (MockAutopilot, f64) {
        let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0, 0.0, -height], 0.0);
        ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
        let hold = velocity_setpoint_ned(1, 1, 0, [0.0; 3]);
        let mut t = 0.0;
        while t < 1.25 {
            ap.handle(&H, &hold, t);
            ap.tick(t);
            t += 0.1;
        }
        assert_eq!(
            ack(&ap.handle(&H, &set_mode(1, 1, FlightMode::PX4_OFFBOARD), t)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        (ap, t)
    }

    fn heartbeat_mode(ap: &mut MockAutopilot, now: f64) -> Option<(u32, bool)> {
        ap.restart_telemetry(now);
        ap.telemetry(now).into_iter().find_map(|m| match m {
            MavMessage::HEARTBEAT(hb) => Some((
                hb.custom_mode,
                hb.base_mode
                    .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED),
            )),
            _ => None,
        })
    }

    #[test]
    fn land_when_armed_descends_at_the_land_speed_and_disarms_at_touchdown() {
        let (mut ap, mut t) = offboard_at(2.0);
        assert_eq!(
            ack(&ap.handle(&H, &land(1, 1), t)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(ap.mode(), FlightMode::PX4_LAND);
        assert_eq!(
            heartbeat_mode(&mut ap, t),
            Some(((4 << 16) | (6 << 24), true)),
            "AUTO.LAND, armed"
        );
        let start = t;
        while ap.armed() && t < start + 10.0 {
            t += 0.1;
            let v = ap.tick(t).velocity_ned;
            if ap.armed() {
                assert_eq!(v, [0.0, 0.0, LAND_SPEED]);
            }
        }
        let touchdown = ap.touchdown_at().expect("touched down");
        assert_eq!(ap.landing_since(), Some(start));
        // 2 m at 0.7 m/s: 2.86 s, noticed on the next 0.1 s tick.
        assert!(
            (touchdown - start - 2.0 / LAND_SPEED).abs() <= 0.15,
            "touchdown {:.2} s after the command",
            touchdown - start
        );
        assert!(!ap.armed());
        assert_eq!(ap.position_ned()[2], 0.0, "stopped by the floor");
        assert_eq!(ap.tick(t + 1.0).velocity_ned, [0.0; 3]);
        assert_eq!(heartbeat_mode(&mut ap, t + 1.0).map(|m| m.1), Some(false));
        // ArduPilot reports LAND as mode 9.
        let mut ap = MockAutopilot::new(AutopilotConfig::ardupilot(2), [0.0, 0.0, -1.0], 0.0);
        ap.handle(&H, &arm_disarm(2, 1, true), 0.0);
        assert_eq!(
            ack(&ap.handle(&H, &land(2, 1), 0.0)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(heartbeat_mode(&mut ap, 0.0).map(|m| m.0), Some(9));
    }

    #[test]
    fn land_is_denied_when_disarmed() {
        let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0, 0.0, -2.0], 0.0);
        assert_eq!(
            ack(&ap.handle(&H, &land(1, 1), 0.0)),
            MavResult::MAV_RESULT_DENIED
        );
        assert_eq!(ap.mode(), FlightMode::PX4_HOLD);
        assert_eq!(ap.rejections().commands_refused, 1);
        assert_eq!(ap.touchdown_at(), None);
    }

    #[test]
    fn setpoints_are_ignored_while_landing() {
        let (mut ap, mut t) = offboard_at(3.0);
        ap.handle(&H, &land(1, 1), t);
        ap.tick(t);
        let before = ap.position_ned()[2];
        let up_and_away = velocity_setpoint_ned(1, 1, 0, [2.0, 1.0, -1.0]);
        for _ in 0..10 {
            ap.handle(&H, &up_and_away, t);
            t += 0.1;
            assert_eq!(ap.tick(t).velocity_ned, [0.0, 0.0, LAND_SPEED]);
        }
        let p = ap.position_ned();
        assert_eq!((p[0], p[1]), (0.0, 0.0), "straight down");
        assert!((p[2] - (before + LAND_SPEED)).abs() < 1e-9, "{p:?}");
        assert_eq!(
            ap.mode(),
            FlightMode::PX4_LAND,
            "no switch back, no failsafe"
        );
        assert_eq!(ap.failsafe_events(), 0);
        assert!(ap.rejections().outside_external_mode >= 10);
    }

    #[test]
    fn bad_setpoints_are_counted_and_ignored() {
        let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
        let good = velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]);
        let MavMessage::SET_POSITION_TARGET_LOCAL_NED(base) = good else {
            unreachable!()
        };
        let mut body = base.clone();
        body.coordinate_frame = MavFrame::MAV_FRAME_BODY_FRD;
        let mut mask = base.clone();
        mask.type_mask = PositionTargetTypemask::from_bits_truncate(0x0FF8);
        let mut nan = base.clone();
        nan.vx = f32::NAN;
        let mut other = base;
        other.target_system = 9;
        for s in [body, mask, nan, other] {
            ap.handle(&H, &MavMessage::SET_POSITION_TARGET_LOCAL_NED(s), 0.0);
        }
        let r = ap.rejections();
        assert_eq!(
            (r.wrong_frame, r.wrong_type_mask, r.non_finite, r.not_for_us),
            (1, 1, 1, 1)
        );
        assert!(!ap.streaming_long_enough(2.0));
    }

    #[test]
    fn telemetry_rates_and_battery_drain() {
        let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
        ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
        let (mut positions, mut heartbeats) = (0, 0);
        for k in 0..=100 {
            for m in ap.tick(k as f64 * 0.01 * 10.0).telemetry {
                match m {
                    MavMessage::LOCAL_POSITION_NED(_) => positions += 1,
                    MavMessage::HEARTBEAT(_) => heartbeats += 1,
                    _ => {}
                }
            }
        }
        // 10 s ticked at 10 Hz: every tick carries a position (>= 10 Hz), 1 Hz heartbeats.
        assert!(positions >= 100, "{positions}");
        assert!((10..=11).contains(&heartbeats), "{heartbeats}");
        assert!(ap.battery_pct() < 100.0 && ap.battery_pct() > 98.0);
    }
}
