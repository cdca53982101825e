//! A learned actor as a simulator [`Policy`]: decentralised execution exactly as on the drone.
//!
//! Every herder encodes its own observation with the onboard encoder (through
//! [`EncoderBuffers`], the one copy), asks the actor for a normalised local-frame action and turns
//! it into a simulator-frame velocity with `LocalFrame::action_to_world`. [`ModelPolicy`] loads a
//! quantized model file and runs it through `skyherd_onboard::actor::Actor`, the code that flies,
//! and through the daemon's flight rules ([`ActorPolicy::flying`]: `skyherd_onboard::safety`'s
//! fence, altitude band and speed caps over `Limits::arena`, and the encoder reading the drone's
//! height above the band's floor), so `skyherd-sim eval --methods model:models/mtddpg-v1.skym`
//! evaluates the shipped model as it flies beside the baselines. The trainer's rollouts use the
//! bare actor ([`ActorPolicy::new`]).
//!
//! ```
//! use skyherd_sim::learned::ModelPolicy;
//! use skyherd_sim::{Env, PolicyFactory, Scenario, run_episode};
//!
//! let model = ModelPolicy::from_file("../models/mtddpg-v1.skym".as_ref()).unwrap();
//! let mut scenario = Scenario::paper_drive();
//! scenario.targets = 4;
//! let mut env = Env::new(scenario).unwrap();
//! let mut policy = model.make();
//! let summary = run_episode(&mut env, policy.as_mut(), 7, |_, _| {}).unwrap();
//! assert!(summary.steps > 0);
//! ```

use std::fmt;
use std::path::{Path, PathBuf};

use skyherd_model::{FloatActor, FormatError, Task};
use skyherd_onboard::actor::Actor;
use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES, version_for};
use skyherd_onboard::safety::{self, Braking, Limits, Situation};
use skyherd_onboard::separation::{Peer, SeparationConfig, separate};

/// The separation rule keeps this much beyond the breach distance (as `skyherd-sitl
/// --keep-apart` does): it steers on the others' last step.
pub const KEEP_APART_MARGIN: f32 = 1.1;

use crate::obs::EncoderBuffers;
use crate::policy::{Policy, PolicyFactory};
use crate::world::World;

/// Something that maps features to a normalised local-frame action.
pub trait Infer {
    /// The action in `[-1, 1]^3` for `features` in `task`.
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3];

    /// The encoder version whose features the actor reads; the policy encodes only those.
    fn encoder_version(&self) -> u16 {
        ENCODER_VERSION
    }
}

impl<T: Infer + ?Sized> Infer for &T {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        (**self).infer(task, features)
    }

    fn encoder_version(&self) -> u16 {
        (**self).encoder_version()
    }
}

impl Infer for FloatActor {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        self.forward(task, features)
    }

    fn encoder_version(&self) -> u16 {
        let width = self
            .task_inputs
            .first()
            .map_or(FEATURES, |layer| layer.inputs);
        version_for(width).unwrap_or(ENCODER_VERSION)
    }
}

impl Infer for Actor<'_> {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        Actor::infer(self, task, features)
    }

    fn encoder_version(&self) -> u16 {
        self.model().encoder_version
    }
}

/// A learned actor as a per-herder simulator policy.
#[derive(Clone, Debug)]
pub struct ActorPolicy<A> {
    actor: A,
    buffers: EncoderBuffers,
    loaded_step: Option<u64>,
    features: [f32; FEATURES],
    /// Whether the daemon's flight rules apply (see [`ActorPolicy::flying`]).
    flight_rules: bool,
    /// Whether the daemon's separation rule applies (see [`ActorPolicy::keeping_apart`]).
    keep_apart: bool,
    /// How the herders answer a new velocity, which the separation rule counts (see
    /// [`ActorPolicy::responding_in`]).
    braking: Option<Braking>,
    /// The last step seen (`None` after a reset) and its herder positions, for the peers'
    /// velocities.
    previous_step: Option<u64>,
    previous: Vec<[f64; 3]>,
    /// Each herder's velocity over the last step, m/s (zero at the start).
    velocities: Vec<[f32; 3]>,
    /// Scratch for the separation rule's peers.
    peers: Vec<Peer>,
    /// Every encoded observation is appended here when recording (for calibration and parity).
    pub recorded: Option<Vec<(Task, [f32; FEATURES])>>,
}

