//! The simulator side of a software-in-the-loop mission: the paper's world, one mock autopilot
//! per drone on its own UDP socket, and the tracking sensor reporting to the ground station —
//! stepped in lockstep with the onboard daemons.
//!
//! One tick is [`SitlConfig::tick_s`] of simulated time (0.1 s: autopilots report positions at
//! 10 Hz, daemons answer each one):
//! 1. every live autopilot node receives what arrived and flies its current setpoint;
//! 2. the world advances one tick with the velocities the autopilots fly (herders first, as in
//!    [`skyherd_sim::world::advance`]), and each autopilot is told where the world put its drone;
//! 3. on sensor ticks the detection sensor scans the targets and sends the scan (MAVLink
//!    `DEBUG_VECT`, see `skyherd_ground::detections`) to the ground station, and the loop waits
//!    for the ground's acknowledgement (`det_ack`), sent once it has tracked the scan and sent
//!    its snapshot up;
//! 4. every autopilot sends its telemetry, stamped with the simulated time: the position the
//!    world just put it at. A daemon answers each position, so it decides on its own position
//!    and targets of the same instant, as a policy does in the simulator (the other drones'
//!    positions in the snapshot are one tick older: the ground hears them in step 4);
//! 5. **lockstep**: every drone whose daemon has been heard is waited for until it has answered
//!    this tick's position. The daemon ends each answer with a heartbeat, so the pre-flight,
//!    before any setpoint, is in lockstep too. The loop runs as fast as the processes allow and
//!    never outruns them; the answer is flown in the next tick's step 1.
//!
//! Waits (steps 3 and 5) are patient ([`SitlConfig::lockstep_patience`], 400 ms of wall time) for
//! a process that answered its last tick, brief ([`SitlConfig::lockstep_timeout`], 50 ms) for
//! one that did not (a dead daemon costs the mission 50 ms a tick, not 400 ms) and on links that
//! lose datagrams on purpose; a wait given up during the episode is a lockstep miss.
//!
//! Nothing depends on how long anything takes in wall time: the pre-roll only listens,
//! simulated time starts on the next whole second, the world holds still until every drone
//! flies, and the sensor's noise, the wind's gusts and the autopilots' estimate errors start
//! at the release (before it the air is calm). A seed reproduces its mission, unless a wait
//! was given up (`lockstep_misses` in result.json).
//!
//! The world is integrated with the tick as its time step: for the `indoor` preset that is the
//! scenario's own 0.1 s; for the paper presets (1 s steps) it integrates the same velocity field
//! ten times finer.

use std::net::{SocketAddr, UdpSocket};
use std::thread;
use std::time::{Duration, Instant};

use skyherd_ground::detections::{acknowledged_scan, scan_messages};
use skyherd_link::{Codec, Flavour, Frame, Signing};
use skyherd_onboard::frame::{ned_to_sim, sim_to_ned};
use thiserror::Error;

use super::arducopter::{ArduCopter, ArduCopterBundle, ArduCopterOptions};
use super::autopilot::{AutopilotConfig, Home, MockAutopilot, Motion};
use super::faults::FaultConfig;
use super::node::{AutopilotNode, NodeOptions};
use super::sensor::{DetectionSensor, SensorConfig, SensorError};
use skyherd_sim::dynamics::{DynamicsLimits, WindConfig};
use skyherd_sim::env::Env;
use skyherd_sim::scenario::{Scenario, ScenarioError};
use skyherd_sim::world::{StepScratch, World, WorldError, advance, closest_pair_m};

/// System id of the tracking sensor on the fleet link.
pub const SENSOR_SYSTEM_ID: u8 = 200;

