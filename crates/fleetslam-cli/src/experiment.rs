//! `fleetslam experiment`: the paper's four experiments in simulation (3D point landmarks)
//! and the MRCLAM Dataset 6 comparison, EKF against the learned updaters, written as
//! markdown tables and PNG charts.

use crate::learned::{load_model, print_report, run_with, train_with_progress};
use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::log::Log;
use fleetslam_core::pose::wrap_angle;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use fleetslam_core::updater::LandmarkUpdater;
use fleetslam_data::evaluate::{EvalOptions, evaluate, interpolate};
use fleetslam_data::formats::Truth;
use fleetslam_data::import::{MrclamOptions, import_mrclam};
use fleetslam_data::run::RunOutput;
use fleetslam_data::sim::{SimConfig, random_landmarks, simulate};
use fleetslam_learned::row::write_ndjson_path;
use fleetslam_learned::training::{TrainConfig, save_model_dir};
use fleetslam_learned::{MlpModel, MlpUpdater, RecordingConfig, RecordingUpdater, TrainingRow};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Debug, Subcommand)]
pub enum ExperimentCommand {
    /// The paper's four experiments (Vidal & Rosa 2015, Sec. 5) in simulation, 3D points.
    Paper(PaperArgs),
    /// MRCLAM Dataset 6 (2D range-bearing), models trained on simulated data only.
    Mrclam(MrclamArgs),
}

pub fn cmd_experiment(c: ExperimentCommand) -> Result<()> {
    match c {
        ExperimentCommand::Paper(a) => cmd_paper(a),
        ExperimentCommand::Mrclam(a) => cmd_mrclam(a),
    }
}

/// Training shared by both experiments.
#[derive(Debug, Args, Clone)]
pub struct TrainingArgs {
    /// Simulated runs whose EKF updates are logged for training: split by run into
    /// training runs, one validation run (early stopping) and one test run (the report).
    #[arg(long, default_value_t = 5)]
    pub train_runs: usize,
    /// Particles of the training runs.
    #[arg(long, default_value_t = 200)]
    pub train_particles: usize,
    /// Fraction of updates logged in the training runs.
    #[arg(long, default_value_t = 0.02)]
    pub training_rate: f64,
    /// Epochs of the paper preset (the paper's 1000 by default).
    #[arg(long)]
    pub paper_epochs: Option<usize>,
    /// Epochs of the default preset.
    #[arg(long)]
    pub default_epochs: Option<usize>,
    /// Use this paper-preset model instead of training one.
    #[arg(long)]
    pub paper_model: Option<PathBuf>,
    /// Use this default-preset model instead of training one.
    #[arg(long)]
    pub default_model: Option<PathBuf>,
    /// Epochs of the structured preset.
    #[arg(long)]
    pub structured_epochs: Option<usize>,
    /// Use this structured-preset model instead of training one.
    #[arg(long)]
    pub structured_model: Option<PathBuf>,
    /// Where models and training rows go.
    #[arg(long, default_value = "target/experiments")]
    pub work: PathBuf,
}

