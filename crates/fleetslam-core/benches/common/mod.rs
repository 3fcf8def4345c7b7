//! Shared setup of the filter benchmarks: one stationary robot at the origin among landmarks
//! with known ids. Landmark `id` sits at a fixed place (bearings spread by the golden angle,
//! ranges 2-20 m), so a map of `m` landmarks holds ids `0..m` in slots `0..m`.

use fleetslam_core::filter::ParticleState;
use fleetslam_core::log::{LandmarkObservation, Record};
use fleetslam_core::math;
use fleetslam_core::motion::Motion;
use fleetslam_core::pose::wrap_angle;
use fleetslam_core::{FastSlam, FilterConfig, Pose2, PoseGaussian};

pub const ROBOT: &str = "r1";
/// New landmarks per map-building record.
const IDS_PER_RECORD: usize = 50;

/// Exact (range, bearing) of landmark `id` from the origin, facing +x.
fn landmark_z(id: u32) -> [f64; 2] {
    let k = f64::from(id);
    let bearing = wrap_angle(k * 2.399_963_229_728_653);
    let range = 2.0 + 18.0 * (k * 0.618_033_988_749_895).fract();
    [range, bearing]
}

/// The robot's next record (0.1 s after its last one, standing still) observing `ids`, with
/// `noise` added to the ranges (and a fifth of it taken off the bearings).
fn record(slam: &FastSlam, ids: impl IntoIterator<Item = u32>, noise: f64) -> Record {
    let st = &slam.robots()[0];
    Record {
        robot: ROBOT.into(),
        seq: st.records,
        t: st.last_t + 0.1,
        motion: Some(Motion::Velocity(vec![[0.0, 0.0, 0.1]])),
        landmarks: ids
            .into_iter()
            .map(|id| {
                let [r, b] = landmark_z(id);
                LandmarkObservation {
                    id: Some(id),
                    z: vec![r + noise, b - 0.2 * noise],
                }
            })
            .collect(),
        robots: vec![],
    }
}

/// A filter of `particles` particles (FastSLAM 2.0, known ids, never resampling) with the
/// robot added at the origin.
pub fn new_filter(particles: usize) -> FastSlam {
    let cfg = FilterConfig {
        particles,
        resample_threshold: 0.0,
        ..Default::default()
    };
    let mut slam = FastSlam::new(cfg).unwrap();
    slam.add_robot(ROBOT, &PoseGaussian::exact(Pose2::default()), 0.0)
        .unwrap();
    slam
}

/// Steps records of `IDS_PER_RECORD` new ids until every particle maps `m` landmarks. The
/// particles' maps are built independently, as in a run without resampling.
pub fn grow_map(slam: &mut FastSlam, m: usize) {
    let mut have = slam.particles()[0].map.len();
    while have < m {
        let end = (have + IDS_PER_RECORD).min(m);
        let rec = record(slam, have as u32..end as u32, 0.0);
        slam.step(&rec).unwrap();
        have = end;
    }
    assert_eq!(slam.particles()[0].map.len(), m);
}

/// A filter of `particles` particles (as [`new_filter`]) whose maps are all one map of `m`
/// landmarks: every particle descends from one ancestor, as resampling makes them over a run
/// (landmarks out of view stay shared), so the maps share every trie node until a step writes.
/// [`grow_map`] gives the other extreme: every particle's map its own.
pub fn shared_filter(particles: usize, m: usize) -> FastSlam {
    let mut one = new_filter(1);
    grow_map(&mut one, m);
    let mut s = one.snapshot();
    let ancestor = s.particles.pop().expect("one particle");
    s.particles = vec![
        ParticleState {
            log_w: -math::ln(particles as f64),
            ..ancestor
        };
        particles
    ];
    s.config.particles = particles;
    FastSlam::from_snapshot(s, one.updater().clone()).unwrap()
}

/// The same filter state with a changed configuration (particles and maps are shared).
pub fn with_config(slam: &FastSlam, f: impl FnOnce(&mut FilterConfig)) -> FastSlam {
    let mut s = slam.snapshot();
    f(&mut s.config);
    FastSlam::from_snapshot(s, slam.updater().clone()).unwrap()
}

/// The timed record: 5 known landmarks spread over a map of `m`, with small innovations.
pub fn observe_five(slam: &FastSlam, m: usize) -> Record {
    record(slam, (0..5).map(|j| ((2 * j + 1) * m / 10) as u32), 0.05)
}
