//! The MTDDPG network shape of the paper's Fig. 2, used for both actor and critic: a
//! task-specific input layer, shared hidden layers (all ReLU), and a task-specific output layer.
//!
//! * Actor: `FEATURES -> H` (per task) `-> H ... -> H` (shared) `-> 3` (per task), then `tanh`:
//!   a normalised velocity in the encoder's local frame.
//! * Critic: `FEATURES + 3 -> H -> ... -> 1`, no output activation: `Q(s, a)`.
//!
//! ```
//! use skyherd_trainer::network::{MlpShape, MultiTaskMlp};
//! use rand::SeedableRng;
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
//! let actor = MultiTaskMlp::new(MlpShape::actor(46, 64, 1), &mut rng);
//! let action = actor.predict(0, &[0.1; 46]);
//! assert_eq!(action.len(), 3);
//! assert!(action.iter().all(|a| a.abs() <= 1.0));
//! ```

use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::nn::{Activation, Dense};

/// Final-layer init bound: small outputs at the start, as in cleanrl's DDPG (and the original
/// paper), so the untrained actor neither saturates tanh nor the critic explodes.
pub const OUTPUT_INIT_BOUND: f32 = 3e-3;

/// The shape of a [`MultiTaskMlp`]: how many tasks, the layer widths and the output squashing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MlpShape {
    /// Tasks (each with its own input and output layer): 2 for driving and collecting.
    pub tasks: usize,
    /// Input width (the encoder's feature count for an actor).
    pub inputs: usize,
    /// Width of every hidden layer.
    pub hidden: usize,
    /// Hidden layers shared between the tasks.
    pub shared_layers: usize,
    /// Output width (3 for an actor's velocity, 1 for a critic's value).
    pub outputs: usize,
    /// What the output layer applies.
    pub output_activation: Activation,
}

impl MlpShape {
    /// An actor's shape: two tasks (driving, collecting), `inputs` features in, a velocity
    /// (3 outputs, tanh) out.
    pub fn actor(inputs: usize, hidden: usize, shared_layers: usize) -> Self {
        Self {
            tasks: 2,
            inputs,
            hidden,
            shared_layers,
            outputs: 3,
            output_activation: Activation::Tanh,
        }
    }
}

/// A multi-task MLP: per-task input layer -> shared hidden layers -> per-task output layer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MultiTaskMlp {
    /// One `inputs -> hidden` layer per task (followed by ReLU).
    pub task_inputs: Vec<Dense>,
    /// Shared `hidden -> hidden` layers (each followed by ReLU).
    pub shared: Vec<Dense>,
    /// One `hidden -> outputs` layer per task.
    pub task_outputs: Vec<Dense>,
    /// What follows the output layer.
    pub output_activation: Activation,
}

/// The activations of one forward pass, kept for the backward pass.
#[derive(Clone, Debug, Default)]
pub struct Tape {
    /// Which task's layers ran.
    pub task: usize,
    /// Rows in the batch.
    pub batch: usize,
    /// `activations[0]` is the input, `activations[i]` the output of layer `i` after its
    /// activation; the last is the network's output.
    pub activations: Vec<Vec<f32>>,
}

impl Tape {
    /// The network's output for the batch, row-major `[batch][outputs]`.
    pub fn output(&self) -> &[f32] {
        self.activations.last().map(Vec::as_slice).unwrap_or(&[])
    }
}

impl MultiTaskMlp {
    /// A freshly initialised network for `tasks` tasks.
    pub fn new<R: Rng>(shape: MlpShape, rng: &mut R) -> MultiTaskMlp {
        let MlpShape {
            tasks,
            inputs,
            hidden,
            shared_layers,
            outputs,
            output_activation,
        } = shape;
        MultiTaskMlp {
            task_inputs: (0..tasks)
                .map(|_| Dense::new_uniform(inputs, hidden, rng))
                .collect(),
            shared: (0..shared_layers)
                .map(|_| Dense::new_uniform(hidden, hidden, rng))
                .collect(),
            task_outputs: (0..tasks)
                .map(|_| Dense::new_uniform_bound(hidden, outputs, OUTPUT_INIT_BOUND, rng))
                .collect(),
            output_activation,
        }
    }

    /// Number of tasks.
    pub fn tasks(&self) -> usize {
        self.task_inputs.len()
    }

    /// Input width.
    pub fn inputs(&self) -> usize {
        self.task_inputs.first().map_or(0, |l| l.inputs)
    }

