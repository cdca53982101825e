//! Tracker update time at 1024 targets, 10 Hz, with 10% misses and 20 false alarms per scan.

// criterion_group! generates an undocumented pub fn.
#![allow(missing_docs)]

#[path = "../tests/support/scenario.rs"]
mod scenario;

use criterion::{Criterion, criterion_group, criterion_main};
use scenario::{Scenario, ScenarioConfig};
use skyherd_ground::tracking::{Tracker, TrackerConfig};
use std::hint::black_box;
use std::time::{Duration, Instant};

fn tracker_1024(c: &mut Criterion) {
    let config = ScenarioConfig {
        targets: 1024,
        // ~39 m^2 per target: about 6 m apart, like a 1024-head flock held near the goal.
        arena: 200.0,
        dt: 0.1,
        max_speed: 3.0,
        accel_std: 1.0,
        measurement_std: 0.3,
        p_detect: 0.9,
        false_alarms_per_scan: 20,
    };
    let mut world = Scenario::new(config, 42);
    let scans: Vec<Vec<[f64; 2]>> = (0..300)
        .map(|_| {
            world.step();
            world.detect()
        })
        .collect();
    let warmup = 30;
    let mut warm = Tracker::new(TrackerConfig::default()).unwrap();
    for scan in &scans[..warmup] {
        warm.update(0.1, scan).unwrap();
    }
    let confirmed = warm.confirmed().count();
    assert!(confirmed > 950, "warm-up confirmed only {confirmed} tracks");

    c.bench_function("tracker_update_1024_targets", |b| {
        b.iter_custom(|iters| {
            let mut tracker = warm.clone();
            let mut k = warmup;
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                if k == scans.len() {
                    // Replaying from the start would teleport every target: restart warm.
                    tracker = warm.clone();
                    k = warmup;
                }
                let start = Instant::now();
                black_box(tracker.update(0.1, black_box(&scans[k])).unwrap());
                total += start.elapsed();
                k += 1;
            }
            total
        })
    });
}

criterion_group!(benches, tracker_1024);
criterion_main!(benches);
