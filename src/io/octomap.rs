//! OctoMap `.bt` (binary maximum-likelihood tree) reader and writer.
//!
//! This module owns the `.bt` text header and the 2-bits-per-child pre-order payload
//! (docs/formats.md §1), the conversion between OctoMap keys (0..65535) and bgkmap cell keys
//! (OctoMap key − 32768), and building a tree bottom-up from labelled cells with optional
//! liboctomap-style pruning. Reading validates strictly (first line, `res > 0`, payload length,
//! `size` = decoded nodes) and never panics; writing reproduces liboctomap's bytes for the given
//! leaves (`writeBinaryConst`; with [`BtTree::from_cells`] pruning, also `writeBinary`).

use crate::core::key::CellKey;

const TREE_DEPTH: u8 = 16;
const KEY_OFFSET: i32 = 32768;
const FIRST_LINE: &[u8] = b"# Octomap OcTree binary file";

/// One leaf of a `.bt` tree.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct BtLeaf {
    /// 1..=16; a leaf at depth d covers 2^(16−d) cells per axis.
    pub depth: u8,
    /// bgkmap key of the leaf's minimum cell.
    pub min_cell: CellKey,
    pub occupied: bool,
}

/// A decoded (or to-be-written) `.bt` tree.
#[derive(Debug, Clone, PartialEq)]
pub struct BtTree {
    pub resolution: f64,
    /// Leaves in pre-order (depth-first, children 0..7), which is Morton order of their corners.
    pub leaves: Vec<BtLeaf>,
    /// Inner nodes, root included.
    pub inner_nodes: usize,
}

/// Why a `.bt` file could not be read or a tree could not be built.
#[derive(Debug, thiserror::Error)]
pub enum BtError {
    #[error("BT header: first line must start with \"# Octomap OcTree binary file\"")]
    BadFirstLine,
    #[error("BT header: {0}")]
    Header(String),
    #[error("BT header: res must be a finite number > 0, got {0}")]
    BadResolution(f64),
    #[error(
        "BT payload truncated: inner node {node} needs 2 bytes at offset {offset}, payload has {len} bytes"
    )]
    Truncated { node: usize, offset: usize, len: usize },
    #[error("BT payload: inner node code below depth 16")]
    InnerAtMaxDepth,
    #[error("BT payload: inner node at depth {depth} has no children")]
    EmptyInner { depth: u8 },
    #[error("Tree size mismatch: header says {header}, decoded {decoded}")]
    SizeMismatch { header: u64, decoded: usize },
    #[error("cell key ({}, {}, {}) is outside OctoMap's key range -32768..=32767", .0.x, .0.y, .0.z)]
    KeyOutOfRange(CellKey),
}

impl BtTree {
    /// Inner nodes plus leaves: the header's `size`.
    pub fn node_count(&self) -> usize {
        self.inner_nodes + self.leaves.len()
    }

    pub fn occupied_leaves(&self) -> usize {
        self.leaves.iter().filter(|l| l.occupied).count()
    }

    /// Every cell (of edge `resolution`) covered by a leaf, with its label (true = occupied).
    /// A leaf at depth d covers 2^(16−d) cells per axis; leaves with a depth outside 1..=16
    /// yield nothing.
    pub fn cells(&self) -> impl Iterator<Item = (CellKey, bool)> + '_ {
        self.leaves.iter().flat_map(|l| {
            let side: u64 = if (1..=TREE_DEPTH).contains(&l.depth) { 1 << (TREE_DEPTH - l.depth) } else { 0 };
            (0..side * side * side).map(move |i| {
                let d = [i % side, (i / side) % side, i / (side * side)].map(|v| v as i32);
                let c = l.min_cell;
                (
                    CellKey::new(c.x.wrapping_add(d[0]), c.y.wrapping_add(d[1]), c.z.wrapping_add(d[2])),
                    l.occupied,
                )
            })
        })
    }

    /// Builds a tree from labelled cells (depth-16 leaves). With `prune`, 8 sibling leaves of the
    /// same class collapse into their parent, repeatedly up to depth 1 (the root is never a
    /// leaf), as liboctomap's `writeBinary` does. Duplicate cells: the last one wins.
    pub fn from_cells(
        resolution: f64,
        cells: impl IntoIterator<Item = (CellKey, bool)>,
        prune: bool,
    ) -> Result<BtTree, BtError> {
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(BtError::BadResolution(resolution));
        }
        let mut items = Vec::new();
        for (cell, occupied) in cells {
            items.push((morton(octo_key(cell).ok_or(BtError::KeyOutOfRange(cell))?), occupied));
        }
        items.sort_by_key(|e| e.0);
        let mut unique: Vec<(u64, bool)> = Vec::with_capacity(items.len());
        for e in items {
            match unique.last_mut() {
                Some(last) if last.0 == e.0 => *last = e,
                _ => unique.push(e),
            }
        }
        let nodes = if prune {
            prune_cells(unique)
        } else {
            unique.into_iter().map(|(m, o)| (m, TREE_DEPTH, o)).collect()
        };
        let leaves =
            nodes.iter().map(|&(m, depth, occupied)| BtLeaf { depth, min_cell: cell_of(m), occupied });
        Ok(BtTree { resolution, leaves: leaves.collect(), inner_nodes: count_inner(&nodes) })
    }
}

