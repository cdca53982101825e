//! Mission control: when to start the task, when it is done, when to abort. Pure: the caller
//! passes the time, what the fleet reports and what the tracker sees; it gets back what to do.
//!
//! * **Start** once every planned drone has been heard with a position.
//! * **Complete** when the tracker has seen at least the expected number of targets and all of
//!   them have stayed inside the goal for [`MissionPlan::settle_s`]; the drones are then told to
//!   hold (an `Abort` mission command is "stop and hold").
//! * **Abort** (all drones hold) when a drone leaves the geofence, when every drone is lost,
//!   or at the time limit. One lost drone alone does not abort: the others go on.
//!
//! Simulator frame, metres, seconds.
//!
//! ```
//! use skyherd_ground::mission::{DroneReport, MissionStep, MissionControl, MissionPlan, Phase};
//! use skyherd_onboard::Task;
//!
//! let plan = MissionPlan::new(Task::Driving, [8.0, 8.0], 1.5, [10.0, 10.0, 3.0], vec![1, 2]);
//! let mut mission = MissionControl::new(plan);
//! let drones = [
//!     DroneReport { system_id: 1, position: Some([1.0, 1.0, 0.0]), last_heard: 0.0 },
//!     DroneReport { system_id: 2, position: Some([2.0, 1.0, 0.0]), last_heard: 0.0 },
//! ];
//! assert_eq!(mission.update(0.0, &drones, &[[3.0, 3.0]]), Some(MissionStep::Start));
//! assert!(matches!(mission.phase(), Phase::Flying { .. }));
//! ```

/// What the mission is about; simulator frame, metres, seconds.
#[derive(Clone, Debug, PartialEq)]
pub struct MissionPlan {
    /// The task to fly.
    pub task: skyherd_onboard::Task,
    /// Goal centre `[x, y]`.
    pub goal: [f32; 2],
    /// Goal radius.
    pub goal_radius: f32,
    /// Arena `[width, depth, ceiling]` from the origin: the geofence.
    pub area: [f32; 3],
    /// The drones' system ids; herder index = position in this list.
    pub drones: Vec<u8>,
    /// Targets expected (completion needs at least this many tracks); 0 = as many as tracked.
    pub expected_targets: usize,
    /// How long all tracks must stay inside the goal before the mission counts as complete.
    pub settle_s: f64,
    /// A drone unheard for this long is lost.
    pub lost_after_s: f64,
    /// Abort when the task is not complete this long after the start.
    pub time_limit_s: f64,
    /// Slack around the geofence before a drone counts as outside (sensor noise), metres.
    pub fence_margin: f32,
}

impl MissionPlan {
    /// A plan with defaults: 1 s settle, 3 s to lose a drone, 600 s limit, 0.5 m fence slack.
    pub fn new(
        task: skyherd_onboard::Task,
        goal: [f32; 2],
        goal_radius: f32,
        area: [f32; 3],
        drones: Vec<u8>,
    ) -> Self {
        Self {
            task,
            goal,
            goal_radius,
            area,
            drones,
            expected_targets: 0,
            settle_s: 1.0,
            lost_after_s: 3.0,
            time_limit_s: 600.0,
            fence_margin: 0.5,
        }
    }
}

/// What the fleet says of one drone.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DroneReport {
    /// Its system id.
    pub system_id: u8,
    /// Last known position `[x, y, z]`, simulator frame (z up).
    pub position: Option<[f32; 3]>,
    /// When it was last heard (mission clock, s).
    pub last_heard: f64,
}

/// Why a mission was aborted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AbortReason {
    /// A drone was outside the geofence.
    Geofence {
        /// Which one.
        system_id: u8,
    },
    /// No drone has been heard for `lost_after_s`.
    AllDronesLost,
    /// The time limit passed.
    TimeLimit,
    /// The operator said so.
    Operator,
}

/// Where the mission stands.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Phase {
    /// Waiting to hear every drone.
    WaitingForFleet,
    /// Flying the task since `started_at`.
    Flying {
        /// Mission clock at the start, s.
        started_at: f64,
        /// Since when every track has been inside the goal, if they are.
        inside_since: Option<f64>,
    },
    /// Done: every target in the goal.
    Complete {
        /// Mission clock at the start, s.
        started_at: f64,
        /// Mission clock when it completed, s.
        at: f64,
    },
    /// Stopped early.
    Aborted {
        /// Mission clock when it was aborted, s.
        at: f64,
        /// Why.
        reason: AbortReason,
    },
}

impl Phase {
    /// Whether the mission has ended (complete or aborted).
    pub fn is_over(&self) -> bool {
        matches!(self, Phase::Complete { .. } | Phase::Aborted { .. })
    }

