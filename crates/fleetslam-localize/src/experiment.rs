//! The experiment of the real-time particle filter paper (Kwok, Fox, Meila, section 4),
//! reproduced in simulation: `fleetslam experiment rtpf`.
//!
//! **Worlds.** A rectangular hallway loop ([`LoopWorld`]) lined with identical posts, in two
//! settings ([`Setting`]):
//! - `building` ([`LoopWorld::building`], [`RtpfExperiment::building`]), the paper-like
//!   one: a 36 m x 12 m loop whose posts repeat in a 12 m module (8 identical places), a
//!   dense scan of about ten readings per record through two side-looking fields of view
//!   (the paper's robot measured the distances to the walls on its left and right), and
//!   four distinguishing posts that are recognised in about two consecutive records only;
//! - `corridor` ([`LoopWorld::default`]): a 24 m x 12 m loop whose second half is the
//!   first turned by half a turn (every view recurs once), a forward-looking sensor and
//!   three distinguishing posts visible for several metres.
//!
//! Observations carry no ids (association by maximum likelihood), as the paper's robot saw
//! only distances to walls.
//!
//! **Robot.** It drives around the loop from a random place (one per seed) at 0.5 m per
//! record (one record per second), reports noisy odometry, and sees the posts in its fields
//! of view with range-bearing noise.
//!
//! **Prior.** Uniform along the corridor, facing along it in either direction
//! ([`RtpfExperiment::corridor_prior`]): the free space of the paper's map is its corridors.
//!
//! **Policies.** With a fixed sample budget `N` per update, a window of `k` records per
//! update: `skip`, `naive`, `uniform` and `rtpf` ([`crate::config::Policy`]), and the
//! baseline that integrates every record with `N` samples (unlimited time).
//!
//! **Measures.** The localization error after each update is the weighted mean distance of
//! the samples from the true position (the paper's "average distance between the samples
//! and the reference positions"); the localization time of a run is the first time from
//! which the error stays below a threshold for a hold period (runs that never localize count
//! at the end time and are reported). Means come with 95% confidence intervals
//! (`± 1.96 s / √n`, the normal approximation), and the speedup of RTPF over skip is the
//! ratio of their mean localization times with a paired bootstrap interval ([`speedups`]).

use crate::config::{LocalizeConfig, Models, Policy, Window};
use crate::error::LocalizeError;
use crate::localizer::Localizer;
use crate::map::{LandmarkSet, LikelihoodParams, MapLandmark};
use crate::rtpf::RtpfParams;
use fleetslam_core::log::{LandmarkObservation, Record};
use fleetslam_core::math;
use fleetslam_core::motion::{AckermannParams, Motion, MotionModel, MotionNoise};
use fleetslam_core::pose::{Pose2, wrap_angle};
use fleetslam_core::rng::StandardNormal;
use fleetslam_core::rng::chacha_stream as stream;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise, range_bearing_predict};
use fleetslam_core::updater::LandmarkGaussian;
use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::FRAC_PI_2;
use std::fmt::Write as _;
use std::path::Path;

/// The simulated corridor loop.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoopWorld {
    /// Length of the loop's long sides (centre line) [m]. Default 24.
    pub length: f64,
    /// Length of the short sides [m]. Default 12.
    pub width: f64,
    /// Mean spacing of the posts along the loop [m]. Default 2.
    pub post_spacing: f64,
    /// Distance of the walls' posts from the centre line [m]. Default 1.5.
    pub wall_offset: f64,
    /// Distinguishing posts, placed at unique places. Default 3.
    pub features: usize,
    /// Distance travelled per record [m]. Default 0.5 (the paper's 50 cm).
    pub step: f64,
    /// Sensor range [m]. Default 3.5.
    pub max_range: f64,
    /// Sensor field of view [rad]. Default π (the half plane ahead).
    pub fov: f64,
    /// Probability that a post in view is detected. Default 0.9.
    pub detection: f64,
    /// Length of the repeated module of posts along the loop [m]. Default 0: the posts of
    /// the first half of the loop recur on the second half turned by half a turn (every view
    /// recurs once). A positive length repeats one module's posts all around the loop, as
    /// identical offices along a hallway: every view recurs `perimeter / period` times.
    pub period: f64,
    /// Where the sensor looks. Default false: one field of view of `fov` centred ahead. True:
    /// two fields of view of `fov` each, centred to the left and to the right, as the
    /// paper's robot saw the walls with two laser beams pointing sideways.
    pub sides: bool,
    /// Range within which a distinguishing post is detected [m]. Default 3.5 (as the other
    /// posts). Shorter makes the distinguishing posts visible in fewer consecutive records,
    /// the "valuable sensor data occurring at unpredictable time points" for which the paper
    /// expects the largest gain.
    pub feature_range: f64,
}

impl Default for LoopWorld {
    fn default() -> Self {
        Self {
            length: 24.0,
            width: 12.0,
            post_spacing: 2.0,
            wall_offset: 1.5,
            features: 3,
            step: 0.5,
            max_range: 3.5,
            fov: std::f64::consts::PI,
            detection: 0.9,
            period: 0.0,
            sides: false,
            feature_range: 3.5,
        }
    }
}

impl LoopWorld {
    /// The paper-like building (`--setting building`): a 36 m x 12 m hallway loop whose
    /// walls are lined with posts every 0.5 m on average (a dense scan: about nine readings
    /// per record), in a 12 m module repeated 8 times around the loop (identical offices:
    /// every view recurs 8 times, and each side of the loop is a whole number of modules,
    /// so the corners look alike too); the robot sees both walls through two side-looking
    /// fields of view of 120°, as the paper's robot saw them with two beams pointing left
    /// and right; four distinguishing posts half-way to the wall are recognised within
    /// 0.9 m only, that is in about two consecutive records.
    pub fn building() -> Self {
        Self {
            length: 36.0,
            width: 12.0,
            post_spacing: 0.5,
            wall_offset: 1.5,
            features: 4,
            step: 0.5,
            max_range: 3.5,
            fov: 120f64.to_radians(),
            detection: 0.9,
            period: 12.0,
            sides: true,
            feature_range: 0.9,
        }
    }
}

/// The robot's sensor noise in the experiment.
pub const SENSOR_NOISE: SensorNoise = SensorNoise {
    range: 0.1,
    bearing: 0.05,
    xyz: [0.05; 3],
    range_per_m: 0.0,
};

/// One simulated run: the map, the records and the true pose after each record.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopRun {
    pub map: LandmarkSet,
    pub records: Vec<Record>,
    pub truth: Vec<Pose2>,
    /// Distinguishing posts detected in each record (the readings carry no ids; this is the
    /// simulator's knowledge, used only by the diagnostics of [`RunResult`]).
    pub features: Vec<u32>,
}

impl LoopWorld {
    /// The perimeter of the centre line [m].
    pub fn perimeter(&self) -> f64 {
        2.0 * (self.length + self.width)
    }

