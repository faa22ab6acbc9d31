//! A large outdoor scene for benchmarks: a town of streets on a square grid, buildings in the
//! blocks between them, trees, poles and parked cars along the kerbs; a 64-beam LiDAR
//!  and a drive around the town's streets.
//!
//! Scenes are built from the same exact [`Solid`]s as the room, so scans are deterministic bit
//! for bit. A scan only considers the solids within its LiDAR's range ([`Scene::near`]), which
//! keeps a 130k-ray scan of a scene of thousands of solids at a fraction of a second.

use super::lidar::{Lidar, SimScan};
use super::scene::Scene;
use super::solid::Solid;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Streets run every this many metres in x and y.
pub const OUTDOOR_STREET_PITCH_M: f64 = 40.0;
/// Width of a street, kerb to kerb (m).
const STREET_WIDTH_M: f64 = 12.0;
/// Thickness of the ground slab below z = 0 (m).
const GROUND_DEPTH_M: f64 = 0.5;
/// Height of the LiDAR above the road (m), as on a car roof.
pub const OUTDOOR_SENSOR_HEIGHT_M: f64 = 1.8;

impl Lidar {
    /// A dense 64-beam spinning LiDAR: 64 lasers over −24.8°..+2° (as an HDL-64), 2700 azimuth
    /// steps (172,800 rays per scan; about 130k of them return in the town, the rest point at
    /// the sky), 30 m range, 2 cm range noise.
    pub fn dense64() -> Self {
        Self {
            horizontal_beams: 2700,
            vertical_beams: 64,
            vertical_fov_deg: (-24.8, 2.0),
            max_range_m: 30.0,
            range_noise_sigma_m: 0.02,
        }
    }
}

impl Scene {
    /// A town of `blocks`×`blocks` city blocks ([`OUTDOOR_STREET_PITCH_M`] apart), ground at
    /// z = 0; the route drives around the streets of the whole town. Deterministic per seed.
    pub fn outdoor(seed: u64, blocks: u32) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let n = blocks.max(1);
        let size = f64::from(n) * OUTDOOR_STREET_PITCH_M;
        let half_street = 0.5 * STREET_WIDTH_M;
        let mut solids = vec![Solid::Aabb {
            min: [-half_street, -half_street, -GROUND_DEPTH_M],
            max: [size + half_street, size + half_street, 0.0],
        }];
        for bx in 0..n {
            for by in 0..n {
                let lo = [
                    f64::from(bx) * OUTDOOR_STREET_PITCH_M + half_street,
                    f64::from(by) * OUTDOOR_STREET_PITCH_M + half_street,
                ];
                city_block(&mut rng, lo, OUTDOOR_STREET_PITCH_M - STREET_WIDTH_M, &mut solids);
            }
        }
        let mut scene = Scene::new(solids, [-half_street, -half_street, 0.0], [size + half_street; 3]);
        scene.interior_max[2] = 40.0;
        // Around the outer streets, then up and down the inner ones (a closed loop).
        let mut route = vec![[0.0, 0.0]];
        for i in 0..=n {
            let x = f64::from(i) * OUTDOOR_STREET_PITCH_M;
            let (y0, y1) = if i % 2 == 0 { (0.0, size) } else { (size, 0.0) };
            route.push([x, y0]);
            route.push([x, y1]);
        }
        route.push([size, 0.0]);
        route.dedup();
        scene.route_xy = route;
        scene
    }

    /// The solids whose bounding boxes come within `range_m` of `p` (the rest cannot be hit by
    /// a ray of that length from `p`).
    pub fn near(&self, p: [f64; 3], range_m: f64) -> Scene {
        let solids = self
            .solids
            .iter()
            .filter(|s| {
                let (lo, hi) = s.bounds();
                let d2: f64 = (0..3).map(|i| (lo[i] - p[i]).max(p[i] - hi[i]).max(0.0).powi(2)).sum();
                d2 <= range_m * range_m
            })
            .copied()
            .collect();
        Scene { solids, ..self.clone() }
    }
}

