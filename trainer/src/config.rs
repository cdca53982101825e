//! The training configuration: one TOML file holds every knob of a run, and `seed` makes the run
//! reproducible (network init, exploration noise, replay sampling, episode seeds, curriculum
//! draws all derive from it).
//!
//! Every section may be left out; missing keys take the documented defaults below, which are
//! the settings of the shipped model (`trainer/configs/mtddpg-v1.toml` spells them all out).
//!
//! ```
//! use skyherd_trainer::config::TrainConfig;
//! let config = TrainConfig::from_toml_str(r#"
//!     seed = 7
//!     [ddpg]
//!     batch_size = 64
//! "#).unwrap();
//! assert_eq!(config.seed, 7);
//! assert_eq!(config.ddpg.batch_size, 64);
//! assert!(config.warm_start.enabled); // default
//! assert!(TrainConfig::from_toml_str("sede = 1").is_err()); // typos are errors
//! ```

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use skyherd_model::Task;
use skyherd_sim::baseline::Method;
use skyherd_sim::task::task_serde;
use thiserror::Error;

use crate::ddpg::{DdpgConfig, NetworkConfig};
use crate::eval::EvalScenario;
use crate::reward::{AuditedReward, RewardKind};

/// Why a configuration was rejected.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read config {path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Not valid TOML or an unknown/mistyped key.
    #[error("bad config: {0}")]
    Parse(#[from] toml::de::Error),
    /// A value is out of range.
    #[error("invalid config field `{field}`: {reason}")]
    Invalid {
        /// Dotted field name.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

/// One scenario the evolution stage herds: a task, N, M (0 = adaptive), the layout and how many
/// episodes each perturbed actor herds per generation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvolutionScenario {
    /// `driving` or `collecting`.
    #[serde(with = "task_serde")]
    pub task: Task,
    /// Targets N.
    pub targets: usize,
    /// Herders M; 0 for the adaptive count.
    pub herders: usize,
    /// The indoor room's layout at paper scale (as `training.room_layout_fraction` draws).
    #[serde(default)]
    pub room: bool,
    /// The indoor preset itself instead of the paper arena: the 10 x 10 x 3 m room at 0.1 s
    /// steps, as the mission flies it (its N and M are this entry's).
    #[serde(default)]
    pub indoor: bool,
    /// Fly the herders through a motion model (a name of `skyherd_sim::HerderDynamics::LIMITS`:
    /// `px4`, `px4-auto`, `indoor`) instead of at their commands; absent, at once (the paper's
    /// protocol).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dynamics: Option<String>,
    /// The wind with `dynamics`: `calm` (the default), `arena` or `room`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wind: Option<String>,
    /// With `dynamics`: commands reach the vehicle this long into each step, s (the MAVLink
    /// loop's sensor tick, 0.1 s; `skyherd_sim::HerderDynamics::command_delay_s`).
    #[serde(default)]
    pub command_delay_s: f64,
    /// Episodes per perturbed actor per generation.
    pub episodes: usize,
}

impl EvolutionScenario {
    /// A paper-layout scenario.
    pub fn paper(task: Task, targets: usize, herders: usize, episodes: usize) -> Self {
        EvolutionScenario {
            task,
            targets,
            herders,
            room: false,
            indoor: false,
            dynamics: None,
            wind: None,
            command_delay_s: 0.0,
            episodes,
        }
    }

    /// The motion model and wind it names, if any; the error says which name is unknown.
    pub fn herder_dynamics(&self) -> Result<Option<skyherd_sim::HerderDynamics>, String> {
        if !(self.command_delay_s.is_finite() && self.command_delay_s >= 0.0) {
            return Err(format!(
                "`command_delay_s` must be 0 s or more, got {}",
                self.command_delay_s
            ));
        }
        if self.command_delay_s != 0.0 && self.dynamics.is_none() {
            return Err("`command_delay_s` needs `dynamics`".into());
        }
        match (&self.dynamics, &self.wind) {
            (None, None) => Ok(None),
            (None, Some(_)) => {
                Err("`wind` needs `dynamics`: without a motion model nothing feels it".into())
            }
            (Some(d), w) => {
                let w = w.as_deref().unwrap_or("calm");
                let delay = self.command_delay_s;
                skyherd_sim::HerderDynamics::named(d, w)
                    .map(|named| {
                        Some(skyherd_sim::HerderDynamics {
                            command_delay_s: delay,
                            ..named
                        })
                    })
                    .ok_or_else(|| {
                    format!(
                        "dynamics `{d}` in wind `{w}`: the motion models are {:?} and the winds {:?}",
                        skyherd_sim::HerderDynamics::LIMITS,
                        skyherd_sim::HerderDynamics::WINDS
                    )
                })
            }
        }
    }

    /// A room-layout scenario.
    pub fn room(task: Task, targets: usize, herders: usize, episodes: usize) -> Self {
        EvolutionScenario {
            room: true,
            ..EvolutionScenario::paper(task, targets, herders, episodes)
        }
    }
}

/// The evolution stage after MTDDPG (`skyherd_trainer::evolve`): evolution strategies on each
/// task's own layers, scored by completion time over the lower bound.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvolutionConfig {
    /// Run it (off: the best MTDDPG checkpoint is the result).
    pub enabled: bool,
    /// Generations per task.
    pub generations: usize,
    /// Antithetic pairs per generation (twice as many actors herd).
    pub population: usize,
    /// Noise scale on the parameters.
    pub sigma: f32,
    /// Adam step size.
    pub learning_rate: f32,
    /// A failed episode scores this many lower bounds.
    pub failure_ratio: f64,
    /// A failed episode scores `failure_progress_span * (1 - f)` more, where `f` is the largest
    /// fraction of the targets that were inside the goal at once: partial credit, so that
    /// perturbations that get a big flock closer to done rank above those that do not, where
    /// every episode fails (N >= 256). 0 (the default) scores every failure alike.
    pub failure_progress_span: f64,
    /// Rank the perturbed actors within each scenario and average the rank differences
    /// (weighted by episodes) instead of ranking them on the mean score of all episodes.
    pub rank_per_scenario: bool,
    /// Episodes are cut (and count as failed) after this many steps.
    pub step_limit: u64,
    /// Check the current heads on held-out seeds every this many generations (and after the last).
    pub check_every: usize,
    /// The check herds each scenario this many times its `episodes`.
    pub check_rounds: usize,
    /// First seed of the check (apart from the training, warm-start and evaluation seeds).
    pub check_seed_base: u64,
    /// What the perturbed actors herd; a task with none is left as it is.
    pub scenarios: Vec<EvolutionScenario>,
}

impl EvolutionConfig {
    /// The configured scenarios of `task`.
    pub fn scenarios_of(&self, task: Task) -> impl Iterator<Item = &EvolutionScenario> {
        self.scenarios.iter().filter(move |s| s.task == task)
    }
}

impl Default for EvolutionConfig {
    fn default() -> Self {
        EvolutionConfig {
            enabled: true,
            generations: 100,
            population: 16,
            sigma: 0.02,
            learning_rate: 0.01,
            failure_ratio: 12.0,
            failure_progress_span: 0.0,
            rank_per_scenario: false,
            step_limit: 900,
            check_every: 5,
            check_rounds: 4,
            check_seed_base: 3_000_000_000,
            scenarios: vec![
                EvolutionScenario::room(Task::Driving, 4, 2, 10),
                EvolutionScenario::paper(Task::Driving, 4, 4, 2),
                EvolutionScenario::paper(Task::Driving, 16, 4, 2),
                EvolutionScenario::paper(Task::Driving, 64, 4, 1),
                EvolutionScenario::paper(Task::Driving, 8, 1, 2),
                EvolutionScenario::paper(Task::Driving, 16, 2, 2),
                EvolutionScenario::paper(Task::Driving, 128, 4, 1),
                EvolutionScenario::paper(Task::Collecting, 4, 2, 2),
                EvolutionScenario::paper(Task::Collecting, 16, 4, 2),
                EvolutionScenario::paper(Task::Collecting, 64, 4, 1),
                EvolutionScenario::paper(Task::Collecting, 8, 1, 2),
                EvolutionScenario::paper(Task::Collecting, 32, 2, 1),
                EvolutionScenario::paper(Task::Collecting, 16, 8, 1),
            ],
        }
    }
}

/// Which shepherding scenarios one curriculum stage draws episodes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurriculumStage {
    /// The stage starts once this fraction of `training.env_steps` is done (0 for the first
    /// stage). Counted in steps, not time, so that a seed fixes the run on any machine.
    pub from_progress: f64,
    /// Target counts N drawn uniformly per episode.
    pub targets: Vec<usize>,
    /// Herder counts M drawn uniformly per episode; 0 means the adaptive count for N.
    pub herders: Vec<usize>,
    /// (N, M) drawn together, each as likely as one entry of `targets` (whose M comes from
    /// `herders`), for counts that only make sense together: a lone herder with one or two
    /// targets, say, without a lone herder facing sixteen. Empty by default, which draws
    /// exactly as a stage without the field.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pairs: Vec<[usize; 2]>,
}

/// The curriculum over N and M. Disabled: every episode draws from the last stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CurriculumConfig {
    /// Whether to go through the stages in order.
    pub enabled: bool,
    /// Stages in increasing `from_progress`.
    pub stages: Vec<CurriculumStage>,
    /// Driving episodes whose goal is pulled towards the flock early in training (a reverse
    /// curriculum); off unless configured.
    pub driving_goal_distance: GoalDistanceCurriculum,
    /// Driving episodes whose herders spawn pulled towards the flock early in training; off
    /// unless configured.
    pub driving_herder_distance: SpawnShareCurriculum,
    /// Collecting episodes whose scattered targets are pulled towards the goal early in
    /// training: each keeps a share of its distance beyond the goal's edge
    /// (`rollout::pull_targets_to_goal`); off unless configured.
    pub collecting_target_distance: SpawnShareCurriculum,
}

