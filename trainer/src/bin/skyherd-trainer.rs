//! `skyherd-trainer`: train the MTDDPG actor, export it as a quantized model file, evaluate it.
//!
//! ```text
//! skyherd-trainer train  --config trainer/configs/mtddpg-v1.toml [--resume]
//! skyherd-trainer evolve --config trainer/configs/mtddpg-v1.toml   # the last stage alone
//! skyherd-trainer export --checkpoint runs/mtddpg-v1/evolved.safetensors --out models/mtddpg-v1.skym
//! skyherd-trainer eval   --model models/mtddpg-v1.skym --episodes 20 --baselines
//! skyherd-trainer plot   --log runs/mtddpg-v1/log.csv --out runs/mtddpg-v1/curve.png
//! ```

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use skyherd_model::Task;
use skyherd_onboard::actor::Actor;
use skyherd_sim::baseline::{Method, RulePolicy};
use skyherd_sim::learned::ModelPolicy;
use skyherd_trainer::audit::{Candidate, audit, gate, markdown as audit_markdown};
use skyherd_trainer::checkpoint;
use skyherd_trainer::config::TrainConfig;
use skyherd_trainer::distill::{DistillConfig, distill};
use skyherd_trainer::eval::{
    EVAL_TABLE_CSV_HEADER, EvalRow, EvalScenario, csv_table, evaluate_flat, markdown_table,
};
use skyherd_trainer::export::{calibration_scenarios, export, parity, record_observations};
use skyherd_trainer::policy::ActorPolicy;
use skyherd_trainer::report::read_log;
use skyherd_trainer::rollout::Draw;
use skyherd_trainer::train::{EvolutionOutcome, Observer, evolve_checkpoint, train};

/// `print!` through [`emit`], so that a reader that has gone away ends the program quietly.
macro_rules! out {
    ($($arg:tt)*) => { emit(&format!($($arg)*))? };
}

/// `println!` through [`emit`].
macro_rules! outln {
    ($($arg:tt)*) => { emit(&format!("{}\n", format_args!($($arg)*)))? };
}

#[derive(Parser)]
#[command(
    name = "skyherd-trainer",
    about = "MTDDPG training and export for skyherd"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train (warm start, MTDDPG, held-out evaluation) as configured.
    Train(TrainArgs),
    /// Run the evolution stage alone (`[evolution]` of the config) on a checkpoint, writing
    /// `<output_dir>/evolved.safetensors`; `train` runs it after MTDDPG.
    Evolve(EvolveArgs),
    /// Distil a rule into a float actor where the rule herds better (`skyherd_trainer::distill`:
    /// DAgger on the config's teach scenarios, anchored to the actor's own actions on its keep
    /// scenarios), writing the student as an actor file.
    Distill(DistillArgs),
    /// Quantize a checkpoint's actor into a quantized model file and check it against the float
    /// actor.
    Export(ExportArgs),
    /// Redraw the learning-curve PNG of a training log.
    Plot(PlotArgs),
    /// Evaluate a quantized model file (as it flies) and optionally the baselines, with test noise.
    Eval(EvalArgs),
    /// The reward audit: the discounted return the learner would see for hovering, every rule
    /// and optionally a model, beside success and time (`skyherd_trainer::audit`). With
    /// `--gate`, exit non-zero unless every successful rule beats hovering and the rules rank
    /// by completion time.
    AuditReward(AuditRewardArgs),
    /// Run the end-of-run choice again on a finished run's folder: its finalists (and, with
    /// `--average-finalists-from` or the run's `eval.average_finalists_from`, the mean of the
    /// late ones' actors) on the second episode set; the best becomes `best.safetensors`.
    /// Learning is not touched: this is how a run trained before the mean existed gets it.
    Choose(ChooseArgs),
    /// Read an ablation's runs (`<runs>/<arm>-seed<S>/eval.csv`, from `train --arm --seed`)
    /// and write its table, verdict and learning curves (`skyherd_trainer::ablation`).
    AblationReport(AblationReportArgs),
}

