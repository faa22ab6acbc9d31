//! One scan → labelled training points (algorithm.md §4).
//!
//! 1. Non-finite points are dropped (and counted).
//! 2. Hits are downsampled to the centroid of each `floor(x/ds)` voxel.
//! 3. Each centroid `h` at range `r = |h − o|`:
//!    - `r ≤ max_range` (or max_range = 0): a hit (label 1) plus free samples along `o → h`;
//!    - `r > max_range`, [`RangeMode::Truncate`] (default): no hit; the ray is a free-only ray of
//!      length `max_range` (the beam crossed that much free space), sampled like any other ray;
//!    - `r > max_range`, [`RangeMode::Drop`]: discarded entirely (la3dm).
//! 4. Free samples sit at `d = fr, 2fr, … < L` and, if `L > fr`, one more at `L − fr`, where `L`
//!    is the ray length; the end point itself is never a free sample.
//! 5. The sensor origin is one more free sample (once per scan, if `origin_as_free`).
//! 6. All free samples are downsampled to voxel centroids at `ds`, separately from hits.
//!
//! Each centroid is its voxel's sum, in la3dm's order, divided by its count, so the same scan
//! always gives the same training set, bit for bit. Hits come in first-occurrence order of their
//! voxels; free voxels too, except that a large scan's go shell by shell (see `FreeRay`): their
//! order carries no meaning (evidence sums are integers, the same in any order).

use crate::core::params::{MapParams, RangeMode};

/// Labelled training points of one scan, in world metres.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrainingSet {
    /// Downsampled hit centroids (label 1).
    pub hits: Vec<[f64; 3]>,
    /// Downsampled free-space samples (label 0).
    pub frees: Vec<[f64; 3]>,
    /// Input points that were not finite or lay farther than 2^20 voxels from the origin.
    pub dropped_points: usize,
    /// Hit voxels before the range test.
    pub hit_voxels: usize,
    /// Centroids beyond max range (truncated or dropped, per the range mode).
    pub beyond_range: usize,
}

impl TrainingSet {
    pub fn len(&self) -> usize {
        self.hits.len() + self.frees.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

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
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct CompactSlot(u64);

/// Bits of each coordinate in a [`CompactSlot`]'s key (x, y, z), and of its index: 64 in all.
const COMPACT_BITS: [u32; 3] = [13, 13, 14];
const COMPACT_INDEX_BITS: u32 = 64 - (COMPACT_BITS[0] + COMPACT_BITS[1] + COMPACT_BITS[2]);
/// Voxels per axis within which [`CompactSlot`] keys differ: the fewest a field tells apart
/// (x's, as few as y's).
const COMPACT_SPAN: f64 = (1u64 << COMPACT_BITS[0]) as f64;
/// Voxels a table of [`CompactSlot`]s can hold (their index + 1 must fit its bits).
const COMPACT_VOXELS: usize = (1 << COMPACT_INDEX_BITS) - 2;

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
            (key << COMPACT_BITS[a])
                | (super::cell_points::floor_i64(s[a]) as u64 & ((1 << COMPACT_BITS[a]) - 1))
        })
    }
}

