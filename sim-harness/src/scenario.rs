//! Scenario files (TOML): every knob of an episode, the presets, and validation that names the
//! offending field.
//!
//! A file is either complete (see `sim-harness/scenarios/*.toml`, which are the presets and
//! document every choice) or starts with `base = "<preset>"` and overrides some keys:
//!
//! ```
//! use skyherd_sim::scenario::{HerderCount, Scenario};
//! let s = Scenario::from_toml_str(r#"
//!     base = "paper-drive"
//!     targets = 64
//!     herders = "adaptive"
//!     [noise]
//!     sensing_std = 0.0
//! "#).unwrap();
//! assert_eq!(s.herders, HerderCount::Adaptive);
//! assert_eq!(s.herder_count(), 8);
//! assert_eq!(s.noise.boids_param_rel_std, 0.2); // from the preset
//!
//! let err = Scenario::from_toml_str("base = \"paper-drive\"\n[boids]\nseparaton = 1.0").unwrap_err();
//! assert!(err.to_string().contains("separaton"));
//! ```

use std::fmt;
use std::path::Path;

use serde::de::{self, Visitor};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use skyherd_model::Task;
use thiserror::Error;

use crate::noise::NoiseConfig;
use crate::reward::{RewardCorrection, RewardParams};
use crate::task::{Layout, centre_box};
use crate::world::{Area, BoidsParams, SpeedLimits, adaptive_herders};

/// Everything that defines an episode family; one seed picks one episode.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// A label for reports.
    pub name: String,
    /// Driving or collecting.
    #[serde(with = "crate::task::task_serde")]
    pub task: Task,
    /// Number of herders (drones) M, or adaptive in N.
    pub herders: HerderCount,
    /// Number of targets N.
    pub targets: usize,
    /// Default episode seed for single runs.
    pub seed: u64,
    /// Steps after which an episode is truncated.
    pub step_limit: u64,
    /// Seconds per step.
    pub dt: f64,
    /// The arena.
    pub area: Area,
    /// Spawn rules.
    pub layout: Layout,
    /// Boids coefficients before noise.
    pub boids: BoidsParams,
    /// Speed limits.
    pub limits: SpeedLimits,
    /// Reward constants and the training correction.
    pub reward: RewardParams,
    /// Noise levels.
    pub noise: NoiseConfig,
    /// How the herders follow their commands: absent, at once (every preset, every earlier
    /// number); present, through the multicopter model of [`crate::dynamics`] in its wind.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dynamics: Option<HerderDynamics>,
}

/// The herders' motion model and their air (TOML `[dynamics]` with `limits` and `wind` tables).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HerderDynamics {
    /// Acceleration, jerk and speed limits, lag.
    pub limits: crate::dynamics::DynamicsLimits,
    /// The wind.
    pub wind: crate::dynamics::WindConfig,
    /// How long a command takes to reach the autopilot, s (0 to one step `dt`): for that long
    /// into each step the vehicle still flies the previous command. Through the MAVLink loop
    /// a command rides on a snapshot one sensor tick old (0.1 s); the presets leave it at 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub command_delay_s: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl HerderDynamics {
    /// The motion models by name: `px4` ([`DynamicsLimits::px4`](crate::dynamics::DynamicsLimits::px4)),
    /// `px4-auto` ([`DynamicsLimits::px4_auto`](crate::dynamics::DynamicsLimits::px4_auto)) and
    /// `indoor` ([`DynamicsLimits::indoor`](crate::dynamics::DynamicsLimits::indoor)).
    pub const LIMITS: [&'static str; 3] = ["px4", "px4-auto", "indoor"];
    /// The winds by name: `calm`, `arena` and `room` ([`WindConfig`](crate::dynamics::WindConfig)).
    pub const WINDS: [&'static str; 3] = ["calm", "arena", "room"];

    /// A named motion model in a named wind (the names of [`Self::LIMITS`] and [`Self::WINDS`],
    /// as `skyherd-sim eval --dynamics --wind` and the trainer's configs take them); `None` when
    /// either name is not one of them.
    ///
    /// ```
    /// use skyherd_sim::HerderDynamics;
    /// let room = HerderDynamics::named("indoor", "room").unwrap();
    /// assert_eq!(room.limits.max_speed_horizontal, 1.0);
    /// assert!(HerderDynamics::named("indoor", "gale").is_none());
    /// ```
    pub fn named(limits: &str, wind: &str) -> Option<HerderDynamics> {
        use crate::dynamics::{DynamicsLimits, WindConfig};
        let limits = match limits {
            "px4" => DynamicsLimits::px4(),
            "px4-auto" => DynamicsLimits::px4_auto(),
            "indoor" => DynamicsLimits::indoor(),
            _ => return None,
        };
        let wind = match wind {
            "calm" => WindConfig::CALM,
            "arena" => WindConfig::arena(),
            "room" => WindConfig::room(),
            _ => return None,
        };
        Some(HerderDynamics {
            limits,
            wind,
            command_delay_s: 0.0,
        })
    }
}

/// The herder count M: fixed, or `2^floor(log2(N)/2)` (TOML: an integer or `"adaptive"`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum HerderCount {
    /// Exactly this many.
    Fixed(usize),
    /// [`adaptive_herders`] of the target count.
    Adaptive,
}

