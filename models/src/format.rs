//! The byte layout of a model file and its zero-copy decoder.
//!
//! # Layout (format version 2)
//!
//! All integers and floats are **little-endian, fixed width**; nothing is aligned, nothing is
//! variable-length. The file is hand-laid-out rather than postcard-encoded on purpose: postcard
//! writes integers as varints, so neither the header nor the bias / multiplier arrays would
//! sit at offsets computable from the header, and [`decode`] could not hand out borrowed slices
//! of them. With a fixed layout every array is a sub-slice of the input at a known offset.
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | `[u8; 4]` | magic [`MAGIC`] = `b"SKYM"` |
//! | 4 | `u16` | format version, [`FORMAT_VERSION`] |
//! | 6 | `u16` | header length in bytes, [`HEADER_LEN`] |
//! | 8 | `u32` | total file length in bytes, CRC trailer included |
//! | 12 | `u16` | observation-encoder version the model was trained with |
//! | 14 | `u16` | feature count `F` (encoder output length) |
//! | 16 | `u16` | hidden width `H` |
//! | 18 | `u8` | task count `T` (must be [`Task::COUNT`]) |
//! | 19 | `u8` | shared hidden layer count `S` |
//! | 20 | `u8` | action count (must be [`ACTIONS`]) |
//! | 21 | `u8` | reserved, 0 |
//! | 22 | `u16` | reserved, 0 |
//! | 24 | `f32` | max speed, m/s: a normalised action of 1 means this speed |
//! | 28 | `u32` | reserved, 0 |
//! | 32 | `[f32; F]` | input quantization scale per feature |
//! | 32 + 4F | `[i16; F]` | input quantization zero point per feature |
//! | 32 + 6F | layers | `T` task input layers (`F -> H`, ReLU), `S` shared (`H -> H`, ReLU), `T` task output layers (`H -> 3`, none) |
//! | len - 4 | `u32` | CRC-32 (ISO-HDLC, as zlib) of every byte before it |
//!
//! Each layer record with `I` inputs, `O` outputs and `B` bytes per weight:
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | `u16` | `I` |
//! | 2 | `u16` | `O` |
//! | 4 | `u8` | activation: 0 none, 1 ReLU (fused into the output clamp) |
//! | 5 | `u8` | bytes per weight `B`: 1 (int8) or 2 (int16), see [`WeightWidth`] |
//! | 6 | `i16` | output zero point |
//! | 8 | `f32` | output scale |
//! | 12 | `[i8; O*I]` or `[i16; O*I]` | weights, row-major `[out][in]` |
//! | 12 + BOI | `[f32; O]` | per-output-channel weight scale |
//! | 12 + BOI + 4O | `[i64; O]` | bias with the input zero point folded in |
//! | | `[i32; O]` | requantization multiplier `M`, `0 <= M < 2^31` |
//! | | `[u8; O]` | requantization right shift `s`, `1..=62` |
//!
//! # Arithmetic (what the numbers mean)
//!
//! **Weights are int8** (symmetric, per output channel), except where a layer record says int16:
//! the quantizer gives the two task input layers int16 weights, because the trained actor's first
//! layer is where rounding costs most (int8 there alone moves the action by 6 % of max speed RMS,
//! 12-bit weights by 0.3 %). **Activations are affine int16**: `real = scale * (q - zero_point)`.
//! The model input is quantized per feature,
//! `q_j = clamp(round_half_away(x_j / scale_j) + zp_j, -32768, 32767)`; the per-feature scale is
//! folded into the first layer's float weights before they are quantized, so the first layer
//! sees an input scale of 1. A layer computes, per output channel `o`,
//!
//! ```text
//! acc_o = bias_o + sum_i w_oi * q_i                      (exact: int32 for int8 weights,
//!                                                         int64 for int16 weights)
//! y_o   = clamp(zp_out + requantize(acc_o, M_o, s_o), lo, 32767)
//! requantize(a, M, s) = (a * M + 2^(s-1)) >> s           (int64, or int128 for int64 acc)
//! ```
//!
//! with `lo = zp_out` for ReLU layers and `-32768` otherwise. The rounding is **single rounding,
//! half towards +infinity** (TFLite's `TFLITE_SINGLE_ROUNDING` form), see [`requantize`]. The
//! decoder guarantees `|bias| <=` [`BIAS_LIMIT_INT8`] for int8-weight layers
//! ([`BIAS_LIMIT_INT16`] for int16) and widths `<= MAX_WIDTH`, so no accumulator or product can
//! overflow. The task output layer's int16 values are dequantized with its output scale and zero
//! point and squashed with `tanh` into `[-1, 1]`.
//!
//! Version 1 (int8 activations and weights throughout, int32 bias) is not read any more: its
//! int8 activations and first-layer weights put the shipped actor 4.9 % of max speed (RMS) away
//! from its float self.

