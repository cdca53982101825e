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
//! | index | name in [`feature`] | feature |
//! |---|---|---|
//! | 0-1 | [`GOAL`](feature::GOAL) | goal centre, relative to the drone |
//! | 2-3 | [`CENTROID`](feature::CENTROID) | flock centroid, relative |
//! | 4-5 | [`FARTHEST_TARGET`](feature::FARTHEST_TARGET) | target farthest from the goal, relative |
//! | 6 | [`FARTHEST_TARGET_TO_EDGE`](feature::FARTHEST_TARGET_TO_EDGE) | its distance to the goal edge, `sc(d / R - 1)` |
//! | 7 | [`FLOCK_RADIUS`](feature::FLOCK_RADIUS) | flock radius (max distance to centroid), `sc(r / R)` |
//! | 8 | [`MEAN_SPREAD`](feature::MEAN_SPREAD) | mean distance to centroid, `sc(r / R)` |
//! | 9 | [`IN_GOAL`](feature::IN_GOAL) | fraction of targets inside the goal |
//! | 10 | [`CENTROID_TO_GOAL`](feature::CENTROID_TO_GOAL) | centroid distance to goal, `sc(d / R)` |
//! | 11-12 | [`SHARE_FARTHEST`](feature::SHARE_FARTHEST) | in the drone's own share (targets nearer to it than to any other herder): the one farthest from the goal, relative |
//! | 13 | [`SHARE`](feature::SHARE) | fraction of all targets in the drone's share |
//! | 14 | [`SHARE_FARTHEST_TO_EDGE`](feature::SHARE_FARTHEST_TO_EDGE) | that target's distance to the goal edge, `sc(d / R - 1)` |
//! | 15-16 | [`SHARE_BEHIND`](feature::SHARE_BEHIND) | the point [`STANDOFF`] x R behind that target on the goal line, relative |
//! | 17-18 | [`FLOCK_BEHIND`](feature::FLOCK_BEHIND) | the point behind the whole flock (centroid + (radius + standoff) away from the goal), relative |
//! | 19-20 | [`NEAREST_TARGET`](feature::NEAREST_TARGET) | nearest target, relative |
//! | 21 | [`NEAREST_TARGET_DISTANCE`](feature::NEAREST_TARGET_DISTANCE) | its distance, `sc(d / R)` |
//! | 22 | [`ALTITUDE`](feature::ALTITUDE) | own altitude, `sc(z / R)` |
//! | 23-24 | [`NEAREST_HERDER`](feature::NEAREST_HERDER) | nearest other herder, relative (zero when alone) |
//! | 25 | [`NEAREST_HERDER_DISTANCE`](feature::NEAREST_HERDER_DISTANCE) | its distance, `sc(d / R)` (zero when alone) |
//! | 26 | [`NOT_ALONE`](feature::NOT_ALONE) | 1 when there are other herders, else 0 |
//! | 27-28 | [`OTHER_HERDERS`](feature::OTHER_HERDERS) | centroid of the other herders, relative (zero when alone) |
//! | 29 | [`HERDER_COUNT`](feature::HERDER_COUNT) | (M - 1) / 31, clamped to [0, 1] |
//! | 30 | [`TARGET_COUNT`](feature::TARGET_COUNT) | ln(N) / ln(1024), clamped to [0, 1] |
//! | 31-32 | [`FROM_CENTROID`](feature::FROM_CENTROID) | unit direction from the flock centroid to the drone (its place around the flock) |
//! | 33-40 | [`OCTANTS`](feature::OCTANTS) | fraction of targets in each of 8 octants around the drone (local frame, counter-clockwise from the first axis) |
//! | 41-42 | [`NEAREST_WALL`](feature::NEAREST_WALL) | nearest arena wall, relative (the closest point on it) |
//! | 43 | [`WALL_DISTANCE`](feature::WALL_DISTANCE) | drone distance to the nearest wall, `sc(d / R)` |
//! | 44 | [`FLOCK_WALL_DISTANCE`](feature::FLOCK_WALL_DISTANCE) | smallest target distance to any wall, `sc(d / R)` |
//! | 45 | [`NEARBY_TARGETS`](feature::NEARBY_TARGETS) | fraction of targets within one goal radius of the drone |
//! | 46-47 | [`RING_SLOT`](feature::RING_SLOT) | (v4) the drone's slot on the enclosing ring, relative (see below) |
//! | 48-49 | [`RING_WAY`](feature::RING_WAY) | (v4) where to head now for that slot without crossing the flock, relative |
//! | 50 | [`RING_BEARING`](feature::RING_BEARING) | (v4) the slot's bearing from straight behind the flock, counter-clockwise, in half turns |
//! | 51-52 | [`ASSIGNED`](feature::ASSIGNED) | (v5) the drone's own target in the team's assignment (see below), relative |
//! | 53 | [`ASSIGNED_TO_EDGE`](feature::ASSIGNED_TO_EDGE) | (v5) its distance to the goal edge, `sc(d / R - 1)` |
//! | 54-55 | [`ASSIGNED_BEHIND`](feature::ASSIGNED_BEHIND) | (v5) the point [`STANDOFF`] x R behind it on its goal line, relative |
//!
//! The enclosing ring (features 46-50) is the geometry of the simulator's Enclose rule, which
//! herds flocks of 256: every drone stands on an arc behind the flock, at the flock radius plus
//! [`STANDOFF`], in the order of the drones' bearing round the centroid, evenly spaced; the arc
//! opens from [`RING_ARC`] to a full ring as the centroid comes within [`RING_WRAP`] goal radii
//! of the goal, and the ring's centre moves up to [`RING_SHIFT`] goal radii goalwards. The way
//! there goes round the flock disc (radius plus half the stand-off); both points are kept
//! [`RING_WALL_MARGIN`] inside the walls. A drone needs its rank
//! among all herders for its slot, which no v3 feature gives.
//!
//! The assignment (features 51-55) gives every drone a target of its own, the same one in
//! every drone's view: the targets outside the goal are ranked farthest from the goal first,
//! and rank by rank the nearest herder not yet given one takes it; with more herders than such
//! targets the ranks wrap round, so the spare herders double up from the farthest
//! ([`assignment`]). The v1 share (features 11-16) is each drone's nearest targets, which
//! leaves some drones none and others several and changes owner as the drones move. At most
//! [`ASSIGNED_RANKS`] ranks are handed out; a drone without one (more herders than that, or
//! every target in the goal) reads zeros.
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
use core::ops::Range;

use core::f32::consts::{PI, TAU};

use libm::{atan2f, cosf, logf, sinf, sqrtf};

