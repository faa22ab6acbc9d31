//! Training points → per-cell evidence (the exact kernel sum of algorithm.md §5).
//!
//! Every cell centre within `ell` of a training point receives that point's quantised unit
//! kernel mass ([`KernelTable::quantized`]): hits add to `A`, free samples to `B`. Sums are
//! `i64` fixed-point with [`FIXED_SHIFT`](super::integrate::kernel::FIXED_SHIFT) fractional bits, so they
//! are associative: any scan order, thread count or merge order gives identical bits.
//!
//! The fast path scatters: each training point visits the lattice cells of its support ball and
//! adds into a dense per-scan block accumulator (a slot grid over the scan's block bounding box,
//! no hashing per cell). [`brute_force_cell`] is the gather-side reference used by tests.

use super::integrate::kernel::{COORD_SHIFT, KernelTable, TABLE_INTERVALS};
use super::key::{BLOCK_CELLS, BLOCK_EDGE, BlockKey, CellKey};
use super::map::probability_variance;
use super::params::{MapParams, Thresholds};
use super::integrate::training::TrainingSet;
use std::sync::Arc;

/// The raw evidence of one cell: occupied mass `a` and free mass `b` (fixed-point, unit kernel).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[repr(C)]
pub struct Evidence {
    pub a: i64,
    pub b: i64,
}

impl Evidence {
    pub fn is_empty(self) -> bool {
        self.a == 0 && self.b == 0
    }
}

/// The largest probability and variance over all cells of a block (cells without evidence
/// count with the prior's). Ray walks use it to pass whole blocks where no cell can stop them
/// without reading any cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockSummary {
    /// `+∞` when some cell's probability or variance is not a number.
    pub max_probability: f64,
    pub max_variance: f64,
}

impl BlockSummary {
    /// The summary of `block` under `params` (the map's).
    pub fn of(block: &BlockEvidence, params: &MapParams) -> Self {
        let (mut max_p, mut max_var) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
        for e in block.cells() {
            let (p, var) = probability_variance(e, params);
            if p.is_nan() || var.is_nan() {
                (max_p, max_var) = (f64::INFINITY, f64::INFINITY);
                break;
            }
            max_p = max_p.max(p);
            max_var = max_var.max(var);
        }
        Self { max_probability: max_p, max_variance: max_var }
    }

    /// True when no cell of the block can be occupied under `th` (none has p > `p_occ`).
    pub fn none_occupied(&self, th: &Thresholds) -> bool {
        self.max_probability <= th.p_occ
    }

    /// True when every cell of the block is free under `th`.
    pub fn all_free(&self, th: &Thresholds) -> bool {
        self.max_probability < th.p_free && self.max_variance < th.var_max
    }
}

/// Evidence of one map block, in one of two layouts chosen by what the block holds:
///
/// - **wide** (8 KiB): each cell's two sums side by side, `a b a b …`. A reader of one cell
///   touches one cache line (a cell is 16 bytes at a multiple of 16, so no cell straddles two
///   64-byte lines), which is what point and ray queries over maps far larger than the caches
///   wait on.
/// - **narrow** (4 KiB): only the free sums, `b b …`, for a block no hit has reached, whose `a`
///   are all zero. Most of the space a range sensor sweeps is such blocks, far from any surface:
///   half the blocks of the simulated outdoor drive, a quarter of the room's.
///
/// The layout is storage only: equality, the store's encoding and every answer depend on the
/// cells' values alone. A narrow block is widened when the first hit mass reaches it; a block
/// read from the store is narrow whenever it can be.
///
/// A dynamically sized type (the slice's length is the layout), so always behind a pointer:
/// `Arc<BlockEvidence>` in maps (copied on write, see [`BlockEvidence::make_mut`]) and
/// `Box<BlockEvidence>` when loaded. Both come from `malloc`, whose blocks are 16-byte aligned,
/// and the slice starts 0 (box) or 16 (arc, after its two counters) bytes in, so each wide cell
/// sits at a multiple of 16. The zeroed blocks come from `calloc`, which hands out memory fresh
/// from the system without writing zeros over it again.
#[repr(transparent)]
pub struct BlockEvidence {
    data: [i64],
}

/// Words of a wide block.
const WIDE: usize = 2 * BLOCK_CELLS;

impl std::fmt::Debug for BlockEvidence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let layout = if self.is_wide() { "wide" } else { "narrow" };
        write!(f, "BlockEvidence {{ {layout}, cells with evidence: {} }}", self.cells_with_evidence())
    }
}

/// Equal when every cell holds the same evidence, whatever the two layouts.
impl PartialEq for BlockEvidence {
    fn eq(&self, other: &Self) -> bool {
        if self.is_wide() == other.is_wide() {
            self.data == other.data
        } else {
            (0..BLOCK_CELLS).all(|i| self.get(i) == other.get(i))
        }
    }
}

impl Eq for BlockEvidence {}

// The one place blocks are made from their words: each cast keeps the slice's length (the
// layout), and `BlockEvidence` is a transparent wrapper of that slice.
#[allow(unsafe_code)]
impl BlockEvidence {
    /// A shared block without evidence, `wide` or narrow, allocated zeroed (`calloc`):
    /// `Arc::new` of a zero block built it and then copied it into the heap, where the
    /// allocator can hand out memory it knows is zero and skip both passes. Writing a new
    /// block's first rows instead of adding to zeros would win nothing: the fold loads those
    /// lines next either way.
    pub fn zeroed_arc(wide: bool) -> Arc<Self> {
        let len = if wide { WIDE } else { BLOCK_CELLS };
        // SAFETY: all-zero bytes are a valid `i64` (0).
        let words: Arc<[i64]> = unsafe { Arc::<[i64]>::new_zeroed_slice(len).assume_init() };
        // SAFETY: `Self` is `repr(transparent)` over `[i64]`, so the pointer (with its length)
        // points at a valid `Self` in the same allocation.
        unsafe { Arc::from_raw(Arc::into_raw(words) as *const Self) }
    }

    fn from_words_box(words: Box<[i64]>) -> Box<Self> {
        debug_assert!(words.len() == WIDE || words.len() == BLOCK_CELLS);
        // SAFETY: as in `zeroed_arc`.
        unsafe { Box::from_raw(Box::into_raw(words) as *mut Self) }
    }

    fn from_words_arc(words: Arc<[i64]>) -> Arc<Self> {
        debug_assert!(words.len() == WIDE || words.len() == BLOCK_CELLS);
        // SAFETY: as in `zeroed_arc`.
        unsafe { Arc::from_raw(Arc::into_raw(words) as *const Self) }
    }

