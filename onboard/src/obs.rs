//! The observation encoder: what one drone knows of the world -> a fixed-size feature vector.
//!
//! This is the only copy of the encoder. The trainer, the simulator's learned policy and the
//! drone all call [`encode`], so what is trained is exactly what flies.
//!
//! # Input
//! [`ObsInput`] is the paper's (M + N + 1) x 3 observation in the simulator frame (x east,
//! y north, z up, metres): every herder's 3-D position (the encoding drone's own entry is
//! `herders[own_index]`), every target's ground position, the goal circle, the arena size and the
//! drone's speed limit.
//!
//! # Output
//! [`FEATURES`] numbers that do not depend on N or M, nor on the order of targets or herders:
//! * **Egocentric and rotated.** Vectors are taken relative to the drone and expressed in a
//!   [`LocalFrame`] whose first axis points from the flock centroid to the goal (the driving
//!   direction). The actor's output is read in the same frame, so the learned behaviour does not
//!   depend on where the goal happens to lie.
//! * **Scale-free.** Lengths are divided by the goal radius, so the 45 m paper arena and the
//!   1.5 m indoor goal look alike, then compressed with `ln(1 + d)` (keeping direction) so that a
//!   500 m arena does not swamp nearby detail.
//! * **Counts as fractions.** Per-sector target counts are divided by N.
//!
//! | index | feature |
//! |---|---|
//! | 0-1 | goal centre, relative to the drone |
//! | 2-3 | flock centroid, relative |
//! | 4-5 | target farthest from the goal, relative |
//! | 6 | its distance to the goal edge, `sc(d / R - 1)` |
//! | 7 | flock radius (max distance to centroid), `sc(r / R)` |
//! | 8 | mean distance to centroid, `sc(r / R)` |
//! | 9 | fraction of targets inside the goal |
//! | 10 | centroid distance to goal, `sc(d / R)` |
//! | 11-12 | in the drone's own share (targets nearer to it than to any other herder): the one farthest from the goal, relative |
//! | 13 | fraction of all targets in the drone's share |
//! | 14 | that target's distance to the goal edge, `sc(d / R - 1)` |
//! | 15-16 | the point [`STANDOFF`] x R behind that target on the goal line, relative |
//! | 17-18 | the point behind the whole flock (centroid + (radius + standoff) away from the goal), relative |
//! | 19-20 | nearest target, relative |
//! | 21 | its distance, `sc(d / R)` |
//! | 22 | own altitude, `sc(z / R)` |
//! | 23-24 | nearest other herder, relative (zero when alone) |
//! | 25 | its distance, `sc(d / R)` (zero when alone) |
//! | 26 | 1 when there are other herders, else 0 |
//! | 27-28 | centroid of the other herders, relative (zero when alone) |
//! | 29 | (M - 1) / 31, clamped to [0, 1] |
//! | 30 | ln(N) / ln(1024), clamped to [0, 1] |
//! | 31-32 | unit direction from the flock centroid to the drone (its place around the flock) |
//! | 33-40 | fraction of targets in each of 8 octants around the drone (local frame, counter-clockwise from the first axis) |
//! | 41-42 | nearest arena wall, relative (the closest point on it) |
//! | 43 | drone distance to the nearest wall, `sc(d / R)` |
//! | 44 | smallest target distance to any wall, `sc(d / R)` |
//! | 45 | fraction of targets within one goal radius of the drone |
//!
//! "relative" means `compress((p - own) / R)` in the local frame, with
//! `compress(v) = v * ln(1 + |v|) / |v|`; `sc(x) = sign(x) ln(1 + |x|)`.
//!
//! ```
//! use skyherd_onboard::obs::{encode, ObsInput, FEATURES};
//! let herders = [[100.0_f32, 100.0, 2.0], [140.0, 90.0, 2.0]];
//! let targets = [[120.0_f32, 120.0], [125.0, 118.0], [118.0, 125.0]];
//! let input = ObsInput {
//!     own_index: 0,
//!     herders: &herders,
//!     targets: &targets,
//!     goal: [300.0, 300.0],
//!     goal_radius: 45.0,
//!     area: [500.0, 500.0, 10.0],
//!     max_speed: 5.0,
//! };
//! let mut features = [0.0_f32; FEATURES];
//! let frame = encode(&input, &mut features).unwrap();
//! // The actor answers in the local frame; "full speed along the first axis" is towards the goal.
//! let v = frame.action_to_world([1.0, 0.0, 0.0]);
//! assert!((v[0] - v[1]).abs() < 1e-4 && v[0] > 0.0);
//! ```

