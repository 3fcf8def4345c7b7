//! The filter's accuracy over seeds, as the README reports it:
//!
//! ```sh
//! cargo run --release --example filter_seeds -- mrclam [--no-ids] [--seeds 1-10] \
//!     [--particles 1000] [--version 2] [--duration S] [--dataset DIR] [--windows S]
//! cargo run --release --example filter_seeds -- control-noise [--seeds 1-5] \
//!     [--particles 100] [--duration 60]
//! cargo run --release --example filter_seeds -- sims [--seeds 1-5] [--particles 100]
//! cargo run --release --example filter_seeds -- late-join [--seeds 1-5] [--particles 200] \
//!     [--duration 200] [--join-after 60]
//! cargo run --release --example filter_seeds -- range-noise [--seeds 1-5] [--particles 100]
//! cargo run --release --example filter_seeds -- clusters [--seeds 1-5] [--particles 200]
//! cargo run --release --example filter_seeds -- victoria [--seeds 1] [--particles 100] \
//!     [--duration S] [--dataset DIR] [--windows S]
//! cargo run --release --example filter_seeds -- speed [--seeds 1] [--particles N]
//! cargo run --release --example filter_seeds -- snapshot [--seeds 1] [--particles N] \
//!     [--duration S]
//! ```
//!
//! `mrclam` runs MRCLAM Dataset 6 (all five robots) once per seed and prints team ATE, RPE
//! and the landmark figures (without ids: against the truth's 6 landmark groups, each
//! matched within 0.3 m), then their mean and worst; with `--windows S`, also each seed's
//! team error per S seconds before and after that window's own SE(2) fit (a drift of the
//! whole team's frame, or the robots' own error). `control-noise` runs the simulated
//! high-control-noise scenario with FastSLAM 1.0 and 2.0 per seed and prints ATE and
//! landmark NEES. `sims` checks the settings tuned on MRCLAM on simulations they were not
//! tuned on (other noise, landmark densities, fields of view, motion), FastSLAM 2.0 with and
//! without deferred pose sampling and 1.0, and prints team ATE per scenario. `range-noise`
//! checks the range noise that grows with the range (`sensor_noise.range_per_m`, which
//! MRCLAM's header suggests) on simulations whose sensor has such noise: the filter told the
//! true model against one told a constant range noise. `late-join` runs MRCLAM with robot 5's
//! start forgotten and its records before `--join-after` seconds dropped, and prints when it
//! joined and its error after joining. `clusters`
//! checks the minimum landmark separation that MRCLAM's `--no-ids` header suggests (half the
//! smallest distance between landmark groups) on simulations without ids whose landmarks
//! stand in groups of 2-3 features, as MRCLAM's barcodes do, at other group spacings,
//! sensors and motion, against the filter's default separation. `victoria` runs
//! Victoria Park (unknown association) and prints the ATE against GPS after SE(2) alignment
//! per seed, then their mean, median and worst and the seeds above 4 m;
//! with `--windows S`, also each seed's run per S seconds: the error against GPS (after the
//! whole run's alignment), the particles' spread, the smallest effective sample size, the
//! resamples and the observations per record.
//! `speed` prints the filter's cost (issue 13): wall time per particle and record and per
//! particle and landmark observation on a simulated log with 6 or more observations per
//! record (known ids, 100 and 1,000 particles), MRCLAM Dataset 6 with known ids at 1,000
//! particles as a multiple of real time (and a second run of it, its steps timed by the
//! kind of record), and Victoria Park (unknown association, 100 particles); on all the rayon
//! threads (`RAYON_NUM_THREADS` sets them). With `--particles
//! N`, only the simulated log, at N particles (a workload small enough for callgrind).
//! `snapshot` runs MRCLAM Dataset 6 with and without ids (1,000 particles) and Victoria Park
//! (100) and prints their final snapshots' size, write time and read-and-restore time with
//! the maps in a node pool and, as before it, each particle's map whole.

/// The `fleetslam` binary's allocator (crates/fleetslam-cli/src/main.rs), so that the figures
/// are the binary's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

use fleetslam_core::config::{DeferSampling, FastSlamVersion};
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::SensorRange;
use fleetslam_core::motion::{MotionModel, MotionNoise};
use fleetslam_core::sensor::SensorNoise;
use fleetslam_data::evaluate::{EvalOptions, evaluate};
use fleetslam_data::formats::Truth;
use fleetslam_data::import::{VictoriaOptions, import_victoria_park};
use fleetslam_data::run::{JoinOptions, TrajectoryEstimate, run_log, run_log_joining};
use fleetslam_data::sim::{SimConfig, simulate};
use fleetslam_localize::{LateJoinSlam, LocalizeConfig};
use fleetslam_suite::experiments::{
    control_noise, experiment_config, first_record_time, mrclam, mrclam_eval_options, run,
    run_and_evaluate,
};
use std::path::PathBuf;
use std::time::Instant;

fn usage() -> ! {
    eprintln!(
        "usage: filter_seeds mrclam|control-noise|sims|range-noise|clusters|victoria|speed|snapshot [--no-ids] [--seeds A-B|a,b,c] \
         [--particles N] [--version 1|2] [--duration S] [--dataset DIR] [--windows S]"
    );
    std::process::exit(2)
}

