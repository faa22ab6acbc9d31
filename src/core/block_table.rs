//! The map's block table: block key → value, open addressing that a batch of lookups can
//! prefetch stage by stage.
//!
//! Values live in one dense vector of `(key, value)` entries, one to a cache line ([`Entry`]).
//! Slots are two parallel arrays, linear probing at a load of at most ½: a tag byte (0 = empty,
//! else 0x80 | 7 bits of the key's hash) and the entry's index (`u32`). A lookup reads the tags 8
//! at a time (one `u64`, matched bytewise without branches; the first 8 tags are mirrored past the
//! end so a group never wraps) up to the first empty one, then the index of each matching slot,
//! then compares the entry's key. The tags are small (one byte per slot, 64 KiB for 32k blocks), so
//! they stay in cache: a key that is absent — most of the blocks a ray enters — costs no miss and
//! one well-predicted branch, as in a SwissTable.
//!
//! Why not a general hash map: a point query on a large map makes three dependent cache
//! misses (table slot, entry, cell). A general map hides where its slot lies, so a batch of
//! lookups can only overlap the misses as far as the CPU's reorder window reaches. Here the
//! slot of a key is known from its hash alone, so a batch prefetches all its slots, then all
//! its entries, then all its cells ([`BlockTable::home`], [`BlockTable::candidate`],
//! [`BlockTable::confirm`]).
//!
//! Removal swaps the last entry into the hole (and repoints its slot) and closes the probe
//! run behind the removed slot (backward shift), so no tombstones accumulate. Both touch other
//! entries, so the map's ingest does not remove a block to change it: it swaps the block out
//! and back in place ([`crate::core::BlockSink::take_block`]). Iteration order
//! is the entries' order, which depends on the order of inserts and removes: callers that emit
//! anything sort first.

use super::key::BlockKey;

const MIN_SLOTS: usize = 16;
/// Tags read per probe step.
const GROUP: usize = 8;
const LOW7: u64 = 0x7F7F_7F7F_7F7F_7F7F;
const HIGH: u64 = 0x8080_8080_8080_8080;

/// A key's 64-bit multiplicative (Fibonacci) hash: the home slot is its top bits, the tag the
/// 7 bits below them (the product's high bits depend on every bit of the key; one multiply
/// keeps the lookup's dependency chain short).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct KeyHash(u64);

impl KeyHash {
    #[inline(always)]
    pub fn of(key: BlockKey) -> Self {
        let packed =
            (u64::from(key.x as u32) << 42) ^ (u64::from(key.y as u32) << 21) ^ u64::from(key.z as u32);
        Self(packed.wrapping_mul(0x9E37_79B9_7F4A_7C15))
    }
}

/// Block key → value, see the module docs.
#[derive(Debug, Clone)]
pub struct BlockTable<V> {
    /// Per slot: 0 (empty) or the tag of the key whose entry `index` names; then a copy of
    /// the first [`GROUP`] tags.
    tags: Vec<u8>,
    index: Vec<u32>,
    entries: Vec<Entry<V>>,
}

/// A key and its value, one entry to a cache line, so that the one prefetch of
/// [`BlockTable::candidate`] brings in everything a lookup then reads.
///
/// Aligned to 64 bytes because an unaligned 56-byte entry straddles a line at three of its
/// eight offsets, and the block pointer in the second, unprefetched line then stalls the
/// lookup before its cell can be prefetched (aligned, point queries run ~4–5% faster). It
/// costs 8 bytes a block, 0.016 per cell.
#[derive(Debug, Clone)]
#[repr(C, align(64))]
pub struct Entry<V>(BlockKey, V);

impl<V> Default for BlockTable<V> {
    fn default() -> Self {
        Self { tags: Vec::new(), index: Vec::new(), entries: Vec::new() }
    }
}

impl<V> BlockTable<V> {
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Bytes of table per entry at the worst load just after growing (¼): one entry and four
    /// slots (tag and index). For memory figures.
    pub const WORST_BYTES_PER_ENTRY: usize = std::mem::size_of::<Entry<V>>() + 4 * (1 + 4);

    #[inline(always)]
    fn mask(&self) -> usize {
        self.index.len().wrapping_sub(1)
    }

