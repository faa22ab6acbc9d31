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

pub mod codec;
pub mod grpc;
pub mod http;
pub mod status;
