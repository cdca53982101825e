//! Multi-target tracking over anonymous 2-D detections.
//!
//! Frame and units: the simulator frame (x east, y north), metres, seconds, m/s. The tracker
//! is pure: every [`Tracker::update`] takes the detections of one scan and the time since the
//! previous scan; there is no clock and no I/O.
//!
//! Per scan:
//! 1. **Predict** every track with a constant-velocity Kalman filter (white-noise acceleration).
//! 2. **Gate**: detections are binned into a uniform grid whose cell is the largest gate radius,
//!    so each track only looks at the 3 x 3 cells around its prediction (O(N) for bounded
//!    density, not O(N^2)). A pair passes when its Mahalanobis distance is within the chi-square
//!    gate and its Euclidean distance within [`TrackerConfig::max_gate_radius`].
//! 3. **Assign**: gated pairs form a bipartite graph; union-find splits it into clusters. A
//!    one-to-one cluster is assigned directly, a small cluster exactly with the Hungarian
//!    algorithm (O(k^3) on k <= [`TrackerConfig::max_exact_cluster`]), a larger one greedily by
//!    ascending cost. Plain Hungarian over all 1024 x 1024 pairs would cost ~10^9 operations.
//! 4. **Update** assigned tracks; **birth**: each unassigned detection starts a tentative track,
//!    confirmed once it has been hit in `confirm_hits` of the last `confirm_window` scans;
//!    **death**: a tentative track that can no longer reach that count, or a confirmed track
//!    missed `max_misses` scans in a row, is deleted.
//!
//! Because x and y share the same motion model and the measurement noise is isotropic, the
//! 4 x 4 covariance of `[x, y, vx, vy]` stays block-diagonal with two identical 2 x 2 blocks
//! (position, velocity per axis). The filter stores one such block: exact, and 3 numbers
//! instead of 10.
//!
//! ```
//! use skyherd_ground::tracking::{Tracker, TrackerConfig};
//!
//! let mut tracker = Tracker::new(TrackerConfig::default()).unwrap();
//! // One target moving east at 1 m/s, seen every 0.1 s.
//! for step in 0..20 {
//!     let x = 10.0 + 0.1 * step as f64;
//!     tracker.update(0.1, &[[x, 5.0]]).unwrap();
//! }
//! let confirmed: Vec<_> = tracker.confirmed().collect();
//! assert_eq!(confirmed.len(), 1);
//! assert!((confirmed[0].velocity[0] - 1.0).abs() < 0.2);
//! ```

use thiserror::Error;

/// Why a tracker could not be built or updated.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum TrackerError {
    /// A configuration value is out of range; the message says which and why.
    #[error("invalid tracker configuration: {0}")]
    InvalidConfig(&'static str),
    /// The time since the previous scan must be finite and > 0 (seconds).
    #[error("invalid time step {0} s: must be finite and > 0")]
    InvalidTimeStep(f64),
}

/// Tuning of the tracker. Units: metres, seconds.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackerConfig {
    /// Standard deviation of the detection position noise, per axis (m).
    pub measurement_std: f64,
    /// Standard deviation of the white-noise acceleration driving the motion model (m/s^2).
    pub acceleration_std: f64,
    /// Standard deviation of the velocity of a newborn track, per axis (m/s): about the
    /// targets' top speed.
    pub initial_velocity_std: f64,
    /// Squared Mahalanobis distance gate; 13.8 keeps 99.9% of true detections (chi-square, 2 dof).
    pub gate_chi2: f64,
    /// Hard Euclidean gate (m): bounds the grid cell and keeps coasting tracks from grabbing
    /// far detections.
    pub max_gate_radius: f64,
    /// Hits needed within the confirmation window (the M of M-of-N).
    pub confirm_hits: u8,
    /// Length of the confirmation window in scans (the N of M-of-N, at most 32).
    pub confirm_window: u8,
    /// A confirmed track is deleted after this many consecutive missed scans.
    pub max_misses: u8,
    /// Clusters with at most this many tracks and detections are assigned exactly
    /// (Hungarian); larger ones greedily.
    pub max_exact_cluster: usize,
    /// No track is born within this distance (m) of a confirmed track's prediction: such a
    /// detection is far more likely a noise outlier of that target than a new one, and a
    /// track born from it would compete with the original. Keep it below the targets'
    /// closest spacing.
    pub birth_exclusion_radius: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            measurement_std: 0.3,
            acceleration_std: 3.0,
            initial_velocity_std: 3.0,
            gate_chi2: 13.8,
            max_gate_radius: 3.0,
            confirm_hits: 3,
            confirm_window: 5,
            max_misses: 5,
            max_exact_cluster: 40,
            birth_exclusion_radius: 1.5,
        }
    }
}

