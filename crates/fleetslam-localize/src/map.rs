//! The fixed landmark map a robot is localized in, and the observation likelihood.
//!
//! A map is a list of landmark Gaussians (mean and covariance, as FastSLAM's per-landmark
//! EKFs leave them) with their ids when the run associates by id. The likelihood of one
//! measurement `z` from pose `x` integrates the landmark's uncertainty: with `ẑ = h(x, μ)`,
//! `H_m = ∂h/∂m` and the sensor noise `Q`,
//!
//! ```text
//! p(z | x, m) = N(z; ẑ, S),   S = H_m Σ H_mᵀ + Q
//! ```
//!
//! the same marginal that FastSLAM uses to weigh a particle (Montemerlo et al. 2002, eq. for
//! the importance weight; the Rao-Blackwellized notes in `shared/papers`). Observations without a
//! usable id are associated by maximum likelihood over the map's landmarks (the most likely
//! landmark's term is used). A flat tail beyond the squared Mahalanobis distance
//! `outlier_mahalanobis2` keeps one unexplained reading from annihilating a sample: the
//! robust mixture of Monte Carlo localization, where a measurement that no map feature
//! explains has a small constant probability (Thrun, Burgard, Fox, ch. 6, the `z_rand` term).

use crate::error::LocalizeError;
use fleetslam_core::filter::{Estimate, FastSlam};
use fleetslam_core::log::LandmarkObservation;
use fleetslam_core::math;
use fleetslam_core::pose::Pose2;
use fleetslam_core::sensor::{
    LandmarkKind, MeasurementModel, Point3Model, RangeBearingModel, SensorNoise,
};
use fleetslam_core::stats::gaussian_log_density;
use fleetslam_core::updater::LandmarkGaussian;
use nalgebra::{Matrix2, Matrix3, SMatrix, SVector};
use serde::{Deserialize, Serialize};

/// One landmark of a fixed map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MapLandmark {
    /// The landmark's id when observations carry ids.
    pub id: Option<u32>,
    pub gaussian: LandmarkGaussian,
}

/// A fixed landmark map of one kind.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LandmarkSet {
    pub kind: LandmarkKind,
    pub landmarks: Vec<MapLandmark>,
}

/// The rectangle a map covers: the landmarks' bounding box grown by a margin.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Extent {
    pub min: [f64; 2],
    pub max: [f64; 2],
}

impl LandmarkSet {
    /// Checks that every landmark is finite with a positive semi-definite covariance.
    pub fn new(kind: LandmarkKind, landmarks: Vec<MapLandmark>) -> Result<Self, LocalizeError> {
        for (i, l) in landmarks.iter().enumerate() {
            if !l.gaussian.is_finite() {
                return Err(LocalizeError::Map(format!(
                    "landmark {i} has a non-finite number"
                )));
            }
            let c = &l.gaussian.cov;
            if c[0] < 0.0 || c[3] < 0.0 || c[5] < 0.0 || c[0] * c[3] - c[1] * c[1] < -1e-12 {
                return Err(LocalizeError::Map(format!(
                    "landmark {i}'s covariance is not positive semi-definite: {c:?}"
                )));
            }
        }
        Ok(Self { kind, landmarks })
    }

    /// The landmarks of the SLAM filter's best particle (the run's current best map).
    pub fn from_best_particle(slam: &FastSlam) -> Self {
        let best = &slam.particles()[slam.best_index()];
        Self {
            kind: slam.config().landmark_kind,
            landmarks: best
                .map
                .iter()
                .filter(|(_, l)| slam.config().is_confirmed(l))
                .map(|(_, l)| MapLandmark {
                    id: l.id,
                    gaussian: l.gaussian,
                })
                .collect(),
        }
    }

    /// The landmarks of an estimate (a finished run's final map, as the API returns it).
    pub fn from_estimate(kind: LandmarkKind, est: &Estimate) -> Result<Self, LocalizeError> {
        Self::new(
            kind,
            est.landmarks
                .iter()
                .map(|l| MapLandmark {
                    id: l.id,
                    gaussian: l.gaussian,
                })
                .collect(),
        )
    }

    pub fn len(&self) -> usize {
        self.landmarks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.landmarks.is_empty()
    }

