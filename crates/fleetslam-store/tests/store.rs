//! The store's test suite: every test is a function taking a `&Store`, run against SQLite (in
//! a fresh temporary directory) always, and against PostgreSQL (in a fresh database, dropped
//! afterwards) when `FLEETSLAM_TEST_POSTGRES_URL` is set, e.g.
//! `FLEETSLAM_TEST_POSTGRES_URL=postgres://postgres@127.0.0.1:5432/test cargo test -p fleetslam-store`.

use std::collections::{BTreeMap, BTreeSet};
use std::future::Future;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use fleetslam_store::{
    NewModel, NewObservation, NewRobot, NewRun, NewSnapshot, RunFilter, Store, StoreError,
};
use serde_json::json;
use sqlx::Connection;

const PG_ENV: &str = "FLEETSLAM_TEST_POSTGRES_URL";

/// Runs `test` on a store in a fresh SQLite file.
async fn with_sqlite<F, Fut>(test: F)
where
    F: FnOnce(Store) -> Fut,
    Fut: Future<Output = ()> + Send + 'static,
{
    let dir = tempfile::tempdir().expect("temporary directory");
    let store = Store::open_default(dir.path())
        .await
        .expect("open SQLite store");
    assert_eq!(store.backend(), "sqlite");
    test(store.clone()).await;
    store.close().await;
}

/// Runs `test` on a store in a fresh PostgreSQL database, dropped afterwards (also when the
/// test fails); skipped, saying so, when no server is configured.
async fn with_postgres<F, Fut>(test: F)
where
    F: FnOnce(Store) -> Fut,
    Fut: Future<Output = ()> + Send + 'static,
{
    let Ok(url) = std::env::var(PG_ENV) else {
        eprintln!(
            "PostgreSQL skipped: set {PG_ENV} (e.g. postgres://postgres@127.0.0.1:5432/test) to run this test against it"
        );
        return;
    };
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    let name = format!(
        "fleetslam_test_{}_{}_{}",
        std::process::id(),
        nanos,
        COUNTER.fetch_add(1, Ordering::Relaxed)
    );
    let mut admin = sqlx::PgConnection::connect(&url)
        .await
        .expect("connect to the PostgreSQL test server");
    sqlx::query(&format!("CREATE DATABASE \"{name}\""))
        .execute(&mut admin)
        .await
        .expect("create the test database");
    let store = Store::open(&fleetslam_store::admin::with_database(&url, &name))
        .await
        .expect("open PostgreSQL store");
    assert_eq!(store.backend(), "postgres");
    // Run the test in its own task so that the database is dropped even when it panics.
    let outcome = tokio::spawn(test(store.clone())).await;
    store.close().await;
    sqlx::query(&format!("DROP DATABASE IF EXISTS \"{name}\" WITH (FORCE)"))
        .execute(&mut admin)
        .await
        .expect("drop the test database");
    if let Err(e) = outcome {
        std::panic::resume_unwind(e.into_panic());
    }
}

/// Declares each test once per backend.
macro_rules! suite {
    ($($name:ident),* $(,)?) => {
        mod sqlite {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() {
                    super::with_sqlite(|s| async move { super::$name(&s).await }).await;
                }
            )*
        }
        mod postgres {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() {
                    super::with_postgres(|s| async move { super::$name(&s).await }).await;
                }
            )*
        }
    };
}

suite!(
    migrations_from_empty,
    run_crud,
    list_runs_filters_pages_and_counts,
    robots_and_duplicate_conflict,
    append_arrivals_duplicates_and_paging,
    large_appends_span_several_statements,
    append_rejects_bad_input,
    concurrent_appends_group_commit,
    snapshots_latest_and_at_or_before,
    delete_run_removes_everything,
    evaluations_training_and_models,
    artifacts_and_snapshot_index,
    quarantine_marks_records_and_keeps_their_seq,
    records_in_time_reads_only_the_window,
    failed_runs_keep_their_reason,
);

fn new_run(id: &str) -> NewRun {
    NewRun {
        id: id.to_owned(),
        name: Some(format!("run {id}")),
        config: json!({"particles": 100, "seed": 7, "noise": 0.1}),
        header: Some(json!({"fleetslam_log": 1, "landmark_kind": "range_bearing_2d"})),
    }
}

fn robot(id: &str) -> NewRobot {
    NewRobot {
        robot_id: id.to_owned(),
        start: Some(json!({"mean": {"x": 1.0, "y": 2.0, "theta": 0.5}})),
        token_hash: format!("hash-of-{id}"),
        t0: Some(1_248_444_175.103),
    }
}

fn obs(robot: &str, seq: i64) -> NewObservation {
    NewObservation {
        robot_id: robot.to_owned(),
        seq,
        t: 100.0 + seq as f64 * 0.1,
        body: format!(
            r#"{{"robot":"{robot}","seq":{seq},"t":{}}}"#,
            100.0 + seq as f64 * 0.1
        ),
    }
}