impl<A: Infer> ActorPolicy<A> {
    /// Wraps `actor`: the bare actor, as the trainer rolls it out.
    pub fn new(actor: A) -> Self {
        ActorPolicy {
            buffers: EncoderBuffers::for_version(actor.encoder_version()),
            actor,
            loaded_step: None,
            features: [0.0; FEATURES],
            flight_rules: false,
            keep_apart: false,
            braking: None,
            previous_step: None,
            previous: Vec::new(),
            velocities: Vec::new(),
            peers: Vec::new(),
            recorded: None,
        }
    }

    /// The same, with the daemon's separation rule (`skyherd_onboard::separation`, as
    /// `skyherd-onboard --separation-m` runs it) before the flight rules: each herder keeps
    /// 10 % beyond the arena's breach distance (`Area::breach_distance_m`) from the others,
    /// whose velocities it takes from their last step, as the daemon does from two snapshots.
    pub fn keeping_apart(mut self, keep_apart: bool) -> Self {
        self.keep_apart = keep_apart;
        self
    }

    /// The separation rule counts herders that answer a new velocity as `braking` says
    /// (`SeparationConfig::braking`; with a motion model, its
    /// [`DynamicsLimits::response_lag_s`] and 1/sqrt(2) of its horizontal acceleration).
    /// `None`, the default: they fly it at once.
    ///
    /// [`DynamicsLimits::response_lag_s`]: crate::dynamics::DynamicsLimits::response_lag_s
    pub fn responding_in(mut self, braking: Option<Braking>) -> Self {
        self.braking = braking;
        self
    }

    /// The separation rule's settings for `world`: 10 % beyond its breach distance (the
    /// room's 0.5 m or the arena's 3 m).
    fn separation(&self, world: &World) -> SeparationConfig {
        let breach = world.area.breach_distance_m() as f32;
        SeparationConfig {
            braking: self.braking,
            ..SeparationConfig::keeping(breach * KEEP_APART_MARGIN, world.limits.herder as f32)
        }
    }

    /// Each herder's velocity over the step that led to `world`.
    fn track_velocities(&mut self, world: &World) {
        self.velocities.clear();
        match self.previous_step {
            Some(step) if step + 1 == world.step && self.previous.len() == world.herders.len() => {
                let dt = world.dt.max(f64::MIN_POSITIVE);
                self.velocities
                    .extend(self.previous.iter().zip(&world.herders).map(|(a, b)| {
                        [
                            ((b[0] - a[0]) / dt) as f32,
                            ((b[1] - a[1]) / dt) as f32,
                            ((b[2] - a[2]) / dt) as f32,
                        ]
                    }));
            }
            _ => self.velocities.resize(world.herders.len(), [0.0; 3]),
        }
        self.previous_step = Some(world.step);
        self.previous.clone_from(&world.herders);
    }

    /// Wraps `actor` as the onboard daemon flies it: the encoder reads the drone's height above
    /// the altitude band's floor, and every command goes through `skyherd_onboard::safety::check`
    /// with `Limits::arena(area, herder speed limit)` at the drone's observed position (the
    /// simulator has no uplink delay: snapshot age 0). A herder that the bare actor would fly
    /// out of the arena, ending the episode, is trimmed at the fence as on the drone.
    pub fn flying(actor: A) -> Self {
        ActorPolicy {
            flight_rules: true,
            ..ActorPolicy::new(actor)
        }
    }

    /// Wraps `actor` and records every observation it sees.
    pub fn recording(actor: A) -> Self {
        ActorPolicy {
            recorded: Some(Vec::new()),
            ..ActorPolicy::new(actor)
        }
    }

