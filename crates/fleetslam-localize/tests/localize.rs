//! Monte Carlo localization, the real-time policies and the late-joiner wrapper on small
//! simulated worlds with landmark ids.

use fleetslam_core::config::FilterConfig;
use fleetslam_core::log::{LandmarkObservation, Record};
use fleetslam_core::math;
use fleetslam_core::motion::{Motion, MotionModel, MotionNoise};
use fleetslam_core::pose::{Pose2, PoseGaussian, wrap_angle};
use fleetslam_core::rng::StandardNormal;
use fleetslam_core::rng::chacha_stream as stream;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise, range_bearing_predict};
use fleetslam_core::updater::LandmarkGaussian;
use fleetslam_localize::config::{KldParams, Window};
use fleetslam_localize::map::MapLandmark;
use fleetslam_localize::{
    LandmarkSet, LateJoinSlam, LocalizeConfig, Localizer, Models, Phase, Policy,
};
use rand::Rng;

const SENSOR: SensorNoise = SensorNoise {
    range: 0.1,
    bearing: 0.03,
    xyz: [0.05; 3],
    range_per_m: 0.0,
};

fn noise() -> MotionNoise {
    MotionNoise {
        trans_per_m: 0.05,
        lateral_per_m: 0.02,
        rot_per_rad: 0.05,
        rot_per_m: 0.02,
        trans_per_sqrt_s: 0.01,
        rot_per_sqrt_s: 0.01,
        random_walk_max_dt: 1.0,
    }
}

fn models() -> Models {
    Models {
        landmark_kind: LandmarkKind::RangeBearing2d,
        motion_model: MotionModel::Odometry,
        motion_noise: noise(),
        ackermann: Default::default(),
        sensor_noise: SENSOR,
    }
}

/// 16 landmarks with ids on a jittered 4 x 4 grid over 16 m x 16 m.
fn landmarks() -> Vec<(u32, [f64; 2])> {
    let mut rng = stream(99, 0, 0);
    (0..16)
        .map(|i| {
            let (gx, gy) = ((i % 4) as f64, (i / 4) as f64);
            (
                i as u32,
                [
                    2.0 + 4.0 * gx + rng.random_range(-1.0..1.0),
                    2.0 + 4.0 * gy + rng.random_range(-1.0..1.0),
                ],
            )
        })
        .collect()
}

fn fixed_map() -> LandmarkSet {
    LandmarkSet::new(
        LandmarkKind::RangeBearing2d,
        landmarks()
            .into_iter()
            .map(|(id, m)| MapLandmark {
                id: Some(id),
                gaussian: LandmarkGaussian {
                    mean: [m[0], m[1], 0.0],
                    cov: [1e-3, 0.0, 0.0, 1e-3, 0.0, 1e-3],
                },
            })
            .collect(),
    )
    .unwrap()
}

/// A robot driving a circle of radius `r` around `c`, one record every 0.5 s, seeing the
/// landmarks within 6 m ahead (half plane) with ids. Returns the records and true poses.
fn circle_robot(
    id: &str,
    c: [f64; 2],
    r: f64,
    phase: f64,
    n: usize,
    t0: f64,
    seed: u64,
) -> (Vec<Record>, Vec<Pose2>) {
    let mut rng = stream(seed, 1, 0);
    let lms = landmarks();
    let v = 1.0; // m/s
    let dt = 0.5;
    let w = v / r;
    let mut pose = Pose2::new(
        c[0] + r * math::cos(phase),
        c[1] + r * math::sin(phase),
        wrap_angle(phase + std::f64::consts::FRAC_PI_2),
    );
    let mut recs = Vec::new();
    let mut truth = Vec::new();
    for k in 0..n {
        let inc = fleetslam_core::motion::velocity_increment(v, w, dt);
        pose = pose.compose(&inc);
        let var = noise().variances(&inc, dt);
        let odo = [
            inc.x + var[0].sqrt() * rng.sample::<f64, _>(StandardNormal),
            inc.y + var[1].sqrt() * rng.sample::<f64, _>(StandardNormal),
            inc.theta + var[2].sqrt() * rng.sample::<f64, _>(StandardNormal),
        ];
        let mut obs = Vec::new();
        for (lid, m) in &lms {
            let (z, _, _) = range_bearing_predict(&pose, m[0], m[1]).unwrap();
            if z[0] < 6.0 && z[1].abs() < std::f64::consts::FRAC_PI_2 {
                obs.push(LandmarkObservation {
                    id: Some(*lid),
                    z: vec![
                        (z[0] + SENSOR.range * rng.sample::<f64, _>(StandardNormal)).max(0.05),
                        wrap_angle(z[1] + SENSOR.bearing * rng.sample::<f64, _>(StandardNormal)),
                    ],
                });
            }
        }
        recs.push(Record {
            robot: id.into(),
            seq: k as u64,
            t: t0 + (k + 1) as f64 * dt,
            motion: Some(Motion::Odometry(odo)),
            landmarks: obs,
            robots: vec![],
        });
        truth.push(pose);
    }
    (recs, truth)
}

