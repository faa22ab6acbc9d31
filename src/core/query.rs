//! Point, box and ray queries over an [`EvidenceMap`], all in-process and read-only.
//!
//! Geometric arguments are world-frame metres. Answers name the cell they came from.

use super::key::{BLOCK_CELLS, CellKey};
use super::map::{CellEstimate, CellState, Evidence, EvidenceMap};
use super::params::Thresholds;

/// One answer of a point query.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointAnswer {
    pub cell: CellKey,
    pub estimate: CellEstimate,
}

/// Answers for points in the world frame (metres). Points outside the key range or not finite
/// answer `None`.
pub fn query_points(
    map: &EvidenceMap,
    points_world: &[[f64; 3]],
    th: &Thresholds,
) -> Vec<Option<PointAnswer>> {
    let res = map.params().resolution_m;
    points_world
        .iter()
        .map(|&p| {
            CellKey::from_point(p, res).map(|cell| PointAnswer { cell, estimate: map.estimate(cell, th) })
        })
        .collect()
}

/// An axis-aligned box query.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxQuery {
    pub min_world: [f64; 3],
    pub max_world: [f64; 3],
    /// Keep only cells in this state (`None`: every cell with evidence).
    pub state: Option<CellState>,
    /// Aggregate 2^coarsen cells per axis into one answer (evidence summed over the children).
    pub coarsen: u8,
}

/// A cube of the answer: `size_cells` cells per edge starting at `min_cell`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxCell {
    pub min_cell: CellKey,
    pub size_cells: i32,
    pub estimate: CellEstimate,
}

/// Why a box query was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BoxError {
    #[error("box: min and max must be finite with min ≤ max on every axis")]
    Malformed,
    #[error("box: {cells} cells exceeds the limit of {limit}; shrink the box or coarsen")]
    TooLarge { cells: u128, limit: u64 },
    #[error("box: coarsen must be at most 10, got {0}")]
    Coarsen(u8),
}

/// Cells inside `q` (inclusive of boundary cells) that hold evidence, sorted by key (x, then y,
/// then z); coarse cubes sum their children's evidence (clipped to the box). `max_cells` bounds
/// the number of lattice positions of the answer (at the query's coarsened resolution); the
/// work is bounded by the blocks that exist, never by the volume of the box.
pub fn query_box(
    map: &EvidenceMap,
    q: &BoxQuery,
    th: &Thresholds,
    max_cells: u64,
) -> Result<Vec<BoxCell>, BoxError> {
    if q.coarsen > 10 {
        return Err(BoxError::Coarsen(q.coarsen));
    }
    let res = map.params().resolution_m;
    let (lo, hi) = match (CellKey::from_point(q.min_world, res), CellKey::from_point(q.max_world, res)) {
        (Some(lo), Some(hi)) if lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z => (lo, hi),
        _ => return Err(BoxError::Malformed),
    };
    let s = q.coarsen;
    let span = |a: i32, b: i32| (i64::from(b >> s) - i64::from(a >> s) + 1) as u128;
    let cells = span(lo.x, hi.x) * span(lo.y, hi.y) * span(lo.z, hi.z);
    if cells > u128::from(max_cells) {
        return Err(BoxError::TooLarge { cells, limit: max_cells });
    }
    let mut cubes: std::collections::BTreeMap<CellKey, Evidence> = std::collections::BTreeMap::new();
    for key in blocks_in_box(map, lo, hi) {
        let Some(block) = map.block(key) else { continue };
        for i in 0..BLOCK_CELLS {
            let (a, b) = (block.a[i], block.b[i]);
            let cell = key.cell(i);
            let inside = (lo.x..=hi.x).contains(&cell.x)
                && (lo.y..=hi.y).contains(&cell.y)
                && (lo.z..=hi.z).contains(&cell.z);
            if (a != 0 || b != 0) && inside {
                let e = cubes
                    .entry(CellKey::new(cell.x >> s << s, cell.y >> s << s, cell.z >> s << s))
                    .or_default();
                e.a += a;
                e.b += b;
            }
        }
    }
    let size = 1i32 << s;
    Ok(cubes
        .into_iter()
        .map(|(min_cell, e)| BoxCell {
            min_cell,
            size_cells: size,
            estimate: CellEstimate::from_evidence(e, map.params(), th),
        })
        .filter(|c| q.state.is_none_or(|st| st == c.estimate.state))
        .collect())
}

