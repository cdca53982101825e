//! Experience collection: a set of simulator environments stepped together, every herder acting
//! on its own encoded observation (decentralised execution), one transition per herder per step
//! into the replay buffer of the environment's task.
//!
//! The learner's reward is the simulator's (with its documented leave correction when enabled),
//! optionally with a weaker flight term, divided by the episode's step cost when normalising
//! (see [`crate::config::RewardConfig`]).

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use skyherd_model::Task;
use skyherd_onboard::obs::{FEATURES, LocalFrame};
use skyherd_onboard::safety::{self, Limits, Situation};
use skyherd_sim::baseline::{Method, RulePolicy};
use skyherd_sim::obs::EncoderBuffers;
use skyherd_sim::policy::act_all;
use skyherd_sim::{Env, EnvError, HerderCount, Policy, RewardCorrection, Scenario};

use crate::config::{
    CurriculumStage, LoopConfig, ROOM_LAYOUT_MAX_TARGETS, RewardConfig, TrainConfig,
    WarmStartConfig,
};
use crate::ddpg::{
    ACTION_DIM, DdpgConfig, Exploration, FASTER_MIN, FASTER_WINDOW, PARAMETER_NOISE_ADAPT,
    PARAMETER_NOISE_INITIAL_SCALE, PARAMETER_NOISE_ROWS, SelfImitationEpisodes,
};
use crate::network::{MultiTaskMlp, Tape};
use crate::replay::{NStep, OneStep, Others, ReplayBuffer, pool_others};
use crate::reward::LearnerReward;

/// One training scenario: task, N and M (0 = adaptive).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Draw {
    /// The task.
    pub task: Task,
    /// Targets N.
    pub targets: usize,
    /// Herders M, 0 for the adaptive count.
    pub herders: usize,
    /// The indoor room's layout at paper scale instead of the paper's (see
    /// `LoopConfig::room_layout_fraction`).
    pub room: bool,
    /// The share of the spawned distance to the goal kept, in thousandths (1000: the layout's
    /// own). Driving: of the start-goal distance, the goal moved (`GoalDistanceCurriculum`);
    /// collecting: of each target's distance beyond the goal's edge, the targets moved
    /// ([`pull_targets_to_goal`]). An integer so that a draw stays `Eq`.
    pub goal_distance_permille: u16,
    /// Driving: the share of each herder's spawned distance to the flock kept, in thousandths
    /// (1000: where the layout put it; see `SpawnShareCurriculum`).
    pub herder_distance_permille: u16,
}

impl Draw {
    /// A paper-layout draw.
    pub fn paper(task: Task, targets: usize, herders: usize) -> Draw {
        Draw {
            task,
            targets,
            herders,
            room: false,
            goal_distance_permille: 1000,
            herder_distance_permille: 1000,
        }
    }
}

/// Whether a draw of `task` with `targets` goes into the room layout.
fn draw_room(config: &TrainConfig, rng: &mut ChaCha8Rng, task: Task, targets: usize) -> bool {
    task == Task::Driving
        && targets <= ROOM_LAYOUT_MAX_TARGETS
        && config.training.room_layout_fraction > 0.0
        && rng.random_bool(config.training.room_layout_fraction.min(1.0))
}

/// A configured herder count as the simulator's: 0 is the adaptive count, anything else fixed.
pub fn herder_count(herders: usize) -> HerderCount {
    if herders == 0 {
        HerderCount::Adaptive
    } else {
        HerderCount::Fixed(herders)
    }
}

/// The paper scenario of `draw`, with the learner's step limit, noise on or off, and the
/// simulator's leave correction at the learner's gamma when `reward.leave_correction`.
pub fn training_scenario(
    draw: Draw,
    step_limit: u64,
    noise: bool,
    reward: &RewardConfig,
    gamma: f64,
) -> Scenario {
    let mut s = Scenario::paper(draw.task);
    if draw.room {
        // The indoor preset's layout, zoomed back up to the paper arena (10 m room -> 500 m).
        let room = Scenario::indoor();
        let zoom = s.area.width / room.area.width;
        s.layout.wall_margin = room.layout.wall_margin * zoom;
        s.layout.min_start_goal_distance = room.layout.min_start_goal_distance * zoom;
    }
    s.targets = draw.targets;
    s.herders = herder_count(draw.herders);
    s.step_limit = step_limit;
    if !noise {
        s = s.without_noise();
    }
    if reward.leave_correction {
        s.reward.correction = RewardCorrection::LeaveCoversRemainingSteps { gamma };
    }
    s
}

/// The other herders of herder `own` whose observation the encoder gave, nearest first (by
/// ground distance, ties by index), at most `max`: the ones a centralised critic pools.
pub fn nearest_others(
    positions: &[[f64; 3]],
    own: usize,
    max: usize,
    frames: &[Option<LocalFrame>],
) -> Vec<usize> {
    let p = positions[own];
    let mut others: Vec<(f64, usize)> = (0..positions.len())
        .filter(|&j| j != own && frames.get(j).is_some_and(Option::is_some))
        .map(|j| ((positions[j][0] - p[0]).hypot(positions[j][1] - p[1]), j))
        .collect();
    others.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    others.into_iter().take(max).map(|(_, j)| j).collect()
}

/// `world` with its goal moved along the line from the flock centroid, keeping `share` of the
/// distance (the goal stays inside the arena: both ends of the line are).
pub fn pull_goal(world: &skyherd_sim::World, share: f64) -> skyherd_sim::World {
    pull_goal_at_least(world, share, 0.0)
}

/// [`pull_goal`], keeping the goal's centre at least `min_radii` goal radii from the flock's
/// centroid (or where it was, if that is nearer).
pub fn pull_goal_at_least(
    world: &skyherd_sim::World,
    share: f64,
    min_radii: f64,
) -> skyherd_sim::World {
    let mut w = world.clone();
    let c = w.flock_centroid();
    let g = w.goal.center;
    let distance = (g[0] - c[0]).hypot(g[1] - c[1]);
    let mut share = share.clamp(0.0, 1.0);
    if distance > 0.0 {
        let floor = (min_radii.max(0.0) * w.goal.radius / distance).min(1.0);
        share = share.max(floor);
    }
    w.goal.center = [c[0] + share * (g[0] - c[0]), c[1] + share * (g[1] - c[1])];
    w
}

/// `world` with each herder moved along the line towards the flock's centroid, keeping `share`
/// of its ground distance but staying at least `keep_out` metres from the centroid (a herder
/// already nearer stays where it is). Altitude is kept; the herder stays inside the arena since
/// both ends of the line are.
pub fn pull_herders(world: &skyherd_sim::World, share: f64, keep_out: f64) -> skyherd_sim::World {
    let mut w = world.clone();
    let c = w.flock_centroid();
    let share = share.clamp(0.0, 1.0);
    for h in &mut w.herders {
        let distance = (h[0] - c[0]).hypot(h[1] - c[1]);
        if distance <= keep_out || distance <= 0.0 {
            continue;
        }
        let kept = (share * distance).max(keep_out.max(0.0)) / distance;
        h[0] = c[0] + kept * (h[0] - c[0]);
        h[1] = c[1] + kept * (h[1] - c[1]);
    }
    w
}

/// The least a pulled target keeps beyond the goal's edge, in goal radii: it still has to be
/// herded in.
pub const PULLED_TARGET_MIN_BEYOND_EDGE_RADII: f64 = 0.2;

/// `world` with each target outside the goal moved along the line towards the goal's centre,
/// keeping `share` of its distance beyond the goal's edge but at least
/// [`PULLED_TARGET_MIN_BEYOND_EDGE_RADII`] goal radii of it (a target already nearer stays where
/// it is). The target stays inside the arena since both ends of the line are. The collecting
/// curriculum's start states: scattered targets, but a shorter way to the goal.
pub fn pull_targets_to_goal(world: &skyherd_sim::World, share: f64) -> skyherd_sim::World {
    let mut w = world.clone();
    let g = w.goal.center;
    let r = w.goal.radius.max(0.0);
    let min_beyond = PULLED_TARGET_MIN_BEYOND_EDGE_RADII * r;
    let share = share.clamp(0.0, 1.0);
    for t in &mut w.targets {
        let distance = (t[0] - g[0]).hypot(t[1] - g[1]);
        let beyond = distance - r;
        if beyond <= min_beyond || distance <= 0.0 {
            continue;
        }
        let kept = (r + (share * beyond).max(min_beyond)) / distance;
        t[0] = g[0] + kept * (t[0] - g[0]);
        t[1] = g[1] + kept * (t[1] - g[1]);
    }
    w
}

/// What one finished training episode did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeStats {
    /// The scenario.
    pub draw: Draw,
    /// All targets reached the goal.
    pub success: bool,
    /// Steps taken.
    pub steps: u64,
    /// Sum of learner rewards.
    pub learner_return: f64,
    /// Sum of the paper's rewards.
    pub paper_return: f64,
}

