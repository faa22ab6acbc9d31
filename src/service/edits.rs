//! The exact edits of a live map — retract, re-pose, merge: validated here, then handed to the
//! map's writer thread, which runs them in order with the scans journaled before them (see
//! [`crate::store::edits`]). The caller blocks until the writer answers.
//!
//! Depends on the writer only for its queue ([`Work`], [`Edit`]); the writer never depends on
//! this module.

use super::scan::{validate_seq, validate_source};
use super::writer::{Edit, Work};
use super::{MapService, ServiceError};
use crate::core::Pose;
use crate::store::{Change, ScanId, ScanSelector};
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
        self.run_edit(name, Edit::Retract(selector))
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
        self.run_edit(name, Edit::Repose(poses))
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
        self.run_edit(name, Edit::Merge(path))
    }

    fn run_edit(&self, name: &str, edit: Edit) -> Result<Change, ServiceError> {
        let h = self.handle(name)?;
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        {
            let work = super::lock(&h.work);
            let sender = work.as_ref().ok_or(ServiceError::ShuttingDown)?;
            sender
                .send(Work::Edit(edit, Box::new(move |r| drop(tx.send(r)))))
                .map_err(|_| ServiceError::ShuttingDown)?;
        }
        rx.recv().unwrap_or(Err(ServiceError::ShuttingDown))
    }
}