/// The world a tracker is tuned for (see [`TrackerConfig::scaled`]). Metres, m/s, seconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedWorld {
    /// Goal radius: the length scale (45 m in the paper's arena).
    pub goal_radius: f64,
    /// Top speed of anything in the world (the herders' limit bounds the targets'), m/s.
    pub max_speed: f64,
    /// Detection position noise per axis, m.
    pub measurement_std: f64,
    /// Time between scans, s.
    pub scan_period_s: f64,
}

impl TrackerConfig {
    /// The defaults (tuned for the paper's arena: 45 m goal radius, 5 m/s herders) scaled to
    /// `world`: lengths with the goal radius, speeds with the speed limit.
    ///
    /// The hard gate is also kept wide enough for the worst motion between two scans: a target
    /// at top speed that reverses (`2 v dt`) plus the noise of both fixes (`4 sigma`). Scaling
    /// the paper's 3 m gate by length alone gives 6 cm in the 10 m room, less than a vehicle
    /// kicked by a drone moves in one 0.1 s scan; its detection then fell outside the gate,
    /// a second track was born beside it, and the drones flew on a flock with ghosts (the
    /// wrong number of targets in half the snapshots).
    pub fn scaled(world: TrackedWorld) -> TrackerConfig {
        let defaults = TrackerConfig::default();
        let length = world.goal_radius / 45.0;
        let speed = world.max_speed / 5.0;
        let sigma = world.measurement_std;
        let motion_gate = 2.0 * world.max_speed * world.scan_period_s + 4.0 * sigma;
        TrackerConfig {
            measurement_std: sigma,
            acceleration_std: defaults.acceleration_std * speed * speed / length,
            initial_velocity_std: defaults.initial_velocity_std * speed,
            max_gate_radius: (defaults.max_gate_radius * length)
                .max(5.0 * sigma)
                .max(motion_gate),
            birth_exclusion_radius: defaults.birth_exclusion_radius * length,
            ..defaults
        }
    }

    fn validate(&self) -> Result<(), TrackerError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.measurement_std) {
            return Err(TrackerError::InvalidConfig("measurement_std must be > 0"));
        }
        if !positive(self.acceleration_std) {
            return Err(TrackerError::InvalidConfig("acceleration_std must be > 0"));
        }
        if !positive(self.initial_velocity_std) {
            return Err(TrackerError::InvalidConfig(
                "initial_velocity_std must be > 0",
            ));
        }
        if !positive(self.gate_chi2) {
            return Err(TrackerError::InvalidConfig("gate_chi2 must be > 0"));
        }
        if !positive(self.max_gate_radius) {
            return Err(TrackerError::InvalidConfig("max_gate_radius must be > 0"));
        }
        if self.confirm_window == 0 || self.confirm_window > 32 {
            return Err(TrackerError::InvalidConfig(
                "confirm_window must be in 1..=32",
            ));
        }
        if self.confirm_hits == 0 || self.confirm_hits > self.confirm_window {
            return Err(TrackerError::InvalidConfig(
                "confirm_hits must be in 1..=confirm_window",
            ));
        }
        if self.max_misses == 0 {
            return Err(TrackerError::InvalidConfig("max_misses must be >= 1"));
        }
        if !(self.birth_exclusion_radius.is_finite() && self.birth_exclusion_radius >= 0.0) {
            return Err(TrackerError::InvalidConfig(
                "birth_exclusion_radius must be >= 0",
            ));
        }
        if self.max_exact_cluster == 0 {
            return Err(TrackerError::InvalidConfig(
                "max_exact_cluster must be >= 1",
            ));
        }
        Ok(())
    }
}

/// Stable identity of a track, never reused within one [`Tracker`].
pub type TrackId = u64;

/// Whether a track has earned confirmation yet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackStatus {
    /// Born from an unassigned detection, not yet `confirm_hits` of `confirm_window`.
    Tentative,
    /// Confirmed; reported to the mission.
    Confirmed,
}

