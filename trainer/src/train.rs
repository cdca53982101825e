//! The training run, top to bottom:
//!
//! 1. **Warm start** (switchable): roll out the rule-based baselines over every curriculum
//!    stage, record each herder's `(features, action)` (the rule's velocity in the local frame,
//!    normalised by the speed limit) and its transitions; regress the actor onto the rule's
//!    actions (behaviour cloning); evaluate the cloned actor with critic-only TD updates on
//!    those transitions so the critic starts out knowing the rule's values.
//! 2. **MTDDPG** fine-tuning: environments of both tasks stepped together with Gaussian
//!    exploration, per-task replay, one minibatch per task per update, N and M drawn from the
//!    curriculum stage in force.
//! 3. **Evaluation** on held-out seeds every `eval.every_updates` updates (and after the warm
//!    start); the best actor by success rate, then time, is kept in `best.safetensors`.
//!    With `eval.finalists`, the few best are kept and, at the end, the one that scores best
//!    on a second episode set replaces it ([`crate::finalists`]).
//! 4. **Evolution** (switchable, [`crate::evolve`]): evolution strategies on each task's own
//!    layers of the best actor, scored by completion time over the lower bound; the result is
//!    `evolved.safetensors` (the best checkpoint with the evolved actor), which is what gets
//!    exported. A resumed run that finished MTDDPG runs this stage again from `best.safetensors`.
//!
//! Output in `output_dir`: `last.safetensors` (every `checkpoint_every_s` seconds and at the
//! end, for `--resume`), `best.safetensors`, `evolved.safetensors`, `log.csv`, `curve.png`,
//! `eval.csv`; with finalists also `finalist-<env steps>.safetensors`, `finalists.csv` and
//! `finalists-eval.csv`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use skyherd_model::Task;
use skyherd_onboard::obs::{FEATURES, feature_count};
use skyherd_sim::EnvError;
use skyherd_sim::task::task_name;
use thiserror::Error;

use crate::checkpoint::{self, Checkpoint, CheckpointError, Progress};
use crate::config::{TaskResetRule, TrainConfig};
use crate::ddpg::{ACTION_DIM, Agent};
use crate::eval::{EvalRow, EvalScenario, better, evaluate_flat, score, task_success};
use crate::evolve::{Fitness, evolve_task};
use crate::finalists::{self, Finalist};
use crate::nn::{Adam, AdamConfig};
use crate::policy::ActorPolicy;
use crate::replay::{Batch, ReplayBuffer};
use crate::report::{CsvLog, LogRow, ReportError, plot_curve, read_log};
use crate::rollout::{Controller, EpisodeStats, Rollouts, draw_from_all_stages, draw_from_stage};

