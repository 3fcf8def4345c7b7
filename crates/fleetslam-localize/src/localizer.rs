//! Monte Carlo localization of one robot in a fixed landmark map, with KLD-sampling and the
//! real-time policies for windows of several records.
//!
//! The belief is a weighted sample set over the robot's pose (Dellaert, Fox, Burgard, Thrun
//! 1999; the Monte Carlo localization notes in `shared/papers`):
//!
//! 1. **Global initialisation.** `max_samples` poses drawn uniformly over the map's extent
//!    (the landmarks' bounding box grown by `init_margin`) with uniform headings.
//! 2. **Prediction.** Each sample moves by the run's motion model: the record's increment
//!    plus Gaussian noise in the robot frame with the variances of
//!    [`fleetslam_core::motion::MotionNoise::variances`], exactly as FastSLAM 1.0 samples a
//!    pose: `x' = x ⊕ (Δ + e)`, `e ~ N(0, diag(σ²))`.
//! 3. **Correction.** Each sample is weighed by the likelihood of the record's observations
//!    in the fixed map ([`crate::map::Scorer`]).
//! 4. **Resampling.** Low-variance (systematic) resampling at the start of an update, to a
//!    number of samples chosen by KLD-sampling (Fox 2001, [`crate::config::KldParams`]):
//!    multinomial draws from the weighted set are binned until the bound for the number of
//!    occupied bins is reached, and that many samples are then drawn systematically. A
//!    one-record update whose budget is unchanged skips resampling while the effective
//!    sample size stays above `resample_threshold` (Doucet, de Freitas, Gordon 2001), which
//!    keeps the modes of a symmetric map's belief alive.
//!
//! An update covers a window of `k` records ([`crate::config::Window`]); with `k > 1` the
//! [`crate::config::Policy`] decides how the sample budget `N` is spent (see
//! [`crate::rtpf`] for the mixture of the real-time particle filter).
//!
//! Every random draw comes from [`fleetslam_core::rng::chacha_stream`] keyed by (seed,
//! update, lane), with one lane per sample and sample set, so the results do not depend on
//! the number of threads, and the whole state (samples, weights, counters and the pending
//! records) serialises: a localizer restored from JSON continues bit for bit.

use crate::config::{LocalizeConfig, Models, Policy, Window};
use crate::error::LocalizeError;
use crate::map::{LandmarkSet, ResolvedObs, Scorer};
use crate::rtpf::{group_by_grid, grouped_beliefs, optimise_weights};
use fleetslam_core::log::Record;
use fleetslam_core::math;
use fleetslam_core::motion::Motion;
use fleetslam_core::pose::{Pose2, weighted_mean_pose, wrap_angle};
use fleetslam_core::resample::normalize_log_weights;
use fleetslam_core::rng::StandardNormal;
use fleetslam_core::rng::chacha_stream as stream;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use std::f64::consts::PI;

/// Lane of sample `i` of sample set `set`: `set << 32 | i`.
const SET_SHIFT: u32 = 32;
/// Pseudo-set of the trajectories of the RTPF gradient estimate.
const SET_TRAJECTORIES: u64 = 100;
/// Pseudo-set of the global initialisation.
const SET_INIT: u64 = 101;
/// Lane of KLD-sampling's draws.
const LANE_KLD: u64 = u64::MAX - 1000;

/// Counters of one localizer, for the API and the experiment.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LocalizerStats {
    /// Records given to the localizer.
    pub records: u64,
    /// Records that arrived before the map had `min_landmarks` landmarks (motion dropped).
    pub waiting_records: u64,
    /// Updates (windows) processed.
    pub updates: u64,
    /// Records with observations whose observations were integrated.
    pub integrated: u64,
    /// Records with observations that the `skip` policy dropped.
    pub skipped: u64,
    /// Observations whose landmark id the map does not hold (not mapped yet).
    pub unmatched_observations: u64,
    /// Window sizes: size -> number of updates.
    pub windows: BTreeMap<usize, u64>,
    /// Likelihood evaluations of a record's observations in the sample sets.
    pub likelihood_evals: u64,
    /// Likelihood evaluations for RTPF's gradient estimate (its overhead).
    pub gradient_evals: u64,
}

