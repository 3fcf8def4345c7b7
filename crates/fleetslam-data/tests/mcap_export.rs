//! The MCAP export read back with the `mcap` crate: channels, schemas, message counts and
//! time range of a simulated run with its ground truth.

use fleetslam_core::config::FilterConfig;
use fleetslam_core::filter::FastSlam;
use fleetslam_data::mcap::{McapError, write_mcap};
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_data::sim::{SimConfig, simulate};
use std::collections::BTreeMap;

#[test]
fn mcap_export_reads_back_with_every_topic() {
    let sim = simulate(&SimConfig {
        robots: 2,
        landmarks: 6,
        duration: 10.0,
        seed: 3,
        ..SimConfig::default()
    })
    .unwrap();
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 20;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    let est = &out.estimate;
    let bytes = write_mcap(est, Some(&sim.truth)).unwrap();

    let mut count: BTreeMap<String, (String, usize)> = BTreeMap::new();
    let (mut first, mut last) = (u64::MAX, 0u64);
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let schema = m.channel.schema.as_ref().map(|s| s.name.clone()).unwrap();
        count
            .entry(m.channel.topic.clone())
            .or_insert((schema, 0))
            .1 += 1;
        first = first.min(m.log_time);
        last = last.max(m.log_time);
    }
    let poses = |r: &str| est.trajectories[r].len();
    let truth_poses = |r: &str| sim.truth.trajectories[r].len();
    let want: BTreeMap<String, (String, usize)> = [
        ("/tf", "foxglove.FrameTransform", poses("1") + poses("2")),
        ("/robot/1/pose", "foxglove.PoseInFrame", poses("1")),
        ("/robot/2/pose", "foxglove.PoseInFrame", poses("2")),
        ("/truth/1/pose", "foxglove.PoseInFrame", truth_poses("1")),
        ("/truth/2/pose", "foxglove.PoseInFrame", truth_poses("2")),
        ("/landmarks", "foxglove.SceneUpdate", 1),
        ("/truth/landmarks", "foxglove.SceneUpdate", 1),
    ]
    .into_iter()
    .map(|(t, s, n)| (t.to_string(), (s.to_string(), n)))
    .collect();
    assert_eq!(count, want);
    // The time range is the run's: its first pose to its last (estimate or truth), in ns.
    let times: Vec<f64> = est
        .trajectories
        .values()
        .chain(sim.truth.trajectories.values())
        .flatten()
        .map(|p| p.t)
        .collect();
    let ns = |t: f64| (t * 1e9).round() as u64;
    let t0 = times.iter().copied().fold(f64::INFINITY, f64::min);
    let t1 = times.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    assert!(first.abs_diff(ns(t0)) <= 1, "{first} vs {t0}");
    assert!(last.abs_diff(ns(t1)) <= 1, "{last} vs {t1}");

    // A run whose times are negative cannot be written, and says so.
    let mut bad = est.clone();
    bad.trajectories.get_mut("1").unwrap()[0].t = -1.0;
    assert!(matches!(write_mcap(&bad, None), Err(McapError::Time(t)) if t == -1.0));
}
