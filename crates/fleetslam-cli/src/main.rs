//! The `fleetslam` command.
//!
//! Run with `cargo run --release -p fleetslam-cli -- --help`.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use fleetslam_core::config::{Association, FastSlamVersion, FilterConfig, overlay};
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::Log;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_data::evaluate::{Alignment, EvalOptions, evaluate_dir};
use fleetslam_data::import::{MrclamOptions, VictoriaOptions, import_mrclam, import_victoria_park};
use fleetslam_data::run::{JoinOptions, TrajectoryEstimate, run_log_joining};
use fleetslam_data::sim::{SimConfig, simulate};
use fleetslam_localize::experiment::RtpfExperiment;
use fleetslam_localize::{LateJoinSlam, LocalizeConfig, Policy};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};

/// mimalloc: the filter's steps clone and free many small lists and map nodes, on several
/// threads; it made the speed runs 4-17 % faster than the system allocator (medians, README,
/// session 18).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

mod chart;
mod cluster_bench;
mod experiment;
mod history;
mod learned;
mod localcluster;
mod localize;
mod replay;
mod truth_experiment;

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
    /// Run the server: HTTP and websocket API on the embedded store (or PostgreSQL).
    Serve(ServeArgs),
    /// Play a log into a server as k concurrent robot clients, one per robot.
    Replay(ReplayArgs),
    /// The main job: a server with simulated robots posting to it over HTTP.
    Demo(DemoArgs),
    /// List stored runs with their summaries.
    Runs(history::RunsArgs),
    /// Write a run's trajectories (TUM), landmarks (CSV), metrics and log into a directory.
    Export(history::ExportArgs),
    /// Delete a run and all its data.
    Delete(history::DeleteArgs),
    /// Localization only: localize a log's robots in a fixed map (a finished run's).
    Localize(localize::LocalizeArgs),
    /// Train an MLP landmark updater (burn) on logged landmark updates.
    Train(learned::TrainArgs),
    /// Write the training rows of stored runs as an NDJSON dataset.
    ExportTraining(learned::ExportTrainingArgs),
    /// ns per landmark update of the EKF and MLP models, and whole runs with each.
    BenchUpdaters(learned::BenchArgs),
    /// Cluster figures on this machine: records/s and ack latency with 1, 2, 3 replicas on a
    /// 3-node NATS cluster, and failover time (needs nats-server and PostgreSQL).
    ClusterBench(ClusterBenchArgs),
    /// Reproduce an experiment: `rtpf` (the real-time particle filter paper's), `paper`
    /// (the FastSLAM-MLP paper's four), `mrclam` (EKF against the learned updaters),
    /// `mrclam-truth` (a model trained against ground truth, on unseen robots and time).
    Experiment {
        #[command(subcommand)]
        which: ExperimentCommand,
    },
}

#[derive(Debug, Subcommand)]
enum ExperimentCommand {
    /// Global localization in a symmetric loop with a fixed sample budget and windows of k
    /// records: baseline, skip, naive, uniform and rtpf. Writes errors.csv, times.csv,
    /// speedup.csv and rtpf.png into OUT.
    Rtpf(RtpfArgs),
    /// The FastSLAM-MLP paper's four experiments (Vidal & Rosa 2015, Sec. 5) in simulation.
    Paper(experiment::PaperArgs),
    /// MRCLAM Dataset 6 with models trained on simulated data only.
    Mrclam(experiment::MrclamArgs),
    /// MRCLAM Dataset 6: a model trained against the landmarks' true positions on some
    /// robots and a time span, tested on other robots and a later span.
    MrclamTruth(truth_experiment::MrclamTruthArgs),
}

