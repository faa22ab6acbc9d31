//! The zenoh side of a ROS 2 bridge: subscriptions to the cloud topic and to the pose source
//! (rmw_zenoh keys, any type hash), one worker thread that feeds [`RosBridge`] in arrival order
//! and hands its scans to the service.

use super::ZenohError;
use super::config::{RosPose, RosTopicConfig};
use super::ingest::IngestContext;
use super::ros_bridge::{Incoming, Outcome, RosBridge};
use crate::io::ros2::keys::{POINT_CLOUD2, POSE_STAMPED, TF_MESSAGE, topic_key};
use std::sync::Arc;
use std::sync::mpsc::SyncSender;
use zenoh::pubsub::Subscriber;

/// Messages waiting for the bridge's worker before the subscriptions block.
const ROS_CHANNEL: usize = 64;

/// How a subscription wraps its payloads for the bridge.
type Wrap = fn(Vec<u8>) -> Incoming;

/// The subscriptions of one bridge: (key, how to wrap the payload).
fn subscriptions(cfg: &RosTopicConfig) -> Result<Vec<(String, Wrap)>, ZenohError> {
    let key = |explicit: &Option<String>, topic: &str, type_name: &str| {
        explicit
            .clone()
            .or_else(|| topic_key(cfg.domain_id, topic, type_name))
            .ok_or_else(|| ZenohError::Config(format!("{topic:?} is not a ROS topic name")))
    };
    let mut subs: Vec<(String, Wrap)> =
        vec![(key(&cfg.cloud_key, &cfg.cloud_topic, POINT_CLOUD2)?, Incoming::Cloud)];
    match cfg.pose {
        RosPose::Identity => {}
        RosPose::Topic => {
            let topic = cfg.pose_topic.as_deref().unwrap_or_default();
            subs.push((key(&cfg.pose_key, topic, POSE_STAMPED)?, Incoming::Pose));
        }
        RosPose::Tf => {
            subs.push((key(&None, "/tf", TF_MESSAGE)?, |payload| Incoming::Tf { payload, is_static: false }));
            subs.push((key(&None, "/tf_static", TF_MESSAGE)?, |payload| Incoming::Tf {
                payload,
                is_static: true,
            }));
        }
    }
    Ok(subs)
}

async fn subscribe(
    session: &zenoh::Session,
    key: &str,
    wrap: Wrap,
    tx: SyncSender<Incoming>,
) -> Result<Subscriber<()>, ZenohError> {
    session
        .declare_subscriber(key)
        .callback(move |sample| {
            let _ = tx.send(wrap(sample.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(|e| ZenohError::declare(key, e))
}

/// Declares the bridge's subscriptions and starts its worker, which ends once they are gone and
/// their channel is drained (refusing the clouds still waiting for a pose).
pub async fn spawn_bridge(
    session: &zenoh::Session,
    ctx: Arc<IngestContext>,
    cfg: &RosTopicConfig,
    index: usize,
) -> Result<(Vec<Subscriber<()>>, std::thread::JoinHandle<()>), ZenohError> {
    let (tx, rx) = std::sync::mpsc::sync_channel(ROS_CHANNEL);
    let mut subs = Vec::new();
    let mut keys = Vec::new();
    for (key, wrap) in subscriptions(cfg)? {
        subs.push(subscribe(session, &key, wrap, tx.clone()).await?);
        keys.push(key);
    }
    drop(tx);
    let (map, source) = (cfg.map.clone(), cfg.source_name().to_string());
    eprintln!("bgkmap: zenoh: ROS 2 point clouds of {source:?} into map {map:?} from {}", keys.join(", "));
    let mut bridge = RosBridge::new(cfg);
    let apply = move |o: Outcome| match o {
        Outcome::Scan(scan) => ctx.submit(&map, scan),
        Outcome::Reject { kind, reason } => ctx.reject(&map, &source, kind, &reason),
        Outcome::Fault { kind, reason } => ctx.log_once(&map, &source, kind, &reason),
    };
    let worker = std::thread::Builder::new()
        .name(format!("bgkmap-ros-{index}"))
        .spawn(move || {
            while let Ok(msg) = rx.recv() {
                bridge.handle(msg).into_iter().for_each(&apply);
            }
            bridge.finish().into_iter().for_each(&apply);
        })
        .map_err(|e| ZenohError::Zenoh(format!("starting the ROS 2 bridge worker: {e}")))?;
    Ok((subs, worker))
}