impl HerderCount {
    /// M for `targets` targets.
    pub fn resolve(self, targets: usize) -> usize {
        match self {
            HerderCount::Fixed(m) => m,
            HerderCount::Adaptive => adaptive_herders(targets),
        }
    }
}

impl fmt::Display for HerderCount {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            HerderCount::Fixed(m) => write!(f, "{m}"),
            HerderCount::Adaptive => f.write_str("adaptive"),
        }
    }
}

impl std::str::FromStr for HerderCount {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "adaptive" {
            return Ok(HerderCount::Adaptive);
        }
        match s.parse::<usize>() {
            Ok(m) if m >= 1 => Ok(HerderCount::Fixed(m)),
            _ => Err(format!(
                "herder count `{s}` is neither an integer >= 1 nor `adaptive`"
            )),
        }
    }
}

impl Serialize for HerderCount {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            HerderCount::Fixed(m) => s.serialize_u64(*m as u64),
            HerderCount::Adaptive => s.serialize_str("adaptive"),
        }
    }
}

impl<'de> Deserialize<'de> for HerderCount {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl Visitor<'_> for V {
            type Value = HerderCount;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a herder count >= 1 or \"adaptive\"")
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<HerderCount, E> {
                if v >= 1 {
                    Ok(HerderCount::Fixed(v as usize))
                } else {
                    Err(E::custom(format!("herders must be >= 1, got {v}")))
                }
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<HerderCount, E> {
                self.visit_i64(v.min(i64::MAX as u64) as i64)
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<HerderCount, E> {
                v.parse().map_err(E::custom)
            }
        }
        d.deserialize_any(V)
    }
}

/// Why a scenario was rejected.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum ScenarioError {
    /// The file could not be read.
    #[error("cannot read scenario file {path}: {message}")]
    Io {
        /// The path.
        path: String,
        /// The OS error.
        message: String,
    },
    /// Not TOML, or a field has the wrong type, is unknown or missing.
    #[error("bad scenario: {message}")]
    Parse {
        /// The parser's message (it names the field).
        message: String,
    },
    /// `base = ...` or a `--scenario` argument names no preset.
    #[error("unknown preset `{name}`; presets are {}", PRESETS.join(", "))]
    UnknownPreset {
        /// The name given.
        name: String,
    },
    /// A field is out of its domain.
    #[error("invalid scenario field `{field}`: {reason}")]
    Invalid {
        /// Dotted path of the field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

/// Names of the built-in presets.
pub const PRESETS: [&str; 3] = ["paper-drive", "paper-collect", "indoor"];

fn preset_text(name: &str) -> Option<&'static str> {
    match name {
        "paper-drive" => Some(include_str!("../scenarios/paper-drive.toml")),
        "paper-collect" => Some(include_str!("../scenarios/paper-collect.toml")),
        "indoor" => Some(include_str!("../scenarios/indoor.toml")),
        _ => None,
    }
}

fn parse_table(text: &str) -> Result<toml::Table, ScenarioError> {
    text.parse::<toml::Table>()
        .map_err(|e| ScenarioError::Parse {
            message: e.to_string(),
        })
}

