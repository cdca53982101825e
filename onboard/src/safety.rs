//! The last word before a velocity reaches the autopilot: speed and altitude limits, the
//! geofence, and holding when the world snapshot cannot be trusted. Pure: no clock, no state.
//!
//! Frame and units: simulator frame (x east, y north, z **up**), metres, seconds, m/s. Convert
//! to NED with [`crate::frame::sim_to_ned`] only after [`check`].
//!
//! Rules, in order (every rule that fires sets a bit in [`Reasons`]):
//! 1. **Invalid limits** (NaN, non-positive speeds, an empty fence): hold with zero velocity.
//! 2. **Hold** when the world snapshot is **stale** (`age` not in `0..=max_snapshot_age_s`,
//!    NaN included) or anything is **non-finite** (snapshot, own position, requested velocity):
//!    the requested velocity is dropped and replaced by zero.
//! 3. **Fence** (a box; z bounds are the altitude band), per axis, only with a finite position:
//!    outside a bound, the velocity along that axis points back in at least
//!    `return_speed`; inside, it is trimmed so that `position + velocity * lookahead_s` stays
//!    inside and, with [`Limits::braking`], so that a vehicle flying it can still stop before
//!    the bound (it needs `v * lag + v^2 / (2 a)`). Steering back in happens while holding too;
//!    steering out never happens.
//! 4. **Speed**: `|v_z| <= max_vertical_speed`, then `|v| <= max_speed`, by scaling, which keeps
//!    every component's sign and so never undoes rule 3's direction.
//!
//! ```
//! use skyherd_onboard::safety::{check, Limits, Reasons, Situation};
//! let limits = Limits::arena([500.0, 500.0, 10.0], 5.0);
//! // Below the altitude band, asked to fly down at 20 m/s on a stale snapshot:
//! let d = check(&limits, &Situation {
//!     position: [250.0, 250.0, 0.1], velocity: [0.0, 0.0, -20.0],
//!     snapshot_age_s: 3.0, snapshot_finite: true, current_velocity: None,
//! });
//! assert!(d.hold && d.reasons.contains(Reasons::STALE | Reasons::ALTITUDE));
//! assert!(d.velocity[2] > 0.0); // climbing back in, not down
//! ```

use core::fmt;
use core::ops::BitOr;

/// Why a [`Decision`] differs from the request: a set of flags.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Reasons(u8);

impl Reasons {
    /// Nothing fired: the request went through unchanged.
    pub const NONE: Reasons = Reasons(0);
    /// The world snapshot is older than allowed (or its age is unknown).
    pub const STALE: Reasons = Reasons(1);
    /// NaN or infinity in the snapshot, the own position or the requested velocity.
    pub const NON_FINITE: Reasons = Reasons(1 << 1);
    /// Outside the horizontal fence: steering back in.
    pub const OUTSIDE_FENCE: Reasons = Reasons(1 << 2);
    /// Inside the fence, but the request would have left it within the look-ahead: trimmed.
    pub const FENCE_LIMITED: Reasons = Reasons(1 << 3);
    /// Outside the altitude band (steering back) or about to leave it (trimmed).
    pub const ALTITUDE: Reasons = Reasons(1 << 4);
    /// Faster than the speed or vertical-speed limit: scaled down.
    pub const OVER_SPEED: Reasons = Reasons(1 << 5);
    /// The limits themselves are unusable: holding.
    pub const INVALID_LIMITS: Reasons = Reasons(1 << 6);

    const NAMES: [(Reasons, &'static str); 7] = [
        (Reasons::STALE, "stale snapshot"),
        (Reasons::NON_FINITE, "non-finite data"),
        (Reasons::OUTSIDE_FENCE, "outside fence"),
        (Reasons::FENCE_LIMITED, "fence limited"),
        (Reasons::ALTITUDE, "altitude"),
        (Reasons::OVER_SPEED, "over speed"),
        (Reasons::INVALID_LIMITS, "invalid limits"),
    ];

    /// Whether every flag of `other` is set.
    pub const fn contains(self, other: Reasons) -> bool {
        self.0 & other.0 == other.0
    }
    /// Whether no flag is set.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }
    /// The raw bits (for telemetry).
    pub const fn bits(self) -> u8 {
        self.0
    }
    fn insert(&mut self, other: Reasons) {
        self.0 |= other.0;
    }
}

impl BitOr for Reasons {
    type Output = Reasons;
    fn bitor(self, rhs: Reasons) -> Reasons {
        Reasons(self.0 | rhs.0)
    }
}

impl fmt::Display for Reasons {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.is_empty() {
            return f.write_str("ok");
        }
        let mut first = true;
        for (flag, name) in Reasons::NAMES {
            if self.contains(flag) {
                if !first {
                    f.write_str(", ")?;
                }
                f.write_str(name)?;
                first = false;
            }
        }
        Ok(())
    }
}

