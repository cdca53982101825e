//! Replay memory: a fixed-capacity ring of `(s, a, r, s', terminated)` per task.
//!
//! `terminated` is stored separately from truncation: an episode cut by the step limit is *not*
//! terminal (its next state still has a value), so the learner bootstraps through it.
//!
//! ```
//! use skyherd_trainer::replay::{Batch, ReplayBuffer};
//! use rand::SeedableRng;
//! let mut buffer = ReplayBuffer::new(2, 1, 100);
//! buffer.push(&[0.0, 1.0], &[0.5], -1.0, &[0.1, 1.1], false);
//! buffer.push(&[0.1, 1.1], &[0.4], 10.0, &[0.2, 1.2], true);
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
//! let mut batch = Batch::default();
//! buffer.sample(8, &mut rng, &mut batch);
//! assert_eq!(batch.rewards.len(), 8);
//! assert!(batch.continues.iter().all(|&c| c == 0.0 || c == 1.0));
//! ```

use rand::Rng;

/// One task's replay memory.
#[derive(Clone, Debug)]
pub struct ReplayBuffer {
    obs_dim: usize,
    action_dim: usize,
    capacity: usize,
    len: usize,
    next: usize,
    obs: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    next_obs: Vec<f32>,
    /// `gamma^(k-1) (1 - terminated)` of a `k`-step transition: what multiplies
    /// `gamma Q'(s')` in its TD target.
    continues: Vec<f32>,
}

/// A sampled minibatch, row-major.
#[derive(Clone, Debug, Default)]
pub struct Batch {
    /// Rows.
    pub size: usize,
    /// `[size][obs_dim]`.
    pub obs: Vec<f32>,
    /// `[size][action_dim]`.
    pub actions: Vec<f32>,
    /// `[size]`.
    pub rewards: Vec<f32>,
    /// `[size][obs_dim]`.
    pub next_obs: Vec<f32>,
    /// `1 - terminated` for one-step transitions; `gamma^(k-1) (1 - terminated)` for `k`-step
    /// ones: the TD target is `r + gamma continues Q'(next_obs)`.
    pub continues: Vec<f32>,
}

impl ReplayBuffer {
    /// An empty buffer holding at most `capacity` transitions (at least one).
    pub fn new(obs_dim: usize, action_dim: usize, capacity: usize) -> ReplayBuffer {
        let capacity = capacity.max(1);
        ReplayBuffer {
            obs_dim,
            action_dim,
            capacity,
            len: 0,
            next: 0,
            obs: vec![0.0; capacity * obs_dim],
            actions: vec![0.0; capacity * action_dim],
            rewards: vec![0.0; capacity],
            next_obs: vec![0.0; capacity * obs_dim],
            continues: vec![1.0; capacity],
        }
    }

    /// Stored transitions.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether nothing is stored yet.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Width of the stored observations.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Adds a one-step transition, overwriting the oldest when full.
    pub fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        terminated: bool,
    ) {
        let continues = if terminated { 0.0 } else { 1.0 };
        self.push_discounted(obs, action, reward, next_obs, continues);
    }

    /// Adds a transition whose TD target is `reward + gamma continues Q'(next_obs)` (an
    /// n-step transition: see [`NStep`]).
    pub fn push_discounted(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        continues: f32,
    ) {
        assert_eq!(obs.len(), self.obs_dim, "observation width");
        assert_eq!(next_obs.len(), self.obs_dim, "next observation width");
        assert_eq!(action.len(), self.action_dim, "action width");
        let i = self.next;
        let (o, a) = (self.obs_dim, self.action_dim);
        self.obs[i * o..(i + 1) * o].copy_from_slice(obs);
        self.next_obs[i * o..(i + 1) * o].copy_from_slice(next_obs);
        self.actions[i * a..(i + 1) * a].copy_from_slice(action);
        self.rewards[i] = reward;
        self.continues[i] = continues;
        self.next = (self.next + 1) % self.capacity;
        self.len = (self.len + 1).min(self.capacity);
    }

    /// Draws `size` transitions uniformly with replacement into `batch` (empty if the buffer is).
    pub fn sample<R: Rng>(&self, size: usize, rng: &mut R, batch: &mut Batch) {
        let (o, a) = (self.obs_dim, self.action_dim);
        batch.obs.clear();
        batch.actions.clear();
        batch.rewards.clear();
        batch.next_obs.clear();
        batch.continues.clear();
        batch.size = if self.len == 0 { 0 } else { size };
        for _ in 0..batch.size {
            let i = rng.random_range(0..self.len);
            batch.obs.extend_from_slice(&self.obs[i * o..(i + 1) * o]);
            batch
                .actions
                .extend_from_slice(&self.actions[i * a..(i + 1) * a]);
            batch.rewards.push(self.rewards[i]);
            batch
                .next_obs
                .extend_from_slice(&self.next_obs[i * o..(i + 1) * o]);
            batch.continues.push(self.continues[i]);
        }
    }
}