    /// Cell `i`'s first word and the layout (1 wide, 0 narrow): `i << 1` wide, `i` narrow.
    #[inline(always)]
    fn word_of(&self, i: usize) -> (usize, usize) {
        assert!(i < BLOCK_CELLS, "cell {i} of a block of {BLOCK_CELLS}");
        let wide = usize::from(self.is_wide());
        (i << wide, wide)
    }

    #[inline(always)]
    fn word(&self, at: usize) -> &i64 {
        debug_assert!(at < self.data.len());
        // SAFETY: `at` comes from `word_of` (i < BLOCK_CELLS), so it is below the length of
        // either layout: `i` < BLOCK_CELLS narrow, `2i` < 2 · BLOCK_CELLS wide.
        unsafe { self.data.get_unchecked(at) }
    }

    /// The words at `at` and `at + wide` (`at` from `word_of`): a wide cell's two sums, or a
    /// narrow cell's `b` twice. Point and ray queries read cells here, without bounds checks.
    #[inline(always)]
    fn two_words(&self, at: usize, wide: usize) -> (i64, i64) {
        debug_assert!(at + wide < self.data.len());
        // SAFETY: as in `word`; wide, `2i + 1` < 2 · BLOCK_CELLS too.
        unsafe { (*self.data.get_unchecked(at), *self.data.get_unchecked(at + wide)) }
    }

    /// A wide block's cells.
    fn pairs(&self) -> &[Evidence; BLOCK_CELLS] {
        assert!(self.is_wide());
        // SAFETY: `Evidence` is two `i64` (`repr(C)`, alignment 8), and a wide block is
        // `2 · BLOCK_CELLS` of them.
        unsafe { &*self.data.as_ptr().cast::<[Evidence; BLOCK_CELLS]>() }
    }

    fn pairs_mut(&mut self) -> &mut [Evidence; BLOCK_CELLS] {
        assert!(self.is_wide());
        // SAFETY: as in `pairs`, and `self` is borrowed mutably.
        unsafe { &mut *self.data.as_mut_ptr().cast::<[Evidence; BLOCK_CELLS]>() }
    }
}

impl BlockEvidence {
    /// A narrow block without evidence.
    pub fn zeroed() -> Box<Self> {
        Self::from_words_box(vec![0; BLOCK_CELLS].into_boxed_slice())
    }

    /// A wide block without evidence.
    pub fn zeroed_wide() -> Box<Self> {
        Self::from_words_box(vec![0; WIDE].into_boxed_slice())
    }

    /// A copy of the block in the same layout.
    pub fn to_box(&self) -> Box<Self> {
        Self::from_words_box(self.data.into())
    }

    /// A copy of the block, in the wide layout if `wide` (one copy, where copying and then
    /// widening would make two).
    pub fn to_box_widened(&self, wide: bool) -> Box<Self> {
        if wide && !self.is_wide() {
            Self::from_words_box(self.widened_words().into_boxed_slice())
        } else {
            self.to_box()
        }
    }

    /// True when the block keeps both sums per cell (see the type's docs); false when every
    /// `a` is zero and only the `b` are kept.
    #[inline(always)]
    pub fn is_wide(&self) -> bool {
        self.data.len() == WIDE
    }

    /// Bytes the block's cells take (its layout's).
    pub fn data_bytes(&self) -> usize {
        std::mem::size_of_val(&self.data)
    }

    /// Cell `i` (local index, [`CellKey::index_in_block`]), without a branch on the layout.
    #[inline(always)]
    pub fn get(&self, i: usize) -> Evidence {
        let (at, wide) = self.word_of(i);
        // Wide: `a` at `2i`, `b` after it. Narrow: `b` at `i`, and `a` is zero (the word at `i`
        // read and masked off).
        let (a, b) = self.two_words(at, wide);
        Evidence { a: a & -(wide as i64), b }
    }

    /// The first word of cell `i`, e.g. to prefetch it.
    #[inline(always)]
    pub fn cell(&self, i: usize) -> &i64 {
        let (at, _) = self.word_of(i);
        self.word(at)
    }