#[derive(Debug, Args)]
struct RtpfArgs {
    #[arg(long)]
    out: PathBuf,
    /// `building` (the paper-like setting: a 36 m x 12 m hallway loop of 8 identical
    /// modules, dense side-looking scans, windows 4 and 8-12, 2000 samples, 300 records) or
    /// `corridor` (the small symmetric loop: windows 2-14, 3000 samples, 300 records).
    #[arg(long, value_enum, default_value = "building")]
    setting: SettingArg,
    /// Runs per policy and window size (default 30).
    #[arg(long)]
    seeds: Option<usize>,
    /// Window sizes, comma-separated (default: the setting's).
    #[arg(long, value_delimiter = ',')]
    windows: Option<Vec<usize>>,
    /// Policies besides the baseline, comma-separated (default all four).
    #[arg(long, value_delimiter = ',')]
    policies: Option<Vec<PolicyArg>>,
    /// Sample budget per update (default: the setting's).
    #[arg(long)]
    samples: Option<usize>,
    /// Records (seconds) per run (default: the setting's).
    #[arg(long)]
    records: Option<usize>,
    /// Leave out the baseline runs (every record with the full budget), which cost as much
    /// as a window of `k` runs of `k` policies: for ablations that do not change it.
    #[arg(long)]
    no_baseline: bool,
    /// Also run RTPF with oracle weights (policy `oracle`: each window's weight on the
    /// records that saw a distinguishing post), the bound of what the weighting can gain.
    #[arg(long)]
    oracle: bool,
    /// A JSON or TOML file with any RtpfExperiment fields over the setting's; flags given
    /// explicitly win.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum SettingArg {
    Building,
    Corridor,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PolicyArg {
    Skip,
    Naive,
    Uniform,
    Rtpf,
}

impl From<PolicyArg> for Policy {
    fn from(p: PolicyArg) -> Self {
        match p {
            PolicyArg::Skip => Policy::Skip,
            PolicyArg::Naive => Policy::Naive,
            PolicyArg::Uniform => Policy::Uniform,
            PolicyArg::Rtpf => Policy::Rtpf,
        }
    }
}

/// `serve`'s flags: the top layer of the server's configuration
/// ([`fleetslam_server::config::ServerConfig::load`]); a flag not given leaves the layers
/// below (defaults, the TOML file, `FLEETSLAM_*` variables).
#[derive(Debug, Args, serde::Serialize)]
struct ServeArgs {
    /// A TOML file (see fleetslam.example.toml); FLEETSLAM_* variables and flags override it.
    #[arg(long)]
    #[serde(skip)]
    config: Option<PathBuf>,
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    bind: Option<String>,
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    data_dir: Option<PathBuf>,
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    database_url: Option<String>,
    /// Token for creating, ending and deleting runs and registering robots (at least 16
    /// characters); required to serve a non-loopback address.
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    admin_token: Option<String>,
    /// Token for reading (state, runs, exports, metrics) when reads need one.
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    read_token: Option<String>,
    /// Serve as one replica of a cluster: records through NATS JetStream (--nats), runs
    /// owned by lease, the store in PostgreSQL (--database-url) shared by every replica.
    #[arg(long)]
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    cluster: bool,
    /// NATS servers (comma-separated) for --cluster.
    #[arg(long)]
    #[serde(rename = "nats_url", skip_serializing_if = "Option::is_none")]
    nats: Option<String>,
    /// This replica's name in the cluster (default: a random one).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    replica_id: Option<String>,
    /// Replicas of the record stream and lease buckets (3 on a 3-node NATS cluster).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    stream_replicas: Option<usize>,
    /// Also stream live runs to Foxglove over its WebSocket protocol on this address
    /// (e.g. 127.0.0.1:8765; in Foxglove: Open connection, Foxglove WebSocket,
    /// ws://127.0.0.1:8765).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    foxglove_bind: Option<String>,
}

#[derive(Debug, Args)]
struct ReplayArgs {
    log: PathBuf,
    /// The server's base URL; several (comma-separated or repeated) for a cluster's
    /// replicas: the robots are spread over them and move on when one fails.
    #[arg(long, default_value = "http://127.0.0.1:8080", value_delimiter = ',', num_args = 1..)]
    server: Vec<String>,
    /// Join an existing run (its robots must not be registered yet) instead of creating one.
    #[arg(long)]
    run: Option<String>,
    /// Data time runs this many times faster than real time.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// As fast as the server acknowledges (ignores --speed).
    #[arg(long)]
    fast: bool,
    /// Most records per request.
    #[arg(long, default_value_t = 50)]
    batch: usize,
    #[arg(long)]
    particles: Option<usize>,
    #[arg(long)]
    seed: Option<u64>,
    /// A JSON or TOML file of FilterConfig fields for the new run.
    #[arg(long)]
    config: Option<PathBuf>,
    #[arg(long, env = "FLEETSLAM_ADMIN_TOKEN")]
    admin_token: Option<String>,
    /// Leave the run open when the log is done (default: end it if the replay created it).
    #[arg(long)]
    keep_open: bool,
    /// The new run stores this fraction of its landmark updates as training rows for the
    /// learned updater (`fleetslam export-training`).
    #[arg(long)]
    log_training: Option<f64>,
    /// A ground-truth directory (as `import` and `simulate` write) to upload with the run,
    /// for the dashboard's overlay and GET /v1/runs/{id}/evaluation.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// A request that failed for a reason that may pass (no answer, 5xx, 503/429 busy) is
    /// retried after this many seconds at first, then doubling waits (each plus a random
    /// jitter of up to its own length), and never sooner than the server's Retry-After.
    #[arg(long, value_name = "SECONDS", default_value_t = replay::RetryPolicy::DEFAULT.min_delay.as_secs_f64())]
    retry_min_delay: f64,
    /// The longest wait between retries, in seconds, before jitter (Retry-After may ask
    /// for longer).
    #[arg(long, value_name = "SECONDS", default_value_t = replay::RetryPolicy::DEFAULT.max_delay.as_secs_f64())]
    retry_max_delay: f64,
    /// Give up on a request (and fail the replay) when its next attempt would start more
    /// than this many seconds after its first; the default survives a server restart.
    #[arg(long, value_name = "SECONDS", default_value_t = replay::RetryPolicy::DEFAULT.max_elapsed.as_secs_f64())]
    retry_max_elapsed: f64,
    /// Also give up on a request after this many attempts (default: only
    /// --retry-max-elapsed bounds them).
    #[arg(long, value_name = "N")]
    retry_max_attempts: Option<usize>,
}

#[derive(Debug, Args)]
struct ClusterBenchArgs {
    /// A PostgreSQL server where the bench may create (and drops) its databases.
    #[arg(long, default_value = "postgres://postgres@127.0.0.1:5432/test")]
    database_url: String,
    /// Replica counts to measure, comma-separated.
    #[arg(long, default_value = "1,2,3", value_delimiter = ',')]
    replicas: Vec<usize>,
    /// Runs posting at once (3 simulated robots each).
    #[arg(long, default_value_t = 6)]
    runs: usize,
    /// Simulated seconds per run.
    #[arg(long, default_value_t = 60.0)]
    duration: f64,
    /// Records per request.
    #[arg(long, default_value_t = 20)]
    batch: usize,
    /// The nats-server binary (default: where Debian's package puts it).
    #[arg(long)]
    nats_server: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct DemoArgs {
    #[arg(long, default_value = "127.0.0.1:8080")]
    bind: String,
    #[arg(long, default_value = "data")]
    data_dir: PathBuf,
    #[arg(long, default_value_t = 4)]
    robots: usize,
    #[arg(long, default_value_t = 200)]
    particles: usize,
    /// Simulated seconds per run; the demo starts a new run when one ends.
    #[arg(long, default_value_t = 300.0)]
    duration: f64,
    /// Data time runs this many times faster than real time.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(Debug, Args)]
struct SimulateArgs {
    /// Robots [default: the config file's, else 3].
    #[arg(long)]
    robots: Option<usize>,
    /// Randomly placed landmarks [default: the config file's, else 20].
    #[arg(long)]
    landmarks: Option<usize>,
    /// Landmark kind [default: the config file's, else range_bearing_2d].
    #[arg(long, value_enum)]
    kind: Option<KindArg>,
    /// Simulated time [s] [default: the config file's, else 60].
    #[arg(long)]
    duration: Option<f64>,
    /// [default: the config file's, else 0]
    #[arg(long)]
    seed: Option<u64>,
    /// Leave landmark ids out of the observations (unknown data association).
    #[arg(long)]
    no_ids: bool,
    /// A JSON or TOML file with any SimConfig fields; flags given explicitly win, and a
    /// field the file sets keeps its value unless its flag is given.
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
        /// Seconds added to odometry times (odometry leads Vicon by 0.15-0.2 s; 0 keeps
        /// the data as recorded).
        #[arg(long, default_value_t = fleetslam_data::import::SUGGESTED_ODOMETRY_DELAY)]
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
        /// GPS spike test: a fix farther from each neighbour than this speed [m/s] times
        /// the time between them plus `--gps-jitter` is dropped from the truth (reported).
        #[arg(long, default_value_t = VictoriaOptions::default().gps_max_speed)]
        gps_max_speed: f64,
        /// GPS spike test: how far [m] the GPS jumps by itself between fixes.
        #[arg(long, default_value_t = VictoriaOptions::default().gps_jitter)]
        gps_jitter: f64,
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
    /// Landmark updater: `ekf`, or an MLP model file (`model.json` or a `fleetslam train`
    /// output directory) [default: ekf; a config file that names another updater needs
    /// its model file here].
    #[arg(long)]
    updater: Option<String>,
    #[command(flatten)]
    learned: learned::RunLearnedArgs,
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
    /// Forget this robot's start pose: it is localized in the others' map and merged when
    /// localized (repeatable). Robots the header gives no start are always localized.
    #[arg(long)]
    unknown: Vec<String>,
    /// The --unknown robots' records before this time [s, log time] are dropped: they join
    /// the run then.
    #[arg(long)]
    join_at: Option<f64>,
    /// A JSON or TOML file with any LocalizeConfig fields, for the joining robots.
    #[arg(long)]
    localize_config: Option<PathBuf>,
    /// Real-time policy of the joining robots' localizers (for windows of several records).
    #[arg(long, value_enum)]
    policy: Option<PolicyArg>,
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
    /// Truth landmarks closer than this (m) to each other count as one group at their centre
    /// (for maps without ids, whose sensor cannot tell such landmarks apart).
    #[arg(long)]
    group_within: Option<f64>,
    /// Largest distance (m) of a nearest-neighbour landmark match.
    #[arg(long, default_value_t = 1.0)]
    landmark_match_radius: f64,
    /// Distance (m) the truth travels between the two poses of a relative pose error.
    #[arg(long, default_value_t = 1.0)]
    rpe_distance: f64,
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
        Command::Serve(a) => runtime()?.block_on(cmd_serve(a)),
        Command::Replay(a) => runtime()?.block_on(cmd_replay(a)),
        Command::Demo(a) => runtime()?.block_on(cmd_demo(a)),
        Command::Runs(a) => runtime()?.block_on(history::cmd_runs(a)),
        Command::Export(a) => runtime()?.block_on(history::cmd_export(a)),
        Command::Delete(a) => runtime()?.block_on(history::cmd_delete(a)),
        Command::Localize(a) => {
            let cfg = layered(&LocalizeConfig::default(), a.localize_config())?;
            localize::cmd_localize(a, cfg)
        }
        Command::Train(a) => learned::cmd_train(a),
        Command::ExportTraining(a) => learned::cmd_export_training(a),
        Command::BenchUpdaters(a) => learned::cmd_bench_updaters(a),
        Command::ClusterBench(a) => {
            runtime()?.block_on(cluster_bench::run(cluster_bench::BenchOptions {
                database_url: a.database_url,
                replicas: a.replicas,
                runs: a.runs,
                duration_s: a.duration,
                batch: a.batch,
                nats_server: a.nats_server,
            }))
        }
        Command::Experiment { which } => match which {
            ExperimentCommand::Rtpf(a) => cmd_experiment_rtpf(a),
            ExperimentCommand::Paper(a) => {
                experiment::cmd_experiment(experiment::ExperimentCommand::Paper(a))
            }
            ExperimentCommand::MrclamTruth(a) => truth_experiment::cmd_mrclam_truth(a),
            ExperimentCommand::Mrclam(a) => {
                experiment::cmd_experiment(experiment::ExperimentCommand::Mrclam(a))
            }
        },
    }
}

/// Reads a JSON or TOML file (by extension) into a JSON value, for layering over defaults.
fn read_config_value(path: &Path) -> Result<serde_json::Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let v = if path.extension().is_some_and(|e| e == "toml") {
        let t: toml::Value =
            toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        serde_json::to_value(t)?
    } else {
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
    };
    Ok(v)
}

/// `base` with the fields of a JSON or TOML file over it, when one is given.
fn layered<T: serde::Serialize + serde::de::DeserializeOwned>(
    base: &T,
    file: Option<&Path>,
) -> Result<T> {
    let patch = match file {
        Some(path) => read_config_value(path)?,
        None => serde_json::Value::Null,
    };
    overlay(base, patch).with_context(|| match file {
        Some(p) => format!("invalid configuration in {}", p.display()),
        None => "invalid configuration".into(),
    })
}

fn cmd_simulate(a: SimulateArgs) -> Result<()> {
    let mut cfg: SimConfig = layered(&SimConfig::default(), a.config.as_deref())?;
    if let Some(v) = a.robots {
        cfg.robots = v;
    }
    if let Some(v) = a.landmarks {
        cfg.landmarks = v;
    }
    if let Some(v) = a.kind {
        cfg.kind = v.into();
    }
    if let Some(v) = a.duration {
        cfg.duration = v;
    }
    if let Some(v) = a.seed {
        cfg.seed = v;
    }
    if a.no_ids {
        cfg.with_ids = false;
    }
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
        ImportCommand::Mrclam {
            dir,
            out,
            no_ids,
            duration,
            odometry_delay,
        } => {
            let opts = MrclamOptions {
                no_ids,
                duration,
                odometry_delay,
                ..Default::default()
            };
            (import_mrclam(&dir, &opts)?, out)
        }
        ImportCommand::VictoriaPark {
            dir,
            out,
            duration,
            max_range,
            gps_max_speed,
            gps_jitter,
        } => {
            let opts = VictoriaOptions {
                duration,
                max_range,
                gps_max_speed,
                gps_jitter,
                ..Default::default()
            };
            (import_victoria_park(&dir, &opts)?, out)
        }
    };
    imported.write(&out)?;
    println!("{}", imported.report);
    println!(
        "wrote {}/log.ndjson and {}/truth/",
        out.display(),
        out.display()
    );
    Ok(())
}

