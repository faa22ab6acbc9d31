//! The protobuf codec of the generated gRPC code: prost's, except that
//! - a message that does not decode is the caller's fault — `INVALID_ARGUMENT` naming the
//!   problem — not `INTERNAL`;
//! - a message over the server's limit ([`set_max_message_bytes`]) is `RESOURCE_EXHAUSTED`, as
//!   gRPC specifies (tonic's own check, which says `OUT_OF_RANGE`, is set 4× higher as a backstop
//!   against unbounded buffering);
//! - the point-query answer, the one bulk message, is encoded and decoded by the private
//!   `proto::wire` module (prost's bytes, written in blocks); [`encoded_len`], [`encode_to_vec`]
//!   and [`decode`] use it too, for transports other than gRPC.

use super::{pb, wire};
use std::any::{Any, TypeId};
use std::marker::PhantomData;
use std::sync::atomic::{AtomicUsize, Ordering};

static MAX_MESSAGE_BYTES: AtomicUsize = AtomicUsize::new(usize::MAX);

/// Sets the largest message the decoder accepts (process-wide; the server sets it once).
pub fn set_max_message_bytes(limit: usize) {
    MAX_MESSAGE_BYTES.store(limit, Ordering::Relaxed);
}
use tonic::Status;
use tonic::codec::{BufferSettings, Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
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
    type Encoder = StrictEncoder<T>;
    type Decoder = StrictDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        StrictEncoder(ProstEncoder::default())
    }

    fn decoder(&mut self) -> Self::Decoder {
        StrictDecoder(ProstDecoder::default())
    }
}

/// Encodes like prost.
#[derive(Debug)]
pub struct StrictEncoder<T>(ProstEncoder<T>);

impl<T: prost::Message + 'static> Encoder for StrictEncoder<T> {
    type Item = T;
    type Error = Status;

    fn encode(&mut self, item: T, buf: &mut EncodeBuf<'_>) -> Result<(), Status> {
        let Some(r) = as_points(&item) else { return self.0.encode(item, buf) };
        let len = wire::points_response_len(r);
        buf.reserve(len.total);
        wire::encode_points_response(r, &len, buf);
        Ok(())
    }

    fn buffer_settings(&self) -> BufferSettings {
        self.0.buffer_settings()
    }
}

/// `msg` if it is the point-query answer, the one message `proto::wire` handles.
fn as_points<M: 'static>(msg: &M) -> Option<&pb::QueryPointsResponse> {
    (msg as &dyn Any).downcast_ref()
}

/// The encoded length of `msg`.
pub fn encoded_len<M: prost::Message + 'static>(msg: &M) -> usize {
    as_points(msg).map_or_else(|| msg.encoded_len(), |r| wire::points_response_len(r).total)
}

/// `msg`'s bytes.
pub fn encode_to_vec<M: prost::Message + 'static>(msg: &M) -> Vec<u8> {
    let Some(r) = as_points(msg) else { return msg.encode_to_vec() };
    let len = wire::points_response_len(r);
    let mut out = Vec::with_capacity(len.total);
    wire::encode_points_response(r, &len, &mut out);
    out
}

/// Decodes `bytes` as prost does.
pub fn decode<M: prost::Message + Default + 'static>(bytes: &[u8]) -> Result<M, prost::DecodeError> {
    if TypeId::of::<M>() == TypeId::of::<pb::QueryPointsResponse>() {
        let mut fast = wire::decode_points_response(bytes);
        if let Some(m) = (&mut fast as &mut dyn Any).downcast_mut::<Option<M>>().and_then(Option::take) {
            return Ok(m);
        }
    }
    M::decode(bytes)
}

/// Decodes like prost; a decode failure becomes `INVALID_ARGUMENT`.
#[derive(Debug)]
pub struct StrictDecoder<U>(ProstDecoder<U>);

impl<U: prost::Message + Default + 'static> Decoder for StrictDecoder<U> {
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
        let malformed =
            |m: &dyn std::fmt::Display| Status::invalid_argument(format!("malformed protobuf message: {m}"));
        // A message in one contiguous chunk (the usual case) goes through `decode`.
        let bytes = prost::bytes::Buf::chunk(buf);
        if bytes.len() == len {
            let r = decode::<U>(bytes).map_err(|e| malformed(&e))?;
            prost::bytes::Buf::advance(buf, len);
            return Ok(Some(r));
        }
        self.0.decode(buf).map_err(|s| malformed(&s.message()))
    }

    fn buffer_settings(&self) -> BufferSettings {
        self.0.buffer_settings()
    }
}
