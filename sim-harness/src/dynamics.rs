//! How a multicopter follows a velocity command: a pure model of the autopilot's velocity
//! control and the airframe, and the wind that pushes it.
//!
//! Frame and units: the simulator's (x east, y north, z **up**), metres, m/s, m/s^2, m/s^3,
//! seconds. Everything takes explicit state and a time step; nothing reads a clock.
//!
//! # The model
//! Each step of `dt`:
//! 1. The command is clamped to the speed limits: horizontal norm `max_speed_horizontal`,
//!    vertical `[-max_speed_down, max_speed_up]`.
//! 2. The controller asks for the acceleration that closes the velocity error in `time_constant`
//!    seconds (a first-order lag), clamped to `max_accel_horizontal` (norm) and
//!    `[-max_accel_down, max_accel_up]`, then rate-limited by `max_jerk` (norm of the change per
//!    second), as PX4's jerk-limited trajectory shapes its setpoints.
//! 3. The wind adds `drag * wind`, after the limits: the controller is taken to cancel the
//!    airframe's own drag in still air, and what the wind adds is the disturbance its lag lets
//!    through (a steady wind `w` leaves a drift of `time_constant * drag * w`; a gust can push
//!    a drone beyond what its controller would ask).
//! 4. Velocity and position integrate (semi-implicit Euler); a drone on the ground (`z <= 0`)
//!    stays there and loses its downward velocity.
//!
//! # The presets
//! How a multicopter answers a velocity setpoint depends on the autopilot's mode, so there are
//! two PX4 sets (values from PX4-Autopilot's parameter definitions,
//! `src/modules/mc_pos_control/*_params.yaml` and `mc_att_control_params.c`):
//!
//! * [`DynamicsLimits::px4`]: **Offboard** velocity setpoints, which is how the daemon flies.
//!   PX4 feeds them straight to its velocity controller (`PositionControl::_velocityControl`):
//!   `MPC_ACC_HOR` and `MPC_JERK_*` shape only PX4's own position-mode and mission
//!   trajectories, not Offboard setpoints (PX4-Autopilot issue #27612; pull request #20323, a
//!   jerk limit in the controller, was turned down). What bounds the response is the velocity
//!   loop, the tilt limit and the attitude loop:
//!
//! | field | from | value |
//! |---|---|---|
//! | `time_constant` | 1 / `MPC_XY_VEL_P_ACC` (1.8 /s) | 0.55 s |
//! | `max_accel_horizontal` | g tan(`MPC_TILTMAX_AIR` = 45 deg) | 9.8 m/s^2 |
//! | `max_accel_up` | g (`MPC_THR_MAX` / `MPC_THR_HOVER` - 1) = g (1 / 0.5 - 1) | 9.8 m/s^2 |
//! | `max_accel_down` | g (1 - `MPC_THR_MIN` / `MPC_THR_HOVER`) = g (1 - 0.12 / 0.5) | 7.5 m/s^2 |
//! | `max_jerk` | the tilt follows the attitude loop in 1 / `MC_ROLL_P` (6.5) = 0.15 s: 9.8 / 0.15 | 65 m/s^3 |
//! | `max_speed_horizontal` | `MPC_XY_VEL_MAX` | 12.0 m/s |
//! | `max_speed_up` / `max_speed_down` | `MPC_Z_VEL_MAX_UP` / `MPC_Z_VEL_MAX_DN` | 3.0 / 1.5 m/s |
//! | `takeoff_speed` / `land_speed` | `MPC_TKO_SPEED` / `MPC_LAND_SPEED` | 1.5 / 0.7 m/s |
//!
//! * [`DynamicsLimits::px4_auto`]: PX4's jerk-limited trajectory of its position and mission
//!   modes, applied to every setpoint: a harsher stand-in for an autopilot that smooths
//!   velocity commands (ArduCopter's Guided mode shapes them too):
//!
//! | field | PX4 parameter | default |
//! |---|---|---|
//! | `max_accel_horizontal` | `MPC_ACC_HOR` (multicopter_autonomous_params) | 3.0 m/s^2 |
//! | `max_accel_up` | `MPC_ACC_UP_MAX` (multicopter_altitude_mode_params) | 4.0 m/s^2 |
//! | `max_accel_down` | `MPC_ACC_DOWN_MAX` (multicopter_altitude_mode_params) | 3.0 m/s^2 |
//! | `max_jerk` | `MPC_JERK_AUTO` (multicopter_autonomous_params) | 4.0 m/s^3 |
//!
//!   with the Offboard set's speeds, a 0.3 s lag and the same takeoff and landing rates.
//!
//! * [`DynamicsLimits::indoor`]: the room's drones, PX4 in Offboard as above, with the room's
//!   speed caps (1 m/s across, 0.5 m/s up and down) and a cautious indoor tilt limit of 20 deg.
//!
//! The drag (0.2 /s) is not a PX4 parameter: it stands for a small quadrotor's linear drag.
//!
//! ```
//! use skyherd_sim::dynamics::{DynamicsLimits, Multicopter};
//! let limits = DynamicsLimits::px4();
//! let mut drone = Multicopter::hovering_at([0.0, 0.0, 2.0]);
//! // Asked for 5 m/s east from a hover, a drone does not get there in one step.
//! drone.step([5.0, 0.0, 0.0], [0.0; 3], &limits, 0.1);
//! assert!(drone.velocity[0] > 0.0 && drone.velocity[0] < 1.0);
//! for _ in 0..100 {
//!     drone.step([5.0, 0.0, 0.0], [0.0; 3], &limits, 0.1);
//! }
//! assert!((drone.velocity[0] - 5.0).abs() < 0.05);
//! ```

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// What limits a multicopter's motion. Metres, seconds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamicsLimits {
    /// Largest horizontal acceleration the controller asks for, m/s^2.
    pub max_accel_horizontal: f64,
    /// Largest upward acceleration, m/s^2.
    pub max_accel_up: f64,
    /// Largest downward acceleration, m/s^2.
    pub max_accel_down: f64,
    /// Largest rate of change of the asked acceleration (norm), m/s^3.
    pub max_jerk: f64,
    /// Horizontal speed limit, m/s.
    pub max_speed_horizontal: f64,
    /// Climb rate limit, m/s.
    pub max_speed_up: f64,
    /// Descent rate limit, m/s.
    pub max_speed_down: f64,
    /// The velocity loop closes an error in about this long, s.
    pub time_constant: f64,
    /// How strongly the wind pushes: `drag * wind` is the disturbance acceleration, 1/s.
    pub drag: f64,
    /// Climb rate of a takeoff, m/s.
    pub takeoff_speed: f64,
    /// Descent rate of a landing, m/s.
    pub land_speed: f64,
}

