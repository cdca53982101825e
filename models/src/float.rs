//! The f32 reference actor (std): the network the trainer optimises and the quantizer reads.

use crate::Task;
use crate::format::ACTIONS;

/// A fully connected layer, `y = W x + b`, weights row-major `[out][in]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Dense {
    /// Input width.
    pub inputs: usize,
    /// Output width.
    pub outputs: usize,
    /// `outputs * inputs` weights, row-major `[out][in]`.
    pub weights: Vec<f32>,
    /// `outputs` biases.
    pub bias: Vec<f32>,
}

impl Dense {
    /// A layer with uniform random weights in `±sqrt(6 / inputs)` (He-uniform) and biases in
    /// `±0.1`, drawn from `rng`. Untrained: for tests, benchmarks and as a training start.
    pub fn random(inputs: usize, outputs: usize, rng: &mut SplitMix64) -> Dense {
        let limit = (6.0 / inputs.max(1) as f64).sqrt();
        Dense {
            inputs,
            outputs,
            weights: (0..inputs * outputs)
                .map(|_| rng.uniform(-limit, limit) as f32)
                .collect(),
            bias: (0..outputs)
                .map(|_| rng.uniform(-0.1, 0.1) as f32)
                .collect(),
        }
    }

    /// Whether the weight and bias lengths match the declared widths.
    pub fn is_consistent(&self) -> bool {
        self.weights.len() == self.inputs * self.outputs && self.bias.len() == self.outputs
    }

    /// `out = W x + b`. Reads `min(x.len(), inputs)` inputs and writes `min(out.len(), outputs)`.
    pub fn forward(&self, x: &[f32], out: &mut [f32]) {
        for ((o, row), b) in out
            .iter_mut()
            .zip(self.weights.chunks_exact(self.inputs.max(1)))
            .zip(&self.bias)
        {
            *o = b + row.iter().zip(x).map(|(w, v)| w * v).sum::<f32>();
        }
    }
}

/// Widths of a multi-task actor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ActorShape {
    /// Input feature count `F`.
    pub features: usize,
    /// Hidden width `H`.
    pub hidden: usize,
    /// Number of shared hidden layers `S`.
    pub shared_layers: usize,
}

/// The multi-task actor of the paper's Fig. 2 in f32: per task an input `Dense(F -> H)` + ReLU,
/// `S` shared `Dense(H -> H)` + ReLU, per task an output `Dense(H -> 3)` then `tanh`.
///
/// Vectors are indexed by [`Task::index`].
#[derive(Clone, Debug, PartialEq)]
pub struct FloatActor {
    /// Per task, the input layer `F -> H`.
    pub task_inputs: Vec<Dense>,
    /// The shared hidden layers `H -> H`.
    pub shared: Vec<Dense>,
    /// Per task, the output layer `H -> 3`.
    pub task_outputs: Vec<Dense>,
}

/// Activations of every layer for one input, as the quantizer's calibration needs them.
#[derive(Clone, Debug, Default)]
pub struct Trace {
    /// Output of the task input layer, after ReLU.
    pub input_layer: Vec<f32>,
    /// Output of each shared layer, after ReLU.
    pub shared: Vec<Vec<f32>>,
    /// Output of the task output layer, before tanh.
    pub pre_tanh: [f32; ACTIONS],
}

impl FloatActor {
    /// An untrained actor with seeded random weights (see [`Dense::random`]).
    ///
    /// Nothing about it is trained; tests and benchmarks use it until a trained model ships.
    pub fn random(shape: ActorShape, seed: u64) -> FloatActor {
        let mut rng = SplitMix64::new(seed);
        let ActorShape {
            features,
            hidden,
            shared_layers,
        } = shape;
        FloatActor {
            task_inputs: Task::ALL
                .iter()
                .map(|_| Dense::random(features, hidden, &mut rng))
                .collect(),
            shared: (0..shared_layers)
                .map(|_| Dense::random(hidden, hidden, &mut rng))
                .collect(),
            task_outputs: Task::ALL
                .iter()
                .map(|_| Dense::random(hidden, ACTIONS, &mut rng))
                .collect(),
        }
    }

    /// The actor's widths, or `None` when the layers do not chain into the Fig. 2 architecture.
    pub fn shape(&self) -> Option<ActorShape> {
        let first = self.task_inputs.first()?;
        let (features, hidden) = (first.inputs, first.outputs);
        let ok = self.task_inputs.len() == Task::COUNT
            && self.task_outputs.len() == Task::COUNT
            && self
                .task_inputs
                .iter()
                .all(|d| d.is_consistent() && (d.inputs, d.outputs) == (features, hidden))
            && self
                .shared
                .iter()
                .all(|d| d.is_consistent() && (d.inputs, d.outputs) == (hidden, hidden))
            && self
                .task_outputs
                .iter()
                .all(|d| d.is_consistent() && (d.inputs, d.outputs) == (hidden, ACTIONS));
        ok.then_some(ActorShape {
            features,
            hidden,
            shared_layers: self.shared.len(),
        })
    }

    /// Every layer's activations for `features` (missing features read as 0).
    pub fn trace(&self, task: Task, features: &[f32]) -> Trace {
        let relu = |v: &mut Vec<f32>| v.iter_mut().for_each(|x| *x = x.max(0.0));
        let Some(input) = self.task_inputs.get(task.index()) else {
            return Trace::default();
        };
        let mut x = vec![0.0; input.outputs];
        input.forward(features, &mut x);
        relu(&mut x);
        let mut trace = Trace {
            input_layer: x.clone(),
            ..Trace::default()
        };
        for layer in &self.shared {
            let mut y = vec![0.0; layer.outputs];
            layer.forward(&x, &mut y);
            relu(&mut y);
            trace.shared.push(y.clone());
            x = y;
        }
        if let Some(output) = self.task_outputs.get(task.index()) {
            output.forward(&x, &mut trace.pre_tanh);
        }
        trace
    }

    /// The normalised action in `[-1, 1]^3` for `features`.
    pub fn forward(&self, task: Task, features: &[f32]) -> [f32; ACTIONS] {
        self.trace(task, features).pre_tanh.map(f32::tanh)
    }
}

/// SplitMix64: a tiny seeded generator, so seeded weights and test inputs are the same on every
/// platform and with every version of every dependency (golden files depend on it).
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator with the given seed.
    pub fn new(seed: u64) -> SplitMix64 {
        SplitMix64(seed)
    }
    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        let unit = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        lo + (hi - lo) * unit
    }
}
