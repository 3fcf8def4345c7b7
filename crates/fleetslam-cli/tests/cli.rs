//! The `fleetslam` command end to end: simulate, run, evaluate, and clear errors.

mod common;
use common::{fails, fleetslam, json, ok};

#[test]
fn simulate_run_evaluate() {
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
    assert!(dir.path().join("sim/log.ndjson").is_file());
    assert!(dir.path().join("sim/truth/trajectory_1.tum").is_file());
    let printed = ok(&[
        "run",
        &d("sim/log.ndjson"),
        "--particles",
        "50",
        "--seed",
        "1",
        "--out",
        &d("run"),
    ]);
    assert!(printed.contains("landmark updates"), "{printed}");
    for f in [
        "trajectory_1.tum",
        "trajectory_2.tum",
        "landmarks.csv",
        "metrics.json",
    ] {
        assert!(dir.path().join("run").join(f).is_file(), "{f} missing");
    }
    let m = json(&dir.path().join("run/metrics.json"));
    for key in [
        "wall_time_s",
        "steps",
        "step_ms_p50",
        "step_ms_p95",
        "step_ms_max",
        "landmark_updates",
        "ns_per_landmark_update",
        "ns_per_particle_record",
        "ns_per_particle_observation",
    ] {
        assert!(m[key].is_number(), "metrics.json lacks {key}: {m}");
    }
    assert!(m["landmark_updates"].as_u64().unwrap() > 0);
    // The per-particle costs are the wall time spread over particles and records (or
    // landmark observations, which the simulated robots make).
    let per = |k: &str| m[k].as_f64().unwrap();
    let wall_ns = per("wall_time_s") * 1e9;
    let particles = per("particles");
    let steps = per("steps");
    assert!(per("ns_per_particle_record") > 0.0);
    assert!(
        (per("ns_per_particle_record") * particles * steps - wall_ns).abs() <= 1e-6 * wall_ns,
        "{m}"
    );
    assert!(per("ns_per_particle_observation") > 0.0);
    let printed = ok(&["evaluate", &d("run"), "--truth", &d("sim/truth")]);
    assert!(printed.contains("team"), "{printed}");
    let e = json(&dir.path().join("run/evaluation.json"));
    let ate = e["team"]["ate_rmse"].as_f64().unwrap();
    assert!(ate < 0.3, "team ATE {ate}");
    assert!(e["robots"]["1"]["ate_rmse"].is_number());
    assert!(e["team"]["landmark_rmse"].is_number());
}

#[test]
fn same_seed_same_files() {
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_string_lossy().into_owned();
    ok(&[
        "simulate",
        "--robots",
        "2",
        "--duration",
        "10",
        "--out",
        &d("sim"),
    ]);
    for (out, threads) in [("a", "1"), ("b", "2")] {
        ok(&[
            "run",
            &d("sim/log.ndjson"),
            "--particles",
            "40",
            "--seed",
            "9",
            "--threads",
            threads,
            "--out",
            &d(out),
        ]);
    }
    for f in ["trajectory_1.tum", "trajectory_2.tum", "landmarks.csv"] {
        let a = std::fs::read(dir.path().join("a").join(f)).unwrap();
        let b = std::fs::read(dir.path().join("b").join(f)).unwrap();
        assert!(a == b, "{f} differs between 1 and 2 threads");
    }
}

