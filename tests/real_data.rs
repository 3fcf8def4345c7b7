//! The filter on real data: MRCLAM Dataset 6 (5 robots, known ids) and Victoria Park
//! (unknown association). Shortened slices; the full runs are commands (see README).

use fleetslam_core::config::{Association, FastSlamVersion, FilterConfig, OdometryCalibration};
use fleetslam_core::filter::FastSlam;
use fleetslam_data::evaluate::{EvalOptions, evaluate};
use fleetslam_data::import::{MrclamOptions, VictoriaOptions, import_mrclam, import_victoria_park};
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_suite::{dataset, experiments};

/// Seeds of the 300 s no-ids slice (200 particles): one seed's map is a lottery (README).
const NO_IDS_SEEDS: std::ops::RangeInclusive<u64> = 1..=4;
/// Bound on their mean team ATE (measured 0.245 m since session 31's `libm` functions and
/// normal draws; before, 0.2505 m, and seeds 1-12: 0.253 m).
const NO_IDS_MEAN_ATE_BOUND: f64 = 0.25;
/// Seeds among them that map every group within 0.3 m with no spurious landmark (measured 3
/// of 4, as before session 31; seeds 1-12 then: 10 of 12).
const NO_IDS_PERFECT_SEEDS: usize = 3;
/// The fewest groups any of them maps, and the most spurious landmarks (measured 5 and 1,
/// in seed 1; before session 31 in seed 2).
const NO_IDS_MIN_GROUPS: usize = 5;
const NO_IDS_MAX_SPURIOUS: usize = 1;
/// Bound on the optimal-matching landmark RMSE of a seed that maps every group (measured
/// 0.078, 0.082 and 0.135 m; before session 31, 0.144, 0.134 and 0.090 m).
const NO_IDS_PERFECT_RMSE_BOUND: f64 = 0.15;

#[test]
fn mrclam_five_robots_shared_map_500_particles() {
    let Some(dir) = dataset("mrclam-dataset6") else {
        return;
    };
    let opts = MrclamOptions {
        duration: Some(300.0),
        ..Default::default()
    };
    let imp = import_mrclam(&dir, &opts).unwrap();
    let mut cfg = FilterConfig::from_header(&imp.log.header);
    assert!(
        cfg.odometry_calibration.enabled(),
        "the header suggests calibration"
    );
    // Without the odometry calibration the header suggests: over the first 300 s the scales
    // are not identified yet and their dimensions cost accuracy (seeds 1-4: team ATE mean
    // 0.235 m with, 0.203 m without); they pay on the full run (README).
    cfg.odometry_calibration = OdometryCalibration::default();
    cfg.particles = 500;
    cfg.seed = 1;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, &imp.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    assert!(out.metrics.shared_frame);
    let ev = evaluate(&out.estimate, &imp.truth, true, &EvalOptions::default());
    println!("{ev}");
    assert_eq!(ev.robots.len(), 5);
    // Measured 0.187 m (landmarks 0.115 m, 15/15; robots 0.139-0.240 m) since session 31's
    // elementary functions from `libm` and normal draws from `fleetslam_core::rng`; with
    // glibc's and `rand_distr`'s before, 0.171 m (landmarks 0.073 m; robots 0.132-0.211 m):
    // one draw of the filter's randomness against another (seeds 1-30 of the full run have
    // the same mean either way, README). Before the range noise that grows with the range
    // (the header's suggestion with ids since session 21), with a constant 0.3 m: 0.214 m
    // (landmarks 0.159 m; robots 0.155-0.277 m).
    // Before deferred sampling and the odometry delay, 0.213 m, and seed 2 lost robot 4
    // (0.39 m); dead reckoning is about 2.8 m on the full run.
    assert!(ev.team.ate_rmse < 0.19, "team ATE {} m", ev.team.ate_rmse);
    for (id, r) in &ev.robots {
        assert!(r.ate_rmse < 0.25, "robot {id} ATE {} m", r.ate_rmse);
    }
    let lm = ev.team.landmark_rmse.expect("MRCLAM has landmark truth");
    assert!(lm < 0.12, "landmark RMSE {lm} m");
    assert!(
        ev.team.landmarks_matched == 15,
        "{} landmarks matched",
        ev.team.landmarks_matched
    );
    assert_eq!(ev.team.landmarks_spurious, 0);
}

#[test]
fn mrclam_dead_reckoning_is_far_worse() {
    // The same slice with the observations removed: the filter is only as good as odometry.
    // Guards the test above against passing for the wrong reason.
    let Some(dir) = dataset("mrclam-dataset6") else {
        return;
    };
    let opts = MrclamOptions {
        duration: Some(300.0),
        ..Default::default()
    };
    let mut imp = import_mrclam(&dir, &opts).unwrap();
    for r in &mut imp.log.records {
        r.landmarks.clear();
        r.robots.clear();
    }
    let mut cfg = FilterConfig::from_header(&imp.log.header);
    cfg.particles = 50;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, &imp.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    let ev = evaluate(&out.estimate, &imp.truth, true, &EvalOptions::default());
    assert!(
        ev.team.ate_rmse > 0.5,
        "dead reckoning ATE {} m",
        ev.team.ate_rmse
    );
}