use core::fmt;

use crate::Task;

/// First four bytes of every model file.
pub const MAGIC: [u8; 4] = *b"SKYM";
/// The format version this crate reads and writes.
pub const FORMAT_VERSION: u16 = 2;
/// Length of the fixed header in bytes.
pub const HEADER_LEN: usize = 32;
/// Length of a layer record's fixed part in bytes.
pub const LAYER_HEADER_LEN: usize = 12;
/// Length of the CRC trailer in bytes.
pub const CRC_LEN: usize = 4;
/// Outputs of the actor: a normalised 3-D velocity.
pub const ACTIONS: usize = 3;
/// Largest feature count a model may declare (the inference core's input buffer).
pub const MAX_FEATURES: usize = 256;
/// Largest hidden width a model may declare (the inference core's activation buffers).
pub const MAX_WIDTH: usize = 256;
/// Largest number of shared hidden layers.
pub const MAX_SHARED_LAYERS: usize = 8;
/// Largest number of layer records in a file.
pub const MAX_LAYERS: usize = 2 * Task::COUNT + MAX_SHARED_LAYERS;
/// Largest magnitude of a stored bias in a layer with int8 weights. With widths `<= MAX_WIDTH`
/// its int32 accumulator stays below `(2^30 - 1) + 256 * 128 * 32768 = 2^31 - 1`.
pub const BIAS_LIMIT_INT8: i64 = (1 << 30) - 1;
/// Largest magnitude of a stored bias in a layer with int16 weights. Its int64 accumulator stays
/// below `2^40 + 256 * 2^30 < 2^41`, and times a multiplier `< 2^31` below `2^72`: the
/// requantization of such a layer runs in int128.
pub const BIAS_LIMIT_INT16: i64 = 1 << 40;
/// Smallest and largest requantization right shift.
pub const SHIFT_RANGE: core::ops::RangeInclusive<u8> = 1..=62;

/// Activation code for "no activation" in a layer record.
pub const ACTIVATION_NONE: u8 = 0;
/// Activation code for ReLU in a layer record.
pub const ACTIVATION_RELU: u8 = 1;

/// The CRC used for the trailer: CRC-32/ISO-HDLC (the zlib / PNG CRC).
pub const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// How a layer's weights are stored: the byte at offset 5 of its record.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum WeightWidth {
    /// One byte per weight, `-128..=127` (the quantizer uses `±127`).
    #[default]
    Int8 = 1,
    /// Two bytes per weight, little-endian `i16` (the quantizer uses `±32767`).
    Int16 = 2,
}