#[derive(clap::Args, Debug)]
struct AblationReportArgs {
    /// The folder holding the runs (the config's `output_dir`).
    #[arg(long)]
    runs: PathBuf,
    /// Where `ablation.md` and the curves go.
    #[arg(long, default_value = "docs/learning")]
    out: PathBuf,
}

#[derive(clap::Args, Debug)]
struct AuditRewardArgs {
    /// The training config whose reward, gamma and step limit are audited.
    #[arg(long)]
    config: PathBuf,
    /// Episodes per scenario and policy (the same seeds for every policy).
    #[arg(long, default_value_t = 8)]
    episodes: usize,
    /// First episode seed (held out from training and evaluation).
    #[arg(long, default_value_t = 3_500_000_000)]
    seed_base: u64,
    /// Scenarios as `task:N:M` (M = 0 adaptive).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "driving:4:4,driving:16:4,collecting:16:4,driving:16:1"
    )]
    scenarios: Vec<String>,
    /// Also fly this model file.
    #[arg(long)]
    model: Option<PathBuf>,
    /// Exit with status 1 when the gate fails.
    #[arg(long)]
    gate: bool,
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    threads: usize,
}

#[derive(clap::Args, Debug)]
struct TrainArgs {
    /// The TOML config.
    #[arg(long)]
    config: PathBuf,
    /// Continue from `<output_dir>/last.safetensors`.
    #[arg(long)]
    resume: bool,
    /// Override the config's seed (with `--arm`, one run of an ablation; the output goes to
    /// `<output_dir>/<arm>-seed<SEED>`).
    #[arg(long)]
    seed: Option<u64>,
    /// Train one arm of the multi-task ablation: `mtddpg` (both tasks through the shared
    /// layers), or `single-driving` / `single-collecting` (one task, half the env steps and
    /// twice the updates per step: the same env steps and gradient steps per task as the
    /// MTDDPG arm gives each).
    #[arg(long, value_enum)]
    arm: Option<Arm>,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum Arm {
    Mtddpg,
    SingleDriving,
    SingleCollecting,
}

impl Arm {
    fn name(self) -> &'static str {
        match self {
            Arm::Mtddpg => "mtddpg",
            Arm::SingleDriving => "single-driving",
            Arm::SingleCollecting => "single-collecting",
        }
    }
}

/// The config of one ablation run: `config` with `seed` and `arm` applied.
fn ablation_config(
    mut config: TrainConfig,
    seed: Option<u64>,
    arm: Option<Arm>,
) -> Result<TrainConfig> {
    if seed.is_none() && arm.is_none() {
        return Ok(config);
    }
    if let Some(seed) = seed {
        config.seed = seed;
    }
    let arm = arm.unwrap_or(Arm::Mtddpg);
    let t = &mut config.training;
    match arm {
        Arm::Mtddpg => t.tasks = Task::ALL.to_vec(),
        Arm::SingleDriving | Arm::SingleCollecting => {
            let task = if matches!(arm, Arm::SingleDriving) {
                Task::Driving
            } else {
                Task::Collecting
            };
            if t.tasks.len() == Task::COUNT {
                // The same env steps per task as the MTDDPG arm gives each, and the same
                // gradient steps per task: an MTDDPG update carries a batch of every task,
                // a single-task update one task's, so the single arm updates twice as often.
                t.env_steps /= Task::COUNT as u64;
                t.random_warmup_steps /= Task::COUNT as u64;
                t.learning_starts /= Task::COUNT as u64;
                t.updates_per_env_step *= Task::COUNT as f64;
            }
            t.tasks = vec![task];
        }
    }
    config.output_dir = config
        .output_dir
        .join(format!("{}-seed{}", arm.name(), config.seed));
    config.validate().context("the ablation run's config")?;
    Ok(config)
}