    /// The point at arc length `s` along the centre line (counter-clockwise from the origin)
    /// and the heading of the side it is on.
    fn along(&self, s: f64) -> (f64, f64, f64) {
        let s = s.rem_euclid(self.perimeter());
        let (l, w) = (self.length, self.width);
        if s < l {
            (s, 0.0, 0.0)
        } else if s < l + w {
            (l, s - l, FRAC_PI_2)
        } else if s < 2.0 * l + w {
            (l - (s - l - w), w, std::f64::consts::PI)
        } else {
            (0.0, w - (s - 2.0 * l - w), -FRAC_PI_2)
        }
    }

    /// The posts: along the first half of the loop, at irregular spacings (between 0.5 and
    /// 1.5 times `post_spacing`, from a fixed seed) on either wall; the second half is the
    /// first turned by half a turn about the loop's centre, so that the map is symmetric
    /// and every view of one half recurs in the other. The distinguishing posts sit at
    /// unique places, half-way to the inner wall.
    pub fn map(&self) -> LandmarkSet {
        let mut lms = Vec::new();
        let cov = [1e-4, 0.0, 0.0, 1e-4, 0.0, 1e-4];
        let post = |x: f64, y: f64| MapLandmark {
            id: None,
            gaussian: LandmarkGaussian {
                mean: [x, y, 0.0],
                cov,
            },
        };
        let mut rng = stream(0x5EED_10CA, 0, 0);
        let wall = |s: f64, side: f64| {
            let (x, y, th) = self.along(s);
            (
                x - side * self.wall_offset * math::sin(th),
                y + side * self.wall_offset * math::cos(th),
            )
        };
        if self.period > 0.0 {
            // One module's posts (arc length within the module, side), then every copy.
            let mut module = Vec::new();
            let mut s = rng.random::<f64>() * self.post_spacing;
            while s < self.period {
                module.push((s, if rng.random::<bool>() { 1.0 } else { -1.0 }));
                s += self.post_spacing * (0.5 + rng.random::<f64>());
            }
            let copies = (self.perimeter() / self.period).floor() as usize;
            for c in 0..copies {
                for &(s, side) in &module {
                    let (px, py) = wall(c as f64 * self.period + s, side);
                    lms.push(post(px, py));
                }
            }
        } else {
            let half = 0.5 * self.perimeter();
            let mut s = rng.random::<f64>() * self.post_spacing;
            while s < half {
                let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
                let (px, py) = wall(s, side);
                lms.push(post(px, py));
                lms.push(post(self.length - px, self.width - py));
                s += self.post_spacing * (0.5 + rng.random::<f64>());
            }
        }
        for f in 0..self.features {
            let frac = [0.35, 0.6, 0.9, 0.15, 0.7][f % 5] + 0.01 * (f / 5) as f64;
            let (x, y, th) = self.along(frac * self.perimeter());
            let off = 0.5 * self.wall_offset;
            lms.push(post(x - off * math::sin(th), y + off * math::cos(th)));
        }
        LandmarkSet {
            kind: LandmarkKind::RangeBearing2d,
            landmarks: lms,
        }
    }

    /// Simulates `records` records from a start chosen by `seed`. The robot follows the
    /// centre line (forward `step` per record, a quarter turn in place at each corner); its
    /// odometry reports each increment with noise drawn from `noise`.
    pub fn simulate(&self, seed: u64, records: usize, noise: &MotionNoise) -> LoopRun {
        let map = self.map();
        let mut rng = stream(seed, 0, 0x51A1);
        let steps_per_side_l = (self.length / self.step).round() as usize;
        let steps_per_side_w = (self.width / self.step).round() as usize;
        let sides = [
            steps_per_side_l,
            steps_per_side_w,
            steps_per_side_l,
            steps_per_side_w,
        ];
        // Start at a random step of a random side.
        let mut side = rng.random_range(0..4usize);
        let mut done = rng.random_range(0..sides[side]);
        let s0 = sides[..side].iter().sum::<usize>() as f64 * self.step + done as f64 * self.step;
        let (x, y, th) = self.along(s0);
        let mut truth_pose = Pose2::new(x, y, th);
        let mut out = LoopRun {
            map: map.clone(),
            records: Vec::with_capacity(records),
            truth: Vec::with_capacity(records),
            features: Vec::with_capacity(records),
        };
        for r in 0..records {
            let inc = if done >= sides[side] {
                side = (side + 1) % 4;
                done = 0;
                Pose2::new(0.0, 0.0, FRAC_PI_2)
            } else {
                done += 1;
                Pose2::new(self.step, 0.0, 0.0)
            };
            truth_pose = truth_pose.compose(&inc);
            let var = noise.variances(&inc, 1.0);
            let odo: [f64; 3] = std::array::from_fn(|i| {
                [inc.x, inc.y, inc.theta][i] + var[i].sqrt() * rng.sample::<f64, _>(StandardNormal)
            });
            let mut landmarks = Vec::new();
            let mut features = 0u32;
            let first_feature = map.len() - self.features;
            for (li, l) in map.landmarks.iter().enumerate() {
                let Some((z, _, _)) =
                    range_bearing_predict(&truth_pose, l.gaussian.mean[0], l.gaussian.mean[1])
                else {
                    continue;
                };
                let range = if li >= first_feature {
                    self.max_range.min(self.feature_range)
                } else {
                    self.max_range
                };
                let off_axis = if self.sides {
                    (z[1].abs() - FRAC_PI_2).abs()
                } else {
                    z[1].abs()
                };
                if z[0] > range || off_axis > 0.5 * self.fov {
                    continue;
                }
                if rng.random::<f64>() > self.detection {
                    continue;
                }
                features += u32::from(li >= first_feature);
                let range =
                    (z[0] + SENSOR_NOISE.range * rng.sample::<f64, _>(StandardNormal)).max(0.01);
                let bearing =
                    wrap_angle(z[1] + SENSOR_NOISE.bearing * rng.sample::<f64, _>(StandardNormal));
                landmarks.push(LandmarkObservation {
                    id: None,
                    z: vec![range, bearing],
                });
            }
            out.records.push(Record {
                robot: "r".into(),
                seq: r as u64,
                t: (r + 1) as f64,
                motion: Some(Motion::Odometry(odo)),
                landmarks,
                robots: Vec::new(),
            });
            out.truth.push(truth_pose);
            out.features.push(features);
        }
        out
    }
}

/// The experiment's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RtpfExperiment {
    pub world: LoopWorld,
    /// Window sizes. Default 2 to 14.
    pub windows: Vec<usize>,
    /// Policies besides the baseline. Default all four.
    pub policies: Vec<Policy>,
    /// Seeds (runs per policy and window). Default 30.
    pub seeds: usize,
    /// Sample budget per update. Default 3000.
    pub samples: usize,
    /// Records per run (one per second). Default 300 (about two laps).
    pub records: usize,
    /// Localization error threshold [m]. Default 1.0.
    pub threshold: f64,
    /// The error must stay below the threshold this long [s]. Default 20.
    pub hold_seconds: f64,
    /// Odometry noise of the simulated robot (and of the filter).
    pub motion_noise: MotionNoise,
    /// RTPF's mixture-weight optimisation.
    pub rtpf: RtpfParams,
    /// The localizer's `resample_threshold` (one-record and skip updates). Default 0.5;
    /// 1.0 resamples at every update, as the paper's filters do.
    pub resample_threshold: f64,
    /// Run the baseline (every record with the full budget). Default true; an ablation
    /// that does not change it can leave it out (it costs as much as `k` policies' runs
    /// at window `k`).
    pub baseline: bool,
    /// Also run RTPF with oracle weights (policy `oracle`): each window's mixture weight
    /// spread evenly over the records in which a distinguishing post was detected (uniform
    /// when there is none), in place of the optimised weights. Default false. It bounds
    /// what the weighting can gain: the speedup the weighting would give if it recognised
    /// the valuable records without error.
    pub oracle: bool,
}

