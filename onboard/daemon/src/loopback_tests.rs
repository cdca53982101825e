//! The daemon over real UDP sockets on 127.0.0.1 (ephemeral ports), against a minimal fake PX4
//! and fake ground stations written here with the mavlink crate: one with the right signing key,
//! one with a wrong key, one unsigned.

use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::Ordering;
use std::sync::mpsc;
use std::thread;
use std::time::{Duration, Instant};

use mavlink::dialects::common::{
    COMMAND_ACK_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA, MavAutopilot, MavCmd, MavFrame,
    MavMessage, MavModeFlag, MavResult, MavState, MavTunnelPayloadType, MavType, TUNNEL_DATA,
};
use mavlink::{Connectable, MavConnection, MavHeader, UdpConfig, UdpMode};
use skyherd_link::VELOCITY_ONLY_TYPE_MASK;
use skyherd_link::signing::{SigningKey, signing_config};

use crate::control::{CoreConfig, CoreCounters, DaemonCore, HoldReason, Status};
use crate::io::{COMPONENT_ID, ClockMode, Daemon, LinkOptions, ShellCounters};
use crate::selftest::builtin_model;
use skyherd_link::Flavour;
use skyherd_onboard::Task;
use skyherd_onboard::actor::Actor;
use skyherd_onboard::wire::{
    MAX_MESSAGE, MissionAction, MissionCommand, Uplink, WorldSnapshot, chunks, encode_uplink,
};

const DRONE: u8 = 3;
const KEY: [u8; 32] = [0x5A; 32];
const WRONG_KEY: [u8; 32] = [0xA5; 32];
const PX4_OFFBOARD: u32 = 6 << 16;

type Link = mavlink::Connection<MavMessage>;

/// The core's state when the daemon stopped.
#[derive(Debug)]
struct CoreSummary {
    status: Status,
    counters: CoreCounters,
}

/// A UDP link bound to 127.0.0.1:0, talking to `peer` (or answering whoever writes first).
fn udp_link(peer: Option<SocketAddr>, signing: Option<[u8; 32]>) -> (Link, SocketAddr) {
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    socket
        .set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();
    let local = socket.local_addr().unwrap();
    let config = match peer {
        Some(peer) => {
            socket.connect(peer).unwrap();
            UdpConfig::from_socket(socket, UdpMode::Udpout).unwrap()
        }
        None => UdpConfig::from_socket(socket, UdpMode::Udpin).unwrap(),
    };
    let mut link = config.connect::<MavMessage>().unwrap();
    if let Some(key) = signing {
        link.setup_signing(Some(signing_config(&SigningKey(key), 0)));
    }
    (link, local)
}

/// Sends one uplink message as TUNNEL chunks from `link`.
fn send_uplink(link: &Link, from_system: u32, message_id: u16, message: &Uplink) {
    let mut buffer = vec![0u8; MAX_MESSAGE];
    let bytes = encode_uplink(message, &mut buffer).unwrap();
    for chunk in chunks(message_id, bytes).unwrap() {
        let data = chunk.as_bytes();
        let mut payload = [0u8; 128];
        payload[..data.len()].copy_from_slice(data);
        let tunnel = MavMessage::TUNNEL(TUNNEL_DATA {
            payload_type: MavTunnelPayloadType::MAV_TUNNEL_PAYLOAD_TYPE_UNKNOWN,
            target_system: DRONE,
            target_component: COMPONENT_ID,
            payload_length: data.len() as u8,
            payload,
        });
        let header = MavHeader {
            system_id: from_system,
            component_id: 190,
            sequence: 0,
        };
        link.send(&header, &tunnel).unwrap();
    }
}

fn command(sequence: u32, action: MissionAction) -> Uplink {
    Uplink::Command(MissionCommand {
        sequence,
        task: Task::Driving,
        goal: [50.0, 80.0],
        goal_radius: 8.0,
        action,
    })
}

