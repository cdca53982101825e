//! The ground station's mission loop as a pure core: scans, telemetry and time in, what to
//! send out.
//!
//! [`GroundStation`] is shaped like smoltcp's `Interface::poll(now, ..)`: the caller owns the
//! sockets and the clock, hands in what arrived ([`GroundStation::hear`] for fleet frames,
//! [`GroundStation::drone_said`] for the drones' STATUSTEXT, [`GroundStation::on_scan`] once a
//! sensor scan is complete, with what the fleet says of each drone) and gets back the frames
//! to send ([`Reply`]), the events worth a console line ([`StationEvent`]) and one CSV row.
//!
//! The mission clock is the tracking sensor's: every scan advances it, updates the tracker and
//! sends one snapshot to each drone, so a simulator that runs faster than real time drives the
//! ground with it. Simulator frame (x east, y north, z up), metres, seconds.
//!
//! ```
//! use skyherd_ground::detections::Scan;
//! use skyherd_ground::mission::{DroneReport, MissionPlan};
//! use skyherd_ground::station::{GroundStation, StationConfig, StationEvent};
//! use skyherd_onboard::Task;
//!
//! let plan = MissionPlan::new(Task::Driving, [8.0, 8.0], 1.5, [10.0, 10.0, 3.0], vec![1]);
//! let config = StationConfig::new(plan, 1.0);
//! let mut station = GroundStation::new(config).unwrap();
//! let drone = [DroneReport { system_id: 1, position: Some([1.0, 1.0, 0.0]), last_heard: 0.0 }];
//! let scan = Scan { time_s: 0.0, detections: vec![[3.0, 3.0]], complete: true };
//! let reply = station.on_scan(&scan, &drone).unwrap();
//! assert_eq!(reply.events, vec![StationEvent::Started { at: 0.0 }]);
//! assert_eq!(reply.uplink.len(), 2); // the start command, then the first snapshot
//! ```

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;

use mavlink::dialects::common::MavMessage;
use serde::Serialize;
use skyherd_onboard::wire::MissionAction;
use thiserror::Error;

use crate::detections::{Scan, ScanAssembler, scan_ack};
use crate::fleet::Fleet;
use crate::mission::{AbortReason, DroneReport, MissionControl, MissionPlan, MissionStep, Phase};
use crate::tracking::{TrackedWorld, Tracker, TrackerConfig, TrackerError};
use crate::uplink::{SnapshotInputs, UplinkEncoder, UplinkError};

/// How often a mission command is repeated (same sequence number: the drones act once), so
/// a lost datagram only delays it. Seconds of mission clock.
const COMMAND_REPEAT_S: f64 = 1.0;
/// After the mission ends, the hold is repeated this long before the station stops. Seconds.
const HOLD_REPEAT_S: f64 = 2.0;
/// The time step assumed for the first scan, seconds (the tracker is not updated for it).
const FIRST_SCAN_DT_S: f64 = 0.1;

/// A fault to inject: nothing goes up to the drones in `[start_s, start_s + duration_s)` of
/// mission clock.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UplinkCut {
    /// Start, mission clock seconds.
    pub start_s: f64,
    /// Length, seconds.
    pub duration_s: f64,
}

impl UplinkCut {
    fn covers(&self, now: f64) -> bool {
        now >= self.start_s && now < self.start_s + self.duration_s
    }
}

/// What the station is asked to do.
#[derive(Clone, Debug, PartialEq)]
pub struct StationConfig {
    /// The mission: task, goal, arena (the geofence), drones, expected targets, limits.
    pub plan: MissionPlan,
    /// Herders' speed limit, m/s.
    pub max_speed: f32,
    /// System id of the tracking sensor.
    pub sensor_system_id: u8,
    /// Tracker measurement noise (standard deviation), metres.
    pub measurement_std: f64,
    /// Time between the sensor's scans, seconds.
    pub scan_period_s: f64,
    /// Fault injection: an uplink cut, if any.
    pub uplink_cut: Option<UplinkCut>,
}

impl StationConfig {
    /// A configuration for `plan` with the defaults of `skyherd-ground mission`: sensor
    /// system id 200, 0.1 m measurement noise, 0.1 s scans, no fault.
    pub fn new(plan: MissionPlan, max_speed: f32) -> Self {
        Self {
            plan,
            max_speed,
            sensor_system_id: 200,
            measurement_std: 0.1,
            scan_period_s: 0.1,
            uplink_cut: None,
        }
    }

    /// The drones' system ids, in herder order.
    pub fn drones(&self) -> &[u8] {
        &self.plan.drones
    }
}