    /// The landmarks' bounding box grown by `margin` metres on every side; `None` for an
    /// empty map.
    pub fn extent(&self, margin: f64) -> Option<Extent> {
        let first = self.landmarks.first()?;
        let mut min = [first.gaussian.mean[0], first.gaussian.mean[1]];
        let mut max = min;
        for l in &self.landmarks {
            for a in 0..2 {
                min[a] = min[a].min(l.gaussian.mean[a]);
                max[a] = max[a].max(l.gaussian.mean[a]);
            }
        }
        Some(Extent {
            min: [min[0] - margin, min[1] - margin],
            max: [max[0] + margin, max[1] + margin],
        })
    }

    /// The index of the landmark with this id.
    pub fn find_id(&self, id: u32) -> Option<usize> {
        self.landmarks.iter().position(|l| l.id == Some(id))
    }
}

/// How observations are scored against a fixed map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LikelihoodParams {
    /// Use the ids observations carry (when the map has them). Default true. False treats
    /// every observation as anonymous (maximum-likelihood association).
    pub use_ids: bool,
    /// Factor on the sensor noise's standard deviations. Default 2.0. A particle filter
    /// represents a peaked likelihood poorly: with samples spread over a whole map, few or
    /// none fall inside a narrow likelihood peak, and the filter can settle on a wrong pose.
    /// Overestimating the noise smooths the likelihood (Thrun, Burgard, Fox, Probabilistic
    /// Robotics, section 6.3, and the Monte Carlo localization notes). 1 uses the run's
    /// noise as is.
    pub noise_scale: f64,
    /// Squared Mahalanobis distance at which a reading's likelihood stops falling (it is
    /// floored at the sensor-noise Gaussian's value there). Default 16 (4 sigma). Lower
    /// tolerates more unexplained readings and localizes more slowly; higher trusts the
    /// map more (one unexplained reading then nearly kills a sample). Finite.
    pub outlier_mahalanobis2: f64,
}

impl Default for LikelihoodParams {
    fn default() -> Self {
        Self {
            use_ids: true,
            noise_scale: 2.0,
            outlier_mahalanobis2: 16.0,
        }
    }
}

/// Maps with at least this many range-bearing landmarks get a grid index for the
/// maximum-likelihood association of anonymous readings; smaller maps are scanned whole
/// (cheaper than the index's bookkeeping).
pub const INDEX_MIN_LANDMARKS: usize = 64;
/// Cell size of the landmark index [m]. Smaller cells hold fewer landmarks each but a
/// reading's search disc (a few metres at long range) covers more of them.
pub const INDEX_CELL: f64 = 1.0;

/// A uniform grid over the landmarks' positions, each cell listing its landmarks (in map
/// order), for the association of anonymous range-bearing readings: only landmarks near
/// the point a reading predicts can beat the likelihood floor.
#[derive(Debug, Clone)]
struct LandmarkIndex {
    min: [f64; 2],
    nx: usize,
    ny: usize,
    /// `items[start[c]..start[c + 1]]`: the landmarks of cell `c = cx + cy · nx`.
    start: Vec<u32>,
    items: Vec<u32>,
    /// The largest trace of a landmark covariance.
    max_trace: f64,
}

impl LandmarkIndex {
    fn new(map: &LandmarkSet) -> Option<Self> {
        let ext = map.extent(0.0)?;
        let nx = ((ext.max[0] - ext.min[0]) / INDEX_CELL).floor() as usize + 1;
        let ny = ((ext.max[1] - ext.min[1]) / INDEX_CELL).floor() as usize + 1;
        let cell_of = |l: &MapLandmark| {
            let cx = ((l.gaussian.mean[0] - ext.min[0]) / INDEX_CELL).floor() as usize;
            let cy = ((l.gaussian.mean[1] - ext.min[1]) / INDEX_CELL).floor() as usize;
            cx.min(nx - 1) + cy.min(ny - 1) * nx
        };
        let mut count = vec![0u32; nx * ny + 1];
        for l in &map.landmarks {
            count[cell_of(l) + 1] += 1;
        }
        for c in 1..count.len() {
            count[c] += count[c - 1];
        }
        let start = count.clone();
        let mut fill = count;
        let mut items = vec![0u32; map.len()];
        for (i, l) in map.landmarks.iter().enumerate() {
            let c = cell_of(l);
            items[fill[c] as usize] = i as u32;
            fill[c] += 1;
        }
        let max_trace = map
            .landmarks
            .iter()
            .map(|l| l.gaussian.cov[0] + l.gaussian.cov[3] + l.gaussian.cov[5])
            .fold(0.0, f64::max);
        Some(Self {
            min: ext.min,
            nx,
            ny,
            start,
            items,
            max_trace,
        })
    }

