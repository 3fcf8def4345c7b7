//! How a run's state is published (issue 13): the coordinator publishes a copy of the filter
//! and builds no state that nobody reads; a state built later, on the reader's side, is the
//! state of the filter as it was when published, equal to one built eagerly there; and a
//! websocket listener receives the run's final state.

use fleetslam_core::log::{Record, record_order};
use fleetslam_localize::LateJoinSlam;
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_server::coordinator::{self, CoordinatorConfig};
use fleetslam_server::history;
use fleetslam_store::Store;
use futures::StreamExt;
use serde_json::{Value, json};
use std::time::Duration;

mod common;
use common::{register_header_robots, sim_log, store_with_run};

#[tokio::test]
async fn a_state_published_lazily_equals_the_eager_one_and_is_built_only_when_read() {
    let log = sim_log(2, 12.0);
    let dir = tempfile::tempdir().unwrap();
    let (store, cfg) = store_with_run(dir.path(), "lazy", &log, 40, 3).await;
    let filter = LateJoinSlam::new(cfg, Default::default()).unwrap();
    // The same filter, stepped here by hand: the eager reference.
    let mut twin = filter.clone();
    let coord = CoordinatorConfig {
        // A publication at every chance, and the merge never waits for a silent robot.
        state_rate_hz: 1000.0,
        reorder_window: Duration::from_secs(60),
        ..CoordinatorConfig::default()
    };
    let particle_sample = coord.particle_sample;
    let handle = coordinator::spawn(
        "lazy".into(),
        filter,
        store.clone(),
        coord,
        None,
        None,
        coordinator::Clock::Wall,
    );
    for r in &log.header.robots {
        twin.add_robot(&r.id, &r.start.unwrap(), r.t0.unwrap_or(0.0))
            .unwrap();
    }
    register_header_robots(&handle, &log).await;
    // Watches the publications: each is unbuilt until read here. The first whose filter has
    // applied some records but not all is kept.
    let mut state_rx = handle.state.clone();
    state_rx.borrow_and_update();
    let n = log.records.len() as u64;
    let watcher = tokio::spawn(async move {
        loop {
            state_rx.changed().await.unwrap();
            let p = state_rx.borrow_and_update().clone();
            assert!(!p.is_built(), "a state nobody read was built");
            let probe = p.clone();
            let s = tokio::task::spawn_blocking(move || probe.get())
                .await
                .unwrap();
            if s.applied > 0 && s.applied < n {
                return (p, s);
            }
        }
    });
    for chunk in log.records.chunks(10) {
        let acks = handle.ingest(chunk.to_vec()).await.unwrap();
        assert!(acks.iter().all(|a| a.status == "stored"), "{acks:?}");
    }
    let (p, lazy) = tokio::time::timeout(Duration::from_secs(30), watcher)
        .await
        .expect("a state published while the records were applied")
        .unwrap();
    assert!(p.is_built());
    // Building it again gives the same state, once.
    assert!(std::sync::Arc::ptr_eq(&p.get(), &lazy));
    handle.end().await.unwrap();
    let end = handle.current_state();
    assert_eq!(end.status, "ended");
    assert_eq!(end.applied as usize, log.records.len());
    assert!(
        lazy.applied < end.applied,
        "the run went on after the state was published"
    );

    // The eager state of the filter after the same records, in the merge's order.
    let mut order: Vec<&Record> = log.records.iter().collect();
    order.sort_by(|a, b| record_order(a, b));
    for r in &order[..lazy.applied as usize] {
        twin.step(r).unwrap();
    }
    let eager = history::base_state(
        "lazy",
        "active",
        &twin,
        lazy.applied,
        lazy.t,
        particle_sample,
    );
    let figures = |s: &coordinator::RunState| {
        json!({
            "applied": s.applied, "t": s.t, "ess": s.ess, "particles": s.particles,
            "resamples": s.resamples, "landmarks": s.landmarks,
            "particle_sample": s.particle_sample,
            "robots": s.robots.iter().map(|r| json!({
                "id": r.id, "mode": r.mode, "best": r.best, "mean": r.mean, "cov": r.cov,
            })).collect::<Vec<Value>>(),
        })
    };
    assert_eq!(figures(&lazy), figures(&eager));
    // The coordinator's own figures are laid over it.
    for r in &lazy.robots {
        assert!(r.records > 0 && r.last_seq.is_some(), "{r:?}");
    }

    // The final state (published lazily, read here) is the stored result's (built eagerly
    // from the same filter), but for the step time, measured since the last publication.
    let stored: Value = serde_json::from_str(
        &store
            .get_artifact("lazy", history::RESULT)
            .await
            .unwrap()
            .unwrap(),
    )
    .unwrap();
    let mut read = serde_json::to_value(&*end).unwrap();
    let mut result = stored["state"].clone();
    read.as_object_mut().unwrap().remove("step_ms");
    result.as_object_mut().unwrap().remove("step_ms");
    assert_eq!(read, result);
}

