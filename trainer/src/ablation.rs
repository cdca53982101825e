//! The multi-task ablation the paper implies: MTDDPG (both tasks through shared hidden
//! layers) against single-task DDPG (one task per run, so the hidden layers learn from that
//! task alone), the same layers, hyper-parameters and environment steps per task.
//!
//! Each run is one process, `skyherd-trainer train --config C --arm ARM --seed S`, writing
//! `<output_dir>/<arm>-seed<S>/eval.csv` (held-out success per scenario at every evaluation);
//! `scripts/ablation.sh` runs them all locally, and any scheduler can spread them over
//! machines. [`report`] reads the runs back: per task, the learning curve of each arm (mean
//! success over the task's scenarios against the environment steps that task had, mean and
//! spread over seeds), the steps to reach [`TARGET_SUCCESS`], the area under the curve, and a
//! verdict.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use plotters::prelude::*;
use skyherd_model::Task;
use skyherd_sim::task::{parse_task, task_name};

use crate::report::ReportError;

/// Success that counts as "learned" for the steps-to-target measure.
pub const TARGET_SUCCESS: f64 = 0.9;

/// One evaluation of one run for one task: the mean success over that task's scenarios.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CurvePoint {
    /// Environment steps the task had when evaluated.
    pub task_env_steps: u64,
    /// Mean held-out success over the task's scenarios.
    pub success: f64,
}

/// Parses `eval.csv` text into one curve per task.
///
/// # Errors
/// [`ReportError::Parse`] naming the line that is not a row of [`crate::train::EVAL_CSV_HEADER`].
pub fn parse_eval_csv(text: &str) -> Result<Vec<(Task, Vec<CurvePoint>)>, ReportError> {
    let mut rows: Vec<(Task, u64, f64)> = Vec::new();
    for (k, line) in text.lines().enumerate().skip(1) {
        if line.trim().is_empty() {
            continue;
        }
        let bad = || ReportError::Parse(format!("eval.csv line {}: {line:?}", k + 1));
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 9 {
            return Err(bad());
        }
        let task = parse_task(f[2]).ok_or_else(bad)?;
        let steps: u64 = f[1].parse().map_err(|_| bad())?;
        let success: f64 = f[6].parse().map_err(|_| bad())?;
        rows.push((task, steps, success));
    }
    let mut out = Vec::new();
    for task in Task::ALL {
        let mut steps: Vec<u64> = rows.iter().filter(|r| r.0 == task).map(|r| r.1).collect();
        steps.sort_unstable();
        steps.dedup();
        // Scenarios of one evaluation share its step count: average them.
        let points: Vec<CurvePoint> = steps
            .into_iter()
            .map(|at| {
                let here: Vec<f64> = rows
                    .iter()
                    .filter(|r| r.0 == task && r.1 == at)
                    .map(|r| r.2)
                    .collect();
                CurvePoint {
                    task_env_steps: at,
                    success: mean(&here),
                }
            })
            .collect();
        if !points.is_empty() {
            out.push((task, points));
        }
    }
    Ok(out)
}

/// The first step count at which the curve reaches `target`, if it does.
pub fn steps_to(curve: &[CurvePoint], target: f64) -> Option<u64> {
    curve
        .iter()
        .find(|p| p.success >= target)
        .map(|p| p.task_env_steps)
}

/// The area under the curve up to `horizon` steps, as a fraction of `horizon` (trapezoids,
/// success 0 before the first evaluation, the last value held to the horizon).
pub fn area_under(curve: &[CurvePoint], horizon: u64) -> f64 {
    if horizon == 0 {
        return 0.0;
    }
    let mut area = 0.0;
    let (mut x0, mut y0) = (0.0_f64, 0.0_f64);
    for p in curve.iter().filter(|p| p.task_env_steps <= horizon) {
        let x = p.task_env_steps as f64;
        area += (x - x0) * (y0 + p.success) / 2.0;
        (x0, y0) = (x, p.success);
    }
    area += (horizon as f64 - x0).max(0.0) * y0;
    area / horizon as f64
}

