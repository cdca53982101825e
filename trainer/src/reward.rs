//! The reward the learner sees, one number per herder per step, from the simulator's step and
//! the world before and after it.
//!
//! Two kinds ([`RewardKind`]):
//!
//! * **`paper`**: the simulator's reward (eqs 7-11 with its leave correction when configured),
//!   its flight term scaled, divided by the episode's step cost when normalising. Every herder
//!   gets the team's number. This is what `mtddpg-v1` was trained with; under it hovering
//!   beats every rule (see `skyherd-trainer audit-reward` and `docs/learning/`).
//! * **`audited`**: a reward built so that finishing sooner is always better and doing nothing
//!   is never a refuge, in units of one step:
//!
//!   ```text
//!   r_h = - time_cost                                  every step, until the episode ends
//!         + shaping (gamma Phi(s') - Phi(s))             potential-based: the optimal policy is
//!                                                      the unshaped one's (Ng et al. 1999);
//!                                                      or (Phi(s') - Phi(s)), the progress
//!                                                      form ([`ShapingForm`])
//!         - flight_cost |v_h| / v_max                    this herder's own flight, not the team's
//!         + success_bonus                                when every target is in the goal
//!         - leave_penalty_horizons / (1 - gamma)         once, when anything leaves the arena
//!   Phi(s) = - mean over targets of max(0, |p - g| - R) / R     0 in a terminal state
//!            - straggler * max over targets of max(0, |p - g| - R) / R
//!   + credit (Phi(s') - Phi(s' without h))               each herder's own part of the
//!                                                      progress (the mean summed over the
//!                                                      targets when credit_per_target)
//!   ```
//!
//!   Hovering forever is worth `-time_cost / (1 - gamma)`; an episode that succeeds at step
//!   `T` is worth `-time_cost (1 - gamma^T) / (1 - gamma)` plus its bonus, more for every step
//!   saved; leaving costs more than hovering forever, at any step, so the observation needs no
//!   clock. The shaping telescopes: over an episode it adds `gamma^T Phi(s_T) - Phi(s_0)`.
//!
//! The paper's reward stays what `eval` reports; this module only decides what the learner
//! optimises.

use serde::{Deserialize, Serialize};
use skyherd_sim::{Env, ReplayScratch, Scenario, StepOutcome, World};

use crate::config::RewardConfig;

/// Which reward the learner optimises.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RewardKind {
    /// The simulator's reward with the options of [`RewardConfig`] (the default, so older
    /// configs train as they did).
    #[default]
    Paper,
    /// Time cost, potential shaping, own flight cost, success bonus and a fixed leave penalty
    /// ([`AuditedReward`]).
    Audited,
}

/// The weights of the `audited` reward, in units of one step's time cost.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AuditedReward {
    /// Paid every step until the episode ends.
    pub time_cost: f64,
    /// Weight of the shaping on the flock's distance to the goal edge (in goal radii, averaged
    /// over the targets).
    pub shaping: f64,
    /// How the shaping term is formed from the potential.
    pub shaping_form: ShapingForm,
    /// Each herder pays this times its own speed over the speed limit, per step.
    pub flight_cost: f64,
    /// Weight of each herder's own potential-based shaping on its distance to the nearest
    /// target ([`approach_potential`]): the flock only moves, and so the other terms only speak,
    /// where a herder is near it, and a herder spawned 200 m away learns that first. 0: off.
    pub approach: f64,
    /// Paid once when every target is in the goal.
    pub success_bonus: f64,
    /// Leaving the arena costs this many horizons `1 / (1 - gamma)` of time cost, once: more
    /// than hovering forever when it is above 1.
    pub leave_penalty_horizons: f64,
    /// Weight of each herder's own difference credit ([`difference_credits`]): the progress
    /// the flock made this step because that herder was there, `Phi(s') - Phi(s' without h)`.
    /// Added to the team's terms, so a herder pushing the flock the wrong way is told so even
    /// when the others' pushes outweigh it. 0: off.
    pub credit: f64,
    /// Weight of the farthest target's distance beyond the goal edge in the potential, beside
    /// the mean's ([`flock_potential`]). An episode ends when its last target is in, but the
    /// mean gives that straggler only 1/N of the potential, as much as any target in a clump
    /// near the goal. Shaping and difference credit both read this potential. 0: off (older
    /// configs train as before).
    pub straggler: f64,
    /// The difference credit counts each target's own progress, summed over the targets,
    /// instead of the mean's ([`credit_potential`]): the mean gives a herder pushing one target
    /// of N only 1/N of what it gives at N = 1. The team's shaping keeps the mean. false: off
    /// (older configs train as before).
    pub credit_per_target: bool,
}

