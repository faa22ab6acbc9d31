//! The [`Integrator`]: one scan's points → training data → evidence, as a delta or straight
//! into a [`BlockSink`], on one thread or on slabs of blocks over several.

use super::cell_points::{CellPoint, PairGeometry};
use super::delta::ScanDelta;
use super::kernel::KernelTable;
use super::scatter::Scatter;
use super::sink::BlockSink;
use super::training::{TrainingBuilder, TrainingSet};
use crate::core::map::EvidenceMap;
use crate::core::params::MapParams;

/// Turns scans into evidence deltas. Holds the kernel table and scratch buffers, so a long
/// sequence of scans allocates (almost) nothing.
#[derive(Debug)]
pub struct Integrator {
    params: MapParams,
    geometry: PairGeometry,
    table: KernelTable,
    training: TrainingBuilder,
    set: TrainingSet,
    scatter: Scatter,
    /// With several threads per scan: the training points in cell units, each thread's slab
    /// of them, and the scatters of the threads beyond the first.
    cells: Vec<CellPoint>,
    slabs: Vec<Vec<CellPoint>>,
    helpers: Vec<Scatter>,
}

impl Integrator {
    pub fn new(params: MapParams) -> Self {
        Self {
            geometry: PairGeometry::of(&params),
            params,
            table: KernelTable::new(),
            training: TrainingBuilder::default(),
            set: TrainingSet::default(),
            scatter: Scatter::default(),
            cells: Vec::new(),
            slabs: Vec::new(),
            helpers: Vec::new(),
        }
    }

    pub fn params(&self) -> &MapParams {
        &self.params
    }

    pub fn geometry(&self) -> &PairGeometry {
        &self.geometry
    }

    pub fn table(&self) -> &KernelTable {
        &self.table
    }

    /// Training data for one scan (world frame, metres).
    pub fn training(&mut self, points_world: &[[f32; 3]], origin_world: [f64; 3]) -> &TrainingSet {
        self.training.build_into(points_world, origin_world, &self.params, &mut self.set);
        &self.set
    }

    /// The evidence one scan adds, computed on `threads` threads (same bits for any count).
    pub fn scan_delta(
        &mut self,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
    ) -> ScanDelta {
        self.scan_delta_with_range(points_world, origin_world, threads, None)
    }

    /// As [`Self::scan_delta`] with the scan's own maximum range (m), if it has one: the map's
    /// `max_range_m` caps it (0 = unlimited on either side).
    pub fn scan_delta_with_range(
        &mut self,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
        scan_max_range_m: Option<f64>,
    ) -> ScanDelta {
        let params = self.scan_params(scan_max_range_m);
        self.training.build_into(points_world, origin_world, &params, &mut self.set);
        self.training_delta(threads)
    }

    /// The map's parameters with a scan's own maximum range (m), if it has one, capped by the
    /// map's (0 = unlimited on either side).
    fn scan_params(&self, scan_max_range_m: Option<f64>) -> MapParams {
        let mut params = self.params;
        if let Some(r) = scan_max_range_m.filter(|r| *r > 0.0) {
            params.max_range_m = if params.max_range_m > 0.0 { params.max_range_m.min(r) } else { r };
        }
        params
    }

    /// The evidence of the training set built by the last [`Self::training`] call.
    pub fn training_delta(&mut self, threads: usize) -> ScanDelta {
        if threads <= 1 {
            return self.scatter.delta(&self.set, &self.geometry, &self.table);
        }
        let delta_of = |scatter: &mut Scatter,
                        slab: &[CellPoint],
                        geo: &PairGeometry,
                        table: &KernelTable| { scatter.delta_of(slab, geo, table) };
        let (mine, theirs) = self.on_slabs(threads, delta_of, delta_of);
        let parts = std::iter::once(mine).chain(theirs).collect();
        ScanDelta::sum(parts)
    }

    /// Adds the evidence of the training set built by the last [`Self::training`] call to
    /// `sink`, straight into its blocks. The same bits as applying [`Self::training_delta`],
    /// for any number of threads.
    ///
    /// With several threads the points are cut into slabs of whole blocks along x, each with
    /// about as many points. The first slab goes into `sink` on this thread; every other slab
    /// into a map of its own on a thread of its own, whose blocks are then added into `sink`
    /// (new blocks are moved in; only the blocks where the windows of two slabs meet are added
    /// cell by cell). Sums are integers, so the split changes no bit.
    /// Per-thread deltas, summed and then applied, were more than twice as slow as one thread.
    pub fn add_training_into<S: BlockSink + ?Sized>(&mut self, sink: &mut S, threads: usize) {
        if threads <= 1 {
            self.scatter.add_into(&self.set, &self.geometry, &self.table, sink);
            return;
        }
        let params = self.params;
        let (_, maps) = self.on_slabs(
            threads,
            |scatter, slab, geo, table| scatter.add_cells_into(slab, geo, table, sink),
            |scatter, slab, geo, table| {
                let mut own = EvidenceMap::new(params);
                scatter.add_cells_into(slab, geo, table, &mut own);
                own
            },
        );
        for map in maps {
            map.add_into(sink);
        }
    }

