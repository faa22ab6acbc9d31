//! The lane-wise evidence path: fixed W³ windows per point, accumulated in a per-bucket brick.
//!
//! A training point at `p = c + ½ + f` (cell `c`, offset `f ∈ [−½, ½)` per axis, cell units)
//! reaches only cells whose axis offset `o` from `c` satisfies `|o − f| < L` (`L` = ell in
//! cells). Per axis those are at most `W = ⌈2L⌉` consecutive offsets starting at
//! `⌊f − L⌋ + 1`. So every point evaluates the same W×W×W window — 64 pairs for la3dm's
//! defaults (L = 2) — with no branches: pairs outside the ball land on the table's cut-off and
//! add exactly 0. The loop over a window's lanes vectorises (coordinates in f64, the table
//! interpolation in i32 lanes, see [`KernelTable::quantized_lane`]).
//!
//! With `sub_cells = n` (the default, 8), training points sit at sub-cell centres
//! ([`to_cell_units`](super::cell_points::to_cell_units)), so `f` takes only `n` values per axis
//! and a window is one of `n³` ([`SnappedWindows`], 128 KiB for la3dm's geometry): computed once
//! per map geometry by the same arithmetic, then read and added (about a third less evidence
//! time than computing each window). Placing such a point is integer arithmetic too, read from a table (`SnappedWindows::place`): the
//! float-to-int casts of `Brick::place` (saturating, NaN-checked) cost as much as the old
//! window's lookups.
//!
//! Points arrive bucketed by the `S`³ blocks their cell lies in (see [`super::scatter`]). A
//! bucket's windows all fall inside a brick of `(S·B + 2M)³` cells — its blocks plus a margin
//! of `M` cells — so a window is `W²` contiguous rows of `W` cells in the brick, added without
//! any block lookup. When the bucket is done, the brick is folded into the (up to (S + 2)³)
//! blocks it overlaps, only the regions some window touched, and zeroed on the way.
//!
//! The brick holds `u32` (half the memory traffic of the blocks' `i64`): one pair adds at most
//! `2^F` ([`FIXED_SHIFT`]) and masses are never negative, so up to [`BRICK_POINTS`] points of a
//! label fit without overflow, and any number of them while no cell holds two (see
//! `CellMarks`); otherwise a bucket is folded every [`BRICK_POINTS`] points.
//!
//! Bits equal the reference: every lane computes `(o − f)²` per axis and sums z, y, then x,
//! exactly as [`pair_coord`](super::cell_points::pair_coord).

use super::cell_points::{CellPoint, PairGeometry, SUB_FRAC, SubPoint, split_point};
use super::floor::floor_i32;
use super::kernel::{KernelTable, round_to_i64};
use crate::core::key::BLOCK_EDGE;
use crate::core::posterior::FIXED_SHIFT;

const B: usize = BLOCK_EDGE as usize;

/// Blocks per bucket edge: a bucket, and the brick its windows go to, span `S`³ blocks. Two
/// blocks a side (a 20³ brick for la3dm's geometry, 62 KiB for both labels): a block's
/// margins are folded into its neighbours, and inside a bucket of 2³ blocks there are none.
pub const S: usize = 2;
/// Cells per bucket edge.
pub const SB: usize = S * B;
/// Regions per brick axis: the low margin, the `S` blocks, the high margin.
const R: usize = S + 2;

/// Points of one label a brick takes between folds: each adds at most `2^F` to a cell, and
/// brick cells are `u32` (masses are never negative), so `BRICK_POINTS · 2^F < 2^32`.
///
/// No limit applies while no bucket cell holds two points of a label (see `CellMarks`), which
/// is the rule for voxel centroids with `ds` equal to the cell edge: a bit per cell and label
/// costs ~15 instructions a point, and then a bucket is folded once, at its end.
pub const BRICK_POINTS: u32 = u32::MAX >> FIXED_SHIFT;

