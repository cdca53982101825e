//! Rule-based herders behind the same per-herder [`Policy`] trait as the learned actor.
//!
//! All rules measure in goal radii `R`, so one rule serves the 45 m paper goal and the 0.9 m
//! indoor goal: stand-off `8/45 R` (8 m in the paper world), herding altitude `2/45 R` (2 m).
//! They read only the observation (positions; never the noisy boids parameters). Work shared by
//! all herders (rankings, shares) is done once per step and cached: every herder would compute
//! the same thing, so this is still decentralised behaviour, just cheaper to simulate.
//!
//! * [`Method::Strombom`]: Strömbom et al. (2014) for several herders: when some target is
//!   farther than `f(N) = 0.22 R N^0.37` from the flock centroid (about 1.3 times the radius a
//!   flock of N spreads to under separation alone), the herders take the farthest stragglers, one
//!   each, and push them towards the centroid; the others drive: they spread on an arc of 120°
//!   behind the flock (seen from the goal) at the flock radius plus the stand-off.
//! * [`Method::ControlTutor`]: the control-tutor rule of CTRL (de Lellis et al.) as the paper
//!   describes it: each herder, on its own, chases the target farthest from the goal and pushes
//!   it in from behind. No coordination: they all pick the same target.
//! * [`Method::Lama`]: after Lama & di Bernardo (2024): each herder takes the targets outside the
//!   goal for which it is the nearest herder and pushes the one of them farthest from the goal
//!   from behind; a herder with no share goes behind the flock.
//! * [`Method::FarthestTargets`]: the best simple rule of DESIGN §2: the M targets farthest from
//!   the goal are handed out, farthest first, each to the nearest herder not yet given one, and
//!   each herder sits behind its target on the target-goal line.
//! * [`Method::Enclose`]: Strömbom whose driving arc wraps round the flock as the flock nears the
//!   goal (120 degrees from 2 goal radii out, a full ring at the goal), the ring's centre shifted
//!   goalwards of the centroid so that the herders behind press harder than those in front, and
//!   the ring herders going round the flock, not through it, to their slots. The closed ring
//!   squeezes a flock far below its resting size (256 targets from ~58 m to ~30 m radius, 1024
//!   to the 45 m goal), which no other rule here does: it is the teacher for large flocks.
//!
//! "Push from behind" means: fly to the point `stand-off` behind the target on the line from the
//! goal through it; a herder on the goal side first swings round the target at 2 stand-offs, so
//! that it does not drive the target the wrong way on its way there.

use std::fmt;
use std::str::FromStr;

use crate::policy::{Policy, PolicyFactory};
use crate::world::{World, dist2};

/// Stand-off behind a pushed target, in goal radii (8 m at R = 45 m).
pub(crate) const STANDOFF_R: f64 = 8.0 / 45.0;
/// How far inside the walls a herder keeps, in goal radii (1 m at R = 45 m).
pub(crate) const WALL_MARGIN_R: f64 = 1.0 / 45.0;
/// Strömbom's driving arc behind the flock, radians (120 degrees).
pub(crate) const STROMBOM_ARC: f64 = 120.0 * std::f64::consts::PI / 180.0;
/// [`Method::Enclose`] starts wrapping its arc round the flock at this centroid distance, goal radii.
pub(crate) const ENCLOSE_WRAP_R: f64 = 2.0;
/// [`Method::Enclose`] shifts its closed ring this far goalwards of the centroid, in goal radii.
pub(crate) const ENCLOSE_SHIFT_R: f64 = 0.8;
/// Herding altitude, in goal radii (2 m at R = 45 m).
pub(crate) const ALTITUDE_R: f64 = 2.0 / 45.0;

/// The rule-based methods.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Method {
    /// Strömbom-style collect/drive with herders on an arc.
    Strombom,
    /// CTRL-style control tutor: everyone chases the target farthest from the goal.
    ControlTutor,
    /// Lama & di Bernardo-style: own share, farthest from the goal.
    Lama,
    /// DESIGN §2's best simple rule: each herder a different far target.
    FarthestTargets,
    /// Strömbom whose driving arc closes into a ring round the flock near the goal.
    Enclose,
}