impl WeightWidth {
    /// Bytes per weight.
    pub const fn bytes(self) -> usize {
        self as usize
    }
    /// Largest weight magnitude the quantizer writes: `2^(bits-1) - 1`.
    pub const fn max_level(self) -> i32 {
        match self {
            WeightWidth::Int8 => i8::MAX as i32,
            WeightWidth::Int16 => i16::MAX as i32,
        }
    }
    /// The width for a record's byte, if it names one.
    pub const fn from_code(code: u8) -> Option<WeightWidth> {
        match code {
            1 => Some(WeightWidth::Int8),
            2 => Some(WeightWidth::Int16),
            _ => None,
        }
    }
    /// Largest stored bias magnitude for this width ([`BIAS_LIMIT_INT8`], [`BIAS_LIMIT_INT16`]).
    pub const fn bias_limit(self) -> i64 {
        match self {
            WeightWidth::Int8 => BIAS_LIMIT_INT8,
            WeightWidth::Int16 => BIAS_LIMIT_INT16,
        }
    }
}

/// The weight widths the quantizer writes: int16 for the task input layers, int8 elsewhere.
pub const INPUT_LAYER_WEIGHTS: WeightWidth = WeightWidth::Int16;

/// Byte length of a layer record with `inputs` inputs, `outputs` outputs and `width` weights.
pub const fn layer_record_len(inputs: usize, outputs: usize, width: WeightWidth) -> usize {
    LAYER_HEADER_LEN + outputs * inputs * width.bytes() + 17 * outputs
}

/// Byte length of a whole model file with the given shape, as the quantizer writes it (task
/// input layers [`INPUT_LAYER_WEIGHTS`], the others int8).
pub const fn file_len(features: usize, hidden: usize, shared_layers: usize) -> usize {
    HEADER_LEN
        + 6 * features
        + Task::COUNT * layer_record_len(features, hidden, INPUT_LAYER_WEIGHTS)
        + shared_layers * layer_record_len(hidden, hidden, WeightWidth::Int8)
        + Task::COUNT * layer_record_len(hidden, ACTIONS, WeightWidth::Int8)
        + CRC_LEN
}

/// The fixed-point requantization every layer uses: `(acc * multiplier + 2^(shift-1)) >> shift`
/// in 64-bit arithmetic, saturated to `i32`.
///
/// Single rounding, half towards +infinity. For the values [`decode`] admits
/// (`0 <= multiplier < 2^31`, `shift` in [`SHIFT_RANGE`], `|acc| < 2^31`) nothing can overflow; for
/// anything else the shift is clamped into range, so the function never panics.
///
/// ```
/// use skyherd_model::format::requantize;
/// // multiplier 2^30 with shift 31 is x 0.5: 3 * 0.5 = 1.5 rounds up to 2, -3 * 0.5 to -1.
/// assert_eq!(requantize(3, 1 << 30, 31), 2);
/// assert_eq!(requantize(-3, 1 << 30, 31), -1);
/// ```
#[inline]
pub fn requantize(acc: i32, multiplier: i32, shift: u8) -> i32 {
    let shift = shift.clamp(*SHIFT_RANGE.start(), *SHIFT_RANGE.end()) as u32;
    let product = (acc as i64).saturating_mul(multiplier as i64);
    let rounded = product.saturating_add(1i64 << (shift - 1)) >> shift;
    rounded.clamp(i32::MIN as i64, i32::MAX as i64) as i32
}

/// [`requantize`] for the int64 accumulator of a layer with int16 weights, in int128: the same
/// single rounding, saturated to `i32`.
///
/// ```
/// use skyherd_model::format::{requantize, requantize_wide};
/// assert_eq!(requantize_wide(3, 1 << 30, 31), requantize(3, 1 << 30, 31));
/// // 2^40 * 0.5 does not fit an i32: it saturates.
/// assert_eq!(requantize_wide(1 << 40, 1 << 30, 31), i32::MAX);
/// ```
#[inline]
pub fn requantize_wide(acc: i64, multiplier: i32, shift: u8) -> i32 {
    let shift = shift.clamp(*SHIFT_RANGE.start(), *SHIFT_RANGE.end()) as u32;
    let product = (acc as i128).saturating_mul(multiplier as i128);
    let rounded = product.saturating_add(1i128 << (shift - 1)) >> shift;
    rounded.clamp(i32::MIN as i128, i32::MAX as i128) as i32
}

