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
//!
//! TD3 (Fujimoto et al. 2018), each part optional in [`DdpgConfig`]: twin critics whose
//! smaller target value is the TD target (clipped double-Q), Gaussian smoothing noise on the
//! target actor's action, and the delayed actor (`policy_frequency`). With n-step returns the
//! replay's `continues` already holds `gamma^(k-1) (1 - terminated)` for a `k`-step
//! transition, so the target is `r_k + gamma continues Q'` either way.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
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
    /// Std of the exploration noise on the normalised action (at the start of the run; see
    /// [`DdpgConfig::exploration_noise_final`]).
    pub exploration_noise: f32,
    /// Where the exploration noise ends: from `exploration_noise_decay_from` to
    /// `exploration_noise_decay_to` (fractions of `training.env_steps`) the std goes linearly
    /// from `exploration_noise` to this, and stays there. `None` (the default): constant.
    pub exploration_noise_final: Option<f32>,
    /// Run progress (a fraction of `training.env_steps`) at which the noise starts to fall.
    pub exploration_noise_decay_from: f32,
    /// Run progress at which the noise reaches `exploration_noise_final`.
    pub exploration_noise_decay_to: f32,
    /// How exploration noise is drawn.
    pub exploration: Exploration,
    /// Mean reversion per step of the Ornstein-Uhlenbeck noise (its stationary std is
    /// `exploration_noise`).
    pub ou_theta: f32,
    /// TD3: a second critic; the TD target takes the smaller of the two target critics.
    pub twin_critics: bool,
    /// With twin critics, the TD target's next value is `w min(Q1', Q2') + (1 - w) mean(Q1',
    /// Q2')` (the weighted double Q of WD3, He and Hou 2020): 1 (the default) is TD3's clipped
    /// double Q, 0 the plain mean. The min under-estimates most where the critics disagree,
    /// which is where the replay is thin; a weight below 1 softens that pessimism.
    pub twin_min_weight: f32,
    /// TD3 target policy smoothing: std of the Gaussian noise added to the target actor's
    /// action (0: none).
    pub target_noise: f32,
    /// The smoothing noise is clipped to plus or minus this.
    pub target_noise_clip: f32,
    /// Returns over this many steps (1: one-step TD), cut at terminals and bootstrapped at
    /// truncation.
    pub n_step: usize,
    /// Planar herding: the vertical action is held at zero (the drones keep the altitude they
    /// start at), in exploration, in the stored actions and in the TD target.
    pub planar: bool,
    /// A centralised critic for training: `Q(o_h, a_h, pool_j o_j, pool_j a_j)` sees, beside
    /// the herder's own features and action, the mean features and mean action of the other
    /// herders ([`crate::replay::pool_others`]); in the TD target the others' next actions come
    /// from the target actor. The actor stays decentralised: it flies on its own features.
    pub centralised_critic: bool,
    /// The centralised critic pools at most this many other herders (the nearest).
    pub critic_max_others: usize,
    /// Self-imitation (Oh et al. 2018, for a deterministic actor): the actor also minimises
    /// `weight * mean over the batch of [R > Q(s, mu(s))] |mu(s) - a|^2`, where `a` is the
    /// action the herder took and `R` the discounted return it went on to collect to the end of
    /// its episode (`reward_scale` applied, as Q has it). It pulls the actor towards its own
    /// past actions that did better than the critic expects of the actor now, which the
    /// critic's gradient alone may not resolve. Only transitions of episodes that ended
    /// (success or a target leaving) have a return; truncated ones never pull. 0 (the
    /// default): off, and the update is plain TD3.
    pub self_imitation: f32,
    /// Which ended episodes give their transitions a return for self-imitation.
    pub self_imitation_episodes: SelfImitationEpisodes,
    /// An advantage-decomposed critic (deep advantage updating: Tallec, Blier and Ollivier,
    /// *Making Deep Q-learning Methods Robust to Time Discretization*, 2019), with this scale
    /// `k`: each critic is `Q(s, a) = V(s) + k (A(s, a) - A(s, mu(s)))`, a state-value network
    /// `V` beside an advantage network `A` (the critic's usual network, fed the features and the
    /// action). The TD target is `reward_scale r + gamma V'(s')` (with twins, the smaller of the
    /// two target values, mixed by `twin_min_weight`): `Q(s', mu(s')) = V(s')`, so no target
    /// action and no target smoothing. The actor climbs `A(s, mu(s))`. At a fine time step one
    /// action changes the return by a hundredth of its value, and a single network fitting
    /// `Q(s, a)` learns the action's part inside the errors of the state's; here `A` holds only
    /// the action's part, on its own scale (`k` about the size of one step's advantage over the
    /// value). Not with the centralised critic. 0 (the default): off, a plain critic.
    pub advantage_scale: f32,
}

/// Which ended episodes self-imitation may learn from ([`DdpgConfig::self_imitation_episodes`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SelfImitationEpisodes {
    /// Every episode that ended (a success, or a target leaving); only the row test
    /// `R > Q(s, mu(s))` chooses.
    #[default]
    Ended,
    /// Only successes that took fewer steps than the median of the last
    /// [`FASTER_WINDOW`] successes of the same task, flock size and team size (every success
    /// while fewer than [`FASTER_MIN`] are known). The row test still applies. Twin critics
    /// read low, so `R > Q` alone passes most rows of any ended episode; this keeps the pull
    /// to episodes that beat the actor's recent ones on the measure the aim is about.
    FasterThanMedian,
}

/// Successes per scenario kept for [`SelfImitationEpisodes::FasterThanMedian`]'s median.
pub const FASTER_WINDOW: usize = 32;
/// Below this many known successes of a scenario, every success counts as faster.
pub const FASTER_MIN: usize = 8;

/// How exploration noise is drawn.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Exploration {
    /// Independent Gaussian noise every step.
    #[default]
    Gaussian,
    /// Temporally correlated Ornstein-Uhlenbeck noise, one process per herder.
    OrnsteinUhlenbeck,
    /// Parameter-space noise (Plappert et al., *Parameter Space Noise for Exploration*, 2018):
    /// each episode flies the actor plus `scale` times a standard normal direction in its
    /// parameters, drawn when the episode starts and kept to its end, with no noise on the
    /// actions. The exploration then depends on the state and holds for a whole episode: a
    /// perturbed actor that comes nearer the targets does so wherever they are, step after
    /// step, which action noise of any correlation time averages away. The scale adapts, per
    /// task, so that the perturbed actor's actions differ from the actor's by the configured
    /// noise std (RMS over recent observations, [`PARAMETER_NOISE_ADAPT`]).
    Parameter,
}

/// Parameter-space noise: the scale's first value, per task (on parameters initialised at
/// about 0.1).
pub const PARAMETER_NOISE_INITIAL_SCALE: f32 = 0.05;
/// Parameter-space noise: at each draw the scale is divided by this when the new perturbed
/// actor's actions are further than the wanted distance from the actor's, multiplied by it
/// otherwise (Plappert et al. use 1.01 every 50 steps; one draw an episode needs a larger
/// step).
pub const PARAMETER_NOISE_ADAPT: f32 = 1.05;
/// Parameter-space noise: the distance is measured on at most this many of the task's most
/// recent observations.
pub const PARAMETER_NOISE_ROWS: usize = 256;

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
            exploration_noise_final: None,
            exploration_noise_decay_from: 0.0,
            exploration_noise_decay_to: 1.0,
            exploration: Exploration::Gaussian,
            ou_theta: 0.15,
            twin_critics: false,
            twin_min_weight: 1.0,
            target_noise: 0.0,
            target_noise_clip: 0.5,
            n_step: 1,
            planar: false,
            centralised_critic: false,
            critic_max_others: 7,
            self_imitation: 0.0,
            self_imitation_episodes: SelfImitationEpisodes::Ended,
            advantage_scale: 0.0,
        }
    }
}

