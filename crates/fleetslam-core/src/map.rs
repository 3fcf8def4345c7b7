//! The per-particle landmark map, persistent so that particles share what they have in common.
//!
//! Montemerlo's log(N) FastSLAM stores each particle's landmarks in a balanced tree whose
//! nodes are shared between particles: resampling copies a pointer, and updating one
//! landmark copies only the path from the root to it. [`LandmarkMap`] is such a tree: a
//! bit-partitioned trie whose branch nodes have [`BRANCH`] children behind `Arc`s and whose
//! leaves hold [`LEAF`] landmarks inline. Reading a landmark follows about log₈(M/4)
//! pointers; writing one copies the nodes of its path only where another map shares them
//! (`make_mut`), so a particle that updates the same leaf twice in a step copies it
//! once, and a resample copies nothing but the root pointer. Landmarks are not behind
//! pointers of their own: a leaf copy is one allocation, and freeing it touches no per
//! landmark counter. (`rpds`/`imbl` vectors either keep every element behind its own
//! reference count or copy 64-element chunks; neither fits a map written on every
//! observation.)
//!
//! Slots are never reused within a particle: a removed (spurious) landmark leaves an empty
//! slot, so a slot number names one landmark for the life of the map.
//!
//! The map also keeps a spatial index, persistent and shared like the trie: the slots of its
//! landmarks by ground-plane cell of [`INDEX_CELL`] metres (a hash trie from `rpds`, keyed by
//! `foldhash`'s fixed-seed hash: two integers need no SipHash), and a
//! list of the landmarks too uncertain to be placed in one cell ([`INDEX_WIDE_TRACE`]).
//! [`LandmarkMap::for_each_near`] visits the landmarks that may lie within a distance of a
//! point through it, so that association, merging and the existence pass cost O(k + log M)
//! for k landmarks nearby instead of O(M). The index only changes when a landmark is added,
//! removed, or moves to another cell (rare once it has converged), and it never changes which
//! landmarks a caller finds: it is derived from the landmarks and rebuilt when a map is read.
//! A map that is never searched by place (the filter's maps under known association, where
//! ids name the landmarks) keeps no index ([`LandmarkMap::without_index`]): its writes then
//! cost only the trie's path.
//!
//! A map serialises as the list of its slots. Maps that share nodes (a filter's particles)
//! serialise together through a node pool ([`MapPool`]), which writes each shared node
//! once and reads back maps that share what they shared.

use crate::updater::LandmarkGaussian;
use rpds::HashTrieMapSync;

mod pool;
pub use pool::{MAX_HEIGHT, MapPool, PoolError, PoolReader, PoolWriter, PooledMap};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::sync::Arc;
/// The handle of what maps share and copy on write (trie nodes, held existence values):
/// `triomphe`'s `Arc`, which has no weak count, so that `make_mut` on what this map alone
/// holds (every write of a path copied earlier in the step) is one load of the count, not
/// `std`'s compare-and-swap on it (a locked instruction, one per level of every landmark
/// write).
type CowArc<T> = triomphe::Arc<T>;

/// The value behind `a` for writing, copied first if another handle shares it:
/// `CowArc::make_mut` with its common case (the map alone holds the node: every write after
/// the first on a path in a step) inlined into the walk and the copy out of line. As a call,
/// `make_mut` cost about 20 instructions per trie level of every landmark write (README,
/// session 30).
#[inline(always)]
fn own<T: Clone>(a: &mut CowArc<T>) -> &mut T {
    if !a.is_unique() {
        copy_shared(a);
    }
    CowArc::get_mut(a).expect("a copy is held by this handle alone")
}

/// Replaces the shared value behind `a` with a copy of its own.
#[cold]
#[inline(never)]
fn copy_shared<T: Clone>(a: &mut CowArc<T>) {
    *a = CowArc::new(T::clone(a));
}

/// Side of a cell of the spatial index [m]. The index does not change results, only speed:
/// a query looks up each cell its disc overlaps (a lookup in the persistent hash trie costs
/// about 100 instructions) and visits the landmarks they hold, so larger cells mean fewer
/// lookups and more landmarks visited. On Victoria Park (association radii of several
/// metres, trees some 10 m apart) the filter's steps took 4,204 M instructions with 4 m
/// cells, 3,618 M with 8 m, 3,512 M with 12 m and 3,523 M with 16 m (`RAYON_NUM_THREADS=1
/// valgrind --tool=callgrind <filter_seeds> victoria --duration 200`; an earlier filter ran
/// the whole park in 7.2 s of CPU with 2 m cells against 6.3 s with 4 m); on the
/// association benchmark's 3 m lattice (`cargo bench -p fleetslam-core --bench
/// association`) 8 m cells cost about the same as 4 m up to M = 10,000 and 14 % more at
/// 100,000 (README, session 30).
pub const INDEX_CELL: f64 = 8.0;
/// Landmarks whose ground-plane position variance (`cov_xx + cov_yy`) exceeds this [m²],
/// or whose mean is not finite, are kept in a list that every query visits, because the
/// association radius grows with a landmark's own variance: a landmark in a cell is then
/// found by a query of the radius its caller computes with this bound.
pub const INDEX_WIDE_TRACE: f64 = 1.0;
/// Existence values the map holds apart from their landmarks at most ([`LandmarkMap::
/// set_existence`]); beyond that they are written into the trie. Bounds what a particle copy
/// costs beyond its pointers.
pub const PENDING_EXISTENCE: usize = 64;
/// A query that would visit more cells than the map has landmarks divided by this visits
/// every landmark instead (a cell lookup costs about as much as this many distance checks).
const CELL_LOOKUP_COST: f64 = 4.0;

