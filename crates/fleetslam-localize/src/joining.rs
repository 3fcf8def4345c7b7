//! Late joiners: robots that join a running shared-map FastSLAM at an unknown pose, and
//! localization in a stored map.
//!
//! [`LateJoinSlam`] owns the run's [`FastSlam`] and one [`Localizer`] per robot registered
//! without a start pose. A record of such a robot goes to its localizer, which runs Monte
//! Carlo localization against the run's current best map (the landmarks of the filter's
//! best particle, taken afresh for every record). Each robot goes through three phases
//! ([`Phase`]):
//!
//! 1. **Localizing**: the localizer has not passed its convergence test.
//! 2. **Converged**: the test passed at the latest observing update (the start of a streak);
//!    the posterior of that update is kept as the join candidate and the robot's records
//!    from then on are buffered. If the test fails before the streak is long enough
//!    (`hold_updates`), the candidate and the buffer are dropped (the localizer has used
//!    those records) and the robot is Localizing again.
//! 3. **Mapping**: the streak reached `hold_updates`. The robot is added to every SLAM
//!    particle with [`FastSlam::add_robot_from_samples`] (each particle draws its pose from
//!    the candidate posterior, at the candidate's time), the buffered records are applied
//!    to the filter in order, and from then on the robot's records go to the filter like
//!    any other robot's.
//!
//! While a robot localizes, its records' sightings of other robots are not used, and the
//! other robots' sightings of it count as unmatched in the filter (as for any robot the
//! filter does not hold yet).
//!
//! Everything is deterministic: windows are decided from record times, every draw comes
//! from a counter-based stream (the localizer's seed is derived from the run's seed and the
//! robot's id), and the whole state serialises ([`LateJoinSnapshot`]) and continues bit for
//! bit after a JSON round trip.
//!
//! [`MapLocalization`] localizes robots in a fixed map (a finished run's final map) without
//! changing it.

use crate::config::{LocalizeConfig, Models};
use crate::error::LocalizeError;
use crate::localizer::{Localizer, LocalizerStatus, UpdateReport};
use crate::map::LandmarkSet;
use fleetslam_core::config::FilterConfig;
use fleetslam_core::filter::{FastSlam, Snapshot, StepReport};
use fleetslam_core::log::Record;
use fleetslam_core::pose::{Pose2, PoseGaussian};
use fleetslam_core::updater::LandmarkUpdater;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Where a robot stands in a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Being localized in the map; its records do not change the map.
    Localizing,
    /// Localized at the latest update; waiting for the convergence streak to complete.
    Converged,
    /// Part of the SLAM filter: it maps like the robots with known starts.
    Mapping,
}

impl Phase {
    pub fn as_str(self) -> &'static str {
        match self {
            Phase::Localizing => "localizing",
            Phase::Converged => "converged",
            Phase::Mapping => "mapping",
        }
    }
}

/// The posterior at the start of a convergence streak.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JoinCandidate {
    /// Time of the update [s].
    pub t: f64,
    pub poses: Vec<Pose2>,
    /// Normalised weights.
    pub weights: Vec<f64>,
}

/// A robot that joined at an unknown pose, until it maps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Joiner {
    pub id: String,
    pub phase: Phase,
    pub localizer: Localizer,
    pub candidate: Option<JoinCandidate>,
    /// Records since the candidate, applied to the filter when the robot joins.
    pub buffered: Vec<Record>,
    /// Time at which it entered the filter (the candidate's time).
    pub joined_at: Option<f64>,
}

/// One robot's phase, for the API, the websocket and the dashboard.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotPhase {
    pub id: String,
    pub phase: Phase,
    /// Time it entered the filter: `None` for robots with a known start and robots still
    /// localizing.
    pub joined_at: Option<f64>,
    /// Records buffered while the convergence streak completes.
    pub buffered: usize,
    /// The localizer's state, for robots that joined at an unknown pose (kept after they
    /// map, for its counters).
    pub localization: Option<LocalizerStatus>,
}

