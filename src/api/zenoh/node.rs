//! The zenoh session of the server: opened from [`ZenohConfig`], carrying the scan subscriber,
//! the ingest and query queryables and the ROS 2 bridges, and closed after they drained.

use super::config::{ZenohConfig, ZenohMode};
use super::ingest::{IngestContext, spawn_scan_worker};
use super::updates::Publishers;
use super::{ZenohError, queries, ros, updates};
use crate::api::proto::calls::ProtoCalls;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;
use zenoh::pubsub::Subscriber;
use zenoh::query::Queryable;

/// How long shutdown waits for queries in flight (acknowledged ingest waits for its scan).
const DRAIN_QUERIES: Duration = Duration::from_secs(30);
/// How long shutdown waits for the updates publishers to put what the maps hold for them.
const DRAIN_PUBLISHERS: Duration = Duration::from_secs(5);

/// A running zenoh transport.
pub struct ZenohTransport {
    session: zenoh::Session,
    locators: Vec<String>,
    subscribers: Vec<Subscriber<()>>,
    queryables: Vec<Queryable<()>>,
    workers: Vec<std::thread::JoinHandle<()>>,
    in_flight: Arc<AtomicUsize>,
    ingest: Arc<IngestContext>,
    publishers: Arc<Publishers>,
}

impl std::fmt::Debug for ZenohTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohTransport").field("locators", &self.locators).finish_non_exhaustive()
    }
}

/// The zenoh configuration of a session from ours: mode, endpoints, multicast scouting.
fn session_config(c: &ZenohConfig) -> Result<zenoh::Config, ZenohError> {
    let json = |v: &[String]| serde_json::to_string(v).unwrap_or_else(|_| "[]".into());
    let mut z = zenoh::Config::default();
    let set = |z: &mut zenoh::Config, key: &str, value: String| {
        z.insert_json5(key, &value).map_err(|e| ZenohError::Config(format!("zenoh {key} = {value}: {e}")))
    };
    set(&mut z, "mode", format!("\"{}\"", c.mode.as_str()))?;
    set(&mut z, "scouting/multicast/enabled", c.multicast_scouting.to_string())?;
    set(&mut z, "connect/endpoints", json(&c.connect))?;
    if c.mode == ZenohMode::Peer {
        set(&mut z, "listen/endpoints", json(&c.listen))?;
    }
    Ok(z)
}

impl ZenohTransport {
    /// Opens the session and declares everything; must run inside the server's tokio runtime
    /// (query handlers are spawned on it).
    pub async fn start(calls: ProtoCalls, config: &ZenohConfig) -> Result<Self, ZenohError> {
        config.validate().map_err(ZenohError::Config)?;
        let session = zenoh::open(session_config(config)?).await.map_err(ZenohError::open)?;
        let locators = session.info().locators().await.iter().map(ToString::to_string).collect();
        let runtime = tokio::runtime::Handle::current();
        let publishers = Publishers::start(calls.service(), &session, &runtime);
        let ingest = Arc::new(IngestContext::new(calls));
        let in_flight = Arc::new(AtomicUsize::new(0));
        let mut me = Self {
            session,
            locators,
            subscribers: Vec::new(),
            queryables: Vec::new(),
            workers: Vec::new(),
            in_flight,
            ingest,
            publishers,
        };
        let (sub, worker) = spawn_scan_worker(&me.session, me.ingest.clone()).await?;
        me.subscribers.push(sub);
        me.workers.push(worker);
        let flight = queries::InFlight::new(me.in_flight.clone(), runtime);
        me.queryables.extend(queries::declare(&me.session, me.ingest.clone(), flight).await?);
        for (i, topic) in config.ros.iter().enumerate() {
            let (subs, worker) = ros::spawn_bridge(&me.session, me.ingest.clone(), topic, i).await?;
            me.subscribers.extend(subs);
            me.workers.push(worker);
        }
        Ok(me)
    }

    /// The locators the session listens on (`tcp/127.0.0.1:7450`), with bound ports.
    pub fn locators(&self) -> &[String] {
        &self.locators
    }

    /// The session (to publish or query from the same process).
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// Publishes one change of `map` on `bgkmap/<map>/updates` as the transport does for every
    /// change of its maps: `payload` is the encoded `MapUpdate`, the attachment the new map
    /// version as 8 little-endian bytes, so a subscriber can order and gap-check changes
    /// without decoding them.
    pub async fn publish_update(&self, map: &str, version: u64, payload: Vec<u8>) -> Result<(), ZenohError> {
        // The transport's own maps are valid names already; a caller's may not be.
        crate::service::validate_map_name(map).map_err(|e| ZenohError::Config(e.to_string()))?;
        updates::put(&self.session, map, version, payload).await
    }

    /// Stops taking scans and queries, lets the workers hand what they received to the service,
    /// waits (bounded) for queries in flight, and closes the session. The service itself is
    /// drained by its owner afterwards.
    pub async fn shutdown(self) {
        let Self { session, subscribers, queryables, workers, in_flight, publishers, .. } = self;
        for s in subscribers {
            let _ = s.undeclare().await;
        }
        for q in queryables {
            let _ = q.undeclare().await;
        }
        let deadline = tokio::time::Instant::now() + DRAIN_QUERIES;
        while in_flight.load(Ordering::Acquire) > 0 && tokio::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        // The publishers end once the service has closed its updates (the server does that first).
        publishers.finish(DRAIN_PUBLISHERS).await;
        // Closing drops every callback, so the workers' channels disconnect once drained.
        let _ = session.close().await;
        let _ = tokio::task::spawn_blocking(move || {
            for w in workers {
                let _ = w.join();
            }
        })
        .await;
    }
}
