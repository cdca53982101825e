//! The reward audit on the committed configs: the shipped config's paper reward fails the gate
//! (hovering beats every rule), the from-scratch configs' audited rewards pass it.

use std::path::Path;

use skyherd_model::Task;
use skyherd_trainer::audit::{Candidate, audit, gate};
use skyherd_trainer::config::TrainConfig;
use skyherd_trainer::rollout::Draw;

fn config(name: &str) -> TrainConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("configs")
        .join(name);
    TrainConfig::load(&path).expect("committed config loads")
}

fn small_set() -> Vec<Draw> {
    vec![
        Draw::paper(Task::Driving, 4, 4),
        Draw::paper(Task::Driving, 16, 4),
        Draw::paper(Task::Collecting, 8, 4),
    ]
}

#[test]
fn under_the_shipped_reward_hovering_beats_the_rules() {
    let rows = audit(
        &config("mtddpg-v1.toml"),
        &small_set(),
        &Candidate::hover_and_rules(),
        4,
        3_600_000_000,
    )
    .expect("the small set is valid");
    let report = gate(&rows);
    assert!(!report.passed);
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.contains("lama") && p.contains("hovering")),
        "{:?}",
        report.problems
    );
}

#[test]
fn the_from_scratch_configs_pass_the_audit() {
    for name in [
        "mtddpg-scratch.toml",
        "mtddpg-scratch2.toml",
        "mtddpg-scratch6.toml",
        "mtddpg-scratch9.toml",
        "mtddpg-scratch13.toml",
        "mtddpg-scratch15.toml",
        "mtddpg-scratch16.toml",
        "mtddpg-scratch17.toml",
        "mtddpg-scratch21.toml",
        "mtddpg-scratch22.toml",
        "mtddpg-scratch30.toml",
        "mtddpg-scratch42.toml",
    ] {
        passes(name);
    }
}

fn passes(name: &str) {
    let rows = audit(
        &config(name),
        &small_set(),
        &Candidate::hover_and_rules(),
        4,
        3_600_000_000,
    )
    .expect("the small set is valid");
    let report = gate(&rows);
    assert!(report.passed, "{name}: {:?}", report.problems);
    // Something succeeds in every scenario, so the gate had something to judge.
    for draw in small_set() {
        assert!(
            rows.iter()
                .any(|r| r.draw == draw && r.policy != "hover" && r.success_rate >= 0.9)
        );
    }
}