/// The two settings of the experiment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Setting {
    /// The paper-like building ([`LoopWorld::building`], [`RtpfExperiment::building`]).
    Building,
    /// The small symmetric corridor loop ([`LoopWorld::default`], [`RtpfExperiment::default`]).
    Corridor,
}

impl RtpfExperiment {
    /// The settings of one experiment: the building's are [`RtpfExperiment::building`].
    pub fn preset(setting: Setting) -> Self {
        match setting {
            Setting::Building => Self::building(),
            Setting::Corridor => Self::default(),
        }
    }

    /// The paper-like experiment: the building of [`LoopWorld::building`], 30 seeds, the
    /// paper's windows 4 and 8 to 12, 2000 samples per update (the budget of one update;
    /// a window of `k` records spends it on `k` records), 300 records per run (about two
    /// laps). The budget and the length are what the 2-core machine of this project runs
    /// for 30 seeds in minutes; the paper used 20,000 samples.
    pub fn building() -> Self {
        Self {
            world: LoopWorld::building(),
            windows: vec![4, 8, 9, 10, 11, 12],
            samples: 2000,
            records: 300,
            ..Self::default()
        }
    }
}

impl Default for RtpfExperiment {
    fn default() -> Self {
        Self {
            world: LoopWorld::default(),
            windows: (2..=14).collect(),
            policies: Policy::ALL.to_vec(),
            seeds: 30,
            samples: 3000,
            records: 300,
            threshold: 1.0,
            hold_seconds: 20.0,
            motion_noise: MotionNoise {
                trans_per_m: 0.1,
                lateral_per_m: 0.05,
                rot_per_rad: 0.05,
                rot_per_m: 0.05,
                trans_per_sqrt_s: 0.01,
                rot_per_sqrt_s: 0.01,
                random_walk_max_dt: 1.0,
            },
            rtpf: RtpfParams::default(),
            resample_threshold: 0.5,
            baseline: true,
            oracle: false,
        }
    }
}

/// The result of one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    /// "baseline" or a policy's name.
    pub policy: String,
    /// Window size (1 for the baseline).
    pub window: usize,
    pub seed: u64,
    /// Error [m] at each second 1..=records (the latest update's).
    pub error: Vec<f64>,
    /// Localization time [s]; `None` if the run never localized.
    pub time: Option<f64>,
    pub skipped: u64,
    pub integrated: u64,
    pub likelihood_evals: u64,
    pub gradient_evals: u64,
    /// Diagnostics of how the run used the distinguishing posts ([`Diagnostics`]).
    pub diagnostics: Diagnostics,
}

/// A sample is at the true place when it is within this distance of the true position
/// [m] (the paper's 200 cm localization threshold) ...
pub const TRUE_PLACE_RADIUS: f64 = 2.0;
/// ... and within this angle of the true heading [rad] (the loop is travelled both ways, so
/// a sample at the right spot facing the wrong way is at one of the similar places).
pub const TRUE_PLACE_HEADING: f64 = std::f64::consts::FRAC_PI_4;
/// The belief has lost the true place when its mass there falls below this.
pub const LOST_MASS: f64 = 1e-3;

/// What a run did with the distinguishing posts, and whether its belief kept the true place:
/// the measures that separate the ingredients of RTPF's gain (the simulator knows which
/// readings came from a distinguishing post; the filter does not).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Diagnostics {
    /// Updates whose window held a record in which a distinguishing post was detected.
    pub feature_windows: u64,
    /// Of those, the updates that integrated such a record (skip integrates only the newest
    /// record with readings; the other policies integrate every record).
    pub feature_integrated: u64,
    /// Sum over the feature windows of the mixture weight on the sample sets that integrated
    /// a feature record (the mixtures: `uniform`, `rtpf` and `oracle`; 0 for the others).
    pub feature_alpha: f64,
    /// Sums over the updates that integrated a feature record of the belief's mass at the
    /// true place before (after the previous update) and after the update.
    pub feature_mass_before: f64,
    pub feature_mass_after: f64,
    /// The smallest mass at the true place over the updates before the run localized (over
    /// the whole run if it never did).
    pub min_true_mass: f64,
}

/// The weight of the samples at the true place ([`TRUE_PLACE_RADIUS`], [`TRUE_PLACE_HEADING`]).
pub fn true_place_mass(poses: &[Pose2], weights: &[f64], truth: &Pose2) -> f64 {
    poses
        .iter()
        .zip(weights)
        .filter(|(p, _)| {
            p.distance(truth) <= TRUE_PLACE_RADIUS
                && wrap_angle(p.theta - truth.theta).abs() <= TRUE_PLACE_HEADING
        })
        .fold(0.0, |m, (_, w)| m + w)
}

/// Mean and 95% confidence half-width (normal approximation).
pub fn mean_ci(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    if xs.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let m = xs.iter().sum::<f64>() / n;
    if xs.len() < 2 {
        return (m, 0.0);
    }
    let var = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, 1.96 * (var / n).sqrt())
}

/// The first time from which `error` (one value per second, from t = 1) stays at or below
/// `threshold` for `hold` seconds; `None` if never.
pub fn localization_time(error: &[f64], threshold: f64, hold: f64) -> Option<f64> {
    let hold = hold.ceil() as usize;
    let mut run = 0usize;
    for (i, e) in error.iter().enumerate() {
        if *e <= threshold {
            run += 1;
            if run > hold {
                return Some((i + 1 - hold) as f64);
            }
        } else {
            run = 0;
        }
    }
    None
}

impl RtpfExperiment {
    pub fn validate(&self) -> Result<(), LocalizeError> {
        let bad = |m: String| Err(LocalizeError::Config(m));
        if self.windows.is_empty() || self.windows.iter().any(|k| !(1..=64).contains(k)) {
            return bad(format!(
                "windows must be sizes between 1 and 64, got {:?}",
                self.windows
            ));
        }
        if self.seeds == 0 || self.records == 0 || self.samples < 2 {
            return bad("seeds and records must be >= 1 and samples >= 2".into());
        }
        if !(self.threshold > 0.0 && self.hold_seconds >= 0.0) {
            return bad("threshold must be > 0 and hold_seconds >= 0".into());
        }
        let w = &self.world;
        if !(w.length > 0.0 && w.width > 0.0 && w.post_spacing > 0.0 && w.step > 0.0) {
            return bad("world lengths must be > 0".into());
        }
        self.motion_noise.validate().map_err(LocalizeError::Config)
    }

    /// The models of the simulated robot (and of its localizer).
    pub fn models(&self) -> Models {
        Models {
            landmark_kind: LandmarkKind::RangeBearing2d,
            motion_model: MotionModel::Odometry,
            motion_noise: self.motion_noise,
            ackermann: AckermannParams::default(),
            sensor_noise: SENSOR_NOISE,
        }
    }

