//! skyherd-sim: the shepherding world of Wang et al. ("Multi-Drone Collaborative Shepherding
//! Through Multi-Task Reinforcement Learning"), Section III-A and IV-A, built to be exact and
//! fast enough to train on.
//!
//! * [`world`]: the state and eqs (1)-(6), with a spatial grid (O(N) per step, no allocation)
//!   and a naive O(N^2) reference; the update order is documented there.
//! * [`reward`]: eqs (7)-(11) per task, term by term, and a switchable training correction.
//! * [`task`]: spawn rules, success/leave/step-limit termination, the time lower bound.
//! * [`noise`]: seeded boids-parameter, sensing and actuation noise.
//! * [`scenario`]: TOML scenarios with presets `paper-drive`, `paper-collect`, `indoor`.
//! * [`env`](mod@env): [`Env`] (`reset(seed)`, `step(actions)`), episodes, and the batched [`BatchEnv`].
//! * [`policy`]: the per-herder [`Policy`] trait and [`policy::PolicyFactory`].
//! * [`baseline`]: rule-based herders (Strömbom, control-tutor, Lama & di Bernardo, farthest
//!   targets).
//! * [`eval`]: the paper's evaluation sweep and its reports; [`plot`]: Fig. 3 and Fig. 4 plots.
//! * [`learned`]: a learned actor (an int8 model file through the onboard `Actor`) as a policy.
//! * [`obs`]: f64 world -> the onboard encoder's f32 input (the one encoder the drone runs).
//! * [`trace`]: the JSON state schema of `skyherd-sim step` and of run traces.
//!
//! ```
//! use skyherd_sim::{Env, Scenario};
//!
//! let mut scenario = Scenario::paper_drive().without_noise();
//! scenario.targets = 2;
//! scenario.herders = skyherd_sim::scenario::HerderCount::Fixed(1);
//! let mut env = Env::new(scenario).unwrap();
//! env.reset(42);
//! let before = env.world().targets.clone();
//! let out = env.step(&[[0.0, 0.0, 0.0]]).unwrap();
//! assert_ne!(env.world().targets, before); // the flock moved
//! assert!(out.reward < 0.0); // two targets cost k0 k3 r3 = -0.18 each, give or take their motion
//! assert!(!out.terminated);
//! ```

pub mod baseline;
pub mod env;
pub mod eval;
pub mod learned;
pub mod noise;
pub mod obs;
pub mod plot;
pub mod policy;
pub mod reward;
pub mod scenario;
pub mod task;
pub mod trace;
pub mod world;

pub use env::{BatchEnv, Env, EnvError, EpisodeInfo, EpisodeSummary, StepOutcome, run_episode};
pub use policy::{Policy, PolicyFactory};
pub use reward::{RewardCorrection, RewardParams, RewardTerms};
pub use scenario::{HerderCount, Scenario, ScenarioError};
pub use skyherd_model::Task;
pub use world::{World, WorldError};
