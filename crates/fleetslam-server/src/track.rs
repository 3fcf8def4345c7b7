//! The trajectories of a live run, shared with readers without copying them.
//!
//! A run's trajectories grow by one point per applied record for as long as the run lasts.
//! The coordinator publishes them beside its state (readers of `GET state`, `trajectories`,
//! `timeline` and `export` never go through its command queue), so a publication must not
//! copy the whole history: each robot's points are kept as sealed chunks of [`CHUNK`] points
//! behind `Arc`s plus an open tail, and a copy of a [`TrajectoryLog`] shares the sealed
//! chunks (it costs one pointer per chunk and at most `CHUNK` points per robot).
//!
//! Beside the robots' poses the log keeps the filter's own series, one point per applied
//! record ([`FilterPoint`]): it is stored in the same pieces as the trajectories, under the
//! track name [`FILTER_TRACK`] (which no robot id can be: ids have no '/'), so that it
//! follows the snapshots, recovery and deletion of the run as they do. Readers of
//! trajectories never see it ([`TrajectoryLog::to_map`]).

use crate::history::Trajectories;
use std::collections::BTreeMap;
use std::sync::Arc;

/// Points per sealed chunk.
pub const CHUNK: usize = 256;

/// The stored track name of the filter's series (see the module's doc).
pub const FILTER_TRACK: &str = "/filter";

/// The filter after an applied record: `[t, ess, step_ms, landmarks]` (data time [s], the
/// effective sample size, the wall time of the record's step [ms], landmarks in the best
/// particle). A step that did not move the map (a robot being localized) leaves the ESS and
/// landmarks as they were.
pub type FilterPoint = [f64; 4];

/// Per-robot trajectories as `[t, x, y, theta]` and the filter's series, cheap to copy (see
/// the module's doc).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrajectoryLog {
    robots: BTreeMap<String, Track>,
    filter: Track,
}

#[derive(Debug, Clone, Default, PartialEq)]
struct Track {
    sealed: Vec<Arc<[[f64; 4]]>>,
    tail: Vec<[f64; 4]>,
}

impl Track {
    fn from_points(pts: Vec<[f64; 4]>) -> Self {
        let mut track = Track::default();
        for p in pts {
            track.push(p);
        }
        track
    }

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
        self.iter_from(0)
    }

    /// The points from index `from` on, without walking the sealed chunks before it (a
    /// live reader asks for the few newest points many times a second).
    fn iter_from(&self, from: usize) -> impl Iterator<Item = &[f64; 4]> {
        let first = (from / CHUNK).min(self.sealed.len());
        self.sealed[first..]
            .iter()
            .flat_map(|c| c.iter())
            .chain(self.tail.iter())
            .skip(from - first * CHUNK)
    }
}

impl TrajectoryLog {
    pub fn new() -> Self {
        Self::default()
    }

    /// The log of `t`'s points; a [`FILTER_TRACK`] entry is the filter's series.
    pub fn from_map(t: Trajectories) -> Self {
        let mut log = Self::new();
        for (robot, pts) in t {
            if robot == FILTER_TRACK {
                log.filter = Track::from_points(pts);
            } else {
                log.insert(robot, pts);
            }
        }
        log
    }

    /// Sets a robot's points (replacing any it had).
    pub fn insert(&mut self, robot: String, pts: Vec<[f64; 4]>) {
        self.robots.insert(robot, Track::from_points(pts));
    }

    /// Appends a point to a robot's trajectory (starting it if needed).
    pub fn push(&mut self, robot: &str, p: [f64; 4]) {
        match self.robots.get_mut(robot) {
            Some(t) => t.push(p),
            None => self.robots.entry(robot.to_string()).or_default().push(p),
        }
    }

    /// Appends the filter's point after a record.
    pub fn push_filter(&mut self, p: FilterPoint) {
        self.filter.push(p);
    }

    /// The filter's last point.
    pub fn last_filter(&self) -> Option<FilterPoint> {
        self.filter
            .tail
            .last()
            .or_else(|| self.filter.sealed.last().and_then(|c| c.last()))
            .copied()
    }

    /// The filter's points.
    pub fn filter_series(&self) -> Vec<FilterPoint> {
        self.filter.iter().copied().collect()
    }

    /// Points of each track (each robot, and [`FILTER_TRACK`] once it has points): what a
    /// snapshot covers.
    pub fn lens(&self) -> BTreeMap<String, usize> {
        let filter = (self.filter.len() > 0).then(|| (FILTER_TRACK.to_string(), self.filter.len()));
        self.robots
            .iter()
            .map(|(r, t)| (r.clone(), t.len()))
            .chain(filter)
            .collect()
    }

    /// The points of each track from index `from[track]` (0 for a track not in `from`) on:
    /// what was added since `from` was taken with [`TrajectoryLog::lens`], to store. Tracks
    /// with none are left out.
    pub fn since(&self, from: &BTreeMap<String, usize>) -> Trajectories {
        let filter = FILTER_TRACK.to_string();
        self.robots
            .iter()
            .chain(std::iter::once((&filter, &self.filter)))
            .filter_map(|(r, t)| {
                let skip = from.get(r).copied().unwrap_or(0);
                let pts: Vec<[f64; 4]> = t.iter_from(skip).copied().collect();
                (!pts.is_empty()).then(|| (r.clone(), pts))
            })
            .collect()
    }

    /// Every robot's points, as the plain map (a copy: for readers and the final result).
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
        // From marks at and past a sealed chunk's edge: what walking from the start skips to.
        let all = log.to_map()["a"].clone();
        for from in [CHUNK - 1, CHUNK, CHUNK + 5, all.len(), all.len() + 3] {
            let mark = BTreeMap::from([("a".to_string(), from), ("b".to_string(), 1)]);
            let want: Vec<[f64; 4]> = all.iter().skip(from).copied().collect();
            assert_eq!(log.since(&mark).get("a").cloned().unwrap_or_default(), want);
        }
    }

    /// The filter's series is stored with the tracks (lens, since, from_map) and never read
    /// as a robot's trajectory.
    #[test]
    fn the_filter_series_is_stored_beside_the_robots_but_not_read_as_one() {
        let mut log = TrajectoryLog::new();
        log.push("a", pt(0));
        assert_eq!(log.last_filter(), None);
        assert!(!log.lens().contains_key(FILTER_TRACK));
        for i in 0..(CHUNK + 3) {
            log.push_filter(pt(i));
        }
        assert_eq!(log.last_filter(), Some(pt(CHUNK + 2)));
        assert_eq!(log.lens()[FILTER_TRACK], CHUNK + 3);
        assert_eq!(log.to_map().len(), 1);
        assert_eq!(log.first_t(), Some(0.0));
        let stored = log.since(&BTreeMap::new());
        assert_eq!(stored[FILTER_TRACK].len(), CHUNK + 3);
        assert_eq!(TrajectoryLog::from_map(stored), log);
        let mark = log.lens();
        log.push_filter(pt(9000));
        assert_eq!(log.since(&mark)[FILTER_TRACK], vec![pt(9000)]);
        let series = log.filter_series();
        assert_eq!(series.len(), CHUNK + 4);
        assert_eq!(
            series[CHUNK + 1..],
            [pt(CHUNK + 1), pt(CHUNK + 2), pt(9000)]
        );
    }
}
