//! Target detections on the wire: how a tracking sensor (a camera or motion-capture system at
//! the ground station; in SITL the simulator's detection sensor) reports one scan.
//!
//! A scan is a run of MAVLink `DEBUG_VECT` messages named `det` (x, y = position in the
//! simulator frame, metres; z = 0), closed by one named `det_end` whose `x` is the number of
//! detections sent. Every message of a scan carries the scan time in `time_usec`. Standard
//! `common` messages keep the sensor readable by any MAVLink tool; a scan whose closing count
//! does not match what arrived (a lost datagram) is still used, and counted as incomplete.
//!
//! ```
//! use skyherd_ground::detections::{ScanAssembler, scan_messages};
//! let messages = scan_messages(2.5, &[[1.0, 2.0], [3.0, 4.0]]);
//! let mut assembler = ScanAssembler::default();
//! let mut done = None;
//! for m in &messages {
//!     if let Some(scan) = assembler.push(m) {
//!         done = Some(scan);
//!     }
//! }
//! let scan = done.unwrap();
//! assert_eq!(scan.time_s, 2.5);
//! assert_eq!(scan.detections, vec![[1.0, 2.0], [3.0, 4.0]]);
//! assert!(scan.complete);
//! ```

use mavlink::dialects::common::{DEBUG_VECT_DATA, MavMessage};

/// `DEBUG_VECT` name of one detection.
pub const DETECTION_NAME: &str = "det";
/// `DEBUG_VECT` name of the message that closes a scan.
pub const SCAN_END_NAME: &str = "det_end";
/// `DEBUG_VECT` name of the ground's answer once it has acted on a scan (tracked, sent the
/// snapshots up): a simulator waits for it to keep the ground in lockstep.
pub const SCAN_ACK_NAME: &str = "det_ack";

/// The ground's acknowledgement of the scan taken at `time_s`.
pub fn scan_ack(time_s: f64) -> MavMessage {
    MavMessage::DEBUG_VECT(DEBUG_VECT_DATA {
        time_usec: (time_s.max(0.0) * 1e6).round() as u64,
        x: 0.0,
        y: 0.0,
        z: 0.0,
        name: SCAN_ACK_NAME.into(),
    })
}

/// The scan time (s) a message acknowledges, if it is a scan acknowledgement.
pub fn acknowledged_scan(message: &MavMessage) -> Option<f64> {
    match message {
        MavMessage::DEBUG_VECT(v) if v.name.to_str() == Ok(SCAN_ACK_NAME) => {
            Some(v.time_usec as f64 / 1e6)
        }
        _ => None,
    }
}

/// The messages reporting one scan at `time_s` (seconds of the sensor's clock).
pub fn scan_messages(time_s: f64, detections: &[[f64; 2]]) -> Vec<MavMessage> {
    let time_usec = (time_s.max(0.0) * 1e6).round() as u64;
    let vector = |name: &str, x: f32, y: f32| {
        MavMessage::DEBUG_VECT(DEBUG_VECT_DATA {
            time_usec,
            x,
            y,
            z: 0.0,
            name: name.into(),
        })
    };
    detections
        .iter()
        .map(|d| vector(DETECTION_NAME, d[0] as f32, d[1] as f32))
        .chain(std::iter::once(vector(
            SCAN_END_NAME,
            detections.len() as f32,
            0.0,
        )))
        .collect()
}

/// One scan as received.
#[derive(Clone, Debug, PartialEq)]
pub struct Scan {
    /// Sensor time of the scan, seconds.
    pub time_s: f64,
    /// Detected positions `[x, y]`, simulator frame, metres.
    pub detections: Vec<[f64; 2]>,
    /// Whether as many detections arrived as the sensor said it sent.
    pub complete: bool,
}

/// Collects `DEBUG_VECT` detections into scans.
#[derive(Clone, Debug, Default)]
pub struct ScanAssembler {
    time_usec: Option<u64>,
    detections: Vec<[f64; 2]>,
    incomplete_scans: u64,
    ignored: u64,
}

