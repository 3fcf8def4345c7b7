//! Recovery on start: every run the store still lists as active is loaded again from its
//! latest snapshot, and the records stored after that snapshot go back into the merge, so
//! the run continues exactly as if the server had never stopped (same records, same order,
//! same random streams: the filter's randomness is a function of (seed, step, particle)).
//!
//! Quarantined records are skipped, and a stored record whose body cannot be parsed back is
//! quarantined now instead of failing the recovery. A run that cannot be recovered becomes
//! `failed` in the store with the reason: it is no longer tried on each start, and it can
//! still be read, exported and deleted.

use crate::app::AppState;
use crate::coordinator::{Clock, Recovered};
use crate::error::ApiError;
use crate::history::{self, RunSnapshot, Trajectories};
use fleetslam_core::config::FilterConfig;
use fleetslam_core::pose::PoseGaussian;
use fleetslam_store::RunRow;
use std::collections::{BTreeMap, HashMap};
use std::time::Instant;

/// Recovers every active run; returns how many were recovered. A run that cannot be
/// recovered is marked `failed` in the store with the reason.
pub async fn recover(state: &AppState) -> Result<usize, ApiError> {
    let mut n = 0;
    for row in state.store.active_runs().await? {
        let started = Instant::now();
        match recover_run(state, &row, Clock::Wall).await {
            Ok(pending) => {
                n += 1;
                tracing::info!(
                    run = %row.id,
                    records = row.records,
                    replayed = pending,
                    ms = started.elapsed().as_millis() as u64,
                    "run recovered"
                );
            }
            Err(e) => {
                tracing::error!(run = %row.id, error = %e, "run could not be recovered: it is marked failed");
                let reason = format!("its recovery failed: {}", cause(&e));
                if let Err(e) = state.store.set_run_failed(&row.id, &reason).await {
                    tracing::error!(run = %row.id, error = %e, "marking the run failed failed");
                }
            }
        }
    }
    Ok(n)
}

/// Loads one run (its merge on `clock`); returns how many records it has to apply again.
pub(crate) async fn recover_run(
    state: &AppState,
    row: &RunRow,
    clock: Clock,
) -> Result<usize, ApiError> {
    let store = &state.store;
    let config: FilterConfig = serde_json::from_value(row.config.clone())
        .map_err(|e| ApiError::internal(anyhow::anyhow!("stored config: {e}")))?;
    let robots = store.robots(&row.id).await?;
    let updater = history::updater_for(store, &config).await?;
    let snap = match store.latest_snapshot(&row.id).await? {
        Some(s) => Some(
            tokio::task::spawn_blocking(move || RunSnapshot::decode(&s.data))
                .await
                .map_err(ApiError::internal)??,
        ),
        None => None,
    };
    // Before its first snapshot a run starts from what it was created with.
    let setup = match store.get_artifact(&row.id, crate::app::SETUP).await? {
        Some(body) => serde_json::from_str::<crate::app::RunSetup>(&body)
            .map_err(|e| ApiError::internal(anyhow::anyhow!("stored run setup: {e}")))?,
        None => crate::app::RunSetup::default(),
    };
    let training_cfg = match &snap {
        Some(s) => s.training,
        None => setup.training,
    };
    let (updater, training) = history::recording(updater, training_cfg)?;
    let (mut filter, applied, last, mut trajectories, stored_lens) = match snap {
        Some(snap) => {
            let last = snap.last_key();
            let trajectories = snap.load_trajectories(store, &row.id).await?;
            let stored_lens = snap.trajectory_lens.clone().unwrap_or_default();
            let filter = history::restore_filter(snap.filter, updater)?;
            (filter, snap.applied, last, trajectories, stored_lens)
        }
        None => (
            history::new_filter(&config, setup.localize.unwrap_or_default(), updater)?,
            0,
            None,
            Trajectories::new(),
            BTreeMap::new(),
        ),
    };
    // A robot stored but not in the latest snapshot was being registered when the server
    // stopped (its registration was never answered): add it now. In a cluster its
    // registration is in the run's stream after the owner's position, and adds it at its
    // place in the run's order (crate::cluster).
    let from_stream = matches!(clock, Clock::Stream(_));
    for r in &robots {
        if from_stream || filter.phase(&r.robot_id).is_some() {
            continue;
        }
        let again = |e: fleetslam_localize::LocalizeError| {
            ApiError::internal(anyhow::anyhow!("re-adding a robot: {e}"))
        };
        match &r.start {
            Some(start) => {
                let start: PoseGaussian = serde_json::from_value(start.clone())
                    .map_err(|e| ApiError::internal(anyhow::anyhow!("stored start pose: {e}")))?;
                let t0 = r.t0.unwrap_or(0.0);
                let i = filter.add_robot(&r.robot_id, &start, t0).map_err(again)?;
                trajectories.insert(
                    r.robot_id.clone(),
                    vec![history::trajectory_point(filter.slam(), i, t0)],
                );
            }
            None => filter.add_unknown_robot(&r.robot_id).map_err(again)?,
        }
    }
    let stored = history::all_records(store, &row.id).await?;
    let mut seqs: HashMap<&str, BTreeMap<u64, f64>> = HashMap::new();
    for o in &stored {
        seqs.entry(o.robot_id.as_str())
            .or_default()
            .insert(o.seq as u64, o.t);
    }
    let robot_states = robots
        .iter()
        .filter(|r| filter.phase(&r.robot_id).is_some())
        .map(|r| {
            (
                r.robot_id.clone(),
                r.t0.unwrap_or(0.0),
                seqs.get(r.robot_id.as_str()).cloned().unwrap_or_default(),
            )
        })
        .collect();
    let (records, skipped) = crate::poison::usable(&stored);
    let mut quarantined: BTreeMap<String, (u64, String)> = BTreeMap::new();
    for s in skipped {
        if !s.marked {
            tracing::warn!(run = %row.id, robot = %s.robot, seq = s.seq, reason = %s.reason, "stored record quarantined");
            store
                .quarantine(&row.id, &s.robot, s.seq as i64, &s.reason)
                .await?;
        }
        let q = quarantined.entry(s.robot).or_insert((0, String::new()));
        q.0 += 1;
        q.1 = s.reason;
    }
    let pending = history::records_after_snapshot(records, &filter, last.as_ref(), None);
    let n = pending.len();
    let tokens = robots
        .iter()
        .map(|r| (r.token_hash.clone(), r.robot_id.clone()))
        .collect();
    let enrollment = crate::app::stored_enrollment(store, &row.id).await?;
    state
        .insert_live(
            row.id.clone(),
            config,
            filter,
            Some(Recovered {
                applied,
                last,
                trajectories: crate::track::TrajectoryLog::from_map(trajectories),
                trajectories_stored: stored_lens,
                robots: robot_states,
                pending,
                quarantined,
            }),
            tokens,
            enrollment,
            training,
            clock,
        )
        .await;
    Ok(n)
}

/// An error's full message, the cause of an internal one included (it is stored as the
/// reason of the failed run, for its operator).
fn cause(e: &ApiError) -> String {
    match e {
        ApiError::Internal(inner) => format!("{inner:#}"),
        other => other.to_string(),
    }
}
