//! The daemon's pure decision core: explicit state and time in, decisions out.
//!
//! [`DaemonCore`] is fed what arrives (uplink messages from the ground, autopilot heartbeats and
//! positions) together with the daemon's time, and is asked once per control period
//! ([`DaemonCore::tick`]) what to send: a velocity setpoint (MAVLink `LOCAL_NED`, m/s), maybe an
//! autopilot command (arm, mode switch), and a [`Status`] that says what it is doing and why.
//! It owns no socket and reads no clock, so the same code runs against wall time, against a
//! simulator's lockstep clock, and in tests.
//!
//! # Mission flow
//! On a start command the core brings the autopilot under control and into the air, the way
//! each family wants it:
//! * **PX4**: stream zero-velocity setpoints, arm, and once the stream has run for
//!   [`CoreConfig::stream_before_mode`] ask for OFFBOARD; then climb on its own upward
//!   setpoints (PX4 OFFBOARD takes off on them; zero setpoints on the ground would let PX4
//!   disarm itself after `COM_DISARM_PRFLT`).
//! * **ArduPilot**: ask for GUIDED, then arm, then at once `MAV_CMD_NAV_TAKEOFF` (ArduCopter's
//!   GUIDED velocity commands do not lift a landed copter, and it disarms `DISARM_DELAY`
//!   after arming without a takeoff); no setpoints while the takeoff climbs, since one would
//!   cut it short.
//!
//! Either way the core is airborne once its height (above the autopilot's home, the local
//! origin) reaches [`CoreConfig::takeoff_altitude`] less [`TAKEOFF_TOLERANCE_M`]; a vehicle
//! that is already up there when the mission starts is airborne at once, one in the air below
//! it climbs on setpoints. Until airborne, an autopilot that disarms on the ground is armed
//! again (its own timeout, not a pilot); after, any loss of control is the pilot's. Then the
//! core flies: world snapshot (own position replaced by the autopilot's, which
//! is fresher, its height counted from the altitude band's floor) -> [`skyherd_onboard::obs::encode`] -> [`OnboardPolicy::act`] ->
//! [`skyherd_onboard::obs::LocalFrame::action_to_world`] -> [`skyherd_onboard::safety::check`] ->
//! [`skyherd_onboard::frame::sim_to_ned`].
//! It holds (zero-velocity setpoints) when the uplink is stale, when the autopilot link is lost,
//! after an abort, and when the pilot takes control away; every hold names its [`HoldReason`].
//! Holds with a fresh own position still pass through the safety rules, so a drone outside the
//! geofence or below the altitude band is steered back in rather than frozen there.
//!
//! # When the ground dies
//! A stale uplink is a hold, because the ground usually comes back (a radio fade, a restart).
//! A ground that stays silent while the drone flies (killed, crashed, out of range for good)
//! would leave it hovering until its battery runs out, so after
//! [`CoreConfig::land_after`] of continuous staleness in flight the core lands instead
//! ([`Status::Landing`]): it asks the autopilot to land where it is
//! ([`AutopilotCommand::Land`], `MAV_CMD_NAV_LAND`), repeated until the autopilot reports it
//! has left the control mode or disarmed, and sends no more setpoints (in its LAND mode the
//! autopilot flies the descent and disarms on touchdown). A landing is not undone by the uplink
//! coming back, nor by an abort or complete: only a new start command flies again.
//!
//! Uplink bytes arrive as TUNNEL payloads ([`DaemonCore::on_tunnel_payload`]): the
//! [`wire`](skyherd_onboard::wire) reassembler turns chunks into [`Uplink`] messages; bad chunks are
//! counted and dropped.
//!
//! ```
//! use skyherd_daemon::control::{CoreConfig, DaemonCore, Millis, OnboardPolicy, Status};
//! use skyherd_link::Flavour;
//! use skyherd_onboard::obs::FEATURES;
//! use skyherd_onboard::wire::{MissionAction, MissionCommand, Uplink};
//! use skyherd_onboard::Task;
//!
//! /// A policy for the example: always "towards the goal".
//! struct Forward;
//! impl OnboardPolicy for Forward {
//!     fn act(&mut self, _task: Task, _features: &[f32; FEATURES]) -> [f32; 3] {
//!         [1.0, 0.0, 0.0]
//!     }
//! }
//!
//! // System id 1, herder 0 in the ground's snapshots.
//! let mut core = DaemonCore::new(CoreConfig::new(1, 0, Flavour::Px4), Forward);
//! assert_eq!(core.tick(Millis(0)).status, Status::Idle);
//! let start = MissionCommand {
//!     sequence: 1,
//!     task: Task::Driving,
//!     goal: [5.0, 5.0],
//!     goal_radius: 1.5,
//!     action: MissionAction::Start,
//! };
//! core.on_uplink(Millis(0), Uplink::Command(start));
//! // No autopilot heard yet: the core holds and says why.
//! assert!(matches!(core.tick(Millis(100)).status, Status::Holding(_)));
//! ```

use std::fmt;
use std::time::Duration;

use log::{info, warn};
use skyherd_link::Flavour;

use skyherd_onboard::Task;
use skyherd_onboard::actor::Actor;
use skyherd_onboard::frame::{ned_to_sim, sim_to_ned};
use skyherd_onboard::obs::{self, FEATURES, ObsError, ObsInput};
use skyherd_onboard::safety::{self, Braking, Limits, Reasons, Situation};
use skyherd_onboard::separation::{Peer, SeparationConfig, separate};
use skyherd_onboard::wire::{
    MissionAction, MissionCommand, Reassembler, Uplink, WireError, WorldSnapshot, decode_uplink,
};

/// The daemon's time: milliseconds since an arbitrary start (boot of the daemon, or the
/// autopilot's `time_boot_ms` in lockstep mode). Monotonic by contract of the caller.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Millis(pub u64);

impl Millis {
    /// The time from `earlier` to `self`, zero if `earlier` is later.
    pub fn since(self, earlier: Millis) -> Duration {
        Duration::from_millis(self.0.saturating_sub(earlier.0))
    }

    /// `span` later (whole milliseconds, saturating).
    pub fn after(self, span: Duration) -> Millis {
        Millis(
            self.0
                .saturating_add(span.as_millis().try_into().unwrap_or(u64::MAX)),
        )
    }
}

/// Tunables of the core. Times in milliseconds of the daemon's clock; speeds in m/s.
#[derive(Clone, Debug, PartialEq)]
pub struct CoreConfig {
    /// This drone's MAVLink system id (the autopilot's).
    pub system_id: u8,
    /// This drone's index in the world snapshots' herder list.
    pub herder_index: usize,
    /// Autopilot family.
    pub flavour: Flavour,
    /// Speed limit of this drone, m/s; the snapshot's limit applies too (the smaller wins).
    pub max_speed: f32,
    /// A world snapshot older than this is stale: hold.
    pub uplink_timeout: Duration,
    /// Nothing heard from the autopilot for this long: link lost, hold.
    pub autopilot_timeout: Duration,
    /// How long to stream setpoints before asking for the control mode (PX4 wants > 2 Hz for
    /// 1 s).
    pub stream_before_mode: Duration,
    /// Arm and mode requests are repeated this often until the autopilot reports them done.
    pub command_retry: Duration,
    /// Land after the uplink has been stale (older than [`uplink_timeout`](Self::uplink_timeout))
    /// continuously for this long while flying; `None`: hold for as long as it takes.
    pub land_after: Option<Duration>,
    /// Keep apart from the other drones of the snapshot (`skyherd_onboard::separation`), before
    /// the safety rules; `None`: off, the actor's request goes to the rules as it is.
    pub separation: Option<SeparationConfig>,
    /// Height to take off to before the actor flies, m above the autopilot's home (its local
    /// origin, NED z = 0 on the ground there).
    pub takeoff_altitude: f32,
    /// Climb speed of a takeoff on setpoints (PX4, or an ArduCopter already in the air), m/s.
    pub climb_speed: f32,
    /// Where the autopilot's local origin (its home: LOCAL_POSITION_NED (0, 0, 0)) lies in
    /// the ground's world frame, simulator frame (x east, y north), metres. Zero when the
    /// autopilot's local frame is the world's (the mock autopilots); a real autopilot's EKF
    /// origin is where it booted, which the ground's surveyed frame has to be told.
    pub local_origin: [f32; 2],
    /// How the vehicle brakes (`skyherd_onboard::safety::Braking`): the fence then keeps the
    /// stopping distance. `None`: the vehicle is taken to fly its setpoint at once.
    pub braking: Option<Braking>,
}

impl CoreConfig {
    /// Defaults for a drone: 5 m/s, uplink stale after 1 s (the ground sends at >= 5 Hz),
    /// autopilot lost after 1.5 s, 1.2 s of stream before the mode switch, retries every 1 s,
    /// landing after 10 s of stale uplink (11 s after the last snapshot), takeoff to 1 m at
    /// 0.7 m/s.
    pub fn new(system_id: u8, herder_index: usize, flavour: Flavour) -> Self {
        CoreConfig {
            system_id,
            herder_index,
            flavour,
            max_speed: 5.0,
            uplink_timeout: Duration::from_millis(1000),
            autopilot_timeout: Duration::from_millis(1500),
            stream_before_mode: Duration::from_millis(1200),
            command_retry: Duration::from_millis(1000),
            land_after: Some(Duration::from_secs(10)),
            separation: None,
            takeoff_altitude: 1.0,
            climb_speed: 0.7,
            local_origin: [0.0; 2],
            braking: None,
        }
    }
}

