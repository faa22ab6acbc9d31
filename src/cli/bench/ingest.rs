//! `bgkmap bench ingest`: scan integration (training data, evidence, map update) timed per scan
//! and per pass, on one or several workers; scans are loaded or simulated before timing.

use super::common::percentile;
use super::world::{as_scans, outdoor_scans};
use crate::cli::args::{ScanArgs, load_scan};
use crate::core::{EvidenceMap, Integrator, MapParams, Workers, integrate_parallel};
use crate::io::scan::Scan;
use crate::sim::{Lidar, simulate};
use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct IngestArgs {
    /// PCD scans (default: 12 scans of the built-in simulated room).
    pub scans: Vec<PathBuf>,
    /// Instead: this many scans of a simulated dense 64-beam LiDAR (~130k points, 30 m) driving
    /// through a town; `--max-range` then defaults to the LiDAR's 30 m.
    #[arg(long, conflicts_with = "scans")]
    pub lidar64: Option<usize>,
    /// Timed passes over all scans (after one untimed warm-up pass), each into a fresh map.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Worker threads: scans are integrated concurrently, one per worker (same bits).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Threads splitting each scan's evidence (same bits); for single large scans.
    #[arg(long, default_value_t = 1)]
    pub threads_per_scan: usize,
    /// With several workers, the passes on one worker that `speedup_vs_one_worker` compares
    /// with alternate with theirs in runs of this many (1: pass by pass).
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..))]
    pub alternate_every: u64,
    /// Maximum range (m); 0 = unlimited. Default 8 (30 with `--lidar64`).
    #[arg(long)]
    pub max_range: Option<f64>,
    /// Hits beyond max range: `truncate` (default) or `drop` (la3dm's work, for comparison).
    #[arg(long, default_value = "truncate")]
    pub range_mode: crate::core::RangeMode,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub scan: ScanArgs,
}

/// What [`timed_scan`] records of a scan.
#[derive(Debug, Clone, Copy)]
struct ScanTime {
    training_points: usize,
    training: std::time::Duration,
    evidence: std::time::Duration,
    /// When the scan was done.
    done: Instant,
    /// The thread of the worker that did it.
    thread: std::thread::ThreadId,
}
/// Every scan's, in the order they were done.
type ScanTimes = std::sync::Mutex<Vec<ScanTime>>;

/// Builds one scan's training data, then runs `evidence` on it, and records both times.
fn timed_scan<R>(
    integ: &mut Integrator,
    s: &Scan,
    timed: &ScanTimes,
    evidence: impl FnOnce(&mut Integrator) -> R,
) -> R {
    let t0 = Instant::now();
    let n_train = integ.training(&s.points_world, s.origin_world).len();
    let t1 = Instant::now();
    let out = evidence(integ);
    let t2 = Instant::now();
    let thread = std::thread::current().id();
    lock(timed).push(ScanTime {
        training_points: n_train,
        training: t1 - t0,
        evidence: t2 - t1,
        done: t2,
        thread,
    });
    out
}

/// What [`ingest_pass`] records of a pass: its wall time (ms), each scan's times, and when it
/// started and ended.
struct PassTime {
    wall_ms: f64,
    scans: Vec<ScanTime>,
    start: Instant,
    end: Instant,
}

/// One timed pass over `scans` into a fresh map.
fn ingest_pass(workers: &mut Workers, scans: &[Scan], params: MapParams, split: usize) -> PassTime {
    let mut map = EvidenceMap::new(params);
    let timed: ScanTimes = std::sync::Mutex::new(Vec::with_capacity(scans.len()));
    let t_pass = Instant::now();
    let done = integrate_parallel(workers, scans, &mut map, |integ, s, sink| {
        timed_scan(integ, s, &timed, |integ| integ.add_training_into(sink, split));
        Ok::<_, std::convert::Infallible>(())
    });
    if let Err(never) = done {
        match never {}
    }
    let t_end = Instant::now();
    let timed = timed.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner);
    PassTime { wall_ms: (t_end - t_pass).as_secs_f64() * 1e3, scans: timed, start: t_pass, end: t_end }
}