#[derive(Debug, Args)]
pub struct PaperArgs {
    /// Particle counts (the paper: 1000, 2000, 4000, 8000).
    #[arg(long, value_delimiter = ',', default_values_t = [1000, 2000, 4000, 8000])]
    pub particles: Vec<usize>,
    /// Simulated seconds per run.
    #[arg(long, default_value_t = 60.0)]
    pub duration: f64,
    /// Robots (the paper's Sec. 4: two robots sharing a map).
    #[arg(long, default_value_t = 2)]
    pub robots: usize,
    #[arg(long, default_value_t = 20)]
    pub landmarks: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub training: TrainingArgs,
    /// Where the markdown table and PNG chart go.
    #[arg(long, default_value = "docs")]
    pub out_dir: PathBuf,
    /// Only rewrite the table and chart from a results file written by an earlier run
    /// (`WORK/paper-results.json`), with the models given by --paper-model and
    /// --default-model.
    #[arg(long, value_name = "RESULTS_JSON")]
    pub replot: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct MrclamArgs {
    /// The MRCLAM Dataset 6 directory.
    #[arg(long, default_value = "../shared/datasets/mrclam-dataset6")]
    pub dataset: PathBuf,
    /// Keep only the first SECONDS of the data set.
    #[arg(long)]
    pub duration: Option<f64>,
    #[arg(long, value_delimiter = ',', default_values_t = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10])]
    pub seeds: Vec<u64>,
    #[arg(long, default_value_t = 500)]
    pub particles: usize,
    /// Simulated seconds of each training run.
    #[arg(long, default_value_t = 300.0)]
    pub train_duration: f64,
    #[command(flatten)]
    pub training: TrainingArgs,
    #[arg(long, default_value = "docs")]
    pub out_dir: PathBuf,
}

/// One scored run.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct Scored {
    pub experiment: String,
    pub particles: usize,
    pub seed: u64,
    pub updater: String,
    pub rms_x: f64,
    pub rms_y: f64,
    pub rms_heading: f64,
    pub ate: f64,
    pub landmark_rmse: Option<f64>,
    pub ns_per_update: f64,
    pub wall_s: f64,
}

/// RMS error of x, y and heading of every estimated pose against the interpolated truth.
fn axis_rms(est: &Truth, truth: &Truth) -> (f64, f64, f64) {
    let (mut sx, mut sy, mut sh, mut n) = (0.0, 0.0, 0.0, 0usize);
    for (robot, pts) in &est.trajectories {
        let Some(tr) = truth.trajectories.get(robot) else {
            continue;
        };
        for p in pts {
            if let Some(t) = interpolate(tr, p.t, 1.0) {
                sx += (p.pose.x - t.x).powi(2);
                sy += (p.pose.y - t.y).powi(2);
                sh += wrap_angle(p.pose.theta - t.theta).powi(2);
                n += 1;
            }
        }
    }
    let n = n.max(1) as f64;
    ((sx / n).sqrt(), (sy / n).sqrt(), (sh / n).sqrt())
}

pub(crate) fn score(experiment: &str, seed: u64, out: &RunOutput, truth: &Truth) -> Scored {
    let ev = evaluate(
        &out.estimate,
        truth,
        out.metrics.shared_frame,
        &EvalOptions::default(),
    );
    let (rx, ry, rh) = axis_rms(&out.estimate, truth);
    Scored {
        experiment: experiment.into(),
        particles: out.metrics.particles,
        seed,
        updater: out.metrics.updater.clone(),
        rms_x: rx,
        rms_y: ry,
        rms_heading: rh,
        ate: ev.team.ate_rmse,
        landmark_rmse: ev.team.landmark_rmse,
        ns_per_update: out.metrics.ns_per_landmark_update,
        wall_s: out.metrics.wall_time_s,
    }
}

/// Logs the EKF's updates of `log` at `rate` (all rows, deterministic order).
pub(crate) fn record_rows(
    log: &Log,
    cfg: &FilterConfig,
    rate: f64,
    seed: u64,
) -> Result<Vec<TrainingRow>> {
    let ekf: Arc<dyn LandmarkUpdater> =
        Arc::new(EkfUpdater::new(cfg.landmark_kind, &cfg.sensor_noise));
    let rec = Arc::new(RecordingUpdater::new(
        ekf,
        RecordingConfig {
            rate,
            cap: 2_000_000,
            seed,
        },
    )?);
    run_with(log, cfg.clone(), rec.clone())?;
    Ok(rec.drain_rows())
}