impl Default for AuditedReward {
    fn default() -> Self {
        Self {
            time_cost: 1.0,
            shaping: 1.0,
            shaping_form: ShapingForm::Potential,
            flight_cost: 0.05,
            approach: 0.0,
            success_bonus: 10.0,
            leave_penalty_horizons: 2.0,
            credit: 0.0,
            straggler: 0.0,
            credit_per_target: false,
        }
    }
}

/// How the shaping term is formed from the potential `Phi`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapingForm {
    /// `gamma Phi(s') - Phi(s)`, with `Phi = 0` in a terminal state: potential-based shaping
    /// (Ng et al. 1999). It leaves every policy's advantage unchanged, so once the critic has
    /// converged it adds no pull towards the goal: it only speeds up early value learning.
    #[default]
    Potential,
    /// `Phi(s') - Phi(s)`: the progress made this step (a terminal state keeps its real
    /// potential). This is the potential form plus `(1 - gamma) Phi(s')`, a dense cost on the
    /// flock's distance to the goal, so bringing the flock closer sooner keeps paying after the
    /// critic converges; it changes the optimum only towards being near the goal earlier.
    /// Over an episode it sums (undiscounted) to `Phi(s_T) - Phi(s_0)`.
    Progress,
}

/// The potential of a world: minus the targets' mean distance beyond the goal edge, in goal
/// radii (0 when every target is inside). [`flock_potential`] with no straggler weight.
pub fn potential(world: &World) -> f64 {
    flock_potential(world, 0.0)
}

/// Minus the targets' mean distance beyond the goal edge and `straggler` times the farthest
/// one's, in goal radii (0 when every target is inside, and with no targets).
pub fn flock_potential(world: &World, straggler: f64) -> f64 {
    let (sum, farthest) = distances_beyond_goal(world);
    let mut phi = -sum / world.targets.len().max(1) as f64;
    if straggler != 0.0 {
        phi -= straggler * farthest;
    }
    phi
}

/// The potential the difference credit reads: [`flock_potential`], or with
/// `per_target` the targets' summed distance beyond the goal edge in place of their mean
/// (the straggler's term unchanged), so pushing one target a metre earns the same at any N.
pub fn credit_potential(world: &World, straggler: f64, per_target: bool) -> f64 {
    if !per_target {
        return flock_potential(world, straggler);
    }
    let (sum, farthest) = distances_beyond_goal(world);
    -sum - straggler * farthest
}

/// The targets' summed and largest distance beyond the goal edge, in goal radii.
fn distances_beyond_goal(world: &World) -> (f64, f64) {
    let [cx, cy] = world.goal.center;
    let r = world.goal.radius.max(1e-9);
    world
        .targets
        .iter()
        .map(|p| (((p[0] - cx).powi(2) + (p[1] - cy).powi(2)).sqrt() - r).max(0.0) / r)
        .fold((0.0, 0.0_f64), |(sum, farthest), d| {
            (sum + d, farthest.max(d))
        })
}

