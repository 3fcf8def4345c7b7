//! The learned updater end to end: training (split by run) reduces the error, models
//! round-trip, the inference kernel equals burn's forward pass, the posterior does not depend
//! on what the filter asks for or on how items are batched, the structured model's mean is
//! linear in the innovation, mismatched models are refused, the recorder is deterministic,
//! and an MLP inside FastSLAM stays finite and close to the EKF.

use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use fleetslam_core::updater::{LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput};
use fleetslam_data::evaluate::{EvalOptions, evaluate, interpolate};
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_data::sim::{SimConfig, simulate};
use fleetslam_learned::dataset::{synthetic_rows, synthetic_rows_biased};
use fleetslam_learned::kernel::Kernel;
use fleetslam_learned::model::MlpModel;
use fleetslam_learned::training::{
    BurnMlp, BurnPredictor, TrainConfig, Trained, save_model_dir, train,
};
use fleetslam_learned::{
    InputLayout, LearnedError, MlpUpdater, RecordingConfig, RecordingUpdater, TrainingRow,
    label_rows,
};
use std::sync::{Arc, OnceLock};

/// A labelled row's truth lies this close [m] to a true landmark, the difference being the
/// particle's pose error (measured over 5,064 rows: median 0.050 m, 99th percentile 0.163 m,
/// largest 0.248 m).
const LABEL_NEAR: f64 = 0.25;

/// Truth-trained model against the EKF, posterior-mean RMSE to truth on the test run, with
/// a +0.2 m range bias the EKF does not know (twice the range noise). Measured 0.750
/// (0.0726 m against 0.0968 m; the unbiased EKF's is 0.0723 m: the bias is learned whole).
const TRUTH_BIASED_BOUND: f64 = 0.77;
/// The same without a bias, where the EKF is right. Measured 1.004.
const TRUTH_UNBIASED_BOUND: f64 = 1.02;

