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
    /// The discounted return from `s` to its episode's end, in reward units, once the episode
    /// has ended ([`ReplayBuffer::set_return`]); NaN until then and for truncated episodes.
    returns: Vec<f32>,
    /// Transitions pushed since the buffer was made (never reset): a push's stamp.
    pushed: u64,
    /// `pushed` at the last [`ReplayBuffer::clear`]: older stamps are gone.
    stamp_base: u64,
    /// The centralised critic's columns, when kept.
    others: Option<OthersColumns>,
}

/// What a centralised critic needs beyond one herder's own transition: the other herders
/// pooled where the transition starts, and one by one where it ends (their next actions come
/// from the target actor at update time, so their observations must be kept).
#[derive(Clone, Debug)]
struct OthersColumns {
    max_others: usize,
    /// `[capacity][obs_dim + action_dim]`: [`pool_others`] at `s`.
    context: Vec<f32>,
    /// `[capacity][max_others][obs_dim]`: the others' observations at `s'`, zero-padded.
    next_others: Vec<f32>,
    /// How many of `next_others` rows are real.
    next_count: Vec<u8>,
}

/// The other herders of one transition, as the centralised critic sees them.
#[derive(Clone, Copy, Debug)]
pub struct Others<'a> {
    /// [`pool_others`] of their observations and actions at `s`.
    pub context: &'a [f32],
    /// Their observations at `s'`, one row each (at most the buffer's `max_others`).
    pub next_obs: &'a [f32],
}

