//! Environment behaviour: determinism, noise streams, termination, the reward correction.

use skyherd_sim::baseline::Method;
use skyherd_sim::env::run_episodes_parallel;
use skyherd_sim::noise::NoiseConfig;
use skyherd_sim::world::{BoidsParams, Goal};
use skyherd_sim::{
    BatchEnv, Env, EnvError, HerderCount, PolicyFactory, RewardCorrection, Scenario, World,
    run_episode,
};

fn small(targets: usize, herders: usize) -> Scenario {
    let mut s = Scenario::paper_drive();
    s.targets = targets;
    s.herders = HerderCount::Fixed(herders);
    s.step_limit = 300;
    s
}

fn trace(scenario: &Scenario, method: Method, seed: u64) -> Vec<World> {
    let mut env = Env::new(scenario.clone()).unwrap();
    let mut policy = method.make();
    let mut states = Vec::new();
    run_episode(&mut env, policy.as_mut(), seed, |w, _| {
        states.push(w.clone())
    })
    .unwrap();
    states
}

#[test]
fn same_seed_same_trace_with_all_noise_on() {
    let s = small(16, 4);
    assert!(!s.noise.is_off());
    let a = trace(&s, Method::Strombom, 11);
    let b = trace(&s, Method::Strombom, 11);
    assert!(a.len() > 10);
    assert_eq!(a, b);
    let c = trace(&s, Method::Strombom, 12);
    assert_ne!(a[0], c[0], "another seed, another episode");
}

#[test]
fn parallel_episodes_match_sequential_ones() {
    let s = small(8, 2);
    let seeds: Vec<u64> = (0..6).collect();
    let par = run_episodes_parallel(&s, &seeds, || {
        skyherd_sim::baseline::RulePolicy::new(Method::Lama)
    })
    .unwrap();
    for (summary, &seed) in par.iter().zip(&seeds) {
        let mut env = Env::new(s.clone()).unwrap();
        let mut p = Method::Lama.make();
        let one = run_episode(&mut env, p.as_mut(), seed, |_, _| {}).unwrap();
        assert_eq!(*summary, one);
    }
}

#[test]
fn noise_streams_are_independent() {
    // With idle herders, sensing noise must not change the true trajectory nor the spawn.
    let quiet = small(8, 2).without_noise();
    let mut sensed = quiet.clone();
    sensed.noise.sensing_std = 2.0;
    let mut a = Env::new(quiet).unwrap();
    let mut b = Env::new(sensed).unwrap();
    a.reset(5);
    b.reset(5);
    assert_eq!(a.world(), b.world());
    assert_ne!(
        b.observation().targets,
        b.world().targets,
        "observation is noisy"
    );
    assert_eq!(
        a.observation(),
        a.world(),
        "noise-free observation is the truth"
    );
    for _ in 0..20 {
        a.step(&[[0.0; 3]; 2]).unwrap();
        b.step(&[[0.0; 3]; 2]).unwrap();
    }
    assert_eq!(a.world(), b.world());
}

#[test]
fn boids_parameter_noise_is_per_episode() {
    let mut env = Env::new(small(4, 1)).unwrap();
    env.reset(1);
    let p1 = env.world().params;
    env.step(&[[0.0; 3]]).unwrap();
    assert_eq!(env.world().params, p1, "fixed within an episode");
    env.reset(2);
    assert_ne!(env.world().params, p1);
    assert_ne!(p1, BoidsParams::PAPER);
    let mut quiet = Env::new(small(4, 1).without_noise()).unwrap();
    quiet.reset(1);
    assert_eq!(quiet.world().params, BoidsParams::PAPER);
}

fn handmade(targets: Vec<[f64; 2]>, herders: Vec<[f64; 3]>) -> World {
    let n = targets.len();
    let s = Scenario::paper_drive();
    World {
        task: s.task,
        area: s.area,
        goal: Goal {
            center: [250.0, 250.0],
            radius: 45.0,
        },
        params: BoidsParams::PAPER,
        limits: s.limits,
        dt: 1.0,
        step: 0,
        herders,
        targets,
        target_velocities: vec![[0.0; 2]; n],
    }
}