use core::fmt;

use libm::{logf, sqrtf};

/// Version of the feature layout; written into every model file, a mismatch is an error.
///
/// v2 replaced v1's feature 45 (speed limit per goal radius per *second*), which differs
/// between the paper arena (1 s steps) and the scaled indoor room (0.1 s steps) although the
/// two worlds are the same map; v2 has no feature that depends on the time step.
///
/// v3 measures the drone's altitude (feature 22) in goal radii instead of as a fraction of the
/// ceiling: a room's 3 m ceiling does not shrink with the rest of the world, so under v2 a
/// policy trained in the 10 m-high paper arena flew at 0.6 m indoors, 15 goal radii higher (and
/// so much weaker, eq 6 follows the 3-D distance) than the 2 m it learned.
pub const ENCODER_VERSION: u16 = 3;

/// Length of the feature vector.
pub const FEATURES: usize = 46;

/// How far behind a target (in goal radii) the "behind point" features sit: 8 m at the paper's
/// 45 m goal, the stand-off of the best simple driving rule we know.
pub const STANDOFF: f32 = 8.0 / 45.0;

/// Smallest goal radius the encoder accepts, in metres; guards the division by R.
pub const MIN_GOAL_RADIUS: f32 = 0.05;

/// One drone's view of the world, simulator frame (x east, y north, z up), metres.
#[derive(Clone, Copy, Debug)]
pub struct ObsInput<'a> {
    /// Index of the encoding drone in `herders`.
    pub own_index: usize,
    /// Every herder's position `[x, y, z]`, the encoding drone included.
    pub herders: &'a [[f32; 3]],
    /// Every target's ground position `[x, y]`.
    pub targets: &'a [[f32; 2]],
    /// Goal circle centre `[x, y]`.
    pub goal: [f32; 2],
    /// Goal circle radius, metres.
    pub goal_radius: f32,
    /// Arena size `[width (x), depth (y), ceiling (z)]`; the arena starts at the origin.
    pub area: [f32; 3],
    /// The drone's speed limit, m/s; scales the actor's normalised output.
    pub max_speed: f32,
}

/// Why an observation could not be encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObsError {
    /// `own_index` does not name a herder.
    OwnIndexOutOfRange {
        /// The index given.
        own_index: usize,
        /// How many herders there are.
        herders: usize,
    },
    /// A position, the goal or the area holds NaN or infinity.
    NonFinite,
    /// Goal radius, arena size or speed limit is not positive.
    BadGeometry,
}

impl fmt::Display for ObsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ObsError::OwnIndexOutOfRange { own_index, herders } => {
                write!(
                    f,
                    "own index {own_index} out of range for {herders} herders"
                )
            }
            ObsError::NonFinite => f.write_str("observation holds NaN or infinity"),
            ObsError::BadGeometry => {
                f.write_str("goal radius, arena size and speed limit must be positive")
            }
        }
    }
}

/// The drone-centred, goal-aligned frame the features and the actor's actions live in.
///
/// The first axis points from the flock centroid to the goal (or from the drone to the goal when
/// the flock sits on the goal), the second is the first turned 90 degrees counter-clockwise, and
/// the third is up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalFrame {
    /// First axis, a unit vector in the simulator's x-y plane.
    pub forward: [f32; 2],
    /// Speed limit that scales normalised actions, m/s.
    pub max_speed: f32,
}

