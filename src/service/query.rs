//! The one front door of the read-only queries (points, box, rays; the viewer's cells and the
//! export in [`cells`]): every transport — gRPC, HTTP, the viewer, zenoh — opens [`Queries`]
//! on a map's current snapshot, resolves the thresholds, builds one validated query (limits
//! and corrupt-block checks applied here, so every transport refuses the same requests), asks
//! it whether it [runs inline](PointsQuery::runs_inline), and runs it: on the calling thread or
//! on a blocking one (the transports share `api::offload` for that).
//!
//! Synchronous, no wire types: answers are core types handed to the caller's closure, so a
//! transport writes them straight into its own message without an intermediate copy. Errors
//! ([`QueryError`]) say what is wrong with which element; each transport names the field in
//! its own vocabulary (`bgkmap.v1.QueryPointsRequest.xyz_f32: point 1 …`, `points[1]: …`).

pub mod cells;

use super::{MapService, ServiceError, Snapshot};
use crate::core::query::{BoxCell, BoxError, BoxQuery, PointAnswer, RayError, RayHit, StopAt};
use crate::core::query::{cast_ray, count_box, for_each_point, query_box};
use crate::core::{CellState, Thresholds};
use crate::store::CorruptBlock;
use std::sync::Arc;

/// Points a point query answers on the calling thread; more move to a blocking thread, so a
/// large batch never holds an async worker while a small one pays no thread hand-off.
const INLINE_POINTS: usize = 10_000;

/// The finest-to-coarsest span of a box query: cubes of at most 2^10 cells per edge.
pub const MAX_COARSEN: u32 = 10;

/// Limits of the read-only queries, the same on every transport.
#[derive(Debug, Clone, Copy)]
pub struct QueryLimits {
    /// Most lattice positions one box query may visit (at its coarsened resolution); the
    /// viewer's cells coarsen until they fit. Default 4 M.
    pub max_box_cells: u64,
}

impl Default for QueryLimits {
    fn default() -> Self {
        Self { max_box_cells: 4_000_000 }
    }
}

/// Why a query was refused. The transports map each variant once, naming their own field.
#[derive(Debug)]
pub enum QueryError {
    /// A threshold override is out of range (`name` is `p_free`, `p_occ` or `var_max`).
    Threshold { name: &'static str, reason: String },
    /// Point `index` has a coordinate that is not finite.
    NotFinite { index: usize },
    /// Point `index` lies outside the map's key range.
    Outside { index: usize },
    /// `coarsen` is over [`MAX_COARSEN`].
    Coarsen(u32),
    /// The box is malformed or over the limit.
    Box(BoxError),
    /// Ray `index` cannot be cast.
    Ray { index: usize, error: RayError },
    /// Ray `index` passes a corrupt block: its answer would be the prior (see [`Snapshot::loss`]).
    RayCorrupt { index: usize, block: CorruptBlock },
    /// Anything the service itself answers (a corrupt block under the query: DATA_LOSS).
    Service(ServiceError),
}

impl From<ServiceError> for QueryError {
    fn from(e: ServiceError) -> Self {
        Self::Service(e)
    }
}

/// Threshold overrides of one query; unset fields take the map's defaults.
#[derive(Debug, Clone, Copy, Default)]
pub struct ThresholdsIn {
    pub p_free: Option<f64>,
    pub p_occ: Option<f64>,
    pub var_max: Option<f64>,
}

/// The queries of one snapshot of a map, under the service's limits.
#[derive(Debug, Clone)]
pub struct Queries {
    snap: Arc<Snapshot>,
    limits: QueryLimits,
}

impl MapService {
    /// Opens the current snapshot of `map` for queries (NOT_FOUND for an unknown map).
    pub fn queries(&self, map: &str) -> Result<Queries, ServiceError> {
        Ok(Queries { snap: self.snapshot(map)?, limits: self.config.queries })
    }
}

impl Queries {
    /// The snapshot every query of this scope reads.
    pub fn snapshot(&self) -> &Arc<Snapshot> {
        &self.snap
    }

    /// The thresholds of a query: the map's defaults with `t`'s overrides, validated.
    pub fn thresholds(&self, t: ThresholdsIn) -> Result<Thresholds, QueryError> {
        let d = self.snap.map.params().thresholds;
        let th = Thresholds {
            p_free: t.p_free.unwrap_or(d.p_free),
            p_occ: t.p_occ.unwrap_or(d.p_occ),
            var_max: t.var_max.unwrap_or(d.var_max),
        };
        th.validate().map_err(|e| QueryError::Threshold { name: e.name, reason: e.reason })?;
        Ok(th)
    }

