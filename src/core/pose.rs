//! Rigid sensor poses (`world_from_sensor`) and the frame convention of scan points.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

/// Largest accepted |q| − 1 for a rotation given as a quaternion (text and f32 round-offs).
pub const UNIT_QUATERNION_TOLERANCE: f64 = 1e-3;

/// The frame a scan's points are given in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PointFrame {
    /// Points are in the world (map) frame; the pose gives only the ray origin (la3dm).
    #[default]
    World,
    /// Points are in the sensor frame: `p_world = q · p + t`.
    Sensor,
}

/// The sensor pose in the world: translation (m) and rotation as a unit quaternion (w, x, y, z).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub translation_m: [f64; 3],
    pub rotation_wxyz: [f64; 4],
}

/// What is wrong with a pose; names the field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseError {
    #[error("translation must be finite, got {0:?}")]
    Translation([f64; 3]),
    #[error("rotation must be a finite unit quaternion (w, x, y, z), got {0:?}")]
    Rotation([f64; 4]),
}

impl Pose {
    pub const IDENTITY: Pose = Pose { translation_m: [0.0; 3], rotation_wxyz: [1.0, 0.0, 0.0, 0.0] };

    /// A pose at `translation_m` with identity rotation.
    pub fn at(translation_m: [f64; 3]) -> Self {
        Self { translation_m, ..Self::IDENTITY }
    }

    /// Checks finiteness and that the quaternion is unit within [`UNIT_QUATERNION_TOLERANCE`].
    pub fn validate(&self) -> Result<UnitQuaternion<f64>, PoseError> {
        if !self.translation_m.iter().all(|v| v.is_finite()) {
            return Err(PoseError::Translation(self.translation_m));
        }
        let [w, x, y, z] = self.rotation_wxyz;
        let q = Quaternion::new(w, x, y, z);
        if !((q.norm() - 1.0).abs() < UNIT_QUATERNION_TOLERANCE) {
            return Err(PoseError::Rotation(self.rotation_wxyz));
        }
        Ok(UnitQuaternion::from_quaternion(q))
    }

    /// Moves sensor-frame points into the world frame in place (`p ← q·p + t`).
    pub fn sensor_to_world(&self, points: &mut [[f32; 3]]) -> Result<(), PoseError> {
        let rot = self.validate()?;
        let t = Vector3::from(self.translation_m);
        for p in points {
            let w = rot * Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) + t;
            *p = [w.x as f32, w.y as f32, w.z as f32];
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_then_translation() {
        let h = std::f64::consts::FRAC_1_SQRT_2; // 90° about z
        let pose = Pose { translation_m: [1.0, 2.0, 3.0], rotation_wxyz: [h, 0.0, 0.0, h] };
        let mut pts = [[1.0f32, 0.0, 0.0]];
        pose.sensor_to_world(&mut pts).unwrap();
        assert!(
            (pts[0][0] - 1.0).abs() < 1e-6
                && (pts[0][1] - 3.0).abs() < 1e-6
                && (pts[0][2] - 3.0).abs() < 1e-6
        );
    }

    #[test]
    fn bad_poses_are_named() {
        let nan = Pose { translation_m: [f64::NAN, 0.0, 0.0], ..Pose::IDENTITY };
        assert!(matches!(nan.validate(), Err(PoseError::Translation(_))));
        let scaled = Pose { rotation_wxyz: [2.0, 0.0, 0.0, 0.0], ..Pose::IDENTITY };
        assert!(matches!(scaled.validate(), Err(PoseError::Rotation(_))));
        let nanq = Pose { rotation_wxyz: [f64::NAN, 0.0, 0.0, 0.0], ..Pose::IDENTITY };
        assert!(matches!(nanq.validate(), Err(PoseError::Rotation(_))));
    }
}