#[test]
fn global_localization_converges_from_a_uniform_prior_and_kld_shrinks_the_set() {
    let map = fixed_map();
    let (recs, truth) = circle_robot("r", [8.0, 8.0], 4.0, 0.3, 120, 0.0, 1);
    let cfg = LocalizeConfig {
        max_samples: 4000,
        kld: Some(KldParams::default()),
        ..Default::default()
    };
    let mut loc = Localizer::new(models(), cfg, 7).unwrap();
    let mut first = None;
    let mut converged_at = None;
    let mut last = None;
    for (k, r) in recs.iter().enumerate() {
        let rep = loc.push(r, &map).unwrap().expect("window of one record");
        if first.is_none() {
            first = Some(rep.clone());
        }
        if rep.converged && converged_at.is_none() {
            converged_at = Some(k);
        }
        last = Some((rep, truth[k]));
    }
    let first = first.unwrap();
    // From a uniform prior over ~20 m x 20 m the first update leaves a wide posterior.
    assert!(
        first.position_spread > 2.0,
        "first spread {}",
        first.position_spread
    );
    assert!(!first.converged);
    let k = converged_at.expect("global localization converged");
    assert!(k < 60, "converged only after {k} records");
    let (rep, t) = last.unwrap();
    let err = rep.mean.distance(&t);
    println!(
        "converged after {k} records; final error {err:.3} m, samples {} -> {}",
        first.samples, rep.samples
    );
    assert!(err < 0.3, "final error {err} m");
    // KLD-sampling: the converged filter needs a fraction of the global set.
    assert_eq!(first.samples, 4000);
    assert!(
        rep.samples <= 800,
        "{} samples after convergence",
        rep.samples
    );
    assert!(loc.is_converged());
}

#[test]
fn rtpf_weights_sum_to_one_and_favour_the_informative_observation() {
    let map = fixed_map();
    // A window of 5 records; only the third sees a landmark.
    let (mut recs, _) = circle_robot("r", [8.0, 8.0], 4.0, 0.3, 5, 0.0, 2);
    for (i, r) in recs.iter_mut().enumerate() {
        if i == 2 {
            r.landmarks.truncate(1);
            assert_eq!(r.landmarks.len(), 1, "the robot sees a landmark");
        } else {
            r.landmarks.clear();
        }
    }
    let run = |policy| {
        let mut cfg = LocalizeConfig {
            max_samples: 3000,
            kld: None,
            policy,
            window: Window::Fixed { k: 5 },
            ..Default::default()
        };
        // Enough trajectories that some fall where the sighting is likely, few enough that
        // they do not fill the grouping grid.
        cfg.rtpf.trajectories = 1000;
        let mut loc = Localizer::new(models(), cfg, 3).unwrap();
        let mut rep = None;
        for r in &recs {
            rep = loc.push(r, &map).unwrap();
        }
        rep.expect("the fifth record closes the window")
    };
    let rtpf = run(Policy::Rtpf);
    assert_eq!(rtpf.window, 5);
    let sum: f64 = rtpf.alpha.iter().sum();
    assert!((sum - 1.0).abs() < 1e-9, "weights sum to {sum}");
    assert!(rtpf.alpha.iter().all(|a| *a >= 0.0));
    println!("rtpf weights {:?}", rtpf.alpha);
    let informative = rtpf.alpha[2];
    assert!(
        rtpf.alpha
            .iter()
            .enumerate()
            .all(|(i, a)| i == 2 || *a < informative),
        "{:?}",
        rtpf.alpha
    );
    assert!(informative > 0.4, "{:?}", rtpf.alpha);
    // The uniform mixture keeps 1/k: the difference is the optimisation.
    let uniform = run(Policy::Uniform);
    assert!(uniform.alpha.iter().all(|a| (a - 0.2).abs() < 1e-12));
    // Skip drops nothing here (one observing record); the mixture is tighter than uniform's.
    assert!(rtpf.position_spread < uniform.position_spread);
}

