//! An immutable view of a map for readers, and the checks that keep answers honest around
//! corrupt blocks: a query whose answer depends on a block that failed its checksum gets
//! [`ServiceError::DataLoss`] instead of the prior; queries elsewhere are answered as usual.

use super::{BlockVersions, ServiceError};
use crate::core::key::BLOCK_EDGE;
use crate::core::{BlockKey, CellKey, EvidenceMap};
use crate::store::CorruptBlock;
use std::sync::Arc;

/// An immutable view of a map after a whole number of scans.
#[derive(Debug)]
pub struct Snapshot {
    /// The map version (see the store's `meta.version`).
    pub version: u64,
    pub map: EvidenceMap,
    /// Blocks that failed their checks when the map was opened (absent from `map`).
    pub corrupt: Arc<Vec<CorruptBlock>>,
    /// Per block, the version at which it last changed (see [`super::MapService::changes_since`]).
    pub block_versions: Arc<BlockVersions>,
    /// The version the map was opened at: block history is known from there on (see the
    /// `updates` module).
    pub history_from: u64,
}

impl Snapshot {
    /// DATA_LOSS: `what` depends on the corrupt block `c`.
    pub fn loss(c: &CorruptBlock, what: String) -> ServiceError {
        ServiceError::DataLoss(format!(
            "{what} touches block ({}, {}, {}), which is corrupt ({}); run `bgkmap check` on the map file",
            c.key.x, c.key.y, c.key.z, c.reason
        ))
    }

    /// World-frame bounds (m) of a block.
    fn block_bounds(&self, k: BlockKey) -> ([f64; 3], [f64; 3]) {
        let size = f64::from(BLOCK_EDGE) * self.map.params().resolution_m;
        let lo = [f64::from(k.x) * size, f64::from(k.y) * size, f64::from(k.z) * size];
        (lo, [lo[0] + size, lo[1] + size, lo[2] + size])
    }

    /// DATA_LOSS when any point (world frame, m) lies in a corrupt block.
    pub fn check_points(&self, points_world: &[[f64; 3]]) -> Result<(), ServiceError> {
        if self.corrupt.is_empty() {
            return Ok(());
        }
        let res = self.map.params().resolution_m;
        for (i, p) in points_world.iter().enumerate() {
            let Some(block) = CellKey::from_point(*p, res).map(CellKey::block) else { continue };
            if let Some(c) = self.corrupt.iter().find(|c| c.key == block) {
                return Err(Self::loss(c, format!("point {i}")));
            }
        }
        Ok(())
    }

    /// DATA_LOSS when the box `[min, max]` (world frame, m) overlaps a corrupt block.
    pub fn check_box(&self, min_world: [f64; 3], max_world: [f64; 3]) -> Result<(), ServiceError> {
        for c in self.corrupt.iter() {
            let (lo, hi) = self.block_bounds(c.key);
            if (0..3).all(|i| min_world[i] < hi[i] && max_world[i] >= lo[i]) {
                return Err(Self::loss(c, "the box".into()));
            }
        }
        Ok(())
    }

    /// DATA_LOSS when the segment `from → to` (world frame, m) passes through a corrupt block.
    pub fn check_segment(
        &self,
        from_world: [f64; 3],
        to_world: [f64; 3],
        what: &str,
    ) -> Result<(), ServiceError> {
        for c in self.corrupt.iter() {
            let (lo, hi) = self.block_bounds(c.key);
            if segment_hits_box(from_world, to_world, lo, hi) {
                return Err(Self::loss(c, what.to_string()));
            }
        }
        Ok(())
    }

