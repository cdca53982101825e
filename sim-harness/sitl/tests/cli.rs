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
    // Out of range, or not a number at all: refused with the flag's name, before any process
    // starts or any file is written.
    for (flag, value) in [
        ("--loss", "nan"),
        ("--loss", "2"),
        ("--latency-ms", "-1"),
        ("--latency-ms", "inf"),
        ("--speed", "nan"),
        ("--speed", "-1"),
        ("--lose-drone", "99@5"),
        ("--lose-drone", "0@nan"),
        ("--cut-uplink", "5"),
        ("--cut-uplink", "3,-5"),
        ("--estimate-noise-m", "nan"),
        ("--estimate-noise-m", "-1"),
        ("--estimate-noise-m", "0.5,"),
        ("--estimate-noise-m", "0.5,0.1,0.2"),
        ("--estimate-noise-m", "0.5,-0.1"),
        ("--land-after-s", "nan"),
        ("--land-after-s", "-1"),
        ("--land-after-s", "inf"),
        ("--kill-ground-at", "nan"),
        ("--kill-ground-at", "-2"),
        ("--kill-ground-at", "inf"),
        ("--kill-ground-at", "soon"),
        ("--kill-daemon", "5@10"),
        ("--kill-daemon", "0@nan"),
        ("--kill-daemon", "0"),
    ] {
        let arg = format!("{flag}={value}");
        let (ok, err) = sitl(&["--scenario", "indoor", "--model", model, "--out", out, &arg]);
        assert!(!ok, "{arg} accepted");
        assert!(err.contains(flag), "{arg}: {err}");
        assert!(!err.contains("panicked"), "{arg}: {err}");
        assert!(
            !std::path::Path::new(out).join("mission.key").exists(),
            "{arg}: nothing is written"
        );
    }
    // Wind with no motion model to feel it.
    let (ok, err) = sitl(&[
        "--scenario",
        "indoor",
        "--model",
        model,
        "--out",
        out,
        "--dynamics",
        "off",
        "--wind=arena",
    ]);
    assert!(!ok, "--wind=arena with --dynamics off accepted");
    assert!(err.contains("--wind"), "{err}");
    let _ = std::fs::remove_dir_all(out);
}
