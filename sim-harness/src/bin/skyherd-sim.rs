//! `skyherd-sim`: run an episode, step a state, sweep the evaluation, draw the plots.
//!
//! ```text
//! skyherd-sim run  --scenario paper-drive --policy strombom --seed 3 --out trace.jsonl
//! skyherd-sim step --state state.json > next.json
//! skyherd-sim eval --episodes 100 --out-dir docs/baselines
//! skyherd-sim eval --methods model:models/mtddpg-v1.skym,strombom --out-dir docs/learned
//! skyherd-sim plot-trajectory --policy ctrl --targets 8 --herders 4 --out docs/baselines/fig4-ctrl
//! ```

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, anyhow, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use skyherd_onboard::safety::Braking;
use skyherd_sim::baseline::Method;
use skyherd_sim::eval::{
    ConfigResult, SweepSpec, comparison_markdown, run_sweep, to_csv, to_markdown,
};
use skyherd_sim::learned::ModelPolicy;
use skyherd_sim::task::parse_task;
use skyherd_sim::trace::{TraceLine, step_state_json};
use skyherd_sim::{
    Env, HerderCount, HerderDynamics, PolicyFactory, Scenario, World, plot, run_episode,
};

#[derive(Parser)]
#[command(
    name = "skyherd-sim",
    about = "The skyherd shepherding simulator",
    version
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run one episode and write every step's state as JSON Lines.
    Run(RunArgs),
    /// Read a state (JSON), apply exactly one noise-free step, print it in the same schema.
    Step(StepArgs),
    /// Sweep ⟨task, method, M, N⟩ with fixed seeds and test-time noise.
    Eval(EvalArgs),
    /// Merge results.json files written by `eval` (for example the baselines' and a model's),
    /// draw the Fig. 3 plots of all their methods and write the merged results.md/.csv.
    PlotFig3(PlotFig3Args),
    /// Run one driving episode and draw its Fig. 4-style trajectory (PNG + SVG).
    PlotTrajectory(PlotTrajectoryArgs),
    /// Print a preset as complete TOML.
    Scenario(ScenarioArgs),
}

#[derive(clap::Args, Debug)]
struct RunArgs {
    /// A preset (paper-drive, paper-collect, indoor) or a scenario TOML file.
    #[arg(long, default_value = "paper-drive")]
    scenario: String,
    /// Policy: strombom, ctrl, lama, farthest, or `model:PATH` (a quantized model file).
    #[arg(long, default_value = "strombom")]
    policy: String,
    /// Episode seed (default: the scenario's).
    #[arg(long)]
    seed: Option<u64>,
    /// Override N.
    #[arg(long)]
    targets: Option<usize>,
    /// Override M (a count or `adaptive`).
    #[arg(long)]
    herders: Option<HerderCount>,
    /// Trace file (JSON Lines); none if omitted.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
struct StepArgs {
    /// State file; `-` reads stdin.
    #[arg(long)]
    state: PathBuf,
}

#[derive(clap::Args, Debug)]
struct EvalArgs {
    /// Tasks, comma separated.
    #[arg(long, value_delimiter = ',', default_value = "driving,collecting")]
    tasks: Vec<String>,
    /// Methods, comma separated: baselines and `model:PATH` model files.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "strombom,ctrl,lama,farthest"
    )]
    methods: Vec<String>,
    /// Target counts, comma separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1,2,4,8,16,32,64,128,256,512,1024"
    )]
    targets: Vec<usize>,
    /// Herder settings, comma separated (counts or `adaptive`).
    #[arg(long, value_delimiter = ',', default_value = "1,4,adaptive")]
    herders: Vec<HerderCount>,
    /// Episodes per configuration.
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    /// Base of the episode seeds.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Override the presets' step limit.
    #[arg(long)]
    step_limit: Option<u64>,
    /// Run shard i of n (`i/n`, 0-based).
    #[arg(long, default_value = "0/1")]
    shard: String,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Write results.csv, results.json, results.md (and plots with --plots) here.
    #[arg(long)]
    out_dir: Option<PathBuf>,
    /// Also draw the Fig. 3 plots into --out-dir.
    #[arg(long)]
    plots: bool,
    /// Print the summary of the single configuration as JSON on stdout.
    #[arg(long)]
    json: bool,
    /// Model files fly with the daemon's separation rule (`skyherd_onboard::separation`,
    /// 10 % beyond the breach distance: 0.5 m in a room, 3 m in the arena) before its flight
    /// rules; reported as `NAME+apart`. Every result reports the closest approach and the
    /// episodes that breached, with or without it.
    #[arg(long)]
    keep_apart: bool,
    /// Fly the herders through a multicopter model (`skyherd_sim::dynamics`): `px4` (PX4 in
    /// Offboard), `px4-auto` (PX4's jerk-limited mission trajectory on every command) or
    /// `indoor` (PX4 in Offboard with the room's speed caps) [default: they fly their commands
    /// at once, the paper's protocol].
    #[arg(long, value_enum)]
    dynamics: Option<DynamicsArg>,
    /// The wind with --dynamics: `calm`, `arena` (3 m/s, 1 m/s gusts) or `room` (draughts).
    #[arg(long, value_enum, default_value_t = WindArg::Calm)]
    wind: WindArg,
    /// With --dynamics: commands reach the vehicle this long into each step, s (0 to one step;
    /// the MAVLink loop's is one 0.1 s sensor tick).
    #[arg(long, default_value_t = 0.0)]
    command_delay_s: f64,
}

