//! The cost of a snapshot and of a recovery for a large run.
//!
//! Posts a log to an in-process server (its robots as in the header), waits until every
//! record is applied, tears the runtime down without ending the run (a crash), then starts
//! again on the same store and times the recovery; then times one snapshot's parts
//! (capture, encoding, storing) on the recovered run's latest snapshot.
//!
//! ```sh
//! cargo run --release -p fleetslam-server --example recovery_cost -- LOG [PARTICLES] [DATABASE_URL]
//! ```

use axum::body::Body;
use axum::http::{Request, StatusCode};
use fleetslam_core::log::Log;
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_server::history::RunSnapshot;
use fleetslam_store::{NewSnapshot, Store};
use serde_json::{Value, json};
use std::time::{Duration, Instant};
use tower::ServiceExt;

async fn call(
    router: &axum::Router,
    method: &str,
    uri: &str,
    token: Option<&str>,
    body: Vec<u8>,
) -> (StatusCode, Value) {
    let mut req = Request::builder()
        .method(method)
        .uri(uri)
        .header("content-type", "application/json");
    if let Some(t) = token {
        req = req.header("authorization", format!("Bearer {t}"));
    }
    let resp = router
        .clone()
        .oneshot(req.body(Body::from(body)).unwrap())
        .await
        .unwrap();
    let status = resp.status();
    let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX)
        .await
        .unwrap();
    (
        status,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

async fn open(url: &Option<String>, dir: &std::path::Path) -> Store {
    match url {
        Some(u) => Store::open(u).await.unwrap(),
        None => Store::open_default(dir).await.unwrap(),
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let path = args
        .get(1)
        .expect("usage: recovery_cost LOG [PARTICLES] [DATABASE_URL]");
    let particles: usize = args.get(2).map_or(1000, |p| p.parse().unwrap());
    let url = args.get(3).cloned();
    let mut log = Log::read_path(path).unwrap();
    log.sort();
    let n = log.records.len();
    let dir = tempfile::tempdir().unwrap();
    let cfg = ApiConfig::default();
    let every = cfg.coordinator.snapshot_every;

    let rt = tokio::runtime::Runtime::new().unwrap();
    let (run, post_s) = rt.block_on(async {
        let store = open(&url, dir.path()).await;
        let router = app(AppState::new(store, cfg.clone()));
        let body = json!({"header": log.header, "config": {"particles": particles, "seed": 1}});
        let (s, v) = call(
            &router,
            "POST",
            "/v1/runs",
            None,
            serde_json::to_vec(&body).unwrap(),
        )
        .await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        let run = v["id"].as_str().unwrap().to_string();
        let mut tokens = std::collections::HashMap::new();
        for r in &log.header.robots {
            let b = json!({"id": r.id, "start": r.start, "t0": r.t0});
            let (s, v) = call(
                &router,
                "POST",
                &format!("/v1/runs/{run}/robots"),
                None,
                serde_json::to_vec(&b).unwrap(),
            )
            .await;
            assert_eq!(s, StatusCode::CREATED, "{v}");
            tokens.insert(r.id.clone(), v["token"].as_str().unwrap().to_string());
        }
        let started = Instant::now();
        for chunk in log.records.chunks(200) {
            for (robot, token) in &tokens {
                let mine: Vec<_> = chunk.iter().filter(|r| &r.robot == robot).collect();
                if !mine.is_empty() {
                    let (s, v) = call(
                        &router,
                        "POST",
                        &format!("/v1/runs/{run}/observations"),
                        Some(token),
                        serde_json::to_vec(&mine).unwrap(),
                    )
                    .await;
                    assert_eq!(s, StatusCode::OK, "{v}");
                }
            }
        }
        loop {
            let (_, v) = call(
                &router,
                "GET",
                &format!("/v1/runs/{run}/state"),
                None,
                vec![],
            )
            .await;
            if v["applied"].as_u64().unwrap_or(0) as usize == n {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        (run, started.elapsed().as_secs_f64())
    });
    rt.shutdown_background();
    println!(
        "{n} records, {particles} particles, snapshot every {every} records; applied in {post_s:.1} s"
    );

    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let store = open(&url, dir.path()).await;
        let latest = store.latest_snapshot(&run).await.unwrap().unwrap();
        let replayed = n as i64 - latest.applied;
        let state = AppState::new(store.clone(), cfg.clone());
        let t = Instant::now();
        let recovered = fleetslam_server::recovery::recover(&state).await.unwrap();
        let load_ms = t.elapsed().as_secs_f64() * 1e3;
        assert_eq!(recovered, 1);
        // The recovered run re-applies the records after its snapshot.
        let router = app(state);
        loop {
            let (_, v) = call(&router, "GET", &format!("/v1/runs/{run}/state"), None, vec![]).await;
            if v["applied"].as_u64().unwrap_or(0) as usize == n {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let total_ms = t.elapsed().as_secs_f64() * 1e3;
        println!(
            "recovery: {load_ms:.0} ms to load the snapshot and {n} stored records; {total_ms:.0} ms until the {replayed} records after the snapshot were applied again (they wait for the robots or the {} ms reorder window)",
            cfg.coordinator.reorder_window.as_millis()
        );
        // The worst case: a crash just before a snapshot replays `snapshot_every` records.
        let index = store.snapshot_index(&run).await.unwrap();
        if index.len() >= 3 {
            let (a0, _) = index[index.len() - 3];
            let (a1, t1) = index[index.len() - 2];
            let t = Instant::now();
            let s = fleetslam_server::history::state_at(&store, &run, "active", t1.next_down(), 10, false)
                .await
                .unwrap();
            println!(
                "replay from a snapshot: {} records in {:.0} ms (from snapshot {a0} to just before snapshot {a1})",
                s.state.applied as i64 - a0,
                t.elapsed().as_secs_f64() * 1e3
            );
        }
        let t = Instant::now();
        let snap = RunSnapshot::decode(&latest.data).unwrap();
        let decode_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let updater = fleetslam_server::history::updater_for(&store, &snap.filter.slam.config)
            .await
            .unwrap();
        let filter =
            fleetslam_server::history::restore_filter(snap.filter.clone(), updater).unwrap();
        let restore_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let captured = filter.snapshot();
        let capture_ms = t.elapsed().as_secs_f64() * 1e3;
        drop(captured);
        let t = Instant::now();
        let bytes = snap.encode().unwrap();
        let encode_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        store
            .put_snapshot(&run, &NewSnapshot { applied: latest.applied, t: latest.t, data: bytes.clone() })
            .await
            .unwrap();
        let put_ms = t.elapsed().as_secs_f64() * 1e3;
        println!(
            "snapshot: {:.1} MB; capture {capture_ms:.1} ms (on the coordinator), encode {encode_ms:.0} ms and store {put_ms:.0} ms (on the snapshot writer); decode {decode_ms:.0} ms, restore {restore_ms:.1} ms",
            bytes.len() as f64 / 1e6
        );
    });
}
