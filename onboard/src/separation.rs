//! Keeping drones apart: a decentralised rule each drone applies to its own velocity request,
//! from the other drones' positions and velocities. Pure, `no_std`, no allocation.
//!
//! Frame and units: simulator frame (x east, y north, z up), metres, m/s, seconds; 3-D.
//!
//! # The rule
//! Two drones at distance `d` (unit direction `n` from this one to the peer) may close on each
//! other at most `allowed = (d - r) / horizon` m/s, `r` the minimum separation; inside `r`
//! already, they must open at `escape_speed` at least (`allowed = -escape_speed`). As in ORCA
//! (van den Berg et al., reciprocal collision avoidance), each drone takes its `share` of the
//! correction relative to the *current* velocities: its new velocity `v` must satisfy
//!
//! ```text
//! v . n <= v_own . n + share (allowed - (v_own - v_peer) . n)
//! ```
//!
//! With `share` 1/2 on both sides the two half-spaces add up to `(v - v'_peer) . n <= allowed`,
//! so the distance shrinks by at most `(d - r) dt / horizon < d - r` in a tick of
//! `dt <= horizon`: it never falls below `r`. A request outside its half-space is moved onto
//! it, and as much again is added to the drone's right (horizontally, perpendicular to `n`):
//! two drones meeting symmetrically would otherwise slow down together and never pass. The
//! half-spaces are applied peer by peer in `passes` rounds; a request still outside one after
//! that is stopped.
//!
//! A peer whose position is older than `max_peer_age_s` may have moved: its separation grows by
//! `peer_speed_bound * age`, its velocity is taken as zero, and the drone takes the whole
//! correction (`share` 1), since it cannot count on the peer's half: `v . n <= allowed`.
//!
//! ```
//! use skyherd_onboard::separation::{separate, Peer, SeparationConfig};
//! let config = SeparationConfig::arena();
//! // Head-on at 5 m/s each, 10 m apart: the closing speed may be (10 - 3) / 2 = 3.5 m/s, so
//! // this drone's half leaves it 5 + (3.5 - 10) / 2 = 1.75 m/s towards the peer (and it veers
//! // right, to the south, by as much as it gave up).
//! let peer = Peer { position: [10.0, 0.0, 2.0], velocity: [-5.0, 0.0, 0.0], age_s: 0.0 };
//! let own = [0.0, 0.0, 2.0];
//! let out = separate(&config, own, [5.0, 0.0, 0.0], [5.0, 0.0, 0.0], &[peer]);
//! assert!(out.adjusted && (out.velocity[0] - 1.75).abs() < 1e-4);
//! assert!((out.velocity[1] + 3.25).abs() < 1e-4);
//! ```

use crate::safety::{Braking, Limits};

/// Another drone as this one knows it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Peer {
    /// Its position, m.
    pub position: [f32; 3],
    /// Its velocity, m/s (from its telemetry or two successive snapshots; zero if unknown).
    pub velocity: [f32; 3],
    /// How old that position is, s.
    pub age_s: f32,
}

/// The rule's parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SeparationConfig {
    /// The smallest 3-D distance two drones may come to, m.
    pub min_separation: f32,
    /// The closing speed is limited so that the separation holds for this long, s (at least
    /// one control period).
    pub horizon_s: f32,
    /// The share of a correction this drone takes against a fresh peer (0.5: reciprocal).
    pub share: f32,
    /// Inside the minimum separation, back away at least this fast, m/s.
    pub escape_speed: f32,
    /// Positions older than this are stale, s.
    pub max_peer_age_s: f32,
    /// How fast a stale peer may have moved since, m/s (its separation grows by this times
    /// its age).
    pub peer_speed_bound: f32,
    /// Rounds over the peers.
    pub passes: u8,
    /// How the vehicle answers a new velocity (`None`: at once): after `lag_s` (an
    /// autopilot's velocity lag plus its jerk ramp; `skyherd-onboard --braking`'s LAG), at
    /// `deceleration` at most. A pair closing at `c` keeps closing over the lag and over the
    /// age of the peer's position, and needs `c^2 / (2 a)` more to stop closing, `a` the
    /// deceleration of both drones against a fresh peer (each takes its half), of this one
    /// alone against a stale one: the gap the rule shares out shrinks by all of it first.
    pub braking: Option<Braking>,
    /// The altitude band the flight rules hold the drone in after this rule, `[floor,
    /// ceiling]` (z, m; `None`: no band). On (or within [`AT_BAND_EDGE_M`] of) its floor a
    /// drone cannot take the downward part of a correction, nor the upward part at its
    /// ceiling: the rule then takes that part horizontally, so the pair does not close by
    /// what the band takes away.
    pub altitude_band: Option<[f32; 2]>,
}