/// Everything a SITL world needs.
#[derive(Clone, Debug)]
pub struct SitlConfig {
    /// The episode family; `seed` picks the episode.
    pub scenario: Scenario,
    /// Episode seed (spawn, boids-parameter noise, sensor noise, faults).
    pub seed: u64,
    /// Simulated seconds per tick.
    pub tick_s: f64,
    /// Seconds between sensor scans.
    pub sensor_period_s: f64,
    /// The ground station's fleet address (telemetry and scans go there).
    pub ground: SocketAddr,
    /// MAVLink 2 signing on the autopilot and sensor links.
    pub signing: Option<Signing>,
    /// Faults on the autopilot links.
    pub faults: FaultConfig,
    /// Sensor model.
    pub sensor: SensorConfig,
    /// How long to wait for a streaming daemon's answer, wall time, once it has missed a
    /// tick (a daemon that died or was cut off costs this each tick) or while the autopilot
    /// links carry faults (a lost datagram is no answer at all).
    pub lockstep_timeout: Duration,
    /// How long to wait, wall time, for a daemon or ground station that answered its last
    /// tick in time: on a loaded machine a live process can take longer than
    /// `lockstep_timeout`, and going on without its answer would make the mission differ from
    /// run to run. A tick waits at most twice this (the ground, then the daemons), which must
    /// stay under the ground's idle timeout (1 s as fast as possible): a ground that hears no
    /// scan for that long takes the simulation for over.
    pub lockstep_patience: Duration,
    /// 0 = as fast as possible; 1 = real time; k = k times real time.
    pub speed: f64,
    /// Give up this many simulated seconds after the start of flight.
    pub time_limit_s: f64,
    /// Cut drone `index` off (its autopilot stops, its herder holds) at simulated time `t`.
    pub lose_drone: Option<(usize, f64)>,
    /// The ground station acknowledges every scan (`skyherd-ground` does): wait for that from
    /// the first scan on. Otherwise the loop waits only once an acknowledgement has come, and
    /// until then whether the ground saw a tick's telemetry before its scan is a race.
    pub ground_acks_scans: bool,
    /// The vehicles' motion model (`None`: they fly their setpoints at once, as every number
    /// before the dynamics model was measured) and the wind they fly in.
    pub dynamics: Option<DynamicsLimits>,
    /// The wind (with `dynamics` only).
    pub wind: WindConfig,
    /// The autopilots' position-estimate error (with `dynamics` only): each horizontal axis of
    /// what they report wanders from the truth as a Gauss-Markov process of this stationary
    /// standard deviation (m) over [`ESTIMATE_TIME_S`], starting from none at the release.
    /// Defaults: 0.03 m in a room (motion capture or ultra-wideband), 0.5 m in the arena
    /// (GNSS) (`--estimate-noise-m`).
    pub estimate_std_m: f64,
    /// The same on the vertical axis. Defaults: 0.03 m in a room, 0.1 m in the arena (an EKF's
    /// height relative to takeoff leans on the barometer; a GNSS-like 0.5 m from the ground up
    /// would fly the drones into the ground under the 0.5 m altitude floor).
    pub estimate_vertical_std_m: f64,
    /// Two drones closer than this (3-D, m) during flight is a separation breach: 0.5 m in a
    /// room-sized arena (50 m or less across), 3 m otherwise.
    pub separation_m: f64,
    /// The daemons land after their uplink has been stale this long in flight
    /// (`skyherd-onboard --land-after-s`), s of simulated time; 0: they never land.
    pub land_after_s: f64,
    /// Fault: the mission kills the ground station (SIGKILL) at this simulated time, s.
    pub kill_ground_at: Option<f64>,
    /// Fault: kill drone `.0`'s daemon (SIGKILL) at simulated time `.1`, seconds.
    pub kill_daemon: Option<(usize, f64)>,
    /// Which autopilot the mocks behave like (the daemons are told the same).
    pub autopilot: Flavour,
    /// The drones start on the floor below their spawn points and take off to this height,
    /// m; the episode starts when every one is up there under external control. Defaults to
    /// the scenario's herder altitude, but at least 0.6 m (the onboard altitude band starts at
    /// 0.5 m: the room preset's zoomed 4 cm is where no real drone hovers) and at most 0.5 m
    /// below the ceiling.
    pub takeoff_altitude_m: f64,
    /// Drones flown by a real ArduCopter SITL instead of a mock ([`crate::arducopter`]).
    pub arducopter: Option<RealDrones>,
}

/// Which drones a real ArduCopter flies, and how.
#[derive(Clone, Debug)]
pub struct RealDrones {
    /// The binary and its defaults.
    pub bundle: ArduCopterBundle,
    /// Herder indices flown by ArduCopter (the others are mocks).
    pub indices: Vec<usize>,
    /// ArduCopter's simulation speed over the wall clock. The mission follows its clock.
    pub speedup: f64,
    /// A folder for each instance's console log (`arducopter-N.log`).
    pub logs: Option<std::path::PathBuf>,
}

/// How a drone's daemon reaches its autopilot.
#[derive(Clone, Debug, PartialEq)]
pub struct AutopilotLink {
    /// `skyherd-onboard --autopilot` address: `udpout:` a mock's socket, `udpin:` where a
    /// real ArduCopter's SERIAL0 sends.
    pub address: String,
    /// Whether the link is signed with the fleet key (mocks; ArduCopter's stands for a cable).
    pub signed: bool,
    /// `--local-origin`: where the autopilot's home lies in the world (x east, y north), m.
    pub local_origin: Option<[f64; 2]>,
    /// The autopilot's family (`--flavour`).
    pub flavour: Flavour,
    /// The simulator steps this autopilot in lockstep with the daemon's answers (a mock);
    /// `false` for a real ArduCopter, which runs on its own clock
    /// (`skyherd-onboard --autopilot-runs-free`).
    pub lockstep: bool,
}

/// How long (wall time) a tick waits for a real ArduCopter's clock before the mission fails.
const REAL_CLOCK_TIMEOUT: Duration = Duration::from_secs(10);

/// How long the autopilots' position-estimate error takes to wander, s (a GNSS receiver's and
/// an EKF's errors change over seconds, not from one report to the next).
pub const ESTIMATE_TIME_S: f64 = 5.0;

/// The episode starts once every drone has come this close (m) below the takeoff altitude.
pub const AIRBORNE_TOLERANCE_M: f64 = 0.15;

impl SitlConfig {
    /// Defaults for a scenario: 0.1 s ticks and scans, sensor noise from the scenario's sensing
    /// noise with 95 % detection and no false alarms, 50 ms lockstep wait (400 ms for a
    /// process that kept pace), as fast as
    /// possible, the scenario's step limit as time limit, a ground that acknowledges scans.
    pub fn new(scenario: Scenario, seed: u64, ground: SocketAddr) -> Self {
        let sensor = SensorConfig::for_scenario(&scenario);
        let time_limit_s = scenario.step_limit as f64 * scenario.dt;
        let takeoff_altitude_m = scenario
            .layout
            .herder_altitude
            .max(0.6)
            .min(scenario.area.ceiling - 0.5);
        Self {
            scenario,
            seed,
            tick_s: 0.1,
            sensor_period_s: 0.1,
            ground,
            signing: None,
            faults: FaultConfig::default(),
            sensor,
            lockstep_timeout: Duration::from_millis(50),
            lockstep_patience: Duration::from_millis(400),
            speed: 0.0,
            time_limit_s,
            lose_drone: None,
            ground_acks_scans: true,
            dynamics: None,
            wind: WindConfig::CALM,
            estimate_std_m: 0.0,
            estimate_vertical_std_m: 0.0,
            separation_m: 0.0,
            land_after_s: 10.0,
            kill_ground_at: None,
            kill_daemon: None,
            autopilot: Flavour::Px4,
            takeoff_altitude_m,
            arducopter: None,
        }
        .with_default_separation()
    }

