//! Quantization of a [`FloatActor`] into a model file, and the model file encoder (std).
//!
//! Scheme (TFLite-style integer arithmetic, W8A16 with an int16 first layer; pinned by the golden
//! files):
//! * **Weights**: symmetric per output channel, `scale_o = max_i |w_oi| / L`, int8 (`L = 127`)
//!   in the shared and task output layers, int16 (`L = 32767`) in the task input layers
//!   ([`format::INPUT_LAYER_WEIGHTS`]), rounded with error compensation (GPTQ's update,
//!   `ErrorCompensation` below): each weight's rounding error is pushed onto the row's weights
//!   not yet rounded, weighted by the calibration inputs' second moment, so that the layer's
//!   *output* stays close rather than each weight.
//! * **Input**: affine int16 per feature; the per-feature scale is folded into the first layer's
//!   weights before they are quantized.
//! * **Activations**: affine int16 per tensor. The task input layers share one output
//!   quantization (the shared layers must read both tasks' hidden vectors with one scale); ReLU
//!   layers have their minimum at 0, so their zero point is -32768. Task output layers are
//!   quantized per task before `tanh`, their range clipped to `±OUTPUT_CLIP` where `tanh` is
//!   flat.
//! * **Ranges**: each tensor's (and each input feature's) min and max over the calibration set,
//!   widened to include 0 and then by [`RANGE_MARGIN`]: with 16 bits a wide range costs little
//!   resolution, and a value the calibration did not reach is not clipped.
//! * **Bias**: int64 at scale `input_scale * weight_scale_o`, the input zero points folded in.
//! * **Requantization**: `input_scale * weight_scale_o / output_scale` as a Q31 multiplier in
//!   `[2^30, 2^31)` and a right shift, see [`crate::format::requantize`].
//!
//! Why these widths, measured on the shipped actor (RMS action error in units of max speed, each
//! part alone, plain rounding): int8 first-layer weights 6.0 % (12-bit 0.3 %), int8 activations
//! 1.9 % (16-bit 0.02 %), int8 input 2.2 %, int8 shared and output weights 1.6 % and 1.0 %
//! (0.8 % together with error compensation). The format-1 scheme, int8 everywhere, came to 4.9 %
//! after error compensation and quantization-aware fine-tuning.

use core::fmt;

use crate::Task;
use crate::float::FloatActor;
use crate::format::{
    self, ACTIONS, ACTIVATION_NONE, ACTIVATION_RELU, CRC32, FORMAT_VERSION, HEADER_LEN,
    INPUT_LAYER_WEIGHTS, MAGIC, MAX_FEATURES, MAX_SHARED_LAYERS, MAX_WIDTH, WeightWidth,
};

/// Largest pre-tanh magnitude the output quantization represents (`1 - tanh(8) < 3e-7`).
pub const OUTPUT_CLIP: f32 = 8.0;

/// Factor by which every calibrated range is widened (see the module docs).
pub const RANGE_MARGIN: f32 = 2.0;

/// What the model file records besides the weights.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ModelMeta {
    /// Version of the observation encoder the actor was trained with
    /// (`skyherd_onboard::obs::ENCODER_VERSION`).
    pub encoder_version: u16,
    /// Speed in m/s that a normalised action of 1 stands for.
    pub max_speed: f32,
}

/// Why an actor could not be quantized.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum QuantizeError {
    /// The layers do not chain into the Fig. 2 architecture.
    Shape,
    /// A width or count is zero or beyond the inference core's capacity.
    Capacity {
        /// Which field.
        field: &'static str,
        /// Its value.
        value: usize,
        /// The largest value accepted.
        max: usize,
    },
    /// No calibration observations were given.
    NoCalibration,
    /// A calibration observation has the wrong length.
    CalibrationLength {
        /// Features the actor takes.
        expected: usize,
        /// Length found.
        found: usize,
    },
    /// A weight, bias, calibration value or the max speed is NaN or infinite (or the speed not
    /// positive).
    NonFinite,
    /// A bias does not fit the range the inference core is proven for (see
    /// [`format::BIAS_LIMIT_INT8`]).
    BiasOverflow,
    /// A requantization multiplier is too large to represent (a degenerate scale).
    Multiplier,
}

