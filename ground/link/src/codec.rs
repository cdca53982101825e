//! MAVLink 2 framing, signing and parsing over raw bytes: pure, no sockets, no clock.
//!
//! Why not `MavConnection::recv`: it silently skips bad frames, and the ground station must
//! count them (a link that corrupts frames is a link to distrust) and log the exact bytes to
//! the `.tlog`. This codec reuses `mavlink`'s frame type, CRC and signature code and only
//! adds the bookkeeping.
//!
//! Signing (MAVLink 2 message signing, <https://mavlink.io/en/guide/message_signing.html>):
//! with a [`Signing`] config every outgoing frame is signed and every incoming frame must carry
//! a valid signature under the same key; unsigned frames are rejected unless
//! [`Signing::accept_unsigned`]. The signature timestamp comes from the `mavlink` crate (wall
//! clock, 10 us units since 2015) as the protocol requires; what arrives goes through a
//! [`ReplayGuard`]: replays, new streams older than a minute and frames from more than a
//! minute in the future are rejected.

use crate::replay::{ReplayGuard, SigningTime};
use crate::signing::{Signing, SigningKey, signing_data};
use mavlink::dialects::common::MavMessage;
use mavlink::{MAVLinkV1MessageRaw, MAVLinkV2MessageRaw, MavHeader, MavlinkVersion, Message};

const STX_V2: u8 = 0xFD;
const STX_V1: u8 = 0xFE;
const IFLAG_SIGNED: u8 = 0x01;
/// STX + 9 header bytes + 2 CRC bytes.
const V2_OVERHEAD: usize = 12;
const SIGNATURE_LEN: usize = 13;
/// STX + 5 header bytes + 2 CRC bytes.
const V1_OVERHEAD: usize = 8;

/// Counters of what the decoder saw. Everything but `frames` is a frame or byte dropped.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CodecStats {
    /// Frames accepted and parsed.
    pub frames: u64,
    /// Bytes skipped while hunting for a frame start.
    pub garbage_bytes: u64,
    /// Frames cut short (end of datagram inside a frame).
    pub truncated: u64,
    /// Frames whose CRC did not match.
    pub bad_crc: u64,
    /// Frames with a message id outside the common dialect.
    pub unknown_message: u64,
    /// Frames with incompatibility flags other than "signed".
    pub unsupported_flags: u64,
    /// Frames whose CRC was fine but whose payload did not parse (e.g. an unknown enum value).
    pub undecodable: u64,
    /// Signed frames whose signature or timestamp did not verify.
    pub bad_signature: u64,
    /// Unsigned frames on a link that requires signing.
    pub unsigned_rejected: u64,
    /// Valid MAVLink 1 frames (this stack speaks MAVLink 2 only).
    pub mavlink1_rejected: u64,
}

impl CodecStats {
    /// Frames (not garbage bytes) dropped for any reason.
    pub fn dropped_frames(&self) -> u64 {
        self.truncated
            + self.bad_crc
            + self.unknown_message
            + self.unsupported_flags
            + self.undecodable
            + self.bad_signature
            + self.unsigned_rejected
            + self.mavlink1_rejected
    }
}

/// One accepted frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Sender and sequence.
    pub header: MavHeader,
    /// The parsed message.
    pub message: MavMessage,
    /// The exact bytes received (for the `.tlog`).
    pub raw: Vec<u8>,
    /// Whether the frame carried a signature (verified when the link signs).
    pub signed: bool,
}

/// A signed link's state: the signer (the `mavlink` crate's, wall-clock timestamps), the key
/// and the replay guard that checks what arrives.
struct LinkSigning {
    signer: mavlink::SigningData,
    key: SigningKey,
    accept_unsigned: bool,
    guard: ReplayGuard,
    clock: fn() -> SigningTime,
}

/// Encoder/decoder for one link endpoint: our system/component id, sequence, signing, stats.
pub struct Codec {
    system_id: u8,
    component_id: u8,
    sequence: u8,
    signing: Option<LinkSigning>,
    stats: CodecStats,
    /// Stream transports: the start of a frame whose end has not arrived yet.
    stream_tail: Vec<u8>,
}

impl std::fmt::Debug for Codec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Codec")
            .field("system_id", &self.system_id)
            .field("component_id", &self.component_id)
            .field("signed", &self.signing.is_some())
            .field("stats", &self.stats)
            .finish()
    }
}

