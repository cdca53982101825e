//! The paper's world, eqs (1)-(6): a boids flock of ground targets pushed by 3-D point herders.
//!
//! Pure code: [`advance`] takes the whole state ([`World`], which carries its own `dt`) and the
//! herders' commanded velocities, and touches no clock, file or global.
//!
//! # Update order (not in the paper; it changes the result)
//! One step of `dt` seconds is, in this order:
//! 1. **Herders move first.** Each command is capped at the herder speed limit (3-D norm), the
//!    herder moves by `v dt`, and its altitude is clamped to `[0, ceiling]`.
//! 2. **Targets react to the herders' new positions.** Every target's velocity is computed from
//!    the same snapshot (synchronous, Jacobi-style: no target sees another's new position):
//!    separation and cohesion from the targets' positions before the step, alignment from their
//!    velocities of the previous step, herder repulsion from the herders' positions *after*
//!    step 1. The result is capped at the target speed limit.
//! 3. **Targets move** by `v dt`; `v` becomes their "previous velocity" for the next step.
//!
//! Herders-first means an action shows its effect on the flock in the same step, which gives a
//! learner a one-step shorter credit path. Concretely a target 20 m ahead of a herder that
//! closes in at 5 m/s is pushed at `a5 / 15^2 = 2.67` m/s, not `a5 / 20^2 = 1.5` m/s
//! (test `update_order_herders_move_first`).
//!
//! # Cost
//! Separation (eq 2) is found through a uniform grid of cell side `G1` rebuilt every step by a
//! counting sort into buffers that [`StepScratch`] keeps between steps, and each in-range pair is
//! visited once: a step costs O(N + N M) and allocates nothing once the scratch has seen the
//! flock's size. [`reference_step`] is the plain O(N^2) transcription of the equations; the
//! tests use it as the oracle.

use serde::{Deserialize, Serialize};
use skyherd_model::Task;
use thiserror::Error;

/// The arena `[0, width] x [0, depth] x [0, ceiling]`, metres, corner at the origin.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Area {
    /// Extent along x (east), metres.
    pub width: f64,
    /// Extent along y (north), metres.
    pub depth: f64,
    /// Highest allowed herder altitude, metres.
    pub ceiling: f64,
}

impl Area {
    /// Whether a ground point lies in the arena (edges included).
    pub fn contains_xy(&self, p: [f64; 2]) -> bool {
        p[0] >= 0.0 && p[0] <= self.width && p[1] >= 0.0 && p[1] <= self.depth
    }

    /// How close two drones may come (3-D, m) before it counts as a separation breach: 0.5 m
    /// in a room-sized arena (50 m or less across: small indoor drones), 3 m otherwise.
    pub fn breach_distance_m(&self) -> f64 {
        if self.width.max(self.depth) <= 50.0 {
            0.5
        } else {
            3.0
        }
    }
}

/// The smallest 3-D distance between two of `herders`, m (infinity with fewer than two).
pub fn closest_pair_m(herders: &[[f64; 3]]) -> f64 {
    let mut closest = f64::INFINITY;
    for (i, a) in herders.iter().enumerate() {
        for b in &herders[i + 1..] {
            let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
            closest = closest.min(d);
        }
    }
    closest
}

/// The goal circle on the ground.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Goal {
    /// Centre `[x, y]`, metres.
    pub center: [f64; 2],
    /// Radius, metres.
    pub radius: f64,
}

impl Goal {
    /// Whether a ground point lies inside the goal circle (edge included).
    pub fn contains(&self, p: [f64; 2]) -> bool {
        dist2(p, self.center) <= self.radius * self.radius
    }
}

/// Boids coefficients of eqs (1), (5), (6); paper defaults in [`BoidsParams::PAPER`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoidsParams {
    /// `a1`, separation weight.
    pub separation: f64,
    /// `a2`, alignment weight.
    pub alignment: f64,
    /// `a3`, cohesion weight.
    pub cohesion: f64,
    /// `a4`, weight of the flock's own rules.
    pub flock: f64,
    /// `a5`, weight of the herders' repulsion.
    pub herder: f64,
    /// `G1`, separation range, metres.
    pub separation_range: f64,
    /// How a target perceives a herder's height in the repulsion's 3-D distance (eq 4): the
    /// herder counts as `herder_height_scale * z` above the ground. 1 (the default) is the
    /// paper's plain 3-D distance. Below 1 models ground vehicles that react to a drone flying
    /// higher than the world's own length scale would put it (the `indoor` room, whose ceiling is
    /// not zoomed with the floor). Not one of the paper's six: test-time noise leaves it alone.
    #[serde(default = "paper_height_scale")]
    pub herder_height_scale: f64,
}

fn paper_height_scale() -> f64 {
    1.0
}

impl BoidsParams {
    /// Section IV-A: a1=100, a2=0.05, a3=0.01, a4=0.5, a5=600, G1=5 m.
    pub const PAPER: BoidsParams = BoidsParams {
        separation: 100.0,
        alignment: 0.05,
        cohesion: 0.01,
        flock: 0.5,
        herder: 600.0,
        separation_range: 5.0,
        herder_height_scale: 1.0,
    };

    /// The paper's six values in a fixed order (a1, a2, a3, a4, a5, G1).
    pub fn to_array(self) -> [f64; 6] {
        [
            self.separation,
            self.alignment,
            self.cohesion,
            self.flock,
            self.herder,
            self.separation_range,
        ]
    }

