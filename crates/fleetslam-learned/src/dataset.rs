//! From training rows to network inputs and targets, the sensor noise estimate, and the
//! validation report of an updater against the EKF's logged results. No burn here.

use crate::LearnedError;
use crate::frame::{Frame, InputLayout, frame2, frame3, paper_features, paper_targets};
use crate::row::TrainingRow;
use fleetslam_core::math;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use fleetslam_core::updater::{LandmarkGaussian, LandmarkUpdater, UpdateNeeds};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use serde::{Deserialize, Serialize};

/// What a network's posterior-mean outputs are trained to predict.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrainTarget {
    /// The EKF's logged posterior mean: the network mimics the EKF.
    #[default]
    Ekf,
    /// The landmark's true position seen from the row's pose (rows labelled with
    /// [`crate::truth::label_rows`]). Under a squared loss the best prediction is
    /// `E[truth | inputs]`, the posterior mean under the data's own error distribution (the
    /// real sensor's biases and range-dependent noise), which the EKF's Gaussian model only
    /// approximates. The
    /// covariance outputs keep the EKF's posterior as their target (one truth position per
    /// row cannot determine a covariance). The `gain` layout cannot take it: its outputs
    /// are a gain, which one position cannot determine either.
    Truth,
}

impl TrainTarget {
    pub fn as_str(self) -> &'static str {
        match self {
            TrainTarget::Ekf => "ekf",
            TrainTarget::Truth => "truth",
        }
    }
}

impl std::str::FromStr for TrainTarget {
    type Err = LearnedError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "ekf" => Ok(TrainTarget::Ekf),
            "truth" => Ok(TrainTarget::Truth),
            o => Err(LearnedError::Config(format!(
                "unknown target {o:?}: use ekf or truth"
            ))),
        }
    }
}

/// Inputs and targets, row-major.
#[derive(Debug, Clone, Default)]
pub struct Encoded {
    pub n_in: usize,
    pub n_out: usize,
    pub x: Vec<f64>,
    pub y: Vec<f64>,
}

