//! A mock autopilot as a pure state machine: messages and time in, replies, telemetry and a
//! velocity out. No socket, no clock.
//!
//! Frame: MAVLink LOCAL_NED (x north, y east, z down) with its origin at home on the floor,
//! metres and m/s; convert to the simulator frame only with `skyherd_onboard::frame`.
//!
//! One code for both flavours; where PX4 and ArduCopter differ, [`Flavour`] and the
//! flavour's [`Params`] decide. What is modelled (each rule has a test below):
//! * **Ground and air.** A vehicle starts landed on the floor (NED z = 0), disarmed. It leaves
//!   the ground only by taking off: PX4 with `MAV_CMD_NAV_TAKEOFF` (AUTO.TAKEOFF, to
//!   `MIS_TAKEOFF_ALT` or the command's AMSL altitude, then AUTO.LOITER) or in OFFBOARD on an
//!   upward setpoint; ArduCopter only with `MAV_CMD_NAV_TAKEOFF` in GUIDED (its GUIDED
//!   velocity commands do not lift a landed copter). It lands in the LAND mode
//!   (`MAV_CMD_NAV_LAND`), at the end of RTL, or by descending onto the floor; touchdown is
//!   detected at [`TOUCHDOWN_M`].
//! * **Disarming.** Refused in the air (PX4 DENIED, ArduCopter FAILED) unless forced
//!   (param 2 = 21196: the vehicle falls). Automatic: after arming without a takeoff
//!   (`COM_DISARM_PRFLT`, `DISARM_DELAY`), after landing (`COM_DISARM_LAND`, `DISARM_DELAY`;
//!   at once at the end of LAND and RTL).
//! * **External control.** PX4 accepts OFFBOARD only while setpoints stream (the last one
//!   at most 0.5 s old) and falls back to AUTO.LOITER when they stop for `COM_OF_LOSS_T`; ArduCopter accepts
//!   GUIDED at any time and stops (still GUIDED) when a velocity command is older than
//!   `GUID_TIMEOUT`. Setpoints: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED,
//!   LOCAL_OFFSET_NED, BODY_NED or BODY_OFFSET_NED, with any type mask that uses all three
//!   position axes, all three velocity axes or both (velocity as feed-forward), with or
//!   without yaw or yaw rate; acceleration and force setpoints are refused and counted.
//! * **Commands.** COMMAND_LONG and COMMAND_INT alike, for this system (or broadcast, 0) and
//!   this component (or 0): arm/disarm, DO_SET_MODE (and the SET_MODE message), NAV_TAKEOFF,
//!   NAV_LAND, NAV_RETURN_TO_LAUNCH, SET_MESSAGE_INTERVAL, REQUEST_MESSAGE,
//!   REQUEST_AUTOPILOT_CAPABILITIES. Every one is acknowledged, with the requester's system
//!   and component in the ACK's target fields; unknown commands are UNSUPPORTED. Every
//!   refusal and every failsafe also says why in a STATUSTEXT.
//! * **Telemetry.** HEARTBEAT at the status period. PX4 also streams SYS_STATUS,
//!   LOCAL_POSITION_NED, GLOBAL_POSITION_INT, ATTITUDE, EXTENDED_SYS_STATE, BATTERY_STATUS and
//!   HOME_POSITION by default; ArduCopter (default stream rates) streams nothing else until
//!   asked (SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM). AUTOPILOT_VERSION on request.
//! * **Protocols.** Parameters (PARAM_REQUEST_LIST / READ / SET, values that drive the rules
//!   above), missions (zero items; uploads other than an empty one are refused), TIMESYNC.

// Real clients still send the superseded SET_MODE and REQUEST_DATA_STREAM (pymavlink's
// set_mode, MAVProxy) and the body frames; an honest stand-in serves them.
#![allow(deprecated)]

mod params;

pub use params::{Param, ParamError, Params};

use mavlink::MavHeader;
use mavlink::dialects::common::{
    ATTITUDE_DATA, AUTOPILOT_VERSION_DATA, BATTERY_STATUS_DATA, COMMAND_ACK_DATA, COMMAND_INT_DATA,
    COMMAND_LONG_DATA, EXTENDED_SYS_STATE_DATA, GLOBAL_POSITION_INT_DATA, HEARTBEAT_DATA,
    HOME_POSITION_DATA, LOCAL_POSITION_NED_DATA, MISSION_ACK_DATA, MISSION_COUNT_DATA,
    MavBatteryChargeState, MavBatteryFunction, MavBatteryType, MavCmd, MavDataStream, MavFrame,
    MavLandedState, MavMessage, MavMissionResult, MavModeFlag, MavProtocolCapability, MavResult,
    MavSeverity, MavState, MavSysStatusSensor, MavType, MavVtolState, PARAM_VALUE_DATA,
    SET_POSITION_TARGET_LOCAL_NED_DATA, STATUSTEXT_DATA, SYS_STATUS_DATA, TIMESYNC_DATA,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use skyherd_link::Flavour;
use skyherd_link::{DAEMON_COMPONENT_ID, FlightMode};
use skyherd_onboard::frame::{ned_to_sim, sim_to_ned};
use skyherd_sim::dynamics::{DynamicsLimits, Multicopter, Wind, WindConfig};

/// Where home is on the Earth: what GLOBAL_POSITION_INT and HOME_POSITION report. Degrees and
/// metres above mean sea level.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Home {
    /// Latitude, degrees north.
    pub latitude_deg: f64,
    /// Longitude, degrees east.
    pub longitude_deg: f64,
    /// Altitude of the floor, m AMSL.
    pub altitude_amsl_m: f64,
}

impl Home {
    /// ArduPilot's SITL default (CMAC, Canberra), so a mock and a real SITL report alike.
    pub const CMAC: Home = Home {
        latitude_deg: -35.363261,
        longitude_deg: 149.165230,
        altitude_amsl_m: 584.0,
    };

    /// Latitude, longitude (degrees) of a point `north`, `east` metres from home (flat Earth,
    /// exact to millimetres over a field).
    pub fn offset(&self, north: f64, east: f64) -> (f64, f64) {
        const EARTH_RADIUS_M: f64 = 6_378_137.0;
        let latitude = self.latitude_deg + (north / EARTH_RADIUS_M).to_degrees();
        let longitude = self.longitude_deg
            + (east / (EARTH_RADIUS_M * self.latitude_deg.to_radians().cos())).to_degrees();
        (latitude, longitude)
    }
}

/// Configuration of one mock autopilot. Units: seconds, metres, m/s, percent.
#[derive(Debug, Clone, PartialEq)]
pub struct AutopilotConfig {
    /// MAVLink system id of this vehicle.
    pub system_id: u8,
    /// Autopilot component id (1 = MAV_COMP_ID_AUTOPILOT1).
    pub component_id: u8,
    /// PX4 (default) or ArduPilot behaviour.
    pub flavour: Flavour,
    /// LOCAL_POSITION_NED rate of PX4's default stream and of an ArduPilot stream request
    /// that names no rate (Hz), >= 10.
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
    /// Where home is (GLOBAL_POSITION_INT, HOME_POSITION, the AMSL altitude of PX4's takeoff).
    pub home: Home,
}

