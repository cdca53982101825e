#![allow(deprecated)]

use super::*;
use mavlink::Message;
use mavlink::dialects::common::{
    MISSION_REQUEST_LIST_DATA, MavMissionType, MavParamType, PARAM_REQUEST_LIST_DATA,
    PARAM_SET_DATA, PositionTargetTypemask, SET_MODE_DATA,
};
use skyherd_link::command::{arm_disarm, command_long, land, set_mode, velocity_setpoint_ned};

/// MPC_LAND_SPEED's default, as the f32 parameter holds it.
const PX4_LAND_SPEED: f64 = 0.7_f32 as f64;

const H: MavHeader = MavHeader {
    system_id: 255,
    component_id: 190,
    sequence: 0,
};

fn ack(replies: &[MavMessage]) -> MavResult {
    match replies.first() {
        Some(MavMessage::COMMAND_ACK(a)) => a.result,
        other => panic!("expected an ACK first, got {other:?}"),
    }
}

fn texts(messages: &[MavMessage]) -> Vec<String> {
    messages
        .iter()
        .filter_map(|m| match m {
            MavMessage::STATUSTEXT(t) => Some(t.text.to_str().unwrap_or("?").to_owned()),
            _ => None,
        })
        .collect()
}

fn takeoff(system: u8, altitude: f32) -> MavMessage {
    command_long(
        system,
        1,
        MavCmd::MAV_CMD_NAV_TAKEOFF,
        [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, altitude],
    )
}

/// Ticks at 10 Hz from `t` for `seconds`, streaming `setpoint` when given; returns the new time.
fn run(ap: &mut MockAutopilot, mut t: f64, seconds: f64, setpoint: Option<&MavMessage>) -> f64 {
    let end = t + seconds;
    while t < end - 1e-9 {
        t += 0.1;
        if let Some(sp) = setpoint {
            ap.handle(&H, sp, t);
        }
        ap.tick(t);
    }
    t
}

#[test]
fn px4_offboard_needs_a_stream_then_fails_safe_on_loss() {
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::px4(1), [0.0, 0.0, -2.0], 0.0);
    let offboard = set_mode(1, 1, FlightMode::PX4_OFFBOARD);
    let refused = ap.handle(&H, &offboard, 0.0);
    assert_eq!(ack(&refused), MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
    assert_eq!(texts(&refused), ["Offboard denied: no setpoint stream"]);
    // One setpoint is a stream for 0.5 s, then it is gone.
    let sp = velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]);
    ap.handle(&H, &sp, 0.0);
    assert_eq!(
        ack(&ap.handle(&H, &offboard, 0.6)),
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED
    );
    ap.handle(&H, &sp, 0.7);
    let mut t = 0.8;
    assert_eq!(
        ack(&ap.handle(&H, &offboard, t)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    let start = ap.position_ned()[0];
    for _ in 0..10 {
        ap.handle(&H, &sp, t);
        ap.tick(t);
        t += 0.1;
    }
    assert!(
        (ap.position_ned()[0] - start - 0.9).abs() < 0.15,
        "{:?}",
        ap.position_ned()
    );
    // Stop streaming: still OFFBOARD 0.95 s after the last setpoint, hold after COM_OF_LOSS_T.
    let last_setpoint = t - 0.1;
    ap.tick(last_setpoint + 0.95);
    assert_eq!(ap.mode(), FlightMode::PX4_OFFBOARD);
    let tick = ap.tick(last_setpoint + 1.05);
    assert_eq!(ap.mode(), FlightMode::PX4_HOLD);
    assert_eq!(ap.failsafe_events(), 1);
    assert_eq!(
        texts(&tick.telemetry),
        ["Failsafe: offboard setpoints lost, holding"]
    );
    assert_eq!(ap.tick(last_setpoint + 1.15).velocity_ned, [0.0; 3]);
}

#[test]
fn the_offboard_loss_timeout_is_the_parameter() {
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::px4(1), [0.0, 0.0, -2.0], 0.0);
    let set = MavMessage::PARAM_SET(PARAM_SET_DATA {
        param_value: 3.0,
        target_system: 1,
        target_component: 1,
        param_id: "COM_OF_LOSS_T".into(),
        param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
    });
    let replies = ap.handle(&H, &set, 0.0);
    assert!(
        matches!(&replies[..], [MavMessage::PARAM_VALUE(v)] if v.param_value == 3.0),
        "{replies:?}"
    );
    let sp = velocity_setpoint_ned(1, 1, 0, [0.0; 3]);
    let t = run(&mut ap, 0.0, 1.5, Some(&sp));
    ap.handle(&H, &set_mode(1, 1, FlightMode::PX4_OFFBOARD), t);
    ap.tick(t + 2.5);
    assert_eq!(ap.mode(), FlightMode::PX4_OFFBOARD, "2.5 s < 3 s");
    ap.tick(t + 3.2);
    assert_eq!(ap.mode(), FlightMode::PX4_HOLD);
}