/// The paper, default and structured models: loaded, or trained on `runs` (split by run)
/// and saved under `work`.
fn models(
    t: &TrainingArgs,
    runs: &[Vec<TrainingRow>],
    kind: LandmarkKind,
    noise: SensorNoise,
    tag: &str,
) -> Result<Vec<MlpModel>> {
    let mut out = Vec::new();
    for (preset, given, epochs) in [
        ("paper", &t.paper_model, t.paper_epochs),
        ("default", &t.default_model, t.default_epochs),
        ("structured", &t.structured_model, t.structured_epochs),
    ] {
        if let Some(p) = given {
            out.push(load_model(p)?);
            continue;
        }
        let id = format!("mlp-{preset}-{tag}");
        let mut cfg = TrainConfig::preset(preset, &id)?;
        cfg.kind = Some(kind);
        cfg.noise = Some(noise);
        if let Some(e) = epochs {
            cfg.epochs = e;
        }
        let trained = train_with_progress(runs, &cfg)?;
        print_report(&trained);
        let dir = t.work.join(&id);
        save_model_dir(&dir, &trained)?;
        println!("saved {}", dir.display());
        out.push(trained.model);
    }
    Ok(out)
}

/// Writes each run's rows to `work/<stem>-run<k>.ndjson` (one file per run, as `fleetslam
/// train --data` takes them).
pub(crate) fn write_runs(
    work: &std::path::Path,
    stem: &str,
    runs: &[Vec<TrainingRow>],
) -> Result<()> {
    std::fs::create_dir_all(work)?;
    for (k, rows) in runs.iter().enumerate() {
        let path = work.join(format!("{stem}-run{k}.ndjson"));
        write_ndjson_path(&path, rows)?;
        println!("{} training rows -> {}", rows.len(), path.display());
    }
    Ok(())
}

pub(crate) fn updaters(
    cfg: &FilterConfig,
    models: &[MlpModel],
) -> Result<Vec<Arc<dyn LandmarkUpdater>>> {
    let mut v: Vec<Arc<dyn LandmarkUpdater>> = vec![Arc::new(EkfUpdater::new(
        cfg.landmark_kind,
        &cfg.sensor_noise,
    ))];
    for m in models {
        let mut c = cfg.clone();
        c.updater = m.id.clone();
        v.push(Arc::new(MlpUpdater::for_run(m.clone(), &c)?));
    }
    Ok(v)
}

// ---------------------------------------------------------------------------- paper

fn sim3(a: &PaperArgs, positions: Vec<[f64; 3]>, seed: u64) -> SimConfig {
    SimConfig {
        robots: a.robots,
        landmarks: positions.len(),
        kind: LandmarkKind::Point3d,
        duration: a.duration,
        seed,
        landmark_positions: Some(positions),
        ..SimConfig::default()
    }
}

