//! Folding a bucket's brick of window sums into blocks: the [`FoldTarget`]s (a scan's delta
//! blocks or a map's own), and the row-by-row tests of which brick rows carry mass.

use super::{B, NO_SLOT, SlotGrid};
use crate::core::block::{BlockEvidence, TakenBlock};
use crate::core::integrate::delta::{DeltaBlock, RowMask};
use crate::core::integrate::sink::BlockSink;
use crate::core::integrate::window::{Brick, S, SB};
use crate::core::key::BlockKey;

/// Where a folded brick's rows go: the blocks of a per-scan delta, or a map's own blocks.
pub(super) trait FoldTarget {
    type Block<'a>: FoldBlock
    where
        Self: 'a;
    /// The block at key `b`, taken or allocated on first use; `hits` when the rows to come
    /// may hold hit mass.
    fn block(&mut self, b: [i32; 3], hits: bool) -> Self::Block<'_>;
}

/// One block of a [`FoldTarget`], open for adding rows.
pub(super) trait FoldBlock {
    /// Adds the hit mass `a` and the free mass `b` to row `row` (`8z + y`) from cell `x` on,
    /// and zeroes both.
    fn add_row<const N: usize>(&mut self, row: usize, x: usize, a: &mut [u32; N], b: &mut [u32; N]);
    /// As [`Self::add_row`] for a row whose hit mass is zero: adds and zeroes `b` only.
    fn add_free_row<const N: usize>(&mut self, row: usize, x: usize, b: &mut [u32; N]);
}

/// Folds into the scatter's delta blocks.
pub(super) struct DeltaTarget<'a> {
    pub(super) delta: &'a mut SlotGrid,
    pub(super) spare: &'a mut Vec<Box<DeltaBlock>>,
}

/// A delta block and its row mask.
pub(super) struct DeltaRows<'a> {
    block: &'a mut DeltaBlock,
    rows: &'a mut RowMask,
}

impl FoldTarget for DeltaTarget<'_> {
    type Block<'a>
        = DeltaRows<'a>
    where
        Self: 'a;

    #[inline(always)]
    fn block(&mut self, b: [i32; 3], _hits: bool) -> DeltaRows<'_> {
        let i = self.delta.block_index(b, self.spare) as usize;
        DeltaRows { block: &mut self.delta.blocks[i].1, rows: &mut self.delta.rows[i] }
    }
}

impl DeltaRows<'_> {
    /// Adds `src` to label `label`'s row `row` from cell `x` on and zeroes it.
    #[inline(always)]
    fn add_label_row<const N: usize>(&mut self, label: usize, row: usize, x: usize, src: &mut [u32; N]) {
        if src.iter().any(|&v| v != 0) {
            self.rows[label] |= 1 << row;
            let at = row * B as usize + x;
            let dst = if label == 0 { &mut self.block.a } else { &mut self.block.b };
            for (d, s) in dst[at..at + N].iter_mut().zip(src.iter_mut()) {
                *d += i64::from(*s);
                *s = 0;
            }
        }
    }
}

impl FoldBlock for DeltaRows<'_> {
    #[inline(always)]
    fn add_row<const N: usize>(&mut self, row: usize, x: usize, a: &mut [u32; N], b: &mut [u32; N]) {
        self.add_label_row(0, row, x, a);
        self.add_label_row(1, row, x, b);
    }

    #[inline(always)]
    fn add_free_row<const N: usize>(&mut self, row: usize, x: usize, b: &mut [u32; N]) {
        self.add_label_row(1, row, x, b);
    }
}

/// Folds straight into the blocks of a [`BlockSink`], each taken out once per tile.
pub(super) struct SinkTarget<'a, S: BlockSink + ?Sized> {
    pub(super) slots: &'a mut SlotGrid,
    pub(super) taken: &'a mut Vec<(BlockKey, TakenBlock)>,
    pub(super) sink: &'a mut S,
}

impl<S: BlockSink + ?Sized> FoldTarget for SinkTarget<'_, S> {
    type Block<'a>
        = &'a mut BlockEvidence
    where
        Self: 'a;

    #[inline(always)]
    fn block(&mut self, b: [i32; 3], hits: bool) -> &mut BlockEvidence {
        let s = self.slots.index(b);
        if self.slots.slots[s] == NO_SLOT {
            self.slots.slots[s] = self.taken.len() as u32;
            let key = BlockKey::new(b[0], b[1], b[2]);
            self.taken.push((key, TakenBlock::new(self.sink.take_block(key, hits))));
        }
        // Copies the block first only if a snapshot shares it, widens it if hit mass comes to
        // a narrow one.
        self.taken[self.slots.slots[s] as usize].1.get(hits)
    }
}

