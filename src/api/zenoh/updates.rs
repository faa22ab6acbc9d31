//! The change stream on zenoh: every change of every map is put on `bgkmap/<map>/updates` as
//! the `bgkmap.v1.MapUpdate` gRPC `WatchUpdates` streams (the attachment is the new map version,
//! 8 little-endian bytes), and `bgkmap/<map>/updates/since` answers a `WatchUpdatesRequest`
//! (`since_version`, optional box) with the catch-up: every block changed after that version.
//!
//! A planner that starts late (or lost its session) declares its subscriber first, then asks
//! `updates/since` with the last version it holds, applies the catch-up and then every live
//! update whose version is above the catch-up's: it ends with the blocks of one that watched
//! from the start. A gap in the live versions (a put lost while the subscriber was away) is
//! mended the same way.
//!
//! One publishing task per map follows the map's updates ([`crate::service::MapService::watch`])
//! from the moment the transport starts, or from version 0 for a map created later (so the
//! scans it took before its task ran arrive as one catch-up message). A subscriber that falls
//! behind gets a `RESYNC` message, as on gRPC. The tasks end when the service closes the
//! maps' updates (shutdown).

use super::ZenohError;
use crate::api::proto::pb;
use crate::api::proto::updates::update_to_pb;
use crate::service::{MapService, Next, Subscription};
use prost::Message;
use std::sync::{Arc, Mutex, PoisonError};
use zenoh::bytes::Encoding;

/// Key of the change stream of `map`.
pub fn updates_key(map: &str) -> String {
    format!("bgkmap/{map}/updates")
}

/// Puts one change of `map` (a valid map name) on its updates key.
pub(super) async fn put(
    session: &zenoh::Session,
    map: &str,
    version: u64,
    payload: Vec<u8>,
) -> Result<(), ZenohError> {
    let key = updates_key(map);
    session
        .put(&key, payload)
        .encoding(Encoding::APPLICATION_PROTOBUF)
        .attachment(version.to_le_bytes().to_vec())
        .await
        .map_err(|e| ZenohError::Zenoh(format!("publishing on {key}: {e}")))
}

/// The publishing tasks of all maps.
#[derive(Debug)]
pub(super) struct Publishers {
    tasks: Mutex<Option<Vec<tokio::task::JoinHandle<()>>>>,
}

impl Publishers {
    /// Follows every map of `service`, those there now and those created later.
    pub(super) fn start(
        service: &Arc<MapService>,
        session: &zenoh::Session,
        runtime: &tokio::runtime::Handle,
    ) -> Arc<Self> {
        let me = Arc::new(Self { tasks: Mutex::new(Some(Vec::new())) });
        let follow = {
            let (me, weak, session, runtime) =
                (Arc::downgrade(&me), Arc::downgrade(service), session.clone(), runtime.clone());
            move |map: &str, since: Option<u64>| {
                let (Some(me), Some(service)) = (me.upgrade(), weak.upgrade()) else { return };
                let mut tasks = me.tasks.lock().unwrap_or_else(PoisonError::into_inner);
                // After shutdown, maps created meanwhile are not followed.
                let Some(tasks) = tasks.as_mut() else { return };
                match service.watch(map, since, None) {
                    Ok((first, sub)) => {
                        let resolution = match service.snapshot(map) {
                            Ok(s) => s.map.params().resolution_m,
                            Err(_) => return,
                        };
                        let first = (!first.blocks.is_empty() || first.version > first.from_version)
                            .then(|| update_to_pb(&first, resolution));
                        let task = publish(session.clone(), map.to_string(), resolution, first, sub);
                        tasks.push(runtime.spawn(task));
                    }
                    Err(e) => eprintln!("bgkmap: zenoh: not publishing the changes of map {map:?}: {e}"),
                }
            }
        };
        let created = follow.clone();
        let existing = service.on_map_created(move |map| created(map, Some(0)));
        for map in existing {
            follow(&map, None);
        }
        me
    }

    /// Waits for the tasks, which end once the service has closed its updates (at most `wait`;
    /// the rest are stopped); maps created from now on are not followed.
    pub(super) async fn finish(&self, wait: std::time::Duration) {
        let tasks = self.tasks.lock().unwrap_or_else(PoisonError::into_inner).take().unwrap_or_default();
        let deadline = tokio::time::Instant::now() + wait;
        for mut t in tasks {
            if tokio::time::timeout_at(deadline, &mut t).await.is_err() {
                t.abort();
            }
        }
    }
}

/// Puts `first` (if any) and then every update of `sub` until the service closes them.
async fn publish(
    session: zenoh::Session,
    map: String,
    resolution: f64,
    first: Option<pb::MapUpdate>,
    mut sub: Subscription,
) {
    let mut logged = false;
    let mut send = async |u: pb::MapUpdate| {
        if let Err(e) = put(&session, &map, u.version, u.encode_to_vec()).await
            && !std::mem::replace(&mut logged, true)
        {
            eprintln!("bgkmap: zenoh: {e} (further failures of this map are not logged)");
        }
    };
    if let Some(u) = first {
        send(u).await;
    }
    // Until the service closes the updates (shutdown).
    while let Next::Update(u) = std::future::poll_fn(|cx| sub.poll_next(cx)).await {
        send(update_to_pb(&u, resolution)).await;
    }
}