/// What one update did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UpdateReport {
    /// Time of the window's last record [s].
    pub t: f64,
    /// Records in the window.
    pub window: usize,
    /// Samples after the update.
    pub samples: usize,
    pub ess: f64,
    pub mean: Pose2,
    pub position_spread: f64,
    pub heading_spread: f64,
    /// Whether the update integrated any observation.
    pub observed: bool,
    /// The convergence test held for `hold_updates` consecutive observing updates.
    pub converged: bool,
    /// The mixture weights of the window's sample sets (uniform and rtpf), else empty.
    pub alpha: Vec<f64>,
}

/// The state of a localizer as the API shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LocalizerStatus {
    /// False until the map had enough landmarks to start.
    pub initialised: bool,
    pub samples: usize,
    pub ess: f64,
    pub mean: Pose2,
    pub position_spread: f64,
    pub heading_spread: f64,
    pub converged: bool,
    /// Consecutive observing updates that passed the convergence test.
    pub hold: usize,
    pub policy: Policy,
    /// Records waiting for the current window to fill.
    pub pending: usize,
    /// Mixture weights of the last window (uniform and rtpf).
    pub alpha: Vec<f64>,
    pub stats: LocalizerStats,
}

/// Monte Carlo localization of one robot (see the module documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Localizer {
    models: Models,
    config: LocalizeConfig,
    seed: u64,
    /// Updates so far (and the global initialisation): the `step` of the random streams.
    step: u64,
    poses: Vec<Pose2>,
    /// Normalised log-weights.
    log_w: Vec<f64>,
    last_t: Option<f64>,
    window_open_t: f64,
    pending: Vec<Record>,
    alpha: Vec<f64>,
    /// Mixture weights given for the next mixture update ([`Localizer::set_next_weights`]);
    /// not part of the state a snapshot keeps.
    #[serde(skip)]
    next_weights: Option<Vec<f64>>,
    ess: f64,
    hold: usize,
    converged: bool,
    stats: LocalizerStats,
}

/// Weighted spread of a sample set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    pub mean: Pose2,
    /// `sqrt(Σ w ((x - x̄)² + (y - ȳ)²))` [m].
    pub position: f64,
    /// `sqrt(-2 ln R)`, R the weighted mean resultant length of the headings [rad].
    pub heading: f64,
}

/// Weighted mean and spread of poses with normalised weights.
pub fn spread(poses: &[Pose2], weights: &[f64]) -> Spread {
    let mean = weighted_mean_pose(poses.iter().zip(weights.iter().copied()));
    let (mut v, mut s, mut c) = (0.0, 0.0, 0.0);
    for (p, w) in poses.iter().zip(weights) {
        v += w * ((p.x - mean.x).powi(2) + (p.y - mean.y).powi(2));
        s += w * math::sin(p.theta);
        c += w * math::cos(p.theta);
    }
    let total: f64 = weights.iter().sum();
    let r = (math::hypot(s, c) / total.max(f64::MIN_POSITIVE)).clamp(1e-300, 1.0);
    Spread {
        mean,
        position: (v / total.max(f64::MIN_POSITIVE)).max(0.0).sqrt(),
        heading: (-2.0 * math::ln(r)).max(0.0).sqrt(),
    }
}

/// The deterministic increment of a record and the standard deviations of its noise, as
/// the core filter computes them.
fn motion_of(models: &Models, rec: &Record, last_t: Option<f64>) -> (Pose2, [f64; 3]) {
    let gap = last_t.map_or(0.0, |l| rec.t - l);
    let (inc, dt) = match &rec.motion {
        None => (Pose2::default(), gap),
        Some(m @ Motion::Odometry(_)) => (m.increment(&models.ackermann), gap),
        Some(m) => (m.increment(&models.ackermann), m.duration()),
    };
    let var = models.motion_noise.variances(&inc, dt);
    (inc, var.map(f64::sqrt))
}