fn cmd_paper(a: PaperArgs) -> Result<()> {
    if let Some(path) = &a.replot {
        let results: Vec<Scored> = serde_json::from_slice(
            &std::fs::read(path).with_context(|| format!("reading {}", path.display()))?,
        )?;
        let models = [
            &a.training.paper_model,
            &a.training.default_model,
            &a.training.structured_model,
        ]
        .into_iter()
        .flatten()
        .map(|p| load_model(p))
        .collect::<Result<Vec<_>>>()?;
        return write_paper_outputs(&a, &results, &models);
    }
    let base = SimConfig::default();
    let world_a = random_landmarks(a.landmarks, base.arena, base.landmark_height, 100 + a.seed);
    // Training: the EKF's updates in world A, on trajectories of other seeds than the tests'.
    let mut runs = Vec::new();
    let mut cfg_train = None;
    for k in 0..a.training.train_runs {
        let sim = simulate(&sim3(&a, world_a.clone(), 1000 + k as u64 + 10 * a.seed))?;
        let mut cfg = FilterConfig::from_header(&sim.log.header);
        cfg.particles = a.training.train_particles;
        cfg.seed = 1000 + k as u64;
        runs.push(record_rows(
            &sim.log,
            &cfg,
            a.training.training_rate,
            k as u64,
        )?);
        cfg_train = Some(cfg);
    }
    let cfg_train = cfg_train.context("--train-runs must be at least 1")?;
    write_runs(&a.training.work, "paper-training", &runs)?;
    let models = models(
        &a.training,
        &runs,
        LandmarkKind::Point3d,
        cfg_train.sensor_noise,
        "point3d",
    )?;

    // The four worlds of the paper's experiments.
    let [w, h] = base.arena;
    let mirrored: Vec<[f64; 3]> = world_a.iter().map(|p| [w - p[0], h - p[1], p[2]]).collect();
    let other_heights =
        random_landmarks(a.landmarks, base.arena, base.landmark_height, 300 + a.seed);
    let same_xy_other: Vec<[f64; 3]> = world_a
        .iter()
        .zip(&other_heights)
        .map(|(p, o)| [p[0], p[1], o[2]])
        .collect();
    let world_d = random_landmarks(a.landmarks, base.arena, base.landmark_height, 400 + a.seed);
    let worlds = [
        ("1: training landmarks, training positions", world_a.clone()),
        ("2: same landmarks, mirrored positions", mirrored),
        (
            "3: other landmarks (new heights), same positions",
            same_xy_other,
        ),
        ("4: other landmarks, other positions", world_d),
    ];
    let mut results = Vec::new();
    for (e, (name, world)) in worlds.iter().enumerate() {
        let sim = simulate(&sim3(&a, world.clone(), 2000 + e as u64 + 10 * a.seed))?;
        for &n in &a.particles {
            let mut cfg = FilterConfig::from_header(&sim.log.header);
            cfg.particles = n;
            cfg.seed = a.seed;
            for u in updaters(&cfg, &models)? {
                let out = run_with(&sim.log, cfg.clone(), u)?;
                let s = score(name, a.seed, &out, &sim.truth);
                println!(
                    "experiment {name}, {n} particles, {}: RMS x {:.3} y {:.3} heading {:.3}; landmarks {:.3} m; {:.0} ns/update; {:.1} s",
                    s.updater,
                    s.rms_x,
                    s.rms_y,
                    s.rms_heading,
                    s.landmark_rmse.unwrap_or(f64::NAN),
                    s.ns_per_update,
                    s.wall_s
                );
                results.push(s);
            }
        }
    }
    let json = a.training.work.join("paper-results.json");
    std::fs::write(&json, serde_json::to_vec_pretty(&results)?)?;
    println!("wrote {}", json.display());
    write_paper_outputs(&a, &results, &models)
}

fn write_paper_outputs(a: &PaperArgs, results: &[Scored], models: &[MlpModel]) -> Result<()> {
    std::fs::create_dir_all(&a.out_dir)?;
    let md = paper_markdown(a, results, models);
    let md_path = a.out_dir.join("learned-paper.md");
    std::fs::write(&md_path, md)?;
    let png = a.out_dir.join("learned-paper.png");
    crate::chart::paper_chart(&png, results)?;
    println!("wrote {} and {}", md_path.display(), png.display());
    Ok(())
}

pub(crate) fn fmt_opt(v: Option<String>) -> String {
    v.unwrap_or_else(|| "-".into())
}

/// A length or ratio with 3 decimals; a diverged run's (not finite or beyond 1 km) in
/// scientific notation, marked.
pub(crate) fn fmt_m(v: f64) -> String {
    if v.is_finite() && v.abs() < 1e3 {
        format!("{v:.3}")
    } else {
        format!("{v:.1e} (diverged)")
    }
}

/// A ratio as a signed percentage difference; a diverged one marked.
pub(crate) fn fmt_pct(ratio: f64) -> String {
    if ratio.is_finite() && ratio.abs() < 1e3 {
        format!("{:+.1} %", 100.0 * (ratio - 1.0))
    } else {
        "diverged".into()
    }
}

