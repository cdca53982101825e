//! MTDDPG: DDPG (Lillicrap et al.) with the paper's shared multi-task actor and critic.
//!
//! One update, as in cleanrl's `ddpg_continuous_action.py`, but over one minibatch per task
//! whose gradients meet in the shared layers:
//!
//! 1. **Critic.** `y = r + gamma * (1 - terminated) * Q'(s', mu'(s'))` from the target networks;
//!    minimise the mean of `(Q(s, a) - y)^2` over both tasks' batches.
//! 2. **Actor** (every `policy_frequency` updates). Maximise `Q(s, mu(s))`: backpropagate
//!    `-dQ/da` through the critic's input into the actor.
//! 3. **Targets.** Polyak averaging `theta' <- tau theta + (1 - tau) theta'`.
//!
//! The critic sees the actor's features and the action (`FEATURES + 3` inputs); rewards are
//! multiplied by `reward_scale` before they enter the TD target, so Q stays O(10).

use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::network::{MlpShape, MultiTaskMlp, Tape};
use crate::nn::{Activation, Adam, AdamConfig};
use crate::replay::Batch;

/// Width of the action: a normalised 3-D velocity in the encoder's local frame.
pub const ACTION_DIM: usize = 3;

/// Network sizes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NetworkConfig {
    /// Units per hidden layer (the onboard quantized actor must fit 64 KiB of weights).
    pub hidden: usize,
    /// Shared hidden layers between the per-task input and output layers.
    pub shared_layers: usize,
}

impl Default for NetworkConfig {
    fn default() -> Self {
        NetworkConfig {
            hidden: 128,
            shared_layers: 1,
        }
    }
}

/// DDPG hyper-parameters (cleanrl's defaults where they apply).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DdpgConfig {
    /// Discount factor.
    pub gamma: f32,
    /// Soft update rate of the target networks.
    pub tau: f32,
    /// Actor learning rate.
    pub actor_learning_rate: f32,
    /// Critic learning rate.
    pub critic_learning_rate: f32,
    /// Transitions per update, split evenly over the tasks (paper: 256).
    pub batch_size: usize,
    /// Actor and target updates happen every this many critic updates.
    pub policy_frequency: u32,
    /// Multiplies rewards before they reach the critic.
    pub reward_scale: f32,
    /// Std of the Gaussian exploration noise on the normalised action.
    pub exploration_noise: f32,
}

impl Default for DdpgConfig {
    fn default() -> Self {
        DdpgConfig {
            gamma: 0.99,
            tau: 0.005,
            actor_learning_rate: 5e-5,
            critic_learning_rate: 3e-4,
            batch_size: 256,
            policy_frequency: 2,
            reward_scale: 0.1,
            exploration_noise: 0.1,
        }
    }
}

/// What one update measured.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateStats {
    /// Mean squared TD error.
    pub critic_loss: f32,
    /// `-mean Q(s, mu(s))` (0 when the actor was not updated).
    pub actor_loss: f32,
    /// Mean `Q(s, a)` on the batch.
    pub q_mean: f32,
}

/// Actor, critic, their targets and optimisers.
#[derive(Clone, Debug)]
pub struct Agent {
    /// The policy `mu(s)`: what gets exported and flown.
    pub actor: MultiTaskMlp,
    /// `Q(s, a)`.
    pub critic: MultiTaskMlp,
    /// Slow copy of the actor for TD targets.
    pub target_actor: MultiTaskMlp,
    /// Slow copy of the critic for TD targets.
    pub target_critic: MultiTaskMlp,
    /// Adam state of the actor.
    pub actor_optimizer: Adam,
    /// Adam state of the critic.
    pub critic_optimizer: Adam,
    /// Hyper-parameters.
    pub config: DdpgConfig,
    /// Critic updates done so far.
    pub updates: u64,
}

/// Row-wise `[obs | action]`.
fn concat_rows(obs: &[f32], obs_dim: usize, actions: &[f32], rows: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(rows * (obs_dim + ACTION_DIM));
    for r in 0..rows {
        out.extend_from_slice(&obs[r * obs_dim..(r + 1) * obs_dim]);
        out.extend_from_slice(&actions[r * ACTION_DIM..(r + 1) * ACTION_DIM]);
    }
    out
}

