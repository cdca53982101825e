//! What a trained critic thinks of Lama's actions: along the states of a flown trajectory
//! (Lama's or the actor's own), each herder's `Q(s, a)` for the actor's action, for the action
//! Lama's rule takes in that state, and for hovering, read by the checkpoint's first critic.
//!
//! `Q(s, a)` is the value of taking `a` once and then following the actor, so where Lama's
//! action reads higher than the actor's the actor is not at a maximum of its own critic
//! (its gradient steps have not found the better action); where it reads lower the critic
//! itself does not see the better behaviour (a value-learning or exploration shortfall).
//! Beside it, on Lama's own trajectory: the critic's value of the actor in each state
//! (`Q(s, mu(s))`) against the discounted return Lama goes on to collect from there under the
//! run's reward, both in the critic's units (times `ddpg.reward_scale`).
//!
//! ```sh
//! cargo run --release -p skyherd-trainer --example critic_probe -- \
//!     runs/mtddpg-scratch32/mtddpg-seed127/best.safetensors collecting 4 4 24 3900000000 lama
//! ```
//! Arguments: checkpoint, task (`driving` or `collecting`), N, M, episodes, first seed, and
//! whose trajectory to follow (`lama` or `actor`). Test noise is on, as in evaluation.

use std::path::Path;

use anyhow::{Context, bail};
use skyherd_onboard::obs::FEATURES;
use skyherd_sim::baseline::{Method, RulePolicy};
use skyherd_sim::obs::EncoderBuffers;
use skyherd_sim::policy::act_all;
use skyherd_sim::task::parse_task;
use skyherd_sim::{Env, Policy};
use skyherd_trainer::ddpg::ACTION_DIM;
use skyherd_trainer::rollout::Draw;
use skyherd_trainer::{audit, checkpoint};

