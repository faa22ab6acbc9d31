//! Protobuf encoding and decoding of the point-query answer, written out by hand for speed.
//!
//! A 100k-point answer is 200k doubles and 400k varints. prost writes them one element at a
//! time through `BufMut` (a capacity check and a length update per 8-byte double) and measured
//! a third of a gRPC point query's time; here the doubles are copied in blocks and the varints
//! written into a stack buffer. The bytes are exactly prost's (fields in tag order, repeated
//! fields packed, nothing for empty fields and a zero version), which the tests check.
//!
//! Decoding takes the fast path only for what this encoder (or any proto3 encoder) writes:
//! the five known fields, packed or not. Anything else — unknown fields, malformed varints, a
//! truncated message — goes to prost, so errors and unknown-field handling are prost's.

use super::pb;
use prost::bytes::BufMut;
use prost::encoding::{
    WireType, decode_varint, encode_key, encode_varint, encoded_len_varint, key_len, uint64,
};

const VARINT: u64 = WireType::Varint as u64;
const FIXED64: u64 = WireType::SixtyFourBit as u64;
const LEN: u64 = WireType::LengthDelimited as u64;

#[inline(always)]
fn zigzag(v: i32) -> u64 {
    u64::from(((v << 1) ^ (v >> 31)) as u32)
}

#[inline(always)]
fn unzigzag(v: u64) -> i32 {
    let v = v as u32;
    (v >> 1) as i32 ^ -((v & 1) as i32)
}

/// An `int32`/enum value as prost writes it: sign-extended to 64 bits.
#[inline(always)]
fn enum_varint(v: i32) -> u64 {
    i64::from(v) as u64
}

/// Bytes of a packed field whose body is `body` bytes (nothing when empty).
fn packed_len(tag: u32, body: usize) -> usize {
    if body == 0 { 0 } else { key_len(tag) + encoded_len_varint(body as u64) + body }
}

/// `encoded_len_varint` as a sum of comparisons, which vectorises over a column.
#[inline(always)]
fn varint_len_by_steps(v: u64) -> usize {
    1 + (1..10).map(|k| usize::from(v >> (7 * k) != 0)).sum::<usize>()
}

fn state_body(r: &pb::QueryPointsResponse) -> usize {
    r.state.iter().map(|&v| varint_len_by_steps(enum_varint(v))).sum()
}

fn cell_body(r: &pb::QueryPointsResponse) -> usize {
    // Zigzagged i32 fit 32 bits: at most 5 varint bytes.
    r.cell.iter().map(|&v| 1 + (1..5).map(|k| usize::from(zigzag(v) >> (7 * k) != 0)).sum::<usize>()).sum()
}

/// The sizes of a point-query answer, counted once for both reserving and writing it.
#[derive(Debug, Clone, Copy)]
pub struct PointsLen {
    /// Bytes of the packed `state` and `cell` bodies.
    state: usize,
    cell: usize,
    /// The whole message (equal to prost's `encoded_len`).
    pub total: usize,
}

/// Measures a point-query answer.
pub fn points_response_len(r: &pb::QueryPointsResponse) -> PointsLen {
    let (state, cell) = (state_body(r), cell_body(r));
    let total = packed_len(1, 8 * r.probability.len())
        + packed_len(2, 8 * r.variance.len())
        + packed_len(3, state)
        + packed_len(4, cell)
        + if r.version == 0 { 0 } else { uint64::encoded_len(5, &r.version) };
    PointsLen { state, cell, total }
}

/// Writes varints through a stack buffer, handing it to `buf` in large slices.
struct Varints<'a, B: BufMut> {
    buf: &'a mut B,
    tmp: [u8; 4096],
    used: usize,
}

impl<'a, B: BufMut> Varints<'a, B> {
    fn new(buf: &'a mut B) -> Self {
        Self { buf, tmp: [0; 4096], used: 0 }
    }

    #[inline(always)]
    fn put(&mut self, mut v: u64) {
        if self.used > self.tmp.len() - 10 {
            self.flush();
        }
        while v >= 0x80 {
            self.tmp[self.used] = v as u8 | 0x80;
            v >>= 7;
            self.used += 1;
        }
        self.tmp[self.used] = v as u8;
        self.used += 1;
    }

