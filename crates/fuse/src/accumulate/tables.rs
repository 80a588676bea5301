//! The exact-sum containers: W's blocks of per-Gaussian entry chains, the (Gaussian, group,
//! sum) records of a tile, and the small hash table that sums a tile's hits in L1.

use super::*;

/// One nonzero W[g, group]: its exact sum (as two halves: 24 bytes, not a 16-aligned 32)
/// and the next entry of the same Gaussian.
#[derive(Debug, Clone, Copy)]
pub(super) struct Entry {
    pub(super) lo: u64,
    pub(super) hi: u64,
    pub(super) group: u32,
    pub(super) next: u32,
}

impl Entry {
    #[inline]
    pub(super) fn sum(&self) -> u128 {
        u128::from(self.lo) | (u128::from(self.hi) << 64)
    }

    #[inline]
    pub(super) fn add(&mut self, q: u128) {
        let (lo, carry) = self.lo.overflowing_add(q as u64);
        self.lo = lo;
        self.hi = self.hi.wrapping_add((q >> 64) as u64 + u64::from(carry));
    }
}

/// The Gaussians of one block, each with a linked list of its entries.
#[derive(Debug, Default)]
pub(super) struct Block {
    pub(super) head: Vec<u32>,
    pub(super) entries: Vec<Entry>,
    pub(super) overflow: bool,
}

impl Block {
    pub(super) fn new(len: usize) -> Self {
        Block {
            head: vec![END; len],
            entries: Vec::new(),
            overflow: false,
        }
    }

    /// W[g, group] += q, with `local` = g's index in the block. A Gaussian has a handful
    /// of groups, so the list walk is short.
    #[inline]
    pub(super) fn add(&mut self, local: usize, group: u32, q: u128) {
        let first = self.head[local];
        let mut e = first;
        while e != END {
            let entry = &mut self.entries[e as usize];
            if entry.group == group {
                entry.add(q);
                return;
            }
            e = entry.next;
        }
        if self.entries.len() >= END as usize {
            self.overflow = true;
            return;
        }
        self.head[local] = self.entries.len() as u32;
        self.entries.push(Entry {
            lo: q as u64,
            hi: (q >> 64) as u64,
            group,
            next: first,
        });
    }

    /// Gaussian `local`'s entries, sorted by group.
    pub(super) fn row(&self, local: usize, out: &mut Vec<(u32, u128)>) {
        out.clear();
        let mut e = self.head[local];
        while e != END {
            let entry = self.entries[e as usize];
            out.push((entry.group, entry.sum()));
            e = entry.next;
        }
        out.sort_unstable_by_key(|(group, _)| *group);
    }

    pub(super) fn row_len(&self, local: usize) -> u64 {
        let mut n = 0;
        let mut e = self.head[local];
        while e != END {
            n += 1;
            e = self.entries[e as usize].next;
        }
        n
    }

    pub(super) fn heap_bytes(&self) -> usize {
        self.head.capacity() * std::mem::size_of::<u32>()
            + self.entries.capacity() * std::mem::size_of::<Entry>()
    }
}

/// A tile's partial sum of W[g, group] (the sum as two halves keeps the record 8-aligned).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Record {
    pub(super) g: u32,
    pub(super) group: u32,
    pub(super) lo: u64,
    pub(super) hi: u64,
}

impl Record {
    #[inline]
    pub(super) fn sum(&self) -> u128 {
        u128::from(self.lo) | (u128::from(self.hi) << 64)
    }
}

/// Open-addressing table summing one tile's hits per (Gaussian, group).
///
/// A slot holds its key and both halves of its sum, so a probe touches one cache line;
/// the fixed-size arrays and the masked index let the probe loop run without bounds
/// checks (it is the innermost loop of registration: one probe per hit).
#[derive(Debug)]
pub(super) struct TileTable {
    pub(super) slots: Box<[Slot; TABLE_SLOTS]>,
    pub(super) used: Box<[u16; TABLE_SLOTS / 2]>,
    pub(super) len: usize,
}

/// One slot of a [`TileTable`]: `key` = (Gaussian << 32) | group, or `EMPTY`.
#[derive(Debug, Clone, Copy)]
pub(super) struct Slot {
    pub(super) key: u64,
    pub(super) lo: u64,
    pub(super) hi: u64,
}

impl Default for TileTable {
    fn default() -> Self {
        Self::new()
    }
}

impl TileTable {
    pub(super) const EMPTY: u64 = u64::MAX;

    pub(super) fn new() -> Self {
        let empty = Slot {
            key: Self::EMPTY,
            lo: 0,
            hi: 0,
        };
        TileTable {
            slots: Box::new([empty; TABLE_SLOTS]),
            used: Box::new([0; TABLE_SLOTS / 2]),
            len: 0,
        }
    }

    #[inline(always)]
    pub(super) fn add(&mut self, g: u32, group: u32, q: u64, out: &mut Vec<Record>) {
        let key = (u64::from(g) << 32) | u64::from(group);
        let mut i = (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 54) as usize & (TABLE_SLOTS - 1);
        loop {
            let slot = &mut self.slots[i];
            if slot.key == key {
                let (lo, carry) = slot.lo.overflowing_add(q);
                slot.lo = lo;
                slot.hi += u64::from(carry);
                return;
            }
            if slot.key == Self::EMPTY {
                *slot = Slot { key, lo: q, hi: 0 };
                self.used[self.len] = i as u16;
                self.len += 1;
                if self.len == TABLE_SLOTS / 2 {
                    self.flush(out);
                }
                return;
            }
            i = (i + 1) & (TABLE_SLOTS - 1);
        }
    }

    pub(super) fn flush(&mut self, out: &mut Vec<Record>) {
        for &i in &self.used[..self.len] {
            let slot = &mut self.slots[usize::from(i) & (TABLE_SLOTS - 1)];
            out.push(Record {
                g: (slot.key >> 32) as u32,
                group: slot.key as u32,
                lo: slot.lo,
                hi: slot.hi,
            });
            slot.key = Self::EMPTY;
        }
        self.len = 0;
    }
}
