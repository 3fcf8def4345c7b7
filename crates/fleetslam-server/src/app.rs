//! The HTTP API (versioned under `/v1`), built as `app(state) -> Router` so tests can call it
//! with `tower::ServiceExt::oneshot`.

use crate::api_history;
use crate::auth::AuthConfig;
use crate::coordinator::{self, CoordinatorConfig, PublishedState, RecordAck, RunHandle};
use crate::error::ApiError;
use crate::history;
use crate::limits::Limits;
use axum::body::Bytes;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use fleetslam_core::config::{FilterConfig, overlay};
use fleetslam_core::log::{LogHeader, Record};
use fleetslam_core::pose::PoseGaussian;
use fleetslam_store::{NewRobot, NewRun, RunFilter, Store};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::Arc;
use tokio::sync::RwLock;

/// Server-wide settings the handlers need.
#[derive(Debug, Clone)]
pub struct ApiConfig {
    /// Tokens, who may read, allowed origins ([`crate::auth`]).
    pub auth: AuthConfig,
    /// Input bounds.
    pub limits: Limits,
    /// Largest request body [bytes].
    pub body_limit: usize,
    pub coordinator: CoordinatorConfig,
    /// The dashboard's files, served at `/`.
    pub web_dir: std::path::PathBuf,
}

/// The `web/` directory of the source tree this server was built from.
pub fn default_web_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../web")
}

impl Default for ApiConfig {
    fn default() -> Self {
        Self {
            auth: AuthConfig {
                loopback: true,
                ..AuthConfig::default()
            },
            limits: Limits::default(),
            body_limit: 16 << 20,
            coordinator: CoordinatorConfig::default(),
            web_dir: default_web_dir(),
        }
    }
}

/// A live run: its coordinator and who may post as which robot.
#[derive(Debug)]
pub(crate) struct LiveRun {
    pub(crate) handle: RunHandle,
    pub(crate) config: FilterConfig,
    /// sha256(token) hex -> robot id.
    pub(crate) tokens: RwLock<HashMap<String, String>>,
    /// sha256 hex of the run's enrollment token, with which robots may register themselves.
    pub(crate) enrollment: Option<String>,
}

/// Shared state of the handlers.
#[derive(Debug, Clone)]
pub struct AppState {
    pub store: Store,
    pub config: Arc<ApiConfig>,
    pub(crate) runs: Arc<RwLock<HashMap<String, Arc<LiveRun>>>>,
    pub(crate) metrics: Arc<crate::metrics::Metrics>,
    /// Held while a run is created, so that `max_active_runs` holds under concurrent
    /// requests.
    creating: Arc<tokio::sync::Mutex<()>>,
    pub(crate) ws: Arc<crate::ws_limit::WsLimits>,
    /// Set in cluster mode ([`crate::cluster`]): records go through JetStream and runs are
    /// owned by lease.
    pub cluster: Option<Arc<crate::cluster::Cluster>>,
    /// Set with `foxglove_bind`: live runs are also streamed to Foxglove
    /// ([`crate::foxglove_live`]).
    pub foxglove: Option<Arc<crate::foxglove_live::FoxgloveLive>>,
}

impl AppState {
    pub fn new(store: Store, config: ApiConfig) -> Self {
        Self {
            store,
            config: Arc::new(config),
            runs: Arc::default(),
            metrics: Arc::default(),
            creating: Arc::default(),
            ws: Arc::default(),
            cluster: None,
            foxglove: None,
        }
    }

    /// The same state, streaming its live runs to Foxglove too.
    pub fn with_foxglove(mut self, foxglove: Arc<crate::foxglove_live::FoxgloveLive>) -> Self {
        self.foxglove = Some(foxglove);
        self
    }

    /// The same state as a replica of a cluster.
    pub fn with_cluster(mut self, cluster: Arc<crate::cluster::Cluster>) -> Self {
        self.cluster = Some(cluster);
        self
    }

    /// Starts the coordinator of a run and makes it reachable.
    // Each argument is one part of how a run starts (new, recovered, re-run); a struct
    // would only rename them.
    #[allow(clippy::too_many_arguments)]
    pub(crate) async fn insert_live(
        &self,
        id: String,
        config: FilterConfig,
        filter: fleetslam_localize::LateJoinSlam,
        recovered: Option<coordinator::Recovered>,
        tokens: HashMap<String, String>,
        enrollment: Option<String>,
        training: Option<history::Training>,
        clock: coordinator::Clock,
    ) -> Arc<LiveRun> {
        let handle = coordinator::spawn(
            id.clone(),
            filter,
            self.store.clone(),
            self.config.coordinator.clone(),
            recovered,
            training,
            clock,
        );
        if let Some(f) = &self.foxglove {
            f.watch(&handle, self.config.coordinator.state_rate_hz);
        }
        let live = Arc::new(LiveRun {
            handle,
            config,
            tokens: RwLock::new(tokens),
            enrollment,
        });
        self.runs.write().await.insert(id, live.clone());
        live
    }

