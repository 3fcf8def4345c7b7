//! The deterministic merge of k robots' record streams.
//!
//! Records reach the server concurrently and out of order, but the filter must apply them in
//! one order, the same as `fleetslam run` does offline: by (time, robot, sequence number).
//! Each robot's own records carry consecutive sequence numbers and non-decreasing times, so
//! once robot `j` has delivered every record up to time `w_j` (its *watermark*), no record of
//! `j` can come before `w_j` any more. A buffered record `(t, r, s)` is therefore safe to
//! apply when every other robot `j` that still counts has a watermark past it: `w_j > t`, or
//! `w_j == t` with `j` ordered after `r`.
//!
//! A robot that stays silent for longer than the reorder window (wall-clock) stops counting,
//! so one stalled robot cannot hold the whole fleet back; its later records that fall behind
//! what was already applied are refused (the server answers 409). With every robot posting,
//! the merged order equals the sorted order exactly, whatever the arrival order: the test
//! `arrival_order_does_not_matter` checks it.

use fleetslam_core::log::Record;
use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

/// Total-order key of a record: (time bits in total order, robot, seq).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct OrderKey {
    t: TotalF64,
    robot: String,
    seq: u64,
}

impl OrderKey {
    pub fn of(r: &Record) -> Self {
        Self {
            t: TotalF64(r.t),
            robot: r.robot.clone(),
            seq: r.seq,
        }
    }

    pub fn new(t: f64, robot: &str, seq: u64) -> Self {
        Self {
            t: TotalF64(t),
            robot: robot.to_string(),
            seq,
        }
    }

    pub fn t(&self) -> f64 {
        self.t.0
    }

    pub fn robot(&self) -> &str {
        &self.robot
    }

    pub fn seq(&self) -> u64 {
        self.seq
    }
}

/// An `f64` ordered by `total_cmp`.
#[derive(Debug, Clone, Copy)]
struct TotalF64(f64);

impl PartialEq for TotalF64 {
    fn eq(&self, o: &Self) -> bool {
        self.0.total_cmp(&o.0).is_eq()
    }
}
impl Eq for TotalF64 {}
impl PartialOrd for TotalF64 {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for TotalF64 {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&o.0)
    }
}

/// Why a record cannot be merged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    #[error(
        "record {seq} of robot {robot:?} at t={t} is older than what the run has already applied (t={applied}); records may arrive at most the reorder window late"
    )]
    TooOld {
        robot: String,
        seq: u64,
        t: f64,
        applied: f64,
    },
    #[error(
        "record {seq} of robot {robot:?} at t={t} goes back in time: its record {prev_seq} is at t={prev_t}"
    )]
    TimeRegression {
        robot: String,
        seq: u64,
        t: f64,
        prev_seq: u64,
        prev_t: f64,
    },
    #[error("robot {0:?} is not merged in this run")]
    UnknownRobot(String),
}

#[derive(Debug, Clone)]
struct Stream {
    /// Next sequence number expected to extend the contiguous prefix.
    next_seq: u64,
    /// Time of the last record of the contiguous prefix (the watermark).
    watermark: f64,
    /// Records received beyond a gap in the sequence, by seq, with their times.
    ahead: BTreeMap<u64, f64>,
    last_heard: Instant,
}

/// The merge buffer of one run.
#[derive(Debug)]
pub struct Merger {
    streams: HashMap<String, Stream>,
    pending: BTreeMap<OrderKey, Record>,
    /// Key of the last record handed out.
    applied: Option<OrderKey>,
    window: Duration,
}

impl Merger {
    /// `window`: how long a silent robot holds the others back.
    pub fn new(window: Duration) -> Self {
        Self {
            streams: HashMap::new(),
            pending: BTreeMap::new(),
            applied: None,
            window,
        }
    }

    /// Adds a robot whose records start after `t0` (its start time) and whose first record
    /// has sequence number `first_seq`.
    pub fn add_robot(&mut self, robot: &str, t0: f64, first_seq: u64, now: Instant) {
        self.streams.insert(
            robot.to_string(),
            Stream {
                next_seq: first_seq,
                watermark: t0,
                ahead: BTreeMap::new(),
                last_heard: now,
            },
        );
    }

