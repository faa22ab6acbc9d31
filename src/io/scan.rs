//! A decoded scan in the world frame, and the PCD → scan conversion (docs/formats.md §3.4).

use super::pcd::PcdCloud;

/// Points (world frame, metres) plus the sensor origin they were seen from.
#[derive(Debug, Clone, PartialEq)]
pub struct Scan {
    pub points_world: Vec<[f32; 3]>,
    pub origin_world: [f64; 3],
    /// Input points dropped because they were not finite.
    pub dropped_nonfinite: usize,
}

pub use crate::core::pose::PointFrame;
use crate::core::pose::Pose;

/// Why a cloud could not be turned into a scan.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScanError {
    #[error("no sensor origin: the PCD file has no VIEWPOINT line (give --origin X,Y,Z)")]
    NoOrigin,
    #[error("VIEWPOINT rotation (w, x, y, z) is not a unit quaternion: {0:?}")]
    BadRotation([f64; 4]),
    #[error("sensor origin must be finite")]
    BadOrigin,
}

/// Converts a PCD cloud; `origin_override` (world frame) replaces the VIEWPOINT translation.
pub fn scan_from_pcd(
    cloud: PcdCloud,
    frame: PointFrame,
    origin_override: Option<[f64; 3]>,
) -> Result<Scan, ScanError> {
    let vp = cloud.viewpoint;
    let origin_world = match (origin_override, vp) {
        (Some(o), _) => o,
        (None, Some(v)) => [v[0], v[1], v[2]],
        (None, None) => return Err(ScanError::NoOrigin),
    };
    if !origin_world.iter().all(|v| v.is_finite()) {
        return Err(ScanError::BadOrigin);
    }
    let mut points_world = cloud.points;
    if frame == PointFrame::Sensor {
        let v = vp.unwrap_or([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
        let pose = Pose { translation_m: origin_world, rotation_wxyz: [v[3], v[4], v[5], v[6]] };
        pose.sensor_to_world(&mut points_world).map_err(|_| ScanError::BadRotation(pose.rotation_wxyz))?;
    }
    Ok(Scan { points_world, origin_world, dropped_nonfinite: cloud.dropped_nonfinite })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(viewpoint: Option<[f64; 7]>) -> PcdCloud {
        PcdCloud { points: vec![[1.0, 0.0, 0.0]], viewpoint, dropped_nonfinite: 0, width: 1, height: 1 }
    }

    #[test]
    fn world_frame_keeps_points_and_uses_viewpoint_origin() {
        let s =
            scan_from_pcd(cloud(Some([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0])), PointFrame::World, None).unwrap();
        assert_eq!(s.points_world, vec![[1.0, 0.0, 0.0]]);
        assert_eq!(s.origin_world, [1.0, 2.0, 3.0]);
    }

    #[test]
    fn sensor_frame_rotates_then_translates() {
        let h = std::f64::consts::FRAC_1_SQRT_2; // 90° about z
        let s =
            scan_from_pcd(cloud(Some([1.0, 2.0, 3.0, h, 0.0, 0.0, h])), PointFrame::Sensor, None).unwrap();
        let p = s.points_world[0];
        assert!((p[0] - 1.0).abs() < 1e-6 && (p[1] - 3.0).abs() < 1e-6 && (p[2] - 3.0).abs() < 1e-6, "{p:?}");
    }

    #[test]
    fn missing_viewpoint_needs_an_origin() {
        assert_eq!(scan_from_pcd(cloud(None), PointFrame::World, None).unwrap_err(), ScanError::NoOrigin);
        assert!(scan_from_pcd(cloud(None), PointFrame::World, Some([0.0; 3])).is_ok());
        let bad = cloud(Some([0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0]));
        assert!(matches!(scan_from_pcd(bad, PointFrame::Sensor, None), Err(ScanError::BadRotation(_))));
    }
}
