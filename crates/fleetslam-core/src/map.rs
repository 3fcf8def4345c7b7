//! The per-particle landmark map, persistent so that particles share what they have in common.
//!
//! Montemerlo's log(N) FastSLAM stores each particle's landmarks in a balanced tree whose
//! nodes are shared between particles: resampling copies a pointer, and updating one
//! landmark copies only the path from the root to it. [`LandmarkMap`] gets the same
//! behaviour from `rpds::Vector` (a persistent bit-partitioned trie of `Arc` nodes) with a
//! branching factor of 8: an update copies about log₈ M small nodes, a resample copies none.
//!
//! Slots are never reused within a particle: a removed (spurious) landmark leaves an empty
//! slot, so a slot number names one landmark for the life of the map.

use crate::updater::LandmarkGaussian;
use rpds::vector::VectorSync;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Branching factor 2^3 = 8: shallow enough to be fast, narrow enough that a copied node is
/// small.
const BITS: u8 = 3;

/// One landmark of one particle's map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    pub gaussian: LandmarkGaussian,
    /// The id given by observations, when association is by id.
    pub id: Option<u32>,
    /// Existence log-odds: raised when the landmark is observed, lowered when it was in view
    /// but not observed; the landmark is removed when it falls below zero.
    pub existence: f64,
    /// How many observations updated it.
    pub hits: u32,
}

/// A persistent map of landmark slots.
#[derive(Debug, Clone)]
pub struct LandmarkMap {
    slots: VectorSync<Option<Landmark>>,
    live: usize,
}

impl Default for LandmarkMap {
    fn default() -> Self {
        Self {
            slots: VectorSync::new_with_bits(BITS),
            live: 0,
        }
    }
}

impl PartialEq for LandmarkMap {
    fn eq(&self, other: &Self) -> bool {
        self.live == other.live && self.slots == other.slots
    }
}

impl LandmarkMap {
    pub fn new() -> Self {
        Self::default()
    }

    /// Number of slots (including removed ones).
    pub fn slots(&self) -> usize {
        self.slots.len()
    }

    /// Number of landmarks present.
    pub fn len(&self) -> usize {
        self.live
    }

    pub fn is_empty(&self) -> bool {
        self.live == 0
    }

    pub fn get(&self, slot: usize) -> Option<&Landmark> {
        self.slots.get(slot).and_then(|s| s.as_ref())
    }

    /// Adds a landmark in a new slot and returns the slot.
    pub fn push(&mut self, lm: Landmark) -> usize {
        self.slots.push_back_mut(Some(lm));
        self.live += 1;
        self.slots.len() - 1
    }

    /// Grows the map with empty slots up to `len` (known-id maps keep slot = id index).
    pub fn ensure_slots(&mut self, len: usize) {
        while self.slots.len() < len {
            self.slots.push_back_mut(None);
        }
    }

    /// Puts a landmark into `slot` (which must exist), replacing what was there.
    pub fn set(&mut self, slot: usize, lm: Landmark) {
        let was_live = self.get(slot).is_some();
        let ok = self.slots.set_mut(slot, Some(lm));
        debug_assert!(ok, "slot {slot} out of range");
        if ok && !was_live {
            self.live += 1;
        }
    }

    /// Removes the landmark in `slot`, leaving the slot empty.
    pub fn remove(&mut self, slot: usize) {
        if self.get(slot).is_some() {
            self.slots.set_mut(slot, None);
            self.live -= 1;
        }
    }

    /// Present landmarks with their slots.
    pub fn iter(&self) -> impl Iterator<Item = (usize, &Landmark)> {
        self.slots
            .iter()
            .enumerate()
            .filter_map(|(i, s)| s.as_ref().map(|l| (i, l)))
    }
}

impl Serialize for LandmarkMap {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.slots.iter())
    }
}

impl<'de> Deserialize<'de> for LandmarkMap {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let v: Vec<Option<Landmark>> = Vec::deserialize(d)?;
        let mut m = LandmarkMap::default();
        for s in v {
            if s.is_some() {
                m.live += 1;
            }
            m.slots.push_back_mut(s);
        }
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lm(x: f64) -> Landmark {
        Landmark {
            gaussian: LandmarkGaussian {
                mean: [x, 0.0, 0.0],
                cov: [1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
            },
            id: None,
            existence: 1.0,
            hits: 1,
        }
    }

    #[test]
    fn copies_are_independent() {
        let mut a = LandmarkMap::new();
        for i in 0..100 {
            a.push(lm(i as f64));
        }
        let mut b = a.clone();
        b.set(42, lm(-1.0));
        b.remove(7);
        assert_eq!(a.get(42).unwrap().gaussian.mean[0], 42.0);
        assert_eq!(b.get(42).unwrap().gaussian.mean[0], -1.0);
        assert!(a.get(7).is_some() && b.get(7).is_none());
        assert_eq!((a.len(), b.len(), b.slots()), (100, 99, 100));
        assert_eq!(b.iter().count(), 99);
    }

    #[test]
    fn serde_round_trip() {
        let mut a = LandmarkMap::new();
        a.push(lm(1.0));
        a.push(lm(2.0));
        a.remove(0);
        let json = serde_json::to_string(&a).unwrap();
        let b: LandmarkMap = serde_json::from_str(&json).unwrap();
        assert_eq!(a, b);
        assert_eq!(b.len(), 1);
    }

    #[test]
    fn ensure_slots_pads_with_empty() {
        let mut a = LandmarkMap::new();
        a.ensure_slots(5);
        assert_eq!((a.slots(), a.len()), (5, 0));
        a.set(3, lm(3.0));
        assert_eq!(a.len(), 1);
        assert_eq!(a.iter().next().unwrap().0, 3);
    }
}