/// The learned actor as the core sees it: features in, normalised action out.
///
/// The daemon flies [`Actor`] (quantized, from a model file); tests may use anything.
pub trait OnboardPolicy {
    /// Normalised action, each component in [-1, 1], in the encoder's
    /// [`LocalFrame`](skyherd_onboard::obs::LocalFrame).
    fn act(&mut self, task: Task, features: &[f32; FEATURES]) -> [f32; 3];

    /// The encoder version whose features the policy reads; the daemon encodes only those
    /// ([`obs::encode_version`]), so a model for an older encoder does not pay for later ones.
    fn encoder_version(&self) -> u16 {
        obs::ENCODER_VERSION
    }
}

impl OnboardPolicy for Actor<'_> {
    fn act(&mut self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        self.infer(task, features)
    }

    fn encoder_version(&self) -> u16 {
        self.model().encoder_version
    }
}

/// A command for the autopilot; the shell turns it into a `COMMAND_LONG`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AutopilotCommand {
    /// `MAV_CMD_COMPONENT_ARM_DISARM`, param 1 = 1.
    Arm,
    /// `MAV_CMD_DO_SET_MODE`, param 1 = 1 (custom mode enabled), param 2 = `custom_main_mode`.
    SetMode {
        /// PX4 main mode or ArduPilot mode number.
        custom_main_mode: u8,
    },
    /// `MAV_CMD_NAV_LAND`: land where you are (the autopilot's LAND mode, disarm on touchdown).
    Land,
    /// `MAV_CMD_NAV_TAKEOFF` to `altitude_m` above home (ArduPilot, in GUIDED, armed, landed).
    Takeoff {
        /// Metres above home.
        altitude_m: f32,
    },
}

/// A velocity setpoint for `SET_POSITION_TARGET_LOCAL_NED` (type_mask 0x0DC7).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Setpoint {
    /// Velocity `[north, east, down]`, m/s, `MAV_FRAME_LOCAL_NED`.
    pub velocity_ned: [f32; 3],
}

impl Setpoint {
    /// Zero velocity: hover where you are.
    pub const HOLD: Setpoint = Setpoint {
        velocity_ned: [0.0; 3],
    };
}

/// Where the mission start sequence stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preparing {
    /// Waiting for the autopilot to report armed.
    Arming,
    /// Armed; streaming setpoints long enough for the mode switch to be accepted.
    Streaming,
    /// Waiting for the autopilot to report the control mode.
    SwitchingMode,
    /// Under control, climbing to the takeoff altitude.
    TakingOff,
}

/// A takeoff is over this close (m) below [`CoreConfig::takeoff_altitude`] (ArduCopter's
/// settles 0.03 m short of it).
pub const TAKEOFF_TOLERANCE_M: f32 = 0.1;

/// Below this height (m above home) the vehicle is on the ground: ArduPilot takes off with
/// `MAV_CMD_NAV_TAKEOFF` from here, and a disarm here before the takeoff is the autopilot's.
pub const ON_GROUND_M: f32 = 0.3;

/// Why the core sends zero-velocity setpoints instead of the actor's.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HoldReason {
    /// Nothing heard from the autopilot within [`CoreConfig::autopilot_timeout`].
    AutopilotLost,
    /// No LOCAL_POSITION_NED yet, or none within the autopilot timeout.
    NoPosition,
    /// No world snapshot since the mission started.
    NoSnapshot,
    /// The newest snapshot is older than [`CoreConfig::uplink_timeout`].
    UplinkStale {
        /// Age of the newest snapshot, ms.
        age_ms: u64,
    },
    /// The ground aborted the mission.
    Aborted,
    /// The ground reported the task done.
    Complete,
    /// Someone else disarmed the vehicle or switched it out of the control mode while the
    /// autopilot link was healthy: the pilot has it, the daemon does not take it back until
    /// the next start command.
    ControlReleased,
    /// The snapshot could not be encoded (NaN, bad geometry, own index out of range).
    BadObservation(ObsError),
    /// The safety rules dropped the request (stale or non-finite data, unusable limits).
    Safety(Reasons),
}

impl fmt::Display for HoldReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            HoldReason::AutopilotLost => f.write_str("autopilot link lost"),
            HoldReason::NoPosition => f.write_str("no fresh position from the autopilot"),
            HoldReason::NoSnapshot => f.write_str("no world snapshot yet"),
            HoldReason::UplinkStale { age_ms } => {
                write!(f, "uplink stale (newest snapshot {age_ms} ms old)")
            }
            HoldReason::Aborted => f.write_str("mission aborted by the ground"),
            HoldReason::Complete => f.write_str("mission complete"),
            HoldReason::ControlReleased => {
                f.write_str("control taken away (disarmed or mode changed by someone else)")
            }
            HoldReason::BadObservation(e) => write!(f, "bad observation: {e}"),
            HoldReason::Safety(reasons) => write!(f, "safety: {reasons}"),
        }
    }
}

/// Why the core gave up on the mission and landed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LandReason {
    /// The uplink stayed stale for [`CoreConfig::land_after`] in flight: no snapshot for
    /// `silent_ms` when the landing began.
    GroundSilent {
        /// Age of the newest snapshot when the core decided to land, ms.
        silent_ms: u64,
    },
}

impl fmt::Display for LandReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LandReason::GroundSilent { silent_ms } => {
                write!(f, "ground silent for {:.1} s", *silent_ms as f64 / 1000.0)
            }
        }
    }
}

/// What the core is doing, as of the last tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Status {
    /// No mission yet: no setpoints, no commands.
    Idle,
    /// Mission started; bringing the autopilot under control.
    Preparing(Preparing),
    /// Flying the actor's velocity, after the safety rules; the rules that changed it, if any
    /// (fence, altitude, speed).
    Flying(Reasons),
    /// Sending zero-velocity setpoints.
    Holding(HoldReason),
    /// Landing: no setpoints, `MAV_CMD_NAV_LAND` until the autopilot has taken over.
    Landing(LandReason),
}

impl Status {
    /// Whether two statuses say the same thing to an operator: a stale hold's age and the
    /// safety trims while flying change every tick without being news.
    pub fn same_kind(&self, other: &Status) -> bool {
        same_kind(self, other)
    }

    /// Whether the core is holding.
    pub fn is_hold(&self) -> bool {
        matches!(self, Status::Holding(_))
    }

    /// Whether an operator should be warned: a hold, or a landing the ground did not ask for.
    pub fn is_warning(&self) -> bool {
        matches!(self, Status::Holding(_) | Status::Landing(_))
    }
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Status::Idle => f.write_str("idle"),
            Status::Preparing(p) => write!(f, "preparing ({p:?})"),
            Status::Flying(reasons) if reasons.is_empty() => f.write_str("flying"),
            Status::Flying(reasons) => write!(f, "flying ({reasons})"),
            Status::Holding(r) => write!(f, "holding: {r}"),
            Status::Landing(r) => write!(f, "landing: {r}"),
        }
    }
}

/// What to send after one control tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ControlOutput {
    /// The setpoint to stream, if any (none while idle).
    pub setpoint: Option<Setpoint>,
    /// A command for the autopilot, if one is due.
    pub command: Option<AutopilotCommand>,
    /// What the core is doing and why.
    pub status: Status,
}

/// Counts of what the core has seen, for logs and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CoreCounters {
    /// Control ticks run.
    pub ticks: u64,
    /// Ticks that ended in a hold.
    pub hold_ticks: u64,
    /// World snapshots accepted.
    pub snapshots: u64,
    /// Snapshots dropped because their sequence number was not newer.
    pub stale_snapshots: u64,
    /// Mission commands accepted.
    pub mission_commands: u64,
    /// Mission commands dropped because their sequence number was not newer (repeats).
    pub repeated_commands: u64,
    /// Uplink chunks taken by the reassembler.
    pub chunks: u64,
    /// Chunks refused (bad header, stale message id) and messages dropped (CRC, decode).
    pub bad_chunks: u64,
    /// Times the ground's message ids went back after a silence (a ground restart).
    pub ground_restarts: u64,
    /// Autopilot commands issued.
    pub commands_sent: u64,
    /// Landings begun because the ground went silent.
    pub landings: u64,
}

/// How long after an accepted arm or mode command a heartbeat contradicting it is taken for
/// one sent before the command (1.5 heartbeat periods at 1 Hz), ms.
pub const COMMAND_ACCEPTED_GRACE: Duration = Duration::from_millis(1500);

/// What the autopilot last told us.
#[derive(Clone, Copy, Debug, Default)]
struct AutopilotView {
    last_heard: Option<Millis>,
    armed: bool,
    in_control_mode: bool,
    /// When the autopilot last accepted our arm / mode command (see `on_command_accepted`).
    arm_accepted_at: Option<Millis>,
    mode_accepted_at: Option<Millis>,
    /// Own position, simulator frame, and when it arrived.
    position: Option<([f32; 3], Millis)>,
    /// Own velocity from the last two positions, m/s, simulator frame.
    velocity: [f32; 3],
}

#[derive(Clone, Copy, Debug)]
struct ActiveMission {
    task: Task,
    goal: [f32; 2],
    goal_radius: f32,
    streaming_since: Option<Millis>,
    last_arm_request: Option<Millis>,
    last_mode_request: Option<Millis>,
    /// The autopilot has been armed and in the control mode under this mission.
    engaged: bool,
    /// The takeoff is over: the actor flies.
    airborne: bool,
    last_takeoff_request: Option<Millis>,
    /// The autopilot accepted `MAV_CMD_NAV_TAKEOFF`: it climbs on its own.
    takeoff_accepted: bool,
    released: bool,
    /// The autopilot link dropped during the mission; cleared on the first healthy tick.
    link_was_lost: bool,
}