fn cmd_run(a: RunArgs) -> Result<()> {
    let log = Log::read_path(&a.log).with_context(|| format!("reading {}", a.log.display()))?;
    let mut cfg: FilterConfig =
        layered(&FilterConfig::from_header(&log.header), a.config.as_deref())?;
    if let Some(n) = a.particles {
        cfg.particles = n;
    }
    if let Some(s) = a.seed {
        cfg.seed = s;
    }
    if let Some(v) = a.version.as_deref() {
        cfg.version = if v == "1" {
            FastSlamVersion::V1
        } else {
            FastSlamVersion::V2
        };
    }
    if let Some(v) = a.association.as_deref() {
        cfg.association = if v == "known" {
            Association::Known
        } else {
            Association::Unknown
        };
    }
    let spec = match &a.updater {
        Some(spec) => spec.clone(),
        None if cfg.updater == "ekf" => "ekf".into(),
        None => bail!(
            "the configuration names updater {:?}: give its model file with --updater",
            cfg.updater
        ),
    };
    let updater = learned::updater_from_spec(&spec, &mut cfg)?;
    let (updater, recorder) = learned::maybe_record(updater, &a.learned)?;
    let which = if a.trajectory == "best" {
        TrajectoryEstimate::Best
    } else {
        TrajectoryEstimate::Mean
    };
    let threads = a.threads.unwrap_or(0);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let mut localize: LocalizeConfig =
        layered(&LocalizeConfig::default(), a.localize_config.as_deref())?;
    if let Some(p) = a.policy {
        localize.policy = p.into();
    }
    let slam = FastSlam::with_updater(cfg, updater).context("configuring the filter")?;
    let mut run = LateJoinSlam::from_slam(slam, localize.clone())
        .context("configuring the localization of joining robots")?;
    let opts = JoinOptions {
        unknown: a.unknown.clone(),
        join_at: a.join_at,
        localize,
    };
    let bar = ProgressBar::new(log.records.len() as u64);
    bar.set_style(ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} records ({per_sec}, eta {eta})",
    )?);
    let out = pool.install(|| {
        run_log_joining(&mut run, &log, which, &opts, |done, _| {
            bar.set_position(done as u64)
        })
    })?;
    bar.finish_and_clear();
    out.write(&a.out)
        .with_context(|| format!("writing {}", a.out.display()))?;
    learned::write_recorded(recorder.as_deref(), &a.learned)?;
    let m = &out.metrics;
    println!(
        "{} steps in {:.2} s (step p50 {:.3} ms, p95 {:.3} ms, max {:.3} ms; {:.0} ns per particle and record, {:.0} per particle and observation); {} landmark updates at {:.0} ns each; {} landmarks; {} resamples -> {}",
        m.steps,
        m.wall_time_s,
        m.step_ms_p50,
        m.step_ms_p95,
        m.step_ms_max,
        m.ns_per_particle_record,
        m.ns_per_particle_observation,
        m.landmark_updates,
        m.ns_per_landmark_update,
        m.landmarks,
        m.resamples,
        a.out.display()
    );
    for j in &m.joiners {
        match j.joined_at {
            Some(t) => println!(
                "robot {} joined at t={t:.2} after {} localization updates ({} samples now)",
                j.id, j.localization.stats.updates, j.localization.samples
            ),
            None => println!(
                "robot {} did not localize: {} updates, position spread {:.2} m",
                j.id, j.localization.stats.updates, j.localization.position_spread
            ),
        }
    }
    Ok(())
}