impl Method {
    /// Every baseline, in report order.
    pub const ALL: [Method; 5] = [
        Method::Strombom,
        Method::ControlTutor,
        Method::Lama,
        Method::FarthestTargets,
        Method::Enclose,
    ];

    /// The name used on the command line and in reports.
    pub fn as_str(self) -> &'static str {
        match self {
            Method::Strombom => "strombom",
            Method::ControlTutor => "ctrl",
            Method::Lama => "lama",
            Method::FarthestTargets => "farthest",
            Method::Enclose => "enclose",
        }
    }

    /// How far inside the walls the rule keeps its herders, in goal radii. [`Method::Enclose`]
    /// keeps 4 m (at R = 45 m): its ring reaches the walls when the flock does, and the
    /// actuation noise would carry a herder over a 1 m margin.
    pub fn wall_margin_r(self) -> f64 {
        match self {
            Method::Enclose => 4.0 * WALL_MARGIN_R,
            _ => WALL_MARGIN_R,
        }
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Method::ALL
            .into_iter()
            .find(|m| m.as_str() == s)
            .ok_or_else(|| {
                format!(
                    "unknown method `{s}`; baselines are {}",
                    Method::ALL.map(Method::as_str).join(", ")
                )
            })
    }
}

/// In configs a method is its name (`"lama"`, `"enclose"`, ...): [`Method::as_str`].
impl serde::Serialize for Method {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> serde::Deserialize<'de> for Method {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = <String as serde::Deserialize>::deserialize(d)?;
        name.parse().map_err(<D::Error as serde::de::Error>::custom)
    }
}

impl PolicyFactory for Method {
    fn name(&self) -> String {
        self.as_str().to_owned()
    }
    fn make(&self) -> Box<dyn Policy + Send> {
        Box::new(RulePolicy::new(*self))
    }
}

/// A rule-based herder team; one instance answers for every herder.
#[derive(Clone, Debug)]
pub struct RulePolicy {
    method: Method,
    cached_step: Option<u64>,
    /// Per herder: the ground point to reach this step.
    goals: Vec<[f64; 2]>,
    /// Per herder: the target it pushes (for the swing-round), if any.
    pushed: Vec<Option<[f64; 2]>>,
    order: Vec<u32>,
    dist: Vec<f64>,
    taken: Vec<bool>,
    share_best: Vec<Option<(f64, usize)>>,
    by_angle: Vec<(f64, usize)>,
    /// Per herder, [`Method::Enclose`] only: the flock disc (centre, radius) to go round, not
    /// through, on the way to its slot.
    orbit: Vec<Option<([f64; 2], f64)>>,
}

impl RulePolicy {
    /// A team following `method`.
    pub fn new(method: Method) -> Self {
        RulePolicy {
            method,
            cached_step: None,
            goals: Vec::new(),
            pushed: Vec::new(),
            order: Vec::new(),
            dist: Vec::new(),
            taken: Vec::new(),
            share_best: Vec::new(),
            by_angle: Vec::new(),
            orbit: Vec::new(),
        }
    }

    /// The method it follows.
    pub fn method(&self) -> Method {
        self.method
    }

