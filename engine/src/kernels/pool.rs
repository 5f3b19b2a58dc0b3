//! A fixed team of worker threads for the kernels' parallel regions.
//!
//! One generation has about a hundred parallel regions per Euler step (every GEMM, every
//! attention block), each a millisecond or less, with a few microseconds of serial work between
//! them. What matters is how fast an idle thread notices the next region and how fast the caller
//! notices the end of one:
//! - idle workers and the waiting caller first spin (with `spin_loop` hints, never yielding the
//!   core) for up to [`SPIN`], which covers the gaps between regions, and only then block on a
//!   condition variable;
//! - they never call `sched_yield`. On a machine shared with other jobs a yield hands the core to
//!   another process for a whole time slice; work-stealing pools that yield while idle (rayon's
//!   default) then take many times their CPU time in wall time.
//!
//! Parts are claimed one at a time under a mutex, so a thread that gets less CPU simply claims
//! fewer parts. Which thread runs a part never changes its result.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How long an idle thread spins before it blocks.
pub const SPIN: Duration = Duration::from_micros(100);

/// The current region's work, type-erased; valid while its `run` call has not returned.
#[derive(Clone, Copy)]
struct JobRef {
    data: *const (),
    call: unsafe fn(*const (), usize),
}

// SAFETY: the pointee is a `Fn(usize) + Sync` closure that `run` keeps alive (and borrowed) until
// every claimed part has finished; only `call` dereferences it.
unsafe impl Send for JobRef {}

struct State {
    epoch: u64,
    job: Option<JobRef>,
    next: usize,
    parts: usize,
    shutdown: bool,
}

struct Shared {
    state: Mutex<State>,
    work: Condvar,
    done: Condvar,
    /// Mirror of `State::epoch` for spinning without the lock.
    epoch: AtomicU64,
    /// Parts of the current region not finished yet.
    remaining: AtomicUsize,
    /// The payload of a part that panicked in the current region, re-raised by `run`.
    panic: Mutex<Option<Box<dyn std::any::Any + Send>>>,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        match self.state.lock() {
            Ok(g) => g,
            Err(poisoned) => poisoned.into_inner(),
        }
    }

    /// Claim and run parts of region `epoch` until none are left.
    fn work_on(&self, epoch: u64) {
        loop {
            let (job, part) = {
                let mut st = self.lock();
                if st.epoch != epoch || st.next >= st.parts {
                    return;
                }
                let part = st.next;
                st.next += 1;
                match st.job {
                    Some(job) => (job, part),
                    None => return,
                }
            };
            let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                // SAFETY: the part was claimed in the region whose `run` call is still waiting
                // for `remaining` to reach zero, so the closure `job.data` points to is alive,
                // and `job.call` is the `call` that `run` paired with it.
                unsafe { (job.call)(job.data, part) }
            }));
            if let (Err(payload), Ok(mut slot)) = (result, self.panic.lock()) {
                slot.get_or_insert(payload);
            }
            if self.remaining.fetch_sub(1, Ordering::AcqRel) == 1 {
                let _guard = self.lock();
                self.done.notify_all();
            }
        }
    }
}

/// Worker threads plus the calling thread.
pub struct Team {
    shared: Arc<Shared>,
    workers: Vec<JoinHandle<()>>,
    /// Serialises regions from concurrent callers.
    region: Mutex<()>,
}

