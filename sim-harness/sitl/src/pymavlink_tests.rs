//! Interop with pymavlink as an independent peer (MAVLINK20=1): it sees a mock autopilot's
//! HEARTBEAT and LOCAL_POSITION_NED, arms it, switches it to OFFBOARD, and reads a `.tlog`
//! written by the ground station. The peer script is `ground/tests/peers/pymavlink_peer.py`;
//! the Python environment is `.venv` at the workspace root (scripts/setup.sh). A missing
//! venv fails the test unless SKYHERD_ALLOW_SKIP=1.

use std::io::{BufRead, BufReader};
use std::net::UdpSocket;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use skyherd_ground::fleet::{GroundLink, LinkConfig};
use skyherd_link::command::arm_disarm;
use skyherd_link::{CommandOutcome, FlightMode};

use super::{AutopilotConfig, AutopilotNode, MockAutopilot, NodeOptions};

fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .nth(2)
        .expect("sim-harness/sitl sits two levels down in the workspace")
        .to_path_buf()
}

/// A `.tlog` from a short lockstep session: ground <-> autopilot, with an arm command.
fn write_tlog(path: &std::path::Path) -> u64 {
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut node = AutopilotNode::bind(
        "127.0.0.1:0".parse().unwrap(),
        MockAutopilot::new(AutopilotConfig::px4(1), [1.0, 2.0, 0.0], 0.0),
        NodeOptions {
            peers: vec![socket.local_addr().unwrap()],
            ..NodeOptions::default()
        },
    )
    .unwrap();
    let mut ground = GroundLink::from_udp_socket(
        socket,
        Some(node.local_addr().unwrap()),
        LinkConfig {
            // The sim clock's zero: 2026-01-01T00:00:00Z.
            tlog_epoch_us: 1_767_225_600_000_000,
            ..LinkConfig::default()
        },
    );
    ground.log_to(Box::new(std::io::BufWriter::new(
        std::fs::File::create(path).unwrap(),
    )));
    let mut now = 0.0;
    let mut acked = false;
    while now < 3.0 {
        node.step(now).unwrap();
        ground.tick(now).unwrap();
        ground.poll(now, Duration::from_millis(2)).unwrap();
        if (1.0..1.05).contains(&now) {
            ground
                .send_command(1, &arm_disarm(1, 1, true), now)
                .unwrap();
        }
        acked |= ground.take_command_results().iter().any(|r| {
            r.outcome
                == CommandOutcome::Acked(mavlink::dialects::common::MavResult::MAV_RESULT_ACCEPTED)
        });
        now += 0.05;
    }
    ground.flush_log().unwrap();
    assert!(acked, "the tlog session must contain an acknowledged arm");
    assert_eq!(
        ground.fleet().get(1).map(|v| v.flight_mode()),
        Some(FlightMode::PX4_HOLD)
    );
    ground.stats().frames
}

