//! The environment: a [`World`] plus spawn, noise, reward and termination, behind `reset`/`step`;
//! and a batched form that steps many environments on all cores.
//!
//! ```
//! use skyherd_sim::{Env, Scenario, Policy};
//! use skyherd_sim::baseline::Method;
//! use skyherd_sim::policy::PolicyFactory;
//!
//! let mut scenario = Scenario::paper_drive();
//! scenario.targets = 8;
//! scenario.step_limit = 50;
//! let mut env = Env::new(scenario).unwrap();
//! let mut policy = Method::FarthestTargets.make();
//! policy.reset(env.reset(7), 7);
//! let mut actions = Vec::new();
//! loop {
//!     skyherd_sim::policy::act_all(policy.as_mut(), env.observation(), &mut actions);
//!     let out = env.step(&actions).unwrap();
//!     if out.terminated || out.truncated {
//!         break;
//!     }
//! }
//! assert!(env.world().step <= 50);
//! ```

use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::dynamics::{Multicopter, Wind};
use crate::noise::{Stream, actuate, perturb_params, sense, stream_rng};
use crate::policy::{Policy, act_all};
use crate::reward::{RewardParams, RewardTerms, StepFacts, reward};
use crate::scenario::{Scenario, ScenarioError};
use crate::task::{lower_bound_time, spawn};
use crate::world::{StepScratch, World, WorldError, advance, closest_pair_m, dist2};

/// What one step produced.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepOutcome {
    /// The learner's reward: the paper's plus the scenario's correction (if any).
    pub reward: f64,
    /// The paper's reward, eq (7) times k0, whatever the correction.
    pub paper_reward: f64,
    /// Each weighted term.
    pub terms: RewardTerms,
    /// The episode ended by success or by leaving the arena (no bootstrap past it).
    pub terminated: bool,
    /// The episode hit the step limit without terminating (bootstrap past it).
    pub truncated: bool,
    /// Every target is in the goal and nothing left the arena.
    pub success: bool,
    /// Some herder or target left the arena.
    pub left_area: bool,
}

/// Why a step was refused.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum EnvError {
    /// The actions do not fit the world.
    #[error(transparent)]
    World(#[from] WorldError),
    /// The episode already ended; call `reset`.
    #[error("the episode is over; call reset first")]
    EpisodeOver,
    /// A batch got a different number of action lists than it has environments.
    #[error("expected {expected} action lists, one per environment, got {got}")]
    BatchSize {
        /// Environments in the batch.
        expected: usize,
        /// Action lists given.
        got: usize,
    },
    /// The scenario is invalid.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// A herder index past the world's herders.
    #[error("no herder {herder}: the world has {herders}")]
    NoSuchHerder {
        /// The index asked for.
        herder: usize,
        /// Herders in the world.
        herders: usize,
    },
}

/// Per-episode bookkeeping beside the state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EpisodeInfo {
    /// The seed given to `reset`.
    pub seed: u64,
    /// Steps taken.
    pub steps: u64,
    /// Total herder travel so far, metres (eq 11's distances summed).
    pub path_length: f64,
    /// [`lower_bound_time`] at reset, seconds.
    pub lower_bound_s: f64,
    /// Sum of rewards so far.
    pub return_total: f64,
    /// Sum of the paper's rewards so far.
    pub paper_return_total: f64,
    /// Whether the episode has ended.
    pub done: bool,
    /// Whether it ended in success.
    pub success: bool,
}

/// One shepherding environment.
#[derive(Clone, Debug)]
pub struct Env {
    scenario: Scenario,
    world: World,
    observed: World,
    scratch: StepScratch,
    sensing_rng: ChaCha8Rng,
    actuation_rng: ChaCha8Rng,
    goal_distance: Vec<f64>,
    previous_herders: Vec<[f64; 3]>,
    noisy_actions: Vec<[f64; 3]>,
    info: EpisodeInfo,
    /// With `scenario.dynamics`: each herder's multicopter, wind and last command (m/s), and
    /// the wind's stream.
    drones: Vec<(Multicopter, Wind, [f64; 3])>,
    wind_rng: ChaCha8Rng,
    /// With [`Env::keep_last_step`]: the true world as the last step found it (the velocities
    /// it was advanced with stay in `noisy_actions` until the next step).
    last_step_start: Option<World>,
}

