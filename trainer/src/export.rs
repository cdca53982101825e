//! Export: the float actor -> `skyherd_model::FloatActor` -> quantized model file through the model
//! crate's quantizer, calibrated on observations recorded while the float actor flies; and the
//! parity check of the exported quantized actor (run by `skyherd_onboard::actor::Actor`, as on the
//! drone) against the float actor.

use skyherd_model::{Dense as ModelDense, FloatActor, ModelMeta, QuantizeError, Task, quantize};
use skyherd_onboard::actor::Actor;
use skyherd_onboard::obs::{FEATURES, version_for};
use skyherd_sim::{Env, EnvError, run_episode};
use thiserror::Error;

use crate::eval::EvalScenario;
use crate::network::MultiTaskMlp;
use crate::nn::Dense;
use crate::policy::{ActorPolicy, Infer};

/// Why export failed.
#[derive(Debug, Error)]
pub enum ExportError {
    /// The quantizer refused the actor.
    #[error("quantizer: {0:?}")]
    Quantize(QuantizeError),
    /// The exported bytes do not load as an onboard actor.
    #[error("exported model does not load: {0:?}")]
    Load(skyherd_model::FormatError),
    /// A calibration rollout failed.
    #[error("calibration rollout: {0}")]
    Env(#[from] EnvError),
    /// The actor's input width is no encoder version's feature count.
    #[error("the actor reads {0} inputs, which no encoder version this build serves gives")]
    Width(usize),
}

fn to_model_dense(d: &Dense) -> ModelDense {
    ModelDense {
        inputs: d.inputs,
        outputs: d.outputs,
        weights: d.weights.clone(),
        bias: d.bias.clone(),
    }
}

/// The trained actor in the model crate's f32 form (same layout, a copy).
pub(crate) fn to_float_actor(actor: &MultiTaskMlp) -> FloatActor {
    FloatActor {
        task_inputs: actor.task_inputs.iter().map(to_model_dense).collect(),
        shared: actor.shared.iter().map(to_model_dense).collect(),
        task_outputs: actor.task_outputs.iter().map(to_model_dense).collect(),
    }
}

/// The scenarios calibration and parity observations are recorded on: both tasks, small to
/// large flocks, one to many herders.
pub fn calibration_scenarios() -> Vec<EvalScenario> {
    let mut v = Vec::new();
    for task in Task::ALL {
        for (targets, herders) in [(4, 1), (16, 4), (64, 4), (256, 0)] {
            v.push(EvalScenario {
                task,
                targets,
                herders,
            });
        }
    }
    v
}

/// Runs `actor` for `episodes` episodes per scenario (seeds `seed_base..`, test-time noise on,
/// at most `step_limit` steps) and returns every `stride`-th observation it encoded.
pub fn record_observations<A: Infer>(
    actor: A,
    scenarios: &[EvalScenario],
    episodes: usize,
    seed_base: u64,
    step_limit: u64,
    stride: usize,
) -> Result<Vec<(Task, [f32; FEATURES])>, EnvError> {
    let mut policy = ActorPolicy::recording(actor);
    let mut seed = seed_base;
    for sc in scenarios {
        let mut s = sc.scenario();
        s.step_limit = step_limit;
        let mut env = Env::new(s)?;
        for _ in 0..episodes {
            run_episode(&mut env, &mut policy, seed, |_, _| {})?;
            seed += 1;
        }
    }
    Ok(policy
        .recorded
        .unwrap_or_default()
        .into_iter()
        .step_by(stride.max(1))
        .collect())
}

/// Quantizes `actor` into model-file bytes, calibrated on `calibration`.
pub fn export(
    actor: &MultiTaskMlp,
    max_speed: f32,
    calibration: &[(Task, [f32; FEATURES])],
) -> Result<Vec<u8>, ExportError> {
    // The model declares the encoder its input width belongs to; an actor made for an older
    // encoder is calibrated on the prefix of each observation that is its encoding.
    let width = actor.inputs();
    let meta = ModelMeta {
        encoder_version: version_for(width).ok_or(ExportError::Width(width))?,
        max_speed,
    };
    let bytes = quantize(
        &to_float_actor(actor),
        meta,
        calibration.iter().map(|(t, f)| (*t, &f[..width])),
    )
    .map_err(ExportError::Quantize)?;
    Actor::from_bytes(&bytes).map_err(ExportError::Load)?;
    Ok(bytes)
}

/// How far the quantized actor is from the float actor on a set of observations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Parity {
    /// Observations compared.
    pub samples: usize,
    /// RMS over all action components of the difference, in units of the speed limit.
    pub rms_component: f64,
    /// RMS over observations of the difference vector's norm, in units of the speed limit.
    pub rms_vector: f64,
    /// Largest component difference.
    pub max_component: f64,
}

