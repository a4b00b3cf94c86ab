//! Renewing a factor without a stall: a fresh factor built beside the live one on another
//! thread, kept up to date with the live system's changes, and swapped in at a point of the
//! run fixed in advance.
//!
//! The live factor fills as the graph grows (new nodes go to the end of its order); a renewal
//! builds the same system in a fill-reducing order from a snapshot. Every change the live
//! system makes after the snapshot is queued for the builder, which applies it to its copy as
//! it comes. At the point the owner fixed when the renewal started (counted in steps and in
//! the live factor's own work, so the run does not depend on the threads' timing), the owner
//! **takes over** the builder's state between two
//! changes, applies whatever changes the builder had not reached yet itself, and swaps the
//! result in. Taking over instead of asking the builder to finish saves the round trip of
//! waking it (20–130 µs a renewal on the development machine, more when it is descheduled):
//! a step waits only while the builder is still building its snapshot, or applying one change
//! (a step that finds it applying one asks it to leave its state out after that change rather
//! than take the next: it used to take them all, and the step waited until its queue was empty).
//! Applying the same changes in the same order to the same state gives the same bits on
//! either thread, so the answers do not depend on who applied them. (A build reads no state
//! but its own, with one exception kept in check: METIS, which splits the graphs of large
//! renewals, draws from a generator the whole process shares, so its calls are made one at a
//! time — `estimate::incremental::dissection`.)

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};

/// A job for a [`Worker`].
type Job = Box<dyn FnOnce() + Send>;

/// A long-lived thread that runs jobs in the order given: builds of renewed factors, and the
/// freeing of retired ones (a factor's thousands of rows cost a step about a millisecond to
/// free). One thread for the estimator's life, so no step pays for starting a thread after the
/// first renewal. Each job is sent with the thread kept off the sender's current core
/// ([`avoid_callers_core`]).
#[derive(Default)]
pub(crate) struct Worker {
    tx: Option<std::sync::mpsc::Sender<Job>>,
    /// The worker thread's kernel id (Linux; 0 when unknown), to keep it off the caller's core.
    tid: std::sync::Arc<std::sync::atomic::AtomicI32>,
    /// Tests: start no thread, as when the system refuses one.
    #[cfg(test)]
    refuse: bool,
}

impl Worker {
    /// Run `job` on the worker thread (started on first use as `name`). False when no thread
    /// can be started or it is gone: the caller goes on without.
    pub fn run(&mut self, name: &str, job: Job) -> bool {
        if !self.ready(name) {
            return false;
        }
        avoid_callers_core(self.tid.load(std::sync::atomic::Ordering::Acquire));
        match &self.tx {
            Some(tx) if tx.send(job).is_ok() => true,
            _ => {
                self.tx = None;
                false
            }
        }
    }

    /// Whether the worker thread is there, started as `name` if it was not: false when no
    /// thread can be started.
    pub fn ready(&mut self, name: &str) -> bool {
        #[cfg(test)]
        if self.refuse {
            return false;
        }
        if self.tx.is_none() {
            let (tx, rx) = std::sync::mpsc::channel::<Job>();
            let tid = std::sync::Arc::clone(&self.tid);
            let spawned = std::thread::Builder::new()
                .name(name.into())
                .spawn(move || {
                    tid.store(thread_id(), std::sync::atomic::Ordering::Release);
                    builder_scheduling();
                    for job in rx {
                        job();
                    }
                })
                .is_ok();
            if !spawned {
                return false;
            }
            self.tx = Some(tx);
        }
        true
    }

    /// A worker that never starts a thread (tests: the path of a system that refuses one).
    #[cfg(test)]
    pub fn refusing() -> Self {
        Self {
            refuse: true,
            ..Self::default()
        }
    }

    /// Free `value` on the worker thread (here if there is none).
    pub fn retire<T: Send + 'static>(&mut self, name: &str, value: T) {
        self.run(name, Box::new(move || drop(value)));
    }
}

/// The calling thread's kernel id (Linux), 0 elsewhere.
fn thread_id() -> i32 {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid reads nothing of ours.
    return unsafe { libc::gettid() };
    #[cfg(not(target_os = "linux"))]
    0
}

