//! Shared by the API tests: a router over a fresh SQLite store, called with `oneshot`.
#![allow(dead_code)]

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use fleetslam_core::config::FilterConfig;
use fleetslam_core::log::Log;
use fleetslam_data::sim::{SimConfig, simulate};
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_server::coordinator::RunHandle;
use fleetslam_store::{NewRobot, NewRun, Store};
use serde_json::{Value, json};
use tower::ServiceExt;

pub struct Harness {
    pub router: axum::Router,
    pub store: Store,
    pub dir: tempfile::TempDir,
}

pub async fn harness(config: ApiConfig) -> Harness {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open_default(dir.path()).await.unwrap();
    Harness {
        router: app(AppState::new(store.clone(), config)),
        store,
        dir,
    }
}

impl Harness {
    pub async fn call(
        &self,
        method: &str,
        uri: &str,
        token: Option<&str>,
        content_type: &str,
        body: Vec<u8>,
    ) -> (StatusCode, Value) {
        let mut req = Request::builder()
            .method(method)
            .uri(uri)
            .header(header::CONTENT_TYPE, content_type);
        if let Some(t) = token {
            req = req.header(header::AUTHORIZATION, format!("Bearer {t}"));
        }
        let resp = self
            .router
            .clone()
            .oneshot(req.body(Body::from(body)).unwrap())
            .await
            .unwrap();
        let status = resp.status();
        let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX)
            .await
            .unwrap();
        let v = serde_json::from_slice(&bytes)
            .unwrap_or(Value::String(String::from_utf8_lossy(&bytes).into()));
        (status, v)
    }

    pub async fn json(
        &self,
        method: &str,
        uri: &str,
        token: Option<&str>,
        body: Value,
    ) -> (StatusCode, Value) {
        self.call(
            method,
            uri,
            token,
            "application/json",
            serde_json::to_vec(&body).unwrap(),
        )
        .await
    }

    /// The status and raw body of a bodiless request.
    pub async fn raw(&self, method: &str, uri: &str) -> (StatusCode, Vec<u8>) {
        let req = Request::builder()
            .method(method)
            .uri(uri)
            .body(Body::empty())
            .unwrap();
        let resp = self.router.clone().oneshot(req).await.unwrap();
        let status = resp.status();
        let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX)
            .await
            .unwrap();
        (status, bytes.to_vec())
    }

    pub async fn get(&self, uri: &str) -> (StatusCode, Value) {
        self.call("GET", uri, None, "application/json", Vec::new())
            .await
    }

    /// The run's state once `ready` holds (states are published at a bounded rate).
    pub async fn state_when(&self, run: &str, ready: impl Fn(&Value) -> bool) -> Value {
        let uri = format!("/v1/runs/{run}/state");
        for _ in 0..200 {
            let (_, v) = self.get(&uri).await;
            if ready(&v) {
                return v;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
        panic!("state never became ready: {}", self.get(&uri).await.1);
    }
}

pub fn sim_log(robots: usize, duration: f64) -> Log {
    let mut log = simulate(&SimConfig {
        robots,
        duration,
        seed: 5,
        ..SimConfig::default()
    })
    .unwrap()
    .log;
    log.sort();
    log
}

/// Creates a run from the log's header and registers its robots; returns (run, tokens).
pub async fn setup(h: &Harness, log: &Log, config: Value) -> (String, Vec<(String, String)>) {
    let (s, v) = h
        .json(
            "POST",
            "/v1/runs",
            None,
            json!({"name": "t", "header": log.header, "config": config}),
        )
        .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let run = v["id"].as_str().unwrap().to_string();
    let mut tokens = Vec::new();
    for r in &log.header.robots {
        let (s, v) = h
            .json(
                "POST",
                &format!("/v1/runs/{run}/robots"),
                None,
                json!({"id": r.id, "start": r.start, "t0": r.t0}),
            )
            .await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        assert_eq!(v["mode"], "mapping");
        tokens.push((r.id.clone(), v["token"].as_str().unwrap().to_string()));
    }
    (run, tokens)
}

/// [`setup`] over real HTTP at `base`: creates a run from the log's header with `config`
/// and registers its robots; returns (run, tokens).
pub async fn setup_over_http(
    c: &reqwest::Client,
    base: &str,
    log: &Log,
    config: Value,
) -> (String, Vec<(String, String)>) {
    let post = |url: String, body: Value| async move {
        let resp = c.post(url).json(&body).send().await.unwrap();
        assert!(resp.status().is_success(), "{}", resp.status());
        resp.json::<Value>().await.unwrap()
    };
    let v = post(
        format!("{base}/v1/runs"),
        json!({"header": log.header, "config": config}),
    )
    .await;
    let run = v["id"].as_str().unwrap().to_string();
    let mut tokens = Vec::new();
    for r in &log.header.robots {
        let v = post(
            format!("{base}/v1/runs/{run}/robots"),
            json!({"id": r.id, "start": r.start, "t0": r.t0}),
        )
        .await;
        tokens.push((r.id.clone(), v["token"].as_str().unwrap().to_string()));
    }
    (run, tokens)
}

/// A fresh SQLite store in `dir` holding one run `id` for `log`, with the header's filter
/// configuration at `particles` and `seed`: the set-up of the tests that drive a
/// coordinator directly.
pub async fn store_with_run(
    dir: &std::path::Path,
    id: &str,
    log: &Log,
    particles: usize,
    seed: u64,
) -> (Store, FilterConfig) {
    let store = Store::open_default(dir).await.unwrap();
    let mut cfg = FilterConfig::from_header(&log.header);
    cfg.particles = particles;
    cfg.seed = seed;
    store
        .create_run(&NewRun {
            id: id.into(),
            name: None,
            config: serde_json::to_value(&cfg).unwrap(),
            header: None,
        })
        .await
        .unwrap();
    (store, cfg)
}

/// Registers the log header's robots (start pose, t0, a token named after the robot) with
/// a coordinator driven directly.
pub async fn register_header_robots(handle: &RunHandle, log: &Log) {
    for r in &log.header.robots {
        handle
            .add_robot(
                NewRobot {
                    robot_id: r.id.clone(),
                    start: r.start.map(|s| serde_json::to_value(s).unwrap()),
                    token_hash: fleetslam_server::auth::token_hash(&r.id),
                    t0: r.t0,
                },
                r.start,
                r.t0,
            )
            .await
            .unwrap();
    }
}