    /// Cuts the last training set's points into `threads` slabs of whole blocks along x
    /// ([`slabs_by_block_x`]) and runs `first` on the first slab with this integrator's scatter,
    /// on the calling thread, and `other` on every other non-empty slab with a scatter of its
    /// own (kept between scans), each on a thread of its own. Returns `first`'s result and the
    /// others', in slab order.
    fn on_slabs<A, R: Send>(
        &mut self,
        threads: usize,
        first: impl FnOnce(&mut Scatter, &[CellPoint], &PairGeometry, &KernelTable) -> A,
        other: impl Fn(&mut Scatter, &[CellPoint], &PairGeometry, &KernelTable) -> R + Sync,
    ) -> (A, Vec<R>) {
        let (geo, table) = (&self.geometry, &self.table);
        super::cell_points::labelled_cell_points(&self.set, geo, &mut self.cells);
        slabs_by_block_x(&self.cells, threads, &mut self.slabs);
        self.helpers.resize_with(threads.saturating_sub(1), Scatter::default);
        let (head, others) = self.slabs.split_at(1.min(self.slabs.len()));
        let first_slab = head.first().map_or(&[][..], Vec::as_slice);
        std::thread::scope(|scope| {
            let other = &other;
            let handles: Vec<_> = others
                .iter()
                .zip(&mut self.helpers)
                .filter(|(slab, _)| !slab.is_empty())
                .map(|(slab, scatter)| scope.spawn(move || other(scatter, slab, geo, table)))
                .collect();
            let mine = first(&mut self.scatter, first_slab, geo, table);
            let theirs = handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
                .collect();
            (mine, theirs)
        })
    }

    /// Adds one scan's evidence to `sink` ([`Self::scan_delta_with_range`]'s, without the delta).
    pub fn add_scan_into<S: BlockSink + ?Sized>(
        &mut self,
        sink: &mut S,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
        scan_max_range_m: Option<f64>,
    ) {
        let params = self.scan_params(scan_max_range_m);
        self.training.build_into(points_world, origin_world, &params, &mut self.set);
        self.add_training_into(sink, threads);
    }

    /// Returns a delta's block buffers for reuse by later scans.
    pub fn recycle(&mut self, delta: ScanDelta) {
        self.scatter.recycle(delta);
    }

    /// Integrates one scan into `map`.
    pub fn integrate(
        &mut self,
        map: &mut EvidenceMap,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
    ) {
        self.add_scan_into(map, points_world, origin_world, threads, None);
    }
}

/// Cuts `pts` into `n` slabs of whole blocks along x (block column `x >> BLOCK_SHIFT` of each
/// point's cell), each holding about `1/n` of the points, into `slabs` (cleared first; some
/// may end up empty). Points keep their order within a slab.
fn slabs_by_block_x(pts: &[CellPoint], n: usize, slabs: &mut Vec<Vec<CellPoint>>) {
    use crate::core::key::BLOCK_SHIFT;
    slabs.resize_with(n, Vec::new);
    slabs.iter_mut().for_each(Vec::clear);
    let column = |p: &[f64; 3]| super::cell_points::split_point(*p).0[0] >> BLOCK_SHIFT;
    let (Some(lo), Some(hi)) =
        (pts.iter().map(|(p, _)| column(p)).min(), pts.iter().map(|(p, _)| column(p)).max())
    else {
        return;
    };
    // Points per block column, then the first column of each slab: where the running count
    // passes the next multiple of 1/n of the points.
    let mut count = vec![0usize; (i64::from(hi) - i64::from(lo) + 1) as usize];
    for (p, _) in pts {
        count[(column(p) - lo) as usize] += 1;
    }
    let mut slab_of = vec![0usize; count.len()];
    let (mut seen, mut slab) = (0usize, 0usize);
    for (c, &k) in count.iter().enumerate() {
        while slab + 1 < n && seen * n >= (slab + 1) * pts.len() {
            slab += 1;
        }
        slab_of[c] = slab;
        seen += k;
    }
    for &(p, hit) in pts {
        slabs[slab_of[(column(&p) - lo) as usize]].push((p, hit));
    }
}

#[cfg(test)]
#[path = "integrator_tests.rs"]
mod tests;
