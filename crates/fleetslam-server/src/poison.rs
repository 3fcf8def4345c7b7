//! Poison isolation: a record that makes the filter fail or panic is quarantined, and the
//! run goes on.
//!
//! A step that returns an error or panics (also inside the filter's rayon workers: rayon
//! hands the panic back to the stepping thread) may have left the filter half-updated, so
//! the filter is not trusted after it: it is rebuilt from the copy taken with the latest
//! snapshot (`base`) and the records applied since, without the poison record. Every draw
//! of the filter is a function of (seed, step, particle), so the rebuilt filter is exactly
//! the one a restart computes (latest snapshot, then the stored non-quarantined records
//! after it) and the one an offline run of the log without that record computes.
//!
//! The same guarded step serves the live coordinator, recovery (through it) and the state
//! at a time ([`crate::history::state_at`]).

use fleetslam_core::log::Record;
use fleetslam_learned::RecordingUpdater;
use fleetslam_localize::LateJoinSlam;
use fleetslam_localize::joining::JoinStep;
use fleetslam_store::StoredObservation;
use std::any::Any;
use std::panic::{AssertUnwindSafe, catch_unwind};

/// The message of a caught panic.
pub fn panic_message(payload: &(dyn Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".to_string()
    }
}

/// Steps `r`, catching a panic. `Err` holds why the record is poison; the filter must then
/// be rebuilt ([`rebuild`]) before it is used again.
pub fn try_step(filter: &mut LateJoinSlam, r: &Record) -> Result<JoinStep, String> {
    match catch_unwind(AssertUnwindSafe(|| filter.step(r))) {
        Ok(Ok(step)) => Ok(step),
        Ok(Err(e)) => Err(format!("the filter refused it: {e}")),
        Err(panic) => Err(format!(
            "the filter panicked on it: {}",
            panic_message(&*panic)
        )),
    }
}

/// The filter `base` after `since` (records that applied before, in the order they were
/// applied). `recorder` is the run's training recorder, if any: the rows it holds were
/// recorded since `base` was taken (a snapshot drains them), so they are dropped and
/// recorded again by the replay, and the poison record's partial updates leave no row.
/// `Err` when a record that applied before fails now, which would be a bug: the caller
/// fails the run.
pub fn rebuild(
    base: &LateJoinSlam,
    since: &[Record],
    recorder: Option<&RecordingUpdater>,
) -> Result<LateJoinSlam, String> {
    if let Some(r) = recorder {
        r.drain_rows();
    }
    let mut filter = base.clone();
    for r in since {
        try_step(&mut filter, r).map_err(|e| {
            format!(
                "rebuilding the filter after a quarantined record: record {} of robot {:?}, \
                 which applied before, failed: {e}",
                r.seq, r.robot
            )
        })?;
    }
    Ok(filter)
}

/// A stored record that is not to be applied, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    pub robot: String,
    pub seq: u64,
    pub reason: String,
    /// True when the store already has it quarantined; false when it was found unreadable
    /// just now (the caller may mark it).
    pub marked: bool,
}

/// The records of `stored` to apply, and those to skip: quarantined ones and those whose
/// body cannot be parsed back.
pub fn usable(stored: &[StoredObservation]) -> (Vec<Record>, Vec<Skipped>) {
    let mut records = Vec::with_capacity(stored.len());
    let mut skipped = Vec::new();
    for o in stored {
        let seq = o.seq.max(0) as u64;
        if let Some(reason) = &o.rejected {
            skipped.push(Skipped {
                robot: o.robot_id.clone(),
                seq,
                reason: reason.clone(),
                marked: true,
            });
            continue;
        }
        match serde_json::from_str::<Record>(&o.body) {
            Ok(r) if r.robot == o.robot_id && r.seq == seq => records.push(r),
            Ok(r) => skipped.push(Skipped {
                robot: o.robot_id.clone(),
                seq,
                reason: format!(
                    "its stored body is record {} of robot {:?}, not the one stored under its key",
                    r.seq, r.robot
                ),
                marked: false,
            }),
            Err(e) => skipped.push(Skipped {
                robot: o.robot_id.clone(),
                seq,
                reason: format!("its stored body cannot be parsed: {e}"),
                marked: false,
            }),
        }
    }
    (records, skipped)
}
