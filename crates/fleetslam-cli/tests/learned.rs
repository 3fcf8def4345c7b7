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

/// The MRCLAM Dataset 6 directory beside the clone; a missing one fails under
/// `FLEETSLAM_REQUIRE_DATA=1` (CI) and skips otherwise.
fn mrclam() -> Option<std::path::PathBuf> {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/datasets/mrclam-dataset6");
    if p.is_dir() {
        return Some(p);
    }
    assert!(
        !std::env::var("FLEETSLAM_REQUIRE_DATA").is_ok_and(|v| v == "1"),
        "{} is missing and FLEETSLAM_REQUIRE_DATA=1",
        p.display()
    );
    println!("skipped: {} is missing", p.display());
    None
}

/// `experiment mrclam-truth` on a slice: three sets split by robot and time, every row of
/// each matched to its observation and labelled, two models trained and saved, the filter
/// run on the test set with the EKF and both, and the table written.
#[test]
fn experiment_mrclam_truth_on_a_slice() {
    let Some(data) = mrclam() else { return };
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_string_lossy().into_owned();
    let printed = ok(&[
        "experiment",
        "mrclam-truth",
        "--dataset",
        &data.to_string_lossy(),
        "--duration",
        "120",
        "--split",
        "60",
        "--seeds",
        "1",
        "--particles",
        "50",
        "--train-particles",
        "50",
        "--training-rate",
        "0.2",
        "--epochs",
        "20",
        "--prior-gate",
        "9.21",
        "--work",
        &d("work"),
        "--out-dir",
        &d("docs"),
    ]);
    for set in ["training set", "validation set", "test set"] {
        let line = printed
            .lines()
            .find(|l| l.starts_with(set))
            .unwrap_or_else(|| panic!("no {set} line: {printed}"));
        assert!(line.contains(", 0 not in the log"), "{line}");
        let labelled: usize = line
            .split(" rows logged, ")
            .nth(1)
            .and_then(|s| s.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap();
        assert!(labelled > 100, "{line}");
    }
    for id in ["mlp-truth-mrclam", "mlp-truth-layout-ekf-target-mrclam"] {
        let m = json(&dir.path().join("work").join(id).join("model.json"));
        assert_eq!(m["layout"], "line_of_sight_range");
        let truth = &m["metadata"]["report"]["updater"]["truth"];
        assert!(truth["rows"].as_u64().unwrap() > 0, "{truth}");
    }
    let results = json(&dir.path().join("work/mrclam-truth-results.json"));
    let results = results.as_array().unwrap();
    assert_eq!(results.len(), 3);
    assert!(
        results
            .iter()
            .all(|r| r["ate"].as_f64().unwrap().is_finite())
    );
    let md = std::fs::read_to_string(dir.path().join("docs/learned-mrclam-truth.md")).unwrap();
    assert!(md.contains("| test | 4, 5 | 60 s to 120 s |"), "{md}");
    assert!(md.contains("| ekf | 1 |"), "{md}");
}
