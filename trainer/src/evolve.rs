//! Evolution-strategies fine-tuning of the task heads: a training aid that optimises what the
//! evaluation measures (completion time over the lower bound, with failures penalised) directly,
//! where DDPG's critic could not get the actor past the rule it was cloned from.
//!
//! For each task in turn, the parameters of that task's own layers (its input layer and its
//! output layer, Fig. 2) are perturbed with antithetic Gaussian noise, `theta ± sigma eps`; every
//! perturbed actor herds the same episodes (common random numbers: one seed set per
//! generation), each episode scoring `time / lower bound` or, if it fails, `failure_ratio` plus
//! optional partial credit (`failure_progress_span` times the share of the flock that never made
//! it into the goal at once); the
//! centred ranks of the scores weight the noise into a gradient estimate (Salimans et al. 2017)
//! and Adam takes the step. The shared hidden layers are left alone, so tuning one task never
//! changes the other's behaviour. Every `check_every` generations the current heads herd a
//! fixed held-out seed set and the best heads by that check are kept: the result is never worse
//! on the check than the actor it started from.
//!
//! Pure and seeded: the same actor, config and seed give the same heads on any thread count.
//!
//! ```
//! use rand::SeedableRng;
//! use skyherd_model::Task;
//! use skyherd_trainer::config::{EvolutionConfig, EvolutionScenario};
//! use skyherd_trainer::evolve::{evolve_task, head_parameters};
//! use skyherd_trainer::network::{MlpShape, MultiTaskMlp};
//!
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
//! let actor = MultiTaskMlp::new(MlpShape::actor(46, 8, 1), &mut rng);
//! let config = EvolutionConfig {
//!     generations: 1,
//!     population: 2,
//!     step_limit: 30,
//!     check_every: 1,
//!     check_rounds: 1,
//!     scenarios: vec![EvolutionScenario::paper(Task::Driving, 2, 1, 1)],
//!     ..EvolutionConfig::default()
//! };
//! let out = evolve_task(&actor, Task::Driving, &config, 7, |_| {}).unwrap();
//! // Only the driving head may change.
//! let collecting = Task::Collecting.index();
//! assert_eq!(
//!     head_parameters(&out.actor, collecting),
//!     head_parameters(&actor, collecting)
//! );
//! assert!(out.best_check.fitness <= 0.0);
//! ```

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use skyherd_model::Task;
use skyherd_sim::env::run_episode;
use skyherd_sim::world::World;
use skyherd_sim::{Env, EnvError, Scenario};

use crate::config::{EvolutionConfig, EvolutionScenario, RewardConfig};
use crate::network::MultiTaskMlp;
use crate::policy::ActorPolicy;
use crate::rollout::{Draw, herder_count, training_scenario};

/// Seeds of the training episodes start here (generation `g` uses `TRAIN_SEED_BASE + g * 1000`
/// onwards); the check uses the config's own base, far from both and from the warm start's.
const TRAIN_SEED_BASE: u64 = 5_000_000_000;

/// How a set of episodes went.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fitness {
    /// Minus the mean per-episode score (`time / lower bound`, or the failure ratio): higher is
    /// better, 0 would be every episode at its lower bound.
    pub fitness: f64,
    /// Fraction of episodes that succeeded.
    pub success_rate: f64,
    /// Mean `time / lower bound` of the successful episodes (NaN if none).
    pub time_ratio: f64,
    /// Episodes run.
    pub episodes: usize,
}

/// One generation's report, for the progress bar and the log.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GenerationReport {
    /// The task being tuned.
    pub task: Task,
    /// Generation index, from 0.
    pub generation: usize,
    /// Mean fitness of the perturbed actors this generation (training seeds).
    pub population_fitness: f64,
    /// The held-out check of the current heads, if one ran after this generation.
    pub check: Option<Fitness>,
    /// Whether that check is the best so far (the heads were kept).
    pub kept: bool,
}