#[derive(clap::Args, Debug)]
struct EvolveArgs {
    /// The TOML config.
    #[arg(long)]
    config: PathBuf,
    /// The checkpoint to start from [default: `<output_dir>/best.safetensors`].
    #[arg(long, conflicts_with = "actor")]
    checkpoint: Option<PathBuf>,
    /// Start from an actor file instead (`trainer/shipped/*.actor.safetensors`, as `export
    /// --actor-out` writes them): a checkpoint whose critic is fresh, which the stage never reads.
    #[arg(long)]
    actor: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
struct DistillArgs {
    /// The distillation TOML config.
    #[arg(long)]
    config: PathBuf,
    /// The actor to start from (an actor file or a checkpoint).
    #[arg(long)]
    actor: PathBuf,
    /// The student actor file to write.
    #[arg(long)]
    out: PathBuf,
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    threads: usize,
}

#[derive(clap::Args, Debug)]
struct ExportArgs {
    /// A checkpoint (`best.safetensors` or `last.safetensors`) or an actor file.
    #[arg(long)]
    checkpoint: PathBuf,
    /// The model file to write.
    #[arg(long)]
    out: PathBuf,
    /// Episode steps recorded per calibration scenario.
    #[arg(long, default_value_t = 800)]
    calibration_steps: u64,
    /// Calibration episodes per scenario.
    #[arg(long, default_value_t = 6)]
    calibration_episodes: usize,
    /// Quantization-aware fine-tuning steps before quantizing (`skyherd_trainer::qat`; 0:
    /// quantize the checkpoint's actor as it is). The quantized model is compared with, and
    /// `--actor-out` writes, the checkpoint's actor.
    #[arg(long, default_value_t = 4_000)]
    qat_steps: usize,
    /// Also write the float actor here (the reference the parity test compares against).
    #[arg(long)]
    actor_out: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
struct ChooseArgs {
    /// The run's folder (holding `last.safetensors`, `finalists.csv` and the finalists).
    #[arg(long)]
    run: PathBuf,
    /// Average the finalists checked at or after this share of the run's env steps into one
    /// more candidate (overrides the run's config).
    #[arg(long)]
    average_finalists_from: Option<f64>,
}

#[derive(clap::Args, Debug)]
struct PlotArgs {
    /// The run's `log.csv`.
    #[arg(long)]
    log: PathBuf,
    /// The PNG to write.
    #[arg(long)]
    out: PathBuf,
}

#[derive(clap::Args, Debug)]
struct EvalArgs {
    /// The model file.
    #[arg(long)]
    model: PathBuf,
    /// Episodes per scenario.
    #[arg(long, default_value_t = 20)]
    episodes: usize,
    /// First episode seed (held out from training).
    #[arg(long, default_value_t = 2_000_000_000)]
    seed_base: u64,
    /// Also run the rule-based baselines (every `skyherd_sim::baseline::Method`).
    #[arg(long)]
    baselines: bool,
    /// Also run these rules only (comma-separated names, e.g. `lama,farthest`); with
    /// `--baselines` every rule runs anyway.
    #[arg(long, value_delimiter = ',')]
    rules: Vec<String>,
    /// Also write every table's rows at full precision to this CSV file (the Markdown table
    /// rounds the time ratio to two decimals).
    #[arg(long)]
    csv: Option<PathBuf>,
    /// Also run this float actor (the export's `--actor-out`, or a checkpoint).
    #[arg(long)]
    actor: Option<PathBuf>,
    /// Scenarios as `task:N:M` (M = 0 adaptive); default: a standard set.
    #[arg(long, value_delimiter = ',')]
    scenarios: Vec<String>,
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    threads: usize,
}

/// indicatif progress bar for the training phases.
struct Bar {
    bar: Option<ProgressBar>,
}

impl Observer for Bar {
    fn phase(&mut self, name: &str, total: u64) {
        if let Some(b) = self.bar.take() {
            b.finish();
        }
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>20} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_prefix(name.to_owned());
        self.bar = Some(bar);
    }
    fn progress(&mut self, done: u64, message: &str) {
        if let Some(b) = &self.bar {
            b.set_position(done);
            b.set_message(message.to_owned());
            // Without a terminal (nohup) the bar is hidden: log the line instead.
            if b.is_hidden() {
                eprintln!("[{}] {done}: {message}", b.prefix());
            }
        }
    }
    fn note(&mut self, line: &str) {
        match &self.bar {
            Some(b) if !b.is_hidden() => b.println(line),
            _ => eprintln!("{line}"),
        }
    }
}

fn parse_scenario(s: &str) -> Result<EvalScenario> {
    let parts: Vec<&str> = s.split(':').collect();
    if parts.len() != 3 {
        bail!("scenario `{s}` is not task:N:M");
    }
    Ok(EvalScenario {
        task: skyherd_sim::task::parse_task(parts[0])
            .with_context(|| format!("unknown task in `{s}` (driving or collecting)"))?,
        targets: parts[1]
            .parse()
            .with_context(|| format!("N in `{s}` is not a count"))?,
        herders: parts[2]
            .parse()
            .with_context(|| format!("M in `{s}` is not a count"))?,
    })
}

fn print_evolution(e: &EvolutionOutcome) -> Result<()> {
    outln!("evolution: {:.0} s -> {}", e.wall_s, e.checkpoint.display());
    for (task, before, after) in &e.tasks {
        outln!(
            "  {}: held-out check {:.3} -> {:.3}, success {:.0}% -> {:.0}%, time {:.2}x -> {:.2}x lower bound",
            skyherd_sim::task::task_name(*task),
            before.fitness,
            after.fitness,
            100.0 * before.success_rate,
            100.0 * after.success_rate,
            before.time_ratio,
            after.time_ratio
        );
    }
    out!("{}", markdown_table("float (evolved)", &e.eval));
    Ok(())
}

/// Writes `text` to standard output. A reader that has gone away (`skyherd-trainer eval ... |
/// head`) ends the program quietly with status 0, as other Unix tools stop, where `print!`
/// would panic.
fn emit(text: &str) -> Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => std::process::exit(0),
        other => other.context("writing to standard output"),
    }
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Train(args) => run_train(args),
        Command::Evolve(args) => run_evolve(args),
        Command::Distill(args) => run_distill(args),
        Command::Export(args) => run_export(args),
        Command::Plot(args) => run_plot(args),
        Command::Choose(args) => run_choose(args),
        Command::Eval(args) => run_eval(args),
        Command::AuditReward(args) => run_audit_reward(args),
        Command::AblationReport(args) => {
            let text = skyherd_trainer::ablation::report(&args.runs, &args.out)
                .with_context(|| format!("reading the runs in {}", args.runs.display()))?;
            out!("{text}");
            Ok(())
        }
    }
}

