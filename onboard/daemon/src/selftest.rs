//! `skyherd-onboard self-test`: the core exercised end to end without sockets.
//!
//! On a built-in deterministic scene (2 herders, 16 targets, seeded) it
//! 1. builds a small model in memory with the model crate's quantizer from seeded, untrained
//!    weights (or reads the model file given), and decodes it into the quantized [`Actor`];
//! 2. encodes the scene and runs the quantized actor (and, for the built-in model, the f32 reference
//!    it was quantized from, reporting the difference);
//! 3. checks the safety rules on four situations (stale, NaN, over speed, outside the fence);
//! 4. flies a whole mission through [`DaemonCore`] against a scripted autopilot, every uplink
//!    message going through the wire format (postcard, chunks in reverse order, reassembly):
//!    start -> arm -> stream -> control mode -> fly -> uplink cut (hold) -> resume -> abort
//!    (hold), checking every setpoint is finite and within the speed limit.
//!
//! It is cheap enough to run under qemu in CI.

use std::fmt;

use skyherd_model::{ActorShape, FloatActor, ModelMeta, quantize};

use crate::control::{
    AutopilotCommand, CoreConfig, DaemonCore, HoldReason, Millis, OnboardPolicy, Status,
};
use skyherd_link::Flavour;
use skyherd_onboard::Task;
use skyherd_onboard::actor::Actor;
use skyherd_onboard::obs::{self, ENCODER_VERSION, FEATURES, ObsInput};
use skyherd_onboard::safety::{self, Limits, Reasons, Situation};
use skyherd_onboard::wire::{
    MAX_MESSAGE, MissionAction, MissionCommand, Uplink, WorldSnapshot, chunks, encode_uplink,
};

/// Seed of the built-in model's weights.
pub const MODEL_SEED: u64 = 0x5EED_0001;

/// A self-test failure: which step, and what was seen.
#[derive(Clone, Debug, PartialEq)]
pub struct SelfTestError {
    /// The step that failed.
    pub step: &'static str,
    /// What went wrong.
    pub detail: String,
}

impl fmt::Display for SelfTestError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "self-test failed at {}: {}", self.step, self.detail)
    }
}

impl std::error::Error for SelfTestError {}

fn fail(step: &'static str, detail: impl fmt::Display) -> SelfTestError {
    SelfTestError {
        step,
        detail: detail.to_string(),
    }
}

/// What the self-test measured; `Display` is the one-line summary the binary prints.
#[derive(Clone, Debug, PartialEq)]
pub struct SelfTestReport {
    /// Where the model came from (`built-in seeded` or the file name).
    pub model_source: String,
    /// Model size in bytes and its widths.
    pub model_bytes: usize,
    /// Hidden width.
    pub hidden: usize,
    /// Shared layers.
    pub shared_layers: usize,
    /// The quantized actor's world velocity for herder 0 on the scene, m/s, simulator frame.
    pub scene_velocity: [f32; 3],
    /// Largest difference between the quantized and the f32 actions on the scene (built-in model
    /// only), in units of the normalised action.
    pub int8_error: Option<f32>,
    /// Uplink chunks the mission's messages took.
    pub chunks: u64,
    /// Control ticks the mission took.
    pub ticks: u64,
    /// Statuses in the order they were first seen.
    pub flow: Vec<String>,
}

impl fmt::Display for SelfTestReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let v = self.scene_velocity;
        write!(
            f,
            "self-test ok: model {} ({} B, {}x{}x{}), quantized v = ({:.2}, {:.2}, {:.2}) m/s",
            self.model_source,
            self.model_bytes,
            FEATURES,
            self.hidden,
            self.shared_layers,
            v[0],
            v[1],
            v[2],
        )?;
        if let Some(e) = self.int8_error {
            write!(f, " (quantized vs f32 {e:.3})")?;
        }
        write!(
            f,
            ", safety 4/4, mission {} in {} ticks over {} uplink chunks",
            self.flow.join(" > "),
            self.ticks,
            self.chunks
        )
    }
}

