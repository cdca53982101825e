//! `skyherd-ground`: the ground station. Tracks the vehicles from the sensor's anonymous
//! detections, hears the fleet, sends world snapshots up to every drone and runs the mission.
//!
//! ```text
//! skyherd-ground keygen --dir keys --drones 1,2 --fleet     # one key per drone, and the fleet's
//! skyherd-ground mission --fleet udpin:127.0.0.1:14550 --fleet-key keys/fleet.key \
//!     --drone 1=udpout:127.0.0.1:14601 --drone 2=udpout:127.0.0.1:14602 --key-dir keys \
//!     --task driving --goal 8,8 --goal-radius 1.5 --area 10,10,3 --max-speed 1.5 \
//!     --targets 4 --tlog out/ground.tlog --csv out/ground.csv
//! ```
//!
//! The mission loop is `skyherd_ground::station::GroundStation`, a pure core: this program
//! parses its arguments, opens the links and moves bytes between them and the core. The
//! mission clock is the tracking sensor's (MAVLink `DEBUG_VECT` scans, see
//! `skyherd_ground::detections`), so a simulator that runs faster than real time drives the
//! ground with it.

use std::fs::File;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use mavlink::dialects::common::MavMessage;
use skyherd_ground::fleet::{GroundLink, LinkConfig};
use skyherd_ground::mission::MissionPlan;
use skyherd_ground::spool::{Spool, SpoolStatus};
use skyherd_ground::station::{GroundStation, ScanRow, StationConfig, UplinkCut, drone_reports};
use skyherd_link::{Signing, SigningKey};
use skyherd_onboard::Task;

#[derive(Parser, Debug)]
#[command(name = "skyherd-ground", version, about = "skyherd ground station")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run one mission: track, uplink, start, watch, finish; prints a JSON summary.
    Mission(Box<MissionArgs>),
    /// Make signing keys from the operating system's randomness: `drone-ID.key` for each
    /// drone (shared by the ground and that drone only) and, with --fleet, `fleet.key` (the
    /// autopilots' and the sensor's link). Files are created 0600 and never overwritten.
    Keygen(KeygenArgs),
}