/// `SPREAD[axis][mask]`: the region mask (bit `x + R·(y + R·z)` for region (x, y, z)) of every
/// region whose coordinate along `axis` is in the `R`-bit `mask`.
const SPREAD: [[u64; 1 << R]; 3] = {
    let mut t = [[0u64; 1 << R]; 3];
    let mut axis = 0;
    while axis < 3 {
        let mut mask = 0;
        while mask < 1 << R {
            let mut bit = 0;
            while bit < R * R * R {
                let r = [bit % R, bit / R % R, bit / (R * R)];
                if mask >> r[axis] & 1 != 0 {
                    t[axis][mask] |= 1 << bit;
                }
                bit += 1;
            }
            mask += 1;
        }
        axis += 1;
    }
    t
};

/// Window size `W` and brick margin `M` for a kernel length (cells), if the lane path has a
/// compiled width for it.
pub fn window_shape(ell_cells: f64) -> Option<(usize, usize)> {
    let w = (2.0 * ell_cells).ceil();
    if !(1.0..=6.0).contains(&w) {
        return None;
    }
    let w = w as i32;
    // Smallest start offset (f → −½) and largest end offset (f → ½).
    let left = -(floor_i32(-0.5 - ell_cells) + 1);
    let right = floor_i32(0.5 - ell_cells) + w;
    Some((w as usize, left.max(right).max(0) as usize))
}

/// Accumulates one bucket's windows (occupied mass `a`, free mass `b`) in a dense brick.
#[derive(Debug, Default)]
pub struct Brick {
    /// Brick edge `SB + 2M` and margin `M`.
    edge: usize,
    margin: usize,
    pub a: Vec<u32>,
    pub b: Vec<u32>,
    /// Points added since the last fold, per label (at most `cap` each).
    points: [u32; 2],
    /// Per label, the points the brick takes between folds: any number while no bucket cell
    /// holds two of them (see [`CellMarks`]), [`BRICK_POINTS`] once one does.
    cap: [u32; 2],
    /// Which bucket cells hold a point of each label since the last fold.
    marks: CellMarks,
    /// Per label (0 = a, 1 = b): bit `x + R·(y + R·z)` set when a window touched region
    /// (x, y, z); along an axis region 0 is the low margin, 1 to `S` the bucket's blocks and
    /// `S + 1` the high margin.
    pub touched: [u64; 2],
}

/// Words of [`CellMarks`] per label: a bit per cell of a bucket.
const MARK_WORDS: usize = SB * SB * SB / 64;

/// Per label, a bit per cell of the bucket: set when a point of that label in the cell was
/// added since the last fold.
///
/// While no cell holds two points of a label, a brick cell sums the windows of at most
/// `(2M + 1)³` of them (those whose cell lies within the margin `M` of it on every axis), each
/// adding at most `2^F`: 125 · 2^F < 2^32 for la3dm's geometry (M = 2), so the brick takes
/// any number of them. Training points are voxel centroids, and with `ds` equal to the cell
/// edge (the default) a cell holds at most one of each label: rounding can put a centroid on
/// its voxel's far side, which the marks catch, and a bucket then folds every [`BRICK_POINTS`]
/// points as before.
#[derive(Debug, Clone)]
struct CellMarks([u64; 2 * MARK_WORDS]);

impl Default for CellMarks {
    fn default() -> Self {
        Self([0; 2 * MARK_WORDS])
    }
}

/// True when a brick of margin `margin` cannot overflow while no cell holds two points of a
/// label: `(2M + 1)³ ≤ BRICK_POINTS` (M ≤ 2, windows up to 4 cells wide).
const fn unique_cells_fit(margin: usize) -> bool {
    let side = 2 * margin as u64 + 1;
    side * side * side <= BRICK_POINTS as u64
}

impl Brick {
    pub fn reset(&mut self, margin: usize) {
        let edge = SB + 2 * margin;
        if self.edge != edge {
            *self = Self { edge, margin, ..Self::default() };
            self.a = vec![0; edge * edge * edge];
            self.b = vec![0; edge * edge * edge];
        }
        self.folded();
    }

    /// Marks the brick folded (its cells are zero again).
    pub fn folded(&mut self) {
        self.touched = [0; 2];
        self.points = [0; 2];
        self.cap = [if unique_cells_fit(self.margin) { u32::MAX } else { BRICK_POINTS }; 2];
        self.marks = CellMarks::default();
    }