/// Reusable buffers for [`Env::replay_last_step_without`] (no allocation once warm).
#[derive(Clone, Debug, Default)]
pub struct ReplayScratch {
    step: StepScratch,
    flown: Vec<[f64; 3]>,
}

/// Sub-step of the motion model inside one environment step, s (at most; the step is split
/// evenly): a 1 s paper step is far too coarse for a 0.3 s lag.
const MOTION_STEP_S: f64 = 0.02;

impl Env {
    /// An environment for `scenario` (validated again here), reset with the scenario's seed.
    pub fn new(scenario: Scenario) -> Result<Env, ScenarioError> {
        scenario.validate()?;
        let n = scenario.targets;
        let m = scenario.herder_count();
        let world = World {
            task: scenario.task,
            area: scenario.area,
            goal: crate::world::Goal {
                center: [0.0, 0.0],
                radius: scenario.layout.goal_radius,
            },
            params: scenario.boids,
            limits: scenario.limits,
            dt: scenario.dt,
            step: 0,
            herders: vec![[0.0; 3]; m],
            targets: vec![[0.0; 2]; n],
            target_velocities: vec![[0.0; 2]; n],
        };
        let seed = scenario.seed;
        let mut env = Env {
            observed: world.clone(),
            world,
            scenario,
            scratch: StepScratch::with_capacity(n),
            sensing_rng: stream_rng(seed, Stream::Sensing),
            actuation_rng: stream_rng(seed, Stream::Actuation),
            goal_distance: vec![0.0; n],
            previous_herders: vec![[0.0; 3]; m],
            noisy_actions: Vec::with_capacity(m),
            info: EpisodeInfo::default(),
            drones: Vec::new(),
            wind_rng: stream_rng(seed, Stream::Wind),
            last_step_start: None,
        };
        env.reset(seed);
        Ok(env)
    }

    /// Starts a new episode from `seed` (spawn, boids-parameter noise, noise streams) and
    /// returns the first observation.
    pub fn reset(&mut self, seed: u64) -> &World {
        let s = &self.scenario;
        let mut spawn_rng = stream_rng(seed, Stream::Spawn);
        let sp = spawn(
            s.task,
            &s.layout,
            &s.area,
            s.herder_count(),
            s.targets,
            &mut spawn_rng,
        );
        let mut param_rng = stream_rng(seed, Stream::BoidsParams);
        self.world.params = perturb_params(s.boids, s.noise.boids_param_rel_std, &mut param_rng);
        self.world.goal = sp.goal;
        self.world.herders.clone_from(&sp.herders);
        self.world.targets.clone_from(&sp.targets);
        self.world.target_velocities.fill([0.0, 0.0]);
        self.world.step = 0;
        self.sensing_rng = stream_rng(seed, Stream::Sensing);
        self.actuation_rng = stream_rng(seed, Stream::Actuation);
        self.reset_drones(seed);
        let goal = self.world.goal.center;
        for (d, &t) in self.goal_distance.iter_mut().zip(&self.world.targets) {
            *d = dist2(t, goal).sqrt();
        }
        self.info = EpisodeInfo {
            seed,
            lower_bound_s: lower_bound_time(&self.world),
            ..EpisodeInfo::default()
        };
        self.forget_last_step();
        self.refresh_observation();
        self.observation()
    }

