//! A small hand-written f32 neural-network kit: dense layers, ReLU/tanh, forward passes that keep
//! the activations backprop needs, backward passes, and Adam.
//!
//! Batches are row-major `[batch][features]` slices. Weights are row-major `[out][in]`, the
//! layout of `skyherd_model`'s `Dense`, so export is a copy. Matrix products go through
//! `matrixmultiply::sgemm` (about 2.7 ms per DDPG update at 128 units, batch 256, on a 2-core machine).
//!
//! ```
//! use skyherd_trainer::nn::Dense;
//! use rand::SeedableRng;
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
//! let layer = Dense::new_uniform(3, 2, &mut rng);
//! let x = [1.0_f32, 2.0, 3.0, -1.0, 0.0, 1.0]; // a batch of two inputs
//! let mut y = vec![0.0; 4];
//! layer.forward(&x, 2, &mut y);
//! let manual: f32 = (0..3).map(|k| layer.weights[k] * x[k]).sum::<f32>() + layer.bias[0];
//! assert!((y[0] - manual).abs() < 1e-5);
//! ```

use rand::Rng;
use serde::{Deserialize, Serialize};

/// `C = alpha * A B + beta * C` for `A: m x k`, `B: k x n`, `C: m x n`, each given with its row
/// and column strides. Checks that every index stays inside its slice, so the single `unsafe`
/// call below cannot read or write out of bounds.
#[allow(clippy::too_many_arguments)]
pub(crate) fn gemm(
    m: usize,
    k: usize,
    n: usize,
    alpha: f32,
    a: &[f32],
    a_strides: (usize, usize),
    b: &[f32],
    b_strides: (usize, usize),
    beta: f32,
    c: &mut [f32],
    c_strides: (usize, usize),
) {
    if m == 0 || n == 0 {
        return;
    }
    let last = |rows: usize, cols: usize, (rs, cs): (usize, usize)| {
        (rows.saturating_sub(1)) * rs + (cols.saturating_sub(1)) * cs
    };
    assert!(
        k == 0 || last(m, k, a_strides) < a.len(),
        "gemm: A too short"
    );
    assert!(
        k == 0 || last(k, n, b_strides) < b.len(),
        "gemm: B too short"
    );
    assert!(last(m, n, c_strides) < c.len(), "gemm: C too short");
    // Strides as isize: the sizes here are far below isize::MAX.
    let s = |x: usize| x as isize;
    // SAFETY: the asserts above keep every element sgemm touches inside `a`, `b` and `c`, and
    // `c` is borrowed mutably, so it cannot alias `a` or `b`.
    #[allow(unsafe_code)]
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            alpha,
            a.as_ptr(),
            s(a_strides.0),
            s(a_strides.1),
            b.as_ptr(),
            s(b_strides.0),
            s(b_strides.1),
            beta,
            c.as_mut_ptr(),
            s(c_strides.0),
            s(c_strides.1),
        );
    }
}

/// A fully connected layer `y = W x + b`, `W` row-major `[outputs][inputs]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dense {
    /// Input width.
    pub inputs: usize,
    /// Output width.
    pub outputs: usize,
    /// Row-major `[outputs][inputs]`.
    pub weights: Vec<f32>,
    /// One per output.
    pub bias: Vec<f32>,
}

impl Dense {
    /// All-zero layer (also the shape of a gradient).
    pub fn zeros(inputs: usize, outputs: usize) -> Dense {
        Dense {
            inputs,
            outputs,
            weights: vec![0.0; inputs * outputs],
            bias: vec![0.0; outputs],
        }
    }

    /// PyTorch's default init: weights and bias uniform in `±1/sqrt(inputs)`.
    pub fn new_uniform<R: Rng>(inputs: usize, outputs: usize, rng: &mut R) -> Dense {
        let bound = 1.0 / (inputs.max(1) as f32).sqrt();
        Dense::new_uniform_bound(inputs, outputs, bound, rng)
    }

    /// Weights and bias uniform in `±bound` (cleanrl-style small output layers use 3e-3).
    pub fn new_uniform_bound<R: Rng>(
        inputs: usize,
        outputs: usize,
        bound: f32,
        rng: &mut R,
    ) -> Dense {
        let mut layer = Dense::zeros(inputs, outputs);
        for w in layer.weights.iter_mut().chain(layer.bias.iter_mut()) {
            *w = rng.random_range(-bound..=bound);
        }
        layer
    }

    /// `y[b] = W x[b] + bias` for a batch of `batch` rows; `y` must hold `batch * outputs`.
    pub fn forward(&self, x: &[f32], batch: usize, y: &mut [f32]) {
        debug_assert_eq!(x.len(), batch * self.inputs);
        let y = &mut y[..batch * self.outputs];
        for row in y.chunks_exact_mut(self.outputs) {
            row.copy_from_slice(&self.bias);
        }
        // Y (B x out) += X (B x in) W^T (in x out)
        gemm(
            batch,
            self.inputs,
            self.outputs,
            1.0,
            x,
            (self.inputs, 1),
            &self.weights,
            (1, self.inputs),
            1.0,
            y,
            (self.outputs, 1),
        );
    }