#[test]
fn pymavlink_sees_arms_switches_mode_and_reads_our_tlog() {
    let python = workspace_root().join(".venv/bin/python");
    if !python.exists() {
        let message = format!(
            "pymavlink interop: no Python venv at {} (run scripts/setup.sh)",
            python.display()
        );
        if std::env::var("SKYHERD_ALLOW_SKIP").as_deref() == Ok("1") {
            eprintln!("\n!!!!!!!! SKIPPED: {message} (SKYHERD_ALLOW_SKIP=1) !!!!!!!!\n");
            return;
        }
        panic!("{message}; set SKYHERD_ALLOW_SKIP=1 to skip");
    }
    let dir = std::env::temp_dir().join(format!("skyherd-pymavlink-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tlog = dir.join("session.tlog");
    let received = write_tlog(&tlog);

    let node = AutopilotNode::bind(
        "127.0.0.1:0".parse().unwrap(),
        MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0),
        NodeOptions::default(),
    )
    .unwrap();
    let node_addr = node.local_addr().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let runner = node.spawn_realtime(50.0, stop.clone());

    let mut child = Command::new(&python)
        .arg(workspace_root().join("ground/tests/peers/pymavlink_peer.py"))
        .args(["--autopilot", &node_addr.to_string(), "--tlog"])
        .arg(&tlog)
        .env("MAVLINK20", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("start the pymavlink peer");
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > Duration::from_secs(60) {
            child.kill().ok();
            panic!("pymavlink peer did not finish within 60 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    stop.store(true, Ordering::Relaxed);
    let node = runner.join().unwrap().unwrap();
    std::fs::remove_dir_all(&dir).ok();

    eprintln!("pymavlink peer: {line}");
    assert!(status.success(), "pymavlink peer failed: {line}");
    let report: serde_json::Value = serde_json::from_str(&line).expect("peer prints JSON");
    assert_eq!(report["mavlink20"], true);
    assert_eq!(report["frame_is_v2"], true);
    assert_eq!(report["heartbeat"]["system"], 1);
    assert_eq!(report["arm_ack"], 0); // MAV_RESULT_ACCEPTED
    assert_eq!(report["offboard_early_ack"], 1); // TEMPORARILY_REJECTED before streaming
    assert_eq!(report["offboard_ack"], 0);
    assert_eq!(report["offboard_heartbeat"], true);
    assert!(node.autopilot().armed());
    // pymavlink read back our .tlog: telemetry and the ACK, timestamps from our epoch.
    let counts = &report["tlog_counts"];
    assert!(counts["HEARTBEAT"].as_u64().unwrap_or(0) >= 3, "{counts}");
    assert!(
        counts["LOCAL_POSITION_NED"].as_u64().unwrap_or(0) >= 30,
        "{counts}"
    );
    assert_eq!(counts["COMMAND_ACK"], 1, "{counts}");
    assert_eq!(counts["COMMAND_LONG"], 1, "{counts}");
    assert!(counts.get("BAD_DATA").is_none(), "{counts}");
    let logged: u64 = counts
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert!(
        logged > received,
        "received frames plus sent ones: {logged} vs {received}"
    );
    let first = report["tlog_first_timestamp"].as_f64().unwrap();
    assert!((first - 1_767_225_600.0).abs() < 5.0, "tlog time {first}");
}

/// Row 4 of the threat table (`docs/security.md`): an autopilot whose link is signed refuses
/// an unsigned, forced disarm from a foreign system (pymavlink as the attacker, the script
/// `tests/peers/attacker.py`), while the key holder's signed arm is acknowledged.
#[test]
fn a_signing_autopilot_refuses_a_foreign_unsigned_disarm() {
    let python = workspace_root().join(".venv/bin/python");
    assert!(
        python.exists(),
        "no Python venv at {} with pymavlink: run scripts/setup.sh",
        python.display()
    );
    let dir = std::env::temp_dir().join(format!("skyherd-disarm-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let key_path = dir.join("fleet.key");
    let _ = std::fs::remove_file(&key_path);
    let key = skyherd_link::SigningKey::generate().unwrap();
    key.write_new_file(&key_path).unwrap();
    let node = AutopilotNode::bind(
        "127.0.0.1:0".parse().unwrap(),
        MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0),
        NodeOptions {
            signing: Some(skyherd_link::Signing {
                key,
                link_id: 2,
                accept_unsigned: false,
            }),
            ..NodeOptions::default()
        },
    )
    .unwrap();
    let port = node.local_addr().unwrap().port();
    let stop = Arc::new(AtomicBool::new(false));
    let runner = node.spawn_realtime(50.0, stop.clone());
    let out = Command::new(&python)
        .arg(workspace_root().join("tests/peers/attacker.py"))
        .args(["disarm", "--autopilot", &port.to_string(), "--key"])
        .arg(&key_path)
        .env("MAVLINK20", "1")
        .output()
        .expect("the attacker starts");
    stop.store(true, Ordering::Relaxed);
    let node = runner.join().unwrap().unwrap();
    std::fs::remove_dir_all(&dir).ok();
    let line = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{line} {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_str(line.trim()).expect("JSON");
    eprintln!("attacker: {report}");
    assert_eq!(
        report["acks_to_signed_arm"],
        serde_json::json!([0]),
        "{report}"
    );
    assert_eq!(
        report["acks_to_unsigned_disarm"],
        serde_json::json!([]),
        "{report}"
    );
    assert!(node.autopilot().armed(), "the forged disarm disarmed it");
    assert_eq!(
        node.codec_stats().unsigned_rejected,
        3,
        "{:?}",
        node.codec_stats()
    );
}