    /// One word for logs: `waiting`, `flying`, `complete` or `aborted`.
    pub fn name(&self) -> &'static str {
        match self {
            Phase::WaitingForFleet => "waiting",
            Phase::Flying { .. } => "flying",
            Phase::Complete { .. } => "complete",
            Phase::Aborted { .. } => "aborted",
        }
    }
}

/// The next step of the mission: what to tell the drones.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MissionStep {
    /// Send the start command.
    Start,
    /// Send the hold command (the mission is complete or aborted).
    Hold,
}

/// The mission state machine.
#[derive(Clone, Debug)]
pub struct MissionControl {
    plan: MissionPlan,
    phase: Phase,
    lost: Vec<u8>,
}

impl MissionControl {
    /// A mission waiting for its fleet.
    pub fn new(plan: MissionPlan) -> Self {
        Self {
            plan,
            phase: Phase::WaitingForFleet,
            lost: Vec::new(),
        }
    }

    /// The plan.
    pub fn plan(&self) -> &MissionPlan {
        &self.plan
    }

    /// Where the mission stands.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// Drones declared lost so far.
    pub fn lost(&self) -> &[u8] {
        &self.lost
    }

    /// The operator aborts; returns the hold action unless the mission is already over.
    pub fn abort(&mut self, now: f64) -> Option<MissionStep> {
        if self.phase.is_over() {
            return None;
        }
        self.phase = Phase::Aborted {
            at: now,
            reason: AbortReason::Operator,
        };
        Some(MissionStep::Hold)
    }

    /// Advance to `now` with the fleet's reports and the tracked targets (simulator frame).
    pub fn update(
        &mut self,
        now: f64,
        drones: &[DroneReport],
        targets: &[[f32; 2]],
    ) -> Option<MissionStep> {
        let report = |id: u8| drones.iter().find(|d| d.system_id == id);
        match self.phase {
            Phase::WaitingForFleet => {
                let all_heard = self
                    .plan
                    .drones
                    .iter()
                    .all(|&id| report(id).is_some_and(|d| d.position.is_some()));
                if all_heard {
                    self.phase = Phase::Flying {
                        started_at: now,
                        inside_since: None,
                    };
                    return Some(MissionStep::Start);
                }
                None
            }
            Phase::Flying {
                started_at,
                inside_since,
            } => {
                for &id in &self.plan.drones {
                    let heard = report(id).map_or(f64::NEG_INFINITY, |d| d.last_heard);
                    if now - heard > self.plan.lost_after_s && !self.lost.contains(&id) {
                        self.lost.push(id);
                    }
                }
                let abort = |reason| (Phase::Aborted { at: now, reason }, Some(MissionStep::Hold));
                let (phase, action) = if let Some(id) = self.first_outside_fence(drones) {
                    abort(AbortReason::Geofence { system_id: id })
                } else if self.lost.len() == self.plan.drones.len() {
                    abort(AbortReason::AllDronesLost)
                } else if now - started_at > self.plan.time_limit_s {
                    abort(AbortReason::TimeLimit)
                } else if self.all_inside(targets) {
                    let since = inside_since.unwrap_or(now);
                    if now - since >= self.plan.settle_s {
                        (
                            Phase::Complete {
                                started_at,
                                at: now,
                            },
                            Some(MissionStep::Hold),
                        )
                    } else {
                        (
                            Phase::Flying {
                                started_at,
                                inside_since: Some(since),
                            },
                            None,
                        )
                    }
                } else {
                    (
                        Phase::Flying {
                            started_at,
                            inside_since: None,
                        },
                        None,
                    )
                };
                self.phase = phase;
                action
            }
            Phase::Complete { .. } | Phase::Aborted { .. } => None,
        }
    }

    fn all_inside(&self, targets: &[[f32; 2]]) -> bool {
        let enough = !targets.is_empty() && targets.len() >= self.plan.expected_targets;
        let r2 = self.plan.goal_radius * self.plan.goal_radius;
        enough
            && targets.iter().all(|t| {
                let dx = t[0] - self.plan.goal[0];
                let dy = t[1] - self.plan.goal[1];
                dx * dx + dy * dy <= r2
            })
    }

