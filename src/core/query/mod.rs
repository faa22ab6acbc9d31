//! Point, box and ray queries over an [`EvidenceMap`], all in-process and read-only.
//!
//! Geometric arguments are world-frame metres. Answers name the cell they came from.

use super::block::BlockEvidence;
use super::key::{BLOCK_CELLS, BlockKey, CellKey};
use super::map::EvidenceMap;
use super::params::Thresholds;
use super::posterior::{CellEstimate, CellState, Evidence, alpha_beta, mean_variance};

pub mod ray;

/// One answer of a point query.
///
/// `repr(C)` here and on [`CellEstimate`]: in Rust's own layout the state byte sat in the
/// middle of the answer, and every answer pushed went through a stack copy in 16-byte pieces
/// starting just after it, at odd offsets, whose loads waited on the narrower stores just made
/// there (store forwarding fails across them).
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C)]
pub struct PointAnswer {
    pub cell: CellKey,
    pub estimate: CellEstimate,
}

/// Answers for points in the world frame (metres). Points outside the key range or not finite
/// answer `None`.
pub fn query_points(
    map: &EvidenceMap,
    points_world: &[[f64; 3]],
    th: &Thresholds,
) -> Vec<Option<PointAnswer>> {
    let mut out = Vec::with_capacity(points_world.len());
    for_each_point(map, points_world, th, |a| out.push(a));
    out
}

/// Points looked up per round of [`for_each_point`]: that many independent hash lookups and
/// loads are issued back to back, so their cache misses overlap instead of queueing one
/// behind the other. 64 is the most [`EvidenceMap::blocks_of`] takes (checked at compile
/// time); 32 was slower, 96 and 128 no faster.
const POINT_BATCH: usize = 64;
const _: () = assert!(POINT_BATCH <= EvidenceMap::MAX_BATCH_LOOKUPS, "a round is one blocks_of call");

/// [`query_points`] without the answer vector: `f` gets each point's answer, in order.
///
/// Points are processed in rounds of 64: keys, then the block lookups in stages (every table
/// slot, then every entry; [`EvidenceMap::blocks_of`]), then a prefetch of every cell, then
/// the estimates (measured: faster than prefetching inside the lookup loop). A cell without
/// evidence answers the prior estimate computed once (the same bits as
/// [`CellEstimate::from_evidence`] of zero evidence).
///
/// Keys and estimates are computed stage by stage over the round, so their five divisions per
/// point run as packed pairs. The block lookups are about half a point's time; the rest is
/// the cells' misses, which a round already keeps in flight to the limit of the core's miss
/// buffers.
pub fn for_each_point(
    map: &EvidenceMap,
    points_world: &[[f64; 3]],
    th: &Thresholds,
    mut f: impl FnMut(Option<PointAnswer>),
) {
    let params = map.params();
    let res = params.resolution_m;
    let prior = CellEstimate::from_evidence(Evidence::default(), params, th);
    let mut cells = [None::<CellKey>; POINT_BATCH];
    let mut block_keys = [None::<BlockKey>; POINT_BATCH];
    let mut blocks: [Option<&BlockEvidence>; POINT_BATCH] = [None; POINT_BATCH];
    let mut evidence = [Evidence::default(); POINT_BATCH];
    for chunk in points_world.chunks(POINT_BATCH) {
        let n = chunk.len();
        // Each stage is a loop over the round, so the divisions (three per key, two per
        // estimate) go two at a time (packed); the same IEEE operations per point, so the same
        // bits as `CellKey::from_point` and `CellEstimate::from_evidence`.
        let mut q = [[0.0; 3]; POINT_BATCH];
        for (q, p) in q.iter_mut().zip(chunk) {
            *q = p.map(|v| v / res);
        }
        for (c, q) in cells.iter_mut().zip(&q[..n]) {
            *c = CellKey::from_cells(*q);
        }
        for (k, c) in block_keys.iter_mut().zip(&cells[..n]) {
            *k = c.map(|c| c.block());
        }
        map.blocks_of(&block_keys[..n], &mut blocks[..n]);
        for (b, c) in blocks.iter().zip(&cells[..n]) {
            if let (Some(b), Some(c)) = (b, c) {
                crate::core::prefetch::prefetch(b.cell(c.index_in_block()));
            }
        }
        let (mut alpha, mut beta) = ([0.0; POINT_BATCH], [0.0; POINT_BATCH]);
        for i in 0..n {
            evidence[i] = match (blocks[i], cells[i]) {
                (Some(b), Some(c)) => b.get(c.index_in_block()),
                _ => Evidence::default(),
            };
            (alpha[i], beta[i]) = alpha_beta(evidence[i], params);
        }
        let (mut mean, mut var) = ([0.0; POINT_BATCH], [0.0; POINT_BATCH]);
        for i in 0..POINT_BATCH {
            (mean[i], var[i]) = mean_variance(alpha[i], beta[i]);
        }
        for i in 0..n {
            let e = evidence[i];
            f(cells[i].map(|cell| PointAnswer {
                cell,
                estimate: if e.is_empty() {
                    prior
                } else {
                    CellEstimate::from_moments(e, (mean[i], var[i]), th)
                },
            }));
        }
    }
}

