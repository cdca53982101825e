//! `skyherd-ground`: the ground station. Tracks the vehicles from the sensor's anonymous
//! detections, hears the fleet, sends world snapshots up to every drone and runs the mission.
//!
//! ```text
//! skyherd-ground mission --fleet udpin:127.0.0.1:14550 \
//!     --drone 1=udpout:127.0.0.1:14601 --drone 2=udpout:127.0.0.1:14602 \
//!     --task driving --goal 8,8 --goal-radius 1.5 --area 10,10,3 --max-speed 1.5 \
//!     --targets 4 --key uplink.key --tlog out/ground.tlog --csv out/ground.csv
//! ```
//!
//! The mission clock is the tracking sensor's: every scan (MAVLink `DEBUG_VECT` detections, see
//! `skyherd_ground::detections`) advances it, updates the tracker and sends one snapshot to
//! each drone, so a simulator that runs faster than real time drives the ground with it.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use mavlink::dialects::common::MavMessage;
use skyherd_ground::detections::{ScanAssembler, scan_ack};
use skyherd_ground::fleet::{GroundLink, LinkConfig};
use skyherd_ground::mission::{
    AbortReason, DroneReport, MissionAction, MissionControl, MissionPlan, Phase,
};
use skyherd_ground::tracking::{TrackedWorld, Tracker, TrackerConfig};
use skyherd_ground::uplink::{SnapshotInputs, UplinkEncoder};
use skyherd_link::{Signing, SigningKey};
use skyherd_onboard::Task;
use skyherd_onboard::wire::MissionAction as WireAction;

#[derive(Parser, Debug)]
#[command(name = "skyherd-ground", version, about = "skyherd ground station")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run one mission: track, uplink, start, watch, finish; prints a JSON summary.
    Mission(MissionArgs),
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum TaskArg {
    Driving,
    Collecting,
}

#[derive(clap::Args, Debug)]
struct MissionArgs {
    /// Where the autopilots' telemetry and the sensor's scans arrive.
    #[arg(long, default_value = "udpin:127.0.0.1:14550")]
    fleet: String,
    /// One drone: SYSTEM_ID=ADDRESS of its onboard daemon's uplink (repeat; herder index =
    /// order given).
    #[arg(long = "drone", required = true)]
    drones: Vec<String>,
    /// MAVLink 2 signing key (32 raw bytes or 64 hex digits) for the uplinks to the drones'
    /// onboard computers.
    #[arg(long)]
    key: Option<PathBuf>,
    /// Signing key for the fleet link (autopilot telemetry and sensor scans) [default: unsigned].
    #[arg(long)]
    fleet_key: Option<PathBuf>,
    /// The task.
    #[arg(long, value_enum, default_value_t = TaskArg::Driving)]
    task: TaskArg,
    /// Goal centre X,Y (simulator frame, metres).
    #[arg(long)]
    goal: String,
    /// Goal radius, metres.
    #[arg(long)]
    goal_radius: f32,
    /// Arena WIDTH,DEPTH,CEILING from the origin, metres.
    #[arg(long)]
    area: String,
    /// Herders' speed limit, m/s.
    #[arg(long)]
    max_speed: f32,
    /// Targets expected; completion needs at least this many tracks.
    #[arg(long, default_value_t = 0)]
    targets: usize,
    /// Abort when not complete this long after the start, seconds of mission clock.
    #[arg(long, default_value_t = 600.0)]
    time_limit: f64,
    /// System id of the tracking sensor.
    #[arg(long, default_value_t = 200)]
    sensor_system_id: u8,
    /// Tracker measurement noise, metres (standard deviation).
    #[arg(long, default_value_t = 0.1)]
    measurement_std: f64,
    /// Time between the sensor's scans, seconds (widens the tracker's gate to what a target
    /// can move between two of them).
    #[arg(long, default_value_t = 0.1)]
    scan_period: f64,
    /// Give up when no scan arrives for this long, wall seconds.
    #[arg(long, default_value_t = 10.0)]
    idle_timeout: f64,
    /// Write the fleet link's MAVLink traffic here (pymavlink's .tlog format).
    #[arg(long)]
    tlog: Option<PathBuf>,
    /// Write one CSV row per scan here.
    #[arg(long)]
    csv: Option<PathBuf>,
    /// Fault injection: send nothing up to the drones from START for DURATION seconds of
    /// mission clock (START,DURATION).
    #[arg(long)]
    cut_uplink: Option<String>,
}

