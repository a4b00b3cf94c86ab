//! Work counted, not timed: how many nodes the cycle searches settle and how many entries of
//! the factors the estimator visits, on the calling thread.
//!
//! A step's latency depends on the machine and on what else runs on it (the same build and
//! file have measured 2× apart on different days here); the work a step does does not. The
//! online estimator counts three kinds of it as it goes:
//!
//! ```text
//! search_nodes          nodes settled by the incremental basis's shortest-path searches
//!                       (new loop closures, examinations of suspects, replays) and by the
//!                       landmarks' distance updates
//! estimate_entries      entries of R visited in the estimate's square-root factors: Givens
//!                       rotations of new rows (tried rows taken back included), forward and
//!                       back substitutions, right-hand sides rewritten
//! conditioning_entries  entries of the factor L of P_UU visited by the triangular solves that
//!                       condition a new cycle on the determined ones
//! ```
//!
//! The counts are deterministic: the same input gives the same counts in every run of a
//! build, on any machine. A factor renewed beside the live one is built on another thread, whose work is
//! not counted here; the step that collects it applies the changes the builder has not
//! reached yet, a number that depends on the threads' timing, and that work is not counted
//! either. So a count measures the algorithm, and a latency the machine.
//!
//! The counters belong to the thread ([`on_this_thread`]): a program that runs one estimator
//! per thread, as `so2lin stream` does, reads its estimator's work as the difference of two
//! readings. They are written here rather than kept in the estimator because the estimator
//! replaces itself when it replays (an eviction) and hands factors between threads; a
//! thread's count follows the work wherever the state goes.

use std::cell::Cell;

use serde::Serialize;

/// Work done on one thread ([`on_this_thread`]; module docs for what each counts).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Work {
    /// Nodes settled by the cycle searches and the landmarks' updates.
    pub search_nodes: u64,
    /// Entries of the estimate's square-root factors visited.
    pub estimate_entries: u64,
    /// Entries of the factor of P_UU visited by conditioning solves.
    pub conditioning_entries: u64,
}

impl Work {
    /// The work done between `earlier` and this reading (of the same thread).
    pub fn since(self, earlier: Work) -> Work {
        Work {
            search_nodes: self.search_nodes.saturating_sub(earlier.search_nodes),
            estimate_entries: self
                .estimate_entries
                .saturating_sub(earlier.estimate_entries),
            conditioning_entries: (self.conditioning_entries)
                .saturating_sub(earlier.conditioning_entries),
        }
    }
}

thread_local! {
    static COUNTED: Cell<Work> = const {
        Cell::new(Work {
            search_nodes: 0,
            estimate_entries: 0,
            conditioning_entries: 0,
        })
    };
    static PAUSED: Cell<bool> = const { Cell::new(false) };
}

/// The work this thread has done so far (module docs).
pub fn on_this_thread() -> Work {
    COUNTED.with(Cell::get)
}

fn add(f: impl FnOnce(&mut Work)) {
    if PAUSED.with(Cell::get) {
        return;
    }
    COUNTED.with(|c| {
        let mut w = c.get();
        f(&mut w);
        c.set(w);
    });
}

/// Count `n` nodes settled by a search.
pub(crate) fn searched(n: u64) {
    add(|w| w.search_nodes += n);
}

/// Count `n` entries of an estimate factor visited.
pub(crate) fn estimated(n: u64) {
    add(|w| w.estimate_entries += n);
}

/// Count `n` entries of the factor of P_UU visited.
pub(crate) fn conditioned(n: u64) {
    add(|w| w.conditioning_entries += n);
}

/// Run `f` without counting its work: the changes a renewal's collection applies itself
/// because the builder had not reached them (how many depends on the threads' timing).
pub(crate) fn paused<T>(f: impl FnOnce() -> T) -> T {
    let was = PAUSED.with(|p| p.replace(true));
    let out = f();
    PAUSED.with(|p| p.set(was));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_add_up_and_pause() {
        let before = on_this_thread();
        searched(3);
        estimated(5);
        paused(|| {
            conditioned(100);
            searched(100);
        });
        conditioned(7);
        let w = on_this_thread().since(before);
        assert_eq!(
            w,
            Work {
                search_nodes: 3,
                estimate_entries: 5,
                conditioning_entries: 7
            }
        );
    }
}