/// A value's name on the command line (`px4-auto`), as `HerderDynamics::named` takes it.
fn value_name(value: impl clap::ValueEnum) -> String {
    value
        .to_possible_value()
        .map_or_else(String::new, |v| v.get_name().to_owned())
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum DynamicsArg {
    Px4,
    Px4Auto,
    Indoor,
}

#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum)]
enum WindArg {
    Calm,
    Arena,
    Room,
}

#[derive(clap::Args, Debug)]
struct PlotFig3Args {
    /// results.json files from `eval`, comma separated or repeated.
    #[arg(long, value_delimiter = ',', required = true)]
    results: Vec<PathBuf>,
    /// Output directory.
    #[arg(long)]
    out_dir: PathBuf,
    /// Also write comparison.md: this method beside the best other method per configuration.
    #[arg(long)]
    compare: Option<String>,
}

#[derive(clap::Args, Debug)]
struct PlotTrajectoryArgs {
    /// Scenario preset or file.
    #[arg(long, default_value = "paper-drive")]
    scenario: String,
    /// Policy (a baseline or `model:PATH`).
    #[arg(long, default_value = "farthest")]
    policy: String,
    /// Episode seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// N.
    #[arg(long, default_value_t = 8)]
    targets: usize,
    /// M.
    #[arg(long, default_value_t = 4)]
    herders: usize,
    /// Output path without extension.
    #[arg(long)]
    out: PathBuf,
}

#[derive(clap::Args, Debug)]
struct ScenarioArgs {
    /// Preset name.
    preset: String,
}

/// The policies the command line knows: a baseline by name, or `model:PATH`, a quantized model file
/// run through the onboard actor as it flies.
fn policy_factory(name: &str) -> Result<Arc<dyn PolicyFactory>> {
    policy_factory_apart(name, false, None)
}

/// The same; `keep_apart`: model files fly with the daemon's separation rule too.
/// `braking`: how the herders answer a new velocity (with a motion model), which the separation
/// rule counts.
fn policy_factory_apart(
    name: &str,
    keep_apart: bool,
    braking: Option<Braking>,
) -> Result<Arc<dyn PolicyFactory>> {
    if let Some(path) = name.strip_prefix("model:") {
        let model = ModelPolicy::from_file(path.as_ref())?.responding_in(braking);
        return Ok(Arc::new(if keep_apart {
            model.keeping_apart()
        } else {
            model
        }));
    }
    let method: Method = name
        .parse()
        .map_err(|e: String| anyhow!("{e} (or `model:PATH` for a model file)"))?;
    Ok(Arc::new(method))
}

/// Writes `text` to standard output. A reader that has gone away (`skyherd-sim run ... | head`)
/// ends the program quietly with status 0, as other Unix tools stop, where `print!` would panic.
fn emit(text: &str) -> Result<()> {
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => std::process::exit(0),
        other => other.context("writing to standard output"),
    }
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Run(args) => run_command(args),
        Command::Step(args) => step_command(args),
        Command::Eval(args) => eval_command(args),
        Command::PlotFig3(args) => plot_fig3_command(args),
        Command::PlotTrajectory(args) => plot_trajectory_command(args),
        Command::Scenario(args) => scenario_command(args),
    }
}

fn run_command(args: RunArgs) -> Result<()> {
    let RunArgs {
        scenario,
        policy,
        seed,
        targets,
        herders,
        out,
    } = args;
    run(&scenario, &policy, seed, targets, herders, out.as_deref())
}

