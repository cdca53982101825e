//! The paper's evaluation protocol: sweep ⟨task, method, M, N⟩, a fixed set of seeded episodes
//! per configuration with the scenario's test-time noise, and the metrics of Section V-A.
//!
//! Metrics per configuration: success rate; over the successful episodes, mean completion time,
//! mean total herder path length and mean ratio of the time to its lower bound
//! ([`crate::task::lower_bound_time`]: the farthest target's distance to the goal edge at 3 m/s).
//! Episode seeds depend on the task, N, the M setting and the episode index but not on the
//! method, so every method faces the same episodes.

use std::sync::Arc;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use skyherd_model::Task;
use thiserror::Error;

use crate::env::{Env, EnvError, EpisodeSummary, run_episode};
use crate::policy::PolicyFactory;
use crate::scenario::{HerderCount, Scenario, ScenarioError};
use crate::task::task_name;

/// One point of the sweep.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct EvalConfig {
    /// Task.
    #[serde(with = "crate::task::task_serde")]
    pub task: Task,
    /// Method name (a [`PolicyFactory::name`]).
    pub method: String,
    /// Herder setting.
    pub herders: HerderSetting,
    /// N.
    pub targets: usize,
}

/// [`HerderCount`] as it appears in reports: `"1"`, `"4"`, `"adaptive"`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(into = "String", try_from = "String")]
pub struct HerderSetting(pub HerderCount);

impl From<HerderSetting> for String {
    fn from(h: HerderSetting) -> String {
        h.0.to_string()
    }
}

impl TryFrom<String> for HerderSetting {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse().map(HerderSetting)
    }
}

/// What to sweep.
#[derive(Clone)]
pub struct SweepSpec {
    /// Tasks (each uses its paper preset).
    pub tasks: Vec<Task>,
    /// Methods.
    pub methods: Vec<Arc<dyn PolicyFactory>>,
    /// Herder settings.
    pub herders: Vec<HerderCount>,
    /// Target counts.
    pub targets: Vec<usize>,
    /// Episodes per configuration.
    pub episodes: usize,
    /// Base of every episode seed.
    pub base_seed: u64,
    /// Override of the presets' step limit.
    pub step_limit: Option<u64>,
    /// `(i, n)`: run only configurations whose index is `i` modulo `n`.
    pub shard: (usize, usize),
    /// Herder dynamics and wind for every configuration (`None`: the presets' instant
    /// herders, the paper's protocol).
    pub dynamics: Option<crate::scenario::HerderDynamics>,
}

impl SweepSpec {
    /// The paper's sweep: both tasks, N = 1, 2, 4, ..., 1024, M = 1, 4, adaptive, 100 episodes.
    pub fn paper(methods: Vec<Arc<dyn PolicyFactory>>) -> Self {
        SweepSpec {
            tasks: Task::ALL.to_vec(),
            methods,
            herders: vec![
                HerderCount::Fixed(1),
                HerderCount::Fixed(4),
                HerderCount::Adaptive,
            ],
            targets: (0..=10).map(|k| 1usize << k).collect(),
            episodes: 100,
            base_seed: 0,
            step_limit: None,
            shard: (0, 1),
            dynamics: None,
        }
    }

    /// The configurations of this shard, in sweep order (task, M setting, N, method).
    pub fn configs(&self) -> Vec<EvalConfig> {
        let mut out = Vec::new();
        for &task in &self.tasks {
            for &herders in &self.herders {
                for &targets in &self.targets {
                    for m in &self.methods {
                        out.push(EvalConfig {
                            task,
                            method: m.name(),
                            herders: HerderSetting(herders),
                            targets,
                        });
                    }
                }
            }
        }
        let (i, n) = self.shard;
        out.into_iter()
            .enumerate()
            .filter(|(k, _)| n > 0 && k % n == i)
            .map(|(_, c)| c)
            .collect()
    }

    /// The scenario of one configuration.
    pub fn scenario(&self, config: &EvalConfig) -> Scenario {
        let mut s = Scenario::paper(config.task);
        s.name = format!("{}-{}", task_name(config.task), config.method);
        s.targets = config.targets;
        s.herders = config.herders.0;
        if let Some(limit) = self.step_limit {
            s.step_limit = limit;
        }
        s.dynamics = self.dynamics;
        s
    }
}