    fn with_default_separation(mut self) -> Self {
        self.separation_m = self.scenario.area.breach_distance_m();
        (self.estimate_std_m, self.estimate_vertical_std_m) = if self.separation_m <= 1.0 {
            (0.03, 0.03)
        } else {
            (0.5, 0.1)
        };
        self
    }
}

/// The detection sensor's seed for an episode seed.
pub fn sensor_seed(seed: u64) -> u64 {
    seed ^ 0x5EA5_0000
}

/// Why the SITL world could not run.
#[derive(Debug, Error)]
pub enum SitlError {
    /// The scenario is invalid.
    #[error("scenario: {0}")]
    Scenario(#[from] ScenarioError),
    /// The sensor configuration is invalid.
    #[error("sensor: {0}")]
    Sensor(#[from] SensorError),
    /// The world refused a step.
    #[error("world: {0}")]
    World(#[from] WorldError),
    /// A socket failed.
    #[error("network: {0}")]
    Io(#[from] std::io::Error),
    /// A setting is out of its range.
    #[error("{field}: {reason}")]
    Invalid {
        /// The setting.
        field: &'static str,
        /// What was wrong.
        reason: String,
    },
}

impl SitlConfig {
    /// Every setting in its range (NaN never is): the faults, the speed, the time limit, the
    /// lost drone and the killed daemon. [`SitlWorld::new`] refuses a config that fails this.
    pub fn validate(&self) -> Result<(), SitlError> {
        let bad = |field, reason: &str| {
            Err(SitlError::Invalid {
                field,
                reason: reason.to_owned(),
            })
        };
        self.faults
            .validate()
            .map_err(|(field, reason)| SitlError::Invalid {
                field,
                reason: reason.to_owned(),
            })?;
        if !(self.speed.is_finite() && self.speed >= 0.0) {
            return bad(
                "speed",
                "must be a finite number >= 0 (0: as fast as possible)",
            );
        }
        if !(self.time_limit_s.is_finite() && self.time_limit_s > 0.0) {
            return bad("time limit", "must be a positive number of seconds");
        }
        if !(self.tick_s.is_finite() && self.tick_s > 0.0) {
            return bad("tick", "must be a positive number of seconds");
        }
        if let Some(limits) = &self.dynamics {
            limits.validate().map_err(|field| SitlError::Invalid {
                field: "dynamics",
                reason: format!("{field} must be finite and > 0"),
            })?;
        }
        if let Err(reason) = self.wind.validate() {
            return bad("wind", reason);
        }
        let ceiling = self.scenario.area.ceiling;
        if !(self.takeoff_altitude_m.is_finite()
            && self.takeoff_altitude_m >= 0.3
            && self.takeoff_altitude_m <= ceiling)
        {
            return Err(SitlError::Invalid {
                field: "takeoff altitude",
                reason: format!("must be 0.3 m to the ceiling ({ceiling} m)"),
            });
        }
        if !(self.separation_m.is_finite() && self.separation_m >= 0.0) {
            return bad("separation", "must be a finite distance >= 0");
        }
        // At most a day, as the daemon accepts.
        if !(self.land_after_s.is_finite() && (0.0..=86_400.0).contains(&self.land_after_s)) {
            return bad(
                "land after",
                "must be 0 (never land) to 86400 seconds of stale uplink",
            );
        }
        if let Some(at) = self.kill_ground_at
            && !(at.is_finite() && at >= 0.0)
        {
            return bad(
                "ground kill",
                "the time must be a finite number of seconds >= 0",
            );
        }
        if let Some(real) = &self.arducopter {
            let drones = self.scenario.herder_count();
            if real.indices.iter().any(|&i| i >= drones) {
                return bad("arducopter", "a drone index is not among the drones");
            }
            if !(real.speedup.is_finite() && (0.1..=100.0).contains(&real.speedup)) {
                return bad("arducopter", "the speedup must be 0.1 to 100");
            }
            if self
                .lose_drone
                .is_some_and(|(i, _)| real.indices.contains(&i))
            {
                return bad("lost drone", "a real ArduCopter cannot be cut off here");
            }
        }
        for (field, fault) in [
            ("lost drone", self.lose_drone),
            ("killed daemon", self.kill_daemon),
        ] {
            let Some((index, at)) = fault else {
                continue;
            };
            let drones = self.scenario.herder_count();
            if index >= drones {
                return Err(SitlError::Invalid {
                    field,
                    reason: format!("index {index}, but the drones are 0..{drones}"),
                });
            }
            if !(at.is_finite() && at >= 0.0) {
                return bad(field, "the time must be a finite number of seconds >= 0");
            }
        }
        Ok(())
    }
}

/// How an episode ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Ending {
    /// Every target is inside the goal.
    Success,
    /// A herder or target left the arena.
    LeftArea,
    /// The time limit passed.
    TimeLimit,
    /// The ground station process exited (killed, crashed) before the episode ended; the
    /// loop goes on until the drones have landed (see [`LANDING_WAIT_S`]).
    GroundExited,
}

/// After the ground station exited, the loop runs on until every drone has landed and
/// disarmed, or this many simulated seconds have passed.
pub const LANDING_WAIT_S: f64 = 30.0;

/// What one tick did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickReport {
    /// Simulated time after the tick, s.
    pub time_s: f64,
    /// Drones flying under external control (armed, OFFBOARD/GUIDED).
    pub flying: usize,
    /// Live drones armed (flying, holding, landing): not yet on the ground and disarmed.
    pub armed: usize,
    /// Set once the episode has ended.
    pub ending: Option<Ending>,
}

/// The SITL world: the true state, the autopilots and the sensor.
pub struct SitlWorld {
    config: SitlConfig,
    world: World,
    scratch: StepScratch,
    nodes: Vec<Option<AutopilotNode>>,
    /// Real ArduCopters by herder index, with their clock's offset from the world's (s).
    real: Vec<Option<(ArduCopter, f64)>>,
    /// The daemons' `udpin` ports of the real ones.
    real_ports: Vec<Option<u16>>,
    sensor: DetectionSensor,
    sensor_socket: UdpSocket,
    sensor_codec: Codec,
    time_s: f64,
    next_scan: f64,
    flight_start: Option<f64>,
    /// Which drones have reached their takeoff altitude under external control since the
    /// mission began: a takeoff is an event, so a gust that drops a drone below the altitude
    /// after it got there does not hold the episode's start back.
    reached_altitude: Vec<bool>,
    ending: Option<(Ending, f64)>,
    path_length: f64,
    actions: Vec<[f64; 3]>,
    /// Where each real ArduCopter is at the tick's time, world frame.
    real_targets: Vec<[f64; 3]>,
    /// Herder positions before the step (reused, no allocation per tick).
    before: Vec<[f64; 3]>,
    wall_start: Instant,
    lockstep_misses: u64,
    /// Drones (by index) whose daemon missed its last lockstep answer: they get the short wait.
    late_daemons: Vec<bool>,
    /// The ground missed its last acknowledgement.
    ground_late: bool,
    /// Drones whose daemon is dead: not waited for.
    daemons_gone: Vec<usize>,
    ground_acking: bool,
    acked_scan: f64,
    ack_frames: Vec<Frame>,
    min_separation_m: f64,
    separation_breaches: u64,
    /// When the ground station exited, s, and how (its exit status, in words).
    ground_exit: Option<(f64, String)>,
    /// What was outside the arena when the episode ended there.
    left_area: Vec<String>,
}

impl std::fmt::Debug for SitlWorld {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SitlWorld")
            .field("time_s", &self.time_s)
            .field("drones", &self.nodes.len())
            .finish()
    }
}

impl SitlWorld {
    /// Spawns the episode (the scenario's spawn rules and per-episode boids noise) and binds one
    /// autopilot per drone on an ephemeral loopback port.
    pub fn new(config: SitlConfig) -> Result<Self, SitlError> {
        config.validate()?;
        let mut env = Env::new(config.scenario.clone())?;
        let mut world = env.reset(config.seed).clone();
        world.dt = config.tick_s;
        // On the floor below the spawn point: they take off before the episode starts.
        for herder in &mut world.herders {
            herder[2] = 0.0;
        }
        let scratch = StepScratch::with_capacity(world.targets.len());
        let mut nodes = Vec::with_capacity(world.herders.len());
        let mut real = Vec::with_capacity(world.herders.len());
        let mut real_ports = Vec::with_capacity(world.herders.len());
        for (i, herder) in world.herders.iter().enumerate() {
            if let Some(drones) = config
                .arducopter
                .as_ref()
                .filter(|d| d.indices.contains(&i))
            {
                let port = crate::launch::free_udp_port()?;
                let options = ArduCopterOptions {
                    system_id: i as u8 + 1,
                    speedup: drones.speedup,
                    serial0: ([127, 0, 0, 1], port).into(),
                    home: Home::CMAC,
                    origin_world: [herder[0], herder[1]],
                    log: drones
                        .logs
                        .as_ref()
                        .map(|d| d.join(format!("arducopter-{}.log", i + 1))),
                };
                let copter = ArduCopter::start(
                    &drones.bundle,
                    &options,
                    Some((config.signing.clone(), config.ground)),
                )
                .map_err(|e| SitlError::Invalid {
                    field: "arducopter",
                    reason: e.to_string(),
                })?;
                nodes.push(None);
                real.push(Some((copter, 0.0)));
                real_ports.push(Some(port));
                continue;
            }
            real.push(None);
            real_ports.push(None);
            let mut autopilot = AutopilotConfig::for_flavour(config.autopilot, i as u8 + 1);
            autopilot.max_speed = config.scenario.limits.herder;
            autopilot.dynamics = config.dynamics.map(|limits| Motion {
                limits,
                wind: config.wind,
                wind_seed: config.seed.wrapping_add(5000 + i as u64),
                estimate_std_m: config.estimate_std_m,
                estimate_vertical_std_m: config.estimate_vertical_std_m,
                estimate_time_s: ESTIMATE_TIME_S,
            });
            let options = NodeOptions {
                signing: config.signing.clone(),
                faults: config.faults.clone(),
                seed: config.seed.wrapping_add(1000 + i as u64),
                peers: vec![config.ground],
            };
            let node = AutopilotNode::bind(
                "127.0.0.1:0".parse().expect("literal address"),
                MockAutopilot::new(autopilot, sim_to_ned(*herder), 0.0),
                options,
            )?;
            nodes.push(Some(node));
        }
        let sensor = DetectionSensor::new(config.sensor.clone(), sensor_seed(config.seed))?;
        let sensor_socket = UdpSocket::bind("127.0.0.1:0")?;
        sensor_socket.set_nonblocking(true)?;
        let sensor_codec = Codec::new(SENSOR_SYSTEM_ID, 1, config.signing.clone());
        let herders = world.herders.len();
        let ground_acking = config.ground_acks_scans;
        Ok(Self {
            config,
            world,
            scratch,
            nodes,
            real,
            real_ports,
            sensor,
            sensor_socket,
            sensor_codec,
            time_s: 0.0,
            next_scan: 0.0,
            flight_start: None,
            reached_altitude: Vec::new(),
            ending: None,
            path_length: 0.0,
            actions: vec![[0.0; 3]; herders],
            real_targets: vec![[0.0; 3]; herders],
            before: Vec::with_capacity(herders),
            wall_start: Instant::now(),
            lockstep_misses: 0,
            late_daemons: vec![false; herders],
            ground_late: false,
            daemons_gone: Vec::new(),
            ground_acking,
            acked_scan: f64::NEG_INFINITY,
            ack_frames: Vec::new(),
            min_separation_m: f64::INFINITY,
            separation_breaches: 0,
            ground_exit: None,
            left_area: Vec::new(),
        })
    }