impl fmt::Display for QuantizeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            QuantizeError::Shape => f.write_str("actor layers do not chain into F->H, H->H, H->3"),
            QuantizeError::Capacity { field, value, max } => {
                write!(f, "{field} = {value} is outside 1..={max}")
            }
            QuantizeError::NoCalibration => f.write_str("no calibration observations"),
            QuantizeError::CalibrationLength { expected, found } => write!(
                f,
                "calibration observation has {found} features, the actor takes {expected}"
            ),
            QuantizeError::NonFinite => {
                f.write_str("NaN or infinity in weights, calibration data or max speed")
            }
            QuantizeError::BiasOverflow => {
                f.write_str("a quantized bias exceeds the format's limit (2^30 int8, 2^40 int16)")
            }
            QuantizeError::Multiplier => f.write_str("a requantization multiplier exceeds 2^30"),
        }
    }
}

impl std::error::Error for QuantizeError {}

/// One quantized dense layer, ready to be written.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantizedLayer {
    /// Input width.
    pub inputs: usize,
    /// Output width.
    pub outputs: usize,
    /// ReLU fused into the output clamp.
    pub relu: bool,
    /// How the weights are stored.
    pub weight_width: WeightWidth,
    /// Output zero point.
    pub output_zero_point: i16,
    /// Output scale.
    pub output_scale: f32,
    /// Weights, row-major `[out][in]`, each within `±weight_width.max_level()`.
    pub weights: Vec<i16>,
    /// Per-output-channel weight scale.
    pub weight_scales: Vec<f32>,
    /// Bias (input zero point folded in).
    pub bias: Vec<i64>,
    /// Requantization multiplier per output channel.
    pub multiplier: Vec<i32>,
    /// Requantization right shift per output channel.
    pub shift: Vec<u8>,
}

/// A quantized actor: everything a model file holds, as owned values.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantizedModel {
    /// Encoder version and max speed.
    pub meta: ModelMeta,
    /// Hidden width.
    pub hidden: usize,
    /// Per-feature input scale.
    pub input_scales: Vec<f32>,
    /// Per-feature input zero point.
    pub input_zero_points: Vec<i16>,
    /// Layers in file order: task inputs, shared, task outputs.
    pub layers: Vec<QuantizedLayer>,
}

impl QuantizedModel {
    /// The model file bytes (layout in [`crate::format`]). Does not validate; [`format::decode`]
    /// does.
    pub fn to_bytes(&self) -> Vec<u8> {
        let features = self.input_scales.len();
        let shared_layers = self.layers.len().saturating_sub(2 * Task::COUNT);
        let mut out = Vec::with_capacity(format::file_len(features, self.hidden, shared_layers));
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&(HEADER_LEN as u16).to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes()); // file length, patched below
        out.extend_from_slice(&self.meta.encoder_version.to_le_bytes());
        out.extend_from_slice(&(features as u16).to_le_bytes());
        out.extend_from_slice(&(self.hidden as u16).to_le_bytes());
        out.push(Task::COUNT as u8);
        out.push(shared_layers as u8);
        out.push(ACTIONS as u8);
        out.push(0);
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.meta.max_speed.to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        debug_assert_eq!(out.len(), HEADER_LEN);
        self.input_scales
            .iter()
            .for_each(|s| out.extend_from_slice(&s.to_le_bytes()));
        self.input_zero_points
            .iter()
            .for_each(|z| out.extend_from_slice(&z.to_le_bytes()));
        for layer in &self.layers {
            out.extend_from_slice(&(layer.inputs as u16).to_le_bytes());
            out.extend_from_slice(&(layer.outputs as u16).to_le_bytes());
            out.push(if layer.relu {
                ACTIVATION_RELU
            } else {
                ACTIVATION_NONE
            });
            out.push(layer.weight_width as u8);
            out.extend_from_slice(&layer.output_zero_point.to_le_bytes());
            out.extend_from_slice(&layer.output_scale.to_le_bytes());
            for &w in &layer.weights {
                match layer.weight_width {
                    WeightWidth::Int8 => out.push(w as i8 as u8),
                    WeightWidth::Int16 => out.extend_from_slice(&w.to_le_bytes()),
                }
            }
            for s in &layer.weight_scales {
                out.extend_from_slice(&s.to_le_bytes());
            }
            for b in &layer.bias {
                out.extend_from_slice(&b.to_le_bytes());
            }
            for m in &layer.multiplier {
                out.extend_from_slice(&m.to_le_bytes());
            }
            out.extend_from_slice(&layer.shift);
        }
        let total = (out.len() + format::CRC_LEN) as u32;
        out[8..12].copy_from_slice(&total.to_le_bytes());
        let crc = CRC32.checksum(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }
}