    pub(crate) async fn live(&self, id: &str) -> Result<Arc<LiveRun>, ApiError> {
        if let Some(r) = self.running(id).await {
            return Ok(r);
        }
        match self.store.get_run(id).await? {
            Some(row) => Err(api_history::not_running(&row)),
            None => Err(ApiError::NotFound(format!(
                "no run {id}: list runs with GET /v1/runs"
            ))),
        }
    }
}

pub fn app(state: AppState) -> Router {
    let limit = state.config.body_limit;
    Router::new()
        .route("/healthz", get(healthz))
        .route("/metrics", get(crate::metrics::metrics))
        .route("/v1/openapi.json", get(crate::openapi::openapi))
        .route("/v1/runs", post(create_run).get(list_runs))
        .route(
            "/v1/runs/{run}",
            get(get_run).delete(api_history::delete_run),
        )
        .route("/v1/runs/{run}/end", post(end_run))
        .route("/v1/runs/{run}/robots", post(register_robot))
        .route("/v1/runs/{run}/observations", post(post_observations))
        .route("/v1/runs/{run}/state", get(api_history::get_state))
        .route("/v1/runs/{run}/live", get(live))
        .route("/v1/runs/{run}/timeline", get(api_history::timeline))
        .route("/v1/runs/{run}/series", get(api_history::series))
        .route(
            "/v1/runs/{run}/trajectories",
            get(api_history::trajectories),
        )
        .route(
            "/v1/runs/{run}/truth",
            get(api_history::get_truth).put(api_history::put_truth),
        )
        .route("/v1/runs/{run}/evaluation", get(api_history::evaluation))
        .route("/v1/runs/{run}/export", get(api_history::export))
        .route("/v1/runs/{run}/rerun", post(api_history::rerun))
        .route("/v1/models", get(api_history::list_models))
        .fallback_service(tower_http::services::ServeDir::new(&state.config.web_dir))
        .layer(DefaultBodyLimit::max(limit))
        // Inside out: authorization (per route, so it sees the route pattern), metrics,
        // every refusal as a JSON body, tracing.
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            crate::auth::authorize,
        ))
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            crate::metrics::track,
        ))
        .layer(axum::middleware::from_fn(crate::error::json_errors))
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(state)
}

/// `GET /healthz`
#[utoipa::path(get, path = "/healthz", tag = "server",
    responses((status = 200, description = "The server is up", body = String)))]
pub(crate) async fn healthz() -> &'static str {
    "ok"
}

pub(crate) use crate::auth::token_hash;

/// 401 unless the request carries the admin token (when one is configured).
pub(crate) fn check_admin(state: &AppState, headers: &HeaderMap) -> Result<(), ApiError> {
    crate::auth::check_admin(&state.config.auth, headers)
}

/// A new random token (192 bits, hex).
fn new_token() -> String {
    hex::encode(rand::random::<[u8; 24]>())
}

/// The artifact that holds a run's enrollment token hash (never served).
pub(crate) const ENROLLMENT: &str = "enrollment";

/// The hash of a run's enrollment token, as stored in [`ENROLLMENT`].
pub(crate) async fn stored_enrollment(
    store: &Store,
    run: &str,
) -> Result<Option<String>, ApiError> {
    Ok(match store.get_artifact(run, ENROLLMENT).await? {
        Some(body) => serde_json::from_str::<serde_json::Value>(&body)
            .ok()
            .and_then(|v| v["token_sha256"].as_str().map(str::to_string)),
        None => None,
    })
}

/// The artifact that holds what a run was created with beyond its filter configuration: a
/// recovery before the run's first snapshot (and a cluster replica that takes a new run)
/// starts from it.
pub(crate) const SETUP: &str = "setup";

/// The body of [`SETUP`].
#[derive(Debug, Default, Serialize, Deserialize)]
pub(crate) struct RunSetup {
    pub(crate) localize: Option<fleetslam_localize::LocalizeConfig>,
    pub(crate) training: Option<fleetslam_learned::RecordingConfig>,
}

/// Parses JSON into `T`, turning serde's message into a 400 that names the field.
pub(crate) fn parse_json<T: serde::de::DeserializeOwned>(
    what: &str,
    body: &[u8],
) -> Result<T, ApiError> {
    let de = &mut serde_json::Deserializer::from_slice(body);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        if path == "." {
            ApiError::BadRequest(format!("{what}: {}", e.inner()))
        } else {
            ApiError::BadRequest(format!("{what}: field `{path}`: {}", e.inner()))
        }
    })
}

/// Body of `POST /v1/runs`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateRun {
    pub name: Option<String>,
    /// A log header: models, suggested noise and robots (robots are registered separately).
    #[schema(value_type = Option<Object>)]
    pub header: Option<LogHeader>,
    /// Any `FilterConfig` fields, over the header's suggestions.
    #[schema(value_type = Option<Object>)]
    pub config: Option<serde_json::Value>,
    /// Any `LocalizeConfig` fields: how robots registered at an unknown pose are localized
    /// (samples, KLD-sampling, convergence, real-time policy).
    #[schema(value_type = Option<Object>)]
    pub localize: Option<serde_json::Value>,
    /// Log a sample of the landmark updates as training rows for the learned updater:
    /// `{"rate": 0.05, "cap": 200000, "seed": 0}` (any of them). Off when absent.
    #[schema(value_type = Option<Object>)]
    pub training: Option<serde_json::Value>,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct RunCreated {
    pub id: String,
    #[schema(value_type = Object)]
    pub config: FilterConfig,
    /// With it (`Authorization: Bearer <token>`) robots may register themselves in this run
    /// and nothing else. Shown once; stored only as a hash.
    pub enrollment_token: String,
}

