//! Runs `obs::encode_version` a given number of times on one seeded world, for counting
//! instructions: `valgrind --tool=cachegrind` on two counts gives the instructions per encode,
//! a number the noise of a shared machine does not move. The optional fourth argument is the
//! encoder version a model reads (this build's by default).
//!
//! ```sh
//! cargo build --release -p skyherd-onboard --example encode_count
//! valgrind --tool=cachegrind --cache-sim=no target/release/examples/encode_count 1024 4 1000 4
//! ```
use std::hint::black_box;

use skyherd_model::SplitMix64;
use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES, ObsInput, encode_version, feature};

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("N M COUNT [VERSION]"))
        .collect();
    let (n, m, count, version) = match args[..] {
        [n, m, count] => (n, m, count, ENCODER_VERSION),
        [n, m, count, v] => (n, m, count, u16::try_from(v).expect("a version")),
        _ => panic!("usage: encode_count N M COUNT [VERSION]"),
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
        encode_version(&input, version, &mut features).expect("a valid world and version");
        sum += black_box(features[feature::GOAL.start]);
    }
    println!("{sum}");
}