    /// Every cell, by local index.
    pub fn cells(&self) -> impl Iterator<Item = Evidence> + '_ {
        (0..BLOCK_CELLS).map(|i| self.get(i))
    }

    /// Sets cell `i`. A narrow block takes only `a` = 0 (widen it first: [`Self::widen_box`]).
    pub fn set(&mut self, i: usize, e: Evidence) {
        if self.is_wide() {
            self.pairs_mut()[i] = e;
        } else {
            assert_eq!(e.a, 0, "hit mass set in a narrow block");
            self.data[i] = e.b;
        }
    }

    pub fn is_empty(&self) -> bool {
        self.data.iter().all(|&v| v == 0)
    }

    pub fn cells_with_evidence(&self) -> usize {
        if self.is_wide() {
            self.pairs().iter().filter(|e| !e.is_empty()).count()
        } else {
            self.data.iter().filter(|&&b| b != 0).count()
        }
    }

    /// The same cells in the wide layout (a copy; a new allocation).
    fn widened_words(&self) -> Vec<i64> {
        if self.is_wide() {
            return self.data.to_vec();
        }
        let mut w = vec![0; WIDE];
        for (pair, &b) in w.chunks_exact_mut(2).zip(&self.data) {
            pair[1] = b;
        }
        w
    }

    /// Makes `block` wide (in place if it is already).
    pub fn widen_box(block: &mut Box<Self>) {
        if !block.is_wide() {
            *block = block.to_box_widened(true);
        }
    }

    /// `block` narrow when every `a` is zero (a copy), else as it is.
    pub fn narrowed(block: Box<Self>) -> Box<Self> {
        if !block.is_wide() || block.pairs().iter().any(|e| e.a != 0) {
            return block;
        }
        Self::from_words_box(block.pairs().iter().map(|e| e.b).collect())
    }

    /// The block, to change it: copied first if another holder (a snapshot) shares it, and
    /// widened first if `wide` and it is narrow (the caller is about to add hit mass).
    ///
    /// One atomic read-modify-write when the block is already the caller's alone (the fold
    /// calls this once per block region of every brick): asking `Arc::get_mut` a second time
    /// after a first test nearly doubles its cost.
    #[allow(unsafe_code)]
    pub fn make_mut(block: &mut Arc<Self>, wide: bool) -> &mut Self {
        if wide && !block.is_wide() {
            *block = Self::from_words_arc(block.widened_words().into());
        } else if let Some(unique) = Arc::get_mut(block).map(|b| b as *mut Self) {
            // SAFETY: `unique` is the block `Arc::get_mut` just lent out of `block`, returned
            // with `block`'s own mutable borrow, so nothing else can reach it while it lives.
            // (Returning `Arc::get_mut`'s reference itself on this branch is refused only
            // because `block` is replaced on the other: NLL's "problem case 3".)
            return unsafe { &mut *unique };
        } else {
            *block = Self::from_words_arc(block.data.into());
        }
        Arc::get_mut(block).expect("a block just copied has one holder")
    }

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
                add(&mut self.data[r.clone()], &d.b[r], sign);
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

    /// Adds the brick rows `a` (hit mass) and `b` (free mass) to the cells `at..at + N` and
    /// zeroes them; `a` must be zero if the block is narrow. Brick masses are never negative
    /// (sums of kernel values), so they are `u32` and widen with zeros, which baseline x86-64
    /// does in one instruction where sign extension takes several.
    #[inline(always)]
    pub(crate) fn fold_row<const N: usize>(&mut self, at: usize, a: &mut [u32; N], b: &mut [u32; N]) {
        if self.is_wide() {
            let dst: &mut [Evidence; N] = (&mut self.pairs_mut()[at..at + N]).try_into().expect("N cells");
            for i in 0..N {
                dst[i].a += i64::from(a[i]);
                dst[i].b += i64::from(b[i]);
            }
        } else {
            debug_assert!(a.iter().all(|&v| v == 0), "hit mass folded into a narrow block");
            let dst: &mut [i64; N] = (&mut self.data[at..at + N]).try_into().expect("N cells");
            for i in 0..N {
                dst[i] += i64::from(b[i]);
            }
        }
        (*a, *b) = ([0; N], [0; N]);
    }

    /// As [`Self::fold_row`] for a row without hit mass (its `a` all zero): adds and zeroes the
    /// free mass `b` only, so a wide block's `a` words are left as they are.
    #[inline(always)]
    pub(crate) fn fold_free_row<const N: usize>(&mut self, at: usize, b: &mut [u32; N]) {
        if self.is_wide() {
            let dst: &mut [Evidence; N] = (&mut self.pairs_mut()[at..at + N]).try_into().expect("N cells");
            for i in 0..N {
                dst[i].b += i64::from(b[i]);
            }
        } else {
            let dst: &mut [i64; N] = (&mut self.data[at..at + N]).try_into().expect("N cells");
            for i in 0..N {
                dst[i] += i64::from(b[i]);
            }
        }
        *b = [0; N];
    }

    /// `self += other` (`sign` ≥ 0) or `self -= other` (`sign` < 0). `self` must be wide if
    /// `other` is.
    pub fn add_scaled(&mut self, other: &BlockEvidence, sign: i64) {
        assert!(self.is_wide() || !other.is_wide(), "a wide block added into a narrow one");
        // Plain loops (no multiply) so the compiler vectorises them.
        fn add<'a>(pairs: impl Iterator<Item = (&'a mut i64, &'a i64)>, sign: i64) {
            if sign >= 0 {
                pairs.for_each(|(x, y)| *x += y);
            } else {
                pairs.for_each(|(x, y)| *x -= y);
            }
        }
        if self.is_wide() == other.is_wide() {
            add(self.data.iter_mut().zip(&other.data), sign);
        } else {
            // Wide += narrow: the `b` words.
            add(self.data.iter_mut().skip(1).step_by(2).zip(&other.data), sign);
        }
    }
}

/// A block taken out of a map to be changed many times in a row (the fold asks for it once per
/// block region of every brick): [`BlockEvidence::make_mut`] on the first request, and on
/// later ones only when hit mass comes to a narrow block.
///
/// `make_mut`'s atomic compare-exchange per request is a visible share of dense ingest, and on
/// x86 a locked instruction also waits for every store before it (the previous region's
/// fold) to drain.
#[derive(Debug)]
pub struct TakenBlock {
    block: Arc<BlockEvidence>,
    /// True once `make_mut` has made `block` this holder's alone.
    alone: bool,
}

impl TakenBlock {
    pub fn new(block: Arc<BlockEvidence>) -> Self {
        Self { block, alone: false }
    }

    /// The block, to change it (widened first if `wide` and it is narrow).
    #[allow(unsafe_code)]
    #[inline(always)]
    pub fn get(&mut self, wide: bool) -> &mut BlockEvidence {
        if self.alone && (!wide || self.block.is_wide()) {
            // SAFETY: `make_mut` made `block` unique (one strong holder, no weak ones), and it
            // has stayed so: it is private to `self`, which hands out no shared handle to it,
            // and this `&mut self` borrow keeps every other reference to the block out while
            // the returned one lives — what `Arc::get_mut` would check, known without asking.
            return unsafe { &mut *Arc::as_ptr(&self.block).cast_mut() };
        }
        self.alone = true;
        BlockEvidence::make_mut(&mut self.block, wide)
    }

    /// The block, to put back.
    pub fn into_inner(self) -> Arc<BlockEvidence> {
        self.block
    }
}

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

/// Training points converted to cell units (`x / res`), the coordinates every pair uses; with
/// `sub_cells = n > 0`, each moved to the centre of its sub-cell (`floor(x·n) + ½) / n` per axis,
/// so it stays in its cell, at most `1/(2n)` of a cell away. `n` is a power of two, so every
/// step is exact in f64.
#[inline]
pub fn to_cell_units(p_m: [f64; 3], geo: &PairGeometry) -> [f64; 3] {
    let cells = p_m.map(|v| v / geo.res_m);
    if geo.sub_cells == 0 {
        return cells;
    }
    let n = f64::from(geo.sub_cells);
    // `/ n` is `* (1/n)` exactly (n is a power of two), and a multiplication is cheaper.
    let inv_n = 1.0 / n;
    cells.map(|v| (floor_f64(v * n) + 0.5) * inv_n)
}

/// [`floor_i64`] as a double, `floor_i64(v) as f64` for the same values, without the
/// integer-to-float conversion (baseline x86-64 has none for packed i64), so a loop of it
/// vectorises: `(v + 1.5·2^52) − 1.5·2^52` is round(v), exactly, then one less where that
/// rounded up.
#[inline(always)]
pub(crate) fn floor_f64(v: f64) -> f64 {
    use super::integrate::kernel::ROUND_MAGIC;
    debug_assert!(v.abs() < (1u64 << 51) as f64, "floor of {v} out of range");
    let r = (v + ROUND_MAGIC) - ROUND_MAGIC;
    r - if r > v { 1.0 } else { 0.0 }
}