impl Agent {
    /// A fresh agent for `obs_dim` features and `tasks` tasks.
    pub fn new<R: Rng>(
        obs_dim: usize,
        tasks: usize,
        network: NetworkConfig,
        config: DdpgConfig,
        rng: &mut R,
    ) -> Agent {
        let actor = MultiTaskMlp::new(
            MlpShape {
                tasks,
                inputs: obs_dim,
                hidden: network.hidden,
                shared_layers: network.shared_layers,
                outputs: ACTION_DIM,
                output_activation: Activation::Tanh,
            },
            rng,
        );
        let critic = MultiTaskMlp::new(
            MlpShape {
                tasks,
                inputs: obs_dim + ACTION_DIM,
                hidden: network.hidden,
                shared_layers: network.shared_layers,
                outputs: 1,
                output_activation: Activation::Identity,
            },
            rng,
        );
        Agent::from_networks(actor, critic, config)
    }

    /// An agent around given networks (targets start as copies, optimisers fresh).
    pub fn from_networks(actor: MultiTaskMlp, critic: MultiTaskMlp, config: DdpgConfig) -> Agent {
        let actor_optimizer = Adam::new(
            AdamConfig {
                learning_rate: config.actor_learning_rate,
                ..AdamConfig::default()
            },
            actor.layers(),
        );
        let critic_optimizer = Adam::new(
            AdamConfig {
                learning_rate: config.critic_learning_rate,
                ..AdamConfig::default()
            },
            critic.layers(),
        );
        Agent {
            target_actor: actor.clone(),
            target_critic: critic.clone(),
            actor,
            critic,
            actor_optimizer,
            critic_optimizer,
            config,
            updates: 0,
        }
    }

    /// Feature width.
    pub fn obs_dim(&self) -> usize {
        self.actor.inputs()
    }

    /// One MTDDPG update from one batch per task (`batches[t]` feeds task `t`; empty ones are
    /// skipped).
    pub fn update(&mut self, batches: &[Batch]) -> UpdateStats {
        self.update_with_imitation(batches, &[], 0.0)
    }

    /// An MTDDPG update whose actor step also pulls towards demonstrated actions
    /// (`demos[t]`, TD3+BC style): the actor minimises
    /// `-Q(s, mu(s)) / mean|Q| + imitation_weight * |mu(s_demo) - a_demo|^2`.
    /// With `imitation_weight = 0` this is plain DDPG (no Q normalisation).
    pub fn update_with_imitation(
        &mut self,
        batches: &[Batch],
        demos: &[Batch],
        imitation_weight: f32,
    ) -> UpdateStats {
        let c = self.config;
        let mut stats = self.critic_step(batches);
        if stats.critic_loss.is_nan() {
            return stats;
        }
        // 2. Actor and 3. targets, every `policy_frequency` critic updates.
        if self
            .updates
            .is_multiple_of(u64::from(c.policy_frequency.max(1)))
        {
            stats.actor_loss = self.actor_step(batches, demos, imitation_weight);
            self.target_actor.soft_update_from(&self.actor, c.tau);
            self.target_critic.soft_update_from(&self.critic, c.tau);
        }
        stats
    }

    /// Policy evaluation only: a critic step towards the target actor's TD target and a soft
    /// update of the target critic; the actor stays put (warm-start critic pretraining).
    pub fn evaluate_policy_step(&mut self, batches: &[Batch]) -> UpdateStats {
        let stats = self.critic_step(batches);
        self.target_critic
            .soft_update_from(&self.critic, self.config.tau);
        stats
    }

