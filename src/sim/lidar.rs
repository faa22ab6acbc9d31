//! A simulated spinning LiDAR with Gaussian range noise.

use super::scene::Scene;

/// A spinning multi-beam LiDAR: `vertical_beams` lasers fanned over `vertical_fov_deg`, each
/// fired `horizontal_beams` times per revolution at evenly spaced azimuths.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lidar {
    /// Azimuth steps per revolution (360° / step).
    pub horizontal_beams: u32,
    /// Lasers, evenly spaced in elevation over `vertical_fov_deg` (both ends included; a single
    /// laser points at the middle of the range).
    pub vertical_beams: u32,
    /// (lowest, highest) elevation in degrees; 0 is horizontal, positive up.
    pub vertical_fov_deg: (f64, f64),
    /// Rays whose first surface is at or beyond this distance give no return.
    pub max_range_m: f64,
    /// Standard deviation of the additive Gaussian range noise (metres); 0 for exact ranges.
    pub range_noise_sigma_m: f64,
}

impl Default for Lidar {
    /// A 16-beam spinning LiDAR (VLP-16-like): 16 lasers over −15°..+15°, 1° azimuth steps
    /// (5760 rays per scan), 30 m range, 1 cm range noise.
    fn default() -> Self {
        Self {
            horizontal_beams: 360,
            vertical_beams: 16,
            vertical_fov_deg: (-15.0, 15.0),
            max_range_m: 30.0,
            range_noise_sigma_m: 0.01,
        }
    }
}

/// One simulated scan.
#[derive(Debug, Clone, PartialEq)]
pub struct SimScan {
    /// Sensor position, world frame (metres).
    pub origin: [f64; 3],
    /// Sensor heading about +z (radians, from +x).
    pub yaw_rad: f64,
    /// The returns (hits only), world frame, in firing order: azimuth-major, then elevation
    /// from lowest to highest.
    pub points_world: Vec<[f32; 3]>,
}

impl Lidar {
    /// Rays per scan: `horizontal_beams · vertical_beams`.
    pub fn rays_per_scan(&self) -> usize {
        self.horizontal_beams as usize * self.vertical_beams as usize
    }

    /// The unit ray directions (world frame) for a sensor with heading `yaw_rad`, in firing
    /// order: azimuth `yaw + 2π·i/H` (i = 0..H) outer, elevation lowest to highest inner.
    pub fn directions(&self, yaw_rad: f64) -> Vec<[f64; 3]> {
        let (lo, hi) = self.vertical_fov_deg;
        let v = self.vertical_beams;
        let elevations: Vec<(f64, f64)> = (0..v)
            .map(|j| {
                let deg =
                    if v > 1 { lo + (hi - lo) * f64::from(j) / f64::from(v - 1) } else { 0.5 * (lo + hi) };
                let rad = deg.to_radians();
                (libm::cos(rad), libm::sin(rad))
            })
            .collect();
        let h = self.horizontal_beams;
        let mut dirs = Vec::with_capacity(self.rays_per_scan());
        for i in 0..h {
            let az = yaw_rad + 2.0 * std::f64::consts::PI * f64::from(i) / f64::from(h);
            let (ca, sa) = (libm::cos(az), libm::sin(az));
            dirs.extend(elevations.iter().map(|&(ce, se)| [ce * ca, ce * sa, se]));
        }
        dirs
    }

    /// Scan `scene` from a sensor at `origin` with heading `yaw_rad` (rotation about +z).
    ///
    /// Each ray is cast exactly ([`Scene::ray_cast`]); a ray with nothing closer than
    /// `max_range_m` gives no point. A hit's range gets additive Gaussian noise of
    /// `range_noise_sigma_m` (Box–Muller on `rng`'s uniforms, one normal per hit, none drawn
    /// when sigma is 0), clamped at 0, and the point is `origin + range · dir` rounded to f32.
    /// The same `rng` state gives the same points bit for bit on every machine.
    pub fn scan(&self, scene: &Scene, origin: [f64; 3], yaw_rad: f64, rng: &mut impl rand::Rng) -> SimScan {
        let sigma = self.range_noise_sigma_m;
        let mut normal = Normal::default();
        let mut points_world = Vec::with_capacity(self.rays_per_scan());
        for d in self.directions(yaw_rad) {
            let Some(t) = scene.ray_cast(origin, d, self.max_range_m) else {
                continue;
            };
            let r = if sigma > 0.0 { (t + sigma * normal.sample(rng)).max(0.0) } else { t };
            points_world.push([0, 1, 2].map(|k| (origin[k] + r * d[k]) as f32));
        }
        SimScan { origin, yaw_rad, points_world }
    }
}

/// Standard normal deviates by the Box–Muller transform with `libm`, both outputs used.
#[derive(Debug, Default)]
pub(crate) struct Normal {
    spare: Option<f64>,
}