    /// These parameters with the paper's six replaced by `a` (the order of
    /// [`BoidsParams::to_array`]); the rest are kept.
    pub fn with_array(self, a: [f64; 6]) -> Self {
        BoidsParams {
            separation: a[0],
            alignment: a[1],
            cohesion: a[2],
            flock: a[3],
            herder: a[4],
            separation_range: a[5],
            ..self
        }
    }
}

/// Speed limits, m/s.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpeedLimits {
    /// Targets' top speed (paper: 3 m/s).
    pub target: f64,
    /// Herders' top speed, 3-D norm (paper: 5 m/s).
    pub herder: f64,
}

impl SpeedLimits {
    /// Section IV-A: targets 3 m/s, herders 5 m/s.
    pub const PAPER: SpeedLimits = SpeedLimits {
        target: 3.0,
        herder: 5.0,
    };
}

/// The full simulator state; also the JSON schema of `skyherd-sim step` and of traces.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct World {
    /// Which task the episode is.
    #[serde(with = "crate::task::task_serde")]
    pub task: Task,
    /// The arena.
    pub area: Area,
    /// The goal circle.
    pub goal: Goal,
    /// Boids coefficients in force (after any per-episode noise).
    pub params: BoidsParams,
    /// Speed limits.
    pub limits: SpeedLimits,
    /// Length of one step, seconds (paper: 1 s).
    pub dt: f64,
    /// Steps taken since reset.
    pub step: u64,
    /// Herder positions `[x, y, z]`, metres.
    pub herders: Vec<[f64; 3]>,
    /// Target ground positions `[x, y]`, metres (their z is always 0).
    pub targets: Vec<[f64; 2]>,
    /// Each target's velocity of the previous step, m/s (eq 3 averages these).
    pub target_velocities: Vec<[f64; 2]>,
}

/// Why a world or an action list cannot be stepped.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum WorldError {
    /// The number of actions differs from the number of herders.
    #[error("expected {expected} herder actions, got {got}")]
    ActionCount {
        /// Herders in the world.
        expected: usize,
        /// Actions given.
        got: usize,
    },
    /// An action holds NaN or infinity.
    #[error("action of herder {herder} is not finite: {action:?}")]
    NonFiniteAction {
        /// Which herder.
        herder: usize,
        /// The action.
        action: [f64; 3],
    },
    /// A state field is out of its domain.
    #[error("invalid world field `{field}`: {reason}")]
    Invalid {
        /// Dotted path of the field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

fn invalid(field: &'static str, reason: impl Into<String>) -> WorldError {
    WorldError::Invalid {
        field,
        reason: reason.into(),
    }
}

/// The largest magnitude any length, coordinate, speed or boids weight of a valid world may
/// have: 1,000 km (or 10^6 in the weight's units). Far beyond any arena, and small enough that
/// no arithmetic of a step overflows (a target at -1.7e308 m once made the separation grid
/// index out of bounds).
pub const MAX_MAGNITUDE: f64 = 1.0e6;

fn check_finite_pos(field: &'static str, v: f64) -> Result<(), WorldError> {
    if v > MAX_MAGNITUDE {
        return Err(invalid(
            field,
            format!("must be at most {MAX_MAGNITUDE:e}, got {v}"),
        ));
    }
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(field, format!("must be finite and > 0, got {v}")))
    }
}

fn check_finite_nonneg(field: &'static str, v: f64) -> Result<(), WorldError> {
    if v > MAX_MAGNITUDE {
        return Err(invalid(
            field,
            format!("must be at most {MAX_MAGNITUDE:e}, got {v}"),
        ));
    }
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(invalid(field, format!("must be finite and >= 0, got {v}")))
    }
}

impl World {
    /// Checks every field's domain: positive sizes, finite coordinates, matching lengths.
    pub fn validate(&self) -> Result<(), WorldError> {
        check_finite_pos("area.width", self.area.width)?;
        check_finite_pos("area.depth", self.area.depth)?;
        check_finite_nonneg("area.ceiling", self.area.ceiling)?;
        check_finite_pos("goal.radius", self.goal.radius)?;
        let in_range = |c: &f64| c.is_finite() && c.abs() <= MAX_MAGNITUDE;
        if !self.goal.center.iter().all(in_range) {
            return Err(invalid(
                "goal.center",
                format!("must be finite, within {MAX_MAGNITUDE:e} m"),
            ));
        }
        check_finite_nonneg("params.separation", self.params.separation)?;
        check_finite_nonneg("params.alignment", self.params.alignment)?;
        check_finite_nonneg("params.cohesion", self.params.cohesion)?;
        check_finite_nonneg("params.flock", self.params.flock)?;
        check_finite_nonneg("params.herder", self.params.herder)?;
        check_finite_nonneg("params.separation_range", self.params.separation_range)?;
        check_finite_nonneg(
            "params.herder_height_scale",
            self.params.herder_height_scale,
        )?;
        check_finite_nonneg("limits.target", self.limits.target)?;
        check_finite_nonneg("limits.herder", self.limits.herder)?;
        check_finite_pos("dt", self.dt)?;
        if self.herders.is_empty() {
            return Err(invalid("herders", "need at least one herder"));
        }
        if self.targets.is_empty() {
            return Err(invalid("targets", "need at least one target"));
        }
        if self.target_velocities.len() != self.targets.len() {
            return Err(invalid(
                "target_velocities",
                format!(
                    "has {} entries for {} targets",
                    self.target_velocities.len(),
                    self.targets.len()
                ),
            ));
        }
        if !self.herders.iter().flatten().all(in_range) {
            return Err(invalid(
                "herders",
                format!("coordinates must be finite, within {MAX_MAGNITUDE:e} m"),
            ));
        }
        if !self.targets.iter().flatten().all(in_range) {
            return Err(invalid(
                "targets",
                format!("coordinates must be finite, within {MAX_MAGNITUDE:e} m"),
            ));
        }
        if !self.target_velocities.iter().flatten().all(in_range) {
            return Err(invalid(
                "target_velocities",
                format!("must be finite, within {MAX_MAGNITUDE:e} m/s"),
            ));
        }
        Ok(())
    }

