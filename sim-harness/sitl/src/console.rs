//! The mission's console and its end: a pure watcher over the lockstep loop, and the final
//! result with its summary table.
//!
//! [`MissionWatch`] takes each tick's report, the world and the wall time (all passed in: no
//! clock here) and says what to do: record the state for the trajectory plot, print a
//! progress line (at most one per wall second, so a mission at 250x real time prints a few
//! lines, not hundreds), or stop (three simulated seconds after the episode ended, or when the
//! drones never took off; after the ground station exited, once every drone has landed and
//! disarmed, or [`LANDING_WAIT_S`] later). [`MissionResult`] is `result.json`; [`MissionResult::table`] is
//! what a person reads at the end.
//!
//! ```
//! use skyherd_sitl::console::{MissionWatch, Stop};
//! use skyherd_sitl::mission::{Ending, TickReport};
//!
//! let mut watch = MissionWatch::new(2, 4);
//! let tick = TickReport { time_s: 1.0, flying: 2, armed: 2, ending: None };
//! let step = watch.observe(&tick, 3, 0.0, true);
//! assert!(step.record_state && step.progress.is_some() && step.stop.is_none());
//! let end = TickReport { time_s: 30.0, flying: 2, armed: 2, ending: Some(Ending::Success) };
//! assert!(watch.observe(&end, 4, 0.5, true).progress.unwrap().contains("episode ended"));
//! let later = TickReport { time_s: 33.0, ..end };
//! assert_eq!(watch.observe(&later, 4, 0.6, true).stop, Some(Stop::Ended));
//! ```

use std::fmt::Write as _;

use serde::Serialize;

use crate::mission::{Ending, LANDING_WAIT_S, TickReport};

/// Simulated seconds the loop runs on after the episode ended, so the ground can see the
/// mission through and the drones hold.
pub const GRACE_S: f64 = 3.0;
/// Wall seconds the drones get to take off before the mission is given up (a daemon under
/// qemu needs seconds to get going).
pub const TAKEOFF_LIMIT_S: f64 = 60.0;
/// Wall seconds between progress lines.
pub const PROGRESS_PERIOD_S: f64 = 1.0;

/// Why the loop stops.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    /// The episode ended and the grace period is over.
    Ended,
    /// The drones did not all take off within [`TAKEOFF_LIMIT_S`] of wall time.
    NoTakeoff,
}

/// What to do after one tick.
#[derive(Clone, Debug, PartialEq)]
pub struct WatchStep {
    /// Keep this tick's world for the trajectory (one state per simulated second).
    pub record_state: bool,
    /// A console line to print.
    pub progress: Option<String>,
    /// Stop the loop.
    pub stop: Option<Stop>,
}

/// Watches the lockstep loop; see the [module docs](self).
#[derive(Clone, Debug)]
pub struct MissionWatch {
    drones: usize,
    targets: usize,
    next_progress_wall_s: f64,
    ended_at: Option<f64>,
    ending: Option<Ending>,
    /// After the ground exited: every drone down (or the wait over) has been reported.
    landing_reported: bool,
}

impl MissionWatch {
    /// A watcher for `drones` drones herding `targets` targets.
    pub fn new(drones: usize, targets: usize) -> Self {
        Self {
            drones,
            targets,
            next_progress_wall_s: 0.0,
            ended_at: None,
            ending: None,
            landing_reported: false,
        }
    }