/// Overlays `over` on `base`, recursing into tables so that `[noise] sensing_std = 0` keeps the
/// other noise keys.
fn merge(base: &mut toml::Table, over: toml::Table) {
    for (k, v) in over {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

impl Scenario {
    /// A built-in preset by name (see [`PRESETS`]).
    pub fn preset(name: &str) -> Result<Scenario, ScenarioError> {
        let text = preset_text(name).ok_or_else(|| ScenarioError::UnknownPreset {
            name: name.to_owned(),
        })?;
        Scenario::from_toml_str(text)
    }

    /// The `paper-drive` preset.
    pub fn paper_drive() -> Scenario {
        Scenario::preset("paper-drive").unwrap_or_else(unreachable_preset)
    }

    /// The `paper-collect` preset.
    pub fn paper_collect() -> Scenario {
        Scenario::preset("paper-collect").unwrap_or_else(unreachable_preset)
    }

    /// The `indoor` preset.
    pub fn indoor() -> Scenario {
        Scenario::preset("indoor").unwrap_or_else(unreachable_preset)
    }

    /// The paper preset of `task`.
    pub fn paper(task: Task) -> Scenario {
        match task {
            Task::Driving => Scenario::paper_drive(),
            Task::Collecting => Scenario::paper_collect(),
        }
    }

    /// Parses and validates TOML text (complete, or `base = "<preset>"` plus overrides).
    pub fn from_toml_str(text: &str) -> Result<Scenario, ScenarioError> {
        let mut table = parse_table(text)?;
        if let Some(base) = table.remove("base") {
            let name = base.as_str().ok_or_else(|| ScenarioError::Invalid {
                field: "base",
                reason: "must be a preset name string".into(),
            })?;
            let text = preset_text(name).ok_or_else(|| ScenarioError::UnknownPreset {
                name: name.to_owned(),
            })?;
            let mut full = parse_table(text)?;
            merge(&mut full, table);
            table = full;
        }
        let scenario: Scenario =
            toml::Value::Table(table)
                .try_into()
                .map_err(|e: toml::de::Error| ScenarioError::Parse {
                    message: e.to_string(),
                })?;
        scenario.validate()?;
        Ok(scenario)
    }

    /// Reads a scenario file.
    pub fn load(path: &Path) -> Result<Scenario, ScenarioError> {
        let text = std::fs::read_to_string(path).map_err(|e| ScenarioError::Io {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
        Scenario::from_toml_str(&text)
    }

    /// A preset name or a file path.
    pub fn from_arg(arg: &str) -> Result<Scenario, ScenarioError> {
        if preset_text(arg).is_some() {
            Scenario::preset(arg)
        } else {
            Scenario::load(Path::new(arg))
        }
    }

    /// This scenario as complete TOML (no comments).
    pub fn to_toml(&self) -> Result<String, ScenarioError> {
        toml::to_string(self).map_err(|e| ScenarioError::Parse {
            message: e.to_string(),
        })
    }

    /// M after resolving "adaptive".
    pub fn herder_count(&self) -> usize {
        self.herders.resolve(self.targets)
    }

    /// The same scenario with every noise level at zero.
    pub fn without_noise(mut self) -> Scenario {
        self.noise = NoiseConfig::NONE;
        self
    }

    /// Checks every field's domain; the error names the first bad field.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let bad =
            |field: &'static str, reason: String| Err(ScenarioError::Invalid { field, reason });
        if let Some(d) = &self.dynamics {
            if let Err(field) = d.limits.validate() {
                return bad("dynamics.limits", format!("{field} must be finite and > 0"));
            }
            if let Err(reason) = d.wind.validate() {
                return bad("dynamics.wind", reason.into());
            }
            if !(d.command_delay_s.is_finite()
                && d.command_delay_s >= 0.0
                && d.command_delay_s <= self.dt)
            {
                return bad(
                    "dynamics.command_delay_s",
                    format!("must be 0 to one step ({} s)", self.dt),
                );
            }
        }
        // Finite is not enough: 1e308 passes it and overflows a step (see
        // `world::MAX_MAGNITUDE`).
        let max = crate::world::MAX_MAGNITUDE;
        let pos = |field: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 && v <= max {
                Ok(())
            } else {
                bad(
                    field,
                    format!("must be finite, > 0 and <= {max:e}, got {v}"),
                )
            }
        };
        let nonneg = |field: &'static str, v: f64| {
            if v.is_finite() && v >= 0.0 && v <= max {
                Ok(())
            } else {
                bad(
                    field,
                    format!("must be finite, >= 0 and <= {max:e}, got {v}"),
                )
            }
        };
        let finite = |field: &'static str, v: f64| {
            if v.is_finite() && v.abs() <= max {
                Ok(())
            } else {
                bad(field, format!("must be finite and within {max:e}, got {v}"))
            }
        };
        const MAX_TARGETS: usize = 1 << 20;
        const MAX_HERDERS: usize = 4096;
        if self.targets == 0 || self.targets > MAX_TARGETS {
            return bad(
                "targets",
                format!("must be in 1..={MAX_TARGETS}, got {}", self.targets),
            );
        }
        if let HerderCount::Fixed(m) = self.herders
            && (m == 0 || m > MAX_HERDERS)
        {
            return bad("herders", format!("must be in 1..={MAX_HERDERS}, got {m}"));
        }
        if self.step_limit == 0 {
            return bad("step_limit", "must be >= 1".into());
        }
        pos("dt", self.dt)?;
        pos("area.width", self.area.width)?;
        pos("area.depth", self.area.depth)?;
        pos("area.ceiling", self.area.ceiling)?;
        let l = &self.layout;
        pos("layout.goal_radius", l.goal_radius)?;
        pos("layout.start_radius", l.start_radius)?;
        nonneg("layout.min_start_goal_distance", l.min_start_goal_distance)?;
        nonneg("layout.wall_margin", l.wall_margin)?;
        nonneg("layout.herder_clearance", l.herder_clearance)?;
        nonneg("layout.herder_altitude", l.herder_altitude)?;
        if l.herder_altitude > self.area.ceiling {
            return bad(
                "layout.herder_altitude",
                format!(
                    "{} is above the ceiling {}",
                    l.herder_altitude, self.area.ceiling
                ),
            );
        }
        let fits = |r: f64| {
            let need = 2.0 * (r + l.wall_margin);
            need <= self.area.width && need <= self.area.depth
        };
        if !fits(l.goal_radius) {
            return bad(
                "layout.goal_radius",
                "the goal circle plus wall_margin does not fit in the area".into(),
            );
        }
        if 2.0 * l.wall_margin >= self.area.width.min(self.area.depth) {
            return bad("layout.wall_margin", "leaves no room in the area".into());
        }
        if self.task == Task::Driving {
            if !fits(l.start_radius) {
                return bad(
                    "layout.start_radius",
                    "the start circle plus wall_margin does not fit in the area".into(),
                );
            }
            // The farthest two centres can be; demand some slack so rejection sampling is quick.
            let (glo, ghi) = centre_box(&self.area, l.goal_radius, l.wall_margin);
            let (slo, shi) = centre_box(&self.area, l.start_radius, l.wall_margin);
            let dx = (ghi[0] - slo[0]).max(shi[0] - glo[0]);
            let dy = (ghi[1] - slo[1]).max(shi[1] - glo[1]);
            let reach = dx.hypot(dy);
            if l.min_start_goal_distance > 0.95 * reach {
                return bad(
                    "layout.min_start_goal_distance",
                    format!(
                        "{} m cannot be met reliably in this area (the centres can be at most {reach:.2} m apart)",
                        l.min_start_goal_distance
                    ),
                );
            }
        }
        let b = &self.boids;
        nonneg("boids.separation", b.separation)?;
        nonneg("boids.alignment", b.alignment)?;
        nonneg("boids.cohesion", b.cohesion)?;
        nonneg("boids.flock", b.flock)?;
        nonneg("boids.herder", b.herder)?;
        nonneg("boids.separation_range", b.separation_range)?;
        nonneg("boids.herder_height_scale", b.herder_height_scale)?;
        pos("limits.target", self.limits.target)?;
        pos("limits.herder", self.limits.herder)?;
        let r = &self.reward;
        finite("reward.k0", r.k0)?;
        finite("reward.r1", r.r1)?;
        finite("reward.r2", r.r2)?;
        finite("reward.r3", r.r3)?;
        finite("reward.k1", r.k1)?;
        finite("reward.k2", r.k2)?;
        finite("reward.k3", r.k3)?;
        finite("reward.k4", r.k4)?;
        if let RewardCorrection::LeaveCoversRemainingSteps { gamma } = r.correction
            && !(gamma > 0.0 && gamma <= 1.0)
        {
            return bad(
                "reward.correction.gamma",
                format!("must be in (0, 1], got {gamma}"),
            );
        }
        nonneg("noise.boids_param_rel_std", self.noise.boids_param_rel_std)?;
        nonneg("noise.sensing_std", self.noise.sensing_std)?;
        nonneg("noise.actuation_std", self.noise.actuation_std)?;
        Ok(())
    }
}