/// Running min and max of a set of values.
#[derive(Clone, Copy, Debug)]
struct Range {
    min: f32,
    max: f32,
}

impl Range {
    const EMPTY: Range = Range {
        min: f32::INFINITY,
        max: f32::NEG_INFINITY,
    };
    fn add(&mut self, v: f32) {
        self.min = self.min.min(v);
        self.max = self.max.max(v);
    }
    fn add_all(&mut self, vs: &[f32]) {
        vs.iter().for_each(|&v| self.add(v));
    }
    /// Affine int16 parameters covering the range widened to include 0, clipped to `±limit`,
    /// then widened by [`RANGE_MARGIN`].
    fn affine(self, limit: f32) -> (f32, i16) {
        let (min, max) = if self.min <= self.max {
            (self.min.max(-limit), self.max.min(limit))
        } else {
            (0.0, 0.0)
        };
        let (min, max) = (RANGE_MARGIN * min.min(0.0), RANGE_MARGIN * max.max(0.0));
        let scale = ((max - min) / 65535.0).max(1e-9);
        let zero_point = (-32768.0 - min / scale).round().clamp(-32768.0, 32767.0) as i16;
        (scale, zero_point)
    }
}

/// `multiplier * 2^-shift ~= m`, `multiplier` in `[2^30, 2^31)` (or 0 for a vanishing `m`).
pub fn quantize_multiplier(m: f64) -> Result<(i32, u8), QuantizeError> {
    if !m.is_finite() || m < 0.0 {
        return Err(QuantizeError::NonFinite);
    }
    if m == 0.0 {
        return Ok((0, 31));
    }
    // m = f * 2^e with f in [0.5, 1).
    let mut e = m.log2().floor() as i32 + 1;
    let mut f = m / 2f64.powi(e);
    while f >= 1.0 {
        f /= 2.0;
        e += 1;
    }
    while f < 0.5 {
        f *= 2.0;
        e -= 1;
    }
    let mut q = (f * (1u64 << 31) as f64).round() as i64;
    if q == 1i64 << 31 {
        q /= 2;
        e += 1;
    }
    let mut shift = 31 - e;
    if shift < 1 {
        return Err(QuantizeError::Multiplier);
    }
    if shift > 62 {
        let extra = (shift - 62).min(63) as u32;
        q = (q + (1i64 << (extra - 1))) >> extra;
        shift = 62;
    }
    Ok((q as i32, shift as u8))
}

fn check_capacity(field: &'static str, value: usize, max: usize) -> Result<(), QuantizeError> {
    if (1..=max).contains(&value) {
        Ok(())
    } else {
        Err(QuantizeError::Capacity { field, value, max })
    }
}

