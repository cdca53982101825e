//! Log output that never blocks the thread that logs: formatted lines go through a bounded
//! queue to a thread of its own that writes them out (the daemon's stderr, usually a file).
//!
//! Why: a write to a file can block for hundreds of milliseconds when the kernel throttles
//! writers under writeback pressure (a large build writing gigabytes beside the mission), and
//! the daemon logs from its control thread, whose setpoints PX4 drops out of OFFBOARD for
//! after 1 s without. A full queue drops lines and says how many.
//!
//! ```
//! use std::io::Write;
//! use skyherd_daemon::log_queue::LogQueue;
//! let (mut line_sink, queue) = LogQueue::spawn(Vec::new(), 16);
//! line_sink.write_all(b"hello\n").unwrap();
//! drop(line_sink); // a logger installed for the process keeps it: see `wait_written`
//! let written = queue.finish();
//! assert_eq!(written, b"hello\n");
//! ```

use std::io::{self, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::thread;
use std::time::{Duration, Instant};

/// The logging side: `Write` that queues each write and returns at once.
#[derive(Debug)]
pub struct QueuedWriter {
    sender: SyncSender<Vec<u8>>,
    counts: Arc<Counts>,
}

/// Shared between the two sides.
#[derive(Debug, Default)]
struct Counts {
    /// Writes dropped since the writer last said so.
    dropped: AtomicU64,
    /// Writes queued and not yet written.
    pending: AtomicU64,
}

impl Write for QueuedWriter {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        // Counted before it is sent, so that the writer never counts it down first.
        self.counts.pending.fetch_add(1, Ordering::AcqRel);
        match self.sender.try_send(buf.to_vec()) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                self.counts.pending.fetch_sub(1, Ordering::AcqRel);
                self.counts.dropped.fetch_add(1, Ordering::Relaxed);
            }
            // The writer has gone: nothing left to write to.
            Err(TrySendError::Disconnected(_)) => {
                self.counts.pending.fetch_sub(1, Ordering::AcqRel);
            }
        }
        Ok(buf.len())
    }

    /// Returns at once: the writer thread writes (and flushes) in its own time.
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// The writing side: the thread and what it writes to.
#[derive(Debug)]
pub struct LogQueue<W> {
    thread: thread::JoinHandle<W>,
    counts: Arc<Counts>,
}

impl<W: Write + Send + 'static> LogQueue<W> {
    /// A queue of at most `capacity` writes in front of `out`, and its writer thread.
    pub fn spawn(out: W, capacity: usize) -> (QueuedWriter, Self) {
        let (sender, receiver) = mpsc::sync_channel(capacity.max(1));
        let counts = Arc::new(Counts::default());
        let writer = QueuedWriter {
            sender,
            counts: counts.clone(),
        };
        let shared = counts.clone();
        let thread = thread::spawn(move || drain(receiver, out, &shared));
        (writer, Self { thread, counts })
    }

    /// Waits until every queued line is written, once every `QueuedWriter` is gone; the
    /// output back.
    pub fn finish(self) -> W {
        self.thread
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    }

    /// Waits (at most `timeout`) until what is queued now is written, for a process about to
    /// end whose logger still holds its `QueuedWriter`. Whether it all was.
    pub fn wait_written(&self, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        while self.counts.pending.load(Ordering::Acquire) > 0 {
            if Instant::now() >= deadline || self.thread.is_finished() {
                return false;
            }
            thread::sleep(Duration::from_millis(1));
        }
        true
    }
}

fn drain<W: Write>(receiver: Receiver<Vec<u8>>, mut out: W, counts: &Counts) -> W {
    for line in receiver {
        let lost = counts.dropped.swap(0, Ordering::Relaxed);
        if lost > 0 {
            let _ = writeln!(out, "[log: {lost} lines dropped, the output was too slow]");
        }
        let _ = out.write_all(&line);
        let _ = out.flush();
        counts.pending.fetch_sub(1, Ordering::AcqRel);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An output whose first write blocks until opened, like a file under writeback
    /// throttling; it says when that write has begun.
    struct Gate {
        entered: mpsc::Sender<()>,
        open: mpsc::Receiver<()>,
        written: Vec<u8>,
        waited: bool,
    }

    impl Write for Gate {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            if !self.waited {
                self.waited = true;
                let _ = self.entered.send(());
                let _ = self.open.recv();
            }
            self.written.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_blocked_output_does_not_block_the_logger_and_lost_lines_are_counted() {
        let (entered_tx, entered) = mpsc::channel();
        let (open, open_rx) = mpsc::channel();
        let out = Gate {
            entered: entered_tx,
            open: open_rx,
            written: Vec::new(),
            waited: false,
        };
        let (mut writer, queue) = LogQueue::spawn(out, 2);
        writer.write_all(b"line 0\n").unwrap();
        // The writer thread is stuck in its first write ...
        entered.recv().unwrap();
        // ... so two lines fill the queue and three are dropped; every write returns at once.
        for i in 1..6 {
            writer.write_all(format!("line {i}\n").as_bytes()).unwrap();
        }
        writer.flush().unwrap();
        assert!(
            !queue.wait_written(Duration::from_millis(20)),
            "still blocked"
        );
        open.send(()).unwrap();
        assert!(queue.wait_written(Duration::from_secs(5)));
        drop(writer);
        let text = String::from_utf8(queue.finish().written).unwrap();
        assert_eq!(
            text,
            "line 0\n[log: 3 lines dropped, the output was too slow]\nline 1\nline 2\n"
        );
    }
}