    /// The wrapped actor.
    pub fn actor(&self) -> &A {
        &self.actor
    }
}

impl<A: Infer> Policy for ActorPolicy<A> {
    fn reset(&mut self, world: &World, _seed: u64) {
        self.buffers.fill(world);
        self.loaded_step = Some(world.step);
        self.previous_step = None;
        if self.keep_apart {
            self.track_velocities(world);
        }
    }

    fn act(&mut self, world: &World, herder: usize) -> [f64; 3] {
        // The f32 copy of the world is made once per step; herder 0 starts a new step (a reset
        // can leave the step counter equal, so it always reloads).
        if herder == 0 || self.loaded_step != Some(world.step) {
            self.buffers.fill(world);
            self.loaded_step = Some(world.step);
            if self.keep_apart && self.previous_step != Some(world.step) {
                self.track_velocities(world);
            }
        }
        let limits = self.flight_rules.then(|| {
            let a = world.area;
            Limits::arena(
                [a.width as f32, a.depth as f32, a.ceiling as f32],
                world.limits.herder as f32,
            )
        });
        let own = world.herders.get(herder).map(|h| h.map(|c| c as f32));
        let encoded = match (limits, own) {
            // As the daemon: the height above the band's floor (core.rs, `encoded_own`).
            (Some(l), Some(p)) => self.buffers.encode_at_altitude(
                herder,
                (p[2] - l.fence_min[2]).max(0.0),
                &mut self.features,
            ),
            _ => self.buffers.encode(herder, &mut self.features),
        };
        // The drone's failsafe for an unusable observation: hold position (through the rules).
        let request = match encoded {
            Ok(frame) => {
                if let Some(log) = self.recorded.as_mut() {
                    log.push((world.task, self.features));
                }
                frame.action_to_world(self.actor.infer(world.task, &self.features))
            }
            Err(_) => [0.0; 3],
        };
        // Keep apart first; the flight rules still have the last word (as in the daemon).
        let request = match own {
            Some(position) if self.keep_apart && encoded.is_ok() => {
                let config = match &limits {
                    Some(l) => self.separation(world).within(l),
                    None => self.separation(world),
                };
                self.peers.clear();
                for (i, p) in world.herders.iter().enumerate() {
                    if i != herder {
                        self.peers.push(Peer {
                            position: p.map(|c| c as f32),
                            velocity: self.velocities.get(i).copied().unwrap_or([0.0; 3]),
                            age_s: 0.0,
                        });
                    }
                }
                let velocity = self.velocities.get(herder).copied().unwrap_or([0.0; 3]);
                separate(&config, position, velocity, request, &self.peers).velocity
            }
            _ => request,
        };
        match (limits, own) {
            (Some(l), Some(position)) => safety::check(
                &l,
                &Situation {
                    position,
                    velocity: request,
                    snapshot_age_s: 0.0,
                    snapshot_finite: true,
                    current_velocity: None,
                },
            )
            .velocity
            .map(f64::from),
            _ => request.map(f64::from),
        }
    }
}

/// Why a model file could not be used as a policy.
#[derive(Debug)]
pub enum ModelPolicyError {
    /// The file could not be read.
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The bytes are not a model for this build's encoder.
    Format {
        /// The file.
        path: PathBuf,
        /// What was wrong.
        source: FormatError,
    },
}

impl fmt::Display for ModelPolicyError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ModelPolicyError::Read { path, source } => {
                write!(f, "cannot read model {}: {source}", path.display())
            }
            ModelPolicyError::Format { path, source } => {
                write!(f, "model {} rejected: {source}", path.display())
            }
        }
    }
}

impl std::error::Error for ModelPolicyError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            ModelPolicyError::Read { source, .. } => Some(source),
            ModelPolicyError::Format { source, .. } => Some(source),
        }
    }
}