    /// A point query (world frame, m): every point finite, none in a corrupt block.
    pub fn points(self, points_world: Vec<[f64; 3]>, th: Thresholds) -> Result<PointsQuery, QueryError> {
        if let Some(index) = points_world.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(QueryError::NotFinite { index });
        }
        self.snap.check_points(&points_world)?;
        Ok(PointsQuery { snap: self.snap, points_world, th })
    }

    /// A box query: `coarsen` at most [`MAX_COARSEN`], no corrupt block in the box. The box
    /// itself (finite, min ≤ max, under the limit) is checked when it runs.
    pub fn cuboid(self, req: BoxRequest, th: Thresholds) -> Result<CuboidQuery, QueryError> {
        let coarsen = u8::try_from(req.coarsen)
            .ok()
            .filter(|c| u32::from(*c) <= MAX_COARSEN)
            .ok_or(QueryError::Coarsen(req.coarsen))?;
        self.snap.check_box(req.min_world, req.max_world)?;
        let q = BoxQuery { min_world: req.min_world, max_world: req.max_world, state: req.state, coarsen };
        Ok(CuboidQuery { snap: self.snap, q, th, max_cells: self.limits.max_box_cells })
    }

    /// A batch of rays; each is checked as it is cast.
    pub fn rays(self, rays: Vec<RayRequest>, stop: StopAt, th: Thresholds) -> RaysQuery {
        RaysQuery { snap: self.snap, rays, stop, th }
    }
}

/// A validated point query.
#[derive(Debug)]
pub struct PointsQuery {
    snap: Arc<Snapshot>,
    points_world: Vec<[f64; 3]>,
    th: Thresholds,
}

impl PointsQuery {
    /// Small batches answer on the calling thread; large ones belong on a blocking thread.
    pub fn runs_inline(&self) -> bool {
        self.points_world.len() <= INLINE_POINTS
    }

    pub fn len(&self) -> usize {
        self.points_world.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points_world.is_empty()
    }

    pub fn version(&self) -> u64 {
        self.snap.version
    }

    /// Hands `each` the answer of every point in order; the first point outside the key range
    /// (every point before it answered) is the error.
    pub fn run(&self, mut each: impl FnMut(PointAnswer)) -> Result<(), QueryError> {
        let mut outside = None;
        let mut answered = 0;
        for_each_point(&self.snap.map, &self.points_world, &self.th, |a| match a {
            Some(a) => {
                answered += 1;
                each(a);
            }
            None => {
                outside.get_or_insert(answered);
            }
        });
        match outside {
            Some(index) => Err(QueryError::Outside { index }),
            None => Ok(()),
        }
    }
}

/// A box query as the transports give it (world frame, m).
#[derive(Debug, Clone, Copy)]
pub struct BoxRequest {
    pub min_world: [f64; 3],
    pub max_world: [f64; 3],
    /// Keep only cells in this state (`None`: every cell with evidence).
    pub state: Option<CellState>,
    /// Cubes of 2^coarsen cells per edge.
    pub coarsen: u32,
}

/// A validated box query.
#[derive(Debug)]
pub struct CuboidQuery {
    snap: Arc<Snapshot>,
    q: BoxQuery,
    th: Thresholds,
    max_cells: u64,
}

/// The answer of a box query.
#[derive(Debug)]
pub struct BoxAnswer {
    /// Cubes with evidence, sorted by key.
    pub cells: Vec<BoxCell>,
    /// Cubes per state: free, occupied, unknown.
    pub counts: [usize; 3],
    pub version: u64,
}

impl CuboidQuery {
    /// Its cost is bounded by the blocks in the box, unknown until it runs: always off the
    /// calling thread.
    pub fn runs_inline(&self) -> bool {
        false
    }

    pub fn run(&self) -> Result<BoxAnswer, QueryError> {
        let cells = query_box(&self.snap.map, &self.q, &self.th, self.max_cells).map_err(QueryError::Box)?;
        let counts = count_box(&cells);
        Ok(BoxAnswer { cells, counts, version: self.snap.version })
    }
}

/// One ray (world frame, m).
#[derive(Debug, Clone, Copy)]
pub struct RayRequest {
    pub origin_world: [f64; 3],
    pub direction_world: [f64; 3],
    pub max_range_m: f64,
}