    /// The localizer configuration of one run: fixed budget (no KLD), anonymous posts.
    pub fn localize_config(&self, policy: Policy, window: usize) -> LocalizeConfig {
        LocalizeConfig {
            max_samples: self.samples,
            kld: None,
            init_margin: 1.0,
            min_landmarks: 1,
            likelihood: LikelihoodParams {
                use_ids: false,
                ..Default::default()
            },
            policy,
            window: Window::Fixed { k: window },
            rtpf: self.rtpf,
            resample_threshold: self.resample_threshold,
            ..Default::default()
        }
    }

    /// The prior of a run: uniform along the corridor (arc length uniform, up to 0.5 m across
    /// the centre line) with the heading along the corridor in either direction (σ 0.1 rad):
    /// the robot is known to be in the corridor facing along it, not where nor which way.
    pub fn corridor_prior(&self, seed: u64) -> Vec<Pose2> {
        let w = &self.world;
        (0..self.samples)
            .map(|i| {
                let mut rng = stream(seed, 0, 0xC0_0000 + i as u64);
                let (x, y, th) = w.along(rng.random::<f64>() * w.perimeter());
                let lat = rng.random_range(-0.5..0.5);
                let back = if rng.random::<bool>() {
                    std::f64::consts::PI
                } else {
                    0.0
                };
                let dth = 0.1 * rng.sample::<f64, _>(StandardNormal);
                Pose2::new(
                    x - lat * math::sin(th),
                    y + lat * math::cos(th),
                    wrap_angle(th + back + dth),
                )
            })
            .collect()
    }

    /// One run of a policy (`None`: the baseline).
    pub fn run_one(
        &self,
        sim: &LoopRun,
        policy: Option<Policy>,
        window: usize,
        seed: u64,
    ) -> Result<RunResult, LocalizeError> {
        self.run_with(sim, policy, window, seed, false)
    }

    /// One run of RTPF with oracle weights ([`RtpfExperiment::oracle`]).
    pub fn run_oracle(
        &self,
        sim: &LoopRun,
        window: usize,
        seed: u64,
    ) -> Result<RunResult, LocalizeError> {
        self.run_with(sim, Some(Policy::Rtpf), window, seed, true)
    }

    fn run_with(
        &self,
        sim: &LoopRun,
        policy: Option<Policy>,
        window: usize,
        seed: u64,
        oracle: bool,
    ) -> Result<RunResult, LocalizeError> {
        let cfg = self.localize_config(policy.unwrap_or_default(), window);
        let mut loc = Localizer::new(self.models(), cfg, seed.wrapping_mul(1000) + window as u64)?;
        let prior = self.corridor_prior(seed);
        // The first update's "before" is the prior's mass around the first true pose.
        let mut mass = true_place_mass(
            &prior,
            &vec![1.0 / prior.len() as f64; prior.len()],
            &sim.truth[0],
        );
        loc.initialise_with(prior, 0.0)?;
        let mut error = Vec::with_capacity(sim.records.len());
        let mut current = f64::NAN;
        let mut diag = Diagnostics::default();
        // (update time, mass at the true place after it), for `min_true_mass`.
        let mut masses: Vec<(f64, f64)> = Vec::new();
        let mut window_start = 0usize;
        for (i, r) in sim.records.iter().enumerate() {
            if oracle && window > 1 && (i + 1) % window == 0 {
                // The window's last record: weigh the records that saw a feature.
                let seen = &sim.features[i + 1 - window..=i];
                let count = seen.iter().filter(|f| **f > 0).count();
                let alpha = seen
                    .iter()
                    .map(|f| match count {
                        0 => 1.0 / window as f64,
                        c if *f > 0 => 1.0 / c as f64,
                        _ => 0.0,
                    })
                    .collect();
                loc.set_next_weights(alpha)?;
            }
            if let Some(rep) = loc.push(r, &sim.map)? {
                // The belief is at the window's last record, which is this one.
                let (poses, w) = loc.posterior();
                let truth = sim.truth[(rep.t as usize) - 1];
                current = poses
                    .iter()
                    .zip(&w)
                    .map(|(p, w)| w * p.distance(&truth))
                    .sum();
                let after = true_place_mass(&poses, &w, &truth);
                let window = window_start..=i;
                window_start = i + 1;
                let seen: Vec<bool> = sim.features[window.clone()]
                    .iter()
                    .map(|f| *f > 0)
                    .collect();
                if seen.iter().any(|s| *s) {
                    diag.feature_windows += 1;
                    let integrated = match policy {
                        Some(Policy::Skip) => sim.records[window]
                            .iter()
                            .rposition(|r| !r.landmarks.is_empty())
                            .is_some_and(|j| seen[j]),
                        _ => true,
                    };
                    if rep.alpha.len() == seen.len() {
                        diag.feature_alpha += rep
                            .alpha
                            .iter()
                            .zip(&seen)
                            .filter(|(_, s)| **s)
                            .map(|(a, _)| a)
                            .sum::<f64>();
                    }
                    if integrated {
                        diag.feature_integrated += 1;
                        diag.feature_mass_before += mass;
                        diag.feature_mass_after += after;
                    }
                }
                mass = after;
                masses.push((rep.t, after));
            }
            error.push(current);
        }
        // Before the first update the belief is the uniform prior: its error is large.
        let first = error
            .iter()
            .position(|e| e.is_finite())
            .unwrap_or(error.len());
        let fill = error.get(first).copied().unwrap_or(f64::NAN);
        error.iter_mut().take(first).for_each(|e| *e = fill);
        let st = loc.stats();
        let time = localization_time(&error, self.threshold, self.hold_seconds);
        diag.min_true_mass = masses
            .iter()
            .filter(|(t, _)| time.is_none_or(|lt| *t < lt))
            .map(|(_, m)| *m)
            .fold(1.0, f64::min);
        Ok(RunResult {
            policy: match policy {
                _ if oracle => "oracle".into(),
                None => "baseline".into(),
                Some(p) => p.as_str().into(),
            },
            window,
            seed,
            time,
            error,
            skipped: st.skipped,
            integrated: st.integrated,
            likelihood_evals: st.likelihood_evals,
            gradient_evals: st.gradient_evals,
            diagnostics: diag,
        })
    }

    /// Every run: the baseline once per seed (unless left out), each policy for each window
    /// and seed. Runs go in parallel; each is deterministic, so the result does not depend
    /// on the threads.
    pub fn run(
        &self,
        progress: impl Fn(usize, usize) + Sync,
    ) -> Result<Vec<RunResult>, LocalizeError> {
        self.validate()?;
        let sims: Vec<LoopRun> = (0..self.seeds as u64)
            .into_par_iter()
            .map(|s| self.world.simulate(s, self.records, &self.motion_noise))
            .collect();
        // (policy, oracle weights, window, seed)
        let mut jobs: Vec<(Option<Policy>, bool, usize, u64)> = if self.baseline {
            (0..self.seeds as u64)
                .map(|s| (None, false, 1, s))
                .collect()
        } else {
            Vec::new()
        };
        for &k in &self.windows {
            let oracle = self.oracle.then_some((Policy::Rtpf, true));
            for (p, o) in self.policies.iter().map(|p| (*p, false)).chain(oracle) {
                for s in 0..self.seeds as u64 {
                    jobs.push((Some(p), o, k, s));
                }
            }
        }
        let total = jobs.len();
        let done = std::sync::atomic::AtomicUsize::new(0);
        jobs.par_iter()
            .map(|&(p, o, k, s)| {
                let r = self.run_with(&sims[s as usize], p, k, s, o);
                let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                progress(d, total);
                r
            })
            .collect()
    }
}

