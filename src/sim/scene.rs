//! The scene: a union of solids, the free interior they bound, and the robot's route.

use super::solid::Solid;

/// A static world made of [`Solid`]s (their union is the occupied space).
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// The solids; they may overlap (walls overlap the floor, for example).
    pub solids: Vec<Solid>,
    /// Lower corner of the free interior of the room (metres). The floor, walls and ceiling are
    /// solids just outside `interior_min ..= interior_max`; furniture lies inside it.
    pub interior_min: [f64; 3],
    /// Upper corner of the free interior of the room (metres).
    pub interior_max: [f64; 3],
    /// The robot's route: a closed loop of waypoints (x, y in metres; the last one connects
    /// back to the first) that [`trajectory`](super::trajectory) follows at
    /// [`SENSOR_HEIGHT_M`](super::SENSOR_HEIGHT_M) above `interior_min[2]`. [`Scene::room`] sets
    /// a route that keeps at least [`ROUTE_CLEARANCE_M`](super::ROUTE_CLEARANCE_M) from every
    /// solid; when empty, the trajectory falls back to a rectangle through the quarter points
    /// of the interior, with no clearance guarantee.
    pub route_xy: Vec<[f64; 2]>,
}

impl Scene {
    /// A scene with the given solids and interior and no route.
    pub fn new(solids: Vec<Solid>, interior_min: [f64; 3], interior_max: [f64; 3]) -> Self {
        Self { solids, interior_min, interior_max, route_xy: Vec::new() }
    }

    /// Distance along the unit vector `dir` from `origin` to the first solid surface, if it is
    /// less than `max_range`.
    ///
    /// Exact analytic intersection (slab method for boxes, quadratic for cylinders including
    /// their caps and for spheres). An `origin` inside a solid or on its surface is already in
    /// matter and gives `Some(0.0)`. A zero or non-finite `dir` or non-finite `origin` gives
    /// `None`. When `dir` is not unit length the result is the ray parameter, not a distance.
    pub fn ray_cast(&self, origin: [f64; 3], dir: [f64; 3], max_range: f64) -> Option<f64> {
        if !origin.iter().chain(dir.iter()).all(|v| v.is_finite()) || dir == [0.0; 3] {
            return None;
        }
        let mut best = f64::INFINITY;
        for solid in &self.solids {
            if let Some((t0, t1)) = solid.line_interval(origin, dir)
                && t1 >= 0.0
            {
                best = best.min(t0.max(0.0));
            }
        }
        (best < max_range).then_some(best)
    }

    /// Whether `p` lies in any solid (surfaces included).
    pub fn is_occupied(&self, p: [f64; 3]) -> bool {
        self.solids.iter().any(|s| s.contains(p))
    }