/// Let thread `tid` run on the cores the caller may use, but not the one it is on now (Linux):
/// a builder woken by the robot's thread was queued behind it on the same core (at nice 10
/// then; a batch thread now, [`builder_scheduling`]) until the step blocked — M3500's worst
/// steps were those waits, up to 9 ms for a 0.3 ms build. The core avoided, or None (nothing
/// changed) when `tid` is not known yet, the caller may use one core only, or the system
/// refuses.
fn avoid_callers_core(tid: i32) -> Option<usize> {
    #[cfg(target_os = "linux")]
    // SAFETY: a zeroed cpu_set_t filled by sched_getaffinity and the libc macros, passed by
    // pointer with its size; sched_getcpu reads nothing of ours.
    unsafe {
        if tid <= 0 {
            return None;
        }
        let size = std::mem::size_of::<libc::cpu_set_t>();
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        let here = usize::try_from(libc::sched_getcpu()).ok()?;
        if libc::sched_getaffinity(0, size, &mut set) != 0 || here >= libc::CPU_SETSIZE as usize {
            return None;
        }
        libc::CPU_CLR(here, &mut set);
        if libc::CPU_COUNT(&set) == 0 || libc::sched_setaffinity(tid, size, &set) != 0 {
            return None;
        }
        Some(here)
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = tid;
        None
    }
}

/// The builder's scheduling (Linux; elsewhere nothing): `SCHED_BATCH` at the process's own
/// nice value. A batch thread does not preempt a running thread when it wakes, so a builder
/// woken on the robot's core does not take it from a step; otherwise it gets a fair share of
/// the machine. The builder used to run at nice 10, which kept it off the step's core as well but
/// starved it behind any other busy process on the machine (a nice-10 thread weighs a tenth of
/// a nice-0 one): the collection that needed its factor then waited. With processes spinning
/// beside the stream (`so2lin stream FILE --json`, robot order, the newest pose read after
/// every step), nice 10 against batch at nice 0: M3500 with two, worst step 14–39 ms against
/// 5.5–8.1 ms and 0.24 against 0.17 s of steps; city10000 with one, 34–55 ms against 16–20 ms
/// and 1.38 against 1.03 s. Quiet, the same within the noise (M3500 worst step 0.45–4.8 ms
/// against 0.41–2.3 ms over fourteen runs each, p99 143 against 140 µs). A refusal leaves the
/// thread as it was.
fn builder_scheduling() {
    #[cfg(target_os = "linux")]
    // SAFETY: sched_setscheduler with pid 0 changes only the calling thread's policy, reading
    // the sched_param we pass by pointer; nothing else of ours is read or written.
    unsafe {
        let param = libc::sched_param { sched_priority: 0 };
        libc::sched_setscheduler(0, libc::SCHED_BATCH, &param);
    }
}

/// What the owner and the builder share (under one lock, held only to move values).
struct Shared<S, M> {
    /// Changes sent and not yet taken by the builder, oldest first.
    queue: VecDeque<M>,
    /// The builder's state between two changes (None while it builds or applies one).
    state: Option<S>,
    /// The build, or a change, failed.
    failed: bool,
    /// The owner took the state over, or dropped the renewal: the builder stops.
    done: bool,
    /// The builder is waiting for a change (a change sent then must wake it; otherwise the
    /// owner's step saves the system call).
    idle: bool,
    /// The owner is waiting to take the state over: the builder leaves it after the change it
    /// is applying instead of taking the next one.
    wanted: bool,
}

/// The lock and the condition both sides wait on.
type Link<S, M> = Arc<(Mutex<Shared<S, M>>, Condvar)>;

/// A factor built beside the live one on a [`Worker`] (see the module docs): state `S`
/// built from a snapshot, changes `M` applied to it, result `T` swapped in. The one renewal
/// mechanism of the estimate's factors and of the factor of P_UU; they differ only in what
/// they build and which changes they send.
pub(crate) struct Beside<S, T, M> {
    link: Link<S, M>,
    apply: fn(&mut S, M) -> Option<()>,
    finish: fn(S) -> T,
}

/// When a renewal is collected: at the first step that is at least `step` and at which the
/// owner's live work (entries of its factor visited, counted) has reached `work` — counts, not
/// clocks, so the run does not depend on the threads' timing.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Due {
    /// The step, at least.
    pub step: u64,
    /// The live work, at least.
    pub work: u64,
}

