//! The whole-map reads: the viewer's cells (a box coarsened until it fits the limit, or the
//! blocks changed since a version) and the export (every cell with evidence, sorted by key).
//! Both walk many blocks, so both run off the calling thread.

use super::{MAX_COARSEN, Queries, QueryError};
use crate::core::key::{BLOCK_CELLS, BLOCK_SHIFT};
use crate::core::query::{BoxCell, BoxError, BoxQuery, query_box};
use crate::core::{BlockKey, CellEstimate, CellKey, CellState, EvidenceMap, Thresholds};
use crate::service::Snapshot;
use std::ops::ControlFlow;
use std::sync::Arc;

/// A world box `(min, max)`, metres.
pub type WorldBox = ([f64; 3], [f64; 3]);

/// Why a cells request was refused, beyond what every query checks.
#[derive(Debug)]
pub enum CellsError {
    /// `since` is ahead of the map's version.
    SinceAhead {
        since: u64,
        version: u64,
    },
    /// `since` predates the version the map was opened at, whose block history is not kept.
    SinceForgotten {
        history_from: u64,
    },
    /// With `since`, cubes may not straddle blocks: `coarsen` at most [`BLOCK_SHIFT`].
    CoarsenWithSince,
    Query(QueryError),
}

/// The viewer's cells request.
#[derive(Debug, Clone, Copy)]
pub struct CellsRequest {
    /// Default: every block of the map.
    pub box_world: Option<WorldBox>,
    /// The finest level wanted; raised until the box fits the limit (not with `since`).
    pub coarsen: u32,
    pub state: Option<CellState>,
    pub th: Thresholds,
    /// Only the cells of blocks changed after this version.
    pub since: Option<u64>,
}

/// A validated cells query.
#[derive(Debug)]
pub struct CellsQuery {
    snap: Arc<Snapshot>,
    req: CellsRequest,
    coarsen: u8,
    max_cells: u64,
}

/// The answer of a cells query.
#[derive(Debug)]
pub struct CellsAnswer {
    pub cells: Vec<BoxCell>,
    /// The coarsen level used.
    pub coarsen: u8,
    /// With `since`: every block changed (so a client drops what it held there).
    pub blocks: Vec<BlockKey>,
    /// The lowest and highest block keys of the map (`None`: empty).
    pub extent: Option<(BlockKey, BlockKey)>,
}

impl Queries {
    /// The viewer's cells: `coarsen` and `since` checked against the snapshot.
    pub fn cells(self, req: CellsRequest) -> Result<CellsQuery, CellsError> {
        let coarsen = u8::try_from(req.coarsen)
            .ok()
            .filter(|c| u32::from(*c) <= MAX_COARSEN)
            .ok_or(CellsError::Query(QueryError::Coarsen(req.coarsen)))?;
        if let Some(since) = req.since {
            let snap = &self.snap;
            if since > snap.version {
                return Err(CellsError::SinceAhead { since, version: snap.version });
            }
            if since < snap.history_from {
                return Err(CellsError::SinceForgotten { history_from: snap.history_from });
            }
            if u32::from(coarsen) > BLOCK_SHIFT {
                return Err(CellsError::CoarsenWithSince);
            }
        }
        Ok(CellsQuery { snap: self.snap, req, coarsen, max_cells: self.limits.max_box_cells })
    }

    /// Every cell with evidence, inside the world box `bounds` if given (its cells' keys,
    /// inclusive); no corrupt block may lie under it. A box not finite, outside the key range
    /// or inverted is [`BoxError::Malformed`].
    pub fn export(self, bounds: Option<WorldBox>, th: Thresholds) -> Result<ExportQuery, QueryError> {
        let keys = match bounds {
            None => {
                self.snap.check_whole()?;
                None
            }
            Some((min, max)) => {
                let res = self.snap.map.params().resolution_m;
                match (CellKey::from_point(min, res), CellKey::from_point(max, res)) {
                    (Some(lo), Some(hi)) if lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z => {
                        self.snap.check_cells(lo, hi)?;
                        Some((lo, hi))
                    }
                    _ => return Err(QueryError::Box(BoxError::Malformed)),
                }
            }
        };
        Ok(ExportQuery { snap: self.snap, keys, th })
    }
}

impl CellsQuery {
    pub fn runs_inline(&self) -> bool {
        false
    }

    pub fn version(&self) -> u64 {
        self.snap.version
    }

    pub fn resolution_m(&self) -> f64 {
        self.snap.map.params().resolution_m
    }

    pub fn run(&self) -> Result<CellsAnswer, QueryError> {
        let (cells, coarsen, blocks) = self.select().map_err(QueryError::Box)?;
        Ok(CellsAnswer { cells, coarsen, blocks, extent: block_extent(&self.snap.map) })
    }

