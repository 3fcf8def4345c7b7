//! The run-history endpoints: state at a chosen time, timeline, trajectories, ground truth,
//! evaluation, export, re-run and deletion.

use crate::app::{AppState, check_admin, parse_json, token_hash};
use crate::coordinator::RunState;
use crate::error::ApiError;
use crate::history::{self, RESULT, TRUTH, Trajectories};
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use fleetslam_core::config::{FilterConfig, overlay};
use fleetslam_core::log::{LogHeader, RobotStart};
use fleetslam_core::pose::PoseGaussian;
use fleetslam_data::evaluate::{EvalOptions, evaluate};
use fleetslam_data::formats::{write_landmarks_csv, write_tum};
use fleetslam_store::{NewRobot, NewRun, RunRow, Store};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::sync::Arc;

/// The compact summary stored with a run when it ends and shown in run lists.
pub fn summary(s: &RunState, records: i64, metrics: Option<&history::RunMetrics>) -> Value {
    json!({
        "robots": s.robots.len(),
        "records": records,
        "applied": s.applied,
        "landmarks": s.landmarks.len(),
        "t_start": metrics.and_then(|m| m.t_start),
        "t_end": s.t,
        "duration_s": metrics.and_then(|m| Some(s.t? - m.t_start?)),
        "particles": s.particles,
        "final_ess": s.ess,
        "resamples": s.resamples,
        "updater": metrics.map(|m| m.updater.clone()),
        "step_ms_p50": metrics.map(|m| m.step_ms_p50),
        "ns_per_landmark_update": metrics.map(|m| m.ns_per_landmark_update),
    })
}

/// A finished run's stored result.
#[derive(Debug, Deserialize)]
struct StoredResult {
    state: Value,
    trajectories: Trajectories,
    metrics: Value,
}

async fn run_row(store: &Store, run: &str) -> Result<RunRow, ApiError> {
    store
        .get_run(run)
        .await?
        .ok_or_else(|| ApiError::NotFound(format!("no run {run}: list runs with GET /v1/runs")))
}

async fn stored_result(store: &Store, run: &str) -> Result<Option<StoredResult>, ApiError> {
    match store.get_artifact(run, RESULT).await? {
        Some(body) => serde_json::from_str(&body)
            .map(Some)
            .map_err(|e| ApiError::internal(anyhow::anyhow!("run {run}'s result: {e}"))),
        None => Ok(None),
    }
}

impl AppState {
    /// Starts the coordinator of run `id`, already created in the store (and not running),
    /// with a filter its caller built (any updater): for embedders and tests. Its robots are
    /// registered through the API as usual.
    pub async fn start_run(
        &self,
        id: &str,
        filter: fleetslam_localize::LateJoinSlam,
    ) -> Result<crate::coordinator::RunHandle, ApiError> {
        let row = run_row(&self.store, id).await?;
        if self.running(id).await.is_some() {
            return Err(ApiError::Conflict(format!("run {id} is already running")));
        }
        if row.status != fleetslam_store::STATUS_ACTIVE {
            return Err(not_running(&row));
        }
        let config: FilterConfig = serde_json::from_value(row.config)
            .map_err(|e| ApiError::internal(anyhow::anyhow!("run {id}'s config: {e}")))?;
        let live = self
            .insert_live(
                id.to_string(),
                config,
                filter,
                None,
                HashMap::new(),
                None,
                None,
                crate::coordinator::Clock::Wall,
            )
            .await;
        Ok(live.handle.clone())
    }

    /// The run's coordinator, when it is still running. A coordinator that has stopped (its
    /// run failed) is dropped here, so that the run is served from the store.
    pub(crate) async fn running(&self, run: &str) -> Option<Arc<crate::app::LiveRun>> {
        let live = self.runs.read().await.get(run).cloned()?;
        if !live.handle.is_closed() {
            return Some(live);
        }
        let mut runs = self.runs.write().await;
        if runs.get(run).is_some_and(|l| l.handle.is_closed()) {
            runs.remove(run);
        }
        None
    }
}

