//! Poison isolation and failed runs (issue 11): a record that makes the filter panic is
//! quarantined live and the run goes on; a restart with quarantined and unreadable records
//! in the store recovers and continues; a run whose recovery fails is `failed` and can
//! still be read, ended (a clear answer) and deleted. Every result is compared bit for bit
//! with an offline `run_log` of the log without the quarantined records.

use axum::http::StatusCode;
use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::{Log, Record};
use fleetslam_core::pose::Pose2;
use fleetslam_core::updater::{
    LandmarkGaussian, LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput,
};
use fleetslam_data::run::{RunOutput, TrajectoryEstimate, run_log};
use fleetslam_server::app::{ApiConfig, AppState, app};
use fleetslam_server::coordinator::{self, CoordinatorConfig, Event};
use fleetslam_store::{NewObservation, NewRobot, Store};
use serde_json::{Value, json};
use std::sync::Arc;

mod common;
use common::{Harness, register_header_robots, setup, sim_log, store_with_run};

/// The EKF, except that it panics on a measurement whose first component is `magic`: a
/// deterministic poison record, through the coordinator's public `spawn`.
#[derive(Debug)]
struct PanicOn {
    inner: EkfUpdater,
    magic: f64,
}

impl LandmarkUpdater for PanicOn {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn kind(&self) -> fleetslam_core::sensor::LandmarkKind {
        self.inner.kind()
    }
    fn initialize(&self, pose: &Pose2, z: &[f64; 3]) -> LandmarkGaussian {
        assert!(z[0] != self.magic, "poison measurement {}", z[0]);
        self.inner.initialize(pose, z)
    }
    fn update_batch(
        &self,
        needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
    ) {
        assert!(
            inputs.iter().all(|i| i.z[0] != self.magic),
            "poison measurement in a batch"
        );
        self.inner.update_batch(needs, inputs, outputs)
    }
}

const MAGIC: f64 = 4.321_234_567;

fn offline(log: &Log, particles: usize, seed: u64) -> (FastSlam, RunOutput) {
    let mut cfg = FilterConfig::from_header(&log.header);
    cfg.particles = particles;
    cfg.seed = seed;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    (slam, out)
}

