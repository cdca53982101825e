//! Conformance with real clients: MAVSDK's own client (the `mavsdk-grpc` wheel's Python API and
//! its bundled `mavsdk_server`, installed by `scripts/setup.sh`) flies the mock PX4 that
//! `skyherd-sitl autopilot` runs for outside clients, and pymavlink drives the calls a ground
//! station makes against both mock flavours and a real ArduCopter SITL. Every call must succeed
//! (`--strict`); each one's line is printed. `docs/autopilots.md` tabulates them.

use std::net::UdpSocket;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use skyherd_e2e::{binary, repo};
use skyherd_sitl::arducopter::{ArduCopter, ArduCopterBundle, ArduCopterOptions};
use skyherd_sitl::autopilot::Home;

fn free_udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("a free port")
        .port()
}

fn venv_python() -> std::path::PathBuf {
    let python = repo().join(".venv/bin/python");
    assert!(
        python.exists(),
        "no {}: run scripts/setup.sh",
        python.display()
    );
    python
}

/// Runs `tests/peers/pymavlink_conformance.py` against whatever sends to `port`; its output.
fn pymavlink_conformance(port: u16, flavour: &str) -> String {
    let output = Command::new(venv_python())
        .arg(repo().join("tests/peers/pymavlink_conformance.py"))
        .arg(format!("udpin:127.0.0.1:{port}"))
        .args(["--flavour", flavour, "--strict"])
        .stderr(Stdio::inherit())
        .output()
        .expect("the pymavlink client runs");
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    eprintln!("{text}");
    let calls = text.lines().filter(|l| l.contains("CALL ")).count();
    let failed: Vec<&str> = text.lines().filter(|l| l.contains(" FAIL ")).collect();
    assert!(calls >= 19, "{flavour}: only {calls} calls ran:\n{text}");
    assert!(failed.is_empty(), "{flavour}: failed calls: {failed:#?}");
    assert!(output.status.success(), "{flavour}: {}", output.status);
    text
}

#[test]
fn pymavlink_drives_both_mock_flavours_through_every_call() {
    for flavour in ["px4", "ardupilot"] {
        let port = free_udp_port();
        let mut autopilot = Command::new(binary("skyherd-sitl"))
            .args(["autopilot", "--autopilot", flavour, "--duration-s", "120"])
            .args(["--port", &port.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("skyherd-sitl autopilot starts");
        let text = pymavlink_conformance(port, flavour);
        let _ = autopilot.kill();
        let _ = autopilot.wait();
        // PX4 refuses a disarm in the air with DENIED (2), ArduCopter with FAILED (4).
        let refusal = if flavour == "px4" {
            "result 2"
        } else {
            "result 4"
        };
        assert!(
            text.lines()
                .any(|l| l.contains("disarm in the air") && l.contains(refusal)),
            "{flavour}: {text}"
        );
    }
}

#[test]
fn pymavlink_drives_a_real_arducopter_through_the_same_calls() {
    let bundle = ArduCopterBundle::locate(&repo())
        .unwrap_or_else(|e| panic!("{e} (scripts/setup.sh finds or builds one)"));
    let port = free_udp_port();
    let options = ArduCopterOptions {
        system_id: 1,
        speedup: 5.0,
        serial0: ([127, 0, 0, 1], port).into(),
        home: Home::CMAC,
        origin_world: [0.0; 2],
        log: None,
    };
    let copter = ArduCopter::start(&bundle, &options, None).expect("ArduCopter starts");
    let text = pymavlink_conformance(port, "ardupilot");
    drop(copter);
    assert!(
        text.lines()
            .any(|l| l.contains("disarm in the air") && l.contains("result 4")),
        "{text}"
    );
}

#[test]
fn mavsdk_flies_the_mock_px4_end_to_end() {
    let python = venv_python();
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
    let port = free_udp_port();
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