/// `POST /v1/runs` (admin): a new run from a log header and configuration fields.
#[utoipa::path(post, path = "/v1/runs", tag = "runs", request_body = CreateRun,
    responses((status = 201, description = "Created", body = RunCreated),
              (status = 400, description = "A bad configuration: the message names the field", body = crate::error::ErrorBody),
              (status = 401, description = "Missing or wrong admin token", body = crate::error::ErrorBody)))]
pub(crate) async fn create_run(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<(StatusCode, Json<RunCreated>), ApiError> {
    check_admin(&state, &headers)?;
    let req: CreateRun = parse_json("run", &body)?;
    let limits = &state.config.limits;
    if let Some(name) = &req.name {
        limits
            .check_name("name", name)
            .map_err(ApiError::BadRequest)?;
    }
    if let Some(h) = &req.header
        && h.robots.len() > limits.max_robots_per_run
    {
        return Err(ApiError::BadRequest(format!(
            "header.robots: {} robots, at most {} per run (max_robots_per_run)",
            h.robots.len(),
            limits.max_robots_per_run
        )));
    }
    let base = req
        .header
        .as_ref()
        .map(FilterConfig::from_header)
        .unwrap_or_default();
    let config = overlay(&base, req.config.unwrap_or(serde_json::Value::Null))
        .map_err(|e| ApiError::BadRequest(format!("config: {e}")))?;
    config
        .validate()
        .map_err(|e| ApiError::BadRequest(format!("config: {e}")))?;
    let localize = overlay(
        &fleetslam_localize::LocalizeConfig::default(),
        req.localize.unwrap_or(serde_json::Value::Null),
    )
    .map_err(|e| ApiError::BadRequest(format!("localize: {e}")))?;
    let training = req
        .training
        .map(|t| overlay(&fleetslam_learned::RecordingConfig::default(), t))
        .transpose()
        .map_err(|e| ApiError::BadRequest(format!("training: {e}")))?;
    let setup = serde_json::to_string(&RunSetup {
        localize: Some(localize.clone()),
        training,
    })
    .map_err(ApiError::internal)?;
    let updater = history::updater_for(&state.store, &config).await?;
    let (updater, training) = history::recording(updater, training)?;
    let filter = history::new_filter(&config, localize, updater)?;
    // Counted and inserted under one lock, so that concurrent requests cannot pass the bound.
    let _creating = state.creating.lock().await;
    // In a cluster the bound is the cluster's: every active run in the store.
    let active = match &state.cluster {
        Some(_) => state.store.active_run_ids().await?.len(),
        None => state.runs.read().await.len(),
    };
    if active >= limits.max_active_runs {
        return Err(ApiError::Busy {
            message: format!(
                "{active} runs are running, the most this server takes (max_active_runs); end \
                 one or retry later"
            ),
            retry_after_s: 60,
        });
    }
    let id = uuid::Uuid::new_v4().to_string();
    let enrollment_token = new_token();
    let enrollment = token_hash(&enrollment_token);
    state
        .store
        .create_run(&NewRun {
            id: id.clone(),
            name: req.name,
            config: serde_json::to_value(&config).map_err(ApiError::internal)?,
            header: req
                .header
                .as_ref()
                .map(serde_json::to_value)
                .transpose()
                .map_err(ApiError::internal)?,
        })
        .await?;
    state
        .store
        .put_artifact(
            &id,
            ENROLLMENT,
            &serde_json::json!({ "token_sha256": enrollment }).to_string(),
        )
        .await?;
    state.store.put_artifact(&id, SETUP, &setup).await?;
    if state.cluster.is_some() {
        // The least loaded replica takes it (crate::cluster).
        tracing::info!(run = %id, "run created; a replica will take it");
        return Ok((
            StatusCode::CREATED,
            Json(RunCreated {
                id,
                config,
                enrollment_token,
            }),
        ));
    }
    state
        .insert_live(
            id.clone(),
            config.clone(),
            filter,
            None,
            HashMap::new(),
            Some(enrollment),
            training,
            coordinator::Clock::Wall,
        )
        .await;
    tracing::info!(run = %id, "run created");
    Ok((
        StatusCode::CREATED,
        Json(RunCreated {
            id,
            config,
            enrollment_token,
        }),
    ))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ListQuery {
    status: Option<String>,
    created_after: Option<i64>,
    created_before: Option<i64>,
    limit: Option<i64>,
    offset: Option<i64>,
}

/// `GET /v1/runs`: runs, newest first, with their summaries.
#[utoipa::path(get, path = "/v1/runs", tag = "runs",
    params(("status" = Option<String>, Query, description = "active, ended or failed"),
           ("created_after" = Option<i64>, Query, description = "Unix ms"),
           ("created_before" = Option<i64>, Query, description = "Unix ms"),
           ("limit" = Option<i64>, Query, description = "Page size, 1 to 1000 (default 50)"),
           ("offset" = Option<i64>, Query, description = "Runs to skip")),
    responses((status = 200, description = "{\"runs\": [...], \"total\": n}")))]