/// Children of a branch node: 2^3.
pub const BRANCH: usize = 1 << BRANCH_BITS;
const BRANCH_BITS: u32 = 3;
/// Landmarks in a leaf: 2^2. Small, because an update copies its whole (shared) leaf.
pub const LEAF: usize = 1 << LEAF_BITS;
const LEAF_BITS: u32 = 2;

/// One landmark of one particle's map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    pub gaussian: LandmarkGaussian,
    /// The id given by observations, when association is by id.
    pub id: Option<u32>,
    /// Existence log-odds: raised when the landmark is observed, lowered when it was in view
    /// but not observed; the landmark is removed when it falls below zero. In a map, the
    /// current value is [`LandmarkMap::existence`]: this field may lag behind it.
    pub existence: f64,
    /// How many observations updated it.
    pub hits: u32,
}

#[derive(Debug, Clone)]
/// A node of the trie, behind its own `Arc` so that a branch holds 8 small handles (a copied
/// branch is 128 bytes, a copied leaf 4 landmarks).
enum Node {
    Branch(CowArc<[Option<Node>; BRANCH]>),
    Leaf(CowArc<[Option<Landmark>; LEAF]>),
}

impl Node {
    fn empty(leaf: bool) -> Node {
        if leaf {
            Node::Leaf(CowArc::new([None; LEAF]))
        } else {
            Node::Branch(CowArc::new(Default::default()))
        }
    }
}

/// Where the spatial index keeps a landmark.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Place {
    Cell(i32, i32),
    Wide,
}

impl Place {
    fn of(lm: &Landmark) -> Place {
        let g = &lm.gaussian;
        let trace = g.cov[0] + g.cov[3];
        if !(trace <= INDEX_WIDE_TRACE && g.mean[0].is_finite() && g.mean[1].is_finite()) {
            return Place::Wide;
        }
        Place::Cell(cell(g.mean[0]), cell(g.mean[1]))
    }
}

/// The cell coordinate of a ground-plane coordinate (saturating far away).
#[inline]
fn cell(v: f64) -> i32 {
    (v / INDEX_CELL).floor() as i32
}

/// The spatial index: slots by [`Place`]. The cells' lists are in a persistent hash trie;
/// the wide list, which every query visits, is held beside it, so that a query looks up only
/// the cells its disc overlaps (a lookup costs about 100 instructions; the wide list's were
/// 1.1 M of Victoria Park's 5.2 M lookups; README, session 30).
#[derive(Debug, Clone, Default)]
struct SpatialIndex {
    cells: HashTrieMapSync<(i32, i32), Arc<[u32]>, foldhash::fast::FixedState>,
    wide: Option<Arc<[u32]>>,
}

impl SpatialIndex {
    /// The slots kept at `place`.
    #[inline(always)]
    fn get(&self, place: Place) -> Option<&Arc<[u32]>> {
        match place {
            Place::Cell(x, y) => self.cells.get(&(x, y)),
            Place::Wide => self.wide.as_ref(),
        }
    }

    /// Keeps `list` at `place` (`None`: nothing).
    fn set(&mut self, place: Place, list: Option<Arc<[u32]>>) {
        match (place, list) {
            (Place::Cell(x, y), Some(l)) => {
                self.cells.insert_mut((x, y), l);
            }
            (Place::Cell(x, y), None) => {
                self.cells.remove_mut(&(x, y));
            }
            (Place::Wide, l) => self.wide = l,
        }
    }

    #[cfg(test)]
    fn is_empty(&self) -> bool {
        self.cells.is_empty() && self.wide.is_none()
    }

    /// Every place with its slots (cells in no particular order, then the wide list).
    #[cfg(test)]
    fn iter(&self) -> impl Iterator<Item = (Place, &Arc<[u32]>)> {
        self.cells
            .iter()
            .map(|(&(x, y), l)| (Place::Cell(x, y), l))
            .chain(self.wide.as_ref().map(|l| (Place::Wide, l)))
    }
}

/// Moves `slot` in `index` from place `a` to place `b` (`None`: not indexed).
fn move_in_index(index: &mut SpatialIndex, slot: usize, a: Option<Place>, b: Option<Place>) {
    if a == b {
        return;
    }
    let slot = slot as u32;
    if let Some(a) = a {
        match index.get(a) {
            Some(l) if l.len() == 1 => index.set(a, None),
            Some(l) => {
                let list: Arc<[u32]> = l.iter().copied().filter(|s| *s != slot).collect();
                index.set(a, Some(list));
            }
            None => debug_assert!(false, "slot {slot} missing from the index"),
        }
    }
    if let Some(b) = b {
        let list: Arc<[u32]> = match index.get(b) {
            Some(l) => l.iter().copied().chain([slot]).collect(),
            None => Arc::new([slot]),
        };
        index.set(b, Some(list));
    }
}

/// A persistent map of landmark slots.
#[derive(Debug, Clone, Default)]
pub struct LandmarkMap {
    root: Option<Node>,
    /// Branch levels above the leaves; the trie holds `LEAF · BRANCH^height` slots.
    height: u32,
    /// Number of slots (including empty ones).
    slots: usize,
    live: usize,
    /// The spatial index: slots by [`Place`].
    index: SpatialIndex,
    /// Existence values newer than their landmarks' `existence` field, by slot (sorted):
    /// the existence pass lowers the value of every landmark in view on every record, and
    /// writing each into the trie would copy its leaf (after a resample, its whole path).
    /// `None` when there are none (never an empty list), so that reading a landmark's
    /// existence in a map without any costs no trip to the heap.
    pending: Option<CowArc<Vec<(u32, f64)>>>,
    /// No spatial index is kept ([`LandmarkMap::without_index`]); `index` stays empty and
    /// [`LandmarkMap::for_each_near`] visits every landmark.
    unindexed: bool,
}

