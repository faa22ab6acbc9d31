//! Ray queries: the cells a ray passes through (Amanatides–Woo) and where it stops.
//!
//! Geometric arguments are world-frame metres. The walk looks a block up only when it enters a
//! new one and derives a cell's estimate only where the cell holds evidence (every other cell
//! answers the prior, computed once per ray), which is what makes long rays cheap.

use super::evidence::{BlockEvidence, BlockSummary};
use super::key::{BlockKey, CellKey};
use super::map::{CellEstimate, CellState, Evidence, EvidenceMap};
use super::params::Thresholds;

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
    let mut ray = RayCast::new(map, origin_world, direction_world, max_range_m, stop, th)?;
    loop {
        if let Some(hit) = ray.advance() {
            return Ok(hit);
        }
    }
}

/// One ray being walked: the cell it is in, where it entered it, and its block reader.
struct RayCast<'m> {
    walk: VoxelWalk,
    cells: CellReader<'m>,
    cell: CellKey,
    entry_m: f64,
    max_range_m: f64,
}

impl<'m> RayCast<'m> {
    fn new(
        map: &'m EvidenceMap,
        origin_world: [f64; 3],
        direction_world: [f64; 3],
        max_range_m: f64,
        stop: StopAt,
        th: &'m Thresholds,
    ) -> Result<Self, RayError> {
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
        let cell = CellKey::from_point(origin_world, res).ok_or(RayError::Origin)?;
        let far = origin_world.iter().zip(&dir).map(|(o, d)| o + d * max_range_m);
        if far.clone().any(|v| !(v / res).abs().lt(&(i32::MAX as f64 - 2.0))) {
            return Err(RayError::Origin);
        }
        Ok(Self {
            walk: VoxelWalk::new(origin_world, dir, cell, res),
            cells: CellReader::new(map, th, stop),
            cell,
            entry_m: 0.0,
            max_range_m,
        })
    }

    /// Tests the current cell and moves to the next; the verdict once the ray is done.
    #[inline(always)]
    fn advance(&mut self) -> Option<RayHit> {
        if let Some(estimate) = self.cells.stops_at(self.cell) {
            return Some(RayHit::Blocked { cell: self.cell, distance_m: self.entry_m, estimate });
        }
        let (next_cell, next_entry) = self.walk.step();
        if next_entry > self.max_range_m {
            return Some(RayHit::Clear);
        }
        self.cell = next_cell;
        self.entry_m = next_entry;
        None
    }
}

/// Reads cells along a walk: the block is looked up once per block entered, and a cell without
/// evidence answers the prior estimate computed once (the same bits
/// [`CellEstimate::from_evidence`] gives for zero evidence). A block whose summary shows that
/// none of its cells can stop the ray is passed without reading a cell.
struct CellReader<'m> {
    map: &'m EvidenceMap,
    th: &'m Thresholds,
    stop: StopAt,
    prior: CellEstimate,
    prior_stops: bool,
    block_key: Option<BlockKey>,
    /// The current block, `None` when it is absent or cannot stop the ray.
    block: Option<&'m BlockEvidence>,
    /// Whether an absent block's cells (the prior) stop the ray; false for a passed block.
    absent_stops: bool,
}

impl<'m> CellReader<'m> {
    fn new(map: &'m EvidenceMap, th: &'m Thresholds, stop: StopAt) -> Self {
        let prior = CellEstimate::from_evidence(Evidence::default(), map.params(), th);
        let prior_stops = Self::stops(stop, prior.state);
        Self { map, th, stop, prior, prior_stops, block_key: None, block: None, absent_stops: prior_stops }
    }

    /// Whether some cell of a block may stop the ray (false only when its summary rules it out).
    fn may_stop(&self, s: &BlockSummary) -> bool {
        match self.stop {
            StopAt::Occupied => !s.none_occupied(self.th),
            StopAt::NotFree => !s.all_free(self.th),
        }
    }