    /// The corrupt block a ray from `origin` along `direction` (world frame) passes within
    /// `reach_m` metres, if any (the caller names the ray in its DATA_LOSS, see [`Self::loss`]).
    pub fn corrupt_on_ray(
        &self,
        origin: [f64; 3],
        direction: [f64; 3],
        reach_m: f64,
    ) -> Option<&CorruptBlock> {
        if self.corrupt.is_empty() {
            return None;
        }
        let norm = direction.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(norm.is_finite() && norm > 0.0 && reach_m.is_finite()) {
            return None;
        }
        let to = [0, 1, 2].map(|i| origin[i] + direction[i] / norm * reach_m);
        self.corrupt.iter().find(|c| {
            let (lo, hi) = self.block_bounds(c.key);
            segment_hits_box(origin, to, lo, hi)
        })
    }

    /// DATA_LOSS when a corrupt block holds any cell with key in `[lo, hi]`.
    pub fn check_cells(&self, lo: CellKey, hi: CellKey) -> Result<(), ServiceError> {
        let (bl, bh) = (lo.block(), hi.block());
        let inside = |k: BlockKey| {
            (bl.x..=bh.x).contains(&k.x) && (bl.y..=bh.y).contains(&k.y) && (bl.z..=bh.z).contains(&k.z)
        };
        match self.corrupt.iter().find(|c| inside(c.key)) {
            Some(c) => Err(Self::loss(c, "the export".into())),
            None => Ok(()),
        }
    }

    /// DATA_LOSS when any corrupt block exists (whole-map answers such as exports).
    pub fn check_whole(&self) -> Result<(), ServiceError> {
        match self.corrupt.first() {
            Some(c) => Err(Self::loss(c, "the whole map".into())),
            None => Ok(()),
        }
    }
}

/// Slab test: does the segment `a → b` meet the closed box `[lo, hi]`?
fn segment_hits_box(a: [f64; 3], b: [f64; 3], lo: [f64; 3], hi: [f64; 3]) -> bool {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for i in 0..3 {
        let d = b[i] - a[i];
        if d == 0.0 {
            if a[i] < lo[i] || a[i] > hi[i] {
                return false;
            }
            continue;
        }
        let (mut ta, mut tb) = ((lo[i] - a[i]) / d, (hi[i] - a[i]) / d);
        if ta > tb {
            std::mem::swap(&mut ta, &mut tb);
        }
        t0 = t0.max(ta);
        t1 = t1.min(tb);
        if t0 > t1 {
            return false;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::MapParams;

    fn snap() -> Snapshot {
        let corrupt = vec![CorruptBlock { key: BlockKey::new(2, 0, 0), reason: "checksum mismatch".into() }];
        Snapshot {
            version: 1,
            map: EvidenceMap::new(MapParams::default()),
            corrupt: Arc::new(corrupt),
            block_versions: Arc::default(),
            history_from: 1,
        }
    }

    #[test]
    fn only_answers_that_touch_the_corrupt_block_are_refused() {
        // Block (2, 0, 0) spans x ∈ [1.6, 2.4), y, z ∈ [0, 0.8) at 0.1 m.
        let s = snap();
        assert!(s.check_points(&[[0.1, 0.1, 0.1], [3.0, 0.1, 0.1]]).is_ok());
        let e = s.check_points(&[[0.1, 0.1, 0.1], [2.0, 0.5, 0.5]]).unwrap_err();
        assert!(
            matches!(&e, ServiceError::DataLoss(m) if m.contains("point 1") && m.contains("(2, 0, 0)")),
            "{e}"
        );
        assert!(s.check_box([0.0; 3], [1.5, 1.0, 1.0]).is_ok());
        assert!(s.check_box([0.0; 3], [1.7, 1.0, 1.0]).is_err());
        assert!(s.check_segment([0.1, 0.4, 0.4], [1.5, 0.4, 0.4], "ray 0").is_ok());
        assert!(s.check_segment([0.1, 0.4, 0.4], [3.0, 0.4, 0.4], "ray 0").is_err());
        assert!(s.check_segment([2.0, 2.0, 0.4], [2.0, 1.0, 0.4], "ray 0").is_ok());
        assert!(s.check_whole().is_err());
    }
}
