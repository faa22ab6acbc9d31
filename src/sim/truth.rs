//! Analytic ground truth: which map cells the scene's solids occupy.

use super::scene::Scene;
use crate::core::key::CellKey;

/// Relative distance from a grid plane within which `v / res` is snapped onto it, so a face
/// lying on a grid plane (10 m at 0.1 m) is not pushed one cell out by rounding.
const SNAP: f64 = 1e-9;

fn snapped(v: f64) -> f64 {
    let r = v.round();
    if (v - r).abs() < SNAP { r } else { v }
}

impl Scene {
    /// Ground truth per cell at resolution `res` (metres), sorted by key.
    ///
    /// Lists every cell of the interior's bounding box grown by one cell on each side — keys
    /// `floor(interior_min / res) − 1 ..= ceil(interior_max / res)` per axis, i.e. the cells
    /// covering `interior_min − res .. interior_max + res` — so the inner layer of the walls,
    /// floor and ceiling is included. A cell is occupied (`true`) when its cube
    /// `[key·res, (key + 1)·res]` shares positive volume with any solid (exact box–box,
    /// box–cylinder and box–sphere overlap, not centre sampling; faces that only touch, up to
    /// 1e-9 m, do not count), free (`false`) otherwise.
    ///
    /// Returns an empty list when `res` is not positive and finite, the interior is not finite
    /// or empty, or a key would leave the `i32` range.
    pub fn truth_cells(&self, res: f64) -> Vec<(CellKey, bool)> {
        let Some((lo, dims)) = self.truth_grid(res) else {
            return Vec::new();
        };
        let [nx, ny, nz] = dims;
        let index = |k: [i64; 3]| {
            ((k[0] - lo[0]) as usize * ny + (k[1] - lo[1]) as usize) * nz + (k[2] - lo[2]) as usize
        };
        let mut occupied = vec![false; nx * ny * nz];
        for solid in &self.solids {
            let (bmin, bmax) = solid.bounds();
            // Candidate key range: the solid's bounds, one cell of slack against rounding,
            // clipped to the grid.
            let mut range = [(0i64, 0i64); 3];
            let mut empty = false;
            for i in 0..3 {
                let grid_first = lo[i] as f64;
                let grid_last = (lo[i] + dims[i] as i64 - 1) as f64;
                let first = ((bmin[i] / res).floor() - 1.0).max(grid_first);
                let last = ((bmax[i] / res).floor() + 1.0).min(grid_last);
                if first.is_nan() || last.is_nan() || first > last {
                    empty = true;
                    break;
                }
                range[i] = (first as i64, last as i64);
            }
            if empty {
                continue;
            }
            for x in range[0].0..=range[0].1 {
                for y in range[1].0..=range[1].1 {
                    for z in range[2].0..=range[2].1 {
                        let k = [x, y, z];
                        let i = index(k);
                        if occupied[i] {
                            continue;
                        }
                        let cell_lo = k.map(|v| v as f64 * res);
                        let cell_hi = k.map(|v| (v + 1) as f64 * res);
                        occupied[i] = solid.overlaps_box(cell_lo, cell_hi);
                    }
                }
            }
        }
        let mut cells = Vec::with_capacity(occupied.len());
        for x in 0..nx as i64 {
            for y in 0..ny as i64 {
                for z in 0..nz as i64 {
                    let k = [x + lo[0], y + lo[1], z + lo[2]];
                    // The range was checked against i32 in `truth_grid`.
                    let key = CellKey::new(k[0] as i32, k[1] as i32, k[2] as i32);
                    cells.push((key, occupied[index(k)]));
                }
            }
        }
        cells
    }

