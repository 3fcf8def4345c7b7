//! The learned updater end to end: training reduces the error, models round-trip, the plain
//! path equals burn's forward pass, mismatched models are refused, the recorder is
//! deterministic, and an MLP inside FastSLAM stays finite and close to the EKF.

use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use fleetslam_core::updater::{LandmarkUpdater, UpdateOutput};
use fleetslam_data::evaluate::{EvalOptions, evaluate};
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_data::sim::{SimConfig, simulate};
use fleetslam_learned::dataset::synthetic_rows;
use fleetslam_learned::model::MlpModel;
use fleetslam_learned::training::{
    BurnMlp, BurnPredictor, TrainConfig, Trained, save_model_dir, train,
};
use fleetslam_learned::{
    InputLayout, LearnedError, MlpUpdater, RecordingConfig, RecordingUpdater, TrainingRow,
};
use std::sync::{Arc, OnceLock};

fn noise() -> SensorNoise {
    SensorNoise {
        range: 0.1,
        bearing: 0.03,
        xyz: [0.05; 3],
    }
}

fn small_config(id: &str) -> TrainConfig {
    let mut c = TrainConfig::default_preset(id);
    c.hidden = vec![24, 24];
    c.epochs = 40;
    c.batch_size = 128;
    c.patience = 10;
    c
}

/// One small model, trained once for the tests that only need a model.
fn trained_2d() -> &'static Trained {
    static T: OnceLock<Trained> = OnceLock::new();
    T.get_or_init(|| {
        let rows = synthetic_rows(LandmarkKind::RangeBearing2d, &noise(), 4000, 1);
        train(&rows, &small_config("test-2d"), |_, _, _, _| {}).unwrap()
    })
}

#[test]
fn training_reduces_validation_error_below_a_bound() {
    let t = trained_2d();
    let r = &t.report;
    assert!(
        r.best_val_loss < 0.1 * r.first_val_loss,
        "validation loss {} -> {}",
        r.first_val_loss,
        r.best_val_loss
    );
    // The updater's posterior mean is much closer to the EKF's than not updating.
    assert!(
        r.updater.mean_rmse < 0.3 * r.updater.no_update_rmse,
        "{:?}",
        r.updater
    );
    // The sensor noise was recovered from the EKF's updates.
    assert!(
        (r.noise.range - 0.1).abs() < 1e-6 && (r.noise.bearing - 0.03).abs() < 1e-6,
        "{:?}",
        r.noise
    );
    // Likelihood and Mahalanobis distance are the EKF's closed form.
    assert!(r.updater.log_likelihood_rmse < 1e-6 && r.updater.mahalanobis2_rmse < 1e-6);
    assert_eq!(r.updater.rejected, 0);
}

#[test]
fn paper_preset_trains_a_two_neuron_identity_network() {
    let rows = synthetic_rows(LandmarkKind::Point3d, &noise(), 1500, 2);
    let mut c = TrainConfig::paper("test-paper");
    c.epochs = 15;
    let t = train(&rows, &c, |_, _, _, _| {}).unwrap();
    assert_eq!(t.model.hidden(), vec![2]);
    assert_eq!(t.model.layout.dims(LandmarkKind::Point3d), (9, 4));
    assert!(t.report.best_val_loss.is_finite());
    assert!(t.report.best_val_loss <= t.report.first_val_loss);
}

#[test]
fn saved_model_reloads_and_predicts_identically() {
    let t = trained_2d();
    let dir = tempfile::tempdir().unwrap();
    save_model_dir(dir.path(), t).unwrap();
    let loaded = MlpModel::read_path(&dir.path().join("model.json")).unwrap();
    assert_eq!(loaded, t.model);
    let rows = synthetic_rows(LandmarkKind::RangeBearing2d, &noise(), 300, 9);
    let inputs: Vec<_> = rows.iter().map(TrainingRow::input).collect();
    let (a, b) = (
        MlpUpdater::new(t.model.clone()).unwrap(),
        MlpUpdater::new(loaded.clone()).unwrap(),
    );
    let mut oa = vec![UpdateOutput::default(); inputs.len()];
    let mut ob = oa.clone();
    a.update_batch(&inputs, &mut oa);
    b.update_batch(&inputs, &mut ob);
    assert_eq!(oa, ob);
    // burn's own record reloads to the same weights.
    let net = BurnMlp::load_burnpack(
        &loaded,
        &dir.path().join("model.bpk"),
        &burn::tensor::Device::flex(),
    )
    .unwrap();
    assert_eq!(net.dense_layers().unwrap(), t.model.layers);
}

#[test]
fn plain_forward_matches_burn_forward() {
    let t = trained_2d();
    let (n_in, n_out) = t.model.layout.dims(t.model.kind);
    let n = 500;
    let x: Vec<f32> = (0..n * n_in)
        .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
        .collect();
    let burn = BurnPredictor::new(&t.model).forward_normalized(&x);
    let mut y = vec![0f32; n_out];
    let mut worst = 0f32;
    for (k, xi) in x.chunks_exact(n_in).enumerate() {
        t.model.forward_normalized(xi, &mut y);
        for j in 0..n_out {
            worst = worst.max((y[j] - burn[k * n_out + j]).abs());
        }
    }
    assert!(worst < 1e-4, "largest difference {worst}");
}

