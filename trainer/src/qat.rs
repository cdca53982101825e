//! Quantization-aware fine-tuning before export: the float actor is distilled into a copy of
//! itself that runs with the quantized actor's rounding in the loop (input features, weights
//! and hidden activations rounded to the model's grids, straight-through gradients), so that
//! after quantization the actor behaves like the float teacher rather than each weight being
//! close.
//!
//! The grids are the quantizer's (`skyherd_model::quantize_model` run on the teacher):
//! per-feature affine int16 inputs folded into the first layer, symmetric per-row weights
//! (int16 in the task input layers, int8 elsewhere), int16 ReLU activations from 0 with one
//! scale per tensor.

use rand::Rng;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use skyherd_model::Task;
use skyherd_onboard::obs::{FEATURES, version_for};

use skyherd_model::format::WeightWidth;
use skyherd_model::{ModelMeta, quantize_model};
use skyherd_onboard::obs::ENCODER_VERSION;

use crate::export::to_float_actor;
use crate::network::{MultiTaskMlp, Tape};
use crate::nn::{Adam, AdamConfig, Dense};

/// Settings of [`finetune`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QatConfig {
    /// Adam steps (one batch per task each).
    pub steps: usize,
    /// Observations per task per step.
    pub batch: usize,
    /// Adam step size.
    pub learning_rate: f32,
    /// Seed of the batch sampling.
    pub seed: u64,
}

impl Default for QatConfig {
    fn default() -> Self {
        QatConfig {
            steps: 4_000,
            batch: 256,
            learning_rate: 1e-4,
            seed: 1,
        }
    }
}

fn round_input(x: f32, (scale, zero): (f32, f32)) -> f32 {
    scale * (((x / scale).round() + zero).clamp(-32768.0, 32767.0) - zero)
}

/// `weights` rounded per row to `max |w| / L` steps (`L` the width's largest level);
/// `column_scales` (the first layer's input scales) are folded in before rounding, as the
/// quantizer does, and taken out again.
fn round_weights(layer: &mut Dense, column_scales: Option<&[f32]>, width: WeightWidth) {
    let inputs = layer.inputs;
    for row in layer.weights.chunks_mut(inputs) {
        let folded = |j: usize, w: f32| column_scales.map_or(w, |s| w * s[j]);
        let max = row
            .iter()
            .enumerate()
            .fold(0.0f32, |m, (j, &w)| m.max(folded(j, w).abs()));
        if max == 0.0 {
            continue;
        }
        let step = max / width.max_level() as f32;
        for (j, w) in row.iter_mut().enumerate() {
            let q = (folded(j, *w) / step).round() * step;
            *w = column_scales.map_or(q, |s| q / s[j]);
        }
    }
}

/// The student with its weights on the model's grids (`widths` in file order, as the plan's).
fn rounded(student: &MultiTaskMlp, input_scales: &[f32], widths: &[WeightWidth]) -> MultiTaskMlp {
    let mut q = student.clone();
    let mut widths = widths.iter().copied();
    for l in q.task_inputs.iter_mut() {
        round_weights(l, Some(input_scales), widths.next().unwrap_or_default());
    }
    for l in q.shared.iter_mut().chain(q.task_outputs.iter_mut()) {
        round_weights(l, None, widths.next().unwrap_or_default());
    }
    q
}