/// A landing in progress; see the module docs ("When the ground dies").
#[derive(Clone, Copy, Debug)]
struct Landing {
    reason: LandReason,
    last_request: Option<Millis>,
    /// The autopilot acknowledged `MAV_CMD_NAV_LAND` with ACCEPTED.
    accepted: bool,
}

#[derive(Clone, Copy, Debug)]
enum Mission {
    Idle,
    Active(ActiveMission),
    /// Ended by the ground (aborted or complete): hold with this reason until a new start.
    Ended(HoldReason),
    /// Given up without the ground: landing, until a new start.
    Landing(Landing),
}

/// The daemon's decision core. See the [module docs](self).
pub struct DaemonCore<P> {
    config: CoreConfig,
    policy: P,
    autopilot: AutopilotView,
    world: Option<(WorldSnapshot, Millis)>,
    last_command: Option<u32>,
    reassembler: Box<Reassembler>,
    last_message_at: Option<Millis>,
    mission: Mission,
    last_status: Status,
    counters: CoreCounters,
    // Scratch buffers reused every tick so flying allocates nothing after warm-up.
    herders: Vec<[f32; 3]>,
    features: [f32; FEATURES],
    /// The other drones' velocities between the last two snapshots, by herder index.
    peer_velocities: Vec<[f32; 3]>,
    /// Scratch for the separation rule's peers.
    peers: Vec<Peer>,
}

impl<P: OnboardPolicy> DaemonCore<P> {
    /// A core with no mission, no world and no autopilot heard yet.
    pub fn new(config: CoreConfig, policy: P) -> Self {
        DaemonCore {
            config,
            policy,
            autopilot: AutopilotView::default(),
            world: None,
            last_command: None,
            reassembler: Box::new(Reassembler::new()),
            last_message_at: None,
            mission: Mission::Idle,
            last_status: Status::Idle,
            counters: CoreCounters::default(),
            herders: Vec::new(),
            features: [0.0; FEATURES],
            peer_velocities: Vec::new(),
            peers: Vec::new(),
        }
    }

    /// The configuration the core runs with.
    pub fn config(&self) -> &CoreConfig {
        &self.config
    }

    /// Status as of the last tick.
    pub fn status(&self) -> Status {
        self.last_status
    }

    /// What the core has counted so far.
    pub fn counters(&self) -> CoreCounters {
        self.counters
    }

    /// Whether the last tick steered on the world snapshot (flying, or held by a safety rule
    /// that reads it): then which snapshot the next tick sees changes what it sends. Not
    /// while idle, preparing, landing, or holding for a reason of the mission's (complete,
    /// aborted, uplink stale).
    pub fn steers_on_snapshots(&self) -> bool {
        matches!(
            self.status(),
            Status::Flying(_) | Status::Holding(HoldReason::Safety(_))
        )
    }

    /// Lockstep: the snapshot stamped `now` counts as heard at `now`. The simulator sends it
    /// before the positions of that instant, but the two links' reader threads may deliver it
    /// just before or just after the position; without this its age (which the separation
    /// and safety rules read) would depend on which came first.
    pub fn heard_snapshot_at(&mut self, now: Millis) {
        if let Some((snapshot, received)) = self.world.as_mut()
            && snapshot.timestamp_ms.abs_diff(now.0) <= 1
        {
            *received = now;
        }
    }

    /// Ground timestamp (ms) of the newest world snapshot accepted, if any.
    pub fn snapshot_timestamp_ms(&self) -> Option<u64> {
        self.world
            .as_ref()
            .map(|(snapshot, _)| snapshot.timestamp_ms)
    }

    /// Own position (simulator frame, metres) as last reported by the autopilot.
    pub fn own_position(&self) -> Option<[f32; 3]> {
        self.autopilot.position.map(|(p, _)| p)
    }

    /// An autopilot HEARTBEAT: `base_mode` (MAV_MODE_FLAG bits; 0x80 = armed) and
    /// `custom_mode` as sent.
    pub fn on_heartbeat(&mut self, now: Millis, base_mode: u8, custom_mode: u32) {
        const SAFETY_ARMED: u8 = 0x80;
        let armed = base_mode & SAFETY_ARMED != 0;
        let in_mode = self.config.flavour.is_control_mode(custom_mode);
        if armed != self.autopilot.armed || in_mode != self.autopilot.in_control_mode {
            info!(
                "autopilot now {}, {} {}",
                if armed { "armed" } else { "disarmed" },
                if in_mode { "in" } else { "not in" },
                self.config.flavour.control_mode_name()
            );
        }
        // A heartbeat sent before the autopilot accepted our command can arrive after its
        // acknowledgement; within the grace period it does not undo what was acknowledged.
        let fresh = |accepted: Option<Millis>| {
            accepted.is_none_or(|at| now.since(at) > COMMAND_ACCEPTED_GRACE)
        };
        if armed || fresh(self.autopilot.arm_accepted_at) {
            self.autopilot.armed = armed;
        }
        if in_mode || fresh(self.autopilot.mode_accepted_at) {
            self.autopilot.in_control_mode = in_mode;
        }
        self.autopilot.last_heard = Some(now);
    }

    /// The autopilot accepted one of our commands (COMMAND_ACK with MAV_RESULT_ACCEPTED): it
    /// is armed, or in the control mode, from now, instead of from its next HEARTBEAT (up to a
    /// second later at 1 Hz, a second the drones would hover after takeoff). Heartbeats stay
    /// the authority: one that says otherwise after [`COMMAND_ACCEPTED_GRACE`] (a pilot's
    /// switch away, a disarm) wins. (The ACK names no requester in the dialect as built, so a
    /// forwarded ACK of another client's mode switch could pass for ours; the autopilot then
    /// ignores our setpoints anyway, and the release is noticed one grace period later.)
    pub fn on_command_accepted(&mut self, now: Millis, command: AutopilotCommand) {
        match command {
            AutopilotCommand::Arm => {
                self.autopilot.armed = true;
                self.autopilot.arm_accepted_at = Some(now);
            }
            AutopilotCommand::SetMode { custom_main_mode }
                if custom_main_mode == self.config.flavour.control_mode() =>
            {
                self.autopilot.in_control_mode = true;
                self.autopilot.mode_accepted_at = Some(now);
            }
            AutopilotCommand::SetMode { .. } => {}
            AutopilotCommand::Land => {
                if let Mission::Landing(landing) = &mut self.mission {
                    landing.accepted = true;
                }
            }
            AutopilotCommand::Takeoff { .. } => {
                if let Mission::Active(mission) = &mut self.mission {
                    mission.takeoff_accepted = true;
                }
            }
        }
    }

    /// An autopilot LOCAL_POSITION_NED: position `[north, east, down]`, metres, from the
    /// autopilot's local origin (moved into the world frame by [`CoreConfig::local_origin`]).
    pub fn on_local_position(&mut self, now: Millis, position_ned: [f32; 3]) {
        self.autopilot.last_heard = Some(now);
        if position_ned.iter().all(|x| x.is_finite()) {
            let local = ned_to_sim(position_ned);
            let [east, north] = self.config.local_origin;
            let position = [local[0] + east, local[1] + north, local[2]];
            self.autopilot.velocity = match self.autopilot.position {
                Some((before, at)) => finite_difference(before, position, now.since(at)),
                None => [0.0; 3],
            };
            self.autopilot.position = Some((position, now));
        } else {
            warn!("ignoring non-finite LOCAL_POSITION_NED {position_ned:?}");
        }
    }

    /// One uplink TUNNEL payload (a [`wire`](skyherd_onboard::wire) chunk). A chunk that completes a
    /// message delivers it to [`on_uplink`](Self::on_uplink). Bad chunks and messages are
    /// counted, logged and dropped; the error says why.
    pub fn on_tunnel_payload(&mut self, now: Millis, chunk: &[u8]) -> Result<(), WireError> {
        self.counters.chunks += 1;
        let mut pushed = push_and_decode(&mut self.reassembler, chunk);
        if let Err(WireError::Stale { message_id }) = pushed
            && self.uplink_silent(now)
        {
            // Only old ids for longer than the uplink timeout: the ground restarted and counts
            // from scratch. Start over with it rather than stay deaf.
            warn!("uplink: message ids restarted at {message_id}; assuming a ground restart");
            self.counters.ground_restarts += 1;
            self.reassembler.reset();
            self.last_command = None;
            self.world = None;
            pushed = push_and_decode(&mut self.reassembler, chunk);
        }
        match pushed {
            Ok(None) => Ok(()),
            Ok(Some(message)) => {
                self.last_message_at = Some(now);
                self.on_uplink(now, message);
                Ok(())
            }
            Err(e) => {
                self.counters.bad_chunks += 1;
                log::debug!("uplink chunk dropped: {e}");
                Err(e)
            }
        }
    }

    /// No whole uplink message for longer than the uplink timeout.
    fn uplink_silent(&self, now: Millis) -> bool {
        self.last_message_at
            .is_none_or(|t| now.since(t) > self.config.uplink_timeout)
    }

    /// A decoded uplink message from the ground.
    pub fn on_uplink(&mut self, now: Millis, message: Uplink) {
        match message {
            Uplink::Snapshot(snapshot) => self.on_snapshot(now, snapshot),
            Uplink::Command(command) => self.on_command(command),
        }
    }