    /// Starts an episode from a given state instead of a spawn (tests, curricula, replays).
    /// The boids parameters, step and shapes come from `world`; the noise streams from `seed`.
    /// The scenario's task, area and herder/target counts are replaced by the world's.
    pub fn reset_to(&mut self, world: World, seed: u64) -> Result<&World, EnvError> {
        world.validate()?;
        let n = world.targets.len();
        self.scenario.task = world.task;
        self.scenario.area = world.area;
        self.scenario.targets = n;
        self.scenario.herders = crate::scenario::HerderCount::Fixed(world.herders.len());
        self.goal_distance.clear();
        self.goal_distance.extend(
            world
                .targets
                .iter()
                .map(|&t| dist2(t, world.goal.center).sqrt()),
        );
        self.world = world;
        self.sensing_rng = stream_rng(seed, Stream::Sensing);
        self.actuation_rng = stream_rng(seed, Stream::Actuation);
        self.reset_drones(seed);
        self.info = EpisodeInfo {
            seed,
            lower_bound_s: lower_bound_time(&self.world),
            ..EpisodeInfo::default()
        };
        self.forget_last_step();
        self.refresh_observation();
        Ok(self.observation())
    }

    /// With dynamics: every herder hovering where it is, its gusts drawn from the episode's
    /// wind stream.
    fn reset_drones(&mut self, seed: u64) {
        self.drones.clear();
        self.wind_rng = stream_rng(seed, Stream::Wind);
        if let Some(d) = self.scenario.dynamics {
            for h in &self.world.herders {
                let wind = Wind::new(&d.wind, &mut self.wind_rng);
                self.drones
                    .push((Multicopter::hovering_at(*h), wind, [0.0; 3]));
            }
        }
    }

    /// With dynamics: replaces each commanded velocity by the mean velocity the herder's
    /// multicopter flies over the step (so that velocity * dt is where it goes).
    fn fly_drones(&mut self) {
        let Some(d) = self.scenario.dynamics else {
            return;
        };
        let dt = self.world.dt;
        let steps = (dt / MOTION_STEP_S).ceil().max(1.0) as usize;
        let h = dt / steps as f64;
        for ((drone, wind, previous), (action, herder)) in self
            .drones
            .iter_mut()
            .zip(self.noisy_actions.iter_mut().zip(&self.world.herders))
        {
            // The world is the truth (it caps speeds and the ceiling): start from it.
            drone.position = *herder;
            let command = *action;
            for k in 0..steps {
                let air = wind.step(&d.wind, h, &mut self.wind_rng);
                // The new command arrives `command_delay_s` into the step.
                let flying = if (k as f64) * h < d.command_delay_s - 1e-9 {
                    *previous
                } else {
                    command
                };
                drone.step(flying, air, &d.limits, h);
            }
            *previous = command;
            *action = std::array::from_fn(|k| (drone.position[k] - herder[k]) / dt);
        }
    }

    fn refresh_observation(&mut self) {
        if self.scenario.noise.sensing_std <= 0.0 {
            // `observation()` hands out the true world; no copy needed.
            return;
        }
        sense(
            &self.world,
            &mut self.observed,
            self.scenario.noise.sensing_std,
            &mut self.sensing_rng,
        );
    }