    /// One tick: its report, how many targets are in the goal now, the wall seconds since the
    /// loop began, and whether every drone has taken off.
    pub fn observe(
        &mut self,
        tick: &TickReport,
        in_goal: usize,
        wall_s: f64,
        took_off: bool,
    ) -> WatchStep {
        let t = tick.time_s;
        let mut progress = None;
        if let Some(ending) = tick.ending
            && self.ended_at.is_none()
        {
            self.ended_at = Some(t);
            self.ending = Some(ending);
            progress = Some(format!(
                "t={t:6.1}s episode ended: {} ({in_goal}/{} targets in the goal)",
                ending_text(ending),
                self.targets
            ));
        } else if wall_s >= self.next_progress_wall_s && self.ended_at.is_none() {
            self.next_progress_wall_s = wall_s + PROGRESS_PERIOD_S;
            progress = Some(format!(
                "t={t:6.1}s flying {}/{} targets in goal {in_goal}/{} (wall {wall_s:.1}s)",
                tick.flying, self.drones, self.targets
            ));
        }
        let stop = if let (Some(Ending::GroundExited), Some(e)) = (self.ending, self.ended_at) {
            // Without a ground the drones land on their own: watch them down.
            let down = tick.armed == 0;
            let over = t - e >= LANDING_WAIT_S;
            if (down || over) && !self.landing_reported {
                self.landing_reported = true;
                progress = Some(if down {
                    format!(
                        "t={t:6.1}s every drone has landed and disarmed, {:.1} s after the ground exited",
                        t - e
                    )
                } else {
                    format!(
                        "t={t:6.1}s {}/{} drones still armed {LANDING_WAIT_S} s after the ground exited",
                        tick.armed, self.drones
                    )
                });
            }
            (down || over).then_some(Stop::Ended)
        } else if self.ended_at.is_some_and(|e| t - e >= GRACE_S) {
            Some(Stop::Ended)
        } else if !took_off && wall_s > TAKEOFF_LIMIT_S {
            Some(Stop::NoTakeoff)
        } else {
            None
        };
        WatchStep {
            record_state: ((t * 10.0).round() as u64).is_multiple_of(10),
            progress,
            stop,
        }
    }
}

/// Words for an ending.
pub(crate) fn ending_text(ending: Ending) -> &'static str {
    match ending {
        Ending::Success => "every target in the goal",
        Ending::LeftArea => "something left the arena",
        Ending::TimeLimit => "time limit",
        Ending::GroundExited => "the ground station exited",
    }
}

/// How a mission was flown: what `result.json` records beside the outcome.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FlightSettings {
    /// The model file the drones flew.
    pub model: String,
    /// The vehicles' motion model (`off`, `room`, `px4`, `px4-auto`).
    pub dynamics: String,
    /// The wind (`calm`, `room`, `arena`).
    pub wind: String,
    /// Whether the daemons ran the separation rule.
    pub keep_apart: bool,
    /// The distance they kept (3-D, m; `skyherd-onboard --separation-m`), with the rule.
    pub keep_apart_m: Option<f64>,
}

/// One mission's outcome: what `result.json` holds.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MissionResult {
    /// Scenario name.
    pub scenario: String,
    /// Episode seed.
    pub seed: u64,
    /// Drones.
    pub herders: usize,
    /// Targets.
    pub targets: usize,
    /// Every target reached the goal.
    pub success: bool,
    /// How the episode ended, if it did.
    pub ending: Option<Ending>,
    /// When every drone was flying, simulated s.
    pub flight_start_s: Option<f64>,
    /// When the episode ended, simulated s.
    pub end_s: Option<f64>,
    /// From take-off to success, s (successes only, as in the paper).
    pub mission_time_s: Option<f64>,
    /// Summed herder path, m.
    pub path_length_m: f64,
    /// Simulated time at the end, s.
    pub sim_time_s: f64,
    /// Wall time of the loop, s.
    pub wall_time_s: f64,
    /// Simulated over wall time.
    pub real_time_factor: f64,
    /// Ticks where some answer did not arrive in time.
    pub lockstep_misses: u64,
    /// Autopilot failsafes (setpoint loss and the like).
    pub autopilot_failsafes: u64,
    /// The smallest 3-D distance between two drones during flight, m (none with one drone).
    pub min_separation_m: Option<f64>,
    /// Ticks of flight with two drones closer than `separation_threshold_m`.
    pub separation_breaches: u64,
    /// The separation a breach is counted against, m.
    pub separation_threshold_m: f64,
    /// The ground station's own JSON summary (null when it printed none).
    pub ground: serde_json::Value,
    /// When the ground station exited before the mission ended, simulated s (null otherwise).
    pub ground_exit_s: Option<f64>,
    /// How it exited: its exit status, e.g. `signal: 9 (SIGKILL)` (null otherwise).
    pub ground_exit: Option<String>,
    /// Drones that landed and disarmed themselves (a landing without the ground).
    pub drones_landed: usize,
    /// When each drone began to land (its autopilot accepted `MAV_CMD_NAV_LAND`), simulated
    /// s, by herder index (null: it did not).
    pub landing_start_s: Vec<Option<f64>>,
    /// Each drone's touchdown time, simulated s, by herder index (null: did not land).
    pub touchdown_s: Vec<Option<f64>>,
    /// What was outside the arena when the mission ended there (`herder N`, `target N`).
    pub left_area: Vec<String>,
    /// How it was flown.
    pub flight: FlightSettings,
}