/// The map's blocks that overlap cells `lo..=hi`: by walking the block range when it is small,
/// else by filtering the map's blocks.
fn blocks_in_box(map: &EvidenceMap, lo: CellKey, hi: CellKey) -> Vec<super::key::BlockKey> {
    let (bl, bh) = (lo.block(), hi.block());
    let n = |a: i32, b: i32| (i64::from(b) - i64::from(a) + 1) as u128;
    let range = n(bl.x, bh.x) * n(bl.y, bh.y) * n(bl.z, bh.z);
    if range <= map.block_count() as u128 {
        let mut keys = Vec::new();
        for z in bl.z..=bh.z {
            for y in bl.y..=bh.y {
                for x in bl.x..=bh.x {
                    let k = super::key::BlockKey::new(x, y, z);
                    if map.block(k).is_some() {
                        keys.push(k);
                    }
                }
            }
        }
        keys
    } else {
        map.blocks_unsorted()
            .map(|(k, _)| *k)
            .filter(|k| {
                (bl.x..=bh.x).contains(&k.x) && (bl.y..=bh.y).contains(&k.y) && (bl.z..=bh.z).contains(&k.z)
            })
            .collect()
    }
}

/// Counts of cells with evidence inside a box, per state.
pub fn count_box(cells: &[BoxCell]) -> [usize; 3] {
    let mut n = [0usize; 3];
    for c in cells {
        n[c.estimate.state as usize] += 1;
    }
    n
}

/// Where a ray stops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopAt {
    /// Stop at the first occupied cell; free and unknown cells are passed.
    Occupied,
    /// Stop at the first cell that is not free (occupied or unknown).
    NotFree,
}

/// One ray's verdict.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RayHit {
    /// The ray reached its max range without stopping.
    Clear,
    /// The first stopping cell, the distance (m) at which the ray enters it, and its estimate.
    Blocked { cell: CellKey, distance_m: f64, estimate: CellEstimate },
}

/// Why a ray could not be cast.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RayError {
    #[error("ray: origin must be finite and inside the map's key range")]
    Origin,
    #[error("ray: direction must be finite and non-zero")]
    Direction,
    #[error("ray: max_range must be finite and in (0, {0}] m")]
    Range(f64),
}

/// Longest ray accepted, in cells (bounds the work per ray).
pub const MAX_RAY_CELLS: f64 = 1.0e6;

/// Walks the cells a ray passes through (Amanatides–Woo), from the origin's cell, until a cell
/// matching `stop` or `max_range_m`. The origin cell itself is tested too.
pub fn cast_ray(
    map: &EvidenceMap,
    origin_world: [f64; 3],
    direction_world: [f64; 3],
    max_range_m: f64,
    stop: StopAt,
    th: &Thresholds,
) -> Result<RayHit, RayError> {
    let res = map.params().resolution_m;
    let limit = MAX_RAY_CELLS * res;
    if !(max_range_m.is_finite() && max_range_m > 0.0 && max_range_m <= limit) {
        return Err(RayError::Range(limit));
    }
    let norm = direction_world.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !(norm.is_finite() && norm > 0.0) {
        return Err(RayError::Direction);
    }
    let dir = direction_world.map(|v| v / norm);
    let mut cell = CellKey::from_point(origin_world, res).ok_or(RayError::Origin)?;
    let far = origin_world.iter().zip(&dir).map(|(o, d)| o + d * max_range_m);
    if far.clone().any(|v| !(v / res).abs().lt(&(i32::MAX as f64 - 2.0))) {
        return Err(RayError::Origin);
    }
    let mut walk = VoxelWalk::new(origin_world, dir, cell, res);
    let mut entry_m = 0.0;
    loop {
        let estimate = map.estimate(cell, th);
        let stops = match stop {
            StopAt::Occupied => estimate.state == CellState::Occupied,
            StopAt::NotFree => estimate.state != CellState::Free,
        };
        if stops {
            return Ok(RayHit::Blocked { cell, distance_m: entry_m, estimate });
        }
        let (next_cell, next_entry) = walk.step();
        if next_entry > max_range_m {
            return Ok(RayHit::Clear);
        }
        cell = next_cell;
        entry_m = next_entry;
    }
}