    /// Applies the herders' commands (m/s, sim frame; actuation noise and the speed cap are the
    /// environment's) and advances one step.
    pub fn step(&mut self, actions: &[[f64; 3]]) -> Result<StepOutcome, EnvError> {
        if self.info.done {
            return Err(EnvError::EpisodeOver);
        }
        self.previous_herders.clone_from(&self.world.herders);
        if let Some(start) = self.last_step_start.as_mut() {
            start.clone_from(&self.world);
        }
        self.noisy_actions.clear();
        self.noisy_actions.extend_from_slice(actions);
        actuate(
            &mut self.noisy_actions,
            self.scenario.noise.actuation_std,
            &mut self.actuation_rng,
        );
        self.fly_drones();
        advance(&mut self.world, &self.noisy_actions, &mut self.scratch)?;
        for ((drone, _, _), herder) in self.drones.iter_mut().zip(&self.world.herders) {
            drone.position = *herder;
        }

        let goal = self.world.goal;
        let r2 = goal.radius * goal.radius;
        let mut closer_sum = 0.0;
        let mut all_in = true;
        let mut left = false;
        for (last, &t) in self.goal_distance.iter_mut().zip(&self.world.targets) {
            let d2 = dist2(t, goal.center);
            all_in &= d2 <= r2;
            left |= !self.world.area.contains_xy(t);
            let d = d2.sqrt();
            closer_sum += *last - d;
            *last = d;
        }
        let mut travel = 0.0;
        for (h, p) in self.world.herders.iter().zip(&self.previous_herders) {
            let d = [h[0] - p[0], h[1] - p[1], h[2] - p[2]];
            travel += (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            left |= !self.world.area.contains_xy([h[0], h[1]]);
        }
        let success = all_in && !left;
        let step = self.world.step;
        let limit = self.scenario.step_limit;
        let terminated = success || left;
        let truncated = !terminated && step >= limit;
        let terms = reward(
            &self.scenario.reward,
            &StepFacts {
                success,
                left_area: left,
                closer_sum,
                targets: self.world.targets.len(),
                herder_travel: travel,
                steps_left: limit.saturating_sub(step),
            },
        );
        let outcome = StepOutcome {
            reward: terms.total(),
            paper_reward: terms.paper(),
            terms,
            terminated,
            truncated,
            success,
            left_area: left,
        };
        self.info.steps = step;
        self.info.path_length += travel;
        self.info.return_total += outcome.reward;
        self.info.paper_return_total += outcome.paper_reward;
        self.info.done = terminated || truncated;
        self.info.success = success;
        self.refresh_observation();
        Ok(outcome)
    }

    /// A new episode has taken no step yet: nothing to replay.
    fn forget_last_step(&mut self) {
        if let Some(start) = self.last_step_start.as_mut() {
            start.clone_from(&self.world);
        }
    }

    /// Keep a copy of the true world as each step finds it, so that
    /// [`Env::replay_last_step_without`] can replay that step (off by default: it costs a copy
    /// of the world per step). Turning it on takes effect from the next step.
    pub fn keep_last_step(&mut self, keep: bool) {
        if !keep {
            self.last_step_start = None;
        } else if self.last_step_start.is_none() {
            self.last_step_start = Some(self.world.clone());
        }
    }

    /// The last step replayed as if herder `herder` had not been there: the true world as
    /// that step found it, without that herder, advanced by the boids rules with the other
    /// herders' velocities exactly as they were flown (actuation noise and dynamics included),
    /// written into `out`. The targets' motion is deterministic given those, so `out` differs
    /// from [`Env::world`] only by what that one herder did to the flock in that step: the
    /// counterfactual of a difference reward (Wolpert and Tumer 2002).
    ///
    /// `Ok(false)` (and `out` untouched) when no step has been taken since the episode began
    /// or [`Env::keep_last_step`] is off.
    pub fn replay_last_step_without(
        &self,
        herder: usize,
        out: &mut World,
        scratch: &mut ReplayScratch,
    ) -> Result<bool, EnvError> {
        let Some(start) = self.last_step_start.as_ref() else {
            return Ok(false);
        };
        if self.world.step == 0 || start.step + 1 != self.world.step {
            return Ok(false);
        }
        if herder >= start.herders.len() {
            return Err(EnvError::NoSuchHerder {
                herder,
                herders: start.herders.len(),
            });
        }
        out.clone_from(start);
        out.herders.remove(herder);
        scratch.flown.clone_from(&self.noisy_actions);
        scratch.flown.remove(herder);
        advance(out, &scratch.flown, &mut scratch.step)?;
        Ok(true)
    }

    /// What the herders sense: the world with sensing noise (the true world when it is off).
    pub fn observation(&self) -> &World {
        if self.scenario.noise.sensing_std <= 0.0 {
            &self.world
        } else {
            &self.observed
        }
    }

    /// The true state.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// The scenario this environment runs.
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }

    /// Reward constants in force.
    pub fn reward_params(&self) -> &RewardParams {
        &self.scenario.reward
    }

    /// Episode bookkeeping.
    pub fn info(&self) -> EpisodeInfo {
        self.info
    }
}

/// The result of one whole episode.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeSummary {
    /// Seed of the episode.
    pub seed: u64,
    /// All targets reached the goal.
    pub success: bool,
    /// Some object left the arena.
    pub left_area: bool,
    /// Steps taken.
    pub steps: u64,
    /// Seconds simulated (`steps * dt`).
    pub time_s: f64,
    /// Total herder travel, metres.
    pub path_length: f64,
    /// Time lower bound, seconds.
    pub lower_bound_s: f64,
    /// Sum of rewards (with the correction).
    pub return_total: f64,
    /// Sum of the paper's rewards.
    pub paper_return_total: f64,
    /// The closest two herders came (3-D, m) after any step (the spawn is not counted: it is
    /// not theirs to choose); infinity with one herder.
    pub min_separation_m: f64,
}