fn parse_seeds(s: &str) -> Vec<u64> {
    if let Some((a, b)) = s.split_once('-') {
        let (a, b): (u64, u64) = (
            a.parse().unwrap_or_else(|_| usage()),
            b.parse().unwrap_or_else(|_| usage()),
        );
        (a..=b).collect()
    } else {
        s.split(',')
            .map(|x| x.parse().unwrap_or_else(|_| usage()))
            .collect()
    }
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

fn max(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::NEG_INFINITY, f64::max)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(what) = args.first().cloned() else {
        usage()
    };
    let mut no_ids = false;
    let mut seeds: Option<Vec<u64>> = None;
    let mut particles: Option<usize> = None;
    let mut versions = vec![FastSlamVersion::V1, FastSlamVersion::V2];
    let mut duration: Option<f64> = None;
    let mut dataset = PathBuf::from("../shared/datasets/mrclam-dataset6");
    let mut odometry_delay: Option<f64> = None;
    let mut windows: Option<f64> = None;
    let mut join_after = 60.0;
    let mut it = args[1..].iter();
    while let Some(a) = it.next() {
        let mut val = || it.next().cloned().unwrap_or_else(|| usage());
        match a.as_str() {
            "--no-ids" => no_ids = true,
            "--seeds" => seeds = Some(parse_seeds(&val())),
            "--particles" => particles = Some(val().parse().unwrap_or_else(|_| usage())),
            "--version" => {
                versions = match val().as_str() {
                    "1" => vec![FastSlamVersion::V1],
                    "2" => vec![FastSlamVersion::V2],
                    _ => usage(),
                }
            }
            "--duration" => duration = Some(val().parse().unwrap_or_else(|_| usage())),
            "--dataset" => dataset = PathBuf::from(val()),
            "--odometry-delay" => odometry_delay = Some(val().parse().unwrap_or_else(|_| usage())),
            "--windows" => windows = Some(val().parse().unwrap_or_else(|_| usage())),
            "--join-after" => join_after = val().parse().unwrap_or_else(|_| usage()),
            _ => usage(),
        }
    }
    match what.as_str() {
        "mrclam" => {
            let version = *versions.last().expect("one version");
            let seeds = seeds.unwrap_or_else(|| (1..=10).collect());
            let particles = particles.unwrap_or(1000);
            let imp = mrclam(&dataset, no_ids, duration, odometry_delay);
            let opts = mrclam_eval_options(no_ids);
            println!(
                "MRCLAM Dataset 6, {}, {particles} particles, FastSLAM {:?}{}",
                if no_ids { "no ids" } else { "known ids" },
                version,
                duration.map_or(String::new(), |d| format!(", first {d} s")),
            );
            let (mut ates, mut rpes, mut lms) = (Vec::new(), Vec::new(), Vec::new());
            for &seed in &seeds {
                let t = Instant::now();
                let out = run(&imp.log, particles, seed, version);
                let ev = evaluate(&out.estimate, &imp.truth, out.metrics.shared_frame, &opts);
                let (m, est) = (&out.metrics, &out.final_estimate);
                let tm = &ev.team;
                println!(
                    "seed {seed:>2}: team ATE {:.3} m, RPE {:.3} m / {:.2} deg, landmarks \
                     {}/{} matched{} (worst {:.3} m, rmse {:.3} m), spurious {}, optimal rmse \
                     {:.3} m; created {}, removed {}; {:.0} s",
                    tm.ate_rmse,
                    tm.rpe_rmse,
                    tm.rpe_heading_rmse.to_degrees(),
                    tm.landmarks_matched,
                    tm.landmarks_matched + tm.landmarks_missed,
                    if no_ids { " groups" } else { "" },
                    tm.landmark_match_max.unwrap_or(f64::NAN),
                    tm.landmark_rmse.unwrap_or(f64::NAN),
                    tm.landmarks_spurious,
                    tm.landmark_rmse_optimal.unwrap_or(f64::NAN),
                    m.landmarks_created,
                    m.landmarks_removed,
                    t.elapsed().as_secs_f64(),
                );
                if est.robots.iter().any(|r| r.odometry_scale != [1.0; 2]) {
                    let scales: Vec<String> = est
                        .robots
                        .iter()
                        .map(|r| {
                            format!(
                                "{} {:.3}/{:.3}",
                                r.id, r.odometry_scale[0], r.odometry_scale[1]
                            )
                        })
                        .collect();
                    println!(
                        "         odometry scales (distance/rotation): {}",
                        scales.join(", ")
                    );
                }
                if let Some(w) = windows {
                    drift_windows(&out.estimate, &imp.truth, w);
                }
                ates.push(tm.ate_rmse);
                rpes.push(tm.rpe_rmse);
                lms.push(tm.landmark_rmse_optimal.unwrap_or(f64::NAN));
            }
            println!(
                "mean team ATE {:.3} m (worst seed {:.3} m), mean RPE {:.3} m, mean optimal \
                 landmark rmse {:.3} m over {} seeds",
                mean(&ates),
                max(&ates),
                mean(&rpes),
                mean(&lms),
                seeds.len()
            );
        }
        "control-noise" => {
            let seeds = seeds.unwrap_or_else(|| (1..=5).collect());
            let particles = particles.unwrap_or(100);
            let duration = duration.unwrap_or(60.0);
            println!(
                "high control noise, 1 robot, 38 landmarks, {duration} s, {particles} particles"
            );
            for version in versions {
                let (mut ates, mut nees, mut fit_nees) = (Vec::new(), Vec::new(), Vec::new());
                for &seed in &seeds {
                    let (log, truth) = control_noise(seed, duration);
                    let opts = Default::default();
                    let (ev, m, _) =
                        run_and_evaluate(&log, &truth, particles, seed, version, &opts);
                    let t = &ev.team;
                    println!(
                        "FastSLAM {version:?} seed {seed}: ATE {:.3} m, landmark rmse {:.3} m, \
                         landmark NEES {:.2} (dimension 2); after the map's own SE(2) fit \
                         rmse {:.3} m, NEES {:.2}; proposal fallbacks {}",
                        t.ate_rmse,
                        t.landmark_rmse.unwrap_or(f64::NAN),
                        t.landmark_nees.unwrap_or(f64::NAN),
                        t.landmark_rmse_map_fit.unwrap_or(f64::NAN),
                        t.landmark_nees_map_fit.unwrap_or(f64::NAN),
                        m.proposal_fallbacks,
                    );
                    ates.push(t.ate_rmse);
                    nees.push(t.landmark_nees.unwrap_or(f64::NAN));
                    fit_nees.push(t.landmark_nees_map_fit.unwrap_or(f64::NAN));
                }
                println!(
                    "FastSLAM {version:?}: mean ATE {:.3} m (worst {:.3}), mean landmark NEES \
                     {:.2}, after the map fit {:.2} (worst seed {:.2})",
                    mean(&ates),
                    max(&ates),
                    mean(&nees),
                    mean(&fit_nees),
                    max(&fit_nees),
                );
            }
        }
        "sims" => {
            let seeds = seeds.unwrap_or_else(|| (1..=5).collect());
            let particles = particles.unwrap_or(100);
            println!("simulations not tuned on, {particles} particles, seeds {seeds:?}");
            for (name, make) in scenarios() {
                let mut line = format!("{name:<44}");
                for (label, version, defer) in [
                    ("2.0", FastSlamVersion::V2, true),
                    ("2.0 no defer", FastSlamVersion::V2, false),
                    ("1.0", FastSlamVersion::V1, false),
                ] {
                    let mut ates = Vec::new();
                    for &seed in &seeds {
                        let sim = simulate(&make(seed)).expect("valid simulation");
                        let mut cfg = experiment_config(&sim.log.header);
                        cfg.particles = particles;
                        cfg.seed = seed;
                        cfg.version = version;
                        cfg.defer_pose_sampling = if defer {
                            DeferSampling::Auto
                        } else {
                            DeferSampling::Never
                        };
                        let mut slam = FastSlam::new(cfg).expect("valid configuration");
                        let out = run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {})
                            .expect("run");
                        let ev = evaluate(&out.estimate, &sim.truth, true, &Default::default());
                        ates.push(ev.team.ate_rmse);
                    }
                    line += &format!(
                        " | {label}: mean {:.3} worst {:.3}",
                        mean(&ates),
                        max(&ates)
                    );
                }
                println!("{line}");
            }
        }
        "late-join" => {
            // Robot 5 forgets its start and joins `--join-after` s into the log (default 60),
            // as tests/late_joiner.rs does on its 200-s slice at 200 particles.
            let seeds = seeds.unwrap_or_else(|| (1..=5).collect());
            let particles = particles.unwrap_or(200);
            let imp = mrclam(&dataset, false, duration.or(Some(200.0)), odometry_delay);
            let t_start = first_record_time(&imp.log);
            let join_at = t_start + join_after;
            println!(
                "MRCLAM Dataset 6, robot 5 joins {:.0} s in, {particles} particles{}",
                join_at - t_start,
                duration.map_or(", first 200 s".to_string(), |d| format!(", first {d} s"))
            );
            let (mut late, mut r5s, mut teams) = (Vec::new(), Vec::new(), Vec::new());
            for &seed in &seeds {
                let mut cfg = experiment_config(&imp.log.header);
                cfg.particles = particles;
                cfg.seed = seed;
                let mut run = LateJoinSlam::new(cfg, LocalizeConfig::default()).expect("config");
                let jo = JoinOptions {
                    unknown: vec!["5".into()],
                    join_at: Some(join_at),
                    localize: LocalizeConfig::default(),
                };
                let out =
                    run_log_joining(&mut run, &imp.log, TrajectoryEstimate::Mean, &jo, |_, _| {})
                        .expect("run");
                let joined = out.metrics.joiners[0].joined_at.map(|t| t - join_at);
                let ev = evaluate(&out.estimate, &imp.truth, true, &Default::default());
                let r5 = ev.robots.get("5").map_or(f64::NAN, |r| r.ate_rmse);
                println!(
                    "seed {seed:>2}: joined {} s after join_at, robot 5 after joining ATE \
                     {r5:.3} m, team ATE {:.3} m",
                    joined.map_or("never".into(), |j| format!("{j:.1}")),
                    ev.team.ate_rmse
                );
                late.push(joined.unwrap_or(f64::NAN));
                r5s.push(r5);
                teams.push(ev.team.ate_rmse);
            }
            println!(
                "mean: joined {:.1} s (latest {:.1} s), robot 5 {:.3} m (worst {:.3} m), team \
                 {:.3} m over {} seeds",
                mean(&late),
                max(&late),
                mean(&r5s),
                max(&r5s),
                mean(&teams),
                seeds.len()
            );
        }
        "range-noise" => {
            let seeds = seeds.unwrap_or_else(|| (1..=5).collect());
            let particles = particles.unwrap_or(100);
            println!(
                "range noise that grows with the range, {particles} particles, 120 s, seeds \
                 {seeds:?}: team ATE mean (worst) of the filter told the true model \
                 (range_per_m), the true model with twice its growth, and a constant range \
                 noise, the true one at half and at the whole sensor range"
            );
            for (name, make) in range_noise_scenarios() {
                let mut line = format!("{name:<52}");
                let probe = make(0);
                let true_noise = probe.true_sensor_noise;
                let max_range = probe.sensor_range.max_range;
                for (label, at) in [
                    ("true", None),
                    ("growth x2", Some(-2.0)),
                    ("half", Some(0.5)),
                    ("whole", Some(1.0)),
                ] {
                    let mut ates = Vec::new();
                    for &seed in &seeds {
                        let sim = simulate(&make(seed)).expect("valid simulation");
                        let mut cfg = experiment_config(&sim.log.header);
                        cfg.particles = particles;
                        cfg.seed = seed;
                        match at {
                            // The growth doubled, as MRCLAM's header suggests twice the
                            // growth measured there.
                            Some(f) if f < 0.0 => cfg.sensor_noise.range_per_m *= -f,
                            Some(at) => {
                                cfg.sensor_noise.range = true_noise.range_std_at(at * max_range);
                                cfg.sensor_noise.range_per_m = 0.0;
                            }
                            None => {}
                        }
                        let mut slam = FastSlam::new(cfg).expect("valid configuration");
                        let out = run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {})
                            .expect("run");
                        let ev = evaluate(&out.estimate, &sim.truth, true, &Default::default());
                        ates.push(ev.team.ate_rmse);
                    }
                    line += &format!(" | {label}: {:.3} ({:.3})", mean(&ates), max(&ates));
                }
                println!("{line}");
            }
        }
        "clusters" => {
            let seeds = seeds.unwrap_or_else(|| (1..=5).collect());
            let particles = particles.unwrap_or(200);
            let duration = duration.unwrap_or(120.0);
            println!(
                "clustered landmarks without ids, {particles} particles, {duration} s, seeds \
                 {seeds:?}; per setting: team ATE mean (worst), groups mapped within 0.3 m \
                 (fewest), spurious landmarks (most)"
            );
            let opts = EvalOptions {
                group_within: Some(0.3),
                landmark_match_radius: 0.3,
                ..EvalOptions::default()
            };
            for (name, spacing, make) in cluster_scenarios(duration) {
                // Group centres stand at least 0.8 grid spacings apart: the suggestion is
                // half of that, as MRCLAM's header suggests half its groups' 1.8 m.
                let suggested = 0.4 * spacing;
                let mut line = format!("{name:<52}");
                for (label, separation) in [
                    ("default 0.45 m", None),
                    ("half the spacing", Some(suggested)),
                ] {
                    let (mut ates, mut groups, mut spurious) = (Vec::new(), Vec::new(), Vec::new());
                    let mut total = 0;
                    for &seed in &seeds {
                        let mut sc = make(seed);
                        sc.landmark_separation = separation;
                        let sim = simulate(&sc).expect("valid simulation");
                        let mut cfg = experiment_config(&sim.log.header);
                        cfg.particles = particles;
                        cfg.seed = seed;
                        let mut slam = FastSlam::new(cfg).expect("valid configuration");
                        let out = run_log(&mut slam, &sim.log, TrajectoryEstimate::Mean, |_, _| {})
                            .expect("run");
                        let ev = evaluate(&out.estimate, &sim.truth, true, &opts);
                        ates.push(ev.team.ate_rmse);
                        groups.push(ev.team.landmarks_matched);
                        total = ev.team.landmarks_matched + ev.team.landmarks_missed;
                        spurious.push(ev.team.landmarks_spurious);
                    }
                    line += &format!(
                        " | {label} ({:.2} m): {:.3} ({:.3}) m, {}/{total}, {}",
                        separation.unwrap_or(0.45),
                        mean(&ates),
                        max(&ates),
                        groups.iter().min().copied().unwrap_or(0),
                        spurious.iter().max().copied().unwrap_or(0),
                    );
                }
                println!("{line}");
            }
        }
        "victoria" => {
            let seeds = seeds.unwrap_or_else(|| vec![1]);
            let particles = particles.unwrap_or(100);
            if dataset.ends_with("mrclam-dataset6") {
                dataset = PathBuf::from("../shared/datasets/victoria-park");
            }
            let opts = VictoriaOptions {
                duration,
                ..Default::default()
            };
            let imp = import_victoria_park(&dataset, &opts).expect("import Victoria Park");
            println!("Victoria Park, {particles} particles, FastSLAM 2.0, unknown association");
            let mut ates = Vec::new();
            for &seed in &seeds {
                let t = Instant::now();
                let mut cfg = experiment_config(&imp.log.header);
                cfg.particles = particles;
                cfg.seed = seed;
                let mut slam = FastSlam::new(cfg).expect("valid configuration");
                let out =
                    run_log(&mut slam, &imp.log, TrajectoryEstimate::Mean, |_, _| {}).expect("run");
                let ev = evaluate(&out.estimate, &imp.truth, false, &Default::default());
                println!(
                    "seed {seed}: ATE against GPS {:.3} m after SE(2) alignment, {} landmarks \
                     (created {}, removed {}, merged {}); {:.0} s",
                    ev.team.ate_rmse,
                    out.estimate.landmarks.len(),
                    out.metrics.landmarks_created,
                    out.metrics.landmarks_removed,
                    out.metrics.landmarks_merged,
                    t.elapsed().as_secs_f64()
                );
                if let Some(w) = windows {
                    victoria_windows(&imp, slam.config().clone(), &ev, w);
                }
                ates.push(ev.team.ate_rmse);
            }
            let mut sorted = ates.clone();
            sorted.sort_by(f64::total_cmp);
            let median = (sorted[(sorted.len() - 1) / 2] + sorted[sorted.len() / 2]) / 2.0;
            println!(
                "ATE against GPS over {} seeds: mean {:.3} m, median {median:.3} m, worst {:.3} m, \
                 {} seeds above {VICTORIA_WORSE} m",
                ates.len(),
                mean(&ates),
                max(&ates),
                ates.iter().filter(|&&a| a > VICTORIA_WORSE).count()
            );
        }
        "snapshot" => {
            let seed = seeds.and_then(|s| s.first().copied()).unwrap_or(1);
            println!(
                "snapshots at the end of a run (seed {seed}): the node pool against each \
                 particle's map written whole (the format before it)"
            );
            let mrclam_ids = mrclam(&dataset, false, duration, odometry_delay);
            let mrclam_no_ids = mrclam(&dataset, true, duration, odometry_delay);
            let vp = import_victoria_park(
                &PathBuf::from("../shared/datasets/victoria-park"),
                &VictoriaOptions {
                    duration,
                    ..Default::default()
                },
            )
            .expect("import Victoria Park");
            let p = particles.unwrap_or(1000);
            for (name, log, n) in [
                ("MRCLAM Dataset 6, known ids", &mrclam_ids.log, p),
                ("MRCLAM Dataset 6, no ids", &mrclam_no_ids.log, p),
                ("Victoria Park", &vp.log, particles.unwrap_or(100)),
            ] {
                let mut cfg = experiment_config(&log.header);
                cfg.particles = n;
                cfg.seed = seed;
                let mut slam = FastSlam::new(cfg).expect("valid configuration");
                run_log(&mut slam, log, TrajectoryEstimate::Mean, |_, _| {}).expect("run");
                snapshot_sizes(name, &slam);
            }
        }
        "speed" => {
            let seed = seeds.and_then(|s| s.first().copied()).unwrap_or(1);
            println!(
                "filter speed on {} threads, seed {seed}",
                rayon::current_num_threads()
            );
            let span = |log: &fleetslam_core::log::Log| {
                let ts = log.records.iter().map(|r| r.t);
                ts.clone().fold(f64::NEG_INFINITY, f64::max) - ts.fold(f64::INFINITY, f64::min)
            };
            // Wall time of a run per particle and record, and per particle and landmark
            // observation (as metrics.json reports them).
            let timed = |log: &fleetslam_core::log::Log, particles: usize| {
                let mut cfg = experiment_config(&log.header);
                cfg.particles = particles;
                cfg.seed = seed;
                let mut slam = FastSlam::new(cfg).expect("valid configuration");
                let out =
                    run_log(&mut slam, log, TrajectoryEstimate::Mean, |_, _| {}).expect("run");
                let obs: usize = log.records.iter().map(|r| r.landmarks.len()).sum();
                let per = |n: usize| out.metrics.wall_time_s * 1e9 / (particles * n) as f64;
                (
                    out.metrics.wall_time_s,
                    per(log.records.len()),
                    per(obs),
                    state_digest(&slam),
                )
            };
            let sim = simulate(&speed_scenario(seed)).expect("valid simulation");
            let obs: usize = sim.log.records.iter().map(|r| r.landmarks.len()).sum();
            // `--particles N`: the simulated log alone, at N particles (a small workload for a
            // profiler such as callgrind).
            let counts = particles.map_or(vec![100, 1000], |n| vec![n]);
            for &particles in &counts {
                let (wall, per_record, per_obs, digest) = timed(&sim.log, particles);
                println!(
                    "simulated, known ids, {} records, {:.1} observations per record, \
                     {particles} particles: {wall:.2} s, {per_record:.0} ns per particle and \
                     record, {per_obs:.0} ns per particle and observation; state {digest:016x}",
                    sim.log.records.len(),
                    obs as f64 / sim.log.records.len() as f64,
                );
            }
            if particles.is_some() {
                return;
            }
            let imp = mrclam(&dataset, false, duration, odometry_delay);
            let (wall, per_record, per_obs, digest) = timed(&imp.log, 1000);
            println!(
                "MRCLAM Dataset 6, known ids, 1000 particles: {:.0} s of data in {wall:.2} s, \
                 {:.0} times real time; {per_record:.0} ns per particle and record, \
                 {per_obs:.0} per particle and observation; state {digest:016x}",
                span(&imp.log),
                span(&imp.log) / wall,
            );
            // Where that time goes: the same run stepped here (on a thread of rayon's pool,
            // as `run_log` steps), timed by the kind of record: neither landmark observations
            // nor sightings (2.0 moves each particle's deferred pose Gaussian), sightings only,
            // landmark observations.
            let mut cfg = experiment_config(&imp.log.header);
            cfg.particles = 1000;
            cfg.seed = seed;
            let mut slam = FastSlam::new(cfg).expect("valid configuration");
            fleetslam_data::run::add_header_robots(&mut slam, &imp.log).expect("header robots");
            let mut order: Vec<&fleetslam_core::log::Record> = imp.log.records.iter().collect();
            order.sort_by(|a, b| fleetslam_core::log::record_order(a, b));
            let mut by_kind = [(0usize, 0.0f64); 3];
            // Records without landmarks whose motion keeps the heading exactly (no rotation:
            // their particles' headings keep their sine and cosine).
            let mut unturned = 0;
            rayon::scope(|_| {
                for rec in order {
                    if slam.robot_index(&rec.robot).is_none() {
                        continue;
                    }
                    let kind = match (rec.landmarks.is_empty(), rec.robots.is_empty()) {
                        (true, true) => 0,
                        (true, false) => 1,
                        (false, _) => 2,
                    };
                    let turn = rec
                        .motion
                        .as_ref()
                        .map_or(0.0, |m| m.increment(&slam.config().ackermann).theta);
                    if kind < 2 && turn == 0.0 {
                        unturned += 1;
                    }
                    let t = Instant::now();
                    slam.step(rec).expect("step");
                    by_kind[kind].0 += 1;
                    by_kind[kind].1 += t.elapsed().as_secs_f64();
                }
            });
            let [none, sightings, landmarks] = by_kind;
            println!(
                "  its steps by record: {} without observations or sightings {:.2} s, {} with \
                 sightings only {:.2} s, {} with landmark observations {:.2} s; {unturned} of \
                 those without landmarks do not turn",
                none.0, none.1, sightings.0, sightings.1, landmarks.0, landmarks.1
            );
            let vp = import_victoria_park(
                &PathBuf::from("../shared/datasets/victoria-park"),
                &VictoriaOptions::default(),
            )
            .expect("import Victoria Park");
            let (wall, _, per_obs, digest) = timed(&vp.log, 100);
            println!(
                "Victoria Park, unknown association, 100 particles: {:.0} s of data in \
                 {wall:.2} s, {per_obs:.0} ns per particle and observation; state {digest:016x}",
                span(&vp.log)
            );
        }
        _ => usage(),
    }
}

