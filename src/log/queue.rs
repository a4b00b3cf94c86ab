//! The hand-off queue between the estimator's thread and the log writer thread.
//!
//! It bounds what a crash can lose: it counts the steps pushed and not yet **durable** (in a
//! chunk the writer closed and flushed to the sink), and a step that would make them more than
//! the backlog bound ([`LogOptions::max_backlog`](super::LogOptions::max_backlog)) waits until
//! the writer's next flush (back-pressure). Other records (snapshots, sync, finish) never wait:
//! there is one snapshot per `snapshot_every` steps, so they are bounded by the steps.

use std::sync::{Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// How often an idle writer looks at the queue.
const POLL: Duration = Duration::from_millis(1);

/// The hand-off between the estimator's thread and the writer. Pushing a step takes an
/// uncontended lock and never wakes the writer — std's channels wake a parked receiver on
/// every send, a system call per step that cost more than the step itself; the writer looks
/// every [`POLL`] instead, and is woken at once for `sync`, `finish` and a full backlog.
pub(super) struct Queue<T> {
    inbox: Mutex<Inbox<T>>,
    wake: Condvar,
    space: Condvar,
    /// Steps not yet durable at most this many (at least 1).
    max_backlog: usize,
}

struct Inbox<T> {
    records: Vec<T>,
    /// Steps pushed and not yet durable (queued, or taken by the writer and in an open chunk).
    undurable: usize,
    /// A producer is waiting for the writer's flush.
    waiting: bool,
    /// No more records will come.
    closed: bool,
    /// The writer stopped (on an error).
    gone: bool,
}

fn lock<T>(m: &Mutex<Inbox<T>>) -> MutexGuard<'_, Inbox<T>> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl<T> Queue<T> {
    /// A queue holding at most `max_backlog` (at least 1) steps that are not durable yet.
    pub(super) fn new(max_backlog: usize) -> Self {
        Self {
            inbox: Mutex::new(Inbox {
                records: Vec::new(),
                undurable: 0,
                waiting: false,
                closed: false,
                gone: false,
            }),
            wake: Condvar::new(),
            space: Condvar::new(),
            max_backlog: max_backlog.max(1),
        }
    }

    /// Append a record; `urgent` wakes the writer. A `step` waits while `max_backlog` steps
    /// are not durable yet. `None` when the writer is gone, else how long the push waited
    /// (`None` inside: it did not wait).
    pub(super) fn push(&self, record: T, urgent: bool, step: bool) -> Option<Option<Duration>> {
        let mut inbox = lock(&self.inbox);
        let mut waited = None;
        if step && inbox.undurable >= self.max_backlog && !inbox.gone {
            let start = Instant::now();
            while inbox.undurable >= self.max_backlog && !inbox.gone {
                inbox.waiting = true;
                self.wake.notify_one();
                inbox = self
                    .space
                    .wait(inbox)
                    .unwrap_or_else(PoisonError::into_inner);
            }
            waited = Some(start.elapsed());
        }
        if inbox.gone {
            return None;
        }
        inbox.records.push(record);
        if step {
            inbox.undurable += 1;
        }
        if urgent {
            self.wake.notify_one();
        }
        Some(waited)
    }

    /// No more records.
    pub(super) fn close(&self) {
        lock(&self.inbox).closed = true;
        self.wake.notify_one();
    }

    /// The writer: wait for records until `deadline` (if any), move them all into `batch`;
    /// true once closed. Returns with an empty batch at the deadline, and when a producer
    /// waits for a flush.
    pub(super) fn take(&self, batch: &mut Vec<T>, deadline: Option<Instant>) -> bool {
        let mut inbox = lock(&self.inbox);
        while inbox.records.is_empty() && !inbox.closed && !inbox.waiting {
            let wait = match deadline {
                Some(d) => match d.checked_duration_since(Instant::now()) {
                    Some(left) if !left.is_zero() => left.min(POLL),
                    _ => break,
                },
                None => POLL,
            };
            inbox = self
                .wake
                .wait_timeout(inbox, wait)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        std::mem::swap(&mut inbox.records, batch);
        inbox.closed
    }

    /// Whether a producer is waiting for the writer's next flush.
    pub(super) fn producer_waiting(&self) -> bool {
        lock(&self.inbox).waiting
    }

    /// The writer flushed `steps` steps to the sink: they are durable; release a waiting
    /// producer.
    pub(super) fn durable(&self, steps: usize) {
        let mut inbox = lock(&self.inbox);
        inbox.undurable = inbox.undurable.saturating_sub(steps);
        inbox.waiting = false;
        drop(inbox);
        self.space.notify_all();
    }

    /// The writer stopped: drop what is queued and release a waiting producer.
    pub(super) fn gone(&self) {
        let mut inbox = lock(&self.inbox);
        inbox.gone = true;
        inbox.records.clear();
        drop(inbox);
        self.space.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn records_come_out_in_order_and_close_is_seen() {
        let q = Queue::new(100);
        for k in 0..10 {
            assert_eq!(q.push(k, false, true), Some(None));
        }
        let mut batch = Vec::new();
        assert!(!q.take(&mut batch, None));
        assert_eq!(batch, (0..10).collect::<Vec<_>>());
        batch.clear();
        assert!(q.push(10, false, false).is_some());
        q.close();
        assert!(q.take(&mut batch, None));
        assert_eq!(batch, vec![10]);
    }

    #[test]
    fn an_idle_take_returns_at_its_deadline() {
        let q: Queue<u32> = Queue::new(1);
        let mut batch = Vec::new();
        assert!(!q.take(&mut batch, Some(Instant::now())));
        assert!(batch.is_empty());
    }

    /// Steps wait once `max_backlog` of them are not durable, taken or not, until the writer
    /// flushes; other records never wait; a gone writer refuses.
    #[test]
    fn steps_wait_for_durability_and_a_gone_writer_refuses() {
        const MAX: usize = 8;
        let q = Arc::new(Queue::new(MAX));
        for k in 0..MAX {
            assert_eq!(q.push(k, false, true), Some(None));
        }
        // Taking them does not make them durable; a non-step record still goes in.
        let mut batch = Vec::new();
        q.take(&mut batch, None);
        assert_eq!(batch.len(), MAX);
        assert_eq!(q.push(100, false, false), Some(None));
        let writer = {
            let q = Arc::clone(&q);
            std::thread::spawn(move || {
                let mut batch = Vec::new();
                while !q.producer_waiting() {
                    q.take(&mut batch, None);
                }
                q.durable(MAX);
            })
        };
        // Blocks until the writer declares the steps durable (a writer waiting in `take`
        // returns, empty-handed, to flush).
        assert!(matches!(q.push(MAX, false, true), Some(Some(_))));
        writer.join().unwrap();
        assert!(!q.producer_waiting());
        q.gone();
        assert_eq!(q.push(0, true, true), None);
    }
}
