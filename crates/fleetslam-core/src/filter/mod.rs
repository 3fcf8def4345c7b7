//! The multi-robot, shared-map FastSLAM filter.
//!
//! Each particle holds the pose of every robot of the run and one [`LandmarkMap`] (the
//! filter stores a particle's map and weight as a [`Particle`], and its robots' poses by
//! robot, as [`RobotParticles`]). A record of robot `r` is applied to every particle:
//!
//! 1. **Association.** By id, or (unknown ids) per particle for the whole record at once,
//!    with mutual exclusion: the (observation, landmark) pairs within the Mahalanobis gate
//!    (a χ² quantile for the measurement's dimension unless set) are taken greedily, most
//!    likely first, each landmark and each observation at most once. An observation left
//!    over that lies beyond `new_landmark` from every landmark (and from those the record
//!    started) starts a tentative landmark; otherwise it is ambiguous and changes nothing.
//!    FastSLAM 2.0 associates at the motion prediction with its covariance, 1.0 at the
//!    sampled pose.
//! 2. **Pose.** FastSLAM 1.0 samples robot `r`'s new pose from the motion model. FastSLAM 2.0
//!    (Montemerlo et al. 2003) first refines the motion prediction `N(x̂, R)` with each
//!    matched observation, as a Kalman update of the pose with `S = Hₓ P Hₓᵀ + H_m Σ H_mᵀ + Q`,
//!    and samples from the result; a particle whose proposal is degenerate (non-finite, or
//!    no Cholesky factor) samples 1.0's proposal instead and is weighed as in 1.0 (counted in
//!    `proposal_fallbacks`). The other robots' poses are untouched.
//! 3. **Landmarks.** Matched landmarks are updated by the run's [`LandmarkUpdater`], one
//!    batch per observation across the particles of a work item; new ones are initialised by
//!    it. Innovations beyond the optional `outlier` distance leave the landmark alone.
//! 4. **Weight.** Every observation adds `ln(N(z; ẑ, S) + exp(clutter_log_density))`: the
//!    Gaussian likelihood of the landmark explaining it best (the updater's in 1.0; the
//!    proposal's marginal in 2.0, which includes the pose uncertainty) mixed with a constant
//!    density for clutter and new landmarks. The weight thus falls monotonically with the
//!    Mahalanobis distance whether the observation matched, was ambiguous, an outlier or
//!    new. Each sighting of another robot adds the same mixture given the two robots' poses
//!    in that particle. Over robots these sums are the product of the paper.
//! 5. **Existence.** With unknown association, landmarks in the sensor's field of view but
//!    not observed lose existence log-odds and are removed below zero (spurious landmarks);
//!    a landmark is reported only once observed `confirm_hits` times.
//! 6. **Resampling.** Systematic, when the effective sample size falls below a fraction of N.
//!
//! The code: `filter/mod.rs` holds the filter's types, its step (steps 1-6 over the
//! particles) and estimates; `work_item.rs` takes one work item of particles through a
//! record's phases; `association.rs` associates a record in one particle; `proposal.rs`
//! moves a pose (2.0's proposal, sightings, 1.0's motion sample, odometry scales);
//! `gauss.rs` holds the pose-Gaussian math they share; the measurement models' math, generic
//! over the landmark kind, is [`crate::sensor::MeasurementModel`].
//!
//! Particles are processed in parallel with rayon, in [`WORK_ITEMS_PER_THREAD`] work items
//! per thread (the updater gets at most `batch_size` updates per call).
//! Every random draw comes from a stream keyed by (seed, step, particle), so the results are
//! bit-identical for any number of threads.

mod association;
mod gauss;
mod proposal;
mod proposal_lanes;
mod snapshot;
mod work_item;

use crate::config::{
    Association, ConfigError, FastSlamVersion, FilterConfig, WORK_ITEMS_PER_THREAD,
};
use crate::log::Record;
use crate::map::LandmarkMap;
use crate::math;
use crate::motion::Motion;
use crate::pose::{
    Pose2, PoseGaussian, PositionHeading, weighted_mean_pose, weighted_mean_pose_sc, wrap_angle,
};
use crate::resample::{normalize_log_weights_keeping, systematic_weights};
use crate::rng::{LANE_ADD_ROBOT, LANE_RESAMPLE, StepStreams, stream};
use crate::sensor::LandmarkKind;
use crate::updater::{LandmarkGaussian, LandmarkUpdater};
use gauss::{cholesky_psd, normal3, sym3};
use nalgebra::{Matrix2, Matrix3, Vector3};
use proposal::draw_scales;
use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
pub use snapshot::{ParticleState, Snapshot};
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use work_item::{Chunk, process_chunk};

/// Errors of the filter; each says what was wrong with the input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    #[error("invalid configuration: {0}")]
    Config(#[from] ConfigError),
    #[error("robot {0:?} is not part of this run; add it first")]
    UnknownRobot(String),
    #[error("robot {0:?} is already part of this run")]
    DuplicateRobot(String),
    #[error("record of robot {robot:?} at t={t} is older than its previous record (t={last})")]
    TimeRegression { robot: String, t: f64, last: f64 },
    #[error("invalid record: {0}")]
    InvalidRecord(String),
    #[error("invalid start pose: {0}")]
    InvalidStart(String),
    #[error("the updater {updater:?} serves {got} landmarks but the run maps {want} landmarks")]
    UpdaterKind {
        updater: String,
        got: &'static str,
        want: &'static str,
    },
    #[error("the run's configuration names updater {want:?} but was given {got:?}")]
    UpdaterName { want: String, got: String },
    #[error("snapshot does not fit: {0}")]
    Snapshot(String),
}

/// One hypothesis's shared landmark map and weight. What it holds of each robot (pose, pose
/// Gaussian, odometry scales) is stored by robot, in [`RobotParticles`]: a step of one robot
/// then reads and writes that robot's lists from one end to the other, instead of a few
/// bytes from each particle's lists scattered over the heap.
#[derive(Debug, Clone, PartialEq)]
pub struct Particle {
    pub map: LandmarkMap,
    /// Normalised log-weight.
    pub log_w: f64,
}

/// What the particles hold of one robot: entry `i` of each list is particle `i`'s.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RobotParticles {
    /// The robot's pose.
    pub poses: Vec<Pose2>,
    /// The covariance of the pose around `poses` (upper triangle: xx, xy, xθ, yy, yθ, θθ):
    /// zero once sampled. With FastSLAM 2.0 and `defer_pose_sampling`, a record without
    /// landmark observations moves this Gaussian (linearised) instead of sampling a pose,
    /// and the next record that observes a landmark samples from the proposal built on it.
    pub pose_covs: Vec<[f64; 6]>,
    /// The scales (distance, rotation) the particle applies to the robot's motion
    /// increments ([`crate::config::OdometryCalibration`]); `[1, 1]` when not estimated.
    pub odometry_scales: Vec<[f64; 2]>,
}

impl RobotParticles {
    /// Particle `i`'s entries, as a snapshot writes them.
    fn at(&self, i: usize) -> (Pose2, [f64; 6], [f64; 2]) {
        (self.poses[i], self.pose_covs[i], self.odometry_scales[i])
    }

    /// The lists in the particles' new order after a resample: entry `k` is the old
    /// entry `idx[k]`.
    fn gather(&self, idx: &[usize]) -> Self {
        Self {
            poses: idx.iter().map(|&i| self.poses[i]).collect(),
            pose_covs: idx.iter().map(|&i| self.pose_covs[i]).collect(),
            odometry_scales: idx.iter().map(|&i| self.odometry_scales[i]).collect(),
        }
    }
}

/// The robots' lists other than the stepping robot's, whose list the work items hold
/// mutably in pieces: sightings read another robot's pose Gaussian in each particle.
#[derive(Clone, Copy)]
struct OtherRobots<'a> {
    before: &'a [RobotParticles],
    after: &'a [RobotParticles],
    robot: usize,
}

impl<'a> OtherRobots<'a> {
    /// Robot `other`'s pose and pose covariance in particle `i`; `None` for the stepping
    /// robot itself (a record's sighting of its own robot is refused before a step).
    fn get(&self, other: usize, i: usize) -> Option<(&'a Pose2, &'a [f64; 6])> {
        let list = match other.cmp(&self.robot) {
            std::cmp::Ordering::Less => self.before.get(other)?,
            std::cmp::Ordering::Equal => return None,
            std::cmp::Ordering::Greater => self.after.get(other - self.robot - 1)?,
        };
        Some((list.poses.get(i)?, list.pose_covs.get(i)?))
    }
}

/// A robot of the run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotState {
    pub id: String,
    /// Time of its latest record (or its start).
    pub last_t: f64,
    /// Number of records applied.
    pub records: u64,
    /// Seconds of the odometry scales' random walk not drawn yet. A record whose pose stays
    /// a deferred Gaussian (FastSLAM 2.0, no landmark observation) draws nothing; the walk
    /// over its time is drawn at the robot's next record that samples, as one step over
    /// the whole time (the same distribution at that record: a Gaussian walk's steps add
    /// up). 0 in snapshots written before it was kept.
    #[serde(default)]
    pub scale_walk_pending_s: f64,
}

/// Counters over the life of the filter.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct FilterStats {
    pub steps: u64,
    /// Landmark observations the steps applied (each record's, once; those without an id
    /// under known association are not applied and not counted). Zero in snapshots written
    /// before it existed.
    #[serde(default)]
    pub observations: u64,
    /// Landmark updates computed by the updater (one per particle and observation).
    pub landmark_updates: u64,
    /// Time spent inside the updater's batch calls, summed over threads [ns].
    pub update_nanos: u64,
    pub landmarks_created: u64,
    pub landmarks_removed: u64,
    pub outliers: u64,
    pub ignored_observations: u64,
    /// Sightings of robots that are not (yet) in the filter.
    pub unmatched_sightings: u64,
    pub resamples: u64,
    /// FastSLAM 2.0 particles whose proposal was degenerate (non-finite, or a covariance
    /// without a Cholesky factor) and that used 1.0's proposal instead.
    #[serde(default)]
    pub proposal_fallbacks: u64,
    /// Landmarks merged into another of their map for lying closer than
    /// `association_params.min_separation` (unknown association).
    #[serde(default)]
    pub landmarks_merged: u64,
}