/// `x ⊕ (Δ + e)` with `e ~ N(0, diag(σ²))` in the robot frame.
#[inline]
fn sample_motion(prev: &Pose2, inc: &Pose2, std: &[f64; 3], rng: &mut ChaCha8Rng) -> Pose2 {
    let e0: f64 = rng.sample(StandardNormal);
    let e1: f64 = rng.sample(StandardNormal);
    let e2: f64 = rng.sample(StandardNormal);
    prev.compose(&Pose2::new(
        inc.x + std[0] * e0,
        inc.y + std[1] * e1,
        inc.theta + std[2] * e2,
    ))
}

/// Systematic resampling of `n` indices from normalised log-weights (Thrun, Burgard, Fox,
/// table 4.4, with `n` pointers spaced `1/n` apart).
pub fn systematic_n(log_w: &[f64], n: usize, rng: &mut ChaCha8Rng) -> Vec<usize> {
    let mut out = Vec::with_capacity(n);
    if log_w.is_empty() || n == 0 {
        return out;
    }
    let step = 1.0 / n as f64;
    let mut u = rng.random::<f64>() * step;
    let mut c = math::exp(log_w[0]);
    let mut i = 0;
    for _ in 0..n {
        while u > c && i + 1 < log_w.len() {
            i += 1;
            c += math::exp(log_w[i]);
        }
        out.push(i);
        u += step;
    }
    out
}

/// One record of a window, ready for the sample sets.
struct Step {
    inc: Pose2,
    std: [f64; 3],
    obs: Vec<ResolvedObs>,
}

/// What one pass of a sample set through a window returns.
struct SetResult {
    poses: Vec<Pose2>,
    /// Sum of the integrated records' log-likelihoods per sample.
    ll: Vec<f64>,
    /// `per_record[j][m]`: record `j`'s log-likelihood at sample `m` (trajectories only).
    per_record: Vec<Vec<f64>>,
}

impl Localizer {
    /// A localizer for one robot; `seed` keys its random streams (the late-joiner wrapper
    /// derives it from the run's seed and the robot's id).
    pub fn new(models: Models, config: LocalizeConfig, seed: u64) -> Result<Self, LocalizeError> {
        config.validate().map_err(LocalizeError::Config)?;
        models
            .motion_noise
            .validate()
            .map_err(LocalizeError::Config)?;
        models
            .sensor_noise
            .validate("sensor_noise")
            .map_err(LocalizeError::Config)?;
        Ok(Self {
            models,
            config,
            seed,
            step: 0,
            poses: Vec::new(),
            log_w: Vec::new(),
            last_t: None,
            window_open_t: 0.0,
            pending: Vec::new(),
            alpha: Vec::new(),
            next_weights: None,
            ess: 0.0,
            hold: 0,
            converged: false,
            stats: LocalizerStats::default(),
        })
    }

    pub fn config(&self) -> &LocalizeConfig {
        &self.config
    }

    pub fn models(&self) -> &Models {
        &self.models
    }

    pub fn is_initialised(&self) -> bool {
        !self.poses.is_empty()
    }

    /// The convergence test held for `hold_updates` consecutive observing updates.
    pub fn is_converged(&self) -> bool {
        self.converged
    }

    pub fn stats(&self) -> &LocalizerStats {
        &self.stats
    }

    /// Consecutive observing updates that passed the convergence test.
    pub fn hold(&self) -> usize {
        self.hold
    }

    /// Time of the last record given (applied or pending).
    pub fn last_time(&self) -> Option<f64> {
        self.pending.last().map(|r| r.t).or(self.last_t)
    }

    /// Time of the last applied record.
    pub fn applied_time(&self) -> Option<f64> {
        self.last_t
    }

    /// The samples and their normalised weights (empty before initialisation).
    pub fn posterior(&self) -> (Vec<Pose2>, Vec<f64>) {
        (
            self.poses.clone(),
            self.log_w.iter().map(|&w| math::exp(w)).collect(),
        )
    }

    /// Up to `max` samples evenly spaced over the set, with their normalised weights.
    pub fn sample(&self, max: usize) -> Vec<(Pose2, f64)> {
        let stride = self.poses.len().div_ceil(max.max(1)).max(1);
        self.poses
            .iter()
            .zip(&self.log_w)
            .step_by(stride)
            .map(|(p, w)| (*p, math::exp(*w)))
            .collect()
    }

