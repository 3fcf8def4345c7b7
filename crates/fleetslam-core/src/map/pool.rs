//! Maps written with their sharing kept: a node pool.
//!
//! A filter's particles share most of their maps' trie nodes (resampling copies pointers; a
//! write copies only its path). Writing each map as a list of its landmarks, as
//! [`LandmarkMap`]'s own serialisation does, writes every shared landmark once per particle
//! that holds it, and reading it back gives each particle a whole copy. A [`MapPool`] holds
//! every distinct node of a set of maps once, children before their parents, and a
//! [`PooledMap`] names its root in the pool: the text grows with the distinct nodes, not with
//! particles × landmarks, and the maps read back share exactly the nodes they shared when
//! written (so a restored filter takes the memory the running one took, and continues with
//! the same copies on write).
//!
//! Reading a pool checks its structure (children before parents, one level per node, leaves
//! at the bottom, every landmark within its map's slots), so a damaged pool is an error, not
//! a map that panics when read. Spatial indexes are not written: a map that keeps one gets
//! it from the previous map read from the same pool, changed only where their tries differ
//! ([`PoolReader::map`]), so maps that share most of their nodes share most of their index.

use super::{
    BRANCH, BRANCH_BITS, CowArc, LEAF, LEAF_BITS, Landmark, LandmarkMap, Node, PENDING_EXISTENCE,
};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Branch levels a pooled map may have: a trie of this height holds `LEAF · BRANCH^20`
/// (2^62) slots, the most a 64-bit slot number can address with room to spare.
pub const MAX_HEIGHT: u32 = 20;

/// One node of a pool: a leaf's landmarks (boxed, as the trie holds them, so that a branch
/// entry stays small), or a branch's children as pool indices (each below the branch's own
/// index).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum PoolNode {
    Leaf(Box<[Option<Landmark>; LEAF]>),
    Branch([Option<u32>; BRANCH]),
}

/// The distinct trie nodes of a set of maps (see the module's documentation).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct MapPool {
    nodes: Vec<PoolNode>,
}

impl MapPool {
    /// Number of distinct nodes.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Number of landmarks the pool holds (each shared one once).
    pub fn landmarks(&self) -> usize {
        self.nodes
            .iter()
            .map(|n| match n {
                PoolNode::Leaf(l) => l.iter().flatten().count(),
                PoolNode::Branch(_) => 0,
            })
            .sum()
    }
}

/// A map whose trie is in a [`MapPool`]: its root's index and what is not in the nodes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PooledMap {
    /// The root node's pool index; `None` for a map that has never held a landmark.
    root: Option<u32>,
    /// Branch levels above the leaves.
    height: u32,
    /// Slots, including empty ones.
    slots: usize,
    /// Existence values held apart from their landmarks (slot, log-odds), by slot.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pending: Vec<(u32, f64)>,
    /// The map keeps no spatial index.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    unindexed: bool,
}

/// Builds a [`MapPool`] from maps, each distinct node once (nodes are told apart by
/// address: the borrow keeps every map, and so every address, alive while the pool grows).
#[derive(Debug, Default)]
pub struct PoolWriter<'a> {
    pool: MapPool,
    seen: HashMap<*const (), u32>,
    /// Ties the writer to the maps it has read.
    _maps: std::marker::PhantomData<&'a LandmarkMap>,
}

impl<'a> PoolWriter<'a> {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds `map`'s nodes that the pool does not hold yet; returns the map's entry, or an
    /// error when the pool would hold more nodes than a `u32` index can name.
    pub fn add(&mut self, map: &'a LandmarkMap) -> Result<PooledMap, PoolError> {
        let root = match map.root.as_ref() {
            Some(n) => self.node(n)?,
            None => None,
        };
        Ok(PooledMap {
            root,
            height: map.height,
            slots: map.slots,
            pending: map.pending().to_vec(),
            unindexed: map.unindexed,
        })
    }