    /// log2 of the slot count (at least 4 whenever there are slots; callers check for none).
    #[inline(always)]
    fn bits(&self) -> u32 {
        self.index.len().trailing_zeros()
    }

    /// The home slot of a hash.
    #[inline(always)]
    fn home_slot(&self, h: KeyHash) -> usize {
        (h.0 >> (64 - self.bits().max(1))) as usize & self.mask()
    }

    /// The slot tag of a hash: never 0 (empty).
    #[inline(always)]
    fn tag(&self, h: KeyHash) -> u8 {
        0x80 | (h.0 >> (57 - self.bits().min(57))) as u8 & 0x7F
    }

    /// The slot holding `key`'s entry, if any.
    #[inline]
    fn find_slot(&self, key: BlockKey, h: KeyHash) -> Option<usize> {
        self.probe(h, |s| self.entries[self.index[s] as usize].0 == key)
    }

    /// Walks `h`'s probe run a group of tags at a time: `hit` gets each slot whose tag matches,
    /// in probe order, until it says yes (that slot is the answer) or the run ends at an empty
    /// slot (`None`).
    #[inline(always)]
    fn probe(&self, h: KeyHash, mut hit: impl FnMut(usize) -> bool) -> Option<usize> {
        if self.index.is_empty() {
            return None;
        }
        let mask = self.mask();
        let pattern = u64::from(self.tag(h)) * 0x0101_0101_0101_0101;
        let mut i = self.home_slot(h);
        loop {
            let mut group = [0u8; GROUP];
            group.copy_from_slice(&self.tags[i..i + GROUP]);
            let word = u64::from_le_bytes(group);
            // High bit of each byte: set where the tag equals ours (x's byte is 0; no carry
            // crosses bytes), and where the slot is empty (tags in use have it set).
            let x = word ^ pattern;
            let matches = !(((x & LOW7) + LOW7) | x) & HIGH;
            let empties = !word & HIGH;
            // Only the slots before the first empty one belong to the run.
            let mut m = matches & (empties.wrapping_sub(1) & !empties);
            while m != 0 {
                let s = (i + m.trailing_zeros() as usize / 8) & mask;
                if hit(s) {
                    return Some(s);
                }
                m &= m - 1;
            }
            if empties != 0 {
                return None;
            }
            i = (i + GROUP) & mask;
        }
    }

    /// The index of `key`'s entry, if any.
    #[inline]
    fn find_entry(&self, key: BlockKey, h: KeyHash) -> Option<usize> {
        self.find_slot(key, h).map(|i| self.index[i] as usize)
    }

    #[inline]
    pub fn get(&self, key: &BlockKey) -> Option<&V> {
        let e = self.find_entry(*key, KeyHash::of(*key))?;
        Some(&self.entries[e].1)
    }

    #[inline]
    pub fn get_mut(&mut self, key: &BlockKey) -> Option<&mut V> {
        let e = self.find_entry(*key, KeyHash::of(*key))?;
        Some(&mut self.entries[e].1)
    }

    /// The value of `key`, inserted from `make` if absent.
    pub fn get_or_insert_with(&mut self, key: BlockKey, make: impl FnOnce() -> V) -> &mut V {
        let h = KeyHash::of(key);
        let e = match self.find_entry(key, h) {
            Some(e) => e,
            None => self.push(key, h, make()),
        };
        &mut self.entries[e].1
    }

    /// Inserts or replaces; returns the value replaced.
    pub fn insert(&mut self, key: BlockKey, value: V) -> Option<V> {
        let h = KeyHash::of(key);
        match self.find_entry(key, h) {
            Some(e) => Some(std::mem::replace(&mut self.entries[e].1, value)),
            None => {
                self.push(key, h, value);
                None
            }
        }
    }

    /// Appends an entry for a key known to be absent; returns its index.
    fn push(&mut self, key: BlockKey, h: KeyHash, value: V) -> usize {
        if 2 * (self.entries.len() + 1) > self.index.len() {
            self.grow();
        }
        let e = self.entries.len();
        assert!(e < u32::MAX as usize, "block table full");
        self.entries.push(Entry(key, value));
        self.place(h, e);
        e
    }