#[derive(clap::Args, Debug)]
struct KeygenArgs {
    /// Folder for the keys, created 0700 if missing.
    #[arg(long)]
    dir: PathBuf,
    /// System ids of the drones, comma-separated (1..=254).
    #[arg(long, value_delimiter = ',', required = true, value_parser = clap::value_parser!(u8).range(1..=254))]
    drones: Vec<u8>,
    /// Also make `fleet.key`.
    #[arg(long)]
    fleet: bool,
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
    /// A folder of per-drone uplink keys, `drone-ID.key` (as `keygen` makes them): each drone
    /// is signed to with its own key, so a frame for one drone is refused by every other.
    #[arg(long, conflicts_with = "key")]
    key_dir: Option<PathBuf>,
    /// One MAVLink 2 signing key (32 raw bytes or 64 hex digits) for every drone's uplink
    /// (prefer --key-dir: with one key, a frame for one drone passes every drone's check).
    #[arg(long)]
    key: Option<PathBuf>,
    /// Send unsigned uplink (bench tests only).
    #[arg(long, conflicts_with_all = ["key", "key_dir"])]
    insecure: bool,
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

/// `keygen`: one fresh key per drone (and the fleet's), each in a new 0600 file.
fn keygen(args: &KeygenArgs) -> Result<()> {
    let mut builder = std::fs::DirBuilder::new();
    builder.recursive(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::DirBuilderExt;
        builder.mode(0o700);
    }
    builder
        .create(&args.dir)
        .with_context(|| format!("creating {}", args.dir.display()))?;
    let mut names: Vec<String> = args
        .drones
        .iter()
        .map(|id| format!("drone-{id}.key"))
        .collect();
    if args.fleet {
        names.push("fleet.key".into());
    }
    for name in names {
        let path = args.dir.join(&name);
        SigningKey::generate()?.write_new_file(&path)?;
        println!("{}", path.display());
    }
    Ok(())
}

fn main() -> Result<()> {
    let args = match Cli::parse().command {
        Command::Mission(args) => *args,
        Command::Keygen(args) => return keygen(&args),
    };
    let mut station = GroundStation::new(args.station_config()?)?;
    let mut links = Links::open(&args, station.config().drones())?;
    let c = station.config();
    say(format!(
        "mission {:?} to goal ({:.1}, {:.1}) r={:.2} m with drones {:?}",
        c.plan.task, c.plan.goal[0], c.plan.goal[1], c.plan.goal_radius, c.plan.drones
    ));
    let sensor_silent = links.fly(&mut station, &args)?;
    links.fleet.flush_log()?;
    if let Some(w) = &mut links.csv {
        w.flush()?;
    }
    // The logs are written on threads of their own (skyherd_ground::spool): wait for them.
    for (name, status) in &links.spools {
        status
            .wait_written(LOG_DRAIN)
            .with_context(|| format!("writing the {name}"))?;
    }
    let mut summary = serde_json::to_value(station.summary())?;
    summary["sensor_silent"] = sensor_silent.into();
    summary["fleet_frames_dropped"] = links.fleet.stats().dropped_frames().into();
    println!("{summary}");
    Ok(())
}

/// A scan's handling (station, uplinks, logs) that takes longer than this is reported.
const SLOW_SCAN_WORK: Duration = Duration::from_millis(200);

/// How long the end of a mission waits for its log files to reach the disk.
const LOG_DRAIN: Duration = Duration::from_secs(10);

/// The station's sockets and files: the fleet link, one uplink per drone, the CSV log.
struct Links {
    fleet: GroundLink,
    uplinks: Vec<(u8, GroundLink)>,
    csv: Option<Spool>,
    /// The `.tlog` and CSV writers' progress, by file.
    spools: Vec<(String, SpoolStatus)>,
}

impl Links {
    fn open(args: &MissionArgs, drone_ids: &[u8]) -> Result<Self> {
        let shared_key = read_key(args.key.as_ref())?;
        if shared_key.is_none() && args.key_dir.is_none() && !args.insecure {
            bail!(
                "no uplink keys: pass --key-dir DIR (make one with skyherd-ground keygen), or --insecure for a bench test"
            );
        }
        let fleet_key = read_key(args.fleet_key.as_ref())?;
        let mut fleet = GroundLink::open(&args.fleet, link_config(&fleet_key, 0))
            .with_context(|| format!("opening the fleet link {}", args.fleet))?;
        let mut spools = Vec::new();
        if let Some(path) = &args.tlog {
            let tlog = Spool::new(create(path)?);
            spools.push((format!(".tlog {}", path.display()), tlog.status()));
            fleet.log_to(Box::new(tlog));
        }
        let mut uplinks = Vec::new();
        for (i, (id, address)) in args.drone_addresses()?.iter().enumerate() {
            let key = match &args.key_dir {
                Some(dir) => Some(
                    SigningKey::from_file(&dir.join(format!("drone-{id}.key")))
                        .with_context(|| format!("the uplink key of drone {id}"))?,
                ),
                None => shared_key.clone(),
            };
            let link = GroundLink::open(address, link_config(&key, i as u8 + 1))
                .with_context(|| format!("opening the uplink {address} of drone {id}"))?;
            uplinks.push((*id, link));
        }
        let csv = match &args.csv {
            Some(path) => {
                let mut w = Spool::new(create(path)?);
                spools.push((format!("CSV log {}", path.display()), w.status()));
                writeln!(w, "{}", ScanRow::csv_header(drone_ids))?;
                Some(w)
            }
            None => None,
        };
        Ok(Self {
            fleet,
            uplinks,
            csv,
            spools,
        })
    }