/// What [`evolve_task`] returns.
#[derive(Clone, Debug)]
pub struct Evolved {
    /// The actor with the best heads found for the task (the others untouched).
    pub actor: MultiTaskMlp,
    /// The held-out check of the starting actor.
    pub start_check: Fitness,
    /// The held-out check of the returned actor.
    pub best_check: Fitness,
}

/// The task's own parameters, flattened: input layer weights and bias, then output layer
/// weights and bias.
pub fn head_parameters(actor: &MultiTaskMlp, task: usize) -> Vec<f32> {
    let mut v = Vec::new();
    for layer in [&actor.task_inputs[task], &actor.task_outputs[task]] {
        v.extend_from_slice(&layer.weights);
        v.extend_from_slice(&layer.bias);
    }
    v
}

/// Writes `theta` (laid out as [`head_parameters`]) into the task's layers.
pub(crate) fn set_head_parameters(actor: &mut MultiTaskMlp, task: usize, theta: &[f32]) {
    let mut at = 0;
    for layer in [&mut actor.task_inputs[task], &mut actor.task_outputs[task]] {
        for part in [&mut layer.weights, &mut layer.bias] {
            let n = part.len();
            part.copy_from_slice(&theta[at..at + n]);
            at += n;
        }
    }
}

/// The simulator scenario of one configured evolution scenario (test-time noise on).
pub fn scenario_of(s: &EvolutionScenario, step_limit: u64) -> Scenario {
    // A config's names were checked when it loaded; one built in code with a bad name flies
    // without dynamics rather than panicking.
    let dynamics = s.herder_dynamics().ok().flatten();
    if s.indoor {
        let mut room = Scenario::indoor();
        room.task = s.task;
        room.targets = s.targets;
        room.herders = herder_count(s.herders);
        room.step_limit = step_limit;
        room.dynamics = dynamics;
        return room;
    }
    let draw = Draw {
        task: s.task,
        targets: s.targets,
        herders: s.herders,
        room: s.room,
        goal_distance_permille: 1000,
        herder_distance_permille: 1000,
    };
    // The score reads only success and time, so the reward settings do not matter here.
    let mut scenario = training_scenario(draw, step_limit, true, &RewardConfig::default(), 0.99);
    scenario.dynamics = dynamics;
    scenario
}

/// How an episode is scored: `time / lower bound` when it succeeds, else
/// `failure_ratio + progress_span * (1 - f)` with `f` the largest fraction of the targets that
/// were inside the goal at once.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scoring {
    /// A failed episode scores at least this many lower bounds.
    pub failure_ratio: f64,
    /// How much more a failure that never had any target inside the goal scores.
    pub progress_span: f64,
}

impl Scoring {
    /// The scoring `config` asks for.
    pub fn of(config: &EvolutionConfig) -> Scoring {
        Scoring {
            failure_ratio: config.failure_ratio,
            progress_span: config.failure_progress_span,
        }
    }
}

/// Fraction of `world`'s targets inside the goal circle (1 for an empty flock).
pub(crate) fn fraction_inside(world: &World) -> f64 {
    let n = world.targets.len();
    if n == 0 {
        return 1.0;
    }
    let g = world.goal;
    let r2 = g.radius * g.radius;
    let inside = world
        .targets
        .iter()
        .filter(|t| {
            let (dx, dy) = (t[0] - g.center[0], t[1] - g.center[1]);
            dx * dx + dy * dy <= r2
        })
        .count();
    inside as f64 / n as f64
}

/// One episode's score and outcome.
#[derive(Clone, Copy, Debug)]
struct Scored {
    score: f64,
    success: bool,
    ratio: f64,
}

/// Herds every scenario's episodes (seeds `seed_base + 100 k + i` for scenario `k`) with
/// `actor` and scores them.
pub fn fitness(
    actor: &MultiTaskMlp,
    scenarios: &[(Scenario, usize)],
    scoring: Scoring,
    seed_base: u64,
) -> Result<Fitness, EnvError> {
    Ok(fitness_by_scenario(actor, scenarios, scoring, seed_base)?.0)
}