/// Why training stopped early.
#[derive(Debug, Error)]
pub enum TrainError {
    /// The simulator refused a step or a scenario.
    #[error("simulator: {0}")]
    Env(#[from] EnvError),
    /// A checkpoint could not be written or read.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// The log or plot could not be written.
    #[error(transparent)]
    Report(#[from] ReportError),
    /// The thread pool could not be built.
    #[error("thread pool: {0}")]
    Threads(String),
    /// An actor file the evolution stage was to start from does not fit the config.
    #[error("actor {path} does not fit the config: {reason}")]
    ActorShape {
        /// The actor file.
        path: String,
        /// What differs.
        reason: String,
    },
    /// The fine-tune's actor does not fit the config.
    #[error("fine_tune.actor {path}: {reason}")]
    FineTuneActor {
        /// The actor file.
        path: String,
        /// What does not fit.
        reason: String,
    },
}

/// What the caller hears about while training runs (a progress bar, a quiet test).
pub trait Observer {
    /// A phase started; `total` units of work are expected.
    fn phase(&mut self, name: &str, total: u64);
    /// `done` units of the current phase are finished; `message` says how it goes.
    fn progress(&mut self, done: u64, message: &str);
    /// A free-form line.
    fn note(&mut self, line: &str);
}

/// An observer that ignores everything.
pub struct Quiet;

impl Observer for Quiet {
    fn phase(&mut self, _: &str, _: u64) {}
    fn progress(&mut self, _: u64, _: &str) {}
    fn note(&mut self, _: &str) {}
}

/// How a run ended.
#[derive(Clone, Debug)]
pub struct TrainOutcome {
    /// Counters at the end.
    pub progress: Progress,
    /// Where the best checkpoint is.
    pub best_checkpoint: PathBuf,
    /// Where the last checkpoint is.
    pub last_checkpoint: PathBuf,
    /// The last evaluation.
    pub last_eval: Vec<EvalRow>,
    /// Mean seconds per DDPG update (NaN when none ran).
    pub seconds_per_update: f64,
    /// The evolution stage, when enabled.
    pub evolution: Option<EvolutionOutcome>,
}

/// What the evolution stage did.
#[derive(Clone, Debug)]
pub struct EvolutionOutcome {
    /// Where the evolved checkpoint is.
    pub checkpoint: PathBuf,
    /// Per task tuned: its held-out check before and after.
    pub tasks: Vec<(Task, Fitness, Fitness)>,
    /// The evolved actor on the run's held-out evaluation (`eval.scenarios`).
    pub eval: Vec<EvalRow>,
    /// Wall-clock seconds the stage took.
    pub wall_s: f64,
}

/// A checkpoint holding the actor file at `path` and a fresh critic of `config`'s shape, at
/// step 0: what the evolution stage needs to start from a shipped actor. The actor must have the
/// config's inputs, tasks, outputs and hidden layers.
pub fn checkpoint_of_actor(config: &TrainConfig, path: &Path) -> Result<Checkpoint, TrainError> {
    let actor = checkpoint::load_actor(path)?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let mut agent = Agent::new(
        feature_count(config.encoder_version).unwrap_or(FEATURES),
        Task::COUNT,
        config.network,
        config.ddpg,
        &mut rng,
    );
    let shape = |a: &crate::network::MultiTaskMlp| {
        (
            a.inputs(),
            a.tasks(),
            a.outputs(),
            a.shared.len(),
            a.shared.first().map(|l| l.weights.len()),
        )
    };
    if shape(&actor) != shape(&agent.actor) {
        return Err(TrainError::ActorShape {
            path: path.display().to_string(),
            reason: format!(
                "{} inputs, {} tasks, {} outputs, {} shared layers; the config's actor has {}, {}, {}, {} (encoder_version and [network] must match the actor)",
                actor.inputs(),
                actor.tasks(),
                actor.outputs(),
                actor.shared.len(),
                agent.actor.inputs(),
                agent.actor.tasks(),
                agent.actor.outputs(),
                agent.actor.shared.len(),
            ),
        });
    }
    agent.target_actor = actor.clone();
    agent.actor = actor;
    Ok(Checkpoint {
        agent,
        progress: Progress::default(),
        config: config.clone(),
    })
}

/// Runs the evolution stage (`config.evolution`) on `source`'s actor, each task with
/// scenarios in turn, logging to `output_dir/log.csv` (phase 3) and writing
/// `output_dir/evolved.safetensors`: `source` with the evolved actor and the stage's wall time
/// added. Runs on the current rayon pool.
pub fn evolve_checkpoint(
    config: &TrainConfig,
    source: &Checkpoint,
    observer: &mut dyn Observer,
) -> Result<EvolutionOutcome, TrainError> {
    let started = Instant::now();
    let dir = config.output_dir.clone();
    std::fs::create_dir_all(&dir).map_err(ReportError::from)?;
    let mut log = CsvLog::open(&dir.join("log.csv"))?;
    let wall_offset = source.progress.wall_time_s;
    let ev = &config.evolution;
    let mut actor = source.agent.actor.clone();
    let mut tasks = Vec::new();
    for task in Task::ALL {
        let label = task_name(task);
        if ev.scenarios_of(task).next().is_none() {
            continue;
        }
        observer.phase(&format!("evolution: {label} heads"), ev.generations as u64);
        let mut rows = Vec::new();
        let out = evolve_task(&actor, task, ev, config.seed, |r| {
            let check = r.check.map_or(String::new(), |c| {
                format!(
                    ", check {:.3} ({:.0}% success, {:.2}x){}",
                    c.fitness,
                    100.0 * c.success_rate,
                    c.time_ratio,
                    if r.kept { " kept" } else { "" }
                )
            });
            observer.progress(
                r.generation as u64 + 1,
                &format!("population {:.3}{check}", r.population_fitness),
            );
            rows.push(LogRow {
                phase: 3,
                wall_s: wall_offset + started.elapsed().as_secs_f64(),
                env_steps: source.progress.env_steps,
                updates: r.generation as u64 + 1,
                episodes: source.progress.episodes,
                recent_return: r.population_fitness,
                recent_success: f64::NAN,
                critic_loss: f64::NAN,
                actor_loss: f64::NAN,
                q_mean: f64::NAN,
                eval_success: r.check.map_or(f64::NAN, |c| c.success_rate),
                eval_time_ratio: r.check.map_or(f64::NAN, |c| c.time_ratio),
            });
        })?;
        for row in &rows {
            log.write(row)?;
        }
        observer.note(&format!(
            "evolution, {label}: held-out check {:.3} -> {:.3} (success {:.0}% -> {:.0}%, time {:.2}x -> {:.2}x)",
            out.start_check.fitness,
            out.best_check.fitness,
            100.0 * out.start_check.success_rate,
            100.0 * out.best_check.success_rate,
            out.start_check.time_ratio,
            out.best_check.time_ratio,
        ));
        tasks.push((task, out.start_check, out.best_check));
        actor = out.actor;
    }
    let scenarios = config.eval.scenario_list();
    let e = &config.eval;
    let eval = evaluate_flat(&scenarios, e.episodes, e.seed_base, || {
        ActorPolicy::new(&actor)
    })?;
    let s = score(&eval);
    observer.note(&format!(
        "evolved actor on the held-out evaluation: success {:.1}%, time {:.2}x lower bound",
        100.0 * s.0,
        s.1
    ));
    let wall_s = started.elapsed().as_secs_f64();
    let mut evolved = source.clone();
    evolved.agent.actor = actor;
    evolved.progress.wall_time_s = wall_offset + wall_s;
    let path = dir.join("evolved.safetensors");
    checkpoint::save(&path, &evolved)?;
    log.write(&LogRow::evaluation(
        evolved.progress.wall_time_s,
        source.progress.env_steps,
        source.agent.updates,
        source.progress.episodes,
        s,
    ))?;
    Ok(EvolutionOutcome {
        checkpoint: path,
        tasks,
        eval,
        wall_s,
    })
}

/// Appends one evaluation's rows to `eval.csv` (written with its header when new): the learning
/// curves per scenario that `skyherd-trainer ablation-report` reads. Rows already there from
/// `env_steps` on are dropped first: a resumed run goes back to its last checkpoint and
/// evaluates those steps again, and its new rows supersede the old ones (one row per
/// scenario and step, as the report expects).
fn append_eval_rows(
    path: &Path,
    env_steps: u64,
    task_env_steps: &[u64; Task::COUNT],
    rows: &[EvalRow],
) -> Result<(), TrainError> {
    let old = read_if_there(path)?;
    let mut text = String::with_capacity(old.len() + 128 * rows.len());
    text.push_str(EVAL_CSV_HEADER);
    text.push('\n');
    for line in old.lines().skip(1) {
        // A row from before `env_steps` stays; one from then on (or unreadable) goes.
        let step = line.split(',').next().and_then(|v| v.parse::<u64>().ok());
        if step.is_some_and(|s| s < env_steps) {
            text.push_str(line);
            text.push('\n');
        }
    }
    for r in rows {
        text.push_str(&format!(
            "{env_steps},{},{},{},{},{},{},{},{}\n",
            task_env_steps[r.scenario.task.index()],
            task_name(r.scenario.task),
            r.scenario.targets,
            r.scenario.herders,
            r.episodes,
            r.success_rate,
            r.mean_time_s,
            r.mean_time_ratio
        ));
    }
    // A crash mid-write leaves the old curve whole.
    write_atomically(path, &text)
}

/// Each finalist's rows on the second episode set, as `eval.csv`'s columns.
pub const FINALISTS_EVAL_FILE: &str = "finalists-eval.csv";

/// The finalists' mean's rows on the second episode set (`eval.average_finalists_from`), as
/// `eval.csv`'s columns, under its latest member's env steps.
pub const FINALISTS_MEAN_EVAL_FILE: &str = "finalists-mean-eval.csv";

/// What the end-of-run choice kept as `best.safetensors`.
#[derive(Clone, Debug, PartialEq)]
pub struct KeptFinalist {
    /// The finalist's env steps; for the finalists' mean, its members'.
    pub env_steps: Vec<u64>,
    /// The training-time check's score; `None` for the mean, which the check never herded.
    pub check: Option<(f64, f64)>,
    /// The score on the second episode set.
    pub final_score: (f64, f64),
}

/// The end-of-run choice of the run in `dir`: herds every finalist (and, with
/// `eval.average_finalists_from`, the mean of the late ones' actors) on the second episode set
/// and copies the best by that set to `best.safetensors`. The scores go to `finalists.csv`,
/// each finalist's rows to `finalists-eval.csv` and the mean's to `finalists-mean-eval.csv`.
/// `None` when there are no finalists. Also what `skyherd-trainer choose` runs on a finished
/// run.
pub fn choose_finalist(
    config: &TrainConfig,
    dir: &Path,
    finalists: &[Finalist],
    scenarios: &[EvalScenario],
    observer: &mut dyn Observer,
) -> Result<Option<KeptFinalist>, TrainError> {
    if finalists.is_empty() {
        return Ok(None);
    }
    let e = &config.eval;
    let herd = |actor: &crate::network::MultiTaskMlp| {
        evaluate_flat(scenarios, e.final_episodes, e.final_seed_base, || {
            ActorPolicy::new(actor)
        })
    };
    let mut scores = Vec::with_capacity(finalists.len() + 1);
    let mut rows_of = Vec::with_capacity(finalists.len());
    for f in finalists {
        let c = checkpoint::load(&finalists::file(dir, f.env_steps))?;
        let rows = herd(&c.agent.actor)?;
        let s = score(&rows);
        observer.note(&format!(
            "finalist at {} env steps: check {:.1}% at {:.2}x, final set {:.1}% at {:.2}x",
            f.env_steps,
            100.0 * f.check.0,
            f.check.1,
            100.0 * s.0,
            s.1
        ));
        scores.push(s);
        rows_of.push((f.env_steps, c.progress.task_env_steps, rows));
    }
    let members = e.average_finalists_from.map_or_else(Vec::new, |from| {
        finalists::mean_members(finalists, config.training.env_steps, from)
    });
    let mean_path = dir.join(finalists::MEAN_FILE);
    let mean_eval_path = dir.join(FINALISTS_MEAN_EVAL_FILE);
    remove_if_there(&mean_path)?;
    remove_if_there(&mean_eval_path)?;
    let mut mean_score = None;
    if let Some(&latest) = members.last() {
        let mut actors = Vec::with_capacity(members.len());
        for &m in &members {
            actors.push(checkpoint::load(&finalists::file(dir, m))?.agent.actor);
        }
        let refs: Vec<_> = actors.iter().collect();
        let mean =
            crate::network::MultiTaskMlp::mean_of(&refs).ok_or_else(|| TrainError::ActorShape {
                path: finalists::file(dir, latest).display().to_string(),
                reason: "the finalists' actors differ in shape, so they cannot be averaged"
                    .to_owned(),
            })?;
        let mut c = checkpoint::load(&finalists::file(dir, latest))?;
        c.agent.actor = mean;
        checkpoint::save(&mean_path, &c)?;
        let rows = herd(&c.agent.actor)?;
        let s = score(&rows);
        observer.note(&format!(
            "mean of the finalists at {members:?} env steps: final set {:.1}% at {:.2}x",
            100.0 * s.0,
            s.1
        ));
        append_eval_rows(&mean_eval_path, latest, &c.progress.task_env_steps, &rows)?;
        scores.push(s);
        mean_score = Some(s);
    }
    let Some(chosen) = finalists::choose(&scores) else {
        return Ok(None);
    };
    let kept = if let Some(f) = finalists.get(chosen) {
        std::fs::copy(
            finalists::file(dir, f.env_steps),
            dir.join("best.safetensors"),
        )
        .map_err(ReportError::from)?;
        KeptFinalist {
            env_steps: vec![f.env_steps],
            check: Some(f.check),
            final_score: scores[chosen],
        }
    } else {
        std::fs::copy(&mean_path, dir.join("best.safetensors")).map_err(ReportError::from)?;
        KeptFinalist {
            env_steps: members.clone(),
            check: None,
            final_score: scores[chosen],
        }
    };
    observer.note(&format!(
        "finalists: {} kept as best.safetensors ({:.1}% at {:.2}x on {} episodes a scenario it was not chosen on)",
        if kept.check.is_some() {
            format!("the one at {} env steps is", kept.env_steps[0])
        } else {
            format!("the mean of those at {:?} env steps is", kept.env_steps)
        },
        100.0 * kept.final_score.0,
        kept.final_score.1,
        e.final_episodes
    ));
    let mut csv = finalists::to_csv(finalists, Some((&scores[..finalists.len()], chosen)));
    if let Some(s) = mean_score {
        csv.push_str(&finalists::mean_csv_line(
            &members,
            s,
            chosen == finalists.len(),
        ));
    }
    write_atomically(&dir.join(finalists::CSV_FILE), &csv)?;
    let eval_path = dir.join(FINALISTS_EVAL_FILE);
    remove_if_there(&eval_path)?;
    // In step order, so that each append keeps the rows before it.
    rows_of.sort_by_key(|r| r.0);
    for (env_steps, task_env_steps, rows) in &rows_of {
        append_eval_rows(&eval_path, *env_steps, task_env_steps, rows)?;
    }
    Ok(Some(kept))
}

/// Removes the file at `path`; one already gone is fine.
fn remove_if_there(path: &Path) -> Result<(), TrainError> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(ReportError::from(e).into()),
    }
}