async fn migrations_from_empty(store: &Store) {
    // A fresh database has the whole schema and nothing in it.
    assert!(
        store
            .list_runs(&RunFilter::default())
            .await
            .expect("list")
            .is_empty()
    );
    assert!(store.active_runs().await.expect("active").is_empty());
    assert!(store.list_models().await.expect("models").is_empty());
    assert_eq!(store.record_count("nothing").await.expect("count"), 0);
    assert!(store.get_run("nothing").await.expect("get").is_none());
}

async fn run_crud(store: &Store) {
    let created = store.create_run(&new_run("a")).await.expect("create");
    assert_eq!(created.status, "active");
    assert!(created.created_at > 0);
    let got = store.get_run("a").await.expect("get").expect("exists");
    assert_eq!(got, created);
    assert!(matches!(
        store.create_run(&new_run("a")).await,
        Err(StoreError::Conflict(_))
    ));
    assert!(matches!(
        store.create_run(&new_run("")).await,
        Err(StoreError::Invalid(_))
    ));
    assert_eq!(store.active_runs().await.expect("active").len(), 1);

    let summary = json!({"team": {"ate_rmse": 0.217}});
    store
        .set_run_status("a", "ended", Some(&summary))
        .await
        .expect("end");
    let ended = store.get_run("a").await.expect("get").expect("exists");
    assert_eq!(ended.status, "ended");
    assert_eq!(ended.summary, Some(summary.clone()));
    assert!(ended.ended_at.is_some_and(|t| t >= ended.created_at));
    assert!(store.active_runs().await.expect("active").is_empty());
    // Without a summary the stored one is kept.
    store
        .set_run_status("a", "failed", None)
        .await
        .expect("fail");
    let failed = store.get_run("a").await.expect("get").expect("exists");
    assert_eq!(
        (failed.status.as_str(), failed.summary),
        ("failed", Some(summary))
    );
    assert_eq!(failed.ended_at, ended.ended_at);
    store
        .set_run_status("a", "active", None)
        .await
        .expect("reactivate");
    assert_eq!(
        store
            .get_run("a")
            .await
            .expect("get")
            .expect("exists")
            .ended_at,
        None
    );

    assert!(matches!(
        store.set_run_status("a", "paused", None).await,
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        store.set_run_status("missing", "ended", None).await,
        Err(StoreError::NotFound(_))
    ));
}

async fn list_runs_filters_pages_and_counts(store: &Store) {
    let mut ids = Vec::new();
    for i in 0..7 {
        let id = format!("run-{i}");
        store.create_run(&new_run(&id)).await.expect("create");
        ids.push(id);
        // Distinct creation times, so that the order is by time.
        tokio::time::sleep(std::time::Duration::from_millis(3)).await;
    }
    for id in ["run-1", "run-3", "run-5"] {
        store.set_run_status(id, "ended", None).await.expect("end");
    }
    store.add_robot("run-2", &robot("1")).await.expect("robot");
    store.add_robot("run-2", &robot("2")).await.expect("robot");
    store
        .append("run-2", (0..4).map(|s| obs("1", s)).collect())
        .await
        .expect("append");

    let all = store.list_runs(&RunFilter::default()).await.expect("list");
    let listed: Vec<&str> = all.iter().map(|r| r.id.as_str()).collect();
    let newest_first: Vec<&str> = ids.iter().rev().map(String::as_str).collect();
    assert_eq!(listed, newest_first);
    let r2 = all.iter().find(|r| r.id == "run-2").expect("run-2 listed");
    assert_eq!((r2.robots, r2.records), (2, 4));
    assert!(
        all.iter()
            .filter(|r| r.id != "run-2")
            .all(|r| r.robots == 0 && r.records == 0)
    );
    assert_eq!(
        store
            .get_run("run-2")
            .await
            .expect("get")
            .expect("exists")
            .records,
        4
    );

    let ended = RunFilter {
        status: Some("ended".into()),
        ..RunFilter::default()
    };
    let got: Vec<String> = store
        .list_runs(&ended)
        .await
        .expect("list")
        .into_iter()
        .map(|r| r.id)
        .collect();
    assert_eq!(got, ["run-5", "run-3", "run-1"]);
    assert_eq!(store.count_runs(&ended).await.expect("count"), 3);

    // Paging: 3 per page covers all 7 exactly once, in order.
    let mut paged = Vec::new();
    for page in 0..3 {
        let f = RunFilter {
            limit: 3,
            offset: page * 3,
            ..RunFilter::default()
        };
        paged.extend(
            store
                .list_runs(&f)
                .await
                .expect("page")
                .into_iter()
                .map(|r| r.id),
        );
    }
    assert_eq!(paged, newest_first);

    // Dates: created in [t(run-2), t(run-5)).
    let t2 = all
        .iter()
        .find(|r| r.id == "run-2")
        .expect("run-2")
        .created_at;
    let t5 = all
        .iter()
        .find(|r| r.id == "run-5")
        .expect("run-5")
        .created_at;
    let window = RunFilter {
        created_after: Some(t2),
        created_before: Some(t5),
        ..RunFilter::default()
    };
    let got: Vec<String> = store
        .list_runs(&window)
        .await
        .expect("list")
        .into_iter()
        .map(|r| r.id)
        .collect();
    assert_eq!(got, ["run-4", "run-3", "run-2"]);
    assert_eq!(store.count_runs(&window).await.expect("count"), 3);
    let both = RunFilter {
        status: Some("active".into()),
        ..window
    };
    let got: Vec<String> = store
        .list_runs(&both)
        .await
        .expect("list")
        .into_iter()
        .map(|r| r.id)
        .collect();
    assert_eq!(got, ["run-4", "run-2"]);

    assert!(matches!(
        store
            .list_runs(&RunFilter {
                limit: 0,
                ..RunFilter::default()
            })
            .await,
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        store
            .list_runs(&RunFilter {
                status: Some("x".into()),
                ..RunFilter::default()
            })
            .await,
        Err(StoreError::Invalid(_))
    ));
}