impl FilterStats {
    fn add(mut self, o: FilterStats) -> FilterStats {
        self.landmark_updates += o.landmark_updates;
        self.update_nanos += o.update_nanos;
        self.landmarks_created += o.landmarks_created;
        self.landmarks_removed += o.landmarks_removed;
        self.outliers += o.outliers;
        self.ignored_observations += o.ignored_observations;
        self.proposal_fallbacks += o.proposal_fallbacks;
        self.landmarks_merged += o.landmarks_merged;
        self
    }
}

/// What one step did.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepReport {
    /// Index of the robot that moved.
    pub robot: usize,
    pub ess: f64,
    pub resampled: bool,
    /// Landmarks in the best particle after the step.
    pub landmarks: usize,
    /// Landmarks the best particle gained and lost in this step.
    pub landmarks_added: usize,
    pub landmarks_removed: usize,
}

/// A robot's estimated pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotEstimate {
    pub id: String,
    /// The pose in the particle of highest weight.
    pub best: Pose2,
    /// The weighted mean pose (circular mean for the heading).
    pub mean: Pose2,
    /// Weighted covariance of (x, y, theta) around the mean.
    pub cov: [[f64; 3]; 3],
    pub last_t: f64,
    pub records: u64,
    /// The weighted mean of the particles' odometry scales (distance, rotation) of this
    /// robot; `[1, 1]` without [`crate::config::OdometryCalibration`].
    #[serde(default = "unit_scales")]
    pub odometry_scale: [f64; 2],
}

fn unit_scales() -> [f64; 2] {
    [1.0; 2]
}

/// A landmark of the best particle's map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LandmarkEstimate {
    pub slot: usize,
    pub id: Option<u32>,
    /// With known ids, the landmark's marginal over the particles (their Gaussians' weighted
    /// mixture, moment-matched: it holds the uncertainty of the trajectories that mapped
    /// it); with unknown association, whose slots differ between particles, the best
    /// particle's Gaussian.
    pub gaussian: LandmarkGaussian,
    pub hits: u32,
}

/// The filter's current estimate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub robots: Vec<RobotEstimate>,
    pub landmarks: Vec<LandmarkEstimate>,
    pub ess: f64,
    pub particles: usize,
    pub best_particle: usize,
    pub step: u64,
}

/// The filter.
#[derive(Debug, Clone)]
pub struct FastSlam {
    config: FilterConfig,
    updater: Arc<dyn LandmarkUpdater>,
    robots: Vec<RobotState>,
    robot_index: HashMap<String, usize>,
    particles: Vec<Particle>,
    /// `by_robot[r]`: what the particles hold of robot r.
    by_robot: Vec<RobotParticles>,
    known_slots: BTreeMap<u32, usize>,
    step: u64,
    ess: f64,
    stats: FilterStats,
    /// Thresholds derived from the (immutable) configuration once, not per step.
    derived: Derived,
    /// `exp(log_w)` of each particle as the last normalisation or resample computed it (the
    /// same bits as computing it again); empty before the first step. Estimates read it
    /// instead of taking an `exp` per particle on every record.
    weights: Vec<f64>,
    /// `headings[r][i]`: robot r's position and `(sin θ, cos θ)` of its heading in particle
    /// i, computed in parallel by the last step that moved robot r (no other step changes
    /// that pose), for its mean pose and for its next step's motion; a robot's list is empty
    /// (and computed when needed) before its first step and after a restore.
    headings: Vec<Vec<PositionHeading>>,
    /// The instruction set the steps' work items are compiled for, detected at construction
    /// (AVX2 where the CPU has it, as the EKF's batches): the filter's pose and matrix
    /// arithmetic then takes fewer instructions (three-operand forms, wider moves). Rust
    /// never fuses a multiply and an add on its own, so every instruction set gives the
    /// same bits ([`FastSlam::baseline_simd`] and its test).
    arch: pulp::Arch,
}

/// The association thresholds and clutter densities that follow from a configuration (χ²
/// quantiles by bisection: too slow to recompute on every step).
#[derive(Debug, Clone, Copy)]
struct Derived {
    /// Gate and new-landmark threshold (squared Mahalanobis distances) for the run's
    /// measurement dimension.
    gate: f64,
    new_landmark: f64,
    /// Log density of a landmark observation that no mapped landmark explains.
    clutter: f64,
    /// The same for a robot sighting (range-bearing, the sighting noise).
    sighting_clutter: f64,
    /// The new-landmark threshold of a range-bearing reading (2 components): a reading
    /// whose noise grows with its range has a clutter density of its own
    /// ([`range_bearing_noise`]), built with it on every step without the χ² quantile's
    /// bisection.
    new_landmark_2d: f64,
}

/// A range-bearing reading's noise at its measured range `r` and the log density of the
/// reading if nothing explains it: `constant_clutter` (derived once per filter) with the
/// noise's constant part when its range noise does not grow with the range, else the
/// clutter density of the reading's own noise (`AssociationParams::clutter_for`).
fn range_bearing_noise(
    noise: &crate::sensor::SensorNoise,
    r: f64,
    association: &crate::config::AssociationParams,
    derived: &Derived,
    constant_clutter: f64,
) -> (Matrix2<f64>, f64) {
    if noise.range_per_m > 0.0 {
        let q = noise.q2_at(r);
        let clutter = association.clutter_at(derived.new_landmark_2d, 2, math::ln(q.determinant()));
        (q, clutter)
    } else {
        (noise.q2(), constant_clutter)
    }
}

impl Derived {
    fn of(cfg: &FilterConfig) -> Self {
        let dim = cfg.landmark_kind.dim();
        let q_logdet = match cfg.landmark_kind {
            LandmarkKind::RangeBearing2d => math::ln(cfg.sensor_noise.q2().determinant()),
            LandmarkKind::Point3d => math::ln(cfg.sensor_noise.q3().determinant()),
        };
        let a = &cfg.association_params;
        Self {
            gate: a.gate_for(dim),
            new_landmark: a.new_landmark_for(dim),
            clutter: a.clutter_for(dim, q_logdet),
            sighting_clutter: a.clutter_for(2, math::ln(cfg.sighting_noise.q2().determinant())),
            new_landmark_2d: a.new_landmark_for(2),
        }
    }
}

/// What a particle does with one observation.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Action {
    Update(usize),
    /// A new landmark; in a known-id map, at this slot.
    New(Option<usize>),
    Ignore,
    Outlier,
}

/// One observation, resolved before the parallel part.
#[derive(Debug, Clone, Copy)]
struct Obs {
    z: [f64; 3],
    id: Option<u32>,
    /// Known association: the landmark's slot.
    slot: Option<usize>,
    /// Log density of this observation if no mapped landmark explains it (the sensor
    /// noise's at the new-landmark distance; it depends on the measured range when the
    /// range noise does).
    clutter: f64,
}

/// A sighting of another robot, resolved before the parallel part.
#[derive(Debug, Clone, Copy)]
struct Sighting {
    /// The seen robot's index.
    robot: usize,
    /// Range and bearing.
    z: [f64; 2],
    /// The sighting noise at this range.
    q: Matrix2<f64>,
    /// Log density of the sighting if no robot explains it (the sighting noise's at the
    /// new-landmark distance).
    clutter: f64,
}

/// Read-only inputs of one step, shared by the work items.
struct StepCtx<'a> {
    cfg: &'a FilterConfig,
    updater: &'a dyn LandmarkUpdater,
    inc: Pose2,
    /// The standard deviations of the odometry scales' random walk over the motion's
    /// duration and the deferred records' before it ([`proposal::scale_walk`],
    /// [`RobotState::scale_walk_pending_s`]), the same for every particle; `None` on a
    /// deferred record.
    scale_walk: Option<[f64; 2]>,
    /// Variances of the (longitudinal, lateral, heading) increment noise.
    var: [f64; 3],
    /// Their square roots.
    std: [f64; 3],
    obs: &'a [Obs],
    sightings: &'a [Sighting],
    /// The other robots' poses in the particles, for the sightings.
    others: OtherRobots<'a>,
    /// The particles' random streams of this step (lane: the particle's slot).
    streams: StepStreams,
    known_len: usize,
    /// The association gate and new-landmark threshold (squared Mahalanobis distances) for
    /// the run's measurement dimension.
    gate: f64,
    new_landmark: f64,
    /// Whether this record's poses stay deferred Gaussians: FastSLAM 2.0 deferring pose
    /// sampling (`defer_pose_sampling` for the filter's current number of robots) and a
    /// record without landmark observations.
    defer: bool,
}

impl FastSlam {
    /// A filter with the EKF updater of the configured landmark kind and sensor noise.
    /// Refuses a configuration that names another updater: build that one and pass it to
    /// [`FastSlam::with_updater`].
    pub fn new(config: FilterConfig) -> Result<Self, FilterError> {
        if config.updater != crate::config::EKF_UPDATER {
            return Err(FilterError::UpdaterName {
                want: config.updater.clone(),
                got: crate::config::EKF_UPDATER.to_string(),
            });
        }
        let ekf = crate::ekf::EkfUpdater::new(config.landmark_kind, &config.sensor_noise);
        Self::with_updater(config, Arc::new(ekf))
    }

    /// A filter with the given landmark updater.
    pub fn with_updater(
        config: FilterConfig,
        updater: Arc<dyn LandmarkUpdater>,
    ) -> Result<Self, FilterError> {
        config.validate()?;
        check_updater(&config, updater.as_ref())?;
        let n = config.particles;
        let particles = (0..n)
            .map(|_| Particle {
                map: new_map(config.association),
                log_w: -math::ln(n as f64),
            })
            .collect();
        Ok(Self {
            derived: Derived::of(&config),
            config,
            updater,
            robots: Vec::new(),
            robot_index: HashMap::new(),
            particles,
            by_robot: Vec::new(),
            known_slots: BTreeMap::new(),
            step: 0,
            ess: n as f64,
            stats: FilterStats::default(),
            weights: Vec::new(),
            headings: Vec::new(),
            arch: pulp::Arch::new(),
        })
    }