/// One track: a constant-velocity Kalman filter and its bookkeeping.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    /// Stable identity.
    pub id: TrackId,
    /// Estimated position (m, sim frame).
    pub position: [f64; 2],
    /// Estimated velocity (m/s, sim frame).
    pub velocity: [f64; 2],
    /// Per-axis covariance block `[var(p), cov(p, v), var(v)]` (m^2, m^2/s, m^2/s^2).
    pub covariance: [f64; 3],
    /// Tentative or confirmed.
    pub status: TrackStatus,
    /// Consecutive scans without a detection.
    pub misses: u8,
    /// Scans since birth.
    pub age: u32,
    /// Bit i set = hit i scans ago (bit 0 = the latest scan).
    hit_history: u32,
}

impl Track {
    /// Standard deviation of the position estimate, per axis (m).
    pub fn position_std(&self) -> f64 {
        self.covariance[0].max(0.0).sqrt()
    }

    fn predict(&mut self, dt: f64, accel_var: f64) {
        self.position[0] += self.velocity[0] * dt;
        self.position[1] += self.velocity[1] * dt;
        let [p, c, v] = self.covariance;
        // P = F P F^T + Q, F = [[1, dt], [0, 1]], Q = q [[dt^4/4, dt^3/2], [dt^3/2, dt^2]].
        let dt2 = dt * dt;
        self.covariance = [
            p + 2.0 * dt * c + dt2 * v + accel_var * dt2 * dt2 / 4.0,
            c + dt * v + accel_var * dt2 * dt / 2.0,
            v + accel_var * dt2,
        ];
    }

    fn correct(&mut self, z: [f64; 2], meas_var: f64) {
        let [p, c, v] = self.covariance;
        let s = p + meas_var;
        let (kp, kv) = (p / s, c / s);
        for ((p, v), z) in self.position.iter_mut().zip(&mut self.velocity).zip(z) {
            let innovation = z - *p;
            *p += kp * innovation;
            *v += kv * innovation;
        }
        // Joseph form is unnecessary for a 2 x 2 block with this gain; keep it symmetric.
        self.covariance = [(1.0 - kp) * p, (1.0 - kp) * c, v - kv * c];
    }

    fn hits_in_window(&self, window: u8) -> u32 {
        let mask = if window >= 32 {
            u32::MAX
        } else {
            (1u32 << window) - 1
        };
        (self.hit_history & mask).count_ones()
    }
}

/// What one update did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UpdateReport {
    /// Detections assigned to existing tracks.
    pub assigned: usize,
    /// Tentative tracks born from unassigned detections.
    pub born: usize,
    /// Tracks that became confirmed this scan.
    pub confirmed: usize,
    /// Tracks deleted this scan (misses or failed confirmation).
    pub deleted: usize,
    /// Unassigned detections not allowed to start a track: inside some track's gate or
    /// within [`TrackerConfig::birth_exclusion_radius`] of a confirmed track.
    pub suppressed_births: usize,
    /// Detections dropped because a coordinate was NaN or infinite.
    pub rejected_detections: usize,
    /// Gated track-detection pairs.
    pub gated_pairs: usize,
    /// Size (tracks + detections) of the largest assignment cluster.
    pub largest_cluster: usize,
    /// Clusters too big for the exact assignment, solved greedily.
    pub greedy_clusters: usize,
}

/// A gated track-detection pair with its assignment cost (negative log-likelihood).
#[derive(Debug, Clone, Copy)]
struct Edge {
    track: u32,
    detection: u32,
    cost: f64,
    cluster: u32,
}

/// Scratch buffers reused across updates so that a steady-state update does not allocate.
#[derive(Debug, Default, Clone)]
struct Scratch {
    valid: Vec<[f64; 2]>,
    cell_of: Vec<u32>,
    cell_start: Vec<u32>,
    sorted: Vec<u32>,
    edges: Vec<Edge>,
    parent: Vec<u32>,
    track_match: Vec<u32>,
    detection_taken: Vec<bool>,
    birth_blocked: Vec<bool>,
    local_tracks: Vec<u32>,
    local_detections: Vec<u32>,
    cost: Vec<f64>,
    hungarian: Hungarian,
}

const UNASSIGNED: u32 = u32::MAX;

/// Extra assignment cost for a tentative track (a log-likelihood ratio; 4 to 12 measured alike): a
/// confirmed track keeps a contested detection unless the tentative one fits clearly better,
/// so a track born from one noise outlier cannot take over its target.
const TENTATIVE_PENALTY: f64 = 8.0;