    /// Output width.
    pub fn outputs(&self) -> usize {
        self.task_outputs.first().map_or(0, |l| l.outputs)
    }

    /// Hidden width.
    pub fn hidden(&self) -> usize {
        self.task_inputs.first().map_or(0, |l| l.outputs)
    }

    /// The layers one task's input runs through, in order.
    fn path(&self, task: usize) -> impl Iterator<Item = &Dense> {
        std::iter::once(&self.task_inputs[task])
            .chain(self.shared.iter())
            .chain(std::iter::once(&self.task_outputs[task]))
    }

    /// Every layer in a fixed order (task inputs, shared, task outputs): what optimisers and
    /// soft updates walk over.
    pub fn layers(&self) -> impl Iterator<Item = &Dense> {
        self.task_inputs
            .iter()
            .chain(self.shared.iter())
            .chain(self.task_outputs.iter())
    }

    /// Every layer, mutably, in the order of [`layers`](Self::layers).
    pub fn layers_mut(&mut self) -> impl Iterator<Item = &mut Dense> {
        self.task_inputs
            .iter_mut()
            .chain(self.shared.iter_mut())
            .chain(self.task_outputs.iter_mut())
    }

    /// The same network reading `inputs` inputs, the new ones appended with zero weights: its
    /// outputs do not change, and training can then learn to use them. `None` if `inputs` is
    /// fewer than it reads now.
    pub fn widen_inputs(&self, inputs: usize) -> Option<MultiTaskMlp> {
        let old = self.inputs();
        if inputs < old {
            return None;
        }
        let mut wide = self.clone();
        for layer in &mut wide.task_inputs {
            let mut weights = vec![0.0; inputs * layer.outputs];
            for (row, old_row) in weights
                .chunks_exact_mut(inputs)
                .zip(layer.weights.chunks_exact(old))
            {
                row[..old].copy_from_slice(old_row);
            }
            layer.weights = weights;
            layer.inputs = inputs;
        }
        Some(wide)
    }

    /// Draws `task`'s own input and output layers afresh (as [`new`](Self::new) does), leaving
    /// the shared layers and the other tasks' layers as they are. Returns those two layers'
    /// indices in [`layers`](Self::layers) order, for the optimiser's moments. Out-of-range
    /// `task`: nothing changes and the result is empty.
    pub fn reinit_task<R: Rng>(&mut self, task: usize, rng: &mut R) -> Vec<usize> {
        if task >= self.tasks() {
            return Vec::new();
        }
        let (inputs, hidden, outputs) = (self.inputs(), self.hidden(), self.outputs());
        self.task_inputs[task] = Dense::new_uniform(inputs, hidden, rng);
        self.task_outputs[task] = Dense::new_uniform_bound(hidden, outputs, OUTPUT_INIT_BOUND, rng);
        vec![task, self.tasks() + self.shared.len() + task]
    }

    /// Copies `task`'s own input and output layers from `source` (same shape): a target network
    /// following a [`reinit_task`](Self::reinit_task) of its online network.
    pub fn copy_task_from(&mut self, source: &MultiTaskMlp, task: usize) {
        if task < self.tasks() && task < source.tasks() {
            self.task_inputs[task] = source.task_inputs[task].clone();
            self.task_outputs[task] = source.task_outputs[task].clone();
        }
    }

    /// The same shape with every parameter zero: a gradient accumulator.
    pub fn zeros_like(&self) -> MultiTaskMlp {
        let mut z = self.clone();
        z.layers_mut().for_each(Dense::fill_zero);
        z
    }

    /// Total parameter count.
    pub fn parameter_count(&self) -> usize {
        self.layers().map(Dense::parameter_count).sum()
    }

    /// Runs a batch of `task` inputs (row-major `[batch][inputs]`), recording into `tape`.
    pub fn forward(&self, task: usize, x: &[f32], batch: usize, tape: &mut Tape) {
        self.forward_rounding(task, x, batch, tape, &[]);
    }