    fn flush(&mut self) {
        self.buf.put_slice(&self.tmp[..self.used]);
        self.used = 0;
    }
}

/// The key and length of a packed field.
fn put_packed_head<B: BufMut>(buf: &mut B, tag: u32, body: usize) {
    encode_key(tag, WireType::LengthDelimited, buf);
    encode_varint(body as u64, buf);
}

fn put_doubles<B: BufMut>(buf: &mut B, tag: u32, values: &[f64]) {
    if values.is_empty() {
        return;
    }
    put_packed_head(buf, tag, 8 * values.len());
    let mut tmp = [0u8; 4096];
    for chunk in values.chunks(tmp.len() / 8) {
        for (out, v) in tmp.chunks_exact_mut(8).zip(chunk) {
            out.copy_from_slice(&v.to_le_bytes());
        }
        buf.put_slice(&tmp[..8 * chunk.len()]);
    }
}

fn put_varints<B: BufMut>(buf: &mut B, tag: u32, body: usize, values: impl Iterator<Item = u64>) {
    if body == 0 {
        return;
    }
    put_packed_head(buf, tag, body);
    let mut w = Varints::new(buf);
    values.for_each(|v| w.put(v));
    w.flush();
}

/// Encodes a point-query answer (prost's bytes); `len` is its [`points_response_len`].
pub fn encode_points_response<B: BufMut>(r: &pb::QueryPointsResponse, len: &PointsLen, buf: &mut B) {
    put_doubles(buf, 1, &r.probability);
    put_doubles(buf, 2, &r.variance);
    put_varints(buf, 3, len.state, r.state.iter().map(|&v| enum_varint(v)));
    put_varints(buf, 4, len.cell, r.cell.iter().map(|&v| zigzag(v)));
    if r.version != 0 {
        uint64::encode(5, &r.version, buf);
    }
}

/// A cursor over the message bytes; every read is `None` where prost would have to judge.
struct Reader<'a> {
    bytes: &'a [u8],
}

impl<'a> Reader<'a> {
    /// A varint read by prost's own reader (so what counts as malformed is prost's).
    #[inline(always)]
    fn varint(&mut self) -> Option<u64> {
        decode_varint(&mut self.bytes).ok()
    }

    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let (head, rest) = (self.bytes.get(..n)?, self.bytes.get(n..)?);
        self.bytes = rest;
        Some(head)
    }

    fn len_delimited(&mut self) -> Option<&'a [u8]> {
        let n = usize::try_from(self.varint()?).ok()?;
        self.take(n)
    }
}

fn doubles(r: &mut Reader<'_>, wire_type: u64, out: &mut Vec<f64>) -> Option<()> {
    let body = match wire_type {
        LEN => r.len_delimited()?,
        FIXED64 => r.take(8)?,
        _ => return None,
    };
    if body.len() % 8 != 0 {
        return None;
    }
    out.extend(body.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().unwrap_or_default())));
    Some(())
}

fn varints(r: &mut Reader<'_>, wire_type: u64, mut push: impl FnMut(u64)) -> Option<()> {
    match wire_type {
        LEN => {
            let mut body = Reader { bytes: r.len_delimited()? };
            while !body.bytes.is_empty() {
                push(body.varint()?);
            }
        }
        VARINT => push(r.varint()?),
        _ => return None,
    }
    Some(())
}