    fn on_snapshot(&mut self, now: Millis, snapshot: WorldSnapshot) {
        if let Some((newest, _)) = &self.world
            && snapshot.sequence <= newest.sequence
        {
            self.counters.stale_snapshots += 1;
            return;
        }
        self.counters.snapshots += 1;
        // The other drones' velocities, from this snapshot and the one before (ground clock).
        self.peer_velocities.clear();
        if let Some((before, _)) = &self.world {
            let dt =
                Duration::from_millis(snapshot.timestamp_ms.saturating_sub(before.timestamp_ms));
            for (i, p) in snapshot.herders.iter().enumerate() {
                let v = before
                    .herders
                    .get(i)
                    .map_or([0.0; 3], |b| finite_difference(*b, *p, dt));
                self.peer_velocities.push(v);
            }
        }
        self.world = Some((snapshot, now));
    }

    fn on_command(&mut self, command: MissionCommand) {
        // The ground repeats commands over a lossy link; only a newer one changes anything (a
        // repeated start must not undo a pilot's takeover).
        if self
            .last_command
            .is_some_and(|last| command.sequence <= last)
        {
            self.counters.repeated_commands += 1;
            return;
        }
        self.last_command = Some(command.sequence);
        self.counters.mission_commands += 1;
        match command.action {
            MissionAction::Start => {
                let MissionCommand {
                    task,
                    goal,
                    goal_radius,
                    ..
                } = command;
                info!(
                    "mission start: {task:?} to goal ({:.1}, {:.1}) r {goal_radius:.2} m",
                    goal[0], goal[1]
                );
                self.mission = Mission::Active(ActiveMission {
                    task,
                    goal,
                    goal_radius,
                    streaming_since: None,
                    last_arm_request: None,
                    last_mode_request: None,
                    engaged: false,
                    airborne: false,
                    last_takeoff_request: None,
                    takeoff_accepted: false,
                    released: false,
                    link_was_lost: false,
                });
            }
            // A landing is not called off by the ground (see the module docs); it was
            // going to end the mission anyway.
            MissionAction::Abort | MissionAction::Complete
                if matches!(self.mission, Mission::Landing(_)) =>
            {
                info!("mission {:?} while landing: landing on", command.action);
            }
            MissionAction::Abort => {
                info!("mission abort: holding");
                self.mission = Mission::Ended(HoldReason::Aborted);
            }
            MissionAction::Complete => {
                info!("mission complete: holding");
                self.mission = Mission::Ended(HoldReason::Complete);
            }
        }
    }

    /// One control tick at `now`: what to send. Call at the control rate (>= 10 Hz).
    pub fn tick(&mut self, now: Millis) -> ControlOutput {
        self.counters.ticks += 1;
        let decision = self.decide(now);
        if decision.command.is_some() {
            self.counters.commands_sent += 1;
        }
        if matches!(decision.status, Status::Holding(_)) {
            self.counters.hold_ticks += 1;
        }
        if !same_kind(&decision.status, &self.last_status) {
            if decision.status.is_warning() {
                warn!("{}", decision.status);
            } else {
                info!("{}", decision.status);
            }
        }
        self.last_status = decision.status;
        decision
    }

    fn decide(&mut self, now: Millis) -> ControlOutput {
        let hold = |reason| ControlOutput {
            setpoint: Some(Setpoint::HOLD),
            command: None,
            status: Status::Holding(reason),
        };
        let link_ok = self
            .autopilot
            .last_heard
            .is_some_and(|t| now.since(t) <= self.config.autopilot_timeout);
        let given_up = self.ground_given_up(now);
        let mission = match &mut self.mission {
            Mission::Idle => {
                return ControlOutput {
                    setpoint: None,
                    command: None,
                    status: Status::Idle,
                };
            }
            Mission::Ended(reason) => return hold(*reason),
            Mission::Landing(landing) => {
                // Until the autopilot has taken over (left the control mode, or disarmed on
                // the ground), ask again every retry period; after that, it flies.
                let retry = self.config.command_retry;
                let due = link_ok
                    && !landing.accepted
                    && self.autopilot.armed
                    && self.autopilot.in_control_mode
                    && landing.last_request.is_none_or(|t| now.since(t) >= retry);
                if due {
                    landing.last_request = Some(now);
                }
                return ControlOutput {
                    setpoint: None,
                    command: due.then_some(AutopilotCommand::Land),
                    status: Status::Landing(landing.reason),
                };
            }
            Mission::Active(mission) => mission,
        };
        if !link_ok {
            mission.link_was_lost = true;
            return hold(HoldReason::AutopilotLost);
        }
        let in_control = self.autopilot.armed && self.autopilot.in_control_mode;
        if mission.link_was_lost {
            mission.link_was_lost = false;
            if mission.engaged && !in_control {
                // The autopilot's own failsafe took over while it could not hear us; that was
                // not a pilot's decision, so bring it back under control.
                info!("autopilot link back; re-engaging after its failsafe");
                mission.engaged = false;
                mission.streaming_since = None;
            }
        }
        let height = self.autopilot.position.map(|(p, _)| p[2]);
        let on_ground = height.is_some_and(|h| h < ON_GROUND_M);
        if mission.engaged && !in_control {
            if !mission.airborne && !self.autopilot.armed && on_ground {
                // Disarmed on the ground before the takeoff: the autopilot's own timeout
                // (PX4 COM_DISARM_PRFLT, ArduCopter DISARM_DELAY), not a pilot. Start over.
                info!("autopilot disarmed on the ground before the takeoff: arming again");
                mission.engaged = false;
                mission.streaming_since = None;
                mission.takeoff_accepted = false;
                mission.last_takeoff_request = None;
            } else {
                mission.released = true;
            }
        }
        if mission.released {
            return hold(HoldReason::ControlReleased);
        }
        let streaming_since = *mission.streaming_since.get_or_insert(now);
        let retry = self.config.command_retry;
        let due = |last: Option<Millis>| last.is_none_or(|t| now.since(t) >= retry);
        if !in_control {
            let by_command = self.config.flavour.takes_off_by_command();
            let in_mode = self.autopilot.in_control_mode;
            let mode_request = |mission: &mut ActiveMission| {
                due(mission.last_mode_request).then(|| {
                    mission.last_mode_request = Some(now);
                    AutopilotCommand::SetMode {
                        custom_main_mode: self.config.flavour.control_mode(),
                    }
                })
            };
            let (command, step) = if by_command && !in_mode {
                // ArduCopter: GUIDED first, so that the takeoff can follow the arming at once.
                (mode_request(mission), Preparing::SwitchingMode)
            } else if !self.autopilot.armed {
                let command = due(mission.last_arm_request).then(|| {
                    mission.last_arm_request = Some(now);
                    AutopilotCommand::Arm
                });
                (command, Preparing::Arming)
            } else if now.since(streaming_since) < self.config.stream_before_mode {
                (None, Preparing::Streaming)
            } else {
                (mode_request(mission), Preparing::SwitchingMode)
            };
            return ControlOutput {
                setpoint: Some(Setpoint::HOLD),
                command,
                status: Status::Preparing(step),
            };
        }
        mission.engaged = true;
        if !mission.airborne {
            let Some(height) = height else {
                return hold(HoldReason::NoPosition);
            };
            if height >= self.config.takeoff_altitude - TAKEOFF_TOLERANCE_M {
                info!("airborne at {height:.2} m: flying the mission");
                mission.airborne = true;
            } else if self.config.flavour.takes_off_by_command() && on_ground {
                // ArduCopter climbs on NAV_TAKEOFF by itself; a setpoint now would end it.
                let command = (!mission.takeoff_accepted && due(mission.last_takeoff_request))
                    .then(|| {
                        mission.last_takeoff_request = Some(now);
                        AutopilotCommand::Takeoff {
                            altitude_m: self.config.takeoff_altitude,
                        }
                    });
                return ControlOutput {
                    setpoint: None,
                    command,
                    status: Status::Preparing(Preparing::TakingOff),
                };
            } else if !(self.config.flavour.takes_off_by_command() && mission.takeoff_accepted) {
                // Climb on setpoints: PX4 OFFBOARD lifts off on them; in the air they work
                // for both.
                let climb = self.config.climb_speed.min(self.config.max_speed);
                return ControlOutput {
                    setpoint: Some(Setpoint {
                        velocity_ned: [0.0, 0.0, -climb],
                    }),
                    command: None,
                    status: Status::Preparing(Preparing::TakingOff),
                };
            } else {
                // ArduCopter's own takeoff, under way above the ground.
                return ControlOutput {
                    setpoint: None,
                    command: None,
                    status: Status::Preparing(Preparing::TakingOff),
                };
            }
        }
        if let Some(reason) = given_up {
            warn!("uplink stale for longer than the land-after time in flight: landing");
            self.counters.landings += 1;
            self.mission = Mission::Landing(Landing {
                reason,
                last_request: None,
                accepted: false,
            });
            return self.decide(now);
        }
        let mission = *mission;
        let (setpoint, status) = self.fly(now, &mission);
        ControlOutput {
            setpoint: Some(setpoint),
            command: None,
            status,
        }
    }

    /// In flight: whether the uplink has been stale for longer than
    /// [`CoreConfig::land_after`], and how long the ground has been silent. (Without any
    /// snapshot there is no flight to give up: the drone never flew the mission.)
    fn ground_given_up(&self, now: Millis) -> Option<LandReason> {
        let land_after = self.config.land_after?;
        let (_, received) = self.world.as_ref()?;
        let silent = now.since(*received);
        let stale_for = silent.checked_sub(self.config.uplink_timeout)?;
        (stale_for > land_after).then(|| LandReason::GroundSilent {
            silent_ms: u64::try_from(silent.as_millis()).unwrap_or(u64::MAX),
        })
    }

