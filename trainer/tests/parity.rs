//! The shipped model as it flies (int8, run by `skyherd_onboard::actor::Actor`) against the float
//! actor it was exported from (`trainer/shipped/mtddpg-v1.actor.safetensors`):
//! * on a small held-out evaluation (test-time noise), the success rates are within 1 point;
//! * on observations recorded while the float actor herds, the RMS action error stays at the
//!   level measured at export. The aim is 1 % of the speed limit (DESIGN §4); the shipped model
//!   does **not** meet it (about 3.8 %, see `models/MODEL.md`), so this test guards the measured
//!   level against regressions in export, quantizer and onboard inference instead.

use std::path::Path;

use skyherd_model::Task;
use skyherd_onboard::actor::Actor;
use skyherd_trainer::checkpoint::load_actor;
use skyherd_trainer::eval::{EvalScenario, evaluate_flat};
use skyherd_trainer::export::{parity, record_observations};
use skyherd_trainer::policy::ActorPolicy;

fn shipped() -> (skyherd_trainer::network::MultiTaskMlp, Vec<u8>) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let actor = load_actor(&root.join("shipped/mtddpg-v1.actor.safetensors"))
        .expect("the float reference of the shipped model is committed");
    let bytes = std::fs::read(root.join("../models/mtddpg-v1.skym"))
        .expect("the shipped model file is committed");
    (actor, bytes)
}

fn scenarios() -> Vec<EvalScenario> {
    Task::ALL
        .iter()
        .map(|&task| EvalScenario {
            task,
            targets: 16,
            herders: 4,
        })
        .collect()
}

/// RMS action error measured on the shipped model, in units of the speed limit, plus a margin:
/// 0.038 on the export's held-out observations, 0.051 on this test's recording (N = 16, M = 4;
/// 0.093 on the export's with plain rounding and no fine-tuning).
const MEASURED_RMS_BOUND: f64 = 0.06;

#[test]
fn int8_action_error_stays_at_the_measured_level() {
    let (actor, bytes) = shipped();
    let obs = record_observations(&actor, &scenarios(), 2, 4_000_000_000, 400, 2)
        .expect("recording rollouts");
    assert!(obs.len() > 1000, "{} observations", obs.len());
    let p = parity(&actor, &bytes, &obs).expect("parity");
    assert!(p.rms_component <= MEASURED_RMS_BOUND, "{p:?}");
}

#[test]
fn int8_success_rate_matches_the_float_actor() {
    let (actor, bytes) = shipped();
    let onboard = Actor::from_bytes(&bytes).expect("model loads");
    let seeds = 4_100_000_000;
    let float = evaluate_flat(&scenarios(), 10, seeds, || ActorPolicy::new(&actor)).expect("eval");
    let int8 = evaluate_flat(&scenarios(), 10, seeds, || ActorPolicy::new(onboard)).expect("eval");
    for (f, q) in float.iter().zip(&int8) {
        let gap = 100.0 * (f.success_rate - q.success_rate).abs();
        assert!(
            gap <= 1.0,
            "{}: float {:.0}% vs int8 {:.0}%",
            f.scenario.label(),
            100.0 * f.success_rate,
            100.0 * q.success_rate
        );
    }
}