/// Runs one episode of `env` from `seed` under `policy`; `on_step` sees the true world after
/// reset (with `None`) and after every step.
pub fn run_episode(
    env: &mut Env,
    policy: &mut dyn Policy,
    seed: u64,
    mut on_step: impl FnMut(&World, Option<&StepOutcome>),
) -> Result<EpisodeSummary, EnvError> {
    let first = env.reset(seed);
    policy.reset(first, seed);
    on_step(env.world(), None);
    // In flight: where the herders spawn is not theirs to choose, so the first measurement is
    // after their first step.
    let mut min_separation_m = f64::INFINITY;
    let mut actions = Vec::with_capacity(env.world().herders.len());
    let last = loop {
        act_all(policy, env.observation(), &mut actions);
        let out = env.step(&actions)?;
        min_separation_m = min_separation_m.min(closest_pair_m(&env.world().herders));
        on_step(env.world(), Some(&out));
        if out.terminated || out.truncated {
            break out;
        }
    };
    let info = env.info();
    Ok(EpisodeSummary {
        seed,
        success: info.success,
        left_area: last.left_area,
        steps: info.steps,
        time_s: info.steps as f64 * env.world().dt,
        path_length: info.path_length,
        lower_bound_s: info.lower_bound_s,
        return_total: info.return_total,
        paper_return_total: info.paper_return_total,
        min_separation_m,
    })
}

/// Many environments stepped together on all cores (rayon); each keeps its own state and noise
/// streams, so results do not depend on the thread count.
#[derive(Clone, Debug)]
pub struct BatchEnv {
    envs: Vec<Env>,
}

impl BatchEnv {
    /// `count` environments of `scenario`.
    pub fn new(scenario: &Scenario, count: usize) -> Result<BatchEnv, ScenarioError> {
        let envs = (0..count)
            .map(|_| Env::new(scenario.clone()))
            .collect::<Result<_, _>>()?;
        Ok(BatchEnv { envs })
    }

    /// The environments.
    pub fn envs(&self) -> &[Env] {
        &self.envs
    }

    /// Mutable access, e.g. to reset one that finished.
    pub fn envs_mut(&mut self) -> &mut [Env] {
        &mut self.envs
    }

    /// Resets environment `i` with `seeds[i]`, in parallel.
    pub fn reset_all(&mut self, seeds: &[u64]) {
        self.envs
            .par_iter_mut()
            .zip(seeds.par_iter())
            .for_each(|(env, &seed)| {
                env.reset(seed);
            });
    }

    /// Steps environment `i` with `actions[i]`, in parallel. Any error (a wrong batch size, an
    /// environment whose episode is over: reset those first) fails the whole call.
    pub fn step_all(&mut self, actions: &[Vec<[f64; 3]>]) -> Result<Vec<StepOutcome>, EnvError> {
        if actions.len() != self.envs.len() {
            return Err(EnvError::BatchSize {
                expected: self.envs.len(),
                got: actions.len(),
            });
        }
        self.envs
            .par_iter_mut()
            .zip(actions.par_iter())
            .map(|(env, a)| env.step(a))
            .collect()
    }
}

/// Runs `seeds.len()` episodes of `scenario` in parallel, each with a fresh policy from `make`.
/// Results come back in seed order whatever the thread count.
pub fn run_episodes_parallel<P: Policy>(
    scenario: &Scenario,
    seeds: &[u64],
    make: impl Fn() -> P + Sync,
) -> Result<Vec<EpisodeSummary>, EnvError> {
    let env = Env::new(scenario.clone())?;
    seeds
        .par_iter()
        .map_with(env, |env, &seed| {
            let mut policy = make();
            run_episode(env, &mut policy, seed, |_, _| {})
        })
        .collect()
}