    /// The lowest key and the size (cells per axis) of the truth grid, if valid.
    fn truth_grid(&self, res: f64) -> Option<([i64; 3], [usize; 3])> {
        if !(res > 0.0 && res.is_finite()) {
            return None;
        }
        let mut lo = [0i64; 3];
        let mut dims = [0usize; 3];
        for i in 0..3 {
            let (a, b) = (self.interior_min[i], self.interior_max[i]);
            if !(a.is_finite() && b.is_finite() && a <= b) {
                return None;
            }
            let first = snapped(a / res).floor() - 1.0;
            let last = snapped(b / res).ceil();
            let range = f64::from(i32::MIN)..=f64::from(i32::MAX);
            if !(range.contains(&first) && range.contains(&last)) {
                return None;
            }
            lo[i] = first as i64;
            dims[i] = usize::try_from(last as i64 - lo[i] + 1).ok()?;
        }
        dims[0].checked_mul(dims[1])?.checked_mul(dims[2])?;
        Some((lo, dims))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::Solid;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn lookup(cells: &[(CellKey, bool)], k: CellKey) -> bool {
        let i = cells.binary_search_by_key(&k, |c| c.0).expect("cell listed");
        cells[i].1
    }

    #[test]
    fn truth_grid_covers_the_interior_plus_one_cell_sorted() {
        let scene = Scene::room(0);
        let cells = scene.truth_cells(0.1);
        // x: −1..=100, y: −1..=120, z: −1..=30.
        assert_eq!(cells.len(), 102 * 122 * 32);
        assert_eq!(cells[0].0, CellKey::new(-1, -1, -1));
        assert_eq!(cells[cells.len() - 1].0, CellKey::new(100, 120, 30));
        assert!(cells.windows(2).all(|w| w[0].0 < w[1].0));
        // The outer layer is the inside of the walls, floor and ceiling: all occupied.
        for &(k, occ) in &cells {
            if k.x == -1 || k.x == 100 || k.y == -1 || k.y == 120 || k.z == -1 || k.z == 30 {
                assert!(occ, "{k:?}");
            }
        }
        assert!(Scene::room(0).truth_cells(0.0).is_empty());
        assert!(Scene::room(0).truth_cells(f64::NAN).is_empty());
    }

    #[test]
    fn truth_cells_of_the_default_crate_are_occupied_and_the_room_middle_is_free() {
        let cells = Scene::room(0).truth_cells(0.1);
        // Bottom crate [0.3, 1.1] × [0.3, 1.0] × [0, 0.8]: cells x 3..=10, y 3..=9, z 0..=7.
        for x in 3..=10 {
            for y in 3..=9 {
                for z in 0..=7 {
                    assert!(lookup(&cells, CellKey::new(x, y, z)), "({x}, {y}, {z})");
                }
            }
        }
        // Cells that merely touch the crate's faces are free.
        assert!(!lookup(&cells, CellKey::new(11, 5, 3)));
        assert!(!lookup(&cells, CellKey::new(5, 10, 3)));
        assert!(!lookup(&cells, CellKey::new(2, 5, 3)));
        // The stacked crate [0.4, 0.9]² × [0.8, 1.2] is above it; the air around it is free.
        assert!(lookup(&cells, CellKey::new(4, 4, 11)));
        assert!(!lookup(&cells, CellKey::new(3, 3, 8)));
        // The middle of the free south room, on the route, and the doorway.
        assert!(!lookup(&cells, CellKey::from_point([7.0, 2.0, 1.5], 0.1).expect("key")));
        assert!(!lookup(&cells, CellKey::from_point([5.0, 7.0, 1.0], 0.1).expect("key")));
        assert!(lookup(&cells, CellKey::from_point([5.0, 7.0, 2.5], 0.1).expect("key")));
    }

    #[test]
    fn truth_cylinder_overlap_is_exact_not_centre_sampled() {
        let cells = Scene::room(0).truth_cells(0.1);
        // Pillar at (9.3, 3.5), r 0.25.
        let k = |x: i32, y: i32| CellKey::new(x, y, 10);
        assert!(lookup(&cells, k(93, 35)));
        // [9.5, 9.6] × [3.6, 3.7]: centre 0.29 m from the axis, nearest corner 0.22 m.
        assert!(lookup(&cells, k(95, 36)));
        // [9.5, 9.6] × [3.7, 3.8]: nearest corner 0.28 m.
        assert!(!lookup(&cells, k(95, 37)));
        // [9.5, 9.6] × [3.4, 3.5] touches the rim region: nearest point (9.5, 3.5) at 0.2 m.
        assert!(lookup(&cells, k(95, 34)));
        // [9.6, 9.7] is 0.3 m out.
        assert!(!lookup(&cells, k(96, 35)));
    }

    #[test]
    fn truth_agrees_with_point_sampling() {
        // Every cell whose sampled point is in matter is occupied, and every free cell has no
        // matter at any sampled interior point.
        for seed in [0, 7] {
            let scene = Scene::room(seed);
            let res = 0.25;
            let cells = scene.truth_cells(res);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            for &(k, occ) in &cells {
                let base = [k.x, k.y, k.z].map(|v| f64::from(v) * res);
                let mut any = false;
                for _ in 0..12 {
                    let p = base.map(|b| b + res * (0.001 + 0.998 * rng.random::<f64>()));
                    any |= scene.is_occupied(p);
                }
                if any {
                    assert!(occ, "seed {seed}: {k:?} has matter but is free");
                }
            }
        }
    }

    #[test]
    fn truth_single_sphere_by_hand() {
        let scene =
            Scene::new(vec![Solid::Sphere { centre: [0.5, 0.5, 0.5], radius: 0.3 }], [0.0; 3], [1.0; 3]);
        let cells = scene.truth_cells(0.5);
        // Keys −1..=2 per axis.
        assert_eq!(cells.len(), 64);
        let occupied: Vec<CellKey> = cells.iter().filter(|c| c.1).map(|c| c.0).collect();
        // The ball straddles the corner shared by the 8 cells with keys in {0, 1}³.
        assert_eq!(occupied.len(), 8);
        assert!(occupied.iter().all(|k| [k.x, k.y, k.z].iter().all(|v| (0..=1).contains(v))));
    }
}