/// Summary of the runs of one policy and window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub policy: String,
    pub window: usize,
    pub runs: usize,
    pub localized: usize,
    /// Mean localization time [s] (runs that never localized count at the end time).
    pub time_mean: f64,
    pub time_ci95: f64,
    /// Mean error over the whole run [m].
    pub error_mean: f64,
    pub skipped_per_run: f64,
    /// RTPF's gradient overhead: gradient evaluations / sample-set evaluations.
    pub gradient_overhead: f64,
    /// Feature windows per run ([`Diagnostics::feature_windows`]).
    pub feature_windows_per_run: f64,
    /// The fraction of feature windows whose feature record was integrated.
    pub feature_integrated: f64,
    /// Mean mixture weight on the feature records' sets in feature windows (mixture
    /// policies; NaN for the others).
    pub feature_alpha: f64,
    /// Mean mass at the true place before and after an update that integrated a feature.
    pub feature_mass_before: f64,
    pub feature_mass_after: f64,
    /// Runs whose belief lost the true place (mass below [`LOST_MASS`]) before localizing.
    pub lost: usize,
}

/// Summaries per (policy, window), the baseline first.
pub fn summarize(results: &[RunResult], end_time: f64) -> Vec<Summary> {
    let mut keys: Vec<(String, usize)> = Vec::new();
    for r in results {
        let k = (r.policy.clone(), r.window);
        if !keys.contains(&k) {
            keys.push(k);
        }
    }
    keys.iter()
        .map(|(p, k)| {
            let rs: Vec<&RunResult> = results
                .iter()
                .filter(|r| &r.policy == p && r.window == *k)
                .collect();
            let times: Vec<f64> = rs.iter().map(|r| r.time.unwrap_or(end_time)).collect();
            let (tm, tc) = mean_ci(&times);
            let errs: Vec<f64> = rs
                .iter()
                .map(|r| r.error.iter().sum::<f64>() / r.error.len().max(1) as f64)
                .collect();
            let sum = |f: &dyn Fn(&Diagnostics) -> f64| -> f64 {
                rs.iter().map(|r| f(&r.diagnostics)).sum()
            };
            let fw: u64 = rs.iter().map(|r| r.diagnostics.feature_windows).sum();
            let fi: u64 = rs.iter().map(|r| r.diagnostics.feature_integrated).sum();
            let evals: u64 = rs.iter().map(|r| r.likelihood_evals).sum();
            let grad: u64 = rs.iter().map(|r| r.gradient_evals).sum();
            Summary {
                policy: p.clone(),
                window: *k,
                runs: rs.len(),
                localized: rs.iter().filter(|r| r.time.is_some()).count(),
                time_mean: tm,
                time_ci95: tc,
                error_mean: mean_ci(&errs).0,
                skipped_per_run: rs.iter().map(|r| r.skipped as f64).sum::<f64>()
                    / rs.len().max(1) as f64,
                gradient_overhead: if evals > 0 {
                    grad as f64 / evals as f64
                } else {
                    0.0
                },
                feature_windows_per_run: fw as f64 / rs.len().max(1) as f64,
                feature_integrated: fi as f64 / fw as f64,
                feature_alpha: if ["uniform", "rtpf", "oracle"].contains(&p.as_str()) {
                    sum(&|d| d.feature_alpha) / fw as f64
                } else {
                    f64::NAN
                },
                feature_mass_before: sum(&|d| d.feature_mass_before) / fi as f64,
                feature_mass_after: sum(&|d| d.feature_mass_after) / fi as f64,
                lost: rs
                    .iter()
                    .filter(|r| r.diagnostics.min_true_mass < LOST_MASS)
                    .count(),
            }
        })
        .collect()
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> LocalizeError {
    LocalizeError::Io {
        path: path.display().to_string(),
        message: e.to_string(),
    }
}

/// The mean error curve (and its 95% half-width) of one policy and window.
fn error_curve(results: &[RunResult], policy: &str, window: usize) -> Vec<(f64, f64)> {
    let rs: Vec<&RunResult> = results
        .iter()
        .filter(|r| r.policy == policy && r.window == window)
        .collect();
    let len = rs.iter().map(|r| r.error.len()).min().unwrap_or(0);
    (0..len)
        .map(|t| mean_ci(&rs.iter().map(|r| r.error[t]).collect::<Vec<_>>()))
        .collect()
}

/// Writes `errors.csv` (mean error per second with CI, per policy and window), `times.csv`
/// (the summaries), `diagnostics.csv` (the runs' [`Diagnostics`], summarised),
/// `speedup.csv` (RTPF over skip; `speedup-oracle.csv` too with the oracle) and `rtpf.png`
/// into `dir`; returns the summaries.
pub fn write_outputs(
    exp: &RtpfExperiment,
    results: &[RunResult],
    dir: &Path,
) -> Result<Vec<Summary>, LocalizeError> {
    std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
    let end = exp.records as f64;
    let sums = summarize(results, end);
    let mut keys: Vec<(String, usize)> =
        sums.iter().map(|s| (s.policy.clone(), s.window)).collect();
    keys.dedup();

    let mut errors = String::from("policy,window,t,error_mean,error_ci95\n");
    for (p, k) in &keys {
        for (t, (m, c)) in error_curve(results, p, *k).iter().enumerate() {
            writeln!(errors, "{p},{k},{},{m:.4},{c:.4}", t + 1).expect("writing to a String");
        }
    }
    let path = dir.join("errors.csv");
    std::fs::write(&path, errors).map_err(|e| io_err(&path, e))?;

    let mut times = String::from(
        "policy,window,runs,localized,time_mean_s,time_ci95_s,error_mean_m,skipped_per_run,gradient_overhead\n",
    );
    for s in &sums {
        writeln!(
            times,
            "{},{},{},{},{:.2},{:.2},{:.4},{:.1},{:.4}",
            s.policy,
            s.window,
            s.runs,
            s.localized,
            s.time_mean,
            s.time_ci95,
            s.error_mean,
            s.skipped_per_run,
            s.gradient_overhead
        )
        .expect("writing to a String");
    }
    let path = dir.join("times.csv");
    std::fs::write(&path, times).map_err(|e| io_err(&path, e))?;

    let mut diag = String::from(
        "policy,window,runs,lost,feature_windows_per_run,feature_integrated,feature_alpha,feature_mass_before,feature_mass_after\n",
    );
    for s in &sums {
        writeln!(
            diag,
            "{},{},{},{},{:.2},{:.4},{:.4},{:.4},{:.4}",
            s.policy,
            s.window,
            s.runs,
            s.lost,
            s.feature_windows_per_run,
            s.feature_integrated,
            s.feature_alpha,
            s.feature_mass_before,
            s.feature_mass_after
        )
        .expect("writing to a String");
    }
    let path = dir.join("diagnostics.csv");
    std::fs::write(&path, diag).map_err(|e| io_err(&path, e))?;

    let speed = speedups(results, end);
    let compared = if exp.oracle {
        vec!["rtpf", "oracle"]
    } else {
        vec!["rtpf"]
    };
    for policy in compared {
        let mut sp = format!(
            "window,skip_time_s,{policy}_time_s,speedup_{policy}_over_skip,speedup_ci95_low,speedup_ci95_high\n"
        );
        // RTPF's speedups are `speed`, already computed for the plot.
        let other;
        let rows = if policy == "rtpf" {
            &speed
        } else {
            other = speedups_of(results, policy, end);
            &other
        };
        for x in rows {
            writeln!(
                sp,
                "{},{:.2},{:.2},{:.3},{:.3},{:.3}",
                x.window, x.skip_time, x.rtpf_time, x.speedup, x.ci_low, x.ci_high
            )
            .expect("writing to a String");
        }
        let name = match policy {
            "rtpf" => "speedup.csv".to_string(),
            other => format!("speedup-{other}.csv"),
        };
        let path = dir.join(name);
        std::fs::write(&path, sp).map_err(|e| io_err(&path, e))?;
    }

    plot(exp, results, &speed, &dir.join("rtpf.png"))?;
    Ok(sums)
}

/// Bootstrap resamples of the speedup's confidence interval. Default 10000: the interval's
/// ends move by less than 0.01 between bootstrap seeds at 30 runs.
pub const BOOTSTRAP_RESAMPLES: usize = 10_000;
/// Seed of the bootstrap's random stream (fixed: the same runs give the same interval).
const BOOTSTRAP_SEED: u64 = 0xB007;

/// RTPF's speedup over skip at one window size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Speedup {
    pub window: usize,
    /// Mean localization times [s].
    pub skip_time: f64,
    /// Mean time of the policy compared with skip (RTPF, or the oracle in
    /// [`speedups_of`]).
    pub rtpf_time: f64,
    /// `skip_time / rtpf_time`.
    pub speedup: f64,
    /// 95% confidence interval of the speedup: percentile bootstrap over the seeds, the
    /// runs of both policies with the same seed (same data) kept as a pair, as the paper's
    /// paired tests over its 30 runs.
    pub ci_low: f64,
    pub ci_high: f64,
}