    /// The landmarks of the cells that meet the square of half-side `r` around `p`, in map
    /// order within each cell.
    fn near(&self, p: [f64; 2], r: f64) -> impl Iterator<Item = usize> + '_ {
        let span = |v: f64, min: f64, n: usize| {
            let lo = ((v - r - min) / INDEX_CELL).floor();
            let hi = ((v + r - min) / INDEX_CELL).floor();
            let lo = lo.max(0.0);
            let hi = hi.min(n as f64 - 1.0);
            if lo > hi || lo.is_nan() || hi.is_nan() {
                (1usize, 0usize)
            } else {
                (lo as usize, hi as usize)
            }
        };
        let (x0, x1) = span(p[0], self.min[0], self.nx);
        let (y0, y1) = span(p[1], self.min[1], self.ny);
        (y0..=y1).flat_map(move |cy| {
            let (a, b) = if x0 <= x1 {
                (
                    self.start[x0 + cy * self.nx] as usize,
                    self.start[x1 + cy * self.nx + 1] as usize,
                )
            } else {
                (0, 0)
            };
            self.items[a..b].iter().map(|&i| i as usize)
        })
    }
}

/// The measurement noise matrix and the map, ready to score poses.
#[derive(Debug, Clone)]
pub struct Scorer<'a> {
    map: &'a LandmarkSet,
    /// The range-bearing noise, scaled: `q2` at range 0, and its growth with the range.
    q2: Matrix2<f64>,
    range_per_m: f64,
    q3: Matrix3<f64>,
    params: LikelihoodParams,
    index: Option<LandmarkIndex>,
}

/// One observation resolved against the map: the landmark when its id is known.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResolvedObs {
    pub z: [f64; 3],
    /// `Some(i)`: landmark `i` of the map; `None`: maximum likelihood over the map.
    pub landmark: Option<usize>,
}

impl<'a> Scorer<'a> {
    pub fn new(map: &'a LandmarkSet, noise: &SensorNoise, params: LikelihoodParams) -> Self {
        let s2 = params.noise_scale * params.noise_scale;
        let index = if map.kind == LandmarkKind::RangeBearing2d && map.len() >= INDEX_MIN_LANDMARKS
        {
            LandmarkIndex::new(map)
        } else {
            None
        };
        Self {
            map,
            q2: noise.q2() * s2,
            range_per_m: noise.range_per_m * params.noise_scale,
            q3: noise.q3() * s2,
            params,
            index,
        }
    }

    /// A scorer that scans every landmark for each anonymous reading (no index): the
    /// reference the index is tested against.
    pub fn without_index(
        map: &'a LandmarkSet,
        noise: &SensorNoise,
        params: LikelihoodParams,
    ) -> Self {
        Self {
            index: None,
            ..Self::new(map, noise, params)
        }
    }

    /// The best landmark term of an anonymous range-bearing reading, over the landmarks
    /// near the point it predicts. A landmark whose squared Mahalanobis distance is below
    /// the outlier bound `b` has `|Δr| ≤ √(b S_rr)` and `|Δφ| ≤ √(b S_φφ)` (each squared
    /// component over its variance bounds the whole form), with `S_rr ≤ tr Σ + Q_rr` and
    /// `r S_φφ^½ ≤ √(tr Σ + r² Q_φφ)`, so it lies within `|Δr| + r|Δφ|` of that point. The
    /// landmarks further away score below the floor and cannot change the result, which is
    /// bit for bit that of the whole scan.
    fn indexed_best(&self, index: &LandmarkIndex, pose: &Pose2, z: &[f64; 3]) -> Option<f64> {
        let b = self.params.outlier_mahalanobis2;
        let q2 = self.q2_at(z);
        let dr = (b * (index.max_trace + q2[(0, 0)])).sqrt();
        let rmax = z[0].max(0.0) + dr;
        let radius =
            (dr + (b * (index.max_trace + rmax * rmax * q2[(1, 1)])).sqrt()) * (1.0 + 1e-9) + 1e-9;
        let a = pose.theta + z[1];
        let p = [pose.x + z[0] * math::cos(a), pose.y + z[0] * math::sin(a)];
        index
            .near(p, radius)
            .filter_map(|i| self.landmark_ll(pose, z, &self.map.landmarks[i].gaussian))
            .reduce(f64::max)
    }

    pub fn map(&self) -> &LandmarkSet {
        self.map
    }