    /// The paper's observation: an (M + N + 1) x 3 matrix of herders, targets (z = 0) and the goal
    /// centre (z = 0), written into `out` (cleared first, so a reused buffer does not allocate).
    pub fn observation_matrix(&self, out: &mut Vec<[f64; 3]>) {
        out.clear();
        out.extend_from_slice(&self.herders);
        out.extend(self.targets.iter().map(|t| [t[0], t[1], 0.0]));
        out.push([self.goal.center[0], self.goal.center[1], 0.0]);
    }

    /// Mean target position.
    pub fn flock_centroid(&self) -> [f64; 2] {
        let n = self.targets.len().max(1) as f64;
        let (sx, sy) = self
            .targets
            .iter()
            .fold((0.0, 0.0), |(sx, sy), t| (sx + t[0], sy + t[1]));
        [sx / n, sy / n]
    }

    /// Whether every target is inside the goal circle.
    pub fn all_targets_in_goal(&self) -> bool {
        self.targets.iter().all(|&t| self.goal.contains(t))
    }

    /// Whether any herder or target is outside the arena's ground rectangle.
    pub fn anything_outside(&self) -> bool {
        self.targets.iter().any(|&t| !self.area.contains_xy(t))
            || self
                .herders
                .iter()
                .any(|h| !self.area.contains_xy([h[0], h[1]]))
    }
}

/// Herder count for `n` targets when "adaptive": `2^floor(log2(n) / 2)`, at least 1.
///
/// The paper prints `S / 2^floor(log2 S / 2)`, which is 2 for every power of two, so we read it
/// as the square-root-like rule: 1, 1, 2, 2, 4, 4, 8, 8, 16, 16, 32 for n = 1, 2, 4, ..., 1024.
pub fn adaptive_herders(n: usize) -> usize {
    if n <= 1 {
        return 1;
    }
    let log2 = usize::BITS - 1 - n.leading_zeros();
    1 << (log2 / 2)
}

#[inline]
pub(crate) fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    let dx = a[0] - b[0];
    let dy = a[1] - b[1];
    dx * dx + dy * dy
}

/// Scales `v` down to norm `max` if it is longer; keeps its direction.
#[inline]
pub(crate) fn cap2(v: [f64; 2], max: f64) -> [f64; 2] {
    let n2 = v[0] * v[0] + v[1] * v[1];
    if n2 > max * max {
        let s = max / n2.sqrt();
        [v[0] * s, v[1] * s]
    } else {
        v
    }
}

/// 3-D version of [`cap2`].
#[inline]
pub(crate) fn cap3(v: [f64; 3], max: f64) -> [f64; 3] {
    let n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    if n2 > max * max {
        let s = max / n2.sqrt();
        [v[0] * s, v[1] * s, v[2] * s]
    } else {
        v
    }
}

/// Pairs closer than this (squared, m^2) have no defined direction and add no separation or
/// repulsion; random spawns never produce them, exact copies in a hand-made state might.
const COINCIDENT_D2: f64 = 1e-18;

/// Step 1 of the update order: move the herders by their capped commands, clamp altitude.
fn move_herders(world: &mut World, actions: &[[f64; 3]]) -> Result<(), WorldError> {
    if actions.len() != world.herders.len() {
        return Err(WorldError::ActionCount {
            expected: world.herders.len(),
            got: actions.len(),
        });
    }
    if let Some((herder, &action)) = actions
        .iter()
        .enumerate()
        .find(|(_, a)| !a.iter().all(|c| c.is_finite()))
    {
        return Err(WorldError::NonFiniteAction { herder, action });
    }
    let dt = world.dt;
    let ceiling = world.area.ceiling;
    let vmax = world.limits.herder;
    for (h, &a) in world.herders.iter_mut().zip(actions) {
        let v = cap3(a, vmax);
        h[0] += v[0] * dt;
        h[1] += v[1] * dt;
        h[2] = (h[2] + v[2] * dt).clamp(0.0, ceiling);
    }
    Ok(())
}

/// Reusable buffers for [`advance`]: the spatial grid and per-target accumulators.
#[derive(Clone, Debug, Default)]
pub struct StepScratch {
    cell_of: Vec<u32>,
    cell_start: Vec<u32>,
    order: Vec<u32>,
    sorted_pos: Vec<[f64; 2]>,
    sorted_sep: Vec<[f64; 2]>,
    new_velocity: Vec<[f64; 2]>,
    repulsion: Vec<[f64; 2]>,
}

impl StepScratch {
    /// Buffers sized for `targets` targets, so the first step does not allocate either.
    pub fn with_capacity(targets: usize) -> Self {
        let mut s = StepScratch::default();
        s.ensure(targets);
        s
    }