/// A reverse curriculum for driving: early driving episodes keep only a share of the paper
/// layout's start-goal distance, so that the learner meets successes (and so the value of
/// finishing sooner) before it meets the long drives. Each driving episode draws its share
/// uniformly from `[floor, 1]`, the floor rising linearly from `first_share` at progress 0 to 1
/// at `full_at_progress`; from then on every episode is the paper's. The goal moves along the
/// line from the flock's centroid, so it stays inside the arena. Evaluation never uses it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GoalDistanceCurriculum {
    /// The smallest share of the start-goal distance, at progress 0 (1: off).
    pub first_share: f64,
    /// The progress (fraction of `training.env_steps`) from which every driving episode has the
    /// full distance.
    pub full_at_progress: f64,
    /// The pulled goal's centre stays at least this many goal radii from the flock's centroid
    /// (never nearer than the paper's layout put it; 0: no floor). Without it a share of 0.2
    /// puts the flock at the goal's edge, so "fly to the goal" and "fly to the flock" are one
    /// behaviour early on, and an actor that learned the first never drives.
    #[serde(default)]
    pub min_centre_distance_radii: f64,
}

impl Default for GoalDistanceCurriculum {
    fn default() -> Self {
        Self {
            first_share: 1.0,
            full_at_progress: 0.0,
            min_centre_distance_radii: 0.0,
        }
    }
}

impl GoalDistanceCurriculum {
    /// The smallest share drawn at `progress`.
    pub fn floor_at(&self, progress: f64) -> f64 {
        let first = self.first_share.clamp(0.0, 1.0);
        if self.full_at_progress <= 0.0 || progress >= self.full_at_progress {
            return 1.0;
        }
        first + (1.0 - first) * (progress / self.full_at_progress).clamp(0.0, 1.0)
    }
}

/// A start-state curriculum that moves spawned things along a line, keeping only a share of
/// their distance; the share is drawn per episode uniformly from `[floor, 1]`, the floor rising
/// linearly from `first_share` at progress 0 to 1 at `full_at_progress`. Both ends of the line
/// are inside the arena, so what is moved stays in it. Evaluation never uses it. Two uses:
///
/// * driving's herders (`curriculum.driving_herder_distance`): each herder's spawn towards the
///   flock's centroid, never nearer than the start circle plus the layout's herder clearance
///   (`rollout::pull_herders`). Herders spawn anywhere in the arena, up to 400 m from the flock,
///   so random flight rarely finishes a drive and a seed can meet no success at all.
/// * collecting's targets (`curriculum.collecting_target_distance`): each scattered target
///   towards the goal's centre, the share taken of its distance beyond the goal's edge
///   (`rollout::pull_targets_to_goal`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SpawnShareCurriculum {
    /// The smallest share of the distance kept, at progress 0 (1: off).
    pub first_share: f64,
    /// The progress (fraction of `training.env_steps`) from which every episode of the task
    /// spawns where the layout put it.
    pub full_at_progress: f64,
}

impl Default for SpawnShareCurriculum {
    fn default() -> Self {
        Self {
            first_share: 1.0,
            full_at_progress: 0.0,
        }
    }
}

impl SpawnShareCurriculum {
    /// The smallest share drawn at `progress`.
    pub fn floor_at(&self, progress: f64) -> f64 {
        GoalDistanceCurriculum {
            first_share: self.first_share,
            full_at_progress: self.full_at_progress,
            min_centre_distance_radii: 0.0,
        }
        .floor_at(progress)
    }
}

impl Default for CurriculumConfig {
    fn default() -> Self {
        let stage = |from_progress: f64, targets: &[usize], herders: &[usize]| CurriculumStage {
            from_progress,
            targets: targets.to_vec(),
            herders: herders.to_vec(),
            pairs: Vec::new(),
        };
        CurriculumConfig {
            enabled: true,
            driving_goal_distance: GoalDistanceCurriculum::default(),
            driving_herder_distance: SpawnShareCurriculum::default(),
            collecting_target_distance: SpawnShareCurriculum::default(),
            stages: vec![
                stage(0.0, &[2, 4, 8, 16], &[1, 2, 4]),
                stage(0.25, &[4, 8, 16, 32, 64], &[1, 2, 4, 8, 0]),
                stage(0.5, &[8, 16, 32, 64, 128, 256], &[1, 4, 8, 0]),
            ],
        }
    }
}

/// Warm start by behaviour cloning a rule-based baseline (the control-tutor idea of CTRL), then
/// policy evaluation of the cloned actor to give the critic a head start.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WarmStartConfig {
    /// Whether to warm start at all.
    pub enabled: bool,
    /// The baseline imitated in the driving task (a `skyherd_sim::baseline::Method` name).
    pub driving_baseline: Method,
    /// The baseline imitated in the collecting task.
    pub collecting_baseline: Method,
    /// Demonstration episodes per task (scenarios drawn from every curriculum stage).
    pub episodes_per_task: usize,
    /// Imitation minibatch updates (one batch per task each).
    pub imitation_updates: usize,
    /// Imitation learning rate (the actor's Adam is reset to the DDPG rate afterwards).
    pub imitation_learning_rate: f32,
    /// Critic-only TD updates on the demonstrations before DDPG starts.
    pub critic_updates: usize,
    /// During DDPG, weight of the pull towards the demonstrated actions (TD3+BC's
    /// `1 / alpha`; the Q term is normalised by mean |Q|). 0 is plain DDPG after the warm start.
    pub imitation_weight: f32,
    /// Teachers for particular flocks, tried in order before the per-task baselines above: no
    /// single rule is best everywhere (docs/baselines: Strömbom drives fastest with several
    /// herders, Lama-style alone and when collecting).
    pub teachers: Vec<TeacherRule>,
}

/// "Imitate `baseline` in `task` when M >= `herders_at_least` and N <= `targets_at_most`."
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TeacherRule {
    /// `driving` or `collecting`.
    #[serde(with = "task_serde")]
    pub task: Task,
    /// Smallest herder count M (after resolving the adaptive count) the rule applies to.
    #[serde(default)]
    pub herders_at_least: usize,
    /// Largest target count N the rule applies to.
    #[serde(default = "unbounded")]
    pub targets_at_most: usize,
    /// The baseline imitated (a `skyherd_sim::baseline::Method` name).
    pub baseline: Method,
}

fn unbounded() -> usize {
    usize::MAX
}

impl WarmStartConfig {
    /// The baseline imitated in `task` with `targets` targets and `herders` herders.
    pub fn teacher(&self, task: Task, targets: usize, herders: usize) -> Method {
        let rule = self.teachers.iter().find(|r| {
            r.task == task && herders >= r.herders_at_least && targets <= r.targets_at_most
        });
        match (rule, task) {
            (Some(r), _) => r.baseline,
            (None, Task::Driving) => self.driving_baseline,
            (None, Task::Collecting) => self.collecting_baseline,
        }
    }
}

impl Default for WarmStartConfig {
    fn default() -> Self {
        WarmStartConfig {
            enabled: true,
            driving_baseline: Method::Lama,
            collecting_baseline: Method::Lama,
            episodes_per_task: 48,
            imitation_updates: 20_000,
            imitation_learning_rate: 1e-3,
            critic_updates: 5_000,
            imitation_weight: 0.4,
            teachers: Vec::new(),
        }
    }
}

/// How the environment's reward reaches the learner.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RewardConfig {
    /// Apply the simulator's `leave-covers-remaining-steps` correction of the suicide problem
    /// (the printed reward rewards leaving: see `skyherd_sim::reward`) with the learner's gamma. Off: the paper's reward as printed.
    pub leave_correction: bool,
    /// Divide each episode's rewards by its idle-plus-flight cost per step,
    /// `k0 (k3 |r3| N + k4 v_max M)`, so that N = 1 and N = 256 episodes give Q-values of the
    /// same size. A constant factor per episode: each scenario's best policy is unchanged.
    pub normalize_by_step_cost: bool,
    /// Multiplies the flight term (eq 11). 1 is the paper; below 1 weakens the term that makes
    /// standing still cheaper than herding (see MODEL.md).
    pub flight_scale: f64,
    /// Which reward the learner optimises: `paper` (the simulator's, with the three options
    /// above) or `audited` (time cost, potential shaping, own flight cost, success bonus,
    /// fixed leave penalty: `skyherd_trainer::reward`).
    pub kind: RewardKind,
    /// The weights of the `audited` reward.
    pub audited: AuditedReward,
    /// Driving's own weights, in place of `audited` for that task (a whole set: fields left
    /// out take `AuditedReward`'s defaults, not `audited`'s). The critic has a head per task,
    /// so each task's values may have a scale of their own.
    pub audited_driving: Option<AuditedReward>,
    /// Collecting's own weights, likewise.
    pub audited_collecting: Option<AuditedReward>,
}

impl Default for RewardConfig {
    fn default() -> Self {
        RewardConfig {
            leave_correction: true,
            normalize_by_step_cost: true,
            flight_scale: 0.1,
            kind: RewardKind::Paper,
            audited: AuditedReward::default(),
            audited_driving: None,
            audited_collecting: None,
        }
    }
}

impl RewardConfig {
    /// The `audited` weights that `task` trains with.
    pub fn audited_for(&self, task: skyherd_model::Task) -> &AuditedReward {
        let own = match task {
            skyherd_model::Task::Driving => self.audited_driving.as_ref(),
            skyherd_model::Task::Collecting => self.audited_collecting.as_ref(),
        };
        own.unwrap_or(&self.audited)
    }
}

