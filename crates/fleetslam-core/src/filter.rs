//! The multi-robot, shared-map FastSLAM filter.
//!
//! Each [`Particle`] holds the pose of every robot of the run and one [`LandmarkMap`]. A
//! record of robot `r` is applied to every particle:
//!
//! 1. **Pose.** FastSLAM 1.0 samples robot `r`'s new pose from the motion model. FastSLAM 2.0
//!    (Montemerlo et al. 2003) first refines the motion prediction `N(x̂, R)` with each
//!    associated observation, as a Kalman update of the pose with `S = Hₓ P Hₓᵀ + H_m Σ H_mᵀ + Q`,
//!    and samples from the result. The other robots' poses are untouched.
//! 2. **Association.** By id, or (unknown ids) per particle by maximum likelihood among the
//!    landmarks within the Mahalanobis `gate`; beyond `new_landmark` from all of them the
//!    observation starts a new landmark, and in between it is ignored as ambiguous.
//! 3. **Landmarks.** Associated landmarks are updated by the run's [`LandmarkUpdater`], one
//!    batch per observation across the particles of a work item; new ones are initialised by
//!    it. Innovations beyond the `outlier` distance leave the landmark alone.
//! 4. **Weight.** The particle's log-weight gains the log-likelihood of each observation (the
//!    updater's in 1.0; the proposal's marginal in 2.0, which includes the motion noise), with
//!    outliers floored at the outlier boundary, and of each sighting of another robot given the
//!    two robots' poses in that particle. Over robots these sums are the product of the paper.
//! 5. **Existence.** With unknown association, landmarks in view but not observed lose
//!    existence log-odds and are removed below zero (spurious landmarks).
//! 6. **Resampling.** Systematic, when the effective sample size falls below a fraction of N.
//!
//! Particles are processed in parallel with rayon, in work items of `batch_size` particles.
//! Every random draw comes from a stream keyed by (seed, step, particle), so the results are
//! bit-identical for any number of threads.

use crate::config::{Association, ConfigError, FastSlamVersion, FilterConfig};
use crate::log::Record;
use crate::map::{Landmark, LandmarkMap};
use crate::motion::{Motion, covariance_in_world};
use crate::pose::{Pose2, PoseGaussian, weighted_mean_pose, wrap_angle};
use crate::resample::{normalize_log_weights, systematic};
use crate::rng::{LANE_ADD_ROBOT, LANE_RESAMPLE, stream};
use crate::sensor::{LandmarkKind, point3_predict, range_bearing_inverse, range_bearing_predict};
use crate::updater::{LandmarkGaussian, LandmarkUpdater, UpdateInput, UpdateOutput};
use nalgebra::{Matrix3, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Instant;

const LN_2PI: f64 = 1.837_877_066_409_345_3;

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

/// One hypothesis: every robot's pose and one shared landmark map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Particle {
    /// Pose of each robot, in the order robots were added.
    pub poses: Vec<Pose2>,
    pub map: LandmarkMap,
    /// Normalised log-weight.
    pub log_w: f64,
}

/// A robot of the run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotState {
    pub id: String,
    /// Time of its latest record (or its start).
    pub last_t: f64,
    /// Number of records applied.
    pub records: u64,
}

/// Counters over the life of the filter.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct FilterStats {
    pub steps: u64,
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
}

impl FilterStats {
    fn add(mut self, o: FilterStats) -> FilterStats {
        self.landmark_updates += o.landmark_updates;
        self.update_nanos += o.update_nanos;
        self.landmarks_created += o.landmarks_created;
        self.landmarks_removed += o.landmarks_removed;
        self.outliers += o.outliers;
        self.ignored_observations += o.ignored_observations;
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
}

/// A landmark of the best particle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LandmarkEstimate {
    pub slot: usize,
    pub id: Option<u32>,
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

/// Everything needed to continue a filter bit for bit: the random state is (seed, step).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Snapshot {
    pub config: FilterConfig,
    pub robots: Vec<RobotState>,
    pub particles: Vec<Particle>,
    pub known_slots: BTreeMap<u32, usize>,
    pub step: u64,
    pub ess: f64,
    pub stats: FilterStats,
}