impl DynamicsLimits {
    /// PX4 flying Offboard velocity setpoints (see the module docs for where each value
    /// comes from).
    pub const fn px4() -> Self {
        Self {
            max_accel_horizontal: 9.8,
            max_accel_up: 9.8,
            max_accel_down: 7.5,
            max_jerk: 65.0,
            max_speed_horizontal: 12.0,
            max_speed_up: 3.0,
            max_speed_down: 1.5,
            time_constant: 0.55,
            drag: 0.2,
            takeoff_speed: 1.5,
            land_speed: 0.7,
        }
    }

    /// PX4's jerk-limited position-mode and mission trajectory limits applied to every
    /// setpoint (`MPC_ACC_HOR`, `MPC_ACC_UP_MAX`, `MPC_ACC_DOWN_MAX`, `MPC_JERK_AUTO`): how an
    /// autopilot that smooths velocity commands flies them.
    pub const fn px4_auto() -> Self {
        Self {
            max_accel_horizontal: 3.0,
            max_accel_up: 4.0,
            max_accel_down: 3.0,
            max_jerk: 4.0,
            time_constant: 0.3,
            ..Self::px4()
        }
    }

    /// The indoor room's drones: PX4 in Offboard with the room's speed caps (1 m/s across,
    /// 0.5 m/s up and down, as the preset's 1 m/s herders), a 20 deg tilt limit (g tan 20 deg
    /// = 3.6 m/s^2, the jerk bound scaled with it) and gentle takeoff and landing.
    pub const fn indoor() -> Self {
        Self {
            max_accel_horizontal: 3.6,
            max_accel_up: 3.0,
            max_accel_down: 2.0,
            max_jerk: 24.0,
            max_speed_horizontal: 1.0,
            max_speed_up: 0.5,
            max_speed_down: 0.5,
            time_constant: 0.55,
            drag: 0.2,
            takeoff_speed: 0.3,
            land_speed: 0.2,
        }
    }

