//! Block evidence ⇄ bytes (encodings 1 and 2, documented in the parent module).

use crate::core::key::BLOCK_CELLS;
use crate::core::{block::BlockEvidence, posterior::Evidence};

/// Both sums per present cell.
const ENCODING_BOTH: u8 = 1;
/// `B` alone per present cell: every `A` of the block is 0.
const ENCODING_FREE: u8 = 2;
const BITMAP_BYTES: usize = BLOCK_CELLS / 8;

/// Appends the encoding of `block` to `out`: `2` when no cell has hit mass, else `1` (the bytes
/// depend on the cells alone, not on the block's layout).
pub fn encode_block(block: &BlockEvidence, out: &mut Vec<u8>) {
    let free_only = !block.is_wide() || block.cells().all(|e| e.a == 0);
    out.push(if free_only { ENCODING_FREE } else { ENCODING_BOTH });
    let start = out.len();
    out.resize(start + BITMAP_BYTES, 0);
    for (i, Evidence { a, b }) in block.cells().enumerate() {
        if a != 0 || b != 0 {
            out[start + i / 8] |= 1 << (i % 8);
            if !free_only {
                put_varint(out, zigzag(a));
            }
            put_varint(out, zigzag(b));
        }
    }
}

/// Decodes a block (narrow whenever no cell has hit mass); the error says what is wrong.
pub fn decode_block(data: &[u8]) -> Result<Box<BlockEvidence>, String> {
    let (&enc, rest) = data.split_first().ok_or("empty block data")?;
    if enc != ENCODING_BOTH && enc != ENCODING_FREE {
        return Err(format!("unknown block encoding {enc}"));
    }
    if rest.len() < BITMAP_BYTES {
        return Err("block data shorter than its bitmap".into());
    }
    let (bitmap, mut payload) = rest.split_at(BITMAP_BYTES);
    let mut block = if enc == ENCODING_FREE { BlockEvidence::zeroed() } else { BlockEvidence::zeroed_wide() };
    for i in 0..BLOCK_CELLS {
        if bitmap[i / 8] & (1 << (i % 8)) != 0 {
            let a = if enc == ENCODING_FREE { 0 } else { unzigzag(get_varint(&mut payload)?) };
            let e = Evidence { a, b: unzigzag(get_varint(&mut payload)?) };
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
