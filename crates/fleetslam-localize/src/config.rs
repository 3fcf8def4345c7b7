//! The configuration of Monte Carlo localization and of the real-time policies. Every field
//! documents its default, unit and trade-off.

use crate::map::LikelihoodParams;
use crate::rtpf::RtpfParams;
use fleetslam_core::config::FilterConfig;
use fleetslam_core::motion::{AckermannParams, MotionModel, MotionNoise};
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use serde::{Deserialize, Serialize};

/// The models a localizer shares with its run (taken from the run's [`FilterConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Models {
    pub landmark_kind: LandmarkKind,
    pub motion_model: MotionModel,
    pub motion_noise: MotionNoise,
    pub ackermann: AckermannParams,
    pub sensor_noise: SensorNoise,
}

impl Models {
    pub fn from_filter(cfg: &FilterConfig) -> Self {
        Self {
            landmark_kind: cfg.landmark_kind,
            motion_model: cfg.motion_model,
            motion_noise: cfg.motion_noise,
            ackermann: cfg.ackermann,
            sensor_noise: cfg.sensor_noise,
        }
    }
}

/// KLD-sampling (Fox 2001): the number of samples is chosen so that, with probability
/// `1 - δ`, the KL divergence between the sample-based and the true posterior stays below
/// `epsilon`, with the posterior discretised into bins of `bin_xy` x `bin_xy` x `bin_theta`:
///
/// ```text
/// n = (k - 1) / (2ε) · (1 - 2/(9(k - 1)) + sqrt(2/(9(k - 1))) · z_{1-δ})³
/// ```
///
/// where `k` is the number of bins with support (Wilson-Hilferty's approximation of the
/// χ² quantile).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct KldParams {
    /// Bin size in x and y [m]. Default 0.5. Smaller bins need more samples.
    pub bin_xy: f64,
    /// Bin size in heading [rad]. Default 10° (0.1745).
    pub bin_theta: f64,
    /// Bound ε on the KL divergence. Default 0.05. Smaller needs more samples.
    pub epsilon: f64,
    /// Upper standard normal quantile `z_{1-δ}`. Default 2.326 (δ = 0.01).
    pub z_quantile: f64,
    /// Fewest samples. Default 100: below that a converged filter cannot recover.
    pub min_samples: usize,
}

impl Default for KldParams {
    fn default() -> Self {
        Self {
            bin_xy: 0.5,
            bin_theta: 10f64.to_radians(),
            epsilon: 0.05,
            z_quantile: 2.326,
            min_samples: 100,
        }
    }
}

impl KldParams {
    /// The bound of Fox 2001 for `k` occupied bins (at least 1 sample).
    pub fn bound(&self, k: usize) -> usize {
        if k < 2 {
            return 1;
        }
        let k1 = (k - 1) as f64;
        let a = 2.0 / (9.0 * k1);
        let c = 1.0 - a + a.sqrt() * self.z_quantile;
        (k1 / (2.0 * self.epsilon) * c * c * c).ceil() as usize
    }
}

/// When a localizer's posterior counts as converged.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ConvergenceParams {
    /// Largest weighted position spread `sqrt(var x + var y)` [m]. Default 0.5.
    pub max_position_spread: f64,
    /// Largest weighted heading spread `sqrt(-2 ln R)` (R the mean resultant length) [rad].
    /// Default 0.25.
    pub max_heading_spread: f64,
    /// Smallest effective sample size, as a fraction of the samples. Default 0.02: a
    /// posterior carried by a handful of samples may look tight by accident.
    pub min_ess_fraction: f64,
    /// Consecutive updates the three tests must hold. Default 5. More is safer and later.
    /// Only updates that integrated an observation count; pure motion updates neither count
    /// nor reset the streak.
    pub hold_updates: usize,
}

impl Default for ConvergenceParams {
    fn default() -> Self {
        Self {
            max_position_spread: 0.5,
            max_heading_spread: 0.25,
            min_ess_fraction: 0.02,
            hold_updates: 5,
        }
    }
}

/// What to do with the observations that arrive during one filter update.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Policy {
    /// Integrate the newest observation of the window with all samples; drop the rest (counted).
    Skip,
    /// One particle filter update per observation, each with `N / k` samples.
    Naive,
    /// `k` sample sets of `N / k`, set `i` integrating observation `i`; equal mixture weights.
    Uniform,
    /// As `uniform`, with mixture weights that minimise the KL divergence to the full
    /// posterior (Kwok, Fox, Meila). The default.
    #[default]
    Rtpf,
}

impl Policy {
    pub const ALL: [Policy; 4] = [Policy::Skip, Policy::Naive, Policy::Uniform, Policy::Rtpf];

    pub fn as_str(self) -> &'static str {
        match self {
            Policy::Skip => "skip",
            Policy::Naive => "naive",
            Policy::Uniform => "uniform",
            Policy::Rtpf => "rtpf",
        }
    }
}

/// How many records one update covers. Decided from the records' timestamps only, never
/// from the wall clock, so that the same data gives the same windows (and results) on any
/// machine and after a crash recovery.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Window {
    /// Exactly `k` records per update (`k = 1`: every record is integrated with all samples,
    /// the policies coincide).
    Fixed { k: usize },
    /// A compute budget: one update of `N` samples takes `N / samples_per_second` seconds of
    /// data time, and the records whose time falls within it form the window (at most
    /// `max`). With KLD-sampling, a converged filter's small `N` shrinks the window to one
    /// record, as the paper's conclusion suggests.
    Budget { samples_per_second: f64, max: usize },
}

