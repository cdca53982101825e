//! A target-tracking sensor: noisy, anonymous detections of all targets, as a pure function
//! of the true positions and a seeded RNG (sim frame, metres).

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, Poisson};
use thiserror::Error;

use skyherd_sim::scenario::Scenario;

/// Sensor model. Units: metres.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorConfig {
    /// Position noise per axis, standard deviation (m).
    pub position_std: f64,
    /// Probability that a target is detected in a scan.
    pub p_detect: f64,
    /// Expected false alarms per scan (Poisson), uniform over the area.
    pub false_alarms_per_scan: f64,
    /// Area the false alarms fall in: `[0, w] x [0, h]` (m, sim frame).
    pub area: [f64; 2],
}

/// Why a sensor could not be built.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum SensorError {
    /// A parameter is out of range; the message says which.
    #[error("invalid sensor configuration: {0}")]
    InvalidConfig(&'static str),
}

impl SensorConfig {
    /// The SITL's sensor for `scenario`: its sensing noise, 95 % detection, no false alarms,
    /// over its floor.
    pub fn for_scenario(scenario: &Scenario) -> SensorConfig {
        SensorConfig {
            position_std: scenario.noise.sensing_std,
            p_detect: 0.95,
            false_alarms_per_scan: 0.0,
            area: [scenario.area.width, scenario.area.depth],
        }
    }
}

/// The sensor with its random stream.
#[derive(Debug, Clone)]
pub struct DetectionSensor {
    config: SensorConfig,
    noise: Normal<f64>,
    false_alarms: Option<Poisson<f64>>,
    rng: ChaCha8Rng,
}

impl DetectionSensor {
    /// A sensor whose randomness is fully determined by `seed`.
    ///
    /// # Errors
    /// [`SensorError::InvalidConfig`] for a negative or non-finite noise, a probability
    /// outside [0, 1], or a degenerate area.
    pub fn new(config: SensorConfig, seed: u64) -> Result<Self, SensorError> {
        if !(config.position_std.is_finite() && config.position_std >= 0.0) {
            return Err(SensorError::InvalidConfig("position_std must be >= 0"));
        }
        if !(0.0..=1.0).contains(&config.p_detect) {
            return Err(SensorError::InvalidConfig("p_detect must be in [0, 1]"));
        }
        if !(config.false_alarms_per_scan.is_finite() && config.false_alarms_per_scan >= 0.0) {
            return Err(SensorError::InvalidConfig(
                "false_alarms_per_scan must be >= 0",
            ));
        }
        if !(config.area.iter().all(|a| a.is_finite() && *a > 0.0)) {
            return Err(SensorError::InvalidConfig("area must be positive"));
        }
        let noise = Normal::new(0.0, config.position_std)
            .map_err(|_| SensorError::InvalidConfig("position_std"))?;
        let false_alarms = if config.false_alarms_per_scan > 0.0 {
            Some(
                Poisson::new(config.false_alarms_per_scan)
                    .map_err(|_| SensorError::InvalidConfig("false_alarms_per_scan"))?,
            )
        } else {
            None
        };
        Ok(Self {
            config,
            noise,
            false_alarms,
            rng: ChaCha8Rng::seed_from_u64(seed),
        })
    }

    /// Restarts the random stream from `seed`, as if the sensor were new.
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// One scan of `targets` (true positions, m, sim frame): each seen with probability
    /// `p_detect`, with Gaussian noise, plus false alarms, shuffled so that the order carries
    /// no identity.
    pub fn scan(&mut self, targets: &[[f64; 2]]) -> Vec<[f64; 2]> {
        let mut out = Vec::with_capacity(targets.len() + 4);
        for t in targets {
            if self.rng.random_bool(self.config.p_detect) {
                out.push([
                    t[0] + self.noise.sample(&mut self.rng),
                    t[1] + self.noise.sample(&mut self.rng),
                ]);
            }
        }
        if let Some(poisson) = &self.false_alarms {
            let n = poisson.sample(&mut self.rng) as usize;
            for _ in 0..n {
                out.push([
                    self.rng.random_range(0.0..self.config.area[0]),
                    self.rng.random_range(0.0..self.config.area[1]),
                ]);
            }
        }
        out.shuffle(&mut self.rng);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> SensorConfig {
        SensorConfig {
            position_std: 0.5,
            p_detect: 0.8,
            false_alarms_per_scan: 2.0,
            area: [100.0, 100.0],
        }
    }

    #[test]
    fn same_seed_same_scans() {
        let targets: Vec<[f64; 2]> = (0..50).map(|i| [i as f64, 50.0]).collect();
        let mut a = DetectionSensor::new(config(), 7).unwrap();
        let mut b = DetectionSensor::new(config(), 7).unwrap();
        for _ in 0..5 {
            assert_eq!(a.scan(&targets), b.scan(&targets));
        }
        let mut c = DetectionSensor::new(config(), 8).unwrap();
        assert_ne!(a.scan(&targets), c.scan(&targets));
    }

    #[test]
    fn statistics_match_the_model() {
        let targets = vec![[50.0, 50.0]; 1];
        let mut s = DetectionSensor::new(
            SensorConfig {
                false_alarms_per_scan: 0.0,
                ..config()
            },
            1,
        )
        .unwrap();
        let (mut seen, mut sq) = (0usize, 0.0);
        let scans = 20_000;
        for _ in 0..scans {
            for d in s.scan(&targets) {
                seen += 1;
                sq += (d[0] - 50.0).powi(2);
            }
        }
        let p = seen as f64 / scans as f64;
        let std = (sq / seen as f64).sqrt();
        assert!((p - 0.8).abs() < 0.02, "p_detect {p}");
        assert!((std - 0.5).abs() < 0.02, "std {std}");
    }

    #[test]
    fn false_alarms_fall_in_the_area_and_bad_configs_are_refused() {
        let mut s = DetectionSensor::new(
            SensorConfig {
                p_detect: 0.0,
                false_alarms_per_scan: 5.0,
                ..config()
            },
            3,
        )
        .unwrap();
        let mut total = 0;
        for _ in 0..1000 {
            let d = s.scan(&[[1.0, 1.0]]);
            assert!(
                d.iter()
                    .all(|p| (0.0..100.0).contains(&p[0]) && (0.0..100.0).contains(&p[1]))
            );
            total += d.len();
        }
        assert!((total as f64 / 1000.0 - 5.0).abs() < 0.3);
        assert!(
            DetectionSensor::new(
                SensorConfig {
                    p_detect: 1.5,
                    ..config()
                },
                0
            )
            .is_err()
        );
        assert!(
            DetectionSensor::new(
                SensorConfig {
                    position_std: f64::NAN,
                    ..config()
                },
                0
            )
            .is_err()
        );
    }
}