    /// The (scaled) range-bearing noise of a reading `z`: its range variance grows with the
    /// measured range by `range_per_m` ([`SensorNoise::range_per_m`]).
    #[inline]
    fn q2_at(&self, z: &[f64; 3]) -> Matrix2<f64> {
        if self.range_per_m == 0.0 {
            self.q2
        } else {
            let g = self.range_per_m * z[0];
            let mut q = self.q2;
            q[(0, 0)] += g * g;
            q
        }
    }

    /// Resolves a record's observations. Observations whose id the map does not hold are
    /// left out (the landmark is not mapped yet) and counted in the second value.
    pub fn resolve(&self, obs: &[LandmarkObservation]) -> (Vec<ResolvedObs>, usize) {
        let mut out = Vec::with_capacity(obs.len());
        let mut unmatched = 0;
        for o in obs {
            let mut z = [0.0; 3];
            let n = o.z.len().min(3);
            z[..n].copy_from_slice(&o.z[..n]);
            let landmark = match (self.params.use_ids, o.id) {
                (true, Some(id)) => match self.map.find_id(id) {
                    Some(i) => Some(i),
                    None => {
                        unmatched += 1;
                        continue;
                    }
                },
                _ => None,
            };
            out.push(ResolvedObs { z, landmark });
        }
        (out, unmatched)
    }

    /// `log N(z; h(x, μ), H_m Σ H_mᵀ + Q)`, or `None` when it is certainly below the
    /// floor (the squared Mahalanobis distance is at least `outlier_mahalanobis2`, checked
    /// first on the range or point distance alone, which bounds it from below: for any
    /// positive-definite `S`, `νᵀS⁻¹ν ≥ νᵢ² / Sᵢᵢ`), when the landmark sits on the robot (no
    /// bearing) or when the covariance is degenerate.
    #[inline]
    fn landmark_ll(&self, pose: &Pose2, z: &[f64; 3], l: &LandmarkGaussian) -> Option<f64> {
        let bound = self.params.outlier_mahalanobis2;
        let tr = l.cov[0] + l.cov[3] + l.cov[5];
        match self.map.kind {
            LandmarkKind::RangeBearing2d => {
                let r = math::hypot(l.mean[0] - pose.x, l.mean[1] - pose.y);
                let nr = z[0] - r;
                let q2 = self.q2_at(z);
                if nr * nr > bound * (tr + q2[(0, 0)]) {
                    return None;
                }
                let (zhat, hm, _) = RangeBearingModel::predict(pose, &l.mean)?;
                let nu = RangeBearingModel::innovation(z, &zhat);
                gaussian_ll::<2, RangeBearingModel>(&q2, l, &nu, &hm)
            }
            LandmarkKind::Point3d => {
                let (zhat, hm, _) = Point3Model::predict(pose, &l.mean)?;
                let nu = Point3Model::innovation(z, &zhat);
                let qmax = self.q3[(0, 0)].max(self.q3[(1, 1)]).max(self.q3[(2, 2)]);
                if nu.norm_squared() > bound * (tr + qmax) {
                    return None;
                }
                gaussian_ll::<3, Point3Model>(&self.q3, l, &nu, &hm)
            }
        }
    }

    /// The log-likelihood of one resolved observation from `pose`: `max(log N(z; ẑ, S), f)`
    /// with `f` the [floor](Self::floor); over the map's landmarks (their maximum) when the
    /// id is unknown. Since `det S ≥ det Q`, a landmark whose Mahalanobis distance exceeds
    /// the outlier bound is below the floor, so skipping it changes nothing.
    #[inline]
    pub fn obs_ll(&self, pose: &Pose2, o: &ResolvedObs) -> f64 {
        let floor = self.floor_at(&o.z);
        let best = match o.landmark {
            Some(i) => self.landmark_ll(pose, &o.z, &self.map.landmarks[i].gaussian),
            None => match &self.index {
                Some(index) => self.indexed_best(index, pose, &o.z),
                None => self
                    .map
                    .landmarks
                    .iter()
                    .filter_map(|l| self.landmark_ll(pose, &o.z, &l.gaussian))
                    .reduce(f64::max),
            },
        };
        best.map_or(floor, |b| b.max(floor))
    }

    /// The log-likelihood of all of a record's observations (independent given the pose).
    #[inline]
    pub fn record_ll(&self, pose: &Pose2, obs: &[ResolvedObs]) -> f64 {
        obs.iter().map(|o| self.obs_ll(pose, o)).sum()
    }

