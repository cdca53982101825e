//! Which features a trained actor steers by: along the actor's own trajectories, for each
//! feature group, how far its actions move when that group's values are swapped for those of
//! another state drawn at random (permutation importance, RMS over the planar action,
//! normalised units), and how well the action lines up with each "relative" point feature
//! (mean cosine between the planar action and the feature's vector, both in the local frame).
//!
//! ```sh
//! cargo run --release -p skyherd-trainer --example feature_use -- \
//!     runs/mtddpg-scratch37/mtddpg-seed143/best.safetensors collecting 4 4 24 3900000000
//! ```
//! Arguments: checkpoint, task, N, M, episodes, first seed. Test noise is on, as in evaluation.

use std::ops::Range;
use std::path::Path;

use anyhow::{Context, bail};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use skyherd_onboard::obs::{FEATURES, feature};
use skyherd_sim::Env;
use skyherd_sim::obs::EncoderBuffers;
use skyherd_sim::task::parse_task;
use skyherd_trainer::rollout::Draw;
use skyherd_trainer::{audit, checkpoint};

/// The feature groups, as `skyherd_onboard::obs` documents them.
/// (A model made for an older encoder does not read the newer groups: they move nothing.)
const GROUPS: [(&str, Range<usize>); 30] = [
    ("goal", feature::GOAL),
    ("centroid", feature::CENTROID),
    ("farthest target", feature::FARTHEST_TARGET),
    ("farthest to edge", 6..7),
    ("flock radius", 7..8),
    ("mean spread", 8..9),
    ("in goal", 9..10),
    ("centroid to goal", 10..11),
    ("share farthest", feature::SHARE_FARTHEST),
    ("share", 13..14),
    ("share farthest to edge", 14..15),
    ("share behind", feature::SHARE_BEHIND),
    ("flock behind", feature::FLOCK_BEHIND),
    ("nearest target", feature::NEAREST_TARGET),
    ("nearest target distance", 21..22),
    ("nearest herder", feature::NEAREST_HERDER),
    ("nearest herder distance", 25..26),
    ("other herders", feature::OTHER_HERDERS),
    ("counts (not alone, M, N)", 26..27),
    ("from centroid", feature::FROM_CENTROID),
    ("octants", feature::OCTANTS),
    ("nearest wall", feature::NEAREST_WALL),
    ("wall distances", 43..45),
    ("nearby targets", 45..46),
    ("ring slot", feature::RING_SLOT),
    ("ring way", feature::RING_WAY),
    ("ring bearing", 50..51),
    ("assigned", feature::ASSIGNED),
    ("assigned to edge", 53..54),
    ("assigned behind", feature::ASSIGNED_BEHIND),
];

/// The point features whose direction an action may follow.
const POINTS: [(&str, Range<usize>); 11] = [
    ("goal", feature::GOAL),
    ("centroid", feature::CENTROID),
    ("farthest target", feature::FARTHEST_TARGET),
    ("share farthest", feature::SHARE_FARTHEST),
    ("share behind", feature::SHARE_BEHIND),
    ("flock behind", feature::FLOCK_BEHIND),
    ("nearest target", feature::NEAREST_TARGET),
    ("ring slot", feature::RING_SLOT),
    ("ring way", feature::RING_WAY),
    ("assigned", feature::ASSIGNED),
    ("assigned behind", feature::ASSIGNED_BEHIND),
];

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [path, task, n, m, episodes, seed_base] = args.as_slice() else {
        bail!("usage: feature_use CHECKPOINT TASK N M EPISODES SEED_BASE");
    };
    let task = parse_task(task).with_context(|| format!("unknown task `{task}`"))?;
    let targets: usize = n.parse().context("N")?;
    let herders: usize = m.parse().context("M")?;
    let episodes: u64 = episodes.parse().context("EPISODES")?;
    let seed_base: u64 = seed_base.parse().context("SEED_BASE")?;
    let cp = checkpoint::load(Path::new(path))?;
    let agent = &cp.agent;
    let draw = Draw::paper(task, targets, herders);
    let mut rows: Vec<[f32; FEATURES]> = Vec::new();
    let mut buffers = EncoderBuffers::default();
    let mut features = [0.0_f32; FEATURES];
    // An actor made for an older encoder reads the prefix that is its encoding.
    let width = agent.actor.inputs();
    let mut velocities = Vec::new();
    for k in 0..episodes {
        let (scenario, _) = audit::audited_setup(&cp.config, draw);
        let mut env = Env::new(scenario)?;
        env.reset(seed_base + k);
        loop {
            let world = env.observation().clone();
            buffers.fill(&world);
            velocities.clear();
            for h in 0..world.herders.len() {
                let frame = buffers
                    .encode(h, &mut features)
                    .map_err(|e| anyhow::anyhow!("encoding herder {h}: {e:?}"))?;
                let mut a = agent.act(task.index(), &features[..width]);
                a[2] = 0.0;
                velocities.push(frame.action_to_world(a).map(f64::from));
                rows.push(features);
            }
            let out = env.step(&velocities)?;
            if out.terminated || out.truncated {
                break;
            }
        }
    }
    let act = |x: &[f32; FEATURES]| {
        let a = agent.act(task.index(), &x[..width]);
        [a[0], a[1]]
    };
    let actions: Vec<[f32; 2]> = rows.iter().map(act).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    println!(
        "{path}: {task:?}, N = {targets}, M = {herders}, {episodes} episodes from {seed_base}, the actor's own trajectories, {} herder-states",
        rows.len()
    );
    println!();
    println!("| feature group | action moved (RMS, planar) when swapped |");
    println!("|---|---|");
    let mut moved: Vec<(f64, &str)> = GROUPS
        .iter()
        .map(|(name, range)| {
            let mut sum = 0.0_f64;
            for (x, a) in rows.iter().zip(&actions) {
                let other = &rows[rng.random_range(0..rows.len())];
                let mut y = *x;
                y[range.clone()].copy_from_slice(&other[range.clone()]);
                let b = act(&y);
                sum += f64::from((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2));
            }
            ((sum / (2 * rows.len()) as f64).sqrt(), *name)
        })
        .collect();
    moved.sort_by(|a, b| b.0.total_cmp(&a.0));
    for (d, name) in moved {
        println!("| {name} | {d:.3} |");
    }
    println!();
    println!("| point | mean cosine with the action | share of states within 30 degrees |");
    println!("|---|---|---|");
    for (name, range) in POINTS {
        let (mut cos_sum, mut within, mut count) = (0.0_f64, 0usize, 0usize);
        for (x, a) in rows.iter().zip(&actions) {
            let v = [x[range.start], x[range.start + 1]];
            let (na, nv) = (a[0].hypot(a[1]), v[0].hypot(v[1]));
            if na < 1e-3 || nv < 1e-3 {
                continue;
            }
            let c = f64::from((a[0] * v[0] + a[1] * v[1]) / (na * nv));
            cos_sum += c;
            within += usize::from(c > 30f64.to_radians().cos());
            count += 1;
        }
        if count > 0 {
            println!(
                "| {name} | {:.2} | {:.0} % |",
                cos_sum / count as f64,
                100.0 * within as f64 / count as f64
            );
        }
    }
    Ok(())
}
