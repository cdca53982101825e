//! Verifying MAVLink 2 signatures with replay protection that survives a restart.
//!
//! The `mavlink` crate's own check has three gaps that an attacker on the link can use: a
//! frame dated far in the future is accepted (and drags the receiver's clock with it, so that
//! every honest new stream then looks too old), its per-stream state is lost when the process
//! restarts (a freshly started daemon accepted a 50 s old signed Start), and it reads the wall
//! clock itself. [`ReplayGuard`] closes them, following the signing specification
//! (<https://mavlink.io/en/guide/message_signing.html>):
//!
//! * one last timestamp per stream `(link id, system id, component id)`; a frame whose
//!   timestamp is not newer than its stream's last is a replay;
//! * a new stream is accepted only within [`NEW_STREAM_WINDOW`] (one minute) of the guard's
//!   current time, the newest of the caller's clock and every timestamp accepted so far;
//! * a frame more than `max_future` ahead of the caller's clock is refused and moves nothing;
//! * the state encodes to a small file ([`ReplayGuard::to_bytes`], magic `SKRP`, version 1,
//!   little-endian fixed-width integers) that the caller writes and reads back at start.
//!
//! Pure: the caller passes the time in, as [`SigningTime`] (10 us units since 2015-01-01,
//! the protocol's clock); [`SigningTime::now`] reads the system clock at the edge.
//!
//! ```
//! use skyherd_link::replay::{ReplayGuard, SigningTime};
//! let guard = ReplayGuard::new(SigningTime(1_000_000));
//! let bytes = guard.to_bytes();
//! let back = ReplayGuard::from_bytes(&bytes).unwrap();
//! assert_eq!(back.current(), SigningTime(1_000_000));
//! ```

use std::collections::BTreeMap;

use mavlink::MAVLinkV2MessageRaw;
use thiserror::Error;

use crate::signing::SigningKey;

/// A MAVLink 2 signing timestamp: 10 us units since 2015-01-01 00:00:00 UTC (48 bits used).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct SigningTime(pub u64);

/// Unix time of 2015-01-01 00:00:00 UTC, the signing clock's epoch, seconds.
const EPOCH_2015_UNIX_S: u64 = 1_420_070_400;
/// Signing-clock units per second.
pub const UNITS_PER_SECOND: u64 = 100_000;
/// How far behind the current time a new stream may start: one minute, as the specification
/// suggests.
pub const NEW_STREAM_WINDOW: u64 = 60 * UNITS_PER_SECOND;
/// Default bound on how far ahead of the receiver's clock a timestamp may be: one minute
/// (clocks of separate computers differ; a year-ahead frame is an attack, not skew).
pub const DEFAULT_MAX_FUTURE: u64 = 60 * UNITS_PER_SECOND;
/// Streams remembered at most (only validly signed frames open one, so this bounds a key
/// holder's mistakes, not an attacker's).
pub const MAX_STREAMS: usize = 4096;

impl SigningTime {
    /// The system clock as a signing time (0 before 2015).
    pub fn now() -> Self {
        let micros = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_micros());
        let since_2015 = micros.saturating_sub(u128::from(EPOCH_2015_UNIX_S) * 1_000_000);
        SigningTime(u64::try_from(since_2015 / 10).unwrap_or(u64::MAX))
    }

    /// This time plus `seconds` (saturating; negative moves back).
    pub fn plus_seconds(self, seconds: f64) -> Self {
        let units = seconds * UNITS_PER_SECOND as f64;
        if units >= 0.0 {
            SigningTime(self.0.saturating_add(units as u64))
        } else {
            SigningTime(self.0.saturating_sub((-units) as u64))
        }
    }
}

/// One signing stream: link id, system id, component id.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct StreamId {
    /// The link id in the signature.
    pub link_id: u8,
    /// The sender's system id.
    pub system_id: u8,
    /// The sender's component id.
    pub component_id: u8,
}