impl FoldBlock for &mut BlockEvidence {
    #[inline(always)]
    fn add_row<const N: usize>(&mut self, row: usize, x: usize, a: &mut [u32; N], b: &mut [u32; N]) {
        self.fold_row(row * B as usize + x, a, b);
    }

    #[inline(always)]
    fn add_free_row<const N: usize>(&mut self, row: usize, x: usize, b: &mut [u32; N]) {
        self.fold_free_row(row * B as usize + x, b);
    }
}

/// Adds the touched regions of the brick into the blocks around `block` (the bucket's) in
/// `target`, zeroing them.
pub(super) fn fold_brick(brick: &mut Brick, block: [i32; 3], target: &mut impl FoldTarget) {
    // The margin is 1 to 3 cells for every width the window path compiles (`window_shape`);
    // a margin and edge known at compile time make every row a fixed-length vector operation.
    match brick.margin() {
        1 => fold_brick_with::<1, { SB + 2 }>(brick, block, target),
        2 => fold_brick_with::<2, { SB + 4 }>(brick, block, target),
        3 => fold_brick_with::<3, { SB + 6 }>(brick, block, target),
        m => unreachable!("brick margin {m} outside 1..=3"),
    }
}

/// Folds a brick of margin `M` and edge `E = S·B + 2M` whose first block is `block`, by rows
/// of regions: the regions that share a y and a z range (along x the low margin, the `S`
/// blocks and the high margin) are tested together, one brick row of `E` cells at a time
/// (when no margin of them was touched, just the blocks' cells), and then each x region's rows
/// with mass are folded into its block. Testing a row's parts in one pass, not region by
/// region, matters because the margins' rows are two cells wide: testing them on their own
/// costs as much as testing the block's.
///
/// Rows no hit window reached (half the blocks of an outdoor drive see free mass only) are
/// tested on their `b` cells and folded as free rows, `a` neither read, added nor zeroed.
fn fold_brick_with<const M: usize, const E: usize>(
    brick: &mut Brick,
    block: [i32; 3],
    target: &mut impl FoldTarget,
) {
    const R: usize = S + 2;
    let b = B as usize;
    debug_assert_eq!((brick.edge(), E), (SB + 2 * M, SB + 2 * M));
    // Per region along an axis: (first brick cell, first target cell, length).
    let span = |r: usize| match r {
        0 => (0, b - M, M),
        r if r <= S => (M + (r - 1) * b, 0, b),
        _ => (M + SB, 0, M),
    };
    let touched = brick.touched[0] | brick.touched[1];
    let hit_touched = brick.touched[0];
    let (cells_a, cells_b) = (&mut brick.a[..], &mut brick.b[..]);
    for rz in 0..R {
        for ry in 0..R {
            let xs = touched >> (R * (ry + R * rz)) & ((1 << R) - 1);
            if xs == 0 {
                continue;
            }
            let (y, z) = (span(ry), span(rz));
            let at = |zi: usize, yi: usize| ((z.0 + zi) * E + y.0 + yi) * E;
            // Rows with mass per x region, bit 8z + y (a region is at most 8 × 8 rows). Where no
            // hit window touched the regions of these rows, their `a` cells are all zero and
            // only the `b` cells are read.
            let hits = hit_touched >> (R * (ry + R * rz));
            let rows = if hits & ((1 << R) - 1) == 0 {
                rows_with_mass::<M, E, false>(cells_a, cells_b, xs, y, z, at)
            } else {
                rows_with_mass::<M, E, true>(cells_a, cells_b, xs, y, z, at)
            };
            // Per x region, its block's key and whether a hit window touched the region (else
            // its `a` cells are zero, and the block may stay narrow).
            let key =
                |rx: usize| ([0, 1, 2].map(|i| block[i] + [rx, ry, rz][i] as i32 - 1), hits >> rx & 1 != 0);
            let rows_of = (y, z, at);
            fold_rows::<M>(cells_a, cells_b, rows[0], (0, b - M), rows_of, key(0), target);
            for rx in 1..=S {
                fold_rows::<8>(cells_a, cells_b, rows[rx], (M + (rx - 1) * b, 0), rows_of, key(rx), target);
            }
            fold_rows::<M>(cells_a, cells_b, rows[R - 1], (M + SB, 0), rows_of, key(R - 1), target);
        }
    }
    brick.folded();
}