    /// The smallest signed distance from `p` to any solid (positive outside all of them).
    /// Outside the solids this is the exact distance to the occupied space; inside it is
    /// negative but, where solids overlap, not necessarily the depth below the union's surface.
    /// `+∞` for a scene without solids.
    pub fn signed_distance(&self, p: [f64; 3]) -> f64 {
        self.solids.iter().map(|s| s.signed_distance(p)).fold(f64::INFINITY, f64::min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn close(a: Option<f64>, b: f64) -> bool {
        a.is_some_and(|a| (a - b).abs() < 1e-12)
    }

    fn one(s: Solid) -> Scene {
        Scene::new(vec![s], [-10.0; 3], [10.0; 3])
    }

    #[test]
    fn ray_cast_box_hand_computed() {
        let s = one(Solid::Aabb { min: [1.0, -1.0, -1.0], max: [2.0, 1.0, 1.0] });
        assert!(close(s.ray_cast([0.0; 3], [1.0, 0.0, 0.0], 30.0), 1.0));
        // Steep in the xy plane: for x in [1, 2] the ray has y = 4x/3 > 1, so it passes beside.
        let d = [0.6, 0.8, 0.0];
        assert_eq!(s.ray_cast([0.0; 3], d, 30.0), None);
        let d = [0.8, 0.6, 0.0];
        // x = 1 at t = 1.25 (y = 0.75): hits the x face.
        assert!(close(s.ray_cast([0.0; 3], d, 30.0), 1.25));
        // From above, hitting the top face z = 1 at t = 2.
        assert!(close(s.ray_cast([1.5, 0.0, 3.0], [0.0, 0.0, -1.0], 30.0), 2.0));
        // Behind the origin: no hit.
        assert_eq!(s.ray_cast([0.0; 3], [-1.0, 0.0, 0.0], 30.0), None);
        // Out of range (strictly less than max_range counts).
        assert_eq!(s.ray_cast([0.0; 3], [1.0, 0.0, 0.0], 1.0), None);
        assert!(close(s.ray_cast([0.0; 3], [1.0, 0.0, 0.0], 1.0 + 1e-9), 1.0));
    }

    #[test]
    fn ray_cast_cylinder_side_and_caps() {
        let s = one(Solid::Cylinder { centre_xy: [0.0, 0.0], radius: 1.0, z_min: 0.0, z_max: 2.0 });
        // Side, head-on.
        assert!(close(s.ray_cast([-5.0, 0.0, 1.0], [1.0, 0.0, 0.0], 30.0), 4.0));
        // Side, off-centre chord at y = 0.6: x = −0.8.
        assert!(close(s.ray_cast([-5.0, 0.6, 1.0], [1.0, 0.0, 0.0], 30.0), 4.2));
        // Top cap from above and bottom cap from below.
        assert!(close(s.ray_cast([0.5, 0.0, 10.0], [0.0, 0.0, -1.0], 30.0), 8.0));
        assert!(close(s.ray_cast([0.0, 0.0, -3.0], [0.0, 0.0, 1.0], 30.0), 3.0));
        // Oblique onto the top cap: z = 2 at t = √2, where x = −0.5 (inside the rim).
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(close(s.ray_cast([-1.5, 0.0, 3.0], [h, 0.0, -h], 30.0), 2f64.sqrt()));
        // Oblique onto the side: x = −1 at t = 2.5·√2, where z = 1.
        assert!(close(s.ray_cast([-3.5, 0.0, 3.5], [h, 0.0, -h], 30.0), 2.5 * 2f64.sqrt()));
        // Passing over the top.
        assert_eq!(s.ray_cast([-3.0, 0.0, 2.5], [1.0, 0.0, 0.0], 30.0), None);
        // Beside it.
        assert_eq!(s.ray_cast([-5.0, 1.5, 1.0], [1.0, 0.0, 0.0], 30.0), None);
    }

    #[test]
    fn ray_cast_sphere_hand_computed() {
        let s = one(Solid::Sphere { centre: [3.0, 0.0, 0.0], radius: 1.0 });
        assert!(close(s.ray_cast([0.0; 3], [1.0, 0.0, 0.0], 30.0), 2.0));
        assert!(close(s.ray_cast([0.0, 0.6, 0.0], [1.0, 0.0, 0.0], 30.0), 2.2));
        assert!(close(s.ray_cast([3.0, 0.0, 5.0], [0.0, 0.0, -1.0], 30.0), 4.0));
        assert_eq!(s.ray_cast([0.0, 1.5, 0.0], [1.0, 0.0, 0.0], 30.0), None);
    }

    #[test]
    fn ray_starting_inside_or_on_a_solid_returns_zero() {
        for solid in [
            Solid::Aabb { min: [-1.0; 3], max: [1.0; 3] },
            Solid::Cylinder { centre_xy: [0.0, 0.0], radius: 1.0, z_min: -1.0, z_max: 1.0 },
            Solid::Sphere { centre: [0.0; 3], radius: 1.0 },
        ] {
            let s = one(solid);
            assert_eq!(s.ray_cast([0.0; 3], [0.0, 0.6, 0.8], 30.0), Some(0.0), "{solid:?}");
            assert_eq!(s.ray_cast([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], 30.0), Some(0.0), "{solid:?}");
            assert!(s.is_occupied([0.0; 3]));
        }
    }

    #[test]
    fn ray_cast_rejects_degenerate_input_and_takes_the_nearest_solid() {
        let s = Scene::new(
            vec![
                Solid::Aabb { min: [5.0, -1.0, -1.0], max: [6.0, 1.0, 1.0] },
                Solid::Sphere { centre: [3.0, 0.0, 0.0], radius: 0.5 },
            ],
            [-10.0; 3],
            [10.0; 3],
        );
        assert!(close(s.ray_cast([0.0; 3], [1.0, 0.0, 0.0], 30.0), 2.5));
        assert_eq!(s.ray_cast([0.0; 3], [0.0; 3], 30.0), None);
        assert_eq!(s.ray_cast([f64::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], 30.0), None);
        assert_eq!(s.ray_cast([0.0; 3], [f64::INFINITY, 0.0, 0.0], 30.0), None);
    }

    #[test]
    fn ray_cast_agrees_with_marching_and_is_occupied_just_past_the_hit() {
        // Random rays from the free interior of the default room: the exact hit is in matter a
        // hair further on, and a fine march never finds matter before it.
        let scene = Scene::room(0);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut rays = 0;
        while rays < 300 {
            let o = [0, 1, 2].map(|i| {
                let u: f64 = rng.random();
                scene.interior_min[i] + u * (scene.interior_max[i] - scene.interior_min[i])
            });
            if scene.signed_distance(o) < 0.05 {
                continue;
            }
            let d = random_unit(&mut rng);
            let t = scene.ray_cast(o, d, 30.0).expect("closed room");
            let at = |t: f64| [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            assert!(scene.is_occupied(at(t + 1e-9)), "o {o:?} d {d:?} t {t}");
            let mut s = 0.0;
            while s < t - 1e-6 {
                assert!(!scene.is_occupied(at(s)), "matter before the hit: o {o:?} d {d:?} s {s} t {t}");
                s += 0.005;
            }
            rays += 1;
        }
    }

    pub(crate) fn random_unit(rng: &mut impl Rng) -> [f64; 3] {
        loop {
            let v = [0, 1, 2].map(|_| 2.0 * rng.random::<f64>() - 1.0);
            let n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
            if n2 > 1e-6 && n2 <= 1.0 {
                let n = n2.sqrt();
                return v.map(|c| c / n);
            }
        }
    }

    #[test]
    fn default_room_is_closed_every_ray_from_inside_hits() {
        for seed in [0, 1, 2, 3] {
            let scene = Scene::room(seed);
            let mut rng = ChaCha8Rng::seed_from_u64(seed + 100);
            for _ in 0..2000 {
                let o = [0, 1, 2].map(|i| {
                    let u: f64 = rng.random();
                    scene.interior_min[i] + u * (scene.interior_max[i] - scene.interior_min[i])
                });
                let d = random_unit(&mut rng);
                let t = scene.ray_cast(o, d, 30.0);
                assert!(t.is_some(), "seed {seed}: escaped from {o:?} along {d:?}");
            }
        }
    }

    #[test]
    fn is_occupied_and_signed_distance_in_the_default_room() {
        let scene = Scene::room(0);
        assert!(scene.is_occupied([5.0, 6.0, -0.1])); // floor
        assert!(scene.is_occupied([5.0, 6.0, 3.1])); // ceiling
        assert!(scene.is_occupied([-0.1, 6.0, 1.0])); // wall
        assert!(scene.is_occupied([1.0, 7.0, 1.0])); // partition
        assert!(!scene.is_occupied([5.0, 7.0, 1.0])); // doorway
        assert!(scene.is_occupied([5.0, 7.0, 2.5])); // lintel
        assert!(!scene.is_occupied([5.0, 2.0, 1.5])); // on the route
        assert!((scene.signed_distance([5.0, 2.0, 0.7]) - 0.7).abs() < 1e-12); // floor nearest
    }
}