fn without(log: &Log, drop: &[(&str, u64)]) -> Log {
    let mut cut = log.clone();
    cut.records
        .retain(|r| !drop.contains(&(r.robot.as_str(), r.seq)));
    assert_eq!(cut.records.len(), log.records.len() - drop.len());
    cut
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

fn trajectories_of(out: &RunOutput) -> Value {
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

/// The index of the first record at or after `from` of `robot` that observes landmarks.
fn observing(log: &Log, robot: &str, from: usize) -> usize {
    (from..log.records.len())
        .find(|&i| log.records[i].robot == robot && !log.records[i].landmarks.is_empty())
        .expect("a record with landmark observations")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_record_is_quarantined_live_and_the_run_goes_on() {
    let log = sim_log(2, 12.0);
    let n = log.records.len();
    let poison_at = observing(&log, "1", n / 2);
    let mut posted = log.records.clone();
    posted[poison_at].landmarks[0].z[0] = MAGIC;
    let poison = (posted[poison_at].robot.clone(), posted[poison_at].seq);

    let dir = tempfile::tempdir().unwrap();
    let (store, cfg) = store_with_run(dir.path(), "p", &log, 30, 6).await;
    let updater = Arc::new(PanicOn {
        inner: EkfUpdater::new(cfg.landmark_kind, &cfg.sensor_noise),
        magic: MAGIC,
    });
    let slam = FastSlam::with_updater(cfg.clone(), updater).unwrap();
    let filter = fleetslam_localize::LateJoinSlam::from_slam(slam, Default::default()).unwrap();
    let coord = CoordinatorConfig {
        snapshot_every: 25,
        ..CoordinatorConfig::default()
    };
    let handle = coordinator::spawn(
        "p".into(),
        filter,
        store.clone(),
        coord,
        None,
        None,
        coordinator::Clock::Wall,
    );
    let mut events = handle.events.subscribe();
    let seen = tokio::spawn(async move {
        let mut quarantined = Vec::new();
        loop {
            match events.recv().await {
                Ok(Event::RecordQuarantined { robot, seq, reason }) => {
                    quarantined.push((robot, seq, reason))
                }
                Ok(Event::RunEnded) => return quarantined,
                Ok(_) | Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                Err(_) => return quarantined,
            }
        }
    });
    register_header_robots(&handle, &log).await;
    for chunk in posted.chunks(20) {
        let acks = handle.ingest(chunk.to_vec()).await.unwrap();
        assert!(acks.iter().all(|a| a.status == "stored"), "{acks:?}");
    }
    // Everything before the poison record and after it is applied once the merge releases it.
    let mut state = handle.current_state();
    for _ in 0..500 {
        state = handle.current_state();
        if state.applied as usize >= n - 1 - 20 {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
    assert!(
        state.applied as usize > poison_at,
        "the run went on past the poison record: {}",
        state.applied
    );
    handle.end().await.unwrap();
    let state = handle.current_state();
    assert_eq!(state.status, "ended");
    assert_eq!(
        state.applied as usize,
        n - 1,
        "every record but the poison one"
    );
    let r1 = state.robots.iter().find(|r| r.id == poison.0).unwrap();
    assert_eq!(r1.quarantined, 1);
    let reason = r1.quarantine_reason.clone().unwrap();
    assert!(
        reason.contains("panicked") && reason.contains("poison"),
        "{reason}"
    );
    let r2 = state.robots.iter().find(|r| r.id != poison.0).unwrap();
    assert_eq!((r2.quarantined, r2.quarantine_reason.as_deref()), (0, None));
    assert_eq!(
        r1.records as usize,
        log.records.iter().filter(|r| r.robot == poison.0).count()
    );

    // The event, and the mark in the store (so that a restart skips it).
    let quarantined = seen.await.unwrap();
    assert_eq!(quarantined.len(), 1, "{quarantined:?}");
    assert_eq!((&quarantined[0].0, quarantined[0].1), (&poison.0, poison.1));
    let stored = fleetslam_server::history::all_records(&store, "p")
        .await
        .unwrap();
    let marked: Vec<_> = stored
        .iter()
        .filter(|o| o.rejected.is_some())
        .map(|o| (o.robot_id.clone(), o.seq as u64))
        .collect();
    assert_eq!(marked, std::slice::from_ref(&poison));

    // Bit for bit the offline run of the log without the poison record, trajectories too.
    let cut = without(&log, &[(poison.0.as_str(), poison.1)]);
    let (slam, out) = offline(&cut, 30, 6);
    assert_eq!(
        essence(&serde_json::to_value(&state).unwrap()),
        essence_of(&slam)
    );
    let result: Value =
        serde_json::from_str(&store.get_artifact("p", "result").await.unwrap().unwrap()).unwrap();
    assert_eq!(result["trajectories"], trajectories_of(&out));

    // Scrubbing skips it too: the state at the end equals the same offline run.
    let at = fleetslam_server::history::state_at(&store, "p", "ended", f64::MAX, 10, true)
        .await
        .unwrap();
    assert_eq!(
        essence(&serde_json::to_value(&at.state).unwrap()),
        essence_of(&slam)
    );
    // Its trajectories, reassembled from the pieces stored with the snapshots.
    assert_eq!(json!(at.trajectories), trajectories_of(&out));
}

/// Starts the API on `dir`'s store in its own runtime (recovering its active runs), runs
/// `f`, then drops the runtime without ending anything, as in a crash.
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

fn config(snapshot_every: u64) -> ApiConfig {
    let mut c = ApiConfig::default();
    c.coordinator.snapshot_every = snapshot_every;
    c
}

/// Posts `records` (sorted) in chunks, each robot's part of a chunk with its token; every
/// record is stored or a duplicate.
async fn post(h: &Harness, run: &str, tokens: &[(String, String)], records: &[Record]) {
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

#[test]
fn a_run_with_quarantined_records_in_the_store_recovers_and_continues() {
    let log = sim_log(3, 20.0);
    let dir = tempfile::tempdir().unwrap();
    let n = log.records.len();
    // Two records the client has not sent yet when the server dies.
    let a = observing(&log, "1", n * 7 / 10);
    let b = observing(&log, "2", n * 8 / 10);
    let (ra, rb) = (log.records[a].clone(), log.records[b].clone());
    let (run, tokens) = in_runtime(dir.path(), config(25), async |h| {
        let (run, tokens) = setup(h, &log, json!({"particles": 30, "seed": 9})).await;
        post(h, &run, &tokens, &log.records[..n * 6 / 10]).await;
        h.state_when(&run, |v| v["applied"].as_u64().unwrap_or(0) > 50)
            .await;
        // While the server runs: a record whose stored body cannot be parsed back (A), and a
        // good record quarantined (B), as a crash right after quarantining it would leave.
        let stored = h
            .store
            .append(
                &run,
                vec![
                    NewObservation {
                        robot_id: ra.robot.clone(),
                        seq: ra.seq as i64,
                        t: ra.t,
                        body: "{\"robot\": \"1\", \"seq\": truncated".into(),
                    },
                    NewObservation {
                        robot_id: rb.robot.clone(),
                        seq: rb.seq as i64,
                        t: rb.t,
                        body: serde_json::to_string(&rb).unwrap(),
                    },
                ],
            )
            .await
            .unwrap();
        assert_eq!(stored.inserted(), 2);
        assert!(
            h.store
                .quarantine(
                    &run,
                    &rb.robot,
                    rb.seq as i64,
                    "the filter panicked on it: test"
                )
                .await
                .unwrap()
        );
        (run, tokens)
    });
    let (end_state, traj, exported) = in_runtime(dir.path(), config(25), async |h| {
        let (s, v) = h.get(&format!("/v1/runs/{run}")).await;
        assert_eq!(s, StatusCode::OK);
        assert_eq!(v["run"]["status"], "active", "{v}");
        // Recovery quarantined the unreadable record instead of failing.
        let rows = fleetslam_server::history::all_records(&h.store, &run)
            .await
            .unwrap();
        let reason_of = |robot: &str, seq: u64| {
            rows.iter()
                .find(|o| o.robot_id == robot && o.seq as u64 == seq)
                .and_then(|o| o.rejected.clone())
        };
        let why = reason_of(&ra.robot, ra.seq).expect("A is quarantined");
        assert!(why.contains("cannot be parsed"), "{why}");
        let st = h
            .state_when(&run, |v| {
                v["robots"].as_array().is_some_and(|r| r.len() == 3)
            })
            .await;
        for (robot, count) in [("1", 1), ("2", 1), ("3", 0)] {
            let r = st["robots"]
                .as_array()
                .unwrap()
                .iter()
                .find(|r| r["id"] == robot)
                .unwrap();
            assert_eq!(r["quarantined"], count, "{r}");
        }
        // The client re-sends from 40% on: A and B are acknowledged as duplicates, never applied.
        post(h, &run, &tokens, &log.records[n * 4 / 10..]).await;
        let (s, v) = h
            .json("POST", &format!("/v1/runs/{run}/end"), None, json!({}))
            .await;
        assert_eq!(s, StatusCode::NO_CONTENT, "{v}");
        assert_eq!(h.store.record_count(&run).await.unwrap() as usize, n);
        let (_, st) = h.get(&format!("/v1/runs/{run}/state")).await;
        let (_, traj) = h.get(&format!("/v1/runs/{run}/trajectories")).await;
        let (s, exported) = h
            .raw("GET", &format!("/v1/runs/{run}/export?format=log"))
            .await;
        assert_eq!(s, StatusCode::OK);
        (st, traj, exported)
    });
    let cut = without(
        &log,
        &[(ra.robot.as_str(), ra.seq), (rb.robot.as_str(), rb.seq)],
    );
    let (slam, out) = offline(&cut, 30, 9);
    assert_eq!(end_state["applied"].as_u64().unwrap() as usize, n - 2);
    assert_eq!(essence(&end_state), essence_of(&slam));
    assert_eq!(traj["robots"], trajectories_of(&out));
    // The exported log leaves them out and runs offline to the same result.
    let exported = Log::read(std::io::Cursor::new(exported)).unwrap();
    assert_eq!(exported.records.len(), n - 2);
    let (again, _) = offline(&exported, 30, 9);
    assert_eq!(essence_of(&again), essence_of(&slam));
}

#[test]
fn a_run_whose_recovery_fails_is_failed_readable_and_deletable() {
    let log = sim_log(2, 10.0);
    let dir = tempfile::tempdir().unwrap();
    let n = log.records.len();
    let run = in_runtime(dir.path(), config(25), async |h| {
        let (run, tokens) = setup(h, &log, json!({"particles": 20, "seed": 2})).await;
        post(h, &run, &tokens, &log.records[..n / 2]).await;
        h.state_when(&run, |v| v["applied"].as_u64().unwrap_or(0) > 20)
            .await;
        // A robot whose stored start pose cannot be read: its run cannot be recovered.
        h.store
            .add_robot(
                &run,
                &NewRobot {
                    robot_id: "broken".into(),
                    start: Some(json!({"mean": "nowhere"})),
                    token_hash: "x".into(),
                    t0: Some(0.0),
                },
            )
            .await
            .unwrap();
        run
    });
    in_runtime(dir.path(), config(25), async |h| {
        let (s, v) = h.get(&format!("/v1/runs/{run}")).await;
        assert_eq!(s, StatusCode::OK);
        assert_eq!(v["run"]["status"], "failed", "{v}");
        let reason = v["run"]["reason"].as_str().unwrap();
        assert!(
            reason.contains("recovery") && reason.contains("start pose"),
            "{reason}"
        );
        let (_, list) = h.get("/v1/runs?status=failed").await;
        assert_eq!(list["total"], 1, "{list}");
        assert_eq!(list["runs"][0]["reason"], reason);

        // Readable: its state (latest snapshot and the records after it), trajectories,
        // export.
        let (s, st) = h.get(&format!("/v1/runs/{run}/state")).await;
        assert_eq!(s, StatusCode::OK, "{st}");
        assert_eq!(st["status"], "failed");
        assert_eq!(st["reason"], reason);
        assert!(st["applied"].as_u64().unwrap() > 20, "{st}");
        let (s, traj) = h.get(&format!("/v1/runs/{run}/trajectories")).await;
        assert_eq!(s, StatusCode::OK, "{traj}");
        assert_eq!(traj["robots"].as_object().unwrap().len(), 2, "{traj}");
        let (s, zip) = h.raw("GET", &format!("/v1/runs/{run}/export")).await;
        assert_eq!(s, StatusCode::OK);
        assert!(zip.starts_with(b"PK"));

        // Ending it answers clearly; posting to it too; deleting it works.
        let (s, v) = h
            .json("POST", &format!("/v1/runs/{run}/end"), None, json!({}))
            .await;
        assert_eq!(s, StatusCode::CONFLICT, "{v}");
        assert_eq!(v["error"], "conflict");
        let msg = v["message"].as_str().unwrap();
        assert!(msg.contains("failed") && msg.contains("DELETE"), "{msg}");
        let (s, v) = h
            .json(
                "POST",
                &format!("/v1/runs/{run}/robots"),
                None,
                json!({"id": "late"}),
            )
            .await;
        assert_eq!(s, StatusCode::CONFLICT, "{v}");
        let (s, _) = h.raw("DELETE", &format!("/v1/runs/{run}")).await;
        assert_eq!(s, StatusCode::NO_CONTENT);
        let (s, _) = h.get(&format!("/v1/runs/{run}")).await;
        assert_eq!(s, StatusCode::NOT_FOUND);
    });
}