impl Encoded {
    pub fn len(&self) -> usize {
        self.x.len() / self.n_in.max(1)
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

/// The posterior whose mean the network learns: the EKF's, or the truth position with the
/// EKF's covariance. `None` for a truth target on a row without truth.
fn target_posterior(row: &TrainingRow, target: TrainTarget) -> Option<LandmarkGaussian> {
    let ekf = row.output().posterior;
    match target {
        TrainTarget::Ekf => Some(ekf),
        TrainTarget::Truth => row.truth.map(|mean| LandmarkGaussian { mean, ..ekf }),
    }
}

fn encode_frame<const D: usize>(
    layout: InputLayout,
    target: TrainTarget,
    f: &Frame<D>,
    row: &TrainingRow,
    x: &mut [f64],
    y: &mut [f64],
) -> Option<()> {
    let s = f.prior_std();
    let (corr, cov) = f.frame_posterior(&row.prior_mean, &target_posterior(row, target)?);
    if layout == InputLayout::Gain {
        // The gain is not in a row (one correction cannot determine a matrix): it is the
        // EKF's gain `Σ (Σ + Q)⁻¹` from the row's prior and the noise estimated from the
        // logged updates; the covariance target is the logged posterior.
        f.prior_features(&s, x);
        f.gain_targets(&f.innovation(false)?, &cov, y)?;
    } else {
        if layout == InputLayout::LineOfSightRange {
            f.los_range_features(&s, x);
        } else {
            f.los_features(&s, x);
        }
        f.los_targets(&corr, &cov, y)?;
    }
    x.iter()
        .chain(y.iter())
        .all(|v| v.is_finite())
        .then_some(())
}

/// Encodes rows of `kind` for `layout` with the mean target `target`; rows of another kind,
/// degenerate geometry, a posterior that is not positive definite or (target `truth`) no
/// truth position are skipped. Returns the encoding and how many rows were skipped.
pub fn encode(
    rows: &[TrainingRow],
    kind: LandmarkKind,
    layout: InputLayout,
    target: TrainTarget,
    noise: &SensorNoise,
) -> (Encoded, usize) {
    let (n_in, n_out) = layout.dims(kind);
    let mut e = Encoded {
        n_in,
        n_out,
        x: Vec::with_capacity(rows.len() * n_in),
        y: Vec::with_capacity(rows.len() * n_out),
    };
    let mut skipped = 0;
    let mut x = vec![0.0; n_in];
    let mut y = vec![0.0; n_out];
    for row in rows {
        if row.kind != kind {
            skipped += 1;
            continue;
        }
        let inp = row.input();
        let ok = match layout {
            InputLayout::Paper => target_posterior(row, target).map(|post| {
                paper_features(kind, &inp, &mut x);
                paper_targets(kind, &post, &mut y);
            }),
            InputLayout::LineOfSight | InputLayout::LineOfSightRange | InputLayout::Gain => {
                match kind {
                    LandmarkKind::RangeBearing2d => frame2(&inp, noise)
                        .and_then(|f| encode_frame(layout, target, &f, row, &mut x, &mut y)),
                    LandmarkKind::Point3d => {
                        encode_frame(layout, target, &frame3(&inp, noise), row, &mut x, &mut y)
                    }
                }
            }
        };
        if ok.is_some() {
            e.x.extend_from_slice(&x);
            e.y.extend_from_slice(&y);
        } else {
            skipped += 1;
        }
    }
    (e, skipped)
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    Some(v[v.len() / 2])
}

/// Estimates the sensor noise behind logged EKF updates. In the measurement frame the EKF
/// is a linear update with `H = I`, so the information form gives
/// `Q⁻¹ = Σ'⁻¹ − Σ⁻¹` for every row; the estimate is the per-axis median over rows.
pub fn estimate_noise(
    rows: &[TrainingRow],
    kind: LandmarkKind,
) -> Result<SensorNoise, LearnedError> {
    let probe = SensorNoise::default();
    let mut axes: [Vec<f64>; 3] = Default::default();
    for row in rows.iter().filter(|r| r.kind == kind) {
        let inp = row.input();
        match kind {
            LandmarkKind::RangeBearing2d => {
                let Some(f) = frame2(&inp, &probe) else {
                    continue;
                };
                let (_, post) = f.frame_posterior(&row.prior_mean, &row.output().posterior);
                let (Some(pi), Some(si)) = (post.try_inverse(), f.sigma.try_inverse()) else {
                    continue;
                };
                let info = pi - si;
                // q[1] of the frame is r² σb²; recover σb² from the probe's scaling.
                let r2 = f.q[1] / (probe.bearing * probe.bearing);
                if info[(0, 0)] > 0.0 {
                    axes[0].push(1.0 / info[(0, 0)]);
                }
                if info[(1, 1)] > 0.0 {
                    axes[1].push(1.0 / info[(1, 1)] / r2);
                }
            }
            LandmarkKind::Point3d => {
                let f = frame3(&inp, &probe);
                let (_, post) = f.frame_posterior(&row.prior_mean, &row.output().posterior);
                let (Some(pi), Some(si)) = (post.try_inverse(), f.sigma.try_inverse()) else {
                    continue;
                };
                let info = pi - si;
                for (k, axis) in axes.iter_mut().enumerate() {
                    if info[(k, k)] > 0.0 {
                        axis.push(1.0 / info[(k, k)]);
                    }
                }
            }
        }
    }
    let sd = |v: &Vec<f64>| median(v.clone()).map(f64::sqrt);
    let noise = match kind {
        LandmarkKind::RangeBearing2d => {
            let (Some(r), Some(b)) = (sd(&axes[0]), sd(&axes[1])) else {
                return Err(LearnedError::Data(
                    "no usable range-bearing rows to estimate the sensor noise from".into(),
                ));
            };
            SensorNoise {
                range: r,
                bearing: b,
                ..SensorNoise::default()
            }
        }
        LandmarkKind::Point3d => {
            let (Some(x), Some(y), Some(z)) = (sd(&axes[0]), sd(&axes[1]), sd(&axes[2])) else {
                return Err(LearnedError::Data(
                    "no usable 3D point rows to estimate the sensor noise from".into(),
                ));
            };
            SensorNoise {
                xyz: [x, y, z],
                ..SensorNoise::default()
            }
        }
    };
    noise
        .validate("estimated noise")
        .map_err(LearnedError::Data)?;
    Ok(noise)
}

/// Training, validation and test rows, split by run: every run's rows go to exactly one set,
/// so that the near-identical updates of one observation across particles (and of one
/// landmark over a run) never sit on both sides.
#[derive(Debug, Clone, Default)]
pub struct RunSplit {
    pub train: Vec<TrainingRow>,
    pub val: Vec<TrainingRow>,
    pub test: Vec<TrainingRow>,
    /// Indices (into the runs given) of each set's runs.
    pub train_runs: Vec<usize>,
    pub val_runs: Vec<usize>,
    pub test_runs: Vec<usize>,
}

/// Splits `runs` (each the rows of one run) into `val_runs` validation runs, `test_runs`
/// test runs and the rest for training, after a seeded shuffle of the runs. Errors when
/// fewer than `val_runs + test_runs + 1` runs hold rows.
pub fn split_runs(
    runs: &[Vec<TrainingRow>],
    val_runs: usize,
    test_runs: usize,
    seed: u64,
) -> Result<RunSplit, LearnedError> {
    let mut idx: Vec<usize> = (0..runs.len()).filter(|&i| !runs[i].is_empty()).collect();
    if val_runs == 0 || idx.len() < val_runs + test_runs + 1 {
        return Err(LearnedError::Data(format!(
            "{} runs hold training rows, but a split by run needs at least {} (1 or more for \
             training, {val_runs} for validation, {test_runs} for test; validation needs 1 or \
             more): log rows from more runs (each file or store run is one run)",
            idx.len(),
            val_runs.max(1) + test_runs + 1
        )));
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    idx.shuffle(&mut rng);
    let mut out = RunSplit {
        val_runs: idx[..val_runs].to_vec(),
        test_runs: idx[val_runs..val_runs + test_runs].to_vec(),
        train_runs: idx[val_runs + test_runs..].to_vec(),
        ..Default::default()
    };
    for v in [&mut out.val_runs, &mut out.test_runs, &mut out.train_runs] {
        v.sort_unstable();
    }
    let gather = |ids: &[usize]| ids.iter().flat_map(|&i| runs[i].iter().copied()).collect();
    out.train = gather(&out.train_runs);
    out.val = gather(&out.val_runs);
    out.test = gather(&out.test_runs);
    Ok(out)
}

/// How far an updater's results are from the EKF's logged ones.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct UpdaterError {
    pub rows: usize,
    /// RMS distance between posterior means [m].
    pub mean_rmse: f64,
    /// The same for not updating at all (prior mean against the EKF's posterior) [m]: the
    /// baseline a useful model must beat by far.
    pub no_update_rmse: f64,
    /// RMS over rows of `‖Σ' − Σ'_ekf‖_F / ‖Σ'_ekf‖_F`.
    pub cov_rel_rmse: f64,
    /// RMS difference of the log-likelihoods.
    pub log_likelihood_rmse: f64,
    /// RMS difference of the squared Mahalanobis distances.
    pub mahalanobis2_rmse: f64,
    /// Rows the updater rejected (kept the prior).
    pub rejected: usize,
    /// Against ground truth, on the rows that carry it (`None` when none does).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthError>,
}

/// Posterior means against the landmarks' true positions.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct TruthError {
    /// Rows with a truth position.
    pub rows: usize,
    /// RMS distance from the updater's posterior mean to the truth [m].
    pub updater_rmse: f64,
    /// The same for the EKF's logged posterior mean [m].
    pub ekf_rmse: f64,
    /// The same for the prior mean (not updating) [m].
    pub prior_rmse: f64,
}

/// Runs `updater` on the rows' inputs (in one batch) and compares with the rows' outputs.
pub fn updater_error(updater: &dyn LandmarkUpdater, rows: &[TrainingRow]) -> UpdaterError {
    let inputs: Vec<_> = rows.iter().map(TrainingRow::input).collect();
    let mut outs = vec![Default::default(); inputs.len()];
    updater.update_batch(UpdateNeeds::PosteriorAndLikelihood, &inputs, &mut outs);
    let mut e = UpdaterError {
        rows: rows.len(),
        ..Default::default()
    };
    if rows.is_empty() {
        return e;
    }
    let (mut sm, mut s0, mut sc, mut sl, mut s2) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let mut counted = 0usize;
    let mut truth = TruthError::default();
    for (row, o) in rows.iter().zip(&outs) {
        let d2 = |a: &[f64; 3], b: &[f64; 3]| -> f64 {
            a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
        };
        if let Some(t) = &row.truth {
            truth.rows += 1;
            truth.updater_rmse += d2(&o.posterior.mean, t);
            truth.ekf_rmse += d2(&row.post_mean, t);
            truth.prior_rmse += d2(&row.prior_mean, t);
        }
        if !o.log_likelihood.is_finite() {
            e.rejected += 1;
        }
        sm += d2(&o.posterior.mean, &row.post_mean);
        s0 += d2(&row.prior_mean, &row.post_mean);
        // Frobenius norm of a symmetric matrix from its upper triangle.
        let fro = |c: &[f64; 6]| -> f64 {
            c[0] * c[0]
                + c[3] * c[3]
                + c[5] * c[5]
                + 2.0 * (c[1] * c[1] + c[2] * c[2] + c[4] * c[4])
        };
        let diff: [f64; 6] = std::array::from_fn(|k| o.posterior.cov[k] - row.post_cov[k]);
        let denom = fro(&row.post_cov);
        if denom > 0.0 {
            sc += fro(&diff) / denom;
        }
        if o.log_likelihood.is_finite() {
            sl += (o.log_likelihood - row.log_likelihood).powi(2);
            s2 += (o.mahalanobis2 - row.mahalanobis2).powi(2);
            counted += 1;
        }
    }
    let n = rows.len() as f64;
    e.mean_rmse = (sm / n).sqrt();
    e.no_update_rmse = (s0 / n).sqrt();
    e.cov_rel_rmse = (sc / n).sqrt();
    let c = counted.max(1) as f64;
    e.log_likelihood_rmse = (sl / c).sqrt();
    e.mahalanobis2_rmse = (s2 / c).sqrt();
    if truth.rows > 0 {
        let n = truth.rows as f64;
        for v in [
            &mut truth.updater_rmse,
            &mut truth.ekf_rmse,
            &mut truth.prior_rmse,
        ] {
            *v = (*v / n).sqrt();
        }
        e.truth = Some(truth);
    }
    e
}

/// `n` generated EKF updates of `kind` under `noise`: a robot pose, a landmark prior from an
/// initial observation with its covariance scaled by a log-uniform factor in [0.02, 2] (from
/// fresh to well-observed landmarks), the true landmark drawn from that prior and a noisy
/// observation of it, and the EKF's result; each row carries the true position. Used by
/// tests, benchmarks and as a quick dataset.
pub fn synthetic_rows(
    kind: LandmarkKind,
    noise: &SensorNoise,
    n: usize,
    seed: u64,
) -> Vec<TrainingRow> {
    synthetic_rows_biased(kind, noise, n, seed, [0.0; 3])
}

/// As [`synthetic_rows`] from a sensor whose measurements are off by `bias` (added to
/// `[range, bearing, 0]` or `[dx, dy, dz]`) that the EKF does not know of: what a model
/// trained against truth can learn and the EKF cannot.
pub fn synthetic_rows_biased(
    kind: LandmarkKind,
    noise: &SensorNoise,
    n: usize,
    seed: u64,
    bias: [f64; 3],
) -> Vec<TrainingRow> {
    use fleetslam_core::ekf::EkfUpdater;
    use fleetslam_core::pose::Pose2;
    use fleetslam_core::rng::StandardNormal;
    use fleetslam_core::sensor::{point3_predict, range_bearing_predict};
    use fleetslam_core::updater::UpdateInput;
    use rand::Rng;
    use rand::distr::Distribution;
    let ekf = EkfUpdater::new(kind, noise);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let g = |rng: &mut rand_chacha::ChaCha8Rng| -> f64 { StandardNormal.sample(rng) };
    let mut rows = Vec::with_capacity(n);
    while rows.len() < n {
        let pose = Pose2::new(
            rng.random_range(-10.0..10.0),
            rng.random_range(-10.0..10.0),
            rng.random_range(-3.1..3.1),
        );
        let r = rng.random_range(0.5..6.0);
        let b: f64 = rng.random_range(-1.5..1.5);
        let z0 = match kind {
            LandmarkKind::RangeBearing2d => [r, b, 0.0],
            LandmarkKind::Point3d => [
                r * math::cos(b),
                r * math::sin(b),
                rng.random_range(0.2..2.0),
            ],
        };
        let mut prior = ekf.initialize(&pose, &z0);
        let scale = math::exp(rng.random_range(math::ln(0.02)..math::ln(2.0)));
        prior.cov.iter_mut().for_each(|c| *c *= scale);
        // The true landmark, drawn from the prior.
        let chol = match kind {
            LandmarkKind::RangeBearing2d => {
                let c = prior.cov2().cholesky().map(|c| c.l());
                c.map(|l| {
                    let e = nalgebra::Vector2::new(g(&mut rng), g(&mut rng));
                    let d = l * e;
                    [d[0], d[1], 0.0]
                })
            }
            LandmarkKind::Point3d => prior.cov3().cholesky().map(|c| {
                let e = nalgebra::Vector3::new(g(&mut rng), g(&mut rng), g(&mut rng));
                let d = c.l() * e;
                [d[0], d[1], d[2]]
            }),
        };
        let Some(d) = chol else { continue };
        let truth = [
            prior.mean[0] + d[0],
            prior.mean[1] + d[1],
            prior.mean[2] + d[2],
        ];
        let z = match kind {
            LandmarkKind::RangeBearing2d => {
                let Some((zh, _, _)) = range_bearing_predict(&pose, truth[0], truth[1]) else {
                    continue;
                };
                [
                    zh[0] + bias[0] + noise.range_std_at(zh[0]) * g(&mut rng),
                    zh[1] + bias[1] + noise.bearing * g(&mut rng),
                    0.0,
                ]
            }
            LandmarkKind::Point3d => {
                let (zh, _, _) = point3_predict(&pose, &truth);
                [
                    zh[0] + bias[0] + noise.xyz[0] * g(&mut rng),
                    zh[1] + bias[1] + noise.xyz[1] * g(&mut rng),
                    zh[2] + bias[2] + noise.xyz[2] * g(&mut rng),
                ]
            }
        };
        let input = UpdateInput { prior, pose, z };
        if let Some(mut row) = TrainingRow::new(kind, &input, &ekf.update(&input)) {
            row.truth = Some(truth);
            rows.push(row);
        }
    }
    rows
}
