//! The quantized multi-task actor (the paper's Fig. 2) over a decoded model file: int8 weights
//! (int16 in the task input layers), int16 activations, integer arithmetic throughout.
//!
//! `features -> [task input layer, ReLU] -> [shared layer, ReLU] x S -> [task output layer]`
//! `-> dequantize -> tanh`, all in fixed-size stack buffers ([`MAX_FEATURES`], [`MAX_WIDTH`]
//! int16 values each), no heap and no panic for any model [`decode`] accepts. The arithmetic is
//! specified in [`skyherd_model::format`]; the int16 output of the task output layer is what the
//! golden vectors in `models/golden/` pin bit for bit.
//!
//! The action is a normalised velocity in `[-1, 1]^3` in the encoder's
//! [`LocalFrame`](crate::obs::LocalFrame); `LocalFrame::action_to_world` turns it into m/s.
//!
//! The float reference beside this path is `skyherd_model::FloatActor` (feature `std` of the
//! model crate); `tests/actor.rs` checks the two against each other.
//!
//! ```
//! # #[cfg(feature = "std")] {
//! use skyherd_model::{quantize, ActorShape, FloatActor, ModelMeta, Task};
//! use skyherd_onboard::actor::Actor;
//! use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES};
//!
//! // Seeded, untrained weights stand in for a trained model here.
//! let shape = ActorShape { features: FEATURES, hidden: 32, shared_layers: 2 };
//! let float = FloatActor::random(shape, 5);
//! let calibration = [[0.25_f32; FEATURES], [-0.5; FEATURES]];
//! let meta = ModelMeta { encoder_version: ENCODER_VERSION, max_speed: 5.0 };
//! let bytes = quantize(&float, meta, calibration.iter().map(|f| (Task::Driving, &f[..]))).unwrap();
//!
//! let actor = Actor::from_bytes(&bytes).unwrap();
//! let action = actor.infer(Task::Driving, &[0.1; FEATURES]);
//! assert!(action.iter().all(|a| (-1.0..=1.0).contains(a)));
//! # }
//! ```

use libm::{roundf, tanhf};
use skyherd_model::format::{ACTIONS, WeightWidth, requantize, requantize_wide};
pub use skyherd_model::format::{MAX_FEATURES, MAX_WIDTH};
use skyherd_model::{FormatError, LayerView, ModelView, Task, decode};

use crate::obs::{ENCODER_VERSION, FEATURES};

/// The quantized actor, checked against this build's observation encoder.
#[derive(Clone, Copy, Debug)]
pub struct Actor<'m> {
    model: ModelView<'m>,
}

impl<'m> Actor<'m> {
    /// An actor over a decoded model; fails with [`FormatError::EncoderMismatch`] unless the model
    /// was made for [`ENCODER_VERSION`] and [`FEATURES`].
    pub fn new(model: ModelView<'m>) -> Result<Actor<'m>, FormatError> {
        if let Err(e) = model.check_encoder(ENCODER_VERSION, FEATURES) {
            log::warn!("model {:#010x} rejected: {}", model.crc(), e);
            return Err(e);
        }
        log::info!(
            "actor: model {:#010x}, {} features, hidden {} x {} shared, {} weights ({} int16), max speed {} m/s",
            model.crc(),
            model.features,
            model.hidden,
            model.shared_layers,
            model.weight_count(),
            model.wide_weight_count(),
            model.max_speed
        );
        Ok(Actor { model })
    }

    /// [`decode`]s `bytes` and checks the encoder, see [`Actor::new`].
    pub fn from_bytes(bytes: &'m [u8]) -> Result<Actor<'m>, FormatError> {
        Actor::new(decode(bytes)?)
    }

    /// The model behind the actor.
    pub fn model(&self) -> &ModelView<'m> {
        &self.model
    }

    /// Speed in m/s that a normalised action of 1 stands for (from the model file).
    pub fn max_speed(&self) -> f32 {
        self.model.max_speed
    }

    /// The normalised action in `[-1, 1]^3` (local frame) for an encoded observation.
    pub fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        infer_any(&self.model, task, features)
    }

    /// The int16 output of the task output layer, before dequantization and `tanh`.
    pub fn infer_quantized(&self, task: Task, features: &[f32; FEATURES]) -> [i16; 3] {
        infer_quantized_any(&self.model, task, features)
    }
}

/// Quantizes the model input: `q_j = clamp(round_half_away(x_j / scale_j) + zp_j, -32768, 32767)`.
///
/// Reads the first `model.features` values of `features` (missing ones count as 0; NaN becomes
/// 0 before the zero point is added) into the front of `out`.
pub fn quantize_input(model: &ModelView<'_>, features: &[f32], out: &mut [i16; MAX_FEATURES]) {
    for (j, q) in out.iter_mut().enumerate().take(model.features) {
        let x = features.get(j).copied().unwrap_or(0.0);
        let scaled = roundf(x / model.input_scale(j)) + model.input_zero_point(j) as f32;
        // `as` saturates and maps NaN to 0.
        *q = scaled.clamp(-32768.0, 32767.0) as i16;
    }
}