/// Why the station could not go on.
#[derive(Debug, Error, PartialEq)]
pub enum StationError {
    /// The tracker refused its configuration or a time step.
    #[error("tracker: {0}")]
    Tracker(#[from] TrackerError),
    /// A snapshot or command could not be encoded for the uplink.
    #[error("uplink: {0}")]
    Uplink(#[from] UplinkError),
}

/// Something that happened, worth one console line.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StationEvent {
    /// Every drone was heard: the task starts.
    Started {
        /// Mission clock, s.
        at: f64,
    },
    /// The mission is over (complete or aborted); every drone is told to hold.
    Ended {
        /// Mission clock, s.
        at: f64,
        /// How it ended.
        phase: Phase,
    },
    /// The injected uplink cut began.
    UplinkCut {
        /// Mission clock, s.
        at: f64,
    },
    /// The injected uplink cut ended.
    UplinkRestored {
        /// Mission clock, s.
        at: f64,
    },
    /// A scan's time stamp went backwards or jumped further than a scan can: the mission
    /// clock moved on by one scan period instead (reported for the first such scan only).
    ClockJump {
        /// Mission clock, s.
        at: f64,
        /// The scan's own time stamp, s.
        stamped: f64,
    },
}

impl fmt::Display for StationEvent {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::Started { at } => write!(f, "t={at:.1}s every drone heard, starting the task"),
            Self::ClockJump { at, stamped } => write!(
                f,
                "t={at:.1}s a scan stamped {stamped:.1} s: not a step a sensor makes, the mission clock moves one scan period (further jumps are counted)"
            ),
            Self::Ended {
                at,
                phase: Phase::Complete { started_at, .. },
            } => write!(
                f,
                "t={at:.1}s mission complete ({:.1} s after the start command), holding",
                at - started_at
            ),
            Self::Ended {
                at,
                phase: Phase::Aborted { reason, .. },
            } => write!(
                f,
                "t={at:.1}s mission aborted ({}), telling every drone to hold",
                abort_text(reason)
            ),
            Self::Ended { at, phase } => write!(f, "t={at:.1}s {phase:?}, holding"),
            Self::UplinkCut { at } => write!(f, "t={at:.1}s uplink cut (fault injection)"),
            Self::UplinkRestored { at } => write!(f, "t={at:.1}s uplink restored"),
        }
    }
}

/// Words for an abort reason, as the summary reports it.
pub(crate) fn abort_text(reason: AbortReason) -> String {
    match reason {
        AbortReason::Geofence { system_id } => format!("geofence (drone {system_id})"),
        AbortReason::AllDronesLost => "all drones lost".to_string(),
        AbortReason::TimeLimit => "time limit".to_string(),
        AbortReason::Operator => "operator".to_string(),
    }
}

/// One row of the per-scan log.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanRow {
    /// Mission clock, s.
    pub time_s: f64,
    /// The mission's phase after this scan.
    pub phase: Phase,
    /// Detections in the scan.
    pub detections: usize,
    /// Confirmed tracks after it.
    pub tracks: usize,
    /// Every drone's last known position `[x, y, z]`, in herder order.
    pub herders: Vec<[f32; 3]>,
}

impl ScanRow {
    /// The CSV header for `drones` (system ids), matching [`ScanRow::csv`].
    pub fn csv_header(drones: &[u8]) -> String {
        let mut header = String::from("time_s,phase,detections,tracks");
        for id in drones {
            header.push_str(&format!(",d{id}_x,d{id}_y,d{id}_z"));
        }
        header
    }

    /// This row as CSV (no newline).
    pub fn csv(&self) -> String {
        let mut row = format!(
            "{:.3},{},{},{}",
            self.time_s,
            self.phase.name(),
            self.detections,
            self.tracks
        );
        for h in &self.herders {
            row.push_str(&format!(",{:.3},{:.3},{:.3}", h[0], h[1], h[2]));
        }
        row
    }
}

/// What to do after one scan.
#[derive(Clone, Debug, PartialEq)]
pub struct Reply {
    /// Frames for each drone's uplink, in the order to send them (commands first, then
    /// snapshots).
    pub uplink: Vec<(u8, Vec<MavMessage>)>,
    /// The acknowledgement to send to the sensor (a simulator keeps lockstep with it).
    pub scan_ack: MavMessage,
    /// Events worth a console line.
    pub events: Vec<StationEvent>,
    /// The per-scan log row.
    pub row: ScanRow,
    /// The mission is over and its hold has been repeated long enough: stop.
    pub finished: bool,
}