    /// 1. Critic: regress Q(s, a) onto the TD target, both tasks into one gradient.
    fn critic_step(&mut self, batches: &[Batch]) -> UpdateStats {
        let obs_dim = self.obs_dim();
        let total: usize = batches.iter().map(|b| b.size).sum();
        if total == 0 {
            return UpdateStats {
                critic_loss: f32::NAN,
                ..UpdateStats::default()
            };
        }
        let c = self.config;
        let mut stats = UpdateStats::default();
        let mut critic_grads = self.critic.zeros_like();
        let mut tape = Tape::default();
        for (task, b) in batches.iter().enumerate().filter(|(_, b)| b.size > 0) {
            self.target_actor
                .forward(task, &b.next_obs, b.size, &mut tape);
            let next_actions = tape.output().to_vec();
            let next_input = concat_rows(&b.next_obs, obs_dim, &next_actions, b.size);
            self.target_critic
                .forward(task, &next_input, b.size, &mut tape);
            let targets: Vec<f32> = (0..b.size)
                .map(|r| {
                    c.reward_scale * b.rewards[r] + c.gamma * b.continues[r] * tape.output()[r]
                })
                .collect();
            let input = concat_rows(&b.obs, obs_dim, &b.actions, b.size);
            self.critic.forward(task, &input, b.size, &mut tape);
            let q = tape.output();
            let d_q: Vec<f32> = q
                .iter()
                .zip(&targets)
                .map(|(q, y)| 2.0 * (q - y) / total as f32)
                .collect();
            stats.critic_loss += q
                .iter()
                .zip(&targets)
                .map(|(q, y)| (q - y) * (q - y))
                .sum::<f32>()
                / total as f32;
            stats.q_mean += q.iter().sum::<f32>() / total as f32;
            self.critic
                .backward(&tape, &d_q, Some(&mut critic_grads), false);
        }
        self.critic_optimizer
            .update(self.critic.layers_mut(), critic_grads.layers());
        self.updates += 1;
        stats
    }

    /// Gradient ascent on `mean Q(s, mu(s))` (plus the imitation pull); returns `-mean Q`.
    fn actor_step(&mut self, batches: &[Batch], demos: &[Batch], imitation_weight: f32) -> f32 {
        let obs_dim = self.obs_dim();
        let total: usize = batches.iter().map(|b| b.size).sum();
        let mut actor_grads = self.actor.zeros_like();
        let mut actor_tape = Tape::default();
        let mut tape = Tape::default();
        let mut loss = 0.0;
        let mut q_tapes = Vec::new();
        let mut mean_abs_q = 0.0;
        for (task, b) in batches.iter().enumerate().filter(|(_, b)| b.size > 0) {
            self.actor.forward(task, &b.obs, b.size, &mut actor_tape);
            let input = concat_rows(&b.obs, obs_dim, actor_tape.output(), b.size);
            self.critic.forward(task, &input, b.size, &mut tape);
            loss -= tape.output().iter().sum::<f32>() / total as f32;
            mean_abs_q += tape.output().iter().map(|q| q.abs()).sum::<f32>() / total as f32;
            q_tapes.push((task, actor_tape.clone(), tape.clone()));
        }
        // TD3+BC's normalisation keeps the imitation weight meaningful whatever Q's scale.
        let q_scale = if imitation_weight > 0.0 {
            1.0 / mean_abs_q.max(1e-3)
        } else {
            1.0
        };
        for (_, a_tape, q_tape) in &q_tapes {
            let d_q = vec![-q_scale / total as f32; q_tape.batch];
            let d_input = self
                .critic
                .backward(q_tape, &d_q, None, true)
                .unwrap_or_default();
            let stride = obs_dim + ACTION_DIM;
            let d_action: Vec<f32> = d_input
                .chunks_exact(stride)
                .flat_map(|row| row[obs_dim..].iter().copied())
                .collect();
            self.actor
                .backward(a_tape, &d_action, Some(&mut actor_grads), false);
        }
        if imitation_weight > 0.0 {
            let demo_total: usize = demos.iter().map(|b| b.size * ACTION_DIM).sum();
            for (task, b) in demos.iter().enumerate().filter(|(_, b)| b.size > 0) {
                self.actor.forward(task, &b.obs, b.size, &mut actor_tape);
                let d: Vec<f32> = actor_tape
                    .output()
                    .iter()
                    .zip(&b.actions)
                    .map(|(y, t)| imitation_weight * 2.0 * (y - t) / demo_total as f32)
                    .collect();
                self.actor
                    .backward(&actor_tape, &d, Some(&mut actor_grads), false);
            }
        }
        self.actor_optimizer
            .update(self.actor.layers_mut(), actor_grads.layers());
        loss
    }