/// One herder's n-step return accumulator: push each one-step transition, get back the
/// n-step transitions that are complete.
///
/// A transition `k` steps old is emitted when `k = n` with `r_t + gamma r_(t+1) + ... +
/// gamma^(n-1) r_(t+n-1)`, the state `n` steps later and `continues = gamma^(n-1)`. At a
/// terminal every pending transition is emitted with its partial sum and `continues = 0` (no
/// bootstrap past the end); at a truncation with its partial sum, the last state, and
/// `continues = gamma^(k-1)` (bootstrapped: the episode was cut, not finished).
#[derive(Clone, Debug)]
pub struct NStep {
    n: usize,
    gamma: f32,
    pending: std::collections::VecDeque<(Vec<f32>, Vec<f32>, f32, usize)>,
}

/// An n-step transition: `(obs, action, discounted reward sum, next_obs, continues)`.
pub type NStepTransition = (Vec<f32>, Vec<f32>, f32, Vec<f32>, f32);

/// One environment step of one herder, as [`NStep::push`] takes it.
#[derive(Clone, Copy, Debug)]
pub struct OneStep<'a> {
    /// The observation acted on.
    pub obs: &'a [f32],
    /// The action taken.
    pub action: &'a [f32],
    /// The reward received.
    pub reward: f32,
    /// The observation after the step.
    pub next_obs: &'a [f32],
    /// The episode ended (no bootstrap past it).
    pub terminated: bool,
    /// The episode was cut by the step limit (bootstrap past it).
    pub truncated: bool,
}

impl NStep {
    /// An accumulator for `n`-step returns (`n >= 1`) discounted by `gamma`.
    pub fn new(n: usize, gamma: f32) -> Self {
        Self {
            n: n.max(1),
            gamma,
            pending: std::collections::VecDeque::new(),
        }
    }

    /// One step; the finished n-step transitions are appended to `out`.
    pub fn push(&mut self, step: OneStep<'_>, out: &mut Vec<NStepTransition>) {
        let OneStep {
            obs,
            action,
            reward,
            next_obs,
            terminated,
            truncated,
        } = step;
        // Every pending transition gains this step's reward at its own discount.
        for (_, _, sum, steps) in self.pending.iter_mut() {
            *sum += self.gamma.powi(*steps as i32) * reward;
            *steps += 1;
        }
        self.pending
            .push_back((obs.to_vec(), action.to_vec(), reward, 1));
        if terminated || truncated {
            for (o, a, sum, steps) in self.pending.drain(..) {
                let continues = if terminated {
                    0.0
                } else {
                    self.gamma.powi(steps as i32 - 1)
                };
                out.push((o, a, sum, next_obs.to_vec(), continues));
            }
            return;
        }
        if self.pending.front().is_some_and(|p| p.3 >= self.n)
            && let Some((o, a, sum, steps)) = self.pending.pop_front()
        {
            out.push((
                o,
                a,
                sum,
                next_obs.to_vec(),
                self.gamma.powi(steps as i32 - 1),
            ));
        }
    }