    /// [`forward`](Self::forward) with every hidden layer's output (after ReLU) rounded to a
    /// multiple of `hidden_steps[i]` and clipped at 65535 steps, as the quantized actor stores it
    /// (int16 from the zero point -32768)
    /// (quantization-aware training; the backward pass treats the rounding as identity). An
    /// empty `hidden_steps` rounds nothing.
    pub fn forward_rounding(
        &self,
        task: usize,
        x: &[f32],
        batch: usize,
        tape: &mut Tape,
        hidden_steps: &[f32],
    ) {
        assert!(task < self.tasks(), "task {task} out of range");
        assert_eq!(
            x.len(),
            batch * self.inputs(),
            "input batch has the wrong size"
        );
        let depth = self.shared.len() + 2;
        tape.task = task;
        tape.batch = batch;
        tape.activations.resize_with(depth + 1, Vec::new);
        tape.activations[0].clear();
        tape.activations[0].extend_from_slice(x);
        for (i, layer) in self.path(task).enumerate() {
            let (done, rest) = tape.activations.split_at_mut(i + 1);
            let y = &mut rest[0];
            y.resize(batch * layer.outputs, 0.0);
            layer.forward(&done[i], batch, y);
            let activation = if i + 1 == depth {
                self.output_activation
            } else {
                Activation::Relu
            };
            activation.apply(y);
            if let Some(&step) = hidden_steps.get(i).filter(|&&s| i + 1 < depth && s > 0.0) {
                let top = 65535.0 * step;
                y.iter_mut()
                    .for_each(|v| *v = ((*v / step).round() * step).min(top));
            }
        }
    }

    /// Backpropagates `d_output = dL/d(output)` through the pass in `tape`. Parameter gradients
    /// are added into `grads` (shaped like `self`, see [`zeros_like`](Self::zeros_like)) when
    /// given; `dL/d(input)` is returned when `want_input_grad`.
    pub fn backward(
        &self,
        tape: &Tape,
        d_output: &[f32],
        mut grads: Option<&mut MultiTaskMlp>,
        want_input_grad: bool,
    ) -> Option<Vec<f32>> {
        let task = tape.task;
        let batch = tape.batch;
        let depth = self.shared.len() + 2;
        let mut delta = d_output.to_vec();
        self.output_activation
            .backward(&tape.activations[depth], &mut delta);
        let layers: Vec<&Dense> = self.path(task).collect();
        for i in (0..depth).rev() {
            let layer = layers[i];
            let x = &tape.activations[i];
            let grad = grads.as_deref_mut().map(|g| {
                if i == 0 {
                    &mut g.task_inputs[task]
                } else if i + 1 == depth {
                    &mut g.task_outputs[task]
                } else {
                    &mut g.shared[i - 1]
                }
            });
            let need_dx = i > 0 || want_input_grad;
            if need_dx {
                let mut dx = vec![0.0; batch * layer.inputs];
                layer.backward(x, &delta, batch, grad, Some(&mut dx));
                if i > 0 {
                    // The layer below ended in a ReLU whose outputs are `x`.
                    Activation::Relu.backward(x, &mut dx);
                }
                delta = dx;
            } else {
                layer.backward(x, &delta, batch, grad, None);
            }
        }
        want_input_grad.then_some(delta)
    }

    /// One input through `task`'s layers (no tape kept): for acting and tests.
    pub fn predict(&self, task: usize, x: &[f32]) -> Vec<f32> {
        let mut tape = Tape::default();
        self.forward(task, x, 1, &mut tape);
        tape.output().to_vec()
    }

    /// A batch of `batch` inputs through `task`'s layers (no tape kept).
    pub fn predict_batch(&self, task: usize, x: &[f32], batch: usize) -> Vec<f32> {
        let mut tape = Tape::default();
        self.forward(task, x, batch, &mut tape);
        tape.output().to_vec()
    }

    /// A direction in parameter space for parameter-space noise: a standard normal draw for
    /// every weight and bias on `task`'s path (its input layer, the shared layers, its output
    /// layer), zero on the other tasks' own layers. `None` if there is no such task.
    pub fn random_direction<R: Rng>(&self, task: usize, rng: &mut R) -> Option<MultiTaskMlp> {
        if task >= self.tasks() {
            return None;
        }
        let mut d = self.zeros_like();
        let path = std::iter::once(&mut d.task_inputs[task])
            .chain(d.shared.iter_mut())
            .chain(std::iter::once(&mut d.task_outputs[task]));
        for layer in path {
            for p in layer.weights.iter_mut().chain(layer.bias.iter_mut()) {
                *p = rng.sample(rand_distr::StandardNormal);
            }
        }
        Some(d)
    }

    /// `self + scale * direction`, parameter by parameter (`direction` of the same shape, as
    /// [`random_direction`](Self::random_direction) draws it).
    pub fn plus_scaled(&self, direction: &MultiTaskMlp, scale: f32) -> MultiTaskMlp {
        let mut out = self.clone();
        out.assign_plus_scaled(self, direction, scale);
        out
    }

