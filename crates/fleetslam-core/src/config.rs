//! The filter's configuration: every field documents its default, unit and trade-off.

use crate::log::{LogHeader, SensorRange};
use crate::motion::{AckermannParams, MotionModel, MotionNoise};
use crate::sensor::{LandmarkKind, SensorNoise};
use serde::{Deserialize, Serialize};

/// FastSLAM 1.0 (pose sampled from the motion model) or 2.0 (pose sampled from a proposal
/// that includes the current observations; Montemerlo et al. 2003).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FastSlamVersion {
    #[serde(rename = "1", alias = "v1", alias = "1.0")]
    V1,
    #[serde(rename = "2", alias = "v2", alias = "2.0")]
    V2,
}

/// When FastSLAM 2.0 defers the pose sampling of a robot's records without landmark
/// observations ([`FilterConfig::defer_pose_sampling`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DeferSampling {
    /// While the filter holds more than one robot.
    Auto,
    Always,
    Never,
}

impl DeferSampling {
    /// Whether to defer in a filter of `robots` robots.
    pub fn defers(self, robots: usize) -> bool {
        match self {
            DeferSampling::Auto => robots > 1,
            DeferSampling::Always => true,
            DeferSampling::Never => false,
        }
    }
}

/// Online odometry calibration: each particle carries, per robot, a scale on the distance
/// and one on the rotation of every motion increment, drawn at the robot's start from
/// `N(1, std²)` and moved by a random walk of `walk_per_sqrt_s · √dt` per record (`dt` the
/// record's motion duration; for an odometry increment or a record without motion, the
/// time since the robot's previous record, uncapped; FastSLAM 2.0 draws the walk of the
/// records it keeps deferred at the robot's next record that samples, over their summed
/// time), so that particles whose scales fit the robot's odometry survive resampling (the increment
/// `(dx, dy, dθ)` becomes `(s_d dx, s_d dy, s_θ dθ)`, first order in the scale error of
/// an arc). Wheel radii and track widths wear and differ from their nominal values, and
/// commanded velocities are not what the wheels do: on MRCLAM Dataset 6 the odometry
/// over-reports distance by 5-9 % and rotation by 3-6 % (regression of the Vicon truth's
/// displacement on the odometry's over 1-3 s windows, per robot), and the MRCLAM importer
/// suggests it with ids (figures at `suggested_odometry_calibration` in `fleetslam-data`).
/// The scales are extra dimensions for the particles to cover: on odometry without bias
/// they cost accuracy (simulations, 120 s, 100 particles, prior 0.05, walk 0.001/√s: team
/// ATE 0.036 → 0.073 m with 3 robots and 20 landmarks, 0.112 → 0.223 m with 8 landmarks in
/// a 60° wedge), and so does a short run (`cargo run --release --example filter_seeds --
/// sims`). A zero standard deviation and walk keep that scale at 1; with all four zero (the
/// default) calibration is off and draws nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OdometryCalibration {
    /// Prior standard deviation of the distance scale (dimensionless). Default 0 (off).
    pub distance_std: f64,
    /// Prior standard deviation of the rotation scale (dimensionless). Default 0 (off).
    pub rotation_std: f64,
    /// Random walk of the distance scale, per √s of the record's `dt` (above). Default 0.
    pub distance_walk_per_sqrt_s: f64,
    /// Random walk of the rotation scale, per √s of the record's `dt` (above). Default 0.
    pub rotation_walk_per_sqrt_s: f64,
}

impl OdometryCalibration {
    /// Whether any scale is estimated (draws random numbers).
    pub fn enabled(&self) -> bool {
        self.distance_std > 0.0 || self.rotation_std > 0.0 || self.walks()
    }

    /// Whether the random walk moves a scale.
    pub fn walks(&self) -> bool {
        self.distance_walk_per_sqrt_s > 0.0 || self.rotation_walk_per_sqrt_s > 0.0
    }

