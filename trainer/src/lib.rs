//! skyherd-trainer: MTDDPG (the paper's multi-task DDPG, Section III-B) on the skyherd
//! simulator, and export of the trained actor as a quantized model file.
//!
//! Read top to bottom, like cleanrl's `ddpg_continuous_action.py`:
//! * [`nn`]: f32 dense layers on `matrixmultiply`, ReLU/tanh, backprop, Adam.
//! * [`network`]: Fig. 2's multi-task MLP (task input layer -> shared layers -> task output
//!   layer) for actor and critic, gradient-checked against finite differences.
//! * [`replay`]: per-task replay buffers (terminated vs truncated kept apart).
//! * [`ddpg`]: the update (critic TD step, actor step, Polyak targets), imitation steps.
//! * [`policy`]: decentralised execution through `skyherd_onboard::obs::encode` and
//!   `LocalFrame::action_to_world`; any actor as a `skyherd_sim::Policy`.
//! * [`rollout`]: environments of both tasks stepped together; [`reward`]: the learner's
//!   reward (the paper's, or the audited one), checked by [`audit`] against hovering and the rules;
//!   [`ablation`]: MTDDPG against single-task DDPG, read back from the runs' learning curves.
//! * [`train`]: warm start (behaviour cloning of a rule), MTDDPG with a curriculum over N and
//!   M, held-out evaluation keeping the best checkpoint; then [`evolve`]: evolution strategies
//!   on each task's own layers, scored by completion time. [`config`] documents every knob.
//! * [`checkpoint`]: safetensors checkpoints for `--resume`; [`export`]: the quantizer of
//!   `skyherd-model` and the quantized-vs-float parity check; [`eval`], [`report`]: metrics, CSV, PNG.
//!
//! ```
//! use rand::SeedableRng;
//! use skyherd_onboard::obs::FEATURES;
//! use skyherd_sim::{Env, Scenario, run_episode};
//! use skyherd_trainer::ddpg::{Agent, DdpgConfig, NetworkConfig};
//! use skyherd_trainer::policy::ActorPolicy;
//!
//! // A fresh (untrained) agent; every herder flies the same actor on its own observation.
//! let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
//! let network = NetworkConfig { hidden: 32, shared_layers: 1 };
//! let agent = Agent::new(FEATURES, 2, network, DdpgConfig::default(), &mut rng);
//! let mut scenario = Scenario::paper_drive();
//! scenario.targets = 4;
//! scenario.step_limit = 20;
//! let mut env = Env::new(scenario).unwrap();
//! let mut policy = ActorPolicy::new(&agent.actor);
//! let summary = run_episode(&mut env, &mut policy, 7, |_, _| {}).unwrap();
//! assert!(summary.steps <= 20);
//! ```
#![forbid(unsafe_op_in_unsafe_fn)]

pub mod ablation;
pub mod audit;
pub mod checkpoint;
pub mod config;
pub mod ddpg;
pub mod distill;
pub mod eval;
pub mod evolve;
pub mod export;
pub mod finalists;
pub mod network;
pub mod nn;
pub mod policy;
pub mod qat;
pub mod replay;
pub mod report;
pub mod reward;
pub mod rollout;
pub mod train;
