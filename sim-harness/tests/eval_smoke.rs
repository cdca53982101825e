//! A seconds-long run of the evaluation sweep, its reports and its plots.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use skyherd_sim::baseline::Method;
use skyherd_sim::eval::{SweepSpec, run_sweep, to_csv, to_markdown};
use skyherd_sim::{HerderCount, PolicyFactory, Task};

fn spec() -> SweepSpec {
    SweepSpec {
        tasks: vec![Task::Driving, Task::Collecting],
        methods: vec![
            Arc::new(Method::FarthestTargets) as Arc<dyn PolicyFactory>,
            Arc::new(Method::Strombom),
        ],
        herders: vec![HerderCount::Fixed(2), HerderCount::Adaptive],
        targets: vec![1, 4],
        episodes: 3,
        base_seed: 9,
        step_limit: Some(400),
        shard: (0, 1),
        dynamics: None,
    }
}

#[test]
fn small_sweep_runs_reports_and_plots() {
    let count = AtomicUsize::new(0);
    let results = run_sweep(&spec(), &|| {
        count.fetch_add(1, Ordering::Relaxed);
    })
    .unwrap();
    assert_eq!(results.len(), 2 * 2 * 2 * 2);
    assert_eq!(count.load(Ordering::Relaxed), 16 * 3);
    for r in &results {
        assert_eq!(r.episodes, 3);
        assert!((0.0..=1.0).contains(&r.success_rate));
        assert_eq!(r.mean_time_s.is_some(), r.successes > 0);
        if let Some(ratio) = r.mean_time_ratio {
            assert!(ratio >= 1.0, "no episode beats the lower bound: {r:?}");
        }
        assert!(r.step_limit == 400);
    }
    // One target and two herders is easy: the best simple rule must manage it.
    let easy = results
        .iter()
        .find(|r| {
            r.config.targets == 1 && r.config.method == "farthest" && r.config.task == Task::Driving
        })
        .unwrap();
    assert!(easy.successes >= 2, "{easy:?}");
    // Same seeds, same numbers, whatever the thread count.
    let again = run_sweep(&spec(), &|| {}).unwrap();
    assert_eq!(results, again);

    let csv = to_csv(&results);
    assert_eq!(csv.lines().count(), 1 + results.len());
    let md = to_markdown(&results);
    assert!(md.contains("| driving | adaptive (1) | 1 |"), "{md}");

    let dir = std::env::temp_dir().join(format!("skyherd-sim-smoke-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let files = skyherd_sim::plot::fig3(&results, &dir).unwrap();
    assert_eq!(files.len(), 2 * 2 * 2, "png + svg per task and M setting");
    for f in &files {
        assert!(
            std::fs::metadata(f).unwrap().len() > 1000,
            "{}",
            f.display()
        );
    }
    let svg = std::fs::read_to_string(dir.join("fig3-driving-m2.svg")).unwrap();
    assert!(svg.contains("success rate"));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_shard_is_an_error() {
    let mut s = spec();
    s.shard = (2, 2);
    assert!(run_sweep(&s, &|| {}).is_err());
}