/// Herder `h`'s approach potential: minus its ground distance to the nearest target, in goal
/// radii (0 with no targets). Potential-based (`gamma Phi(s') - Phi(s)`, 0 at a terminal), so
/// it changes no policy's ranking; it only tells a far herder early that coming closer is
/// where progress starts.
pub fn approach_potential(world: &World, h: usize) -> f64 {
    let Some(p) = world.herders.get(h) else {
        return 0.0;
    };
    let r = world.goal.radius.max(1e-9);
    let nearest = world
        .targets
        .iter()
        .map(|t| (t[0] - p[0]).hypot(t[1] - p[1]))
        .fold(f64::INFINITY, f64::min);
    if nearest.is_finite() {
        -nearest / r
    } else {
        0.0
    }
}

/// Reusable buffers for [`difference_credits`].
#[derive(Clone, Debug, Default)]
pub struct CreditScratch {
    world: Option<World>,
    replay: ReplayScratch,
}

/// Each herder's difference credit for the step `env` last took, into `out` (one per herder):
/// `Phi(s') - Phi(s'_-h)`, where `s'_-h` is that step replayed without herder `h`
/// ([`Env::replay_last_step_without`]). It is what herder `h` itself added to the flock's
/// progress towards the goal this step (in goal radii, averaged over the targets): positive
/// behind the flock, negative on the goal's side of it, zero far from it. The team's progress
/// is shared by every herder alike, so a herder can only read its own part from the team's
/// reward through the noise of the others' actions; this credit gives it that part directly
/// (the difference reward of Wolpert and Tumer 2002, with the simulator as the counterfactual).
///
/// The potential is [`credit_potential`]: [`flock_potential`] with weight `straggler` on the
/// farthest target, its mean part summed over the targets instead when `per_target`.
///
/// All zeros when `env` does not keep its last step or has taken none this episode.
pub fn difference_credits(
    env: &Env,
    straggler: f64,
    per_target: bool,
    scratch: &mut CreditScratch,
    out: &mut Vec<f64>,
) {
    let after = env.world();
    let actual = credit_potential(after, straggler, per_target);
    let m = after.herders.len();
    out.clear();
    out.resize(m, 0.0);
    let world = scratch.world.get_or_insert_with(|| after.clone());
    for (h, credit) in out.iter_mut().enumerate() {
        // Only an index past the herders could fail, and `h` is not one.
        if let Ok(true) = env.replay_last_step_without(h, world, &mut scratch.replay) {
            *credit = actual - credit_potential(world, straggler, per_target);
        }
    }
}

/// The per-step cost of idling and flying at full speed, `k0 (k3 |r3| N + s k4 v_max M)` with
/// `s` the flight scale: the natural unit of an episode's paper rewards.
pub(crate) fn step_cost(s: &Scenario, flight_scale: f64) -> f64 {
    let r = &s.reward;
    let cost = r.k0
        * (r.k3 * r.r3.abs() * s.targets as f64
            + flight_scale * r.k4 * s.limits.herder * s.herder_count() as f64);
    cost.max(1e-6)
}

/// The learner's reward for one episode: call [`LearnerReward::start`] after each reset and
/// [`LearnerReward::step`] after each step.
#[derive(Clone, Debug)]
pub struct LearnerReward {
    config: RewardConfig,
    gamma: f64,
    step_cost: f64,
    max_speed: f64,
    potential: f64,
    approach: Vec<f64>,
    weights: AuditedReward,
    credits: Vec<f64>,
    credit_scratch: CreditScratch,
}

impl LearnerReward {
    /// The reward of `config` for episodes of `scenario`, discounted by `gamma`.
    pub fn new(config: &RewardConfig, gamma: f64, scenario: &Scenario) -> Self {
        Self {
            step_cost: step_cost(scenario, config.flight_scale),
            max_speed: scenario.limits.herder.max(1e-9),
            config: config.clone(),
            gamma,
            potential: 0.0,
            approach: Vec::new(),
            weights: config.audited_for(scenario.task).clone(),
            credits: Vec::new(),
            credit_scratch: CreditScratch::default(),
        }
    }