    /// Marks bucket cell `cell` (`x + SB·(y + SB·z)`) as holding a point of label `label`;
    /// false when the brick must be folded before it takes that point (the marks then need
    /// no undoing: a fold clears them). [`Self::note`] counts the point once its window is in.
    #[inline(always)]
    fn admit(&mut self, label: usize, cell: usize) -> bool {
        let word = &mut self.marks.0[(label * MARK_WORDS + cell / 64) % (2 * MARK_WORDS)];
        let bit = 1u64 << (cell % 64);
        if *word & bit != 0 {
            self.cap[label] = BRICK_POINTS;
        }
        *word |= bit;
        self.points[label] < self.cap[label]
    }

    pub fn edge(&self) -> usize {
        self.edge
    }

    pub fn margin(&self) -> usize {
        self.margin
    }

    /// The region (0 to `S + 1`) of brick coordinate `i` along an axis.
    #[inline(always)]
    fn region(&self, i: usize) -> u32 {
        if i < self.margin { 0 } else { ((i - self.margin) / B + 1).min(S + 1) as u32 }
    }

    /// Where the window of the point `p` (cell units) lies: its offset `f` from its cell's
    /// centre, the first window offset per axis, the brick index of the window's first cell
    /// and the regions it touches. `bucket_origin` is the first cell of the bucket (the point's
    /// cell must lie in the bucket).
    #[inline(always)]
    pub(crate) fn place<const W: usize>(
        &self,
        p: [f64; 3],
        bucket_origin: [i32; 3],
        ell_cells: f64,
    ) -> Placement {
        let (c, f) = split_point(p);
        let start = f.map(|v| window_start(v, ell_cells));
        let cell = std::array::from_fn(|a| c[a] - bucket_origin[a]);
        let (at, regions) = self.locate::<W>(std::array::from_fn(|a| cell[a] + start[a]));
        Placement { f, start, at, regions, cell: bucket_cell(cell) }
    }

    /// The brick index of a window's first cell and the regions the window touches, from that
    /// cell's offset (per axis) from the first cell of the bucket.
    #[inline(always)]
    fn locate<const W: usize>(&self, first: [i32; 3]) -> (usize, u64) {
        let mut base = [0usize; 3];
        let mut regions = [0u32; 3];
        for a in 0..3 {
            // In the brick: the bucket's cells start after the margin.
            let b = first[a] as isize + self.margin as isize;
            debug_assert!(b >= 0 && b as usize + W <= self.edge, "window outside the brick");
            base[a] = b as usize;
            regions[a] = self.axis_regions::<W>(base[a]);
        }
        let e = self.edge;
        let regions =
            SPREAD[0][regions[0] as usize] & SPREAD[1][regions[1] as usize] & SPREAD[2][regions[2] as usize];
        ((base[2] * e + base[1]) * e + base[0], regions)
    }

    /// The regions (along one axis, as an `R`-bit mask) of a window whose first cell is at
    /// brick coordinate `base` (a window spans at most two: W ≤ 6 < B).
    #[inline(always)]
    fn axis_regions<const W: usize>(&self, base: usize) -> u32 {
        let (r0, r1) = (self.region(base), self.region(base + W - 1));
        (0b11 >> (1 - (r1 - r0))) << r0
    }

    /// Records one added window of label `hit` that touched `regions`.
    #[inline(always)]
    pub(crate) fn note(&mut self, hit: bool, regions: u64) {
        let label = usize::from(!hit);
        debug_assert!(self.points[label] < self.cap[label], "brick not folded in time");
        self.points[label] += 1;
        self.touched[label] |= regions;
    }