/// OctoMap key of a bgkmap cell, if in range.
fn octo_key(c: CellKey) -> Option<[u16; 3]> {
    let k = |v: i32| u16::try_from(i64::from(v) + i64::from(KEY_OFFSET)).ok();
    Some([k(c.x)?, k(c.y)?, k(c.z)?])
}

/// Interleaves key bits so that each 3-bit group, from the top, is a child index `x + 2y + 4z`.
fn morton(k: [u16; 3]) -> u64 {
    (0..16).fold(0, |m, b| {
        let bit = |a: usize| u64::from((k[a] >> b) & 1) << (3 * b + a);
        m | bit(0) | bit(1) | bit(2)
    })
}

fn cell_of(m: u64) -> CellKey {
    let axis = |a: usize| (0..16).fold(0i32, |k, b| k | (((m >> (3 * b + a)) & 1) as i32) << b) - KEY_OFFSET;
    CellKey::new(axis(0), axis(1), axis(2))
}

/// Collapses complete same-class sibling octets bottom-up. Input: sorted unique depth-16 Morton
/// codes. Output: `(Morton code of the minimum corner, depth, occupied)` in Morton order.
fn prune_cells(cells: Vec<(u64, bool)>) -> Vec<(u64, u8, bool)> {
    let mut done = Vec::new();
    let mut cur = cells; // prefixes of nodes at `depth`
    for depth in (2..=TREE_DEPTH).rev() {
        let shift = 3 * u32::from(TREE_DEPTH - depth);
        let mut next = Vec::with_capacity(cur.len() / 8);
        let mut i = 0;
        while i < cur.len() {
            let parent = cur[i].0 >> 3;
            let n = cur[i..].iter().take_while(|e| e.0 >> 3 == parent).count();
            let group = &cur[i..i + n];
            if n == 8 && group.iter().all(|e| e.1 == group[0].1) {
                next.push((parent, group[0].1));
            } else {
                done.extend(group.iter().map(|&(p, o)| (p << shift, depth, o)));
            }
            i += n;
        }
        cur = next;
    }
    done.extend(cur.into_iter().map(|(p, o)| (p << (3 * u32::from(TREE_DEPTH - 1)), 1, o)));
    done.sort_unstable_by_key(|e| e.0);
    done
}

/// Distinct ancestors (root included) of non-overlapping leaves sorted in Morton order.
fn count_inner(nodes: &[(u64, u8, bool)]) -> usize {
    if nodes.is_empty() {
        return 0;
    }
    (0..TREE_DEPTH)
        .map(|d| {
            let shift = 3 * u32::from(TREE_DEPTH - d);
            let mut prefixes = nodes.iter().filter(|e| e.1 > d).map(|e| e.0 >> shift).collect::<Vec<_>>();
            prefixes.dedup();
            prefixes.len()
        })
        .sum()
}

