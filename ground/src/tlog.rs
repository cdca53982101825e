//! `.tlog` telemetry logs in pymavlink's format: each record is the receive time as a
//! big-endian u64 of microseconds since the Unix epoch, then the raw MAVLink frame bytes.
//!
//! The writer is pure over any [`Write`] and takes the timestamp from the caller, so a
//! simulated clock can stamp the log.
//!
//! ```
//! use skyherd_ground::tlog::TlogWriter;
//! let mut log = TlogWriter::new(Vec::new());
//! log.write_frame(1_700_000_000_000_000, &[0xFD, 0x00]).unwrap();
//! let bytes = log.into_inner();
//! assert_eq!(&bytes[..8], &1_700_000_000_000_000u64.to_be_bytes());
//! assert_eq!(&bytes[8..], &[0xFD, 0x00]);
//! ```

use std::io::{self, Write};

/// Appends timestamped frames to a `.tlog`.
#[derive(Debug)]
pub struct TlogWriter<W: Write> {
    out: W,
    records: u64,
}

impl<W: Write> TlogWriter<W> {
    /// A writer over `out` (a file, or a `Vec<u8>` in tests).
    pub fn new(out: W) -> Self {
        Self { out, records: 0 }
    }

    /// Append one frame received or sent at `unix_time_us` (microseconds since 1970-01-01).
    ///
    /// # Errors
    /// The underlying writer's I/O error.
    pub fn write_frame(&mut self, unix_time_us: u64, frame: &[u8]) -> io::Result<()> {
        self.out.write_all(&unix_time_us.to_be_bytes())?;
        self.out.write_all(frame)?;
        self.records += 1;
        Ok(())
    }

    /// Records written so far.
    pub fn records(&self) -> u64 {
        self.records
    }

    /// Flush the underlying writer.
    ///
    /// # Errors
    /// The underlying writer's I/O error.
    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    /// The underlying writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}