/// Why a signed frame was refused.
#[derive(Clone, Copy, Debug, Error, PartialEq)]
pub enum SignatureError {
    /// The frame carries no signature.
    #[error("the frame is not signed")]
    Unsigned,
    /// The signature does not match the key.
    #[error("the signature does not match the key")]
    WrongSignature,
    /// Not newer than its stream's last accepted timestamp.
    #[error("replayed: timestamp {got} is not newer than the stream's last, {last}")]
    Replayed {
        /// The stream's last accepted timestamp.
        last: u64,
        /// The frame's.
        got: u64,
    },
    /// A new stream more than [`NEW_STREAM_WINDOW`] behind the current time.
    #[error("a new stream starting {behind_s:.1} s in the past (at most 60 s)")]
    TooOld {
        /// How far behind, seconds.
        behind_s: f64,
    },
    /// Further ahead of the receiver's clock than allowed.
    #[error("timestamp {ahead_s:.1} s ahead of this clock")]
    FromTheFuture {
        /// How far ahead, seconds.
        ahead_s: f64,
    },
}

/// Why a replay state file could not be read.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum ReplayStateError {
    /// Too short for its header or its entries.
    #[error("replay state truncated: {len} bytes, expected {expected}")]
    Truncated {
        /// Bytes found.
        len: usize,
        /// Bytes needed.
        expected: usize,
    },
    /// Not a replay state file.
    #[error("not a replay state file (magic {found:02x?}, expected \"SKRP\")")]
    BadMagic {
        /// The first four bytes.
        found: [u8; 4],
    },
    /// A version this build does not read.
    #[error("replay state version {0} is not supported (this build reads version 1)")]
    BadVersion(u16),
    /// More streams than [`MAX_STREAMS`].
    #[error("replay state lists {0} streams, at most {MAX_STREAMS}")]
    TooManyStreams(u32),
    /// Bytes after the last entry.
    #[error("replay state has {0} bytes after its last entry")]
    TrailingBytes(usize),
}

/// Per-stream signing timestamps, the receiver's current time and the future bound.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReplayGuard {
    streams: BTreeMap<StreamId, u64>,
    current: u64,
    max_future: u64,
    dirty: bool,
}

const MAGIC: [u8; 4] = *b"SKRP";
const VERSION: u16 = 1;
const HEADER_LEN: usize = 4 + 2 + 2 + 8 + 4;
const ENTRY_LEN: usize = 4 + 8;

impl ReplayGuard {
    /// A fresh guard whose current time is `now`: frames older than a minute before it are
    /// refused even on streams never seen.
    pub fn new(now: SigningTime) -> Self {
        ReplayGuard {
            streams: BTreeMap::new(),
            current: now.0,
            max_future: DEFAULT_MAX_FUTURE,
            dirty: false,
        }
    }

    /// The same guard with another bound on timestamps ahead of the clock (signing units).
    pub fn with_max_future(mut self, units: u64) -> Self {
        self.max_future = units;
        self
    }

    /// The newest of the caller's clock and every accepted timestamp.
    pub fn current(&self) -> SigningTime {
        SigningTime(self.current)
    }

    /// The last accepted timestamp of `stream`.
    pub fn last(&self, stream: StreamId) -> Option<SigningTime> {
        self.streams.get(&stream).copied().map(SigningTime)
    }

    /// How many streams are remembered.
    pub fn stream_count(&self) -> usize {
        self.streams.len()
    }

    /// Whether anything changed since the last [`mark_saved`](Self::mark_saved).
    pub fn is_dirty(&self) -> bool {
        self.dirty
    }

    /// The caller has written [`to_bytes`](Self::to_bytes) out.
    pub fn mark_saved(&mut self) {
        self.dirty = false;
    }