    fn plan(&mut self, w: &World) {
        let m = w.herders.len();
        self.goals.clear();
        self.goals.resize(m, w.goal.center);
        self.pushed.clear();
        self.pushed.resize(m, None);
        self.orbit.clear();
        self.orbit.resize(m, None);
        let g = w.goal.center;
        let r = w.goal.radius;
        let standoff = STANDOFF_R * r;
        self.dist.clear();
        self.dist
            .extend(w.targets.iter().map(|&t| dist2(t, g).sqrt()));
        // Targets still outside the goal; if none, keep everyone where they are.
        self.order.clear();
        self.order
            .extend((0..w.targets.len() as u32).filter(|&j| self.dist[j as usize] > r));
        if self.order.is_empty() {
            for (goal, h) in self.goals.iter_mut().zip(&w.herders) {
                *goal = [h[0], h[1]];
            }
            return;
        }
        match self.method {
            Method::ControlTutor => {
                let far = self.farthest_outside();
                for i in 0..m {
                    self.push(i, w.targets[far], g, standoff);
                }
            }
            Method::FarthestTargets => {
                let k = m.min(self.order.len());
                let dist = &self.dist;
                let by_far = |a: &u32, b: &u32| dist[*b as usize].total_cmp(&dist[*a as usize]);
                if k < self.order.len() {
                    self.order.select_nth_unstable_by(k - 1, by_far);
                }
                self.order[..k].sort_unstable_by(by_far);
                self.taken.clear();
                self.taken.resize(m, false);
                for rank in 0..m {
                    // More herders than targets outside: the spare ones double up, farthest first.
                    let j = self.order[rank % k] as usize;
                    let t = w.targets[j];
                    let Some(i) = nearest_free(&w.herders, &self.taken, t) else {
                        break;
                    };
                    self.taken[i] = true;
                    self.push(i, t, g, standoff);
                }
            }
            Method::Lama => {
                self.share_best.clear();
                self.share_best.resize(m, None);
                for &j in &self.order {
                    let j = j as usize;
                    let t = w.targets[j];
                    let i = nearest_herder(&w.herders, t, &[]);
                    let d = self.dist[j];
                    let best = &mut self.share_best[i];
                    if best.is_none_or(|(bd, _)| d > bd) {
                        *best = Some((d, j));
                    }
                }
                let (centroid, radius) = centroid_radius(w);
                let behind_flock = behind(centroid, g, radius + standoff);
                for i in 0..m {
                    match self.share_best[i] {
                        Some((_, j)) => self.push(i, w.targets[j], g, standoff),
                        None => self.goals[i] = behind_flock,
                    }
                }
            }
            Method::Enclose => {
                // The driving arc wraps round the flock as it nears the goal until it is a ring
                // that squeezes it; the ring's centre sits a little goalwards of the centroid, so
                // the herders behind press harder than those in front and the flock keeps going.
                let d = dist2(w.flock_centroid(), g).sqrt() / r;
                let closing = ((ENCLOSE_WRAP_R - d) / ENCLOSE_WRAP_R).clamp(0.0, 1.0);
                let arc = STROMBOM_ARC + closing * (std::f64::consts::TAU - STROMBOM_ARC);
                let shift = ENCLOSE_SHIFT_R * r * closing * d.min(1.0);
                self.plan_strombom(w, arc, shift)
            }
            Method::Strombom => self.plan_strombom(w, STROMBOM_ARC, 0.0),
        }
    }

    /// Strömbom: collect the stragglers beyond `f(N)`, drive with the rest on an arc.
    fn plan_strombom(&mut self, w: &World, arc: f64, shift: f64) {
        let m = w.herders.len();
        let g = w.goal.center;
        let r = w.goal.radius;
        let standoff = STANDOFF_R * r;
        let (centroid, radius) = centroid_radius(w);
        let n = w.targets.len() as f64;
        let f_n = 0.22 * r * n.powf(0.37);
        // Stragglers: every target beyond f(N) from the centroid, farthest first.
        self.dist.clear();
        self.dist
            .extend(w.targets.iter().map(|&t| dist2(t, centroid).sqrt()));
        self.order.clear();
        self.order
            .extend((0..w.targets.len() as u32).filter(|&j| self.dist[j as usize] > f_n));
        let k = m.min(self.order.len());
        let dist = &self.dist;
        let by_far = |a: &u32, b: &u32| dist[*b as usize].total_cmp(&dist[*a as usize]);
        if k > 0 && k < self.order.len() {
            self.order.select_nth_unstable_by(k - 1, by_far);
        }
        self.order[..k].sort_unstable_by(by_far);
        self.taken.clear();
        self.taken.resize(m, false);
        for rank in 0..k {
            let t = w.targets[self.order[rank] as usize];
            if let Some(i) = nearest_free(&w.herders, &self.taken, t) {
                self.taken[i] = true;
                // Collect: push the straggler towards the flock centroid.
                self.push(i, t, centroid, standoff);
            }
        }
        // Drive: the rest spread on an arc behind the flock, in the order of their
        // bearing around it so that they do not cross.
        let back = unit([centroid[0] - g[0], centroid[1] - g[1]]);
        let base = back[1].atan2(back[0]);
        let by_angle = &mut self.by_angle;
        by_angle.clear();
        by_angle.extend((0..m).filter(|&i| !self.taken[i]).map(|i| {
            let h = w.herders[i];
            let a = (h[1] - centroid[1]).atan2(h[0] - centroid[0]) - base;
            (wrap_angle(a), i)
        }));
        let d = by_angle.len();
        if d > 0 {
            by_angle.sort_by(|a, b| a.0.total_cmp(&b.0));
            let ring = radius + standoff;
            // Evenly over the arc, ends included, but never closer than a full ring's spacing
            // (a 360-degree arc must not put its two ends on one spot). Strömbom's arc (120
            // degrees) never meets that cap, and its slots keep their original expression: the
            // same angles, but rounded differently, and episodes are chaotic enough that the
            // committed sweeps of each rule reproduce only with their own expression.
            let enclose = self.method == Method::Enclose;
            let spacing = if d == 1 {
                0.0
            } else {
                (arc / (d - 1) as f64).min(std::f64::consts::TAU / d as f64)
            };
            for (slot, &(_, i)) in self.by_angle.iter().enumerate() {
                let a = if enclose {
                    self.orbit[i] = Some((centroid, radius + 0.5 * standoff));
                    base + (slot as f64 - 0.5 * (d - 1) as f64) * spacing
                } else {
                    let frac = if d == 1 {
                        0.0
                    } else {
                        slot as f64 / (d - 1) as f64 - 0.5
                    };
                    base + frac * arc
                };
                self.goals[i] = [
                    centroid[0] + ring * a.cos() - shift * back[0],
                    centroid[1] + ring * a.sin() - shift * back[1],
                ];
            }
        }
    }