/// Distils `teacher` into a quantization-aware copy on `observations` (the export's calibration
/// set); returns the student, whose quantized export follows the teacher more closely.
pub fn finetune(
    teacher: &MultiTaskMlp,
    observations: &[(Task, [f32; FEATURES])],
    config: QatConfig,
) -> MultiTaskMlp {
    // The grids are the quantizer's own, chosen on the teacher: the student learns to live with
    // exactly the rounding the export will apply.
    // An actor made for an older encoder reads the prefix of each observation.
    let width = teacher.inputs().min(FEATURES);
    let meta = ModelMeta {
        encoder_version: version_for(width).unwrap_or(ENCODER_VERSION),
        max_speed: 1.0,
    };
    let Ok(plan) = quantize_model(
        &to_float_actor(teacher),
        meta,
        observations.iter().map(|(t, f)| (*t, &f[..width])),
    ) else {
        return teacher.clone();
    };
    let input_scales = plan.input_scales.clone();
    let widths: Vec<WeightWidth> = plan.layers.iter().map(|l| l.weight_width).collect();
    let grids: Vec<(f32, f32)> = plan
        .input_scales
        .iter()
        .zip(&plan.input_zero_points)
        .map(|(&s, &z)| (s, f32::from(z)))
        .collect();
    // Hidden tensors: the task input layers' common output, then each shared layer's.
    let hidden_steps: Vec<f32> = std::iter::once(&plan.layers[0])
        .chain(&plan.layers[Task::COUNT..Task::COUNT + teacher.shared.len()])
        .map(|l| l.output_scale)
        .collect();
    // Per task: rounded inputs and the teacher's actions on the true inputs.
    let mut by_task: Vec<(Vec<f32>, Vec<f32>)> = vec![(Vec::new(), Vec::new()); Task::COUNT];
    let mut tape = Tape::default();
    for (task, f) in observations {
        let t = task.index();
        by_task[t]
            .0
            .extend(f.iter().zip(&grids).map(|(&x, &g)| round_input(x, g)));
        teacher.forward(t, &f[..width], 1, &mut tape);
        by_task[t].1.extend_from_slice(tape.output());
    }
    let mut student = teacher.clone();
    let mut adam = Adam::new(
        AdamConfig {
            learning_rate: config.learning_rate,
            ..AdamConfig::default()
        },
        student.layers(),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let outputs = teacher.outputs();
    let (mut x, mut target) = (Vec::new(), Vec::new());
    for step in 0..config.steps {
        let q = rounded(&student, &input_scales, &widths);
        let mut grads = student.zeros_like();
        for (t, (inputs, actions)) in by_task.iter().enumerate() {
            let n = actions.len() / outputs;
            if n == 0 {
                continue;
            }
            x.clear();
            target.clear();
            for _ in 0..config.batch {
                let i = rng.random_range(0..n);
                x.extend_from_slice(&inputs[i * width..(i + 1) * width]);
                target.extend_from_slice(&actions[i * outputs..(i + 1) * outputs]);
            }
            q.forward_rounding(t, &x, config.batch, &mut tape, &hidden_steps);
            let scale = 2.0 / (config.batch * outputs * Task::COUNT) as f32;
            let d: Vec<f32> = tape
                .output()
                .iter()
                .zip(&target)
                .map(|(y, a)| scale * (y - a))
                .collect();
            // Straight-through: the rounded copy's gradients update the float student.
            q.backward(&tape, &d, Some(&mut grads), false);
        }
        // Linear decay to zero: the last steps settle on the grid instead of hopping across it.
        adam.config.learning_rate =
            config.learning_rate * (1.0 - step as f32 / config.steps as f32);
        adam.update(student.layers_mut(), grads.layers());
    }
    // On the grid: the export's rounding then keeps every weight where training left it.
    rounded(&student, &input_scales, &widths)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::{calibration_scenarios, export, parity, record_observations};
    use crate::network::MlpShape;

    #[test]
    fn finetuning_brings_the_quantized_export_closer_to_the_teacher() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut teacher = MultiTaskMlp::new(MlpShape::actor(FEATURES, 32, 1), &mut rng);
        // Steep int8 layers (shared and output), like a trained actor's, so that their rounding
        // matters: with the int16 first layer and activations of model format 2 the int8 weights
        // are where the error is.
        for l in teacher
            .shared
            .iter_mut()
            .chain(teacher.task_outputs.iter_mut())
        {
            *l = Dense::new_uniform_bound(l.inputs, l.outputs, 1.5, &mut rng);
        }
        let obs = record_observations(&teacher, &calibration_scenarios()[..2], 1, 11, 150, 1)
            .expect("rollouts");
        let plain = parity(&teacher, &export(&teacher, 5.0, &obs).unwrap(), &obs).unwrap();
        let config = QatConfig {
            steps: 300,
            ..QatConfig::default()
        };
        let student = finetune(&teacher, &obs, config);
        let tuned = parity(&teacher, &export(&student, 5.0, &obs).unwrap(), &obs).unwrap();
        eprintln!("fine-tuned {tuned:?} vs plain {plain:?}");
        assert!(
            tuned.rms_component < plain.rms_component,
            "fine-tuned {tuned:?} vs plain {plain:?}"
        );
    }
}