/// Quantizes `actor` into model file bytes, calibrating activation ranges on `calibration`:
/// recorded `(task, features)` observations, ideally from the states the policy visits.
///
/// ```
/// use skyherd_model::{decode, quantize, ActorShape, FloatActor, ModelMeta, Task};
/// let actor = FloatActor::random(ActorShape { features: 4, hidden: 8, shared_layers: 1 }, 7);
/// let obs = [[0.1, -0.3, 0.5, 0.0], [0.9, 0.2, -0.4, 1.0]];
/// let calibration = obs.iter().map(|o| (Task::Driving, &o[..]));
/// let meta = ModelMeta { encoder_version: 1, max_speed: 5.0 };
/// let bytes = quantize(&actor, meta, calibration).unwrap();
/// assert_eq!(decode(&bytes).unwrap().hidden, 8);
/// ```
pub fn quantize<'o>(
    actor: &FloatActor,
    meta: ModelMeta,
    calibration: impl IntoIterator<Item = (Task, &'o [f32])>,
) -> Result<Vec<u8>, QuantizeError> {
    Ok(quantize_model(actor, meta, calibration)?.to_bytes())
}

/// Like [`quantize`], returning the owned [`QuantizedModel`] instead of bytes.
pub fn quantize_model<'o>(
    actor: &FloatActor,
    meta: ModelMeta,
    calibration: impl IntoIterator<Item = (Task, &'o [f32])>,
) -> Result<QuantizedModel, QuantizeError> {
    let shape = actor.shape().ok_or(QuantizeError::Shape)?;
    check_capacity("feature count", shape.features, MAX_FEATURES)?;
    check_capacity("hidden width", shape.hidden, MAX_WIDTH)?;
    if shape.shared_layers > MAX_SHARED_LAYERS {
        return Err(QuantizeError::Capacity {
            field: "shared layer count",
            value: shape.shared_layers,
            max: MAX_SHARED_LAYERS,
        });
    }
    if !(meta.max_speed.is_finite() && meta.max_speed > 0.0) {
        return Err(QuantizeError::NonFinite);
    }
    let all_layers = actor
        .task_inputs
        .iter()
        .chain(&actor.shared)
        .chain(&actor.task_outputs);
    if all_layers
        .flat_map(|d| d.weights.iter().chain(&d.bias))
        .any(|v| !v.is_finite())
    {
        return Err(QuantizeError::NonFinite);
    }

    // One pass over the calibration set collects every tensor's range.
    let mut input = vec![Range::EMPTY; shape.features];
    let mut hidden_in = Range::EMPTY;
    let mut shared = vec![Range::EMPTY; shape.shared_layers];
    let mut outputs = vec![Range::EMPTY; Task::COUNT];
    // Second moments of every layer's input, for the error-compensating rounding.
    let mut moments = LayerMoments::new(shape);
    let mut count = 0usize;
    for (task, features) in calibration {
        if features.len() != shape.features {
            return Err(QuantizeError::CalibrationLength {
                expected: shape.features,
                found: features.len(),
            });
        }
        if features.iter().any(|v| !v.is_finite()) {
            return Err(QuantizeError::NonFinite);
        }
        input.iter_mut().zip(features).for_each(|(r, &v)| r.add(v));
        let trace = actor.trace(task, features);
        hidden_in.add_all(&trace.input_layer);
        shared
            .iter_mut()
            .zip(&trace.shared)
            .for_each(|(r, v)| r.add_all(v));
        outputs[task.index()].add_all(&trace.pre_tanh);
        moments.add(task, features, &trace);
        count += 1;
    }
    if count == 0 {
        return Err(QuantizeError::NoCalibration);
    }

    let (input_scales, input_zero_points): (Vec<f32>, Vec<i16>) =
        input.iter().map(|r| r.affine(f32::INFINITY)).unzip();
    let hidden_in = hidden_in.affine(f32::INFINITY);
    let shared: Vec<(f32, i16)> = shared.iter().map(|r| r.affine(f32::INFINITY)).collect();
    let last_hidden = shared.last().copied().unwrap_or(hidden_in);

    let mut layers = Vec::with_capacity(2 * Task::COUNT + shape.shared_layers);
    for (t, dense) in actor.task_inputs.iter().enumerate() {
        // Per-feature input scale folded into the weights; the layer sees input scale 1, so
        // its inputs' second moments are taken in units of each feature's scale.
        let folded: Vec<f32> = dense
            .weights
            .chunks_exact(dense.inputs)
            .flat_map(|row| row.iter().zip(&input_scales).map(|(w, s)| w * s))
            .collect();
        let hessian = moments.task_input[t].scaled(&input_scales);
        layers.push(quantize_layer(
            dense.inputs,
            &folded,
            &dense.bias,
            1.0,
            &input_zero_points,
            hidden_in,
            true,
            INPUT_LAYER_WEIGHTS,
            &hessian,
        )?);
    }
    let mut previous = hidden_in;
    for ((dense, &out), m) in actor.shared.iter().zip(&shared).zip(&moments.shared) {
        let zero_points = vec![previous.1; dense.inputs];
        layers.push(quantize_layer(
            dense.inputs,
            &dense.weights,
            &dense.bias,
            previous.0,
            &zero_points,
            out,
            true,
            WeightWidth::Int8,
            m,
        )?);
        previous = out;
    }
    for ((dense, range), m) in actor
        .task_outputs
        .iter()
        .zip(&outputs)
        .zip(&moments.task_output)
    {
        let range = if range.min <= range.max {
            *range
        } else {
            // A task without calibration observations: the whole clipped range.
            Range {
                min: -OUTPUT_CLIP,
                max: OUTPUT_CLIP,
            }
        };
        let output_quantization = range.affine(OUTPUT_CLIP);
        let zero_points = vec![last_hidden.1; dense.inputs];
        layers.push(quantize_layer(
            dense.inputs,
            &dense.weights,
            &dense.bias,
            last_hidden.0,
            &zero_points,
            output_quantization,
            false,
            WeightWidth::Int8,
            m,
        )?);
    }
    Ok(QuantizedModel {
        meta,
        hidden: shape.hidden,
        input_scales,
        input_zero_points,
        layers,
    })
}