/// The text of the file at `path`; empty when there is none yet.
fn read_if_there(path: &Path) -> Result<String, TrainError> {
    match std::fs::read_to_string(path) {
        Ok(text) => Ok(text),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(String::new()),
        Err(e) => Err(ReportError::from(e).into()),
    }
}

/// Writes `text` beside `path` and renames it over, so a crash mid-write leaves the old file whole.
fn write_atomically(path: &Path, text: &str) -> Result<(), TrainError> {
    let partial = path.with_extension("partial");
    std::fs::write(&partial, text.as_bytes()).map_err(ReportError::from)?;
    std::fs::rename(&partial, path).map_err(ReportError::from)?;
    Ok(())
}

/// The columns of `eval.csv`.
pub const EVAL_CSV_HEADER: &str = "env_steps,task_env_steps,task,targets,herders,episodes,success_rate,mean_time_s,mean_time_ratio";

/// Running means over the most recent training episodes.
struct Recent {
    window: Vec<EpisodeStats>,
}

impl Recent {
    fn push(&mut self, e: &[EpisodeStats]) {
        self.window.extend_from_slice(e);
        let excess = self.window.len().saturating_sub(100);
        self.window.drain(..excess);
    }
    fn means(&self) -> (f64, f64) {
        if self.window.is_empty() {
            return (f64::NAN, f64::NAN);
        }
        let n = self.window.len() as f64;
        (
            self.window.iter().map(|e| e.learner_return).sum::<f64>() / n,
            self.window.iter().filter(|e| e.success).count() as f64 / n,
        )
    }
}

fn sample_per_task(
    buffers: &[ReplayBuffer],
    batch_size: usize,
    rng: &mut ChaCha8Rng,
    out: &mut [Batch],
) {
    let per_task = (batch_size / buffers.len()).max(1);
    for (b, buf) in out.iter_mut().zip(buffers) {
        buf.sample(per_task, rng, b);
    }
}

/// Each task's share of the updates under `training.passed_task_update_share`: 1 for every
/// task, except that while some trained task's latest evaluation (`latest`, mean success per
/// `Task::index`) is below `passed_task_bar`, a trained task at or above it gets the share.
/// Tasks not trained get 0. Pure.
pub(crate) fn update_shares(
    t: &crate::config::LoopConfig,
    tasks: &[Task],
    latest: &[f64; Task::COUNT],
) -> [f64; Task::COUNT] {
    passed_task_shares(t.passed_task_bar, t.passed_task_update_share, tasks, latest)
}

/// Each task's weight in the parallel environments under `training.passed_task_env_share`,
/// as [`update_shares`] with that share. Pure.
pub(crate) fn env_shares(
    t: &crate::config::LoopConfig,
    tasks: &[Task],
    latest: &[f64; Task::COUNT],
) -> [f64; Task::COUNT] {
    passed_task_shares(t.passed_task_bar, t.passed_task_env_share, tasks, latest)
}

fn passed_task_shares(
    bar: f64,
    share: f64,
    tasks: &[Task],
    latest: &[f64; Task::COUNT],
) -> [f64; Task::COUNT] {
    let passed = |task: &Task| latest[task.index()] >= bar;
    let focus = tasks.iter().any(passed) && !tasks.iter().all(passed);
    let mut shares = [0.0; Task::COUNT];
    for task in tasks {
        shares[task.index()] = if focus && passed(task) { share } else { 1.0 };
    }
    shares
}

/// How many of `envs` parallel environments run each task under `weights` (see
/// [`env_shares`]): proportional to the weights, rounded to the nearest, at least one per
/// trained task, `envs` in all (the largest rounding errors give way first, ties to the lower
/// `Task::index`). Tasks with weight 0 get none. Pure.
pub(crate) fn env_slots(envs: usize, weights: &[f64; Task::COUNT]) -> [usize; Task::COUNT] {
    let mut slots = [0usize; Task::COUNT];
    let total: f64 = weights.iter().filter(|w| **w > 0.0).sum();
    let trained = weights.iter().filter(|w| **w > 0.0).count();
    if total <= 0.0 || envs < trained {
        return slots;
    }
    let ideal = weights.map(|w| {
        if w > 0.0 {
            envs as f64 * w / total
        } else {
            0.0
        }
    });
    for i in 0..Task::COUNT {
        if weights[i] > 0.0 {
            slots[i] = (ideal[i].round() as usize).max(1);
        }
    }
    loop {
        let sum: usize = slots.iter().sum();
        if sum == envs {
            return slots;
        }
        // The task furthest above (or below) its ideal count gives (or takes) one.
        let candidates =
            (0..Task::COUNT).filter(|&i| weights[i] > 0.0 && (sum < envs || slots[i] > 1));
        let error = |i: usize| slots[i] as f64 - ideal[i];
        let pick = if sum > envs {
            candidates.fold(None, |best: Option<usize>, i| match best {
                Some(b) if error(b) >= error(i) => Some(b),
                _ => Some(i),
            })
        } else {
            candidates.fold(None, |best: Option<usize>, i| match best {
                Some(b) if error(b) <= error(i) => Some(b),
                _ => Some(i),
            })
        };
        let Some(i) = pick else { return slots };
        if sum > envs {
            slots[i] -= 1;
        } else {
            slots[i] += 1;
        }
    }
}

/// Which tasks' minibatches go into updates under `shares` (see [`update_shares`]): each
/// task's credit grows by its share per update and it takes part whenever a whole one has
/// built up, so a share of 0.25 is every fourth update, spread evenly. Deterministic.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct UpdateTurns {
    credit: [f64; Task::COUNT],
}

impl UpdateTurns {
    /// The next update's tasks.
    pub(crate) fn next(&mut self, shares: &[f64; Task::COUNT]) -> [bool; Task::COUNT] {
        let mut take = [false; Task::COUNT];
        for (i, share) in shares.iter().enumerate() {
            self.credit[i] = (self.credit[i] + share).min(1.0 + share);
            // A tolerance, so that four shares of 0.25 make a whole turn despite rounding.
            if self.credit[i] >= 1.0 - 1e-9 {
                self.credit[i] -= 1.0;
                take[i] = true;
            }
        }
        take
    }
}

/// Updates per env step that keep the minibatch rows per env step as configured when tasks
/// take part in only `shares` of the updates: `updates_per_env_step * tasks / sum(shares)`.
pub(crate) fn focused_updates_per_env_step(
    updates_per_env_step: f64,
    tasks: &[Task],
    shares: &[f64; Task::COUNT],
) -> f64 {
    let total: f64 = tasks.iter().map(|t| shares[t.index()]).sum();
    if total <= 0.0 {
        return updates_per_env_step;
    }
    updates_per_env_step * tasks.len() as f64 / total
}

/// One buffer per task; `others` > 0 keeps that many other herders per transition for the
/// centralised critic.
fn new_buffers(width: usize, capacity: usize, others: usize) -> Vec<ReplayBuffer> {
    Task::ALL
        .iter()
        .map(|_| {
            let buffer = ReplayBuffer::new(width, ACTION_DIM, capacity);
            if others > 0 {
                buffer.with_others(others)
            } else {
                buffer
            }
        })
        .collect()
}

