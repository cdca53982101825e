//! The `skyherd-ground` binary refuses bad flags before it opens a socket, naming the flag.

use std::process::Command;

fn mission(extra: &[&str]) -> (bool, String) {
    let goal: &[&str] = if extra.contains(&"--goal") {
        &[]
    } else {
        &["--goal", "8,8"]
    };
    let out = Command::new(env!("CARGO_BIN_EXE_skyherd-ground"))
        .args(["mission", "--fleet", "udpin:127.0.0.1:0"])
        .args(goal)
        .args(["--goal-radius", "0.9", "--area", "10,10,3"])
        .args(["--max-speed", "0.5", "--idle-timeout", "0.2"])
        .args(extra)
        .output()
        .expect("skyherd-ground starts");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_flags_are_refused_with_their_names() {
    let one = ["--drone", "1=127.0.0.1:9"];
    for (args, named) in [
        (vec!["--time-limit", "nan"], "--time-limit"),
        (vec!["--time-limit=-5"], "--time-limit"),
        (vec!["--scan-period", "0"], "--scan-period"),
        (vec!["--measurement-std", "inf"], "--measurement-std"),
        (vec!["--goal", "80,8"], "outside the area"),
        (vec!["--cut-uplink", "5"], "--cut-uplink"),
        (vec!["--cut-uplink", "3,-5"], "--cut-uplink"),
    ] {
        let mut all = one.to_vec();
        all.extend(args.iter().copied());
        let (ok, err) = mission(&all);
        assert!(!ok, "{args:?} accepted");
        assert!(err.contains(named), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    let (ok, err) = mission(&["--drone", "1=127.0.0.1:9", "--drone", "1=127.0.0.1:10"]);
    assert!(!ok);
    assert!(err.contains("twice"), "{err}");
}