    /// The constant a reading gets when no landmark explains it: the Gaussian of the sensor
    /// noise alone at the outlier boundary, `-b/2 - (d ln 2π + ln det Q)/2`.
    pub fn floor(&self) -> f64 {
        self.floor_at(&[0.0; 3])
    }

    /// The [floor](Self::floor) of reading `z`, whose range sets its range noise.
    pub fn floor_at(&self, z: &[f64; 3]) -> f64 {
        let (dim, logdet) = match self.map.kind {
            LandmarkKind::RangeBearing2d => (2, math::ln(self.q2_at(z).determinant())),
            LandmarkKind::Point3d => (3, math::ln(self.q3.determinant())),
        };
        gaussian_log_density(self.params.outlier_mahalanobis2, logdet, dim)
    }
}

/// `log N(ν; 0, H_m Σ H_mᵀ + Q)` in measurement model `M`, for an innovation `ν` and a
/// Jacobian `H_m` already predicted; `None` when the covariance is degenerate.
#[inline]
fn gaussian_ll<const D: usize, M: MeasurementModel<D>>(
    q: &SMatrix<f64, D, D>,
    l: &LandmarkGaussian,
    nu: &SVector<f64, D>,
    hm: &SMatrix<f64, D, D>,
) -> Option<f64> {
    let s = hm * M::cov(l) * hm.transpose() + q;
    let (inv, det) = M::inverse_det(&s)?;
    Some(gaussian_log_density(nu.dot(&(inv * nu)), math::ln(det), D))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(kind: LandmarkKind, mean: [f64; 3]) -> LandmarkSet {
        LandmarkSet::new(
            kind,
            vec![MapLandmark {
                id: Some(4),
                gaussian: LandmarkGaussian {
                    mean,
                    cov: [0.01, 0.0, 0.0, 0.01, 0.0, 0.01],
                },
            }],
        )
        .unwrap()
    }

    #[test]
    fn likelihood_peaks_at_the_true_pose_and_integrates_landmark_covariance() {
        let map = one(LandmarkKind::RangeBearing2d, [2.0, 0.0, 0.0]);
        let exact = LikelihoodParams {
            noise_scale: 1.0,
            ..Default::default()
        };
        let s = Scorer::new(&map, &SensorNoise::default(), exact);
        let obs = [LandmarkObservation {
            id: Some(4),
            z: vec![2.0, 0.0],
        }];
        let (r, un) = s.resolve(&obs);
        assert_eq!((r.len(), un), (1, 0));
        let at = s.record_ll(&Pose2::new(0.0, 0.0, 0.0), &r);
        let off = s.record_ll(&Pose2::new(1.0, 0.0, 0.0), &r);
        assert!(at > off + 1.0, "{at} {off}");
        // 1 m off is beyond the outlier bound: the floor.
        assert_eq!(off, s.floor());
        // A vaguer landmark gives a flatter likelihood: lower peak, higher tail.
        let mut vague = map.clone();
        vague.landmarks[0].gaussian.cov = [1.0, 0.0, 0.0, 1.0, 0.0, 1.0];
        let sv = Scorer::new(&vague, &SensorNoise::default(), exact);
        assert!(sv.record_ll(&Pose2::default(), &r) < at);
        assert!(sv.record_ll(&Pose2::new(1.0, 0.0, 0.0), &r) > off);
    }

    #[test]
    fn range_noise_that_grows_with_range_scores_as_the_constant_noise_at_that_range() {
        let map = one(LandmarkKind::RangeBearing2d, [3.0, 0.5, 0.0]);
        let params = LikelihoodParams {
            noise_scale: 1.5,
            ..Default::default()
        };
        let grow = SensorNoise {
            range: 0.05,
            range_per_m: 0.04,
            ..SensorNoise::default()
        };
        let s = Scorer::new(&map, &grow, params);
        for (z, pose) in [
            ([3.1, 0.15], Pose2::default()),
            ([2.7, 0.2], Pose2::new(0.2, 0.1, 0.05)),
            ([6.0, 0.1], Pose2::default()),
        ] {
            let fixed = SensorNoise {
                range: grow.range_std_at(z[0]),
                range_per_m: 0.0,
                ..grow
            };
            let f = Scorer::new(&map, &fixed, params);
            let o = ResolvedObs {
                z: [z[0], z[1], 0.0],
                landmark: Some(0),
            };
            let (a, b) = (s.obs_ll(&pose, &o), f.obs_ll(&pose, &o));
            assert!(
                (a - b).abs() < 1e-12 * (1.0 + b.abs()),
                "{z:?}: {a} against {b}"
            );
            assert!((s.floor_at(&o.z) - f.floor()).abs() < 1e-12, "{z:?}");
            let anon = ResolvedObs {
                landmark: None,
                ..o
            };
            assert!((s.obs_ll(&pose, &anon) - b).abs() < 1e-12 * (1.0 + b.abs()));
        }
    }

    #[test]
    fn unknown_ids_take_the_most_likely_landmark_and_missing_ids_are_counted() {
        let mut map = one(LandmarkKind::Point3d, [1.0, 0.0, 0.5]);
        map.landmarks.push(MapLandmark {
            id: Some(9),
            gaussian: LandmarkGaussian {
                mean: [0.0, 1.0, 0.5],
                cov: [0.01, 0.0, 0.0, 0.01, 0.0, 0.01],
            },
        });
        let s = Scorer::new(&map, &SensorNoise::default(), LikelihoodParams::default());
        let obs = [
            LandmarkObservation {
                id: None,
                z: vec![0.0, 1.0, 0.5],
            },
            LandmarkObservation {
                id: Some(77),
                z: vec![1.0, 0.0, 0.5],
            },
        ];
        let (r, un) = s.resolve(&obs);
        assert_eq!((r.len(), un), (1, 1));
        let ml = s.record_ll(&Pose2::default(), &r);
        let by_id = s.obs_ll(
            &Pose2::default(),
            &ResolvedObs {
                z: [0.0, 1.0, 0.5],
                landmark: Some(1),
            },
        );
        assert_eq!(ml, by_id);
    }

    #[test]
    fn the_landmark_index_scores_anonymous_readings_as_the_whole_scan() {
        use fleetslam_core::rng::stream;
        use rand::Rng;
        // 300 landmarks over 30 m x 10 m, some vague; readings near and far, poses anywhere.
        let mut rng = stream(11, 0, 0);
        let landmarks = (0..300)
            .map(|i| {
                let v = if i % 7 == 0 { 0.3 } else { 1e-4 };
                MapLandmark {
                    id: None,
                    gaussian: LandmarkGaussian {
                        mean: [rng.random::<f64>() * 30.0, rng.random::<f64>() * 10.0, 0.0],
                        cov: [v, 0.0, 0.0, v, 0.0, v],
                    },
                }
            })
            .collect();
        let map = LandmarkSet::new(LandmarkKind::RangeBearing2d, landmarks).unwrap();
        let params = LikelihoodParams::default();
        let indexed = Scorer::new(&map, &SensorNoise::default(), params);
        assert!(indexed.index.is_some());
        let scan = Scorer::without_index(&map, &SensorNoise::default(), params);
        let mut above_floor = 0;
        for _ in 0..5000 {
            let pose = Pose2::new(
                rng.random::<f64>() * 36.0 - 3.0,
                rng.random::<f64>() * 16.0 - 3.0,
                rng.random::<f64>() * 6.3 - 3.15,
            );
            let o = ResolvedObs {
                z: [
                    rng.random::<f64>() * 6.0,
                    rng.random::<f64>() * 6.3 - 3.15,
                    0.0,
                ],
                landmark: None,
            };
            let (a, b) = (indexed.obs_ll(&pose, &o), scan.obs_ll(&pose, &o));
            assert_eq!(a.to_bits(), b.to_bits(), "{pose:?} {o:?}");
            above_floor += usize::from(a > scan.floor());
        }
        // The test means something only if many readings find a landmark.
        assert!(above_floor > 500, "{above_floor} readings above the floor");
    }

    #[test]
    fn bad_maps_are_refused() {
        let mut m = one(LandmarkKind::RangeBearing2d, [0.0, 0.0, 0.0]);
        m.landmarks[0].gaussian.mean[0] = f64::NAN;
        assert!(LandmarkSet::new(m.kind, m.landmarks.clone()).is_err());
        m.landmarks[0].gaussian.mean[0] = 0.0;
        m.landmarks[0].gaussian.cov[0] = -1.0;
        assert!(LandmarkSet::new(m.kind, m.landmarks).is_err());
        let e = one(LandmarkKind::RangeBearing2d, [1.0, 2.0, 0.0])
            .extent(1.0)
            .unwrap();
        assert_eq!(e.min, [0.0, 1.0]);
        assert_eq!(e.max, [2.0, 3.0]);
    }
}
