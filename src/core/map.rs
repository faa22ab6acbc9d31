//! The evidence map: sparse blocks of fixed-point evidence in a block table, with the log of
//! the blocks that changed.
//!
//! Part of the data model: depends on `key`, `params`, `posterior`, `block` and `block_table`,
//! never on the integration pipeline (which adds to the map through `pub(in crate::core)` parts).

use super::block::{BlockEvidence, BlockSummary};
use super::block_table::BlockTable;
use super::key::{BlockKey, CellKey};
use super::params::{MapParams, Thresholds};
use super::posterior::{CellEstimate, Evidence};
use std::sync::{Arc, OnceLock};

/// A sparse map of evidence blocks with its parameters.
///
/// Blocks are shared (`Arc`) and copied on write, so a clone is a cheap immutable snapshot for
/// readers (one reference count per block) while the writer goes on updating its own copy.
#[derive(Debug, Clone)]
pub struct EvidenceMap {
    pub(in crate::core) params: MapParams,
    pub(in crate::core) blocks: BlockTable<Slot>,
    pub(in crate::core) changes: ChangeLog,
}

/// The keys of the blocks changed since [`EvidenceMap::take_changes`] last ran, so whoever
/// publishes snapshots of a map learns what changed from the changes themselves, not by
/// comparing every block of two maps (which cost the server milliseconds per scan on a map of
/// 30k blocks, and grew with the map). A key may be noted for a block that in the end did not
/// change; no changed block goes unnoted.
#[derive(Debug, Default)]
pub(in crate::core) struct ChangeLog {
    keys: Vec<BlockKey>,
    /// False until the first [`EvidenceMap::take_changes`], and after an overflow: what changed
    /// is then unknown.
    complete: bool,
}

impl ChangeLog {
    /// Keys kept at most; past this many the log gives up (and takers compare maps instead).
    const MAX_KEYS: usize = 1 << 20;

    #[inline]
    pub(in crate::core) fn note(&mut self, key: BlockKey) {
        if self.complete {
            if self.keys.len() < Self::MAX_KEYS {
                self.keys.push(key);
            } else {
                (self.complete, self.keys) = (false, Vec::new());
            }
        }
    }
}

/// A clone starts with an unknown history: it is a different map from whatever its
/// changes were counted against.
impl Clone for ChangeLog {
    fn clone(&self) -> Self {
        Self::default()
    }
}

/// A map block and its [`BlockSummary`], computed by the first reader that asks and dropped by
/// every change. It lives beside the block's pointer, so a ray reads it with the hash lookup
/// it makes anyway.
#[derive(Debug, Clone)]
pub(in crate::core) struct Slot {
    pub(in crate::core) block: Arc<BlockEvidence>,
    summary: OnceLock<BlockSummary>,
}

// A block's table entry (its key and slot) fills one cache line, which a batched lookup
// prefetches whole (`block_table::Entry`); a larger slot would take two lines a block.
const _: () = assert!(std::mem::size_of::<super::block_table::Entry<Slot>>() == 64, "entry > 64 bytes");

impl Slot {
    pub(in crate::core) fn new(block: Arc<BlockEvidence>) -> Self {
        Self { block, summary: OnceLock::new() }
    }

    /// A slot with a zero block (`wide` or narrow).
    pub(in crate::core) fn zeroed(wide: bool) -> Self {
        Self::new(BlockEvidence::zeroed_arc(wide))
    }

    /// The block, to change it (copied first if a snapshot shares it, widened first if `wide`:
    /// [`BlockEvidence::make_mut`]).
    pub(in crate::core) fn block_mut(&mut self, wide: bool) -> &mut BlockEvidence {
        self.summary.take();
        BlockEvidence::make_mut(&mut self.block, wide)
    }
}

impl EvidenceMap {
    /// Bytes of block table per block (key, block pointer, summary and slots) at the table's
    /// worst load, for memory figures.
    pub const TABLE_BYTES_PER_BLOCK: usize = BlockTable::<Slot>::WORST_BYTES_PER_ENTRY;

    /// An empty map. `params` must be valid ([`MapParams::validate`]).
    pub fn new(params: MapParams) -> Self {
        Self { params, blocks: BlockTable::default(), changes: ChangeLog::default() }
    }

    /// The keys (sorted, distinct) of every block that may have changed since the last call,
    /// or `None` the first time, after a clone and when too many changed to list: then any
    /// block may have. Starts a new log either way.
    pub fn take_changes(&mut self) -> Option<Vec<BlockKey>> {
        let log = std::mem::replace(&mut self.changes, ChangeLog { keys: Vec::new(), complete: true });
        log.complete.then(|| {
            let mut keys = log.keys;
            keys.sort_unstable();
            keys.dedup();
            keys
        })
    }

    pub fn params(&self) -> &MapParams {
        &self.params
    }

    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    pub fn cells_with_evidence(&self) -> usize {
        self.blocks.values().map(|s| s.block.cells_with_evidence()).sum()
    }

    pub fn block(&self, key: BlockKey) -> Option<&BlockEvidence> {
        self.blocks.get(&key).map(|s| &*s.block)
    }

    /// Keys one [`Self::blocks_of`] call takes at most.
    pub const MAX_BATCH_LOOKUPS: usize = 64;

