//! The JSON state schema shared by `skyherd-sim step` and the lines of a run trace.
//!
//! A [`StepState`] is a full [`World`] (every field required, unknown fields rejected) plus the
//! herders' commanded velocities. `skyherd-sim step` applies exactly one noise-free
//! [`crate::world::advance`] and writes the same schema back, actions unchanged, so the output
//! can be fed in again. A run trace (JSON Lines) has one [`TraceLine`] per state: the initial
//! state with empty `actions` and no `outcome`, then one per step with the actions that led to it.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::env::StepOutcome;
use crate::world::{StepScratch, World, WorldError, advance};

/// A world and the commands for its next step (the `step` command's input and output).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepState {
    /// The full state.
    pub world: World,
    /// One `[vx, vy, vz]` (m/s, sim frame) per herder.
    pub actions: Vec<[f64; 3]>,
}

/// One line of a run trace.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TraceLine {
    /// The true state after the step (the initial state on the first line).
    pub world: World,
    /// The commands applied in the step (empty on the first line).
    pub actions: Vec<[f64; 3]>,
    /// Reward and flags of the step (absent on the first line).
    pub outcome: Option<StepOutcome>,
}

/// Why a state file could not be stepped.
#[derive(Debug, Error)]
pub enum StateError {
    /// Not JSON of the schema; the message names the field.
    #[error("bad state JSON: {0}")]
    Json(#[from] serde_json::Error),
    /// A field is out of its domain, or the actions do not fit.
    #[error(transparent)]
    World(#[from] WorldError),
}

/// Parses a [`StepState`], validates it, advances it one noise-free step and returns it.
pub fn step_state_json(text: &str) -> Result<StepState, StateError> {
    let mut state: StepState = serde_json::from_str(text)?;
    state.world.validate()?;
    let mut scratch = StepScratch::with_capacity(state.world.targets.len());
    advance(&mut state.world, &state.actions, &mut scratch)?;
    Ok(state)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::{Area, BoidsParams, Goal, SpeedLimits};
    use skyherd_model::Task;

    fn state() -> StepState {
        StepState {
            world: World {
                task: Task::Driving,
                area: Area {
                    width: 500.0,
                    depth: 500.0,
                    ceiling: 10.0,
                },
                goal: Goal {
                    center: [400.0, 400.0],
                    radius: 45.0,
                },
                params: BoidsParams::PAPER,
                limits: SpeedLimits::PAPER,
                dt: 1.0,
                step: 0,
                herders: vec![[80.0, 100.0, 0.0]],
                targets: vec![[100.0, 100.0]],
                target_velocities: vec![[0.0, 0.0]],
            },
            actions: vec![[5.0, 0.0, 0.0]],
        }
    }

    #[test]
    fn step_round_trips_the_schema() {
        let text = serde_json::to_string(&state()).unwrap();
        let out = step_state_json(&text).unwrap();
        assert_eq!(out.world.step, 1);
        assert_eq!(out.actions, state().actions);
        assert_eq!(out.world.herders[0], [85.0, 100.0, 0.0]);
        assert!((out.world.targets[0][0] - (100.0 + 600.0 / 225.0)).abs() < 1e-12);
        // Output parses as input again.
        let again = step_state_json(&serde_json::to_string(&out).unwrap()).unwrap();
        assert_eq!(again.world.step, 2);
    }

    #[test]
    fn bad_states_are_named_errors() {
        let mut v = serde_json::to_value(state()).unwrap();
        v["world"]["colour"] = serde_json::json!(1);
        let e = step_state_json(&v.to_string()).unwrap_err();
        assert!(e.to_string().contains("colour"), "{e}");
        let mut v = serde_json::to_value(state()).unwrap();
        v["world"]
            .as_object_mut()
            .unwrap()
            .remove("target_velocities");
        let e = step_state_json(&v.to_string()).unwrap_err();
        assert!(e.to_string().contains("target_velocities"), "{e}");
        let mut s = state();
        s.actions.push([0.0; 3]);
        let e = step_state_json(&serde_json::to_string(&s).unwrap()).unwrap_err();
        assert!(e.to_string().contains("expected 1 herder actions"), "{e}");
        let mut s = state();
        s.world.dt = 0.0;
        let e = step_state_json(&serde_json::to_string(&s).unwrap()).unwrap_err();
        assert!(e.to_string().contains("`dt`"), "{e}");
    }
}
