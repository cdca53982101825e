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

use std::fs::File;
use std::io::{Read, Write};
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Parser;
use skyherd_sim::scenario::HerderCount;
use skyherd_sim::{Scenario, World};
use skyherd_sitl::FaultConfig;
use skyherd_sitl::mission::{Ending, SitlConfig, SitlWorld};

#[derive(Parser, Debug)]
#[command(
    name = "skyherd-sitl",
    version,
    about = "Fly one SITL herding mission: simulator + ground station + one onboard daemon per drone"
)]
struct Cli {
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
    /// The trained model the drones fly.
    #[arg(long, default_value = "models/mtddpg-v3.skym")]
    model: PathBuf,
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
    /// Cut the ground's uplink to every drone for DURATION seconds from START (START,DURATION).
    #[arg(long)]
    cut_uplink: Option<String>,
    /// Give up this many simulated seconds after the drones start flying. A mission's abort
    /// limit is mission control's choice, not the scenario's training-episode step limit.
    #[arg(long, default_value_t = 300.0)]
    time_limit: f64,
}

/// A child process that is killed when dropped.
struct Guard(Option<Child>);

impl Drop for Guard {
    fn drop(&mut self) {
        if let Some(child) = &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn free_udp_port() -> Result<u16> {
    Ok(UdpSocket::bind("127.0.0.1:0")?.local_addr()?.port())
}

fn sibling(name: &str) -> Result<PathBuf> {
    let me = std::env::current_exe().context("locating this program")?;
    let path = me.with_file_name(name);
    if !path.exists() {
        bail!(
            "{} not found beside {} (build it: cargo build --release -p skyherd-ground -p skyherd-onboard --features skyherd-onboard/std)",
            name,
            me.display()
        );
    }
    Ok(path)
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let mut scenario = Scenario::from_arg(&cli.scenario)
        .with_context(|| format!("loading scenario {:?}", cli.scenario))?;
    if let Some(m) = cli.herders {
        scenario.herders = HerderCount::Fixed(m);
    }
    if let Some(n) = cli.targets {
        scenario.targets = n;
    }
    scenario.validate()?;
    let seed = cli.seed.unwrap_or(scenario.seed);
    if !cli.model.exists() {
        bail!(
            "model file {} not found (train one with skyherd-trainer, or pass --model)",
            cli.model.display()
        );
    }
    std::fs::create_dir_all(&cli.out).with_context(|| format!("creating {}", cli.out.display()))?;

    // A fresh signing key for this mission, shared by every link.
    let key_path = cli.out.join("mission.key");
    let key: [u8; 32] = std::array::from_fn(|i| {
        (seed
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .rotate_left(i as u32 * 7)
            >> 8) as u8
            ^ (std::process::id() as u8).wrapping_add(i as u8)
    });
    File::create(&key_path)?.write_all(&key)?;

    let ground_port = free_udp_port()?;
    let ground_addr: SocketAddr = ([127, 0, 0, 1], ground_port).into();
    let mut config = SitlConfig::new(scenario.clone(), seed, ground_addr);
    // The uplink (ground -> onboard computer) is signed; the autopilot links stand for the
    // serial cable on the drone and the telemetry radio's own link layer, and stay unsigned.
    config.speed = cli.speed;
    config.faults = FaultConfig {
        loss: cli.loss,
        latency: cli.latency_ms / 1000.0,
        cuts: Vec::new(),
    };
    if !(cli.time_limit.is_finite() && cli.time_limit > 0.0) {
        bail!("--time-limit must be a positive number of seconds");
    }
    config.time_limit_s = cli.time_limit;
    if let Some(spec) = &cli.lose_drone {
        let (index, at) = spec
            .split_once('@')
            .with_context(|| format!("--lose-drone must be INDEX@TIME, got {spec:?}"))?;
        config.lose_drone = Some((index.parse()?, at.parse()?));
    }
    let mut sitl = SitlWorld::new(config)?;
    let world = sitl.world().clone();
    let drones = world.herders.len();
    let autopilots = sitl.autopilot_addresses();
    eprintln!(
        "sitl: {} — {} drones, {} targets, seed {seed}, goal ({:.1}, {:.1}) r={:.2} m",
        scenario.name,
        drones,
        world.targets.len(),
        world.goal.center[0],
        world.goal.center[1],
        world.goal.radius
    );

    // The ground station.
    let uplink_ports: Vec<u16> = (0..drones)
        .map(|_| free_udp_port())
        .collect::<Result<_>>()?;
    let task = match world.task {
        skyherd_onboard::Task::Driving => "driving",
        skyherd_onboard::Task::Collecting => "collecting",
    };
    let mut ground_cmd = Command::new(sibling("skyherd-ground")?);
    ground_cmd
        .arg("mission")
        .arg("--fleet")
        .arg(format!("udpin:{ground_addr}"))
        .args(["--task", task])
        .arg("--goal")
        .arg(format!("{},{}", world.goal.center[0], world.goal.center[1]))
        .arg("--goal-radius")
        .arg(world.goal.radius.to_string())
        .arg("--area")
        .arg(format!(
            "{},{},{}",
            world.area.width, world.area.depth, world.area.ceiling
        ))
        .arg("--max-speed")
        .arg(scenario.limits.herder.to_string())
        .arg("--targets")
        .arg(world.targets.len().to_string())
        .arg("--measurement-std")
        .arg(scenario.noise.sensing_std.max(1e-3).to_string())
        .arg("--scan-period")
        .arg(sitl.config().sensor_period_s.to_string())
        .arg("--key")
        .arg(&key_path)
        .arg("--tlog")
        .arg(cli.out.join("ground.tlog"))
        .arg("--csv")
        .arg(cli.out.join("ground.csv"))
        // The ground stops one wall second after the last scan and prints its summary.
        .args(["--idle-timeout", "1"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    if let Some(cut) = &cli.cut_uplink {
        ground_cmd.arg("--cut-uplink").arg(cut);
    }
    for (i, port) in uplink_ports.iter().enumerate() {
        ground_cmd
            .arg("--drone")
            .arg(format!("{}=udpout:127.0.0.1:{port}", i + 1));
    }
    let mut ground = Guard(Some(ground_cmd.spawn().context("starting skyherd-ground")?));

    // One daemon per drone.
    let daemon_path = match &cli.daemon {
        Some(p) => p.clone(),
        None => sibling("skyherd-onboard")?,
    };
    let mut daemons = Vec::new();
    for i in 0..drones {
        let log = File::create(cli.out.join(format!("daemon-{}.log", i + 1)))?;
        let mut cmd = match &cli.daemon_wrapper {
            Some(wrapper) => {
                let mut parts = wrapper.split_whitespace();
                let program = parts.next().context("--daemon-wrapper is empty")?;
                let mut cmd = Command::new(program);
                cmd.args(parts).arg(&daemon_path);
                cmd
            }
            None => Command::new(&daemon_path),
        };
        cmd.arg("run")
            .arg("--model")
            .arg(&cli.model)
            .arg("--system-id")
            .arg((i + 1).to_string())
            .arg("--herder-index")
            .arg(i.to_string())
            .arg("--autopilot")
            .arg(format!("udpout:{}", autopilots[i]))
            .arg("--ground")
            .arg(format!("udpin:127.0.0.1:{}", uplink_ports[i]))
            .arg("--key")
            .arg(&key_path)
            .arg("--sim-clock")
            .arg("--max-speed")
            .arg(scenario.limits.herder.to_string())
            .stdout(Stdio::null())
            .stderr(log);
        daemons.push(Guard(Some(cmd.spawn().with_context(|| {
            format!("starting the daemon {}", daemon_path.display())
        })?)));
    }

    if !sitl.wait_for_daemons(Duration::from_secs(30))? {
        bail!(
            "the daemons did not reach their autopilots within 30 s (see {}/daemon-*.log)",
            cli.out.display()
        );
    }
    let wall = Instant::now();
    let mut states: Vec<World> = vec![sitl.world().clone()];
    let mut next_print = 0.0;
    let mut ended_at = None;
    let grace_s = 3.0;
    // A mission that never takes off (daemons that cannot arm, a ground that never starts) is
    // bounded in wall time: slow hosts (a daemon under qemu) need seconds to get going.
    let start_limit = Duration::from_secs(60);
    loop {
        let report = sitl.tick()?;
        let t = report.time_s;
        if ((t * 10.0).round() as u64).is_multiple_of(10) {
            states.push(sitl.world().clone());
        }
        if t >= next_print {
            next_print = t + 5.0;
            let w = sitl.world();
            let inside = w.targets.iter().filter(|p| w.goal.contains(**p)).count();
            eprintln!(
                "sitl: t={t:6.1}s flying {}/{} targets in goal {}/{} (wall {:.1}s)",
                report.flying,
                drones,
                inside,
                w.targets.len(),
                wall.elapsed().as_secs_f64()
            );
        }
        if let Some(ending) = report.ending
            && ended_at.is_none()
        {
            eprintln!("sitl: t={t:.1}s episode ended: {ending:?}");
            ended_at = Some(t);
        }
        if ended_at.is_some_and(|e| t - e >= grace_s) {
            break;
        }
        if sitl.flight_start().is_none() && wall.elapsed() > start_limit {
            eprintln!(
                "sitl: the drones did not all take off within {} s of wall time",
                start_limit.as_secs()
            );
            break;
        }
    }
    let wall_s = wall.elapsed().as_secs_f64();
    // The ground ends on its own once it has seen the mission through; give it a moment.
    let ground_summary = read_ground_summary(&mut ground, Duration::from_secs(3));
    drop(daemons);

    let (ending, end_time) = match sitl.ending() {
        Some((e, t)) => (Some(e), Some(t)),
        None => (None, None),
    };
    let start = sitl.flight_start();
    let success = ending == Some(Ending::Success);
    // Completion time counts only for a success, as in the paper.
    let mission_time = match (start, end_time) {
        (Some(s), Some(e)) if success => Some(e - s),
        _ => None,
    };
    let result = serde_json::json!({
        "scenario": scenario.name,
        "seed": seed,
        "herders": drones,
        "targets": world.targets.len(),
        "success": success,
        "ending": ending,
        "flight_start_s": start,
        "end_s": end_time,
        "mission_time_s": mission_time,
        "path_length_m": sitl.path_length(),
        "sim_time_s": sitl.time_s(),
        "wall_time_s": wall_s,
        "real_time_factor": sitl.time_s() / wall_s.max(1e-9),
        "lockstep_misses": sitl.lockstep_misses(),
        "autopilot_failsafes": sitl.failsafe_events(),
        "ground": ground_summary,
    });
    let result_path = cli.out.join("result.json");
    std::fs::write(&result_path, serde_json::to_string_pretty(&result)?)?;
    let plot_stem = cli.out.join("trajectory");
    let title = format!(
        "{}: {} drones, {} targets, seed {seed}",
        scenario.name,
        drones,
        world.targets.len()
    );
    let plots = skyherd_sim::plot::trajectory(&states, &title, &plot_stem)
        .map_err(|e| anyhow::anyhow!("plotting the trajectory: {e}"))?;
    print_summary(&result, &plots, &result_path);
    Ok(())
}

fn read_ground_summary(ground: &mut Guard, wait: Duration) -> serde_json::Value {
    let Some(child) = ground.0.as_mut() else {
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

fn print_summary(result: &serde_json::Value, plots: &[PathBuf], result_path: &Path) {
    let f = |k: &str| {
        result[k]
            .as_f64()
            .map_or("-".to_string(), |v| format!("{v:.1}"))
    };
    println!(
        "mission: {} | success: {} | time to goal: {} s (from takeoff) | herder path: {} m | sim {} s in wall {} s ({}x real time)",
        result["scenario"].as_str().unwrap_or("?"),
        result["success"],
        f("mission_time_s"),
        f("path_length_m"),
        f("sim_time_s"),
        f("wall_time_s"),
        f("real_time_factor"),
    );
    println!("result: {}", result_path.display());
    for p in plots {
        println!("plot:   {}", p.display());
    }
}