    /// The smallest 3-D distance between two drones seen during flight, m (infinity with one
    /// drone or before the flight).
    pub fn min_separation_m(&self) -> f64 {
        self.min_separation_m
    }

    /// The ground station exited at the current simulated time, `how` (its exit status, in
    /// words). Before the end of the episode that ends it, as [`Ending::GroundExited`]; the
    /// loop stops waiting for the ground's scan acknowledgements either way. Only the first
    /// call counts.
    pub fn ground_exited(&mut self, how: String) {
        if self.ground_exit.is_some() {
            return;
        }
        self.ground_exit = Some((self.time_s, how));
        self.ground_acking = false;
        if self.ending.is_none() {
            self.ending = Some((Ending::GroundExited, self.time_s));
        }
    }

    /// What was outside the arena (`herder N`, `target N`, 1-based) when the episode ended
    /// there; empty otherwise.
    pub fn left_area(&self) -> &[String] {
        &self.left_area
    }

    /// When the ground station exited, s, and how.
    pub fn ground_exit(&self) -> Option<&(f64, String)> {
        self.ground_exit.as_ref()
    }

    /// When each drone began to land, s, by herder index: its autopilot accepted
    /// `MAV_CMD_NAV_LAND` (`None`: it did not, or its link was cut).
    pub fn landing_starts(&self) -> Vec<Option<f64>> {
        self.nodes
            .iter()
            .map(|n| n.as_ref().and_then(|n| n.autopilot().landing_since()))
            .collect()
    }