impl Codec {
    /// A codec sending as `system_id`/`component_id`, signing when `signing` is set.
    pub fn new(system_id: u8, component_id: u8, signing: Option<Signing>) -> Self {
        Self {
            system_id,
            component_id,
            sequence: 0,
            signing: signing.map(|s| LinkSigning {
                signer: signing_data(&s.key, s.link_id),
                key: s.key,
                accept_unsigned: s.accept_unsigned,
                guard: ReplayGuard::new(SigningTime::now()),
                clock: SigningTime::now,
            }),
            stats: CodecStats::default(),
            stream_tail: Vec::new(),
        }
    }

    /// The same codec reading its signing clock from `clock` instead of the system's (tests,
    /// and simulations whose signers keep their own time).
    pub fn with_signing_clock(mut self, clock: fn() -> SigningTime) -> Self {
        if let Some(signing) = &mut self.signing {
            signing.clock = clock;
            signing.guard = ReplayGuard::new(clock());
        }
        self
    }

    /// Our system id.
    pub fn system_id(&self) -> u8 {
        self.system_id
    }

    /// What the decoder has seen so far.
    pub fn stats(&self) -> &CodecStats {
        &self.stats
    }

    /// Serialise `message` as the next frame from this endpoint (signed if configured).
    pub fn encode(&mut self, message: &MavMessage) -> Vec<u8> {
        let header = MavHeader {
            system_id: u32::from(self.system_id),
            component_id: self.component_id,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        // The raw frame buffer is sized for the largest MAVLink 2 frame, so serialising a
        // typed message cannot overflow it.
        let mut raw = MAVLinkV2MessageRaw::new();
        match &self.signing {
            Some(signing) => {
                raw.serialize_message_for_signing(header, message);
                signing.signer.sign_message(&mut raw);
            }
            None => raw.serialize_message(header, message),
        }
        raw.raw_bytes().to_vec()
    }

    /// Decode every frame in one datagram, appending accepted frames to `out`. A frame cut
    /// at the end of the datagram is counted as truncated. Never panics on any input.
    pub fn decode(&mut self, datagram: &[u8], out: &mut Vec<Frame>) {
        let consumed = self.decode_bytes(datagram, out, false);
        debug_assert_eq!(consumed, datagram.len());
    }

    /// Decode a chunk of a byte stream (TCP, serial): a frame cut at the end is kept and
    /// completed by the next chunk. Never panics on any input.
    pub fn decode_stream(&mut self, chunk: &[u8], out: &mut Vec<Frame>) {
        let mut buffer = std::mem::take(&mut self.stream_tail);
        buffer.extend_from_slice(chunk);
        let consumed = self.decode_bytes(&buffer, out, true);
        buffer.drain(..consumed);
        self.stream_tail = buffer;
    }

    /// Returns how many bytes were consumed (all, unless `stream` and a frame is incomplete).
    fn decode_bytes(&mut self, bytes: &[u8], out: &mut Vec<Frame>, stream: bool) -> usize {
        let mut i = 0;
        while i < bytes.len() {
            let step = match bytes[i] {
                STX_V2 => self.decode_v2(&bytes[i..], out),
                STX_V1 => self.skip_v1(&bytes[i..]),
                _ => {
                    self.stats.garbage_bytes += 1;
                    Step::Skip(1)
                }
            };
            match step {
                Step::Skip(n) => i += n,
                Step::Incomplete if stream => return i,
                Step::Incomplete => {
                    self.stats.truncated += 1;
                    return bytes.len();
                }
            }
        }
        i
    }

    /// Decode one v2 frame at the start of `bytes`.
    fn decode_v2(&mut self, bytes: &[u8], out: &mut Vec<Frame>) -> Step {
        if bytes.len() < V2_OVERHEAD {
            return Step::Incomplete;
        }
        let payload_len = usize::from(bytes[1]);
        let flags = bytes[2];
        if flags & !IFLAG_SIGNED != 0 {
            self.stats.unsupported_flags += 1;
            return Step::Skip(1);
        }
        let signed = flags & IFLAG_SIGNED != 0;
        let total = V2_OVERHEAD + payload_len + if signed { SIGNATURE_LEN } else { 0 };
        if bytes.len() < total {
            return Step::Incomplete;
        }
        let mut raw = MAVLinkV2MessageRaw::new();
        raw.as_mut_slice()[..total].copy_from_slice(&bytes[..total]);
        let message_id = raw.message_id();
        if MavMessage::default_message_from_id(message_id).is_none() {
            // The length byte is probably right: skip the whole frame.
            self.stats.unknown_message += 1;
            return Step::Skip(total);
        }
        if !raw.has_valid_crc::<MavMessage>() {
            // Cannot trust the length: resynchronise one byte further.
            self.stats.bad_crc += 1;
            return Step::Skip(1);
        }
        if let Some(signing) = &mut self.signing {
            if signed {
                let now = (signing.clock)();
                if signing.guard.verify(&signing.key, &raw, now).is_err() {
                    self.stats.bad_signature += 1;
                    return Step::Skip(total);
                }
            } else if !signing.accept_unsigned {
                self.stats.unsigned_rejected += 1;
                return Step::Skip(total);
            }
        }
        match MavMessage::parse(MavlinkVersion::V2, message_id, raw.payload()) {
            Ok(message) => {
                self.stats.frames += 1;
                out.push(Frame {
                    header: MavHeader {
                        system_id: raw.system_id(),
                        component_id: raw.component_id(),
                        sequence: raw.sequence(),
                    },
                    message,
                    raw: bytes[..total].to_vec(),
                    signed,
                });
            }
            Err(_) => self.stats.undecodable += 1,
        }
        Step::Skip(total)
    }

    /// Skip a well-formed MAVLink 1 frame (counted), or one byte of garbage.
    fn skip_v1(&mut self, bytes: &[u8]) -> Step {
        if bytes.len() >= V1_OVERHEAD {
            let total = V1_OVERHEAD + usize::from(bytes[1]);
            if bytes.len() >= total {
                let mut raw = MAVLinkV1MessageRaw::new();
                raw.as_mut_slice()[..total].copy_from_slice(&bytes[..total]);
                if raw.has_valid_crc::<MavMessage>() {
                    self.stats.mavlink1_rejected += 1;
                    return Step::Skip(total);
                }
            }
        }
        self.stats.garbage_bytes += 1;
        Step::Skip(1)
    }
}

/// What the decoder does next at one position.
enum Step {
    /// Move on by this many bytes.
    Skip(usize),
    /// A frame starts here but its end has not arrived.
    Incomplete,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signing::{KeyFileError, SigningKey};
    use mavlink::dialects::common::{HEARTBEAT_DATA, MavAutopilot, MavModeFlag, MavState, MavType};