fn parse_floats<const N: usize>(text: &str, what: &str) -> Result<[f32; N]> {
    let values: Vec<f32> = text
        .split(',')
        .map(|v| v.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{what} must be {N} comma-separated numbers, got {text:?}"))?;
    let array: [f32; N] = values
        .try_into()
        .map_err(|_| anyhow::anyhow!("{what} must be {N} comma-separated numbers, got {text:?}"))?;
    if array.iter().any(|v| !v.is_finite()) {
        bail!("{what} must be finite, got {text:?}");
    }
    Ok(array)
}

fn parse_drone(text: &str) -> Result<(u8, String)> {
    let (id, address) = text
        .split_once('=')
        .with_context(|| format!("--drone must be SYSTEM_ID=ADDRESS, got {text:?}"))?;
    let id: u8 = id
        .parse()
        .with_context(|| format!("--drone system id must be 1..=254, got {id:?}"))?;
    if id == 0 || id == 255 {
        bail!("--drone system id must be 1..=254, got {id}");
    }
    Ok((id, address.to_string()))
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Mission(args) => mission(args),
    }
}

struct Uplinks {
    links: Vec<(u8, GroundLink)>,
    frames_sent: u64,
}

impl Uplinks {
    fn send(&mut self, system_id: u8, frames: &[MavMessage]) -> Result<()> {
        for (id, link) in &mut self.links {
            if *id == system_id {
                for frame in frames {
                    link.broadcast(frame)
                        .with_context(|| format!("uplink to drone {id}"))?;
                    self.frames_sent += 1;
                }
            }
        }
        Ok(())
    }

    fn drain(&mut self, now: f64) -> Result<()> {
        for (id, link) in &mut self.links {
            for frame in link
                .poll(now, Duration::ZERO)
                .with_context(|| format!("uplink from drone {id}"))?
            {
                if let MavMessage::STATUSTEXT(text) = &frame.message {
                    eprintln!(
                        "ground: drone {id} says: {}",
                        text.text.to_str().unwrap_or("?").trim_end_matches('\0')
                    );
                }
            }
            link.tick(now)?;
        }
        Ok(())
    }
}