fn noise() -> SensorNoise {
    SensorNoise {
        range: 0.1,
        bearing: 0.03,
        xyz: [0.05; 3],
        range_per_m: 0.0,
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

/// `n` generated runs of `per_run` updates each (one seed per run).
fn runs(kind: LandmarkKind, n: u64, per_run: usize) -> Vec<Vec<TrainingRow>> {
    (1..=n)
        .map(|seed| synthetic_rows(kind, &noise(), per_run, seed))
        .collect()
}

/// One small model, trained once for the tests that only need a model.
fn trained_2d() -> &'static Trained {
    static T: OnceLock<Trained> = OnceLock::new();
    T.get_or_init(|| {
        let runs = runs(LandmarkKind::RangeBearing2d, 5, 1100);
        train(&runs, &small_config("test-2d"), |_, _, _, _| {}).unwrap()
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
    // Three runs trained, one validated, one tested: whole runs, never rows.
    assert_eq!(
        (r.train_runs.len(), r.val_runs.len(), r.test_runs.len()),
        (3, 1, 1)
    );
    let mut all: Vec<usize> = [&r.train_runs, &r.val_runs, &r.test_runs]
        .into_iter()
        .flatten()
        .copied()
        .collect();
    all.sort_unstable();
    assert_eq!(all, vec![0, 1, 2, 3, 4]);
    assert_eq!(
        r.train_rows + r.val_rows + r.test_rows + r.skipped_rows,
        5500
    );
    assert!(r.val_rows > 1000 && r.test_rows > 1000, "{r:?}");
    // The updater's posterior mean (on the test run) is much closer to the EKF's than not
    // updating.
    let u = r.updater.unwrap();
    assert!(u.mean_rmse < 0.3 * u.no_update_rmse, "{u:?}");
    // The sensor noise was recovered from the EKF's updates.
    assert!(
        (r.noise.range - 0.1).abs() < 1e-6 && (r.noise.bearing - 0.03).abs() < 1e-6,
        "{:?}",
        r.noise
    );
    // Likelihood and Mahalanobis distance are the EKF's closed form.
    assert!(u.log_likelihood_rmse < 1e-6 && u.mahalanobis2_rmse < 1e-6);
    assert_eq!(u.rejected, 0);
}

#[test]
fn paper_preset_trains_a_two_neuron_identity_network() {
    let mut c = TrainConfig::paper("test-paper");
    c.epochs = 15;
    let t = train(&runs(LandmarkKind::Point3d, 3, 500), &c, |_, _, _, _| {}).unwrap();
    assert_eq!(t.model.hidden(), vec![2]);
    // The new coordinates only: the paper's P_ii output is not trained (the covariance is
    // the closed form).
    assert_eq!(t.model.layout.dims(LandmarkKind::Point3d), (9, 3));
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
    a.update_batch(UpdateNeeds::PosteriorAndLikelihood, &inputs, &mut oa);
    b.update_batch(UpdateNeeds::PosteriorAndLikelihood, &inputs, &mut ob);
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
fn inference_kernel_matches_burn_forward() {
    // The network itself: without the training-range clamp (tested in the kernel's unit
    // tests), which burn's forward does not apply.
    let mut m = trained_2d().model.clone();
    m.input_norm.min.clear();
    m.input_norm.max.clear();
    let m = &m;
    let (n_in, n_out) = m.layout.dims(m.kind);
    let n = 500;
    // Standardised inputs for burn; the kernel takes the raw features they stand for.
    let x: Vec<f32> = (0..n * n_in)
        .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
        .collect();
    let burn = BurnPredictor::new(m).forward_normalized(&x);
    let kernel = Kernel::new(m);
    let mut worst = 0f64;
    let mut raw = vec![0.0; n_in];
    let mut y = vec![0.0; n_out];
    for (k, xi) in x.chunks_exact(n_in).enumerate() {
        for i in 0..n_in {
            raw[i] = xi[i] as f64 * m.input_norm.std[i] + m.input_norm.mean[i];
        }
        kernel.predict(&raw, &mut y);
        for j in 0..n_out {
            let b = burn[k * n_out + j] as f64 * m.output_norm.std[j] + m.output_norm.mean[j];
            worst = worst.max((y[j] - b).abs() / m.output_norm.std[j]);
        }
    }
    assert!(worst < 1e-4, "largest difference {worst} output std");
}

/// Models of every layout, trained briefly on generated 2D and 3D updates.
fn layout_models() -> &'static Vec<MlpModel> {
    static M: OnceLock<Vec<MlpModel>> = OnceLock::new();
    M.get_or_init(|| {
        let mut out = Vec::new();
        for kind in [LandmarkKind::RangeBearing2d, LandmarkKind::Point3d] {
            let runs = runs(kind, 3, 600);
            for preset in TrainConfig::PRESETS {
                let mut c =
                    TrainConfig::preset(preset, &format!("{preset}-{}", kind.as_str())).unwrap();
                c.epochs = 4;
                c.hidden = if preset == "paper" {
                    vec![2]
                } else {
                    vec![8, 8]
                };
                out.push(train(&runs, &c, |_, _, _, _| {}).unwrap().model);
            }
        }
        out
    })
}

fn inputs_of(kind: LandmarkKind, n: usize, seed: u64) -> Vec<UpdateInput> {
    synthetic_rows(kind, &noise(), n, seed)
        .iter()
        .map(TrainingRow::input)
        .collect()
}

/// The posterior is the same bits whether the filter asks for the likelihood or not, whether
/// an item is updated alone or in a batch (any lane of a pass) and whether the pass runs with
/// AVX2 or the baseline instruction set; the likelihood, when asked, is the EKF's.
#[test]
fn posterior_depends_neither_on_needs_nor_on_batching() {
    for m in layout_models() {
        let u = MlpUpdater::new(m.clone()).unwrap();
        let ekf = EkfUpdater::new(m.kind, &m.noise);
        let inputs = inputs_of(m.kind, 203, 21);
        let mut full = vec![UpdateOutput::default(); inputs.len()];
        let mut post = full.clone();
        u.update_batch(UpdateNeeds::PosteriorAndLikelihood, &inputs, &mut full);
        u.update_batch(UpdateNeeds::Posterior, &inputs, &mut post);
        for (k, (f, p)) in full.iter().zip(&post).enumerate() {
            assert_eq!(f.posterior, p.posterior, "{} item {k}", m.id);
            assert!(p.log_likelihood.is_nan() && p.mahalanobis2.is_nan());
            let e = ekf.update(&inputs[k]);
            assert!(
                (f.log_likelihood - e.log_likelihood).abs() < 1e-9,
                "{} item {k}: {} vs {}",
                m.id,
                f.log_likelihood,
                e.log_likelihood
            );
            let alone = u.update(&inputs[k]);
            assert_eq!(alone.posterior, f.posterior, "{} item {k} alone", m.id);
        }
        // The baseline instruction set gives the same bits as the dispatched one.
        let base = MlpUpdater::new(m.clone()).unwrap().baseline_simd();
        let mut b = vec![UpdateOutput::default(); inputs.len()];
        base.update_batch(UpdateNeeds::PosteriorAndLikelihood, &inputs, &mut b);
        assert_eq!(b, full, "{}", m.id);
    }
}

/// The structured model's correction is `K ν`: none when the observation is exactly the
/// predicted one, and twice the innovation moves the landmark twice as far.
#[test]
fn structured_mean_is_linear_in_the_innovation() {
    let m = layout_models()
        .iter()
        .find(|m| m.layout == InputLayout::Gain && m.kind == LandmarkKind::Point3d)
        .unwrap();
    let u = MlpUpdater::new(m.clone()).unwrap();
    for inp in inputs_of(LandmarkKind::Point3d, 50, 5) {
        let (s, c) = fleetslam_core::math::sin_cos(inp.pose.theta);
        let d = [
            inp.prior.mean[0] - inp.pose.x,
            inp.prior.mean[1] - inp.pose.y,
            inp.prior.mean[2],
        ];
        let zhat = [c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]];
        let at = |k: f64| {
            let z = std::array::from_fn(|i| zhat[i] + k * (inp.z[i] - zhat[i]));
            u.update(&UpdateInput { z, ..inp }).posterior.mean
        };
        let (m0, m1, m2) = (at(0.0), at(1.0), at(2.0));
        for i in 0..3 {
            assert!((m0[i] - inp.prior.mean[i]).abs() < 1e-9, "{m0:?}");
            let (d1, d2) = (m1[i] - m0[i], m2[i] - m0[i]);
            assert!((d2 - 2.0 * d1).abs() < 1e-9 * (1.0 + d1.abs()), "{d1} {d2}");
        }
    }
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
    recorded_sim(4, threads, rate, cap)
}

fn recorded_sim(sim_seed: u64, threads: usize, rate: f64, cap: usize) -> (Vec<TrainingRow>, u64) {
    let sim = small_sim(LandmarkKind::RangeBearing2d, sim_seed);
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
    // Train on the EKF's updates of three simulations (one each for training, validation
    // and test), score on another seed's.
    let runs: Vec<Vec<TrainingRow>> = [4, 5, 6]
        .iter()
        .map(|&s| recorded_sim(s, 2, 0.5, 40_000).0)
        .collect();
    let mut c = small_config("sim-mlp");
    c.epochs = 60;
    let t = train(&runs, &c, |_, _, _, _| {}).unwrap();
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

/// Rows of a simulated run are labelled with the landmark each one updated, placed from
/// the row's pose by the noise-free measurement: every row, and all but at most 1 in 1,000
/// next to the true landmark nearest the row's posterior; a measurement that the log holds
/// twice is left unlabelled, as is every row of another log.
#[test]
fn rows_are_labelled_with_the_landmark_they_updated() {
    let sim = small_sim(LandmarkKind::RangeBearing2d, 4);
    let (mut rows, _) = recorded_sim(4, 2, 0.05, usize::MAX);
    let truth: std::collections::BTreeMap<u32, [f64; 3]> = sim
        .truth
        .landmarks
        .iter()
        .map(|l| (l.id.unwrap(), l.mean))
        .collect();
    let true_pose = |robot: &str, t: f64| interpolate(sim.truth.trajectories.get(robot)?, t, 1.0);
    let stats = label_rows(&mut rows, &sim.log, &truth, true_pose);
    assert_eq!(stats.rows, rows.len());
    assert_eq!(stats.labelled, rows.len(), "{stats:?}");
    let nearest = |p: &[f64; 3]| {
        truth
            .values()
            .min_by(|a, b| dist(a, p).total_cmp(&dist(b, p)))
            .copied()
            .unwrap()
    };
    let agree = rows
        .iter()
        .filter(|r| {
            let t = r.truth.unwrap();
            let m = nearest(&t);
            m == nearest(&r.post_mean) && dist(&m, &t) < LABEL_NEAR
        })
        .count();
    println!("{agree} of {} rows lie nearest their label", rows.len());
    // Measured: 5,089 of 5,090 rows with session 31's `libm` functions and normal draws
    // and the learned crate's own since session 32 (the one a particle whose landmark
    // estimate strayed nearer another landmark; before session 31, 4,983 of 4,984; with the
    // ChaCha8 streams of sessions 1-16, all).
    assert!(
        agree * 1000 >= rows.len() * 999,
        "{agree} of {} rows lie nearest their label",
        rows.len()
    );

    // A reading repeated within its record is still one observation; the same measurement
    // of another landmark makes it ambiguous; rows of another log match nothing.
    let mut log = sim.log.clone();
    let z = rows[0].z;
    let rec = log
        .records
        .iter_mut()
        .find(|r| r.landmarks.iter().any(|o| o.z[..2] == z[..2]))
        .unwrap();
    let seen = rec
        .landmarks
        .iter()
        .find(|o| o.z[..2] == z[..2])
        .unwrap()
        .clone();
    rec.landmarks.push(seen.clone());
    let stats = label_rows(&mut rows[..1], &log, &truth, true_pose);
    assert_eq!(stats.labelled, 1);
    rec_push(&mut log, &z, seen.id.unwrap() + 1000);
    let stats = label_rows(&mut rows[..1], &log, &truth, true_pose);
    assert_eq!((stats.ambiguous, rows[0].truth), (1, None));
    let other = small_sim(LandmarkKind::RangeBearing2d, 5);
    let stats = label_rows(&mut rows, &other.log, &truth, true_pose);
    assert_eq!(stats.not_in_log, rows.len());
}

/// Adds an observation of landmark `id` with measurement `z` to the first record.
fn rec_push(log: &mut fleetslam_core::log::Log, z: &[f64; 3], id: u32) {
    log.records[0]
        .landmarks
        .push(fleetslam_core::log::LandmarkObservation {
            id: Some(id),
            z: vec![z[0], z[1]],
        });
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Trained against truth, a model learns a sensor bias the EKF does not know of and beats
/// the EKF's posterior on unseen runs; without a bias it matches the EKF (which is then
/// the right answer).
#[test]
fn truth_preset_learns_a_sensor_bias_the_ekf_cannot() {
    let kind = LandmarkKind::RangeBearing2d;
    for (bias, bound) in [(0.2, TRUTH_BIASED_BOUND), (0.0, TRUTH_UNBIASED_BOUND)] {
        let runs: Vec<Vec<TrainingRow>> = (1..=5)
            .map(|seed| synthetic_rows_biased(kind, &noise(), 1100, seed, [bias, 0.0, 0.0]))
            .collect();
        let mut c = TrainConfig::truth("test-truth");
        c.hidden = vec![24, 24];
        c.epochs = 40;
        c.batch_size = 128;
        c.patience = 10;
        c.noise = Some(noise());
        let t = train(&runs, &c, |_, _, _, _| {}).unwrap();
        assert_eq!(t.model.layout, InputLayout::LineOfSightRange);
        let e = t.report.updater.unwrap().truth.unwrap();
        assert!(e.rows > 1000);
        let ratio = e.updater_rmse / e.ekf_rmse;
        println!(
            "bias {bias}: model {:.4} m vs EKF {:.4} m (ratio {ratio:.3})",
            e.updater_rmse, e.ekf_rmse
        );
        assert!(
            ratio < bound,
            "bias {bias}: model {} m vs EKF {} m (ratio {ratio:.3})",
            e.updater_rmse,
            e.ekf_rmse
        );
        // With the bias the EKF's update moves landmarks away from the truth (worse than
        // not updating); the model's moves them closer.
        assert!(e.updater_rmse < e.prior_rmse, "{e:?}");
    }
    // Unlabelled rows are refused, as is the gain layout.
    let mut c = TrainConfig::truth("test-truth");
    let mut unlabelled = runs(kind, 3, 200);
    for run in &mut unlabelled {
        run[0].truth = None;
    }
    let err = train(&unlabelled, &c, |_, _, _, _| {}).unwrap_err();
    assert!(err.to_string().contains("no truth"), "{err}");
    c.layout = InputLayout::Gain;
    assert!(c.validate().is_err());
}
