//! Point, box and ray queries over an [`EvidenceMap`], all in-process and read-only; this module
//! holds the point queries, [`boxes`] and [`ray`] the others. Queries read the data model only.
//!
//! Geometric arguments are world-frame metres. Answers name the cell they came from.

use super::block::BlockEvidence;
use super::key::{BLOCK_CELLS, BlockKey, CellKey};
use super::map::EvidenceMap;
use super::params::Thresholds;
use super::posterior::{CellEstimate, Evidence, alpha_beta, mean_variance};

pub mod boxes;
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

pub use boxes::{BoxCell, BoxError, BoxQuery, count_box, query_box};
pub use ray::{MAX_RAY_CELLS, RayError, RayHit, StopAt, cast_ray, traverse};

const _: () = assert!(BLOCK_CELLS == 512);

#[cfg(test)]
pub(crate) mod tests;