const KEY_BITS: u32 = 21;
const KEY_LIMIT: f64 = (1u64 << (KEY_BITS - 1)) as f64;

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
    fn clear(&mut self) {
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
    fn add_all<const CHECKED: bool>(&mut self, points: &[[f64; 3]], inv_ds: f64) -> usize {
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
    fn add_samples(&mut self, samples: &[[f64; 3]], inv_ds: f64, bounded: bool) {
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

    fn centroids_into(&self, out: &mut Vec<[f64; 3]>) {
        out.clear();
        self.append_centroids(out);
    }

    fn append_centroids(&self, out: &mut Vec<[f64; 3]>) {
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
    s.iter()
        .fold(0, |key, &v| (key << KEY_BITS) | ((super::cell_points::floor_i64(v) + KEY_LIMIT as i64) as u64))
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
        key = (key << KEY_BITS) | ((super::cell_points::floor_i64(s) + KEY_LIMIT as i64) as u64);
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

/// Builds training sets; holds scratch space so repeated scans allocate nothing new.
#[derive(Debug, Default)]
pub struct TrainingBuilder {
    hits: VoxelCentroids,
    frees: VoxelCentroids,
    /// The free samples of one shell, when a scan's fit [`CompactSlot`]s (see
    /// [`Self::frees_by_shell`]).
    shell_frees: VoxelCentroids<CompactSlot>,
    centroids: Vec<[f64; 3]>,
    /// Points on their way into `hits` or `frees`, in the order they are added.
    samples: Vec<[f64; 3]>,
    /// The scan's rays with free samples.
    rays: Vec<FreeRay>,
    /// Per ray with one, the extra sample `fr` short of its end (and the origin); then the
    /// same by shell.
    extras: Vec<Extra>,
    sorted_extras: Vec<Extra>,
    /// Counting sort of `extras` by shell.
    shell_ends: Vec<usize>,
    /// Whether the last scan's free samples went in shell by shell ([`FreeRay`]), and
    /// whether into a table of [`CompactSlot`]s.
    by_shell: bool,
    compact_shells: bool,
}

/// Points gathered before they go into a voxel table (a few rays' worth of free samples).
const SAMPLE_BUFFER: usize = 1024;

/// Items a loop of square roots and divisions takes at a time, so that they go four to an
/// instruction: the hits whose rays [`TrainingBuilder::build_into`] measures, the extra samples
/// whose shells [`TrainingBuilder::frees_by_shell`] finds.
const RAY_CHUNK: usize = 64;

/// Free samples (about) from which a scan's go in shell by shell ([`FreeRay`]): 2^16, whose
/// voxels, up to 72 bytes each in slots, sums and keys, would fill more than a 2 MB L2 cache
/// in one table. With fewer, the scan's table stays in L2 anyway, and sorting each ray's extra
/// sample by shell and a table round per shell are work for nothing: the 12 sample scans
/// (1k to 17k samples each) took a third longer to train (0.195 ms against 0.147).
const SHELL_MIN_SAMPLES: f64 = 65536.0;

impl TrainingBuilder {
    /// Training data for `points_world` seen from `origin_world` (both metres, world frame).
    pub fn build(
        &mut self,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        params: &MapParams,
    ) -> TrainingSet {
        let mut out = TrainingSet::default();
        self.build_into(points_world, origin_world, params, &mut out);
        out
    }

    pub fn build_into(
        &mut self,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        params: &MapParams,
        out: &mut TrainingSet,
    ) {
        let inv_ds = 1.0 / params.ds_resolution_m;
        self.hits.clear();
        self.frees.clear();
        out.hits.clear();
        out.dropped_points = 0;
        out.beyond_range = 0;
        // A point that is not finite has no voxel key, so the key test drops it too.
        for chunk in points_world.chunks(SAMPLE_BUFFER) {
            self.samples.clear();
            self.samples.extend(chunk.iter().map(|p| p.map(f64::from)));
            out.dropped_points += self.hits.add_all::<true>(&self.samples, inv_ds);
        }
        self.hits.centroids_into(&mut self.centroids);
        out.hit_voxels = self.centroids.len();
        let o = origin_world;
        let fr = params.free_resolution_m;
        let max_r = params.max_range_m;
        // The rays, in the order of their hit voxels' first occurrence.
        self.rays.clear();
        let mut longest = 0.0f64;
        // The rays' total length, for the number of free samples.
        let mut samples = 0.0;
        // Per chunk of hits, their offsets from the origin, lengths and directions first, in
        // loops without branches, so the square roots and divisions go four to an instruction.
        let mut vs = [[0.0f64; 3]; RAY_CHUNK];
        let mut rs = [0.0f64; RAY_CHUNK];
        for chunk in self.centroids.chunks(RAY_CHUNK) {
            for ((v, r), h) in vs.iter_mut().zip(&mut rs).zip(chunk) {
                *v = [h[0] - o[0], h[1] - o[1], h[2] - o[2]];
                *r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            }
            for (v, &r) in vs[..chunk.len()].iter_mut().zip(&rs) {
                *v = [v[0] / r, v[1] / r, v[2] / r];
            }
            for ((&h, &n), &r) in chunk.iter().zip(&vs).zip(&rs) {
                let len = if max_r > 0.0 && r > max_r {
                    out.beyond_range += 1;
                    match params.range_mode {
                        RangeMode::Drop => continue,
                        RangeMode::Truncate => max_r,
                    }
                } else {
                    out.hits.push(h);
                    r
                };
                if r > 0.0 {
                    self.rays.push(FreeRay { n, len, order: self.rays.len() as u32 });
                    longest = longest.max(len);
                    samples += len;
                }
            }
        }
        out.frees.clear();
        // A ray's samples lie within its length of the origin: when that stays a voxel short of
        // the key range on every axis, they need no range test (almost always: ±2^20 voxels is
        // ±105 km at 0.1 m).
        let o_max = o.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let finite = o.iter().all(|v| v.is_finite());
        let in_range = |len: f64| finite && (o_max + len) * inv_ds < KEY_LIMIT - 1.0;
        if samples / fr >= SHELL_MIN_SAMPLES
            && in_range(longest)
            && shells_separate_voxels(params.ds_resolution_m, fr, o_max + longest)
        {
            self.by_shell = true;
            // A shell's samples lie within `longest` of the origin, so their voxels span at
            // most 2·longest/ds + 1 per axis (+ 2 for rounding), and number at most one per
            // ray and its extra sample, + 1 for the origin.
            self.compact_shells =
                2.0 * longest * inv_ds + 3.0 < COMPACT_SPAN && 2 * self.rays.len() + 1 < COMPACT_VOXELS;
            if self.compact_shells {
                let mut table = std::mem::take(&mut self.shell_frees);
                self.frees_by_shell(&mut table, o, params, out);
                self.shell_frees = table;
            } else {
                let mut table = std::mem::take(&mut self.frees);
                self.frees_by_shell(&mut table, o, params, out);
                self.frees = table;
            }
            return;
        }
        (self.by_shell, self.compact_shells) = (false, false);
        // Whether every sample in `samples` is known to be in range.
        let mut bounded = in_range(0.0);
        self.samples.clear();
        for r in &self.rays {
            free_samples(&mut self.samples, o, r.n, r.len, fr);
            bounded &= in_range(r.len);
            if self.samples.len() >= SAMPLE_BUFFER {
                self.frees.add_samples(&self.samples, inv_ds, bounded);
                self.samples.clear();
                bounded = in_range(0.0);
            }
        }
        if params.origin_as_free {
            self.samples.push(o);
        }
        self.frees.add_samples(&self.samples, inv_ds, bounded);
        self.frees.append_centroids(&mut out.frees);
    }

    /// The free centroids of `self.rays`, one shell at a time (see [`FreeRay`]) into `table`:
    /// every sample must be inside the key range, [`shells_separate_voxels`] must hold, and a
    /// shell's voxels must fit the table's slot type.
    ///
    /// [`CompactSlot`]s, 8 bytes where [`Slot`]s take 16, serve the shells of a scan within
    /// ±400 m at 0.1 m: a dense scan's busiest shells hold 14k–17k voxels, a table of 64k slots,
    /// and 512 KiB of slots and sums fit in a 1 MiB L2 where 1 MiB of 16-byte slots did not.
    ///
    /// One pass over the rays per shell places each ray's sample and the extras between them;
    /// a ray that has ended writes its sample without counting it, and the ended rays are
    /// dropped once a quarter have (dropping them every shell moved every 40-byte ray after the
    /// first that had ended). The shells' table inserts are about half of a dense scan's
    /// training.
    /// table's 6.4 ns a sample before any summing.
    fn frees_by_shell<S: TableSlot>(
        &mut self,
        table: &mut VoxelCentroids<S>,
        o: [f64; 3],
        params: &MapParams,
        out: &mut TrainingSet,
    ) {
        let (ds, fr) = (params.ds_resolution_m, params.free_resolution_m);
        let inv_ds = 1.0 / ds;
        let shell = |p: [f64; 3]| shell_of(p, o, ds, inv_ds, fr);
        // Each ray's extra sample, and the origin after every ray.
        self.extras.clear();
        self.extras.extend(self.rays.iter().filter(|r| r.len > fr).map(|r| Extra {
            shell: 0,
            order: r.order,
            p: along(o, r.n, r.len - fr),
        }));
        if params.origin_as_free {
            self.extras.push(Extra { shell: 0, order: u32::MAX, p: o });
        }
        // Their shells by chunks, the square roots and divisions four to an instruction.
        let mut d2 = [0.0f64; RAY_CHUNK];
        for chunk in self.extras.chunks_mut(RAY_CHUNK) {
            for (d, e) in d2.iter_mut().zip(chunk.iter()) {
                *d = centre_distance_squared(e.p, o, ds, inv_ds);
            }
            for (e, &d) in chunk.iter_mut().zip(&d2) {
                e.shell = shell_at(d, fr);
            }
        }
        self.sort_extras_by_shell();
        let mut next_extra = 0;
        let mut k = 0u32;
        // Rays that may still have samples: all of them before shell 1, then those whose
        // sample in the last shell was regular.
        let mut live = self.rays.len();
        self.samples.clear();
        self.samples.resize(SAMPLE_BUFFER, [0.0; 3]);
        while live > 0 || next_extra < self.sorted_extras.len() {
            let d = f64::from(k) * fr;
            let end = self.shell_ends.get(k as usize).copied().unwrap_or(next_extra);
            let extras = &self.sorted_extras[next_extra..end];
            next_extra = end;
            let buf: &mut [[f64; 3]; SAMPLE_BUFFER] =
                (&mut self.samples[..SAMPLE_BUFFER]).try_into().expect("a sample buffer");
            let mut n = 0;
            let mut e = 0;
            // Shell 0 has no regular samples.
            if k > 0 {
                debug_assert!(
                    self.rays.iter().filter(|r| d < r.len).all(|r| shell(along(o, r.n, d)) == k),
                    "a sample {d} m along a ray left its shell"
                );
                // One pass over the rays per shell: each extra goes after the regular samples
                // of the rays up to its own (by ray number), before those of the rays after
                // it; a ray no longer than `d` has ended, and writes its sample without
                // counting it. (The origin's number, u32::MAX, is also "no extra left": it
                // follows every ray.)
                let mut next_order = extras.first().map_or(u32::MAX, |x| x.order);
                live = 0;
                for r in &self.rays {
                    while next_order < r.order {
                        n = push_sample(buf, n, extras[e].p, table, inv_ds);
                        e += 1;
                        next_order = extras.get(e).map_or(u32::MAX, |x| x.order);
                    }
                    // Not `push_sample` with a count of 0 or 1 (or a subtraction after it):
                    // that compiles to many more instructions.
                    if n >= SAMPLE_BUFFER {
                        table.add_all::<false>(buf, inv_ds);
                        n = 0;
                    }
                    buf[n] = along(o, r.n, d);
                    let regular = usize::from(d < r.len);
                    n += regular;
                    live += regular;
                }
            }
            for x in &extras[e..] {
                n = push_sample(buf, n, x.p, table, inv_ds);
            }
            table.add_all::<false>(&buf[..n], inv_ds);
            table.append_centroids(&mut out.frees);
            table.clear();
            // The rays that ended stay (writing nothing) until a quarter have: dropping them
            // every shell moved every ray after the first that ended.
            if k > 0 && live <= self.rays.len() - self.rays.len() / 4 {
                self.rays.retain(|r| d < r.len);
            }
            k += 1;
        }
    }

    /// `extras` into `sorted_extras` by shell, a stable counting sort (each shell's stay in ray
    /// order); `shell_ends[k]` becomes where shell k's end.
    fn sort_extras_by_shell(&mut self) {
        let shells = self.extras.iter().map(|e| e.shell as usize + 1).max().unwrap_or(0);
        self.shell_ends.clear();
        self.shell_ends.resize(shells + 1, 0);
        for e in &self.extras {
            self.shell_ends[e.shell as usize + 1] += 1;
        }
        for i in 1..self.shell_ends.len() {
            self.shell_ends[i] += self.shell_ends[i - 1];
        }
        // Each shell's start, moved on as its extras are placed: its end once they all are.
        self.sorted_extras.clear();
        self.sorted_extras.resize(self.extras.len(), Extra::default());
        for &e in &self.extras {
            let at = &mut self.shell_ends[e.shell as usize];
            self.sorted_extras[*at] = e;
            *at += 1;
        }
    }
}

/// A free sample placed by shell rather than by ray: a ray's extra one (`fr` short of its end)
/// or the origin (ray number `u32::MAX`: after every ray).
#[derive(Debug, Clone, Copy, Default)]
struct Extra {
    shell: u32,
    order: u32,
    p: [f64; 3],
}

/// A ray whose free samples [`TrainingBuilder`] has to place: its unit direction `n`, its
/// length, and its number in the scan's order.
///
/// Free samples are summed per voxel in the order la3dm makes them: ray by ray, each ray's
/// regular samples outward and then its extra one, the origin last. The sum of a voxel depends
/// only on the order of its own samples, though, and when the sample spacing `fr` exceeds a
/// voxel's diagonal, every voxel belongs to one **shell**: the distance of its centre from the
/// origin, rounded to a multiple of `fr` ([`shell_of`]). The regular samples of shell k are the
/// k-th of each ray (a voxel holding one has its centre within half a diagonal of `k·fr`); an
/// extra sample, or the origin, falls in the shell of its voxel. So the samples can go in
/// shell by shell, each shell in la3dm's order, with the same bits per voxel, into a table
/// that holds one shell at a time: the voxels at one distance, not the scan's.
///
/// This is why the dense scans' training is fast: ray by ray, their free table of 0.2–0.5 M
/// voxels (tens of MB) missed the caches on most samples. Small scans keep to ray by ray
/// ([`SHELL_MIN_SAMPLES`]).
#[derive(Debug, Clone, Copy)]
struct FreeRay {
    n: [f64; 3],
    len: f64,
    order: u32,
}

/// Whether voxels of edge `ds` fall in one shell each ([`FreeRay`]) with a margin for rounding,
/// for coordinates up to `extent` metres: `fr` exceeds a voxel's diagonal by more than a
/// millionth of the voxel and a billionth of the extent.
fn shells_separate_voxels(ds: f64, fr: f64, extent: f64) -> bool {
    fr > 3f64.sqrt() * ds + 2.0 * (1e-6 * ds + 1e-9 * (extent + 1.0))
}

/// The shell of the voxel holding `p` (inside the key range): the distance of its centre from
/// `o` in multiples of `fr`, rounded (a function of the voxel alone).
fn shell_of(p: [f64; 3], o: [f64; 3], ds: f64, inv_ds: f64, fr: f64) -> u32 {
    shell_at(centre_distance_squared(p, o, ds, inv_ds), fr)
}

/// The squared distance from `o` of the centre of the voxel holding `p` (inside the key range),
/// without branches.
#[inline(always)]
fn centre_distance_squared(p: [f64; 3], o: [f64; 3], ds: f64, inv_ds: f64) -> f64 {
    // The voxel as the table keys it (`v · inv_ds`, floored), and its centre as
    // `CellKey::centre` gives it.
    let c = p.map(|v| (super::cell_points::floor_f64(v * inv_ds) + 0.5) * ds);
    let d = [c[0] - o[0], c[1] - o[1], c[2] - o[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

/// [`shell_of`] from the squared distance of the voxel's centre.
#[inline(always)]
fn shell_at(distance_squared: f64, fr: f64) -> u32 {
    // Through `i32`, which packed conversions have (a shell number is far below 2^31 inside
    // the key range): the same number as `as u32`.
    (distance_squared.sqrt() / fr + 0.5) as i32 as u32
}

/// Writes `p` at `buf[n]` and returns the number of samples in `buf`, handing a full buffer to
/// `table` first.
#[inline(always)]
fn push_sample<S: TableSlot>(
    buf: &mut [[f64; 3]; SAMPLE_BUFFER],
    mut n: usize,
    p: [f64; 3],
    table: &mut VoxelCentroids<S>,
    inv_ds: f64,
) -> usize {
    if n >= SAMPLE_BUFFER {
        table.add_all::<false>(buf, inv_ds);
        n = 0;
    }
    buf[n] = p;
    n + 1
}

/// The point `d` metres from `o` along the unit direction `n`.
#[inline(always)]
fn along(o: [f64; 3], n: [f64; 3], d: f64) -> [f64; 3] {
    [o[0] + n[0] * d, o[1] + n[1] * d, o[2] + n[2] * d]
}

/// Appends the free samples along the unit direction `n` from `o` to `out`: `fr, 2fr, … <
/// ray_len`, plus `ray_len − fr`.
///
/// The regular samples go in as one run: their number first (from an estimate, corrected by
/// the same test `i·fr < ray_len` a sample-by-sample loop would stop on), then one `extend`.
fn free_samples(out: &mut Vec<[f64; 3]>, o: [f64; 3], n: [f64; 3], ray_len: f64, fr: f64) {
    let at = |d: f64| along(o, n, d);
    let below = |i: u32| f64::from(i) * fr < ray_len;
    // Saturating: NaN gives 0, anything past u32::MAX the maximum. Never too low: if
    // `(count + 1)·fr < ray_len` held in floating point, it would hold exactly too (rounding
    // cannot carry a product at or past `ray_len` below it, as `ray_len` is a double), and then
    // `ray_len / fr` would round to at least `count + 1`.
    let mut count = (ray_len / fr) as u32;
    while count > 0 && !below(count) {
        count -= 1;
    }
    debug_assert!(count == u32::MAX || !below(count + 1), "{ray_len} / {fr}: too few samples");
    out.extend((1..=count).map(|i| at(f64::from(i) * fr)));
    if ray_len > fr {
        out.push(at(ray_len - fr));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(max_range_m: f64, mode: RangeMode) -> MapParams {
        MapParams { max_range_m, range_mode: mode, ..Default::default() }
    }

    #[test]
    fn free_samples_stop_where_a_sample_by_sample_loop_does() {
        // Lengths at, just below and just above multiples of the spacing (where the count's
        // estimate and the test `i·fr < len` can disagree), zero, tiny, and not a number.
        let plain = |o: [f64; 3], n: [f64; 3], len: f64, fr: f64| {
            let mut out = Vec::new();
            let mut i = 1u32;
            while f64::from(i) * fr < len {
                out.push(along(o, n, f64::from(i) * fr));
                i += 1;
            }
            if len > fr {
                out.push(along(o, n, len - fr));
            }
            out
        };
        let (o, n) = ([1.0, -2.0, 0.5], [0.6, 0.0, 0.8]);
        let mut cases = vec![0.0, 1e-300, f64::NAN, -1.0];
        for fr in [0.5, 0.1, 0.3, 0.7] {
            for k in 0..200 {
                let len = f64::from(k) * fr;
                cases.extend([len, len.next_down(), len.next_up(), len + 0.5 * fr]);
            }
            for &len in &cases {
                let mut out = vec![[9.0; 3]];
                free_samples(&mut out, o, n, len, fr);
                let want = plain(o, n, len, fr);
                assert_eq!(
                    out[1..].iter().map(|p| p.map(f64::to_bits)).collect::<Vec<_>>(),
                    want.iter().map(|p| p.map(f64::to_bits)).collect::<Vec<_>>(),
                    "length {len:e}, spacing {fr}"
                );
            }
        }
    }

    #[test]
    fn free_samples_follow_la3dm_spacing() {
        // One hit at 2.01 m along x: samples at 0.5, 1.0, 1.5, 2.0 and the extra one at 1.51.
        let mut b = TrainingBuilder::default();
        let p = MapParams { ds_resolution_m: 0.001, origin_as_free: false, ..params(0.0, RangeMode::Drop) };
        let t = b.build(&[[2.01, 0.0, 0.0]], [0.0, 0.0, 0.0], &p);
        assert_eq!(t.hits.len(), 1);
        let mut xs: Vec<f64> = t.frees.iter().map(|f| f[0]).collect();
        xs.sort_by(f64::total_cmp);
        let want = [0.5, 1.0, 1.5, 1.51, 2.0];
        assert_eq!(xs.len(), want.len());
        for (x, w) in xs.iter().zip(want) {
            assert!((x - w).abs() < 1e-6, "{xs:?}");
        }
    }

    #[test]
    fn range_modes() {
        let mut b = TrainingBuilder::default();
        let pts = [[10.0f32, 0.05, 0.05]];
        let drop = b.build(&pts, [0.05, 0.05, 0.05], &params(8.0, RangeMode::Drop));
        assert!(drop.hits.is_empty());
        assert_eq!(drop.frees.len(), 1, "only the origin");
        let trunc = b.build(&pts, [0.05, 0.05, 0.05], &params(8.0, RangeMode::Truncate));
        assert!(trunc.hits.is_empty());
        assert_eq!(trunc.beyond_range, 1);
        let max_x = trunc.frees.iter().map(|f| f[0]).fold(f64::MIN, f64::max);
        assert!(max_x < 8.05 && max_x > 7.5, "free samples stop short of max range: {max_x}");
    }

    #[test]
    fn non_finite_points_are_dropped_and_counted() {
        let mut b = TrainingBuilder::default();
        let t = b.build(
            &[[f32::NAN, 0.0, 0.0], [1.0, f32::INFINITY, 0.0], [1.0, 1.0, 1.0]],
            [0.0; 3],
            &MapParams::default(),
        );
        assert_eq!(t.dropped_points, 2);
        assert_eq!(t.hits.len(), 1);
    }

    /// Emptying a table of tagged slots moves its tag on, and when the tags come round the
    /// slots are emptied for real: a voxel written 2^32 generations back is not found again.
    #[test]
    fn tags_coming_round_empty_the_table() {
        let inv_ds = 10.0;
        let (p, q) = ([0.05, 0.05, 0.05], [0.35, 0.05, 0.05]);
        let mut table = VoxelCentroids::<Slot>::default();
        let centroids = |table: &VoxelCentroids<Slot>| {
            let mut out = Vec::new();
            table.centroids_into(&mut out);
            out
        };
        table.add_all::<true>(&[p], inv_ds);
        assert_eq!(centroids(&table), vec![p]);
        // An ordinary generation later: p's slot is stale, q then p are two new voxels.
        table.clear();
        assert_eq!(table.tag, 2);
        table.add_all::<true>(&[q, p], inv_ds);
        assert_eq!(centroids(&table), vec![q, p]);
        // The last tag before they come round: p's slot was written with tag 2, which the tag
        // after the wrap would take for a full slot if the slots were not emptied.
        table.tag = u32::MAX;
        table.clear();
        table.clear();
        assert_eq!(table.tag, 2);
        table.add_all::<true>(&[q, p], inv_ds);
        assert_eq!(centroids(&table), vec![q, p], "a slot of an old generation was taken as full");
    }

    /// The batched, prefetching table equals a plain map from voxel to sum, bit for bit and in
    /// first-occurrence order, across table growth and with points it must reject.
    #[test]
    fn voxel_table_equals_a_plain_map() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let inv_ds = 10.0;
        let mut table = VoxelCentroids::<Slot>::default();
        let mut compact = VoxelCentroids::<CompactSlot>::default();
        for round in 0..4 {
            // Clustered points (many per voxel) and scattered ones (a new voxel each), so the
            // table grows several times within one call, past the size where rounds get
            // longer (`LARGE_TABLE_BYTES`); then fewer, into that large table, so that the last
            // clear walks the occupied slots instead of emptying the whole table.
            let n = [500, 100_000, 30_000, 200][round];
            assert_eq!(table.is_large(), round >= 2, "round {round} on a large table");
            let pts: Vec<[f64; 3]> = (0..n)
                .map(|i| match i % 97 {
                    0 => [f64::NAN, 0.0, 0.0],
                    1 => [2e5, 0.0, 0.0],
                    // At and around the ends of the key range, on each axis, and an infinity.
                    3 => [0.0, -KEY_LIMIT / inv_ds, 1.0],
                    4 => [0.0, 1.0, (KEY_LIMIT / inv_ds).next_down()],
                    5 => [KEY_LIMIT / inv_ds, 0.0, 0.0],
                    6 => [0.0, 0.0, f64::NEG_INFINITY],
                    // A voxel of its own whose points have negative zeros: its centroid keeps
                    // their signs.
                    2 if round == 1 => [-0.0, -0.0, 500.05],
                    _ if i % 3 == 0 => [0.0; 3].map(|_| rng.random_range(-1.0..1.0)),
                    _ => [0.0; 3].map(|_| rng.random_range(-300.0..300.0)),
                })
                .collect();
            table.clear();
            let rejected = table.add_all::<true>(&pts, inv_ds);
            let mut order = Vec::new();
            let mut sums = std::collections::HashMap::<u64, ([f64; 3], u32)>::new();
            let mut want_rejected = 0;
            for p in &pts {
                let Some(k) = voxel_key(*p, inv_ds) else {
                    want_rejected += 1;
                    continue;
                };
                match sums.entry(k) {
                    std::collections::hash_map::Entry::Vacant(v) => {
                        order.push(k);
                        v.insert((*p, 1));
                    }
                    std::collections::hash_map::Entry::Occupied(mut o) => {
                        let e = o.get_mut();
                        e.0 = [e.0[0] + p[0], e.0[1] + p[1], e.0[2] + p[2]];
                        e.1 += 1;
                    }
                }
            }
            assert_eq!(rejected, want_rejected);
            let want: Vec<[f64; 3]> = order
                .iter()
                .map(|k| {
                    let (s, n) = sums[k];
                    s.map(|v| v / f64::from(n))
                })
                .collect();
            // Bits, so that −0 and 0 differ.
            let bits = |v: &[[f64; 3]]| v.iter().map(|p| p.map(f64::to_bits)).collect::<Vec<_>>();
            let want = bits(&want);
            let mut got = Vec::new();
            table.centroids_into(&mut got);
            assert_eq!(bits(&got), want, "round {round}");
            // Without range tests, for the points inside the range: the same table.
            let inside: Vec<[f64; 3]> =
                pts.iter().copied().filter(|&p| voxel_key(p, inv_ds).is_some()).collect();
            let mut unchecked = VoxelCentroids::<Slot>::default();
            assert_eq!(unchecked.add_all::<false>(&inside, inv_ds), 0);
            let mut got_unchecked = Vec::new();
            unchecked.centroids_into(&mut got_unchecked);
            assert_eq!(bits(&got_unchecked), want, "round {round}, unchecked");
            // Compact slots, for the points within half their span of 0 (most): the same
            // centroids as full keys give those points. Voxels a span apart share a compact key
            // (so the test can fail), which is why the shell path checks a scan's extent.
            let near: Vec<[f64; 3]> =
                inside.iter().copied().filter(|p| p.iter().all(|v| (v * inv_ds).abs() < 4000.0)).collect();
            assert!(near.len() > n / 2, "round {round}: most points are near");
            let mut wide = VoxelCentroids::<Slot>::default();
            wide.add_all::<false>(&near, inv_ds);
            compact.clear();
            compact.add_all::<false>(&near, inv_ds);
            let (mut want_near, mut got_compact) = (Vec::new(), Vec::new());
            wide.centroids_into(&mut want_near);
            compact.centroids_into(&mut got_compact);
            assert_eq!(bits(&got_compact), bits(&want_near), "round {round}, compact slots");
        }
    }

    /// Rays near the end of the voxel key range take the range-tested path, and their samples
    /// beyond it are left out: the training set equals one built by adding every sample with
    /// its range test.
    #[test]
    fn rays_near_the_key_range_limit() {
        let edge = KEY_LIMIT * 0.1;
        let params = MapParams { max_range_m: 0.0, ..Default::default() };
        // A sensor just beyond the range (its first samples are too), one just inside it, one
        // near the other end, and one at home.
        for origin in
            [[edge + 1.0, 0.0, 0.0], [edge - 4.0, 0.0, 0.0], [-edge + 1.0, 3.0, -2.0], [1.0, 2.0, 3.0]]
        {
            let toward = if origin[0] > 0.0 { -1.0 } else { 1.0 };
            let pts: Vec<[f32; 3]> = (0..200)
                .map(|i| {
                    let a = f64::from(i) * 0.031;
                    [origin[0] + toward * (3.0 + a.cos()), origin[1] + 3.5 * a.sin(), origin[2] + 0.3]
                        .map(|v| v as f32)
                })
                .collect();
            let got = TrainingBuilder::default().build(&pts, origin, &params);
            let (hits, frees, rejected) = ray_major_reference(&pts, origin, &params);
            assert_eq!(got.hits, hits, "origin {origin:?}");
            assert_eq!(sorted_bits(&got.frees), sorted_bits(&frees), "origin {origin:?}");
            assert_eq!(rejected > 0, origin[0] > edge, "samples beyond the key range, origin {origin:?}");
        }
    }

    /// The training set the plain way, every point through range-tested tables: hits, free
    /// centroids (ray by ray, each ray's samples outward, the origin last) and the free
    /// samples the table rejected.
    fn ray_major_reference(
        pts: &[[f32; 3]],
        origin: [f64; 3],
        params: &MapParams,
    ) -> (Vec<[f64; 3]>, Vec<[f64; 3]>, usize) {
        let inv_ds = 1.0 / params.ds_resolution_m;
        let mut hits = VoxelCentroids::<Slot>::default();
        let raw: Vec<[f64; 3]> = pts.iter().map(|p| p.map(f64::from)).collect();
        hits.add_all::<true>(&raw, inv_ds);
        let mut centroids = Vec::new();
        hits.centroids_into(&mut centroids);
        let mut samples = Vec::new();
        let mut kept = Vec::new();
        for &h in &centroids {
            let v = [h[0] - origin[0], h[1] - origin[1], h[2] - origin[2]];
            let r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            let mut len = r;
            if params.max_range_m > 0.0 && r > params.max_range_m {
                match params.range_mode {
                    RangeMode::Drop => continue,
                    RangeMode::Truncate => len = params.max_range_m,
                }
            } else {
                kept.push(h);
            }
            free_samples(&mut samples, origin, v.map(|c| c / r), len, params.free_resolution_m);
        }
        if params.origin_as_free {
            samples.push(origin);
        }
        let mut frees = VoxelCentroids::<Slot>::default();
        let rejected = frees.add_all::<true>(&samples, inv_ds);
        let mut want = Vec::new();
        frees.centroids_into(&mut want);
        (kept, want, rejected)
    }

    /// Points as bit patterns, sorted: the multiset, for sets whose order is not a contract.
    fn sorted_bits(points: &[[f64; 3]]) -> Vec<[u64; 3]> {
        let mut bits: Vec<[u64; 3]> = points.iter().map(|p| p.map(f64::to_bits)).collect();
        bits.sort_unstable();
        bits
    }

    /// Free samples shell by shell give every free voxel the same bits as ray by ray: random
    /// scenes large enough for shells, around origins off the grid (negative coordinates too),
    /// with rays ending anywhere in a shell, both range modes, with and without the origin as a
    /// free sample, at sample spacings just above a voxel's diagonal and well above it; and
    /// scans that keep to ray by ray (small, or spacing within the diagonal) are checked too.
    #[test]
    fn shells_give_the_ray_major_centroids() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut builder = TrainingBuilder::default();
        let mut shelled = 0;
        for case in 0..12 {
            let origin =
                [rng.random_range(-50.0..50.0), rng.random_range(-50.0..50.0), rng.random_range(-3.0..3.0)];
            let fr = [0.5, 0.18, 0.3, 0.15][case % 4];
            let params = MapParams {
                free_resolution_m: fr,
                max_range_m: [30.0, 0.0, 20.0][case % 3],
                range_mode: if case % 2 == 0 { RangeMode::Truncate } else { RangeMode::Drop },
                origin_as_free: case % 5 != 0,
                ..Default::default()
            };
            let n = if case == 5 { 40 } else { 2500 };
            // Cases 4 and 10 (unlimited range) have a hit 450 m out, whose shells span more
            // voxels than compact slots tell apart: they take full keys.
            let far = case == 4 || case == 10;
            let mut pts: Vec<[f32; 3]> = (0..n)
                .map(|_| {
                    let d: [f64; 3] = [
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-0.3..0.3),
                    ];
                    let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
                    let r = rng.random_range(0.05..40.0);
                    [0, 1, 2].map(|i| (origin[i] + d[i] / norm * r) as f32)
                })
                .collect();
            if far {
                pts.push([origin[0] + 450.0, origin[1] - 3.0, origin[2]].map(|v| v as f32));
            }
            let got = builder.build(&pts, origin, &params);
            let (hits, frees, rejected) = ray_major_reference(&pts, origin, &params);
            let shells = fr > 3f64.sqrt() * params.ds_resolution_m && n > 1000;
            assert_eq!(builder.by_shell, shells, "case {case}: path taken");
            assert_eq!(builder.compact_shells, shells && !far, "case {case}: slots");
            shelled += usize::from(builder.by_shell);
            assert_eq!(rejected, 0);
            assert_eq!(got.hits, hits, "case {case}");
            assert_eq!(got.frees.len(), frees.len(), "case {case}");
            assert_eq!(sorted_bits(&got.frees), sorted_bits(&frees), "case {case}");
        }
        assert_eq!(shelled, 8, "cases that went shell by shell");
    }

    #[test]
    fn hits_are_voxel_centroids() {
        let mut b = TrainingBuilder::default();
        let t = b.build(
            &[[1.01, 1.01, 1.01], [1.03, 1.05, 1.07], [1.21, 1.0, 1.0]],
            [0.0; 3],
            &MapParams::default(),
        );
        assert_eq!(t.hits.len(), 2);
        assert!((t.hits[0][0] - 1.02).abs() < 1e-6 && (t.hits[0][2] - 1.04).abs() < 1e-6);
    }

    /// algorithm.md §4: the exact training-set sizes of la3dm's semantics on the sample data
    /// (ds 0.1, fr 0.5, max range 8, rays beyond range dropped). Skipped without `../shared`.
    #[test]
    fn sample_data_training_counts_match_la3dm() {
        let dir =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/la3dm/sim_structured");
        if !dir.is_dir() {
            eprintln!("skipped: {} not present", dir.display());
            return;
        }
        let voxels = [1918, 1459, 446, 544, 1414, 1733, 1737, 1919, 1587, 1398, 1779, 2162];
        let kept = [1720, 1297, 446, 544, 1049, 1604, 1677, 1481, 1384, 1210, 1728, 1958];
        let total = [5546, 3966, 711, 1076, 3806, 4672, 4655, 6591, 4516, 4228, 4699, 6561];
        let params = params(8.0, RangeMode::Drop);
        let mut b = TrainingBuilder::default();
        for i in 0..12 {
            let bytes = std::fs::read(dir.join(format!("sim_structured_{}.pcd", i + 1))).unwrap();
            let cloud = crate::io::pcd::read_pcd(&bytes).unwrap();
            let v = cloud.viewpoint.unwrap();
            let t = b.build(&cloud.points, [v[0], v[1], v[2]], &params);
            assert_eq!(
                (t.hit_voxels, t.hits.len(), t.len()),
                (voxels[i], kept[i], total[i]),
                "scan {}",
                i + 1
            );
        }
    }
}
