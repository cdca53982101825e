//! The mock autopilots' parameters: the names and defaults of the real ones whose values the
//! mock's behaviour reads, served over the MAVLink parameter protocol.
//!
//! Every parameter here drives something (a timeout, a speed, a delay); nothing is listed
//! only to look complete. Values are SI as the real autopilot stores them (PX4: seconds, m/s,
//! metres; ArduPilot: its own units, e.g. cm/s for speeds), converted where they are read.

use mavlink::dialects::common::MavParamType;
use skyherd_link::Flavour;

/// One parameter: name (at most 16 ASCII bytes), value, its MAVLink type, and the range a
/// PARAM_SET must respect.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Param {
    /// Name as the autopilot spells it.
    pub name: &'static str,
    /// Current value.
    pub value: f32,
    /// The type the autopilot reports (and expects in PARAM_SET).
    pub kind: MavParamType,
    /// Smallest accepted value.
    pub min: f32,
    /// Largest accepted value.
    pub max: f32,
}

const fn real(name: &'static str, value: f32, min: f32, max: f32) -> Param {
    Param {
        name,
        value,
        kind: MavParamType::MAV_PARAM_TYPE_REAL32,
        min,
        max,
    }
}

const fn int(name: &'static str, value: f32, min: f32, max: f32) -> Param {
    Param {
        name,
        value,
        kind: MavParamType::MAV_PARAM_TYPE_INT16,
        min,
        max,
    }
}

/// PX4's, with its defaults (PX4 v1.14 parameter reference).
const PX4: &[Param] = &[
    // Offboard loss timeout: setpoints older than this leave OFFBOARD (s).
    real("COM_OF_LOSS_T", 1.0, 0.0, 60.0),
    // Auto-disarm after arming when the vehicle does not take off (s; 0 off).
    real("COM_DISARM_PRFLT", 10.0, -1.0, 20.0),
    // Auto-disarm after landing (s; 0 off).
    real("COM_DISARM_LAND", 2.0, -1.0, 20.0),
    // Takeoff altitude of AUTO.TAKEOFF without an altitude (m above home).
    real("MIS_TAKEOFF_ALT", 2.5, 0.0, 80.0),
    // Climb speed of AUTO.TAKEOFF (m/s).
    real("MPC_TKO_SPEED", 1.5, 1.0, 5.0),
    // Descent speed of AUTO.LAND near the ground (m/s).
    real("MPC_LAND_SPEED", 0.7, 0.6, 5.0),
    // Horizontal speed limit (m/s).
    real("MPC_XY_VEL_MAX", 12.0, 0.0, 20.0),
    // Horizontal speed of the return in AUTO.RTL (m/s).
    real("MPC_XY_CRUISE", 5.0, 3.0, 20.0),
];

/// ArduCopter's, with its defaults (ArduCopter 4.6 parameter reference).
const ARDUPILOT: &[Param] = &[
    // GUIDED: a velocity command older than this stops the vehicle (s).
    real("GUID_TIMEOUT", 3.0, 0.1, 5.0),
    // Auto-disarm when landed and armed this long (s; 0 off).
    int("DISARM_DELAY", 10.0, 0.0, 127.0),
    // Descent speed of LAND in the last stage (cm/s).
    int("LAND_SPEED", 50.0, 30.0, 200.0),
    // Climb speed of a takeoff and of GUIDED climbs (cm/s).
    real("WPNAV_SPEED_UP", 250.0, 10.0, 1000.0),
    // Horizontal speed of GUIDED and RTL (cm/s).
    real("WPNAV_SPEED", 1000.0, 10.0, 2000.0),
];

/// A flavour's parameter table.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    params: Vec<Param>,
}

/// Why a PARAM_SET was refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ParamError {
    /// No parameter by that name.
    Unknown,
    /// Not finite, or outside the parameter's range.
    OutOfRange {
        /// Smallest accepted.
        min: f32,
        /// Largest accepted.
        max: f32,
    },
}

impl Params {
    /// The defaults of `flavour`.
    pub fn defaults(flavour: Flavour) -> Self {
        let table = match flavour {
            Flavour::Px4 => PX4,
            Flavour::ArduPilot => ARDUPILOT,
        };
        Self {
            params: table.to_vec(),
        }
    }

    /// How many there are.
    pub fn len(&self) -> usize {
        self.params.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }

    /// By index, with the index.
    pub fn by_index(&self, index: usize) -> Option<&Param> {
        self.params.get(index)
    }

    /// By name: the parameter and its index.
    pub fn by_name(&self, name: &str) -> Option<(usize, &Param)> {
        self.params.iter().enumerate().find(|(_, p)| p.name == name)
    }

    /// The value of `name`. Panics on a name not in the table: callers name the table's own.
    pub fn get(&self, name: &str) -> f64 {
        match self.by_name(name) {
            Some((_, p)) => f64::from(p.value),
            None => unreachable!("parameter {name} is not in the table"),
        }
    }

    /// Sets `name` to `value`; returns its index.
    pub fn set(&mut self, name: &str, value: f32) -> Result<usize, ParamError> {
        let (index, _) = self.by_name(name).ok_or(ParamError::Unknown)?;
        let p = &mut self.params[index];
        if !(value.is_finite() && value >= p.min && value <= p.max) {
            return Err(ParamError::OutOfRange {
                min: p.min,
                max: p.max,
            });
        }
        p.value = if p.kind == MavParamType::MAV_PARAM_TYPE_INT16 {
            value.round()
        } else {
            value
        };
        Ok(index)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_fit_the_protocol_and_defaults_are_in_range() {
        for flavour in [Flavour::Px4, Flavour::ArduPilot] {
            let params = Params::defaults(flavour);
            assert!(!params.is_empty());
            for i in 0..params.len() {
                let p = params.by_index(i).copied().expect("index in range");
                assert!(p.name.len() <= 16 && p.name.is_ascii(), "{}", p.name);
                assert!(p.min <= p.value && p.value <= p.max, "{}", p.name);
            }
        }
    }

    #[test]
    fn set_checks_name_and_range() {
        let mut params = Params::defaults(Flavour::Px4);
        assert_eq!(params.set("COM_OF_LOSS_T", 2.5), Ok(0));
        assert_eq!(params.get("COM_OF_LOSS_T"), 2.5);
        assert_eq!(params.set("NO_SUCH", 1.0), Err(ParamError::Unknown));
        assert!(matches!(
            params.set("COM_OF_LOSS_T", f32::NAN),
            Err(ParamError::OutOfRange { .. })
        ));
        assert!(matches!(
            params.set("MPC_TKO_SPEED", 9.0),
            Err(ParamError::OutOfRange { .. })
        ));
        let mut ardupilot = Params::defaults(Flavour::ArduPilot);
        ardupilot.set("DISARM_DELAY", 4.6).expect("in range");
        assert_eq!(ardupilot.get("DISARM_DELAY"), 5.0, "integers round");
    }
}
