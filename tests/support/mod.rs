//! Support for the workspace's end-to-end tests: where the shared data sets live and small
//! simulated logs.

use fleetslam_core::log::Log;
use fleetslam_data::sim::{SimConfig, Simulated, simulate};
use std::path::PathBuf;

/// `../shared/datasets/<name>` beside the checkout, if present.
pub fn dataset(name: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("shared")
        .join("datasets")
        .join(name);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("note: {} is missing; skipping", p.display());
        None
    }
}

/// A small simulated log: `robots` robots for `duration` seconds.
pub fn small_sim(
    robots: usize,
    duration: f64,
    seed: u64,
    f: impl FnOnce(&mut SimConfig),
) -> Simulated {
    let mut cfg = SimConfig {
        robots,
        duration,
        seed,
        ..SimConfig::default()
    };
    f(&mut cfg);
    simulate(&cfg).expect("valid simulator config")
}

/// The log as NDJSON text.
pub fn to_ndjson(log: &Log) -> String {
    let mut buf = Vec::new();
    log.write(&mut buf).expect("writing to memory");
    String::from_utf8(buf).expect("JSON is UTF-8")
}
