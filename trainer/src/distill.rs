//! Distillation of a rule into a trained actor where the rule herds better (a training aid).
//!
//! DAgger (Ross et al. 2011) with an anchor: in the *teach* scenarios the labels are a rule-based
//! teacher's actions, in the *keep* scenarios they are the starting actor's own actions, so the
//! student learns the teacher where it is taught and stays what it was everywhere else (the
//! network sees N and M in features 29-30 and can tell the two apart). Round 0 rolls out the
//! teacher (teach) and the starting actor (keep); every later round rolls out the student as
//! it flies, labels what it saw, adds it to the data and trains on all of it: the student
//! learns to recover from its own mistakes, which plain behaviour cloning does not.
//!
//! Observations are encoded as the daemon flies (height above the altitude band's floor) and
//! the students roll out through the daemon's flight rules, as the evaluation flies them.
//!
//! Pure and seeded: the same actor, config and seed give the same student on any thread count.
//!
//! ```
//! use rand::SeedableRng;
//! use skyherd_trainer::config::EvolutionScenario;
//! use skyherd_trainer::distill::{DistillConfig, distill};
//! use skyherd_trainer::network::MultiTaskMlp;
//! use skyherd_trainer::nn::Activation;
//!
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
//! let actor = MultiTaskMlp::new(2, 46, 8, 1, 3, Activation::Tanh, &mut rng);
//! let config = DistillConfig {
//!     rounds: 2,
//!     updates_per_round: 20,
//!     step_limit: 40,
//!     teach: vec![EvolutionScenario::paper("driving", 8, 2, 1)],
//!     keep: vec![EvolutionScenario::paper("collecting", 4, 1, 1)],
//!     ..DistillConfig::default()
//! };
//! let out = distill(&actor, &config, |_| {}).unwrap();
//! assert_eq!(out.rounds.len(), 2);
//! assert!(out.rounds[1].teach_samples > out.rounds[0].teach_samples);
//! ```

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use skyherd_model::Task;
use skyherd_onboard::obs::FEATURES;
use skyherd_onboard::safety::Limits;
use skyherd_sim::baseline::{Method, RulePolicy};
use skyherd_sim::obs::EncoderBuffers;
use skyherd_sim::policy::Policy;
use skyherd_sim::{Env, EnvError, Scenario};

use crate::config::EvolutionScenario;
use crate::ddpg::ACTION_DIM;
use crate::evolve::{Fitness, Scoring, fitness, scenario_of};
use crate::network::{MultiTaskMlp, Tape};
use crate::nn::{Adam, AdamConfig};
use crate::policy::ActorPolicy;

/// Seeds of the distillation episodes start here (round `k`, scenario `s`, episode `i`:
/// `SEED_BASE + 1_000_000 k + 1000 s + i`), away from every other seed range of the trainer.
const SEED_BASE: u64 = 7_000_000_000;

/// The `skyherd-trainer distill` config (TOML, every key documented; unknown keys are errors).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DistillConfig {
    /// Seed of the minibatch draws.
    pub seed: u64,
    /// The teacher: a `skyherd_sim::baseline::Method` name.
    pub teacher: String,
    /// DAgger rounds; round 0 rolls out the teacher, later rounds the student.
    pub rounds: usize,
    /// Adam updates after each round's roll-outs.
    pub updates_per_round: usize,
    /// Adam learning rate.
    pub learning_rate: f32,
    /// Minibatch size per update, split evenly over the non-empty (task, teach/keep) pools.
    pub batch_size: usize,
    /// Episode step limit of the roll-outs.
    pub step_limit: u64,
    /// Every `stride`-th step of a roll-out is labelled (consecutive steps are near copies).
    pub stride: u64,
    /// Where the teacher's actions are the labels (episodes per round each).
    pub teach: Vec<EvolutionScenario>,
    /// Where the starting actor's actions are the labels (episodes per round each).
    pub keep: Vec<EvolutionScenario>,
    /// Held-out check after every round (episodes each): the student with the best check is
    /// the result, scored as the evolution stage scores (`time / lower bound`, a failure
    /// `failure_ratio`). Empty: the last round's student is the result.
    pub check: Vec<EvolutionScenario>,
    /// First seed of the check episodes (the same episodes every round).
    pub check_seed_base: u64,
    /// A failed check episode scores this many lower bounds.
    pub failure_ratio: f64,
}