    /// How long a new horizontal velocity takes to take hold from a steady flight, s: the lag
    /// plus the time the jerk limit needs to reach full acceleration (what a separation rule
    /// must count; braking from full speed takes twice the ramp).
    pub fn response_lag_s(&self) -> f64 {
        self.time_constant + self.max_accel_horizontal / self.max_jerk
    }

    /// Every field finite and positive: on failure, the field's name.
    pub fn validate(&self) -> Result<(), &'static str> {
        let fields = [
            ("max_accel_horizontal", self.max_accel_horizontal),
            ("max_accel_up", self.max_accel_up),
            ("max_accel_down", self.max_accel_down),
            ("max_jerk", self.max_jerk),
            ("max_speed_horizontal", self.max_speed_horizontal),
            ("max_speed_up", self.max_speed_up),
            ("max_speed_down", self.max_speed_down),
            ("time_constant", self.time_constant),
            ("takeoff_speed", self.takeoff_speed),
            ("land_speed", self.land_speed),
        ];
        for (name, v) in fields {
            if !(v.is_finite() && v > 0.0) {
                return Err(name);
            }
        }
        if !(self.drag.is_finite() && self.drag >= 0.0) {
            return Err("drag");
        }
        Ok(())
    }
}

/// One multicopter's motion state. Simulator frame, z up.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Multicopter {
    /// Position, m.
    pub position: [f64; 3],
    /// Velocity over the ground, m/s.
    pub velocity: [f64; 3],
    /// The acceleration the controller asked for last step (before the wind), m/s^2.
    pub commanded_accel: [f64; 3],
}

impl Multicopter {
    /// At rest at `position`.
    pub const fn hovering_at(position: [f64; 3]) -> Self {
        Self {
            position,
            velocity: [0.0; 3],
            commanded_accel: [0.0; 3],
        }
    }

    /// One step of `dt` seconds towards `command` (m/s) in `wind` (m/s); see the module docs.
    /// A non-finite or non-positive `dt`, or a non-finite command, leaves the state as it is.
    pub fn step(&mut self, command: [f64; 3], wind: [f64; 3], limits: &DynamicsLimits, dt: f64) {
        if !(dt.is_finite() && dt > 0.0 && command.iter().all(|c| c.is_finite())) {
            return;
        }
        // 1. Speed limits.
        let mut target = command;
        scale_horizontal(&mut target, limits.max_speed_horizontal);
        target[2] = target[2].clamp(-limits.max_speed_down, limits.max_speed_up);
        // 2. First-order lag, acceleration limits, jerk limit.
        let tau = limits.time_constant.max(dt);
        let mut accel: [f64; 3] = std::array::from_fn(|k| (target[k] - self.velocity[k]) / tau);
        scale_horizontal(&mut accel, limits.max_accel_horizontal);
        accel[2] = accel[2].clamp(-limits.max_accel_down, limits.max_accel_up);
        let mut change: [f64; 3] = std::array::from_fn(|k| accel[k] - self.commanded_accel[k]);
        let norm = norm3(change);
        let max_change = limits.max_jerk * dt;
        if norm > max_change {
            change.iter_mut().for_each(|c| *c *= max_change / norm);
        }
        for (a, c) in self.commanded_accel.iter_mut().zip(change) {
            *a += c;
        }
        // 3. Wind, after the limits (a non-finite wind pushes nothing).
        let push = if wind.iter().all(|w| w.is_finite()) {
            wind.map(|w| limits.drag * w)
        } else {
            [0.0; 3]
        };
        // 4. Semi-implicit Euler.
        for (k, push) in push.into_iter().enumerate() {
            self.velocity[k] += (self.commanded_accel[k] + push) * dt;
            self.position[k] += self.velocity[k] * dt;
        }
        if self.position[2] <= 0.0 {
            self.position[2] = 0.0;
            self.velocity[2] = self.velocity[2].max(0.0);
            self.commanded_accel[2] = self.commanded_accel[2].max(0.0);
        }
    }