    fn validate(&self) -> Result<(), ConfigError> {
        for (name, v, max) in [
            ("distance_std", self.distance_std, 0.5),
            ("rotation_std", self.rotation_std, 0.5),
            (
                "distance_walk_per_sqrt_s",
                self.distance_walk_per_sqrt_s,
                0.1,
            ),
            (
                "rotation_walk_per_sqrt_s",
                self.rotation_walk_per_sqrt_s,
                0.1,
            ),
        ] {
            if !(v.is_finite() && (0.0..=max).contains(&v)) {
                return Err(ConfigError(format!(
                    "odometry_calibration.{name} must lie in [0, {max}], got {v}"
                )));
            }
        }
        Ok(())
    }
}

/// How observations are matched to landmarks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Association {
    /// By the id each observation carries.
    Known,
    /// Per-particle maximum likelihood with a Mahalanobis gate (ids are ignored).
    Unknown,
}

/// Thresholds of data association, the robust measurement model and landmark existence.
///
/// Every observation adds to its particle's log-weight the log of a mixture: the Gaussian
/// likelihood of the landmark that explains it best (its squared Mahalanobis distance m²
/// under the innovation covariance S) plus a constant density for an observation that no
/// mapped landmark explains (clutter, an outlier or a new landmark):
///
/// ```text
/// ln p(z) = ln( exp(−½ m² − ½ ln|2πS|) + exp(clutter_log_density) )
/// ```
///
/// So the weight falls monotonically as the fit worsens, whether the observation updates a
/// landmark, is ambiguous, is an outlier or starts a new landmark, and it is the same
/// expression in FastSLAM 1.0 and 2.0 (2.0's S also holds the pose uncertainty).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AssociationParams {
    /// Unknown association: an observation may join a landmark when its squared Mahalanobis
    /// distance is below this. Default `null`: the χ² quantile of `gate_probability` for the
    /// measurement's dimension (9.21 for 2D range-bearing, 11.34 for 3D points at 0.99).
    pub gate: Option<f64>,
    /// Probability mass of a true match inside the gate, when `gate` is `null`. Default 0.99.
    pub gate_probability: f64,
    /// Unknown association: an observation farther than this from every landmark (squared
    /// Mahalanobis distance) starts a tentative landmark; between the gate and this it is
    /// ambiguous and changes no landmark (its weight still counts). Default `null`: the χ²
    /// quantile of `new_landmark_probability` (13.82 in 2D, 16.27 in 3D at 0.999). Lower
    /// values create more (possibly duplicate) landmarks.
    pub new_landmark: Option<f64>,
    /// Probability for the default `new_landmark` threshold. Default 0.999.
    pub new_landmark_probability: f64,
    /// Log density of an observation that no mapped landmark explains (clutter, outlier or
    /// new landmark), in the measurement's units (per m·rad in 2D, per m³ in 3D). Default
    /// `null`: the density of the sensor noise N(0, Q) at the `new_landmark` distance,
    /// `−½ (new_landmark + ln|2πQ|)`, so that an observation weighs the same whether it starts
    /// a landmark or matches one at that distance. Higher values make the weights more
    /// tolerant of gross outliers and of a robot that is off.
    pub clutter_log_density: Option<f64>,
    /// Any association: an innovation beyond this squared Mahalanobis distance is an outlier
    /// that does not update the landmark (its weight is the mixture above, like any other).
    /// Default `null` (off): once a robot is lost, a gate rejects the very observations that
    /// would bring it back. On MRCLAM Dataset 6 (500 particles, seeds 1-3) a gate of 25 lost
    /// a robot for good in one run of three (team ATE 0.89 m) where no gate gave 0.18-0.30 m.
    pub outlier: Option<f64>,
    /// Existence log-odds of a landmark before its first observation. Default 0.
    pub existence_prior: f64,
    /// Existence log-odds added per observation of a landmark. Default 1.0.
    pub existence_hit: f64,
    /// Existence log-odds removed when a landmark in the sensor's field of view was not
    /// observed (unknown association; needs `sensor_range`). Default 0.1. Higher removes
    /// spurious landmarks faster, and real ones missed by the detector too: on MRCLAM
    /// Dataset 6 without ids (first 300 s, 200 particles, seed 1), whose narrow camera often
    /// misses barcodes in its field of view, 0.4 mapped 1 of the 6 landmark groups within
    /// 0.3 m (team ATE 0.57 m) and 0.1 mapped 3 (0.33 m). A landmark is removed when its
    /// log-odds fall below zero.
    pub existence_miss: f64,
    /// Existence log-odds cap, so that long-lived landmarks can still be removed. Default 8.
    pub existence_max: f64,
    /// Unknown association: a landmark is tentative (kept and associated, but not reported
    /// in the estimate's map) until it has been observed this many times. Default 3; 1
    /// reports every landmark at once.
    pub confirm_hits: u32,
    /// Unknown association: the smallest distance (m, in the ground plane) between two
    /// landmarks of a map. An observation left without a match whose point lies closer than
    /// this to a landmark (or to one the same record started) is ambiguous and starts no
    /// landmark, and two landmarks that updates bring closer than this are merged (the one
    /// observed more often stays). Default 0.45. Features closer than this count as one
    /// landmark: MRCLAM's barcodes stand in groups whose members are 0.18-0.25 m apart
    /// (groups more than 1 m apart), which an accurate bearing otherwise splits into a
    /// landmark per member. Measured on MRCLAM Dataset 6 without ids (first 300 s, 200
    /// particles, bearing noise 0.03 rad, odometry delay 0.1 s, seeds 1-3): 0 left 9-10
    /// spurious landmarks, 0.3 left 4-7 and 0.45 left 1-4 (with 0.04 rad, 0.15 s and 0.45:
    /// 0-1 over seeds 1-4). 0 lets the Mahalanobis thresholds alone decide. A log header's
    /// `landmark_separation` replaces the default ([`FilterConfig::from_header`]):
    /// MRCLAM's `--no-ids` import suggests 0.9 m, half the distance between its groups,
    /// which also stops a drifted robot from mapping shifted copies of them.
    pub min_separation: f64,
}

