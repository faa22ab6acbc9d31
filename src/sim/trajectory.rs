//! The robot's trajectory: poses spaced evenly along the scene's route.

use super::scene::Scene;

/// Height of the sensor above the floor (`interior_min[2]`), metres.
pub const SENSOR_HEIGHT_M: f64 = 0.7;
/// Minimum distance (metres) between the trajectory of [`Scene::room`] and any solid.
pub const ROUTE_CLEARANCE_M: f64 = 0.5;

/// `n` sensor poses `(position, yaw_rad)` spaced evenly by arc length around the scene's closed
/// route ([`Scene::route_xy`]), starting at its first waypoint, at [`SENSOR_HEIGHT_M`] above
/// `interior_min[2]`. The yaw (about +z, from +x) is the direction of travel along the current
/// segment. For [`Scene::room`] every pose keeps at least [`ROUTE_CLEARANCE_M`] from every solid.
///
/// A scene without a route uses the rectangle through the quarter points of its interior
/// (no clearance guarantee). A route of one point, or of zero length, gives poses at that
/// point turning on the spot through a full circle.
pub fn trajectory(scene: &Scene, n: usize) -> Vec<([f64; 3], f64)> {
    let route = if scene.route_xy.is_empty() {
        let (lo, hi) = (scene.interior_min, scene.interior_max);
        let q = |i: usize, f: f64| lo[i] + f * (hi[i] - lo[i]);
        vec![
            [q(0, 0.25), q(1, 0.25)],
            [q(0, 0.75), q(1, 0.25)],
            [q(0, 0.75), q(1, 0.75)],
            [q(0, 0.25), q(1, 0.75)],
        ]
    } else {
        scene.route_xy.clone()
    };
    let z = scene.interior_min[2] + SENSOR_HEIGHT_M;
    let m = route.len();
    let segments: Vec<([f64; 2], [f64; 2], f64)> = (0..m)
        .map(|i| {
            let (a, b) = (route[i], route[(i + 1) % m]);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            (a, b, (dx * dx + dy * dy).sqrt())
        })
        .filter(|s| s.2 > 0.0)
        .collect();
    let total: f64 = segments.iter().map(|s| s.2).sum();
    if !(total > 0.0 && total.is_finite()) {
        let p = route[0];
        let turn = 2.0 * std::f64::consts::PI / n.max(1) as f64;
        return (0..n).map(|i| ([p[0], p[1], z], i as f64 * turn)).collect();
    }
    let mut poses = Vec::with_capacity(n);
    let mut seg = 0;
    let mut seg_start = 0.0;
    for i in 0..n {
        let s = total * i as f64 / n as f64;
        while seg + 1 < segments.len() && s >= seg_start + segments[seg].2 {
            seg_start += segments[seg].2;
            seg += 1;
        }
        let (a, b, len) = segments[seg];
        let f = ((s - seg_start) / len).clamp(0.0, 1.0);
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        poses.push(([a[0] + f * dx, a[1] + f * dy, z], libm::atan2(dy, dx)));
    }
    poses
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::Solid;

    #[test]
    fn trajectory_keeps_clearance() {
        for seed in 0..30 {
            let scene = Scene::room(seed);
            for (p, _) in trajectory(&scene, 500) {
                for s in &scene.solids {
                    let d = s.signed_distance(p);
                    assert!(d >= ROUTE_CLEARANCE_M, "seed {seed}: pose {p:?} is {d} m from {s:?}");
                }
            }
        }
    }

    #[test]
    fn trajectory_spacing_and_yaw() {
        let scene = Scene::room(0);
        assert!(trajectory(&scene, 0).is_empty());
        let poses = trajectory(&scene, 200);
        assert_eq!(poses.len(), 200);
        assert_eq!(poses[0], ([2.0, 2.0, SENSOR_HEIGHT_M], 0.0));
        // The loop is 6+3+3+3.5+3+2+6+2+3+3.5+3+3 = 41 m long: steps of 0.205 m.
        for w in poses.windows(2) {
            let (a, b) = (w[0].0, w[1].0);
            let step = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            assert!(step <= 41.0 / 200.0 + 1e-9, "{a:?} → {b:?}");
        }
        // Second segment runs +y: yaw π/2.
        let on_second = poses.iter().find(|(p, _)| p[0] == 8.0 && p[1] > 2.5 && p[1] < 4.5).expect("pose");
        assert!((on_second.1 - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
    }

    #[test]
    fn trajectory_without_route_circles_the_middle() {
        let scene =
            Scene::new(vec![Solid::Sphere { centre: [2.0, 2.0, 1.0], radius: 0.5 }], [0.0; 3], [4.0; 3]);
        let poses = trajectory(&scene, 8);
        assert_eq!(poses.len(), 8);
        for (p, _) in &poses {
            assert!(p[0] >= 1.0 && p[0] <= 3.0 && p[1] >= 1.0 && p[1] <= 3.0 && p[2] == SENSOR_HEIGHT_M);
            assert!(scene.signed_distance(*p) > 0.5);
        }
        let spin = Scene { route_xy: vec![[1.0, 1.0]], ..scene };
        let poses = trajectory(&spin, 4);
        assert_eq!(poses[1], ([1.0, 1.0, SENSOR_HEIGHT_M], std::f64::consts::FRAC_PI_2));
    }
}
