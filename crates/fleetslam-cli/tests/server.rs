//! `fleetslam serve` and `fleetslam replay` as separate processes over real HTTP.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `fleetslam serve` on a free port; returns the process and its base URL.
fn serve(data: &std::path::Path) -> (Server, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_fleetslam"))
        .args([
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--data-dir",
            data.to_str().unwrap(),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no URL in {line:?}"))
        .to_string();
    (Server(child), url)
}

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
    let (_server, url) = serve(&dir.path().join("data"));
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
