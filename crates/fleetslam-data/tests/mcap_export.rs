//! The MCAP export read back with the `mcap` crate: channels, schemas, message counts and
//! time range of a simulated run with its ground truth.

use fleetslam_core::config::FilterConfig;
use fleetslam_core::filter::FastSlam;
use fleetslam_data::mcap::{McapError, McapRun, write_mcap};
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
    // A filter series (one point per pose of robot 1) and a particle sample per robot.
    let series: Vec<[f64; 4]> = est.trajectories["1"]
        .iter()
        .enumerate()
        .map(|(k, p)| [p.t, 20.0 - k as f64 * 0.01, 0.5, k as f64])
        .collect();
    let particles: BTreeMap<String, Vec<[f64; 4]>> = (0..2)
        .map(|i| {
            let id = slam.robots()[i].id.clone();
            let sample = slam
                .particle_sample(i, 7)
                .into_iter()
                .map(|(p, w)| [p.x, p.y, p.theta, w])
                .collect();
            (id, sample)
        })
        .collect();
    let bytes = write_mcap(&McapRun {
        estimate: est,
        truth: Some(&sim.truth),
        series: &series,
        particles: &particles,
    })
    .unwrap();

    let mut count: BTreeMap<String, (String, usize)> = BTreeMap::new();
    let (mut first, mut last) = (u64::MAX, 0u64);
    let mut filter_msgs: Vec<serde_json::Value> = Vec::new();
    let mut sample_sizes: BTreeMap<String, usize> = BTreeMap::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let schema = m.channel.schema.as_ref().map(|s| s.name.clone()).unwrap();
        if m.channel.topic == "/filter" {
            assert_eq!(m.channel.message_encoding, "json");
            assert_eq!(m.channel.schema.as_ref().unwrap().encoding, "jsonschema");
            filter_msgs.push(serde_json::from_slice(&m.data).unwrap());
        }
        if schema == "foxglove.PosesInFrame" {
            let msg =
                <foxglove::schemas::PosesInFrame as foxglove::Decode>::decode(&m.data[..]).unwrap();
            sample_sizes.insert(m.channel.topic.clone(), msg.poses.len());
        }
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
        ("/robot/1/particles", "foxglove.PosesInFrame", 1),
        ("/robot/2/particles", "foxglove.PosesInFrame", 1),
        ("/filter", "fleetslam.FilterStats", series.len()),
        ("/truth/landmarks", "foxglove.SceneUpdate", 1),
    ]
    .into_iter()
    .map(|(t, s, n)| (t.to_string(), (s.to_string(), n)))
    .collect();
    assert_eq!(count, want);
    // Each sample arrives whole; each filter point as its fields, in order.
    for (i, r) in ["1", "2"].iter().enumerate() {
        assert_eq!(
            sample_sizes[&format!("/robot/{r}/particles")],
            particles[slam.robots()[i].id.as_str()].len()
        );
    }
    assert!(particles.values().all(|s| s.len() == 7));
    for (m, p) in filter_msgs.iter().zip(&series) {
        assert_eq!(
            [&m["t"], &m["ess"], &m["step_ms"], &m["landmarks"]].map(|v| v.as_f64().unwrap()),
            *p
        );
    }
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
    assert!(matches!(
        write_mcap(&McapRun::estimate(&bad)),
        Err(McapError::Time(t)) if t == -1.0
    ));
}
