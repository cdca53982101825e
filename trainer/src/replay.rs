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
    terminated: Vec<bool>,
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
    /// `1 - terminated`: whether to bootstrap from `next_obs`.
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
            terminated: vec![false; capacity],
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

    /// Adds a transition, overwriting the oldest when full.
    pub fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        terminated: bool,
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
        self.terminated[i] = terminated;
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
            batch
                .continues
                .push(if self.terminated[i] { 0.0 } else { 1.0 });
        }
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
}
