//! A scan's evidence as a delta: [`ScanDelta`], blocks of both sums ([`DeltaBlock`]) with the
//! rows that may hold mass ([`RowMask`]), and how a delta is added to a block or a map.
//!
//! The fast path adds straight into the map's blocks; deltas remain for removing a scan, for
//! kernels too long for the window path, and for edits computed aside from the map.

use crate::core::block::BlockEvidence;
use crate::core::key::{BLOCK_CELLS, BLOCK_EDGE, BlockKey};
use crate::core::map::{EvidenceMap, Slot};
use crate::core::posterior::Evidence;
use std::sync::Arc;

/// One block of a scan's evidence as the scatter writes it: all `a` sums, then all `b` sums, so
/// a window adds into one contiguous row of 8 cells per label.
#[derive(Clone, PartialEq, Eq)]
pub struct DeltaBlock {
    pub a: [i64; BLOCK_CELLS],
    pub b: [i64; BLOCK_CELLS],
}

impl std::fmt::Debug for DeltaBlock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "DeltaBlock {{ cells with evidence: {} }}", self.cells_with_evidence())
    }
}

impl DeltaBlock {
    pub fn zeroed() -> Box<Self> {
        Box::new(Self { a: [0; BLOCK_CELLS], b: [0; BLOCK_CELLS] })
    }

    pub fn is_empty(&self) -> bool {
        self.a.iter().all(|&v| v == 0) && self.b.iter().all(|&v| v == 0)
    }

    pub fn cells_with_evidence(&self) -> usize {
        self.a.iter().zip(&self.b).filter(|(a, b)| **a != 0 || **b != 0).count()
    }

    /// `self += other` on the rows of `rows` (rows whose bit is clear must be zero in `other`).
    pub fn add_rows(&mut self, other: &DeltaBlock, rows: RowMask) {
        for (label, (dst, src)) in [(&mut self.a, &other.a), (&mut self.b, &other.b)].into_iter().enumerate()
        {
            for r in row_ranges(rows[label]) {
                dst[r.clone()].iter_mut().zip(&src[r]).for_each(|(x, y)| *x += y);
            }
        }
    }

    /// Zeroes the rows of `rows` (every other row must already be zero).
    pub fn clear_rows(&mut self, rows: RowMask) {
        if rows == ALL_ROWS {
            self.a.fill(0);
            self.b.fill(0);
            return;
        }
        for (label, cells) in [&mut self.a, &mut self.b].into_iter().enumerate() {
            for r in row_ranges(rows[label]) {
                cells[r].fill(0);
            }
        }
    }
}

/// Cells per block row (one x run at fixed y, z).
const ROW: usize = BLOCK_EDGE as usize;
/// Which rows of a block's `a` (`[0]`) and `b` (`[1]`) may hold evidence: bit `r` for the cells
/// `8r..8r + 8`, row `r = 8z + y`.
pub type RowMask = [u64; 2];
/// Every row.
pub const ALL_ROWS: RowMask = [u64::MAX; 2];
const _: () = assert!(BLOCK_CELLS / ROW == 64, "a row mask is one bit per row of a block");

/// The cell ranges of the rows whose bits are set in `mask` (one half of a [`RowMask`]), in
/// increasing order.
fn row_ranges(mut mask: u64) -> impl Iterator<Item = std::ops::Range<usize>> {
    std::iter::from_fn(move || {
        (mask != 0).then(|| {
            let r = mask.trailing_zeros() as usize * ROW;
            mask &= mask - 1;
            r..r + ROW
        })
    })
}

/// The evidence one scan adds: blocks sorted by key.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScanDelta {
    pub blocks: Vec<(BlockKey, Box<DeltaBlock>)>,
    /// Per block, the rows that may hold evidence (all others are zero), so adding a sparse
    /// delta touches only those; empty means every row.
    pub rows: Vec<RowMask>,
}

impl ScanDelta {
    /// Block `i`'s row mask ([`ALL_ROWS`] when none is kept).
    pub fn rows_of(&self, i: usize) -> RowMask {
        self.rows.get(i).copied().unwrap_or(ALL_ROWS)
    }

    /// Blocks with their row masks.
    pub fn iter(&self) -> impl Iterator<Item = (BlockKey, &DeltaBlock, RowMask)> {
        self.blocks.iter().enumerate().map(|(i, (k, b))| (*k, &**b, self.rows_of(i)))
    }