pub(crate) async fn list_runs(
    State(state): State<AppState>,
    Query(q): Query<ListQuery>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let limit = q.limit.unwrap_or(50);
    if !(1..=1000).contains(&limit) {
        return Err(ApiError::BadRequest(format!(
            "limit must be between 1 and 1000, got {limit}"
        )));
    }
    let filter = RunFilter {
        status: q.status,
        created_after: q.created_after,
        created_before: q.created_before,
        limit,
        offset: q.offset.unwrap_or(0).max(0),
    };
    let rows = state.store.list_runs(&filter).await?;
    let total = state.store.count_runs(&filter).await?;
    let live = state.runs.read().await;
    let runs: Vec<serde_json::Value> = rows
        .into_iter()
        .map(|mut row| {
            // A running run's summary is its live state's.
            if let Some(l) = live.get(&row.id) {
                row.summary = Some(api_history::summary(
                    &l.handle.current_state(),
                    row.records,
                    None,
                ));
            }
            let mut v = serde_json::to_value(&row).unwrap_or_default();
            if let Some(summary) = v.get_mut("summary").and_then(|s| s.as_object_mut())
                && summary.get("updater").is_none_or(|u| u.is_null())
            {
                summary.insert("updater".into(), row.config["updater"].clone());
            }
            v
        })
        .collect();
    Ok(Json(serde_json::json!({ "runs": runs, "total": total })))
}

/// `GET /v1/runs/{run}`
#[utoipa::path(get, path = "/v1/runs/{run}", tag = "runs",
    params(("run" = String, Path, description = "Run id")),
    responses((status = 200, description = "{\"run\": {...}}"), (status = 404, body = crate::error::ErrorBody)))]
pub(crate) async fn get_run(
    State(state): State<AppState>,
    Path(run): Path<String>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let row =
        state.store.get_run(&run).await?.ok_or_else(|| {
            ApiError::NotFound(format!("no run {run}: list runs with GET /v1/runs"))
        })?;
    Ok(Json(serde_json::json!({ "run": row })))
}

/// `POST /v1/runs/{run}/end` (admin): applies what the run holds, stores its result, ends it.
#[utoipa::path(post, path = "/v1/runs/{run}/end", tag = "runs",
    params(("run" = String, Path, description = "Run id")),
    responses((status = 204, description = "Ended"), (status = 409, body = crate::error::ErrorBody)))]
pub(crate) async fn end_run(
    State(state): State<AppState>,
    headers: HeaderMap,
    Path(run): Path<String>,
) -> Result<StatusCode, ApiError> {
    check_admin(&state, &headers)?;
    if let Some(cluster) = &state.cluster {
        // Through the run's subject, so that its owner ends it after every record
        // acknowledged before.
        ClusterRun::load(&state, &run).await?;
        cluster.end_run(&state, &run).await?;
        return Ok(StatusCode::NO_CONTENT);
    }
    let live = state.live(&run).await?;
    finish_run(&state, &run, &live).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// Ends a live run: the coordinator applies what it holds and stores its result, then the
/// run is marked ended with its summary.
pub(crate) async fn finish_run(
    state: &AppState,
    run: &str,
    live: &LiveRun,
) -> Result<(), ApiError> {
    live.handle.end().await?;
    let final_state = live.handle.current_state();
    let records = state.store.record_count(run).await?;
    let metrics = state
        .store
        .get_artifact(run, history::RESULT)
        .await?
        .and_then(|b| serde_json::from_str::<serde_json::Value>(&b).ok())
        .and_then(|v| serde_json::from_value::<history::RunMetrics>(v["metrics"].clone()).ok());
    let summary = api_history::summary(&final_state, records, metrics.as_ref());
    state
        .store
        .set_run_status(run, "ended", Some(&summary))
        .await?;
    state.runs.write().await.remove(run);
    tracing::info!(run = %run, "run ended");
    Ok(())
}

/// Body of `POST /v1/runs/{run}/robots`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RegisterRobot {
    pub id: String,
    /// The start pose (mean and covariance), or null/absent when unknown: the robot is then
    /// localized against the run's map (Monte Carlo localization) and joins the SLAM filter
    /// once its pose has converged.
    #[schema(value_type = Option<Object>)]
    pub start: Option<PoseGaussian>,
    /// Time of the start pose [s]. When given, it also bounds the times of the run's first
    /// records (`max_future_s`); default: the filter takes 0.
    pub t0: Option<f64>,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct RobotRegistered {
    pub robot: String,
    /// Send as `Authorization: Bearer <token>` when posting as this robot. Shown once.
    pub token: String,
    /// `mapping`, or `localizing` for a robot registered at an unknown pose.
    pub mode: &'static str,
}

/// `POST /v1/runs/{run}/robots`: registers a robot; the answer holds its token. Needs the
/// admin token or the run's enrollment token when the server has an admin token. Everything
/// is checked before anything is stored: a refused registration leaves no trace.
#[utoipa::path(post, path = "/v1/runs/{run}/robots", tag = "robots", request_body = RegisterRobot,
    params(("run" = String, Path, description = "Run id")),
    responses((status = 201, body = RobotRegistered),
              (status = 400, description = "A bad id, start pose or t0: the message names the field", body = crate::error::ErrorBody),
              (status = 401, description = "Neither the admin token nor the run's enrollment token", body = crate::error::ErrorBody),
              (status = 409, description = "The id is taken, or the run takes no more robots", body = crate::error::ErrorBody)))]