/// The trainer's state between phases.
struct Run<'a> {
    config: &'a TrainConfig,
    agent: Agent,
    progress: Progress,
    rng: ChaCha8Rng,
    replay: Vec<ReplayBuffer>,
    demos: Vec<ReplayBuffer>,
    log: CsvLog,
    started: Instant,
    wall_offset: f64,
    eval_scenarios: Vec<EvalScenario>,
    last_eval: Vec<EvalRow>,
    /// Pause the DDPG phase at this many env steps (a restart candidate's trial).
    stop_at: Option<u64>,
    /// The best checkpoints by the check, best first (`eval.finalists`; empty when off).
    finalists: Vec<Finalist>,
}

impl Run<'_> {
    fn wall(&self) -> f64 {
        self.wall_offset + self.started.elapsed().as_secs_f64()
    }

    fn dir(&self) -> PathBuf {
        self.config.output_dir.clone()
    }

    fn checkpoint(&self) -> Checkpoint {
        let mut progress = self.progress;
        progress.wall_time_s = self.wall();
        Checkpoint {
            agent: self.agent.clone(),
            progress,
            config: self.config.clone(),
        }
    }

    fn save_last(&self) -> Result<(), TrainError> {
        checkpoint::save(&self.dir().join("last.safetensors"), &self.checkpoint())?;
        Ok(())
    }

    /// Evaluates the float actor on the held-out seeds; keeps it if it is the best so far.
    fn evaluate(&mut self, observer: &mut dyn Observer) -> Result<(), TrainError> {
        let e = &self.config.eval;
        let actor = &self.agent.actor;
        let rows = evaluate_flat(&self.eval_scenarios, e.episodes, e.seed_base, || {
            ActorPolicy::new(actor)
        })?;
        let s = score(&rows);
        let best = (self.progress.best_success, self.progress.best_time_ratio);
        let improved = !self.dir().join("best.safetensors").exists() || better(s, best);
        if improved {
            self.progress.best_success = s.0;
            self.progress.best_time_ratio = s.1;
            checkpoint::save(&self.dir().join("best.safetensors"), &self.checkpoint())?;
        }
        self.keep_finalist(s)?;
        observer.note(&format!(
            "eval at {} env steps / {} updates: success {:.1}%, time {:.2}x lower bound{}",
            self.progress.env_steps,
            self.agent.updates,
            100.0 * s.0,
            s.1,
            if improved { " (new best)" } else { "" }
        ));
        self.log.write(&LogRow::evaluation(
            self.wall(),
            self.progress.env_steps,
            self.agent.updates,
            self.progress.episodes,
            s,
        ))?;
        // Per scenario, with the environment steps its task has had.
        append_eval_rows(
            &self.dir().join("eval.csv"),
            self.progress.env_steps,
            &self.progress.task_env_steps,
            &rows,
        )?;
        for &task in &self.config.training.tasks {
            if let Some(success) = task_success(&rows, task) {
                self.progress.task_latest_success[task.index()] = success;
            }
        }
        self.last_eval = rows;
        Ok(())
    }

    /// Keeps the checkpoint just checked (score `s`) among the finalists if it is one of the
    /// best `eval.finalists` so far; the one it pushes out is deleted.
    fn keep_finalist(&mut self, s: (f64, f64)) -> Result<(), TrainError> {
        let capacity = self.config.eval.finalists;
        if capacity == 0 {
            return Ok(());
        }
        let env_steps = self.progress.env_steps;
        let dir = self.dir();
        let admission = finalists::admit(
            &mut self.finalists,
            Finalist {
                env_steps,
                check: s,
            },
            capacity,
        );
        if admission.kept {
            checkpoint::save(&finalists::file(&dir, env_steps), &self.checkpoint())?;
        }
        if let Some(gone) = admission.dropped {
            remove_if_there(&finalists::file(&dir, gone))?;
        }
        write_atomically(
            &dir.join(finalists::CSV_FILE),
            &finalists::to_csv(&self.finalists, None),
        )
    }

    /// The finalists a resumed run goes on with: those checked before the step it resumes
    /// from whose files are there; the rest (a future the run now lives again) are deleted.
    fn reload_finalists(&mut self) -> Result<(), TrainError> {
        let dir = self.dir();
        let text = read_if_there(&dir.join(finalists::CSV_FILE))?;
        for f in finalists::from_csv(&text) {
            let path = finalists::file(&dir, f.env_steps);
            if f.env_steps <= self.progress.env_steps && path.exists() {
                self.finalists.push(f);
            } else {
                remove_if_there(&path)?;
            }
        }
        Ok(())
    }

    /// The end-of-run choice ([`choose_finalist`]); the kept checkpoint's check score becomes
    /// the run's best, as a run without finalists reports its best's (the finalists' mean was
    /// never checked, so its final-set score stands in).
    fn choose_finalist(&mut self, observer: &mut dyn Observer) -> Result<(), TrainError> {
        let dir = self.dir();
        let kept = choose_finalist(
            self.config,
            &dir,
            &self.finalists,
            &self.eval_scenarios,
            observer,
        )?;
        if let Some(kept) = kept {
            let (success, time) = kept.check.unwrap_or(kept.final_score);
            self.progress.best_success = success;
            self.progress.best_time_ratio = time;
        }
        Ok(())
    }

    /// After an evaluation: starts over any task that has stalled (see [`stalled_tasks`]).
    fn reset_stalled_tasks(&mut self, observer: &mut dyn Observer) {
        let t = &self.config.training;
        for task in stalled_tasks(t, &t.tasks, &mut self.progress, &self.last_eval) {
            let i = task.index();
            // Seeded by the run, the task and the reset's number: reproducible, and unlike
            // the draws that follow it.
            let mut rng = ChaCha8Rng::seed_from_u64(
                self.config.seed
                    ^ 0x7A5C_4E5E_7000
                    ^ ((i as u64) << 8)
                    ^ u64::from(self.progress.task_resets[i]),
            );
            self.agent.reset_task(i, &mut rng);
            // Started over: not learned, whatever its last evaluation said.
            self.progress.task_latest_success[i] = 0.0;
            if t.task_reset_clears_replay {
                self.replay[i].clear();
            }
            observer.note(&format!(
                "task reset: {} stalled below {:.0}% held-out success for {} of its env steps; \
                 its layers start over (reset {} of {})",
                task_name(task),
                100.0 * t.task_reset_below,
                t.task_reset_after_task_env_steps,
                self.progress.task_resets[i],
                t.task_resets_max
            ));
        }
    }

    fn warm_start(&mut self, observer: &mut dyn Observer) -> Result<(), TrainError> {
        let w = &self.config.warm_start;
        let config = self.config;
        // 1a. Demonstrations from every curriculum stage.
        let (ret, succ) = self.record_demonstrations(observer)?;

        // 1b. Behaviour cloning.
        observer.phase("imitation", w.imitation_updates as u64);
        let ddpg_optimizer = self.agent.actor_optimizer.clone();
        self.agent.actor_optimizer = Adam::new(
            AdamConfig {
                learning_rate: w.imitation_learning_rate,
                ..AdamConfig::default()
            },
            self.agent.actor.layers(),
        );
        let mut batches = vec![Batch::default(); Task::COUNT];
        let mut loss_avg = 0.0;
        for u in 0..w.imitation_updates {
            sample_per_task(
                &self.demos,
                config.ddpg.batch_size,
                &mut self.rng,
                &mut batches,
            );
            let loss = self.agent.imitation_step(&batches);
            loss_avg = if u == 0 {
                loss
            } else {
                0.99 * loss_avg + 0.01 * loss
            };
            if u % 500 == 0 || u + 1 == w.imitation_updates {
                observer.progress(u as u64 + 1, &format!("imitation loss {loss_avg:.4}"));
                self.log.write(&LogRow {
                    phase: 0,
                    wall_s: self.wall(),
                    updates: u as u64,
                    recent_return: ret,
                    recent_success: succ,
                    critic_loss: f64::NAN,
                    actor_loss: f64::from(loss_avg),
                    q_mean: f64::NAN,
                    eval_success: f64::NAN,
                    eval_time_ratio: f64::NAN,
                    ..LogRow::default()
                })?;
            }
        }
        self.agent.actor_optimizer = ddpg_optimizer;
        self.agent.sync_targets();

        // 1c. Critic pretraining: evaluate the cloned policy on the demonstrations.
        observer.phase("critic pretraining", w.critic_updates as u64);
        for u in 0..w.critic_updates {
            sample_per_task(
                &self.replay,
                config.ddpg.batch_size,
                &mut self.rng,
                &mut batches,
            );
            let stats = self.agent.evaluate_policy_step(&batches);
            if u % 500 == 0 || u + 1 == w.critic_updates {
                observer.progress(
                    u as u64 + 1,
                    &format!(
                        "critic loss {:.4}, Q {:.2}",
                        stats.critic_loss, stats.q_mean
                    ),
                );
            }
        }
        self.agent.sync_targets();
        self.agent.updates = 0;
        self.progress.warm_start_done = true;
        self.evaluate(observer)?;
        self.save_last()
    }

    fn ddpg(&mut self, observer: &mut dyn Observer) -> Result<f64, TrainError> {
        let config = self.config;
        let t = &config.training;
        let start_steps = self.progress.env_steps;
        // Curriculum progress counts environment steps only, so a seed fixes the run whatever
        // the machine's speed (the wall-clock limit only decides where it stops).
        let fraction = |steps: u64| (steps as f64 / t.env_steps.max(1) as f64).min(1.0);
        // Each task's curriculum counts from its last stalled-task reset (0 if none).
        let draw_at = |env_steps: u64, reset_at: [u64; 2]| {
            move |rng: &mut ChaCha8Rng, task: Task| {
                let since = env_steps.saturating_sub(reset_at[task.index()]);
                draw_from_stage(config, fraction(since), rng, task)
            }
        };
        let rollout_rng = ChaCha8Rng::seed_from_u64(
            config
                .seed
                .wrapping_add(2)
                .wrapping_add(start_steps.wrapping_mul(0x9E37_79B9)),
        );
        let mut rollouts = Rollouts::new(
            t.envs,
            config,
            rollout_rng,
            &mut draw_at(start_steps, self.progress.task_reset_env_steps),
        )?;
        observer.phase("MTDDPG", t.env_steps);
        if self.progress.task_env_steps == [0; Task::COUNT] && self.progress.env_steps > 0 {
            // A checkpoint from before the count: its environments cycled through the tasks.
            let each = self.progress.env_steps / t.tasks.len().max(1) as u64;
            for task in &t.tasks {
                self.progress.task_env_steps[task.index()] = each;
            }
        }
        let mut last_env_slots = None;
        let mut batches = vec![Batch::default(); Task::COUNT];
        let mut demo_batches = vec![Batch::default(); Task::COUNT];
        let mut recent = Recent { window: Vec::new() };
        let mut updates_owed = 0.0_f64;
        let mut turns = UpdateTurns::default();
        // Full shares are where every run starts; only a change is worth a note.
        let mut last_shares = update_shares(t, &t.tasks, &[0.0; Task::COUNT]);
        let mut last_checkpoint = Instant::now();
        let mut last_log = Instant::now();
        let mut update_time = 0.0_f64;
        let mut update_count = 0u64;
        let mut stats = crate::ddpg::UpdateStats::default();
        // The last actor step's self-imitation share (critic-only updates report none).
        let mut self_imitation_share = 0.0_f32;
        let mut next_eval = self.agent.updates + config.eval.every_updates;
        let tasks = config.training.tasks.len().max(1) as u64;
        let by_steps = config.eval.every_task_env_steps > 0;
        let task_steps = |env_steps: u64| env_steps / tasks;
        let mut next_eval_steps =
            (task_steps(self.progress.env_steps) / config.eval.every_task_env_steps.max(1) + 1)
                * config.eval.every_task_env_steps;
        let imitation_weight = if config.warm_start.enabled {
            config.warm_start.imitation_weight
        } else {
            0.0
        };
        let limit = self.stop_at.map_or(t.env_steps, |s| s.min(t.env_steps));
        while self.progress.env_steps < limit && self.wall() < t.wall_clock_limit_s {
            // A task started over by a stalled-task reset has a warm-up of its own.
            let reset_warmup = Task::ALL.map(|task| {
                let at = self.progress.task_reset_env_steps[task.index()];
                at > 0 && self.progress.env_steps < at.saturating_add(t.task_reset_warmup_steps)
            });
            // The exploration noise may fall over the run (DdpgConfig::exploration_noise_at).
            let noise = config
                .ddpg
                .exploration_noise_at(self.progress.env_steps as f64 / t.env_steps.max(1) as f64);
            let controller = if self.progress.env_steps < t.random_warmup_steps {
                Controller::RandomWaypoints
            } else if reset_warmup.contains(&true) {
                Controller::ActorExceptRandomTasks(&self.agent.actor, noise, reset_warmup)
            } else {
                Controller::Actor(&self.agent.actor, noise)
            };
            if t.passed_task_env_share < 1.0 {
                let weights = env_shares(t, &t.tasks, &self.progress.task_latest_success);
                let slots = env_slots(t.envs, &weights);
                if last_env_slots != Some(slots) {
                    // The first setting is the even split every run starts from.
                    if last_env_slots.is_some() {
                        observer.note(&format!(
                            "environments per task: {}",
                            t.tasks
                                .iter()
                                .map(|task| format!("{} {}", task_name(*task), slots[task.index()]))
                                .collect::<Vec<_>>()
                                .join(", ")
                        ));
                    }
                    last_env_slots = Some(slots);
                    rollouts.set_task_slots(Some(slots));
                }
            }
            let before = rollouts.env_steps;
            let before_tasks = rollouts.task_env_steps;
            let finished = rollouts.step(
                &controller,
                &mut self.replay,
                None,
                &mut draw_at(self.progress.env_steps, self.progress.task_reset_env_steps),
            )?;
            let stepped = rollouts.env_steps - before;
            self.progress.env_steps += stepped;
            for (i, steps) in self.progress.task_env_steps.iter_mut().enumerate() {
                *steps += rollouts.task_env_steps[i] - before_tasks[i];
            }
            self.progress.episodes += finished.len() as u64;
            recent.push(&finished);

            let stored: u64 = self.replay.iter().map(|b| b.len() as u64).sum();
            if stored >= t.learning_starts {
                let shares = update_shares(t, &t.tasks, &self.progress.task_latest_success);
                if shares != last_shares {
                    last_shares = shares;
                    observer.note(&format!(
                        "update shares: {}",
                        t.tasks
                            .iter()
                            .map(|task| format!("{} {:.2}", task_name(*task), shares[task.index()]))
                            .collect::<Vec<_>>()
                            .join(", ")
                    ));
                }
                updates_owed += stepped as f64
                    * focused_updates_per_env_step(t.updates_per_env_step, &t.tasks, &shares);
                while updates_owed >= 1.0 {
                    updates_owed -= 1.0;
                    let tick = Instant::now();
                    sample_per_task(
                        &self.replay,
                        config.ddpg.batch_size,
                        &mut self.rng,
                        &mut batches,
                    );
                    // A task sitting this update out contributes no rows, unless no task
                    // taking part has any (a reset task's emptied replay refilling).
                    let take = turns.next(&shares);
                    if batches.iter().zip(take).any(|(b, take)| take && b.size > 0) {
                        for (batch, take) in batches.iter_mut().zip(take) {
                            if !take {
                                batch.size = 0;
                            }
                        }
                    }
                    if imitation_weight > 0.0 {
                        sample_per_task(
                            &self.demos,
                            config.ddpg.batch_size,
                            &mut self.rng,
                            &mut demo_batches,
                        );
                    }
                    stats = if self.progress.env_steps < config.fine_tune.critic_only_env_steps {
                        self.agent.evaluate_policy_step(&batches)
                    } else {
                        self.agent
                            .update_with_imitation(&batches, &demo_batches, imitation_weight)
                    };
                    if let Some(share) = stats.self_imitation_share {
                        self_imitation_share = share;
                    }
                    update_time += tick.elapsed().as_secs_f64();
                    update_count += 1;
                }
            }

            if last_log.elapsed().as_secs_f64() >= 5.0 {
                last_log = Instant::now();
                let (ret, succ) = recent.means();
                let n = config.stage_at(fraction(self.progress.env_steps));
                observer.progress(
                    self.progress.env_steps - start_steps.min(self.progress.env_steps),
                    &format!(
                        "succ {:.0}% ret {ret:.1} critic {:.3} Q {:.1} N {:?}{} {:.1} ms/upd{}{}",
                        100.0 * succ,
                        stats.critic_loss,
                        stats.q_mean,
                        n.targets,
                        if n.pairs.is_empty() {
                            String::new()
                        } else {
                            format!(" (N, M) {:?}", n.pairs)
                        },
                        1e3 * update_time / update_count.max(1) as f64,
                        if config.ddpg.self_imitation > 0.0 {
                            format!(" sil {:.0}%", 100.0 * self_imitation_share)
                        } else {
                            String::new()
                        },
                        if config.ddpg.exploration == crate::ddpg::Exploration::Parameter {
                            let s = rollouts.parameter_noise_scales();
                            format!(" param noise driving {:.4} collecting {:.4}", s[0], s[1])
                        } else {
                            String::new()
                        }
                    ),
                );
                self.log.write(&LogRow {
                    phase: 1,
                    wall_s: self.wall(),
                    env_steps: self.progress.env_steps,
                    updates: self.agent.updates,
                    episodes: self.progress.episodes,
                    recent_return: ret,
                    recent_success: succ,
                    critic_loss: f64::from(stats.critic_loss),
                    actor_loss: f64::from(stats.actor_loss),
                    q_mean: f64::from(stats.q_mean),
                    eval_success: f64::NAN,
                    eval_time_ratio: f64::NAN,
                })?;
            }
            if by_steps && task_steps(self.progress.env_steps) >= next_eval_steps {
                next_eval_steps += config.eval.every_task_env_steps;
                self.evaluate(observer)?;
                self.reset_stalled_tasks(observer);
            } else if !by_steps && self.agent.updates >= next_eval {
                next_eval = self.agent.updates + config.eval.every_updates;
                self.evaluate(observer)?;
            }
            if last_checkpoint.elapsed().as_secs_f64() >= t.checkpoint_every_s {
                last_checkpoint = Instant::now();
                self.save_last()?;
                let _ = plot_curve(
                    &read_log(&self.dir().join("log.csv"))?,
                    &self.dir().join("curve.png"),
                );
            }
        }
        Ok(if update_count == 0 {
            f64::NAN
        } else {
            update_time / update_count as f64
        })
    }
}