/// The answer to a request that needs a run's coordinator, for a run without one.
pub(crate) fn not_running(row: &RunRow) -> ApiError {
    let id = &row.id;
    match row.status.as_str() {
        "active" => ApiError::Conflict(format!(
            "run {id} is active in the store but not running in this server; see the server log"
        )),
        "failed" => ApiError::Conflict(format!(
            "run {id} failed ({}): it takes no more data and has nothing left to end; its \
             state, trajectories and export can still be read, and DELETE /v1/runs/{id} \
             removes it",
            row.reason.as_deref().unwrap_or("no reason recorded")
        )),
        other => ApiError::Conflict(format!("run {id} is {other}: it takes no more data")),
    }
}

/// What a run shows now: its live state and trajectories, or its stored result.
struct View {
    state: Value,
    trajectories: Arc<Trajectories>,
    metrics: Option<Value>,
}

impl View {
    /// The run's trajectories and landmarks as the files `fleetslam run` writes.
    fn estimate(&self) -> Result<fleetslam_data::formats::Truth, ApiError> {
        let landmarks: Vec<crate::coordinator::LandmarkState> =
            serde_json::from_value(self.state.get("landmarks").cloned().unwrap_or(json!([])))
                .map_err(ApiError::internal)?;
        Ok(history::to_truth(
            &self.trajectories,
            &history::landmark_rows(&landmarks),
        ))
    }
}

async fn view(state: &AppState, run: &str) -> Result<View, ApiError> {
    let live = state.running(run).await;
    if let Some(live) = live {
        // Published beside the state: never through the coordinator's queue, so a busy run
        // answers as fast as an idle one.
        let s = live.handle.current_state();
        let trajectories = Arc::new(live.handle.trajectories());
        return Ok(View {
            state: serde_json::to_value(&*s).map_err(ApiError::internal)?,
            trajectories,
            metrics: None,
        });
    }
    let row = run_row(&state.store, run).await?;
    if let Some(r) = stored_result(&state.store, run).await? {
        return Ok(View {
            state: r.state,
            trajectories: Arc::new(r.trajectories),
            metrics: Some(r.metrics),
        });
    }
    // A run that failed or whose recovery failed: its latest snapshot and the log after it.
    let at = history::state_at(
        &state.store,
        run,
        &row.status,
        f64::MAX,
        state.config.coordinator.particle_sample,
        true,
    )
    .await?;
    let mut s = at.state;
    s.t = s.t.filter(|t| *t < f64::MAX);
    s.reason = row.reason.clone();
    Ok(View {
        state: serde_json::to_value(&s).map_err(ApiError::internal)?,
        trajectories: Arc::new(at.trajectories),
        metrics: None,
    })
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StateQuery {
    /// Data time [s]: the state after every record up to it.
    t: Option<f64>,
}

/// `GET /v1/runs/{run}/state[?t=SECONDS]`
#[utoipa::path(get, path = "/v1/runs/{run}/state", tag = "runs",
    params(("run" = String, Path, description = "Run id"),
           ("t" = Option<f64>, Query, description = "Data time [s]: the state as of then (scrubbing)")),
    responses((status = 200, description = "The run's state", body = RunState),
              (status = 404, description = "No such run, or no state that early", body = crate::error::ErrorBody)))]
pub async fn get_state(
    State(state): State<AppState>,
    Path(run): Path<String>,
    Query(q): Query<StateQuery>,
) -> Result<Json<Value>, ApiError> {
    match q.t {
        Some(t) => {
            if !t.is_finite() {
                return Err(ApiError::BadRequest(format!(
                    "t must be a finite time in seconds, got {t}"
                )));
            }
            let row = run_row(&state.store, &run).await?;
            let at = history::state_at(
                &state.store,
                &run,
                &row.status,
                t,
                state.config.coordinator.particle_sample,
                false,
            )
            .await?;
            Ok(Json(
                serde_json::to_value(&at.state).map_err(ApiError::internal)?,
            ))
        }
        None => Ok(Json(view(&state, &run).await?.state)),
    }
}

/// `GET /v1/runs/{run}/timeline`: the span of data time a run covers, for scrubbing.
#[utoipa::path(get, path = "/v1/runs/{run}/timeline", tag = "runs",
    params(("run" = String, Path, description = "Run id")),
    responses((status = 200, description = "t_start, t_end (data time [s]), records applied, snapshots")))]