/// One arm's runs for one task.
#[derive(Clone, Debug, PartialEq)]
pub struct ArmCurves {
    /// `mtddpg` or `single`.
    pub arm: String,
    /// The task.
    pub task: Task,
    /// `(seed, curve)` per run.
    pub runs: Vec<(u64, Vec<CurvePoint>)>,
}

/// Reads every `<arm>-seed<S>/eval.csv` below `dir`.
///
/// # Errors
/// When `dir` cannot be listed or an `eval.csv` cannot be read or parsed.
pub fn read_runs(dir: &Path) -> Result<Vec<ArmCurves>, ReportError> {
    let mut out: Vec<ArmCurves> = Vec::new();
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for path in entries {
        let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
            continue;
        };
        let Some((arm, seed)) = name.rsplit_once("-seed") else {
            continue;
        };
        let Ok(seed) = seed.parse::<u64>() else {
            continue;
        };
        let csv = path.join("eval.csv");
        if !csv.exists() {
            continue;
        }
        let arm = if arm.starts_with("single") {
            "single"
        } else {
            arm
        };
        for (task, curve) in parse_eval_csv(&std::fs::read_to_string(&csv)?)? {
            match out.iter_mut().find(|a| a.arm == arm && a.task == task) {
                Some(a) => a.runs.push((seed, curve)),
                None => out.push(ArmCurves {
                    arm: arm.to_string(),
                    task,
                    runs: vec![(seed, curve)],
                }),
            }
        }
    }
    Ok(out)
}

/// One arm's summary for one task.
#[derive(Clone, Debug, PartialEq)]
pub struct ArmSummary {
    /// The arm.
    pub arm: String,
    /// The task.
    pub task: Task,
    /// Runs (seeds).
    pub seeds: usize,
    /// Steps to [`TARGET_SUCCESS`] per seed (`None`: not reached).
    pub steps_to_target: Vec<Option<u64>>,
    /// Area under the curve per seed (fraction of the horizon).
    pub auc: Vec<f64>,
    /// Final success per seed.
    pub final_success: Vec<f64>,
}

/// Summaries of every arm and task, each task up to its horizon: `horizon` task steps, or
/// when `None` the last evaluation that every run of that task reached (so an unfinished run
/// shortens the comparison instead of skewing it).
pub fn summarize(curves: &[ArmCurves], horizon: Option<u64>) -> Vec<(u64, ArmSummary)> {
    let task_horizon = |task: Task| {
        horizon.unwrap_or_else(|| {
            curves
                .iter()
                .filter(|a| a.task == task)
                .flat_map(|a| a.runs.iter())
                .filter_map(|(_, c)| c.last().map(|p| p.task_env_steps))
                .min()
                .unwrap_or(0)
        })
    };
    curves
        .iter()
        .map(|a| {
            let horizon = task_horizon(a.task);
            let summary = ArmSummary {
                arm: a.arm.clone(),
                task: a.task,
                seeds: a.runs.len(),
                steps_to_target: a
                    .runs
                    .iter()
                    .map(|(_, c)| steps_to(c, TARGET_SUCCESS).filter(|&steps| steps <= horizon))
                    .collect(),
                auc: a.runs.iter().map(|(_, c)| area_under(c, horizon)).collect(),
                final_success: a
                    .runs
                    .iter()
                    .map(|(_, c)| {
                        c.iter()
                            .rev()
                            .find(|p| p.task_env_steps <= horizon)
                            .map_or(0.0, |p| p.success)
                    })
                    .collect(),
            };
            (horizon, summary)
        })
        .collect()
}

fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// The verdict for one task: does sharing the hidden layers learn faster here?
pub fn verdict(multi: &ArmSummary, single: &ArmSummary) -> String {
    let (m, s) = (mean(&multi.auc), mean(&single.auc));
    if multi.seeds < 2 || single.seeds < 2 {
        return format!(
            "{}: AUC {m:.3} MTDDPG vs {s:.3} single-task from one seed per arm: no verdict (seeds decide, and one is not enough)",
            task_name(multi.task)
        );
    }
    let (m_lo, m_hi) = min_max(&multi.auc);
    let (s_lo, s_hi) = min_max(&single.auc);
    let task = task_name(multi.task);
    if m_lo > s_hi {
        format!(
            "{task}: MTDDPG learns faster (AUC {m:.3} vs {s:.3}; every MTDDPG seed above every single-task seed): the claim holds here"
        )
    } else if s_lo > m_hi {
        format!(
            "{task}: single-task DDPG learns faster (AUC {s:.3} vs {m:.3}, no seed overlap): the claim does not hold here"
        )
    } else {
        format!(
            "{task}: no clear difference (AUC {m:.3} MTDDPG vs {s:.3} single-task; the seeds overlap): the claim is not shown here"
        )
    }
}

fn min_max(v: &[f64]) -> (f64, f64) {
    v.iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(*x), hi.max(*x))
        })
}

/// The report as Markdown: the table and the verdicts.
pub fn markdown(summaries: &[(u64, ArmSummary)]) -> String {
    let mut out = format!(
        "Success is the mean held-out success over the task's scenarios; each task is compared up to the last evaluation every one of its runs reached.\n\n| task | up to (task steps) | arm | seeds | steps to {:.0} % (per seed) | AUC mean (min-max) | final success mean |\n|---|---|---|---|---|---|---|\n",
        100.0 * TARGET_SUCCESS
    );
    for (horizon, s) in summaries {
        let steps: Vec<String> = s
            .steps_to_target
            .iter()
            .map(|x| x.map_or("-".into(), |v| v.to_string()))
            .collect();
        let (lo, hi) = min_max(&s.auc);
        let _ = writeln!(
            out,
            "| {} | {horizon} | {} | {} | {} | {:.3} ({lo:.3}-{hi:.3}) | {:.0} % |",
            task_name(s.task),
            s.arm,
            s.seeds,
            steps.join(", "),
            mean(&s.auc),
            100.0 * mean(&s.final_success)
        );
    }
    out.push('\n');
    for task in Task::ALL {
        let find = |arm: &str| {
            summaries
                .iter()
                .map(|(_, s)| s)
                .find(|s| s.task == task && s.arm == arm)
        };
        if let (Some(m), Some(s)) = (find("mtddpg"), find("single")) {
            let _ = writeln!(out, "- {}", verdict(m, s));
        }
    }
    out
}

/// Draws one task's curves (every seed thin, the mean over seeds thick; MTDDPG blue,
/// single-task red) as PNG and SVG at `stem.png` / `stem.svg`.
///
/// # Errors
/// [`ReportError::Plot`] when drawing fails.
pub fn plot_task(curves: &[ArmCurves], task: Task, stem: &Path) -> Result<(), ReportError> {
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    draw(
        curves,
        task,
        BitMapBackend::new(&png, (900, 500)).into_drawing_area(),
    )?;
    draw(
        curves,
        task,
        SVGBackend::new(&svg, (900, 500)).into_drawing_area(),
    )?;
    Ok(())
}