impl Due {
    /// Whether the renewal is due at `step` with the live work at `work`.
    pub fn reached(&self, step: u64, work: u64) -> bool {
        step >= self.step && work >= self.work
    }
}

/// Owned by a builder's job: however the job ends — done, failed, panicked, or dropped
/// unrun because the worker thread is gone — an owner waiting for the state is woken, and
/// finds the renewal failed unless it has taken the state already.
struct Abandon<S, M>(Link<S, M>);

impl<S, M> Drop for Abandon<S, M> {
    fn drop(&mut self) {
        let (m, cv) = &*self.0;
        if let Ok(mut g) = m.lock()
            && g.state.is_none()
        {
            g.failed = true;
        }
        cv.notify_all();
    }
}

/// Lock, treating a poisoned lock (a builder that panicked) as gone.
fn lock<S, M>(m: &Mutex<Shared<S, M>>) -> Option<std::sync::MutexGuard<'_, Shared<S, M>>> {
    m.lock().ok()
}

impl<S: Send + 'static, T, M: Send + 'static> Beside<S, T, M> {
    /// Start a builder on `worker`: `build` makes the fresh state from the snapshot it owns,
    /// `apply` applies each change sent later (None: the renewal fails; run by the builder
    /// or, for the changes it has not reached at the collection, by the owner), `finish`
    /// turns the state into the result. None when the worker cannot take it: the live factor
    /// goes on, and the owner may try again later.
    pub fn start(
        worker: &mut Worker,
        name: &str,
        build: impl FnOnce() -> Option<S> + Send + 'static,
        apply: fn(&mut S, M) -> Option<()>,
        finish: fn(S) -> T,
    ) -> Option<Self> {
        let link: Link<S, M> = Arc::new((
            Mutex::new(Shared {
                queue: VecDeque::new(),
                state: None,
                failed: false,
                done: false,
                idle: false,
                wanted: false,
            }),
            Condvar::new(),
        ));
        let theirs = Abandon(Arc::clone(&link));
        let job: Job = Box::new(move || {
            let (m, cv) = &*theirs.0;
            let built = build();
            let Some(mut g) = lock(m) else { return };
            match built {
                Some(s) => g.state = Some(s),
                None => g.failed = true,
            }
            cv.notify_all();
            while !g.failed {
                g.idle = true;
                let idle = |s: &mut Shared<S, M>| (s.queue.is_empty() || s.wanted) && !s.done;
                let Ok(waited) = cv.wait_while(g, idle) else {
                    return;
                };
                g = waited;
                g.idle = false;
                if g.done {
                    return;
                }
                let (Some(change), Some(mut s)) = (g.queue.pop_front(), g.state.take()) else {
                    return;
                };
                drop(g);
                let ok = apply(&mut s, change).is_some();
                let Some(back) = lock(m) else { return };
                g = back;
                if ok {
                    g.state = Some(s);
                } else {
                    g.failed = true;
                }
                cv.notify_all();
            }
        });
        worker.run(name, job).then_some(Self {
            link,
            apply,
            finish,
        })
    }

    /// Queue a change for the builder; false when it is gone (the owner drops the renewal).
    pub fn send(&self, change: M) -> bool {
        self.send_all(std::iter::once(change))
    }

    /// Queue changes for the builder, in order, under one lock and with one wake-up; false
    /// when it is gone (the owner drops the renewal).
    pub fn send_all(&self, changes: impl IntoIterator<Item = M>) -> bool {
        let (m, cv) = &*self.link;
        let Some(mut g) = lock(m) else { return false };
        if g.failed {
            return false;
        }
        g.queue.extend(changes);
        let wake = g.idle;
        drop(g);
        if wake {
            cv.notify_all();
        }
        true
    }

