//! Free-space sampling along the rays of a scan: the regular samples of a ray
//! ([`free_samples`]), and for large scans the same samples taken shell by shell ([`FreeRay`]),
//! so that the voxel table holds one shell's voxels at a time.

use super::training::{RAY_CHUNK, SAMPLE_BUFFER, TrainingBuilder, TrainingSet};
use super::voxel_table::{TableSlot, VoxelCentroids};
use crate::core::params::MapParams;

impl TrainingBuilder {
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
    ///
    /// [`CompactSlot`]: super::voxel_table::CompactSlot
    /// [`Slot`]: super::voxel_table::Slot
    pub(super) fn frees_by_shell<S: TableSlot>(
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
pub(super) struct Extra {
    pub(super) shell: u32,
    pub(super) order: u32,
    pub(super) p: [f64; 3],
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
///
/// [`SHELL_MIN_SAMPLES`]: super::training::SHELL_MIN_SAMPLES
#[derive(Debug, Clone, Copy)]
pub(super) struct FreeRay {
    pub(super) n: [f64; 3],
    pub(super) len: f64,
    pub(super) order: u32,
}

/// Whether voxels of edge `ds` fall in one shell each ([`FreeRay`]) with a margin for rounding,
/// for coordinates up to `extent` metres: `fr` exceeds a voxel's diagonal by more than a
/// millionth of the voxel and a billionth of the extent.
pub(super) fn shells_separate_voxels(ds: f64, fr: f64, extent: f64) -> bool {
    fr > 3f64.sqrt() * ds + 2.0 * (1e-6 * ds + 1e-9 * (extent + 1.0))
}

/// The shell of the voxel holding `p` (inside the key range): the distance of its centre from
/// `o` in multiples of `fr`, rounded (a function of the voxel alone).
pub(super) fn shell_of(p: [f64; 3], o: [f64; 3], ds: f64, inv_ds: f64, fr: f64) -> u32 {
    shell_at(centre_distance_squared(p, o, ds, inv_ds), fr)
}

/// The squared distance from `o` of the centre of the voxel holding `p` (inside the key range),
/// without branches.
#[inline(always)]
fn centre_distance_squared(p: [f64; 3], o: [f64; 3], ds: f64, inv_ds: f64) -> f64 {
    // The voxel as the table keys it (`v · inv_ds`, floored), and its centre as
    // `CellKey::centre` gives it.
    let c = p.map(|v| (super::floor::floor_f64(v * inv_ds) + 0.5) * ds);
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
pub(super) fn push_sample<S: TableSlot>(
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
pub(super) fn along(o: [f64; 3], n: [f64; 3], d: f64) -> [f64; 3] {
    [o[0] + n[0] * d, o[1] + n[1] * d, o[2] + n[2] * d]
}

/// Appends the free samples along the unit direction `n` from `o` to `out`: `fr, 2fr, … <
/// ray_len`, plus `ray_len − fr`.
///
/// The regular samples go in as one run: their number first (from an estimate, corrected by
/// the same test `i·fr < ray_len` a sample-by-sample loop would stop on), then one `extend`.
pub(super) fn free_samples(out: &mut Vec<[f64; 3]>, o: [f64; 3], n: [f64; 3], ray_len: f64, fr: f64) {
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