    fn first_outside_fence(&self, drones: &[DroneReport]) -> Option<u8> {
        let m = self.plan.fence_margin;
        let area = self.plan.area;
        drones
            .iter()
            .filter(|d| self.plan.drones.contains(&d.system_id))
            .find(|d| {
                d.position.is_some_and(|p| {
                    p[0] < -m
                        || p[1] < -m
                        || p[0] > area[0] + m
                        || p[1] > area[1] + m
                        || p[2] > area[2] + m
                })
            })
            .map(|d| d.system_id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_onboard::Task;

    fn plan() -> MissionPlan {
        let mut p = MissionPlan::new(
            Task::Driving,
            [8.0, 8.0],
            1.5,
            [10.0, 10.0, 3.0],
            vec![1, 2],
        );
        p.expected_targets = 2;
        p
    }

    fn drone(id: u8, pos: [f32; 3], heard: f64) -> DroneReport {
        DroneReport {
            system_id: id,
            position: Some(pos),
            last_heard: heard,
        }
    }

    fn started() -> MissionControl {
        let mut m = MissionControl::new(plan());
        let d = [
            drone(1, [1.0, 1.0, 1.0], 0.0),
            drone(2, [2.0, 1.0, 1.0], 0.0),
        ];
        assert_eq!(m.update(0.0, &d, &[]), Some(MissionStep::Start));
        m
    }

    #[test]
    fn waits_for_every_drone() {
        let mut m = MissionControl::new(plan());
        assert_eq!(m.update(0.0, &[drone(1, [1.0, 1.0, 1.0], 0.0)], &[]), None);
        let no_position = DroneReport {
            system_id: 2,
            position: None,
            last_heard: 0.0,
        };
        assert_eq!(
            m.update(0.1, &[drone(1, [1.0, 1.0, 1.0], 0.1), no_position], &[]),
            None
        );
        assert_eq!(m.phase(), Phase::WaitingForFleet);
    }

    #[test]
    fn completes_after_the_targets_settle_in_the_goal() {
        let mut m = started();
        let d = [
            drone(1, [1.0, 1.0, 1.0], 1.0),
            drone(2, [2.0, 1.0, 1.0], 1.0),
        ];
        let inside = [[8.0, 8.5], [7.5, 8.0]];
        // One target is not enough when two are expected.
        assert_eq!(m.update(1.0, &d, &inside[..1]), None);
        assert_eq!(m.update(1.5, &d, &inside), None);
        assert_eq!(m.update(2.0, &d, &inside), None);
        assert_eq!(m.update(2.5, &d, &inside), Some(MissionStep::Hold));
        assert_eq!(
            m.phase(),
            Phase::Complete {
                started_at: 0.0,
                at: 2.5
            }
        );
        assert_eq!(
            m.update(3.0, &d, &inside),
            None,
            "an ended mission stays ended"
        );
    }

    #[test]
    fn a_target_leaving_the_goal_restarts_the_settle_clock() {
        let mut m = started();
        let d = [
            drone(1, [1.0, 1.0, 1.0], 1.0),
            drone(2, [2.0, 1.0, 1.0], 1.0),
        ];
        let inside = [[8.0, 8.5], [7.5, 8.0]];
        let outside = [[8.0, 8.5], [5.0, 5.0]];
        assert_eq!(m.update(1.0, &d, &inside), None);
        assert_eq!(m.update(1.6, &d, &outside), None);
        assert_eq!(m.update(2.2, &d, &inside), None);
        assert_eq!(m.update(2.9, &d, &inside), None);
        assert_eq!(m.update(3.2, &d, &inside), Some(MissionStep::Hold));
    }

    #[test]
    fn a_drone_outside_the_fence_aborts() {
        let mut m = started();
        let d = [
            drone(1, [1.0, 1.0, 1.0], 1.0),
            drone(2, [11.0, 1.0, 1.0], 1.0),
        ];
        assert_eq!(m.update(1.0, &d, &[]), Some(MissionStep::Hold));
        assert_eq!(
            m.phase(),
            Phase::Aborted {
                at: 1.0,
                reason: AbortReason::Geofence { system_id: 2 }
            }
        );
    }

    #[test]
    fn one_lost_drone_goes_on_all_lost_aborts() {
        let mut m = started();
        let d = [
            drone(1, [1.0, 1.0, 1.0], 5.0),
            drone(2, [2.0, 1.0, 1.0], 0.0),
        ];
        assert_eq!(m.update(5.0, &d, &[]), None);
        assert_eq!(m.lost(), &[2]);
        assert!(matches!(m.phase(), Phase::Flying { .. }));
        let d = [
            drone(1, [1.0, 1.0, 1.0], 5.0),
            drone(2, [2.0, 1.0, 1.0], 0.0),
        ];
        assert_eq!(m.update(9.0, &d, &[]), Some(MissionStep::Hold));
        assert_eq!(
            m.phase(),
            Phase::Aborted {
                at: 9.0,
                reason: AbortReason::AllDronesLost
            }
        );
    }

    #[test]
    fn the_time_limit_aborts_and_the_operator_can_abort() {
        let mut m = started();
        let d = [
            drone(1, [1.0, 1.0, 1.0], 700.0),
            drone(2, [2.0, 1.0, 1.0], 700.0),
        ];
        assert_eq!(m.update(700.0, &d, &[]), Some(MissionStep::Hold));
        assert!(matches!(
            m.phase(),
            Phase::Aborted {
                reason: AbortReason::TimeLimit,
                ..
            }
        ));
        let mut m = started();
        assert_eq!(m.abort(1.0), Some(MissionStep::Hold));
        assert_eq!(m.abort(2.0), None);
    }
}