// One call per layer with everything it needs spelled out; a parameter struct would only rename.
#[allow(clippy::too_many_arguments)]
fn quantize_layer(
    inputs: usize,
    weights: &[f32],
    bias: &[f32],
    input_scale: f32,
    input_zero_points: &[i16],
    (output_scale, output_zero_point): (f32, i16),
    relu: bool,
    weight_width: WeightWidth,
    inputs_moment: &Moment,
) -> Result<QuantizedLayer, QuantizeError> {
    let rounding = ErrorCompensation::new(inputs_moment);
    let outputs = bias.len();
    let mut layer = QuantizedLayer {
        inputs,
        outputs,
        relu,
        weight_width,
        output_zero_point,
        output_scale,
        weights: Vec::with_capacity(inputs * outputs),
        weight_scales: Vec::with_capacity(outputs),
        bias: Vec::with_capacity(outputs),
        multiplier: Vec::with_capacity(outputs),
        shift: Vec::with_capacity(outputs),
    };
    for (row, &b) in weights.chunks_exact(inputs).zip(bias) {
        let max = row.iter().fold(0.0f32, |m, w| m.max(w.abs()));
        let levels = weight_width.max_level();
        let scale = if max > 0.0 { max / levels as f32 } else { 1.0 };
        let q = rounding.round_row(row, scale, levels);
        let accumulator_scale = input_scale as f64 * scale as f64;
        let folded = (b as f64 / accumulator_scale).round()
            - q.iter()
                .zip(input_zero_points)
                .map(|(&w, &z)| w as f64 * z as f64)
                .sum::<f64>();
        if folded.is_nan() || folded.abs() > weight_width.bias_limit() as f64 {
            return Err(QuantizeError::BiasOverflow);
        }
        let (multiplier, shift) = quantize_multiplier(accumulator_scale / output_scale as f64)?;
        layer.weights.extend_from_slice(&q);
        layer.weight_scales.push(scale);
        layer.bias.push(folded as i64);
        layer.multiplier.push(multiplier);
        layer.shift.push(shift);
    }
    Ok(layer)
}

