//! The same seed and inputs give bit-identical filters: for any rayon pool size, and when a
//! run is stopped at a snapshot and continued.

use fleetslam_core::config::{Association, FastSlamVersion, FilterConfig};
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::filter::{FastSlam, Snapshot};
use fleetslam_core::log::Log;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_suite::small_sim;
use std::sync::Arc;

fn run_with_threads(log: &Log, cfg: &FilterConfig, threads: usize) -> (Snapshot, String) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| run_filter(FastSlam::new(cfg.clone()).unwrap(), log))
}

/// Runs `slam` over `log`: its final state and its trajectories as text.
fn run_filter(mut slam: FastSlam, log: &Log) -> (Snapshot, String) {
    let out = run_log(&mut slam, log, TrajectoryEstimate::Mean, |_, _| {}).unwrap();
    let traj = format!("{:?}", out.estimate.trajectories);
    (slam.snapshot(), traj)
}

/// The filter's state as text, without the one field that is a wall-clock measurement.
fn state_text(s: &Snapshot) -> String {
    let mut s = s.clone();
    s.stats.update_nanos = 0;
    serde_json::to_string(&s).unwrap()
}

/// Asserts bitwise equality of two states, showing where they first differ.
fn assert_same_state(a: &Snapshot, b: &Snapshot) {
    let (ta, tb) = (state_text(a), state_text(b));
    if ta != tb {
        let at = ta
            .bytes()
            .zip(tb.bytes())
            .position(|(x, y)| x != y)
            .unwrap_or(ta.len().min(tb.len()));
        let from = at.saturating_sub(120);
        panic!(
            "states differ at byte {at}:\n  {}\n  {}",
            &ta[from..(at + 80).min(ta.len())],
            &tb[from..(at + 80).min(tb.len())]
        );
    }
}

fn check_thread_counts(log: &Log, cfg: FilterConfig) {
    let (a, ta) = run_with_threads(log, &cfg, 1);
    let (b, tb) = run_with_threads(log, &cfg, 2);
    assert!(
        a.stats.landmark_updates > 0,
        "the run must exercise the updater"
    );
    assert!(a.stats.resamples > 0, "the run must exercise resampling");
    assert_same_state(&a, &b);
    assert!(ta == tb, "trajectories differ");
}

#[test]
fn thread_count_determinism_2d_known_v2() {
    let sim = small_sim(3, 20.0, 7, |_| {});
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 150;
    cfg.batch_size = 16;
    cfg.seed = 42;
    check_thread_counts(&sim.log, cfg);
}

#[test]
fn thread_count_determinism_3d_unknown_v1() {
    let sim = small_sim(2, 20.0, 8, |c| {
        c.kind = LandmarkKind::Point3d;
        c.with_ids = false;
    });
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    assert_eq!(cfg.association, Association::Unknown);
    cfg.particles = 100;
    cfg.batch_size = 8;
    cfg.version = FastSlamVersion::V1;
    check_thread_counts(&sim.log, cfg);
}

#[test]
fn snapshot_restore_continues_bit_for_bit() {
    let sim = small_sim(3, 20.0, 9, |_| {});
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 80;
    cfg.seed = 5;
    let mut log = sim.log.clone();
    log.sort();
    let half = log.records.len() / 2;

    let mut whole = FastSlam::new(cfg.clone()).unwrap();
    fleetslam_data::run::add_header_robots(&mut whole, &log).unwrap();
    for r in &log.records {
        whole.step(r).unwrap();
    }

    let mut first = FastSlam::new(cfg).unwrap();
    fleetslam_data::run::add_header_robots(&mut first, &log).unwrap();
    for r in &log.records[..half] {
        first.step(r).unwrap();
    }
    // Through JSON, as a store would keep it.
    let json = serde_json::to_string(&first.snapshot()).unwrap();
    drop(first);
    let snap: Snapshot = serde_json::from_str(&json).unwrap();
    let updater = Arc::new(fleetslam_core::ekf::EkfUpdater::new(
        snap.config.landmark_kind,
        &snap.config.sensor_noise,
    ));
    let mut resumed = FastSlam::from_snapshot(snap, updater).unwrap();
    for r in &log.records[half..] {
        resumed.step(r).unwrap();
    }
    assert_same_state(&resumed.snapshot(), &whole.snapshot());
}

