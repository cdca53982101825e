//! Fault injection for a UDP link: packet loss, latency, and link cuts, decided by a pure,
//! seeded [`FaultPlan`] on the simulated clock; [`FaultyUdp`] is the thin socket shell.

use std::collections::VecDeque;
use std::io;
use std::net::{SocketAddr, UdpSocket};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// What to do to the traffic. Times in seconds of simulated time.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FaultConfig {
    /// Probability that a datagram is lost, in [0, 1].
    pub loss: f64,
    /// Delay added to every datagram (s).
    pub latency: f64,
    /// Windows `[start, end)` during which everything is dropped.
    pub cuts: Vec<(f64, f64)>,
}

impl FaultConfig {
    /// The loss a probability, the latency and the cut windows finite and non-negative: on
    /// failure, the setting and what was wrong.
    pub fn validate(&self) -> Result<(), (&'static str, &'static str)> {
        if !(0.0..=1.0).contains(&self.loss) {
            return Err(("loss", "must be a probability in [0, 1]"));
        }
        if !(self.latency.is_finite() && (0.0..=60.0).contains(&self.latency)) {
            return Err(("latency", "must be between 0 and 60 s"));
        }
        if self
            .cuts
            .iter()
            .any(|&(a, b)| !(a.is_finite() && b.is_finite() && a >= 0.0 && b >= a))
        {
            return Err(("cuts", "every window needs 0 <= start <= end, both finite"));
        }
        Ok(())
    }
}

/// The fate of one datagram.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Verdict {
    /// Dropped by random loss.
    Lost,
    /// Dropped because the link is cut.
    Cut,
    /// Delivered at this time (s).
    DeliverAt(f64),
}

/// Counters of what the plan did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Datagrams offered.
    pub offered: u64,
    /// Lost at random.
    pub lost: u64,
    /// Dropped during a cut.
    pub cut: u64,
}

/// Pure decision logic: same seed, same sequence of verdicts.
#[derive(Debug, Clone)]
pub struct FaultPlan {
    config: FaultConfig,
    rng: ChaCha8Rng,
    stats: FaultStats,
}

impl FaultPlan {
    /// A plan with its own random stream.
    pub fn new(config: FaultConfig, seed: u64) -> Self {
        Self {
            config,
            rng: ChaCha8Rng::seed_from_u64(seed),
            stats: FaultStats::default(),
        }
    }

    /// Decide the fate of a datagram sent at `now` (s).
    pub fn decide(&mut self, now: f64) -> Verdict {
        self.stats.offered += 1;
        if self.is_cut(now) {
            self.stats.cut += 1;
            return Verdict::Cut;
        }
        // Draw for every datagram so that the stream of verdicts does not depend on cuts.
        // A loss that is not a probability (NaN) loses nothing rather than panicking; the
        // configs that reach here have passed `FaultConfig::validate`.
        let p = if (0.0..=1.0).contains(&self.config.loss) {
            self.config.loss
        } else {
            0.0
        };
        let lost = self.rng.random_bool(p);
        if lost {
            self.stats.lost += 1;
            return Verdict::Lost;
        }
        Verdict::DeliverAt(now + self.config.latency.max(0.0))
    }

    /// Whether the link is cut at `now`.
    pub fn is_cut(&self, now: f64) -> bool {
        self.config.cuts.iter().any(|&(a, b)| now >= a && now < b)
    }

    /// What happened so far.
    pub fn stats(&self) -> &FaultStats {
        &self.stats
    }
}

/// Datagrams accepted by the plan, waiting for their delivery time.
#[derive(Debug, Clone, Default)]
pub struct DelayLine {
    queue: VecDeque<(f64, SocketAddr, Vec<u8>)>,
}

impl DelayLine {
    /// Queue a datagram for `at` (s). Delivery order is by time, then by arrival.
    pub fn push(&mut self, at: f64, to: SocketAddr, bytes: Vec<u8>) {
        let index = self.queue.partition_point(|(t, _, _)| *t <= at);
        self.queue.insert(index, (at, to, bytes));
    }

    /// Take every datagram due at `now`.
    pub fn due(&mut self, now: f64) -> Vec<(SocketAddr, Vec<u8>)> {
        let n = self.queue.partition_point(|(t, _, _)| *t <= now);
        self.queue.drain(..n).map(|(_, a, b)| (a, b)).collect()
    }

    /// Datagrams still in flight.
    pub fn len(&self) -> usize {
        self.queue.len()
    }

    /// Nothing in flight.
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }
}

/// A UDP socket whose outgoing datagrams go through a [`FaultPlan`] and a [`DelayLine`].
/// Call [`FaultyUdp::flush`] every step to release due datagrams.
#[derive(Debug)]
pub struct FaultyUdp {
    socket: UdpSocket,
    plan: FaultPlan,
    line: DelayLine,
}