fn cmd_experiment_rtpf(a: RtpfArgs) -> Result<()> {
    use fleetslam_localize::experiment::Setting;
    let setting = match a.setting {
        SettingArg::Building => Setting::Building,
        SettingArg::Corridor => Setting::Corridor,
    };
    let mut exp: RtpfExperiment = layered(&RtpfExperiment::preset(setting), a.config.as_deref())?;
    if let Some(v) = a.seeds {
        exp.seeds = v;
    }
    if let Some(v) = &a.windows {
        exp.windows = v.clone();
    }
    if let Some(v) = &a.policies {
        exp.policies = v.iter().map(|p| (*p).into()).collect();
    }
    if let Some(v) = a.samples {
        exp.samples = v;
    }
    if let Some(v) = a.records {
        exp.records = v;
    }
    if a.no_baseline {
        exp.baseline = false;
    }
    if a.oracle {
        exp.oracle = true;
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(a.threads.unwrap_or(0))
        .build()?;
    let runs = exp.seeds
        * (usize::from(exp.baseline)
            + exp.windows.len() * (exp.policies.len() + usize::from(exp.oracle)));
    let bar = ProgressBar::new(runs as u64);
    bar.set_style(ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} runs (eta {eta})",
    )?);
    let started = std::time::Instant::now();
    let results = pool.install(|| exp.run(|done, _| bar.set_position(done as u64)))?;
    bar.finish_and_clear();
    let sums = fleetslam_localize::experiment::write_outputs(&exp, &results, &a.out)?;
    println!(
        "{runs} runs in {:.1} s -> {}",
        started.elapsed().as_secs_f64(),
        a.out.display()
    );
    let speed = fleetslam_localize::experiment::speedups(&results, exp.records as f64);
    println!(
        "{}",
        fleetslam_localize::experiment::markdown_table(&sums, &speed, exp.records as f64)
    );
    if exp.oracle {
        for x in fleetslam_localize::experiment::speedups_of(&results, "oracle", exp.records as f64)
        {
            println!(
                "oracle speedup over skip, window {}: {:.2}x [{:.2}, {:.2}]",
                x.window, x.speedup, x.ci_low, x.ci_high
            );
        }
        println!();
    }
    println!(
        "{}",
        fleetslam_localize::experiment::diagnostics_table(&sums)
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
        group_within: a.group_within,
        landmark_match_radius: a.landmark_match_radius,
        rpe_distance: a.rpe_distance,
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

fn runtime() -> Result<tokio::runtime::Runtime> {
    init_tracing();
    Ok(tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?)
}

/// Logs to stderr, filtered by RUST_LOG (default: info for fleetslam, warn otherwise).
fn init_tracing() {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        EnvFilter::new("warn,fleetslam=info,fleetslam_server=info,fleetslam_store=info")
    });
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(ansi)
        .with_writer(std::io::stderr)
        .try_init();
}