    /// The pool index of `node`, added after its children if new; `None` for a branch
    /// without children (read back as an absent child, which reads the same).
    fn node(&mut self, node: &'a Node) -> Result<Option<u32>, PoolError> {
        let key = match node {
            Node::Leaf(l) => CowArc::as_ptr(l).cast::<()>(),
            Node::Branch(c) => CowArc::as_ptr(c).cast::<()>(),
        };
        if let Some(&i) = self.seen.get(&key) {
            return Ok(Some(i));
        }
        let entry = match node {
            Node::Leaf(l) => PoolNode::Leaf(Box::new(**l)),
            Node::Branch(c) => {
                let mut kids = [None; BRANCH];
                for (kid, child) in kids.iter_mut().zip(c.iter()) {
                    if let Some(n) = child {
                        *kid = self.node(n)?;
                    }
                }
                if kids.iter().all(Option::is_none) {
                    return Ok(None);
                }
                PoolNode::Branch(kids)
            }
        };
        let i = u32::try_from(self.pool.nodes.len()).map_err(|_| {
            PoolError(format!(
                "the maps have more than {} distinct trie nodes",
                u32::MAX
            ))
        })?;
        self.pool.nodes.push(entry);
        self.seen.insert(key, i);
        Ok(Some(i))
    }

    pub fn finish(self) -> MapPool {
        self.pool
    }
}

/// Why a pool or a pooled map cannot be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("map pool: {0}")]
pub struct PoolError(String);

/// What reading a node found out about it.
#[derive(Debug, Clone, Copy)]
struct NodeInfo {
    /// 0 for a leaf, `k` for a branch whose children are at level `k - 1`.
    level: u32,
    /// Landmarks below it.
    count: usize,
    /// The highest slot offset below it that holds a landmark.
    last: Option<usize>,
}

/// Reads the maps of a [`MapPool`] (see [`PoolReader::map`]).
#[derive(Debug)]
pub struct PoolReader {
    nodes: Vec<(Node, NodeInfo)>,
    /// The last indexed map read: the next indexed map's index is derived from it.
    previous: Option<LandmarkMap>,
}

impl PoolReader {
    /// Checks the pool's structure and builds its nodes, shared as they were written.
    pub fn new(pool: MapPool) -> Result<Self, PoolError> {
        let mut nodes: Vec<(Node, NodeInfo)> = Vec::with_capacity(pool.nodes.len());
        for (i, n) in pool.nodes.into_iter().enumerate() {
            let built = match n {
                PoolNode::Leaf(l) => {
                    let info = NodeInfo {
                        level: 0,
                        count: l.iter().flatten().count(),
                        last: l.iter().rposition(Option::is_some),
                    };
                    (Node::Leaf(CowArc::new(*l)), info)
                }
                PoolNode::Branch(kids) => {
                    let mut level = None;
                    let (mut count, mut last) = (0usize, None);
                    let mut children: [Option<Node>; BRANCH] = Default::default();
                    for (k, kid) in kids.iter().enumerate() {
                        let Some(c) = *kid else { continue };
                        let Some((node, info)) = nodes.get(c as usize) else {
                            return Err(PoolError(format!(
                                "node {i} names node {c} as a child, which does not precede it"
                            )));
                        };
                        if info.level >= MAX_HEIGHT {
                            return Err(PoolError(format!(
                                "node {i} stands more than {MAX_HEIGHT} levels above its leaves"
                            )));
                        }
                        if level.is_some_and(|l| l != info.level) {
                            return Err(PoolError(format!(
                                "node {i} has children at different levels"
                            )));
                        }
                        level = Some(info.level);
                        let shift = LEAF_BITS + BRANCH_BITS * info.level;
                        count += info.count;
                        if let Some(l) = info.last {
                            last = Some((k << shift) + l);
                        }
                        children[k] = Some(node.clone());
                    }
                    let Some(child_level) = level else {
                        return Err(PoolError(format!("node {i} is a branch without children")));
                    };
                    let info = NodeInfo {
                        level: child_level + 1,
                        count,
                        last,
                    };
                    (Node::Branch(CowArc::new(children)), info)
                }
            };
            nodes.push(built);
        }
        Ok(Self {
            nodes,
            previous: None,
        })
    }