pub async fn timeline(
    State(state): State<AppState>,
    Path(run): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let v = view(&state, &run).await?;
    let t_start = v
        .trajectories
        .values()
        .filter_map(|p| p.first().map(|p| p[0]))
        .fold(None, |m: Option<f64>, t| Some(m.map_or(t, |m| m.min(t))));
    let snapshots: Vec<Value> = state
        .store
        .snapshot_index(&run)
        .await?
        .into_iter()
        .filter(|(_, t)| *t > f64::MIN)
        .map(|(applied, t)| json!({"applied": applied, "t": t}))
        .collect();
    Ok(Json(json!({
        "t_start": t_start,
        "t_end": v.state.get("t"),
        "applied": v.state.get("applied"),
        "snapshots": snapshots,
    })))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SinceQuery {
    /// Data time [s]: only points after it (what a reader that has the points up to it
    /// lacks).
    since: Option<f64>,
    /// At most this many points per track, evenly thinned (the last point always kept).
    max_points: Option<usize>,
}

impl SinceQuery {
    fn check(&self) -> Result<(), ApiError> {
        if self.since.is_some_and(|t| !t.is_finite()) {
            return Err(ApiError::BadRequest(format!(
                "since must be a finite time in seconds, got {:?}",
                self.since
            )));
        }
        if self.max_points == Some(0) {
            return Err(ApiError::BadRequest("max_points must be at least 1".into()));
        }
        Ok(())
    }

    /// `pts` after `since`, thinned to `max_points`.
    fn select(&self, pts: &[[f64; 4]]) -> Vec<[f64; 4]> {
        let from = self.since.map_or(0, |s| pts.partition_point(|p| p[0] <= s));
        thin(&pts[from..], self.max_points)
    }
}

/// Every `ceil(n / max)`-th point of `pts` and the last one: at most `max` points spread
/// evenly over the span, ending where `pts` ends.
fn thin(pts: &[[f64; 4]], max: Option<usize>) -> Vec<[f64; 4]> {
    match max {
        Some(max) if pts.len() > max => {
            let step = pts.len().div_ceil(max);
            let last = pts.len() - 1;
            // Counted from the end, so that the last point is one of them.
            let mut out: Vec<[f64; 4]> = (0..max)
                .filter_map(|k| last.checked_sub(k * step).map(|i| pts[i]))
                .collect();
            out.reverse();
            out
        }
        _ => pts.to_vec(),
    }
}

/// `GET /v1/runs/{run}/trajectories[?since=T&max_points=N]`
#[utoipa::path(get, path = "/v1/runs/{run}/trajectories", tag = "runs",
    params(("run" = String, Path, description = "Run id"),
           ("since" = Option<f64>, Query, description = "Data time [s]: only the points after it, for a reader that has those up to it"),
           ("max_points" = Option<usize>, Query, description = "At most this many points per robot, evenly thinned, the last one kept")),
    responses((status = 200, description = "{\"robots\": {id: [[t, x, y, theta], ...]}}: the mean pose after each record")))]
pub async fn trajectories(
    State(state): State<AppState>,
    Path(run): Path<String>,
    Query(q): Query<SinceQuery>,
) -> Result<Json<Value>, ApiError> {
    q.check()?;
    let v = view(&state, &run).await?;
    if q.since.is_none() && q.max_points.is_none() {
        return Ok(Json(json!({ "robots": &*v.trajectories })));
    }
    let robots: BTreeMap<&String, Vec<[f64; 4]>> = v
        .trajectories
        .iter()
        .map(|(r, pts)| (r, q.select(pts)))
        .collect();
    Ok(Json(json!({ "robots": robots })))
}

/// The filter's series of a run: published beside a live run's state, read from the store
/// for any other (as far as its last stored snapshot).
async fn filter_series(
    state: &AppState,
    run: &str,
) -> Result<Vec<crate::track::FilterPoint>, ApiError> {
    match state.running(run).await {
        Some(live) => Ok(live.handle.filter_series()),
        None => {
            run_row(&state.store, run).await?;
            history::stored_series(&state.store, run).await
        }
    }
}

