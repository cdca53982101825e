//! What each part of the flight loop costs a model indoors, measured in-process.
//!
//! The SITL mission (`skyherd-sitl`) differs from the simulator in several ways at once. This
//! replays the `indoor` preset in the simulator with one loop effect at a time wrapped around
//! the model, over many seeds, and prints the completion times:
//!
//! * `simulator`: the bare actor (`ActorPolicy::new`), none of the loop's effects;
//! * `tracked`: the model sees the ground's tracks (`TrackerConfig::scaled`, fed by the SITL
//!   detection sensor, `SensorConfig::for_scenario`: 2 cm noise, 95 % detection) instead of the
//!   simulator's noisy truth;
//!   `narrow-gate` the same with the tracker gate scaled by length alone, as it was before;
//! * `fence+floor`: the onboard safety rules (`Limits::arena`: 0.25 m fence, 0.5 m floor) trim
//!   every command, and the encoder reads the height above the floor, as the daemon does
//!   (what `skyherd-sim` does with a model file: `ActorPolicy::flying`);
//! * `stale-other`: the other drones' positions are one tick old, as in the ground's snapshot;
//!   `stale-extrap` the same, extrapolated one tick ahead from their last two positions;
//! * `all`: the three together (`all-extrap` with the extrapolation).
//!
//! ```sh
//! cargo run --release -p skyherd-sitl --example loop_costs -- models/mtddpg-v1.skym 64
//! ```

use skyherd_ground::tracking::{TrackedWorld, Tracker, TrackerConfig};
use skyherd_onboard::safety::{self, Limits, Situation};
use skyherd_sim::learned::{ActorPolicy, ModelPolicy};
use skyherd_sim::policy::Policy;
use skyherd_sim::world::World;
use skyherd_sim::{Env, Scenario, run_episode};
use skyherd_sitl::mission::sensor_seed;
use skyherd_sitl::sensor::{DetectionSensor, SensorConfig};

/// The loop effects applied around the model.
#[derive(Clone, Copy, Debug, Default)]
struct Effects {
    tracked: bool,
    /// The tracker's hard gate scaled by length alone, as before `TrackerConfig::scaled`
    /// widened it (10 cm here): ghost tracks beside kicked vehicles.
    narrow_gate: bool,
    safety: bool,
    stale_other: bool,
    /// With `stale_other`: the drone extrapolates the other drones one tick ahead from their
    /// last two positions (constant velocity), as a daemon could from two snapshots.
    extrapolate: bool,
}

/// The model with the chosen loop effects; see the module docs.
struct LoopLike {
    model: Box<dyn Policy + Send>,
    effects: Effects,
    limits: Limits,
    sensor: SensorConfig,
    tracking: Option<(DetectionSensor, Tracker)>,
    tracks: Vec<[f64; 2]>,
    before_previous: Vec<[f64; 3]>,
    previous_herders: Vec<[f64; 3]>,
    herders_now: Vec<[f64; 3]>,
    loaded_step: Option<u64>,
    seen: Option<World>,
}

impl LoopLike {
    fn new(model: Box<dyn Policy + Send>, effects: Effects, scenario: &Scenario) -> Self {
        let area = [
            scenario.area.width as f32,
            scenario.area.depth as f32,
            scenario.area.ceiling as f32,
        ];
        LoopLike {
            model,
            effects,
            limits: Limits::arena(area, scenario.limits.herder as f32),
            sensor: SensorConfig::for_scenario(scenario),
            tracking: None,
            tracks: Vec::new(),
            before_previous: Vec::new(),
            previous_herders: Vec::new(),
            herders_now: Vec::new(),
            loaded_step: None,
            seen: None,
        }
    }

    /// Once per step: scan and track, remember where the herders were.
    fn load(&mut self, world: &World) {
        if self.loaded_step == Some(world.step) {
            return;
        }
        self.loaded_step = Some(world.step);
        let previous = std::mem::replace(&mut self.herders_now, world.herders.clone());
        self.before_previous = std::mem::replace(&mut self.previous_herders, previous);
        if self.previous_herders.is_empty() {
            self.previous_herders = world.herders.clone();
        }
        if self.before_previous.is_empty() {
            self.before_previous = self.previous_herders.clone();
        }
        if let Some((sensor, tracker)) = self.tracking.as_mut() {
            let detections = sensor.scan(&world.targets);
            tracker
                .update(world.dt, &detections)
                .expect("a positive time step");
            self.tracks = tracker.confirmed().map(|t| t.position).collect();
        }
    }
}