    fn max_cells(n: usize) -> usize {
        (4 * n).max(1024)
    }

    fn ensure(&mut self, n: usize) {
        if self.cell_of.len() != n {
            self.cell_of.resize(n, 0);
            self.order.resize(n, 0);
            self.sorted_pos.resize(n, [0.0; 2]);
            self.sorted_sep.resize(n, [0.0; 2]);
            self.new_velocity.resize(n, [0.0; 2]);
            self.repulsion.resize(n, [0.0; 2]);
        }
        let cells = Self::max_cells(n) + 1;
        if self.cell_start.len() < cells {
            self.cell_start.resize(cells, 0);
        }
    }
}

/// Eq (2) for every target through the grid: `sep[i] = sum_j (x_i - x_j) / |x_i - x_j|^3` over
/// the others within `range` (inclusive). Writes into `scratch.new_velocity` (indexed like
/// `targets`).
fn separation_grid(targets: &[[f64; 2]], range: f64, scratch: &mut StepScratch) {
    let n = targets.len();
    scratch.ensure(n);
    if range <= 0.0 || n < 2 {
        scratch.new_velocity.fill([0.0, 0.0]);
        return;
    }
    let (mut min_x, mut min_y, mut max_x, mut max_y) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for t in targets {
        min_x = min_x.min(t[0]);
        min_y = min_y.min(t[1]);
        max_x = max_x.max(t[0]);
        max_y = max_y.max(t[1]);
    }
    // A cell a hair wider than G1 guarantees in-range pairs sit in adjacent cells despite rounding;
    // a spread-out flock gets wider cells (still correct, fewer of them) so the buffer stays bounded.
    let max_cells = StepScratch::max_cells(n);
    let mut cell = range * (1.0 + 1e-9);
    let (mut nx, mut ny);
    loop {
        // Saturating: a validated world keeps these small, and an unvalidated one must not
        // wrap them to 0.
        nx = (((max_x - min_x) / cell) as usize).saturating_add(1);
        ny = (((max_y - min_y) / cell) as usize).saturating_add(1);
        if nx.saturating_mul(ny) <= max_cells {
            break;
        }
        cell *= 2.0;
    }
    let inv_cell = 1.0 / cell;
    let cells = nx * ny;
    let StepScratch {
        cell_of,
        cell_start,
        order,
        sorted_pos,
        sorted_sep,
        ..
    } = scratch;
    let cell_start = &mut cell_start[..cells + 1];
    cell_start.fill(0);
    for (i, t) in targets.iter().enumerate() {
        let cx = (((t[0] - min_x) * inv_cell) as usize).min(nx - 1);
        let cy = (((t[1] - min_y) * inv_cell) as usize).min(ny - 1);
        let c = cy * nx + cx;
        cell_of[i] = c as u32;
        cell_start[c + 1] += 1;
    }
    for c in 0..cells {
        cell_start[c + 1] += cell_start[c];
    }
    // Counting sort; `cell_start[c]` is used as the fill cursor and restored afterwards.
    for (i, &c) in cell_of.iter().enumerate() {
        let slot = cell_start[c as usize] as usize;
        order[slot] = i as u32;
        sorted_pos[slot] = targets[i];
        cell_start[c as usize] += 1;
    }
    for c in (1..=cells).rev() {
        cell_start[c] = cell_start[c - 1];
    }
    cell_start[0] = 0;
    sorted_sep.fill([0.0, 0.0]);

    let range2 = range * range;
    // Each pair once: within the cell (b > a), then the four "forward" neighbour cells. The sum
    // for `a` stays in registers (`acc`); only the partners' sums go through memory.
    let pairs = |a: usize, others: std::ops::Range<usize>, sorted_sep: &mut [[f64; 2]]| {
        let pa = sorted_pos[a];
        let mut acc = [0.0, 0.0];
        for b in others {
            let pb = sorted_pos[b];
            let dx = pa[0] - pb[0];
            let dy = pa[1] - pb[1];
            let d2 = dx * dx + dy * dy;
            let inv = if d2 <= range2 && d2 > COINCIDENT_D2 {
                1.0 / (d2 * d2.sqrt())
            } else {
                0.0
            };
            let fx = dx * inv;
            let fy = dy * inv;
            acc[0] += fx;
            acc[1] += fy;
            sorted_sep[b][0] -= fx;
            sorted_sep[b][1] -= fy;
        }
        sorted_sep[a][0] += acc[0];
        sorted_sep[a][1] += acc[1];
    };
    for cy in 0..ny {
        for cx in 0..nx {
            let c = cy * nx + cx;
            let (s, e) = (cell_start[c] as usize, cell_start[c + 1] as usize);
            if s == e {
                continue;
            }
            // Forward neighbours that exist: (+1, 0), (-1, +1), (0, +1), (+1, +1).
            let right = cx + 1 < nx;
            let up = cy + 1 < ny;
            let span = |d: usize| cell_start[d] as usize..cell_start[d + 1] as usize;
            for a in s..e {
                pairs(a, a + 1..e, sorted_sep);
                if right {
                    pairs(a, span(c + 1), sorted_sep);
                }
                if up {
                    let above = c + nx;
                    if cx > 0 {
                        pairs(a, span(above - 1), sorted_sep);
                    }
                    pairs(a, span(above), sorted_sep);
                    if right {
                        pairs(a, span(above + 1), sorted_sep);
                    }
                }
            }
        }
    }
    for slot in 0..n {
        scratch.new_velocity[scratch.order[slot] as usize] = scratch.sorted_sep[slot];
    }
}