#[test]
fn given_mixture_weights_replace_the_optimised_ones_for_one_update() {
    let map = fixed_map();
    let (recs, _) = circle_robot("r", [8.0, 8.0], 4.0, 0.3, 6, 0.0, 2);
    let cfg = LocalizeConfig {
        max_samples: 600,
        kld: None,
        policy: Policy::Rtpf,
        window: Window::Fixed { k: 3 },
        ..Default::default()
    };
    let mut loc = Localizer::new(models(), cfg.clone(), 3).unwrap();
    for bad in [vec![0.5, 0.5], vec![0.5, 0.6, -0.1], vec![0.2, 0.2, 0.2]] {
        let e = loc.set_next_weights(bad.clone()).unwrap_err().to_string();
        assert!(e.contains("mixture weights"), "{bad:?}: {e}");
    }
    loc.set_next_weights(vec![0.0, 1.0, 0.0]).unwrap();
    let mut reports = Vec::new();
    for r in &recs {
        reports.extend(loc.push(r, &map).unwrap());
    }
    assert_eq!(reports.len(), 2);
    assert_eq!(reports[0].alpha, vec![0.0, 1.0, 0.0]);
    // Without them the first window's weights are the optimised ones.
    let mut plain = Localizer::new(models(), cfg.clone(), 3).unwrap();
    let first = recs[..3]
        .iter()
        .filter_map(|r| plain.push(r, &map).unwrap())
        .next()
        .unwrap();
    assert_ne!(first.alpha, reports[0].alpha);
    assert_eq!(first.alpha.len(), 3);
    // Weights need a fixed window.
    let budget = LocalizeConfig {
        window: Window::Budget {
            samples_per_second: 1000.0,
            max: 4,
        },
        ..cfg
    };
    let mut loc = Localizer::new(models(), budget, 3).unwrap();
    assert!(loc.set_next_weights(vec![1.0]).is_err());
}

#[test]
fn skip_counts_what_it_drops_and_budget_windows_follow_record_times() {
    let map = fixed_map();
    let (recs, _) = circle_robot("r", [8.0, 8.0], 4.0, 0.3, 40, 0.0, 3);
    let cfg = LocalizeConfig {
        max_samples: 1000,
        kld: None,
        policy: Policy::Skip,
        // 1000 samples at 500 samples per second of data: a window spans 2 s, 4 records.
        window: Window::Budget {
            samples_per_second: 500.0,
            max: 10,
        },
        ..Default::default()
    };
    let mut loc = Localizer::new(models(), cfg, 3).unwrap();
    for r in &recs {
        loc.push(r, &map).unwrap();
    }
    let st = loc.stats();
    // The window opens at the first record (t = 0.5): records 0.5..=2.5 form the first
    // window, then every 2 s of data closes one of 4 records; 3 records stay pending.
    let expect: std::collections::BTreeMap<usize, u64> = [(4, 8), (5, 1)].into();
    assert_eq!(st.windows, expect);
    let observing = recs[..37]
        .iter()
        .filter(|r| !r.landmarks.is_empty())
        .count() as u64;
    assert_eq!(st.integrated, 9);
    assert_eq!(st.skipped, observing - 9);
    assert_eq!(loc.status().pending, 3);
}

