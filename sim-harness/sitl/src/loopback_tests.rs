//! Ground station <-> mock autopilot over real UDP sockets on 127.0.0.1 ephemeral ports,
//! lockstep on a simulated clock, every wait bounded.

use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;

use mavlink::dialects::common::{MavCmd, MavResult};
use skyherd_ground::fleet::{GroundLink, LinkConfig};
use skyherd_link::command::{arm_disarm, set_mode, velocity_setpoint_ned};
use skyherd_link::{CommandOutcome, FlightMode};
use skyherd_link::{Signing, SigningKey};

use super::{AutopilotConfig, AutopilotNode, FaultConfig, MockAutopilot, NodeOptions};

const DT: f64 = 0.05;
/// Upper bound of simulated seconds any test waits for something.
const LIMIT: f64 = 20.0;

struct Rig {
    ground: GroundLink,
    node: AutopilotNode,
    now: f64,
}

fn ground_socket() -> UdpSocket {
    UdpSocket::bind("127.0.0.1:0").unwrap()
}

impl Rig {
    fn new(
        config: AutopilotConfig,
        signing: Option<Signing>,
        ground_signing: Option<Signing>,
    ) -> Self {
        let socket = ground_socket();
        let ground_addr = socket.local_addr().unwrap();
        let node = AutopilotNode::bind(
            "127.0.0.1:0".parse().unwrap(),
            MockAutopilot::new(config, [0.0; 3], 0.0),
            NodeOptions {
                signing,
                peers: vec![ground_addr],
                ..NodeOptions::default()
            },
        )
        .unwrap();
        let node_addr = node.local_addr().unwrap();
        let ground = GroundLink::from_udp_socket(
            socket,
            Some(node_addr),
            LinkConfig {
                signing: ground_signing,
                ..LinkConfig::default()
            },
        );
        Self {
            ground,
            node,
            now: 0.0,
        }
    }

    /// One lockstep step: autopilot, then ground (waiting a little for datagrams in flight).
    fn step(&mut self) -> [f64; 3] {
        let v = self.node.step(self.now).unwrap();
        self.ground.tick(self.now).unwrap();
        self.ground
            .poll(self.now, Duration::from_millis(2))
            .unwrap();
        self.now += DT;
        v
    }

    fn step_until(&mut self, mut done: impl FnMut(&mut Self) -> bool) -> bool {
        let end = self.now + LIMIT;
        while self.now < end {
            self.step();
            if done(self) {
                return true;
            }
        }
        false
    }

    /// Send a command and step until its outcome.
    fn command(&mut self, message: &mavlink::dialects::common::MavMessage) -> CommandOutcome {
        self.ground.send_command(1, message, self.now).unwrap();
        let mut outcome = None;
        self.step_until(|rig| {
            outcome = rig
                .ground
                .take_command_results()
                .into_iter()
                .next()
                .map(|r| r.outcome);
            outcome.is_some()
        });
        outcome.expect("command outcome within the time limit")
    }

    fn stream_setpoints(&mut self, seconds: f64, velocity_ned: [f32; 3]) {
        let end = self.now + seconds;
        while self.now < end {
            self.ground
                .send_to(1, &velocity_setpoint_ned(1, 1, 0, velocity_ned))
                .unwrap();
            self.step();
        }
    }
}

#[test]
fn heartbeat_position_and_battery_reach_the_ground() {
    let mut rig = Rig::new(AutopilotConfig::px4(1), None, None);
    assert!(rig.step_until(|r| {
        r.ground
            .fleet()
            .get(1)
            .is_some_and(|v| v.position_ned.is_some() && v.battery_remaining_pct.is_some())
    }));
    let v = rig.ground.fleet().get(1).unwrap();
    assert_eq!(
        v.mav_type,
        mavlink::dialects::common::MavType::MAV_TYPE_QUADROTOR
    );
    assert_eq!(v.flight_mode(), FlightMode::PX4_HOLD);
    assert_eq!(v.position_sim(), Some([0.0; 3]), "on the floor at home");
    assert!(!v.armed);
    // The ground's heartbeats reach the autopilot too.
    for _ in 0..25 {
        rig.step();
    }
    assert!(rig.node.codec_stats().frames >= 1);
}

