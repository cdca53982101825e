//! The `skyherd-sitl` binary refuses bad input before it starts any process, with a message
//! that says what was wrong. (Being an integration test of this package, it also makes
//! `cargo test --workspace` build the binary that the end-to-end tests run.)

use std::process::Command;

fn sitl(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_skyherd-sitl"))
        .args(args)
        .output()
        .expect("skyherd-sitl starts");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn an_unknown_scenario_is_named() {
    let (ok, err) = sitl(&["--scenario", "moon-landing"]);
    assert!(!ok);
    assert!(err.contains("moon-landing"), "{err}");
}

#[test]
fn a_missing_model_is_named() {
    let (ok, err) = sitl(&["--model", "/nonexistent/herd.skym"]);
    assert!(!ok);
    assert!(err.contains("/nonexistent/herd.skym"), "{err}");
}

#[test]
fn a_bad_fault_flag_is_refused() {
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/mtddpg-v3.skym");
    let out = std::env::temp_dir().join(format!("skyherd-sitl-cli-{}", std::process::id()));
    let out = out.to_str().unwrap();
    let (ok, err) = sitl(&["--model", model, "--out", out, "--time-limit=-3"]);
    assert!(!ok);
    assert!(err.contains("--time-limit"), "{err}");
    let (ok, err) = sitl(&["--model", model, "--out", out, "--lose-drone", "one@ten"]);
    assert!(!ok);
    assert!(err.contains("--lose-drone"), "{err}");
    let _ = std::fs::remove_dir_all(out);
}
