//! Block storage: the evidence of one map block ([`BlockEvidence`], narrow or wide), its
//! summary for ray walks ([`BlockSummary`]), and a block taken out of a map to be changed
//! ([`TakenBlock`]).
//!
//! Part of the data model: depends on `key`, `params` and `posterior` only.

use super::key::BLOCK_CELLS;
use super::params::{MapParams, Thresholds};
use super::posterior::{Evidence, probability_variance};
use std::sync::Arc;

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

    pub(in crate::core) fn pairs_mut(&mut self) -> &mut [Evidence; BLOCK_CELLS] {
        assert!(self.is_wide());
        // SAFETY: as in `pairs`, and `self` is borrowed mutably.
        unsafe { &mut *self.data.as_mut_ptr().cast::<[Evidence; BLOCK_CELLS]>() }
    }
}

impl BlockEvidence {
    /// The block's words (the layout's: `b` sums if narrow, `a b` pairs if wide), to change them.
    pub(in crate::core) fn words_mut(&mut self) -> &mut [i64] {
        &mut self.data
    }

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

    /// Cell `i` (local index,
    /// [`CellKey::index_in_block`](crate::core::key::CellKey::index_in_block)), without a branch
    /// on the layout.
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
