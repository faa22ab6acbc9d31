//! A scan as it arrives at the service, and its validation.

use super::ServiceError;
use crate::core::{PointFrame, Pose, RawScan};

/// One scan from a transport: identity, sensor pose, points and an optional max range.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanInput {
    /// Who produced the scan (a robot or sensor name); with `seq`, its identity in the map.
    pub source: String,
    pub seq: u64,
    pub world_from_sensor: Pose,
    pub frame: PointFrame,
    pub points: Vec<[f32; 3]>,
    /// The scan's own maximum range (m), capped by the map's.
    pub max_range_m: Option<f64>,
    /// When the scan was taken (Unix ns); the arrival time when absent. Used by retraction of a
    /// time range.
    pub stamp_nanos: Option<i64>,
}

/// Limits on one scan.
#[derive(Debug, Clone, Copy)]
pub struct ScanLimits {
    /// Most points in one scan. Default 4 Mi (a 128-beam lidar sweep is ~0.3 M).
    pub max_points: usize,
    /// Longest source name in bytes. Default 128.
    pub max_source_len: usize,
}

impl Default for ScanLimits {
    fn default() -> Self {
        Self { max_points: 4 << 20, max_source_len: 128 }
    }
}

/// A validated scan: exactly what is journaled (finite points, in the frame they came in).
#[derive(Debug, Clone)]
pub(super) struct PreparedScan {
    pub source: String,
    pub seq: u64,
    pub stamp_nanos: Option<i64>,
    pub raw: RawScan,
    pub dropped_points: usize,
}

/// Checks a source name (also used by retraction and re-posing).
pub(super) fn validate_source(source: &str, limits: &ScanLimits) -> Result<(), ServiceError> {
    if source.is_empty() || source.len() > limits.max_source_len {
        return Err(ServiceError::invalid("source", format!("must be 1–{} bytes", limits.max_source_len)));
    }
    Ok(())
}

/// Checks a sequence number (stored as a signed 64-bit integer).
pub(super) fn validate_seq(seq: u64) -> Result<(), ServiceError> {
    if seq > i64::MAX as u64 {
        return Err(ServiceError::invalid("seq", "must be below 2^63"));
    }
    Ok(())
}

impl ScanInput {
    /// Checks every field (errors name it) and drops non-finite points.
    pub(super) fn prepare(&self, limits: &ScanLimits) -> Result<PreparedScan, ServiceError> {
        validate_source(&self.source, limits)?;
        validate_seq(self.seq)?;
        self.world_from_sensor
            .validate()
            .map_err(|e| ServiceError::invalid("world_from_sensor", e.to_string()))?;
        if let Some(r) = self.max_range_m
            && !(r.is_finite() && r >= 0.0)
        {
            return Err(ServiceError::invalid("max_range", "must be finite and ≥ 0"));
        }
        if self.points.is_empty() {
            return Err(ServiceError::invalid("points", "the scan has no points"));
        }
        if self.points.len() > limits.max_points {
            return Err(ServiceError::invalid(
                "points",
                format!("{} points exceed the limit of {}", self.points.len(), limits.max_points),
            ));
        }
        let points: Vec<[f32; 3]> =
            self.points.iter().copied().filter(|p| p.iter().all(|v| v.is_finite())).collect();
        let dropped_points = self.points.len() - points.len();
        if points.is_empty() {
            return Err(ServiceError::invalid("points", "no finite points"));
        }
        Ok(PreparedScan {
            source: self.source.clone(),
            seq: self.seq,
            stamp_nanos: self.stamp_nanos,
            raw: RawScan {
                frame: self.frame,
                world_from_sensor: self.world_from_sensor,
                points,
                max_range_m: self.max_range_m,
            },
            dropped_points,
        })
    }
}