    /// Adds the windows of `pts`, all in the bucket starting at cell `bucket_origin`, up to the
    /// first that needs a fold first; returns how many it added. With `snapped`, the points
    /// sit on its sub-cell centres and their windows are read from it instead of computed.
    pub fn add_points<const W: usize, const W3: usize>(
        &mut self,
        pts: &[CellPoint],
        bucket_origin: [i32; 3],
        geo: &PairGeometry,
        table: &KernelTable,
        snapped: Option<&SnappedWindows>,
    ) -> usize {
        // The margin of width W is ⌈W/2⌉ (see `window_shape`): a brick edge known at compile
        // time makes the window's row offsets constants, checked once per window, not per row.
        let e = SB + 2 * W.div_ceil(2);
        assert_eq!(e, self.edge, "a brick of width {W}'s edge");
        match snapped {
            Some(windows) => {
                return self.add_snapped::<W, W3, _>(pts, windows, |p| {
                    debug_assert_eq!(split_point(p).0.map(|c| c & !(SB as i32 - 1)), bucket_origin);
                    windows.place(p)
                });
            }
            None => {
                for (i, &(p, hit)) in pts.iter().enumerate() {
                    let pl = self.place::<W>(p, bucket_origin, geo.ell_cells);
                    if !self.admit(usize::from(!hit), pl.cell) {
                        return i;
                    }
                    let cells = if hit { &mut self.a } else { &mut self.b };
                    add_window::<W, W3>(&window_axes::<W>(pl.start, pl.f), geo.scale, table, cells, pl.at, e);
                    self.note(hit, pl.regions);
                }
            }
        }
        pts.len()
    }

    /// [`Self::add_points`] for points at sub-cell centres given as [`SubPoint`]s, whose
    /// windows are read from `windows`. Not inlined: in its caller the loop had fewer
    /// registers and ran more instructions.
    #[inline(never)]
    pub fn add_sub_points<const W: usize, const W3: usize>(
        &mut self,
        pts: &[SubPoint],
        windows: &SnappedWindows,
    ) -> usize {
        self.add_snapped::<W, W3, _>(pts, windows, |q| windows.place_sub_point(q))
    }

    /// The windows of points at sub-cell centres, read from `windows` where `place` (one of
    /// [`SnappedWindows`]' placements) says they lie, as [`Self::add_points`] adds them.
    #[inline(always)]
    fn add_snapped<const W: usize, const W3: usize, T: Copy>(
        &mut self,
        pts: &[(T, bool)],
        windows: &SnappedWindows,
        place: impl Fn(T) -> (usize, u64, usize, usize),
    ) -> usize {
        let e = SB + 2 * W.div_ceil(2);
        assert_eq!(e, self.edge, "a brick of width {W}'s edge");
        assert_eq!(windows.brick_edge, e, "windows placed for another brick");
        for (i, &(p, hit)) in pts.iter().enumerate() {
            let (at, regions, window, cell) = place(p);
            if !self.admit(usize::from(!hit), cell) {
                return i;
            }
            let cells = if hit { &mut self.a } else { &mut self.b };
            add_values::<W, W3>(windows.window::<W3>(window), cells, at, e);
            self.note(hit, regions);
        }
        pts.len()
    }
}

/// The first window offset along an axis for a point at offset `f` from its cell's centre.
#[inline(always)]
fn window_start(f: f64, ell_cells: f64) -> i32 {
    floor_i32(f - ell_cells) + 1
}

/// Squared axis distances `(start + k − f)²` of a window's W offsets, per axis.
#[inline(always)]
fn window_axes<const W: usize>(start: [i32; 3], f: [f64; 3]) -> [[f64; W]; 3] {
    std::array::from_fn(|a| {
        std::array::from_fn(|k| {
            let d = f64::from(start[a] + k as i32) - f[a];
            d * d
        })
    })
}

/// Largest table of [`SnappedWindows`] built, in bytes (la3dm's geometry at 8 sub-cells:
/// 128 KiB); a geometry that needs more computes its windows.
const MAX_SNAPPED_BYTES: usize = 1 << 20;

/// Every window a point at a sub-cell centre can have. With `sub_cells = n`, a point's offset
/// from its cell's centre is one of `n` values per axis ([`to_cell_units`]), so its W³ pair
/// values are one of `n³` windows: computed once per geometry by the same arithmetic as a
/// computed window, then read and added (a few vector adds per window instead of W³ table
/// lookups).
///
/// [`to_cell_units`]: super::cell_points::to_cell_units
#[derive(Debug, Default)]
pub struct SnappedWindows {
    /// What `values` was built for: ell (bits), scale (bits), sub-cells, W.
    built_for: (u64, u64, u32, usize),
    /// `n = 2^shift` sub-cells per cell edge.
    shift: u32,
    /// The edge of the bricks the windows are placed in (see [`Brick`]).
    brick_edge: usize,
    /// Per cell `l` of a bucket and sub-cell `k` along an axis, at `l·n + k` (the low bits of a
    /// point's sub-cell index), per axis: where the point and its window lie (see
    /// [`AxisPlace`]).
    places: Vec<[AxisPlace; 3]>,
    /// `n³` windows of W³ values; window `kx + n·(ky + n·kz)` for sub-cell `k` per axis.
    values: Vec<i32>,
}

