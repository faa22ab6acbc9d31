//! `bgkmap bench scale`: does a scan cost more as the map grows, and what a cell costs in RAM
//! and on disk.
//!
//! Growth: for each level the map holds `level` filler blocks — copies of real blocks (of the
//! simulated room), tiled beside the room and sharing their evidence (`Arc`), so a map of 10⁶
//! blocks builds in seconds and fits in memory — and then the 12 room scans are integrated
//! into it (one untimed pass creating their blocks, then timed passes revisiting them). The
//! hash table, the part of the map a scan's cost could grow with, is full size; the filler's
//! cell data is shared, so its RAM is not. Queries are timed on the same maps (points uniform
//! over all blocks, 8 m rays from the route).
//!
//! The levels' maps are all built first and their passes then alternate (a pass over the room
//! on each level in turn), so a host whose speed drifts during the run weighs on every level
//! alike instead of reading as growth (or shrinkage) with map size.
//!
//! Memory: RAM per cell is the map's own layout — per block the evidence, the `Arc` counters
//! and a hash-table slot at its lowest load (1/2) — divided by its cells, because the process's
//! resident set mixes in allocator and runtime memory; disk per cell is the size of the saved
//! map file. "Allocated cells" are all 512 cells of each allocated block; "cells with evidence"
//! those holding any.

use super::common::{Cleanup, percentile};
use super::world::{RaySpec, build_map, outdoor_params, outdoor_scans, random_direction};
use crate::core::key::BLOCK_CELLS;
use crate::core::query::{StopAt, cast_ray, query_points};
use crate::core::{BlockKey, EvidenceMap, Integrator, MapParams};
use crate::sim::{Lidar, SimScan, simulate};
use anyhow::{Result, ensure};
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::time::Instant;

#[derive(Debug, Args)]
pub struct ScaleArgs {
    /// Filler blocks per level (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = [0usize, 10_000, 100_000, 1_000_000])]
    pub levels: Vec<usize>,
    /// Timed passes over the 12 room scans per level.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Scans of the 64-beam outdoor drive whose map is measured for memory (0 skips it).
    #[arg(long, default_value_t = 4)]
    pub outdoor_scans: usize,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// Points per timed point query and rays per timed ray batch.
const QUERY_POINTS: usize = 100_000;
const QUERY_RAYS: usize = 10_000;

pub fn run(a: ScaleArgs) -> Result<()> {
    ensure!(a.repeat > 0 && !a.levels.is_empty(), "--repeat and --levels must be non-empty");
    let (_, room) = simulate(0, 12, &Lidar::default());
    let params = MapParams::default();
    let filler_source = build_map(&simulate(1, 24, &Lidar::default()).1, params, 1);
    let mut maps: Vec<Level> = a.levels.iter().map(|&n| Level::new(&filler_source, n)).collect();
    for pass in 0..=a.repeat {
        for l in &mut maps {
            l.pass(&room, pass > 0);
        }
    }
    let levels: Vec<Value> = maps.into_iter().map(|l| l.summary(&room)).collect();
    let mut memory = json!({"room": memory_of(&build_map(&room, params, 1))?});
    if a.outdoor_scans > 0 {
        memory["outdoor"] = memory_of(&build_map(&outdoor_scans(a.outdoor_scans), outdoor_params(), 2))?;
    }
    let v = json!({"bench": "scale", "scans_per_pass": room.len(), "repeat": a.repeat,
                   "levels": levels, "memory": memory});
    if a.json {
        println!("{v}");
    } else {
        print_summary(&v);
    }
    Ok(())
}

/// One level: a map of `filler` shared blocks into which the room scans go, pass by pass.
struct Level {
    filler: usize,
    map: EvidenceMap,
    integ: Integrator,
    /// Per timed scan, its time.
    ms: Vec<f64>,
}

impl Level {
    fn new(source: &EvidenceMap, filler: usize) -> Self {
        let params = *source.params();
        let mut map = EvidenceMap::new(params);
        add_filler(&mut map, source, filler);
        Self { filler, map, integ: Integrator::new(params), ms: Vec::new() }
    }

    /// One pass over the room's scans, each timed if `timed`.
    fn pass(&mut self, room: &[SimScan], timed: bool) {
        for s in room {
            let t0 = Instant::now();
            self.integ.integrate(&mut self.map, &s.points_world, s.origin, 1);
            if timed {
                self.ms.push(t0.elapsed().as_secs_f64() * 1e3);
            }
        }
    }