impl Default for Window {
    fn default() -> Self {
        Window::Fixed { k: 1 }
    }
}

/// The largest window.
pub const MAX_WINDOW: usize = 64;

/// The configuration of one localizer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LocalizeConfig {
    /// Samples of the global initialisation, the upper bound of KLD-sampling and the budget
    /// of an update when KLD-sampling is off. Default 5000. Global localization in a large
    /// or symmetric map needs many.
    pub max_samples: usize,
    /// KLD-sampling; `null` keeps `max_samples` throughout. Default on.
    pub kld: Option<KldParams>,
    /// Margin around the landmarks' bounding box for the uniform initialisation [m].
    /// Default 2.0: a robot can stand outside the landmarks' hull.
    pub init_margin: f64,
    /// Landmarks the map needs before localization starts. Default 3: with fewer, a
    /// range-bearing robot's pose is not determined.
    pub min_landmarks: usize,
    pub likelihood: LikelihoodParams,
    pub convergence: ConvergenceParams,
    /// A one-record (or `skip`) update keeps the weighted samples without resampling while
    /// their effective sample size stays at or above this fraction of the samples and the
    /// budget is unchanged. Default 0.5. Resampling at every update makes the modes of a
    /// multi-modal belief (a symmetric map) die out at random; 1.0 resamples always. The
    /// mixture policies always draw their sample sets anew.
    pub resample_threshold: f64,
    /// Policy for windows of more than one record. Default `rtpf`.
    pub policy: Policy,
    /// Window size rule. Default one record per update.
    pub window: Window,
    pub rtpf: RtpfParams,
}

impl Default for LocalizeConfig {
    fn default() -> Self {
        Self {
            max_samples: 5000,
            kld: Some(KldParams::default()),
            init_margin: 2.0,
            min_landmarks: 3,
            likelihood: LikelihoodParams::default(),
            convergence: ConvergenceParams::default(),
            resample_threshold: 0.5,
            policy: Policy::default(),
            window: Window::default(),
            rtpf: RtpfParams::default(),
        }
    }
}

impl LocalizeConfig {
    /// Checks every field; the message names the field and the allowed values.
    pub fn validate(&self) -> Result<(), String> {
        if !(1..=1_000_000).contains(&self.max_samples) {
            return Err(format!(
                "max_samples must be between 1 and 1000000, got {}",
                self.max_samples
            ));
        }
        if let Some(k) = &self.kld {
            for (name, v) in [
                ("kld.bin_xy", k.bin_xy),
                ("kld.bin_theta", k.bin_theta),
                ("kld.epsilon", k.epsilon),
                ("kld.z_quantile", k.z_quantile),
            ] {
                if !(v.is_finite() && v > 0.0) {
                    return Err(format!("{name} must be a finite number > 0, got {v}"));
                }
            }
            if k.min_samples == 0 || k.min_samples > self.max_samples {
                return Err(format!(
                    "kld.min_samples must be between 1 and max_samples ({}), got {}",
                    self.max_samples, k.min_samples
                ));
            }
        }
        if !(self.init_margin.is_finite() && self.init_margin >= 0.0) {
            return Err(format!(
                "init_margin must be a finite length >= 0 [m], got {}",
                self.init_margin
            ));
        }
        if !(self.resample_threshold.is_finite() && (0.0..=1.0).contains(&self.resample_threshold))
        {
            return Err(format!(
                "resample_threshold must be a fraction between 0 and 1, got {}",
                self.resample_threshold
            ));
        }
        if self.min_landmarks == 0 {
            return Err("min_landmarks must be at least 1".into());
        }
        let l = &self.likelihood;
        if !(l.noise_scale.is_finite() && l.noise_scale > 0.0) {
            return Err(format!(
                "likelihood.noise_scale must be a finite number > 0, got {}",
                l.noise_scale
            ));
        }
        if !(l.outlier_mahalanobis2.is_finite() && l.outlier_mahalanobis2 > 0.0) {
            return Err(format!(
                "likelihood.outlier_mahalanobis2 must be a finite number > 0, got {}",
                l.outlier_mahalanobis2
            ));
        }
        let c = &self.convergence;
        for (name, v) in [
            ("convergence.max_position_spread", c.max_position_spread),
            ("convergence.max_heading_spread", c.max_heading_spread),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be a finite number > 0, got {v}"));
            }
        }
        if !(c.min_ess_fraction.is_finite() && (0.0..=1.0).contains(&c.min_ess_fraction)) {
            return Err(format!(
                "convergence.min_ess_fraction must be between 0 and 1, got {}",
                c.min_ess_fraction
            ));
        }
        if c.hold_updates == 0 {
            return Err("convergence.hold_updates must be at least 1".into());
        }
        match self.window {
            Window::Fixed { k } if !(1..=MAX_WINDOW).contains(&k) => {
                return Err(format!(
                    "window.fixed.k must be between 1 and {MAX_WINDOW}, got {k}"
                ));
            }
            Window::Budget {
                samples_per_second,
                max,
            } => {
                if !(samples_per_second.is_finite() && samples_per_second > 0.0) {
                    return Err(format!(
                        "window.budget.samples_per_second must be a finite number > 0, got {samples_per_second}"
                    ));
                }
                if !(1..=MAX_WINDOW).contains(&max) {
                    return Err(format!(
                        "window.budget.max must be between 1 and {MAX_WINDOW}, got {max}"
                    ));
                }
            }
            _ => {}
        }
        self.rtpf.validate()
    }
}