/// Robot "a" (known start) and robot "b" (unknown start), interleaved in the run's order.
fn two_robot_log() -> (Vec<Record>, Pose2) {
    let (a, _) = circle_robot("a", [7.0, 7.0], 4.0, 0.0, 160, 0.0, 11);
    let (b, _) = circle_robot("b", [9.0, 9.0], 3.0, 2.0, 140, 10.0, 12);
    let mut all: Vec<Record> = a.into_iter().chain(b).collect();
    all.sort_by(fleetslam_core::log::record_order);
    // a's pose at t = 0: on its circle at phase 0, heading along it.
    (all, Pose2::new(7.0 + 4.0, 7.0, std::f64::consts::FRAC_PI_2))
}

fn join_config() -> (FilterConfig, LocalizeConfig) {
    let mut cfg = FilterConfig {
        particles: 40,
        motion_model: MotionModel::Odometry,
        motion_noise: noise(),
        sensor_noise: SENSOR,
        seed: 5,
        ..Default::default()
    };
    cfg.batch_size = 8;
    let loc = LocalizeConfig {
        max_samples: 3000,
        window: Window::Fixed { k: 3 },
        policy: Policy::Rtpf,
        ..Default::default()
    };
    (cfg, loc)
}

fn fresh_run() -> LateJoinSlam {
    let (cfg, loc) = join_config();
    let (_, start_a) = two_robot_log();
    let mut run = LateJoinSlam::new(cfg, loc).unwrap();
    run.add_robot("a", &PoseGaussian::exact(start_a), 0.0)
        .unwrap();
    run.add_unknown_robot("b").unwrap();
    run
}

/// The state as text, without the one wall-clock field.
fn text(run: &LateJoinSlam) -> String {
    let mut s = run.snapshot();
    s.slam.stats.update_nanos = 0;
    serde_json::to_string(&s).unwrap()
}

#[test]
fn late_joiner_localizes_joins_and_maps() {
    let (recs, _) = two_robot_log();
    let mut run = fresh_run();
    let mut phases = vec![];
    let mut joined = None;
    for r in &recs {
        let st = run.step(r).unwrap();
        if r.robot == "b" && phases.last() != Some(&st.phase) {
            phases.push(st.phase);
        }
        if st.joined {
            joined = Some((r.t, st.replayed));
        }
    }
    println!("phases of b: {phases:?}, joined {joined:?}");
    assert_eq!(phases.first(), Some(&Phase::Localizing));
    assert_eq!(phases.last(), Some(&Phase::Mapping));
    assert!(phases.contains(&Phase::Converged));
    let (t, replayed) = joined.expect("b joined");
    assert!(replayed > 0, "records since the streak began are replayed");
    assert!(t < 60.0, "joined at {t}");
    assert_eq!(run.phase("b"), Some(Phase::Mapping));
    assert_eq!(run.slam().robots().len(), 2);
    // Its localizer's counters stay visible.
    let ph = run.phases();
    let b = ph.iter().find(|p| p.id == "b").unwrap();
    assert!(b.joined_at.is_some() && b.localization.is_some());
    // Its mapped pose is near the truth at the end: the circle of b.
    let est = run.slam().estimate();
    let bpose = est.robots.iter().find(|r| r.id == "b").unwrap().mean;
    let (_, tb) = circle_robot("b", [9.0, 9.0], 3.0, 2.0, 140, 10.0, 12);
    let err = bpose.distance(tb.last().unwrap());
    println!("b's final error {err:.3} m");
    assert!(err < 0.5, "b's final error {err} m");
}

#[test]
fn snapshot_round_trip_continues_bit_for_bit() {
    let (recs, _) = two_robot_log();
    let mut whole = fresh_run();
    for r in &recs {
        whole.step(r).unwrap();
    }
    // Stop at several points: while b localizes (with a window pending), and after.
    for cut in [15, 40, recs.len() / 2] {
        let mut first = fresh_run();
        for r in &recs[..cut] {
            first.step(r).unwrap();
        }
        let json = serde_json::to_string(&first.snapshot()).unwrap();
        drop(first);
        let snap = serde_json::from_str(&json).unwrap();
        let mut resumed = LateJoinSlam::from_snapshot_ekf(snap).unwrap();
        for r in &recs[cut..] {
            resumed.step(r).unwrap();
        }
        assert!(
            text(&resumed) == text(&whole),
            "differs after a cut at {cut}"
        );
    }
    assert_eq!(whole.phase("b"), Some(Phase::Mapping));
}

