//! The run's CSV log (returns, losses, evaluation metrics) and its learning-curve PNG.
//!
//! The top panel shows the recent training success rate (blue) and the held-out evaluation
//! success rate (red dots), the bottom panel the recent mean learner return per episode
//! (green), against wall time. Text uses the DejaVu Sans font the simulator ships
//! (`sim-harness/assets`), compiled in from there.

use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::Path;

use plotters::prelude::*;
use thiserror::Error;

/// Why the log or the plot could not be written.
#[derive(Debug, Error)]
pub enum ReportError {
    /// File system trouble.
    #[error("log/plot I/O: {0}")]
    Io(#[from] std::io::Error),
    /// The plotting backend failed.
    #[error("plot: {0}")]
    Plot(String),
    /// A file is not in the format it should be (the message names the line).
    #[error("bad file: {0}")]
    Parse(String),
}

/// One line of the CSV log.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LogRow {
    /// `0` warm start, `1` DDPG, `2` evaluation, `3` evolution generation (its held-out check in
    /// the evaluation columns when one ran).
    pub phase: u8,
    /// Wall-clock seconds since the run started.
    pub wall_s: f64,
    /// DDPG environment steps.
    pub env_steps: u64,
    /// Gradient updates (imitation or DDPG).
    pub updates: u64,
    /// Finished training episodes.
    pub episodes: u64,
    /// Mean learner return of recent training episodes.
    pub recent_return: f64,
    /// Success rate of recent training episodes.
    pub recent_success: f64,
    /// Critic TD loss (NaN when not measured).
    pub critic_loss: f64,
    /// Actor loss, or imitation loss in the warm start.
    pub actor_loss: f64,
    /// Mean Q on the batch.
    pub q_mean: f64,
    /// Held-out success rate (NaN unless an evaluation row).
    pub eval_success: f64,
    /// Held-out mean time over lower bound (NaN unless an evaluation row).
    pub eval_time_ratio: f64,
}

impl LogRow {
    /// A held-out evaluation row (phase 2): `score` is (success rate, time ratio); the training
    /// columns are NaN.
    pub fn evaluation(
        wall_s: f64,
        env_steps: u64,
        updates: u64,
        episodes: u64,
        score: (f64, f64),
    ) -> LogRow {
        LogRow {
            phase: 2,
            wall_s,
            env_steps,
            updates,
            episodes,
            recent_return: f64::NAN,
            recent_success: f64::NAN,
            critic_loss: f64::NAN,
            actor_loss: f64::NAN,
            q_mean: f64::NAN,
            eval_success: score.0,
            eval_time_ratio: score.1,
        }
    }
}

const HEADER: &str = "phase,wall_s,env_steps,updates,episodes,recent_return,recent_success,critic_loss,actor_loss,q_mean,eval_success,eval_time_ratio";

/// An append-only CSV log.
pub struct CsvLog {
    file: File,
}

impl CsvLog {
    /// Opens (appending) or creates the log with its header.
    pub fn open(path: &Path) -> Result<CsvLog, ReportError> {
        let fresh = !path.exists();
        let mut file = OpenOptions::new().create(true).append(true).open(path)?;
        if fresh {
            writeln!(file, "{HEADER}")?;
        }
        Ok(CsvLog { file })
    }

    /// Appends a row.
    pub fn write(&mut self, r: &LogRow) -> Result<(), ReportError> {
        writeln!(
            self.file,
            "{},{:.1},{},{},{},{:.4},{:.4},{:.6},{:.6},{:.4},{:.4},{:.4}",
            r.phase,
            r.wall_s,
            r.env_steps,
            r.updates,
            r.episodes,
            r.recent_return,
            r.recent_success,
            r.critic_loss,
            r.actor_loss,
            r.q_mean,
            r.eval_success,
            r.eval_time_ratio
        )?;
        self.file.flush()?;
        Ok(())
    }
}