impl SnappedWindows {
    /// Makes these the windows of width W for `geo`; false (and nothing built) when `geo`
    /// keeps points where they are or the table would exceed 1 MiB.
    pub fn prepare<const W: usize, const W3: usize>(
        &mut self,
        geo: &PairGeometry,
        table: &KernelTable,
    ) -> bool {
        let n = geo.sub_cells as usize;
        if n == 0 || n * n * n * W3 * size_of::<i32>() > MAX_SNAPPED_BYTES {
            return false;
        }
        let built_for = (geo.ell_cells.to_bits(), geo.scale.to_bits(), geo.sub_cells, W);
        if self.built_for == built_for && !self.values.is_empty() {
            return true;
        }
        self.values.clear();
        self.values.reserve(n * n * n * W3);
        let offset = |k: usize| Self::offset(k, n);
        let mut window = [0i32; W3];
        for kz in 0..n {
            for ky in 0..n {
                for kx in 0..n {
                    let f = [offset(kx), offset(ky), offset(kz)];
                    let axis = window_axes::<W>(f.map(|v| window_start(v, geo.ell_cells)), f);
                    window_values_portable::<W, W3>(&axis, geo.scale, table, &mut window);
                    self.values.extend_from_slice(&window);
                }
            }
        }
        let (_, margin) = window_shape(geo.ell_cells).expect("a window of width W");
        let e = SB + 2 * margin;
        let mut probe = Brick::default();
        probe.reset(margin);
        self.places = (0..SB * n)
            .map(|i| {
                let (l, k) = (i / n, i % n);
                // The brick coordinate of the window's first cell, for a point in cell l of the
                // bucket (the bucket's cells start after the margin).
                let first = (l as i32 + window_start(offset(k), geo.ell_cells) + margin as i32) as usize;
                let regions = probe.axis_regions::<W>(first) as usize;
                std::array::from_fn(|a| AxisPlace {
                    step: (first * e.pow(a as u32)) as u32,
                    cell: (l * SB.pow(a as u32)) as u32,
                    spread: SPREAD[a][regions],
                })
            })
            .collect();
        (self.built_for, self.shift, self.brick_edge) = (built_for, geo.sub_cells.trailing_zeros(), e);
        true
    }

    /// Where the window of a point at a sub-cell centre lies in the brick of its bucket: the
    /// brick index of the window's first cell, the regions the window touches (see
    /// [`Brick::touched`]), the window's index here and the point's cell in the bucket (see
    /// [`Placement::cell`]). The sub-cell index per axis,
    /// `floor(p·n)`, is `p·n − ½` exactly, rounded without a saturating cast; its low bits
    /// are the cell in the bucket and the sub-cell, whose placement is read from a table.
    #[inline(always)]
    pub(crate) fn place(&self, p: [f64; 3]) -> (usize, u64, usize, usize) {
        let n = f64::from(1u32 << self.shift);
        let sub: [i64; 3] = std::array::from_fn(|a| {
            let sub = round_to_i64(p[a] * n - 0.5);
            debug_assert!((sub as f64 + 0.5) / n == p[a], "point not at a sub-cell centre: {p:?}");
            sub
        });
        self.place_sub(sub)
    }

    /// [`Self::place`] for a [`SubPoint`]'s coordinates (whose sub-cell index per axis is
    /// `floor(q / 2^(SUB_FRAC − shift))`, a shift).
    #[inline(always)]
    pub(crate) fn place_sub_point(&self, q: [i32; 3]) -> (usize, u64, usize, usize) {
        self.place_sub(q.map(|v| i64::from(v >> (SUB_FRAC - self.shift))))
    }