/// `floor` to i64 without a libm call (baseline x86-64 has no SSE4.1 `roundsd`) and without a
/// saturating conversion (`as` adds two compares and two selects for NaN and overflow): round to
/// the nearest integer by adding 1.5·2^52, as [`round_to_i64`](super::integrate::kernel::round_to_i64)
/// does, then step down where that rounded up. Exact for |v| < 2^51, which every caller's values
/// are (points inside the voxel key range; the callers range-test anything else first).
#[inline(always)]
pub(crate) fn floor_i64(v: f64) -> i64 {
    use super::integrate::kernel::ROUND_MAGIC;
    debug_assert!(v.abs() < (1u64 << 51) as f64, "floor of {v} out of range");
    // `t`'s low mantissa bits hold round(v), and `t − 1.5·2^52` is round(v) as a double, exactly
    // (no integer-to-float conversion): all of it vectorises, even on baseline x86-64.
    let t = v + ROUND_MAGIC;
    let r = t.to_bits() as i64 - ROUND_MAGIC.to_bits() as i64;
    r - i64::from(t - ROUND_MAGIC > v)
}

/// Fractional bits of a [`SubPoint`]'s coordinates: the centre of sub-cell `k` of `n` (a power
/// of two up to [`MAX_SUB_CELLS`](super::params::MAX_SUB_CELLS)) is `(2k + 1) / 2n` of a cell,
/// a multiple of `2^-SUB_FRAC`.
pub const SUB_FRAC: u32 = super::params::MAX_SUB_CELLS.trailing_zeros() + 1;

/// A labelled training point at a sub-cell centre (true = hit): its coordinates in cell units
/// as fixed point with [`SUB_FRAC`] fractional bits, exactly what [`to_cell_units`] gives for
/// `sub_cells > 0`, in 16 bytes where a `([f64; 3], bool)` takes 32. The evidence path's
/// passes over the points (bounds, bucketing, placing the windows) read and move half the
/// bytes and find cells and sub-cells with shifts.
pub type SubPoint = ([i32; 3], bool);

/// [`labelled_cell_points`] as [`SubPoint`]s (`geo.sub_cells > 0`), replacing `out`; false
/// (and `out` unusable) when some point lies 2^23 cells or more from the origin, beyond what
/// the fixed point holds.
pub fn labelled_sub_points(set: &TrainingSet, geo: &PairGeometry, out: &mut Vec<SubPoint>) -> bool {
    use super::integrate::kernel::ROUND_MAGIC;
    assert!(geo.sub_cells > 0, "sub-cell points need sub-cells");
    let shift = geo.sub_cells.trailing_zeros();
    let n = f64::from(geo.sub_cells);
    // Sub-cell k's centre is k·step + half in units of 2^-SUB_FRAC cells: an integer, exact in
    // a double, whose low 32 bits after adding 1.5·2^52 are its two's complement (no
    // saturating conversion, with its tests for NaN and overflow). Below `limit` sub-cells
    // every coordinate stays under 2^30 (and its cell under 2^23); the farthest is tested
    // once at the end (one pass over the points: a dense scan's do not fit the caches), and a
    // point beyond it leaves `out` unusable.
    let limit = (1u64 << (30 - SUB_FRAC + shift)) as f64;
    let (step, half) = ((1u32 << (SUB_FRAC - shift)) as f64, (1u32 << (SUB_FRAC - shift - 1)) as f64);
    let res = geo.res_m;
    // The farthest coordinate so far, per lane of a chunk (reduced at the end): every axis has
    // the same limit.
    let mut far = [0.0f64; 3 * SUB_CHUNK];
    let mut q = [0i32; 3 * SUB_CHUNK];
    out.clear();
    out.reserve(set.len());
    for (points, hit) in [(&set.hits, true), (&set.frees, false)] {
        // Chunks of points as flat runs of coordinates, so the divisions go four to an
        // instruction (a dense scan converts ~360k points, and scalar divisions were what the
        // loop waited on).
        for chunk in points.chunks(SUB_CHUNK) {
            let flat = chunk.as_flattened();
            for ((q, f), &v) in q.iter_mut().zip(&mut far).zip(flat) {
                // As `to_cell_units`: cells, then times n, then the floor.
                let k = v / res * n;
                // A plain comparison, not `f64::max` (whose NaN rules cost instructions).
                *f = if k.abs() > *f { k.abs() } else { *f };
                *q = (floor_f64(k) * step + half + ROUND_MAGIC).to_bits() as u32 as i32;
            }
            out.extend(q[..flat.len()].chunks_exact(3).map(|c| ([c[0], c[1], c[2]], hit)));
        }
    }
    far.iter().all(|&f| f + 1.0 < limit)
}

/// Points [`labelled_sub_points`] converts at a time.
const SUB_CHUNK: usize = 64;

/// A [`SubPoint`]'s coordinates in cell units (exact).
#[inline(always)]
pub fn sub_point_cell_units(q: [i32; 3]) -> [f64; 3] {
    q.map(|v| f64::from(v) / f64::from(1u32 << SUB_FRAC))
}

/// A training set as labelled points in cell units (hits first, `true`), replacing `out`.
pub fn labelled_cell_points(set: &TrainingSet, geo: &PairGeometry, out: &mut Vec<([f64; 3], bool)>) {
    out.clear();
    out.extend(set.hits.iter().map(|&p| (to_cell_units(p, geo), true)));
    out.extend(set.frees.iter().map(|&p| (to_cell_units(p, geo), false)));
}

/// `floor` for values whose floor fits an i32 (|v| < 2^31: the key range), computed as the
/// crate's `floor_i64` computes it.
#[inline(always)]
pub fn floor_i32(v: f64) -> i32 {
    debug_assert!(v.abs() < (1u64 << 31) as f64, "floor of {v} out of range");
    floor_i64(v) as i32
}

/// A training point (cell units) split into its cell and its offset from that cell's centre:
/// `p = cell + ½ + offset`, offset in [−½, ½).
#[inline(always)]
pub fn split_point(p_cells: [f64; 3]) -> ([i32; 3], [f64; 3]) {
    let c = p_cells.map(floor_i32);
    (c, [0, 1, 2].map(|i| (p_cells[i] - f64::from(c[i])) - 0.5))
}