impl Default for AssociationParams {
    fn default() -> Self {
        Self {
            gate: None,
            gate_probability: 0.99,
            new_landmark: None,
            new_landmark_probability: 0.999,
            clutter_log_density: None,
            outlier: None,
            existence_prior: 0.0,
            existence_hit: 1.0,
            existence_miss: 0.1,
            existence_max: 8.0,
            confirm_hits: 3,
            min_separation: 0.45,
        }
    }
}

impl AssociationParams {
    /// The association gate (squared Mahalanobis distance) for measurements of `dim`
    /// components.
    pub fn gate_for(&self, dim: usize) -> f64 {
        self.gate
            .unwrap_or_else(|| crate::stats::chi2_quantile(self.gate_probability, dim as u32))
    }

    /// The new-landmark threshold for measurements of `dim` components (never below the
    /// gate).
    pub fn new_landmark_for(&self, dim: usize) -> f64 {
        let t = self.new_landmark.unwrap_or_else(|| {
            crate::stats::chi2_quantile(self.new_landmark_probability, dim as u32)
        });
        t.max(self.gate_for(dim))
    }

    /// The clutter log density for measurement noise `q` (the covariance of `dim`
    /// components): unless set, the sensor noise's Gaussian density at the new-landmark
    /// threshold.
    pub fn clutter_for(&self, dim: usize, q_logdet: f64) -> f64 {
        self.clutter_at(self.new_landmark_for(dim), dim, q_logdet)
    }