/// Seed of episode `episode` of a configuration; the method does not enter.
pub fn episode_seed(
    base: u64,
    task: Task,
    targets: usize,
    herders: HerderCount,
    episode: usize,
) -> u64 {
    let h = match herders {
        HerderCount::Fixed(m) => m as u64,
        HerderCount::Adaptive => 0,
    };
    let mut x = base ^ 0x5eed_5eed_5eed_5eed;
    for v in [task.index() as u64, targets as u64, h, episode as u64] {
        x = splitmix(x ^ v);
    }
    x
}

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Aggregated result of one configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConfigResult {
    /// The configuration.
    #[serde(flatten)]
    pub config: EvalConfig,
    /// M actually used.
    pub herder_count: usize,
    /// Episodes run.
    pub episodes: usize,
    /// Step limit in force.
    pub step_limit: u64,
    /// Successful episodes.
    pub successes: usize,
    /// Episodes ended by something leaving the arena.
    pub left_area: usize,
    /// `successes / episodes`.
    pub success_rate: f64,
    /// Mean completion time of successful episodes, seconds.
    pub mean_time_s: Option<f64>,
    /// Mean total herder path length of successful episodes, metres.
    pub mean_path_m: Option<f64>,
    /// Mean of time / lower bound over successful episodes.
    pub mean_time_ratio: Option<f64>,
    /// Mean total herder path length of all episodes, metres.
    pub mean_path_all_m: f64,
    /// The closest two herders came in any episode (3-D, m); `None` with one herder (and in
    /// results written before it was measured).
    #[serde(default)]
    pub min_separation_m: Option<f64>,
    /// Episodes in which two herders came closer than the arena's breach distance
    /// (`Area::breach_distance_m`: 0.5 m in a room, 3 m in the paper's arena).
    #[serde(default)]
    pub separation_breach_episodes: usize,
}