    /// Each drone's touchdown time, s, by herder index: when its autopilot landed and disarmed
    /// itself (`None`: it did not, or its link was cut).
    pub fn touchdowns(&self) -> Vec<Option<f64>> {
        self.nodes
            .iter()
            .map(|n| n.as_ref().and_then(|n| n.autopilot().touchdown_at()))
            .collect()
    }

    /// Ticks of flight in which some two drones were closer than the config's `separation_m`.
    pub fn separation_breaches(&self) -> u64 {
        self.separation_breaches
    }

    /// How each drone's daemon reaches its autopilot, by herder index (system id = index + 1).
    pub fn autopilot_links(&self) -> Vec<AutopilotLink> {
        let mut links = Vec::with_capacity(self.nodes.len());
        for (i, node) in self.nodes.iter().enumerate() {
            if let (Some(port), Some(Some((copter, _)))) = (self.real_ports[i], self.real.get(i)) {
                let origin = copter.to_world([0.0; 3]);
                links.push(AutopilotLink {
                    address: format!("udpin:127.0.0.1:{port}"),
                    signed: false,
                    local_origin: Some([origin[0], origin[1]]),
                    flavour: Flavour::ArduPilot,
                    lockstep: false,
                });
            } else if let Some(addr) = node.as_ref().and_then(|n| n.local_addr().ok()) {
                links.push(AutopilotLink {
                    address: format!("udpout:{addr}"),
                    signed: true,
                    local_origin: None,
                    flavour: self.config.autopilot,
                    lockstep: true,
                });
            }
        }
        links
    }

    /// Whether any drone is a real ArduCopter (the mission then follows its clock).
    pub fn has_real_autopilots(&self) -> bool {
        self.real.iter().any(Option::is_some)
    }

    /// Polls every real ArduCopter until each has reported a position at least as late as
    /// world time `t` (its clock offset applied), or `timeout` of wall time passes.
    fn follow_real_clocks(&mut self, t: f64, timeout: Duration) -> Result<(), SitlError> {
        let start = Instant::now();
        loop {
            let mut behind = None;
            for (i, slot) in self.real.iter_mut().enumerate() {
                if let Some((copter, offset)) = slot {
                    copter.poll()?;
                    if copter.time_s().is_none_or(|at| at + 1e-9 < t + *offset) {
                        behind = Some(i);
                    }
                }
            }
            let Some(i) = behind else {
                return Ok(());
            };
            if start.elapsed() > timeout {
                return Err(SitlError::Invalid {
                    field: "arducopter",
                    reason: format!(
                        "drone {} reported no position for simulated time {t:.1} s within {:.0} s",
                        i + 1,
                        timeout.as_secs_f64()
                    ),
                });
            }
            thread::sleep(Duration::from_micros(500));
        }
    }