    /// The same filter with its steps compiled for the baseline instruction set (no runtime
    /// dispatch): for checking that the dispatch changes no result.
    pub fn baseline_simd(mut self) -> Self {
        self.arch = pulp::Arch::Scalar;
        self
    }

    pub fn config(&self) -> &FilterConfig {
        &self.config
    }

    pub fn updater(&self) -> &Arc<dyn LandmarkUpdater> {
        &self.updater
    }

    pub fn robots(&self) -> &[RobotState] {
        &self.robots
    }

    pub fn robot_index(&self, id: &str) -> Option<usize> {
        self.robot_index.get(id).copied()
    }

    pub fn particles(&self) -> &[Particle] {
        &self.particles
    }

    /// What the particles hold of each robot, in the order robots were added.
    pub fn robot_particles(&self) -> &[RobotParticles] {
        &self.by_robot
    }

    pub fn stats(&self) -> &FilterStats {
        &self.stats
    }

    pub fn ess(&self) -> f64 {
        self.ess
    }

    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// Adds a robot at a known pose: each particle draws its pose from `start`.
    pub fn add_robot(
        &mut self,
        id: &str,
        start: &PoseGaussian,
        t0: f64,
    ) -> Result<usize, FilterError> {
        self.check_new_robot(id, t0)?;
        if !start.mean.is_finite() || start.cov.iter().flatten().any(|v| !v.is_finite()) {
            return Err(FilterError::InvalidStart(format!(
                "{start:?} has a non-finite number"
            )));
        }
        let cov = Matrix3::from_fn(|i, j| 0.5 * (start.cov[i][j] + start.cov[j][i]));
        let chol = if cov.iter().all(|v| *v == 0.0) {
            None
        } else {
            Some(cholesky_psd(&cov).ok_or_else(|| {
                FilterError::InvalidStart("covariance is not positive semi-definite".into())
            })?)
        };
        let (seed, step) = (self.config.seed, self.step);
        let mean = start.mean;
        let poses = (0..self.particles.len())
            .into_par_iter()
            .map(|i| match &chol {
                None => mean,
                Some(l) => {
                    let mut rng = stream(seed, step, LANE_ADD_ROBOT + i as u64);
                    let e = l * normal3(&mut rng);
                    Pose2::new(mean.x + e[0], mean.y + e[1], wrap_angle(mean.theta + e[2]))
                }
            })
            .collect();
        Ok(self.finish_add_robot(id, t0, poses))
    }

    /// Adds a robot whose pose is known as a weighted sample set (a localization posterior):
    /// each particle draws one sample with probability proportional to its weight.
    pub fn add_robot_from_samples(
        &mut self,
        id: &str,
        samples: &[Pose2],
        weights: &[f64],
        t0: f64,
    ) -> Result<usize, FilterError> {
        self.check_new_robot(id, t0)?;
        if samples.is_empty() || samples.len() != weights.len() {
            return Err(FilterError::InvalidStart(
                "need as many weights as samples, and at least one".into(),
            ));
        }
        if samples.iter().any(|s| !s.is_finite())
            || weights.iter().any(|w| !(w.is_finite() && *w >= 0.0))
        {
            return Err(FilterError::InvalidStart(
                "non-finite sample or negative weight".into(),
            ));
        }
        let mut cum: Vec<f64> = weights
            .iter()
            .scan(0.0, |acc, w| {
                *acc += w;
                Some(*acc)
            })
            .collect();
        let total = *cum.last().unwrap_or(&0.0);
        if total <= 0.0 {
            return Err(FilterError::InvalidStart("the weights sum to zero".into()));
        }
        cum.iter_mut().for_each(|c| *c /= total);
        let (seed, step) = (self.config.seed, self.step);
        let poses = (0..self.particles.len())
            .into_par_iter()
            .map(|i| {
                let u: f64 = stream(seed, step, LANE_ADD_ROBOT + i as u64).random();
                samples[cum.partition_point(|&c| c < u).min(samples.len() - 1)]
            })
            .collect();
        Ok(self.finish_add_robot(id, t0, poses))
    }

    fn check_new_robot(&self, id: &str, t0: f64) -> Result<(), FilterError> {
        if id.is_empty() {
            return Err(FilterError::InvalidStart(
                "robot id must not be empty".into(),
            ));
        }
        if self.robot_index.contains_key(id) {
            return Err(FilterError::DuplicateRobot(id.to_string()));
        }
        if !t0.is_finite() {
            return Err(FilterError::InvalidStart(format!(
                "start time {t0} is not finite"
            )));
        }
        Ok(())
    }

    /// Registers a robot whose poses in the particles are `poses` (sampled, no pose
    /// covariance), each particle drawing its odometry scales of the robot.
    fn finish_add_robot(&mut self, id: &str, t0: f64, poses: Vec<Pose2>) -> usize {
        let (seed, step) = (self.config.seed, self.step);
        let calibration = self.config.odometry_calibration;
        let n = poses.len();
        self.by_robot.push(RobotParticles {
            poses,
            pose_covs: vec![[0.0; 6]; n],
            odometry_scales: (0..n)
                .into_par_iter()
                .map(|i| draw_scales(&calibration, seed, step, i))
                .collect(),
        });
        let idx = self.robots.len();
        self.robots.push(RobotState {
            id: id.to_string(),
            last_t: t0,
            records: 0,
            scale_walk_pending_s: 0.0,
        });
        self.robot_index.insert(id.to_string(), idx);
        self.step += 1;
        idx
    }

    /// Applies one record. On error nothing changed.
    pub fn step(&mut self, rec: &Record) -> Result<StepReport, FilterError> {
        let cfg = &self.config;
        rec.validate(cfg.landmark_kind, cfg.motion_model)
            .map_err(FilterError::InvalidRecord)?;
        let r = self
            .robot_index(&rec.robot)
            .ok_or_else(|| FilterError::UnknownRobot(rec.robot.clone()))?;
        let last = self.robots[r].last_t;
        if rec.t < last {
            return Err(FilterError::TimeRegression {
                robot: rec.robot.clone(),
                t: rec.t,
                last,
            });
        }
        let gap = rec.t - last;
        let (inc, dt) = match &rec.motion {
            None => (Pose2::default(), gap),
            Some(m @ Motion::Odometry(_)) => (m.increment(&cfg.ackermann), gap),
            Some(m) => (m.increment(&cfg.ackermann), m.duration()),
        };
        let var = cfg.motion_noise.variances(&inc, dt);

        // Resolve known ids to slots (new ids get the next slot in every particle; a new id
        // seen twice in the record takes one).
        let mut known_len = self.known_slots.len();
        let mut new_ids = Vec::new();
        let mut slot_of = |id: u32| {
            let seen = self.known_slots.get(&id).copied();
            seen.or_else(|| new_ids.iter().find(|(i, _)| *i == id).map(|&(_, s)| s))
                .unwrap_or_else(|| {
                    let s = known_len;
                    known_len += 1;
                    new_ids.push((id, s));
                    s
                })
        };
        let obs: Vec<Obs> = rec
            .landmarks
            .iter()
            .map(|o| {
                let mut z = [0.0; 3];
                z[..o.z.len()].copy_from_slice(&o.z);
                let slot = match (cfg.association, o.id) {
                    (Association::Known, Some(id)) => Some(slot_of(id)),
                    _ => None,
                };
                // Landmarks keep the observations' ids only when association is by id.
                let id = (cfg.association == Association::Known)
                    .then_some(o.id)
                    .flatten();
                let clutter = match cfg.landmark_kind {
                    LandmarkKind::RangeBearing2d => {
                        let (a, d) = (&cfg.association_params, &self.derived);
                        range_bearing_noise(&cfg.sensor_noise, z[0], a, d, d.clutter).1
                    }
                    LandmarkKind::Point3d => self.derived.clutter,
                };
                Obs {
                    z,
                    id,
                    slot,
                    clutter,
                }
            })
            .filter(|o| cfg.association == Association::Unknown || o.slot.is_some())
            .collect();
        let ignored_no_id = rec.landmarks.len() - obs.len();

        let mut sightings = Vec::new();
        let mut unmatched = 0;
        for s in &rec.robots {
            match self.robot_index(&s.robot) {
                Some(j) => {
                    let (q, clutter) = range_bearing_noise(
                        &cfg.sighting_noise,
                        s.z[0],
                        &cfg.association_params,
                        &self.derived,
                        self.derived.sighting_clutter,
                    );
                    sightings.push(Sighting {
                        robot: j,
                        z: [s.z[0], s.z[1]],
                        q,
                        clutter,
                    })
                }
                None => unmatched += 1,
            }
        }

        let reweighs = !obs.is_empty() || !sightings.is_empty();
        // The best particle and its map's size before the step, for the landmarks a
        // reweighing step added or removed.
        let (best_before, slots_before) = if reweighs {
            let best = self.best_index();
            (best, self.particles[best].map.len())
        } else {
            (0, 0)
        };
        let n = self.particles.len();
        self.headings.resize(self.robots.len(), Vec::new());
        let headings = &mut self.headings[r];
        let (before, rest) = self.by_robot.split_at_mut(r);
        let (mine, after) = rest
            .split_first_mut()
            .expect("every robot of the run has its particles' lists");
        // Kept since the robot last moved, or computed first (its first step, or after a
        // restore).
        let headings_known = headings.len() == n;
        headings.resize(n, PositionHeading::default());
        let d = self.derived;
        let defer = cfg.version == FastSlamVersion::V2
            && cfg.defer_pose_sampling.defers(self.robots.len())
            && obs.is_empty();
        // The odometry scales walk at the records that sample, over the time since the
        // robot's last such record.
        let walk_s = self.robots[r].scale_walk_pending_s + dt;
        let (scale_walk, walk_pending) = if defer {
            (None, walk_s)
        } else {
            (proposal::scale_walk(&cfg.odometry_calibration, walk_s), 0.0)
        };
        let ctx = StepCtx {
            cfg,
            updater: self.updater.as_ref(),
            inc,
            scale_walk,
            var,
            std: var.map(f64::sqrt),
            obs: &obs,
            sightings: &sightings,
            others: OtherRobots {
                before,
                after,
                robot: r,
            },
            streams: StepStreams::new(cfg.seed, self.step),
            known_len,
            gate: d.gate,
            new_landmark: d.new_landmark,
            defer,
        };

        let batch = work_item_len(n, rayon::current_num_threads());
        let arch = self.arch;
        let step_stats = (
            self.particles.par_chunks_mut(batch),
            mine.poses.par_chunks_mut(batch),
            mine.pose_covs.par_chunks_mut(batch),
            mine.odometry_scales.par_chunks_mut(batch),
            headings.par_chunks_mut(batch),
        )
            .into_par_iter()
            .enumerate()
            .map(
                |(c, (particles, poses, pose_covs, odometry_scales, headings))| {
                    if !headings_known {
                        for (p, h) in poses.iter().zip(headings.iter_mut()) {
                            *h = PositionHeading::of(p);
                        }
                    }
                    let mut chunk = Chunk {
                        base: c * batch,
                        particles,
                        poses,
                        pose_covs,
                        odometry_scales,
                    };
                    let stats = process_chunk(arch, &ctx, &mut chunk, headings);
                    for (p, h) in chunk.poses.iter().zip(headings.iter_mut()) {
                        h.move_to(p);
                    }
                    stats
                },
            )
            .reduce(FilterStats::default, FilterStats::add);

        for (id, s) in new_ids {
            self.known_slots.insert(id, s);
        }
        self.robots[r].last_t = rec.t;
        self.robots[r].records += 1;
        self.robots[r].scale_walk_pending_s = walk_pending;
        self.stats = self.stats.add(step_stats);
        self.stats.ignored_observations += ignored_no_id as u64;
        self.stats.unmatched_sightings += unmatched;
        self.stats.steps += 1;
        self.stats.observations += obs.len() as u64;

        // A record without observations or sightings changes no weight and no map: the
        // weights stay as the last step normalised them, and the ESS and the decision to
        // resample with them (the last step already took it).
        let (mut added, mut removed, mut resampled) = (0, 0, false);
        if reweighs {
            let mut log_w: Vec<f64> = self.particles.iter().map(|p| p.log_w).collect();
            self.ess = normalize_log_weights_keeping(&mut log_w, &mut self.weights);
            for (p, w) in self.particles.iter_mut().zip(&log_w) {
                p.log_w = *w;
            }
            let best = self.best_index();
            if best == best_before {
                let now = self.particles[best].map.len();
                added = now.saturating_sub(slots_before);
                removed = slots_before.saturating_sub(now);
            }
            resampled = self.ess < self.config.resample_threshold * n as f64;
            if resampled {
                self.resample();
            }
        }
        self.step += 1;
        Ok(StepReport {
            robot: r,
            ess: self.ess,
            resampled,
            landmarks: self.particles[self.best_index()].map.len(),
            landmarks_added: added,
            landmarks_removed: removed,
        })
    }