    fn farthest_outside(&self) -> usize {
        let mut best = self.order[0] as usize;
        for &j in &self.order {
            if self.dist[j as usize] > self.dist[best] {
                best = j as usize;
            }
        }
        best
    }

    /// Herder `i` pushes `target` away from `from` (the goal, or the centroid when collecting).
    fn push(&mut self, i: usize, target: [f64; 2], from: [f64; 2], standoff: f64) {
        self.goals[i] = behind_point(target, from, standoff);
        self.pushed[i] = Some(target);
    }
}

fn nearest_herder(herders: &[[f64; 3]], t: [f64; 2], taken: &[bool]) -> usize {
    let mut best = 0;
    let mut best_d = f64::INFINITY;
    for (i, h) in herders.iter().enumerate() {
        if taken.get(i).copied().unwrap_or(false) {
            continue;
        }
        let d = dist2([h[0], h[1]], t);
        if d < best_d {
            best_d = d;
            best = i;
        }
    }
    best
}

fn nearest_free(herders: &[[f64; 3]], taken: &[bool], t: [f64; 2]) -> Option<usize> {
    if taken.iter().all(|&x| x) {
        return None;
    }
    Some(nearest_herder(herders, t, taken))
}

fn centroid_radius(w: &World) -> ([f64; 2], f64) {
    let c = w.flock_centroid();
    let r = w
        .targets
        .iter()
        .map(|&t| dist2(t, c))
        .fold(0.0, f64::max)
        .sqrt();
    (c, r)
}

fn unit(v: [f64; 2]) -> [f64; 2] {
    let n = (v[0] * v[0] + v[1] * v[1]).sqrt();
    if n > 1e-12 {
        [v[0] / n, v[1] / n]
    } else {
        [1.0, 0.0]
    }
}

fn wrap_angle(a: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    let mut a = a % tau;
    if a > std::f64::consts::PI {
        a -= tau;
    } else if a < -std::f64::consts::PI {
        a += tau;
    }
    a
}

/// The point `standoff` beyond `target` on the ray from `from` through it.
pub(crate) fn behind_point(target: [f64; 2], from: [f64; 2], standoff: f64) -> [f64; 2] {
    behind(target, from, standoff)
}

fn behind(p: [f64; 2], from: [f64; 2], dist: f64) -> [f64; 2] {
    let u = unit([p[0] - from[0], p[1] - from[1]]);
    [p[0] + u[0] * dist, p[1] + u[1] * dist]
}

