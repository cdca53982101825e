//! The one place where the simulator frame and MAVLink's NED frame meet.
//!
//! * Simulator frame: x east, y north, z **up**, origin at the south-west ground corner of the
//!   arena, metres (positions) and m/s (velocities).
//! * MAVLink `MAV_FRAME_LOCAL_NED`: x north, y east, z **down**, with the same origin.
//!
//! The mapping is its own inverse up to naming: swap the horizontal axes and negate z. It is
//! generic so that the f64 simulator and the f32 onboard core call the same function.
//!
//! ```
//! use skyherd_onboard::frame::{ned_to_sim, sim_to_ned};
//! let sim = [10.0_f32, 20.0, 2.0]; // 10 m east, 20 m north, 2 m up
//! assert_eq!(sim_to_ned(sim), [20.0, 10.0, -2.0]);
//! assert_eq!(ned_to_sim(sim_to_ned(sim)), sim);
//! ```

use core::ops::Neg;

/// Simulator (east, north, up) to NED (north, east, down); positions and velocities alike.
pub fn sim_to_ned<T: Copy + Neg<Output = T>>(v: [T; 3]) -> [T; 3] {
    [v[1], v[0], -v[2]]
}

/// NED (north, east, down) to simulator (east, north, up); positions and velocities alike.
pub fn ned_to_sim<T: Copy + Neg<Output = T>>(v: [T; 3]) -> [T; 3] {
    [v[1], v[0], -v[2]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn up_is_negative_down() {
        assert_eq!(sim_to_ned([0.0_f64, 0.0, 3.0]), [0.0, 0.0, -3.0]);
        assert_eq!(ned_to_sim([0.0_f64, 0.0, -3.0]), [0.0, 0.0, 3.0]);
    }

    #[test]
    fn east_is_ned_y_and_north_is_ned_x() {
        assert_eq!(sim_to_ned([1.0_f32, 0.0, 0.0]), [0.0, 1.0, 0.0]);
        assert_eq!(sim_to_ned([0.0_f32, 1.0, 0.0]), [1.0, 0.0, 0.0]);
    }

    #[test]
    fn round_trip_is_identity() {
        let v = [-3.5_f64, 7.25, 1.5];
        assert_eq!(ned_to_sim(sim_to_ned(v)), v);
        assert_eq!(sim_to_ned(ned_to_sim(v)), v);
    }
}