    /// Sets `self` to `base + scale * direction` in place, reusing its buffers when it already
    /// has `base`'s shape (the rollout's perturbed actor, rebuilt every step without
    /// allocating).
    pub fn assign_plus_scaled(
        &mut self,
        base: &MultiTaskMlp,
        direction: &MultiTaskMlp,
        scale: f32,
    ) {
        let same_shape = self.layers().count() == base.layers().count()
            && self
                .layers()
                .zip(base.layers())
                .all(|(a, b)| a.weights.len() == b.weights.len() && a.bias.len() == b.bias.len());
        if !same_shape {
            *self = base.clone();
        }
        self.output_activation = base.output_activation;
        for ((o, b), d) in self.layers_mut().zip(base.layers()).zip(direction.layers()) {
            for ((p, x), e) in o
                .weights
                .iter_mut()
                .chain(o.bias.iter_mut())
                .zip(b.weights.iter().chain(b.bias.iter()))
                .zip(d.weights.iter().chain(d.bias.iter()))
            {
                *p = x + scale * e;
            }
        }
    }

    /// Whether `other` has this network's layers, layer for layer (what averaging needs).
    pub fn same_shape(&self, other: &MultiTaskMlp) -> bool {
        self.task_inputs.len() == other.task_inputs.len()
            && self.shared.len() == other.shared.len()
            && self.task_outputs.len() == other.task_outputs.len()
            && self.layers().zip(other.layers()).all(|(a, b)| {
                a.inputs == b.inputs
                    && a.outputs == b.outputs
                    && a.weights.len() == b.weights.len()
                    && a.bias.len() == b.bias.len()
            })
    }

    /// The parameter-wise mean of `nets` (weight averaging, as in stochastic weight averaging:
    /// Izmailov et al. 2018, Nikishin et al. 2018 for RL). `None` when `nets` is empty or their
    /// shapes differ. The output activation is the first network's.
    pub fn mean_of(nets: &[&MultiTaskMlp]) -> Option<MultiTaskMlp> {
        let (first, rest) = nets.split_first()?;
        if !rest.iter().all(|n| first.same_shape(n)) {
            return None;
        }
        let mut mean = (*first).clone();
        // A running mean: after k networks, each has weight 1/k.
        for (k, net) in rest.iter().enumerate() {
            mean.soft_update_from(net, 1.0 / (k as f32 + 2.0));
        }
        Some(mean)
    }