/// Decodes a point-query answer, or `None` when the bytes hold anything but its five fields
/// well formed (the caller then lets prost decode them, and report what is wrong).
pub fn decode_points_response(bytes: &[u8]) -> Option<pb::QueryPointsResponse> {
    let mut r = Reader { bytes };
    let mut out = pb::QueryPointsResponse::default();
    while !r.bytes.is_empty() {
        let key = r.varint()?;
        let (field, wire_type) = (key >> 3, key & 7);
        match field {
            1 => doubles(&mut r, wire_type, &mut out.probability)?,
            2 => doubles(&mut r, wire_type, &mut out.variance)?,
            // prost reads an int32 by truncating the varint.
            3 => varints(&mut r, wire_type, |v| out.state.push(v as i32))?,
            4 => varints(&mut r, wire_type, |v| out.cell.push(unzigzag(v)))?,
            5 if wire_type == VARINT => out.version = r.varint()?,
            _ => return None,
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use prost::Message;

    fn response() -> impl Strategy<Value = pb::QueryPointsResponse> {
        let double = prop_oneof![any::<f64>(), Just(0.5), Just(-0.0), Just(f64::NAN), Just(f64::INFINITY)];
        let int = prop_oneof![any::<i32>(), 0..3i32, -3..0i32, Just(i32::MIN), Just(i32::MAX)];
        (
            prop::collection::vec(double.clone(), 0..40),
            prop::collection::vec(double, 0..40),
            prop::collection::vec(int.clone(), 0..40),
            prop::collection::vec(int, 0..120),
            prop_oneof![Just(0u64), any::<u64>()],
        )
            .prop_map(|(probability, variance, state, cell, version)| pb::QueryPointsResponse {
                probability,
                variance,
                state,
                cell,
                version,
            })
    }

    /// Compares with NaN equal to itself (bit patterns).
    fn same(a: &pb::QueryPointsResponse, b: &pb::QueryPointsResponse) -> bool {
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        bits(&a.probability) == bits(&b.probability)
            && bits(&a.variance) == bits(&b.variance)
            && a.state == b.state
            && a.cell == b.cell
            && a.version == b.version
    }

    proptest! {
        #[test]
        fn encoding_is_prosts(r in response()) {
            let mut fast = Vec::new();
            let len = points_response_len(&r);
            encode_points_response(&r, &len, &mut fast);
            prop_assert_eq!(&fast, &r.encode_to_vec());
            prop_assert_eq!(len.total, r.encoded_len());
            for v in r.cell.iter().map(|&c| zigzag(c)).chain(r.state.iter().map(|&c| enum_varint(c))) {
                prop_assert_eq!(varint_len_by_steps(v), encoded_len_varint(v));
            }
            let back = decode_points_response(&fast).expect("own encoding takes the fast path");
            prop_assert!(same(&back, &r));
        }

        /// Unpacked repeated fields, fields out of order and repeated fields split in two are
        /// all valid encodings: the fast path reads them as prost does.
        #[test]
        fn other_valid_encodings_decode_as_prost_does(r in response(), split in 0usize..40) {
            let mut bytes = Vec::new();
            for v in &r.variance {
                prost::encoding::double::encode(2, v, &mut bytes);
            }
            let (a, b) = r.probability.split_at(split.min(r.probability.len()));
            prost::encoding::double::encode_packed(1, a, &mut bytes);
            prost::encoding::sint32::encode_packed(4, &r.cell, &mut bytes);
            for v in &r.state {
                prost::encoding::int32::encode(3, v, &mut bytes);
            }
            prost::encoding::double::encode_packed(1, b, &mut bytes);
            prost::encoding::uint64::encode(5, &r.version, &mut bytes);
            let want = pb::QueryPointsResponse::decode(&*bytes).unwrap();
            let got = decode_points_response(&bytes).expect("valid and known fields only");
            prop_assert!(same(&got, &want));
        }

        /// Whatever the bytes, the fast path either declines or agrees with prost.
        #[test]
        fn arbitrary_bytes_decline_or_agree(r in response(), cut in any::<prop::sample::Index>(),
                                            noise in prop::collection::vec(any::<u8>(), 0..16)) {
            let mut bytes = r.encode_to_vec();
            bytes.truncate(cut.index(bytes.len() + 1));
            bytes.extend(noise);
            if let Some(fast) = decode_points_response(&bytes) {
                let slow = pb::QueryPointsResponse::decode(&*bytes);
                prop_assert!(slow.as_ref().is_ok_and(|s| same(s, &fast)), "fast {fast:?}, prost {slow:?}");
            }
        }
    }

    #[test]
    fn unknown_fields_and_bad_varints_go_to_prost() {
        let mut unknown = pb::QueryPointsResponse { version: 3, ..Default::default() }.encode_to_vec();
        prost::encoding::uint64::encode(9, &1, &mut unknown);
        assert!(decode_points_response(&unknown).is_none());
        // An eleven-byte varint.
        assert!(
            decode_points_response(&[0x28, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01])
                .is_none()
        );
        // A packed double field whose length is not a multiple of 8.
        assert!(decode_points_response(&[0x0a, 0x03, 1, 2, 3]).is_none());
    }
}