fn snapshot(sequence: u32) -> Uplink {
    let mut w = WorldSnapshot::empty(Task::Driving, [100.0, 100.0, 10.0]);
    w.sequence = sequence;
    w.goal = [50.0, 80.0];
    w.goal_radius = 8.0;
    w.herders
        .extend_from_slice(&[[40.0, 20.0, 2.0], [60.0, 20.0, 2.0]])
        .unwrap();
    w.targets
        .extend_from_slice(&[[48.0, 40.0], [52.0, 41.0], [50.0, 44.0]])
        .unwrap();
    Uplink::Snapshot(w)
}

/// What the fake autopilot saw from the daemon.
#[derive(Default, Debug)]
struct Seen {
    heartbeats: usize,
    arm_commands: usize,
    mode_commands: Vec<(f32, f32)>,
    setpoints: usize,
    bad_setpoints: usize,
    moving_setpoints: usize,
}

#[test]
fn daemon_flies_a_fake_px4_and_rejects_forged_uplink() {
    let (autopilot, autopilot_addr) = udp_link(None, None);

    // The daemon in its own thread, as the binary runs it (wall clock, 20 Hz).
    let (ready_tx, ready_rx) = mpsc::channel();
    let daemon = thread::spawn(move || {
        let (_, bytes) = builtin_model(5.0).unwrap();
        let actor = Actor::from_bytes(&bytes).unwrap();
        let options = LinkOptions {
            autopilot: format!("udpout:{autopilot_addr}"),
            ground: "udpin:127.0.0.1:0".to_string(),
            replay_state: None,
            autopilot_key: None,
            signing_key: Some(KEY),
            clock: ClockMode::Wall { rate_hz: 20.0 },
        };
        let core = DaemonCore::new(CoreConfig::new(DRONE, 0, Flavour::Px4), actor);
        let mut daemon = Daemon::connect(&options, core).unwrap();
        ready_tx
            .send((daemon.ground_address().unwrap(), daemon.stop_flag()))
            .unwrap();
        daemon.run().unwrap();
        let core = daemon.core();
        (
            daemon.counters(),
            CoreSummary {
                status: core.status(),
                counters: core.counters(),
            },
        )
    });
    let (ground_addr, stop) = ready_rx.recv_timeout(Duration::from_secs(5)).unwrap();

    let (ground, _) = udp_link(Some(ground_addr), Some(KEY));
    let (forger, _) = udp_link(Some(ground_addr), Some(WRONG_KEY));
    let (plain, _) = udp_link(Some(ground_addr), None);

    let mut seen = Seen::default();
    let (mut armed, mut custom_mode) = (false, 0u32);
    let mut position = [20.0_f32, 40.0, -2.0]; // NED of sim (40, 20, 2)
    let started = Instant::now();
    let mut next_telemetry = Duration::ZERO;
    let mut next_uplink = Duration::ZERO;
    let mut sequence = 1u32;
    let mut message_id = 1u16;
    let (mut forged, mut unsigned) = (0u64, 0u64);
    let mut flying_since = None;
    while started.elapsed() < Duration::from_secs(8) {
        let now = started.elapsed();
        if now >= next_uplink {
            next_uplink = now + Duration::from_millis(100);
            if sequence == 1 {
                send_uplink(&ground, 255, message_id, &command(1, MissionAction::Start));
                message_id += 1;
            }
            send_uplink(&ground, 255, message_id, &snapshot(sequence));
            message_id += 1;
            sequence += 1;
            // Forged aborts (newer sequence numbers): would stop the mission if let through.
            let abort = command(100 + sequence, MissionAction::Abort);
            send_uplink(&forger, 255, 1000 + message_id, &abort);
            send_uplink(&plain, 255, 2000 + message_id, &abort);
            // One chunk each (a command fits in one).
            forged += 1;
            unsigned += 1;
        }
        if now >= next_telemetry {
            next_telemetry = now + Duration::from_millis(50);
            let header = MavHeader {
                system_id: u32::from(DRONE),
                component_id: 1,
                sequence: 0,
            };
            let mut base_mode = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
            if armed {
                base_mode |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
            }
            let heartbeat = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode,
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
                base_mode,
                system_status: MavState::MAV_STATE_ACTIVE,
                mavlink_version: 3,
            });
            let local = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: now.as_millis() as u32,
                x: position[0],
                y: position[1],
                z: position[2],
                ..Default::default()
            });
            // Before the daemon's first packet the udpin side has nobody to answer: Ok(0).
            autopilot.send(&header, &heartbeat).unwrap();
            autopilot.send(&header, &local).unwrap();
        }
        let Ok((header, message)) = autopilot.recv() else {
            continue;
        };
        assert_eq!(header.system_id, u32::from(DRONE));
        assert_eq!(header.component_id, COMPONENT_ID);
        match message {
            MavMessage::HEARTBEAT(hb) => {
                assert_eq!(hb.mavtype, MavType::MAV_TYPE_ONBOARD_CONTROLLER);
                seen.heartbeats += 1;
                if seen.heartbeats == 1 {
                    // A ground station's mode change acknowledged on the shared link: not
                    // the daemon's, whatever the command.
                    let theirs = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                        command: MavCmd::MAV_CMD_DO_SET_MODE,
                        result: MavResult::MAV_RESULT_ACCEPTED,
                        target_system: 255,
                        target_component: 190,
                        ..Default::default()
                    });
                    let header = MavHeader {
                        system_id: u32::from(DRONE),
                        component_id: 1,
                        sequence: 0,
                    };
                    autopilot.send(&header, &theirs).unwrap();
                }
            }
            MavMessage::COMMAND_LONG(c) => {
                assert_eq!((c.target_system, c.target_component), (DRONE, 1));
                let result = match c.command {
                    MavCmd::MAV_CMD_COMPONENT_ARM_DISARM if c.param1 == 1.0 => {
                        seen.arm_commands += 1;
                        armed = true;
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    MavCmd::MAV_CMD_DO_SET_MODE => {
                        seen.mode_commands.push((c.param1, c.param2));
                        // PX4 wants the stream first; the daemon waits for it.
                        assert!(
                            seen.setpoints >= 10,
                            "mode asked after {} setpoints",
                            seen.setpoints
                        );
                        custom_mode = (c.param2 as u32) << 16;
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    // The daemon asks for the position stream until it flows.
                    MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                        assert_eq!((c.param1, c.param2), (32.0, 100_000.0));
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    other => panic!("unexpected command {other:?}"),
                };
                let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                    command: c.command,
                    result,
                    target_system: DRONE,
                    target_component: COMPONENT_ID,
                    ..Default::default()
                });
                autopilot
                    .send(
                        &MavHeader {
                            system_id: u32::from(DRONE),
                            component_id: 1,
                            sequence: 0,
                        },
                        &ack,
                    )
                    .unwrap();
            }
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(sp) => {
                seen.setpoints += 1;
                let ok = sp.coordinate_frame == MavFrame::MAV_FRAME_LOCAL_NED
                    && sp.type_mask.bits() == VELOCITY_ONLY_TYPE_MASK
                    && (sp.target_system, sp.target_component) == (DRONE, 1);
                if !ok {
                    seen.bad_setpoints += 1;
                }
                let v = [sp.vx, sp.vy, sp.vz];
                if v != [0.0; 3] {
                    assert!(
                        armed && custom_mode == PX4_OFFBOARD,
                        "moving before OFFBOARD: {v:?}"
                    );
                    seen.moving_setpoints += 1;
                    // Integrate at the stream's nominal 50 ms.
                    for (p, v) in position.iter_mut().zip(v) {
                        *p += v * 0.05;
                    }
                }
            }
            _ => {}
        }
        if custom_mode == PX4_OFFBOARD && flying_since.is_none() {
            flying_since = Some(started.elapsed());
        }
        if let Some(t) = flying_since
            && started.elapsed() > t + Duration::from_millis(600)
        {
            break;
        }
    }
    // The daemon signs its heartbeats to the ground: the right key reads them. (A udpin link
    // answers whoever wrote last, so the real ground writes last.)
    send_uplink(&ground, 255, message_id, &snapshot(sequence));
    // Then the uplink goes quiet; the daemon holds and tells the ground with a STATUSTEXT.
    let mut ground_heard = false;
    let mut texts = Vec::new();
    let listen = Instant::now();
    while listen.elapsed() < Duration::from_millis(2500) {
        match ground.recv() {
            Ok((header, MavMessage::HEARTBEAT(hb))) => {
                ground_heard |= header.system_id == u32::from(DRONE)
                    && hb.mavtype == MavType::MAV_TYPE_ONBOARD_CONTROLLER;
            }
            Ok((_, MavMessage::STATUSTEXT(st))) => {
                texts.push(
                    st.text
                        .to_str()
                        .unwrap_or("")
                        .trim_end_matches('\0')
                        .to_string(),
                );
            }
            _ => {}
        }
        if ground_heard && texts.iter().any(|t| t.contains("uplink stale")) {
            break;
        }
    }
    stop.store(true, Ordering::Relaxed);
    let (counters, core): (ShellCounters, CoreSummary) = daemon.join().unwrap();

    assert!(seen.heartbeats >= 1, "{seen:?}");
    assert_eq!(counters.autopilot.others_acks, 1, "{counters:?}");
    assert!(seen.arm_commands >= 1, "{seen:?}");
    assert_eq!(seen.mode_commands.first(), Some(&(1.0, 6.0)), "{seen:?}");
    assert!(seen.setpoints >= 20, "{seen:?}");
    assert_eq!(seen.bad_setpoints, 0, "{seen:?}");
    assert!(seen.moving_setpoints >= 3, "{seen:?}");
    assert!(
        ground_heard,
        "the signed ground never read a daemon heartbeat"
    );
    assert!(
        texts
            .iter()
            .any(|t| t.starts_with("skyherd: holding: uplink stale")),
        "{texts:?}"
    );
    // Held for the quiet uplink, not aborted by the forged commands.
    assert!(
        matches!(core.status, Status::Holding(HoldReason::UplinkStale { .. })),
        "ended {:?}; {counters:?}",
        core.status
    );
    // Every forged and unsigned frame was dropped and counted; none reached the core.
    assert_eq!(counters.uplink.bad_signature, forged, "{counters:?}");
    assert_eq!(counters.uplink.unsigned, unsigned, "{counters:?}");
    assert_eq!(core.counters.mission_commands, 1, "{core:?}");
    assert!(core.counters.snapshots >= 5, "{core:?}");
}