async fn robots_and_duplicate_conflict(store: &Store) {
    store.create_run(&new_run("r")).await.expect("create");
    store.add_robot("r", &robot("1")).await.expect("robot 1");
    store
        .add_robot(
            "r",
            &NewRobot {
                robot_id: "2".into(),
                start: None,
                token_hash: "h2".into(),
                t0: None,
            },
        )
        .await
        .expect("robot 2");
    assert!(matches!(
        store.add_robot("r", &robot("1")).await,
        Err(StoreError::Conflict(_))
    ));
    assert!(matches!(
        store.add_robot("missing", &robot("1")).await,
        Err(StoreError::NotFound(_))
    ));
    let robots = store.robots("r").await.expect("robots");
    let ids: BTreeSet<&str> = robots.iter().map(|r| r.robot_id.as_str()).collect();
    assert_eq!(ids, BTreeSet::from(["1", "2"]));
    let one = robots.iter().find(|r| r.robot_id == "1").expect("robot 1");
    assert_eq!(one.token_hash, "hash-of-1");
    assert_eq!(one.t0, Some(1_248_444_175.103));
    assert_eq!(one.start, robot("1").start);
    // The token hash is never serialized.
    let shown = serde_json::to_value(one).expect("serialize");
    assert!(shown.get("token_hash").is_none());
    assert_eq!(
        store
            .get_run("r")
            .await
            .expect("get")
            .expect("exists")
            .robots,
        2
    );
}

async fn append_arrivals_duplicates_and_paging(store: &Store) {
    store.create_run(&new_run("log")).await.expect("create");
    let first: Vec<NewObservation> = (0..10)
        .map(|s| obs("1", s))
        .chain((0..5).map(|s| obs("2", s)))
        .collect();
    let out = store.append("log", first.clone()).await.expect("append");
    assert_eq!(out.items.len(), 15);
    assert_eq!(out.inserted(), 15);
    for (i, item) in out.items.iter().enumerate() {
        assert_eq!(item.arrival, i as i64 + 1);
        assert!(!item.duplicate);
        assert_eq!(
            (item.robot_id.as_str(), item.seq),
            (first[i].robot_id.as_str(), first[i].seq)
        );
    }

    // A retry mixing repeats and new records: repeats keep their arrival, new ones go on.
    let retry = vec![
        obs("1", 3),
        obs("2", 5),
        obs("1", 9),
        obs("2", 6),
        obs("2", 5),
    ];
    let out = store.append("log", retry).await.expect("append again");
    let got: Vec<(i64, bool)> = out.items.iter().map(|a| (a.arrival, a.duplicate)).collect();
    assert_eq!(
        got,
        [(4, true), (16, false), (10, true), (17, false), (16, true)]
    );
    assert_eq!(store.record_count("log").await.expect("count"), 17);
    assert_eq!(
        store
            .get_run("log")
            .await
            .expect("get")
            .expect("exists")
            .records,
        17
    );

    // The log reads back in arrival order, byte for byte, in pages.
    let mut all = Vec::new();
    let mut after = 0;
    loop {
        let page = store.records_after("log", after, 4).await.expect("page");
        assert!(page.len() <= 4);
        let Some(last) = page.last() else { break };
        after = last.arrival;
        all.extend(page);
    }
    assert_eq!(
        all.iter().map(|r| r.arrival).collect::<Vec<_>>(),
        (1..=17).collect::<Vec<_>>()
    );
    assert_eq!(all[0].body, first[0].body);
    assert_eq!((all[0].t, all[0].seq), (first[0].t, 0));
    assert_eq!((all[15].robot_id.as_str(), all[15].seq), ("2", 5));
    assert_eq!(
        store
            .records_after("log", 15, 100)
            .await
            .expect("tail")
            .len(),
        2
    );
    assert!(
        store
            .records_after("log", 17, 100)
            .await
            .expect("end")
            .is_empty()
    );
    assert!(matches!(
        store.records_after("log", 0, 0).await,
        Err(StoreError::Invalid(_))
    ));

    let seqs = store.last_seqs("log").await.expect("last seqs");
    assert_eq!(
        seqs,
        BTreeMap::from([("1".to_owned(), 9), ("2".to_owned(), 6)])
    );
    assert!(store.last_seqs("other").await.expect("none").is_empty());
    assert!(
        store
            .append("log", Vec::new())
            .await
            .expect("empty")
            .items
            .is_empty()
    );
}