/// Evaluation on held-out seeds, keeping the best checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalConfig {
    /// Evaluate every this many DDPG updates (and after the warm start).
    pub every_updates: u64,
    /// Instead, when above 0: evaluate every this many environment steps per trained task
    /// (the ablation's cadence, the same for a one-task and a two-task run).
    pub every_task_env_steps: u64,
    /// Episodes per evaluation scenario.
    pub episodes: usize,
    /// Episode seeds are `seed_base + k`; far from the training seeds.
    pub seed_base: u64,
    /// The scenarios evaluated, with test-time noise, written as `[task, N, M]` triples
    /// (`["driving", 16, 4]`); M = 0 is adaptive.
    #[serde(with = "eval_triples")]
    pub scenarios: Vec<EvalScenario>,
    /// When above 0: the this-many best checkpoints by the training-time check are kept as
    /// finalists (`finalist-<env steps>.safetensors`), and at the end of the run the one that
    /// scores best on a second, independent episode set becomes `best.safetensors`. The check
    /// reads some forty checkpoints on one set, so its best reads high by luck; the second set
    /// has not been chosen on. 0: off (the check's own best is kept).
    pub finalists: usize,
    /// Episodes per scenario of the finalists' episode set.
    pub final_episodes: usize,
    /// The finalists' episode seeds are `final_seed_base + k`: apart from the check's and from
    /// every report set.
    pub final_seed_base: u64,
    /// When set: the actors of the finalists checked at or after this share of
    /// `training.env_steps` are also averaged, parameter by parameter, into one more candidate
    /// for the end-of-run choice, scored on the same second set and kept only if it scores best
    /// there (`skyherd_trainer::finalists::mean_members`). Learning is unchanged. Off (`None`)
    /// by default.
    pub average_finalists_from: Option<f64>,
}

impl EvalConfig {
    /// The evaluated scenarios.
    pub fn scenario_list(&self) -> Vec<EvalScenario> {
        self.scenarios.clone()
    }
}

/// Serde for evaluation scenarios as `[task, N, M]` triples.
mod eval_triples {
    use serde::{Deserialize, Deserializer, Serialize, Serializer, de::Error};
    use skyherd_sim::task::{parse_task, task_name};

    use crate::eval::EvalScenario;

    pub(super) fn serialize<S: Serializer>(list: &[EvalScenario], s: S) -> Result<S::Ok, S::Error> {
        list.iter()
            .map(|e| (task_name(e.task), e.targets, e.herders))
            .collect::<Vec<_>>()
            .serialize(s)
    }

    pub(super) fn deserialize<'de, D: Deserializer<'de>>(
        d: D,
    ) -> Result<Vec<EvalScenario>, D::Error> {
        Vec::<(String, usize, usize)>::deserialize(d)?
            .into_iter()
            .map(|(task, targets, herders)| {
                let task = parse_task(&task).ok_or_else(|| {
                    D::Error::custom(format!(
                        "unknown task `{task}`, expected `driving` or `collecting`"
                    ))
                })?;
                Ok(EvalScenario {
                    task,
                    targets,
                    herders,
                })
            })
            .collect()
    }
}

impl Default for EvalConfig {
    fn default() -> Self {
        EvalConfig {
            every_updates: 10_000,
            every_task_env_steps: 0,
            episodes: 8,
            seed_base: 1_000_000_000,
            finalists: 0,
            final_episodes: 48,
            final_seed_base: 6_000_000_000,
            average_finalists_from: None,
            scenarios: [
                (Task::Driving, 16, 4),
                (Task::Driving, 64, 4),
                (Task::Driving, 256, 0),
                (Task::Collecting, 16, 4),
                (Task::Collecting, 64, 4),
            ]
            .map(|(task, targets, herders)| EvalScenario {
                task,
                targets,
                herders,
            })
            .to_vec(),
        }
    }
}

/// The DDPG phase: how much experience, how many updates.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoopConfig {
    /// Environment steps (summed over the parallel environments) of DDPG fine-tuning.
    pub env_steps: u64,
    /// Environments stepped together, half of them per task.
    pub envs: usize,
    /// Gradient updates per environment step.
    pub updates_per_env_step: f64,
    /// Transitions kept per task.
    pub replay_capacity: usize,
    /// Steps of pure experience collection before the first DDPG update (after a warm start
    /// the demonstrations already fill the buffers).
    pub learning_starts: u64,
    /// Training episodes are truncated (and bootstrapped) after this many steps.
    pub episode_step_limit: u64,
    /// Stop the DDPG phase after this many seconds of wall time, whatever `env_steps` says.
    pub wall_clock_limit_s: f64,
    /// Write `last.safetensors` every this many seconds.
    pub checkpoint_every_s: f64,
    /// Threads for rollouts and evaluation (the machine has 2 cores).
    pub threads: usize,
    /// Train with the scenario's test-time noise (boids parameters, sensing, actuation), so
    /// that the policy meets in training what it meets in evaluation.
    pub noise: bool,
    /// Fraction of driving episodes with N <= [`ROOM_LAYOUT_MAX_TARGETS`] laid out like the
    /// indoor room zoomed back to the paper's scale: start and goal at least 400 m apart,
    /// 25 m from the walls (the paper layout keeps 50 m and 150 m), so the long drives from
    /// corner to corner that the room asks for are met in training too.
    pub room_layout_fraction: f64,
    /// The first this many environment steps of the DDPG phase fly random waypoints instead
    /// of the actor (`rollout::Controller::RandomWaypoints`); they count towards `env_steps`.
    pub random_warmup_steps: u64,
    /// Train as the drones fly: every herder's command goes through the onboard rules
    /// (`skyherd_onboard::safety::check` with `Limits::arena`: geofence, altitude band, speed
    /// caps) before it reaches the simulator, and the encoder reads the height above the
    /// band's floor, exactly as `skyherd-sim eval` and the daemon fly a model. The replay keeps
    /// the actor's own action; the rules are part of the world it learns.
    pub flight_rules: bool,
    /// The tasks trained (`["driving", "collecting"]`: MTDDPG; one task: the single-task arm
    /// of the ablation, whose shared layers then learn from that task alone). The parallel
    /// environments cycle through them; evaluation keeps the scenarios of these tasks.
    #[serde(with = "task_list_serde")]
    pub tasks: Vec<Task>,
    /// Random restarts: this many candidates, seeded apart, each trained for
    /// `restart_trial_env_steps`; the best on the training-time evaluation goes on. Every
    /// candidate's steps count towards `env_steps`. 1: off (`train::train_with_restarts`).
    pub restart_candidates: usize,
    /// Each restart candidate's trial, env steps.
    pub restart_trial_env_steps: u64,
    /// How the restart candidates are ranked at the end of their trials.
    pub restart_score: RestartScore,
    /// Stalled-task resets: a task whose training-time evaluation has not reached
    /// `task_reset_below` mean success within this many of its own env steps (since the run
    /// began or since its last reset) is started over (`ddpg::Agent::reset_task`: its own
    /// layers of actor and critics drawn afresh, its curriculum from the start); the shared
    /// layers, the other task and the replay stay. Needs `eval.every_task_env_steps`. 0: off.
    pub task_reset_after_task_env_steps: u64,
    /// The mean held-out success (over the task's evaluation scenarios) a task must have
    /// reached, at some evaluation since its last reset, not to be reset.
    pub task_reset_below: f64,
    /// Resets per task at most.
    pub task_resets_max: u32,
    /// Whether a reset task's replay is emptied too (its transitions are the stalled actor's:
    /// valid off-policy, but without a success in them).
    pub task_reset_clears_replay: bool,
    /// After a reset, that task's environments fly random waypoints for this many env steps
    /// (of the whole run, as `random_warmup_steps` counts them), the other task its actor.
    pub task_reset_warmup_steps: u64,
    /// Which evaluations the patience reads ([`TaskResetRule`]).
    pub task_reset_rule: TaskResetRule,
    /// Updates go where learning is left: while some trained task's latest training-time
    /// evaluation is below `passed_task_bar` mean success, a task at or above it has its
    /// minibatch in only this share of the updates, and the updates per env step rise so that
    /// the minibatch rows per env step (the update compute) stay as configured. The other
    /// tasks get the updates a learned one no longer needs. Needs `eval.every_task_env_steps`.
    /// 1: off (every update holds every task's minibatch).
    pub passed_task_update_share: f64,
    /// The mean held-out success (over the task's evaluation scenarios, at its latest
    /// evaluation) at which a task counts as learned for `passed_task_update_share` and
    /// `passed_task_env_share`.
    pub passed_task_bar: f64,
    /// Env steps go where learning is left: under the same condition as
    /// `passed_task_update_share`, a learned task's weight in the parallel environments is
    /// this share and an unlearned one's is 1; each environment takes its next episode's task
    /// so that the environments per task follow the weights (at least one each), so the
    /// unlearned task gets more of the run's env steps while the total stays as configured.
    /// The update rate and each update's minibatches are untouched. Evaluation cadence, reset
    /// patience and curricula keep counting the run's env steps divided by the task count.
    /// Needs `eval.every_task_env_steps`. 1: off (environment `i` always runs task `i % 2`).
    pub passed_task_env_share: f64,
    /// Exploration excursions (off by default: 0): while the actor flies an environment of one
    /// of `excursion_tasks`, each of its herders starts, with this probability per step, an
    /// excursion: it flies at full speed to a point drawn `excursion_radius_m` from a target
    /// drawn at random, on any side of it, for at most `excursion_max_steps` steps or until it
    /// is there, and the actor (with its noise) takes over again. The replay keeps the flown
    /// actions, as in the random-waypoint warm-up. What the herder should do near a target is
    /// still learned from the reward alone; the excursions only put it there, where the
    /// actor's own noise seldom takes it (`rollout::Excursions`).
    pub excursion_rate: f64,
    /// Nearest and farthest distance (metres, simulator frame) of an excursion's waypoint from
    /// its target.
    pub excursion_radius_m: [f64; 2],
    /// Steps an excursion lasts at most.
    pub excursion_max_steps: u64,
    /// The tasks whose environments fly excursions.
    #[serde(with = "task_list_serde")]
    pub excursion_tasks: Vec<Task>,
    /// Action repeat: the actor decides every this many simulator steps and each herder holds
    /// the velocity it chose until the next decision; one transition spans the held steps,
    /// its reward their discounted sum and its bootstrap `gamma` to their number
    /// (`rollout::Rollouts::step`, `replay::NStep`), and `ddpg.n_step` counts decisions. A
    /// one-second step moves a herder at most 5 m, so one action changes the return little
    /// and the critic's action gradient is small beside its errors; holding it longer makes
    /// each decision count for more. Evaluation and flight still ask the actor every step.
    /// With `flight_rules`, the onboard rules check the velocity when it is decided.
    /// 1: off (every step a decision).
    pub action_repeat: usize,
}

