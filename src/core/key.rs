//! Integer cell and block keys.
//!
//! A cell key is `floor(x / res)` per axis; the cell centre is `(key + ½)·res`. These are the
//! same cells as OctoMap voxels (OctoMap key − 32768) and la3dm leaves. Cells are grouped into
//! blocks of [`BLOCK_EDGE`]³ cells; a block key is the cell key shifted right by
//! [`BLOCK_SHIFT`] (an arithmetic shift, so it floors for negative keys too).

/// log2 of the block edge in cells.
pub const BLOCK_SHIFT: u32 = 3;
/// Cells per block edge (B). 8 cells of 0.1 m make 0.8 m blocks.
pub const BLOCK_EDGE: i32 = 1 << BLOCK_SHIFT;
/// Cells per block (B³).
pub const BLOCK_CELLS: usize = (BLOCK_EDGE * BLOCK_EDGE * BLOCK_EDGE) as usize;
pub(crate) const BLOCK_MASK: i32 = BLOCK_EDGE - 1;

/// Integer coordinates of one map cell: `floor(x / res)` per axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct CellKey {
    pub x: i32,
    pub y: i32,
    pub z: i32,
}

/// Integer coordinates of one block of `BLOCK_EDGE`³ cells.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct BlockKey {
    pub x: i32,
    pub y: i32,
    pub z: i32,
}

impl CellKey {
    pub const fn new(x: i32, y: i32, z: i32) -> Self {
        Self { x, y, z }
    }

    /// The cell containing world point `p_m` (metres) at resolution `res_m`, or `None` when the
    /// point is not finite or lies outside the i32 key range.
    pub fn from_point(p_m: [f64; 3], res_m: f64) -> Option<Self> {
        Self::from_cells(p_m.map(|v| v / res_m))
    }

    /// The cell containing `q`, a point in units of cells (a world point divided by the
    /// resolution, as [`Self::from_point`] divides it), or `None` outside the i32 key range.
    #[inline(always)]
    pub fn from_cells(q: [f64; 3]) -> Option<Self> {
        // floor(v) is in the i32 range ⇔ MIN ≤ v < MAX + 1 (false for NaN and ±∞). Inside it the
        // floor is the truncation, minus one where that rounded up: no libm `floor` call, which
        // baseline x86-64 (no SSE4.1 `roundsd`) would make per coordinate.
        let k = |q: f64| {
            (q >= f64::from(i32::MIN) && q < f64::from(i32::MAX) + 1.0).then(|| {
                let t = q as i32;
                if f64::from(t) > q { t - 1 } else { t }
            })
        };
        Some(Self::new(k(q[0])?, k(q[1])?, k(q[2])?))
    }

    /// World coordinates (metres) of the cell centre.
    pub fn centre(self, res_m: f64) -> [f64; 3] {
        [
            (f64::from(self.x) + 0.5) * res_m,
            (f64::from(self.y) + 0.5) * res_m,
            (f64::from(self.z) + 0.5) * res_m,
        ]
    }

    pub fn block(self) -> BlockKey {
        BlockKey { x: self.x >> BLOCK_SHIFT, y: self.y >> BLOCK_SHIFT, z: self.z >> BLOCK_SHIFT }
    }

    /// Index of this cell inside its block, x fastest: `x + B·y + B²·z` of the local coordinates.
    pub fn index_in_block(self) -> usize {
        ((self.x & BLOCK_MASK)
            | ((self.y & BLOCK_MASK) << BLOCK_SHIFT)
            | ((self.z & BLOCK_MASK) << (2 * BLOCK_SHIFT))) as usize
    }
}

impl BlockKey {
    pub const fn new(x: i32, y: i32, z: i32) -> Self {
        Self { x, y, z }
    }

    /// The cell at local index `i` (as produced by [`CellKey::index_in_block`]).
    pub fn cell(self, i: usize) -> CellKey {
        let i = i as i32;
        CellKey {
            x: (self.x << BLOCK_SHIFT) | (i & BLOCK_MASK),
            y: (self.y << BLOCK_SHIFT) | ((i >> BLOCK_SHIFT) & BLOCK_MASK),
            z: (self.z << BLOCK_SHIFT) | (i >> (2 * BLOCK_SHIFT)),
        }
    }

    /// The first (minimum) cell of the block.
    pub fn min_cell(self) -> CellKey {
        self.cell(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cell_block_round_trip_including_negative_keys() {
        for &(x, y, z) in &[(0, 0, 0), (-1, -1, -1), (7, 8, -9), (-8, 15, 16), (i32::MIN, i32::MAX, 3)] {
            let c = CellKey::new(x, y, z);
            assert_eq!(c.block().cell(c.index_in_block()), c);
        }
        assert_eq!(CellKey::new(-1, 0, 7).block(), BlockKey::new(-1, 0, 0));
    }

    #[test]
    fn key_of_point_floors_and_centre_is_half_offset() {
        let k = CellKey::from_point([0.05, -0.05, 1.0], 0.1).unwrap();
        assert_eq!(k, CellKey::new(0, -1, 10));
        let c = k.centre(0.1);
        assert!((c[1] + 0.05).abs() < 1e-12);
        assert!(CellKey::from_point([f64::NAN, 0.0, 0.0], 0.1).is_none());
        assert!(CellKey::from_point([1e12, 0.0, 0.0], 0.1).is_none());
        // The edges of the key range, against the libm floor.
        for v in [
            -2147483648.0,
            -2147483647.5,
            -2147483648.5,
            2147483647.0,
            2147483647.9,
            2147483648.0,
            -0.0,
            -1e-300,
        ] {
            let f: f64 = libm::floor(v);
            let want = (f >= f64::from(i32::MIN) && f <= f64::from(i32::MAX)).then_some(f as i32);
            assert_eq!(CellKey::from_point([v, 0.0, 0.0], 1.0).map(|c| c.x), want, "{v}");
        }
        assert!(CellKey::from_point([f64::INFINITY, 0.0, 0.0], 0.1).is_none());
    }
}
