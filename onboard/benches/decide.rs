//! One drone decision on the host: `obs::encode` + `Actor::infer` for N = 16, 256, 1024 targets,
//! with M = 4 herders and with the adaptive M = 2^floor(log2(N) / 2). Checks zero heap use with
//! a counting allocator. Model: the mission's `models/mtddpg-v3.skym` (encoder v4, F = 51,
//! H = 128, S = 1), what flies; inference alone also for a seeded F = 51, H = 64, S = 2 model (the
//! timing does not depend on the weights, only on the shape).
#![allow(missing_docs)]
// The counting allocator that proves "zero heap" must implement `GlobalAlloc`, an unsafe trait;
// it only forwards to `System`.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::hint::black_box;
use std::sync::atomic::{AtomicUsize, Ordering};

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use skyherd_model::{ActorShape, FloatActor, ModelMeta, SplitMix64, Task, quantize};
use skyherd_onboard::actor::Actor;
use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES, ObsInput, encode};

struct Counting;
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

struct World {
    herders: Vec<[f32; 3]>,
    targets: Vec<[f32; 2]>,
}

fn world(n: usize, m: usize) -> World {
    let mut rng = SplitMix64::new(n as u64 * 31 + m as u64);
    World {
        herders: (0..m)
            .map(|_| {
                [
                    rng.uniform(0.0, 500.0) as f32,
                    rng.uniform(0.0, 500.0) as f32,
                    2.0,
                ]
            })
            .collect(),
        targets: (0..n)
            .map(|_| {
                [
                    rng.uniform(150.0, 350.0) as f32,
                    rng.uniform(150.0, 350.0) as f32,
                ]
            })
            .collect(),
    }
}

fn input(w: &World) -> ObsInput<'_> {
    ObsInput {
        own_index: 0,
        herders: &w.herders,
        targets: &w.targets,
        goal: [400.0, 400.0],
        goal_radius: 45.0,
        area: [500.0, 500.0, 10.0],
        max_speed: 5.0,
    }
}

/// The mission's model file.
fn shipped_model() -> Vec<u8> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/mtddpg-v3.skym");
    std::fs::read(path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// A seeded, untrained H = 64, S = 2 model.
fn seeded_model() -> Vec<u8> {
    let shape = ActorShape {
        features: FEATURES,
        hidden: 64,
        shared_layers: 2,
    };
    let calibration: Vec<[f32; FEATURES]> = [16, 256, 1024]
        .iter()
        .map(|&n| {
            let mut f = [0.0; FEATURES];
            encode(&input(&world(n, 4)), &mut f).unwrap();
            f
        })
        .collect();
    let meta = ModelMeta {
        encoder_version: ENCODER_VERSION,
        max_speed: 5.0,
    };
    quantize(
        &FloatActor::random(shape, 1),
        meta,
        calibration.iter().map(|f| (Task::Driving, &f[..])),
    )
    .unwrap()
}

fn decide(actor: &Actor<'_>, input: &ObsInput<'_>) -> [f32; 3] {
    let mut features = [0.0; FEATURES];
    match encode(input, &mut features) {
        Ok(frame) => frame.action_to_world(actor.infer(Task::Driving, &features)),
        Err(_) => [0.0; 3],
    }
}

/// Nanoseconds this thread has spent on a CPU (Linux `schedstat`), so that the per-decision
/// figure printed beside criterion's wall-clock one is not inflated by a loaded machine.
fn thread_cpu_ns() -> Option<u64> {
    let stat = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    stat.split_whitespace().next()?.parse().ok()
}

fn cpu_time_per_call(mut f: impl FnMut()) -> Option<f64> {
    const CALLS: u32 = 20_000;
    let start = thread_cpu_ns()?;
    for _ in 0..CALLS {
        f();
    }
    Some((thread_cpu_ns()? - start) as f64 / CALLS as f64 / 1000.0)
}

fn bench(c: &mut Criterion) {
    let shipped = shipped_model();
    let actor = Actor::from_bytes(&shipped).unwrap();
    let mut group = c.benchmark_group("decide");
    for n in [16usize, 256, 1024] {
        let adaptive = 1usize << ((n.ilog2() / 2) as usize);
        for m in [4, adaptive] {
            let w = world(n, m);
            let before = ALLOCATIONS.load(Ordering::Relaxed);
            for _ in 0..100 {
                black_box(decide(&actor, &input(&w)));
            }
            let allocations = ALLOCATIONS.load(Ordering::Relaxed) - before;
            assert_eq!(allocations, 0, "encode + infer allocated at N={n}, M={m}");
            if let Some(us) = cpu_time_per_call(|| {
                black_box(decide(&actor, black_box(&input(&w))));
            }) {
                println!(
                    "thread CPU time per decision, N={n} M={m}: {us:.2} us (zero heap allocations)"
                );
            }
            group.bench_with_input(
                BenchmarkId::new(format!("encode+infer/M={m}"), n),
                &w,
                |b, w| b.iter(|| decide(&actor, black_box(&input(w)))),
            );
            if m == adaptive {
                break;
            }
        }
    }
    let w = world(1024, 4);
    let mut features = [0.0; FEATURES];
    encode(&input(&w), &mut features).unwrap();
    let mut scratch = [0.0; FEATURES];
    group.bench_function("encode only (N=1024, M=4)", |b| {
        b.iter(|| encode(black_box(&input(&w)), &mut scratch).map(|frame| frame.forward))
    });
    let seeded = seeded_model();
    let small = Actor::from_bytes(&seeded).unwrap();
    group.bench_function("encode+infer, seeded H=64, S=2 (N=1024, M=4)", |b| {
        b.iter(|| decide(&small, black_box(&input(&w))))
    });
    for (name, actor) in [
        ("shipped, H=128, S=1", &actor),
        ("seeded, H=64, S=2", &small),
    ] {
        if let Some(us) = cpu_time_per_call(|| {
            black_box(actor.infer(Task::Driving, black_box(&features)));
        }) {
            println!("thread CPU time per infer ({name}): {us:.2} us");
        }
        group.bench_function(format!("infer only ({name})"), |b| {
            b.iter(|| actor.infer(Task::Driving, black_box(&features)))
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