/// The mean of the other herders' observations and the mean of their actions, `[mean obs |
/// mean action]` (zeros when there are none): a summary that does not depend on their order
/// or number, so one critic serves any team size.
pub fn pool_others(obs: &[f32], actions: &[f32], obs_dim: usize, action_dim: usize) -> Vec<f32> {
    let mut out = vec![0.0; obs_dim + action_dim];
    let count = obs.len() / obs_dim.max(1);
    if count == 0 {
        return out;
    }
    for row in obs.chunks_exact(obs_dim) {
        out[..obs_dim]
            .iter_mut()
            .zip(row)
            .for_each(|(o, x)| *o += x);
    }
    for row in actions.chunks_exact(action_dim) {
        out[obs_dim..]
            .iter_mut()
            .zip(row)
            .for_each(|(o, x)| *o += x);
    }
    out.iter_mut().for_each(|o| *o /= count as f32);
    out
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
    /// `[size]`: the discounted return from `obs` to the episode's end in reward units, NaN
    /// where not known (self-imitation's; empty in hand-made batches).
    pub returns: Vec<f32>,
    /// Centralised critic only (else empty): `[size][obs_dim + action_dim]`, the other herders
    /// pooled at `s`.
    pub context: Vec<f32>,
    /// Centralised critic only: `[size][max_others][obs_dim]`, the others at `s'`.
    pub next_others: Vec<f32>,
    /// Centralised critic only: real rows of `next_others` per transition.
    pub next_others_count: Vec<u8>,
    /// Centralised critic only: rows of `next_others` per transition (0 otherwise).
    pub max_others: usize,
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
            returns: vec![f32::NAN; capacity],
            pushed: 0,
            stamp_base: 0,
            others: None,
        }
    }

    /// This buffer, also keeping the other herders (at most `max_others` of them) for a
    /// centralised critic; transitions must then be pushed with
    /// [`ReplayBuffer::push_with_others`].
    pub fn with_others(mut self, max_others: usize) -> ReplayBuffer {
        let max_others = max_others.clamp(1, usize::from(u8::MAX));
        let (c, o) = (self.capacity, self.obs_dim);
        self.others = Some(OthersColumns {
            max_others,
            context: vec![0.0; c * (o + self.action_dim)],
            next_others: vec![0.0; c * max_others * o],
            next_count: vec![0; c],
        });
        self
    }

    /// The most other herders a transition keeps (0: no centralised critic columns).
    pub fn max_others(&self) -> usize {
        self.others.as_ref().map_or(0, |o| o.max_others)
    }

    /// Forgets every stored transition (the memory stays allocated for the next ones).
    pub fn clear(&mut self) {
        self.len = 0;
        self.next = 0;
        self.stamp_base = self.pushed;
    }

    /// Sets the return-to-go (reward units) of the transition whose push returned `stamp`;
    /// false, and nothing set, when that transition is gone (overwritten or cleared).
    pub fn set_return(&mut self, stamp: u64, value: f32) -> bool {
        if stamp < self.stamp_base || stamp >= self.pushed {
            return false;
        }
        if self.pushed - stamp > self.capacity as u64 {
            return false;
        }
        let i = ((stamp - self.stamp_base) % self.capacity as u64) as usize;
        self.returns[i] = value;
        true
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

    /// Adds a one-step transition, overwriting the oldest when full; returns its stamp (for
    /// [`ReplayBuffer::set_return`]).
    pub fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        terminated: bool,
    ) -> u64 {
        let continues = if terminated { 0.0 } else { 1.0 };
        self.push_discounted(obs, action, reward, next_obs, continues)
    }

    /// Adds a transition whose TD target is `reward + gamma continues Q'(next_obs)` (an
    /// n-step transition: see [`NStep`]); returns its stamp (for [`ReplayBuffer::set_return`]).
    pub fn push_discounted(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        continues: f32,
    ) -> u64 {
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
        self.returns[i] = f32::NAN;
        if let Some(cols) = self.others.as_mut() {
            // A transition without others (a lone herder) has an empty pool.
            let w = o + a;
            cols.context[i * w..(i + 1) * w].fill(0.0);
            cols.next_count[i] = 0;
        }
        self.next = (self.next + 1) % self.capacity;
        self.len = (self.len + 1).min(self.capacity);
        let stamp = self.pushed;
        self.pushed += 1;
        stamp
    }

    /// Adds a transition with its other herders (a buffer made [`ReplayBuffer::with_others`];
    /// on a plain buffer the others are dropped). Others beyond `max_others` are dropped too:
    /// the caller passes the nearest first.
    pub fn push_with_others(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        continues: f32,
        others: Others<'_>,
    ) -> u64 {
        let i = self.next;
        let stamp = self.push_discounted(obs, action, reward, next_obs, continues);
        let (o, a) = (self.obs_dim, self.action_dim);
        let Some(cols) = self.others.as_mut() else {
            return stamp;
        };
        let w = o + a;
        assert_eq!(others.context.len(), w, "pooled context width");
        cols.context[i * w..(i + 1) * w].copy_from_slice(others.context);
        let k = (others.next_obs.len() / o.max(1)).min(cols.max_others);
        let row = cols.max_others * o;
        let dst = &mut cols.next_others[i * row..(i + 1) * row];
        dst[..k * o].copy_from_slice(&others.next_obs[..k * o]);
        dst[k * o..].fill(0.0);
        cols.next_count[i] = k as u8;
        stamp
    }

    /// The stored return-to-go of the `i`-th row in storage order (NaN where unknown).
    #[cfg(test)]
    pub(crate) fn return_at(&self, i: usize) -> f32 {
        self.returns[i]
    }

    /// The stored reward and `continues` of the `i`-th row in storage order.
    #[cfg(test)]
    pub(crate) fn reward_at(&self, i: usize) -> (f32, f32) {
        (self.rewards[i], self.continues[i])
    }

    /// Draws `size` transitions uniformly with replacement into `batch` (empty if the buffer is).
    pub fn sample<R: Rng>(&self, size: usize, rng: &mut R, batch: &mut Batch) {
        let (o, a) = (self.obs_dim, self.action_dim);
        batch.obs.clear();
        batch.actions.clear();
        batch.rewards.clear();
        batch.next_obs.clear();
        batch.continues.clear();
        batch.returns.clear();
        batch.context.clear();
        batch.next_others.clear();
        batch.next_others_count.clear();
        batch.max_others = self.max_others();
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
            batch.returns.push(self.returns[i]);
            if let Some(cols) = &self.others {
                let w = o + a;
                batch
                    .context
                    .extend_from_slice(&cols.context[i * w..(i + 1) * w]);
                let row = cols.max_others * o;
                batch
                    .next_others
                    .extend_from_slice(&cols.next_others[i * row..(i + 1) * row]);
                batch.next_others_count.push(cols.next_count[i]);
            }
        }
    }
}

/// The discounted return-to-go of every step of an ended episode: `R_k = r_k + gamma^(s_k)
/// R_(k+1)` with `R` past the last step 0, where each step is `(reward, simulator steps it
/// spans)` (a held action's reward is already its steps' discounted sum, see [`OneStep`]).
pub fn returns_to_go(steps: &[(f32, usize)], gamma: f32) -> Vec<f32> {
    let mut out = vec![0.0; steps.len()];
    let mut after = 0.0_f32;
    for (k, &(reward, sim_steps)) in steps.iter().enumerate().rev() {
        after = reward + gamma.powi(sim_steps.max(1) as i32) * after;
        out[k] = after;
    }
    out
}