fn paper_markdown(a: &PaperArgs, results: &[Scored], models: &[MlpModel]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<!-- Written by `fleetslam experiment paper` (seed {}, {} robots, {} landmarks, {} s runs, particles {:?}). -->\n",
        a.seed, a.robots, a.landmarks, a.duration, a.particles
    );
    let table_n = if a.particles.contains(&2000) {
        2000
    } else {
        a.particles[0]
    };
    let _ = writeln!(
        s,
        "RMS error of x [m], y [m] and heading [rad] with {table_n} particles (the paper's Table 1 layout):\n"
    );
    let _ = writeln!(
        s,
        "| experiment | updater | x | y | heading |\n|---|---|---|---|---|"
    );
    for r in results.iter().filter(|r| r.particles == table_n) {
        let _ = writeln!(
            s,
            "| {} | {} | {:.3} | {:.3} | {:.3} |",
            r.experiment, r.updater, r.rms_x, r.rms_y, r.rms_heading
        );
    }
    let _ = writeln!(s, "\nEvery run:\n");
    let _ = writeln!(
        s,
        "| experiment | particles | updater | x | y | heading | landmark RMSE [m] | ns per update | run [s] |\n|---|---|---|---|---|---|---|---|---|"
    );
    for r in results {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {} | {:.0} | {:.1} |",
            r.experiment,
            r.particles,
            r.updater,
            r.rms_x,
            r.rms_y,
            r.rms_heading,
            fmt_opt(r.landmark_rmse.map(fmt_m)),
            r.ns_per_update,
            r.wall_s
        );
    }
    s.push_str(&model_lines(models));
    s
}

/// One line per model: layout, network and its error against the EKF on its test run.
pub(crate) fn model_lines(models: &[MlpModel]) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "\nModels:\n");
    for m in models {
        let v = m.metadata.get("report").and_then(|r| r.get("updater"));
        let f = |k: &str| {
            v.and_then(|v| v.get(k))
                .and_then(|v| v.as_f64())
                .map_or("-".into(), |v| format!("{v:.5}"))
        };
        let _ = writeln!(
            s,
            "- `{}`: {} layout, hidden {:?} {}; on its test run (never trained or validated on): \
             posterior-mean RMSE against the EKF {} m (not updating: {} m), covariance relative \
             RMSE {}",
            m.id,
            m.layout.as_str(),
            m.hidden(),
            m.activation.as_str(),
            f("mean_rmse"),
            f("no_update_rmse"),
            f("cov_rel_rmse"),
        );
    }
    s
}

// ---------------------------------------------------------------------------- MRCLAM

fn cmd_mrclam(a: MrclamArgs) -> Result<()> {
    let imp = import_mrclam(
        &a.dataset,
        &MrclamOptions {
            duration: a.duration,
            ..Default::default()
        },
    )
    .with_context(|| format!("importing {}", a.dataset.display()))?;
    let base_cfg = FilterConfig::from_header(&imp.log.header);
    // Training data: simulated 5-robot range-bearing runs, logged by an EKF that assumes
    // the same sensor noise as the MRCLAM runs (never MRCLAM data).
    let mut runs = Vec::new();
    for k in 0..a.training.train_runs {
        let sim = simulate(&SimConfig {
            robots: 5,
            landmarks: 15,
            kind: LandmarkKind::RangeBearing2d,
            duration: a.train_duration,
            true_sensor_noise: SensorNoise {
                range: base_cfg.sensor_noise.range / 2.0,
                bearing: base_cfg.sensor_noise.bearing / 2.0,
                ..SensorNoise::default()
            },
            seed: 500 + k as u64,
            ..SimConfig::default()
        })?;
        let mut cfg = FilterConfig::from_header(&sim.log.header);
        cfg.sensor_noise = base_cfg.sensor_noise;
        cfg.particles = a.training.train_particles;
        cfg.seed = 500 + k as u64;
        runs.push(record_rows(
            &sim.log,
            &cfg,
            a.training.training_rate,
            k as u64,
        )?);
    }
    write_runs(&a.training.work, "mrclam-sim-training", &runs)?;
    let models = models(
        &a.training,
        &runs,
        LandmarkKind::RangeBearing2d,
        base_cfg.sensor_noise,
        "range_bearing_2d",
    )?;
    let mut results = Vec::new();
    for &seed in &a.seeds {
        let mut cfg = base_cfg.clone();
        cfg.particles = a.particles;
        cfg.seed = seed;
        for u in updaters(&cfg, &models)? {
            let out = run_with(&imp.log, cfg.clone(), u)?;
            let s = score("mrclam-dataset6", seed, &out, &imp.truth);
            println!(
                "seed {seed}, {}: team ATE {:.3} m, landmarks {:.3} m, {:.0} ns/update, {:.1} s",
                s.updater,
                s.ate,
                s.landmark_rmse.unwrap_or(f64::NAN),
                s.ns_per_update,
                s.wall_s
            );
            results.push(s);
        }
    }
    std::fs::create_dir_all(&a.out_dir)?;
    let json = a.training.work.join("mrclam-results.json");
    std::fs::write(&json, serde_json::to_vec_pretty(&results)?)?;
    let md_path = a.out_dir.join("learned-mrclam.md");
    std::fs::write(&md_path, mrclam_markdown(&a, &results, &models))?;
    println!("wrote {} and {}", md_path.display(), json.display());
    Ok(())
}