/// A quantized model file as a [`PolicyFactory`]: every policy runs the onboard `Actor` under the
/// daemon's flight rules ([`ActorPolicy::flying`]).
#[derive(Clone, Debug)]
pub struct ModelPolicy {
    name: String,
    actor: Actor<'static>,
    keep_apart: bool,
    braking: Option<Braking>,
}

impl ModelPolicy {
    /// Loads and validates `path`. The bytes stay alive for the rest of the process (the
    /// zero-copy `Actor` borrows them); a run loads a handful of models at most.
    pub fn from_file(path: &Path) -> Result<Self, ModelPolicyError> {
        let bytes = skyherd_model::read_model_file(path).map_err(|e| ModelPolicyError::Read {
            path: path.to_owned(),
            source: match e {
                skyherd_model::ReadModelError::Io(e) => e,
                too_large => std::io::Error::new(std::io::ErrorKind::InvalidData, too_large),
            },
        })?;
        let name = path
            .file_stem()
            .map_or_else(|| "model".to_owned(), |s| s.to_string_lossy().into_owned());
        Self::from_bytes(name, bytes).map_err(|source| ModelPolicyError::Format {
            path: path.to_owned(),
            source,
        })
    }

    /// Validates `bytes` as a model called `name` in reports.
    pub fn from_bytes(name: String, bytes: Vec<u8>) -> Result<Self, FormatError> {
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        Ok(ModelPolicy {
            name,
            actor: Actor::from_bytes(bytes)?,
            keep_apart: false,
            braking: None,
        })
    }

    /// The same model with the daemon's separation rule on ([`ActorPolicy::keeping_apart`]);
    /// its name in reports gets `+apart`.
    pub fn keeping_apart(mut self) -> Self {
        self.keep_apart = true;
        self.name.push_str("+apart");
        self
    }

    /// The same model, its separation rule counting herders that answer as `braking` says
    /// ([`ActorPolicy::responding_in`]).
    pub fn responding_in(mut self, braking: Option<Braking>) -> Self {
        self.braking = braking;
        self
    }

    /// The onboard actor.
    pub fn actor(&self) -> &Actor<'static> {
        &self.actor
    }
}

