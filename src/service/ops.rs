//! The exact operations on a live map — retract, re-pose, merge — run by its writer thread in
//! order with the scans journaled before them (see [`crate::store::ops`]).

use super::scan::{validate_seq, validate_source};
use super::writer::{Work, Writer};
use super::{MapService, ServiceError};
use crate::core::Pose;
use crate::store::{Change, OpError, ScanId, ScanSelector};
use std::path::PathBuf;

/// Where a merge takes its evidence from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MergeSource {
    /// Another map of this service.
    Map(String),
    /// A map file on the server's file system (relative paths are relative to the data
    /// directory). It is only read.
    File(PathBuf),
}

/// An operation for a map's writer.
#[derive(Debug)]
pub(super) enum Op {
    Retract(ScanSelector),
    Repose(Vec<(ScanId, Pose)>),
    Merge(PathBuf),
}

impl MapService {
    /// Removes scans (listed, or all matching a source and/or stamp range) exactly: the map
    /// becomes bit-identical to one built without them. Blocks until done.
    pub fn retract(&self, name: &str, selector: ScanSelector) -> Result<Change, ServiceError> {
        if let Some(s) = &selector.source {
            validate_source(s, &self.config.limits)?;
        }
        for (s, q) in &selector.scans {
            validate_source(s, &self.config.limits)?;
            validate_seq(*q)?;
        }
        if let (Some(f), Some(t)) = (selector.from_stamp_nanos, selector.to_stamp_nanos)
            && f >= t
        {
            return Err(ServiceError::invalid("to_stamp_nanos", "must be greater than from_stamp_nanos"));
        }
        self.run_op(name, Op::Retract(selector))
    }

    /// Re-integrates scans under corrected poses: bit-identical to having built them with those
    /// poses. Blocks until done.
    pub fn repose(&self, name: &str, poses: Vec<(ScanId, Pose)>) -> Result<Change, ServiceError> {
        if poses.is_empty() {
            return Err(ServiceError::invalid("poses", "no scans to re-pose"));
        }
        for ((s, q), pose) in &poses {
            validate_source(s, &self.config.limits)?;
            validate_seq(*q)?;
            pose.validate()
                .map_err(|e| ServiceError::invalid("world_from_sensor", format!("scan ({s}, {q}): {e}")))?;
        }
        self.run_op(name, Op::Repose(poses))
    }

    /// Adds another map's evidence exactly, counting scans both hold once. Blocks until done.
    pub fn merge(&self, name: &str, from: MergeSource) -> Result<Change, ServiceError> {
        let path = match from {
            MergeSource::Map(other) => {
                if other == name {
                    return Err(ServiceError::invalid("from_map", "a map cannot be merged into itself"));
                }
                self.handle(&other)?.path.clone()
            }
            MergeSource::File(p) if p.as_os_str().is_empty() => {
                return Err(ServiceError::invalid("from_file", "empty path"));
            }
            MergeSource::File(p) => self.data_dir.join(p),
        };
        self.run_op(name, Op::Merge(path))
    }

    fn run_op(&self, name: &str, op: Op) -> Result<Change, ServiceError> {
        let h = self.handle(name)?;
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        {
            let ops = super::lock(&h.ops);
            let sender = ops.as_ref().ok_or(ServiceError::ShuttingDown)?;
            sender
                .send(Work::Op(op, Box::new(move |r| drop(tx.send(r)))))
                .map_err(|_| ServiceError::ShuttingDown)?;
        }
        rx.recv().unwrap_or(Err(ServiceError::ShuttingDown))
    }
}

impl Writer {
    /// Runs one operation on the writer's map and publishes the result.
    pub(super) fn run_op(&mut self, op: Op) -> Result<Change, ServiceError> {
        if let Some(reason) = self.shared.faults.read_only() {
            return Err(ServiceError::ReadOnly { map: self.name(), reason });
        }
        let result = match op {
            Op::Retract(sel) => self.map.retract(&sel),
            Op::Repose(poses) => self.map.repose(&poses),
            Op::Merge(path) => self.map.merge_from(&path),
        };
        match result {
            Ok(change) => {
                if change.scans > 0 || change.blocks_changed > 0 {
                    self.publish();
                }
                Ok(change)
            }
            Err(OpError::Refused(m)) => Err(ServiceError::Precondition(m)),
            Err(OpError::NotFound(m)) => Err(ServiceError::ScansNotFound(m)),
            Err(OpError::Invalid(m)) => Err(ServiceError::invalid("request", m)),
            Err(OpError::Store(e)) if e.is_corruption() => Err(e.into()),
            Err(OpError::Store(e)) => {
                let reason = e.to_string();
                self.shared.faults.apply_failed(reason.clone());
                Err(ServiceError::ReadOnly { map: self.name(), reason })
            }
        }
    }
}
