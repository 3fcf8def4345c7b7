//! `fleetslam experiment mrclam-truth`: a learned updater trained against MRCLAM's landmark
//! ground truth, evaluated on robots and a time span it never saw.
//!
//! The data set is cut in two by robot and by time:
//!
//! | set | robots (default) | time span | used for |
//! |---|---|---|---|
//! | training | 1, 2, 3 | before the split | fitting the weights |
//! | validation | 1, 2, 3 | after the split | early stopping |
//! | test | 4, 5 | after the split | the per-update report and the filter runs |
//!
//! Each set is a run of its own (imported with `robots`, `duration` and `start`), its EKF
//! updates logged and labelled with the true position of the landmark each one updated, as
//! seen from the row's pose ([`fleetslam_learned::label_rows`] says why). Three models come from the same rows: the `truth`
//! preset (mean learned from the true positions), the same network and inputs learned from
//! the EKF's posterior (the ablation that tells what the target buys), and any models given
//! with `--compare` (for example the simulation-trained ones of `experiment mrclam`). The
//! filter then runs the test set (robots that start at their true pose at the split, on an
//! empty map) with the EKF and every model, over seeds.

use crate::experiment::{
    Scored, fmt_m, fmt_opt, model_lines, record_rows, score, summary_table, updaters, write_runs,
};
use crate::learned::{load_model, print_report, run_with, train_split_with_progress};
use anyhow::{Context, Result, bail};
use clap::Args;
use fleetslam_core::config::FilterConfig;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_data::evaluate::interpolate;
use fleetslam_data::import::{Imported, MrclamOptions, import_mrclam};
use fleetslam_learned::training::{TrainConfig, save_model_dir};
use fleetslam_learned::truth::truth_mahalanobis2;
use fleetslam_learned::{LabelStats, MlpModel, RunSplit, TrainTarget, TrainingRow, label_rows};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::PathBuf;

/// The widest gap [s] between two ground-truth poses across which a robot's true pose at a
/// measurement's time is interpolated (the importer keeps MRCLAM's Vicon truth at up to
/// 20 Hz; a wider gap, where Vicon lost the robot, leaves the row unlabelled).
const TRUE_POSE_MAX_GAP: f64 = 0.5;

#[derive(Debug, Args)]
pub struct MrclamTruthArgs {
    /// The MRCLAM Dataset 6 directory.
    #[arg(long, default_value = "../shared/datasets/mrclam-dataset6")]
    pub dataset: PathBuf,
    /// Seconds after the earliest start where the later span begins (the data set runs
    /// about 886 s).
    #[arg(long, default_value_t = 443.0)]
    pub split: f64,
    /// Keep only the first SECONDS of the data set (the later span ends there).
    #[arg(long)]
    pub duration: Option<f64>,
    /// Robots whose updates train and validate the models.
    #[arg(long, value_delimiter = ',', default_values = ["1", "2", "3"])]
    pub train_robots: Vec<String>,
    /// Robots of the test set (after the split).
    #[arg(long, value_delimiter = ',', default_values = ["4", "5"])]
    pub test_robots: Vec<String>,
    #[arg(long, value_delimiter = ',', default_values_t = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10])]
    pub seeds: Vec<u64>,
    /// Particles of the evaluation runs.
    #[arg(long, default_value_t = 500)]
    pub particles: usize,
    /// Particles of the EKF runs whose updates are logged.
    #[arg(long, default_value_t = 200)]
    pub train_particles: usize,
    /// Fraction of updates logged.
    #[arg(long, default_value_t = 0.05)]
    pub training_rate: f64,
    /// Epochs of both trained models (the presets' default when not given).
    #[arg(long)]
    pub epochs: Option<usize>,
    /// Keep only rows whose truth lies within this squared Mahalanobis distance of the
    /// prior (rows where the particle's belief is consistent with the truth; 9.21 is the
    /// chi-square 99 % point for 2 degrees of freedom). On MRCLAM 79-84 % of the rows
    /// fall outside it: the filter's landmark covariances are over-confident there, and a
    /// model fitted to those rows learns to trust the measurement over any prior.
    #[arg(long)]
    pub prior_gate: Option<f64>,
    /// Use this truth-trained model instead of training one.
    #[arg(long)]
    pub truth_model: Option<PathBuf>,
    /// Use this EKF-target model (same layout and network) instead of training one.
    #[arg(long)]
    pub ekf_target_model: Option<PathBuf>,
    /// Other models to run on the test set too (model.json files).
    #[arg(long = "compare", value_name = "MODEL_JSON")]
    pub compare: Vec<PathBuf>,
    /// Where models and training rows go.
    #[arg(long, default_value = "target/experiments")]
    pub work: PathBuf,
    #[arg(long, default_value = "docs")]
    pub out_dir: PathBuf,
}

