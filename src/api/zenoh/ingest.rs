//! Scans over zenoh: the subscriber on `bgkmap/<map>/scans/<source>` (fire and forget), the
//! acknowledged `bgkmap/<map>/ingest` query, and what both share with the ROS 2 bridges —
//! submitting to the service with back-pressure, and counting and logging refusals.
//!
//! A put has no reply, so a refused scan is counted as `rejected` for its source (visible in
//! `GetMap` and `/metrics`) and logged once per map, source and kind of fault; the session keeps
//! going. A full writer queue is not a refusal: the worker waits and retries, which holds the
//! subscriber's channel and, through TCP, the publisher (use `CongestionControl::Block` there).
//! One worker serves every map, in arrival order: while one map's queue is full, puts to the
//! others wait too (the acknowledged query has no such coupling).

use super::ZenohError;
use crate::api::proto::calls::ProtoCalls;
use crate::api::proto::convert::scan_input;
use crate::api::proto::pb;
use crate::service::{ScanInput, ServiceError};
use prost::Message as _;
use std::collections::HashSet;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tonic::Status;
use zenoh::pubsub::Subscriber;

/// Every scan key of every map.
pub const SCANS_KEY: &str = "bgkmap/*/scans/**";
/// Samples waiting for the scan worker before the subscriber blocks (and with it the link).
const SCAN_CHANNEL: usize = 64;
/// Distinct (map, source, kind) refusals logged; later ones are only counted.
const MAX_LOGGED: usize = 10_000;
/// Longest wait between retries of a scan the writer queue refused as busy.
const MAX_RETRY_WAIT: Duration = Duration::from_secs(1);

/// `bgkmap/<map>/<kind>[/<rest>]` → (map, rest); `None` unless the map chunk is a map name.
pub fn parse_key<'a>(key: &'a str, kind: &str) -> Option<(&'a str, &'a str)> {
    let (map, rest) = key.strip_prefix("bgkmap/")?.split_once('/')?;
    let tail = rest.strip_prefix(kind)?;
    let tail = if tail.is_empty() { tail } else { tail.strip_prefix('/')? };
    crate::service::validate_map_name(map).ok()?;
    Some((map, tail))
}

/// What the zenoh handlers share: the protobuf calls and the log of refusals.
#[derive(Debug)]
pub struct IngestContext {
    pub calls: ProtoCalls,
    logged: Mutex<HashSet<(String, String, &'static str)>>,
}

impl IngestContext {
    pub fn new(calls: ProtoCalls) -> Self {
        Self { calls, logged: Mutex::default() }
    }

    /// Logs `reason` unless this (map, source, kind) was logged before.
    pub fn log_once(&self, map: &str, source: &str, kind: &'static str, reason: &str) {
        let mut logged = self.logged.lock().unwrap_or_else(PoisonError::into_inner);
        if logged.len() >= MAX_LOGGED || !logged.insert((map.to_string(), source.to_string(), kind)) {
            return;
        }
        eprintln!(
            "bgkmap: zenoh: map {map:?}, source {source:?}: {kind}: {reason} \
             (counted; further {kind} faults of this source are not logged)"
        );
    }

    /// A scan refused before it reached the service: counted for its source, logged once.
    pub fn reject(&self, map: &str, source: &str, kind: &'static str, reason: &str) {
        let counted = self.calls.service().count_rejected(map, source);
        let reason = match counted {
            Ok(()) => reason.to_string(),
            Err(e) => format!("{reason}; not counted: {e}"),
        };
        self.log_once(map, source, kind, &reason);
    }

    /// Submits a scan without waiting for it to be applied; a busy queue is waited out.
    /// Refusals are counted by the service and logged once here.
    pub fn submit(self: &Arc<Self>, map: &str, scan: ScanInput) {
        let source = scan.source.clone();
        loop {
            let (me, m, s) = (self.clone(), map.to_string(), source.clone());
            let done = Box::new(move |r: Result<_, ServiceError>| {
                if let Err(e) = r {
                    me.log_once(&m, &s, "store", &e.to_string());
                }
            });
            match self.calls.service().submit_scan(map, scan.clone(), done) {
                Ok(()) => return,
                Err(ServiceError::Busy { retry_after_ms, .. }) => {
                    std::thread::sleep(Duration::from_millis(retry_after_ms.max(1)).min(MAX_RETRY_WAIT));
                }
                Err(e @ ServiceError::InvalidArgument { .. }) => {
                    return self.log_once(map, &source, "invalid scan", &e.to_string());
                }
                Err(e) => return self.log_once(map, &source, "refused", &e.to_string()),
            }
        }
    }