    /// The map `m` names, sharing the pool's nodes. A map that keeps a spatial index gets
    /// the previous indexed map's index changed where the two tries differ (the same
    /// landmarks per cell as one built from scratch).
    pub fn map(&mut self, m: &PooledMap) -> Result<LandmarkMap, PoolError> {
        if m.height > MAX_HEIGHT {
            return Err(PoolError(format!(
                "a map of height {} (at most {MAX_HEIGHT})",
                m.height
            )));
        }
        if m.slots > LandmarkMap::capacity(m.height) {
            return Err(PoolError(format!(
                "a map of {} slots in a trie of height {}",
                m.slots, m.height
            )));
        }
        let (root, live) = match m.root {
            None => (None, 0),
            Some(r) => {
                let Some((node, info)) = self.nodes.get(r as usize) else {
                    return Err(PoolError(format!("a map's root {r} is not in the pool")));
                };
                if info.level != m.height {
                    return Err(PoolError(format!(
                        "a map of height {} has a root of height {}",
                        m.height, info.level
                    )));
                }
                if info.last.is_some_and(|l| l >= m.slots) {
                    return Err(PoolError(format!(
                        "a map of {} slots holds a landmark in slot {}",
                        m.slots,
                        info.last.unwrap_or_default()
                    )));
                }
                (Some(node.clone()), info.count)
            }
        };
        let mut map = LandmarkMap {
            root,
            height: m.height,
            slots: m.slots,
            live,
            index: Default::default(),
            pending: None,
            unindexed: m.unindexed,
        };
        if m.pending.len() > PENDING_EXISTENCE {
            return Err(PoolError(format!(
                "a map holds {} existence values apart (at most {PENDING_EXISTENCE})",
                m.pending.len()
            )));
        }
        if !m.pending.is_sorted_by(|a, b| a.0 < b.0) {
            return Err(PoolError(
                "a map's held existence values are not in slot order".into(),
            ));
        }
        if let Some((s, _)) = m
            .pending
            .iter()
            .find(|(s, _)| map.get(*s as usize).is_none())
        {
            return Err(PoolError(format!(
                "a map holds an existence value for its empty slot {s}"
            )));
        }
        map.pending = (!m.pending.is_empty()).then(|| CowArc::new(m.pending.clone()));
        if !map.unindexed {
            map.index_from(self.previous.as_ref());
            self.previous = Some(map.clone());
        }
        Ok(map)
    }
}

impl LandmarkMap {
    /// Sets this map's spatial index: `base`'s (an indexed map of the same height) with the
    /// slots where the two tries differ moved, or one built from every landmark.
    fn index_from(&mut self, base: Option<&LandmarkMap>) {
        self.index = Default::default();
        let root = self.root.clone();
        match base {
            Some(b) if b.is_indexed() && b.height == self.height => {
                self.index = b.index.clone();
                let levels = self.height;
                self.reindex_diff(b.root.as_ref(), root.as_ref(), levels, 0);
            }
            _ => self.reindex_diff(None, root.as_ref(), self.height, 0),
        }
    }