    /// The built factor with every change sent applied (the ones the builder has not reached
    /// are applied here; a step that finds the builder still building, or inside a change,
    /// waits and counts in `waits`), or None when the build failed or the builder is gone
    /// (the live factor goes on). The owner collects when a [`Due`] fixed in advance is
    /// reached (not when the builder happens to be done), so that the run does not depend on
    /// the threads' timing.
    pub fn collect(self, waits: &mut usize) -> Option<T> {
        let (m, cv) = &*self.link;
        let mut g = lock(m)?;
        if g.state.is_none() && !g.failed {
            *waits += 1;
            // The builder leaves its state out after the change it is applying, rather than
            // going on through its queue while this step waits.
            g.wanted = true;
            g = cv.wait_while(g, |s| s.state.is_none() && !s.failed).ok()?;
        }
        g.done = true;
        let state = g.state.take();
        let left = std::mem::take(&mut g.queue);
        drop(g);
        cv.notify_all();
        let mut state = state?;
        // How many changes are left here depends on the threads' timing: their work is not
        // counted (module `crate::work`), so that the counts stay deterministic.
        let apply = self.apply;
        crate::work::paused(|| {
            left.into_iter()
                .try_for_each(|change| apply(&mut state, change))
        })?;
        Some((self.finish)(state))
    }
}