fn step_command(args: StepArgs) -> Result<()> {
    let StepArgs { state } = args;
    let text = if state.as_os_str() == "-" {
        std::io::read_to_string(std::io::stdin()).context("reading stdin")?
    } else {
        fs::read_to_string(&state).with_context(|| format!("reading {}", state.display()))?
    };
    let next = step_state_json(&text)?;
    emit(&format!("{}\n", serde_json::to_string_pretty(&next)?))?;
    Ok(())
}

fn eval_command(args: EvalArgs) -> Result<()> {
    let EvalArgs {
        tasks,
        methods,
        targets,
        herders,
        episodes,
        seed,
        step_limit,
        shard,
        threads,
        out_dir,
        plots,
        json,
        keep_apart,
        dynamics,
        wind,
        command_delay_s,
    } = args;
    if command_delay_s != 0.0 && dynamics.is_none() {
        bail!("--command-delay-s needs --dynamics: without a motion model a command acts at once");
    }
    let dynamics = match dynamics {
        None if wind != WindArg::Calm => {
            bail!("--wind needs --dynamics: without a motion model nothing feels it")
        }
        None => None,
        Some(d) => {
            let (limits, air) = (value_name(d), value_name(wind));
            let named = HerderDynamics::named(&limits, &air)
                .ok_or_else(|| anyhow!("no motion model {limits:?} in wind {air:?}"))?;
            Some(HerderDynamics {
                command_delay_s,
                ..named
            })
        }
    };
    let spec = SweepSpec {
        tasks: tasks
            .iter()
            .map(|t| parse_task(t).ok_or_else(|| anyhow!("unknown task `{t}`")))
            .collect::<Result<_>>()?,
        methods: methods
            .iter()
            .map(|m| {
                // A lagging herder turns late; braking along one axis while turning along the
                // other gets 1/sqrt(2) of its horizontal limit.
                let braking = dynamics.map(|d| Braking {
                    deceleration: (d.limits.max_accel_horizontal * std::f64::consts::FRAC_1_SQRT_2)
                        as f32,
                    lag_s: d.limits.response_lag_s() as f32,
                });
                policy_factory_apart(m, keep_apart, braking)
            })
            .collect::<Result<_>>()?,
        herders,
        targets,
        episodes,
        base_seed: seed,
        step_limit,
        shard: parse_shard(&shard)?,
        dynamics,
    };
    eval(spec, threads, out_dir.as_deref(), plots, json)
}

fn plot_fig3_command(args: PlotFig3Args) -> Result<()> {
    let PlotFig3Args {
        results,
        out_dir,
        compare,
    } = args;
    let mut merged: Vec<ConfigResult> = Vec::new();
    for path in &results {
        let text =
            fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let part: Vec<ConfigResult> = serde_json::from_str(&text)
            .with_context(|| format!("{} is not an eval results.json", path.display()))?;
        merged.extend(part);
    }
    fs::create_dir_all(&out_dir)?;
    for f in plot::fig3(&merged, &out_dir)? {
        eprintln!("wrote {}", f.display());
    }
    if results.len() > 1 {
        fs::write(out_dir.join("results.md"), to_markdown(&merged))?;
        fs::write(out_dir.join("results.csv"), to_csv(&merged))?;
    }
    if let Some(method) = compare {
        if !merged.iter().any(|r| r.config.method == method) {
            bail!("no results for method `{method}` to compare");
        }
        fs::write(
            out_dir.join("comparison.md"),
            comparison_markdown(&merged, &method),
        )?;
    }
    Ok(())
}

fn plot_trajectory_command(args: PlotTrajectoryArgs) -> Result<()> {
    let PlotTrajectoryArgs {
        scenario,
        policy,
        seed,
        targets,
        herders,
        out,
    } = args;
    let mut s = Scenario::from_arg(&scenario)?;
    s.targets = targets;
    s.herders = HerderCount::Fixed(herders);
    s.validate()?;
    let mut env = Env::new(s)?;
    let factory = policy_factory(&policy)?;
    let name = factory.name();
    let mut p = factory.make();
    let mut states: Vec<World> = Vec::new();
    let summary = run_episode(&mut env, p.as_mut(), seed, |w, _| states.push(w.clone()))?;
    let title = format!(
        "{name}: {herders} herders, {targets} targets, seed {seed}: {} in {} s",
        if summary.success {
            "success"
        } else {
            "failure"
        },
        summary.time_s
    );
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        fs::create_dir_all(dir)?;
    }
    for f in plot::trajectory(&states, &title, &out)? {
        eprintln!("wrote {}", f.display());
    }
    Ok(())
}