#[test]
fn success_terminates_with_the_completion_reward() {
    let mut env = Env::new(small(2, 1).without_noise()).unwrap();
    env.reset_to(
        handmade(
            vec![[250.0, 250.0], [260.0, 250.0]],
            vec![[100.0, 100.0, 2.0]],
        ),
        0,
    )
    .unwrap();
    let out = env.step(&[[0.0; 3]]).unwrap();
    assert!(out.success && out.terminated && !out.truncated && !out.left_area);
    assert!((out.terms.complete - 45.0).abs() < 1e-12);
    assert_eq!(env.step(&[[0.0; 3]]), Err(EnvError::EpisodeOver));
}

#[test]
fn leaving_terminates_with_the_leave_penalty() {
    let mut env = Env::new(small(1, 1).without_noise()).unwrap();
    env.reset_to(handmade(vec![[100.0, 100.0]], vec![[498.0, 300.0, 2.0]]), 0)
        .unwrap();
    let out = env.step(&[[5.0, 0.0, 0.0]]).unwrap();
    assert!(out.left_area && out.terminated && !out.success);
    assert!((out.terms.leave + 180.0).abs() < 1e-12);
    assert!(
        (out.terms.flight + 9.0).abs() < 1e-12,
        "5 m flown: 0.9 * 2 * -5"
    );
}

#[test]
fn step_limit_truncates() {
    let mut s = small(1, 1).without_noise();
    s.step_limit = 3;
    let mut env = Env::new(s).unwrap();
    env.reset_to(handmade(vec![[100.0, 100.0]], vec![[300.0, 300.0, 2.0]]), 0)
        .unwrap();
    let outs: Vec<_> = (0..3).map(|_| env.step(&[[0.0; 3]]).unwrap()).collect();
    assert!(!outs[1].truncated && !outs[1].terminated);
    assert!(outs[2].truncated && !outs[2].terminated);
}

#[test]
fn the_correction_makes_leaving_worse_than_idling() {
    let mut s = small(16, 4).without_noise();
    s.step_limit = 1500;
    s.reward.correction = RewardCorrection::LeaveCoversRemainingSteps { gamma: 0.99 };
    let mut env = Env::new(s).unwrap();
    // 16 targets on a 4 x 4 lattice far from the goal, one herder next to the east wall.
    let targets = (0..16)
        .map(|k| [100.0 + 6.0 * (k % 4) as f64, 100.0 + 6.0 * (k / 4) as f64])
        .collect();
    let herders = vec![
        [498.0, 300.0, 2.0],
        [300.0, 300.0, 2.0],
        [310.0, 300.0, 2.0],
        [320.0, 300.0, 2.0],
    ];
    env.reset_to(handmade(targets, herders), 0).unwrap();
    let out = env
        .step(&[[5.0, 0.0, 0.0], [0.0; 3], [0.0; 3], [0.0; 3]])
        .unwrap();
    assert!(out.left_area && out.terminated);
    // Idling for the whole budget costs about k0 k3 |r3| N = 2.88 per step, discounted.
    let idle: f64 = (0..1500).map(|k| 0.99f64.powi(k) * -2.88).sum();
    assert!(
        out.paper_reward > idle,
        "the paper's reward pays for leaving: {}",
        out.paper_reward
    );
    assert!(
        out.reward < idle,
        "the corrected one does not: {} vs {idle}",
        out.reward
    );
}

#[test]
fn batch_steps_all_environments() {
    let s = small(8, 2);
    let mut batch = BatchEnv::new(&s, 3).unwrap();
    batch.reset_all(&[1, 2, 3]);
    let outs = batch.step_all(&vec![vec![[1.0, 0.0, 0.0]; 2]; 3]).unwrap();
    assert_eq!(outs.len(), 3);
    let mut single = Env::new(s).unwrap();
    single.reset(2);
    single.step(&[[1.0, 0.0, 0.0]; 2]).unwrap();
    assert_eq!(batch.envs()[1].world(), single.world());
    assert!(matches!(
        batch.step_all(&[vec![[0.0; 3]; 2]]),
        Err(EnvError::BatchSize {
            expected: 3,
            got: 1
        })
    ));
}