fn mrclam_markdown(a: &MrclamArgs, results: &[Scored], models: &[MlpModel]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<!-- Written by `fleetslam experiment mrclam` ({} particles, seeds {:?}, duration {}). -->\n",
        a.particles,
        a.seeds,
        a.duration.map_or("all".into(), |d| format!("{d} s"))
    );
    let _ = writeln!(
        s,
        "| seed | updater | team ATE RMSE [m] | ATE / EKF's | landmark RMSE [m] | ns per update | run [s] |\n|---|---|---|---|---|---|---|"
    );
    for r in results {
        let ekf = results
            .iter()
            .find(|e| e.seed == r.seed && e.updater == "ekf")
            .map_or(f64::NAN, |e| e.ate);
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {:.0} | {:.1} |",
            r.seed,
            r.updater,
            fmt_m(r.ate),
            fmt_m(r.ate / ekf),
            fmt_opt(r.landmark_rmse.map(fmt_m)),
            r.ns_per_update,
            r.wall_s
        );
    }
    s.push_str(&summary_table(results, false));
    s.push_str(&model_lines(models));
    s
}

/// Mean and worst seed of every updater's team ATE, against the EKF's; with `landmarks`, the
/// mean landmark RMSE too.
pub(crate) fn summary_table(results: &[Scored], landmarks: bool) -> String {
    let mut s = String::new();
    let mut names: Vec<&str> = results.iter().map(|r| r.updater.as_str()).collect();
    names.sort();
    names.dedup();
    let (lm_head, lm_rule) = if landmarks {
        (" mean landmark RMSE [m] |", "---|")
    } else {
        ("", "")
    };
    let _ = writeln!(
        s,
        "\nOver seeds (worst seed: the largest team ATE; ratios against the EKF's mean and worst):\n\n\
         | updater | seeds | mean team ATE [m] | mean / EKF's | worst team ATE [m] (seed) | worst / EKF's worst |{lm_head} ns per update (mean) |\n|---|---|---|---|---|---|{lm_rule}---|"
    );
    let stats = |n: &str| -> (usize, f64, f64, u64, f64, f64) {
        let v: Vec<&Scored> = results.iter().filter(|r| r.updater == n).collect();
        let k = v.len().max(1) as f64;
        let worst = v
            .iter()
            .copied()
            .max_by(|a, b| a.ate.total_cmp(&b.ate))
            .map_or((f64::NAN, 0), |r| (r.ate, r.seed));
        (
            v.len(),
            v.iter().map(|r| r.ate).sum::<f64>() / k,
            worst.0,
            worst.1,
            v.iter().map(|r| r.ns_per_update).sum::<f64>() / k,
            v.iter()
                .map(|r| r.landmark_rmse.unwrap_or(f64::NAN))
                .sum::<f64>()
                / k,
        )
    };
    let (_, ekf_mean, ekf_worst, _, _, _) = stats("ekf");
    for n in names {
        let (count, mean, worst, worst_seed, ns, lm) = stats(n);
        let lm = if landmarks {
            format!(" {} |", fmt_m(lm))
        } else {
            String::new()
        };
        let _ = writeln!(
            s,
            "| {n} | {count} | {} | {} | {} ({worst_seed}) | {} |{lm} {ns:.0} |",
            fmt_m(mean),
            fmt_pct(mean / ekf_mean),
            fmt_m(worst),
            fmt_pct(worst / ekf_worst),
        );
    }
    s
}