    /// Resamples by the normalised weights the step kept (`self.weights`).
    fn resample(&mut self) {
        let mut rng = stream(self.config.seed, self.step, LANE_RESAMPLE);
        let idx = systematic_weights(&self.weights, &mut rng);
        let n = self.particles.len();
        let uniform = -math::ln(n as f64);
        self.weights.clear();
        self.weights.resize(n, math::exp(uniform));
        for h in self.headings.iter_mut().filter(|h| h.len() == n) {
            *h = idx.iter().map(|&i| h[i]).collect();
        }
        for list in &mut self.by_robot {
            *list = list.gather(&idx);
        }
        // Each parent's last child takes the parent itself; only the others are copies. The
        // copies are made, and the particles no child took are dropped (their maps' nodes
        // freed where no other particle shares them), in parallel: the reference counts they
        // leave do not depend on the order, and the moves in between are serial.
        let mut children = vec![0u32; n];
        for &i in &idx {
            children[i] += 1;
        }
        let takes: Vec<bool> = idx
            .iter()
            .map(|&i| {
                children[i] -= 1;
                children[i] == 0
            })
            .collect();
        let old = std::mem::take(&mut self.particles);
        let copies: Vec<Option<Particle>> = idx
            .par_iter()
            .zip(&takes)
            .map(|(&i, &take)| (!take).then(|| old[i].clone()))
            .collect();
        let mut old: Vec<Option<Particle>> = old.into_iter().map(Some).collect();
        self.particles = copies
            .into_iter()
            .zip(idx.iter().zip(&takes))
            .map(|(copy, (&i, &take))| {
                let parent = if take { old[i].take() } else { copy };
                Particle {
                    log_w: uniform,
                    ..parent.expect("a parent is taken by its last child only")
                }
            })
            .collect();
        old.into_par_iter().for_each(drop);
        self.ess = n as f64;
        self.stats.resamples += 1;
    }

    /// Index of the particle of highest weight (the first on ties).
    pub fn best_index(&self) -> usize {
        let mut best = 0;
        for (i, p) in self.particles.iter().enumerate() {
            if p.log_w > self.particles[best].log_w {
                best = i;
            }
        }
        best
    }

    /// Weighted mean pose of one robot.
    pub fn mean_pose(&self, robot: usize) -> Pose2 {
        let n = self.particles.len();
        let headings = self.headings.get(robot).filter(|h| h.len() == n);
        match headings {
            Some(h) => {
                weighted_mean_pose_sc(h.iter().enumerate().map(|(i, &h)| (h, self.weight(i))))
            }
            None => weighted_mean_pose(
                self.by_robot[robot]
                    .poses
                    .iter()
                    .enumerate()
                    .map(|(i, p)| (p, self.weight(i))),
            ),
        }
    }

    /// Particle `i`'s normalised weight `exp(log_w)`: the one the last normalisation kept
    /// (the same bits), or computed when there is none (a new or restored filter).
    #[inline]
    fn weight(&self, i: usize) -> f64 {
        match self.weights.get(i) {
            Some(&w) if self.weights.len() == self.particles.len() => w,
            _ => math::exp(self.particles[i].log_w),
        }
    }

    /// Up to `max` particles' poses of one robot, evenly spaced over the particle set, with
    /// their normalised weights.
    pub fn particle_sample(&self, robot: usize, max: usize) -> Vec<(Pose2, f64)> {
        let n = self.particles.len();
        let stride = n.div_ceil(max.max(1)).max(1);
        self.by_robot[robot]
            .poses
            .iter()
            .enumerate()
            .step_by(stride)
            .map(|(i, p)| (*p, self.weight(i)))
            .collect()
    }

    /// The current estimate: robot poses (best and mean), the best particle's landmarks.
    pub fn estimate(&self) -> Estimate {
        let best = self.best_index();
        let robots = self
            .robots
            .iter()
            .enumerate()
            .map(|(r, st)| {
                let mean = self.mean_pose(r);
                let mut cov = [[0.0; 3]; 3];
                let (mut odometry_scale, mut sw) = ([0.0; 2], 0.0);
                let list = &self.by_robot[r];
                for i in 0..self.particles.len() {
                    let w = self.weight(i);
                    sw += w;
                    for (m, s) in odometry_scale.iter_mut().zip(list.odometry_scales[i]) {
                        *m += w * s;
                    }
                    let q = &list.poses[i];
                    let d = [q.x - mean.x, q.y - mean.y, wrap_angle(q.theta - mean.theta)];
                    // The spread of the particles plus each one's own pose covariance.
                    let pc = sym3(&list.pose_covs[i]);
                    for i in 0..3 {
                        for j in 0..3 {
                            cov[i][j] += w * (d[i] * d[j] + pc[(i, j)]);
                        }
                    }
                }
                // Divided by the weights' sum, so that scales of 1 read exactly 1.
                odometry_scale = odometry_scale.map(|m| m / sw);
                RobotEstimate {
                    id: st.id.clone(),
                    best: list.poses[best],
                    mean,
                    cov,
                    last_t: st.last_t,
                    records: st.records,
                    odometry_scale,
                }
            })
            .collect();
        let known = self.config.association == Association::Known;
        let landmarks = self.particles[best]
            .map
            .iter()
            .filter(|(_, l)| self.config.is_confirmed(l))
            .map(|(slot, l)| LandmarkEstimate {
                slot,
                id: l.id,
                gaussian: if known {
                    self.landmark_marginal(slot).unwrap_or(l.gaussian)
                } else {
                    l.gaussian
                },
                hits: l.hits,
            })
            .collect();
        Estimate {
            robots,
            landmarks,
            ess: self.ess,
            particles: self.particles.len(),
            best_particle: best,
            step: self.step,
        }
    }

    /// The marginal of a known-id landmark over the particles: the weighted mixture of its
    /// Gaussians, moment-matched (`Σ wᵢ μᵢ`, `Σ wᵢ (Σᵢ + (μᵢ - μ)(μᵢ - μ)ᵀ)`), so that its
    /// covariance holds the uncertainty of the trajectories that mapped it, which each
    /// particle's own Gaussian (conditioned on its trajectory) leaves out. `None` when no
    /// particle has weight on it.
    fn landmark_marginal(&self, slot: usize) -> Option<LandmarkGaussian> {
        let mut sw = 0.0;
        let mut mean = Vector3::zeros();
        for (i, p) in self.particles.iter().enumerate() {
            if let Some(l) = p.map.get(slot) {
                let w = self.weight(i);
                sw += w;
                mean += w * Vector3::from(l.gaussian.mean);
            }
        }
        if sw.is_nan() || sw <= 0.0 {
            return None;
        }
        mean /= sw;
        let mut cov = Matrix3::zeros();
        for (i, p) in self.particles.iter().enumerate() {
            if let Some(l) = p.map.get(slot) {
                let w = self.weight(i) / sw;
                let d = Vector3::from(l.gaussian.mean) - mean;
                cov += w * (l.gaussian.cov3() + d * d.transpose());
            }
        }
        let g = LandmarkGaussian::from_3d(mean.into(), &cov);
        g.is_finite().then_some(g)
    }

