//! The `fleetslam` command.
//!
//! Run with `cargo run --release -p fleetslam-cli -- --help`.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use fleetslam_core::config::{Association, FastSlamVersion, FilterConfig};
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::Log;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_data::evaluate::{Alignment, EvalOptions, evaluate_dir};
use fleetslam_data::import::{MrclamOptions, VictoriaOptions, import_mrclam, import_victoria_park};
use fleetslam_data::run::{TrajectoryEstimate, run_log};
use fleetslam_data::sim::{SimConfig, simulate};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};

#[derive(Debug, Parser)]
#[command(name = "fleetslam", version, about = "Multi-robot shared-map FastSLAM")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Simulate k robots among landmarks: writes OUT/log.ndjson and OUT/truth/.
    Simulate(SimulateArgs),
    /// Convert a real data set to OUT/log.ndjson and OUT/truth/.
    Import {
        #[command(subcommand)]
        dataset: ImportCommand,
    },
    /// Run the filter offline on a log: writes trajectories, landmarks and metrics.
    Run(RunArgs),
    /// Compare an estimate directory with ground truth: prints and writes evaluation.json.
    Evaluate(EvaluateArgs),
}

#[derive(Debug, Args)]
struct SimulateArgs {
    #[arg(long, default_value_t = 3)]
    robots: usize,
    #[arg(long, default_value_t = 20)]
    landmarks: usize,
    /// Landmark kind.
    #[arg(long, value_enum, default_value_t = KindArg::RangeBearing2d)]
    kind: KindArg,
    /// Simulated time [s].
    #[arg(long, default_value_t = 60.0)]
    duration: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Leave landmark ids out of the observations (unknown data association).
    #[arg(long)]
    no_ids: bool,
    /// A JSON or TOML file with any SimConfig fields; flags given explicitly win.
    #[arg(long)]
    config: Option<PathBuf>,
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum KindArg {
    #[value(name = "range_bearing_2d", alias = "2d")]
    RangeBearing2d,
    #[value(name = "point3d", alias = "3d")]
    Point3d,
}

impl From<KindArg> for LandmarkKind {
    fn from(k: KindArg) -> Self {
        match k {
            KindArg::RangeBearing2d => LandmarkKind::RangeBearing2d,
            KindArg::Point3d => LandmarkKind::Point3d,
        }
    }
}

#[derive(Debug, Subcommand)]
enum ImportCommand {
    /// UTIAS MRCLAM (a dataset directory with RobotN_*.dat files).
    Mrclam {
        dir: PathBuf,
        #[arg(long)]
        out: PathBuf,
        /// Drop landmark ids (to test unknown association on real data).
        #[arg(long)]
        no_ids: bool,
        /// Keep only the first SECONDS of the data set.
        #[arg(long)]
        duration: Option<f64>,
        /// Seconds added to odometry times (odometry leads Vicon by 0.15-0.2 s).
        #[arg(long, default_value_t = 0.0)]
        odometry_delay: f64,
    },
    /// Victoria Park (inputs.dat, measurements.dat, gps.dat).
    VictoriaPark {
        dir: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        duration: Option<f64>,
        /// Drop tree detections beyond this range [m].
        #[arg(long, default_value_t = 30.0)]
        max_range: f64,
    },
}

#[derive(Debug, Args)]
struct RunArgs {
    /// The observation log (NDJSON, header first).
    log: PathBuf,
    #[arg(long)]
    out: PathBuf,
    /// A JSON or TOML file with any FilterConfig fields (defaults come from the log header);
    /// flags given explicitly win.
    #[arg(long)]
    config: Option<PathBuf>,
    #[arg(long)]
    particles: Option<usize>,
    /// Landmark updater: `ekf`.
    #[arg(long, default_value = "ekf")]
    updater: String,
    #[arg(long)]
    seed: Option<u64>,
    /// FastSLAM version.
    #[arg(long, value_parser = ["1", "2"])]
    version: Option<String>,
    /// Data association.
    #[arg(long, value_parser = ["known", "unknown"])]
    association: Option<String>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Which pose the trajectories record.
    #[arg(long, value_parser = ["mean", "best"], default_value = "mean")]
    trajectory: String,
}

#[derive(Debug, Args)]
struct EvaluateArgs {
    /// A directory written by `fleetslam run`.
    dir: PathBuf,
    #[arg(long)]
    truth: PathBuf,
    /// Alignment: auto (none when the run's start poses share the truth's frame), none, se2.
    #[arg(long, value_parser = ["auto", "none", "se2"], default_value = "auto")]
    align: String,
}

/// Prints to stdout; a closed pipe (`| head`) ends the output quietly instead of panicking.
fn emit(text: &str) -> Result<()> {
    use std::io::Write;
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => std::process::exit(0),
        r => Ok(r?),
    }
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Simulate(a) => cmd_simulate(a),
        Command::Import { dataset } => cmd_import(dataset),
        Command::Run(a) => cmd_run(a),
        Command::Evaluate(a) => cmd_evaluate(a),
    }
}

/// Reads a JSON or TOML file (by extension) into a JSON value, for layering over defaults.
fn read_config_value(path: &Path) -> Result<serde_json::Value> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let v = if path.extension().is_some_and(|e| e == "toml") {
        let t: toml::Value = toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        serde_json::to_value(t)?
    } else {
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
    };
    Ok(v)
}