pub(crate) async fn register_robot(
    State(state): State<AppState>,
    Path(run): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<(StatusCode, Json<RobotRegistered>), ApiError> {
    if state.cluster.is_some() {
        return register_robot_in_cluster(&state, &run, &headers, &body).await;
    }
    let live = state.live(&run).await?;
    let req = check_registration(&state, &headers, &body, live.enrollment.as_deref())?;
    {
        let tokens = live.tokens.read().await;
        check_robot_is_new(&state, &run, &req.id, tokens.values())?;
    }
    let (token, row) = robot_row(&req)?;
    let hash = row.token_hash.clone();
    // The coordinator checks the id again, stores the robot, then adds it to the filter.
    live.handle.add_robot(row, req.start, req.t0).await?;
    live.tokens.write().await.insert(hash, req.id.clone());
    Ok(registered(req, token))
}

/// Checks a registration before anything is stored: the admin token or the run's
/// enrollment token (when the server has an admin token), then the body (id, t0, start).
fn check_registration(
    state: &AppState,
    headers: &HeaderMap,
    body: &[u8],
    enrollment: Option<&str>,
) -> Result<RegisterRobot, ApiError> {
    let auth = &state.config.auth;
    if auth.admin_token.is_some() {
        let given = crate::auth::bearer(headers);
        let admin = crate::auth::is_admin(auth, headers);
        let enrolled = match (given, enrollment) {
            (Some(g), Some(hash)) => crate::auth::hash_matches(g, hash),
            _ => false,
        };
        if !(admin | enrolled) {
            return Err(ApiError::Unauthorized(
                "registering a robot needs the admin token or the run's enrollment token \
                 (`enrollment_token` from POST /v1/runs): send `Authorization: Bearer <token>`"
                    .into(),
            ));
        }
    }
    let req: RegisterRobot = parse_json("robot", body)?;
    state
        .config
        .limits
        .check_name("id", &req.id)
        .map_err(ApiError::BadRequest)?;
    if let Some(t0) = req.t0
        && !t0.is_finite()
    {
        return Err(ApiError::BadRequest(format!(
            "t0 must be a finite time in seconds, got {t0}"
        )));
    }
    if let Some(start) = &req.start {
        crate::limits::check_start(start)
            .map_err(|e| ApiError::BadRequest(format!("start: {e}")))?;
    }
    Ok(req)
}

/// 409 when the run already has robot `id`, or as many robots as a run takes.
fn check_robot_is_new<'a>(
    state: &AppState,
    run: &str,
    id: &str,
    robots: impl ExactSizeIterator<Item = &'a String>,
) -> Result<(), ApiError> {
    let n = robots.len();
    let mut robots = robots;
    if robots.any(|r| r == id) {
        return Err(ApiError::Conflict(format!(
            "robot {id:?} is already registered in this run"
        )));
    }
    if n >= state.config.limits.max_robots_per_run {
        return Err(ApiError::Conflict(format!(
            "run {run} has {n} robots, the most a run takes (max_robots_per_run)"
        )));
    }
    Ok(())
}

/// A new token for the robot, and the row that stores it (with the token's hash only).
fn robot_row(req: &RegisterRobot) -> Result<(String, NewRobot), ApiError> {
    let token = new_token();
    let row = NewRobot {
        robot_id: req.id.clone(),
        start: req
            .start
            .as_ref()
            .map(serde_json::to_value)
            .transpose()
            .map_err(ApiError::internal)?,
        token_hash: token_hash(&token),
        t0: req.t0,
    };
    Ok((token, row))
}