    /// Checks `frame`'s signature under `key` at the caller's time `now`, and on success
    /// records its timestamp. A refused frame changes nothing.
    ///
    /// # Errors
    /// [`SignatureError`] says why the frame is refused.
    pub fn verify(
        &mut self,
        key: &SigningKey,
        frame: &MAVLinkV2MessageRaw,
        now: SigningTime,
    ) -> Result<(), SignatureError> {
        const IFLAG_SIGNED: u8 = 0x01;
        if frame.incompatibility_flags() & IFLAG_SIGNED == 0 {
            return Err(SignatureError::Unsigned);
        }
        let stamp = frame.signature_timestamp();
        let stream = StreamId {
            link_id: frame.signature_link_id(),
            // One byte on the wire.
            system_id: u8::try_from(frame.system_id()).unwrap_or(u8::MAX),
            component_id: frame.component_id(),
        };
        let seconds = |units: u64| units as f64 / UNITS_PER_SECOND as f64;
        if stamp > now.0.saturating_add(self.max_future) {
            return Err(SignatureError::FromTheFuture {
                ahead_s: seconds(stamp - now.0),
            });
        }
        // The signature before the replay state: a forged frame is a forgery, whatever its
        // timestamp; only a validly signed frame can be a replay.
        let mut expected = [0u8; 6];
        frame.calculate_signature(&key.0, &mut expected);
        // Compare every byte whatever the first difference, so that timing tells nothing.
        let difference = expected
            .iter()
            .zip(frame.signature_value())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b));
        if difference != 0 {
            return Err(SignatureError::WrongSignature);
        }
        let current = self.current.max(now.0);
        match self.streams.get(&stream) {
            Some(&last) if stamp <= last => {
                return Err(SignatureError::Replayed { last, got: stamp });
            }
            Some(_) => {}
            None if stamp.saturating_add(NEW_STREAM_WINDOW) < current => {
                return Err(SignatureError::TooOld {
                    behind_s: seconds(current - stamp),
                });
            }
            None => {}
        }
        if self.streams.len() >= MAX_STREAMS && !self.streams.contains_key(&stream) {
            // Forget the stalest stream: its sender has long been quiet.
            if let Some((&oldest, _)) = self.streams.iter().min_by_key(|(_, t)| **t) {
                self.streams.remove(&oldest);
            }
        }
        self.streams.insert(stream, stamp);
        self.current = current.max(stamp);
        self.dirty = true;
        Ok(())
    }

    /// The state as bytes: `SKRP`, version u16, reserved u16, current u64, stream count u32,
    /// then per stream link id, system id, component id, a zero byte and the timestamp u64;
    /// all little-endian.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_LEN + ENTRY_LEN * self.streams.len());
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.current.to_le_bytes());
        // At most MAX_STREAMS entries, so the count fits.
        out.extend_from_slice(&(self.streams.len() as u32).to_le_bytes());
        for (stream, stamp) in &self.streams {
            out.extend_from_slice(&[stream.link_id, stream.system_id, stream.component_id, 0]);
            out.extend_from_slice(&stamp.to_le_bytes());
        }
        out
    }

    /// A guard from [`to_bytes`](Self::to_bytes), with the default future bound.
    ///
    /// # Errors
    /// [`ReplayStateError`] names what is wrong with the bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ReplayStateError> {
        let truncated = |expected| ReplayStateError::Truncated {
            len: bytes.len(),
            expected,
        };
        if bytes.len() < HEADER_LEN {
            return Err(truncated(HEADER_LEN));
        }
        let u64_at = |at: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&bytes[at..at + 8]);
            u64::from_le_bytes(b)
        };
        let magic = [bytes[0], bytes[1], bytes[2], bytes[3]];
        if magic != MAGIC {
            return Err(ReplayStateError::BadMagic { found: magic });
        }
        let version = u16::from_le_bytes([bytes[4], bytes[5]]);
        if version != VERSION {
            return Err(ReplayStateError::BadVersion(version));
        }
        let current = u64_at(8);
        let count = u32::from_le_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]);
        if count as usize > MAX_STREAMS {
            return Err(ReplayStateError::TooManyStreams(count));
        }
        let expected = HEADER_LEN + ENTRY_LEN * count as usize;
        if bytes.len() < expected {
            return Err(truncated(expected));
        }
        if bytes.len() > expected {
            return Err(ReplayStateError::TrailingBytes(bytes.len() - expected));
        }
        let streams = bytes[HEADER_LEN..]
            .chunks_exact(ENTRY_LEN)
            .map(|e| {
                let mut b = [0u8; 8];
                b.copy_from_slice(&e[4..12]);
                (
                    StreamId {
                        link_id: e[0],
                        system_id: e[1],
                        component_id: e[2],
                    },
                    u64::from_le_bytes(b),
                )
            })
            .collect();
        Ok(ReplayGuard {
            streams,
            current,
            max_future: DEFAULT_MAX_FUTURE,
            dirty: false,
        })
    }
}

