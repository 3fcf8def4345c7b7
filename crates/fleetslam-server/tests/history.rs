//! Run history through the API: the state at a chosen time, timeline, export, ground truth
//! and evaluation, re-run, deletion, OpenAPI and metrics, and recovery after the server's
//! runtime is torn down in the middle of a run.

use fleetslam_core::config::FilterConfig;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::Log;
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_store::Store;
use serde_json::{Value, json};
use std::io::Read;

mod common;
use axum::http::StatusCode;
use common::{Harness, harness, setup, sim_log};

/// Snapshots every `snapshot_every` records, the filter's work never bringing one sooner.
fn config(snapshot_every: u64) -> ApiConfig {
    let mut c = ApiConfig::default();
    c.coordinator.snapshot_every = snapshot_every;
    c.coordinator.snapshot_every_work = std::time::Duration::MAX;
    c
}

/// Posts `records` (sorted) in chunks, each robot's part of a chunk with its token.
async fn post(
    h: &Harness,
    run: &str,
    tokens: &[(String, String)],
    records: &[fleetslam_core::log::Record],
) {
    for chunk in records.chunks(40) {
        for (robot, token) in tokens {
            let mine: Vec<_> = chunk.iter().filter(|r| &r.robot == robot).collect();
            if mine.is_empty() {
                continue;
            }
            let (s, v) = h
                .call(
                    "POST",
                    &format!("/v1/runs/{run}/observations"),
                    Some(token),
                    "application/json",
                    serde_json::to_vec(&mine).unwrap(),
                )
                .await;
            assert_eq!(s, StatusCode::OK, "{v}");
        }
    }
}

fn offline(log: &Log, particles: usize, seed: u64) -> (FastSlam, fleetslam_data::run::RunOutput) {
    let mut cfg = FilterConfig::from_header(&log.header);
    cfg.particles = particles;
    cfg.seed = seed;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    (slam, out)
}

/// The robots' poses and the landmarks of a state, for exact comparison.
fn essence(state: &Value) -> Value {
    let robots: Vec<Value> = state["robots"]
        .as_array()
        .unwrap_or_else(|| panic!("not a state: {state}"))
        .iter()
        .map(|r| json!([r["id"], r["best"], r["mean"]]))
        .collect();
    let landmarks: Vec<Value> = state["landmarks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| json!([l["id"], l["mean"], l["cov"]]))
        .collect();
    json!({"robots": robots, "landmarks": landmarks})
}

fn essence_of(slam: &FastSlam) -> Value {
    let est = slam.estimate();
    let robots: Vec<Value> = est
        .robots
        .iter()
        .map(|r| json!([r.id, r.best, r.mean]))
        .collect();
    let landmarks: Vec<Value> = est
        .landmarks
        .iter()
        .map(|l| json!([l.id, l.gaussian.mean, l.gaussian.cov]))
        .collect();
    json!({"robots": robots, "landmarks": landmarks})
}

fn trajectories_of(out: &fleetslam_data::run::RunOutput) -> Value {
    out.estimate
        .trajectories
        .iter()
        .map(|(r, pts)| {
            let v: Vec<[f64; 4]> = pts
                .iter()
                .map(|p| [p.t, p.pose.x, p.pose.y, p.pose.theta])
                .collect();
            (r.clone(), json!(v))
        })
        .collect::<serde_json::Map<_, _>>()
        .into()
}

/// A run ended with records the filter has not applied yet (here all of them: the merger
/// holds them for a robot that never posts, within a long reorder window) still stores a
/// snapshot every `snapshot_every` records while its end works the backlog off.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ending_with_a_backlog_keeps_the_snapshot_spacing() {
    let applied = end_with_a_backlog(config(40)).await;
    let n = *applied.last().unwrap();
    let mut expected: Vec<u64> = (1..=n / 40).map(|k| 40 * k).collect();
    if !n.is_multiple_of(40) {
        expected.push(n);
    }
    assert!(n > 120, "{n} records");
    assert_eq!(applied, expected);
}