    /// Restores a robot's stream after a restart from the sequence numbers and times of its
    /// stored records (`seqs`: seq -> t), which need not be contiguous.
    pub fn restore_robot(&mut self, robot: &str, t0: f64, seqs: &BTreeMap<u64, f64>, now: Instant) {
        let mut next_seq = 0;
        let mut watermark = t0;
        while let Some(t) = seqs.get(&next_seq) {
            watermark = *t;
            next_seq += 1;
        }
        let ahead = seqs.range(next_seq..).map(|(s, t)| (*s, *t)).collect();
        self.streams.insert(
            robot.to_string(),
            Stream {
                next_seq,
                watermark,
                ahead,
                last_heard: now,
            },
        );
    }

    /// Restores the key of the last record handed out (from a snapshot) after a restart.
    pub fn restore_applied(&mut self, key: Option<OrderKey>) {
        self.applied = key;
    }

    /// Puts back a stored record that was not applied before a restart; its stream was
    /// restored with [`Merger::restore_robot`], which already counts it.
    pub fn restore_pending(&mut self, r: Record) {
        self.pending.insert(OrderKey::of(&r), r);
    }

    /// The key of the last record handed out.
    pub fn applied_key(&self) -> Option<&OrderKey> {
        self.applied.as_ref()
    }

    pub fn has_robot(&self, robot: &str) -> bool {
        self.streams.contains_key(robot)
    }

    /// Time of the last record handed out for application.
    pub fn applied_t(&self) -> Option<f64> {
        self.applied.as_ref().map(OrderKey::t)
    }

    /// Records buffered, waiting for the other robots.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Records of one robot buffered in the merge.
    pub fn pending_of(&self, robot: &str) -> usize {
        self.pending.keys().filter(|k| k.robot == robot).count()
    }

    /// Checks that a record can still be merged, without taking it.
    pub fn check(&self, r: &Record) -> Result<(), MergeError> {
        let s = self
            .streams
            .get(&r.robot)
            .ok_or_else(|| MergeError::UnknownRobot(r.robot.clone()))?;
        if let Some(a) = &self.applied
            && OrderKey::of(r) <= *a
        {
            return Err(MergeError::TooOld {
                robot: r.robot.clone(),
                seq: r.seq,
                t: r.t,
                applied: a.t(),
            });
        }
        // Within a robot, time must not go back relative to its neighbours in seq.
        if r.seq >= s.next_seq && r.t < s.watermark {
            return Err(MergeError::TimeRegression {
                robot: r.robot.clone(),
                seq: r.seq,
                t: r.t,
                prev_seq: s.next_seq.saturating_sub(1),
                prev_t: s.watermark,
            });
        }
        Ok(())
    }

    /// Takes a record (already checked and stored). A record whose seq was already taken is
    /// ignored (it is a repeat).
    pub fn push(&mut self, r: Record, now: Instant) -> Result<(), MergeError> {
        self.check(&r)?;
        let s = self.streams.get_mut(&r.robot).expect("checked above");
        s.last_heard = now;
        if r.seq < s.next_seq || s.ahead.contains_key(&r.seq) {
            return Ok(());
        }
        if r.seq == s.next_seq {
            s.next_seq += 1;
            s.watermark = r.t;
            while let Some(t) = s.ahead.remove(&s.next_seq) {
                s.next_seq += 1;
                s.watermark = t;
            }
        } else {
            s.ahead.insert(r.seq, r.t);
        }
        self.pending.insert(OrderKey::of(&r), r);
        Ok(())
    }

    /// Records that are safe to apply now, in order. `flush` hands out everything (the run
    /// is ending).
    pub fn ready(&mut self, now: Instant, flush: bool) -> Vec<Record> {
        let mut out = Vec::new();
        while let Some((key, _)) = self.pending.first_key_value() {
            if !flush && !self.safe(key, now) {
                break;
            }
            let (key, rec) = self.pending.pop_first().expect("peeked above");
            self.applied = Some(key);
            out.push(rec);
        }
        out
    }

    fn safe(&self, key: &OrderKey, now: Instant) -> bool {
        // A record beyond a gap in its own robot's sequence waits for the gap to fill (or
        // for the robot to fall silent past the window).
        let own = &self.streams[&key.robot];
        let own_silent = now.duration_since(own.last_heard) > self.window;
        if key.seq >= own.next_seq && !own_silent {
            return false;
        }
        self.streams.iter().all(|(id, s)| {
            if *id == key.robot || now.duration_since(s.last_heard) > self.window {
                return true;
            }
            s.watermark > key.t() || (s.watermark == key.t() && id.as_str() > key.robot.as_str())
        })
    }