    /// One sample from the scan subscriber.
    fn on_scan(self: &Arc<Self>, key: &str, payload: &[u8]) {
        let Some((map, source)) = parse_key(key, "scans").filter(|(_, s)| !s.is_empty()) else {
            return self.log_once("?", key, "key", "not bgkmap/<map>/scans/<source>");
        };
        let limit = self.calls.max_message_bytes();
        if payload.len() > limit {
            let reason = format!("payload of {} bytes exceeds max_message_bytes {limit}", payload.len());
            return self.reject(map, source, "size", &reason);
        }
        let mut scan = match pb::Scan::decode(payload) {
            Ok(s) => s,
            Err(e) => return self.reject(map, source, "protobuf", &format!("malformed bgkmap.v1.Scan: {e}")),
        };
        if scan.source.is_empty() {
            scan.source = source.to_string();
        } else if scan.source != source {
            let reason = format!("bgkmap.v1.Scan.source {:?} differs from the key's source", scan.source);
            return self.reject(map, source, "source", &reason);
        }
        match scan_input(Some(scan)) {
            Ok(input) => self.submit(map, input),
            Err(status) => self.reject(map, source, "scan", status.message()),
        }
    }

    /// The acknowledged path: decodes the query's scan, waits until it is durable in the map's
    /// journal (or found a duplicate; with `wait_applied`, until it is integrated) and returns
    /// the encoded `InsertScanResponse`, as gRPC `InsertScan` does.
    pub async fn ingest_query(
        &self,
        map: &str,
        payload: &[u8],
        wait_applied: bool,
    ) -> Result<Vec<u8>, Status> {
        let scan = pb::Scan::decode(payload)
            .map_err(|e| Status::invalid_argument(format!("malformed protobuf bgkmap.v1.Scan: {e}")))?;
        let ack = self.calls.insert(map, scan_input(Some(scan))?, wait_applied).await?;
        let response = pb::InsertScanResponse {
            applied: ack.applied,
            version: ack.version,
            dropped_points: ack.dropped_points as u64,
        };
        Ok(response.encode_to_vec())
    }
}

/// Declares the scan subscriber and starts its worker thread, which hands each scan to the
/// service in arrival order and ends when the subscriber is gone and its channel drained.
pub async fn spawn_scan_worker(
    session: &zenoh::Session,
    ctx: Arc<IngestContext>,
) -> Result<(Subscriber<()>, std::thread::JoinHandle<()>), ZenohError> {
    let (tx, rx) = std::sync::mpsc::sync_channel::<zenoh::sample::Sample>(SCAN_CHANNEL);
    let sub = session
        .declare_subscriber(SCANS_KEY)
        .callback(move |sample| {
            let _ = tx.send(sample);
        })
        .await
        .map_err(|e| ZenohError::declare(SCANS_KEY, e))?;
    let worker = std::thread::Builder::new()
        .name("bgkmap-zenoh-scans".into())
        .spawn(move || {
            while let Ok(sample) = rx.recv() {
                ctx.on_scan(sample.key_expr().as_str(), &sample.payload().to_bytes());
            }
        })
        .map_err(|e| ZenohError::Zenoh(format!("starting the scan worker: {e}")))?;
    Ok((sub, worker))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_name_a_map_kind_and_rest() {
        assert_eq!(parse_key("bgkmap/office/scans/robot1", "scans"), Some(("office", "robot1")));
        assert_eq!(parse_key("bgkmap/office/scans/fleet/r2", "scans"), Some(("office", "fleet/r2")));
        assert_eq!(parse_key("bgkmap/office/ingest", "ingest"), Some(("office", "")));
        assert_eq!(parse_key("bgkmap/office/query/points", "query"), Some(("office", "points")));
        assert_eq!(parse_key("bgkmap/*/query/points", "query"), None);
        assert_eq!(parse_key("bgkmap/office/ingestx", "ingest"), None);
        assert_eq!(parse_key("other/office/ingest", "ingest"), None);
    }
}
