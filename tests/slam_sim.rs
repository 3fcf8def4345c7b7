//! The filter on simulated data: accuracy in 2D and 3D, known and unknown association,
//! spurious landmark removal, robots joining late, and robustness to extreme inputs.

use fleetslam_core::config::{Association, FastSlamVersion, FilterConfig};
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::{LandmarkObservation, Record, RobotSighting};
use fleetslam_core::math;
use fleetslam_core::motion::Motion;
use fleetslam_core::pose::{Pose2, PoseGaussian};
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_data::evaluate::{EvalOptions, evaluate};
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_suite::small_sim;
use proptest::prelude::*;

fn run_and_eval(kind: LandmarkKind, ids: bool, version: FastSlamVersion) -> (f64, f64, usize) {
    let sim = small_sim(3, 40.0, 11, |c| {
        c.kind = kind;
        c.with_ids = ids;
        c.landmarks = 25;
    });
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 100;
    cfg.version = version;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    let ev = evaluate(&out.estimate, &sim.truth, true, &EvalOptions::default());
    println!("{kind:?} ids={ids} {version:?}\n{ev}");
    (
        ev.team.ate_rmse,
        ev.team.landmark_rmse.unwrap(),
        ev.team.landmarks_spurious,
    )
}

#[test]
fn accurate_in_2d_and_3d_with_known_and_unknown_ids() {
    for kind in [LandmarkKind::RangeBearing2d, LandmarkKind::Point3d] {
        for version in [FastSlamVersion::V1, FastSlamVersion::V2] {
            let (ate, lm, _) = run_and_eval(kind, true, version);
            assert!(
                ate < 0.25 && lm < 0.25,
                "{kind:?} {version:?}: ATE {ate}, landmarks {lm}"
            );
        }
        let (ate, lm, spurious) = run_and_eval(kind, false, FastSlamVersion::V2);
        assert!(
            ate < 0.3 && lm < 0.3,
            "{kind:?} unknown ids: ATE {ate}, landmarks {lm}"
        );
        assert!(spurious <= 3, "{kind:?}: {spurious} spurious landmarks");
    }
}

fn one_robot(cfg: FilterConfig) -> FastSlam {
    let mut slam = FastSlam::new(cfg).unwrap();
    slam.add_robot("a", &PoseGaussian::exact(Pose2::default()), 0.0)
        .unwrap();
    slam
}

fn rec(seq: u64, t: f64, landmarks: Vec<LandmarkObservation>) -> Record {
    Record {
        robot: "a".into(),
        seq,
        t,
        motion: Some(Motion::Velocity(vec![[0.0, 0.0, 0.2]])),
        landmarks,
        robots: vec![],
    }
}

fn obs(z: [f64; 2]) -> LandmarkObservation {
    LandmarkObservation {
        id: None,
        z: z.to_vec(),
    }
}

#[test]
fn spurious_landmark_is_removed_real_one_kept() {
    let mut cfg = FilterConfig {
        particles: 20,
        association: Association::Unknown,
        sensor_range: Some(fleetslam_core::log::SensorRange {
            max_range: 10.0,
            fov: 3.0,
        }),
        ..FilterConfig::default()
    };
    cfg.motion_noise.trans_per_sqrt_s = 0.0;
    cfg.motion_noise.rot_per_sqrt_s = 0.0;
    // A ghost seen once (log-odds 1) goes after 3 misses at 0.4.
    cfg.association_params.existence_miss = 0.4;
    let mut slam = one_robot(cfg);
    // A real landmark at (3, 0) seen every time; a ghost at (3, 2) seen once.
    slam.step(&rec(
        0,
        0.2,
        vec![
            obs([3.0, 0.0]),
            obs([13f64.sqrt(), math::atan2(2.0f64, 3.0)]),
        ],
    ))
    .unwrap();
    assert_eq!(slam.particles()[0].map.len(), 2);
    assert_eq!(
        slam.estimate().landmarks.len(),
        0,
        "both are tentative after one sighting"
    );
    for k in 1..10 {
        slam.step(&rec(k, 0.2 * (k + 1) as f64, vec![obs([3.0, 0.0])]))
            .unwrap();
    }
    let est = slam.estimate();
    assert_eq!(est.landmarks.len(), 1, "{:?}", est.landmarks);
    assert!((est.landmarks[0].gaussian.mean[0] - 3.0).abs() < 0.05);
    assert!(slam.stats().landmarks_removed > 0);
}