/// `GET /v1/runs/{run}/series[?since=T&max_points=N]`: the filter after each applied record.
#[utoipa::path(get, path = "/v1/runs/{run}/series", tag = "runs",
    params(("run" = String, Path, description = "Run id"),
           ("since" = Option<f64>, Query, description = "Data time [s]: only the points after it"),
           ("max_points" = Option<usize>, Query, description = "At most this many points, evenly thinned, the last one kept")),
    responses((status = 200, description = "{\"columns\": [\"t\", \"ess\", \"step_ms\", \"landmarks\"], \"points\": [[...], ...]}: after each applied record, its data time [s], the effective sample size, the record's step time [ms] and the landmarks of the best particle"),
              (status = 404, description = "No such run", body = crate::error::ErrorBody)))]
pub async fn series(
    State(state): State<AppState>,
    Path(run): Path<String>,
    Query(q): Query<SinceQuery>,
) -> Result<Json<Value>, ApiError> {
    q.check()?;
    let pts = filter_series(&state, &run).await?;
    Ok(Json(json!({
        "columns": ["t", "ess", "step_ms", "landmarks"],
        "points": q.select(&pts),
    })))
}

/// `PUT /v1/runs/{run}/truth` (admin): the run's ground truth, for overlays and evaluation.
#[utoipa::path(put, path = "/v1/runs/{run}/truth", tag = "runs",
    params(("run" = String, Path, description = "Run id")),
    request_body(content = Object, description = "{\"robots\": {id: [[t, x, y, theta]]}, \"landmarks\": [{\"id\", \"x\", \"y\"}]}"),
    responses((status = 204, description = "Stored"), (status = 400, body = crate::error::ErrorBody)))]
pub async fn put_truth(
    State(state): State<AppState>,
    headers: HeaderMap,
    Path(run): Path<String>,
    body: Bytes,
) -> Result<StatusCode, ApiError> {
    check_admin(&state, &headers)?;
    run_row(&state.store, &run).await?;
    let truth = history::truth_from_json(&body)?;
    let text = history::truth_to_json(&truth).to_string();
    state.store.put_artifact(&run, TRUTH, &text).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// `GET /v1/runs/{run}/truth`
#[utoipa::path(get, path = "/v1/runs/{run}/truth", tag = "runs",
    params(("run" = String, Path, description = "Run id")),
    responses((status = 200, description = "The ground truth"), (status = 404, body = crate::error::ErrorBody)))]
pub async fn get_truth(
    State(state): State<AppState>,
    Path(run): Path<String>,
) -> Result<Response, ApiError> {
    run_row(&state.store, &run).await?;
    match state.store.get_artifact(&run, TRUTH).await? {
        Some(body) => Ok(([(header::CONTENT_TYPE, "application/json")], body).into_response()),
        None => Err(ApiError::NotFound(format!(
            "run {run} has no ground truth: upload it with PUT /v1/runs/{run}/truth"
        ))),
    }
}

/// Whether a run's estimate is in its ground truth's frame: every robot started at a known
/// pose and the header says the poses are truth's.
async fn shared_frame(store: &Store, row: &RunRow) -> Result<bool, ApiError> {
    let header_says = row
        .header
        .as_ref()
        .and_then(|h| h.get("truth_frame"))
        .and_then(Value::as_bool)
        .unwrap_or(false);
    let robots = store.robots(&row.id).await?;
    Ok(header_says && robots.iter().all(|r| r.start.is_some()))
}

/// `GET /v1/runs/{run}/evaluation`: the run's errors against its ground truth.
#[utoipa::path(get, path = "/v1/runs/{run}/evaluation", tag = "runs",
    params(("run" = String, Path, description = "Run id")),
    responses((status = 200, description = "ATE per robot and team, landmark RMSE (as `fleetslam evaluate`)"),
              (status = 404, description = "No such run or no ground truth", body = crate::error::ErrorBody)))]