/// Decodes a `.bt` file held in memory. Bytes after the tree are ignored (as liboctomap does).
pub fn read_bt(bytes: &[u8]) -> Result<BtTree, BtError> {
    let (size, resolution, start) = parse_header(bytes)?;
    if !(resolution.is_finite() && resolution > 0.0) {
        return Err(BtError::BadResolution(resolution));
    }
    let mut dec = Decoder { payload: &bytes[start..], pos: 0, leaves: Vec::new(), inner: 0 };
    if size > 0 {
        dec.node(0, [0; 3])?;
    }
    let decoded = dec.inner + dec.leaves.len();
    if decoded as u64 != size {
        return Err(BtError::SizeMismatch { header: size, decoded });
    }
    Ok(BtTree { resolution, leaves: dec.leaves, inner_nodes: dec.inner })
}

/// Parses the text header; returns `(size, res, payload offset)`.
fn parse_header(bytes: &[u8]) -> Result<(u64, f64, usize), BtError> {
    if !bytes.starts_with(FIRST_LINE) {
        return Err(BtError::BadFirstLine);
    }
    let mut cur = Cursor { b: bytes, pos: 0 };
    cur.skip_line();
    let (mut size, mut res) = (0u64, 0f64);
    loop {
        let token = cur.token().ok_or_else(|| BtError::Header("missing 'data' line".into()))?;
        match token {
            b"data" => {
                cur.skip_line();
                return Ok((size, res, cur.pos));
            }
            t if t.starts_with(b"#") => cur.skip_line(),
            b"id" => {
                cur.value("id")?;
            }
            b"size" => {
                size = cur.value("size")?.parse().map_err(|_| BtError::Header("invalid size".into()))?
            }
            b"res" => res = cur.value("res")?.parse().map_err(|_| BtError::Header("invalid res".into()))?,
            _ => cur.skip_line(),
        }
    }
}

/// Whitespace-separated tokens, like C++ `istream >> std::string`.
struct Cursor<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn token(&mut self) -> Option<&'a [u8]> {
        while self.b.get(self.pos).is_some_and(u8::is_ascii_whitespace) {
            self.pos += 1;
        }
        let start = self.pos;
        while self.b.get(self.pos).is_some_and(|c| !c.is_ascii_whitespace()) {
            self.pos += 1;
        }
        (self.pos > start).then(|| &self.b[start..self.pos])
    }

    fn value(&mut self, key: &str) -> Result<&'a str, BtError> {
        let t = self.token().ok_or_else(|| BtError::Header(format!("'{key}' has no value")))?;
        std::str::from_utf8(t).map_err(|_| BtError::Header(format!("'{key}' value is not text")))
    }

    /// Moves past the next `\n` (or to the end).
    fn skip_line(&mut self) {
        let rest = &self.b[self.pos..];
        self.pos += rest.iter().position(|&c| c == b'\n').map_or(rest.len(), |i| i + 1);
    }
}

struct Decoder<'a> {
    payload: &'a [u8],
    pos: usize,
    leaves: Vec<BtLeaf>,
    inner: usize,
}

impl Decoder<'_> {
    /// Reads the inner node at `depth` (0..=15) whose OctoMap key prefix is `key`, then its subtree.
    fn node(&mut self, depth: u8, key: [u16; 3]) -> Result<(), BtError> {
        let truncated = BtError::Truncated { node: self.inner, offset: self.pos, len: self.payload.len() };
        let b = self.payload.get(self.pos..self.pos + 2).ok_or(truncated)?;
        let word = u16::from_le_bytes([b[0], b[1]]);
        self.pos += 2;
        self.inner += 1;
        if word == 0 && depth > 0 {
            return Err(BtError::EmptyInner { depth });
        }
        let half = 1u16 << (TREE_DEPTH - 1 - depth);
        for c in 0..8 {
            let child = [0, 1, 2].map(|a| key[a] | if c >> a & 1 == 1 { half } else { 0 });
            let min_cell = || {
                let [x, y, z] = child.map(|k| i32::from(k) - KEY_OFFSET);
                CellKey::new(x, y, z)
            };
            match (word >> (2 * c)) & 3 {
                0 => {}
                1 => self.leaves.push(BtLeaf { depth: depth + 1, min_cell: min_cell(), occupied: false }),
                2 => self.leaves.push(BtLeaf { depth: depth + 1, min_cell: min_cell(), occupied: true }),
                _ if depth + 1 == TREE_DEPTH => return Err(BtError::InnerAtMaxDepth),
                _ => self.node(depth + 1, child)?,
            }
        }
        Ok(())
    }
}