/// The tasks to start over after an evaluation (`training.task_reset_after_task_env_steps`),
/// with `progress` brought up to date: each task's best mean success since its last reset, and
/// the step of its last evaluation at or above `task_reset_below`, take this evaluation's
/// `rows` in. A task that has had the patience's worth of its own env steps (the parallel
/// environments share the steps evenly between `tasks`) without reaching the bar, counted from
/// its last reset (`TaskResetRule::BestSinceReset`) or from its last reset or last pass,
/// whichever is later (`TaskResetRule::Recent`), and has resets left, is counted as reset now.
/// Pure: the caller resets the networks.
pub(crate) fn stalled_tasks(
    t: &crate::config::LoopConfig,
    tasks: &[Task],
    progress: &mut Progress,
    rows: &[EvalRow],
) -> Vec<Task> {
    let mut stalled = Vec::new();
    let per_task = |steps: u64| steps / tasks.len().max(1) as u64;
    for &task in tasks {
        let i = task.index();
        let Some(success) = task_success(rows, task) else {
            continue;
        };
        progress.task_best_since_reset[i] = progress.task_best_since_reset[i].max(success);
        if success >= t.task_reset_below {
            progress.task_last_pass_env_steps[i] = progress.env_steps;
        }
        let (since, stalled_now) = match t.task_reset_rule {
            TaskResetRule::BestSinceReset => (
                progress.task_reset_env_steps[i],
                progress.task_best_since_reset[i] < t.task_reset_below,
            ),
            // The patience counts from the later of the reset and the last pass, so a pass
            // within it keeps the task.
            TaskResetRule::Recent => (
                progress.task_reset_env_steps[i].max(progress.task_last_pass_env_steps[i]),
                true,
            ),
        };
        let waited = per_task(progress.env_steps.saturating_sub(since));
        if t.task_reset_after_task_env_steps > 0
            && waited >= t.task_reset_after_task_env_steps
            && stalled_now
            && progress.task_resets[i] < t.task_resets_max
        {
            progress.task_resets[i] += 1;
            progress.task_reset_env_steps[i] = progress.env_steps;
            progress.task_best_since_reset[i] = 0.0;
            stalled.push(task);
        }
    }
    stalled
}