#[test]
fn mrclam_without_ids_maps_each_landmark_group_once() {
    // Without ids the 15 barcodes form 6 groups whose members (0.18-0.25 m apart) no
    // sensor of this noise tells apart: the right map has one landmark per group.
    let Some(dir) = dataset("mrclam-dataset6") else {
        return;
    };
    let imp = experiments::mrclam(&dir, true, Some(300.0), None);
    let cfg = FilterConfig::from_header(&imp.log.header);
    assert_eq!(cfg.association, Association::Unknown);
    let opts = experiments::mrclam_eval_options(true);
    assert_eq!(
        cfg.association_params.min_separation,
        fleetslam_data::import::NO_IDS_LANDMARK_SEPARATION
    );
    // Measured (session 25, the robots' sightings in 2.0's proposal, the default without
    // ids), seeds 1-4: groups mapped within 0.3 m 6, 5, 6, 6 of 6; spurious 0, 1, 0, 0;
    // team ATE 0.233, 0.270, 0.256, 0.243 m; optimal-matching RMSE 0.09-0.21 m. Seeds
    // 1-12: 10 of 12 perfect, mean ATE 0.253 m. Without the sightings in the proposal:
    // seeds 1-4 5, 6, 4, 6 groups, 1, 0, 2, 0 spurious, mean 0.254 m; seeds 1-12 8 of 12
    // perfect. Before deferred sampling, the minimum separation and the odometry delay: 3
    // of 6, 6 spurious, 0.33 m.
    let (mut perfect, mut ate) = (0, 0.0);
    for seed in NO_IDS_SEEDS {
        let (ev, metrics, _) = experiments::run_and_evaluate(
            &imp.log,
            &imp.truth,
            200,
            seed,
            FastSlamVersion::V2,
            &opts,
        );
        println!("seed {seed}: {ev}\n{metrics:?}");
        assert_eq!(ev.landmark_groups, Some(6));
        let t = &ev.team;
        assert!(
            t.landmarks_matched >= NO_IDS_MIN_GROUPS,
            "seed {seed}: {ev}"
        );
        assert!(
            t.landmarks_spurious <= NO_IDS_MAX_SPURIOUS,
            "seed {seed}: {ev}"
        );
        if t.landmarks_matched == 6 && t.landmarks_spurious == 0 {
            perfect += 1;
            let rmse = t.landmark_rmse_optimal.expect("MRCLAM has landmark truth");
            assert!(rmse < NO_IDS_PERFECT_RMSE_BOUND, "seed {seed}: {ev}");
        }
        ate += t.ate_rmse;
    }
    let n = NO_IDS_SEEDS.count() as f64;
    assert!(
        perfect >= NO_IDS_PERFECT_SEEDS,
        "{perfect} seeds map every group"
    );
    assert!(
        ate / n < NO_IDS_MEAN_ATE_BOUND,
        "mean team ATE {} m",
        ate / n
    );
}

#[test]
fn victoria_park_unknown_association_fastslam2() {
    let Some(dir) = dataset("victoria-park") else {
        return;
    };
    let opts = VictoriaOptions {
        duration: Some(150.0),
        ..Default::default()
    };
    let imp = import_victoria_park(&dir, &opts).unwrap();
    let mut cfg = FilterConfig::from_header(&imp.log.header);
    assert_eq!(cfg.association, Association::Unknown);
    cfg.version = FastSlamVersion::V2;
    cfg.particles = 30;
    let mut slam = FastSlam::new(cfg).unwrap();
    let out = run_log(&mut slam, &imp.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    assert!(!out.metrics.shared_frame, "GPS has its own frame");
    let ev = evaluate(&out.estimate, &imp.truth, false, &EvalOptions::default());
    println!("{ev}\n{:?}", out.metrics);
    // Measured: 80 landmarks, ATE against GPS 1.116 m after alignment with session 32's
    // heading noise of 0.005 rad per metre (1.09 m with 0.02; 1.22 m before session 31's
    // `libm` functions and normal draws).
    let n = out.estimate.landmarks.len();
    assert!((65..95).contains(&n), "{n} landmarks");
    assert!(
        out.metrics.landmarks_removed > 0,
        "spurious landmarks are removed"
    );
    assert!(
        ev.team.ate_rmse < 1.2,
        "ATE against GPS {} m",
        ev.team.ate_rmse
    );
}