    /// Number of training-point / cell pairs is not kept; this counts cells with evidence.
    pub fn cells_with_evidence(&self) -> usize {
        self.blocks.iter().map(|(_, b)| b.cells_with_evidence()).sum()
    }

    /// Sums several deltas (e.g. per-thread partial results) into one, sorted by block key.
    pub fn sum(parts: Vec<ScanDelta>) -> ScanDelta {
        let mut all: Vec<(BlockKey, Box<DeltaBlock>, RowMask)> = Vec::new();
        for d in parts {
            let rows: Vec<RowMask> = (0..d.blocks.len()).map(|i| d.rows_of(i)).collect();
            all.extend(d.blocks.into_iter().zip(rows).map(|((k, b), r)| (k, b, r)));
        }
        all.sort_by_key(|(k, _, _)| *k);
        let mut out = ScanDelta::default();
        for (k, b, r) in all {
            match (out.blocks.last_mut(), out.rows.last_mut()) {
                (Some((lk, lb)), Some(lr)) if *lk == k => {
                    lb.add_rows(&b, r);
                    *lr = [lr[0] | r[0], lr[1] | r[1]];
                }
                _ => {
                    out.blocks.push((k, b));
                    out.rows.push(r);
                }
            }
        }
        out
    }
}

impl BlockEvidence {
    /// `self += d` (`sign` ≥ 0) or `self -= d` (`sign` < 0) on the rows of `rows` (see
    /// [`ScanDelta::rows`]): rows whose bit is clear must be zero in `d`. A narrow block takes
    /// only deltas without `a` rows ([`Self::make_mut`] widens it).
    pub fn add_delta(&mut self, d: &DeltaBlock, sign: i64, rows: RowMask) {
        fn add(dst: &mut [i64], src: &[i64], sign: i64) {
            if sign >= 0 {
                dst.iter_mut().zip(src).for_each(|(x, y)| *x += y);
            } else {
                dst.iter_mut().zip(src).for_each(|(x, y)| *x -= y);
            }
        }
        if !self.is_wide() {
            assert_eq!(rows[0], 0, "hit mass added to a narrow block");
            for r in row_ranges(rows[1]) {
                add(&mut self.words_mut()[r.clone()], &d.b[r], sign);
            }
            return;
        }
        let add_pairs = |dst: &mut [Evidence], a: &[i64], b: &[i64]| {
            let cells = dst.iter_mut().zip(a.iter().zip(b));
            if sign >= 0 {
                cells.for_each(|(e, (a, b))| {
                    e.a += a;
                    e.b += b;
                });
            } else {
                cells.for_each(|(e, (a, b))| {
                    e.a -= a;
                    e.b -= b;
                });
            }
        };
        let cells = self.pairs_mut();
        if rows == ALL_ROWS {
            return add_pairs(cells, &d.a, &d.b);
        }
        for r in row_ranges(rows[0] | rows[1]) {
            add_pairs(&mut cells[r.clone()], &d.a[r.clone()], &d.b[r]);
        }
    }
}

impl EvidenceMap {
    /// Adds (`sign` = 1) or removes (`sign` = −1) a scan's evidence. Blocks left without any
    /// evidence are dropped, so removing a scan restores the map exactly.
    pub fn apply(&mut self, delta: &ScanDelta, sign: i64) {
        for (key, d, rows) in delta.iter() {
            self.changes.note(key);
            let wide = rows[0] != 0;
            let blk = self.blocks.get_or_insert_with(key, || Slot::zeroed(wide)).block_mut(wide);
            blk.add_delta(d, sign, rows);
            if sign < 0 && blk.is_empty() {
                self.blocks.remove(&key);
            }
        }
    }

    /// The blocks a delta would produce, without changing the map: `(key, new block)`, `None`
    /// where the block would be left without evidence. Apply them with [`Self::set_blocks`].
    pub fn blocks_after(&self, delta: &ScanDelta, sign: i64) -> Vec<(BlockKey, Option<Arc<BlockEvidence>>)> {
        delta
            .iter()
            .map(|(key, d, rows)| {
                // Wide from the start when the delta brings hit mass.
                let wide = rows[0] != 0;
                let mut b = match self.blocks.get(&key) {
                    Some(old) => old.block.to_box_widened(wide),
                    None if wide => BlockEvidence::zeroed_wide(),
                    None => BlockEvidence::zeroed(),
                };
                b.add_delta(d, sign, rows);
                (key, (!b.is_empty()).then(|| Arc::from(b)))
            })
            .collect()
    }
}