#[test]
fn robot_added_late_at_a_known_pose_maps_in_the_shared_map() {
    let sim = small_sim(2, 30.0, 4, |_| {});
    let mut log = sim.log.clone();
    log.sort();
    let mut cfg = FilterConfig::from_header(&log.header);
    cfg.particles = 60;
    let mut slam = FastSlam::new(cfg).unwrap();
    let first = &log.header.robots[0];
    slam.add_robot(&first.id, first.start.as_ref().unwrap(), 0.0)
        .unwrap();
    let (early, late): (Vec<_>, Vec<_>) = log.records.iter().partition(|r| r.t < 10.0);
    for r in early.iter().filter(|r| r.robot == first.id) {
        slam.step(r).unwrap();
    }
    let mapped = slam.estimate().landmarks.len();
    // Robot 2 joins at t = 10 s at its true pose then, with some uncertainty.
    let second = &log.header.robots[1].id;
    let truth = sim.truth.trajectories[second]
        .iter()
        .find(|p| p.t >= 10.0 - 1e-9)
        .unwrap()
        .pose;
    slam.add_robot(
        second,
        &PoseGaussian::diagonal(truth, 0.05, 0.05, 0.02),
        10.0 - 1e-9,
    )
    .unwrap();
    for r in late {
        slam.step(r).unwrap();
    }
    let est = slam.estimate();
    assert_eq!(est.robots.len(), 2);
    assert!(est.landmarks.len() >= mapped);
    let end = sim.truth.trajectories[second].last().unwrap().pose;
    let err = est.robots[1].mean.distance(&end);
    assert!(err < 0.3, "late robot ends {err} m from truth");
}

#[test]
fn bad_records_are_refused_without_changing_the_filter() {
    let mut slam = one_robot(FilterConfig {
        particles: 10,
        ..FilterConfig::default()
    });
    slam.step(&rec(0, 1.0, vec![obs([2.0, 0.1])])).unwrap();
    let before = slam.snapshot();
    let mut unknown = rec(1, 2.0, vec![]);
    unknown.robot = "ghost".into();
    assert!(
        slam.step(&unknown)
            .unwrap_err()
            .to_string()
            .contains("ghost")
    );
    assert!(
        slam.step(&rec(1, 0.5, vec![]))
            .unwrap_err()
            .to_string()
            .contains("older")
    );
    let nan = rec(1, 2.0, vec![obs([f64::NAN, 0.0])]);
    assert!(slam.step(&nan).is_err());
    let mut odo = rec(1, 2.0, vec![]);
    odo.motion = Some(Motion::Odometry([1.0, 0.0, 0.0]));
    assert!(
        slam.step(&odo)
            .unwrap_err()
            .to_string()
            .contains("motion model")
    );
    assert_eq!(slam.snapshot(), before);
}

#[test]
fn updater_of_another_kind_is_refused() {
    let ekf3 = fleetslam_core::ekf::EkfUpdater::new(LandmarkKind::Point3d, &Default::default());
    let err =
        FastSlam::with_updater(FilterConfig::default(), std::sync::Arc::new(ekf3)).unwrap_err();
    assert!(err.to_string().contains("point3d"), "{err}");
}

