//! How large an undisturbed flock settles, against the goal circle it must fit into.
//!
//! Driving succeeds when every target is inside the goal (radius 45 m in the paper's world). The
//! boids' separation (eq 2: `a1 / d^2` within `G1 = 5 m`) holds targets about one separation
//! range apart, so a large flock at rest is wider than the goal, and the herders must squeeze it.
//! This places N targets as the paper-drive preset does, keeps the herder far away, lets eqs
//! (1)-(6) run for 600 s (noise-free) and prints the settled flock's radius around its centroid
//! and how many targets a goal-sized circle there would hold.
//!
//! ```sh
//! cargo run --release -p skyherd-sim --example flock_size
//! ```

use skyherd_sim::scenario::HerderCount;
use skyherd_sim::world::{StepScratch, advance};
use skyherd_sim::{Env, Scenario};

fn main() {
    let settle_steps = 600;
    println!("paper-drive boids, herder 10 km away, {settle_steps} s, seed 1");
    println!(
        "| N | flock radius (max) | 90th percentile | within 45 m of the centroid | nearest-neighbour spacing (median) |"
    );
    println!("|---|---|---|---|---|");
    for n in [16usize, 64, 128, 256, 512, 1024] {
        let mut scenario = Scenario::paper_drive();
        scenario.targets = n;
        scenario.herders = HerderCount::Fixed(1);
        let goal_radius = scenario.layout.goal_radius;
        let mut env = Env::new(scenario).expect("the paper-drive preset is valid");
        let mut world = env.reset(1).clone();
        world.herders = vec![[-10_000.0, -10_000.0, 2.0]];
        let mut scratch = StepScratch::with_capacity(n);
        for _ in 0..settle_steps {
            advance(&mut world, &[[0.0; 3]], &mut scratch).expect("a valid world");
        }
        let c = world.flock_centroid();
        let distance = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
        let mut radii: Vec<f64> = world.targets.iter().map(|t| distance(*t, c)).collect();
        radii.sort_by(f64::total_cmp);
        let mut spacing: Vec<f64> = world
            .targets
            .iter()
            .enumerate()
            .map(|(i, a)| {
                world
                    .targets
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, b)| distance(*a, *b))
                    .fold(f64::INFINITY, f64::min)
            })
            .collect();
        spacing.sort_by(f64::total_cmp);
        let inside = radii.iter().filter(|r| **r <= goal_radius).count();
        println!(
            "| {n} | {:.1} m | {:.1} m | {inside} ({:.0} %) | {:.2} m |",
            radii[n - 1],
            radii[n * 9 / 10],
            100.0 * inside as f64 / n as f64,
            spacing[n / 2]
        );
    }
}
