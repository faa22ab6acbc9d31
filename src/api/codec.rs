//! The protobuf codec of the generated gRPC code: prost's, except that
//! - a message that does not decode is the caller's fault — `INVALID_ARGUMENT` naming the
//!   problem — not `INTERNAL`;
//! - a message over the server's limit ([`set_max_message_bytes`]) is `RESOURCE_EXHAUSTED`, as
//!   gRPC specifies (tonic's own check, which says `OUT_OF_RANGE`, is set 4× higher as a backstop
//!   against unbounded buffering).

use std::marker::PhantomData;
use std::sync::atomic::{AtomicUsize, Ordering};

static MAX_MESSAGE_BYTES: AtomicUsize = AtomicUsize::new(usize::MAX);

/// Sets the largest message the decoder accepts (process-wide; the server sets it once).
pub fn set_max_message_bytes(limit: usize) {
    MAX_MESSAGE_BYTES.store(limit, Ordering::Relaxed);
}
use tonic::Status;
use tonic::codec::{BufferSettings, Codec, DecodeBuf, Decoder};
use tonic_prost::{ProstDecoder, ProstEncoder};

/// prost's codec with malformed input reported as `INVALID_ARGUMENT`.
#[derive(Debug, Clone)]
pub struct StrictCodec<T, U>(PhantomData<(T, U)>);

impl<T, U> Default for StrictCodec<T, U> {
    fn default() -> Self {
        Self(PhantomData)
    }
}

impl<T, U> Codec for StrictCodec<T, U>
where
    T: prost::Message + Send + 'static,
    U: prost::Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = StrictDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstEncoder::default()
    }

    fn decoder(&mut self) -> Self::Decoder {
        StrictDecoder(ProstDecoder::default())
    }
}

/// Decodes like prost; a decode failure becomes `INVALID_ARGUMENT`.
#[derive(Debug)]
pub struct StrictDecoder<U>(ProstDecoder<U>);

impl<U: prost::Message + Default> Decoder for StrictDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        let limit = MAX_MESSAGE_BYTES.load(Ordering::Relaxed);
        let len = prost::bytes::Buf::remaining(buf);
        if len > limit {
            return Err(Status::resource_exhausted(format!(
                "message of {len} bytes exceeds the limit of {limit} bytes (max_message_bytes)"
            )));
        }
        self.0
            .decode(buf)
            .map_err(|s| Status::invalid_argument(format!("malformed protobuf message: {}", s.message())))
    }

    fn buffer_settings(&self) -> BufferSettings {
        self.0.buffer_settings()
    }
}