impl LocalFrame {
    /// Second axis (forward turned counter-clockwise).
    pub fn left(&self) -> [f32; 2] {
        [-self.forward[1], self.forward[0]]
    }

    /// A world (simulator frame) x-y vector in local coordinates.
    pub fn to_local(&self, v: [f32; 2]) -> [f32; 2] {
        let l = self.left();
        [
            v[0] * self.forward[0] + v[1] * self.forward[1],
            v[0] * l[0] + v[1] * l[1],
        ]
    }

    /// A local x-y vector in world (simulator frame) coordinates.
    pub fn to_world(&self, v: [f32; 2]) -> [f32; 2] {
        let l = self.left();
        [
            v[0] * self.forward[0] + v[1] * l[0],
            v[0] * self.forward[1] + v[1] * l[1],
        ]
    }

    /// The actor's normalised action (each component in [-1, 1], local frame) as a velocity in
    /// m/s in the simulator frame, its norm at most the speed limit. Non-finite components
    /// count as zero.
    pub fn action_to_world(&self, action: [f32; 3]) -> [f32; 3] {
        let a = action.map(|x| {
            if x.is_finite() {
                x.clamp(-1.0, 1.0)
            } else {
                0.0
            }
        });
        let xy = self.to_world([a[0], a[1]]);
        let mut v = [
            xy[0] * self.max_speed,
            xy[1] * self.max_speed,
            a[2] * self.max_speed,
        ];
        let norm = sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
        if norm > self.max_speed {
            let k = self.max_speed / norm;
            v = v.map(|x| x * k);
        }
        v
    }

    /// The inverse of [`action_to_world`](Self::action_to_world) for velocities within the
    /// limit: a simulator-frame velocity (m/s) as a normalised local action. Used to imitate
    /// rule-based herders.
    pub fn world_to_action(&self, velocity: [f32; 3]) -> [f32; 3] {
        let inv = 1.0 / self.max_speed;
        let xy = self.to_local([velocity[0], velocity[1]]);
        [
            (xy[0] * inv).clamp(-1.0, 1.0),
            (xy[1] * inv).clamp(-1.0, 1.0),
            (velocity[2] * inv).clamp(-1.0, 1.0),
        ]
    }
}

/// `sign(x) ln(1 + |x|)`: keeps small values, tames large ones.
fn soft(x: f32) -> f32 {
    if x >= 0.0 {
        logf(1.0 + x)
    } else {
        -logf(1.0 - x)
    }
}

/// Scales a vector so its length becomes `ln(1 + length)`, keeping its direction.
fn compress(v: [f32; 2]) -> [f32; 2] {
    let d = sqrtf(v[0] * v[0] + v[1] * v[1]);
    if d < 1e-6 {
        return v;
    }
    let k = logf(1.0 + d) / d;
    [v[0] * k, v[1] * k]
}