    /// Writes entry `e` into the first empty slot of `h`'s probe run.
    #[inline]
    fn place(&mut self, h: KeyHash, e: usize) {
        let mask = self.mask();
        let mut i = self.home_slot(h);
        while self.tags[i] != 0 {
            i = (i + 1) & mask;
        }
        self.set_tag(i, self.tag(h));
        self.index[i] = e as u32;
    }

    /// Sets slot `i`'s tag (and its mirror).
    #[inline(always)]
    fn set_tag(&mut self, i: usize, t: u8) {
        self.tags[i] = t;
        if i < GROUP {
            let n = self.index.len();
            self.tags[n + i] = t;
        }
    }

    fn grow(&mut self) {
        let n = (self.index.len() * 2).max(MIN_SLOTS);
        self.tags.clear();
        self.tags.resize(n + GROUP, 0);
        self.index.clear();
        self.index.resize(n, 0);
        for e in 0..self.entries.len() {
            self.place(KeyHash::of(self.entries[e].0), e);
        }
    }

    pub fn remove(&mut self, key: &BlockKey) -> Option<V> {
        let i = self.find_slot(*key, KeyHash::of(*key))?;
        let e = self.index[i] as usize;
        self.clear_slot(i);
        let last = self.entries.len() - 1;
        if e != last {
            // The last entry moves into the hole: repoint its slot.
            let moved = KeyHash::of(self.entries[last].0);
            let mask = self.mask();
            let mut j = self.home_slot(moved);
            while !(self.tags[j] != 0 && self.index[j] as usize == last) {
                j = (j + 1) & mask;
            }
            self.index[j] = e as u32;
        }
        Some(self.entries.swap_remove(e).1)
    }

    /// Empties slot `i` and shifts later slots of the probe run back, so every remaining entry
    /// stays reachable from its home slot without tombstones.
    fn clear_slot(&mut self, mut i: usize) {
        let mask = self.mask();
        let mut j = i;
        loop {
            self.set_tag(i, 0);
            loop {
                j = (j + 1) & mask;
                if self.tags[j] == 0 {
                    return;
                }
                let home = self.home_slot(KeyHash::of(self.entries[self.index[j] as usize].0));
                // Slot j's entry may move to i unless its home lies cyclically in (i, j].
                let stays = if i <= j { i < home && home <= j } else { i < home || home <= j };
                if !stays {
                    self.set_tag(i, self.tags[j]);
                    self.index[i] = self.index[j];
                    i = j;
                    break;
                }
            }
        }
    }

    pub fn iter(&self) -> impl Iterator<Item = (&BlockKey, &V)> {
        self.entries.iter().map(|Entry(k, v)| (k, v))
    }

    pub fn keys(&self) -> impl Iterator<Item = &BlockKey> {
        self.entries.iter().map(|Entry(k, _)| k)
    }

    pub fn values(&self) -> impl Iterator<Item = &V> {
        self.entries.iter().map(|Entry(_, v)| v)
    }

    /// Batched lookups, stage 1: `key`'s hash, with its home slot prefetched.
    #[inline(always)]
    pub fn home(&self, key: BlockKey) -> KeyHash {
        let h = KeyHash::of(key);
        if !self.index.is_empty() {
            let i = self.home_slot(h);
            crate::core::prefetch::prefetch(&self.tags[i]);
            crate::core::prefetch::prefetch(&self.index[i]);
        }
        h
    }

    /// Stage 2: the entry that probably holds the key of hash `h` (the first slot of its run
    /// whose tag matches), with that entry prefetched; `None` when the key is absent.
    #[inline(always)]
    pub fn candidate(&self, h: KeyHash) -> Option<u32> {
        let e = self.index[self.probe(h, |_| true)?];
        crate::core::prefetch::prefetch(&self.entries[e as usize]);
        Some(e)
    }

    /// Stage 3: `key`'s value from its [`Self::candidate`] (a full lookup if the tag matched
    /// another key's).
    #[inline(always)]
    pub fn confirm(&self, key: BlockKey, candidate: Option<u32>) -> Option<&V> {
        let Entry(k, v) = &self.entries[candidate? as usize];
        if *k == key { Some(v) } else { self.get(&key) }
    }
}

