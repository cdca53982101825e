//! Steps per second of on-CPU time (Linux): the benchmark's configurations timed by the thread's
//! own CPU clock, so that a busy shared machine does not distort them as much as wall time.
//!
//! `cargo run --release -p skyherd-sim --example steps_per_cpu_second`
use skyherd_sim::world::{StepScratch, advance, reference_step};
use skyherd_sim::{Env, HerderCount, Scenario};
/// Seconds this thread has run on a CPU (first field of `/proc/thread-self/schedstat`, ns).
fn oncpu() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .map_or(f64::NAN, |ns| ns * 1e-9)
}
fn main() {
    for &(n, m) in &[
        (16, 4),
        (100, 4),
        (1024, 4),
        (16, 10),
        (100, 10),
        (1024, 10),
    ] {
        let mut s = Scenario::paper_drive().without_noise();
        s.targets = n;
        s.herders = HerderCount::Fixed(m);
        s.step_limit = u64::MAX / 2;
        let mut env = Env::new(s).unwrap();
        env.reset(1);
        let a = vec![[0.0; 3]; m];
        for _ in 0..20 {
            env.step(&a).unwrap();
        }
        let start = env.world().clone();
        let iters = (2_000_000 / n).max(2000);
        let t = oncpu();
        let mut seed = 1;
        for _ in 0..iters {
            let o = env.step(&a).unwrap();
            if o.terminated || o.truncated {
                seed += 1;
                env.reset(seed);
            }
        }
        let env_rate = iters as f64 / (oncpu() - t);
        let mut w = start.clone();
        let mut sc = StepScratch::with_capacity(n);
        let t = oncpu();
        for _ in 0..iters {
            if w.step.is_multiple_of(200) {
                w.clone_from(&start);
            }
            advance(&mut w, &a, &mut sc).unwrap();
        }
        let grid_rate = iters as f64 / (oncpu() - t);
        let it2 = (iters / 20).max(50);
        let mut w = start.clone();
        let t = oncpu();
        for _ in 0..it2 {
            if w.step.is_multiple_of(200) {
                w.clone_from(&start);
            }
            reference_step(&mut w, &a).unwrap();
        }
        let naive_rate = it2 as f64 / (oncpu() - t);
        println!(
            "N={n:5} M={m:3}  env {env_rate:>10.0}/s  grid {grid_rate:>10.0}/s  naive {naive_rate:>10.0}/s"
        );
    }
}