    /// The configuration the world runs with.
    pub fn config(&self) -> &SitlConfig {
        &self.config
    }

    /// The true world.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// Simulated time, s.
    pub fn time_s(&self) -> f64 {
        self.time_s
    }

    /// When every live drone was first flying under external control, s.
    pub fn flight_start(&self) -> Option<f64> {
        self.flight_start
    }

    /// How the episode ended and when, once it has.
    pub fn ending(&self) -> Option<(Ending, f64)> {
        self.ending
    }

    /// Total distance flown by all herders since the start of flight, metres.
    pub fn path_length(&self) -> f64 {
        self.path_length
    }

    /// Drone `index`'s daemon is known to be dead (the harness killed it): lockstep stops
    /// waiting for its answers, so that the other drones fly on at full pace.
    pub fn daemon_gone(&mut self, index: usize) {
        if !self.daemons_gone.contains(&index) {
            self.daemons_gone.push(index);
        }
    }

    /// Waits given up during the episode (from the release to its ending), on a streaming
    /// daemon's answer or the ground's acknowledgement: each may have changed the mission, so a
    /// seeded run reproduces another only when both have none. (Before the release the world
    /// holds still; after the ending the ground stops answering on purpose.)
    pub fn lockstep_misses(&self) -> u64 {
        self.lockstep_misses
    }

    /// Autopilot failsafes (setpoint loss) so far, all drones.
    pub fn failsafe_events(&self) -> u64 {
        self.nodes
            .iter()
            .flatten()
            .map(|n| n.autopilot().failsafe_events())
            .sum()
    }

    /// Pre-roll: let the autopilots listen on the wall clock (the world does not move, nothing
    /// is reported) until every one has heard its daemon's heartbeat, or `timeout` passes;
    /// returns whether all did. Simulated time then goes on from the next whole second after
    /// the pre-roll (never back, so delayed datagrams still fall due).
    pub fn wait_for_daemons(&mut self, timeout: Duration) -> Result<bool, SitlError> {
        let start = Instant::now();
        loop {
            let mut all = true;
            let now = start.elapsed().as_secs_f64();
            for node in self.nodes.iter_mut().flatten() {
                // Listen only: a position now would start the daemon's control ticks on the
                // pre-roll's wall clock, and what it made of the ground's first messages
                // would depend on that clock.
                node.receive_and_fly(now)?;
                all &= node.autopilot().companion_heartbeat_at().is_some();
            }
            // A real ArduCopter is ready once its positions flow (its EKF has an origin).
            let mut real_clock = None;
            for (copter, _) in self.real.iter_mut().flatten() {
                copter.poll()?;
                match copter.time_s() {
                    Some(at) => real_clock = real_clock.or(Some(at)),
                    None => all = false,
                }
            }
            if all {
                // Simulated time goes on from the next whole second, not the wall time the
                // pre-roll happened to take, so the episode's tick times are the same each run.
                // With real ArduCopters the world runs on the first one's clock (the others'
                // are offset), so that every process stamps time alike.
                let now = real_clock.unwrap_or(now).ceil();
                for (copter, offset) in self.real.iter_mut().flatten() {
                    *offset = copter.time_s().map_or(0.0, |at| at.ceil() - now);
                }
                self.time_s = now;
                self.next_scan = now;
                for node in self.nodes.iter_mut().flatten() {
                    node.autopilot_mut().start_episode(now);
                }
                self.wall_start = Instant::now()
                    - Duration::from_secs_f64(now / self.config.speed.max(1e-9))
                        .min(start.elapsed());
                return Ok(true);
            }
            if start.elapsed() > timeout {
                return Ok(false);
            }
            thread::sleep(Duration::from_millis(5));
        }
    }

