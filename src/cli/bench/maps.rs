//! `bgkmap bench restart` and the map-size half of `bgkmap bench durable`: large map files
//! (tiled from the blocks of real simulated scans, with a journal of raw scans), the time and
//! memory to open them as the server does on restart, and the time of an exact offline merge.

use super::common::Cleanup;
use crate::core::block::BlockEvidence;
use crate::core::{BlockKey, EvidenceMap, Integrator, MapParams, PointFrame, Pose, RawScan};
use crate::service::{MapService, ServiceConfig};
use crate::sim::{Lidar, simulate};
use crate::store::{DurableMap, MapReader, NewScan, save_map_with_scans};
use anyhow::{Context, Result, ensure};
use clap::Args;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The large maps `bench restart` and `bench merge` generate.
#[derive(Debug, Args)]
pub struct LargeMapArgs {
    /// Blocks per generated map.
    #[arg(long, default_value_t = 100_000)]
    pub blocks: usize,
    /// Raw scans journaled in each generated map.
    #[arg(long, default_value_t = 1000)]
    pub journal_scans: usize,
    /// Points per journaled scan.
    #[arg(long, default_value_t = 3500)]
    pub points: usize,
    /// Where to create the (temporary) directory of generated maps.
    #[arg(long, default_value = ".")]
    pub dir: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct RestartArgs {
    /// Data directory to open as `bgkmap serve` does (every map file, journals replayed), in
    /// this process. Without it, a large map is generated and opened in a fresh process.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    #[command(flatten)]
    pub large: LargeMapArgs,
}

#[derive(Debug, Args)]
pub struct MergeArgs {
    #[command(flatten)]
    pub large: LargeMapArgs,
}

fn generated_dir(a: &LargeMapArgs, what: &str) -> Result<(PathBuf, Cleanup)> {
    ensure!(a.blocks > 0 && a.points > 0, "--blocks and --points must be > 0");
    let root = a.dir.join(format!("bgkmap-bench-{what}-{}", std::process::id()));
    std::fs::create_dir_all(root.join("maps"))
        .with_context(|| format!("{}: cannot create", root.display()))?;
    Ok((root.clone(), Cleanup(root)))
}

/// `bench merge`: generates two large maps and merges them as `bgkmap merge` does.
pub fn run_merge(a: MergeArgs) -> Result<()> {
    let a = a.large;
    let (root, _cleanup) = generated_dir(&a, "merge")?;
    let (pa, pb) = (root.join("a.bgkmap"), root.join("b.bgkmap"));
    let write_s = write_maps(&pa, &pb, a.blocks, a.journal_scans, a.points)?;
    let (merge_s, blocks) = merge(&pa, &pb, &root.join("merged.bgkmap"))?;
    let bytes = std::fs::metadata(root.join("merged.bgkmap")).map(|m| m.len()).unwrap_or(0);
    let v = json!({"bench": "merge", "map_blocks": a.blocks, "journal_scans_per_map": a.journal_scans,
                   "points_per_scan": a.points, "write_maps_s": write_s, "merge_s": merge_s,
                   "merged_blocks": blocks, "merged_file_mb": bytes as f64 / 1e6});
    if a.json {
        println!("{v}");
    } else {
        println!(
            "merge: two maps of {} blocks with {} journaled scans each (half the blocks overlap): exact merge \
             {merge_s:.2} s → {blocks} blocks, {:.0} MB file (maps written in {write_s:.1} s)",
            a.blocks,
            a.journal_scans,
            bytes as f64 / 1e6
        );
    }
    Ok(())
}

/// Resident and peak memory of this process (kB), from `/proc/self/status`.
pub(super) fn memory_kb() -> (u64, u64) {
    let text = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next()?.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// Opens a data directory like a restarting server and reports time and memory; without
/// `--data-dir`, generates a large map and does that in a fresh process.
pub fn run_restart(a: RestartArgs) -> Result<()> {
    let Some(data_dir) = a.data_dir else {
        let l = a.large;
        let (root, _cleanup) = generated_dir(&l, "restart")?;
        let path = root.join("maps").join("a.bgkmap");
        write_map(&path, &base_map()?, l.blocks, 0, "robot-a", &scans_of(l.points, l.journal_scans))?;
        let mut v = restart_in_child(&root.join("maps"))?;
        v["file_mb"] = json!(std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0) as f64 / 1e6);
        if l.json {
            println!("{v}");
        } else {
            println!(
                "restart: a map of {} blocks with {} journaled scans ({:.0} MB file), opened in a fresh process: \
                 {:.2} s, resident memory {:.0} MB",
                v["blocks"],
                v["scans"],
                v["file_mb"].as_f64().unwrap_or(f64::NAN),
                v["open_s"].as_f64().unwrap_or(f64::NAN),
                v["rss_after_mb"].as_f64().unwrap_or(f64::NAN)
            );
        }
        return Ok(());
    };
    let (rss0, _) = memory_kb();
    let t0 = Instant::now();
    let service = MapService::open(&data_dir, ServiceConfig::default())?;
    let open_s = t0.elapsed().as_secs_f64();
    let (rss1, hwm) = memory_kb();
    let maps = service.list_maps();
    let blocks: usize = maps.iter().map(|m| m.blocks).sum();
    let scans: u64 = maps.iter().map(|m| m.scans).sum();
    service.shutdown();
    let v = json!({"bench": "restart", "maps": maps.len(), "blocks": blocks, "scans": scans, "open_s": open_s,
                   "rss_before_mb": rss0 as f64 / 1024.0, "rss_after_mb": rss1 as f64 / 1024.0,
                   "peak_rss_mb": hwm as f64 / 1024.0});
    if a.large.json {
        println!("{v}");
    } else {
        println!(
            "restart {}: {} maps, {blocks} blocks, {scans} journaled scans: open {open_s:.2} s, resident memory +{:.0} MB ({:.0} MB, peak {:.0} MB)",
            data_dir.display(),
            maps.len(),
            (rss1.saturating_sub(rss0)) as f64 / 1024.0,
            rss1 as f64 / 1024.0,
            hwm as f64 / 1024.0
        );
    }
    Ok(())
}

/// Simulated scans of the built-in room thinned to exactly `points` points each (world frame).
pub(super) fn scans_of(points: usize, n: usize) -> Vec<RawScan> {
    let (_, sim) = simulate(0, n.clamp(1, 48), &Lidar::default());
    (0..n)
        .map(|i| {
            let s = &sim[i % sim.len()];
            let step = (s.points_world.len() / points.max(1)).max(1);
            let pts: Vec<[f32; 3]> = s.points_world.iter().step_by(step).take(points).copied().collect();
            RawScan {
                frame: PointFrame::World,
                world_from_sensor: Pose::at(s.origin),
                points: pts,
                max_range_m: None,
            }
        })
        .collect()
}

/// A map of about `blocks` blocks: the blocks of 24 real scans, tiled over a grid of copies;
/// tiles start at `first_tile` (two maps overlap where their tile ranges do).
fn tiled(base: &EvidenceMap, blocks: usize, first_tile: usize) -> EvidenceMap {
    let keys = base.block_keys_sorted();
    let span = |f: fn(&BlockKey) -> i32| {
        keys.iter().map(f).max().unwrap_or(0) - keys.iter().map(f).min().unwrap_or(0) + 1
    };
    let (sx, sy) = (span(|k| k.x), span(|k| k.y));
    let mut map = EvidenceMap::new(*base.params());
    let mut tile = first_tile;
    while map.block_count() < blocks {
        let (tx, ty) = ((tile % 16) as i32 * sx, (tile / 16) as i32 * sy);
        for k in &keys {
            if map.block_count() >= blocks {
                break;
            }
            let block: &BlockEvidence = base.block(*k).expect("key of the map");
            map.insert_block(BlockKey::new(k.x + tx, k.y + ty, k.z), block.to_box());
        }
        tile += 1;
    }
    map
}

/// The blocks of 24 real scans of the simulated room: what large maps are tiled from.
fn base_map() -> Result<EvidenceMap> {
    let params = MapParams::default();
    let mut base = EvidenceMap::new(params);
    let mut integ = Integrator::new(params);
    for r in &scans_of(5760, 24) {
        r.add_into(&mut integ, &mut base, 1)?;
    }
    Ok(base)
}

/// Writes a map of `blocks` blocks tiled from `base` starting at tile `first_tile`, journaling
/// `journal` as applied scans of `source`.
fn write_map(
    path: &Path,
    base: &EvidenceMap,
    blocks: usize,
    first_tile: usize,
    source: &str,
    journal: &[RawScan],
) -> Result<()> {
    let map = tiled(base, blocks, first_tile);
    let rows: Vec<NewScan> = journal
        .iter()
        .enumerate()
        .map(|(i, s)| NewScan {
            source: source.into(),
            seq: i as u64 + 1,
            stamp_nanos: 1,
            received_nanos: 1,
            scan: s.clone(),
        })
        .collect();
    save_map_with_scans(path, &map, &rows, rows.len() as u64)?;
    Ok(())
}

/// Writes the two bench maps `a` and `b` (half of b's tiles overlap a's; each journals
/// `journal` raw scans under its own source). Returns seconds spent.
pub(super) fn write_maps(a: &Path, b: &Path, blocks: usize, journal: usize, points: usize) -> Result<f64> {
    let t0 = Instant::now();
    let base = base_map()?;
    let tiles = blocks.div_ceil(base.block_count().max(1));
    let journal_scans = scans_of(points, journal);
    write_map(a, &base, blocks, 0, "robot-a", &journal_scans)?;
    write_map(b, &base, blocks, tiles / 2, "robot-b", &journal_scans)?;
    Ok(t0.elapsed().as_secs_f64())
}

/// Restart of `dir` in a fresh process (`bgkmap bench restart`), for clean memory figures.
pub(super) fn restart_in_child(dir: &Path) -> Result<Value> {
    let args = ["bench", "restart", "--json", "--data-dir"].map(std::ffi::OsString::from);
    super::common::bench_in_child(&[&args[..], &[dir.as_os_str().to_owned()]].concat())
}

/// The offline exact merge of `a` and `b` into `out`, as `bgkmap merge` does it.
pub(super) fn merge(a: &Path, b: &Path, out: &Path) -> Result<(f64, u64)> {
    let t0 = Instant::now();
    MapReader::open(a)?.copy_to(out)?;
    let mut merged = DurableMap::open_recovered(out)?;
    merged.merge_from(b)?;
    let blocks = merged.map().block_count() as u64;
    merged.close()?;
    Ok((t0.elapsed().as_secs_f64(), blocks))
}