    /// Behaviour cloning step: minimise the mean of `|mu(s) - a*|^2` over one batch per task of
    /// `(obs, expert action)`; returns the loss. Uses the actor's optimiser.
    pub fn imitation_step(&mut self, batches: &[Batch]) -> f32 {
        let total: usize = batches.iter().map(|b| b.size * ACTION_DIM).sum();
        if total == 0 {
            return 0.0;
        }
        let mut grads = self.actor.zeros_like();
        let mut tape = Tape::default();
        let mut loss = 0.0;
        for (task, b) in batches.iter().enumerate().filter(|(_, b)| b.size > 0) {
            self.actor.forward(task, &b.obs, b.size, &mut tape);
            let d: Vec<f32> = tape
                .output()
                .iter()
                .zip(&b.actions)
                .map(|(y, t)| {
                    loss += (y - t) * (y - t) / total as f32;
                    2.0 * (y - t) / total as f32
                })
                .collect();
            self.actor.backward(&tape, &d, Some(&mut grads), false);
        }
        self.actor_optimizer
            .update(self.actor.layers_mut(), grads.layers());
        loss
    }

    /// Copies the online networks into the targets (after a warm start).
    pub fn sync_targets(&mut self) {
        self.target_actor = self.actor.clone();
        self.target_critic = self.critic.clone();
    }

    /// The deterministic action for one observation.
    pub fn act(&self, task: usize, obs: &[f32]) -> [f32; ACTION_DIM] {
        let y = self.actor.predict(task, obs);
        [y[0], y[1], y[2]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::replay::ReplayBuffer;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// A one-step bandit per task: reward = -|a - a*_task|^2, episodes end at once. DDPG must
    /// find each task's best action, which differs between the tasks.
    #[test]
    fn learns_a_different_best_action_per_task() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let config = DdpgConfig {
            batch_size: 64,
            reward_scale: 1.0,
            actor_learning_rate: 2e-3,
            critic_learning_rate: 3e-3,
            policy_frequency: 1,
            ..DdpgConfig::default()
        };
        let network = NetworkConfig {
            hidden: 64,
            shared_layers: 1,
        };
        let mut agent = Agent::new(2, 2, network, config, &mut rng);
        let best = [[0.5_f32, -0.3, 0.0], [-0.6, 0.2, 0.4]];
        let mut buffers: Vec<ReplayBuffer> =
            (0..2).map(|_| ReplayBuffer::new(2, 3, 4096)).collect();
        for (task, buffer) in buffers.iter_mut().enumerate() {
            for _ in 0..2000 {
                let obs = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
                let a: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
                let r = -(0..3).map(|k| (a[k] - best[task][k]).powi(2)).sum::<f32>();
                buffer.push(&obs, &a, r, &obs, true);
            }
        }
        let mut batches = vec![Batch::default(); 2];
        for _ in 0..2000 {
            for (b, buf) in batches.iter_mut().zip(&buffers) {
                buf.sample(32, &mut rng, b);
            }
            agent.update(&batches);
        }
        for (task, target) in best.iter().enumerate() {
            let a = agent.act(task, &[0.1, -0.2]);
            let err: f32 = (0..3)
                .map(|k| (a[k] - target[k]).powi(2))
                .sum::<f32>()
                .sqrt();
            assert!(err < 0.15, "task {task}: {a:?} vs {target:?}");
        }
    }

    #[test]
    fn imitation_fits_a_linear_expert() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let mut agent = Agent::new(
            3,
            2,
            NetworkConfig {
                hidden: 32,
                shared_layers: 1,
            },
            DdpgConfig {
                actor_learning_rate: 3e-3,
                ..DdpgConfig::default()
            },
            &mut rng,
        );
        let expert = |task: usize, o: &[f32]| {
            let s = if task == 0 { 0.5 } else { -0.5 };
            [s * o[0], 0.3 * o[1] - 0.2 * o[2], s * o[2]]
        };
        let mut batches = vec![Batch::default(); 2];
        let mut last = f32::MAX;
        for _ in 0..800 {
            for (task, b) in batches.iter_mut().enumerate() {
                *b = Batch::default();
                b.size = 64;
                for _ in 0..64 {
                    let o: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
                    b.obs.extend_from_slice(&o);
                    b.actions.extend_from_slice(&expert(task, &o));
                }
            }
            last = agent.imitation_step(&batches);
        }
        assert!(last < 2e-3, "imitation loss {last}");
    }
}