#[tokio::test]
async fn a_websocket_listener_receives_every_state_change_up_to_the_final_one() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open_default(dir.path()).await.unwrap();
    let router = app(AppState::new(store, ApiConfig::default()));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let server = tokio::spawn(async move { axum::serve(listener, router).await.unwrap() });
    let base = format!("http://{addr}");
    let c = reqwest::Client::new();
    let log = sim_log(2, 8.0);
    let n = log.records.len() as u64;
    let (run, tokens) =
        common::setup_over_http(&c, &base, &log, json!({"particles": 30, "seed": 2})).await;
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/v1/runs/{run}/live"))
        .await
        .unwrap();
    let listen = tokio::spawn(async move {
        let mut applied = Vec::new();
        while let Ok(Some(Ok(msg))) = tokio::time::timeout(Duration::from_secs(10), ws.next()).await
        {
            let Ok(text) = msg.into_text() else { continue };
            let v: Value = serde_json::from_str(&text).unwrap();
            if v["type"] == "state" {
                applied.push(v["state"]["applied"].as_u64().unwrap());
                if v["state"]["status"] == "ended" {
                    break;
                }
            }
        }
        applied
    });
    for (robot, token) in &tokens {
        let mine: Vec<&Record> = log.records.iter().filter(|r| &r.robot == robot).collect();
        for chunk in mine.chunks(15) {
            let resp = c
                .post(format!("{base}/v1/runs/{run}/observations"))
                .bearer_auth(token)
                .json(&chunk)
                .send()
                .await
                .unwrap();
            assert!(resp.status().is_success(), "{}", resp.status());
        }
    }
    let resp = c
        .post(format!("{base}/v1/runs/{run}/end"))
        .send()
        .await
        .unwrap();
    assert!(resp.status().is_success(), "{}", resp.status());
    let applied = listen.await.unwrap();
    // The first state (before any record), states as records are applied, and the final
    // state (sent after the coordinator stopped) with every record.
    assert_eq!(applied.first(), Some(&0), "{applied:?}");
    assert_eq!(applied.last(), Some(&n), "the final state: {applied:?}");
    assert!(
        applied.windows(2).all(|w| w[0] <= w[1]),
        "states in order: {applied:?}"
    );
    server.abort();
}

#[tokio::test]
async fn snapshots_taken_while_released_records_wait_for_the_filter_cover_only_applied_ones() {
    //! The merger releases records before the filter steps through them (the filter works
    //! in slices of one publication interval); a snapshot taken in between must record the
    //! position of the filter, not the merger's, or a recovery would skip the waiting ones.
    let log = sim_log(2, 12.0);
    let dir = tempfile::tempdir().unwrap();
    let (store, cfg) = store_with_run(dir.path(), "snap", &log, 60, 4).await;
    let filter = LateJoinSlam::new(cfg, Default::default()).unwrap();
    let coord = CoordinatorConfig {
        // Slices of 50 us (a step or two): most leave released records waiting.
        state_rate_hz: 20_000.0,
        reorder_window: Duration::from_secs(60),
        snapshot_every: 3,
        ..CoordinatorConfig::default()
    };
    let handle = coordinator::spawn(
        "snap".into(),
        filter,
        store.clone(),
        coord,
        None,
        None,
        coordinator::Clock::Wall,
    );
    register_header_robots(&handle, &log).await;
    // One robot's records first, then the other's: the merge releases them in large sets.
    for r in &log.header.robots {
        let mine: Vec<Record> = log
            .records
            .iter()
            .filter(|x| x.robot == r.id)
            .cloned()
            .collect();
        for chunk in mine.chunks(25) {
            let acks = handle.ingest(chunk.to_vec()).await.unwrap();
            assert!(acks.iter().all(|a| a.status == "stored"), "{acks:?}");
        }
    }
    // The filter works the backlog off in slices (the end would apply it in one go).
    for _ in 0..500 {
        if handle.current_state().applied as usize > log.records.len() / 2 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    handle.end().await.unwrap();
    assert_eq!(handle.current_state().applied as usize, log.records.len());
    let index = store.snapshot_index("snap").await.unwrap();
    assert!(index.len() > 10, "{} snapshots", index.len());
    for (applied, _) in index {
        let row = store
            .snapshot_at_or_before_applied("snap", applied)
            .await
            .unwrap()
            .unwrap();
        let snap = history::RunSnapshot::decode(&row.data).unwrap();
        // Stored as CBOR; a snapshot stored as JSON (before session 24) reads back the same.
        assert_ne!(row.data.first(), Some(&b'{'), "a CBOR snapshot");
        let json = serde_json::to_vec(&snap).unwrap();
        let from_json = history::RunSnapshot::decode(&json).unwrap();
        assert_eq!(
            serde_json::to_value(&from_json).unwrap(),
            serde_json::to_value(&snap).unwrap()
        );
        assert_eq!(
            from_json.encode().unwrap(),
            row.data,
            "the same bytes again"
        );
        let covered = match snap.last_key() {
            None => 0,
            Some(last) => log
                .records
                .iter()
                .filter(|r| fleetslam_server::merge::OrderKey::of(r) <= last)
                .count(),
        };
        assert_eq!(
            covered as u64, snap.applied,
            "the snapshot at {applied} records says it holds every record up to {:?}",
            snap.last
        );
    }
}