/// A snapshot falls due once the filter has stepped for `snapshot_every_work`, before
/// `snapshot_every` records: with 1 ns, after every record (each step takes longer), the
/// thread stepping the backlog coming back for it after each.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_filter_work_brings_a_snapshot_due() {
    let mut cfg = config(1_000_000);
    cfg.coordinator.snapshot_every_work = std::time::Duration::from_nanos(1);
    let applied = end_with_a_backlog(cfg).await;
    let n = *applied.last().unwrap();
    assert!(n > 120, "{n} records");
    assert_eq!(applied, (1..=n).collect::<Vec<_>>());
}

/// Posts a simulated run's records but one robot's (so the merger holds them all), ends the
/// run and returns the `applied` count of each of its stored snapshots.
async fn end_with_a_backlog(mut cfg: ApiConfig) -> Vec<u64> {
    let log = sim_log(3, 21.0);
    cfg.coordinator.reorder_window = std::time::Duration::from_secs(600);
    let h = harness(cfg).await;
    let (run, tokens) = setup(&h, &log, json!({"particles": 20, "seed": 3})).await;
    // Robots 1 and 2 post everything; robot 3 nothing, so nothing is safe to apply.
    let silent = &tokens[2].0;
    let posted: Vec<_> = log
        .records
        .iter()
        .filter(|r| &r.robot != silent)
        .cloned()
        .collect();
    post(&h, &run, &tokens[..2], &posted).await;
    let (s, _) = h
        .json("POST", &format!("/v1/runs/{run}/end"), None, json!({}))
        .await;
    assert_eq!(s, StatusCode::NO_CONTENT);
    let (s, tl) = h.get(&format!("/v1/runs/{run}/timeline")).await;
    assert_eq!(s, StatusCode::OK, "{tl}");
    let applied: Vec<u64> = tl["snapshots"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["applied"].as_u64().unwrap())
        .collect();
    assert_eq!(applied.last(), Some(&(posted.len() as u64)), "{tl}");
    applied
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scrub_export_truth_rerun_and_delete() {
    let log = sim_log(3, 20.0);
    let h = harness(config(40)).await;
    let (run, tokens) = setup(&h, &log, json!({"particles": 40, "seed": 3})).await;
    post(&h, &run, &tokens, &log.records).await;
    // Not deletable while active.
    let (s, v) = h
        .call(
            "DELETE",
            &format!("/v1/runs/{run}"),
            None,
            "application/json",
            vec![],
        )
        .await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    let (s, _) = h
        .json("POST", &format!("/v1/runs/{run}/end"), None, json!({}))
        .await;
    assert_eq!(s, StatusCode::NO_CONTENT);

    // The state at a chosen time equals the offline filter after the records up to then.
    let (s, tl) = h.get(&format!("/v1/runs/{run}/timeline")).await;
    assert_eq!(s, StatusCode::OK, "{tl}");
    let (t0, t1) = (
        tl["t_start"].as_f64().unwrap(),
        tl["t_end"].as_f64().unwrap(),
    );
    assert!(t1 > t0 + 10.0, "{tl}");
    assert!(tl["snapshots"].as_array().unwrap().len() >= 3, "{tl}");
    for frac in [0.3, 0.77] {
        let t = t0 + frac * (t1 - t0);
        let (s, st) = h.get(&format!("/v1/runs/{run}/state?t={t}")).await;
        assert_eq!(s, StatusCode::OK, "{st}");
        assert_eq!(st["t"].as_f64(), Some(t));
        let mut cut = log.clone();
        cut.records.retain(|r| r.t <= t);
        let (slam, _) = offline(&cut, 40, 3);
        assert_eq!(essence(&st), essence_of(&slam), "state at t={t}");
        assert_eq!(st["applied"].as_u64().unwrap() as usize, cut.records.len());
    }
    let (s, v) = h.get(&format!("/v1/runs/{run}/state?t=-5")).await;
    assert_eq!(
        s,
        StatusCode::OK,
        "before the first record: the start state {v}"
    );
    let (s, v) = h.get(&format!("/v1/runs/{run}/state?t=abc")).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");

    // Export: the zip holds the files `fleetslam run` writes and the log it reads.
    let (slam, out) = offline(&log, 40, 3);
    let (s, v) = h.get(&format!("/v1/runs/{run}/export?format=pdf")).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    let resp = h.raw("GET", &format!("/v1/runs/{run}/export")).await;
    assert_eq!(resp.0, StatusCode::OK);
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(resp.1)).unwrap();
    let mut files = std::collections::BTreeMap::new();
    for i in 0..zip.len() {
        let mut f = zip.by_index(i).unwrap();
        let mut text = String::new();
        f.read_to_string(&mut text).unwrap();
        files.insert(f.name().to_string(), text);
    }
    let dir = tempfile::tempdir().unwrap();
    out.write(dir.path()).unwrap();
    for r in &log.header.robots {
        let name = format!("trajectory_{}.tum", r.id);
        let want = std::fs::read_to_string(dir.path().join(&name)).unwrap();
        assert_eq!(files[&name], want, "{name}");
    }
    assert_eq!(
        files["landmarks.csv"],
        std::fs::read_to_string(dir.path().join("landmarks.csv")).unwrap()
    );
    let exported = Log::read(std::io::Cursor::new(files["log.ndjson"].as_bytes())).unwrap();
    assert_eq!(exported.records.len(), log.records.len());
    let (again, _) = offline(&exported, 40, 3);
    assert_eq!(
        essence_of(&again),
        essence_of(&slam),
        "the exported log runs the same"
    );
    let metrics: Value = serde_json::from_str(&files["metrics.json"]).unwrap();
    assert_eq!(
        metrics["applied"].as_u64().unwrap() as usize,
        log.records.len()
    );
    // The step time per particle and record, and per particle and observation: the mean
    // step time spread over the particles, and over the log's observations.
    let per = |k: &str| metrics[k].as_f64().unwrap();
    let observations: usize = log.records.iter().map(|r| r.landmarks.len()).sum();
    let per_record = per("ns_per_particle_record");
    assert!(
        (per_record - per("step_ms_mean") * 1e6 / per("particles")).abs() <= 1e-6 * per_record,
        "{metrics}"
    );
    let per_obs = per("ns_per_particle_observation");
    assert!(
        (per_obs * observations as f64 - per_record * log.records.len() as f64).abs()
            <= 1e-6 * per_obs * observations as f64,
        "{metrics}"
    );

    // Ground truth and evaluation.
    let (s, _) = h.get(&format!("/v1/runs/{run}/evaluation")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    let truth: serde_json::Map<String, Value> = log
        .header
        .robots
        .iter()
        .map(|r| {
            let pts: Vec<[f64; 4]> = out.estimate.trajectories[&r.id]
                .iter()
                .map(|p| [p.t, p.pose.x + 0.1, p.pose.y, p.pose.theta])
                .collect();
            (r.id.clone(), json!(pts))
        })
        .collect();
    let (s, v) = h
        .json(
            "PUT",
            &format!("/v1/runs/{run}/truth"),
            None,
            json!({"robots": truth, "landmarks": []}),
        )
        .await;
    assert_eq!(s, StatusCode::NO_CONTENT, "{v}");
    let (s, v) = h
        .json(
            "PUT",
            &format!("/v1/runs/{run}/truth"),
            None,
            json!({"robots": {"1": [[0, 1, 2]]}}),
        )
        .await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    let (s, ev) = h.get(&format!("/v1/runs/{run}/evaluation")).await;
    assert_eq!(s, StatusCode::OK, "{ev}");
    let ate = ev["team"]["ate_rmse"].as_f64().unwrap();
    assert!((ate - 0.1).abs() < 1e-6, "a truth shifted 0.1 m: {ev}");

    // Re-run with another seed: a new run that ends by itself and equals the offline run
    // with that seed.
    let (s, v) = h
        .json(
            "POST",
            &format!("/v1/runs/{run}/rerun"),
            None,
            json!({"config": {"seed": 4}}),
        )
        .await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let rerun = v["id"].as_str().unwrap().to_string();
    let mut status = Value::Null;
    for _ in 0..500 {
        let (_, v) = h.get(&format!("/v1/runs/{rerun}")).await;
        status = v["run"]["status"].clone();
        if status != "active" {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_eq!(status, "ended");
    let (_, st) = h.get(&format!("/v1/runs/{rerun}/state")).await;
    let (seed4, _) = offline(&log, 40, 4);
    assert_eq!(essence(&st), essence_of(&seed4));
    assert_ne!(essence_of(&seed4), essence_of(&slam));
    let (s, _) = h.get(&format!("/v1/runs/{rerun}/truth")).await;
    assert_eq!(s, StatusCode::OK, "the truth goes with the re-run");
    let (s, v) = h
        .json(
            "POST",
            &format!("/v1/runs/{run}/rerun"),
            None,
            json!({"config": {"particles": 0}}),
        )
        .await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert!(v["message"].as_str().unwrap().contains("particles"), "{v}");

    // The list shows both with summaries.
    let (_, list) = h.get("/v1/runs?status=ended").await;
    assert_eq!(list["total"], 2, "{list}");
    let first = &list["runs"][0]["summary"];
    assert_eq!(
        first["landmarks"].as_u64().unwrap() as usize,
        st["landmarks"].as_array().unwrap().len()
    );
    assert_eq!(first["updater"], "ekf", "{first}");

    // Retention.
    let (s, _) = h.raw("DELETE", &format!("/v1/runs/{rerun}")).await;
    assert_eq!(s, StatusCode::NO_CONTENT);
    let (s, _) = h.get(&format!("/v1/runs/{rerun}/state")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert_eq!(h.store.record_count(&rerun).await.unwrap(), 0);
    let (s, _) = h.raw("DELETE", &format!("/v1/runs/{rerun}")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
}

#[tokio::test]
async fn openapi_and_metrics() {
    let h = harness(ApiConfig::default()).await;
    let (s, doc) = h.get("/v1/openapi.json").await;
    assert_eq!(s, StatusCode::OK);
    for path in [
        "/v1/runs",
        "/v1/runs/{run}/observations",
        "/v1/runs/{run}/state",
        "/v1/runs/{run}/export",
        "/metrics",
    ] {
        assert!(
            doc["paths"].get(path).is_some(),
            "{path} missing from {doc}"
        );
    }
    assert!(doc["components"]["schemas"].get("RunState").is_some());
    let log = sim_log(1, 2.0);
    let (run, _) = setup(&h, &log, json!({"particles": 7})).await;
    let (s, text) = h.get("/metrics").await;
    assert_eq!(s, StatusCode::OK);
    let text = text.as_str().unwrap();
    assert!(text.contains("fleetslam_runs_active 1"), "{text}");
    assert!(
        text.contains(&format!("fleetslam_run_particles{{run=\"{run}\"}} 7")),
        "{text}"
    );
    assert!(
        text.contains(
            "fleetslam_http_requests_total{method=\"POST\",route=\"/v1/runs\",status=\"201\"} 1"
        ),
        "{text}"
    );
}

/// Starts the API on `dir`'s store in its own runtime, runs `f`, then drops the runtime
/// without ending anything: tasks stop where they are, as in a crash.
fn in_runtime<T>(dir: &std::path::Path, cfg: ApiConfig, f: impl AsyncFnOnce(&Harness) -> T) -> T {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let out = rt.block_on(async {
        let store = Store::open_default(dir).await.unwrap();
        let state = AppState::new(store.clone(), cfg);
        fleetslam_server::recovery::recover(&state).await.unwrap();
        let h = Harness {
            router: app(state),
            store,
            dir: tempfile::tempdir().unwrap(),
        };
        f(&h).await
    });
    rt.shutdown_background();
    out
}

#[test]
fn a_run_recovers_after_a_crash_bit_for_bit() {
    let log = sim_log(3, 20.0);
    let dir = tempfile::tempdir().unwrap();
    let n = log.records.len();
    // First life: the first 60% posted, then the runtime dies mid-run.
    let (run, tokens) = in_runtime(dir.path(), config(25), async |h| {
        let (run, tokens) = setup(h, &log, json!({"particles": 30, "seed": 9})).await;
        post(h, &run, &tokens, &log.records[..n * 6 / 10]).await;
        h.state_when(&run, |v| v["applied"].as_u64().unwrap_or(0) > 50)
            .await;
        (run, tokens)
    });
    // Second life: recovered from its snapshot and log; the client re-sends from 40% on
    // (repeats are acknowledged again, applied once), then the rest.
    let (end_state, traj) = in_runtime(dir.path(), config(25), async |h| {
        let (s, v) = h.get(&format!("/v1/runs/{run}")).await;
        assert_eq!(s, StatusCode::OK);
        assert_eq!(v["run"]["status"], "active");
        post(h, &run, &tokens, &log.records[n * 4 / 10..]).await;
        let (s, v) = h
            .json("POST", &format!("/v1/runs/{run}/end"), None, json!({}))
            .await;
        assert_eq!(s, StatusCode::NO_CONTENT, "{v}");
        assert_eq!(h.store.record_count(&run).await.unwrap() as usize, n);
        let (_, st) = h.get(&format!("/v1/runs/{run}/state")).await;
        let (_, traj) = h.get(&format!("/v1/runs/{run}/trajectories")).await;
        (st, traj)
    });
    let (slam, out) = offline(&log, 30, 9);
    assert_eq!(end_state["applied"].as_u64().unwrap() as usize, n);
    assert_eq!(essence(&end_state), essence_of(&slam));
    assert_eq!(traj["robots"], trajectories_of(&out));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_at_an_unknown_pose_is_localized_then_maps_as_offline() {
    let mut log = sim_log(3, 40.0);
    let h = harness(ApiConfig::default()).await;
    let (s, v) = h
        .json(
            "POST",
            "/v1/runs",
            None,
            json!({"header": log.header, "config": {"particles": 40, "seed": 2}}),
        )
        .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let run = v["id"].as_str().unwrap().to_string();
    let mut tokens = Vec::new();
    for r in &mut log.header.robots {
        if r.id == "3" {
            r.start = None;
        }
        let (s, v) = h
            .json(
                "POST",
                &format!("/v1/runs/{run}/robots"),
                None,
                json!({"id": r.id, "start": r.start, "t0": r.t0}),
            )
            .await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        let want = if r.start.is_some() {
            "mapping"
        } else {
            "localizing"
        };
        assert_eq!(v["mode"], want);
        tokens.push((r.id.clone(), v["token"].as_str().unwrap().to_string()));
    }
    let st = h
        .state_when(&run, |v| {
            v["robots"].as_array().is_some_and(|r| r.len() == 3)
        })
        .await;
    assert_eq!(st["robots"][2]["mode"], "localizing", "{st}");
    assert!(
        st["robots"][2]["best"].is_null(),
        "no pose before it is localized"
    );
    post(&h, &run, &tokens, &log.records).await;
    let (s, _) = h
        .json("POST", &format!("/v1/runs/{run}/end"), None, json!({}))
        .await;
    assert_eq!(s, StatusCode::NO_CONTENT);
    let (_, st) = h.get(&format!("/v1/runs/{run}/state")).await;
    assert_eq!(st["robots"][2]["mode"], "mapping", "robot 3 joined: {st}");

    // Offline, the same log with robot 3 unknown: the same filter, bit for bit.
    let mut cfg = FilterConfig::from_header(&log.header);
    cfg.particles = 40;
    cfg.seed = 2;
    let mut joining = fleetslam_localize::LateJoinSlam::new(cfg, Default::default()).unwrap();
    fleetslam_data::run::run_log_joining(
        &mut joining,
        &log,
        TrajectoryEstimate::Mean,
        &Default::default(),
        |_, _| {},
    )
    .unwrap();
    assert_eq!(essence(&st), essence_of(joining.slam()));
}