#[test]
fn errors_say_what_was_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("log.ndjson");
    std::fs::write(&log, "{\"fleetslam_log\":1,\"landmark_kind\":\"cones\"}\n").unwrap();
    let out = fleetslam(&[
        "run",
        log.to_str().unwrap(),
        "--out",
        dir.path().join("o").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("line 1") && err.contains("cones"), "{err}");

    let out = fleetslam(&["run", "/nonexistent/log.ndjson", "--out", "/tmp/x"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/log.ndjson"));

    let cfg = dir.path().join("bad.json");
    std::fs::write(&cfg, "{\"particles\": 0}").unwrap();
    ok(&[
        "simulate",
        "--robots",
        "1",
        "--duration",
        "2",
        "--out",
        dir.path().join("s").to_str().unwrap(),
    ]);
    let slog = dir.path().join("s/log.ndjson");
    let out = fleetslam(&[
        "run",
        slog.to_str().unwrap(),
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        dir.path().join("o").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("particles"), "{err}");
}

#[test]
fn run_localizes_a_robot_whose_start_is_forgotten() {
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_string_lossy().into_owned();
    ok(&[
        "simulate",
        "--robots",
        "3",
        "--duration",
        "60",
        "--seed",
        "4",
        "--out",
        &d("sim"),
    ]);
    let printed = ok(&[
        "run",
        &d("sim/log.ndjson"),
        "--particles",
        "50",
        "--seed",
        "1",
        "--unknown",
        "3",
        "--join-at",
        "10",
        "--out",
        &d("run"),
    ]);
    assert!(printed.contains("robot 3 joined"), "{printed}");
    let m = json(&dir.path().join("run/metrics.json"));
    let j = &m["joiners"][0];
    assert_eq!(j["id"], "3");
    assert!(j["joined_at"].as_f64().unwrap() >= 10.0, "{j}");
    assert!(j["dropped_before_join"].as_u64().unwrap() > 0, "{j}");
    assert_eq!(j["localization"]["converged"], true);
    // A robot the log does not have is an error that names it.
    let out = fleetslam(&[
        "run",
        &d("sim/log.ndjson"),
        "--unknown",
        "nobody",
        "--out",
        &d("bad"),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("nobody"));
}

#[test]
fn experiment_rtpf_writes_its_tables_and_plot() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rtpf");
    let printed = ok(&[
        "experiment",
        "rtpf",
        "--seeds",
        "2",
        "--windows",
        "2,4",
        "--samples",
        "400",
        "--records",
        "60",
        "--out",
        &out.to_string_lossy(),
    ]);
    assert!(printed.contains("rtpf speedup over skip"), "{printed}");
    assert!(printed.contains("lost the true place"), "{printed}");
    for f in [
        "errors.csv",
        "times.csv",
        "diagnostics.csv",
        "speedup.csv",
        "rtpf.png",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let times = std::fs::read_to_string(out.join("times.csv")).unwrap();
    // The baseline and 4 policies x 2 windows.
    assert_eq!(times.lines().count(), 1 + 1 + 8, "{times}");
    let diag = std::fs::read_to_string(out.join("diagnostics.csv")).unwrap();
    assert_eq!(diag.lines().count(), 1 + 1 + 8, "{diag}");
    // One speedup per window, with its bootstrap interval around it.
    let speedup = std::fs::read_to_string(out.join("speedup.csv")).unwrap();
    assert!(speedup.starts_with("window,skip_time_s,rtpf_time_s,speedup_rtpf_over_skip,speedup_ci95_low,speedup_ci95_high\n"), "{speedup}");
    assert_eq!(speedup.lines().count(), 1 + 2, "{speedup}");
    for line in speedup.lines().skip(1) {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        assert!(v[4] <= v[3] && v[3] <= v[5], "{line}");
    }
    let png = std::fs::read(out.join("rtpf.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");

    // An ablation without the baseline: only the policies' runs.
    let lean = dir.path().join("lean");
    ok(&[
        "experiment",
        "rtpf",
        "--seeds",
        "2",
        "--windows",
        "2",
        "--policies",
        "skip",
        "--samples",
        "400",
        "--records",
        "60",
        "--no-baseline",
        "--out",
        &lean.to_string_lossy(),
    ]);
    let times = std::fs::read_to_string(lean.join("times.csv")).unwrap();
    assert_eq!(times.lines().count(), 1 + 1, "{times}");
    assert!(
        times.lines().nth(1).unwrap().starts_with("skip,2,2,"),
        "{times}"
    );
}

#[test]
fn localize_in_a_finished_runs_map() {
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_string_lossy().into_owned();
    ok(&[
        "simulate",
        "--robots",
        "2",
        "--duration",
        "60",
        "--seed",
        "8",
        "--out",
        &d("sim"),
    ]);
    ok(&[
        "run",
        &d("sim/log.ndjson"),
        "--particles",
        "50",
        "--out",
        &d("map"),
    ]);
    let before = std::fs::read_to_string(d("map/landmarks.csv")).unwrap();
    let out = ok(&[
        "localize",
        &d("sim/log.ndjson"),
        "--map",
        &d("map"),
        "--out",
        &d("loc"),
        "--seed",
        "1",
    ]);
    assert!(out.contains("robot 1: localized at"), "{out}");
    let summary = json(&dir.path().join("loc/localization.json"));
    for r in summary["robots"].as_array().unwrap() {
        assert_eq!(r["converged"], true, "{summary}");
    }
    // The localized trajectories end near the truth; the map is unchanged.
    let eval = ok(&[
        "evaluate",
        &d("loc"),
        "--truth",
        &d("sim/truth"),
        "--align",
        "none",
    ]);
    let e = json(&dir.path().join("loc/evaluation.json"));
    let ate = e["team"]["ate_rmse"].as_f64().unwrap();
    assert!(ate < 1.5, "localization ATE {ate} m: {eval}");
    assert_eq!(
        before,
        std::fs::read_to_string(d("map/landmarks.csv")).unwrap()
    );
    let bad = fleetslam(&[
        "localize",
        &d("sim/log.ndjson"),
        "--map",
        &d("nowhere"),
        "--out",
        &d("x"),
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("reading the map"));
}

/// A `--config` file's fields hold unless their flag is given (`simulate`, `run` and
/// `experiment rtpf` once let the flags' defaults overwrite them).
#[test]
fn config_files_keep_their_fields_unless_a_flag_is_given() {
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_string_lossy().into_owned();
    std::fs::write(
        dir.path().join("sim.json"),
        r#"{"robots": 2, "landmarks": 7, "duration": 5.0, "seed": 9}"#,
    )
    .unwrap();
    let config = d("sim.json");
    let sim = |out: &str, extra: &[&str]| {
        let out = d(out);
        let mut args = vec!["simulate", "--config", &config, "--out", &out];
        args.extend_from_slice(extra);
        ok(&args);
        let log = std::fs::read_to_string(dir.path().join(&out).join("log.ndjson")).unwrap();
        let header: serde_json::Value = serde_json::from_str(log.lines().next().unwrap()).unwrap();
        let last: serde_json::Value = serde_json::from_str(log.lines().last().unwrap()).unwrap();
        let landmarks =
            std::fs::read_to_string(dir.path().join(&out).join("truth/landmarks.csv")).unwrap();
        (
            header["robots"].as_array().unwrap().len(),
            landmarks.lines().count() - 1,
            last["t"].as_f64().unwrap(),
        )
    };
    let (robots, landmarks, t_end) = sim("a", &[]);
    assert_eq!((robots, landmarks), (2, 7));
    assert!(t_end <= 5.0 + 1e-9, "last record at {t_end}");
    // A flag given wins over the file; the file's other fields stay.
    let (robots, landmarks, _) = sim("b", &["--robots", "3"]);
    assert_eq!((robots, landmarks), (3, 7));

    // `run`: the file's particle count holds; a file naming a learned updater needs its
    // model file.
    std::fs::write(dir.path().join("run.json"), r#"{"particles": 30}"#).unwrap();
    ok(&[
        "run",
        &d("a/log.ndjson"),
        "--config",
        &d("run.json"),
        "--out",
        &d("run"),
    ]);
    let m = json(&dir.path().join("run/metrics.json"));
    assert_eq!(m["particles"].as_u64(), Some(30), "{m}");
    std::fs::write(dir.path().join("mlp.json"), r#"{"updater": "mlp-x"}"#).unwrap();
    let err = fails(&[
        "run",
        &d("a/log.ndjson"),
        "--config",
        &d("mlp.json"),
        "--out",
        &d("r2"),
    ]);
    assert!(err.contains("mlp-x") && err.contains("--updater"), "{err}");

    // `experiment rtpf`: the file's seeds, windows, policies and sizes hold.
    std::fs::write(
        dir.path().join("rtpf.json"),
        r#"{"seeds": 1, "windows": [3], "policies": ["skip"], "samples": 200, "records": 30}"#,
    )
    .unwrap();
    let out = dir.path().join("rtpf");
    ok(&[
        "experiment",
        "rtpf",
        "--config",
        &d("rtpf.json"),
        "--out",
        &out.to_string_lossy(),
    ]);
    let times = std::fs::read_to_string(out.join("times.csv")).unwrap();
    // The header, the baseline and skip at window 3.
    assert_eq!(times.lines().count(), 3, "{times}");
}