/// The vehicle's motion model and its air.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// Acceleration, jerk and speed limits, lag.
    pub limits: DynamicsLimits,
    /// The wind it flies in.
    pub wind: WindConfig,
    /// Seed of the wind's gusts (one stream per vehicle); the estimate error draws from a
    /// stream of its own derived from it, so the gusts do not depend on it.
    pub wind_seed: u64,
    /// Stationary standard deviation of the reported position's error on each horizontal
    /// axis, m (0: exact).
    pub estimate_std_m: f64,
    /// The same on the vertical axis, m (an EKF's height leans on the barometer, not GNSS).
    pub estimate_vertical_std_m: f64,
    /// The error's correlation time, s.
    pub estimate_time_s: f64,
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
            home: Home::CMAC,
        }
    }

    /// The same, as ArduPilot.
    pub fn ardupilot(system_id: u8) -> Self {
        Self {
            flavour: Flavour::ArduPilot,
            ..Self::px4(system_id)
        }
    }

    /// The same, for `flavour`.
    pub fn for_flavour(flavour: Flavour, system_id: u8) -> Self {
        match flavour {
            Flavour::Px4 => Self::px4(system_id),
            Flavour::ArduPilot => Self::ardupilot(system_id),
        }
    }
}

/// PX4 accepts OFFBOARD only while setpoints stream: the last one at most this old (s), i.e.
/// faster than 2 Hz. (One fresh setpoint is enough: MAVSDK sends one, then asks.)
pub const PX4_MAX_STREAM_GAP: f64 = 0.5;
/// Height above the floor (m) at which a descending vehicle counts as on the ground.
pub const TOUCHDOWN_M: f64 = 0.01;
/// `param2` of MAV_CMD_COMPONENT_ARM_DISARM that forces a disarm in the air.
pub const FORCE_DISARM_MAGIC: f32 = 21196.0;
/// How fast a vehicle disarmed in the air falls (m/s): no model of a tumbling airframe,
/// only that it does not stay up.
const FALL_SPEED: f64 = 5.0;
/// Upward setpoint speed (m/s) at which PX4 OFFBOARD lifts off.
const LIFTOFF_SPEED: f64 = 0.1;
/// A takeoff ends this close (m) below its altitude.
const TAKEOFF_TOLERANCE_M: f64 = 0.02;
/// Gain of a position setpoint (1/s): the velocity towards it per metre of error.
const POSITION_GAIN: f64 = 1.0;

// Message ids of the telemetry streams.
const ID_SYS_STATUS: u32 = 1;
const ID_ATTITUDE: u32 = 30;
const ID_LOCAL_POSITION_NED: u32 = 32;
const ID_GLOBAL_POSITION_INT: u32 = 33;
const ID_BATTERY_STATUS: u32 = 147;
const ID_AUTOPILOT_VERSION: u32 = 148;
const ID_HOME_POSITION: u32 = 242;
const ID_EXTENDED_SYS_STATE: u32 = 245;
/// Every message a stream or a request can name.
const STREAMABLE: [u32; 7] = [
    ID_SYS_STATUS,
    ID_ATTITUDE,
    ID_LOCAL_POSITION_NED,
    ID_GLOBAL_POSITION_INT,
    ID_BATTERY_STATUS,
    ID_HOME_POSITION,
    ID_EXTENDED_SYS_STATE,
];

/// Setpoints and commands refused, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Rejections {
    /// Setpoint in a frame other than the four local ones.
    pub wrong_frame: u64,
    /// Setpoint type_mask that uses neither all position nor all velocity axes, or asks for
    /// acceleration or force.
    pub wrong_type_mask: u64,
    /// Setpoint value NaN or infinite.
    pub non_finite: u64,
    /// Setpoints and commands addressed to another system or component.
    pub not_for_us: u64,
    /// Setpoints received while not in OFFBOARD/GUIDED (PX4 still counts them as stream).
    pub outside_external_mode: u64,
    /// Commands answered with a refusal (DENIED, FAILED, TEMPORARILY_REJECTED, UNSUPPORTED).
    pub commands_refused: u64,
    /// Parameter reads and writes refused (unknown name or index, value out of range).
    pub params_refused: u64,
}

/// What [`MockAutopilot::tick`] says the vehicle should do, and what to send.
#[derive(Debug, Clone, PartialEq)]
pub struct Tick {
    /// Velocity the vehicle flies now (m/s, NED); zero when holding.
    pub velocity_ned: [f64; 3],
    /// Telemetry due now.
    pub telemetry: Vec<MavMessage>,
}

/// What the vehicle is doing, from its mode and state.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Behaviour {
    /// Following external setpoints (OFFBOARD, GUIDED).
    External,
    /// Climbing to this height above home (m).
    TakingOff(f64),
    /// Descending where it is.
    Landing,
    /// Flying home, then landing.
    Returning,
    /// Holding where it is.
    Holding,
}

/// An external setpoint, NED.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Target {
    /// Fly this velocity (m/s).
    Velocity([f64; 3]),
    /// Fly to this position (m), with an optional feed-forward velocity (m/s).
    Position([f64; 3], [f64; 3]),
}

/// One telemetry stream: its interval (s; `None` off) and when it is next due.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Stream {
    id: u32,
    interval: Option<f64>,
    next: f64,
}

/// A COMMAND_LONG or COMMAND_INT, as one.
#[derive(Debug, Clone, Copy)]
struct Command {
    command: MavCmd,
    params: [f32; 7],
    target_system: u8,
    target_component: u8,
}

impl From<&COMMAND_LONG_DATA> for Command {
    fn from(c: &COMMAND_LONG_DATA) -> Self {
        Self {
            command: c.command,
            params: [
                c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7,
            ],
            target_system: c.target_system,
            target_component: c.target_component,
        }
    }
}

impl From<&COMMAND_INT_DATA> for Command {
    fn from(c: &COMMAND_INT_DATA) -> Self {
        // x and y are integers (degE7 in global frames); none of the commands served here
        // reads them, so they pass as numbers.
        Self {
            command: c.command,
            params: [
                c.param1, c.param2, c.param3, c.param4, c.x as f32, c.y as f32, c.z,
            ],
            target_system: c.target_system,
            target_component: c.target_component,
        }
    }
}

/// The autopilot; see the [module docs](self).
#[derive(Debug, Clone)]
pub struct MockAutopilot {
    config: AutopilotConfig,
    params: Params,
    boot_time: f64,
    armed: bool,
    /// When (s) it was last armed.
    armed_at: f64,
    /// Whether it has left the ground since it was armed.
    flew_since_arming: bool,
    /// On the ground, and since when (s).
    landed_since: Option<f64>,
    mode: FlightMode,
    /// Height (m above home) of the takeoff in progress.
    takeoff_height: Option<f64>,
    position_ned: [f64; 3],
    velocity_ned: [f64; 3],
    /// Heading, radians from north.
    heading: f64,
    /// Yaw rate commanded by the last setpoint, rad/s.
    yaw_rate: f64,
    target: Target,
    last_setpoint: Option<f64>,
    companion_heartbeat_at: Option<f64>,
    failsafe_events: u64,
    /// When (s) the last landing began (`MAV_CMD_NAV_LAND` accepted).
    landing_since: Option<f64>,
    /// When (s) a landing ended in touchdown and the vehicle disarmed itself.
    touchdown_at: Option<f64>,
    battery_pct: f64,
    last_tick: Option<f64>,
    next_status: f64,
    streams: Vec<Stream>,
    /// Acceleration over the last tick (m/s², NED), for ATTITUDE.
    acceleration: [f64; 3],
    /// STATUSTEXTs and other unprompted messages waiting for the next telemetry.
    outbox: Vec<MavMessage>,
    rejections: Rejections,
    /// The motion model's state, its wind and the wind's random stream (with `dynamics`).
    motion: Option<MotionState>,
    /// The position estimate's error (m, NED) as the wind model's Gauss-Markov process, that
    /// process's settings and its random stream (with `dynamics`).
    estimate: Option<EstimateError>,
    /// Between [`start_episode`](Self::start_episode) and [`release`](Self::release): the
    /// air is calm and the estimate exact, and neither random stream draws.
    random_held: bool,
}

/// A standard deviation as given, or 0 when it is not a usable one (negative, not finite).
fn usable_std(std: f64) -> f64 {
    if std.is_finite() { std.max(0.0) } else { 0.0 }
}