    /// Polyak averaging towards `source`: `self = tau * source + (1 - tau) * self`.
    pub fn soft_update_from(&mut self, source: &MultiTaskMlp, tau: f32) {
        for (t, s) in self.layers_mut().zip(source.layers()) {
            for (tw, sw) in t
                .weights
                .iter_mut()
                .chain(t.bias.iter_mut())
                .zip(s.weights.iter().chain(s.bias.iter()))
            {
                *tw += tau * (sw - *tw);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn a_random_direction_lies_on_its_tasks_path_and_adds_linearly() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let net = MultiTaskMlp::new(MlpShape::actor(5, 8, 2), &mut rng);
        assert!(
            net.random_direction(2, &mut rng).is_none(),
            "two tasks only"
        );
        let d = net.random_direction(1, &mut rng).expect("task 1");
        let all = |l: &Dense, f: fn(&f32) -> bool| l.weights.iter().chain(&l.bias).all(f);
        assert!(
            all(&d.task_inputs[0], |p| *p == 0.0),
            "task 0's input layer untouched"
        );
        assert!(
            all(&d.task_outputs[0], |p| *p == 0.0),
            "task 0's output layer untouched"
        );
        for layer in [
            &d.task_inputs[1],
            &d.shared[0],
            &d.shared[1],
            &d.task_outputs[1],
        ] {
            assert!(
                all(layer, |p| *p != 0.0),
                "every parameter on task 1's path drawn"
            );
        }
        let moved = net.plus_scaled(&d, 0.5);
        assert_eq!(moved.task_inputs[0], net.task_inputs[0]);
        for (m, (n, e)) in moved.layers().zip(net.layers().zip(d.layers())) {
            for (k, w) in m.weights.iter().enumerate() {
                assert!((w - (n.weights[k] + 0.5 * e.weights[k])).abs() < 1e-6);
            }
        }
        let back = moved.plus_scaled(&d, -0.5);
        for (b, n) in back.layers().zip(net.layers()) {
            for (x, y) in b.weights.iter().zip(&n.weights) {
                assert!((x - y).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn widening_adds_inputs_that_change_nothing_until_trained() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let net = MultiTaskMlp::new(MlpShape::actor(5, 8, 1), &mut rng);
        let wide = net.widen_inputs(7).expect("wider");
        assert_eq!((wide.inputs(), wide.hidden(), wide.outputs()), (7, 8, 3));
        let x = [0.3, -0.2, 0.9, 0.1, -0.7];
        for task in 0..2 {
            let mut long = x.to_vec();
            long.extend([5.0, -9.0]);
            assert_eq!(wide.predict(task, &long), net.predict(task, &x));
        }
        assert_eq!(net.widen_inputs(5).as_ref(), Some(&net));
        assert!(net.widen_inputs(4).is_none());
    }

    /// Checks every parameter's and every input's gradient of `L = sum c * output` against
    /// central differences, for each task.
    fn gradient_check(net: &MultiTaskMlp, batch: usize, seed: u64) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for task in 0..net.tasks() {
            let x: Vec<f32> = (0..batch * net.inputs())
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let c: Vec<f32> = (0..batch * net.outputs())
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let loss = |net: &MultiTaskMlp, x: &[f32]| -> f64 {
                let mut tape = Tape::default();
                net.forward(task, x, batch, &mut tape);
                tape.output()
                    .iter()
                    .zip(&c)
                    .map(|(&y, &c)| y as f64 * c as f64)
                    .sum()
            };
            let mut tape = Tape::default();
            net.forward(task, &x, batch, &mut tape);
            let mut grads = net.zeros_like();
            let dx = net
                .backward(&tape, &c, Some(&mut grads), true)
                .expect("input gradient requested");
            // Small enough not to cross ReLU kinks, large enough for f32 round-off.
            let h = 2e-3_f32;
            let close = |numeric: f64, analytic: f32, what: &str| {
                let tol = 2e-3 + 2e-2 * numeric.abs();
                assert!(
                    (numeric - analytic as f64).abs() < tol,
                    "task {task} {what}: numeric {numeric} vs analytic {analytic}"
                );
            };
            let layer_count = net.layers().count();
            for li in 0..layer_count {
                let size = net.layers().nth(li).map_or(0, |l| l.weights.len());
                let bias = net.layers().nth(li).map_or(0, |l| l.bias.len());
                for k in 0..size + bias {
                    let nudge = |delta: f32| {
                        let mut n = net.clone();
                        if let Some(l) = n.layers_mut().nth(li) {
                            if k < size {
                                l.weights[k] += delta;
                            } else {
                                l.bias[k - size] += delta;
                            }
                        }
                        loss(&n, &x)
                    };
                    let numeric = (nudge(h) - nudge(-h)) / (2.0 * h as f64);
                    let g = grads.layers().nth(li).map_or(0.0, |l| {
                        if k < size {
                            l.weights[k]
                        } else {
                            l.bias[k - size]
                        }
                    });
                    close(numeric, g, &format!("layer {li} param {k}"));
                }
            }
            for i in 0..x.len() {
                let mut plus = x.clone();
                plus[i] += h;
                let mut minus = x.clone();
                minus[i] -= h;
                let numeric = (loss(net, &plus) - loss(net, &minus)) / (2.0 * h as f64);
                close(numeric, dx[i], &format!("input {i}"));
            }
        }
    }

    /// A net with larger output weights than the default init, so tanh is exercised away from
    /// its linear region and the check is not trivially satisfied.
    fn test_net(inputs: usize, outputs: usize, act: Activation, seed: u64) -> MultiTaskMlp {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut net = MultiTaskMlp::new(
            MlpShape {
                tasks: 2,
                inputs,
                hidden: 6,
                shared_layers: 2,
                outputs,
                output_activation: act,
            },
            &mut rng,
        );
        for l in net.task_outputs.iter_mut() {
            *l = Dense::new_uniform_bound(l.inputs, l.outputs, 0.8, &mut rng);
        }
        net
    }

    #[test]
    fn the_mean_of_networks_is_their_parameter_wise_mean_and_shapes_must_agree() {
        let nets = [1, 2, 3].map(|s| test_net(5, 3, Activation::Tanh, s));
        let mean = MultiTaskMlp::mean_of(&[&nets[0], &nets[1], &nets[2]]).expect("same shapes");
        for (((m, a), b), c) in mean
            .layers()
            .zip(nets[0].layers())
            .zip(nets[1].layers())
            .zip(nets[2].layers())
        {
            let all = |d: &Dense| d.weights.iter().chain(d.bias.iter()).copied().collect();
            let (m, a, b, c): (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) =
                (all(m), all(a), all(b), all(c));
            for i in 0..m.len() {
                let want = (a[i] + b[i] + c[i]) / 3.0;
                assert!((m[i] - want).abs() < 1e-6, "{} against {want}", m[i]);
            }
        }
        // One network is its own mean; none has none; another shape is refused.
        assert_eq!(MultiTaskMlp::mean_of(&[&nets[1]]), Some(nets[1].clone()));
        assert_eq!(MultiTaskMlp::mean_of(&[]), None);
        let wider = test_net(6, 3, Activation::Tanh, 4);
        assert_eq!(MultiTaskMlp::mean_of(&[&nets[0], &wider]), None);
        assert!(!nets[0].same_shape(&wider));
    }

    #[test]
    fn actor_gradients_match_finite_differences() {
        gradient_check(&test_net(5, 3, Activation::Tanh, 10), 3, 11);
    }

    #[test]
    fn critic_gradients_match_finite_differences() {
        gradient_check(&test_net(7, 1, Activation::Identity, 20), 4, 21);
    }

    #[test]
    fn tasks_share_hidden_layers_but_not_their_own() {
        let net = test_net(4, 2, Activation::Identity, 5);
        let mut tape = Tape::default();
        net.forward(0, &[0.5, -0.2, 0.1, 0.9], 1, &mut tape);
        let mut grads = net.zeros_like();
        net.backward(&tape, &[1.0, -1.0], Some(&mut grads), false);
        let nonzero = |l: &Dense| l.weights.iter().chain(&l.bias).any(|&w| w != 0.0);
        assert!(nonzero(&grads.task_inputs[0]) && nonzero(&grads.task_outputs[0]));
        assert!(grads.shared.iter().any(nonzero));
        assert!(!nonzero(&grads.task_inputs[1]) && !nonzero(&grads.task_outputs[1]));
        // Different tasks give different answers from the same input.
        assert_ne!(net.predict(0, &[0.5; 4]), net.predict(1, &[0.5; 4]));
    }

    #[test]
    fn reinit_task_redraws_one_tasks_own_layers_only() {
        let net = test_net(5, 3, Activation::Tanh, 11);
        let mut fresh = net.clone();
        let mut rng = ChaCha8Rng::seed_from_u64(99);
        let touched = fresh.reinit_task(1, &mut rng);
        assert_eq!(touched, vec![1, 2 + net.shared.len() + 1]);
        assert_eq!(fresh.task_inputs[0], net.task_inputs[0]);
        assert_eq!(fresh.task_outputs[0], net.task_outputs[0]);
        assert_eq!(fresh.shared, net.shared);
        assert_ne!(fresh.task_inputs[1], net.task_inputs[1]);
        assert_ne!(fresh.task_outputs[1], net.task_outputs[1]);
        // The fresh output layer starts small, as a new network's does.
        assert!(
            fresh.task_outputs[1]
                .weights
                .iter()
                .all(|w| w.abs() <= OUTPUT_INIT_BOUND)
        );
        let x = [0.3, -0.2, 0.5, 0.1, -0.7];
        assert_eq!(fresh.predict(0, &x), net.predict(0, &x));
        assert!(fresh.reinit_task(2, &mut rng).is_empty());
        let mut target = net.clone();
        target.copy_task_from(&fresh, 1);
        assert_eq!(target, fresh);
    }

    #[test]
    fn soft_update_moves_a_fraction_of_the_way() {
        let a = test_net(3, 1, Activation::Identity, 1);
        let b = test_net(3, 1, Activation::Identity, 2);
        let mut t = a.clone();
        t.soft_update_from(&b, 0.25);
        let (wa, wb, wt) = (
            a.shared[0].weights[0],
            b.shared[0].weights[0],
            t.shared[0].weights[0],
        );
        assert!((wt - (0.75 * wa + 0.25 * wb)).abs() < 1e-6);
        t.soft_update_from(&b, 1.0);
        let max_gap = t
            .layers()
            .zip(b.layers())
            .flat_map(|(x, y)| x.weights.iter().zip(&y.weights).map(|(p, q)| (p - q).abs()))
            .fold(0.0_f32, f32::max);
        assert!(max_gap < 1e-6, "tau = 1 copies the source, gap {max_gap}");
    }
}