async fn cmd_serve(a: ServeArgs) -> Result<()> {
    use fleetslam_server::config::ServerConfig;
    let cfg = ServerConfig::load(a.config.as_deref(), &a).map_err(anyhow::Error::msg)?;
    let running = fleetslam_server::server::start(&cfg).await?;
    println!(
        "fleetslam serving on http://{} (store: {})",
        running.addr,
        running.store.backend()
    );
    if let Some(f) = running.foxglove {
        println!("Foxglove live view: ws://{f} (Foxglove: Open connection, Foxglove WebSocket)");
    }
    let signal = fleetslam_server::server::shutdown_signal().await?;
    // On stderr: stdout may be a pipe nobody reads any more.
    eprintln!("{signal}: stopping (answering requests under way, storing snapshots)");
    running.stop().await
}

fn replay_options(a: &ReplayArgs) -> Result<replay::ReplayOptions> {
    let mut config = match &a.config {
        Some(p) => read_config_value(p)?,
        None => serde_json::json!({}),
    };
    if let Some(n) = a.particles {
        config["particles"] = n.into();
    }
    if let Some(s) = a.seed {
        config["seed"] = s.into();
    }
    if !(a.speed.is_finite() && a.speed > 0.0) {
        bail!("--speed must be > 0, got {}", a.speed);
    }
    let seconds = |flag: &str, s: f64| {
        std::time::Duration::try_from_secs_f64(s)
            .ok()
            .filter(|d| !d.is_zero())
            .with_context(|| format!("{flag} must be a number of seconds > 0, got {s}"))
    };
    let retry = replay::RetryPolicy {
        min_delay: seconds("--retry-min-delay", a.retry_min_delay)?,
        max_delay: seconds("--retry-max-delay", a.retry_max_delay)?,
        max_elapsed: seconds("--retry-max-elapsed", a.retry_max_elapsed)?,
        max_attempts: a.retry_max_attempts,
    };
    if retry.max_delay < retry.min_delay {
        bail!(
            "--retry-max-delay ({}) must not be below --retry-min-delay ({})",
            a.retry_max_delay,
            a.retry_min_delay
        );
    }
    if retry.max_attempts == Some(0) {
        bail!("--retry-max-attempts must be at least 1");
    }
    Ok(replay::ReplayOptions {
        servers: a.server.clone(),
        run: a.run.clone(),
        config,
        admin_token: a.admin_token.clone(),
        pace: if a.fast {
            replay::Pace::Fast
        } else {
            replay::Pace::Scaled(a.speed)
        },
        batch: a.batch,
        progress: true,
        training_rate: a.log_training,
        retry,
    })
}