/// A batch of rays.
#[derive(Debug)]
pub struct RaysQuery {
    snap: Arc<Snapshot>,
    rays: Vec<RayRequest>,
    stop: StopAt,
    th: Thresholds,
}

impl RaysQuery {
    /// A ray walks up to its range in cells: always off the calling thread.
    pub fn runs_inline(&self) -> bool {
        false
    }

    pub fn len(&self) -> usize {
        self.rays.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    pub fn version(&self) -> u64 {
        self.snap.version
    }

    /// Casts every ray in order, handing `each` the ray and its hit; the first ray that cannot
    /// be cast, or whose answer depends on a corrupt block, is the error.
    pub fn run(&self, mut each: impl FnMut(&RayRequest, RayHit)) -> Result<(), QueryError> {
        let map = &self.snap.map;
        let res = map.params().resolution_m;
        for (index, r) in self.rays.iter().enumerate() {
            let hit = cast_ray(map, r.origin_world, r.direction_world, r.max_range_m, self.stop, &self.th)
                .map_err(|error| QueryError::Ray { index, error })?;
            // A blocked ray's answer depends on the cells up to its hit, whose far corner lies
            // at most a cell diagonal beyond the hit distance.
            let reach = match hit {
                RayHit::Clear => r.max_range_m,
                RayHit::Blocked { distance_m, .. } => distance_m + res * 3f64.sqrt(),
            };
            if let Some(c) = self.snap.corrupt_on_ray(r.origin_world, r.direction_world, reach) {
                return Err(QueryError::RayCorrupt { index, block: c.clone() });
            }
            each(r, hit);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::MapParams;
    use crate::service::ServiceConfig;

    fn service(dir: &std::path::Path, max_box_cells: u64) -> MapService {
        let config = ServiceConfig { queries: QueryLimits { max_box_cells }, ..ServiceConfig::default() };
        let svc = MapService::open(dir, config).unwrap();
        svc.create_map("m", MapParams::default()).unwrap();
        svc
    }

    #[test]
    fn the_front_door_refuses_each_fault_by_element_and_decides_where_to_run() {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path(), 1000);
        assert!(matches!(svc.queries("nope"), Err(ServiceError::NotFound(_))));
        let q = svc.queries("m").unwrap();
        let bad = ThresholdsIn { p_free: Some(0.9), ..ThresholdsIn::default() };
        assert!(matches!(q.thresholds(bad), Err(QueryError::Threshold { name: "p_free", .. })));
        let th = q.thresholds(ThresholdsIn::default()).unwrap();

        let nan = vec![[0.0; 3], [f64::NAN, 0.0, 0.0]];
        assert!(matches!(q.clone().points(nan, th), Err(QueryError::NotFinite { index: 1 })));
        let far = vec![[0.0; 3], [1e12, 0.0, 0.0], [1e12, 0.0, 0.0]];
        let mut answered = 0;
        let r = q.clone().points(far, th).unwrap().run(|_| answered += 1);
        assert!(matches!(r, Err(QueryError::Outside { index: 1 })) && answered == 1, "{r:?}");
        assert!(q.clone().points(vec![[0.0; 3]; INLINE_POINTS], th).unwrap().runs_inline());
        assert!(!q.clone().points(vec![[0.0; 3]; INLINE_POINTS + 1], th).unwrap().runs_inline());

        let cuboid =
            |coarsen, max: f64| BoxRequest { min_world: [0.0; 3], max_world: [max; 3], state: None, coarsen };
        assert!(matches!(q.clone().cuboid(cuboid(11, 1.0), th), Err(QueryError::Coarsen(11))));
        let big = q.clone().cuboid(cuboid(0, 10.0), th).unwrap().run();
        assert!(matches!(big, Err(QueryError::Box(BoxError::TooLarge { limit: 1000, .. }))), "{big:?}");
        assert_eq!(q.clone().cuboid(cuboid(0, 0.5), th).unwrap().run().unwrap().cells.len(), 0);

        let ray = |d: [f64; 3]| RayRequest { origin_world: [0.0; 3], direction_world: d, max_range_m: 1.0 };
        let rays = q.rays(vec![ray([1.0, 0.0, 0.0]), ray([0.0; 3])], StopAt::Occupied, th);
        let r = rays.run(|_, _| {});
        assert!(matches!(r, Err(QueryError::Ray { index: 1, .. })), "{r:?}");
    }
}
