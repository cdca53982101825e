//! The per-herder policy interface shared by the rule-based baselines and the learned actor.

use crate::world::World;

/// A decentralised controller: the same object is asked once per herder per step.
///
/// `act` sees the *observed* world (with sensing noise when enabled) and returns the herder's
/// commanded velocity, m/s, simulator frame (x east, y north, z up); the environment caps it.
pub trait Policy {
    /// Called at the start of each episode with the first observation and the episode seed.
    fn reset(&mut self, world: &World, seed: u64);
    /// The velocity command of herder `herder` (index into `world.herders`).
    fn act(&mut self, world: &World, herder: usize) -> [f64; 3];
}

/// Builds fresh policies by name; what `eval` sweeps over.
///
/// The baselines implement it through [`crate::baseline::Method`]; a learned actor (a model
/// file) is plugged in by another implementation, without touching the sweep.
pub trait PolicyFactory: Send + Sync {
    /// Short name used in reports and tables.
    fn name(&self) -> String;
    /// A new policy instance for one episode.
    fn make(&self) -> Box<dyn Policy + Send>;
}

/// Asks `policy` for every herder's command, writing into `out` (resized to M).
pub fn act_all(policy: &mut dyn Policy, world: &World, out: &mut Vec<[f64; 3]>) {
    out.clear();
    for h in 0..world.herders.len() {
        out.push(policy.act(world, h));
    }
}
