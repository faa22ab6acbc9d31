//! Box queries: the cells with evidence inside an axis-aligned world box, optionally
//! coarsened into cubes, and their counts per state. Read the model only.

use crate::core::key::{BlockKey, CellKey};
use crate::core::map::EvidenceMap;
use crate::core::params::Thresholds;
use crate::core::posterior::{CellEstimate, CellState, Evidence};

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
fn blocks_in_box(map: &EvidenceMap, lo: CellKey, hi: CellKey) -> Vec<BlockKey> {
    let (bl, bh) = (lo.block(), hi.block());
    let n = |a: i32, b: i32| (i64::from(b) - i64::from(a) + 1) as u128;
    let range = n(bl.x, bh.x) * n(bl.y, bh.y) * n(bl.z, bh.z);
    if range <= map.block_count() as u128 {
        let mut keys = Vec::new();
        for z in bl.z..=bh.z {
            for y in bl.y..=bh.y {
                for x in bl.x..=bh.x {
                    let k = BlockKey::new(x, y, z);
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