/// The multi-target tracker; see the [module docs](self).
#[derive(Debug, Clone)]
pub struct Tracker {
    config: TrackerConfig,
    tracks: Vec<Track>,
    next_id: TrackId,
    scratch: Scratch,
}

impl Tracker {
    /// A tracker with no tracks.
    ///
    /// # Errors
    /// [`TrackerError::InvalidConfig`] when a value is out of range.
    pub fn new(config: TrackerConfig) -> Result<Self, TrackerError> {
        config.validate()?;
        Ok(Self {
            config,
            tracks: Vec::new(),
            next_id: 1,
            scratch: Scratch::default(),
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// All live tracks, tentative and confirmed.
    pub fn tracks(&self) -> &[Track] {
        &self.tracks
    }

    /// Confirmed tracks only: what the mission should believe.
    pub fn confirmed(&self) -> impl Iterator<Item = &Track> + '_ {
        self.tracks
            .iter()
            .filter(|t| t.status == TrackStatus::Confirmed)
    }

    /// Advance all tracks by `dt` seconds and fold in one scan of anonymous detections
    /// (sim-frame metres). Non-finite detections are dropped and counted.
    ///
    /// # Errors
    /// [`TrackerError::InvalidTimeStep`] when `dt` is not finite and positive; the tracker is
    /// left unchanged.
    pub fn update(
        &mut self,
        dt: f64,
        detections: &[[f64; 2]],
    ) -> Result<UpdateReport, TrackerError> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(TrackerError::InvalidTimeStep(dt));
        }
        let mut report = UpdateReport::default();
        let mut scratch = std::mem::take(&mut self.scratch);

        scratch.valid.clear();
        for d in detections {
            if d[0].is_finite() && d[1].is_finite() {
                scratch.valid.push(*d);
            } else {
                report.rejected_detections += 1;
            }
        }

        let accel_var = self.config.acceleration_std.powi(2);
        for track in &mut self.tracks {
            track.predict(dt, accel_var);
            track.age = track.age.saturating_add(1);
            track.hit_history <<= 1;
        }

        self.gate(&mut scratch, &mut report);
        self.assign(&mut scratch, &mut report);

        // Update assigned tracks, age the others.
        let meas_var = self.config.measurement_std.powi(2);
        for (ti, track) in self.tracks.iter_mut().enumerate() {
            let matched = scratch.track_match[ti];
            if matched == UNASSIGNED {
                track.misses = track.misses.saturating_add(1);
            } else {
                track.correct(scratch.valid[matched as usize], meas_var);
                track.misses = 0;
                track.hit_history |= 1;
                report.assigned += 1;
                if track.status == TrackStatus::Tentative
                    && track.hits_in_window(self.config.confirm_window)
                        >= u32::from(self.config.confirm_hits)
                {
                    track.status = TrackStatus::Confirmed;
                    report.confirmed += 1;
                }
            }
        }

        // Death.
        let config = &self.config;
        let before = self.tracks.len();
        self.tracks.retain(|t| match t.status {
            TrackStatus::Confirmed => t.misses < config.max_misses,
            TrackStatus::Tentative => {
                // Scans left in the window this track can still be hit in.
                let seen = t.age.min(u32::from(config.confirm_window)) + 1;
                let remaining = u32::from(config.confirm_window).saturating_sub(seen);
                t.hits_in_window(config.confirm_window) + remaining
                    >= u32::from(config.confirm_hits)
            }
        });
        report.deleted = before - self.tracks.len();

        // Birth.
        let pos_var = meas_var;
        let vel_var = self.config.initial_velocity_std.powi(2);
        for (di, d) in scratch.valid.iter().enumerate() {
            if scratch.detection_taken[di] {
                continue;
            }
            if scratch.birth_blocked[di] {
                report.suppressed_births += 1;
            } else {
                self.tracks.push(Track {
                    id: self.next_id,
                    position: *d,
                    velocity: [0.0, 0.0],
                    covariance: [pos_var, 0.0, vel_var],
                    status: if self.config.confirm_hits <= 1 {
                        TrackStatus::Confirmed
                    } else {
                        TrackStatus::Tentative
                    },
                    misses: 0,
                    age: 0,
                    hit_history: 1,
                });
                self.next_id += 1;
                report.born += 1;
            }
        }

        self.scratch = scratch;
        Ok(report)
    }