impl<S, T, M> Drop for Beside<S, T, M> {
    /// A renewal dropped before its collection stops its builder.
    fn drop(&mut self) {
        let (m, cv) = &*self.link;
        if let Ok(mut g) = m.lock() {
            g.done = true;
        }
        cv.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A worker that has run its first job, and its thread's kernel id.
    fn running_worker() -> (Worker, i32) {
        let mut worker = Worker::default();
        let (tx, rx) = std::sync::mpsc::channel();
        assert!(worker.run(
            "t",
            Box::new(move || {
                let _ = tx.send(());
            })
        ));
        rx.recv().expect("the first job ran");
        let tid = worker.tid.load(std::sync::atomic::Ordering::Acquire);
        (worker, tid)
    }

    /// A job is sent with the worker kept off the sender's core: on Linux, when the sending
    /// thread may use two cores or more, the worker's allowed cores lack the one the sender was
    /// on, and keep the others.
    #[test]
    fn the_worker_runs_off_the_senders_core() {
        let (_worker, tid) = running_worker();
        #[cfg(target_os = "linux")]
        // SAFETY: zeroed cpu_set_t values filled by sched_getaffinity, read by the libc macros.
        unsafe {
            assert!(tid > 0, "the worker's id is known once it runs");
            let size = std::mem::size_of::<libc::cpu_set_t>();
            let mut mine: libc::cpu_set_t = std::mem::zeroed();
            assert_eq!(libc::sched_getaffinity(0, size, &mut mine), 0);
            let cores = libc::CPU_COUNT(&mine);
            match avoid_callers_core(tid) {
                Some(core) => {
                    let mut theirs: libc::cpu_set_t = std::mem::zeroed();
                    assert_eq!(libc::sched_getaffinity(tid, size, &mut theirs), 0);
                    assert!(!libc::CPU_ISSET(core, &theirs), "core {core} still allowed");
                    assert_eq!(libc::CPU_COUNT(&theirs), cores - 1);
                }
                None => {
                    assert!(cores < 2, "not applied with {cores} cores");
                    println!("skipped: this thread may use one core only");
                }
            }
        }
        #[cfg(not(target_os = "linux"))]
        assert_eq!(avoid_callers_core(tid), None);
    }

    /// The worker thread is a batch thread (Linux): it does not preempt the step's thread when
    /// it wakes, and is not starved behind other busy processes as a niced thread was.
    #[test]
    fn the_worker_is_a_batch_thread() {
        let (_worker, tid) = running_worker();
        #[cfg(target_os = "linux")]
        // SAFETY: sched_getscheduler and getpriority read a thread's settings, nothing of ours.
        unsafe {
            assert!(tid > 0, "the worker's id is known once it runs");
            assert_eq!(libc::sched_getscheduler(tid), libc::SCHED_BATCH);
            let mine = libc::getpriority(libc::PRIO_PROCESS, 0);
            assert_eq!(
                libc::getpriority(libc::PRIO_PROCESS, tid as libc::id_t),
                mine
            );
        }
        #[cfg(not(target_os = "linux"))]
        let _ = tid;
    }

    /// An owner that collects while the builder has changes queued takes the state over after
    /// the change the builder is applying, and applies the rest itself (the builder does not
    /// go on through its queue while the owner waits).
    #[test]
    fn a_waiting_owner_takes_over_after_the_current_change() {
        use std::sync::atomic::{AtomicBool, Ordering};
        static RELEASE: AtomicBool = AtomicBool::new(false);
        static ON_BUILDER: Mutex<Vec<u32>> = Mutex::new(Vec::new());
        fn apply(s: &mut Vec<u32>, c: u32) -> Option<()> {
            if std::thread::current().name() == Some("slow") {
                ON_BUILDER.lock().ok()?.push(c);
                // Change 1 holds the builder until the owner is waiting for the state.
                while c == 1 && !RELEASE.load(Ordering::Acquire) {
                    std::thread::yield_now();
                }
            }
            s.push(c);
            Some(())
        }
        let mut worker = Worker::default();
        let r = Beside::start(&mut worker, "slow", || Some(vec![0u32]), apply, |s| s)
            .expect("a worker thread");
        for c in 1..=50 {
            assert!(r.send(c));
        }
        while !ON_BUILDER.lock().is_ok_and(|on| on.contains(&1)) {
            std::thread::yield_now();
        }
        let link = Arc::clone(&r.link);
        let releaser = std::thread::spawn(move || {
            // (Released after a minute regardless, so that a regression fails, not hangs.)
            let start = std::time::Instant::now();
            while !lock(&link.0).is_some_and(|g| g.wanted) && start.elapsed().as_secs() < 60 {
                std::thread::yield_now();
            }
            RELEASE.store(true, Ordering::Release);
        });
        let mut waits = 0;
        assert_eq!(r.collect(&mut waits), Some((0..=50).collect::<Vec<_>>()));
        releaser.join().expect("the releaser ends");
        assert_eq!(*ON_BUILDER.lock().expect("not poisoned"), [1]);
        assert_eq!(waits, 1);
    }

    /// The state built from the snapshot, with every change applied in order whoever applied
    /// it; a failed change fails the renewal; a dropped renewal frees its worker.
    #[test]
    fn the_owner_takes_over_between_changes() {
        let mut worker = Worker::default();
        let push = |s: &mut Vec<u32>, c: u32| (c != 999).then(|| s.push(c));
        let r = Beside::start(&mut worker, "t", || Some(vec![0u32]), push, |s| s)
            .expect("a worker thread");
        for c in 1..=200 {
            assert!(r.send(c));
        }
        let mut waits = 0;
        assert_eq!(r.collect(&mut waits), Some((0..=200).collect::<Vec<_>>()));
        // A change that fails fails the renewal.
        let r =
            Beside::start(&mut worker, "t", || Some(vec![]), push, |s| s).expect("a worker thread");
        assert!(r.send(999));
        assert!(r.collect(&mut waits).is_none());
        // A failed build.
        let r = Beside::start(&mut worker, "t", || None, push, |s| s).expect("worker");
        assert!(r.collect(&mut waits).is_none());
        // Dropped: the worker goes on to the next job.
        let r = Beside::start(&mut worker, "t", || Some(vec![]), push, |s| s).expect("w");
        drop(r);
        let r = Beside::start(&mut worker, "t", || Some(vec![7]), push, |s| s).expect("w");
        assert!(r.send(8));
        assert!(r.collect(&mut waits) == Some(vec![7, 8]));
        // A builder that panics (here on its first change, on the worker thread, which ends
        // with it) fails the renewal instead of leaving the owner waiting. (Should the owner
        // take the state first and apply the change itself, the change fails there.)
        let boom = |_: &mut Vec<u32>, _: u32| -> Option<()> {
            if std::thread::current().name() == Some("t") {
                panic!("a builder's bug");
            }
            None
        };
        let r = Beside::start(&mut worker, "t", || Some(vec![]), boom, |s| s).expect("w");
        assert!(r.send(1));
        assert!(r.collect(&mut waits).is_none());
        // A builder that panics while building (the worker thread ends with it).
        let r = Beside::start(&mut worker, "t", || panic!("a build's bug"), push, |s| s);
        assert!(r.is_none_or(|r| r.collect(&mut waits).is_none()));
        // A job queued on a worker whose thread is gone never runs: also a failed renewal.
        let r = Beside::start(&mut worker, "t", || Some(vec![]), push, |s| s);
        assert!(r.is_none_or(|r| r.collect(&mut waits).is_none()));
    }
}