    pub fn spread(&self) -> Spread {
        let w: Vec<f64> = self.log_w.iter().map(|&w| math::exp(w)).collect();
        spread(&self.poses, &w)
    }

    pub fn status(&self) -> LocalizerStatus {
        let s = self.spread();
        LocalizerStatus {
            initialised: self.is_initialised(),
            samples: self.poses.len(),
            ess: self.ess,
            mean: s.mean,
            position_spread: s.position,
            heading_spread: s.heading,
            converged: self.converged,
            hold: self.hold,
            policy: self.config.policy,
            pending: self.pending.len(),
            alpha: self.alpha.clone(),
            stats: self.stats.clone(),
        }
    }

    /// Checks a restored state's invariants.
    pub fn check(&self) -> Result<(), LocalizeError> {
        self.config
            .validate()
            .map_err(|e| LocalizeError::Snapshot(e.to_string()))?;
        if self.poses.len() != self.log_w.len() {
            return Err(LocalizeError::Snapshot(format!(
                "{} samples but {} weights",
                self.poses.len(),
                self.log_w.len()
            )));
        }
        if self.poses.iter().any(|p| !p.is_finite()) || self.log_w.iter().any(|w| w.is_nan()) {
            return Err(LocalizeError::Snapshot(
                "a sample or weight is not finite".into(),
            ));
        }
        Ok(())
    }

    /// Gives one record of the robot. The record waits in the current window; when the
    /// window is complete ([`Window`]) the update runs against `map` and its report is
    /// returned. Before the map has `min_landmarks` landmarks the record is only counted.
    /// On error nothing changed.
    pub fn push(
        &mut self,
        rec: &Record,
        map: &LandmarkSet,
    ) -> Result<Option<UpdateReport>, LocalizeError> {
        rec.validate(self.models.landmark_kind, self.models.motion_model)
            .map_err(LocalizeError::Record)?;
        if map.kind != self.models.landmark_kind {
            return Err(LocalizeError::Map(format!(
                "the map holds {} landmarks but the robot observes {}",
                map.kind.as_str(),
                self.models.landmark_kind.as_str()
            )));
        }
        if let Some(last) = self.last_time()
            && rec.t < last
        {
            return Err(LocalizeError::Record(format!(
                "record of robot {:?} at t={} is older than its previous record (t={last})",
                rec.robot, rec.t
            )));
        }
        self.stats.records += 1;
        if !self.is_initialised() {
            if map.len() < self.config.min_landmarks {
                self.stats.waiting_records += 1;
                self.last_t = Some(rec.t);
                return Ok(None);
            }
            self.initialise(map, rec.t)?;
        }
        self.pending.push(rec.clone());
        let complete = match self.config.window {
            Window::Fixed { k } => self.pending.len() >= k,
            Window::Budget {
                samples_per_second,
                max,
            } => {
                self.pending.len() >= max
                    || (rec.t - self.window_open_t) * samples_per_second >= self.poses.len() as f64
            }
        };
        if complete {
            self.update(map).map(Some)
        } else {
            Ok(None)
        }
    }

    /// Runs the update of the records waiting in an incomplete window (at the end of a log).
    pub fn flush(&mut self, map: &LandmarkSet) -> Result<Option<UpdateReport>, LocalizeError> {
        if self.pending.is_empty() || !self.is_initialised() {
            return Ok(None);
        }
        self.update(map).map(Some)
    }

    /// Starts from the given samples (equal weights) instead of the uniform prior over the
    /// map: for a robot known to be in some region (a corridor, a room). `t` is the time of
    /// the prior; records before it are refused.
    pub fn initialise_with(&mut self, poses: Vec<Pose2>, t: f64) -> Result<(), LocalizeError> {
        if poses.is_empty() || poses.iter().any(|p| !p.is_finite()) || !t.is_finite() {
            return Err(LocalizeError::Config(
                "a prior needs at least one sample, all finite, and a finite time".into(),
            ));
        }
        if self.is_initialised() || !self.pending.is_empty() {
            return Err(LocalizeError::Config(
                "the localizer is already initialised".into(),
            ));
        }
        let n = poses.len();
        self.poses = poses;
        self.log_w = vec![-math::ln(n as f64); n];
        self.ess = n as f64;
        self.window_open_t = t;
        self.last_t = Some(t);
        self.step += 1;
        Ok(())
    }