impl Policy for LoopLike {
    fn reset(&mut self, world: &World, seed: u64) {
        self.loaded_step = None;
        self.herders_now.clear();
        self.previous_herders.clear();
        self.before_previous.clear();
        self.tracks.clear();
        self.tracking = self.effects.tracked.then(|| {
            let sensor = DetectionSensor::new(self.sensor.clone(), sensor_seed(seed))
                .expect("a valid sensor");
            // As `skyherd-sitl` configures the ground's tracker.
            let mut config = TrackerConfig::scaled(TrackedWorld {
                goal_radius: world.goal.radius,
                max_speed: world.limits.herder,
                measurement_std: self.sensor.position_std.max(1e-3),
                scan_period_s: world.dt,
            });
            if self.effects.narrow_gate {
                let length = world.goal.radius / 45.0;
                config.max_gate_radius = (TrackerConfig::default().max_gate_radius * length)
                    .max(5.0 * config.measurement_std);
            }
            let tracker = Tracker::new(config).expect("a valid tracker");
            (sensor, tracker)
        });
        self.model.reset(world, seed);
    }

    fn act(&mut self, world: &World, herder: usize) -> [f64; 3] {
        self.load(world);
        let seen = self.seen.get_or_insert_with(|| world.clone());
        seen.clone_from(world);
        if self.effects.tracked {
            if self.tracks.is_empty() {
                // The daemon cannot encode a world without targets: it holds.
                return [0.0; 3];
            }
            seen.targets.clone_from(&self.tracks);
        }
        for (j, h) in seen.herders.iter_mut().enumerate() {
            if self.effects.stale_other && j != herder {
                let (last, before) = (self.previous_herders[j], self.before_previous[j]);
                *h = if self.effects.extrapolate {
                    [0, 1, 2].map(|k| 2.0 * last[k] - before[k])
                } else {
                    last
                };
            }
            if self.effects.safety {
                h[2] = (h[2] - f64::from(self.limits.fence_min[2])).max(0.0);
            }
        }
        let velocity = self.model.act(seen, herder);
        if !self.effects.safety {
            return velocity;
        }
        let decision = safety::check(
            &self.limits,
            &Situation {
                position: world.herders[herder].map(|x| x as f32),
                velocity: velocity.map(|x| x as f32),
                snapshot_age_s: 0.0,
                snapshot_finite: true,
                current_velocity: None,
            },
        );
        decision.velocity.map(f64::from)
    }
}

fn main() {
    let mut args = std::env::args().skip(1);
    let model_path = args
        .next()
        .unwrap_or_else(|| "models/mtddpg-v1.skym".into());
    let seeds: u64 = args.next().map_or(64, |s| s.parse().expect("a seed count"));
    let model = ModelPolicy::from_file(model_path.as_ref()).expect("a model file");
    let mut scenario = Scenario::preset("indoor").expect("the indoor preset");
    scenario.step_limit = 3000;
    let variants = [
        ("simulator", Effects::default()),
        (
            "tracked",
            Effects {
                tracked: true,
                ..Effects::default()
            },
        ),
        (
            "narrow-gate",
            Effects {
                tracked: true,
                narrow_gate: true,
                ..Effects::default()
            },
        ),
        (
            "fence+floor",
            Effects {
                safety: true,
                ..Effects::default()
            },
        ),
        (
            "stale-other",
            Effects {
                stale_other: true,
                ..Effects::default()
            },
        ),
        (
            "stale-extrap",
            Effects {
                stale_other: true,
                extrapolate: true,
                ..Effects::default()
            },
        ),
        (
            "all",
            Effects {
                tracked: true,
                safety: true,
                stale_other: true,
                ..Effects::default()
            },
        ),
        (
            "all-extrap",
            Effects {
                tracked: true,
                safety: true,
                stale_other: true,
                extrapolate: true,
                ..Effects::default()
            },
        ),
    ];
    println!("{model_path}, indoor, seeds 0..{seeds}");
    for (name, effects) in variants {
        let mut env = Env::new(scenario.clone()).expect("a valid scenario");
        let mut times = Vec::new();
        for seed in 0..seeds {
            let mut policy = LoopLike::new(
                Box::new(ActorPolicy::new(*model.actor())),
                effects,
                &scenario,
            );
            let summary = run_episode(&mut env, &mut policy, seed, |_, _| {}).expect("an episode");
            times.push(if summary.success {
                summary.time_s
            } else {
                f64::INFINITY
            });
        }
        let mut sorted = times.clone();
        sorted.sort_by(f64::total_cmp);
        let solved: Vec<f64> = times.iter().copied().filter(|t| t.is_finite()).collect();
        println!(
            "{name:12} median {:5.1} s  mean {:5.1} s  success {}/{seeds}  <= 30 s: {}",
            sorted[sorted.len() / 2],
            solved.iter().sum::<f64>() / solved.len().max(1) as f64,
            solved.len(),
            solved.iter().filter(|t| **t <= 30.0).count()
        );
    }
}