/// What one record did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JoinStep {
    /// The robot's phase after the record.
    pub phase: Phase,
    /// The filter's report of the last record it applied (the record itself when the robot
    /// maps; the last buffered record when it has just joined).
    pub slam: Option<StepReport>,
    /// The localizer's update, when the record completed a window.
    pub localization: Option<UpdateReport>,
    /// The robot joined the filter with this record.
    pub joined: bool,
    /// Buffered records applied to the filter when the robot joined.
    pub replayed: usize,
}

/// The serialisable state of a [`LateJoinSlam`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LateJoinSnapshot {
    pub slam: Snapshot,
    pub localize: LocalizeConfig,
    /// Robots that joined at an unknown pose, in order of registration (kept after they map).
    pub joiners: Vec<Joiner>,
}

/// A shared-map FastSLAM run whose robots may join at an unknown pose.
///
/// # Use
///
/// ```
/// use fleetslam_core::config::FilterConfig;
/// use fleetslam_core::log::Record;
/// use fleetslam_core::pose::{Pose2, PoseGaussian};
/// use fleetslam_localize::{LateJoinSlam, LateJoinSnapshot, LocalizeConfig, Phase};
///
/// // Construct from the run's filter configuration and a localization configuration.
/// let mut cfg = FilterConfig::default();
/// cfg.particles = 30;
/// let mut run = LateJoinSlam::new(cfg, LocalizeConfig::default()).unwrap();
/// // Robots with a known start map at once; robots without one are localized first.
/// run.add_robot("1", &PoseGaussian::exact(Pose2::default()), 0.0).unwrap();
/// run.add_unknown_robot("2").unwrap();
/// // Feed every record, of any robot, in the run's deterministic order (time, robot, seq).
/// let rec: Record = serde_json::from_str(
///     r#"{"robot":"2","seq":0,"t":1.0,"landmarks":[{"id":3,"z":[2.0,0.1]}]}"#).unwrap();
/// let step = run.step(&rec).unwrap();
/// assert_eq!(step.phase, Phase::Localizing);
/// // Query phases (and a subsample of localization particles) for the API.
/// assert_eq!(run.phases().len(), 2);
/// assert!(run.localization_particles("2", 100).is_some());
/// // Snapshot (serde) and restore: the restored run continues bit for bit.
/// let json = serde_json::to_string(&run.snapshot()).unwrap();
/// let snap: LateJoinSnapshot = serde_json::from_str(&json).unwrap();
/// let restored = LateJoinSlam::from_snapshot_ekf(snap).unwrap();
/// assert_eq!(restored.snapshot(), run.snapshot());
/// ```
#[derive(Debug, Clone)]
pub struct LateJoinSlam {
    slam: FastSlam,
    localize: LocalizeConfig,
    joiners: Vec<Joiner>,
    /// Robot id -> index into `joiners`.
    joiner_index: BTreeMap<String, usize>,
}

