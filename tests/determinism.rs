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
/// hold: measured 585 written for 1,140 held (1.95 times fewer). Which particles survive
/// resampling is a draw: with the robots' sightings kept out of 2.0's proposal (the
/// default without ids before session 25) the same run writes 869 (1.31 times fewer);
/// before session 31 (glibc's elementary functions, `rand_distr`'s normal draws) those were
/// 969 and 582, and with the ChaCha8 streams of sessions 1-16, 531 without the sightings.
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

/// The filters the bit-for-bit tests below run on a 15 s simulation of 2 robots: landmark
/// kind, known ids, FastSLAM version and outlier gate (2.0's proposal, 1.0's sampling, the
/// unknown association's search; the last case gates outliers, with a bound tight enough
/// that the proposal's gate takes some).
const CASES: [(LandmarkKind, bool, FastSlamVersion, Option<f64>); 5] = [
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
    for case in CASES {
        let (kind, with_ids, _, outlier) = case;
        let (sim, cfg) = case_setup(case);
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

/// [`CASES`]' simulation and filter configuration.
fn case_setup(
    (kind, with_ids, version, outlier): (LandmarkKind, bool, FastSlamVersion, Option<f64>),
) -> (fleetslam_data::sim::Simulated, FilterConfig) {
    let sim = small_sim(2, 15.0, 11, |c| {
        c.kind = kind;
        c.with_ids = with_ids;
    });
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 60;
    cfg.version = version;
    cfg.association_params.outlier = outlier;
    (sim, cfg)
}

/// The cases [`the_c_librarys_cpu_variants_change_no_bit`] also runs with the learned
/// updater (its measurement frame computes logarithms, exponentials and rotations of its
/// own, in both measurement models).
/// They are [`CASES`]' first (2D, ids, 2.0) and fourth (3D points, no ids, 1.0).
const LEARNED_CASES: [(LandmarkKind, bool, FastSlamVersion, Option<f64>); 2] = [CASES[0], CASES[3]];

/// A learned updater's model with seeded weights instead of trained ones (small, tanh
/// hidden layers, the `line_of_sight` layout): the bits a filter gets from it depend on the
/// updater's arithmetic, not on how good the network is, and it needs no training (burn).
fn seeded_model(
    kind: LandmarkKind,
    noise: fleetslam_core::sensor::SensorNoise,
    id: &str,
) -> fleetslam_learned::MlpModel {
    use fleetslam_learned::model::{DenseLayer, MODEL_FORMAT, MODEL_FORMAT_VERSION, Normalization};
    use fleetslam_learned::{Activation, InputLayout};
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let layout = InputLayout::LineOfSight;
    let (n_in, n_out) = layout.dims(kind);
    let layers = DenseLayer::uniform_stack(&[n_in, 12, 12, n_out], 0.3, 0.1, &mut rng);
    let unit = |n: usize| Normalization {
        mean: vec![0.0; n],
        std: vec![1.0; n],
        min: Vec::new(),
        max: Vec::new(),
    };
    fleetslam_learned::MlpModel {
        format: MODEL_FORMAT.into(),
        format_version: MODEL_FORMAT_VERSION,
        id: id.into(),
        kind,
        layout,
        layout_version: InputLayout::VERSION,
        preset: "seeded".into(),
        noise,
        activation: Activation::Tanh,
        covariance: Default::default(),
        input_norm: unit(n_in),
        output_norm: unit(n_out),
        layers,
        metadata: serde_json::Value::Null,
    }
}

/// What [`the_c_librarys_cpu_variants_change_no_bit`] compares between two processes: a
/// hash of each simulated log, filter state and trajectory of [`CASES`], of
/// [`LEARNED_CASES`] with the learned updater and of a robot that joins a simulated run at
/// an unknown pose (the localizer), one line each; and a last line
/// with the hash of the C library's own `exp` over 200,000 arguments.
fn digests() -> Vec<String> {
    use std::hash::{DefaultHasher, Hash, Hasher};
    let hash = |text: &str| {
        let mut h = DefaultHasher::new();
        text.hash(&mut h);
        format!("{:016x}", h.finish())
    };
    let mut lines = Vec::new();
    for case in CASES {
        let (sim, cfg) = case_setup(case);
        let (state, traj) = run_filter(FastSlam::new(cfg).unwrap(), &sim.log);
        lines.push(format!(
            "{case:?}: log {} state {} trajectories {}",
            hash(&fleetslam_suite::to_ndjson(&sim.log)),
            hash(&state_text(&state)),
            hash(&traj)
        ));
    }
    let sim = small_sim(3, 20.0, 7, |_| {});
    let mut cfg = FilterConfig::from_header(&sim.log.header);
    cfg.particles = 60;
    let mut run =
        fleetslam_localize::LateJoinSlam::new(cfg, fleetslam_localize::LocalizeConfig::default())
            .unwrap();
    let join = fleetslam_data::run::JoinOptions {
        unknown: vec![fleetslam_data::sim::SimConfig::robot_id(2)],
        join_at: Some(5.0),
        ..Default::default()
    };
    let out = fleetslam_data::run::run_log_joining(
        &mut run,
        &sim.log,
        TrajectoryEstimate::Mean,
        &join,
        |_, _| {},
    )
    .unwrap();
    let joined = out.metrics.joiners[0].joined_at;
    assert!(joined.is_some(), "the late joiner never localized");
    lines.push(format!(
        "late joiner joined at {joined:?}: state {} trajectories {}",
        hash(&state_text(&run.slam().snapshot())),
        hash(&format!("{:?}", out.estimate.trajectories))
    ));
    for case in LEARNED_CASES {
        let (sim, mut cfg) = case_setup(case);
        cfg.updater = "seeded".into();
        let model = seeded_model(cfg.landmark_kind, cfg.sensor_noise, &cfg.updater);
        let mlp = fleetslam_learned::MlpUpdater::for_run(model, &cfg).unwrap();
        let (state, traj) = run_filter(
            FastSlam::with_updater(cfg, Arc::new(mlp)).unwrap(),
            &sim.log,
        );
        assert!(state.stats.landmark_updates > 0 && state.stats.resamples > 0);
        lines.push(format!(
            "{case:?} with the learned updater: state {} trajectories {}",
            hash(&state_text(&state)),
            hash(&traj)
        ));
    }
    let glibc: String = (0..200_000)
        .map(|k| format!("{:x}", (k as f64 * 1e-4 - 10.0).exp().to_bits()))
        .collect();
    lines.push(format!("the C library's exp: {}", hash(&glibc)));
    lines
}

/// The same seed and log give the same bits on every CPU: glibc picks an FMA variant of
/// `exp`, `log`, `sin`, `cos`, ... on CPUs that have FMA, which rounds some arguments
/// differently from its baseline, so the filter computes with `fleetslam_core::math`
/// (libm) instead. A child process of this test, with
/// `GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA` (glibc's baseline functions), simulates and
/// filters [`CASES`], [`LEARNED_CASES`] with the learned updater and a late joiner and must
/// give this process's bits (the learned updater's `f64` functions from the standard
/// library gave other bits in both of its cases); that its C
/// library's `exp` does give other bits shows that the tunable took effect (on x86-64 with
/// FMA, as the test machines are).
#[test]
fn the_c_librarys_cpu_variants_change_no_bit() {
    const CHILD: &str = "FLEETSLAM_DETERMINISM_CHILD";
    if std::env::var_os(CHILD).is_some() {
        println!("<digests>\n{}\n</digests>", digests().join("\n"));
        return;
    }
    let child = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "the_c_librarys_cpu_variants_change_no_bit",
            "--exact",
            "--nocapture",
        ])
        .env(CHILD, "1")
        .env("GLIBC_TUNABLES", "glibc.cpu.hwcaps=-AVX2,-FMA")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&child.stdout);
    assert!(child.status.success(), "the child failed:\n{stdout}");
    let theirs: Vec<&str> = stdout
        .split("<digests>\n")
        .nth(1)
        .and_then(|t| t.split("\n</digests>").next())
        .unwrap_or_else(|| panic!("no digests in the child's output:\n{stdout}"))
        .lines()
        .collect();
    let ours = digests();
    let (ours_libc, ours) = ours.split_last().unwrap();
    let (theirs_libc, theirs) = theirs.split_last().unwrap();
    #[cfg(target_arch = "x86_64")]
    let fma = std::arch::is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    let fma = false;
    if fma {
        assert_ne!(
            ours_libc, theirs_libc,
            "the tunable did not change the C library's exp: the test compares nothing"
        );
    }
    assert_eq!(
        ours, theirs,
        "the filter's bits depend on the C library's variant"
    );
}