/// [`fitness`], with each scenario's mean score beside it (in the order of `scenarios`).
pub(crate) fn fitness_by_scenario(
    actor: &MultiTaskMlp,
    scenarios: &[(Scenario, usize)],
    scoring: Scoring,
    seed_base: u64,
) -> Result<(Fitness, Vec<f64>), EnvError> {
    let mut per_scenario = Vec::with_capacity(scenarios.len());
    let mut total = 0.0;
    let mut episodes = 0usize;
    let mut wins = 0usize;
    let mut win_ratio = 0.0;
    for (k, (scenario, count)) in scenarios.iter().enumerate() {
        let seeds: Vec<u64> = (0..*count as u64)
            .map(|i| seed_base + 100 * k as u64 + i)
            .collect();
        let env = Env::new(scenario.clone())?;
        let scored = seeds
            .par_iter()
            .map_with(env, |env, &seed| {
                let mut policy = ActorPolicy::new(actor);
                // Only watched when partial credit is asked for (it costs a pass over the flock).
                let watch = scoring.progress_span > 0.0;
                let mut best_inside = 0.0f64;
                let e = run_episode(env, &mut policy, seed, |world, _| {
                    if watch {
                        best_inside = best_inside.max(fraction_inside(world));
                    }
                })?;
                let ratio = e.time_s / e.lower_bound_s.max(1e-9);
                let score = if e.success {
                    ratio
                } else {
                    scoring.failure_ratio + scoring.progress_span * (1.0 - best_inside)
                };
                Ok(Scored {
                    score,
                    success: e.success,
                    ratio,
                })
            })
            .collect::<Result<Vec<Scored>, EnvError>>()?;
        let mut scenario_total = 0.0;
        for e in &scored {
            episodes += 1;
            total += e.score;
            scenario_total += e.score;
            if e.success {
                wins += 1;
                win_ratio += e.ratio;
            }
        }
        per_scenario.push(scenario_total / scored.len().max(1) as f64);
    }
    let n = episodes.max(1) as f64;
    let fitness = Fitness {
        fitness: -total / n,
        success_rate: wins as f64 / n,
        time_ratio: if wins > 0 {
            win_ratio / wins as f64
        } else {
            f64::NAN
        },
        episodes,
    };
    Ok((fitness, per_scenario))
}

