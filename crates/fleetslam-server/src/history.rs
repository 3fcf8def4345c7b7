//! What a run leaves behind and how it is read back: the snapshots the coordinator stores
//! (filter, merge position and trajectories, so that a restart continues bit for bit), the
//! final result, ground truth, the state at a chosen time (latest snapshot before it, then
//! the stored log up to it), and exports in the files `fleetslam run` writes.

use crate::coordinator::{LandmarkState, RobotStatus, RunState};
use crate::error::ApiError;
use crate::merge::OrderKey;
use fleetslam_core::config::{EKF_UPDATER, FilterConfig};
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::{Record, record_order};
use fleetslam_core::pose::Pose2;
use fleetslam_core::updater::LandmarkUpdater;
use fleetslam_data::formats::{LandmarkRow, TrajectoryPoint, Truth};
use fleetslam_learned::{
    MlpModel, MlpUpdater, RecordingConfig, RecordingUpdater, STORE_MODEL_KIND,
};
use fleetslam_localize::{LateJoinSlam, LateJoinSnapshot, LocalizeConfig};
use fleetslam_store::{MAX_RECORDS_PAGE, Store, StoredObservation};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Per-robot trajectories as `[t, x, y, theta]`: the robot's estimated (weighted mean) pose
/// at its start and after each of its records, exactly as `fleetslam run` records them.
pub type Trajectories = BTreeMap<String, Vec<[f64; 4]>>;

/// Artifact name of a finished run's result ([`RunResult`]).
pub const RESULT: &str = "result";
/// Artifact name of a run's ground truth ([`truth_to_json`]).
pub const TRUTH: &str = "truth";

/// A stored snapshot of a running run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunSnapshot {
    /// The filter with its localizers of robots that joined at an unknown pose.
    pub filter: LateJoinSnapshot,
    /// Records applied.
    pub applied: u64,
    /// Key `(t, robot, seq)` of the last record applied: every stored record of a merged
    /// robot ordered before or at it is in `filter`, every later one is not.
    pub last: Option<(f64, String, u64)>,
    /// The trajectories, in snapshots written before trajectories were stored in pieces
    /// (empty in newer ones: see `trajectory_lens`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub trajectories: Trajectories,
    /// How many points of each robot's trajectory the snapshot covers; the points are in
    /// the store's trajectory pieces (each snapshot stores those added since the previous
    /// one), so a snapshot does not grow with the run's length. `None` in older snapshots,
    /// which carry `trajectories` whole.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trajectory_lens: Option<BTreeMap<String, usize>>,
    /// The sampling of landmark updates as training rows, when the run logs them.
    #[serde(default)]
    pub training: Option<RecordingConfig>,
}

impl RunSnapshot {
    pub fn last_key(&self) -> Option<OrderKey> {
        self.last
            .as_ref()
            .map(|(t, robot, seq)| OrderKey::new(*t, robot, *seq))
    }

    /// The time a snapshot is filed under: that of its last record, or before any time.
    pub fn filed_t(&self) -> f64 {
        self.last.as_ref().map_or(f64::MIN, |l| l.0)
    }

    /// The tracks this snapshot covers: the trajectories it carries (older snapshots), or
    /// the trajectories and the filter's series ([`crate::track::FILTER_TRACK`])
    /// reassembled from the run's stored pieces.
    pub async fn load_trajectories(
        &self,
        store: &Store,
        run: &str,
    ) -> Result<Trajectories, ApiError> {
        match &self.trajectory_lens {
            None => Ok(self.trajectories.clone()),
            Some(lens) => {
                let chunks = store.trajectory_chunks(run).await?;
                let lens = lens.clone();
                tokio::task::spawn_blocking(move || assemble_trajectories(chunks, &lens))
                    .await
                    .map_err(ApiError::internal)?
            }
        }
    }

