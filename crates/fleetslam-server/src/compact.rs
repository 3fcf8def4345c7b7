//! Compact live states, for a websocket client that asks for them (`GET
//! /v1/runs/{run}/live?landmarks=delta`; the dashboard does).
//!
//! A full state carries every landmark with its covariance: with 5,000 landmarks about
//! 0.8 MB, ten times a second. Most landmarks do not change between two states (only those
//! in view of a robot do, unless the best particle changes to one with another map), so a
//! compact state carries only the landmarks that changed since the state this connection
//! was last sent, and the slots of those that went away:
//!
//! ```json
//! {"type": "state", "state": {... every field but "landmarks" ...},
//!  "landmarks": {"reset": false, "count": 5000,
//!                "upsert": [[slot, id|null, x, y, z, xx, xy, xz, yy, yz, zz], ...],
//!                "remove": [slot, ...]}}
//! ```
//!
//! The first message of a connection has `reset: true` and every landmark. Numbers are
//! rounded to what a map shows: positions to [`POSITION_STEP`], covariances to
//! [`COVARIANCE_STEP`], particle poses to [`POSITION_STEP`] (headings to [`HEADING_STEP`]) and
//! their weights to [`WEIGHT_STEP`]; a landmark counts as changed when its rounded numbers do.

use crate::coordinator::{LandmarkState, RunState};
use serde::Serialize;
use serde_json::Value;
use std::collections::{BTreeMap, HashMap};

/// Resolution of positions in compact states [m].
pub const POSITION_STEP: f64 = 1e-3;
/// Resolution of landmark covariances in compact states [m^2] (a 2-sigma axis of 1 mm).
pub const COVARIANCE_STEP: f64 = 1e-6;
/// Resolution of particle headings in compact states [rad].
pub const HEADING_STEP: f64 = 1e-3;
/// Resolution of particle weights in compact states.
pub const WEIGHT_STEP: f64 = 1e-6;

/// `v` in units of `step`.
fn units(v: f64, step: f64) -> i64 {
    (v / step).round() as i64
}

/// `v` rounded to `step`, as the float whose shortest decimal form is the rounded value.
fn rounded(v: f64, step: f64) -> f64 {
    if !v.is_finite() {
        return v;
    }
    // Dividing by the exact reciprocal gives the double nearest to k * step.
    (v / step).round() / (1.0 / step).round()
}

/// A landmark's numbers in units of their resolution: what decides whether it changed.
fn key(l: &LandmarkState) -> [i64; 9] {
    let mut k = [0; 9];
    for (i, m) in l.mean.iter().enumerate() {
        k[i] = units(*m, POSITION_STEP);
    }
    for (i, c) in l.cov.iter().enumerate() {
        k[3 + i] = units(*c, COVARIANCE_STEP);
    }
    k
}

/// The state without its landmarks, its particle sample rounded.
#[derive(Serialize)]
struct Lean<'a> {
    run: &'a str,
    status: &'a str,
    applied: u64,
    t: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    t_start: Option<f64>,
    ess: f64,
    particles: usize,
    resamples: u64,
    robots: &'a [crate::coordinator::RobotStatus],
    particle_sample: BTreeMap<&'a str, Vec<[f64; 4]>>,
    step_ms: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    reason: Option<&'a str>,
}

#[derive(Serialize)]
struct Delta {
    reset: bool,
    count: usize,
    upsert: Vec<Value>,
    remove: Vec<usize>,
}

/// What one connection was sent of the landmarks.
#[derive(Debug, Default)]
pub struct LandmarkDelta {
    sent: HashMap<usize, [i64; 9]>,
    /// Nothing sent yet: the next message resets the client's map.
    started: bool,
}

impl LandmarkDelta {
    pub fn new() -> Self {
        Self::default()
    }

