//! The skyherd model file format: a quantized multi-task (MTDDPG) actor.
//!
//! The actor is the paper's Fig. 2 network: per task an input `Dense(F -> H)` + ReLU, `S` shared
//! `Dense(H -> H)` + ReLU, per task an output `Dense(H -> 3)`, then `tanh`. A model file holds it
//! quantized: int8 weights, int16 in the task input layers, int16 activations (layout and
//! arithmetic in [`mod@format`]); [`decode`] validates a file and
//! returns a zero-copy [`ModelView`]. Inference lives in `skyherd_onboard::actor`.
//!
//! `#![no_std]` without alloc. Features (additive):
//! * `serde`: `Serialize`/`Deserialize` on [`Task`].
//! * `std` (implies `serde`): the f32 reference actor `FloatActor`, the quantizer
//!   `quantize`, the model encoder `QuantizedModel::to_bytes`, and the `skyherd-model` CLI
//!   (`inspect`, `validate`).
//!
//! ```
//! # #[cfg(feature = "std")] {
//! use skyherd_model::{decode, quantize, ActorShape, FloatActor, ModelMeta, Task};
//! // Untrained, seeded weights: a stand-in until the trainer ships a model.
//! let actor = FloatActor::random(ActorShape { features: 6, hidden: 16, shared_layers: 2 }, 1);
//! let observations = [[0.0, 0.5, -1.0, 0.25, 1.0, -0.5]; 4];
//! let calibration = observations.iter().map(|o| (Task::Collecting, &o[..]));
//! let bytes = quantize(&actor, ModelMeta { encoder_version: 1, max_speed: 5.0 }, calibration).unwrap();
//! let model = decode(&bytes).unwrap();
//! assert_eq!((model.features, model.hidden, model.shared_layers), (6, 16, 2));
//! assert!(decode(&bytes[..bytes.len() - 1]).is_err());
//! # }
//! ```
#![cfg_attr(not(feature = "std"), no_std)]

#[cfg(feature = "std")]
pub mod file;
#[cfg(feature = "std")]
pub mod float;
pub mod format;
#[cfg(feature = "std")]
pub mod quantize;

#[cfg(feature = "std")]
pub use file::{MAX_MODEL_FILE_BYTES, ReadModelError, read_model_file};
#[cfg(feature = "std")]
pub use float::{ActorShape, Dense, FloatActor, SplitMix64};
pub use format::{FormatError, LayerView, ModelView, decode};
#[cfg(feature = "std")]
pub use quantize::{
    ModelMeta, QuantizeError, QuantizedLayer, QuantizedModel, quantize, quantize_model,
};

/// The two shepherding tasks of the paper; the index selects the task-specific layers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[repr(u8)]
pub enum Task {
    /// Drive a flock from a start circle into the goal circle.
    Driving = 0,
    /// Gather scattered targets into the goal circle.
    Collecting = 1,
}

impl Task {
    /// Number of tasks a model serves.
    pub const COUNT: usize = 2;
    /// Both tasks, in index order.
    pub const ALL: [Task; 2] = [Task::Driving, Task::Collecting];

    /// The task's index into per-task layers.
    pub const fn index(self) -> usize {
        self as usize
    }

    /// The task with the given index, if any.
    pub const fn from_index(index: usize) -> Option<Task> {
        match index {
            0 => Some(Task::Driving),
            1 => Some(Task::Collecting),
            _ => None,
        }
    }
}