thread_local! {
    static IN_REGION: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

impl Team {
    /// `threads - 1` workers; the caller of [`Team::run`] is the last thread.
    pub fn new(threads: usize, name: &str) -> std::io::Result<Team> {
        let shared = Arc::new(Shared {
            state: Mutex::new(State {
                epoch: 0,
                job: None,
                next: 0,
                parts: 0,
                shutdown: false,
            }),
            work: Condvar::new(),
            done: Condvar::new(),
            epoch: AtomicU64::new(0),
            remaining: AtomicUsize::new(0),
            panic: Mutex::new(None),
        });
        let workers = (1..threads.max(1))
            .map(|i| {
                let shared = Arc::clone(&shared);
                std::thread::Builder::new()
                    .name(format!("{name}-{i}"))
                    .spawn(move || worker(&shared))
            })
            .collect::<std::io::Result<Vec<_>>>()?;
        Ok(Team {
            shared,
            workers,
            region: Mutex::new(()),
        })
    }

    /// Run `f(part)` for every `part in 0..parts` on the team (the caller included) and return
    /// when all are done. Called from inside a part, it runs the parts inline.
    pub fn run(&self, parts: usize, f: &(dyn Fn(usize) + Sync)) {
        if parts == 0 {
            return;
        }
        if self.workers.is_empty() || parts == 1 || IN_REGION.with(|r| r.get()) {
            for p in 0..parts {
                f(p);
            }
            return;
        }
        let _region = match self.region.lock() {
            Ok(g) => g,
            Err(poisoned) => poisoned.into_inner(),
        };
        /// Runs part `part` of the region's closure.
        ///
        /// # Safety
        /// `data` must be the `&&(dyn Fn(usize) + Sync)` that `run` stored beside this function
        /// in the region's [`JobRef`], and that region's `run` call must not have returned (it
        /// waits for every claimed part, so the closure is alive while a part runs).
        unsafe fn call(data: *const (), part: usize) {
            // SAFETY: `data` is the `&&dyn Fn` below, alive for the whole region.
            let f = unsafe { &*(data as *const &(dyn Fn(usize) + Sync)) };
            struct Reset;
            impl Drop for Reset {
                fn drop(&mut self) {
                    IN_REGION.with(|r| r.set(false));
                }
            }
            IN_REGION.with(|r| r.set(true));
            let _reset = Reset;
            f(part);
        }
        let data = &f as *const &(dyn Fn(usize) + Sync) as *const ();
        let epoch = {
            let mut st = self.shared.lock();
            st.epoch += 1;
            st.job = Some(JobRef { data, call });
            st.next = 0;
            st.parts = parts;
            self.shared.remaining.store(parts, Ordering::Release);
            self.shared.epoch.store(st.epoch, Ordering::Release);
            st.epoch
        };
        self.shared.work.notify_all();
        self.shared.work_on(epoch);
        // Wait for parts other threads claimed: spin, then block.
        let start = Instant::now();
        while self.shared.remaining.load(Ordering::Acquire) != 0 {
            if start.elapsed() > SPIN {
                let mut st = self.shared.lock();
                while self.shared.remaining.load(Ordering::Acquire) != 0 {
                    st = match self.shared.done.wait(st) {
                        Ok(g) => g,
                        Err(poisoned) => poisoned.into_inner(),
                    };
                }
                break;
            }
            std::hint::spin_loop();
        }
        self.shared.lock().job = None;
        let payload = self
            .shared
            .panic
            .lock()
            .ok()
            .and_then(|mut slot| slot.take());
        if let Some(payload) = payload {
            std::panic::resume_unwind(payload);
        }
    }
}

impl Drop for Team {
    fn drop(&mut self) {
        self.shared.lock().shutdown = true;
        self.shared.work.notify_all();
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}

fn worker(shared: &Shared) {
    let mut seen = 0u64;
    loop {
        // Spin for the next region, then block.
        let start = Instant::now();
        while shared.epoch.load(Ordering::Acquire) == seen && start.elapsed() < SPIN {
            std::hint::spin_loop();
        }
        let epoch = {
            let mut st = shared.lock();
            while st.epoch == seen && !st.shutdown {
                st = match shared.work.wait(st) {
                    Ok(g) => g,
                    Err(poisoned) => poisoned.into_inner(),
                };
            }
            if st.shutdown {
                return;
            }
            st.epoch
        };
        seen = epoch;
        shared.work_on(epoch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;

    #[test]
    fn every_part_runs_exactly_once() {
        let team = Team::new(3, "t").unwrap();
        for parts in [1, 2, 7, 64] {
            for _ in 0..200 {
                let hits: Vec<AtomicUsize> = (0..parts).map(|_| AtomicUsize::new(0)).collect();
                team.run(parts, &|p| {
                    hits[p].fetch_add(1, Ordering::Relaxed);
                });
                assert!(hits.iter().all(|h| h.load(Ordering::Relaxed) == 1));
            }
        }
    }

    #[test]
    fn a_panicking_part_reaches_the_caller_and_the_team_survives() {
        let team = Team::new(2, "t").unwrap();
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            team.run(8, &|p| assert!(p != 5, "part five"));
        }));
        assert!(caught.is_err());
        let count = AtomicUsize::new(0);
        team.run(8, &|_| {
            count.fetch_add(1, Ordering::Relaxed);
        });
        assert_eq!(count.load(Ordering::Relaxed), 8);
    }

    #[test]
    fn nested_regions_run_inline_and_concurrent_callers_serialise() {
        let team = Arc::new(Team::new(2, "t").unwrap());
        let total = Arc::new(AtomicUsize::new(0));
        let callers: Vec<_> = (0..3)
            .map(|_| {
                let (team, total) = (Arc::clone(&team), Arc::clone(&total));
                std::thread::spawn(move || {
                    for _ in 0..100 {
                        team.run(4, &|_| {
                            team.run(3, &|_| {
                                total.fetch_add(1, Ordering::Relaxed);
                            });
                        });
                    }
                })
            })
            .collect();
        for c in callers {
            c.join().unwrap();
        }
        assert_eq!(total.load(Ordering::Relaxed), 3 * 100 * 4 * 3);
    }
}
