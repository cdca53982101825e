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

use crate::obs::{ENCODER_VERSION, FEATURES, feature_count};

/// The quantized actor, checked against this build's observation encoder.
#[derive(Clone, Copy, Debug)]
pub struct Actor<'m> {
    model: ModelView<'m>,
}

impl<'m> Actor<'m> {
    /// An actor over a decoded model; fails with [`FormatError::EncoderMismatch`] unless the model
    /// was made for an encoder version this build serves ([`ENCODER_VERSION`], or an older one
    /// whose features are a prefix, see [`feature_count`]) with that version's feature count.
    pub fn new(model: ModelView<'m>) -> Result<Actor<'m>, FormatError> {
        let expected = match feature_count(model.encoder_version) {
            Some(features) => (model.encoder_version, features),
            None => (ENCODER_VERSION, FEATURES),
        };
        if let Err(e) = model.check_encoder(expected.0, expected.1) {
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
pub(crate) fn quantize_input(
    model: &ModelView<'_>,
    features: &[f32],
    out: &mut [i16; MAX_FEATURES],
) {
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
    let finish = |scaled: i32| {
        scaled
            .saturating_add(zero_point)
            .clamp(floor, i16::MAX as i32) as i16
    };
    match layer.weight_width {
        WeightWidth::Int8 => {
            for (o, y) in output.iter_mut().enumerate().take(layer.outputs) {
                // The decoder bounds the bias by 2^30 - 1 for int8 layers.
                let acc = (layer.bias(o) as i32).wrapping_add(dot_int8(layer.row(o), input));
                *y = finish(requantize(acc, layer.multiplier(o), layer.shift(o)));
            }
        }
        WeightWidth::Int16 => {
            // x = 256 hi + lo with hi in [-128, 127] and lo in [0, 255], split once per layer
            // so that every row is two int16 dot products in i32 lanes instead of one in i64.
            let mut high = [0i16; MAX_WIDTH];
            let mut low = [0i16; MAX_WIDTH];
            for ((x, h), l) in input.iter().zip(&mut high).zip(&mut low) {
                *h = x >> 8;
                *l = x & 0xff;
            }
            let n = input.len();
            let (high, low) = (&high[..n], &low[..n]);
            for (o, y) in output.iter_mut().enumerate().take(layer.outputs) {
                let (high, low) = dot_int16_split(layer.row(o), high, low);
                let product = (i64::from(high) << 8) + i64::from(low);
                let acc = layer.bias(o).wrapping_add(product);
                *y = finish(requantize_wide(acc, layer.multiplier(o), layer.shift(o)));
            }
        }
    }
}

/// `sum_i w_i * x_i` for int8 weights (as raw bytes) and int16 activations.
///
/// Written in lanes of 16 so that the compiler emits widening SIMD multiply-adds (`pmaddwd`
/// on x86); every product fits an `i32` lane with room for the sum (`|w x| <= 2^22`, widths
/// are at most [`MAX_WIDTH`]). Not inlined: inlined into [`dense`]'s row loop, the lanes were
/// unrolled into scalar registers instead (see the measurements in `onboard/README.md`).
#[inline(never)]
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

/// `(sum_i w_i * high_i, sum_i w_i * low_i)` for int16 weights (little-endian byte pairs) and
/// the two byte-sized halves of the int16 activations ([`dense`] splits them), in `i32` lanes:
/// with `|w| <= 2^15`, at most [`MAX_WIDTH`] = 256 terms, `high` in `[-128, 127]` and `low` in
/// `[0, 255]`, each sum stays below `256 * 2^15 * 255 < 2^31`.
#[inline(never)]
fn dot_int16_split(weights: &[u8], high: &[i16], low: &[i16]) -> (i32, i32) {
    (dot_int16_i32(weights, high), dot_int16_i32(weights, low))
}

/// `sum_i w_i * x_i` for int16 weights and activations in `i32` lanes; the caller bounds the
/// sum ([`dot_int16_split`]).
#[inline(always)]
fn dot_int16_i32(weights: &[u8], input: &[i16]) -> i32 {
    const LANES: usize = 16;
    const HALF: usize = LANES / 2;
    let mut lanes = [0i32; LANES];
    let (w_chunks, x_chunks) = (weights.chunks_exact(2 * LANES), input.chunks_exact(LANES));
    let (w_rest, x_rest) = (w_chunks.remainder(), x_chunks.remainder());
    for (w, x) in w_chunks.zip(x_chunks) {
        for k in 0..LANES {
            let wk = i16::from_le_bytes([w[2 * k], w[2 * k + 1]]) as i32;
            lanes[k] = lanes[k].wrapping_add(wk * x[k] as i32);
        }
    }
    // The remainder in half-width lanes, then one by one: a 46-feature row is 2 x 16 + 8 + 6.
    let (w_half, x_half) = (w_rest.chunks_exact(2 * HALF), x_rest.chunks_exact(HALF));
    let tail: i32 = w_half
        .remainder()
        .chunks_exact(2)
        .zip(x_half.remainder())
        .map(|(w, &x)| i16::from_le_bytes([w[0], w[1]]) as i32 * x as i32)
        .fold(0, i32::wrapping_add);
    for (w, x) in w_half.zip(x_half) {
        for k in 0..HALF {
            let wk = i16::from_le_bytes([w[2 * k], w[2 * k + 1]]) as i32;
            lanes[k] = lanes[k].wrapping_add(wk * x[k] as i32);
        }
    }
    lanes.iter().fold(tail, |sum, &lane| sum.wrapping_add(lane))
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
pub(crate) fn dequantize_action(model: &ModelView<'_>, task: Task, q: [i16; 3]) -> [f32; 3] {
    let layer = model.task_output(task);
    q.map(|q| tanhf(layer.output_scale * (q as i32 - layer.output_zero_point as i32) as f32))
}

/// The normalised action for any decoded model, whatever its feature count.
pub fn infer_any(model: &ModelView<'_>, task: Task, features: &[f32]) -> [f32; 3] {
    dequantize_action(model, task, infer_quantized_any(model, task, features))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain definition the kernels must equal: every product in i64.
    fn reference(weights: &[i16], input: &[i16]) -> i64 {
        weights
            .iter()
            .zip(input)
            .map(|(&w, &x)| i64::from(w) * i64::from(x))
            .sum()
    }

    /// What [`dense`] computes for an int16 row.
    fn split_dot(weights: &[i16], input: &[i16]) -> i64 {
        let n = weights.len();
        let mut bytes = [0u8; 2 * MAX_WIDTH];
        let (mut high, mut low) = ([0i16; MAX_WIDTH], [0i16; MAX_WIDTH]);
        for (k, (&w, &x)) in weights.iter().zip(input).enumerate() {
            bytes[2 * k..2 * k + 2].copy_from_slice(&w.to_le_bytes());
            high[k] = x >> 8;
            low[k] = x & 0xff;
        }
        let (high, low) = dot_int16_split(&bytes[..2 * n], &high[..n], &low[..n]);
        (i64::from(high) << 8) + i64::from(low)
    }

    #[test]
    fn the_split_int16_dot_product_is_exact_at_the_extremes() {
        // Widest row, every weight and input at the corners of int16: the sums the i32 lanes
        // must hold without overflow.
        for (w, x) in [
            (i16::MIN, i16::MIN),
            (i16::MIN, i16::MAX),
            (i16::MAX, i16::MIN),
            (i16::MAX, i16::MAX),
            (i16::MIN, -1),
            (i16::MIN, 255),
        ] {
            let (weights, input) = ([w; MAX_WIDTH], [x; MAX_WIDTH]);
            assert_eq!(
                split_dot(&weights, &input),
                reference(&weights, &input),
                "w = {w}, x = {x}"
            );
        }
        // Every length from 0 to the widest (lanes and tails), pseudo-random values.
        let mut state = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state as i16
        };
        for n in 0..=MAX_WIDTH {
            let (mut weights, mut input) = ([0i16; MAX_WIDTH], [0i16; MAX_WIDTH]);
            for k in 0..n {
                weights[k] = next();
                input[k] = next();
            }
            let (weights, input) = (&weights[..n], &input[..n]);
            assert_eq!(
                split_dot(weights, input),
                reference(weights, input),
                "n = {n}"
            );
        }
    }

    #[test]
    fn the_int8_dot_product_is_exact_at_the_extremes() {
        for (w, x) in [
            (i8::MIN, i16::MIN),
            (i8::MAX, i16::MIN),
            (i8::MIN, i16::MAX),
        ] {
            let (weights, input) = ([w as u8; MAX_WIDTH], [x; MAX_WIDTH]);
            let expected = reference(&[i16::from(w); MAX_WIDTH], &input);
            assert_eq!(i64::from(dot_int8(&weights, &input)), expected);
        }
        // Every length (the 16-lane body and its tail), pseudo-random values.
        let mut state = 0x2545_F491_4F6C_DD1D_u64;
        for n in 0..=MAX_WIDTH {
            let (mut bytes, mut wide, mut input) =
                ([0u8; MAX_WIDTH], [0i16; MAX_WIDTH], [0i16; MAX_WIDTH]);
            for k in 0..n {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                bytes[k] = state as u8;
                wide[k] = i16::from(state as u8 as i8);
                input[k] = (state >> 16) as i16;
            }
            assert_eq!(
                i64::from(dot_int8(&bytes[..n], &input[..n])),
                reference(&wide[..n], &input[..n]),
                "n = {n}"
            );
        }
    }
}