/// An axis-aligned box query.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxQuery {
    pub min_world: [f64; 3],
    pub max_world: [f64; 3],
    /// Keep only cells in this state (`None`: every cell with evidence).
    pub state: Option<CellState>,
    /// Aggregate 2^coarsen cells per axis into one answer (evidence summed over the children).
    pub coarsen: u8,
}

/// A cube of the answer: `size_cells` cells per edge starting at `min_cell`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxCell {
    pub min_cell: CellKey,
    pub size_cells: i32,
    pub estimate: CellEstimate,
}

/// Why a box query was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BoxError {
    #[error("box: min and max must be finite with min ≤ max on every axis")]
    Malformed,
    #[error("box: {cells} cells exceeds the limit of {limit}; shrink the box or coarsen")]
    TooLarge { cells: u128, limit: u64 },
    #[error("box: coarsen must be at most 10, got {0}")]
    Coarsen(u8),
}

/// Cells inside `q` (inclusive of boundary cells) that hold evidence, sorted by key (x, then y,
/// then z); coarse cubes sum their children's evidence (clipped to the box). `max_cells` bounds
/// the number of lattice positions of the answer (at the query's coarsened resolution); the
/// work is bounded by the blocks that exist, never by the volume of the box.
pub fn query_box(
    map: &EvidenceMap,
    q: &BoxQuery,
    th: &Thresholds,
    max_cells: u64,
) -> Result<Vec<BoxCell>, BoxError> {
    if q.coarsen > 10 {
        return Err(BoxError::Coarsen(q.coarsen));
    }
    let res = map.params().resolution_m;
    let (lo, hi) = match (CellKey::from_point(q.min_world, res), CellKey::from_point(q.max_world, res)) {
        (Some(lo), Some(hi)) if lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z => (lo, hi),
        _ => return Err(BoxError::Malformed),
    };
    let s = q.coarsen;
    let span = |a: i32, b: i32| (i64::from(b >> s) - i64::from(a >> s) + 1) as u128;
    let cells = span(lo.x, hi.x) * span(lo.y, hi.y) * span(lo.z, hi.z);
    if cells > u128::from(max_cells) {
        return Err(BoxError::TooLarge { cells, limit: max_cells });
    }
    let mut cubes: std::collections::BTreeMap<CellKey, Evidence> = std::collections::BTreeMap::new();
    for key in blocks_in_box(map, lo, hi) {
        let Some(block) = map.block(key) else { continue };
        for (i, e) in block.cells().enumerate() {
            let (a, b) = (e.a, e.b);
            let cell = key.cell(i);
            let inside = (lo.x..=hi.x).contains(&cell.x)
                && (lo.y..=hi.y).contains(&cell.y)
                && (lo.z..=hi.z).contains(&cell.z);
            if (a != 0 || b != 0) && inside {
                let e = cubes
                    .entry(CellKey::new(cell.x >> s << s, cell.y >> s << s, cell.z >> s << s))
                    .or_default();
                e.a += a;
                e.b += b;
            }
        }
    }
    let size = 1i32 << s;
    Ok(cubes
        .into_iter()
        .map(|(min_cell, e)| BoxCell {
            min_cell,
            size_cells: size,
            estimate: CellEstimate::from_evidence(e, map.params(), th),
        })
        .filter(|c| q.state.is_none_or(|st| st == c.estimate.state))
        .collect())
}

/// The map's blocks that overlap cells `lo..=hi`: by walking the block range when it is small,
/// else by filtering the map's blocks.
fn blocks_in_box(map: &EvidenceMap, lo: CellKey, hi: CellKey) -> Vec<super::key::BlockKey> {
    let (bl, bh) = (lo.block(), hi.block());
    let n = |a: i32, b: i32| (i64::from(b) - i64::from(a) + 1) as u128;
    let range = n(bl.x, bh.x) * n(bl.y, bh.y) * n(bl.z, bh.z);
    if range <= map.block_count() as u128 {
        let mut keys = Vec::new();
        for z in bl.z..=bh.z {
            for y in bl.y..=bh.y {
                for x in bl.x..=bh.x {
                    let k = super::key::BlockKey::new(x, y, z);
                    if map.block(k).is_some() {
                        keys.push(k);
                    }
                }
            }
        }
        keys
    } else {
        map.blocks_unsorted()
            .map(|(k, _)| *k)
            .filter(|k| {
                (bl.x..=bh.x).contains(&k.x) && (bl.y..=bh.y).contains(&k.y) && (bl.z..=bh.z).contains(&k.z)
            })
            .collect()
    }
}

