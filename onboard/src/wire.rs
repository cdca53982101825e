//! The uplink from the ground station: world snapshots and mission commands, postcard-encoded,
//! split into chunks that fit one MAVLink `TUNNEL` payload (128 bytes), and reassembled on the
//! drone with fixed memory, tolerating lost, duplicated and reordered chunks.
//!
//! # Frames and units
//! Everything is in the **simulator frame**: x east, y north, z **up**, metres, origin at the
//! arena's south-west ground corner; speeds in m/s; `timestamp_ms` is the ground station's
//! clock in milliseconds (monotonic, any epoch), used only to judge staleness against the same
//! clock's later stamps. The drone converts to NED only for the autopilot
//! ([`crate::frame`]).
//!
//! # Chunk layout (wire version 1)
//! A message (postcard bytes of [`Uplink`], at most [`MAX_MESSAGE`] bytes) is cut into
//! `ceil(len / CHUNK_DATA)` chunks. Each chunk is a 14-byte little-endian header and up to
//! [`CHUNK_DATA`] bytes of the message:
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | `u8` | [`CHUNK_MAGIC`] |
//! | 1 | `u8` | [`WIRE_VERSION`] |
//! | 2 | `u16` | message id (wrapping; a newer id supersedes an unfinished older message) |
//! | 4 | `u16` | chunk index, `0..count` |
//! | 6 | `u16` | chunk count |
//! | 8 | `u16` | message length in bytes |
//! | 10 | `u32` | CRC-32 (ISO-HDLC) of the whole message |
//! | 14 | bytes | message bytes `index * CHUNK_DATA ..` (exactly as many as belong there) |
//!
//! ```
//! use skyherd_onboard::wire::{chunks, decode_uplink, encode_uplink, Reassembler, Uplink,
//!     WorldSnapshot, MAX_MESSAGE, TUNNEL_PAYLOAD};
//! use skyherd_onboard::Task;
//!
//! let mut snapshot = WorldSnapshot::empty(Task::Driving, [500.0, 500.0, 10.0]);
//! snapshot.sequence = 7;
//! for i in 0..300 {
//!     snapshot.targets.push([i as f32, 100.0]).unwrap();
//! }
//! let mut buffer = [0u8; MAX_MESSAGE];
//! let message = encode_uplink(&Uplink::Snapshot(snapshot.clone()), &mut buffer).unwrap();
//!
//! // Ground: one TUNNEL payload per chunk, sent in any order.
//! let mut sent: Vec<_> = chunks(1, message).unwrap().collect();
//! sent.reverse();
//! assert!(sent.iter().all(|c| c.as_bytes().len() <= TUNNEL_PAYLOAD));
//!
//! // Drone:
//! let mut reassembler = Reassembler::new();
//! let mut done = None;
//! for chunk in &sent {
//!     if let Some(bytes) = reassembler.push(chunk.as_bytes()).unwrap() {
//!         done = Some(decode_uplink(bytes).unwrap());
//!     }
//! }
//! assert_eq!(done, Some(Uplink::Snapshot(snapshot)));
//! ```

use core::fmt;

use heapless::Vec;
use serde::{Deserialize, Serialize};

use crate::Task;
use crate::obs::ObsInput;

/// Largest MAVLink `TUNNEL` payload, bytes.
pub const TUNNEL_PAYLOAD: usize = 128;
/// Bytes of chunk header.
pub const CHUNK_HEADER_LEN: usize = 14;
/// Message bytes carried per chunk.
pub const CHUNK_DATA: usize = TUNNEL_PAYLOAD - CHUNK_HEADER_LEN;
/// First byte of every chunk.
pub const CHUNK_MAGIC: u8 = 0xA7;
/// Chunk layout version.
pub const WIRE_VERSION: u8 = 1;
/// Most targets a snapshot carries.
pub const MAX_TARGETS: usize = 1024;
/// Most herders a snapshot carries.
pub const MAX_HERDERS: usize = 32;
/// Largest encoded message: a snapshot at full capacity is at most 8,624 bytes.
pub const MAX_MESSAGE: usize = 8704;
/// Most chunks of one message.
pub const MAX_CHUNKS: usize = MAX_MESSAGE.div_ceil(CHUNK_DATA);