/// Why a sweep failed.
#[derive(Debug, Error)]
pub enum EvalError {
    /// A configuration made an invalid scenario.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// An episode failed to step.
    #[error(transparent)]
    Env(#[from] EnvError),
    /// A method name is not in the spec.
    #[error("no policy factory named `{0}`")]
    UnknownMethod(String),
    /// The spec is unusable.
    #[error("bad sweep: {0}")]
    Spec(String),
}

/// Aggregates episode summaries into the metrics.
pub fn summarize(config: EvalConfig, scenario: &Scenario, eps: &[EpisodeSummary]) -> ConfigResult {
    let ok: Vec<&EpisodeSummary> = eps.iter().filter(|e| e.success).collect();
    let mean = |f: &dyn Fn(&EpisodeSummary) -> f64| {
        (!ok.is_empty()).then(|| ok.iter().map(|e| f(e)).sum::<f64>() / ok.len() as f64)
    };
    ConfigResult {
        herder_count: scenario.herder_count(),
        episodes: eps.len(),
        step_limit: scenario.step_limit,
        successes: ok.len(),
        left_area: eps.iter().filter(|e| e.left_area).count(),
        success_rate: if eps.is_empty() {
            0.0
        } else {
            ok.len() as f64 / eps.len() as f64
        },
        mean_time_s: mean(&|e| e.time_s),
        mean_path_m: mean(&|e| e.path_length),
        mean_time_ratio: mean(&|e| e.time_s / e.lower_bound_s.max(f64::MIN_POSITIVE)),
        mean_path_all_m: if eps.is_empty() {
            0.0
        } else {
            eps.iter().map(|e| e.path_length).sum::<f64>() / eps.len() as f64
        },
        min_separation_m: Some(
            eps.iter()
                .map(|e| e.min_separation_m)
                .fold(f64::INFINITY, f64::min),
        )
        .filter(|d| d.is_finite()),
        separation_breach_episodes: eps
            .iter()
            .filter(|e| e.min_separation_m < scenario.area.breach_distance_m())
            .count(),
        config,
    }
}

/// Runs the sweep on all cores; `progress` is called once per finished episode.
pub fn run_sweep(
    spec: &SweepSpec,
    progress: &(dyn Fn() + Sync),
) -> Result<Vec<ConfigResult>, EvalError> {
    if spec.shard.1 == 0 || spec.shard.0 >= spec.shard.1 {
        return Err(EvalError::Spec(format!(
            "shard {}/{} is not i/n with i < n",
            spec.shard.0, spec.shard.1
        )));
    }
    let configs = spec.configs();
    let scenarios: Vec<Scenario> = configs.iter().map(|c| spec.scenario(c)).collect();
    for s in &scenarios {
        s.validate()?;
    }
    let factories: Vec<Arc<dyn PolicyFactory>> = configs
        .iter()
        .map(|c| {
            spec.methods
                .iter()
                .find(|m| m.name() == c.method)
                .cloned()
                .ok_or_else(|| EvalError::UnknownMethod(c.method.clone()))
        })
        .collect::<Result<_, _>>()?;
    // Biggest flocks first so that the long episodes do not straggle at the end.
    let mut jobs: Vec<(usize, usize)> = (0..configs.len())
        .flat_map(|c| (0..spec.episodes).map(move |e| (c, e)))
        .collect();
    jobs.sort_by_key(|&(c, e)| (std::cmp::Reverse(configs[c].targets), c, e));
    let done: Vec<(usize, usize, EpisodeSummary)> = jobs
        .par_iter()
        .map(|&(c, e)| {
            let cfg = &configs[c];
            let seed = episode_seed(spec.base_seed, cfg.task, cfg.targets, cfg.herders.0, e);
            let mut env = Env::new(scenarios[c].clone())?;
            let mut policy = factories[c].make();
            let summary = run_episode(&mut env, policy.as_mut(), seed, |_, _| {})?;
            progress();
            Ok((c, e, summary))
        })
        .collect::<Result<_, EvalError>>()?;
    let mut per_config: Vec<Vec<Option<EpisodeSummary>>> =
        vec![vec![None; spec.episodes]; configs.len()];
    for (c, e, s) in done {
        per_config[c][e] = Some(s);
    }
    Ok(configs
        .into_iter()
        .zip(per_config)
        .zip(&scenarios)
        .map(|((cfg, eps), s)| {
            let eps: Vec<EpisodeSummary> = eps.into_iter().flatten().collect();
            summarize(cfg, s, &eps)
        })
        .collect())
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(String::new, |x| format!("{x:.digits$}"))
}

/// CSV with a header row.
pub fn to_csv(results: &[ConfigResult]) -> String {
    let mut out = String::from(
        "task,method,herders,herder_count,targets,episodes,step_limit,successes,left_area,success_rate,mean_time_s,mean_path_m,mean_time_ratio,mean_path_all_m,min_separation_m,separation_breach_episodes\n",
    );
    for r in results {
        out.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{:.4},{},{},{},{:.1},{},{}\n",
            task_name(r.config.task),
            r.config.method,
            r.config.herders.0,
            r.herder_count,
            r.config.targets,
            r.episodes,
            r.step_limit,
            r.successes,
            r.left_area,
            r.success_rate,
            opt(r.mean_time_s, 1),
            opt(r.mean_path_m, 1),
            opt(r.mean_time_ratio, 2),
            r.mean_path_all_m,
            opt(r.min_separation_m, 2),
            r.separation_breach_episodes,
        ));
    }
    out
}

/// A markdown table: one row per ⟨task, M setting, N⟩, one column group per method
/// (success %, time s, path m, time ratio); "–" where no episode succeeded.
pub fn to_markdown(results: &[ConfigResult]) -> String {
    let mut methods: Vec<String> = Vec::new();
    for r in results {
        if !methods.contains(&r.config.method) {
            methods.push(r.config.method.clone());
        }
    }
    let mut out = String::from("| task | M | N |");
    for m in &methods {
        out.push_str(&format!(
            " {m} success | {m} time s | {m} path m | {m} ratio |"
        ));
    }
    out.push_str("\n|---|---|---|");
    for _ in &methods {
        out.push_str("---:|---:|---:|---:|");
    }
    out.push('\n');
    let mut rows: Vec<(Task, String, usize, usize)> = Vec::new();
    for r in results {
        let key = (
            r.config.task,
            r.config.herders.0.to_string(),
            r.herder_count,
            r.config.targets,
        );
        if !rows.contains(&key) {
            rows.push(key);
        }
    }
    for (task, setting, m, n) in rows {
        let label = if setting == m.to_string() {
            setting.clone()
        } else {
            format!("{setting} ({m})")
        };
        out.push_str(&format!("| {} | {label} | {n} |", task_name(task)));
        for method in &methods {
            let r = results.iter().find(|r| {
                r.config.task == task
                    && r.config.herders.0.to_string() == setting
                    && r.config.targets == n
                    && &r.config.method == method
            });
            match r {
                Some(r) => out.push_str(&format!(
                    " {:.0}% | {} | {} | {} |",
                    100.0 * r.success_rate,
                    opt(r.mean_time_s, 0).or_dash(),
                    opt(r.mean_path_m, 0).or_dash(),
                    opt(r.mean_time_ratio, 2).or_dash(),
                )),
                None => out.push_str(" | | | |"),
            }
        }
        out.push('\n');
    }
    out
}