    /// The compact `state` message of `s` for this connection, which then counts as sent.
    pub fn message(&mut self, s: &RunState) -> String {
        let reset = !self.started;
        self.started = true;
        let mut upsert = Vec::new();
        let mut seen: HashMap<usize, [i64; 9]> = HashMap::with_capacity(s.landmarks.len());
        for l in &s.landmarks {
            let k = key(l);
            if self.sent.get(&l.slot) != Some(&k) {
                let mut row = vec![Value::from(l.slot), l.id.map_or(Value::Null, Value::from)];
                row.extend(
                    l.mean
                        .iter()
                        .map(|m| Value::from(rounded(*m, POSITION_STEP))),
                );
                row.extend(
                    l.cov
                        .iter()
                        .map(|c| Value::from(rounded(*c, COVARIANCE_STEP))),
                );
                upsert.push(Value::Array(row));
            }
            seen.insert(l.slot, k);
        }
        let mut remove: Vec<usize> = self
            .sent
            .keys()
            .filter(|slot| !seen.contains_key(slot))
            .copied()
            .collect();
        remove.sort_unstable();
        self.sent = seen;
        let lean = Lean {
            run: &s.run,
            status: &s.status,
            applied: s.applied,
            t: s.t,
            t_start: s.t_start,
            ess: s.ess,
            particles: s.particles,
            resamples: s.resamples,
            robots: &s.robots,
            particle_sample: s
                .particle_sample
                .iter()
                .map(|(id, ps)| {
                    let ps = ps
                        .iter()
                        .map(|p| {
                            [
                                rounded(p[0], POSITION_STEP),
                                rounded(p[1], POSITION_STEP),
                                rounded(p[2], HEADING_STEP),
                                rounded(p[3], WEIGHT_STEP),
                            ]
                        })
                        .collect();
                    (id.as_str(), ps)
                })
                .collect(),
            step_ms: s.step_ms,
            reason: s.reason.as_deref(),
        };
        serde_json::json!({
            "type": "state",
            "state": lean,
            "landmarks": Delta {
                reset,
                count: s.landmarks.len(),
                upsert,
                remove,
            },
        })
        .to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn landmark(slot: usize, x: f64) -> LandmarkState {
        LandmarkState {
            slot,
            id: Some(slot as u32 + 100),
            mean: [x, 2.0, 0.0],
            cov: [0.01, 0.001, 0.0, 0.02, 0.0, 0.0],
        }
    }

    fn state(landmarks: Vec<LandmarkState>) -> RunState {
        RunState {
            run: "r".into(),
            status: "active".into(),
            applied: 3,
            t: Some(1.5),
            t_start: Some(0.5),
            ess: 12.5,
            particles: 20,
            resamples: 1,
            robots: Vec::new(),
            landmarks,
            particle_sample: [("1".to_string(), vec![[1.23456789, -2.0, 0.1234567, 0.05]])]
                .into_iter()
                .collect(),
            step_ms: 0.25,
            reason: None,
        }
    }

    fn parse(msg: &str) -> Value {
        serde_json::from_str(msg).unwrap()
    }

    /// Applying the messages to an empty map gives the states' landmarks (rounded), and
    /// each message carries only what changed.
    #[test]
    fn deltas_rebuild_the_landmarks_and_carry_only_changes() {
        let mut d = LandmarkDelta::new();
        let mut client: BTreeMap<u64, Vec<f64>> = BTreeMap::new();
        let mut apply = |m: &Value| {
            if m["landmarks"]["reset"].as_bool().unwrap() {
                client.clear();
            }
            for row in m["landmarks"]["upsert"].as_array().unwrap() {
                let row = row.as_array().unwrap();
                let nums = row[2..].iter().map(|v| v.as_f64().unwrap()).collect();
                client.insert(row[0].as_u64().unwrap(), nums);
            }
            for slot in m["landmarks"]["remove"].as_array().unwrap() {
                client.remove(&slot.as_u64().unwrap());
            }
            assert_eq!(
                m["landmarks"]["count"].as_u64().unwrap() as usize,
                client.len()
            );
            client.clone()
        };
        let first = parse(&d.message(&state(vec![landmark(0, 1.0), landmark(1, 3.0)])));
        assert_eq!(first["landmarks"]["upsert"].as_array().unwrap().len(), 2);
        assert!(first["state"].get("landmarks").is_none());
        apply(&first);
        // Landmark 0 moves by less than the resolution, 1 moves, 2 is new.
        let m = parse(&d.message(&state(vec![
            landmark(0, 1.0 + 0.2 * POSITION_STEP),
            landmark(1, 3.5),
            landmark(2, 7.0),
        ])));
        assert!(!m["landmarks"]["reset"].as_bool().unwrap());
        let slots: Vec<u64> = m["landmarks"]["upsert"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r[0].as_u64().unwrap())
            .collect();
        assert_eq!(slots, vec![1, 2]);
        let map = apply(&m);
        assert_eq!(map[&1][0], 3.5);
        assert_eq!(
            map[&2],
            vec![7.0, 2.0, 0.0, 0.01, 0.001, 0.0, 0.02, 0.0, 0.0]
        );
        // Landmark 1 goes away.
        let m = parse(&d.message(&state(vec![landmark(0, 1.0), landmark(2, 7.0)])));
        assert_eq!(m["landmarks"]["remove"], serde_json::json!([1]));
        assert!(m["landmarks"]["upsert"].as_array().unwrap().is_empty());
        assert_eq!(apply(&m).len(), 2);
        // Nothing changed: nothing sent.
        let m = parse(&d.message(&state(vec![landmark(0, 1.0), landmark(2, 7.0)])));
        assert!(m["landmarks"]["upsert"].as_array().unwrap().is_empty());
        assert!(m["landmarks"]["remove"].as_array().unwrap().is_empty());
    }

    /// A compact state has every field of the full one but the landmarks, the particle
    /// sample rounded to its resolutions.
    #[test]
    fn a_compact_state_has_every_other_field() {
        let s = state(vec![landmark(0, 1.0)]);
        let full = serde_json::to_value(&s).unwrap();
        let compact = parse(&LandmarkDelta::new().message(&s));
        let mut keys: Vec<&String> = full.as_object().unwrap().keys().collect();
        keys.retain(|k| *k != "landmarks");
        let lean: Vec<&String> = compact["state"].as_object().unwrap().keys().collect();
        assert_eq!(
            keys.iter().collect::<std::collections::BTreeSet<_>>(),
            lean.iter().collect()
        );
        assert_eq!(
            compact["state"]["particle_sample"]["1"],
            serde_json::json!([[1.235, -2.0, 0.123, 0.05]])
        );
        assert_eq!(compact["state"]["ess"], full["ess"]);
    }
}