    /// The answer's cubes, the coarsen level used and the changed blocks.
    fn select(&self) -> Result<(Vec<BoxCell>, u8, Vec<BlockKey>), BoxError> {
        let (snap, req) = (&self.snap, &self.req);
        let res = snap.map.params().resolution_m;
        if let Some(since) = req.since {
            let mut blocks: Vec<BlockKey> =
                snap.block_versions.iter().filter(|(_, v)| **v > since).map(|(k, _)| *k).collect();
            blocks.sort_unstable();
            let mut cells = Vec::new();
            for k in &blocks {
                let (mut lo, mut hi) = cell_span_world(k.min_cell(), k.cell(BLOCK_CELLS - 1), res);
                if let Some((bmin, bmax)) = req.box_world {
                    lo = [0, 1, 2].map(|i| lo[i].max(bmin[i]));
                    hi = [0, 1, 2].map(|i| hi[i].min(bmax[i]));
                    if (0..3).any(|i| lo[i] > hi[i]) {
                        continue;
                    }
                }
                let q = BoxQuery { min_world: lo, max_world: hi, state: req.state, coarsen: self.coarsen };
                // Each block alone is far under any limit; the limit is for whole boxes.
                cells.extend(query_box(&snap.map, &q, &req.th, u64::MAX)?);
            }
            return Ok((cells, self.coarsen, blocks));
        }
        let (min_world, max_world) = match (req.box_world, block_extent(&snap.map)) {
            (Some(b), _) => b,
            (None, Some((lo, hi))) => cell_span_world(lo.min_cell(), hi.cell(BLOCK_CELLS - 1), res),
            (None, None) => return Ok((Vec::new(), self.coarsen, Vec::new())),
        };
        let mut coarsen = self.coarsen;
        loop {
            let q = BoxQuery { min_world, max_world, state: req.state, coarsen };
            match query_box(&snap.map, &q, &req.th, self.max_cells) {
                Ok(cells) => return Ok((cells, coarsen, Vec::new())),
                Err(BoxError::TooLarge { .. }) if u32::from(coarsen) < MAX_COARSEN => coarsen += 1,
                Err(e) => return Err(e),
            }
        }
    }
}

/// The world box spanning cells `lo..=hi` (their centres, so flooring gives them back).
fn cell_span_world(lo: CellKey, hi: CellKey, res: f64) -> WorldBox {
    (lo.centre(res), hi.centre(res))
}

/// The lowest and highest block keys of the map.
fn block_extent(map: &EvidenceMap) -> Option<(BlockKey, BlockKey)> {
    map.blocks_unsorted().map(|(k, _)| *k).fold(None, |acc, k| {
        let (lo, hi) = acc.unwrap_or((k, k));
        Some((
            BlockKey::new(lo.x.min(k.x), lo.y.min(k.y), lo.z.min(k.z)),
            BlockKey::new(hi.x.max(k.x), hi.y.max(k.y), hi.z.max(k.z)),
        ))
    })
}

/// A validated export.
#[derive(Debug)]
pub struct ExportQuery {
    snap: Arc<Snapshot>,
    keys: Option<(CellKey, CellKey)>,
    th: Thresholds,
}

impl ExportQuery {
    pub fn resolution_m(&self) -> f64 {
        self.snap.map.params().resolution_m
    }

    /// Hands `each` every cell with evidence (inside the bounds) sorted by key, until it
    /// breaks. Blocks come sorted by block key, so all cells of one block-x slab precede the
    /// next slab's: sorting one slab at a time gives the global key order with one slab in
    /// memory.
    pub fn for_each_sorted(&self, mut each: impl FnMut(CellKey, CellEstimate) -> ControlFlow<()>) {
        let map = &self.snap.map;
        let bounds = self.keys;
        let inside = |c: CellKey| {
            bounds.is_none_or(|(lo, hi)| {
                (lo.x..=hi.x).contains(&c.x) && (lo.y..=hi.y).contains(&c.y) && (lo.z..=hi.z).contains(&c.z)
            })
        };
        let block_overlaps = |b: BlockKey| {
            bounds.is_none_or(|(lo, hi)| {
                let (bl, bh) = (lo.block(), hi.block());
                (bl.x..=bh.x).contains(&b.x) && (bl.y..=bh.y).contains(&b.y) && (bl.z..=bh.z).contains(&b.z)
            })
        };
        let keys: Vec<_> = map.block_keys_sorted().into_iter().filter(|k| block_overlaps(*k)).collect();
        let mut slab: Vec<CellKey> = Vec::new();
        for (i, key) in keys.iter().enumerate() {
            if let Some(block) = map.block(*key) {
                for j in 0..BLOCK_CELLS {
                    if !block.get(j).is_empty() {
                        let cell = key.cell(j);
                        if inside(cell) {
                            slab.push(cell);
                        }
                    }
                }
            }
            let slab_ends = keys.get(i + 1).is_none_or(|next| next.x != key.x);
            if !slab_ends {
                continue;
            }
            slab.sort_unstable();
            for cell in slab.drain(..) {
                if each(cell, map.estimate(cell, &self.th)).is_break() {
                    return;
                }
            }
        }
    }
}