/// Runs (or resumes) a training run as configured; see the module docs.
pub fn train(
    config: &TrainConfig,
    resume: Option<Checkpoint>,
    observer: &mut (dyn Observer + Send),
) -> Result<TrainOutcome, TrainError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(config.training.threads)
        .build()
        .map_err(|e| TrainError::Threads(e.to_string()))?;
    pool.install(|| train_in_pool(config, resume, observer))
}

fn train_in_pool(
    config: &TrainConfig,
    resume: Option<Checkpoint>,
    observer: &mut dyn Observer,
) -> Result<TrainOutcome, TrainError> {
    if config.training.restart_candidates > 1 && resume.is_none() {
        return train_with_restarts(config, observer);
    }
    let run = start_run(config, resume, observer)?;
    finish_run(run, observer)
}

/// Random restarts (`training.restart_candidates`): whether an actor-critic run finds the
/// behaviour that the reward pays for is often settled in its first tens of thousands of
/// steps, by the seed. So `K` candidates, seeded apart, each train for
/// `restart_trial_env_steps`; the one with the best held-out score (the training-time
/// evaluation's seeds, never the reporting seeds) goes on, the others are dropped. Every
/// candidate's steps count: the winner goes on to `env_steps - (K - 1) * trial`, so the run
/// as a whole takes `env_steps`. Each candidate writes to `<output_dir>/candidate-<i>`, and
/// `<output_dir>/restarts.json` records the trial scores and the winner.
fn train_with_restarts(
    config: &TrainConfig,
    observer: &mut dyn Observer,
) -> Result<TrainOutcome, TrainError> {
    let t = &config.training;
    let k = t.restart_candidates as u64;
    let trial = t.restart_trial_env_steps;
    // `TrainConfig::validate` keeps every trial inside the budget; saturating all the same.
    let budget = t.env_steps.saturating_sub((k - 1).saturating_mul(trial));
    let dir = config.output_dir.clone();
    std::fs::create_dir_all(&dir).map_err(ReportError::from)?;
    let candidates: Vec<TrainConfig> = (0..k)
        .map(|i| {
            let mut c = config.clone();
            c.seed = config.seed.wrapping_add(i * 1_000_003);
            c.training.env_steps = budget;
            c.training.restart_candidates = 1;
            c.output_dir = restart_candidate_dir(&dir, i as usize);
            c
        })
        .collect();
    let mut runs = Vec::with_capacity(candidates.len());
    let mut scores = Vec::with_capacity(candidates.len());
    for (i, candidate) in candidates.iter().enumerate() {
        observer.note(&format!(
            "restart candidate {i} (seed {}): {trial} env steps",
            candidate.seed
        ));
        let mut run = start_run(candidate, None, observer)?;
        run.stop_at = Some(trial);
        run.ddpg(observer)?;
        run.evaluate(observer)?;
        run.save_last()?;
        scores.push(match t.restart_score {
            crate::config::RestartScore::Mean => score(&run.last_eval),
            crate::config::RestartScore::WeakestTask => {
                crate::eval::weakest_task_score(&run.last_eval)
            }
        });
        runs.push(run);
    }
    let winner = (1..scores.len()).fold(0, |best, i| {
        if crate::eval::better(scores[i], scores[best]) {
            i
        } else {
            best
        }
    });
    let record = serde_json::json!({
        "trial_env_steps": trial,
        "score": format!("{:?}", t.restart_score),
        "winner": winner,
        "winner_env_steps": budget,
        "total_env_steps": t.env_steps,
        "candidates": candidates.iter().zip(&scores).map(|(c, s)| serde_json::json!({
            "seed": c.seed,
            "success": s.0,
            "time_ratio": s.1,
        })).collect::<Vec<_>>(),
    });
    std::fs::write(
        dir.join(RESTARTS_FILE),
        serde_json::to_string_pretty(&record).unwrap_or_default(),
    )
    .map_err(ReportError::from)?;
    observer.note(&format!(
        "restarts: candidate {winner} goes on (trial scores {scores:?})"
    ));
    let mut run = runs.swap_remove(winner);
    drop(runs);
    run.stop_at = None;
    finish_run(run, observer)
}

/// Where restart candidate `i` of the run in `dir` writes.
pub fn restart_candidate_dir(dir: &std::path::Path, i: usize) -> PathBuf {
    dir.join(format!("candidate-{i}"))
}