/// How one method fared against the best of the others in one configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison<'a> {
    /// The method under test.
    pub method: &'a ConfigResult,
    /// The best other method here: highest success rate, then lowest mean time ratio.
    pub best_other: Option<&'a ConfigResult>,
}

impl Comparison<'_> {
    /// Whether both methods solved at least one episode, so times and paths compare.
    pub fn both_succeed(&self) -> bool {
        self.method.successes > 0 && self.best_other.is_some_and(|b| b.successes > 0)
    }

    /// Mean time ratio of the method over the best other's (< 1: faster), where both succeed.
    pub fn time_vs_best(&self) -> Option<f64> {
        let b = self.best_other?;
        Some(self.method.mean_time_s? / b.mean_time_s?)
    }

    /// Mean path length of the method over the best other's (< 1: shorter), where both succeed.
    pub fn path_vs_best(&self) -> Option<f64> {
        let b = self.best_other?;
        Some(self.method.mean_path_m? / b.mean_path_m?)
    }
}

/// For every configuration `method` ran, the best of the other methods in the same
/// ⟨task, M setting, N⟩ (by success rate, then time ratio).
pub fn compare<'a>(results: &'a [ConfigResult], method: &str) -> Vec<Comparison<'a>> {
    let rank = |r: &ConfigResult| (r.success_rate, -r.mean_time_ratio.unwrap_or(f64::INFINITY));
    results
        .iter()
        .filter(|r| r.config.method == method)
        .map(|m| {
            let best_other = results
                .iter()
                .filter(|o| {
                    o.config.method != method
                        && o.config.task == m.config.task
                        && o.config.herders == m.config.herders
                        && o.config.targets == m.config.targets
                })
                .max_by(|a, b| {
                    rank(a)
                        .partial_cmp(&rank(b))
                        .unwrap_or(std::cmp::Ordering::Equal)
                });
            Comparison {
                method: m,
                best_other,
            }
        })
        .collect()
}

/// A markdown table of [`compare`]: the method beside the best other method per configuration,
/// with time and path relative to it where both succeed.
pub fn comparison_markdown(results: &[ConfigResult], method: &str) -> String {
    let mut out = format!(
        "| task | M | N | {method} success | {method} time s | {method} path m | {method} ratio | best other | its success | its time s | its path m | its ratio | time vs best | path vs best |\n|---|---|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|\n"
    );
    let cells = |r: &ConfigResult| {
        format!(
            "{:.0}% | {} | {} | {}",
            100.0 * r.success_rate,
            opt(r.mean_time_s, 0).or_dash(),
            opt(r.mean_path_m, 0).or_dash(),
            opt(r.mean_time_ratio, 2).or_dash(),
        )
    };
    for c in compare(results, method) {
        let m = c.method;
        let label = if m.config.herders.0.to_string() == m.herder_count.to_string() {
            m.herder_count.to_string()
        } else {
            format!("{} ({})", m.config.herders.0, m.herder_count)
        };
        let other = c.best_other.map_or_else(
            || "– | | | | ".to_owned(),
            |b| format!("{} | {}", b.config.method, cells(b)),
        );
        out.push_str(&format!(
            "| {} | {label} | {} | {} | {other} | {} | {} |\n",
            task_name(m.config.task),
            m.config.targets,
            cells(m),
            opt(c.time_vs_best(), 2).or_dash(),
            opt(c.path_vs_best(), 2).or_dash(),
        ));
    }
    out
}

trait OrDash {
    fn or_dash(self) -> String;
}

