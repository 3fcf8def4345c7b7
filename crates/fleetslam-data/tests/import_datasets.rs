//! The dataset importers through the public API: import a slice, write it, read it back.

use fleetslam_core::log::Log;
use fleetslam_data::formats::Truth;
use fleetslam_data::import::{MrclamOptions, VictoriaOptions, import_mrclam, import_victoria_park};
use std::path::Path;

const DATASETS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/datasets");

fn dataset(name: &str) -> Option<std::path::PathBuf> {
    let p = Path::new(DATASETS).join(name);
    if p.is_dir() {
        Some(p)
    } else {
        assert!(
            !std::env::var("FLEETSLAM_REQUIRE_DATA").is_ok_and(|v| v == "1"),
            "{} is missing and FLEETSLAM_REQUIRE_DATA=1",
            p.display()
        );
        println!("skipped: {} is missing", p.display());
        None
    }
}

#[test]
fn import_mrclam_slice_writes_log_truth_and_report() {
    let Some(dir) = dataset("mrclam-dataset6") else {
        return;
    };
    let opts = MrclamOptions {
        duration: Some(30.0),
        odometry_delay: 0.15,
        ..MrclamOptions::default()
    };
    let imp = import_mrclam(&dir, &opts).expect("import");
    let out = tempfile::TempDir::new().expect("tempdir");
    imp.write(out.path()).expect("write");

    let log = Log::read_path(out.path().join("log.ndjson")).expect("log reads back");
    assert_eq!(log, imp.log);
    let truth = Truth::read_dir(&out.path().join("truth")).expect("truth reads back");
    assert_eq!(truth.trajectories.len(), 5);
    assert_eq!(truth.landmarks.len(), 15);
    let report: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.path().join("import_report.json")).expect("report"),
    )
    .expect("the report is JSON");
    for key in [
        "records",
        "landmark_observations",
        "robot_sightings",
        "misread_barcodes",
        "control_gaps",
        "longest_control_gap",
        "repeated_timestamps",
        "truth_ends_early",
        "detections_dropped",
        "warnings",
    ] {
        assert!(report.get(key).is_some(), "{key} missing from the report");
    }
    assert!(
        imp.report
            .notes
            .iter()
            .any(|n| n.contains("shifted by +0.150 s"))
    );
}

#[test]
fn import_victoria_slice_writes_log_and_gps_truth() {
    let Some(dir) = dataset("victoria-park") else {
        return;
    };
    let opts = VictoriaOptions {
        duration: Some(20.0),
        max_record_interval: 0.25,
        ..VictoriaOptions::default()
    };
    let imp = import_victoria_park(&dir, &opts).expect("import");
    // Scans 0.213 s apart fit in 0.25 s: (almost) every record carries a scan.
    assert!(imp.report.motion_only_records * 10 < imp.report.records);
    assert!(imp.report.warnings.is_empty(), "{:?}", imp.report.warnings);
    let out = tempfile::TempDir::new().expect("tempdir");
    imp.write(out.path()).expect("write");
    let log = Log::read_path(out.path().join("log.ndjson")).expect("log reads back");
    assert_eq!(log, imp.log);
    let truth = Truth::read_dir(&out.path().join("truth")).expect("truth reads back");
    assert!(truth.landmarks.is_empty());
    assert!(truth.trajectories["1"].len() > 50);
}