/// Who picks the actions.
pub enum Controller<'a> {
    /// The learned actor plus exploration noise of this std (normalised units), drawn as
    /// [`DdpgConfig::exploration`] says (for parameter-space noise: the RMS distance its
    /// perturbed actors' actions are kept at from the actor's).
    Actor(&'a MultiTaskMlp, f32),
    /// The random-waypoint warm-up: every herder flies at full speed towards a point drawn
    /// uniformly in the arena, and draws a new one when it gets there (or after
    /// [`WAYPOINT_STEPS`] steps). Fills the replay with varied, purposeful flight before the
    /// actor has learned anything.
    RandomWaypoints,
    /// The actor as [`Controller::Actor`], except in the environments of the tasks marked
    /// (`Task::index`), which fly [`Controller::RandomWaypoints`]: a task started over by a
    /// stalled-task reset has a warm-up of its own while the other task flies its actor.
    ActorExceptRandomTasks(&'a MultiTaskMlp, f32, [bool; Task::COUNT]),
    /// The rule-based baselines, one per task and flock (the warm start's teacher table); their
    /// velocities are recorded as normalised local-frame actions.
    Baseline(&'a WarmStartConfig),
}

/// A warm-up waypoint is redrawn after this many steps even if not reached.
pub const WAYPOINT_STEPS: u64 = 60;

/// Per herder: its n-step accumulator, its Ornstein-Uhlenbeck noise state, its warm-up
/// waypoint and when it was drawn.
#[derive(Clone, Debug)]
struct HerderState {
    nstep: NStep,
    ou: [f32; ACTION_DIM],
    waypoint: Option<([f64; 2], u64)>,
    /// An exploration excursion under way: its waypoint and the step it ends at.
    excursion: Option<([f64; 2], u64)>,
    /// Self-imitation only: this episode's transitions so far, for their returns at its end.
    episode: EpisodeLog,
}

/// The steps of the last [`FASTER_WINDOW`] successes per scenario (task, N, M), for
/// [`SelfImitationEpisodes::FasterThanMedian`].
#[derive(Clone, Debug, Default)]
struct RecentSuccesses {
    steps: std::collections::HashMap<(usize, usize, usize), std::collections::VecDeque<u64>>,
}

impl RecentSuccesses {
    /// Whether an episode of `draw` that ended (`success`, in `steps`) may be imitated under
    /// `which`; records a success for later episodes.
    fn admits(
        &mut self,
        which: SelfImitationEpisodes,
        draw: Draw,
        success: bool,
        steps: u64,
    ) -> bool {
        match which {
            SelfImitationEpisodes::Ended => true,
            SelfImitationEpisodes::FasterThanMedian => {
                if !success {
                    return false;
                }
                let key = (draw.task.index(), draw.targets, draw.herders);
                let window = self.steps.entry(key).or_default();
                let faster = window.len() < FASTER_MIN || steps < median(window);
                window.push_back(steps);
                if window.len() > FASTER_WINDOW {
                    window.pop_front();
                }
                faster
            }
        }
    }
}

/// The median of a non-empty window (the upper one of an even count).
fn median(window: &std::collections::VecDeque<u64>) -> u64 {
    let mut sorted: Vec<u64> = window.iter().copied().collect();
    sorted.sort_unstable();
    sorted[sorted.len() / 2]
}

/// One herder's transitions of the running episode, kept (with self-imitation) so that their
/// returns can be written into the replay when the episode ends: `steps[k]` is the k-th step
/// pushed (its reward and simulator steps) and `stamps[k]` the replay stamp of the
/// transition that starts there, once pushed (n-step transitions come out in the order they
/// start).
#[derive(Clone, Debug, Default)]
struct EpisodeLog {
    steps: Vec<(f32, usize)>,
    stamps: Vec<u64>,
}

impl EpisodeLog {
    /// A broken chain (an observation the encoder refused): the steps kept so far are missing
    /// a reward, so none of them gets a return.
    fn clear(&mut self) {
        self.steps.clear();
        self.stamps.clear();
    }

    /// At the episode's end: each pushed transition's return-to-go into `replay`.
    fn write_returns(&mut self, replay: &mut ReplayBuffer, gamma: f32) {
        let returns = crate::replay::returns_to_go(&self.steps, gamma);
        for (&stamp, &ret) in self.stamps.iter().zip(&returns) {
            replay.set_return(stamp, ret);
        }
        self.clear();
    }
}

/// Exploration excursions ([`LoopConfig::excursion_rate`](crate::config::LoopConfig)): while
/// the actor flies, a herder now and then flies at full speed to a random point near a
/// random target, then hands back to the actor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Excursions {
    /// Probability per herder and step of starting one (0: off).
    pub rate: f64,
    /// Nearest and farthest distance of the waypoint from its target, metres.
    pub radius_m: [f64; 2],
    /// Steps one lasts at most.
    pub max_steps: u64,
    /// Which tasks' environments fly them (`Task::index`).
    pub tasks: [bool; Task::COUNT],
}

impl Excursions {
    /// The excursions `config` asks for.
    pub fn from_config(config: &LoopConfig) -> Excursions {
        let mut tasks = [false; Task::COUNT];
        for t in &config.excursion_tasks {
            tasks[t.index()] = true;
        }
        Excursions {
            rate: config.excursion_rate,
            radius_m: config.excursion_radius_m,
            max_steps: config.excursion_max_steps,
            tasks,
        }
    }
}

/// Full speed from `from` towards `to` in the plane (simulator frame, m/s; zero when there).
fn full_speed_towards(from: [f64; 3], to: [f64; 2], v_max: f64) -> [f32; 3] {
    let (dx, dy) = (to[0] - from[0], to[1] - from[1]);
    let d = dx.hypot(dy);
    if d < 1e-9 {
        return [0.0; 3];
    }
    [(v_max * dx / d) as f32, (v_max * dy / d) as f32, 0.0]
}

struct Slot {
    env: Env,
    draw: Draw,
    reward: LearnerReward,
    herders: Vec<HerderState>,
    features: Vec<[f32; FEATURES]>,
    frames: Vec<Option<LocalFrame>>,
    rule: RulePolicy,
    rule_method: Option<Method>,
    learner_return: f64,
    paper_return: f64,
    /// The decision being held (`training.action_repeat` above 1), until its last step.
    held: Option<Held>,
    /// Parameter-space noise: this episode's direction in the actor's parameters, drawn at its
    /// first step.
    perturbation: Option<MultiTaskMlp>,
}

/// Parameter-space noise's state ([`Exploration::Parameter`]): the scale per task
/// (`Task::index`) and each task's most recent observations, on which the distance of a new
/// perturbation is measured.
#[derive(Clone, Debug)]
struct ParameterNoise {
    scale: [f32; Task::COUNT],
    recent: [Vec<[f32; FEATURES]>; Task::COUNT],
    next: [usize; Task::COUNT],
}

impl ParameterNoise {
    fn new() -> ParameterNoise {
        ParameterNoise {
            scale: [PARAMETER_NOISE_INITIAL_SCALE; Task::COUNT],
            recent: std::array::from_fn(|_| Vec::new()),
            next: [0; Task::COUNT],
        }
    }

    /// Keeps `row` among the task's last [`PARAMETER_NOISE_ROWS`] observations.
    fn remember(&mut self, task: usize, row: &[f32; FEATURES]) {
        let recent = &mut self.recent[task];
        if recent.len() < PARAMETER_NOISE_ROWS {
            recent.push(*row);
        } else {
            recent[self.next[task]] = *row;
        }
        self.next[task] = (self.next[task] + 1) % PARAMETER_NOISE_ROWS;
    }
}

/// The RMS difference between the actions of actors `a` and `b` for `task` on the observations
/// `rows`, over the first `dims` action components (normalised units). 0 for no rows.
pub fn action_distance(
    a: &MultiTaskMlp,
    b: &MultiTaskMlp,
    task: usize,
    rows: &[[f32; FEATURES]],
    dims: usize,
) -> f32 {
    if rows.is_empty() || dims == 0 {
        return 0.0;
    }
    let inputs = a.inputs();
    let x: Vec<f32> = rows
        .iter()
        .flat_map(|r| r[..inputs].iter().copied())
        .collect();
    let (ya, yb) = (
        a.predict_batch(task, &x, rows.len()),
        b.predict_batch(task, &x, rows.len()),
    );
    let outputs = a.outputs();
    let mut sum = 0.0_f64;
    for k in 0..rows.len() {
        for j in 0..dims.min(outputs) {
            let d = f64::from(ya[k * outputs + j] - yb[k * outputs + j]);
            sum += d * d;
        }
    }
    (sum / (rows.len() * dims.min(outputs)) as f64).sqrt() as f32
}

/// Parameter-space noise's adaptation: the next scale after a perturbation at `scale` moved the
/// actions by `distance` where `wanted` was asked for.
pub fn adapted_scale(scale: f32, distance: f32, wanted: f32) -> f32 {
    if distance > wanted {
        scale / PARAMETER_NOISE_ADAPT
    } else {
        scale * PARAMETER_NOISE_ADAPT
    }
}

/// A decision held over several simulator steps: what was decided, on what, and the reward
/// gathered since.
struct Held {
    /// The velocities flown while it holds (m/s, simulator frame).
    velocities: Vec<[f64; 3]>,
    /// Each herder's normalised action, as the replay keeps it.
    actions: Vec<[f32; ACTION_DIM]>,
    /// The features and frames the decision was taken on.
    features: Vec<[f32; FEATURES]>,
    frames: Vec<Option<LocalFrame>>,
    /// Each herder's discounted reward sum over the steps held so far.
    rewards: Vec<f32>,
    /// `gamma` to the steps held so far.
    discount: f32,
    /// Simulator steps held so far.
    sim_steps: usize,
}

/// Environments stepped together; slot `i` runs task `i % 2` (of the configured tasks)
/// unless [`Rollouts::set_task_slots`] asks for other counts per task.
pub struct Rollouts {
    slots: Vec<Slot>,
    /// Environments wanted per task (`Task::index`); `None`: each keeps its first task.
    task_slots: Option<[usize; Task::COUNT]>,
    /// Environment steps taken per task (`Task::index`).
    pub task_env_steps: [u64; Task::COUNT],
    observer: EncoderBuffers,
    rng: ChaCha8Rng,
    reward: RewardConfig,
    gamma: f64,
    step_limit: u64,
    noise: bool,
    ddpg: DdpgConfig,
    flight_rules: bool,
    /// The driving curriculum's floor on the pulled goal's distance, goal radii.
    min_centre_distance_radii: f64,
    excursions: Excursions,
    /// Simulator steps a decision is held for (`training.action_repeat`).
    action_repeat: usize,
    /// Recent successes' steps per scenario, for self-imitation's episode filter.
    recent_successes: RecentSuccesses,
    /// Parameter-space noise's scales and recent observations.
    parameter_noise: ParameterNoise,
    /// Parameter-space noise: the perturbed actor being flown, rebuilt in place for each
    /// environment every step.
    perturbed: Option<MultiTaskMlp>,
    /// Environment steps taken (summed over slots).
    pub env_steps: u64,
}

/// The onboard rules' limits for `world` (see `LoopConfig::flight_rules`).
fn flight_limits(world: &skyherd_sim::World) -> Limits {
    let a = world.area;
    Limits::arena(
        [a.width as f32, a.depth as f32, a.ceiling as f32],
        world.limits.herder as f32,
    )
}

/// The velocity (m/s, simulator frame) that normalised `action` in `frame` becomes: through
/// the onboard rules at the herder's observed `position` when `limits` are given; zero when
/// the encoder refused the observation (the drone's hold).
fn flown_velocity(
    frame: Option<LocalFrame>,
    action: [f32; ACTION_DIM],
    limits: Option<&Limits>,
    position: [f64; 3],
) -> [f32; 3] {
    let request = frame.map_or([0.0; 3], |f| f.action_to_world(action));
    match limits {
        Some(l) => {
            let situation = Situation {
                position: position.map(|c| c as f32),
                velocity: request,
                snapshot_age_s: 0.0,
                snapshot_finite: true,
                current_velocity: None,
            };
            safety::check(l, &situation).velocity
        }
        None => request,
    }
}

fn observe(observer: &mut EncoderBuffers, slot: &mut Slot, flight_rules: bool) {
    let world = slot.env.observation();
    observer.fill(world);
    let m = world.herders.len();
    slot.features.resize(m, [0.0; FEATURES]);
    slot.frames.resize(m, None);
    let floor = flight_rules.then(|| flight_limits(world).fence_min[2]);
    for h in 0..m {
        slot.frames[h] = match floor {
            // As the daemon and `ActorPolicy::flying`: the height above the band's floor.
            Some(floor) => {
                let z = world.herders[h][2] as f32;
                observer.encode_at_altitude(h, (z - floor).max(0.0), &mut slot.features[h])
            }
            None => observer.encode(h, &mut slot.features[h]),
        }
        .ok();
    }
}

impl Rollouts {
    /// `count` environments; the first scenario of each slot comes from `draw`.
    pub fn new(
        count: usize,
        config: &TrainConfig,
        rng: ChaCha8Rng,
        draw: &mut dyn FnMut(&mut ChaCha8Rng, Task) -> Draw,
    ) -> Result<Rollouts, EnvError> {
        let mut r = Rollouts {
            slots: Vec::with_capacity(count),
            task_slots: None,
            task_env_steps: [0; Task::COUNT],
            observer: EncoderBuffers::for_version(config.encoder_version),
            rng,
            reward: config.reward.clone(),
            gamma: f64::from(config.ddpg.gamma),
            step_limit: config.training.episode_step_limit,
            noise: config.training.noise,
            ddpg: config.ddpg,
            flight_rules: config.training.flight_rules,
            min_centre_distance_radii: config
                .curriculum
                .driving_goal_distance
                .min_centre_distance_radii,
            excursions: Excursions::from_config(&config.training),
            action_repeat: config.training.action_repeat.max(1),
            recent_successes: RecentSuccesses::default(),
            parameter_noise: ParameterNoise::new(),
            perturbed: None,
            env_steps: 0,
        };
        for i in 0..count {
            let tasks = &config.training.tasks;
            let task = tasks[i % tasks.len()];
            let d = draw(&mut r.rng, task);
            let slot = r.fresh_slot(d)?;
            r.slots.push(slot);
        }
        Ok(r)
    }

    /// From now on, each environment whose episode ends takes the task furthest below its
    /// count in `slots` (environments per task, `Task::index`), its own task when that is as
    /// far below as any: the counts move one finished episode at a time and never cut an
    /// episode short. `None` keeps every environment on its task.
    pub fn set_task_slots(&mut self, slots: Option<[usize; Task::COUNT]>) {
        self.task_slots = slots;
    }

    /// The task environment `slot` runs next, its episode having ended on `current`.
    fn next_task(&self, slot: usize, current: Task) -> Task {
        let Some(wanted) = self.task_slots else {
            return current;
        };
        let mut running = [0usize; Task::COUNT];
        for (i, s) in self.slots.iter().enumerate() {
            if i != slot {
                running[s.draw.task.index()] += 1;
            }
        }
        let lack = |t: Task| wanted[t.index()] as i64 - running[t.index()] as i64;
        let mut best = current;
        for task in Task::ALL {
            if wanted[task.index()] > 0 && lack(task) > lack(best) {
                best = task;
            }
        }
        best
    }

    fn fresh_slot(&mut self, draw: Draw) -> Result<Slot, EnvError> {
        let scenario =
            training_scenario(draw, self.step_limit, self.noise, &self.reward, self.gamma);
        let mut reward = LearnerReward::new(&self.reward, self.gamma, &scenario);
        let mut env = Env::new(scenario)?;
        // Training episode seeds stay below the held-out evaluation seeds (>= 1e9).
        let seed = self.rng.random_range(0..1_000_000_000u64);
        env.reset(seed);
        let pulls_goal = draw.goal_distance_permille < 1000;
        let pulls_herders = draw.herder_distance_permille < 1000;
        if draw.task == Task::Collecting && pulls_goal {
            let world =
                pull_targets_to_goal(env.world(), f64::from(draw.goal_distance_permille) / 1000.0);
            env.reset_to(world, seed)?;
        } else if draw.task == Task::Driving && (pulls_goal || pulls_herders) {
            let mut world = env.world().clone();
            if pulls_goal {
                world = pull_goal_at_least(
                    &world,
                    f64::from(draw.goal_distance_permille) / 1000.0,
                    self.min_centre_distance_radii,
                );
            }
            if pulls_herders {
                let layout = &env.scenario().layout;
                let keep_out = layout.start_radius + layout.herder_clearance;
                world = pull_herders(
                    &world,
                    f64::from(draw.herder_distance_permille) / 1000.0,
                    keep_out,
                );
            }
            env.reset_to(world, seed)?;
        }
        reward.start(&mut env);
        let herder = HerderState {
            nstep: NStep::new(self.ddpg.n_step, self.gamma as f32),
            ou: [0.0; ACTION_DIM],
            waypoint: None,
            excursion: None,
            episode: EpisodeLog::default(),
        };
        let mut slot = Slot {
            herders: vec![herder; env.world().herders.len()],
            env,
            draw,
            reward,
            features: Vec::new(),
            frames: Vec::new(),
            rule: RulePolicy::new(Method::FarthestTargets),
            rule_method: None,
            learner_return: 0.0,
            paper_return: 0.0,
            held: None,
            perturbation: None,
        };
        observe(&mut self.observer, &mut slot, self.flight_rules);
        Ok(slot)
    }

    /// One step of every environment: actions, transitions into `replay[task]` (and the
    /// `(features, action)` pairs into `demos[task]` when given), resets of finished episodes
    /// with new scenarios from `draw`. Returns the episodes that finished.
    pub fn step(
        &mut self,
        controller: &Controller<'_>,
        replay: &mut [ReplayBuffer],
        mut demos: Option<&mut [ReplayBuffer]>,
        draw: &mut dyn FnMut(&mut ChaCha8Rng, Task) -> Draw,
    ) -> Result<Vec<EpisodeStats>, EnvError> {
        let mut actions = self.choose_actions(controller);
        if self.ddpg.planar {
            actions.iter_mut().flatten().for_each(|a| a[2] = 0.0);
        }
        let mut emitted = Vec::new();
        let mut finished = Vec::new();
        let mut velocities = Vec::new();
        let mut herder_rewards = Vec::new();
        let repeat = self.action_repeat;
        for (i, slot_actions) in actions.iter().enumerate() {
            let slot = &mut self.slots[i];
            velocities.clear();
            if let Some(held) = &slot.held {
                // Between decisions every herder flies what it last decided.
                velocities.extend_from_slice(&held.velocities);
            } else {
                let limits = self
                    .flight_rules
                    .then(|| flight_limits(slot.env.observation()));
                for (h, a) in slot_actions.iter().enumerate() {
                    let position = slot.env.observation().herders[h];
                    let v = flown_velocity(slot.frames[h], *a, limits.as_ref(), position);
                    velocities.push([f64::from(v[0]), f64::from(v[1]), f64::from(v[2])]);
                }
            }
            let centralised = self.ddpg.centralised_critic;
            let positions_before = if centralised {
                slot.env.world().herders.clone()
            } else {
                Vec::new()
            };
            let out = slot.env.step(&velocities)?;
            self.env_steps += 1;
            self.task_env_steps[slot.draw.task.index()] += 1;
            slot.reward
                .step(&out, &slot.env, &velocities, &mut herder_rewards);
            slot.learner_return += herder_rewards.first().copied().map_or(0.0, f64::from);
            slot.paper_return += out.paper_reward;
            let mut before = std::mem::take(&mut slot.features);
            let mut before_frames = std::mem::take(&mut slot.frames);
            observe(&mut self.observer, slot, self.flight_rules);
            let ended = out.terminated || out.truncated;
            // What the transitions carry: this step's, or a held decision's once it ends.
            let mut decided: &[[f32; ACTION_DIM]] = slot_actions;
            let mut gathered: &[f32] = &herder_rewards;
            let mut sim_steps = 1;
            let finished_hold: Held;
            if repeat > 1 {
                // A new decision keeps what it was taken on until its last step.
                let mut held = slot.held.take().unwrap_or_else(|| Held {
                    velocities: velocities.clone(),
                    actions: slot_actions.clone(),
                    features: std::mem::take(&mut before),
                    frames: std::mem::take(&mut before_frames),
                    rewards: vec![0.0; herder_rewards.len()],
                    discount: 1.0,
                    sim_steps: 0,
                });
                for (sum, r) in held.rewards.iter_mut().zip(&herder_rewards) {
                    *sum += held.discount * r;
                }
                held.discount *= self.gamma as f32;
                held.sim_steps += 1;
                if held.sim_steps < repeat && !ended {
                    slot.held = Some(held);
                    continue;
                }
                before = std::mem::take(&mut held.features);
                before_frames = std::mem::take(&mut held.frames);
                sim_steps = held.sim_steps;
                finished_hold = held;
                decided = &finished_hold.actions;
                gathered = &finished_hold.rewards;
            }
            let task = slot.draw.task.index();
            let logs_returns = self.ddpg.self_imitation > 0.0;
            let writes_returns = logs_returns
                && out.terminated
                && self.recent_successes.admits(
                    self.ddpg.self_imitation_episodes,
                    slot.draw,
                    out.success,
                    slot.env.info().steps,
                );
            for h in 0..before.len() {
                if before_frames[h].is_none() || slot.frames[h].is_none() {
                    // An observation the encoder refused carries no transition (and breaks
                    // an n-step chain).
                    slot.herders[h].nstep.clear();
                    slot.herders[h].episode.clear();
                    continue;
                }
                // A buffer as wide as an older encoder's features keeps that prefix.
                let w = replay[task].obs_dim();
                let r = gathered[h];
                let max_others = self.ddpg.critic_max_others;
                let (context, next_others) = if centralised {
                    let near = nearest_others(&positions_before, h, max_others, &before_frames);
                    let obs: Vec<f32> =
                        near.iter().flat_map(|&j| before[j][..w].to_vec()).collect();
                    let acts: Vec<f32> = near.iter().flat_map(|&j| decided[j]).collect();
                    let after = &slot.env.world().herders;
                    let near_after = nearest_others(after, h, max_others, &slot.frames);
                    let next: Vec<f32> = near_after
                        .iter()
                        .flat_map(|&j| slot.features[j][..w].to_vec())
                        .collect();
                    (pool_others(&obs, &acts, w, ACTION_DIM), next)
                } else {
                    (Vec::new(), Vec::new())
                };
                let others = Others {
                    context: &context,
                    next_obs: &next_others,
                };
                if logs_returns {
                    slot.herders[h].episode.steps.push((r, sim_steps));
                }
                if self.ddpg.n_step <= 1 && repeat == 1 {
                    let continues = if out.terminated { 0.0 } else { 1.0 };
                    let stamp = if centralised {
                        replay[task].push_with_others(
                            &before[h][..w],
                            &decided[h],
                            r,
                            &slot.features[h][..w],
                            continues,
                            others,
                        )
                    } else {
                        replay[task].push(
                            &before[h][..w],
                            &decided[h],
                            r,
                            &slot.features[h][..w],
                            out.terminated,
                        )
                    };
                    if logs_returns {
                        slot.herders[h].episode.stamps.push(stamp);
                    }
                } else {
                    emitted.clear();
                    let step = OneStep {
                        obs: &before[h][..w],
                        action: &decided[h],
                        reward: r,
                        next_obs: &slot.features[h][..w],
                        terminated: out.terminated,
                        truncated: out.truncated,
                        context: &context,
                        sim_steps,
                    };
                    slot.herders[h].nstep.push(step, &mut emitted);
                    for t in &emitted {
                        let stamp = if centralised {
                            let others = Others {
                                context: &t.context,
                                next_obs: &next_others,
                            };
                            replay[task].push_with_others(
                                &t.obs,
                                &t.action,
                                t.reward,
                                &t.next_obs,
                                t.continues,
                                others,
                            )
                        } else {
                            replay[task].push_discounted(
                                &t.obs,
                                &t.action,
                                t.reward,
                                &t.next_obs,
                                t.continues,
                            )
                        };
                        if logs_returns {
                            slot.herders[h].episode.stamps.push(stamp);
                        }
                    }
                }
                if writes_returns {
                    // Only an episode that ended has returns; a truncated one's stay unknown.
                    slot.herders[h]
                        .episode
                        .write_returns(&mut replay[task], self.gamma as f32);
                }
                if let Some(d) = demos.as_deref_mut() {
                    let w = d[task].obs_dim();
                    d[task].push(
                        &before[h][..w],
                        &decided[h],
                        r,
                        &slot.features[h][..w],
                        false,
                    );
                }
            }
            if out.terminated || out.truncated {
                finished.push(EpisodeStats {
                    draw: slot.draw,
                    success: out.success,
                    steps: slot.env.info().steps,
                    learner_return: slot.learner_return,
                    paper_return: slot.paper_return,
                });
                let current = slot.draw.task;
                let task = self.next_task(i, current);
                let d = draw(&mut self.rng, task);
                self.slots[i] = self.fresh_slot(d)?;
            }
        }
        Ok(finished)
    }

    /// Replaces the actor's action of every herder on an [`Excursions`] excursion (starting
    /// and ending them first). Draws nothing when excursions are off, so older configs keep
    /// their random streams.
    fn fly_excursions(&mut self, out: &mut [Vec<[f32; ACTION_DIM]>]) {
        let Rollouts {
            slots,
            rng,
            excursions: e,
            ..
        } = self;
        if e.rate <= 0.0 {
            return;
        }
        for (s, actions) in slots.iter_mut().zip(out.iter_mut()) {
            if !e.tasks[s.draw.task.index()] {
                continue;
            }
            let world = s.env.observation();
            if world.targets.is_empty() {
                continue;
            }
            let (area, step) = (world.area, world.step);
            let v_max = world.limits.herder;
            // There: within one step's flight.
            let arrived = v_max * world.dt;
            for (h, action) in actions.iter_mut().enumerate() {
                let p = world.herders[h];
                let state = &mut s.herders[h];
                if let Some((w, until)) = state.excursion
                    && (step >= until || (w[0] - p[0]).hypot(w[1] - p[1]) <= arrived)
                {
                    state.excursion = None;
                }
                if state.excursion.is_none() && rng.random_bool(e.rate) {
                    let t = world.targets[rng.random_range(0..world.targets.len())];
                    let angle = rng.random_range(0.0..std::f64::consts::TAU);
                    let r = rng.random_range(e.radius_m[0]..=e.radius_m[1]);
                    let w = [
                        (t[0] + r * angle.cos()).clamp(0.0, area.width),
                        (t[1] + r * angle.sin()).clamp(0.0, area.depth),
                    ];
                    state.excursion = Some((w, step + e.max_steps));
                }
                if let (Some((w, _)), Some(frame)) = (state.excursion, s.frames[h]) {
                    *action = frame.world_to_action(full_speed_towards(p, w, v_max));
                }
            }
        }
    }

    /// Parameter-space noise: every environment flies the actor plus its episode's
    /// perturbation, drawn (and the task's scale adapted towards `wanted`) at the episode's
    /// first step. With `wanted` at 0 the actor flies unperturbed.
    fn perturbed_actions(
        &mut self,
        actor: &MultiTaskMlp,
        wanted: f32,
    ) -> Vec<Vec<[f32; ACTION_DIM]>> {
        let dims = if self.ddpg.planar { 2 } else { ACTION_DIM };
        let mut tape = Tape::default();
        let mut out = Vec::with_capacity(self.slots.len());
        for i in 0..self.slots.len() {
            let task = self.slots[i].draw.task.index();
            let flown = if wanted > 0.0 {
                if self.slots[i].perturbation.is_none() {
                    let direction = actor
                        .random_direction(task, &mut self.rng)
                        .unwrap_or_else(|| actor.zeros_like());
                    let noise = &mut self.parameter_noise;
                    if !noise.recent[task].is_empty() {
                        let trial = actor.plus_scaled(&direction, noise.scale[task]);
                        let d = action_distance(actor, &trial, task, &noise.recent[task], dims);
                        noise.scale[task] = adapted_scale(noise.scale[task], d, wanted);
                    }
                    self.slots[i].perturbation = Some(direction);
                }
                match self.slots[i].perturbation.as_ref() {
                    Some(direction) => {
                        let perturbed = self.perturbed.get_or_insert_with(|| actor.clone());
                        perturbed.assign_plus_scaled(
                            actor,
                            direction,
                            self.parameter_noise.scale[task],
                        );
                        Some(&*perturbed)
                    }
                    None => None,
                }
            } else {
                None
            };
            let slot = &self.slots[i];
            let input: Vec<f32> = slot
                .features
                .iter()
                .flat_map(|f| f[..actor.inputs()].iter().copied())
                .collect();
            flown
                .unwrap_or(actor)
                .forward(task, &input, slot.features.len(), &mut tape);
            let actions: Vec<[f32; ACTION_DIM]> = (0..slot.features.len())
                .map(|h| {
                    std::array::from_fn(|j| tape.output()[h * ACTION_DIM + j].clamp(-1.0, 1.0))
                })
                .collect();
            for f in &slot.features {
                self.parameter_noise.remember(task, f);
            }
            out.push(actions);
        }
        out
    }

    /// The scale of parameter-space noise now, per task (`Task::index`).
    pub fn parameter_noise_scales(&self) -> [f32; Task::COUNT] {
        self.parameter_noise.scale
    }

    fn choose_actions(&mut self, controller: &Controller<'_>) -> Vec<Vec<[f32; ACTION_DIM]>> {
        match *controller {
            Controller::Actor(actor, noise_std)
                if self.ddpg.exploration == Exploration::Parameter =>
            {
                let mut out = self.perturbed_actions(actor, noise_std);
                self.fly_excursions(&mut out);
                out
            }
            Controller::Actor(actor, noise_std) => {
                let mut out: Vec<Vec<[f32; 3]>> = self
                    .slots
                    .iter()
                    .map(|s| vec![[0.0; 3]; s.features.len()])
                    .collect();
                let noise = Normal::new(0.0_f32, noise_std.max(0.0)).ok();
                let unit = Normal::new(0.0_f32, 1.0).ok();
                let ou = self.ddpg.exploration == Exploration::OrnsteinUhlenbeck;
                // x <- (1 - theta) x + sigma sqrt(1 - (1 - theta)^2) e: stationary std sigma.
                let theta = self.ddpg.ou_theta.clamp(1e-3, 1.0);
                let ou_scale = noise_std.max(0.0) * (1.0 - (1.0 - theta).powi(2)).sqrt();
                let mut tape = Tape::default();
                for task in Task::ALL {
                    // One batched forward per task over every herder of every slot.
                    let mut rows = Vec::new();
                    let mut input = Vec::new();
                    for (i, s) in self.slots.iter().enumerate() {
                        if s.draw.task == task {
                            for (h, f) in s.features.iter().enumerate() {
                                rows.push((i, h));
                                input.extend_from_slice(&f[..actor.inputs()]);
                            }
                        }
                    }
                    if rows.is_empty() {
                        continue;
                    }
                    actor.forward(task.index(), &input, rows.len(), &mut tape);
                    for (k, &(i, h)) in rows.iter().enumerate() {
                        let mut a = [0.0; 3];
                        for (j, v) in a.iter_mut().enumerate() {
                            let n = if ou {
                                let e = unit.map_or(0.0, |d| d.sample(&mut self.rng));
                                let x = &mut self.slots[i].herders[h].ou[j];
                                *x = (1.0 - theta) * *x + ou_scale * e;
                                *x
                            } else {
                                noise.map_or(0.0, |d| d.sample(&mut self.rng))
                            };
                            *v = (tape.output()[k * 3 + j] + n).clamp(-1.0, 1.0);
                        }
                        out[i][h] = a;
                    }
                }
                self.fly_excursions(&mut out);
                out
            }
            Controller::ActorExceptRandomTasks(actor, noise_std, random) => {
                let mut out = self.choose_actions(&Controller::Actor(actor, noise_std));
                let waypoints = self.choose_actions(&Controller::RandomWaypoints);
                for ((slot, actions), flown) in self.slots.iter().zip(&mut out).zip(waypoints) {
                    if random[slot.draw.task.index()] {
                        *actions = flown;
                    }
                }
                out
            }
            Controller::RandomWaypoints => {
                let rng = &mut self.rng;
                self.slots
                    .iter_mut()
                    .map(|s| {
                        let world = s.env.observation();
                        let (area, step) = (world.area, world.step);
                        let v_max = world.limits.herder;
                        (0..world.herders.len())
                            .map(|h| {
                                let p = world.herders[h];
                                let state = &mut s.herders[h];
                                let stale = state.waypoint.is_none_or(|(w, at)| {
                                    step >= at + WAYPOINT_STEPS
                                        || (w[0] - p[0]).hypot(w[1] - p[1]) < 0.02 * area.width
                                });
                                if stale {
                                    let w = [
                                        rng.random_range(0.0..area.width),
                                        rng.random_range(0.0..area.depth),
                                    ];
                                    state.waypoint = Some((w, step));
                                }
                                let (w, _) = state.waypoint.unwrap_or(([p[0], p[1]], step));
                                let v = full_speed_towards(p, w, v_max);
                                s.frames[h].map_or([0.0; 3], |f| f.world_to_action(v))
                            })
                            .collect()
                    })
                    .collect()
            }
            Controller::Baseline(teachers) => {
                let mut velocities = Vec::new();
                self.slots
                    .iter_mut()
                    .map(|s| {
                        let world = s.env.world();
                        let method =
                            teachers.teacher(s.draw.task, world.targets.len(), world.herders.len());
                        if s.rule_method != Some(method) || world.step == 0 {
                            s.rule = RulePolicy::new(method);
                            s.rule.reset(s.env.observation(), s.env.info().seed);
                            s.rule_method = Some(method);
                        }
                        act_all(&mut s.rule, s.env.observation(), &mut velocities);
                        velocities
                            .iter()
                            .enumerate()
                            .map(|(h, v)| {
                                s.frames[h].map_or([0.0; 3], |f| {
                                    f.world_to_action([v[0] as f32, v[1] as f32, v[2] as f32])
                                })
                            })
                            .collect()
                    })
                    .collect()
            }
        }
    }
}

/// The curriculum's scenario draw at `progress` (a fraction of the DDPG phase).
pub(crate) fn draw_from_stage(
    config: &TrainConfig,
    progress: f64,
    rng: &mut ChaCha8Rng,
    task: Task,
) -> Draw {
    draw_in(config, config.stage_at(progress), rng, task, progress)
}

/// A draw from any stage at random: the warm start's demonstrations cover the whole curriculum.
pub(crate) fn draw_from_all_stages(config: &TrainConfig, rng: &mut ChaCha8Rng, task: Task) -> Draw {
    let stages = &config.curriculum.stages;
    draw_in(
        config,
        &stages[rng.random_range(0..stages.len())],
        rng,
        task,
        1.0,
    )
}

/// N, M and the layout drawn from `stage`, at `progress` of the DDPG phase.
fn draw_in(
    config: &TrainConfig,
    stage: &CurriculumStage,
    rng: &mut ChaCha8Rng,
    task: Task,
    progress: f64,
) -> Draw {
    // One index over `targets` and then `pairs`: without pairs this is the draw it always was.
    let pick = rng.random_range(0..stage.targets.len() + stage.pairs.len());
    let (targets, herders) = match pick.checked_sub(stage.targets.len()) {
        Some(pair) => (stage.pairs[pair][0], stage.pairs[pair][1]),
        None => (
            stage.targets[pick],
            stage.herders[rng.random_range(0..stage.herders.len())],
        ),
    };
    let room = draw_room(config, rng, task, targets);
    let floor = match task {
        Task::Driving => config.curriculum.driving_goal_distance.floor_at(progress),
        Task::Collecting => config
            .curriculum
            .collecting_target_distance
            .floor_at(progress),
    };
    let goal_distance_permille = if floor < 1.0 {
        (rng.random_range(floor..=1.0) * 1000.0).round() as u16
    } else {
        1000
    };
    let floor = config.curriculum.driving_herder_distance.floor_at(progress);
    let herder_distance_permille = if task == Task::Driving && floor < 1.0 {
        (rng.random_range(floor..=1.0) * 1000.0).round() as u16
    } else {
        1000
    };
    Draw {
        task,
        targets,
        herders,
        room,
        goal_distance_permille,
        herder_distance_permille,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::MlpShape;
    use crate::replay::Batch;
    use rand::SeedableRng;

    #[test]
    fn a_stages_pairs_are_drawn_together_and_a_stage_without_them_draws_as_before() {
        use crate::config::CurriculumStage;
        let mut config = TrainConfig::default();
        config.curriculum.enabled = false;
        config.curriculum.stages = vec![CurriculumStage {
            from_progress: 0.0,
            targets: vec![4, 8, 16],
            herders: vec![2, 4],
            pairs: Vec::new(),
        }];
        // Without pairs: one index into `targets`, then one into `herders`, as always.
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut same = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..200 {
            let d = draw_from_stage(&config, 0.5, &mut rng, Task::Collecting);
            let targets = [4, 8, 16][same.random_range(0..3)];
            let herders = [2, 4][same.random_range(0..2)];
            assert_eq!((d.targets, d.herders), (targets, herders));
            // Whatever else the draw reads comes after N and M; start the next one level.
            same = rng.clone();
        }
        // With pairs: each pair as likely as one entry of `targets`, and never split.
        config.curriculum.stages[0].pairs = vec![[1, 1], [2, 2]];
        let mut counts = std::collections::HashMap::new();
        for _ in 0..5_000 {
            let d = draw_from_stage(&config, 0.5, &mut rng, Task::Collecting);
            *counts.entry((d.targets, d.herders)).or_insert(0usize) += 1;
        }
        let share = |n, m| counts.get(&(n, m)).copied().unwrap_or(0) as f64 / 5_000.0;
        for pair in [(1, 1), (2, 2)] {
            assert!(
                (share(pair.0, pair.1) - 0.2).abs() < 0.03,
                "{pair:?}: {counts:?}"
            );
        }
        for n in [4, 8, 16] {
            assert!(
                (share(n, 2) + share(n, 4) - 0.2).abs() < 0.03,
                "N = {n}: {counts:?}"
            );
        }
        let allowed = [
            (1, 1),
            (2, 2),
            (4, 2),
            (4, 4),
            (8, 2),
            (8, 4),
            (16, 2),
            (16, 4),
        ];
        assert!(counts.keys().all(|k| allowed.contains(k)), "{counts:?}");
    }

    #[test]
    fn room_layout_draws_are_long_drives_near_the_walls_and_valid() {
        let config = TrainConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let draws: Vec<Draw> = (0..400)
            .map(|_| draw_from_stage(&config, 0.9, &mut rng, Task::Driving))
            .collect();
        let rooms = draws.iter().filter(|d| d.room).count();
        assert!(
            (60..140).contains(&rooms),
            "{rooms} of 400 at fraction 0.25"
        );
        assert!(
            draws
                .iter()
                .all(|d| !d.room || d.targets <= ROOM_LAYOUT_MAX_TARGETS)
        );
        let collecting = draw_from_stage(&config, 0.9, &mut rng, Task::Collecting);
        assert!(!collecting.room);
        let draw = Draw {
            room: true,
            ..Draw::paper(Task::Driving, 16, 2)
        };
        let s = training_scenario(draw, 600, true, &config.reward, 0.99);
        assert_eq!(s.layout.wall_margin, 25.0);
        assert_eq!(s.layout.min_start_goal_distance, 400.0);
        s.validate().expect("the room layout is a valid scenario");
        let mut env = Env::new(s).expect("env");
        env.reset(5);
        let w = env.world();
        let c = w.flock_centroid();
        let d = ((c[0] - w.goal.center[0]).powi(2) + (c[1] - w.goal.center[1]).powi(2)).sqrt();
        assert!(d > 330.0, "start-goal {d} m");
    }

    #[test]
    fn the_goal_distance_curriculum_pulls_early_driving_goals_in_and_lets_go_later() {
        let mut config = TrainConfig::default();
        config.curriculum.driving_goal_distance = crate::config::GoalDistanceCurriculum {
            first_share: 0.25,
            full_at_progress: 0.5,
            min_centre_distance_radii: 0.0,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let early: Vec<Draw> = (0..200)
            .map(|_| draw_from_stage(&config, 0.0, &mut rng, Task::Driving))
            .collect();
        assert!(
            early
                .iter()
                .all(|d| (250..=1000).contains(&d.goal_distance_permille))
        );
        assert!(early.iter().any(|d| d.goal_distance_permille < 400));
        let mid = draw_from_stage(&config, 0.25, &mut rng, Task::Driving);
        assert!(mid.goal_distance_permille >= 625, "{mid:?}");
        for progress in [0.5, 0.9] {
            let late = draw_from_stage(&config, progress, &mut rng, Task::Driving);
            assert_eq!(late.goal_distance_permille, 1000);
        }
        let collecting = draw_from_stage(&config, 0.0, &mut rng, Task::Collecting);
        assert_eq!(collecting.goal_distance_permille, 1000);
        // The pulled goal lies on the line from the centroid, at the share of the distance.
        let mut env = Env::new(Scenario::paper(Task::Driving)).expect("env");
        env.reset(7);
        let w = env.world().clone();
        // With a floor of 1.5 goal radii the pulled centre stays that far from the flock.
        let floored = pull_goal_at_least(&w, 0.0, 1.5);
        let c = w.flock_centroid();
        let d = (floored.goal.center[0] - c[0]).hypot(floored.goal.center[1] - c[1]);
        assert!((d - 1.5 * w.goal.radius).abs() < 1e-9, "{d}");
        let pulled = pull_goal(&w, 0.25);
        let c = w.flock_centroid();
        let d = |g: [f64; 2]| (g[0] - c[0]).hypot(g[1] - c[1]);
        assert!((d(pulled.goal.center) - 0.25 * d(w.goal.center)).abs() < 1e-9);
        assert_eq!(pulled.targets, w.targets);
        pulled.validate().expect("a pulled goal is a valid world");
        // The default is off.
        assert_eq!(
            TrainConfig::default()
                .curriculum
                .driving_goal_distance
                .floor_at(0.0),
            1.0
        );
    }

    #[test]
    fn the_collecting_curriculum_pulls_early_targets_towards_the_goal_and_lets_go_later() {
        let mut config = TrainConfig::default();
        config.curriculum.collecting_target_distance = crate::config::SpawnShareCurriculum {
            first_share: 0.2,
            full_at_progress: 0.5,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let early: Vec<Draw> = (0..200)
            .map(|_| draw_from_stage(&config, 0.0, &mut rng, Task::Collecting))
            .collect();
        assert!(
            early
                .iter()
                .all(|d| (200..=1000).contains(&d.goal_distance_permille))
        );
        assert!(early.iter().any(|d| d.goal_distance_permille < 300));
        let late = draw_from_stage(&config, 0.5, &mut rng, Task::Collecting);
        assert_eq!(late.goal_distance_permille, 1000);
        // Driving draws are not touched by it.
        let driving = draw_from_stage(&config, 0.0, &mut rng, Task::Driving);
        assert_eq!(driving.goal_distance_permille, 1000);
        // Each target keeps the share of its distance beyond the edge, on its line to the
        // goal's centre, never nearer the edge than the floor; the goal and herders stay.
        let mut env = Env::new(Scenario::paper(Task::Collecting)).expect("env");
        env.reset(3);
        let w = env.world().clone();
        let g = w.goal.center;
        let r = w.goal.radius;
        let beyond = |p: &[f64; 2]| (p[0] - g[0]).hypot(p[1] - g[1]) - r;
        let pulled = pull_targets_to_goal(&w, 0.5);
        assert_eq!(pulled.goal, w.goal);
        assert_eq!(pulled.herders, w.herders);
        for (before, after) in w.targets.iter().zip(&pulled.targets) {
            let want = (0.5 * beyond(before)).max(PULLED_TARGET_MIN_BEYOND_EDGE_RADII * r);
            assert!(
                (beyond(after) - want).abs() < 1e-9,
                "{before:?} -> {after:?}"
            );
            let cross =
                (before[0] - g[0]) * (after[1] - g[1]) - (before[1] - g[1]) * (after[0] - g[0]);
            assert!(cross.abs() < 1e-6, "on the line to the centre");
        }
        let floored = pull_targets_to_goal(&w, 0.0);
        assert!(
            floored
                .targets
                .iter()
                .all(|p| (beyond(p) - PULLED_TARGET_MIN_BEYOND_EDGE_RADII * r).abs() < 1e-9)
        );
        floored
            .validate()
            .expect("pulled targets make a valid world");
        let kept = pull_targets_to_goal(&w, 1.0);
        for (a, b) in kept.targets.iter().zip(&w.targets) {
            assert!(
                (a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9,
                "{a:?} {b:?}"
            );
        }
        // A training slot of such a draw starts from the same episode's world, pulled.
        let start = |permille: u16| {
            let draw = Draw {
                goal_distance_permille: permille,
                ..Draw::paper(Task::Collecting, 8, 4)
            };
            let r = Rollouts::new(1, &config, ChaCha8Rng::seed_from_u64(1), &mut |_, _| draw)
                .expect("rollouts");
            r.slots[0].env.world().clone()
        };
        let (full, short) = (start(1000), start(300));
        assert_eq!(short.targets, pull_targets_to_goal(&full, 0.3).targets);
        assert_ne!(short.targets, full.targets);
    }

    #[test]
    fn the_herder_distance_curriculum_spawns_early_driving_herders_near_the_flock() {
        let mut config = TrainConfig::default();
        config.curriculum.driving_herder_distance = crate::config::SpawnShareCurriculum {
            first_share: 0.0,
            full_at_progress: 0.5,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let early: Vec<Draw> = (0..200)
            .map(|_| draw_from_stage(&config, 0.0, &mut rng, Task::Driving))
            .collect();
        assert!(early.iter().any(|d| d.herder_distance_permille < 200));
        assert!(early.iter().all(|d| d.goal_distance_permille == 1000));
        let mid = draw_from_stage(&config, 0.25, &mut rng, Task::Driving);
        assert!(mid.herder_distance_permille >= 500, "{mid:?}");
        let late = draw_from_stage(&config, 0.5, &mut rng, Task::Driving);
        assert_eq!(late.herder_distance_permille, 1000);
        let collecting = draw_from_stage(&config, 0.0, &mut rng, Task::Collecting);
        assert_eq!(collecting.herder_distance_permille, 1000);
        assert_eq!(
            TrainConfig::default()
                .curriculum
                .driving_herder_distance
                .floor_at(0.0),
            1.0
        );
        // Each herder moves towards the centroid, to the share of its distance, but no nearer
        // than the keep-out radius; a herder inside it stays put.
        let mut env = Env::new(Scenario::paper(Task::Driving)).expect("env");
        env.reset(11);
        let mut w = env.world().clone();
        let c = w.flock_centroid();
        w.herders[0] = [c[0] + 20.0, c[1], w.herders[0][2]];
        let ground = |h: [f64; 3]| (h[0] - c[0]).hypot(h[1] - c[1]);
        let keep_out = 60.0;
        let pulled = pull_herders(&w, 0.25, keep_out);
        assert_eq!(pulled.herders[0], w.herders[0]);
        for (before, after) in w.herders.iter().zip(&pulled.herders).skip(1) {
            let want = (0.25 * ground(*before)).max(keep_out);
            assert!(
                (ground(*after) - want).abs() < 1e-9,
                "{before:?} -> {after:?}"
            );
            assert_eq!(after[2], before[2]);
            // On the line from the centroid: the direction is kept.
            let cross =
                (before[0] - c[0]) * (after[1] - c[1]) - (before[1] - c[1]) * (after[0] - c[0]);
            assert!(cross.abs() < 1e-6 * ground(*before) * ground(*after).max(1.0));
        }
        assert_eq!(pulled.targets, w.targets);
        assert_eq!(pulled.goal, w.goal);
        pulled
            .validate()
            .expect("pulled herders make a valid world");
        // A slot built from such a draw starts with its herders pulled in.
        let mut slots = Rollouts::new(1, &config, ChaCha8Rng::seed_from_u64(2), &mut |_, _| Draw {
            herder_distance_permille: 0,
            ..Draw::paper(Task::Driving, 8, 4)
        })
        .expect("rollouts");
        let slot = &mut slots.slots[0];
        let w = slot.env.world();
        let layout = &slot.env.scenario().layout;
        let near = layout.start_radius + layout.herder_clearance;
        let c = w.flock_centroid();
        for h in &w.herders {
            let d = (h[0] - c[0]).hypot(h[1] - c[1]);
            assert!(
                d <= near + 1e-6,
                "herder {d} m from the flock, keep-out {near} m"
            );
        }
    }

    #[test]
    fn suicide_no_longer_pays_under_the_learner_reward() {
        // Leaving on step 1 must be worse than idling for the whole episode (the printed reward
        // rewards leaving: see `skyherd_sim::reward`).
        let config = TrainConfig::default();
        let draw = Draw::paper(Task::Driving, 16, 4);
        let s = training_scenario(draw, 600, false, &config.reward, 0.99);
        let cost = crate::reward::step_cost(&s, config.reward.flight_scale);
        let mut reward = LearnerReward::new(&config.reward, 0.99, &s);
        let gamma = 0.99_f64;
        // Idle: every step costs k0 k3 |r3| N (the targets barely move), discounted.
        let idle_per_step = -s.reward.k0 * s.reward.k3 * s.reward.r3.abs() * 16.0 / cost;
        let idle: f64 = (0..600).map(|t| gamma.powi(t) * idle_per_step).sum();
        // Fly one herder out of the arena: the first step ends the episode.
        let mut env = Env::new(s.clone()).expect("scenario");
        env.reset(3);
        reward.start(&mut env);
        let mut actions = vec![[0.0; 3]; 4];
        let mut rewards = Vec::new();
        let mut leave = 0.0;
        let mut discount = 1.0;
        let out = loop {
            let h = env.world().herders[0];
            actions[0] = [if h[0] < 250.0 { -5.0 } else { 5.0 }, 0.0, 0.0];
            let out = env.step(&actions).expect("step");
            reward.step(&out, &env, &actions, &mut rewards);
            leave += discount * f64::from(rewards[0]);
            discount *= gamma;
            if out.terminated || out.truncated {
                break out;
            }
        };
        assert!(out.left_area);
        assert!(
            leave < idle,
            "leaving ({leave}) must cost more than idling ({idle})"
        );
    }

    #[test]
    fn environments_change_task_only_when_an_episode_ends_and_then_follow_the_counts() {
        let mut config = TrainConfig::default();
        config.training.episode_step_limit = 5;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let mut draw = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 2);
        let mut rollouts =
            Rollouts::new(8, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let mut replay: Vec<ReplayBuffer> = (0..2)
            .map(|_| ReplayBuffer::new(FEATURES, 3, 1000))
            .collect();
        let tasks_now = |r: &Rollouts| {
            let mut n = [0usize; Task::COUNT];
            for s in &r.slots {
                n[s.draw.task.index()] += 1;
            }
            n
        };
        let mut step = |r: &mut Rollouts| {
            r.step(
                &Controller::Actor(&actor, 0.3),
                &mut replay,
                None,
                &mut draw,
            )
            .expect("step")
        };
        assert_eq!(tasks_now(&rollouts), [4, 4], "an even start");
        for _ in 0..3 {
            assert!(step(&mut rollouts).is_empty());
        }
        rollouts.set_task_slots(Some([2, 6]));
        // Mid-episode: nobody moves.
        assert!(step(&mut rollouts).is_empty());
        assert_eq!(tasks_now(&rollouts), [4, 4]);
        assert_eq!(rollouts.task_env_steps, [16, 16]);
        // Every episode ends at the step limit together; two driving ones turn to collecting.
        assert_eq!(step(&mut rollouts).len(), 8);
        assert_eq!(tasks_now(&rollouts), [2, 6]);
        for _ in 0..5 {
            step(&mut rollouts);
        }
        assert_eq!(rollouts.task_env_steps, [20 + 10, 20 + 30]);
        assert_eq!(rollouts.env_steps, 80);
        // Back to the even split, and without counts each environment keeps its task.
        rollouts.set_task_slots(Some([4, 4]));
        for _ in 0..5 {
            step(&mut rollouts);
        }
        assert_eq!(tasks_now(&rollouts), [4, 4]);
        rollouts.set_task_slots(None);
        for _ in 0..5 {
            step(&mut rollouts);
        }
        assert_eq!(tasks_now(&rollouts), [4, 4]);
        assert_eq!(rollouts.task_env_steps, [60, 100]);
    }

    #[test]
    fn a_centralised_critic_gets_every_other_herder_pooled_and_one_by_one() {
        let mut config = TrainConfig::default();
        config.training.episode_step_limit = 6;
        config.ddpg.centralised_critic = true;
        config.ddpg.critic_max_others = 7;
        config.ddpg.n_step = 3;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let mut draw = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 3);
        let mut rollouts =
            Rollouts::new(2, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let mut replay: Vec<ReplayBuffer> = (0..2)
            .map(|_| ReplayBuffer::new(FEATURES, 3, 100).with_others(7))
            .collect();
        for _ in 0..6 {
            rollouts
                .step(
                    &Controller::Actor(&actor, 0.3),
                    &mut replay,
                    None,
                    &mut draw,
                )
                .expect("step");
        }
        assert_eq!(
            replay[0].len(),
            18,
            "3 herders x 6 steps, flushed at the truncation"
        );
        let mut batch = crate::replay::Batch::default();
        replay[0].sample(32, &mut rng, &mut batch);
        assert!(
            batch.next_others_count.iter().all(|&k| k == 2),
            "two others each"
        );
        let w = FEATURES + ACTION_DIM;
        for r in 0..batch.size {
            let context = &batch.context[r * w..(r + 1) * w];
            assert!(
                context.iter().any(|&x| x != 0.0),
                "row {r} has an empty pool"
            );
        }
        // The nearest come first, ties by index, and refused observations are left out.
        let positions = [
            [0.0, 0.0, 2.0],
            [5.0, 0.0, 2.0],
            [1.0, 1.0, 2.0],
            [1.0, 1.0, 2.0],
        ];
        let frame = Some(LocalFrame {
            forward: [1.0, 0.0],
            max_speed: 5.0,
        });
        let frames = [frame, frame, frame, None];
        assert_eq!(nearest_others(&positions, 0, 7, &frames), vec![2, 1]);
        assert_eq!(nearest_others(&positions, 0, 1, &frames), vec![2]);
    }

    #[test]
    fn with_flight_rules_training_flies_through_the_onboard_fence() {
        let world = Env::new(Scenario::paper(Task::Driving))
            .expect("env")
            .world()
            .clone();
        let limits = flight_limits(&world);
        let east = Some(LocalFrame {
            forward: [1.0, 0.0],
            max_speed: 5.0,
        });
        // Beyond the east fence, asked to fly further east at full speed: steered back in.
        let outside = [499.8, 250.0, 2.0];
        let free = flown_velocity(east, [1.0, 0.0, 0.0], None, outside);
        assert!(
            free[0] > 4.9,
            "without the rules the request goes through: {free:?}"
        );
        let ruled = flown_velocity(east, [1.0, 0.0, 0.0], Some(&limits), outside);
        assert!(ruled[0] < 0.0, "the fence steers back in: {ruled:?}");
        // Inside, a request that stays inside is left alone.
        let inside = flown_velocity(east, [0.2, 0.0, 0.0], Some(&limits), [250.0, 250.0, 2.0]);
        assert!((inside[0] - 1.0).abs() < 1e-5 && inside[1].abs() < 1e-6);
        // A refused observation holds.
        assert_eq!(
            flown_velocity(None, [1.0, 0.0, 0.0], Some(&limits), [250.0, 250.0, 2.0]),
            [0.0; 3]
        );
        // The encoder reads the height above the band's floor, as in flight.
        let mut config = TrainConfig::default();
        let mut draw = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 2);
        let plain =
            Rollouts::new(1, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        config.training.flight_rules = true;
        let flown =
            Rollouts::new(1, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let (a, b) = (&plain.slots[0].features[0], &flown.slots[0].features[0]);
        let altitude = skyherd_onboard::obs::feature::ALTITUDE;
        assert!(
            b[altitude] < a[altitude],
            "{} vs {}",
            b[altitude],
            a[altitude]
        );
        for k in (0..FEATURES).filter(|&k| k != altitude) {
            assert_eq!(a[k], b[k], "feature {k}");
        }
    }

    #[test]
    fn a_task_marked_random_flies_waypoints_while_the_other_flies_the_actor() {
        use crate::replay::Batch;
        let mut config = TrainConfig::default();
        config.training.episode_step_limit = 50;
        config.ddpg.n_step = 1;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        // A fresh actor's outputs are tiny (OUTPUT_INIT_BOUND); the waypoints fly at full speed.
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let mut draw = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 3);
        let mut rollouts =
            Rollouts::new(2, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let mut replay: Vec<ReplayBuffer> = (0..2)
            .map(|_| ReplayBuffer::new(FEATURES, 3, 100))
            .collect();
        let controller = Controller::ActorExceptRandomTasks(&actor, 0.0, [true, false]);
        for _ in 0..4 {
            rollouts
                .step(&controller, &mut replay, None, &mut draw)
                .expect("step");
        }
        let planar_speed = |buffer: &ReplayBuffer| {
            let mut batch = Batch::default();
            buffer.sample(32, &mut ChaCha8Rng::seed_from_u64(4), &mut batch);
            assert!(batch.size > 0);
            batch
                .actions
                .chunks_exact(3)
                .map(|a| a[0].hypot(a[1]))
                .fold(f32::INFINITY, f32::min)
        };
        assert!(
            planar_speed(&replay[0]) > 0.5,
            "driving flies its waypoints"
        );
        let mut batch = Batch::default();
        replay[1].sample(32, &mut ChaCha8Rng::seed_from_u64(5), &mut batch);
        assert!(
            batch.actions.iter().all(|a| a.abs() < 0.05),
            "collecting flies the fresh actor"
        );
    }

    #[test]
    fn parameter_noise_flies_one_perturbed_actor_per_episode_and_adapts_its_scale() {
        let mut config = TrainConfig::default();
        config.training.episode_step_limit = 5;
        config.ddpg.n_step = 1;
        config.ddpg.exploration = Exploration::Parameter;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let mut draw = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 3);
        let mut rollouts =
            Rollouts::new(2, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let own = |r: &Rollouts, i: usize, net: &MultiTaskMlp| -> Vec<[f32; ACTION_DIM]> {
            let slot = &r.slots[i];
            let x: Vec<f32> = slot.features.iter().flatten().copied().collect();
            let y = net.predict_batch(slot.draw.task.index(), &x, slot.features.len());
            y.chunks_exact(ACTION_DIM)
                .map(|a| std::array::from_fn(|j| a[j].clamp(-1.0, 1.0)))
                .collect()
        };

        // Within an episode: the same perturbed actor, no per-step noise, not the actor itself.
        let first = rollouts.perturbed_actions(&actor, 0.3);
        let again = rollouts.perturbed_actions(&actor, 0.3);
        assert_eq!(first, again, "no noise on the actions between draws");
        for (i, actions) in first.iter().enumerate() {
            let task = rollouts.slots[i].draw.task.index();
            let direction = rollouts.slots[i].perturbation.clone().expect("drawn");
            let scale = rollouts.parameter_noise_scales()[task];
            assert_eq!(
                *actions,
                own(&rollouts, i, &actor.plus_scaled(&direction, scale))
            );
            assert_ne!(
                *actions,
                own(&rollouts, i, &actor),
                "slot {i} flies a perturbed actor"
            );
        }
        // The first draws had no observations to measure on, so the scale has not moved.
        assert_eq!(
            rollouts.parameter_noise_scales(),
            [PARAMETER_NOISE_INITIAL_SCALE; 2]
        );

        // An episode's end draws a new direction.
        let before = rollouts.slots[0].perturbation.clone();
        let mut replay: Vec<ReplayBuffer> = (0..2)
            .map(|_| ReplayBuffer::new(FEATURES, 3, 100))
            .collect();
        let controller = Controller::Actor(&actor, 0.3);
        let mut ended = 0;
        for _ in 0..6 {
            ended += rollouts
                .step(&controller, &mut replay, None, &mut draw)
                .expect("step")
                .len();
        }
        assert!(ended >= 2, "the 5-step episodes ended");
        assert!(rollouts.slots[0].perturbation.is_some());
        assert_ne!(
            rollouts.slots[0].perturbation, before,
            "a new episode, a new direction"
        );

        // The scale follows the wanted distance: actions in [-1, 1] are never 5 apart, so
        // asking for 5 grows it by the factor at a draw; asking for 1e-9 shrinks it.
        let grow = |r: &mut Rollouts, wanted: f32| {
            for s in &mut r.slots {
                s.perturbation = None;
            }
            r.perturbed_actions(&actor, wanted);
        };
        let start = rollouts.parameter_noise_scales();
        grow(&mut rollouts, 5.0);
        let grown = rollouts.parameter_noise_scales();
        for t in 0..2 {
            assert!(
                (grown[t] / start[t] - PARAMETER_NOISE_ADAPT).abs() < 1e-4,
                "{grown:?}"
            );
        }
        grow(&mut rollouts, 1e-9);
        grow(&mut rollouts, 1e-9);
        let shrunk = rollouts.parameter_noise_scales();
        for t in 0..2 {
            let twice = PARAMETER_NOISE_ADAPT * PARAMETER_NOISE_ADAPT;
            assert!((grown[t] / shrunk[t] - twice).abs() < 1e-4, "{shrunk:?}");
        }

        // Without a wanted distance the actor flies as it is.
        let plain = rollouts.perturbed_actions(&actor, 0.0);
        for (i, actions) in plain.iter().enumerate() {
            assert_eq!(*actions, own(&rollouts, i, &actor));
        }
    }

    #[test]
    fn the_action_distance_is_zero_for_one_actor_and_grows_with_the_perturbation() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let rows: Vec<[f32; FEATURES]> = (0..32)
            .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
            .collect();
        assert_eq!(action_distance(&actor, &actor, 1, &rows, 2), 0.0);
        assert_eq!(action_distance(&actor, &actor, 1, &[], 2), 0.0);
        let direction = actor.random_direction(1, &mut rng).expect("task 1");
        let near = actor.plus_scaled(&direction, 0.01);
        let far = actor.plus_scaled(&direction, 0.1);
        let (d_near, d_far) = (
            action_distance(&actor, &near, 1, &rows, 2),
            action_distance(&actor, &far, 1, &rows, 2),
        );
        assert!(d_near > 0.0 && d_far > 2.0 * d_near, "{d_near} {d_far}");
        assert_eq!(
            d_far,
            action_distance(&far, &actor, 1, &rows, 2),
            "symmetric"
        );
        assert_eq!(adapted_scale(0.1, 0.5, 0.3), 0.1 / PARAMETER_NOISE_ADAPT);
        assert_eq!(adapted_scale(0.1, 0.2, 0.3), 0.1 * PARAMETER_NOISE_ADAPT);
    }

    #[test]
    fn excursions_fly_collecting_herders_at_full_speed_to_a_target_and_leave_driving_alone() {
        let mut config = TrainConfig::default();
        config.training.excursion_rate = 1.0;
        config.training.excursion_radius_m = [0.0, 0.0];
        config.training.excursion_max_steps = 7;
        config.training.excursion_tasks = vec![Task::Collecting];
        config.validate().expect("valid excursions");
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let mut draw = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 3);
        let mut rollouts =
            Rollouts::new(2, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let actions = rollouts.choose_actions(&Controller::Actor(&actor, 0.0));
        for (slot, flown) in rollouts.slots.iter().zip(&actions) {
            let world = slot.env.observation();
            let v_max = world.limits.herder;
            for (h, a) in flown.iter().enumerate() {
                let v = slot.frames[h].expect("encoded").action_to_world(*a);
                let speed = f64::from(v[0].hypot(v[1]));
                if slot.draw.task == Task::Driving {
                    assert!(speed < 0.05 * v_max, "driving flies the fresh actor");
                    assert!(slot.herders[h].excursion.is_none());
                    continue;
                }
                assert!((speed - v_max).abs() < 1e-3 * v_max, "full speed: {speed}");
                let (w, until) = slot.herders[h].excursion.expect("on an excursion");
                assert_eq!(until, world.step + 7);
                assert!(
                    world.targets.contains(&w),
                    "radius 0: the waypoint is a target"
                );
                let p = world.herders[h];
                let (dx, dy) = (w[0] - p[0], w[1] - p[1]);
                let along = (f64::from(v[0]) * dx + f64::from(v[1]) * dy) / (speed * dx.hypot(dy));
                assert!(along > 0.999, "heads for its target: cos {along}");
            }
        }
        // Off (the default), the actor's actions are untouched.
        let plain = TrainConfig::default();
        let mut off =
            Rollouts::new(2, &plain, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let quiet = off.choose_actions(&Controller::Actor(&actor, 0.0));
        assert!(quiet.iter().flatten().flatten().all(|a| a.abs() < 0.05));
        // A radius that runs backwards, or excursions without a task, are refused by name.
        let mut bad = config.clone();
        bad.training.excursion_radius_m = [20.0, 5.0];
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("excursion_radius_m")
        );
        let mut bad = config.clone();
        bad.training.excursion_tasks.clear();
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("excursion_tasks")
        );
    }

    #[test]
    fn a_held_action_is_flown_for_its_steps_and_replayed_as_one_transition() {
        let mut config = TrainConfig::default();
        config.training.episode_step_limit = 7;
        config.training.action_repeat = 3;
        config.training.noise = false;
        config.ddpg.gamma = 0.5;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let mut draw = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 3);
        let mut rollouts =
            Rollouts::new(2, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let mut replay: Vec<ReplayBuffer> = (0..2)
            .map(|_| ReplayBuffer::new(FEATURES, 3, 100))
            .collect();
        let mut moves = Vec::new();
        for _ in 0..7 {
            let before = rollouts.slots[0].env.world().herders[0];
            // Noisy actions, so that a new decision flies a new velocity.
            rollouts
                .step(
                    &Controller::Actor(&actor, 0.3),
                    &mut replay,
                    None,
                    &mut draw,
                )
                .expect("step");
            if moves.len() < 6 {
                let after = rollouts.slots[0].env.world().herders[0];
                moves.push([after[0] - before[0], after[1] - before[1]]);
            }
        }
        // Steps 0-2 and 3-5 each fly one decision; the decisions differ.
        let close = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]) < 1e-9;
        assert!(
            close(moves[0], moves[1]) && close(moves[1], moves[2]),
            "{moves:?}"
        );
        assert!(
            close(moves[3], moves[4]) && close(moves[4], moves[5]),
            "{moves:?}"
        );
        assert!(
            !close(moves[2], moves[3]),
            "a new decision at step 3: {moves:?}"
        );
        // Seven steps: two holds of three and one of one (cut by the step limit), a transition
        // each per herder, bootstrapped over the simulator steps they span.
        for buffer in &replay {
            assert_eq!(buffer.len(), 9);
            let mut batch = Batch::default();
            buffer.sample(400, &mut ChaCha8Rng::seed_from_u64(3), &mut batch);
            let mut seen: Vec<f32> = batch.continues.clone();
            seen.sort_by(f32::total_cmp);
            seen.dedup();
            assert_eq!(
                seen,
                vec![0.25, 1.0],
                "gamma^(3-1) for a full hold, gamma^0 for the cut one"
            );
        }
        // The run is refused with a centralised critic, or with no decision at all.
        config.ddpg.centralised_critic = true;
        assert!(config.validate().is_err());
        config.ddpg.centralised_critic = false;
        config.training.action_repeat = 0;
        assert!(config.validate().is_err());
    }

    #[test]
    fn rollouts_fill_both_tasks_buffers_with_one_transition_per_herder() {
        let mut config = TrainConfig::default();
        config.training.episode_step_limit = 5;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let actor = MultiTaskMlp::new(MlpShape::actor(FEATURES, 16, 1), &mut rng);
        let fixed = |_: &mut ChaCha8Rng, task| Draw::paper(task, 4, 3);
        let mut draw = fixed;
        let mut rollouts =
            Rollouts::new(2, &config, ChaCha8Rng::seed_from_u64(2), &mut draw).expect("envs");
        let mut replay: Vec<ReplayBuffer> = (0..2)
            .map(|_| ReplayBuffer::new(FEATURES, 3, 100))
            .collect();
        let mut episodes = Vec::new();
        for _ in 0..5 {
            episodes.extend(
                rollouts
                    .step(
                        &Controller::Actor(&actor, 0.1),
                        &mut replay,
                        None,
                        &mut draw,
                    )
                    .expect("step"),
            );
        }
        assert_eq!(replay[0].len(), 15);
        assert_eq!(replay[1].len(), 15);
        assert_eq!(episodes.len(), 2, "both episodes truncated at 5 steps");
        let mut demos: Vec<ReplayBuffer> = (0..2)
            .map(|_| ReplayBuffer::new(FEATURES, 3, 100))
            .collect();
        rollouts
            .step(
                &Controller::Baseline(&WarmStartConfig {
                    driving_baseline: Method::FarthestTargets,
                    collecting_baseline: Method::FarthestTargets,
                    ..WarmStartConfig::default()
                }),
                &mut replay,
                Some(&mut demos),
                &mut draw,
            )
            .expect("step");
        assert_eq!(demos[0].len(), 3);
    }

    #[test]
    fn with_self_imitation_an_ended_episode_writes_each_transition_its_return() {
        let mut config = TrainConfig::default();
        config.ddpg.self_imitation = 0.5;
        config.ddpg.n_step = 5;
        // Undiscounted, herder 0's first return is the episode's learner return.
        config.ddpg.gamma = 1.0;
        config.training.episode_step_limit = 600;
        let rule = WarmStartConfig {
            driving_baseline: Method::FarthestTargets,
            collecting_baseline: Method::FarthestTargets,
            ..WarmStartConfig::default()
        };
        let run = |config: &TrainConfig| {
            let mut draw = |_: &mut ChaCha8Rng, _| Draw::paper(Task::Collecting, 4, 3);
            let mut rollouts =
                Rollouts::new(1, config, ChaCha8Rng::seed_from_u64(4), &mut draw).expect("envs");
            let mut replay: Vec<ReplayBuffer> = (0..2)
                .map(|_| ReplayBuffer::new(FEATURES, 3, 10_000))
                .collect();
            let task = Task::Collecting.index();
            for _ in 0..600 {
                let ended = rollouts
                    .step(&Controller::Baseline(&rule), &mut replay, None, &mut draw)
                    .expect("step");
                if let Some(e) = ended.first() {
                    let rows = replay[task].len();
                    return (*e, rows, replay.swap_remove(task));
                }
            }
            panic!("the rule did not end a collecting episode in 600 steps");
        };
        let (episode, rows, replay) = run(&config);
        assert!(episode.success, "the rule collects N = 4");
        assert_eq!(
            rows,
            3 * episode.steps as usize,
            "one transition per herder and step"
        );
        for i in 0..rows {
            let ret = replay.return_at(i);
            assert!(
                ret.is_finite(),
                "row {i} of an ended episode has its return"
            );
            let (reward, continues) = replay.reward_at(i);
            if continues == 0.0 {
                // The last transitions run to the end: their return is their own reward sum.
                assert!((ret - reward).abs() < 1e-3, "row {i}: {ret} vs {reward}");
            }
        }
        let first = f64::from(replay.return_at(0));
        assert!(
            (first - episode.learner_return).abs() < 1e-3 * episode.learner_return.abs().max(1.0),
            "herder 0's first return {first} vs the episode's {}",
            episode.learner_return
        );
        // Without self-imitation nothing is written.
        config.ddpg.self_imitation = 0.0;
        let (_, rows, replay) = run(&config);
        assert!((0..rows).all(|i| replay.return_at(i).is_nan()));
        // A truncated episode's returns stay unknown: it has no end to count to.
        config.ddpg.self_imitation = 0.5;
        config.training.episode_step_limit = 20;
        let (episode, rows, replay) = run(&config);
        assert!(!episode.success && episode.steps == 20);
        assert!((0..rows).all(|i| replay.return_at(i).is_nan()));
    }

    #[test]
    fn the_faster_filter_admits_successes_below_the_scenarios_recent_median() {
        let mut recent = RecentSuccesses::default();
        let faster = SelfImitationEpisodes::FasterThanMedian;
        let four = Draw::paper(Task::Collecting, 4, 4);
        let sixteen = Draw::paper(Task::Collecting, 16, 4);
        // Until FASTER_MIN successes are known, every success is admitted, no failure ever.
        assert!(!recent.admits(faster, four, false, 50));
        for k in 0..FASTER_MIN as u64 {
            assert!(recent.admits(faster, four, true, 200 + k));
        }
        // The window holds 200..=207: its median is 204.
        assert!(recent.admits(faster, four, true, 203));
        assert!(!recent.admits(faster, four, true, 204));
        assert!(!recent.admits(faster, four, false, 10));
        // Another flock size keeps a window of its own.
        assert!(recent.admits(faster, sixteen, true, 900));
        // The window keeps the last FASTER_WINDOW successes: after that many fast ones, the
        // slow early ones no longer set the median.
        for _ in 0..FASTER_WINDOW {
            recent.admits(faster, four, true, 100);
        }
        assert!(!recent.admits(faster, four, true, 150));
        assert!(recent.admits(faster, four, true, 99));
        // Without the filter, every ended episode is admitted.
        assert!(recent.admits(SelfImitationEpisodes::Ended, four, false, 600));
    }
}