/// Version of the feature layout; written into every model file, a mismatch is an error.
///
/// v2 replaced v1's feature 45 (speed limit per goal radius per *second*), which differs
/// between the paper arena (1 s steps) and the scaled indoor room (0.1 s steps) although the
/// two worlds are the same map; v2 has no feature that depends on the time step.
///
/// v3 measures the drone's altitude (feature 22, [`feature::ALTITUDE`]) in goal radii instead of as
/// a fraction of the ceiling: a room's 3 m ceiling does not shrink with the rest of the world, so
/// under v2 a policy trained in the 10 m-high paper arena flew at 0.6 m indoors, 15 goal radii
/// higher (and so much weaker, eq 6 follows the 3-D distance) than the 2 m it learned.
///
/// v4 appends five features (46-50: the drone's slot on the enclosing ring and the way to it
/// round the flock) and leaves the first 46 exactly as v3 computes them, so a v3 model still
/// flies: it reads the first [`V3_FEATURES`] (see [`feature_count`]).
///
/// v5 appends five more (51-55: the drone's own target in the team's assignment, [`assignment`])
/// and leaves the first 51 exactly as v4 computes them, so v3 and v4 models still fly.
pub const ENCODER_VERSION: u16 = 5;

/// Length of the feature vector [`encode`] writes (encoder v5).
pub const FEATURES: usize = 56;

/// Length of encoder v4's feature vector, a prefix of v5's.
pub const V4_FEATURES: usize = 51;

/// Length of encoder v3's feature vector, a prefix of v4's.
pub const V3_FEATURES: usize = 46;

/// Where each feature sits in [`encode`]'s output: the table in the [module docs](self), named
/// once (a range for a vector or a group, an index for a single number). The version in each
/// line is the encoder version that gave the feature its present meaning; "relative" and `sc`
/// are as in the module docs.
pub mod feature {
    use core::ops::Range;

    /// (v1) Goal centre, relative to the drone.
    pub const GOAL: Range<usize> = 0..2;
    /// (v1) Flock centroid, relative.
    pub const CENTROID: Range<usize> = 2..4;
    /// (v1) The target farthest from the goal, relative.
    pub const FARTHEST_TARGET: Range<usize> = 4..6;
    /// (v1) That target's distance to the goal edge, `sc(d / R - 1)`.
    pub const FARTHEST_TARGET_TO_EDGE: usize = 6;
    /// (v1) Flock radius (largest distance to the centroid), `sc(r / R)`.
    pub const FLOCK_RADIUS: usize = 7;
    /// (v1) Mean distance of the targets to the centroid, `sc(r / R)`.
    pub const MEAN_SPREAD: usize = 8;
    /// (v1) Fraction of the targets inside the goal.
    pub const IN_GOAL: usize = 9;
    /// (v1) Centroid distance to the goal centre, `sc(d / R)`.
    pub const CENTROID_TO_GOAL: usize = 10;
    /// (v1) In the drone's own share (targets nearer to it than to any other herder), the one
    /// farthest from the goal, relative.
    pub const SHARE_FARTHEST: Range<usize> = 11..13;
    /// (v1) Fraction of all targets in the drone's share.
    pub const SHARE: usize = 13;
    /// (v1) Distance of [`SHARE_FARTHEST`] to the goal edge, `sc(d / R - 1)`.
    pub const SHARE_FARTHEST_TO_EDGE: usize = 14;
    /// (v1) The point [`STANDOFF`](super::STANDOFF) x R behind [`SHARE_FARTHEST`] on its goal
    /// line, relative.
    pub const SHARE_BEHIND: Range<usize> = 15..17;
    /// (v1) The point behind the whole flock (centroid + (radius + stand-off) away from the
    /// goal), relative.
    pub const FLOCK_BEHIND: Range<usize> = 17..19;
    /// (v1) The nearest target, relative.
    pub const NEAREST_TARGET: Range<usize> = 19..21;
    /// (v1) Its distance, `sc(d / R)`.
    pub const NEAREST_TARGET_DISTANCE: usize = 21;
    /// (v3) The drone's own altitude, `sc(z / R)` (v1 and v2: a fraction of the ceiling).
    pub const ALTITUDE: usize = 22;
    /// (v1) The nearest other herder, relative (zero when alone).
    pub const NEAREST_HERDER: Range<usize> = 23..25;
    /// (v1) Its distance, `sc(d / R)` (zero when alone).
    pub const NEAREST_HERDER_DISTANCE: usize = 25;
    /// (v1) 1 when there are other herders, else 0.
    pub const NOT_ALONE: usize = 26;
    /// (v1) Centroid of the other herders, relative (zero when alone).
    pub const OTHER_HERDERS: Range<usize> = 27..29;
    /// (v1) Herder count M as (M - 1) / 31, clamped to [0, 1].
    pub const HERDER_COUNT: usize = 29;
    /// (v1) Target count N as ln(N) / ln(1024), clamped to [0, 1] (0 without targets).
    pub const TARGET_COUNT: usize = 30;
    /// (v1) Unit direction from the flock centroid to the drone (its place around the flock).
    pub const FROM_CENTROID: Range<usize> = 31..33;
    /// (v1) Fraction of the targets in each of 8 octants around the drone (local frame,
    /// counter-clockwise from the first axis).
    pub const OCTANTS: Range<usize> = 33..41;
    /// (v1) The nearest arena wall (the closest point on it), relative.
    pub const NEAREST_WALL: Range<usize> = 41..43;
    /// (v1) The drone's distance to the nearest wall, `sc(d / R)`.
    pub const WALL_DISTANCE: usize = 43;
    /// (v1) The smallest distance of any target to any wall, `sc(d / R)`.
    pub const FLOCK_WALL_DISTANCE: usize = 44;
    /// (v2) Fraction of the targets within one goal radius of the drone.
    pub const NEARBY_TARGETS: usize = 45;
    /// (v4) The drone's slot on the enclosing ring, relative.
    pub const RING_SLOT: Range<usize> = 46..48;
    /// (v4) Where to head now for [`RING_SLOT`] without crossing the flock, relative.
    pub const RING_WAY: Range<usize> = 48..50;
    /// (v4) The slot's bearing from straight behind the flock, counter-clockwise, in half
    /// turns.
    pub const RING_BEARING: usize = 50;
    /// (v5) The drone's own target in the team's assignment ([`assignment`](super::assignment)),
    /// relative (zero without one).
    pub const ASSIGNED: Range<usize> = 51..53;
    /// (v5) Its distance to the goal edge, `sc(d / R - 1)`.
    pub const ASSIGNED_TO_EDGE: usize = 53;
    /// (v5) The point [`STANDOFF`](super::STANDOFF) x R behind [`ASSIGNED`] on its goal line,
    /// relative.
    pub const ASSIGNED_BEHIND: Range<usize> = 54..56;

    /// Every feature in index order, single ones as one-element ranges.
    const LAYOUT: [Range<usize>; 34] = [
        GOAL,
        CENTROID,
        FARTHEST_TARGET,
        one(FARTHEST_TARGET_TO_EDGE),
        one(FLOCK_RADIUS),
        one(MEAN_SPREAD),
        one(IN_GOAL),
        one(CENTROID_TO_GOAL),
        SHARE_FARTHEST,
        one(SHARE),
        one(SHARE_FARTHEST_TO_EDGE),
        SHARE_BEHIND,
        FLOCK_BEHIND,
        NEAREST_TARGET,
        one(NEAREST_TARGET_DISTANCE),
        one(ALTITUDE),
        NEAREST_HERDER,
        one(NEAREST_HERDER_DISTANCE),
        one(NOT_ALONE),
        OTHER_HERDERS,
        one(HERDER_COUNT),
        one(TARGET_COUNT),
        FROM_CENTROID,
        OCTANTS,
        NEAREST_WALL,
        one(WALL_DISTANCE),
        one(FLOCK_WALL_DISTANCE),
        one(NEARBY_TARGETS),
        RING_SLOT,
        RING_WAY,
        one(RING_BEARING),
        ASSIGNED,
        one(ASSIGNED_TO_EDGE),
        ASSIGNED_BEHIND,
    ];