/// The uncentred second moment `E[x x^T]` of a layer's input over the calibration set.
#[derive(Clone, Debug)]
struct Moment {
    n: usize,
    sum: Vec<f64>,
    count: usize,
}

impl Moment {
    fn new(n: usize) -> Moment {
        Moment {
            n,
            sum: vec![0.0; n * n],
            count: 0,
        }
    }

    fn add(&mut self, x: &[f32]) {
        for (i, &xi) in x.iter().enumerate().take(self.n) {
            if xi == 0.0 {
                continue;
            }
            let row = &mut self.sum[i * self.n..(i + 1) * self.n];
            for (s, &xj) in row.iter_mut().zip(x) {
                *s += f64::from(xi) * f64::from(xj);
            }
        }
        self.count += 1;
    }

    /// The moment of `x_i / scales_i`.
    fn scaled(&self, scales: &[f32]) -> Moment {
        let mut m = self.clone();
        for i in 0..self.n {
            for j in 0..self.n {
                m.sum[i * self.n + j] /= f64::from(scales[i]) * f64::from(scales[j]);
            }
        }
        m
    }
}

/// Input moments of every layer: per task for the task layers, over both tasks for the shared.
struct LayerMoments {
    task_input: Vec<Moment>,
    shared: Vec<Moment>,
    task_output: Vec<Moment>,
}

impl LayerMoments {
    fn new(shape: crate::float::ActorShape) -> LayerMoments {
        LayerMoments {
            task_input: vec![Moment::new(shape.features); Task::COUNT],
            shared: vec![Moment::new(shape.hidden); shape.shared_layers],
            task_output: vec![Moment::new(shape.hidden); Task::COUNT],
        }
    }

    fn add(&mut self, task: Task, features: &[f32], trace: &crate::float::Trace) {
        self.task_input[task.index()].add(features);
        let mut previous = &trace.input_layer;
        for (m, out) in self.shared.iter_mut().zip(&trace.shared) {
            m.add(previous);
            previous = out;
        }
        self.task_output[task.index()].add(previous);
    }
}

/// Rounding that compensates each weight's rounding error in the weights not yet rounded, in
/// proportion to how the layer's inputs co-vary (the optimal-brain-quantizer update of GPTQ,
/// Frantar et al. 2023): it minimises the error of the layer's *output* over the calibration
/// inputs rather than of each weight. Deterministic (fixed order, f64).
struct ErrorCompensation {
    n: usize,
    /// Upper Cholesky factor `U` of the damped inverse moment (`H^-1 = U^T U`); empty when the
    /// moment is unusable, which falls back to round-to-nearest.
    upper: Vec<f64>,
}

/// Damping added to the moment's diagonal, relative to its mean diagonal.
const DAMPING: f64 = 0.01;

impl ErrorCompensation {
    fn new(moment: &Moment) -> ErrorCompensation {
        let n = moment.n;
        let none = ErrorCompensation {
            n,
            upper: Vec::new(),
        };
        if moment.count == 0 {
            return none;
        }
        let mut h: Vec<f64> = moment.sum.iter().map(|s| s / moment.count as f64).collect();
        let mean_diag = (0..n).map(|i| h[i * n + i]).sum::<f64>() / n as f64;
        if !(mean_diag.is_finite() && mean_diag > 0.0) {
            return none;
        }
        for i in 0..n {
            // Inputs that are always zero get the mean curvature (their weights' errors then
            // cost something, and the moment stays invertible).
            if h[i * n + i] <= 0.0 {
                h[i * n + i] = mean_diag;
            }
            h[i * n + i] += DAMPING * mean_diag;
        }
        let Some(inverse) = cholesky_lower(&h, n).map(|l| inverse_from_cholesky(&l, n)) else {
            return none;
        };
        match cholesky_lower(&inverse, n) {
            // U = L^T.
            Some(l) => ErrorCompensation {
                n,
                upper: (0..n * n).map(|k| l[(k % n) * n + k / n]).collect(),
            },
            None => none,
        }
    }