/// Appends larger than one look-up and one multi-row insert (1,000 records each): every
/// record is stored once with its arrival in call order, repeats (stored before, or earlier in
/// the same call) keep the first arrival, and the body reads back byte for byte.
async fn large_appends_span_several_statements(store: &Store) {
    store.create_run(&new_run("big")).await.expect("create");
    let first: Vec<NewObservation> = (0..2500).map(|s| obs(&format!("{}", s % 3), s)).collect();
    let out = store.append("big", first.clone()).await.expect("append");
    assert_eq!(out.inserted(), 2500);
    assert!(
        out.items
            .iter()
            .enumerate()
            .all(|(i, a)| a.arrival == i as i64 + 1 && !a.duplicate)
    );
    // A retry of all of it with 1,200 new records interleaved and a repeat of a new one.
    let mut retry = Vec::new();
    for s in 0..2500 {
        retry.push(first[s as usize].clone());
        if s < 1200 {
            retry.push(obs("9", s));
        }
    }
    retry.push(obs("9", 7));
    let out = store.append("big", retry.clone()).await.expect("retry");
    assert_eq!(out.items.len(), retry.len());
    assert_eq!(out.inserted(), 1200);
    let mut new_arrival = 2501;
    for (item, rec) in out.items.iter().zip(&retry) {
        assert_eq!(
            (item.robot_id.as_str(), item.seq),
            (rec.robot_id.as_str(), rec.seq)
        );
        if rec.robot_id == "9" && !(item.duplicate) {
            assert_eq!(item.arrival, new_arrival);
            new_arrival += 1;
        } else {
            assert!(item.duplicate);
            let want = if rec.robot_id == "9" {
                2501 + 7
            } else {
                rec.seq + 1
            };
            assert_eq!(item.arrival, want, "{} {}", rec.robot_id, rec.seq);
        }
    }
    assert_eq!(new_arrival, 3701);
    assert_eq!(store.record_count("big").await.expect("count"), 3700);
    let back = store.records_after("big", 2500, 5000).await.expect("read");
    assert_eq!(back.len(), 1200);
    assert_eq!((back[7].robot_id.as_str(), back[7].seq), ("9", 7));
    assert_eq!(back[7].body, obs("9", 7).body);
    // A seq below its robot's highest that was never stored is new (robot "0" holds the
    // multiples of 3 up to 2,499), and its repeat in the same call is one.
    let out = store
        .append("big", vec![obs("0", 2), obs("0", 3), obs("0", 2)])
        .await
        .expect("below the highest");
    let got: Vec<(i64, bool)> = out.items.iter().map(|a| (a.arrival, a.duplicate)).collect();
    assert_eq!(got, [(3701, false), (4, true), (3701, true)]);
    assert_eq!(store.record_count("big").await.expect("count"), 3701);
}

async fn append_rejects_bad_input(store: &Store) {
    assert!(matches!(
        store.append("missing", vec![obs("1", 0)]).await,
        Err(StoreError::NotFound(_))
    ));
    store.create_run(&new_run("bad")).await.expect("create");
    let mut nan = obs("1", 0);
    nan.t = f64::NAN;
    assert!(matches!(
        store.append("bad", vec![nan]).await,
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        store.append("bad", vec![obs("1", -1)]).await,
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        store.append("bad", vec![obs("", 0)]).await,
        Err(StoreError::Invalid(_))
    ));
    // Nothing of a refused call was written, and the log still starts at 1.
    assert_eq!(store.record_count("bad").await.expect("count"), 0);
    let out = store
        .append("bad", vec![obs("1", 0)])
        .await
        .expect("append");
    assert_eq!(out.items[0].arrival, 1);
}