/// The record of a run's restarts, in its output folder.
pub const RESTARTS_FILE: &str = "restarts.json";

/// A run ready for its DDPG phase: networks fresh (or resumed), buffers empty, the warm start
/// done if configured.
fn start_run<'a>(
    config: &'a TrainConfig,
    resume: Option<Checkpoint>,
    observer: &mut dyn Observer,
) -> Result<Run<'a>, TrainError> {
    let dir = config.output_dir.clone();
    std::fs::create_dir_all(&dir).map_err(ReportError::from)?;
    let mut init_rng = ChaCha8Rng::seed_from_u64(config.seed);
    let (agent, progress) = match resume {
        Some(c) => (c.agent, c.progress),
        None => {
            let mut agent = Agent::new(
                feature_count(config.encoder_version).unwrap_or(FEATURES),
                Task::COUNT,
                config.network,
                config.ddpg,
                &mut init_rng,
            );
            if let Some(path) = &config.fine_tune.actor {
                let actor = checkpoint::load_actor(path)?;
                let fits = actor.inputs() == agent.actor.inputs()
                    && actor.tasks() == agent.actor.tasks()
                    && actor.outputs() == agent.actor.outputs();
                if !fits {
                    return Err(TrainError::FineTuneActor {
                        path: path.display().to_string(),
                        reason: format!(
                            "{} inputs, {} tasks, {} outputs; the config's actor has {}, {}, {}",
                            actor.inputs(),
                            actor.tasks(),
                            actor.outputs(),
                            agent.actor.inputs(),
                            agent.actor.tasks(),
                            agent.actor.outputs()
                        ),
                    });
                }
                agent.actor = actor;
                agent.target_actor = agent.actor.clone();
                agent.actor_optimizer = crate::nn::Adam::new(
                    crate::nn::AdamConfig {
                        learning_rate: config.ddpg.actor_learning_rate,
                        ..crate::nn::AdamConfig::default()
                    },
                    agent.actor.layers(),
                );
            }
            (agent, Progress::default())
        }
    };
    // A resumed run continues from a stream of its own, derived from where it stopped.
    let rng = ChaCha8Rng::seed_from_u64(
        config
            .seed
            .wrapping_mul(31)
            .wrapping_add(progress.env_steps)
            .wrapping_add(3),
    );
    let eval_scenarios: Vec<EvalScenario> = config
        .eval
        .scenario_list()
        .into_iter()
        .filter(|s| config.training.tasks.contains(&s.task))
        .collect();
    // As wide as the actor's input (a resumed actor keeps the width it was made with).
    let width = agent.actor.inputs();
    let mut run = Run {
        config,
        agent,
        progress,
        rng,
        replay: new_buffers(
            width,
            config.training.replay_capacity,
            if config.ddpg.centralised_critic {
                config.ddpg.critic_max_others
            } else {
                0
            },
        ),
        demos: new_buffers(width, config.training.replay_capacity, 0),
        log: CsvLog::open(&dir.join("log.csv"))?,
        started: Instant::now(),
        wall_offset: progress.wall_time_s,
        eval_scenarios,
        last_eval: Vec::new(),
        stop_at: None,
        finalists: Vec::new(),
    };
    if config.eval.finalists > 0 && run.progress.env_steps > 0 {
        run.reload_finalists()?;
    }
    if config.warm_start.enabled && !run.progress.warm_start_done {
        run.warm_start(observer)?;
    } else if config.warm_start.enabled && config.warm_start.imitation_weight > 0.0 {
        // A resumed run needs demonstrations again for the imitation pull.
        observer.note("resume: re-recording demonstrations for the imitation term");
        run.record_demonstrations(observer)?;
    }
    Ok(run)
}

/// The DDPG phase to its end, the last evaluation and checkpoint, the evolution stage if
/// configured.
fn finish_run(mut run: Run<'_>, observer: &mut dyn Observer) -> Result<TrainOutcome, TrainError> {
    let config = run.config;
    let dir = config.output_dir.clone();
    let seconds_per_update = run.ddpg(observer)?;
    run.evaluate(observer)?;
    run.choose_finalist(observer)?;
    run.save_last()?;
    let evolution = if config.evolution.enabled {
        let mut best = checkpoint::load(&dir.join("best.safetensors"))?;
        // The stage's clock starts where the run's ends.
        best.progress.wall_time_s = run.wall();
        Some(evolve_checkpoint(config, &best, observer)?)
    } else {
        None
    };
    let rows = read_log(&dir.join("log.csv"))?;
    plot_curve(&rows, &dir.join("curve.png"))?;
    let mut progress = run.progress;
    // Includes the evolution stage.
    progress.wall_time_s = run.wall();
    Ok(TrainOutcome {
        progress,
        best_checkpoint: dir.join("best.safetensors"),
        last_checkpoint: dir.join("last.safetensors"),
        last_eval: run.last_eval,
        seconds_per_update,
        evolution,
    })
}

