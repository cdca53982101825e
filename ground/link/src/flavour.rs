//! Autopilot families and their flight-mode numbering: PX4 packs its main and sub mode into
//! HEARTBEAT `custom_mode`, ArduPilot Copter numbers its modes. Written once here for the
//! daemon (which mode to ask for, whether it got it) and the mock autopilots (which mode to
//! report, where to fall back).

use mavlink::dialects::common::MavAutopilot;

/// A flight mode in the autopilot's own numbering.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FlightMode {
    /// PX4: `custom_mode = main << 16 | sub << 24`.
    Px4 {
        /// Main mode (6 = OFFBOARD, 4 = AUTO).
        main: u8,
        /// Sub mode (AUTO: 3 = LOITER, i.e. hold; 6 = LAND).
        sub: u8,
    },
    /// ArduPilot Copter: `custom_mode` is the mode number (4 = GUIDED, 5 = LOITER, 9 = LAND).
    ArduPilot(u32),
    /// Another autopilot: its raw `custom_mode`.
    Other(u32),
}

impl FlightMode {
    /// PX4 OFFBOARD (external setpoints).
    pub const PX4_OFFBOARD: Self = Self::Px4 { main: 6, sub: 0 };
    /// PX4 AUTO.LOITER: hold position.
    pub const PX4_HOLD: Self = Self::Px4 { main: 4, sub: 3 };
    /// PX4 AUTO.LAND: descend where it is, disarm on touchdown (`MAV_CMD_NAV_LAND`).
    pub const PX4_LAND: Self = Self::Px4 { main: 4, sub: 6 };
    /// PX4 AUTO.TAKEOFF: climb to the takeoff altitude, then hold (AUTO.LOITER).
    pub const PX4_TAKEOFF: Self = Self::Px4 { main: 4, sub: 2 };
    /// PX4 AUTO.RTL: return to home and land.
    pub const PX4_RTL: Self = Self::Px4 { main: 4, sub: 5 };
    /// ArduPilot GUIDED (external setpoints).
    pub const ARDUPILOT_GUIDED: Self = Self::ArduPilot(4);
    /// ArduPilot LOITER: hold position.
    pub const ARDUPILOT_LOITER: Self = Self::ArduPilot(5);
    /// ArduPilot LAND: descend where it is, disarm on touchdown.
    pub const ARDUPILOT_LAND: Self = Self::ArduPilot(9);
    /// ArduPilot RTL: return to home and land.
    pub const ARDUPILOT_RTL: Self = Self::ArduPilot(6);

    /// The mode a heartbeat reports.
    pub fn from_heartbeat(autopilot: MavAutopilot, custom_mode: u32) -> Self {
        match autopilot {
            MavAutopilot::MAV_AUTOPILOT_PX4 => Self::Px4 {
                main: ((custom_mode >> 16) & 0xFF) as u8,
                sub: (custom_mode >> 24) as u8,
            },
            MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Self::ArduPilot(custom_mode),
            _ => Self::Other(custom_mode),
        }
    }

    /// The heartbeat `custom_mode` of this mode.
    pub fn custom_mode(self) -> u32 {
        match self {
            Self::Px4 { main, sub } => (u32::from(main) << 16) | (u32::from(sub) << 24),
            Self::ArduPilot(mode) | Self::Other(mode) => mode,
        }
    }

    /// The offboard/guided mode of an autopilot flavour (None for unknown flavours).
    pub fn external_control(autopilot: MavAutopilot) -> Option<Self> {
        match autopilot {
            MavAutopilot::MAV_AUTOPILOT_PX4 => Some(Self::PX4_OFFBOARD),
            MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Some(Self::ARDUPILOT_GUIDED),
            _ => None,
        }
    }
}

/// Which autopilot family a vehicle runs; they name their external-control mode differently.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Flavour {
    /// PX4: OFFBOARD (main mode 6, HEARTBEAT `custom_mode` = 6 << 16), hold is AUTO.LOITER.
    Px4,
    /// ArduPilot Copter: GUIDED (mode 4), hold is LOITER (5).
    ArduPilot,
}

impl Flavour {
    /// The HEARTBEAT `autopilot` field of this family.
    pub fn mav_autopilot(self) -> MavAutopilot {
        match self {
            Self::Px4 => MavAutopilot::MAV_AUTOPILOT_PX4,
            Self::ArduPilot => MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
        }
    }