    /// [`AssociationParams::clutter_for`] given the new-landmark threshold `new_landmark`
    /// for `dim` components, for a caller that keeps it (a χ² quantile is a bisection).
    pub fn clutter_at(&self, new_landmark: f64, dim: usize, q_logdet: f64) -> f64 {
        self.clutter_log_density
            .unwrap_or_else(|| crate::stats::gaussian_log_density(new_landmark, q_logdet, dim))
    }
}

/// Work items per rayon thread in a filter step: a step splits its particles into this many
/// contiguous work items per thread, so that every thread gets work and an uneven item
/// (a particle that associates more) can be balanced, while each item's set-up (scratch
/// buffers, loops over the record's observations) is paid a few times per step, not once per
/// `batch_size` particles. Results do not depend on it (every draw is keyed by particle).
pub const WORK_ITEMS_PER_THREAD: usize = 4;

/// The name of the built-in EKF updater in [`FilterConfig::updater`].
pub const EKF_UPDATER: &str = "ekf";

/// The configuration of one filter (one run).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FilterConfig {
    /// Number of particles N. Default 100. Cost grows linearly; accuracy saturates.
    pub particles: usize,
    /// FastSLAM version. Default 2.0, which needs far fewer particles with accurate sensors.
    pub version: FastSlamVersion,
    pub landmark_kind: LandmarkKind,
    pub motion_model: MotionModel,
    /// Vehicle constants for the Ackermann model. Default: the Victoria Park car.
    pub ackermann: AckermannParams,
    pub motion_noise: MotionNoise,
    /// Online estimation of each robot's odometry scales ([`OdometryCalibration`]). Default
    /// off; a log header may suggest it.
    pub odometry_calibration: OdometryCalibration,
    /// Landmark measurement noise assumed by the filter.
    pub sensor_noise: SensorNoise,
    /// Robot-sighting (range, bearing) noise assumed by the filter.
    pub sighting_noise: SensorNoise,
    pub association: Association,
    pub association_params: AssociationParams,
    /// The sensor's field of view, for the existence score. `None` disables removal.
    pub sensor_range: Option<SensorRange>,
    /// FastSLAM 2.0: a record without landmark observations moves each particle's pose
    /// Gaussian of its robot (mean and covariance, linearised; sightings of other robots
    /// update it) instead of sampling a pose; the next record with a landmark observation
    /// samples from the proposal built on the whole Gaussian. With many robots in one
    /// particle, resampling for one robot's observations thins out the pose hypotheses of a
    /// robot that sees nothing; a Gaussian per particle keeps its whole dead-reckoning
    /// uncertainty for the proposal to draw from when it sees a landmark again (on MRCLAM
    /// Dataset 6 one robot sees nothing for 70 s). Default `auto`: on while the filter holds
    /// more than one robot. A lone robot's hypotheses are thinned by nothing while it is
    /// blind, and a Gaussian shared by the particles makes them all associate alike: on
    /// Victoria Park (one car, unknown association, 100 particles, seeds 1-3) deferring gave
    /// ATE against GPS 4.31, 6.13 and 3.06 m, sampling 3.29, 2.82 and 2.90 m. Not used by 1.0.
    pub defer_pose_sampling: DeferSampling,
    /// FastSLAM 2.0: a record's sightings of other robots refine the proposal as its
    /// landmark observations do (the other robot's position as a landmark with its pose
    /// covariance); otherwise they only weigh the sampled pose. Default `null`: on with
    /// unknown association, off with known ids ([`FilterConfig::sightings_refine_proposal`]).
    /// Without ids a sighting is the one observation whose association is certain (it
    /// keeps its robot's id): on MRCLAM Dataset 6 without ids (1,000 particles, the header's
    /// 0.9 m separation, session 25) it mapped all 6 landmark groups within 0.3 m in 28 of
    /// seeds 1-30 (team ATE mean 0.244 m) against 17 (0.289 m) off, and left the clustered
    /// and other simulations not tuned on about where they were (README). With ids the
    /// landmarks already pin the poses and the sightings' linearisation costs accuracy:
    /// team ATE mean 0.226 m (worst 0.286 m) on seeds 1-10 against 0.215 m (0.243 m) off.
    /// Records without landmark observations always update the deferred Gaussian with their
    /// sightings.
    pub sightings_in_proposal: Option<bool>,
    /// Resample when the effective sample size falls below this fraction of N. Default 0.5.
    pub resample_threshold: f64,
    /// Seed of every random draw. Default 0.
    pub seed: u64,
    /// The most landmark updates one call of the updater's `update_batch` gets (the
    /// particles of a work item that update a landmark with one observation). Default 64:
    /// large enough to amortise a batched (learned) updater. Work items themselves are sized
    /// by the thread count ([`WORK_ITEMS_PER_THREAD`]), not by this.
    pub batch_size: usize,
    /// The landmark updater: `ekf` (default) or the id of a learned model. [`FastSlam::new`]
    /// builds the EKF; a learned updater is built by its crate and passed to
    /// [`FastSlam::with_updater`], which checks that its name matches.
    ///
    /// [`FastSlam::new`]: crate::FastSlam::new
    /// [`FastSlam::with_updater`]: crate::FastSlam::with_updater
    pub updater: String,
}