    /// Fill `scratch.edges` with gated pairs, using a uniform grid over the detections.
    fn gate(&self, scratch: &mut Scratch, report: &mut UpdateReport) {
        scratch.edges.clear();
        scratch.birth_blocked.clear();
        scratch.birth_blocked.resize(scratch.valid.len(), false);
        let detections = &scratch.valid;
        if detections.is_empty() || self.tracks.is_empty() {
            return;
        }
        let meas_var = self.config.measurement_std.powi(2);
        let chi2 = self.config.gate_chi2;
        let max_r = self.config.max_gate_radius;
        // The cell must be at least the widest gate so the 3 x 3 neighbourhood covers it.
        let widest = self
            .tracks
            .iter()
            .map(|t| (chi2 * (t.covariance[0] + meas_var)).sqrt())
            .fold(0.0_f64, f64::max)
            .min(max_r)
            .max(self.config.birth_exclusion_radius);

        let (mut min, mut max) = ([f64::MAX; 2], [f64::MIN; 2]);
        for d in detections {
            for a in 0..2 {
                min[a] = min[a].min(d[a]);
                max[a] = max[a].max(d[a]);
            }
        }
        // Bound the grid to ~4 cells per detection: a few far-off false alarms must not blow
        // up memory.
        let mut cell = widest.max(1e-6);
        let budget = (4 * detections.len()).max(16) as f64;
        let span = [(max[0] - min[0]).max(0.0), (max[1] - min[1]).max(0.0)];
        while (span[0] / cell + 1.0) * (span[1] / cell + 1.0) > budget {
            cell *= 2.0;
        }
        let nx = (span[0] / cell) as usize + 1;
        let ny = (span[1] / cell) as usize + 1;
        // A track more than one cell outside the grid cannot gate with anything.
        let cell_index = |p: [f64; 2]| -> Option<(isize, isize)> {
            let cx = ((p[0] - min[0]) / cell).floor();
            let cy = ((p[1] - min[1]) / cell).floor();
            (cx >= -1.0 && cy >= -1.0 && cx <= nx as f64 && cy <= ny as f64)
                .then_some((cx as isize, cy as isize))
        };

        // Counting sort of detections by cell.
        scratch.cell_start.clear();
        scratch.cell_start.resize(nx * ny + 1, 0);
        scratch.cell_of.clear();
        for d in detections {
            let cx = (((d[0] - min[0]) / cell) as usize).min(nx - 1);
            let cy = (((d[1] - min[1]) / cell) as usize).min(ny - 1);
            let c = (cy * nx + cx) as u32;
            scratch.cell_of.push(c);
            scratch.cell_start[c as usize + 1] += 1;
        }
        for i in 0..nx * ny {
            scratch.cell_start[i + 1] += scratch.cell_start[i];
        }
        scratch.sorted.clear();
        scratch.sorted.resize(detections.len(), 0);
        {
            // Reuse `parent` as the per-cell write cursor.
            let cursor = &mut scratch.parent;
            cursor.clear();
            cursor.extend_from_slice(&scratch.cell_start[..nx * ny]);
            for (di, &c) in scratch.cell_of.iter().enumerate() {
                let slot = &mut cursor[c as usize];
                scratch.sorted[*slot as usize] = di as u32;
                *slot += 1;
            }
        }

        let max_r2 = max_r * max_r;
        let exclusion2 = self.config.birth_exclusion_radius.powi(2);
        for (ti, track) in self.tracks.iter().enumerate() {
            let s = track.covariance[0] + meas_var;
            // Negative log-likelihood up to a constant: d^2/S + ln|S| with |S| = s^2, offset by
            // ln(R^2) so it stays >= 0. Without the log term the most uncertain track (a
            // newborn with a wide gate) would win every contest.
            let confirmed = track.status == TrackStatus::Confirmed;
            let log_det =
                2.0 * (s / meas_var).ln() + if confirmed { 0.0 } else { TENTATIVE_PENALTY };
            let Some((cx, cy)) = cell_index(track.position) else {
                continue;
            };
            for gy in (cy - 1).max(0)..=(cy + 1).min(ny as isize - 1) {
                for gx in (cx - 1).max(0)..=(cx + 1).min(nx as isize - 1) {
                    let c = gy as usize * nx + gx as usize;
                    let range = scratch.cell_start[c] as usize..scratch.cell_start[c + 1] as usize;
                    for &di in &scratch.sorted[range] {
                        let d = detections[di as usize];
                        let (ex, ey) = (d[0] - track.position[0], d[1] - track.position[1]);
                        let dist2 = ex * ex + ey * ey;
                        let mahalanobis2 = dist2 / s;
                        let gated = mahalanobis2 <= chi2 && dist2 <= max_r2;
                        if gated || (confirmed && dist2 <= exclusion2) {
                            scratch.birth_blocked[di as usize] = true;
                        }
                        if gated {
                            let cost = mahalanobis2 + log_det;
                            scratch.edges.push(Edge {
                                track: ti as u32,
                                detection: di,
                                cost,
                                cluster: 0,
                            });
                        }
                    }
                }
            }
        }
        report.gated_pairs = scratch.edges.len();
    }