async fn concurrent_appends_group_commit(store: &Store) {
    const ROBOTS: usize = 5;
    const EACH: i64 = 200;
    store.create_run(&new_run("fleet")).await.expect("create");
    let before = store.writer_stats();
    let mut tasks = Vec::new();
    for r in 0..ROBOTS {
        let store = store.clone();
        tasks.push(tokio::spawn(async move {
            let robot = format!("robot-{r}");
            let mut arrivals = Vec::new();
            for seq in 0..EACH {
                // Each record is awaited before the next, like a robot waiting for its ack.
                let out = store
                    .append("fleet", vec![obs(&robot, seq)])
                    .await
                    .expect("append");
                assert!(!out.items[0].duplicate);
                arrivals.push(out.items[0].arrival);
            }
            arrivals
        }));
    }
    let mut all = Vec::new();
    for task in tasks {
        let arrivals = task.await.expect("task");
        // One robot's records arrive in its order.
        assert!(arrivals.windows(2).all(|w| w[0] < w[1]));
        all.extend(arrivals);
    }
    all.sort_unstable();
    let total = ROBOTS as i64 * EACH;
    assert_eq!(
        all,
        (1..=total).collect::<Vec<_>>(),
        "unique contiguous arrivals"
    );
    assert_eq!(store.record_count("fleet").await.expect("count"), total);
    let seqs = store.last_seqs("fleet").await.expect("seqs");
    assert_eq!(seqs.len(), ROBOTS);
    assert!(seqs.values().all(|&s| s == EACH - 1));
    // The stored log has every record exactly once.
    let stored = store.records_after("fleet", 0, 10_000).await.expect("read");
    let keys: BTreeSet<(String, i64)> =
        stored.iter().map(|r| (r.robot_id.clone(), r.seq)).collect();
    assert_eq!((stored.len(), keys.len()), (total as usize, total as usize));
    let stats = store.writer_stats();
    assert_eq!(stats.records - before.records, total as u64);
    assert_eq!(stats.appends - before.appends, total as u64);
    eprintln!(
        "{}: {} single-record appends from {ROBOTS} tasks in {} commits",
        store.backend(),
        total,
        stats.commits - before.commits
    );
}

async fn snapshots_latest_and_at_or_before(store: &Store) {
    store.create_run(&new_run("snap")).await.expect("create");
    assert!(store.latest_snapshot("snap").await.expect("none").is_none());
    for (applied, t) in [(10, 1.0), (20, 2.0), (30, 3.0)] {
        let data: Vec<u8> = (0..=255u8).chain([0, applied as u8]).collect();
        store
            .put_snapshot("snap", &NewSnapshot { applied, t, data })
            .await
            .expect("put");
    }
    let latest = store
        .latest_snapshot("snap")
        .await
        .expect("latest")
        .expect("some");
    assert_eq!(
        (latest.applied, latest.t, latest.data.len()),
        (30, 3.0, 258)
    );
    assert_eq!(latest.data[..256], (0..=255u8).collect::<Vec<_>>()[..]);
    assert_eq!(latest.run_id, "snap");
    let at = |t| store.snapshot_at_or_before("snap", t);
    assert_eq!(at(2.5).await.expect("at").map(|s| s.applied), Some(20));
    assert_eq!(at(2.0).await.expect("at").map(|s| s.applied), Some(20));
    assert_eq!(at(100.0).await.expect("at").map(|s| s.applied), Some(30));
    assert!(at(0.5).await.expect("at").is_none());
    // The same watermark again replaces the snapshot.
    store
        .put_snapshot(
            "snap",
            &NewSnapshot {
                applied: 30,
                t: 3.5,
                data: vec![7],
            },
        )
        .await
        .expect("replace");
    let latest = store
        .latest_snapshot("snap")
        .await
        .expect("latest")
        .expect("some");
    assert_eq!((latest.t, latest.data), (3.5, vec![7]));
    assert!(matches!(
        store
            .put_snapshot(
                "missing",
                &NewSnapshot {
                    applied: 1,
                    t: 0.0,
                    data: vec![]
                }
            )
            .await,
        Err(StoreError::NotFound(_))
    ));
}