    /// The vectors (two numbers each).
    const VECTORS: [Range<usize>; 15] = [
        GOAL,
        CENTROID,
        FARTHEST_TARGET,
        SHARE_FARTHEST,
        SHARE_BEHIND,
        FLOCK_BEHIND,
        NEAREST_TARGET,
        NEAREST_HERDER,
        OTHER_HERDERS,
        FROM_CENTROID,
        NEAREST_WALL,
        RING_SLOT,
        RING_WAY,
        ASSIGNED,
        ASSIGNED_BEHIND,
    ];

    const fn one(i: usize) -> Range<usize> {
        i..i + 1
    }

    /// Whether `layout` covers `0..end` in order, each range non-empty and starting where the
    /// one before it ends (no gap, no overlap).
    const fn tiles(layout: &[Range<usize>], end: usize) -> bool {
        let mut next = 0;
        let mut k = 0;
        while k < layout.len() {
            if layout[k].start != next || layout[k].end <= layout[k].start {
                return false;
            }
            next = layout[k].end;
            k += 1;
        }
        next == end
    }

    const _: () = {
        assert!(
            tiles(&LAYOUT, super::FEATURES),
            "the features must tile 0..FEATURES"
        );
        assert!(
            RING_SLOT.start == super::V3_FEATURES,
            "v4 appends to v3: its first feature sits at V3_FEATURES"
        );
        assert!(
            ASSIGNED.start == super::V4_FEATURES,
            "v5 appends to v4: its first feature sits at V4_FEATURES"
        );
        assert!(OCTANTS.end - OCTANTS.start == 8, "one feature per octant");
        let mut k = 0;
        while k < VECTORS.len() {
            assert!(
                VECTORS[k].end - VECTORS[k].start == 2,
                "a vector is two numbers"
            );
            k += 1;
        }
    };

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn the_layout_check_sees_gaps_and_overlaps() {
            assert!(tiles(&LAYOUT, super::super::FEATURES));
            assert!(tiles(&[0..2, 2..3], 3));
            assert!(!tiles(&[0..2, 3..4], 4), "gap");
            assert!(!tiles(&[0..2, 1..3], 3), "overlap");
            assert!(!tiles(&[0..2, 2..2, 2..3], 3), "empty");
            assert!(!tiles(&[0..2, 2..3], 4), "short");
        }
    }
}

/// How many features a model made for encoder `version` reads, or `None` for a version this
/// encoder cannot serve. Every supported version's features are a prefix of [`encode`]'s.
pub const fn feature_count(version: u16) -> Option<usize> {
    match version {
        3 => Some(V3_FEATURES),
        4 => Some(V4_FEATURES),
        5 => Some(FEATURES),
        _ => None,
    }
}

/// The encoder version whose feature vector has `features` entries, if any.
pub const fn version_for(features: usize) -> Option<u16> {
    match features {
        V3_FEATURES => Some(3),
        V4_FEATURES => Some(4),
        FEATURES => Some(5),
        _ => None,
    }
}

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
    /// [`encode_version`] was asked for an encoder version this build cannot serve (see
    /// [`feature_count`]).
    UnknownVersion(u16),
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
            ObsError::UnknownVersion(v) => write!(
                f,
                "encoder version {v} is not one this build serves (3 to {ENCODER_VERSION})"
            ),
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
///
/// The passes, in order: validate the input; survey the targets (the first pass over them,
/// which gives the centroid and so the frame); measure their spread (the second pass, in the
/// frame); then write each group of [`feature`]s: the flock, the drone's share, the drone
/// itself, the other herders, the walls, the v4 ring slot and the v5 assignment.
pub fn encode(input: &ObsInput<'_>, out: &mut [f32; FEATURES]) -> Result<LocalFrame, ObsError> {
    encode_version(input, ENCODER_VERSION, out)
}

/// As [`encode`], for a model made for encoder `version`: writes only the features that
/// version reads (the first [`feature_count`]`(version)`, bit for bit [`encode`]'s) and zeros
/// the rest, skipping the passes of later versions. A v4 model's drone does not pay for the v5
/// assignment, nor a v3 model's for the v4 ring. Fails with [`ObsError::UnknownVersion`] for a
/// version this build cannot serve.
///
/// ```
/// use skyherd_onboard::obs::{encode, encode_version, feature_count, ObsInput, FEATURES};
/// let herders = [[100.0_f32, 100.0, 2.0], [140.0, 90.0, 2.0]];
/// let targets = [[120.0_f32, 120.0], [125.0, 118.0], [118.0, 125.0]];
/// let input = ObsInput {
///     own_index: 0,
///     herders: &herders,
///     targets: &targets,
///     goal: [300.0, 300.0],
///     goal_radius: 45.0,
///     area: [500.0, 500.0, 10.0],
///     max_speed: 5.0,
/// };
/// let (mut all, mut v4) = ([0.0_f32; FEATURES], [0.0_f32; FEATURES]);
/// encode(&input, &mut all).unwrap();
/// encode_version(&input, 4, &mut v4).unwrap();
/// let width = feature_count(4).unwrap();
/// assert_eq!(v4[..width], all[..width]);
/// assert!(v4[width..].iter().all(|&x| x == 0.0));
/// assert!(encode_version(&input, 2, &mut v4).is_err());
/// ```
pub fn encode_version(
    input: &ObsInput<'_>,
    version: u16,
    out: &mut [f32; FEATURES],
) -> Result<LocalFrame, ObsError> {
    let width = feature_count(version).ok_or(ObsError::UnknownVersion(version))?;
    validate(input)?;
    *out = [0.0; FEATURES];

    let own3 = input.herders[input.own_index];
    let own = [own3[0], own3[1]];
    let survey = survey_targets(input, own);
    let view = View {
        input,
        own,
        inv_r: 1.0 / input.goal_radius,
        frame: local_frame(input, own, survey.centroid),
    };
    let spread = spread_targets(&view, survey.centroid);

    flock_features(&view, &survey, &spread, out);
    share_features(&view, &survey, out);
    own_features(&view, survey.centroid, out);
    herder_features(&view, out);
    wall_features(&view, &survey, out);
    // The later versions' groups, each only for a model that reads it.
    if width > V3_FEATURES {
        ring_features(&view, survey.centroid, spread.flock_radius, out);
    }
    if width > V4_FEATURES {
        assigned_features(&view, out);
    }
    Ok(view.frame)
}

/// What every feature pass of [`encode`] reads: the input, the drone's ground position, the
/// inverse goal radius and the local frame.
struct View<'i, 'a> {
    input: &'i ObsInput<'a>,
    own: [f32; 2],
    inv_r: f32,
    frame: LocalFrame,
}