/// How the mission went, for the station's JSON summary.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StationSummary {
    /// `complete`, `aborted` or `unfinished`.
    pub outcome: &'static str,
    /// Why it was aborted, if it was.
    pub abort_reason: Option<String>,
    /// When the task started (completed missions only), mission clock s.
    pub started_at_s: Option<f64>,
    /// When it ended, mission clock s.
    pub ended_at_s: Option<f64>,
    /// Scans handled.
    pub scans: u64,
    /// Scans that lacked detections the sensor said it sent.
    pub incomplete_scans: u64,
    /// Confirmed tracks at the end.
    pub tracks: usize,
    /// Drones lost during the mission.
    pub lost_drones: Vec<u8>,
    /// Frames sent up to the drones.
    pub uplink_frames_sent: u64,
    /// Scans whose time stamp went backwards or jumped (see [`StationEvent::ClockJump`]).
    pub clock_jumps: u64,
}

/// Relays the drones' status texts to the console, debounced: a drone's status is reported
/// once per change of its reason set. A drone whose status flaps between "flying" and
/// "flying (altitude)" is reported once for each, until it changes kind (idle, preparing,
/// flying, holding), which starts a new set.
#[derive(Clone, Debug, Default)]
struct StatusRelay {
    per_drone: BTreeMap<u8, (String, BTreeSet<String>)>,
}

impl StatusRelay {
    fn relay(&mut self, system_id: u8, text: &str) -> Option<String> {
        let text = text.trim_end_matches('\0').trim();
        let status = text.strip_prefix("skyherd: ").unwrap_or(text);
        let kind = status
            .split([' ', ':', '('])
            .next()
            .unwrap_or(status)
            .to_string();
        let (last_kind, seen) = self.per_drone.entry(system_id).or_default();
        if *last_kind != kind {
            *last_kind = kind;
            seen.clear();
        }
        seen.insert(status.to_string())
            .then(|| format!("drone {system_id}: {status}"))
    }
}

/// The ground station's mission loop, without sockets or clock.
pub struct GroundStation {
    config: StationConfig,
    mission: MissionControl,
    tracker: Tracker,
    uplink: UplinkEncoder,
    assembler: ScanAssembler,
    relay: StatusRelay,
    last_scan: Option<f64>,
    command_frames: Vec<MavMessage>,
    last_command_at: f64,
    ended_at: Option<f64>,
    scans: u64,
    herders: Vec<[f32; 3]>,
    cut_reported: bool,
    uplink_frames_sent: u64,
    /// When each drone's onboard daemon was last heard on its uplink (mission clock).
    daemon_heard: BTreeMap<u8, f64>,
    /// The mission clock, s: advanced by each scan's step, bounded (see [`MAX_SCAN_STEP_S`]).
    clock: f64,
    clock_jumps: u64,
    /// The first scan's mission time, s.
    first_scan_s: Option<f64>,
}

/// The largest step between two scans' time stamps that moves the mission clock by itself:
/// ten scan periods, and at least 1 s. A longer step (a forged stamp 10^6 s ahead, say), or
/// one backwards, moves it by one scan period instead.
pub const MAX_SCAN_STEP_PERIODS: f64 = 10.0;
/// See [`MAX_SCAN_STEP_PERIODS`].
pub const MAX_SCAN_STEP_S: f64 = 1.0;

impl GroundStation {
    /// A station waiting for its fleet.
    ///
    /// # Errors
    /// [`StationError::Tracker`] when the tracker cannot be configured for this world.
    pub fn new(config: StationConfig) -> Result<Self, StationError> {
        // The tracker's defaults are for the paper's arena (45 m goal, 5 m/s herders); a
        // smaller world scales them (see `TrackerConfig::scaled`).
        let tracker = Tracker::new(TrackerConfig::scaled(TrackedWorld {
            goal_radius: f64::from(config.plan.goal_radius),
            max_speed: f64::from(config.max_speed),
            measurement_std: config.measurement_std,
            scan_period_s: config.scan_period_s,
        }))?;
        Ok(Self {
            herders: vec![[0.0; 3]; config.plan.drones.len()],
            mission: MissionControl::new(config.plan.clone()),
            tracker,
            uplink: UplinkEncoder::new(),
            assembler: ScanAssembler::default(),
            relay: StatusRelay::default(),
            last_scan: None,
            command_frames: Vec::new(),
            last_command_at: f64::NEG_INFINITY,
            ended_at: None,
            scans: 0,
            cut_reported: false,
            uplink_frames_sent: 0,
            daemon_heard: BTreeMap::new(),
            clock: 0.0,
            clock_jumps: 0,
            first_scan_s: None,
            config,
        })
    }

