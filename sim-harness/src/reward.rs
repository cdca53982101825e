//! Eqs (7)-(11): the paper's reward with its Section IV-A constants, term by term, and a
//! switchable training correction.
//!
//! `r = k0 (k1 r_complete + k2 r_leave + k3 r_closer + k4 r_flight)` with
//! `r_closer = sum_j (r3 - |x_j - g| + |x_j^last - g|)` and `r_flight = -sum_i |x_i - x_i^last|`.
//!
//! # Why a correction
//! As printed, the reward pays for leaving the arena: with `r3 = -10` per target each step costs
//! about `-(0.18 N + 9 M)` (driving, after `k0`), while leaving costs `-180` once and ends the
//! episode, so flying out on step 1 beats every honest policy. [`RewardCorrection::LeaveCoversRemainingSteps`]
//! adds, on leaving, the discounted cost of standing still for the rest of the step budget:
//! `k0 k3 |r3| N (1 - gamma^R) / (1 - gamma)` with `R` the steps left. Leaving is then never
//! cheaper than idling, and idling is never cheaper than finishing sooner. The paper's reward is
//! always reported beside it (`StepOutcome::paper_reward`).

use serde::{Deserialize, Serialize};
use skyherd_model::Task;

/// Constants of eqs (7)-(11) for one task.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardParams {
    /// `k0`, global scale (paper: 0.9).
    pub k0: f64,
    /// `r1`, completion reward.
    pub r1: f64,
    /// `r2`, leave penalty.
    pub r2: f64,
    /// `r3`, per-target per-step constant of `r_closer`.
    pub r3: f64,
    /// `k1`, weight of `r_complete`.
    pub k1: f64,
    /// `k2`, weight of `r_leave`.
    pub k2: f64,
    /// `k3`, weight of `r_closer`.
    pub k3: f64,
    /// `k4`, weight of `r_flight`.
    pub k4: f64,
    /// Training correction; `none` is the paper's reward.
    pub correction: RewardCorrection,
}

impl RewardParams {
    /// Section IV-A constants for `task`, k0 = 0.9, no correction.
    pub fn paper(task: Task) -> Self {
        match task {
            Task::Driving => RewardParams {
                k0: 0.9,
                r1: 100.0,
                r2: -200.0,
                r3: -10.0,
                k1: 0.5,
                k2: 1.0,
                k3: 0.02,
                k4: 2.0,
                correction: RewardCorrection::None,
            },
            Task::Collecting => RewardParams {
                k0: 0.9,
                r1: 50.0,
                r2: -200.0,
                r3: -10.0,
                k1: 0.1,
                k2: 1.0,
                k3: 0.05,
                k4: 2.0,
                correction: RewardCorrection::None,
            },
        }
    }
}

/// A documented change to the paper's reward for training (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum RewardCorrection {
    /// The paper's reward as printed.
    None,
    /// On leaving, also charge the discounted idle cost of the remaining steps.
    LeaveCoversRemainingSteps {
        /// The learner's discount factor, in (0, 1].
        gamma: f64,
    },
}

/// Each term's weighted contribution (`k0 k_i r_i`); `total()` is the reward the learner gets.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RewardTerms {
    /// `k0 k1 r_complete`.
    pub complete: f64,
    /// `k0 k2 r_leave`.
    pub leave: f64,
    /// `k0 k3 r_closer`.
    pub closer: f64,
    /// `k0 k4 r_flight`.
    pub flight: f64,
    /// The training correction (0 under [`RewardCorrection::None`]).
    pub correction: f64,
}

impl RewardTerms {
    /// The paper's reward, eq (7) times k0.
    pub fn paper(&self) -> f64 {
        self.complete + self.leave + self.closer + self.flight
    }

    /// The paper's reward plus the correction.
    pub fn total(&self) -> f64 {
        self.paper() + self.correction
    }
}

/// What the reward needs to know about one step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepFacts {
    /// All targets in the goal (and nothing left the arena).
    pub success: bool,
    /// Some herder or target is outside the arena.
    pub left_area: bool,
    /// `sum_j (|x_j^last - g| - |x_j - g|)`: how much closer the targets got, metres.
    pub closer_sum: f64,
    /// Number of targets.
    pub targets: usize,
    /// `sum_i |x_i - x_i^last|`: herders' travel this step, metres.
    pub herder_travel: f64,
    /// Steps still in the budget after this one.
    pub steps_left: u64,
}

