//! zenoh transport: bgkmap as a zenoh citizen (feature `zenoh`).
//!
//! One session per server (peer or client, explicit TCP endpoints, multicast scouting off by
//! default). Key space, `<map>` a map name:
//!
//! | key | what | payload |
//! |---|---|---|
//! | `bgkmap/<map>/scans/<source>` | put a scan (no reply) | `bgkmap.v1.Scan` |
//! | `bgkmap/<map>/ingest` | query: a scan, answered once stored | `Scan` → `InsertScanResponse` |
//! | `bgkmap/<map>/query/points` | query | `QueryPointsRequest` → `QueryPointsResponse` |
//! | `bgkmap/<map>/query/box` | query | `QueryBoxRequest` → `QueryBoxResponse` |
//! | `bgkmap/<map>/query/rays` | query | `CastRaysRequest` → `CastRaysResponse` |
//! | `bgkmap/<map>/updates` | put per change of the map | `bgkmap.v1.MapUpdate`, attachment: version (u64 LE) |
//! | `bgkmap/<map>/updates/since` | query: the blocks changed since a version | `WatchUpdatesRequest` → `MapUpdate` |
//! | `<domain>/<topic>/sensor_msgs::msg::dds_::PointCloud2_/*` | ROS 2 clouds (rmw_zenoh) | CDR |
//!
//! Scans and queries go through the same [`crate::api::proto::calls`] as gRPC (never through
//! the gRPC transport itself), so validation, exactly-once `(source, seq)` and every answer are
//! gRPC's. A put that cannot be used is counted as rejected for its source and logged once
//! ([`ingest`]); queries answer errors with `reply_err` ([`queries`]). The updates (the change
//! stream): [`updates`]. ROS 2 clouds: [`ros_bridge`].
//!
//! [`config`] builds without zenoh; everything else needs the `zenoh` feature.

pub mod config;
#[cfg(feature = "zenoh")]
pub mod ingest;
#[cfg(feature = "zenoh")]
mod node;
#[cfg(feature = "zenoh")]
pub mod queries;
#[cfg(feature = "zenoh")]
mod ros;
#[cfg(feature = "zenoh")]
pub mod ros_bridge;
#[cfg(feature = "zenoh")]
pub mod updates;

pub use config::{RosPose, RosTopicConfig, ZenohConfig, ZenohMode};
#[cfg(feature = "zenoh")]
pub use node::ZenohTransport;
#[cfg(feature = "zenoh")]
pub use updates::updates_key;

/// Errors of the zenoh transport (start-up and publishing; per-message faults are counted and
/// logged where they happen).
#[derive(Debug, thiserror::Error)]
pub enum ZenohError {
    #[error("{0}")]
    Config(String),
    #[error("zenoh: {0}")]
    Zenoh(String),
}

impl ZenohError {
    #[cfg(feature = "zenoh")]
    fn open(e: zenoh::Error) -> Self {
        Self::Zenoh(format!("opening the session: {e}"))
    }

    #[cfg(feature = "zenoh")]
    fn declare(key: &str, e: zenoh::Error) -> Self {
        Self::Zenoh(format!("declaring {key}: {e}"))
    }
}
