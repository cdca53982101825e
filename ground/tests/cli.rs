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

fn keygen(dir: &std::path::Path, extra: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_skyherd-ground"))
        .arg("keygen")
        .arg("--dir")
        .arg(dir)
        .args(extra)
        .output()
        .expect("skyherd-ground starts")
}

#[test]
fn keygen_makes_one_private_key_per_drone_and_never_overwrites() {
    use std::os::unix::fs::PermissionsExt;
    let dir = std::env::temp_dir().join(format!("skyherd-keygen-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = keygen(&dir, &["--drones", "1,2", "--fleet"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut keys = Vec::new();
    for name in ["drone-1.key", "drone-2.key", "fleet.key"] {
        let path = dir.join(name);
        let mode = std::fs::metadata(&path).expect(name).permissions().mode();
        assert_eq!(mode & 0o777, 0o600, "{name} mode {mode:o}");
        let key = skyherd_link::SigningKey::from_file(&path).expect(name);
        assert!(!keys.contains(&key), "{name} repeats a key");
        keys.push(key);
    }
    let dir_mode = std::fs::metadata(&dir).expect("dir").permissions().mode();
    assert_eq!(dir_mode & 0o077, 0, "key folder mode {dir_mode:o}");
    // Run again: the existing keys are kept, and the refusal names the file.
    let again = keygen(&dir, &["--drones", "1"]);
    assert!(!again.status.success());
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(err.contains("drone-1.key"), "{err}");
    assert_eq!(
        skyherd_link::SigningKey::from_file(&dir.join("drone-1.key")).expect("kept"),
        keys[0]
    );
    // A bad drone id is refused by name.
    let bad = keygen(&dir, &["--drones", "0"]);
    assert!(!bad.status.success());
    // The mission refuses to fly without keys, and refuses a key open to others.
    let (ok, err) = mission(&["--drone", "1=udpout:127.0.0.1:9"]);
    assert!(!ok);
    assert!(err.contains("--key-dir"), "{err}");
    std::fs::set_permissions(
        dir.join("drone-1.key"),
        std::fs::Permissions::from_mode(0o644),
    )
    .expect("chmod");
    let dir_arg = dir.display().to_string();
    let (ok, err) = mission(&["--drone", "1=udpout:127.0.0.1:9", "--key-dir", &dir_arg]);
    assert!(!ok);
    assert!(err.contains("644") && err.contains("drone 1"), "{err}");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