/// The seed of a robot's localizer: the run's seed mixed with a hash of the id (FNV-1a), so
/// that two joiners of one run draw different numbers.
pub fn localizer_seed(run_seed: u64, robot: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in robot.as_bytes() {
        h ^= u64::from(*b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    run_seed ^ h.rotate_left(29) ^ 0x4c4f_4341_4c49_5a45
}

impl LateJoinSlam {
    /// A run with the EKF updater of `filter`'s landmark kind.
    pub fn new(filter: FilterConfig, localize: LocalizeConfig) -> Result<Self, LocalizeError> {
        Self::from_slam(FastSlam::new(filter)?, localize)
    }

    /// Wraps an existing filter (with any updater, and any robots it already has).
    pub fn from_slam(slam: FastSlam, localize: LocalizeConfig) -> Result<Self, LocalizeError> {
        localize.validate().map_err(LocalizeError::Config)?;
        Ok(Self {
            slam,
            localize,
            joiners: Vec::new(),
            joiner_index: BTreeMap::new(),
        })
    }

    /// The SLAM filter (estimates, particles, stats).
    pub fn slam(&self) -> &FastSlam {
        &self.slam
    }

    /// Gives the filter back (its robots are those that map).
    pub fn into_slam(self) -> FastSlam {
        self.slam
    }

    pub fn localize_config(&self) -> &LocalizeConfig {
        &self.localize
    }

    /// Adds a robot with a known start pose: it maps from its first record.
    pub fn add_robot(
        &mut self,
        id: &str,
        start: &PoseGaussian,
        t0: f64,
    ) -> Result<usize, LocalizeError> {
        if self.joiner_index.contains_key(id) {
            return Err(LocalizeError::Robot(format!(
                "robot {id:?} is already part of this run"
            )));
        }
        Ok(self.slam.add_robot(id, start, t0)?)
    }

    /// Registers a robot whose start pose is unknown: it is localized first.
    pub fn add_unknown_robot(&mut self, id: &str) -> Result<(), LocalizeError> {
        if id.is_empty() {
            return Err(LocalizeError::Robot("robot id must not be empty".into()));
        }
        if self.joiner_index.contains_key(id) || self.slam.robot_index(id).is_some() {
            return Err(LocalizeError::Robot(format!(
                "robot {id:?} is already part of this run"
            )));
        }
        let models = Models::from_filter(self.slam.config());
        let seed = localizer_seed(self.slam.config().seed, id);
        let localizer = Localizer::new(models, self.localize.clone(), seed)?;
        self.joiner_index.insert(id.to_string(), self.joiners.len());
        self.joiners.push(Joiner {
            id: id.to_string(),
            phase: Phase::Localizing,
            localizer,
            candidate: None,
            buffered: Vec::new(),
            joined_at: None,
        });
        Ok(())
    }

    /// The phase of a robot; `None` for a robot the run does not know.
    pub fn phase(&self, id: &str) -> Option<Phase> {
        match self.joiner_index.get(id) {
            Some(&j) => Some(self.joiners[j].phase),
            None => self.slam.robot_index(id).map(|_| Phase::Mapping),
        }
    }

    /// Every robot's phase: the filter's robots in their order, then the robots still being
    /// localized in order of registration.
    pub fn phases(&self) -> Vec<RobotPhase> {
        let mut out: Vec<RobotPhase> = self
            .slam
            .robots()
            .iter()
            .map(|r| {
                let j = self.joiner_index.get(&r.id).map(|&j| &self.joiners[j]);
                RobotPhase {
                    id: r.id.clone(),
                    phase: Phase::Mapping,
                    joined_at: j.and_then(|j| j.joined_at),
                    buffered: 0,
                    localization: j.map(|j| j.localizer.status()),
                }
            })
            .collect();
        for j in self.joiners.iter().filter(|j| j.phase != Phase::Mapping) {
            out.push(RobotPhase {
                id: j.id.clone(),
                phase: j.phase,
                joined_at: None,
                buffered: j.buffered.len(),
                localization: Some(j.localizer.status()),
            });
        }
        out
    }

    /// Up to `max` of a joining robot's localization samples with their weights (for the
    /// dashboard); `None` for robots that started at a known pose or are unknown.
    pub fn localization_particles(&self, id: &str, max: usize) -> Option<Vec<(Pose2, f64)>> {
        self.joiner_index
            .get(id)
            .map(|&j| self.joiners[j].localizer.sample(max))
    }

    /// The localizer of a robot that joined at an unknown pose.
    pub fn localizer(&self, id: &str) -> Option<&Localizer> {
        self.joiner_index
            .get(id)
            .map(|&j| &self.joiners[j].localizer)
    }

    /// The run's current best map: the landmarks of the filter's best particle.
    pub fn best_map(&self) -> LandmarkSet {
        LandmarkSet::from_best_particle(&self.slam)
    }

    /// Applies one record: to the filter for a mapping robot, to the localizer for a joining
    /// one (which may make it join). Records must come in the run's deterministic order
    /// ([`fleetslam_core::log::record_order`]). On error nothing changed.
    pub fn step(&mut self, rec: &Record) -> Result<JoinStep, LocalizeError> {
        let Some(&j) = self.joiner_index.get(&rec.robot) else {
            let report = self.slam.step(rec)?;
            return Ok(JoinStep {
                phase: Phase::Mapping,
                slam: Some(report),
                localization: None,
                joined: false,
                replayed: 0,
            });
        };
        if self.joiners[j].phase == Phase::Mapping {
            let report = self.slam.step(rec)?;
            return Ok(JoinStep {
                phase: Phase::Mapping,
                slam: Some(report),
                localization: None,
                joined: false,
                replayed: 0,
            });
        }
        let map = self.best_map();
        let joiner = &mut self.joiners[j];
        let report = joiner.localizer.push(rec, &map)?;
        if joiner.candidate.is_some() {
            joiner.buffered.push(rec.clone());
        }
        let Some(rep) = report else {
            return Ok(JoinStep {
                phase: joiner.phase,
                slam: None,
                localization: None,
                joined: false,
                replayed: 0,
            });
        };
        if rep.observed {
            match joiner.localizer.hold() {
                0 => {
                    joiner.candidate = None;
                    joiner.buffered.clear();
                    joiner.phase = Phase::Localizing;
                }
                1 => {
                    let (poses, weights) = joiner.localizer.posterior();
                    joiner.candidate = Some(JoinCandidate {
                        t: rep.t,
                        poses,
                        weights,
                    });
                    joiner.buffered.clear();
                    joiner.phase = Phase::Converged;
                }
                _ => {}
            }
        }
        if !rep.converged {
            return Ok(JoinStep {
                phase: joiner.phase,
                slam: None,
                localization: Some(rep),
                joined: false,
                replayed: 0,
            });
        }
        // Join: every particle draws the robot's pose from the candidate posterior.
        let cand = joiner
            .candidate
            .take()
            .expect("a converged streak starts with a candidate");
        let buffered = std::mem::take(&mut joiner.buffered);
        joiner.phase = Phase::Mapping;
        joiner.joined_at = Some(cand.t);
        let id = joiner.id.clone();
        self.slam
            .add_robot_from_samples(&id, &cand.poses, &cand.weights, cand.t)?;
        let mut last = None;
        for b in &buffered {
            last = Some(self.slam.step(b)?);
        }
        Ok(JoinStep {
            phase: Phase::Mapping,
            slam: last,
            localization: Some(rep),
            joined: true,
            replayed: buffered.len(),
        })
    }

    /// The whole state, for a store: [`LateJoinSlam::from_snapshot`] continues bit for bit.
    pub fn snapshot(&self) -> LateJoinSnapshot {
        LateJoinSnapshot {
            slam: self.slam.snapshot(),
            localize: self.localize.clone(),
            joiners: self.joiners.clone(),
        }
    }

    /// Restores a run from a snapshot, with the updater the run uses.
    pub fn from_snapshot(
        snap: LateJoinSnapshot,
        updater: Arc<dyn LandmarkUpdater>,
    ) -> Result<Self, LocalizeError> {
        snap.localize.validate().map_err(LocalizeError::Config)?;
        let slam = FastSlam::from_snapshot(snap.slam, updater)?;
        let mut joiner_index = BTreeMap::new();
        for (i, j) in snap.joiners.iter().enumerate() {
            j.localizer.check()?;
            let in_filter = slam.robot_index(&j.id).is_some();
            if in_filter != (j.phase == Phase::Mapping) {
                return Err(LocalizeError::Snapshot(format!(
                    "robot {:?} is {} but {} the filter",
                    j.id,
                    j.phase.as_str(),
                    if in_filter { "in" } else { "not in" }
                )));
            }
            if joiner_index.insert(j.id.clone(), i).is_some() {
                return Err(LocalizeError::Snapshot(format!(
                    "robot {:?} is listed twice",
                    j.id
                )));
            }
        }
        Ok(Self {
            slam,
            localize: snap.localize,
            joiners: snap.joiners,
            joiner_index,
        })
    }

    /// [`LateJoinSlam::from_snapshot`] with the EKF updater of the snapshot's configuration.
    pub fn from_snapshot_ekf(snap: LateJoinSnapshot) -> Result<Self, LocalizeError> {
        let updater = Arc::new(fleetslam_core::ekf::EkfUpdater::new(
            snap.slam.config.landmark_kind,
            &snap.slam.config.sensor_noise,
        ));
        Self::from_snapshot(snap, updater)
    }
}

/// Localization only: robots are localized in a fixed map (e.g. a finished run's final
/// map), which never changes. Serialisable as a whole; a restored value continues bit for
/// bit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapLocalization {
    map: LandmarkSet,
    models: Models,
    config: LocalizeConfig,
    seed: u64,
    robots: BTreeMap<String, Localizer>,
}

impl MapLocalization {
    /// `models` must observe the map's landmark kind.
    pub fn new(
        map: LandmarkSet,
        models: Models,
        config: LocalizeConfig,
        seed: u64,
    ) -> Result<Self, LocalizeError> {
        config.validate().map_err(LocalizeError::Config)?;
        if models.landmark_kind != map.kind {
            return Err(LocalizeError::Map(format!(
                "the map holds {} landmarks but the robots observe {}",
                map.kind.as_str(),
                models.landmark_kind.as_str()
            )));
        }
        if map.len() < config.min_landmarks {
            return Err(LocalizeError::Map(format!(
                "the map has {} landmarks; localization needs at least min_landmarks = {}",
                map.len(),
                config.min_landmarks
            )));
        }
        Ok(Self {
            map,
            models,
            config,
            seed,
            robots: BTreeMap::new(),
        })
    }

    pub fn map(&self) -> &LandmarkSet {
        &self.map
    }

    /// Registers a robot to localize.
    pub fn add_robot(&mut self, id: &str) -> Result<(), LocalizeError> {
        if id.is_empty() || self.robots.contains_key(id) {
            return Err(LocalizeError::Robot(format!(
                "robot id {id:?} is empty or already registered"
            )));
        }
        let loc = Localizer::new(
            self.models,
            self.config.clone(),
            localizer_seed(self.seed, id),
        )?;
        self.robots.insert(id.to_string(), loc);
        Ok(())
    }

    /// Applies one record of a registered robot.
    pub fn step(&mut self, rec: &Record) -> Result<Option<UpdateReport>, LocalizeError> {
        let loc = self.robots.get_mut(&rec.robot).ok_or_else(|| {
            LocalizeError::Robot(format!(
                "robot {:?} is not registered for localization",
                rec.robot
            ))
        })?;
        loc.push(rec, &self.map)
    }

    pub fn localizer(&self, id: &str) -> Option<&Localizer> {
        self.robots.get(id)
    }

    /// Every robot's phase (localizing or converged) and localizer state.
    pub fn phases(&self) -> Vec<RobotPhase> {
        self.robots
            .iter()
            .map(|(id, l)| RobotPhase {
                id: id.clone(),
                phase: if l.is_converged() {
                    Phase::Converged
                } else {
                    Phase::Localizing
                },
                joined_at: None,
                buffered: 0,
                localization: Some(l.status()),
            })
            .collect()
    }

    /// Checks a deserialised value's invariants.
    pub fn check(&self) -> Result<(), LocalizeError> {
        self.config
            .validate()
            .map_err(|e| LocalizeError::Snapshot(e.to_string()))?;
        self.robots.values().try_for_each(Localizer::check)
    }
}