    /// A snapshot from which [`FastSlam::from_snapshot`] continues bit for bit.
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            config: self.config.clone(),
            robots: self.robots.clone(),
            particles: self
                .particles
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    let n = self.by_robot.len();
                    let (mut poses, mut pose_covs, mut odometry_scales) = (
                        Vec::with_capacity(n),
                        Vec::with_capacity(n),
                        Vec::with_capacity(n),
                    );
                    for list in &self.by_robot {
                        let (pose, cov, scales) = list.at(i);
                        poses.push(pose);
                        pose_covs.push(cov);
                        odometry_scales.push(scales);
                    }
                    ParticleState {
                        poses,
                        pose_covs,
                        odometry_scales,
                        map: p.map.clone(),
                        log_w: p.log_w,
                    }
                })
                .collect(),
            known_slots: self.known_slots.clone(),
            step: self.step,
            ess: self.ess,
            stats: self.stats,
        }
    }

    /// Restores a filter from a snapshot, with the updater the run uses.
    pub fn from_snapshot(
        mut s: Snapshot,
        updater: Arc<dyn LandmarkUpdater>,
    ) -> Result<Self, FilterError> {
        s.config.validate()?;
        check_updater(&s.config, updater.as_ref())?;
        if s.particles.len() != s.config.particles {
            return Err(FilterError::Snapshot(format!(
                "{} particles but the configuration says {}",
                s.particles.len(),
                s.config.particles
            )));
        }
        if s.particles.iter().any(|p| p.poses.len() != s.robots.len()) {
            return Err(FilterError::Snapshot(
                "a particle lacks a robot's pose".into(),
            ));
        }
        for p in &mut s.particles {
            if s.config.association == Association::Known {
                p.map.drop_index();
            }
            if p.pose_covs.len() != p.poses.len() {
                if !p.pose_covs.is_empty() {
                    return Err(FilterError::Snapshot(
                        "a particle's pose covariances do not match its poses".into(),
                    ));
                }
                p.pose_covs = vec![[0.0; 6]; p.poses.len()];
            }
            if p.odometry_scales.len() != p.poses.len() {
                if !p.odometry_scales.is_empty() {
                    return Err(FilterError::Snapshot(
                        "a particle's odometry scales do not match its poses".into(),
                    ));
                }
                p.odometry_scales = vec![[1.0; 2]; p.poses.len()];
            }
        }
        let robot_index = s
            .robots
            .iter()
            .enumerate()
            .map(|(i, r)| (r.id.clone(), i))
            .collect();
        let n = s.particles.len();
        let mut by_robot: Vec<RobotParticles> = (0..s.robots.len())
            .map(|_| RobotParticles {
                poses: Vec::with_capacity(n),
                pose_covs: Vec::with_capacity(n),
                odometry_scales: Vec::with_capacity(n),
            })
            .collect();
        let particles = s
            .particles
            .into_iter()
            .map(|p| {
                for (r, list) in by_robot.iter_mut().enumerate() {
                    list.poses.push(p.poses[r]);
                    list.pose_covs.push(p.pose_covs[r]);
                    list.odometry_scales.push(p.odometry_scales[r]);
                }
                Particle {
                    map: p.map,
                    log_w: p.log_w,
                }
            })
            .collect();
        Ok(Self {
            derived: Derived::of(&s.config),
            config: s.config,
            updater,
            robots: s.robots,
            robot_index,
            particles,
            by_robot,
            known_slots: s.known_slots,
            step: s.step,
            ess: s.ess,
            stats: s.stats,
            weights: Vec::new(),
            headings: Vec::new(),
            arch: pulp::Arch::new(),
        })
    }
}

/// A particle's empty map: with known association, landmarks are found by their ids' slots
/// alone, so the map keeps no spatial index (which would cost every landmark write).
fn new_map(association: Association) -> LandmarkMap {
    match association {
        Association::Known => LandmarkMap::without_index(),
        Association::Unknown => LandmarkMap::new(),
    }
}

/// Particles per work item of a step: the particles spread over
/// [`WORK_ITEMS_PER_THREAD`] items per thread.
fn work_item_len(particles: usize, threads: usize) -> usize {
    particles
        .div_ceil(threads.max(1) * WORK_ITEMS_PER_THREAD)
        .max(1)
}