impl ScanAssembler {
    /// Scans whose closing count did not match what arrived, and scans dropped unfinished
    /// (their closing message lost) when a newer one started.
    pub fn incomplete_scans(&self) -> u64 {
        self.incomplete_scans
    }

    /// Messages that were not detections, or were non-finite.
    pub fn ignored(&self) -> u64 {
        self.ignored
    }

    /// Feed one message; returns a scan when its closing message arrives. Detections of an
    /// older scan still pending when a newer one starts are dropped with it.
    pub fn push(&mut self, message: &MavMessage) -> Option<Scan> {
        let MavMessage::DEBUG_VECT(v) = message else {
            self.ignored += 1;
            return None;
        };
        let name = v.name.to_str().unwrap_or("");
        if self.time_usec != Some(v.time_usec) {
            if self.time_usec.is_some() {
                // The pending scan never closed: its end marker was lost.
                self.incomplete_scans += 1;
            }
            self.time_usec = Some(v.time_usec);
            self.detections.clear();
        }
        match name {
            DETECTION_NAME if v.x.is_finite() && v.y.is_finite() => {
                self.detections.push([f64::from(v.x), f64::from(v.y)]);
                None
            }
            SCAN_END_NAME => {
                let complete = v.x.is_finite() && v.x as usize == self.detections.len();
                if !complete {
                    self.incomplete_scans += 1;
                }
                self.time_usec = None;
                Some(Scan {
                    time_s: v.time_usec as f64 / 1e6,
                    detections: std::mem::take(&mut self.detections),
                    complete,
                })
            }
            _ => {
                self.ignored += 1;
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn acknowledgements_round_trip_and_are_not_detections() {
        let ack = scan_ack(12.3);
        assert_eq!(acknowledged_scan(&ack), Some(12.3));
        assert_eq!(acknowledged_scan(&scan_messages(1.0, &[])[0]), None);
        let mut assembler = ScanAssembler::default();
        assert_eq!(assembler.push(&ack), None);
        assert_eq!(assembler.ignored(), 1);
    }

    #[test]
    fn a_lost_detection_gives_an_incomplete_scan() {
        let mut messages = scan_messages(1.0, &[[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]);
        messages.remove(1);
        let mut assembler = ScanAssembler::default();
        let scans: Vec<Scan> = messages.iter().filter_map(|m| assembler.push(m)).collect();
        assert_eq!(scans.len(), 1);
        assert_eq!(scans[0].detections.len(), 2);
        assert!(!scans[0].complete);
        assert_eq!(assembler.incomplete_scans(), 1);
    }

    #[test]
    fn a_new_scan_drops_the_unfinished_old_one() {
        let mut old = scan_messages(1.0, &[[1.0, 1.0], [2.0, 2.0]]);
        old.pop(); // its end marker is lost
        let new = scan_messages(1.1, &[[5.0, 5.0]]);
        let mut assembler = ScanAssembler::default();
        let scans: Vec<Scan> = old
            .iter()
            .chain(new.iter())
            .filter_map(|m| assembler.push(m))
            .collect();
        assert_eq!(scans.len(), 1);
        assert_eq!(scans[0].detections, vec![[5.0, 5.0]]);
        assert!(scans[0].complete);
        // The lost one is counted.
        assert_eq!(assembler.incomplete_scans(), 1);
    }

    #[test]
    fn other_messages_and_nan_are_ignored() {
        let mut assembler = ScanAssembler::default();
        let nan = MavMessage::DEBUG_VECT(DEBUG_VECT_DATA {
            time_usec: 5,
            x: f32::NAN,
            y: 0.0,
            z: 0.0,
            name: DETECTION_NAME.into(),
        });
        assert_eq!(assembler.push(&nan), None);
        assert_eq!(
            assembler.push(&skyherd_link::command::gcs_heartbeat()),
            None
        );
        assert_eq!(assembler.ignored(), 2);
        let end = scan_messages(5e-6, &[]);
        let scan = assembler.push(&end[0]).unwrap();
        assert!(scan.detections.is_empty());
        assert!(scan.complete);
    }
}
