//! `fleetslam localize`: a localization-only run. The log's robots are localized (Monte
//! Carlo localization from a uniform prior over the map, KLD-sampling, the real-time
//! policies) in a fixed map, e.g. the `landmarks.csv` of a finished run, which never changes.

use anyhow::{Context, Result};
use clap::Args;
use fleetslam_core::config::FilterConfig;
use fleetslam_core::log::{Log, record_order};
use fleetslam_core::updater::LandmarkGaussian;
use fleetslam_data::formats::{TrajectoryPoint, Truth, landmarks_file, read_landmarks_csv_path};
use fleetslam_localize::map::{LandmarkSet, MapLandmark};
use fleetslam_localize::{LocalizeConfig, MapLocalization, Models};
use std::collections::BTreeMap;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct LocalizeArgs {
    /// The observation log.
    log: PathBuf,
    /// A directory holding the map as `landmarks.csv` (what `fleetslam run` and
    /// `fleetslam export` write).
    #[arg(long)]
    map: PathBuf,
    /// Writes `trajectory_<robot>.tum` (each robot's localization mean after each of its
    /// records, once initialised) and `localization.json` here.
    #[arg(long)]
    out: PathBuf,
    /// Only these robots (default: every robot of the log).
    #[arg(long, value_delimiter = ',')]
    robots: Vec<String>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A JSON or TOML file of `LocalizeConfig` fields.
    #[arg(long)]
    localize_config: Option<PathBuf>,
}

impl LocalizeArgs {
    pub fn localize_config(&self) -> Option<&std::path::Path> {
        self.localize_config.as_deref()
    }
}

pub fn cmd_localize(a: LocalizeArgs, localize: LocalizeConfig) -> Result<()> {
    let log = Log::read_path(&a.log).with_context(|| format!("reading {}", a.log.display()))?;
    let cfg = FilterConfig::from_header(&log.header);
    let rows = read_landmarks_csv_path(&landmarks_file(&a.map))
        .with_context(|| format!("reading the map in {}", a.map.display()))?;
    let map = LandmarkSet::new(
        cfg.landmark_kind,
        rows.iter()
            .map(|r| MapLandmark {
                id: r.id,
                gaussian: LandmarkGaussian {
                    mean: r.mean,
                    cov: r.cov,
                },
            })
            .collect(),
    )?;
    let mut ml = MapLocalization::new(map, Models::from_filter(&cfg), localize, a.seed)?;
    let robots: Vec<String> = if a.robots.is_empty() {
        log.header.robots.iter().map(|r| r.id.clone()).collect()
    } else {
        a.robots.clone()
    };
    for r in &robots {
        ml.add_robot(r)?;
    }
    let mut records: Vec<_> = log
        .records
        .iter()
        .filter(|r| robots.contains(&r.robot))
        .collect();
    records.sort_by(|x, y| record_order(x, y));
    let mut traj: BTreeMap<String, Vec<TrajectoryPoint>> = BTreeMap::new();
    let mut converged_at: BTreeMap<String, f64> = BTreeMap::new();
    for rec in records {
        ml.step(rec)?;
        let s = ml
            .localizer(&rec.robot)
            .expect("every robot was added")
            .status();
        if s.initialised {
            traj.entry(rec.robot.clone())
                .or_default()
                .push(TrajectoryPoint {
                    t: rec.t,
                    pose: s.mean,
                });
        }
        if s.converged {
            converged_at.entry(rec.robot.clone()).or_insert(rec.t);
        }
    }
    Truth {
        trajectories: traj,
        landmarks: Vec::new(),
    }
    .write_dir(&a.out)
    .with_context(|| format!("writing {}", a.out.display()))?;
    let summary: Vec<serde_json::Value> = ml
        .phases()
        .into_iter()
        .map(|p| {
            let s = p.localization;
            serde_json::json!({
                "robot": p.id,
                "first_converged_t": converged_at.get(&p.id),
                "converged": s.as_ref().map(|s| s.converged),
                "samples": s.as_ref().map(|s| s.samples),
                "position_spread": s.as_ref().map(|s| s.position_spread),
                "updates": s.as_ref().map(|s| s.stats.updates),
            })
        })
        .collect();
    std::fs::write(
        a.out.join("localization.json"),
        serde_json::to_string_pretty(&serde_json::json!({"robots": summary}))?,
    )?;
    for s in &summary {
        println!(
            "robot {}: {}",
            s["robot"].as_str().unwrap_or(""),
            match s["first_converged_t"].as_f64() {
                Some(t) => format!("localized at t={t:.2} ({} samples now)", s["samples"]),
                None => format!("not localized (spread {} m)", s["position_spread"]),
            }
        );
    }
    println!("-> {}", a.out.display());
    Ok(())
}
