//! Evaluation of an estimate against ground truth: trajectory error (ATE), heading error,
//! landmark error and consistency (NEES).
//!
//! Both sides are [`Truth`]s: one trajectory per robot and a landmark list, as written by
//! [`Truth::write_dir`] (`trajectory_<robot>.tum`, `landmarks.csv`).
//!
//! # Time association
//!
//! Each estimate pose at time `t` is compared with the truth interpolated at `t`. With
//! truth samples `(t_i, p_i, theta_i)` and `t_i <= t <= t_{i+1}`, `a = (t - t_i) / (t_{i+1} - t_i)`:
//!
//! ```text
//! p(t)     = p_i + a (p_{i+1} - p_i)
//! theta(t) = wrap(theta_i + a wrap(theta_{i+1} - theta_i))        (shortest arc)
//! ```
//!
//! Poses outside the truth's time span (beyond a 1 µs tolerance) or inside a truth gap
//! `t_{i+1} - t_i > max_truth_gap` are skipped (unless they fall on a truth sample).
//!
//! # Alignment
//!
//! When the estimate is not in the truth's frame ([`Alignment::Se2`]; the automatic choice
//! when the run did not share one frame) the rigid transform `x -> R(phi) x + t` that
//! minimises `sum |R e_k + t - g_k|^2` over all robots' matched positions `(e_k, g_k)`
//! jointly is applied to the estimate first (Horn/Umeyama in 2D, no scale):
//!
//! ```text
//! e'_k = e_k - mean(e),  g'_k = g_k - mean(g)
//! phi  = atan2(sum e'_k x g'_k, sum e'_k . g'_k)      (x: the 2D cross product)
//! t    = mean(g) - R(phi) mean(e)
//! ```
//!
//! Headings turn by `phi`, landmark means by `R(phi)` (about the z axis) plus `t`, and
//! landmark covariances become `R Σ R^T`.
//!
//! # Errors
//!
//! ```text
//! ATE RMSE      = sqrt(mean_k |e'_k - g_k|^2)      (per robot, and pooled over the team)
//! heading RMSE  = sqrt(mean_k wrap(theta'_k - theta_k)^2)
//! landmark RMSE = sqrt(mean_j |m'_j - l_j|^2)      (over matched landmarks, 3D distance)
//! NEES          = mean_j d_j^T Σ_j^-1 d_j,  d_j = m'_j - l_j
//! ```
//!
//! Landmarks are matched one to one: first by id (estimate rows whose id the truth knows),
//! then every remaining estimate row to the nearest remaining truth landmark within
//! `landmark_match_radius`, greedily by increasing distance. Unmatched truth landmarks are
//! *missed*, unmatched estimate rows *spurious*. The NEES uses the xy block when the
//! estimate's z variances are all zero (2D maps; expected value 2) and the full 3x3
//! covariance otherwise (expected value 3); rows whose covariance is not positive definite
//! (e.g. unknown, all zero) are skipped.
//!
//! A map can be right in shape and off as a whole: a SLAM estimate's frame is tied to the
//! truth's only through the robots' start poses, and an error of the frame moves every
//! landmark alike. `landmark_rmse_map_fit` and `landmark_nees_map_fit` give the RMSE and
//! NEES after the matched landmarks' own least-squares SE(2) fit onto the truth (the fit
//! above over landmark positions instead of poses, at least 3 pairs; covariances turned
//! with it): the map's shape. A FastSLAM's landmark covariances are conditioned on its
//! particles' trajectories, which after resampling share one ancestor, so they leave the
//! frame's error out: its NEES is large where the map-fit NEES is not.
//!
//! Beside this capped matching, `landmark_rmse_optimal` matches every estimate landmark
//! with a truth landmark one to one (as many pairs as the smaller side has) minimising the
//! sum of squared distances (Hungarian / Kuhn-Munkres, no radius, ids ignored): a map with
//! the right number of landmarks in the wrong places cannot hide behind the radius.
//!
//! With `group_within = g`, truth landmarks closer than `g` to each other (transitively)
//! count as one group, placed at the mean of its members: without ids no sensor of a given
//! noise separates landmarks much closer than that noise, so the right map holds one
//! landmark per group. Missed and spurious counts are then over groups.
//!
//! # Relative pose error
//!
//! For each matched pose `i` of a robot, `j` is the first later pose at which the truth has
//! travelled at least `rpe_distance` metres; with `Δe = e_i⁻¹ e_j` and `Δg = g_i⁻¹ g_j`
//! (relative poses, independent of any alignment):
//!
//! ```text
//! RPE RMSE = sqrt(mean_i |Δe_i.xy − Δg_i.xy|²),  RPE heading RMSE = sqrt(mean_i wrap(Δe_i.θ − Δg_i.θ)²)
//! ```
//!
//! Estimates of runs without known data association must leave the landmark ids empty:
//! ids that merely number the filter's own landmarks would be matched to the truth's ids.

use crate::formats::{
    LandmarkRow, TrajectoryPoint, Truth, landmarks_file, read_landmarks_csv_path, read_tum_path,
    robots_in, trajectory_file,
};
use fleetslam_core::math;
use fleetslam_core::pose::{Pose2, wrap_angle};
use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::{Path, PathBuf};

/// Tolerance on timestamps (s): TUM files keep microseconds.
const TIME_EPS: f64 = 1e-6;

/// How the estimate is brought into the truth's frame before errors are computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Alignment {
    /// Compare as is: the estimate already is in the truth's frame.
    None,
    /// Fit the least-squares rotation and translation (no scale) first.
    Se2,
}

impl Alignment {
    pub fn as_str(self) -> &'static str {
        match self {
            Alignment::None => "none",
            Alignment::Se2 => "se2",
        }
    }
}

impl fmt::Display for Alignment {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Alignment {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "none" => Ok(Alignment::None),
            "se2" => Ok(Alignment::Se2),
            _ => Err(format!(
                "unknown alignment {s:?}: expected \"none\" or \"se2\""
            )),
        }
    }
}

/// Options of [`evaluate`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EvalOptions {
    /// `None` chooses automatically: no alignment when the estimate shares the truth's
    /// frame, SE(2) otherwise.
    pub alignment: Option<Alignment>,
    /// Largest distance for nearest-neighbour landmark matching (m). Default 1.0. A
    /// negative or NaN radius matches by id only.
    pub landmark_match_radius: f64,
    /// Largest truth gap interpolated across (s). Default 0.5. Infinity interpolates across
    /// any gap; a negative or NaN value only keeps poses that fall on truth samples.
    pub max_truth_gap: f64,
    /// Truth landmarks closer than this to each other (m, transitively) count as one group
    /// at the members' mean (module docs). Default `None`: every landmark on its own.
    pub group_within: Option<f64>,
    /// Distance the truth travels between the two poses of a relative pose error (m).
    /// Default 1.0.
    pub rpe_distance: f64,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            alignment: None,
            landmark_match_radius: 1.0,
            max_truth_gap: 0.5,
            group_within: None,
            rpe_distance: 1.0,
        }
    }
}

/// Errors of one robot's trajectory. Error fields are NaN (`null` in JSON) when no pose
/// could be matched.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotEval {
    /// Poses in the estimate's trajectory.
    pub estimate_poses: usize,
    /// Estimate poses compared with the truth (the others fell outside it or into a gap).
    pub matched_poses: usize,
    /// Root mean square position error (m).
    #[serde(with = "nan_as_null")]
    pub ate_rmse: f64,
    /// Mean position error (m).
    #[serde(with = "nan_as_null")]
    pub ate_mean: f64,
    /// Largest position error (m).
    #[serde(with = "nan_as_null")]
    pub ate_max: f64,
    /// Root mean square heading error (rad).
    #[serde(with = "nan_as_null")]
    pub heading_rmse: f64,
    /// Relative pose error over `rpe_distance` (module docs): RMSE of the position part (m).
    #[serde(with = "nan_as_null", default = "nan")]
    pub rpe_rmse: f64,
    /// RMSE of the heading part of the relative pose error (rad).
    #[serde(with = "nan_as_null", default = "nan")]
    pub rpe_heading_rmse: f64,
    /// Relative poses the RPE averages over.
    #[serde(default)]
    pub rpe_count: usize,
}

fn nan() -> f64 {
    f64::NAN
}