/// The answer to a registration.
fn registered(req: RegisterRobot, token: String) -> (StatusCode, Json<RobotRegistered>) {
    let mode = if req.start.is_some() {
        "mapping"
    } else {
        "localizing"
    };
    (
        StatusCode::CREATED,
        Json(RobotRegistered {
            robot: req.id,
            token,
            mode,
        }),
    )
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct IngestResponse {
    pub acks: Vec<RecordAck>,
}

/// One record, an array of records, or NDJSON (one record per line); at most `max`.
fn parse_records(headers: &HeaderMap, body: &[u8], max: usize) -> Result<Vec<Record>, ApiError> {
    let records = parse_records_unbounded(headers, body)?;
    if records.len() > max {
        return Err(ApiError::TooLarge(format!(
            "{} records in one request, at most {max} (max_records_per_request): send them in \
             several requests",
            records.len()
        )));
    }
    Ok(records)
}

fn parse_records_unbounded(headers: &HeaderMap, body: &[u8]) -> Result<Vec<Record>, ApiError> {
    let ndjson = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|c| {
            c.starts_with("application/x-ndjson") || c.starts_with("application/jsonl")
        });
    if ndjson {
        let text = std::str::from_utf8(body)
            .map_err(|e| ApiError::BadRequest(format!("body is not UTF-8: {e}")))?;
        return text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
            .map(|(i, l)| parse_json(&format!("line {}", i + 1), l.as_bytes()))
            .collect();
    }
    let first = body.iter().find(|b| !b.is_ascii_whitespace());
    match first {
        Some(b'[') => parse_json("records", body),
        Some(b'{') => Ok(vec![parse_json("record", body)?]),
        _ => Err(ApiError::BadRequest(
            "body must be a JSON record, a JSON array of records, or NDJSON (Content-Type: application/x-ndjson)".into(),
        )),
    }
}

/// `POST /v1/runs/{run}/observations` (robot token): one record, an array, or NDJSON.
#[utoipa::path(post, path = "/v1/runs/{run}/observations", tag = "robots",
    params(("run" = String, Path, description = "Run id")),
    request_body(content = Object, description = "A record, an array of records, or NDJSON (application/x-ndjson) in the log format"),
    responses((status = 200, description = "Every record stored or a duplicate", body = IngestResponse),
              (status = 409, description = "Some records were rejected (see each ack)", body = IngestResponse),
              (status = 503, description = "The run's queue is full; retry after Retry-After", body = crate::error::ErrorBody)))]
pub(crate) async fn post_observations(
    State(state): State<AppState>,
    Path(run): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    if state.cluster.is_some() {
        return post_observations_in_cluster(&state, &run, &headers, &body).await;
    }
    let live = state.live(&run).await?;
    let robot = live
        .tokens
        .read()
        .await
        .get(&token_hash(robot_token(&headers)?))
        .cloned()
        .ok_or_else(unknown_robot_token)?;
    let records = check_records(&state, &headers, &body, &robot, &live.config)?;
    let acks = live.handle.ingest(records).await?;
    let status = if acks.iter().any(|a| a.status == "rejected") {
        StatusCode::CONFLICT
    } else {
        StatusCode::OK
    };
    Ok((status, Json(IngestResponse { acks })).into_response())
}

/// The robot token a POST of records carries.
fn robot_token(headers: &HeaderMap) -> Result<&str, ApiError> {
    crate::auth::bearer(headers).ok_or_else(|| {
        ApiError::Unauthorized(
            "send the robot's token as `Authorization: Bearer <token>` (from registration)".into(),
        )
    })
}

fn unknown_robot_token() -> ApiError {
    ApiError::Unauthorized("unknown robot token for this run".into())
}

/// Parses the records of a POST by `robot` and checks each against the run's models and
/// the server's limits; the first bad one is the error.
fn check_records(
    state: &AppState,
    headers: &HeaderMap,
    body: &[u8],
    robot: &str,
    config: &FilterConfig,
) -> Result<Vec<Record>, ApiError> {
    let limits = &state.config.limits;
    let records = parse_records(headers, body, limits.max_records_per_request)?;
    if records.is_empty() {
        return Err(ApiError::BadRequest("no records in the body".into()));
    }
    for (i, r) in records.iter().enumerate() {
        if r.robot != robot {
            return Err(ApiError::Forbidden(format!(
                "record {i} is for robot {:?} but the token is robot {robot:?}'s: a robot \
                 posts only its own records",
                crate::limits::truncate(&r.robot, 80)
            )));
        }
        r.validate(config.landmark_kind, config.motion_model)
            .and_then(|()| limits.check_record(r))
            .map_err(|e| ApiError::BadRequest(format!("record {i} (seq {}): {e}", r.seq)))?;
    }
    Ok(records)
}

#[derive(Debug, Deserialize)]
pub(crate) struct LiveQuery {
    /// `full` (default): every state carries every landmark; `delta`: compact states with
    /// the landmarks that changed ([`crate::compact`]).
    landmarks: Option<String>,
}

/// `GET /v1/runs/{run}/live[?landmarks=full|delta]` (websocket): states and events.
#[utoipa::path(get, path = "/v1/runs/{run}/live", tag = "runs",
    params(("run" = String, Path, description = "Run id"),
           ("landmarks" = Option<String>, Query, description = "full (default): every state carries every landmark; delta: states carry the landmarks that changed since the connection's previous state (see the compact module)")),
    responses((status = 101, description = "Websocket: {\"type\": \"state\"|\"event\"|\"lagged\"|\"heartbeat\", ...}")))]