const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// What the ground station knows of the world, sent to every drone. Simulator frame, metres.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorldSnapshot {
    /// Increments with every snapshot; lets the drone drop old ones.
    pub sequence: u32,
    /// Ground clock when the snapshot was taken, milliseconds.
    pub timestamp_ms: u64,
    /// The task being flown.
    pub task: Task,
    /// Every herder's position `[x, y, z]` (z up), in herder-id order.
    pub herders: Vec<[f32; 3], MAX_HERDERS>,
    /// Every tracked target's ground position `[x, y]`.
    pub targets: Vec<[f32; 2], MAX_TARGETS>,
    /// Goal circle centre `[x, y]`.
    pub goal: [f32; 2],
    /// Goal circle radius, metres.
    pub goal_radius: f32,
    /// Arena `[width (x), depth (y), ceiling (z)]`, from the origin.
    pub area: [f32; 3],
    /// Herders' speed limit, m/s.
    pub max_speed: f32,
}

impl WorldSnapshot {
    /// A snapshot with no herders or targets, the goal in the arena's centre with a 45 m radius
    /// and a 5 m/s speed limit: a starting point to fill in.
    pub fn empty(task: Task, area: [f32; 3]) -> WorldSnapshot {
        WorldSnapshot {
            sequence: 0,
            timestamp_ms: 0,
            task,
            herders: Vec::new(),
            targets: Vec::new(),
            goal: [area[0] / 2.0, area[1] / 2.0],
            goal_radius: 45.0,
            area,
            max_speed: 5.0,
        }
    }

    /// Whether every number is finite (the safety layer holds otherwise).
    pub fn is_finite(&self) -> bool {
        let finite = |xs: &[f32]| xs.iter().all(|x| x.is_finite());
        self.herders.iter().all(|h| finite(h))
            && self.targets.iter().all(|t| finite(t))
            && finite(&self.goal)
            && self.goal_radius.is_finite()
            && finite(&self.area)
            && self.max_speed.is_finite()
    }

    /// The encoder's view of this snapshot for herder `own_index`.
    pub fn obs_input(&self, own_index: usize) -> ObsInput<'_> {
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
}

/// Start or stop the task.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum MissionAction {
    /// Start (or restart) flying the task.
    Start,
    /// Stop: hold position and wait.
    Abort,
    /// The task is done (every target in the goal): hold position. Appended after `Abort`,
    /// so earlier encodings are unchanged.
    Complete,
}

/// A mission command from the ground station.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MissionCommand {
    /// Increments with every command.
    pub sequence: u32,
    /// The task to fly.
    pub task: Task,
    /// Goal circle centre `[x, y]`, simulator frame, metres.
    pub goal: [f32; 2],
    /// Goal circle radius, metres.
    pub goal_radius: f32,
    /// Start or abort.
    pub action: MissionAction,
}

/// Everything the ground sends up.
///
/// The snapshot variant is ~8.6 KiB inline on purpose: the core has no heap to box it in.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Uplink {
    /// A world snapshot.
    Snapshot(WorldSnapshot),
    /// A mission command.
    Command(MissionCommand),
}

