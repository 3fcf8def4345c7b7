//! The trajectories of a live run, shared with readers without copying them.
//!
//! A run's trajectories grow by one point per applied record for as long as the run lasts.
//! The coordinator publishes them beside its state (readers of `GET state`, `trajectories`,
//! `timeline` and `export` never go through its command queue), so a publication must not
//! copy the whole history: each robot's points are kept as sealed chunks of [`CHUNK`] points
//! behind `Arc`s plus an open tail, and a copy of a [`TrajectoryLog`] shares the sealed
//! chunks (it costs one pointer per chunk and at most `CHUNK` points per robot).

use crate::history::Trajectories;
use std::collections::BTreeMap;
use std::sync::Arc;

/// Points per sealed chunk.
pub const CHUNK: usize = 256;

/// Per-robot trajectories as `[t, x, y, theta]`, cheap to copy (see the module's doc).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrajectoryLog {
    robots: BTreeMap<String, Track>,
}

#[derive(Debug, Clone, Default, PartialEq)]
struct Track {
    sealed: Vec<Arc<[[f64; 4]]>>,
    tail: Vec<[f64; 4]>,
}

impl Track {
    fn len(&self) -> usize {
        self.sealed.len() * CHUNK + self.tail.len()
    }

    fn push(&mut self, p: [f64; 4]) {
        self.tail.push(p);
        if self.tail.len() == CHUNK {
            let full = std::mem::replace(&mut self.tail, Vec::with_capacity(CHUNK));
            self.sealed.push(full.into());
        }
    }

    fn iter(&self) -> impl Iterator<Item = &[f64; 4]> {
        self.sealed
            .iter()
            .flat_map(|c| c.iter())
            .chain(self.tail.iter())
    }
}

impl TrajectoryLog {
    pub fn new() -> Self {
        Self::default()
    }

    /// The log of `t`'s points.
    pub fn from_map(t: Trajectories) -> Self {
        let mut log = Self::new();
        for (robot, pts) in t {
            log.insert(robot, pts);
        }
        log
    }

    /// Sets a robot's points (replacing any it had).
    pub fn insert(&mut self, robot: String, pts: Vec<[f64; 4]>) {
        let mut track = Track::default();
        for p in pts {
            track.push(p);
        }
        self.robots.insert(robot, track);
    }

    /// Appends a point to a robot's trajectory (starting it if needed).
    pub fn push(&mut self, robot: &str, p: [f64; 4]) {
        match self.robots.get_mut(robot) {
            Some(t) => t.push(p),
            None => self.robots.entry(robot.to_string()).or_default().push(p),
        }
    }

    /// Points of each robot.
    pub fn lens(&self) -> BTreeMap<String, usize> {
        self.robots
            .iter()
            .map(|(r, t)| (r.clone(), t.len()))
            .collect()
    }

    /// The points of each robot from index `from[robot]` (0 for a robot not in `from`) on:
    /// what was added since `from` was taken with [`TrajectoryLog::lens`]. Robots with none
    /// are left out.
    pub fn since(&self, from: &BTreeMap<String, usize>) -> Trajectories {
        self.robots
            .iter()
            .filter_map(|(r, t)| {
                let skip = from.get(r).copied().unwrap_or(0);
                let pts: Vec<[f64; 4]> = t.iter().skip(skip).copied().collect();
                (!pts.is_empty()).then(|| (r.clone(), pts))
            })
            .collect()
    }

    /// Every point, as the plain map (a copy: for readers and the final result).
    pub fn to_map(&self) -> Trajectories {
        self.robots
            .iter()
            .map(|(r, t)| (r.clone(), t.iter().copied().collect()))
            .collect()
    }

    /// The earliest first point's time (a start pose).
    pub fn first_t(&self) -> Option<f64> {
        self.robots
            .values()
            .filter_map(|t| t.iter().next().map(|p| p[0]))
            .reduce(f64::min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pt(i: usize) -> [f64; 4] {
        [i as f64, i as f64 * 2.0, 0.5, -0.25]
    }

    #[test]
    fn copies_share_sealed_chunks_and_read_back_in_order() {
        let mut log = TrajectoryLog::new();
        log.insert("a".into(), vec![pt(0)]);
        for i in 1..(3 * CHUNK + 7) {
            log.push("a", pt(i));
        }
        log.push("b", pt(5));
        let copy = log.clone();
        // The copy shares the sealed chunks: same allocations.
        let (la, ca) = (&log.robots["a"], &copy.robots["a"]);
        assert_eq!(la.sealed.len(), 3);
        for (x, y) in la.sealed.iter().zip(&ca.sealed) {
            assert!(Arc::ptr_eq(x, y));
        }
        assert_eq!(ca.tail.len(), 7);
        let map = copy.to_map();
        assert_eq!(map["a"], (0..3 * CHUNK + 7).map(pt).collect::<Vec<_>>());
        assert_eq!(map["b"], vec![pt(5)]);
        assert_eq!(TrajectoryLog::from_map(map.clone()), log);
        assert_eq!(log.first_t(), Some(0.0));
        // Growing the original does not change the copy.
        log.push("a", pt(9999));
        assert_eq!(copy.to_map()["a"].len(), 3 * CHUNK + 7);
    }

    #[test]
    fn since_gives_what_was_added() {
        let mut log = TrajectoryLog::new();
        for i in 0..10 {
            log.push("a", pt(i));
        }
        let mark = log.lens();
        assert_eq!(mark["a"], 10);
        assert!(log.since(&mark).is_empty());
        for i in 10..(CHUNK + 20) {
            log.push("a", pt(i));
        }
        log.push("b", pt(1));
        let new = log.since(&mark);
        assert_eq!(new["a"], (10..CHUNK + 20).map(pt).collect::<Vec<_>>());
        assert_eq!(new["b"], vec![pt(1)]);
        assert_eq!(log.since(&BTreeMap::new()), log.to_map());
    }
}