/// Why a byte string is not a valid model file.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FormatError {
    /// Fewer bytes than the structure needs.
    Truncated {
        /// Bytes needed.
        needed: usize,
        /// Bytes available.
        available: usize,
    },
    /// The first four bytes are not [`MAGIC`].
    BadMagic,
    /// A format version this build does not read.
    UnsupportedVersion(u16),
    /// The header length field is not [`HEADER_LEN`].
    BadHeaderLength(u16),
    /// The length recorded in the header differs from the byte count given.
    LengthMismatch {
        /// Length in the header.
        declared: u32,
        /// Bytes given.
        actual: usize,
    },
    /// The CRC trailer does not match the content.
    CrcMismatch {
        /// CRC stored in the file.
        stored: u32,
        /// CRC of the content.
        computed: u32,
    },
    /// A reserved field is not zero (offset of the field in the file).
    ReservedNotZero(usize),
    /// A count or width is zero or above what the inference core can hold.
    Capacity {
        /// Which field.
        field: &'static str,
        /// Its value.
        value: usize,
        /// The largest value accepted.
        max: usize,
    },
    /// The task count is not the number of [`Task`]s.
    TaskCount(u8),
    /// The action count is not [`ACTIONS`].
    ActionCount(u8),
    /// The max speed is not a positive finite number.
    MaxSpeed,
    /// A quantization scale is not a positive finite number (layer index, or `None` for the input).
    Scale {
        /// Layer index in file order, `None` for the input quantization.
        layer: Option<u8>,
        /// Channel (feature or output) index.
        channel: u16,
    },
    /// A layer's dimensions do not fit the architecture.
    LayerShape {
        /// Layer index in file order.
        layer: u8,
        /// Expected inputs and outputs.
        expected: (u16, u16),
        /// Found inputs and outputs.
        found: (u16, u16),
    },
    /// A layer's activation code is unknown or wrong for its position.
    Activation {
        /// Layer index in file order.
        layer: u8,
        /// The code found.
        code: u8,
    },
    /// A layer's bytes-per-weight code is neither 1 (int8) nor 2 (int16).
    WeightWidth {
        /// Layer index in file order.
        layer: u8,
        /// The code found.
        code: u8,
    },
    /// A bias, multiplier or shift is out of the range the arithmetic is proven for.
    Requantization {
        /// Layer index in file order.
        layer: u8,
        /// Output channel.
        channel: u16,
    },
    /// Bytes are left between the last layer and the CRC trailer.
    TrailingBytes(usize),
    /// The model was made for another observation encoder.
    EncoderMismatch {
        /// Encoder version and feature count in the model.
        model: (u16, u16),
        /// Encoder version and feature count of this build.
        expected: (u16, u16),
    },
}

