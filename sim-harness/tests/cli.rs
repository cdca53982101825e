//! The `skyherd-sim` binary: `step` round trip, `run` traces, clear errors for bad input.

use std::path::PathBuf;
use std::process::Command;

use skyherd_sim::trace::{StepState, TraceLine};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_skyherd-sim"))
}

fn temp(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("skyherd-sim-cli-{}-{name}", std::process::id()))
}

const STATE: &str = r#"{
  "world": {
    "task": "driving",
    "area": { "width": 500.0, "depth": 500.0, "ceiling": 10.0 },
    "goal": { "center": [400.0, 400.0], "radius": 45.0 },
    "params": { "separation": 100.0, "alignment": 0.05, "cohesion": 0.01, "flock": 0.5, "herder": 600.0, "separation_range": 5.0 },
    "limits": { "target": 3.0, "herder": 5.0 },
    "dt": 1.0,
    "step": 0,
    "herders": [[80.0, 100.0, 0.0]],
    "targets": [[100.0, 100.0], [100.0, 104.0]],
    "target_velocities": [[0.0, 0.0], [0.5, 0.0]]
  },
  "actions": [[5.0, 0.0, 0.0]]
}"#;

#[test]
fn step_matches_the_readme_example_and_round_trips() {
    let path = temp("state.json");
    std::fs::write(&path, STATE).unwrap();
    let out = bin().args(["step", "--state"]).arg(&path).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let next: StepState = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(next.world.step, 1);
    assert_eq!(next.world.herders, vec![[85.0, 100.0, 0.0]]);
    // The numbers quoted in README.md.
    assert!((next.world.targets[0][0] - 101.95360273124975).abs() < 1e-12);
    assert!((next.world.targets[1][1] - 106.52447293905882).abs() < 1e-12);
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn bad_state_is_a_clear_error_not_a_panic() {
    let path = temp("bad.json");
    std::fs::write(&path, STATE.replace("\"dt\": 1.0", "\"dt\": -1.0")).unwrap();
    let out = bin().args(["step", "--state"]).arg(&path).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("`dt`"));
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn bad_scenario_file_names_the_field() {
    let path = temp("bad.toml");
    std::fs::write(
        &path,
        "base = \"paper-drive\"\n[layout]\ngoal_radius = -3.0\n",
    )
    .unwrap();
    let out = bin()
        .args(["run", "--scenario"])
        .arg(&path)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("layout.goal_radius"));
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn run_writes_one_trace_line_per_state() {
    let path = temp("trace.jsonl");
    let out = bin()
        .args([
            "run",
            "--scenario",
            "indoor",
            "--policy",
            "farthest",
            "--seed",
            "4",
            "--out",
        ])
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let lines: Vec<TraceLine> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len() as u64, summary["steps"].as_u64().unwrap() + 1);
    assert!(lines[0].outcome.is_none() && lines[0].actions.is_empty());
    assert!(
        lines[1..]
            .iter()
            .all(|l| l.outcome.is_some() && l.actions.len() == 2)
    );
    assert_eq!(lines.last().unwrap().world.step, lines.len() as u64 - 1);
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn a_reader_that_goes_away_ends_the_run_quietly_not_with_a_panic() {
    // `skyherd-sim run ... | head -1`: the reader closes its end before the summary comes.
    let mut child = bin()
        .args([
            "run",
            "--scenario",
            "paper-collect",
            "--policy",
            "lama",
            "--targets",
            "4",
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(out.status.code(), Some(0), "{stderr}");
}