/// How near its floor or ceiling (m) the drone counts as on it, for
/// [`SeparationConfig::altitude_band`].
pub const AT_BAND_EDGE_M: f32 = 0.05;

impl SeparationConfig {
    /// The paper's arena: 3 m apart, 2 s horizon, 5 m/s herders.
    pub const fn arena() -> Self {
        Self {
            min_separation: 3.0,
            horizon_s: 2.0,
            share: 0.5,
            escape_speed: 1.0,
            max_peer_age_s: 0.5,
            peer_speed_bound: 5.0,
            passes: 3,
            braking: None,
            altitude_band: None,
        }
    }

    /// The indoor room: 0.5 m apart, 1 s horizon, 0.5 m/s herders.
    pub const fn room() -> Self {
        Self {
            min_separation: 0.5,
            horizon_s: 1.0,
            share: 0.5,
            escape_speed: 0.2,
            max_peer_age_s: 0.5,
            peer_speed_bound: 0.5,
            passes: 3,
            braking: None,
            altitude_band: None,
        }
    }

    /// The same rule for a drone the flight rules hold inside `limits`' altitude band
    /// ([`SeparationConfig::altitude_band`]).
    pub fn within(self, limits: &Limits) -> Self {
        Self {
            altitude_band: Some([limits.fence_min[2], limits.fence_max[2]]),
            ..self
        }
    }

    /// Keeping `min_separation` m from drones as fast as `peer_speed_bound` m/s: the room's
    /// horizon and escape for a separation of 1 m or less (small drones), else the arena's.
    pub fn keeping(min_separation: f32, peer_speed_bound: f32) -> Self {
        let base = if min_separation <= 1.0 {
            Self::room()
        } else {
            Self::arena()
        };
        Self {
            min_separation,
            peer_speed_bound,
            ..base
        }
    }
}

/// What the rule made of a request.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Separated {
    /// The velocity to fly, m/s.
    pub velocity: [f32; 3],
    /// Whether the request was changed.
    pub adjusted: bool,
    /// The nearest peer's distance, m (infinity with none).
    pub nearest_m: f32,
}