/// Tunes `task`'s heads of `actor` as `config` says; `seed` fixes the noise and the episodes.
/// `on_generation` hears about every generation.
pub fn evolve_task(
    actor: &MultiTaskMlp,
    task: Task,
    config: &EvolutionConfig,
    seed: u64,
    mut on_generation: impl FnMut(&GenerationReport),
) -> Result<Evolved, EnvError> {
    let t = task.index();
    let train: Vec<(Scenario, usize)> = config
        .scenarios_of(task)
        .map(|s| (scenario_of(s, config.step_limit), s.episodes))
        .collect();
    let check: Vec<(Scenario, usize)> = train
        .iter()
        .map(|(s, n)| (s.clone(), n * config.check_rounds))
        .collect();
    let check_of =
        |a: &MultiTaskMlp| fitness(a, &check, Scoring::of(config), config.check_seed_base);
    let start_check = check_of(actor)?;
    let mut current = actor.clone();
    let mut best = (start_check, actor.clone());
    if train.is_empty() || config.population == 0 {
        return Ok(Evolved {
            actor: best.1,
            start_check,
            best_check: start_check,
        });
    }
    let mut theta = head_parameters(actor, t);
    let dim = theta.len();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (0xE5 + t as u64));
    let (mut m, mut v) = (vec![0f32; dim], vec![0f32; dim]);
    let sigma = config.sigma;
    for generation in 0..config.generations {
        let noise: Vec<Vec<f32>> = (0..config.population)
            .map(|_| (0..dim).map(|_| rng.sample(StandardNormal)).collect())
            .collect();
        let seed_base = TRAIN_SEED_BASE + 1000 * generation as u64 + 100_000 * t as u64;
        // Per pair: the overall fitness and each scenario's mean score, of + and of -.
        let results = noise
            .par_iter()
            .map(|eps| {
                let mut pair = [(0.0, Vec::new()), (0.0, Vec::new())];
                for (slot, sign) in [(0, 1.0f32), (1, -1.0)] {
                    let mut a = current.clone();
                    let p: Vec<f32> = theta
                        .iter()
                        .zip(eps)
                        .map(|(x, z)| x + sign * sigma * z)
                        .collect();
                    set_head_parameters(&mut a, t, &p);
                    let (f, by) = fitness_by_scenario(&a, &train, Scoring::of(config), seed_base)?;
                    pair[slot] = (f.fitness, by);
                }
                Ok(pair)
            })
            .collect::<Result<Vec<_>, EnvError>>()?;
        let scores: Vec<[f64; 2]> = results.iter().map(|p| [p[0].0, p[1].0]).collect();
        let weights = if config.rank_per_scenario {
            // Each scenario ranks the pairs on its own (minus its mean score: higher is better)
            // and the rank differences are averaged, weighted by its episodes: a scenario whose
            // scores span 12 lower bounds cannot drown one whose span is a tenth of one.
            let total: usize = train.iter().map(|(_, n)| n).sum();
            let mut w = vec![0f32; results.len()];
            for (k, (_, episodes)) in train.iter().enumerate() {
                let of_k: Vec<[f64; 2]> =
                    results.iter().map(|p| [-p[0].1[k], -p[1].1[k]]).collect();
                let share = *episodes as f32 / total.max(1) as f32;
                for (wi, d) in w.iter_mut().zip(tied_centred_rank_differences(&of_k)) {
                    *wi += share * d;
                }
            }
            w
        } else {
            centred_rank_differences(&scores)
        };
        let scale = 1.0 / (config.population as f32 * sigma);
        let mut grad = vec![0f32; dim];
        for (w, eps) in weights.iter().zip(&noise) {
            for (g, z) in grad.iter_mut().zip(eps) {
                *g += w * z * scale;
            }
        }
        adam_ascent(
            &mut theta,
            &grad,
            &mut m,
            &mut v,
            generation + 1,
            config.learning_rate,
        );
        set_head_parameters(&mut current, t, &theta);
        let population_fitness =
            scores.iter().map(|p| p[0] + p[1]).sum::<f64>() / (2 * scores.len()) as f64;
        let mut report = GenerationReport {
            task,
            generation,
            population_fitness,
            check: None,
            kept: false,
        };
        let last = generation + 1 == config.generations;
        if (generation + 1) % config.check_every.max(1) == 0 || last {
            let c = check_of(&current)?;
            report.check = Some(c);
            if c.fitness > best.0.fitness {
                best = (c, current.clone());
                report.kept = true;
            }
        }
        on_generation(&report);
    }
    Ok(Evolved {
        actor: best.1,
        start_check,
        best_check: best.0,
    })
}

/// As [`centred_rank_differences`], with tied scores sharing their mean rank, so that a scenario
/// where every actor scores alike (all fail, or all finish on the same step) adds nothing.
pub(crate) fn tied_centred_rank_differences(scores: &[[f64; 2]]) -> Vec<f32> {
    let n = 2 * scores.len();
    let mut order = both_sides(scores);
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut rank = vec![0f32; n];
    let denominator = (n.max(2) - 1) as f32;
    let mut start = 0;
    while start < n {
        let mut end = start + 1;
        while end < n && order[end].0 == order[start].0 {
            end += 1;
        }
        let mean = (start + end - 1) as f32 / 2.0;
        for &(_, i) in &order[start..end] {
            rank[i] = mean / denominator - 0.5;
        }
        start = end;
    }
    pair_differences(&rank)
}