/// Reads a log written by [`CsvLog`] (malformed lines are skipped).
pub fn read_log(path: &Path) -> Result<Vec<LogRow>, ReportError> {
    let reader = BufReader::new(File::open(path)?);
    let mut rows = Vec::new();
    for line in reader.lines().skip(1) {
        let line = line?;
        let v: Vec<f64> = line.split(',').filter_map(|x| x.parse().ok()).collect();
        if v.len() != 12 {
            continue;
        }
        rows.push(LogRow {
            phase: v[0] as u8,
            wall_s: v[1],
            env_steps: v[2] as u64,
            updates: v[3] as u64,
            episodes: v[4] as u64,
            recent_return: v[5],
            recent_success: v[6],
            critic_loss: v[7],
            actor_loss: v[8],
            q_mean: v[9],
            eval_success: v[10],
            eval_time_ratio: v[11],
        });
    }
    Ok(rows)
}

const FONT: &[u8] = include_bytes!("../../sim-harness/assets/DejaVuSans.ttf");
pub(crate) const FAMILY: &str = "sans-serif";

pub(crate) fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // A failure only loses the labels; the font is known to parse.
        let _ = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT);
    });
}

/// Draws the learning curve of `rows` into a PNG at `path`.
pub fn plot_curve(rows: &[LogRow], path: &Path) -> Result<(), ReportError> {
    register_font();
    let err = |e: &dyn std::fmt::Display| ReportError::Plot(e.to_string());
    let root = BitMapBackend::new(path, (900, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (top, bottom) = root.split_vertically(300);
    let t_max = rows.iter().map(|r| r.wall_s).fold(1.0, f64::max);
    let train: Vec<&LogRow> = rows.iter().filter(|r| r.phase == 1).collect();

    let mut chart = ChartBuilder::on(&top)
        .margin(10)
        .caption(
            "success: training episodes (blue), held-out evaluation (red), evolution checks (green)",
            (FAMILY, 16),
        )
        .x_label_area_size(30)
        .y_label_area_size(45)
        .build_cartesian_2d(0.0..t_max, 0.0..1.05)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .y_desc("success rate")
        .label_style((FAMILY, 12))
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(LineSeries::new(
            train.iter().map(|r| (r.wall_s, r.recent_success)),
            &BLUE,
        ))
        .map_err(|e| err(&e))?;
    chart
        .draw_series(
            rows.iter()
                .filter(|r| r.phase == 2 && r.eval_success.is_finite())
                .map(|r| Circle::new((r.wall_s, r.eval_success), 4, RED.filled())),
        )
        .map_err(|e| err(&e))?;
    chart
        .draw_series(
            rows.iter()
                .filter(|r| r.phase == 3 && r.eval_success.is_finite())
                .map(|r| Circle::new((r.wall_s, r.eval_success), 3, GREEN.filled())),
        )
        .map_err(|e| err(&e))?;

    let returns: Vec<f64> = train
        .iter()
        .map(|r| r.recent_return)
        .filter(|v| v.is_finite())
        .collect();
    let lo = returns.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = returns.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) = if lo.is_finite() && hi > lo {
        (lo, hi)
    } else {
        (-1.0, 0.0)
    };
    let mut chart = ChartBuilder::on(&bottom)
        .margin(10)
        .caption("mean learner return per training episode", (FAMILY, 16))
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(0.0..t_max, lo..hi)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_desc("wall time (s)")
        .y_desc("return")
        .label_style((FAMILY, 12))
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(LineSeries::new(
            train
                .iter()
                .filter(|r| r.recent_return.is_finite())
                .map(|r| (r.wall_s, r.recent_return)),
            &GREEN,
        ))
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_round_trips_and_plots() {
        let dir = std::env::temp_dir().join(format!("skyherd-log-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("log.csv");
        let mut log = CsvLog::open(&path).expect("open");
        let row = |phase, wall_s, recent_success| LogRow {
            phase,
            wall_s,
            recent_success,
            recent_return: -wall_s,
            eval_success: f64::NAN,
            eval_time_ratio: f64::NAN,
            ..LogRow::default()
        };
        log.write(&row(1, 1.0, 0.25)).expect("write");
        log.write(&row(1, 2.0, 0.5)).expect("write");
        let mut eval = row(2, 2.0, 0.0);
        eval.eval_success = 0.75;
        log.write(&eval).expect("write");
        let back = read_log(&path).expect("read");
        assert_eq!(back.len(), 3);
        assert_eq!(back[1].recent_success, 0.5);
        assert_eq!(back[2].eval_success, 0.75);
        let png = dir.join("curve.png");
        plot_curve(&back, &png).expect("plot");
        assert!(std::fs::metadata(&png).expect("png").len() > 1000);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