/// The ratio of mean localization times `a / b` over pairs, with the 2.5 and 97.5
/// percentiles of its bootstrap distribution (pairs resampled with replacement).
pub fn ratio_ci(pairs: &[(f64, f64)]) -> (f64, f64, f64) {
    let ratio = |idx: &mut dyn Iterator<Item = usize>| {
        let (mut a, mut b) = (0.0, 0.0);
        for i in idx {
            a += pairs[i].0;
            b += pairs[i].1;
        }
        a / b
    };
    let r = ratio(&mut (0..pairs.len()));
    if pairs.len() < 2 {
        return (r, r, r);
    }
    let mut rng = stream(BOOTSTRAP_SEED, pairs.len() as u64, 0);
    let n = pairs.len();
    let mut boot: Vec<f64> = (0..BOOTSTRAP_RESAMPLES)
        .map(|_| {
            let idx: Vec<usize> = (0..n).map(|_| rng.random_range(0..n)).collect();
            ratio(&mut idx.into_iter())
        })
        .collect();
    boot.sort_by(f64::total_cmp);
    let q = |p: f64| boot[((p * (boot.len() - 1) as f64).round() as usize).min(boot.len() - 1)];
    (r, q(0.025), q(0.975))
}

/// RTPF's speedup over skip for every window with both policies, runs paired by seed;
/// a run that never localized counts at `end_time`.
pub fn speedups(results: &[RunResult], end_time: f64) -> Vec<Speedup> {
    speedups_of(results, "rtpf", end_time)
}

/// The speedup over skip of `policy`'s runs (`rtpf`, `oracle`, ...), as [`speedups`].
pub fn speedups_of(results: &[RunResult], policy: &str, end_time: f64) -> Vec<Speedup> {
    let mut windows: Vec<usize> = results
        .iter()
        .filter(|r| r.policy == policy)
        .map(|r| r.window)
        .collect();
    windows.sort_unstable();
    windows.dedup();
    let time = |r: &RunResult| r.time.unwrap_or(end_time);
    windows
        .into_iter()
        .filter_map(|k| {
            let pairs: Vec<(f64, f64)> = results
                .iter()
                .filter(|r| r.policy == "skip" && r.window == k)
                .filter_map(|s| {
                    results
                        .iter()
                        .find(|r| r.policy == policy && r.window == k && r.seed == s.seed)
                        .map(|r| (time(s), time(r)))
                })
                .collect();
            if pairs.is_empty() {
                return None;
            }
            let (speedup, ci_low, ci_high) = ratio_ci(&pairs);
            let n = pairs.len() as f64;
            Some(Speedup {
                window: k,
                skip_time: pairs.iter().map(|p| p.0).sum::<f64>() / n,
                rtpf_time: pairs.iter().map(|p| p.1).sum::<f64>() / n,
                speedup,
                ci_low,
                ci_high,
            })
        })
        .collect()
}

/// A markdown table: per window size, each policy's mean localization time ± 95% CI
/// (localized runs / runs), and RTPF's speedup over skip with its 95% interval; the
/// baseline in the first row.
pub fn markdown_table(sums: &[Summary], speed: &[Speedup], end_time: f64) -> String {
    let mut policies: Vec<String> = Vec::new();
    for s in sums.iter().filter(|s| s.policy != "baseline") {
        if !policies.contains(&s.policy) {
            policies.push(s.policy.clone());
        }
    }
    let cell = |s: &Summary| {
        format!(
            "{:.1} ± {:.1} ({}/{})",
            s.time_mean, s.time_ci95, s.localized, s.runs
        )
    };
    let mut out = String::new();
    let _ = write!(out, "| window |");
    for p in &policies {
        let _ = write!(out, " {p} [s] |");
    }
    let _ = writeln!(out, " rtpf speedup over skip [95% CI] |");
    let _ = write!(out, "|---|");
    for _ in &policies {
        let _ = write!(out, "---|");
    }
    let _ = writeln!(out, "---|");
    if let Some(b) = sums.iter().find(|s| s.policy == "baseline") {
        let _ = writeln!(
            out,
            "| 1 (baseline: every record, full budget) | {} |{}",
            cell(b),
            " |".repeat(policies.len())
        );
    }
    let mut windows: Vec<usize> = sums
        .iter()
        .filter(|s| s.policy != "baseline")
        .map(|s| s.window)
        .collect();
    windows.sort_unstable();
    windows.dedup();
    for k in windows {
        let _ = write!(out, "| {k} |");
        for p in &policies {
            match sums.iter().find(|s| &s.policy == p && s.window == k) {
                Some(s) => {
                    let _ = write!(out, " {} |", cell(s));
                }
                None => {
                    let _ = write!(out, " |");
                }
            }
        }
        match speed.iter().find(|s| s.window == k) {
            Some(s) => {
                let _ = writeln!(
                    out,
                    " {:.2}x [{:.2}, {:.2}] |",
                    s.speedup, s.ci_low, s.ci_high
                );
            }
            None => {
                let _ = writeln!(out, " |");
            }
        }
    }
    let _ = writeln!(
        out,
        "\nTimes in seconds of data (one record per second); a run that never localized counts as {end_time:.0} s."
    );
    out
}

