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

use super::free_space::{Extra, FreeRay, free_samples, shells_separate_voxels};
use super::voxel_table::{COMPACT_SPAN, COMPACT_VOXELS, CompactSlot, KEY_LIMIT, VoxelCentroids};
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

/// Builds training sets; holds scratch space so repeated scans allocate nothing new.
#[derive(Debug, Default)]
pub struct TrainingBuilder {
    pub(super) hits: VoxelCentroids,
    pub(super) frees: VoxelCentroids,
    /// The free samples of one shell, when a scan's fit [`CompactSlot`]s (see
    /// [`Self::frees_by_shell`]).
    pub(super) shell_frees: VoxelCentroids<CompactSlot>,
    pub(super) centroids: Vec<[f64; 3]>,
    /// Points on their way into `hits` or `frees`, in the order they are added.
    pub(super) samples: Vec<[f64; 3]>,
    /// The scan's rays with free samples.
    pub(super) rays: Vec<FreeRay>,
    /// Per ray with one, the extra sample `fr` short of its end (and the origin); then the
    /// same by shell.
    pub(super) extras: Vec<Extra>,
    pub(super) sorted_extras: Vec<Extra>,
    /// Counting sort of `extras` by shell.
    pub(super) shell_ends: Vec<usize>,
    /// Whether the last scan's free samples went in shell by shell ([`FreeRay`]), and
    /// whether into a table of [`CompactSlot`]s.
    pub(super) by_shell: bool,
    pub(super) compact_shells: bool,
}

/// Points gathered before they go into a voxel table (a few rays' worth of free samples).
pub(super) const SAMPLE_BUFFER: usize = 1024;

/// Items a loop of square roots and divisions takes at a time, so that they go four to an
/// instruction: the hits whose rays [`TrainingBuilder::build_into`] measures, the extra samples
/// whose shells [`TrainingBuilder::frees_by_shell`] finds.
pub(super) const RAY_CHUNK: usize = 64;

/// Free samples (about) from which a scan's go in shell by shell ([`FreeRay`]): 2^16, whose
/// voxels, up to 72 bytes each in slots, sums and keys, would fill more than a 2 MB L2 cache
/// in one table. With fewer, the scan's table stays in L2 anyway, and sorting each ray's extra
/// sample by shell and a table round per shell are work for nothing: the 12 sample scans
/// (1k to 17k samples each) took a third longer to train (0.195 ms against 0.147).
pub(super) const SHELL_MIN_SAMPLES: f64 = 65536.0;

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
}

#[cfg(test)]
#[path = "training_tests.rs"]
mod tests;