    /// The actor's velocity through the safety rules, or a hold and why.
    fn fly(&mut self, now: Millis, mission: &ActiveMission) -> (Setpoint, Status) {
        let hold = |reason| (Setpoint::HOLD, Status::Holding(reason));
        let own = match self.autopilot.position {
            Some((p, at)) if now.since(at) <= self.config.autopilot_timeout => p,
            _ => return hold(HoldReason::NoPosition),
        };
        let Some((world, received)) = self.world.as_ref() else {
            return hold(HoldReason::NoSnapshot);
        };
        let age = now.since(*received);
        let age_ms = u64::try_from(age.as_millis()).unwrap_or(u64::MAX);
        let max_speed = self.config.max_speed.min(world.max_speed);
        let mut limits = Limits::arena(world.area, max_speed);
        limits.braking = self.config.braking;
        limits.max_snapshot_age_s = self.config.uplink_timeout.as_millis() as f32 / 1000.0;
        // The actor learned to herd from as low as the ground; this drone may not fly below
        // its altitude band, so it reads its height above the band's floor (feature 22): held
        // at the floor, it is as low as it can go, as the actor expects. Only the encoding
        // sees this; the safety rules below get the true position.
        let encoded_own = [own[0], own[1], (own[2] - limits.fence_min[2]).max(0.0)];
        // Own entry replaced by the autopilot's position, which is fresher than the ground's
        // track; appended if the ground does not track this drone yet.
        self.herders.clear();
        self.herders.extend_from_slice(&world.herders);
        let own_index = if self.config.herder_index < self.herders.len() {
            self.herders[self.config.herder_index] = encoded_own;
            self.config.herder_index
        } else {
            self.herders.push(encoded_own);
            self.herders.len() - 1
        };
        let (request, own_reason) = if age > self.config.uplink_timeout {
            ([0.0; 3], Some(HoldReason::UplinkStale { age_ms }))
        } else {
            let input = ObsInput {
                own_index,
                herders: &self.herders,
                targets: &world.targets,
                goal: mission.goal,
                goal_radius: mission.goal_radius,
                area: world.area,
                max_speed,
            };
            match obs::encode_version(&input, self.policy.encoder_version(), &mut self.features) {
                Ok(frame) => {
                    let action = self.policy.act(mission.task, &self.features);
                    (frame.action_to_world(action), None)
                }
                Err(e) => ([0.0; 3], Some(HoldReason::BadObservation(e))),
            }
        };
        // Keep apart from the other drones first; the safety rules still have the last word.
        let request = match &self.config.separation {
            Some(separation) if own_reason.is_none() => {
                self.peers.clear();
                for (i, p) in world.herders.iter().enumerate() {
                    if i != self.config.herder_index {
                        let velocity = self.peer_velocities.get(i).copied().unwrap_or([0.0; 3]);
                        self.peers.push(Peer {
                            position: *p,
                            velocity,
                            age_s: age_ms as f32 / 1000.0,
                        });
                    }
                }
                let own_velocity = self.autopilot.velocity;
                // The flight rules below hold it in the altitude band: the rule must not count
                // on a descent through the floor.
                let separation = separation.within(&limits);
                separate(&separation, own, own_velocity, request, &self.peers).velocity
            }
            _ => request,
        };
        let checked = safety::check(
            &limits,
            &Situation {
                position: own,
                velocity: request,
                snapshot_age_s: age_ms as f32 / 1000.0,
                snapshot_finite: world.is_finite(),
                current_velocity: Some(self.autopilot.velocity),
            },
        );
        // Even a hold goes through the rules: outside the fence they steer back in.
        let setpoint = Setpoint {
            velocity_ned: sim_to_ned(checked.velocity),
        };
        let status = match own_reason {
            Some(reason) => Status::Holding(reason),
            None if checked.hold => Status::Holding(HoldReason::Safety(checked.reasons)),
            None => Status::Flying(checked.reasons),
        };
        (setpoint, status)
    }
}

/// `(after - before) / dt` in m/s, zero when `dt` is not a usable interval (0, or over 2 s).
fn finite_difference(before: [f32; 3], after: [f32; 3], dt: Duration) -> [f32; 3] {
    let dt = dt.as_secs_f32();
    if !(dt > 0.0 && dt <= 2.0) {
        return [0.0; 3];
    }
    let v = [
        (after[0] - before[0]) / dt,
        (after[1] - before[1]) / dt,
        (after[2] - before[2]) / dt,
    ];
    if v.iter().all(|c| c.is_finite()) {
        v
    } else {
        [0.0; 3]
    }
}

/// One chunk into the reassembler; the message it completes, decoded.
fn push_and_decode(
    reassembler: &mut Reassembler,
    chunk: &[u8],
) -> Result<Option<Uplink>, WireError> {
    match reassembler.push(chunk)? {
        Some(message) => decode_uplink(message).map(Some),
        None => Ok(None),
    }
}