/// A hint to fetch the cache line holding `r` (no load, no effect on results).
#[inline(always)]
fn prefetch<T>(r: &T) {
    #[cfg(all(target_arch = "x86_64", target_feature = "sse"))]
    safe_arch::prefetch_t0(r);
    #[cfg(not(all(target_arch = "x86_64", target_feature = "sse")))]
    let _ = r;
}

impl PartialEq for LandmarkMap {
    /// Equal contents, with current existence values (however they are held).
    fn eq(&self, other: &Self) -> bool {
        self.slots == other.slots && self.live == other.live && self.current().eq(other.current())
    }
}

impl LandmarkMap {
    pub fn new() -> Self {
        Self::default()
    }

    /// An empty map that keeps no spatial index: for maps whose landmarks are found by slot
    /// only. [`LandmarkMap::for_each_near`] still finds the same landmarks, by visiting all.
    pub fn without_index() -> Self {
        Self {
            unindexed: true,
            ..Self::default()
        }
    }

    /// Stops keeping the spatial index (see [`LandmarkMap::without_index`]) and frees it.
    pub fn drop_index(&mut self) {
        self.unindexed = true;
        self.index = Default::default();
    }

    /// Whether the map keeps a spatial index.
    pub fn is_indexed(&self) -> bool {
        !self.unindexed
    }

    /// Number of slots (including removed ones).
    pub fn slots(&self) -> usize {
        self.slots
    }

    /// Number of landmarks present.
    pub fn len(&self) -> usize {
        self.live
    }

    pub fn is_empty(&self) -> bool {
        self.live == 0
    }

    fn capacity(height: u32) -> usize {
        LEAF << (BRANCH_BITS * height)
    }

    /// The child index of `slot` at branch `level` (0 = just above the leaves).
    #[inline]
    fn child(slot: usize, level: u32) -> usize {
        (slot >> (LEAF_BITS + BRANCH_BITS * level)) & (BRANCH - 1)
    }

    /// The landmark in `slot` (its `existence` field may lag: see
    /// [`LandmarkMap::existence`]).
    #[inline]
    pub fn get(&self, slot: usize) -> Option<&Landmark> {
        if slot >= self.slots {
            return None;
        }
        let mut node = self.root.as_ref()?;
        for level in (0..self.height).rev() {
            match node {
                Node::Branch(c) => node = c[Self::child(slot, level)].as_ref()?,
                Node::Leaf(_) => unreachable!("a leaf above the leaf level"),
            }
        }
        match node {
            Node::Leaf(l) => l[slot & (LEAF - 1)].as_ref(),
            Node::Branch(_) => unreachable!("a branch at the leaf level"),
        }
    }

    /// Asks the processor to fetch, without waiting for it, what lies `depth` levels below
    /// the root on the path to `slot`: the root node's entry on that path at depth 0, the
    /// slot's landmark at depth `height` (a larger `depth` counts as `height`). The `depth`
    /// nodes above it are read, so a caller walks a path down in stages, one level per call
    /// some work apart, each stage's node fetched by the one before
    /// ([`LandmarkMap::prefetch_stages`]).
    /// No effect on any result; nothing where the path is absent or the processor has no
    /// prefetch instruction.
    #[inline]
    pub fn prefetch_path(&self, slot: usize, depth: u32) {
        if slot >= self.slots {
            return;
        }
        let Some(mut node) = self.root.as_ref() else {
            return;
        };
        let walk = depth.min(self.height);
        for level in (self.height - walk..self.height).rev() {
            match node {
                Node::Branch(c) => match c[Self::child(slot, level)].as_ref() {
                    Some(n) => node = n,
                    None => return,
                },
                Node::Leaf(_) => return,
            }
        }
        match node {
            Node::Branch(c) => {
                prefetch(&c[Self::child(slot, self.height - walk - 1)]);
            }
            Node::Leaf(l) => prefetch(&l[slot & (LEAF - 1)]),
        }
    }

    /// How many stages [`LandmarkMap::prefetch_path`] takes to reach a landmark: one per
    /// branch level and one for the leaf.
    pub fn prefetch_stages(&self) -> u32 {
        self.height + 1
    }

    /// Grows the trie (a new root above the old one) until it can hold `len` slots.
    fn grow_to(&mut self, len: usize) {
        while Self::capacity(self.height) < len {
            if let Some(old) = self.root.take() {
                let mut c: [Option<Node>; BRANCH] = Default::default();
                c[0] = Some(old);
                self.root = Some(Node::Branch(CowArc::new(c)));
            }
            self.height += 1;
        }
    }

    /// The slot's cell for writing: the nodes of its path are copied where shared and
    /// created where missing. `slot` must be below `slots`.
    fn cell_mut(&mut self, slot: usize) -> &mut Option<Landmark> {
        debug_assert!(slot < self.slots);
        let height = self.height;
        let mut node = self.root.get_or_insert_with(|| Node::empty(height == 0));
        for level in (0..height).rev() {
            node = match node {
                Node::Branch(c) => {
                    own(c)[Self::child(slot, level)].get_or_insert_with(|| Node::empty(level == 0))
                }
                Node::Leaf(_) => unreachable!("a leaf above the leaf level"),
            };
        }
        match node {
            Node::Leaf(l) => &mut own(l)[slot & (LEAF - 1)],
            Node::Branch(_) => unreachable!("a branch at the leaf level"),
        }
    }

    /// Keeps the index in step with a slot whose landmark changed from `old` to `new`.
    fn reindex(&mut self, slot: usize, old: Option<&Landmark>, new: Option<&Landmark>) {
        if self.unindexed {
            return;
        }
        move_in_index(
            &mut self.index,
            slot,
            old.map(Place::of),
            new.map(Place::of),
        );
    }

