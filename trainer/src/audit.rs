//! The reward audit: does the learner's reward rank behaviours the way success and speed do?
//!
//! For each scenario it flies hovering in place, every rule (`skyherd_sim::baseline::Method`)
//! and optionally a model file, on the same held-out seeds with test-time noise, and measures
//! what the learner would see: the discounted return of whole episodes under the config's
//! reward ([`crate::reward::LearnerReward`], herder 0's share, gamma of the config), beside
//! success and completion time. It is the gate for a training config ([`gate`]):
//!
//! * every rule that succeeds (at least [`SUCCESS_SHARE`] of its episodes) must beat hovering;
//! * rules that always succeed must rank by completion time: one that finishes more than
//!   [`TIME_MARGIN`] faster must have the higher return.
//!
//! A reward that fails it teaches the critic that doing nothing is good, whatever the
//! learner's other merits.
//!
//! ```
//! use skyherd_model::Task;
//! use skyherd_trainer::audit::{Candidate, audit, gate};
//! use skyherd_trainer::config::TrainConfig;
//! use skyherd_trainer::rollout::Draw;
//!
//! let mut config = TrainConfig::default();
//! config.training.episode_step_limit = 40;
//! let rows = audit(&config, &[Draw::paper(Task::Driving, 2, 1)], &[Candidate::Hover], 1, 7).unwrap();
//! assert_eq!(rows.len(), 1);
//! assert!(rows[0].mean_return < 0.0);
//! assert!(gate(&rows).passed); // nothing to compare hovering with
//! ```

use std::fmt::Write as _;

use rayon::prelude::*;
use skyherd_sim::baseline::{Method, RulePolicy};
use skyherd_sim::learned::ModelPolicy;
use skyherd_sim::policy::act_all;
use skyherd_sim::{Env, Policy, PolicyFactory, Scenario, ScenarioError, World};

use crate::config::TrainConfig;
use crate::reward::LearnerReward;
use crate::rollout::{Draw, training_scenario};

/// A rule "succeeds" in a scenario when at least this share of its episodes do.
pub const SUCCESS_SHARE: f64 = 0.9;
/// Two always-successful rules must rank by time when one is this much faster (relative).
pub const TIME_MARGIN: f64 = 0.1;

/// What flies in the audit.
#[derive(Clone, Debug)]
pub enum Candidate {
    /// Every herder holds still where it starts.
    Hover,
    /// A rule-based baseline.
    Rule(Method),
    /// A model file, flown as the drones fly it (the daemon's flight rules).
    Model(Box<ModelPolicy>),
}

impl Candidate {
    /// Hovering and every rule.
    pub fn hover_and_rules() -> Vec<Candidate> {
        std::iter::once(Candidate::Hover)
            .chain(Method::ALL.into_iter().map(Candidate::Rule))
            .collect()
    }

    /// The label in the table.
    pub fn name(&self) -> String {
        match self {
            Candidate::Hover => "hover".into(),
            Candidate::Rule(m) => m.as_str().into(),
            Candidate::Model(model) => model.name(),
        }
    }

    fn policy(&self) -> Box<dyn Policy + Send> {
        match self {
            Candidate::Hover => Box::new(Hover),
            Candidate::Rule(m) => Box::new(RulePolicy::new(*m)),
            Candidate::Model(model) => model.make(),
        }
    }
}

/// Holds every herder still.
struct Hover;

impl Policy for Hover {
    fn reset(&mut self, _world: &World, _seed: u64) {}
    fn act(&mut self, _world: &World, _herder: usize) -> [f64; 3] {
        [0.0; 3]
    }
}

/// One candidate in one scenario.
#[derive(Clone, Debug, PartialEq)]
pub struct AuditRow {
    /// The scenario.
    pub draw: Draw,
    /// The candidate's label.
    pub policy: String,
    /// Episodes flown.
    pub episodes: usize,
    /// Share of episodes that ended with every target in the goal.
    pub success_rate: f64,
    /// Mean steps of the successful episodes.
    pub mean_steps: Option<f64>,
    /// Mean discounted return of whole episodes under the learner's reward (herder 0).
    pub mean_return: f64,
    /// Its standard deviation over episodes.
    pub return_std: f64,
}

/// `draw` as the audit flies it under `config` (test noise on, the run's step limit) and the
/// learner's reward for it at the run's gamma.
pub fn audited_setup(config: &TrainConfig, draw: Draw) -> (Scenario, LearnerReward) {
    let gamma = f64::from(config.ddpg.gamma);
    let scenario = training_scenario(
        draw,
        config.training.episode_step_limit,
        true,
        &config.reward,
        gamma,
    );
    let reward = LearnerReward::new(&config.reward, gamma, &scenario);
    (scenario, reward)
}

