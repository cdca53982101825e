//! `skyherd-onboard`: the companion-computer daemon that flies one drone with the int8 actor.
//!
//! ```text
//! skyherd-onboard run --model models/herd.skym --system-id 1 --herder-index 0 \
//!     --autopilot udpout:127.0.0.1:14540 --ground udpin:0.0.0.0:14600 --key uplink.key
//! skyherd-onboard run ... --sim-clock          # lockstep with a simulator's time_boot_ms
//! skyherd-onboard self-test [--model FILE]     # no sockets; prints one line
//! ```
//! Logging through `RUST_LOG` (default `info`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use skyherd_daemon::control::{CoreConfig, DaemonCore};
use skyherd_daemon::io::{ClockMode, Daemon, LinkOptions};
use skyherd_daemon::log_queue::LogQueue;
use skyherd_daemon::selftest;
use skyherd_link::Flavour;
use skyherd_link::SigningKey;
use skyherd_onboard::actor::Actor;
use skyherd_onboard::separation::SeparationConfig;

#[derive(Parser, Debug)]
#[command(
    name = "skyherd-onboard",
    version,
    about = "skyherd onboard daemon: flies one drone with the int8 MTDDPG actor over MAVLink"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Connect to the autopilot and the ground station and fly missions.
    Run(Box<RunArgs>),
    /// Exercise the core without sockets (model, encoder, actor, safety, wire, mission flow).
    SelfTest {
        /// A model file to check instead of the built-in seeded one.
        #[arg(long)]
        model: Option<PathBuf>,
    },
}

#[derive(clap::Args, Debug)]
struct RunArgs {
    /// Model file (.skym) with the int8 actor.
    #[arg(long)]
    model: PathBuf,
    /// Autopilot link: udpout:HOST:PORT, udpin:HOST:PORT, serial:DEVICE:BAUD, tcpout:HOST:PORT.
    #[arg(long, default_value = "udpout:127.0.0.1:14540")]
    autopilot: String,
    /// Ground link, same syntax. Loopback unless told otherwise: on a drone, name the radio's
    /// address (for example udpin:0.0.0.0:14600) deliberately.
    #[arg(long, default_value = "udpin:127.0.0.1:14600")]
    ground: String,
    /// MAVLink 2 signing key for the ground link (32 raw bytes or 64 hex digits). Required
    /// unless --insecure.
    #[arg(long)]
    key: Option<PathBuf>,
    /// Run without a key, accepting unsigned uplink from anyone who can reach the ground port:
    /// for bench tests only.
    #[arg(long)]
    insecure: bool,
    /// MAVLink 2 signing key for the autopilot link (the autopilot must hold the same key and
    /// verify it: then it refuses commands from anyone else) [default: unsigned].
    #[arg(long)]
    autopilot_key: Option<PathBuf>,
    /// Keep the uplink's replay state (per-stream signing timestamps) in this file, so that a
    /// restarted daemon still refuses frames it accepted before [default: in memory only].
    #[arg(long)]
    replay_state: Option<PathBuf>,
    /// This drone's MAVLink system id (its autopilot's).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=254))]
    system_id: u8,
    /// This drone's index in the ground's world snapshots [default: system id - 1].
    #[arg(long)]
    herder_index: Option<usize>,
    /// Autopilot family.
    #[arg(long, value_enum, default_value_t = FlavourArg::Px4)]
    flavour: FlavourArg,
    /// Control rate in wall-clock mode, Hz.
    #[arg(long, default_value_t = 20.0)]
    rate_hz: f32,
    /// Take time from the autopilot's time_boot_ms and tick once per LOCAL_POSITION_NED.
    #[arg(long)]
    sim_clock: bool,
    /// With --sim-clock: the autopilot runs on its own clock (a real ArduCopter SITL) rather
    /// than waiting for this daemon's answers (a lockstep simulator's mock), so its positions
    /// may run ahead of the ground's snapshots and a tick never waits long for one.
    #[arg(long, requires = "sim_clock")]
    autopilot_runs_free: bool,
    /// Speed limit, m/s [default: the model's].
    #[arg(long)]
    max_speed: Option<f32>,
    /// Hold when the newest world snapshot is older than this, ms of the daemon's clock
    /// (simulator time with --sim-clock).
    #[arg(long, default_value_t = 1000)]
    uplink_timeout_ms: u64,
    /// Land after the uplink has been stale this long in flight, seconds of the daemon's clock
    /// (a dead ground station); 0: never land, hold until the ground is back.
    #[arg(long, default_value_t = 10.0)]
    land_after_s: f64,
    /// Keep at least this far (3-D, m) from the other drones of the snapshot (the reciprocal
    /// rule of skyherd_onboard::separation); 0: off.
    #[arg(long, default_value_t = 0.0)]
    separation_m: f32,
    /// Take off to this height above the autopilot's home before flying the mission, m
    /// (PX4: climbing in OFFBOARD; ArduPilot: MAV_CMD_NAV_TAKEOFF in GUIDED).
    #[arg(long, default_value_t = 1.0)]
    takeoff_alt_m: f32,
    /// Where the autopilot's local origin (its home, where it booted) lies in the ground's
    /// world frame: EAST,NORTH metres [default: 0,0, the frames coincide].
    #[arg(long)]
    local_origin: Option<String>,
    /// The vehicle's braking, DECELERATION,LAG (m/s², s): the fence keeps the distance it
    /// needs to stop (its velocity lag plus v^2 / 2a) [default: it flies its setpoint at once].
    #[arg(long)]
    braking: Option<String>,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum FlavourArg {
    /// PX4 (OFFBOARD).
    Px4,
    /// ArduPilot (GUIDED).
    Ardupilot,
}

/// A model or key file, at most `skyherd_model::MAX_MODEL_FILE_BYTES` of it: a path such as
/// `/dev/zero` is refused instead of filling memory.
fn read(path: &Path, what: &str) -> Result<Vec<u8>> {
    use std::io::Read;
    let limit = skyherd_model::MAX_MODEL_FILE_BYTES;
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(limit + 1).read_to_end(&mut bytes))
        .with_context(|| format!("cannot read the {what} {}", path.display()))?;
    if bytes.len() as u64 > limit {
        bail!(
            "the {what} {} holds more than {limit} bytes: not a {what}",
            path.display()
        );
    }
    Ok(bytes)
}