    /// The existence values held apart, by slot (sorted).
    pub(crate) fn pending(&self) -> &[(u32, f64)] {
        self.pending.as_deref().map_or(&[], |v| v.as_slice())
    }

    fn pending_at(&self, slot: usize) -> Result<usize, usize> {
        self.pending().binary_search_by_key(&(slot as u32), |p| p.0)
    }

    /// Removes and returns the pending existence value of `slot`, if it has one (its
    /// landmark is being written whole). Inlined where the map holds none (every map under
    /// known association), which is then one test.
    #[inline(always)]
    fn take_pending(&mut self, slot: usize) -> Option<f64> {
        self.pending.as_ref()?;
        self.take_held(slot)
    }

    /// [`LandmarkMap::take_pending`] where the map holds values apart.
    fn take_held(&mut self, slot: usize) -> Option<f64> {
        let i = self.pending_at(slot).ok()?;
        let v = CowArc::make_mut(self.pending.as_mut()?);
        let (_, e) = v.remove(i);
        if v.is_empty() {
            self.pending = None;
        }
        Some(e)
    }

    /// The current existence log-odds of the landmark in `slot`.
    pub fn existence(&self, slot: usize) -> Option<f64> {
        self.get(slot).map(|l| self.current_existence(slot, l))
    }

    /// The current existence log-odds of `l`, the landmark read from `slot`: its held value
    /// if any ([`LandmarkMap::existence`] without reading the landmark again).
    pub fn current_existence(&self, slot: usize, l: &Landmark) -> f64 {
        match self.pending_at(slot) {
            Ok(i) => self.pending()[i].1,
            Err(_) => l.existence,
        }
    }

    /// Sets the existence log-odds of the landmark in `slot` (if present) without writing the
    /// landmark: the value is held apart (up to [`PENDING_EXISTENCE`] of them, then all are
    /// written into the trie) until the landmark is next written whole.
    pub fn set_existence(&mut self, slot: usize, e: f64) {
        if self.get(slot).is_none() {
            return;
        }
        let at = self.pending_at(slot);
        let v = CowArc::make_mut(self.pending.get_or_insert_with(Default::default));
        match at {
            Ok(i) => v[i].1 = e,
            Err(i) => v.insert(i, (slot as u32, e)),
        }
        if v.len() > PENDING_EXISTENCE {
            let held = std::mem::take(v);
            self.pending = None;
            for (s, e) in held {
                let cell = self.cell_mut(s as usize);
                if let Some(l) = cell {
                    l.existence = e;
                }
            }
        }
    }

