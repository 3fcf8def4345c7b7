//! The HTTP API (versioned under `/v1`), built as `app(state) -> Router` so tests can call it
//! with `tower::ServiceExt::oneshot`.

use crate::coordinator::{self, CoordinatorConfig, RecordAck, RunHandle, RunState};
use crate::error::ApiError;
use axum::body::Bytes;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use fleetslam_core::config::{FilterConfig, overlay};
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::{LogHeader, Record};
use fleetslam_core::pose::PoseGaussian;
use fleetslam_store::{NewRobot, NewRun, RunFilter, Store};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::sync::Arc;
use tokio::sync::RwLock;

/// Server-wide settings the handlers need.
#[derive(Debug, Clone)]
pub struct ApiConfig {
    /// Required as `Authorization: Bearer <token>` to create and end runs, when set.
    pub admin_token: Option<String>,
    /// Largest request body [bytes].
    pub body_limit: usize,
    pub coordinator: CoordinatorConfig,
}

impl Default for ApiConfig {
    fn default() -> Self {
        Self {
            admin_token: None,
            body_limit: 16 << 20,
            coordinator: CoordinatorConfig::default(),
        }
    }
}

/// A live run: its coordinator and who may post as which robot.
#[derive(Debug)]
struct LiveRun {
    handle: RunHandle,
    config: FilterConfig,
    /// sha256(token) hex -> robot id.
    tokens: RwLock<HashMap<String, String>>,
}

/// Shared state of the handlers.
#[derive(Debug, Clone)]
pub struct AppState {
    pub store: Store,
    pub config: Arc<ApiConfig>,
    runs: Arc<RwLock<HashMap<String, Arc<LiveRun>>>>,
}

impl AppState {
    pub fn new(store: Store, config: ApiConfig) -> Self {
        Self {
            store,
            config: Arc::new(config),
            runs: Arc::default(),
        }
    }

    async fn live(&self, id: &str) -> Result<Arc<LiveRun>, ApiError> {
        if let Some(r) = self.runs.read().await.get(id) {
            return Ok(r.clone());
        }
        match self.store.get_run(id).await? {
            Some(row) if row.status == "active" => Err(ApiError::Conflict(format!(
                "run {id} is active in the store but not running in this server (it was started \
                 before a restart, and recovery is not implemented yet); create a new run"
            ))),
            Some(row) => Err(ApiError::Conflict(format!(
                "run {id} is {}: it takes no more data",
                row.status
            ))),
            None => Err(ApiError::NotFound(format!(
                "no run {id}: list runs with GET /v1/runs"
            ))),
        }
    }
}

pub fn app(state: AppState) -> Router {
    let limit = state.config.body_limit;
    Router::new()
        .route("/healthz", get(|| async { "ok" }))
        .route("/v1/runs", post(create_run).get(list_runs))
        .route("/v1/runs/{run}", get(get_run))
        .route("/v1/runs/{run}/end", post(end_run))
        .route("/v1/runs/{run}/robots", post(register_robot))
        .route("/v1/runs/{run}/observations", post(post_observations))
        .route("/v1/runs/{run}/state", get(get_state))
        .route("/v1/runs/{run}/live", get(live))
        .layer(DefaultBodyLimit::max(limit))
        .with_state(state)
}

fn token_hash(token: &str) -> String {
    hex::encode(Sha256::digest(token.as_bytes()))
}

fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers
        .get(header::AUTHORIZATION)?
        .to_str()
        .ok()?
        .strip_prefix("Bearer ")
        .map(str::trim)
}

fn check_admin(state: &AppState, headers: &HeaderMap) -> Result<(), ApiError> {
    match &state.config.admin_token {
        None => Ok(()),
        Some(t) if bearer(headers) == Some(t.as_str()) => Ok(()),
        Some(_) => Err(ApiError::Unauthorized(
            "this action needs the admin token: send `Authorization: Bearer <admin token>`".into(),
        )),
    }
}