/// The built-in scene: 2 herders, 16 targets in a seeded cluster, an arena of 100 x 100 x 10 m.
pub struct Scene {
    /// Herder positions, simulator frame.
    pub herders: [[f32; 3]; 2],
    /// Target positions.
    pub targets: [[f32; 2]; 16],
    /// Goal centre.
    pub goal: [f32; 2],
    /// Goal radius.
    pub goal_radius: f32,
    /// Arena.
    pub area: [f32; 3],
}

impl Scene {
    /// The deterministic scene.
    pub fn builtin() -> Scene {
        let mut state = 0x9E37_79B9_u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state as f32 / u32::MAX as f32 - 0.5
        };
        let mut targets = [[0.0; 2]; 16];
        for t in &mut targets {
            *t = [30.0 + 16.0 * next(), 30.0 + 16.0 * next()];
        }
        Scene {
            herders: [[20.0, 15.0, 2.0], [15.0, 25.0, 2.0]],
            targets,
            goal: [75.0, 70.0],
            goal_radius: 10.0,
            area: [100.0, 100.0, 10.0],
        }
    }

    /// The scene as one herder's encoder input.
    pub fn input(&self, own_index: usize, max_speed: f32) -> ObsInput<'_> {
        ObsInput {
            own_index,
            herders: &self.herders,
            targets: &self.targets,
            goal: self.goal,
            goal_radius: self.goal_radius,
            area: self.area,
            max_speed,
        }
    }
}

/// Builds the self-test's model: seeded, untrained weights quantized by the model crate,
/// calibrated on the built-in scene's features. Returns the float actor and the file bytes.
pub fn builtin_model(max_speed: f32) -> Result<(FloatActor, Vec<u8>), SelfTestError> {
    let shape = ActorShape {
        features: FEATURES,
        hidden: 32,
        shared_layers: 1,
    };
    let actor = FloatActor::random(shape, MODEL_SEED);
    let scene = Scene::builtin();
    let mut calibration = Vec::new();
    for own in 0..scene.herders.len() {
        let mut features = [0.0; FEATURES];
        obs::encode(&scene.input(own, max_speed), &mut features)
            .map_err(|e| fail("calibration encode", e))?;
        calibration.push(features);
    }
    let observations = calibration
        .iter()
        .flat_map(|f| Task::ALL.map(|task| (task, &f[..])));
    let bytes = quantize(
        &actor,
        ModelMeta {
            encoder_version: ENCODER_VERSION,
            max_speed,
        },
        observations,
    )
    .map_err(|e| fail("quantize", e))?;
    Ok((actor, bytes))
}

/// Runs the self-test. `model_file` is `(name, bytes)` of a model to check instead of the
/// built-in one.
pub fn run(model_file: Option<(&str, &[u8])>) -> Result<SelfTestReport, SelfTestError> {
    let (float_actor, built) = builtin_model(5.0)?;
    let (source, bytes, reference) = match model_file {
        Some((name, bytes)) => (name.to_string(), bytes, None),
        None => (
            "built-in seeded (untrained)".to_string(),
            &built[..],
            Some(float_actor),
        ),
    };
    let actor = Actor::from_bytes(bytes).map_err(|e| fail("model decode", e))?;
    let max_speed = actor.max_speed();

    let scene = Scene::builtin();
    let mut features = [0.0; FEATURES];
    // As the daemon encodes: only the features of the model's encoder version.
    let version = actor.model().encoder_version;
    let frame = obs::encode_version(&scene.input(0, max_speed), version, &mut features)
        .map_err(|e| fail("encode", e))?;
    let action = actor.infer(Task::Driving, &features);
    let int8_error = reference.map(|r| {
        let exact = r.forward(Task::Driving, &features);
        (0..3)
            .map(|k| (exact[k] - action[k]).abs())
            .fold(0.0, f32::max)
    });
    let scene_velocity = frame.action_to_world(action);
    let speed = norm(scene_velocity);
    if !(speed.is_finite() && speed <= max_speed * 1.0001) {
        return Err(fail(
            "infer",
            format!("velocity {scene_velocity:?} over {max_speed} m/s"),
        ));
    }
    if let Some(e) = int8_error
        && (e.is_nan() || e >= 0.1)
    {
        return Err(fail(
            "infer",
            format!("quantized action differs from f32 by {e}"),
        ));
    }

    check_safety(scene.area, max_speed)?;
    let (ticks, chunks, flow) = fly_mission(actor, &scene, max_speed)?;
    Ok(SelfTestReport {
        model_source: source,
        model_bytes: bytes.len(),
        hidden: actor.model().hidden,
        shared_layers: actor.model().shared_layers,
        scene_velocity,
        int8_error,
        chunks,
        ticks,
        flow,
    })
}