impl DdpgConfig {
    /// The exploration noise's std at `progress` (env steps so far over the run's total):
    /// `exploration_noise` until `exploration_noise_decay_from`, then linearly down (or up) to
    /// `exploration_noise_final` at `exploration_noise_decay_to`, and that from there on.
    pub fn exploration_noise_at(&self, progress: f64) -> f32 {
        let Some(last) = self.exploration_noise_final else {
            return self.exploration_noise;
        };
        let from = f64::from(self.exploration_noise_decay_from);
        let to = f64::from(self.exploration_noise_decay_to);
        let share = if to > from {
            ((progress - from) / (to - from)).clamp(0.0, 1.0)
        } else if progress >= to {
            1.0
        } else {
            0.0
        };
        let first = f64::from(self.exploration_noise);
        (first + share * (f64::from(last) - first)) as f32
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
    /// The share of the actor step's rows whose return beat `Q(s, mu(s))` (the rows that
    /// self-imitated; 0 without self-imitation); `None` when this update did not step the
    /// actor (`policy_frequency`).
    pub self_imitation_share: Option<f32>,
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
    /// TD3's second critic, when [`DdpgConfig::twin_critics`].
    pub twin: Option<Box<TwinCritic>>,
    /// Draws the target smoothing noise; seeded, so a run is reproducible.
    pub noise_rng: ChaCha8Rng,
    /// With [`DdpgConfig::advantage_scale`], the state values `V`: the first pairs with
    /// `critic` (then an advantage network), the second with the twin's. Empty otherwise.
    pub values: Vec<StateValue>,
}

/// The state-value half of an advantage-decomposed critic ([`DdpgConfig::advantage_scale`]).
#[derive(Clone, Debug)]
pub struct StateValue {
    /// `V(s)`: the features in, one number out.
    pub value: MultiTaskMlp,
    /// Slow copy of it, for the TD target.
    pub target: MultiTaskMlp,
    /// Its Adam state.
    pub optimizer: Adam,
}

impl StateValue {
    /// A state value around `value` (target a copy, optimiser fresh).
    pub fn new(value: MultiTaskMlp, learning_rate: f32) -> Self {
        let optimizer = fresh_adam(&value, learning_rate);
        Self {
            target: value.clone(),
            value,
            optimizer,
        }
    }
}

/// A fresh Adam state for `net`'s layers.
fn fresh_adam(net: &MultiTaskMlp, learning_rate: f32) -> Adam {
    Adam::new(
        AdamConfig {
            learning_rate,
            ..AdamConfig::default()
        },
        net.layers(),
    )
}

/// TD3's second critic with its target and optimiser.
#[derive(Clone, Debug)]
pub struct TwinCritic {
    /// `Q2(s, a)`.
    pub critic: MultiTaskMlp,
    /// Slow copy of it.
    pub target: MultiTaskMlp,
    /// Its Adam state.
    pub optimizer: Adam,
}

impl TwinCritic {
    /// A twin around `critic` (target a copy, optimiser fresh).
    pub fn new(critic: MultiTaskMlp, learning_rate: f32) -> Self {
        let optimizer = fresh_adam(&critic, learning_rate);
        Self {
            target: critic.clone(),
            critic,
            optimizer,
        }
    }
}

/// One task's rows for the advantage-decomposed critic step.
struct AdvantageRows<'a> {
    task: usize,
    batch: &'a Batch,
    /// `reward_scale r + gamma V'(s')`.
    targets: Vec<f32>,
    /// The critic inputs `(s, a)` of every row, then `(s, mu(s))` of every row.
    stacked: Vec<f32>,
}

/// What one state value and advantage pair learned from a step.
struct PairGradients {
    value: MultiTaskMlp,
    advantage: MultiTaskMlp,
    loss: f32,
    q_mean: f32,
}

/// Seed of the target smoothing noise after `updates` updates.
const NOISE_SEED: u64 = 0x7D3_5EED;

/// What [`self_imitation_pull`] needs besides the rows.
#[derive(Clone, Copy, Debug)]
pub struct SelfImitation {
    /// [`DdpgConfig::self_imitation`].
    pub weight: f32,
    /// [`DdpgConfig::reward_scale`]: returns are stored in reward units, Q in scaled ones.
    pub reward_scale: f32,
    /// The vertical component is left alone (the planar pull owns it).
    pub planar: bool,
    /// Rows of the whole actor step (the mean's denominator).
    pub rows: usize,
}

/// Adds the self-imitation gradient to `d_action` (one row of [`ACTION_DIM`] per transition):
/// `weight * 2 (mu(s) - a) / rows` on every row whose stored return `R` (reward units, NaN
/// where unknown) beats the actor's value there, `reward_scale R > Q(s, mu(s))`. Returns how
/// many rows pulled.
pub fn self_imitation_pull(
    sil: &SelfImitation,
    q_of_actor: &[f32],
    returns: &[f32],
    actor_actions: &[f32],
    taken_actions: &[f32],
    d_action: &mut [f32],
) -> usize {
    let dims = if sil.planar { 2 } else { ACTION_DIM };
    let scale = sil.weight * 2.0 / sil.rows.max(1) as f32;
    let mut pulled = 0;
    for (r, (&q, &ret)) in q_of_actor.iter().zip(returns).enumerate() {
        // NaN: no return known, nothing to imitate.
        if ret.is_nan() || sil.reward_scale * ret <= q {
            continue;
        }
        pulled += 1;
        let row = r * ACTION_DIM..r * ACTION_DIM + dims;
        for ((d, mu), a) in d_action[row.clone()]
            .iter_mut()
            .zip(&actor_actions[row.clone()])
            .zip(&taken_actions[row])
        {
            *d += scale * (mu - a);
        }
    }
    pulled
}

/// Row-wise `[obs | action]`.
#[cfg(test)]
fn concat_rows(obs: &[f32], obs_dim: usize, actions: &[f32], rows: usize) -> Vec<f32> {
    critic_rows(obs, obs_dim, actions, &[], 0, rows)
}