/// A labelled subset of the samples.
type Group = (&'static str, fn(&Sample) -> bool);

/// One herder in one state.
struct Sample {
    step: u64,
    /// Ground distance to the nearest target, metres.
    nearest_m: f64,
    q_actor: f32,
    q_lama: f32,
    q_hover: f32,
    /// The return the followed policy went on to collect from this state (critic units).
    return_to_go: f32,
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [path, task, n, m, episodes, seed_base, follow] = args.as_slice() else {
        bail!("usage: critic_probe CHECKPOINT TASK N M EPISODES SEED_BASE lama|actor");
    };
    let task = parse_task(task).with_context(|| format!("unknown task `{task}`"))?;
    let targets: usize = n.parse().context("N")?;
    let herders: usize = m.parse().context("M")?;
    let episodes: u64 = episodes.parse().context("EPISODES")?;
    let seed_base: u64 = seed_base.parse().context("SEED_BASE")?;
    let follow_lama = match follow.as_str() {
        "lama" => true,
        "actor" => false,
        other => bail!("follow `lama` or `actor`, not `{other}`"),
    };
    let cp = checkpoint::load(Path::new(path))?;
    let agent = &cp.agent;
    let config = &cp.config;
    if agent.context_dim() != 0 {
        bail!(
            "a centralised critic needs the other herders' context; this probe reads plain critics"
        );
    }
    let gamma = f64::from(config.ddpg.gamma);
    let scale = config.ddpg.reward_scale;
    let planar = config.ddpg.planar;
    let draw = Draw::paper(task, targets, herders);
    let mut samples = Vec::new();
    let mut buffers = EncoderBuffers::default();
    let mut features = [0.0_f32; FEATURES];
    // An actor made for an older encoder reads the prefix that is its encoding.
    let width = agent.actor.inputs();
    for k in 0..episodes {
        let seed = seed_base + k;
        let (scenario, mut reward) = audit::audited_setup(config, draw);
        let mut env = Env::new(scenario)?;
        env.reset(seed);
        let mut lama = RulePolicy::new(Method::Lama);
        lama.reset(env.observation(), seed);
        reward.start(&mut env);
        let (mut lama_v, mut actor_v, mut rewards) = (Vec::new(), Vec::new(), Vec::new());
        let mut episode: Vec<Vec<Sample>> = Vec::new();
        let mut per_step_rewards: Vec<Vec<f32>> = Vec::new();
        loop {
            let world = env.observation().clone();
            act_all(&mut lama, &world, &mut lama_v);
            buffers.fill(&world);
            actor_v.clear();
            let mut here = Vec::new();
            for (h, lv) in lama_v.iter().enumerate() {
                let frame = buffers
                    .encode(h, &mut features)
                    .map_err(|e| anyhow::anyhow!("encoding herder {h}: {e:?}"))?;
                let mut a = agent.act(task.index(), &features[..width]);
                if planar {
                    a[2] = 0.0;
                }
                actor_v.push(frame.action_to_world(a).map(f64::from));
                let max_speed = world.limits.herder;
                let local =
                    frame.to_local([(lv[0] / max_speed) as f32, (lv[1] / max_speed) as f32]);
                let vz = if planar {
                    0.0
                } else {
                    (lv[2] / max_speed) as f32
                };
                let a_lama = [local[0], local[1], vz].map(|x| x.clamp(-1.0, 1.0));
                let q = |action: [f32; ACTION_DIM]| {
                    agent.q_value(task.index(), &features[..width], action)
                };
                let p = world.herders[h];
                let nearest_m = world
                    .targets
                    .iter()
                    .map(|t| (t[0] - p[0]).hypot(t[1] - p[1]))
                    .fold(f64::INFINITY, f64::min);
                here.push(Sample {
                    step: world.step,
                    nearest_m,
                    q_actor: q(a),
                    q_lama: q(a_lama),
                    q_hover: q([0.0; ACTION_DIM]),
                    return_to_go: 0.0,
                });
            }
            let velocities = if follow_lama { &lama_v } else { &actor_v };
            let out = env.step(velocities)?;
            reward.step(&out, &env, velocities, &mut rewards);
            episode.push(here);
            per_step_rewards.push(rewards.iter().map(|r| r * scale).collect());
            if out.terminated || out.truncated {
                break;
            }
        }
        // Each herder's discounted return from every step on (a truncated episode's tail is
        // cut, so its late returns read high; the probe reports early states).
        let mut to_go = vec![0.0_f32; per_step_rewards[0].len()];
        for (state, r) in episode.iter_mut().zip(&per_step_rewards).rev() {
            for ((sample, g), r) in state.iter_mut().zip(to_go.iter_mut()).zip(r) {
                *g = r + gamma as f32 * *g;
                sample.return_to_go = *g;
            }
        }
        samples.extend(episode.into_iter().flatten());
    }
    println!(
        "{path}: {task:?}, N = {targets}, M = {herders}, {episodes} episodes from {seed_base}, following {follow}; Q in the critic's units"
    );
    println!(
        "| states | herder-states | Q(s, actor) | Q(s, Lama) | Q(s, hover) | Lama's action reads higher | return to go of the followed policy |"
    );
    println!("|---|---|---|---|---|---|---|");
    let groups: [Group; 5] = [
        ("all", |_| true),
        ("steps 0-39", |s| s.step < 40),
        ("steps 40+", |s| s.step >= 40),
        ("herder > 40 m from its nearest target", |s| {
            s.nearest_m > 40.0
        }),
        ("herder <= 20 m from its nearest target", |s| {
            s.nearest_m <= 20.0
        }),
    ];
    for (label, keep) in groups {
        let picked: Vec<&Sample> = samples.iter().filter(|s| keep(s)).collect();
        if picked.is_empty() {
            continue;
        }
        let mean = |f: &dyn Fn(&Sample) -> f32| {
            picked.iter().map(|s| f64::from(f(s))).sum::<f64>() / picked.len() as f64
        };
        let higher = picked.iter().filter(|s| s.q_lama > s.q_actor).count();
        println!(
            "| {label} | {} | {:.3} | {:.3} | {:.3} | {:.0} % | {:.3} |",
            picked.len(),
            mean(&|s| s.q_actor),
            mean(&|s| s.q_lama),
            mean(&|s| s.q_hover),
            100.0 * higher as f64 / picked.len() as f64,
            mean(&|s| s.return_to_go),
        );
    }
    Ok(())
}
