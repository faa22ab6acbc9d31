//! Ingest on several cores: [`Workers`], an integrator per thread whose threads outlive a batch,
//! and [`integrate_parallel`], which spreads a batch of scans over them.
//!
//! Starting threads per batch and joining them after it cost about 5% of a pass over the
//! sample scans, on a machine where an idle vCPU is slow to wake; threads that wait for the
//! next batch cost a message instead.
//!
//! This module's one `unsafe`: a batch's jobs borrow the caller's
//! scans and closure, which a thread that outlives the call cannot name, so their lifetime is
//! erased when they are handed over (`Batch::start`) and every job is waited for before the
//! borrowed data can go (`Batch`'s `Drop`, which runs on unwinding as well).
#![allow(unsafe_code)]

use super::integrator::Integrator;
use super::sink::{BlockSink, add_whole};
use crate::core::block::BlockEvidence;
use crate::core::key::BlockKey;
use crate::core::map::EvidenceMap;
use crate::core::params::MapParams;
use std::any::Any;
use std::marker::PhantomData;
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, Sender, TryRecvError};

/// The integrators of [`integrate_parallel`]: the first works on the calling thread, each other
/// on a thread of its own, started with the pool and ended when it is dropped.
#[derive(Debug)]
pub struct Workers {
    first: Integrator,
    helpers: Vec<Helper>,
    /// Per helper, the blocks of its last map whose evidence was added into the sink's: freed
    /// by that helper at the start of the next batch, while the calling thread integrates,
    /// rather than by the calling thread after the last scan, where the pass waits for it.
    /// They hold memory until then (the sample scans: ~400 blocks of 4 KiB).
    ///
    /// Freeing them in the jobs that add the shares instead is slower: both threads then free
    /// into the helper's heap at once.
    spent: Vec<Vec<Arc<BlockEvidence>>>,
}

/// A job for a helper thread, run with the thread's integrator.
type Job = Box<dyn FnOnce(&mut Integrator) + Send + 'static>;
/// What a helper reports after each job: the panic it raised, if it did.
type Outcome = Option<Box<dyn Any + Send>>;

#[derive(Debug)]
struct Helper {
    /// `None` once the pool is being dropped (the thread then ends).
    jobs: Option<Sender<Job>>,
    done: Receiver<Outcome>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Workers {
    /// `threads` integrators for maps of `params` (at least one); every one beyond the first
    /// starts a thread.
    pub fn new(params: MapParams, threads: usize) -> Self {
        let helpers: Vec<_> = (1..threads.max(1)).map(|i| Helper::start(params, i)).collect();
        let spent = helpers.iter().map(|_| Vec::new()).collect();
        Self { first: Integrator::new(params), helpers, spent }
    }

    /// Integrators in the pool (threads, counting the caller's).
    pub fn threads(&self) -> usize {
        1 + self.helpers.len()
    }
}

impl Helper {
    fn start(params: MapParams, i: usize) -> Self {
        let (jobs, job_rx) = mpsc::channel::<Job>();
        let (done_tx, done) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name(format!("bgkmap-ingest-{i}"))
            .spawn(move || {
                let mut integ = Integrator::new(params);
                while let Some(job) = receive_soon(&job_rx) {
                    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| job(&mut integ)));
                    if outcome.is_err() {
                        // Its scratch may be half-written: start again from a clean one.
                        integ = Integrator::new(params);
                    }
                    if done_tx.send(outcome.err()).is_err() {
                        break;
                    }
                }
            })
            .expect("starting an ingest thread");
        Self { jobs: Some(jobs), done, thread: Some(thread) }
    }
}

impl Drop for Helper {
    fn drop(&mut self) {
        self.jobs = None;
        if let Some(t) = self.thread.take() {
            // A job's panic was caught and reported; the thread itself does not panic.
            let _ = t.join();
        }
    }
}

/// The next message, waited for by spinning a little first: within a batch the next job (or
/// the answer to one) comes microseconds after the last, and a thread that sleeps in the kernel
/// (on a VM, a vCPU that halts) can take longer to wake than the job takes to do.
fn receive_soon<T>(rx: &Receiver<T>) -> Option<T> {
    let until = std::time::Instant::now() + std::time::Duration::from_micros(200);
    loop {
        match rx.try_recv() {
            Ok(m) => return Some(m),
            Err(TryRecvError::Disconnected) => return None,
            Err(TryRecvError::Empty) if std::time::Instant::now() < until => std::hint::spin_loop(),
            Err(TryRecvError::Empty) => return rx.recv().ok(),
        }
    }
}