    /// Drop what is pending (a broken chain: an observation the encoder refused).
    pub fn clear(&mut self) {
        self.pending.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn ring_overwrites_the_oldest_and_keeps_rows_together() {
        let mut b = ReplayBuffer::new(1, 1, 3);
        for k in 0..5 {
            let v = k as f32;
            b.push(
                &[v],
                &[-v],
                10.0 * v,
                &[v + 0.5],
                (k as usize).is_multiple_of(2),
            );
        }
        assert_eq!(b.len(), 3);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut batch = Batch::default();
        b.sample(64, &mut rng, &mut batch);
        for r in 0..batch.size {
            let v = batch.obs[r];
            assert!(v >= 2.0, "transition {v} should have been overwritten");
            assert_eq!(batch.actions[r], -v);
            assert_eq!(batch.rewards[r], 10.0 * v);
            assert_eq!(batch.next_obs[r], v + 0.5);
            let terminated = (v as usize).is_multiple_of(2);
            assert_eq!(batch.continues[r], if terminated { 0.0 } else { 1.0 });
        }
    }

    fn run(n: usize, rewards: &[f32], terminated: bool) -> Vec<NStepTransition> {
        let mut acc = NStep::new(n, 0.5);
        let mut out = Vec::new();
        for (t, r) in rewards.iter().enumerate() {
            let last = t + 1 == rewards.len();
            let step = OneStep {
                obs: &[t as f32],
                action: &[0.0],
                reward: *r,
                next_obs: &[t as f32 + 1.0],
                terminated: last && terminated,
                truncated: last && !terminated,
            };
            acc.push(step, &mut out);
        }
        out
    }

    #[test]
    fn n_step_sums_discount_and_bootstrap_n_steps_later() {
        let out = run(3, &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0], false);
        // Transitions 0-3 are complete 3-step ones; at the truncation 4 and 5 are flushed.
        assert_eq!(out.len(), 6);
        let (o, _, sum, next, continues) = &out[0];
        assert_eq!((o[0], next[0]), (0.0, 3.0));
        assert_eq!(*sum, 1.0 + 0.5 * 2.0 + 0.25 * 4.0);
        assert_eq!(
            *continues, 0.25,
            "gamma^(n-1): the target adds gamma * this * Q'"
        );
        for (k, (o, _, _, next, _)) in out.iter().take(4).enumerate() {
            assert_eq!((o[0], next[0]), (k as f32, k as f32 + 3.0));
        }
    }

    #[test]
    fn n_step_targets_are_cut_at_a_terminal() {
        let out = run(3, &[1.0, 2.0, 4.0, 8.0], true);
        assert_eq!(out.len(), 4);
        // The last three end at the terminal: partial sums, no bootstrap.
        let tail: Vec<(f32, f32, f32)> = out[1..].iter().map(|t| (t.0[0], t.2, t.4)).collect();
        assert_eq!(
            tail,
            vec![
                (1.0, 2.0 + 2.0 + 2.0, 0.0),
                (2.0, 4.0 + 4.0, 0.0),
                (3.0, 8.0, 0.0)
            ]
        );
        assert!(out.iter().all(|t| t.3[0] == 4.0 || t.0[0] == 0.0));
    }

    #[test]
    fn n_step_targets_bootstrap_at_a_truncation_with_their_own_discount() {
        let out = run(3, &[1.0, 2.0], false);
        // Cut after two steps: the first bootstraps 2 steps on (gamma^1), the second 1 step.
        assert_eq!(out.len(), 2);
        assert_eq!(
            (out[0].2, out[0].3[0], out[0].4),
            (1.0 + 0.5 * 2.0, 2.0, 0.5)
        );
        assert_eq!((out[1].2, out[1].3[0], out[1].4), (2.0, 2.0, 1.0));
    }

    #[test]
    fn one_step_n_step_is_the_plain_transition() {
        let out = run(1, &[3.0, 5.0], true);
        assert_eq!(out.len(), 2);
        assert_eq!((out[0].2, out[0].3[0], out[0].4), (3.0, 1.0, 1.0));
        assert_eq!((out[1].2, out[1].3[0], out[1].4), (5.0, 2.0, 0.0));
    }
}