fn run_train(args: TrainArgs) -> Result<()> {
    let TrainArgs {
        config,
        resume,
        seed,
        arm,
    } = args;
    let mut config = ablation_config(TrainConfig::load(&config)?, seed, arm)?;
    if resume && config.training.restart_candidates > 1 {
        // The trials are over once restarts.json exists: the winner's run goes on from its
        // own folder, as a run of its own.
        let record = config
            .output_dir
            .join(skyherd_trainer::train::RESTARTS_FILE);
        let text = std::fs::read_to_string(&record).with_context(|| {
            format!(
                "resuming a run with restarts needs {} (the candidates' trials had not finished: start the run afresh, without --resume)",
                record.display()
            )
        })?;
        let r: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("{} is not JSON", record.display()))?;
        let (Some(winner), Some(seed), Some(steps)) = (
            r["winner"].as_u64(),
            r["candidates"][r["winner"].as_u64().unwrap_or(0) as usize]["seed"].as_u64(),
            r["winner_env_steps"].as_u64(),
        ) else {
            bail!(
                "{} lacks the winner, its seed or its env steps",
                record.display()
            );
        };
        config.seed = seed;
        config.training.env_steps = steps;
        config.training.restart_candidates = 1;
        config.output_dir =
            skyherd_trainer::train::restart_candidate_dir(&config.output_dir, winner as usize);
    }
    let resume_from = if resume {
        let path = config.output_dir.join("last.safetensors");
        let c =
            checkpoint::load(&path).with_context(|| format!("resuming from {}", path.display()))?;
        eprintln!(
            "resuming at {} env steps, {} updates",
            c.progress.env_steps, c.agent.updates
        );
        Some(c)
    } else {
        None
    };
    let started = Instant::now();
    let mut bar = Bar { bar: None };
    let outcome = train(&config, resume_from, &mut bar)?;
    if let Some(b) = bar.bar.take() {
        b.finish();
    }
    outln!(
        "done: {} env steps, {} episodes, {:.0} s in this process ({:.0} s with any earlier resumed part), {:.2} ms per update",
        outcome.progress.env_steps,
        outcome.progress.episodes,
        started.elapsed().as_secs_f64(),
        outcome.progress.wall_time_s,
        1e3 * outcome.seconds_per_update
    );
    outln!(
        "best: success {:.1}%, time {:.2}x lower bound -> {}",
        100.0 * outcome.progress.best_success,
        outcome.progress.best_time_ratio,
        outcome.best_checkpoint.display()
    );
    out!("{}", markdown_table("float (last)", &outcome.last_eval));
    if let Some(e) = &outcome.evolution {
        print_evolution(e)?;
    }
    Ok(())
}