impl Default for FilterConfig {
    fn default() -> Self {
        Self {
            particles: 100,
            version: FastSlamVersion::V2,
            landmark_kind: LandmarkKind::RangeBearing2d,
            motion_model: MotionModel::Velocity,
            ackermann: AckermannParams::default(),
            motion_noise: MotionNoise::default(),
            odometry_calibration: OdometryCalibration::default(),
            sensor_noise: SensorNoise::default(),
            sighting_noise: SensorNoise::default(),
            association: Association::Known,
            association_params: AssociationParams::default(),
            sensor_range: None,
            defer_pose_sampling: DeferSampling::Auto,
            sightings_in_proposal: None,
            resample_threshold: 0.5,
            seed: 0,
            batch_size: 64,
            updater: EKF_UPDATER.to_string(),
        }
    }
}

/// A configuration error; the message names the field and the allowed values.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct ConfigError(pub String);

/// Overlays the fields of `patch` onto `base` (objects merge recursively, other values
/// replace) and parses the result; the error names the offending field. Used for layered
/// configuration: defaults or a log header, then a file, then an API request's fields.
pub fn overlay<T: Serialize + serde::de::DeserializeOwned>(
    base: &T,
    patch: serde_json::Value,
) -> Result<T, ConfigError> {
    fn merge(base: &mut serde_json::Value, patch: serde_json::Value) {
        match (base, patch) {
            (serde_json::Value::Object(b), serde_json::Value::Object(p)) => {
                for (k, v) in p {
                    merge(b.entry(k).or_insert(serde_json::Value::Null), v);
                }
            }
            (b, p) => *b = p,
        }
    }
    let mut v = serde_json::to_value(base).map_err(|e| ConfigError(e.to_string()))?;
    if !patch.is_null() {
        merge(&mut v, patch);
    }
    serde_path_to_error::deserialize(v).map_err(|e| {
        let path = e.path().to_string();
        if path == "." {
            ConfigError(e.inner().to_string())
        } else {
            ConfigError(format!("field `{path}`: {}", e.inner()))
        }
    })
}

impl FilterConfig {
    /// The configuration a log's header suggests (its models and noise).
    pub fn from_header(h: &LogHeader) -> Self {
        let d = Self::default();
        Self {
            landmark_kind: h.landmark_kind,
            motion_model: h.motion_model,
            ackermann: h.ackermann.unwrap_or(d.ackermann),
            motion_noise: h.motion_noise.unwrap_or(d.motion_noise),
            odometry_calibration: h.odometry_calibration.unwrap_or(d.odometry_calibration),
            sensor_noise: h.sensor_noise.unwrap_or(d.sensor_noise),
            sighting_noise: h
                .sighting_noise
                .or(h.sensor_noise)
                .unwrap_or(d.sighting_noise),
            association: if h.landmark_ids {
                Association::Known
            } else {
                Association::Unknown
            },
            sensor_range: h.sensor_range,
            association_params: AssociationParams {
                min_separation: h
                    .landmark_separation
                    .unwrap_or(d.association_params.min_separation),
                ..d.association_params
            },
            ..d
        }
    }

