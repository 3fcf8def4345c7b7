//! Cost of unknown association against the size of the map (issue 13: it must grow at most
//! logarithmically with M).
//!
//! `association_vs_landmarks/<M>`: one FastSLAM 2.0 step with unknown association, N = 100
//! particles, of a robot standing among M landmarks on a square lattice of 3 m (the map
//! grows in area, its density stays that of a building or a park), observing the 5
//! landmarks nearest to it with a 10 m, 360° sensor (so the existence pass checks the
//! landmarks in view too). Every particle holds the same map (shared, as after a resample),
//! and every iteration steps a fresh clone of the filter, so the step copies the paths it
//! writes. Divide by 5 × N for the cost per particle and observation.

use criterion::{BatchSize, BenchmarkId, Criterion, SamplingMode, criterion_group, criterion_main};
use fleetslam_core::config::Association;
use fleetslam_core::log::{LandmarkObservation, Record, SensorRange};
use fleetslam_core::map::{Landmark, LandmarkMap};
use fleetslam_core::math;
use fleetslam_core::motion::Motion;
use fleetslam_core::updater::LandmarkGaussian;
use fleetslam_core::{FastSlam, FilterConfig, Pose2, PoseGaussian};
use std::time::Duration;

const PARTICLES: usize = 100;
const SPACING: f64 = 3.0;

/// The lattice's landmarks, centred on the origin (the robot stands 0.4 m off a lattice point
/// so that no landmark lies at range zero).
fn lattice(m: usize) -> Vec<[f64; 2]> {
    let side = (m as f64).sqrt().ceil() as usize;
    let half = (side / 2) as f64;
    (0..m)
        .map(|k| {
            let (i, j) = ((k % side) as f64, (k / side) as f64);
            [(i - half) * SPACING, (j - half) * SPACING]
        })
        .collect()
}

fn filter_with_map(m: usize) -> (FastSlam, Record) {
    let cfg = FilterConfig {
        particles: PARTICLES,
        association: Association::Unknown,
        sensor_range: Some(SensorRange {
            max_range: 10.0,
            fov: std::f64::consts::TAU,
        }),
        resample_threshold: 0.0,
        ..Default::default()
    };
    let mut slam = FastSlam::new(cfg).unwrap();
    let start = Pose2::new(0.4, 0.3, 0.0);
    slam.add_robot("r1", &PoseGaussian::exact(start), 0.0)
        .unwrap();
    let points = lattice(m);
    let mut map = LandmarkMap::new();
    for p in &points {
        map.push(Landmark {
            gaussian: LandmarkGaussian {
                mean: [p[0], p[1], 0.0],
                cov: [0.01, 0.0, 0.0, 0.01, 0.0, 0.0],
            },
            id: None,
            existence: 5.0,
            hits: 10,
        });
    }
    let mut snap = slam.snapshot();
    for part in &mut snap.particles {
        part.map = map.clone();
    }
    let slam = FastSlam::from_snapshot(snap, slam.updater().clone()).unwrap();
    let mut near = points.clone();
    let d = |p: &[f64; 2]| math::hypot(p[0] - start.x, p[1] - start.y);
    near.sort_by(|a, b| d(a).total_cmp(&d(b)));
    let rec = Record {
        robot: "r1".into(),
        seq: 0,
        t: 0.1,
        motion: Some(Motion::Velocity(vec![[0.0, 0.0, 0.1]])),
        landmarks: near[..5.min(m)]
            .iter()
            .map(|p| {
                let (dx, dy) = (p[0] - start.x, p[1] - start.y);
                LandmarkObservation {
                    id: None,
                    z: vec![math::hypot(dx, dy) + 0.02, math::atan2(dy, dx) - 0.005],
                }
            })
            .collect(),
        robots: vec![],
    };
    (slam, rec)
}

fn bench_association(c: &mut Criterion) {
    let mut g = c.benchmark_group("association_vs_landmarks");
    g.sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(2));
    for m in [10usize, 100, 1_000, 10_000, 100_000] {
        let (slam, rec) = filter_with_map(m);
        // Every observation matches its landmark: nothing is created or removed.
        let mut check = slam.clone();
        check.step(&rec).unwrap();
        assert_eq!(check.stats().landmarks_created, 0, "M = {m}");
        assert_eq!(check.stats().landmark_updates, (5 * PARTICLES) as u64);
        g.bench_function(BenchmarkId::from_parameter(m), |b| {
            b.iter_batched(
                || slam.clone(),
                |mut s| {
                    s.step(&rec).unwrap();
                    s
                },
                BatchSize::PerIteration,
            )
        });
    }
    g.finish();
}

criterion_group!(benches, bench_association);
criterion_main!(benches);