#[test]
fn arm_offboard_refused_then_accepted_setpoint_moves_and_loss_holds() {
    let mut rig = Rig::new(AutopilotConfig::px4(1), None, None);
    rig.step_until(|r| r.ground.fleet().get(1).is_some());
    assert_eq!(
        rig.command(&arm_disarm(1, 1, true)),
        CommandOutcome::Acked(MavResult::MAV_RESULT_ACCEPTED)
    );
    assert!(rig.step_until(|r| r.ground.fleet().get(1).is_some_and(|v| v.armed)));

    let offboard = set_mode(1, 1, FlightMode::PX4_OFFBOARD);
    assert_eq!(
        rig.command(&offboard),
        CommandOutcome::Acked(MavResult::MAV_RESULT_TEMPORARILY_REJECTED)
    );

    // Stream 1.3 s at 20 Hz, then ask again while still streaming.
    rig.stream_setpoints(1.3, [1.0, 0.0, 0.0]);
    rig.ground.send_command(1, &offboard, rig.now).unwrap();
    let mut outcome = None;
    let end = rig.now + 2.0;
    while outcome.is_none() && rig.now < end {
        rig.ground
            .send_to(1, &velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]))
            .unwrap();
        rig.step();
        outcome = rig
            .ground
            .take_command_results()
            .into_iter()
            .next()
            .map(|r| r.outcome);
    }
    assert_eq!(
        outcome,
        Some(CommandOutcome::Acked(MavResult::MAV_RESULT_ACCEPTED))
    );

    // North and up: a landed vehicle lifts off only on an upward setpoint.
    let north_before = rig.node.autopilot().position_ned()[0];
    rig.stream_setpoints(2.0, [1.0, 0.0, -1.0]);
    assert!(!rig.node.autopilot().landed());
    let moved = rig.node.autopilot().position_ned()[0] - north_before;
    assert!(
        (1.7..2.3).contains(&moved),
        "moved {moved} m north in 2 s at 1 m/s"
    );
    assert!(rig.step_until(|r| r.ground.fleet().get(1).is_some_and(|v| {
        v.position_ned
            .is_some_and(|p| (p[0] as f64 - r.node.autopilot().position_ned()[0]).abs() < 0.2)
    })));
    assert_eq!(
        rig.ground.fleet().get(1).unwrap().flight_mode(),
        FlightMode::PX4_OFFBOARD
    );

    // Stop streaming: after 1 s the autopilot holds and says so in its heartbeat.
    assert!(rig.step_until(|r| {
        r.ground
            .fleet()
            .get(1)
            .is_some_and(|v| v.flight_mode() == FlightMode::PX4_HOLD)
    }));
    assert_eq!(rig.node.autopilot().failsafe_events(), 1);
    let held = rig.node.autopilot().position_ned();
    for _ in 0..20 {
        assert_eq!(rig.step(), [0.0; 3]);
    }
    assert_eq!(rig.node.autopilot().position_ned(), held);
}

#[test]
fn ardupilot_flavour_goes_guided() {
    let mut rig = Rig::new(AutopilotConfig::ardupilot(1), None, None);
    rig.step_until(|r| r.ground.fleet().get(1).is_some());
    assert_eq!(
        rig.command(&set_mode(1, 1, FlightMode::ARDUPILOT_GUIDED)),
        CommandOutcome::Acked(MavResult::MAV_RESULT_ACCEPTED)
    );
    assert!(rig.step_until(|r| {
        r.ground
            .fleet()
            .get(1)
            .is_some_and(|v| v.flight_mode() == FlightMode::ARDUPILOT_GUIDED)
    }));
}

