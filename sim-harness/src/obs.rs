//! The bridge from the simulator's f64 [`World`] to the onboard encoder's f32 [`ObsInput`]: the
//! trainer and a learned policy call the one encoder in `skyherd-onboard` through this.

use skyherd_onboard::obs::{
    ENCODER_VERSION, FEATURES, LocalFrame, ObsError, ObsInput, encode_version,
};

use crate::world::World;

/// f32 copies of a world's positions, reused from step to step (no allocation once sized).
#[derive(Clone, Debug)]
pub struct EncoderBuffers {
    herders: Vec<[f32; 3]>,
    targets: Vec<[f32; 2]>,
    goal: [f32; 2],
    goal_radius: f32,
    area: [f32; 3],
    max_speed: f32,
    /// The encoder version whose features [`EncoderBuffers::encode`] writes (the rest stay 0).
    encoder_version: u16,
}

impl Default for EncoderBuffers {
    /// Empty buffers that encode every feature of this build's encoder.
    fn default() -> Self {
        EncoderBuffers::for_version(ENCODER_VERSION)
    }
}

impl EncoderBuffers {
    /// Empty buffers that encode only what a model made for encoder `version` reads
    /// (`skyherd_onboard::obs::encode_version`); an unknown version makes every encode fail
    /// with `ObsError::UnknownVersion`.
    pub fn for_version(encoder_version: u16) -> Self {
        EncoderBuffers {
            herders: Vec::new(),
            targets: Vec::new(),
            goal: [0.0; 2],
            goal_radius: 0.0,
            area: [0.0; 3],
            max_speed: 0.0,
            encoder_version,
        }
    }

    /// Copies `world` (usually `Env::observation()`) into the buffers.
    pub fn fill(&mut self, world: &World) {
        self.herders.clear();
        self.herders
            .extend(world.herders.iter().map(|h| h.map(|c| c as f32)));
        self.targets.clear();
        self.targets
            .extend(world.targets.iter().map(|t| t.map(|c| c as f32)));
        self.goal = world.goal.center.map(|c| c as f32);
        self.goal_radius = world.goal.radius as f32;
        self.area = [
            world.area.width as f32,
            world.area.depth as f32,
            world.area.ceiling as f32,
        ];
        self.max_speed = world.limits.herder as f32;
    }

    /// The encoder input of herder `own_index` over the last filled world.
    pub fn input(&self, own_index: usize) -> ObsInput<'_> {
        ObsInput {
            own_index,
            herders: &self.herders,
            targets: &self.targets,
            goal: self.goal,
            goal_radius: self.goal_radius,
            area: self.area,
            max_speed: self.max_speed,
        }
    }

    /// As [`EncoderBuffers::encode`], with the encoding drone's own altitude read as
    /// `own_altitude` (metres) instead of the filled one; the buffers are left as filled.
    pub fn encode_at_altitude(
        &mut self,
        own_index: usize,
        own_altitude: f32,
        out: &mut [f32; FEATURES],
    ) -> Result<LocalFrame, ObsError> {
        let Some(own) = self.herders.get(own_index).copied() else {
            return self.encode(own_index, out);
        };
        self.herders[own_index][2] = own_altitude;
        let frame = self.encode(own_index, out);
        self.herders[own_index] = own;
        frame
    }

    /// Encodes herder `own_index`'s features (those of the buffers' encoder version, the rest
    /// 0) into `out`; returns its local frame, in which the actor's normalised action is
    /// read (`LocalFrame::action_to_world`).
    pub fn encode(
        &self,
        own_index: usize,
        out: &mut [f32; FEATURES],
    ) -> Result<LocalFrame, ObsError> {
        encode_version(&self.input(own_index), self.encoder_version, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Env, Scenario};

    #[test]
    fn encodes_every_herder_of_a_preset_world() {
        let mut env = Env::new(Scenario::paper_drive()).unwrap();
        env.reset(4);
        let mut buffers = EncoderBuffers::default();
        buffers.fill(env.observation());
        let mut features = [0.0f32; FEATURES];
        for i in 0..env.world().herders.len() {
            let frame = buffers.encode(i, &mut features).unwrap();
            assert!(features.iter().all(|f| f.is_finite()));
            let v = frame.action_to_world([1.0, 0.0, 0.0]);
            let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!(
                (speed - 5.0).abs() < 1e-3,
                "full action = top speed: {speed}"
            );
        }
        assert!(buffers.encode(99, &mut features).is_err());
    }
}