    /// The mission clock, s: the first scan's time stamp plus the bounded steps since.
    pub fn now(&self) -> f64 {
        self.clock
    }

    /// A HEARTBEAT from drone `system_id`'s onboard daemon on its uplink link, at mission time
    /// `now`. Once a daemon has been heard, its silence counts as the drone's: a drone whose
    /// autopilot still reports but whose daemon died cannot herd, so it is lost after
    /// `lost_after_s` like one that fell silent altogether.
    pub fn daemon_heard(&mut self, system_id: u8, now: f64) {
        let at = self.daemon_heard.entry(system_id).or_insert(now);
        *at = at.max(now);
    }

    /// The configuration.
    pub fn config(&self) -> &StationConfig {
        &self.config
    }

    /// The mission's phase.
    pub fn phase(&self) -> Phase {
        self.mission.phase()
    }

    /// Scans handled so far.
    pub fn scans(&self) -> u64 {
        self.scans
    }

    /// A frame heard on the fleet link from `system_id`: the completed scan, when this frame
    /// completes one of the sensor's.
    pub fn hear(&mut self, system_id: u32, message: &MavMessage) -> Option<Scan> {
        if system_id != u32::from(self.config.sensor_system_id) {
            return None;
        }
        self.assembler.push(message)
    }

    /// A drone's STATUSTEXT: the console line to print, or `None` when it is no news (see
    /// the debouncing rule on the relay).
    pub fn drone_said(&mut self, system_id: u8, text: &str) -> Option<String> {
        self.relay.relay(system_id, text)
    }

    /// One complete scan, with what the fleet says of every drone: track, decide, and say
    /// what to send.
    ///
    /// # Errors
    /// [`StationError`] when the tracker refuses the time step or the uplink cannot encode;
    /// the station is then in an undefined place in its mission and should stop.
    pub fn on_scan(&mut self, scan: &Scan, drones: &[DroneReport]) -> Result<Reply, StationError> {
        let mut events = Vec::new();
        let mut uplink = Vec::new();
        self.scans += 1;
        let max_step = (MAX_SCAN_STEP_PERIODS * self.config.scan_period_s).max(MAX_SCAN_STEP_S);
        let dt = match self.last_scan {
            None => {
                self.clock = scan.time_s;
                FIRST_SCAN_DT_S
            }
            Some(t) => {
                let step = scan.time_s - t;
                if step > 0.0 && step <= max_step {
                    self.clock += step;
                    step
                } else {
                    // Not obeyed: the clock moves one period, and the tracker one period.
                    self.clock += self.config.scan_period_s;
                    self.clock_jumps += 1;
                    if self.clock_jumps == 1 {
                        events.push(StationEvent::ClockJump {
                            at: self.clock,
                            stamped: scan.time_s,
                        });
                    }
                    self.config.scan_period_s
                }
            }
        };
        self.last_scan = Some(scan.time_s);
        let now = self.clock;
        if dt > 0.0 {
            self.tracker.update(dt, &scan.detections)?;
        }
        let targets: Vec<[f32; 2]> = self
            .tracker
            .confirmed()
            .map(|t| [t.position[0] as f32, t.position[1] as f32])
            .collect();
        for (slot, report) in self.herders.iter_mut().zip(drones) {
            if let Some(p) = report.position {
                *slot = p;
            }
        }

        // A drone is only as recent as its daemon, once that has spoken. What was heard before
        // the first scan was heard before the mission clock started (at 0, while the first
        // scan may be stamped 42 s: a real autopilot's clock): it counts as heard then.
        let first = self.first_scan_s.get_or_insert(scan.time_s).min(now);
        let drones: Vec<DroneReport> = drones
            .iter()
            .map(|d| {
                let vehicle = if d.last_heard.is_finite() {
                    d.last_heard.max(first)
                } else {
                    d.last_heard
                };
                let last_heard = match self.daemon_heard.get(&d.system_id) {
                    Some(&daemon) => vehicle.min(daemon.max(first)),
                    None => vehicle,
                };
                DroneReport { last_heard, ..*d }
            })
            .collect();
        let plan = &self.config.plan;
        let (task, goal, radius) = (plan.task, plan.goal, plan.goal_radius);
        match self.mission.update(now, &drones, &targets) {
            Some(MissionStep::Start) => {
                events.push(StationEvent::Started { at: now });
                self.command_frames =
                    self.uplink
                        .command(task, goal, radius, MissionAction::Start, 0)?;
                self.last_command_at = f64::NEG_INFINITY;
            }
            Some(MissionStep::Hold) => {
                let phase = self.mission.phase();
                events.push(StationEvent::Ended { at: now, phase });
                let action = match phase {
                    Phase::Complete { .. } => MissionAction::Complete,
                    _ => MissionAction::Abort,
                };
                self.command_frames = self.uplink.command(task, goal, radius, action, 0)?;
                self.last_command_at = f64::NEG_INFINITY;
                self.ended_at = Some(now);
            }
            None => {}
        }
        let cut = self.config.uplink_cut.is_some_and(|c| c.covers(now));
        if cut && !self.cut_reported {
            events.push(StationEvent::UplinkCut { at: now });
            self.cut_reported = true;
        } else if !cut && self.cut_reported {
            events.push(StationEvent::UplinkRestored { at: now });
            self.cut_reported = false;
        }
        if now - self.last_command_at >= COMMAND_REPEAT_S && !cut {
            if self.last_command_at.is_finite()
                && let Some(repeat) = self.uplink.repeat_command(0)
            {
                self.command_frames = repeat?;
            }
            if !self.command_frames.is_empty() {
                for &id in &self.config.plan.drones {
                    uplink.push((id, self.command_frames.clone()));
                }
                self.last_command_at = now;
            }
        }
        if !matches!(self.mission.phase(), Phase::WaitingForFleet) && !cut {
            let inputs = SnapshotInputs {
                task,
                herders: &self.herders,
                targets: &targets,
                goal,
                goal_radius: radius,
                area: self.config.plan.area,
                max_speed: self.config.max_speed,
                timestamp_ms: (now * 1000.0).round() as u64,
            };
            for &id in &self.config.plan.drones {
                uplink.push((id, self.uplink.snapshot(&inputs, id)?));
            }
        }
        self.uplink_frames_sent += uplink.iter().map(|(_, f)| f.len() as u64).sum::<u64>();
        Ok(Reply {
            uplink,
            scan_ack: scan_ack(scan.time_s),
            events,
            row: ScanRow {
                time_s: now,
                phase: self.mission.phase(),
                detections: scan.detections.len(),
                tracks: targets.len(),
                herders: self.herders.clone(),
            },
            finished: self.ended_at.is_some_and(|t| now - t >= HOLD_REPEAT_S),
        })
    }