/// The filter.
#[derive(Debug, Clone)]
pub struct FastSlam {
    config: FilterConfig,
    updater: Arc<dyn LandmarkUpdater>,
    robots: Vec<RobotState>,
    robot_index: HashMap<String, usize>,
    particles: Vec<Particle>,
    known_slots: BTreeMap<u32, usize>,
    step: u64,
    ess: f64,
    stats: FilterStats,
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
}

/// Read-only inputs of one step, shared by the work items.
struct StepCtx<'a> {
    cfg: &'a FilterConfig,
    updater: &'a dyn LandmarkUpdater,
    robot: usize,
    inc: Pose2,
    /// Variances of the (longitudinal, lateral, heading) increment noise.
    var: [f64; 3],
    /// Their square roots.
    std: [f64; 3],
    obs: &'a [Obs],
    sightings: &'a [(usize, [f64; 2])],
    step: u64,
    known_len: usize,
    /// Log-likelihood given to an observation that starts a new landmark.
    ll_new: f64,
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
                poses: Vec::new(),
                map: LandmarkMap::new(),
                log_w: -(n as f64).ln(),
            })
            .collect();
        Ok(Self {
            config,
            updater,
            robots: Vec::new(),
            robot_index: HashMap::new(),
            particles,
            known_slots: BTreeMap::new(),
            step: 0,
            ess: n as f64,
            stats: FilterStats::default(),
        })
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
        self.particles
            .par_iter_mut()
            .enumerate()
            .for_each(|(i, p)| {
                let pose = match &chol {
                    None => mean,
                    Some(l) => {
                        let mut rng = stream(seed, step, LANE_ADD_ROBOT + i as u64);
                        let e = l * normal3(&mut rng);
                        Pose2::new(mean.x + e[0], mean.y + e[1], wrap_angle(mean.theta + e[2]))
                    }
                };
                p.poses.push(pose);
            });
        Ok(self.finish_add_robot(id, t0))
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
        self.particles
            .par_iter_mut()
            .enumerate()
            .for_each(|(i, p)| {
                let u: f64 = stream(seed, step, LANE_ADD_ROBOT + i as u64).random();
                let k = cum.partition_point(|&c| c < u).min(samples.len() - 1);
                p.poses.push(samples[k]);
            });
        Ok(self.finish_add_robot(id, t0))
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

    fn finish_add_robot(&mut self, id: &str, t0: f64) -> usize {
        let idx = self.robots.len();
        self.robots.push(RobotState {
            id: id.to_string(),
            last_t: t0,
            records: 0,
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

        // Resolve known ids to slots (new ids get the next slot in every particle).
        let mut known_len = self.known_slots.len();
        let mut new_ids = Vec::new();
        let obs: Vec<Obs> = rec
            .landmarks
            .iter()
            .map(|o| {
                let mut z = [0.0; 3];
                z[..o.z.len()].copy_from_slice(&o.z);
                let slot = match (cfg.association, o.id) {
                    (Association::Known, Some(id)) => Some(match self.known_slots.get(&id) {
                        Some(&s) => s,
                        None => {
                            let s = known_len;
                            known_len += 1;
                            new_ids.push((id, s));
                            s
                        }
                    }),
                    _ => None,
                };
                // Landmarks keep the observations' ids only when association is by id.
                let id = (cfg.association == Association::Known)
                    .then_some(o.id)
                    .flatten();
                Obs { z, id, slot }
            })
            .filter(|o| cfg.association == Association::Unknown || o.slot.is_some())
            .collect();
        let ignored_no_id = rec.landmarks.len() - obs.len();

        let mut sightings = Vec::new();
        let mut unmatched = 0;
        for s in &rec.robots {
            match self.robot_index(&s.robot) {
                Some(j) => sightings.push((j, [s.z[0], s.z[1]])),
                None => unmatched += 1,
            }
        }

        let q_det = match cfg.landmark_kind {
            LandmarkKind::RangeBearing2d => cfg.sensor_noise.q2().determinant(),
            LandmarkKind::Point3d => cfg.sensor_noise.q3().determinant(),
        };
        let dim = cfg.landmark_kind.dim() as f64;
        let ctx = StepCtx {
            cfg,
            updater: self.updater.as_ref(),
            robot: r,
            inc,
            var,
            std: var.map(f64::sqrt),
            obs: &obs,
            sightings: &sightings,
            step: self.step,
            known_len,
            ll_new: -0.5 * cfg.association_params.new_landmark - 0.5 * (dim * LN_2PI + q_det.ln()),
        };
        let best_before = self.best_index();
        let slots_before = self.particles[best_before].map.len();
        let batch = cfg.batch_size;
        let step_stats = self
            .particles
            .par_chunks_mut(batch)
            .enumerate()
            .map(|(c, chunk)| process_chunk(&ctx, c * batch, chunk))
            .reduce(FilterStats::default, FilterStats::add);

        for (id, s) in new_ids {
            self.known_slots.insert(id, s);
        }
        self.robots[r].last_t = rec.t;
        self.robots[r].records += 1;
        self.stats = self.stats.add(step_stats);
        self.stats.ignored_observations += ignored_no_id as u64;
        self.stats.unmatched_sightings += unmatched;
        self.stats.steps += 1;

        let mut log_w: Vec<f64> = self.particles.iter().map(|p| p.log_w).collect();
        self.ess = normalize_log_weights(&mut log_w);
        for (p, w) in self.particles.iter_mut().zip(&log_w) {
            p.log_w = *w;
        }
        let best = self.best_index();
        let (added, removed) = if best == best_before {
            let now = self.particles[best].map.len();
            (
                now.saturating_sub(slots_before),
                slots_before.saturating_sub(now),
            )
        } else {
            (0, 0)
        };
        let n = self.particles.len() as f64;
        let resampled = self.ess < self.config.resample_threshold * n;
        if resampled {
            self.resample(&log_w);
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

    fn resample(&mut self, log_w: &[f64]) {
        let mut rng = stream(self.config.seed, self.step, LANE_RESAMPLE);
        let idx = systematic(log_w, &mut rng);
        let n = self.particles.len();
        let uniform = -(n as f64).ln();
        let old = std::mem::take(&mut self.particles);
        self.particles = idx
            .into_iter()
            .map(|i| Particle {
                log_w: uniform,
                ..old[i].clone()
            })
            .collect();
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
        weighted_mean_pose(
            self.particles
                .iter()
                .map(|p| (&p.poses[robot], p.log_w.exp())),
        )
    }

    /// Up to `max` particles' poses of one robot, evenly spaced over the particle set, with
    /// their normalised weights.
    pub fn particle_sample(&self, robot: usize, max: usize) -> Vec<(Pose2, f64)> {
        let n = self.particles.len();
        let stride = n.div_ceil(max.max(1)).max(1);
        self.particles
            .iter()
            .step_by(stride)
            .map(|p| (p.poses[robot], p.log_w.exp()))
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
                for p in &self.particles {
                    let w = p.log_w.exp();
                    let q = &p.poses[r];
                    let d = [q.x - mean.x, q.y - mean.y, wrap_angle(q.theta - mean.theta)];
                    for i in 0..3 {
                        for j in 0..3 {
                            cov[i][j] += w * d[i] * d[j];
                        }
                    }
                }
                RobotEstimate {
                    id: st.id.clone(),
                    best: self.particles[best].poses[r],
                    mean,
                    cov,
                    last_t: st.last_t,
                    records: st.records,
                }
            })
            .collect();
        let landmarks = self.particles[best]
            .map
            .iter()
            .map(|(slot, l)| LandmarkEstimate {
                slot,
                id: l.id,
                gaussian: l.gaussian,
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

    /// A snapshot from which [`FastSlam::from_snapshot`] continues bit for bit.
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            config: self.config.clone(),
            robots: self.robots.clone(),
            particles: self.particles.clone(),
            known_slots: self.known_slots.clone(),
            step: self.step,
            ess: self.ess,
            stats: self.stats,
        }
    }

    /// Restores a filter from a snapshot, with the updater the run uses.
    pub fn from_snapshot(
        s: Snapshot,
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
        let robot_index = s
            .robots
            .iter()
            .enumerate()
            .map(|(i, r)| (r.id.clone(), i))
            .collect();
        Ok(Self {
            config: s.config,
            updater,
            robots: s.robots,
            robot_index,
            particles: s.particles,
            known_slots: s.known_slots,
            step: s.step,
            ess: s.ess,
            stats: s.stats,
        })
    }
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

#[inline]
fn normal3(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
    )
}

/// Lower Cholesky factor of a symmetric positive semi-definite matrix (with a tiny jitter
/// for semi-definite ones).
fn cholesky_psd(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    if let Some(c) = m.cholesky() {
        return Some(c.l());
    }
    let jitter = 1e-12 * (1.0 + m.trace().abs());
    (m + Matrix3::identity() * jitter).cholesky().map(|c| c.l())
}

/// Measurement prediction of a landmark from a pose, in the run's kind, as 3-vectors (the
/// third component unused in 2D): (ẑ, H_m, Hₓ).
#[inline]
fn predict(
    kind: LandmarkKind,
    pose: &Pose2,
    m: &[f64; 3],
) -> Option<(Vector3<f64>, Matrix3<f64>, Matrix3<f64>)> {
    match kind {
        LandmarkKind::RangeBearing2d => {
            let (z, hm, hx) = range_bearing_predict(pose, m[0], m[1])?;
            let mut hm3 = Matrix3::zeros();
            hm3.fixed_view_mut::<2, 2>(0, 0).copy_from(&hm);
            let mut hx3 = Matrix3::zeros();
            hx3.fixed_view_mut::<2, 3>(0, 0).copy_from(&hx);
            Some((Vector3::new(z[0], z[1], 0.0), hm3, hx3))
        }
        LandmarkKind::Point3d => Some(point3_predict(pose, m)),
    }
}

/// Innovation, with the bearing wrapped in 2D.
#[inline]
fn innovation(kind: LandmarkKind, z: &[f64; 3], zhat: &Vector3<f64>) -> Vector3<f64> {
    match kind {
        LandmarkKind::RangeBearing2d => {
            Vector3::new(z[0] - zhat[0], wrap_angle(z[1] - zhat[1]), 0.0)
        }
        LandmarkKind::Point3d => Vector3::new(z[0] - zhat[0], z[1] - zhat[1], z[2] - zhat[2]),
    }
}

/// Inverse, log-determinant of an innovation covariance of the run's dimension, embedded in
/// 3x3 (the unused block is zero in 2D).
#[inline]
fn inv_logdet(kind: LandmarkKind, s: &Matrix3<f64>) -> Option<(Matrix3<f64>, f64)> {
    match kind {
        LandmarkKind::RangeBearing2d => {
            let det = s[(0, 0)] * s[(1, 1)] - s[(0, 1)] * s[(1, 0)];
            if !(det > 0.0 && det.is_finite()) {
                return None;
            }
            let mut inv = Matrix3::zeros();
            inv[(0, 0)] = s[(1, 1)] / det;
            inv[(0, 1)] = -s[(0, 1)] / det;
            inv[(1, 0)] = -s[(1, 0)] / det;
            inv[(1, 1)] = s[(0, 0)] / det;
            Some((inv, det.ln()))
        }
        LandmarkKind::Point3d => {
            let c = s.cholesky()?;
            let det = c.determinant();
            (det > 0.0 && det.is_finite()).then(|| (c.inverse(), det.ln()))
        }
    }
}

fn q_matrix(cfg: &FilterConfig) -> Matrix3<f64> {
    match cfg.landmark_kind {
        LandmarkKind::RangeBearing2d => {
            let mut q = Matrix3::zeros();
            q.fixed_view_mut::<2, 2>(0, 0)
                .copy_from(&cfg.sensor_noise.q2());
            q
        }
        LandmarkKind::Point3d => cfg.sensor_noise.q3(),
    }
}

/// Unknown association: the most likely landmark within the gate, `New` beyond
/// `new_landmark` from every landmark, `Ignore` in between. `p` is the pose covariance
/// (zero in FastSLAM 1.0).
fn associate(
    cfg: &FilterConfig,
    q: &Matrix3<f64>,
    map: &LandmarkMap,
    pose: &Pose2,
    p: &Matrix3<f64>,
    z: &[f64; 3],
) -> Action {
    let kind = cfg.landmark_kind;
    let params = &cfg.association_params;
    // The observation's world point, for a cheap and conservative pre-check: the squared
    // Mahalanobis distance is at least d² / trace(S_world).
    let (wx, wy, q_world) = match kind {
        LandmarkKind::RangeBearing2d => {
            let (x, y) = range_bearing_inverse(pose, z[0], z[1]);
            let n = &cfg.sensor_noise;
            (x, y, n.range * n.range + (z[0] * n.bearing).powi(2))
        }
        LandmarkKind::Point3d => {
            let w = crate::sensor::point3_inverse(pose, z);
            (w[0], w[1], q.trace())
        }
    };
    let pose_term = p[(0, 0)] + p[(1, 1)] + p[(2, 2)] * (z[0] * z[0] + z[1] * z[1]);
    let mut best: Option<(usize, f64)> = None;
    let mut nearest_m2 = f64::INFINITY;
    for (slot, lm) in map.iter() {
        let g = &lm.gaussian;
        let d2 = (g.mean[0] - wx).powi(2) + (g.mean[1] - wy).powi(2);
        let bound = (g.cov[0] + g.cov[3] + q_world + pose_term) * 1.5;
        if d2 > params.new_landmark * bound {
            continue;
        }
        let Some((zhat, hm, hx)) = predict(kind, pose, &g.mean) else {
            continue;
        };
        let s = hm * g.cov3() * hm.transpose() + q + hx * p * hx.transpose();
        let Some((s_inv, logdet)) = inv_logdet(kind, &s) else {
            continue;
        };
        let nu = innovation(kind, z, &zhat);
        let m2 = nu.dot(&(s_inv * nu));
        nearest_m2 = nearest_m2.min(m2);
        if m2 < params.gate {
            let ll = -0.5 * m2 - 0.5 * logdet;
            if best.is_none_or(|(_, b)| ll > b) {
                best = Some((slot, ll));
            }
        }
    }
    match best {
        Some((slot, _)) => Action::Update(slot),
        None if nearest_m2 > params.new_landmark => Action::New(None),
        None => Action::Ignore,
    }
}

/// Flat-tailed log-likelihood of an outlier: the Gaussian's value on the outlier boundary.
#[inline]
fn outlier_ll(ll: f64, m2: f64, bound: f64) -> f64 {
    if ll.is_finite() && m2.is_finite() {
        ll + 0.5 * (m2 - bound)
    } else {
        -0.5 * bound - 20.0
    }
}

/// One work item: `chunk` holds particles `base..base + chunk.len()`.
fn process_chunk(ctx: &StepCtx<'_>, base: usize, chunk: &mut [Particle]) -> FilterStats {
    let cfg = ctx.cfg;
    let kind = cfg.landmark_kind;
    let r = ctx.robot;
    let n = chunk.len();
    let nobs = ctx.obs.len();
    let q = q_matrix(cfg);
    let outlier = cfg.association_params.outlier;
    let mut stats = FilterStats::default();
    let mut rngs: Vec<ChaCha8Rng> = (0..n)
        .map(|i| stream(cfg.seed, ctx.step, (base + i) as u64))
        .collect();
    if ctx.known_len > 0 {
        for p in chunk.iter_mut() {
            p.map.ensure_slots(ctx.known_len);
        }
    }
    // actions[i * nobs + j]: what particle i does with observation j.
    let mut actions = vec![Action::Ignore; n * nobs];
    let use_v2 = cfg.version == FastSlamVersion::V2 && nobs > 0;

    // 1. Poses (and, in 2.0, association and weights from the proposal).
    for (i, p) in chunk.iter_mut().enumerate() {
        let prev = p.poses[r];
        let rng = &mut rngs[i];
        if !use_v2 {
            let e = Pose2::new(
                ctx.std[0] * rng.sample::<f64, _>(StandardNormal),
                ctx.std[1] * rng.sample::<f64, _>(StandardNormal),
                ctx.std[2] * rng.sample::<f64, _>(StandardNormal),
            );
            let noisy = Pose2::new(ctx.inc.x + e.x, ctx.inc.y + e.y, ctx.inc.theta + e.theta);
            p.poses[r] = prev.compose(&noisy);
            continue;
        }
        let mean0 = prev.compose(&ctx.inc);
        let mut mu = Vector3::new(mean0.x, mean0.y, mean0.theta);
        let mut pc = covariance_in_world(&prev, &ctx.var);
        for (j, o) in ctx.obs.iter().enumerate() {
            let pose = Pose2::new(mu[0], mu[1], mu[2]);
            let action = match o.slot {
                Some(s) => match p.map.get(s) {
                    Some(_) => Action::Update(s),
                    None => Action::New(Some(s)),
                },
                None => associate(cfg, &q, &p.map, &pose, &pc, &o.z),
            };
            let slot = match action {
                Action::Update(s) => s,
                Action::New(_) => {
                    p.log_w += ctx.ll_new;
                    actions[i * nobs + j] = action;
                    continue;
                }
                _ => {
                    actions[i * nobs + j] = action;
                    continue;
                }
            };
            let Some(lm) = p.map.get(slot) else { continue };
            let Some((zhat, hm, hx)) = predict(kind, &pose, &lm.gaussian.mean) else {
                actions[i * nobs + j] = Action::Outlier;
                p.log_w += outlier_ll(f64::NAN, f64::NAN, outlier.unwrap_or(25.0));
                continue;
            };
            let qj = hm * lm.gaussian.cov3() * hm.transpose() + q;
            let pht = pc * hx.transpose();
            let s = hx * pht + qj;
            let Some((s_inv, logdet)) = inv_logdet(kind, &s) else {
                actions[i * nobs + j] = Action::Outlier;
                p.log_w += outlier_ll(f64::NAN, f64::NAN, outlier.unwrap_or(25.0));
                continue;
            };
            let nu = innovation(kind, &o.z, &zhat);
            let m2 = nu.dot(&(s_inv * nu));
            let dim = kind.dim() as f64;
            let ll = -0.5 * m2 - 0.5 * (dim * LN_2PI + logdet);
            if let Some(bound) = outlier
                && m2 > bound
            {
                actions[i * nobs + j] = Action::Outlier;
                p.log_w += outlier_ll(ll, m2, bound);
                continue;
            }
            actions[i * nobs + j] = Action::Update(slot);
            p.log_w += ll;
            let k = pht * s_inv;
            mu += k * nu;
            mu[2] = wrap_angle(mu[2]);
            let ikh = Matrix3::identity() - k * hx;
            pc = ikh * pc * ikh.transpose() + k * qj * k.transpose();
            pc = 0.5 * (pc + pc.transpose());
        }
        let e = match cholesky_psd(&pc) {
            Some(l) => l * normal3(rng),
            None => Vector3::zeros(),
        };
        p.poses[r] = Pose2::new(mu[0] + e[0], mu[1] + e[1], wrap_angle(mu[2] + e[2]));
    }

    // 2. Landmarks, one updater batch per observation.
    let mut inputs: Vec<UpdateInput> = Vec::with_capacity(n);
    let mut outputs: Vec<UpdateOutput> = Vec::with_capacity(n);
    let mut who: Vec<(usize, usize)> = Vec::with_capacity(n);
    let mut observed: Vec<Vec<usize>> = vec![
        Vec::new();
        if cfg.association == Association::Unknown {
            n
        } else {
            0
        }
    ];
    for (j, o) in ctx.obs.iter().enumerate() {
        inputs.clear();
        who.clear();
        for (i, p) in chunk.iter_mut().enumerate() {
            let pose = p.poses[r];
            let mut action = if use_v2 {
                actions[i * nobs + j]
            } else {
                match o.slot {
                    Some(s) => match p.map.get(s) {
                        Some(_) => Action::Update(s),
                        None => Action::New(Some(s)),
                    },
                    None => associate(cfg, &q, &p.map, &pose, &Matrix3::zeros(), &o.z),
                }
            };
            // A known id seen twice in one record: the second sighting updates the landmark
            // the first one created.
            if let Action::New(Some(s)) = action
                && p.map.get(s).is_some()
            {
                action = Action::Update(s);
                if use_v2 {
                    // The proposal counted it as new; it is an update now.
                    p.log_w -= ctx.ll_new;
                }
            }
            match action {
                Action::Update(s) => {
                    if let Some(lm) = p.map.get(s) {
                        inputs.push(UpdateInput {
                            prior: lm.gaussian,
                            pose,
                            z: o.z,
                        });
                        who.push((i, s));
                    }
                }
                Action::New(slot) => {
                    let g = ctx.updater.initialize(&pose, &o.z);
                    let lm = Landmark {
                        gaussian: g,
                        id: o.id,
                        existence: cfg.association_params.existence_hit,
                        hits: 1,
                    };
                    let s = match slot {
                        Some(s) => {
                            p.map.set(s, lm);
                            s
                        }
                        None => {
                            if !use_v2 {
                                p.log_w += ctx.ll_new;
                            }
                            p.map.push(lm)
                        }
                    };
                    if !observed.is_empty() {
                        observed[i].push(s);
                    }
                    stats.landmarks_created += 1;
                }
                Action::Ignore => stats.ignored_observations += 1,
                Action::Outlier => stats.outliers += 1,
            }
        }
        if inputs.is_empty() {
            continue;
        }
        outputs.clear();
        outputs.resize(inputs.len(), UpdateOutput::default());
        let t0 = Instant::now();
        ctx.updater.update_batch(&inputs, &mut outputs);
        stats.update_nanos += t0.elapsed().as_nanos() as u64;
        stats.landmark_updates += inputs.len() as u64;
        for (&(i, s), out) in who.iter().zip(&outputs) {
            let p = &mut chunk[i];
            if !use_v2 {
                if let Some(bound) = outlier
                    && (out.mahalanobis2.is_nan() || out.mahalanobis2 > bound)
                {
                    p.log_w += outlier_ll(out.log_likelihood, out.mahalanobis2, bound);
                    stats.outliers += 1;
                    continue;
                }
                p.log_w += if out.log_likelihood.is_finite() {
                    out.log_likelihood
                } else {
                    outlier_ll(f64::NAN, f64::NAN, outlier.unwrap_or(25.0))
                };
            }
            if !out.posterior.is_finite() {
                continue;
            }
            let Some(old) = p.map.get(s).copied() else {
                continue;
            };
            let a = &cfg.association_params;
            p.map.set(
                s,
                Landmark {
                    gaussian: out.posterior,
                    existence: (old.existence + a.existence_hit).min(a.existence_max),
                    hits: old.hits + 1,
                    ..old
                },
            );
            if !observed.is_empty() {
                observed[i].push(s);
            }
        }
    }

    // 3. Sightings of other robots.
    if !ctx.sightings.is_empty() {
        let qs = cfg.sighting_noise.q2();
        let qs_inv = qs.try_inverse().unwrap_or_else(nalgebra::Matrix2::identity);
        let logdet = qs.determinant().ln();
        let bound = outlier.unwrap_or(f64::INFINITY);
        for p in chunk.iter_mut() {
            for &(other, z) in ctx.sightings {
                let q = p.poses[other];
                let Some((zhat, _, _)) = range_bearing_predict(&p.poses[r], q.x, q.y) else {
                    continue;
                };
                let nu = nalgebra::Vector2::new(z[0] - zhat[0], wrap_angle(z[1] - zhat[1]));
                let m2 = nu.dot(&(qs_inv * nu));
                let ll = -0.5 * m2 - LN_2PI - 0.5 * logdet;
                p.log_w += if m2 > bound {
                    outlier_ll(ll, m2, bound)
                } else {
                    ll
                };
            }
        }
    }

    // 4. Existence of landmarks in view (unknown association).
    if let (Some(range), false) = (&cfg.sensor_range, observed.is_empty() || nobs == 0) {
        let a = &cfg.association_params;
        for (i, p) in chunk.iter_mut().enumerate() {
            let pose = p.poses[r];
            let seen = &observed[i];
            let missed: Vec<(usize, Landmark)> = p
                .map
                .iter()
                .filter(|(s, l)| {
                    if seen.contains(s) {
                        return false;
                    }
                    let dx = l.gaussian.mean[0] - pose.x;
                    let dy = l.gaussian.mean[1] - pose.y;
                    let d = dx.hypot(dy);
                    d < range.max_range
                        && wrap_angle(dy.atan2(dx) - pose.theta).abs() < 0.5 * range.fov
                })
                .map(|(s, l)| (s, *l))
                .collect();
            for (s, l) in missed {
                let e = l.existence - a.existence_miss;
                if e < 0.0 {
                    p.map.remove(s);
                    stats.landmarks_removed += 1;
                } else {
                    p.map.set(s, Landmark { existence: e, ..l });
                }
            }
        }
    }
    for p in chunk.iter_mut() {
        if !p.log_w.is_finite() {
            p.log_w = f64::MIN;
        }
    }
    stats
}