/// The motion model's vehicle, its wind and the wind's random stream.
type MotionState = (Multicopter, Wind, ChaCha8Rng);
/// The position estimate's error, its process's settings and its random stream.
type EstimateError = (Wind, WindConfig, ChaCha8Rng);

impl MockAutopilot {
    /// A disarmed autopilot booted at `now` (s), at `position_ned` (m): on the ground when that
    /// is on the floor (z >= -[`TOUCHDOWN_M`]), else falling to it.
    pub fn new(config: AutopilotConfig, position_ned: [f64; 3], now: f64) -> Self {
        let mode = config.flavour.hold_mode();
        let (motion, estimate) = Self::random_processes(&config, position_ned);
        let streams = Self::default_streams(&config, now);
        let on_floor = position_ned[2] >= -TOUCHDOWN_M;
        Self {
            params: Params::defaults(config.flavour),
            config,
            boot_time: now,
            armed: false,
            armed_at: now,
            flew_since_arming: false,
            landed_since: on_floor.then_some(now),
            mode,
            takeoff_height: None,
            position_ned,
            velocity_ned: [0.0; 3],
            heading: 0.0,
            yaw_rate: 0.0,
            target: Target::Velocity([0.0; 3]),
            last_setpoint: None,
            companion_heartbeat_at: None,
            failsafe_events: 0,
            landing_since: None,
            touchdown_at: None,
            battery_pct: 100.0,
            last_tick: None,
            next_status: now,
            streams,
            acceleration: [0.0; 3],
            outbox: Vec::new(),
            rejections: Rejections::default(),
            random_held: false,
            motion,
            estimate,
        }
    }

    /// The motion model (at `position_ned`, at rest) and the position estimate's error, each
    /// with its random stream at the start of its seeded sequence (`None` without dynamics).
    fn random_processes(
        config: &AutopilotConfig,
        position_ned: [f64; 3],
    ) -> (Option<MotionState>, Option<EstimateError>) {
        let motion = config.dynamics.as_ref().map(|m| {
            let mut rng = ChaCha8Rng::seed_from_u64(m.wind_seed);
            let wind = Wind::new(&m.wind, &mut rng);
            (
                Multicopter::hovering_at(ned_to_sim(position_ned)),
                wind,
                rng,
            )
        });
        let estimate = config.dynamics.as_ref().map(|m| {
            let mut rng = ChaCha8Rng::seed_from_u64(m.wind_seed ^ 0xE571_3A7E);
            // The same process as the gusts': a stationary start, then a step per tick.
            // A unit process, scaled per axis in `estimated_position`.
            let process = WindConfig {
                mean: [0.0; 3],
                gust_std: if usable_std(m.estimate_std_m) > 0.0
                    || usable_std(m.estimate_vertical_std_m) > 0.0
                {
                    1.0
                } else {
                    0.0
                },
                gust_time: m.estimate_time_s,
            };
            (Wind::new(&process, &mut rng), process, rng)
        });
        (motion, estimate)
    }

    /// An autopilot already flying at `position_ned`: armed, in the air, holding (as after
    /// a takeoff). For tests and for worlds that start their vehicles airborne.
    pub fn new_flying(config: AutopilotConfig, position_ned: [f64; 3], now: f64) -> Self {
        let mut autopilot = Self::new(config, position_ned, now);
        autopilot.armed = true;
        autopilot.flew_since_arming = true;
        autopilot.landed_since = None;
        autopilot
    }