    /// One lockstep tick; see the module docs.
    pub fn tick(&mut self) -> Result<TickReport, SitlError> {
        let t = self.time_s + self.config.tick_s;
        if let Some((index, at)) = self.config.lose_drone
            && t >= at
            && let Some(slot) = self.nodes.get_mut(index)
        {
            *slot = None;
        }
        // 0. Real ArduCopters run free: the world waits for their clocks to pass `t`.
        if self.has_real_autopilots() {
            self.follow_real_clocks(t, REAL_CLOCK_TIMEOUT)?;
        }
        // 1. Autopilots: receive and fly (they report after the world has moved, step 4).
        let (mut flying, mut armed) = (0, 0);
        let airborne = self.config.takeoff_altitude_m - AIRBORNE_TOLERANCE_M;
        let drones = self.real.len().max(self.nodes.len());
        self.reached_altitude.resize(drones, false);
        let reached = &mut self.reached_altitude;
        for (i, slot) in self.real.iter().enumerate() {
            if let Some((copter, offset)) = slot {
                let (ned, _) = copter.state_at(t + offset).unwrap_or(([0.0; 3], [0.0; 3]));
                let target = copter.to_world(ned);
                let here = self.world.herders[i];
                // The velocity that takes the world's herder to where ArduCopter is at `t`.
                self.actions[i] = [
                    (target[0] - here[0]) / self.config.tick_s,
                    (target[1] - here[1]) / self.config.tick_s,
                    (target[2] - here[2]) / self.config.tick_s,
                ];
                self.real_targets[i] = target;
                if copter.armed() && copter.guided() && -ned[2] >= airborne {
                    reached[i] = true;
                }
                flying += usize::from(reached[i]);
                armed += usize::from(copter.armed());
            }
        }
        for (i, slot) in self.nodes.iter_mut().enumerate() {
            if self.real[i].is_some() {
                continue;
            }
            self.actions[i] = match slot {
                Some(node) => {
                    let v = ned_to_sim(node.receive_and_fly(t)?);
                    let ap = node.autopilot();
                    if ap.under_external_control() && -ap.position_ned()[2] >= airborne {
                        reached[i] = true;
                    }
                    flying += usize::from(reached[i]);
                    armed += usize::from(ap.armed());
                    v
                }
                None => [0.0; 3],
            };
        }
        let live = self.nodes.iter().flatten().count() + self.real.iter().flatten().count();
        if self.flight_start.is_none() && live > 0 && flying == live {
            self.flight_start = Some(t);
            // The episode's sensor noise starts with the episode, not after however many
            // scans the pre-flight took.
            self.sensor.reseed(sensor_seed(self.config.seed));
            // So do the wind and the position estimate's error.
            for node in self.nodes.iter_mut().flatten() {
                node.autopilot_mut().release();
            }
        }
        // 2. The world, with the velocities flown; then the autopilots follow the world. Until
        // every drone flies it holds still: the vehicles are released at takeoff, as a
        // simulator episode starts at step 0, so how long the processes take to arm and switch
        // modes (wall time) does not change the episode.
        self.before.clear();
        self.before.extend_from_slice(&self.world.herders);
        let before = &self.before;
        if self.flight_start.is_some() {
            advance(&mut self.world, &self.actions, &mut self.scratch)?;
            // ArduCopter's own physics decide where its herder is, to the centimetre.
            for (i, slot) in self.real.iter().enumerate() {
                if slot.is_some() {
                    self.world.herders[i] = self.real_targets[i];
                }
            }
            for (i, slot) in self.nodes.iter_mut().enumerate() {
                if let Some(node) = slot {
                    let p = self.world.herders[i];
                    let v = [
                        (p[0] - before[i][0]) / self.config.tick_s,
                        (p[1] - before[i][1]) / self.config.tick_s,
                        (p[2] - before[i][2]) / self.config.tick_s,
                    ];
                    node.autopilot_mut().set_state(sim_to_ned(p), sim_to_ned(v));
                }
            }
        } else {
            // Before the episode the vehicles take off on their own: the world follows them
            // (the flock holds still).
            for (i, slot) in self.nodes.iter().enumerate() {
                if let Some(node) = slot {
                    self.world.herders[i] = ned_to_sim(node.autopilot().position_ned());
                } else if self.real[i].is_some() {
                    self.world.herders[i] = self.real_targets[i];
                }
            }
        }
        if self.flight_start.is_some() && self.ending.is_none() {
            let closest = closest_pair_m(&self.world.herders);
            self.min_separation_m = self.min_separation_m.min(closest);
            if closest < self.config.separation_m {
                self.separation_breaches += 1;
            }
            self.path_length += before
                .iter()
                .zip(&self.world.herders)
                .map(|(a, b)| {
                    ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) + (b[2] - a[2]).powi(2)).sqrt()
                })
                .sum::<f64>();
        }
        // 3. The sensor.
        if t + 1e-9 >= self.next_scan {
            self.next_scan = t + self.config.sensor_period_s;
            let detections = self.sensor.scan(&self.world.targets);
            for message in scan_messages(t, &detections) {
                let bytes = self.sensor_codec.encode(&message);
                match self.sensor_socket.send_to(&bytes, self.config.ground) {
                    Ok(_) => {}
                    // Nobody listening yet (ICMP unreachable): the ground is starting or gone.
                    Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {}
                    Err(e) => return Err(e.into()),
                }
            }
        }
        self.time_s = t;
        self.wait_for_ground()?;
        // 4. The autopilots report where the world put them. After the ground has turned the
        // scan into a snapshot, so a daemon answering this position flies on targets seen at
        // the same instant, as a policy does in the simulator.
        for node in self.nodes.iter_mut().flatten() {
            node.send_telemetry(t)?;
        }
        // The truth decides the episode.
        if self.ending.is_none() {
            if self.world.anything_outside() {
                self.ending = Some((Ending::LeftArea, t));
                let area = self.world.area;
                self.left_area = self
                    .world
                    .herders
                    .iter()
                    .enumerate()
                    .filter(|(_, h)| !area.contains_xy([h[0], h[1]]))
                    .map(|(i, _)| format!("herder {}", i + 1))
                    .chain(
                        self.world
                            .targets
                            .iter()
                            .enumerate()
                            .filter(|(_, p)| !area.contains_xy(**p))
                            .map(|(i, _)| format!("target {}", i + 1)),
                    )
                    .collect();
            } else if self.world.all_targets_in_goal() {
                self.ending = Some((Ending::Success, t));
            } else if self
                .flight_start
                .is_some_and(|s| t - s > self.config.time_limit_s)
            {
                self.ending = Some((Ending::TimeLimit, t));
            }
        }
        // 5. Lockstep: wait for every daemon's answer to this tick's position.
        self.wait_for_answers(t)?;
        if self.config.speed > 0.0 {
            let due = Duration::from_secs_f64(t / self.config.speed);
            if let Some(rest) = due.checked_sub(self.wall_start.elapsed()) {
                thread::sleep(rest);
            }
        }
        Ok(TickReport {
            time_s: t,
            flying,
            armed,
            ending: self.ending.map(|(e, _)| e),
        })
    }

    /// Once the ground station acknowledges scans, wait (up to the lockstep timeout) until it
    /// has acted on the latest scan, so its snapshots are as fresh as the world.
    fn wait_for_ground(&mut self) -> Result<(), SitlError> {
        let start = Instant::now();
        let mut buffer = [0u8; 512];
        loop {
            loop {
                match self.sensor_socket.recv_from(&mut buffer) {
                    Ok((n, _)) => {
                        self.ack_frames.clear();
                        self.sensor_codec.decode(&buffer[..n], &mut self.ack_frames);
                        for frame in &self.ack_frames {
                            // (A late acknowledgement from a ground that has exited does
                            // not make the loop wait for it again.)
                            if let Some(at) = acknowledged_scan(&frame.message)
                                && self.ground_exit.is_none()
                            {
                                self.ground_acking = true;
                                self.acked_scan = self.acked_scan.max(at);
                            }
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                    Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => break,
                    Err(e) => return Err(e.into()),
                }
            }
            // Scans are stamped to the microsecond.
            let scanned = self.next_scan - self.config.sensor_period_s;
            if !self.ground_acking || self.acked_scan >= scanned - 1e-6 {
                self.ground_late = false;
                return Ok(());
            }
            // Once the episode has ended the ground stops acknowledging on purpose.
            let late = self.ground_late || self.ending.is_some();
            if start.elapsed() > self.lockstep_wait(late) {
                self.count_miss();
                self.ground_late = true;
                return Ok(());
            }
            thread::sleep(Duration::from_micros(50));
        }
    }

    /// Waits until every live drone whose companion has been heard answers this tick's
    /// position (in lockstep the daemon ends its answer to each one with a heartbeat, after
    /// any setpoint or command).
    fn wait_for_answers(&mut self, t: f64) -> Result<(), SitlError> {
        let start = Instant::now();
        let unanswered = |node: &AutopilotNode| {
            node.autopilot()
                .companion_heartbeat_at()
                .is_some_and(|at| at < t - 1e-9)
        };
        // Each daemon is waited for as long as its record allows: a miss gives up on it for
        // this tick only.
        let mut given_up = vec![false; self.nodes.len()];
        let (patient, brief) = (self.lockstep_wait(false), self.lockstep_wait(true));
        loop {
            let mut waiting = false;
            let elapsed = start.elapsed();
            for (i, gave_up) in given_up.iter_mut().enumerate() {
                if self.daemons_gone.contains(&i) || *gave_up {
                    continue;
                }
                let Some(node) = self.nodes[i].as_mut() else {
                    continue;
                };
                if !unanswered(node) {
                    continue;
                }
                // Same `t`: the autopilot receives without moving or re-sending telemetry.
                node.step(t)?;
                if !unanswered(node) {
                    self.late_daemons[i] = false;
                } else if elapsed > if self.late_daemons[i] { brief } else { patient } {
                    self.count_miss();
                    self.late_daemons[i] = true;
                    *gave_up = true;
                } else {
                    waiting = true;
                }
            }
            if !waiting {
                return Ok(());
            }
            thread::sleep(Duration::from_micros(50));
        }
    }

    fn count_miss(&mut self) {
        if self.flight_start.is_some() && self.ending.is_none() {
            self.lockstep_misses += 1;
        }
    }

    /// How long to wait for a process's lockstep answer: patiently for one that kept pace,
    /// briefly for one that missed its last answer or when the links lose datagrams on
    /// purpose.
    fn lockstep_wait(&self, late: bool) -> Duration {
        let faults = &self.config.faults;
        let lossy = faults.loss > 0.0 || faults.latency > 0.0 || !faults.cuts.is_empty();
        if late || lossy {
            self.config.lockstep_timeout
        } else {
            self.config
                .lockstep_patience
                .max(self.config.lockstep_timeout)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_config_out_of_range_is_refused_naming_the_setting() {
        let ground: SocketAddr = "127.0.0.1:9".parse().expect("literal");
        let ok = SitlConfig::new(Scenario::indoor(), 0, ground);
        assert!(ok.validate().is_ok());
        let field = |c: SitlConfig| match c.validate() {
            Err(SitlError::Invalid { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        let mut c = ok.clone();
        c.speed = f64::NAN;
        assert_eq!(field(c), "speed");
        let mut c = ok.clone();
        c.lose_drone = Some((2, 5.0)); // the indoor preset flies drones 0 and 1
        assert_eq!(field(c), "lost drone");
        let mut c = ok.clone();
        c.kill_daemon = Some((2, 5.0));
        assert_eq!(field(c), "killed daemon");
        let mut c = ok.clone();
        c.kill_daemon = Some((0, f64::NAN));
        assert_eq!(field(c), "killed daemon");
        let mut c = ok.clone();
        c.faults.loss = f64::NAN;
        assert_eq!(field(c), "loss");
        let mut c = ok.clone();
        c.time_limit_s = 0.0;
        assert_eq!(field(c), "time limit");
        for bad in [f64::NAN, -1.0, f64::INFINITY] {
            let mut c = ok.clone();
            c.land_after_s = bad;
            assert_eq!(field(c), "land after");
            let mut c = ok.clone();
            c.kill_ground_at = Some(bad);
            assert_eq!(field(c), "ground kill");
        }
        let mut c = ok;
        c.speed = -1.0;
        assert!(SitlWorld::new(c).is_err(), "the world refuses it too");
    }
}