impl View<'_, '_> {
    /// A point as a "relative" feature: `compress((p - own) / R)` in the local frame.
    fn rel(&self, p: [f32; 2]) -> [f32; 2] {
        let own = self.own;
        let inv_r = self.inv_r;
        compress(
            self.frame
                .to_local([(p[0] - own[0]) * inv_r, (p[1] - own[1]) * inv_r]),
        )
    }
}

/// Writes the two numbers of a vector feature.
fn put2(out: &mut [f32; FEATURES], at: Range<usize>, v: [f32; 2]) {
    out[at].copy_from_slice(&v);
}

/// The first pass over the targets, in the simulator frame (the local frame follows from its
/// centroid).
struct Survey {
    /// Flock centroid; the drone's position when there are no targets.
    centroid: [f32; 2],
    /// Squared goal distance and position of the target farthest from the goal.
    farthest: (f32, [f32; 2]),
    /// Squared distance and position of the target nearest to the drone.
    nearest: (f32, [f32; 2]),
    /// Targets inside the goal.
    inside: usize,
    /// Targets in the drone's share.
    mine: usize,
    /// As `farthest`, among the drone's share.
    my_farthest: (f32, [f32; 2]),
    /// The flock's bounding box (lower and upper corner); it gives the smallest
    /// target-to-wall distance without a per-target wall search.
    lo: [f32; 2],
    hi: [f32; 2],
    /// Targets within one goal radius of the drone.
    near_me: usize,
}

/// Pass 1 over targets: centroid, farthest from goal, nearest to me, goal occupancy, my share.
fn survey_targets(input: &ObsInput<'_>, own: [f32; 2]) -> Survey {
    let goal = input.goal;
    let n = input.targets.len();
    let mut sum = [0.0_f32; 2];
    let mut farthest = (f32::NEG_INFINITY, goal);
    let mut nearest = (f32::INFINITY, own);
    let mut inside = 0usize;
    let mut mine = 0usize;
    let mut my_farthest = (f32::NEG_INFINITY, own);
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
    Survey {
        centroid,
        farthest,
        nearest,
        inside,
        mine,
        my_farthest,
        lo,
        hi,
        near_me,
    }
}

/// The frame: from the flock to the goal; from me to the goal when the flock sits on it.
fn local_frame(input: &ObsInput<'_>, own: [f32; 2], centroid: [f32; 2]) -> LocalFrame {
    let goal = input.goal;
    LocalFrame {
        forward: unit_or(sub(goal, centroid), unit_or(sub(goal, own), [1.0, 0.0])),
        max_speed: input.max_speed,
    }
}

/// The second pass over the targets, which needs the centroid and the frame.
struct Spread {
    /// Largest target distance to the centroid, metres.
    flock_radius: f32,
    /// Sum of the target distances to the centroid, metres.
    spread_sum: f32,
    /// Targets per octant around the drone, local frame.
    octants: [usize; 8],
}

/// Pass 2 over targets: spread around the centroid and octant occupancy around me.
fn spread_targets(view: &View<'_, '_>, centroid: [f32; 2]) -> Spread {
    let mut max_spread2 = 0.0_f32;
    let mut spread_sum = 0.0_f32;
    let mut octants = [0usize; 8];
    for &t in view.input.targets {
        let d2 = dist2(t, centroid);
        max_spread2 = larger(max_spread2, d2);
        spread_sum += sqrtf(d2);
        octants[octant(view.frame.to_local(sub(t, view.own)))] += 1;
    }
    Spread {
        flock_radius: sqrtf(max_spread2),
        spread_sum,
        octants,
    }
}

/// The goal and the whole flock: [`feature::GOAL`] to [`feature::CENTROID_TO_GOAL`],
/// [`feature::FLOCK_BEHIND`] to [`feature::NEAREST_TARGET_DISTANCE`],
/// [`feature::TARGET_COUNT`], [`feature::OCTANTS`] and [`feature::NEARBY_TARGETS`]; all but
/// the goal stay zero without targets.
fn flock_features(
    view: &View<'_, '_>,
    survey: &Survey,
    spread: &Spread,
    out: &mut [f32; FEATURES],
) {
    let goal = view.input.goal;
    let inv_r = view.inv_r;
    let n = view.input.targets.len();
    put2(out, feature::GOAL, view.rel(goal));
    if n > 0 {
        let centroid = survey.centroid;
        put2(out, feature::CENTROID, view.rel(centroid));
        put2(out, feature::FARTHEST_TARGET, view.rel(survey.farthest.1));
        out[feature::FARTHEST_TARGET_TO_EDGE] = soft(sqrtf(survey.farthest.0) * inv_r - 1.0);
        out[feature::FLOCK_RADIUS] = soft(spread.flock_radius * inv_r);
        out[feature::MEAN_SPREAD] = soft(spread.spread_sum / n as f32 * inv_r);
        out[feature::IN_GOAL] = survey.inside as f32 / n as f32;
        out[feature::CENTROID_TO_GOAL] = soft(sqrtf(dist2(centroid, goal)) * inv_r);
        let forward = view.frame.forward;
        let away = unit_or(sub(centroid, goal), [-forward[0], -forward[1]]);
        let behind = spread.flock_radius + STANDOFF * view.input.goal_radius;
        put2(
            out,
            feature::FLOCK_BEHIND,
            view.rel([
                centroid[0] + away[0] * behind,
                centroid[1] + away[1] * behind,
            ]),
        );
        put2(out, feature::NEAREST_TARGET, view.rel(survey.nearest.1));
        out[feature::NEAREST_TARGET_DISTANCE] = soft(sqrtf(survey.nearest.0) * inv_r);
        for (o, &count) in out[feature::OCTANTS].iter_mut().zip(&spread.octants) {
            *o = count as f32 / n as f32;
        }
        out[feature::NEARBY_TARGETS] = survey.near_me as f32 / n as f32;
        out[feature::TARGET_COUNT] = (logf(n as f32) / logf(1024.0)).clamp(0.0, 1.0);
    }
}

/// The drone's share of the flock: [`feature::SHARE_FARTHEST`] to [`feature::SHARE_BEHIND`],
/// zero when the share is empty.
fn share_features(view: &View<'_, '_>, survey: &Survey, out: &mut [f32; FEATURES]) {
    if survey.mine == 0 {
        return;
    }
    let n = view.input.targets.len();
    out[feature::SHARE] = survey.mine as f32 / n as f32;
    let (d2, t) = survey.my_farthest;
    target_features(
        view,
        t,
        d2,
        [feature::SHARE_FARTHEST, feature::SHARE_BEHIND],
        feature::SHARE_FARTHEST_TO_EDGE,
        out,
    );
}

/// One target a drone is to push in (its share's farthest, its assigned one): the target,
/// relative, at `points[0]`; its distance to the goal edge, `sc(d / R - 1)` from its squared
/// goal distance `d2`, at `to_edge`; the point [`STANDOFF`] x R behind it on its goal line,
/// relative, at `points[1]`.
fn target_features(
    view: &View<'_, '_>,
    t: [f32; 2],
    d2: f32,
    points: [Range<usize>; 2],
    to_edge: usize,
    out: &mut [f32; FEATURES],
) {
    let [at, behind] = points;
    put2(out, at, view.rel(t));
    out[to_edge] = soft(sqrtf(d2) * view.inv_r - 1.0);
    let forward = view.frame.forward;
    let away = unit_or(sub(t, view.input.goal), [-forward[0], -forward[1]]);
    let standoff = STANDOFF * view.input.goal_radius;
    put2(
        out,
        behind,
        view.rel([t[0] + away[0] * standoff, t[1] + away[1] * standoff]),
    );
}