impl Default for DistillConfig {
    fn default() -> Self {
        DistillConfig {
            seed: 1,
            teacher: "enclose".into(),
            rounds: 4,
            updates_per_round: 5_000,
            learning_rate: 3e-4,
            batch_size: 256,
            step_limit: 1_500,
            stride: 4,
            teach: Vec::new(),
            keep: Vec::new(),
            check: Vec::new(),
            check_seed_base: 8_000_000_000,
            failure_ratio: 12.0,
        }
    }
}

/// Why distillation could not run.
#[derive(Debug, thiserror::Error)]
pub enum DistillError {
    /// The teacher is not a baseline name.
    #[error("distill: {0}")]
    Teacher(String),
    /// A scenario's task is neither `driving` nor `collecting`.
    #[error("distill: scenario task `{0}` is neither `driving` nor `collecting`")]
    Task(String),
    /// The actor's shape does not fit the encoder or the action.
    #[error(
        "distill: the actor maps {inputs} inputs to {outputs} outputs, the encoder gives {FEATURES} and actions have {ACTION_DIM}"
    )]
    Shape {
        /// Actor inputs.
        inputs: usize,
        /// Actor outputs.
        outputs: usize,
    },
    /// The simulator refused a scenario or a step.
    #[error("distill: {0}")]
    Env(#[from] EnvError),
    /// A scenario did not validate.
    #[error("distill: {0}")]
    Scenario(#[from] skyherd_sim::scenario::ScenarioError),
}

/// What one round did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoundReport {
    /// The round, from 0.
    pub round: usize,
    /// Labelled teach samples so far (all rounds).
    pub teach_samples: usize,
    /// Labelled keep samples so far.
    pub keep_samples: usize,
    /// Success rate of this round's teach roll-outs (the teacher's in round 0).
    pub teach_success: f64,
    /// Success rate of this round's keep roll-outs.
    pub keep_success: f64,
    /// Mean squared error of the last 100 updates' batches.
    pub loss: f32,
    /// The student's held-out check after this round (`None` without check scenarios).
    pub check: Option<Fitness>,
}

/// The distilled actor and how it got there.
#[derive(Clone, Debug)]
pub struct Distilled {
    /// The student: the best by the check, else the last round's.
    pub actor: MultiTaskMlp,
    /// The round it comes from.
    pub best_round: usize,
    /// One report per round.
    pub rounds: Vec<RoundReport>,
}

/// Labelled samples of one (task, kind) pool: features and normalised local-frame actions.
#[derive(Clone, Debug, Default)]
struct Pool {
    obs: Vec<f32>,
    actions: Vec<f32>,
}

impl Pool {
    fn len(&self) -> usize {
        self.actions.len() / ACTION_DIM
    }

    fn extend(&mut self, other: Pool) {
        self.obs.extend_from_slice(&other.obs);
        self.actions.extend_from_slice(&other.actions);
    }
}

/// Who flies a roll-out.
#[derive(Clone, Copy)]
enum Pilot<'a> {
    Teacher(Method),
    Student(&'a MultiTaskMlp),
}

/// Who labels what the pilot saw.
#[derive(Clone, Copy)]
enum Labeller<'a> {
    Teacher(Method),
    Anchor(&'a MultiTaskMlp),
}