#[test]
fn signed_link_rejects_unsigned_and_wrong_key() {
    let key = |b: u8| Signing {
        key: SigningKey([b; 32]),
        link_id: 0,
        accept_unsigned: false,
    };
    // Same key on both ends: commands work.
    let mut rig = Rig::new(AutopilotConfig::px4(1), Some(key(7)), Some(key(7)));
    rig.step_until(|r| r.ground.fleet().get(1).is_some());
    assert_eq!(
        rig.command(&arm_disarm(1, 1, true)),
        CommandOutcome::Acked(MavResult::MAV_RESULT_ACCEPTED)
    );
    assert_eq!(
        rig.node.codec_stats().bad_signature + rig.node.codec_stats().unsigned_rejected,
        0
    );

    // Unsigned ground, then wrong-key ground: the autopilot drops everything, counted.
    for (ground_signing, what) in [(None, "unsigned"), (Some(key(8)), "wrong key")] {
        let mut rig = Rig::new(AutopilotConfig::px4(1), Some(key(7)), ground_signing);
        rig.ground
            .send_command(1, &arm_disarm(1, 1, true), 0.0)
            .unwrap();
        for _ in 0..40 {
            rig.step();
        }
        assert!(!rig.node.autopilot().armed(), "{what}: must not arm");
        let results = rig.ground.take_command_results();
        assert!(
            results
                .iter()
                .any(|r| r.command == MavCmd::MAV_CMD_COMPONENT_ARM_DISARM
                    && r.outcome == CommandOutcome::TimedOut),
            "{what}: {results:?}"
        );
        let s = rig.node.codec_stats();
        assert!(s.bad_signature + s.unsigned_rejected >= 2, "{what}: {s:?}");
        assert_eq!(s.frames, 0, "{what}");
        // And the ground, with no or the wrong key, does not accept the autopilot's frames
        // either when it signs (wrong key); unsigned ground accepts signed frames unverified.
        if what == "wrong key" {
            assert!(rig.ground.fleet().get(1).is_none());
            assert!(rig.ground.stats().bad_signature > 0);
        }
    }
}

#[test]
fn malformed_bytes_are_counted_and_dropped() {
    let mut rig = Rig::new(AutopilotConfig::px4(1), None, None);
    rig.step_until(|r| r.ground.fleet().get(1).is_some());
    let attacker = UdpSocket::bind("127.0.0.1:0").unwrap();
    let node_addr: SocketAddr = rig.node.local_addr().unwrap();
    let mut codec = skyherd_link::Codec::new(255, 190, None);
    let good = codec.encode(&arm_disarm(1, 1, true));
    let mut bad_crc = good.clone();
    let n = bad_crc.len();
    bad_crc[n - 1] ^= 0xFF;
    for datagram in [
        &b"hello, not mavlink"[..],
        &[0xFD][..],
        &good[..good.len() / 2],
        &bad_crc[..],
        &[
            0xFD, 0xFF, 0x00, 0x00, 0x00, 0x01, 0x01, 0xFF, 0xFF, 0xFF, 0x00, 0x00,
        ][..],
    ] {
        attacker.send_to(datagram, node_addr).unwrap();
    }
    for _ in 0..10 {
        rig.step();
    }
    let s = *rig.node.codec_stats();
    assert!(s.garbage_bytes >= 18, "{s:?}");
    assert!(s.truncated >= 2 && s.bad_crc >= 1, "{s:?}");
    assert!(
        !rig.node.autopilot().armed(),
        "a corrupt arm command must not arm"
    );
    // The link still works.
    assert_eq!(
        rig.command(&arm_disarm(1, 1, true)),
        CommandOutcome::Acked(MavResult::MAV_RESULT_ACCEPTED)
    );
}

#[test]
fn lossy_link_still_delivers_with_counted_losses() {
    let socket = ground_socket();
    let ground_addr = socket.local_addr().unwrap();
    let mut node = AutopilotNode::bind(
        "127.0.0.1:0".parse().unwrap(),
        MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0),
        NodeOptions {
            faults: FaultConfig {
                loss: 0.2,
                latency: 0.2,
                cuts: vec![(3.0, 5.0)],
            },
            seed: 5,
            peers: vec![ground_addr],
            ..NodeOptions::default()
        },
    )
    .unwrap();
    let mut ground = GroundLink::from_udp_socket(
        socket,
        Some(node.local_addr().unwrap()),
        LinkConfig::default(),
    );
    let mut now = 0.0;
    let mut heard_during_cut = false;
    while now < 8.0 {
        node.step(now).unwrap();
        ground.tick(now).unwrap();
        ground.poll(now, Duration::from_millis(2)).unwrap();
        if let Some(v) = ground.fleet().get(1)
            && (3.5..5.0).contains(&now)
            && v.link.age(now) < 0.25
        {
            heard_during_cut = true;
        }
        now += DT;
    }
    let v = ground.fleet().get(1).expect("heard despite the faults");
    assert!(!heard_during_cut, "the cut must silence the link");
    assert!(v.link.age(now) < 0.5, "the link came back after the cut");
    assert!(v.link.lost > 0, "losses show up as sequence gaps");
    let (out, _) = node.fault_stats();
    assert!(out.lost > 0 && out.cut > 0);
}