    /// Given `dy = dL/dy` for the batch, adds `dL/dW`, `dL/db` into `grad` (when given) and writes
    /// `dL/dx` into `dx` (when given).
    pub fn backward(
        &self,
        x: &[f32],
        dy: &[f32],
        batch: usize,
        grad: Option<&mut Dense>,
        dx: Option<&mut [f32]>,
    ) {
        if let Some(g) = grad {
            // dW (out x in) += dY^T (out x B) X (B x in)
            gemm(
                self.outputs,
                batch,
                self.inputs,
                1.0,
                dy,
                (1, self.outputs),
                x,
                (self.inputs, 1),
                1.0,
                &mut g.weights,
                (self.inputs, 1),
            );
            for row in dy.chunks_exact(self.outputs).take(batch) {
                for (gb, d) in g.bias.iter_mut().zip(row) {
                    *gb += d;
                }
            }
        }
        if let Some(dx) = dx {
            // dX (B x in) = dY (B x out) W (out x in)
            gemm(
                batch,
                self.outputs,
                self.inputs,
                1.0,
                dy,
                (self.outputs, 1),
                &self.weights,
                (self.inputs, 1),
                0.0,
                &mut dx[..batch * self.inputs],
                (self.inputs, 1),
            );
        }
    }

    /// Number of parameters.
    pub fn parameter_count(&self) -> usize {
        self.weights.len() + self.bias.len()
    }

    /// Sets every parameter to zero.
    pub fn fill_zero(&mut self) {
        self.weights.fill(0.0);
        self.bias.fill(0.0);
    }
}

/// Element-wise activations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Activation {
    /// `max(0, x)`.
    Relu,
    /// `tanh(x)`: bounded outputs, the actor's [-1, 1] action.
    Tanh,
    /// No change: the critic's Q-value.
    Identity,
}

impl Activation {
    /// Applies the activation in place.
    pub fn apply(self, v: &mut [f32]) {
        match self {
            Activation::Relu => v.iter_mut().for_each(|x| *x = x.max(0.0)),
            Activation::Tanh => v.iter_mut().for_each(|x| *x = x.tanh()),
            Activation::Identity => {}
        }
    }

    /// Turns `dL/dy` into `dL/dx` in place, given the activation's outputs `y`.
    pub fn backward(self, y: &[f32], dy: &mut [f32]) {
        match self {
            Activation::Relu => dy.iter_mut().zip(y).for_each(|(d, &y)| {
                if y <= 0.0 {
                    *d = 0.0;
                }
            }),
            Activation::Tanh => dy.iter_mut().zip(y).for_each(|(d, &y)| *d *= 1.0 - y * y),
            Activation::Identity => {}
        }
    }
}

/// Adam hyper-parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    /// Step size.
    pub learning_rate: f32,
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// Denominator guard.
    pub epsilon: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        AdamConfig {
            learning_rate: 3e-4,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
        }
    }
}

/// Adam's state for one parameter list (one moment pair per [`Dense`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    /// Hyper-parameters.
    pub config: AdamConfig,
    /// Steps taken (for bias correction).
    pub step: u64,
    /// First moments, shaped like the parameters.
    pub first: Vec<Dense>,
    /// Second moments, shaped like the parameters.
    pub second: Vec<Dense>,
}