#[test]
fn ardupilot_guided_and_velocity_timeout() {
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::ardupilot(2), [0.0, 0.0, -2.0], 0.0);
    let guided = set_mode(2, 1, FlightMode::ARDUPILOT_GUIDED);
    assert_eq!(
        ack(&ap.handle(&H, &guided, 0.0)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    ap.handle(&H, &velocity_setpoint_ned(2, 1, 0, [0.0, 2.0, 0.0]), 0.0);
    assert_eq!(ap.tick(2.9).velocity_ned, [0.0, 2.0, 0.0]);
    assert_eq!(ap.tick(3.1).velocity_ned, [0.0; 3]);
    assert_eq!(ap.mode(), FlightMode::ARDUPILOT_GUIDED);
}

#[test]
fn px4_takes_off_with_nav_takeoff_then_holds() {
    let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
    assert!(ap.landed());
    let early = ap.handle(&H, &takeoff(1, f32::NAN), 0.0);
    assert_eq!(ack(&early), MavResult::MAV_RESULT_DENIED);
    assert_eq!(texts(&early), ["Takeoff denied: disarmed"]);
    ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
    // PX4's param 7 is AMSL: home is 584 m, so 587 m is 3 m up.
    assert_eq!(
        ack(&ap.handle(&H, &takeoff(1, 587.0), 0.1)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(ap.mode(), FlightMode::PX4_TAKEOFF);
    let t = run(&mut ap, 0.1, 1.0, None);
    assert!(!ap.landed());
    assert!(ap.velocity_ned()[2] < -1.0, "{:?}", ap.velocity_ned());
    run(&mut ap, t, 6.0, None);
    assert!(
        (ap.position_ned()[2] + 3.0).abs() < 0.05,
        "{:?}",
        ap.position_ned()
    );
    assert_eq!(
        ap.mode(),
        FlightMode::PX4_HOLD,
        "AUTO.LOITER after the climb"
    );
    assert!(ap.armed());
}

#[test]
fn px4_offboard_lifts_off_on_an_upward_setpoint_only() {
    let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
    ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
    let sideways = velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]);
    let t = run(&mut ap, 0.0, 1.2, Some(&sideways));
    assert_eq!(
        ack(&ap.handle(&H, &set_mode(1, 1, FlightMode::PX4_OFFBOARD), t)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    let t = run(&mut ap, t, 2.0, Some(&sideways));
    assert!(ap.landed(), "a landed multicopter does not slide");
    assert_eq!(ap.position_ned(), [0.0; 3]);
    let up = velocity_setpoint_ned(1, 1, 0, [0.0, 0.0, -1.0]);
    run(&mut ap, t, 1.0, Some(&up));
    assert!(!ap.landed());
    assert!(
        (ap.position_ned()[2] + 1.0).abs() < 0.15,
        "{:?}",
        ap.position_ned()
    );
}

#[test]
fn px4_disarms_itself_when_armed_without_a_takeoff() {
    let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
    ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
    let hold = velocity_setpoint_ned(1, 1, 0, [0.0; 3]);
    let t = run(&mut ap, 0.0, 9.8, Some(&hold));
    assert!(ap.armed());
    let mut said = Vec::new();
    let mut t = t;
    while t < 10.5 {
        t += 0.1;
        said.extend(ap.tick(t).telemetry);
    }
    assert!(!ap.armed(), "COM_DISARM_PRFLT is 10 s");
    assert_eq!(texts(&said), ["Auto-disarmed: no takeoff for 10 s"]);
}

#[test]
fn ardupilot_needs_guided_and_nav_takeoff_and_ignores_velocity_on_the_ground() {
    let mut ap = MockAutopilot::new(AutopilotConfig::ardupilot(1), [0.0; 3], 0.0);
    ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
    let refused = ap.handle(&H, &takeoff(1, 2.0), 0.0);
    assert_eq!(
        ack(&refused),
        MavResult::MAV_RESULT_FAILED,
        "LOITER takes no takeoff"
    );
    ap.handle(&H, &set_mode(1, 1, FlightMode::ARDUPILOT_GUIDED), 0.0);
    let up = velocity_setpoint_ned(1, 1, 0, [0.0, 0.0, -1.0]);
    let t = run(&mut ap, 0.0, 2.0, Some(&up));
    assert!(ap.landed(), "GUIDED velocity does not lift a landed copter");
    assert_eq!(
        ack(&ap.handle(&H, &takeoff(1, 2.0), t)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    let t = run(&mut ap, t, 5.0, None);
    assert!(
        (ap.position_ned()[2] + 2.0).abs() < 0.05,
        "{:?}",
        ap.position_ned()
    );
    assert_eq!(
        ap.mode(),
        FlightMode::ARDUPILOT_GUIDED,
        "still GUIDED after the takeoff"
    );
    let east = velocity_setpoint_ned(1, 1, 0, [0.0, 1.0, 0.0]);
    run(&mut ap, t, 1.0, Some(&east));
    assert!(
        (ap.position_ned()[1] - 1.0).abs() < 0.15,
        "{:?}",
        ap.position_ned()
    );
    // Armed on the ground without a takeoff: DISARM_DELAY (10 s) later it disarms.
    let mut ap = MockAutopilot::new(AutopilotConfig::ardupilot(1), [0.0; 3], 0.0);
    ap.handle(&H, &set_mode(1, 1, FlightMode::ARDUPILOT_GUIDED), 0.0);
    ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
    run(&mut ap, 0.0, 10.1, Some(&up));
    assert!(!ap.armed());
}

#[test]
fn disarming_in_the_air_is_refused_unless_forced() {
    for (flavour, refusal) in [
        (Flavour::Px4, MavResult::MAV_RESULT_DENIED),
        (Flavour::ArduPilot, MavResult::MAV_RESULT_FAILED),
    ] {
        let config = AutopilotConfig::for_flavour(flavour, 1);
        let mut ap = MockAutopilot::new_flying(config, [0.0, 0.0, -2.0], 0.0);
        let replies = ap.handle(&H, &arm_disarm(1, 1, false), 0.0);
        assert_eq!(ack(&replies), refusal, "{flavour:?}");
        assert_eq!(texts(&replies), ["Disarm denied: not landed"]);
        assert!(ap.armed());
        let force = command_long(
            1,
            1,
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [0.0, FORCE_DISARM_MAGIC, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        assert_eq!(
            ack(&ap.handle(&H, &force, 0.0)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        run(&mut ap, 0.0, 1.0, None);
        assert!(ap.landed() && !ap.armed(), "it falls");
    }
}

/// A PX4 autopilot armed and flying OFFBOARD at `height` m (NED z = -height), at t = 1.3 s.
fn offboard_at(height: f64) -> (MockAutopilot, f64) {
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::px4(1), [0.0, 0.0, -height], 0.0);
    let hold = velocity_setpoint_ned(1, 1, 0, [0.0; 3]);
    let mut t = 0.0;
    while t < 1.25 {
        ap.handle(&H, &hold, t);
        ap.tick(t);
        t += 0.1;
    }
    assert_eq!(
        ack(&ap.handle(&H, &set_mode(1, 1, FlightMode::PX4_OFFBOARD), t)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    (ap, t)
}

fn heartbeat_mode(ap: &mut MockAutopilot, now: f64) -> Option<(u32, bool)> {
    ap.restart_telemetry(now);
    ap.telemetry(now).into_iter().find_map(|m| match m {
        MavMessage::HEARTBEAT(hb) => Some((
            hb.custom_mode,
            hb.base_mode
                .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED),
        )),
        _ => None,
    })
}

#[test]
fn land_when_armed_descends_at_the_land_speed_and_disarms_at_touchdown() {
    let (mut ap, mut t) = offboard_at(2.0);
    assert_eq!(
        ack(&ap.handle(&H, &land(1, 1), t)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(ap.mode(), FlightMode::PX4_LAND);
    assert_eq!(
        heartbeat_mode(&mut ap, t),
        Some(((4 << 16) | (6 << 24), true)),
        "AUTO.LAND, armed"
    );
    let start = t;
    while ap.armed() && t < start + 10.0 {
        t += 0.1;
        let v = ap.tick(t).velocity_ned;
        if ap.armed() {
            assert_eq!(v, [0.0, 0.0, PX4_LAND_SPEED]);
        }
    }
    let touchdown = ap.touchdown_at().expect("touched down");
    assert_eq!(ap.landing_since(), Some(start));
    // 2 m at MPC_LAND_SPEED 0.7 m/s: 2.86 s, noticed on the next 0.1 s tick.
    assert!(
        (touchdown - start - 2.0 / 0.7).abs() <= 0.15,
        "touchdown {:.2} s after the command",
        touchdown - start
    );
    assert!(!ap.armed() && ap.landed());
    assert_eq!(ap.position_ned()[2], 0.0, "stopped by the floor");
    assert_eq!(ap.tick(t + 1.0).velocity_ned, [0.0; 3]);
    assert_eq!(heartbeat_mode(&mut ap, t + 1.0).map(|m| m.1), Some(false));
    // ArduPilot reports LAND as mode 9 and descends at LAND_SPEED (50 cm/s).
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::ardupilot(2), [0.0, 0.0, -1.0], 0.0);
    assert_eq!(
        ack(&ap.handle(&H, &land(2, 1), 0.0)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(heartbeat_mode(&mut ap, 0.0).map(|m| m.0), Some(9));
    assert_eq!(ap.tick(0.1).velocity_ned, [0.0, 0.0, 0.5]);
}

#[test]
fn land_is_denied_when_disarmed() {
    let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
    let replies = ap.handle(&H, &land(1, 1), 0.0);
    assert_eq!(ack(&replies), MavResult::MAV_RESULT_DENIED);
    assert_eq!(texts(&replies), ["Land denied: disarmed"]);
    assert_eq!(ap.mode(), FlightMode::PX4_HOLD);
    assert_eq!(ap.rejections().commands_refused, 1);
    assert_eq!(ap.touchdown_at(), None);
}

#[test]
fn rtl_flies_home_and_lands() {
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::px4(1), [3.0, 4.0, -2.0], 0.0);
    let rtl = command_long(1, 1, MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH, [0.0; 7]);
    assert_eq!(
        ack(&ap.handle(&H, &rtl, 0.0)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(ap.mode(), FlightMode::PX4_RTL);
    run(&mut ap, 0.0, 15.0, None);
    let p = ap.position_ned();
    assert!(
        p[0].abs() < 0.15 && p[1].abs() < 0.15 && p[2] == 0.0,
        "{p:?}"
    );
    assert!(!ap.armed() && ap.touchdown_at().is_some());
}

#[test]
fn setpoints_are_ignored_while_landing() {
    let (mut ap, mut t) = offboard_at(3.0);
    ap.handle(&H, &land(1, 1), t);
    ap.tick(t);
    let before = ap.position_ned()[2];
    let up_and_away = velocity_setpoint_ned(1, 1, 0, [2.0, 1.0, -1.0]);
    for _ in 0..10 {
        ap.handle(&H, &up_and_away, t);
        t += 0.1;
        assert_eq!(ap.tick(t).velocity_ned, [0.0, 0.0, PX4_LAND_SPEED]);
    }
    let p = ap.position_ned();
    assert_eq!((p[0], p[1]), (0.0, 0.0), "straight down");
    assert!((p[2] - (before + PX4_LAND_SPEED)).abs() < 1e-9, "{p:?}");
    assert_eq!(
        ap.mode(),
        FlightMode::PX4_LAND,
        "no switch back, no failsafe"
    );
    assert_eq!(ap.failsafe_events(), 0);
    assert!(ap.rejections().outside_external_mode >= 10);
}

#[test]
fn bad_setpoints_are_counted_and_ignored() {
    let mut ap = MockAutopilot::new(AutopilotConfig::px4(1), [0.0; 3], 0.0);
    let good = velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]);
    let MavMessage::SET_POSITION_TARGET_LOCAL_NED(base) = good else {
        unreachable!()
    };
    let mut global = base.clone();
    global.coordinate_frame = MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT;
    let mut acceleration = base.clone();
    acceleration.type_mask = PositionTargetTypemask::from_bits_truncate(0x0C3F);
    let mut partial = base.clone();
    partial.type_mask = PositionTargetTypemask::from_bits_truncate(0x0DC6);
    let mut nan = base.clone();
    nan.vx = f32::NAN;
    let mut other = base.clone();
    other.target_system = 9;
    let mut other_component = base;
    other_component.target_component = 42;
    for s in [global, acceleration, partial, nan, other, other_component] {
        ap.handle(&H, &MavMessage::SET_POSITION_TARGET_LOCAL_NED(s), 0.0);
    }
    let r = ap.rejections();
    assert_eq!(
        (r.wrong_frame, r.wrong_type_mask, r.non_finite, r.not_for_us),
        (1, 2, 1, 2)
    );
    assert!(!ap.streaming(2.0));
}

#[test]
fn every_local_frame_and_velocity_mask_a_client_sends_is_flown() {
    // MAVSDK's velocity with yaw (0x09C7), ours (0x0DC7), with yaw rate (0x05C7), a position
    // (0x0DF8) and position with velocity feed-forward (0x0DC0); local and body frames.
    let cases = [
        (
            MavFrame::MAV_FRAME_LOCAL_NED,
            0x09C7,
            [1.0, 0.0, 0.0],
            [1.0, 0.0],
        ),
        (
            MavFrame::MAV_FRAME_LOCAL_NED,
            0x0DC7,
            [0.0, 1.0, 0.0],
            [0.0, 1.0],
        ),
        (
            MavFrame::MAV_FRAME_LOCAL_NED,
            0x05C7,
            [1.0, 0.0, 0.0],
            [1.0, 0.0],
        ),
        (
            MavFrame::MAV_FRAME_BODY_NED,
            0x0DC7,
            [1.0, 0.0, 0.0],
            [1.0, 0.0],
        ),
        (
            MavFrame::MAV_FRAME_BODY_OFFSET_NED,
            0x0DC7,
            [0.0, -1.0, 0.0],
            [0.0, -1.0],
        ),
    ];
    for (frame, mask, v, moved) in cases {
        let (mut ap, t) = offboard_at(2.0);
        let MavMessage::SET_POSITION_TARGET_LOCAL_NED(mut s) =
            velocity_setpoint_ned(1, 1, 0, [v[0], v[1], v[2]])
        else {
            unreachable!()
        };
        s.coordinate_frame = frame;
        s.type_mask = PositionTargetTypemask::from_bits_truncate(mask);
        let sp = MavMessage::SET_POSITION_TARGET_LOCAL_NED(s);
        run(&mut ap, t, 1.0, Some(&sp));
        let p = ap.position_ned();
        assert!(
            (p[0] - moved[0]).abs() < 0.15 && (p[1] - moved[1]).abs() < 0.15,
            "{frame:?} {mask:#06x}: {p:?}"
        );
        assert_eq!(ap.rejections().wrong_type_mask, 0);
    }
    // A position setpoint: flies there and stops.
    let (mut ap, t) = offboard_at(2.0);
    let MavMessage::SET_POSITION_TARGET_LOCAL_NED(mut s) = velocity_setpoint_ned(1, 1, 0, [0.0; 3])
    else {
        unreachable!()
    };
    s.type_mask = PositionTargetTypemask::from_bits_truncate(0x0DF8);
    (s.x, s.y, s.z) = (2.0, -1.0, -2.5);
    let sp = MavMessage::SET_POSITION_TARGET_LOCAL_NED(s);
    run(&mut ap, t, 10.0, Some(&sp));
    let p = ap.position_ned();
    assert!(
        (p[0] - 2.0).abs() < 0.05 && (p[1] + 1.0).abs() < 0.05 && (p[2] + 2.5).abs() < 0.05,
        "{p:?}"
    );
}

#[test]
fn commands_are_acknowledged_to_the_requester_and_respect_the_component() {
    let mut ap = MockAutopilot::new(AutopilotConfig::px4(3), [0.0; 3], 0.0);
    let header = MavHeader {
        system_id: 3,
        component_id: DAEMON_COMPONENT_ID,
        sequence: 0,
    };
    let replies = ap.handle(&header, &arm_disarm(3, 1, true), 0.0);
    let [MavMessage::COMMAND_ACK(a)] = &replies[..] else {
        panic!("{replies:?}")
    };
    assert_eq!(
        (a.result, a.target_system, a.target_component),
        (MavResult::MAV_RESULT_ACCEPTED, 3, DAEMON_COMPONENT_ID)
    );
    // For a camera (component 100) on this vehicle: not ours to answer or to do.
    assert!(ap.handle(&H, &arm_disarm(3, 100, false), 0.0).is_empty());
    assert!(ap.armed());
    // Unknown commands: UNSUPPORTED, with a reason.
    let odd = command_long(3, 1, MavCmd::MAV_CMD_DO_SET_SERVO, [1.0; 7]);
    let replies = ap.handle(&H, &odd, 0.0);
    assert_eq!(ack(&replies), MavResult::MAV_RESULT_UNSUPPORTED);
    assert_eq!(texts(&replies), ["MAV_CMD_DO_SET_SERVO unsupported"]);
    // COMMAND_INT is served like COMMAND_LONG.
    let int = MavMessage::COMMAND_INT(COMMAND_INT_DATA {
        command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        target_system: 3,
        target_component: 1,
        param1: 0.0,
        ..Default::default()
    });
    assert_eq!(
        ack(&ap.handle(&H, &int, 0.0)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert!(!ap.armed());
    // The SET_MODE message switches modes as DO_SET_MODE does.
    let loiter = MavMessage::SET_MODE(SET_MODE_DATA {
        custom_mode: FlightMode::PX4_HOLD.custom_mode(),
        target_system: 3,
        base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    });
    ap.handle(
        &H,
        &set_mode(3, 1, FlightMode::Px4 { main: 3, sub: 0 }),
        0.0,
    );
    assert_eq!(ap.mode(), FlightMode::Px4 { main: 3, sub: 0 });
    assert_eq!(
        ack(&ap.handle(&H, &loiter, 0.0)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(ap.mode(), FlightMode::PX4_HOLD);
}

#[test]
fn identity_parameters_missions_and_timesync() {
    let mut ap = MockAutopilot::new(AutopilotConfig::ardupilot(1), [0.0; 3], 0.0);
    let request = |id: f32| {
        command_long(
            1,
            1,
            MavCmd::MAV_CMD_REQUEST_MESSAGE,
            [id, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
    };
    let replies = ap.handle(&H, &request(148.0), 0.0);
    assert!(
        matches!(&replies[..], [MavMessage::COMMAND_ACK(_), MavMessage::AUTOPILOT_VERSION(v)]
            if v.flight_sw_version == 0x0406_00FF),
        "{replies:?}"
    );
    let replies = ap.handle(&H, &request(242.0), 0.0);
    assert!(matches!(&replies[1], MavMessage::HOME_POSITION(h) if h.altitude == 584_000));
    assert_eq!(
        ack(&ap.handle(&H, &request(9999.0), 0.0)),
        MavResult::MAV_RESULT_DENIED
    );
    let list = MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA {
        target_system: 1,
        target_component: 1,
    });
    let values = ap.handle(&H, &list, 0.0);
    assert_eq!(values.len(), ap.params().len());
    assert!(values.iter().any(|m| matches!(m, MavMessage::PARAM_VALUE(v)
        if v.param_id.to_str() == Ok("DISARM_DELAY") && v.param_value == 10.0)));
    let missions = MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
        target_system: 1,
        target_component: 1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
    });
    assert!(matches!(&ap.handle(&H, &missions, 0.0)[..],
        [MavMessage::MISSION_COUNT(c)] if c.count == 0 && c.target_system == 255));
    let sync = MavMessage::TIMESYNC(TIMESYNC_DATA {
        tc1: 0,
        ts1: 42,
        ..Default::default()
    });
    assert!(matches!(&ap.handle(&H, &sync, 2.5)[..],
        [MavMessage::TIMESYNC(t)] if t.ts1 == 42 && t.tc1 == 2_500_000_000));
}

#[test]
fn ardupilot_streams_positions_only_when_asked() {
    let mut ap = MockAutopilot::new(AutopilotConfig::ardupilot(1), [0.0; 3], 0.0);
    let positions = |ap: &mut MockAutopilot, from: f64| {
        let mut n = 0;
        let mut t = from;
        for _ in 0..10 {
            t += 0.1;
            n += ap
                .tick(t)
                .telemetry
                .iter()
                .filter(|m| matches!(m, MavMessage::LOCAL_POSITION_NED(_)))
                .count();
        }
        n
    };
    assert_eq!(positions(&mut ap, 0.0), 0);
    let interval = command_long(
        1,
        1,
        MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        [32.0, 100_000.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(
        ack(&ap.handle(&H, &interval, 1.0)),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(positions(&mut ap, 1.0), 10, "10 Hz");
    let off = command_long(
        1,
        1,
        MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        [32.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    ap.handle(&H, &off, 2.0);
    assert_eq!(positions(&mut ap, 2.0), 0);
}

#[test]
fn telemetry_rates_and_battery_drain() {
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::px4(1), [0.0, 0.0, -1.0], 0.0);
    let mut counts = std::collections::HashMap::new();
    for k in 0..=100 {
        for m in ap.tick(k as f64 * 0.1).telemetry {
            *counts.entry(m.message_name()).or_insert(0) += 1;
        }
    }
    // 10 s ticked at 10 Hz: a position every tick (>= 10 Hz), 1 Hz heartbeats, the rest at
    // their rates.
    assert!(counts["LOCAL_POSITION_NED"] >= 100, "{counts:?}");
    assert!((10..=11).contains(&counts["HEARTBEAT"]), "{counts:?}");
    assert!(
        (48..=51).contains(&counts["GLOBAL_POSITION_INT"]),
        "{counts:?}"
    );
    for name in ["SYS_STATUS", "EXTENDED_SYS_STATE", "BATTERY_STATUS"] {
        assert!((10..=11).contains(&counts[name]), "{name}: {counts:?}");
    }
    assert!(counts.contains_key("ATTITUDE") && counts.contains_key("HOME_POSITION"));
    assert!(ap.battery_pct() < 100.0 && ap.battery_pct() > 98.0);
}

#[test]
fn global_position_follows_the_local_one() {
    let mut ap = MockAutopilot::new_flying(AutopilotConfig::px4(1), [111.32, 0.0, -10.0], 0.0);
    ap.restart_telemetry(0.0);
    let global = ap
        .telemetry(0.0)
        .into_iter()
        .find_map(|m| match m {
            MavMessage::GLOBAL_POSITION_INT(g) => Some(g),
            _ => None,
        })
        .expect("streamed");
    // 111.32 m north is 0.001 degrees of latitude; 10 m up.
    assert!((global.lat - (-353_622_610)).abs() <= 2, "{}", global.lat);
    assert_eq!((global.relative_alt, global.alt), (10_000, 594_000));
}

#[test]
fn an_ardupilot_setpoint_in_the_air_ends_its_takeoff() {
    let mut ap = MockAutopilot::new(AutopilotConfig::ardupilot(1), [0.0; 3], 0.0);
    ap.handle(&H, &set_mode(1, 1, FlightMode::ARDUPILOT_GUIDED), 0.0);
    ap.handle(&H, &arm_disarm(1, 1, true), 0.0);
    ap.handle(&H, &takeoff(1, 5.0), 0.0);
    let t = run(&mut ap, 0.0, 1.0, None);
    let north = velocity_setpoint_ned(1, 1, 0, [1.0, 0.0, 0.0]);
    run(&mut ap, t, 1.0, Some(&north));
    let p = ap.position_ned();
    assert!(p[0] > 0.8, "flies the setpoint: {p:?}");
    assert!(p[2] > -3.0, "no longer climbing to 5 m: {p:?}");
}

#[test]
fn with_dynamics_the_reported_position_wanders_from_the_truth_by_the_estimate_error() {
    let motion = |std: f64| Motion {
        limits: DynamicsLimits::indoor(),
        wind: WindConfig::CALM,
        wind_seed: 9,
        estimate_std_m: std,
        estimate_vertical_std_m: std,
        estimate_time_s: 5.0,
    };
    let reported = |std: f64| {
        let config = AutopilotConfig {
            dynamics: Some(motion(std)),
            ..AutopilotConfig::px4(1)
        };
        let mut ap = MockAutopilot::new_flying(config, [2.0, 3.0, -1.0], 0.0);
        let mut errors = Vec::new();
        let mut t = 0.0;
        for _ in 0..3000 {
            t += 0.1;
            ap.fly(t);
            ap.restart_telemetry(t);
            let truth = ap.position_ned();
            for m in ap.telemetry(t) {
                if let MavMessage::LOCAL_POSITION_NED(p) = m {
                    errors.push([
                        f64::from(p.x) - truth[0],
                        f64::from(p.y) - truth[1],
                        f64::from(p.z) - truth[2],
                    ]);
                }
            }
        }
        errors
    };
    // Exact without an error, to the f32 the message carries.
    assert!(reported(0.0).iter().flatten().all(|e| e.abs() < 1e-5));
    // 0.3 m: each axis spreads about that much over 300 s (60 correlation times), and the error
    // wanders slowly: from one 0.1 s report to the next it moves by far less than its spread.
    let errors = reported(0.3);
    assert!(errors.len() > 2000);
    for axis in 0..3 {
        let n = errors.len() as f64;
        let mean = errors.iter().map(|e| e[axis]).sum::<f64>() / n;
        let std = (errors.iter().map(|e| (e[axis] - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!(std > 0.15 && std < 0.45, "axis {axis}: {std}");
        let lagged = errors
            .windows(2)
            .map(|w| (w[0][axis] - mean) * (w[1][axis] - mean))
            .sum::<f64>()
            / (n - 1.0);
        let correlation = lagged / (std * std);
        assert!(correlation > 0.9, "axis {axis}: correlation {correlation}");
    }
    // Seeded: the same vehicle reports the same errors.
    assert_eq!(reported(0.3), errors);
}

/// A lockstep episode starts its randomness at the release: however long a vehicle hovered
/// before it (the pre-flight's length depends on other processes), the gusts and estimate
/// errors it meets afterwards are the same, and before it the air is calm and the estimate
/// exact.
#[test]
fn the_wind_and_estimate_error_start_at_the_release_whatever_came_before() {
    let config = AutopilotConfig {
        dynamics: Some(Motion {
            limits: DynamicsLimits::indoor(),
            wind: WindConfig {
                mean: [0.3, 0.0, 0.0],
                gust_std: 0.2,
                gust_time: 2.0,
            },
            wind_seed: 4,
            estimate_std_m: 0.05,
            estimate_vertical_std_m: 0.05,
            estimate_time_s: 5.0,
        }),
        ..AutopilotConfig::px4(1)
    };
    let hover = [2.0, 3.0, -1.0];
    // Flies `held` seconds after the episode's start, then 5 s after the release; returns the
    // truth and the reported positions after the release.
    let flight = |held: f64| {
        let mut ap = MockAutopilot::new_flying(config.clone(), hover, 0.0);
        ap.start_episode(0.0);
        let mut t = 0.0;
        while t < held - 1e-9 {
            t += 0.1;
            ap.fly(t);
            ap.set_state(hover, [0.0; 3]);
            // Calm and exact before the release: the vehicle stays put and reports the truth.
            assert_eq!(ap.position_ned(), hover);
            assert_eq!(ap.estimated_position(), hover);
        }
        ap.release();
        let mut after = Vec::new();
        for _ in 0..50 {
            t += 0.1;
            let v = ap.fly(t);
            after.push((v, ap.estimated_position()));
        }
        after
    };
    let (short, long) = (flight(0.5), flight(3.7));
    assert_eq!(short, long);
    // And after the release the wind (east, NED y) does push the vehicle, and the estimate
    // does wander.
    assert!(short.iter().any(|(v, _)| v[1] > 0.02), "{short:?}");
    assert!(
        short.iter().any(|(_, p)| (p[2] - hover[2]).abs() > 0.01),
        "{short:?}"
    );
}

/// The arena's estimate error: GNSS-sized horizontally, barometer-sized vertically, and none at
/// the release, from where it wanders to its spread (no jump in the first reports).
#[test]
fn the_estimate_error_is_set_per_axis_and_grows_from_none_at_the_release() {
    let config = AutopilotConfig {
        dynamics: Some(Motion {
            limits: DynamicsLimits::px4(),
            wind: WindConfig::CALM,
            wind_seed: 21,
            estimate_std_m: 0.5,
            estimate_vertical_std_m: 0.1,
            estimate_time_s: 5.0,
        }),
        ..AutopilotConfig::px4(1)
    };
    let hover = [10.0, 20.0, -3.0];
    let mut ap = MockAutopilot::new_flying(config, hover, 0.0);
    ap.start_episode(0.0);
    ap.release();
    let mut errors = Vec::new();
    let mut t = 0.0;
    for _ in 0..6000 {
        t += 0.1;
        ap.fly(t);
        ap.set_state(hover, [0.0; 3]);
        let p = ap.estimated_position();
        errors.push([p[0] - hover[0], p[1] - hover[1], p[2] - hover[2]]);
    }
    // The first report, 0.1 s after the release, is off by a step of the process (a fifth of
    // its spread, 3.5 of those at most here), not by the spread itself.
    let first = errors[0];
    assert!(first[0].abs() < 0.35 && first[1].abs() < 0.35, "{first:?}");
    assert!(first[2].abs() < 0.07, "{first:?}");
    let spread = |axis: usize| {
        let tail = &errors[1000..];
        (tail.iter().map(|e| e[axis] * e[axis]).sum::<f64>() / tail.len() as f64).sqrt()
    };
    for axis in 0..2 {
        let s = spread(axis);
        assert!(s > 0.3 && s < 0.75, "horizontal axis {axis}: {s}");
    }
    let vertical = spread(2);
    assert!(vertical > 0.05 && vertical < 0.16, "vertical: {vertical}");
}