impl OrDash for String {
    fn or_dash(self) -> String {
        if self.is_empty() {
            "–".to_owned()
        } else {
            self
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::baseline::Method;

    #[test]
    fn seeds_do_not_depend_on_the_method_and_differ_elsewhere() {
        let a = episode_seed(0, Task::Driving, 16, HerderCount::Fixed(4), 3);
        assert_eq!(
            a,
            episode_seed(0, Task::Driving, 16, HerderCount::Fixed(4), 3)
        );
        assert_ne!(
            a,
            episode_seed(0, Task::Driving, 16, HerderCount::Fixed(4), 4)
        );
        assert_ne!(
            a,
            episode_seed(0, Task::Collecting, 16, HerderCount::Fixed(4), 3)
        );
        assert_ne!(
            a,
            episode_seed(0, Task::Driving, 16, HerderCount::Adaptive, 3)
        );
    }

    #[test]
    fn shards_partition_the_sweep() {
        let mut spec = SweepSpec::paper(vec![Arc::new(Method::Lama), Arc::new(Method::Strombom)]);
        let all = spec.configs();
        assert_eq!(all.len(), 2 * 3 * 11 * 2);
        let mut union = Vec::new();
        for i in 0..3 {
            spec.shard = (i, 3);
            union.extend(spec.configs());
        }
        assert_eq!(union.len(), all.len());
        for c in &all {
            assert!(union.contains(c));
        }
    }

    #[test]
    fn comparison_picks_the_most_successful_then_fastest_other_method() {
        let s = Scenario::paper_drive();
        let result = |method: &str, successes: usize, time_s: f64, path_m: f64| {
            let ep = |i: usize| EpisodeSummary {
                seed: 0,
                success: i < successes,
                left_area: false,
                steps: time_s as u64,
                time_s,
                path_length: path_m,
                lower_bound_s: 50.0,
                return_total: 0.0,
                paper_return_total: 0.0,
                min_separation_m: f64::INFINITY,
            };
            let eps: Vec<EpisodeSummary> = (0..4).map(ep).collect();
            let cfg = EvalConfig {
                task: Task::Driving,
                method: method.into(),
                herders: HerderSetting(HerderCount::Fixed(4)),
                targets: 16,
            };
            summarize(cfg, &s, &eps)
        };
        let results = [
            result("model", 4, 100.0, 1000.0),
            result("slow", 4, 300.0, 900.0),
            result("fast", 4, 200.0, 2000.0),
            result("faster-but-flaky", 2, 50.0, 100.0),
        ];
        let c = compare(&results, "model");
        assert_eq!(c.len(), 1);
        assert_eq!(
            c[0].best_other.map(|b| b.config.method.as_str()),
            Some("fast")
        );
        assert!(c[0].both_succeed());
        assert_eq!(c[0].time_vs_best(), Some(0.5));
        assert_eq!(c[0].path_vs_best(), Some(0.5));
        let md = comparison_markdown(&results, "model");
        assert!(
            md.contains("| driving | 4 | 16 | 100% | 100 | 1000 | 2.00 | fast | 100% | 200 | 2000 | 4.00 | 0.50 | 0.50 |"),
            "{md}"
        );
    }

    #[test]
    fn summarize_counts_only_successes_for_time_and_path() {
        let s = Scenario::paper_drive();
        let ep = |success, time_s, path_length| EpisodeSummary {
            seed: 0,
            success,
            left_area: !success,
            steps: time_s as u64,
            time_s,
            path_length,
            lower_bound_s: 50.0,
            return_total: 0.0,
            paper_return_total: 0.0,
            min_separation_m: 2.0 + time_s / 1000.0,
        };
        let cfg = EvalConfig {
            task: Task::Driving,
            method: "x".into(),
            herders: HerderSetting(HerderCount::Fixed(4)),
            targets: 16,
        };
        let r = summarize(
            cfg,
            &s,
            &[
                ep(true, 100.0, 1000.0),
                ep(true, 200.0, 3000.0),
                ep(false, 7.0, 5.0),
            ],
        );
        assert!((r.success_rate - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(r.mean_time_s, Some(150.0));
        assert_eq!(r.mean_path_m, Some(2000.0));
        assert_eq!(r.mean_time_ratio, Some(3.0));
        assert_eq!(r.left_area, 1);
        // Closest approach over all episodes (2.007 m); the paper's arena breaches below 3 m.
        assert_eq!(r.min_separation_m, Some(2.007));
        assert_eq!(r.separation_breach_episodes, 3);
        let md = to_markdown(std::slice::from_ref(&r));
        assert!(
            md.contains("| driving | 4 | 16 | 67% | 150 | 2000 | 3.00 |"),
            "{md}"
        );
        let csv = to_csv(&[r]);
        assert!(
            csv.lines()
                .nth(1)
                .unwrap()
                .starts_with("driving,x,4,4,16,3,1500,2,1,0.6667,150.0,2000.0,3.00")
        );
        assert!(csv.lines().nth(1).unwrap().ends_with(",2.01,3"), "{csv}");
    }
}