/// Errors of the whole team and of the map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TeamEval {
    /// Matched poses of all robots.
    pub matched_poses: usize,
    /// Root mean square position error over all robots' matched poses (m).
    #[serde(with = "nan_as_null")]
    pub ate_rmse: f64,
    #[serde(with = "nan_as_null")]
    pub ate_mean: f64,
    #[serde(with = "nan_as_null")]
    pub ate_max: f64,
    /// Root mean square heading error over all robots' matched poses (rad).
    #[serde(with = "nan_as_null")]
    pub heading_rmse: f64,
    /// Root mean square landmark position error (m); `None` without landmark truth or
    /// without matched landmarks.
    pub landmark_rmse: Option<f64>,
    /// Landmarks of the truth that an estimate landmark matched.
    pub landmarks_matched: usize,
    /// Landmarks of the truth that no estimate landmark matched.
    pub landmarks_missed: usize,
    /// Estimate landmarks that matched no landmark of the truth.
    pub landmarks_spurious: usize,
    /// Mean landmark NEES; `None` when no matched landmark has a positive definite
    /// covariance.
    pub landmark_nees: Option<f64>,
    /// Landmarks the NEES averages over.
    pub landmark_nees_count: usize,
    /// Landmark RMSE (m) after the matched landmarks' own least-squares SE(2) fit onto the
    /// truth (module docs): the error of the map's shape, without the error of its frame
    /// that every landmark shares. `None` below 3 matched landmarks.
    #[serde(default)]
    pub landmark_rmse_map_fit: Option<f64>,
    /// Mean landmark NEES after that fit (covariances turned with the map); `None` below 3
    /// matched landmarks or without a positive definite covariance.
    #[serde(default)]
    pub landmark_nees_map_fit: Option<f64>,
    /// Largest distance of a landmark pair matched within the radius (m).
    #[serde(default)]
    pub landmark_match_max: Option<f64>,
    /// Landmark RMSE of the optimal one-to-one matching without radius (m; module docs).
    #[serde(default)]
    pub landmark_rmse_optimal: Option<f64>,
    /// Pairs of that matching: the smaller of the estimate's and the truth's counts.
    #[serde(default)]
    pub landmarks_optimal_pairs: usize,
    /// Relative pose error over all robots (m, rad) and its count.
    #[serde(with = "nan_as_null", default = "nan")]
    pub rpe_rmse: f64,
    #[serde(with = "nan_as_null", default = "nan")]
    pub rpe_heading_rmse: f64,
    #[serde(default)]
    pub rpe_count: usize,
}

/// The result of [`evaluate`]; serialises with the keys `robots.<id>.ate_rmse`,
/// `team.ate_rmse`, `team.landmark_rmse`, ...
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    /// Per robot of the estimate or the truth.
    pub robots: BTreeMap<String, RobotEval>,
    pub team: TeamEval,
    /// The alignment used: `"none"` or `"se2"`.
    pub alignment: String,
    /// The transform applied to the estimate, `[tx, ty, phi]` (`x -> R(phi) x + t`); `None`
    /// when nothing was applied.
    pub transform: Option<[f64; 3]>,
    /// The `group_within` distance used (m) and the number of truth landmark groups it
    /// formed; absent when landmarks were not grouped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub group_within: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub landmark_groups: Option<usize>,
    /// The distance of the relative pose error (m).
    #[serde(default)]
    pub rpe_distance: f64,
}

/// Serialises NaN as `null` and reads `null` back as NaN.
mod nan_as_null {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else {
            s.serialize_none()
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
    }
}

/// Errors of [`evaluate_dir`]; each names the file or directory at fault.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: no trajectory_<robot>.tum nor landmarks.csv in this directory", path.display())]
    Empty { path: PathBuf },
    #[error("{}: {message}", path.display())]
    Metrics { path: PathBuf, message: String },
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> EvalError + '_ {
    move |source| EvalError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Reads a directory written by [`Truth::write_dir`] (the same files as
/// [`Truth::read_dir`]), naming the failing file in errors.
fn read_truth_dir(dir: &Path) -> Result<Truth, EvalError> {
    let mut truth = Truth::default();
    for robot in robots_in(dir).map_err(io_error(dir))? {
        let path = trajectory_file(dir, &robot);
        let pts = read_tum_path(&path).map_err(io_error(&path))?;
        truth.trajectories.insert(robot, pts);
    }
    let lm = landmarks_file(dir);
    if lm.exists() {
        truth.landmarks = read_landmarks_csv_path(&lm).map_err(io_error(&lm))?;
    }
    if truth.trajectories.is_empty() && !lm.exists() {
        return Err(EvalError::Empty {
            path: dir.to_path_buf(),
        });
    }
    Ok(truth)
}

/// Whether `<dir>/metrics.json` says the estimate is in the truth's frame (`false` when the
/// file or the key is absent).
fn shared_frame(dir: &Path) -> Result<bool, EvalError> {
    let path = dir.join("metrics.json");
    if !path.exists() {
        return Ok(false);
    }
    let text = std::fs::read_to_string(&path).map_err(io_error(&path))?;
    let metrics: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| EvalError::Metrics {
            path: path.clone(),
            message: format!("not valid JSON: {e}"),
        })?;
    match metrics.get("shared_frame") {
        None | Some(serde_json::Value::Null) => Ok(false),
        Some(serde_json::Value::Bool(b)) => Ok(*b),
        Some(v) => Err(EvalError::Metrics {
            path,
            message: format!("\"shared_frame\" must be true or false, got {v}"),
        }),
    }
}

/// Evaluates the estimate directory `est_dir` against the truth directory `truth_dir`.
/// Whether the estimate shares the truth's frame is read from `est_dir/metrics.json`
/// (`"shared_frame": true`), defaulting to `false`. Writes nothing.
pub fn evaluate_dir(
    est_dir: &Path,
    truth_dir: &Path,
    opts: &EvalOptions,
) -> Result<Evaluation, EvalError> {
    let estimate = read_truth_dir(est_dir)?;
    let truth = read_truth_dir(truth_dir)?;
    let shared = shared_frame(est_dir)?;
    Ok(evaluate(&estimate, &truth, shared, opts))
}

/// The truth's finite samples, sorted by time.
fn clean_truth(points: &[TrajectoryPoint]) -> Vec<TrajectoryPoint> {
    let mut pts: Vec<TrajectoryPoint> = points
        .iter()
        .filter(|p| p.t.is_finite() && p.pose.is_finite())
        .copied()
        .collect();
    pts.sort_by(|a, b| a.t.total_cmp(&b.t));
    pts
}

/// The truth at time `t` (see the module docs), or `None` outside its span or in a gap
/// longer than `max_gap` (a NaN `max_gap` only keeps times on samples). `truth` must be
/// sorted by time.
pub fn interpolate(truth: &[TrajectoryPoint], t: f64, max_gap: f64) -> Option<Pose2> {
    let (first, last) = (truth.first()?, truth.last()?);
    if !t.is_finite() || t < first.t - TIME_EPS || t > last.t + TIME_EPS {
        return None;
    }
    // First sample strictly after t; the one before it is at or before t.
    let hi = truth.partition_point(|p| p.t <= t);
    if hi == 0 {
        return Some(first.pose);
    }
    let a = &truth[hi - 1];
    let Some(b) = truth.get(hi) else {
        return Some(last.pose);
    };
    if t - a.t <= TIME_EPS {
        return Some(a.pose);
    }
    if b.t - t <= TIME_EPS {
        return Some(b.pose);
    }
    let gap = b.t - a.t;
    if max_gap.is_nan() || gap > max_gap {
        return None;
    }
    let f = (t - a.t) / gap;
    Some(Pose2::new(
        a.pose.x + f * (b.pose.x - a.pose.x),
        a.pose.y + f * (b.pose.y - a.pose.y),
        wrap_angle(a.pose.theta + f * wrap_angle(b.pose.theta - a.pose.theta)),
    ))
}

/// Time-associated `(estimate pose, truth pose)` pairs.
type PosePairs = Vec<(Pose2, Pose2)>;

/// A rigid transform of the plane, `x -> R(phi) x + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Se2 {
    tx: f64,
    ty: f64,
    phi: f64,
}