/// One step of `world.dt` seconds with the herders' commanded velocities (m/s, sim frame), in
/// the documented update order, noise-free. `scratch` is reused between calls.
pub fn advance(
    world: &mut World,
    actions: &[[f64; 3]],
    scratch: &mut StepScratch,
) -> Result<(), WorldError> {
    move_herders(world, actions)?;
    let n = world.targets.len();
    // The separation sums land in `new_velocity` first; the loop below turns them into velocities.
    separation_grid(&world.targets, world.params.separation_range, scratch);
    let (mean_v, mean_x) = means(&world.target_velocities, &world.targets);
    let p = world.params;
    // Herder-major so that the inner loop runs over targets without branches and vectorises.
    scratch.repulsion.clear();
    scratch.repulsion.resize(n, [0.0, 0.0]);
    let height_scale = world.params.herder_height_scale;
    for h in &world.herders {
        let hz = height_scale * h[2];
        let hz2 = hz * hz;
        for (t, acc) in world.targets.iter().zip(scratch.repulsion.iter_mut()) {
            let dx = t[0] - h[0];
            let dy = t[1] - h[1];
            let d2 = dx * dx + dy * dy + hz2;
            let inv = if d2 > COINCIDENT_D2 {
                1.0 / (d2 * d2.sqrt())
            } else {
                0.0
            };
            acc[0] += dx * inv;
            acc[1] += dy * inv;
        }
    }
    for i in 0..n {
        let x = world.targets[i];
        let sep = scratch.new_velocity[i];
        let rep = scratch.repulsion[i];
        let mut v = [0.0; 2];
        for k in 0..2 {
            let boids =
                p.separation * sep[k] + p.alignment * mean_v[k] + p.cohesion * (mean_x[k] - x[k]);
            v[k] = p.flock * boids + p.herder * rep[k];
        }
        scratch.new_velocity[i] = cap2(v, world.limits.target);
    }
    integrate_targets(world, &scratch.new_velocity);
    world.step = world.step.saturating_add(1);
    Ok(())
}

fn means(velocities: &[[f64; 2]], positions: &[[f64; 2]]) -> ([f64; 2], [f64; 2]) {
    let n = positions.len().max(1) as f64;
    let mut sv = [0.0, 0.0];
    let mut sx = [0.0, 0.0];
    for (v, x) in velocities.iter().zip(positions) {
        sv[0] += v[0];
        sv[1] += v[1];
        sx[0] += x[0];
        sx[1] += x[1];
    }
    ([sv[0] / n, sv[1] / n], [sx[0] / n, sx[1] / n])
}

fn integrate_targets(world: &mut World, velocities: &[[f64; 2]]) {
    let dt = world.dt;
    for ((x, v_prev), &v) in world
        .targets
        .iter_mut()
        .zip(world.target_velocities.iter_mut())
        .zip(velocities)
    {
        x[0] += v[0] * dt;
        x[1] += v[1] * dt;
        *v_prev = v;
    }
}

