//! The protobuf layer shared by the two protobuf transports, gRPC and zenoh; not a transport
//! itself: the generated types ([`pb`]), their codec ([`codec`], with the hand-written bytes of
//! the point-query answer in `wire`), the conversions between wire and service types
//! ([`convert`], whose errors name the proto field), the calls both transports answer
//! identically by construction ([`calls`]), and the updates as protobuf messages ([`updates`]).
//!
//! It may depend on the service, `offload` and `status`; never on a transport.

pub mod calls;
pub mod codec;
pub mod convert;
pub mod updates;
mod wire;

pub mod pb {
    //! Types generated from `proto/bgkmap/v1/bgkmap.proto`.
    #![allow(missing_debug_implementations, clippy::all)]
    tonic::include_proto!("bgkmap.v1");

    /// The encoded file descriptor set, for gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("bgkmap_descriptor");
}

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
