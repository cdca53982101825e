//! `skyherd-sitl`: one complete software-in-the-loop herding mission.
//!
//! This process is the simulator (the world, one mock autopilot per drone, the tracking
//! sensor). It starts the ground station (`skyherd-ground`) and one onboard daemon
//! (`skyherd-onboard`) per drone as separate processes, all talking MAVLink 2 over UDP on
//! loopback with message signing, runs the mission in lockstep, and prints progress and the
//! final metrics; it writes a trajectory plot, the ground's `.tlog` and CSV, each daemon's log
//! and `result.json` into `--out`.
//!
//! ```text
//! skyherd-sitl --scenario indoor
//! skyherd-sitl --scenario paper-drive --herders 4 --targets 16 --speed 0
//! ```

use std::io::{Read, Write};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Parser;
use skyherd_link::Signing;
use skyherd_sim::dynamics::{DynamicsLimits, WindConfig};
use skyherd_sim::scenario::HerderCount;
use skyherd_sim::{Scenario, World};
use skyherd_sitl::FaultConfig;
use skyherd_sitl::console::{FlightSettings, MissionResult, MissionWatch, Stop};
use skyherd_sitl::launch::{self, Guard, KeyFolder, LaunchPlan};
use skyherd_sitl::mission::{Ending, SitlConfig, SitlError, SitlWorld};

#[derive(Parser, Debug)]
#[command(
    name = "skyherd-sitl",
    version,
    about = "Fly one SITL herding mission: simulator + ground station + one onboard daemon per drone",
    args_conflicts_with_subcommands = true,
    args_override_self = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Sub>,
    #[command(flatten)]
    mission: MissionArgs,
}

#[derive(clap::Subcommand, Debug)]
enum Sub {
    /// Run one mock autopilot for an outside client (MAVSDK, QGroundControl, pymavlink), on
    /// the wall clock, the way PX4's SITL does: it sends its MAVLink to the client's UDP port
    /// on loopback (14540 is MAVSDK's default `udpin://0.0.0.0:14540`) and answers whoever
    /// talks to it. Unsigned. Runs until killed or for --duration-s.
    Autopilot(AutopilotArgs),
}

#[derive(clap::Args, Debug)]
struct AutopilotArgs {
    /// The client's UDP port on 127.0.0.1.
    #[arg(long, default_value_t = 14540)]
    port: u16,
    /// Which autopilot to behave like.
    #[arg(long, value_enum, default_value_t = AutopilotArg::Px4)]
    autopilot: AutopilotArg,
    /// MAVLink system id.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=254))]
    system_id: u8,
    /// Stop after this many seconds [default: run until killed].
    #[arg(long)]
    duration_s: Option<f64>,
    /// Steps per second of the state machine and its motion.
    #[arg(long, default_value_t = 50.0)]
    rate_hz: f64,
}