#[test]
fn updater_other_than_the_configured_one_is_refused() {
    let cfg = FilterConfig {
        updater: "mlp-123".into(),
        ..FilterConfig::default()
    };
    let err = FastSlam::new(cfg.clone()).unwrap_err();
    assert!(err.to_string().contains("mlp-123"), "{err}");
    let ekf =
        fleetslam_core::ekf::EkfUpdater::new(LandmarkKind::RangeBearing2d, &Default::default());
    let err = FastSlam::with_updater(cfg, std::sync::Arc::new(ekf)).unwrap_err();
    assert!(err.to_string().contains("\"ekf\""), "{err}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    /// Extreme and conflicting observations never produce NaN, and the invariants hold:
    /// weights normalised, landmark covariances symmetric positive definite.
    #[test]
    fn invariants_hold_under_extreme_observations(
        zs in proptest::collection::vec((1e-3f64..1e5, -10.0f64..10.0, 0u32..4), 1..30),
        v in -50.0f64..50.0, w in -20.0f64..20.0,
        unknown in any::<bool>(), v1 in any::<bool>(),
    ) {
        let cfg = FilterConfig {
            particles: 16,
            batch_size: 5,
            association: if unknown { Association::Unknown } else { Association::Known },
            version: if v1 { FastSlamVersion::V1 } else { FastSlamVersion::V2 },
            ..FilterConfig::default()
        };
        let mut slam = FastSlam::new(cfg).unwrap();
        slam.add_robot("a", &PoseGaussian::diagonal(Pose2::default(), 0.1, 0.1, 0.1), 0.0).unwrap();
        slam.add_robot("b", &PoseGaussian::exact(Pose2::new(1.0, 1.0, 0.0)), 0.0).unwrap();
        for (k, (r, b, id)) in zs.iter().enumerate() {
            let mut record = rec(k as u64, k as f64 * 0.1, vec![LandmarkObservation { id: Some(*id), z: vec![*r, *b] }]);
            record.motion = Some(Motion::Velocity(vec![[v, w, 0.1]]));
            record.robots = vec![RobotSighting { robot: "b".into(), z: vec![*r, *b] }];
            slam.step(&record).unwrap();
            let sum: f64 = slam.particles().iter().map(|p| math::exp(p.log_w)).sum();
            prop_assert!((sum - 1.0).abs() < 1e-9, "weights sum to {}", sum);
            prop_assert!(slam.ess().is_finite() && slam.ess() >= 1.0 - 1e-9);
            for robot in slam.robot_particles() {
                prop_assert!(robot.poses.iter().all(|q| q.is_finite()));
            }
            for p in slam.particles() {
                for (_, l) in p.map.iter() {
                    let c = l.gaussian.cov2();
                    prop_assert!(l.gaussian.is_finite());
                    prop_assert!((c[(0, 1)] - c[(1, 0)]).abs() < 1e-12);
                    prop_assert!(c[(0, 0)] > 0.0 && c.determinant() > 0.0, "cov {:?}", c);
                }
            }
        }
    }
}

#[test]
fn fastslam2_keeps_up_with_1_under_high_control_noise() {
    // The high-control-noise scenario (one robot, 38 landmarks in view, speed noise 0.5 m/s,
    // turn-rate noise 10 deg/s, 10 records/s, accurate sensor), shortened. The full runs
    // are `cargo run --release --example filter_seeds -- control-noise` (README).
    // One seed decides little here (per seed, 2.0's ATE is 0.65-1.8 times 1.0's, its NEES
    // 0.2-18 times): the test compares means over 8 seeds.
    let (mut a1, mut a2, mut n1, mut n2, mut fit_nees) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for seed in CONTROL_NOISE_SEEDS {
        let (log, truth) = fleetslam_suite::experiments::control_noise(seed, 20.0);
        let run = |version| {
            fleetslam_suite::experiments::run_and_evaluate(
                &log,
                &truth,
                50,
                seed,
                version,
                &EvalOptions::default(),
            )
            .0
        };
        let (e1, e2) = (run(FastSlamVersion::V1), run(FastSlamVersion::V2));
        println!("seed {seed}\n1.0: {e1}\n2.0: {e2}");
        a1 += e1.team.ate_rmse;
        a2 += e2.team.ate_rmse;
        n1 += e1.team.landmark_nees.unwrap();
        n2 += e2.team.landmark_nees.unwrap();
        // Almost all of the landmarks' error is the error of the map's frame, which every
        // landmark shares: after the map's own SE(2) fit onto the truth, 2.0's landmark
        // RMSE is 0.019-0.030 m and its NEES 1.39-3.03, within 3 times the dimension.
        let (fit_rmse, nees) = (
            e2.team.landmark_rmse_map_fit.unwrap(),
            e2.team.landmark_nees_map_fit.unwrap(),
        );
        assert!(fit_rmse < 0.03, "seed {seed}: map-fit RMSE {fit_rmse}");
        assert!(nees < 3.5, "seed {seed}: map-fit NEES {nees}");
        fit_nees += nees;
    }
    let n = CONTROL_NOISE_SEEDS.count() as f64;
    let (a1, a2, n1, n2, fit_nees) = (a1 / n, a2 / n, n1 / n, n2 / n, fit_nees / n);
    println!(
        "mean ATE 1.0 {a1:.3} m, 2.0 {a2:.3} m; NEES 1.0 {n1:.0}, 2.0 {n2:.0}; 2.0's map-fit NEES {fit_nees:.2}"
    );
    // Measured (50 particles, 20 s, seeds 1-8; session 31's `libm` functions and normal
    // draws): mean ATE 1.0 0.142 m, 2.0 0.123 m; landmark NEES (of the landmarks' marginals
    // over the particles) 1.0 372, 2.0 351: 2.0 is no less accurate and less over-confident,
    // but neither is consistent (NEES should be near 2); 2.0's map-fit NEES 2.48. Before
    // session 31: 0.143 / 0.139 m, NEES 376 / 306, map-fit 2.19; with the ChaCha8 streams of
    // sessions 1-16: 0.139 / 0.115 m, NEES 337 / 375, map-fit 2.54.
    assert!(a2 <= a1, "mean ATE 2.0 {a2} vs 1.0 {a1}");
    assert!(n2 < n1, "mean NEES 2.0 {n2}, 1.0 {n1}");
    assert!(fit_nees < 2.5, "2.0's mean map-fit NEES {fit_nees}");
}

/// Seeds of the high-control-noise comparison above.
const CONTROL_NOISE_SEEDS: std::ops::RangeInclusive<u64> = 1..=8;

/// Robots whose odometry over-reports distance by 7.5 % and rotation by 5 % (they truly
/// move 0.93 and 0.95 of each commanded increment): with the filter estimating each
/// robot's scales, the trajectories are more accurate than without in most seeds and on
/// average, and the estimated scales move from the prior towards the true ones. Figures of this scenario over 5 seeds and 100 particles
/// are `cargo run --release --example filter_seeds -- sims` ("biased odometry").
#[test]
fn online_odometry_calibration_learns_biased_odometry() {
    use fleetslam_core::config::OdometryCalibration;
    let truth_scale = [0.93, 0.95];
    let mut results = Vec::new();
    for seed in 1..=10 {
        let sim = small_sim(3, 120.0, seed, |c| c.odometry_scale = truth_scale);
        let run = |cal: OdometryCalibration| {
            let mut cfg = FilterConfig::from_header(&sim.log.header);
            cfg.particles = 100;
            cfg.seed = seed;
            cfg.odometry_calibration = cal;
            let mut slam = FastSlam::new(cfg).unwrap();
            let out = run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
            let ev = evaluate(&out.estimate, &sim.truth, true, &EvalOptions::default());
            let scales: Vec<[f64; 2]> = out
                .final_estimate
                .robots
                .iter()
                .map(|r| r.odometry_scale)
                .collect();
            (ev.team.ate_rmse, scales)
        };
        let (off, unit) = run(OdometryCalibration::default());
        let (on, scales) = run(OdometryCalibration {
            distance_std: 0.05,
            rotation_std: 0.05,
            distance_walk_per_sqrt_s: 0.001,
            rotation_walk_per_sqrt_s: 0.001,
        });
        println!("seed {seed}: ATE off {off:.3} m, on {on:.3} m, scales {scales:?}");
        results.push((off, on, unit, scales));
    }
    // Measured, seeds 1-10 (session 31, `libm`'s functions and `fleetslam_core::rng`'s
    // normal draws): ATE off 0.107-0.187 m (mean 0.142), on 0.063-0.240 m (mean 0.121); the
    // calibration helps by more than 10 % in 7 seeds and hurts in 3 (seeds 1, 2 and 5, where
    // a robot's distance scale settles at 1.04-1.08). The robots' distance scales average
    // 0.977 (0.890-1.076 each; truth 0.93, prior mean 1), the rotation scales 0.981 (truth
    // 0.95). Before session 31 (glibc's functions, `rand_distr`'s draws): off mean 0.141 m,
    // on 0.115 m, helped in 7 seeds, scales 0.968 / 0.973. With the ChaCha8 streams of
    // sessions 1-16, seeds 1 and 2 gave 0.098 / 0.076 m against 0.112 / 0.164 m, distance
    // scales 0.940-0.982: a good draw.
    let n = results.len() as f64;
    let (mut off_sum, mut on_sum, mut helped, mut distance, mut rotation) = (0.0, 0.0, 0, 0.0, 0.0);
    for (off, on, unit, scales) in &results {
        assert!(unit.iter().all(|s| *s == [1.0; 2]));
        off_sum += off;
        on_sum += on;
        helped += usize::from(*on < 0.9 * off);
        distance += scales.iter().map(|s| s[0]).sum::<f64>() / scales.len() as f64;
        rotation += scales.iter().map(|s| s[1]).sum::<f64>() / scales.len() as f64;
    }
    let (distance, rotation) = (distance / n, rotation / n);
    println!(
        "mean ATE off {:.3} m, on {:.3} m; helped in {helped} seeds; mean scales {distance:.3} / {rotation:.3}",
        off_sum / n,
        on_sum / n
    );
    assert!(
        on_sum < 0.86 * off_sum,
        "mean ATE on {on_sum} vs off {off_sum} (sums)"
    );
    assert!(helped >= 7, "the calibration helped in {helped} seeds");
    assert!(
        distance < 0.98,
        "mean distance scale {distance} (truth {truth_scale:?})"
    );
    assert!(
        rotation < 0.985,
        "mean rotation scale {rotation} (truth {truth_scale:?})"
    );
}