    /// The blocks of a batch of at most [`Self::MAX_BATCH_LOOKUPS`] keys into `out` (same
    /// length), their lookups staged so the cache misses of the whole batch overlap: all table
    /// slots, then all entries (see [`BlockTable`]).
    pub fn blocks_of<'a>(&'a self, keys: &[Option<BlockKey>], out: &mut [Option<&'a BlockEvidence>]) {
        const MAX: usize = EvidenceMap::MAX_BATCH_LOOKUPS;
        assert!(keys.len() <= MAX && out.len() == keys.len(), "batches of at most {MAX} keys");
        let mut hashes = [None; MAX];
        for (h, k) in hashes.iter_mut().zip(keys) {
            *h = k.map(|k| self.blocks.home(k));
        }
        let mut candidates = [None; MAX];
        for (c, h) in candidates.iter_mut().zip(&hashes[..keys.len()]) {
            *c = h.and_then(|h| self.blocks.candidate(h));
        }
        for ((o, k), c) in out.iter_mut().zip(keys).zip(&candidates) {
            *o = k.and_then(|k| self.blocks.confirm(k, *c)).map(|s| &*s.block);
        }
    }

    /// A block with its [`BlockSummary`] (computed now if no reader asked since it changed).
    pub fn block_with_summary(&self, key: BlockKey) -> Option<(&BlockEvidence, BlockSummary)> {
        self.blocks
            .get(&key)
            .map(|s| (&*s.block, *s.summary.get_or_init(|| BlockSummary::of(&s.block, &self.params))))
    }

    /// A shared handle to one block (cheap: a reference count).
    pub fn block_arc(&self, key: BlockKey) -> Option<Arc<BlockEvidence>> {
        self.blocks.get(&key).map(|s| s.block.clone())
    }

    /// Blocks in table order (callers that emit anything sort first; see [`Self::block_keys_sorted`]).
    pub fn blocks_unsorted(&self) -> impl Iterator<Item = (&BlockKey, &BlockEvidence)> {
        self.blocks.iter().map(|(k, s)| (k, &*s.block))
    }

    pub fn block_keys_sorted(&self) -> Vec<BlockKey> {
        let mut keys: Vec<BlockKey> = self.blocks.keys().copied().collect();
        keys.sort_unstable();
        keys
    }

    pub fn evidence(&self, cell: CellKey) -> Evidence {
        match self.blocks.get(&cell.block()) {
            Some(s) => s.block.get(cell.index_in_block()),
            None => Evidence::default(),
        }
    }

    pub fn estimate(&self, cell: CellKey, th: &Thresholds) -> CellEstimate {
        CellEstimate::from_evidence(self.evidence(cell), &self.params, th)
    }

    /// Replaces blocks (from [`Self::blocks_after`]); `None` removes a block.
    pub fn set_blocks(&mut self, blocks: Vec<(BlockKey, Option<Arc<BlockEvidence>>)>) {
        for (key, b) in blocks {
            self.changes.note(key);
            match b {
                Some(b) => self.blocks.insert(key, Slot::new(b)),
                None => self.blocks.remove(&key),
            };
        }
    }

    /// Inserts a whole block (used by the store when loading). Empty blocks are not kept.
    pub fn insert_block(&mut self, key: BlockKey, block: Box<BlockEvidence>) {
        self.changes.note(key);
        if block.is_empty() {
            self.blocks.remove(&key);
        } else {
            self.blocks.insert(key, Slot::new(Arc::from(block)));
        }
    }

    /// Inserts a block shared with another map (copied on its first write). Empty blocks are
    /// not kept.
    pub fn insert_shared_block(&mut self, key: BlockKey, block: Arc<BlockEvidence>) {
        self.changes.note(key);
        if block.is_empty() {
            self.blocks.remove(&key);
        } else {
            self.blocks.insert(key, Slot::new(block));
        }
    }

    /// Makes blocks `keys` what they are in `other` (shared with it, summaries and all; absent
    /// where `other` has none). A snapshot kept from an earlier version of `other` is brought
    /// up to date this way in the time of what changed since, not of the whole map.
    pub fn copy_blocks_from(&mut self, other: &EvidenceMap, keys: &[BlockKey]) {
        for &key in keys {
            self.changes.note(key);
            match other.blocks.get(&key) {
                Some(slot) => self.blocks.insert(key, slot.clone()),
                None => self.blocks.remove(&key),
            };
        }
    }

    /// The map's blocks, taken apart.
    pub(crate) fn into_blocks(self) -> impl Iterator<Item = (BlockKey, Arc<BlockEvidence>)> {
        self.blocks.into_iter().map(|(key, slot)| (key, slot.block))
    }

    /// True when both maps hold the same blocks with the same evidence, cell by cell (tests).
    #[cfg(test)]
    pub(crate) fn same_blocks_as(&self, other: &EvidenceMap) -> bool {
        self.block_keys_sorted() == other.block_keys_sorted()
            && self.block_keys_sorted().into_iter().all(|k| self.block(k) == other.block(k))
    }

    /// True when both maps hold the same keys and share every block (not merely equal ones):
    /// what a map and a fresh clone of it satisfy.
    pub fn shares_blocks_with(&self, other: &EvidenceMap) -> bool {
        self.params == other.params
            && self.blocks.len() == other.blocks.len()
            && self
                .blocks
                .iter()
                .all(|(k, s)| other.blocks.get(k).is_some_and(|o| Arc::ptr_eq(&s.block, &o.block)))
    }
}
