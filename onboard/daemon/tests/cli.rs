//! The `skyherd-onboard` binary as a user meets it: the self-test passes, and bad input (a
//! missing or corrupt model file, an out-of-range system id) is refused with a message that
//! says what was wrong. (Being an integration test of this package, it also makes
//! `cargo test --workspace` build the binary that the end-to-end SITL tests fly.)

use std::process::Command;

fn daemon() -> Command {
    Command::new(env!("CARGO_BIN_EXE_skyherd-onboard"))
}

fn run_with(args: &[&str]) -> (bool, String) {
    let out = daemon()
        .args(["run", "--herder-index", "0"])
        .args([
            "--autopilot",
            "udpout:127.0.0.1:9",
            "--ground",
            "udpin:127.0.0.1:0",
        ])
        .args(args)
        .output()
        .expect("the daemon starts");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn the_self_test_passes() {
    let out = daemon()
        .arg("self-test")
        .output()
        .expect("the daemon starts");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("self-test ok"));
}

#[test]
fn a_missing_model_file_is_named() {
    let (ok, err) = run_with(&["--model", "/nonexistent/model.skym", "--system-id", "1"]);
    assert!(!ok);
    assert!(err.contains("/nonexistent/model.skym"), "{err}");
}

#[test]
fn a_corrupt_model_file_is_refused_not_flown() {
    let path = std::env::temp_dir().join(format!("skyherd-bad-{}.skym", std::process::id()));
    std::fs::write(&path, b"SKYHnot a model at all").expect("temp file");
    let (ok, err) = run_with(&["--model", path.to_str().unwrap(), "--system-id", "1"]);
    let _ = std::fs::remove_file(&path);
    assert!(!ok);
    assert!(err.contains("not usable"), "{err}");
}

#[cfg(unix)]
#[test]
fn an_endless_model_file_is_refused_not_read_to_the_end() {
    // /dev/zero never ends: the daemon reads at most the size cap, then says why it stopped.
    let (ok, err) = run_with(&["--model", "/dev/zero", "--system-id", "1"]);
    assert!(!ok);
    assert!(
        err.contains("/dev/zero") && err.contains("more than"),
        "{err}"
    );
    let out = daemon()
        .args(["self-test", "--model", "/dev/zero"])
        .output()
        .expect("the daemon starts");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("more than"), "{err}");
}

#[test]
fn an_out_of_range_system_id_is_refused() {
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/mtddpg-v3.skym");
    let (ok, err) = run_with(&["--model", model, "--system-id", "0"]);
    assert!(!ok);
    assert!(err.contains("1..=254"), "{err}");
}

#[test]
fn without_a_key_the_daemon_refuses_to_fly_unless_told_it_is_a_bench_test() {
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/mtddpg-v3.skym");
    let (ok, err) = run_with(&["--model", model, "--system-id", "1"]);
    assert!(!ok);
    assert!(err.contains("--key") && err.contains("--insecure"), "{err}");
    // --insecure gets past the key, so the next checks speak, each naming its flag.
    for (flag, value) in [
        ("--separation-m", "nan"),
        ("--separation-m", "-1"),
        ("--rate-hz", "0"),
        ("--rate-hz", "nan"),
        ("--rate-hz", "1e9"),
        ("--land-after-s", "nan"),
        ("--land-after-s", "-1"),
        ("--land-after-s", "inf"),
        ("--land-after-s", "1e300"),
        ("--takeoff-alt-m", "0"),
        ("--takeoff-alt-m", "nan"),
        ("--braking", "0.5"),
        ("--braking", "0,1"),
        ("--braking", "0.5,-1"),
        ("--braking", "x,1"),
        ("--local-origin", "1,nan"),
        ("--local-origin", "1,2,3"),
    ] {
        let arg = format!("{flag}={value}");
        let (ok, err) = run_with(&["--model", model, "--system-id", "1", "--insecure", &arg]);
        assert!(!ok, "{arg} accepted");
        assert!(err.contains(flag), "{arg}: {err}");
        assert!(!err.contains("panicked"), "{arg}: {err}");
    }
}