/// The plain O(N^2) transcription of eqs (1)-(6) in the same update order: the test oracle and
/// the benchmark's baseline. Allocates; do not use it in a training loop.
pub fn reference_step(world: &mut World, actions: &[[f64; 3]]) -> Result<(), WorldError> {
    move_herders(world, actions)?;
    let n = world.targets.len();
    let p = world.params;
    let nf = n as f64;
    let mut velocities = Vec::with_capacity(n);
    for i in 0..n {
        let xi = world.targets[i];
        let mut sep = [0.0, 0.0];
        let mut align = [0.0, 0.0];
        let mut coh = [0.0, 0.0];
        for j in 0..n {
            let xj = world.targets[j];
            align[0] += world.target_velocities[j][0] / nf;
            align[1] += world.target_velocities[j][1] / nf;
            coh[0] += xj[0] / nf;
            coh[1] += xj[1] / nf;
            if j == i {
                continue;
            }
            let d = [xi[0] - xj[0], xi[1] - xj[1]];
            let norm = (d[0] * d[0] + d[1] * d[1]).sqrt();
            if norm <= p.separation_range && norm * norm > COINCIDENT_D2 {
                sep[0] += d[0] / norm.powi(3);
                sep[1] += d[1] / norm.powi(3);
            }
        }
        coh[0] -= xi[0];
        coh[1] -= xi[1];
        let mut rep = [0.0, 0.0, 0.0];
        for h in &world.herders {
            let d = [xi[0] - h[0], xi[1] - h[1], -p.herder_height_scale * h[2]];
            let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if norm * norm > COINCIDENT_D2 {
                for k in 0..3 {
                    rep[k] += d[k] / norm.powi(3);
                }
            }
        }
        rep[2] = 0.0;
        let mut v = [0.0, 0.0];
        for k in 0..2 {
            let boids = p.separation * sep[k] + p.alignment * align[k] + p.cohesion * coh[k];
            v[k] = p.flock * boids + p.herder * rep[k];
        }
        velocities.push(cap2(v, world.limits.target));
    }
    integrate_targets(world, &velocities);
    world.step = world.step.saturating_add(1);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn world(herders: Vec<[f64; 3]>, targets: Vec<[f64; 2]>, params: BoidsParams) -> World {
        let n = targets.len();
        World {
            task: Task::Driving,
            area: Area {
                width: 500.0,
                depth: 500.0,
                ceiling: 10.0,
            },
            goal: Goal {
                center: [400.0, 400.0],
                radius: 45.0,
            },
            params,
            limits: SpeedLimits::PAPER,
            dt: 1.0,
            step: 0,
            herders,
            targets,
            target_velocities: vec![[0.0; 2]; n],
        }
    }

    fn step(w: &mut World, actions: &[[f64; 3]]) {
        advance(w, actions, &mut StepScratch::default()).unwrap();
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-9 * (1.0 + b.abs())
    }

    #[test]
    fn two_targets_one_herder_by_hand() {
        // A at (50, 50), B 4.5 m east, herder 20 m south of A at 2 m altitude, idle.
        let mut w = world(
            vec![[50.0, 30.0, 2.0]],
            vec![[50.0, 50.0], [54.5, 50.0]],
            BoidsParams::PAPER,
        );
        w.target_velocities = vec![[1.0, 0.0], [0.0, 1.0]];
        step(&mut w, &[[0.0; 3]]);
        // A: sep = (-4.5, 0) / 4.5^3; align = mean v = (0.5, 0.5); coh = (52.25 - 50, 0).
        let sep_x = -4.5 / (4.5f64 * 4.5 * 4.5);
        let boids_ax = 100.0 * sep_x + 0.05 * 0.5 + 0.01 * 2.25;
        let boids_ay = 0.05 * 0.5;
        // Repulsion: (0, 20, -2) / |(0, 20, -2)|^3, z dropped.
        let d3 = 404f64.powf(1.5);
        let rep_ay = 20.0 / d3;
        let va = [0.5 * boids_ax, 0.5 * boids_ay + 600.0 * rep_ay];
        assert!(va[0].hypot(va[1]) < 3.0, "case must stay under the cap");
        assert!(close(w.target_velocities[0][0], va[0]));
        assert!(close(w.target_velocities[0][1], va[1]));
        assert!(close(w.targets[0][0], 50.0 + va[0]));
        assert!(close(w.targets[0][1], 50.0 + va[1]));
        // B mirrors A's separation and cohesion; the herder is at (-4.5, 20, -2) from it.
        let boids_bx = -100.0 * sep_x + 0.05 * 0.5 - 0.01 * 2.25;
        let db3 = (4.5f64 * 4.5 + 400.0 + 4.0).powf(1.5);
        let vb = [
            0.5 * boids_bx + 600.0 * 4.5 / db3,
            0.5 * (0.05 * 0.5) + 600.0 * 20.0 / db3,
        ];
        // B's raw speed is about 3.1 m/s, so the 3 m/s cap scales it down.
        let speed = vb[0].hypot(vb[1]);
        assert!(speed > 3.0);
        let vb = [vb[0] * 3.0 / speed, vb[1] * 3.0 / speed];
        assert!(close(w.target_velocities[1][0], vb[0]));
        assert!(close(w.target_velocities[1][1], vb[1]));
        assert_eq!(w.step, 1);
    }

    fn separation_only() -> BoidsParams {
        BoidsParams {
            alignment: 0.0,
            cohesion: 0.0,
            herder: 0.0,
            ..BoidsParams::PAPER
        }
    }

    #[test]
    fn separation_range_edge_is_inclusive() {
        // Exactly G1 apart: a4 a1 / G1^2 = 0.5 * 100 / 25 = 2 m/s apart.
        let mut w = world(
            vec![[0.0; 3]],
            vec![[100.0, 100.0], [105.0, 100.0]],
            separation_only(),
        );
        step(&mut w, &[[0.0; 3]]);
        assert!(close(w.target_velocities[0][0], -2.0));
        assert!(close(w.target_velocities[1][0], 2.0));
        // A hair beyond G1: no separation at all.
        let mut w = world(
            vec![[0.0; 3]],
            vec![[100.0, 100.0], [105.000_001, 100.0]],
            separation_only(),
        );
        step(&mut w, &[[0.0; 3]]);
        assert_eq!(w.target_velocities, vec![[0.0; 2]; 2]);
    }

    #[test]
    fn target_speed_is_capped_at_3() {
        let mut w = world(
            vec![[100.0, 99.0, 0.0]],
            vec![[100.0, 100.0]],
            BoidsParams::PAPER,
        );
        step(&mut w, &[[0.0; 3]]);
        let v = w.target_velocities[0];
        assert!(close(v[0].hypot(v[1]), 3.0));
        assert!(close(v[1], 3.0) && v[0].abs() < 1e-12);
    }

    #[test]
    fn herder_speed_capped_at_5_and_altitude_clamped() {
        let mut w = world(
            vec![
                [100.0, 100.0, 2.0],
                [200.0, 200.0, 9.0],
                [300.0, 300.0, 1.0],
            ],
            vec![[10.0, 10.0]],
            BoidsParams::PAPER,
        );
        step(
            &mut w,
            &[[3.0, 4.0, 12.0], [0.0, 0.0, 5.0], [1.0, 0.0, -4.0]],
        );
        // (3, 4, 12) has norm 13 -> scaled by 5/13.
        let h = w.herders[0];
        assert!(close(h[0], 100.0 + 15.0 / 13.0));
        assert!(close(h[1], 100.0 + 20.0 / 13.0));
        assert!(close(h[2], 2.0 + 60.0 / 13.0));
        assert_eq!(w.herders[1][2], 10.0, "ceiling");
        assert_eq!(w.herders[2][2], 0.0, "ground");
        assert_eq!(w.herders[2][0], 301.0);
    }

    #[test]
    fn repulsion_uses_3d_distance_and_drops_z() {
        let params = BoidsParams {
            herder: 10.0,
            ..separation_only()
        };
        // Herder 3 m east of the target, 4 m up: distance 5, push 10 * 3 / 125 westwards.
        let mut w = world(vec![[103.0, 100.0, 4.0]], vec![[100.0, 100.0]], params);
        step(&mut w, &[[0.0; 3]]);
        assert!(close(w.target_velocities[0][0], -10.0 * 3.0 / 125.0));
        assert_eq!(w.target_velocities[0][1], 0.0);
        // Straight overhead the push is all z, which is dropped: the target stays put.
        let mut w = world(vec![[100.0, 100.0, 4.0]], vec![[100.0, 100.0]], params);
        step(&mut w, &[[0.0; 3]]);
        assert_eq!(w.targets[0], [100.0, 100.0]);
    }

    #[test]
    fn height_scale_shrinks_the_herders_height_only() {
        let params = BoidsParams {
            herder: 10.0,
            herder_height_scale: 0.5,
            ..separation_only()
        };
        // Herder 3 m east, 8 m up, seen at 4 m: distance 5, push 10 * 3 / 125 westwards.
        let mut w = world(vec![[103.0, 100.0, 8.0]], vec![[100.0, 100.0]], params);
        step(&mut w, &[[0.0; 3]]);
        assert!(close(w.target_velocities[0][0], -10.0 * 3.0 / 125.0));
        // The herder itself still flies at 8 m, and the oracle agrees.
        assert_eq!(w.herders[0][2], 8.0);
        let mut r = world(vec![[103.0, 100.0, 8.0]], vec![[100.0, 100.0]], params);
        reference_step(&mut r, &[[0.0; 3]]).unwrap();
        assert!(close(r.target_velocities[0][0], w.target_velocities[0][0]));
        // A scale of 0: the vehicles react to the drone's ground position alone.
        let flat = BoidsParams {
            herder_height_scale: 0.0,
            ..params
        };
        let mut w = world(vec![[103.0, 100.0, 8.0]], vec![[100.0, 100.0]], flat);
        step(&mut w, &[[0.0; 3]]);
        assert!(close(w.target_velocities[0][0], -10.0 / 9.0));
    }

    #[test]
    fn update_order_herders_move_first() {
        let params = BoidsParams {
            herder: 600.0,
            ..separation_only()
        };
        // Herder 20 m west of a lone target, closing at 5 m/s: the target feels it at 15 m.
        let mut w = world(vec![[80.0, 100.0, 0.0]], vec![[100.0, 100.0]], params);
        step(&mut w, &[[5.0, 0.0, 0.0]]);
        assert!(close(w.target_velocities[0][0], 600.0 / 225.0));
        assert!(close(w.targets[0][0], 100.0 + 600.0 / 225.0));
    }

    #[test]
    fn targets_update_synchronously() {
        // Alignment reads the previous velocities, cohesion the previous positions: a target
        // moving first must not change what the second one sees.
        let params = BoidsParams {
            separation: 0.0,
            herder: 0.0,
            ..BoidsParams::PAPER
        };
        let mut w = world(vec![[0.0; 3]], vec![[100.0, 100.0], [120.0, 100.0]], params);
        w.target_velocities = vec![[2.0, 0.0], [0.0, 0.0]];
        step(&mut w, &[[0.0; 3]]);
        let v0 = 0.5 * (0.05 * 1.0 + 0.01 * 10.0);
        let v1 = 0.5 * (0.05 * 1.0 - 0.01 * 10.0);
        assert!(close(w.target_velocities[0][0], v0));
        assert!(close(w.target_velocities[1][0], v1));
    }

    fn random_world(rng: &mut ChaCha8Rng, n: usize, m: usize, spread: f64) -> World {
        let targets = (0..n)
            .map(|_| {
                [
                    250.0 + rng.random_range(-spread..spread),
                    250.0 + rng.random_range(-spread..spread),
                ]
            })
            .collect();
        let herders = (0..m)
            .map(|_| {
                [
                    rng.random_range(0.0..500.0),
                    rng.random_range(0.0..500.0),
                    rng.random_range(0.0..10.0),
                ]
            })
            .collect();
        let mut w = world(herders, targets, BoidsParams::PAPER);
        for v in &mut w.target_velocities {
            *v = [rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0)];
        }
        w
    }

    #[test]
    fn grid_step_matches_naive_step() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut scratch = StepScratch::default();
        for &(n, m, spread) in &[
            (1, 1, 10.0),
            (2, 3, 3.0),
            (50, 4, 20.0),
            (300, 10, 30.0),
            (400, 2, 240.0),
        ] {
            // Step by step from the same state: over many steps the chaotic near-collisions would
            // amplify the last-bit differences of a different summation order.
            let mut fast = random_world(&mut rng, n, m, spread);
            for _ in 0..20 {
                let mut slow = fast.clone();
                let actions: Vec<[f64; 3]> = (0..m)
                    .map(|_| {
                        [
                            rng.random_range(-6.0..6.0),
                            rng.random_range(-6.0..6.0),
                            rng.random_range(-6.0..6.0),
                        ]
                    })
                    .collect();
                advance(&mut fast, &actions, &mut scratch).unwrap();
                reference_step(&mut slow, &actions).unwrap();
                for (a, b) in fast.targets.iter().zip(&slow.targets) {
                    assert!(
                        close(a[0], b[0]) && close(a[1], b[1]),
                        "n={n}: {a:?} vs {b:?}"
                    );
                }
                for (a, b) in fast.target_velocities.iter().zip(&slow.target_velocities) {
                    assert!(
                        close(a[0], b[0]) && close(a[1], b[1]),
                        "n={n}: {a:?} vs {b:?}"
                    );
                }
                assert_eq!(fast.herders, slow.herders);
                assert_eq!(fast.step, slow.step);
            }
        }
    }

    #[test]
    fn grid_handles_a_spread_that_overflows_the_cell_budget() {
        // 3 targets spread over 1e6 m: the grid must widen its cells rather than allocate.
        let mut w = world(
            vec![[0.0; 3]],
            vec![[0.0, 0.0], [1e6, 1e6], [1e6 + 1.0, 1e6]],
            BoidsParams::PAPER,
        );
        let mut slow = w.clone();
        advance(&mut w, &[[0.0; 3]], &mut StepScratch::default()).unwrap();
        reference_step(&mut slow, &[[0.0; 3]]).unwrap();
        assert_eq!(w.targets.len(), 3);
        for (a, b) in w.targets.iter().zip(&slow.targets) {
            assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
        }
    }

    #[test]
    fn step_reuses_its_buffers() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut w = random_world(&mut rng, 256, 4, 40.0);
        let mut scratch = StepScratch::with_capacity(256);
        let ptrs = |s: &StepScratch| {
            (
                s.cell_start.as_ptr(),
                s.order.as_ptr(),
                s.sorted_pos.as_ptr(),
                s.new_velocity.as_ptr(),
            )
        };
        let before = ptrs(&scratch);
        for _ in 0..50 {
            advance(&mut w, &[[1.0, 0.0, 0.0]; 4], &mut scratch).unwrap();
        }
        assert_eq!(ptrs(&scratch), before);
    }

    #[test]
    fn bad_actions_are_errors() {
        let mut w = world(vec![[0.0; 3]; 2], vec![[1.0, 1.0]], BoidsParams::PAPER);
        let mut s = StepScratch::default();
        assert_eq!(
            advance(&mut w, &[[0.0; 3]], &mut s),
            Err(WorldError::ActionCount {
                expected: 2,
                got: 1
            })
        );
        assert!(matches!(
            advance(&mut w, &[[0.0; 3], [f64::NAN, 0.0, 0.0]], &mut s),
            Err(WorldError::NonFiniteAction { herder: 1, .. })
        ));
        assert_eq!(w.step, 0, "a refused step changes nothing");
    }

    #[test]
    fn validate_names_the_field() {
        let mut w = world(vec![[0.0; 3]], vec![[1.0, 1.0]], BoidsParams::PAPER);
        w.target_velocities.clear();
        assert!(matches!(
            w.validate(),
            Err(WorldError::Invalid {
                field: "target_velocities",
                ..
            })
        ));
        let mut w = world(vec![[0.0; 3]], vec![[1.0, 1.0]], BoidsParams::PAPER);
        w.goal.radius = -1.0;
        assert!(matches!(
            w.validate(),
            Err(WorldError::Invalid {
                field: "goal.radius",
                ..
            })
        ));
        let mut w = world(vec![[0.0; 3]], vec![[1.0, 1.0]], BoidsParams::PAPER);
        w.params.herder_height_scale = f64::NAN;
        assert!(matches!(
            w.validate(),
            Err(WorldError::Invalid {
                field: "params.herder_height_scale",
                ..
            })
        ));
    }

    #[test]
    fn finite_but_absurd_values_are_refused_and_never_panic_a_step() {
        let field = |w: &World| match w.validate() {
            Err(WorldError::Invalid { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        let mut w = world(
            vec![[0.0; 3]],
            vec![[1.0, 1.0], [2.0, 2.0]],
            BoidsParams::PAPER,
        );
        w.targets[0][0] = -1.7e308;
        assert_eq!(field(&w), "targets");
        // Stepped anyway (a caller that skipped validation): no panic.
        let mut scratch = StepScratch::with_capacity(2);
        let _ = advance(&mut w, &[[0.0; 3]], &mut scratch);
        let mut w = world(vec![[0.0; 3]], vec![[1.0, 1.0]], BoidsParams::PAPER);
        w.params.separation = 1e308;
        assert_eq!(field(&w), "params.separation");
        let mut w = world(vec![[0.0; 3]], vec![[1.0, 1.0]], BoidsParams::PAPER);
        w.herders[0][2] = 2e6;
        assert_eq!(field(&w), "herders");
        let mut w = world(vec![[0.0; 3]], vec![[1.0, 1.0]], BoidsParams::PAPER);
        w.step = u64::MAX;
        assert!(w.validate().is_ok());
        let mut scratch = StepScratch::with_capacity(1);
        let _ = advance(&mut w, &[[0.0; 3]], &mut scratch);
        assert_eq!(
            w.step,
            u64::MAX,
            "the step counter saturates, it does not wrap"
        );
    }

    #[test]
    fn adaptive_herder_count() {
        let got: Vec<usize> = (0..=10).map(|k| adaptive_herders(1 << k)).collect();
        assert_eq!(got, vec![1, 1, 2, 2, 4, 4, 8, 8, 16, 16, 32]);
        assert_eq!(adaptive_herders(0), 1);
        assert_eq!(adaptive_herders(100), 8);
    }
}