    /// [`Self::place`] from the point's sub-cell index per axis, `floor(p·n)`.
    #[inline(always)]
    fn place_sub(&self, sub: [i64; 3]) -> (usize, u64, usize, usize) {
        let (mut at, mut regions, mut window, mut cell) = (0usize, u64::MAX, 0usize, 0usize);
        for a in 0..3 {
            let sub = sub[a];
            let place = self.places[(sub & (((SB as i64) << self.shift) - 1)) as usize][a];
            at += place.step as usize;
            regions &= place.spread;
            window |= ((sub & ((1 << self.shift) - 1)) as usize) << (self.shift as usize * a);
            cell += place.cell as usize;
        }
        (at, regions, window, cell)
    }

    /// The offset from its cell's centre of sub-cell `k`'s centre: what [`split_point`] gives
    /// for a point placed there (exact: `n` is a power of two).
    fn offset(k: usize, n: usize) -> f64 {
        (k as f64 + 0.5) / n as f64 - 0.5
    }

    /// Window `i` (see [`Self::place`]).
    #[inline(always)]
    fn window<const W3: usize>(&self, i: usize) -> &[i32; W3] {
        self.values[i * W3..(i + 1) * W3].try_into().expect("W3 values per window")
    }
}

/// Along one axis, for a point in a given cell of its bucket and sub-cell (see
/// [`SnappedWindows::place`]): the brick index step of the window's first cell (its brick
/// coordinate times the axis' stride), the step of the point's cell in [`Placement::cell`],
/// and the [`SPREAD`] of the regions the window touches.
#[derive(Debug, Clone, Copy)]
struct AxisPlace {
    step: u32,
    cell: u32,
    spread: u64,
}

/// Where one point's window lies in a brick (see [`Brick::place`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Placement {
    /// The point's offset from its cell's centre, per axis, in [−½, ½).
    pub f: [f64; 3],
    /// The window's first offset from the point's cell, per axis.
    pub start: [i32; 3],
    /// Brick index of the window's first cell.
    pub at: usize,
    /// Regions the window touches (see [`Brick::touched`]).
    pub regions: u64,
    /// The point's cell in its bucket, `x + SB·(y + SB·z)`.
    pub cell: usize,
}

/// The index `x + SB·(y + SB·z)` of the cell at offset `c` (each in `0..SB`) from a bucket's
/// first cell.
#[inline(always)]
fn bucket_cell(c: [i32; 3]) -> usize {
    debug_assert!(c.iter().all(|v| (0..SB as i32).contains(v)), "cell {c:?} outside the bucket");
    c.iter().rev().fold(0, |i, &v| i * SB + v as usize)
}

/// Adds one window's W³ pair values to the brick `cells` (edge `e`), whose first cell is `at`.
#[inline(always)]
fn add_window<const W: usize, const W3: usize>(
    axis: &[[f64; W]; 3],
    scale: f64,
    table: &KernelTable,
    cells: &mut [u32],
    at: usize,
    e: usize,
) {
    if W == 4 {
        let axis4: [[f64; 4]; 3] = std::array::from_fn(|a| std::array::from_fn(|k| axis[a][k]));
        if super::simd::add_window_w4(&axis4, scale, table, cells, at, e) {
            return;
        }
    }
    let mut vals = [0i32; W3];
    window_values_portable::<W, W3>(axis, scale, table, &mut vals);
    add_values::<W, W3>(&vals, cells, at, e);
}

/// Adds a window's W³ values (z-major, then y, then x) to the brick `cells` (edge `e`), whose
/// first cell is `at`.
///
/// Every row is added, zero or not. No row is zero in every window, so none can be left out at
/// compile time (for la3dm's geometry: a window starts where its point's offset puts it, and for a point 1/16 cell past its cell's centre the corner rows lie 1.5
/// cells away, inside the kernel's 2); leaving out each window's own zero rows would make the
/// row loop's length vary from point to point, a branch no predictor learns.
#[inline(always)]
fn add_values<const W: usize, const W3: usize>(vals: &[i32; W3], cells: &mut [u32], at: usize, e: usize) {
    let cells = &mut cells[at..at + ((W - 1) * e + W - 1) * e + W];
    for z in 0..W {
        for y in 0..W {
            let from = (z * e + y) * e;
            let row = &mut cells[from..from + W];
            let v = &vals[(z * W + y) * W..(z * W + y + 1) * W];
            for x in 0..W {
                // Window values are kernel masses, never negative.
                row[x] += v[x] as u32;
            }
        }
    }
}