impl Se2 {
    const IDENTITY: Se2 = Se2 {
        tx: 0.0,
        ty: 0.0,
        phi: 0.0,
    };

    fn apply_xy(&self, x: f64, y: f64) -> (f64, f64) {
        let (s, c) = math::sin_cos(self.phi);
        (c * x - s * y + self.tx, s * x + c * y + self.ty)
    }

    fn apply_pose(&self, p: &Pose2) -> Pose2 {
        let (x, y) = self.apply_xy(p.x, p.y);
        Pose2::new(x, y, wrap_angle(p.theta + self.phi))
    }

    fn apply_landmark(&self, row: &LandmarkRow) -> LandmarkRow {
        let (x, y) = self.apply_xy(row.mean[0], row.mean[1]);
        let (s, c) = math::sin_cos(self.phi);
        let r = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
        let cov = r * full_cov(&row.cov) * r.transpose();
        LandmarkRow {
            id: row.id,
            mean: [x, y, row.mean[2]],
            cov: [
                cov[(0, 0)],
                cov[(0, 1)],
                cov[(0, 2)],
                cov[(1, 1)],
                cov[(1, 2)],
                cov[(2, 2)],
            ],
        }
    }
}

/// The least-squares SE(2) transform taking `pairs[k].0` onto `pairs[k].1` (module docs).
/// `None` without pairs; a single pair (or coincident points) gives a pure translation.
fn fit_se2(pairs: &[(Pose2, Pose2)]) -> Option<Se2> {
    if pairs.is_empty() {
        return None;
    }
    let n = pairs.len() as f64;
    let (mut ex, mut ey, mut gx, mut gy) = (0.0, 0.0, 0.0, 0.0);
    for (e, g) in pairs {
        ex += e.x;
        ey += e.y;
        gx += g.x;
        gy += g.y;
    }
    let (ex, ey, gx, gy) = (ex / n, ey / n, gx / n, gy / n);
    let (mut dot, mut cross) = (0.0, 0.0);
    for (e, g) in pairs {
        let (ax, ay) = (e.x - ex, e.y - ey);
        let (bx, by) = (g.x - gx, g.y - gy);
        dot += ax * bx + ay * by;
        cross += ax * by - ay * bx;
    }
    let phi = if dot == 0.0 && cross == 0.0 {
        0.0
    } else {
        math::atan2(cross, dot)
    };
    let (s, c) = math::sin_cos(phi);
    let fit = Se2 {
        tx: gx - (c * ex - s * ey),
        ty: gy - (s * ex + c * ey),
        phi,
    };
    (fit.tx.is_finite() && fit.ty.is_finite() && fit.phi.is_finite()).then_some(fit)
}

/// Position and heading error statistics of a set of pose pairs.
#[derive(Debug, Clone, Copy)]
struct Stats {
    n: usize,
    rmse: f64,
    mean: f64,
    max: f64,
    heading_rmse: f64,
}

fn stats(pairs: impl Iterator<Item = (Pose2, Pose2)>) -> Stats {
    let (mut n, mut sq, mut sum, mut max, mut hsq) = (0usize, 0.0, 0.0, 0.0f64, 0.0);
    for (e, g) in pairs {
        let d = e.distance(&g);
        let h = wrap_angle(e.theta - g.theta);
        n += 1;
        sq += d * d;
        sum += d;
        max = max.max(d);
        hsq += h * h;
    }
    if n == 0 {
        return Stats {
            n,
            rmse: f64::NAN,
            mean: f64::NAN,
            max: f64::NAN,
            heading_rmse: f64::NAN,
        };
    }
    let k = n as f64;
    Stats {
        n,
        rmse: (sq / k).sqrt(),
        mean: sum / k,
        max,
        heading_rmse: (hsq / k).sqrt(),
    }
}

fn full_cov(c: &[f64; 6]) -> Matrix3<f64> {
    Matrix3::new(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5])
}

/// `d^T Σ^-1 d` for an estimate row, on the xy block when its z variances are zero; `None`
/// when the covariance is not positive definite.
fn nees(est: &LandmarkRow, truth: &LandmarkRow) -> Option<f64> {
    let c = &est.cov;
    let d = Vector3::from_fn(|i, _| est.mean[i] - truth.mean[i]);
    let value = if c[2] == 0.0 && c[4] == 0.0 && c[5] == 0.0 {
        let chol = Matrix2::new(c[0], c[1], c[1], c[3]).cholesky()?;
        let d2 = Vector2::new(d[0], d[1]);
        d2.dot(&chol.solve(&d2))
    } else {
        let chol = full_cov(c).cholesky()?;
        d.dot(&chol.solve(&d))
    };
    value.is_finite().then_some(value)
}

/// Landmark RMSE and mean NEES of the matched `pairs` after the estimate landmarks'
/// least-squares SE(2) fit onto their truth landmarks (module docs); `None`s below
/// [`MAP_FIT_MIN_PAIRS`] pairs.
fn map_fit_errors(
    est: &[LandmarkRow],
    truth: &[LandmarkRow],
    pairs: &[(usize, usize)],
) -> (Option<f64>, Option<f64>) {
    if pairs.len() < MAP_FIT_MIN_PAIRS {
        return (None, None);
    }
    let points: Vec<(Pose2, Pose2)> = pairs
        .iter()
        .map(|&(i, j)| {
            let (e, g) = (&est[i].mean, &truth[j].mean);
            (Pose2::new(e[0], e[1], 0.0), Pose2::new(g[0], g[1], 0.0))
        })
        .collect();
    let Some(fit) = fit_se2(&points) else {
        return (None, None);
    };
    let moved: Vec<LandmarkRow> = pairs
        .iter()
        .map(|&(i, _)| fit.apply_landmark(&est[i]))
        .collect();
    let sq: f64 = moved
        .iter()
        .zip(pairs)
        .map(|(m, &(_, j))| landmark_distance(m, &truth[j]).powi(2))
        .sum();
    let rmse = (sq / pairs.len() as f64).sqrt();
    let nees_values: Vec<f64> = moved
        .iter()
        .zip(pairs)
        .filter_map(|(m, &(_, j))| nees(m, &truth[j]))
        .collect();
    let mean_nees = (!nees_values.is_empty())
        .then(|| nees_values.iter().sum::<f64>() / nees_values.len() as f64);
    (Some(rmse), mean_nees)
}

/// Matched landmarks a map fit needs (fewer determine the fit's three parameters too
/// closely for the residual to mean anything).
pub const MAP_FIT_MIN_PAIRS: usize = 3;

fn landmark_distance(a: &LandmarkRow, b: &LandmarkRow) -> f64 {
    let d: f64 = (0..3).map(|i| (a.mean[i] - b.mean[i]).powi(2)).sum();
    d.sqrt()
}

/// One-to-one landmark matching (module docs): `(estimate index, truth index)` pairs.
fn match_landmarks(est: &[LandmarkRow], truth: &[LandmarkRow], radius: f64) -> Vec<(usize, usize)> {
    let mut truth_by_id: HashMap<u32, usize> = HashMap::new();
    for (j, row) in truth.iter().enumerate() {
        if let Some(id) = row.id {
            truth_by_id.entry(id).or_insert(j);
        }
    }
    let mut est_used = vec![false; est.len()];
    let mut truth_used = vec![false; truth.len()];
    let mut pairs = Vec::new();
    for (i, row) in est.iter().enumerate() {
        if let Some(&j) = row.id.and_then(|id| truth_by_id.get(&id))
            && !truth_used[j]
        {
            est_used[i] = true;
            truth_used[j] = true;
            pairs.push((i, j));
        }
    }
    if radius >= 0.0 {
        let mut candidates = Vec::new();
        for (i, e) in est.iter().enumerate().filter(|(i, _)| !est_used[*i]) {
            for (j, g) in truth.iter().enumerate().filter(|(j, _)| !truth_used[*j]) {
                let d = landmark_distance(e, g);
                if d <= radius {
                    candidates.push((d, i, j));
                }
            }
        }
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then((a.1, a.2).cmp(&(b.1, b.2))));
        for (_, i, j) in candidates {
            if !est_used[i] && !truth_used[j] {
                est_used[i] = true;
                truth_used[j] = true;
                pairs.push((i, j));
            }
        }
    }
    pairs
}