/// A snapshot as written before the node pool: each particle's map whole.
#[derive(serde::Serialize)]
struct WholeMaps<'a> {
    config: &'a fleetslam_core::config::FilterConfig,
    robots: &'a [fleetslam_core::filter::RobotState],
    particles: &'a [fleetslam_core::filter::ParticleState],
    known_slots: &'a std::collections::BTreeMap<u32, usize>,
    step: u64,
    ess: f64,
    stats: &'a fleetslam_core::filter::FilterStats,
}

/// Prints a filter's snapshot in both formats: size, time to write, time to read and
/// restore, and landmarks written.
fn snapshot_sizes(name: &str, slam: &FastSlam) {
    let snap = slam.snapshot();
    let held: usize = snap.particles.iter().map(|p| p.map.len()).sum();
    let updater = slam.updater().clone();
    let time = |f: &mut dyn FnMut()| {
        // The best of three: the machine's other work only adds.
        (0..3)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64() * 1e3
            })
            .fold(f64::INFINITY, f64::min)
    };
    let mut pooled = Vec::new();
    let write_pooled = time(&mut || pooled = serde_json::to_vec(&snap).expect("encode"));
    let old = WholeMaps {
        config: &snap.config,
        robots: &snap.robots,
        particles: &snap.particles,
        known_slots: &snap.known_slots,
        step: snap.step,
        ess: snap.ess,
        stats: &snap.stats,
    };
    let mut whole = Vec::new();
    let write_whole = time(&mut || whole = serde_json::to_vec(&old).expect("encode"));
    let read = |data: &[u8]| {
        let s: fleetslam_core::filter::Snapshot = serde_json::from_slice(data).expect("decode");
        FastSlam::from_snapshot(s, updater.clone()).expect("restore")
    };
    let read_pooled = time(&mut || drop(read(&pooled)));
    let read_whole = time(&mut || drop(read(&whole)));
    let restored = read(&pooled);
    assert!(
        restored.particles() == slam.particles()
            && restored.robot_particles() == slam.robot_particles(),
        "restored particles differ"
    );
    let value: serde_json::Value = serde_json::from_slice(&pooled).expect("JSON");
    let pool: fleetslam_core::map::MapPool =
        serde_json::from_value(value["map_nodes"].clone()).expect("a pool");
    let in_pool = pool.landmarks();
    println!(
        "{name}, {} particles, {} landmarks in the best map: landmarks written {in_pool} \
         (pool, {} nodes) against {held}; {:.1} MB against {:.1} MB; write {write_pooled:.0} \
         against {write_whole:.0} ms; read and restore {read_pooled:.0} against \
         {read_whole:.0} ms",
        snap.particles.len(),
        slam.estimate().landmarks.len(),
        pool.len(),
        pooled.len() as f64 / 1e6,
        whole.len() as f64 / 1e6,
    );
}