/// Whether two statuses are the same for logging purposes (a hold's age changes every tick).
fn same_kind(a: &Status, b: &Status) -> bool {
    match (a, b) {
        (
            Status::Holding(HoldReason::UplinkStale { .. }),
            Status::Holding(HoldReason::UplinkStale { .. }),
        ) => true,
        _ => a == b,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ID: u8 = 7;
    const ARMED: u8 = 0x80;
    const PX4_OFFBOARD: u32 = 6 << 16;
    /// PX4 POSCTL (main mode 3): what a pilot switches to.
    const PX4_POSCTL: u32 = 3 << 16;

    /// Always "full speed along the local first axis", i.e. from the flock towards the goal.
    struct TowardsGoal;
    impl OnboardPolicy for TowardsGoal {
        fn act(&mut self, _task: Task, _features: &[f32; FEATURES]) -> [f32; 3] {
            [1.0, 0.0, 0.0]
        }
    }

    fn command(sequence: u32, action: MissionAction) -> Uplink {
        Uplink::Command(MissionCommand {
            sequence,
            task: Task::Driving,
            goal: [50.0, 90.0],
            goal_radius: 5.0,
            action,
        })
    }

    fn start() -> Uplink {
        command(1, MissionAction::Start)
    }

    fn world(seq: u32) -> WorldSnapshot {
        let mut w = WorldSnapshot::empty(Task::Driving, [100.0, 100.0, 10.0]);
        w.sequence = seq;
        w.goal = [50.0, 90.0];
        w.goal_radius = 5.0;
        // Herder 0 is another drone; herder 1 is us, where the ground last saw us (replaced).
        w.herders
            .extend_from_slice(&[[60.0, 30.0, 2.0], [0.0, 0.0, 0.0]])
            .unwrap();
        w.targets
            .extend_from_slice(&[[49.0, 40.0], [51.0, 40.0], [50.0, 41.0], [50.0, 39.0]])
            .unwrap();
        w
    }

    /// Flock at (50, 40), goal due north at (50, 90); this drone at (45, 30), another at (60, 30).
    fn snapshot(seq: u32) -> Uplink {
        Uplink::Snapshot(world(seq))
    }

    fn core(flavour: Flavour) -> DaemonCore<TowardsGoal> {
        DaemonCore::new(CoreConfig::new(ID, 1, flavour), TowardsGoal)
    }

    /// Feeds the autopilot's view at `t` ms: heartbeat and position (NED of sim (45, 30, 2)).
    fn autopilot<P: OnboardPolicy>(
        core: &mut DaemonCore<P>,
        t: u64,
        armed: bool,
        custom_mode: u32,
    ) {
        core.on_heartbeat(Millis(t), if armed { ARMED } else { 0 }, custom_mode);
        core.on_local_position(Millis(t), sim_to_ned([45.0, 30.0, 2.0]));
    }

    /// A PX4 core driven through start to flying; returns it and the time reached (ms).
    fn flying() -> (DaemonCore<TowardsGoal>, u64) {
        flying_with(CoreConfig::new(ID, 1, Flavour::Px4))
    }

    /// The same with `config`.
    fn flying_with(config: CoreConfig) -> (DaemonCore<TowardsGoal>, u64) {
        let mut c = DaemonCore::new(config, TowardsGoal);
        autopilot(&mut c, 0, true, PX4_OFFBOARD);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        let d = c.tick(Millis(0));
        assert_eq!(d.status, Status::Flying(Reasons::NONE));
        (c, 0)
    }

    #[test]
    fn idle_sends_nothing() {
        let mut c = core(Flavour::Px4);
        autopilot(&mut c, 0, false, 0);
        let d = c.tick(Millis(100));
        assert_eq!(
            d,
            ControlOutput {
                setpoint: None,
                command: None,
                status: Status::Idle
            }
        );
    }

    #[test]
    fn px4_start_streams_arms_then_switches_to_offboard_and_flies() {
        let mut c = core(Flavour::Px4);
        autopilot(&mut c, 0, false, 0);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));

        let d = c.tick(Millis(0));
        assert_eq!(d.status, Status::Preparing(Preparing::Arming));
        assert_eq!(d.command, Some(AutopilotCommand::Arm));
        assert_eq!(d.setpoint, Some(Setpoint::HOLD));
        // Not repeated before the retry period...
        autopilot(&mut c, 500, false, 0);
        assert_eq!(c.tick(Millis(500)).command, None);
        // ...but after it.
        c.on_uplink(Millis(1000), snapshot(2));
        autopilot(&mut c, 1000, false, 0);
        assert_eq!(c.tick(Millis(1000)).command, Some(AutopilotCommand::Arm));

        // Armed, but the stream has run only 1.1 s of the 1.2 s PX4 wants.
        autopilot(&mut c, 1100, true, 0);
        let d = c.tick(Millis(1100));
        assert_eq!(d.status, Status::Preparing(Preparing::Streaming));
        assert_eq!((d.command, d.setpoint), (None, Some(Setpoint::HOLD)));

        autopilot(&mut c, 1200, true, 0);
        let d = c.tick(Millis(1200));
        assert_eq!(d.status, Status::Preparing(Preparing::SwitchingMode));
        assert_eq!(
            d.command,
            Some(AutopilotCommand::SetMode {
                custom_main_mode: 6
            })
        );

        c.on_uplink(Millis(1300), snapshot(3));
        autopilot(&mut c, 1300, true, PX4_OFFBOARD);
        let d = c.tick(Millis(1300));
        assert_eq!(d.status, Status::Flying(Reasons::NONE));
        assert_eq!(d.command, None);
    }

    #[test]
    fn accepted_commands_count_before_the_next_heartbeat_and_stale_ones_do_not_undo_them() {
        let mut c = core(Flavour::Px4);
        autopilot(&mut c, 0, false, 0);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        assert_eq!(c.tick(Millis(0)).command, Some(AutopilotCommand::Arm));
        // The ACK arrives; the heartbeat that still says "disarmed" was sent before it.
        c.on_command_accepted(Millis(100), AutopilotCommand::Arm);
        autopilot(&mut c, 100, false, 0);
        assert_eq!(
            c.tick(Millis(100)).status,
            Status::Preparing(Preparing::Streaming)
        );
        // After 1.2 s of stream: the mode switch, accepted, flies at once.
        autopilot(&mut c, 1200, true, 0);
        let d = c.tick(Millis(1200));
        assert_eq!(
            d.command,
            Some(AutopilotCommand::SetMode {
                custom_main_mode: 6
            })
        );
        c.on_command_accepted(Millis(1300), d.command.unwrap());
        autopilot(&mut c, 1300, true, 0);
        c.on_uplink(Millis(1300), snapshot(2));
        assert_eq!(c.tick(Millis(1300)).status, Status::Flying(Reasons::NONE));
        // A heartbeat past the grace period that says otherwise wins: a pilot took over.
        let later = 1300 + COMMAND_ACCEPTED_GRACE.as_millis() as u64 + 100;
        autopilot(&mut c, later, true, 0);
        c.on_uplink(Millis(later), snapshot(3));
        assert_eq!(
            c.tick(Millis(later)).status,
            Status::Holding(HoldReason::ControlReleased)
        );
    }

    #[test]
    fn flying_velocity_is_ned_and_points_from_the_flock_to_the_goal() {
        let (mut c, _) = flying();
        let v = c.tick(Millis(100)).setpoint.unwrap().velocity_ned;
        // Goal due north of the flock: full speed north (NED x), nothing east, nothing down.
        assert!((v[0] - 5.0).abs() < 1e-3, "{v:?}");
        assert!(v[1].abs() < 1e-3 && v[2].abs() < 1e-3, "{v:?}");
    }

    #[test]
    fn own_position_comes_from_the_autopilot_not_the_snapshot() {
        /// Records feature 22, own height above the altitude band's floor, `ln(1 + h / R)`.
        struct Altitude(f32);
        impl OnboardPolicy for Altitude {
            fn act(&mut self, _task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
                self.0 = features[obs::feature::ALTITUDE];
                [0.0; 3]
            }
        }
        let mut c = DaemonCore::new(CoreConfig::new(ID, 1, Flavour::Px4), Altitude(-1.0));
        c.on_heartbeat(Millis(0), ARMED, PX4_OFFBOARD);
        // Autopilot: 4 m up (NED z = -4); the snapshot says 0 m.
        c.on_local_position(Millis(0), [30.0, 45.0, -4.0]);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        assert_eq!(c.tick(Millis(0)).status, Status::Flying(Reasons::NONE));
        assert!(
            // 4 m up, 3.5 m above the 0.5 m floor, at a 5 m goal radius.
            (c.policy.0 - 1.7_f32.ln()).abs() < 1e-6,
            "altitude feature {}",
            c.policy.0
        );
        assert_eq!(c.own_position(), Some([45.0, 30.0, 4.0]));
    }

    /// Feeds a heartbeat and a position at `height` m above home (sim (45, 30, height)).
    fn autopilot_at(
        core: &mut DaemonCore<TowardsGoal>,
        t: u64,
        armed: bool,
        custom_mode: u32,
        height: f32,
    ) {
        core.on_heartbeat(Millis(t), if armed { ARMED } else { 0 }, custom_mode);
        core.on_local_position(Millis(t), sim_to_ned([45.0, 30.0, height]));
    }

    #[test]
    fn ardupilot_goes_guided_arms_and_takes_off_by_command() {
        let mut c = core(Flavour::ArduPilot);
        autopilot_at(&mut c, 0, false, 0, 0.0);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        // GUIDED first (mode 4), before arming: the takeoff must follow the arming at once.
        let d = c.tick(Millis(0));
        assert_eq!(d.status, Status::Preparing(Preparing::SwitchingMode));
        assert_eq!(
            d.command,
            Some(AutopilotCommand::SetMode {
                custom_main_mode: 4
            })
        );
        autopilot_at(&mut c, 100, false, 4, 0.0);
        let d = c.tick(Millis(100));
        assert_eq!(
            (d.status, d.command),
            (
                Status::Preparing(Preparing::Arming),
                Some(AutopilotCommand::Arm)
            )
        );
        autopilot_at(&mut c, 200, true, 4, 0.0);
        let d = c.tick(Millis(200));
        assert_eq!(d.status, Status::Preparing(Preparing::TakingOff));
        assert_eq!(
            d.command,
            Some(AutopilotCommand::Takeoff { altitude_m: 1.0 })
        );
        assert_eq!(
            d.setpoint, None,
            "a setpoint would cut ArduCopter's takeoff short"
        );
        c.on_command_accepted(Millis(250), AutopilotCommand::Takeoff { altitude_m: 1.0 });
        autopilot_at(&mut c, 300, true, 4, 0.0);
        let d = c.tick(Millis(300));
        assert_eq!(
            (d.command, d.setpoint),
            (None, None),
            "accepted: no repeat, no setpoint"
        );
        autopilot_at(&mut c, 900, true, 4, 0.6);
        assert_eq!(c.tick(Millis(900)).setpoint, None);
        c.on_uplink(Millis(1500), snapshot(2));
        autopilot_at(&mut c, 1500, true, 4, 0.95);
        assert_eq!(c.tick(Millis(1500)).status, Status::Flying(Reasons::NONE));
        // PX4's OFFBOARD number means nothing to ArduPilot.
        assert!(!Flavour::ArduPilot.is_control_mode(PX4_OFFBOARD));
        assert!(Flavour::Px4.is_control_mode(PX4_OFFBOARD | (1 << 24)));
    }

    #[test]
    fn px4_climbs_on_setpoints_after_offboard() {
        let mut c = core(Flavour::Px4);
        autopilot_at(&mut c, 0, false, 0, 0.0);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        assert_eq!(c.tick(Millis(0)).command, Some(AutopilotCommand::Arm));
        autopilot_at(&mut c, 100, true, 0, 0.0);
        assert_eq!(
            c.tick(Millis(100)).status,
            Status::Preparing(Preparing::Streaming)
        );
        autopilot_at(&mut c, 1300, true, 0, 0.0);
        assert_eq!(
            c.tick(Millis(1300)).command,
            Some(AutopilotCommand::SetMode {
                custom_main_mode: 6
            })
        );
        autopilot_at(&mut c, 1400, true, PX4_OFFBOARD, 0.0);
        let d = c.tick(Millis(1400));
        assert_eq!(d.status, Status::Preparing(Preparing::TakingOff));
        assert_eq!(d.command, None, "no NAV_TAKEOFF on PX4");
        assert_eq!(
            d.setpoint,
            Some(Setpoint {
                velocity_ned: [0.0, 0.0, -0.7]
            })
        );
        c.on_uplink(Millis(2900), snapshot(2));
        autopilot_at(&mut c, 2900, true, PX4_OFFBOARD, 0.92);
        assert_eq!(c.tick(Millis(2900)).status, Status::Flying(Reasons::NONE));
    }

    #[test]
    fn a_disarm_on_the_ground_before_the_takeoff_is_retried_one_in_the_air_is_the_pilots() {
        let mut c = core(Flavour::Px4);
        autopilot_at(&mut c, 0, true, PX4_OFFBOARD, 0.0);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        assert_eq!(
            c.tick(Millis(0)).status,
            Status::Preparing(Preparing::TakingOff)
        );
        // COM_DISARM_PRFLT fired: on the ground, never airborne. Arm again.
        autopilot_at(&mut c, 2000, false, 4 << 16 | 3 << 24, 0.0);
        let d = c.tick(Millis(2000));
        assert_eq!(
            (d.status, d.command),
            (
                Status::Preparing(Preparing::Arming),
                Some(AutopilotCommand::Arm)
            )
        );
        // Airborne, then switched to hold by someone: released.
        autopilot_at(&mut c, 2100, true, PX4_OFFBOARD, 1.0);
        c.on_uplink(Millis(2100), snapshot(2));
        assert_eq!(c.tick(Millis(2100)).status, Status::Flying(Reasons::NONE));
        autopilot_at(&mut c, 4000, true, 4 << 16 | 3 << 24, 1.0);
        c.on_uplink(Millis(4000), snapshot(3));
        assert_eq!(
            c.tick(Millis(4000)).status,
            Status::Holding(HoldReason::ControlReleased)
        );
    }

    #[test]
    fn stale_uplink_holds_and_a_fresh_snapshot_resumes() {
        let (mut c, _) = flying();
        autopilot(&mut c, 1000, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(1000)).status, Status::Flying(Reasons::NONE));
        autopilot(&mut c, 1001, true, PX4_OFFBOARD);
        let d = c.tick(Millis(1001));
        assert_eq!(
            d.status,
            Status::Holding(HoldReason::UplinkStale { age_ms: 1001 })
        );
        assert_eq!(d.setpoint, Some(Setpoint::HOLD));
        c.on_uplink(Millis(1100), snapshot(2));
        autopilot(&mut c, 1100, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(1100)).status, Status::Flying(Reasons::NONE));
    }

    /// PX4 AUTO.LAND as a heartbeat reports it (main mode 4, sub mode 6).
    const PX4_LAND: u32 = (4 << 16) | (6 << 24);

    /// Ticks every 100 ms from `from` to `to` (inclusive) with the autopilot armed in
    /// OFFBOARD and no uplink; every status seen.
    fn silent_ticks(c: &mut DaemonCore<TowardsGoal>, from: u64, to: u64) -> Vec<ControlOutput> {
        (from / 100..=to / 100)
            .map(|k| {
                autopilot(c, k * 100, true, PX4_OFFBOARD);
                c.tick(Millis(k * 100))
            })
            .collect()
    }

    #[test]
    fn a_stale_uplink_shorter_than_land_after_holds() {
        let (mut c, _) = flying();
        // Snapshot at 0, stale from 1 s; 10 s of staleness is not more than land_after.
        for d in silent_ticks(&mut c, 1100, 11_000) {
            assert!(
                matches!(d.status, Status::Holding(HoldReason::UplinkStale { .. })),
                "{:?}",
                d.status
            );
            assert_eq!(d.command, None);
            assert!(d.setpoint.is_some());
        }
        assert_eq!(c.counters().landings, 0);
    }

    #[test]
    fn a_longer_silence_in_flight_lands_and_keeps_landing() {
        let (mut c, _) = flying();
        silent_ticks(&mut c, 100, 11_000);
        autopilot(&mut c, 11_001, true, PX4_OFFBOARD);
        let d = c.tick(Millis(11_001));
        assert_eq!(
            d.status,
            Status::Landing(LandReason::GroundSilent { silent_ms: 11_001 })
        );
        assert_eq!(d.status.to_string(), "landing: ground silent for 11.0 s");
        assert!(d.status.is_warning() && !d.status.is_hold());
        assert_eq!(
            (d.setpoint, d.command),
            (None, Some(AutopilotCommand::Land))
        );
        assert_eq!(c.counters().landings, 1);
        // The ground is back: a fresh snapshot does not undo the landing, nor does an abort.
        c.on_uplink(Millis(11_100), snapshot(2));
        c.on_uplink(Millis(11_100), command(2, MissionAction::Abort));
        autopilot(&mut c, 11_100, true, PX4_OFFBOARD);
        let d = c.tick(Millis(11_100));
        assert!(matches!(d.status, Status::Landing(_)), "{:?}", d.status);
        assert_eq!(
            (d.setpoint, d.command),
            (None, None),
            "not before the retry"
        );
        // Not yet out of OFFBOARD after the retry period: asked again.
        autopilot(&mut c, 12_001, true, PX4_OFFBOARD);
        c.on_uplink(Millis(12_001), snapshot(3));
        let d = c.tick(Millis(12_001));
        assert_eq!(
            (d.setpoint, d.command),
            (None, Some(AutopilotCommand::Land))
        );
        // In AUTO.LAND, then disarmed on the ground: nothing more to send, still landing.
        for (t, armed, mode) in [(13_100, true, PX4_LAND), (20_000, false, PX4_LAND)] {
            autopilot(&mut c, t, armed, mode);
            c.on_uplink(Millis(t), snapshot(t as u32));
            let d = c.tick(Millis(t));
            assert!(matches!(d.status, Status::Landing(_)), "{:?}", d.status);
            assert_eq!((d.setpoint, d.command), (None, None));
        }
        // A new start from the ground flies again.
        c.on_uplink(Millis(20_100), command(3, MissionAction::Start));
        autopilot(&mut c, 20_100, false, PX4_LAND);
        assert_eq!(c.tick(Millis(20_100)).command, Some(AutopilotCommand::Arm));
    }

    #[test]
    fn an_accepted_land_is_not_repeated() {
        let (mut c, _) = flying();
        silent_ticks(&mut c, 100, 11_000);
        autopilot(&mut c, 11_100, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(11_100)).command, Some(AutopilotCommand::Land));
        c.on_command_accepted(Millis(11_200), AutopilotCommand::Land);
        // Its heartbeat still says OFFBOARD, but it said yes.
        autopilot(&mut c, 12_200, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(12_200)).command, None);
    }

    #[test]
    fn without_land_after_a_silent_ground_is_held_for_ever() {
        let mut config = CoreConfig::new(ID, 1, Flavour::Px4);
        config.land_after = None;
        let (mut c, _) = flying_with(config);
        for d in silent_ticks(&mut c, 1100, 120_000) {
            assert!(d.status.is_hold(), "{:?}", d.status);
            assert_eq!(d.command, None);
        }
    }

    #[test]
    fn staleness_before_take_off_or_before_the_mission_does_not_land() {
        // No mission: the snapshot ages, nothing happens.
        let mut c = core(Flavour::Px4);
        c.on_uplink(Millis(0), snapshot(1));
        for d in silent_ticks(&mut c, 0, 30_000) {
            assert_eq!(d.status, Status::Idle);
        }
        // Started, but the autopilot never arms: still preparing, asking to arm.
        let mut c = core(Flavour::Px4);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        for k in 0..=300 {
            autopilot(&mut c, k * 100, false, 0);
            let d = c.tick(Millis(k * 100));
            assert_eq!(d.status, Status::Preparing(Preparing::Arming));
            assert_ne!(d.command, Some(AutopilotCommand::Land));
        }
        // Started and armed, but never let into OFFBOARD: not in flight either.
        let mut c = core(Flavour::Px4);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        for k in 0..=300 {
            autopilot(&mut c, k * 100, true, 0);
            let d = c.tick(Millis(k * 100));
            assert!(matches!(d.status, Status::Preparing(_)), "{:?}", d.status);
            assert_ne!(d.command, Some(AutopilotCommand::Land));
        }
        assert_eq!(c.counters().landings, 0);
    }

    #[test]
    fn out_of_order_snapshots_are_ignored() {
        let (mut c, _) = flying();
        c.on_uplink(Millis(900), snapshot(1));
        autopilot(&mut c, 1100, true, PX4_OFFBOARD);
        // Seq 1 again is not news: the world is still the one from t = 0.
        assert!(matches!(
            c.tick(Millis(1100)).status,
            Status::Holding(HoldReason::UplinkStale { .. })
        ));
        assert_eq!(c.counters().stale_snapshots, 1);
    }

    #[test]
    fn no_snapshot_holds() {
        let mut c = core(Flavour::Px4);
        autopilot(&mut c, 0, true, PX4_OFFBOARD);
        c.on_uplink(Millis(0), start());
        assert_eq!(
            c.tick(Millis(0)).status,
            Status::Holding(HoldReason::NoSnapshot)
        );
    }

    #[test]
    fn lost_autopilot_holds_and_resumes_when_it_is_back_in_control() {
        let (mut c, _) = flying();
        c.on_uplink(Millis(1600), snapshot(2));
        let d = c.tick(Millis(1600));
        assert_eq!(d.status, Status::Holding(HoldReason::AutopilotLost));
        assert_eq!((d.setpoint, d.command), (Some(Setpoint::HOLD), None));
        autopilot(&mut c, 1700, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(1700)).status, Status::Flying(Reasons::NONE));
    }

    #[test]
    fn autopilot_failsafe_during_link_loss_is_re_engaged() {
        let (mut c, _) = flying();
        assert_eq!(
            c.tick(Millis(1600)).status,
            Status::Holding(HoldReason::AutopilotLost)
        );
        // Back, but its own failsafe has left OFFBOARD: that was no pilot; take it back.
        c.on_uplink(Millis(1700), snapshot(2));
        autopilot(&mut c, 1700, true, PX4_POSCTL);
        let d = c.tick(Millis(1700));
        assert_eq!(d.status, Status::Preparing(Preparing::Streaming));
        autopilot(&mut c, 2900, true, PX4_POSCTL);
        c.on_uplink(Millis(2900), snapshot(3));
        assert_eq!(
            c.tick(Millis(2900)).command,
            Some(AutopilotCommand::SetMode {
                custom_main_mode: 6
            })
        );
    }

    #[test]
    fn a_pilot_taking_over_is_not_fought() {
        let (mut c, _) = flying();
        autopilot(&mut c, 100, true, PX4_POSCTL);
        for t in [100, 1500, 3000] {
            autopilot(&mut c, t, true, PX4_POSCTL);
            let d = c.tick(Millis(t));
            assert_eq!(d.status, Status::Holding(HoldReason::ControlReleased));
            assert_eq!(d.command, None);
        }
        // Disarming counts the same.
        let (mut c, _) = flying();
        autopilot(&mut c, 100, false, PX4_OFFBOARD);
        assert_eq!(
            c.tick(Millis(100)).status,
            Status::Holding(HoldReason::ControlReleased)
        );
        // A repeated start is not a new one...
        c.on_uplink(Millis(200), start());
        autopilot(&mut c, 200, false, PX4_OFFBOARD);
        assert_eq!(
            c.tick(Millis(200)).status,
            Status::Holding(HoldReason::ControlReleased)
        );
        // ...a new start command re-engages.
        c.on_uplink(Millis(200), command(2, MissionAction::Start));
        autopilot(&mut c, 200, false, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(200)).command, Some(AutopilotCommand::Arm));
    }

    #[test]
    fn abort_holds_until_the_next_start() {
        let (mut c, _) = flying();
        c.on_uplink(Millis(100), command(2, MissionAction::Abort));
        for t in [100, 200, 5000] {
            autopilot(&mut c, t, true, PX4_OFFBOARD);
            let d = c.tick(Millis(t));
            assert_eq!(d.status, Status::Holding(HoldReason::Aborted));
            assert_eq!((d.setpoint, d.command), (Some(Setpoint::HOLD), None));
        }
        c.on_uplink(Millis(5000), command(3, MissionAction::Start));
        c.on_uplink(Millis(5000), snapshot(2));
        assert_eq!(c.tick(Millis(5000)).status, Status::Flying(Reasons::NONE));
    }

    #[test]
    fn a_completed_mission_holds_and_says_so() {
        let (mut c, _) = flying();
        c.on_uplink(Millis(100), command(2, MissionAction::Complete));
        autopilot(&mut c, 200, true, PX4_OFFBOARD);
        let d = c.tick(Millis(200));
        assert_eq!(d.status, Status::Holding(HoldReason::Complete));
        assert_eq!(d.status.to_string(), "holding: mission complete");
        assert_eq!((d.setpoint, d.command), (Some(Setpoint::HOLD), None));
    }

    /// Flies "towards the goal", says it reads encoder `version`, and keeps what it was given.
    struct Versioned {
        version: u16,
        seen: std::rc::Rc<std::cell::Cell<Option<[f32; FEATURES]>>>,
    }
    impl OnboardPolicy for Versioned {
        fn act(&mut self, _task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
            self.seen.set(Some(*features));
            [1.0, 0.0, 0.0]
        }
        fn encoder_version(&self) -> u16 {
            self.version
        }
    }

    /// One tick of a started mission flown by a policy that reads encoder `version`: the
    /// status and the features the policy was given.
    fn tick_reading(version: u16) -> (Status, Option<[f32; FEATURES]>) {
        let seen = std::rc::Rc::default();
        let policy = Versioned {
            version,
            seen: std::rc::Rc::clone(&seen),
        };
        let mut c = DaemonCore::new(CoreConfig::new(ID, 1, Flavour::Px4), policy);
        autopilot(&mut c, 0, true, PX4_OFFBOARD);
        c.on_uplink(Millis(0), start());
        c.on_uplink(Millis(0), snapshot(1));
        (c.tick(Millis(0)).status, seen.get())
    }

    #[test]
    fn the_policy_is_given_the_features_of_its_encoder_version_and_an_unknown_one_holds() {
        let (status, all) = tick_reading(obs::ENCODER_VERSION);
        assert_eq!(status, Status::Flying(Reasons::NONE));
        let all = all.expect("the policy was asked");
        for version in [3, 4] {
            let (status, some) = tick_reading(version);
            assert_eq!(status, Status::Flying(Reasons::NONE));
            let some = some.expect("the policy was asked");
            let width = obs::feature_count(version).expect("a served version");
            assert_eq!(some[..width], all[..width], "v{version}");
            assert!(some[width..].iter().all(|&x| x == 0.0), "v{version}");
        }
        // A policy for an encoder this build does not serve is never asked; the drone holds.
        let (status, seen) = tick_reading(2);
        assert_eq!(
            status,
            Status::Holding(HoldReason::BadObservation(ObsError::UnknownVersion(2)))
        );
        assert_eq!(seen, None);
    }

    #[test]
    fn a_snapshot_with_nan_holds_with_the_reason() {
        let (mut c, _) = flying();
        let Uplink::Snapshot(mut bad) = snapshot(2) else {
            unreachable!()
        };
        bad.targets[0][1] = f32::NAN;
        c.on_uplink(Millis(100), Uplink::Snapshot(bad));
        autopilot(&mut c, 100, true, PX4_OFFBOARD);
        assert_eq!(
            c.tick(Millis(100)).status,
            Status::Holding(HoldReason::BadObservation(ObsError::NonFinite))
        );
    }

    #[test]
    fn non_finite_positions_are_ignored() {
        let (mut c, _) = flying();
        c.on_local_position(Millis(50), [f32::NAN, 0.0, 0.0]);
        assert_eq!(c.own_position(), Some([45.0, 30.0, 2.0]));
    }

    #[test]
    fn outside_the_fence_a_hold_still_steers_back_in() {
        let (mut c, _) = flying();
        c.on_uplink(Millis(100), command(2, MissionAction::Abort));
        // Aborted: plain zero.
        autopilot(&mut c, 100, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(100)).setpoint, Some(Setpoint::HOLD));
        // Uplink stale while 0.2 m above the ground (below the 0.5 m band): climb back in.
        let (mut c, _) = flying();
        c.on_heartbeat(Millis(1500), ARMED, PX4_OFFBOARD);
        c.on_local_position(Millis(1500), sim_to_ned([45.0, 30.0, 0.2]));
        let d = c.tick(Millis(1500));
        assert!(matches!(
            d.status,
            Status::Holding(HoldReason::UplinkStale { .. })
        ));
        let v = d.setpoint.unwrap().velocity_ned;
        assert!(
            v[2] < 0.0,
            "NED down velocity {v:?} should be negative (climbing)"
        );
    }

    #[test]
    fn the_fence_trims_the_actor_and_says_so() {
        let mut c = core(Flavour::Px4);
        // 0.5 m from the north fence (at 99 m), flying north at 5 m/s.
        c.on_heartbeat(Millis(0), ARMED, PX4_OFFBOARD);
        c.on_local_position(Millis(0), sim_to_ned([45.0, 98.5, 2.0]));
        c.on_uplink(Millis(0), start());
        let mut w = world(1);
        w.goal = [50.0, 99.5];
        c.on_uplink(Millis(0), Uplink::Snapshot(w));
        let d = c.tick(Millis(0));
        let Status::Flying(reasons) = d.status else {
            panic!("{:?}", d.status)
        };
        assert!(reasons.contains(Reasons::FENCE_LIMITED), "{reasons}");
        assert!(d.setpoint.unwrap().velocity_ned[0] <= 0.5 + 1e-4);
    }

    #[test]
    fn tunnel_chunks_are_reassembled_and_bad_ones_counted() {
        use skyherd_onboard::wire::{MAX_MESSAGE, chunks, encode_uplink};
        let mut c = core(Flavour::Px4);
        let mut buffer = [0u8; MAX_MESSAGE];
        let bytes = encode_uplink(&snapshot(1), &mut buffer).unwrap();
        let mut sent: Vec<_> = chunks(10, bytes).unwrap().collect();
        sent.reverse();
        for chunk in &sent {
            c.on_tunnel_payload(Millis(0), chunk.as_bytes()).unwrap();
        }
        assert_eq!(c.counters().snapshots, 1);
        assert!(c.on_tunnel_payload(Millis(0), &[0xFF; 20]).is_err());
        assert!(c.on_tunnel_payload(Millis(0), &[]).is_err());
        let n = c.counters();
        assert_eq!((n.chunks, n.bad_chunks), (sent.len() as u64 + 2, 2));
    }

    #[test]
    fn a_restarted_ground_is_heard_again_after_a_silence() {
        use skyherd_onboard::wire::{MAX_MESSAGE, chunks, encode_uplink};
        let mut buffer = [0u8; MAX_MESSAGE];
        let mut send = |c: &mut DaemonCore<TowardsGoal>, t: u64, id: u16, message: &Uplink| {
            let bytes = encode_uplink(message, &mut buffer).unwrap();
            let mut last = Ok(());
            for chunk in chunks(id, bytes).unwrap() {
                last = c.on_tunnel_payload(Millis(t), chunk.as_bytes());
            }
            last
        };
        let mut c = core(Flavour::Px4);
        autopilot(&mut c, 0, true, PX4_OFFBOARD);
        send(&mut c, 0, 500, &start()).unwrap();
        send(&mut c, 0, 501, &snapshot(900)).unwrap();
        assert_eq!(c.tick(Millis(0)).status, Status::Flying(Reasons::NONE));
        // The ground restarts: ids and sequence numbers from 1 again. Within the timeout an old
        // id is just a late chunk...
        assert!(matches!(
            send(&mut c, 500, 1, &snapshot(1)),
            Err(WireError::Stale { .. })
        ));
        // ...after it, a restart.
        send(&mut c, 1500, 2, &command(1, MissionAction::Start)).unwrap();
        send(&mut c, 1500, 3, &snapshot(1)).unwrap();
        autopilot(&mut c, 1500, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(1500)).status, Status::Flying(Reasons::NONE));
        assert_eq!(c.counters().ground_restarts, 1);
    }

    #[test]
    fn random_tunnel_payloads_are_counted_never_a_panic() {
        let (mut c, _) = flying();
        let mut seed = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let mut payload = [0u8; 128];
        for i in 0..20_000 {
            let len = (next() % 129) as usize;
            for b in payload.iter_mut() {
                *b = next() as u8;
            }
            // Half of them look like chunks, to get past the magic and version checks.
            if i % 2 == 0 && len >= 2 {
                payload[0] = skyherd_onboard::wire::CHUNK_MAGIC;
                payload[1] = skyherd_onboard::wire::WIRE_VERSION;
            }
            let _ = c.on_tunnel_payload(Millis(10), &payload[..len]);
        }
        assert_eq!(c.counters().bad_chunks + c.counters().snapshots, 20_000 + 1);
        autopilot(&mut c, 20, true, PX4_OFFBOARD);
        assert_eq!(c.tick(Millis(20)).status, Status::Flying(Reasons::NONE));
    }

    #[test]
    fn counters_count() {
        let (mut c, _) = flying();
        c.tick(Millis(1600));
        let n = c.counters();
        assert_eq!(
            (n.ticks, n.hold_ticks, n.snapshots, n.mission_commands),
            (2, 1, 1, 1)
        );
    }
}