/// A markdown table of the runs' [`Diagnostics`] per policy and window: runs that lost the
/// true place before localizing, feature windows per run, the fraction of them whose
/// feature record was integrated, the mixture weight on the feature records' sets, and the
/// mass at the true place before and after an update that integrated a feature.
pub fn diagnostics_table(sums: &[Summary]) -> String {
    let mut out = String::from(
        "| policy | window | lost the true place | feature windows per run | feature integrated | weight on feature sets | true-place mass before -> after a feature |\n|---|---|---|---|---|---|---|\n",
    );
    for s in sums {
        let alpha = if s.feature_alpha.is_nan() {
            String::new()
        } else {
            format!("{:.2}", s.feature_alpha)
        };
        let _ = writeln!(
            out,
            "| {} | {} | {}/{} | {:.1} | {:.2} | {} | {:.2} -> {:.2} |",
            s.policy,
            s.window,
            s.lost,
            s.runs,
            s.feature_windows_per_run,
            s.feature_integrated,
            alpha,
            s.feature_mass_before,
            s.feature_mass_after
        );
    }
    out
}

/// DejaVu Sans, compiled in so that plotting needs no system fonts (its licence is in
/// `assets/DejaVuSans-LICENSE.txt`).
static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

fn plot(
    exp: &RtpfExperiment,
    results: &[RunResult],
    speed: &[Speedup],
    path: &Path,
) -> Result<(), LocalizeError> {
    use plotters::prelude::*;
    let e = |x: &dyn std::fmt::Display| io_err(path, x);
    plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
        .map_err(|_| e(&"the bundled font does not load"))?;
    let root = BitMapBackend::new(path, (1400, 1000)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let panels = root.split_evenly((2, 2));
    // Three error panels: small, middle and large window sizes of those run.
    let mut ws = exp.windows.clone();
    ws.sort_unstable();
    let picks = [ws[0], ws[ws.len() / 2], ws[ws.len() - 1]];
    let colors = [BLACK, RED, BLUE, GREEN, MAGENTA];
    let names: Vec<String> = std::iter::once("baseline".to_string())
        .chain(exp.policies.iter().map(|p| p.as_str().to_string()))
        .chain(exp.oracle.then(|| "oracle".to_string()))
        .collect();
    let ymax = results
        .iter()
        .flat_map(|r| r.error.iter())
        .fold(0.0f64, |a, b| a.max(*b))
        .clamp(1.0, 20.0);
    for (panel, &k) in panels.iter().take(3).zip(&picks) {
        let mut chart = ChartBuilder::on(panel)
            .caption(
                format!("Localization error, window size {k}"),
                ("sans-serif", 22),
            )
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(0f64..exp.records as f64, 0f64..ymax)
            .map_err(|x| e(&x))?;
        chart
            .configure_mesh()
            .x_desc("time [s]")
            .y_desc("error [m]")
            .draw()
            .map_err(|x| e(&x))?;
        for (ci, name) in names.iter().enumerate() {
            let win = if name == "baseline" { 1 } else { k };
            let curve = error_curve(results, name, win);
            if curve.is_empty() {
                continue;
            }
            let col = colors[ci % colors.len()];
            chart
                .draw_series(LineSeries::new(
                    curve
                        .iter()
                        .enumerate()
                        .map(|(t, (m, _))| ((t + 1) as f64, *m)),
                    col.stroke_width(2),
                ))
                .map_err(|x| e(&x))?
                .label(name.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], col));
            // 95% band as thin lines every 10 s.
            chart
                .draw_series(curve.iter().enumerate().step_by(10).map(|(t, (m, c))| {
                    PathElement::new(
                        vec![((t + 1) as f64, (m - c).max(0.0)), ((t + 1) as f64, m + c)],
                        col.mix(0.6),
                    )
                }))
                .map_err(|x| e(&x))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|x| e(&x))?;
    }
    let smax = speed
        .iter()
        .map(|s| s.ci_high)
        .filter(|x| x.is_finite())
        .fold(1.0f64, f64::max)
        * 1.1;
    let kmax = ws[ws.len() - 1] as f64 + 1.0;
    let mut chart = ChartBuilder::on(&panels[3])
        .caption("Speedup of RTPF over skip", ("sans-serif", 22))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(0f64..kmax, 0f64..smax)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("window size")
        .y_desc("skip time / rtpf time")
        .draw()
        .map_err(|x| e(&x))?;
    chart
        .draw_series(LineSeries::new(
            speed.iter().map(|s| (s.window as f64, s.speedup)),
            BLUE.stroke_width(2),
        ))
        .map_err(|x| e(&x))?;
    chart
        .draw_series(
            speed
                .iter()
                .map(|s| Circle::new((s.window as f64, s.speedup), 4, BLUE.filled())),
        )
        .map_err(|x| e(&x))?;
    // The 95% bootstrap interval of each speedup.
    chart
        .draw_series(speed.iter().map(|s| {
            PathElement::new(
                vec![(s.window as f64, s.ci_low), (s.window as f64, s.ci_high)],
                BLUE.stroke_width(2),
            )
        }))
        .map_err(|x| e(&x))?;
    chart
        .draw_series(LineSeries::new([(0.0, 1.0), (kmax, 1.0)], BLACK.mix(0.5)))
        .map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_true_place_is_near_the_true_pose_and_faces_its_way() {
        let truth = Pose2::new(3.0, 1.0, 0.2);
        let poses = [
            Pose2::new(3.5, 1.5, 0.3),                                   // at the place
            Pose2::new(3.0, 1.0, 0.2 + std::f64::consts::PI),            // facing the other way
            Pose2::new(3.0 + TRUE_PLACE_RADIUS + 0.1, 1.0, 0.2),         // too far
            Pose2::new(3.0, 1.0 - 1.9, 0.2 - TRUE_PLACE_HEADING + 0.01), // at the edges
        ];
        let m = true_place_mass(&poses, &[0.1, 0.2, 0.3, 0.4], &truth);
        assert!((m - 0.5).abs() < 1e-12, "{m}");
    }

    #[test]
    fn the_diagnostics_follow_the_windows_and_the_feature_records() {
        let k = 4;
        let exp = RtpfExperiment {
            samples: 400,
            records: 120,
            ..RtpfExperiment::building()
        };
        let sim = exp.world.simulate(2, exp.records, &exp.motion_noise);
        let windows: Vec<&[u32]> = sim.features.chunks(k).collect();
        let feature_windows = windows.iter().filter(|w| w.iter().any(|f| *f > 0)).count() as u64;
        assert!(feature_windows >= 2, "{:?}", sim.features);
        // Uniform: every feature window integrates its features, with weight 1/k per record.
        let uniform = exp.run_one(&sim, Some(Policy::Uniform), k, 2).unwrap();
        let d = uniform.diagnostics;
        assert_eq!(d.feature_windows, feature_windows);
        assert_eq!(d.feature_integrated, feature_windows);
        let alpha: f64 = windows
            .iter()
            .map(|w| w.iter().filter(|f| **f > 0).count() as f64 / k as f64)
            .sum();
        assert!((d.feature_alpha - alpha).abs() < 1e-12, "{d:?} {alpha}");
        // Skip: only the windows whose newest record with readings saw a feature.
        let skip = exp.run_one(&sim, Some(Policy::Skip), k, 2).unwrap();
        let integrated = sim
            .records
            .chunks(k)
            .zip(&windows)
            .filter(|(rs, fs)| {
                rs.iter()
                    .rposition(|r| !r.landmarks.is_empty())
                    .is_some_and(|j| fs[j] > 0)
            })
            .count() as u64;
        assert!(integrated < feature_windows, "{integrated}");
        assert_eq!(skip.diagnostics.feature_windows, feature_windows);
        assert_eq!(skip.diagnostics.feature_integrated, integrated);
        assert_eq!(skip.diagnostics.feature_alpha, 0.0);
        // RTPF: the weights on feature sets are between none and all.
        let rtpf = exp.run_one(&sim, Some(Policy::Rtpf), k, 2).unwrap();
        let d = rtpf.diagnostics;
        assert!(d.feature_alpha > 0.0 && d.feature_alpha <= d.feature_windows as f64 + 1e-9);
        // The oracle puts all the weight on the feature records of every feature window.
        let oracle = exp.run_oracle(&sim, k, 2).unwrap();
        assert_eq!(oracle.policy, "oracle");
        let d = oracle.diagnostics;
        assert_eq!(d.feature_windows, feature_windows);
        assert!(
            (d.feature_alpha - feature_windows as f64).abs() < 1e-9,
            "{d:?}"
        );
        // Masses are fractions; the smallest is at most any update's.
        for r in [&uniform, &skip, &rtpf, &oracle] {
            // The records before the first update carry its error.
            assert!(r.error.iter().all(|e| e.is_finite()), "{:?}", &r.error[..k]);
            assert_eq!(r.error[0], r.error[k - 1]);
            let d = r.diagnostics;
            assert!((0.0..=1.0).contains(&d.min_true_mass), "{d:?}");
            assert!(d.feature_mass_after <= d.feature_integrated as f64 + 1e-9);
        }
    }

    #[test]
    fn loop_world_is_symmetric_and_the_robot_stays_on_it() {
        let w = LoopWorld::default();
        let map = w.map();
        // Symmetric pairs, plus the distinguishing posts.
        assert_eq!((map.len() - 3) % 2, 0);
        assert!(map.len() > 30, "{} posts", map.len());
        for pair in map.landmarks[..map.len() - 3].chunks(2) {
            let (a, b) = (pair[0].gaussian.mean, pair[1].gaussian.mean);
            assert!((a[0] + b[0] - 24.0).abs() < 1e-9 && (a[1] + b[1] - 12.0).abs() < 1e-9);
        }
        let run = w.simulate(3, 200, &RtpfExperiment::default().motion_noise);
        assert_eq!(run.records.len(), 200);
        let seen = run
            .records
            .iter()
            .filter(|r| !r.landmarks.is_empty())
            .count();
        assert!(seen > 150, "{seen} records see posts");
        // The robot follows the loop.
        let far = run
            .truth
            .iter()
            .filter(|p| p.x < -1e-6 || p.x > 24.0 + 1e-6 || p.y < -1e-6 || p.y > 12.0 + 1e-6)
            .count();
        assert_eq!(far, 0);
    }

    #[test]
    fn the_building_repeats_its_module_scans_densely_and_shows_features_briefly() {
        let w = LoopWorld::building();
        let map = w.map();
        let copies = (w.perimeter() / w.period) as usize;
        let posts = map.len() - w.features;
        assert_eq!(posts % copies, 0, "{posts} posts in {copies} modules");
        // Along the first side, post i of module c is post i of module 0 moved c modules on.
        let per = posts / copies;
        let side = (w.length / w.period) as usize;
        let mut checked = 0;
        for c in 1..side {
            for i in 0..per {
                let (a, b) = (
                    map.landmarks[i].gaussian.mean,
                    map.landmarks[c * per + i].gaussian.mean,
                );
                if a[0] + c as f64 * w.period < w.length {
                    assert!(
                        (b[0] - a[0] - c as f64 * w.period).abs() < 1e-9
                            && (b[1] - a[1]).abs() < 1e-9,
                        "module {c} post {i}: {a:?} {b:?}"
                    );
                    checked += 1;
                }
            }
        }
        // Module 0 lies on the first side, so its copies 1 and 2 do too: all are checked.
        assert_eq!(checked, (side - 1) * per);
        let run = w.simulate(5, 300, &RtpfExperiment::building().motion_noise);
        let readings: usize = run.records.iter().map(|r| r.landmarks.len()).sum();
        let mean = readings as f64 / run.records.len() as f64;
        println!("{mean:.1} readings per record");
        assert!(mean > 8.0, "{mean} readings per record");
        // A distinguishing post, seen: the records within 0.9 m of it, at most 4 in a row.
        let features = &map.landmarks[posts..];
        let mut longest = 0;
        let mut current = 0;
        let mut sightings = 0;
        for p in &run.truth {
            let near = features.iter().any(|f| {
                math::hypot(f.gaussian.mean[0] - p.x, f.gaussian.mean[1] - p.y) <= w.feature_range
            });
            current = if near { current + 1 } else { 0 };
            sightings += usize::from(near);
            longest = longest.max(current);
        }
        assert!(
            sightings > 0 && longest <= 4,
            "{sightings} records near a feature, {longest} in a row"
        );
    }

    #[test]
    fn the_speedup_interval_holds_the_ratio_and_narrows_with_agreement() {
        let noisy: Vec<(f64, f64)> = (0..30)
            .map(|i| (100.0 + (i % 7) as f64 * 20.0, 50.0 + (i % 5) as f64 * 15.0))
            .collect();
        let (r, lo, hi) = ratio_ci(&noisy);
        let exact = noisy.iter().map(|p| p.0).sum::<f64>() / noisy.iter().map(|p| p.1).sum::<f64>();
        assert!((r - exact).abs() < 1e-12);
        assert!(lo < r && r < hi, "{lo} {r} {hi}");
        // Every pair at the same ratio: no spread.
        let same: Vec<(f64, f64)> = (1..31).map(|i| (2.0 * i as f64, i as f64)).collect();
        let (r, lo, hi) = ratio_ci(&same);
        assert!((r - 2.0).abs() < 1e-12 && (hi - lo).abs() < 1e-12);
        // Same runs, same interval.
        assert_eq!(ratio_ci(&noisy), ratio_ci(&noisy));
    }

    #[test]
    fn localization_time_needs_the_hold() {
        let e = [5.0, 0.5, 0.5, 3.0, 0.5, 0.5, 0.5, 0.5];
        assert_eq!(localization_time(&e, 1.0, 2.0), Some(5.0));
        assert_eq!(localization_time(&e, 1.0, 5.0), None);
        let (m, c) = mean_ci(&[1.0, 3.0]);
        assert!((m - 2.0).abs() < 1e-12 && c > 0.0);
    }
}