    /// The snapshot as stored: CBOR (RFC 8949, the `ciborium` crate). A snapshot is mostly
    /// the particles' floats, which CBOR writes as their 8 bytes where JSON wrote each as
    /// its shortest decimal: on MRCLAM's first 300 s with 1,000 particles the last snapshot
    /// is 2.2 MB in CBOR against 4.1 MB in JSON, encoded in 5-7 ms against 7 ms and stored
    /// on SQLite in 5-9 ms against 12-14 ms (`recovery_cost`, README, session 24). Both give
    /// back the same bits.
    pub fn encode(&self) -> Result<Vec<u8>, ApiError> {
        let mut out = Vec::new();
        self.encode_into(&mut out)?;
        Ok(out)
    }

    /// [`RunSnapshot::encode`] into `out`, which is cleared first and keeps its capacity.
    /// A run's snapshot writer passes the buffer of its last snapshot: grown by doubling
    /// from empty, the buffer of a 2 MB snapshot is reallocated about 18 times, and the
    /// kernel's zeroing of fresh pages was the largest single part of the async runtime's
    /// samples under `perf`, about half of it under this buffer (README, sessions 26-27).
    pub fn encode_into(&self, out: &mut Vec<u8>) -> Result<(), ApiError> {
        out.clear();
        ciborium::into_writer(self, out).map_err(|e| {
            ApiError::internal(anyhow::anyhow!("a snapshot could not be encoded: {e}"))
        })
    }

    /// A stored snapshot: CBOR ([`RunSnapshot::encode`]), or JSON as snapshots were stored
    /// before session 24. A JSON snapshot is an object and starts with `{`, which no CBOR
    /// map does (its first byte is 0xa0-0xbf), so the first byte tells them apart.
    pub fn decode(data: &[u8]) -> Result<Self, ApiError> {
        let unreadable =
            |e: &dyn std::fmt::Display| anyhow::anyhow!("a stored snapshot is unreadable: {e}");
        if data.first() == Some(&b'{') {
            serde_json::from_slice(data).map_err(|e| ApiError::internal(unreadable(&e)))
        } else {
            ciborium::from_reader(data).map_err(|e| ApiError::internal(unreadable(&e)))
        }
    }
}

/// The stored pieces of a run's trajectories as of a snapshot that covers `lens` points of
/// each robot: pieces are laid end to end (a piece written again after a crash may overlap
/// the next; points are deterministic, so overlaps agree) and cut to `lens`; points beyond
/// (written for a snapshot that a crash kept from being stored) are left out.
pub fn assemble_trajectories(
    chunks: Vec<fleetslam_store::TrajectoryChunk>,
    lens: &BTreeMap<String, usize>,
) -> Result<Trajectories, ApiError> {
    let mut out: Trajectories = lens.keys().map(|r| (r.clone(), Vec::new())).collect();
    for c in chunks {
        let Some(pts) = out.get_mut(&c.robot_id) else {
            continue;
        };
        let want = lens[&c.robot_id];
        let first = usize::try_from(c.first).unwrap_or(usize::MAX);
        if pts.len() >= want || first > pts.len() {
            continue;
        }
        lay_piece(pts, first, &c)?;
        pts.truncate(want);
    }
    for (robot, pts) in &out {
        if pts.len() != lens[robot] {
            return Err(ApiError::internal(anyhow::anyhow!(
                "the stored trajectory of robot {robot:?} has {} points where its snapshot \
                 covers {}",
                pts.len(),
                lens[robot]
            )));
        }
    }
    Ok(out)
}

/// Lays the stored piece `c`, whose first point has index `first` (at most `pts.len()`),
/// at the end of `pts`, skipping the points `pts` already has (a piece written again after
/// a crash overlaps the next one; the first one stored wins where they overlap).
fn lay_piece(
    pts: &mut Vec<[f64; 4]>,
    first: usize,
    c: &fleetslam_store::TrajectoryChunk,
) -> Result<(), ApiError> {
    let piece: Vec<[f64; 4]> = serde_json::from_str(&c.points).map_err(|e| {
        ApiError::internal(anyhow::anyhow!(
            "a stored trajectory piece of robot {:?} is unreadable: {e}",
            c.robot_id
        ))
    })?;
    let skip = pts.len() - first;
    pts.extend(piece.into_iter().skip(skip));
    Ok(())
}

