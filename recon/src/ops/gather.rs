//! One operator shared by several solver threads, whose products are served together.
//!
//! `auto` runs its candidate models' paths side by side, and every candidate's solver asks for
//! `A x` and `A^T r` on every iteration. [`Gather::run`] runs the candidates on threads of their
//! own; while they run, a product asked of the [`Gather`] waits for the other candidates' next
//! requests, and the requests pending are served together by one batched product
//! ([`LinearOperator::apply_batch`], [`LinearOperator::adjoint_batch`]): for packed 0/1 patterns
//! one pass over the bits serves up to four vectors, at about half the cost per vector of
//! single products (`ops::bench`, `bench_bits_kernel`). The work between products (proximal
//! steps, transforms) runs on the candidates' threads in parallel meanwhile.
//!
//! A serve answers the requests of one kind (forward or adjoint), the oldest request's; the
//! others wait for the next serve, where the served members' next requests (of the other kind:
//! a solver alternates them) meet them. Members that fall out of step (a backtracking step adds
//! one forward product) so come back into step instead of costing two passes a serve for good.
//! Measured on the 128x128 Bernoulli photo's `auto` race (1,121 requests): 645-691 passes over
//! the bits against 882-930 serving both kinds (568 in lockstep), with the same wall and CPU
//! time within this VM's noise: there the candidates' own steps, not the products, set the pace.
//!
//! A request waits until every candidate still running is waiting for a product, or at most as
//! long as one product takes ([`State::patience`]): waiting for a partner then costs at most
//! what serving it would cost again. Without the bound, a candidate whose steps are slow for
//! other reasons (the DCT's non-negative proximal map on 256x256 Hadamard rows, ~100 ms an
//! iteration, against 0.3 ms a product) held every other candidate to its pace: there `auto`
//! took 16.4 s in lockstep against 12.4 s sequentially (measured before the early elimination
//! that now drops the DCT there). "One product" is the fastest time per request served so far:
//! taking the last one instead, a product slowed by the other threads' work on the 2 cores
//! raised the patience, which made the next waits longer, and one run of that case took 40 s.

//! The answers are the products the operator gives one vector at a time, bit for bit
//! ([`BitMatrix`](super::BitMatrix) and the other batched operators do the same arithmetic per
//! vector in a batch; tested), so a solver's result does not depend on which other requests its
//! own were served with: `auto` stays deterministic.
//!
//! Outside [`Gather::run`] a product is passed straight to the inner operator, and so is every
//! product when batching does not pay for it ([`LinearOperator::batching_pays`]): the packed-bit
//! products with the AVX-512 kernel take one pass per vector (at less than half the cost of the
//! portable kernel's batches of four per vector), so waiting for a partner would only cost.
//! Measured on the 128x128 Bernoulli photo's `auto`, 8 interleaved runs: 0.76 s median with
//! products straight through against 0.87 s gathered.

use std::collections::HashMap;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use crate::linop::LinearOperator;

pub struct Gather<'a> {
    inner: &'a dyn LinearOperator,
    /// Whether requests wait for each other at all ([`LinearOperator::batching_pays`]).
    gathers: bool,
    state: Mutex<State>,
    changed: Condvar,
}

struct Request {
    ticket: u64,
    adjoint: bool,
    input: Vec<f64>,
}

#[derive(Default)]
struct State {
    /// Threads of the current [`Gather::run`] that have not finished.
    members: usize,
    /// Members blocked in a product (their request pending or being served).
    waiting: usize,
    /// A member is computing the pending requests.
    serving: bool,
    /// A product panicked; every waiting member panics too instead of waiting forever.
    failed: bool,
    pending: Vec<Request>,
    /// When the oldest pending request arrived.
    since: Option<Instant>,
    /// How long a pending request waits for the others at most.
    patience: Duration,
    /// `patience` is the fastest time per request of a batch served so far (zero until one
    /// was). The fastest, not the last: contention only ever slows a product down.
    adaptive: bool,
    done: HashMap<u64, Vec<f64>>,
    next_ticket: u64,
    /// Batched products served, and the requests they served (for the report and tests).
    batches: usize,
    requests: usize,
}

/// How a [`Gather`] served its requests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GatherStats {
    pub batches: usize,
    pub requests: usize,
}