fn run_evolve(args: EvolveArgs) -> Result<()> {
    let EvolveArgs {
        config,
        checkpoint: source,
        actor,
    } = args;
    let config = TrainConfig::load(&config)?;
    let mut c = match actor {
        Some(path) => skyherd_trainer::train::checkpoint_of_actor(&config, &path)
            .with_context(|| format!("evolving from {}", path.display()))?,
        None => {
            let path = source.unwrap_or_else(|| config.output_dir.join("best.safetensors"));
            checkpoint::load(&path).with_context(|| format!("evolving from {}", path.display()))?
        }
    };
    // The stage's clock starts where the run's log ends, as in `train`.
    if let Ok(rows) = read_log(&config.output_dir.join("log.csv")) {
        let end = rows.iter().map(|r| r.wall_s).fold(0.0, f64::max);
        c.progress.wall_time_s = c.progress.wall_time_s.max(end);
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(config.training.threads)
        .build()?;
    let mut bar = Bar { bar: None };
    let outcome = pool.install(|| evolve_checkpoint(&config, &c, &mut bar))?;
    if let Some(b) = bar.bar.take() {
        b.finish();
    }
    print_evolution(&outcome)?;
    Ok(())
}

fn run_distill(args: DistillArgs) -> Result<()> {
    let DistillArgs {
        config,
        actor,
        out,
        threads,
    } = args;
    let text = std::fs::read_to_string(&config)
        .with_context(|| format!("reading {}", config.display()))?;
    let config: DistillConfig =
        toml::from_str(&text).with_context(|| format!("parsing {}", config.display()))?;
    let start = checkpoint::load_actor(&actor)
        .with_context(|| format!("distilling from {}", actor.display()))?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let t0 = std::time::Instant::now();
    let outcome = pool.install(|| {
            distill(&start, &config, |r| {
                let check = r.check.map_or(String::new(), |c| {
                    format!(
                        ", check {:.3} (success {:.0}%, time {:.2}x)",
                        c.fitness,
                        100.0 * c.success_rate,
                        c.time_ratio
                    )
                });
                // A progress line: the distillation goes on if standard output fails.
                let _ = emit(&format!(
                    "round {}: {} teach + {} keep samples, teach success {:.0}%, keep success {:.0}%, MSE teach {:.5} keep {:.5}{check} ({:.0} s)\n",
                    r.round,
                    r.teach_samples,
                    r.keep_samples,
                    100.0 * r.teach_success,
                    100.0 * r.keep_success,
                    r.teach_loss,
                    r.keep_loss,
                    t0.elapsed().as_secs_f64()
                ));
            })
        })?;
    outln!("kept round {}", outcome.best_round);
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    checkpoint::save_actor(&out, &outcome.actor)?;
    outln!("wrote {}", out.display());
    Ok(())
}

fn run_export(args: ExportArgs) -> Result<()> {
    let ExportArgs {
        checkpoint: path,
        out,
        calibration_steps,
        calibration_episodes,
        qat_steps,
        actor_out,
    } = args;
    let actor =
        &checkpoint::load_actor(&path).with_context(|| format!("exporting {}", path.display()))?;
    // Calibration and parity use different episodes (seeds) of the same scenarios.
    let scenarios = calibration_scenarios();
    let calibration = record_observations(
        actor,
        &scenarios,
        calibration_episodes,
        3_000_000_000,
        calibration_steps,
        2,
    )?;
    let max_speed = skyherd_sim::Scenario::paper_drive().limits.herder as f32;
    let tuned = (qat_steps > 0).then(|| {
        let config = skyherd_trainer::qat::QatConfig {
            steps: qat_steps,
            ..Default::default()
        };
        skyherd_trainer::qat::finetune(actor, &calibration, config)
    });
    let bytes = export(tuned.as_ref().unwrap_or(actor), max_speed, &calibration)?;
    let held_out = record_observations(actor, &scenarios, 2, 3_100_000_000, 600, 3)?;
    let on_calibration = parity(actor, &bytes, &calibration)?;
    outln!(
        "parity on the calibration observations: RMS {:.4} per component, max {:.4}",
        on_calibration.rms_component,
        on_calibration.max_component
    );
    let p = parity(actor, &bytes, &held_out)?;
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&out, &bytes)?;
    if let Some(path) = actor_out {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        checkpoint::save_actor(&path, actor)?;
        outln!("wrote the float actor to {}", path.display());
    }
    outln!(
        "wrote {} ({} bytes), calibrated on {} observations",
        out.display(),
        bytes.len(),
        calibration.len()
    );
    outln!(
        "parity on {} held-out observations: RMS {:.4} per component, {:.4} per vector, max {:.4} (units of max speed)",
        p.samples,
        p.rms_component,
        p.rms_vector,
        p.max_component
    );
    Ok(())
}