impl FaultyUdp {
    /// Wrap a bound socket.
    pub fn new(socket: UdpSocket, plan: FaultPlan) -> Self {
        Self {
            socket,
            plan,
            line: DelayLine::default(),
        }
    }

    /// The socket (for receiving and its address).
    pub fn socket(&self) -> &UdpSocket {
        &self.socket
    }

    /// The plan's counters.
    pub fn stats(&self) -> &FaultStats {
        self.plan.stats()
    }

    /// Offer a datagram at `now`; it is dropped or queued.
    ///
    /// # Errors
    /// I/O errors of datagrams released immediately (zero latency).
    pub fn send_to(&mut self, bytes: &[u8], to: SocketAddr, now: f64) -> io::Result<()> {
        if let Verdict::DeliverAt(at) = self.plan.decide(now) {
            self.line.push(at, to, bytes.to_vec());
        }
        self.flush(now)
    }

    /// Send everything due at `now`.
    ///
    /// # Errors
    /// Socket errors other than an unreachable peer.
    pub fn flush(&mut self, now: f64) -> io::Result<()> {
        for (to, bytes) in self.line.due(now) {
            match self.socket.send_to(&bytes, to) {
                Ok(_) => {}
                Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fault_config_outside_its_ranges_is_refused_and_nan_never_panics() {
        let ok = FaultConfig {
            loss: 0.2,
            latency: 0.2,
            cuts: vec![(3.0, 8.0)],
        };
        assert_eq!(ok.validate(), Ok(()));
        for (config, field) in [
            (
                FaultConfig {
                    loss: f64::NAN,
                    ..ok.clone()
                },
                "loss",
            ),
            (
                FaultConfig {
                    loss: 1.5,
                    ..ok.clone()
                },
                "loss",
            ),
            (
                FaultConfig {
                    latency: -0.1,
                    ..ok.clone()
                },
                "latency",
            ),
            (
                FaultConfig {
                    latency: f64::INFINITY,
                    ..ok.clone()
                },
                "latency",
            ),
            (
                FaultConfig {
                    cuts: vec![(5.0, 1.0)],
                    ..ok.clone()
                },
                "cuts",
            ),
            (
                FaultConfig {
                    cuts: vec![(f64::NAN, 1.0)],
                    ..ok.clone()
                },
                "cuts",
            ),
        ] {
            assert_eq!(config.validate().map_err(|e| e.0), Err(field), "{config:?}");
            // A plan made from it anyway does not panic.
            let mut plan = FaultPlan::new(config, 1);
            let _ = plan.decide(1.0);
        }
    }

    #[test]
    fn loss_rate_latency_and_cuts() {
        let mut plan = FaultPlan::new(
            FaultConfig {
                loss: 0.2,
                latency: 0.2,
                cuts: vec![(5.0, 10.0)],
            },
            42,
        );
        let mut delivered = 0;
        for k in 0..10_000 {
            let now = k as f64 * 0.0004; // 0..4 s: before the cut
            match plan.decide(now) {
                Verdict::DeliverAt(at) => {
                    assert!((at - now - 0.2).abs() < 1e-12);
                    delivered += 1;
                }
                Verdict::Lost => {}
                Verdict::Cut => panic!("no cut before 5 s"),
            }
        }
        assert!((delivered as f64 / 10_000.0 - 0.8).abs() < 0.02);
        assert_eq!(plan.decide(7.0), Verdict::Cut);
        assert!(plan.is_cut(9.99) && !plan.is_cut(10.0));
        let replay: Vec<Verdict> = {
            let mut p = FaultPlan::new(
                FaultConfig {
                    loss: 0.5,
                    ..FaultConfig::default()
                },
                1,
            );
            (0..20).map(|_| p.decide(0.0)).collect()
        };
        let mut p = FaultPlan::new(
            FaultConfig {
                loss: 0.5,
                ..FaultConfig::default()
            },
            1,
        );
        assert_eq!(replay, (0..20).map(|_| p.decide(0.0)).collect::<Vec<_>>());
    }

    #[test]
    fn delay_line_releases_in_time_order() {
        let a: SocketAddr = ([127, 0, 0, 1], 1).into();
        let mut line = DelayLine::default();
        line.push(0.3, a, vec![3]);
        line.push(0.1, a, vec![1]);
        line.push(0.2, a, vec![2]);
        assert!(line.due(0.05).is_empty());
        assert_eq!(
            line.due(0.2)
                .into_iter()
                .map(|(_, b)| b[0])
                .collect::<Vec<_>>(),
            vec![1, 2]
        );
        assert_eq!(line.len(), 1);
    }
}