fn draw<DB: DrawingBackend>(
    curves: &[ArmCurves],
    task: Task,
    root: DrawingArea<DB, plotters::coord::Shift>,
) -> Result<(), ReportError> {
    crate::report::register_font();
    let err = |e: &dyn std::fmt::Display| ReportError::Plot(e.to_string());
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let x_max = curves
        .iter()
        .filter(|a| a.task == task)
        .flat_map(|a| a.runs.iter())
        .filter_map(|(_, c)| c.last().map(|p| p.task_env_steps))
        .max()
        .unwrap_or(1) as f64;
    let mut chart = ChartBuilder::on(&root)
        .margin(12)
        .caption(
            format!(
                "{}: held-out success vs env steps of the task (MTDDPG blue, single-task red)",
                task_name(task)
            ),
            (crate::report::FAMILY, 16),
        )
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(0.0..x_max, 0.0..1.02)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("environment steps of this task")
        .y_desc("success rate")
        .draw()
        .map_err(|e| err(&e))?;
    for arm in curves.iter().filter(|a| a.task == task) {
        let colour = if arm.arm == "mtddpg" { BLUE } else { RED };
        for (_, c) in &arm.runs {
            chart
                .draw_series(LineSeries::new(
                    c.iter().map(|p| (p.task_env_steps as f64, p.success)),
                    colour.mix(0.3),
                ))
                .map_err(|e| err(&e))?;
        }
        // The mean over seeds at the evaluation points of the first run.
        if let Some((_, first)) = arm.runs.first() {
            let mean_curve: Vec<(f64, f64)> = first
                .iter()
                .map(|p| {
                    let at: Vec<f64> = arm
                        .runs
                        .iter()
                        .filter_map(|(_, c)| {
                            c.iter()
                                .find(|q| q.task_env_steps == p.task_env_steps)
                                .map(|q| q.success)
                        })
                        .collect();
                    (p.task_env_steps as f64, mean(&at))
                })
                .collect();
            chart
                .draw_series(LineSeries::new(mean_curve, colour.stroke_width(3)))
                .map_err(|e| err(&e))?;
        }
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// Reads the runs below `runs`, writes `<out>/ablation.md` and the curves; returns the
/// Markdown.
///
/// # Errors
/// When the runs cannot be read or the files cannot be written.
pub fn report(runs: &Path, out: &Path) -> Result<String, ReportError> {
    let curves = read_runs(runs)?;
    std::fs::create_dir_all(out)?;
    let summaries = summarize(&curves, None);
    let text = markdown(&summaries);
    std::fs::write(out.join("ablation.md"), &text)?;
    for task in Task::ALL {
        if curves.iter().any(|a| a.task == task) {
            plot_task(
                &curves,
                task,
                &out.join(format!("curve-{}", task_name(task))),
            )?;
        }
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    const CSV: &str = "env_steps,task_env_steps,task,targets,herders,episodes,success_rate,mean_time_s,mean_time_ratio
100,50,driving,4,4,8,0.5,10,2
100,50,driving,8,4,8,0.25,10,2
100,50,collecting,4,4,8,1,10,2
200,100,driving,4,4,8,1,10,2
200,100,driving,8,4,8,0.8,10,2
";

    #[test]
    fn eval_csv_becomes_one_mean_curve_per_task() {
        let curves = parse_eval_csv(CSV).unwrap();
        assert_eq!(curves.len(), 2);
        let (task, driving) = &curves[0];
        assert_eq!(*task, Task::Driving);
        assert_eq!(
            driving,
            &vec![
                CurvePoint {
                    task_env_steps: 50,
                    success: 0.375
                },
                CurvePoint {
                    task_env_steps: 100,
                    success: 0.9
                },
            ]
        );
        assert_eq!(steps_to(driving, 0.9), Some(100));
        assert_eq!(steps_to(driving, 0.95), None);
        assert!(parse_eval_csv("header\n1,2,grazing,4,4,8,1,1,1").is_err());
    }

    #[test]
    fn the_area_is_a_fraction_of_the_horizon() {
        let always = [CurvePoint {
            task_env_steps: 10,
            success: 1.0,
        }];
        // 0 -> 1 over the first 10 steps, then 1 to 100: 0.5 * 10 + 90 = 95 of 100.
        assert!((area_under(&always, 100) - 0.95).abs() < 1e-12);
        assert_eq!(area_under(&[], 100), 0.0);
    }

    #[test]
    fn the_verdict_needs_the_seeds_to_separate() {
        let summary = |arm: &str, auc: Vec<f64>| ArmSummary {
            arm: arm.into(),
            task: Task::Driving,
            seeds: auc.len(),
            steps_to_target: vec![None; auc.len()],
            final_success: auc.clone(),
            auc,
        };
        let m = summary("mtddpg", vec![0.6, 0.7, 0.65]);
        assert!(
            verdict(&summary("mtddpg", vec![0.9]), &summary("single", vec![0.1]))
                .contains("no verdict")
        );
        assert!(verdict(&m, &summary("single", vec![0.3, 0.4, 0.5])).contains("claim holds"));
        assert!(verdict(&m, &summary("single", vec![0.8, 0.9, 0.85])).contains("does not hold"));
        assert!(verdict(&m, &summary("single", vec![0.5, 0.66, 0.8])).contains("not shown"));
    }
}