/// The drone itself: [`feature::ALTITUDE`] and [`feature::FROM_CENTROID`].
fn own_features(view: &View<'_, '_>, centroid: [f32; 2], out: &mut [f32; FEATURES]) {
    let z = view.input.herders[view.input.own_index][2];
    out[feature::ALTITUDE] = soft(z.max(0.0) * view.inv_r);
    put2(
        out,
        feature::FROM_CENTROID,
        view.frame
            .to_local(unit_or(sub(view.own, centroid), [0.0, 0.0])),
    );
}

/// The pass over the other herders: [`feature::NEAREST_HERDER`] to
/// [`feature::OTHER_HERDERS`] (zero when alone) and [`feature::HERDER_COUNT`].
fn herder_features(view: &View<'_, '_>, out: &mut [f32; FEATURES]) {
    let input = view.input;
    let m = input.herders.len();
    if m > 1 {
        let mut nearest_herder = (f32::INFINITY, view.own);
        let mut others = [0.0_f32; 2];
        for (j, h) in input.herders.iter().enumerate() {
            if j == input.own_index {
                continue;
            }
            let p = [h[0], h[1]];
            others[0] += p[0];
            others[1] += p[1];
            let d2 = dist2(p, view.own);
            if d2 < nearest_herder.0 {
                nearest_herder = (d2, p);
            }
        }
        let k = 1.0 / (m - 1) as f32;
        put2(out, feature::NEAREST_HERDER, view.rel(nearest_herder.1));
        out[feature::NEAREST_HERDER_DISTANCE] = soft(sqrtf(nearest_herder.0) * view.inv_r);
        out[feature::NOT_ALONE] = 1.0;
        put2(
            out,
            feature::OTHER_HERDERS,
            view.rel([others[0] * k, others[1] * k]),
        );
    }
    out[feature::HERDER_COUNT] = ((m as f32 - 1.0) / 31.0).clamp(0.0, 1.0);
}

/// The arena walls: [`feature::NEAREST_WALL`], [`feature::WALL_DISTANCE`] and (zero without
/// targets) [`feature::FLOCK_WALL_DISTANCE`].
fn wall_features(view: &View<'_, '_>, survey: &Survey, out: &mut [f32; FEATURES]) {
    let area = view.input.area;
    let (wall_distance, wall_point) = nearest_wall(view.own, area);
    put2(out, feature::NEAREST_WALL, view.rel(wall_point));
    out[feature::WALL_DISTANCE] = soft(wall_distance * view.inv_r);
    if !view.input.targets.is_empty() {
        let (lo, hi) = (survey.lo, survey.hi);
        let min_wall = lo[0]
            .min(lo[1])
            .min(area[0] - hi[0])
            .min(area[1] - hi[1])
            .max(0.0);
        out[feature::FLOCK_WALL_DISTANCE] = soft(min_wall * view.inv_r);
    }
}

/// v4: the drone's slot on the enclosing ring and the way there round the flock,
/// [`feature::RING_SLOT`] to [`feature::RING_BEARING`]; zero without targets.
fn ring_features(
    view: &View<'_, '_>,
    centroid: [f32; 2],
    flock_radius: f32,
    out: &mut [f32; FEATURES],
) {
    let input = view.input;
    if input.targets.is_empty() {
        return;
    }
    let frame = &view.frame;
    let slot = ring_slot(input, frame, centroid, flock_radius);
    // Kept off the walls as the rule keeps its herders: a slot beyond a wall would teach
    // the drone to wait at the fence, where the actuation noise carries it out.
    let margin = RING_WALL_MARGIN * input.goal_radius;
    let inside = |p: [f32; 2]| {
        let clamp = |x: f32, size: f32| {
            x.clamp(
                smaller(margin, 0.5 * size),
                larger(size - margin, 0.5 * size),
            )
        };
        [clamp(p[0], input.area[0]), clamp(p[1], input.area[1])]
    };
    let slot_world = inside(add(centroid, frame.to_world(slot.point)));
    let way_world = inside(add(centroid, frame.to_world(slot.waypoint)));
    put2(out, feature::RING_SLOT, view.rel(slot_world));
    put2(out, feature::RING_WAY, view.rel(way_world));
    out[feature::RING_BEARING] = slot.angle * (1.0 / PI);
}

/// Where the ring rule puts a drone, in the local frame relative to the flock centroid.
#[derive(Clone, Copy, Debug, PartialEq)]
struct RingSlot {
    /// Slot angle from straight behind the flock (away from the goal), counter-clockwise,
    /// radians in [-pi, pi].
    angle: f32,
    /// The slot.
    point: [f32; 2],
    /// Where to head now to reach the slot without crossing the flock disc.
    waypoint: [f32; 2],
}

/// The enclosing-ring slot (encoder v4, [`feature::RING_SLOT`] to [`feature::RING_BEARING`]): the
/// drones stand on an arc behind the flock at its radius plus the stand-off, in the order of their
/// bearing around the centroid, evenly spaced; the arc opens from 120 degrees to a full ring as the
/// centroid comes within [`RING_WRAP`] goal radii of the goal, and the ring's centre moves up to
/// [`RING_SHIFT`] goal radii goalwards. Every drone sees every herder, so each computes its own
/// slot alone and the slots do not collide. The geometry is the simulator's Enclose rule; the
/// collectors it sets aside are not known here, so all drones count.
fn ring_slot(
    input: &ObsInput<'_>,
    frame: &LocalFrame,
    centroid: [f32; 2],
    flock_radius: f32,
) -> RingSlot {
    let r = input.goal_radius;
    let standoff = STANDOFF * r;
    // Bearings are measured in the "behind" frame: the local frame turned half a turn, whose
    // first axis points from the goal through the centroid.
    let behind = |p: [f32; 3]| {
        let v = frame.to_local(sub([p[0], p[1]], centroid));
        [-v[0], -v[1]]
    };
    let own = behind(input.herders[input.own_index]);
    let own_key = pseudo_angle(own);
    let mut rank = 0usize;
    for (j, &h) in input.herders.iter().enumerate() {
        let key = pseudo_angle(behind(h));
        rank += usize::from(key < own_key || (key == own_key && j < input.own_index));
    }
    let m = input.herders.len();
    let d = sqrtf(dist2(centroid, input.goal)) / r;
    let closing = ((RING_WRAP - d) / RING_WRAP).clamp(0.0, 1.0);
    let arc = RING_ARC + closing * (TAU - RING_ARC);
    let shift = RING_SHIFT * r * closing * d.min(1.0);
    let spacing = if m > 1 {
        (arc / (m - 1) as f32).min(TAU / m as f32)
    } else {
        0.0
    };
    let angle = (rank as f32 - 0.5 * (m - 1) as f32) * spacing;
    let ring = flock_radius + standoff;
    // Back in the local frame: "behind" is the negative first axis, the shift is forward.
    let point = [shift - ring * cosf(angle), -ring * sinf(angle)];
    let here = [-own[0], -own[1]];
    let waypoint = round_the_disc(here, point, flock_radius + 0.5 * standoff);
    RingSlot {
        angle,
        point,
        waypoint,
    }
}

