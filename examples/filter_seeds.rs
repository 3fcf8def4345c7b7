//! The filter's accuracy over seeds, as the README reports it:
//!
//! ```sh
//! cargo run --release --example filter_seeds -- mrclam [--no-ids] [--seeds 1-10] \
//!     [--particles 1000] [--version 2] [--duration S] [--dataset DIR]
//! cargo run --release --example filter_seeds -- control-noise [--seeds 1-5] \
//!     [--particles 100] [--duration 60]
//! ```
//!
//! `mrclam` runs MRCLAM Dataset 6 (all five robots) once per seed and prints team ATE, RPE
//! and the landmark figures (without ids: against the truth's 6 landmark groups, each
//! matched within 0.3 m), then their mean and worst. `control-noise` runs the simulated
//! high-control-noise scenario with FastSLAM 1.0 and 2.0 per seed and prints ATE and
//! landmark NEES.

use fleetslam_core::config::FastSlamVersion;
use fleetslam_suite::experiments::{control_noise, mrclam, mrclam_eval_options, run_and_evaluate};
use std::path::PathBuf;
use std::time::Instant;

fn usage() -> ! {
    eprintln!(
        "usage: filter_seeds mrclam|control-noise [--no-ids] [--seeds A-B|a,b,c] \
         [--particles N] [--version 1|2] [--duration S] [--dataset DIR]"
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
            _ => usage(),
        }
    }
    match what.as_str() {
        "mrclam" => {
            let version = *versions.last().expect("one version");
            let seeds = seeds.unwrap_or_else(|| (1..=10).collect());
            let particles = particles.unwrap_or(1000);
            let imp = mrclam(&dataset, no_ids, duration);
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
                let (ev, m) =
                    run_and_evaluate(&imp.log, &imp.truth, particles, seed, version, &opts);
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
                let (mut ates, mut nees) = (Vec::new(), Vec::new());
                for &seed in &seeds {
                    let (log, truth) = control_noise(seed, duration);
                    let opts = Default::default();
                    let (ev, m) = run_and_evaluate(&log, &truth, particles, seed, version, &opts);
                    println!(
                        "FastSLAM {version:?} seed {seed}: ATE {:.3} m, landmark rmse {:.3} m, \
                         landmark NEES {:.2} (dimension 2), proposal fallbacks {}",
                        ev.team.ate_rmse,
                        ev.team.landmark_rmse.unwrap_or(f64::NAN),
                        ev.team.landmark_nees.unwrap_or(f64::NAN),
                        m.proposal_fallbacks,
                    );
                    ates.push(ev.team.ate_rmse);
                    nees.push(ev.team.landmark_nees.unwrap_or(f64::NAN));
                }
                println!(
                    "FastSLAM {version:?}: mean ATE {:.3} m (worst {:.3}), mean landmark NEES {:.2}",
                    mean(&ates),
                    max(&ates),
                    mean(&nees)
                );
            }
        }
        _ => usage(),
    }
}