/// A run's stored filter series ([`crate::track::FILTER_TRACK`]): its pieces laid end to
/// end ([`lay_piece`]).
pub async fn stored_series(
    store: &Store,
    run: &str,
) -> Result<Vec<crate::track::FilterPoint>, ApiError> {
    let chunks = store.track_chunks(run, crate::track::FILTER_TRACK).await?;
    tokio::task::spawn_blocking(move || {
        let mut out: Vec<crate::track::FilterPoint> = Vec::new();
        for c in chunks {
            let first = usize::try_from(c.first).unwrap_or(usize::MAX);
            if first > out.len() {
                return Err(ApiError::internal(anyhow::anyhow!(
                    "the stored filter series has a hole before point {first}"
                )));
            }
            lay_piece(&mut out, first, &c)?;
        }
        Ok(out)
    })
    .await
    .map_err(ApiError::internal)?
}

/// The pieces to store with a snapshot: the points of `new` (robot -> points from index
/// `from[robot]` on), encoded.
pub fn trajectory_chunks(
    new: &Trajectories,
    from: &BTreeMap<String, usize>,
) -> Result<Vec<fleetslam_store::TrajectoryChunk>, ApiError> {
    new.iter()
        .map(|(robot, pts)| {
            Ok(fleetslam_store::TrajectoryChunk {
                robot_id: robot.clone(),
                first: from.get(robot).copied().unwrap_or(0) as i64,
                points: serde_json::to_string(pts).map_err(ApiError::internal)?,
            })
        })
        .collect()
}

/// Timing and counts of a run, for comparisons.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct RunMetrics {
    pub applied: u64,
    /// Data time of the earliest trajectory point (a start pose) [s].
    pub t_start: Option<f64>,
    pub step_ms_p50: f64,
    pub step_ms_p95: f64,
    pub step_ms_mean: f64,
    pub landmark_updates: u64,
    pub ns_per_landmark_update: f64,
    pub updater: String,
    pub particles: usize,
    pub seed: u64,
    pub resamples: u64,
    pub landmarks: usize,
    pub final_ess: f64,
    /// The filter's step time in this process per particle and record [ns] (a live run has
    /// no single wall time: the sum of its step times stands for it).
    #[serde(default)]
    pub ns_per_particle_record: f64,
    /// The same per particle and landmark observation of those steps [ns].
    #[serde(default)]
    pub ns_per_particle_observation: f64,
}

/// What a run leaves when it ends: its final state, trajectories and metrics.
#[derive(Debug, Clone, Serialize)]
pub struct RunResult<'a> {
    pub state: &'a RunState,
    pub trajectories: &'a Trajectories,
    pub metrics: &'a RunMetrics,
}

/// The mean pose of robot `i`, as a trajectory point at `t`.
pub fn trajectory_point(filter: &FastSlam, i: usize, t: f64) -> [f64; 4] {
    let p = filter.mean_pose(i);
    [t, p.x, p.y, p.theta]
}

/// The filter's point after a record stepped in `ns` nanoseconds (see
/// [`crate::track::FilterPoint`]): a step that moved the map reports its ESS and landmarks;
/// one that did not (a robot being localized) leaves them as they were (`last`), and before
/// any such step the map is empty and every particle weighs the same.
pub fn filter_point(
    filter: &FastSlam,
    rep: Option<&fleetslam_core::filter::StepReport>,
    last: Option<crate::track::FilterPoint>,
    t: f64,
    ns: u64,
) -> crate::track::FilterPoint {
    let (ess, landmarks) = match (rep, last) {
        (Some(r), _) => (r.ess, r.landmarks as f64),
        (None, Some(l)) => (l[1], l[3]),
        (None, None) => (filter.config().particles as f64, 0.0),
    };
    [t, ess, ns as f64 / 1e6, landmarks]
}