/// One dense layer: `y = clamp(zp + requantize(bias + W x), floor, 32767)`.
///
/// Reads `layer.inputs` values of `input`, writes `layer.outputs` values of `output`. Int8
/// weights accumulate in `i32`, int16 weights in `i64` (bounds in [`skyherd_model::format`]).
#[inline]
pub fn dense(layer: &LayerView<'_>, input: &[i16], output: &mut [i16]) {
    let input = input.get(..layer.inputs).unwrap_or(input);
    let floor = layer.output_floor() as i32;
    let zero_point = layer.output_zero_point as i32;
    for (o, y) in output.iter_mut().enumerate().take(layer.outputs) {
        let scaled = match layer.weight_width {
            WeightWidth::Int8 => {
                // The decoder bounds the bias by 2^30 - 1 for int8 layers.
                let acc = (layer.bias(o) as i32).wrapping_add(dot_int8(layer.row(o), input));
                requantize(acc, layer.multiplier(o), layer.shift(o))
            }
            WeightWidth::Int16 => {
                let acc = layer.bias(o).wrapping_add(dot_int16(layer.row(o), input));
                requantize_wide(acc, layer.multiplier(o), layer.shift(o))
            }
        };
        *y = scaled
            .saturating_add(zero_point)
            .clamp(floor, i16::MAX as i32) as i16;
    }
}

/// `sum_i w_i * x_i` for int8 weights (as raw bytes) and int16 activations.
///
/// Written in lanes of 16 so that the compiler emits widening SIMD multiply-adds; every
/// product fits an `i32` lane with room for the sum (`|w x| <= 2^22`, widths are at most
/// [`MAX_WIDTH`]).
#[inline]
fn dot_int8(weights: &[u8], input: &[i16]) -> i32 {
    const LANES: usize = 16;
    let mut lanes = [0i32; LANES];
    let (w_chunks, x_chunks) = (weights.chunks_exact(LANES), input.chunks_exact(LANES));
    let tail: i32 = w_chunks
        .remainder()
        .iter()
        .zip(x_chunks.remainder())
        .map(|(&w, &x)| (w as i8 as i32) * (x as i32))
        .sum();
    for (w, x) in w_chunks.zip(x_chunks) {
        for k in 0..LANES {
            lanes[k] = lanes[k].wrapping_add((w[k] as i8 as i32) * (x[k] as i32));
        }
    }
    lanes.iter().fold(tail, |sum, &lane| sum.wrapping_add(lane))
}

/// `sum_i w_i * x_i` for int16 weights (little-endian byte pairs) and int16 activations, in
/// `i64` (each product fits an `i32`: `|w x| <= 2^30`).
#[inline]
fn dot_int16(weights: &[u8], input: &[i16]) -> i64 {
    const LANES: usize = 8;
    let mut lanes = [0i64; LANES];
    let (w_chunks, x_chunks) = (weights.chunks_exact(2 * LANES), input.chunks_exact(LANES));
    let tail: i64 = w_chunks
        .remainder()
        .chunks_exact(2)
        .zip(x_chunks.remainder())
        .map(|(w, &x)| i64::from(i16::from_le_bytes([w[0], w[1]]) as i32 * x as i32))
        .sum();
    for (w, x) in w_chunks.zip(x_chunks) {
        for k in 0..LANES {
            let wk = i16::from_le_bytes([w[2 * k], w[2 * k + 1]]) as i32;
            lanes[k] += i64::from(wk * x[k] as i32);
        }
    }
    lanes.iter().sum::<i64>() + tail
}

/// The int16 output of `task`'s output layer for any decoded model, whatever its feature count.
pub fn infer_quantized_any(model: &ModelView<'_>, task: Task, features: &[f32]) -> [i16; 3] {
    let mut input = [0i16; MAX_FEATURES];
    let mut a = [0i16; MAX_WIDTH];
    let mut b = [0i16; MAX_WIDTH];
    quantize_input(model, features, &mut input);
    dense(model.task_input(task), &input, &mut a);
    for layer in model.shared() {
        dense(layer, &a, &mut b);
        core::mem::swap(&mut a, &mut b);
    }
    let mut out = [0i16; ACTIONS];
    dense(model.task_output(task), &a, &mut out);
    out
}

/// `tanh(scale * (q - zp))` with the task output layer's quantization: the normalised action.
pub fn dequantize_action(model: &ModelView<'_>, task: Task, q: [i16; 3]) -> [f32; 3] {
    let layer = model.task_output(task);
    q.map(|q| tanhf(layer.output_scale * (q as i32 - layer.output_zero_point as i32) as f32))
}

/// The normalised action for any decoded model, whatever its feature count.
pub fn infer_any(model: &ModelView<'_>, task: Task, features: &[f32]) -> [f32; 3] {
    dequantize_action(model, task, infer_quantized_any(model, task, features))
}