/// One herder's n-step return accumulator: push each one-step transition, get back the
/// n-step transitions that are complete.
///
/// A transition `k` steps old is emitted when `k = n` with `r_t + gamma r_(t+1) + ... +
/// gamma^(n-1) r_(t+n-1)`, the state `n` steps later and `continues = gamma^(n-1)`. At a
/// terminal every pending transition is emitted with its partial sum and `continues = 0` (no
/// bootstrap past the end); at a truncation with its partial sum, the last state, and
/// `continues = gamma^(k-1)` (bootstrapped: the episode was cut, not finished).
///
/// A step may span several simulator steps (an action held for them, `training.action_repeat`;
/// [`OneStep::sim_steps`]): its reward is then their discounted sum, `n` counts such steps, and
/// every discount runs over simulator steps, so a transition spanning `s` of them in all has
/// `continues = gamma^(s-1)` and the next step's reward enters at `gamma^s`.
#[derive(Clone, Debug)]
pub struct NStep {
    n: usize,
    gamma: f32,
    pending: std::collections::VecDeque<Pending>,
}

/// A transition waiting for its later rewards.
#[derive(Clone, Debug)]
struct Pending {
    obs: Vec<f32>,
    action: Vec<f32>,
    context: Vec<f32>,
    sum: f32,
    /// Steps pushed since it started (what `n` counts).
    steps: usize,
    /// Simulator steps those span (the discount's exponent).
    sim_steps: usize,
}

