//! The two tasks: where things spawn, when an episode succeeds or fails, and its time lower bound.
//!
//! The paper fixes the arena, the goal radius (45 m) and the driving start radius (50 m); it is
//! silent on the rest, so these are our choices (one default each, in the presets):
//! * circles (goal, driving start) lie wholly inside the arena, `wall_margin` (50 m) clear of
//!   the walls, so that a flock spreading under separation does not start out of bounds;
//! * driving: start and goal centres are at least `min_start_goal_distance` (150 m) apart,
//!   targets uniform over the start disc;
//! * collecting: targets uniform over the arena less `wall_margin`, outside the goal circle;
//! * herders: uniform over the arena less `wall_margin`, at `herder_altitude` (2 m), and for
//!   driving at least `herder_clearance` (10 m) outside the start circle, so none spawns in the
//!   flock.

use rand::Rng;
use serde::{Deserialize, Serialize};
use skyherd_model::Task;

use crate::world::{Area, Goal, World, dist2};

/// Serde for [`Task`] as `"driving"` / `"collecting"` (the model crate's enum has no serde).
pub mod task_serde {
    use serde::{Deserialize, Deserializer, Serializer, de::Error};
    use skyherd_model::Task;

    /// Writes `"driving"` or `"collecting"`.
    pub fn serialize<S: Serializer>(task: &Task, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(super::task_name(*task))
    }

    /// Reads `"driving"` or `"collecting"`.
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Task, D::Error> {
        let name = String::deserialize(d)?;
        super::parse_task(&name).ok_or_else(|| {
            D::Error::custom(format!(
                "unknown task `{name}`, expected `driving` or `collecting`"
            ))
        })
    }
}

/// `"driving"` or `"collecting"`.
pub fn task_name(task: Task) -> &'static str {
    match task {
        Task::Driving => "driving",
        Task::Collecting => "collecting",
    }
}

/// Inverse of [`task_name`] (also accepts `drive` / `collect`).
pub fn parse_task(name: &str) -> Option<Task> {
    match name {
        "driving" | "drive" => Some(Task::Driving),
        "collecting" | "collect" => Some(Task::Collecting),
        _ => None,
    }
}

/// Where things spawn at reset. Lengths in metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Layout {
    /// Goal circle radius (paper: 45 m).
    pub goal_radius: f64,
    /// Driving start circle radius (paper: 50 m).
    pub start_radius: f64,
    /// Least distance between the driving start and goal centres.
    pub min_start_goal_distance: f64,
    /// Clearance between spawned circles or points and the arena walls.
    pub wall_margin: f64,
    /// Herders' spawn altitude.
    pub herder_altitude: f64,
    /// Driving: least distance between a spawned herder and the start circle's edge.
    pub herder_clearance: f64,
}

/// Rejection-sampling budget; validation guarantees that a far larger share than 1/1000 of draws
/// is acceptable, and if the budget is ever spent the best draw is kept (never a panic).
const MAX_DRAWS: usize = 100_000;

fn uniform_in_box<R: Rng>(rng: &mut R, lo: [f64; 2], hi: [f64; 2]) -> [f64; 2] {
    [
        rng.random_range(lo[0]..=hi[0]),
        rng.random_range(lo[1]..=hi[1]),
    ]
}

fn uniform_in_disc<R: Rng>(rng: &mut R, center: [f64; 2], radius: f64) -> [f64; 2] {
    let r = radius * rng.random::<f64>().sqrt();
    let a = rng.random::<f64>() * std::f64::consts::TAU;
    [center[0] + r * a.cos(), center[1] + r * a.sin()]
}

/// Box of centres for a circle of `radius` that keeps `margin` from the walls.
pub(crate) fn centre_box(area: &Area, radius: f64, margin: f64) -> ([f64; 2], [f64; 2]) {
    let m = radius + margin;
    ([m, m], [area.width - m, area.depth - m])
}