pub async fn evaluation(
    State(state): State<AppState>,
    Path(run): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let row = run_row(&state.store, &run).await?;
    let Some(truth) = state.store.get_artifact(&run, TRUTH).await? else {
        return Err(ApiError::NotFound(format!(
            "run {run} has no ground truth: upload it with PUT /v1/runs/{run}/truth"
        )));
    };
    let truth = history::truth_from_json(truth.as_bytes())
        .map_err(|e| ApiError::internal(anyhow::anyhow!("stored truth: {e}")))?;
    let v = view(&state, &run).await?;
    let est = v.estimate()?;
    let shared = shared_frame(&state.store, &row).await?;
    let eval = evaluate(&est, &truth, shared, &EvalOptions::default());
    Ok(Json(
        serde_json::to_value(&eval).map_err(ApiError::internal)?,
    ))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExportQuery {
    /// `zip` (default): every file; or one file: `log`, `landmarks`, `metrics`, `tum`
    /// (with `robot`).
    format: Option<String>,
    robot: Option<String>,
}

/// The header of a run's exported log: the stored header with the robots as registered.
async fn export_header(store: &Store, row: &RunRow) -> Result<LogHeader, ApiError> {
    let config: FilterConfig = serde_json::from_value(row.config.clone())
        .map_err(|e| ApiError::internal(anyhow::anyhow!("run {}'s config: {e}", row.id)))?;
    let mut header: LogHeader = match &row.header {
        Some(h) => serde_json::from_value(h.clone())
            .map_err(|e| ApiError::internal(anyhow::anyhow!("run {}'s header: {e}", row.id)))?,
        None => serde_json::from_value(json!({
            "fleetslam_log": fleetslam_core::log::LOG_VERSION,
            "landmark_kind": config.landmark_kind,
            "motion_model": config.motion_model,
            "landmark_ids": config.association == fleetslam_core::config::Association::Known,
        }))
        .map_err(ApiError::internal)?,
    };
    header.robots = store
        .robots(&row.id)
        .await?
        .into_iter()
        .map(|r| {
            // A start pose that cannot be read back (a run that failed for it) is exported
            // as unknown rather than failing the export.
            let start = r
                .start
                .map(serde_json::from_value::<PoseGaussian>)
                .transpose()
                .unwrap_or_else(|e| {
                    tracing::warn!(run = %row.id, robot = %r.robot_id, error = %e, "unreadable start pose left out of the export");
                    None
                });
            RobotStart {
                id: r.robot_id,
                start,
                t0: r.t0,
            }
        })
        .collect();
    Ok(header)
}

/// The stored log as NDJSON: the header, then every record in arrival order, without the
/// quarantined ones (and any whose stored body cannot be parsed): the log that runs offline
/// as the run did.
async fn export_log(store: &Store, row: &RunRow) -> Result<Vec<u8>, ApiError> {
    let header = export_header(store, row).await?;
    let mut out = serde_json::to_vec(&header).map_err(ApiError::internal)?;
    out.push(b'\n');
    let stored = history::all_records(store, &row.id).await?;
    let skipped: std::collections::HashSet<(String, u64)> = crate::poison::usable(&stored)
        .1
        .into_iter()
        .map(|s| (s.robot, s.seq))
        .collect();
    for o in stored {
        if skipped.contains(&(o.robot_id.clone(), o.seq.max(0) as u64)) {
            continue;
        }
        out.extend_from_slice(o.body.as_bytes());
        out.push(b'\n');
    }
    Ok(out)
}

/// `GET /v1/runs/{run}/export[?format=zip|log|landmarks|metrics|tum|mcap&robot=ID]`
#[utoipa::path(get, path = "/v1/runs/{run}/export", tag = "runs",
    params(("run" = String, Path, description = "Run id"),
           ("format" = Option<String>, Query, description = "zip (default), log, landmarks, metrics, tum, mcap (Foxglove schemas: poses, frame transforms, landmarks with 2-sigma ellipses, the final particle sample, ESS, step time and landmark count after each record, ground truth when uploaded)"),
           ("robot" = Option<String>, Query, description = "The robot, for format=tum")),
    responses((status = 200, description = "A zip of trajectory_<robot>.tum, landmarks.csv, metrics.json and log.ndjson (the files `fleetslam run` writes, and the log it reads), or one of them")))]