    /// How the mission went so far.
    pub fn summary(&self) -> StationSummary {
        let (outcome, reason, started, ended) = match self.mission.phase() {
            Phase::Complete { started_at, at } => ("complete", None, Some(started_at), Some(at)),
            Phase::Aborted { at, reason } => ("aborted", Some(abort_text(reason)), None, Some(at)),
            Phase::WaitingForFleet | Phase::Flying { .. } => ("unfinished", None, None, None),
        };
        StationSummary {
            outcome,
            abort_reason: reason,
            started_at_s: started,
            ended_at_s: ended,
            scans: self.scans,
            incomplete_scans: self.assembler.incomplete_scans(),
            tracks: self.tracker.confirmed().count(),
            lost_drones: self.mission.lost().to_vec(),
            uplink_frames_sent: self.uplink_frames_sent,
            clock_jumps: self.clock_jumps,
        }
    }
}

/// What the fleet says of each of `drones` (system ids), for [`GroundStation::on_scan`].
pub fn drone_reports(fleet: &Fleet, drones: &[u8]) -> Vec<DroneReport> {
    drones
        .iter()
        .map(|&id| {
            let vehicle = fleet.get(id);
            DroneReport {
                system_id: id,
                position: vehicle.and_then(|v| v.position_sim()),
                last_heard: vehicle.map_or(f64::NEG_INFINITY, |v| v.link.last_heard),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_onboard::Task;
    use skyherd_onboard::wire::{Reassembler, Uplink, decode_uplink};

    const GOAL: [f32; 2] = [8.0, 8.0];

    fn station(drones: Vec<u8>) -> GroundStation {
        let mut plan = MissionPlan::new(Task::Driving, GOAL, 1.5, [10.0, 10.0, 3.0], drones);
        plan.expected_targets = 2;
        plan.time_limit_s = 60.0;
        let mut config = StationConfig::new(plan, 1.0);
        config.measurement_std = 0.05;
        GroundStation::new(config).unwrap()
    }

    fn drone(system_id: u8, position: [f32; 3], last_heard: f64) -> DroneReport {
        DroneReport {
            system_id,
            position: Some(position),
            last_heard,
        }
    }

    fn scan(time_s: f64, detections: &[[f64; 2]]) -> Scan {
        Scan {
            time_s,
            detections: detections.to_vec(),
            complete: true,
        }
    }

    /// Every uplink message the reply sends to `system_id`, decoded as the drone would.
    fn decoded(reply: &Reply, system_id: u8) -> Vec<Uplink> {
        let mut out = Vec::new();
        for (id, frames) in &reply.uplink {
            if *id != system_id {
                continue;
            }
            let mut reassembler = Reassembler::new();
            for frame in frames {
                let MavMessage::TUNNEL(t) = frame else {
                    panic!("uplink frames are TUNNEL frames")
                };
                if let Some(bytes) = reassembler
                    .push(&t.payload[..usize::from(t.payload_length)])
                    .unwrap()
                {
                    out.push(decode_uplink(bytes).unwrap());
                }
            }
        }
        out
    }

    fn command_actions(reply: &Reply, system_id: u8) -> Vec<MissionAction> {
        decoded(reply, system_id)
            .into_iter()
            .filter_map(|u| match u {
                Uplink::Command(c) => Some(c.action),
                Uplink::Snapshot(_) => None,
            })
            .collect()
    }

    fn snapshots(reply: &Reply, system_id: u8) -> usize {
        decoded(reply, system_id)
            .iter()
            .filter(|u| matches!(u, Uplink::Snapshot(_)))
            .count()
    }

    #[test]
    fn it_waits_until_every_drone_is_heard_then_starts() {
        let mut s = station(vec![1, 2]);
        let only_one = [
            drone(1, [1.0, 1.0, 0.0], 0.0),
            DroneReport {
                system_id: 2,
                position: None,
                last_heard: f64::NEG_INFINITY,
            },
        ];
        let reply = s.on_scan(&scan(0.0, &[[3.0, 3.0]]), &only_one).unwrap();
        assert!(reply.events.is_empty() && reply.uplink.is_empty());
        assert_eq!(s.phase(), Phase::WaitingForFleet);
        assert_eq!(reply.row.phase.name(), "waiting");

        let both = [
            drone(1, [1.0, 1.0, 0.0], 0.1),
            drone(2, [2.0, 1.0, 0.0], 0.1),
        ];
        let reply = s.on_scan(&scan(0.1, &[[3.0, 3.0]]), &both).unwrap();
        assert_eq!(reply.events, vec![StationEvent::Started { at: 0.1 }]);
        for id in [1, 2] {
            assert_eq!(command_actions(&reply, id), vec![MissionAction::Start]);
            assert_eq!(snapshots(&reply, id), 1);
        }
        assert_eq!(reply.row.herders, vec![[1.0, 1.0, 0.0], [2.0, 1.0, 0.0]]);
        assert!(!reply.finished);
    }

    #[test]
    fn the_start_is_repeated_every_second_and_snapshots_go_up_every_scan() {
        let mut s = station(vec![1]);
        let mut starts = 0;
        for k in 0..=25 {
            let t = f64::from(k) * 0.1;
            let reply = s
                .on_scan(&scan(t, &[[3.0, 3.0]]), &[drone(1, [1.0, 1.0, 0.0], t)])
                .unwrap();
            starts += command_actions(&reply, 1).len();
            assert_eq!(snapshots(&reply, 1), 1, "t={t}");
        }
        // At 0.0, then about every second after (1.0 and 2.0 on a 0.1 s grid, give or take
        // the rounding of the grid).
        assert!((2..=3).contains(&starts), "{starts} starts");
    }

    #[test]
    fn targets_settled_in_the_goal_complete_the_mission_and_the_drones_hold() {
        let mut s = station(vec![1]);
        let in_goal = [[8.0, 8.2], [7.8, 7.9]];
        let mut ended = None;
        let mut finished_at = None;
        for k in 0..80 {
            let t = f64::from(k) * 0.1;
            let reply = s
                .on_scan(&scan(t, &in_goal), &[drone(1, [1.0, 1.0, 1.0], t)])
                .unwrap();
            if let Some(StationEvent::Ended { at, phase }) = reply.events.first().copied() {
                assert!(matches!(phase, Phase::Complete { .. }));
                assert_eq!(command_actions(&reply, 1), vec![MissionAction::Complete]);
                assert!(reply.events[0].to_string().contains("mission complete"));
                ended = Some(at);
            }
            if reply.finished {
                finished_at = Some(t);
                break;
            }
        }
        let ended = ended.expect("the mission completed");
        // Tracks are confirmed after a few scans, then must stay inside for the settle time.
        assert!((1.0..3.0).contains(&ended), "completed at {ended}");
        // The hold is repeated for two seconds, then the station is done.
        assert!(finished_at.unwrap() - ended >= HOLD_REPEAT_S - 1e-9);
        let summary = s.summary();
        assert_eq!(summary.outcome, "complete");
        assert_eq!(summary.tracks, 2);
        assert_eq!(summary.started_at_s, Some(0.0));
    }

    #[test]
    fn losing_the_only_drone_aborts_and_losing_one_of_two_does_not() {
        let mut alone = station(vec![1]);
        let mut pair = station(vec![1, 2]);
        let mut aborted = None;
        for k in 0..60 {
            let t = f64::from(k) * 0.1;
            // Drone 1 is last heard at 0.5 s; drone 2 keeps talking.
            let heard = t.min(0.5);
            let r = alone
                .on_scan(&scan(t, &[[3.0, 3.0]]), &[drone(1, [1.0, 1.0, 1.0], heard)])
                .unwrap();
            if let Some(StationEvent::Ended { phase, .. }) = r.events.first() {
                aborted.get_or_insert(*phase);
                assert_eq!(command_actions(&r, 1), vec![MissionAction::Abort]);
            }
            let both = [
                drone(1, [1.0, 1.0, 1.0], heard),
                drone(2, [2.0, 1.0, 1.0], t),
            ];
            let r = pair.on_scan(&scan(t, &[[3.0, 3.0]]), &both).unwrap();
            assert!(
                !r.events
                    .iter()
                    .any(|e| matches!(e, StationEvent::Ended { .. })),
                "one lost drone of two must not end the mission"
            );
        }
        assert!(matches!(
            aborted,
            Some(Phase::Aborted {
                reason: AbortReason::AllDronesLost,
                ..
            })
        ));
        assert_eq!(
            alone.summary().abort_reason.as_deref(),
            Some("all drones lost")
        );
        assert_eq!(pair.summary().lost_drones, vec![1]);
        assert_eq!(pair.summary().outcome, "unfinished");
    }

    #[test]
    fn a_dead_daemon_is_a_lost_drone_though_its_autopilot_still_reports() {
        let mut pair = station(vec![1, 2]);
        for k in 0..80 {
            let t = f64::from(k) * 0.1;
            // Both autopilots report every scan; drone 1's daemon falls silent after 1 s,
            // drone 2's keeps its heartbeat. A daemon never heard (none here) changes nothing.
            if t <= 1.0 {
                pair.daemon_heard(1, t);
            }
            pair.daemon_heard(2, t);
            let both = [drone(1, [1.0, 1.0, 1.0], t), drone(2, [2.0, 1.0, 1.0], t)];
            pair.on_scan(&scan(t, &[[3.0, 3.0]]), &both).unwrap();
        }
        assert_eq!(pair.summary().lost_drones, vec![1]);
        // Without daemon heartbeats at all, both autopilots reporting keep both drones.
        let mut quiet = station(vec![1, 2]);
        for k in 0..80 {
            let t = f64::from(k) * 0.1;
            let both = [drone(1, [1.0, 1.0, 1.0], t), drone(2, [2.0, 1.0, 1.0], t)];
            quiet.on_scan(&scan(t, &[[3.0, 3.0]]), &both).unwrap();
        }
        assert!(quiet.summary().lost_drones.is_empty());
    }

    #[test]
    fn a_forged_scan_stamp_does_not_drag_the_mission_clock() {
        let mut pair = station(vec![1, 2]);
        let mut jumps = Vec::new();
        for k in 0..40 {
            let t = f64::from(k) * 0.1;
            // Scan 20 carries a stamp 10^6 s ahead (the attack that once made the ground
            // declare every drone lost); the real scans go on after it.
            let stamp = if k == 20 { 1.0e6 } else { t };
            let both = [drone(1, [1.0, 1.0, 1.0], t), drone(2, [2.0, 1.0, 1.0], t)];
            let r = pair.on_scan(&scan(stamp, &[[3.0, 3.0]]), &both).unwrap();
            jumps.extend(
                r.events
                    .iter()
                    .filter(|e| matches!(e, StationEvent::ClockJump { .. }))
                    .cloned(),
            );
            assert!(pair.now() < 5.0, "scan {k}: clock {}", pair.now());
        }
        // Reported once; counted twice (the jump ahead, and the step back after it).
        assert_eq!(jumps.len(), 1, "{jumps:?}");
        assert_eq!(pair.summary().clock_jumps, 2);
        assert!(
            pair.summary().lost_drones.is_empty(),
            "no drone lost to a forged clock"
        );
        assert_ne!(pair.summary().outcome, "aborted");
        // Each bounded step stood in for one period, so the clock is where the scans are.
        assert!((pair.now() - 3.9).abs() < 1e-6, "{}", pair.now());
    }

    #[test]
    fn a_drone_outside_the_geofence_aborts_the_mission() {
        let mut s = station(vec![1, 2]);
        let inside = [
            drone(1, [1.0, 1.0, 1.0], 0.0),
            drone(2, [2.0, 1.0, 1.0], 0.0),
        ];
        s.on_scan(&scan(0.0, &[[3.0, 3.0]]), &inside).unwrap();
        let outside = [
            drone(1, [1.0, 1.0, 1.0], 0.1),
            drone(2, [11.0, 1.0, 1.0], 0.1),
        ];
        let reply = s.on_scan(&scan(0.1, &[[3.0, 3.0]]), &outside).unwrap();
        assert!(matches!(
            reply.events.as_slice(),
            [StationEvent::Ended {
                phase: Phase::Aborted {
                    reason: AbortReason::Geofence { system_id: 2 },
                    ..
                },
                ..
            }]
        ));
        for id in [1, 2] {
            assert_eq!(command_actions(&reply, id), vec![MissionAction::Abort]);
        }
        assert!(reply.events[0].to_string().contains("geofence (drone 2)"));
        assert_eq!(
            s.summary().abort_reason.as_deref(),
            Some("geofence (drone 2)")
        );
    }

    #[test]
    fn an_uplink_cut_sends_nothing_up_and_is_reported_once_each_way() {
        let plan = MissionPlan::new(Task::Driving, GOAL, 1.5, [10.0, 10.0, 3.0], vec![1]);
        let mut config = StationConfig::new(plan, 1.0);
        config.uplink_cut = Some(UplinkCut {
            start_s: 1.0,
            duration_s: 0.5,
        });
        let mut s = GroundStation::new(config).unwrap();
        let mut events = Vec::new();
        for k in 0..30 {
            let t = f64::from(k) * 0.1;
            let reply = s
                .on_scan(&scan(t, &[[3.0, 3.0]]), &[drone(1, [1.0, 1.0, 1.0], t)])
                .unwrap();
            if (1.0..1.5).contains(&t) {
                assert!(reply.uplink.is_empty(), "t={t}");
            } else {
                assert!(!reply.uplink.is_empty(), "t={t}");
            }
            events.extend(reply.events);
        }
        assert_eq!(events.len(), 3, "{events:?}");
        assert!(matches!(events[1], StationEvent::UplinkCut { .. }));
        assert!(matches!(events[2], StationEvent::UplinkRestored { .. }));
    }

    #[test]
    fn only_sensor_frames_make_scans() {
        let mut s = station(vec![1]);
        let heartbeat = skyherd_link::command::gcs_heartbeat();
        assert_eq!(s.hear(1, &heartbeat), None);
        assert_eq!(s.hear(200, &heartbeat), None);
    }

    #[test]
    fn status_texts_are_relayed_once_per_change_of_reason_set() {
        let mut s = station(vec![1, 2]);
        let mut lines = Vec::new();
        for text in [
            "skyherd: preparing (Arming)",
            "skyherd: flying",
            "skyherd: flying (altitude)",
            "skyherd: flying",
            "skyherd: flying (altitude)",
            "skyherd: flying\0\0",
            "skyherd: holding: mission complete",
            "skyherd: flying",
        ] {
            lines.extend(s.drone_said(1, text));
        }
        assert_eq!(
            lines,
            [
                "drone 1: preparing (Arming)",
                "drone 1: flying",
                "drone 1: flying (altitude)",
                "drone 1: holding: mission complete",
                "drone 1: flying",
            ]
        );
        // Drones are debounced separately.
        assert_eq!(
            s.drone_said(2, "skyherd: flying").as_deref(),
            Some("drone 2: flying")
        );
    }

    #[test]
    fn the_csv_row_matches_its_header() {
        let row = ScanRow {
            time_s: 1.25,
            phase: Phase::WaitingForFleet,
            detections: 4,
            tracks: 3,
            herders: vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]],
        };
        let header = ScanRow::csv_header(&[1, 2]);
        assert_eq!(header.split(',').count(), row.csv().split(',').count());
        assert_eq!(
            row.csv(),
            "1.250,waiting,4,3,1.000,2.000,3.000,4.000,5.000,6.000"
        );
    }
}