/// Every score with its slot: `+` of pair `i` at `2 i`, `-` at `2 i + 1`.
fn both_sides(scores: &[[f64; 2]]) -> Vec<(f64, usize)> {
    scores
        .iter()
        .enumerate()
        .flat_map(|(i, p)| [(p[0], 2 * i), (p[1], 2 * i + 1)])
        .collect()
}

/// `rank(+) - rank(-)` of every pair, from the ranks laid out as [`both_sides`] numbers them.
fn pair_differences(rank: &[f32]) -> Vec<f32> {
    rank.chunks_exact(2).map(|r| r[0] - r[1]).collect()
}

/// Per antithetic pair, `rank(+) - rank(-)` with ranks centred in `[-0.5, 0.5]`: the fitness
/// shaping that makes the step blind to the scale of the scores (and to outliers).
pub(crate) fn centred_rank_differences(scores: &[[f64; 2]]) -> Vec<f32> {
    let n = 2 * scores.len();
    let mut order = both_sides(scores);
    order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut rank = vec![0f32; n];
    let denominator = (n.max(2) - 1) as f32;
    for (r, &(_, i)) in order.iter().enumerate() {
        rank[i] = r as f32 / denominator - 0.5;
    }
    pair_differences(&rank)
}

/// One Adam step uphill (step `t` from 1, default betas).
fn adam_ascent(theta: &mut [f32], grad: &[f32], m: &mut [f32], v: &mut [f32], t: usize, lr: f32) {
    let (b1, b2) = (0.9f32, 0.999f32);
    let t = t.min(i32::MAX as usize) as i32;
    let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
    for (((p, &g), m), v) in theta
        .iter_mut()
        .zip(grad)
        .zip(m.iter_mut())
        .zip(v.iter_mut())
    {
        *m = b1 * *m + (1.0 - b1) * g;
        *v = b2 * *v + (1.0 - b2) * g * g;
        *p += lr * (*m / c1) / ((*v / c2).sqrt() + 1e-8);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::MlpShape;

    fn tiny_actor() -> MultiTaskMlp {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        MultiTaskMlp::new(MlpShape::actor(46, 8, 1), &mut rng)
    }

    #[test]
    fn head_parameters_round_trip_and_leave_the_shared_layers() {
        let mut a = tiny_actor();
        let shared = a.shared.clone();
        let t = Task::Collecting.index();
        let theta: Vec<f32> = (0..head_parameters(&a, t).len())
            .map(|i| i as f32)
            .collect();
        set_head_parameters(&mut a, t, &theta);
        assert_eq!(head_parameters(&a, t), theta);
        assert_eq!(a.shared, shared);
        assert_eq!(theta.len(), 46 * 8 + 8 + 8 * 3 + 3);
    }

    #[test]
    fn ranks_reward_the_better_side_of_each_pair() {
        // Pair 0: + is best overall; pair 1: - is better.
        let w = centred_rank_differences(&[[-1.0, -5.0], [-4.0, -2.0]]);
        assert!(w[0] > 0.0 && w[1] < 0.0, "{w:?}");
        assert!(
            (w[0] - 1.0).abs() < 1e-6,
            "best minus worst spans the whole range"
        );
        // Scale-free: multiplying the scores changes nothing.
        let v = centred_rank_differences(&[[-10.0, -50.0], [-40.0, -20.0]]);
        assert_eq!(w, v);
    }

    #[test]
    fn tied_ranks_add_nothing() {
        assert_eq!(
            tied_centred_rank_differences(&[[-12.0, -12.0], [-12.0, -12.0]]),
            vec![0.0, 0.0]
        );
        let w = tied_centred_rank_differences(&[[-1.0, -5.0], [-4.0, -2.0]]);
        assert_eq!(w, centred_rank_differences(&[[-1.0, -5.0], [-4.0, -2.0]]));
        // One pair tied with itself, the other decided.
        let w = tied_centred_rank_differences(&[[-3.0, -3.0], [-1.0, -5.0]]);
        assert_eq!(w[0], 0.0);
        assert!(w[1] > 0.0);
    }

    #[test]
    fn adam_climbs_a_concave_bowl() {
        // Maximise -(x - 3)^2 from 0 with its exact gradient.
        let (mut x, mut m, mut v) = ([0f32], [0f32], [0f32]);
        for t in 1..=2000 {
            let g = [-2.0 * (x[0] - 3.0)];
            adam_ascent(&mut x, &g, &mut m, &mut v, t, 0.05);
        }
        assert!((x[0] - 3.0).abs() < 0.05, "{x:?}");
    }

    /// Two generations of two pairs on one short driving scenario, checked every generation.
    fn tiny_config() -> EvolutionConfig {
        EvolutionConfig {
            generations: 2,
            population: 2,
            step_limit: 40,
            check_every: 1,
            check_rounds: 1,
            scenarios: vec![EvolutionScenario::paper(Task::Driving, 2, 1, 1)],
            ..EvolutionConfig::default()
        }
    }

    #[test]
    fn evolution_is_seeded_and_keeps_the_best_check() {
        let actor = tiny_actor();
        let config = tiny_config();
        let mut reports = Vec::new();
        let a = evolve_task(&actor, Task::Driving, &config, 5, |r| reports.push(*r)).unwrap();
        let b = evolve_task(&actor, Task::Driving, &config, 5, |_| {}).unwrap();
        assert_eq!(a.actor, b.actor, "same seed, same heads");
        assert_eq!(reports.len(), 2);
        assert!(reports.iter().all(|r| r.check.is_some()));
        assert!(a.best_check.fitness >= a.start_check.fitness);
        let kept = reports.iter().any(|r| r.kept);
        assert_eq!(
            a.actor != actor,
            kept,
            "the heads change exactly when a check improved"
        );
        assert_eq!(a.actor.shared, actor.shared);
        let c = Task::Collecting.index();
        assert_eq!(head_parameters(&a.actor, c), head_parameters(&actor, c));
    }

    #[test]
    fn partial_credit_ranks_failures_by_how_much_of_the_flock_got_in() {
        // A random actor in 10 steps fails every episode of 16 targets.
        let actor = tiny_actor();
        let scenario = scenario_of(&EvolutionScenario::paper(Task::Driving, 16, 2, 1), 10);
        let episodes = [(scenario, 3)];
        let flat = Scoring {
            failure_ratio: 12.0,
            progress_span: 0.0,
        };
        let plain = fitness(&actor, &episodes, flat, 9).unwrap();
        assert_eq!(plain.success_rate, 0.0);
        assert_eq!(plain.fitness, -12.0, "every failure alike");
        let shaped = Scoring {
            progress_span: 6.0,
            ..flat
        };
        let credited = fitness(&actor, &episodes, shaped, 9).unwrap();
        // Nobody starts in the goal (the start circle is 150 m from it), so none of the credit.
        assert_eq!(credited.fitness, -18.0);

        let mut world = Env::new(Scenario::paper_drive()).unwrap().reset(0).clone();
        assert_eq!(fraction_inside(&world), 0.0);
        let goal = world.goal.center;
        world.targets[..4].fill(goal);
        let n = world.targets.len() as f64;
        assert_eq!(fraction_inside(&world), 4.0 / n);
        world.targets.clear();
        assert_eq!(fraction_inside(&world), 1.0, "an empty flock is all in");
    }

    #[test]
    fn a_task_without_scenarios_is_returned_unchanged() {
        let actor = tiny_actor();
        let out = evolve_task(&actor, Task::Collecting, &tiny_config(), 1, |_| {}).unwrap();
        assert_eq!(out.actor, actor);
    }
}
