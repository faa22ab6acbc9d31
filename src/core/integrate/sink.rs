//! Where the pipeline adds evidence in place: the [`BlockSink`] trait, and the map's side of it.
//!
//! The trait lives with the pipeline rather than with the map because it speaks the pipeline's
//! language (a sink also takes a [`ScanDelta`]); the model's [`EvidenceMap`] and the pipeline's
//! `MapEdit` implement it.

use super::delta::ScanDelta;
use crate::core::block::BlockEvidence;
use crate::core::key::BlockKey;
use crate::core::map::{EvidenceMap, Slot};
use std::sync::Arc;

/// A zero block shared by every caller on this thread (one per thread, so workers do not
/// contend on its reference count): what a map entry holds while its block is taken out.
fn placeholder_block() -> Arc<BlockEvidence> {
    thread_local! {
        static ZERO: Arc<BlockEvidence> = BlockEvidence::zeroed_arc(false);
    }
    ZERO.with(Arc::clone)
}

/// Somewhere a scan's evidence can be added in place, block by block: the map itself or an
/// edit of it. The fast evidence path takes each block it adds to out, changes it (copying it
/// first only if a snapshot shares it) and puts it back, so no per-scan delta is built.
pub trait BlockSink {
    /// Block `key` with its current content (zero if it has none), taken out to be changed;
    /// `wide` says a new block will receive hit mass (a hint: blocks the sink has are taken as
    /// they are, and [`BlockEvidence::make_mut`] widens them).
    fn take_block(&mut self, key: BlockKey, wide: bool) -> Arc<BlockEvidence>;
    /// Puts back a block taken with [`Self::take_block`] after adding evidence to it (so it
    /// holds some: the fast path takes a block only to add mass to it).
    fn put_block(&mut self, key: BlockKey, block: Arc<BlockEvidence>);
    /// Adds (`sign` ≥ 0) or subtracts (`sign` < 0) a scan's delta.
    fn add_delta(&mut self, delta: &ScanDelta, sign: i64);

    /// Block `key` taken out (as [`Self::take_block`]) if the sink has one; `None`, changing
    /// nothing, if it has none.
    fn take_existing_block(&mut self, key: BlockKey) -> Option<Arc<BlockEvidence>>;

    /// Adds a whole block of evidence (another map's, so it holds some) to block `key`; a
    /// block the sink lacks is taken as it is.
    fn add_whole_block(&mut self, key: BlockKey, mut block: Arc<BlockEvidence>) {
        match self.take_existing_block(key) {
            Some(mut mine) => {
                add_whole(&mut mine, &mut block);
                self.put_block(key, mine);
            }
            // Not an emptiness test first: a map's blocks hold evidence, and reading all of
            // one (up to 8 KiB, a block another core has just written) was about a quarter of
            // adding a worker's map in.
            None => self.put_block(key, block),
        }
    }
}

/// `mine += theirs`, leaving the sum in `mine`: added into `theirs` instead (and swapped) where
/// `theirs` is not shared and `mine` is (a snapshot's) or is narrow where `theirs` is wide, so
/// no block is copied or widened that need not be; the sum is the same integers either way.
pub(crate) fn add_whole(mine: &mut Arc<BlockEvidence>, theirs: &mut Arc<BlockEvidence>) {
    let theirs_better = (theirs.is_wide() && !mine.is_wide()) || Arc::get_mut(mine).is_none();
    if theirs_better && Arc::get_mut(theirs).is_some() {
        std::mem::swap(mine, theirs);
    }
    BlockEvidence::make_mut(mine, theirs.is_wide()).add_scaled(theirs, 1);
}

impl BlockSink for EvidenceMap {
    fn take_block(&mut self, key: BlockKey, wide: bool) -> Arc<BlockEvidence> {
        // `put_block` notes the change. The entry stays, holding a shared zero block until
        // `put_block` returns the block: a block that is only updated costs two lookups and no
        // change to the table's layout (removing and re-inserting moved another entry and its
        // slot each time).
        match self.blocks.get_mut(&key) {
            Some(s) => std::mem::replace(&mut s.block, placeholder_block()),
            None => BlockEvidence::zeroed_arc(wide),
        }
    }

    fn put_block(&mut self, key: BlockKey, block: Arc<BlockEvidence>) {
        // Not `insert_shared_block`: its emptiness test reads the whole block (4 or 8 KiB), and a
        // block put back here holds evidence (2% of sample-scan ingest).
        debug_assert!(!block.is_empty(), "a block is put back without evidence");
        self.changes.note(key);
        self.blocks.insert(key, Slot::new(block));
    }

    fn add_delta(&mut self, delta: &ScanDelta, sign: i64) {
        self.apply(delta, sign);
    }

    fn take_existing_block(&mut self, key: BlockKey) -> Option<Arc<BlockEvidence>> {
        self.blocks.get_mut(&key).map(|s| std::mem::replace(&mut s.block, placeholder_block()))
    }
}

impl EvidenceMap {
    /// Adds every block of this map into `sink` ([`BlockSink::add_whole_block`]: moved in where
    /// `sink` has none): how maps of per-thread work go into the map they were for.
    pub fn add_into<K: BlockSink + ?Sized>(self, sink: &mut K) {
        for (key, block) in self.into_blocks() {
            sink.add_whole_block(key, block);
        }
    }

    /// Adds another map's evidence cell by cell (exact). Parameters must be equal.
    pub fn merge_from(&mut self, other: &EvidenceMap) -> Result<(), Vec<String>> {
        let diff = self.params.differences(&other.params);
        if !diff.is_empty() {
            return Err(diff);
        }
        for (key, b) in other.blocks.iter() {
            self.add_whole_block(*key, b.block.clone());
        }
        Ok(())
    }
}