impl PolicyFactory for ModelPolicy {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn make(&self) -> Box<dyn Policy + Send> {
        Box::new(
            ActorPolicy::flying(self.actor)
                .keeping_apart(self.keep_apart)
                .responding_in(self.braking),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::closest_pair_m;
    use crate::{Env, HerderCount, Scenario};

    /// "Full speed forward, up" whatever the observation.
    struct Forward;
    impl Infer for Forward {
        fn infer(&self, _: Task, _: &[f32; FEATURES]) -> [f32; 3] {
            [1.0, 0.0, 1.0]
        }
    }

    #[test]
    fn every_herder_gets_its_own_observation_and_a_capped_velocity() {
        let mut scenario = Scenario::paper_drive().without_noise();
        scenario.targets = 8;
        scenario.herders = HerderCount::Fixed(3);
        let env = Env::new(scenario).expect("valid scenario");
        let world = env.observation();
        let mut policy = ActorPolicy::recording(Forward);
        policy.reset(world, 0);
        for h in 0..3 {
            let v = policy.act(world, h);
            let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((speed - world.limits.herder).abs() < 1e-3, "speed {speed}");
        }
        let recorded = policy.recorded.expect("recording");
        assert_eq!(recorded.len(), 3);
        assert_ne!(recorded[0].1, recorded[1].1, "herders see different worlds");
    }

    /// A world of one herder `at`, four targets at (250, 250) and the goal due east of them.
    fn herder_at(at: [f64; 3]) -> World {
        let mut scenario = Scenario::paper_drive().without_noise();
        scenario.targets = 4;
        scenario.herders = HerderCount::Fixed(1);
        let mut world = Env::new(scenario).expect("valid scenario").reset(0).clone();
        world.targets = vec![
            [250.0, 250.0],
            [252.0, 250.0],
            [250.0, 252.0],
            [252.0, 252.0],
        ];
        world.goal.center = [400.0, 251.0];
        world.herders = vec![at];
        world
    }

    #[test]
    fn keeping_apart_opens_two_herders_to_the_breach_distance() {
        // Two herders 1 m apart, both flying "forward" at the flock: without the rule they
        // stay 1 m apart; with it they open past the arena's 3 m and stay there.
        let fly = |keep_apart: bool| {
            let mut world = herder_at([200.0, 251.0, 2.0]);
            world.herders = vec![[200.0, 250.5, 2.0], [200.0, 251.5, 2.0]];
            let mut policy = ActorPolicy::flying(Forward).keeping_apart(keep_apart);
            policy.reset(&world, 0);
            let mut closest = f64::INFINITY;
            for _ in 0..8 {
                let actions: Vec<[f64; 3]> = (0..2).map(|h| policy.act(&world, h)).collect();
                for (p, v) in world.herders.iter_mut().zip(&actions) {
                    for k in 0..3 {
                        p[k] += v[k] * world.dt;
                    }
                }
                world.step += 1;
                closest = closest_pair_m(&world.herders);
            }
            closest
        };
        let bare = fly(false);
        assert!(bare < 1.5, "without the rule they stay close: {bare} m");
        let apart = fly(true);
        assert!(apart >= 3.0, "with it they open past 3 m: {apart} m");
    }

    #[test]
    fn flying_keeps_the_bare_actor_inside_the_fence() {
        // 0.3 m from the east wall, beyond the 1 m fence; "forward" is east, into the wall.
        let world = herder_at([499.7, 251.0, 2.0]);
        let bare = ActorPolicy::new(Forward).act(&world, 0);
        assert!(
            bare[0] > 3.0,
            "the bare actor flies into the wall: {bare:?}"
        );
        let flown = ActorPolicy::flying(Forward).act(&world, 0);
        assert!(
            flown[0] < 0.0,
            "outside the fence it steers back in: {flown:?}"
        );
        let speed = (flown[0] * flown[0] + flown[1] * flown[1] + flown[2] * flown[2]).sqrt();
        assert!(speed <= world.limits.herder + 1e-6, "{speed}");

        // Well inside, the rules only cap the climb at 2 m/s, keeping the direction.
        let world = herder_at([300.0, 251.0, 2.0]);
        let bare = ActorPolicy::new(Forward).act(&world, 0);
        let flown = ActorPolicy::flying(Forward).act(&world, 0);
        let keep = 2.0 / bare[2];
        for k in 0..3 {
            assert!(
                (flown[k] - keep * bare[k]).abs() < 1e-4,
                "{bare:?} vs {flown:?}"
            );
        }
    }

    #[test]
    fn flying_reads_the_height_above_the_band_floor() {
        // At the 0.5 m floor the actor sees itself on the ground (feature 22 is 0), as onboard.
        let world = herder_at([300.0, 251.0, 0.5]);
        let mut flown = ActorPolicy {
            recorded: Some(Vec::new()),
            ..ActorPolicy::flying(Forward)
        };
        let mut bare = ActorPolicy::recording(Forward);
        flown.act(&world, 0);
        bare.act(&world, 0);
        let (flown, bare) = (flown.recorded.unwrap()[0].1, bare.recorded.unwrap()[0].1);
        assert_eq!(flown[22], 0.0);
        assert!(bare[22] > 0.0);
        assert_eq!(flown[..22], bare[..22]);
        assert_eq!(flown[23..], bare[23..]);
    }

    #[test]
    fn a_broken_model_file_is_a_clear_error() {
        let dir = std::env::temp_dir().join(format!("skyherd-learned-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("broken.skym");
        std::fs::write(&path, b"SKYMnot a model").unwrap();
        let err = ModelPolicy::from_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("broken.skym") && err.contains("rejected"),
            "{err}"
        );
        let missing = ModelPolicy::from_file(&dir.join("missing.skym")).unwrap_err();
        assert!(missing.to_string().contains("cannot read"), "{missing}");
    }
}