    fn summary(mut self, room: &[SimScan]) -> Value {
        let (points_per_s, rays_per_s) = query_rates(&self.map, room);
        json!({"filler_blocks": self.filler, "blocks": self.map.block_count(),
               "per_scan_ms_median": percentile(&mut self.ms.clone(), 0.5),
               "per_scan_ms_p90": percentile(&mut self.ms, 0.9),
               "query_points_per_s": points_per_s, "rays_8m_per_s": rays_per_s})
    }
}

/// Adds `n` blocks sharing the evidence of `source`'s blocks, tiled along +x beyond the room
/// (never where the room scans write).
fn add_filler(map: &mut EvidenceMap, source: &EvidenceMap, n: usize) {
    let keys = source.block_keys_sorted();
    if keys.is_empty() {
        return;
    }
    let span = |f: fn(&BlockKey) -> i32| {
        keys.iter().map(f).max().unwrap_or(0) - keys.iter().map(f).min().unwrap_or(0) + 1
    };
    let (sx, sy) = (span(|k| k.x), span(|k| k.y));
    let mut added = 0;
    for tile in 1.. {
        let (tx, ty) = ((tile % 64) * sx + 4 * sx, (tile / 64) * sy);
        for k in &keys {
            if added >= n {
                return;
            }
            let block = source.block_arc(*k).expect("key of the map");
            map.insert_shared_block(BlockKey::new(k.x + tx, k.y + ty, k.z), block);
            added += 1;
        }
    }
}

/// In-process query rates on `map`: points uniform over all its blocks, 8 m rays from the
/// scans' sensor positions. (points/s, rays/s), best of three runs.
fn query_rates(map: &EvidenceMap, room: &[SimScan]) -> (f64, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let keys = map.block_keys_sorted();
    let block_m = 8.0 * map.params().resolution_m;
    let points: Vec<[f64; 3]> = (0..QUERY_POINTS)
        .map(|_| {
            let k = keys[rng.random_range(0..keys.len())];
            [k.x, k.y, k.z].map(|v| (f64::from(v) + rng.random::<f64>()) * block_m)
        })
        .collect();
    let rays: Vec<RaySpec> = (0..QUERY_RAYS)
        .map(|_| RaySpec {
            origin: room[rng.random_range(0..room.len())].origin,
            direction: random_direction(&mut rng),
            max_range_m: 8.0,
        })
        .collect();
    let th = map.params().thresholds;
    let (mut best_p, mut best_r) = (0.0f64, 0.0f64);
    for _ in 0..3 {
        let t0 = Instant::now();
        std::hint::black_box(query_points(map, &points, &th));
        best_p = best_p.max(QUERY_POINTS as f64 / t0.elapsed().as_secs_f64());
        let t0 = Instant::now();
        for r in &rays {
            let _ = std::hint::black_box(cast_ray(
                map,
                r.origin,
                r.direction,
                r.max_range_m,
                StopAt::Occupied,
                &th,
            ));
        }
        best_r = best_r.max(QUERY_RAYS as f64 / t0.elapsed().as_secs_f64());
    }
    (best_p, best_r)
}

/// RAM and disk bytes per cell of `map` (see the module docs).
fn memory_of(map: &EvidenceMap) -> Result<Value> {
    // Per block: its cells in the block's layout (wide or narrow), the Arc's two counters,
    // and the block table's entry (key, pointer and ray summary) and slots at its worst load
    // just after growing.
    let per_block = 2 * std::mem::size_of::<usize>() + EvidenceMap::TABLE_BYTES_PER_BLOCK;
    let (mut ram, mut wide) = (0usize, 0usize);
    for (_, b) in map.blocks_unsorted() {
        ram += per_block + b.data_bytes();
        wide += usize::from(b.is_wide());
    }
    let ram = ram as f64;
    let dir = std::env::temp_dir().join(format!("bgkmap-bench-scale-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let _cleanup = Cleanup(dir.clone());
    let path = dir.join("m.bgkmap");
    crate::store::save_map(&path, map)?;
    let disk = std::fs::metadata(&path)?.len() as f64;
    let mut block_bytes = 0usize;
    let mut buf = Vec::new();
    for (_, b) in map.blocks_unsorted() {
        buf.clear();
        crate::store::encode_block(b, &mut buf);
        block_bytes += buf.len();
    }
    let allocated = (map.block_count() * BLOCK_CELLS) as f64;
    let with_evidence = map.cells_with_evidence() as f64;
    Ok(
        json!({"blocks": map.block_count(), "wide_blocks": wide, "cells_allocated": allocated, "cells_with_evidence": with_evidence,
              "ram_bytes_per_allocated_cell": ram / allocated, "ram_bytes_per_cell_with_evidence": ram / with_evidence,
              "disk_bytes_per_allocated_cell": disk / allocated,
              "disk_bytes_per_cell_with_evidence": disk / with_evidence,
              "block_data_bytes_per_cell_with_evidence": block_bytes as f64 / with_evidence,
              "file_bytes": disk}),
    )
}

fn print_summary(v: &Value) {
    println!("scale bench: the 12 room scans (16-beam, 5760 points) integrated into maps of growing size");
    for l in v["levels"].as_array().into_iter().flatten() {
        let f = |k: &str| l[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "  {:>9} blocks: per scan median {:.2} ms, p90 {:.2} ms; points {:.1} M/s, 8 m rays {:.2} M/s",
            l["blocks"],
            f("per_scan_ms_median"),
            f("per_scan_ms_p90"),
            f("query_points_per_s") / 1e6,
            f("rays_8m_per_s") / 1e6
        );
    }
    for (name, m) in v["memory"].as_object().into_iter().flatten() {
        let f = |k: &str| m[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "  memory, {name} map ({} blocks, {} cells with evidence): RAM {:.2} B per allocated cell ({:.1} B per cell \
             with evidence); disk {:.2} B per allocated cell ({:.1} B per cell with evidence; block data alone {:.1})",
            m["blocks"],
            m["cells_with_evidence"],
            f("ram_bytes_per_allocated_cell"),
            f("ram_bytes_per_cell_with_evidence"),
            f("disk_bytes_per_allocated_cell"),
            f("disk_bytes_per_cell_with_evidence"),
            f("block_data_bytes_per_cell_with_evidence"),
        );
    }
}