/// Prints the team's error per window of `w` seconds of a run's `estimate`: unaligned,
/// after the window's own least-squares SE(2) fit onto the truth, and that fit (its
/// rotation and translation). An error that the fit removes is a drift of the whole team's
/// frame; one it leaves is the robots' own.
fn drift_windows(estimate: &Truth, truth: &Truth, w: f64) {
    let times = || estimate.trajectories.values().flatten().map(|p| p.t);
    let t0 = times().fold(f64::INFINITY, f64::min);
    let last = times().fold(f64::NEG_INFINITY, f64::max);
    println!(
        "         window (s)  team ATE (m)  after the window's fit (m)  fit rotation (deg), translation (m)"
    );
    let fit_opts = EvalOptions {
        alignment: Some(fleetslam_data::evaluate::Alignment::Se2),
        ..Default::default()
    };
    let mut start = t0;
    while start < last {
        let end = start + w;
        let part = Truth {
            trajectories: estimate
                .trajectories
                .iter()
                .map(|(robot, points)| {
                    let inside = points.iter().filter(|p| p.t >= start && p.t < end);
                    (robot.clone(), inside.cloned().collect())
                })
                .collect(),
            landmarks: Vec::new(),
        };
        let raw = evaluate(&part, truth, true, &Default::default());
        if raw.team.matched_poses > 0 {
            let fit = evaluate(&part, truth, true, &fit_opts);
            let [tx, ty, phi] = fit.transform.unwrap_or([f64::NAN; 3]);
            println!(
                "         {:>4.0}-{:<4.0}      {:>6.3}        {:>6.3}                      {:>6.1}, ({:.2}, {:.2})",
                start - t0,
                end - t0,
                raw.team.ate_rmse,
                fit.team.ate_rmse,
                phi.to_degrees(),
                tx,
                ty
            );
        }
        start = end;
    }
}