/// One episode: success, steps, discounted learner return of herder 0.
fn episode(config: &TrainConfig, draw: Draw, candidate: &Candidate, seed: u64) -> (bool, u64, f64) {
    let gamma = f64::from(config.ddpg.gamma);
    let (scenario, mut reward) = audited_setup(config, draw);
    let mut env = Env::new(scenario).expect("audit validated every scenario");
    let mut policy = candidate.policy();
    env.reset(seed);
    policy.reset(env.observation(), seed);
    reward.start(&mut env);
    let (mut velocities, mut rewards) = (Vec::new(), Vec::new());
    let (mut total, mut discount) = (0.0, 1.0);
    loop {
        act_all(policy.as_mut(), env.observation(), &mut velocities);
        let out = env.step(&velocities).expect("one action per herder");
        reward.step(&out, &env, &velocities, &mut rewards);
        total += discount * f64::from(rewards[0]);
        discount *= gamma;
        if out.terminated || out.truncated {
            return (out.success, env.info().steps, total);
        }
    }
}

/// Fly every candidate in every scenario for `episodes` episodes with seeds `seed_base + k`
/// (the same seeds for every candidate), in parallel on the current rayon pool.
///
/// # Errors
/// [`ScenarioError`] naming the field when a scenario cannot be flown (no targets, say);
/// nothing is flown then.
pub fn audit(
    config: &TrainConfig,
    draws: &[Draw],
    candidates: &[Candidate],
    episodes: usize,
    seed_base: u64,
) -> Result<Vec<AuditRow>, ScenarioError> {
    let gamma = f64::from(config.ddpg.gamma);
    for draw in draws {
        let step_limit = config.training.episode_step_limit;
        training_scenario(*draw, step_limit, true, &config.reward, gamma).validate()?;
    }
    let jobs: Vec<(usize, usize, u64)> = (0..draws.len())
        .flat_map(|d| {
            (0..candidates.len())
                .flat_map(move |c| (0..episodes as u64).map(move |k| (d, c, seed_base + k)))
        })
        .collect();
    let results: Vec<(bool, u64, f64)> = jobs
        .par_iter()
        .map(|&(d, c, seed)| episode(config, draws[d], &candidates[c], seed))
        .collect();
    let mut rows = Vec::new();
    for (d, draw) in draws.iter().enumerate() {
        for (c, candidate) in candidates.iter().enumerate() {
            let runs: Vec<&(bool, u64, f64)> = jobs
                .iter()
                .zip(&results)
                .filter(|((jd, jc, _), _)| *jd == d && *jc == c)
                .map(|(_, r)| r)
                .collect();
            let n = runs.len().max(1) as f64;
            let successes: Vec<f64> = runs.iter().filter(|r| r.0).map(|r| r.1 as f64).collect();
            let mean_return = runs.iter().map(|r| r.2).sum::<f64>() / n;
            let var = runs
                .iter()
                .map(|r| (r.2 - mean_return).powi(2))
                .sum::<f64>()
                / n;
            rows.push(AuditRow {
                draw: *draw,
                policy: candidate.name(),
                episodes: runs.len(),
                success_rate: successes.len() as f64 / n,
                mean_steps: (!successes.is_empty())
                    .then(|| successes.iter().sum::<f64>() / successes.len() as f64),
                mean_return,
                return_std: var.sqrt(),
            });
        }
    }
    Ok(rows)
}

/// The gate's verdict.
#[derive(Clone, Debug, PartialEq)]
pub struct GateReport {
    /// Every check held.
    pub passed: bool,
    /// What failed, one line each.
    pub problems: Vec<String>,
}