/// Jobs handed to the helpers during one call, which may borrow anything that lives for `'a`:
/// dropping the batch waits for all of them.
struct Batch<'h, 'a> {
    helpers: &'h [Helper],
    /// Jobs started and not yet reported done, per helper.
    running: Vec<usize>,
    /// The first panic a job reported.
    panic: Outcome,
    _borrows: PhantomData<&'a ()>,
}

impl<'h, 'a> Batch<'h, 'a> {
    fn new(helpers: &'h [Helper]) -> Self {
        Self { helpers, running: vec![0; helpers.len()], panic: None, _borrows: PhantomData }
    }

    /// Runs `job` on helper `h` (after the jobs it was given before).
    fn start(&mut self, h: usize, job: Box<dyn FnOnce(&mut Integrator) + Send + 'a>) {
        // SAFETY: only the lifetime changes (same fat-pointer layout). The job may borrow data
        // that lives for `'a`; the batch cannot outlive `'a`, is never leaked (it is a local of
        // `integrate_parallel`), and waits in `finish` or `Drop` — unwinding included — until
        // every started job has reported done, so no job runs after its borrows end.
        let job: Job =
            unsafe { std::mem::transmute::<Box<dyn FnOnce(&mut Integrator) + Send + 'a>, Job>(job) };
        let sent = self.helpers[h].jobs.as_ref().map(|jobs| jobs.send(job));
        match sent {
            Some(Ok(())) => self.running[h] += 1,
            // The thread has ended, which it does only when the pool is dropped, and the pool is
            // borrowed here; the job is dropped unrun, and its results never arrive.
            _ => unreachable!("an ingest thread ended while its pool was in use"),
        }
    }

    /// Waits for every started job; the first panic among them is passed on.
    fn finish(mut self) {
        self.wait_all();
        if let Some(p) = self.panic.take() {
            std::panic::resume_unwind(p);
        }
    }

    fn wait_all(&mut self) {
        for (h, running) in self.running.iter_mut().enumerate() {
            while *running > 0 {
                let outcome = receive_soon(&self.helpers[h].done).unwrap_or_else(|| {
                    Some(Box::new("an ingest thread ended in the middle of a job") as Box<dyn Any + Send>)
                });
                *running -= 1;
                self.panic = self.panic.take().or(outcome);
            }
        }
    }
}

impl Drop for Batch<'_, '_> {
    fn drop(&mut self) {
        self.wait_all();
    }
}

/// Integrates many scans into `sink` on every integrator of `workers`: each takes the next scan
/// not yet taken and `add`s it, the first (on the calling thread) straight into `sink`, every
/// other into a map of its own that goes into `sink` once all scans are done (so a helper pays
/// one block addition per block its scans touched, not one delta per scan). Evidence is
/// integer, so any split gives the same bits as adding the scans one after another. With one
/// integrator (or one scan) everything runs on the calling thread. The first error by scan
/// order is returned; the evidence of other scans may have gone into `sink` by then, so callers
/// add into an edit they can drop. A panic in `add` on any thread is passed on to the caller.
///
/// A helper's block that `sink` lacks is moved in; the blocks both hold are added on all the
/// threads at once (see `add_map_on_all_threads`).
pub fn integrate_parallel<S, K, E>(
    workers: &mut Workers,
    scans: &[S],
    sink: &mut K,
    add: impl Fn(&mut Integrator, &S, &mut dyn BlockSink) -> Result<(), E> + Sync,
) -> Result<(), E>
where
    S: Sync,
    K: BlockSink,
    E: Send,
{
    let Workers { first, helpers, spent } = workers;
    let n = (1 + helpers.len()).min(scans.len());
    if n <= 1 {
        return scans.iter().try_for_each(|s| add(first, s, sink));
    }
    let params = *first.params();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let run = |integ: &mut Integrator, sink: &mut dyn BlockSink| -> Result<(), (usize, E)> {
        loop {
            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let Some(s) = scans.get(i) else { return Ok(()) };
            add(integ, s, sink).map_err(|e| (i, e))?;
        }
    };
    let helpers = &helpers[..n - 1];
    let mut batch = Batch::new(helpers);
    let (map_tx, map_rx) = mpsc::channel();
    for h in 0..helpers.len() {
        let (run, map_tx, spent) = (&run, map_tx.clone(), std::mem::take(&mut spent[h]));
        batch.start(
            h,
            Box::new(move |integ: &mut Integrator| {
                drop(spent);
                let mut own = EvidenceMap::new(params);
                let done = run(integ, &mut own);
                let _ = map_tx.send((h, own, done));
            }),
        );
    }
    drop(map_tx);
    let mine = run(first, sink);
    // Every job drops its sender when it ends, so this ends too, even if one panicked.
    let mut theirs: Vec<_> = helpers.iter().map(|_| None).collect();
    for (h, map, done) in map_rx.iter() {
        theirs[h] = Some((map, done));
    }
    if theirs.iter().any(Option::is_none) {
        // A helper panicked before sending its map: `finish` passes the panic on.
        batch.finish();
        unreachable!("a helper sent no map and reported no panic");
    }
    let (maps, done): (Vec<EvidenceMap>, Vec<_>) = theirs.into_iter().flatten().unzip();
    if let Some((_, e)) = std::iter::once(mine).chain(done).filter_map(Result::err).min_by_key(|(i, _)| *i) {
        batch.finish();
        return Err(e);
    }
    for (map, spent) in maps.into_iter().zip(spent.iter_mut()) {
        add_map_on_all_threads(map, sink, &mut batch, spent);
    }
    batch.finish();
    Ok(())
}

/// A block of the map being added to (`.1`) and the same block of a helper's map (`.2`); after
/// [`add_block_pairs`], `.1` holds their sum.
type BlockPair = (BlockKey, Arc<BlockEvidence>, Arc<BlockEvidence>);

/// Adds each pair's blocks into `.1` ([`add_whole`]).
fn add_block_pairs(pairs: &mut [BlockPair]) {
    for (_, mine, theirs) in pairs.iter_mut() {
        add_whole(mine, theirs);
    }
}

/// Adds a helper's `map` into `sink`: blocks `sink` lacks are moved in, the others are added in
/// over go to `spent` (see [`Workers`]). On the sample scans about half of a helper's blocks
/// are the sink's too; adding them in shares rather than on the calling thread alone shortens
/// the wait after the last scan.
fn add_map_on_all_threads<K: BlockSink + ?Sized>(
    map: EvidenceMap,
    sink: &mut K,
    batch: &mut Batch<'_, '_>,
    spent: &mut Vec<Arc<BlockEvidence>>,
) {
    /// Below this many shared blocks (~0.5 µs each) handing shares out costs more than it saves.
    const MIN_PAIRS_TO_SHARE: usize = 64;
    let mut pairs = Vec::new();
    for (key, block) in map.into_blocks() {
        match sink.take_existing_block(key) {
            Some(mine) => pairs.push((key, mine, block)),
            None => sink.put_block(key, block),
        }
    }
    let helpers = batch.helpers.len();
    let mut sums = Vec::new();
    if pairs.len() >= MIN_PAIRS_TO_SHARE {
        let share = pairs.len().div_ceil(helpers + 1);
        for h in 0..helpers {
            let mut part = pairs.split_off(pairs.len().saturating_sub(share));
            let (tx, rx) = mpsc::channel();
            batch.start(
                h,
                Box::new(move |_: &mut Integrator| {
                    add_block_pairs(&mut part);
                    let _ = tx.send(part);
                }),
            );
            sums.push(rx);
        }
    }
    add_block_pairs(&mut pairs);
    for rx in sums {
        // A share whose helper panicked never comes back; the caller's `finish` passes the
        // panic on.
        pairs.extend(receive_soon(&rx).into_iter().flatten());
    }
    spent.reserve(pairs.len());
    for (key, sum, theirs) in pairs {
        sink.put_block(key, sum);
        spent.push(theirs);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A wall of `side` × `side` metres 4 m ahead of the origin, sampled every 5 cm, shifted a
    /// little per scan so the scans' cells differ.
    fn wall_scans(count: usize, side: f32) -> Vec<(Vec<[f32; 3]>, [f64; 3])> {
        let steps = (side / 0.05) as usize;
        (0..count)
            .map(|i| {
                let shift = i as f32 * 0.013;
                let pts = (0..steps * steps)
                    .map(|j| {
                        let (u, v) = ((j / steps) as f32 * 0.05, (j % steps) as f32 * 0.05);
                        [4.0 + shift, -side / 2.0 + u - shift, -side / 2.0 + v]
                    })
                    .collect();
                (pts, [0.05, 0.05, 0.05])
            })
            .collect()
    }

    fn add(
        integ: &mut Integrator,
        s: &(Vec<[f32; 3]>, [f64; 3]),
        sink: &mut dyn BlockSink,
    ) -> Result<(), ()> {
        integ.add_scan_into(sink, &s.0, s.1, 1, None);
        Ok(())
    }

    #[test]
    fn scans_on_several_workers_give_the_same_bits() {
        let params = MapParams::default();
        // Small scans (a few shared blocks, added on the calling thread) and wide ones (hundreds,
        // added in shares).
        for scans in [wall_scans(7, 2.0), wall_scans(5, 12.0)] {
            let mut serial = EvidenceMap::new(params);
            for s in &scans {
                Integrator::new(params).integrate(&mut serial, &s.0, s.1, 1);
            }
            for n in [1, 2, 3] {
                let mut workers = Workers::new(params, n);
                assert_eq!(workers.threads(), n);
                // Into an empty map, and twice into a snapshot's copy of the scans' map (its
                // blocks shared, so sums go into the helpers' blocks instead).
                let mut map = EvidenceMap::new(params);
                integrate_parallel(&mut workers, &scans, &mut map, add).unwrap();
                let mut twice = serial.clone();
                integrate_parallel(&mut workers, &scans, &mut twice, add).unwrap();
                assert_eq!(map.block_keys_sorted(), serial.block_keys_sorted(), "{n} workers");
                for k in serial.block_keys_sorted() {
                    assert!(map.block(k) == serial.block(k), "{n} workers: block {k:?} differs");
                    let mut doubled = serial.block(k).unwrap().to_box();
                    doubled.add_scaled(serial.block(k).unwrap(), 1);
                    assert!(
                        twice.block(k) == Some(&*doubled),
                        "{n} workers, second time: block {k:?} differs"
                    );
                }
                assert!(serial.block_count() > 0);
            }
        }
    }

    #[test]
    fn wide_scans_share_enough_blocks_to_be_added_in_shares() {
        // The test above exercises the shares only if a helper's map shares at least
        // `MIN_PAIRS_TO_SHARE` blocks with the caller's.
        let params = MapParams::default();
        let scans = wall_scans(2, 12.0);
        let (mut a, mut b) = (EvidenceMap::new(params), EvidenceMap::new(params));
        Integrator::new(params).integrate(&mut a, &scans[0].0, scans[0].1, 1);
        Integrator::new(params).integrate(&mut b, &scans[1].0, scans[1].1, 1);
        let shared = b.block_keys_sorted().into_iter().filter(|k| a.block(*k).is_some()).count();
        assert!(shared >= 4 * 64, "only {shared} shared blocks");
    }

    #[test]
    fn the_first_error_by_scan_order_is_returned_and_the_pool_goes_on() {
        let params = MapParams::default();
        let mut workers = Workers::new(params, 3);
        let fail =
            |_: &mut Integrator, i: &usize, _: &mut dyn BlockSink| if *i % 2 == 1 { Err(*i) } else { Ok(()) };
        let err =
            integrate_parallel(&mut workers, &[0usize, 1, 2, 3, 4, 5], &mut EvidenceMap::new(params), fail);
        assert_eq!(err, Err(1));
        let scans = wall_scans(4, 2.0);
        let mut map = EvidenceMap::new(params);
        integrate_parallel(&mut workers, &scans, &mut map, add).unwrap();
        assert!(map.block_count() > 0);
    }

    #[test]
    fn a_panic_on_a_helper_reaches_the_caller_and_the_pool_goes_on() {
        let params = MapParams::default();
        let mut workers = Workers::new(params, 2);
        let scans: Vec<usize> = (0..40).collect();
        let on_helper = |_: &mut Integrator, _: &usize, _: &mut dyn BlockSink| -> Result<(), ()> {
            // Slow enough that both threads take scans; the helper panics on its first.
            std::thread::sleep(std::time::Duration::from_millis(1));
            let name = std::thread::current().name().map(str::to_owned);
            assert!(!name.is_some_and(|n| n.starts_with("bgkmap-ingest")), "scan on a helper");
            Ok(())
        };
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            integrate_parallel(&mut workers, &scans, &mut EvidenceMap::new(params), on_helper)
        }));
        let message = caught.expect_err("the panic is passed on");
        let text =
            message.downcast_ref::<&str>().copied().or(message.downcast_ref::<String>().map(String::as_str));
        let text = text.unwrap_or_default();
        assert!(text.contains("scan on a helper"), "{text:?}");
        // Both threads still work.
        let scans = wall_scans(4, 2.0);
        let (mut map, mut serial) = (EvidenceMap::new(params), EvidenceMap::new(params));
        integrate_parallel(&mut workers, &scans, &mut map, add).unwrap();
        for s in &scans {
            Integrator::new(params).integrate(&mut serial, &s.0, s.1, 1);
        }
        assert!(map.same_blocks_as(&serial));
    }
}