/// Which evaluations decide that a task has stalled ([`LoopConfig::task_reset_after_task_env_steps`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TaskResetRule {
    /// The task has not reached `task_reset_below` at any evaluation since its last reset
    /// (the default, so older configs train as they did). A task that passed once and then
    /// collapsed is never reset.
    #[default]
    BestSinceReset,
    /// The task has not reached `task_reset_below` at any evaluation within the patience, the
    /// last `task_reset_after_task_env_steps` of its own env steps: a collapse is a stall too.
    Recent,
}

/// How restart candidates are ranked ([`LoopConfig::restart_candidates`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RestartScore {
    /// Mean success over every evaluation scenario, then time (`eval::score`).
    #[default]
    Mean,
    /// The weaker task's mean success, then time (`eval::weakest_task_score`).
    WeakestTask,
}

/// Serde for a list of tasks by name.
mod task_list_serde {
    use serde::{Deserialize, Deserializer, Serializer, de::Error, ser::SerializeSeq};
    use skyherd_model::Task;
    use skyherd_sim::task::{parse_task, task_name};

    pub(super) fn serialize<S: Serializer>(tasks: &[Task], s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(tasks.len()))?;
        for t in tasks {
            seq.serialize_element(task_name(*t))?;
        }
        seq.end()
    }

    pub(super) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Task>, D::Error> {
        Vec::<String>::deserialize(d)?
            .iter()
            .map(|name| {
                parse_task(name).ok_or_else(|| {
                    D::Error::custom(format!(
                        "unknown task `{name}`, expected `driving` or `collecting`"
                    ))
                })
            })
            .collect()
    }
}

/// Largest `training.action_repeat` accepted (ten seconds of held flight at the paper's step).
pub const MAX_ACTION_REPEAT: usize = 10;

/// Largest flock drawn into the room layout.
pub const ROOM_LAYOUT_MAX_TARGETS: usize = 64;

impl Default for LoopConfig {
    fn default() -> Self {
        LoopConfig {
            env_steps: 400_000,
            envs: 8,
            updates_per_env_step: 0.5,
            replay_capacity: 500_000,
            learning_starts: 2_000,
            episode_step_limit: 600,
            wall_clock_limit_s: 1_200.0,
            checkpoint_every_s: 120.0,
            threads: 2,
            noise: true,
            room_layout_fraction: 0.25,
            random_warmup_steps: 0,
            flight_rules: false,
            tasks: Task::ALL.to_vec(),
            restart_candidates: 1,
            restart_trial_env_steps: 0,
            restart_score: RestartScore::Mean,
            task_reset_after_task_env_steps: 0,
            task_reset_below: 0.25,
            task_resets_max: 2,
            task_reset_clears_replay: false,
            task_reset_warmup_steps: 0,
            task_reset_rule: TaskResetRule::BestSinceReset,
            passed_task_update_share: 1.0,
            passed_task_bar: 0.95,
            passed_task_env_share: 1.0,
            excursion_rate: 0.0,
            excursion_radius_m: [5.0, 25.0],
            excursion_max_steps: 40,
            action_repeat: 1,
            excursion_tasks: Vec::new(),
        }
    }
}

/// A whole training run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    /// Master seed.
    pub seed: u64,
    /// Where checkpoints, the CSV log and the plot go.
    pub output_dir: PathBuf,
    /// Network sizes.
    pub network: NetworkConfig,
    /// DDPG hyper-parameters.
    pub ddpg: DdpgConfig,
    /// The DDPG loop.
    pub training: LoopConfig,
    /// Curriculum over N and M.
    pub curriculum: CurriculumConfig,
    /// Behaviour-cloning warm start.
    pub warm_start: WarmStartConfig,
    /// Reward handling.
    pub reward: RewardConfig,
    /// Held-out evaluation.
    pub eval: EvalConfig,
    /// Evolution-strategies fine-tuning of the task heads after MTDDPG.
    pub evolution: EvolutionConfig,
    /// Start DDPG from a trained actor instead of a fresh one.
    pub fine_tune: FineTuneConfig,
    /// The observation encoder version the actor is made for
    /// (`skyherd_onboard::obs::feature_count`): its input width. mtddpg-v1 was trained on v3;
    /// the default is [`DEFAULT_ENCODER_VERSION`].
    pub encoder_version: u16,
}

/// The encoder version a config that names none is trained for: v4, which every config
/// written before encoder v5 was trained on, so that each still trains exactly as it did. A
/// config asks for v5's assignment features by name (`encoder_version = 5`).
pub const DEFAULT_ENCODER_VERSION: u16 = 4;

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            seed: 1,
            output_dir: PathBuf::from("runs/mtddpg-v1"),
            network: NetworkConfig::default(),
            ddpg: DdpgConfig::default(),
            training: LoopConfig::default(),
            curriculum: CurriculumConfig::default(),
            warm_start: WarmStartConfig::default(),
            reward: RewardConfig::default(),
            eval: EvalConfig::default(),
            evolution: EvolutionConfig::default(),
            fine_tune: FineTuneConfig::default(),
            encoder_version: DEFAULT_ENCODER_VERSION,
        }
    }
}

/// Reinforcement-learning fine-tuning of an actor that already herds (the distilled
/// `mtddpg-v3`, say): the actor and its target start from `actor`, the critics fresh; for the
/// first `critic_only_env_steps` the loaded actor flies (with exploration noise) and only the
/// critic learns (policy evaluation), so that the actor's first gradient comes from a critic
/// that knows it, not from a random one.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FineTuneConfig {
    /// An actor file (`skyherd-trainer export --actor-out`, or `save_actor`); none: off.
    pub actor: Option<PathBuf>,
    /// Environment steps of critic-only learning before the actor moves.
    pub critic_only_env_steps: u64,
}

impl TrainConfig {
    /// Parses and validates TOML text.
    pub fn from_toml_str(text: &str) -> Result<TrainConfig, ConfigError> {
        let config: TrainConfig = toml::from_str(text)?;
        config.validate()?;
        Ok(config)
    }