/// Row-wise critic input `[obs | action | context]` (`context_dim` 0: no context; a context
/// shorter than `rows * context_dim`, as in a batch from a plain buffer, reads as zeros).
fn critic_rows(
    obs: &[f32],
    obs_dim: usize,
    actions: &[f32],
    context: &[f32],
    context_dim: usize,
    rows: usize,
) -> Vec<f32> {
    let mut out = Vec::with_capacity(rows * (obs_dim + ACTION_DIM + context_dim));
    let has_context = context.len() >= rows * context_dim;
    for r in 0..rows {
        out.extend_from_slice(&obs[r * obs_dim..(r + 1) * obs_dim]);
        out.extend_from_slice(&actions[r * ACTION_DIM..(r + 1) * ACTION_DIM]);
        if has_context {
            out.extend_from_slice(&context[r * context_dim..(r + 1) * context_dim]);
        } else {
            out.extend(std::iter::repeat_n(0.0, context_dim));
        }
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
        let context = if config.centralised_critic {
            obs_dim + ACTION_DIM
        } else {
            0
        };
        let critic_shape = MlpShape {
            tasks,
            inputs: obs_dim + ACTION_DIM + context,
            hidden: network.hidden,
            shared_layers: network.shared_layers,
            outputs: 1,
            output_activation: Activation::Identity,
        };
        let critic = MultiTaskMlp::new(critic_shape, rng);
        let mut agent = Agent::from_networks(actor, critic, config);
        if config.twin_critics {
            let second = MultiTaskMlp::new(critic_shape, rng);
            agent.twin = Some(Box::new(TwinCritic::new(
                second,
                config.critic_learning_rate,
            )));
        }
        if config.advantage_scale > 0.0 {
            // Drawn after everything else, so that without it a seed draws the same networks.
            let value_shape = MlpShape {
                inputs: obs_dim,
                ..critic_shape
            };
            for _ in 0..1 + usize::from(config.twin_critics) {
                agent.values.push(StateValue::new(
                    MultiTaskMlp::new(value_shape, rng),
                    config.critic_learning_rate,
                ));
            }
        }
        agent
    }

    /// An agent around given networks (targets start as copies, optimisers fresh).
    pub fn from_networks(actor: MultiTaskMlp, critic: MultiTaskMlp, config: DdpgConfig) -> Agent {
        let actor_optimizer = fresh_adam(&actor, config.actor_learning_rate);
        let critic_optimizer = fresh_adam(&critic, config.critic_learning_rate);
        Agent {
            target_actor: actor.clone(),
            target_critic: critic.clone(),
            actor,
            critic,
            actor_optimizer,
            critic_optimizer,
            config,
            updates: 0,
            twin: None,
            noise_rng: ChaCha8Rng::seed_from_u64(NOISE_SEED),
            values: Vec::new(),
        }
    }

    /// Re-seed the target smoothing noise from the update count, so that a run resumed from a
    /// checkpoint is reproducible from that checkpoint.
    pub fn reseed_noise(&mut self) {
        self.noise_rng = ChaCha8Rng::seed_from_u64(NOISE_SEED ^ self.updates);
    }

    /// Starts `task` over (`training.task_reset`): its own input and output layers of the
    /// actor and of each critic are drawn afresh, their targets copied from them and their Adam
    /// moments cleared. The shared layers and the other task keep everything they learned, and
    /// the replay buffers are untouched (off-policy data stays valid).
    pub fn reset_task<R: Rng>(&mut self, task: usize, rng: &mut R) {
        for index in self.actor.reinit_task(task, rng) {
            self.actor_optimizer.clear_layer(index);
        }
        self.target_actor.copy_task_from(&self.actor, task);
        for index in self.critic.reinit_task(task, rng) {
            self.critic_optimizer.clear_layer(index);
        }
        self.target_critic.copy_task_from(&self.critic, task);
        if let Some(twin) = self.twin.as_deref_mut() {
            for index in twin.critic.reinit_task(task, rng) {
                twin.optimizer.clear_layer(index);
            }
            twin.target.copy_task_from(&twin.critic, task);
        }
        for v in &mut self.values {
            for index in v.value.reinit_task(task, rng) {
                v.optimizer.clear_layer(index);
            }
            v.target.copy_task_from(&v.value, task);
        }
    }

    /// Feature width.
    pub fn obs_dim(&self) -> usize {
        self.actor.inputs()
    }

    /// Width of the centralised critic's pooled context (0: the critic sees one herder).
    pub fn context_dim(&self) -> usize {
        self.critic
            .inputs()
            .saturating_sub(self.obs_dim() + ACTION_DIM)
    }

    /// The target actor's action for `rows` observations of `task`: smoothed by TD3's clipped
    /// noise when configured, its vertical part zero when planar.
    fn target_actions(&mut self, task: usize, obs: &[f32], rows: usize) -> Vec<f32> {
        let c = self.config;
        let mut tape = Tape::default();
        self.target_actor.forward(task, obs, rows, &mut tape);
        let mut actions = tape.output().to_vec();
        if c.target_noise > 0.0
            && let Ok(noise) = Normal::new(0.0_f32, c.target_noise)
        {
            for a in &mut actions {
                let n = noise
                    .sample(&mut self.noise_rng)
                    .clamp(-c.target_noise_clip, c.target_noise_clip);
                *a = (*a + n).clamp(-1.0, 1.0);
            }
        }
        if c.planar {
            actions
                .chunks_exact_mut(ACTION_DIM)
                .for_each(|a| a[2] = 0.0);
        }
        actions
    }

    /// The centralised critic's context at `s'`: per transition, the other herders' next
    /// observations and the target actor's actions for them, pooled.
    fn next_context(&mut self, task: usize, b: &Batch) -> Vec<f32> {
        let obs_dim = self.obs_dim();
        let width = obs_dim + ACTION_DIM;
        let mut out = vec![0.0; b.size * width];
        if b.max_others == 0 || b.next_others_count.len() < b.size {
            return out;
        }
        // One forward over every real row of every transition.
        let mut rows = Vec::new();
        let stride = b.max_others * obs_dim;
        for r in 0..b.size {
            let k = usize::from(b.next_others_count[r]);
            rows.extend_from_slice(&b.next_others[r * stride..r * stride + k * obs_dim]);
        }
        let total = rows.len() / obs_dim.max(1);
        if total == 0 {
            return out;
        }
        let actions = self.target_actions(task, &rows, total);
        let mut at = 0;
        for r in 0..b.size {
            let k = usize::from(b.next_others_count[r]);
            let pooled = crate::replay::pool_others(
                &rows[at * obs_dim..(at + k) * obs_dim],
                &actions[at * ACTION_DIM..(at + k) * ACTION_DIM],
                obs_dim,
                ACTION_DIM,
            );
            out[r * width..(r + 1) * width].copy_from_slice(&pooled);
            at += k;
        }
        out
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
            let (actor_loss, share) = self.actor_step(batches, demos, imitation_weight);
            stats.actor_loss = actor_loss;
            stats.self_imitation_share = Some(share);
            self.target_actor.soft_update_from(&self.actor, c.tau);
            self.target_critic.soft_update_from(&self.critic, c.tau);
            if let Some(twin) = self.twin.as_mut() {
                twin.target.soft_update_from(&twin.critic, c.tau);
            }
            for v in &mut self.values {
                v.target.soft_update_from(&v.value, c.tau);
            }
        }
        stats
    }

    /// Policy evaluation only: a critic step towards the target actor's TD target and a soft
    /// update of the target critic; the actor stays put (warm-start critic pretraining).
    pub fn evaluate_policy_step(&mut self, batches: &[Batch]) -> UpdateStats {
        let stats = self.critic_step(batches);
        self.target_critic
            .soft_update_from(&self.critic, self.config.tau);
        if let Some(twin) = self.twin.as_mut() {
            twin.target.soft_update_from(&twin.critic, self.config.tau);
        }
        for v in &mut self.values {
            v.target.soft_update_from(&v.value, self.config.tau);
        }
        stats
    }

    /// The TD targets of one task's batch: `reward_scale r + gamma continues Q'(s', a')` with
    /// `a'` the target actor's action (smoothed by TD3's clipped noise when configured, its
    /// vertical part zero when planar) and `Q'` the target critic, or with TD3's twins the
    /// smaller of the two target critics, mixed with their mean by
    /// [`DdpgConfig::twin_min_weight`].
    pub fn td_targets(&mut self, task: usize, b: &Batch) -> Vec<f32> {
        let c = self.config;
        if !self.values.is_empty() {
            return self.value_targets(task, b);
        }
        let obs_dim = self.obs_dim();
        let context_dim = self.context_dim();
        let next_actions = self.target_actions(task, &b.next_obs, b.size);
        let next_context = if context_dim > 0 {
            self.next_context(task, b)
        } else {
            Vec::new()
        };
        let next_input = critic_rows(
            &b.next_obs,
            obs_dim,
            &next_actions,
            &next_context,
            context_dim,
            b.size,
        );
        let mut tape = Tape::default();
        self.target_critic
            .forward(task, &next_input, b.size, &mut tape);
        let mut next_q = tape.output().to_vec();
        if let Some(twin) = &self.twin {
            twin.target.forward(task, &next_input, b.size, &mut tape);
            let w = c.twin_min_weight;
            for (q, q2) in next_q.iter_mut().zip(tape.output()) {
                *q = w * q.min(*q2) + (1.0 - w) * 0.5 * (*q + *q2);
            }
        }
        (0..b.size)
            .map(|r| c.reward_scale * b.rewards[r] + c.gamma * b.continues[r] * next_q[r])
            .collect()
    }

    /// The TD targets of an advantage-decomposed critic ([`DdpgConfig::advantage_scale`]):
    /// `reward_scale r + gamma continues V'(s')`, with two state values the smaller of their
    /// targets mixed with their mean by [`DdpgConfig::twin_min_weight`].
    fn value_targets(&self, task: usize, b: &Batch) -> Vec<f32> {
        let c = self.config;
        let next_value = |index: usize| {
            self.values.get(index).map(|v| {
                let mut tape = Tape::default();
                v.target.forward(task, &b.next_obs, b.size, &mut tape);
                tape.output().to_vec()
            })
        };
        // The two target values side by side when the pool has a second thread.
        let next_v = match rayon::join(|| next_value(0), || next_value(1)) {
            (Some(first), Some(second)) => {
                let w = c.twin_min_weight;
                first
                    .iter()
                    .zip(&second)
                    .map(|(a, b)| w * a.min(*b) + (1.0 - w) * 0.5 * (a + b))
                    .collect()
            }
            (Some(first), None) => first,
            _ => vec![0.0; b.size],
        };
        (0..b.size)
            .map(|r| c.reward_scale * b.rewards[r] + c.gamma * b.continues[r] * next_v[r])
            .collect()
    }

    /// The current actor's actions for `rows` observations of `task`, the vertical part zero
    /// when planar.
    fn policy_actions(&self, task: usize, obs: &[f32], rows: usize) -> Vec<f32> {
        let mut tape = Tape::default();
        self.actor.forward(task, obs, rows, &mut tape);
        let mut actions = tape.output().to_vec();
        if self.config.planar {
            actions
                .chunks_exact_mut(ACTION_DIM)
                .for_each(|a| a[2] = 0.0);
        }
        actions
    }

    /// The advantage network paired with state value `index`: the critic, then the twin's.
    fn advantage_net(&self, index: usize) -> Option<&MultiTaskMlp> {
        match index {
            0 => Some(&self.critic),
            1 => self.twin.as_ref().map(|t| &t.critic),
            _ => None,
        }
    }

    /// 1'. Critic of [`DdpgConfig::advantage_scale`]: regress each `V(s) + k (A(s, a) -
    ///    A(s, mu(s)))` onto the TD target, both tasks into one gradient; the actor is held.
    fn advantage_critic_step(&mut self, batches: &[Batch]) -> UpdateStats {
        let obs_dim = self.obs_dim();
        let total: usize = batches.iter().map(|b| b.size).sum();
        if total == 0 {
            return UpdateStats {
                critic_loss: f32::NAN,
                ..UpdateStats::default()
            };
        }
        // Per task: the targets and, stacked, the rows (s, a) then (s, mu(s)).
        let prepared: Vec<AdvantageRows> = batches
            .iter()
            .enumerate()
            .filter(|(_, b)| b.size > 0)
            .map(|(task, b)| {
                let (mu, targets) = rayon::join(
                    || self.policy_actions(task, &b.obs, b.size),
                    || self.value_targets(task, b),
                );
                let mut stacked = critic_rows(&b.obs, obs_dim, &b.actions, &[], 0, b.size);
                stacked.extend(critic_rows(&b.obs, obs_dim, &mu, &[], 0, b.size));
                AdvantageRows {
                    task,
                    batch: b,
                    targets,
                    stacked,
                }
            })
            .collect();
        // The pairs are independent until their optimiser steps: the twin's runs beside the
        // first when the pool has a second thread.
        let (first, second) = rayon::join(
            || self.advantage_pair_gradients(0, &prepared, total),
            || self.advantage_pair_gradients(1, &prepared, total),
        );
        let mut stats = UpdateStats::default();
        for (i, pair) in [first, second].into_iter().enumerate() {
            let Some(pair) = pair else {
                continue;
            };
            if i == 0 {
                stats.critic_loss = pair.loss;
                stats.q_mean = pair.q_mean;
                self.critic_optimizer
                    .update(self.critic.layers_mut(), pair.advantage.layers());
            } else if let Some(twin) = self.twin.as_mut() {
                twin.optimizer
                    .update(twin.critic.layers_mut(), pair.advantage.layers());
            }
            let v = &mut self.values[i];
            v.optimizer
                .update(v.value.layers_mut(), pair.value.layers());
        }
        self.updates += 1;
        stats
    }

    /// Gradients of state value `index` and its advantage network on the prepared rows:
    /// `Q = V(s) + k (A(s, a) - A(s, mu(s)))` regressed onto the targets (`None` when there
    /// is no such pair).
    fn advantage_pair_gradients(
        &self,
        index: usize,
        prepared: &[AdvantageRows<'_>],
        total: usize,
    ) -> Option<PairGradients> {
        let k = self.config.advantage_scale;
        let value = &self.values.get(index)?.value;
        let advantage = self.advantage_net(index)?;
        let mut out = PairGradients {
            value: value.zeros_like(),
            advantage: advantage.zeros_like(),
            loss: 0.0,
            q_mean: 0.0,
        };
        let (mut v_tape, mut a_tape) = (Tape::default(), Tape::default());
        for rows in prepared {
            let (task, size) = (rows.task, rows.batch.size);
            value.forward(task, &rows.batch.obs, size, &mut v_tape);
            advantage.forward(task, &rows.stacked, 2 * size, &mut a_tape);
            let (taken, own) = a_tape.output().split_at(size);
            let q: Vec<f32> = (0..size)
                .map(|r| v_tape.output()[r] + k * (taken[r] - own[r]))
                .collect();
            let d_q: Vec<f32> = q
                .iter()
                .zip(&rows.targets)
                .map(|(q, y)| 2.0 * (q - y) / total as f32)
                .collect();
            out.loss += q
                .iter()
                .zip(&rows.targets)
                .map(|(q, y)| (q - y) * (q - y))
                .sum::<f32>()
                / total as f32;
            out.q_mean += q.iter().sum::<f32>() / total as f32;
            value.backward(&v_tape, &d_q, Some(&mut out.value), false);
            let d_a: Vec<f32> = d_q
                .iter()
                .map(|d| k * d)
                .chain(d_q.iter().map(|d| -k * d))
                .collect();
            advantage.backward(&a_tape, &d_a, Some(&mut out.advantage), false);
        }
        Some(out)
    }

    /// 1. Critic: regress Q(s, a) (and TD3's Q2) onto the TD target, both tasks into one
    ///    gradient.
    fn critic_step(&mut self, batches: &[Batch]) -> UpdateStats {
        if !self.values.is_empty() {
            return self.advantage_critic_step(batches);
        }
        let obs_dim = self.obs_dim();
        let total: usize = batches.iter().map(|b| b.size).sum();
        if total == 0 {
            return UpdateStats {
                critic_loss: f32::NAN,
                ..UpdateStats::default()
            };
        }
        let mut stats = UpdateStats::default();
        let mut critic_grads = self.critic.zeros_like();
        let mut twin_grads = self.twin.as_ref().map(|t| t.critic.zeros_like());
        let mut tape = Tape::default();
        let context_dim = self.context_dim();
        for (task, b) in batches.iter().enumerate().filter(|(_, b)| b.size > 0) {
            let targets = self.td_targets(task, b);
            let input = critic_rows(&b.obs, obs_dim, &b.actions, &b.context, context_dim, b.size);
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
            if let (Some(twin), Some(grads)) = (&self.twin, twin_grads.as_mut()) {
                twin.critic.forward(task, &input, b.size, &mut tape);
                let d_q2: Vec<f32> = tape
                    .output()
                    .iter()
                    .zip(&targets)
                    .map(|(q, y)| 2.0 * (q - y) / total as f32)
                    .collect();
                twin.critic.backward(&tape, &d_q2, Some(grads), false);
            }
        }
        self.critic_optimizer
            .update(self.critic.layers_mut(), critic_grads.layers());
        if let (Some(twin), Some(grads)) = (self.twin.as_mut(), twin_grads) {
            twin.optimizer
                .update(twin.critic.layers_mut(), grads.layers());
        }
        self.updates += 1;
        stats
    }

    /// Gradient ascent on `mean Q(s, mu(s))` (plus the imitation pull and the self-imitation
    /// pull); returns `-mean Q` and the share of rows that self-imitated.
    fn actor_step(
        &mut self,
        batches: &[Batch],
        demos: &[Batch],
        imitation_weight: f32,
    ) -> (f32, f32) {
        let obs_dim = self.obs_dim();
        let total: usize = batches.iter().map(|b| b.size).sum();
        let mut actor_grads = self.actor.zeros_like();
        let mut actor_tape = Tape::default();
        let mut tape = Tape::default();
        let mut loss = 0.0;
        let mut q_tapes = Vec::new();
        let mut mean_abs_q = 0.0;
        let context_dim = self.context_dim();
        for (task, b) in batches.iter().enumerate().filter(|(_, b)| b.size > 0) {
            self.actor.forward(task, &b.obs, b.size, &mut actor_tape);
            let mut actions = actor_tape.output().to_vec();
            if self.config.planar {
                actions
                    .chunks_exact_mut(ACTION_DIM)
                    .for_each(|a| a[2] = 0.0);
            }
            // The other herders' actions are the ones they took (MADDPG): only this herder's
            // own action follows the actor.
            let input = critic_rows(&b.obs, obs_dim, &actions, &b.context, context_dim, b.size);
            // Q(s, mu(s)): the critic's, or with the advantage decomposition V(s) (beside the
            // advantage network's pass when the pool has a second thread).
            let (q_of_actor, ()) = rayon::join(
                || {
                    self.values
                        .first()
                        .map(|v| v.value.predict_batch(task, &b.obs, b.size))
                },
                || self.critic.forward(task, &input, b.size, &mut tape),
            );
            let q_of_actor = q_of_actor.unwrap_or_else(|| tape.output().to_vec());
            loss -= q_of_actor.iter().sum::<f32>() / total as f32;
            mean_abs_q += q_of_actor.iter().map(|q| q.abs()).sum::<f32>() / total as f32;
            q_tapes.push((task, actor_tape.clone(), tape.clone(), q_of_actor));
        }
        // d Q / d a: the critic's, or k d A / d a under the advantage decomposition.
        let action_scale = if self.values.is_empty() {
            1.0
        } else {
            self.config.advantage_scale
        };
        // TD3+BC's normalisation keeps the imitation weight meaningful whatever Q's scale.
        let q_scale = if imitation_weight > 0.0 {
            1.0 / mean_abs_q.max(1e-3)
        } else {
            1.0
        };
        let mut sil_rows = 0;
        for (task, a_tape, q_tape, q_of_actor) in &q_tapes {
            let d_q = vec![-q_scale * action_scale / total as f32; q_tape.batch];
            let d_input = self
                .critic
                .backward(q_tape, &d_q, None, true)
                .unwrap_or_default();
            let stride = obs_dim + ACTION_DIM + context_dim;
            let mut d_action: Vec<f32> = d_input
                .chunks_exact(stride)
                .flat_map(|row| row[obs_dim..obs_dim + ACTION_DIM].iter().copied())
                .collect();
            if self.config.planar {
                // The critic never sees a vertical action: pull the actor's towards zero so
                // the flown model holds its altitude too.
                for (d, a) in d_action
                    .chunks_exact_mut(ACTION_DIM)
                    .zip(a_tape.output().chunks_exact(ACTION_DIM))
                {
                    d[2] = 2.0 * a[2] / total as f32;
                }
            }
            let b = &batches[*task];
            if self.config.self_imitation > 0.0 && b.returns.len() == b.size {
                sil_rows += self_imitation_pull(
                    &SelfImitation {
                        weight: self.config.self_imitation,
                        reward_scale: self.config.reward_scale,
                        planar: self.config.planar,
                        rows: total,
                    },
                    q_of_actor,
                    &b.returns,
                    a_tape.output(),
                    &b.actions,
                    &mut d_action,
                );
            }
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
        (loss, sil_rows as f32 / total.max(1) as f32)
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
        if let Some(twin) = self.twin.as_mut() {
            twin.target = twin.critic.clone();
        }
        for v in &mut self.values {
            v.target = v.value.clone();
        }
    }

    /// The deterministic action for one observation.
    pub fn act(&self, task: usize, obs: &[f32]) -> [f32; ACTION_DIM] {
        let y = self.actor.predict(task, obs);
        [y[0], y[1], y[2]]
    }

    /// The first critic's `Q(s, a)` for one observation and action (a decentralised critic):
    /// the critic's output, or under [`DdpgConfig::advantage_scale`] `V(s) + k (A(s, a) -
    /// A(s, mu(s)))`.
    pub fn q_value(&self, task: usize, obs: &[f32], action: [f32; ACTION_DIM]) -> f32 {
        let with = |a: &[f32]| {
            let mut input = obs.to_vec();
            input.extend_from_slice(a);
            self.critic.predict(task, &input)[0]
        };
        match self.values.first() {
            None => with(&action),
            Some(v) => {
                let own = self.policy_actions(task, obs, 1);
                v.value.predict(task, obs)[0]
                    + self.config.advantage_scale * (with(&action) - with(&own))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::replay::ReplayBuffer;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// A one-step bandit per task: reward = -|a - a*_task|^2, episodes end at once. The agent
    /// must find each task's best action, which differs between the tasks.
    fn solves_the_two_task_bandit(config: DdpgConfig, updates: usize) {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
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
        for _ in 0..updates {
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

    fn bandit_config() -> DdpgConfig {
        DdpgConfig {
            batch_size: 64,
            reward_scale: 1.0,
            actor_learning_rate: 2e-3,
            critic_learning_rate: 3e-3,
            policy_frequency: 1,
            ..DdpgConfig::default()
        }
    }

    #[test]
    fn the_exploration_noise_falls_linearly_inside_its_window_and_is_constant_by_default() {
        let constant = DdpgConfig {
            exploration_noise: 0.3,
            ..DdpgConfig::default()
        };
        for p in [0.0, 0.5, 1.0] {
            assert_eq!(constant.exploration_noise_at(p), 0.3);
        }
        let falling = DdpgConfig {
            exploration_noise: 0.3,
            exploration_noise_final: Some(0.1),
            exploration_noise_decay_from: 0.4,
            exploration_noise_decay_to: 0.8,
            ..DdpgConfig::default()
        };
        let at = |p: f64| falling.exploration_noise_at(p);
        assert_eq!(at(0.0), 0.3);
        assert_eq!(at(0.4), 0.3);
        assert!((at(0.6) - 0.2).abs() < 1e-6, "{}", at(0.6));
        assert!((at(0.8) - 0.1).abs() < 1e-6);
        assert!((at(1.0) - 0.1).abs() < 1e-6);
        assert!(at(0.5) > at(0.7), "it only falls");
    }

    #[test]
    fn learns_a_different_best_action_per_task() {
        solves_the_two_task_bandit(bandit_config(), 2000);
    }

    #[test]
    fn td3_learns_a_different_best_action_per_task() {
        let config = DdpgConfig {
            policy_frequency: 2,
            twin_critics: true,
            target_noise: 0.2,
            ..bandit_config()
        };
        solves_the_two_task_bandit(config, 3000);
    }

    #[test]
    fn reset_task_starts_one_task_over_and_keeps_the_other() {
        let mut config = bandit_config();
        config.twin_critics = true;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut agent = Agent::new(4, 2, NetworkConfig::default(), config, &mut rng);
        let mut brng = ChaCha8Rng::seed_from_u64(6);
        let batches = vec![batch_of(4, 32, &mut brng), batch_of(4, 32, &mut brng)];
        for _ in 0..20 {
            agent.update(&batches);
        }
        let before = agent.clone();
        agent.reset_task(0, &mut ChaCha8Rng::seed_from_u64(7));
        let obs = [0.1, -0.4, 0.3, 0.2];
        // The other task acts and values exactly as before.
        assert_eq!(agent.act(1, &obs), before.act(1, &obs));
        assert_eq!(agent.critic.task_inputs[1], before.critic.task_inputs[1]);
        assert_eq!(agent.critic.shared, before.critic.shared);
        // The reset task's layers are new, its targets follow them, its moments are zero.
        assert_ne!(agent.actor.task_inputs[0], before.actor.task_inputs[0]);
        assert_eq!(
            agent.target_actor.task_outputs[0],
            agent.actor.task_outputs[0]
        );
        assert_eq!(
            agent.target_critic.task_inputs[0],
            agent.critic.task_inputs[0]
        );
        let twin = agent.twin.as_deref().expect("twin critics");
        assert_ne!(
            twin.critic.task_inputs[0],
            before.twin.as_deref().unwrap().critic.task_inputs[0]
        );
        assert_eq!(twin.target.task_outputs[0], twin.critic.task_outputs[0]);
        assert!(
            agent.actor_optimizer.first[0]
                .weights
                .iter()
                .all(|&m| m == 0.0)
        );
        assert!(
            agent.actor_optimizer.first[1]
                .weights
                .iter()
                .any(|&m| m != 0.0)
        );
        // Its fresh output layer is small: the actor's action starts near zero again.
        assert!(agent.act(0, &obs).iter().all(|a| a.abs() < 0.05));
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

    #[test]
    fn self_imitation_pulls_only_rows_whose_return_beats_the_actor_value() {
        let sil = SelfImitation {
            weight: 0.5,
            reward_scale: 0.1,
            planar: true,
            rows: 4,
        };
        // Q(s, mu(s)) is -1 on every row; the returns, scaled, are -0.5 (better), -2 (worse),
        // unknown, and -1 exactly (not better).
        let q = [-1.0; 4];
        let returns = [-5.0, -20.0, f32::NAN, -10.0];
        let mu = [0.2, 0.2, 0.9, 0.2, 0.2, 0.9, 0.2, 0.2, 0.9, 0.2, 0.2, 0.9];
        let taken = [
            0.6, -0.2, 0.0, 0.6, -0.2, 0.0, 0.6, -0.2, 0.0, 0.6, -0.2, 0.0,
        ];
        let mut d = [0.0; 12];
        let pulled = self_imitation_pull(&sil, &q, &returns, &mu, &taken, &mut d);
        assert_eq!(pulled, 1);
        // weight 2 (mu - a) / rows on the first row's planar components only.
        let expected = [
            0.5 * 2.0 * (0.2 - 0.6) / 4.0,
            0.5 * 2.0 * (0.2 + 0.2) / 4.0,
            0.0,
        ];
        for (got, want) in d[..3].iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
        assert!(d[3..].iter().all(|&x| x == 0.0));
        // Off the plane the vertical component is pulled too.
        let mut d = [0.0; 12];
        self_imitation_pull(
            &SelfImitation {
                planar: false,
                ..sil
            },
            &q,
            &returns,
            &mu,
            &taken,
            &mut d,
        );
        assert!((d[2] - 0.5 * 2.0 * 0.9 / 4.0).abs() < 1e-6);
    }

    #[test]
    fn self_imitation_moves_the_actor_towards_actions_that_beat_its_value() {
        let network = NetworkConfig {
            hidden: 16,
            shared_layers: 1,
        };
        let taken = [0.8_f32, -0.6, 0.0];
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let mut batch = batch_of(4, 32, &mut rng);
        batch.actions = taken.repeat(32);
        // Returns far above anything the critic values: every row beats the actor.
        batch.returns = vec![1e4; 32];
        let gap = |agent: &Agent, obs: &[f32]| {
            let a = agent.act(0, obs);
            (a[0] - taken[0]).abs() + (a[1] - taken[1]).abs()
        };
        let obs = batch.obs[..4].to_vec();
        let mut off = Agent::new(
            4,
            2,
            network,
            DdpgConfig {
                planar: true,
                ..DdpgConfig::default()
            },
            &mut ChaCha8Rng::seed_from_u64(5),
        );
        let mut on = Agent::new(
            4,
            2,
            network,
            DdpgConfig {
                planar: true,
                self_imitation: 5.0,
                actor_learning_rate: 1e-3,
                ..DdpgConfig::default()
            },
            &mut ChaCha8Rng::seed_from_u64(5),
        );
        let before = gap(&on, &obs);
        let mut share = 0.0_f32;
        let mut off_shares = Vec::new();
        for _ in 0..300 {
            if let Some(s) = on
                .update(&[batch.clone(), Batch::default()])
                .self_imitation_share
            {
                share = share.max(s);
            }
            off_shares.extend(
                off.update(&[batch.clone(), Batch::default()])
                    .self_imitation_share,
            );
        }
        assert_eq!(share, 1.0, "every row pulled");
        let after = gap(&on, &obs);
        assert!(after < 0.25 * before, "gap {before} -> {after}");
        // Off, the returns are ignored: every actor step reports no row pulling.
        assert!(!off_shares.is_empty(), "the actor stepped");
        assert!(off_shares.iter().all(|&s| s == 0.0));
    }

    fn batch_of(obs_dim: usize, rows: usize, rng: &mut ChaCha8Rng) -> Batch {
        let mut b = Batch {
            size: rows,
            ..Batch::default()
        };
        for r in 0..rows {
            for _ in 0..obs_dim {
                b.obs.push(rng.random_range(-1.0..1.0));
                b.next_obs.push(rng.random_range(-1.0..1.0));
            }
            b.actions.extend([0.1, -0.2, 0.3]);
            b.rewards.push(r as f32 - 2.0);
            b.continues.push(if r % 3 == 0 { 0.0 } else { 0.5 });
        }
        b
    }

    #[test]
    fn twin_critic_targets_take_the_smaller_target_value() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let config = DdpgConfig {
            twin_critics: true,
            gamma: 0.9,
            reward_scale: 0.5,
            ..DdpgConfig::default()
        };
        let network = NetworkConfig {
            hidden: 16,
            shared_layers: 1,
        };
        let mut agent = Agent::new(4, 2, network, config, &mut rng);
        // Make the two target critics clearly different.
        for layer in agent.twin.as_mut().unwrap().target.layers_mut() {
            layer.bias.iter_mut().for_each(|b| *b += 0.3);
        }
        let b = batch_of(4, 6, &mut rng);
        let targets = agent.td_targets(1, &b);
        let mut tape = Tape::default();
        agent
            .target_actor
            .forward(1, &b.next_obs, b.size, &mut tape);
        let input = concat_rows(&b.next_obs, 4, tape.output(), b.size);
        let forward = |net: &MultiTaskMlp| {
            let mut tape = Tape::default();
            net.forward(1, &input, b.size, &mut tape);
            tape.output().to_vec()
        };
        let q1 = forward(&agent.target_critic);
        let q2 = forward(&agent.twin.as_ref().unwrap().target);
        for r in 0..b.size {
            let expected = 0.5 * b.rewards[r] + 0.9 * b.continues[r] * q1[r].min(q2[r]);
            assert!((targets[r] - expected).abs() < 1e-6, "row {r}");
        }
        assert!(q1.iter().zip(&q2).any(|(a, b)| a != b));
        // A terminal row (continues 0) is the scaled reward alone.
        assert_eq!(targets[0], 0.5 * b.rewards[0]);
        // WD3's weight mixes the smaller with the mean: a quarter of the min, three quarters
        // of the mean.
        agent.config.twin_min_weight = 0.25;
        let mixed = agent.td_targets(1, &b);
        for r in 0..b.size {
            let next = 0.25 * q1[r].min(q2[r]) + 0.75 * 0.5 * (q1[r] + q2[r]);
            let expected = 0.5 * b.rewards[r] + 0.9 * b.continues[r] * next;
            assert!((mixed[r] - expected).abs() < 1e-5, "row {r}");
        }
        assert!(
            mixed.iter().zip(&targets).any(|(m, t)| m > t),
            "the mean lifts the target"
        );
        // Without the twin the target is the first critic's.
        agent.twin = None;
        let single = agent.td_targets(1, &b);
        for r in 0..b.size {
            let expected = 0.5 * b.rewards[r] + 0.9 * b.continues[r] * q1[r];
            assert!((single[r] - expected).abs() < 1e-6);
        }
    }

    #[test]
    fn advantage_targets_are_the_next_value_and_the_loss_is_on_v_plus_scaled_advantage() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let config = DdpgConfig {
            twin_critics: true,
            gamma: 0.9,
            reward_scale: 0.5,
            target_noise: 0.2,
            advantage_scale: 0.1,
            ..DdpgConfig::default()
        };
        let network = NetworkConfig {
            hidden: 16,
            shared_layers: 1,
        };
        let mut agent = Agent::new(4, 2, network, config, &mut rng);
        assert_eq!(agent.values.len(), 2, "one state value per critic");
        for layer in agent.values[1].target.layers_mut() {
            layer.bias.iter_mut().for_each(|b| *b += 0.3);
        }
        let b = batch_of(4, 6, &mut rng);
        let noise_before = agent.noise_rng.clone();
        let targets = agent.td_targets(1, &b);
        assert_eq!(
            agent.noise_rng, noise_before,
            "V(s') needs no target action, so no smoothing noise is drawn"
        );
        let v = |net: &MultiTaskMlp| {
            let mut tape = Tape::default();
            net.forward(1, &b.next_obs, b.size, &mut tape);
            tape.output().to_vec()
        };
        let (v1, v2) = (v(&agent.values[0].target), v(&agent.values[1].target));
        assert!(v1.iter().zip(&v2).any(|(a, b)| a != b));
        for r in 0..b.size {
            let expected = 0.5 * b.rewards[r] + 0.9 * b.continues[r] * v1[r].min(v2[r]);
            assert!((targets[r] - expected).abs() < 1e-6, "row {r}");
        }
        agent.config.twin_min_weight = 0.0;
        let mean = agent.td_targets(1, &b);
        for r in 0..b.size {
            let expected = 0.5 * b.rewards[r] + 0.9 * b.continues[r] * 0.5 * (v1[r] + v2[r]);
            assert!((mean[r] - expected).abs() < 1e-5, "row {r}");
        }
        // One critic step regresses V(s) + k (A(s, a) - A(s, mu(s))) onto those targets (the
        // loss is read before the step).
        agent.config.twin_min_weight = 1.0;
        let forward = |net: &MultiTaskMlp, x: &[f32]| {
            let mut tape = Tape::default();
            net.forward(1, x, b.size, &mut tape);
            tape.output().to_vec()
        };
        let mu = agent.policy_actions(1, &b.obs, b.size);
        let v_now = forward(&agent.values[0].value, &b.obs);
        let a_taken = forward(&agent.critic, &concat_rows(&b.obs, 4, &b.actions, b.size));
        let a_own = forward(&agent.critic, &concat_rows(&b.obs, 4, &mu, b.size));
        let expected_loss = (0..b.size)
            .map(|r| {
                let q = v_now[r] + 0.1 * (a_taken[r] - a_own[r]);
                (q - targets[r]).powi(2)
            })
            .sum::<f32>()
            / b.size as f32;
        assert!(
            a_taken
                .iter()
                .zip(&a_own)
                .any(|(x, y)| (x - y).abs() > 1e-4)
        );
        let value_before = agent.values[0].value.clone();
        let stats = agent.update(&[Batch::default(), b.clone()]);
        assert!(
            (stats.critic_loss - expected_loss).abs() < 1e-5 * expected_loss.max(1.0),
            "{} vs {expected_loss}",
            stats.critic_loss
        );
        assert_ne!(agent.values[0].value, value_before, "V learns");
        // Q at the actor's own action is V(s), whatever A says.
        let obs = &b.obs[..4];
        let own = agent.policy_actions(1, obs, 1);
        let v_here = agent.values[0].value.predict(1, obs)[0];
        assert!((agent.q_value(1, obs, [own[0], own[1], own[2]]) - v_here).abs() < 1e-6);
        assert!((agent.q_value(1, obs, [0.9, -0.9, 0.0]) - v_here).abs() > 1e-6);
        // Off, nothing of it exists and the targets are TD3's.
        let plain = Agent::new(
            4,
            2,
            network,
            DdpgConfig {
                advantage_scale: 0.0,
                ..config
            },
            &mut rng,
        );
        assert!(plain.values.is_empty());
    }

    #[test]
    fn the_advantage_critic_learns_the_same_on_one_thread_as_on_two() {
        let config = DdpgConfig {
            twin_critics: true,
            advantage_scale: 0.1,
            policy_frequency: 1,
            ..DdpgConfig::default()
        };
        let network = NetworkConfig {
            hidden: 16,
            shared_layers: 1,
        };
        let run = |threads: usize| {
            let mut rng = ChaCha8Rng::seed_from_u64(21);
            let mut agent = Agent::new(4, 2, network, config, &mut rng);
            let batches = [batch_of(4, 8, &mut rng), batch_of(4, 6, &mut rng)];
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool");
            pool.install(|| {
                for _ in 0..4 {
                    agent.update(&batches);
                }
            });
            agent
        };
        let (one, two) = (run(1), run(2));
        assert_eq!(one.actor, two.actor);
        assert_eq!(one.critic, two.critic);
        assert_eq!(one.values[1].value, two.values[1].value);
        assert_eq!(one.twin.map(|t| t.critic), two.twin.map(|t| t.critic));
    }

    #[test]
    fn an_advantage_critic_learns_a_different_best_action_per_task() {
        let config = DdpgConfig {
            policy_frequency: 2,
            twin_critics: true,
            advantage_scale: 1.0,
            ..bandit_config()
        };
        solves_the_two_task_bandit(config, 3000);
    }

    /// A batch for a centralised critic: `counts[r]` other herders at `s'` per row.
    fn batch_with_others(obs_dim: usize, counts: &[u8], rng: &mut ChaCha8Rng) -> Batch {
        let mut b = batch_of(obs_dim, counts.len(), rng);
        b.max_others = 3;
        for &k in counts {
            b.context
                .extend((0..obs_dim + ACTION_DIM).map(|_| rng.random_range(-1.0..1.0)));
            for slot in 0..3 {
                for _ in 0..obs_dim {
                    let v = if slot < usize::from(k) {
                        rng.random_range(-1.0..1.0)
                    } else {
                        0.0
                    };
                    b.next_others.push(v);
                }
            }
            b.next_others_count.push(k);
        }
        b
    }

    #[test]
    fn the_centralised_critic_pools_the_other_herders_whatever_their_order() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let config = DdpgConfig {
            centralised_critic: true,
            twin_critics: true,
            planar: true,
            policy_frequency: 1,
            ..DdpgConfig::default()
        };
        let network = NetworkConfig {
            hidden: 16,
            shared_layers: 1,
        };
        let obs_dim = 4;
        let mut agent = Agent::new(obs_dim, 2, network, config, &mut rng);
        assert_eq!(agent.context_dim(), obs_dim + ACTION_DIM);
        assert_eq!(agent.critic.inputs(), 2 * (obs_dim + ACTION_DIM));
        let b = batch_with_others(obs_dim, &[3, 2, 1, 0, 3], &mut rng);
        let targets = agent.td_targets(0, &b);
        // Every order of each row's other herders gives the same targets.
        let stride = 3 * obs_dim;
        for rotation in 1..3 {
            let mut permuted = b.clone();
            for r in 0..b.size {
                let k = usize::from(b.next_others_count[r]);
                let rows = &mut permuted.next_others[r * stride..r * stride + k * obs_dim];
                let mut chunks: Vec<Vec<f32>> = rows.chunks(obs_dim).map(<[f32]>::to_vec).collect();
                chunks.rotate_left(rotation % k.max(1));
                chunks.reverse();
                rows.copy_from_slice(&chunks.concat());
            }
            assert_ne!(permuted.next_others, b.next_others, "the order changed");
            let again = agent.td_targets(0, &permuted);
            for (x, y) in again.iter().zip(&targets) {
                assert!((x - y).abs() < 1e-5, "{x} vs {y}");
            }
        }
        // The others matter: moving one of them moves the target of its row only (row 1:
        // row 0 is terminal, see `batch_of`).
        let mut moved = b.clone();
        moved.next_others[stride] += 0.9;
        let after = agent.td_targets(0, &moved);
        assert!(
            (after[1] - targets[1]).abs() > 1e-7,
            "row 1 should see its other herder"
        );
        for r in [0, 2, 3, 4] {
            assert!((after[r] - targets[r]).abs() < 1e-6, "row {r}");
        }
        // A row without others has an empty pool: the same as a context of zeros.
        let lone = critic_rows(&[0.5; 4], obs_dim, &[0.1, 0.2, 0.0], &[], 7, 1);
        assert_eq!(&lone[7..], &[0.0; 7]);
        // An update runs, and the actor's gradient reaches it through its own action only.
        let before: Vec<Vec<f32>> = agent.actor.layers().map(|l| l.weights.clone()).collect();
        let stats = agent.update(&[b.clone(), b]);
        assert!(stats.critic_loss.is_finite());
        let after: Vec<Vec<f32>> = agent.actor.layers().map(|l| l.weights.clone()).collect();
        assert!(after != before, "the actor moved");
    }

    #[test]
    fn target_smoothing_is_seeded_clipped_and_planar_zeroes_the_vertical_action() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let config = DdpgConfig {
            target_noise: 5.0, // huge: every draw is clipped
            target_noise_clip: 0.1,
            planar: true,
            ..DdpgConfig::default()
        };
        let network = NetworkConfig {
            hidden: 8,
            shared_layers: 1,
        };
        let mut a = Agent::new(3, 2, network, config, &mut rng);
        let mut b = a.clone();
        let batch = batch_of(3, 5, &mut rng);
        assert_eq!(a.td_targets(0, &batch), b.td_targets(0, &batch));
        let noisy = a.td_targets(0, &batch);
        a.config.target_noise = 0.0;
        let clean = a.td_targets(0, &batch);
        assert_ne!(noisy, clean);
        for (n, c) in noisy.iter().zip(&clean) {
            // 0.1 of clipped noise on two action components moves Q' only a little.
            assert!((n - c).abs() < 0.1, "{n} vs {c}");
        }
    }
}