#[derive(clap::Args, Debug)]
struct MissionArgs {
    /// Scenario preset (indoor, paper-drive, paper-collect) or TOML file.
    #[arg(long, default_value = "indoor")]
    scenario: String,
    /// Override the number of herders (drones).
    #[arg(long)]
    herders: Option<usize>,
    /// Override the number of targets.
    #[arg(long)]
    targets: Option<usize>,
    /// Episode seed [default: the scenario's].
    #[arg(long)]
    seed: Option<u64>,
    /// The trained model the drones fly [default: models/mtddpg-room.skym for a room whose
    /// drones fly their dynamics, else models/mtddpg-v3.skym].
    #[arg(long)]
    model: Option<PathBuf>,
    /// Output folder.
    #[arg(long, default_value = "out/mission")]
    out: PathBuf,
    /// 0 = as fast as possible, 1 = real time, k = k times real time.
    #[arg(long, default_value_t = 0.0)]
    speed: f64,
    /// Run each daemon through this command (e.g. "qemu-aarch64 -L /usr/aarch64-linux-gnu").
    #[arg(long)]
    daemon_wrapper: Option<String>,
    /// The daemon executable [default: skyherd-onboard beside this program].
    #[arg(long)]
    daemon: Option<PathBuf>,
    /// Probability that an autopilot-link datagram is lost, in [0, 1].
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// Latency added to autopilot-link datagrams, milliseconds of simulated time.
    #[arg(long, default_value_t = 0.0)]
    latency_ms: f64,
    /// Cut drone INDEX's autopilot link for good at simulated time T: INDEX@T.
    #[arg(long)]
    lose_drone: Option<String>,
    /// Fault: kill drone INDEX's onboard daemon (SIGKILL) at simulated time T: INDEX@T. The
    /// ground should then count that drone as lost.
    #[arg(long)]
    kill_daemon: Option<String>,
    /// Cut the ground's uplink to every drone for DURATION seconds from START (START,DURATION).
    #[arg(long)]
    cut_uplink: Option<String>,
    /// How the vehicles follow their setpoints: `auto` (the default: `room` in a room, `px4`
    /// in the arena), `off` (at once, the paper's protocol and every number measured before
    /// the dynamics model), `px4` (PX4 in Offboard: its velocity loop's lag, tilt and speed
    /// limits), `px4-auto` (PX4's jerk-limited mission trajectory on every setpoint) or `room`
    /// (PX4 in Offboard with the room's speed caps); see skyherd_sim::dynamics.
    #[arg(long, value_enum, default_value_t = DynamicsArg::Auto)]
    dynamics: DynamicsArg,
    /// The daemons keep apart by 10 % beyond the breach distance (0.5 m in a room, 3 m in the
    /// arena) with the reciprocal rule of skyherd_onboard::separation. On by default; this
    /// flag says so explicitly.
    #[arg(long, overrides_with = "no_keep_apart")]
    keep_apart: bool,
    /// Fly without the separation rule (the drones may come within centimetres).
    #[arg(long)]
    no_keep_apart: bool,
    /// The wind: `auto` (the default: with dynamics the room's draughts in a room and the
    /// arena's wind in the arena, calm without), `calm`, `arena` (3 m/s with 1 m/s gusts) or
    /// `room` (0.05 m/s draughts); anything but calm needs a motion model.
    #[arg(long, value_enum, default_value_t = WindArg::Auto)]
    wind: WindArg,
    /// With dynamics: the standard deviation of the autopilots' position-estimate error on
    /// each horizontal axis and on the vertical one, m (a Gauss-Markov wander over 5 s from
    /// none at the release): H,V, or one value for both [default: 0.03 in a room, 0.5,0.1 in
    /// the arena].
    #[arg(long, value_name = "H[,V]")]
    estimate_noise_m: Option<String>,
    /// Give up this many simulated seconds after the drones start flying. A mission's abort
    /// limit is mission control's choice, not the scenario's training-episode step limit.
    #[arg(long, default_value_t = 300.0)]
    time_limit: f64,
    /// The daemons land after their uplink has been stale this long in flight, simulated
    /// seconds (skyherd-onboard --land-after-s); 0: they hold until the ground is back.
    #[arg(long, default_value_t = 10.0)]
    land_after_s: f64,
    /// Fault: kill the ground station (SIGKILL) at this simulated time, seconds. The mission
    /// then fails, once the drones have landed on their own (or 30 simulated s later).
    #[arg(long)]
    kill_ground_at: Option<f64>,
    /// Which autopilot the mock drones behave like: `px4` (OFFBOARD, climbs on setpoints) or
    /// `ardupilot` (ArduCopter: GUIDED, NAV_TAKEOFF, positions only when asked). The daemons
    /// fly the matching flow.
    #[arg(long, value_enum, default_value_t = AutopilotArg::Px4)]
    autopilot: AutopilotArg,
    /// Fly these drones with a real ArduCopter SITL instead of a mock: `all`, or indices
    /// (`0`, `0,1`). Found through SKYHERD_ARDUCOPTER, ../shared/ardupilot-sitl or
    /// .arducopter (scripts/build-arducopter.sh). The mission then follows ArduCopter's clock.
    #[arg(long)]
    arducopter: Option<String>,
    /// ArduCopter's simulation speed over the wall clock (with --arducopter).
    #[arg(long, default_value_t = 5.0)]
    arducopter_speedup: f64,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum AutopilotArg {
    Px4,
    Ardupilot,
}

/// `--keep-apart`: the daemons' separation distance over the breach distance (the same as
/// `skyherd-sim eval --keep-apart`).
const KEEP_APART_MARGIN: f64 = skyherd_sim::learned::KEEP_APART_MARGIN as f64;

/// With an estimate error, the daemons keep this many of its standard deviations (per axis,
/// one autopilot's) beyond [`KEEP_APART_MARGIN`]: each drone steers on positions that are
/// off by its own and the peer's errors, which add to √2 σ along the line between them, and
/// twice that covers 95 % of the time. The room's 3 cm adds 8.5 cm (0.635 m): with the bare
/// 10 % margin one mission of 16 (seed 421) came to 0.489 m.
const ESTIMATE_ERRORS_KEPT: f64 = 2.0 * std::f64::consts::SQRT_2;

/// The distance (3-D, m) the daemons keep: the breach distance with its margin, plus the
/// autopilots' estimate error.
fn keep_apart_m(config: &SitlConfig) -> f64 {
    let estimate = if config.dynamics.is_some() {
        config.estimate_std_m
    } else {
        0.0
    };
    config.separation_m * KEEP_APART_MARGIN + ESTIMATE_ERRORS_KEPT * estimate
}

/// The exit status of a mission that ran but did not succeed (1 is an error before or during
/// the run): scripts can tell a failed mission from a broken one.
const MISSION_FAILED: u8 = 2;

/// A value's name on the command line (`px4-auto`).
fn value_name(value: impl clap::ValueEnum) -> String {
    value
        .to_possible_value()
        .map_or_else(String::new, |v| v.get_name().to_owned())
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum DynamicsArg {
    Auto,
    Off,
    Px4,
    Px4Auto,
    Room,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum WindArg {
    Auto,
    Calm,
    Arena,
    Room,
}

/// `skyherd-sitl autopilot`: one mock on the wall clock for an outside client.
fn run_autopilot(args: &AutopilotArgs) -> Result<std::process::ExitCode> {
    use skyherd_sitl::{AutopilotConfig, AutopilotNode, MockAutopilot, NodeOptions};
    if !(args.rate_hz.is_finite() && (10.0..=1000.0).contains(&args.rate_hz)) {
        bail!("--rate-hz must be 10 to 1000, got {}", args.rate_hz);
    }
    if let Some(d) = args.duration_s
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration-s must be a positive number of seconds, got {d}");
    }
    let flavour = match args.autopilot {
        AutopilotArg::Px4 => skyherd_link::Flavour::Px4,
        AutopilotArg::Ardupilot => skyherd_link::Flavour::ArduPilot,
    };
    let client: SocketAddr = ([127, 0, 0, 1], args.port).into();
    let autopilot = MockAutopilot::new(
        AutopilotConfig::for_flavour(flavour, args.system_id),
        [0.0; 3],
        0.0,
    );
    let mut node = AutopilotNode::bind(
        "127.0.0.1:0".parse().expect("literal address"),
        autopilot,
        NodeOptions {
            peers: vec![client],
            ..NodeOptions::default()
        },
    )
    .context("binding the autopilot's socket")?;
    say(format!(
        "autopilot: {flavour:?} mock, system {}, on the ground at home, sending to {client} from {}",
        args.system_id,
        node.local_addr()?
    ));
    let start = Instant::now();
    let period = Duration::from_secs_f64(1.0 / args.rate_hz);
    let mut next = start;
    loop {
        let now = start.elapsed().as_secs_f64();
        if args.duration_s.is_some_and(|d| now >= d) {
            return Ok(std::process::ExitCode::SUCCESS);
        }
        node.step(now).context("the autopilot's socket")?;
        next += period;
        if let Some(rest) = next.checked_duration_since(Instant::now()) {
            std::thread::sleep(rest);
        } else {
            next = Instant::now();
        }
    }
}

fn main() -> Result<std::process::ExitCode> {
    let cli = Cli::parse();
    if let Some(Sub::Autopilot(args)) = &cli.command {
        return run_autopilot(args);
    }
    let cli = cli.mission;
    let (scenario, seed) = cli.scenario()?;
    let ground_addr: SocketAddr = ([127, 0, 0, 1], free_udp_port()?).into();
    // Every flag is checked before anything is written or started.
    let mut config = cli.sitl_config(&scenario, seed, ground_addr)?;
    std::fs::create_dir_all(&cli.out).with_context(|| format!("creating {}", cli.out.display()))?;
    // Keys live outside the output folder, which is meant to be shared, and go with this
    // process (the folder is removed when `keys` drops).
    let keys = KeyFolder::provision(
        &std::env::temp_dir(),
        config.scenario.herders.resolve(config.scenario.targets),
    )
    .context("making the mission's signing keys")?;
    config.signing = Some(Signing {
        key: keys.fleet_key().clone(),
        link_id: 2,
        accept_unsigned: false,
    });
    let mut sitl = SitlWorld::new(config)?;
    let world = sitl.world().clone();
    let drones = world.herders.len();
    say(format!(
        "{} — {} drones, {} targets, seed {seed}, goal ({:.1}, {:.1}) r={:.2} m",
        scenario.name,
        drones,
        world.targets.len(),
        world.goal.center[0],
        world.goal.center[1],
        world.goal.radius
    ));
    let (dynamics, wind) = cli.flight_names(&scenario);
    let flight = FlightSettings {
        model: cli.model(&scenario).display().to_string(),
        dynamics,
        wind,
        keep_apart: cli.keeps_apart(),
        // The rule keeps 10 % beyond the breach distance (it steers on the other drones'
        // positions of the last snapshot, a tick old), and room for the estimate errors.
        keep_apart_m: cli.keeps_apart().then(|| keep_apart_m(sitl.config())),
    };
    say(format!(
        "flight: {} dynamics, {} wind, {}, model {}",
        flight.dynamics,
        flight.wind,
        match flight.keep_apart_m {
            Some(m) => format!("drones kept {m:.2} m apart"),
            None => "no separation rule".to_string(),
        },
        flight.model
    ));

    let plan = LaunchPlan {
        ground: launch::sibling("skyherd-ground")?,
        daemon: match &cli.daemon {
            Some(p) => p.clone(),
            None => launch::sibling("skyherd-onboard")?,
        },
        daemon_wrapper: cli.daemon_wrapper.clone(),
        model: cli.model(&scenario),
        keys: keys.path().to_path_buf(),
        out: cli.out.clone(),
        cut_uplink: cli.cut_uplink.clone(),
        keep_apart_m: flight.keep_apart_m,
        // As fast as possible, scans come every few milliseconds and a silent second means the
        // simulation is over; in real time (or slower) the pre-roll alone can take a second.
        ground_idle_timeout_s: if cli.speed > 0.0 {
            (3.0 / cli.speed).max(1.0)
        } else {
            1.0
        },
        land_after_s: sitl.config().land_after_s,
        takeoff_alt_m: sitl.config().takeoff_altitude_m,
        // With a dynamics model the daemons are told how the vehicles brake: its horizontal
        // deceleration, after its lag and the time its jerk limit takes to turn a full
        // acceleration into a full deceleration (the worst case: still speeding up towards
        // the wall when it must brake). The horizontal limit bounds the vector, so braking
        // along one axis while turning along the other gets 1/sqrt(2) of it.
        braking: sitl.config().dynamics.map(|d| {
            (
                d.max_accel_horizontal * std::f64::consts::FRAC_1_SQRT_2,
                d.time_constant + 2.0 * d.max_accel_horizontal / d.max_jerk,
            )
        }),
    };
    let uplink_ports: Vec<u16> = (0..drones)
        .map(|_| free_udp_port())
        .collect::<Result<_>>()?;
    let period = sitl.config().sensor_period_s;
    let ground_cmd =
        launch::ground_command(&plan, &scenario, &world, ground_addr, &uplink_ports, period);
    // The ground gives up after a second without scans; a real ArduCopter's pre-roll is
    // longer than that, so with one the ground starts once the pre-roll is over.
    let real = sitl.has_real_autopilots();
    let mut ground = if real {
        Guard::default()
    } else {
        launch::spawn(ground_cmd).context("starting skyherd-ground")?
    };
    let autopilots = sitl.autopilot_links();
    let mut daemons = Vec::new();
    for (i, port) in uplink_ports.iter().enumerate() {
        let cmd = launch::daemon_command(&plan, &scenario, i, &autopilots[i], *port)?;
        daemons.push(
            launch::spawn(cmd)
                .with_context(|| format!("starting the daemon {}", plan.daemon.display()))?,
        );
    }
    // A real ArduCopter's EKF needs about 42 s of its simulated time before it reports a
    // position.
    let pre_roll = if sitl.has_real_autopilots() { 180 } else { 30 };
    if !sitl.wait_for_daemons(Duration::from_secs(pre_roll))? {
        bail!(
            "the daemons did not reach their autopilots within {pre_roll} s (see {}/daemon-*.log{})",
            cli.out.display(),
            if sitl.has_real_autopilots() {
                " and arducopter-*.log"
            } else {
                ""
            }
        );
    }

    if real {
        let ground_cmd =
            launch::ground_command(&plan, &scenario, &world, ground_addr, &uplink_ports, period);
        ground = launch::spawn(ground_cmd).context("starting skyherd-ground")?;
    }
    let (states, wall_s) = fly(&mut sitl, world.targets.len(), &mut ground, &mut daemons)?;
    // The ground ends on its own once it has seen the mission through; give it a moment.
    let ground_summary = read_ground_summary(&mut ground, Duration::from_secs(3));
    drop(daemons);
    let result = mission_result(
        &sitl,
        &scenario,
        seed,
        &world,
        wall_s,
        ground_summary,
        flight,
    );
    let result_path = cli.out.join("result.json");
    std::fs::write(&result_path, serde_json::to_string_pretty(&result)?)?;
    let title = format!(
        "{}: {drones} drones, {} targets, seed {seed}",
        scenario.name,
        world.targets.len()
    );
    let plots = skyherd_sim::plot::trajectory(&states, &title, &cli.out.join("trajectory"))
        .map_err(|e| anyhow::anyhow!("plotting the trajectory: {e}"))?;
    println!("mission summary:");
    print!("{}", result.table());
    println!("  {:<13} {}", "result", result_path.display());
    for p in plots {
        println!("  {:<13} {}", "plot", p.display());
    }
    Ok(if result.success {
        std::process::ExitCode::SUCCESS
    } else {
        std::process::ExitCode::from(MISSION_FAILED)
    })
}

impl MissionArgs {
    fn scenario(&self) -> Result<(Scenario, u64)> {
        let mut scenario = Scenario::from_arg(&self.scenario)
            .with_context(|| format!("loading scenario {:?}", self.scenario))?;
        if let Some(m) = self.herders {
            scenario.herders = HerderCount::Fixed(m);
        }
        if let Some(n) = self.targets {
            scenario.targets = n;
        }
        scenario.validate()?;
        let model = self.model(&scenario);
        if !model.exists() {
            bail!(
                "model file {} not found (train one with skyherd-trainer, or pass --model)",
                model.display()
            );
        }
        Ok((scenario.clone(), self.seed.unwrap_or(scenario.seed)))
    }

    /// Whether `scenario` is a room (its breach distance is the room's 0.5 m, not the arena's).
    fn is_room(scenario: &Scenario) -> bool {
        scenario.area.breach_distance_m() <= 1.0
    }

    /// `--dynamics` and `--wind` for `scenario`, `auto` resolved: the room's model and draughts
    /// in a room, PX4's and the arena's wind in the arena, and no wind without a model.
    fn flight(&self, scenario: &Scenario) -> (DynamicsArg, WindArg) {
        let room = Self::is_room(scenario);
        let dynamics = match self.dynamics {
            DynamicsArg::Auto if room => DynamicsArg::Room,
            DynamicsArg::Auto => DynamicsArg::Px4,
            chosen => chosen,
        };
        let wind = match self.wind {
            WindArg::Auto if matches!(dynamics, DynamicsArg::Off) => WindArg::Calm,
            WindArg::Auto if room => WindArg::Room,
            WindArg::Auto => WindArg::Arena,
            chosen => chosen,
        };
        (dynamics, wind)
    }

    /// The motion model in force for `scenario` (none with `--dynamics off`).
    fn dynamics(&self, scenario: &Scenario) -> Option<DynamicsLimits> {
        match self.flight(scenario).0 {
            DynamicsArg::Off => None,
            DynamicsArg::Auto | DynamicsArg::Px4 => Some(DynamicsLimits::px4()),
            DynamicsArg::Px4Auto => Some(DynamicsLimits::px4_auto()),
            DynamicsArg::Room => Some(DynamicsLimits::indoor()),
        }
    }

    /// The wind in force for `scenario`.
    fn wind(&self, scenario: &Scenario) -> WindConfig {
        match self.flight(scenario).1 {
            WindArg::Auto | WindArg::Calm => WindConfig::CALM,
            WindArg::Arena => WindConfig::arena(),
            WindArg::Room => WindConfig::room(),
        }
    }

    /// The names of the motion model and wind in force, for the console and result.json.
    fn flight_names(&self, scenario: &Scenario) -> (String, String) {
        let (dynamics, wind) = self.flight(scenario);
        (value_name(dynamics), value_name(wind))
    }

    /// Whether the daemons run the separation rule (on unless `--no-keep-apart`).
    fn keeps_apart(&self) -> bool {
        !self.no_keep_apart || self.keep_apart
    }

    /// The model file: `--model`, else the mission's model for `scenario` and its dynamics.
    fn model(&self, scenario: &Scenario) -> PathBuf {
        match &self.model {
            Some(path) => path.clone(),
            None if Self::is_room(scenario) && self.dynamics(scenario).is_some() => {
                PathBuf::from("models/mtddpg-room.skym")
            }
            None => PathBuf::from("models/mtddpg-v3.skym"),
        }
    }

    fn sitl_config(
        &self,
        scenario: &Scenario,
        seed: u64,
        ground: SocketAddr,
    ) -> Result<SitlConfig> {
        let mut config = SitlConfig::new(scenario.clone(), seed, ground);
        // The uplink (ground -> onboard computer) is signed; the autopilot links stand for the
        // serial cable on the drone and the telemetry radio's own link layer, and stay unsigned.
        config.speed = self.speed;
        config.faults = FaultConfig {
            loss: self.loss,
            latency: self.latency_ms / 1000.0,
            cuts: Vec::new(),
        };
        if !(self.time_limit.is_finite() && self.time_limit > 0.0) {
            bail!("--time-limit must be a positive number of seconds");
        }
        config.time_limit_s = self.time_limit;
        config.land_after_s = self.land_after_s;
        config.kill_ground_at = self.kill_ground_at;
        if let Some(spec) = &self.arducopter {
            let drones = scenario.herder_count();
            let indices: Vec<usize> = if spec.trim() == "all" {
                (0..drones).collect()
            } else {
                spec.split(',')
                    .map(|v| v.trim().parse::<usize>())
                    .collect::<Result<_, _>>()
                    .with_context(|| {
                        format!(
                            "--arducopter must be `all` or drone indices like 0,1, got {spec:?}"
                        )
                    })?
            };
            if let Some(bad) = indices.iter().find(|&&i| i >= drones) {
                bail!("--arducopter: drone {bad} does not exist (drones are 0..{drones})");
            }
            if self.speed != 0.0 {
                bail!(
                    "--speed cannot be combined with --arducopter: the mission follows ArduCopter's clock (--arducopter-speedup)"
                );
            }
            let root = std::env::current_dir().context("the working folder")?;
            let bundle = skyherd_sitl::arducopter::ArduCopterBundle::locate(&root)?;
            config.arducopter = Some(skyherd_sitl::mission::RealDrones {
                bundle,
                indices,
                speedup: self.arducopter_speedup,
                logs: Some(self.out.clone()),
            });
        }
        config.autopilot = match self.autopilot {
            AutopilotArg::Px4 => skyherd_link::Flavour::Px4,
            AutopilotArg::Ardupilot => skyherd_link::Flavour::ArduPilot,
        };
        config.dynamics = self.dynamics(scenario);
        config.wind = self.wind(scenario);
        if let Some(spec) = &self.estimate_noise_m {
            let parts: Vec<&str> = spec.split(',').collect();
            let parsed: Vec<f64> = parts
                .iter()
                .map(|p| p.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .ok()
                .filter(|v: &Vec<f64>| {
                    matches!(v.len(), 1 | 2)
                        && v.iter().all(|s| s.is_finite() && (0.0..=10.0).contains(s))
                })
                .with_context(|| {
                    format!("--estimate-noise-m must be H or H,V with each 0 to 10 m, got {spec:?}")
                })?;
            let (horizontal, vertical) = (parsed[0], *parsed.last().unwrap_or(&parsed[0]));
            if config.dynamics.is_none() && (horizontal > 0.0 || vertical > 0.0) {
                bail!("--estimate-noise-m needs a motion model (--dynamics off has none)");
            }
            config.estimate_std_m = horizontal;
            config.estimate_vertical_std_m = vertical;
        }
        if config.dynamics.is_none() && config.wind != WindConfig::CALM {
            bail!("--wind needs a motion model (--dynamics other than off): nothing else feels it");
        }
        if let Some(spec) = &self.cut_uplink {
            // The ground applies it; checked here so that a bad value stops the mission before
            // any process starts, with the flag's name.
            let parts: Vec<f64> = spec
                .split(',')
                .map(|v| v.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .with_context(|| format!("--cut-uplink must be START,DURATION, got {spec:?}"))?;
            match parts[..] {
                [start, length]
                    if start.is_finite() && length.is_finite() && start >= 0.0 && length > 0.0 => {}
                _ => bail!(
                    "--cut-uplink must be START,DURATION with START >= 0 and DURATION > 0 seconds, got {spec:?}"
                ),
            }
        }
        config.kill_daemon = self
            .kill_daemon
            .as_deref()
            .map(|spec| drone_at(spec, "--kill-daemon"))
            .transpose()?;
        config.lose_drone = self
            .lose_drone
            .as_deref()
            .map(|spec| drone_at(spec, "--lose-drone"))
            .transpose()?;
        config.validate().map_err(|e| {
            let flag = match &e {
                SitlError::Invalid { field: "loss", .. } => "--loss",
                SitlError::Invalid {
                    field: "latency", ..
                } => "--latency-ms",
                SitlError::Invalid { field: "speed", .. } => "--speed",
                SitlError::Invalid {
                    field: "lost drone",
                    ..
                } => "--lose-drone",
                SitlError::Invalid {
                    field: "killed daemon",
                    ..
                } => "--kill-daemon",
                SitlError::Invalid {
                    field: "land after",
                    ..
                } => "--land-after-s",
                SitlError::Invalid {
                    field: "ground kill",
                    ..
                } => "--kill-ground-at",
                _ => "settings",
            };
            anyhow::anyhow!("{flag}: {e}")
        })?;
        Ok(config)
    }
}

/// A fault's `INDEX@TIME` (drone index, simulated seconds), as `flag` takes it; its range is
/// `SitlConfig::validate`'s to check.
fn drone_at(spec: &str, flag: &str) -> Result<(usize, f64)> {
    let (index, at) = spec
        .split_once('@')
        .with_context(|| format!("{flag} must be INDEX@TIME, got {spec:?}"))?;
    let index = index
        .parse()
        .with_context(|| format!("{flag} index in {spec:?}"))?;
    let at = at
        .parse()
        .with_context(|| format!("{flag} time in {spec:?}"))?;
    Ok((index, at))
}

/// One whole console line (stderr is shared with the ground station's).
fn say(line: String) {
    let _ = std::io::stderr().write_all(format!("sitl: {line}\n").as_bytes());
}

fn free_udp_port() -> Result<u16> {
    Ok(launch::free_udp_port()?)
}

/// Run the lockstep loop until the watcher stops it: the recorded states and the wall time.
/// Kills the ground station when the config says so, and watches it: one that exits before
/// the episode ended, other than cleanly (it exits 0 only after it has ended the mission with
/// its drones), ends the episode (`Ending::GroundExited`).
fn fly(
    sitl: &mut SitlWorld,
    targets: usize,
    ground: &mut Guard,
    daemons: &mut [Guard],
) -> Result<(Vec<World>, f64)> {
    let drones = sitl.world().herders.len();
    let mut watch = MissionWatch::new(drones, targets);
    let wall = Instant::now();
    let mut states: Vec<World> = vec![sitl.world().clone()];
    let mut kill_at = sitl.config().kill_ground_at;
    let mut kill_daemon = sitl.config().kill_daemon;
    let mut ground_watched = true;
    loop {
        let mut report = sitl.tick()?;
        if let Some((index, at)) = kill_daemon
            && report.time_s + 1e-9 >= at
            && let Some(child) = daemons.get_mut(index).and_then(Guard::child)
        {
            kill_daemon = None;
            sitl.daemon_gone(index);
            match child.kill() {
                Ok(()) => say(format!(
                    "t={:6.1}s fault: killing drone {}'s daemon (SIGKILL, pid {})",
                    report.time_s,
                    index + 1,
                    child.id()
                )),
                Err(e) => say(format!(
                    "fault: could not kill drone {}'s daemon: {e}",
                    index + 1
                )),
            }
        }
        if let Some(at) = kill_at
            && report.time_s + 1e-9 >= at
            && let Some(child) = ground.child()
        {
            kill_at = None;
            // Child::kill is SIGKILL on Unix: a kill -9, no chance to flush or say goodbye.
            match child.kill() {
                Ok(()) => say(format!(
                    "t={:6.1}s fault: killing the ground station (SIGKILL, pid {})",
                    report.time_s,
                    child.id()
                )),
                Err(e) => say(format!("fault: could not kill the ground station: {e}")),
            }
        }
        if ground_watched
            && let Some(child) = ground.child()
            && let Ok(Some(status)) = child.try_wait()
        {
            ground_watched = false;
            if status.success() && report.ending.is_none() {
                say(format!(
                    "t={:6.1}s the ground station finished its mission and exited",
                    report.time_s
                ));
            } else if report.ending.is_none() {
                say(format!(
                    "the ground station exited ({status}) at t={:.1}s, before the mission ended; waiting for the drones to land",
                    report.time_s
                ));
                sitl.ground_exited(status.to_string());
                report.ending = sitl.ending().map(|(e, _)| e);
            }
        }
        let w = sitl.world();
        let in_goal = w.targets.iter().filter(|p| w.goal.contains(**p)).count();
        let step = watch.observe(
            &report,
            in_goal,
            wall.elapsed().as_secs_f64(),
            sitl.flight_start().is_some(),
        );
        if step.record_state {
            states.push(sitl.world().clone());
        }
        if let Some(line) = step.progress {
            say(line);
        }
        match step.stop {
            Some(Stop::Ended) => break,
            Some(Stop::NoTakeoff) => {
                say(format!(
                    "the drones did not all take off within {} s of wall time",
                    skyherd_sitl::console::TAKEOFF_LIMIT_S
                ));
                break;
            }
            None => {}
        }
    }
    Ok((states, wall.elapsed().as_secs_f64()))
}

fn mission_result(
    sitl: &SitlWorld,
    scenario: &Scenario,
    seed: u64,
    world: &World,
    wall_s: f64,
    ground: serde_json::Value,
    flight: FlightSettings,
) -> MissionResult {
    let touchdown_s = sitl.touchdowns();
    let (ending, end_s) = match sitl.ending() {
        Some((e, t)) => (Some(e), Some(t)),
        None => (None, None),
    };
    let flight_start_s = sitl.flight_start();
    let success = ending == Some(Ending::Success);
    // Completion time counts only for a success, as in the paper.
    let mission_time_s = match (flight_start_s, end_s) {
        (Some(s), Some(e)) if success => Some(e - s),
        _ => None,
    };
    MissionResult {
        scenario: scenario.name.clone(),
        seed,
        herders: world.herders.len(),
        targets: world.targets.len(),
        success,
        ending,
        flight_start_s,
        end_s,
        mission_time_s,
        path_length_m: sitl.path_length(),
        sim_time_s: sitl.time_s(),
        wall_time_s: wall_s,
        real_time_factor: sitl.time_s() / wall_s.max(1e-9),
        lockstep_misses: sitl.lockstep_misses(),
        autopilot_failsafes: sitl.failsafe_events(),
        min_separation_m: Some(sitl.min_separation_m()).filter(|d| d.is_finite()),
        separation_breaches: sitl.separation_breaches(),
        separation_threshold_m: sitl.config().separation_m,
        ground,
        ground_exit_s: sitl.ground_exit().map(|(t, _)| *t),
        ground_exit: sitl.ground_exit().map(|(_, how)| how.clone()),
        drones_landed: touchdown_s.iter().flatten().count(),
        landing_start_s: sitl.landing_starts(),
        touchdown_s,
        left_area: sitl.left_area().to_vec(),
        flight,
    }
}

fn read_ground_summary(ground: &mut Guard, wait: Duration) -> serde_json::Value {
    let Some(child) = ground.child() else {
        return serde_json::Value::Null;
    };
    let deadline = Instant::now() + wait;
    while Instant::now() < deadline {
        if let Ok(Some(_)) = child.try_wait() {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    if child.try_wait().ok().flatten().is_none() {
        let _ = child.kill();
        let _ = child.wait();
    }
    let mut text = String::new();
    if let Some(out) = child.stdout.as_mut() {
        let _ = out.read_to_string(&mut text);
    }
    text.lines()
        .last()
        .and_then(|l| serde_json::from_str(l).ok())
        .unwrap_or(serde_json::Value::Null)
}