/// `A,B`: two finite numbers, or an error naming `flag` and the `form` it wants.
fn finite_pair(spec: &str, flag: &str, form: &str) -> Result<[f32; 2]> {
    let parts: Vec<f32> = spec
        .split(',')
        .map(|v| v.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{flag} must be {form}, got {spec:?}"))?;
    match parts[..] {
        [a, b] if a.is_finite() && b.is_finite() => Ok([a, b]),
        _ => bail!("{flag} must be two finite numbers {form}, got {spec:?}"),
    }
}

fn run(args: RunArgs) -> Result<()> {
    let model_bytes = read(&args.model, "model file")?;
    let actor = Actor::from_bytes(&model_bytes)
        .with_context(|| format!("model file {} is not usable", args.model.display()))?;
    let signing_key = match &args.key {
        // Checked as the ground checks its keys: 32 raw bytes or 64 hex digits, at most 4 KiB
        // read, and (on Unix) no access for group or others.
        Some(path) => Some(SigningKey::from_file(path)?.0),
        None if args.insecure => {
            log::warn!("--insecure: unsigned uplink is accepted from anyone on the ground port");
            None
        }
        None => bail!(
            "no uplink signing key: pass --key FILE (skyherd-sitl makes one per mission), or --insecure for a bench test"
        ),
    };
    if !(args.rate_hz.is_finite() && args.rate_hz > 0.0 && args.rate_hz <= 1000.0) {
        bail!("--rate-hz must be in (0, 1000], got {}", args.rate_hz);
    }
    let flavour = match args.flavour {
        FlavourArg::Px4 => Flavour::Px4,
        FlavourArg::Ardupilot => Flavour::ArduPilot,
    };
    let herder_index = args.herder_index.unwrap_or(usize::from(args.system_id) - 1);
    let mut config = CoreConfig::new(args.system_id, herder_index, flavour);
    config.max_speed = args.max_speed.unwrap_or(actor.max_speed());
    config.uplink_timeout = std::time::Duration::from_millis(args.uplink_timeout_ms);
    // At most a day: Duration::from_secs_f64 panics past its range, and a longer wait is a
    // typo for "never" (0).
    if !(args.land_after_s.is_finite() && (0.0..=86_400.0).contains(&args.land_after_s)) {
        bail!(
            "--land-after-s must be 0 (never land) to 86400 seconds, got {}",
            args.land_after_s
        );
    }
    config.land_after =
        (args.land_after_s > 0.0).then(|| std::time::Duration::from_secs_f64(args.land_after_s));
    if !(args.separation_m.is_finite() && (0.0..=100.0).contains(&args.separation_m)) {
        bail!(
            "--separation-m must be 0 (off) to 100 m, got {}",
            args.separation_m
        );
    }
    if args.separation_m > 0.0 {
        config.separation = Some(SeparationConfig::keeping(
            args.separation_m,
            config.max_speed,
        ));
    }
    if !(args.takeoff_alt_m.is_finite() && (0.3..=100.0).contains(&args.takeoff_alt_m)) {
        bail!(
            "--takeoff-alt-m must be 0.3 to 100 m above home, got {}",
            args.takeoff_alt_m
        );
    }
    config.takeoff_altitude = args.takeoff_alt_m;
    if let Some(spec) = &args.braking {
        match finite_pair(spec, "--braking", "DECELERATION,LAG")? {
            [a, lag] if a > 0.0 && lag >= 0.0 => {
                let braking = skyherd_onboard::safety::Braking {
                    deceleration: a,
                    lag_s: lag,
                };
                config.braking = Some(braking);
                // A vehicle that brakes late also turns late: the separation rule counts it.
                if let Some(separation) = &mut config.separation {
                    separation.braking = Some(braking);
                }
            }
            _ => bail!("--braking must be a deceleration > 0 m/s^2 and a lag >= 0 s, got {spec:?}"),
        }
    }
    if let Some(spec) = &args.local_origin {
        config.local_origin = finite_pair(spec, "--local-origin", "EAST,NORTH metres")?;
    }
    if !(config.max_speed.is_finite() && config.max_speed > 0.0) {
        bail!(
            "--max-speed must be a positive number of m/s, got {}",
            config.max_speed
        );
    }
    let clock = if args.sim_clock {
        ClockMode::Simulator {
            lockstep: !args.autopilot_runs_free,
        }
    } else {
        ClockMode::Wall {
            rate_hz: args.rate_hz,
        }
    };
    let options = LinkOptions {
        autopilot: args.autopilot,
        ground: args.ground,
        signing_key,
        replay_state: args.replay_state,
        autopilot_key: args
            .autopilot_key
            .as_deref()
            .map(SigningKey::from_file)
            .transpose()?
            .map(|k| k.0),
        clock,
    };
    log::info!(
        "skyherd-onboard {}: system {} (herder {herder_index}), {flavour:?}, {clock:?}, max {} m/s, land after {:?} of stale uplink",
        env!("CARGO_PKG_VERSION"),
        args.system_id,
        config.max_speed,
        config.land_after
    );
    // Runs until the process is killed; holding is the autopilot's job once we are gone
    // (PX4 and ArduPilot fail safe when setpoints stop).
    let mut daemon = Daemon::connect(&options, DaemonCore::new(config, actor))?;
    daemon.run()?;
    Ok(())
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    // The self-test's one line is its output; its holds and warnings are expected.
    let default_level = match cli.command {
        Command::Run(_) => "info",
        Command::SelfTest { .. } => "error",
    };
    // Log lines reach stderr through a queue (skyherd_daemon::log_queue): a log file under
    // writeback pressure must not stall the control thread that logs.
    let (queued_stderr, log_writer) = LogQueue::spawn(std::io::stderr(), LOG_QUEUE_LINES);
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or(default_level))
        .target(env_logger::Target::Pipe(Box::new(queued_stderr)))
        .init();
    let result = run_command(cli.command);
    // The logger keeps its end of the queue for the process's life: what is queued is
    // written before the process ends.
    log_writer.wait_written(LOG_DRAIN);
    result
}

/// Log lines queued at most before new ones are dropped (and counted).
const LOG_QUEUE_LINES: usize = 4096;

/// How long an ending daemon waits at most for its log writer to catch up.
const LOG_DRAIN: std::time::Duration = std::time::Duration::from_secs(2);

fn run_command(command: Command) -> Result<()> {
    match command {
        Command::Run(args) => run(*args),
        Command::SelfTest { model } => {
            let file = match &model {
                Some(path) => Some((path.display().to_string(), read(path, "model file")?)),
                None => None,
            };
            let report = selftest::run(
                file.as_ref()
                    .map(|(name, bytes)| (name.as_str(), &bytes[..])),
            )?;
            println!("{report}");
            Ok(())
        }
    }
}