impl<'a> Gather<'a> {
    /// Requests wait for each other at most one product's time (see the module docs); not at
    /// all, products going straight through, when batching does not pay for `inner`
    /// ([`LinearOperator::batching_pays`]).
    pub fn new(inner: &'a dyn LinearOperator) -> Self {
        Gather {
            inner,
            gathers: inner.batching_pays(),
            state: Mutex::new(State {
                adaptive: true,
                ..State::default()
            }),
            changed: Condvar::new(),
        }
    }

    /// Requests wait for each other at most `patience` (`Duration::MAX`: until every member
    /// waits, lockstep).
    pub fn with_patience(inner: &'a dyn LinearOperator, patience: Duration) -> Self {
        Gather {
            inner,
            gathers: true,
            state: Mutex::new(State {
                patience,
                ..State::default()
            }),
            changed: Condvar::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Runs every job on a thread of its own, each a member of this gather until it returns;
    /// the results come back in the jobs' order. A job's panic is resumed here once all jobs
    /// have ended.
    pub fn run<'s, R: Send>(&self, jobs: Vec<Box<dyn FnOnce() -> R + Send + 's>>) -> Vec<R> {
        if jobs.len() <= 1 {
            // Nothing to gather with: run on this thread, products go straight through.
            return jobs.into_iter().map(|job| job()).collect();
        }
        self.lock().members = jobs.len();
        std::thread::scope(|scope| {
            let handles: Vec<_> = jobs
                .into_iter()
                .map(|job| {
                    scope.spawn(move || {
                        // Leaves on return and on unwinding alike.
                        let _member = Member(self);
                        job()
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
                })
                .collect()
        })
    }

    /// How long a request currently waits for the others at most.
    pub fn patience(&self) -> Duration {
        self.lock().patience
    }

    pub fn stats(&self) -> GatherStats {
        let s = self.lock();
        GatherStats {
            batches: s.batches,
            requests: s.requests,
        }
    }

    fn leave(&self) {
        let mut s = self.lock();
        s.members -= 1;
        drop(s);
        // The members left may all be waiting now: one of them serves.
        self.changed.notify_all();
    }

    fn product(&self, adjoint: bool, input: &[f64], out: &mut [f64]) {
        let s = self.gathers.then(|| self.lock());
        let Some(mut s) = s.filter(|s| s.members > 0) else {
            if adjoint {
                self.inner.adjoint(input, out)
            } else {
                self.inner.apply(input, out)
            }
            return;
        };
        let ticket = s.next_ticket;
        s.next_ticket += 1;
        s.pending.push(Request {
            ticket,
            adjoint,
            input: input.to_vec(),
        });
        s.since.get_or_insert_with(Instant::now);
        s.waiting += 1;
        loop {
            if let Some(result) = s.done.remove(&ticket) {
                out.copy_from_slice(&result);
                return;
            }
            assert!(!s.failed, "a batched product panicked on another thread");
            if !s.serving && !s.pending.is_empty() {
                let waited = s.since.map_or(Duration::ZERO, |t| t.elapsed());
                if s.waiting == s.members || waited >= s.patience {
                    s = self.serve(s);
                    continue;
                }
                let left = s.patience - waited;
                s = if left > Duration::from_secs(3600) {
                    self.changed.wait(s).unwrap_or_else(|e| e.into_inner())
                } else {
                    self.changed
                        .wait_timeout(s, left)
                        .unwrap_or_else(|e| e.into_inner())
                        .0
                };
                continue;
            }
            s = self.changed.wait(s).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Computes every pending request (the lock released meanwhile), stores the results and
    /// wakes the members.
    fn serve<'g>(&'g self, mut s: MutexGuard<'g, State>) -> MutexGuard<'g, State> {
        // One kind per turn, the oldest request's: the others stay pending and meet the served
        // members' next requests, which are of their kind (a solver alternates `A^T r` and
        // `A z`). Serving both kinds at once kept members that had fallen out of step (one
        // backtracking step is enough) out of step for good, each turn two passes over the
        // bits with no vector shared.
        let kind = s.pending[0].adjoint;
        let (requests, rest): (Vec<Request>, Vec<Request>) = std::mem::take(&mut s.pending)
            .into_iter()
            .partition(|r| r.adjoint == kind);
        s.pending = rest;
        s.since = None;
        s.serving = true;
        drop(s);
        let start = Instant::now();
        let results =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.compute(&requests)));
        let mut s = self.lock();
        s.serving = false;
        match results {
            Ok(results) => {
                if s.adaptive {
                    let per_request = start.elapsed() / results.len().max(1) as u32;
                    s.patience = if s.batches == 0 {
                        per_request
                    } else {
                        s.patience.min(per_request)
                    };
                }
                s.batches += usize::from(requests.iter().any(|r| r.adjoint))
                    + usize::from(requests.iter().any(|r| !r.adjoint));
                s.requests += requests.len();
                s.waiting -= results.len();
                // Requests left pending (or that came meanwhile) wait from now: the served members
                // need their step's time to come back with requests of the same kind.
                if !s.pending.is_empty() {
                    s.since = Some(Instant::now());
                }
                s.done.extend(results);
                self.changed.notify_all();
                s
            }
            Err(panic) => {
                s.failed = true;
                drop(s);
                self.changed.notify_all();
                std::panic::resume_unwind(panic)
            }
        }
    }

    fn compute(&self, requests: &[Request]) -> Vec<(u64, Vec<f64>)> {
        let (m, k) = (self.inner.rows(), self.inner.cols());
        let mut results = Vec::with_capacity(requests.len());
        for adjoint in [false, true] {
            let group: Vec<&Request> = requests.iter().filter(|r| r.adjoint == adjoint).collect();
            if group.is_empty() {
                continue;
            }
            let (from, to) = if adjoint { (m, k) } else { (k, m) };
            let mut xs = Vec::with_capacity(from * group.len());
            for r in &group {
                xs.extend_from_slice(&r.input);
            }
            let mut ys = vec![0.0; to * group.len()];
            if adjoint {
                self.inner.adjoint_batch(&xs, &mut ys, group.len());
            } else {
                self.inner.apply_batch(&xs, &mut ys, group.len());
            }
            results.extend(
                group
                    .iter()
                    .zip(ys.chunks_exact(to))
                    .map(|(r, y)| (r.ticket, y.to_vec())),
            );
        }
        results
    }
}

struct Member<'g, 'a>(&'g Gather<'a>);

impl Drop for Member<'_, '_> {
    fn drop(&mut self) {
        self.0.leave();
    }
}

impl LinearOperator for Gather<'_> {
    fn rows(&self) -> usize {
        self.inner.rows()
    }
    fn cols(&self) -> usize {
        self.inner.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(x.len(), self.cols());
        assert_eq!(y.len(), self.rows());
        self.product(false, x, y);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        assert_eq!(y.len(), self.rows());
        assert_eq!(x.len(), self.cols());
        self.product(true, y, x);
    }
    fn batching_pays(&self) -> bool {
        self.inner.batching_pays()
    }
}

#[cfg(test)]
mod tests {
    use helmholtz_proto::{Family, HadamardOrdering, PatternSpec};

    use super::*;
    use crate::linop::{adjoint_mismatch, test_vector};
    use crate::ops::{BernoulliOperator, measurement_operator};

    fn bernoulli(rows: u64, side: u32) -> BernoulliOperator {
        let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, side, side, rows, 3).unwrap();
        BernoulliOperator::from_spec(&spec, rows).unwrap()
    }

    #[test]
    fn batched_products_equal_single_ones_bit_for_bit() {
        // Every family, Bernoulli at sizes below, across and above the bit kernel's threading
        // threshold (rows x words = 148, 6,400 and 44,800 against 8,192).
        let hadamard = |side: u32, frames: u64| {
            PatternSpec::new(
                Family::Hadamard {
                    ordering: HadamardOrdering::RussianDoll,
                },
                side,
                side,
                frames,
                0,
            )
            .unwrap()
        };
        let bern = |side: u32, rows: u64| {
            PatternSpec::new(Family::Bernoulli { fill: 0.5 }, side, side, rows, 3).unwrap()
        };
        let speckle = PatternSpec::new(Family::Speckle { grain: 2 }, 24, 24, 90, 5).unwrap();
        let raster =
            PatternSpec::new(Family::Raster { block: 1, scans: 1 }, 12, 12, 100, 0).unwrap();
        let cases = [
            (bern(16, 37), 37),
            (bern(64, 100), 100),
            (bern(64, 700), 700),
            (hadamard(32, 600), 600),
            (speckle, 90),
            (raster, 100),
        ];
        for (spec, rows) in cases {
            let op = measurement_operator(&spec, rows);
            let (m, k) = (op.rows(), op.cols());
            for batch in 1..=5 {
                let xs = test_vector(k * batch, 11 + batch as u64);
                let mut ys = vec![0.0; m * batch];
                op.apply_batch(&xs, &mut ys, batch);
                let rs = test_vector(m * batch, 23 + batch as u64);
                let mut zs = vec![0.0; k * batch];
                op.adjoint_batch(&rs, &mut zs, batch);
                for l in 0..batch {
                    let mut y = vec![0.0; m];
                    op.apply(&xs[l * k..(l + 1) * k], &mut y);
                    assert!(
                        y == ys[l * m..(l + 1) * m],
                        "{:?} {m}x{k}, batch {batch}, vector {l}: apply",
                        spec.family()
                    );
                    let mut z = vec![0.0; k];
                    op.adjoint(&rs[l * m..(l + 1) * m], &mut z);
                    assert!(
                        z == zs[l * k..(l + 1) * k],
                        "{:?} {m}x{k}, batch {batch}, vector {l}: adjoint",
                        spec.family()
                    );
                }
            }
        }
    }

    /// One product a member asked for: (adjoint?, input, answer).
    type Asked = (bool, Vec<f64>, Vec<f64>);

    /// Three members with different numbers of products, mixing forward and adjoint; the third
    /// leaves early. Returns every member's products and the stats.
    fn three_members(
        gather: &Gather,
        m: usize,
        k: usize,
        counts: [usize; 3],
    ) -> (Vec<Vec<Asked>>, GatherStats) {
        let jobs: Vec<Box<dyn FnOnce() -> Vec<Asked> + Send + '_>> = counts
            .iter()
            .enumerate()
            .map(|(j, &count)| {
                Box::new(move || {
                    (0..count)
                        .map(|i| {
                            let seed = (j * 1000 + i) as u64;
                            let adjoint = i % 3 == 2;
                            let (input, mut out) = if adjoint {
                                (test_vector(m, seed), vec![0.0; k])
                            } else {
                                (test_vector(k, seed), vec![0.0; m])
                            };
                            if adjoint {
                                gather.adjoint(&input, &mut out)
                            } else {
                                gather.apply(&input, &mut out)
                            }
                            (adjoint, input, out)
                        })
                        .collect()
                })
                    as Box<dyn FnOnce() -> Vec<(bool, Vec<f64>, Vec<f64>)> + Send + '_>
            })
            .collect();
        let answers = gather.run(jobs);
        (answers, gather.stats())
    }

    #[test]
    fn members_get_their_own_products_served_in_batches() {
        let op = bernoulli(300, 32);
        let (m, k) = (op.rows(), op.cols());
        for gather in [Gather::new(&op), Gather::with_patience(&op, Duration::MAX)] {
            assert!(
                adjoint_mismatch(&gather, 5) < 1e-12,
                "outside run: the inner operator's products"
            );
            let counts = [40usize, 25, 3];
            let (answers, stats) = three_members(&gather, m, k, counts);
            for (j, member) in answers.iter().enumerate() {
                assert_eq!(member.len(), counts[j]);
                for (i, (adjoint, input, got)) in member.iter().enumerate() {
                    let mut want = vec![0.0; got.len()];
                    if *adjoint {
                        op.adjoint(input, &mut want)
                    } else {
                        op.apply(input, &mut want)
                    }
                    assert!(*got == want, "member {j}, product {i}");
                }
            }
            // Gathered, or straight through where batching does not pay for this operator.
            let gathered = counts.iter().sum::<usize>();
            assert_eq!(stats.requests, if gather.gathers { gathered } else { 0 });
            // After run, products go straight through again.
            assert!(adjoint_mismatch(&gather, 6) < 1e-12);
        }
        // Lockstep: a serve waits for every member still running, so while three run, every
        // serve answers all three (in one forward and one adjoint batch at most), then two.
        let gather = Gather::with_patience(&op, Duration::MAX);
        let (_, stats) = three_members(&gather, m, k, [40, 25, 3]);
        // Serve i answers every running member's product i, all of one kind: one batch each,
        // 40 in all for 68 requests (3 serves of 3, 22 of 2, 15 of 1).
        assert_eq!(
            stats,
            GatherStats {
                batches: 40,
                requests: 68
            }
        );
    }

    #[test]
    fn members_out_of_step_are_brought_back_into_step() {
        // Member 0 starts with an extra forward product (as after a backtracking step), then
        // both alternate adjoint and forward products: one kind behind the other.
        let op = bernoulli(300, 32);
        let (m, k) = (op.rows(), op.cols());
        let gather = Gather::with_patience(&op, Duration::MAX);
        let jobs: Vec<Box<dyn FnOnce() + Send + '_>> = [true, false]
            .into_iter()
            .map(|forward_first| {
                let gather = &gather;
                Box::new(move || {
                    let count = if forward_first { 21 } else { 20 };
                    for i in 0..count {
                        if (i % 2 == 0) == forward_first {
                            gather.apply(&test_vector(k, i as u64), &mut vec![0.0; m]);
                        } else {
                            gather.adjoint(&test_vector(m, i as u64), &mut vec![0.0; k]);
                        }
                    }
                }) as Box<dyn FnOnce() + Send + '_>
            })
            .collect();
        gather.run(jobs);
        let stats = gather.stats();
        assert_eq!(stats.requests, 41);
        // The first serve answers the oldest request's kind only; the other member's request
        // then meets the served member's next one, of its kind. 21 or 22 serves (by which
        // request came first), each one batch; serving both kinds every turn took 41 batches.
        assert!(stats.batches <= 22, "{stats:?}");
    }

    #[test]
    fn a_slow_member_holds_the_others_back_at_most_its_patience() {
        // Member 0 sleeps 400 ms before its second product; member 1 asks for 20 products
        // meanwhile. With a 2 ms patience it is done long before member 0 wakes; in lockstep it
        // would wait for member 0 at every product.
        let op = bernoulli(100, 16);
        let gather = Gather::with_patience(&op, Duration::from_millis(2));
        let start = Instant::now();
        let jobs: Vec<Box<dyn FnOnce() -> Duration + Send + '_>> = vec![
            Box::new(|| {
                let mut y = vec![0.0; 100];
                gather.apply(&vec![1.0; 256], &mut y);
                std::thread::sleep(Duration::from_millis(400));
                gather.apply(&vec![1.0; 256], &mut y);
                start.elapsed()
            }),
            Box::new(|| {
                let mut y = vec![0.0; 100];
                for _ in 0..20 {
                    gather.apply(&vec![2.0; 256], &mut y);
                }
                start.elapsed()
            }),
        ];
        let done = gather.run(jobs);
        assert!(
            done[1] < Duration::from_millis(200),
            "the fast member took {:?}",
            done[1]
        );
        assert!(done[0] >= Duration::from_millis(400));
    }

