//! A file writer that keeps the station's loop off the disk: writes gather in memory, each
//! [`Write::flush`] hands them to a writer thread, and a disk that stalls delays only that
//! thread.
//!
//! Why: the station answers every sensor scan within one lockstep period. Under writeback
//! pressure a single `write` to the `.tlog` or the CSV log can block for hundreds of
//! milliseconds (the daemon measured 680 ms for its replay state, `docs/security.md`), and a
//! blocked station loop delays the world-state uplink to every drone.
//!
//! Nothing is dropped: while the writer thread is behind, [`Spool::flush`] keeps the bytes in
//! memory, and only once [`MAX_PENDING_BYTES`] are waiting does it wait for the thread. Chunks
//! are written in order, each whole, so flushing at line or frame boundaries keeps the file in
//! whole lines or frames. An I/O error on the thread is kept and returned by the next
//! `write`, `flush` or [`SpoolStatus::wait_written`].
//!
//! ```
//! use std::io::Write;
//! use std::time::Duration;
//! use skyherd_ground::spool::Spool;
//!
//! let dir = std::env::temp_dir().join(format!("skyherd-spool-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! let path = dir.join("log.csv");
//! let mut log = Spool::new(std::fs::File::create(&path).unwrap());
//! let status = log.status();
//! writeln!(log, "t,x").unwrap();
//! log.flush().unwrap(); // returns at once; the thread writes
//! status.wait_written(Duration::from_secs(5)).unwrap();
//! assert_eq!(std::fs::read_to_string(&path).unwrap(), "t,x\n");
//! # std::fs::remove_dir_all(&dir).unwrap();
//! ```

use std::io::{self, Write};
use std::sync::mpsc::{self, SyncSender, TrySendError};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Chunks (flushes) queued for the writer thread before [`Spool::flush`] keeps further bytes
/// in memory instead.
pub const QUEUED_CHUNKS: usize = 256;

/// Bytes kept in memory while the writer thread is behind before [`Spool::flush`] waits for
/// it (the bound on the spool's memory, beside the queued chunks).
pub const MAX_PENDING_BYTES: usize = 8 << 20;

/// A [`Write`] whose bytes reach `W` on a thread of its own.
pub struct Spool {
    pending: Vec<u8>,
    sender: Option<SyncSender<Vec<u8>>>,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

/// What the writer thread has done, seen from any thread ([`Spool::status`]).
#[derive(Clone)]
pub struct SpoolStatus {
    shared: Arc<Shared>,
}

#[derive(Default)]
struct Shared {
    state: Mutex<State>,
    written: Condvar,
}

#[derive(Default)]
struct State {
    queued: u64,
    written: u64,
    bytes_written: u64,
    /// The first I/O error of the thread (kind and message: `io::Error` is not `Clone`).
    error: Option<(io::ErrorKind, String)>,
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn error(&self) -> io::Result<()> {
        match &self.lock().error {
            Some((kind, message)) => Err(io::Error::new(*kind, message.clone())),
            None => Ok(()),
        }
    }
}

impl Spool {
    /// A spool over `out` (a file), with its writer thread started.
    pub fn new<W: Write + Send + 'static>(mut out: W) -> Self {
        let (sender, receiver) = mpsc::sync_channel::<Vec<u8>>(QUEUED_CHUNKS);
        let shared = Arc::new(Shared::default());
        let thread_shared = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("spool".into())
            .spawn(move || {
                for chunk in receiver {
                    // After an error the rest is counted but not written: the file already
                    // has a hole, and the error is what the station reports.
                    let failed = thread_shared.lock().error.is_some();
                    let result = if failed {
                        Ok(())
                    } else {
                        out.write_all(&chunk).and_then(|()| out.flush())
                    };
                    let mut state = thread_shared.lock();
                    match result {
                        Ok(()) if !failed => state.bytes_written += chunk.len() as u64,
                        Ok(()) => {}
                        Err(e) => state.error = Some((e.kind(), e.to_string())),
                    }
                    state.written += 1;
                    drop(state);
                    thread_shared.written.notify_all();
                }
            })
            .ok();
        Self {
            pending: Vec::new(),
            // Without a thread (the system refused one) writes fail with that error below.
            sender: thread.as_ref().map(|_| sender),
            shared,
            thread,
        }
    }

    /// A handle on the writer thread's progress, for waiting until the bytes are on disk.
    pub fn status(&self) -> SpoolStatus {
        SpoolStatus {
            shared: Arc::clone(&self.shared),
        }
    }

    fn no_thread() -> io::Error {
        io::Error::other("the spool's writer thread could not be started")
    }

    /// Hand the pending bytes to the thread; wait for room only when `block`.
    fn hand_over(&mut self, block: bool) -> io::Result<()> {
        if self.pending.is_empty() {
            return Ok(());
        }
        let Some(sender) = &self.sender else {
            return Err(Self::no_thread());
        };
        let chunk = std::mem::take(&mut self.pending);
        let sent = if block {
            sender.send(chunk).map_err(|_| ())
        } else {
            match sender.try_send(chunk) {
                Ok(()) => Ok(()),
                Err(TrySendError::Full(chunk)) => {
                    // Behind: keep the bytes for the next flush.
                    self.pending = chunk;
                    return Ok(());
                }
                Err(TrySendError::Disconnected(_)) => Err(()),
            }
        };
        // Counted once sent: the thread may count it written first, which only means that
        // a waiter finds nothing left to wait for, as is true.
        sent.map(|()| self.shared.lock().queued += 1)
            .map_err(|()| io::Error::other("the spool's writer thread ended"))
    }
}