    fn heartbeat() -> MavMessage {
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 6 << 16,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            system_status: MavState::MAV_STATE_STANDBY,
            mavlink_version: 3,
        })
    }

    fn key(b: u8) -> Signing {
        Signing {
            key: SigningKey([b; 32]),
            link_id: 1,
            accept_unsigned: false,
        }
    }

    #[test]
    fn round_trip_unsigned_with_sequence() {
        let mut tx = Codec::new(7, 1, None);
        let mut rx = Codec::new(255, 190, None);
        let mut bytes = tx.encode(&heartbeat());
        bytes.extend(tx.encode(&heartbeat()));
        let mut out = Vec::new();
        rx.decode(&bytes, &mut out);
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].header.system_id, 7);
        assert_eq!((out[0].header.sequence, out[1].header.sequence), (0, 1));
        assert_eq!(out[0].message, heartbeat());
        assert_eq!(rx.stats().frames, 2);
        assert_eq!(rx.stats().dropped_frames(), 0);
    }

    #[test]
    fn signed_link_rejects_unsigned_and_wrong_key_and_replay() {
        let mut good = Codec::new(7, 1, Some(key(1)));
        let mut wrong = Codec::new(7, 1, Some(key(2)));
        let mut plain = Codec::new(7, 1, None);
        let mut rx = Codec::new(255, 190, Some(key(1)));
        let mut out = Vec::new();
        let signed = good.encode(&heartbeat());
        rx.decode(&signed, &mut out);
        assert_eq!(out.len(), 1);
        assert!(out[0].signed);
        rx.decode(&signed, &mut out); // replay: same timestamp
        rx.decode(&plain.encode(&heartbeat()), &mut out);
        rx.decode(&wrong.encode(&heartbeat()), &mut out);
        assert_eq!(out.len(), 1);
        let s = rx.stats();
        assert_eq!((s.bad_signature, s.unsigned_rejected), (2, 1));
    }

    #[test]
    fn a_frame_from_the_future_is_rejected_and_the_link_keeps_working() {
        use crate::replay::sign;
        let mut rx = Codec::new(255, 190, Some(key(1)));
        let mut raw = MAVLinkV2MessageRaw::new();
        let header = MavHeader {
            system_id: 7,
            component_id: 1,
            sequence: 0,
        };
        raw.serialize_message_for_signing(header, &heartbeat());
        let year_ahead = SigningTime::now().plus_seconds(365.0 * 86_400.0);
        sign(&SigningKey([1; 32]), 1, year_ahead, &mut raw);
        let mut out = Vec::new();
        rx.decode(raw.raw_bytes(), &mut out);
        assert!(out.is_empty());
        assert_eq!(rx.stats().bad_signature, 1);
        // The honest sender, on the same stream, still gets through: nothing was dragged.
        let mut good = Codec::new(7, 1, Some(key(1)));
        rx.decode(&good.encode(&heartbeat()), &mut out);
        assert_eq!(out.len(), 1);
    }

    #[test]
    fn malformed_input_is_counted_never_panics() {
        let mut tx = Codec::new(7, 1, None);
        let mut rx = Codec::new(255, 190, None);
        let good = tx.encode(&heartbeat());
        let mut corrupt = good.clone();
        let last = corrupt.len() - 3;
        corrupt[last] ^= 0xFF; // payload byte: CRC mismatch
        let mut out = Vec::new();
        rx.decode(&corrupt, &mut out);
        rx.decode(&good[..good.len() - 4], &mut out);
        rx.decode(&[0x00, 0x11, 0x22], &mut out);
        rx.decode(&[STX_V2, 0xFF, 0x00], &mut out);
        // Every prefix and every single-byte corruption of a valid frame.
        for n in 0..good.len() {
            rx.decode(&good[..n], &mut out);
            let mut bad = good.clone();
            bad[n] = bad[n].wrapping_add(0x5A);
            rx.decode(&bad, &mut out);
        }
        assert!(out.iter().all(|f| f.message == heartbeat()));
        let s = rx.stats();
        assert!(s.bad_crc >= 1 && s.truncated >= 2 && s.garbage_bytes >= 3);
        rx.decode(&good, &mut out);
        assert_eq!(out.last().unwrap().message, heartbeat());
    }

    #[test]
    fn stream_frames_split_across_chunks() {
        let mut tx = Codec::new(7, 1, None);
        let mut rx = Codec::new(255, 190, None);
        let mut bytes = tx.encode(&heartbeat());
        bytes.extend(tx.encode(&heartbeat()));
        let mut out = Vec::new();
        for chunk in bytes.chunks(5) {
            rx.decode_stream(chunk, &mut out);
        }
        assert_eq!(out.len(), 2);
        assert_eq!(rx.stats().dropped_frames(), 0);
    }

    #[test]
    fn keys_parse_from_raw_or_hex_and_anything_else_is_refused() {
        const KEY: [u8; 32] = [9; 32];
        assert_eq!(SigningKey::parse(&KEY), Some(SigningKey(KEY)));
        let hex = format!("{}\n", "09".repeat(32));
        assert_eq!(SigningKey::parse(hex.as_bytes()), Some(SigningKey(KEY)));
        for bad in [&b""[..], &[0u8; 31], &[0u8; 33], "zz".repeat(32).as_bytes()] {
            assert_eq!(SigningKey::parse(bad), None);
        }
    }

    #[test]
    fn key_file_raw_and_hex() {
        let dir = std::env::temp_dir().join(format!("skyherd-key-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let write = |path: &std::path::Path, bytes: &[u8]| {
            use std::os::unix::fs::PermissionsExt;
            std::fs::write(path, bytes).unwrap();
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600)).unwrap();
        };
        let raw = dir.join("raw.key");
        write(&raw, &[9u8; 32]);
        assert_eq!(SigningKey::from_file(&raw).unwrap(), SigningKey([9; 32]));
        let hex = dir.join("hex.key");
        write(&hex, format!("{}\n", "0a".repeat(32)).as_bytes());
        assert_eq!(SigningKey::from_file(&hex).unwrap(), SigningKey([10; 32]));
        let short = dir.join("short.key");
        write(&short, &[1u8; 5]);
        assert!(matches!(
            SigningKey::from_file(&short),
            Err(KeyFileError::BadLength { .. })
        ));
        // A key open to others is refused, naming the mode.
        let open = dir.join("open.key");
        std::fs::write(&open, [9u8; 32]).unwrap();
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o644)).unwrap();
        }
        let err = SigningKey::from_file(&open).unwrap_err();
        assert!(
            matches!(err, KeyFileError::TooOpen { mode: 0o644, .. }),
            "{err}"
        );
        assert!(err.to_string().contains("644"));
        // A generated key is written 0600, read back, and never overwritten.
        let fresh = dir.join("fresh.key");
        let generated = SigningKey::generate().unwrap();
        generated.write_new_file(&fresh).unwrap();
        assert_eq!(SigningKey::from_file(&fresh).unwrap(), generated);
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&fresh).unwrap().permissions().mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        assert!(matches!(
            SigningKey::generate().unwrap().write_new_file(&fresh),
            Err(KeyFileError::Create { .. })
        ));
        // A symlink in a new key's place is not followed.
        let target = dir.join("target");
        let link = dir.join("link.key");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        assert!(generated.write_new_file(&link).is_err());
        assert!(!target.exists());
        // An endless file is refused, not read to the end.
        assert!(SigningKey::from_file(std::path::Path::new("/dev/zero")).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
