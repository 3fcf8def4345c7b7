//! Shared by the command's tests: run `fleetslam`, read its JSON, start `fleetslam serve`.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};

/// `GET url` as JSON; null when the server cannot be reached or answers no JSON.
pub fn get_json(rt: &tokio::runtime::Runtime, url: &str) -> serde_json::Value {
    rt.block_on(async {
        match reqwest::get(url).await {
            Ok(r) => r.json().await.unwrap_or(serde_json::Value::Null),
            Err(_) => serde_json::Value::Null,
        }
    })
}

pub fn fleetslam(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fleetslam"))
        .args(args)
        .output()
        .expect("running fleetslam")
}

/// Runs `fleetslam args`, which must succeed; returns its standard output.
pub fn ok(args: &[&str]) -> String {
    let out = fleetslam(args);
    assert!(
        out.status.success(),
        "fleetslam {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `fleetslam args`, which must fail; returns its standard error.
pub fn fails(args: &[&str]) -> String {
    let out = fleetslam(args);
    assert!(
        !out.status.success(),
        "fleetslam {args:?} succeeded:\n{}",
        String::from_utf8_lossy(&out.stdout)
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

pub fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// A `fleetslam serve` process, killed (SIGKILL) on drop.
pub struct Server(pub Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `fleetslam serve --bind BIND` with `store` arguments (`--data-dir DIR` or
/// `--database-url URL`); returns once it listens, with its base URL.
pub fn serve(bind: &str, store: &[&str]) -> (Server, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_fleetslam"))
        .args(["serve", "--bind", bind])
        .args(store)
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
        .unwrap_or_else(|| panic!("the server did not start: {line:?}"))
        .to_string();
    (Server(child), url)
}

/// The log exported to `exported` holds exactly `n` records, none of them twice.
pub fn assert_stored_once(exported: &Path, n: usize, what: &str) {
    let stored = std::fs::read_to_string(exported.join("log.ndjson")).unwrap();
    let mut keys: Vec<(String, u64)> = stored
        .lines()
        .skip(1)
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            (
                v["robot"].as_str().unwrap().to_string(),
                v["seq"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(keys.len(), n, "{what}: every acknowledged record stored");
    keys.sort();
    keys.dedup();
    assert_eq!(keys.len(), n, "{what}: a record is stored twice");
}

/// Runs `log` offline (`fleetslam run --particles 50 --seed 5`, the replays' settings)
/// into `offline`; the exported 3 trajectories and landmarks must equal it byte for byte.
pub fn assert_equals_offline(log: &Path, exported: &Path, offline: &Path, what: &str) {
    ok(&[
        "run",
        log.to_str().unwrap(),
        "--particles",
        "50",
        "--seed",
        "5",
        "--out",
        offline.to_str().unwrap(),
    ]);
    let mut compared = 0;
    for entry in std::fs::read_dir(offline).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        if name.ends_with(".tum") || name == "landmarks.csv" {
            let want = std::fs::read_to_string(offline.join(&name)).unwrap();
            let got = std::fs::read_to_string(exported.join(&name)).unwrap();
            assert!(want == got, "{what}: {name} differs from the offline run");
            compared += 1;
        }
    }
    assert_eq!(compared, 4, "3 trajectories and the landmarks");
}
