//! The hand-off queue between the estimator's thread and the log writer thread.

use std::sync::{Condvar, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

/// Records the queue may hold before a push waits for the writer (back-pressure bounds the
/// memory of a writer that cannot keep up).
const QUEUE: usize = 16_384;

/// How often an idle writer looks at the queue.
const POLL: Duration = Duration::from_millis(1);

/// The hand-off between the estimator's thread and the writer. Pushing a step takes an
/// uncontended lock and never wakes the writer — std's channels wake a parked receiver on
/// every send, a system call per step that cost more than the step itself; the writer looks
/// every [`POLL`] instead, and is woken at once for `sync`, `finish` and a full queue.
pub(super) struct Queue<T> {
    inbox: Mutex<Inbox<T>>,
    wake: Condvar,
    space: Condvar,
}

struct Inbox<T> {
    records: Vec<T>,
    /// No more records will come.
    closed: bool,
    /// The writer stopped (on an error).
    gone: bool,
}

fn lock<T>(m: &Mutex<Inbox<T>>) -> MutexGuard<'_, Inbox<T>> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl<T> Queue<T> {
    pub(super) fn new() -> Self {
        Self {
            inbox: Mutex::new(Inbox {
                records: Vec::new(),
                closed: false,
                gone: false,
            }),
            wake: Condvar::new(),
            space: Condvar::new(),
        }
    }

    /// Append a record; `urgent` wakes the writer. False when the writer is gone.
    pub(super) fn push(&self, record: T, urgent: bool) -> bool {
        let mut inbox = lock(&self.inbox);
        while inbox.records.len() >= QUEUE && !inbox.gone {
            self.wake.notify_one();
            inbox = self
                .space
                .wait(inbox)
                .unwrap_or_else(PoisonError::into_inner);
        }
        if inbox.gone {
            return false;
        }
        inbox.records.push(record);
        if urgent {
            self.wake.notify_one();
        }
        true
    }

    /// No more records.
    pub(super) fn close(&self) {
        lock(&self.inbox).closed = true;
        self.wake.notify_one();
    }

    /// The writer: wait for records, move them all into `batch`; true once closed.
    pub(super) fn take(&self, batch: &mut Vec<T>) -> bool {
        let mut inbox = lock(&self.inbox);
        while inbox.records.is_empty() && !inbox.closed {
            inbox = self
                .wake
                .wait_timeout(inbox, POLL)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        std::mem::swap(&mut inbox.records, batch);
        let closed = inbox.closed;
        drop(inbox);
        self.space.notify_all();
        closed
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
        let q = Queue::new();
        for k in 0..10 {
            assert!(q.push(k, false));
        }
        let mut batch = Vec::new();
        assert!(!q.take(&mut batch));
        assert_eq!(batch, (0..10).collect::<Vec<_>>());
        batch.clear();
        assert!(q.push(10, false));
        q.close();
        assert!(q.take(&mut batch));
        assert_eq!(batch, vec![10]);
    }

    #[test]
    fn a_full_queue_waits_for_the_writer_and_a_gone_writer_refuses() {
        let q = Arc::new(Queue::new());
        for k in 0..QUEUE {
            assert!(q.push(k, false));
        }
        let writer = {
            let q = Arc::clone(&q);
            std::thread::spawn(move || {
                let mut batch = Vec::new();
                q.take(&mut batch);
                batch.len()
            })
        };
        // Blocks until the writer has taken the full queue.
        assert!(q.push(QUEUE, false));
        assert_eq!(writer.join().ok(), Some(QUEUE));
        q.gone();
        assert!(!q.push(0, true));
    }
}