impl Normal {
    pub(crate) fn sample(&mut self, rng: &mut impl rand::Rng) -> f64 {
        if let Some(z) = self.spare.take() {
            return z;
        }
        // u1 ∈ (0, 1] so the logarithm is finite.
        let u1 = 1.0 - rng.random::<f64>();
        let u2: f64 = rng.random();
        let radius = (-2.0 * libm::log(u1)).sqrt();
        let angle = 2.0 * std::f64::consts::PI * u2;
        self.spare = Some(radius * libm::sin(angle));
        radius * libm::cos(angle)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::trajectory;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn exact() -> Lidar {
        Lidar { range_noise_sigma_m: 0.0, ..Lidar::default() }
    }

    fn surface_distance(scene: &Scene, p: [f64; 3]) -> f64 {
        scene.solids.iter().map(|s| s.signed_distance(p).abs()).fold(f64::INFINITY, f64::min)
    }

    fn widen(p: [f32; 3]) -> [f64; 3] {
        p.map(f64::from)
    }

    #[test]
    fn default_lidar_has_5760_unit_rays_and_all_return_in_the_closed_room() {
        let lidar = Lidar::default();
        assert_eq!(lidar.rays_per_scan(), 5760);
        let dirs = lidar.directions(0.3);
        assert_eq!(dirs.len(), 5760);
        for d in &dirs {
            assert!(((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - 1.0).abs() < 1e-12);
        }
        assert!((dirs[0][2] - libm::sin((-15f64).to_radians())).abs() < 1e-15);
        assert!((dirs[15][2] - libm::sin(15f64.to_radians())).abs() < 1e-15);
        let scene = Scene::room(0);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for (p, yaw) in trajectory(&scene, 10) {
            assert_eq!(lidar.scan(&scene, p, yaw, &mut rng).points_world.len(), 5760);
        }
    }

    #[test]
    fn noiseless_hits_lie_on_surfaces_and_matter_is_just_beyond() {
        let lidar = exact();
        for seed in [0, 3] {
            let scene = Scene::room(seed);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (mut total, mut beyond_free) = (0usize, 0usize);
            for (o, yaw) in trajectory(&scene, 6) {
                let scan = lidar.scan(&scene, o, yaw, &mut rng);
                for &p in &scan.points_world {
                    let p = widen(p);
                    // f32 rounding of coordinates below 16 m is under 1e-6 m per axis.
                    assert!(surface_distance(&scene, p) < 1e-5, "seed {seed}: {p:?} off every surface");
                    let v = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
                    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                    let beyond = |s: f64| [0, 1, 2].map(|k| p[k] + s * v[k] / n);
                    total += 1;
                    if !scene.is_occupied(beyond(0.02)) {
                        beyond_free += 1;
                    }
                }
            }
            // Only rays clipping an edge (a door jamb, a table leg, a pillar's rim) leave the
            // solid within 2 cm: about 0.4 % of them in the default room.
            assert!(beyond_free * 100 <= total, "seed {seed}: {beyond_free} of {total} free 2 cm beyond");
        }
    }

    #[test]
    fn noisy_hits_stay_within_six_sigma_of_a_surface_with_unbiased_noise() {
        let lidar = Lidar::default();
        let sigma = lidar.range_noise_sigma_m;
        let scene = Scene::room(0);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (mut n, mut sum, mut sum2) = (0.0, 0.0, 0.0);
        for (o, yaw) in trajectory(&scene, 4) {
            let scan = lidar.scan(&scene, o, yaw, &mut rng);
            let dirs = lidar.directions(yaw);
            assert_eq!(scan.points_world.len(), dirs.len());
            for (p, d) in scan.points_world.iter().zip(&dirs) {
                let p = widen(*p);
                assert!(surface_distance(&scene, p) < 6.0 * sigma + 1e-5, "{p:?}");
                let t = scene.ray_cast(o, *d, lidar.max_range_m).expect("closed room");
                let r = (0..3).map(|k| (p[k] - o[k]) * d[k]).sum::<f64>();
                n += 1.0;
                sum += r - t;
                sum2 += (r - t) * (r - t);
            }
        }
        let mean = sum / n;
        let sd = (sum2 / n - mean * mean).sqrt();
        assert!(mean.abs() < 0.05 * sigma, "mean {mean}");
        assert!((sd / sigma - 1.0).abs() < 0.03, "sd {sd}");
    }

    #[test]
    fn no_return_beyond_max_range() {
        let scene = Scene::room(0);
        let short = Lidar { max_range_m: 2.0, ..exact() };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let o = [5.0, 2.0, SENSOR];
        let scan = short.scan(&scene, o, 0.0, &mut rng);
        assert!(!scan.points_world.is_empty() && scan.points_world.len() < short.rays_per_scan());
        for p in &scan.points_world {
            let p = widen(*p);
            let r = ((p[0] - o[0]).powi(2) + (p[1] - o[1]).powi(2) + (p[2] - o[2]).powi(2)).sqrt();
            assert!(r < 2.0 + 1e-5);
        }
    }

    const SENSOR: f64 = crate::sim::SENSOR_HEIGHT_M;

    #[test]
    fn box_muller_is_standard_normal() {
        let mut rng = ChaCha8Rng::seed_from_u64(42);
        let mut normal = Normal::default();
        let n = 200_000;
        let xs: Vec<f64> = (0..n).map(|_| normal.sample(&mut rng)).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n as f64;
        let within_1 = xs.iter().filter(|x| x.abs() < 1.0).count() as f64 / n as f64;
        assert!(mean.abs() < 0.01, "{mean}");
        assert!((var - 1.0).abs() < 0.01, "{var}");
        assert!((within_1 - 0.6827).abs() < 0.005, "{within_1}");
    }
}
