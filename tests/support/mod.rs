//! Support for the workspace's end-to-end tests: where the shared data sets live and small
//! simulated logs.

use fleetslam_core::log::Log;
use fleetslam_data::sim::{SimConfig, Simulated, simulate};
use std::path::PathBuf;

/// `../shared/datasets/<name>` beside the checkout, if present. Panics when it is missing
/// and `FLEETSLAM_REQUIRE_DATA=1` (CI): the real-data tests must run there, not skip.
pub fn dataset(name: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("shared")
        .join("datasets")
        .join(name);
    if p.is_dir() {
        Some(p)
    } else {
        assert!(
            !std::env::var("FLEETSLAM_REQUIRE_DATA").is_ok_and(|v| v == "1"),
            "{} is missing and FLEETSLAM_REQUIRE_DATA=1 (set by .ci/run) requires it",
            p.display()
        );
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

pub mod experiments {
    //! The filter's accuracy experiments, shared by the tests (short spans, few particles)
    //! and `cargo run --release --example filter_seeds` (the full runs the README reports).

    use fleetslam_core::config::{FastSlamVersion, FilterConfig};
    use fleetslam_core::filter::{Estimate, FastSlam};
    use fleetslam_core::log::{Log, LogHeader};
    use fleetslam_data::evaluate::{EvalOptions, Evaluation, evaluate};
    use fleetslam_data::formats::Truth;
    use fleetslam_data::import::{Imported, MrclamOptions, import_mrclam};
    use fleetslam_data::run::{RunMetrics, RunOutput, TrajectoryEstimate, run_log};
    use fleetslam_data::sim::{SimConfig, simulate};
    use std::path::Path;

    /// MRCLAM's landmark groups: members 0.18-0.25 m apart, groups more than 1 m apart.
    pub const MRCLAM_GROUP_WITHIN: f64 = 0.3;
    /// Without ids a group counts as mapped by a landmark within this distance (m) of its
    /// centre.
    pub const MRCLAM_GROUP_RADIUS: f64 = 0.3;

    /// MRCLAM Dataset 6 (all five robots), with or without landmark ids, optionally cut to
    /// its first `duration` seconds.
    pub fn mrclam(
        dir: &Path,
        no_ids: bool,
        duration: Option<f64>,
        odometry_delay: Option<f64>,
    ) -> Imported {
        let d = MrclamOptions::default();
        let opts = MrclamOptions {
            no_ids,
            duration,
            odometry_delay: odometry_delay.unwrap_or(d.odometry_delay),
            ..d
        };
        import_mrclam(dir, &opts).expect("import MRCLAM")
    }

    /// The time of the log's first record (MRCLAM's robots start their odometry at
    /// different times): where a late joiner's delay is counted from.
    pub fn first_record_time(log: &Log) -> f64 {
        log.records
            .iter()
            .map(|r| r.t)
            .fold(f64::INFINITY, f64::min)
    }

    /// How a run on MRCLAM is evaluated: by id with ids; without, against the truth's
    /// landmark groups, each matched within [`MRCLAM_GROUP_RADIUS`].
    pub fn mrclam_eval_options(no_ids: bool) -> EvalOptions {
        if no_ids {
            EvalOptions {
                group_within: Some(MRCLAM_GROUP_WITHIN),
                landmark_match_radius: MRCLAM_GROUP_RADIUS,
                ..EvalOptions::default()
            }
        } else {
            EvalOptions::default()
        }
    }

    /// The configuration the header suggests, with the fields of
    /// `FLEETSLAM_EXPERIMENT_CONFIG` (FilterConfig fields as JSON) laid over it, to try
    /// settings with the example without editing code.
    pub fn experiment_config(header: &LogHeader) -> FilterConfig {
        let cfg = FilterConfig::from_header(header);
        match std::env::var("FLEETSLAM_EXPERIMENT_CONFIG") {
            Ok(patch) => {
                let patch: serde_json::Value =
                    serde_json::from_str(&patch).expect("FLEETSLAM_EXPERIMENT_CONFIG is JSON");
                fleetslam_core::config::overlay(&cfg, patch).expect("valid config fields")
            }
            Err(_) => cfg,
        }
    }

    /// Runs the log through a filter of the header's configuration with `particles`,
    /// `seed` and `version` (trajectories as the particles' weighted mean).
    pub fn run(log: &Log, particles: usize, seed: u64, version: FastSlamVersion) -> RunOutput {
        let mut cfg = experiment_config(&log.header);
        cfg.particles = particles;
        cfg.seed = seed;
        cfg.version = version;
        let mut slam = FastSlam::new(cfg).expect("valid configuration");
        run_log(&mut slam, log, TrajectoryEstimate::Mean, |_, _| {}).expect("run")
    }

    /// [`run`], and the result evaluated; also returns the filter's final estimate.
    pub fn run_and_evaluate(
        log: &Log,
        truth: &Truth,
        particles: usize,
        seed: u64,
        version: FastSlamVersion,
        opts: &EvalOptions,
    ) -> (Evaluation, RunMetrics, Estimate) {
        let out = run(log, particles, seed, version);
        let ev = evaluate(&out.estimate, truth, out.metrics.shared_frame, opts);
        (ev, out.metrics, out.final_estimate)
    }

    /// The high-control-noise simulation ([`SimConfig::high_control_noise`]) of `seed`.
    pub fn control_noise(seed: u64, duration: f64) -> (Log, Truth) {
        let sim = simulate(&SimConfig::high_control_noise(seed, duration)).expect("valid");
        (sim.log, sim.truth)
    }
}
