//! A tiny deterministic target-motion and detection generator for the tracker's accuracy test
//! and benchmark (the simulator crate is independent of the ground station).
//!
//! Targets: velocity random walk (Gaussian acceleration) with short-range separation, speed capped, turned back smoothly
//! near the walls of a square arena. Detections: each target seen with probability `p_detect` with Gaussian
//! position noise, plus uniform false alarms, shuffled so the order carries no identity.

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Parameters of the generated world. Units: metres, seconds.
#[derive(Debug, Clone)]
pub struct ScenarioConfig {
    pub targets: usize,
    pub arena: f64,
    pub dt: f64,
    pub max_speed: f64,
    pub accel_std: f64,
    pub measurement_std: f64,
    pub p_detect: f64,
    pub false_alarms_per_scan: usize,
}

/// Truth and detections, advanced one scan at a time.
pub struct Scenario {
    pub config: ScenarioConfig,
    pub positions: Vec<[f64; 2]>,
    pub velocities: Vec<[f64; 2]>,
    rng: ChaCha8Rng,
}

impl Scenario {
    pub fn new(config: ScenarioConfig, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let positions = (0..config.targets)
            .map(|_| {
                [
                    rng.random_range(0.0..config.arena),
                    rng.random_range(0.0..config.arena),
                ]
            })
            .collect();
        let velocities = (0..config.targets)
            .map(|_| {
                let a = rng.random_range(0.0..std::f64::consts::TAU);
                let s = rng.random_range(0.0..config.max_speed);
                [s * a.cos(), s * a.sin()]
            })
            .collect();
        Self {
            config,
            positions,
            velocities,
            rng,
        }
    }

    /// Advance the truth by one scan period.
    pub fn step(&mut self) {
        let c = &self.config;
        let accel = Normal::new(0.0, c.accel_std).expect("finite std");
        // Separation, as in the flock: targets push apart inside SEPARATION metres, so two
        // never sit on top of each other (the tracker merges tracks that do).
        const SEPARATION: f64 = 2.5;
        let n = self.positions.len();
        let mut push = vec![[0.0; 2]; n];
        for i in 0..n {
            for j in i + 1..n {
                let dx = self.positions[i][0] - self.positions[j][0];
                let dy = self.positions[i][1] - self.positions[j][1];
                let d = dx.hypot(dy);
                if d < SEPARATION && d > 1e-9 {
                    let a = 6.0 * (SEPARATION - d) / SEPARATION / d;
                    push[i][0] += a * dx;
                    push[i][1] += a * dy;
                    push[j][0] -= a * dx;
                    push[j][1] -= a * dy;
                }
            }
        }
        for ((p, v), push) in self
            .positions
            .iter_mut()
            .zip(&mut self.velocities)
            .zip(&push)
        {
            for a in 0..2 {
                // Soft walls: within 10 m of a wall, accelerate inward at up to 2 m/s^2.
                // Targets turn back smoothly, as a herded animal would, instead of bouncing.
                let wall = if p[a] < 10.0 {
                    2.0 * (10.0 - p[a]) / 10.0
                } else if p[a] > c.arena - 10.0 {
                    -2.0 * (p[a] - (c.arena - 10.0)) / 10.0
                } else {
                    0.0
                };
                v[a] += (accel.sample(&mut self.rng) + wall + push[a]) * c.dt;
            }
            let speed = v[0].hypot(v[1]);
            if speed > c.max_speed {
                v[0] *= c.max_speed / speed;
                v[1] *= c.max_speed / speed;
            }
            for a in 0..2 {
                p[a] = (p[a] + v[a] * c.dt).clamp(0.0, c.arena);
            }
        }
    }

    /// One scan of anonymous detections of the current truth.
    pub fn detect(&mut self) -> Vec<[f64; 2]> {
        let c = &self.config;
        let noise = Normal::new(0.0, c.measurement_std).expect("finite std");
        let mut out = Vec::with_capacity(self.positions.len() + c.false_alarms_per_scan);
        for p in &self.positions {
            if self.rng.random_bool(c.p_detect) {
                out.push([
                    p[0] + noise.sample(&mut self.rng),
                    p[1] + noise.sample(&mut self.rng),
                ]);
            }
        }
        for _ in 0..c.false_alarms_per_scan {
            out.push([
                self.rng.random_range(0.0..c.arena),
                self.rng.random_range(0.0..c.arena),
            ]);
        }
        out.shuffle(&mut self.rng);
        out
    }
}