pub fn run(a: IngestArgs) -> Result<()> {
    let (scans, source) = if let Some(n) = a.lidar64 {
        let scans = as_scans(outdoor_scans(n.max(1)));
        (scans, format!("simulated 64-beam LiDAR drive (seed 0, {} scans, town of 4×4 blocks)", n.max(1)))
    } else if a.scans.is_empty() {
        let (_, sim) = simulate(0, 12, &Lidar::default());
        let scans = sim
            .into_iter()
            .map(|s| Scan { points_world: s.points_world, origin_world: s.origin, dropped_nonfinite: 0 })
            .collect::<Vec<_>>();
        (scans, "simulated room (seed 0, 12 scans, 16-beam lidar)".to_string())
    } else {
        let scans = a.scans.iter().map(|p| load_scan(p, &a.scan)).collect::<Result<Vec<_>>>()?;
        (scans, format!("{} PCD files", a.scans.len()))
    };
    let max_range = a.max_range.unwrap_or(if a.lidar64.is_some() { 30.0 } else { 8.0 });
    let params = MapParams { max_range_m: max_range, range_mode: a.range_mode, ..Default::default() };
    params.validate()?;
    let threads = a.threads.max(1);
    let split = a.threads_per_scan.max(1);
    let mut workers = Workers::new(params, threads);
    // With several workers, passes on a single worker alternate with theirs, so the speed-up
    // compares passes taken moments apart: on a shared host the load drifts by tens of percent
    // between runs. They alternate in runs (`--alternate-every`, 10 passes), as a server
    // ingests, not pass by pass: then each pass finds the other's map out of the caches and an
    // idle helper thread's vCPU halts during every one-worker pass, which no steady ingest does.
    let mut solo_workers = (threads > 1).then(|| Workers::new(params, 1));
    let mut per_scan_ms = Vec::new();
    // Per worker that runs scans (the calling thread's first), their time and training points: with
    // several, whether one of them (a slower vCPU, a busy neighbour) holds the others back,
    // compared per training point because each worker gets other scans.
    let mut per_worker: Vec<(std::thread::ThreadId, (f64, usize))> =
        vec![(std::thread::current().id(), (0.0, 0))];
    let mut totals_ms = Vec::new();
    let mut solo_ms = Vec::new();
    // Where the time goes: per scan, training data and evidence (into the map, or into a
    // worker's own map); per pass, the workers that had run out of scans waiting for the
    // others' last, then adding the workers' maps into the map after the last scan.
    let mut phases_ms: [Vec<f64>; 2] = Default::default();
    let mut tail_ms = Vec::new();
    let mut merge_ms = Vec::new();
    let mut pairs_in = (0usize, 0usize);
    // The fewest and most training points of a scan (with all scans' time per training point
    // below): a scan's cost follows its training points (how much free space its rays cross),
    // not its raw points.
    let mut train_range = (usize::MAX, 0usize);
    let (repeat, every) = (a.repeat.max(1), a.alternate_every as usize);
    for pass in 0..=repeat {
        let PassTime { wall_ms, scans: timed, start, end: t_end } =
            ingest_pass(&mut workers, &scans, params, split);
        // After every `every` passes on the workers (and after the last), as many on one worker.
        let run_ends = (pass + 1) % every == 0 || pass == repeat;
        if let Some(w) = solo_workers.as_mut().filter(|_| run_ends) {
            for solo_pass in pass - pass % every..=pass {
                let ms = ingest_pass(w, &scans, params, split).wall_ms;
                if solo_pass > 0 {
                    solo_ms.push(ms);
                }
            }
        }
        if pass > 0 {
            for &ScanTime { training_points: n_train, training, evidence, thread, .. } in timed.iter() {
                let parts = [training, evidence].map(|d| d.as_secs_f64() * 1e3);
                let ms: f64 = parts.iter().sum();
                per_scan_ms.push(ms);
                let (sum_ms, points) = of_thread(&mut per_worker, thread, (0.0, 0));
                (*sum_ms, *points) = (*sum_ms + ms, *points + n_train);
                for (v, ms) in phases_ms.iter_mut().zip(parts) {
                    v.push(ms);
                }
                pairs_in.0 += n_train;
                pairs_in.1 += 1;
                train_range = (train_range.0.min(n_train), train_range.1.max(n_train));
            }
            let last = timed.iter().map(|t| t.done).max().unwrap_or(t_end);
            let ran_out = first_to_run_out(&timed, threads, start).unwrap_or(last);
            tail_ms.push(last.saturating_duration_since(ran_out).as_secs_f64() * 1e3);
            merge_ms.push((t_end - last).as_secs_f64() * 1e3);
            totals_ms.push(wall_ms);
        }
    }
    let [mut train_ms, mut scatter_ms] = phases_ms;
    let phase = [percentile(&mut train_ms, 0.5), percentile(&mut scatter_ms, 0.5)];
    let tail = percentile(&mut tail_ms, 0.5);
    let merge = percentile(&mut merge_ms, 0.5);
    let training_points_mean = pairs_in.0 as f64 / pairs_in.1.max(1) as f64;
    let ns_per_training_point = per_scan_ms.iter().sum::<f64>() * 1e6 / pairs_in.0.max(1) as f64;
    let train_range = if pairs_in.1 == 0 { (0, 0) } else { train_range };
    let points: usize = scans.iter().map(|s| s.points_world.len()).sum();
    let med = percentile(&mut per_scan_ms, 0.5);
    // Workers that ran no scan (a helper that woke after the others had taken them all, or
    // the calling thread beaten to every scan) have no figure.
    let worker_ns: Vec<f64> = per_worker
        .iter()
        .filter(|&&(_, (_, points))| points > 0)
        .map(|&(_, (ms, points))| ms * 1e6 / points as f64)
        .collect();
    let p90 = percentile(&mut per_scan_ms, 0.9);
    let total_med = percentile(&mut totals_ms, 0.5);
    let points_per_s = points as f64 / (total_med / 1e3);
    // The one-worker median and the speed-up over it, with several workers.
    let solo = solo_workers.map(|_| {
        let solo_med = percentile(&mut solo_ms, 0.5);
        (solo_med, solo_med / total_med)
    });
    if a.json {
        let mut v = serde_json::json!({
            "bench": "ingest", "source": source, "scans": scans.len(), "repeat": repeat,
            "threads": threads, "threads_per_scan": split, "max_range": max_range,
            "scans_per_s": scans.len() as f64 / (total_med / 1e3),
            "per_scan_ms_median": med, "per_scan_ms_p90": p90, "total_ms_median": total_med,
            "raw_points": points, "points_per_s": points_per_s,
            "range_mode": params.range_mode.as_str(),
            "training_points_per_scan_mean": training_points_mean,
            "training_points_per_scan_min": train_range.0, "training_points_per_scan_max": train_range.1,
            "ns_per_training_point": ns_per_training_point,
            "phase_ms_median": {"training": phase[0], "evidence": phase[1]},
            "tail_ms_median": tail, "merge_ms_median": merge,
        });
        if let Some((solo_med, speedup)) = solo {
            v["per_worker_ns_per_training_point"] = serde_json::json!(worker_ns);
            v["one_worker_total_ms_median"] = serde_json::json!(solo_med);
            v["speedup_vs_one_worker"] = serde_json::json!(speedup);
            v["one_worker_passes"] = serde_json::json!(solo_ms.len());
            v["alternate_every"] = serde_json::json!(every);
        }
        println!("{v}");
    } else {
        println!(
            "ingest {source}: {} scans × {} passes, {threads} worker(s) × {split} thread(s) per scan: per scan median {med:.3} ms, p90 {p90:.3} ms; \
             all scans median {total_med:.2} ms ({:.2} M raw points/s); per-scan medians: training {:.3} ms, \
             evidence {:.3} ms ({training_points_mean:.0} training points per scan, {}–{}; {ns_per_training_point:.1} ns per training point); \
             per pass: workers out of scans waiting for the others' last {tail:.3} ms, then adding the workers' maps {merge:.3} ms",
            scans.len(),
            repeat,
            points_per_s / 1e6,
            phase[0],
            phase[1],
            train_range.0,
            train_range.1,
        );
        if let Some((solo_med, speedup)) = solo {
            let workers = worker_ns.iter().map(|ns| format!("{ns:.1}")).collect::<Vec<_>>().join(", ");
            println!(
                "  per worker that ran scans (the calling thread first): {workers} ns per training point; one worker, passes alternating with those \
                 in runs of {every}: all scans median {solo_med:.2} ms; {threads} workers are {speedup:.2}× as fast"
            );
        }
    }
    Ok(())
}