impl fmt::Display for FormatError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            FormatError::Truncated { needed, available } => {
                write!(
                    f,
                    "model file truncated: need {needed} bytes, have {available}"
                )
            }
            FormatError::BadMagic => f.write_str("not a skyherd model file (bad magic)"),
            FormatError::UnsupportedVersion(v) => write!(
                f,
                "model format version {v} is not supported (this build reads {FORMAT_VERSION})"
            ),
            FormatError::BadHeaderLength(l) => {
                write!(f, "header length {l}, expected {HEADER_LEN}")
            }
            FormatError::LengthMismatch { declared, actual } => {
                write!(f, "header says {declared} bytes, file has {actual}")
            }
            FormatError::CrcMismatch { stored, computed } => write!(
                f,
                "CRC mismatch: stored {stored:#010x}, computed {computed:#010x} (file corrupted)"
            ),
            FormatError::ReservedNotZero(offset) => {
                write!(f, "reserved field at byte {offset} is not zero")
            }
            FormatError::Capacity { field, value, max } => {
                write!(f, "{field} = {value} is outside 1..={max}")
            }
            FormatError::TaskCount(n) => {
                write!(f, "model has {n} tasks, this build knows {}", Task::COUNT)
            }
            FormatError::ActionCount(n) => write!(f, "model has {n} actions, expected {ACTIONS}"),
            FormatError::MaxSpeed => f.write_str("max speed is not a positive finite number"),
            FormatError::Scale {
                layer: None,
                channel,
            } => {
                write!(
                    f,
                    "input scale of feature {channel} is not positive and finite"
                )
            }
            FormatError::Scale {
                layer: Some(l),
                channel,
            } => write!(
                f,
                "layer {l}: scale of channel {channel} is not positive and finite"
            ),
            FormatError::LayerShape {
                layer,
                expected,
                found,
            } => write!(
                f,
                "layer {layer} is {}x{}, expected {}x{}",
                found.0, found.1, expected.0, expected.1
            ),
            FormatError::Activation { layer, code } => {
                write!(f, "layer {layer}: activation code {code} not valid here")
            }
            FormatError::WeightWidth { layer, code } => write!(
                f,
                "layer {layer}: {code} bytes per weight (must be 1 for int8 or 2 for int16)"
            ),
            FormatError::Requantization { layer, channel } => write!(
                f,
                "layer {layer}, channel {channel}: bias, multiplier or shift out of range"
            ),
            FormatError::TrailingBytes(n) => {
                write!(f, "{n} unexpected bytes before the CRC trailer")
            }
            FormatError::EncoderMismatch { model, expected } => write!(
                f,
                "model was trained for observation encoder v{} ({} features), this build has v{} ({} features)",
                model.0, model.1, expected.0, expected.1
            ),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for FormatError {}

/// A validated model file, borrowing its arrays from the bytes given to [`decode`].
#[derive(Clone, Copy, Debug)]
pub struct ModelView<'a> {
    /// Observation-encoder version the model was trained with.
    pub encoder_version: u16,
    /// Input feature count.
    pub features: usize,
    /// Hidden width.
    pub hidden: usize,
    /// Number of shared hidden layers.
    pub shared_layers: usize,
    /// Speed in m/s that a normalised action of 1 stands for.
    pub max_speed: f32,
    input_scales: &'a [u8],
    input_zero_points: &'a [u8],
    layers: [LayerView<'a>; MAX_LAYERS],
    layer_count: usize,
    crc: u32,
    len: usize,
}

/// One dense layer of a [`ModelView`]; all arrays are little-endian bytes of the file.
#[derive(Clone, Copy, Debug, Default)]
pub struct LayerView<'a> {
    /// Input width.
    pub inputs: usize,
    /// Output width.
    pub outputs: usize,
    /// Whether ReLU is fused into the output clamp.
    pub relu: bool,
    /// How the weights are stored.
    pub weight_width: WeightWidth,
    /// Zero point of the int16 output.
    pub output_zero_point: i16,
    /// Scale of the int16 output.
    pub output_scale: f32,
    /// `outputs * inputs` weights (int8, or little-endian int16), row-major `[out][in]`, as raw
    /// bytes.
    pub weights: &'a [u8],
    weight_scales: &'a [u8],
    bias: &'a [u8],
    multiplier: &'a [u8],
    shift: &'a [u8],
}

#[inline]
fn word<const N: usize>(bytes: &[u8], index: usize) -> [u8; N] {
    let start = index.saturating_mul(N);
    bytes
        .get(start..start.saturating_add(N))
        .and_then(|b| b.try_into().ok())
        .unwrap_or([0; N])
}