    /// Whether this reward replays each step without each herder (the difference credit):
    /// [`LearnerReward::start`] then asks `env` to keep its last step.
    pub fn wants_credit(&self) -> bool {
        self.config.kind == RewardKind::Audited && self.weights.credit != 0.0
    }

    /// A new episode begins in `env` (after its reset).
    pub fn start(&mut self, env: &mut Env) {
        if self.wants_credit() {
            env.keep_last_step(true);
        }
        let world = env.world();
        self.potential = flock_potential(world, self.weights.straggler);
        self.approach = (0..world.herders.len())
            .map(|h| approach_potential(world, h))
            .collect();
    }

    /// The reward of each herder for the step `env` just took (`outcome`) with the herders'
    /// commanded `velocities` (m/s), written into `out` (resized to M).
    pub fn step(
        &mut self,
        outcome: &StepOutcome,
        env: &Env,
        velocities: &[[f64; 3]],
        out: &mut Vec<f32>,
    ) {
        let after = env.world();
        out.clear();
        match self.config.kind {
            RewardKind::Paper => {
                let mut r =
                    outcome.reward - (1.0 - self.config.flight_scale) * outcome.terms.flight;
                if self.config.normalize_by_step_cost {
                    r /= self.step_cost;
                }
                out.resize(velocities.len(), r as f32);
            }
            RewardKind::Audited => {
                let a = &self.weights;
                let (next, discount) = match a.shaping_form {
                    ShapingForm::Potential if outcome.terminated => (0.0, self.gamma),
                    ShapingForm::Potential => (flock_potential(after, a.straggler), self.gamma),
                    ShapingForm::Progress => (flock_potential(after, a.straggler), 1.0),
                };
                let mut team = -a.time_cost + a.shaping * (discount * next - self.potential);
                if outcome.success {
                    team += a.success_bonus;
                }
                if outcome.left_area {
                    team -= a.leave_penalty_horizons * a.time_cost / (1.0 - self.gamma).max(1e-9);
                }
                self.potential = next;
                let gamma = self.gamma;
                let terminated = outcome.terminated;
                self.approach.resize(velocities.len(), 0.0);
                if a.credit != 0.0 {
                    difference_credits(
                        env,
                        a.straggler,
                        a.credit_per_target,
                        &mut self.credit_scratch,
                        &mut self.credits,
                    );
                } else {
                    self.credits.clear();
                }
                self.credits.resize(velocities.len(), 0.0);
                let credits = &self.credits;
                out.extend(velocities.iter().enumerate().map(|(h, v)| {
                    let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                    let mut r =
                        team - a.flight_cost * speed / self.max_speed + a.credit * credits[h];
                    if a.approach != 0.0 {
                        let next = if terminated {
                            0.0
                        } else {
                            approach_potential(after, h)
                        };
                        r += a.approach * (gamma * next - self.approach[h]);
                        self.approach[h] = next;
                    }
                    r as f32
                }));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_sim::scenario::HerderCount;
    use skyherd_sim::{Env, Task};

    fn scenario() -> Scenario {
        let mut s = Scenario::paper(Task::Driving);
        s.targets = 8;
        s.herders = HerderCount::Fixed(2);
        s.step_limit = 60;
        s
    }

    fn audited(shaping: f64, flight_cost: f64) -> RewardConfig {
        RewardConfig {
            kind: RewardKind::Audited,
            audited: AuditedReward {
                time_cost: 0.0,
                shaping,
                shaping_form: ShapingForm::Potential,
                flight_cost,
                approach: 0.0,
                success_bonus: 0.0,
                leave_penalty_horizons: 0.0,
                credit: 0.0,
                straggler: 0.0,
                credit_per_target: false,
            },
            ..RewardConfig::default()
        }
    }

    /// Fly an episode of `scenario` with constant velocities; the rewards of herder 0.
    fn episode(config: &RewardConfig, gamma: f64, velocity: [f64; 3]) -> (Vec<f32>, f64, f64) {
        let scenario = scenario();
        let mut env = Env::new(scenario.clone()).unwrap();
        let mut reward = LearnerReward::new(config, gamma, &scenario);
        env.reset(5);
        reward.start(&mut env);
        let first = potential(env.world());
        let mut rewards = Vec::new();
        let mut per_herder = Vec::new();
        loop {
            let velocities = vec![velocity; env.world().herders.len()];
            let out = env.step(&velocities).unwrap();
            reward.step(&out, &env, &velocities, &mut per_herder);
            rewards.push(per_herder[0]);
            if out.terminated || out.truncated {
                let last = if out.terminated {
                    0.0
                } else {
                    potential(env.world())
                };
                return (rewards, first, last);
            }
        }
    }

    #[test]
    fn the_shaping_telescopes_over_an_episode() {
        let gamma = 0.97;
        for velocity in [[0.0; 3], [3.0, -2.0, 0.0]] {
            let (rewards, first, last) = episode(&audited(1.0, 0.0), gamma, velocity);
            let discounted: f64 = rewards
                .iter()
                .enumerate()
                .map(|(t, r)| gamma.powi(t as i32) * f64::from(*r))
                .sum();
            let expected = gamma.powi(rewards.len() as i32) * last - first;
            assert!(
                (discounted - expected).abs() < 1e-4 * (1.0 + expected.abs()),
                "{discounted} vs {expected}"
            );
            assert!(first < 0.0, "targets start outside the goal");
        }
    }

    #[test]
    fn the_straggler_weight_adds_the_farthest_targets_distance_and_still_telescopes() {
        let (env, _) = flock_world(vec![[138.0, 138.0, 2.0], [480.0, 20.0, 2.0]]);
        let world = env.world();
        let r = world.goal.radius;
        let excess: Vec<f64> = world
            .targets
            .iter()
            .map(|p| ((p[0] - 250.0).hypot(p[1] - 250.0) - r).max(0.0) / r)
            .collect();
        let mean = excess.iter().sum::<f64>() / excess.len() as f64;
        let farthest = excess.iter().copied().fold(0.0, f64::max);
        assert!(farthest > mean && mean > 0.0);
        assert_eq!(flock_potential(world, 0.0), potential(world));
        assert!((potential(world) + mean).abs() < 1e-12);
        assert!((flock_potential(world, 2.0) + mean + 2.0 * farthest).abs() < 1e-12);

        // The shaping on it still telescopes over a whole episode.
        let gamma = 0.97;
        let mut config = audited(1.0, 0.0);
        config.audited.straggler = 2.0;
        let scenario = scenario();
        for velocity in [[0.0; 3], [3.0, -2.0, 0.0]] {
            let mut env = Env::new(scenario.clone()).unwrap();
            let mut reward = LearnerReward::new(&config, gamma, &scenario);
            env.reset(5);
            reward.start(&mut env);
            let first = flock_potential(env.world(), 2.0);
            assert!(
                first < potential(env.world()),
                "the straggler counts twice more"
            );
            let (mut discounted, mut t, mut r) = (0.0, 0, Vec::new());
            let last = loop {
                let velocities = vec![velocity; env.world().herders.len()];
                let out = env.step(&velocities).unwrap();
                reward.step(&out, &env, &velocities, &mut r);
                discounted += gamma.powi(t) * f64::from(r[0]);
                t += 1;
                if out.terminated {
                    break 0.0;
                }
                if out.truncated {
                    break flock_potential(env.world(), 2.0);
                }
            };
            let expected = gamma.powi(t) * last - first;
            assert!(
                (discounted - expected).abs() < 1e-4 * (1.0 + expected.abs()),
                "{discounted} vs {expected}"
            );
        }
    }

    #[test]
    fn the_progress_form_sums_to_the_progress_made() {
        let mut config = audited(2.0, 0.0);
        config.audited.shaping_form = ShapingForm::Progress;
        for velocity in [[0.0; 3], [3.0, -2.0, 0.0], [-5.0, -5.0, 0.0]] {
            let scenario = scenario();
            let mut env = Env::new(scenario.clone()).unwrap();
            let mut reward = LearnerReward::new(&config, 0.97, &scenario);
            env.reset(5);
            reward.start(&mut env);
            let first = potential(env.world());
            let mut total = 0.0;
            let mut r = Vec::new();
            loop {
                let velocities = vec![velocity; env.world().herders.len()];
                let out = env.step(&velocities).unwrap();
                reward.step(&out, &env, &velocities, &mut r);
                total += f64::from(r[0]);
                if out.terminated || out.truncated {
                    break;
                }
            }
            // Undiscounted, and a terminal keeps its real potential (leaving is no escape
            // from the distance still to go).
            let expected = 2.0 * (potential(env.world()) - first);
            assert!((total - expected).abs() < 1e-4, "{total} vs {expected}");
        }
    }

    #[test]
    fn the_approach_term_telescopes_per_herder_and_rewards_coming_closer() {
        let gamma = 0.97;
        let mut config = audited(0.0, 0.0);
        config.audited.approach = 1.5;
        let scenario = scenario();
        let mut env = Env::new(scenario.clone()).unwrap();
        let mut reward = LearnerReward::new(&config, gamma, &scenario);
        env.reset(5);
        reward.start(&mut env);
        let first: Vec<f64> = (0..2).map(|h| approach_potential(env.world(), h)).collect();
        // Herder 0 flies at the nearest target, herder 1 away from it.
        let mut sums = [0.0_f64; 2];
        let mut r = Vec::new();
        for t in 0..20 {
            let w = env.world();
            let c = w.flock_centroid();
            let towards = |h: usize, sign: f64| {
                let p = w.herders[h];
                let (dx, dy) = (c[0] - p[0], c[1] - p[1]);
                let d = dx.hypot(dy).max(1e-9);
                [sign * 2.0 * dx / d, sign * 2.0 * dy / d, 0.0]
            };
            let velocities = vec![towards(0, 1.0), towards(1, -1.0)];
            let out = env.step(&velocities).unwrap();
            reward.step(&out, &env, &velocities, &mut r);
            for h in 0..2 {
                sums[h] += gamma.powi(t) * f64::from(r[h]);
            }
            assert!(!out.terminated && !out.truncated);
        }
        for h in 0..2 {
            let last = approach_potential(env.world(), h);
            let expected = 1.5 * (gamma.powi(20) * last - first[h]);
            assert!(
                (sums[h] - expected).abs() < 1e-4,
                "herder {h}: {} vs {expected}",
                sums[h]
            );
        }
        // (With a discount, standing far off also earns `(1 - gamma) |Phi|` a step, so the
        // comparison is between the two herders, not against zero.)
        assert!(sums[0] > sums[1] + 1.0, "{sums:?}");
    }

    #[test]
    fn a_task_may_have_weights_of_its_own() {
        let mut config = audited(0.0, 0.5);
        let mut driving = config.audited.clone();
        driving.flight_cost = 0.0;
        config.audited_driving = Some(driving);
        let v_max = scenario().limits.herder;
        for (task, expected) in [(Task::Driving, 0.0), (Task::Collecting, -0.5)] {
            let mut s = scenario();
            s.task = task;
            let mut env = Env::new(s.clone()).unwrap();
            let mut reward = LearnerReward::new(&config, 0.99, &s);
            env.reset(1);
            reward.start(&mut env);
            let velocities = [[v_max, 0.0, 0.0], [0.0; 3]];
            let out = env.step(&velocities).unwrap();
            let mut r = Vec::new();
            reward.step(&out, &env, &velocities, &mut r);
            assert!((f64::from(r[0]) - expected).abs() < 1e-6, "{task:?}: {r:?}");
        }
    }

    #[test]
    fn each_herder_pays_its_own_flight() {
        let scenario = scenario();
        let mut env = Env::new(scenario.clone()).unwrap();
        let mut reward = LearnerReward::new(&audited(0.0, 0.5), 0.99, &scenario);
        env.reset(1);
        reward.start(&mut env);
        let v_max = scenario.limits.herder;
        let velocities = [[v_max, 0.0, 0.0], [0.0; 3]];
        let out = env.step(&velocities).unwrap();
        let mut r = Vec::new();
        reward.step(&out, &env, &velocities, &mut r);
        assert!((f64::from(r[0]) + 0.5).abs() < 1e-6, "{r:?}");
        assert_eq!(r[1], 0.0);
    }

    #[test]
    fn leaving_costs_more_than_hovering_forever_and_success_pays() {
        let gamma = 0.99;
        let config = RewardConfig {
            kind: RewardKind::Audited,
            ..RewardConfig::default()
        };
        let a = &config.audited;
        let hover_forever = -a.time_cost / (1.0 - gamma);
        let scenario = scenario();
        let mut env = Env::new(scenario.clone()).unwrap();
        let mut reward = LearnerReward::new(&config, gamma, &scenario);
        env.reset(2);
        reward.start(&mut env);
        // Fly herder 0 straight out of the arena at full speed.
        let mut r = Vec::new();
        let mut total = 0.0;
        for t in 0..400 {
            let velocities = vec![[-5.0, -5.0, 0.0], [0.0; 3]];
            let out = env.step(&velocities).unwrap();
            reward.step(&out, &env, &velocities, &mut r);
            total += gamma.powi(t) * f64::from(r[1]);
            if out.left_area {
                assert!(out.terminated);
                break;
            }
            assert!(
                !out.terminated && !out.truncated,
                "still inside at step {t}"
            );
        }
        assert!(total < hover_forever, "{total} vs {hover_forever}");
    }

    #[test]
    fn the_paper_kind_gives_every_herder_the_team_reward() {
        let scenario = scenario();
        let config = RewardConfig::default();
        let mut env = Env::new(scenario.clone()).unwrap();
        let mut reward = LearnerReward::new(&config, 0.99, &scenario);
        env.reset(3);
        reward.start(&mut env);
        let velocities = [[1.0, 0.0, 0.0], [0.0; 3]];
        let out = env.step(&velocities).unwrap();
        let mut r = Vec::new();
        reward.step(&out, &env, &velocities, &mut r);
        let cost = step_cost(&scenario, config.flight_scale);
        let expected = (out.reward - 0.9 * out.terms.flight) / cost;
        assert_eq!(r, vec![expected as f32; 2]);
    }

    /// A world of 4 targets round (150, 150), the goal at (250, 250), and `herders`.
    fn flock_world(herders: Vec<[f64; 3]>) -> (Env, Scenario) {
        let mut s = scenario().without_noise();
        s.targets = 4;
        s.herders = HerderCount::Fixed(herders.len());
        let mut env = Env::new(s.clone()).unwrap();
        let mut world = env.world().clone();
        world.goal.center = [250.0, 250.0];
        world.targets = vec![
            [150.0, 150.0],
            [154.0, 151.0],
            [151.0, 154.0],
            [147.0, 149.0],
        ];
        world.target_velocities = vec![[0.0; 2]; 4];
        world.herders = herders;
        env.reset_to(world, 0).unwrap();
        (env, s)
    }

    /// Each herder's difference credit for `env`'s last step, with fresh buffers.
    fn credits_of(env: &Env, straggler: f64, per_target: bool) -> Vec<f64> {
        let mut credits = Vec::new();
        difference_credits(
            env,
            straggler,
            per_target,
            &mut CreditScratch::default(),
            &mut credits,
        );
        credits
    }

    #[test]
    fn the_difference_credit_goes_to_the_herder_that_pushed() {
        // Herder 0 behind the flock (away from the goal), herder 1 far off in a corner.
        let (mut env, s) = flock_world(vec![[138.0, 138.0, 2.0], [480.0, 20.0, 2.0]]);
        let mut config = audited(0.0, 0.0);
        config.audited.credit = 3.0;
        let mut reward = LearnerReward::new(&config, 0.99, &s);
        assert!(reward.wants_credit());
        reward.start(&mut env);
        let still = [[0.0; 3]; 2];
        let out = env.step(&still).unwrap();
        let credits = credits_of(&env, 0.0, false);
        assert!(
            credits[0] > 1e-3,
            "pushing towards the goal earns: {credits:?}"
        );
        assert!(
            credits[1].abs() < 1e-2 * credits[0],
            "far off earns ~0: {credits:?}"
        );
        let mut r = Vec::new();
        reward.step(&out, &env, &still, &mut r);
        assert!(
            (f64::from(r[0]) - 3.0 * credits[0]).abs() < 1e-6,
            "{r:?} {credits:?}"
        );

        // On the goal's side of the flock the same herder pushes it away: a debit, although
        // the team's progress alone would not say whose.
        let (mut env, _) = flock_world(vec![[162.0, 162.0, 2.0], [480.0, 20.0, 2.0]]);
        reward.start(&mut env);
        let out = env.step(&still).unwrap();
        reward.step(&out, &env, &still, &mut r);
        assert!(r[0] < -1e-3 && r[1].abs() < 1e-2 * r[0].abs(), "{r:?}");

        // Off, and before any step, there is no credit at all.
        let (mut env, _) = flock_world(vec![[138.0, 138.0, 2.0], [480.0, 20.0, 2.0]]);
        let credits = credits_of(&env, 0.0, false);
        assert_eq!(credits, vec![0.0, 0.0]);
        let mut plain = LearnerReward::new(&audited(0.0, 0.0), 0.99, &s);
        assert!(!plain.wants_credit());
        plain.start(&mut env);
        let out = env.step(&still).unwrap();
        plain.step(&out, &env, &still, &mut r);
        assert_eq!(r, vec![0.0, 0.0]);
    }

    #[test]
    fn the_per_target_credit_is_the_mean_credit_times_n_with_the_straggler_term_kept() {
        let (mut env, s) = flock_world(vec![[138.0, 138.0, 2.0], [480.0, 20.0, 2.0]]);
        let n = env.world().targets.len() as f64;
        let mut config = audited(0.0, 0.0);
        config.audited.credit = 1.0;
        // Starting a crediting reward makes the env keep its last step for the replays.
        LearnerReward::new(&config, 0.99, &s).start(&mut env);
        env.step(&[[0.0; 3]; 2]).unwrap();
        let mean = credits_of(&env, 0.0, false);
        let summed = credits_of(&env, 0.0, true);
        assert!(mean[0] > 1e-4, "herder 0 pushes the flock: {mean:?}");
        for (m, s) in mean.iter().zip(&summed) {
            assert!(
                (s - n * m).abs() < 1e-9 * (1.0 + s.abs()),
                "{mean:?} {summed:?}"
            );
        }
        // The straggler's term is the same in both; only the mean's part is scaled.
        let mean_s = credits_of(&env, 1.0, false);
        let summed_s = credits_of(&env, 1.0, true);
        for h in 0..2 {
            let straggler_part = mean_s[h] - mean[h];
            assert!(
                (summed_s[h] - (summed[h] + straggler_part)).abs() < 1e-9,
                "{mean_s:?} {summed_s:?}"
            );
        }
        let world = env.world();
        assert_eq!(
            credit_potential(world, 0.5, false),
            flock_potential(world, 0.5)
        );
    }
}