    /// Whether a landmark belongs to the reported map: with unknown association only once it
    /// has been observed `confirm_hits` times (before that it is tentative); with ids always.
    pub fn is_confirmed(&self, lm: &crate::map::Landmark) -> bool {
        self.association == Association::Known || lm.hits >= self.association_params.confirm_hits
    }

    /// Whether FastSLAM 2.0's proposal takes a record's sightings of other robots:
    /// `sightings_in_proposal` when set, otherwise with unknown association only.
    pub fn sightings_refine_proposal(&self) -> bool {
        self.sightings_in_proposal
            .unwrap_or(self.association == Association::Unknown)
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        let err = |s: String| Err(ConfigError(s));
        if self.particles == 0 || self.particles > 1_000_000 {
            return err(format!(
                "particles must be between 1 and 1000000, got {}",
                self.particles
            ));
        }
        if self.updater.is_empty() || self.updater.len() > 200 {
            return err(format!(
                "updater must be `ekf` or a model id (1 to 200 characters), got {:?}",
                self.updater
            ));
        }
        if self.batch_size == 0 {
            return err("batch_size must be at least 1".into());
        }
        if !(self.resample_threshold.is_finite() && (0.0..=1.0).contains(&self.resample_threshold))
        {
            return err(format!(
                "resample_threshold must be a fraction between 0 and 1, got {}",
                self.resample_threshold
            ));
        }
        self.motion_noise.validate().map_err(ConfigError)?;
        self.odometry_calibration.validate()?;
        self.sensor_noise
            .validate("sensor_noise")
            .map_err(ConfigError)?;
        self.sighting_noise
            .validate("sighting_noise")
            .map_err(ConfigError)?;
        let a = &self.association_params;
        let prob_ok = |p: f64| p.is_finite() && p > 0.0 && p < 1.0;
        if !prob_ok(a.gate_probability) || !prob_ok(a.new_landmark_probability) {
            return err(format!(
                "association_params.gate_probability and new_landmark_probability must lie in \
                 (0, 1), got {} and {}",
                a.gate_probability, a.new_landmark_probability
            ));
        }
        if let Some(g) = a.gate
            && !(g.is_finite() && g > 0.0)
        {
            return err(format!(
                "association_params.gate must be > 0 or null, got {g}"
            ));
        }
        let dim = self.landmark_kind.dim();
        if let Some(t) = a.new_landmark
            && !(t.is_finite() && t >= a.gate_for(dim))
        {
            return err(format!(
                "association_params.new_landmark must be >= the gate ({}) or null, got {t}",
                a.gate_for(dim)
            ));
        }
        if let Some(c) = a.clutter_log_density
            && !c.is_finite()
        {
            return err(format!(
                "association_params.clutter_log_density must be finite or null, got {c}"
            ));
        }
        if let Some(o) = a.outlier
            && !(o.is_finite() && o > 0.0)
        {
            return err(format!(
                "association_params.outlier must be > 0 or null, got {o}"
            ));
        }
        if !(a.existence_hit >= 0.0
            && a.existence_miss >= 0.0
            && a.existence_max > 0.0
            && a.existence_prior.is_finite()
            && a.existence_prior + a.existence_hit >= 0.0)
        {
            return err(
                "association_params.existence_* must be >= 0 (existence_max > 0, \
                 existence_prior + existence_hit >= 0)"
                    .into(),
            );
        }
        if !(a.min_separation.is_finite() && a.min_separation >= 0.0) {
            return err(format!(
                "association_params.min_separation must be a finite distance >= 0 (m), got {}",
                a.min_separation
            ));
        }
        if a.confirm_hits == 0 {
            return err("association_params.confirm_hits must be at least 1".into());
        }
        if let Some(r) = &self.sensor_range
            && !(r.max_range.is_finite() && r.max_range > 0.0 && r.fov.is_finite() && r.fov > 0.0)
        {
            return err(format!(
                "sensor_range needs max_range > 0 and fov > 0 (radians), got {r:?}"
            ));
        }
        let k = &self.ackermann;
        if self.motion_model == MotionModel::Ackermann
            && !(k.wheel_base.is_finite() && k.wheel_base > 0.0)
        {
            return err(format!(
                "ackermann.wheel_base must be > 0, got {}",
                k.wheel_base
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::LN_2PI;

    #[test]
    fn default_is_valid_and_errors_name_fields() {
        FilterConfig::default().validate().unwrap();
        let bad = FilterConfig {
            particles: 0,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().0.contains("particles"));
        let mut bad = FilterConfig::default();
        bad.sensor_noise.range = -1.0;
        assert!(bad.validate().unwrap_err().0.contains("sensor_noise.range"));
        for v in [-0.01, 0.6, f64::NAN] {
            let mut bad = FilterConfig::default();
            bad.odometry_calibration.rotation_std = v;
            let e = bad.validate().unwrap_err().0;
            assert!(e.contains("odometry_calibration.rotation_std"), "{e}");
        }
        let mut bad = FilterConfig::default();
        bad.odometry_calibration.distance_walk_per_sqrt_s = 0.2;
        let e = bad.validate().unwrap_err().0;
        assert!(
            e.contains("odometry_calibration.distance_walk_per_sqrt_s"),
            "{e}"
        );
    }

    #[test]
    fn gates_are_chi_square_quantiles_by_dimension() {
        let a = AssociationParams::default();
        assert!((a.gate_for(2) - 9.2103).abs() < 1e-3);
        assert!((a.gate_for(3) - 11.3449).abs() < 1e-3);
        assert!((a.new_landmark_for(2) - 13.8155).abs() < 1e-3);
        assert!((a.new_landmark_for(3) - 16.2662).abs() < 1e-3);
        let set = AssociationParams {
            gate: Some(4.0),
            new_landmark: Some(2.0),
            ..a
        };
        assert_eq!((set.gate_for(3), set.new_landmark_for(3)), (4.0, 4.0));
        // The default clutter density is the sensor noise's density at the new-landmark
        // distance.
        let c = a.clutter_for(2, 0.0);
        assert!((c - (-0.5 * (a.new_landmark_for(2) + 2.0 * LN_2PI))).abs() < 1e-12);
    }

    #[test]
    fn overlay_merges_nested_fields_and_names_bad_ones() {
        let base = FilterConfig::default();
        let c = overlay(
            &base,
            serde_json::json!({"particles": 7, "sensor_noise": {"range": 0.5}}),
        )
        .unwrap();
        assert_eq!((c.particles, c.sensor_noise.range), (7, 0.5));
        assert_eq!(c.sensor_noise.bearing, base.sensor_noise.bearing);
        let e = overlay(
            &base,
            serde_json::json!({"association_params": {"gate": "wide"}}),
        )
        .unwrap_err();
        assert!(e.0.contains("association_params.gate"), "{e}");
        assert_eq!(overlay(&base, serde_json::Value::Null).unwrap(), base);
    }

    #[test]
    fn version_spellings() {
        for s in ["\"1\"", "\"v1\"", "\"1.0\""] {
            assert_eq!(
                serde_json::from_str::<FastSlamVersion>(s).unwrap(),
                FastSlamVersion::V1
            );
        }
        let e = serde_json::from_str::<FilterConfig>(r#"{"version":"3"}"#).unwrap_err();
        assert!(e.to_string().contains("expected one of"), "{e}");
    }
}