/// The rules' parameters. Simulator frame, metres, seconds, m/s.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// Largest 3-D speed, m/s.
    pub max_speed: f32,
    /// Largest vertical speed, m/s.
    pub max_vertical_speed: f32,
    /// Fence corner with the smallest x, y and the lowest allowed altitude.
    pub fence_min: [f32; 3],
    /// Fence corner with the largest x, y and the highest allowed altitude.
    pub fence_max: [f32; 3],
    /// Inside the fence, velocities are trimmed so that this many seconds of flight stay inside.
    pub lookahead_s: f32,
    /// Speed along an axis with which a drone outside a bound is steered back, m/s.
    pub return_speed: f32,
    /// Oldest usable world snapshot, seconds.
    pub max_snapshot_age_s: f32,
    /// How the vehicle brakes, when it does not fly its setpoint at once: the fence then keeps
    /// its stopping distance. `None`: the velocity is the setpoint (every earlier number).
    pub braking: Option<Braking>,
}

/// How a vehicle slows down: at most `deceleration`, after a delay of `lag_s` (its velocity
/// loop's lag and the time its jerk limit takes to reach that deceleration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Braking {
    /// m/s², > 0.
    pub deceleration: f32,
    /// s, >= 0.
    pub lag_s: f32,
}

impl Braking {
    /// The fastest speed, m/s, from which the vehicle stops within `distance` m: the root of
    /// `v * lag + v^2 / (2 a) = distance` (0 for no room).
    pub fn stopping_speed(&self, distance: f32) -> f32 {
        if distance <= 0.0 {
            return 0.0;
        }
        let (a, lag) = (self.deceleration, self.lag_s);
        a * (libm::sqrtf(lag * lag + 2.0 * distance / a) - lag)
    }

    /// Both numbers usable: a finite deceleration above 0 and a finite lag of 0 or more.
    pub fn is_valid(&self) -> bool {
        self.deceleration.is_finite()
            && self.deceleration > 0.0
            && self.lag_s.is_finite()
            && self.lag_s >= 0.0
    }
}

impl Limits {
    /// Limits for an arena `[0, W] x [0, H] x [0, ceiling]`: fence [`Limits::fence_margin`]
    /// inside the walls (1 m, less in a small room), altitude band 0.5 m above the ground to
    /// 0.5 m below the ceiling, vertical speed `min(max_speed, 2)` m/s, 1 s look-ahead, 1 m/s
    /// return speed, snapshots up to 1 s old.
    pub fn arena(area: [f32; 3], max_speed: f32) -> Limits {
        let margin = Limits::fence_margin(area);
        Limits {
            max_speed,
            max_vertical_speed: max_speed.min(2.0),
            fence_min: [margin, margin, 0.5],
            fence_max: [area[0] - margin, area[1] - margin, area[2] - 0.5],
            lookahead_s: 1.0,
            return_speed: 1.0,
            max_snapshot_age_s: 1.0,
            braking: None,
        }
    }

    /// How far inside the walls the fence runs: 1 m, but at most 1/40 of the narrower side. In
    /// the paper's 10 m room a 1 m margin would fence the drones out of the outer fifth of the
    /// floor, where the vehicles start (0.5 m from the walls) and must be got behind; 0.25 m
    /// keeps them off the walls without that.
    pub fn fence_margin(area: [f32; 3]) -> f32 {
        let narrower = area[0].min(area[1]);
        if narrower > 0.0 {
            (narrower / 40.0).min(1.0)
        } else {
            // No usable area (NaN, zero, negative): no margin; `is_valid` rejects the fence.
            0.0
        }
    }

    /// Whether the limits can be applied: finite, positive speeds and times, a non-empty fence.
    pub fn is_valid(&self) -> bool {
        let positive = |x: f32| x.is_finite() && x > 0.0;
        positive(self.max_speed)
            && positive(self.max_vertical_speed)
            && positive(self.lookahead_s)
            && positive(self.return_speed)
            && self.max_snapshot_age_s.is_finite()
            && self.max_snapshot_age_s >= 0.0
            && self.braking.is_none_or(|b| b.is_valid())
            && (0..3).all(|i| {
                self.fence_min[i].is_finite()
                    && self.fence_max[i].is_finite()
                    && self.fence_min[i] <= self.fence_max[i]
            })
    }
}