/// A Victoria Park run this far off GPS (m) is counted in `victoria`'s summary, as the
/// tail of bad runs (over seeds 1-80 the median run is 2.37 m off, the worst 5.58 m).
const VICTORIA_WORSE: f64 = 4.0;

/// Runs Victoria Park again with `cfg` (the same bits as the run `ev` evaluated) and prints
/// it per window of `w` seconds: the error against GPS after `ev`'s alignment (the whole
/// run's SE(2) fit), the particles' largest spread about their mean position (the weighted
/// RMS distance), the smallest effective sample size, the resamples and the landmark
/// observations per record. An error far above the spread is a filter that is sure of a
/// wrong pose.
fn victoria_windows(
    imp: &fleetslam_data::import::Imported,
    cfg: fleetslam_core::config::FilterConfig,
    ev: &fleetslam_data::evaluate::Evaluation,
    w: f64,
) {
    let mut slam = FastSlam::new(cfg).expect("valid configuration");
    fleetslam_data::run::add_header_robots(&mut slam, &imp.log).expect("the car starts");
    let gps = &imp.truth.trajectories[fleetslam_data::import::victoria::ROBOT];
    let [tx, ty, phi] = ev.transform.unwrap_or([0.0; 3]);
    let (s, c) = fleetslam_core::math::sin_cos(phi);
    let max_gap = EvalOptions::default().max_truth_gap;
    println!(
        "  window (s)  error vs GPS (m)  particle spread (m)  min ESS  resamples  observations/record"
    );
    /// One window's sums.
    struct Window {
        start: f64,
        squared_error: f64,
        fixes: usize,
        spread: f64,
        ess: f64,
        resamples: usize,
        records: usize,
        observations: usize,
    }
    impl Window {
        fn new(start: f64) -> Self {
            Self {
                start,
                squared_error: 0.0,
                fixes: 0,
                spread: 0.0,
                ess: f64::INFINITY,
                resamples: 0,
                records: 0,
                observations: 0,
            }
        }
        fn print(&self, t0: f64, w: f64) {
            let error = if self.fixes > 0 {
                format!("{:.2}", (self.squared_error / self.fixes as f64).sqrt())
            } else {
                "no GPS".into()
            };
            println!(
                "  {:>5.0}-{:<5.0}  {error:>8}          {:>8.2}             {:>5.1}    {:>4}       {:>5.2}",
                self.start - t0,
                self.start + w - t0,
                self.spread,
                self.ess,
                self.resamples,
                self.observations as f64 / (self.records as f64).max(1.0)
            );
        }
    }
    let t0 = imp.log.records.first().map_or(0.0, |r| r.t);
    let mut win = Window::new(t0);
    for rec in &imp.log.records {
        while rec.t >= win.start + w {
            win.print(t0, w);
            win = Window::new(win.start + w);
        }
        let report = slam.step(rec).expect("step");
        let mean = slam.mean_pose(0);
        let var: f64 = slam
            .particle_sample(0, usize::MAX)
            .iter()
            .map(|(p, wt)| wt * ((p.x - mean.x).powi(2) + (p.y - mean.y).powi(2)))
            .sum();
        win.spread = win.spread.max(var.sqrt());
        win.ess = win.ess.min(report.ess);
        win.resamples += usize::from(report.resampled);
        win.records += 1;
        win.observations += rec.landmarks.len();
        if let Some(truth) = fleetslam_data::evaluate::interpolate(gps, rec.t, max_gap) {
            let (x, y) = (c * mean.x - s * mean.y + tx, s * mean.x + c * mean.y + ty);
            win.squared_error += (x - truth.x).powi(2) + (y - truth.y).powi(2);
            win.fixes += 1;
        }
    }
    win.print(t0, w);
}

