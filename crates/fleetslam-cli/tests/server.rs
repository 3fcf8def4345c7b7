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
}