/// Buildings on the block's perimeter, a tree and a pole every few metres along its kerbs, and
/// parked cars.
fn city_block(rng: &mut ChaCha8Rng, lo: [f64; 2], side: f64, out: &mut Vec<Solid>) {
    let setback = 3.0;
    // Four buildings, one per quadrant, of random footprint and height.
    for (qx, qy) in [(0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)] {
        let x0 = lo[0] + setback + qx * (side - 2.0 * setback) + rng.random_range(0.0..2.0);
        let y0 = lo[1] + setback + qy * (side - 2.0 * setback) + rng.random_range(0.0..2.0);
        let w = rng.random_range(6.0..(0.5 * (side - 2.0 * setback) - 2.0));
        let d = rng.random_range(6.0..(0.5 * (side - 2.0 * setback) - 2.0));
        let h = rng.random_range(4.0..20.0);
        out.push(Solid::Aabb { min: [x0, y0, 0.0], max: [x0 + w, y0 + d, h] });
    }
    // Street furniture along the four kerbs.
    let kerbs = [
        ([lo[0], lo[1] + 0.8], [1.0, 0.0]),
        ([lo[0], lo[1] + side - 0.8], [1.0, 0.0]),
        ([lo[0] + 0.8, lo[1]], [0.0, 1.0]),
        ([lo[0] + side - 0.8, lo[1]], [0.0, 1.0]),
    ];
    for (start, dir) in kerbs {
        let mut s = rng.random_range(1.0..4.0);
        while s < side - 1.0 {
            let c = [start[0] + dir[0] * s, start[1] + dir[1] * s];
            match rng.random_range(0..4) {
                0 | 1 => {
                    let crown = rng.random_range(1.0..2.2);
                    let trunk_h = rng.random_range(2.0..3.5);
                    out.push(Solid::Cylinder { centre_xy: c, radius: 0.15, z_min: 0.0, z_max: trunk_h });
                    out.push(Solid::Sphere { centre: [c[0], c[1], trunk_h + 0.7 * crown], radius: crown });
                }
                2 => out.push(Solid::Cylinder { centre_xy: c, radius: 0.08, z_min: 0.0, z_max: 6.0 }),
                _ => {
                    // A parked car on the street side of the kerb.
                    let (along, across) = (4.2, 1.8);
                    let off = [-dir[1] * 1.5, dir[0] * 1.5];
                    let (hx, hy) = if dir[0] != 0.0 { (along, across) } else { (across, along) };
                    let m = [c[0] - off[0] - 0.5 * hx, c[1] - off[1] - 0.5 * hy];
                    out.push(Solid::Aabb { min: [m[0], m[1], 0.2], max: [m[0] + hx, m[1] + hy, 1.5] });
                }
            }
            s += rng.random_range(5.0..9.0);
        }
    }
}

/// `n` scans of `lidar` driving the town of [`Scene::outdoor`]`(seed, blocks)`: poses evenly
/// spaced along its route at [`OUTDOOR_SENSOR_HEIGHT_M`], range noise from stream 1 of the seed.
pub fn simulate_outdoor(seed: u64, blocks: u32, n: usize, lidar: &Lidar) -> (Scene, Vec<SimScan>) {
    let scene = Scene::outdoor(seed, blocks);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(1);
    let lift = OUTDOOR_SENSOR_HEIGHT_M - super::SENSOR_HEIGHT_M;
    let scans = super::trajectory(&scene, n)
        .into_iter()
        .map(|(p, yaw)| {
            let p = [p[0], p[1], p[2] + lift];
            lidar.scan(&scene.near(p, lidar.max_range_m), p, yaw, &mut rng)
        })
        .collect();
    (scene, scans)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outdoor_drive_is_deterministic_and_dense() {
        let lidar = Lidar { horizontal_beams: 256, ..Lidar::dense64() };
        let (scene, a) = simulate_outdoor(3, 2, 3, &lidar);
        let (_, b) = simulate_outdoor(3, 2, 3, &lidar);
        assert_eq!(a, b);
        assert!(scene.solids.len() > 20, "{} solids", scene.solids.len());
        for s in &a {
            // Beams below −3.5° reach the ground within 30 m (79% of them) where there is
            // ground: on the town's outer streets half the view is beyond its edge.
            assert!(s.points_world.len() > lidar.rays_per_scan() / 2, "{} points", s.points_world.len());
            assert!(!scene.is_occupied(s.origin), "pose {:?} inside a solid", s.origin);
            for p in &s.points_world {
                let d = p.iter().zip(&s.origin).map(|(a, b)| (f64::from(*a) - b).powi(2)).sum::<f64>();
                assert!(d.sqrt() < 30.2);
            }
        }
        assert_eq!(Lidar::dense64().rays_per_scan(), 172_800);
    }

    #[test]
    fn near_keeps_exactly_what_a_ray_can_reach() {
        let scene = Scene::outdoor(0, 3);
        let p = [40.0, 40.0, OUTDOOR_SENSOR_HEIGHT_M];
        let near = scene.near(p, 30.0);
        assert!(near.solids.len() < scene.solids.len());
        let lidar = Lidar { horizontal_beams: 128, range_noise_sigma_m: 0.0, ..Lidar::dense64() };
        for d in lidar.directions(0.3) {
            assert_eq!(scene.ray_cast(p, d, 30.0), near.ray_cast(p, d, 30.0));
        }
    }
}