    /// The distance this drone needs to stop horizontally from its present speed under
    /// `limits`, m: what a fence margin must leave room for.
    pub fn stopping_distance(&self, limits: &DynamicsLimits) -> f64 {
        let v = self.velocity[0].hypot(self.velocity[1]);
        v * v / (2.0 * limits.max_accel_horizontal)
    }
}

fn norm3(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn scale_horizontal(v: &mut [f64; 3], max: f64) {
    let h = v[0].hypot(v[1]);
    if h > max && h > 0.0 {
        v[0] *= max / h;
        v[1] *= max / h;
    }
}

/// The wind: a mean plus gusts, each axis an Ornstein-Uhlenbeck process (a first-order
/// Gauss-Markov process, the simplest stand-in for the Dryden model's low-frequency gusts).
/// Seeded through the caller's random number generator, so a run is reproducible.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WindConfig {
    /// Mean wind, m/s (simulator frame; usually horizontal).
    pub mean: [f64; 3],
    /// Stationary standard deviation of the gusts per axis, m/s.
    pub gust_std: f64,
    /// Correlation time of the gusts, s.
    pub gust_time: f64,
}

impl WindConfig {
    /// Still air.
    pub const CALM: WindConfig = WindConfig {
        mean: [0.0; 3],
        gust_std: 0.0,
        gust_time: 1.0,
    };

    /// The arena's default: 3 m/s from the west with 1 m/s gusts over 2 s (a light breeze).
    pub const fn arena() -> Self {
        Self {
            mean: [3.0, 0.0, 0.0],
            gust_std: 1.0,
            gust_time: 2.0,
        }
    }

    /// The room's default: still air but for 0.05 m/s draughts over 2 s (an indoor hall).
    pub const fn room() -> Self {
        Self {
            mean: [0.0; 3],
            gust_std: 0.05,
            gust_time: 2.0,
        }
    }

    /// What a usable wind is: a mean within 100 m/s, gusts of 0-50 m/s over a positive time
    /// (NaN never is). On failure, that sentence, for the caller's error.
    pub fn validate(&self) -> Result<(), &'static str> {
        let usable = self.mean.iter().all(|c| c.is_finite() && c.abs() <= 100.0)
            && self.gust_std.is_finite()
            && (0.0..=50.0).contains(&self.gust_std)
            && self.gust_time.is_finite()
            && self.gust_time > 0.0;
        if usable {
            Ok(())
        } else {
            Err("mean within 100 m/s, gusts 0-50 m/s over a positive time")
        }
    }
}

/// The wind's state: its gust part per axis.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Wind {
    /// The gusts now, m/s.
    pub gust: [f64; 3],
}

impl Wind {
    /// A stationary start: gusts drawn from the process's own distribution.
    pub fn new<R: Rng>(config: &WindConfig, rng: &mut R) -> Self {
        let mut gust = [0.0; 3];
        for g in &mut gust {
            let e: f64 = StandardNormal.sample(rng);
            *g = config.gust_std * e;
        }
        Self { gust }
    }

    /// Advance `dt` seconds; returns the wind velocity now (mean plus gusts), m/s. The exact
    /// discretisation `x <- a x + sigma sqrt(1 - a^2) e`, `a = exp(-dt / T)`, keeps the gusts'
    /// variance at `gust_std^2` whatever the step.
    pub fn step<R: Rng>(&mut self, config: &WindConfig, dt: f64, rng: &mut R) -> [f64; 3] {
        if dt.is_finite() && dt > 0.0 && config.gust_std > 0.0 && config.gust_time > 0.0 {
            let a = (-dt / config.gust_time).exp();
            let s = config.gust_std * (1.0 - a * a).sqrt();
            for g in &mut self.gust {
                let e: f64 = StandardNormal.sample(rng);
                *g = a * *g + s * e;
            }
        }
        self.velocity(config)
    }