/// Trajectories and landmarks as the files `fleetslam run` writes.
pub fn to_truth(traj: &Trajectories, landmarks: &[LandmarkRow]) -> Truth {
    Truth {
        trajectories: traj
            .iter()
            .map(|(r, pts)| {
                let pts = pts
                    .iter()
                    .map(|p| TrajectoryPoint {
                        t: p[0],
                        pose: Pose2::new(p[1], p[2], p[3]),
                    })
                    .collect();
                (r.clone(), pts)
            })
            .collect(),
        landmarks: landmarks.to_vec(),
    }
}

pub fn landmark_rows(ls: &[LandmarkState]) -> Vec<LandmarkRow> {
    ls.iter()
        .map(|l| LandmarkRow {
            id: l.id,
            mean: l.mean,
            cov: l.cov,
        })
        .collect()
}

/// Ground truth (or an estimate) as JSON:
/// `{"robots": {"<id>": [[t, x, y, theta], ...]}, "landmarks": [{"id", "x", "y", "z"}]}`.
pub fn truth_to_json(t: &Truth) -> Value {
    let robots: BTreeMap<&String, Vec<[f64; 4]>> = t
        .trajectories
        .iter()
        .map(|(r, pts)| {
            (
                r,
                pts.iter()
                    .map(|p| [p.t, p.pose.x, p.pose.y, p.pose.theta])
                    .collect(),
            )
        })
        .collect();
    let landmarks: Vec<Value> = t
        .landmarks
        .iter()
        .map(|l| json!({"id": l.id, "x": l.mean[0], "y": l.mean[1], "z": l.mean[2]}))
        .collect();
    json!({ "robots": robots, "landmarks": landmarks })
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TruthJson {
    #[serde(default)]
    robots: BTreeMap<String, Vec<[f64; 4]>>,
    #[serde(default)]
    landmarks: Vec<TruthLandmark>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TruthLandmark {
    id: Option<u32>,
    x: f64,
    y: f64,
    #[serde(default)]
    z: f64,
}

/// Parses [`truth_to_json`]'s format, refusing non-finite numbers.
pub fn truth_from_json(body: &[u8]) -> Result<Truth, ApiError> {
    let de = &mut serde_json::Deserializer::from_slice(body);
    let t: TruthJson = serde_path_to_error::deserialize(de)
        .map_err(|e| ApiError::BadRequest(format!("truth: field `{}`: {}", e.path(), e.inner())))?;
    for (r, pts) in &t.robots {
        if let Some(i) = pts.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
            return Err(ApiError::BadRequest(format!(
                "truth: robot {r:?} point {i} has a non-finite number"
            )));
        }
    }
    if let Some(i) = t
        .landmarks
        .iter()
        .position(|l| !(l.x.is_finite() && l.y.is_finite() && l.z.is_finite()))
    {
        return Err(ApiError::BadRequest(format!(
            "truth: landmark {i} has a non-finite coordinate"
        )));
    }
    Ok(Truth {
        trajectories: t
            .robots
            .into_iter()
            .map(|(r, pts)| {
                let pts = pts
                    .into_iter()
                    .map(|p| TrajectoryPoint {
                        t: p[0],
                        pose: Pose2::new(p[1], p[2], p[3]),
                    })
                    .collect();
                (r, pts)
            })
            .collect(),
        landmarks: t
            .landmarks
            .into_iter()
            .map(|l| LandmarkRow {
                id: l.id,
                mean: [l.x, l.y, l.z],
                cov: [0.0; 6],
            })
            .collect(),
    })
}

/// The landmark updater a configuration names: the EKF, or a learned model stored in the
/// store (`fleetslam train --data-dir`), refused with a clear message when it is missing or
/// was trained for another landmark kind, input layout or sensor noise.
pub async fn updater_for(
    store: &Store,
    config: &FilterConfig,
) -> Result<Arc<dyn LandmarkUpdater>, ApiError> {
    if config.updater == EKF_UPDATER {
        return Ok(Arc::new(EkfUpdater::new(
            config.landmark_kind,
            &config.sensor_noise,
        )));
    }
    let refuse = |why: String| {
        ApiError::BadRequest(format!(
            "config: field `updater`: {why} (`ekf`, or the id of a stored model; list them with GET /v1/models)"
        ))
    };
    let Some(row) = store.get_model(&config.updater).await? else {
        return Err(refuse(format!(
            "no model {:?} in the store",
            config.updater
        )));
    };
    if row.kind != STORE_MODEL_KIND {
        return Err(refuse(format!(
            "model {:?} is a {:?}, not a landmark updater",
            row.id, row.kind
        )));
    }
    let model = MlpModel::from_json(&row.weights)
        .map_err(|e| ApiError::internal(anyhow::anyhow!("stored model {}: {e}", row.id)))?;
    let updater = MlpUpdater::for_run(model, config).map_err(|e| refuse(e.to_string()))?;
    Ok(Arc::new(updater))
}

/// How a run logs training rows: its sampling and the recorder that holds them.
pub type Training = (RecordingConfig, Arc<RecordingUpdater>);

/// Wraps `updater` so that a sample of its updates is kept as training rows, when asked.
pub fn recording(
    updater: Arc<dyn LandmarkUpdater>,
    training: Option<RecordingConfig>,
) -> Result<(Arc<dyn LandmarkUpdater>, Option<Training>), ApiError> {
    match training {
        None => Ok((updater, None)),
        Some(cfg) => {
            let r = Arc::new(
                RecordingUpdater::new(updater, cfg)
                    .map_err(|e| ApiError::BadRequest(format!("training: {e}")))?,
            );
            Ok((r.clone(), Some((cfg, r))))
        }
    }
}

/// A new run's filter for `config` with `updater`, localizing robots that join at an
/// unknown pose with `localize`.
pub fn new_filter(
    config: &FilterConfig,
    localize: LocalizeConfig,
    updater: Arc<dyn LandmarkUpdater>,
) -> Result<LateJoinSlam, ApiError> {
    let slam = FastSlam::with_updater(config.clone(), updater)
        .map_err(|e| ApiError::BadRequest(format!("config: {e}")))?;
    LateJoinSlam::from_slam(slam, localize)
        .map_err(|e| ApiError::BadRequest(format!("localize: {e}")))
}

/// Restores a filter from a snapshot with `updater` (the one its configuration names).
pub fn restore_filter(
    s: LateJoinSnapshot,
    updater: Arc<dyn LandmarkUpdater>,
) -> Result<LateJoinSlam, ApiError> {
    LateJoinSlam::from_snapshot(s, updater)
        .map_err(|e| ApiError::internal(anyhow::anyhow!("restoring a snapshot: {e}")))
}

/// Every stored record of a run, in arrival order (quarantined ones included, marked).
pub async fn all_records(store: &Store, run: &str) -> Result<Vec<StoredObservation>, ApiError> {
    let mut out = Vec::new();
    let mut after = 0;
    loop {
        let page = store.records_after(run, after, MAX_RECORDS_PAGE).await?;
        let Some(last) = page.last() else { break };
        after = last.arrival;
        let n = page.len();
        out.extend(page);
        if (n as i64) < MAX_RECORDS_PAGE {
            break;
        }
    }
    Ok(out)
}

/// The stored records of a run with a time in `from_t..=until_t`, in arrival order: through
/// the store's index on `(run_id, t)`, so the cost is those records, not the whole log.
pub async fn records_in_time(
    store: &Store,
    run: &str,
    from_t: f64,
    until_t: f64,
) -> Result<Vec<StoredObservation>, ApiError> {
    let mut out = Vec::new();
    let mut after = 0;
    loop {
        let page = store
            .records_in_time(run, from_t, until_t, after, MAX_RECORDS_PAGE)
            .await?;
        let Some(last) = page.last() else { break };
        after = last.arrival;
        let n = page.len();
        out.extend(page);
        if (n as i64) < MAX_RECORDS_PAGE {
            break;
        }
    }
    Ok(out)
}

/// The records to apply of stored ones: quarantined records and records whose stored body
/// cannot be parsed back are left out (see [`crate::poison::usable`]).
pub fn parse_records(obs: &[StoredObservation]) -> Vec<Record> {
    crate::poison::usable(obs).0
}

/// The records a filter restored from `snap` still has to apply, in the merge order: those
/// of robots in the filter ordered after the snapshot's last record, and, when `until` is
/// given, not later than it.
pub fn records_after_snapshot(
    mut records: Vec<Record>,
    filter: &LateJoinSlam,
    last: Option<&OrderKey>,
    until: Option<f64>,
) -> Vec<Record> {
    records.retain(|r| {
        filter.phase(&r.robot).is_some()
            && last.is_none_or(|k| OrderKey::of(r) > *k)
            && until.is_none_or(|u| r.t <= u)
    });
    records.sort_by(record_order);
    records
}

/// A run's state at a time, with its trajectories up to then.
#[derive(Debug)]
pub struct StateAt {
    pub state: RunState,
    pub trajectories: Trajectories,
}

/// The state of a run as of data time `t`: its latest snapshot at or before `t`, then its
/// stored records after the snapshot up to `t` (read by time, never the whole log), skipping
/// quarantined records and any record the filter fails or panics on, as the live run did.
/// Deterministic, so a scrubbed state equals what the live run showed after the same
/// records. The trajectories (which cost the whole run's points) are read only when asked
/// for; otherwise they are left empty.
pub async fn state_at(
    store: &Store,
    run: &str,
    status: &str,
    t: f64,
    particle_sample: usize,
    with_trajectories: bool,
) -> Result<StateAt, ApiError> {
    let snap = store.snapshot_at_or_before(run, t).await?;
    let Some(snap) = snap else {
        return Err(ApiError::NotFound(format!(
            "run {run} has no state at t={t}: it starts later (see GET /v1/runs/{run}/timeline)"
        )));
    };
    let snap = tokio::task::spawn_blocking(move || RunSnapshot::decode(&snap.data))
        .await
        .map_err(ApiError::internal)??;
    let last = snap.last_key();
    let mut applied = snap.applied;
    let updater = updater_for(store, &snap.filter.slam.config).await?;
    let mut trajectories = if with_trajectories {
        let mut t = snap.load_trajectories(store, run).await?;
        t.remove(crate::track::FILTER_TRACK);
        t
    } else {
        Trajectories::new()
    };
    let filter = restore_filter(snap.filter, updater)?;
    // Every record ordered after the snapshot's last one has a time at or after its time.
    let from_t = last.as_ref().map_or(f64::NEG_INFINITY, OrderKey::t);
    let records = parse_records(&records_in_time(store, run, from_t, t).await?);
    let todo = records_after_snapshot(records, &filter, last.as_ref(), Some(t));
    // Replayed on a worker of rayon's pool, as the coordinator steps its batches.
    let (filter, applied, applied_t, trajectories) = tokio::task::spawn_blocking(move || {
        rayon::scope(|_| {
            let base = filter.clone();
            let mut filter = filter;
            let mut since = Vec::new();
            let mut applied_t = last.as_ref().map(OrderKey::t);
            for r in todo {
                if crate::poison::try_step(&mut filter, &r).is_err() {
                    // The live run quarantined it (or will, on its next restart).
                    filter = crate::poison::rebuild(&base, &since, None)
                        .map_err(|e| ApiError::internal(anyhow::anyhow!("replaying: {e}")))?;
                    continue;
                }
                if with_trajectories && let Some(i) = filter.slam().robot_index(&r.robot) {
                    trajectories
                        .entry(r.robot.clone())
                        .or_default()
                        .push(trajectory_point(filter.slam(), i, r.t));
                }
                applied += 1;
                applied_t = Some(r.t);
                since.push(r);
            }
            Ok::<_, ApiError>((filter, applied, applied_t, trajectories))
        })
    })
    .await
    .map_err(ApiError::internal)??;
    let mut state = base_state(run, status, &filter, applied, applied_t, particle_sample);
    state.t = Some(t);
    Ok(StateAt {
        state,
        trajectories,
    })
}

/// A run's state from its filter alone: robots that map with their pose estimates, robots
/// that are being localized with their localization particles.
pub fn base_state(
    run: &str,
    status: &str,
    filter: &LateJoinSlam,
    applied: u64,
    applied_t: Option<f64>,
    particle_sample: usize,
) -> RunState {
    let slam = filter.slam();
    let est = slam.estimate();
    let mut particles: BTreeMap<String, Vec<[f64; 4]>> = est
        .robots
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let v = slam
                .particle_sample(i, particle_sample)
                .into_iter()
                .map(|(p, w)| [p.x, p.y, p.theta, w])
                .collect();
            (r.id.clone(), v)
        })
        .collect();
    let mut robots: Vec<RobotStatus> = filter
        .phases()
        .into_iter()
        .map(|ph| {
            let e = est.robots.iter().find(|r| r.id == ph.id);
            if e.is_none()
                && let Some(ps) = filter.localization_particles(&ph.id, particle_sample)
            {
                particles.insert(
                    ph.id.clone(),
                    ps.into_iter()
                        .map(|(p, w)| [p.x, p.y, p.theta, w])
                        .collect(),
                );
            }
            RobotStatus {
                id: ph.id.clone(),
                mode: ph.phase.as_str(),
                best: e.map(|e| e.best),
                mean: e.map(|e| e.mean),
                cov: e.map(|e| e.cov),
                last_seq: None,
                last_t: e.map(|e| e.last_t),
                records: e.map_or(0, |e| e.records),
                gaps: 0,
                seq_conflicts: 0,
                queue_depth: 0,
                lag_s: 0.0,
                quarantined: 0,
                quarantine_reason: None,
            }
        })
        .collect();
    robots.sort_by(|a, b| a.id.cmp(&b.id));
    RunState {
        run: run.to_string(),
        status: status.to_string(),
        applied,
        t: applied_t,
        t_start: None,
        ess: est.ess,
        particles: est.particles,
        resamples: slam.stats().resamples,
        robots,
        landmarks: est
            .landmarks
            .iter()
            .map(|l| LandmarkState {
                slot: l.slot,
                id: l.id,
                mean: l.gaussian.mean,
                cov: l.gaussian.cov,
            })
            .collect(),
        particle_sample: particles,
        step_ms: 0.0,
        reason: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleetslam_store::TrajectoryChunk;

    fn pts(range: std::ops::Range<usize>) -> Vec<[f64; 4]> {
        range.map(|i| [i as f64, 1.0, 2.0, 0.5]).collect()
    }

    fn chunk(robot: &str, range: std::ops::Range<usize>) -> TrajectoryChunk {
        TrajectoryChunk {
            robot_id: robot.into(),
            first: range.start as i64,
            points: serde_json::to_string(&pts(range)).unwrap(),
        }
    }

    #[test]
    fn trajectory_pieces_are_laid_end_to_end_and_cut_to_the_snapshot() {
        let lens = BTreeMap::from([("a".to_string(), 25), ("b".to_string(), 3)]);
        // A piece written again after a crash overlaps the next; a piece beyond the
        // snapshot and a robot it does not cover are left out.
        let chunks = vec![
            chunk("a", 0..10),
            chunk("a", 10..18),
            chunk("a", 12..30),
            chunk("a", 30..40),
            chunk("b", 0..3),
            chunk("c", 0..4),
        ];
        let t = assemble_trajectories(chunks, &lens).unwrap();
        assert_eq!(t["a"], pts(0..25));
        assert_eq!(t["b"], pts(0..3));
        assert!(!t.contains_key("c"));
        // A hole is an error, not a shorter trajectory.
        let only_a = BTreeMap::from([("a".to_string(), 25)]);
        assert!(
            assemble_trajectories(vec![chunk("a", 0..10), chunk("a", 10..30)], &only_a).is_ok()
        );
        let e = assemble_trajectories(vec![chunk("a", 0..10), chunk("a", 12..30)], &only_a)
            .unwrap_err();
        assert!(matches!(e, ApiError::Internal(_)));
        // The pieces to store read back.
        let new = BTreeMap::from([("a".to_string(), pts(5..9))]);
        let from = BTreeMap::from([("a".to_string(), 5)]);
        let c = trajectory_chunks(&new, &from).unwrap();
        assert_eq!(c, vec![chunk("a", 5..9)]);
    }
}