/// Incremental voxel traversal state (distances in metres along the unit direction).
#[derive(Debug)]
struct VoxelWalk {
    cell: [i32; 3],
    step: [i32; 3],
    t_max: [f64; 3],
    t_delta: [f64; 3],
}

impl VoxelWalk {
    fn new(origin: [f64; 3], dir: [f64; 3], cell: CellKey, res: f64) -> Self {
        let c = [cell.x, cell.y, cell.z];
        let mut step = [0; 3];
        let mut t_max = [f64::INFINITY; 3];
        let mut t_delta = [f64::INFINITY; 3];
        for i in 0..3 {
            if dir[i] > 0.0 {
                step[i] = 1;
                t_max[i] = ((f64::from(c[i]) + 1.0) * res - origin[i]) / dir[i];
                t_delta[i] = res / dir[i];
            } else if dir[i] < 0.0 {
                step[i] = -1;
                t_max[i] = (f64::from(c[i]) * res - origin[i]) / dir[i];
                t_delta[i] = -res / dir[i];
            }
        }
        Self { cell: c, step, t_max, t_delta }
    }

    /// Moves to the next cell; returns it and the distance at which the ray enters it.
    fn step(&mut self) -> (CellKey, f64) {
        let i = if self.t_max[0] <= self.t_max[1] && self.t_max[0] <= self.t_max[2] {
            0
        } else if self.t_max[1] <= self.t_max[2] {
            1
        } else {
            2
        };
        let entry = self.t_max[i].max(0.0);
        self.cell[i] += self.step[i];
        self.t_max[i] += self.t_delta[i];
        (CellKey::new(self.cell[0], self.cell[1], self.cell[2]), entry)
    }
}

/// The cells a ray passes through up to `max_range_m` (for tests and traversal listings).
pub fn traverse(origin_world: [f64; 3], dir_unit: [f64; 3], max_range_m: f64, res: f64) -> Vec<CellKey> {
    let Some(cell) = CellKey::from_point(origin_world, res) else { return Vec::new() };
    let mut walk = VoxelWalk::new(origin_world, dir_unit, cell, res);
    let mut out = vec![cell];
    loop {
        let (c, entry) = walk.step();
        if entry > max_range_m {
            return out;
        }
        out.push(c);
    }
}