impl Run<'_> {
    /// Rolls out the baselines over every curriculum stage, filling the demonstration buffers
    /// and the replay buffers; returns the baselines' mean learner return and success rate.
    fn record_demonstrations(
        &mut self,
        observer: &mut dyn Observer,
    ) -> Result<(f64, f64), TrainError> {
        let w = &self.config.warm_start;
        let config = self.config;
        let mut draw = |rng: &mut ChaCha8Rng, task| draw_from_all_stages(config, rng, task);
        let rollout_rng = ChaCha8Rng::seed_from_u64(config.seed.wrapping_add(1));
        let mut rollouts = Rollouts::new(config.training.envs, config, rollout_rng, &mut draw)?;
        let mut done = [0usize; 2];
        observer.phase("demonstrations", (w.episodes_per_task * 2) as u64);
        let controller = Controller::Baseline(w);
        let mut recent = Recent { window: Vec::new() };
        while done.iter().any(|&d| d < w.episodes_per_task) {
            let finished = rollouts.step(
                &controller,
                &mut self.replay,
                Some(&mut self.demos),
                &mut draw,
            )?;
            for e in &finished {
                done[e.draw.task.index()] += 1;
            }
            recent.push(&finished);
            let total = done
                .iter()
                .map(|&d| d.min(w.episodes_per_task))
                .sum::<usize>();
            observer.progress(
                total as u64,
                &format!(
                    "{} + {} transitions",
                    self.demos[0].len(),
                    self.demos[1].len()
                ),
            );
        }
        let (ret, succ) = recent.means();
        observer.note(&format!(
            "demonstrations: {} driving + {} collecting transitions, baseline success {:.0}%, mean return {:.1}",
            self.demos[0].len(),
            self.demos[1].len(),
            100.0 * succ,
            ret
        ));
        Ok((ret, succ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_model::Task;

    fn row(task: Task, targets: usize, success: f64) -> EvalRow {
        EvalRow {
            scenario: EvalScenario {
                task,
                targets,
                herders: 4,
            },
            episodes: 8,
            success_rate: success,
            mean_time_s: 100.0,
            mean_time_ratio: 2.0,
            mean_path_length: 500.0,
        }
    }

    /// An evaluation with each task at one success rate on N = 4 and 8.
    fn eval(driving: f64, collecting: f64) -> Vec<EvalRow> {
        vec![
            row(Task::Driving, 4, driving),
            row(Task::Driving, 8, driving),
            row(Task::Collecting, 4, collecting),
            row(Task::Collecting, 8, collecting),
        ]
    }

    #[test]
    fn a_task_is_reset_only_after_its_patience_without_success() {
        let t = crate::config::LoopConfig {
            task_reset_after_task_env_steps: 50_000,
            task_reset_below: 0.25,
            task_resets_max: 2,
            ..crate::config::LoopConfig::default()
        };
        let tasks = Task::ALL;
        // 40k steps per task: patience not yet spent.
        let mut progress = Progress {
            env_steps: 80_000,
            ..Progress::default()
        };
        assert!(stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.5)).is_empty());
        // 50k per task: driving never reached 25 % and goes; collecting reached 50 % and stays
        // even though it has fallen to 0 since.
        progress.env_steps = 100_000;
        assert_eq!(
            stalled_tasks(&t, &tasks, &mut progress, &eval(0.125, 0.0)),
            vec![Task::Driving]
        );
        assert_eq!(progress.task_resets, [1, 0]);
        assert_eq!(progress.task_reset_env_steps, [100_000, 0]);
        assert_eq!(progress.task_best_since_reset, [0.0, 0.5]);
        // Its patience counts from the reset.
        progress.env_steps = 180_000;
        assert!(stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.0)).is_empty());
        progress.env_steps = 200_000;
        assert_eq!(
            stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.0)),
            vec![Task::Driving]
        );
        // Two resets at most.
        progress.env_steps = 400_000;
        assert!(stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.0)).is_empty());
        assert_eq!(progress.task_resets, [2, 0]);
        // Off: nothing is ever reset.
        let off = crate::config::LoopConfig::default();
        let mut fresh = Progress {
            env_steps: 1_000_000,
            ..Progress::default()
        };
        assert!(stalled_tasks(&off, &tasks, &mut fresh, &eval(0.0, 0.0)).is_empty());
    }

    #[test]
    fn a_learned_task_gives_its_updates_to_the_unlearned_one_at_the_same_compute() {
        let t = crate::config::LoopConfig {
            passed_task_update_share: 0.25,
            passed_task_bar: 0.95,
            ..crate::config::LoopConfig::default()
        };
        let both = Task::ALL;
        let (d, c) = (Task::Driving.index(), Task::Collecting.index());
        let at = |driving: f64, collecting: f64| {
            let mut latest = [0.0; Task::COUNT];
            latest[d] = driving;
            latest[c] = collecting;
            update_shares(&t, &both, &latest)
        };
        // Neither or both learned: every update holds both tasks.
        assert_eq!(at(0.5, 0.2), [1.0, 1.0]);
        assert_eq!(at(1.0, 0.96), [1.0, 1.0]);
        // Driving at the bar exactly, collecting below: driving sits three updates in four out.
        let shares = at(0.95, 0.9);
        assert_eq!((shares[d], shares[c]), (0.25, 1.0));
        // ... and the updates per env step rise so that the rows stay: 2 / 1.25 of 0.5.
        let per_step = focused_updates_per_env_step(0.5, &both, &shares);
        assert!((per_step - 0.8).abs() < 1e-12, "{per_step}");
        let mut turns = UpdateTurns::default();
        let taken: Vec<[bool; Task::COUNT]> = (0..8).map(|_| turns.next(&shares)).collect();
        assert!(taken.iter().all(|take| take[c]));
        let driving_turns: Vec<usize> = (0..8).filter(|&u| taken[u][d]).collect();
        assert_eq!(driving_turns, vec![3, 7], "every fourth update, evenly");
        let rows_per_step = per_step * taken.iter().flatten().filter(|&&x| x).count() as f64 / 8.0;
        assert!(
            (rows_per_step - 1.0).abs() < 1e-12,
            "two tasks' rows at 0.5 updates a step"
        );
        // The single-task arm has nothing to give: the other task is not trained.
        let one = update_shares(&t, &[Task::Driving], &[1.0, 0.0]);
        assert_eq!((one[d], one[c]), (1.0, 0.0));
        assert_eq!(
            focused_updates_per_env_step(0.5, &[Task::Driving], &one),
            0.5
        );
        // Off (the default): full shares whatever the evaluations say.
        let off = crate::config::LoopConfig::default();
        assert_eq!(update_shares(&off, &both, &[1.0, 0.0]), [1.0, 1.0]);
    }

    #[test]
    fn a_learned_task_gives_its_environments_to_the_unlearned_one_keeping_one() {
        let t = crate::config::LoopConfig {
            passed_task_env_share: 0.25,
            passed_task_bar: 0.95,
            ..crate::config::LoopConfig::default()
        };
        let both = Task::ALL;
        let (d, c) = (Task::Driving.index(), Task::Collecting.index());
        let mut latest = [0.0; Task::COUNT];
        latest[d] = 0.97;
        latest[c] = 0.6;
        let weights = env_shares(&t, &both, &latest);
        assert_eq!((weights[d], weights[c]), (0.25, 1.0));
        // 8 x 0.2 = 1.6 rounds to 2; 8 x 0.8 = 6.4 to 6.
        let slots = env_slots(8, &weights);
        assert_eq!((slots[d], slots[c]), (2, 6));
        // The update shares are a key of their own and stay full.
        assert_eq!(update_shares(&t, &both, &latest), [1.0, 1.0]);
        // Both learned, or neither: the even split.
        assert_eq!(env_slots(8, &env_shares(&t, &both, &[0.99, 0.99])), [4, 4]);
        assert_eq!(env_slots(8, &env_shares(&t, &both, &[0.1, 0.2])), [4, 4]);
        // A small share still keeps one environment; rounding up past the total gives way.
        assert_eq!(env_slots(4, &[0.01, 1.0]), [1, 3]);
        assert_eq!(env_slots(3, &[1.0, 1.0]), [1, 2]);
        assert_eq!(env_slots(5, &[1.0, 1.0]), [2, 3]);
        // A single-task arm has every environment.
        assert_eq!(
            env_slots(8, &env_shares(&t, &[Task::Collecting], &latest)),
            [0, 8]
        );
        // Off (the default): full weights whatever the evaluations say.
        let off = crate::config::LoopConfig::default();
        assert_eq!(env_shares(&off, &both, &[1.0, 0.0]), [1.0, 1.0]);
    }

    #[test]
    fn the_recent_rule_also_resets_a_task_that_passed_and_collapsed() {
        let t = crate::config::LoopConfig {
            task_reset_after_task_env_steps: 50_000,
            task_reset_below: 0.25,
            task_resets_max: 2,
            task_reset_rule: TaskResetRule::Recent,
            ..crate::config::LoopConfig::default()
        };
        let tasks = Task::ALL;
        // 25k per task: collecting passes (at the bar exactly), driving does not.
        let mut progress = Progress {
            env_steps: 50_000,
            ..Progress::default()
        };
        assert!(stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.25)).is_empty());
        assert_eq!(progress.task_last_pass_env_steps, [0, 50_000]);
        // 50k per task: driving has never passed and goes, as under the other rule;
        // collecting passed 25k of its steps ago and stays.
        progress.env_steps = 100_000;
        assert_eq!(
            stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.0)),
            vec![Task::Driving]
        );
        // Below the bar at every evaluation of the 50k of its own steps since its pass:
        // collecting has collapsed and goes, where the best-since-reset rule keeps it for ever.
        progress.env_steps = 125_000;
        assert!(stalled_tasks(&t, &tasks, &mut progress, &eval(0.5, 0.125)).is_empty());
        progress.env_steps = 150_000;
        assert_eq!(
            stalled_tasks(&t, &tasks, &mut progress, &eval(0.5, 0.125)),
            vec![Task::Collecting]
        );
        assert_eq!(progress.task_resets, [1, 1]);
        // Driving passed at 125k and 150k: below the bar since, but not yet for its patience.
        progress.env_steps = 200_000;
        assert!(stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.5)).is_empty());
        let mut best = progress;
        let keep = crate::config::LoopConfig {
            task_reset_rule: TaskResetRule::BestSinceReset,
            ..t.clone()
        };
        best.env_steps = 400_000;
        assert!(stalled_tasks(&keep, &tasks, &mut best, &eval(0.0, 0.5)).is_empty());
        progress.env_steps = 400_000;
        assert_eq!(
            stalled_tasks(&t, &tasks, &mut progress, &eval(0.0, 0.5)),
            vec![Task::Driving]
        );
    }

    #[test]
    fn a_resumed_run_replaces_the_evaluations_it_repeats() {
        let dir = std::env::temp_dir().join(format!("skyherd-eval-csv-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("eval.csv");
        let _ = std::fs::remove_file(&path);
        append_eval_rows(&path, 25_000, &[12_500; 2], &[row(Task::Driving, 4, 0.1)]).unwrap();
        append_eval_rows(&path, 50_000, &[25_000; 2], &[row(Task::Driving, 4, 0.2)]).unwrap();
        append_eval_rows(&path, 75_000, &[37_500; 2], &[row(Task::Driving, 4, 0.3)]).unwrap();
        // Resumed from the checkpoint at 50k: 50k is evaluated again and 75k is gone.
        append_eval_rows(&path, 50_000, &[25_000; 2], &[row(Task::Driving, 4, 0.25)]).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], EVAL_CSV_HEADER);
        assert_eq!(lines.len(), 3, "{text}");
        assert!(
            lines[1].starts_with("25000,12500,driving,4,4,8,0.1,"),
            "{text}"
        );
        assert!(
            lines[2].starts_with("50000,25000,driving,4,4,8,0.25,"),
            "{text}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