    /// Present landmarks with their slots, in slot order, with their current existence.
    pub fn current(&self) -> impl Iterator<Item = (usize, Landmark)> + '_ {
        self.iter().map(|(s, l)| {
            let existence = self.current_existence(s, l);
            (s, Landmark { existence, ..*l })
        })
    }

    /// Adds a landmark in a new slot and returns the slot.
    pub fn push(&mut self, lm: Landmark) -> usize {
        let slot = self.slots;
        self.grow_to(slot + 1);
        self.slots += 1;
        *self.cell_mut(slot) = Some(lm);
        self.live += 1;
        self.reindex(slot, None, Some(&lm));
        slot
    }

    /// Grows the map with empty slots up to `len` (known-id maps keep slot = id index).
    pub fn ensure_slots(&mut self, len: usize) {
        if len > self.slots {
            self.grow_to(len);
            self.slots = len;
        }
    }

    /// Puts a landmark into `slot` (which must exist), replacing what was there.
    pub fn set(&mut self, slot: usize, lm: Landmark) {
        debug_assert!(slot < self.slots, "slot {slot} out of range");
        if slot >= self.slots {
            return;
        }
        self.take_pending(slot);
        let old = self.cell_mut(slot).replace(lm);
        if old.is_none() {
            self.live += 1;
        }
        self.reindex(slot, old.as_ref(), Some(&lm));
    }

    /// Rewrites the landmark in `slot` in place: `f` gets it with its `existence` field set to
    /// its current existence log-odds ([`LandmarkMap::current_existence`]; a value held apart
    /// is taken into the landmark) and changes what it will. `get` and `set` in one walk down
    /// the trie ([`LandmarkMap::get_mut`]), without copying the landmark out and back. An
    /// empty slot is left as it is.
    #[inline(always)]
    pub fn update(&mut self, slot: usize, f: impl FnOnce(&mut Landmark)) {
        if let Some(lm) = self.get_mut(slot) {
            lm.write(f);
        }
    }

    /// The landmark in `slot` opened for writing, `None` if the slot holds none: one walk
    /// down the trie that copies the nodes of the slot's path where another map shares them
    /// (for an empty slot no leaf is copied, though branches above it may be). The
    /// landmark's `existence` field is its current log-odds (a value held apart is taken
    /// into it, which changes no [`LandmarkMap::existence`]). Read it with
    /// [`LandmarkMut::get`] and change it with [`LandmarkMut::write`], which keeps the
    /// spatial index in step; a handle dropped unwritten leaves the landmark as it was. The
    /// filter reads each landmark it updates this way and writes its posterior after the
    /// updater's batch: one walk per update instead of a read and a write (README, session
    /// 30).
    #[inline(always)]
    pub fn get_mut(&mut self, slot: usize) -> Option<LandmarkMut<'_>> {
        if slot >= self.slots {
            return None;
        }
        // Only present landmarks have held values (`set_existence`), so taking it before the
        // walk loses nothing.
        let held = self.take_pending(slot);
        let mut node = self.root.as_mut()?;
        for level in (0..self.height).rev() {
            node = match node {
                Node::Branch(c) => {
                    let child = Self::child(slot, level);
                    c[child].as_ref()?;
                    own(c)[child].as_mut()?
                }
                Node::Leaf(_) => unreachable!("a leaf above the leaf level"),
            };
        }
        let lm = match node {
            Node::Leaf(l) => {
                let cell = slot & (LEAF - 1);
                l[cell].as_ref()?;
                own(l)[cell].as_mut()?
            }
            Node::Branch(_) => unreachable!("a branch at the leaf level"),
        };
        if let Some(e) = held {
            lm.existence = e;
        }
        let index = (!self.unindexed).then(|| (&mut self.index, Place::of(lm)));
        Some(LandmarkMut { lm, index, slot })
    }

    /// Removes the landmark in `slot`, leaving the slot empty.
    pub fn remove(&mut self, slot: usize) {
        if self.get(slot).is_some() {
            self.take_pending(slot);
            let old = self.cell_mut(slot).take();
            self.live -= 1;
            self.reindex(slot, old.as_ref(), None);
        }
    }

    /// Calls `f` with every landmark whose mean lies within `r` (ground plane) of `(x, y)`,
    /// and perhaps with others (those of the cells the disc overlaps, and those whose
    /// variance exceeds [`INDEX_WIDE_TRACE`]): each landmark at most once, in no particular
    /// order. The caller applies its own exact test. Always inlined, so that the caller's
    /// closure is compiled with the caller (the filter's steps: for their instruction set).
    #[inline(always)]
    pub fn for_each_near(&self, x: f64, y: f64, r: f64, mut f: impl FnMut(usize, &Landmark)) {
        let span = |v: f64| (cell(v - r), cell(v + r));
        let ((x0, x1), (y0, y1)) = (span(x), span(y));
        let cells = (f64::from(x1) - f64::from(x0) + 1.0) * (f64::from(y1) - f64::from(y0) + 1.0);
        if self.unindexed
            || !(r.is_finite() && x.is_finite() && y.is_finite())
            || cells * CELL_LOOKUP_COST >= self.live as f64
        {
            self.for_each(f);
            return;
        }
        for cx in x0..=x1 {
            for cy in y0..=y1 {
                self.visit_place(Place::Cell(cx, cy), &mut f);
            }
        }
        self.visit_place(Place::Wide, &mut f);
    }

    /// Calls `f` with the landmarks the index keeps at `place` (inlined with
    /// [`LandmarkMap::for_each_near`]).
    #[inline(always)]
    fn visit_place(&self, place: Place, f: &mut impl FnMut(usize, &Landmark)) {
        for &s in self.index.get(place).into_iter().flat_map(|l| l.iter()) {
            let s = s as usize;
            let l = self.get(s).expect("the index names present landmarks");
            f(s, l);
        }
    }

    /// Calls `f` with every present landmark and its slot, in slot order (a recursive walk:
    /// faster than [`LandmarkMap::iter`] when every landmark is wanted).
    pub fn for_each(&self, mut f: impl FnMut(usize, &Landmark)) {
        fn walk(node: &Node, base: usize, level: u32, f: &mut impl FnMut(usize, &Landmark)) {
            match node {
                Node::Leaf(l) => {
                    for (i, lm) in l.iter().enumerate() {
                        if let Some(lm) = lm {
                            f(base + i, lm);
                        }
                    }
                }
                Node::Branch(c) => {
                    let shift = LEAF_BITS + BRANCH_BITS * level;
                    for (i, child) in c.iter().enumerate() {
                        if let Some(n) = child {
                            walk(n, base + (i << shift), level.wrapping_sub(1), f);
                        }
                    }
                }
            }
        }
        if let Some(root) = self.root.as_ref() {
            walk(root, 0, self.height.wrapping_sub(1), &mut f);
        }
    }

    /// Present landmarks with their slots, in slot order.
    pub fn iter(&self) -> Iter<'_> {
        let mut stack = Vec::with_capacity(self.height as usize + 1);
        if let Some(root) = self.root.as_ref() {
            stack.push((root, 0usize, 0usize));
        }
        Iter {
            stack,
            height: self.height,
        }
    }
}

/// A landmark of a map opened for writing ([`LandmarkMap::get_mut`]): its cell in the
/// trie, whose path the map alone holds, and the map's spatial index with the landmark's
/// place in it before the write (`None` for a map without an index).
#[derive(Debug)]
pub struct LandmarkMut<'a> {
    lm: &'a mut Landmark,
    index: Option<(&'a mut SpatialIndex, Place)>,
    slot: usize,
}

impl LandmarkMut<'_> {
    /// The landmark, its `existence` field current.
    #[inline(always)]
    pub fn get(&self) -> &Landmark {
        self.lm
    }

    /// Changes the landmark through `f` and moves it in the spatial index if its place
    /// changed.
    #[inline(always)]
    pub fn write(self, f: impl FnOnce(&mut Landmark)) {
        f(self.lm);
        if let Some((index, before)) = self.index {
            move_in_index(index, self.slot, Some(before), Some(Place::of(self.lm)));
        }
    }
}

/// Iterator over a map's present landmarks ([`LandmarkMap::iter`]): a depth-first walk.
#[derive(Debug)]
pub struct Iter<'a> {
    /// (node, its first slot, next child or cell), from the root down.
    stack: Vec<(&'a Node, usize, usize)>,
    height: u32,
}

