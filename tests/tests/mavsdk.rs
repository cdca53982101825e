//! MAVSDK conformance: MAVSDK's own client (the `mavsdk-grpc` wheel's Python API and its bundled
//! `mavsdk_server`, installed by `scripts/setup.sh`) flies the mock PX4 that
//! `skyherd-sitl autopilot` runs for outside clients: connect, health and telemetry, identity,
//! takeoff altitude parameter, arm, takeoff, offboard velocity, hold, land, disarm. Every call
//! must succeed (`--strict`); each one's line is printed.

use std::net::UdpSocket;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use skyherd_e2e::{binary, repo};

#[test]
fn mavsdk_flies_the_mock_px4_end_to_end() {
    let python = repo().join(".venv/bin/python");
    let has_mavsdk = Command::new(&python)
        .args(["-c", "import mavsdk_grpc"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        has_mavsdk,
        "no {} with mavsdk_grpc: run scripts/setup.sh",
        python.display()
    );
    // MAVSDK listens (udpin) on a free port; the mock sends to it, as PX4's SITL does.
    let port = UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("a free port")
        .port();
    let mut autopilot = Command::new(binary("skyherd-sitl"))
        .args(["autopilot", "--autopilot", "px4", "--duration-s", "300"])
        .args(["--port", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("skyherd-sitl autopilot starts");
    let log =
        std::env::temp_dir().join(format!("skyherd-mavsdk-server-{}.log", std::process::id()));
    let mut client = Command::new(&python)
        .arg(repo().join("tests/peers/mavsdk_flight.py"))
        .arg(format!("udpin://127.0.0.1:{port}"))
        .args(["--own-server", "--strict", "--server-log"])
        .arg(&log)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("the MAVSDK client starts");
    let start = Instant::now();
    let status = loop {
        if let Some(status) = client.try_wait().expect("wait") {
            break Some(status);
        }
        if start.elapsed() > Duration::from_secs(240) {
            let _ = client.kill();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let _ = autopilot.kill();
    let _ = autopilot.wait();
    let mut output = String::new();
    if let Some(mut stdout) = client.stdout.take() {
        use std::io::Read;
        let _ = stdout.read_to_string(&mut output);
    }
    eprintln!("{output}");
    let status = status.expect("the MAVSDK flight finished within 240 s");
    let calls = output.lines().filter(|l| l.contains("CALL ")).count();
    let failed: Vec<&str> = output.lines().filter(|l| l.contains(" FAIL ")).collect();
    assert!(calls >= 30, "only {calls} calls ran:\n{output}");
    assert!(failed.is_empty(), "failed calls: {failed:#?}");
    assert!(status.success(), "{status}:\n{output}");
    assert!(output.contains("SUMMARY failed=none"), "{output}");
    for step in [
        "action.arm OK",
        "action.takeoff OK",
        "offboard.start OK",
        "offboard.moved_north OK",
        "action.land OK",
        "telemetry.armed(wait false) OK False",
    ] {
        assert!(output.contains(step), "no {step:?} in\n{output}");
    }
    let _ = std::fs::remove_file(log);
}