/// The W³ pair values of one window, z-major then y then x (the reference for the AVX2 path).
pub(crate) fn window_values_portable<const W: usize, const W3: usize>(
    axis: &[[f64; W]; 3],
    scale: f64,
    table: &KernelTable,
    out: &mut [i32; W3],
) {
    let mut d2 = [0f64; W3];
    for z in 0..W {
        for y in 0..W {
            let row = axis[2][z] + axis[1][y];
            for x in 0..W {
                d2[(z * W + y) * W + x] = row + axis[0][x];
            }
        }
    }
    for (o, &d) in out.iter_mut().zip(&d2) {
        *o = table.quantized_lane(KernelTable::lane_coordinate(d, scale));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::integrate::cell_points::to_cell_units;

    /// Every sub-cell position in every cell of a bucket, in buckets of either sign: the table
    /// placement finds the brick index and regions of [`Brick::place`], and the precomputed
    /// window is the computed one.
    fn snapped_equals_computed<const W: usize, const W3: usize>(ell_m: f64, n: u32) {
        let geo = PairGeometry::new(0.1, ell_m, n);
        let table = KernelTable::new();
        let (w, margin) = window_shape(geo.ell_cells).expect("a window width");
        assert_eq!(w, W);
        let mut windows = SnappedWindows::default();
        assert!(windows.prepare::<W, W3>(&geo, &table), "built for {n} sub-cells, W = {W}");
        let mut brick = Brick::default();
        brick.reset(margin);
        let n = n as usize;
        for bucket in [[0, 0, 0], [-1, 2, -3]] {
            let origin = bucket.map(|b| b * SB as i32);
            for (sub, shift) in (0..n * n * n).flat_map(|sub| (0..SB).map(move |s| (sub, s))) {
                let k = [sub % n, sub / n % n, sub / (n * n)];
                // A point in cell (k + shift + 3a) mod S·B of the bucket along axis a, at
                // sub-cell k.
                let cell = [0, 1, 2].map(|a| origin[a] + ((k[a] + shift + 3 * a) % SB) as i32);
                let metres: [f64; 3] = std::array::from_fn(|a| {
                    (f64::from(cell[a]) + (k[a] as f64 + 0.3) / n as f64) * geo.res_m
                });
                let p = to_cell_units(metres, &geo);
                let pl = brick.place::<W>(p, origin, geo.ell_cells);
                let (at, regions, i, in_bucket) = windows.place(p);
                assert_eq!((at, regions, in_bucket), (pl.at, pl.regions, pl.cell), "n {n}, sub-cell {k:?}");
                assert_eq!(
                    in_bucket,
                    bucket_cell([0, 1, 2].map(|a| cell[a] - origin[a])),
                    "n {n}, sub-cell {k:?}"
                );
                let mut computed = [0i32; W3];
                window_values_portable::<W, W3>(
                    &window_axes::<W>(pl.start, pl.f),
                    geo.scale,
                    &table,
                    &mut computed,
                );
                assert_eq!(windows.window::<W3>(i), &computed, "n {n}, sub-cell {k:?}");
            }
        }
    }

    #[test]
    fn snapped_windows_equal_computed_windows() {
        for n in [1, 2, 4, 8, 16] {
            snapped_equals_computed::<4, 64>(0.2, n);
        }
        snapped_equals_computed::<6, 216>(0.3, 8);
        snapped_equals_computed::<3, 27>(0.14, 8);
    }

    /// The brick margin of a window of width W is ⌈W/2⌉, which `Brick::add_points` and the fold
    /// rely on to know the brick's edge at compile time.
    #[test]
    fn margins_follow_from_widths() {
        for i in 1..=3000 {
            let ell_cells = f64::from(i) * 0.001;
            if let Some((w, m)) = window_shape(ell_cells) {
                assert_eq!(m, w.div_ceil(2), "ell {ell_cells} cells");
            }
        }
        assert_eq!(window_shape(2.0), Some((4, 2)), "la3dm's geometry");
    }

    /// A bucket with a point of each label in every one of its cells, each at the sub-cell
    /// nearest the centre (the largest window values), goes into the brick without a fold, and
    /// no brick cell wraps: each equals the sum of its windows in 64 bits. A second point in a
    /// cell brings back the limit of [`BRICK_POINTS`] points between folds.
    #[test]
    fn a_brick_takes_one_point_per_cell_without_folds() {
        let geo = PairGeometry::new(0.1, 0.2, 8);
        let table = KernelTable::new();
        let (_, margin) = window_shape(geo.ell_cells).expect("la3dm's window");
        let mut windows = SnappedWindows::default();
        assert!(windows.prepare::<4, 64>(&geo, &table));
        let mut brick = Brick::default();
        brick.reset(margin);
        let origin = [-(SB as i32), 0, 2 * SB as i32];
        let centre = |c: [usize; 3]| {
            to_cell_units(
                std::array::from_fn(|a| (f64::from(origin[a] + c[a] as i32) + 0.45) * geo.res_m),
                &geo,
            )
        };
        let cells: Vec<[usize; 3]> =
            (0..SB * SB * SB).map(|i| [i % SB, i / SB % SB, i / (SB * SB)]).collect();
        let pts: Vec<CellPoint> =
            [true, false].into_iter().flat_map(|hit| cells.iter().map(move |&c| (centre(c), hit))).collect();
        assert!(pts.len() > 10 * BRICK_POINTS as usize);
        let added = brick.add_points::<4, 64>(&pts, origin, &geo, &table, Some(&windows));
        assert_eq!(added, pts.len(), "no fold needed");
        let mut wide = vec![0u64; brick.a.len()];
        for &(p, _) in &pts[..cells.len()] {
            let (at, _, window, _) = windows.place(p);
            let vals = windows.window::<64>(window);
            for (k, &v) in vals.iter().enumerate() {
                let (z, y, x) = (k / 16, k / 4 % 4, k % 4);
                wide[at + (z * brick.edge + y) * brick.edge + x] += v as u64;
            }
        }
        let a: Vec<u64> = brick.a.iter().map(|&v| u64::from(v)).collect();
        assert_eq!(a, wide, "hits");
        assert_eq!(brick.b, brick.a, "frees, the same windows");
        let top = *wide.iter().max().expect("cells");
        assert!(top > 2 << FIXED_SHIFT, "largest sum {top}: windows overlap");

        // After a fold, three points in distinct cells, then the same cell over and over: the
        // brick takes BRICK_POINTS of them in all.
        brick.a.fill(0);
        brick.b.fill(0);
        brick.folded();
        let again: Vec<CellPoint> =
            pts[..3].iter().copied().chain(std::iter::repeat_n(pts[7], 400)).collect();
        let added = brick.add_points::<4, 64>(&again, origin, &geo, &table, Some(&windows));
        assert_eq!(added, BRICK_POINTS as usize);
        // Computed windows (no sub-cells) count the same way.
        brick.a.fill(0);
        brick.folded();
        let raw = PairGeometry::new(0.1, 0.2, 0);
        let added = brick.add_points::<4, 64>(&again, origin, &raw, &table, None);
        assert_eq!(added, BRICK_POINTS as usize);
    }

    #[test]
    fn snapped_windows_are_built_only_where_they_fit() {
        let table = KernelTable::new();
        let mut windows = SnappedWindows::default();
        assert!(!windows.prepare::<4, 64>(&PairGeometry::new(0.1, 0.2, 0), &table), "points where they are");
        assert!(!windows.prepare::<4, 64>(&PairGeometry::new(0.1, 0.2, 32), &table), "8 MiB of windows");
        assert!(windows.prepare::<4, 64>(&PairGeometry::new(0.1, 0.2, 8), &table));
        // Rebuilt when the geometry changes.
        assert!(windows.prepare::<4, 64>(&PairGeometry::new(0.1, 0.2, 2), &table));
        assert_eq!(windows.values.len(), 8 * 64);
    }
}