const _: () = assert!(BLOCK_CELLS == 512);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::{Integrator, MapParams};
    use proptest::prelude::*;

    fn room_map() -> EvidenceMap {
        let params = MapParams::default();
        let mut map = EvidenceMap::new(params);
        let (_, scans) = crate::sim::simulate(0, 4, &crate::sim::Lidar::default());
        let mut integ = Integrator::new(params);
        for s in &scans {
            integ.integrate(&mut map, &s.points_world, s.origin, 1);
        }
        map
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// The voxel walk visits exactly the cells that dense sampling along the ray finds.
        #[test]
        fn traversal_matches_dense_sampling(o in (-3.0f64..3.0, -3.0f64..3.0, -3.0f64..3.0),
                                            d in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
                                            len in 0.05f64..3.0) {
            let n = (d.0 * d.0 + d.1 * d.1 + d.2 * d.2).sqrt();
            prop_assume!(n > 0.1);
            let dir = [d.0 / n, d.1 / n, d.2 / n];
            let origin = [o.0, o.1, o.2];
            let walked = traverse(origin, dir, len, 0.1);
            // Dense samples (1 µm steps would be exact; 0.2 mm steps miss only corner grazes,
            // which the walk includes) must each lie in a walked cell, in order.
            let mut idx = 0;
            let steps = (len / 2e-4) as usize;
            for i in 0..=steps {
                let t = len * i as f64 / steps as f64;
                let c = CellKey::from_point([origin[0] + dir[0] * t, origin[1] + dir[1] * t, origin[2] + dir[2] * t], 0.1).unwrap();
                while idx < walked.len() && walked[idx] != c {
                    idx += 1;
                }
                prop_assert!(idx < walked.len(), "sample at t={t} in {c:?} not walked in order");
            }
            // Consecutive walked cells are face neighbours.
            for w in walked.windows(2) {
                let d = (w[0].x - w[1].x).abs() + (w[0].y - w[1].y).abs() + (w[0].z - w[1].z).abs();
                prop_assert_eq!(d, 1);
            }
        }
    }

    #[test]
    fn point_box_and_ray_queries_agree_with_cell_estimates() {
        let map = room_map();
        let th = Thresholds::default();
        let pts = [[5.0, 2.0, 0.7], [0.05, 5.0, 1.0], [1000.0, 0.0, 0.0], [f64::NAN, 0.0, 0.0]];
        let ans = query_points(&map, &pts, &th);
        assert!(ans[3].is_none());
        for (p, a) in pts.iter().zip(&ans).take(3) {
            let a = a.unwrap();
            assert_eq!(a.cell, CellKey::from_point(*p, 0.1).unwrap());
            assert_eq!(a.estimate, map.estimate(a.cell, &th));
        }
        // The box answer equals the per-cell answers for cells with evidence.
        let q = BoxQuery { min_world: [4.0, 1.0, 0.0], max_world: [5.0, 2.0, 1.0], state: None, coarsen: 0 };
        let cells = query_box(&map, &q, &th, 1_000_000).unwrap();
        assert!(!cells.is_empty());
        for c in &cells {
            assert_eq!(c.estimate, map.estimate(c.min_cell, &th));
        }
        let n_with_evidence = (0..11)
            .flat_map(|z| (10..21).flat_map(move |y| (40..51).map(move |x| CellKey::new(x, y, z))))
            .filter(|c| !map.evidence(*c).is_empty())
            .count();
        assert_eq!(cells.len(), n_with_evidence);
        // Coarsening sums evidence: total mass is preserved.
        let coarse = query_box(&map, &BoxQuery { coarsen: 2, ..q }, &th, 1_000_000).unwrap();
        let sum = |v: &[BoxCell]| v.iter().map(|c| c.estimate.evidence.a).sum::<i64>();
        assert_eq!(sum(&coarse), sum(&cells));
        // Limits.
        assert!(matches!(query_box(&map, &q, &th, 10), Err(BoxError::TooLarge { .. })));
        let bad = BoxQuery { min_world: [1.0, 0.0, 0.0], max_world: [0.0, 1.0, 1.0], ..q };
        assert_eq!(query_box(&map, &bad, &th, 100), Err(BoxError::Malformed));
    }

    #[test]
    fn rays_stop_at_walls_of_the_simulated_room() {
        let map = room_map();
        let th = Thresholds::default();
        // From the route (x = 5, y = 2, sensor height) towards the south wall at y = 0.
        let hit = cast_ray(&map, [5.0, 2.0, 0.7], [0.0, -1.0, 0.0], 8.0, StopAt::Occupied, &th).unwrap();
        match hit {
            RayHit::Blocked { cell, distance_m, estimate } => {
                assert_eq!(estimate.state, CellState::Occupied);
                assert!((1.7..=2.2).contains(&distance_m), "wall at ~2 m, got {distance_m} ({cell:?})");
            }
            RayHit::Clear => panic!("the wall must block the ray"),
        }
        let short = cast_ray(&map, [5.0, 2.0, 0.7], [0.0, -1.0, 0.0], 0.5, StopAt::Occupied, &th).unwrap();
        assert_eq!(short, RayHit::Clear);
        assert_eq!(
            cast_ray(&map, [5.0, 2.0, 0.7], [0.0; 3], 1.0, StopAt::Occupied, &th),
            Err(RayError::Direction)
        );
        assert!(matches!(
            cast_ray(&map, [5.0, 2.0, 0.7], [1.0, 0.0, 0.0], f64::INFINITY, StopAt::Occupied, &th),
            Err(RayError::Range(_))
        ));
    }
}