/// When the first of a pass's `workers` (those that had a scan to take) ran out of scans: the
/// earliest of their last scans' ends, or the pass's `start` if one of them did none. From then
/// until the pass's last scan ends, that worker waits: the imbalance of whole scans handed out
/// one at a time. `None` for a pass without scans.
fn first_to_run_out(timed: &[ScanTime], workers: usize, start: Instant) -> Option<Instant> {
    let mut last_per_thread: Vec<(std::thread::ThreadId, Instant)> = Vec::new();
    for t in timed {
        let done = of_thread(&mut last_per_thread, t.thread, t.done);
        *done = (*done).max(t.done);
    }
    let idle_throughout = !timed.is_empty() && last_per_thread.len() < workers.min(timed.len());
    let first = last_per_thread.iter().map(|&(_, done)| done).min();
    if idle_throughout { Some(start) } else { first }
}

/// The entry of `thread` in a list kept per thread (a pass has a handful), added as `new` if
/// it has none yet.
fn of_thread<T>(
    per_thread: &mut Vec<(std::thread::ThreadId, T)>,
    thread: std::thread::ThreadId,
    new: T,
) -> &mut T {
    let at = match per_thread.iter().position(|(id, _)| *id == thread) {
        Some(at) => at,
        None => {
            per_thread.push((thread, new));
            per_thread.len() - 1
        }
    };
    &mut per_thread[at].1
}

fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn the_wait_starts_when_the_first_worker_runs_out_of_scans() {
        let start = Instant::now();
        let (me, other) =
            (std::thread::current().id(), std::thread::spawn(|| std::thread::current().id()).join().unwrap());
        let scan = |thread, ms| ScanTime {
            training_points: 1,
            training: Duration::ZERO,
            evidence: Duration::ZERO,
            done: start + Duration::from_millis(ms),
            thread,
        };
        // This thread's last scan ends at 5 ms, the other's at 9: the wait starts at 5.
        let timed = [scan(me, 2), scan(other, 3), scan(me, 5), scan(other, 9)];
        assert_eq!(first_to_run_out(&timed, 2, start), Some(start + Duration::from_millis(5)));
        // One worker waits for no one: it ran out when its last scan ended.
        let alone = [scan(me, 2), scan(me, 5)];
        assert_eq!(first_to_run_out(&alone, 1, start), Some(start + Duration::from_millis(5)));
        // Two workers, two scans, both done by one: the other waited from the start.
        assert_eq!(first_to_run_out(&alone, 2, start), Some(start));
        // One scan for two workers: only one of them had a scan to take.
        assert_eq!(first_to_run_out(&alone[..1], 2, start), Some(start + Duration::from_millis(2)));
        assert_eq!(first_to_run_out(&[], 2, start), None);
    }
}