    fn default_streams(config: &AutopilotConfig, now: f64) -> Vec<Stream> {
        let position = 1.0 / config.position_rate_hz;
        STREAMABLE
            .iter()
            .map(|&id| {
                let interval = match (config.flavour, id) {
                    // ArduCopter (default SRn_ rates) sends only its HEARTBEAT to a link that
                    // has not asked for more.
                    (Flavour::ArduPilot, _) => None,
                    (Flavour::Px4, ID_SYS_STATUS) => Some(config.status_period),
                    (Flavour::Px4, ID_LOCAL_POSITION_NED) => Some(position),
                    (Flavour::Px4, ID_GLOBAL_POSITION_INT) => Some(0.2),
                    (Flavour::Px4, ID_ATTITUDE) => Some(0.1),
                    (Flavour::Px4, ID_HOME_POSITION) => Some(2.0),
                    (Flavour::Px4, _) => Some(1.0),
                };
                Stream {
                    id,
                    interval,
                    next: now,
                }
            })
            .collect()
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
    /// Parameters (as set over MAVLink).
    pub fn params(&self) -> &Params {
        &self.params
    }
    /// Armed?
    pub fn armed(&self) -> bool {
        self.armed
    }
    /// On the ground?
    pub fn landed(&self) -> bool {
        self.landed_since.is_some()
    }
    /// Current flight mode.
    pub fn mode(&self) -> FlightMode {
        self.mode
    }
    /// Armed, in the air and in OFFBOARD/GUIDED: flying external setpoints.
    pub fn under_external_control(&self) -> bool {
        self.armed && !self.landed() && self.behaviour() == Behaviour::External
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
    /// How often a failsafe fired (setpoint loss, auto-disarm).
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

    fn behaviour(&self) -> Behaviour {
        let flavour = self.config.flavour;
        if let Some(height) = self.takeoff_height {
            return Behaviour::TakingOff(height);
        }
        if self.mode == flavour.external_mode() {
            Behaviour::External
        } else if self.mode == flavour.land_mode() {
            Behaviour::Landing
        } else if self.mode == flavour.rtl_mode() {
            Behaviour::Returning
        } else {
            Behaviour::Holding
        }
    }

    fn say(&mut self, severity: MavSeverity, text: &str) {
        self.outbox.push(status_text(severity, text));
    }

    /// Handle one received message at `now`; returns the replies (acknowledgements, parameter
    /// values, STATUSTEXTs of refusals).
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
        let mut replies = Vec::new();
        // Messages addressed to a system and component: only ours (or broadcast) are served.
        // (Commands and setpoints check for themselves, counting what is not ours.)
        let addressed = match message {
            MavMessage::SET_MODE(m) => Some((m.target_system, 0)),
            MavMessage::PARAM_REQUEST_LIST(r) => Some((r.target_system, r.target_component)),
            MavMessage::PARAM_REQUEST_READ(r) => Some((r.target_system, r.target_component)),
            MavMessage::PARAM_SET(p) => Some((p.target_system, p.target_component)),
            MavMessage::MISSION_REQUEST_LIST(r) => Some((r.target_system, r.target_component)),
            MavMessage::MISSION_COUNT(c) => Some((c.target_system, c.target_component)),
            MavMessage::MISSION_CLEAR_ALL(c) => Some((c.target_system, c.target_component)),
            MavMessage::REQUEST_DATA_STREAM(r) => Some((r.target_system, r.target_component)),
            _ => None,
        };
        if let Some((system, component)) = addressed
            && !self.for_us(system, component)
        {
            return replies;
        }
        match message {
            MavMessage::COMMAND_LONG(c) => self.on_command(header, &c.into(), now, &mut replies),
            MavMessage::COMMAND_INT(c) => self.on_command(header, &c.into(), now, &mut replies),
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(s) => self.on_setpoint(s, now),
            MavMessage::SET_MODE(m) => {
                // The message form of DO_SET_MODE: PX4 acknowledges it as that command.
                let command = Command {
                    command: MavCmd::MAV_CMD_DO_SET_MODE,
                    params: [
                        f32::from(m.base_mode.bits()),
                        ((m.custom_mode >> 16) & 0xFF) as f32,
                        (m.custom_mode >> 24) as f32,
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                    ],
                    target_system: m.target_system,
                    target_component: 0,
                };
                let command = match self.config.flavour {
                    Flavour::Px4 => command,
                    Flavour::ArduPilot => Command {
                        params: [
                            command.params[0],
                            m.custom_mode as f32,
                            0.0,
                            0.0,
                            0.0,
                            0.0,
                            0.0,
                        ],
                        ..command
                    },
                };
                self.on_command(header, &command, now, &mut replies);
            }
            MavMessage::PARAM_REQUEST_LIST(_) => {
                replies.extend((0..self.params.len()).map(|i| self.param_value(i)));
            }
            MavMessage::PARAM_REQUEST_READ(r) => {
                let index = if r.param_index >= 0 {
                    Some(r.param_index as usize).filter(|&i| i < self.params.len())
                } else {
                    let name = r.param_id.to_str().unwrap_or("");
                    self.params.by_name(name).map(|(i, _)| i)
                };
                match index {
                    Some(i) => replies.push(self.param_value(i)),
                    None => {
                        self.rejections.params_refused += 1;
                        let name = r.param_id.to_str().unwrap_or("?").to_owned();
                        replies.push(status_text(
                            MavSeverity::MAV_SEVERITY_WARNING,
                            &format!("param {name} ({}) unknown", r.param_index),
                        ));
                    }
                }
            }
            MavMessage::PARAM_SET(p) => {
                let name = p.param_id.to_str().unwrap_or("").to_owned();
                match self.params.set(&name, p.param_value) {
                    Ok(i) => replies.push(self.param_value(i)),
                    Err(e) => {
                        self.rejections.params_refused += 1;
                        let why = match e {
                            ParamError::Unknown => format!("param {name} unknown"),
                            ParamError::OutOfRange { min, max } => {
                                format!("param {name} must be {min}..{max}")
                            }
                        };
                        replies.push(status_text(MavSeverity::MAV_SEVERITY_WARNING, &why));
                        // The value it keeps, so the sender's retry loop sees the refusal.
                        if let Some((i, _)) = self.params.by_name(&name) {
                            replies.push(self.param_value(i));
                        }
                    }
                }
            }
            MavMessage::MISSION_REQUEST_LIST(r) => {
                replies.push(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                    count: 0,
                    target_system: header.system_id as u8,
                    target_component: header.component_id,
                    mission_type: r.mission_type,
                    opaque_id: 0,
                }));
            }
            MavMessage::MISSION_COUNT(c) => {
                let result = if c.count == 0 {
                    MavMissionResult::MAV_MISSION_ACCEPTED
                } else {
                    replies.push(status_text(
                        MavSeverity::MAV_SEVERITY_WARNING,
                        "mission upload refused: this vehicle flies no missions",
                    ));
                    MavMissionResult::MAV_MISSION_UNSUPPORTED
                };
                replies.push(mission_ack(header, result, c.mission_type));
            }
            MavMessage::MISSION_CLEAR_ALL(c) => {
                replies.push(mission_ack(
                    header,
                    MavMissionResult::MAV_MISSION_ACCEPTED,
                    c.mission_type,
                ));
            }
            MavMessage::TIMESYNC(t) if t.tc1 == 0 => {
                replies.push(MavMessage::TIMESYNC(TIMESYNC_DATA {
                    tc1: ((now - self.boot_time).max(0.0) * 1e9) as i64,
                    ts1: t.ts1,
                    target_system: header.system_id as u8,
                    target_component: header.component_id,
                }));
            }
            MavMessage::REQUEST_DATA_STREAM(r) => {
                let ids: &[u32] = match r.req_stream_id {
                    MavDataStream::MAV_DATA_STREAM_ALL => &STREAMABLE,
                    MavDataStream::MAV_DATA_STREAM_POSITION => {
                        &[ID_LOCAL_POSITION_NED, ID_GLOBAL_POSITION_INT]
                    }
                    MavDataStream::MAV_DATA_STREAM_EXTRA1 => &[ID_ATTITUDE],
                    MavDataStream::MAV_DATA_STREAM_EXTENDED_STATUS => &[ID_SYS_STATUS],
                    _ => &[],
                };
                let interval = (r.start_stop != 0 && r.req_message_rate > 0)
                    .then(|| 1.0 / f64::from(r.req_message_rate));
                for &id in ids {
                    self.set_stream(id, interval, now);
                }
            }
            _ => {}
        }
        replies
    }

    /// Whether a message for (`system`, `component`) is for this autopilot: its own ids or
    /// broadcast (0).
    fn for_us(&mut self, system: u8, component: u8) -> bool {
        let ours = (system == self.config.system_id || system == 0)
            && (component == self.config.component_id || component == 0);
        if !ours {
            self.rejections.not_for_us += 1;
        }
        ours
    }

    fn set_stream(&mut self, id: u32, interval: Option<f64>, now: f64) {
        if let Some(stream) = self.streams.iter_mut().find(|s| s.id == id) {
            stream.interval = interval;
            stream.next = now;
        }
    }

    fn param_value(&self, index: usize) -> MavMessage {
        let p = self
            .params
            .by_index(index)
            .copied()
            .unwrap_or_else(|| unreachable!("index {index} checked by the caller"));
        MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: p.value,
            param_count: self.params.len() as u16,
            param_index: index as u16,
            param_id: p.name.into(),
            param_type: p.kind,
        })
    }

    fn on_setpoint(&mut self, s: &SET_POSITION_TARGET_LOCAL_NED_DATA, now: f64) {
        if !self.for_us(s.target_system, s.target_component) {
            return;
        }
        let body = match s.coordinate_frame {
            MavFrame::MAV_FRAME_LOCAL_NED | MavFrame::MAV_FRAME_LOCAL_OFFSET_NED => false,
            MavFrame::MAV_FRAME_BODY_NED | MavFrame::MAV_FRAME_BODY_OFFSET_NED => true,
            _ => {
                self.rejections.wrong_frame += 1;
                return;
            }
        };
        let mask = s.type_mask.bits();
        // Bits 0-2 ignore the position axes, 3-5 velocity, 6-8 acceleration, 9 force, 10 yaw,
        // 11 yaw rate.
        let position = mask & 0x007 == 0;
        let velocity = mask & 0x038 == 0;
        let partial = !matches!(mask & 0x007, 0 | 0x007) || !matches!(mask & 0x038, 0 | 0x038);
        let acceleration = mask & 0x1C0 != 0x1C0 || mask & 0x200 != 0;
        if partial || acceleration || !(position || velocity) {
            self.rejections.wrong_type_mask += 1;
            return;
        }
        let yaw = mask & 0x400 == 0;
        let yaw_rate = mask & 0x800 == 0;
        // Only the fields the mask uses must be numbers.
        let finite = |used: bool, values: &[f32]| !used || values.iter().all(|c| c.is_finite());
        let all_finite = finite(position, &[s.x, s.y, s.z])
            && finite(velocity, &[s.vx, s.vy, s.vz])
            && finite(yaw, &[s.yaw])
            && finite(yaw_rate, &[s.yaw_rate]);
        if !all_finite {
            self.rejections.non_finite += 1;
            return;
        }
        let (sin, cos) = self.heading.sin_cos();
        let rotate = |v: [f64; 3]| -> [f64; 3] {
            if body {
                [v[0] * cos - v[1] * sin, v[0] * sin + v[1] * cos, v[2]]
            } else {
                v
            }
        };
        let v = if velocity {
            rotate([f64::from(s.vx), f64::from(s.vy), f64::from(s.vz)])
        } else {
            [0.0; 3]
        };
        self.target = if position {
            let p = rotate([f64::from(s.x), f64::from(s.y), f64::from(s.z)]);
            let offset = matches!(
                s.coordinate_frame,
                MavFrame::MAV_FRAME_LOCAL_OFFSET_NED
                    | MavFrame::MAV_FRAME_BODY_NED
                    | MavFrame::MAV_FRAME_BODY_OFFSET_NED
            );
            let p = if offset {
                [
                    p[0] + self.position_ned[0],
                    p[1] + self.position_ned[1],
                    p[2] + self.position_ned[2],
                ]
            } else {
                p
            };
            Target::Position(p, v)
        } else {
            Target::Velocity(v)
        };
        if yaw {
            self.heading = f64::from(s.yaw);
        }
        self.yaw_rate = if yaw_rate { f64::from(s.yaw_rate) } else { 0.0 };
        self.last_setpoint = Some(now);
        if self.mode != self.config.flavour.external_mode() {
            self.rejections.outside_external_mode += 1;
        } else if self.config.flavour == Flavour::ArduPilot && !self.landed() {
            // ArduCopter: a GUIDED setpoint in the air ends a takeoff still climbing (which is
            // why the daemon sends none until its takeoff is done).
            self.takeoff_height = None;
        }
    }

    fn streaming(&self, now: f64) -> bool {
        self.last_setpoint
            .is_some_and(|last| now - last <= PX4_MAX_STREAM_GAP)
    }

    fn on_command(
        &mut self,
        header: &MavHeader,
        c: &Command,
        now: f64,
        replies: &mut Vec<MavMessage>,
    ) {
        // Broadcast (0) or addressed to us; anything else is another vehicle's or component's,
        // which answers for itself.
        if !self.for_us(c.target_system, c.target_component) {
            return;
        }
        let (result, why) = self.execute(c, now, replies);
        if result != MavResult::MAV_RESULT_ACCEPTED {
            self.rejections.commands_refused += 1;
            let why = why.unwrap_or_else(|| format!("command {:?} refused", c.command));
            replies.push(status_text(MavSeverity::MAV_SEVERITY_WARNING, &why));
        }
        let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command: c.command,
            result,
            progress: 0,
            result_param2: 0,
            target_system: header.system_id as u8,
            target_component: header.component_id,
        });
        // The acknowledgement first, then what was asked for (AUTOPILOT_VERSION, ...).
        replies.insert(0, ack);
    }

    /// Carries out a command; the result and, for a refusal, why.
    fn execute(
        &mut self,
        c: &Command,
        now: f64,
        replies: &mut Vec<MavMessage>,
    ) -> (MavResult, Option<String>) {
        use MavResult::{
            MAV_RESULT_ACCEPTED as ACCEPTED, MAV_RESULT_DENIED as DENIED,
            MAV_RESULT_FAILED as FAILED, MAV_RESULT_UNSUPPORTED as UNSUPPORTED,
        };
        let flavour = self.config.flavour;
        let p = c.params;
        // ArduCopter answers a command its state does not allow with FAILED, PX4 with DENIED.
        let refused = match flavour {
            Flavour::Px4 => DENIED,
            Flavour::ArduPilot => FAILED,
        };
        match c.command {
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM if p[0] == 1.0 => {
                if self.armed {
                    return (ACCEPTED, None);
                }
                let land_or_rtl =
                    self.mode == flavour.land_mode() || self.mode == flavour.rtl_mode();
                if flavour == Flavour::ArduPilot && land_or_rtl {
                    return (refused, Some("Arm: mode not armable".into()));
                }
                if !self.landed() {
                    return (refused, Some("Arm: not on the ground".into()));
                }
                self.armed = true;
                self.armed_at = now;
                self.flew_since_arming = false;
                (ACCEPTED, None)
            }
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM if p[0] == 0.0 => {
                if !self.armed {
                    return (ACCEPTED, None);
                }
                if !self.landed() && p[1] != FORCE_DISARM_MAGIC {
                    return (refused, Some("Disarm denied: not landed".into()));
                }
                self.disarm();
                (ACCEPTED, None)
            }
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => (
                DENIED,
                Some(format!("arm/disarm: param1 {} is not 0 or 1", p[0])),
            ),
            MavCmd::MAV_CMD_DO_SET_MODE => self.on_set_mode(&p, now),
            MavCmd::MAV_CMD_NAV_TAKEOFF => {
                if !self.armed {
                    return (refused, Some("Takeoff denied: disarmed".into()));
                }
                if !self.landed() {
                    return (refused, Some("Takeoff denied: already flying".into()));
                }
                let height = match flavour {
                    Flavour::Px4 if p[6].is_finite() => {
                        f64::from(p[6]) - self.config.home.altitude_amsl_m
                    }
                    Flavour::Px4 => self.params.get("MIS_TAKEOFF_ALT"),
                    Flavour::ArduPilot => {
                        if self.mode != flavour.external_mode() {
                            return (refused, Some("Takeoff: mode does not take off".into()));
                        }
                        f64::from(p[6])
                    }
                };
                if !(height.is_finite() && height > TAKEOFF_TOLERANCE_M && height <= 100.0) {
                    return (
                        DENIED,
                        Some(format!("Takeoff denied: altitude {height:.1} m above home")),
                    );
                }
                self.takeoff_height = Some(height);
                if flavour == Flavour::Px4 {
                    self.mode = FlightMode::PX4_TAKEOFF;
                }
                (ACCEPTED, None)
            }
            // Land where it is; a vehicle on the ground (disarmed) has nothing to land.
            MavCmd::MAV_CMD_NAV_LAND if self.armed => {
                self.begin_landing(now);
                (ACCEPTED, None)
            }
            MavCmd::MAV_CMD_NAV_LAND => (refused, Some("Land denied: disarmed".into())),
            MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH if self.armed && !self.landed() => {
                self.takeoff_height = None;
                self.mode = flavour.rtl_mode();
                (ACCEPTED, None)
            }
            MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH => {
                (refused, Some("RTL denied: not flying".into()))
            }
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                let id = p[0] as u32;
                if !(p[0].is_finite() && STREAMABLE.contains(&id)) {
                    return (DENIED, Some(format!("no stream of message {}", p[0])));
                }
                let interval = match p[1] {
                    -1.0 => None,
                    0.0 => Self::default_streams(&self.config, now)
                        .iter()
                        .find(|s| s.id == id)
                        .and_then(|s| s.interval)
                        .or(Some(1.0 / self.config.position_rate_hz)),
                    x if x.is_finite() && x > 0.0 => Some(f64::from(x) / 1e6),
                    x => return (DENIED, Some(format!("message interval {x} us"))),
                };
                self.set_stream(id, interval, now);
                (ACCEPTED, None)
            }
            MavCmd::MAV_CMD_REQUEST_MESSAGE => {
                let id = p[0] as u32;
                match self.message(id, now) {
                    Some(message) if p[0].is_finite() => {
                        replies.push(message);
                        (ACCEPTED, None)
                    }
                    _ => (DENIED, Some(format!("message {} cannot be sent", p[0]))),
                }
            }
            MavCmd::MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES => {
                replies.push(self.autopilot_version());
                (ACCEPTED, None)
            }
            other => (UNSUPPORTED, Some(format!("{other:?} unsupported"))),
        }
    }

    fn begin_landing(&mut self, now: f64) {
        if !self.landing() {
            self.landing_since = Some(now);
            self.touchdown_at = None;
        }
        self.takeoff_height = None;
        self.mode = self.config.flavour.land_mode();
    }

    fn disarm(&mut self) {
        self.armed = false;
        self.takeoff_height = None;
    }

    fn on_set_mode(&mut self, p: &[f32; 7], now: f64) -> (MavResult, Option<String>) {
        use MavResult::{MAV_RESULT_ACCEPTED as ACCEPTED, MAV_RESULT_DENIED as DENIED};
        if p[0] as u32 & MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits() as u32 == 0 {
            return (DENIED, Some("set mode: custom mode flag not set".into()));
        }
        if !(p[1].is_finite() && p[1] >= 0.0 && p[2].is_finite() && p[2] >= 0.0) {
            return (DENIED, Some("set mode: bad mode number".into()));
        }
        let flavour = self.config.flavour;
        let requested = match flavour {
            Flavour::Px4 => {
                let (main, sub) = (p[1] as u32, p[2] as u32);
                // PX4 main modes 1 (MANUAL) ..= 8 (STABILIZED); AUTO's sub modes 1 ..= 8.
                let known = (1..=8).contains(&main) && (main != 4 || (1..=8).contains(&sub));
                if !known {
                    return (DENIED, Some(format!("mode {main}.{sub} unknown")));
                }
                FlightMode::Px4 {
                    main: main as u8,
                    sub: if main == 4 { sub as u8 } else { 0 },
                }
            }
            Flavour::ArduPilot => {
                // STABILIZE, ACRO, ALT_HOLD, AUTO, GUIDED, LOITER, RTL, LAND, POSHOLD, BRAKE.
                let mode = p[1] as u32;
                if ![0, 1, 2, 3, 4, 5, 6, 9, 16, 17].contains(&mode) {
                    return (DENIED, Some(format!("mode {mode} unknown")));
                }
                FlightMode::ArduPilot(mode)
            }
        };
        if flavour == Flavour::Px4 && requested == FlightMode::PX4_OFFBOARD && !self.streaming(now)
        {
            // PX4 refuses OFFBOARD without a live setpoint stream.
            return (
                MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
                Some("Offboard denied: no setpoint stream".into()),
            );
        }
        if requested == flavour.land_mode() {
            if self.armed {
                self.begin_landing(now);
            } else {
                self.mode = requested;
            }
            return (ACCEPTED, None);
        }
        if requested == FlightMode::PX4_TAKEOFF {
            if !(self.armed && self.landed()) {
                return (
                    DENIED,
                    Some("Takeoff denied: not armed on the ground".into()),
                );
            }
            self.takeoff_height = Some(self.params.get("MIS_TAKEOFF_ALT"));
        } else if !(flavour == Flavour::ArduPilot && requested == flavour.external_mode()) {
            // Any other mode ends a takeoff; ArduCopter's takeoff is part of GUIDED.
            self.takeoff_height = None;
        }
        self.mode = requested;
        (ACCEPTED, None)
    }

    /// Advance to `now`: apply failsafes, integrate the vehicle's own kinematics, drain the
    /// battery, and emit due telemetry. The same as [`fly`](Self::fly) then
    /// [`telemetry`](Self::telemetry).
    pub fn tick(&mut self, now: f64) -> Tick {
        let velocity_ned = self.fly(now);
        Tick {
            velocity_ned,
            telemetry: self.telemetry(now),
        }
    }

    /// The velocity the autopilot commands now (m/s, NED), after its failsafes.
    fn command(&mut self, now: f64) -> [f64; 3] {
        let flavour = self.config.flavour;
        let since_setpoint = self.last_setpoint.map_or(f64::INFINITY, |t| now - t);
        if !self.armed {
            // Disarmed in the air: it falls.
            return if self.landed() {
                [0.0; 3]
            } else {
                [0.0, 0.0, FALL_SPEED]
            };
        }
        let behaviour = self.behaviour();
        if behaviour == Behaviour::External
            && flavour == Flavour::Px4
            && since_setpoint > self.params.get("COM_OF_LOSS_T")
        {
            self.mode = flavour.hold_mode();
            self.failsafe_events += 1;
            self.say(
                MavSeverity::MAV_SEVERITY_CRITICAL,
                "Failsafe: offboard setpoints lost, holding",
            );
            return [0.0; 3];
        }
        let height = -self.position_ned[2];
        let limit = self.config.max_speed;
        match behaviour {
            Behaviour::TakingOff(target) => {
                if height >= target - TAKEOFF_TOLERANCE_M {
                    self.takeoff_height = None;
                    if flavour == Flavour::Px4 {
                        self.mode = flavour.hold_mode();
                    }
                    return [0.0; 3];
                }
                let speed = match flavour {
                    Flavour::Px4 => self.params.get("MPC_TKO_SPEED"),
                    Flavour::ArduPilot => self.params.get("WPNAV_SPEED_UP") / 100.0,
                };
                // Slow down over the last metre, as both autopilots' position controllers do.
                let up = speed.min(limit).min((target - height).max(0.1));
                [0.0, 0.0, -up]
            }
            Behaviour::Landing => [0.0, 0.0, self.land_speed()],
            Behaviour::Returning => {
                let speed = match flavour {
                    Flavour::Px4 => self.params.get("MPC_XY_CRUISE"),
                    Flavour::ArduPilot => self.params.get("WPNAV_SPEED") / 100.0,
                }
                .min(limit);
                let (n, e) = (-self.position_ned[0], -self.position_ned[1]);
                let distance = (n * n + e * e).sqrt();
                if distance < 0.1 {
                    [0.0, 0.0, self.land_speed()]
                } else {
                    let v = speed.min(distance * POSITION_GAIN) / distance;
                    [n * v, e * v, 0.0]
                }
            }
            Behaviour::Holding => [0.0; 3],
            Behaviour::External => {
                let timeout = match flavour {
                    Flavour::Px4 => f64::INFINITY,
                    Flavour::ArduPilot => self.params.get("GUID_TIMEOUT"),
                };
                if since_setpoint > timeout {
                    return [0.0; 3];
                }
                // ArduCopter's GUIDED does not lift a landed copter: it needs NAV_TAKEOFF.
                if self.landed() && flavour == Flavour::ArduPilot {
                    return [0.0; 3];
                }
                let v = match self.target {
                    Target::Velocity(v) => v,
                    Target::Position(p, feed_forward) => [
                        (p[0] - self.position_ned[0]) * POSITION_GAIN + feed_forward[0],
                        (p[1] - self.position_ned[1]) * POSITION_GAIN + feed_forward[1],
                        (p[2] - self.position_ned[2]) * POSITION_GAIN + feed_forward[2],
                    ],
                };
                let max_xy = match flavour {
                    Flavour::Px4 => self.params.get("MPC_XY_VEL_MAX").min(limit),
                    Flavour::ArduPilot => limit,
                };
                let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                let scale = if speed > max_xy { max_xy / speed } else { 1.0 };
                [v[0] * scale, v[1] * scale, v[2] * scale]
            }
        }
    }

    /// Moves the position estimate's error on by `dt`.
    fn wander_estimate(&mut self, dt: f64) {
        if let Some((error, process, rng)) = self.estimate.as_mut()
            && !self.random_held
        {
            error.step(process, dt, rng);
        }
    }

    /// Where the autopilot believes it is (m, NED): the truth plus its estimate's error.
    fn estimated_position(&self) -> [f64; 3] {
        let e = self
            .estimate
            .as_ref()
            .filter(|_| !self.random_held)
            .map_or([0.0; 3], |(error, process, _)| error.velocity(process));
        let std = self.config.dynamics.map_or([0.0; 2], |m| {
            [
                usable_std(m.estimate_std_m),
                usable_std(m.estimate_vertical_std_m),
            ]
        });
        let scale = [std[0], std[0], std[1]];
        std::array::from_fn(|k| self.position_ned[k] + scale[k] * e[k])
    }

    fn land_speed(&self) -> f64 {
        match self.config.flavour {
            Flavour::Px4 => self.params.get("MPC_LAND_SPEED"),
            Flavour::ArduPilot => self.params.get("LAND_SPEED") / 100.0,
        }
    }

    /// Advance to `now` without reporting: failsafes, kinematics, battery. Returns the velocity
    /// the vehicle flies (m/s, NED; zero when holding or on the ground). A lockstep simulator
    /// calls this, moves the world, feeds the true state back with
    /// [`set_state`](Self::set_state) and only then asks for [`telemetry`](Self::telemetry),
    /// so the reported position is the one after the move, as a real autopilot reports its
    /// latest estimate.
    pub fn fly(&mut self, now: f64) -> [f64; 3] {
        let mut command = self.command(now);
        // On the ground a vehicle moves only by lifting off.
        if self.landed() {
            if self.armed && command[2] < -LIFTOFF_SPEED {
                self.landed_since = None;
                self.flew_since_arming = true;
                command[0] = 0.0;
                command[1] = 0.0;
            } else {
                command = [0.0; 3];
            }
        }
        // To the microsecond (MAVLink's time resolution): a tick is the same step whatever
        // time it starts at, so the motion model takes as many sub-steps (and the wind as many
        // draws) after a pre-flight of any length.
        let dt = self
            .last_tick
            .map_or(0.0, |last| ((now - last) * 1e6).round().max(0.0) / 1e6);
        // What the vehicle flies: the command at once, or where the motion model has got to.
        let flown = match (self.motion.as_mut(), self.config.dynamics) {
            (Some((drone, wind, rng)), Some(m)) if dt > 0.0 => {
                let target = ned_to_sim(command);
                let steps = (dt / MOTION_STEP_S).ceil().max(1.0) as usize;
                let h = dt / steps as f64;
                let start = drone.position;
                for _ in 0..steps {
                    let air = if self.random_held {
                        [0.0; 3]
                    } else {
                        wind.step(&m.wind, h, rng)
                    };
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
        let mut flown = if self.landed() {
            // On the ground the wind moves nothing: the motion model stays at rest where the
            // vehicle stands, for the takeoff to start from.
            if let Some((drone, _, _)) = self.motion.as_mut() {
                *drone = Multicopter::hovering_at(ned_to_sim(self.position_ned));
            }
            [0.0; 3]
        } else {
            flown
        };
        self.wander_estimate(dt);
        if dt > 0.0 {
            for (p, v) in self.position_ned.iter_mut().zip(flown) {
                *p += v * dt;
            }
            // The floor (NED z = 0) stops a descent, as the simulator's world does.
            if self.position_ned[2] > 0.0 {
                flown[2] -= self.position_ned[2] / dt;
                self.position_ned[2] = 0.0;
            }
            if self.armed {
                let speed = (flown[0].powi(2) + flown[1].powi(2) + flown[2].powi(2)).sqrt();
                let drain =
                    self.config.hover_drain_pct_per_s + self.config.speed_drain_pct_per_s * speed;
                self.battery_pct = (self.battery_pct - drain * dt).max(0.0);
            }
            for ((a, new), old) in self
                .acceleration
                .iter_mut()
                .zip(flown)
                .zip(self.velocity_ned)
            {
                *a = (new - old) / dt;
            }
            self.heading = (self.heading + self.yaw_rate * dt).rem_euclid(std::f64::consts::TAU);
        }
        self.velocity_ned = flown;
        self.last_tick = Some(now);
        self.detect_landing(command, now);
        self.auto_disarm(now);
        flown
    }

    /// Touchdown: in the air, at the floor, not commanded up.
    fn detect_landing(&mut self, command: [f64; 3], now: f64) {
        if self.landed() || self.position_ned[2] < -TOUCHDOWN_M || command[2] < 0.0 {
            return;
        }
        self.landed_since = Some(now);
        self.velocity_ned = [0.0; 3];
        if let Some((drone, _, _)) = self.motion.as_mut() {
            drone.velocity = [0.0; 3];
        }
        let behaviour = self.behaviour();
        if self.armed && matches!(behaviour, Behaviour::Landing | Behaviour::Returning) {
            // The land detector ends LAND and RTL by disarming.
            self.disarm();
            self.touchdown_at = Some(now);
            self.say(MavSeverity::MAV_SEVERITY_INFO, "Landing detected, disarmed");
        }
    }

    /// Disarm a vehicle left armed on the ground: after arming without a takeoff, and after
    /// landing.
    fn auto_disarm(&mut self, now: f64) {
        let Some(landed_since) = self.landed_since else {
            return;
        };
        if !self.armed {
            return;
        }
        let (delay, since, what) = match (self.config.flavour, self.flew_since_arming) {
            (Flavour::Px4, false) => (
                self.params.get("COM_DISARM_PRFLT"),
                self.armed_at,
                "no takeoff",
            ),
            (Flavour::Px4, true) => (self.params.get("COM_DISARM_LAND"), landed_since, "landed"),
            (Flavour::ArduPilot, flew) => (
                self.params.get("DISARM_DELAY"),
                if flew { landed_since } else { self.armed_at },
                if flew { "landed" } else { "no takeoff" },
            ),
        };
        if delay > 0.0 && now - since >= delay {
            self.disarm();
            self.failsafe_events += 1;
            self.say(
                MavSeverity::MAV_SEVERITY_WARNING,
                &format!("Auto-disarmed: {what} for {delay:.0} s"),
            );
        }
    }

    /// Restart the telemetry schedule at `now`: everything falls due then, and the periodic
    /// messages follow from there. A lockstep simulator calls this when simulated time starts,
    /// so the heartbeat phase does not depend on how long a wall-clock pre-roll took.
    pub fn restart_telemetry(&mut self, now: f64) {
        self.next_status = now;
        for stream in &mut self.streams {
            stream.next = now;
        }
    }

    /// Simulated time begins at `now` (s): every telemetry stream falls due and the clock goes
    /// on from `now`, whatever the autopilot did while it listened on the wall clock before
    /// (a pre-roll of varying length). Until [`release`](Self::release) the air is calm and
    /// the position estimate exact: how many ticks the pre-flight takes (arming and takeoff
    /// wait on other processes) then changes nothing that happens after it.
    pub fn start_episode(&mut self, now: f64) {
        self.restart_telemetry(now);
        self.last_tick = Some(now);
        self.random_held = true;
        if let Some((drone, _, _)) = self.motion.as_mut() {
            *drone = Multicopter::hovering_at(ned_to_sim(self.position_ned));
        }
        self.velocity_ned = [0.0; 3];
        self.acceleration = [0.0; 3];
    }

    /// The episode starts (a lockstep simulator releases its vehicles): the wind's and the
    /// estimate error's random streams start from their seeds, as the simulator's episode
    /// starts its noise at step 0, so a seeded mission flies the same each run.
    pub fn release(&mut self) {
        let (motion, mut estimate) = Self::random_processes(&self.config, self.position_ned);
        if let (Some((_, wind, rng)), Some((_, fresh_wind, fresh_rng))) =
            (self.motion.as_mut(), motion)
        {
            *wind = fresh_wind;
            *rng = fresh_rng;
        }
        // The estimate is exact at the release (as an EKF's local frame starts where the
        // vehicle is) and wanders to its full spread over its correlation time: a report does
        // not jump by the error's whole size from one tick to the next.
        if let Some((error, _, _)) = estimate.as_mut() {
            *error = Wind::default();
        }
        self.estimate = estimate;
        self.random_held = false;
    }

    /// The telemetry due at `now` from the current state: queued STATUSTEXTs, the HEARTBEAT
    /// every status period, and every stream that is due.
    pub fn telemetry(&mut self, now: f64) -> Vec<MavMessage> {
        // A microsecond of slack: ticks that add up 0.1 s steps must not skip a 0.1 s stream.
        const SLACK: f64 = 1e-6;
        let mut telemetry = std::mem::take(&mut self.outbox);
        if now + SLACK >= self.next_status {
            self.next_status = now + self.config.status_period;
            telemetry.push(self.heartbeat());
        }
        for i in 0..self.streams.len() {
            let stream = self.streams[i];
            if let Some(interval) = stream.interval
                && now + SLACK >= stream.next
            {
                self.streams[i].next = now + interval;
                if let Some(message) = self.message(stream.id, now) {
                    telemetry.push(message);
                }
            }
        }
        telemetry
    }

    /// Message `id` as of now, if this autopilot sends it.
    fn message(&self, id: u32, now: f64) -> Option<MavMessage> {
        Some(match id {
            ID_SYS_STATUS => self.sys_status(),
            ID_ATTITUDE => self.attitude(now),
            ID_LOCAL_POSITION_NED => self.local_position(now),
            ID_GLOBAL_POSITION_INT => self.global_position(now),
            ID_BATTERY_STATUS => self.battery_status(),
            ID_AUTOPILOT_VERSION => self.autopilot_version(),
            ID_HOME_POSITION => self.home_position(),
            ID_EXTENDED_SYS_STATE => self.extended_sys_state(),
            _ => return None,
        })
    }

    fn time_boot_ms(&self, now: f64) -> u32 {
        ((now - self.boot_time).max(0.0) * 1000.0) as u32
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

    fn volts(&self) -> f64 {
        // A 4S pack: 16.8 V full, 14.0 V empty, linear in between.
        14.0 + 2.8 * self.battery_pct / 100.0
    }

    fn sys_status(&self) -> MavMessage {
        // What a healthy, armable multicopter with GPS reports (MAVSDK's health reads these).
        let sensors = MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_GYRO
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_MAG
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_GPS
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            | MavSysStatusSensor::MAV_SYS_STATUS_AHRS
            | MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK;
        MavMessage::SYS_STATUS(SYS_STATUS_DATA {
            onboard_control_sensors_present: sensors,
            onboard_control_sensors_enabled: sensors,
            onboard_control_sensors_health: sensors,
            load: 200,
            voltage_battery: (self.volts() * 1000.0) as u16,
            current_battery: if self.armed { 1500 } else { 50 },
            battery_remaining: self.battery_pct.round() as i8,
            ..Default::default()
        })
    }

    fn extended_sys_state(&self) -> MavMessage {
        let landed_state = match (self.landed(), self.behaviour()) {
            (true, _) => MavLandedState::MAV_LANDED_STATE_ON_GROUND,
            (false, Behaviour::TakingOff(_)) => MavLandedState::MAV_LANDED_STATE_TAKEOFF,
            (false, Behaviour::Landing) => MavLandedState::MAV_LANDED_STATE_LANDING,
            (false, _) => MavLandedState::MAV_LANDED_STATE_IN_AIR,
        };
        MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
            vtol_state: MavVtolState::MAV_VTOL_STATE_MC,
            landed_state,
        })
    }

    fn battery_status(&self) -> MavMessage {
        let mut voltages = [u16::MAX; 10];
        voltages[0] = (self.volts() * 1000.0) as u16;
        let charge_state = match self.battery_pct {
            x if x > 30.0 => MavBatteryChargeState::MAV_BATTERY_CHARGE_STATE_OK,
            x if x > 15.0 => MavBatteryChargeState::MAV_BATTERY_CHARGE_STATE_LOW,
            _ => MavBatteryChargeState::MAV_BATTERY_CHARGE_STATE_CRITICAL,
        };
        MavMessage::BATTERY_STATUS(BATTERY_STATUS_DATA {
            current_consumed: -1,
            energy_consumed: -1,
            temperature: i16::MAX,
            voltages,
            current_battery: if self.armed { 1500 } else { 50 },
            id: 0,
            battery_function: MavBatteryFunction::MAV_BATTERY_FUNCTION_ALL,
            mavtype: MavBatteryType::MAV_BATTERY_TYPE_LIPO,
            battery_remaining: self.battery_pct.round() as i8,
            charge_state,
            ..Default::default()
        })
    }

    fn attitude(&self, now: f64) -> MavMessage {
        // A multicopter tilts into its acceleration: pitch down to speed up north-forward.
        const G: f64 = 9.81;
        let (sin, cos) = self.heading.sin_cos();
        let a = self.acceleration;
        let forward = a[0] * cos + a[1] * sin;
        let right = -a[0] * sin + a[1] * cos;
        MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: self.time_boot_ms(now),
            roll: (right / G).atan() as f32,
            pitch: (-forward / G).atan() as f32,
            yaw: wrap_pi(self.heading) as f32,
            rollspeed: 0.0,
            pitchspeed: 0.0,
            yawspeed: self.yaw_rate as f32,
        })
    }

    fn local_position(&self, now: f64) -> MavMessage {
        let p = self.estimated_position();
        let v = self.velocity_ned;
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: self.time_boot_ms(now),
            x: p[0] as f32,
            y: p[1] as f32,
            z: p[2] as f32,
            vx: v[0] as f32,
            vy: v[1] as f32,
            vz: v[2] as f32,
        })
    }

    fn global_position(&self, now: f64) -> MavMessage {
        let p = self.estimated_position();
        let v = self.velocity_ned;
        let home = self.config.home;
        let (latitude, longitude) = home.offset(p[0], p[1]);
        let heading = self.heading.to_degrees().rem_euclid(360.0);
        MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            time_boot_ms: self.time_boot_ms(now),
            lat: (latitude * 1e7).round() as i32,
            lon: (longitude * 1e7).round() as i32,
            alt: ((home.altitude_amsl_m - p[2]) * 1000.0).round() as i32,
            relative_alt: (-p[2] * 1000.0).round() as i32,
            vx: (v[0] * 100.0).round() as i16,
            vy: (v[1] * 100.0).round() as i16,
            vz: (v[2] * 100.0).round() as i16,
            hdg: (heading * 100.0).round() as u16 % 36000,
        })
    }

    fn home_position(&self) -> MavMessage {
        let home = self.config.home;
        MavMessage::HOME_POSITION(HOME_POSITION_DATA {
            latitude: (home.latitude_deg * 1e7).round() as i32,
            longitude: (home.longitude_deg * 1e7).round() as i32,
            altitude: (home.altitude_amsl_m * 1000.0).round() as i32,
            q: [1.0, 0.0, 0.0, 0.0],
            ..Default::default()
        })
    }

    fn autopilot_version(&self) -> MavMessage {
        // PX4 v1.14.0 and ArduCopter V4.6.0, released (type 255), as the real ones encode it;
        // the custom version names this a mock.
        let flight_sw_version = match self.config.flavour {
            Flavour::Px4 => 0x010E_00FF,
            Flavour::ArduPilot => 0x0406_00FF,
        };
        MavMessage::AUTOPILOT_VERSION(AUTOPILOT_VERSION_DATA {
            capabilities: MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_INT
                | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED,
            uid: 0x5348_0000 + u64::from(self.config.system_id),
            flight_sw_version,
            flight_custom_version: *b"skymock\0",
            ..Default::default()
        })
    }
}

/// A STATUSTEXT (cut to its 50 bytes).
fn status_text(severity: MavSeverity, text: &str) -> MavMessage {
    let cut = match text.char_indices().nth(50) {
        Some((at, _)) => &text[..at],
        None => text,
    };
    MavMessage::STATUSTEXT(STATUSTEXT_DATA {
        severity,
        text: cut.into(),
        ..Default::default()
    })
}

fn mission_ack(
    header: &MavHeader,
    result: MavMissionResult,
    mission_type: mavlink::dialects::common::MavMissionType,
) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: header.system_id as u8,
        target_component: header.component_id,
        mavtype: result,
        mission_type,
        opaque_id: 0,
    })
}

fn wrap_pi(angle: f64) -> f64 {
    let a = angle.rem_euclid(std::f64::consts::TAU);
    if a > std::f64::consts::PI {
        a - std::f64::consts::TAU
    } else {
        a
    }
}

#[cfg(test)]
mod tests;
