//! Decentralised execution: every herder runs the same actor on its own observation, encoded by
//! the onboard crate's encoder (the only copy), and its normalised local-frame action becomes a
//! simulator-frame velocity through `LocalFrame::action_to_world`, exactly as on the drone.
//!
//! [`ActorPolicy`] plugs any [`Infer`] (the float training actor, the exported int8 actor) into
//! the simulator's [`Policy`] trait, so the simulator's episode runner and the baselines'
//! evaluation apply unchanged.

use skyherd_model::Task;
use skyherd_onboard::actor::Actor;
use skyherd_onboard::obs::{FEATURES, LocalFrame, ObsError, ObsInput, encode};
use skyherd_sim::{Policy, World};

use crate::network::MultiTaskMlp;

/// Something that maps features to a normalised local-frame action.
pub trait Infer {
    /// The action in `[-1, 1]^3` for `features` in `task`.
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3];
}

impl<T: Infer + ?Sized> Infer for &T {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        (**self).infer(task, features)
    }
}

impl Infer for MultiTaskMlp {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        let y = self.predict(task.index(), features);
        [y[0], y[1], y[2]]
    }
}

impl Infer for skyherd_model::FloatActor {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        self.forward(task, features)
    }
}

impl Infer for Actor<'_> {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        Actor::infer(self, task, features)
    }
}

/// The world in the encoder's f32 form, converted once per step for all herders.
#[derive(Clone, Debug, Default)]
pub struct Observer {
    herders: Vec<[f32; 3]>,
    targets: Vec<[f32; 2]>,
    loaded_step: Option<u64>,
}

impl Observer {
    /// Converts `world` (skipped when this step is already loaded; `force` reloads).
    pub fn load(&mut self, world: &World, force: bool) {
        if !force && self.loaded_step == Some(world.step) {
            return;
        }
        self.herders.clear();
        self.herders.extend(
            world
                .herders
                .iter()
                .map(|h| [h[0] as f32, h[1] as f32, h[2] as f32]),
        );
        self.targets.clear();
        self.targets
            .extend(world.targets.iter().map(|t| [t[0] as f32, t[1] as f32]));
        self.loaded_step = Some(world.step);
    }

    /// Herder `herder`'s features of the loaded world (call [`load`](Self::load) first).
    pub fn encode(
        &self,
        world: &World,
        herder: usize,
        out: &mut [f32; FEATURES],
    ) -> Result<LocalFrame, ObsError> {
        let input = ObsInput {
            own_index: herder,
            herders: &self.herders,
            targets: &self.targets,
            goal: [world.goal.center[0] as f32, world.goal.center[1] as f32],
            goal_radius: world.goal.radius as f32,
            area: [
                world.area.width as f32,
                world.area.depth as f32,
                world.area.ceiling as f32,
            ],
            max_speed: world.limits.herder as f32,
        };
        encode(&input, out)
    }
}

/// A learned actor as a per-herder simulator policy.
#[derive(Clone, Debug)]
pub struct ActorPolicy<A> {
    actor: A,
    observer: Observer,
    features: [f32; FEATURES],
    /// Every encoded observation is appended here when recording (for calibration and parity).
    pub recorded: Option<Vec<(Task, [f32; FEATURES])>>,
}

impl<A: Infer> ActorPolicy<A> {
    /// Wraps `actor`.
    pub fn new(actor: A) -> Self {
        ActorPolicy {
            actor,
            observer: Observer::default(),
            features: [0.0; FEATURES],
            recorded: None,
        }
    }

    /// Wraps `actor` and records every observation it sees.
    pub fn recording(actor: A) -> Self {
        ActorPolicy {
            recorded: Some(Vec::new()),
            ..ActorPolicy::new(actor)
        }
    }
}

impl<A: Infer> Policy for ActorPolicy<A> {
    fn reset(&mut self, world: &World, _seed: u64) {
        self.observer.load(world, true);
    }

    fn act(&mut self, world: &World, herder: usize) -> [f64; 3] {
        // Herder 0 starts a new step: reload even if a reset left the step counter equal.
        self.observer.load(world, herder == 0);
        match self.observer.encode(world, herder, &mut self.features) {
            Ok(frame) => {
                if let Some(log) = self.recorded.as_mut() {
                    log.push((world.task, self.features));
                }
                let v = frame.action_to_world(self.actor.infer(world.task, &self.features));
                [f64::from(v[0]), f64::from(v[1]), f64::from(v[2])]
            }
            // The drone's failsafe for an unusable observation: hold position.
            Err(_) => [0.0; 3],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use skyherd_sim::{Env, HerderCount, Scenario};

    #[test]
    fn every_herder_gets_its_own_observation_and_a_capped_velocity() {
        let mut scenario = Scenario::paper_drive().without_noise();
        scenario.targets = 8;
        scenario.herders = HerderCount::Fixed(3);
        let env = Env::new(scenario).expect("valid scenario");
        let world = env.observation();
        let mut observer = Observer::default();
        observer.load(world, true);
        let mut f0 = [0.0; FEATURES];
        let mut f1 = [0.0; FEATURES];
        observer.encode(world, 0, &mut f0).expect("encodes");
        observer.encode(world, 1, &mut f1).expect("encodes");
        assert_ne!(f0, f1, "herders see the world from different places");
        // An actor that always answers "full speed forward, up".
        struct Forward;
        impl Infer for Forward {
            fn infer(&self, _: Task, _: &[f32; FEATURES]) -> [f32; 3] {
                [1.0, 0.0, 1.0]
            }
        }
        let mut policy = ActorPolicy::recording(Forward);
        policy.reset(world, 0);
        for h in 0..3 {
            let v = policy.act(world, h);
            let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((speed - world.limits.herder).abs() < 1e-3, "speed {speed}");
        }
        assert_eq!(policy.recorded.as_ref().map(Vec::len), Some(3));
    }
}