/// v5: the drone's own target in the team's assignment, [`feature::ASSIGNED`] to
/// [`feature::ASSIGNED_BEHIND`]; zero without one.
fn assigned_features(view: &View<'_, '_>, out: &mut [f32; FEATURES]) {
    let input = view.input;
    let Some(j) = assignment(input) else {
        return;
    };
    let t = input.targets[j];
    target_features(
        view,
        t,
        dist2(t, input.goal),
        [feature::ASSIGNED, feature::ASSIGNED_BEHIND],
        feature::ASSIGNED_TO_EDGE,
        out,
    );
}

/// How many ranks the assignment hands out at most: as many herders as a world snapshot
/// carries (`wire::MAX_HERDERS`). It bounds the encoder's fixed buffers and its O(N x ranks +
/// ranks x M) time.
pub const ASSIGNED_RANKS: usize = 32;

/// The index of the drone's own target in the team's assignment (encoder v5), or `None` when it
/// has none. Every drone that sees the same world computes the same assignment, so no two
/// drones of one rank hold the same target.
///
/// The targets outside the goal are ranked farthest from the goal first (ties: lower index
/// first); the first `K = min(ranks, those targets)` of them are handed out in rank order,
/// rank `r` (for `r` below the herder count and [`ASSIGNED_RANKS`]) taking target `r mod K`,
/// each to the nearest herder on the ground not yet given one (ties: lower index). So with
/// N >= M every herder has a target of its own, and with fewer targets than herders the spare
/// herders double up from the farthest target on. It is the simulator's Farthest-targets rule's
/// assignment, as ring slots are its Enclose rule's geometry.
///
/// ```
/// use skyherd_onboard::obs::{assignment, ObsInput};
/// // Two herders, two targets far apart: each takes the target nearer to it.
/// let herders = [[0.0_f32, 0.0, 2.0], [200.0, 0.0, 2.0]];
/// let targets = [[190.0_f32, 20.0], [10.0, 20.0]];
/// let view = |own_index| ObsInput {
///     own_index,
///     herders: &herders,
///     targets: &targets,
///     goal: [100.0, 300.0],
///     goal_radius: 45.0,
///     area: [400.0, 400.0, 10.0],
///     max_speed: 5.0,
/// };
/// assert_eq!(assignment(&view(0)), Some(1));
/// assert_eq!(assignment(&view(1)), Some(0));
/// ```
pub fn assignment(input: &ObsInput<'_>) -> Option<usize> {
    let goal = input.goal;
    let r2 = input.goal_radius * input.goal_radius;
    let ranks = input.herders.len().min(ASSIGNED_RANKS);
    if ranks == 0 {
        return None;
    }
    // The `ranks` targets farthest from the goal among those outside it, farthest first:
    // (squared goal distance, index), kept sorted by insertion.
    let mut order = [(0.0_f32, 0usize); ASSIGNED_RANKS];
    let mut k = 0usize;
    for (j, &t) in input.targets.iter().enumerate() {
        let d2 = dist2(t, goal);
        if d2 <= r2 || (k == ranks && d2 <= order[k - 1].0) {
            continue;
        }
        // The first place whose target is nearer: equals keep the lower index first.
        let at = order[..k].partition_point(|e| e.0 >= d2);
        let last = if k < ranks { k } else { ranks - 1 };
        order.copy_within(at..last, at + 1);
        order[at] = (d2, j);
        k = (k + 1).min(ranks);
    }
    if k == 0 {
        return None;
    }
    // The herders given a target so far: a bit each for the first 128 (every onboard team,
    // at most 32), the list for any beyond (the simulator's large teams).
    let mut given = [usize::MAX; ASSIGNED_RANKS];
    let mut given_bits = 0u128;
    for r in 0..ranks {
        let j = order[r % k].1;
        let t = input.targets[j];
        let mut nearest = (f32::INFINITY, usize::MAX);
        for (i, h) in input.herders.iter().enumerate() {
            let taken = if i < 128 {
                given_bits >> i & 1 == 1
            } else {
                given[..r].contains(&i)
            };
            if taken {
                continue;
            }
            let d2 = dist2(t, [h[0], h[1]]);
            if d2 < nearest.0 {
                nearest = (d2, i);
            }
        }
        if nearest.1 == input.own_index {
            return Some(j);
        }
        given[r] = nearest.1;
        if nearest.1 < 128 {
            given_bits |= 1 << nearest.1;
        }
    }
    None
}

/// Arc of the ring rule far from the goal, radians (Strömbom's 120 degrees).
pub const RING_ARC: f32 = 120.0 * PI / 180.0;
/// Centroid distance to the goal, in goal radii, within which the ring starts to close.
pub const RING_WRAP: f32 = 2.0;
/// How far goalwards the closed ring's centre sits, in goal radii.
pub const RING_SHIFT: f32 = 0.8;
/// How far inside the walls the ring's slots and ways are kept, in goal radii (4 m at the
/// paper's 45 m goal).
pub const RING_WALL_MARGIN: f32 = 4.0 / 45.0;
/// Bearing step of the detour round the flock, radians (about 17 degrees).
const ORBIT_STEP: f32 = 0.3;

/// Where a drone at `h` bound for `point` (both relative to the disc's centre) heads now so as
/// not to cross the disc of radius `keep_out`: straight there when the segment misses it, else
/// round it at `point`'s distance, at most [`ORBIT_STEP`] of bearing ahead.
fn round_the_disc(h: [f32; 2], point: [f32; 2], keep_out: f32) -> [f32; 2] {
    if segment_distance_to_origin(h, point) >= keep_out {
        return point;
    }
    let ah = atan2f(h[1], h[0]);
    let ap = atan2f(point[1], point[0]);
    let mut delta = ap - ah;
    if delta > PI {
        delta -= TAU;
    } else if delta < -PI {
        delta += TAU;
    }
    if delta.abs() <= ORBIT_STEP {
        return point;
    }
    let a = ah + if delta > 0.0 { ORBIT_STEP } else { -ORBIT_STEP };
    let rho = larger(sqrtf(point[0] * point[0] + point[1] * point[1]), keep_out);
    [rho * cosf(a), rho * sinf(a)]
}