impl<'a> Iterator for Iter<'a> {
    type Item = (usize, &'a Landmark);

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let depth = self.stack.len() as u32;
            let (node, base, next) = self.stack.last_mut()?;
            let node: &'a Node = node;
            match node {
                Node::Leaf(l) => {
                    while *next < LEAF {
                        let i = *next;
                        *next += 1;
                        if let Some(lm) = &l[i] {
                            return Some((*base + i, lm));
                        }
                    }
                }
                Node::Branch(c) => {
                    // This node is at branch level `height - depth`, its children one below.
                    let shift = LEAF_BITS + BRANCH_BITS * (self.height - depth);
                    let mut child = None;
                    while *next < BRANCH && child.is_none() {
                        let i = *next;
                        *next += 1;
                        child = c[i].as_ref().map(|n| (n, *base + (i << shift)));
                    }
                    if let Some((n, b)) = child {
                        self.stack.push((n, b, 0));
                        continue;
                    }
                }
            }
            self.stack.pop();
        }
    }
}

impl Serialize for LandmarkMap {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq((0..self.slots).map(|i| {
            self.get(i).map(|l| Landmark {
                existence: self.current_existence(i, l),
                ..*l
            })
        }))
    }
}

impl<'de> Deserialize<'de> for LandmarkMap {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let v: Vec<Option<Landmark>> = Vec::deserialize(d)?;
        let mut m = LandmarkMap::default();
        m.ensure_slots(v.len());
        for (i, s) in v.into_iter().enumerate() {
            if let Some(lm) = s {
                m.set(i, lm);
            }
        }
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math;

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