    /// Global initialisation: uniform over the map's extent, uniform heading.
    fn initialise(&mut self, map: &LandmarkSet, t: f64) -> Result<(), LocalizeError> {
        let ext = map
            .extent(self.config.init_margin)
            .ok_or_else(|| LocalizeError::Map("the map is empty".into()))?;
        let n = self.config.max_samples;
        let (seed, step) = (self.seed, self.step);
        self.poses = (0..n)
            .into_par_iter()
            .map(|i| {
                let mut rng = stream(seed, step, (SET_INIT << SET_SHIFT) | i as u64);
                let x = ext.min[0] + rng.random::<f64>() * (ext.max[0] - ext.min[0]);
                let y = ext.min[1] + rng.random::<f64>() * (ext.max[1] - ext.min[1]);
                let th = wrap_angle(rng.random::<f64>() * 2.0 * PI - PI);
                Pose2::new(x, y, th)
            })
            .collect();
        self.log_w = vec![-math::ln(n as f64); n];
        self.ess = n as f64;
        self.window_open_t = t;
        self.step += 1;
        Ok(())
    }

    /// The sample budget of the next update: KLD-sampling on the current weighted set, or
    /// `max_samples`.
    fn budget(&self) -> usize {
        let Some(kld) = &self.config.kld else {
            return self.config.max_samples;
        };
        let max = self.config.max_samples;
        let mut cum = Vec::with_capacity(self.log_w.len());
        let mut acc = 0.0;
        for w in &self.log_w {
            acc += math::exp(*w);
            cum.push(acc);
        }
        let mut rng = stream(self.seed, self.step, LANE_KLD);
        let mut bins: HashSet<(i64, i64, i64)> = HashSet::new();
        let mut n = 0;
        while n < max {
            let u = rng.random::<f64>() * acc;
            let i = cum.partition_point(|&c| c < u).min(self.poses.len() - 1);
            let p = &self.poses[i];
            bins.insert((
                (p.x / kld.bin_xy).floor() as i64,
                (p.y / kld.bin_xy).floor() as i64,
                ((p.theta + PI) / kld.bin_theta).floor() as i64,
            ));
            n += 1;
            if n >= kld.min_samples && n >= kld.bound(bins.len()) {
                break;
            }
        }
        n
    }

    /// Resamples `n` samples of `(poses, log_w)` systematically, moves them through the
    /// window's records and adds the log-likelihood of the records marked in `weigh`.
    #[allow(clippy::too_many_arguments)]
    fn run_set(
        &self,
        poses: &[Pose2],
        log_w: &[f64],
        n: usize,
        set: u64,
        steps: &[Step],
        weigh: &[bool],
        scorer: &Scorer<'_>,
        per_record: bool,
        resample: bool,
    ) -> SetResult {
        let idx = if resample {
            let mut rrng = stream(self.seed, self.step, u64::MAX - set);
            systematic_n(log_w, n, &mut rrng)
        } else {
            (0..poses.len()).collect()
        };
        let (seed, step) = (self.seed, self.step);
        let rows: Vec<(Pose2, f64, Vec<f64>)> = idx
            .par_iter()
            .enumerate()
            .map(|(i, &from)| {
                let mut rng = stream(seed, step, (set << SET_SHIFT) | i as u64);
                let mut p = poses[from];
                // Without resampling, a sample keeps its weight.
                let mut ll = if resample { 0.0 } else { log_w[from] };
                let mut rec_ll = Vec::new();
                for (j, s) in steps.iter().enumerate() {
                    p = sample_motion(&p, &s.inc, &s.std, &mut rng);
                    if per_record {
                        rec_ll.push(scorer.record_ll(&p, &s.obs));
                    } else if weigh[j] && !s.obs.is_empty() {
                        ll += scorer.record_ll(&p, &s.obs);
                    }
                }
                (p, ll, rec_ll)
            })
            .collect();
        let mut out = SetResult {
            poses: Vec::with_capacity(n),
            ll: Vec::with_capacity(n),
            per_record: if per_record {
                vec![Vec::with_capacity(n); steps.len()]
            } else {
                Vec::new()
            },
        };
        for (p, ll, rec_ll) in rows {
            out.poses.push(p);
            out.ll.push(ll);
            for (j, l) in rec_ll.into_iter().enumerate() {
                out.per_record[j].push(l);
            }
        }
        out
    }