/// Ends a run through the first of `servers` that answers.
async fn end_run(servers: &[String], run: &str, admin: Option<&str>) -> Result<()> {
    let mut last = None;
    for server in servers {
        let mut req = reqwest::Client::new().post(format!(
            "{}/v1/runs/{run}/end",
            server.trim_end_matches('/')
        ));
        if let Some(t) = admin {
            req = req.bearer_auth(t);
        }
        match req.send().await {
            Ok(resp) if resp.status().is_success() => return Ok(()),
            Ok(resp) if !resp.status().is_server_error() => {
                bail!("ending run {run}: {}", resp.status())
            }
            Ok(resp) => last = Some(anyhow::anyhow!("ending run {run}: {}", resp.status())),
            Err(e) => last = Some(anyhow::Error::new(e).context(format!("ending run {run}"))),
        }
    }
    Err(last.unwrap_or_else(|| anyhow::anyhow!("ending run {run}: no server given")))
}

async fn cmd_replay(a: ReplayArgs) -> Result<()> {
    let log = Log::read_path(&a.log).with_context(|| format!("reading {}", a.log.display()))?;
    let o = replay_options(&a)?;
    let (run, tokens) = replay::setup(&log, &o).await?;
    println!("run {run}");
    if let Some(dir) = &a.truth {
        let truth = fleetslam_data::formats::Truth::read_dir(dir)
            .with_context(|| format!("reading ground truth from {}", dir.display()))?;
        replay::put_truth(&o, &run, &truth).await?;
    }
    let summary = replay::play(&log, &run, tokens, &o).await?;
    if a.run.is_none() && !a.keep_open {
        end_run(&a.server, &run, a.admin_token.as_deref()).await?;
    }
    println!("{summary}");
    Ok(())
}