/// Signs `frame` (already serialised for signing) under `key` on `link_id` with timestamp
/// `stamp`: for tests and tools that need a chosen timestamp (the links sign through the
/// `mavlink` crate, whose timestamps follow the wall clock and never repeat).
pub fn sign(key: &SigningKey, link_id: u8, stamp: SigningTime, frame: &mut MAVLinkV2MessageRaw) {
    let bytes = stamp.0.to_le_bytes();
    frame
        .signature_timestamp_bytes_mut()
        .copy_from_slice(&bytes[..6]);
    *frame.signature_link_id_mut() = link_id;
    let mut value = [0u8; 6];
    frame.calculate_signature(&key.0, &mut value);
    frame.signature_value_mut().copy_from_slice(&value);
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::MavHeader;
    use mavlink::dialects::common::{HEARTBEAT_DATA, MavMessage};

    const KEY: SigningKey = SigningKey([7; 32]);
    const T0: SigningTime = SigningTime(300_000_000_000);

    fn frame(
        system_id: u8,
        link_id: u8,
        stamp: SigningTime,
        key: &SigningKey,
    ) -> MAVLinkV2MessageRaw {
        let mut raw = MAVLinkV2MessageRaw::new();
        let header = MavHeader {
            system_id: u32::from(system_id),
            component_id: 190,
            sequence: 0,
        };
        raw.serialize_message_for_signing(
            header,
            &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
        );
        sign(key, link_id, stamp, &mut raw);
        raw
    }

    #[test]
    fn a_signed_frame_passes_once_and_its_replay_is_refused() {
        let mut guard = ReplayGuard::new(T0);
        let f = frame(255, 1, T0, &KEY);
        assert_eq!(guard.verify(&KEY, &f, T0), Ok(()));
        assert!(guard.is_dirty());
        assert!(matches!(
            guard.verify(&KEY, &f, T0),
            Err(SignatureError::Replayed { .. })
        ));
        let next = frame(255, 1, T0.plus_seconds(0.01), &KEY);
        assert_eq!(guard.verify(&KEY, &next, T0), Ok(()));
    }

    #[test]
    fn wrong_key_unsigned_future_and_stale_new_streams_are_refused_and_change_nothing() {
        let mut guard = ReplayGuard::new(T0);
        let before = guard.clone();
        let wrong = frame(255, 1, T0, &SigningKey([8; 32]));
        assert_eq!(
            guard.verify(&KEY, &wrong, T0),
            Err(SignatureError::WrongSignature)
        );
        let year = frame(255, 1, T0.plus_seconds(365.0 * 86_400.0), &KEY);
        assert!(matches!(
            guard.verify(&KEY, &year, T0),
            Err(SignatureError::FromTheFuture { ahead_s }) if ahead_s > 3e7
        ));
        let old = frame(255, 1, T0.plus_seconds(-61.0), &KEY);
        assert!(matches!(
            guard.verify(&KEY, &old, T0),
            Err(SignatureError::TooOld { .. })
        ));
        let mut plain = MAVLinkV2MessageRaw::new();
        plain.serialize_message(
            MavHeader::default(),
            &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
        );
        assert_eq!(
            guard.verify(&KEY, &plain, T0),
            Err(SignatureError::Unsigned)
        );
        assert_eq!(guard, before, "a refused frame moves nothing");
        // 59 s old on a new stream, and 59 s ahead: within the windows.
        assert_eq!(
            guard.verify(&KEY, &frame(255, 1, T0.plus_seconds(-59.0), &KEY), T0),
            Ok(())
        );
        assert_eq!(
            guard.verify(&KEY, &frame(254, 1, T0.plus_seconds(59.0), &KEY), T0),
            Ok(())
        );
    }

    #[test]
    fn streams_are_kept_per_link_system_and_component() {
        let mut guard = ReplayGuard::new(T0);
        assert_eq!(guard.verify(&KEY, &frame(255, 1, T0, &KEY), T0), Ok(()));
        // The same stamp on another link id or from another system is another stream.
        assert_eq!(guard.verify(&KEY, &frame(255, 2, T0, &KEY), T0), Ok(()));
        assert_eq!(guard.verify(&KEY, &frame(254, 1, T0, &KEY), T0), Ok(()));
        assert!(guard.verify(&KEY, &frame(255, 2, T0, &KEY), T0).is_err());
    }

    #[test]
    fn the_state_survives_a_restart_so_an_old_frame_stays_refused() {
        let mut guard = ReplayGuard::new(T0);
        let start = frame(255, 1, T0, &KEY);
        assert_eq!(guard.verify(&KEY, &start, T0), Ok(()));
        let later = frame(255, 1, T0.plus_seconds(50.0), &KEY);
        assert_eq!(guard.verify(&KEY, &later, T0.plus_seconds(50.0)), Ok(()));
        // Restart 50 s later: the 50 s old Start is inside the new-stream window, so only the
        // persisted stream state refuses it.
        let mut restarted = ReplayGuard::from_bytes(&guard.to_bytes()).unwrap();
        assert!(matches!(
            restarted.verify(&KEY, &start, T0.plus_seconds(50.0)),
            Err(SignatureError::Replayed { .. })
        ));
        let mut forgetful = ReplayGuard::new(T0.plus_seconds(50.0));
        assert_eq!(
            forgetful.verify(&KEY, &start, T0.plus_seconds(50.0)),
            Ok(())
        );
    }

    #[test]
    fn the_state_format_is_pinned() {
        let mut guard = ReplayGuard::new(SigningTime(0x0102_0304_0506));
        let f = frame(9, 3, SigningTime(0x0102_0304_0507), &KEY);
        guard
            .verify(&KEY, &f, SigningTime(0x0102_0304_0506))
            .unwrap();
        let golden: Vec<u8> = [
            b"SKRP".as_slice(),
            &[1, 0, 0, 0],
            &[0x07, 0x05, 0x04, 0x03, 0x02, 0x01, 0, 0],
            &[1, 0, 0, 0],
            &[3, 9, 190, 0],
            &[0x07, 0x05, 0x04, 0x03, 0x02, 0x01, 0, 0],
        ]
        .concat();
        assert_eq!(guard.to_bytes(), golden);
        assert_eq!(ReplayGuard::from_bytes(&golden).unwrap().to_bytes(), golden);
    }

    #[test]
    fn a_bad_state_file_is_named_never_a_panic() {
        let good = ReplayGuard::new(T0).to_bytes();
        assert!(matches!(
            ReplayGuard::from_bytes(&good[..10]),
            Err(ReplayStateError::Truncated { .. })
        ));
        let mut magic = good.clone();
        magic[0] = b'X';
        assert!(matches!(
            ReplayGuard::from_bytes(&magic),
            Err(ReplayStateError::BadMagic { .. })
        ));
        let mut version = good.clone();
        version[4] = 9;
        assert_eq!(
            ReplayGuard::from_bytes(&version),
            Err(ReplayStateError::BadVersion(9))
        );
        let mut count = good.clone();
        count[16..20].copy_from_slice(&5u32.to_le_bytes());
        assert!(matches!(
            ReplayGuard::from_bytes(&count),
            Err(ReplayStateError::Truncated { .. })
        ));
        count[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            ReplayGuard::from_bytes(&count),
            Err(ReplayStateError::TooManyStreams(_))
        ));
        let mut trailing = good;
        trailing.push(0);
        assert_eq!(
            ReplayGuard::from_bytes(&trailing),
            Err(ReplayStateError::TrailingBytes(1))
        );
        for n in 0..64 {
            let junk: Vec<u8> = (0..n).map(|i| (i * 37 + n) as u8).collect();
            let _ = ReplayGuard::from_bytes(&junk);
        }
    }
}