/// One set of the split: its run, and its logged and labelled rows.
struct Set {
    name: &'static str,
    imported: Imported,
    rows: Vec<TrainingRow>,
    labels: LabelStats,
}

impl Set {
    /// Rows kept (labelled, and within the prior gate when one is set).
    fn kept(&self) -> usize {
        self.rows.len()
    }
}

fn import(a: &MrclamTruthArgs, robots: &[String], later: bool) -> Result<Imported> {
    let opts = MrclamOptions {
        robots: Some(robots.to_vec()),
        duration: if later { a.duration } else { Some(a.split) },
        start: later.then_some(a.split),
        ..MrclamOptions::default()
    };
    import_mrclam(&a.dataset, &opts).with_context(|| format!("importing {}", a.dataset.display()))
}

fn truth_positions(imp: &Imported) -> BTreeMap<u32, [f64; 3]> {
    imp.truth
        .landmarks
        .iter()
        .filter_map(|l| l.id.map(|id| (id, l.mean)))
        .collect()
}

/// Imports a set, logs its EKF updates and labels them.
fn set(
    a: &MrclamTruthArgs,
    name: &'static str,
    robots: &[String],
    later: bool,
    seed: u64,
) -> Result<Set> {
    let imported = import(a, robots, later)?;
    let mut cfg = FilterConfig::from_header(&imported.log.header);
    cfg.particles = a.train_particles;
    cfg.seed = seed;
    let mut rows = record_rows(&imported.log, &cfg, a.training_rate, seed)?;
    let trajectories = &imported.truth.trajectories;
    let labels = label_rows(
        &mut rows,
        &imported.log,
        &truth_positions(&imported),
        |robot, t| interpolate(trajectories.get(robot)?, t, TRUE_POSE_MAX_GAP),
    );
    println!(
        "{name} set (robots {}, {}): {} rows logged, {} labelled with truth, {} ambiguous, \
         {} without truth, {} not in the log",
        robots.join(","),
        span(a, later),
        labels.rows,
        labels.labelled,
        labels.ambiguous,
        labels.no_truth,
        labels.not_in_log
    );
    if labels.not_in_log > 0 {
        bail!(
            "{} of {name}'s rows match no observation of its log: the filter no longer passes \
             measurements unchanged, so rows cannot be labelled",
            labels.not_in_log
        );
    }
    // Only labelled rows: every set's reports are against truth too.
    rows.retain(|r| r.truth.is_some());
    if let Some(gate) = a.prior_gate {
        let before = rows.len();
        rows.retain(|r| truth_mahalanobis2(r).is_some_and(|d2| d2 <= gate));
        println!(
            "  {} of {before} rows have their truth within the prior's gate {gate}",
            rows.len()
        );
    }
    Ok(Set {
        name,
        imported,
        rows,
        labels,
    })
}

fn span(a: &MrclamTruthArgs, later: bool) -> String {
    if later {
        match a.duration {
            Some(d) => format!("{} s to {d} s", a.split),
            None => format!("{} s to the end", a.split),
        }
    } else {
        format!("0 to {} s", a.split)
    }
}