/// Why uplink bytes could not be encoded, chunked, reassembled or decoded.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum WireError {
    /// postcard could not encode the message into the buffer given (too small).
    Encode,
    /// postcard could not decode the message bytes.
    Decode(postcard::Error),
    /// The message decoded but bytes were left over.
    TrailingBytes(usize),
    /// A message of this length cannot be chunked (empty, or above [`MAX_MESSAGE`]).
    MessageLength(usize),
    /// A chunk shorter than its header or longer than a TUNNEL payload.
    ChunkLength(usize),
    /// The chunk does not start with [`CHUNK_MAGIC`].
    BadMagic(u8),
    /// A chunk of a wire version this build does not read.
    UnsupportedVersion(u8),
    /// The chunk header's index, count and length do not agree with each other or the data.
    BadChunkHeader,
    /// A chunk of a message older than the one being assembled or last completed.
    Stale {
        /// The chunk's message id.
        message_id: u16,
    },
    /// Every chunk arrived but the message's CRC does not match: the message is dropped.
    CrcMismatch {
        /// The message id.
        message_id: u16,
    },
}

impl fmt::Display for WireError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            WireError::Encode => f.write_str("uplink message does not fit the encode buffer"),
            WireError::Decode(ref e) => write!(f, "uplink message does not decode: {e}"),
            WireError::TrailingBytes(n) => write!(f, "{n} bytes left after the uplink message"),
            WireError::MessageLength(n) => {
                write!(
                    f,
                    "message of {n} bytes cannot be chunked (1..={MAX_MESSAGE})"
                )
            }
            WireError::ChunkLength(n) => write!(
                f,
                "chunk of {n} bytes ({CHUNK_HEADER_LEN}..={TUNNEL_PAYLOAD} expected)"
            ),
            WireError::BadMagic(b) => {
                write!(f, "chunk magic {b:#04x}, expected {CHUNK_MAGIC:#04x}")
            }
            WireError::UnsupportedVersion(v) => {
                write!(f, "chunk wire version {v}, this build reads {WIRE_VERSION}")
            }
            WireError::BadChunkHeader => f.write_str("chunk index, count and length disagree"),
            WireError::Stale { message_id } => {
                write!(
                    f,
                    "chunk of message {message_id}, older than the current one"
                )
            }
            WireError::CrcMismatch { message_id } => {
                write!(
                    f,
                    "message {message_id} reassembled with a CRC mismatch, dropped"
                )
            }
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for WireError {}

/// postcard-encodes `message` into `buffer` and returns the bytes used.
pub fn encode_uplink<'b>(message: &Uplink, buffer: &'b mut [u8]) -> Result<&'b [u8], WireError> {
    postcard::to_slice(message, buffer)
        .map(|used| &*used)
        .map_err(|_| WireError::Encode)
}

/// Decodes one whole message; leftover bytes are an error.
pub fn decode_uplink(bytes: &[u8]) -> Result<Uplink, WireError> {
    let (message, rest) = postcard::take_from_bytes(bytes).map_err(WireError::Decode)?;
    if rest.is_empty() {
        Ok(message)
    } else {
        Err(WireError::TrailingBytes(rest.len()))
    }
}

/// A chunk's header fields.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ChunkHeader {
    /// Message id.
    pub message_id: u16,
    /// This chunk's index.
    pub index: u16,
    /// Chunks in the message.
    pub count: u16,
    /// Message length, bytes.
    pub message_len: u16,
    /// CRC-32 of the message.
    pub message_crc: u32,
}

impl ChunkHeader {
    /// Serialized header.
    pub fn to_bytes(&self) -> [u8; CHUNK_HEADER_LEN] {
        let mut b = [0u8; CHUNK_HEADER_LEN];
        b[0] = CHUNK_MAGIC;
        b[1] = WIRE_VERSION;
        b[2..4].copy_from_slice(&self.message_id.to_le_bytes());
        b[4..6].copy_from_slice(&self.index.to_le_bytes());
        b[6..8].copy_from_slice(&self.count.to_le_bytes());
        b[8..10].copy_from_slice(&self.message_len.to_le_bytes());
        b[10..14].copy_from_slice(&self.message_crc.to_le_bytes());
        b
    }

