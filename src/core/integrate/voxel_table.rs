//! The voxel table of the training data: a hand-written open-addressing hash table from a
//! packed voxel key to the running sum of the voxel's points ([`VoxelCentroids`]), with two
//! slot layouts ([`Slot`], [`CompactSlot`]) behind [`TableSlot`].
//!
//! Cheaper than a general hash map for the tens of thousands of lookups a scan makes, and
//! exact: each centroid is its voxel's sum, in insertion order, divided by its count.

/// Reusable voxel-centroid accumulator (keeps its allocations between scans).
///
/// Voxels are found through an open-addressing table keyed by the packed voxel key (linear
/// probing, multiplicative hash): cheaper than a general hash map for the ~30k lookups a scan
/// makes. Voxel keys must lie within ±2^20 per axis (±100 km at 0.1 m).
///
/// Why it looks as it does:
/// - a slot holds its key beside the voxel's index, so a probe is one load;
/// - points go in by rounds (`ADD_BATCH`) whose home slots are computed and prefetched
///   first, so the misses of a round overlap (a dense scan's table is megabytes);
/// - home slots come from the top bits of the hash (see `slot_of`), and an insert has one
///   branch, taken on collisions only (see `insert`);
/// - range-tested keys (the hits, which may be anything) are computed in a loop of their own
///   without branches, so it vectorises;
/// - a table at least 1/8 full is emptied in one pass rather than slot by slot, and a tagged
///   table ([`Slot`]) is emptied by moving its tag on.
#[derive(Debug, Default)]
pub(crate) struct VoxelCentroids<S: TableSlot = Slot> {
    /// The open-addressing table: the voxel key and its index into `sums` + 1 (0 = empty),
    /// side by side, so a probe is one load.
    slots: Vec<S>,
    /// Voxels so far: `keys[..len]` and `sums[..len]`.
    len: usize,
    /// The keys in first-occurrence order (the occupied slots, for [`Self::clear`]);
    /// `keys[len]` is scratch.
    keys: Vec<u64>,
    /// Per voxel, the sum of its points and their number ([`Sum`]); `sums[len]` is always
    /// (once allocated) [`EMPTY_SUM`], the entry the next new voxel adds its first point to.
    sums: Vec<Sum>,
    /// For [tagged](TableSlot::TAGGED) slots, the tag of the slots that are full: those of
    /// every other are empty. Never 0 (the tag of [`Default`] slots) once slots exist.
    tag: u32,
}

/// A voxel's sum of points (x, y, z) and, as a fourth lane, their number (a double, exact up
/// to 2^53): one 4-lane add per point. The sample buffers keep `[x, y, z]`, not
/// `[x, y, z, 1]`: the keys of a compact table's round vectorise only from the former.
type Sum = [f64; 4];

/// What a voxel's sum starts from: −0 is the identity of floating-point addition (`x + −0 = x`
/// for every `x`, −0 included), so adding a first point to it gives that point, bit for bit.
const EMPTY_SUM: Sum = [-0.0, -0.0, -0.0, 0.0];

/// A slot of a [`VoxelCentroids`] table, and the key it stores of a voxel.
///
/// A slot type with room for it holds the table's `tag` (its generation, see
/// [`VoxelCentroids::tag`]) and is empty unless that matches; one without ignores it.
pub(crate) trait TableSlot: Copy + Default + std::fmt::Debug {
    /// Whether slots hold the table's tag, so that emptying the table is one increment.
    const TAGGED: bool;
    /// The slot of voxel `key` (a key of this slot type) whose sum is at `index − 1`.
    fn new(key: u64, index: u32, tag: u32) -> Self;
    /// The voxel's index into the sums + 1, or 0 for an empty slot.
    fn index(self, tag: u32) -> u32;
    /// Zero where a probe for `key` ends (the slot is empty or holds `key`), not zero where it
    /// goes on: one word for the probe loop's one branch, taken on a collision only. (Left to
    /// itself, the compiler tests whether the slot is empty in a branch of its own, which goes
    /// either way.)
    fn probe(self, key: u64, tag: u32) -> u64;
    /// The key of the voxel of the scaled point `s` (`p / ds`, each coordinate inside the
    /// key range).
    fn pack(s: [f64; 3]) -> u64;
}