/// Counts of cells with evidence inside a box, per state.
pub fn count_box(cells: &[BoxCell]) -> [usize; 3] {
    let mut n = [0usize; 3];
    for c in cells {
        n[c.estimate.state as usize] += 1;
    }
    n
}

pub use ray::{MAX_RAY_CELLS, RayError, RayHit, StopAt, cast_ray, traverse};

const _: () = assert!(BLOCK_CELLS == 512);

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::core::{Integrator, MapParams};

    /// The built-in room after 4 simulated scans (also used by the ray tests).
    pub(crate) fn room_map() -> EvidenceMap {
        let params = MapParams::default();
        let mut map = EvidenceMap::new(params);
        let (_, scans) = crate::sim::simulate(0, 4, &crate::sim::Lidar::default());
        let mut integ = Integrator::new(params);
        for s in &scans {
            integ.integrate(&mut map, &s.points_world, s.origin, 1);
        }
        map
    }

    #[test]
    fn batched_points_equal_one_point_at_a_time() {
        // 2,000 points (62 full rounds and a partial one) over and around the room: cells with
        // and without evidence, blocks that do not exist, points outside the key range.
        let map = room_map();
        let th = Thresholds::default();
        let mut pts: Vec<[f64; 3]> = (0..1997)
            .map(|i| {
                let t = i as f64;
                [(t * 0.0137) % 12.0 - 1.0, (t * 0.0291) % 9.0 - 1.0, (t * 0.0071) % 3.5 - 0.5]
            })
            .collect();
        pts.extend([[f64::NAN, 0.0, 0.0], [1e12, 0.0, 0.0], [0.0, -1e12, 0.0]]);
        let ans = query_points(&map, &pts, &th);
        assert_eq!(ans.len(), pts.len());
        let mut with_evidence = 0;
        for (p, a) in pts.iter().zip(&ans) {
            let expected = CellKey::from_point(*p, 0.1)
                .map(|cell| PointAnswer { cell, estimate: map.estimate(cell, &th) });
            assert_eq!(*a, expected, "point {p:?}");
            with_evidence += usize::from(a.is_some_and(|a| !a.estimate.evidence.is_empty()));
        }
        assert!(with_evidence > 100 && with_evidence < 1900, "{with_evidence} points with evidence");
    }

    #[test]
    fn point_box_and_ray_queries_agree_with_cell_estimates() {
        let map = room_map();
        let th = Thresholds::default();
        let pts = [[5.0, 2.0, 0.7], [0.05, 5.0, 1.0], [1000.0, 0.0, 0.0], [f64::NAN, 0.0, 0.0]];
        let ans = query_points(&map, &pts, &th);
        assert!(ans[3].is_none());
        for (p, a) in pts.iter().zip(&ans).take(3) {
            let a = a.unwrap();
            assert_eq!(a.cell, CellKey::from_point(*p, 0.1).unwrap());
            assert_eq!(a.estimate, map.estimate(a.cell, &th));
        }
        // The box answer equals the per-cell answers for cells with evidence.
        let q = BoxQuery { min_world: [4.0, 1.0, 0.0], max_world: [5.0, 2.0, 1.0], state: None, coarsen: 0 };
        let cells = query_box(&map, &q, &th, 1_000_000).unwrap();
        assert!(!cells.is_empty());
        for c in &cells {
            assert_eq!(c.estimate, map.estimate(c.min_cell, &th));
        }
        let n_with_evidence = (0..11)
            .flat_map(|z| (10..21).flat_map(move |y| (40..51).map(move |x| CellKey::new(x, y, z))))
            .filter(|c| !map.evidence(*c).is_empty())
            .count();
        assert_eq!(cells.len(), n_with_evidence);
        // Coarsening sums evidence: total mass is preserved.
        let coarse = query_box(&map, &BoxQuery { coarsen: 2, ..q }, &th, 1_000_000).unwrap();
        let sum = |v: &[BoxCell]| v.iter().map(|c| c.estimate.evidence.a).sum::<i64>();
        assert_eq!(sum(&coarse), sum(&cells));
        // Limits.
        assert!(matches!(query_box(&map, &q, &th, 10), Err(BoxError::TooLarge { .. })));
        let bad = BoxQuery { min_world: [1.0, 0.0, 0.0], max_world: [0.0, 1.0, 1.0], ..q };
        assert_eq!(query_box(&map, &bad, &th, 100), Err(BoxError::Malformed));
    }
}