/// Compares the float actor and the quantized model `bytes` on `observations`.
pub fn parity(
    actor: &MultiTaskMlp,
    bytes: &[u8],
    observations: &[(Task, [f32; FEATURES])],
) -> Result<Parity, ExportError> {
    let onboard = Actor::from_bytes(bytes).map_err(ExportError::Load)?;
    let (mut sum_c, mut sum_v, mut max_c) = (0.0_f64, 0.0_f64, 0.0_f64);
    for (task, f) in observations {
        let a = actor.infer(*task, f);
        let q = onboard.infer(*task, f);
        let mut v = 0.0;
        for k in 0..3 {
            let d = f64::from(a[k] - q[k]);
            sum_c += d * d;
            v += d * d;
            max_c = max_c.max(d.abs());
        }
        sum_v += v;
    }
    let n = observations.len().max(1) as f64;
    Ok(Parity {
        samples: observations.len(),
        rms_component: (sum_c / (3.0 * n)).sqrt(),
        rms_vector: (sum_v / n).sqrt(),
        max_component: max_c,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::MlpShape;
    use rand::SeedableRng;

    #[test]
    fn model_crate_float_actor_matches_the_training_actor() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let mut actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 32, 1), &mut rng);
        for l in actor.task_outputs.iter_mut() {
            *l = Dense::new_uniform(l.inputs, l.outputs, &mut rng);
        }
        let float = to_float_actor(&actor);
        let obs = record_observations(&actor, &calibration_scenarios()[..2], 1, 5, 20, 1)
            .expect("rollouts");
        assert!(!obs.is_empty());
        for (task, f) in &obs {
            let a = actor.infer(*task, f);
            let b = float.forward(*task, f);
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() < 1e-5, "{a:?} vs {b:?}");
            }
        }
        let bytes = export(&actor, 5.0, &obs).expect("export");
        let p = parity(&actor, &bytes, &obs).expect("parity");
        eprintln!("{p:?}");
        assert!(p.rms_component < 0.05, "{p:?}");
    }

    #[test]
    fn an_actor_for_encoder_v3_exports_as_a_v3_model() {
        // mtddpg-v1 and -v2 read v3's 46 features; re-exported, they must say so.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let actor = MultiTaskMlp::new(
            MlpShape::actor(skyherd_onboard::obs::V3_FEATURES, 16, 1),
            &mut rng,
        );
        let obs = record_observations(&actor, &calibration_scenarios()[..2], 1, 5, 20, 1)
            .expect("rollouts");
        let bytes = export(&actor, 5.0, &obs).expect("export");
        let model = skyherd_model::decode(&bytes).expect("decodes");
        assert_eq!(
            (model.encoder_version, model.features),
            (3, skyherd_onboard::obs::V3_FEATURES)
        );
        let p = parity(&actor, &bytes, &obs).expect("parity");
        assert!(p.rms_component < 0.05, "{p:?}");
        // No encoder gives 40 features.
        let odd = MultiTaskMlp::new(MlpShape::actor(40, 8, 1), &mut rng);
        assert!(matches!(
            export(&odd, 5.0, &obs),
            Err(ExportError::Width(40))
        ));
    }
}