#[test]
fn same_seed_same_result_for_any_thread_count_and_seeds_matter() {
    let (recs, _) = two_robot_log();
    let go = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (mut cfg, loc) = join_config();
            cfg.seed = seed;
            let (_, start_a) = two_robot_log();
            let mut run = LateJoinSlam::new(cfg, loc).unwrap();
            run.add_robot("a", &PoseGaussian::exact(start_a), 0.0)
                .unwrap();
            run.add_unknown_robot("b").unwrap();
            for r in &recs[..120] {
                run.step(r).unwrap();
            }
            text(&run)
        })
    };
    let one = go(1, 5);
    assert!(one == go(2, 5), "thread count changed the result");
    assert!(one == go(1, 5));
    assert!(one != go(1, 6), "another seed gave the same result");
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let map = fixed_map();
    let mut loc = Localizer::new(models(), LocalizeConfig::default(), 1).unwrap();
    let (recs, _) = circle_robot("r", [8.0, 8.0], 4.0, 0.3, 3, 0.0, 1);
    loc.push(&recs[1], &map).unwrap();
    let e = loc.push(&recs[0], &map).unwrap_err().to_string();
    assert!(e.contains("older"), "{e}");
    let mut bad = recs[2].clone();
    bad.landmarks[0].z = vec![f64::NAN, 0.0];
    assert!(loc.push(&bad, &map).is_err());
    let cfg = LocalizeConfig {
        max_samples: 0,
        ..Default::default()
    };
    let e = Localizer::new(models(), cfg, 1).unwrap_err().to_string();
    assert!(e.contains("max_samples"), "{e}");
    let mut run = fresh_run();
    assert!(run.add_unknown_robot("a").is_err());
    assert!(run.add_unknown_robot("b").is_err());
    let stranger = Record {
        robot: "zzz".into(),
        ..recs[0].clone()
    };
    assert!(run.step(&stranger).is_err());
}

#[test]
fn localization_only_in_a_stored_map_leaves_the_map_alone_and_round_trips() {
    use fleetslam_localize::MapLocalization;
    let map = fixed_map();
    let (recs, truth) = circle_robot("r", [8.0, 8.0], 4.0, 1.0, 80, 0.0, 21);
    let new = || {
        let mut m =
            MapLocalization::new(map.clone(), models(), LocalizeConfig::default(), 9).unwrap();
        m.add_robot("r").unwrap();
        m
    };
    let mut whole = new();
    for r in &recs {
        whole.step(r).unwrap();
    }
    assert_eq!(whole.map(), &map, "the stored map never changes");
    let ph = whole.phases();
    assert_eq!(ph[0].phase, Phase::Converged);
    let err = whole
        .localizer("r")
        .unwrap()
        .spread()
        .mean
        .distance(truth.last().unwrap());
    assert!(err < 0.3, "error {err} m");
    // Serialised half-way, restored, continued: the same state.
    let mut first = new();
    for r in &recs[..30] {
        first.step(r).unwrap();
    }
    let json = serde_json::to_string(&first).unwrap();
    let mut resumed: MapLocalization = serde_json::from_str(&json).unwrap();
    resumed.check().unwrap();
    for r in &recs[30..] {
        resumed.step(r).unwrap();
    }
    assert!(resumed == whole);
    // A robot it does not know is an error; a map too small for the configuration too.
    let stranger = Record {
        robot: "x".into(),
        ..recs[0].clone()
    };
    assert!(whole.step(&stranger).is_err());
    let tiny = LandmarkSet::new(LandmarkKind::RangeBearing2d, map.landmarks[..2].to_vec()).unwrap();
    assert!(MapLocalization::new(tiny, models(), LocalizeConfig::default(), 9).is_err());
}