    /// The mode that flies external velocity setpoints (PX4 OFFBOARD, ArduPilot GUIDED).
    pub fn external_mode(self) -> FlightMode {
        match self {
            Self::Px4 => FlightMode::PX4_OFFBOARD,
            Self::ArduPilot => FlightMode::ARDUPILOT_GUIDED,
        }
    }

    /// The mode the autopilot falls back to when it holds position.
    pub fn hold_mode(self) -> FlightMode {
        match self {
            Self::Px4 => FlightMode::PX4_HOLD,
            Self::ArduPilot => FlightMode::ARDUPILOT_LOITER,
        }
    }

    /// The mode the autopilot lands in (`MAV_CMD_NAV_LAND`): PX4 AUTO.LAND, ArduPilot LAND.
    pub fn land_mode(self) -> FlightMode {
        match self {
            Self::Px4 => FlightMode::PX4_LAND,
            Self::ArduPilot => FlightMode::ARDUPILOT_LAND,
        }
    }

    /// The mode the autopilot returns home in (`MAV_CMD_NAV_RETURN_TO_LAUNCH`).
    pub fn rtl_mode(self) -> FlightMode {
        match self {
            Self::Px4 => FlightMode::PX4_RTL,
            Self::ArduPilot => FlightMode::ARDUPILOT_RTL,
        }
    }

    /// Whether the daemon takes off with `MAV_CMD_NAV_TAKEOFF` in the control mode
    /// (ArduCopter: GUIDED velocity commands do not lift a landed copter) rather than by
    /// climbing on its own velocity setpoints (PX4 OFFBOARD takes off on an upward setpoint).
    pub fn takes_off_by_command(self) -> bool {
        matches!(self, Self::ArduPilot)
    }

    /// The custom main mode to request with `MAV_CMD_DO_SET_MODE` (param 2) for
    /// [`Flavour::external_mode`].
    pub fn control_mode(self) -> u8 {
        match self.external_mode() {
            FlightMode::Px4 { main, .. } => main,
            FlightMode::ArduPilot(mode) | FlightMode::Other(mode) => mode as u8,
        }
    }

    /// Whether a HEARTBEAT `custom_mode` says the autopilot is in the external-control mode
    /// (for PX4 the main mode decides, whatever the sub mode).
    pub fn is_control_mode(self, custom_mode: u32) -> bool {
        match self {
            // PX4 packs main mode in bits 16..24 and sub mode in bits 24..32.
            Self::Px4 => (custom_mode >> 16) & 0xFF == u32::from(self.control_mode()),
            Self::ArduPilot => custom_mode == u32::from(self.control_mode()),
        }
    }

    /// Human name of the external-control mode, for logs.
    pub fn control_mode_name(self) -> &'static str {
        match self {
            Self::Px4 => "OFFBOARD",
            Self::ArduPilot => "GUIDED",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_control_mode_is_the_external_mode_each_family_reports() {
        for flavour in [Flavour::Px4, Flavour::ArduPilot] {
            let reported = flavour.external_mode().custom_mode();
            assert!(flavour.is_control_mode(reported), "{flavour:?}");
            assert!(!flavour.is_control_mode(flavour.hold_mode().custom_mode()));
            assert_eq!(
                FlightMode::from_heartbeat(flavour.mav_autopilot(), reported),
                flavour.external_mode()
            );
        }
        assert_eq!(Flavour::Px4.control_mode(), 6);
        assert_eq!(Flavour::ArduPilot.control_mode(), 4);
        // A PX4 sub mode does not change the main mode.
        assert!(Flavour::Px4.is_control_mode((6 << 16) | (1 << 24)));
        assert!(!Flavour::ArduPilot.is_control_mode(6 << 16));
        // Landing is not the control mode: a daemon that asked for it stops commanding.
        assert_eq!(
            Flavour::Px4.land_mode().custom_mode(),
            (4 << 16) | (6 << 24)
        );
        assert_eq!(Flavour::ArduPilot.land_mode().custom_mode(), 9);
        for flavour in [Flavour::Px4, Flavour::ArduPilot] {
            assert!(!flavour.is_control_mode(flavour.land_mode().custom_mode()));
        }
    }
}
