//! Environment steps per second at N = 16, 100, 1024 targets with M = 4 and 10 herders: the full
//! `Env::step` (grid separation, reward, termination; noise off), the bare grid `advance`, and
//! the naive O(N^2) `reference_step`, in the same run.
//!
//! `cargo bench -p skyherd-sim --bench step -- --measurement-time 2 --warm-up-time 1`

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_main};
use skyherd_sim::world::{StepScratch, advance, reference_step};
use skyherd_sim::{Env, HerderCount, Scenario, World};

fn scenario(n: usize, m: usize) -> Scenario {
    let mut s = Scenario::paper_drive().without_noise();
    s.targets = n;
    s.herders = HerderCount::Fixed(m);
    s.step_limit = u64::MAX / 2;
    s
}

/// A world some steps into an episode, so that the flock has its working shape.
fn settled_world(n: usize, m: usize) -> World {
    let mut env = Env::new(scenario(n, m)).unwrap_or_else(|e| panic!("{e}"));
    env.reset(1);
    for _ in 0..20 {
        let _ = env.step(&vec![[0.0; 3]; m]);
    }
    env.world().clone()
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("step");
    group.throughput(Throughput::Elements(1));
    for &m in &[4usize, 10] {
        for &n in &[16usize, 100, 1024] {
            let id = format!("N={n}/M={m}");
            let actions = vec![[0.0; 3]; m];
            group.bench_function(BenchmarkId::new("env", &id), |b| {
                let mut env = Env::new(scenario(n, m)).unwrap_or_else(|e| panic!("{e}"));
                let mut seed = 1;
                env.reset(seed);
                b.iter(|| {
                    let out = env
                        .step(black_box(&actions))
                        .unwrap_or_else(|e| panic!("{e}"));
                    if out.terminated || out.truncated {
                        seed += 1;
                        env.reset(seed);
                    }
                    out.reward
                })
            });
            let start = settled_world(n, m);
            group.bench_function(BenchmarkId::new("grid", &id), |b| {
                let mut w = start.clone();
                let mut scratch = StepScratch::with_capacity(n);
                b.iter(|| {
                    if w.step.is_multiple_of(200) {
                        w.clone_from(&start);
                    }
                    advance(&mut w, black_box(&actions), &mut scratch)
                        .unwrap_or_else(|e| panic!("{e}"));
                })
            });
            group.bench_function(BenchmarkId::new("naive", &id), |b| {
                let mut w = start.clone();
                b.iter(|| {
                    if w.step.is_multiple_of(200) {
                        w.clone_from(&start);
                    }
                    reference_step(&mut w, black_box(&actions)).unwrap_or_else(|e| panic!("{e}"));
                })
            });
        }
    }
    group.finish();
}

// criterion's macro generates an undocumented function.
#[allow(missing_docs)]
mod group {
    criterion::criterion_group!(benches, super::bench);
}
use group::benches;
criterion_main!(benches);