/// The kernel-table coordinate of a training point (cell units) and a cell: the one definition
/// of a pair's distance, shared by the fast path and the reference. Per axis the distance is
/// `(k − c) − offset` with `(c, offset)` from [`split_point`]; squares are summed z, y, then x,
/// and the sum goes through [`KernelTable::coordinate`].
#[inline(always)]
pub fn pair_coord(p_cells: [f64; 3], cell: CellKey, scale: f64) -> i64 {
    let (c, f) = split_point(p_cells);
    let d2 = |k: i32, i: usize| {
        let d = (i64::from(k) - i64::from(c[i])) as f64 - f[i];
        d * d
    };
    KernelTable::coordinate((d2(cell.z, 2) + d2(cell.y, 1)) + d2(cell.x, 0), scale)
}

/// Geometry shared by the scatter and the reference: resolution and kernel length in cells.
#[derive(Debug, Clone, Copy)]
pub struct PairGeometry {
    pub res_m: f64,
    pub ell_cells: f64,
    /// `N·2^COORD_SHIFT / ell_cells²`: turns a squared distance (cells²) into a fixed-point
    /// kernel-table coordinate.
    pub scale: f64,
    /// Training points sit at sub-cell centres, `sub_cells` per cell edge (0: where they are);
    /// see [`to_cell_units`].
    pub sub_cells: u32,
}

impl PairGeometry {
    pub fn new(res_m: f64, ell_m: f64, sub_cells: u32) -> Self {
        assert!(
            sub_cells == 0 || sub_cells.is_power_of_two(),
            "sub_cells {sub_cells} is not 0 or a power of two"
        );
        let ell_cells = ell_m / res_m;
        Self {
            res_m,
            ell_cells,
            scale: TABLE_INTERVALS as f64 * f64::from(1u32 << COORD_SHIFT) / (ell_cells * ell_cells),
            sub_cells,
        }
    }

    /// The geometry of a map's parameters.
    pub fn of(params: &MapParams) -> Self {
        Self::new(params.resolution_m, params.ell_m, params.sub_cells)
    }

    /// Stencil radius: cells within `ell` of a point differ from its cell by at most this.
    pub fn radius_cells(&self) -> i32 {
        floor_i32(self.ell_cells + 0.5)
    }
}

/// Reference: the evidence of one cell by summing over *all* training points (gather, O(N)).
pub fn brute_force_cell(
    set: &TrainingSet,
    cell: CellKey,
    geo: &PairGeometry,
    table: &KernelTable,
) -> (i64, i64) {
    let sum = |pts: &[[f64; 3]]| -> i64 {
        pts.iter().map(|&p| table.quantized_coord(pair_coord(to_cell_units(p, geo), cell, geo.scale))).sum()
    };
    (sum(&set.hits), sum(&set.frees))
}