    /// Assign detections to tracks cluster by cluster; fills `track_match` / `detection_taken`.
    fn assign(&self, scratch: &mut Scratch, report: &mut UpdateReport) {
        let n_tracks = self.tracks.len();
        let n_det = scratch.valid.len();
        scratch.track_match.clear();
        scratch.track_match.resize(n_tracks, UNASSIGNED);
        scratch.detection_taken.clear();
        scratch.detection_taken.resize(n_det, false);
        if scratch.edges.is_empty() {
            return;
        }

        // Union-find over tracks [0, n_tracks) and detections [n_tracks, n_tracks + n_det).
        let parent = &mut scratch.parent;
        parent.clear();
        parent.extend(0..(n_tracks + n_det) as u32);
        fn find(parent: &mut [u32], mut x: u32) -> u32 {
            while parent[x as usize] != x {
                let grand = parent[parent[x as usize] as usize];
                parent[x as usize] = grand;
                x = grand;
            }
            x
        }
        for e in &scratch.edges {
            let a = find(parent, e.track);
            let b = find(parent, n_tracks as u32 + e.detection);
            if a != b {
                parent[a.max(b) as usize] = a.min(b);
            }
        }
        for e in &mut scratch.edges {
            e.cluster = find(parent, e.track);
        }
        scratch
            .edges
            .sort_unstable_by(|a, b| a.cluster.cmp(&b.cluster).then(a.cost.total_cmp(&b.cost)));

        let mut start = 0;
        while start < scratch.edges.len() {
            let cluster = scratch.edges[start].cluster;
            let mut end = start + 1;
            while end < scratch.edges.len() && scratch.edges[end].cluster == cluster {
                end += 1;
            }
            if end - start == 1 {
                // One edge means one track and one detection: nothing to decide.
                let e = scratch.edges[start];
                scratch.track_match[e.track as usize] = e.detection;
                scratch.detection_taken[e.detection as usize] = true;
                report.largest_cluster = report.largest_cluster.max(2);
            } else {
                self.assign_cluster(scratch, start..end, report);
            }
            start = end;
        }
    }

    fn assign_cluster(
        &self,
        scratch: &mut Scratch,
        range: std::ops::Range<usize>,
        report: &mut UpdateReport,
    ) {
        let Scratch {
            edges,
            local_tracks,
            local_detections,
            cost,
            hungarian,
            track_match,
            detection_taken,
            ..
        } = scratch;
        let edges = &edges[range];
        local_tracks.clear();
        local_detections.clear();
        for e in edges {
            local_tracks.push(e.track);
            local_detections.push(e.detection);
        }
        local_tracks.sort_unstable();
        local_tracks.dedup();
        local_detections.sort_unstable();
        local_detections.dedup();
        let (nt, nd) = (local_tracks.len(), local_detections.len());
        report.largest_cluster = report.largest_cluster.max(nt + nd);

        if nt.max(nd) > self.config.max_exact_cluster {
            // Edges are sorted by ascending cost within the cluster.
            report.greedy_clusters += 1;
            for e in edges {
                if track_match[e.track as usize] == UNASSIGNED
                    && !detection_taken[e.detection as usize]
                {
                    track_match[e.track as usize] = e.detection;
                    detection_taken[e.detection as usize] = true;
                }
            }
            return;
        }

        // Square matrix; a non-gated cell costs more than any gated pair, so the solver
        // leaves a track or a detection unassigned only when it has to.
        let n = nt.max(nd);
        let miss = edges.iter().map(|e| e.cost).fold(0.0, f64::max) + 1.0;
        cost.clear();
        cost.resize(n * n, miss);
        for e in edges {
            let r = local_tracks.binary_search(&e.track).unwrap_or(0);
            let c = local_detections.binary_search(&e.detection).unwrap_or(0);
            cost[r * n + c] = e.cost;
        }
        let assignment = hungarian.solve(n, cost);
        for (r, &c) in assignment.iter().enumerate() {
            if r < nt && c < nd && cost[r * n + c] < miss {
                let (t, d) = (local_tracks[r], local_detections[c]);
                track_match[t as usize] = d;
                detection_taken[d as usize] = true;
            }
        }
    }
}