/// The four safety situations the daemon relies on, each with its reason.
fn check_safety(area: [f32; 3], max_speed: f32) -> Result<(), SelfTestError> {
    let limits = Limits::arena(area, max_speed);
    let inside = [50.0, 50.0, 2.0];
    let cases = [
        (
            "stale",
            inside,
            [1.0, 0.0, 0.0],
            5.0,
            true,
            Reasons::STALE,
            true,
        ),
        (
            "nan",
            inside,
            [f32::NAN, 0.0, 0.0],
            0.1,
            true,
            Reasons::NON_FINITE,
            true,
        ),
        (
            "speed",
            inside,
            [30.0, 0.0, 0.0],
            0.1,
            true,
            Reasons::OVER_SPEED,
            false,
        ),
        (
            "fence",
            [-3.0, 50.0, 2.0],
            [-2.0, 0.0, 0.0],
            0.1,
            true,
            Reasons::OUTSIDE_FENCE,
            false,
        ),
    ];
    for (name, position, velocity, age, finite, reason, hold) in cases {
        let d = safety::check(
            &limits,
            &Situation {
                position,
                velocity,
                snapshot_age_s: age,
                snapshot_finite: finite,
                current_velocity: None,
            },
        );
        let ok = d.hold == hold
            && d.reasons.contains(reason)
            && d.speed() <= max_speed * 1.0001
            && (name != "fence" || d.velocity[0] > 0.0);
        if !ok {
            return Err(fail("safety", format!("{name}: {d:?}")));
        }
    }
    Ok(())
}