pub fn cmd_mrclam_truth(a: MrclamTruthArgs) -> Result<()> {
    if a.train_robots.iter().any(|r| a.test_robots.contains(r)) {
        bail!("--train-robots and --test-robots must not share a robot");
    }
    let train = set(&a, "training", &a.train_robots, false, 1)?;
    let val = set(&a, "validation", &a.train_robots, true, 2)?;
    let test = set(&a, "test", &a.test_robots, true, 3)?;
    let base_cfg = FilterConfig::from_header(&test.imported.log.header);
    write_runs(
        &a.work,
        "mrclam-truth",
        &[train.rows.clone(), val.rows.clone(), test.rows.clone()],
    )?;
    let split = RunSplit {
        train: train.rows.clone(),
        val: val.rows.clone(),
        test: test.rows.clone(),
        train_runs: vec![0],
        val_runs: vec![1],
        test_runs: vec![2],
    };
    let mut models = Vec::new();
    for (target, given, id) in [
        (TrainTarget::Truth, &a.truth_model, "mlp-truth-mrclam"),
        (
            TrainTarget::Ekf,
            &a.ekf_target_model,
            "mlp-truth-layout-ekf-target-mrclam",
        ),
    ] {
        if let Some(p) = given {
            models.push(load_model(p)?);
            continue;
        }
        let mut cfg = TrainConfig::truth(id);
        cfg.target = target;
        cfg.kind = Some(LandmarkKind::RangeBearing2d);
        cfg.noise = Some(base_cfg.sensor_noise);
        if let Some(e) = a.epochs {
            cfg.epochs = e;
        }
        let trained = train_split_with_progress(split.clone(), &cfg)?;
        print_report(&trained);
        let dir = a.work.join(id);
        save_model_dir(&dir, &trained)?;
        println!("saved {}", dir.display());
        models.push(trained.model);
    }
    for p in &a.compare {
        models.push(load_model(p)?);
    }

    let mut results = Vec::new();
    for &seed in &a.seeds {
        let mut cfg = base_cfg.clone();
        cfg.particles = a.particles;
        cfg.seed = seed;
        for u in updaters(&cfg, &models)? {
            let out = run_with(&test.imported.log, cfg.clone(), u)?;
            let s = score("mrclam-dataset6-test", seed, &out, &test.imported.truth);
            println!(
                "seed {seed}, {}: team ATE {:.3} m, landmarks {:.3} m",
                s.updater,
                s.ate,
                s.landmark_rmse.unwrap_or(f64::NAN)
            );
            results.push(s);
        }
    }
    std::fs::create_dir_all(&a.out_dir)?;
    let json = a.work.join("mrclam-truth-results.json");
    std::fs::write(&json, serde_json::to_vec_pretty(&results)?)?;
    let md_path = a.out_dir.join("learned-mrclam-truth.md");
    std::fs::write(
        &md_path,
        markdown(&a, &[&train, &val, &test], &results, &models),
    )?;
    println!("wrote {} and {}", md_path.display(), json.display());
    Ok(())
}

fn markdown(a: &MrclamTruthArgs, sets: &[&Set], results: &[Scored], models: &[MlpModel]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<!-- Written by `fleetslam experiment mrclam-truth` (split {} s, train robots {}, test \
         robots {}, {} particles, seeds {:?}, prior gate {}). -->\n",
        a.split,
        a.train_robots.join(","),
        a.test_robots.join(","),
        a.particles,
        a.seeds,
        a.prior_gate.map_or("none".into(), |g| g.to_string())
    );
    let _ = writeln!(
        s,
        "Sets (each its own run; EKF updates logged at rate {} with {} particles, labelled \
         with the true position of the landmark each updated, seen from the particle's pose: \
         placed by the noise-free measurement from the robot's true pose):\n\n\
         | set | robots | span | rows logged | labelled | ambiguous measurement | no truth | kept (truth within the prior gate) |\n\
         |---|---|---|---|---|---|---|---|",
        a.training_rate, a.train_particles
    );
    for set in sets {
        let robots: Vec<&str> = set
            .imported
            .log
            .header
            .robots
            .iter()
            .map(|r| r.id.as_str())
            .collect();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            set.name,
            robots.join(", "),
            span(a, set.name != "training"),
            set.labels.rows,
            set.labels.labelled,
            set.labels.ambiguous,
            set.labels.no_truth,
            set.kept()
        );
    }
    let _ = writeln!(
        s,
        "\nPer-update error on the test set's rows (robots and span never trained on), \
         posterior mean against the landmark's true position:\n\n\
         | model | target | rows | model [m] | EKF [m] | not updating [m] |\n|---|---|---|---|---|---|"
    );
    for m in models {
        let report = m.metadata.get("report");
        let target = report
            .and_then(|r| r.get("target"))
            .and_then(|t| t.as_str())
            .unwrap_or("ekf");
        let truth = report
            .and_then(|r| r.get("updater"))
            .and_then(|u| u.get("truth"));
        let f = |k: &str| {
            fmt_opt(
                truth
                    .and_then(|t| t.get(k))
                    .and_then(|v| v.as_f64())
                    .map(|v| format!("{v:.4}")),
            )
        };
        let rows = truth
            .and_then(|t| t.get("rows"))
            .and_then(|v| v.as_u64())
            .map_or("-".into(), |n| n.to_string());
        let _ = writeln!(
            s,
            "| {} | {target} | {rows} | {} | {} | {} |",
            m.id,
            f("updater_rmse"),
            f("ekf_rmse"),
            f("prior_rmse")
        );
    }
    let _ = writeln!(
        s,
        "\nFilter runs on the test set (robots {} from {} s, starting at their true poses on an \
         empty map):\n\n\
         | seed | updater | team ATE RMSE [m] | landmark RMSE [m] |\n|---|---|---|---|",
        a.test_robots.join(", "),
        a.split
    );
    for r in results {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} |",
            r.seed,
            r.updater,
            fmt_m(r.ate),
            fmt_opt(r.landmark_rmse.map(fmt_m))
        );
    }
    s.push_str(&summary_table(results, true));
    s.push_str(&model_lines(models));
    s
}