/// One episode: flies `pilot`, labels every `stride`-th step's observations with `labeller`.
/// Returns the samples and whether the episode succeeded.
fn roll_out(
    env: &mut Env,
    pilot: Pilot<'_>,
    labeller: Labeller<'_>,
    seed: u64,
    stride: u64,
) -> Result<(Pool, bool), EnvError> {
    env.reset(seed);
    let mut pool = Pool::default();
    let mut teacher = match labeller {
        Labeller::Teacher(m) => Some(RulePolicy::new(m)),
        Labeller::Anchor(_) => None,
    };
    let mut pilot_policy: Box<dyn Policy> = match pilot {
        Pilot::Teacher(m) => Box::new(RulePolicy::new(m)),
        Pilot::Student(actor) => Box::new(ActorPolicy::flying(actor)),
    };
    pilot_policy.reset(env.observation(), seed);
    if let Some(t) = teacher.as_mut() {
        t.reset(env.observation(), seed);
    }
    let mut buffers = EncoderBuffers::default();
    let mut features = [0.0f32; FEATURES];
    let mut actions = Vec::new();
    loop {
        let world = env.observation();
        if world.step % stride.max(1) == 0 {
            let a = world.area;
            let limits = Limits::arena(
                [a.width as f32, a.depth as f32, a.ceiling as f32],
                world.limits.herder as f32,
            );
            buffers.fill(world);
            for (h, p) in world.herders.iter().enumerate() {
                // As the daemon encodes: the height above the altitude band's floor.
                let height = (p[2] as f32 - limits.fence_min[2]).max(0.0);
                let Ok(frame) = buffers.encode_at_altitude(h, height, &mut features) else {
                    continue;
                };
                let label = match (labeller, teacher.as_mut()) {
                    (Labeller::Teacher(_), Some(t)) => {
                        let v = t.act(world, h);
                        frame.world_to_action([v[0] as f32, v[1] as f32, v[2] as f32])
                    }
                    (Labeller::Anchor(anchor), _) => {
                        let y = anchor.predict(world.task.index(), &features);
                        [y[0], y[1], y[2]]
                    }
                    (Labeller::Teacher(_), None) => unreachable!("a teacher labeller has a rule"),
                };
                pool.obs.extend_from_slice(&features);
                pool.actions.extend_from_slice(&label);
            }
        }
        actions.clear();
        for h in 0..world.herders.len() {
            actions.push(pilot_policy.act(world, h));
        }
        let out = env.step(&actions)?;
        if out.terminated || out.truncated {
            return Ok((pool, out.success));
        }
    }
}

