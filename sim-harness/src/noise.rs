//! Seeded noise: per-episode boids-parameter noise, sensing noise, actuation noise.
//!
//! Each kind draws from its own ChaCha8 stream of the episode seed, so switching one off does not
//! change what the others (or the spawn) draw. Levels (0 = off):
//! * `boids_param_rel_std` (default 0.2): each of a1..a5 and G1 becomes `p + N(0, (rel p)^2)`
//!   at reset, the paper's test-time setting ("std = one fifth of the default"). A draw below 0 is
//!   clamped to 0: a negative weight would turn the rule around rather than weaken it.
//! * `sensing_std` (paper presets 0.5 m; indoor 0.02 m): Gaussian on every observed herder
//!   coordinate and target x-y; the goal and the targets' z = 0 are known exactly. A GPS-class
//!   error outdoors, a motion-capture-class error indoors.
//! * `actuation_std` (paper presets 0.25 m/s = 5 % of the herder top speed; indoor 0.05 m/s):
//!   Gaussian added to each commanded velocity component before the speed cap.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::world::{BoidsParams, World};

/// Noise levels; every field 0 means a noise-free world.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseConfig {
    /// Std of each boids parameter's per-episode noise, as a fraction of its value.
    pub boids_param_rel_std: f64,
    /// Std of the sensing noise on positions, metres.
    pub sensing_std: f64,
    /// Std of the actuation noise on velocity components, m/s.
    pub actuation_std: f64,
}

impl NoiseConfig {
    /// No noise at all.
    pub const NONE: NoiseConfig = NoiseConfig {
        boids_param_rel_std: 0.0,
        sensing_std: 0.0,
        actuation_std: 0.0,
    };

    /// The paper presets' test-time levels.
    pub const PAPER_TEST: NoiseConfig = NoiseConfig {
        boids_param_rel_std: 0.2,
        sensing_std: 0.5,
        actuation_std: 0.25,
    };

    /// Whether every level is zero.
    pub fn is_off(&self) -> bool {
        self.boids_param_rel_std == 0.0 && self.sensing_std == 0.0 && self.actuation_std == 0.0
    }
}

/// Stream numbers of one episode seed.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Stream {
    Spawn = 0,
    BoidsParams = 1,
    Sensing = 2,
    Actuation = 3,
    Wind = 4,
}

/// A ChaCha8 generator for `stream` of `seed`.
pub(crate) fn stream_rng(seed: u64, stream: Stream) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream as u64);
    rng
}

/// Per-episode boids-parameter noise: each value gets `N(0, (rel * value)^2)`, clamped at 0.
pub fn perturb_params<R: Rng>(params: BoidsParams, rel_std: f64, rng: &mut R) -> BoidsParams {
    if rel_std <= 0.0 {
        return params;
    }
    let mut a = params.to_array();
    for v in &mut a {
        *v = (*v + gauss(rng) * rel_std * *v).max(0.0);
    }
    params.with_array(a)
}

/// Adds actuation noise to each command in place.
pub fn actuate<R: Rng>(actions: &mut [[f64; 3]], std: f64, rng: &mut R) {
    if std <= 0.0 {
        return;
    }
    for a in actions {
        for c in a.iter_mut() {
            *c += std * gauss(rng);
        }
    }
}

/// Writes `truth` with sensing noise into `sensed` (same shapes; reuses its buffers).
pub fn sense<R: Rng>(truth: &World, sensed: &mut World, std: f64, rng: &mut R) {
    sensed.clone_from(truth);
    if std <= 0.0 {
        return;
    }
    for h in &mut sensed.herders {
        for c in h.iter_mut() {
            *c += std * gauss(rng);
        }
    }
    for t in &mut sensed.targets {
        for c in t.iter_mut() {
            *c += std * gauss(rng);
        }
    }
}

fn gauss<R: Rng>(rng: &mut R) -> f64 {
    StandardNormal.sample(rng)
}