fn mission(args: MissionArgs) -> Result<()> {
    let goal: [f32; 2] = parse_floats(&args.goal, "--goal")?;
    let area: [f32; 3] = parse_floats(&args.area, "--area")?;
    if !(args.goal_radius > 0.0 && args.max_speed > 0.0 && area.iter().all(|&a| a > 0.0)) {
        bail!("--goal-radius, --max-speed and --area must be positive");
    }
    let drones: Vec<(u8, String)> = args
        .drones
        .iter()
        .map(|d| parse_drone(d))
        .collect::<Result<_>>()?;
    let task = match args.task {
        TaskArg::Driving => Task::Driving,
        TaskArg::Collecting => Task::Collecting,
    };
    let read_key = |path: &Option<PathBuf>| {
        path.as_ref()
            .map(|path| SigningKey::from_file(path))
            .transpose()
            .context("reading a signing key")
    };
    let key = read_key(&args.key)?;
    let fleet_key = read_key(&args.fleet_key)?;
    let config = |key: &Option<SigningKey>, link_id: u8| LinkConfig {
        signing: key.clone().map(|key| Signing {
            key,
            link_id,
            accept_unsigned: false,
        }),
        ..LinkConfig::default()
    };

    let mut fleet = GroundLink::open(&args.fleet, config(&fleet_key, 0))
        .with_context(|| format!("opening the fleet link {}", args.fleet))?;
    if let Some(path) = &args.tlog {
        let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        fleet.log_to(Box::new(BufWriter::new(file)));
    }
    let mut uplinks = Uplinks {
        links: drones
            .iter()
            .enumerate()
            .map(|(i, (id, address))| {
                GroundLink::open(address, config(&key, i as u8 + 1))
                    .map(|link| (*id, link))
                    .with_context(|| format!("opening the uplink {address} of drone {id}"))
            })
            .collect::<Result<_>>()?,
        frames_sent: 0,
    };
    let mut csv = match &args.csv {
        Some(path) => {
            let mut w = BufWriter::new(
                File::create(path).with_context(|| format!("creating {}", path.display()))?,
            );
            write!(w, "time_s,phase,detections,tracks")?;
            for (id, _) in &drones {
                write!(w, ",d{id}_x,d{id}_y,d{id}_z")?;
            }
            writeln!(w)?;
            Some(w)
        }
        None => None,
    };

    let mut plan = MissionPlan::new(
        task,
        goal,
        args.goal_radius,
        area,
        drones.iter().map(|(id, _)| *id).collect(),
    );
    plan.expected_targets = args.targets;
    plan.time_limit_s = args.time_limit;
    let mut mission = MissionControl::new(plan);
    // The tracker's defaults are for the paper's arena (45 m goal, 5 m/s herders); a smaller
    // world scales them (see `TrackerConfig::scaled`).
    let mut tracker = Tracker::new(TrackerConfig::scaled(TrackedWorld {
        goal_radius: f64::from(args.goal_radius),
        max_speed: f64::from(args.max_speed),
        measurement_std: args.measurement_std,
        scan_period_s: args.scan_period,
    }))?;
    let mut uplink = UplinkEncoder::new();
    let mut assembler = ScanAssembler::default();
    let mut last_scan: Option<f64> = None;
    let mut last_scan_wall = Instant::now();
    let mut command_frames: Vec<MavMessage> = Vec::new();
    let mut last_command_at = f64::NEG_INFINITY;
    let mut ended_at: Option<f64> = None;
    let mut scans = 0u64;
    let mut sensor_silent = false;
    let mut now = 0.0;
    let mut herders = vec![[0.0f32; 3]; drones.len()];
    let cut: Option<[f32; 2]> = args
        .cut_uplink
        .as_deref()
        .map(|c| parse_floats(c, "--cut-uplink"))
        .transpose()?;
    let uplink_cut = |now: f64| {
        cut.is_some_and(|[start, length]| {
            now >= f64::from(start) && now < f64::from(start) + f64::from(length)
        })
    };
    let mut cut_reported = false;

    eprintln!(
        "ground: mission {task:?} to goal {goal:?} r={} with drones {:?}",
        args.goal_radius,
        drones.iter().map(|(id, _)| *id).collect::<Vec<_>>()
    );
    loop {
        let frames = fleet.poll(now, Duration::from_millis(5))?;
        let mut scan = None;
        for frame in &frames {
            if frame.header.system_id == u32::from(args.sensor_system_id)
                && let Some(s) = assembler.push(&frame.message)
            {
                scan = Some(s);
            }
        }
        uplinks.drain(now)?;
        fleet.tick(now)?;
        let Some(scan) = scan else {
            if last_scan_wall.elapsed().as_secs_f64() > args.idle_timeout {
                if scans == 0 {
                    bail!(
                        "no sensor scan for {} s (is the simulator running and sending to {}?)",
                        args.idle_timeout,
                        args.fleet
                    );
                }
                // The sensor went silent (the simulation ended, or the sensor failed): report
                // where the mission stood.
                eprintln!(
                    "ground: no sensor scan for {} s, stopping",
                    args.idle_timeout
                );
                sensor_silent = true;
                break;
            }
            continue;
        };
        last_scan_wall = Instant::now();
        scans += 1;
        let dt = last_scan.map_or(0.1, |t| scan.time_s - t);
        last_scan = Some(scan.time_s);
        now = scan.time_s;
        if dt > 0.0 {
            tracker.update(dt, &scan.detections)?;
        }
        let targets: Vec<[f32; 2]> = tracker
            .confirmed()
            .map(|t| [t.position[0] as f32, t.position[1] as f32])
            .collect();
        let reports: Vec<DroneReport> = drones
            .iter()
            .map(|(id, _)| {
                let vehicle = fleet.fleet().get(*id);
                DroneReport {
                    system_id: *id,
                    position: vehicle.and_then(|v| v.position_sim()),
                    last_heard: vehicle.map_or(f64::NEG_INFINITY, |v| v.link.last_heard),
                }
            })
            .collect();
        for (slot, report) in herders.iter_mut().zip(&reports) {
            if let Some(p) = report.position {
                *slot = p;
            }
        }

        match mission.update(now, &reports, &targets) {
            Some(MissionAction::Start) => {
                eprintln!("ground: t={now:.1}s every drone heard, starting the task");
                command_frames =
                    uplink.command(task, goal, args.goal_radius, WireAction::Start, 0)?;
                last_command_at = f64::NEG_INFINITY;
            }
            Some(MissionAction::Hold) => {
                eprintln!(
                    "ground: t={now:.1}s {:?}, telling every drone to hold",
                    mission.phase()
                );
                command_frames =
                    uplink.command(task, goal, args.goal_radius, WireAction::Abort, 0)?;
                last_command_at = f64::NEG_INFINITY;
                ended_at = Some(now);
            }
            None => {}
        }
        if uplink_cut(now) {
            if !cut_reported {
                eprintln!("ground: t={now:.1}s uplink cut (fault injection)");
                cut_reported = true;
            }
        } else if cut_reported {
            eprintln!("ground: t={now:.1}s uplink restored");
            cut_reported = false;
        }
        // Commands are repeated every second (same sequence number: the drones act once), so a
        // lost datagram only delays them.
        if now - last_command_at >= 1.0 && !uplink_cut(now) {
            if last_command_at.is_finite()
                && let Some(repeat) = uplink.repeat_command(0)
            {
                command_frames = repeat?;
            }
            if !command_frames.is_empty() {
                for (id, _) in &drones {
                    uplinks.send(*id, &command_frames)?;
                }
                last_command_at = now;
            }
        }
        if !matches!(mission.phase(), Phase::WaitingForFleet) && !uplink_cut(now) {
            let inputs = SnapshotInputs {
                task,
                herders: &herders,
                targets: &targets,
                goal,
                goal_radius: args.goal_radius,
                area,
                max_speed: args.max_speed,
                timestamp_ms: (now * 1000.0).round() as u64,
            };
            for (id, _) in &drones {
                let frames = uplink.snapshot(&inputs, *id)?;
                uplinks.send(*id, &frames)?;
            }
        }
        // Tell the sensor (a simulator keeps lockstep with it) that this scan is dealt with.
        // (A sensor that never spoke has no address yet; a real one need not listen.)
        let _ = fleet.send_to(args.sensor_system_id, &scan_ack(scan.time_s));
        if let Some(w) = &mut csv {
            write!(
                w,
                "{now:.3},{},{},{}",
                phase_name(mission.phase()),
                scan.detections.len(),
                targets.len()
            )?;
            for h in &herders {
                write!(w, ",{:.3},{:.3},{:.3}", h[0], h[1], h[2])?;
            }
            writeln!(w)?;
        }
        // After the end, keep repeating the hold for two seconds of mission clock, then stop.
        if ended_at.is_some_and(|t| now - t >= 2.0) {
            break;
        }
    }
    fleet.flush_log()?;
    if let Some(w) = &mut csv {
        w.flush()?;
    }
    let (outcome, reason, started, ended) = match mission.phase() {
        Phase::Complete { started_at, at } => ("complete", None, Some(started_at), Some(at)),
        Phase::Aborted { at, reason } => ("aborted", Some(reason), None, Some(at)),
        Phase::WaitingForFleet | Phase::Flying { .. } => ("unfinished", None, None, None),
    };
    let summary = serde_json::json!({
        "outcome": outcome,
        "abort_reason": reason.map(|r| match r {
            AbortReason::Geofence { system_id } => format!("geofence (drone {system_id})"),
            AbortReason::AllDronesLost => "all drones lost".to_string(),
            AbortReason::TimeLimit => "time limit".to_string(),
            AbortReason::Operator => "operator".to_string(),
        }),
        "started_at_s": started,
        "ended_at_s": ended,
        "scans": scans,
        "sensor_silent": sensor_silent,
        "incomplete_scans": assembler.incomplete_scans(),
        "tracks": tracker.confirmed().count(),
        "lost_drones": mission.lost(),
        "uplink_frames_sent": uplinks.frames_sent,
        "fleet_frames_dropped": fleet.stats().dropped_frames(),
    });
    println!("{summary}");
    Ok(())
}

fn phase_name(phase: Phase) -> &'static str {
    match phase {
        Phase::WaitingForFleet => "waiting",
        Phase::Flying { .. } => "flying",
        Phase::Complete { .. } => "complete",
        Phase::Aborted { .. } => "aborted",
    }
}