    /// `row / scale` rounded to integers within `±levels`.
    fn round_row(&self, row: &[f32], scale: f32, levels: i32) -> Vec<i16> {
        let levels = f64::from(levels);
        let nearest = |w: f64| (w / f64::from(scale)).round().clamp(-levels, levels);
        if self.upper.is_empty() || row.len() != self.n {
            return row.iter().map(|&w| nearest(f64::from(w)) as i16).collect();
        }
        let n = self.n;
        let mut w: Vec<f64> = row.iter().map(|&x| f64::from(x)).collect();
        let mut q = vec![0i16; n];
        for i in 0..n {
            let qi = nearest(w[i]);
            q[i] = qi as i16;
            let error = (w[i] - qi * f64::from(scale)) / self.upper[i * n + i];
            let row_of_u = &self.upper[i * n + i + 1..(i + 1) * n];
            for (wj, uij) in w[i + 1..].iter_mut().zip(row_of_u) {
                *wj -= error * uij;
            }
        }
        q
    }
}

/// Lower Cholesky factor of the symmetric positive definite `a` (`n x n`, row-major).
fn cholesky_lower(a: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let dot: f64 = (0..j).map(|k| l[i * n + k] * l[j * n + k]).sum();
            let v = a[i * n + j] - dot;
            if i == j {
                if !(v.is_finite() && v > 0.0) {
                    return None;
                }
                l[i * n + i] = v.sqrt();
            } else {
                l[i * n + j] = v / l[j * n + j];
            }
        }
    }
    Some(l)
}