/// A slot for any voxel of the key range: its whole 63-bit key, its index, and the tag of the
/// generation that wrote it, in the 4 bytes the other two leave of 16.
///
/// The tag exists because the free voxels' table is sized for the largest scan so far (a few
/// hundred KiB of slots) and emptying it whole every scan was a visible share of ingest.
/// [`CompactSlot`]s (a dense scan's shells) have no room for a tag and are emptied as before.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Slot {
    key: u64,
    index: u32,
    tag: u32,
}

impl TableSlot for Slot {
    const TAGGED: bool = true;

    #[inline(always)]
    fn new(key: u64, index: u32, tag: u32) -> Self {
        Slot { key, index, tag }
    }

    #[inline(always)]
    fn index(self, tag: u32) -> u32 {
        if self.tag == tag { self.index } else { 0 }
    }

    #[inline(always)]
    fn probe(self, key: u64, tag: u32) -> u64 {
        // Through `black_box` (a store and a load): as the keys' difference masked by the
        // tags' agreement, the compiler splits the test into two branches again, which costs
        // far more than the store and load.
        u64::from(!std::hint::black_box((self.tag != tag) | (self.key == key)))
    }

    #[inline(always)]
    fn pack(s: [f64; 3]) -> u64 {
        pack_key(s)
    }
}

/// A slot of 8 bytes for a table whose voxels span fewer than [`COMPACT_SPAN`] voxels on every
/// axis and number fewer than [`COMPACT_VOXELS`]: the low [`COMPACT_BITS`] bits of each
/// coordinate (which tell such voxels apart) above a 24-bit index.
///
/// The free samples of one shell take these (see [`TrainingBuilder::frees_by_shell`]): a
/// shell lies within a scan's range of its origin.
///
/// [`TrainingBuilder::frees_by_shell`]: super::training::TrainingBuilder::frees_by_shell
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct CompactSlot(u64);

/// Bits of each coordinate in a [`CompactSlot`]'s key (x, y, z), and of its index: 64 in all.
const COMPACT_BITS: [u32; 3] = [13, 13, 14];
const COMPACT_INDEX_BITS: u32 = 64 - (COMPACT_BITS[0] + COMPACT_BITS[1] + COMPACT_BITS[2]);
/// Voxels per axis within which [`CompactSlot`] keys differ: the fewest a field tells apart
/// (x's, as few as y's).
pub(super) const COMPACT_SPAN: f64 = (1u64 << COMPACT_BITS[0]) as f64;
/// Voxels a table of [`CompactSlot`]s can hold (their index + 1 must fit its bits).
pub(super) const COMPACT_VOXELS: usize = (1 << COMPACT_INDEX_BITS) - 2;

impl TableSlot for CompactSlot {
    const TAGGED: bool = false;

    #[inline(always)]
    fn new(key: u64, index: u32, _tag: u32) -> Self {
        debug_assert!(index < 1 << COMPACT_INDEX_BITS && key < 1 << (64 - COMPACT_INDEX_BITS));
        CompactSlot(key << COMPACT_INDEX_BITS | u64::from(index))
    }

    #[inline(always)]
    fn index(self, _tag: u32) -> u32 {
        (self.0 & ((1 << COMPACT_INDEX_BITS) - 1)) as u32
    }

    #[inline(always)]
    fn probe(self, key: u64, _tag: u32) -> u64 {
        // The smaller of the index (0: empty) and the keys' difference (0: the same key):
        // fewer instructions than a `bool` through `black_box`, as `Slot` keeps.
        (self.0 & ((1 << COMPACT_INDEX_BITS) - 1))
            .min((self.0 ^ (key << COMPACT_INDEX_BITS)) >> COMPACT_INDEX_BITS)
    }