pub async fn export(
    State(state): State<AppState>,
    Path(run): Path<String>,
    Query(q): Query<ExportQuery>,
) -> Result<Response, ApiError> {
    let row = run_row(&state.store, &run).await?;
    let v = view(&state, &run).await?;
    let est = v.estimate()?;
    let csv = || {
        let mut b = Vec::new();
        write_landmarks_csv(&mut b, &est.landmarks).map(|_| b)
    };
    let tum = |pts| {
        let mut b = Vec::new();
        write_tum(&mut b, pts).map(|_| b)
    };
    let mut metrics = v.metrics.clone().unwrap_or_else(|| json!({}));
    if let Value::Object(m) = &mut metrics {
        m.insert(
            "shared_frame".into(),
            json!(shared_frame(&state.store, &row).await?),
        );
        m.insert("run".into(), json!(run));
        m.insert("status".into(), json!(row.status));
    }
    let metrics = serde_json::to_vec_pretty(&metrics).map_err(ApiError::internal)?;
    let file = |name: String, ctype: &'static str, body: Vec<u8>| {
        (
            [
                (header::CONTENT_TYPE, ctype.to_string()),
                (
                    header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"{name}\""),
                ),
            ],
            body,
        )
            .into_response()
    };
    match q.format.as_deref().unwrap_or("zip") {
        "log" => Ok(file(
            "log.ndjson".into(),
            "application/x-ndjson",
            export_log(&state.store, &row).await?,
        )),
        "landmarks" => Ok(file(
            "landmarks.csv".into(),
            "text/csv",
            csv().map_err(ApiError::internal)?,
        )),
        "metrics" => Ok(file("metrics.json".into(), "application/json", metrics)),
        "tum" => {
            let robot = q.robot.ok_or_else(|| {
                ApiError::BadRequest("format=tum needs robot=<id>: one file per robot".into())
            })?;
            let pts = est.trajectories.get(&robot).ok_or_else(|| {
                ApiError::NotFound(format!("run {run} has no trajectory of robot {robot:?}"))
            })?;
            Ok(file(
                format!("trajectory_{robot}.tum"),
                "text/plain",
                tum(pts).map_err(ApiError::internal)?,
            ))
        }
        "mcap" => {
            let truth = match state.store.get_artifact(&run, TRUTH).await? {
                Some(t) => Some(
                    history::truth_from_json(t.as_bytes())
                        .map_err(|e| ApiError::internal(anyhow::anyhow!("stored truth: {e}")))?,
                ),
                None => None,
            };
            let series = filter_series(&state, &run).await?;
            let particles: BTreeMap<String, Vec<[f64; 4]>> = serde_json::from_value(
                v.state.get("particle_sample").cloned().unwrap_or(json!({})),
            )
            .map_err(ApiError::internal)?;
            let mcap = tokio::task::spawn_blocking(move || {
                fleetslam_data::mcap::write_mcap(&fleetslam_data::mcap::McapRun {
                    estimate: &est,
                    truth: truth.as_ref(),
                    series: &series,
                    particles: &particles,
                })
            })
            .await
            .map_err(ApiError::internal)?
            .map_err(|e| match e {
                fleetslam_data::mcap::McapError::Time(_) => {
                    ApiError::Conflict(format!("run {run} cannot be exported as MCAP: {e}"))
                }
                other => ApiError::internal(other),
            })?;
            Ok(file(
                format!("run-{run}.mcap"),
                "application/octet-stream",
                mcap,
            ))
        }
        "zip" => {
            let log = export_log(&state.store, &row).await?;
            let mut files: Vec<(String, Vec<u8>)> = Vec::new();
            for (robot, pts) in &est.trajectories {
                files.push((
                    format!("trajectory_{robot}.tum"),
                    tum(pts).map_err(ApiError::internal)?,
                ));
            }
            files.push(("landmarks.csv".into(), csv().map_err(ApiError::internal)?));
            files.push(("metrics.json".into(), metrics));
            files.push(("log.ndjson".into(), log));
            let zip = tokio::task::spawn_blocking(move || zip_files(&files))
                .await
                .map_err(ApiError::internal)?
                .map_err(ApiError::internal)?;
            Ok(file(format!("run-{run}.zip"), "application/zip", zip))
        }
        other => Err(ApiError::BadRequest(format!(
            "format must be zip, log, landmarks, metrics, tum or mcap, got {other:?}"
        ))),
    }
}

fn zip_files(files: &[(String, Vec<u8>)]) -> zip::result::ZipResult<Vec<u8>> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    for (name, body) in files {
        w.start_file(name.as_str(), opts)?;
        w.write_all(body)?;
    }
    Ok(w.finish()?.into_inner())
}