    fn stops(stop: StopAt, state: CellState) -> bool {
        match stop {
            StopAt::Occupied => state == CellState::Occupied,
            StopAt::NotFree => state != CellState::Free,
        }
    }

    /// The cell's estimate when the ray stops there.
    #[inline]
    fn stops_at(&mut self, cell: CellKey) -> Option<CellEstimate> {
        let key = cell.block();
        if self.block_key != Some(key) {
            self.block_key = Some(key);
            let found = self.map.block_with_summary(key);
            let passed = found.is_some_and(|(_, s)| !self.may_stop(&s));
            self.block = found.filter(|_| !passed).map(|(b, _)| b);
            self.absent_stops = self.prior_stops && !passed;
        }
        let e = match self.block {
            Some(b) => b.get(cell.index_in_block()),
            None => return self.absent_stops.then_some(self.prior),
        };
        if e.is_empty() {
            return self.prior_stops.then_some(self.prior);
        }
        let estimate = CellEstimate::from_evidence(e, self.map.params(), self.th);
        Self::stops(self.stop, estimate.state).then_some(estimate)
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
        // The axis whose boundary comes first (x on ties, then y). No array is indexed by the
        // choice and nothing branches on it (it changes from step to step in no pattern a
        // predictor could learn), so the walk's state stays in registers.
        let [t0, t1, t2] = self.t_max;
        let x = (t0 <= t1) & (t0 <= t2);
        let y = !x & (t1 <= t2);
        let z = !x & !y;
        let entry = (if x {
            t0
        } else if y {
            t1
        } else {
            t2
        })
        .max(0.0);
        for (axis, moves) in [x, y, z].into_iter().enumerate() {
            if moves {
                self.cell[axis] += self.step[axis];
                self.t_max[axis] += self.t_delta[axis];
            }
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::query::tests::room_map;
    use proptest::prelude::*;

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

    /// The walk that reads every cell (no block summaries); the first cell that stops wins.
    fn reference_ray(
        map: &EvidenceMap,
        o: [f64; 3],
        d: [f64; 3],
        range: f64,
        stop: StopAt,
        th: &Thresholds,
    ) -> RayHit {
        let res = map.params().resolution_m;
        let n = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        let mut cell = CellKey::from_point(o, res).unwrap();
        let mut walk = VoxelWalk::new(o, d.map(|v| v / n), cell, res);
        let mut entry = 0.0;
        loop {
            let estimate = map.estimate(cell, th);
            if CellReader::stops(stop, estimate.state) {
                return RayHit::Blocked { cell, distance_m: entry, estimate };
            }
            let (next, next_entry) = walk.step();
            if next_entry > range {
                return RayHit::Clear;
            }
            (cell, entry) = (next, next_entry);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// Passing blocks by their summary gives the answers of reading every cell, for both
        /// stop rules and thresholds that make many or few blocks passable.
        #[test]
        fn block_summaries_change_no_ray_answer(o in (0.5f64..9.5, 0.5f64..5.5, 0.1f64..2.4),
                                                d in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
                                                th_i in 0usize..3, range in 0.3f64..12.0) {
            let map = ROOM.with(|m| m.clone());
            prop_assume!(d.0 * d.0 + d.1 * d.1 + d.2 * d.2 > 0.01);
            let th = [Thresholds::default(),
                      Thresholds { p_free: 0.45, p_occ: 0.55, var_max: 0.05 },
                      Thresholds { p_free: 0.2, p_occ: 0.9, var_max: 100.0 }][th_i];
            for stop in [StopAt::Occupied, StopAt::NotFree] {
                let dir = [d.0, d.1, d.2];
                let fast = cast_ray(&map, [o.0, o.1, o.2], dir, range, stop, &th).unwrap();
                prop_assert_eq!(fast, reference_ray(&map, [o.0, o.1, o.2], dir, range, stop, &th));
            }
        }
    }

    thread_local! {
        static ROOM: EvidenceMap = room_map();
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