    /// When the next silent robot stops counting, so that the caller can wake up then.
    pub fn next_deadline(&self) -> Option<Instant> {
        if self.pending.is_empty() {
            return None;
        }
        self.streams
            .values()
            .map(|s| s.last_heard + self.window)
            .min()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleetslam_core::log::record_order;

    fn rec(robot: &str, seq: u64, t: f64) -> Record {
        Record {
            robot: robot.into(),
            seq,
            t,
            motion: None,
            landmarks: vec![],
            robots: vec![],
        }
    }

    fn streams() -> Vec<Record> {
        let mut v = Vec::new();
        for (robot, dt) in [("a", 0.1), ("b", 0.15), ("c", 0.1)] {
            for s in 0..20u64 {
                v.push(rec(robot, s, 0.5 + dt * s as f64));
            }
        }
        v
    }

    fn merger(now: Instant) -> Merger {
        let mut m = Merger::new(Duration::from_secs(3600));
        for r in ["a", "b", "c"] {
            m.add_robot(r, 0.0, 0, now);
        }
        m
    }

    #[test]
    fn arrival_order_does_not_matter() {
        let mut sorted = streams();
        sorted.sort_by(record_order);
        let now = Instant::now();
        // Interleave the robots' streams in many different ways (each robot in seq order, as
        // a robot client posts), and also with seq shuffled within a few places.
        for rot in 0..7usize {
            let mut m = merger(now);
            let mut out = Vec::new();
            let mut queues: Vec<Vec<Record>> = ["a", "b", "c"]
                .iter()
                .map(|id| streams().into_iter().filter(|r| r.robot == *id).collect())
                .collect();
            let mut k = rot;
            while queues.iter().any(|q| !q.is_empty()) {
                let q = &mut queues[k % 3];
                k = k.wrapping_mul(7).wrapping_add(rot + 1);
                if q.is_empty() {
                    continue;
                }
                // Occasionally deliver the second record before the first.
                let idx = if q.len() > 1 && k % 5 == 0 { 1 } else { 0 };
                m.push(q.remove(idx), now).unwrap();
                out.extend(m.ready(now, false));
            }
            out.extend(m.ready(now, true));
            assert_eq!(out, sorted, "rotation {rot}");
        }
    }

    #[test]
    fn too_old_records_are_refused() {
        let now = Instant::now();
        let mut m = merger(now);
        m.push(rec("a", 0, 1.0), now).unwrap();
        m.push(rec("b", 0, 2.0), now).unwrap();
        m.push(rec("c", 0, 2.0), now).unwrap();
        assert_eq!(m.ready(now, false).len(), 1);
        assert_eq!(m.applied_t(), Some(1.0));
        // A repeat of an applied record is refused as too old (the server acknowledges a
        // repeat from the store before it reaches the merger).
        assert!(matches!(
            m.check(&rec("a", 0, 1.0)),
            Err(MergeError::TooOld { .. })
        ));
        let err = m.check(&rec("b", 1, 0.5)).unwrap_err();
        assert!(
            err.to_string()
                .contains("older than what the run has already applied"),
            "{err}"
        );
        assert!(matches!(
            m.check(&rec("z", 0, 5.0)),
            Err(MergeError::UnknownRobot(_))
        ));
        let err = m.check(&rec("b", 1, 1.5)).unwrap_err();
        assert!(matches!(err, MergeError::TimeRegression { .. }), "{err}");
    }

    #[test]
    fn silent_robot_stops_holding_the_others() {
        let t0 = Instant::now();
        let mut m = Merger::new(Duration::from_millis(100));
        m.add_robot("a", 0.0, 0, t0);
        m.add_robot("b", 0.0, 0, t0);
        m.push(rec("a", 0, 1.0), t0).unwrap();
        assert!(
            m.ready(t0, false).is_empty(),
            "b may still send something earlier"
        );
        assert!(m.next_deadline().unwrap() <= t0 + Duration::from_millis(100));
        let later = t0 + Duration::from_millis(150);
        assert_eq!(m.ready(later, false).len(), 1);
    }

    #[test]
    fn gap_in_a_robots_sequence_waits_then_fills() {
        let now = Instant::now();
        let mut m = merger(now);
        for r in ["b", "c"] {
            m.push(rec(r, 0, 10.0), now).unwrap();
        }
        m.push(rec("a", 1, 2.0), now).unwrap();
        assert!(m.ready(now, false).is_empty(), "a's seq 0 is missing");
        m.push(rec("a", 0, 1.0), now).unwrap();
        let got: Vec<_> = m
            .ready(now, false)
            .into_iter()
            .map(|r| (r.robot, r.seq))
            .collect();
        assert_eq!(got, vec![("a".to_string(), 0), ("a".to_string(), 1)]);
    }
}