/// `(L L^T)^-1` from the lower factor `L`.
fn inverse_from_cholesky(l: &[f64], n: usize) -> Vec<f64> {
    // L^-1 by forward substitution, then (L^-1)^T L^-1.
    let mut li = vec![0.0; n * n];
    for c in 0..n {
        for i in c..n {
            let mut v = if i == c { 1.0 } else { 0.0 };
            for k in c..i {
                v -= l[i * n + k] * li[k * n + c];
            }
            li[i * n + c] = v / l[i * n + i];
        }
    }
    let mut inv = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..n {
            inv[i * n + j] = (i.max(j)..n).map(|k| li[k * n + i] * li[k * n + j]).sum();
        }
    }
    inv
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cholesky_inverse_inverts() {
        let a = [4.0, 2.0, 0.6, 2.0, 5.0, 1.0, 0.6, 1.0, 3.0];
        let l = cholesky_lower(&a, 3).expect("positive definite");
        let inv = inverse_from_cholesky(&l, 3);
        for i in 0..3 {
            for j in 0..3 {
                let v: f64 = (0..3).map(|k| a[i * 3 + k] * inv[k * 3 + j]).sum();
                assert!(
                    (v - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12,
                    "{i},{j}: {v}"
                );
            }
        }
        assert!(
            cholesky_lower(&[1.0, 2.0, 2.0, 1.0], 2).is_none(),
            "indefinite"
        );
    }

    #[test]
    fn error_compensation_beats_round_to_nearest_on_the_output() {
        // Strongly correlated inputs (as a trained layer sees): x = (z + small noise per input).
        let mut rng = crate::SplitMix64::new(9);
        let n = 24;
        let samples: Vec<Vec<f32>> = (0..2000)
            .map(|_| {
                let z = rng.uniform(-1.0, 1.0);
                (0..n)
                    .map(|_| (z + 0.1 * rng.uniform(-1.0, 1.0)) as f32)
                    .collect()
            })
            .collect();
        let mut moment = Moment::new(n);
        samples.iter().for_each(|x| moment.add(x));
        let row: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0) as f32).collect();
        let scale = row.iter().fold(0.0f32, |m, w| m.max(w.abs())) / 127.0;
        let output_error = |q: &[i16]| -> f64 {
            samples
                .iter()
                .map(|x| {
                    let y: f64 = row.iter().zip(x).map(|(w, x)| f64::from(w * x)).sum();
                    let yq: f64 = q
                        .iter()
                        .zip(x)
                        .map(|(&q, x)| f64::from(q as f32 * scale * x))
                        .sum();
                    (y - yq).powi(2)
                })
                .sum::<f64>()
        };
        let nearest: Vec<i16> = row.iter().map(|w| (w / scale).round() as i16).collect();
        let compensated = ErrorCompensation::new(&moment).round_row(&row, scale, 127);
        assert_ne!(nearest, compensated);
        let (e_nearest, e_compensated) = (output_error(&nearest), output_error(&compensated));
        assert!(
            e_compensated < 0.5 * e_nearest,
            "compensated {e_compensated} vs nearest {e_nearest}"
        );
        // No calibration: plain round-to-nearest.
        assert_eq!(
            ErrorCompensation::new(&Moment::new(n)).round_row(&row, scale, 127),
            nearest
        );
    }

    #[test]
    fn multiplier_round_trips() {
        for m in [
            1e-9,
            3.7e-5,
            0.001,
            0.25,
            0.5,
            0.999_999_9,
            1.0,
            3.0,
            1000.0,
        ] {
            let (q, s) = quantize_multiplier(m).unwrap();
            let back = q as f64 / 2f64.powi(s as i32);
            assert!(((back - m) / m).abs() < 1e-8, "{m}: {q} >> {s} = {back}");
            assert!((1 << 30..=i32::MAX).contains(&q));
        }
        assert_eq!(quantize_multiplier(0.0), Ok((0, 31)));
        assert_eq!(quantize_multiplier(1e40), Err(QuantizeError::Multiplier));
        // Tiny multipliers lose precision rather than failing.
        let (q, s) = quantize_multiplier(1e-25).unwrap();
        assert_eq!(s, 62);
        assert!(q < 1 << 30);
    }

    #[test]
    fn affine_covers_zero_with_the_margin() {
        // [0, 6.5535] widened by the margin 2 to [0, 13.107]: 65535 steps of 0.0002.
        let (scale, zp) = Range {
            min: 0.0,
            max: 6.5535,
        }
        .affine(f32::INFINITY);
        assert!((scale - 0.0002).abs() < 1e-9, "{scale}");
        assert_eq!(zp, -32768);
        let (_, zp) = Range {
            min: -1.0,
            max: 1.0,
        }
        .affine(f32::INFINITY);
        // 65535 steps over a symmetric range put 0 half a step off the grid's middle.
        assert_eq!(zp, -1);
        // Positive only: 0 is still in range.
        let (scale, zp) = Range { min: 1.0, max: 2.0 }.affine(f32::INFINITY);
        assert_eq!(zp, -32768);
        assert!((scale - 4.0 / 65535.0).abs() < 1e-9);
        // Clipped at the limit before the margin.
        let (scale, _) = Range {
            min: -20.0,
            max: 20.0,
        }
        .affine(OUTPUT_CLIP);
        assert!((scale - 2.0 * 16.0 / 65535.0).abs() < 1e-9);
    }

    #[test]
    fn int16_rounding_stays_within_its_levels() {
        let row = [0.5f32, -1.0, 0.25];
        let q = ErrorCompensation::new(&Moment::new(3)).round_row(&row, 1.0 / 32767.0, 32767);
        assert_eq!(q, vec![16384, -32767, 8192]);
    }
}