async fn cmd_demo(a: DemoArgs) -> Result<()> {
    let cfg = fleetslam_server::config::ServerConfig {
        bind: a.bind.clone(),
        data_dir: a.data_dir.clone(),
        ..Default::default()
    };
    let running = fleetslam_server::server::start(&cfg).await?;
    let server = format!("http://{}", running.addr);
    println!(
        "fleetslam demo: server on {server} (store: {} in {})",
        running.store.backend(),
        a.data_dir.display()
    );
    let demo = async {
        let mut seed = a.seed;
        loop {
            let sim = simulate(&SimConfig {
                robots: a.robots,
                landmarks: 30,
                duration: a.duration,
                seed,
                ..SimConfig::default()
            })?;
            let o = replay::ReplayOptions {
                servers: vec![server.clone()],
                run: None,
                config: serde_json::json!({"particles": a.particles, "seed": seed}),
                admin_token: None,
                pace: replay::Pace::Scaled(a.speed),
                batch: 50,
                progress: false,
                training_rate: None,
                retry: replay::RetryPolicy::default(),
            };
            let (run, tokens) = replay::setup(&sim.log, &o).await?;
            replay::put_truth(&o, &run, &sim.truth).await?;
            println!("run {run}: {} simulated robots posting over HTTP", a.robots);
            println!("  dashboard: {server}/#/run/{run}");
            println!("  state:     {server}/v1/runs/{run}/state");
            println!("  live:      ws://{}/v1/runs/{run}/live", running.addr);
            let summary = replay::play(&sim.log, &run, tokens, &o).await?;
            end_run(std::slice::from_ref(&server), &run, None).await?;
            println!("{summary}");
            seed += 1;
        }
        #[allow(unreachable_code)]
        Ok::<(), anyhow::Error>(())
    };
    tokio::select! {
        r = demo => r?,
        r = fleetslam_server::server::shutdown_signal() => { println!("{}: stopping", r?); }
    }
    running.stop().await
}