    /// The wind velocity now, m/s.
    pub fn velocity(&self, config: &WindConfig) -> [f64; 3] {
        [
            config.mean[0] + self.gust[0],
            config.mean[1] + self.gust[1],
            config.mean[2] + self.gust[2],
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn run(
        drone: &mut Multicopter,
        command: [f64; 3],
        limits: &DynamicsLimits,
        seconds: f64,
        dt: f64,
    ) -> Vec<Multicopter> {
        (0..(seconds / dt).round() as usize)
            .map(|_| {
                drone.step(command, [0.0; 3], limits, dt);
                *drone
            })
            .collect()
    }

    #[test]
    fn a_step_response_respects_the_acceleration_and_jerk_limits() {
        let limits = DynamicsLimits::px4_auto();
        let dt = 0.01;
        let mut drone = Multicopter::hovering_at([0.0, 0.0, 5.0]);
        let trace = run(&mut drone, [10.0, 0.0, 0.0], &limits, 10.0, dt);
        let mut previous = Multicopter::hovering_at([0.0, 0.0, 5.0]);
        for s in &trace {
            let accel = (s.velocity[0] - previous.velocity[0]) / dt;
            assert!(accel <= limits.max_accel_horizontal + 1e-9, "{accel}");
            let jerk = (s.commanded_accel[0] - previous.commanded_accel[0]).abs() / dt;
            assert!(jerk <= limits.max_jerk + 1e-9, "{jerk}");
            previous = *s;
        }
        // The jerk limit makes the first second slower than the acceleration limit alone:
        // 4 m/s^3 for 0.75 s reaches 3 m/s^2, so v(1 s) is about 1.9 m/s, not 3.
        let at_1s = trace[99].velocity[0];
        assert!(at_1s > 1.5 && at_1s < 2.3, "{at_1s}");
        // It settles on the command, without overshooting it by more than a little.
        assert!((trace.last().unwrap().velocity[0] - 10.0).abs() < 0.01);
        let peak = trace.iter().map(|s| s.velocity[0]).fold(0.0, f64::max);
        assert!(peak < 10.3, "overshoot to {peak}");
    }

    #[test]
    fn offboard_setpoints_follow_the_velocity_loop_lag() {
        let limits = DynamicsLimits::px4();
        let dt = 0.01;
        let mut drone = Multicopter::hovering_at([0.0, 0.0, 5.0]);
        let trace = run(&mut drone, [1.0, 0.0, 0.0], &limits, 5.0, dt);
        // A first-order lag of 1 / MPC_XY_VEL_P_ACC: about 1 - 1/e of the step after 0.55 s
        // (the attitude loop's jerk bound costs a few hundredths), all of it after 5 lags.
        let at_tau = trace[54].velocity[0];
        assert!(at_tau > 0.58 && at_tau < 0.64, "{at_tau}");
        assert!((trace.last().unwrap().velocity[0] - 1.0).abs() < 1e-3);
        // A 10 m/s step asks for more than the tilt gives: 9.8 m/s^2 at most, the jerk within
        // the attitude loop's 65 m/s^3.
        let mut fast = Multicopter::hovering_at([0.0, 0.0, 5.0]);
        let trace = run(&mut fast, [10.0, 0.0, 0.0], &limits, 3.0, dt);
        let mut previous = Multicopter::hovering_at([0.0, 0.0, 5.0]);
        let mut peak = 0.0f64;
        for s in &trace {
            let accel = (s.velocity[0] - previous.velocity[0]) / dt;
            peak = peak.max(accel);
            let jerk = (s.commanded_accel[0] - previous.commanded_accel[0]).abs() / dt;
            assert!(jerk <= limits.max_jerk + 1e-9, "{jerk}");
            previous = *s;
        }
        assert!((peak - 9.8).abs() < 1e-6, "{peak}");
        // The room's drones reach their 1 m/s cap within 2 s.
        let mut room = Multicopter::hovering_at([0.0, 0.0, 1.0]);
        let trace = run(
            &mut room,
            [3.0, 0.0, 0.0],
            &DynamicsLimits::indoor(),
            2.0,
            dt,
        );
        assert!((trace.last().unwrap().velocity[0] - 1.0).abs() < 0.03);
    }

    #[test]
    fn speed_limits_clamp_the_command_horizontally_and_vertically() {
        let limits = DynamicsLimits::px4();
        let mut drone = Multicopter::hovering_at([0.0, 0.0, 50.0]);
        run(&mut drone, [20.0, 20.0, -9.0], &limits, 30.0, 0.05);
        let h = drone.velocity[0].hypot(drone.velocity[1]);
        assert!((h - 12.0).abs() < 0.01, "{h}");
        assert!(
            (drone.velocity[2] + 1.5).abs() < 0.01,
            "{}",
            drone.velocity[2]
        );
        let mut climbing = Multicopter::hovering_at([0.0, 0.0, 1.0]);
        run(&mut climbing, [0.0, 0.0, 9.0], &limits, 10.0, 0.05);
        assert!((climbing.velocity[2] - 3.0).abs() < 0.01);
    }

    #[test]
    fn a_takeoff_climbs_at_its_rate_and_a_landing_stops_on_the_ground() {
        let limits = DynamicsLimits::px4();
        let mut drone = Multicopter::hovering_at([0.0, 0.0, 0.0]);
        // On the ground, asked to go down: it stays.
        run(&mut drone, [0.0, 0.0, -1.0], &limits, 2.0, 0.05);
        assert_eq!(drone.position[2], 0.0);
        assert_eq!(drone.velocity[2], 0.0);
        // Takeoff at MPC_TKO_SPEED: about 1.5 m/s after the ramp, 2.5 m high within 3 s.
        let trace = run(
            &mut drone,
            [0.0, 0.0, limits.takeoff_speed],
            &limits,
            3.0,
            0.05,
        );
        assert!((trace.last().unwrap().velocity[2] - 1.5).abs() < 0.05);
        assert!(
            drone.position[2] > 2.5 && drone.position[2] < 4.5,
            "{}",
            drone.position[2]
        );
        // Landing at MPC_LAND_SPEED: down, and it stops at the ground, not below.
        let trace = run(
            &mut drone,
            [0.0, 0.0, -limits.land_speed],
            &limits,
            12.0,
            0.05,
        );
        assert!(trace.iter().all(|s| s.position[2] >= 0.0));
        assert_eq!(drone.position[2], 0.0);
        assert_eq!(drone.velocity[2], 0.0);
    }

    #[test]
    fn stopping_from_1_m_s_takes_about_the_px4_distance() {
        let limits = DynamicsLimits::px4_auto();
        let mut drone = Multicopter::hovering_at([0.0, 0.0, 3.0]);
        run(&mut drone, [1.0, 0.0, 0.0], &limits, 5.0, 0.01);
        assert!((drone.stopping_distance(&limits) - 1.0 / 6.0).abs() < 0.01);
        let start = drone.position[0];
        run(&mut drone, [0.0; 3], &limits, 5.0, 0.01);
        let travelled = drone.position[0] - start;
        // The lag and the jerk limit add to v^2 / 2a = 0.17 m.
        assert!(travelled > 0.17 && travelled < 0.6, "{travelled}");
    }

    #[test]
    fn bad_inputs_leave_the_state_as_it_is() {
        let limits = DynamicsLimits::px4();
        let mut drone = Multicopter::hovering_at([1.0, 2.0, 3.0]);
        let before = drone;
        drone.step([f64::NAN, 0.0, 0.0], [0.0; 3], &limits, 0.1);
        drone.step([1.0, 0.0, 0.0], [0.0; 3], &limits, f64::NAN);
        drone.step([1.0, 0.0, 0.0], [0.0; 3], &limits, -1.0);
        assert_eq!(drone, before);
        // Non-finite wind is ignored, not integrated.
        drone.step([0.0; 3], [f64::INFINITY, 0.0, 0.0], &limits, 0.1);
        assert!(drone.position.iter().all(|p| p.is_finite()));
        assert_eq!(DynamicsLimits::px4().validate(), Ok(()));
        assert_eq!(DynamicsLimits::indoor().validate(), Ok(()));
        assert_eq!(DynamicsLimits::px4_auto().validate(), Ok(()));
        let broken = DynamicsLimits {
            max_jerk: 0.0,
            ..DynamicsLimits::px4()
        };
        assert_eq!(broken.validate(), Err("max_jerk"));
    }

    #[test]
    fn the_wind_has_its_configured_mean_spread_and_memory() {
        let config = WindConfig {
            mean: [3.0, -1.0, 0.0],
            gust_std: 1.5,
            gust_time: 2.0,
        };
        let dt = 0.1;
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let mut wind = Wind::new(&config, &mut rng);
        let samples: Vec<[f64; 3]> = (0..200_000)
            .map(|_| wind.step(&config, dt, &mut rng))
            .collect();
        let n = samples.len() as f64;
        for (k, mean) in config.mean.iter().enumerate() {
            let m = samples.iter().map(|s| s[k]).sum::<f64>() / n;
            let var = samples.iter().map(|s| (s[k] - m).powi(2)).sum::<f64>() / n;
            assert!((m - mean).abs() < 0.1, "axis {k}: mean {m}");
            assert!(
                (var.sqrt() - 1.5).abs() < 0.08,
                "axis {k}: std {}",
                var.sqrt()
            );
        }
        // Lag-one autocorrelation exp(-dt / T) = 0.951.
        let m = samples.iter().map(|s| s[0]).sum::<f64>() / n;
        let (mut c0, mut c1) = (0.0, 0.0);
        for w in samples.windows(2) {
            c0 += (w[0][0] - m).powi(2);
            c1 += (w[0][0] - m) * (w[1][0] - m);
        }
        let rho = c1 / c0;
        assert!((rho - (-dt / 2.0_f64).exp()).abs() < 0.01, "{rho}");
        // Seeded: the same seed, the same gusts.
        let mut a = ChaCha8Rng::seed_from_u64(3);
        let mut b = ChaCha8Rng::seed_from_u64(3);
        let (mut wa, mut wb) = (Wind::new(&config, &mut a), Wind::new(&config, &mut b));
        for _ in 0..10 {
            assert_eq!(wa.step(&config, dt, &mut a), wb.step(&config, dt, &mut b));
        }
        // Calm air is calm.
        let mut calm = Wind::new(&WindConfig::CALM, &mut rng);
        assert_eq!(calm.step(&WindConfig::CALM, dt, &mut rng), [0.0; 3]);
    }

    #[test]
    fn a_hovering_drone_drifts_in_the_wind_and_holds_a_command_against_it() {
        let limits = DynamicsLimits::px4();
        let mut drone = Multicopter::hovering_at([0.0, 0.0, 3.0]);
        for _ in 0..600 {
            drone.step([0.0; 3], [5.0, 0.0, 0.0], &limits, 0.05);
        }
        // Without an integrator, a steady wind leaves a small steady drift:
        // tau drag w = 0.55 * 0.2 * 5 = 0.55 m/s.
        assert!(
            (drone.velocity[0] - 0.55).abs() < 0.01,
            "{}",
            drone.velocity[0]
        );
        assert!(drone.position[0] > 5.0);
        // Commanded against it, the drone still makes headway at nearly the commanded speed.
        for _ in 0..600 {
            drone.step([-2.0, 0.0, 0.0], [5.0, 0.0, 0.0], &limits, 0.05);
        }
        assert!(
            (drone.velocity[0] + 1.45).abs() < 0.01,
            "{}",
            drone.velocity[0]
        );
    }
}