/// What the drone knows when it decides.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Situation {
    /// Own position, simulator frame, metres.
    pub position: [f32; 3],
    /// The requested velocity (the actor's, in m/s, simulator frame).
    pub velocity: [f32; 3],
    /// Age of the world snapshot the request was computed from, seconds.
    pub snapshot_age_s: f32,
    /// Whether every number in that snapshot is finite (see `wire::WorldSnapshot::is_finite`).
    pub snapshot_finite: bool,
    /// The velocity the vehicle flies now, m/s, when known (the autopilot's, or from its last
    /// positions). With [`Limits::braking`], a vehicle already too fast to stop before a bound
    /// is commanded to stop along that axis, not merely to slow to the stopping speed.
    pub current_velocity: Option<[f32; 3]>,
}

/// The velocity to fly and why it differs from the request.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Decision {
    /// Velocity to command, simulator frame, m/s; always finite.
    pub velocity: [f32; 3],
    /// The request was dropped (stale, non-finite or invalid limits).
    pub hold: bool,
    /// Every rule that fired.
    pub reasons: Reasons,
}

impl Decision {
    /// `|velocity|`, m/s.
    pub fn speed(&self) -> f32 {
        norm(self.velocity)
    }
}

fn norm(v: [f32; 3]) -> f32 {
    libm::sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
}

/// Applies the rules (see the module docs) to one request.
pub fn check(limits: &Limits, situation: &Situation) -> Decision {
    let mut reasons = Reasons::NONE;
    if !limits.is_valid() {
        log::warn!("safety: invalid limits, holding");
        return Decision {
            velocity: [0.0; 3],
            hold: true,
            reasons: Reasons::INVALID_LIMITS,
        };
    }
    let age = situation.snapshot_age_s;
    if !(0.0..=limits.max_snapshot_age_s).contains(&age) {
        reasons.insert(Reasons::STALE);
    }
    let position_finite = situation.position.iter().all(|x| x.is_finite());
    if !situation.snapshot_finite
        || !position_finite
        || !situation.velocity.iter().all(|x| x.is_finite())
    {
        reasons.insert(Reasons::NON_FINITE);
    }
    let hold = !reasons.is_empty();
    let mut v = if hold { [0.0; 3] } else { situation.velocity };

    if position_finite {
        // Indexes position, velocity and both fence corners in step.
        #[allow(clippy::needless_range_loop)]
        for axis in 0..3 {
            let (p, lo, hi) = (
                situation.position[axis],
                limits.fence_min[axis],
                limits.fence_max[axis],
            );
            let flag_out = if axis == 2 {
                Reasons::ALTITUDE
            } else {
                Reasons::OUTSIDE_FENCE
            };
            let flag_trim = if axis == 2 {
                Reasons::ALTITUDE
            } else {
                Reasons::FENCE_LIMITED
            };
            if p < lo {
                reasons.insert(flag_out);
                v[axis] = v[axis].max(limits.return_speed);
            } else if p > hi {
                reasons.insert(flag_out);
                v[axis] = v[axis].min(-limits.return_speed);
            } else {
                let (mut up, mut down) = (
                    (hi - p) / limits.lookahead_s,
                    -(p - lo) / limits.lookahead_s,
                );
                if let Some(b) = limits.braking {
                    let (stop_up, stop_down) = (b.stopping_speed(hi - p), b.stopping_speed(p - lo));
                    up = up.min(stop_up);
                    down = down.max(-stop_down);
                    // Already closing faster than it could stop from: brake now (a lagging
                    // vehicle follows a command that merely tapers down too late).
                    if let Some(current) = situation.current_velocity.map(|c| c[axis])
                        && current.is_finite()
                    {
                        if current > stop_up {
                            up = up.min(0.0);
                        }
                        if -current > stop_down {
                            down = down.max(0.0);
                        }
                    }
                }
                if v[axis] > up || v[axis] < down {
                    reasons.insert(flag_trim);
                    v[axis] = v[axis].clamp(down, up);
                }
            }
        }
    }

    if v[2].abs() > limits.max_vertical_speed {
        reasons.insert(Reasons::OVER_SPEED);
        let keep = limits.max_vertical_speed / v[2].abs();
        v = v.map(|x| x * keep);
    }
    let speed = norm(v);
    if speed > limits.max_speed {
        reasons.insert(Reasons::OVER_SPEED);
        let keep = limits.max_speed / speed;
        v = v.map(|x| x * keep);
    }
    if hold {
        log::debug!("safety: holding ({reasons})");
    }
    Decision {
        velocity: v,
        hold,
        reasons,
    }
}