/// Check the audit's rows (see the [module docs](self)); rows of a model are not judged.
pub fn gate(rows: &[AuditRow]) -> GateReport {
    let mut problems = Vec::new();
    let mut draws: Vec<Draw> = Vec::new();
    for r in rows {
        if !draws.contains(&r.draw) {
            draws.push(r.draw);
        }
    }
    let is_rule = |r: &AuditRow| r.policy.parse::<Method>().is_ok();
    for draw in draws {
        let here: Vec<&AuditRow> = rows.iter().filter(|r| r.draw == draw).collect();
        let label = draw_label(draw);
        let hover = here.iter().find(|r| r.policy == "hover");
        let succeeding: Vec<&AuditRow> = here
            .iter()
            .copied()
            .filter(|r| is_rule(r) && r.success_rate >= SUCCESS_SHARE)
            .collect();
        if let Some(h) = hover {
            for r in &succeeding {
                if r.mean_return <= h.mean_return {
                    problems.push(format!(
                        "{label}: {} ({:.0} % success) returns {:.2}, not more than hovering's {:.2}",
                        r.policy,
                        100.0 * r.success_rate,
                        r.mean_return,
                        h.mean_return
                    ));
                }
            }
        }
        let always: Vec<&AuditRow> = succeeding
            .iter()
            .copied()
            .filter(|r| r.success_rate >= 1.0)
            .collect();
        for a in &always {
            for b in &always {
                let (Some(ta), Some(tb)) = (a.mean_steps, b.mean_steps) else {
                    continue;
                };
                if ta < tb * (1.0 - TIME_MARGIN) && a.mean_return <= b.mean_return {
                    problems.push(format!(
                        "{label}: {} finishes in {ta:.0} steps and {} in {tb:.0}, but their returns are {:.2} and {:.2}",
                        a.policy, b.policy, a.mean_return, b.mean_return
                    ));
                }
            }
        }
    }
    GateReport {
        passed: problems.is_empty(),
        problems,
    }
}

fn draw_label(draw: Draw) -> String {
    let task = skyherd_sim::task::task_name(draw.task);
    let m = if draw.herders == 0 {
        "adaptive".to_string()
    } else {
        draw.herders.to_string()
    };
    format!("{task} N={} M={m}", draw.targets)
}

/// The audit as a Markdown table.
pub fn markdown(rows: &[AuditRow]) -> String {
    let mut out = String::from(
        "| scenario | policy | episodes | success | steps (successes) | discounted return | std |\n|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let steps = r.mean_steps.map_or("-".into(), |s| format!("{s:.0}"));
        let _ = writeln!(
            out,
            "| {} | {} | {} | {:.0} % | {steps} | {:.2} | {:.2} |",
            draw_label(r.draw),
            r.policy,
            r.episodes,
            100.0 * r.success_rate,
            r.mean_return,
            r.return_std
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_model::Task;

    fn row(policy: &str, success_rate: f64, steps: Option<f64>, mean_return: f64) -> AuditRow {
        AuditRow {
            draw: Draw::paper(Task::Driving, 4, 4),
            policy: policy.into(),
            episodes: 8,
            success_rate,
            mean_steps: steps,
            mean_return,
            return_std: 1.0,
        }
    }

    #[test]
    fn the_gate_wants_successful_rules_above_hovering_and_ranked_by_time() {
        let good = [
            row("hover", 0.0, None, -90.0),
            row("lama", 1.0, Some(200.0), -60.0),
            row("farthest", 1.0, Some(100.0), -40.0),
            row("ctrl", 0.2, Some(500.0), -95.0), // fails too often to be judged
        ];
        assert!(gate(&good).passed, "{:?}", gate(&good).problems);

        let hover_wins = [
            row("hover", 0.0, None, -20.0),
            row("lama", 1.0, Some(200.0), -60.0),
        ];
        let report = gate(&hover_wins);
        assert!(!report.passed);
        assert!(report.problems[0].contains("lama") && report.problems[0].contains("hovering"));

        let misranked = [
            row("hover", 0.0, None, -90.0),
            row("lama", 1.0, Some(200.0), -40.0),
            row("farthest", 1.0, Some(100.0), -60.0),
        ];
        let report = gate(&misranked);
        assert_eq!(report.problems.len(), 1, "{:?}", report.problems);
        assert!(report.problems[0].contains("farthest finishes in 100"));
    }

    #[test]
    fn the_audit_is_seeded_and_every_candidate_gets_the_same_episodes() {
        let mut config = TrainConfig::default();
        config.training.episode_step_limit = 60;
        let draws = [Draw::paper(Task::Driving, 3, 2)];
        let candidates = [Candidate::Hover, Candidate::Rule(Method::Lama)];
        let a = audit(&config, &draws, &candidates, 2, 11).unwrap();
        let b = audit(&config, &draws, &candidates, 2, 11).unwrap();
        let empty = [Draw::paper(Task::Driving, 0, 2)];
        let e = audit(&config, &empty, &candidates, 1, 11).unwrap_err();
        assert!(e.to_string().contains("targets"), "{e}");
        assert_eq!(a, b);
        assert_eq!(a.len(), 2);
        assert!(a.iter().all(|r| r.episodes == 2));
        assert_ne!(a[0].mean_return, a[1].mean_return);
        let table = markdown(&a);
        assert!(table.contains("| driving N=3 M=2 | hover | 2 |"), "{table}");
    }
}
