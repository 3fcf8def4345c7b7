//! `fleetslam serve` and `fleetslam replay` as separate processes over real HTTP.

mod common;
use std::process::Command;

#[test]
fn replay_into_a_served_run() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let out = Command::new(env!("CARGO_BIN_EXE_fleetslam"))
        .args([
            "simulate",
            "--robots",
            "3",
            "--duration",
            "10",
            "--out",
            sim.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(out.status.success());
    let records = std::fs::read_to_string(sim.join("log.ndjson"))
        .unwrap()
        .lines()
        .count()
        - 1;
    let data = dir.path().join("data");
    let (_server, url) = common::serve("127.0.0.1:0", &["--data-dir", data.to_str().unwrap()]);
    let out = Command::new(env!("CARGO_BIN_EXE_fleetslam"))
        .args([
            "replay",
            sim.join("log.ndjson").to_str().unwrap(),
            "--server",
            &url,
            "--fast",
            "--batch",
            "5",
            "--particles",
            "30",
            "--truth",
            sim.join("truth").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains(&format!(
            "{records} records sent, {records} acknowledged (0 repeats), 0 rejected"
        )),
        "{stdout}"
    );
    assert!(stdout.contains("latency p50"), "{stdout}");
    assert!(
        dir.path().join("data/fleetslam.db").is_file(),
        "the embedded store is created on first start"
    );

    // The run as MCAP (Foxglove's schemas), with the ground truth the replay uploaded.
    let run = stdout
        .lines()
        .find_map(|l| l.strip_prefix("run "))
        .expect("replay names its run");
    let out_dir = dir.path().join("mcap");
    common::ok(&[
        "export",
        run,
        "--server",
        &url,
        "--format",
        "mcap",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    let bytes = std::fs::read(out_dir.join(format!("run-{run}.mcap"))).unwrap();
    let mut topics = std::collections::BTreeMap::<String, (String, usize)>::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let schema = m.channel.schema.as_ref().unwrap().name.clone();
        topics
            .entry(m.channel.topic.clone())
            .or_insert((schema, 0))
            .1 += 1;
    }
    let mut want = vec![
        ("/tf".to_string(), "foxglove.FrameTransform"),
        ("/landmarks".to_string(), "foxglove.SceneUpdate"),
        ("/truth/landmarks".to_string(), "foxglove.SceneUpdate"),
    ];
    want.push(("/filter".to_string(), "fleetslam.FilterStats"));
    for r in 1..=3 {
        want.push((format!("/robot/{r}/pose"), "foxglove.PoseInFrame"));
        want.push((format!("/robot/{r}/particles"), "foxglove.PosesInFrame"));
        want.push((format!("/truth/{r}/pose"), "foxglove.PoseInFrame"));
    }
    for (topic, schema) in &want {
        let (s, n) = topics
            .get(topic)
            .unwrap_or_else(|| panic!("no {topic}: {topics:?}"));
        assert_eq!(s, schema);
        assert!(*n >= 1);
    }
    assert_eq!(topics.len(), want.len(), "{topics:?}");
    assert_eq!(topics["/landmarks"].1, 1);
    // One transform per estimated pose.
    let poses: usize = (1..=3).map(|r| topics[&format!("/robot/{r}/pose")].1).sum();
    assert_eq!(topics["/tf"].1, poses);
    // The filter after every record; one particle sample per robot, at the end.
    assert_eq!(topics["/filter"].1, records);
    for r in 1..=3 {
        assert_eq!(topics[&format!("/robot/{r}/particles")].1, 1);
    }

    // The same series over HTTP, whole, after a time, and thinned.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let get = |path: &str| -> serde_json::Value {
        rt.block_on(async {
            let r = reqwest::get(format!("{url}{path}")).await.unwrap();
            assert!(r.status().is_success(), "{path}: {}", r.status());
            r.json().await.unwrap()
        })
    };
    let all = get(&format!("/v1/runs/{run}/series"));
    assert_eq!(
        all["columns"],
        serde_json::json!(["t", "ess", "step_ms", "landmarks"])
    );
    let pts = all["points"].as_array().unwrap();
    assert_eq!(pts.len(), records);
    let t = |p: &serde_json::Value| p[0].as_f64().unwrap();
    assert!(pts.windows(2).all(|w| t(&w[0]) <= t(&w[1])));
    for p in pts {
        let ess = p[1].as_f64().unwrap();
        assert!(ess > 0.0 && ess <= 30.0 + 1e-9, "{p}");
        assert!(p[2].as_f64().unwrap() >= 0.0, "{p}");
    }
    let mid = t(&pts[pts.len() / 2]);
    let later = get(&format!("/v1/runs/{run}/series?since={mid}"));
    let later = later["points"].as_array().unwrap();
    assert_eq!(
        later.as_slice(),
        &pts[pts.iter().position(|p| t(p) > mid).unwrap()..]
    );
    let thin = get(&format!("/v1/runs/{run}/series?max_points=10"));
    let thin = thin["points"].as_array().unwrap();
    assert_eq!(thin.len(), 10);
    assert_eq!(thin.last(), pts.last());
    // Trajectories too: only the points after a time.
    let whole = get(&format!("/v1/runs/{run}/trajectories"));
    let tail = get(&format!("/v1/runs/{run}/trajectories?since={mid}"));
    for r in 1..=3 {
        let w = whole["robots"][r.to_string()].as_array().unwrap();
        let k = w.iter().position(|p| t(p) > mid).unwrap();
        assert_eq!(
            tail["robots"][r.to_string()].as_array().unwrap().as_slice(),
            &w[k..]
        );
    }
    let bad = rt.block_on(async {
        reqwest::get(format!("{url}/v1/runs/{run}/series?max_points=0"))
            .await
            .unwrap()
    });
    assert_eq!(bad.status(), reqwest::StatusCode::BAD_REQUEST);
}

/// SIGTERM (what `docker stop` sends): the server answers what is under way, stores a final
/// snapshot of each running run and exits 0; started again, the run is back at once from
/// that snapshot, with nothing to replay.
#[test]
fn sigterm_stops_cleanly_with_final_snapshots() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    common::ok(&[
        "simulate",
        "--robots",
        "2",
        "--duration",
        "10",
        "--seed",
        "3",
        "--out",
        sim.to_str().unwrap(),
    ]);
    let records = std::fs::read_to_string(sim.join("log.ndjson"))
        .unwrap()
        .lines()
        .count()
        - 1;
    let data = dir.path().join("data");
    let store = ["--data-dir", data.to_str().unwrap()];
    let (mut server, url) = common::serve("127.0.0.1:0", &store);
    let out = common::ok(&[
        "replay",
        sim.join("log.ndjson").to_str().unwrap(),
        "--server",
        &url,
        "--fast",
        "--particles",
        "30",
        "--keep-open",
    ]);
    let run = out
        .lines()
        .find_map(|l| l.strip_prefix("run "))
        .unwrap_or_else(|| panic!("no run id in {out}"))
        .trim()
        .to_string();
    let state_url = format!("{url}/v1/runs/{run}/state");
    let rt = tokio::runtime::Runtime::new().unwrap();
    let applied = |url: &str| -> u64 {
        rt.block_on(async {
            let v: serde_json::Value = reqwest::get(url).await.unwrap().json().await.unwrap();
            v["applied"].as_u64().unwrap()
        })
    };
    // The robots are silent now: after the reorder window every record is applied.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    while applied(&state_url) < records as u64 {
        assert!(std::time::Instant::now() < deadline, "records not applied");
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    let series = common::get_json(&rt, &format!("{url}/v1/runs/{run}/series"));
    let term = Command::new("kill")
        .args(["-TERM", &server.0.id().to_string()])
        .status()
        .unwrap();
    assert!(term.success());
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    let status = loop {
        if let Some(s) = server.0.try_wait().unwrap() {
            break s;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no exit after SIGTERM"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    assert!(status.success(), "exit status {status}");
    // Back at once: the final snapshot holds every record (without it, the recovered run
    // would first show its registration snapshot's 0 records, then replay them once the
    // 2 s reorder window has passed).
    let (_server, url) = common::serve("127.0.0.1:0", &store);
    assert_eq!(
        applied(&format!("{url}/v1/runs/{run}/state")),
        records as u64
    );
    // The filter's series came back with it, point for point (step times included: none
    // was stepped again).
    let after = common::get_json(&rt, &format!("{url}/v1/runs/{run}/series"));
    assert_eq!(after, series);
    assert_eq!(series["points"].as_array().unwrap().len(), records);
}