    #[inline(always)]
    fn pack(s: [f64; 3]) -> u64 {
        // Two's complement low bits of each floor: congruent coordinates share them, and
        // voxels less than 2^bits apart on an axis are not congruent.
        (0..3).fold(0, |key, a| {
            (key << COMPACT_BITS[a]) | (super::floor::floor_i64(s[a]) as u64 & ((1 << COMPACT_BITS[a]) - 1))
        })
    }
}

const KEY_BITS: u32 = 21;
pub(super) const KEY_LIMIT: f64 = (1u64 << (KEY_BITS - 1)) as f64;

/// Points [`VoxelCentroids::add_all`] looks up per round: their home slots are computed and
/// prefetched first, so the cache misses of a round overlap instead of queueing one behind the
/// other (a dense scan's table is megabytes, and its next voxel is anywhere in it).
const ADD_BATCH: usize = 32;
/// Points per round when the slots take more than [`LARGE_TABLE_BYTES`] (a dense scan's:
/// megabytes, past L2), where a probe misses to L3 and more of them in flight pay; 128 was the
/// best of 32–256 for dense scans. Tables of a few hundred KiB keep 32, faster for them.
const LARGE_TABLE_BATCH: usize = 4 * ADD_BATCH;
const LARGE_TABLE_BYTES: usize = 1 << 20;

impl<S: TableSlot> VoxelCentroids<S> {
    pub(super) fn clear(&mut self) {
        if S::TAGGED {
            // Every slot written so far becomes empty. After 2^32 − 1 generations the tags
            // come round again, and the slots are emptied for real.
            self.tag = self.tag.wrapping_add(1);
            if self.tag == 0 {
                self.slots.fill(S::default());
                self.tag = 1;
            }
        } else if 8 * self.len >= self.slots.len() {
            // A table at least 1/8 full (as after the scan that grew it): one sequential pass
            // beats a cache miss per voxel.
            self.slots.fill(S::default());
        } else {
            // Otherwise empty the occupied slots only (their number is the number of voxels).
            let mask = self.slots.len().wrapping_sub(1);
            for &k in &self.keys[..self.len] {
                let mut i = slot_of(k, mask);
                while self.slots[i].index(self.tag) != 0 {
                    self.slots[i] = S::default();
                    i = (i + 1) & mask;
                }
            }
        }
        self.len = 0;
        if let Some(first) = self.sums.first_mut() {
            *first = EMPTY_SUM;
        }
    }

    /// Adds every point of `points`, in order; returns how many were left out because their
    /// voxel key is outside the packable range (or not a number). With `CHECKED` false every
    /// point must lie inside it (the caller bounded them; debug-asserted), and is not tested.
    pub(super) fn add_all<const CHECKED: bool>(&mut self, points: &[[f64; 3]], inv_ds: f64) -> usize {
        if self.is_large() {
            self.add_all_by::<CHECKED, LARGE_TABLE_BATCH>(points, inv_ds)
        } else {
            self.add_all_by::<CHECKED, ADD_BATCH>(points, inv_ds)
        }
    }

    /// True when the slots take more than [`LARGE_TABLE_BYTES`] (inserts go in longer rounds).
    fn is_large(&self) -> bool {
        self.slots.len() * std::mem::size_of::<S>() > LARGE_TABLE_BYTES
    }