    /// Byte range of the message this chunk carries.
    fn span(&self) -> core::ops::Range<usize> {
        let start = self.index as usize * CHUNK_DATA;
        start..(start + CHUNK_DATA).min(self.message_len as usize)
    }
}

/// Checks a chunk and splits it into its header and the message bytes it carries.
pub fn parse_chunk(chunk: &[u8]) -> Result<(ChunkHeader, &[u8]), WireError> {
    if !(CHUNK_HEADER_LEN..=TUNNEL_PAYLOAD).contains(&chunk.len()) {
        return Err(WireError::ChunkLength(chunk.len()));
    }
    let (head, data) = chunk.split_at(CHUNK_HEADER_LEN);
    if head[0] != CHUNK_MAGIC {
        return Err(WireError::BadMagic(head[0]));
    }
    if head[1] != WIRE_VERSION {
        return Err(WireError::UnsupportedVersion(head[1]));
    }
    let u16_at = |i: usize| u16::from_le_bytes([head[i], head[i + 1]]);
    let header = ChunkHeader {
        message_id: u16_at(2),
        index: u16_at(4),
        count: u16_at(6),
        message_len: u16_at(8),
        message_crc: u32::from_le_bytes([head[10], head[11], head[12], head[13]]),
    };
    let len = header.message_len as usize;
    let consistent = (1..=MAX_MESSAGE).contains(&len)
        && header.count as usize == len.div_ceil(CHUNK_DATA)
        && header.index < header.count
        && header.span().len() == data.len();
    if consistent {
        Ok((header, data))
    } else {
        Err(WireError::BadChunkHeader)
    }
}

/// One chunk, ready to be the payload of a MAVLink `TUNNEL` message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Chunk {
    bytes: [u8; TUNNEL_PAYLOAD],
    len: u8,
}

impl Chunk {
    /// The chunk's bytes (header and data), at most [`TUNNEL_PAYLOAD`].
    pub fn as_bytes(&self) -> &[u8] {
        self.bytes.get(..self.len as usize).unwrap_or(&self.bytes)
    }
}

/// The chunks of one message, in order; see [`chunks`].
#[derive(Clone, Debug)]
pub struct Chunks<'a> {
    message: &'a [u8],
    header: ChunkHeader,
}

/// Splits `message` (at most [`MAX_MESSAGE`] bytes) into chunks with the given message id.
pub fn chunks(message_id: u16, message: &[u8]) -> Result<Chunks<'_>, WireError> {
    if !(1..=MAX_MESSAGE).contains(&message.len()) {
        return Err(WireError::MessageLength(message.len()));
    }
    let header = ChunkHeader {
        message_id,
        index: 0,
        count: message.len().div_ceil(CHUNK_DATA) as u16,
        message_len: message.len() as u16,
        message_crc: CRC32.checksum(message),
    };
    Ok(Chunks { message, header })
}

impl Iterator for Chunks<'_> {
    type Item = Chunk;
    fn next(&mut self) -> Option<Chunk> {
        if self.header.index >= self.header.count {
            return None;
        }
        let data = self.message.get(self.header.span())?;
        let mut bytes = [0u8; TUNNEL_PAYLOAD];
        bytes[..CHUNK_HEADER_LEN].copy_from_slice(&self.header.to_bytes());
        bytes[CHUNK_HEADER_LEN..CHUNK_HEADER_LEN + data.len()].copy_from_slice(data);
        self.header.index += 1;
        Some(Chunk {
            bytes,
            len: (CHUNK_HEADER_LEN + data.len()) as u8,
        })
    }
    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.header.count.saturating_sub(self.header.index) as usize;
        (left, Some(left))
    }
}

impl ExactSizeIterator for Chunks<'_> {}

/// Whether message id `a` is older than `b` (serial-number arithmetic: within half the range).
fn older(a: u16, b: u16) -> bool {
    (a.wrapping_sub(b) as i16) < 0
}