impl Adam {
    /// Fresh state for parameters shaped like `layers`.
    pub fn new<'a>(config: AdamConfig, layers: impl Iterator<Item = &'a Dense>) -> Adam {
        let first: Vec<Dense> = layers.map(|l| Dense::zeros(l.inputs, l.outputs)).collect();
        Adam {
            config,
            step: 0,
            second: first.clone(),
            first,
        }
    }

    /// Zeroes the moments of layer `index` (a layer drawn afresh starts without the old
    /// layer's momentum); an index past the end changes nothing.
    pub fn clear_layer(&mut self, index: usize) {
        for moments in [&mut self.first, &mut self.second] {
            if let Some(layer) = moments.get_mut(index) {
                layer.fill_zero();
            }
        }
    }

    /// One Adam step: `params[i] -= lr * m_hat / (sqrt(v_hat) + eps)` with `grads[i]`.
    pub fn update<'a>(
        &mut self,
        params: impl Iterator<Item = &'a mut Dense>,
        grads: impl Iterator<Item = &'a Dense>,
    ) {
        self.step += 1;
        let c = self.config;
        let t = self.step.min(i32::MAX as u64) as i32;
        let correction1 = 1.0 - c.beta1.powi(t);
        let correction2 = 1.0 - c.beta2.powi(t);
        let step_size = c.learning_rate / correction1;
        for (((p, g), m), v) in params
            .zip(grads)
            .zip(self.first.iter_mut())
            .zip(self.second.iter_mut())
        {
            let pairs = [
                (&mut p.weights, &g.weights, &mut m.weights, &mut v.weights),
                (&mut p.bias, &g.bias, &mut m.bias, &mut v.bias),
            ];
            for (p, g, m, v) in pairs {
                for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                    *m = c.beta1 * *m + (1.0 - c.beta1) * g;
                    *v = c.beta2 * *v + (1.0 - c.beta2) * g * g;
                    *p -= step_size * *m / ((*v / correction2).sqrt() + c.epsilon);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// `L = sum_i c_i y_i`, a loss with a known, non-trivial `dL/dy = c`.
    fn weighted_sum(y: &[f32], c: &[f32]) -> f64 {
        y.iter().zip(c).map(|(&a, &b)| a as f64 * b as f64).sum()
    }

    #[test]
    fn dense_backward_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (inputs, outputs, batch) = (5, 4, 3);
        let layer = Dense::new_uniform(inputs, outputs, &mut rng);
        let x: Vec<f32> = (0..inputs * batch)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let c: Vec<f32> = (0..outputs * batch)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let loss = |layer: &Dense, x: &[f32]| {
            let mut y = vec![0.0; outputs * batch];
            layer.forward(x, batch, &mut y);
            weighted_sum(&y, &c)
        };
        let mut grad = Dense::zeros(inputs, outputs);
        let mut dx = vec![0.0; inputs * batch];
        layer.backward(&x, &c, batch, Some(&mut grad), Some(&mut dx));
        let h = 1e-2_f32;
        for i in 0..layer.weights.len() {
            let mut plus = layer.clone();
            plus.weights[i] += h;
            let mut minus = layer.clone();
            minus.weights[i] -= h;
            let numeric = (loss(&plus, &x) - loss(&minus, &x)) / (2.0 * h as f64);
            assert!(
                (numeric - grad.weights[i] as f64).abs() < 1e-3,
                "w{i}: {numeric} vs {}",
                grad.weights[i]
            );
        }
        for i in 0..layer.bias.len() {
            let mut plus = layer.clone();
            plus.bias[i] += h;
            let mut minus = layer.clone();
            minus.bias[i] -= h;
            let numeric = (loss(&plus, &x) - loss(&minus, &x)) / (2.0 * h as f64);
            assert!((numeric - grad.bias[i] as f64).abs() < 1e-3);
        }
        for i in 0..x.len() {
            let mut plus = x.clone();
            plus[i] += h;
            let mut minus = x.clone();
            minus[i] -= h;
            let numeric = (loss(&layer, &plus) - loss(&layer, &minus)) / (2.0 * h as f64);
            assert!((numeric - dx[i] as f64).abs() < 1e-3, "x{i}");
        }
    }

    #[test]
    fn activations_backward_match_finite_differences() {
        let xs = [-1.3_f32, -0.2, 0.4, 0.9, 2.1];
        for act in [Activation::Relu, Activation::Tanh, Activation::Identity] {
            for &x in &xs {
                let f = |x: f32| {
                    let mut v = [x];
                    act.apply(&mut v);
                    v[0]
                };
                let y = f(x);
                let mut d = [1.0_f32];
                act.backward(&[y], &mut d);
                let h = 1e-3;
                let numeric = (f(x + h) - f(x - h)) / (2.0 * h);
                assert!(
                    (numeric - d[0]).abs() < 1e-3,
                    "{act:?} at {x}: {numeric} vs {}",
                    d[0]
                );
            }
        }
    }

    #[test]
    fn adam_minimises_a_quadratic() {
        // L = sum (w - 3)^2 over one layer's parameters.
        let mut layer = Dense::zeros(2, 2);
        let mut adam = Adam::new(
            AdamConfig {
                learning_rate: 0.05,
                ..AdamConfig::default()
            },
            std::iter::once(&layer),
        );
        for _ in 0..600 {
            let mut grad = Dense::zeros(2, 2);
            for (g, w) in grad.weights.iter_mut().zip(&layer.weights) {
                *g = 2.0 * (w - 3.0);
            }
            for (g, b) in grad.bias.iter_mut().zip(&layer.bias) {
                *g = 2.0 * (b - 3.0);
            }
            adam.update(std::iter::once(&mut layer), std::iter::once(&grad));
        }
        assert!(
            layer
                .weights
                .iter()
                .chain(&layer.bias)
                .all(|w| (w - 3.0).abs() < 0.05),
            "{layer:?}"
        );
    }

    #[test]
    #[should_panic(expected = "gemm: C too short")]
    fn gemm_refuses_short_output() {
        let a = [1.0; 4];
        let mut c = [0.0; 3];
        gemm(2, 2, 2, 1.0, &a, (2, 1), &a, (2, 1), 0.0, &mut c, (2, 1));
    }
}