impl<'a> LayerView<'a> {
    /// Per-output-channel weight scale of channel `o` (0 when out of range).
    pub fn weight_scale(&self, o: usize) -> f32 {
        f32::from_le_bytes(word(self.weight_scales, o))
    }
    /// Bias of channel `o`, input zero point folded in (0 when out of range).
    #[inline]
    pub fn bias(&self, o: usize) -> i64 {
        i64::from_le_bytes(word(self.bias, o))
    }
    /// Requantization multiplier of channel `o` (0 when out of range).
    #[inline]
    pub fn multiplier(&self, o: usize) -> i32 {
        i32::from_le_bytes(word(self.multiplier, o))
    }
    /// Requantization right shift of channel `o` (1 when out of range).
    #[inline]
    pub fn shift(&self, o: usize) -> u8 {
        self.shift.get(o).copied().unwrap_or(1)
    }
    /// Weight row of channel `o` as raw bytes (each an `i8`, or a little-endian `i16` pair);
    /// empty when out of range.
    #[inline]
    pub fn row(&self, o: usize) -> &'a [u8] {
        let len = self.inputs.saturating_mul(self.weight_width.bytes());
        let start = o.saturating_mul(len);
        self.weights
            .get(start..start.saturating_add(len))
            .unwrap_or(&[])
    }
    /// Lowest int16 output value: the zero point for ReLU layers, else -32768.
    #[inline]
    pub fn output_floor(&self) -> i16 {
        if self.relu {
            self.output_zero_point
        } else {
            i16::MIN
        }
    }
}

impl<'a> ModelView<'a> {
    /// Input quantization scale of feature `j` (0 when out of range).
    #[inline]
    pub fn input_scale(&self, j: usize) -> f32 {
        f32::from_le_bytes(word(self.input_scales, j))
    }
    /// Input quantization zero point of feature `j` (0 when out of range).
    #[inline]
    pub fn input_zero_point(&self, j: usize) -> i16 {
        i16::from_le_bytes(word(self.input_zero_points, j))
    }
    /// Every layer in file order: task inputs, shared, task outputs.
    pub fn layers(&self) -> &[LayerView<'a>] {
        self.layers.get(..self.layer_count).unwrap_or(&[])
    }
    /// The task's input layer (`features -> hidden`, ReLU).
    pub fn task_input(&self, task: Task) -> &LayerView<'a> {
        &self.layers[task.index()]
    }
    /// The shared hidden layers (`hidden -> hidden`, ReLU), in order.
    pub fn shared(&self) -> &[LayerView<'a>] {
        self.layers
            .get(Task::COUNT..Task::COUNT + self.shared_layers)
            .unwrap_or(&[])
    }
    /// The task's output layer (`hidden -> 3`, no activation; tanh follows dequantization).
    pub fn task_output(&self, task: Task) -> &LayerView<'a> {
        let index = (Task::COUNT + self.shared_layers + task.index()).min(MAX_LAYERS - 1);
        &self.layers[index]
    }
    /// The CRC-32 of the file (identifies the model in logs).
    pub fn crc(&self) -> u32 {
        self.crc
    }
    /// Length of the file in bytes.
    pub fn file_len(&self) -> usize {
        self.len
    }
    /// Number of weights (int8 and int16 together).
    pub fn weight_count(&self) -> usize {
        self.layers().iter().map(|l| l.inputs * l.outputs).sum()
    }
    /// Number of int16 weights (two bytes each in flash; the rest are int8).
    pub fn wide_weight_count(&self) -> usize {
        self.layers()
            .iter()
            .filter(|l| l.weight_width == WeightWidth::Int16)
            .map(|l| l.inputs * l.outputs)
            .sum()
    }
    /// Fails with [`FormatError::EncoderMismatch`] unless the model was made for this encoder.
    pub fn check_encoder(&self, version: u16, features: usize) -> Result<(), FormatError> {
        if self.encoder_version == version && self.features == features {
            Ok(())
        } else {
            Err(FormatError::EncoderMismatch {
                model: (self.encoder_version, self.features as u16),
                expected: (version, features.min(u16::MAX as usize) as u16),
            })
        }
    }
}

struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], FormatError> {
        let end = self.pos.checked_add(n).ok_or(FormatError::Truncated {
            needed: usize::MAX,
            available: self.bytes.len(),
        })?;
        let slice = self
            .bytes
            .get(self.pos..end)
            .ok_or(FormatError::Truncated {
                needed: end,
                available: self.bytes.len(),
            })?;
        self.pos = end;
        Ok(slice)
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], FormatError> {
        let s = self.take(N)?;
        Ok(word(s, 0))
    }
    fn u8(&mut self) -> Result<u8, FormatError> {
        Ok(self.array::<1>()?[0])
    }
    fn u16(&mut self) -> Result<u16, FormatError> {
        Ok(u16::from_le_bytes(self.array()?))
    }
    fn u32(&mut self) -> Result<u32, FormatError> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    fn f32(&mut self) -> Result<f32, FormatError> {
        Ok(f32::from_le_bytes(self.array()?))
    }
    fn zero<const N: usize>(&mut self) -> Result<(), FormatError> {
        let at = self.pos;
        if self.array::<N>()? == [0; N] {
            Ok(())
        } else {
            Err(FormatError::ReservedNotZero(at))
        }
    }
}

fn positive_finite(x: f32) -> bool {
    x.is_finite() && x > 0.0
}

fn capacity(field: &'static str, value: usize, max: usize) -> Result<usize, FormatError> {
    if (1..=max).contains(&value) {
        Ok(value)
    } else {
        Err(FormatError::Capacity { field, value, max })
    }
}

/// Validates a model file and returns a view borrowing from it.
///
/// Checks, in order: magic, format version, header length, total length, CRC-32, reserved
/// fields, counts and widths against the core's capacities ([`MAX_FEATURES`], [`MAX_WIDTH`],
/// [`MAX_SHARED_LAYERS`], [`Task::COUNT`], [`ACTIONS`]), every layer's shape and activation
/// against the architecture, every scale (positive, finite), every bias, multiplier and shift
/// against the ranges the fixed-point arithmetic is proven for, and that no bytes are left
/// over. The encoder version is recorded, not judged: the onboard actor checks it against its
/// encoder with [`ModelView::check_encoder`].
///
/// Never panics, for any input.
pub fn decode(bytes: &[u8]) -> Result<ModelView<'_>, FormatError> {
    let mut r = Reader { bytes, pos: 0 };
    if r.array::<4>()? != MAGIC {
        return Err(FormatError::BadMagic);
    }
    let version = r.u16()?;
    if version != FORMAT_VERSION {
        return Err(FormatError::UnsupportedVersion(version));
    }
    let header_len = r.u16()?;
    if header_len as usize != HEADER_LEN {
        return Err(FormatError::BadHeaderLength(header_len));
    }
    let declared = r.u32()?;
    if declared as usize != bytes.len() {
        return Err(FormatError::LengthMismatch {
            declared,
            actual: bytes.len(),
        });
    }
    if bytes.len() < HEADER_LEN + CRC_LEN {
        return Err(FormatError::Truncated {
            needed: HEADER_LEN + CRC_LEN,
            available: bytes.len(),
        });
    }
    let (content, trailer) = bytes.split_at(bytes.len() - CRC_LEN);
    let stored = u32::from_le_bytes(word(trailer, 0));
    let computed = CRC32.checksum(content);
    if stored != computed {
        return Err(FormatError::CrcMismatch { stored, computed });
    }
    // From here on read only the content, so the trailer cannot be mistaken for a layer.
    let mut r = Reader {
        bytes: content,
        pos: r.pos,
    };
    let encoder_version = r.u16()?;
    let features = capacity("feature count", r.u16()? as usize, MAX_FEATURES)?;
    let hidden = capacity("hidden width", r.u16()? as usize, MAX_WIDTH)?;
    let task_count = r.u8()?;
    if task_count as usize != Task::COUNT {
        return Err(FormatError::TaskCount(task_count));
    }
    let shared_layers = r.u8()? as usize;
    if shared_layers > MAX_SHARED_LAYERS {
        return Err(FormatError::Capacity {
            field: "shared layer count",
            value: shared_layers,
            max: MAX_SHARED_LAYERS,
        });
    }
    let actions = r.u8()?;
    if actions as usize != ACTIONS {
        return Err(FormatError::ActionCount(actions));
    }
    r.zero::<1>()?;
    r.zero::<2>()?;
    let max_speed = r.f32()?;
    if !positive_finite(max_speed) {
        return Err(FormatError::MaxSpeed);
    }
    r.zero::<4>()?;

    let input_scales = r.take(4 * features)?;
    for j in 0..features {
        if !positive_finite(f32::from_le_bytes(word(input_scales, j))) {
            return Err(FormatError::Scale {
                layer: None,
                channel: j as u16,
            });
        }
    }
    let input_zero_points = r.take(2 * features)?;

    let mut layers = [LayerView::default(); MAX_LAYERS];
    let layer_count = 2 * Task::COUNT + shared_layers;
    for (index, slot) in layers.iter_mut().take(layer_count).enumerate() {
        let (inputs, outputs, relu) = if index < Task::COUNT {
            (features, hidden, true)
        } else if index < Task::COUNT + shared_layers {
            (hidden, hidden, true)
        } else {
            (hidden, ACTIONS, false)
        };
        *slot = read_layer(&mut r, index as u8, inputs, outputs, relu)?;
    }
    if r.pos != content.len() {
        return Err(FormatError::TrailingBytes(content.len() - r.pos));
    }
    Ok(ModelView {
        encoder_version,
        features,
        hidden,
        shared_layers,
        max_speed,
        input_scales,
        input_zero_points,
        layers,
        layer_count,
        crc: computed,
        len: bytes.len(),
    })
}

