//! The learned updater's commands end to end: log training rows from a run, train a model,
//! run with it, register it in a store, and refuse a model of another landmark kind.

mod common;
use common::{fleetslam, json, ok};

#[test]
fn log_rows_train_and_run_with_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_string_lossy().into_owned();
    ok(&[
        "simulate",
        "--robots",
        "2",
        "--duration",
        "20",
        "--seed",
        "3",
        "--out",
        &d("sim"),
    ]);
    let log = d("sim/log.ndjson");
    let out = ok(&[
        "run",
        &log,
        "--particles",
        "50",
        "--out",
        &d("ekf"),
        "--log-training",
        &d("rows.ndjson"),
        "--training-rate",
        "0.5",
        "--training-cap",
        "20000",
    ]);
    assert!(out.contains("training rows"), "{out}");
    let rows = std::fs::read_to_string(d("rows.ndjson")).unwrap();
    assert!(rows.lines().count() > 500, "{} rows", rows.lines().count());
    // The same run logs the same rows.
    ok(&[
        "run",
        &log,
        "--particles",
        "50",
        "--out",
        &d("ekf2"),
        "--log-training",
        &d("rows2.ndjson"),
        "--training-rate",
        "0.5",
        "--training-cap",
        "20000",
        "--threads",
        "1",
    ]);
    assert_eq!(rows, std::fs::read_to_string(d("rows2.ndjson")).unwrap());
    // Two more runs (other filter seeds): training splits runs, never rows.
    for seed in ["2", "3"] {
        ok(&[
            "run",
            &log,
            "--particles",
            "50",
            "--seed",
            seed,
            "--out",
            &d(&format!("ekf-seed{seed}")),
            "--log-training",
            &d(&format!("rows-seed{seed}.ndjson")),
            "--training-rate",
            "0.5",
            "--training-cap",
            "20000",
        ]);
    }
    let err = common::fails(&["train", "--data", &d("rows.ndjson"), "--out", &d("m1")]);
    assert!(err.contains("a split by run needs at least 3"), "{err}");
    let out = ok(&[
        "train",
        "--data",
        &d("rows.ndjson"),
        "--data",
        &d("rows-seed2.ndjson"),
        "--data",
        &d("rows-seed3.ndjson"),
        "--preset",
        "default",
        "--hidden",
        "16,16",
        "--epochs",
        "20",
        "--id",
        "cli-mlp",
        "--out",
        &d("model"),
        "--data-dir",
        &d("store"),
    ]);
    assert!(
        out.contains("test error of each network output (test runs only)"),
        "{out}"
    );
    assert!(out.contains("registered model cli-mlp"), "{out}");
    for f in ["model.json", "model.bpk", "config.json", "report.json"] {
        assert!(dir.path().join("model").join(f).is_file(), "{f} missing");
    }
    ok(&[
        "run",
        &log,
        "--particles",
        "50",
        "--out",
        &d("mlp"),
        "--updater",
        &d("model"),
    ]);
    let m = json(&dir.path().join("mlp/metrics.json"));
    assert_eq!(m["updater"], "cli-mlp");
    assert!(m["landmark_updates"].as_u64().unwrap() > 0);
    // The store holds no server-logged rows yet: the export is empty but works.
    let out = ok(&[
        "export-training",
        "--data-dir",
        &d("store"),
        "--out",
        &d("export.ndjson"),
    ]);
    assert!(out.contains("exported 0 training rows"), "{out}");

    // A server run with the stored model as its updater, logging its own training rows.
    let (server, url) = common::serve("127.0.0.1:0", &["--data-dir", &d("store")]);
    std::fs::write(d("mlp.json"), r#"{"updater": "cli-mlp", "particles": 30}"#).unwrap();
    let replayed = fleetslam(&[
        "replay",
        &log,
        "--server",
        &url,
        "--fast",
        "--config",
        &d("mlp.json"),
        "--log-training",
        "0.5",
    ]);
    let bad_updater = std::fs::write(d("none.json"), r#"{"updater": "no-such-model"}"#);
    bad_updater.unwrap();
    let refused = fleetslam(&[
        "replay",
        &log,
        "--server",
        &url,
        "--config",
        &d("none.json"),
    ]);
    let runs = fleetslam(&["runs", "--server", &url, "--json"]);
    drop(server);
    assert!(
        replayed.status.success(),
        "{}",
        String::from_utf8_lossy(&replayed.stderr)
    );
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("no-such-model"), "{err}");
    let runs: serde_json::Value = serde_json::from_slice(&runs.stdout).unwrap();
    assert_eq!(runs["runs"][0]["summary"]["updater"], "cli-mlp", "{runs}");
    let out = ok(&[
        "export-training",
        "--data-dir",
        &d("store"),
        "--out",
        &d("served.ndjson"),
    ]);
    let served = std::fs::read_to_string(d("served.ndjson")).unwrap();
    assert!(served.lines().count() > 100, "{out}");

    // A 3D run refuses the range-bearing model, saying why.
    ok(&[
        "simulate",
        "--robots",
        "1",
        "--duration",
        "5",
        "--kind",
        "point3d",
        "--out",
        &d("sim3"),
    ]);
    let bad = fleetslam(&[
        "run",
        &d("sim3/log.ndjson"),
        "--out",
        &d("bad"),
        "--updater",
        &d("model"),
    ]);
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("range_bearing_2d") && err.contains("point3d"),
        "{err}"
    );
}