/// Overlays the fields of `patch` onto `base` (objects merge recursively).
fn merge(base: &mut serde_json::Value, patch: serde_json::Value) {
    match (base, patch) {
        (serde_json::Value::Object(b), serde_json::Value::Object(p)) => {
            for (k, v) in p {
                merge(b.entry(k).or_insert(serde_json::Value::Null), v);
            }
        }
        (b, p) => *b = p,
    }
}

fn layered<T: serde::Serialize + serde::de::DeserializeOwned>(base: &T, file: Option<&Path>) -> Result<T> {
    let Some(path) = file else {
        return Ok(serde_json::from_value(serde_json::to_value(base)?)?);
    };
    let mut v = serde_json::to_value(base)?;
    merge(&mut v, read_config_value(path)?);
    serde_json::from_value(v).with_context(|| format!("invalid configuration in {}", path.display()))
}

fn cmd_simulate(a: SimulateArgs) -> Result<()> {
    let mut cfg: SimConfig = layered(&SimConfig::default(), a.config.as_deref())?;
    cfg.robots = a.robots;
    cfg.landmarks = a.landmarks;
    cfg.kind = a.kind.into();
    cfg.duration = a.duration;
    cfg.seed = a.seed;
    cfg.with_ids = !a.no_ids;
    let sim = simulate(&cfg).context("simulating")?;
    std::fs::create_dir_all(&a.out)?;
    sim.log.write_path(a.out.join("log.ndjson"))?;
    sim.truth.write_dir(&a.out.join("truth"))?;
    println!(
        "simulated {} robots, {} landmarks, {} records over {} s -> {}",
        cfg.robots,
        cfg.landmarks,
        sim.log.records.len(),
        cfg.duration,
        a.out.display()
    );
    Ok(())
}

fn cmd_import(d: ImportCommand) -> Result<()> {
    let (imported, out) = match d {
        ImportCommand::Mrclam { dir, out, no_ids, duration, odometry_delay } => {
            let opts = MrclamOptions { no_ids, duration, odometry_delay, ..Default::default() };
            (import_mrclam(&dir, &opts)?, out)
        }
        ImportCommand::VictoriaPark { dir, out, duration, max_range } => {
            let opts = VictoriaOptions { duration, max_range, ..Default::default() };
            (import_victoria_park(&dir, &opts)?, out)
        }
    };
    imported.write(&out)?;
    println!("{}", imported.report);
    println!("wrote {}/log.ndjson and {}/truth/", out.display(), out.display());
    Ok(())
}

fn cmd_run(a: RunArgs) -> Result<()> {
    let log = Log::read_path(&a.log).with_context(|| format!("reading {}", a.log.display()))?;
    let mut cfg: FilterConfig = layered(&FilterConfig::from_header(&log.header), a.config.as_deref())?;
    if let Some(n) = a.particles {
        cfg.particles = n;
    }
    if let Some(s) = a.seed {
        cfg.seed = s;
    }
    if let Some(v) = a.version.as_deref() {
        cfg.version = if v == "1" { FastSlamVersion::V1 } else { FastSlamVersion::V2 };
    }
    if let Some(v) = a.association.as_deref() {
        cfg.association = if v == "known" { Association::Known } else { Association::Unknown };
    }
    if a.updater != "ekf" {
        bail!("unknown updater {:?}: this build has `ekf`", a.updater);
    }
    let which = if a.trajectory == "best" { TrajectoryEstimate::Best } else { TrajectoryEstimate::Mean };
    let threads = a.threads.unwrap_or(0);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let mut slam = FastSlam::new(cfg).context("configuring the filter")?;
    let bar = ProgressBar::new(log.records.len() as u64);
    bar.set_style(ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} records ({per_sec}, eta {eta})",
    )?);
    let out = pool.install(|| {
        run_log(&mut slam, &log, which, |done, _| bar.set_position(done as u64))
    })?;
    bar.finish_and_clear();
    out.write(&a.out).with_context(|| format!("writing {}", a.out.display()))?;
    let m = &out.metrics;
    println!(
        "{} steps in {:.2} s (step p50 {:.3} ms, p95 {:.3} ms, max {:.3} ms); {} landmark updates at {:.0} ns each; {} landmarks; {} resamples -> {}",
        m.steps,
        m.wall_time_s,
        m.step_ms_p50,
        m.step_ms_p95,
        m.step_ms_max,
        m.landmark_updates,
        m.ns_per_landmark_update,
        m.landmarks,
        m.resamples,
        a.out.display()
    );
    Ok(())
}

fn cmd_evaluate(a: EvaluateArgs) -> Result<()> {
    let opts = EvalOptions {
        alignment: match a.align.as_str() {
            "none" => Some(Alignment::None),
            "se2" => Some(Alignment::Se2),
            _ => None,
        },
        ..Default::default()
    };
    let ev = evaluate_dir(&a.dir, &a.truth, &opts)?;
    emit(&ev.to_string())?;
    let path = a.dir.join("evaluation.json");
    std::fs::write(&path, serde_json::to_string_pretty(&ev)?)
        .with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}