    /// Move bytes between the links and the station until the mission is over; whether the
    /// sensor went silent first.
    fn fly(&mut self, station: &mut GroundStation, args: &MissionArgs) -> Result<bool> {
        let mut now = 0.0;
        let mut last_scan_wall = Instant::now();
        let mut last_flush = Instant::now();
        let mut last_flush_at = f64::NEG_INFINITY;
        loop {
            let mut scan = None;
            for frame in self.fleet.poll(now, Duration::from_millis(5))? {
                scan = station
                    .hear(frame.header.system_id, &frame.message)
                    .or(scan);
            }
            drain_uplinks(&mut self.uplinks, station, now)?;
            self.fleet.tick(now)?;
            let Some(scan) = scan else {
                if last_scan_wall.elapsed().as_secs_f64() > args.idle_timeout {
                    if station.scans() == 0 {
                        bail!(
                            "no sensor scan for {} s (is the simulator running and sending to {}?)",
                            args.idle_timeout,
                            args.fleet
                        );
                    }
                    // The sensor went silent (the simulation ended, or the sensor failed).
                    say(format!(
                        "no sensor scan for {} s, stopping",
                        args.idle_timeout
                    ));
                    return Ok(true);
                }
                continue;
            };
            last_scan_wall = Instant::now();
            let work_started = last_scan_wall;
            let drones = drone_reports(self.fleet.fleet(), station.config().drones());
            let reply = station.on_scan(&scan, &drones)?;
            // The station's clock, not the scan's stamp: a forged or broken stamp is bounded.
            now = station.now();
            reply.events.iter().for_each(|e| say(e.to_string()));
            for (id, frames) in &reply.uplink {
                send_up(&mut self.uplinks, *id, frames)?;
            }
            // A sensor that never spoke has no address yet; a real one need not listen.
            let _ = self
                .fleet
                .send_to(station.config().sensor_system_id, &reply.scan_ack);
            if let Some(w) = &mut self.csv {
                writeln!(w, "{}", reply.row.csv())?;
            }
            // At least once a second, wall or mission time (a simulator runs many times faster
            // than real time), so that a killed ground leaves its CSV and .tlog readable, in
            // whole lines, up to the last second before it died.
            if last_flush.elapsed() >= Duration::from_secs(1) || now - last_flush_at >= 1.0 {
                if let Some(w) = &mut self.csv {
                    w.flush()?;
                }
                self.fleet.flush_log()?;
                last_flush = Instant::now();
                last_flush_at = now;
            }
            // A scan's work is a few milliseconds; a long one delays every drone's uplink.
            let work = work_started.elapsed();
            if work > SLOW_SCAN_WORK {
                say(format!(
                    "slow scan: {} ms from the scan to its replies and logs at t={now:.1} s",
                    work.as_millis()
                ));
            }
            if reply.finished {
                return Ok(false);
            }
        }
    }
}

/// One whole console line (stderr is shared with the other mission processes).
fn say(line: String) {
    // One write call per line: unbuffered stderr would otherwise write the pieces separately
    // and another process's line could land in between.
    let _ = std::io::stderr().write_all(format!("ground: {line}\n").as_bytes());
}

fn create(path: &std::path::Path) -> Result<File> {
    File::create(path).with_context(|| format!("creating {}", path.display()))
}

fn read_key(path: Option<&PathBuf>) -> Result<Option<SigningKey>> {
    path.map(|path| SigningKey::from_file(path))
        .transpose()
        .context("reading a signing key")
}

fn link_config(key: &Option<SigningKey>, link_id: u8) -> LinkConfig {
    LinkConfig {
        signing: key.clone().map(|key| Signing {
            key,
            link_id,
            accept_unsigned: false,
        }),
        ..LinkConfig::default()
    }
}

impl MissionArgs {
    fn drone_addresses(&self) -> Result<Vec<(u8, String)>> {
        let drones: Vec<(u8, String)> = self
            .drones
            .iter()
            .map(|d| parse_drone(d))
            .collect::<Result<_>>()?;
        for (i, (id, _)) in drones.iter().enumerate() {
            if drones[..i].iter().any(|(other, _)| other == id) {
                bail!("--drone system id {id} is given twice: each drone needs its own");
            }
        }
        Ok(drones)
    }

