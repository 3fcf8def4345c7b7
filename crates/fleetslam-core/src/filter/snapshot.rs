//! A filter's snapshot and how it is written: the particles' maps go through one node
//! pool ([`crate::map::MapPool`]), so a landmark that many particles share is written once,
//! and a restored filter shares what the running one shared. Snapshots written before the
//! pool (each particle's map as its list of slots, under `map`) still read.

use super::{FilterStats, RobotState};
use crate::config::FilterConfig;
use crate::map::{LandmarkMap, MapPool, PoolError, PoolReader, PoolWriter, PooledMap};
use crate::pose::Pose2;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::collections::BTreeMap;

/// Everything needed to continue a filter bit for bit: the random state is (seed, step).
///
/// Serialised with the particles' maps in one node pool (`map_nodes`; each particle names
/// its map's root in it as `map_ref`); a snapshot with each particle's map written whole
/// (`map`, as before the pool) reads too.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    pub config: FilterConfig,
    pub robots: Vec<RobotState>,
    pub particles: Vec<ParticleState>,
    pub known_slots: BTreeMap<u32, usize>,
    pub step: u64,
    pub ess: f64,
    pub stats: FilterStats,
}

/// One particle as a snapshot holds it: every robot's pose, pose covariance and odometry
/// scales (the filter keeps these by robot, [`super::RobotParticles`]), its map and its
/// weight. Serialised whole (with `map`), it is the format of snapshots before the pool.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParticleState {
    /// Pose of each robot, in the order robots were added.
    pub poses: Vec<Pose2>,
    /// Per robot, the covariance of its pose around `poses` (upper triangle), zero once
    /// sampled ([`super::RobotParticles::pose_covs`]). Empty in snapshots written before it
    /// existed (read as zero).
    #[serde(default)]
    pub pose_covs: Vec<[f64; 6]>,
    /// Per robot, the odometry scales ([`super::RobotParticles::odometry_scales`]). Empty in
    /// snapshots written before they existed (read as `[1, 1]`).
    #[serde(default)]
    pub odometry_scales: Vec<[f64; 2]>,
    pub map: LandmarkMap,
    /// Normalised log-weight.
    pub log_w: f64,
}

#[derive(Serialize)]
struct SnapshotOut<'a> {
    config: &'a FilterConfig,
    robots: &'a [RobotState],
    map_nodes: MapPool,
    particles: Vec<ParticleOut<'a>>,
    known_slots: &'a BTreeMap<u32, usize>,
    step: u64,
    ess: f64,
    stats: &'a FilterStats,
}

#[derive(Serialize)]
struct ParticleOut<'a> {
    poses: &'a [Pose2],
    pose_covs: &'a [[f64; 6]],
    odometry_scales: &'a [[f64; 2]],
    map_ref: PooledMap,
    log_w: f64,
}

impl Serialize for Snapshot {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut pool = PoolWriter::new();
        let particles = self
            .particles
            .iter()
            .map(|p| {
                Ok(ParticleOut {
                    poses: &p.poses,
                    pose_covs: &p.pose_covs,
                    odometry_scales: &p.odometry_scales,
                    map_ref: pool.add(&p.map)?,
                    log_w: p.log_w,
                })
            })
            .collect::<Result<Vec<_>, PoolError>>()
            .map_err(serde::ser::Error::custom)?;
        SnapshotOut {
            config: &self.config,
            robots: &self.robots,
            map_nodes: pool.finish(),
            particles,
            known_slots: &self.known_slots,
            step: self.step,
            ess: self.ess,
            stats: &self.stats,
        }
        .serialize(s)
    }
}

#[derive(Deserialize)]
struct SnapshotIn {
    config: FilterConfig,
    robots: Vec<RobotState>,
    /// Absent in snapshots written before the pool.
    #[serde(default)]
    map_nodes: Option<MapPool>,
    particles: Vec<ParticleIn>,
    known_slots: BTreeMap<u32, usize>,
    step: u64,
    ess: f64,
    stats: FilterStats,
}

#[derive(Deserialize)]
struct ParticleIn {
    poses: Vec<Pose2>,
    /// Empty in snapshots written before it existed (see [`ParticleState::pose_covs`]).
    #[serde(default)]
    pose_covs: Vec<[f64; 6]>,
    /// Empty in snapshots written before it existed (see [`ParticleState::odometry_scales`]).
    #[serde(default)]
    odometry_scales: Vec<[f64; 2]>,
    /// The map's entry in the snapshot's pool.
    #[serde(default)]
    map_ref: Option<PooledMap>,
    /// The whole map, in snapshots written before the pool.
    #[serde(default)]
    map: Option<LandmarkMap>,
    log_w: f64,
}

impl<'de> Deserialize<'de> for Snapshot {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let s = SnapshotIn::deserialize(d)?;
        let mut pool = s
            .map_nodes
            .map(PoolReader::new)
            .transpose()
            .map_err(D::Error::custom)?;
        let particles = s
            .particles
            .into_iter()
            .enumerate()
            .map(|(i, p)| {
                let map = match (p.map_ref, p.map, pool.as_mut()) {
                    (Some(r), None, Some(pool)) => pool
                        .map(&r)
                        .map_err(|e| D::Error::custom(format!("particle {i}: {e}")))?,
                    (None, Some(m), _) => m,
                    (Some(_), None, None) => {
                        return Err(D::Error::custom(format!(
                            "particle {i} names a map in a pool, but the snapshot has no \
                             `map_nodes`"
                        )));
                    }
                    (Some(_), Some(_), _) => {
                        return Err(D::Error::custom(format!(
                            "particle {i} has both `map` and `map_ref`"
                        )));
                    }
                    (None, None, _) => {
                        return Err(D::Error::custom(format!(
                            "particle {i} has no map (`map_ref` or `map`)"
                        )));
                    }
                };
                Ok(ParticleState {
                    poses: p.poses,
                    pose_covs: p.pose_covs,
                    odometry_scales: p.odometry_scales,
                    map,
                    log_w: p.log_w,
                })
            })
            .collect::<Result<Vec<_>, D::Error>>()?;
        Ok(Snapshot {
            config: s.config,
            robots: s.robots,
            particles,
            known_slots: s.known_slots,
            step: s.step,
            ess: s.ess,
            stats: s.stats,
        })
    }
}