impl<V> IntoIterator for BlockTable<V> {
    type Item = (BlockKey, V);
    type IntoIter = std::iter::Map<std::vec::IntoIter<Entry<V>>, fn(Entry<V>) -> (BlockKey, V)>;

    fn into_iter(self) -> Self::IntoIter {
        self.entries.into_iter().map(|Entry(k, v)| (k, v))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::HashMap;

    #[derive(Debug, Clone)]
    enum Op {
        Insert(BlockKey, u32),
        Remove(BlockKey),
        GetOrInsert(BlockKey, u32),
    }

    /// Keys from a small cube, so inserts, replacements and removals of the same keys mix and
    /// probe runs wrap around the slot array.
    fn key() -> impl Strategy<Value = BlockKey> {
        (-4i32..4, -4i32..4, -3i32..3).prop_map(|(x, y, z)| BlockKey::new(x, y, z))
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            3 => (key(), any::<u32>()).prop_map(|(k, v)| Op::Insert(k, v)),
            2 => key().prop_map(Op::Remove),
            1 => (key(), any::<u32>()).prop_map(|(k, v)| Op::GetOrInsert(k, v)),
        ]
    }

    proptest! {
        /// After any sequence of operations the table answers like a `HashMap`, through plain
        /// lookups and through the three batched stages, for present and absent keys alike.
        #[test]
        fn behaves_like_a_hash_map(ops in proptest::collection::vec(op(), 0..600)) {
            let mut t = BlockTable::default();
            let mut m = HashMap::new();
            for op in ops {
                match op {
                    Op::Insert(k, v) => prop_assert_eq!(t.insert(k, v), m.insert(k, v)),
                    Op::Remove(k) => prop_assert_eq!(t.remove(&k), m.remove(&k)),
                    Op::GetOrInsert(k, v) => {
                        prop_assert_eq!(*t.get_or_insert_with(k, || v), *m.entry(k).or_insert(v))
                    }
                }
                prop_assert_eq!(t.len(), m.len());
            }
            for x in -5..5 {
                for y in -5..5 {
                    for z in -4..4 {
                        let k = BlockKey::new(x, y, z);
                        prop_assert_eq!(t.get(&k), m.get(&k));
                        let staged = t.confirm(k, t.candidate(t.home(k)));
                        prop_assert_eq!(staged, m.get(&k));
                    }
                }
            }
            let mut listed: Vec<_> = t.iter().map(|(k, v)| (*k, *v)).collect();
            let mut expected: Vec<_> = m.into_iter().collect();
            listed.sort_unstable();
            expected.sort_unstable();
            prop_assert_eq!(listed, expected);
        }
    }

    #[test]
    fn every_entry_starts_a_cache_line() {
        // A value of 40 bytes, as the map's (block pointer and ray summary), beside its key.
        let mut t = BlockTable::default();
        for x in 0..100 {
            t.insert(BlockKey::new(x, -x, 7), [x as u64; 5]);
        }
        assert_eq!(std::mem::size_of::<Entry<[u64; 5]>>(), 64);
        for e in &t.entries {
            assert_eq!(e as *const Entry<[u64; 5]> as usize % 64, 0);
        }
    }

    #[test]
    fn a_tag_match_of_another_key_falls_back_to_a_full_lookup() {
        let mut t = BlockTable::default();
        let (a, b) = (BlockKey::new(1, 2, 3), BlockKey::new(-7, 0, 9));
        t.insert(a, 'a');
        t.insert(b, 'b');
        // Stage 3 given the wrong entry (as a tag collision would) still finds b.
        let wrong = t.candidate(KeyHash::of(a));
        assert_eq!(t.confirm(b, wrong), Some(&'b'));
        assert_eq!(t.confirm(BlockKey::new(0, 0, 0), wrong), None);
    }

    #[test]
    fn an_empty_table_answers_none_at_every_stage() {
        let t = BlockTable::<u8>::default();
        let k = BlockKey::new(0, 0, 0);
        assert_eq!(t.get(&k), None);
        assert_eq!(t.confirm(k, t.candidate(t.home(k))), None);
    }
}
