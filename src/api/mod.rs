//! Network transports: thin adapters from wire types to [`crate::service::MapService`] calls.
//!
//! Each handler validates and converts its request (errors name the field), calls one service
//! method, and converts the answer back. No domain logic lives here; transports never call each
//! other. [`status`] maps every service error to one gRPC code and one HTTP status.

pub mod pb {
    //! Types generated from `proto/bgkmap/v1/bgkmap.proto`.
    #![allow(missing_debug_implementations, clippy::all)]
    tonic::include_proto!("bgkmap.v1");

    /// The encoded file descriptor set, for gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("bgkmap_descriptor");
}

pub mod calls;
pub mod codec;
pub mod grpc;
mod grpc_ops;
pub use grpc_ops::STREAM_WINDOW;
pub mod http;
mod http_ops;
pub mod status;
pub mod viewer;
pub mod watch;
mod wire;
pub mod zenoh_transport;

impl pb::Scan {
    /// A world-frame scan seen from `origin_world` (identity rotation), points packed as
    /// little-endian f32 — what the CLI's clients send.
    pub fn world(source: &str, seq: u64, origin_world: [f64; 3], points_world: &[[f32; 3]]) -> Self {
        Self {
            source: source.into(),
            seq,
            world_from_sensor: Some(pb::Pose {
                translation: origin_world.to_vec(),
                rotation: vec![1.0, 0.0, 0.0, 0.0],
            }),
            frame: pb::Frame::World as i32,
            xyz_f32: pack_xyz(points_world),
            max_range: None,
            stamp_nanos: None,
        }
    }
}

/// Points as little-endian f32 triplets (the wire layout of `xyz_f32`).
pub fn pack_xyz(points: &[[f32; 3]]) -> Vec<u8> {
    points.iter().flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes())).collect()
}