/// Encodes a tree exactly as liboctomap's `writeBinaryConst` would (header and payload).
///
/// Leaves with a depth outside 1..=16 or a key outside OctoMap's range are skipped; a leaf's
/// corner is aligned down to its depth. `inner_nodes` is not consulted: the structure (and the
/// `size` line) follows from the leaves alone. If leaves overlap, the coarsest one covering a region
/// wins (the last of equals), and the finer ones inside it are dropped. An empty tree is
/// written with `size 0` and no payload.
pub fn write_bt(tree: &BtTree) -> Vec<u8> {
    let mut items: Vec<(u64, u8, bool)> = tree
        .leaves
        .iter()
        .filter(|l| (1..=TREE_DEPTH).contains(&l.depth))
        .filter_map(|l| {
            let mask = !((1u64 << (3 * u32::from(TREE_DEPTH - l.depth))) - 1);
            octo_key(l.min_cell).map(|k| (morton(k) & mask, l.depth, l.occupied))
        })
        .collect();
    items.sort_by_key(|e| (e.0, e.1));
    let mut payload = Vec::new();
    let mut size = 0usize;
    if !items.is_empty() {
        size = 1;
        encode(&items, 0, &mut payload, &mut size);
    }
    let mut out = format!(
        "# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the first line as it is!)\n\
         #\nid OcTree\nsize {size}\nres {}\ndata\n",
        format_g6(tree.resolution)
    )
    .into_bytes();
    out.extend_from_slice(&payload);
    out
}

/// Writes the inner node at `depth` holding `items` (all inside it, finer than `depth`).
fn encode(items: &[(u64, u8, bool)], depth: u8, out: &mut Vec<u8>, size: &mut usize) {
    let shift = 3 * u32::from(TREE_DEPTH - 1 - depth);
    let mut ranges = [(0usize, 0usize); 8];
    let mut i = 0;
    while i < items.len() {
        let c = (items[i].0 >> shift) & 7;
        let n = items[i..].iter().take_while(|e| (e.0 >> shift) & 7 == c).count();
        ranges[c as usize] = (i, i + n);
        i += n;
    }
    // absent 00, free leaf 01, occupied leaf 10, inner 11
    let codes = ranges.map(|(s, e)| {
        if s == e {
            return 0u16;
        }
        match items[s..e].iter().rev().find(|it| it.1 == depth + 1) {
            Some(leaf) => 1 + u16::from(leaf.2),
            None => 3,
        }
    });
    let word = codes.iter().enumerate().fold(0u16, |w, (c, &code)| w | code << (2 * c));
    out.extend_from_slice(&word.to_le_bytes());
    *size += codes.iter().filter(|&&c| c != 0).count();
    for (c, &(s, e)) in ranges.iter().enumerate() {
        if codes[c] == 3 {
            encode(&items[s..e], depth + 1, out, size);
        }
    }
}

