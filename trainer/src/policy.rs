//! Decentralised execution: every herder runs the same actor on its own observation, encoded by
//! the onboard crate's encoder (the only copy), and its normalised local-frame action becomes a
//! simulator-frame velocity through `LocalFrame::action_to_world`, exactly as on the drone.
//!
//! The policy wrapper lives in the simulator ([`skyherd_sim::learned`]) so that `skyherd-sim
//! eval` runs model files the same way; this module adds the training network to it.

use skyherd_model::Task;
use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES, version_for};
pub use skyherd_sim::learned::{ActorPolicy, Infer};

use crate::network::MultiTaskMlp;

impl Infer for MultiTaskMlp {
    fn infer(&self, task: Task, features: &[f32; FEATURES]) -> [f32; 3] {
        // An actor made for an older encoder reads the prefix that is its encoding.
        let y = self.predict(task.index(), &features[..self.inputs().min(FEATURES)]);
        [y[0], y[1], y[2]]
    }

    fn encoder_version(&self) -> u16 {
        version_for(self.inputs()).unwrap_or(ENCODER_VERSION)
    }
}