    /// Gives the mixture weights of the next update of the `rtpf` policy, one per record of
    /// its (fixed) window, in place of the optimised ones; used by that update only. For
    /// experiments: an oracle that knows which records carry the valuable readings bounds
    /// what the weighting can gain (`fleetslam experiment rtpf`, policy `oracle`). Weights
    /// of the wrong length or that do not form a distribution are refused.
    pub fn set_next_weights(&mut self, alpha: Vec<f64>) -> Result<(), LocalizeError> {
        let Window::Fixed { k } = self.config.window else {
            return Err(LocalizeError::Config(
                "mixture weights can be given only with a fixed window".into(),
            ));
        };
        if alpha.len() != k {
            return Err(LocalizeError::Config(format!(
                "{} mixture weights given for a window of {k} records",
                alpha.len()
            )));
        }
        let sum: f64 = alpha.iter().sum();
        if alpha.is_empty()
            || alpha.iter().any(|a| !(a.is_finite() && *a >= 0.0))
            || (sum - 1.0).abs() > 1e-9
        {
            return Err(LocalizeError::Config(format!(
                "mixture weights must be non-negative and sum to 1, got {alpha:?}"
            )));
        }
        self.next_weights = Some(alpha);
        Ok(())
    }

    /// Processes the pending window.
    fn update(&mut self, map: &LandmarkSet) -> Result<UpdateReport, LocalizeError> {
        let records = std::mem::take(&mut self.pending);
        let k = records.len();
        let given = self.next_weights.take().filter(|a| a.len() == k);
        let scorer = Scorer::new(map, &self.models.sensor_noise, self.config.likelihood);
        let mut last = self.last_t;
        let mut steps = Vec::with_capacity(k);
        let mut unmatched = 0u64;
        for r in &records {
            let (inc, std) = motion_of(&self.models, r, last);
            last = Some(r.t);
            let (obs, un) = scorer.resolve(&r.landmarks);
            unmatched += un as u64;
            steps.push(Step { inc, std, obs });
        }
        let has_obs: Vec<bool> = steps.iter().map(|s| !s.obs.is_empty()).collect();
        let observing = has_obs.iter().filter(|b| **b).count();
        let n = self.budget();
        let policy = if k == 1 || observing == 0 {
            Policy::Skip
        } else {
            self.config.policy
        };
        let mut integrated = 0u64;
        let mut skipped = 0u64;
        let mut evals = 0u64;
        let mut gradient_evals = 0u64;
        let mut alpha = Vec::new();
        let (poses, mut log_w) = match policy {
            Policy::Skip => {
                // The newest record with observations; the others' observations are dropped.
                let newest = has_obs.iter().rposition(|b| *b);
                let weigh: Vec<bool> = (0..k).map(|j| Some(j) == newest).collect();
                let keep = n == self.poses.len()
                    && self.ess >= self.config.resample_threshold * n as f64
                    && self.config.resample_threshold < 1.0;
                if newest.is_some() {
                    integrated = 1;
                    skipped = observing as u64 - 1;
                    evals = n as u64;
                }
                let r = self.run_set(
                    &self.poses,
                    &self.log_w,
                    n,
                    0,
                    &steps,
                    &weigh,
                    &scorer,
                    false,
                    !keep,
                );
                (r.poses, r.ll)
            }
            Policy::Naive => {
                // One full filter update per record, with N / k samples each.
                let m = (n / k).max(1);
                let mut poses = self.poses.clone();
                let mut log_w = self.log_w.clone();
                for (j, s) in steps.iter().enumerate() {
                    let r = self.run_set(
                        &poses,
                        &log_w,
                        m,
                        j as u64,
                        std::slice::from_ref(s),
                        &[true],
                        &scorer,
                        false,
                        true,
                    );
                    poses = r.poses;
                    log_w = r.ll;
                    normalize_log_weights(&mut log_w);
                    if has_obs[j] {
                        evals += m as u64;
                    }
                }
                integrated = observing as u64;
                (poses, log_w)
            }
            Policy::Uniform | Policy::Rtpf => {
                // k sample sets; set i integrates record i only (a mixture component).
                let mut poses = Vec::with_capacity(n);
                let mut set_logw: Vec<Vec<f64>> = Vec::with_capacity(k);
                for (i, observes) in has_obs.iter().enumerate() {
                    let ni = (n / k + usize::from(i < n % k)).max(1);
                    let weigh: Vec<bool> = (0..k).map(|j| j == i).collect();
                    let mut r = self.run_set(
                        &self.poses,
                        &self.log_w,
                        ni,
                        i as u64,
                        &steps,
                        &weigh,
                        &scorer,
                        false,
                        true,
                    );
                    normalize_log_weights(&mut r.ll);
                    if *observes {
                        evals += ni as u64;
                    }
                    poses.extend(r.poses);
                    set_logw.push(r.ll);
                }
                integrated = observing as u64;
                alpha = if let Some(given) = given.filter(|_| policy == Policy::Rtpf) {
                    given
                } else if policy == Policy::Rtpf {
                    let m = self.config.rtpf.trajectories_for(n, k);
                    let traj = self.run_set(
                        &self.poses,
                        &self.log_w,
                        m,
                        SET_TRAJECTORIES,
                        &steps,
                        &[],
                        &scorer,
                        true,
                        true,
                    );
                    gradient_evals = (m * observing) as u64;
                    let ends: Vec<[f64; 3]> =
                        traj.poses.iter().map(|p| [p.x, p.y, p.theta]).collect();
                    let groups = group_by_grid(
                        &ends,
                        self.config.rtpf.group_cell,
                        self.config.rtpf.group_cell_theta,
                    );
                    let beliefs = grouped_beliefs(&traj.per_record, &groups);
                    optimise_weights(&beliefs, &self.config.rtpf)
                } else {
                    vec![1.0 / k as f64; k]
                };
                let log_w = set_logw
                    .iter()
                    .zip(&alpha)
                    .flat_map(|(lw, a)| {
                        let la = if *a > 0.0 {
                            math::ln(*a)
                        } else {
                            f64::NEG_INFINITY
                        };
                        lw.iter().map(move |w| w + la)
                    })
                    .collect();
                (poses, log_w)
            }
        };
        self.ess = normalize_log_weights(&mut log_w);
        self.poses = poses;
        self.log_w = log_w;
        self.alpha = alpha;
        self.last_t = last;
        self.window_open_t = last.unwrap_or(self.window_open_t);
        self.step += 1;
        let st = &mut self.stats;
        st.updates += 1;
        st.integrated += integrated;
        st.skipped += skipped;
        st.unmatched_observations += unmatched;
        *st.windows.entry(k).or_insert(0) += 1;
        st.likelihood_evals += evals;
        st.gradient_evals += gradient_evals;

        let s = self.spread();
        let observed = integrated > 0;
        if observed {
            let c = &self.config.convergence;
            let pass = s.position <= c.max_position_spread
                && s.heading <= c.max_heading_spread
                && self.ess >= c.min_ess_fraction * self.poses.len() as f64;
            self.hold = if pass { self.hold + 1 } else { 0 };
            self.converged = self.hold >= c.hold_updates;
        }
        Ok(UpdateReport {
            t: last.unwrap_or(0.0),
            window: k,
            samples: self.poses.len(),
            ess: self.ess,
            mean: s.mean,
            position_spread: s.position,
            heading_spread: s.heading,
            observed,
            converged: self.converged,
            alpha: self.alpha.clone(),
        })
    }
}