fn sub(a: [f32; 2], b: [f32; 2]) -> [f32; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

fn dist2(a: [f32; 2], b: [f32; 2]) -> f32 {
    let d = sub(a, b);
    d[0] * d[0] + d[1] * d[1]
}

/// The smaller of two finite numbers. `f32::min` also sorts out NaN, which costs a compare
/// and a blend on every step of a running minimum; validated input has none.
#[inline(always)]
fn smaller(a: f32, b: f32) -> f32 {
    if b < a { b } else { a }
}

/// The larger of two finite numbers (see [`smaller`]).
#[inline(always)]
fn larger(a: f32, b: f32) -> f32 {
    if b > a { b } else { a }
}

fn unit_or(v: [f32; 2], fallback: [f32; 2]) -> [f32; 2] {
    let n = sqrtf(v[0] * v[0] + v[1] * v[1]);
    if n > 1e-6 {
        [v[0] / n, v[1] / n]
    } else {
        fallback
    }
}

/// Octant (0..8) of a local-frame vector, counter-clockwise from the first axis, without atan2.
fn octant(v: [f32; 2]) -> usize {
    let (x, y) = (v[0], v[1]);
    match (y >= 0.0, x >= 0.0, x.abs() >= y.abs()) {
        (true, true, true) => 0,
        (true, true, false) => 1,
        (true, false, false) => 2,
        (true, false, true) => 3,
        (false, false, true) => 4,
        (false, false, false) => 5,
        (false, true, false) => 6,
        (false, true, true) => 7,
    }
}

/// Distance from a point to the nearest wall of the arena and the closest point on that wall.
fn nearest_wall(p: [f32; 2], area: [f32; 3]) -> (f32, [f32; 2]) {
    let candidates = [
        (p[0], [0.0, p[1]]),
        (area[0] - p[0], [area[0], p[1]]),
        (p[1], [p[0], 0.0]),
        (area[1] - p[1], [p[0], area[1]]),
    ];
    let mut best = candidates[0];
    for c in candidates.iter().skip(1) {
        if c.0 < best.0 {
            best = *c;
        }
    }
    (best.0.max(0.0), best.1)
}

fn validate(input: &ObsInput<'_>) -> Result<(), ObsError> {
    if input.own_index >= input.herders.len() {
        return Err(ObsError::OwnIndexOutOfRange {
            own_index: input.own_index,
            herders: input.herders.len(),
        });
    }
    let scalars = [
        input.goal[0],
        input.goal[1],
        input.goal_radius,
        input.area[0],
        input.area[1],
        input.area[2],
        input.max_speed,
    ];
    // Folded without short-circuit, which vectorises: a branch per coordinate cost a tenth of
    // the encoder at N = 1024.
    let all_finite = |values: &[f32]| values.iter().fold(true, |ok, x| ok & x.is_finite());
    let finite = all_finite(&scalars)
        && all_finite(input.herders.as_flattened())
        && all_finite(input.targets.as_flattened());
    if !finite {
        return Err(ObsError::NonFinite);
    }
    if input.goal_radius < MIN_GOAL_RADIUS
        || input.area.iter().any(|&x| x <= 0.0)
        || input.max_speed <= 0.0
    {
        return Err(ObsError::BadGeometry);
    }
    Ok(())
}

/// Encodes one drone's observation into `out` and returns the frame its action is read in.
///
/// O(N * M) time (each target is assigned to its nearest herder), no heap; pure.
pub fn encode(input: &ObsInput<'_>, out: &mut [f32; FEATURES]) -> Result<LocalFrame, ObsError> {
    validate(input)?;
    *out = [0.0; FEATURES];

    let own3 = input.herders[input.own_index];
    let own = [own3[0], own3[1]];
    let goal = input.goal;
    let inv_r = 1.0 / input.goal_radius;
    let n = input.targets.len();
    let m = input.herders.len();

    // Pass 1 over targets: centroid, farthest from goal, nearest to me, goal occupancy, my share.
    let mut sum = [0.0_f32; 2];
    let mut farthest = (f32::NEG_INFINITY, goal);
    let mut nearest = (f32::INFINITY, own);
    let mut inside = 0usize;
    let mut mine = 0usize;
    let mut my_farthest = (f32::NEG_INFINITY, own);
    // The flock's bounding box gives the smallest target-to-wall distance without a per-target
    // wall search.
    let mut lo = [f32::INFINITY; 2];
    let mut hi = [f32::NEG_INFINITY; 2];
    let mut near_me = 0usize;
    let r2 = input.goal_radius * input.goal_radius;
    for &t in input.targets {
        sum[0] += t[0];
        sum[1] += t[1];
        let to_goal2 = dist2(t, goal);
        if to_goal2 > farthest.0 {
            farthest = (to_goal2, t);
        }
        inside += usize::from(to_goal2 <= r2);
        let to_me2 = dist2(t, own);
        near_me += usize::from(to_me2 <= r2);
        if to_me2 < nearest.0 {
            nearest = (to_me2, t);
        }
        // Ties go to the lower herder index so that exactly one herder owns each target.
        let is_mine = input.herders.iter().enumerate().all(|(j, h)| {
            j == input.own_index || {
                let d = dist2(t, [h[0], h[1]]);
                d > to_me2 || (d == to_me2 && j > input.own_index)
            }
        });
        if is_mine {
            mine += 1;
            if to_goal2 > my_farthest.0 {
                my_farthest = (to_goal2, t);
            }
        }
        lo = [smaller(lo[0], t[0]), smaller(lo[1], t[1])];
        hi = [larger(hi[0], t[0]), larger(hi[1], t[1])];
    }
    let centroid = if n > 0 {
        [sum[0] / n as f32, sum[1] / n as f32]
    } else {
        own
    };

    // The frame: from the flock to the goal; from me to the goal when the flock sits on it.
    let forward = unit_or(sub(goal, centroid), unit_or(sub(goal, own), [1.0, 0.0]));
    let frame = LocalFrame {
        forward,
        max_speed: input.max_speed,
    };
    let rel =
        |p: [f32; 2]| compress(frame.to_local([(p[0] - own[0]) * inv_r, (p[1] - own[1]) * inv_r]));
    let put2 = |out: &mut [f32; FEATURES], i: usize, v: [f32; 2]| {
        out[i] = v[0];
        out[i + 1] = v[1];
    };

    // Pass 2 over targets: spread around the centroid and octant occupancy around me.
    let mut max_spread2 = 0.0_f32;
    let mut spread_sum = 0.0_f32;
    let mut octants = [0usize; 8];
    for &t in input.targets {
        let d2 = dist2(t, centroid);
        max_spread2 = larger(max_spread2, d2);
        spread_sum += sqrtf(d2);
        octants[octant(frame.to_local(sub(t, own)))] += 1;
    }
    let flock_radius = sqrtf(max_spread2);
    let standoff = STANDOFF * input.goal_radius;

    put2(out, 0, rel(goal));
    if n > 0 {
        put2(out, 2, rel(centroid));
        put2(out, 4, rel(farthest.1));
        out[6] = soft(sqrtf(farthest.0) * inv_r - 1.0);
        out[7] = soft(flock_radius * inv_r);
        out[8] = soft(spread_sum / n as f32 * inv_r);
        out[9] = inside as f32 / n as f32;
        out[10] = soft(sqrtf(dist2(centroid, goal)) * inv_r);
        if mine > 0 {
            let t = my_farthest.1;
            put2(out, 11, rel(t));
            out[13] = mine as f32 / n as f32;
            out[14] = soft(sqrtf(my_farthest.0) * inv_r - 1.0);
            let away = unit_or(sub(t, goal), [-forward[0], -forward[1]]);
            put2(
                out,
                15,
                rel([t[0] + away[0] * standoff, t[1] + away[1] * standoff]),
            );
        }
        let away = unit_or(sub(centroid, goal), [-forward[0], -forward[1]]);
        let behind = flock_radius + standoff;
        put2(
            out,
            17,
            rel([
                centroid[0] + away[0] * behind,
                centroid[1] + away[1] * behind,
            ]),
        );
        put2(out, 19, rel(nearest.1));
        out[21] = soft(sqrtf(nearest.0) * inv_r);
        for (k, &count) in octants.iter().enumerate() {
            out[33 + k] = count as f32 / n as f32;
        }
        let min_wall = lo[0]
            .min(lo[1])
            .min(input.area[0] - hi[0])
            .min(input.area[1] - hi[1])
            .max(0.0);
        out[44] = soft(min_wall * inv_r);
        out[45] = near_me as f32 / n as f32;
    }
    out[22] = soft(own3[2].max(0.0) * inv_r);

    // Other herders.
    if m > 1 {
        let mut nearest_herder = (f32::INFINITY, own);
        let mut others = [0.0_f32; 2];
        for (j, h) in input.herders.iter().enumerate() {
            if j == input.own_index {
                continue;
            }
            let p = [h[0], h[1]];
            others[0] += p[0];
            others[1] += p[1];
            let d2 = dist2(p, own);
            if d2 < nearest_herder.0 {
                nearest_herder = (d2, p);
            }
        }
        let k = 1.0 / (m - 1) as f32;
        put2(out, 23, rel(nearest_herder.1));
        out[25] = soft(sqrtf(nearest_herder.0) * inv_r);
        out[26] = 1.0;
        put2(out, 27, rel([others[0] * k, others[1] * k]));
    }
    out[29] = ((m as f32 - 1.0) / 31.0).clamp(0.0, 1.0);
    out[30] = if n > 0 {
        (logf(n as f32) / logf(1024.0)).clamp(0.0, 1.0)
    } else {
        0.0
    };
    put2(
        out,
        31,
        frame.to_local(unit_or(sub(own, centroid), [0.0, 0.0])),
    );
    let (wall_distance, wall_point) = nearest_wall(own, input.area);
    put2(out, 41, rel(wall_point));
    out[43] = soft(wall_distance * inv_r);
    Ok(frame)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input<'a>(herders: &'a [[f32; 3]], targets: &'a [[f32; 2]], own: usize) -> ObsInput<'a> {
        ObsInput {
            own_index: own,
            herders,
            targets,
            goal: [400.0, 380.0],
            goal_radius: 45.0,
            area: [500.0, 500.0, 10.0],
            max_speed: 5.0,
        }
    }

    fn encode_ok(i: &ObsInput<'_>) -> ([f32; FEATURES], LocalFrame) {
        let mut out = [0.0; FEATURES];
        let frame = encode(i, &mut out).expect("valid input");
        (out, frame)
    }

    /// Deterministic pseudo-random scatter (xorshift) so the tests need no RNG crate.
    fn scatter(count: usize, seed: u32, centre: [f32; 2], spread: f32) -> [[f32; 2]; 64] {
        let mut s = seed.max(1);
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            (s as f32 / u32::MAX as f32) * 2.0 - 1.0
        };
        let mut pts = [[0.0; 2]; 64];
        for p in pts.iter_mut().take(count) {
            *p = [centre[0] + next() * spread, centre[1] + next() * spread];
        }
        pts
    }

    #[test]
    fn features_are_finite_and_bounded() {
        let herders = [[10.0, 20.0, 2.0], [30.0, 40.0, 0.0], [490.0, 490.0, 10.0]];
        let targets = scatter(64, 7, [150.0, 150.0], 40.0);
        for own in 0..3 {
            let (f, _) = encode_ok(&input(&herders, &targets, own));
            assert!(f.iter().all(|x| x.is_finite() && x.abs() < 10.0), "{f:?}");
        }
    }

    #[test]
    fn target_order_does_not_matter() {
        let herders = [[100.0, 100.0, 2.0], [200.0, 90.0, 3.0]];
        let targets = scatter(40, 11, [150.0, 150.0], 30.0);
        let mut reversed = targets;
        reversed[..40].reverse();
        let (a, _) = encode_ok(&input(&herders, &targets[..40], 0));
        let (b, _) = encode_ok(&input(&herders, &reversed[..40], 0));
        for (x, y) in a.iter().zip(b.iter()) {
            assert!((x - y).abs() < 1e-5, "{a:?}\n{b:?}");
        }
    }

    #[test]
    fn other_herders_order_does_not_matter() {
        let targets = scatter(20, 3, [150.0, 150.0], 30.0);
        let a_herders = [[100.0, 100.0, 2.0], [200.0, 90.0, 3.0], [120.0, 220.0, 1.0]];
        let b_herders = [[120.0, 220.0, 1.0], [200.0, 90.0, 3.0], [100.0, 100.0, 2.0]];
        let (a, _) = encode_ok(&input(&a_herders, &targets[..20], 0));
        let (b, _) = encode_ok(&input(&b_herders, &targets[..20], 2));
        for (x, y) in a.iter().zip(b.iter()) {
            assert!((x - y).abs() < 1e-5);
        }
    }

    #[test]
    fn duplicating_every_target_changes_only_the_count_feature() {
        // N-independence: the same flock with twice the members encodes the same apart from
        // feature 30 (log N).
        let herders = [[100.0, 100.0, 2.0], [200.0, 90.0, 3.0]];
        let base = scatter(32, 5, [150.0, 150.0], 30.0);
        let mut doubled = [[0.0; 2]; 64];
        doubled[..32].copy_from_slice(&base[..32]);
        doubled[32..].copy_from_slice(&base[..32]);
        let (a, _) = encode_ok(&input(&herders, &base[..32], 0));
        let (b, _) = encode_ok(&input(&herders, &doubled, 0));
        for (k, (x, y)) in a.iter().zip(b.iter()).enumerate() {
            if k != 30 {
                assert!((x - y).abs() < 1e-5, "feature {k}: {x} vs {y}");
            }
        }
        assert!(b[30] > a[30]);
    }

    #[test]
    fn rotating_the_world_leaves_the_features_unchanged() {
        // Rotate everything by 90 degrees about the arena centre: an egocentric, goal-aligned
        // encoding sees the same picture (walls aside: the square arena maps onto itself).
        let rot = |p: [f32; 2]| [500.0 - p[1], p[0]];
        // Off the diagonal: at equal distance to two walls the nearest-wall feature may pick
        // either one.
        let herders = [[100.0, 120.0, 2.0], [200.0, 90.0, 3.0]];
        let targets = scatter(30, 9, [150.0, 150.0], 30.0);
        let r_herders = herders.map(|h| {
            let p = rot([h[0], h[1]]);
            [p[0], p[1], h[2]]
        });
        let r_targets = targets.map(rot);
        let mut a_in = input(&herders, &targets[..30], 0);
        a_in.goal = [400.0, 380.0];
        let mut b_in = input(&r_herders, &r_targets[..30], 0);
        b_in.goal = rot([400.0, 380.0]);
        let (a, fa) = encode_ok(&a_in);
        let (b, fb) = encode_ok(&b_in);
        for (k, (x, y)) in a.iter().zip(b.iter()).enumerate() {
            assert!((x - y).abs() < 1e-4, "feature {k}: {x} vs {y}");
        }
        // The same local action means the rotated world velocity.
        let va = fa.action_to_world([0.3, -0.7, 0.1]);
        let vb = fb.action_to_world([0.3, -0.7, 0.1]);
        assert!((vb[0] - -va[1]).abs() < 1e-4 && (vb[1] - va[0]).abs() < 1e-4);
    }

    #[test]
    fn zooming_the_world_leaves_the_features_unchanged() {
        // The indoor room is the paper arena zoomed by 1/50 in length, except for the ceiling
        // (3 m, not 0.2 m): the features, altitude included, must not see the difference.
        let herders = [[100.0, 100.0, 2.0], [200.0, 90.0, 3.0]];
        let targets = scatter(40, 5, [150.0, 150.0], 30.0);
        let s = 1.0 / 50.0;
        let zoomed_herders = herders.map(|h| [h[0] * s, h[1] * s, h[2] * s]);
        let zoomed_targets = targets.map(|t| [t[0] * s, t[1] * s]);
        for own in 0..2 {
            let (paper, _) = encode_ok(&input(&herders, &targets[..40], own));
            let room = ObsInput {
                goal: [400.0 * s, 380.0 * s],
                goal_radius: 45.0 * s,
                area: [10.0, 10.0, 3.0],
                max_speed: 1.0,
                ..input(&zoomed_herders, &zoomed_targets[..40], own)
            };
            let (zoomed, _) = encode_ok(&room);
            for (k, (a, b)) in paper.iter().zip(&zoomed).enumerate() {
                assert!((a - b).abs() < 1e-4, "feature {k}: paper {a}, room {b}");
            }
        }
    }

    #[test]
    fn forward_axis_points_from_flock_to_goal() {
        let herders = [[0.0, 0.0, 2.0]];
        let targets = [[100.0, 100.0]];
        let mut i = input(&herders, &targets, 0);
        i.goal = [100.0, 300.0];
        let (f, frame) = encode_ok(&i);
        assert!((frame.forward[0]).abs() < 1e-6 && (frame.forward[1] - 1.0).abs() < 1e-6);
        // The goal is ahead of the flock: its local x exceeds the centroid's.
        assert!(f[0] > f[2]);
    }

    #[test]
    fn actions_round_trip_and_respect_the_speed_limit() {
        let frame = LocalFrame {
            forward: [0.6, 0.8],
            max_speed: 5.0,
        };
        let v = [1.0, -2.0, 0.5];
        let back = frame.action_to_world(frame.world_to_action(v));
        for k in 0..3 {
            assert!((back[k] - v[k]).abs() < 1e-5);
        }
        let fast = frame.action_to_world([1.0, 1.0, 1.0]);
        let speed = sqrtf(fast.iter().map(|x| x * x).sum());
        assert!((speed - 5.0).abs() < 1e-4);
        assert_eq!(frame.action_to_world([f32::NAN, 0.0, 0.0]), [0.0, 0.0, 0.0]);
    }

    #[test]
    fn each_target_belongs_to_exactly_one_herder() {
        let herders = [
            [100.0, 100.0, 2.0],
            [100.0, 100.0, 2.0],
            [200.0, 200.0, 2.0],
        ];
        let targets = scatter(50, 13, [150.0, 150.0], 60.0);
        let total: f32 = (0..3)
            .map(|own| encode_ok(&input(&herders, &targets[..50], own)).0[13])
            .sum();
        assert!((total - 1.0).abs() < 1e-5, "shares add up to {total}");
    }

    #[test]
    fn lone_herder_and_empty_flock_are_fine() {
        let herders = [[10.0, 10.0, 1.0]];
        let (f, _) = encode_ok(&input(&herders, &[], 0));
        assert!(f.iter().all(|x| x.is_finite()));
        assert_eq!(f[26], 0.0);
        assert_eq!(f[30], 0.0);
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let herders = [[10.0, 10.0, 1.0]];
        let targets = [[f32::NAN, 1.0]];
        let mut out = [0.0; FEATURES];
        assert_eq!(
            encode(&input(&herders, &targets, 0), &mut out),
            Err(ObsError::NonFinite)
        );
        assert_eq!(
            encode(&input(&herders, &[], 3), &mut out),
            Err(ObsError::OwnIndexOutOfRange {
                own_index: 3,
                herders: 1
            })
        );
        let mut zero_goal = input(&herders, &[], 0);
        zero_goal.goal_radius = 0.0;
        assert_eq!(encode(&zero_goal, &mut out), Err(ObsError::BadGeometry));
    }

    #[test]
    fn octants_cover_the_plane() {
        let mut seen = [false; 8];
        for k in 0..16 {
            let a = k as f32 * core::f32::consts::PI / 8.0 + 0.1;
            seen[octant([libm::cosf(a), libm::sinf(a)])] = true;
        }
        assert!(seen.iter().all(|&s| s));
        assert_eq!(octant([1.0, 0.1]), 0);
        assert_eq!(octant([0.1, 1.0]), 1);
        assert_eq!(octant([-1.0, -0.1]), 4);
    }
}