/// Truth landmarks grouped by single linkage within `within` metres, each group replaced
/// by its members' mean (keeping the id of a lone member only).
fn group_landmarks(truth: &[LandmarkRow], within: f64) -> Vec<LandmarkRow> {
    let n = truth.len();
    let mut parent: Vec<usize> = (0..n).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for i in 0..n {
        for j in i + 1..n {
            if landmark_distance(&truth[i], &truth[j]) < within {
                let (a, b) = (root(&mut parent, i), root(&mut parent, j));
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for i in 0..n {
        let r = root(&mut parent, i);
        groups.entry(r).or_default().push(i);
    }
    groups
        .values()
        .map(|members| {
            let k = members.len() as f64;
            let mut mean = [0.0; 3];
            let mut cov = [0.0; 6];
            for &m in members {
                for (a, b) in mean.iter_mut().zip(&truth[m].mean) {
                    *a += b / k;
                }
                for (a, b) in cov.iter_mut().zip(&truth[m].cov) {
                    *a += b / k;
                }
            }
            LandmarkRow {
                id: if members.len() == 1 {
                    truth[members[0]].id
                } else {
                    None
                },
                mean,
                cov,
            }
        })
        .collect()
}

/// The one-to-one matching of `est` and `truth` landmarks (ids ignored, no radius) that
/// minimises the sum of squared distances (Kuhn-Munkres), as (estimate, truth) pairs.
fn optimal_landmark_pairs(est: &[LandmarkRow], truth: &[LandmarkRow]) -> Vec<(usize, usize)> {
    use pathfinding::kuhn_munkres::kuhn_munkres_min;
    use pathfinding::matrix::Matrix;
    if est.is_empty() || truth.is_empty() {
        return Vec::new();
    }
    // Squared distances in units of 1e-8 m² (0.1 mm resolution), as integers.
    let cost = |a: &LandmarkRow, b: &LandmarkRow| -> i64 {
        (landmark_distance(a, b).powi(2) * 1e8).round().min(1e17) as i64
    };
    let (rows, cols, swap) = if est.len() <= truth.len() {
        (est, truth, false)
    } else {
        (truth, est, true)
    };
    let m = Matrix::from_fn(rows.len(), cols.len(), |(i, j)| cost(&rows[i], &cols[j]));
    let (_, assign) = kuhn_munkres_min(&m);
    assign
        .into_iter()
        .enumerate()
        .map(|(i, j)| if swap { (j, i) } else { (i, j) })
        .collect()
}

/// Relative pose errors of one robot's (estimate, truth) pairs in time order: the position
/// and heading parts, one per pose that has a later pose `distance` metres further along
/// the truth.
fn relative_errors(pairs: &[(Pose2, Pose2)], distance: f64) -> Vec<(f64, f64)> {
    let n = pairs.len();
    let mut along = Vec::with_capacity(n);
    let mut total = 0.0;
    for k in 0..n {
        if k > 0 {
            total += pairs[k].1.distance(&pairs[k - 1].1);
        }
        along.push(total);
    }
    let mut out = Vec::new();
    let mut j = 0;
    for i in 0..n {
        j = j.max(i + 1);
        while j < n && along[j] - along[i] < distance {
            j += 1;
        }
        if j >= n {
            break;
        }
        let de = pairs[j].0.relative_to(&pairs[i].0);
        let dg = pairs[j].1.relative_to(&pairs[i].1);
        out.push((
            math::hypot(de.x - dg.x, de.y - dg.y),
            wrap_angle(de.theta - dg.theta),
        ));
    }
    out
}

fn rms(v: impl Iterator<Item = f64>) -> (f64, usize) {
    let (mut n, mut sq) = (0usize, 0.0);
    for x in v {
        n += 1;
        sq += x * x;
    }
    if n == 0 {
        (f64::NAN, 0)
    } else {
        ((sq / n as f64).sqrt(), n)
    }
}

/// Evaluates `estimate` against `truth` (see the module docs). `shared_frame` says whether
/// the estimate is in the truth's frame, which decides the automatic alignment.
pub fn evaluate(
    estimate: &Truth,
    truth: &Truth,
    shared_frame: bool,
    opts: &EvalOptions,
) -> Evaluation {
    let alignment = opts.alignment.unwrap_or(if shared_frame {
        Alignment::None
    } else {
        Alignment::Se2
    });
    // NaN or negative gaps keep only poses on truth samples.
    let max_gap = if opts.max_truth_gap >= 0.0 {
        opts.max_truth_gap
    } else {
        -1.0
    };
    let radius = if opts.landmark_match_radius >= 0.0 {
        opts.landmark_match_radius
    } else {
        -1.0
    };

    // Time association: (estimate pose, truth pose) per robot.
    let mut matched: BTreeMap<&str, (usize, PosePairs)> = BTreeMap::new();
    for robot in truth.trajectories.keys() {
        matched.insert(robot, (0, Vec::new()));
    }
    for (robot, est) in &estimate.trajectories {
        let reference = truth
            .trajectories
            .get(robot)
            .map(|t| clean_truth(t))
            .unwrap_or_default();
        let pairs = est
            .iter()
            .filter(|p| p.pose.is_finite())
            .filter_map(|p| interpolate(&reference, p.t, max_gap).map(|g| (p.pose, g)))
            .collect();
        matched.insert(robot, (est.len(), pairs));
    }

    let transform = match alignment {
        Alignment::None => None,
        Alignment::Se2 => {
            let all: PosePairs = matched
                .values()
                .flat_map(|(_, p)| p.iter().copied())
                .collect();
            fit_se2(&all)
        }
    };
    let tf = transform.unwrap_or(Se2::IDENTITY);
    for (_, pairs) in matched.values_mut() {
        for (e, _) in pairs.iter_mut() {
            *e = tf.apply_pose(e);
        }
    }

    let rpe: BTreeMap<&str, Vec<(f64, f64)>> = matched
        .iter()
        .map(|(robot, (_, pairs))| (*robot, relative_errors(pairs, opts.rpe_distance)))
        .collect();
    let robots = matched
        .iter()
        .map(|(robot, (n, pairs))| {
            let s = stats(pairs.iter().copied());
            let (rpe_rmse, rpe_count) = rms(rpe[robot].iter().map(|e| e.0));
            let (rpe_heading_rmse, _) = rms(rpe[robot].iter().map(|e| e.1));
            let eval = RobotEval {
                estimate_poses: *n,
                matched_poses: s.n,
                ate_rmse: s.rmse,
                ate_mean: s.mean,
                ate_max: s.max,
                heading_rmse: s.heading_rmse,
                rpe_rmse,
                rpe_heading_rmse,
                rpe_count,
            };
            (robot.to_string(), eval)
        })
        .collect();
    let (team_rpe, team_rpe_count) = rms(rpe.values().flatten().map(|e| e.0));
    let (team_rpe_heading, _) = rms(rpe.values().flatten().map(|e| e.1));
    let team_stats = stats(matched.values().flat_map(|(_, p)| p.iter().copied()));

    // Landmarks, in the truth's frame.
    let est_landmarks: Vec<LandmarkRow> = estimate
        .landmarks
        .iter()
        .filter(|r| r.mean.iter().all(|v| v.is_finite()))
        .map(|r| tf.apply_landmark(r))
        .collect();
    let group_within = opts.group_within.filter(|g| g.is_finite() && *g > 0.0);
    let truth_landmarks = match group_within {
        Some(g) => group_landmarks(&truth.landmarks, g),
        None => truth.landmarks.clone(),
    };
    let pairs = match_landmarks(&est_landmarks, &truth_landmarks, radius);
    let dist = |&(i, j): &(usize, usize)| landmark_distance(&est_landmarks[i], &truth_landmarks[j]);
    let landmark_rmse = (!truth_landmarks.is_empty() && !pairs.is_empty()).then(|| {
        let sq: f64 = pairs.iter().map(|p| dist(p).powi(2)).sum();
        (sq / pairs.len() as f64).sqrt()
    });
    let landmark_match_max = pairs.iter().map(dist).reduce(f64::max);
    let optimal = optimal_landmark_pairs(&est_landmarks, &truth_landmarks);
    let landmark_rmse_optimal = (!optimal.is_empty()).then(|| {
        let sq: f64 = optimal.iter().map(|p| dist(p).powi(2)).sum();
        (sq / optimal.len() as f64).sqrt()
    });
    let nees_values: Vec<f64> = pairs
        .iter()
        .filter_map(|&(i, j)| nees(&est_landmarks[i], &truth_landmarks[j]))
        .collect();
    let landmark_nees = (!nees_values.is_empty())
        .then(|| nees_values.iter().sum::<f64>() / nees_values.len() as f64);
    let (landmark_rmse_map_fit, landmark_nees_map_fit) =
        map_fit_errors(&est_landmarks, &truth_landmarks, &pairs);

    Evaluation {
        robots,
        team: TeamEval {
            matched_poses: team_stats.n,
            ate_rmse: team_stats.rmse,
            ate_mean: team_stats.mean,
            ate_max: team_stats.max,
            heading_rmse: team_stats.heading_rmse,
            landmark_rmse,
            landmarks_matched: pairs.len(),
            landmarks_missed: truth_landmarks.len() - pairs.len(),
            landmarks_spurious: est_landmarks.len() - pairs.len(),
            landmark_nees,
            landmark_nees_count: nees_values.len(),
            landmark_rmse_map_fit,
            landmark_nees_map_fit,
            landmark_match_max,
            landmark_rmse_optimal,
            landmarks_optimal_pairs: optimal.len(),
            rpe_rmse: team_rpe,
            rpe_heading_rmse: team_rpe_heading,
            rpe_count: team_rpe_count,
        },
        alignment: alignment.as_str().to_string(),
        transform: transform.map(|t| [t.tx, t.ty, t.phi]),
        group_within,
        landmark_groups: group_within.map(|_| truth_landmarks.len()),
        rpe_distance: opts.rpe_distance,
    }
}

/// A number with `digits` decimals, or "n/a" when undefined.
struct Num(f64, usize);

impl fmt::Display for Num {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.0.is_finite() {
            write!(f, "{:.*}", self.1, self.0)
        } else {
            f.write_str("n/a")
        }
    }
}

impl fmt::Display for Evaluation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.transform {
            Some([tx, ty, phi]) => writeln!(
                f,
                "alignment: {} (t = [{}, {}] m, rotation {} deg)",
                self.alignment,
                Num(tx, 3),
                Num(ty, 3),
                Num(phi.to_degrees(), 3)
            )?,
            None => writeln!(f, "alignment: {}", self.alignment)?,
        }
        let width = self
            .robots
            .keys()
            .map(|r| r.len())
            .max()
            .unwrap_or(0)
            .max(4);
        for (robot, r) in &self.robots {
            writeln!(
                f,
                "robot {robot:<width$}  ATE rmse {} m, mean {} m, max {} m, heading rmse {} deg \
                 ({}/{} poses); RPE {} m, {} deg",
                Num(r.ate_rmse, 3),
                Num(r.ate_mean, 3),
                Num(r.ate_max, 3),
                Num(r.heading_rmse.to_degrees(), 2),
                r.matched_poses,
                r.estimate_poses,
                Num(r.rpe_rmse, 3),
                Num(r.rpe_heading_rmse.to_degrees(), 2),
            )?;
        }
        let t = &self.team;
        writeln!(
            f,
            "team  {:<width$}  ATE rmse {} m, mean {} m, max {} m, heading rmse {} deg ({} poses)",
            "",
            Num(t.ate_rmse, 3),
            Num(t.ate_mean, 3),
            Num(t.ate_max, 3),
            Num(t.heading_rmse.to_degrees(), 2),
            t.matched_poses,
        )?;
        writeln!(
            f,
            "RPE over {} m: rmse {} m, heading rmse {} deg ({} relative poses)",
            Num(self.rpe_distance, 2),
            Num(t.rpe_rmse, 3),
            Num(t.rpe_heading_rmse.to_degrees(), 2),
            t.rpe_count,
        )?;
        if let (Some(g), Some(n)) = (self.group_within, self.landmark_groups) {
            writeln!(
                f,
                "landmark truth grouped within {} m: {n} groups",
                Num(g, 3)
            )?;
        }
        let total = t.landmarks_matched + t.landmarks_missed;
        match t.landmark_rmse {
            Some(rmse) => write!(
                f,
                "landmarks: rmse {} m, matched {}/{total}, missed {}, spurious {}",
                Num(rmse, 3),
                t.landmarks_matched,
                t.landmarks_missed,
                t.landmarks_spurious,
            )?,
            None if total == 0 => write!(
                f,
                "landmarks: no truth ({} estimated)",
                t.landmarks_spurious
            )?,
            None => write!(
                f,
                "landmarks: none matched of {total}, spurious {}",
                t.landmarks_spurious
            )?,
        }
        if let Some(m) = t.landmark_match_max {
            write!(f, ", worst {} m", Num(m, 3))?;
        }
        if let Some(nees) = t.landmark_nees {
            write!(f, ", NEES {} over {}", Num(nees, 2), t.landmark_nees_count)?;
        }
        if let Some(r) = t.landmark_rmse_map_fit {
            write!(f, "; after the map's own SE(2) fit rmse {} m", Num(r, 3))?;
            if let Some(nees) = t.landmark_nees_map_fit {
                write!(f, ", NEES {}", Num(nees, 2))?;
            }
        }
        if let Some(o) = t.landmark_rmse_optimal {
            write!(
                f,
                "\nlandmarks, optimal matching without radius: rmse {} m over {} pairs",
                Num(o, 3),
                t.landmarks_optimal_pairs
            )?;
        }
        writeln!(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn traj(points: &[(f64, f64, f64, f64)]) -> Vec<TrajectoryPoint> {
        points
            .iter()
            .map(|&(t, x, y, th)| TrajectoryPoint {
                t,
                pose: Pose2::new(x, y, th),
            })
            .collect()
    }

    fn one_robot(points: Vec<TrajectoryPoint>) -> Truth {
        Truth {
            trajectories: [("1".to_string(), points)].into_iter().collect(),
            landmarks: vec![],
        }
    }

    fn no_alignment() -> EvalOptions {
        EvalOptions {
            alignment: Some(Alignment::None),
            ..EvalOptions::default()
        }
    }

    fn row(id: Option<u32>, x: f64, y: f64) -> LandmarkRow {
        LandmarkRow {
            id,
            mean: [x, y, 0.0],
            cov: [0.0; 6],
        }
    }

    #[test]
    fn constant_offset_gives_its_size() {
        let truth = one_robot(traj(&[
            (0.0, 0.0, 0.0, 0.0),
            (1.0, 1.0, 0.0, 0.0),
            (2.0, 2.0, 1.0, 0.5),
        ]));
        let est = one_robot(traj(&[
            (0.0, 0.0, 0.1, 0.0),
            (1.0, 1.0, 0.1, 0.0),
            (2.0, 2.0, 1.1, 0.5),
        ]));
        let e = evaluate(&est, &truth, true, &EvalOptions::default());
        assert_eq!(e.alignment, "none");
        assert!(e.transform.is_none());
        let r = &e.robots["1"];
        assert_eq!((r.matched_poses, r.estimate_poses), (3, 3));
        assert!((r.ate_rmse - 0.1).abs() < 1e-12);
        assert!((r.ate_mean - 0.1).abs() < 1e-12 && (r.ate_max - 0.1).abs() < 1e-12);
        assert!(r.heading_rmse.abs() < 1e-12);
        assert!((e.team.ate_rmse - 0.1).abs() < 1e-12);
    }

    #[test]
    fn hand_worked_rmse_and_heading() {
        // Errors 0.3 and 0.4 m: RMSE sqrt((0.09 + 0.16) / 2), mean 0.35, max 0.4.
        // Heading errors 0.1 and -0.1 across the +-pi seam: RMSE 0.1.
        let pi = std::f64::consts::PI;
        let truth = one_robot(traj(&[
            (0.0, 0.0, 0.0, pi - 0.05),
            (1.0, 5.0, 5.0, -pi + 0.05),
        ]));
        let est = one_robot(traj(&[
            (0.0, 0.3, 0.0, -pi + 0.05),
            (1.0, 5.0, 5.4, pi - 0.05),
        ]));
        let e = evaluate(&est, &truth, true, &EvalOptions::default());
        let r = &e.robots["1"];
        assert!((r.ate_rmse - (0.125f64).sqrt()).abs() < 1e-12);
        assert!((r.ate_mean - 0.35).abs() < 1e-12 && (r.ate_max - 0.4).abs() < 1e-12);
        assert!((r.heading_rmse - 0.1).abs() < 1e-9);
    }

    #[test]
    fn truth_is_interpolated_between_samples() {
        let pi = std::f64::consts::PI;
        let truth = traj(&[(0.0, 0.0, 0.0, pi - 0.1), (1.0, 2.0, -4.0, -pi + 0.1)]);
        assert!(interpolate(&truth, 0.25, 0.5).is_none(), "gap 1 s > 0.5 s");
        let p = interpolate(&truth, 0.25, 2.0).unwrap();
        assert!((p.x - 0.5).abs() < 1e-12 && (p.y + 1.0).abs() < 1e-12);
        // Shortest arc through pi: a quarter of the 0.2 rad from pi - 0.1 to -pi + 0.1.
        assert!(wrap_angle(p.theta - (pi - 0.05)).abs() < 1e-12);
        // Samples, the span and beyond.
        assert_eq!(interpolate(&truth, 0.0, 0.0), Some(truth[0].pose));
        assert_eq!(interpolate(&truth, 1.0, 0.0), Some(truth[1].pose));
        assert_eq!(interpolate(&truth, 1.0000001, 0.0), Some(truth[1].pose));
        assert!(
            interpolate(&truth, -0.1, 9.0).is_none() && interpolate(&truth, 1.1, 9.0).is_none()
        );
        assert!(interpolate(&[], 0.0, 9.0).is_none());

        // An estimate between truth samples is compared with the interpolated truth.
        let truth = one_robot(traj(&[(0.0, 0.0, 0.0, 0.0), (0.4, 4.0, 0.0, 0.0)]));
        let est = one_robot(traj(&[(0.1, 1.0, 0.2, 0.0), (0.3, 3.0, -0.2, 0.0)]));
        let e = evaluate(&est, &truth, true, &EvalOptions::default());
        assert!((e.robots["1"].ate_rmse - 0.2).abs() < 1e-12);
    }

    #[test]
    fn gaps_and_outside_poses_are_skipped() {
        // Truth samples 0, 0.2, 2.0, 2.2: the 1.8 s gap is not interpolated.
        let truth = one_robot(traj(&[
            (0.0, 0.0, 0.0, 0.0),
            (0.2, 0.2, 0.0, 0.0),
            (2.0, 2.0, 0.0, 0.0),
            (2.2, 2.2, 0.0, 0.0),
        ]));
        let est = one_robot(traj(&[
            (-1.0, 0.0, 0.0, 0.0), // before the truth
            (0.1, 0.1, 0.1, 0.0),  // matched, error 0.1
            (1.0, 50.0, 0.0, 0.0), // in the gap
            (2.0, 2.0, 0.1, 0.0),  // on a sample, error 0.1
            (3.0, 0.0, 0.0, 0.0),  // after the truth
        ]));
        let e = evaluate(&est, &truth, true, &EvalOptions::default());
        let r = &e.robots["1"];
        assert_eq!((r.matched_poses, r.estimate_poses), (2, 5));
        assert!((r.ate_rmse - 0.1).abs() < 1e-12);
        // An infinite gap allowance interpolates across it.
        let opts = EvalOptions {
            max_truth_gap: f64::INFINITY,
            ..EvalOptions::default()
        };
        assert_eq!(
            evaluate(&est, &truth, true, &opts).robots["1"].matched_poses,
            3
        );
    }

    #[test]
    fn se2_alignment_recovers_a_rigid_transform() {
        let truth_pts: Vec<TrajectoryPoint> = (0..50)
            .map(|k| {
                let t = k as f64 * 0.2;
                TrajectoryPoint {
                    t,
                    pose: Pose2::new(math::cos(t) * 3.0 + t, math::sin(0.7 * t) * 2.0, 0.3 * t),
                }
            })
            .collect();
        let (phi, tx, ty) = (2.5, -3.0, 7.0);
        // The estimate is the truth seen in another frame: est = T^-1 truth.
        let inv = Se2 { tx, ty, phi };
        let est_pts: Vec<TrajectoryPoint> = truth_pts
            .iter()
            .map(|p| {
                let (s, c) = math::sin_cos(phi);
                let (dx, dy) = (p.pose.x - tx, p.pose.y - ty);
                TrajectoryPoint {
                    t: p.t,
                    pose: Pose2::new(
                        c * dx + s * dy,
                        -s * dx + c * dy,
                        wrap_angle(p.pose.theta - phi),
                    ),
                }
            })
            .collect();
        for p in &est_pts {
            let back = inv.apply_pose(&p.pose);
            let orig = truth_pts.iter().find(|q| q.t == p.t).unwrap().pose;
            assert!(back.distance(&orig) < 1e-9);
        }
        let truth = one_robot(truth_pts);
        let est = one_robot(est_pts);
        let e = evaluate(&est, &truth, false, &EvalOptions::default());
        assert_eq!(e.alignment, "se2");
        let [etx, ety, ephi] = e.transform.unwrap();
        assert!((etx - tx).abs() < 1e-9 && (ety - ty).abs() < 1e-9);
        assert!(wrap_angle(ephi - phi).abs() < 1e-9);
        assert!(e.team.ate_rmse < 1e-9 && e.team.heading_rmse < 1e-9);
        // Without alignment the error is large.
        assert!(evaluate(&est, &truth, false, &no_alignment()).team.ate_rmse > 1.0);
        // And a shared frame turns the automatic alignment off.
        assert_eq!(
            evaluate(&est, &truth, true, &EvalOptions::default()).alignment,
            "none"
        );
    }

    #[test]
    fn alignment_is_fitted_over_all_robots_and_moves_landmarks() {
        // Two robots, each a single point: only the joint fit can recover the rotation.
        let phi = std::f64::consts::FRAC_PI_2;
        let truth = Truth {
            trajectories: [
                ("a".to_string(), traj(&[(0.0, 1.0, 0.0, 0.0)])),
                ("b".to_string(), traj(&[(0.0, -1.0, 0.0, 0.0)])),
            ]
            .into_iter()
            .collect(),
            landmarks: vec![LandmarkRow {
                id: Some(1),
                mean: [0.0, 2.0, 0.0],
                cov: [0.0; 6],
            }],
        };
        // The estimate frame is the truth rotated by -90 degrees.
        let est = Truth {
            trajectories: [
                ("a".to_string(), traj(&[(0.0, 0.0, -1.0, -phi)])),
                ("b".to_string(), traj(&[(0.0, 0.0, 1.0, -phi)])),
            ]
            .into_iter()
            .collect(),
            landmarks: vec![LandmarkRow {
                id: Some(1),
                mean: [2.1, 0.0, 0.0],
                // Variance 0.04 along the estimate's x, which is the truth's y.
                cov: [0.04, 0.0, 0.0, 1.0, 0.0, 0.0],
            }],
        };
        let e = evaluate(&est, &truth, false, &EvalOptions::default());
        assert!(e.team.ate_rmse < 1e-12 && e.team.heading_rmse < 1e-12);
        assert!((e.team.landmark_rmse.unwrap() - 0.1).abs() < 1e-12);
        // The covariance turned with the map: d = (0, 0.1), var_y = 0.04, NEES 0.25.
        assert!((e.team.landmark_nees.unwrap() - 0.25).abs() < 1e-9);
    }

    #[test]
    fn landmarks_match_by_id() {
        let truth = Truth {
            landmarks: vec![
                row(Some(1), 0.0, 0.0),
                row(Some(2), 5.0, 0.0),
                row(Some(3), 9.0, 9.0),
            ],
            ..Truth::default()
        };
        // Id 2 is beyond the match radius from its truth but still matched by id; id 7 is
        // unknown to the truth and near nothing left; id 3 is missed.
        let est = Truth {
            landmarks: vec![
                row(Some(1), 0.3, 0.0),
                row(Some(2), 5.0, 1.5),
                row(Some(7), 20.0, 0.0),
            ],
            ..Truth::default()
        };
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        assert_eq!(
            (
                t.landmarks_matched,
                t.landmarks_missed,
                t.landmarks_spurious
            ),
            (2, 1, 1)
        );
        assert!((t.landmark_rmse.unwrap() - (1.17f64).sqrt()).abs() < 1e-12);
        assert!(t.landmark_nees.is_none() && t.landmark_nees_count == 0);
    }

    #[test]
    fn landmarks_match_by_nearest_one_to_one() {
        let truth = Truth {
            landmarks: vec![
                row(Some(1), 0.0, 0.0),
                row(Some(2), 3.0, 0.0),
                row(Some(3), 9.0, 9.0),
            ],
            ..Truth::default()
        };
        // No ids: (0.2, 0) and (0.5, 0) both want truth 1; the nearer wins and the other is
        // 2.5 m from truth 2, beyond the radius. (3.4, 0) takes truth 2.
        let est = Truth {
            landmarks: vec![
                row(None, 0.5, 0.0),
                row(None, 0.2, 0.0),
                row(None, 3.4, 0.0),
            ],
            ..Truth::default()
        };
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        assert_eq!(
            (
                t.landmarks_matched,
                t.landmarks_missed,
                t.landmarks_spurious
            ),
            (2, 1, 1)
        );
        assert!((t.landmark_rmse.unwrap() - (0.1f64).sqrt()).abs() < 1e-12);
        // A radius of 3 m lets the leftover match truth 2 only if it is free: it is not.
        let opts = EvalOptions {
            landmark_match_radius: 3.0,
            ..EvalOptions::default()
        };
        let t = evaluate(&est, &truth, true, &opts).team;
        assert_eq!((t.landmarks_matched, t.landmarks_spurious), (2, 1));
    }

    #[test]
    fn optimal_matching_has_no_radius_and_minimises_squared_error() {
        let truth = Truth {
            landmarks: vec![row(None, 0.0, 0.0), row(None, 10.0, 0.0)],
            ..Truth::default()
        };
        // Greedy nearest-first would pair (4, 0) with truth (0, 0) (4 m) and leave (-3, 0)
        // 13 m from truth (10, 0); the optimum pairs them the other way round only if it is
        // cheaper: 6² + 3² = 45 < 4² + 13² = 185.
        let est = Truth {
            landmarks: vec![
                row(None, 4.0, 0.0),
                row(None, -3.0, 0.0),
                row(None, 50.0, 0.0),
            ],
            ..Truth::default()
        };
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        assert_eq!(t.landmarks_matched, 0, "nothing within the 1 m radius");
        assert_eq!(t.landmarks_optimal_pairs, 2);
        assert!((t.landmark_rmse_optimal.unwrap() - (45.0f64 / 2.0).sqrt()).abs() < 1e-6);
    }

    #[test]
    fn grouped_truth_landmarks_match_by_their_centre() {
        let truth = Truth {
            landmarks: vec![
                row(Some(1), 0.0, 0.0),
                row(Some(2), 0.2, 0.0),
                row(Some(3), 0.4, 0.0),
                row(Some(4), 5.0, 0.0),
            ],
            ..Truth::default()
        };
        let est = Truth {
            landmarks: vec![row(None, 0.2, 0.1), row(None, 5.0, 0.1)],
            ..Truth::default()
        };
        let opts = EvalOptions {
            group_within: Some(0.3),
            landmark_match_radius: 0.3,
            ..EvalOptions::default()
        };
        let ev = evaluate(&est, &truth, true, &opts);
        assert_eq!(ev.landmark_groups, Some(2));
        let t = &ev.team;
        assert_eq!(
            (
                t.landmarks_matched,
                t.landmarks_missed,
                t.landmarks_spurious
            ),
            (2, 0, 0)
        );
        assert!((t.landmark_match_max.unwrap() - 0.1).abs() < 1e-12);
        // Ungrouped, the same map misses two of four.
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        assert_eq!((t.landmarks_matched, t.landmarks_missed), (2, 2));
        assert!(
            evaluate(&est, &truth, true, &opts)
                .to_string()
                .contains("2 groups")
        );
    }

    #[test]
    fn relative_pose_error_ignores_a_constant_offset_and_sees_drift() {
        // The truth drives along x at 1 m/s; one estimate is shifted by a constant, another
        // drifts 0.1 m per metre sideways.
        let truth_pts: Vec<(f64, f64, f64, f64)> =
            (0..=10).map(|k| (k as f64, k as f64, 0.0, 0.0)).collect();
        let truth = one_robot(traj(&truth_pts));
        let shifted: Vec<_> = truth_pts
            .iter()
            .map(|&(t, x, y, th)| (t, x + 2.0, y + 1.0, th))
            .collect();
        let ev = evaluate(&one_robot(traj(&shifted)), &truth, true, &no_alignment());
        assert!(ev.team.rpe_rmse.abs() < 1e-12 && ev.team.ate_rmse > 2.0);
        assert_eq!(ev.team.rpe_count, 10);
        let drift: Vec<_> = truth_pts
            .iter()
            .map(|&(t, x, _, th)| (t, x, 0.1 * x, th))
            .collect();
        let ev = evaluate(&one_robot(traj(&drift)), &truth, true, &no_alignment());
        assert!(
            (ev.team.rpe_rmse - 0.1).abs() < 1e-12,
            "{}",
            ev.team.rpe_rmse
        );
        assert!((ev.robots["1"].rpe_rmse - 0.1).abs() < 1e-12);
    }

    #[test]
    fn map_fit_removes_the_frame_error_and_keeps_the_shape_error() {
        let square = [(0.0, 0.0), (4.0, 0.0), (0.0, 4.0), (4.0, 4.0)];
        let truth = Truth {
            landmarks: (0..4u32)
                .map(|k| row(Some(k), square[k as usize].0, square[k as usize].1))
                .collect(),
            ..Truth::default()
        };
        // The right shape in a frame turned by 0.05 rad and moved by (0.3, -0.2).
        let frame = Se2 {
            tx: 0.3,
            ty: -0.2,
            phi: 0.05,
        };
        let mut est = truth.clone();
        for l in &mut est.landmarks {
            l.cov = [0.01, 0.0, 0.0, 0.01, 0.0, 0.0];
            *l = frame.apply_landmark(l);
        }
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        // Before the fit every landmark is off by its move: NEES |d|² / 0.01.
        let moved: f64 = square
            .iter()
            .map(|&(x, y)| {
                let (mx, my) = frame.apply_xy(x, y);
                ((mx - x).powi(2) + (my - y).powi(2)) / 0.01
            })
            .sum();
        assert!((t.landmark_nees.unwrap() - moved / 4.0).abs() < 1e-9);
        assert!(moved / 4.0 > 6.0);
        assert!(t.landmark_rmse_map_fit.unwrap() < 1e-9);
        assert!(t.landmark_nees_map_fit.unwrap() < 1e-9);
        // The shape 10 % too large about its centre: the fit is the identity and each
        // landmark is 0.1 * 2√2 m off, NEES 0.08 / 0.01 = 8.
        let mut est = truth.clone();
        for l in &mut est.landmarks {
            l.mean[0] = 2.0 + 1.1 * (l.mean[0] - 2.0);
            l.mean[1] = 2.0 + 1.1 * (l.mean[1] - 2.0);
            l.cov = [0.01, 0.0, 0.0, 0.01, 0.0, 0.0];
        }
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        assert!((t.landmark_rmse_map_fit.unwrap() - 0.2 * 2f64.sqrt()).abs() < 1e-9);
        assert!((t.landmark_nees_map_fit.unwrap() - 8.0).abs() < 1e-9);
        // Below three matched landmarks there is no fit.
        est.landmarks.truncate(2);
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        assert_eq!(t.landmarks_matched, 2);
        assert!(t.landmark_rmse_map_fit.is_none() && t.landmark_nees_map_fit.is_none());
    }

    #[test]
    fn landmark_nees_uses_positive_definite_covariances() {
        let truth = Truth {
            landmarks: vec![
                row(Some(1), 0.0, 0.0),
                row(Some(2), 5.0, 0.0),
                row(Some(3), 9.0, 0.0),
            ],
            ..Truth::default()
        };
        let mut est = truth.clone();
        // 2D: d = (0.2, 0), var_x = 0.01 -> 4.
        est.landmarks[0].mean[0] = 0.2;
        est.landmarks[0].cov = [0.01, 0.0, 0.0, 0.01, 0.0, 0.0];
        // 3D: d = (0, 0, 0.3), var_z = 0.09 -> 1.
        est.landmarks[1].mean[2] = 0.3;
        est.landmarks[1].cov = [1.0, 0.0, 0.0, 1.0, 0.0, 0.09];
        // Not positive definite: skipped.
        est.landmarks[2].cov = [1.0, 2.0, 0.0, 1.0, 0.0, 0.0];
        let t = evaluate(&est, &truth, true, &EvalOptions::default()).team;
        assert_eq!(t.landmark_nees_count, 2);
        assert!((t.landmark_nees.unwrap() - 2.5).abs() < 1e-9);
    }

    #[test]
    fn missing_pieces_are_reported_not_fatal() {
        // A truth robot without estimate, an estimate robot without truth, no landmarks.
        let truth = one_robot(traj(&[(0.0, 0.0, 0.0, 0.0)]));
        let mut est = Truth::default();
        est.trajectories
            .insert("9".into(), traj(&[(0.0, 0.0, 0.0, 0.0)]));
        let e = evaluate(&est, &truth, false, &EvalOptions::default());
        assert_eq!(e.robots["1"].estimate_poses, 0);
        assert_eq!(e.robots["9"].matched_poses, 0);
        assert!(e.team.ate_rmse.is_nan() && e.transform.is_none());
        assert_eq!(e.team.landmark_rmse, None);
        let json = serde_json::to_value(&e).unwrap();
        assert!(json["team"]["ate_rmse"].is_null() && json["team"]["landmark_rmse"].is_null());
        let back: Evaluation = serde_json::from_value(json).unwrap();
        assert!(back.team.ate_rmse.is_nan());
        let text = e.to_string();
        assert!(text.contains("n/a") && text.contains("no truth"), "{text}");
    }

    #[test]
    fn json_keys_and_summary() {
        let truth = Truth {
            landmarks: vec![row(Some(1), 0.0, 0.0)],
            ..one_robot(traj(&[(0.0, 0.0, 0.0, 0.0), (1.0, 1.0, 0.0, 0.0)]))
        };
        let est = Truth {
            landmarks: vec![row(Some(1), 0.1, 0.0)],
            ..one_robot(traj(&[(0.0, 0.0, 0.1, 0.0), (1.0, 1.0, 0.1, 0.0)]))
        };
        let e = evaluate(&est, &truth, true, &EvalOptions::default());
        let json = serde_json::to_value(&e).unwrap();
        assert!((json["robots"]["1"]["ate_rmse"].as_f64().unwrap() - 0.1).abs() < 1e-12);
        assert!((json["team"]["ate_rmse"].as_f64().unwrap() - 0.1).abs() < 1e-12);
        assert!((json["team"]["landmark_rmse"].as_f64().unwrap() - 0.1).abs() < 1e-12);
        assert_eq!(json["alignment"], "none");
        let text = e.to_string();
        assert!(
            text.contains("robot 1") && text.contains("ATE rmse 0.100 m"),
            "{text}"
        );
        assert!(text.contains("matched 1/1"), "{text}");
        assert_eq!("SE2".parse::<Alignment>(), Ok(Alignment::Se2));
        assert!("affine".parse::<Alignment>().is_err());
    }

    #[test]
    fn evaluate_dir_reads_both_and_the_frame_flag() {
        let dir = tempfile::tempdir().unwrap();
        let (est_dir, truth_dir) = (dir.path().join("est"), dir.path().join("truth"));
        let truth = Truth {
            landmarks: vec![row(Some(1), 0.0, 0.0)],
            ..one_robot(traj(&[
                (0.0, 0.0, 0.0, 0.0),
                (1.0, 1.0, 0.0, 0.0),
                (2.0, 1.0, 1.0, 1.0),
            ]))
        };
        let est = Truth {
            landmarks: vec![row(Some(1), 0.1, 0.0)],
            ..one_robot(traj(&[
                (0.0, 0.0, 0.1, 0.0),
                (1.0, 1.0, 0.1, 0.0),
                (2.0, 1.0, 1.1, 1.0),
            ]))
        };
        truth.write_dir(&truth_dir).unwrap();
        est.write_dir(&est_dir).unwrap();
        // No metrics.json: SE(2) alignment absorbs the offset.
        let e = evaluate_dir(&est_dir, &truth_dir, &EvalOptions::default()).unwrap();
        assert_eq!(e.alignment, "se2");
        assert!(e.team.ate_rmse < 1e-5);
        std::fs::write(
            est_dir.join("metrics.json"),
            r#"{"shared_frame":true,"x":1}"#,
        )
        .unwrap();
        let e = evaluate_dir(&est_dir, &truth_dir, &EvalOptions::default()).unwrap();
        assert_eq!(e.alignment, "none");
        assert!((e.team.ate_rmse - 0.1).abs() < 1e-5);
        assert!((e.team.landmark_rmse.unwrap() - 0.1).abs() < 1e-5);

        std::fs::write(est_dir.join("metrics.json"), r#"{"shared_frame":"yes"}"#).unwrap();
        let err = evaluate_dir(&est_dir, &truth_dir, &EvalOptions::default()).unwrap_err();
        assert!(err.to_string().contains("metrics.json"), "{err}");
        std::fs::write(est_dir.join("metrics.json"), "{").unwrap();
        assert!(matches!(
            evaluate_dir(&est_dir, &truth_dir, &EvalOptions::default()),
            Err(EvalError::Metrics { .. })
        ));
        std::fs::remove_file(est_dir.join("metrics.json")).unwrap();

        // Missing directories, empty directories and bad files name their path.
        let missing = dir.path().join("nope");
        let err = evaluate_dir(&missing, &truth_dir, &EvalOptions::default()).unwrap_err();
        assert!(err.to_string().contains("nope"), "{err}");
        let empty = dir.path().join("empty");
        std::fs::create_dir(&empty).unwrap();
        let err = evaluate_dir(&est_dir, &empty, &EvalOptions::default()).unwrap_err();
        assert!(matches!(err, EvalError::Empty { .. }) && err.to_string().contains("empty"));
        std::fs::write(est_dir.join("trajectory_1.tum"), "0 1 2\n").unwrap();
        let err = evaluate_dir(&est_dir, &truth_dir, &EvalOptions::default()).unwrap_err();
        assert!(err.to_string().contains("trajectory_1.tum"), "{err}");
    }

    #[test]
    fn simulated_truth_evaluates_to_zero_against_itself() {
        let sim = crate::sim::simulate(&crate::sim::SimConfig {
            duration: 10.0,
            ..Default::default()
        })
        .unwrap();
        let e = evaluate(&sim.truth, &sim.truth, false, &EvalOptions::default());
        assert_eq!(e.robots.len(), 3);
        assert_eq!(e.team.matched_poses, 3 * 51);
        assert!(e.team.ate_rmse < 1e-9 && e.team.landmark_rmse.unwrap() < 1e-9);
        assert_eq!(e.team.landmarks_matched, 20);
    }

    proptest! {
        #[test]
        fn se2_alignment_undoes_any_rigid_transform(
            pts in prop::collection::vec((-100.0f64..100.0, -100.0f64..100.0, -3.1f64..3.1), 2..40),
            phi in -std::f64::consts::PI..std::f64::consts::PI,
            tx in -1000.0f64..1000.0,
            ty in -1000.0f64..1000.0,
        ) {
            let truth_pts: Vec<TrajectoryPoint> = pts
                .iter()
                .enumerate()
                .map(|(k, &(x, y, th))| TrajectoryPoint { t: k as f64 * 0.1, pose: Pose2::new(x, y, th) })
                .collect();
            let tf = Se2 { tx, ty, phi };
            let est_pts: Vec<TrajectoryPoint> = truth_pts
                .iter()
                .map(|p| TrajectoryPoint { t: p.t, pose: tf.apply_pose(&p.pose) })
                .collect();
            let e = evaluate(&one_robot(est_pts), &one_robot(truth_pts), false, &EvalOptions::default());
            prop_assert_eq!(e.team.matched_poses, pts.len());
            prop_assert!(e.team.ate_rmse < 1e-6, "ate {}", e.team.ate_rmse);
            prop_assert!(e.team.heading_rmse < 1e-6, "heading {}", e.team.heading_rmse);
        }
    }
}