pub(crate) async fn live(
    State(state): State<AppState>,
    Path(run): Path<String>,
    Query(q): Query<LiveQuery>,
    ws: WebSocketUpgrade,
    permit: crate::ws_limit::WsPermit,
) -> Result<Response, ApiError> {
    let delta = match q.landmarks.as_deref() {
        None | Some("full") => false,
        Some("delta") => true,
        Some(other) => {
            return Err(ApiError::BadRequest(format!(
                "landmarks must be full or delta, got {other:?}"
            )));
        }
    };
    if let Some(cluster) = &state.cluster
        && state.running(&run).await.is_none()
    {
        // Owned by another replica: its states and events, relayed.
        ClusterRun::load(&state, &run).await?;
        let (states, events) = cluster.subscribe_live(&run).await?;
        let heartbeat = state.config.coordinator.ws_heartbeat;
        return Ok(ws.on_upgrade(move |socket| async move {
            let _slot = permit;
            relay_run(socket, states, events, heartbeat).await
        }));
    }
    let live = state.live(&run).await?;
    let rate = state.config.coordinator.state_rate_hz;
    let heartbeat = state.config.coordinator.ws_heartbeat;
    Ok(ws.on_upgrade(move |socket| async move {
        let _slot = permit; // held for as long as the connection lives
        stream_run(socket, live.handle.clone(), rate, heartbeat, delta).await
    }))
}

