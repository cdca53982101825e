//! Seeded worlds and models shared by the integration tests.
#![allow(dead_code)]

use skyherd_model::{ActorShape, FloatActor, ModelMeta, SplitMix64, Task, quantize};
use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES, ObsInput, encode};

/// A random paper-like world: `n` targets in a loose flock, `m` herders around it.
pub struct World {
    pub herders: Vec<[f32; 3]>,
    pub targets: Vec<[f32; 2]>,
    pub goal: [f32; 2],
    pub task: Task,
}

impl World {
    pub fn random(rng: &mut SplitMix64, n: usize, m: usize) -> World {
        let centre = [
            rng.uniform(80.0, 420.0) as f32,
            rng.uniform(80.0, 420.0) as f32,
        ];
        let spread = rng.uniform(5.0, 120.0);
        let targets = (0..n)
            .map(|_| {
                [
                    (centre[0] as f64 + rng.uniform(-spread, spread)).clamp(0.0, 500.0) as f32,
                    (centre[1] as f64 + rng.uniform(-spread, spread)).clamp(0.0, 500.0) as f32,
                ]
            })
            .collect();
        let herders = (0..m)
            .map(|_| {
                [
                    rng.uniform(0.0, 500.0) as f32,
                    rng.uniform(0.0, 500.0) as f32,
                    rng.uniform(0.5, 10.0) as f32,
                ]
            })
            .collect();
        let goal = [
            rng.uniform(45.0, 455.0) as f32,
            rng.uniform(45.0, 455.0) as f32,
        ];
        let task = Task::ALL[(rng.next_u64() % 2) as usize];
        World {
            herders,
            targets,
            goal,
            task,
        }
    }

    pub fn input(&self, own_index: usize) -> ObsInput<'_> {
        ObsInput {
            own_index,
            herders: &self.herders,
            targets: &self.targets,
            goal: self.goal,
            goal_radius: 45.0,
            area: [500.0, 500.0, 10.0],
            max_speed: 5.0,
        }
    }

    pub fn features(&self, own_index: usize) -> [f32; FEATURES] {
        let mut out = [0.0; FEATURES];
        encode(&self.input(own_index), &mut out).unwrap();
        out
    }
}

/// `count` recorded-style observations from random worlds with 1..=300 targets, 1..=16 herders.
pub fn observations(seed: u64, count: usize) -> Vec<(Task, [f32; FEATURES])> {
    let mut rng = SplitMix64::new(seed);
    (0..count)
        .map(|_| {
            let n = 1 + (rng.next_u64() % 300) as usize;
            let m = 1 + (rng.next_u64() % 16) as usize;
            let world = World::random(&mut rng, n, m);
            (
                world.task,
                world.features((rng.next_u64() % m as u64) as usize),
            )
        })
        .collect()
}

/// A seeded (untrained) actor quantized with calibration on `observations(seed ^ 1, 2000)`.
pub fn seeded_model(shape: ActorShape, seed: u64) -> (FloatActor, Vec<u8>) {
    let float = FloatActor::random(shape, seed);
    let calibration = observations(seed ^ 1, 2000);
    let meta = ModelMeta {
        encoder_version: ENCODER_VERSION,
        max_speed: 5.0,
    };
    let bytes = quantize(&float, meta, calibration.iter().map(|(t, f)| (*t, &f[..]))).unwrap();
    (float, bytes)
}