impl Write for Spool {
    fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        self.shared.error()?;
        if self.sender.is_none() {
            return Err(Self::no_thread());
        }
        self.pending.extend_from_slice(bytes);
        Ok(bytes.len())
    }

    /// Hands the bytes written so far to the writer thread and returns without waiting for
    /// the disk, unless [`MAX_PENDING_BYTES`] are already waiting.
    fn flush(&mut self) -> io::Result<()> {
        self.shared.error()?;
        let block = self.pending.len() >= MAX_PENDING_BYTES;
        self.hand_over(block)
    }
}

impl Drop for Spool {
    /// Writes what is left and waits for the thread (errors are for [`SpoolStatus`]).
    fn drop(&mut self) {
        let _ = self.hand_over(true);
        self.sender = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl SpoolStatus {
    /// Wait until every chunk flushed so far is written, for at most `timeout`.
    ///
    /// # Errors
    /// The writer thread's first I/O error, or `TimedOut` while chunks are still queued.
    pub fn wait_written(&self, timeout: Duration) -> io::Result<()> {
        let deadline = Instant::now() + timeout;
        let mut state = self.shared.lock();
        while state.written < state.queued {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                let behind = state.queued - state.written;
                drop(state);
                self.shared.error()?;
                return Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    format!("{behind} chunks still unwritten after {timeout:?}"),
                ));
            }
            state = self
                .shared
                .written
                .wait_timeout(state, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        drop(state);
        self.shared.error()
    }

    /// Bytes the writer thread has written so far.
    pub fn bytes_written(&self) -> u64 {
        self.shared.lock().bytes_written
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc::{Receiver, Sender};

    /// A writer that appends into a shared buffer, each write waiting for a go from the test.
    struct Gated {
        out: Arc<Mutex<Vec<u8>>>,
        go: Receiver<()>,
    }

    impl Write for Gated {
        fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
            self.go.recv().map_err(|_| io::Error::other("no more go"))?;
            self.out.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    fn gated() -> (Spool, Arc<Mutex<Vec<u8>>>, Sender<()>) {
        let out = Arc::new(Mutex::new(Vec::new()));
        let (go, gate) = mpsc::channel();
        let spool = Spool::new(Gated {
            out: Arc::clone(&out),
            go: gate,
        });
        (spool, out, go)
    }

    #[test]
    fn a_stalled_disk_does_not_stall_the_flush_and_nothing_is_lost() {
        let (mut spool, out, go) = gated();
        let status = spool.status();
        // The writer is stalled (no go yet): more flushes than the queue holds still return,
        // the ones past the queue keeping their bytes in memory.
        let (done, finished) = mpsc::channel();
        let writer = std::thread::spawn(move || {
            for i in 0..(QUEUED_CHUNKS + 50) {
                writeln!(spool, "line {i}").unwrap();
                spool.flush().unwrap();
            }
            done.send(()).unwrap();
            spool
        });
        finished
            .recv_timeout(Duration::from_secs(30))
            .expect("flush waited for the stalled writer");
        let spool = writer.join().unwrap();
        assert!(out.lock().unwrap().is_empty());
        // The disk comes back: everything arrives, in order, once the spool is dropped.
        std::thread::spawn(move || while go.send(()).is_ok() {});
        drop(spool);
        status.wait_written(Duration::from_secs(30)).unwrap();
        let text = String::from_utf8(out.lock().unwrap().clone()).unwrap();
        let expected: String = (0..(QUEUED_CHUNKS + 50))
            .map(|i| format!("line {i}\n"))
            .collect();
        assert_eq!(text, expected);
        assert_eq!(status.bytes_written(), expected.len() as u64);
    }

    struct Failing;

    impl Write for Failing {
        fn write(&mut self, _: &[u8]) -> io::Result<usize> {
            Err(io::Error::new(io::ErrorKind::StorageFull, "disk full"))
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn the_threads_error_comes_back_to_the_writer() {
        let mut spool = Spool::new(Failing);
        let status = spool.status();
        spool.write_all(b"frame").unwrap();
        spool.flush().unwrap();
        let e = status.wait_written(Duration::from_secs(30)).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::StorageFull);
        assert!(e.to_string().contains("disk full"), "{e}");
        let e = spool.write_all(b"more").unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::StorageFull);
        assert_eq!(
            spool.flush().unwrap_err().kind(),
            io::ErrorKind::StorageFull
        );
        assert_eq!(status.bytes_written(), 0);
    }

    #[test]
    fn waiting_on_a_stalled_disk_times_out_with_what_is_left() {
        let (mut spool, _out, go) = gated();
        let status = spool.status();
        spool.write_all(b"a").unwrap();
        spool.flush().unwrap();
        let e = status.wait_written(Duration::from_millis(50)).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::TimedOut);
        assert!(e.to_string().contains("1 chunks"), "{e}");
        go.send(()).unwrap();
        status.wait_written(Duration::from_secs(30)).unwrap();
        drop(spool);
    }
}