fn scenario_command(args: ScenarioArgs) -> Result<()> {
    let ScenarioArgs { preset } = args;
    emit(&Scenario::preset(&preset)?.to_toml()?)?;
    Ok(())
}

fn parse_shard(s: &str) -> Result<(usize, usize)> {
    let (i, n) = s
        .split_once('/')
        .ok_or_else(|| anyhow!("--shard must be i/n, got `{s}`"))?;
    let (i, n): (usize, usize) = (i.parse()?, n.parse()?);
    if n == 0 || i >= n {
        bail!("--shard {i}/{n}: need 0 <= i < n");
    }
    Ok((i, n))
}

fn run(
    scenario: &str,
    policy: &str,
    seed: Option<u64>,
    targets: Option<usize>,
    herders: Option<HerderCount>,
    out: Option<&Path>,
) -> Result<()> {
    let mut s = Scenario::from_arg(scenario)?;
    if let Some(n) = targets {
        s.targets = n;
    }
    if let Some(m) = herders {
        s.herders = m;
    }
    s.validate()?;
    let seed = seed.unwrap_or(s.seed);
    let mut env = Env::new(s)?;
    let mut p = policy_factory(policy)?.make();
    let mut writer = match out {
        Some(path) => Some(BufWriter::new(
            fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
        )),
        None => None,
    };
    let mut io_error = None;
    let mut last_actions: Vec<[f64; 3]> = Vec::new();
    let mut previous: Option<World> = None;
    let summary = run_episode(&mut env, p.as_mut(), seed, |w, outcome| {
        // The commands of a step are the herders' displacement over dt before the caps: record
        // what the world shows (displacement / dt), which is what was actually flown.
        last_actions.clear();
        if let Some(prev) = &previous {
            last_actions.extend(prev.herders.iter().zip(&w.herders).map(|(a, b)| {
                [
                    (b[0] - a[0]) / w.dt,
                    (b[1] - a[1]) / w.dt,
                    (b[2] - a[2]) / w.dt,
                ]
            }));
        }
        if let Some(wr) = writer.as_mut() {
            let line = TraceLine {
                world: w.clone(),
                actions: last_actions.clone(),
                outcome: outcome.copied(),
            };
            let res = serde_json::to_writer(&mut *wr, &line)
                .map_err(std::io::Error::from)
                .and_then(|()| wr.write_all(b"\n"));
            if let Err(e) = res {
                io_error.get_or_insert(e);
            }
        }
        previous = Some(w.clone());
    })?;
    if let Some(e) = io_error {
        return Err(e).context("writing the trace");
    }
    if let Some(mut wr) = writer {
        wr.flush()?;
    }
    emit(&format!("{}\n", serde_json::to_string_pretty(&summary)?))?;
    Ok(())
}

fn eval(
    spec: SweepSpec,
    threads: Option<usize>,
    out_dir: Option<&Path>,
    plots: bool,
    json: bool,
) -> Result<()> {
    let configs = spec.configs();
    if json && configs.len() != 1 {
        bail!(
            "--json prints one configuration; this sweep (shard) has {}",
            configs.len()
        );
    }
    if plots && out_dir.is_none() {
        bail!("--plots needs --out-dir");
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads.unwrap_or(0))
        .build()?;
    let total = (configs.len() * spec.episodes) as u64;
    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} episodes ({per_sec}, eta {eta})",
        )?
        .progress_chars("=> "),
    );
    let results = pool.install(|| run_sweep(&spec, &|| bar.inc(1)))?;
    bar.finish();
    if json {
        emit(&format!("{}\n", serde_json::to_string_pretty(&results[0])?))?;
    } else if out_dir.is_none() {
        emit(&to_markdown(&results))?;
    }
    if let Some(dir) = out_dir {
        fs::create_dir_all(dir)?;
        fs::write(dir.join("results.csv"), to_csv(&results))?;
        fs::write(
            dir.join("results.json"),
            serde_json::to_string_pretty(&results)?,
        )?;
        fs::write(dir.join("results.md"), to_markdown(&results))?;
        eprintln!("wrote {}/results.{{csv,json,md}}", dir.display());
        if plots {
            for f in plot::fig3(&results, dir)? {
                eprintln!("wrote {}", f.display());
            }
        }
    }
    Ok(())
}