pub use super::integrate::scatter::Scatter;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::integrate::kernel::FIXED_ONE;
    use crate::core::params::MapParams;
    use crate::core::integrate::training::TrainingBuilder;
    use proptest::prelude::*;
    use std::collections::BTreeMap;

    fn delta_cells(d: &ScanDelta) -> BTreeMap<CellKey, (i64, i64)> {
        let mut m = BTreeMap::new();
        for (k, b) in &d.blocks {
            for i in 0..BLOCK_CELLS {
                if b.a[i] != 0 || b.b[i] != 0 {
                    m.insert(k.cell(i), (b.a[i], b.b[i]));
                }
            }
        }
        m
    }

    /// Every cell whose centre is within ell of some training point, by exhaustive search.
    fn candidate_cells(set: &TrainingSet, geo: &PairGeometry) -> Vec<CellKey> {
        let mut out = std::collections::BTreeSet::new();
        let r = geo.ell_cells.ceil() as i32 + 1;
        for p in set.hits.iter().chain(&set.frees) {
            let c = CellKey::from_point(*p, geo.res_m).unwrap();
            for z in -r..=r {
                for y in -r..=r {
                    for x in -r..=r {
                        out.insert(CellKey::new(c.x + x, c.y + y, c.z + z));
                    }
                }
            }
        }
        out.into_iter().collect()
    }

    /// Points, origin and a geometry: resolution, kernel length and sub-cells (0 = points where
    /// they are; 8 is the default; 16 and 64 exceed the precomputed windows' size for some widths).
    fn random_scan() -> impl Strategy<Value = (Vec<[f32; 3]>, [f64; 3], f64, f64, u32)> {
        (
            prop::collection::vec((-4.0f32..4.0, -4.0f32..4.0, -2.0f32..2.0), 1..20),
            (-2.0f64..2.0, -2.0f64..2.0, -1.0f64..1.0),
            prop::sample::select(vec![0.1, 0.2]),
            prop::sample::select(vec![0.1, 0.2, 0.3, 0.45]),
            prop::sample::select(vec![0, 1, 2, 8, 8, 16, 64]),
        )
            .prop_map(|(pts, o, res, ell, sub)| {
                (pts.into_iter().map(|(x, y, z)| [x, y, z]).collect(), [o.0, o.1, o.2], res, ell, sub)
            })
    }

    /// The brute-force gather at every cell with evidence. Any cell outside the candidates is
    /// farther than ell from every point, so gets 0.
    fn brute_cells(
        set: &TrainingSet,
        geo: &PairGeometry,
        table: &KernelTable,
    ) -> BTreeMap<CellKey, (i64, i64)> {
        let mut brute = BTreeMap::new();
        for cell in candidate_cells(set, geo) {
            let (a, b) = brute_force_cell(set, cell, geo, table);
            if a != 0 || b != 0 {
                brute.insert(cell, (a, b));
            }
        }
        brute
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// The scatter equals the brute-force gather over all training points, cell by cell.
        #[test]
        fn scatter_equals_brute_force((pts, origin, res, ell, sub) in random_scan()) {
            let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, free_resolution_m: 0.3, max_range_m: 3.0, ..Default::default() };
            let set = TrainingBuilder::default().build(&pts, origin, &params);
            let geo = PairGeometry::new(res, ell, sub);
            let table = KernelTable::new();
            let fast = delta_cells(&Scatter::default().delta(&set, &geo, &table));
            prop_assert_eq!(fast, brute_cells(&set, &geo, &table));
        }

        /// The compact sub-cell points (what `delta` takes when it can) and `f64` cell points
        /// give the same bits, and so does a set the compact points cannot hold (a point
        /// 2^23 cells out).
        #[test]
        fn sub_points_and_cell_points_give_the_same_delta((pts, origin, res, ell, sub) in random_scan(), far in any::<bool>()) {
            let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, ..Default::default() };
            let mut set = TrainingBuilder::default().build(&pts, origin, &params);
            if far {
                set.frees.push([f64::from(1u32 << 23) * res, 0.0, 0.0]);
            }
            let geo = PairGeometry::new(res, ell, sub);
            let table = KernelTable::new();
            let mut labelled = Vec::new();
            labelled_cell_points(&set, &geo, &mut labelled);
            let compact = Scatter::default().delta(&set, &geo, &table);
            let cells = Scatter::default().delta_of(&labelled, &geo, &table);
            prop_assert_eq!(delta_cells(&compact), delta_cells(&cells));
        }

        /// Splitting the points across threads (partial deltas summed) gives the same bits.
        #[test]
        fn partial_deltas_sum_to_the_whole((pts, origin, res, ell, sub) in random_scan(), split in 0usize..200) {
            let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, ..Default::default() };
            let set = TrainingBuilder::default().build(&pts, origin, &params);
            let geo = PairGeometry::new(res, ell, sub);
            let table = KernelTable::new();
            let mut labelled = Vec::new();
            labelled_cell_points(&set, &geo, &mut labelled);
            let k = split.min(labelled.len());
            let whole = Scatter::default().delta_of(&labelled, &geo, &table);
            let parts = ScanDelta::sum(vec![
                Scatter::default().delta_of(&labelled[k..], &geo, &table),
                Scatter::default().delta_of(&labelled[..k], &geo, &table),
            ]);
            prop_assert_eq!(delta_cells(&whole), delta_cells(&parts));
        }
    }

    /// A block with random evidence: `a` only in cells `i % hit_every == 0` (none if 0).
    fn random_block(seed: u64, hit_every: usize) -> Box<BlockEvidence> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut b = BlockEvidence::zeroed_wide();
        for i in 0..BLOCK_CELLS {
            let a =
                if hit_every > 0 && i % hit_every == 0 { rng.random_range(-1i64 << 40..1 << 40) } else { 0 };
            if rng.random_bool(0.7) {
                b.set(i, Evidence { a, b: rng.random_range(-1i64 << 40..1 << 40) });
            }
        }
        b
    }

    /// Every cell of a block, read one by one.
    fn cell_list(b: &BlockEvidence) -> Vec<Evidence> {
        (0..BLOCK_CELLS).map(|i| b.get(i)).collect()
    }

    /// Narrow and wide blocks hold and add the same evidence: reads, equality, counts, every
    /// sum and delta across the two layouts, widening (also of a block a snapshot shares) and
    /// narrowing.
    #[test]
    fn narrow_and_wide_blocks_hold_and_add_alike() {
        let free = random_block(1, 0);
        assert!(free.is_wide(), "built wide");
        let narrow = BlockEvidence::narrowed(free.to_box());
        assert!(!narrow.is_wide() && narrow.data_bytes() * 2 == free.data_bytes());
        assert_eq!(cell_list(&narrow), cell_list(&free));
        assert_eq!(narrow.cells().collect::<Vec<_>>(), cell_list(&free));
        assert!(*narrow == *free, "narrow equals wide");
        assert!(*free == *narrow, "wide equals narrow");
        assert_eq!(narrow.cells_with_evidence(), free.cells_with_evidence());
        assert!(!narrow.is_empty() && BlockEvidence::zeroed().is_empty());
        for i in [0, 7, 300, BLOCK_CELLS - 1] {
            assert_eq!(*narrow.cell(i), free.get(i).b, "a narrow cell's first word is its b");
            assert_eq!(*free.cell(i), free.get(i).a, "a wide cell's first word is its a");
        }
        let hits = random_block(2, 3);
        assert!(BlockEvidence::narrowed(hits.to_box()).is_wide(), "a block with hits stays wide");
        assert!(*narrow != *hits);
        let other_free = BlockEvidence::narrowed(random_block(3, 0));
        // Sums in every layout pair that may take them, against the cell-by-cell sums.
        for (x, y) in [(&hits, &narrow), (&free, &other_free), (&narrow, &other_free), (&hits, &hits)] {
            for sign in [1, -1] {
                let want: Vec<Evidence> = cell_list(x)
                    .iter()
                    .zip(cell_list(y))
                    .map(|(p, q)| Evidence { a: p.a + sign * q.a, b: p.b + sign * q.b })
                    .collect();
                let mut got = x.to_box();
                got.add_scaled(y, sign);
                assert_eq!(cell_list(&got), want, "sign {sign}");
                assert_eq!(got.is_wide(), x.is_wide());
            }
        }
        // A narrow block widened in an Arc that a snapshot shares: the snapshot keeps its bits.
        let mut shared: Arc<BlockEvidence> = narrow.to_box().into();
        let snapshot = Arc::clone(&shared);
        BlockEvidence::make_mut(&mut shared, true).add_scaled(&hits, 1);
        assert!(shared.is_wide() && !snapshot.is_wide() && *snapshot == *narrow);
        let mut want = free.to_box();
        want.add_scaled(&hits, 1);
        assert!(*shared == *want);
        // Without hits to come, a narrow block stays narrow (copied only because it is shared).
        let mut shared: Arc<BlockEvidence> = narrow.to_box().into();
        let snapshot = Arc::clone(&shared);
        BlockEvidence::make_mut(&mut shared, false).add_scaled(&other_free, 1);
        assert!(!shared.is_wide() && *snapshot == *narrow && *shared != *narrow);
        // Deltas: b rows into a narrow block; a and b rows into a widened one.
        let mut d = DeltaBlock::zeroed();
        (d.b[9], d.b[500]) = (5, -7);
        let rows = [0, 1 << (9 / ROW) | 1 << (500 / ROW)];
        let mut n = narrow.to_box();
        n.add_delta(&d, 1, rows);
        let mut w = free.to_box();
        w.add_delta(&d, 1, rows);
        assert!(!n.is_wide() && *n == *w);
        d.a[64] = 11;
        let rows = [1 << (64 / ROW), rows[1]];
        BlockEvidence::widen_box(&mut n);
        n.add_delta(&d, -1, rows);
        w.add_delta(&d, -1, rows);
        assert!(n.is_wide() && *n == *w && n.get(64).a == -11);
    }

    /// A narrow block refuses hit mass rather than drop it.
    #[test]
    #[should_panic(expected = "hit mass set in a narrow block")]
    fn a_narrow_block_refuses_hit_mass() {
        BlockEvidence::zeroed().set(3, Evidence { a: 1, b: 0 });
    }

    #[test]
    #[should_panic(expected = "a wide block added into a narrow one")]
    fn a_narrow_block_refuses_a_wide_one() {
        BlockEvidence::zeroed().add_scaled(&BlockEvidence::zeroed_wide(), 1);
    }

    /// Adding a training set straight into a map's blocks ([`Scatter::add_into`]) gives the bits
    /// of applying its delta, on top of evidence already there, into a map whose blocks a
    /// snapshot shares (which must not change) and into an edit.
    fn check_add_into(set: &TrainingSet, earlier: &TrainingSet, geo: &PairGeometry) {
        use crate::core::EvidenceMap;
        let table = KernelTable::new();
        // The map's own parameters play no part in adding evidence.
        let mut base = EvidenceMap::new(MapParams::default());
        base.apply(&Scatter::default().delta(earlier, geo, &table), 1);
        let mut want = base.clone();
        want.apply(&Scatter::default().delta(set, geo, &table), 1);
        let snapshot = base.clone();
        let before = snapshot.clone();
        let mut scatter = Scatter::default();
        // Twice through one scatter: scratch space left by the first run must not leak.
        for _ in 0..2 {
            let mut got = base.clone();
            scatter.add_into(set, geo, &table, &mut got);
            assert!(crate::core::EvidenceMap::same_blocks_as(&got, &want), "straight into the map");
        }
        let mut edit = base.edit();
        scatter.add_into(set, geo, &table, &mut edit);
        let blocks = edit.finish();
        let mut edited = base.clone();
        edited.commit_edit(blocks);
        assert!(crate::core::EvidenceMap::same_blocks_as(&edited, &want), "through an edit");
        assert!(
            crate::core::EvidenceMap::same_blocks_as(&snapshot, &before),
            "a snapshot sharing the blocks is untouched"
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        #[test]
        fn adding_into_a_map_equals_applying_the_delta(
            (pts, origin, res, ell, sub) in random_scan(),
            (pts2, origin2, _, _, _) in random_scan(),
        ) {
            let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, free_resolution_m: 0.3, max_range_m: 3.0, ..Default::default() };
            let set = TrainingBuilder::default().build(&pts, origin, &params);
            let earlier = TrainingBuilder::default().build(&pts2, origin2, &params);
            check_add_into(&set, &earlier, &PairGeometry::new(res, ell, sub));
        }
    }

    /// The same for dense buckets (folded mid-bucket), far outliers (several tiles) and every
    /// window width and the stencil path.
    #[test]
    fn adding_into_a_map_equals_applying_the_delta_at_the_edges() {
        let n = 2 * crate::core::integrate::window::BRICK_POINTS as usize + 3;
        let hits: Vec<[f64; 3]> = (0..n).map(|i| [0.05 + (i % 7) as f64 * 0.1, 0.42, 0.37]).collect();
        let dense = TrainingSet { frees: hits[..n / 3].to_vec(), hits, ..Default::default() };
        let far = TrainingSet {
            hits: vec![[0.0, 0.0, 0.0], [5000.0, -4000.0, 3000.0]],
            frees: vec![[0.31, -0.2, 0.1]],
            ..Default::default()
        };
        for sub in [0, 8] {
            let geo = PairGeometry::new(0.1, 0.2, sub);
            check_add_into(&dense, &far, &geo);
            check_add_into(&far, &dense, &geo);
            for ell in [0.04, 0.1, 0.14, 0.2, 0.25, 0.3, 0.45] {
                check_add_into(&far, &far, &PairGeometry::new(0.1, ell, sub));
            }
        }
    }

    /// A bucket with many more points than a brick takes between folds (dense hits in one block,
    /// several at the same spot so cells get the largest sums) still equals the brute force.
    #[test]
    fn dense_buckets_fold_in_time() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let n = 3 * crate::core::integrate::window::BRICK_POINTS as usize + 5;
        let spot = |rng: &mut rand_chacha::ChaCha8Rng| std::array::from_fn(|_| rng.random_range(0.02..0.78));
        let mut hits: Vec<[f64; 3]> = (0..n).map(|_| spot(&mut rng)).collect();
        hits.extend(std::iter::repeat_n([0.45, 0.45, 0.45], n));
        let set = TrainingSet { frees: hits[..n / 2].to_vec(), hits, ..Default::default() };
        for sub in [0, 8] {
            let geo = PairGeometry::new(0.1, 0.2, sub);
            let table = KernelTable::new();
            let fast = delta_cells(&Scatter::default().delta(&set, &geo, &table));
            let brute = brute_cells(&set, &geo, &table);
            assert!(
                brute.values().any(|&(a, _)| a > i64::from(i32::MAX)),
                "sums beyond an i32 are exercised"
            );
            assert_eq!(fast, brute, "sub-cells {sub}");
        }
    }

    /// A bucket with a point of each label in every cell (far more than a brick takes between
    /// folds when cells repeat, none repeating) equals the brute force, with and without
    /// sub-cells; so does the same with one cell holding a second hit halfway through.
    #[test]
    fn buckets_of_one_point_per_cell_equal_the_brute_force() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        let sb = crate::core::integrate::window::SB;
        let mut hits: Vec<[f64; 3]> = (0..sb * sb * sb)
            .map(|i| {
                let c = [i % sb, i / sb % sb, i / (sb * sb)];
                c.map(|v| (v as f64 + rng.random_range(0.05..0.95)) * 0.1 - 0.8)
            })
            .collect();
        let frees: Vec<[f64; 3]> = hits.iter().rev().map(|h| h.map(|v| v + 0.004)).collect();
        assert!(hits.len() > 4 * crate::core::integrate::window::BRICK_POINTS as usize);
        let table = KernelTable::new();
        for repeat in [false, true] {
            if repeat {
                let h = hits[7];
                hits.insert(hits.len() / 2, h.map(|v| v + 0.001));
            }
            let set = TrainingSet { hits: hits.clone(), frees: frees.clone(), ..Default::default() };
            for sub in [0, 8] {
                let geo = PairGeometry::new(0.1, 0.2, sub);
                let fast = delta_cells(&Scatter::default().delta(&set, &geo, &table));
                assert_eq!(
                    fast,
                    brute_cells(&set, &geo, &table),
                    "sub-cells {sub}, a repeated cell: {repeat}"
                );
            }
        }
    }

    /// The float floor equals the integer one converted, at and around integers, halves and
    /// the ends of the range, for both signs.
    #[test]
    fn float_floor_equals_the_integer_floor() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut vs =
            vec![0.0, -0.0, 0.5, -0.5, 1.5, -1.5, 2.5, -2.5, (1u64 << 50) as f64, -((1u64 << 50) as f64)];
        for k in -300i32..300 {
            let v = f64::from(k) * 0.5;
            vs.extend([v, v.next_up(), v.next_down()]);
        }
        vs.extend((0..10_000).map(|_| rng.random_range(-1e7..1e7)));
        vs.extend((0..10_000).map(|_| rng.random_range(-1e15..1e15)));
        for v in vs {
            assert_eq!(floor_f64(v).to_bits(), (floor_i64(v) as f64).to_bits(), "floor of {v}");
        }
    }

    /// Sub-cell placement keeps a point in its cell, at most 1/(2n) of a cell per axis from
    /// where it was, at the centre of its sub-cell; 0 sub-cells leaves it alone.
    #[test]
    fn points_move_to_their_sub_cell_centres() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for n in [1u32, 2, 8, 64] {
            let geo = PairGeometry::new(0.1, 0.2, n);
            for i in 0..10_000 {
                let p: [f64; 3] = std::array::from_fn(|_| match i % 3 {
                    0 => rng.random_range(-1e4..1e4),
                    1 => f64::from(rng.random_range(-1000..1000)) * 0.1 / f64::from(n),
                    _ => rng.random_range(-1.0..1.0),
                });
                let raw = to_cell_units(p, &PairGeometry::new(0.1, 0.2, 0));
                let placed = to_cell_units(p, &geo);
                for a in 0..3 {
                    assert_eq!(floor_i32(placed[a]), floor_i32(raw[a]), "same cell: {p:?}");
                    assert!((placed[a] - raw[a]).abs() <= 0.5 / f64::from(n) + 1e-9, "{p:?}");
                    let k = placed[a] * f64::from(n) - 0.5;
                    assert_eq!(k, k.round(), "a sub-cell centre: {p:?}");
                }
            }
        }
        assert_eq!(
            to_cell_units([0.123, -0.05, 7.0], &PairGeometry::new(0.1, 0.2, 0)),
            [0.123 / 0.1, -0.5, 70.0]
        );
    }

    /// Sub-cell points hold exactly the cell units `to_cell_units` gives, hits first, for every
    /// sub-cell count, both signs and points on sub-cell and cell boundaries; a set with a point
    /// beyond their fixed point's range is refused (the evidence path then takes `f64` points).
    #[test]
    fn sub_points_are_the_cell_points_in_fixed_point() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        for n in [1u32, 2, 4, 8, 16, 32, 64] {
            let geo = PairGeometry::new(0.1, 0.2, n);
            let mut set = TrainingSet::default();
            for i in 0..3_000 {
                let p: [f64; 3] = std::array::from_fn(|_| match i % 4 {
                    0 => rng.random_range(-1e5..1e5),
                    1 => f64::from(rng.random_range(-1000..1000)) * 0.1 / f64::from(n),
                    2 => rng.random_range(-1.0..1.0),
                    _ => f64::from(rng.random_range(-3..3)) * 0.1,
                });
                if i % 2 == 0 { set.hits.push(p) } else { set.frees.push(p) }
            }
            let (mut subs, mut cells) = (Vec::new(), Vec::new());
            assert!(labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
            labelled_cell_points(&set, &geo, &mut cells);
            assert_eq!(subs.len(), cells.len());
            for (&(q, hit), &(p, cell_hit)) in subs.iter().zip(&cells) {
                assert_eq!(hit, cell_hit);
                assert_eq!(sub_point_cell_units(q), p, "n = {n}");
            }
            // 2^23 cells (840 km at 0.1 m) is beyond the fixed point; just inside it is not.
            let edge = f64::from(1u32 << 23) * 0.1;
            set.frees.push([0.0, -(edge - 1.0), 0.0]);
            assert!(labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
            set.frees.push([0.0, 0.0, edge]);
            assert!(!labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
            // Also when the far point comes first, with whole chunks of points after it.
            set.frees.pop();
            set.hits.insert(0, [-edge, 0.0, 0.0]);
            assert!(!labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
        }
    }

    /// The branch-free floors equal `f64::floor` at and around integers, halves and the ends of
    /// their ranges, for both signs.
    #[test]
    fn floors_are_exact() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let near =
            |v: f64| [v, f64::from_bits(v.to_bits() + 1), f64::from_bits(v.to_bits().saturating_sub(1))];
        let mut values = vec![0.0, -0.0, f64::MIN_POSITIVE, -f64::MIN_POSITIVE, 0.5, -0.5];
        for k in [1.0, 2.0, 3.0, 7.5, 1e6, 1048576.5, 2f64.powi(30), 2f64.powi(50) + 0.5] {
            for v in near(k).into_iter().chain(near(-k)) {
                values.push(v);
            }
        }
        values.extend((0..100_000).map(|_| rng.random_range(-1e7..1e7)));
        values.extend((0..100_000).map(|_| f64::from(rng.random_range(-1000..1000)) * 0.1));
        for v in values {
            assert_eq!(floor_i64(v), v.floor() as i64, "{v:e}");
            if v.abs() < 2f64.powi(31) {
                assert_eq!(floor_i32(v), v.floor() as i32, "{v:e}");
            }
        }
    }

    #[test]
    fn far_outliers_are_tiled_not_allocated_densely() {
        let set =
            TrainingSet { hits: vec![[0.0, 0.0, 0.0], [5000.0, -4000.0, 3000.0]], ..Default::default() };
        // Points where they are: a point at a cell centre stays there.
        let geo = PairGeometry::new(0.1, 0.2, 0);
        let d = Scatter::default().delta(&set, &geo, &KernelTable::new());
        let cells = delta_cells(&d);
        assert!(cells.keys().any(|c| c.x > 40000) && cells.keys().any(|c| c.x < 10));
        // One isolated point at a cell centre: 33 lattice centres within 2 cells, minus those at exactly 2.
        let set = TrainingSet { hits: vec![[0.05, 0.05, 0.05]], ..Default::default() };
        let cells = delta_cells(&Scatter::default().delta(&set, &geo, &KernelTable::new()));
        assert_eq!(cells.len(), 27, "offsets with |d|² < 4 cells²: 1 + 6 + 12 + 8");
        assert_eq!(cells[&CellKey::new(0, 0, 0)].0, FIXED_ONE as i64);
    }
}