/// Unknown association (maps with spatial indexes), restored through JSON: the node pool
/// writes what the particles share once and the restored filter shares it again (written
/// anew, it gives the same text), and it continues bit for bit; a snapshot in the format
/// before the pool (each particle's map whole) restores the same particles and continues to
/// the same ones.
#[test]
fn snapshots_keep_the_maps_sharing_and_old_ones_still_restore() {
    let sim = small_sim(3, 20.0, 11, |c| c.with_ids = false);
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    assert_eq!(cfg.association, Association::Unknown);
    cfg.particles = 60;
    cfg.seed = 3;
    // The sharing bound below was measured with the sightings weighing the sampled poses
    // only (the default without ids since session 25 also refines 2.0's proposal with them,
    // and there this run shares 1.18 times: 969 landmarks written for 1,140 held). Which
    // particles survive resampling is a draw; the pool is what this test checks.
    cfg.sightings_in_proposal = Some(false);
    let mut log = sim.log.clone();
    log.sort();
    let half = log.records.len() / 2;
    let updater = || {
        Arc::new(fleetslam_core::ekf::EkfUpdater::new(
            cfg.landmark_kind,
            &cfg.sensor_noise,
        ))
    };

    let mut whole = FastSlam::new(cfg.clone()).unwrap();
    fleetslam_data::run::add_header_robots(&mut whole, &log).unwrap();
    for r in &log.records[..half] {
        whole.step(r).unwrap();
    }
    let snap = whole.snapshot();
    assert!(snap.stats.resamples > 0, "the run must resample");
    let json = serde_json::to_string(&snap).unwrap();
    let value: serde_json::Value = serde_json::from_str(&json).unwrap();
    let pool: fleetslam_core::map::MapPool =
        serde_json::from_value(value["map_nodes"].clone()).unwrap();
    let pooled = pool.landmarks();
    let held: usize = snap.particles.iter().map(|p| p.map.len()).sum();
    assert!(
        pooled as f64 * POOL_SHARE_BOUND < held as f64,
        "the pool holds {pooled} landmarks for the particles' {held}"
    );

    // The format before the pool: every particle's map as its list of slots.
    let mut old = value.clone();
    old.as_object_mut().unwrap().remove("map_nodes");
    for (p, particle) in old["particles"]
        .as_array_mut()
        .unwrap()
        .iter_mut()
        .zip(&snap.particles)
    {
        let p = p.as_object_mut().unwrap();
        p.remove("map_ref");
        p.insert("map".into(), serde_json::to_value(&particle.map).unwrap());
    }

    let restored: Snapshot = serde_json::from_str(&json).unwrap();
    assert_eq!(serde_json::to_string(&restored).unwrap(), json);
    let mut resumed = FastSlam::from_snapshot(restored, updater()).unwrap();
    let from_old: Snapshot = serde_json::from_value(old).unwrap();
    assert!(from_old.particles == snap.particles);
    let mut resumed_old = FastSlam::from_snapshot(from_old, updater()).unwrap();
    for r in &log.records[half..] {
        whole.step(r).unwrap();
        resumed.step(r).unwrap();
        resumed_old.step(r).unwrap();
    }
    assert_same_state(&resumed.snapshot(), &whole.snapshot());
    assert!(resumed_old.particles() == whole.particles());
    assert!(resumed_old.robot_particles() == whole.robot_particles());
    assert_eq!(
        format!("{:?}", resumed_old.estimate()),
        format!("{:?}", whole.estimate())
    );
}

/// How many times fewer landmarks the pool of the test above must write than its particles
/// hold: measured 582 written for 1,140 held (1.96 times fewer; with the ChaCha8 streams of
/// sessions 1-16, 531: which particles survive resampling is a draw).
const POOL_SHARE_BOUND: f64 = 1.9;

#[test]
fn different_seeds_differ() {
    let sim = small_sim(2, 10.0, 3, |_| {});
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 50;
    let (a, _) = run_with_threads(&sim.log, &cfg, 1);
    cfg.seed = 1;
    let (b, _) = run_with_threads(&sim.log, &cfg, 1);
    assert!(
        a.particles != b.particles,
        "different seeds gave the same particles"
    );
}

/// The steps' work items are compiled for the CPU's instruction set (AVX2 where it has it)
/// and for the baseline: both give the same bits, for each measurement model, association
/// and FastSLAM version (2.0's proposal, 1.0's sampling, the unknown association's search).
#[test]
fn the_instruction_set_changes_no_bit() {
    // On x86_64 the comparison needs a CPU with AVX2 and FMA (the test machines have them);
    // without them both filters would run the baseline.
    #[cfg(target_arch = "x86_64")]
    assert!(
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma"),
        "this CPU lacks AVX2 or FMA: the dispatched and the baseline steps would be the same code"
    );
    // The baseline filter also takes the EKF without dispatch, so the 2D updates run one
    // by one there instead of four at a time (`ekf_lanes`), as 2D 2.0's proposals do
    // (`proposal_lanes`); 1.0 weighs by the updates' likelihoods, 2.0 asks for the
    // posteriors only; the last case gates outliers (a tight bound, so that the proposal's
    // gate takes some).
    let cases: [(LandmarkKind, bool, FastSlamVersion, Option<f64>); 5] = [
        (
            LandmarkKind::RangeBearing2d,
            true,
            FastSlamVersion::V2,
            None,
        ),
        (
            LandmarkKind::RangeBearing2d,
            false,
            FastSlamVersion::V2,
            None,
        ),
        (
            LandmarkKind::RangeBearing2d,
            true,
            FastSlamVersion::V1,
            None,
        ),
        (LandmarkKind::Point3d, false, FastSlamVersion::V1, None),
        (
            LandmarkKind::RangeBearing2d,
            true,
            FastSlamVersion::V2,
            Some(1.0),
        ),
    ];
    for (kind, with_ids, version, outlier) in cases {
        let sim = small_sim(2, 15.0, 11, |c| {
            c.kind = kind;
            c.with_ids = with_ids;
        });
        let mut cfg = FilterConfig::from_header(&sim.log.header);
        cfg.particles = 60;
        cfg.version = version;
        cfg.association_params.outlier = outlier;
        let ekf = EkfUpdater::new(cfg.landmark_kind, &cfg.sensor_noise).baseline_simd();
        let baseline = FastSlam::with_updater(cfg.clone(), Arc::new(ekf)).unwrap();
        let slam = FastSlam::new(cfg).unwrap();
        let (a, ta) = run_filter(slam, &sim.log);
        let (b, tb) = run_filter(baseline.baseline_simd(), &sim.log);
        assert!(a.stats.landmark_updates > 0 && a.stats.resamples > 0);
        assert_eq!(
            a.stats.outliers > 0,
            outlier.is_some(),
            "outliers {}",
            a.stats.outliers
        );
        assert_same_state(&a, &b);
        assert!(ta == tb, "trajectories differ ({kind:?}, ids {with_ids})");
    }
}
