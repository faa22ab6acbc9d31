//! A reader for OMG CDR (XCDR1) as ROS 2 serialises messages: a 4-byte encapsulation header,
//! then the body, every primitive of size n aligned to a multiple of n counted from the first
//! byte after the header (docs/formats.md §5.2).
//!
//! Only what ROS messages need: fixed-size primitives, strings (`u32` length including the NUL)
//! and sequences (`u32` count). Every read is bounds-checked; a failure names the field it was
//! reading, so a bad message says where it went wrong.

use super::Ros2Error;

/// Encapsulation identifiers (bytes 0–1 of the header, big-endian).
const CDR_BE: [u8; 2] = [0x00, 0x00];
const CDR_LE: [u8; 2] = [0x00, 0x01];

/// Length of the encapsulation header.
pub const HEADER_LEN: usize = 4;

/// A cursor over the body of one CDR message.
#[derive(Debug, Clone)]
pub struct CdrReader<'a> {
    body: &'a [u8],
    pos: usize,
    little_endian: bool,
}

impl<'a> CdrReader<'a> {
    /// Checks the encapsulation header (plain CDR, either byte order) and starts at the body.
    pub fn new(payload: &'a [u8]) -> Result<Self, Ros2Error> {
        let Some((header, body)) = payload.split_first_chunk::<HEADER_LEN>() else {
            return Err(Ros2Error::Truncated { field: "encapsulation header".into(), at: 0 });
        };
        let little_endian = match [header[0], header[1]] {
            CDR_LE => true,
            CDR_BE => false,
            other => return Err(Ros2Error::Encapsulation(other)),
        };
        Ok(Self { body, pos: 0, little_endian })
    }

    /// Bytes of the body not read yet.
    pub fn remaining(&self) -> usize {
        self.body.len().saturating_sub(self.pos)
    }

    fn align(&mut self, n: usize) {
        self.pos = self.pos.next_multiple_of(n);
    }

    /// The next `n` bytes (no alignment).
    pub fn bytes(&mut self, n: usize, field: &str) -> Result<&'a [u8], Ros2Error> {
        let end = self.pos.checked_add(n).filter(|e| *e <= self.body.len());
        let Some(end) = end else {
            return Err(Ros2Error::Truncated { field: field.into(), at: self.pos });
        };
        let out = &self.body[self.pos..end];
        self.pos = end;
        Ok(out)
    }

    fn array<const N: usize>(&mut self, field: &str) -> Result<[u8; N], Ros2Error> {
        self.align(N);
        let b = self.bytes(N, field)?;
        let mut a = [0u8; N];
        a.copy_from_slice(b);
        if !self.little_endian {
            a.reverse();
        }
        Ok(a)
    }

    pub fn u8(&mut self, field: &str) -> Result<u8, Ros2Error> {
        Ok(self.bytes(1, field)?[0])
    }

    pub fn bool(&mut self, field: &str) -> Result<bool, Ros2Error> {
        match self.u8(field)? {
            0 => Ok(false),
            1 => Ok(true),
            v => Err(Ros2Error::Invalid { field: field.into(), reason: format!("bool byte {v}") }),
        }
    }

    pub fn u32(&mut self, field: &str) -> Result<u32, Ros2Error> {
        self.array::<4>(field).map(u32::from_le_bytes)
    }

    pub fn i32(&mut self, field: &str) -> Result<i32, Ros2Error> {
        self.array::<4>(field).map(i32::from_le_bytes)
    }

    pub fn f64(&mut self, field: &str) -> Result<f64, Ros2Error> {
        self.array::<8>(field).map(f64::from_le_bytes)
    }

    /// A string: `u32` length including the terminating NUL, the bytes, the NUL. UTF-8.
    pub fn string(&mut self, field: &str) -> Result<&'a str, Ros2Error> {
        let len = self.u32(field)? as usize;
        if len == 0 {
            // Some writers encode "" as a bare zero length; accept it.
            return Ok("");
        }
        let raw = self.bytes(len, field)?;
        let (text, nul) = raw.split_at(len - 1);
        if nul != [0] {
            return Err(Ros2Error::Invalid { field: field.into(), reason: "string without its NUL".into() });
        }
        std::str::from_utf8(text)
            .map_err(|_| Ros2Error::Invalid { field: field.into(), reason: "string is not UTF-8".into() })
    }

    /// A sequence length, checked against the bytes left (each element takes at least
    /// `min_element_bytes`), so a corrupt count cannot make the caller allocate wildly.
    pub fn sequence_len(&mut self, field: &str, min_element_bytes: usize) -> Result<usize, Ros2Error> {
        let at = self.pos;
        let n = self.u32(field)? as usize;
        if n.saturating_mul(min_element_bytes.max(1)) > self.remaining() {
            return Err(Ros2Error::Truncated { field: field.into(), at });
        }
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_counts_from_the_body_and_both_byte_orders_read() {
        // LE: u8 1, pad 3, u32 7, f64 at offset 8.
        let mut le = vec![0, 1, 0, 0, 1, 0xff, 0xff, 0xff, 7, 0, 0, 0];
        le.extend_from_slice(&2.5f64.to_le_bytes());
        let mut r = CdrReader::new(&le).unwrap();
        assert_eq!((r.u8("a").unwrap(), r.u32("b").unwrap(), r.f64("c").unwrap()), (1, 7, 2.5));
        assert_eq!(r.remaining(), 0);
        let mut be = vec![0, 0, 0, 0, 0, 0, 0, 7];
        be.extend_from_slice(&(-3i32).to_be_bytes());
        let mut r = CdrReader::new(&be).unwrap();
        assert_eq!((r.u32("a").unwrap(), r.i32("b").unwrap()), (7, -3));
    }

    #[test]
    fn strings_need_their_nul_and_reads_past_the_end_name_the_field() {
        let msg = [0, 1, 0, 0, 4, 0, 0, 0, b'm', b'a', b'p', 0, 1, 0, 0, 0, 0];
        let mut r = CdrReader::new(&msg).unwrap();
        assert_eq!(r.string("frame_id").unwrap(), "map");
        assert_eq!(r.string("empty").unwrap(), "");
        let e = r.u32("height").unwrap_err();
        assert_eq!(e, Ros2Error::Truncated { field: "height".into(), at: 16 });
        let no_nul = [0, 1, 0, 0, 3, 0, 0, 0, b'a', b'b', b'c'];
        assert!(matches!(CdrReader::new(&no_nul).unwrap().string("s"), Err(Ros2Error::Invalid { .. })));
    }

    #[test]
    fn only_plain_cdr_is_accepted() {
        assert_eq!(CdrReader::new(&[0, 3, 0, 0]).unwrap_err(), Ros2Error::Encapsulation([0, 3]));
        assert!(matches!(CdrReader::new(&[0, 1]), Err(Ros2Error::Truncated { .. })));
    }

    #[test]
    fn huge_sequence_counts_are_refused_before_allocating() {
        let msg = [0, 1, 0, 0, 0xff, 0xff, 0xff, 0x7f, 1, 2, 3];
        let mut r = CdrReader::new(&msg).unwrap();
        assert!(matches!(r.sequence_len("fields", 20), Err(Ros2Error::Truncated { .. })));
    }
}
