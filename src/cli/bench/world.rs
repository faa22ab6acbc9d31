//! The outdoor world the `query`, `scale` and dense `ingest` benchmarks share: a simulated
//! 64-beam LiDAR driving through a town ([`crate::sim::simulate_outdoor`]), the map built from
//! it, and random query workloads over that map (seeded, so every run asks the same questions).

use crate::core::{BlockKey, EvidenceMap, Integrator, MapParams};
use crate::io::scan::Scan;
use crate::sim::{Lidar, SimScan, simulate_outdoor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// City blocks per side of the simulated town (40 m each).
pub(super) const TOWN_BLOCKS: u32 = 4;
/// Map parameters of the outdoor benchmarks: the defaults with a 30 m max range (the LiDAR's).
pub(super) fn outdoor_params() -> MapParams {
    MapParams { max_range_m: 30.0, ..Default::default() }
}

/// `n` scans of the 64-beam LiDAR driving the town (seed 0).
pub(super) fn outdoor_scans(n: usize) -> Vec<SimScan> {
    simulate_outdoor(0, TOWN_BLOCKS, n, &Lidar::dense64()).1
}

/// The same scans as [`Scan`]s (what `bench ingest` times).
pub(super) fn as_scans(sim: Vec<SimScan>) -> Vec<Scan> {
    sim.into_iter()
        .map(|s| Scan { points_world: s.points_world, origin_world: s.origin, dropped_nonfinite: 0 })
        .collect()
}

/// The map of `scans` under `params`, integrated on `threads` threads.
pub(super) fn build_map(scans: &[SimScan], params: MapParams, threads: usize) -> EvidenceMap {
    let mut map = EvidenceMap::new(params);
    let mut integ = Integrator::new(params);
    for s in scans {
        integ.integrate(&mut map, &s.points_world, s.origin, threads);
    }
    map
}

/// Random query workloads over one map (world frame, metres).
#[derive(Debug)]
pub(super) struct Workload {
    /// Batches of points drawn uniformly inside the map's allocated blocks.
    pub point_batches: Vec<Vec<[f32; 3]>>,
    /// Single points (same distribution), for latency runs.
    pub singles: Vec<[f32; 3]>,
    /// Per box edge (m): boxes centred on sensor poses.
    pub boxes: Vec<(f64, Vec<WorldBox>)>,
    /// Per ray length (m): batches of rays from sensor poses in uniformly random directions.
    pub rays: Vec<(f64, Vec<Vec<RaySpec>>)>,
}

/// A box `(min, max)`, world frame (m).
pub(super) type WorldBox = ([f64; 3], [f64; 3]);

/// One ray of a workload.
#[derive(Debug, Clone, Copy)]
pub(super) struct RaySpec {
    pub origin: [f64; 3],
    pub direction: [f64; 3],
    pub max_range_m: f64,
}

/// Distinct request payloads a throughput run cycles through.
const DISTINCT: usize = 4;
pub(super) const BOX_EDGES_M: [f64; 2] = [1.0, 10.0];
pub(super) const RAY_RANGES_M: [f64; 2] = [8.0, 30.0];

impl Workload {
    /// Seeded workloads: `batch` points per batch, `singles` single points, `rays_per_batch`
    /// rays per batch; boxes and rays start at the scans' sensor positions.
    pub(super) fn new(
        map: &EvidenceMap,
        poses: &[[f64; 3]],
        batch: usize,
        singles: usize,
        rays_per_batch: usize,
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(0x6267_6b6d);
        let keys = map.block_keys_sorted();
        let block_m = f64::from(crate::core::key::BLOCK_EDGE) * map.params().resolution_m;
        let point = |rng: &mut ChaCha8Rng| random_point_in(&keys, block_m, rng);
        let point_batches = (0..DISTINCT).map(|_| (0..batch).map(|_| point(&mut rng)).collect()).collect();
        let singles = (0..singles).map(|_| point(&mut rng)).collect();
        let pose = |rng: &mut ChaCha8Rng| poses[rng.random_range(0..poses.len().max(1))];
        let boxes = BOX_EDGES_M
            .iter()
            .map(|&e| {
                let list = (0..16)
                    .map(|_| {
                        let c = pose(&mut rng);
                        (c.map(|v| v - 0.5 * e), c.map(|v| v + 0.5 * e))
                    })
                    .collect();
                (e, list)
            })
            .collect();
        let rays = RAY_RANGES_M
            .iter()
            .map(|&r| {
                let batches = (0..DISTINCT)
                    .map(|_| {
                        (0..rays_per_batch)
                            .map(|_| RaySpec {
                                origin: pose(&mut rng),
                                direction: random_direction(&mut rng),
                                max_range_m: r,
                            })
                            .collect()
                    })
                    .collect();
                (r, batches)
            })
            .collect();
        Self { point_batches, singles, boxes, rays }
    }
}

/// A point drawn uniformly inside a uniformly chosen block of `keys`.
fn random_point_in(keys: &[BlockKey], block_m: f64, rng: &mut ChaCha8Rng) -> [f32; 3] {
    let k = keys[rng.random_range(0..keys.len().max(1))];
    let lo = [k.x, k.y, k.z].map(|v| f64::from(v) * block_m);
    lo.map(|v| (v + block_m * rng.random::<f64>()) as f32)
}

/// A uniformly random unit vector (rejection sampling in the unit ball).
pub(super) fn random_direction(rng: &mut ChaCha8Rng) -> [f64; 3] {
    loop {
        let v = [0; 3].map(|_| 2.0 * rng.random::<f64>() - 1.0);
        let n2: f64 = v.iter().map(|x| x * x).sum();
        if n2 > 1e-6 && n2 <= 1.0 {
            let n = n2.sqrt();
            return v.map(|x| x / n);
        }
    }
}