/// Parses JSON into `T`, turning serde's message into a 400 that names the field.
fn parse_json<T: serde::de::DeserializeOwned>(what: &str, body: &[u8]) -> Result<T, ApiError> {
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
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct RunCreated {
    pub id: String,
    #[schema(value_type = Object)]
    pub config: FilterConfig,
}

async fn create_run(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<(StatusCode, Json<RunCreated>), ApiError> {
    check_admin(&state, &headers)?;
    let req: CreateRun = parse_json("run", &body)?;
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
    let filter = FastSlam::new(config.clone()).map_err(|e| ApiError::BadRequest(e.to_string()))?;
    let id = uuid::Uuid::new_v4().to_string();
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
    let handle = coordinator::spawn(
        id.clone(),
        filter,
        state.store.clone(),
        state.config.coordinator.clone(),
    );
    let live = LiveRun {
        handle,
        config: config.clone(),
        tokens: RwLock::default(),
    };
    state.runs.write().await.insert(id.clone(), Arc::new(live));
    tracing::info!(run = %id, "run created");
    Ok((StatusCode::CREATED, Json(RunCreated { id, config })))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ListQuery {
    status: Option<String>,
    created_after: Option<i64>,
    created_before: Option<i64>,
    limit: Option<i64>,
    offset: Option<i64>,
}

async fn list_runs(
    State(state): State<AppState>,
    Query(q): Query<ListQuery>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let limit = q.limit.unwrap_or(50);
    if !(1..=1000).contains(&limit) {
        return Err(ApiError::BadRequest(format!(
            "limit must be between 1 and 1000, got {limit}"
        )));
    }
    let rows = state
        .store
        .list_runs(&RunFilter {
            status: q.status,
            created_after: q.created_after,
            created_before: q.created_before,
            limit,
            offset: q.offset.unwrap_or(0).max(0),
        })
        .await?;
    Ok(Json(serde_json::json!({ "runs": rows })))
}

async fn get_run(
    State(state): State<AppState>,
    Path(run): Path<String>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let row =
        state.store.get_run(&run).await?.ok_or_else(|| {
            ApiError::NotFound(format!("no run {run}: list runs with GET /v1/runs"))
        })?;
    Ok(Json(serde_json::json!({ "run": row })))
}

async fn end_run(
    State(state): State<AppState>,
    headers: HeaderMap,
    Path(run): Path<String>,
) -> Result<StatusCode, ApiError> {
    check_admin(&state, &headers)?;
    let live = state.live(&run).await?;
    live.handle.end().await?;
    let summary =
        serde_json::to_value(&*live.handle.state.borrow().clone()).map_err(ApiError::internal)?;
    state
        .store
        .set_run_status(&run, "ended", Some(&summary))
        .await?;
    state.runs.write().await.remove(&run);
    Ok(StatusCode::NO_CONTENT)
}

/// Body of `POST /v1/runs/{run}/robots`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RegisterRobot {
    pub id: String,
    /// The start pose (mean and covariance), or null/absent when unknown: the robot's records
    /// are then stored but not merged until it is localized.
    #[schema(value_type = Option<Object>)]
    pub start: Option<PoseGaussian>,
    /// Time of the start pose [s]; default 0.
    pub t0: Option<f64>,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct RobotRegistered {
    pub robot: String,
    /// Send as `Authorization: Bearer <token>` when posting as this robot. Shown once.
    pub token: String,
    /// `mapping` or `unknown_pose`.
    pub mode: &'static str,
}

async fn register_robot(
    State(state): State<AppState>,
    Path(run): Path<String>,
    body: Bytes,
) -> Result<(StatusCode, Json<RobotRegistered>), ApiError> {
    let req: RegisterRobot = parse_json("robot", &body)?;
    if req.id.is_empty() || req.id.len() > 64 || req.id.chars().any(|c| c.is_control() || c == '/')
    {
        return Err(ApiError::BadRequest(format!(
            "robot id must be 1-64 printable characters without '/', got {:?}",
            req.id
        )));
    }
    let t0 = req.t0.unwrap_or(0.0);
    if !t0.is_finite() {
        return Err(ApiError::BadRequest(format!(
            "t0 must be a finite time in seconds, got {t0}"
        )));
    }
    let live = state.live(&run).await?;
    let token = hex::encode(rand::random::<[u8; 24]>());
    let hash = token_hash(&token);
    state
        .store
        .add_robot(
            &run,
            &NewRobot {
                robot_id: req.id.clone(),
                start: req
                    .start
                    .as_ref()
                    .map(serde_json::to_value)
                    .transpose()
                    .map_err(ApiError::internal)?,
                token_hash: hash.clone(),
                t0: Some(t0),
            },
        )
        .await?;
    live.handle.add_robot(req.id.clone(), req.start, t0).await?;
    live.tokens.write().await.insert(hash, req.id.clone());
    let mode = if req.start.is_some() {
        "mapping"
    } else {
        "unknown_pose"
    };
    Ok((
        StatusCode::CREATED,
        Json(RobotRegistered {
            robot: req.id,
            token,
            mode,
        }),
    ))
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct IngestResponse {
    pub acks: Vec<RecordAck>,
}

/// One record, an array of records, or NDJSON (one record per line).
fn parse_records(headers: &HeaderMap, body: &[u8]) -> Result<Vec<Record>, ApiError> {
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

async fn post_observations(
    State(state): State<AppState>,
    Path(run): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let live = state.live(&run).await?;
    let token = bearer(&headers).ok_or_else(|| {
        ApiError::Unauthorized(
            "send the robot's token as `Authorization: Bearer <token>` (from registration)".into(),
        )
    })?;
    let robot = live
        .tokens
        .read()
        .await
        .get(&token_hash(token))
        .cloned()
        .ok_or_else(|| ApiError::Unauthorized("unknown robot token for this run".into()))?;
    let records = parse_records(&headers, &body)?;
    if records.is_empty() {
        return Err(ApiError::BadRequest("no records in the body".into()));
    }
    for (i, r) in records.iter().enumerate() {
        if r.robot != robot {
            return Err(ApiError::Unauthorized(format!(
                "record {i} is for robot {:?} but the token is robot {robot:?}'s",
                r.robot
            )));
        }
        r.validate(live.config.landmark_kind, live.config.motion_model)
            .map_err(|e| ApiError::BadRequest(format!("record {i} (seq {}): {e}", r.seq)))?;
    }
    let acks = live.handle.ingest(records).await?;
    let status = if acks.iter().any(|a| a.status == "rejected") {
        StatusCode::CONFLICT
    } else {
        StatusCode::OK
    };
    Ok((status, Json(IngestResponse { acks })).into_response())
}

async fn get_state(
    State(state): State<AppState>,
    Path(run): Path<String>,
) -> Result<Json<Arc<RunState>>, ApiError> {
    let live = state.live(&run).await?;
    let s = live.handle.state.borrow().clone();
    Ok(Json(s))
}

async fn live(
    State(state): State<AppState>,
    Path(run): Path<String>,
    ws: WebSocketUpgrade,
) -> Result<Response, ApiError> {
    let live = state.live(&run).await?;
    let rate = state.config.coordinator.state_rate_hz;
    Ok(ws.on_upgrade(move |socket| stream_run(socket, live.handle.clone(), rate)))
}

/// Streams `{"type":"state",...}` at most `rate` times a second (always the newest state: a
/// slow client skips states, never queues them) and `{"type":"event",...}` as they happen; a
/// client too slow for the events gets a `lagged` notice and a fresh full state.
async fn stream_run(mut socket: WebSocket, handle: RunHandle, rate: f64) {
    let mut state_rx = handle.state.clone();
    let mut events = handle.events.subscribe();
    let period = std::time::Duration::from_secs_f64(1.0 / rate.max(0.1));
    let send_state = |s: &RunState| serde_json::json!({ "type": "state", "state": s }).to_string();
    let first = send_state(&state_rx.borrow_and_update());
    if socket.send(Message::Text(first.into())).await.is_err() {
        return;
    }
    let mut tick = tokio::time::interval(period);
    loop {
        tokio::select! {
            _ = tick.tick() => {
                if state_rx.has_changed().unwrap_or(false) {
                    let text = send_state(&state_rx.borrow_and_update());
                    if socket.send(Message::Text(text.into())).await.is_err() { return; }
                }
            }
            ev = events.recv() => {
                let text = match ev {
                    Ok(e) => serde_json::json!({ "type": "event", "event": e }).to_string(),
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => {
                        let lag = serde_json::json!({ "type": "lagged", "missed_events": n }).to_string();
                        if socket.send(Message::Text(lag.into())).await.is_err() { return; }
                        send_state(&state_rx.borrow_and_update())
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
                };
                if socket.send(Message::Text(text.into())).await.is_err() { return; }
            }
            msg = socket.recv() => match msg {
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return,
                _ => {}
            },
        }
    }
}