    /// [`Self::add_all`] in rounds of `N` points.
    fn add_all_by<const CHECKED: bool, const N: usize>(&mut self, points: &[[f64; 3]], inv_ds: f64) -> usize {
        let mut rejected = 0;
        let mut keys = [0u64; N];
        let mut inside = [true; N];
        let mut homes = [0usize; N];
        for chunk in points.chunks(N) {
            let most = self.len + chunk.len();
            if 2 * most > self.slots.len() {
                self.grow(most);
            }
            // Room for every point of the chunk to be a new voxel, and the scratch entry after.
            if self.sums.len() <= most {
                let n = (2 * most).max(1024);
                self.sums.resize(n, EMPTY_SUM);
                self.keys.resize(n, 0);
            }
            let mask = self.slots.len() - 1;
            // A slice `mask + 1` long, so that an index `& mask` needs no bounds check.
            let slots = &self.slots[..=mask];
            // Keys in a loop of their own, without branches (a point outside the range gets a
            // key of no meaning and `inside` false), so that it vectorises.
            if CHECKED {
                for ((k, ok), &p) in keys.iter_mut().zip(&mut inside).zip(chunk) {
                    (*k, *ok) = voxel_key_or_outside::<S>(p, inv_ds);
                }
            } else {
                for (k, &p) in keys.iter_mut().zip(chunk) {
                    *k = voxel_key_in_range::<S>(p, inv_ds);
                }
            }
            // Every home slot prefetched, an outside point's too (it is a slot of the table).
            for (h, &k) in homes.iter_mut().zip(&keys[..chunk.len()]) {
                *h = slot_of(k, mask);
                crate::core::prefetch::prefetch(&slots[*h]);
            }
            let (mut len, tag) = (self.len, self.tag);
            // Slices of known length: the length in a register, not reloaded past every store.
            let (slots, sums, vkeys) =
                (&mut self.slots[..=mask], &mut self.sums[..=most], &mut self.keys[..=most]);
            for (((&k, &h), &p), &ok) in keys.iter().zip(&homes).zip(chunk).zip(&inside) {
                // Unchecked points are all inside: no test of `inside` per point.
                if !CHECKED || ok {
                    len = insert(slots, sums, vkeys, len, k, h, p, mask, tag);
                } else {
                    rejected += 1;
                }
            }
            self.len = len;
        }
        rejected
    }

    /// [`Self::add_all`] of free samples, without range tests when they are `bounded`.
    pub(super) fn add_samples(&mut self, samples: &[[f64; 3]], inv_ds: f64, bounded: bool) {
        if bounded {
            self.add_all::<false>(samples, inv_ds);
        } else {
            self.add_all::<true>(samples, inv_ds);
        }
    }

    /// Resizes the table to hold `voxels` at most half full.
    fn grow(&mut self, voxels: usize) {
        let cap = (2 * voxels).next_power_of_two().max(1024);
        self.slots.clear();
        self.slots.resize(cap, S::default());
        // The new slots are all empty, whatever the tag; it only must not be theirs.
        self.tag = self.tag.max(1);
        let mask = cap - 1;
        for (n, &k) in self.keys[..self.len].iter().enumerate() {
            let mut i = slot_of(k, mask);
            while self.slots[i].index(self.tag) != 0 {
                i = (i + 1) & mask;
            }
            self.slots[i] = S::new(k, n as u32 + 1, self.tag);
        }
    }

    pub(super) fn centroids_into(&self, out: &mut Vec<[f64; 3]>) {
        out.clear();
        self.append_centroids(out);
    }

    pub(super) fn append_centroids(&self, out: &mut Vec<[f64; 3]>) {
        out.extend(self.sums[..self.len].iter().map(|s| [s[0] / s[3], s[1] / s[3], s[2] / s[3]]));
    }
}