/// Reassembles chunked messages in fixed memory ([`MAX_MESSAGE`] bytes and a bitmap).
///
/// One message is assembled at a time; the newest id wins. Chunks may arrive in any order and
/// more than once. A chunk of a newer message abandons an unfinished older one (it was lost in
/// part; the next snapshot supersedes it anyway); chunks of older messages are refused with
/// [`WireError::Stale`]. Call [`Reassembler::reset`] when the sender restarts its ids.
#[derive(Clone, Debug)]
pub struct Reassembler {
    buffer: [u8; MAX_MESSAGE],
    received: [u32; MAX_CHUNKS.div_ceil(32)],
    current: Option<ChunkHeader>,
    received_count: u16,
    last_completed: Option<u16>,
}

impl Default for Reassembler {
    fn default() -> Self {
        Reassembler::new()
    }
}

impl Reassembler {
    /// An empty reassembler.
    pub const fn new() -> Reassembler {
        Reassembler {
            buffer: [0; MAX_MESSAGE],
            received: [0; MAX_CHUNKS.div_ceil(32)],
            current: None,
            received_count: 0,
            last_completed: None,
        }
    }

    /// Forgets everything, including which message ids were seen.
    pub fn reset(&mut self) {
        self.current = None;
        self.received_count = 0;
        self.received = [0; MAX_CHUNKS.div_ceil(32)];
        self.last_completed = None;
    }

    /// `(received, count)` chunks of the message being assembled, if any.
    pub fn progress(&self) -> Option<(u16, u16)> {
        self.current.map(|h| (self.received_count, h.count))
    }

    fn start(&mut self, header: ChunkHeader) {
        if let Some(old) = self.current {
            log::debug!(
                "uplink: message {} abandoned at {}/{} chunks for {}",
                old.message_id,
                self.received_count,
                old.count,
                header.message_id
            );
        }
        self.current = Some(ChunkHeader { index: 0, ..header });
        self.received = [0; MAX_CHUNKS.div_ceil(32)];
        self.received_count = 0;
    }

    /// Takes one chunk. Returns the whole message when this chunk completed it, `None` while
    /// chunks are missing (duplicates are accepted and ignored), and an error for a chunk that
    /// was not used or a completed message that failed its CRC.
    pub fn push(&mut self, chunk: &[u8]) -> Result<Option<&[u8]>, WireError> {
        let (header, data) = parse_chunk(chunk)?;
        let id = header.message_id;
        match self.current {
            Some(current) if current.message_id == id => {
                let same = (current.count, current.message_len, current.message_crc)
                    == (header.count, header.message_len, header.message_crc);
                if !same {
                    // The sender reused the id for another message: the newer content wins.
                    self.start(header);
                }
            }
            Some(current) if older(id, current.message_id) => {
                return Err(WireError::Stale { message_id: id });
            }
            _ => {
                if let Some(done) = self.last_completed
                    && !older(done, id)
                {
                    return Err(WireError::Stale { message_id: id });
                }
                self.start(header);
            }
        }
        let (word, bit) = (header.index as usize / 32, 1u32 << (header.index % 32));
        let Some(slot) = self.received.get_mut(word) else {
            return Err(WireError::BadChunkHeader);
        };
        if *slot & bit != 0 {
            return Ok(None);
        }
        let span = header.span();
        let Some(target) = self.buffer.get_mut(span) else {
            return Err(WireError::BadChunkHeader);
        };
        target.copy_from_slice(data);
        *slot |= bit;
        self.received_count += 1;
        if self.received_count < header.count {
            return Ok(None);
        }
        self.current = None;
        let message = self
            .buffer
            .get(..header.message_len as usize)
            .unwrap_or(&[]);
        if CRC32.checksum(message) != header.message_crc {
            log::warn!("uplink: message {id} failed its CRC, dropped");
            return Err(WireError::CrcMismatch { message_id: id });
        }
        self.last_completed = Some(id);
        Ok(Some(message))
    }
}