/// The rule applied to `request` (m/s) of the drone at `own` flying at `own_velocity` now,
/// against `peers`; see the module docs. Non-finite peers are skipped; a non-finite request,
/// position or velocity is returned as it is (the safety rules hold on it).
pub fn separate(
    config: &SeparationConfig,
    own: [f32; 3],
    own_velocity: [f32; 3],
    request: [f32; 3],
    peers: &[Peer],
) -> Separated {
    let mut v = request;
    let mut nearest_m = f32::INFINITY;
    let finite = |a: &[f32; 3]| a.iter().all(|x| x.is_finite());
    if !finite(&own) || !finite(&request) || !finite(&own_velocity) {
        return Separated {
            velocity: request,
            adjusted: false,
            nearest_m,
        };
    }
    let usable = |p: &&Peer| finite(&p.position) && finite(&p.velocity) && p.age_s.is_finite();
    let planes = |p: &Peer| half_space(config, own, own_velocity, p);
    for p in peers.iter().filter(usable) {
        nearest_m = nearest_m.min(norm(sub(p.position, own)));
    }
    // What the altitude band leaves of a vertical velocity here.
    let band = config
        .altitude_band
        .filter(|[lo, hi]| lo.is_finite() && hi.is_finite());
    let no_descent = band.is_some_and(|[lo, _]| own[2] <= lo + AT_BAND_EDGE_M);
    let no_climb = band.is_some_and(|[_, hi]| own[2] >= hi - AT_BAND_EDGE_M);
    // The band will take that much of the request anyway; the half-spaces must hold without it.
    if no_descent && v[2] < 0.0 || no_climb && v[2] > 0.0 {
        v[2] = 0.0;
    }
    let mut adjusted = false;
    for _ in 0..config.passes.max(1) {
        let mut changed = false;
        for p in peers.iter().filter(usable) {
            let (n, limit) = planes(p);
            let over = dot(v, n) - limit;
            if over > 1e-6 {
                // Onto the boundary, and as much again to the right of n.
                let right = [n[1], -n[0], 0.0];
                let right_norm = norm(right);
                v = sub(v, scale(n, over));
                // A vertical part the band would take away is made up horizontally
                // (`n_xy / |n_xy|^2` moves `v . n` as `n` does).
                if (no_descent && v[2] < 0.0 && n[2] > 0.0 || no_climb && v[2] > 0.0 && n[2] < 0.0)
                    && right_norm > 1e-3
                {
                    let lost = v[2] * n[2];
                    v[2] = 0.0;
                    v = add(
                        v,
                        scale([n[0], n[1], 0.0], lost / (right_norm * right_norm)),
                    );
                }
                if right_norm > 1e-6 {
                    v = add(v, scale(right, over / right_norm));
                    // The veer must not reopen this half-space (it is perpendicular to n only
                    // when n is horizontal).
                    let again = dot(v, n) - limit;
                    if again > 0.0 {
                        v = sub(v, scale(n, again));
                    }
                }
                changed = true;
            }
        }
        adjusted |= changed;
        if !changed {
            return Separated {
                velocity: v,
                adjusted,
                nearest_m,
            };
        }
    }
    // Still outside a half-space after the passes: stop.
    if peers.iter().filter(usable).any(|p| {
        let (n, limit) = planes(p);
        dot(v, n) > limit + 1e-4
    }) {
        v = [0.0; 3];
        adjusted = true;
    }
    Separated {
        velocity: v,
        adjusted,
        nearest_m,
    }
}

/// The half-space `v . n <= limit` this drone's velocity must keep to against `peer`.
fn half_space(
    config: &SeparationConfig,
    own: [f32; 3],
    own_velocity: [f32; 3],
    peer: &Peer,
) -> ([f32; 3], f32) {
    let rel = sub(peer.position, own);
    let d = norm(rel);
    let stale = peer.age_s > config.max_peer_age_s;
    let radius = if stale {
        // It may be anywhere within peer_speed_bound * age of where it was.
        config.min_separation + config.peer_speed_bound * peer.age_s.max(0.0)
    } else {
        config.min_separation
    };
    // Coincident drones: back off along an arbitrary but fixed direction.
    let n = if d > 1e-6 {
        scale(rel, 1.0 / d)
    } else {
        [1.0, 0.0, 0.0]
    };
    // A stale peer's old velocity is no use: it is taken as standing still.
    let closing = if stale {
        dot(own_velocity, n)
    } else {
        dot(sub(own_velocity, peer.velocity), n)
    };
    // What the pair closes before a new velocity takes hold: over the vehicle's lag, and over
    // the age of a fresh peer's position (it has been closing since; a stale one's growing
    // radius already covers its age).
    let braking = config.braking.filter(Braking::is_valid);
    let lag = braking.map_or(0.0, |b| b.lag_s) + if stale { 0.0 } else { peer.age_s.max(0.0) };
    let closing_now = closing.max(0.0);
    // Both drones brake on a fresh peer's half-space; against a stale one, only this one.
    let to_stop = braking.map_or(0.0, |b| {
        let both = if stale { 1.0 } else { 2.0 } * b.deceleration;
        closing_now * closing_now / (2.0 * both)
    });
    let gap = d - radius - closing_now * lag - to_stop;
    let allowed = if d < radius || gap < 0.0 {
        -config.escape_speed.max(0.0)
    } else {
        gap / config.horizon_s.max(1e-3)
    };
    if stale {
        // No help from the peer: all of the correction is ours.
        return (n, allowed);
    }
    let share = config.share.clamp(1e-3, 1.0);
    (n, dot(own_velocity, n) + share * (allowed - closing))
}

fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scale(a: [f32; 3], k: f32) -> [f32; 3] {
    [a[0] * k, a[1] * k, a[2] * k]
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f32; 3]) -> f32 {
    libm::sqrtf(dot(a, a))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    /// Fly drones with constant requests through the rule for `seconds`; the smallest
    /// pairwise distance seen.
    fn fly(
        config: &SeparationConfig,
        start: &[[f32; 3]],
        requests: &[[f32; 3]],
        seconds: f32,
        dt: f32,
    ) -> (f32, Vec<[f32; 3]>) {
        let mut pos = start.to_vec();
        let mut vel = vec![[0.0f32; 3]; start.len()];
        let mut min = f32::INFINITY;
        for _ in 0..(seconds / dt) as usize {
            let mut next = vel.clone();
            for i in 0..pos.len() {
                let mut peers = [Peer {
                    position: [0.0; 3],
                    velocity: [0.0; 3],
                    age_s: 0.0,
                }; 8];
                let mut k = 0;
                for j in (0..pos.len()).filter(|&j| j != i) {
                    peers[k] = Peer {
                        position: pos[j],
                        velocity: vel[j],
                        age_s: 0.0,
                    };
                    k += 1;
                }
                next[i] = separate(config, pos[i], vel[i], requests[i], &peers[..k]).velocity;
            }
            vel = next;
            for (p, v) in pos.iter_mut().zip(&vel) {
                *p = [p[0] + v[0] * dt, p[1] + v[1] * dt, p[2] + v[2] * dt];
            }
            for i in 0..pos.len() {
                for j in i + 1..pos.len() {
                    min = min.min(norm(sub(pos[i], pos[j])));
                }
            }
        }
        (min, pos)
    }

    /// Drones that decide every `dt` seconds and reach the rule's velocity through a
    /// first-order lag of `tau` seconds, flown in 10 ms sub-steps; they start at their
    /// requests' velocity and the rule sees what they fly. The smallest distance seen.
    fn fly_lagging(
        config: &SeparationConfig,
        start: &[[f32; 3]],
        requests: &[[f32; 3]],
        seconds: f32,
        dt: f32,
        tau: f32,
    ) -> (f32, Vec<[f32; 3]>) {
        let mut pos = start.to_vec();
        let mut vel = requests.to_vec();
        let mut min = f32::INFINITY;
        let h = 0.01f32;
        let subs = (dt / h).round() as usize;
        for _ in 0..(seconds / dt) as usize {
            let mut command = vel.clone();
            for i in 0..pos.len() {
                let peers: Vec<Peer> = (0..pos.len())
                    .filter(|&j| j != i)
                    .map(|j| Peer {
                        position: pos[j],
                        velocity: vel[j],
                        age_s: 0.0,
                    })
                    .collect();
                command[i] = separate(config, pos[i], vel[i], requests[i], &peers).velocity;
            }
            for _ in 0..subs {
                for ((p, v), c) in pos.iter_mut().zip(vel.iter_mut()).zip(&command) {
                    *v = core::array::from_fn(|a| v[a] + (c[a] - v[a]) * (h / tau));
                    *p = core::array::from_fn(|a| p[a] + v[a] * h);
                }
                for i in 0..pos.len() {
                    for j in i + 1..pos.len() {
                        min = min.min(norm(sub(pos[i], pos[j])));
                    }
                }
            }
        }
        (min, pos)
    }

    /// A drone on the altitude floor with a peer closing on it from above and to the side:
    /// its share of the correction points partly down, which the flight rules' band takes
    /// away after the rule. Unaware of the band, what is left after that clamp breaks the
    /// half-space (the pair closes faster than allowed); told of it, the rule flies no
    /// descent and makes the vertical part up sideways, inside the same half-space.
    #[test]
    fn on_the_floor_the_rule_takes_its_share_sideways_when_it_knows_the_band() {
        const FLOOR: f32 = 0.5;
        let own = [0.0f32, 0.0, FLOOR];
        let peer = Peer {
            position: [0.4, 0.0, 0.8],
            velocity: [0.0, 0.0, -0.4],
            age_s: 0.0,
        };
        let own_velocity = [0.2f32, 0.0, 0.0];
        let request = [0.3f32, 0.0, 0.0];
        let config = SeparationConfig::room();
        let (n, limit) = half_space(&config, own, own_velocity, &peer);
        assert!(n[2] > 0.3, "the peer is above: {n:?}");
        let clamped = |mut v: [f32; 3]| {
            v[2] = v[2].max(0.0);
            v
        };
        let unaware = separate(&config, own, own_velocity, request, &[peer]).velocity;
        assert!(unaware[2] < -0.01, "{unaware:?}");
        assert!(dot(clamped(unaware), n) > limit + 0.01, "{unaware:?}");
        let banded = SeparationConfig {
            altitude_band: Some([FLOOR, 2.5]),
            ..config
        };
        let aware = separate(&banded, own, own_velocity, request, &[peer]).velocity;
        assert!(aware[2] >= 0.0, "{aware:?}");
        assert!(dot(aware, n) <= limit + 1e-4, "{aware:?}");
        // Off the floor the band changes nothing.
        let high = [0.0f32, 0.0, 1.2];
        let high_peer = Peer {
            position: [0.4, 0.0, 1.5],
            ..peer
        };
        assert_eq!(
            separate(&banded, high, own_velocity, request, &[high_peer]),
            separate(&config, high, own_velocity, request, &[high_peer]),
        );
    }

    #[test]
    fn head_on_drones_keep_the_separation_and_pass_on_the_right() {
        let config = SeparationConfig::arena();
        let (min, pos) = fly(
            &config,
            &[[0.0, 0.0, 2.0], [20.0, 0.0, 2.0]],
            &[[5.0, 0.0, 0.0], [-5.0, 0.0, 0.0]],
            20.0,
            0.1,
        );
        assert!(min >= config.min_separation - 1e-3, "{min}");
        assert!(
            min < 4.0 * config.min_separation,
            "no wider berth than needed: {min}"
        );
        // They got past each other, each keeping to its right (south for the eastbound one).
        assert!(pos[0][0] > pos[1][0], "{pos:?}");
        assert!(pos[0][1] < pos[1][1], "{pos:?}");
    }

    #[test]
    fn lagging_drones_keep_the_separation_only_when_the_rule_counts_the_lag() {
        // The simulator's 1 s decisions with vehicles that take about 2 s to answer (PX4's
        // jerk-limited mission trajectory turning 5 m/s round, `px4-auto`): drones crossing at
        // 5 m/s each, the rule that assumes an instant answer lets the pair into the
        // separation, the one that counts the lag does not.
        let start = [[0.0, 0.0, 2.0], [20.0, -20.0, 2.0]];
        let requests = [[5.0, 0.0, 0.0], [0.0, 5.0, 0.0]];
        let tau = 2.0;
        let instant = SeparationConfig::arena();
        let (min, _) = fly_lagging(&instant, &start, &requests, 12.0, 1.0, tau);
        assert!(min < instant.min_separation, "{min}");
        let lagging = SeparationConfig {
            braking: Some(Braking {
                deceleration: 3.0,
                lag_s: tau,
            }),
            ..instant
        };
        let (min, pos) = fly_lagging(&lagging, &start, &requests, 12.0, 1.0, tau);
        assert!(min >= lagging.min_separation - 1e-3, "{min}");
        assert!(
            pos[0][0] > 20.0 && pos[1][1] > 0.0,
            "they still get past: {pos:?}"
        );
        // Drones that answer at once see no difference.
        let (a, _) = fly(&instant, &start, &requests, 12.0, 0.1);
        let (b, _) = fly(&lagging, &start, &requests, 12.0, 0.1);
        assert!((a - b).abs() < 1e-3 || b > a, "{a} {b}");
    }

    #[test]
    fn crossing_drones_keep_their_distance_and_get_past() {
        let config = SeparationConfig::arena();
        // Paths cross at (10, 10); both would arrive there at the same moment.
        let (min, pos) = fly(
            &config,
            &[[0.0, 10.0, 2.0], [10.0, 0.0, 2.0]],
            &[[5.0, 0.0, 0.0], [0.0, 5.0, 0.0]],
            8.0,
            0.1,
        );
        assert!(min >= config.min_separation - 1e-3, "{min}");
        assert!(
            pos[0][0] > 15.0 && pos[1][1] > 15.0,
            "both got past: {pos:?}"
        );
    }

    #[test]
    fn three_drones_converging_on_one_point_keep_apart() {
        let config = SeparationConfig::room();
        let c = [5.0, 5.0, 1.0];
        let start = [[2.0, 5.0, 1.0], [6.5, 7.6, 1.0], [6.5, 2.4, 1.0]];
        let requests: Vec<[f32; 3]> = start
            .iter()
            .map(|p| {
                let d = sub(c, *p);
                scale(d, 0.5 / norm(d))
            })
            .collect();
        let (min, _) = fly(&config, &start, &requests, 20.0, 0.1);
        assert!(min >= config.min_separation - 1e-3, "{min}");
    }

    #[test]
    fn a_stale_peer_is_given_a_wider_berth_and_no_share() {
        let config = SeparationConfig::arena();
        let own = [0.0, 0.0, 2.0];
        let fresh = Peer {
            position: [8.0, 0.0, 2.0],
            velocity: [0.0; 3],
            age_s: 0.0,
        };
        let stale = Peer {
            age_s: 1.0,
            ..fresh
        };
        let request = [5.0, 0.0, 0.0];
        let a = separate(&config, own, request, request, &[fresh]);
        let b = separate(&config, own, request, request, &[stale]);
        // Fresh: closing allowed (8 - 3) / 2 = 2.5, half of the excess 2.5 taken: 3.75 m/s.
        assert!((a.velocity[0] - 3.75).abs() < 1e-4, "{a:?}");
        // Stale by 1 s at up to 5 m/s: radius 8 m, so no closing at all, and all of it ours.
        assert!(b.velocity[0].abs() < 1e-4, "{b:?}");
        // Moving away from a stale peer is fine.
        let away = separate(&config, own, [-5.0, 0.0, 0.0], [-5.0, 0.0, 0.0], &[stale]);
        assert!(!away.adjusted);
    }

    #[test]
    fn inside_the_separation_a_drone_backs_away_and_bad_input_changes_nothing() {
        let config = SeparationConfig::arena();
        let peer = Peer {
            position: [1.0, 0.0, 2.0],
            velocity: [0.0; 3],
            age_s: 0.0,
        };
        let out = separate(&config, [0.0, 0.0, 2.0], [0.0; 3], [0.0; 3], &[peer]);
        // Half of the escape, the peer (running the rule) takes the other half.
        assert!(
            out.adjusted && out.velocity[0] <= -config.escape_speed / 2.0 + 1e-4,
            "{out:?}"
        );
        assert_eq!(out.nearest_m, 1.0);
        // Coincident: still a direction to back off in, and finite.
        let on_top = Peer {
            position: [0.0, 0.0, 2.0],
            ..peer
        };
        let out = separate(&config, [0.0, 0.0, 2.0], [0.0; 3], [0.0; 3], &[on_top]);
        assert!(out.velocity.iter().all(|v| v.is_finite()) && out.adjusted);
        // Non-finite peers are skipped; a non-finite request passes through untouched.
        let broken = Peer {
            position: [f32::NAN, 0.0, 0.0],
            ..peer
        };
        let out = separate(
            &config,
            [0.0, 0.0, 2.0],
            [0.0; 3],
            [1.0, 0.0, 0.0],
            &[broken],
        );
        assert!(!out.adjusted && out.nearest_m.is_infinite());
        let out = separate(
            &config,
            [0.0, 0.0, 2.0],
            [0.0; 3],
            [f32::NAN, 0.0, 0.0],
            &[peer],
        );
        assert!(!out.adjusted && out.velocity[0].is_nan());
        // No peers: nothing to do.
        assert!(!separate(&config, [0.0; 3], [0.0; 3], [3.0, 0.0, 0.0], &[]).adjusted);
    }
}