/// An n-step transition: `(obs, action, discounted reward sum, next_obs, continues)`, and the
/// pooled other herders where it started (empty without a centralised critic).
#[derive(Clone, Debug, PartialEq)]
pub struct NStepTransition {
    /// The observation acted on.
    pub obs: Vec<f32>,
    /// The action taken.
    pub action: Vec<f32>,
    /// `r_t + gamma r_(t+1) + ...` over the transition's steps.
    pub reward: f32,
    /// The observation where it ends.
    pub next_obs: Vec<f32>,
    /// What multiplies `gamma Q'(next_obs)` in the target.
    pub continues: f32,
    /// The other herders pooled at `obs` ([`OneStep::context`]).
    pub context: Vec<f32>,
}

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
    /// The other herders pooled at `obs`, for a centralised critic (empty otherwise).
    pub context: &'a [f32],
    /// Simulator steps this step spans (an action held over them, its `reward` their
    /// discounted sum); 1 for a plain step.
    pub sim_steps: usize,
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
            context,
            sim_steps,
        } = step;
        let sim_steps = sim_steps.max(1);
        // Every pending transition gains this step's reward at its own discount.
        for p in self.pending.iter_mut() {
            p.sum += self.gamma.powi(p.sim_steps as i32) * reward;
            p.steps += 1;
            p.sim_steps += sim_steps;
        }
        self.pending.push_back(Pending {
            obs: obs.to_vec(),
            action: action.to_vec(),
            context: context.to_vec(),
            sum: reward,
            steps: 1,
            sim_steps,
        });
        let finish = |p: Pending, continues: f32| NStepTransition {
            obs: p.obs,
            action: p.action,
            reward: p.sum,
            next_obs: next_obs.to_vec(),
            continues,
            context: p.context,
        };
        if terminated || truncated {
            for p in self.pending.drain(..) {
                let continues = if terminated {
                    0.0
                } else {
                    self.gamma.powi(p.sim_steps as i32 - 1)
                };
                out.push(finish(p, continues));
            }
            return;
        }
        if self.pending.front().is_some_and(|p| p.steps >= self.n)
            && let Some(p) = self.pending.pop_front()
        {
            let continues = self.gamma.powi(p.sim_steps as i32 - 1);
            out.push(finish(p, continues));
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

    #[test]
    fn a_cleared_buffer_samples_nothing_and_fills_again() {
        let mut b = ReplayBuffer::new(1, 1, 3);
        for k in 0..4 {
            b.push(&[k as f32], &[0.0], 1.0, &[0.0], false);
        }
        b.clear();
        assert!(b.is_empty());
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut batch = Batch::default();
        b.sample(8, &mut rng, &mut batch);
        assert_eq!(batch.size, 0);
        b.push(&[7.0], &[0.5], 2.0, &[8.0], true);
        b.sample(8, &mut rng, &mut batch);
        assert_eq!(b.len(), 1);
        assert!(batch.obs.iter().all(|&v| v == 7.0));
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
                context: &[],
                sim_steps: 1,
            };
            acc.push(step, &mut out);
        }
        out
    }

    #[test]
    fn held_steps_discount_over_simulator_steps() {
        // Two-step returns over steps that each hold an action for 2 simulator steps (the
        // last for 1: the episode was cut): discounts run over simulator steps.
        let mut acc = NStep::new(2, 0.5);
        let mut out = Vec::new();
        let spans = [2, 2, 2, 1];
        let rewards = [1.0, 2.0, 4.0, 8.0];
        for (t, (&span, &r)) in spans.iter().zip(&rewards).enumerate() {
            let last = t + 1 == spans.len();
            let step = OneStep {
                obs: &[t as f32],
                action: &[0.0],
                reward: r,
                next_obs: &[t as f32 + 1.0],
                terminated: false,
                truncated: last,
                context: &[],
                sim_steps: span,
            };
            acc.push(step, &mut out);
        }
        assert_eq!(out.len(), 4);
        // The first: its own 2 steps, then the next held step's reward at 0.5^2, and it
        // bootstraps 4 simulator steps later: gamma * continues = 0.5^4.
        assert_eq!((out[0].obs[0], out[0].next_obs[0]), (0.0, 2.0));
        assert_eq!(out[0].reward, 1.0 + 0.25 * 2.0);
        assert_eq!(out[0].continues, 0.125);
        // Cut by the truncation: the third spans 2 + 1 simulator steps, the fourth 1.
        assert_eq!(out[2].reward, 4.0 + 0.25 * 8.0);
        assert_eq!(out[2].continues, 0.25);
        assert_eq!((out[3].reward, out[3].continues), (8.0, 1.0));
        // Steps of one simulator step each are plain n-step returns.
        assert_eq!(run(2, &[1.0, 2.0, 4.0], false)[0].continues, 0.5);
    }

    #[test]
    fn n_step_sums_discount_and_bootstrap_n_steps_later() {
        let out = run(3, &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0], false);
        // Transitions 0-3 are complete 3-step ones; at the truncation 4 and 5 are flushed.
        assert_eq!(out.len(), 6);
        let t = &out[0];
        assert_eq!((t.obs[0], t.next_obs[0]), (0.0, 3.0));
        assert_eq!(t.reward, 1.0 + 0.5 * 2.0 + 0.25 * 4.0);
        assert_eq!(
            t.continues, 0.25,
            "gamma^(n-1): the target adds gamma * this * Q'"
        );
        for (k, t) in out.iter().take(4).enumerate() {
            assert_eq!((t.obs[0], t.next_obs[0]), (k as f32, k as f32 + 3.0));
        }
    }

    #[test]
    fn n_step_targets_are_cut_at_a_terminal() {
        let out = run(3, &[1.0, 2.0, 4.0, 8.0], true);
        assert_eq!(out.len(), 4);
        // The last three end at the terminal: partial sums, no bootstrap.
        let tail: Vec<(f32, f32, f32)> = out[1..]
            .iter()
            .map(|t| (t.obs[0], t.reward, t.continues))
            .collect();
        assert_eq!(
            tail,
            vec![
                (1.0, 2.0 + 2.0 + 2.0, 0.0),
                (2.0, 4.0 + 4.0, 0.0),
                (3.0, 8.0, 0.0)
            ]
        );
        assert!(out.iter().all(|t| t.next_obs[0] == 4.0 || t.obs[0] == 0.0));
    }

    #[test]
    fn n_step_targets_bootstrap_at_a_truncation_with_their_own_discount() {
        let out = run(3, &[1.0, 2.0], false);
        // Cut after two steps: the first bootstraps 2 steps on (gamma^1), the second 1 step.
        assert_eq!(out.len(), 2);
        let row = |t: &NStepTransition| (t.reward, t.next_obs[0], t.continues);
        assert_eq!(row(&out[0]), (1.0 + 0.5 * 2.0, 2.0, 0.5));
        assert_eq!(row(&out[1]), (2.0, 2.0, 1.0));
    }

    #[test]
    fn one_step_n_step_is_the_plain_transition() {
        let out = run(1, &[3.0, 5.0], true);
        assert_eq!(out.len(), 2);
        let row = |t: &NStepTransition| (t.reward, t.next_obs[0], t.continues);
        assert_eq!(row(&out[0]), (3.0, 1.0, 1.0));
        assert_eq!(row(&out[1]), (5.0, 2.0, 0.0));
    }

    #[test]
    fn pooling_the_other_herders_ignores_their_order() {
        let obs = [1.0, 2.0, 3.0, 4.0, -5.0, 0.5];
        let actions = [0.1, 0.2, -0.3, 0.4, 0.0, 0.6];
        let pooled = pool_others(&obs, &actions, 2, 2);
        assert_eq!(pooled, vec![-1.0 / 3.0, 6.5 / 3.0, -0.2 / 3.0, 1.2 / 3.0]);
        // Every order of the three herders gives the same pool.
        for order in [[0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]] {
            let o: Vec<f32> = order
                .iter()
                .flat_map(|&k| obs[2 * k..2 * k + 2].to_vec())
                .collect();
            let a: Vec<f32> = order
                .iter()
                .flat_map(|&k| actions[2 * k..2 * k + 2].to_vec())
                .collect();
            let p = pool_others(&o, &a, 2, 2);
            for (x, y) in p.iter().zip(&pooled) {
                assert!((x - y).abs() < 1e-6, "{p:?} vs {pooled:?}");
            }
        }
        assert_eq!(
            pool_others(&[], &[], 2, 2),
            vec![0.0; 4],
            "alone: an empty pool"
        );
    }

    #[test]
    fn others_columns_keep_rows_together_and_pad() {
        let mut b = ReplayBuffer::new(2, 1, 4).with_others(3);
        b.push_with_others(
            &[1.0, 1.0],
            &[0.5],
            -1.0,
            &[2.0, 2.0],
            1.0,
            Others {
                context: &[7.0, 8.0, 9.0],
                next_obs: &[1.0, 2.0, 3.0, 4.0],
            },
        );
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let mut batch = Batch::default();
        b.sample(2, &mut rng, &mut batch);
        assert_eq!(batch.max_others, 3);
        assert_eq!(batch.context, vec![7.0, 8.0, 9.0, 7.0, 8.0, 9.0]);
        assert_eq!(batch.next_others_count, vec![2, 2]);
        assert_eq!(&batch.next_others[..6], &[1.0, 2.0, 3.0, 4.0, 0.0, 0.0]);
        // A plain push on the same buffer is a lone herder: an empty pool.
        let mut lone = ReplayBuffer::new(2, 1, 1).with_others(3);
        lone.push(&[0.0, 0.0], &[0.0], 0.0, &[0.0, 0.0], true);
        lone.sample(1, &mut rng, &mut batch);
        assert_eq!(batch.next_others_count, vec![0]);
        assert_eq!(batch.context, vec![0.0; 3]);
    }

    #[test]
    fn returns_to_go_discount_over_simulator_steps() {
        let gamma = 0.5;
        // Three steps, the middle one an action held over two simulator steps.
        let r = returns_to_go(&[(1.0, 1), (2.0, 2), (4.0, 1)], gamma);
        assert_eq!(
            r,
            vec![1.0 + 0.5 * (2.0 + 0.25 * 4.0), 2.0 + 0.25 * 4.0, 4.0]
        );
        assert!(returns_to_go(&[], gamma).is_empty());
    }

    #[test]
    fn a_return_is_set_by_stamp_and_refused_once_its_row_is_gone() {
        let mut b = ReplayBuffer::new(1, 1, 2);
        let first = b.push(&[0.0], &[0.0], 0.0, &[0.0], false);
        let second = b.push(&[1.0], &[0.0], 0.0, &[1.0], false);
        assert_eq!(second, first + 1);
        assert!(b.return_at(0).is_nan(), "unknown until set");
        assert!(b.set_return(second, 7.0));
        assert_eq!(b.return_at(1), 7.0);
        // A third push overwrites the first row: its stamp no longer reaches anything, and the
        // new row starts unknown.
        let third = b.push(&[2.0], &[0.0], 0.0, &[2.0], false);
        assert!(!b.set_return(first, 1.0));
        assert!(b.return_at(0).is_nan());
        assert!(b.set_return(third, 3.0));
        assert_eq!(b.return_at(0), 3.0);
        assert!(!b.set_return(third + 1, 1.0), "not pushed yet");
        // A cleared buffer forgets every earlier stamp, and stamps keep counting.
        b.clear();
        assert!(!b.set_return(third, 1.0));
        let fourth = b.push(&[3.0], &[0.0], 0.0, &[3.0], true);
        assert_eq!(fourth, third + 1);
        assert!(b.set_return(fourth, -2.0));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut batch = Batch::default();
        b.sample(4, &mut rng, &mut batch);
        assert_eq!(batch.returns, vec![-2.0; 4]);
    }
}
