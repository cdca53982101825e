//! The shipped models as they fly (quantized, run by `skyherd_onboard::actor::Actor`) against the
//! float actors they were exported from (`trainer/shipped/*.actor.safetensors`; mtddpg-v1 reads
//! encoder v3's 46 features, mtddpg-v3 encoder v4's 51, mtddpg-scratch encoder v5's 56):
//! * on a small held-out evaluation (test-time noise), the success rates are within 1 point;
//! * on observations recorded while the float actor herds, the RMS action error is at most 1 %
//!   of the speed limit (the project's aim for the quantized actor).

use std::path::Path;

use skyherd_model::Task;
use skyherd_onboard::actor::Actor;
use skyherd_trainer::checkpoint::load_actor;
use skyherd_trainer::eval::{EvalScenario, evaluate_flat};
use skyherd_trainer::export::{parity, record_observations};
use skyherd_trainer::policy::ActorPolicy;

/// The shipped models: (name, float actor, model file).
fn shipped() -> Vec<(
    &'static str,
    skyherd_trainer::network::MultiTaskMlp,
    Vec<u8>,
)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    ["mtddpg-v1", "mtddpg-v3", "mtddpg-scratch"]
        .into_iter()
        .map(|name| {
            let actor = load_actor(&root.join(format!("shipped/{name}.actor.safetensors")))
                .expect("the float reference of the shipped model is committed");
            let bytes = std::fs::read(root.join(format!("../models/{name}.skym")))
                .expect("the shipped model file is committed");
            (name, actor, bytes)
        })
        .collect()
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

/// The aim: RMS action error at most 1 % of the speed limit. Measured on mtddpg-v1
/// (format 2): 0.0075 on the export's held-out observations, 0.0094 on this test's
/// recording (N = 16, M = 4); mtddpg-v3: 0.0068 on the export's; mtddpg-scratch: 0.0038 on
/// the export's. Format 1 (int8 activations and first layer) measured 0.049 and 0.051.
const RMS_AIM: f64 = 0.01;

#[test]
fn quantized_action_error_is_within_one_percent_of_max_speed() {
    for (name, actor, bytes) in shipped() {
        let obs = record_observations(&actor, &scenarios(), 2, 4_000_000_000, 400, 2)
            .expect("recording rollouts");
        assert!(obs.len() > 1000, "{name}: {} observations", obs.len());
        let p = parity(&actor, &bytes, &obs).expect("parity");
        eprintln!("{name}: {p:?}");
        assert!(p.rms_component <= RMS_AIM, "{name}: {p:?}");
    }
}

#[test]
fn quantized_success_rate_matches_the_float_actor() {
    for (name, actor, bytes) in shipped() {
        let onboard = Actor::from_bytes(&bytes).expect("model loads");
        let seeds = 4_100_000_000;
        let float =
            evaluate_flat(&scenarios(), 10, seeds, || ActorPolicy::new(&actor)).expect("eval");
        let quantized =
            evaluate_flat(&scenarios(), 10, seeds, || ActorPolicy::new(onboard)).expect("eval");
        for (f, q) in float.iter().zip(&quantized) {
            let gap = 100.0 * (f.success_rate - q.success_rate).abs();
            assert!(
                gap <= 1.0,
                "{name} {}: float {:.0}% vs quantized {:.0}%",
                f.scenario.label(),
                100.0 * f.success_rate,
                100.0 * q.success_rate
            );
        }
    }
}