#[test]
fn daemon_startup_errors_are_clear() {
    let (_, bytes) = builtin_model(5.0).unwrap();
    let actor = Actor::from_bytes(&bytes).unwrap();
    let options = LinkOptions {
        autopilot: "bogus:nowhere".to_string(),
        ground: "udpin:127.0.0.1:0".to_string(),
        replay_state: None,
        autopilot_key: None,
        signing_key: None,
        clock: ClockMode::Simulator { lockstep: true },
    };
    let core = DaemonCore::new(CoreConfig::new(DRONE, 0, Flavour::Px4), actor);
    let Err(err) = Daemon::connect(&options, core) else {
        panic!("a bogus address connected");
    };
    assert!(
        err.to_string().contains("autopilot link \"bogus:nowhere\""),
        "{err}"
    );
}

/// Lockstep: the daemon's time is the autopilot's `time_boot_ms`, one tick per position, and
/// it keeps up with a simulator stepping far faster than real time.
#[test]
fn sim_clock_ticks_once_per_position_at_simulator_time() {
    let (autopilot, autopilot_addr) = udp_link(None, None);
    let (ready_tx, ready_rx) = mpsc::channel();
    let daemon = thread::spawn(move || {
        let (_, bytes) = builtin_model(5.0).unwrap();
        let actor = Actor::from_bytes(&bytes).unwrap();
        let options = LinkOptions {
            autopilot: format!("udpout:{autopilot_addr}"),
            ground: "udpin:127.0.0.1:0".to_string(),
            replay_state: None,
            autopilot_key: None,
            signing_key: Some(KEY),
            clock: ClockMode::Simulator { lockstep: true },
        };
        let core = DaemonCore::new(CoreConfig::new(DRONE, 0, Flavour::Px4), actor);
        let mut daemon = Daemon::connect(&options, core).unwrap();
        ready_tx
            .send((daemon.ground_address().unwrap(), daemon.stop_flag()))
            .unwrap();
        daemon.run().unwrap();
        daemon.core().counters()
    });
    let (ground_addr, stop) = ready_rx.recv_timeout(Duration::from_secs(5)).unwrap();
    let (ground, _) = udp_link(Some(ground_addr), Some(KEY));
    // The daemon's first heartbeat tells the udpin fake autopilot where it is.
    let deadline = Instant::now() + Duration::from_secs(3);
    while !matches!(autopilot.recv(), Ok((_, MavMessage::HEARTBEAT(_)))) {
        assert!(Instant::now() < deadline, "no heartbeat from the daemon");
    }
    send_uplink(&ground, 255, 1, &command(1, MissionAction::Start));

    let header = MavHeader {
        system_id: u32::from(DRONE),
        component_id: 1,
        sequence: 0,
    };
    let (mut armed, mut custom_mode) = (false, 0u32);
    let mut flying_steps = 0;
    let steps = 40u32; // 4 s of simulated time at 10 Hz
    let wall = Instant::now();
    for step in 1..=steps {
        let t = step * 100;
        send_uplink(&ground, 255, 1 + step as u16, &snapshot(step));
        let mut base_mode = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        if armed {
            base_mode |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        let heartbeat = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            base_mode,
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        });
        autopilot.send(&header, &heartbeat).unwrap();
        // Let the uplink land before the position that triggers the tick.
        thread::sleep(Duration::from_millis(5));
        let local = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: t,
            x: 20.0,
            y: 40.0,
            z: -2.0,
            ..Default::default()
        });
        autopilot.send(&header, &local).unwrap();
        // Exactly one setpoint answers each position, stamped with its simulator time.
        let deadline = Instant::now() + Duration::from_secs(2);
        loop {
            assert!(Instant::now() < deadline, "no setpoint for t = {t} ms");
            let Ok((_, message)) = autopilot.recv() else {
                continue;
            };
            match message {
                MavMessage::COMMAND_LONG(c)
                    if c.command == MavCmd::MAV_CMD_COMPONENT_ARM_DISARM =>
                {
                    armed = true;
                }
                MavMessage::COMMAND_LONG(c) if c.command == MavCmd::MAV_CMD_DO_SET_MODE => {
                    // Streaming long enough is judged in simulator time: 1.2 s after start.
                    assert!(t >= 1200, "mode switch asked at {t} ms");
                    custom_mode = (c.param2 as u32) << 16;
                }
                MavMessage::SET_POSITION_TARGET_LOCAL_NED(sp) => {
                    assert_eq!(sp.time_boot_ms, t);
                    if [sp.vx, sp.vy, sp.vz] != [0.0; 3] {
                        flying_steps += 1;
                    }
                    break;
                }
                _ => {}
            }
        }
    }
    let wall = wall.elapsed();
    stop.store(true, Ordering::Relaxed);
    let counters = daemon.join().unwrap();
    assert_eq!(counters.ticks, u64::from(steps), "{counters:?}");
    assert!(flying_steps >= 20, "flew {flying_steps} of {steps} steps");
    // 4 s of simulated flight; the fake's 5 ms pauses dominate the wall time.
    assert!(wall < Duration::from_secs(3), "{wall:?}");
}