    fn station_config(&self) -> Result<StationConfig> {
        let goal: [f32; 2] = parse_floats(&self.goal, "--goal")?;
        let area: [f32; 3] = parse_floats(&self.area, "--area")?;
        if !(self.goal_radius > 0.0 && self.max_speed > 0.0 && area.iter().all(|&a| a > 0.0)) {
            bail!("--goal-radius, --max-speed and --area must be positive");
        }
        if !(self.goal_radius.is_finite() && self.max_speed.is_finite()) {
            bail!("--goal-radius and --max-speed must be finite");
        }
        if goal[0] < 0.0 || goal[1] < 0.0 || goal[0] > area[0] || goal[1] > area[1] {
            bail!(
                "--goal {},{} lies outside the area 0..{} x 0..{}",
                goal[0],
                goal[1],
                area[0],
                area[1]
            );
        }
        for (flag, v) in [
            ("--time-limit", self.time_limit),
            ("--scan-period", self.scan_period),
            ("--idle-timeout", self.idle_timeout),
            ("--measurement-std", self.measurement_std),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bail!("{flag} must be a finite number above 0, got {v}");
            }
        }
        let task = match self.task {
            TaskArg::Driving => Task::Driving,
            TaskArg::Collecting => Task::Collecting,
        };
        let drones = self
            .drone_addresses()?
            .into_iter()
            .map(|(id, _)| id)
            .collect();
        let mut plan = MissionPlan::new(task, goal, self.goal_radius, area, drones);
        plan.expected_targets = self.targets;
        plan.time_limit_s = self.time_limit;
        let mut config = StationConfig::new(plan, self.max_speed);
        config.sensor_system_id = self.sensor_system_id;
        config.measurement_std = self.measurement_std;
        config.scan_period_s = self.scan_period;
        config.uplink_cut = self
            .cut_uplink
            .as_deref()
            .map(|c| parse_floats::<2>(c, "--cut-uplink"))
            .transpose()?
            .map(|[start, length]| {
                if start < 0.0 || length <= 0.0 {
                    bail!("--cut-uplink needs START >= 0 and DURATION > 0 seconds, got {start},{length}");
                }
                Ok(UplinkCut {
                    start_s: f64::from(start),
                    duration_s: f64::from(length),
                })
            })
            .transpose()?;
        Ok(config)
    }
}

/// Send `frames` up to drone `system_id`.
fn send_up(uplinks: &mut [(u8, GroundLink)], system_id: u8, frames: &[MavMessage]) -> Result<()> {
    for (id, link) in uplinks.iter_mut().filter(|(id, _)| *id == system_id) {
        for frame in frames {
            link.broadcast(frame)
                .with_context(|| format!("uplink to drone {id}"))?;
        }
    }
    Ok(())
}

/// Read what the drones sent down their uplinks; relay their status texts (debounced).
fn drain_uplinks(
    uplinks: &mut [(u8, GroundLink)],
    station: &mut GroundStation,
    now: f64,
) -> Result<()> {
    for (id, link) in uplinks {
        for frame in link
            .poll(now, Duration::ZERO)
            .with_context(|| format!("uplink from drone {id}"))?
        {
            match &frame.message {
                MavMessage::STATUSTEXT(text) => {
                    if let Some(line) = station.drone_said(*id, text.text.to_str().unwrap_or("?")) {
                        say(line);
                    }
                }
                // The daemon's own heartbeat: its silence is the drone's (a dead daemon).
                MavMessage::HEARTBEAT(_) => station.daemon_heard(*id, now),
                _ => {}
            }
        }
        link.tick(now)?;
    }
    Ok(())
}