#[test]
fn mismatched_models_are_refused() {
    let m = trained_2d().model.clone();
    // Another landmark kind.
    let e = MlpUpdater::for_kind(m.clone(), LandmarkKind::Point3d).unwrap_err();
    assert!(matches!(e, LearnedError::KindMismatch { .. }), "{e}");
    assert!(e.to_string().contains("range_bearing_2d"), "{e}");
    // Another input layout version.
    let mut v = m.clone();
    v.layout_version += 1;
    assert!(matches!(
        MlpUpdater::new(v).unwrap_err(),
        LearnedError::LayoutMismatch { .. }
    ));
    // Another layout than its weights were trained for.
    let mut l = m.clone();
    l.layout = InputLayout::Paper;
    assert!(matches!(
        MlpUpdater::new(l).unwrap_err(),
        LearnedError::LayoutMismatch { .. }
    ));
    // A model file of another kind than it claims (read back through JSON).
    let mut json: serde_json::Value = serde_json::from_slice(&m.to_json()).unwrap();
    json["kind"] = "point3d".into();
    let e = MlpModel::from_json(&serde_json::to_vec(&json).unwrap()).unwrap_err();
    assert!(matches!(e, LearnedError::LayoutMismatch { .. }), "{e}");
    // Garbage and unknown fields.
    assert!(matches!(
        MlpModel::from_json(b"{").unwrap_err(),
        LearnedError::Model(_)
    ));
    json["kind"] = "range_bearing_2d".into();
    json["extra"] = 1.into();
    assert!(matches!(
        MlpModel::from_json(&serde_json::to_vec(&json).unwrap()).unwrap_err(),
        LearnedError::Model(_)
    ));
    // A run with another id or another sensor noise.
    let mut cfg = FilterConfig {
        landmark_kind: LandmarkKind::RangeBearing2d,
        sensor_noise: noise(),
        updater: "other".into(),
        ..FilterConfig::default()
    };
    assert!(MlpUpdater::for_run(m.clone(), &cfg).is_err());
    cfg.updater = m.id.clone();
    assert!(MlpUpdater::for_run(m.clone(), &cfg).is_ok());
    cfg.sensor_noise.range *= 2.0;
    assert!(MlpUpdater::for_run(m, &cfg).is_err());
}

fn small_sim(kind: LandmarkKind, seed: u64) -> fleetslam_data::sim::Simulated {
    simulate(&SimConfig {
        robots: 2,
        landmarks: 15,
        kind,
        duration: 30.0,
        seed,
        ..SimConfig::default()
    })
    .unwrap()
}

fn recorded_run(threads: usize, rate: f64, cap: usize) -> (Vec<TrainingRow>, u64) {
    let sim = small_sim(LandmarkKind::RangeBearing2d, 4);
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 100;
    let ekf: Arc<dyn LandmarkUpdater> =
        Arc::new(EkfUpdater::new(cfg.landmark_kind, &cfg.sensor_noise));
    let rec = Arc::new(RecordingUpdater::new(ekf, RecordingConfig { rate, cap, seed: 5 }).unwrap());
    let mut slam = FastSlam::with_updater(cfg, rec.clone()).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap());
    (rec.drain_rows(), rec.seen())
}

#[test]
fn recorder_is_deterministic_and_respects_rate_and_cap() {
    let (a, seen) = recorded_run(1, 0.05, usize::MAX);
    let (b, _) = recorded_run(2, 0.05, usize::MAX);
    let (c, _) = recorded_run(4, 0.05, usize::MAX);
    assert!(!a.is_empty());
    assert_eq!(a, b);
    assert_eq!(a, c);
    let frac = a.len() as f64 / seen as f64;
    assert!((0.035..0.065).contains(&frac), "kept {} of {seen}", a.len());
    // A cap keeps the same rows whatever the threads: the lowest hashes, i.e. a prefix.
    let (capped, _) = recorded_run(2, 0.05, 100);
    assert_eq!(capped.len(), 100);
    assert_eq!(&capped[..], &a[..100]);
    let (none, _) = recorded_run(2, 0.0, 1000);
    assert!(none.is_empty());
    // Rows round-trip through JSON (the store keeps them as strings).
    for r in &a[..10] {
        assert_eq!(TrainingRow::from_json(&r.to_json()).unwrap(), *r);
    }
}

#[test]
fn mlp_inside_fastslam_stays_finite_and_close_to_the_ekf() {
    // Train on the EKF's updates of one simulation, score on another seed's.
    let (rows, _) = recorded_run(2, 0.5, 40_000);
    let mut c = small_config("sim-mlp");
    c.epochs = 60;
    let t = train(&rows, &c, |_, _, _, _| {}).unwrap();
    let sim = small_sim(LandmarkKind::RangeBearing2d, 11);
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 100;
    let run = |u: Arc<dyn LandmarkUpdater>| {
        let mut c = cfg.clone();
        c.updater = u.name().to_string();
        let mut slam = FastSlam::with_updater(c, u).unwrap();
        let out = run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
        assert!(
            out.final_estimate
                .landmarks
                .iter()
                .all(|l| l.gaussian.is_finite())
        );
        evaluate(&out.estimate, &sim.truth, true, &EvalOptions::default())
    };
    let ekf = run(Arc::new(EkfUpdater::new(
        cfg.landmark_kind,
        &cfg.sensor_noise,
    )));
    let mut c2 = cfg.clone();
    c2.updater = t.model.id.clone();
    let mlp = run(Arc::new(MlpUpdater::for_run(t.model.clone(), &c2).unwrap()));
    assert!(mlp.team.ate_rmse.is_finite());
    assert!(
        mlp.team.ate_rmse < 1.5 * ekf.team.ate_rmse + 0.05,
        "MLP ATE {} vs EKF {}",
        mlp.team.ate_rmse,
        ekf.team.ate_rmse
    );
}