/// Eqs (7)-(11) for one step, with the correction.
pub fn reward(p: &RewardParams, f: &StepFacts) -> RewardTerms {
    let r_complete = if f.success { p.r1 } else { 0.0 };
    let r_leave = if f.left_area { p.r2 } else { 0.0 };
    let r_closer = p.r3 * f.targets as f64 + f.closer_sum;
    let r_flight = -f.herder_travel;
    let correction = match p.correction {
        RewardCorrection::None => 0.0,
        RewardCorrection::LeaveCoversRemainingSteps { gamma } if f.left_area => {
            let per_step = p.k0 * p.k3 * p.r3.abs() * f.targets as f64;
            -per_step * discounted_steps(gamma, f.steps_left)
        }
        RewardCorrection::LeaveCoversRemainingSteps { .. } => 0.0,
    };
    RewardTerms {
        complete: p.k0 * p.k1 * r_complete,
        leave: p.k0 * p.k2 * r_leave,
        closer: p.k0 * p.k3 * r_closer,
        flight: p.k0 * p.k4 * r_flight,
        correction,
    }
}

/// `sum_{t=1}^{steps} gamma^t = gamma (1 - gamma^steps) / (1 - gamma)`: the remaining steps
/// discounted as seen from the leaving step (`steps` when gamma = 1).
pub(crate) fn discounted_steps(gamma: f64, steps: u64) -> f64 {
    if (1.0 - gamma).abs() < 1e-12 {
        steps as f64
    } else {
        let steps = steps.min(i32::MAX as u64) as i32;
        gamma * (1.0 - gamma.powi(steps)) / (1.0 - gamma)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn facts() -> StepFacts {
        StepFacts {
            success: false,
            left_area: false,
            closer_sum: 0.0,
            targets: 2,
            herder_travel: 0.0,
            steps_left: 100,
        }
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    #[test]
    fn each_term_by_hand_driving() {
        let p = RewardParams::paper(Task::Driving);
        let t = reward(
            &p,
            &StepFacts {
                success: true,
                ..facts()
            },
        );
        assert!(close(t.complete, 0.9 * 0.5 * 100.0)); // 45
        let t = reward(
            &p,
            &StepFacts {
                left_area: true,
                ..facts()
            },
        );
        assert!(close(t.leave, -180.0));
        assert_eq!(t.correction, 0.0, "the paper's reward has no correction");
        // Two targets, 3 m closer in total: 0.9 * 0.02 * (2 * -10 + 3).
        let t = reward(
            &p,
            &StepFacts {
                closer_sum: 3.0,
                ..facts()
            },
        );
        assert!(close(t.closer, 0.9 * 0.02 * -17.0));
        assert_eq!((t.complete, t.leave, t.flight), (0.0, 0.0, 0.0));
        // Herders flew 5 m: 0.9 * 2 * -5.
        let t = reward(
            &p,
            &StepFacts {
                herder_travel: 5.0,
                ..facts()
            },
        );
        assert!(close(t.flight, -9.0));
        assert!(close(t.total(), -9.0 + 0.9 * 0.02 * -20.0));
    }

    #[test]
    fn collecting_constants() {
        let p = RewardParams::paper(Task::Collecting);
        let t = reward(
            &p,
            &StepFacts {
                success: true,
                closer_sum: 1.0,
                ..facts()
            },
        );
        assert!(close(t.complete, 0.9 * 0.1 * 50.0));
        assert!(close(t.closer, 0.9 * 0.05 * -19.0));
    }

    #[test]
    fn correction_charges_the_remaining_steps_on_leaving() {
        let mut p = RewardParams::paper(Task::Driving);
        p.correction = RewardCorrection::LeaveCoversRemainingSteps { gamma: 0.99 };
        let f = StepFacts {
            left_area: true,
            targets: 16,
            ..facts()
        };
        let t = reward(&p, &f);
        let per_step = 0.9 * 0.02 * 10.0 * 16.0; // 2.88
        let steps = 0.99 * (1.0 - 0.99f64.powi(100)) / 0.01;
        assert!(close(t.correction, -per_step * steps));
        assert!(close(t.paper(), -180.0 + 0.9 * 0.02 * -160.0));
        // Not leaving: no correction.
        assert_eq!(
            reward(
                &p,
                &StepFacts {
                    targets: 16,
                    ..facts()
                }
            )
            .correction,
            0.0
        );
        // Leaving now is worse than idling out the budget under the same discount.
        let idle: f64 = (0..=100).map(|k| 0.99f64.powi(k) * -per_step).sum();
        assert!(t.total() < idle, "{} vs {idle}", t.total());
        assert_eq!(discounted_steps(1.0, 7), 7.0);
    }
}