fn run_choose(args: ChooseArgs) -> Result<()> {
    let ChooseArgs {
        run,
        average_finalists_from,
    } = args;
    let last = run.join("last.safetensors");
    let mut config = checkpoint::load(&last)
        .with_context(|| format!("reading the run's config from {}", last.display()))?
        .config;
    if average_finalists_from.is_some() {
        config.eval.average_finalists_from = average_finalists_from;
    }
    config.validate()?;
    let csv = run.join(skyherd_trainer::finalists::CSV_FILE);
    let text = std::fs::read_to_string(&csv)
        .with_context(|| format!("reading the run's finalists from {}", csv.display()))?;
    let finalists = skyherd_trainer::finalists::from_csv(&text);
    if finalists.is_empty() {
        bail!(
            "{} names no finalist (was the run trained with eval.finalists?)",
            csv.display()
        );
    }
    let scenarios: Vec<EvalScenario> = config
        .eval
        .scenario_list()
        .into_iter()
        .filter(|s| config.training.tasks.contains(&s.task))
        .collect();
    let mut bar = Bar { bar: None };
    let kept =
        skyherd_trainer::train::choose_finalist(&config, &run, &finalists, &scenarios, &mut bar)?;
    if let Some(kept) = kept {
        outln!(
            "kept {} as {}: {:.1}% at {:.2}x the bound on the second set",
            if kept.check.is_some() {
                format!("the finalist at {} env steps", kept.env_steps[0])
            } else {
                format!(
                    "the mean of the finalists at {:?} env steps",
                    kept.env_steps
                )
            },
            run.join("best.safetensors").display(),
            100.0 * kept.final_score.0,
            kept.final_score.1
        );
    }
    Ok(())
}

fn run_plot(args: PlotArgs) -> Result<()> {
    let PlotArgs { log, out } = args;
    skyherd_trainer::report::plot_curve(&read_log(&log)?, &out)?;
    outln!("wrote {}", out.display());
    Ok(())
}