fn norm(v: [f32; 3]) -> f32 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// A scripted PX4: obeys arm and mode commands at once, reports its position every tick.
/// Uplink messages reach the core as wire chunks, in reverse order.
fn fly_mission<P: OnboardPolicy>(
    policy: P,
    scene: &Scene,
    max_speed: f32,
) -> Result<(u64, u64, Vec<String>), SelfTestError> {
    const SYSTEM_ID: u8 = 1;
    const PX4_OFFBOARD: u32 = 6 << 16;
    const ARMED: u8 = 0x80;
    let mut config = CoreConfig::new(SYSTEM_ID, 0, Flavour::Px4);
    config.max_speed = max_speed;
    let mut core = DaemonCore::new(config, policy);
    let mut flow: Vec<String> = Vec::new();
    let note = |status: Status, flow: &mut Vec<String>| {
        let name = match status {
            Status::Idle => "idle".to_string(),
            Status::Preparing(p) => format!("{p:?}").to_lowercase(),
            Status::Flying(_) => "flying".to_string(),
            Status::Holding(HoldReason::UplinkStale { .. }) => "hold(stale)".to_string(),
            Status::Holding(r) => format!("hold({r:?})").to_lowercase(),
            Status::Landing(_) => "landing".to_string(),
        };
        if flow.last() != Some(&name) {
            flow.push(name);
        }
    };
    let mut buffer = vec![0u8; MAX_MESSAGE];
    let mut message_id = 0u16;
    let mut send = |core: &mut DaemonCore<P>, now: Millis, message: &Uplink| {
        let bytes = encode_uplink(message, &mut buffer).map_err(|e| fail("wire encode", e))?;
        message_id = message_id.wrapping_add(1);
        let mut sent: Vec<_> = chunks(message_id, bytes)
            .map_err(|e| fail("wire chunks", e))?
            .collect();
        sent.reverse();
        for chunk in &sent {
            core.on_tunnel_payload(now, chunk.as_bytes())
                .map_err(|e| fail("wire reassembly", e))?;
        }
        Ok::<(), SelfTestError>(())
    };
    let snapshot = |sequence: u32| {
        let mut w = WorldSnapshot::empty(Task::Driving, scene.area);
        w.sequence = sequence;
        w.goal = scene.goal;
        w.goal_radius = scene.goal_radius;
        w.max_speed = max_speed;
        // The ground's track of this drone is replaced by the autopilot's position.
        w.herders
            .extend_from_slice(&[[0.0; 3], scene.herders[1]])
            .ok();
        w.targets.extend_from_slice(&scene.targets).ok();
        Uplink::Snapshot(w)
    };
    let command = |sequence: u32, action: MissionAction| {
        Uplink::Command(MissionCommand {
            sequence,
            task: Task::Driving,
            goal: scene.goal,
            goal_radius: scene.goal_radius,
            action,
        })
    };
    let mut position = skyherd_onboard::frame::sim_to_ned(scene.herders[0]);
    let (mut armed, mut custom_mode) = (false, 0u32);
    note(core.tick(Millis(0)).status, &mut flow);
    send(&mut core, Millis(0), &command(1, MissionAction::Start))?;
    let mut flown = 0;
    // 100 ms ticks: 4 s of flight, uplink cut from 2.0 s to 3.5 s, abort at 4 s.
    for step in 1..=45u64 {
        let now = Millis(step * 100);
        if !(20..35).contains(&step) {
            send(&mut core, now, &snapshot(step as u32))?;
        }
        if step == 40 {
            send(&mut core, now, &command(2, MissionAction::Abort))?;
        }
        core.on_heartbeat(now, if armed { ARMED } else { 0 }, custom_mode);
        core.on_local_position(now, position);
        let decision = core.tick(now);
        note(decision.status, &mut flow);
        match decision.command {
            Some(AutopilotCommand::Arm) => armed = true,
            Some(AutopilotCommand::SetMode { custom_main_mode }) => {
                custom_mode = u32::from(custom_main_mode) << 16;
            }
            Some(AutopilotCommand::Land) => {
                return Err(fail("mission", format!("landed at {now:?}")));
            }
            Some(AutopilotCommand::Takeoff { .. }) => {
                return Err(fail(
                    "mission",
                    format!("NAV_TAKEOFF on PX4 at {now:?}: it climbs on setpoints"),
                ));
            }
            None => {}
        }
        let Some(setpoint) = decision.setpoint else {
            return Err(fail("mission", format!("no setpoint at {now:?}")));
        };
        let v = setpoint.velocity_ned;
        if !(norm(v).is_finite() && norm(v) <= max_speed * 1.0001) {
            return Err(fail("mission", format!("setpoint {v:?} at {now:?}")));
        }
        if let Status::Flying(_) = decision.status {
            flown += 1;
            for (p, v) in position.iter_mut().zip(v) {
                *p += v * 0.1;
            }
        } else if v != [0.0; 3] {
            return Err(fail(
                "mission",
                format!("moving setpoint {v:?} while {}", decision.status),
            ));
        }
    }
    let expected_end = Status::Holding(HoldReason::Aborted);
    if core.status() != expected_end || flown == 0 || custom_mode != PX4_OFFBOARD {
        return Err(fail(
            "mission",
            format!(
                "ended {} after {flown} flying ticks; flow {flow:?}",
                core.status()
            ),
        ));
    }
    if !flow.iter().any(|s| s == "hold(stale)") {
        return Err(fail(
            "mission",
            format!("uplink cut did not hold: {flow:?}"),
        ));
    }
    let counters = core.counters();
    Ok((counters.ticks, counters.chunks, flow))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn self_test_passes_and_reports_the_whole_flow() {
        let report = run(None).expect("self-test");
        assert_eq!(
            report.flow,
            [
                "idle",
                "arming",
                "streaming",
                "switchingmode",
                "flying",
                "hold(stale)",
                "flying",
                "hold(aborted)"
            ]
        );
        assert!(
            report
                .to_string()
                .starts_with("self-test ok: model built-in")
        );
    }

    #[test]
    fn a_corrupt_model_file_fails_at_decode() {
        let (_, mut bytes) = builtin_model(5.0).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0xFF;
        let err = run(Some(("corrupt.skym", &bytes))).unwrap_err();
        assert_eq!(err.step, "model decode");
    }
}