/// The simulated log of `speed`: 3 robots among 60 landmarks with the default sensor (6 m,
/// 180°), so that records hold 6 or more observations on average (known ids), 120 s.
/// A 64-bit FNV-1a hash of the filter's state as its snapshot writes it in JSON (robots,
/// particles with their maps, known ids, step, effective sample size; every number to the
/// bit: `serde_json` writes the shortest text that reads back to the same `f64`), without
/// the statistics (which hold timings), so that two builds or two machines can be checked
/// for the same bits by command.
fn state_digest(slam: &FastSlam) -> u64 {
    let s = slam.snapshot();
    let state = (&s.robots, &s.particles, &s.known_slots, s.step, s.ess);
    let json = serde_json::to_vec(&state).expect("a snapshot encodes");
    json.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

fn speed_scenario(seed: u64) -> SimConfig {
    SimConfig {
        seed,
        duration: 120.0,
        landmarks: 60,
        ..SimConfig::default()
    }
}

/// Landmarks in groups of 2 or 3 features 0.1-0.13 m from their group's centre (members at
/// most 0.26 m apart, as MRCLAM's barcodes stand 0.18-0.25 m apart), the centres on a grid
/// of `spacing` m over the arena, each moved by up to a tenth of the spacing in x and y.
fn clustered_landmarks(seed: u64, arena: [f64; 2], spacing: f64) -> Vec<[f64; 3]> {
    use rand::Rng;
    let mut rng = fleetslam_core::rng::stream(seed, 0, 0x6C75_7374);
    let mut out = Vec::new();
    let (nx, ny) = (
        (arena[0] / spacing).floor() as usize,
        (arena[1] / spacing).floor() as usize,
    );
    for i in 0..nx {
        for j in 0..ny {
            let cx = (i as f64 + 0.5) * spacing + rng.random_range(-0.1..0.1) * spacing;
            let cy = (j as f64 + 0.5) * spacing + rng.random_range(-0.1..0.1) * spacing;
            let members = rng.random_range(2..=3);
            let a0 = rng.random_range(0.0..std::f64::consts::TAU);
            for k in 0..members {
                let a = a0 + std::f64::consts::TAU * k as f64 / members as f64;
                let r = rng.random_range(0.1..0.13);
                out.push([cx + r * a.cos(), cy + r * a.sin(), 0.0]);
            }
        }
    }
    out
}

/// The `clusters` scenarios: name, group spacing, simulation per seed (no ids).
#[allow(clippy::type_complexity)]
fn cluster_scenarios(duration: f64) -> Vec<(&'static str, f64, Box<dyn Fn(u64) -> SimConfig>)> {
    let base = move |seed, spacing| {
        let d = SimConfig::default();
        SimConfig {
            seed,
            duration,
            with_ids: false,
            landmark_positions: Some(clustered_landmarks(seed, d.arena, spacing)),
            ..d
        }
    };
    vec![
        (
            "3 robots, 6 m 180 deg, groups 2.25 m apart",
            2.25,
            Box::new(move |seed| base(seed, 2.25)),
        ),
        (
            "5 robots, odometry, 4 m 60 deg, groups 3 m apart",
            3.0,
            Box::new(move |seed| SimConfig {
                robots: 5,
                motion_model: MotionModel::Odometry,
                sensor_range: SensorRange {
                    max_range: 4.0,
                    fov: 60f64.to_radians(),
                },
                ..base(seed, 3.0)
            }),
        ),
        (
            "3 robots, motion noise x2, bearing 0.05 rad, 1.5 m",
            1.5,
            Box::new(move |seed| {
                let d = SimConfig::default();
                SimConfig {
                    true_motion_noise: scaled_noise(&d.true_motion_noise, 2.0),
                    true_sensor_noise: SensorNoise {
                        bearing: 0.05,
                        ..d.true_sensor_noise
                    },
                    ..base(seed, 1.5)
                }
            }),
        ),
    ]
}

/// `n` with every standard deviation times `k` (the random walk's time cap kept).
fn scaled_noise(n: &MotionNoise, k: f64) -> MotionNoise {
    MotionNoise {
        trans_per_m: k * n.trans_per_m,
        lateral_per_m: k * n.lateral_per_m,
        rot_per_rad: k * n.rot_per_rad,
        rot_per_m: k * n.rot_per_m,
        trans_per_sqrt_s: k * n.trans_per_sqrt_s,
        rot_per_sqrt_s: k * n.rot_per_sqrt_s,
        ..*n
    }
}

/// Simulations whose range noise grows with the range (a camera that ranges by apparent
/// size), none of them MRCLAM: other fleets, fields of view, ranges and landmark densities.
fn range_noise_scenarios() -> Scenarios {
    let base = |seed| SimConfig {
        seed,
        duration: 120.0,
        true_sensor_noise: SensorNoise {
            range: 0.02,
            range_per_m: 0.05,
            bearing: 0.01,
            ..SensorNoise::default()
        },
        ..SimConfig::default()
    };
    vec![
        (
            "3 robots, 20 landmarks, 6 m 180 deg, 0.02 m + 5 %",
            Box::new(base),
        ),
        (
            "5 robots, odometry, 12 landmarks, 5 m 60 deg",
            Box::new(move |seed| SimConfig {
                robots: 5,
                landmarks: 12,
                motion_model: MotionModel::Odometry,
                sensor_range: SensorRange {
                    max_range: 5.0,
                    fov: 60f64.to_radians(),
                },
                ..base(seed)
            }),
        ),
        (
            "1 robot, 40 landmarks, 12 m all round, 0.05 m + 8 %",
            Box::new(move |seed| SimConfig {
                robots: 1,
                landmarks: 40,
                sensor_range: SensorRange {
                    max_range: 12.0,
                    fov: 2.0 * std::f64::consts::PI,
                },
                true_sensor_noise: SensorNoise {
                    range: 0.05,
                    range_per_m: 0.08,
                    bearing: 0.02,
                    ..SensorNoise::default()
                },
                ..base(seed)
            }),
        ),
    ]
}

/// Named simulations, each made for a seed.
type Scenarios = Vec<(&'static str, Box<dyn Fn(u64) -> SimConfig>)>;

/// Simulated scenarios none of the filter's settings were tuned on.
fn scenarios() -> Scenarios {
    let base = |seed| SimConfig {
        seed,
        duration: 120.0,
        ..SimConfig::default()
    };
    vec![
        (
            "default: 3 robots, 20 landmarks, 6 m 180 deg",
            Box::new(base),
        ),
        (
            "sparse and narrow: 8 landmarks, 4 m 60 deg",
            Box::new(move |seed| SimConfig {
                landmarks: 8,
                sensor_range: SensorRange {
                    max_range: 4.0,
                    fov: 60f64.to_radians(),
                },
                ..base(seed)
            }),
        ),
        (
            "dense, noisy motion x3: 60 landmarks",
            Box::new(move |seed| SimConfig {
                landmarks: 60,
                true_motion_noise: scaled_noise(&SimConfig::default().true_motion_noise, 3.0),
                ..base(seed)
            }),
        ),
        (
            "5 robots, odometry, fast (0.8 m/s), noisy sensor",
            Box::new(move |seed| SimConfig {
                robots: 5,
                motion_model: MotionModel::Odometry,
                speed: 0.8,
                true_sensor_noise: SensorNoise {
                    range: 0.3,
                    bearing: 0.05,
                    ..SensorNoise::default()
                },
                ..base(seed)
            }),
        ),
        (
            "biased odometry: moves 0.93 x distance, 0.95 x turn",
            Box::new(move |seed| SimConfig {
                odometry_scale: [0.93, 0.95],
                ..base(seed)
            }),
        ),
    ]
}