/// Adds `p` to the voxel `key` of a table holding `len` voxels, probing from its home slot
/// `home`; returns the new number of voxels. `sums` and `keys` must have room for one more voxel
/// and its scratch entry, and `sums[len]` must be [`EMPTY_SUM`]. `tag` is the table's (its
/// full slots', for a [tagged](TableSlot::TAGGED) slot type).
///
/// Without a branch on whether the voxel is new (about half of a scan's lookups find it,
/// in no order a predictor learns): a new voxel's index is `len`, whose sum is
/// [`EMPTY_SUM`], so both cases add the point to `sums[index]` and write the slot; the number
/// then grows by one if the voxel was new, and the entry after the last is reset.
///
///
/// The table, the sums and the count are arguments rather than `self`: measurably faster on
/// dense scans. Consecutive equal keys are rare (1.42 samples per run
/// on dense shells, 76% of runs a single sample), so looking a voxel up once per run cannot pay.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn insert<S: TableSlot>(
    slots: &mut [S],
    sums: &mut [Sum],
    keys: &mut [u64],
    len: usize,
    key: u64,
    home: usize,
    p: [f64; 3],
    mask: usize,
    tag: u32,
) -> usize {
    let mut i = home & mask;
    while slots[i].probe(key, tag) != 0 {
        i = (i + 1) & mask;
    }
    let found = slots[i].index(tag);
    let at = if found == 0 { len } else { found as usize - 1 };
    slots[i] = S::new(key, at as u32 + 1, tag);
    keys[len] = key;
    let e = &mut sums[at];
    *e = [e[0] + p[0], e[1] + p[1], e[2] + p[2], e[3] + 1.0];
    let len = len + usize::from(found == 0);
    sums[len] = EMPTY_SUM;
    len
}

/// The home slot of `key` in a table of `mask + 1` slots (a power of two): the top bits of the
/// key times 2^64/φ, the bits every key bit reaches. (Lower bits would ignore x, whose key
/// bits are the highest, and cluster a scan's voxels.)
#[inline(always)]
fn slot_of(key: u64, mask: usize) -> usize {
    debug_assert!(mask.count_ones() >= 1 && mask.wrapping_add(1).is_power_of_two());
    (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> (mask as u64).leading_zeros()) as usize
}

/// [`voxel_key_or_outside`] of a point known to lie inside ±2^20 voxels (no range test).
#[inline]
fn voxel_key_in_range<S: TableSlot>(p: [f64; 3], inv_ds: f64) -> u64 {
    debug_assert!(voxel_key_or_outside::<S>(p, inv_ds).1, "point outside the key range: {p:?}");
    S::pack(p.map(|v| v * inv_ds))
}

/// The floors of voxel coordinates `s` (each inside ±2^20) packed as three 21-bit fields.
#[inline(always)]
fn pack_key(s: [f64; 3]) -> u64 {
    s.iter().fold(0, |key, &v| (key << KEY_BITS) | ((super::floor::floor_i64(v) + KEY_LIMIT as i64) as u64))
}

/// The tests' reference for [`voxel_key_or_outside`], written plainly: the voxel key, or `None`
/// outside ±2^20 voxels.
#[cfg(test)]
fn voxel_key(p: [f64; 3], inv_ds: f64) -> Option<u64> {
    let mut key = 0u64;
    for v in p {
        let s = v * inv_ds;
        if !(-KEY_LIMIT..KEY_LIMIT).contains(&s) {
            return None;
        }
        key = (key << KEY_BITS) | ((super::floor::floor_i64(s) + KEY_LIMIT as i64) as u64);
    }
    Some(key)
}

/// The voxel `floor(p / ds)` packed as three 21-bit fields and true, or a key of no meaning
/// and false for a point outside ±2^20 voxels or not finite; without branches.
#[inline(always)]
fn voxel_key_or_outside<S: TableSlot>(p: [f64; 3], inv_ds: f64) -> (u64, bool) {
    let s = p.map(|v| v * inv_ds);
    let inside = s.map(|v| (-KEY_LIMIT..KEY_LIMIT).contains(&v));
    // Outside the range the floor is not exact (or NaN): take that of 0 instead.
    (S::pack([0, 1, 2].map(|a| if inside[a] { s[a] } else { 0.0 })), inside[0] & inside[1] & inside[2])
}

#[cfg(test)]
#[path = "voxel_table_tests.rs"]
mod tests;
