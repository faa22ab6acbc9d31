//! A batch of changes to an [`EvidenceMap`] computed aside from it: scans added or removed,
//! whole blocks of another map added. The map itself is untouched until the edit is committed
//! with [`EvidenceMap::commit_edit`], so a caller can first make the change durable and only then
//! publish it (and drop the edit if storing fails).

use super::delta::ScanDelta;
use super::sink::BlockSink;
use crate::core::block::BlockEvidence;
use crate::core::key::BlockKey;
use crate::core::map::EvidenceMap;
use rustc_hash::FxHashMap;
use std::sync::Arc;

/// Changed blocks of a map: each starts as the map's block (or zero) on first touch, shared
/// until the first write copies it.
#[derive(Debug)]
pub struct MapEdit<'a> {
    base: &'a EvidenceMap,
    blocks: FxHashMap<BlockKey, Arc<BlockEvidence>>,
}

/// The outcome of an edit: every touched block with its new content (`None`: no evidence left,
/// the block goes), sorted by key.
pub type EditedBlocks = Vec<(BlockKey, Option<Arc<BlockEvidence>>)>;

impl<'a> MapEdit<'a> {
    pub fn new(base: &'a EvidenceMap) -> Self {
        Self { base, blocks: FxHashMap::default() }
    }

    /// Block `key`, to change it (widened first if `wide`: [`BlockEvidence::make_mut`]).
    fn block_mut(&mut self, key: BlockKey, wide: bool) -> &mut BlockEvidence {
        let base = self.base;
        let block = self.blocks.entry(key).or_insert_with(|| shared_or_zero(base, key, wide));
        BlockEvidence::make_mut(block, wide)
    }

    /// Adds (`sign` ≥ 0) or subtracts (`sign` < 0) a scan's evidence.
    pub fn add_delta(&mut self, delta: &ScanDelta, sign: i64) {
        for (key, d, rows) in delta.iter() {
            self.block_mut(key, rows[0] != 0).add_delta(d, sign, rows);
        }
    }

    /// Adds (`sign` ≥ 0) or subtracts (`sign` < 0) one block of evidence.
    pub fn add_block(&mut self, key: BlockKey, block: &BlockEvidence, sign: i64) {
        self.block_mut(key, block.is_wide()).add_scaled(block, sign);
    }

    /// Blocks touched so far.
    pub fn len(&self) -> usize {
        self.blocks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.blocks.is_empty()
    }

    /// The touched blocks and their new content, sorted by key; blocks whose content did not
    /// change are left out.
    pub fn finish(self) -> EditedBlocks {
        let base = self.base;
        let mut out: EditedBlocks = self
            .blocks
            .into_iter()
            .filter(|(k, b)| match base.block(*k) {
                Some(old) => !std::ptr::eq(old, &**b) && *old != **b,
                None => !b.is_empty(),
            })
            .map(|(k, b)| (k, (!b.is_empty()).then_some(b)))
            .collect();
        out.sort_unstable_by_key(|(k, _)| *k);
        out
    }
}

impl BlockSink for MapEdit<'_> {
    fn take_block(&mut self, key: BlockKey, wide: bool) -> Arc<BlockEvidence> {
        let base = self.base;
        self.blocks.remove(&key).unwrap_or_else(|| shared_or_zero(base, key, wide))
    }

    fn put_block(&mut self, key: BlockKey, block: Arc<BlockEvidence>) {
        self.blocks.insert(key, block);
    }

    fn add_delta(&mut self, delta: &ScanDelta, sign: i64) {
        MapEdit::add_delta(self, delta, sign);
    }

    fn take_existing_block(&mut self, key: BlockKey) -> Option<Arc<BlockEvidence>> {
        self.blocks.remove(&key).or_else(|| self.base.block_arc(key))
    }
}

/// `map`'s block `key` (shared until written), or a zero block (`wide` or narrow).
fn shared_or_zero(map: &EvidenceMap, key: BlockKey, wide: bool) -> Arc<BlockEvidence> {
    map.block_arc(key).unwrap_or_else(|| BlockEvidence::zeroed_arc(wide))
}

impl EvidenceMap {
    /// Starts an edit of this map (see [`MapEdit`]).
    pub fn edit(&self) -> MapEdit<'_> {
        MapEdit::new(self)
    }

    /// Installs the blocks of a finished edit.
    pub fn commit_edit(&mut self, blocks: EditedBlocks) {
        self.set_blocks(blocks);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::{Integrator, MapParams};

    #[test]
    fn edit_leaves_the_map_alone_until_committed_and_drops_emptied_blocks() {
        let params = MapParams::default();
        let mut integ = Integrator::new(params);
        let pts: Vec<[f32; 3]> = (0..100).map(|i| [2.0, -0.5 + i as f32 * 0.01, 0.5]).collect();
        let delta = integ.scan_delta(&pts, [0.0, 0.0, 0.5], 1);
        let mut map = EvidenceMap::new(params);
        map.apply(&delta, 1);
        let before = map.clone();
        let mut edit = map.edit();
        edit.add_delta(&delta, -1);
        let blocks = edit.finish();
        assert_eq!(map.block_keys_sorted(), before.block_keys_sorted(), "the map is untouched");
        assert!(blocks.iter().all(|(_, b)| b.is_none()), "removing the only scan empties every block");
        map.commit_edit(blocks);
        assert_eq!(map.block_count(), 0);
        // A change that cancels out touches nothing.
        let mut edit = before.edit();
        edit.add_delta(&delta, 1);
        edit.add_delta(&delta, -1);
        assert!(edit.finish().is_empty());
    }

    #[test]
    fn adding_whole_blocks_to_an_edit_sums_with_the_base_and_the_edit() {
        let params = MapParams::default();
        let mut integ = Integrator::new(params);
        let pts: Vec<[f32; 3]> = (0..100).map(|i| [2.0, -0.5 + i as f32 * 0.01, 0.5]).collect();
        let mut map = EvidenceMap::new(params);
        integ.integrate(&mut map, &pts, [0.0, 0.0, 0.5], 1);
        let before = map.clone();
        let (in_base, new) = (map.block_keys_sorted()[0], BlockKey::new(900, 900, 900));
        let block: Arc<BlockEvidence> = map.block(in_base).unwrap().to_box().into();
        let mut edit = map.edit();
        edit.add_whole_block(in_base, block.clone());
        edit.add_whole_block(in_base, block.clone());
        edit.add_whole_block(new, block.clone());
        let blocks = edit.finish();
        assert_eq!(map.block_keys_sorted(), before.block_keys_sorted(), "the map is untouched");
        let mut tripled = block.to_box();
        tripled.add_scaled(&block, 1);
        tripled.add_scaled(&block, 1);
        let got: std::collections::BTreeMap<_, _> = blocks.into_iter().collect();
        assert_eq!(got.len(), 2);
        assert!(got[&in_base].as_deref() == Some(&tripled), "base + two additions");
        assert!(got[&new].as_deref() == Some(&*block), "a new block is taken as it is");
    }
}