impl MissionResult {
    /// The summary table printed at the end of a mission.
    pub fn table(&self) -> String {
        let num =
            |v: Option<f64>, unit: &str| v.map_or("-".to_string(), |v| format!("{v:.1}{unit}"));
        let ground = |k: &str| match &self.ground[k] {
            serde_json::Value::Null => "-".to_string(),
            serde_json::Value::String(s) => s.clone(),
            v => v.to_string(),
        };
        let outcome = match (self.success, self.ending) {
            (true, _) => "success".to_string(),
            (false, Some(e)) if !self.left_area.is_empty() => {
                format!("failed: {} ({})", ending_text(e), self.left_area.join(", "))
            }
            (false, Some(e)) => format!("failed: {}", ending_text(e)),
            (false, None) => "unfinished".to_string(),
        };
        let mut rows = vec![
            (
                "scenario",
                format!("{} (seed {})", self.scenario, self.seed),
            ),
            (
                "fleet",
                format!("{} drones, {} targets", self.herders, self.targets),
            ),
            ("outcome", outcome),
            ("time to goal", num(self.mission_time_s, " s from take-off")),
            ("herder path", format!("{:.1} m", self.path_length_m)),
            (
                "simulated",
                format!(
                    "{:.1} s in {:.2} s wall ({:.0}x real time)",
                    self.sim_time_s, self.wall_time_s, self.real_time_factor
                ),
            ),
            (
                "lockstep",
                format!(
                    "{} missed ticks, {} autopilot failsafes",
                    self.lockstep_misses, self.autopilot_failsafes
                ),
            ),
            (
                "separation",
                match self.min_separation_m {
                    Some(d) => format!(
                        "closest {d:.2} m, {} breach ticks (< {} m)",
                        self.separation_breaches, self.separation_threshold_m
                    ),
                    None => "-".to_string(),
                },
            ),
            (
                "ground",
                format!(
                    "{} ({} tracks, {} uplink frames, {} fleet frames dropped)",
                    ground("outcome"),
                    ground("tracks"),
                    ground("uplink_frames_sent"),
                    ground("fleet_frames_dropped")
                ),
            ),
        ];
        if let Some(t) = self.ground_exit_s {
            rows.push((
                "ground exit",
                format!(
                    "at {t:.1} s ({}); {}/{} drones landed",
                    self.ground_exit.as_deref().unwrap_or("?"),
                    self.drones_landed,
                    self.herders
                ),
            ));
        }
        let mut out = String::new();
        for (name, value) in rows {
            let _ = writeln!(out, "  {name:<13} {value}");
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tick(time_s: f64, ending: Option<Ending>) -> TickReport {
        TickReport {
            time_s,
            flying: 2,
            armed: 2,
            ending,
        }
    }

    #[test]
    fn progress_is_printed_at_most_once_per_wall_second() {
        let mut watch = MissionWatch::new(2, 4);
        let mut lines = 0;
        // 300 simulated seconds in 2.5 wall seconds.
        for k in 0..3000 {
            let t = f64::from(k) * 0.1;
            let step = watch.observe(&tick(t, None), 0, t / 120.0, true);
            lines += usize::from(step.progress.is_some());
            assert_eq!(step.record_state, k % 10 == 0, "t={t}");
        }
        assert_eq!(lines, 3);
    }

    #[test]
    fn the_end_is_reported_once_and_the_loop_stops_after_the_grace() {
        let mut watch = MissionWatch::new(2, 4);
        let mut ended_lines = 0;
        let mut stopped = None;
        for k in 0..100 {
            let t = 20.0 + f64::from(k) * 0.1;
            let step = watch.observe(&tick(t, Some(Ending::Success)), 4, 0.1, true);
            ended_lines += usize::from(step.progress.is_some());
            if step.stop.is_some() {
                stopped = Some((t, step.stop));
                break;
            }
        }
        assert_eq!(ended_lines, 1);
        let (t, stop) = stopped.expect("stops");
        assert!((t - 20.0 - GRACE_S).abs() < 1e-6 && stop == Some(Stop::Ended));
    }

    #[test]
    fn after_the_ground_exits_the_loop_waits_for_the_drones_to_land() {
        let mut watch = MissionWatch::new(2, 4);
        let exited = tick(12.0, Some(Ending::GroundExited));
        let step = watch.observe(&exited, 1, 0.1, true);
        assert!(step.progress.unwrap().contains("the ground station exited"));
        // Still armed long after the usual grace: the loop goes on.
        let step = watch.observe(&tick(12.0 + GRACE_S + 10.0, exited.ending), 1, 0.2, true);
        assert_eq!(step.stop, None);
        // Both down: stop, and say so.
        let down = TickReport {
            armed: 0,
            ..tick(26.0, exited.ending)
        };
        let step = watch.observe(&down, 1, 0.3, true);
        assert_eq!(step.stop, Some(Stop::Ended));
        assert!(step.progress.unwrap().contains("landed and disarmed"));
        // Never down: stop after the landing wait.
        let mut watch = MissionWatch::new(2, 4);
        watch.observe(&exited, 1, 0.1, true);
        let late = tick(12.0 + LANDING_WAIT_S - 0.1, exited.ending);
        assert_eq!(watch.observe(&late, 1, 0.2, true).stop, None);
        let step = watch.observe(&tick(12.0 + LANDING_WAIT_S, exited.ending), 1, 0.3, true);
        assert_eq!(step.stop, Some(Stop::Ended));
        assert!(step.progress.unwrap().contains("2/2 drones still armed"));
    }

    #[test]
    fn a_fleet_that_never_takes_off_is_given_up() {
        let mut watch = MissionWatch::new(2, 4);
        assert_eq!(watch.observe(&tick(0.0, None), 0, 59.0, false).stop, None);
        assert_eq!(
            watch.observe(&tick(0.0, None), 0, 61.0, false).stop,
            Some(Stop::NoTakeoff)
        );
        assert_eq!(watch.observe(&tick(0.0, None), 0, 61.0, true).stop, None);
    }

    #[test]
    fn the_summary_table_says_what_happened() {
        let result = MissionResult {
            scenario: "indoor".into(),
            seed: 0,
            herders: 2,
            targets: 4,
            success: true,
            ending: Some(Ending::Success),
            flight_start_s: Some(3.0),
            end_s: Some(32.3),
            mission_time_s: Some(29.3),
            path_length_m: 41.25,
            sim_time_s: 35.3,
            wall_time_s: 0.2,
            real_time_factor: 176.5,
            lockstep_misses: 0,
            autopilot_failsafes: 0,
            min_separation_m: Some(1.234),
            separation_breaches: 0,
            separation_threshold_m: 0.5,
            ground: serde_json::json!({"outcome": "complete", "tracks": 4,
                "uplink_frames_sent": 1200, "fleet_frames_dropped": 0}),
            ground_exit_s: None,
            ground_exit: None,
            drones_landed: 0,
            landing_start_s: vec![None, None],
            touchdown_s: vec![None, None],
            left_area: Vec::new(),
            flight: FlightSettings::default(),
        };
        let table = result.table();
        assert!(table.contains("outcome       success"), "{table}");
        assert!(table.contains("29.3 s from take-off"), "{table}");
        assert!(
            table.contains("complete (4 tracks, 1200 uplink frames"),
            "{table}"
        );
        assert!(
            table.contains("closest 1.23 m, 0 breach ticks (< 0.5 m)"),
            "{table}"
        );
        assert_eq!(table.lines().count(), 9);
        let failed = MissionResult {
            success: false,
            ending: Some(Ending::LeftArea),
            mission_time_s: None,
            ground: serde_json::Value::Null,
            ..result
        };
        let table = failed.table();
        assert!(
            table.contains("failed: something left the arena"),
            "{table}"
        );
        assert!(table.contains("time to goal  -"), "{table}");
        let killed = MissionResult {
            ending: Some(Ending::GroundExited),
            ground_exit_s: Some(12.0),
            ground_exit: Some("signal: 9 (SIGKILL)".into()),
            drones_landed: 2,
            landing_start_s: vec![Some(23.1), Some(23.1)],
            touchdown_s: vec![Some(25.9), Some(26.1)],
            left_area: Vec::new(),
            ..failed
        };
        let table = killed.table();
        assert!(
            table.contains("failed: the ground station exited"),
            "{table}"
        );
        assert!(
            table.contains("at 12.0 s (signal: 9 (SIGKILL)); 2/2 drones landed"),
            "{table}"
        );
    }
}