/// Where a herder at `h` bound for `point` heads now so as not to cross the disc
/// (`centre`, `keep_out`): straight there when the segment misses the disc, else round the disc
/// at `point`'s distance from its centre, at most [`ORBIT_STEP`] of bearing ahead.
fn round_the_flock(h: [f64; 2], point: [f64; 2], centre: [f64; 2], keep_out: f64) -> [f64; 2] {
    if segment_distance(centre, h, point) >= keep_out {
        return point;
    }
    let (ah, _) = polar(h, centre);
    let (ap, rp) = polar(point, centre);
    let delta = wrap_angle(ap - ah);
    if delta.abs() <= ORBIT_STEP {
        return point;
    }
    let a = ah + ORBIT_STEP * delta.signum();
    let rho = rp.max(keep_out);
    [centre[0] + rho * a.cos(), centre[1] + rho * a.sin()]
}

/// Bearing step of [`round_the_flock`], radians (about 17 degrees).
const ORBIT_STEP: f64 = 0.3;

fn polar(p: [f64; 2], centre: [f64; 2]) -> (f64, f64) {
    let v = [p[0] - centre[0], p[1] - centre[1]];
    (v[1].atan2(v[0]), (v[0] * v[0] + v[1] * v[1]).sqrt())
}

/// Distance from `p` to the segment `a`-`b`.
fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len2 > 1e-12 {
        (((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    dist2(p, [a[0] + t * ab[0], a[1] + t * ab[1]]).sqrt()
}

/// Velocity that reaches `point` at `altitude` this step if it can, else flies at `vmax`.
pub fn steer(herder: [f64; 3], point: [f64; 2], altitude: f64, vmax: f64, dt: f64) -> [f64; 3] {
    let v = [
        (point[0] - herder[0]) / dt,
        (point[1] - herder[1]) / dt,
        (altitude - herder[2]) / dt,
    ];
    crate::world::cap3(v, vmax)
}

/// Where a herder at `h` should head to get behind `target` (pushed away from the point `from`,
/// aiming at `behind_pt`) without driving it the wrong way: if it is on the near side, swing round.
fn approach(h: [f64; 2], target: [f64; 2], behind_pt: [f64; 2], standoff: f64) -> [f64; 2] {
    let back = unit([behind_pt[0] - target[0], behind_pt[1] - target[1]]);
    let rel = [h[0] - target[0], h[1] - target[1]];
    let dist = (rel[0] * rel[0] + rel[1] * rel[1]).sqrt();
    let along = rel[0] * back[0] + rel[1] * back[1];
    let swing = 2.0 * standoff;
    if dist < 3.0 * standoff && along < 0.5 * dist {
        // Go to the side of the target the herder is already on, a little behind.
        let side = [-back[1], back[0]];
        let s = if rel[0] * side[0] + rel[1] * side[1] >= 0.0 {
            1.0
        } else {
            -1.0
        };
        let p = [
            target[0] + swing * (s * side[0] + 0.5 * back[0]),
            target[1] + swing * (s * side[1] + 0.5 * back[1]),
        ];
        return p;
    }
    behind_pt
}

impl Policy for RulePolicy {
    fn reset(&mut self, _world: &World, _seed: u64) {
        self.cached_step = None;
    }

    fn act(&mut self, world: &World, herder: usize) -> [f64; 3] {
        if self.cached_step != Some(world.step) || self.goals.len() != world.herders.len() {
            self.plan(world);
            self.cached_step = Some(world.step);
        }
        let Some(&h) = world.herders.get(herder) else {
            return [0.0; 3];
        };
        let r = world.goal.radius;
        let mut point = self.goals[herder];
        if let Some(target) = self.pushed[herder] {
            point = approach([h[0], h[1]], target, point, STANDOFF_R * r);
        }
        if let Some((centre, keep_out)) = self.orbit.get(herder).copied().flatten() {
            point = round_the_flock([h[0], h[1]], point, centre, keep_out);
        }
        // Never chase a point outside the arena: leaving it ends the episode.
        let margin = self.method.wall_margin_r() * r;
        point[0] = point[0].clamp(
            margin.min(world.area.width / 2.0),
            (world.area.width - margin).max(world.area.width / 2.0),
        );
        point[1] = point[1].clamp(
            margin.min(world.area.depth / 2.0),
            (world.area.depth - margin).max(world.area.depth / 2.0),
        );
        let altitude = (ALTITUDE_R * r).min(world.area.ceiling);
        steer(h, point, altitude, world.limits.herder, world.dt)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::HerderCount;
    use crate::{Env, Scenario, run_episode};

    #[test]
    fn every_method_parses_from_its_name_and_an_unknown_name_lists_them() {
        for method in Method::ALL {
            assert_eq!(method.as_str().parse::<Method>(), Ok(method));
        }
        let err = "shepherd".parse::<Method>().unwrap_err();
        assert!(err.contains("`shepherd`"), "{err}");
        for method in Method::ALL {
            assert!(err.contains(method.as_str()), "{err}");
        }
    }

    #[test]
    fn round_the_flock_goes_straight_when_clear_and_round_when_not() {
        let centre = [0.0, 0.0];
        // The segment misses the disc: straight to the point.
        assert_eq!(
            round_the_flock([100.0, 50.0], [-100.0, 50.0], centre, 30.0),
            [-100.0, 50.0]
        );
        // Straight through the middle: a step round the disc instead, outside it.
        let p = round_the_flock([100.0, 0.0], [-100.0, 0.0], centre, 30.0);
        let (a, rho) = polar(p, centre);
        assert!((a.abs() - ORBIT_STEP).abs() < 1e-9, "bearing {a}");
        assert!((30.0..=100.0 + 1e-9).contains(&rho), "radius {rho}");
        // Almost there (within one bearing step): straight on.
        let near = [30.0 * 0.2f64.cos(), 30.0 * 0.2f64.sin()];
        assert_eq!(round_the_flock([40.0, 0.0], near, centre, 35.0), near);
    }

    #[test]
    fn segment_distance_is_to_the_nearest_point_of_the_segment() {
        assert!((segment_distance([0.0, 5.0], [-1.0, 0.0], [1.0, 0.0]) - 5.0).abs() < 1e-12);
        assert!(
            (segment_distance([4.0, 3.0], [-1.0, 0.0], [1.0, 0.0]) - 4.242_640_687).abs() < 1e-6
        );
        assert!((segment_distance([3.0, 4.0], [0.0, 0.0], [0.0, 0.0]) - 5.0).abs() < 1e-12);
    }

    /// The ring closes round a flock sitting on the goal: the drive slots are evenly spread
    /// round it and no two herders are sent to one spot.
    #[test]
    fn at_the_goal_the_enclose_slots_are_a_full_even_ring() {
        let mut env = Env::new(Scenario {
            targets: 256,
            herders: HerderCount::Fixed(16),
            ..Scenario::paper_drive().without_noise()
        })
        .unwrap();
        let mut world = env.reset(3).clone();
        let g = world.goal.center;
        // The flock's centroid on the goal centre, its rim (50 m) outside the 45 m goal and
        // inside Strömbom's straggler distance f(256) = 77 m: every herder drives.
        for (j, t) in world.targets.iter_mut().enumerate() {
            let a = j as f64 * 0.618 * std::f64::consts::TAU;
            let rho = 50.0 * ((j % 8) as f64 + 1.0) / 8.0;
            *t = [g[0] + rho * a.cos(), g[1] + rho * a.sin()];
        }
        let c = world.flock_centroid();
        for t in world.targets.iter_mut() {
            *t = [t[0] - c[0] + g[0], t[1] - c[1] + g[1]];
        }
        let mut rule = RulePolicy::new(Method::Enclose);
        rule.plan(&world);
        let mut bearings: Vec<f64> = rule
            .goals
            .iter()
            .zip(&rule.pushed)
            .filter(|(_, pushed)| pushed.is_none())
            .map(|(p, _)| polar(*p, g).0)
            .collect();
        assert_eq!(bearings.len(), 16, "every herder drives");
        bearings.sort_by(f64::total_cmp);
        let d = bearings.len();
        for k in 0..d {
            let gap = (bearings[(k + 1) % d] - bearings[k]).rem_euclid(std::f64::consts::TAU);
            let even = std::f64::consts::TAU / d as f64;
            assert!((gap - even).abs() < 1e-6, "gap {gap} vs {even}");
        }
    }

    /// The onboard encoder's ring features (v4, 46-50) are this rule's geometry: where no target
    /// straggles, every herder heads where feature 48-49 (the way to its slot) points, so a
    /// policy can learn the rule from them. Checked with the ring part-way closed, so the arc,
    /// the goalward shift, the detour round the flock and the wall margin all count.
    #[test]
    fn the_encoders_ring_features_point_where_enclose_herders_go() {
        use skyherd_onboard::obs::{
            FEATURES, RING_ARC, RING_SHIFT, RING_WALL_MARGIN, RING_WRAP, feature,
        };
        // The constants are the rule's, to f32 precision.
        assert!((f64::from(RING_ARC) - STROMBOM_ARC).abs() < 1e-6);
        assert!((f64::from(RING_WRAP) - ENCLOSE_WRAP_R).abs() < 1e-6);
        assert!((f64::from(RING_SHIFT) - ENCLOSE_SHIFT_R).abs() < 1e-6);
        let margin = Method::Enclose.wall_margin_r();
        assert!((f64::from(RING_WALL_MARGIN) - margin).abs() < 1e-6);

        let mut env = Env::new(Scenario {
            targets: 128,
            herders: HerderCount::Fixed(12),
            ..Scenario::paper_drive().without_noise()
        })
        .unwrap();
        let mut world = env.reset(5).clone();
        let g = world.goal.center;
        let r = world.goal.radius;
        // A flock 1.2 goal radii from the goal (the arc 40 % closed), no target beyond 40 m of
        // its centroid (Strömbom's straggler distance at N = 128 is 59 m): every herder drives.
        let away = unit([250.0 - g[0], 250.0 - g[1]]);
        let centre = [g[0] + 1.2 * r * away[0], g[1] + 1.2 * r * away[1]];
        for (j, t) in world.targets.iter_mut().enumerate() {
            let a = j as f64 * 0.618 * std::f64::consts::TAU;
            let rho = 40.0 * ((j % 8) as f64 + 1.0) / 8.0;
            *t = [centre[0] + rho * a.cos(), centre[1] + rho * a.sin()];
        }
        let mut rule = RulePolicy::new(Method::Enclose);
        let mut buffers = crate::obs::EncoderBuffers::default();
        buffers.fill(&world);
        let mut features = [0.0f32; FEATURES];
        let mut compared = 0;
        for h in 0..world.herders.len() {
            let v = rule.act(&world, h);
            assert!(rule.pushed[h].is_none(), "herder {h} collects");
            let speed = v[0].hypot(v[1]);
            if speed < 1e-3 {
                continue; // already in its slot
            }
            let frame = buffers.encode(h, &mut features).unwrap();
            let way: [f32; 2] = features[feature::RING_WAY].try_into().unwrap();
            let way = frame.to_world(way);
            let way = [f64::from(way[0]), f64::from(way[1])];
            let cos = (v[0] * way[0] + v[1] * way[1]) / (speed * way[0].hypot(way[1]));
            assert!(cos > 0.9999, "herder {h}: rule {v:?}, encoder way {way:?}");
            compared += 1;
        }
        assert!(compared >= 10, "{compared} herders compared");
    }

    /// The reason the rule exists: with the adaptive 16 herders, 256 targets are driven into the
    /// goal, where the plain Strömbom rule (its driving arc never closes) fails.
    #[test]
    fn enclose_herds_256_targets_that_strombom_does_not() {
        let scenario = Scenario {
            targets: 256,
            herders: HerderCount::Adaptive,
            ..Scenario::paper_drive()
        };
        let mut env = Env::new(scenario).unwrap();
        let mut wins = |method: Method| {
            (0..3)
                .filter(|&seed| {
                    let mut policy = RulePolicy::new(method);
                    run_episode(&mut env, &mut policy, seed, |_, _| {})
                        .unwrap()
                        .success
                })
                .count()
        };
        let (enclose, strombom) = (wins(Method::Enclose), wins(Method::Strombom));
        assert!(enclose >= 2, "enclose herded {enclose} of 3");
        assert!(strombom < enclose, "strombom {strombom}, enclose {enclose}");
    }
}
