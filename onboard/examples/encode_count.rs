//! Runs `obs::encode` a given number of times on one seeded world, for counting instructions:
//! `valgrind --tool=cachegrind` on two counts gives the instructions per encode, a number the
//! noise of a shared machine does not move.
//!
//! ```sh
//! cargo build --release -p skyherd-onboard --example encode_count
//! valgrind --tool=cachegrind --cache-sim=no target/release/examples/encode_count 1024 4 1000
//! ```
use std::hint::black_box;

use skyherd_model::SplitMix64;
use skyherd_onboard::obs::{FEATURES, ObsInput, encode, feature};

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("N M COUNT"))
        .collect();
    let [n, m, count] = args[..] else {
        panic!("usage: encode_count N M COUNT");
    };
    let mut rng = SplitMix64::new(n as u64 * 31 + m as u64);
    let herders: Vec<[f32; 3]> = (0..m)
        .map(|_| {
            [
                rng.uniform(0.0, 500.0) as f32,
                rng.uniform(0.0, 500.0) as f32,
                2.0,
            ]
        })
        .collect();
    let targets: Vec<[f32; 2]> = (0..n)
        .map(|_| {
            [
                rng.uniform(150.0, 350.0) as f32,
                rng.uniform(150.0, 350.0) as f32,
            ]
        })
        .collect();
    let mut features = [0.0f32; FEATURES];
    let mut sum = 0.0;
    for k in 0..count {
        let input = ObsInput {
            own_index: k % m,
            herders: black_box(&herders),
            targets: black_box(&targets),
            goal: [400.0, 400.0],
            goal_radius: 45.0,
            area: [500.0, 500.0, 10.0],
            max_speed: 5.0,
        };
        encode(&input, &mut features).expect("a valid world");
        sum += black_box(features[feature::GOAL.start]);
    }
    println!("{sum}");
}