/// Formats like C++ `ostream << double` with default precision (`%g`, 6 significant digits).
fn format_g6(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}").to_lowercase();
    }
    let sci = format!("{v:.5e}");
    let Some((mantissa, exp)) = sci.split_once('e') else { return sci };
    let exp: i32 = exp.parse().unwrap_or(0);
    let strip = |s: &str| {
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s.to_string()
        }
    };
    if !(-4..6).contains(&exp) {
        format!("{}e{}{:02}", strip(mantissa), if exp < 0 { '-' } else { '+' }, exp.abs())
    } else {
        strip(&format!("{v:.*}", (5 - exp) as usize))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The sample data's `map.bt`; the tests calling this are ignored unless build.rs found it.
    fn sample_map() -> Vec<u8> {
        let path = format!("{}/../shared/data/la3dm/sim_structured/map.bt", env!("CARGO_MANIFEST_DIR"));
        std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
    }

    fn small_tree() -> BtTree {
        let cells = [(CellKey::new(0, 0, 0), true), (CellKey::new(-1, -1, -1), false)];
        BtTree::from_cells(0.1, cells, true).unwrap()
    }

    #[test]
    #[cfg_attr(not(bgkmap_sample_data), ignore = "needs the sample data ../shared/data/la3dm")]
    fn reads_sample_map() {
        let bytes = sample_map();
        let tree = read_bt(&bytes).unwrap();
        assert_eq!(tree.resolution, 0.1);
        assert_eq!((tree.node_count(), tree.leaves.len(), tree.inner_nodes), (171_287, 138_477, 32_810));
        assert_eq!(tree.occupied_leaves(), 13_829);
        let occ_d15 = tree.leaves.iter().filter(|l| l.occupied && l.depth == 15).count();
        let free_d13 = tree.leaves.iter().filter(|l| !l.occupied && l.depth == 13).count();
        assert_eq!((occ_d15, free_d13), (13, 4));
        let cells: Vec<_> = tree.cells().collect();
        assert_eq!(cells.len(), 197_291);
        assert_eq!(cells.iter().filter(|c| c.1).count(), 13_920);
        let occ = cells.iter().filter(|c| c.1).map(|c| c.0);
        let (lo, hi) = occ.fold(([i32::MAX; 3], [i32::MIN; 3]), |(lo, hi), k| {
            (
                [lo[0].min(k.x), lo[1].min(k.y), lo[2].min(k.z)],
                [hi[0].max(k.x), hi[1].max(k.y), hi[2].max(k.z)],
            )
        });
        assert_eq!((lo, hi), ([0, 0, 0], [72, 101, 21])); // cell bounds x [0, 7.3], y [0, 10.2], z [0, 2.2]
        assert_eq!(write_bt(&tree), bytes);
    }

    /// `map.bt` is liboctomap's `writeBinaryConst` of a tree that was only partly pruned (4464
    /// octets of same-class depth-16 siblings remain), so a fully pruned rebuild cannot give its
    /// bytes. It does give, byte for byte, what liboctomap 1.9.7 `writeBinary` (max-likelihood +
    /// prune) writes for the same map: 131 839 nodes, 55 899 bytes, CRC-32 0xf8a82ddb.
    #[test]
    #[cfg_attr(not(bgkmap_sample_data), ignore = "needs the sample data ../shared/data/la3dm")]
    fn sample_cells_rebuilt_with_pruning_match_liboctomap_write_binary() {
        let bytes = sample_map();
        let tree = read_bt(&bytes).unwrap();
        let t0 = std::time::Instant::now();
        let rebuilt = BtTree::from_cells(0.1, tree.cells(), true).unwrap();
        let out = write_bt(&rebuilt);
        eprintln!("from_cells + write_bt of 197 291 cells: {:?}", t0.elapsed());
        assert_eq!(
            (rebuilt.node_count(), rebuilt.leaves.len(), rebuilt.inner_nodes),
            (131_839, 103_960, 27_879)
        );
        assert_eq!((out.len(), crc32fast::hash(&out)), (55_899, 0xf8a8_2ddb));
        let back = read_bt(&out).unwrap();
        assert!(back == rebuilt);
        let mut a: Vec<_> = back.cells().collect();
        let mut b: Vec<_> = tree.cells().collect();
        a.sort();
        b.sort();
        assert!(a == b);
        let unpruned = BtTree::from_cells(0.1, tree.cells(), false).unwrap();
        assert_eq!(unpruned.leaves.len(), 197_291);
        assert!(read_bt(&write_bt(&unpruned)).unwrap() == unpruned);
    }

    fn hex(s: &str) -> Vec<u8> {
        (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect()
    }

    fn golden(size: u32, res: &str, payload: &str) -> Vec<u8> {
        let head = format!(
            "# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the first line as it \
             is!)\n#\nid OcTree\nsize {size}\nres {res}\ndata\n"
        );
        [head.into_bytes(), hex(payload)].concat()
    }

    /// Bytes written by liboctomap 1.9.7 `writeBinary` after `updateNode`: a 4×4×4 block of
    /// 0.05 m cells at the origin, all occupied except (3, 3, 3), which is free.
    #[test]
    fn pruned_block_matches_liboctomap() {
        let cells = (0..64).map(|i| (CellKey::new(i % 4, (i / 4) % 4, i / 16), i != 63));
        let tree = BtTree::from_cells(0.05, cells, true).unwrap();
        let expect = golden(31, "0.05", &format!("00c0{}aaeaaa6a", "0300".repeat(13)));
        assert_eq!(write_bt(&tree), expect);
        assert_eq!(read_bt(&expect).unwrap(), tree);
    }

    #[test]
    fn two_cell_tree_has_expected_bytes_and_round_trips() {
        let tree = small_tree();
        assert_eq!((tree.inner_nodes, tree.leaves.len(), tree.node_count()), (31, 2, 33));
        // Pre-order: child 0 (key 32767 per axis) comes before child 7 (key 32768).
        assert_eq!(tree.leaves[0], BtLeaf { depth: 16, min_cell: CellKey::new(-1, -1, -1), occupied: false });
        assert_eq!(tree.leaves[1], BtLeaf { depth: 16, min_cell: CellKey::new(0, 0, 0), occupied: true });
        let bytes = write_bt(&tree);
        let header = "# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the first line \
                      as it is!)\n#\nid OcTree\nsize 33\nres 0.1\ndata\n";
        assert_eq!(&bytes[..header.len()], header.as_bytes());
        let payload = &bytes[header.len()..];
        assert_eq!(payload.len(), 62);
        // Root: children 0 and 7 inner. Branch 0 (key 32767: all lower bits 1) continues through child 7.
        assert_eq!(&payload[..4], &[0x03, 0xC0, 0x00, 0xC0]);
        // Depth-15 node of branch 0: free leaf as child 7 (bits 14-15 = 01); branch 1 starts with child 0 inner.
        assert_eq!(&payload[28..34], &[0x00, 0xC0, 0x00, 0x40, 0x03, 0x00]);
        assert_eq!(&payload[60..62], &[0x02, 0x00]); // occupied leaf as child 0 (bits 0-1 = 10)
        // liboctomap 1.9.7 writeBinary of updateNode((0.05, 0.05, 0.05), true), ((-0.05, …), false):
        let ones = "00c0".repeat(14);
        assert_eq!(bytes, golden(33, "0.1", &format!("03c0{ones}0040{}0200", "0300".repeat(14))));
        assert_eq!(read_bt(&bytes).unwrap(), tree);
        let mut cells: Vec<_> = tree.cells().collect();
        cells.sort();
        assert_eq!(cells, vec![(CellKey::new(-1, -1, -1), false), (CellKey::new(0, 0, 0), true)]);
    }

    #[test]
    fn pruning_collapses_uniform_octets_only() {
        let block = |occ: &dyn Fn(i32) -> bool| {
            (0..64).map(|i| (CellKey::new(i % 4, (i / 4) % 4, i / 16), occ(i))).collect::<Vec<_>>()
        };
        let all = BtTree::from_cells(0.1, block(&|_| true), true).unwrap();
        assert_eq!(all.leaves, vec![BtLeaf { depth: 14, min_cell: CellKey::new(0, 0, 0), occupied: true }]);
        assert_eq!(all.inner_nodes, 14);
        let one_free = BtTree::from_cells(0.1, block(&|i| i != 63), true).unwrap();
        assert_eq!(one_free.leaves.len(), 7 + 8); // 7 depth-15 leaves + the mixed octet's 8 cells
        assert_eq!(one_free.cells().count(), 64);
        let unpruned = BtTree::from_cells(0.1, block(&|_| true), false).unwrap();
        assert_eq!(unpruned.leaves.len(), 64);
        assert_eq!(unpruned.inner_nodes, 14 + 1 + 8);
    }

    #[test]
    fn from_cells_validates_keys_and_resolves_duplicates() {
        let err = BtTree::from_cells(0.1, [(CellKey::new(32768, 0, 0), true)], false).unwrap_err();
        assert!(matches!(err, BtError::KeyOutOfRange(_)), "{err}");
        assert!(BtTree::from_cells(0.1, [(CellKey::new(-32768, 32767, 0), true)], false).is_ok());
        assert!(matches!(BtTree::from_cells(0.0, [], false), Err(BtError::BadResolution(_))));
        let dup = [(CellKey::new(1, 2, 3), true), (CellKey::new(1, 2, 3), false)];
        let tree = BtTree::from_cells(0.1, dup, false).unwrap();
        assert_eq!(tree.leaves.len(), 1);
        assert!(!tree.leaves[0].occupied);
    }

    #[test]
    fn empty_tree_writes_size_zero() {
        let tree = BtTree::from_cells(0.05, [], true).unwrap();
        let bytes = write_bt(&tree);
        assert!(bytes.ends_with(b"size 0\nres 0.05\ndata\n"));
        assert_eq!(read_bt(&bytes).unwrap(), tree);
    }

    #[test]
    fn header_validation() {
        let good = write_bt(&small_tree());
        let split = good.windows(5).position(|w| w == b"data\n").unwrap() + 5;
        let with = |from: &str, to: &str| {
            let head = String::from_utf8(good[..split].to_vec()).unwrap().replacen(from, to, 1);
            read_bt(&[head.as_bytes(), &good[split..]].concat())
        };
        assert!(matches!(read_bt(&good[1..]), Err(BtError::BadFirstLine)));
        assert_eq!(
            with("size 33", "size 34").unwrap_err().to_string(),
            "Tree size mismatch: header says 34, decoded 33"
        );
        assert!(matches!(with("res 0.1", "res 0"), Err(BtError::BadResolution(_))));
        assert!(matches!(with("res 0.1\n", ""), Err(BtError::BadResolution(_))));
        assert!(matches!(with("size 33", "size x"), Err(BtError::Header(_))));
        assert!(with("id OcTree", "id OcTree\nfoo bar baz\n# another comment").is_ok());
        assert!(matches!(read_bt(&good[..good.len() - 1]), Err(BtError::Truncated { .. })));
        let mut trailing = good.clone();
        trailing.extend_from_slice(b"extra");
        assert!(read_bt(&trailing).is_ok());
    }

    #[test]
    fn malformed_payloads() {
        let hdr =
            |size: u32| format!("# Octomap OcTree binary file\nid OcTree\nsize {size}\nres 0.1\ndata\n");
        let empty_root = [hdr(1).as_bytes(), &[0, 0]].concat();
        assert_eq!(read_bt(&empty_root).unwrap().node_count(), 1);
        let empty_inner = [hdr(2).as_bytes(), &[3, 0, 0, 0]].concat();
        assert!(matches!(read_bt(&empty_inner), Err(BtError::EmptyInner { depth: 1 })));
        let mut deep = hdr(17).into_bytes();
        (0..16).for_each(|_| deep.extend_from_slice(&[3, 0]));
        assert!(matches!(read_bt(&deep), Err(BtError::InnerAtMaxDepth)));
    }

    #[test]
    fn resolution_prints_like_cpp() {
        let cases = [(0.1, "0.1"), (0.05, "0.05"), (0.2, "0.2"), (1.0, "1"), (0.123456789, "0.123457")];
        for (v, s) in
            cases.into_iter().chain([(1e-5, "1e-05"), (1234567.0, "1.23457e+06"), (100000.0, "100000")])
        {
            assert_eq!(format_g6(v), s);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        #[test]
        fn random_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..300)) {
            let _ = read_bt(&data);
            let _ = read_bt(&[FIRST_LINE, b"\nres 0.1 size 40 data\n", &data].concat());
        }

        #[test]
        fn truncations_fail_and_mutations_never_panic(cut in any::<prop::sample::Index>(),
                                                      flip in any::<prop::sample::Index>(), byte in any::<u8>()) {
            let good = write_bt(&small_tree());
            prop_assert!(read_bt(&good[..cut.index(good.len())]).is_err());
            let mut mutated = good.clone();
            mutated[flip.index(good.len())] = byte;
            let _ = read_bt(&mutated);
        }

        #[test]
        fn cells_round_trip(cells in proptest::collection::vec(((-40i32..40, -40i32..40, -3i32..3), any::<bool>()), 0..300),
                            prune in any::<bool>()) {
            let cells: Vec<_> = cells.into_iter().map(|((x, y, z), o)| (CellKey::new(x, y, z), o)).collect();
            let tree = BtTree::from_cells(0.1, cells.iter().copied(), prune).unwrap();
            let back = read_bt(&write_bt(&tree)).unwrap();
            prop_assert_eq!(&back, &tree);
            let mut expect: std::collections::BTreeMap<CellKey, bool> = Default::default();
            expect.extend(cells);
            let got: std::collections::BTreeMap<CellKey, bool> = back.cells().collect();
            prop_assert_eq!(got, expect);
        }
    }
}