/// Streams `{"type":"state",...}` at most `rate` times a second (always the newest state: a
/// slow client skips states, never queues them) and `{"type":"event",...}` as they happen; a
/// client too slow for the events gets a `lagged` notice and a fresh full state; a heartbeat
/// keeps an idle connection known to be alive ([`crate::ws_limit::Heartbeat`]). With
/// `delta`, states are compact ([`crate::compact`]).
async fn stream_run(
    mut socket: WebSocket,
    handle: RunHandle,
    rate: f64,
    heartbeat: std::time::Duration,
    delta: bool,
) {
    let mut hb = crate::ws_limit::Heartbeat::new(heartbeat);
    let mut state_rx = handle.state.clone();
    let mut events = handle.events.subscribe();
    let period = std::time::Duration::from_secs_f64(1.0 / rate.max(0.1));
    let mut compact = delta.then(crate::compact::LandmarkDelta::new);
    // Built (once per publication, for every listener) and serialized only here.
    let mut send_state = |s: &PublishedState| match &mut compact {
        Some(c) => c.message(&s.get()),
        None => serde_json::json!({ "type": "state", "state": &*s.get() }).to_string(),
    };
    // The state last sent: a newer one is sent at the next tick, also the final one that a
    // run publishes as its coordinator stops (a closed channel reports no change).
    let mut sent = state_rx.borrow_and_update().clone();
    let first = send_state(&sent);
    if socket.send(Message::Text(first.into())).await.is_err() {
        return;
    }
    let mut tick = tokio::time::interval(period);
    loop {
        tokio::select! {
            _ = tick.tick() => {
                let latest = state_rx.borrow_and_update().clone();
                if !Arc::ptr_eq(&latest, &sent) {
                    let text = send_state(&latest);
                    sent = latest;
                    if socket.send(Message::Text(text.into())).await.is_err() { return; }
                }
            }
            ev = events.recv() => {
                let text = match ev {
                    Ok(e) => serde_json::json!({ "type": "event", "event": e }).to_string(),
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => {
                        let lag = serde_json::json!({ "type": "lagged", "missed_events": n }).to_string();
                        if socket.send(Message::Text(lag.into())).await.is_err() { return; }
                        sent = state_rx.borrow_and_update().clone();
                        send_state(&sent)
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
                };
                if socket.send(Message::Text(text.into())).await.is_err() { return; }
            }
            () = hb.beat() => {
                if !beat(&mut socket, &hb).await { return; }
            }
            msg = socket.recv() => match msg {
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return,
                _ => hb.heard(),
            },
        }
    }
}

/// One heartbeat on a live connection: false when the connection is to be dropped (the
/// client has been silent too long, or the send failed).
async fn beat(socket: &mut WebSocket, hb: &crate::ws_limit::Heartbeat) -> bool {
    if hb.dead() {
        tracing::debug!("closing a live connection whose client stopped answering");
        let _ = socket.send(Message::Close(None)).await;
        return false;
    }
    socket
        .send(Message::Ping(axum::body::Bytes::new()))
        .await
        .is_ok()
        && socket
            .send(Message::Text(hb.message().into()))
            .await
            .is_ok()
}

/// What a cluster replica needs to know of a run to check requests for it: read from the
/// store, kept per run (the status is read again on every request).
#[derive(Debug)]
pub(crate) struct ClusterRun {
    pub(crate) config: FilterConfig,
    enrollment: Option<String>,
    /// sha256(token) hex -> robot id; read again from the store on a miss (the robot may
    /// have registered through another replica).
    tokens: RwLock<HashMap<String, String>>,
}

impl ClusterRun {
    /// The run, if it is active (the errors of a single server otherwise).
    pub(crate) async fn load(state: &AppState, run: &str) -> Result<Arc<ClusterRun>, ApiError> {
        let cluster = state
            .cluster
            .as_ref()
            .ok_or_else(|| ApiError::internal(anyhow::anyhow!("not in cluster mode")))?;
        match state.store.run_status(run).await?.as_deref() {
            Some("active") => {}
            Some(_) => {
                cluster.runs.write().await.remove(run);
                let row = state.store.get_run(run).await?;
                return Err(match row {
                    Some(row) => api_history::not_running(&row),
                    None => ApiError::NotFound(format!("no run {run}")),
                });
            }
            None => {
                return Err(ApiError::NotFound(format!(
                    "no run {run}: list runs with GET /v1/runs"
                )));
            }
        }
        if let Some(info) = cluster.runs.read().await.get(run) {
            return Ok(info.clone());
        }
        let row = state
            .store
            .get_run(run)
            .await?
            .ok_or_else(|| ApiError::NotFound(format!("no run {run}")))?;
        let config: FilterConfig = serde_json::from_value(row.config)
            .map_err(|e| ApiError::internal(anyhow::anyhow!("stored config: {e}")))?;
        let enrollment = stored_enrollment(&state.store, run).await?;
        let info = Arc::new(ClusterRun {
            config,
            enrollment,
            tokens: RwLock::new(HashMap::new()),
        });
        info.reload_tokens(state, run).await?;
        cluster
            .runs
            .write()
            .await
            .insert(run.to_string(), info.clone());
        Ok(info)
    }

    async fn reload_tokens(&self, state: &AppState, run: &str) -> Result<(), ApiError> {
        let robots = state.store.robots(run).await?;
        *self.tokens.write().await = robots
            .into_iter()
            .map(|r| (r.token_hash, r.robot_id))
            .collect();
        Ok(())
    }

    /// The robot whose token this is.
    async fn robot(&self, state: &AppState, run: &str, token: &str) -> Result<String, ApiError> {
        let hash = token_hash(token);
        if let Some(r) = self.tokens.read().await.get(&hash) {
            return Ok(r.clone());
        }
        self.reload_tokens(state, run).await?;
        self.tokens
            .read()
            .await
            .get(&hash)
            .cloned()
            .ok_or_else(unknown_robot_token)
    }
}

/// Checks a registration as [`register_robot`] does, stores the robot's row, then publishes
/// the registration to the run's subject: its owner adds the robot at that point of the
/// run's order.
async fn register_robot_in_cluster(
    state: &AppState,
    run: &str,
    headers: &HeaderMap,
    body: &[u8],
) -> Result<(StatusCode, Json<RobotRegistered>), ApiError> {
    let cluster = state.cluster.as_ref().expect("cluster mode");
    let info = ClusterRun::load(state, run).await?;
    let req = check_registration(state, headers, body, info.enrollment.as_deref())?;
    let robots = state.store.robots(run).await?;
    check_robot_is_new(state, run, &req.id, robots.iter().map(|r| &r.robot_id))?;
    let (token, row) = robot_row(&req)?;
    // The store's key refuses a robot registered meanwhile through another replica.
    state.store.add_robot(run, &row).await?;
    cluster
        .publish_registration(run, &req.id, req.start, req.t0, &row.token_hash)
        .await?;
    info.tokens
        .write()
        .await
        .insert(row.token_hash, req.id.clone());
    Ok(registered(req, token))
}

/// Checks records as [`post_observations`] does and publishes them to the run's subject;
/// acknowledged once JetStream has acknowledged each.
async fn post_observations_in_cluster(
    state: &AppState,
    run: &str,
    headers: &HeaderMap,
    body: &[u8],
) -> Result<Response, ApiError> {
    let cluster = state.cluster.as_ref().expect("cluster mode");
    let info = ClusterRun::load(state, run).await?;
    let robot = info.robot(state, run, robot_token(headers)?).await?;
    let records = check_records(state, headers, body, &robot, &info.config)?;
    let acks = cluster.publish_records(run, &records).await?;
    Ok((StatusCode::OK, Json(IngestResponse { acks })).into_response())
}

/// The live websocket of a run that another replica owns: the owner's messages as it
/// publishes them (it throttles the states).
async fn relay_run(
    mut socket: WebSocket,
    mut states: async_nats::Subscriber,
    mut events: async_nats::Subscriber,
    heartbeat: std::time::Duration,
) {
    use futures::StreamExt;
    let mut hb = crate::ws_limit::Heartbeat::new(heartbeat);
    loop {
        let msg = tokio::select! {
            m = states.next() => m,
            m = events.next() => m,
            () = hb.beat() => {
                if !beat(&mut socket, &hb).await { return; }
                continue;
            }
            msg = socket.recv() => match msg {
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return,
                _ => {
                    hb.heard();
                    continue;
                }
            },
        };
        let Some(m) = msg else { return };
        let Ok(text) = String::from_utf8(m.payload.to_vec()) else {
            continue;
        };
        if socket.send(Message::Text(text.into())).await.is_err() {
            return;
        }
    }
}