    /// Products that take at least `delay_ms` (a stand-in for a product slowed by contention).
    struct Slow {
        inner: BernoulliOperator,
        delay_ms: std::sync::atomic::AtomicU64,
    }

    impl LinearOperator for Slow {
        fn rows(&self) -> usize {
            self.inner.rows()
        }
        fn cols(&self) -> usize {
            self.inner.cols()
        }
        fn apply(&self, x: &[f64], y: &mut [f64]) {
            std::thread::sleep(Duration::from_millis(
                self.delay_ms.load(std::sync::atomic::Ordering::Relaxed),
            ));
            self.inner.apply(x, y)
        }
        fn adjoint(&self, y: &[f64], x: &mut [f64]) {
            self.inner.adjoint(y, x)
        }
        fn batching_pays(&self) -> bool {
            true
        }
    }

    #[test]
    fn patience_is_the_fastest_product_seen_not_the_last() {
        let op = Slow {
            inner: bernoulli(20, 4),
            delay_ms: 2.into(),
        };
        let gather = Gather::new(&op);
        let jobs: Vec<Box<dyn FnOnce() + Send + '_>> = vec![
            Box::new(|| {
                let mut y = vec![0.0; 20];
                gather.apply(&[1.0; 16], &mut y);
                op.delay_ms.store(60, std::sync::atomic::Ordering::Relaxed);
                gather.apply(&[1.0; 16], &mut y);
            }),
            Box::new(|| {}),
        ];
        gather.run(jobs);
        let p = gather.patience();
        assert!(
            p >= Duration::from_millis(2) && p < Duration::from_millis(60),
            "patience {p:?}"
        );
    }

    #[test]
    fn a_panicking_member_does_not_leave_the_others_waiting() {
        let op = bernoulli(50, 8);
        let gather = Gather::new(&op);
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let jobs: Vec<Box<dyn FnOnce() + Send + '_>> = vec![
                Box::new(|| {
                    let mut y = vec![0.0; 50];
                    for _ in 0..20 {
                        gather.apply(&vec![1.0; 64], &mut y);
                    }
                }),
                Box::new(|| panic!("member failed")),
            ];
            gather.run(jobs)
        }));
        assert!(result.is_err(), "the member's panic reaches the caller");
    }
}