// The presets are compiled in and parsed by the tests; failing here would be a build defect.
#[allow(clippy::panic)]
fn unreachable_preset(e: ScenarioError) -> Scenario {
    panic!("built-in preset is invalid: {e}")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field_of(text: &str) -> String {
        match Scenario::from_toml_str(text) {
            Err(ScenarioError::Invalid { field, .. }) => field.to_owned(),
            Err(e) => e.to_string(),
            Ok(_) => "accepted".to_owned(),
        }
    }

    #[test]
    fn presets_parse_and_say_what_they_are() {
        let d = Scenario::paper_drive();
        assert_eq!(
            (d.task, d.herder_count(), d.targets),
            (Task::Driving, 4, 16)
        );
        assert_eq!(d.boids, BoidsParams::PAPER);
        assert_eq!(d.reward, RewardParams::paper(Task::Driving));
        let c = Scenario::paper_collect();
        assert_eq!(c.task, Task::Collecting);
        assert_eq!(c.reward, RewardParams::paper(Task::Collecting));
        let i = Scenario::indoor();
        assert_eq!(
            (i.area.width, i.area.depth, i.area.ceiling),
            (10.0, 10.0, 3.0)
        );
        assert_eq!((i.herder_count(), i.targets), (2, 4));
        assert!(i.layout.min_start_goal_distance >= 8.0);
        for name in PRESETS {
            let s = Scenario::preset(name).unwrap();
            // Round trip through the plain TOML writer.
            let again = Scenario::from_toml_str(&s.to_toml().unwrap()).unwrap();
            assert_eq!(again, s);
        }
    }

    #[test]
    fn unknown_fields_are_named() {
        let e = Scenario::from_toml_str("base = \"paper-drive\"\nspeed = 3").unwrap_err();
        assert!(e.to_string().contains("speed"), "{e}");
        let e = Scenario::from_toml_str("base = \"indoor\"\n[noise]\nsensing = 1.0").unwrap_err();
        assert!(e.to_string().contains("sensing"), "{e}");
    }

    #[test]
    fn wrong_types_and_missing_fields_are_named() {
        let e = Scenario::from_toml_str("base = \"paper-drive\"\ntargets = \"many\"").unwrap_err();
        assert!(
            e.to_string().contains("targets") || e.to_string().contains("many"),
            "{e}"
        );
        let e = Scenario::from_toml_str("name = \"x\"\ntask = \"driving\"").unwrap_err();
        assert!(e.to_string().contains("missing field"), "{e}");
        let e = Scenario::from_toml_str("base = \"paper-drive\"\ntask = \"flying\"").unwrap_err();
        assert!(e.to_string().contains("flying"), "{e}");
        let e = Scenario::from_toml_str("base = \"paper-drive\"\nherders = \"lots\"").unwrap_err();
        assert!(e.to_string().contains("lots"), "{e}");
        let e = Scenario::from_toml_str("base = \"paper-drive\"\nherders = 0").unwrap_err();
        assert!(e.to_string().contains(">= 1"), "{e}");
        assert!(matches!(
            Scenario::from_toml_str("base = \"moon\""),
            Err(ScenarioError::UnknownPreset { .. })
        ));
        assert!(matches!(
            Scenario::from_toml_str("this is not toml"),
            Err(ScenarioError::Parse { .. })
        ));
    }

    #[test]
    fn out_of_domain_values_name_their_field() {
        let base = "base = \"paper-drive\"\n";
        assert_eq!(field_of(&format!("{base}targets = 0")), "targets");
        assert_eq!(field_of(&format!("{base}step_limit = 0")), "step_limit");
        assert_eq!(field_of(&format!("{base}dt = -1.0")), "dt");
        assert_eq!(
            field_of(&format!("{base}[layout]\ngoal_radius = -45.0")),
            "layout.goal_radius"
        );
        assert_eq!(
            field_of(&format!("{base}[layout]\ngoal_radius = 400.0")),
            "layout.goal_radius"
        );
        assert_eq!(
            field_of(&format!("{base}[layout]\nmin_start_goal_distance = 900.0")),
            "layout.min_start_goal_distance"
        );
        assert_eq!(
            field_of(&format!("{base}[layout]\nherder_altitude = 11.0")),
            "layout.herder_altitude"
        );
        assert_eq!(
            field_of(&format!("{base}[boids]\nherder = -600.0")),
            "boids.herder"
        );
        assert_eq!(
            field_of(&format!("{base}[boids]\nseparation = nan")),
            "boids.separation"
        );
        assert_eq!(
            field_of(&format!("{base}[limits]\ntarget = 0.0")),
            "limits.target"
        );
        assert_eq!(
            field_of(&format!("{base}[noise]\nsensing_std = -0.1")),
            "noise.sensing_std"
        );
        assert_eq!(
            field_of(&format!(
                "{base}[reward]\ncorrection = {{ kind = \"leave-covers-remaining-steps\", gamma = 1.5 }}"
            )),
            "reward.correction.gamma"
        );
        assert_eq!(field_of(&format!("{base}targets = 64")), "accepted");
    }

    #[test]
    fn adaptive_herders_in_files() {
        let s = Scenario::from_toml_str(
            "base = \"paper-collect\"\nherders = \"adaptive\"\ntargets = 1024",
        )
        .unwrap();
        assert_eq!(s.herder_count(), 32);
        assert_eq!("adaptive".parse::<HerderCount>(), Ok(HerderCount::Adaptive));
        assert!("0".parse::<HerderCount>().is_err());
    }
}
