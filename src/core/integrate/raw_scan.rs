//! A scan exactly as a map received it: frame, pose, points and range — the input from which its
//! evidence is computed, again and again (replay after a crash, retraction, re-posing, exact
//! merges).
//!
//! The evidence of a scan is a pure function of its [`RawScan`] and the map's parameters:
//! [`RawScan::delta`] and [`RawScan::add_into`] always go through [`RawScan::points_world`] and
//! the same training set and scatter, so the service, the replay and the offline tools get the
//! same bits. Points keep their order: downsampling sums points voxel by voxel, so the order
//! is part of the result.

use super::delta::ScanDelta;
use super::integrator::Integrator;
use super::sink::BlockSink;
use crate::core::pose::{PointFrame, Pose, PoseError};
use std::borrow::Cow;

/// One scan's raw input. Points are finite (non-finite ones are dropped before a scan is
/// journaled); in `frame` coordinates, metres.
#[derive(Debug, Clone, PartialEq)]
pub struct RawScan {
    pub frame: PointFrame,
    pub world_from_sensor: Pose,
    pub points: Vec<[f32; 3]>,
    /// The scan's own maximum range (m), capped by the map's.
    pub max_range_m: Option<f64>,
}

impl RawScan {
    /// The sensor origin in the world frame (the pose's translation).
    pub fn origin_world(&self) -> [f64; 3] {
        self.world_from_sensor.translation_m
    }

    /// The points in the world frame: as given for [`PointFrame::World`], else moved by the pose
    /// (`p_world = q · p + t`, rounded to f32).
    pub fn points_world(&self) -> Result<Cow<'_, [[f32; 3]]>, PoseError> {
        match self.frame {
            PointFrame::World => {
                self.world_from_sensor.validate()?;
                Ok(Cow::Borrowed(&self.points))
            }
            PointFrame::Sensor => {
                let mut pts = self.points.clone();
                self.world_from_sensor.sensor_to_world(&mut pts)?;
                Ok(Cow::Owned(pts))
            }
        }
    }

    /// The evidence this scan adds to a map with the integrator's parameters.
    pub fn delta(&self, integrator: &mut Integrator, threads: usize) -> Result<ScanDelta, PoseError> {
        let points = self.points_world()?;
        Ok(integrator.scan_delta_with_range(&points, self.origin_world(), threads, self.max_range_m))
    }

    /// Adds this scan's evidence (the bits of [`Self::delta`]) straight into `sink`.
    pub fn add_into<S: BlockSink + ?Sized>(
        &self,
        integrator: &mut Integrator,
        sink: &mut S,
        threads: usize,
    ) -> Result<(), PoseError> {
        let points = self.points_world()?;
        integrator.add_scan_into(sink, &points, self.origin_world(), threads, self.max_range_m);
        Ok(())
    }

    /// The same scan under a corrected pose (loop closure).
    ///
    /// - Sensor frame: the points stay, the pose is replaced — exactly the scan a client would
    ///   have sent with the corrected pose in the first place.
    /// - World frame: the points were placed with the old pose, so they move rigidly with the
    ///   correction `new · old⁻¹` (computed in f64, rounded to f32): `p' = R_new·R_oldᵀ·(p − t_old)
    ///   + t_new`. Building with these moved points from the start gives the same bits.
    pub fn reposed(&self, new_pose: Pose) -> Result<RawScan, PoseError> {
        let new_rot = new_pose.validate()?;
        let old_rot = self.world_from_sensor.validate()?;
        let points = match self.frame {
            PointFrame::Sensor => self.points.clone(),
            PointFrame::World => {
                let correction = new_rot * old_rot.inverse();
                let t_old = nalgebra::Vector3::from(self.world_from_sensor.translation_m);
                let t_new = nalgebra::Vector3::from(new_pose.translation_m);
                self.points
                    .iter()
                    .map(|p| {
                        let v = nalgebra::Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                        let w = correction * (v - t_old) + t_new;
                        [w.x as f32, w.y as f32, w.z as f32]
                    })
                    .collect()
            }
        };
        Ok(RawScan { points, world_from_sensor: new_pose, ..self.clone() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::{EvidenceMap, MapParams};

    fn wall(frame: PointFrame, pose: Pose) -> RawScan {
        let points =
            (0..300).map(|i| [2.5, -1.0 + (i % 20) as f32 * 0.1, -0.5 + (i / 20) as f32 * 0.1]).collect();
        RawScan { frame, world_from_sensor: pose, points, max_range_m: None }
    }

    #[test]
    fn sensor_frame_repose_equals_the_scan_sent_with_the_new_pose() {
        let params = MapParams::default();
        let mut integ = Integrator::new(params);
        let old = wall(PointFrame::Sensor, Pose::at([0.0, 0.0, 0.5]));
        let h = (0.1f64).cos();
        let new_pose = Pose { translation_m: [0.3, -0.2, 0.5], rotation_wxyz: [h, 0.0, 0.0, (0.1f64).sin()] };
        let moved = old.reposed(new_pose).unwrap();
        assert_eq!(moved, wall(PointFrame::Sensor, new_pose));
        // Old delta out, new delta in: the same bits as the new scan alone.
        let mut map = EvidenceMap::new(params);
        map.apply(&old.delta(&mut integ, 1).unwrap(), 1);
        map.apply(&old.delta(&mut integ, 1).unwrap(), -1);
        map.apply(&moved.delta(&mut integ, 1).unwrap(), 1);
        let mut clean = EvidenceMap::new(params);
        clean.apply(&wall(PointFrame::Sensor, new_pose).delta(&mut integ, 1).unwrap(), 1);
        assert_eq!(map.block_keys_sorted(), clean.block_keys_sorted());
        for k in map.block_keys_sorted() {
            assert_eq!(map.block(k), clean.block(k));
        }
    }

    #[test]
    fn world_frame_repose_moves_points_rigidly() {
        let old = wall(PointFrame::World, Pose::at([0.0, 0.0, 0.5]));
        let moved = old.reposed(Pose::at([1.0, 2.0, 0.5])).unwrap();
        assert_eq!(moved.origin_world(), [1.0, 2.0, 0.5]);
        for (a, b) in old.points.iter().zip(&moved.points) {
            assert!((b[0] - a[0] - 1.0).abs() < 1e-6 && (b[1] - a[1] - 2.0).abs() < 1e-6 && b[2] == a[2]);
        }
        let bad = Pose { rotation_wxyz: [2.0, 0.0, 0.0, 0.0], ..Pose::IDENTITY };
        assert!(old.reposed(bad).is_err());
    }
}