/// Per x region of a fold's rows `y`, `z` (the region spans along y and z, their rows
/// starting at brick index `at(z, y)`; `xs` the x regions touched), the rows with mass: bit
/// `8z + y` of entry `rx`. With `HITS` false the `a` cells are known to be zero and are not
/// read.
#[inline(always)]
fn rows_with_mass<const M: usize, const E: usize, const HITS: bool>(
    cells_a: &[u32],
    cells_b: &[u32],
    xs: u64,
    y: (usize, usize, usize),
    z: (usize, usize, usize),
    at: impl Fn(usize, usize) -> usize,
) -> [u64; S + 2] {
    const R: usize = S + 2;
    let b = B as usize;
    let mut rows = [0u64; R];
    // Every row lies before the last one's end: checked once here, which spares the
    // rows most of their own bounds checks.
    let end = at(z.2 - 1, y.2 - 1) + E;
    let (ca, cb) = (&cells_a[..end], &cells_b[..end]);
    let margins = 1 | 1 << (R - 1);
    let any = |cells: &[u32]| u64::from(cells.iter().fold(0, |acc, &v| acc | v) != 0);
    for zi in 0..z.2 {
        for yi in 0..y.2 {
            let i = at(zi, yi);
            let bit = zi * 8 + yi;
            if xs & margins == 0 {
                let rb: &[u32; SB] = cb[i + M..i + M + SB].try_into().expect("S·B cells");
                let or: [u32; SB] = if HITS {
                    let ra: &[u32; SB] = ca[i + M..i + M + SB].try_into().expect("S·B cells");
                    std::array::from_fn(|k| ra[k] | rb[k])
                } else {
                    *rb
                };
                for (r, cells) in rows[1..=S].iter_mut().zip(or.chunks_exact(b)) {
                    *r |= any(cells) << bit;
                }
            } else {
                let rb: &[u32; E] = cb[i..i + E].try_into().expect("E cells");
                let or: [u32; E] = if HITS {
                    let ra: &[u32; E] = ca[i..i + E].try_into().expect("E cells");
                    std::array::from_fn(|k| ra[k] | rb[k])
                } else {
                    *rb
                };
                rows[0] |= any(&or[..M]) << bit;
                for (r, cells) in rows[1..=S].iter_mut().zip(or[M..M + SB].chunks_exact(b)) {
                    *r |= any(cells) << bit;
                }
                rows[R - 1] |= any(&or[M + SB..]) << bit;
            }
        }
    }
    rows
}

/// Folds the brick rows in `rows` (bit 8z + y of the region's rows `y`, `z`, which start at
/// brick index `at(z, y)`) — `N` cells each from brick cell `x.0`, to cell `x.1` of the
/// target's rows — into block `key` of `target`, zeroing them. The block is taken only if
/// some row has mass.
#[inline(always)]
fn fold_rows<const N: usize>(
    a: &mut [u32],
    b: &mut [u32],
    mut rows: u64,
    x: (usize, usize),
    (y, z, at): ((usize, usize, usize), (usize, usize, usize), impl Fn(usize, usize) -> usize),
    (key, hits): ([i32; 3], bool),
    target: &mut impl FoldTarget,
) {
    if rows == 0 {
        return;
    }
    let mut dst = target.block(key, hits);
    while rows != 0 {
        let r = rows.trailing_zeros() as usize;
        rows &= rows - 1;
        let (zi, yi) = (r >> 3, r & 7);
        let i = at(zi, yi) + x.0;
        let rb: &mut [u32; N] = (&mut b[i..i + N]).try_into().expect("N cells");
        let row = (z.1 + zi) * B as usize + y.1 + yi;
        if hits {
            let ra: &mut [u32; N] = (&mut a[i..i + N]).try_into().expect("N cells");
            dst.add_row(row, x.1, ra, rb);
        } else {
            dst.add_free_row(row, x.1, rb);
        }
    }
}