/// Distance from the origin to the segment `a`-`b`.
fn segment_distance_to_origin(a: [f32; 2], b: [f32; 2]) -> f32 {
    let ab = sub(b, a);
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len2 > 1e-12 {
        (-(a[0] * ab[0] + a[1] * ab[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let p = [a[0] + t * ab[0], a[1] + t * ab[1]];
    sqrtf(p[0] * p[0] + p[1] * p[1])
}

/// A number that orders directions as `atan2(v[1], v[0])` does, in (-2, 2], without the
/// trigonometry: the rank of a bearing needs only its order.
fn pseudo_angle(v: [f32; 2]) -> f32 {
    let s = v[0].abs() + v[1].abs();
    if s == 0.0 {
        return 0.0;
    }
    let p = 1.0 - v[0] / s;
    if v[1] < 0.0 { -p } else { p }
}

fn add(a: [f32; 2], b: [f32; 2]) -> [f32; 2] {
    [a[0] + b[0], a[1] + b[1]]
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

    /// The two numbers of the vector feature `at`.
    fn pair(f: &[f32; FEATURES], at: Range<usize>) -> [f32; 2] {
        [f[at.start], f[at.start + 1]]
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
        // the target count (log N).
        let herders = [[100.0, 100.0, 2.0], [200.0, 90.0, 3.0]];
        let base = scatter(32, 5, [150.0, 150.0], 30.0);
        let mut doubled = [[0.0; 2]; 64];
        doubled[..32].copy_from_slice(&base[..32]);
        doubled[32..].copy_from_slice(&base[..32]);
        let (a, _) = encode_ok(&input(&herders, &base[..32], 0));
        let (b, _) = encode_ok(&input(&herders, &doubled, 0));
        for (k, (x, y)) in a.iter().zip(b.iter()).enumerate() {
            if k != feature::TARGET_COUNT {
                assert!((x - y).abs() < 1e-5, "feature {k}: {x} vs {y}");
            }
        }
        assert!(b[feature::TARGET_COUNT] > a[feature::TARGET_COUNT]);
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
        assert!(pair(&f, feature::GOAL)[0] > pair(&f, feature::CENTROID)[0]);
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
            .map(|own| encode_ok(&input(&herders, &targets[..50], own)).0[feature::SHARE])
            .sum();
        assert!((total - 1.0).abs() < 1e-5, "shares add up to {total}");
    }

    #[test]
    fn lone_herder_and_empty_flock_are_fine() {
        let herders = [[10.0, 10.0, 1.0]];
        let (f, _) = encode_ok(&input(&herders, &[], 0));
        assert!(f.iter().all(|x| x.is_finite()));
        assert_eq!(f[feature::NOT_ALONE], 0.0);
        assert_eq!(f[feature::TARGET_COUNT], 0.0);
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
    fn an_older_versions_encoding_is_the_prefix_it_reads_and_zeros_after_it() {
        let herders = [
            [100.0, 100.0, 2.0],
            [200.0, 90.0, 3.0],
            [150.0, 260.0, 2.0],
            [60.0, 220.0, 2.5],
        ];
        for (seed, count) in [(3, 1), (5, 4), (7, 9), (13, 64)] {
            let targets = scatter(count, seed, [160.0, 170.0], 90.0);
            for own in 0..herders.len() {
                let i = input(&herders, &targets[..count], own);
                let (all, frame) = encode_ok(&i);
                for version in 3..=ENCODER_VERSION {
                    let width = feature_count(version).expect("a served version");
                    let mut some = [f32::NAN; FEATURES];
                    let some_frame = encode_version(&i, version, &mut some).expect("valid input");
                    assert_eq!(some_frame, frame);
                    // Bits, not values: the prefix must be the one each model was trained on.
                    let same = some[..width]
                        .iter()
                        .zip(&all[..width])
                        .all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same, "v{version}: {some:?}\n{all:?}");
                    assert!(
                        some[width..].iter().all(|&x| x.to_bits() == 0),
                        "v{version}"
                    );
                }
            }
        }
        let i = input(&herders, &[], 0);
        let mut out = [0.0; FEATURES];
        for version in [0, 1, 2, ENCODER_VERSION + 1, u16::MAX] {
            assert_eq!(
                encode_version(&i, version, &mut out),
                Err(ObsError::UnknownVersion(version))
            );
        }
    }

    #[test]
    fn extreme_finite_worlds_encode_without_panicking() {
        // Validation lets any finite world through; squares of huge coordinates overflow to
        // infinity, and the ring's clamp, trigonometry and ranks must take that (and
        // coincident drones and targets) without a panic.
        let values = [0.0, 1e-30, 0.05, 1.0, 500.0, 1e19, 3e38, -3e38];
        for (k, &a) in values.iter().enumerate() {
            for &b in &values {
                let herders = [[a, b, 2.0], [a, b, 2.0], [b, a, -1e30]];
                let targets = [[a, a], [b, b], [a, b]];
                for own in 0..3 {
                    let i = ObsInput {
                        own_index: own,
                        herders: &herders,
                        targets: &targets,
                        goal: [b, a],
                        goal_radius: [0.05, 1.0, 3e38][k % 3],
                        area: [500.0, [1e-30, 3e38][k % 2], 10.0],
                        max_speed: 5.0,
                    };
                    let mut out = [0.0; FEATURES];
                    let _ = encode(&i, &mut out);
                }
            }
        }
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

    #[test]
    fn a_lone_drone_far_from_the_goal_has_its_slot_straight_behind_the_flock() {
        // With one herder the arc has one slot, in its middle: the point behind the whole flock
        // (FLOCK_BEHIND); behind the flock already, the way there is straight.
        let herders = [[60.0, 90.0, 2.0]];
        let targets = scatter(40, 13, [150.0, 150.0], 20.0);
        let (f, _) = encode_ok(&input(&herders, &targets[..40], 0));
        let (slot, way) = (pair(&f, feature::RING_SLOT), pair(&f, feature::RING_WAY));
        let behind = pair(&f, feature::FLOCK_BEHIND);
        assert!(
            (slot[0] - behind[0]).abs() < 1e-4 && (slot[1] - behind[1]).abs() < 1e-4,
            "{f:?}"
        );
        assert!((way[0] - slot[0]).abs() < 1e-6 && (way[1] - slot[1]).abs() < 1e-6);
        assert_eq!(f[feature::RING_BEARING], 0.0);
    }

    #[test]
    fn on_the_goal_the_ring_slots_are_even_and_distinct() {
        // The flock sits on the goal: the arc is a full ring, so M drones get M slots TAU / M
        // apart, whatever order they are listed in.
        let targets = scatter(64, 17, [400.0, 380.0], 20.0);
        let herders: [[f32; 3]; 6] = core::array::from_fn(|k| {
            let a = 0.9 * k as f32 + 0.3 * (k * k) as f32;
            [400.0 + 70.0 * cosf(a), 380.0 + 70.0 * sinf(a), 2.0]
        });
        let mut angles: [f32; 6] = core::array::from_fn(|own| {
            encode_ok(&input(&herders, &targets, own)).0[feature::RING_BEARING] * PI
        });
        angles.sort_by(f32::total_cmp);
        for pair in angles.windows(2) {
            assert!((pair[1] - pair[0] - TAU / 6.0).abs() < 1e-4, "{angles:?}");
        }
    }

    /// Undoes `rel` for the point feature `at`: decompress, to world, scale, add the drone's
    /// position.
    fn world_point(
        f: &[f32; FEATURES],
        at: Range<usize>,
        frame: &LocalFrame,
        own: [f32; 3],
    ) -> [f32; 2] {
        let v = pair(f, at);
        let c = sqrtf(v[0] * v[0] + v[1] * v[1]);
        let d = libm::expf(c) - 1.0;
        let local = if c > 0.0 {
            [v[0] * d / c, v[1] * d / c]
        } else {
            v
        };
        let w = frame.to_world(local);
        [own[0] + w[0] * 45.0, own[1] + w[1] * 45.0]
    }

    #[test]
    fn in_front_of_the_flock_the_way_to_the_slot_goes_round_it() {
        // A drone between the flock and the goal is bound for a slot behind the flock; heading
        // straight there would drive the flock back, so the way steps round the flock disc, one
        // orbit step of bearing at a time.
        let targets = scatter(40, 19, [150.0, 150.0], 20.0);
        let herders = [[260.0, 250.0, 2.0]];
        let (f, frame) = encode_ok(&input(&herders, &targets[..40], 0));
        let slot = world_point(&f, feature::RING_SLOT, &frame, herders[0]);
        let way = world_point(&f, feature::RING_WAY, &frame, herders[0]);
        assert!(dist2(slot, way) > 1.0, "slot {slot:?} way {way:?}");
        let n = targets[..40].len() as f32;
        let centroid = targets[..40]
            .iter()
            .fold([0.0, 0.0], |a, t| [a[0] + t[0] / n, a[1] + t[1] / n]);
        let bearing = |p: [f32; 2]| atan2f(p[1] - centroid[1], p[0] - centroid[0]);
        let step = (bearing(way) - bearing([260.0, 250.0])).abs();
        assert!((step - ORBIT_STEP).abs() < 1e-2, "bearing step {step}");
    }

    /// Every drone's assigned target (encoder v5), each from its own view (at most 48 drones).
    fn assignments(herders: &[[f32; 3]], targets: &[[f32; 2]]) -> heapless::Vec<Option<usize>, 48> {
        (0..herders.len())
            .map(|own| assignment(&input(herders, targets, own)))
            .collect()
    }

    #[test]
    fn with_as_many_targets_as_herders_each_drone_has_a_target_of_its_own() {
        // Four herders in a corner and four targets spread over the arena (goal at 400, 380):
        // the nearest-target share would give them all to one or two drones.
        let herders = [
            [20.0, 20.0, 2.0],
            [30.0, 20.0, 2.0],
            [20.0, 30.0, 2.0],
            [30.0, 30.0, 2.0],
        ];
        let targets = [[100.0, 80.0], [300.0, 60.0], [60.0, 300.0], [200.0, 200.0]];
        let got = assignments(&herders, &targets);
        let mut taken: heapless::Vec<usize, 4> = got.iter().map(|a| a.expect("one each")).collect();
        taken.sort_unstable();
        assert_eq!(taken[..], [0, 1, 2, 3], "{got:?}");
        // The farthest target from the goal (index 0) goes to the herder nearest to it.
        assert_eq!(got[3], Some(0), "{got:?}");
        // Its features point at it, and its behind point lies STANDOFF x R beyond it.
        let (f, frame) = encode_ok(&input(&herders, &targets, 3));
        let at = world_point(&f, feature::ASSIGNED, &frame, herders[3]);
        assert!(
            (at[0] - 100.0).abs() < 0.05 && (at[1] - 80.0).abs() < 0.05,
            "{at:?}"
        );
        let behind = world_point(&f, feature::ASSIGNED_BEHIND, &frame, herders[3]);
        let from_goal = sqrtf(dist2(behind, [400.0, 380.0])) - sqrtf(dist2(at, [400.0, 380.0]));
        assert!((from_goal - STANDOFF * 45.0).abs() < 0.05, "{from_goal}");
        let edge = sqrtf(dist2([100.0, 80.0], [400.0, 380.0])) / 45.0 - 1.0;
        assert!((f[feature::ASSIGNED_TO_EDGE] - soft(edge)).abs() < 1e-5);
    }

    #[test]
    fn spare_herders_double_up_from_the_farthest_target() {
        let herders = [
            [20.0, 20.0, 2.0],
            [480.0, 20.0, 2.0],
            [20.0, 480.0, 2.0],
            [250.0, 480.0, 2.0],
        ];
        // Two targets outside the goal, one inside (ignored).
        let targets = [[50.0, 50.0], [400.0, 380.0], [300.0, 100.0]];
        let got = assignments(&herders, &targets);
        // Rank 0 (the farthest, target 0) to herder 0, rank 1 (target 2) to herder 1, then
        // the ranks wrap: target 0 to the nearest free herder (2), target 2 to the last (3).
        assert_eq!(got[..], [Some(0), Some(2), Some(0), Some(2)]);
    }

    #[test]
    fn with_every_target_in_the_goal_there_is_no_assignment_and_its_features_are_zero() {
        let herders = [[20.0, 20.0, 2.0], [480.0, 20.0, 2.0]];
        let targets = [[400.0, 380.0], [410.0, 390.0]];
        assert_eq!(assignments(&herders, &targets)[..], [None, None]);
        let (f, _) = encode_ok(&input(&herders, &targets, 1));
        assert!(
            f[feature::ASSIGNED.start..feature::ASSIGNED_BEHIND.end]
                .iter()
                .all(|&x| x == 0.0)
        );
        let (f, _) = encode_ok(&input(&herders, &[], 0));
        assert!(f[feature::ASSIGNED.start..].iter().all(|&x| x == 0.0));
    }

    #[test]
    fn beyond_the_assigned_ranks_a_drone_reads_no_assignment_and_nothing_panics() {
        let herders: [[f32; 3]; ASSIGNED_RANKS + 8] =
            core::array::from_fn(|k| [10.0 + 10.0 * k as f32, 20.0, 2.0]);
        let targets = scatter(64, 5, [150.0, 150.0], 100.0);
        let got = assignments(&herders, &targets);
        assert_eq!(got.iter().filter(|a| a.is_some()).count(), ASSIGNED_RANKS);
        let mut taken: heapless::Vec<usize, 48> = got.iter().flatten().copied().collect();
        taken.sort_unstable();
        assert!(
            taken.windows(2).all(|w| w[0] != w[1]),
            "one target per rank: {taken:?}"
        );
        // An own index out of range has none (encode refuses it before asking).
        let mut i = input(&herders, &targets, 0);
        i.own_index = herders.len();
        assert_eq!(assignment(&i), None);
        i.herders = &[];
        i.own_index = 0;
        assert_eq!(assignment(&i), None);
    }

    #[test]
    fn ring_slots_stay_inside_the_walls() {
        // A flock against the west wall: its ring would reach past the wall; the slots are kept
        // RING_WALL_MARGIN inside, as the rule keeps its herders.
        let targets = scatter(64, 23, [30.0, 250.0], 25.0);
        let herders: [[f32; 3]; 8] = core::array::from_fn(|k| [80.0, 150.0 + 25.0 * k as f32, 2.0]);
        for own in 0..8 {
            let mut i = input(&herders, &targets, own);
            i.goal = [450.0, 250.0];
            let (f, frame) = encode_ok(&i);
            let x = world_point(&f, feature::RING_SLOT, &frame, herders[own])[0];
            assert!(
                x >= RING_WALL_MARGIN * 45.0 - 1e-2,
                "drone {own}: slot at x = {x}"
            );
        }
    }
}