fn run_eval(args: EvalArgs) -> Result<()> {
    let EvalArgs {
        model,
        episodes,
        seed_base,
        baselines,
        rules,
        csv,
        actor: float_actor,
        scenarios,
        threads,
    } = args;
    let rules: Vec<Method> = if baselines {
        Method::ALL.to_vec()
    } else {
        rules
            .iter()
            .map(|name| {
                name.parse::<Method>()
                    .map_err(|e| anyhow::anyhow!("--rules: {e}"))
            })
            .collect::<Result<_>>()?
    };
    let float_actor = float_actor
        .map(|p| checkpoint::load_actor(&p))
        .transpose()?;
    let bytes = skyherd_model::read_model_file(&model)
        .map_err(|e| anyhow::anyhow!("{}: {e}", model.display()))?;
    let actor =
        Actor::from_bytes(&bytes).map_err(|e| anyhow::anyhow!("{}: {e:?}", model.display()))?;
    let scenarios: Vec<EvalScenario> = if scenarios.is_empty() {
        [
            "driving:16:4",
            "driving:64:4",
            "driving:256:0",
            "collecting:16:4",
            "collecting:64:4",
        ]
        .iter()
        .map(|s| parse_scenario(s))
        .collect::<Result<_>>()?
    } else {
        scenarios
            .iter()
            .map(|s| parse_scenario(s))
            .collect::<Result<_>>()?
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    // The rows go to a `.partial` file beside the CSV, created before the episodes run (so a
    // folder that cannot be written fails at once) and renamed over it at the end (so an earlier
    // file at that path survives a failed evaluation).
    let csv_file = csv
        .map(|path| -> Result<_> {
            let partial = path.with_extension("partial");
            let file = std::fs::File::create(&partial)
                .with_context(|| format!("creating {}", partial.display()))?;
            Ok((file, partial, path))
        })
        .transpose()?;
    outln!("| scenario | method | episodes | success | time (s) | time / bound | path (m) |");
    outln!("|---|---|---|---|---|---|---|");
    // Rows are labelled with the model file's name (`mtddpg-v3` for models/mtddpg-v3.skym).
    let name = model
        .file_stem()
        .map_or_else(|| "model".to_owned(), |s| s.to_string_lossy().into_owned());
    let mut csv_text = format!("{EVAL_TABLE_CSV_HEADER}\n");
    let mut table = |method: &str, rows: &[EvalRow]| -> Result<()> {
        out!("{}", markdown_table(method, rows));
        csv_text.push_str(&csv_table(method, rows));
        Ok(())
    };
    pool.install(|| -> Result<()> {
        let rows = evaluate_flat(&scenarios, episodes, seed_base, || ActorPolicy::new(actor))?;
        table(&format!("{name} (quantized)"), &rows)?;
        if let Some(float) = &float_actor {
            let rows = evaluate_flat(&scenarios, episodes, seed_base, || ActorPolicy::new(float))?;
            table(&format!("{name} (float)"), &rows)?;
        }
        for &method in &rules {
            let rows = evaluate_flat(&scenarios, episodes, seed_base, || RulePolicy::new(method))?;
            table(method.as_str(), &rows)?;
        }
        Ok(())
    })?;
    if let Some((mut file, partial, path)) = csv_file {
        use std::io::Write as _;
        file.write_all(csv_text.as_bytes())
            .with_context(|| format!("writing {}", partial.display()))?;
        std::fs::rename(&partial, &path)
            .with_context(|| format!("renaming {} to {}", partial.display(), path.display()))?;
    }
    Ok(())
}

fn run_audit_reward(args: AuditRewardArgs) -> Result<()> {
    let config = TrainConfig::load(&args.config)?;
    let draws: Vec<Draw> = args
        .scenarios
        .iter()
        .map(|s| parse_scenario(s).map(|e| Draw::paper(e.task, e.targets, e.herders)))
        .collect::<Result<_>>()?;
    let mut candidates = Candidate::hover_and_rules();
    if let Some(path) = &args.model {
        let model = ModelPolicy::from_file(path).with_context(|| format!("{}", path.display()))?;
        candidates.push(Candidate::Model(Box::new(model)));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads)
        .build()?;
    let rows = pool
        .install(|| audit(&config, &draws, &candidates, args.episodes, args.seed_base))
        .context("an audited scenario")?;
    outln!(
        "reward `{:?}`, gamma {}, step limit {}, {} episodes each, seeds from {}",
        config.reward.kind,
        config.ddpg.gamma,
        config.training.episode_step_limit,
        args.episodes,
        args.seed_base
    );
    out!("{}", audit_markdown(&rows));
    let report = gate(&rows);
    if report.passed {
        outln!("gate: passed");
    } else {
        outln!("gate: FAILED");
        for p in &report.problems {
            outln!("  {p}");
        }
        if args.gate {
            std::process::exit(1);
        }
    }
    Ok(())
}