/// Body of `POST /v1/runs/{run}/rerun`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Rerun {
    pub name: Option<String>,
    /// `FilterConfig` fields to change (particles, updater, seed, ...) over the run's own.
    #[schema(value_type = Option<Object>)]
    pub config: Option<Value>,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct RerunStarted {
    /// The new run, which receives the stored log and ends by itself.
    pub id: String,
    #[schema(value_type = Object)]
    pub config: FilterConfig,
}

/// `POST /v1/runs/{run}/rerun` (admin): the stored log of a run again, with another
/// configuration, as a new run (for comparisons such as EKF against MLP on the same data).
#[utoipa::path(post, path = "/v1/runs/{run}/rerun", tag = "runs",
    params(("run" = String, Path, description = "The run whose log to re-run")),
    request_body = Rerun,
    responses((status = 202, description = "The new run is being fed", body = RerunStarted),
              (status = 400, body = crate::error::ErrorBody)))]
pub async fn rerun(
    State(state): State<AppState>,
    headers: HeaderMap,
    Path(run): Path<String>,
    body: Bytes,
) -> Result<(StatusCode, Json<RerunStarted>), ApiError> {
    check_admin(&state, &headers)?;
    if state.cluster.is_some() {
        // A re-run is fed from the store by a local coordinator that holds no lease: in a
        // cluster another replica would take it as a run without an owner.
        return Err(ApiError::Conflict(
            "re-runs are not offered in cluster mode yet: export the run and replay it \
             (fleetslam export, fleetslam replay) into a new run"
                .into(),
        ));
    }
    let req: Rerun = if body.iter().all(u8::is_ascii_whitespace) {
        Rerun {
            name: None,
            config: None,
        }
    } else {
        parse_json("rerun", &body)?
    };
    let row = run_row(&state.store, &run).await?;
    let base: FilterConfig = serde_json::from_value(row.config.clone())
        .map_err(|e| ApiError::internal(anyhow::anyhow!("run {run}'s config: {e}")))?;
    let config = overlay(&base, req.config.unwrap_or(Value::Null))
        .map_err(|e| ApiError::BadRequest(format!("config: {e}")))?;
    config
        .validate()
        .map_err(|e| ApiError::BadRequest(format!("config: {e}")))?;
    // The source's localization settings, from its first snapshot.
    let localize = match state.store.snapshot_at_or_before_applied(&run, 0).await? {
        Some(s) => history::RunSnapshot::decode(&s.data)?.filter.localize,
        None => fleetslam_localize::LocalizeConfig::default(),
    };
    let updater = history::updater_for(&state.store, &config).await?;
    let filter = history::new_filter(&config, localize, updater)?;
    let id = uuid::Uuid::new_v4().to_string();
    let name = req
        .name
        .or_else(|| Some(format!("rerun of {}", row.name.as_deref().unwrap_or(&run))));
    state
        .store
        .create_run(&NewRun {
            id: id.clone(),
            name,
            config: serde_json::to_value(&config).map_err(ApiError::internal)?,
            header: row.header.clone(),
        })
        .await?;
    if let Some(truth) = state.store.get_artifact(&run, TRUTH).await? {
        state.store.put_artifact(&id, TRUTH, &truth).await?;
    }
    let live = state
        .insert_live(
            id.clone(),
            config.clone(),
            filter,
            None,
            HashMap::new(),
            None,
            None,
            crate::coordinator::Clock::Wall,
        )
        .await;
    for r in state.store.robots(&run).await? {
        let start: Option<PoseGaussian> = r
            .start
            .clone()
            .map(serde_json::from_value)
            .transpose()
            .map_err(ApiError::internal)?;
        // Nobody posts to a re-run: its robots' tokens are never shown.
        let token = hex::encode(rand::random::<[u8; 24]>());
        let row = NewRobot {
            robot_id: r.robot_id.clone(),
            start: r.start.clone(),
            token_hash: token_hash(&token),
            t0: r.t0,
        };
        live.handle.add_robot(row, start, r.t0).await?;
    }
    let st = state.clone();
    let (src, dst) = (run.clone(), id.clone());
    tokio::spawn(async move {
        if let Err(e) = feed_rerun(&st, &src, &dst).await {
            tracing::error!(run = %dst, source = %src, error = %e, "re-run failed");
            let reason = match &e {
                ApiError::Internal(inner) => format!("feeding the re-run failed: {inner:#}"),
                other => format!("feeding the re-run failed: {other}"),
            };
            let _ = st.store.set_run_failed(&dst, &reason).await;
            st.runs.write().await.remove(&dst);
        }
    });
    tracing::info!(run = %id, source = %run, "re-run started");
    Ok((StatusCode::ACCEPTED, Json(RerunStarted { id, config })))
}