fn read_layer<'a>(
    r: &mut Reader<'a>,
    layer: u8,
    inputs: usize,
    outputs: usize,
    relu: bool,
) -> Result<LayerView<'a>, FormatError> {
    let found = (r.u16()?, r.u16()?);
    if (found.0 as usize, found.1 as usize) != (inputs, outputs) {
        return Err(FormatError::LayerShape {
            layer,
            expected: (inputs as u16, outputs as u16),
            found,
        });
    }
    let code = r.u8()?;
    let expected_code = if relu {
        ACTIVATION_RELU
    } else {
        ACTIVATION_NONE
    };
    if code != expected_code {
        return Err(FormatError::Activation { layer, code });
    }
    let width_code = r.u8()?;
    let weight_width = WeightWidth::from_code(width_code).ok_or(FormatError::WeightWidth {
        layer,
        code: width_code,
    })?;
    let output_zero_point = r.u16()? as i16;
    let output_scale = r.f32()?;
    if !positive_finite(output_scale) {
        return Err(FormatError::Scale {
            layer: Some(layer),
            channel: 0,
        });
    }
    let view = LayerView {
        inputs,
        outputs,
        relu,
        weight_width,
        output_zero_point,
        output_scale,
        weights: r.take(inputs * outputs * weight_width.bytes())?,
        weight_scales: r.take(4 * outputs)?,
        bias: r.take(8 * outputs)?,
        multiplier: r.take(4 * outputs)?,
        shift: r.take(outputs)?,
    };
    for o in 0..outputs {
        if !positive_finite(view.weight_scale(o)) {
            return Err(FormatError::Scale {
                layer: Some(layer),
                channel: o as u16,
            });
        }
        let limit = weight_width.bias_limit();
        let bias_ok = (-limit..=limit).contains(&view.bias(o));
        if !bias_ok || view.multiplier(o) < 0 || !SHIFT_RANGE.contains(&view.shift(o)) {
            return Err(FormatError::Requantization {
                layer,
                channel: o as u16,
            });
        }
    }
    Ok(view)
}