fn check_updater(cfg: &FilterConfig, u: &dyn LandmarkUpdater) -> Result<(), FilterError> {
    if u.kind() != cfg.landmark_kind {
        return Err(FilterError::UpdaterKind {
            updater: u.name().to_string(),
            got: u.kind().as_str(),
            want: cfg.landmark_kind.as_str(),
        });
    }
    if u.name() != cfg.updater {
        return Err(FilterError::UpdaterName {
            want: cfg.updater.clone(),
            got: u.name().to_string(),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::proposal::propose;
    use super::*;
    use crate::config::{DeferSampling, OdometryCalibration};
    use crate::log::LandmarkObservation;
    use crate::map::Landmark;
    use crate::motion::{MotionNoise, covariance_in_world};
    use crate::sensor::{MeasurementModel, RangeBearingModel, SensorNoise, range_bearing_predict};

    fn still() -> MotionNoise {
        MotionNoise {
            trans_per_m: 0.0,
            lateral_per_m: 0.0,
            rot_per_rad: 0.0,
            rot_per_m: 0.0,
            trans_per_sqrt_s: 0.0,
            rot_per_sqrt_s: 0.0,
            random_walk_max_dt: 1.0,
        }
    }

    fn config(version: FastSlamVersion, association: Association, n: usize) -> FilterConfig {
        FilterConfig {
            particles: n,
            version,
            association,
            motion_noise: still(),
            resample_threshold: 0.0,
            ..Default::default()
        }
    }

    /// A filter whose particle k maps one landmark (id 7) at (2 + offsets[k], 0), robot at
    /// the origin facing +x.
    fn filter_with_offsets(
        version: FastSlamVersion,
        association: Association,
        offsets: &[f64],
    ) -> FastSlam {
        let cfg = config(version, association, offsets.len());
        let f = robot_r(cfg);
        let mut snap = f.snapshot();
        for (p, d) in snap.particles.iter_mut().zip(offsets) {
            p.map.push(Landmark {
                gaussian: LandmarkGaussian {
                    mean: [2.0 + d, 0.0, 0.0],
                    cov: [0.01, 0.0, 0.0, 0.01, 0.0, 0.0],
                },
                id: Some(7),
                existence: 5.0,
                hits: 5,
            });
        }
        snap.known_slots.insert(7, 0);
        FastSlam::from_snapshot(snap, f.updater().clone()).unwrap()
    }

    /// Under known association the particles' maps keep no spatial index, also after a
    /// snapshot (whose maps are read with one); under unknown association they keep one.
    #[test]
    fn only_maps_searched_by_place_keep_an_index() {
        for (association, indexed) in [(Association::Known, false), (Association::Unknown, true)] {
            let mut f = filter_with_offsets(FastSlamVersion::V2, association, &[0.0, 0.1]);
            f.step(&record(&[[2.0, 0.0]])).unwrap();
            let g = FastSlam::from_snapshot(f.snapshot(), f.updater().clone()).unwrap();
            for p in f.particles().iter().chain(g.particles()) {
                assert!(!p.map.is_empty());
                assert_eq!(p.map.is_indexed(), indexed, "{association:?}");
            }
        }
    }

    /// The weights and headings a step keeps give the mean pose that `exp` of each
    /// log-weight and the poses' own headings give, bit for bit, after a step that resampled
    /// and one that did not, and after a restore (which keeps neither).
    #[test]
    fn kept_weights_give_the_mean_of_the_log_weights() {
        let f = filter_with_offsets(FastSlamVersion::V1, Association::Known, &offsets());
        let mut snap = f.snapshot();
        snap.config.resample_threshold = 0.5;
        let mut f = FastSlam::from_snapshot(snap, f.updater().clone()).unwrap();
        f.add_robot(
            "s",
            &PoseGaussian::diagonal(Pose2::new(1.0, 1.0, 0.5), 0.1, 0.1, 0.1),
            0.0,
        )
        .unwrap();
        let direct = |f: &FastSlam, r: usize| {
            weighted_mean_pose(
                f.particles()
                    .iter()
                    .zip(&f.robot_particles()[r].poses)
                    .map(|(p, pose)| (pose, math::exp(p.log_w))),
            )
        };
        let mut resampled = [false, false];
        for k in 0..8 {
            // First a still robot whose range tells the particles' landmarks apart.
            let rec = match k {
                0 => record(&[[2.0, 0.0]]),
                3 | 6 => moving("s", 1.0 + k as f64, &[], &[]),
                _ => moving("r", 1.0 + k as f64, &[[2.0 - 0.1 * k as f64, 0.0]], &[]),
            };
            let before: Vec<u64> = f.particles().iter().map(|p| p.log_w.to_bits()).collect();
            let (ess, kept) = (f.ess(), f.weights.clone());
            let report = f.step(&rec).unwrap();
            resampled[usize::from(report.resampled)] = true;
            assert_eq!(f.weights.len(), f.particles().len());
            if rec.landmarks.is_empty() && rec.robots.is_empty() {
                // Nothing to weigh: weights, ESS and kept weights stay, bit for bit.
                let after = f.particles().iter().map(|p| p.log_w.to_bits());
                assert!(after.eq(before) && !report.resampled);
                assert_eq!((f.ess().to_bits(), &f.weights), (ess.to_bits(), &kept));
            }
            for r in 0..2 {
                assert_eq!(f.mean_pose(r), direct(&f, r));
                // A robot's kept headings are its poses' own, whichever robot moved last.
                let kept = &f.headings[r];
                let own = f.robot_particles()[r].poses.iter().map(PositionHeading::of);
                // (robot "s", 1, moves first at step 3)
                if r == 0 || k >= 3 {
                    assert!(kept.iter().copied().eq(own), "robot {r} after step {k}");
                }
            }
        }
        assert_eq!(resampled, [true, true], "both kinds of step were taken");
        let g = FastSlam::from_snapshot(f.snapshot(), f.updater().clone()).unwrap();
        assert!(g.weights.is_empty() && g.headings.is_empty());
        assert_eq!(g.mean_pose(0), f.mean_pose(0));
        assert_eq!(g.mean_pose(1), f.mean_pose(1));
        assert_eq!(g.estimate(), f.estimate());
    }

    /// Robot "r" observing landmark 7 at `z` at t = 1 without moving.
    fn record(z: &[[f64; 2]]) -> Record {
        Record {
            seq: 0,
            motion: None,
            ..moving("r", 1.0, z, &[])
        }
    }

    fn offsets() -> Vec<f64> {
        // Range innovations 0..1.2 m against S_rr = 0.02: squared Mahalanobis distances from
        // 0 to 72, across the gate (9.21) and the new-landmark threshold (13.8).
        (0..25).map(|k| 0.05 * k as f64).collect()
    }

    fn moving(robot: &str, t: f64, z: &[[f64; 2]], sightings: &[(&str, [f64; 2])]) -> Record {
        Record {
            robot: robot.into(),
            seq: t as u64,
            t,
            motion: Some(Motion::Velocity(vec![[0.5, 0.1, 1.0]])),
            landmarks: z
                .iter()
                .map(|z| LandmarkObservation {
                    id: Some(7),
                    z: z.to_vec(),
                })
                .collect(),
            robots: sightings
                .iter()
                .map(|(r, z)| crate::log::RobotSighting {
                    robot: r.to_string(),
                    z: z.to_vec(),
                })
                .collect(),
        }
    }

    #[test]
    fn fastslam2_defers_sampling_until_a_landmark_is_seen() {
        let cfg = FilterConfig {
            particles: 20,
            defer_pose_sampling: DeferSampling::Always,
            ..Default::default()
        };
        let d = FilterConfig::default();
        assert_eq!(d.defer_pose_sampling, DeferSampling::Auto);
        assert_eq!(d.version, FastSlamVersion::V2);
        let mut f = robot_r(cfg.clone());
        let inc = Motion::Velocity(vec![[0.5, 0.1, 1.0]]).increment(&cfg.ackermann);
        let mut dead_reckoned = Pose2::default();
        let mut trace = 0.0;
        for k in 1..=5 {
            f.step(&moving("r", k as f64, &[], &[])).unwrap();
            dead_reckoned = dead_reckoned.compose(&inc);
            // Every particle holds the dead-reckoned mean and one growing covariance.
            let r0 = &f.robot_particles()[0];
            assert!(r0.poses.iter().all(|p| *p == r0.poses[0]));
            let d = r0.poses[0];
            assert!((d.x - dead_reckoned.x).abs() < 1e-12 && (d.y - dead_reckoned.y).abs() < 1e-12);
            let c = r0.pose_covs[0];
            assert!(c[0] + c[3] + c[5] > trace, "{c:?}");
            trace = c[0] + c[3] + c[5];
            // The estimate's covariance is that Gaussian's.
            let e = f.estimate();
            assert!((e.robots[0].cov[0][0] - c[0]).abs() < 1e-12);
            assert!((e.robots[0].cov[2][2] - c[5]).abs() < 1e-12);
        }
        // The covariance holds what five sampled steps would spread: the heading variance
        // grows linearly in the steps.
        let one = covariance_in_world(&Pose2::default(), &cfg.motion_noise.variances(&inc, 1.0));
        assert!((f.robot_particles()[0].pose_covs[0][5] - 5.0 * one[(2, 2)]).abs() < 1e-12);
        // A landmark observation samples from the proposal built on it.
        f.step(&moving("r", 6.0, &[[2.0, 0.3]], &[])).unwrap();
        let r0 = &f.robot_particles()[0];
        assert!(r0.pose_covs.iter().all(|c| *c == [0.0; 6]));
        let spread = r0
            .poses
            .iter()
            .map(|p| (p.x - r0.poses[0].x).abs())
            .fold(0.0, f64::max);
        assert!(spread > 1e-3, "{spread}");
        // Without deferral every record samples, and so does `auto` with one robot; with
        // two, `auto` defers.
        for (defer, robots, deferred) in [
            (DeferSampling::Never, 1, false),
            (DeferSampling::Never, 2, false),
            (DeferSampling::Auto, 1, false),
            (DeferSampling::Auto, 2, true),
        ] {
            let mut g = FastSlam::new(FilterConfig {
                defer_pose_sampling: defer,
                ..cfg.clone()
            })
            .unwrap();
            for k in 0..robots {
                g.add_robot(
                    &format!("r{k}"),
                    &PoseGaussian::exact(Pose2::default()),
                    0.0,
                )
                .unwrap();
            }
            g.step(&moving("r0", 1.0, &[], &[])).unwrap();
            let r0 = &g.robot_particles()[0];
            let same = r0.poses.iter().all(|p| *p == r0.poses[0]);
            let zero = r0.pose_covs.iter().all(|c| *c == [0.0; 6]);
            assert_eq!(
                (same, !zero),
                (deferred, deferred),
                "{defer:?} with {robots}"
            );
        }
    }

    #[test]
    fn a_deferred_gaussian_survives_a_snapshot_and_old_snapshots_read_as_sampled() {
        let cfg = FilterConfig {
            particles: 8,
            defer_pose_sampling: DeferSampling::Always,
            ..Default::default()
        };
        let mut f = robot_r(cfg);
        for k in 1..=3 {
            f.step(&moving("r", k as f64, &[], &[])).unwrap();
        }
        let json = serde_json::to_value(f.snapshot()).unwrap();
        let back: Snapshot = serde_json::from_value(json.clone()).unwrap();
        let g = FastSlam::from_snapshot(back, f.updater().clone()).unwrap();
        assert_eq!(g.particles(), f.particles());
        assert_eq!(g.robot_particles(), f.robot_particles());
        assert!(g.robot_particles()[0].pose_covs[0][5] > 0.0);
        // A snapshot written before pose covariances existed: every pose is a sample.
        let mut old = json;
        for p in old["particles"].as_array_mut().unwrap() {
            p.as_object_mut().unwrap().remove("pose_covs");
        }
        let old: Snapshot = serde_json::from_value(old).unwrap();
        let h = FastSlam::from_snapshot(old, f.updater().clone()).unwrap();
        let covs = &h.robot_particles()[0].pose_covs;
        assert!(covs.len() == 8 && covs.iter().all(|c| *c == [0.0; 6]));
        // A mismatched one is refused.
        let mut bad = f.snapshot();
        bad.particles[0].pose_covs.push([0.0; 6]);
        assert!(FastSlam::from_snapshot(bad, f.updater().clone()).is_err());
    }

    fn calibrated(cal: OdometryCalibration) -> FastSlam {
        let cfg = FilterConfig {
            particles: 16,
            odometry_calibration: cal,
            ..Default::default()
        };
        robot_r(cfg)
    }

    #[test]
    fn odometry_scales_are_drawn_walk_and_scale_the_increment() {
        // Off: every scale is exactly 1 and the estimate reports 1.
        let f = calibrated(OdometryCalibration::default());
        assert!(
            f.robot_particles()[0]
                .odometry_scales
                .iter()
                .all(|s| *s == [1.0; 2])
        );
        assert_eq!(f.estimate().robots[0].odometry_scale, [1.0; 2]);
        // A prior only: drawn once per particle, spread by about its standard deviation,
        // then fixed.
        let cal = OdometryCalibration {
            distance_std: 0.05,
            rotation_std: 0.02,
            ..Default::default()
        };
        let mut f = calibrated(cal);
        let drawn = f.robot_particles()[0].odometry_scales.clone();
        let spread = |k: usize| {
            let m = drawn.iter().map(|s| s[k]).sum::<f64>() / drawn.len() as f64;
            (drawn.iter().map(|s| (s[k] - m).powi(2)).sum::<f64>() / drawn.len() as f64).sqrt()
        };
        assert!((0.025..0.1).contains(&spread(0)), "{}", spread(0));
        assert!((0.01..0.04).contains(&spread(1)), "{}", spread(1));
        f.step(&moving("r", 1.0, &[], &[])).unwrap();
        let after = f.robot_particles()[0].odometry_scales.clone();
        let sorted = |mut v: Vec<[f64; 2]>| {
            v.sort_by(|a, b| a.partial_cmp(b).unwrap());
            v
        };
        // Resampling may reorder them; the set stays the same without a walk.
        assert!(
            sorted(after)
                .iter()
                .all(|s| sorted(drawn.clone()).contains(s))
        );
        // With a walk and no motion noise, a particle's pose is the scaled increment.
        let cal = OdometryCalibration {
            distance_walk_per_sqrt_s: 0.01,
            rotation_walk_per_sqrt_s: 0.01,
            ..Default::default()
        };
        let cfg = FilterConfig {
            particles: 4,
            motion_noise: still(),
            odometry_calibration: cal,
            ..Default::default()
        };
        let mut f = robot_r(cfg);
        f.step(&moving("r", 1.0, &[], &[])).unwrap();
        let inc = Motion::Velocity(vec![[0.5, 0.1, 1.0]]).increment(&f.config().ackermann);
        let r0 = &f.robot_particles()[0];
        for (&[sd, sr], &got) in r0.odometry_scales.iter().zip(&r0.poses) {
            assert!(sd != 1.0 && sr != 1.0);
            let want = Pose2::new(sd * inc.x, sd * inc.y, sr * inc.theta);
            assert!((got.x - want.x).abs() < 1e-12 && (got.theta - want.theta).abs() < 1e-12);
        }
    }

    /// Records kept as deferred pose Gaussians draw no walk of the scales; the next record
    /// that samples walks them over the whole time since the robot last sampled, which a
    /// snapshot keeps.
    #[test]
    fn deferred_records_walk_the_scales_at_the_next_sampled_record() {
        let walk = 0.1;
        let cfg = FilterConfig {
            particles: 4000,
            motion_noise: still(),
            defer_pose_sampling: DeferSampling::Always,
            odometry_calibration: OdometryCalibration {
                distance_walk_per_sqrt_s: walk,
                rotation_walk_per_sqrt_s: walk,
                ..Default::default()
            },
            ..Default::default()
        };
        let mut f = robot_r(cfg);
        // Four records of 1 s without observations: deferred, nothing drawn.
        for k in 1..=4 {
            f.step(&moving("r", k as f64, &[], &[])).unwrap();
        }
        let scales = |f: &FastSlam| f.robot_particles()[0].odometry_scales.clone();
        assert!(scales(&f).iter().all(|s| *s == [1.0; 2]));
        assert_eq!(f.robots()[0].scale_walk_pending_s, 4.0);
        let mut g = FastSlam::from_snapshot(f.snapshot(), f.updater().clone()).unwrap();
        assert_eq!(g.robots(), f.robots());
        // A record with a landmark samples: the scales walk over 5 s at once. Its landmark
        // is new in every particle, so the weights stay equal and nothing is resampled.
        for h in [&mut f, &mut g] {
            let rep = h.step(&moving("r", 5.0, &[[2.0, 0.0]], &[])).unwrap();
            assert!(!rep.resampled);
            assert_eq!(h.robots()[0].scale_walk_pending_s, 0.0);
        }
        assert_eq!(scales(&f), scales(&g));
        let s = scales(&f);
        for k in 0..2 {
            let m = s.iter().map(|s| s[k]).sum::<f64>() / s.len() as f64;
            let sd = (s.iter().map(|s| (s[k] - m).powi(2)).sum::<f64>() / s.len() as f64).sqrt();
            // 4,000 draws: the spread's standard error is about 1.1 %, the mean's 0.0035
            // (measured: within 0.14 % and 0.0011); a walk of the last 1 s only would
            // spread them by 0.1.
            let want = walk * 5f64.sqrt();
            assert!(
                (sd / want - 1.0).abs() < 0.03,
                "scale {k}: spread {sd}, want {want}"
            );
            assert!((m - 1.0).abs() < 0.01, "scale {k}: mean {m}");
        }
    }

    #[test]
    fn odometry_scales_survive_a_snapshot_and_old_snapshots_read_as_one() {
        let cal = OdometryCalibration {
            distance_std: 0.05,
            rotation_std: 0.05,
            distance_walk_per_sqrt_s: 0.001,
            rotation_walk_per_sqrt_s: 0.001,
        };
        let mut f = calibrated(cal);
        f.step(&moving("r", 1.0, &[], &[])).unwrap();
        let json = serde_json::to_value(f.snapshot()).unwrap();
        let g = FastSlam::from_snapshot(
            serde_json::from_value(json.clone()).unwrap(),
            f.updater().clone(),
        )
        .unwrap();
        assert_eq!(g.particles(), f.particles());
        assert_eq!(g.robot_particles(), f.robot_particles());
        let mut old = json;
        for p in old["particles"].as_array_mut().unwrap() {
            p.as_object_mut().unwrap().remove("odometry_scales");
        }
        let h = FastSlam::from_snapshot(serde_json::from_value(old).unwrap(), f.updater().clone())
            .unwrap();
        assert!(
            h.robot_particles()[0]
                .odometry_scales
                .iter()
                .all(|s| *s == [1.0; 2])
        );
        let mut bad = f.snapshot();
        bad.particles[0].odometry_scales.clear();
        bad.particles[0].odometry_scales.push([1.0; 2]);
        bad.particles[0].odometry_scales.push([1.0; 2]);
        assert!(FastSlam::from_snapshot(bad, f.updater().clone()).is_err());
    }

    /// A filter of `cfg` with robot "r" known exactly at the origin at t = 0.
    fn robot_r(cfg: FilterConfig) -> FastSlam {
        let mut f = FastSlam::new(cfg).unwrap();
        f.add_robot("r", &PoseGaussian::exact(Pose2::default()), 0.0)
            .unwrap();
        f
    }

    /// A filter of `cfg` with robot a at the origin and robot b at `b`, both known exactly
    /// at t = 0: the set-up of the sighting tests.
    fn robots_a_and_b(cfg: FilterConfig, b: Pose2) -> FastSlam {
        let mut f = FastSlam::new(cfg).unwrap();
        f.add_robot("a", &PoseGaussian::exact(Pose2::default()), 0.0)
            .unwrap();
        f.add_robot("b", &PoseGaussian::exact(b), 0.0).unwrap();
        f
    }

    /// A sighting is weighed against the seen robot's pose in the same particle, in every
    /// work item (the seen robot's entries lie in its own list, found by the particle's slot
    /// in the filter), whether the seeing robot defers its pose (2.0) or samples it (1.0).
    #[test]
    fn a_sighting_weighs_each_particle_by_its_own_pose_of_the_seen_robot() {
        let n = 41;
        for version in [FastSlamVersion::V1, FastSlamVersion::V2] {
            let f = robots_a_and_b(config(version, Association::Known, n), Pose2::default());
            // Particle k holds robot a at 2 + 0.02 (k - 20) m ahead of b.
            let mut snap = f.snapshot();
            for (k, p) in snap.particles.iter_mut().enumerate() {
                p.poses[0].x = 2.0 + 0.02 * (k as f64 - 20.0);
            }
            let mut f = FastSlam::from_snapshot(snap, f.updater().clone()).unwrap();
            let mut rec = moving("b", 1.0, &[], &[("a", [2.0, 0.0])]);
            rec.motion = None;
            f.step(&rec).unwrap();
            let w: Vec<f64> = f.particles().iter().map(|p| p.log_w).collect();
            for k in 0..n {
                let (d, inner) = (k.abs_diff(20), if k < 20 { k + 1 } else { k - 1 });
                if d > 0 {
                    assert!(w[k] < w[inner], "{version:?}: particle {k} {w:?}");
                }
            }
        }
    }

    #[test]
    fn a_sighting_updates_the_deferred_pose_gaussian() {
        // Robot b moves blind for 5 s; then it sees robot a (exactly at the origin) at the
        // range and bearing its true pose gives, or sees nothing.
        let run = |sight: bool| {
            let cfg = FilterConfig {
                particles: 4,
                ..Default::default()
            };
            let mut f = robots_a_and_b(cfg, Pose2::new(-2.0, 0.0, 0.0));
            for k in 1..=5 {
                f.step(&moving("b", k as f64, &[], &[])).unwrap();
            }
            // The truth is 0.2 m to the left of where dead reckoning puts b at t = 6.
            let inc = Motion::Velocity(vec![[0.5, 0.1, 1.0]]).increment(&f.config().ackermann);
            let b = f.robot_particles()[1].poses[0].compose(&inc);
            let truth = Pose2::new(b.x, b.y + 0.2, b.theta);
            let (z, _, _) = range_bearing_predict(&truth, 0.0, 0.0).unwrap();
            let sightings: Vec<(&str, [f64; 2])> = if sight {
                vec![("a", [z[0], z[1]])]
            } else {
                vec![]
            };
            f.step(&moving("b", 6.0, &[], &sightings)).unwrap();
            let b = &f.robot_particles()[1];
            (b.poses[0], b.pose_covs[0])
        };
        let (blind, blind_cov) = run(false);
        let (seen, seen_cov) = run(true);
        // Less uncertain, and pulled towards the pose that explains the sighting.
        assert!(
            seen_cov[0] + seen_cov[3] < blind_cov[0] + blind_cov[3],
            "{seen_cov:?} {blind_cov:?}"
        );
        assert!(seen.y > blind.y + 0.01, "{seen:?} {blind:?}");
    }

    #[test]
    fn a_sighting_noise_that_grows_with_range_weighs_as_the_constant_noise_at_that_range() {
        // Robot b, deferred, then moving and seeing a: with sighting noise 0.1 m + 5 % the
        // filter must equal the one told the constant noise at that sighting's range (the
        // deferred update, the weights and their clutter floor), 1.0 and 2.0 alike.
        // The sighting is the one b's dead-reckoned pose at t = 4 gives.
        let inc = Motion::Velocity(vec![[0.5, 0.1, 1.0]]).increment(&Default::default());
        let mut b4 = Pose2::new(-5.0, 0.0, 0.0);
        for _ in 0..4 {
            b4 = b4.compose(&inc);
        }
        let (zh, _, _) = range_bearing_predict(&b4, 0.0, 0.0).unwrap();
        let z = [zh[0], zh[1]];
        for version in [FastSlamVersion::V1, FastSlamVersion::V2] {
            let run = |sighting_noise: SensorNoise| {
                let cfg = FilterConfig {
                    particles: 16,
                    version,
                    sighting_noise,
                    seed: 5,
                    ..Default::default()
                };
                let mut f = robots_a_and_b(cfg, Pose2::new(-5.0, 0.0, 0.0));
                for k in 1..=3 {
                    f.step(&moving("b", k as f64, &[], &[])).unwrap();
                }
                f.step(&moving("b", 4.0, &[], &[("a", z)])).unwrap();
                f.step(&moving("b", 5.0, &[[2.0, 0.2]], &[])).unwrap();
                f
            };
            let grow = SensorNoise {
                range: 0.1,
                range_per_m: 0.05,
                ..SensorNoise::default()
            };
            let fixed = SensorNoise {
                range: grow.range_std_at(z[0]),
                range_per_m: 0.0,
                ..grow
            };
            let (a, b) = (run(grow), run(fixed));
            let close = |x: f64, y: f64| (x - y).abs() <= 1e-9 * (1.0 + y.abs());
            for (pa, pb) in a.particles().iter().zip(b.particles()) {
                assert!(
                    close(pa.log_w, pb.log_w),
                    "{version:?}: {} {}",
                    pa.log_w,
                    pb.log_w
                );
            }
            for (pa, pb) in a.robot_particles()[1]
                .poses
                .iter()
                .zip(&b.robot_particles()[1].poses)
            {
                assert!(close(pa.x, pb.x) && close(pa.y, pb.y), "{pa:?} {pb:?}");
            }
            // And the growth matters: a constant 0.1 m weighs (or resamples) otherwise.
            let c = run(SensorNoise {
                range: 0.1,
                ..SensorNoise::default()
            });
            let differs = a
                .particles()
                .iter()
                .zip(c.particles())
                .any(|(pa, pc)| !close(pa.log_w, pc.log_w))
                || a.robot_particles()[1].poses != c.robot_particles()[1].poses;
            assert!(differs, "{version:?}");
        }
    }

    #[test]
    fn weight_falls_monotonically_with_the_mahalanobis_distance() {
        for version in [FastSlamVersion::V1, FastSlamVersion::V2] {
            for association in [Association::Known, Association::Unknown] {
                let mut f = filter_with_offsets(version, association, &offsets());
                f.step(&record(&[[2.0, 0.0]])).unwrap();
                let w: Vec<f64> = f.particles().iter().map(|p| p.log_w).collect();
                for k in 1..w.len() {
                    assert!(
                        w[k] < w[k - 1] || (w[k] - w[k - 1]).abs() < 1e-9,
                        "{version:?} {association:?}: weight rises from offset {} to {}: {w:?}",
                        offsets()[k - 1],
                        offsets()[k],
                    );
                }
                // Strictly falling while the Gaussian term dominates the clutter term.
                assert!(w[0] > w[6] + 2.0 && w[3] > w[5] + 0.5, "{w:?}");
                // The far particles are explained by clutter alike: the weight flattens.
                assert!((w[23] - w[24]).abs() < 1e-6, "{w:?}");
            }
        }
    }

    #[test]
    fn weights_are_the_same_in_fastslam_1_and_2_without_motion_noise() {
        for association in [Association::Known, Association::Unknown] {
            let run = |version| {
                let mut f = filter_with_offsets(version, association, &offsets());
                f.step(&record(&[[2.0, 0.0], [3.0, 0.5]])).unwrap();
                f.particles().iter().map(|p| p.log_w).collect::<Vec<_>>()
            };
            let (w1, w2) = (run(FastSlamVersion::V1), run(FastSlamVersion::V2));
            for (a, b) in w1.iter().zip(&w2) {
                assert!((a - b).abs() < 1e-9, "{association:?}: {w1:?} vs {w2:?}");
            }
        }
    }

    /// A known id seen twice in the record that first maps it: the id takes one slot, the
    /// first observation creates the landmark and the second updates it, in 1.0 and 2.0
    /// alike. Before session 30 each observation took a slot of its own (two landmarks of
    /// one id), and had they shared one the second would have been dropped (no update, no
    /// likelihood in the weight).
    #[test]
    fn a_new_id_seen_twice_in_a_record_is_created_then_updated() {
        for version in [FastSlamVersion::V1, FastSlamVersion::V2] {
            let n = 8;
            let mut f = robot_r(config(version, Association::Known, n));
            f.step(&record(&[[2.0, 0.0], [2.05, 0.01]])).unwrap();
            let stats = f.stats();
            assert_eq!(f.known_slots.len(), 1, "{version:?}");
            assert_eq!(stats.landmarks_created, n as u64, "{version:?}");
            assert_eq!(stats.landmark_updates, n as u64, "{version:?}");
            let mut once = robot_r(config(version, Association::Known, n));
            once.step(&record(&[[2.0, 0.0]])).unwrap();
            for (p, q) in f.particles().iter().zip(once.particles()) {
                let (l, k) = (p.map.get(0).unwrap(), q.map.get(0).unwrap());
                assert_eq!(l.hits, 2, "{version:?}");
                assert!(
                    l.gaussian.cov[0] < 0.75 * k.gaussian.cov[0],
                    "{version:?}: the second observation narrows the landmark: {:?} vs {:?}",
                    l.gaussian.cov,
                    k.gaussian.cov
                );
            }
        }
    }

    #[test]
    fn one_landmark_explains_at_most_one_observation_of_a_record() {
        for version in [FastSlamVersion::V1, FastSlamVersion::V2] {
            let mut f = filter_with_offsets(version, Association::Unknown, &[0.0; 4]);
            // Both observations gate with the landmark at (2, 0); the second one is too close
            // to it to start a landmark: it is ambiguous.
            f.step(&record(&[[2.0, 0.0], [2.05, 0.01]])).unwrap();
            for p in f.particles() {
                assert_eq!(p.map.len(), 1);
                assert_eq!(p.map.get(0).unwrap().hits, 6);
            }
            assert_eq!(f.stats().ignored_observations, 4);
            // Two distinct new landmarks in one record, and two sightings of one new landmark.
            let mut f = filter_with_offsets(version, Association::Unknown, &[0.0; 4]);
            f.step(&record(&[[5.0, 1.0], [5.0, -1.0], [5.01, -1.0]]))
                .unwrap();
            for p in f.particles() {
                assert_eq!(p.map.len(), 3, "{:?}", p.map);
            }
        }
    }

    /// [`filter_with_offsets`] with range noise 0.05 m, a given minimum separation and
    /// extra landmarks (x, y, hits) in every particle.
    fn filter_with_separation(min_separation: f64, extra: &[(f64, f64, u32)]) -> FastSlam {
        let f = filter_with_offsets(FastSlamVersion::V2, Association::Unknown, &[0.0; 4]);
        let mut snap = f.snapshot();
        snap.config.sensor_noise.range = 0.05;
        snap.config.association_params.min_separation = min_separation;
        for p in &mut snap.particles {
            for &(x, y, hits) in extra {
                p.map.push(Landmark {
                    gaussian: LandmarkGaussian {
                        mean: [x, y, 0.0],
                        cov: [0.01, 0.0, 0.0, 0.01, 0.0, 0.0],
                    },
                    id: None,
                    existence: 5.0,
                    hits,
                });
            }
        }
        let ekf = crate::ekf::EkfUpdater::new(snap.config.landmark_kind, &snap.config.sensor_noise);
        FastSlam::from_snapshot(snap, Arc::new(ekf)).unwrap()
    }

    #[test]
    fn no_landmark_starts_within_the_minimum_separation() {
        // An observation 0.43 m beyond the landmark at (2, 0): squared Mahalanobis distance
        // 0.43² / (0.01 + 0.05²) = 14.8, past the new-landmark threshold (13.8).
        let z = [2.43, 0.0];
        let mut f = filter_with_separation(0.0, &[]);
        f.step(&record(&[z])).unwrap();
        assert!(f.particles().iter().all(|p| p.map.len() == 2));
        let mut f = filter_with_separation(0.45, &[]);
        f.step(&record(&[z])).unwrap();
        assert!(f.particles().iter().all(|p| p.map.len() == 1));
        assert_eq!(f.stats().landmarks_created, 0);
    }

    #[test]
    fn landmarks_closer_than_the_minimum_separation_merge() {
        // A second landmark 0.3 m from the first (hits 5), observed more often (9 hits):
        // observing the first one merges it into the second.
        let mut f = filter_with_separation(0.45, &[(2.0, 0.3, 9)]);
        f.step(&record(&[[2.0, 0.0]])).unwrap();
        for p in f.particles() {
            assert_eq!(p.map.len(), 1, "{:?}", p.map);
            let (_, l) = p.map.iter().next().unwrap();
            assert_eq!(l.gaussian.mean[..2], [2.0, 0.3]);
            assert_eq!(l.hits, 9 + 6);
        }
        assert_eq!(f.stats().landmarks_merged, 4);
        // 0.5 m apart: both stay.
        let mut f = filter_with_separation(0.45, &[(2.0, 0.5, 9)]);
        f.step(&record(&[[2.0, 0.0]])).unwrap();
        assert!(f.particles().iter().all(|p| p.map.len() == 2));
        assert_eq!(f.stats().landmarks_merged, 0);
    }

    #[test]
    fn tentative_landmarks_are_not_reported_until_confirmed() {
        let mut f = filter_with_offsets(FastSlamVersion::V2, Association::Unknown, &[0.0; 4]);
        let far = [6.0, 1.0];
        f.step(&record(&[far])).unwrap();
        assert_eq!(f.particles()[0].map.len(), 2);
        assert_eq!(f.estimate().landmarks.len(), 1, "the new one is tentative");
        for k in 1..3 {
            let mut rec = record(&[far]);
            rec.seq = k;
            rec.t = 1.0 + k as f64;
            f.step(&rec).unwrap();
        }
        assert_eq!(
            f.estimate().landmarks.len(),
            2,
            "confirmed after 3 sightings"
        );
    }

    #[test]
    fn a_degenerate_proposal_falls_back_to_the_motion_model() {
        let f = filter_with_offsets(FastSlamVersion::V2, Association::Known, &[0.0]);
        let cfg = f.config().clone();
        let obs = [Obs {
            z: [2.0, 0.0, 0.0],
            id: Some(7),
            slot: Some(0),
            clutter: -10.0,
        }];
        let ctx = StepCtx {
            cfg: &cfg,
            updater: f.updater().as_ref(),
            inc: Pose2::default(),
            scale_walk: None,
            var: [0.0; 3],
            std: [0.0; 3],
            obs: &obs,
            sightings: &[],
            others: OtherRobots {
                before: &[],
                after: &[],
                robot: 0,
            },
            streams: StepStreams::new(0, 0),
            known_len: 1,
            gate: 9.0,
            new_landmark: 16.0,
            defer: true,
        };
        let q = [RangeBearingModel::noise(
            &cfg.sensor_noise,
            &[1.0, 0.0, 0.0],
        )];
        let part = &f.particles()[0];
        let mut acts = [Action::Update(0)];
        let mut rng = stream(0, 0, 0);
        let mut propose_with = |cov: &Matrix3<f64>| {
            propose::<2, RangeBearingModel>(
                &ctx,
                &q,
                &part.map,
                0,
                &Pose2::default(),
                cov,
                &mut acts,
                &[0.0],
                &mut rng,
            )
        };
        // An indefinite pose covariance: no Cholesky factor, so no proposal (never a
        // noise-free sample).
        let bad = Matrix3::from_diagonal(&Vector3::new(-1.0, 0.01, 0.01));
        assert!(propose_with(&bad).is_none());
        let ok = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.001));
        assert!(propose_with(&ok).is_some());
        // A zero covariance is a point proposal: the mean itself.
        let (pose, _) = propose_with(&Matrix3::zeros()).unwrap();
        assert_eq!(pose, Pose2::default());
    }
}