async fn artifacts_and_snapshot_index(store: &Store) {
    store.create_run(&new_run("art")).await.expect("create");
    assert_eq!(store.get_artifact("art", "truth").await.expect("get"), None);
    store
        .put_artifact("art", "truth", r#"{"a":1}"#)
        .await
        .expect("put");
    store
        .put_artifact("art", "truth", r#"{"a":2}"#)
        .await
        .expect("replace");
    assert_eq!(
        store
            .get_artifact("art", "truth")
            .await
            .expect("get")
            .as_deref(),
        Some(r#"{"a":2}"#)
    );
    assert!(matches!(
        store.put_artifact("missing", "truth", "{}").await,
        Err(StoreError::NotFound(_))
    ));
    assert!(matches!(
        store.put_artifact("art", "", "{}").await,
        Err(StoreError::Invalid(_))
    ));
    for (applied, t) in [(30, 3.0), (10, 1.0), (20, 2.0)] {
        store
            .put_snapshot(
                "art",
                &NewSnapshot {
                    applied,
                    t,
                    data: vec![applied as u8],
                },
            )
            .await
            .expect("snapshot");
    }
    assert_eq!(
        store.snapshot_index("art").await.expect("index"),
        vec![(10, 1.0), (20, 2.0), (30, 3.0)]
    );
    let at = |a| store.snapshot_at_or_before_applied("art", a);
    assert_eq!(at(25).await.expect("at").map(|s| s.data), Some(vec![20]));
    assert_eq!(at(30).await.expect("at").map(|s| s.applied), Some(30));
    assert!(at(9).await.expect("at").is_none());
    assert!(store.delete_run("art").await.expect("delete"));
    assert_eq!(store.get_artifact("art", "truth").await.expect("get"), None);
    assert!(store.snapshot_index("art").await.expect("index").is_empty());
}

async fn delete_run_removes_everything(store: &Store) {
    for id in ["doomed", "kept"] {
        store.create_run(&new_run(id)).await.expect("create");
        store.add_robot(id, &robot("1")).await.expect("robot");
        store
            .append(id, (0..20).map(|s| obs("1", s)).collect())
            .await
            .expect("append");
        store
            .put_snapshot(
                id,
                &NewSnapshot {
                    applied: 20,
                    t: 2.0,
                    data: vec![1, 2, 3],
                },
            )
            .await
            .expect("snapshot");
        store
            .put_evaluation(id, &json!({"ate": 0.2}))
            .await
            .expect("eval");
        store
            .append_training(id, &["{\"x\":1}".to_owned()])
            .await
            .expect("training");
    }
    assert!(store.delete_run("doomed").await.expect("delete"));
    assert!(!store.delete_run("doomed").await.expect("delete again"));
    assert!(store.get_run("doomed").await.expect("get").is_none());
    assert_eq!(store.record_count("doomed").await.expect("count"), 0);
    assert!(store.robots("doomed").await.expect("robots").is_empty());
    assert!(
        store
            .records_after("doomed", 0, 100)
            .await
            .expect("records")
            .is_empty()
    );
    assert!(
        store
            .latest_snapshot("doomed")
            .await
            .expect("snapshot")
            .is_none()
    );
    assert!(store.evaluations("doomed").await.expect("evals").is_empty());
    assert!(
        store
            .training_rows(&["doomed".to_owned()], 10)
            .await
            .expect("training")
            .is_empty()
    );
    assert!(store.last_seqs("doomed").await.expect("seqs").is_empty());

    let kept = store.get_run("kept").await.expect("get").expect("kept");
    assert_eq!((kept.robots, kept.records), (1, 20));
    assert!(
        store
            .latest_snapshot("kept")
            .await
            .expect("snapshot")
            .is_some()
    );
    assert_eq!(store.evaluations("kept").await.expect("evals").len(), 1);
    assert_eq!(
        store.training_rows(&[], 10).await.expect("training").len(),
        1
    );

    // A run re-created under the same id starts a fresh log at arrival 1.
    store
        .create_run(&new_run("doomed"))
        .await
        .expect("re-create");
    let out = store
        .append("doomed", vec![obs("1", 0)])
        .await
        .expect("append");
    assert_eq!((out.items[0].arrival, out.items[0].duplicate), (1, false));
    let out = store
        .append("kept", vec![obs("1", 20)])
        .await
        .expect("append");
    assert_eq!(out.items[0].arrival, 21);
}

async fn evaluations_training_and_models(store: &Store) {
    for id in ["e1", "e2"] {
        store.create_run(&new_run(id)).await.expect("create");
    }
    store
        .put_evaluation("e1", &json!({"n": 1}))
        .await
        .expect("eval");
    store
        .put_evaluation("e1", &json!({"n": 2, "x": 0.1}))
        .await
        .expect("eval");
    assert_eq!(
        store.evaluations("e1").await.expect("evals"),
        vec![json!({"n": 1}), json!({"n": 2, "x": 0.1})]
    );
    assert!(matches!(
        store.put_evaluation("missing", &json!({})).await,
        Err(StoreError::NotFound(_))
    ));

    let rows = |run: &str, n: usize| {
        (0..n)
            .map(|i| format!(r#"{{"run":"{run}","i":{i}}}"#))
            .collect::<Vec<_>>()
    };
    store
        .append_training("e1", &rows("e1", 3))
        .await
        .expect("training");
    store
        .append_training("e2", &rows("e2", 2))
        .await
        .expect("training");
    assert_eq!(
        store
            .training_rows(&["e1".into()], 100)
            .await
            .expect("rows"),
        rows("e1", 3)
    );
    assert_eq!(
        store
            .training_rows(&["e1".into(), "e2".into()], 100)
            .await
            .expect("rows")
            .len(),
        5
    );
    assert_eq!(store.training_rows(&[], 4).await.expect("rows").len(), 4);
    assert!(matches!(
        store.append_training("missing", &rows("m", 1)).await,
        Err(StoreError::NotFound(_))
    ));

    let model = NewModel {
        id: "mlp-1".into(),
        kind: "mlp_updater".into(),
        config: json!({"hidden": [64, 64]}),
        metrics: json!({"rmse": 0.05}),
        weights: (0..1000u32).flat_map(|i| i.to_le_bytes()).collect(),
    };
    store.put_model(&model).await.expect("model");
    let got = store
        .get_model("mlp-1")
        .await
        .expect("get")
        .expect("stored");
    assert_eq!(
        (got.kind.as_str(), &got.config, &got.metrics),
        ("mlp_updater", &model.config, &model.metrics)
    );
    assert_eq!(got.weights, model.weights);
    let listed = store.list_models().await.expect("list");
    assert_eq!(listed.len(), 1);
    assert_eq!(listed[0].weights_len, 4000);
    store
        .put_model(&NewModel {
            weights: vec![1, 2],
            ..model
        })
        .await
        .expect("replace");
    assert_eq!(
        store
            .get_model("mlp-1")
            .await
            .expect("get")
            .expect("stored")
            .weights,
        vec![1, 2]
    );
    assert!(store.get_model("nope").await.expect("get").is_none());
}

/// Durability across a restart: a SQLite store reopened from the same file has everything.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sqlite_reopen_keeps_everything() {
    let dir = tempfile::tempdir().expect("temporary directory");
    let nested = dir.path().join("not/yet/there");
    {
        let store = Store::open_default(&nested).await.expect("open");
        store.create_run(&new_run("durable")).await.expect("create");
        store
            .add_robot("durable", &robot("1"))
            .await
            .expect("robot");
        store
            .append("durable", (0..50).map(|s| obs("1", s)).collect())
            .await
            .expect("append");
        store
            .put_snapshot(
                "durable",
                &NewSnapshot {
                    applied: 50,
                    t: 5.0,
                    data: vec![9; 64],
                },
            )
            .await
            .expect("snapshot");
        // Dropped without close, as in a crash after the acknowledgements.
    }
    assert!(nested.join("fleetslam.db").exists());
    let url = format!("sqlite://{}", nested.join("fleetslam.db").display());
    let store = Store::open(&url).await.expect("reopen");
    let run = store.get_run("durable").await.expect("get").expect("kept");
    assert_eq!(
        (run.status.as_str(), run.robots, run.records),
        ("active", 1, 50)
    );
    assert_eq!(store.active_runs().await.expect("active").len(), 1);
    assert_eq!(
        store
            .latest_snapshot("durable")
            .await
            .expect("snap")
            .expect("kept")
            .data,
        vec![9; 64]
    );
    let log = store.records_after("durable", 0, 1000).await.expect("log");
    assert_eq!(log.len(), 50);
    assert_eq!(log[49].body, obs("1", 49).body);
    // The arrival counter continues from the stored log, and repeats are still recognised.
    let out = store
        .append("durable", vec![obs("1", 10), obs("1", 50)])
        .await
        .expect("append");
    let got: Vec<(i64, bool)> = out.items.iter().map(|a| (a.arrival, a.duplicate)).collect();
    assert_eq!(got, [(11, true), (51, false)]);
    store.close().await;
}

#[tokio::test]
async fn open_refuses_unknown_urls() {
    assert!(matches!(
        Store::open("mysql://localhost/db").await,
        Err(StoreError::Invalid(_))
    ));
}

#[test]
fn database_urls_are_rewritten() {
    assert_eq!(
        fleetslam_store::admin::with_database("postgres://postgres@127.0.0.1:5432/test", "x"),
        "postgres://postgres@127.0.0.1:5432/x"
    );
    assert_eq!(
        fleetslam_store::admin::with_database("postgres://h/test?sslmode=disable", "x"),
        "postgres://h/x?sslmode=disable"
    );
    assert_eq!(
        fleetslam_store::admin::with_database("postgres://h", "x"),
        "postgres://h/x"
    );
}

async fn quarantine_marks_records_and_keeps_their_seq(store: &Store) {
    store.create_run(&new_run("q")).await.expect("create");
    store
        .append("q", (0..5).map(|s| obs("1", s)).collect())
        .await
        .expect("append");
    // New records are in good standing.
    let all = store.records_after("q", 0, 100).await.expect("read");
    assert!(all.iter().all(|r| r.rejected.is_none()), "{all:?}");

    assert!(
        store
            .quarantine("q", "1", 2, "step panicked: boom")
            .await
            .expect("quarantine")
    );
    // Marking again keeps the first reason; an unknown record is reported.
    assert!(store.quarantine("q", "1", 2, "other").await.expect("again"));
    assert!(!store.quarantine("q", "1", 99, "x").await.expect("missing"));
    assert!(
        !store
            .quarantine("other", "1", 2, "x")
            .await
            .expect("no run")
    );

    let all = store.records_after("q", 0, 100).await.expect("read");
    let marked: Vec<(i64, Option<&str>)> =
        all.iter().map(|r| (r.seq, r.rejected.as_deref())).collect();
    assert_eq!(
        marked,
        [
            (0, None),
            (1, None),
            (2, Some("step panicked: boom")),
            (3, None),
            (4, None)
        ]
    );
    // Its seq stays taken: posting it again is a duplicate, nothing new is stored.
    let again = store.append("q", vec![obs("1", 2)]).await.expect("repeat");
    assert!(again.items[0].duplicate);
    assert_eq!(again.items[0].arrival, 3);
    assert_eq!(store.record_count("q").await.expect("count"), 5);
    // The time window reads it with its mark too.
    let window = store
        .records_in_time("q", 100.2, 100.2, 0, 10)
        .await
        .expect("window");
    assert_eq!(window.len(), 1);
    assert_eq!(window[0].rejected.as_deref(), Some("step panicked: boom"));
    // Deleting the run removes it with the rest.
    assert!(store.delete_run("q").await.expect("delete"));
    assert!(
        store
            .records_after("q", 0, 100)
            .await
            .expect("gone")
            .is_empty()
    );
}

async fn records_in_time_reads_only_the_window(store: &Store) {
    store.create_run(&new_run("w")).await.expect("create");
    store.create_run(&new_run("w2")).await.expect("create");
    // Robot 1 at t = 100.0, 100.1, ... 101.9; robot 2 arrives later with earlier times.
    store
        .append("w", (0..20).map(|s| obs("1", s)).collect())
        .await
        .expect("append 1");
    store
        .append("w", (0..10).map(|s| obs("2", s)).collect())
        .await
        .expect("append 2");
    store
        .append("w2", (0..20).map(|s| obs("1", s)).collect())
        .await
        .expect("other run");
    let key = |v: &[fleetslam_store::StoredObservation]| -> Vec<(String, i64, i64)> {
        v.iter()
            .map(|r| (r.robot_id.clone(), r.seq, r.arrival))
            .collect()
    };
    // Inclusive bounds, arrival order, this run only.
    let got = store
        .records_in_time("w", 100.45, 100.75, 0, 100)
        .await
        .expect("window");
    assert_eq!(
        key(&got),
        [
            ("1".to_owned(), 5, 6),
            ("1".to_owned(), 6, 7),
            ("1".to_owned(), 7, 8),
            ("2".to_owned(), 5, 26),
            ("2".to_owned(), 6, 27),
            ("2".to_owned(), 7, 28),
        ]
    );
    let exact = store
        .records_in_time("w", 100.0 + 3.0 * 0.1, 100.0 + 3.0 * 0.1, 0, 100)
        .await
        .expect("exact");
    assert_eq!(exact.len(), 2, "both bounds are inclusive: {exact:?}");
    assert!(exact.iter().all(|r| r.t == 100.0 + 3.0 * 0.1));
    // Paging by arrival.
    let mut paged = Vec::new();
    let mut after = 0;
    loop {
        let page = store
            .records_in_time("w", 100.45, 100.75, after, 4)
            .await
            .expect("page");
        let Some(last) = page.last() else { break };
        after = last.arrival;
        paged.extend(page);
    }
    assert_eq!(key(&paged), key(&got));
    // Open bounds read everything, in arrival order; an empty window reads nothing.
    let all = store
        .records_in_time("w", f64::NEG_INFINITY, f64::INFINITY, 0, 1000)
        .await
        .expect("all");
    assert_eq!(all.len(), 30);
    assert!(all.windows(2).all(|w| w[0].arrival < w[1].arrival));
    assert_eq!(all[29].body, obs("2", 9).body);
    assert!(
        store
            .records_in_time("w", 200.0, 300.0, 0, 100)
            .await
            .expect("empty")
            .is_empty()
    );
    assert!(matches!(
        store.records_in_time("w", 0.0, 1.0, 0, 0).await,
        Err(StoreError::Invalid(_))
    ));
    assert!(matches!(
        store.records_in_time("w", f64::NAN, 1.0, 0, 10).await,
        Err(StoreError::Invalid(_))
    ));
}

async fn failed_runs_keep_their_reason(store: &Store) {
    store.create_run(&new_run("f")).await.expect("create");
    store.create_run(&new_run("ok")).await.expect("create");
    assert_eq!(
        store.get_run("f").await.expect("get").expect("run").reason,
        None
    );
    store
        .set_run_failed("f", "recovery failed: bad start pose")
        .await
        .expect("fail");
    let row = store.get_run("f").await.expect("get").expect("run");
    assert_eq!(row.status, "failed");
    assert_eq!(
        row.reason.as_deref(),
        Some("recovery failed: bad start pose")
    );
    assert!(row.ended_at.is_some());
    // Listed with its reason, and no longer recovered on start.
    let listed = store
        .list_runs(&RunFilter {
            status: Some("failed".into()),
            ..RunFilter::default()
        })
        .await
        .expect("list");
    assert_eq!(listed.len(), 1);
    assert_eq!(listed[0].reason, row.reason);
    let active: Vec<String> = store
        .active_runs()
        .await
        .expect("active")
        .into_iter()
        .map(|r| r.id)
        .collect();
    assert_eq!(active, ["ok"]);
    assert!(matches!(
        store.set_run_failed("missing", "x").await,
        Err(StoreError::NotFound(_))
    ));
    assert!(store.delete_run("f").await.expect("delete"));
}