/// The spawned positions of one episode.
#[derive(Clone, Debug, PartialEq)]
pub struct Spawn {
    /// Goal circle.
    pub goal: Goal,
    /// Driving start circle centre (`None` for collecting).
    pub start_center: Option<[f64; 2]>,
    /// Herder positions.
    pub herders: Vec<[f64; 3]>,
    /// Target positions.
    pub targets: Vec<[f64; 2]>,
}

/// Draws one episode's layout from `rng`. The layout must have passed scenario validation
/// (circles fit in the arena); a non-fitting layout still returns positions, never panics.
pub fn spawn<R: Rng>(
    task: Task,
    layout: &Layout,
    area: &Area,
    herders: usize,
    targets: usize,
    rng: &mut R,
) -> Spawn {
    let (glo, ghi) = centre_box(area, layout.goal_radius, layout.wall_margin);
    let draw_goal = |rng: &mut R| uniform_in_box(rng, glo, fix_hi(glo, ghi));
    let mut goal_center = draw_goal(rng);
    let mut start_center = None;
    if task == Task::Driving {
        let (slo, shi) = centre_box(area, layout.start_radius, layout.wall_margin);
        let shi = fix_hi(slo, shi);
        let need2 = layout.min_start_goal_distance * layout.min_start_goal_distance;
        let mut best = (f64::MIN, goal_center, slo);
        for _ in 0..MAX_DRAWS {
            let g = draw_goal(rng);
            let s = uniform_in_box(rng, slo, shi);
            let d2 = dist2(g, s);
            if d2 > best.0 {
                best = (d2, g, s);
            }
            if d2 >= need2 {
                break;
            }
        }
        goal_center = best.1;
        start_center = Some(best.2);
    }
    let goal = Goal {
        center: goal_center,
        radius: layout.goal_radius,
    };
    let inner_lo = [layout.wall_margin, layout.wall_margin];
    let inner_hi = fix_hi(
        inner_lo,
        [
            area.width - layout.wall_margin,
            area.depth - layout.wall_margin,
        ],
    );
    let targets: Vec<[f64; 2]> = match start_center {
        Some(c) => (0..targets)
            .map(|_| uniform_in_disc(rng, c, layout.start_radius))
            .collect(),
        None => (0..targets)
            .map(|_| draw_until(rng, inner_lo, inner_hi, |p| !goal.contains(p)))
            .collect(),
    };
    let keep_out = start_center.map(|c| (c, layout.start_radius + layout.herder_clearance));
    let herders = (0..herders)
        .map(|_| {
            let p = draw_until(rng, inner_lo, inner_hi, |p| {
                keep_out.is_none_or(|(c, r)| dist2(p, c) > r * r)
            });
            [p[0], p[1], layout.herder_altitude.clamp(0.0, area.ceiling)]
        })
        .collect();
    Spawn {
        goal,
        start_center,
        herders,
        targets,
    }
}

fn fix_hi(lo: [f64; 2], hi: [f64; 2]) -> [f64; 2] {
    [hi[0].max(lo[0]), hi[1].max(lo[1])]
}

fn draw_until<R: Rng>(
    rng: &mut R,
    lo: [f64; 2],
    hi: [f64; 2],
    ok: impl Fn([f64; 2]) -> bool,
) -> [f64; 2] {
    let mut p = uniform_in_box(rng, lo, hi);
    for _ in 0..MAX_DRAWS {
        if ok(p) {
            break;
        }
        p = uniform_in_box(rng, lo, hi);
    }
    p
}

/// Time lower bound of an episode, seconds: the farthest target's distance to the goal circle's
/// edge at top target speed. (No target can be faster, so no policy can finish sooner.)
pub fn lower_bound_time(world: &World) -> f64 {
    let far = world
        .targets
        .iter()
        .map(|&t| dist2(t, world.goal.center).sqrt() - world.goal.radius)
        .fold(0.0, f64::max);
    if world.limits.target > 0.0 {
        far / world.limits.target
    } else {
        f64::INFINITY
    }
}
