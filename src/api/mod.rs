//! Network transports: thin adapters from wire types to [`crate::service::MapService`] calls.
//!
//! - [`grpc`]: `bgkmap.v1.MapService` over tonic (server and config, queries and export,
//!   streamed ingest, edits, the `WatchUpdates` stream), reflection and health;
//! - [`http`]: JSON over axum (router, state and errors, maps and scans, queries, edits, the
//!   updates as server-sent events, metrics) and the web viewer (its page and assets in
//!   `src/api/http/viewer/`);
//! - [`zenoh`]: scans, queries and the updates on a zenoh session, and ROS 2 point clouds.
//!
//! Beside them, three layers that are not transports: [`proto`] (the generated protobuf types,
//! their codec and conversions, and the protobuf calls gRPC and zenoh both answer), `offload`
//! (runs a service query inline or on tokio's blocking pool, as the query decides) and
//! [`status`] (the one mapping of service errors to gRPC codes and HTTP statuses).
//!
//! Each handler converts its request (errors name the field), calls one service function (for
//! reads, the front door [`crate::service::query`], which owns validation, limits and the
//! inline-or-blocking decision), and converts the answer back. No domain logic lives here.
//! Transports never import each other: what two of them share lives in `proto`, `offload`,
//! `status` or the service.

pub mod grpc;
pub mod http;
mod offload;
pub mod proto;
pub mod status;
pub mod zenoh;

pub use grpc::STREAM_WINDOW;
// The wire types and their codec are what the crate's clients (CLI, benches, tests) use.
pub use proto::{codec, pack_xyz, pb};