/// Minimum-cost perfect assignment on a dense square matrix (Hungarian algorithm with
/// potentials, O(n^3)); only ever run on small gated clusters.
#[derive(Debug, Default, Clone)]
struct Hungarian {
    u: Vec<f64>,
    v: Vec<f64>,
    p: Vec<usize>,
    way: Vec<usize>,
    minv: Vec<f64>,
    used: Vec<bool>,
    row_to_col: Vec<usize>,
}

impl Hungarian {
    /// `cost` is row-major n x n; returns for each row its column.
    fn solve(&mut self, n: usize, cost: &[f64]) -> &[usize] {
        // 1-based arrays with a virtual column 0, as in the classic formulation.
        self.u.clear();
        self.u.resize(n + 1, 0.0);
        self.v.clear();
        self.v.resize(n + 1, 0.0);
        self.p.clear();
        self.p.resize(n + 1, 0);
        self.way.clear();
        self.way.resize(n + 1, 0);
        for i in 1..=n {
            self.p[0] = i;
            let mut j0 = 0;
            self.minv.clear();
            self.minv.resize(n + 1, f64::INFINITY);
            self.used.clear();
            self.used.resize(n + 1, false);
            loop {
                self.used[j0] = true;
                let i0 = self.p[j0];
                let mut delta = f64::INFINITY;
                let mut j1 = 0;
                for j in 1..=n {
                    if !self.used[j] {
                        let cur = cost[(i0 - 1) * n + (j - 1)] - self.u[i0] - self.v[j];
                        if cur < self.minv[j] {
                            self.minv[j] = cur;
                            self.way[j] = j0;
                        }
                        if self.minv[j] < delta {
                            delta = self.minv[j];
                            j1 = j;
                        }
                    }
                }
                for j in 0..=n {
                    if self.used[j] {
                        self.u[self.p[j]] += delta;
                        self.v[j] -= delta;
                    } else {
                        self.minv[j] -= delta;
                    }
                }
                j0 = j1;
                if self.p[j0] == 0 {
                    break;
                }
            }
            loop {
                let j1 = self.way[j0];
                self.p[j0] = self.p[j1];
                j0 = j1;
                if j0 == 0 {
                    break;
                }
            }
        }
        self.row_to_col.clear();
        self.row_to_col.resize(n, 0);
        for j in 1..=n {
            if self.p[j] > 0 {
                self.row_to_col[self.p[j] - 1] = j - 1;
            }
        }
        &self.row_to_col
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute_force_min(n: usize, cost: &[f64]) -> f64 {
        fn rec(row: usize, n: usize, cost: &[f64], used: &mut Vec<bool>) -> f64 {
            if row == n {
                return 0.0;
            }
            let mut best = f64::INFINITY;
            for c in 0..n {
                if !used[c] {
                    used[c] = true;
                    best = best.min(cost[row * n + c] + rec(row + 1, n, cost, used));
                    used[c] = false;
                }
            }
            best
        }
        rec(0, n, cost, &mut vec![false; n])
    }

    #[test]
    fn hungarian_matches_brute_force() {
        let mut h = Hungarian::default();
        let mut seed = 7u64;
        for n in 1..=6 {
            for _ in 0..20 {
                let cost: Vec<f64> = (0..n * n)
                    .map(|_| {
                        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
                        (seed >> 33) as f64 / (1u64 << 31) as f64 * 10.0
                    })
                    .collect();
                let total: f64 = h
                    .solve(n, &cost)
                    .iter()
                    .enumerate()
                    .map(|(r, &c)| cost[r * n + c])
                    .sum();
                assert!((total - brute_force_min(n, &cost)).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn rejects_bad_config_and_time_step() {
        let config = TrackerConfig {
            confirm_hits: 6,
            ..TrackerConfig::default()
        };
        assert!(matches!(
            Tracker::new(config),
            Err(TrackerError::InvalidConfig(_))
        ));
        let mut t = Tracker::new(TrackerConfig::default()).unwrap();
        assert_eq!(t.update(0.0, &[]), Err(TrackerError::InvalidTimeStep(0.0)));
        assert!(t.update(f64::NAN, &[]).is_err());
    }

    #[test]
    fn non_finite_detections_are_counted_and_dropped() {
        let mut t = Tracker::new(TrackerConfig::default()).unwrap();
        let r = t
            .update(0.1, &[[f64::NAN, 1.0], [1.0, f64::INFINITY], [2.0, 2.0]])
            .unwrap();
        assert_eq!(r.rejected_detections, 2);
        assert_eq!(r.born, 1);
    }

    #[test]
    fn m_of_n_confirmation_and_death_by_misses() {
        let config = TrackerConfig::default(); // 3 of 5, 5 misses
        let mut t = Tracker::new(config).unwrap();
        t.update(0.1, &[[0.0, 0.0]]).unwrap();
        t.update(0.1, &[]).unwrap();
        assert_eq!(t.confirmed().count(), 0);
        t.update(0.1, &[[0.0, 0.0]]).unwrap();
        assert_eq!(t.confirmed().count(), 0);
        let r = t.update(0.1, &[[0.0, 0.0]]).unwrap();
        assert_eq!(r.confirmed, 1);
        let id = t.confirmed().next().unwrap().id;
        for _ in 0..4 {
            t.update(0.1, &[]).unwrap();
            assert_eq!(t.confirmed().next().map(|t| t.id), Some(id));
        }
        let r = t.update(0.1, &[]).unwrap();
        assert_eq!(r.deleted, 1);
        assert_eq!(t.tracks().len(), 0);
    }

    #[test]
    fn lone_false_alarm_dies_tentative() {
        let mut t = Tracker::new(TrackerConfig::default()).unwrap();
        t.update(0.1, &[[50.0, 50.0]]).unwrap();
        let mut deleted = 0;
        for _ in 0..4 {
            deleted += t.update(0.1, &[]).unwrap().deleted;
        }
        assert_eq!(deleted, 1);
        assert!(t.tracks().is_empty());
    }

    #[test]
    fn crossing_pair_keeps_identities() {
        // Two targets 1.0 m apart in y, crossing in x at 1 m/s each way.
        let mut t = Tracker::new(TrackerConfig {
            measurement_std: 0.05,
            ..TrackerConfig::default()
        })
        .unwrap();
        let pos = |k: usize| {
            let s = k as f64 * 0.1;
            [[-5.0 + s, 0.0], [5.0 - s, 1.0]]
        };
        for k in 0..10 {
            t.update(0.1, &pos(k)).unwrap();
        }
        let id_at = |t: &Tracker, p: [f64; 2]| {
            t.confirmed()
                .min_by(|a, b| {
                    let da = (a.position[0] - p[0]).hypot(a.position[1] - p[1]);
                    let db = (b.position[0] - p[0]).hypot(b.position[1] - p[1]);
                    da.total_cmp(&db)
                })
                .map(|tr| tr.id)
        };
        let first = (id_at(&t, pos(9)[0]), id_at(&t, pos(9)[1]));
        for k in 10..100 {
            t.update(0.1, &pos(k)).unwrap();
        }
        let last = (id_at(&t, pos(99)[0]), id_at(&t, pos(99)[1]));
        assert_eq!(first, last);
        assert_eq!(t.confirmed().count(), 2);
    }

    #[test]
    fn dense_cluster_falls_back_to_greedy_without_losing_targets() {
        let config = TrackerConfig {
            max_exact_cluster: 2,
            max_gate_radius: 3.0,
            ..TrackerConfig::default()
        };
        let mut t = Tracker::new(config).unwrap();
        // A 4 x 4 lattice at 1 m spacing: everything gates with everything nearby.
        let lattice: Vec<[f64; 2]> = (0..16).map(|i| [(i % 4) as f64, (i / 4) as f64]).collect();
        let mut greedy = 0;
        for _ in 0..10 {
            greedy += t.update(0.1, &lattice).unwrap().greedy_clusters;
        }
        assert!(greedy > 0);
        assert_eq!(t.confirmed().count(), 16);
    }
}
