//! Block evidence ⇄ bytes (encoding 1, documented in the parent module).

use crate::core::evidence::{BlockEvidence, Evidence};
use crate::core::key::BLOCK_CELLS;

const ENCODING: u8 = 1;
const BITMAP_BYTES: usize = BLOCK_CELLS / 8;

/// Appends the encoding of `block` to `out`.
pub fn encode_block(block: &BlockEvidence, out: &mut Vec<u8>) {
    out.push(ENCODING);
    let start = out.len();
    out.resize(start + BITMAP_BYTES, 0);
    for (i, Evidence { a, b }) in block.cells().enumerate() {
        if a != 0 || b != 0 {
            out[start + i / 8] |= 1 << (i % 8);
            put_varint(out, zigzag(a));
            put_varint(out, zigzag(b));
        }
    }
}

/// Decodes a block; the error says what is wrong.
pub fn decode_block(data: &[u8]) -> Result<Box<BlockEvidence>, String> {
    let (&enc, rest) = data.split_first().ok_or("empty block data")?;
    if enc != ENCODING {
        return Err(format!("unknown block encoding {enc}"));
    }
    if rest.len() < BITMAP_BYTES {
        return Err("block data shorter than its bitmap".into());
    }
    let (bitmap, mut payload) = rest.split_at(BITMAP_BYTES);
    let mut block = BlockEvidence::zeroed_wide();
    for i in 0..BLOCK_CELLS {
        if bitmap[i / 8] & (1 << (i % 8)) != 0 {
            let e =
                Evidence { a: unzigzag(get_varint(&mut payload)?), b: unzigzag(get_varint(&mut payload)?) };
            block.set(i, e);
            if e.is_empty() {
                return Err(format!("cell {i} is marked present but holds no evidence"));
            }
        }
    }
    if !payload.is_empty() {
        return Err(format!("{} trailing bytes after the last cell", payload.len()));
    }
    // Narrow when no cell has hit mass: the layout a map would have built (see `BlockEvidence`).
    Ok(BlockEvidence::narrowed(block))
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    ((v >> 1) as i64) ^ -((v & 1) as i64)
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn get_varint(buf: &mut &[u8]) -> Result<u64, String> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let (&byte, rest) = buf.split_first().ok_or("block data truncated inside a varint")?;
        *buf = rest;
        if shift == 63 && byte > 1 {
            return Err("varint overflows 64 bits".into());
        }
        v |= u64::from(byte & 0x7f) << shift;
        if byte & 0x80 == 0 {
            return Ok(v);
        }
    }
    Err("varint longer than 10 bytes".into())
}