    /// Reindexes every slot whose landmark differs between the subtrees `old` and `new`
    /// (at branch level `level`, the first slot `base`), skipping shared subtrees.
    fn reindex_diff(&mut self, old: Option<&Node>, new: Option<&Node>, level: u32, base: usize) {
        match (old, new) {
            (None, None) => {}
            (Some(Node::Leaf(a)), Some(Node::Leaf(b))) if CowArc::ptr_eq(a, b) => {}
            (Some(Node::Branch(a)), Some(Node::Branch(b))) if CowArc::ptr_eq(a, b) => {}
            _ if level == 0 => {
                let cells = |n: Option<&Node>| match n {
                    Some(Node::Leaf(l)) => **l,
                    _ => [None; LEAF],
                };
                let (a, b) = (cells(old), cells(new));
                for i in 0..LEAF {
                    self.reindex(base + i, a[i].as_ref(), b[i].as_ref());
                }
            }
            _ => {
                fn kid(n: Option<&Node>, k: usize) -> Option<&Node> {
                    match n {
                        Some(Node::Branch(c)) => c[k].as_ref(),
                        _ => None,
                    }
                }
                let shift = LEAF_BITS + BRANCH_BITS * (level - 1);
                for k in 0..BRANCH {
                    self.reindex_diff(kid(old, k), kid(new, k), level - 1, base + (k << shift));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::Place;
    use crate::map::tests::at;

    /// The index's slots per place, sorted: what a correct index holds whatever order it
    /// was built in.
    fn index_of(m: &LandmarkMap) -> Vec<((u8, i32, i32), Vec<u32>)> {
        let mut v: Vec<_> = m
            .index
            .iter()
            .map(|(p, l)| {
                let key = match p {
                    Place::Cell(x, y) => (0, x, y),
                    Place::Wide => (1, 0, 0),
                };
                let mut l = l.to_vec();
                l.sort_unstable();
                (key, l)
            })
            .collect();
        v.sort();
        v
    }

    /// The index a map would have if built from its landmarks alone.
    fn fresh_index_of(m: &LandmarkMap) -> Vec<((u8, i32, i32), Vec<u32>)> {
        let mut f = LandmarkMap {
            index: Default::default(),
            ..m.clone()
        };
        f.index_from(None);
        index_of(&f)
    }

    /// The address of the leaf holding `slot`, if any.
    fn leaf(m: &LandmarkMap, slot: usize) -> Option<*const Landmark> {
        m.get(slot).map(|l| l as *const Landmark)
    }

    fn write_read(maps: &[LandmarkMap]) -> (MapPool, Vec<LandmarkMap>) {
        let mut w = PoolWriter::new();
        let entries: Vec<PooledMap> = maps.iter().map(|m| w.add(m).unwrap()).collect();
        let pool = w.finish();
        let json = serde_json::to_string(&pool).unwrap();
        let back: MapPool = serde_json::from_str(&json).unwrap();
        assert_eq!(back, pool);
        let mut r = PoolReader::new(back).unwrap();
        let read = entries.iter().map(|e| r.map(e).unwrap()).collect();
        (pool, read)
    }

    /// Maps related by copies and writes (as a filter's particles are) read back from a pool
    /// with the same contents, existence values held apart, indexes (the same landmarks per
    /// cell as built from scratch) and the same sharing: two maps share a leaf after reading
    /// exactly when they did before, and the pool holds each distinct landmark once.
    #[test]
    fn maps_read_back_from_a_pool_share_what_they_shared() {
        use proptest::prelude::*;
        let op = (
            0u8..5,
            0usize..200,
            (-30.0f64..30.0, -30.0f64..30.0, 0.0f64..1.5),
        );
        proptest!(ProptestConfig::with_cases(48), |(
            ops in proptest::collection::vec(op, 1..500),
            unindexed in proptest::bool::ANY,
        )| {
            let mut maps = vec![if unindexed { LandmarkMap::without_index() } else { LandmarkMap::new() }];
            for (kind, at_, (x, y, v)) in ops {
                let k = at_ % maps.len();
                let m = &mut maps[k];
                match kind {
                    0 | 1 => {
                        m.push(at(x, y, v));
                    }
                    2 if m.slots() > 0 => m.set(at_ % m.slots(), at(x, y, v)),
                    3 if m.slots() > 0 => {
                        if at_ % 2 == 0 {
                            m.remove(at_ % m.slots());
                        } else {
                            m.set_existence(at_ % m.slots(), x);
                        }
                    }
                    _ => {
                        let c = m.clone();
                        maps.push(c);
                    }
                }
            }
            let (pool, read) = write_read(&maps);
            let mut distinct = std::collections::HashSet::new();
            for (a, b) in maps.iter().zip(&read) {
                prop_assert_eq!(a, b);
                prop_assert_eq!(a.len(), b.len());
                prop_assert_eq!(a.slots(), b.slots());
                prop_assert_eq!(a.pending(), b.pending());
                prop_assert_eq!(b.is_indexed(), !unindexed);
                prop_assert_eq!(index_of(b), index_of(a));
                prop_assert_eq!(index_of(b), fresh_index_of(a));
                for s in 0..a.slots() {
                    if let Some(p) = leaf(a, s) {
                        distinct.insert(p);
                    }
                }
            }
            prop_assert_eq!(pool.landmarks(), distinct.len());
            for (i, (a, b)) in maps.iter().zip(&read).enumerate() {
                for (c, d) in maps.iter().zip(&read).skip(i + 1) {
                    for s in 0..a.slots().min(c.slots()) {
                        let before = leaf(a, s).is_some() && leaf(a, s) == leaf(c, s);
                        let after = leaf(b, s).is_some() && leaf(b, s) == leaf(d, s);
                        prop_assert_eq!(before, after, "slot {}", s);
                    }
                }
            }
        });
    }

    fn entry(root: Option<u32>, height: u32, slots: usize) -> PooledMap {
        PooledMap {
            root,
            height,
            slots,
            pending: Vec::new(),
            unindexed: false,
        }
    }

    fn read_err(pool: MapPool, m: &PooledMap) -> String {
        match PoolReader::new(pool) {
            Err(e) => e.to_string(),
            Ok(mut r) => r.map(m).expect_err("a damaged pool reads").to_string(),
        }
    }

    /// A damaged pool or entry is an error that says what is wrong, never a map that panics
    /// when read.
    #[test]
    fn a_damaged_pool_is_refused_with_its_fault() {
        let leaf = || PoolNode::Leaf(Box::new([Some(at(1.0, 2.0, 0.1)), None, None, None]));
        let branch = |k: [Option<u32>; BRANCH]| PoolNode::Branch(k);
        let mut kids = [None; BRANCH];
        kids[0] = Some(0);
        let good = MapPool {
            nodes: vec![leaf(), branch(kids)],
        };
        let mut r = PoolReader::new(good.clone()).unwrap();
        let m = r.map(&entry(Some(1), 1, 5)).unwrap();
        assert_eq!(
            (m.len(), m.get(0).map(|l| l.gaussian.mean[0])),
            (1, Some(1.0))
        );

        let cases: Vec<(MapPool, PooledMap, &str)> = vec![
            (
                MapPool {
                    nodes: vec![branch(kids)],
                },
                entry(Some(0), 1, 5),
                "does not precede it",
            ),
            (
                MapPool {
                    nodes: vec![branch([None; BRANCH])],
                },
                entry(Some(0), 1, 5),
                "without children",
            ),
            (
                MapPool {
                    nodes: vec![leaf(), branch(kids), {
                        let mut k = kids;
                        k[1] = Some(1);
                        branch(k)
                    }],
                },
                entry(Some(2), 2, 5),
                "different levels",
            ),
            (good.clone(), entry(Some(1), 2, 5), "has a root of height 1"),
            (good.clone(), entry(Some(0), 1, 5), "has a root of height 0"),
            (good.clone(), entry(Some(7), 1, 5), "not in the pool"),
            (
                good.clone(),
                entry(Some(1), 1, 0),
                "holds a landmark in slot 0",
            ),
            (
                good.clone(),
                entry(Some(1), 1, 33),
                "33 slots in a trie of height 1",
            ),
            (good.clone(), entry(None, MAX_HEIGHT + 1, 0), "height 21"),
            (
                good.clone(),
                PooledMap {
                    pending: vec![(3, 0.5)],
                    ..entry(Some(1), 1, 5)
                },
                "empty slot 3",
            ),
            (
                MapPool {
                    nodes: vec![leaf(), {
                        let mut l = [Some(at(0.0, 0.0, 0.1)); LEAF];
                        l[3] = None;
                        PoolNode::Leaf(Box::new(l))
                    }],
                },
                PooledMap {
                    pending: vec![(1, 0.5), (0, 0.5)],
                    ..entry(Some(1), 0, 4)
                },
                "not in slot order",
            ),
        ];
        for (pool, m, want) in cases {
            let e = read_err(pool, &m);
            assert!(e.contains(want), "{e:?} should say {want:?}");
        }
        // A tower of branches taller than any map.
        let mut nodes = vec![leaf()];
        for i in 0..=MAX_HEIGHT {
            let mut k = [None; BRANCH];
            k[0] = Some(i);
            nodes.push(branch(k));
        }
        let e = read_err(MapPool { nodes }, &entry(None, 0, 0));
        assert!(e.contains("more than 20 levels"), "{e}");
    }
}