    /// Reads a config file.
    pub fn load(path: &Path) -> Result<TrainConfig, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.to_owned(),
            source,
        })?;
        TrainConfig::from_toml_str(&text)
    }

    /// The config as TOML (stored in every checkpoint).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_default()
    }

    /// Checks value ranges; the error names the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &'static str, reason: &str| {
            Err(ConfigError::Invalid {
                field,
                reason: reason.to_owned(),
            })
        };
        if skyherd_onboard::obs::feature_count(self.encoder_version).is_none() {
            return bad("encoder_version", "is not a version this build encodes for");
        }
        let d = &self.ddpg;
        if !(d.gamma > 0.0 && d.gamma <= 1.0) {
            return bad("ddpg.gamma", "must be in (0, 1]");
        }
        if !(d.tau > 0.0 && d.tau <= 1.0) {
            return bad("ddpg.tau", "must be in (0, 1]");
        }
        if !(d.exploration_noise.is_finite() && d.exploration_noise >= 0.0) {
            return bad("ddpg.exploration_noise", "must be a finite number >= 0");
        }
        if let Some(last) = d.exploration_noise_final
            && !(last.is_finite() && last >= 0.0)
        {
            return bad(
                "ddpg.exploration_noise_final",
                "must be a finite number >= 0",
            );
        }
        let (from, to) = (d.exploration_noise_decay_from, d.exploration_noise_decay_to);
        if !(0.0..=1.0).contains(&from) || !(0.0..=1.0).contains(&to) || from > to {
            return bad(
                "ddpg.exploration_noise_decay_from",
                "and exploration_noise_decay_to must be fractions of the run with from <= to",
            );
        }
        if !(d.self_imitation.is_finite() && d.self_imitation >= 0.0) {
            return bad(
                "ddpg.self_imitation",
                "must be a finite number >= 0 (0: off)",
            );
        }
        if !(d.advantage_scale.is_finite() && d.advantage_scale >= 0.0) {
            return bad(
                "ddpg.advantage_scale",
                "must be a finite number >= 0 (0: a plain critic)",
            );
        }
        if d.advantage_scale > 0.0 && d.centralised_critic {
            return bad(
                "ddpg.advantage_scale",
                "the advantage-decomposed critic does not take the centralised critic's context",
            );
        }
        if !(0.0..=1.0).contains(&d.twin_min_weight) {
            return bad(
                "ddpg.twin_min_weight",
                "must be in [0, 1] (1: TD3's min, 0: the mean)",
            );
        }
        if d.batch_size < 2 {
            return bad(
                "ddpg.batch_size",
                "must be >= 2 (one row per task at least)",
            );
        }
        if self.network.hidden == 0 || self.network.hidden > 255 {
            return bad("network.hidden", "must be in 1..=255 (onboard capacity)");
        }
        if self.training.envs < 2 {
            return bad("training.envs", "must be >= 2 (one per task at least)");
        }
        if self.training.threads == 0 {
            return bad("training.threads", "must be >= 1");
        }
        let tasks = &self.training.tasks;
        if tasks.is_empty() || (1..tasks.len()).any(|i| tasks[..i].contains(&tasks[i])) {
            return bad("training.tasks", "needs one or both tasks, each once");
        }
        if self.curriculum.stages.is_empty() {
            return bad("curriculum.stages", "needs at least one stage");
        }
        for s in &self.curriculum.stages {
            if s.targets.is_empty() || s.herders.is_empty() || s.targets.contains(&0) {
                return bad(
                    "curriculum.stages",
                    "every stage needs target counts >= 1 and herder counts",
                );
            }
            if s.pairs.iter().any(|&[targets, _]| targets == 0) {
                return bad(
                    "curriculum.stages",
                    "every (N, M) pair needs N >= 1 (M = 0 is the adaptive count)",
                );
            }
        }
        if self.fine_tune.actor.is_some() && self.warm_start.enabled {
            return bad(
                "fine_tune.actor",
                "a fine-tune starts from its actor: disable [warm_start]",
            );
        }
        if self.ddpg.centralised_critic && self.ddpg.critic_max_others == 0 {
            return bad(
                "ddpg.critic_max_others",
                "must be >= 1 with a centralised critic",
            );
        }
        let t = &self.training;
        if !(1..=16).contains(&t.restart_candidates) {
            return bad("training.restart_candidates", "must be 1 (off) to 16");
        }
        if t.restart_candidates > 1
            && (t.restart_trial_env_steps == 0
                || (t.restart_candidates as u64).saturating_mul(t.restart_trial_env_steps)
                    >= t.env_steps)
        {
            return bad(
                "training.restart_trial_env_steps",
                "must be above 0, and all the candidates' trials below training.env_steps",
            );
        }
        if t.task_reset_after_task_env_steps > 0 {
            if self.eval.every_task_env_steps == 0 {
                return bad(
                    "training.task_reset_after_task_env_steps",
                    "needs eval.every_task_env_steps above 0 (a reset is decided at an evaluation)",
                );
            }
            if t.task_reset_after_task_env_steps < self.eval.every_task_env_steps {
                return bad(
                    "training.task_reset_after_task_env_steps",
                    "must be at least eval.every_task_env_steps",
                );
            }
            if !(t.task_reset_below > 0.0 && t.task_reset_below <= 1.0) {
                return bad("training.task_reset_below", "must be in (0, 1]");
            }
            if !(1..=8).contains(&t.task_resets_max) {
                return bad("training.task_resets_max", "must be 1 to 8");
            }
            if t.task_reset_warmup_steps >= t.env_steps {
                return bad(
                    "training.task_reset_warmup_steps",
                    "must be below training.env_steps",
                );
            }
        }
        if !(t.passed_task_update_share > 0.0 && t.passed_task_update_share <= 1.0) {
            return bad("training.passed_task_update_share", "must be in (0, 1]");
        }
        if !(t.passed_task_env_share > 0.0 && t.passed_task_env_share <= 1.0) {
            return bad("training.passed_task_env_share", "must be in (0, 1]");
        }
        if t.passed_task_env_share < 1.0 && self.eval.every_task_env_steps == 0 {
            return bad(
                "training.passed_task_env_share",
                "needs eval.every_task_env_steps above 0 (it reads each task's evaluations)",
            );
        }
        if t.passed_task_env_share < 1.0 && t.envs < t.tasks.len() * 2 {
            return bad(
                "training.passed_task_env_share",
                "needs at least two environments per task (one is each task's floor)",
            );
        }
        if !(0.0..=1.0).contains(&t.excursion_rate) {
            return bad("training.excursion_rate", "must be a probability in [0, 1]");
        }
        let [near, far] = t.excursion_radius_m;
        if !(near.is_finite() && far.is_finite() && near >= 0.0 && near <= far) {
            return bad(
                "training.excursion_radius_m",
                "must be [nearest, farthest] metres with 0 <= nearest <= farthest",
            );
        }
        if !(1..=MAX_ACTION_REPEAT).contains(&t.action_repeat) {
            return bad(
                "training.action_repeat",
                &format!("must be 1 to {MAX_ACTION_REPEAT} simulator steps per decision"),
            );
        }
        if t.action_repeat > 1 && d.centralised_critic {
            return bad(
                "training.action_repeat",
                "cannot be combined with ddpg.centralised_critic (its pooled context is per step)",
            );
        }
        if t.excursion_rate > 0.0 && (t.excursion_max_steps == 0 || t.excursion_tasks.is_empty()) {
            return bad(
                "training.excursion_tasks",
                "excursions need at least one task and excursion_max_steps above 0",
            );
        }
        if !(t.passed_task_bar > 0.0 && t.passed_task_bar <= 1.0) {
            return bad("training.passed_task_bar", "must be in (0, 1]");
        }
        if t.passed_task_update_share < 1.0 && self.eval.every_task_env_steps == 0 {
            return bad(
                "training.passed_task_update_share",
                "needs eval.every_task_env_steps above 0 (it reads each task's evaluations)",
            );
        }
        let e = &self.eval;
        if e.finalists > 0 {
            if e.final_episodes == 0 {
                return bad(
                    "eval.final_episodes",
                    "must be at least 1 when eval.finalists is",
                );
            }
            // The second set is worth having only if the check has not already seen it.
            let check = e.seed_base..e.seed_base.saturating_add(e.episodes as u64);
            let last = e.final_seed_base.saturating_add(e.final_episodes as u64);
            if e.final_seed_base < check.end && check.start < last {
                return bad(
                    "eval.final_seed_base",
                    "the finalists' episodes overlap the training-time check's (eval.seed_base)",
                );
            }
        }
        if let Some(from) = e.average_finalists_from {
            if e.finalists < 2 {
                return bad(
                    "eval.average_finalists_from",
                    "averages finalists, so eval.finalists must be at least 2",
                );
            }
            if !(0.0..1.0).contains(&from) {
                return bad(
                    "eval.average_finalists_from",
                    "must be a share of the run in [0, 1)",
                );
            }
        }
        let g = &self.curriculum.driving_goal_distance;
        if !(g.first_share > 0.0 && g.first_share <= 1.0) {
            return bad(
                "curriculum.driving_goal_distance.first_share",
                "must be in (0, 1]",
            );
        }
        if !(g.full_at_progress >= 0.0 && g.full_at_progress <= 1.0) {
            return bad(
                "curriculum.driving_goal_distance.full_at_progress",
                "must be in [0, 1]",
            );
        }
        if !(g.min_centre_distance_radii >= 0.0 && g.min_centre_distance_radii <= 100.0) {
            return bad(
                "curriculum.driving_goal_distance.min_centre_distance_radii",
                "must be in [0, 100]",
            );
        }
        for (h, first, full) in [
            (
                &self.curriculum.driving_herder_distance,
                "curriculum.driving_herder_distance.first_share",
                "curriculum.driving_herder_distance.full_at_progress",
            ),
            (
                &self.curriculum.collecting_target_distance,
                "curriculum.collecting_target_distance.first_share",
                "curriculum.collecting_target_distance.full_at_progress",
            ),
        ] {
            if !(h.first_share >= 0.0 && h.first_share <= 1.0) {
                return bad(first, "must be in [0, 1]");
            }
            if !(h.full_at_progress >= 0.0 && h.full_at_progress <= 1.0) {
                return bad(full, "must be in [0, 1]");
            }
        }
        let ev = &self.evolution;
        if ev
            .scenarios
            .iter()
            .any(|s| s.targets == 0 || s.episodes == 0)
        {
            return bad(
                "evolution.scenarios",
                "every scenario needs targets >= 1 and episodes >= 1",
            );
        }
        for s in &ev.scenarios {
            if let Err(reason) = s.herder_dynamics() {
                return Err(ConfigError::Invalid {
                    field: "evolution.scenarios",
                    reason,
                });
            }
            if s.indoor && s.room {
                return bad(
                    "evolution.scenarios",
                    "`indoor` (the room itself) and `room` (its layout at paper scale) exclude each other",
                );
            }
        }
        if !(ev.sigma > 0.0 && ev.sigma.is_finite()) {
            return bad("evolution.sigma", "must be finite and > 0");
        }
        if !(ev.learning_rate > 0.0 && ev.learning_rate.is_finite()) {
            return bad("evolution.learning_rate", "must be finite and > 0");
        }
        if !(ev.failure_ratio >= 1.0 && ev.failure_ratio.is_finite()) {
            return bad("evolution.failure_ratio", "must be finite and >= 1");
        }
        if !(ev.failure_progress_span >= 0.0 && ev.failure_progress_span.is_finite()) {
            return bad("evolution.failure_progress_span", "must be finite and >= 0");
        }
        if ev.step_limit == 0 || ev.check_rounds == 0 {
            return bad("evolution", "step_limit and check_rounds must be >= 1");
        }
        Ok(())
    }

    /// The curriculum stage in force at `progress` (fraction of DDPG steps done).
    pub fn stage_at(&self, progress: f64) -> &CurriculumStage {
        let stages = &self.curriculum.stages;
        if !self.curriculum.enabled {
            return &stages[stages.len() - 1];
        }
        stages
            .iter()
            .rev()
            .find(|s| s.from_progress <= progress)
            .unwrap_or(&stages[0])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each `(from, to, key)`: `text` holds `from`, and with it replaced by `to` the config is
    /// refused with an error that names `key`.
    fn assert_each_edit_is_refused(text: &str, edits: &[(&str, &str, &str)]) {
        for &(from, to, key) in edits {
            assert!(text.contains(from), "{from}");
            let e = TrainConfig::from_toml_str(&text.replace(from, to))
                .unwrap_err()
                .to_string();
            assert!(e.contains(key), "{to}: {e}");
        }
    }

    #[test]
    fn the_shipped_config_file_spells_out_the_defaults() {
        // All but the encoder: mtddpg-v1 reads encoder v3's features, configs that name none v4's.
        let text = include_str!("../configs/mtddpg-v1.toml");
        let file = TrainConfig::from_toml_str(text).expect("shipped config parses");
        assert_eq!(file.encoder_version, 3);
        assert_eq!(
            file,
            TrainConfig {
                encoder_version: 3,
                ..TrainConfig::default()
            }
        );
        let bad = text.replace("encoder_version = 3", "encoder_version = 2");
        let e = TrainConfig::from_toml_str(&bad).unwrap_err().to_string();
        assert!(e.contains("encoder_version"), "{e}");
    }

    /// Asserts that `config` is `base` once `undo` takes back the changes it was made with
    /// (the output directory aside).
    fn assert_is_with_undone(
        config: &TrainConfig,
        base: &TrainConfig,
        undo: impl FnOnce(&mut TrainConfig),
    ) {
        let mut same = config.clone();
        same.output_dir = base.output_dir.clone();
        undo(&mut same);
        assert_eq!(&same, base);
    }

    #[test]
    fn the_twelfth_config_is_the_eleventh_with_recent_resets_and_the_collecting_curriculum() {
        let twelfth = TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch12.toml"))
            .expect("the twelfth config parses");
        assert_eq!(twelfth.training.task_reset_rule, TaskResetRule::Recent);
        let c = twelfth.curriculum.collecting_target_distance;
        assert_eq!((c.first_share, c.full_at_progress), (0.2, 0.3));
        let eleventh = TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch11.toml"))
            .expect("the eleventh config parses");
        assert_eq!(
            eleventh.training.task_reset_rule,
            TaskResetRule::BestSinceReset
        );
        assert_is_with_undone(&twelfth, &eleventh, |same| {
            same.training.task_reset_rule = TaskResetRule::BestSinceReset;
            same.curriculum.collecting_target_distance = SpawnShareCurriculum::default();
        });
        // The thirteenth differs from it only in collecting's shaping.
        let thirteenth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch13.toml"))
                .expect("the thirteenth config parses");
        assert_is_with_undone(&thirteenth, &twelfth, |same| {
            same.reward.audited.shaping = 1.0;
            same.reward.audited.shaping_form = crate::reward::ShapingForm::Potential;
        });
        assert_eq!(thirteenth.reward.audited.shaping, 5.0);
        // The fourteenth differs from it only in where the updates go.
        let fourteenth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch14.toml"))
                .expect("the fourteenth config parses");
        assert_eq!(fourteenth.training.passed_task_update_share, 0.25);
        assert_eq!(fourteenth.training.passed_task_bar, 0.95);
        assert_is_with_undone(&fourteenth, &twelfth, |same| {
            same.training.passed_task_update_share = 1.0;
        });
        // The fifteenth differs from it only in collecting's straggler weight.
        let fifteenth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch15.toml"))
                .expect("the fifteenth config parses");
        assert_eq!(fifteenth.reward.audited.straggler, 1.0);
        assert_eq!(
            fifteenth
                .reward
                .audited_driving
                .as_ref()
                .map(|d| d.straggler),
            Some(0.0)
        );
        assert_is_with_undone(&fifteenth, &twelfth, |same| {
            same.reward.audited.straggler = 0.0;
        });
        // The sixteenth differs from it only in the discount.
        let sixteenth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch16.toml"))
                .expect("the sixteenth config parses");
        assert_eq!(sixteenth.ddpg.gamma, 0.998);
        assert_is_with_undone(&sixteenth, &twelfth, |same| {
            same.ddpg.gamma = 0.995;
        });
        // The seventeenth differs from the fifteenth only in collecting's shaping.
        let seventeenth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch17.toml"))
                .expect("the seventeenth config parses");
        assert_eq!(seventeenth.reward.audited.shaping, 5.0);
        assert_is_with_undone(&seventeenth, &fifteenth, |same| {
            same.reward.audited.shaping = 1.0;
            same.reward.audited.shaping_form = crate::reward::ShapingForm::Potential;
        });
        // The eighteenth differs from the fifteenth only in the return's length.
        let eighteenth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch18.toml"))
                .expect("the eighteenth config parses");
        assert_eq!(eighteenth.ddpg.n_step, 10);
        assert_is_with_undone(&eighteenth, &fifteenth, |same| {
            same.ddpg.n_step = 5;
        });
        // The nineteenth differs from the fifteenth only in where the env steps go.
        let nineteenth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch19.toml"))
                .expect("the nineteenth config parses");
        assert_eq!(nineteenth.training.passed_task_env_share, 0.25);
        assert_is_with_undone(&nineteenth, &fifteenth, |same| {
            same.training.passed_task_env_share = 1.0;
        });
        // The twentieth differs from the nineteenth only in the exploration noise's fall; a
        // window that runs backwards, or a negative noise, is refused by name.
        let twentieth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch20.toml"))
                .expect("the twentieth config parses");
        assert_eq!(twentieth.ddpg.exploration_noise_final, Some(0.1));
        assert_eq!(twentieth.ddpg.exploration_noise_at(0.0), 0.3);
        assert!((twentieth.ddpg.exploration_noise_at(0.9) - 0.1).abs() < 1e-6);
        assert_is_with_undone(&twentieth, &nineteenth, |same| {
            same.ddpg.exploration_noise_final = None;
            same.ddpg.exploration_noise_decay_from = 0.0;
            same.ddpg.exploration_noise_decay_to = 1.0;
        });
        // The twenty-first differs from the twentieth only in collecting's approach term, the
        // twenty-second only in collecting's credit (per target, weight 2).
        let twenty_first =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch21.toml"))
                .expect("the twenty-first config parses");
        assert_eq!(twenty_first.reward.audited.approach, 1.0);
        assert_is_with_undone(&twenty_first, &twentieth, |same| {
            same.reward.audited.approach = 0.0;
        });
        let twenty_second =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch22.toml"))
                .expect("the twenty-second config parses");
        assert!(twenty_second.reward.audited.credit_per_target);
        assert!(
            !twenty_second
                .reward
                .audited_driving
                .as_ref()
                .is_some_and(|d| d.credit_per_target)
        );
        assert_is_with_undone(&twenty_second, &twentieth, |same| {
            same.reward.audited.credit_per_target = false;
            same.reward.audited.credit = 5.0;
        });
        // The twenty-third differs from the twentieth only in collecting's excursions, the
        // twenty-fourth only in the twin critics' target, the twenty-fifth (below) only in
        // the target smoothing's width.
        let twenty_third =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch23.toml"))
                .expect("the twenty-third config parses");
        assert_eq!(twenty_third.training.excursion_rate, 0.01);
        assert_eq!(
            twenty_third.training.excursion_tasks,
            vec![Task::Collecting]
        );
        assert_is_with_undone(&twenty_third, &twentieth, |same| {
            same.training.excursion_rate = 0.0;
            same.training.excursion_radius_m = [5.0, 25.0];
            same.training.excursion_max_steps = 40;
            same.training.excursion_tasks.clear();
        });
        let twenty_fourth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch24.toml"))
                .expect("the twenty-fourth config parses");
        assert_eq!(twenty_fourth.ddpg.twin_min_weight, 0.5);
        assert_is_with_undone(&twenty_fourth, &twentieth, |same| {
            same.ddpg.twin_min_weight = 1.0;
        });
        let twenty_fifth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch25.toml"))
                .expect("the twenty-fifth config parses");
        assert_eq!(twenty_fifth.ddpg.target_noise, 0.05);
        assert_is_with_undone(&twenty_fifth, &twentieth, |same| {
            same.ddpg.target_noise = 0.2;
            same.ddpg.target_noise_clip = 0.5;
        });
        // The twenty-sixth differs from the twentieth only in the layers' width.
        let twenty_sixth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch26.toml"))
                .expect("the twenty-sixth config parses");
        assert_eq!(twenty_sixth.network.hidden, 192);
        assert_is_with_undone(&twenty_sixth, &twentieth, |same| {
            same.network.hidden = 128;
        });
        // The twenty-seventh differs from the twenty-sixth only in the training-time check's size.
        let twenty_seventh =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch27.toml"))
                .expect("the twenty-seventh config parses");
        assert_eq!(twenty_seventh.eval.episodes, 24);
        assert_is_with_undone(&twenty_seventh, &twenty_sixth, |same| {
            same.eval.episodes = 8;
        });
        // The twenty-eighth differs from the twenty-seventh only in the shape of its layers.
        let twenty_eighth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch28.toml"))
                .expect("the twenty-eighth config parses");
        assert_eq!(
            (
                twenty_eighth.network.hidden,
                twenty_eighth.network.shared_layers
            ),
            (128, 2)
        );
        assert_is_with_undone(&twenty_eighth, &twenty_seventh, |same| {
            same.network.hidden = 192;
            same.network.shared_layers = 1;
        });
        // The twenty-ninth differs from the twenty-seventh only in its centralised critic.
        let twenty_ninth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch29.toml"))
                .expect("the twenty-ninth config parses");
        assert_eq!(
            (
                twenty_ninth.ddpg.centralised_critic,
                twenty_ninth.ddpg.critic_max_others
            ),
            (true, 7)
        );
        assert_is_with_undone(&twenty_ninth, &twenty_seventh, |same| {
            same.ddpg.centralised_critic = false;
        });
        // The thirtieth differs from the twenty-seventh only in its leave penalty.
        let thirtieth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch30.toml"))
                .expect("the thirtieth config parses");
        let driving_penalty = |c: &TrainConfig| {
            c.reward
                .audited_driving
                .as_ref()
                .map(|d| d.leave_penalty_horizons)
        };
        assert_eq!(
            (
                thirtieth.reward.audited.leave_penalty_horizons,
                driving_penalty(&thirtieth)
            ),
            (1.25, Some(1.25))
        );
        assert_is_with_undone(&thirtieth, &twenty_seventh, |same| {
            same.reward.audited.leave_penalty_horizons = 2.0;
            if let Some(d) = same.reward.audited_driving.as_mut() {
                d.leave_penalty_horizons = 2.0;
            }
        });
        // The thirty-first differs from the thirtieth only in how often each flock size is drawn.
        let thirty_first =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch31.toml"))
                .expect("the thirty-first config parses");
        let sizes = |c: &TrainConfig| {
            c.curriculum
                .stages
                .iter()
                .map(|s| s.targets.clone())
                .collect::<Vec<_>>()
        };
        assert_eq!(sizes(&thirty_first), vec![vec![4, 4, 8, 8, 16]]);
        assert_eq!(sizes(&thirtieth), vec![vec![4, 8, 16]]);
        assert_is_with_undone(&thirty_first, &thirtieth, |same| {
            same.curriculum.stages[0].targets = vec![4, 8, 16];
        });
        // The thirty-second differs from the thirty-first only in how the kept checkpoint is chosen.
        let thirty_second =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch32.toml"))
                .expect("the thirty-second config parses");
        let e = &thirty_second.eval;
        assert_eq!(
            (e.finalists, e.final_episodes, e.final_seed_base),
            (5, 64, 6_000_000_000)
        );
        assert_eq!(thirty_first.eval.finalists, 0);
        assert_is_with_undone(&thirty_second, &thirty_first, |same| {
            same.eval.finalists = 0;
            same.eval.final_episodes = EvalConfig::default().final_episodes;
            same.eval.final_seed_base = EvalConfig::default().final_seed_base;
        });
        // The thirty-third differs from the thirty-second only in having no collecting curriculum.
        let thirty_third =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch33.toml"))
                .expect("the thirty-third config parses");
        assert_eq!(
            thirty_third.curriculum.collecting_target_distance,
            SpawnShareCurriculum::default()
        );
        assert_eq!(
            thirty_second
                .curriculum
                .collecting_target_distance
                .first_share,
            0.2
        );
        assert_is_with_undone(&thirty_third, &thirty_second, |same| {
            same.curriculum.collecting_target_distance = SpawnShareCurriculum {
                first_share: 0.2,
                full_at_progress: 0.3,
            };
        });
        // The thirty-fourth differs from the thirty-second only in holding each action three steps.
        let thirty_fourth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch34.toml"))
                .expect("the thirty-fourth config parses");
        assert_eq!(thirty_fourth.training.action_repeat, 3);
        assert_eq!(thirty_second.training.action_repeat, 1);
        assert_is_with_undone(&thirty_fourth, &thirty_second, |same| {
            same.training.action_repeat = 1;
        });
        // The thirty-fifth differs from the thirty-third only in self-imitation.
        let thirty_fifth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch35.toml"))
                .expect("the thirty-fifth config parses");
        assert_eq!(thirty_fifth.ddpg.self_imitation, 1.0);
        assert_eq!(thirty_third.ddpg.self_imitation, 0.0);
        assert_is_with_undone(&thirty_fifth, &thirty_third, |same| {
            same.ddpg.self_imitation = 0.0;
        });
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch35.toml"),
            &[(
                "self_imitation = 1.0",
                "self_imitation = -1.0",
                "ddpg.self_imitation",
            )],
        );
        // The thirty-sixth: the thirty-third with self-imitation on the faster episodes.
        let thirty_sixth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch36.toml"))
                .expect("the thirty-sixth config parses");
        assert_eq!(
            thirty_sixth.ddpg.self_imitation_episodes,
            crate::ddpg::SelfImitationEpisodes::FasterThanMedian
        );
        assert_is_with_undone(&thirty_sixth, &thirty_third, |same| {
            same.ddpg.self_imitation = 0.0;
            same.ddpg.self_imitation_episodes = crate::ddpg::SelfImitationEpisodes::Ended;
        });
        assert!(
            TrainConfig::from_toml_str(&include_str!("../configs/mtddpg-scratch36.toml").replace(
                "self_imitation_episodes = \"faster_than_median\"",
                "self_imitation_episodes = \"fastest\""
            ))
            .is_err(),
            "an unknown episode filter is refused"
        );
        // The thirty-seventh: the thirty-third with advantage-decomposed critics.
        let thirty_seventh =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch37.toml"))
                .expect("the thirty-seventh config parses");
        assert_eq!(thirty_seventh.ddpg.advantage_scale, 0.1);
        assert_eq!(thirty_third.ddpg.advantage_scale, 0.0);
        assert_eq!(thirty_seventh.training.threads, 2);
        assert_is_with_undone(&thirty_seventh, &thirty_third, |same| {
            same.ddpg.advantage_scale = 0.0;
            same.training.threads = 1;
        });
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch37.toml"),
            &[
                (
                    "advantage_scale = 0.1",
                    "advantage_scale = -0.1",
                    "ddpg.advantage_scale",
                ),
                (
                    "centralised_critic = false",
                    "centralised_critic = true",
                    "ddpg.advantage_scale",
                ),
            ],
        );
        // The thirty-ninth: the thirty-seventh with flocks of four only for the first 40 %.
        let thirty_ninth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch39.toml"))
                .expect("the thirty-ninth config parses");
        assert_eq!(thirty_ninth.stage_at(0.0).targets, vec![4]);
        assert_eq!(thirty_ninth.stage_at(0.399).targets, vec![4]);
        assert_eq!(thirty_ninth.stage_at(0.4).targets, vec![4, 4, 8, 8, 16]);
        assert_eq!(
            thirty_ninth.stage_at(0.4).herders,
            thirty_seventh.stage_at(0.0).herders
        );
        let mix = thirty_seventh.curriculum.stages.clone();
        assert_is_with_undone(&thirty_ninth, &thirty_seventh, |same| {
            same.curriculum.stages = mix;
        });
        // The forty-first: the thirty-seventh whose stage also draws (1, 1) and (2, 2).
        let forty_first =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch41.toml"))
                .expect("the forty-first config parses");
        assert_eq!(forty_first.stage_at(0.0).pairs, vec![[1, 1], [2, 2]]);
        assert_is_with_undone(&forty_first, &thirty_seventh, |same| {
            same.curriculum.stages[0].pairs.clear();
        });
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch41.toml"),
            &[(
                "pairs = [[1, 1], [2, 2]]",
                "pairs = [[0, 1], [2, 2]]",
                "curriculum.stages",
            )],
        );
        // The forty-second: the forty-first without the difference credit in collecting.
        let forty_second =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch42.toml"))
                .expect("the forty-second config parses");
        assert_eq!(forty_second.reward.audited.credit, 0.0);
        assert_eq!(
            forty_second
                .reward
                .audited_driving
                .as_ref()
                .map(|d| d.credit),
            Some(5.0),
            "driving keeps its credit"
        );
        assert_is_with_undone(&forty_second, &forty_first, |same| {
            same.reward.audited.credit = 5.0;
        });
        // The forty-third: the forty-first on encoder v5 (the assignment features).
        let forty_third =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch43.toml"))
                .expect("the forty-third config parses");
        assert_eq!(forty_third.encoder_version, 5);
        assert_eq!(forty_first.encoder_version, DEFAULT_ENCODER_VERSION);
        assert_is_with_undone(&forty_third, &forty_first, |same| {
            same.encoder_version = DEFAULT_ENCODER_VERSION;
        });
        // The forty-fourth: the forty-third whose end-of-run choice also weighs the mean of
        // its finalists from the second half of the run.
        let forty_fourth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch44.toml"))
                .expect("the forty-fourth config parses");
        assert_eq!(forty_fourth.eval.average_finalists_from, Some(0.5));
        assert_eq!(forty_third.eval.average_finalists_from, None);
        assert_is_with_undone(&forty_fourth, &forty_third, |same| {
            same.eval.average_finalists_from = None;
        });
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch44.toml"),
            &[
                (
                    "average_finalists_from = 0.5",
                    "average_finalists_from = 1.0",
                    "eval.average_finalists_from",
                ),
                (
                    "finalists = 5 ",
                    "finalists = 1 ",
                    "eval.average_finalists_from",
                ),
            ],
        );
        // The fortieth: the thirty-eighth with its perturbations kept at 0.1, no fall.
        let fortieth = TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch40.toml"))
            .expect("the fortieth config parses");
        assert_eq!(fortieth.ddpg.exploration_noise_at(0.0), 0.1);
        assert_eq!(fortieth.ddpg.exploration_noise_at(1.0), 0.1);
        // The thirty-eighth: the thirty-seventh with parameter-space noise.
        let thirty_eighth =
            TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch38.toml"))
                .expect("the thirty-eighth config parses");
        assert_eq!(
            thirty_eighth.ddpg.exploration,
            crate::ddpg::Exploration::Parameter
        );
        assert_is_with_undone(&thirty_eighth, &thirty_seventh, |same| {
            same.ddpg.exploration = crate::ddpg::Exploration::OrnsteinUhlenbeck;
        });
        assert!(
            TrainConfig::from_toml_str(&include_str!("../configs/mtddpg-scratch38.toml").replace(
                "exploration = \"parameter\"",
                "exploration = \"parameters\""
            ))
            .is_err(),
            "an unknown exploration is refused"
        );
        assert_is_with_undone(&fortieth, &thirty_eighth, |same| {
            same.ddpg.exploration_noise = 0.3;
            same.ddpg.exploration_noise_final = Some(0.1);
            same.ddpg.exploration_noise_decay_from = 0.3;
            same.ddpg.exploration_noise_decay_to = 0.8;
        });
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch34.toml"),
            &[(
                "action_repeat = 3",
                "action_repeat = 0",
                "training.action_repeat",
            )],
        );
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch32.toml"),
            &[
                (
                    "final_episodes = 64",
                    "final_episodes = 0",
                    "eval.final_episodes",
                ),
                (
                    "final_seed_base = 6_000_000_000",
                    "final_seed_base = 999_999_990",
                    "eval.final_seed_base",
                ),
            ],
        );
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch24.toml"),
            &[(
                "twin_min_weight = 0.5",
                "twin_min_weight = 1.5",
                "ddpg.twin_min_weight",
            )],
        );
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch20.toml"),
            &[
                (
                    "exploration_noise_decay_to = 0.8",
                    "exploration_noise_decay_to = 0.2",
                    "ddpg.exploration_noise_decay_from",
                ),
                (
                    "exploration_noise_decay_to = 0.8",
                    "exploration_noise_decay_to = 1.5",
                    "ddpg.exploration_noise_decay_from",
                ),
                (
                    "exploration_noise_final = 0.1",
                    "exploration_noise_final = -0.1",
                    "ddpg.exploration_noise_final",
                ),
            ],
        );
        let share = "training.passed_task_env_share";
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch19.toml"),
            &[
                (
                    "passed_task_env_share = 0.25",
                    "passed_task_env_share = 0.0",
                    share,
                ),
                (
                    "passed_task_env_share = 0.25",
                    "passed_task_env_share = 1.5",
                    share,
                ),
                ("envs = 8", "envs = 3", share),
            ],
        );
        assert_each_edit_is_refused(
            include_str!("../configs/mtddpg-scratch14.toml"),
            &[
                (
                    "passed_task_update_share = 0.25",
                    "passed_task_update_share = 0.0",
                    "training.passed_task_update_share",
                ),
                (
                    "passed_task_bar = 0.95",
                    "passed_task_bar = 1.5",
                    "training.passed_task_bar",
                ),
                (
                    "every_task_env_steps = 25_000",
                    "every_task_env_steps = 0",
                    "eval.every_task_env_steps",
                ),
            ],
        );
        let text = include_str!("../configs/mtddpg-scratch12.toml");
        assert_each_edit_is_refused(
            text,
            &[
                (
                    "task_reset_rule = \"recent\"",
                    "task_reset_rule = \"latest\"",
                    "task_reset_rule",
                ),
                (
                    "first_share = 0.2             # scattered",
                    "first_share = -0.2             # scattered",
                    "curriculum.collecting_target_distance.first_share",
                ),
                (
                    "full_at_progress = 0.3        # ... rising to 100 % at 30 % of the run\n\n[warm_start]",
                    "full_at_progress = 1.3\n\n[warm_start]",
                    "curriculum.collecting_target_distance.full_at_progress",
                ),
            ],
        );
    }

    #[test]
    fn stalled_task_resets_read_from_the_tenth_config_and_reject_bad_values() {
        let text = include_str!("../configs/mtddpg-scratch10.toml");
        let file = TrainConfig::from_toml_str(text).expect("the tenth config parses");
        let t = &file.training;
        assert_eq!(t.task_reset_after_task_env_steps, 75_000);
        assert_eq!(t.task_reset_below, 0.25);
        assert_eq!(t.task_resets_max, 3);
        assert!(!t.task_reset_clears_replay);
        let eleventh = TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch11.toml"))
            .expect("the eleventh config parses");
        assert!(eleventh.training.task_reset_clears_replay);
        assert_eq!(eleventh.training.task_reset_warmup_steps, 20_000);
        // Everything else is the eighth config's.
        let eighth = TrainConfig::from_toml_str(include_str!("../configs/mtddpg-scratch8.toml"))
            .expect("the eighth config parses");
        assert_is_with_undone(&file, &eighth, |same| {
            same.training.task_reset_after_task_env_steps = 0;
            same.training.task_reset_below = eighth.training.task_reset_below;
            same.training.task_resets_max = eighth.training.task_resets_max;
            same.training.task_reset_clears_replay = false;
            same.training.task_reset_warmup_steps = 0;
        });
        assert_each_edit_is_refused(
            text,
            &[
                (
                    "task_reset_below = 0.25 ",
                    "task_reset_below = 0.0 ",
                    "training.task_reset_below",
                ),
                (
                    "task_reset_below = 0.25 ",
                    "task_reset_below = 1.5 ",
                    "training.task_reset_below",
                ),
                (
                    "task_resets_max = 3",
                    "task_resets_max = 0",
                    "training.task_resets_max",
                ),
                (
                    "task_reset_after_task_env_steps = 75_000 ",
                    "task_reset_after_task_env_steps = 10_000 ",
                    "training.task_reset_after_task_env_steps",
                ),
                (
                    "every_task_env_steps = 25_000 ",
                    "every_task_env_steps = 0 ",
                    "training.task_reset_after_task_env_steps",
                ),
            ],
        );
    }

    #[test]
    fn the_herder_distance_curriculum_reads_from_the_eighth_config_and_rejects_bad_values() {
        let text = include_str!("../configs/mtddpg-scratch8.toml");
        let file = TrainConfig::from_toml_str(text).expect("the eighth config parses");
        let h = file.curriculum.driving_herder_distance;
        assert_eq!(h.first_share, 0.0);
        assert_eq!(h.full_at_progress, 0.3);
        assert_eq!(h.floor_at(0.15), 0.5);
        assert_eq!(h.floor_at(0.3), 1.0);
        assert_eq!(
            file.curriculum
                .driving_goal_distance
                .min_centre_distance_radii,
            2.5
        );
        for (from, to) in [
            ("first_share = 0.0 ", "first_share = -0.5 "),
            ("first_share = 0.0 ", "first_share = 1.5 "),
        ] {
            let e = TrainConfig::from_toml_str(&text.replace(from, to))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("curriculum.driving_herder_distance.first_share"),
                "{e}"
            );
        }
        let section = text
            .find("[curriculum.driving_herder_distance]")
            .expect("the section");
        let (before, after) = text.split_at(section);
        let late = after.replacen("full_at_progress = 0.3", "full_at_progress = 2.0", 1);
        let e = TrainConfig::from_toml_str(&format!("{before}{late}"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("curriculum.driving_herder_distance.full_at_progress"),
            "{e}"
        );
        let e = TrainConfig::from_toml_str(&text.replace(
            "[curriculum.driving_herder_distance]\n",
            "[curriculum.driving_herder_distance]\nspawn_share = 0.5\n",
        ))
        .unwrap_err()
        .to_string();
        assert!(e.contains("spawn_share"), "{e}");
    }

    #[test]
    fn teachers_are_picked_by_task_and_flock() {
        let rule = |task, herders_at_least, targets_at_most| TeacherRule {
            task,
            herders_at_least,
            targets_at_most,
            baseline: Method::Strombom,
        };
        let w = WarmStartConfig {
            teachers: vec![rule(Task::Driving, 2, 64), rule(Task::Collecting, 8, 64)],
            ..WarmStartConfig::default()
        };
        assert_eq!(
            WarmStartConfig::default().teacher(Task::Driving, 16, 4),
            Method::Lama
        );
        assert_eq!(w.teacher(Task::Driving, 16, 4), Method::Strombom);
        assert_eq!(w.teacher(Task::Driving, 4, 2), Method::Strombom);
        assert_eq!(w.teacher(Task::Driving, 16, 1), Method::Lama, "alone");
        assert_eq!(
            w.teacher(Task::Driving, 128, 8),
            Method::Lama,
            "large flock"
        );
        assert_eq!(w.teacher(Task::Collecting, 16, 4), Method::Lama);
        assert_eq!(w.teacher(Task::Collecting, 64, 8), Method::Strombom);
        let err = TrainConfig::from_toml_str(
            "[warm_start]\nteachers = [{ task = \"herding\", baseline = \"lama\" }]",
        )
        .unwrap_err();
        assert!(err.to_string().contains("teachers"), "{err}");
    }

    #[test]
    fn round_trips_through_toml() {
        let config = TrainConfig::default();
        let back = TrainConfig::from_toml_str(&config.to_toml()).expect("own output parses");
        assert_eq!(back, config);
    }

    #[test]
    fn rejects_out_of_range_values() {
        let err = TrainConfig::from_toml_str("[ddpg]\ngamma = 1.5").unwrap_err();
        assert!(err.to_string().contains("ddpg.gamma"), "{err}");
        let err =
            TrainConfig::from_toml_str("[warm_start]\ndriving_baseline = \"nope\"").unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("driving_baseline") && text.contains("`nope`"),
            "{err}"
        );
        let err = TrainConfig::from_toml_str("[evolution]\nsigma = 0.0").unwrap_err();
        assert!(err.to_string().contains("evolution.sigma"), "{err}");
        let err = TrainConfig::from_toml_str(
            "[evolution]\nscenarios = [{ task = \"driving\", targets = 4, herders = 2, episodes = 0 }]",
        )
        .unwrap_err();
        assert!(err.to_string().contains("evolution.scenarios"), "{err}");
    }

    #[test]
    fn evolution_scenarios_name_their_dynamics_and_the_indoor_preset() {
        let room = "[evolution]\nscenarios = [{ task = \"driving\", targets = 4, herders = 2, indoor = true, dynamics = \"indoor\", wind = \"room\", episodes = 2 }]";
        let c = TrainConfig::from_toml_str(room).expect("a room scenario with dynamics");
        let s = &c.evolution.scenarios[0];
        let d = s.herder_dynamics().unwrap().expect("dynamics on");
        assert_eq!(d.limits.max_speed_horizontal, 1.0);
        let flown = crate::evolve::scenario_of(s, 300);
        assert_eq!(
            (flown.area.width, flown.dt, flown.step_limit),
            (10.0, 0.1, 300)
        );
        assert_eq!(flown.dynamics, Some(d));
        // Unknown names, wind without dynamics, and both layouts at once are refused by name.
        for (bad, says) in [
            ("dynamics = \"jet\"", "the motion models are"),
            ("dynamics = \"px4\", wind = \"gale\"", "gale"),
            ("wind = \"room\"", "`wind` needs `dynamics`"),
            ("room = true, indoor = true", "exclude each other"),
            ("command_delay_s = 0.1", "needs `dynamics`"),
            ("dynamics = \"px4\", command_delay_s = -1.0", "0 s or more"),
        ] {
            let text = format!(
                "[evolution]\nscenarios = [{{ task = \"driving\", targets = 4, herders = 2, episodes = 2, {bad} }}]"
            );
            let err = TrainConfig::from_toml_str(&text).unwrap_err().to_string();
            assert!(
                err.contains("evolution.scenarios") && err.contains(says),
                "{bad}: {err}"
            );
        }
    }

    #[test]
    fn curriculum_moves_through_stages_and_can_be_switched_off() {
        let mut c = TrainConfig::default();
        assert_eq!(c.stage_at(0.0).targets, vec![2, 4, 8, 16]);
        assert_eq!(c.stage_at(0.45).targets, vec![4, 8, 16, 32, 64]);
        assert!(c.stage_at(0.99).targets.contains(&256));
        c.curriculum.enabled = false;
        assert!(c.stage_at(0.0).targets.contains(&256));
    }
}