/// Feeds a run's stored log, in arrival order, to a new run and ends it.
async fn feed_rerun(state: &AppState, src: &str, dst: &str) -> Result<(), ApiError> {
    let live = state.live(dst).await?;
    // Quarantined records stay out of the re-run, as they stayed out of the source.
    let records = history::parse_records(&history::all_records(&state.store, src).await?);
    for chunk in records.chunks(512) {
        loop {
            match live.handle.ingest(chunk.to_vec()).await {
                Ok(acks) => {
                    if let Some(a) = acks.iter().find(|a| a.status == "rejected") {
                        return Err(ApiError::internal(anyhow::anyhow!(
                            "record {} was refused: {}",
                            a.seq,
                            a.error.as_deref().unwrap_or("")
                        )));
                    }
                    break;
                }
                Err(ApiError::Busy { .. }) => {
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await
                }
                Err(e) => return Err(e),
            }
        }
    }
    crate::app::finish_run(state, dst, &live).await
}

/// `DELETE /v1/runs/{run}` (admin): a finished run and all its data.
#[utoipa::path(delete, path = "/v1/runs/{run}", tag = "runs",
    params(("run" = String, Path, description = "Run id")),
    responses((status = 204, description = "Deleted"),
              (status = 409, description = "The run is still active: end it first", body = crate::error::ErrorBody)))]
pub async fn delete_run(
    State(state): State<AppState>,
    headers: HeaderMap,
    Path(run): Path<String>,
) -> Result<StatusCode, ApiError> {
    check_admin(&state, &headers)?;
    let active_elsewhere = state.cluster.is_some()
        && state.store.run_status(&run).await?.as_deref() == Some(fleetslam_store::STATUS_ACTIVE);
    if active_elsewhere || state.running(&run).await.is_some() {
        return Err(ApiError::Conflict(format!(
            "run {run} is active: end it first with POST /v1/runs/{run}/end"
        )));
    }
    if state.store.delete_run(&run).await? {
        tracing::info!(run = %run, "run deleted");
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError::NotFound(format!("no run {run}")))
    }
}

/// `GET /v1/models`: the learned models in the store (without their weights).
#[utoipa::path(get, path = "/v1/models", tag = "runs",
    responses((status = 200, description = "{\"models\": [{id, kind, config, metrics, weights_len, created_at}]}: a run uses one with config.updater = id")))]
pub async fn list_models(State(state): State<AppState>) -> Result<Json<Value>, ApiError> {
    let models = state.store.list_models().await?;
    Ok(Json(json!({ "models": models })))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pts(n: usize) -> Vec<[f64; 4]> {
        (0..n).map(|i| [i as f64, 0.0, 0.0, 0.0]).collect()
    }

    /// Thinning keeps at most the number asked for, evenly spaced, the last point always.
    #[test]
    fn thinning_keeps_evenly_spaced_points_and_the_last() {
        assert_eq!(thin(&pts(5), Some(10)), pts(5));
        assert_eq!(thin(&pts(5), None), pts(5));
        let t = |v: Vec<[f64; 4]>| v.iter().map(|p| p[0] as usize).collect::<Vec<_>>();
        assert_eq!(t(thin(&pts(10), Some(5))), vec![1, 3, 5, 7, 9]);
        assert_eq!(t(thin(&pts(10), Some(4))), vec![0, 3, 6, 9]);
        assert_eq!(t(thin(&pts(1000), Some(3))), vec![331, 665, 999]);
        assert_eq!(t(thin(&pts(7), Some(1))), vec![6]);
    }
}