/// Rolls out every scenario's episodes of one round in parallel; returns the samples per task
/// and the success rate.
fn round_samples(
    scenarios: &[(Task, Scenario, usize)],
    pilot: Pilot<'_>,
    labeller: Labeller<'_>,
    seed_base: u64,
    stride: u64,
) -> Result<([Pool; Task::COUNT], f64), DistillError> {
    let jobs: Vec<(usize, u64)> = scenarios
        .iter()
        .enumerate()
        .flat_map(|(k, (_, _, n))| (0..*n as u64).map(move |i| (k, seed_base + 1000 * k as u64 + i)))
        .collect();
    let results = jobs
        .par_iter()
        .map(|&(k, seed)| {
            let mut env = Env::new(scenarios[k].1.clone())?;
            let (pool, success) = roll_out(&mut env, pilot, labeller, seed, stride)?;
            Ok::<_, DistillError>((scenarios[k].0, pool, success))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut pools: [Pool; Task::COUNT] = Default::default();
    let mut wins = 0usize;
    let total = results.len();
    // Collected in job order, so the data (and the student) do not depend on the thread count.
    for (task, pool, success) in results {
        pools[task.index()].extend(pool);
        wins += usize::from(success);
    }
    let rate = if total > 0 {
        wins as f64 / total as f64
    } else {
        f64::NAN
    };
    Ok((pools, rate))
}

fn scenarios(
    list: &[EvolutionScenario],
    step_limit: u64,
) -> Result<Vec<(Task, Scenario, usize)>, DistillError> {
    list.iter()
        .map(|s| {
            let scenario =
                scenario_of(s, step_limit).ok_or_else(|| DistillError::Task(s.task.clone()))?;
            Ok((scenario.task, scenario, s.episodes))
        })
        .collect()
}

/// Distils `config.teacher` into a copy of `start` as `config` says; `on_round` hears about
/// every round.
pub fn distill(
    start: &MultiTaskMlp,
    config: &DistillConfig,
    mut on_round: impl FnMut(&RoundReport),
) -> Result<Distilled, DistillError> {
    let teacher: Method = config.teacher.parse().map_err(DistillError::Teacher)?;
    if start.inputs() != FEATURES || start.outputs() != ACTION_DIM {
        return Err(DistillError::Shape {
            inputs: start.inputs(),
            outputs: start.outputs(),
        });
    }
    let teach = scenarios(&config.teach, config.step_limit)?;
    let keep = scenarios(&config.keep, config.step_limit)?;
    let check: Vec<(Scenario, usize)> = scenarios(&config.check, config.step_limit)?
        .into_iter()
        .map(|(_, s, n)| (s, n))
        .collect();
    let scoring = Scoring {
        failure_ratio: config.failure_ratio,
        progress_span: 0.0,
    };
    let mut best: Option<(f64, usize, MultiTaskMlp)> = None;
    let mut student = start.clone();
    let mut optimizer = Adam::new(
        AdamConfig {
            learning_rate: config.learning_rate,
            ..AdamConfig::default()
        },
        student.layers(),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    // Pools: [teach driving, teach collecting, keep driving, keep collecting].
    let mut pools: [Pool; 2 * Task::COUNT] = Default::default();
    let mut reports = Vec::with_capacity(config.rounds);
    for round in 0..config.rounds {
        let seed_base = SEED_BASE + 1_000_000 * round as u64;
        let (teach_pilot, keep_pilot) = if round == 0 {
            (Pilot::Teacher(teacher), Pilot::Student(start))
        } else {
            (Pilot::Student(&student), Pilot::Student(&student))
        };
        let (taught, teach_success) = round_samples(
            &teach,
            teach_pilot,
            Labeller::Teacher(teacher),
            seed_base,
            config.stride,
        )?;
        let (kept, keep_success) = round_samples(
            &keep,
            keep_pilot,
            Labeller::Anchor(start),
            seed_base + 500_000,
            config.stride,
        )?;
        for (i, p) in taught.into_iter().chain(kept).enumerate() {
            pools[i].extend(p);
        }
        let loss = train_round(&mut student, &mut optimizer, &pools, config, &mut rng);
        let checked = if check.is_empty() {
            None
        } else {
            Some(fitness(&student, &check, scoring, config.check_seed_base)?)
        };
        // Higher fitness is better; without a check every round beats the one before.
        let score = checked.map_or(round as f64, |f| f.fitness);
        if best.as_ref().is_none_or(|(b, _, _)| score > *b) {
            best = Some((score, round, student.clone()));
        }
        let report = RoundReport {
            round,
            teach_samples: pools[0].len() + pools[1].len(),
            keep_samples: pools[2].len() + pools[3].len(),
            teach_success,
            keep_success,
            loss,
            check: checked,
        };
        on_round(&report);
        reports.push(report);
    }
    let (actor, best_round) = match best {
        Some((_, round, actor)) => (actor, round),
        None => (student, 0),
    };
    Ok(Distilled {
        actor,
        best_round,
        rounds: reports,
    })
}

/// `config.updates_per_round` Adam steps on the mean squared error, each batch drawn evenly
/// from the non-empty pools; returns the mean loss of the last 100 updates.
fn train_round(
    student: &mut MultiTaskMlp,
    optimizer: &mut Adam,
    pools: &[Pool; 2 * Task::COUNT],
    config: &DistillConfig,
    rng: &mut ChaCha8Rng,
) -> f32 {
    let live: Vec<usize> = (0..pools.len()).filter(|&i| pools[i].len() > 0).collect();
    if live.is_empty() {
        return f32::NAN;
    }
    let per_pool = (config.batch_size / live.len()).max(1);
    let mut tape = Tape::default();
    let mut obs = Vec::new();
    let mut targets = Vec::new();
    let mut recent = Vec::new();
    for _ in 0..config.updates_per_round {
        let mut grads = student.zeros_like();
        let mut loss = 0.0;
        let total = (per_pool * live.len() * ACTION_DIM) as f32;
        for &p in &live {
            let task = p % Task::COUNT;
            let pool = &pools[p];
            obs.clear();
            targets.clear();
            for _ in 0..per_pool {
                let j = rng.random_range(0..pool.len());
                obs.extend_from_slice(&pool.obs[j * FEATURES..(j + 1) * FEATURES]);
                targets.extend_from_slice(&pool.actions[j * ACTION_DIM..(j + 1) * ACTION_DIM]);
            }
            student.forward(task, &obs, per_pool, &mut tape);
            let d: Vec<f32> = tape
                .output()
                .iter()
                .zip(&targets)
                .map(|(y, t)| {
                    loss += (y - t) * (y - t) / total;
                    2.0 * (y - t) / total
                })
                .collect();
            student.backward(&tape, &d, Some(&mut grads), false);
        }
        optimizer.update(student.layers_mut(), grads.layers());
        recent.push(loss);
        if recent.len() > 100 {
            recent.remove(0);
        }
    }
    recent.iter().sum::<f32>() / recent.len().max(1) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::Activation;

    fn tiny() -> MultiTaskMlp {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        MultiTaskMlp::new(2, FEATURES, 16, 1, 3, Activation::Tanh, &mut rng)
    }

    fn tiny_config() -> DistillConfig {
        DistillConfig {
            rounds: 2,
            updates_per_round: 300,
            learning_rate: 3e-3,
            step_limit: 60,
            stride: 2,
            teach: vec![EvolutionScenario::paper("driving", 16, 4, 2)],
            keep: vec![EvolutionScenario::paper("collecting", 8, 2, 2)],
            ..DistillConfig::default()
        }
    }

    /// Mean squared distance between two actors' actions on `obs` of `task`.
    fn gap(a: &MultiTaskMlp, b: &MultiTaskMlp, task: Task, obs: &Pool) -> f32 {
        let n = obs.len();
        let mut sum = 0.0;
        for j in 0..n {
            let x = &obs.obs[j * FEATURES..(j + 1) * FEATURES];
            let (ya, yb) = (a.predict(task.index(), x), b.predict(task.index(), x));
            sum += ya.iter().zip(&yb).map(|(p, q)| (p - q) * (p - q)).sum::<f32>();
        }
        sum / n.max(1) as f32
    }

    #[test]
    fn the_student_moves_towards_the_teacher_and_keeps_the_anchor() {
        let start = tiny();
        let config = tiny_config();
        let out = distill(&start, &config, |_| {}).unwrap();
        // Fresh labelled observations of the teacher flying the teach scenario.
        let teach = scenarios(&config.teach, 60).unwrap();
        let (pools, success) = round_samples(
            &teach,
            Pilot::Teacher(Method::Enclose),
            Labeller::Teacher(Method::Enclose),
            99,
            3,
        )
        .unwrap();
        assert!(success.is_finite());
        let labels = &pools[Task::Driving.index()];
        let err = |actor: &MultiTaskMlp| {
            let mut sum = 0.0;
            for j in 0..labels.len() {
                let y = actor.predict(0, &labels.obs[j * FEATURES..(j + 1) * FEATURES]);
                for (k, v) in y.iter().enumerate() {
                    let t = labels.actions[j * ACTION_DIM + k];
                    sum += (v - t) * (v - t);
                }
            }
            sum / labels.len() as f32
        };
        assert!(
            err(&out.actor) < 0.5 * err(&start),
            "imitation error {} vs {} before",
            err(&out.actor),
            err(&start)
        );
        // The keep task's head and the shared layer moved, but its actions stay near the anchor.
        let keep = scenarios(&config.keep, 60).unwrap();
        let (kept, _) = round_samples(
            &keep,
            Pilot::Student(&start),
            Labeller::Anchor(&start),
            77,
            3,
        )
        .unwrap();
        let drift = gap(&out.actor, &start, Task::Collecting, &kept[1]);
        assert!(drift < 0.05, "keep drift {drift}");
        assert_eq!(out.rounds.len(), 2);
        assert!(out.rounds[1].keep_samples > out.rounds[0].keep_samples);
    }

    #[test]
    fn distillation_is_seeded() {
        let start = tiny();
        let config = DistillConfig {
            rounds: 1,
            updates_per_round: 20,
            ..tiny_config()
        };
        let a = distill(&start, &config, |_| {}).unwrap();
        let b = distill(&start, &config, |_| {}).unwrap();
        assert_eq!(
            crate::evolve::head_parameters(&a.actor, 0),
            crate::evolve::head_parameters(&b.actor, 0)
        );
    }

    #[test]
    fn bad_teacher_and_task_are_named() {
        let start = tiny();
        let bad = DistillConfig {
            teacher: "nobody".into(),
            ..tiny_config()
        };
        let e = distill(&start, &bad, |_| {}).unwrap_err().to_string();
        assert!(e.contains("nobody"), "{e}");
        let bad = DistillConfig {
            teach: vec![EvolutionScenario::paper("grazing", 4, 1, 1)],
            ..tiny_config()
        };
        let e = distill(&start, &bad, |_| {}).unwrap_err().to_string();
        assert!(e.contains("grazing"), "{e}");
    }
}