    /// The prefetch walks every path of tries of every height, with holes (absent leaves
    /// and branches), past the last slot and deeper than the trie, without reading out of
    /// bounds, and takes as many stages as levels.
    #[test]
    fn prefetch_walks_any_path_in_bounds() {
        for len in [
            0usize,
            1,
            LEAF,
            LEAF + 1,
            LEAF * BRANCH + 1,
            LEAF * BRANCH * BRANCH + 3,
        ] {
            let mut m = LandmarkMap::new();
            m.ensure_slots(len);
            // Every third slot filled: some leaves and branches stay absent.
            for s in (0..len).step_by(3 * LEAF + 1) {
                m.set(s, lm(s as f64));
            }
            let before = m.clone();
            assert_eq!(m.prefetch_stages(), m.height + 1);
            for slot in 0..len + 2 * LEAF {
                for depth in 0..=m.height + 2 {
                    m.prefetch_path(slot, depth);
                }
            }
            assert_eq!(m, before);
        }
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

    /// A 2D landmark at (x, y) with variance `var` on each axis (also the pool's tests').
    pub(super) fn at(x: f64, y: f64, var: f64) -> Landmark {
        Landmark {
            gaussian: LandmarkGaussian {
                mean: [x, y, 0.0],
                cov: [var, 0.0, 0.0, var, 0.0, 0.0],
            },
            id: None,
            existence: 1.0,
            hits: 1,
        }
    }

    /// Every landmark within the radius is visited, each once, whatever the map's history
    /// (cells entered and left, wide landmarks narrowing, removals, shared copies).
    #[test]
    fn queries_find_every_landmark_within_the_radius() {
        use proptest::prelude::*;
        let op = (
            0u8..3,
            0usize..300,
            (-30.0f64..30.0, -30.0f64..30.0, 0.0f64..1.5),
        );
        let query = (-35.0f64..35.0, -35.0f64..35.0, 0.0f64..12.0);
        proptest!(ProptestConfig::with_cases(64), |(
            ops in proptest::collection::vec(op, 1..400),
            queries in proptest::collection::vec(query, 1..20),
            indexed in any::<bool>(),
        )| {
            let mut map = if indexed { LandmarkMap::new() } else { LandmarkMap::without_index() };
            let mut copies = Vec::new();
            for (i, (kind, pick, (x, y, var))) in ops.into_iter().enumerate() {
                let n = map.slots();
                match kind {
                    1 if n > 0 => map.set(pick % n, at(x, y, var)),
                    2 if n > 0 => map.remove(pick % n),
                    _ => {
                        map.push(at(x, y, var));
                    }
                }
                if i % 50 == 0 {
                    copies.push(map.clone());
                }
            }
            // An index dropped midway: the map answers by visiting everything.
            let mut dropped = map.clone();
            dropped.drop_index();
            copies.push(dropped);
            copies.push(map);
            for map in &copies {
                for &(qx, qy, r) in &queries {
                    let mut seen = Vec::new();
                    map.for_each_near(qx, qy, r, |s, l| {
                        assert_eq!(map.get(s), Some(l));
                        seen.push(s);
                    });
                    let n = seen.len();
                    seen.sort_unstable();
                    seen.dedup();
                    prop_assert_eq!(seen.len(), n, "a landmark visited twice");
                    for (s, l) in map.iter() {
                        let d = math::hypot(l.gaussian.mean[0] - qx, l.gaussian.mean[1] - qy);
                        prop_assert!(d > r || seen.binary_search(&s).is_ok(), "slot {} at {} m missed", s, d);
                    }
                }
            }
        });
    }

    /// A large map answers a small query from its cells, not by visiting every landmark.
    #[test]
    fn a_small_query_in_a_large_map_visits_few_landmarks() {
        let mut map = LandmarkMap::new();
        for i in 0..100 {
            for j in 0..100 {
                map.push(at(i as f64, j as f64, 0.01));
            }
        }
        let mut visited = 0;
        map.for_each_near(50.3, 50.3, 1.0, |_, _| visited += 1);
        // The disc of 1 m lies in one cell (of 8 m: [48, 56) m in x and y): its landmarks
        // on the 1 m lattice.
        assert_eq!(visited, (INDEX_CELL * INDEX_CELL) as usize);
        assert!(visited < 100, "not the map's 10,000");
        // A landmark too uncertain for a cell is visited by every query.
        map.push(at(-500.0, -500.0, 4.0));
        let mut wide = 0;
        map.for_each_near(50.3, 50.3, 1.0, |_, l| {
            wide += usize::from(l.gaussian.mean[0] == -500.0)
        });
        assert_eq!(wide, 1);
    }

    /// A map without an index keeps none through writes, and its queries visit every
    /// landmark; its contents equal an indexed map's under the same writes.
    #[test]
    fn a_map_without_an_index_keeps_none_and_visits_everything() {
        let (mut plain, mut indexed) = (LandmarkMap::without_index(), LandmarkMap::new());
        for i in 0..40 {
            let l = at(i as f64 * 3.0, 0.0, 0.01);
            plain.push(l);
            indexed.push(l);
        }
        plain.set(5, at(-50.0, 9.0, 0.01));
        indexed.set(5, at(-50.0, 9.0, 0.01));
        plain.remove(7);
        indexed.remove(7);
        assert_eq!(plain, indexed);
        assert!(plain.index.is_empty() && !plain.is_indexed());
        assert!(!indexed.index.is_empty() && indexed.is_indexed());
        let count = |m: &LandmarkMap| {
            let mut n = 0;
            m.for_each_near(0.0, 0.0, 1.0, |_, _| n += 1);
            n
        };
        assert_eq!(count(&plain), 39);
        // The query's cells hold the landmarks at x = 0, 3, ... below INDEX_CELL (8 m: 0, 3
        // and 6).
        assert_eq!(count(&indexed), (INDEX_CELL / 3.0).ceil() as usize);
        assert!(count(&indexed) < 39);
        indexed.drop_index();
        assert!(indexed.index.is_empty());
        assert_eq!(count(&indexed), 39);
    }

    /// The map against a plain vector under random pushes, sets, removes and clones: the
    /// same contents, and a clone never sees the original's later writes.
    #[test]
    fn matches_a_vector_model_through_copies() {
        use proptest::prelude::*;
        let op = (0u8..4, 0usize..400, -1e3f64..1e3);
        proptest!(ProptestConfig::with_cases(64), |(ops in proptest::collection::vec(op, 1..600))| {
            let mut map = LandmarkMap::new();
            let mut model: Vec<Option<Landmark>> = Vec::new();
            let mut frozen: Vec<(LandmarkMap, Vec<Option<Landmark>>)> = Vec::new();
            for (kind, at, x) in ops {
                match kind {
                    0 => {
                        let s = map.push(lm(x));
                        prop_assert_eq!(s, model.len());
                        model.push(Some(lm(x)));
                    }
                    1 if !model.is_empty() => {
                        let s = at % model.len();
                        map.set(s, lm(x));
                        model[s] = Some(lm(x));
                    }
                    2 if !model.is_empty() => {
                        let s = at % model.len();
                        map.remove(s);
                        model[s] = None;
                    }
                    _ => {
                        map.ensure_slots(model.len() + at % 9);
                        model.resize(model.len() + at % 9, None);
                        frozen.push((map.clone(), model.clone()));
                    }
                }
            }
            frozen.push((map, model));
            for (map, model) in &frozen {
                prop_assert_eq!(map.slots(), model.len());
                prop_assert_eq!(map.len(), model.iter().flatten().count());
                for (s, want) in model.iter().enumerate() {
                    prop_assert_eq!(map.get(s), want.as_ref());
                }
                prop_assert_eq!(map.get(model.len()), None);
                let listed: Vec<(usize, Landmark)> = map.iter().map(|(s, l)| (s, *l)).collect();
                let want: Vec<(usize, Landmark)> = model
                    .iter()
                    .enumerate()
                    .filter_map(|(s, l)| l.map(|l| (s, l)))
                    .collect();
                prop_assert_eq!(&listed, &want);
                let mut walked = Vec::new();
                map.for_each(|s, l| walked.push((s, *l)));
                prop_assert_eq!(walked, want);
                let json = serde_json::to_string(map).unwrap();
                let back: LandmarkMap = serde_json::from_str(&json).unwrap();
                prop_assert_eq!(&back, map);
            }
        });
    }

    #[test]
    fn a_write_copies_only_a_shared_path() {
        let mut a = LandmarkMap::new();
        for i in 0..1000 {
            a.push(lm(i as f64));
        }
        let b = a.clone();
        a.set(500, lm(-5.0));
        // The untouched leaves are still shared with the clone; the written one is not.
        let leaf_of = |m: &LandmarkMap, slot: usize| m.get(slot).unwrap() as *const Landmark;
        assert_eq!(leaf_of(&a, 4), leaf_of(&b, 4));
        assert_ne!(leaf_of(&a, 500), leaf_of(&b, 500));
        // A second write to the now unshared leaf copies nothing.
        let before = leaf_of(&a, 501);
        a.set(501, lm(-6.0));
        assert_eq!(leaf_of(&a, 501), before);
        assert_eq!(b.get(500).unwrap().gaussian.mean[0], 500.0);
    }

    /// `update` is `get` then `set`: it reads the held existence value where there is one
    /// (and drops it), keeps the index in step when the landmark moves, and copies only the
    /// updated path of a map shared with a copy.
    #[test]
    fn update_is_get_then_set() {
        let mut a = LandmarkMap::new();
        for i in 0..200 {
            a.push(at(i as f64, 0.0, 0.1));
        }
        a.set_existence(5, 0.25);
        let shared = a.clone();
        let mut b = a.clone();
        let step = |old: &Landmark, existence: f64| Landmark {
            gaussian: LandmarkGaussian {
                mean: [old.gaussian.mean[0] + 50.0, 3.0, 0.0],
                ..old.gaussian
            },
            existence: existence + 1.0,
            hits: old.hits + 1,
            ..*old
        };
        for slot in [5, 6, 150] {
            let old = *a.get(slot).unwrap();
            let existence = a.current_existence(slot, &old);
            a.update(slot, |lm| {
                assert_eq!(lm.existence, existence, "the current value, held or not");
                *lm = step(lm, lm.existence);
            });
            b.set(slot, step(&old, existence));
        }
        assert_eq!(a, b);
        assert_eq!(
            a.existence(5),
            Some(1.25),
            "the held value, not the trie's 1.0"
        );
        assert_eq!(a.existence(6), Some(2.0));
        assert!(a.pending().is_empty());
        let near = |m: &LandmarkMap, x: f64, y: f64| {
            let mut found = Vec::new();
            m.for_each_near(x, y, 0.5, |s, l| {
                if math::hypot(l.gaussian.mean[0] - x, l.gaussian.mean[1] - y) < 0.5 {
                    found.push(s);
                }
            });
            found
        };
        assert_eq!(near(&a, 55.0, 3.0), vec![5]);
        assert!(near(&a, 5.0, 0.0).is_empty(), "moved out of its old cell");
        assert_eq!(shared.get(5).unwrap().gaussian.mean[0], 5.0);
        assert_eq!(shared.existence(5), Some(0.25));
        let leaf_of = |m: &LandmarkMap, slot: usize| m.get(slot).unwrap() as *const Landmark;
        assert_eq!(
            leaf_of(&shared, 100),
            leaf_of(&a, 100),
            "untouched leaves stay shared"
        );
        assert_ne!(leaf_of(&shared, 150), leaf_of(&a, 150));
    }

    /// An opened landmark reads as `get` does with its current existence; unwritten it
    /// changes nothing a reader sees; an empty slot opens nothing and copies no leaf; a write
    /// moves the landmark in the index, as `set` would.
    #[test]
    fn get_mut_opens_one_landmark() {
        let mut a = LandmarkMap::new();
        for i in 0..200 {
            a.push(at(i as f64, 0.0, 0.1));
        }
        a.remove(40);
        a.set_existence(7, 0.5);
        let shared = a.clone();
        let leaf_of = |m: &LandmarkMap, slot: usize| m.get(slot).unwrap() as *const Landmark;
        {
            let got = a.get_mut(7).expect("slot 7 holds a landmark");
            assert_eq!(got.get().existence, 0.5, "the held value");
            assert_eq!(got.get().gaussian, shared.get(7).unwrap().gaussian);
        }
        assert_eq!(a, shared, "unwritten: the same map");
        assert_eq!(a.existence(7), Some(0.5));
        assert!(
            a.pending().is_empty(),
            "the held value went into the landmark"
        );
        assert!(a.get_mut(40).is_none(), "a removed landmark");
        assert!(a.get_mut(200).is_none(), "beyond the slots");
        assert_eq!(
            leaf_of(&shared, 41),
            leaf_of(&a, 41),
            "opening an empty slot copies no leaf"
        );
        let mut b = a.clone();
        a.get_mut(9)
            .unwrap()
            .write(|lm| lm.gaussian.mean = [30.0, 30.0, 0.0]);
        b.set(
            9,
            Landmark {
                gaussian: LandmarkGaussian {
                    mean: [30.0, 30.0, 0.0],
                    ..b.get(9).unwrap().gaussian
                },
                ..*b.get(9).unwrap()
            },
        );
        assert_eq!(a, b);
        for m in [&a, &b] {
            let mut found = Vec::new();
            m.for_each_near(30.0, 30.0, 0.5, |s, _| found.push(s));
            assert_eq!(found, vec![9]);
            found.clear();
            m.for_each_near(9.0, 0.0, 0.5, |s, l| {
                if (l.gaussian.mean[0] - 9.0).abs() < 0.5 {
                    found.push(s);
                }
            });
            assert!(found.is_empty(), "moved out of its old cell");
        }
        assert_eq!(shared.get(9).unwrap().gaussian.mean[0], 9.0);
    }

    /// Existence values held apart read back, survive copies, serialisation and equality as
    /// if written, and are written into the trie beyond the bound.
    #[test]
    fn existence_held_apart_reads_as_written() {
        let mut a = LandmarkMap::new();
        for i in 0..200 {
            a.push(lm(i as f64));
        }
        let b = a.clone();
        let mut c = a.clone();
        a.set_existence(3, 0.25);
        c.set(
            3,
            Landmark {
                existence: 0.25,
                ..lm(3.0)
            },
        );
        assert_eq!(a.existence(3), Some(0.25));
        assert_eq!(b.existence(3), Some(1.0));
        assert_eq!(a, c);
        assert_ne!(a, b);
        let back: LandmarkMap = serde_json::from_str(&serde_json::to_string(&a).unwrap()).unwrap();
        assert_eq!(back, a);
        assert_eq!(back.get(3).unwrap().existence, 0.25);
        // A whole write replaces a held value; a removal drops it.
        a.set(3, lm(3.0));
        assert_eq!(a.existence(3), Some(1.0));
        a.set_existence(4, 0.5);
        a.remove(4);
        assert_eq!(a.existence(4), None);
        a.set_existence(4, 0.5);
        assert_eq!(a.existence(4), None, "no value for an empty slot");
        // Past the bound, the held values go into the trie.
        for s in 0..=PENDING_EXISTENCE {
            a.set_existence(s + 10, 0.125);
        }
        assert!(a.pending.is_none());
        for s in 0..=PENDING_EXISTENCE {
            assert_eq!(a.get(s + 10).unwrap().existence, 0.125);
            assert_eq!(a.existence(s + 10), Some(0.125));
        }
        assert_eq!(b.get(10).unwrap().existence, 1.0, "copies unchanged");
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