#[test]
fn indoor_preset_runs_and_keeps_start_and_goal_apart() {
    let s = Scenario::indoor();
    let mut env = Env::new(s.clone()).unwrap();
    for seed in 0..20 {
        env.reset(seed);
        let w = env.world();
        let c = w.flock_centroid();
        let d = ((c[0] - w.goal.center[0]).powi(2) + (c[1] - w.goal.center[1]).powi(2)).sqrt();
        assert!(d > 8.0 - 2.0 * s.layout.start_radius, "seed {seed}: {d}");
        assert!(w.herders.iter().all(|h| h[2] <= s.area.ceiling));
    }
    let mut p = Method::FarthestTargets.make();
    let summary = run_episode(&mut env, p.as_mut(), 0, |_, _| {}).unwrap();
    assert!(summary.steps >= 1 && summary.steps <= s.step_limit);
    let _ = NoiseConfig::NONE;
}

/// `replay_last_step_without(h)` is the step the world would have taken had herder `h` not been
/// there: exactly a step of the world without it, and with actuation noise on, the other
/// herders fly the velocities they were actually flown.
#[test]
fn the_last_step_replays_exactly_without_one_herder() {
    let targets = vec![[100.0, 100.0], [104.0, 101.0], [101.0, 105.0]];
    let mut scratch = skyherd_sim::ReplayScratch::default();

    // Noise-free: the replay is bit for bit a step of an environment that never had herder 1.
    let quiet = small(3, 2).without_noise();
    let mut with = Env::new(quiet.clone()).unwrap();
    with.keep_last_step(true);
    let start = handmade(targets.clone(), vec![[90.0, 95.0, 2.0], [112.0, 92.0, 2.0]]);
    with.reset_to(start.clone(), 0).unwrap();
    let mut out = with.world().clone();
    assert_eq!(
        with.replay_last_step_without(0, &mut out, &mut scratch),
        Ok(false),
        "nothing to replay before the first step"
    );
    with.step(&[[1.0, 0.0, 0.0], [-1.0, 0.5, 0.0]]).unwrap();
    let mut alone = start;
    alone.herders.truncate(1);
    let mut without = Env::new(quiet).unwrap();
    without.reset_to(alone, 0).unwrap();
    without.step(&[[1.0, 0.0, 0.0]]).unwrap();
    assert!(
        with.replay_last_step_without(1, &mut out, &mut scratch)
            .unwrap()
    );
    assert_eq!(&out, without.world());
    assert_ne!(
        out.targets,
        with.world().targets,
        "herder 1 pushed the flock"
    );
    assert_eq!(
        with.replay_last_step_without(2, &mut out, &mut scratch),
        Err(EnvError::NoSuchHerder {
            herder: 2,
            herders: 2
        })
    );

    // Actuation noise on: the others' flown (noisy) velocities are replayed, so a herder 400 m
    // away moves the flock by millimetres, and without the herder beside the flock it barely moves.
    let mut s = small(3, 2);
    s.noise.sensing_std = 0.0;
    s.noise.boids_param_rel_std = 0.0;
    assert!(s.noise.actuation_std > 0.0);
    let mut env = Env::new(s).unwrap();
    env.keep_last_step(true);
    env.reset_to(
        handmade(targets, vec![[90.0, 95.0, 2.0], [400.0, 400.0, 2.0]]),
        3,
    )
    .unwrap();
    for _ in 0..3 {
        env.step(&[[2.0, 1.0, 0.0], [-3.0, 0.0, 0.0]]).unwrap();
    }
    assert!(
        env.replay_last_step_without(1, &mut out, &mut scratch)
            .unwrap()
    );
    assert_eq!(out.herders, env.world().herders[..1]);
    for (a, b) in out.targets.iter().zip(&env.world().targets) {
        assert!((a[0] - b[0]).abs() < 1e-2 && (a[1] - b[1]).abs() < 1e-2);
    }
    assert!(
        env.replay_last_step_without(0, &mut out, &mut scratch)
            .unwrap()
    );
    let speed = |w: &World| {
        w.target_velocities
            .iter()
            .map(|v| v[0].hypot(v[1]))
            .sum::<f64>()
    };
    assert!(speed(&out) < 0.5 * speed(env.world()));
    env.reset(4);
    assert_eq!(
        env.replay_last_step_without(0, &mut out, &mut scratch),
        Ok(false),
        "a reset leaves nothing to replay"
    );
}
