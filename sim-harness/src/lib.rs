#![doc = include_str!("../README.md")]
pub mod baseline;
pub mod dynamics;
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

pub use env::{
    BatchEnv, Env, EnvError, EpisodeInfo, EpisodeSummary, ReplayScratch, StepOutcome, run_episode,
};
pub use policy::{Policy, PolicyFactory};
pub use reward::{RewardCorrection, RewardParams, RewardTerms};
pub use scenario::{HerderCount, HerderDynamics, Scenario, ScenarioError};
pub use skyherd_model::Task;
pub use world::{World, WorldError};
