//! The learned updater's commands: `train`, `export-training`, `bench-updaters`, and the
//! `run` options that pick an MLP model and log training rows.

use anyhow::{Context, Result, bail};
use clap::Args;
use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::Log;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_core::updater::{LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput};
use fleetslam_data::run::{RunOutput, TrajectoryEstimate, run_log};
use fleetslam_learned::dataset::synthetic_rows;
use fleetslam_learned::kernel::{Arch, Kernel, LANES, Scratch};
use fleetslam_learned::row::{read_ndjson_path, write_ndjson_path};
use fleetslam_learned::training::{
    BurnPredictor, TrainConfig, Trained, save_model_dir, train, train_split,
};
use fleetslam_learned::{
    MlpModel, MlpUpdater, RecordingConfig, RecordingUpdater, RunSplit, STORE_MODEL_KIND,
    TrainingRow,
};
use fleetslam_store::{NewModel, Store};
use indicatif::{ProgressBar, ProgressStyle};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// `run`'s options for the learned updater and training rows.
#[derive(Debug, Args, Clone)]
pub struct RunLearnedArgs {
    /// Write a sample of the run's landmark updates as training rows (NDJSON) to FILE.
    #[arg(long, value_name = "FILE")]
    pub log_training: Option<PathBuf>,
    /// Fraction of landmark updates logged (0..=1).
    #[arg(long, default_value_t = RecordingConfig::default().rate)]
    pub training_rate: f64,
    /// Most rows logged.
    #[arg(long, default_value_t = RecordingConfig::default().cap)]
    pub training_cap: usize,
    /// Seed of the row sampling hash.
    #[arg(long, default_value_t = 0)]
    pub training_seed: u64,
}

/// The updater `spec` names: `ekf`, or the path of a model file (`model.json` or a
/// directory written by `fleetslam train`). Sets `cfg.updater` to the updater's name.
pub fn updater_from_spec(spec: &str, cfg: &mut FilterConfig) -> Result<Arc<dyn LandmarkUpdater>> {
    if spec == "ekf" {
        cfg.updater = "ekf".into();
        return Ok(Arc::new(EkfUpdater::new(
            cfg.landmark_kind,
            &cfg.sensor_noise,
        )));
    }
    let model = load_model(Path::new(spec)).with_context(|| {
        format!("--updater {spec:?} is neither `ekf` nor a readable model file")
    })?;
    cfg.updater = model.id.clone();
    Ok(Arc::new(MlpUpdater::for_run(model, cfg)?))
}

/// Reads a model from `model.json` or a directory holding one.
pub fn load_model(path: &Path) -> Result<MlpModel> {
    let file = if path.is_dir() {
        path.join("model.json")
    } else {
        path.to_path_buf()
    };
    Ok(MlpModel::read_path(&file)?)
}

/// The recorder of a run, when it logs training rows.
pub type Recorder = Option<Arc<RecordingUpdater>>;

/// Wraps `updater` in a recorder when `--log-training` is given.
pub fn maybe_record(
    updater: Arc<dyn LandmarkUpdater>,
    a: &RunLearnedArgs,
) -> Result<(Arc<dyn LandmarkUpdater>, Recorder)> {
    if a.log_training.is_none() {
        return Ok((updater, None));
    }
    let rec = Arc::new(RecordingUpdater::new(
        updater,
        RecordingConfig {
            rate: a.training_rate,
            cap: a.training_cap,
            seed: a.training_seed,
        },
    )?);
    Ok((rec.clone(), Some(rec)))
}

/// Writes the recorder's rows to `--log-training`.
pub fn write_recorded(rec: Option<&RecordingUpdater>, a: &RunLearnedArgs) -> Result<()> {
    if let (Some(rec), Some(path)) = (rec, a.log_training.as_deref()) {
        let seen = rec.seen();
        let rows = rec.drain_rows();
        write_ndjson_path(path, &rows)?;
        println!(
            "logged {} training rows of {seen} landmark updates -> {}",
            rows.len(),
            path.display()
        );
    }
    Ok(())
}

// ---------------------------------------------------------------------------- store access

#[derive(Debug, Args, Clone, Default)]
pub struct StoreArgs {
    /// Database URL (sqlite://... or postgres://...).
    #[arg(long, value_name = "URL", conflicts_with = "data_dir")]
    pub store: Option<String>,
    /// The embedded store's data directory (as `fleetslam serve --data-dir`).
    #[arg(long, value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
}

impl StoreArgs {
    pub fn given(&self) -> bool {
        self.store.is_some() || self.data_dir.is_some()
    }

    async fn open(&self) -> Result<Store> {
        Ok(match (&self.store, &self.data_dir) {
            (Some(url), _) => Store::open(url)
                .await
                .with_context(|| format!("opening store {url}"))?,
            (None, Some(dir)) => Store::open_default(dir)
                .await
                .with_context(|| format!("opening the store in {}", dir.display()))?,
            (None, None) => bail!("give --store URL or --data-dir DIR"),
        })
    }
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?)
}

// ---------------------------------------------------------------------------- export-training

#[derive(Debug, Args)]
pub struct ExportTrainingArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    /// Runs whose rows to export (repeat the flag); all runs when none is given.
    #[arg(long = "run", value_name = "ID")]
    pub runs: Vec<String>,
    /// Most rows exported.
    #[arg(long, default_value_t = 10_000_000)]
    pub limit: i64,
    /// The NDJSON dataset to write.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn cmd_export_training(a: ExportTrainingArgs) -> Result<()> {
    let bodies = runtime()?.block_on(async {
        let store = a.store.open().await?;
        let rows = store.training_rows(&a.runs, a.limit).await?;
        store.close().await;
        anyhow::Ok(rows)
    })?;
    let rows = bodies
        .iter()
        .enumerate()
        .map(|(i, b)| TrainingRow::from_json(b).with_context(|| format!("stored row {i}")))
        .collect::<Result<Vec<_>>>()?;
    write_ndjson_path(&a.out, &rows)?;
    println!(
        "exported {} training rows -> {}",
        rows.len(),
        a.out.display()
    );
    Ok(())
}

// ---------------------------------------------------------------------------- train

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Training rows of one run (NDJSON, from `run --log-training` or `export-training`);
    /// repeat it for every run. Runs, never rows, are split into training, validation and
    /// test sets, so at least 3 are needed.
    #[arg(long = "data", value_name = "FILE", required = true)]
    pub data: Vec<PathBuf>,
    /// Starting point: `paper` (the paper's 2-neuron linear network), `default` (2 × 32
    /// ReLU on whitened features and innovation), `structured` (gain and posterior factor
    /// from the prior and noise) or `truth` (the default's inputs and the distance, mean
    /// learned from the landmarks' true positions: rows must carry `truth`, as those of
    /// `experiment mrclam-truth` do).
    #[arg(long, value_parser = TrainConfig::PRESETS, default_value = "default")]
    pub preset: String,
    /// Model id (the updater name runs use); default `mlp-<preset>-<kind>`.
    #[arg(long)]
    pub id: Option<String>,
    /// Hidden widths, comma-separated (e.g. 64,64).
    #[arg(long, value_delimiter = ',')]
    pub hidden: Option<Vec<usize>>,
    #[arg(long, value_parser = ["relu", "tanh", "identity"])]
    pub activation: Option<String>,
    #[arg(long, value_parser = ["sgd", "adam"])]
    pub optimizer: Option<String>,
    #[arg(long)]
    pub lr: Option<f64>,
    #[arg(long)]
    pub epochs: Option<usize>,
    #[arg(long)]
    pub batch_size: Option<usize>,
    /// Runs held out for validation (early stopping).
    #[arg(long)]
    pub val_runs: Option<usize>,
    /// Runs held out for the test report (0: none).
    #[arg(long)]
    pub test_runs: Option<usize>,
    #[arg(long)]
    pub seed: Option<u64>,
    #[arg(long)]
    pub patience: Option<usize>,
    /// Posterior covariance of the default layout: the network's or the EKF's closed form.
    #[arg(long, value_parser = ["network", "closed-form"])]
    pub covariance: Option<String>,
    /// What the posterior mean learns: the EKF's (`ekf`) or the landmarks' true positions
    /// (`truth`; the `truth` preset's choice).
    #[arg(long, value_parser = ["ekf", "truth"])]
    pub target: Option<String>,
    /// Output directory: model.json, model.bpk, config.json, report.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Register the model in this store too.
    #[command(flatten)]
    pub store: StoreArgs,
}

impl TrainArgs {
    fn config(&self, kind: LandmarkKind) -> Result<TrainConfig> {
        let id = self
            .id
            .clone()
            .unwrap_or_else(|| format!("mlp-{}-{}", self.preset, kind.as_str()));
        let mut c = TrainConfig::preset(&self.preset, &id)?;
        c.kind = Some(kind);
        if let Some(h) = &self.hidden {
            c.hidden = h.clone();
        }
        if let Some(a) = &self.activation {
            c.activation = a.parse()?;
        }
        if let Some(o) = &self.optimizer {
            c.optimizer = o.parse()?;
        }
        if let Some(v) = &self.covariance {
            c.covariance = v.parse()?;
        }
        if let Some(v) = &self.target {
            c.target = v.parse()?;
        }
        macro_rules! set {
            ($($f:ident),*) => { $( if let Some(v) = self.$f { c.$f = v; } )* };
        }
        set!(lr, epochs, batch_size, val_runs, test_runs, seed, patience);
        c.validate()?;
        Ok(c)
    }
}

/// Trains on `runs` (the rows of each run) with a progress bar showing the losses.
pub fn train_with_progress(runs: &[Vec<TrainingRow>], cfg: &TrainConfig) -> Result<Trained> {
    let n: usize = runs.iter().map(Vec::len).sum();
    with_progress(cfg, &format!("{n} rows, {} runs", runs.len()), |p| {
        Ok(train(runs, cfg, p)?)
    })
}

/// Trains on a split the caller made (by robot and time span), with a progress bar.
pub fn train_split_with_progress(sets: RunSplit, cfg: &TrainConfig) -> Result<Trained> {
    let what = format!(
        "{} / {} / {} rows",
        sets.train.len(),
        sets.val.len(),
        sets.test.len()
    );
    with_progress(cfg, &what, |p| Ok(train_split(sets, cfg, p)?))
}

fn with_progress(
    cfg: &TrainConfig,
    what: &str,
    f: impl FnOnce(&mut dyn FnMut(usize, usize, f64, f64)) -> Result<Trained>,
) -> Result<Trained> {
    let bar = ProgressBar::new(cfg.epochs as u64);
    bar.set_style(ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {bar:30} epoch {pos}/{len} {msg}",
    )?);
    bar.set_message(format!("{} ({what})", cfg.id));
    let t = f(&mut |epoch, _, tl, vl| {
        bar.set_position(epoch as u64);
        bar.set_message(format!("{}: train loss {tl:.5}, val loss {vl:.5}", cfg.id));
    })?;
    bar.finish_and_clear();
    Ok(t)
}

pub fn print_report(t: &Trained) {
    let r = &t.report;
    println!(
        "model {} ({}, {} layout, hidden {:?} {}, {:?}): {} train / {} validation / {} test rows \
         (runs {:?} / {:?} / {:?}), {} skipped; \
         {} epochs (best {}) in {:.1} s; validation loss {:.5} -> {:.5} (standardised MSE)",
        t.model.id,
        r.kind.as_str(),
        t.model.layout.as_str(),
        t.config.hidden,
        t.config.activation.as_str(),
        t.config.optimizer,
        r.train_rows,
        r.val_rows,
        r.test_rows,
        r.train_runs,
        r.val_runs,
        r.test_runs,
        r.skipped_rows,
        r.epochs_run,
        r.best_epoch,
        r.seconds,
        r.first_val_loss,
        r.best_val_loss,
    );
    println!(
        "sensor noise estimated from the EKF updates: range {:.4} m, bearing {:.4} rad, xyz {:.4?} m",
        r.noise.range, r.noise.bearing, r.noise.xyz
    );
    let Some(u) = &r.updater else {
        println!("no test runs: no test report");
        return;
    };
    println!("test error of each network output (test runs only):");
    for o in &r.outputs {
        println!(
            "  {:<10} RMSE {:.6} ({:.4} of its std)",
            o.name, o.rmse, o.normalized_rmse
        );
    }
    println!(
        "the updater against the EKF on {} test rows: posterior mean RMSE {:.5} m \
         (not updating: {:.5} m), covariance relative RMSE {:.4}, log-likelihood RMSE {:.2e}, \
         Mahalanobis² RMSE {:.2e}, {} rejected",
        u.rows,
        u.mean_rmse,
        u.no_update_rmse,
        u.cov_rel_rmse,
        u.log_likelihood_rmse,
        u.mahalanobis2_rmse,
        u.rejected
    );
    if let Some(t) = &u.truth {
        println!(
            "against the landmarks' true positions on {} test rows: posterior mean RMSE {:.5} m \
             (the EKF's: {:.5} m, not updating: {:.5} m)",
            t.rows, t.updater_rmse, t.ekf_rmse, t.prior_rmse
        );
    }
}

/// Registers a trained model in a store.
pub fn register(store: &StoreArgs, t: &Trained) -> Result<()> {
    runtime()?.block_on(async {
        let s = store.open().await?;
        s.put_model(&NewModel {
            id: t.model.id.clone(),
            kind: STORE_MODEL_KIND.into(),
            config: serde_json::to_value(&t.config)?,
            metrics: serde_json::to_value(&t.report)?,
            weights: t.model.to_json(),
        })
        .await?;
        s.close().await;
        anyhow::Ok(())
    })
}

pub fn cmd_train(a: TrainArgs) -> Result<()> {
    let runs = a
        .data
        .iter()
        .map(|p| read_ndjson_path(p).with_context(|| format!("reading {}", p.display())))
        .collect::<Result<Vec<_>>>()?;
    let Some(first) = runs.iter().flatten().next() else {
        bail!("the training files hold no rows");
    };
    let cfg = a.config(first.kind)?;
    let t = train_with_progress(&runs, &cfg)?;
    print_report(&t);
    save_model_dir(&a.out, &t)?;
    println!(
        "saved {}/{{model.json,model.bpk,config.json,report.json}}",
        a.out.display()
    );
    if a.store.given() {
        register(&a.store, &t)?;
        println!("registered model {} in the store", t.model.id);
    }
    Ok(())
}

// ---------------------------------------------------------------------------- bench-updaters

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Model files (model.json or training output directories) to compare with the EKF.
    #[arg(long = "model", value_name = "PATH", required = true)]
    pub models: Vec<PathBuf>,
    /// A log for the whole-step comparison (its landmark kind must match the models').
    #[arg(long)]
    pub log: Option<PathBuf>,
    /// Particles of the whole-step runs.
    #[arg(long, default_value_t = 1000)]
    pub particles: usize,
    /// Seconds each micro-benchmark runs for.
    #[arg(long, default_value_t = 0.3)]
    pub seconds: f64,
    /// Also write the update and forward-pass tables (markdown) to this file.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Nanoseconds per item of `f(batch)` repeated for about `secs`.
fn ns_per_item(batch: usize, secs: f64, mut f: impl FnMut()) -> f64 {
    f();
    let start = Instant::now();
    let mut calls = 0u64;
    loop {
        f();
        calls += 1;
        let e = start.elapsed().as_secs_f64();
        if e >= secs {
            return e * 1e9 / (calls as f64 * batch as f64);
        }
    }
}

/// ns per update of `u` at each batch size, on `inputs` (cycled), asking for `needs`.
pub fn bench_updater(
    u: &dyn LandmarkUpdater,
    needs: UpdateNeeds,
    inputs: &[UpdateInput],
    secs: f64,
) -> Vec<f64> {
    BATCHES
        .iter()
        .map(|&b| {
            let batch: Vec<UpdateInput> = inputs.iter().cycle().take(b).copied().collect();
            let mut out = vec![UpdateOutput::default(); b];
            ns_per_item(b, secs, || {
                u.update_batch(needs, &batch, &mut out);
                std::hint::black_box(&out);
            })
        })
        .collect()
}

/// ns per item of the network alone at each batch size: the inference kernel (raw features,
/// normalisation folded in, [`LANES`] items per pass) and burn's batched forward (flex, on
/// standardised inputs).
pub fn bench_forward(model: &MlpModel, secs: f64) -> (Vec<f64>, Vec<f64>) {
    let (n_in, n_out) = model.layout.dims(model.kind);
    let burn = BurnPredictor::new(model);
    let kernel = Kernel::new(model);
    let mut scratch = Box::<Scratch>::default();
    let mut plain = Vec::new();
    let mut burned = Vec::new();
    for &b in BATCHES {
        let x: Vec<f32> = (0..b * n_in)
            .map(|i| ((i % 7) as f32 - 3.0) * 0.3)
            .collect();
        let passes = b.div_ceil(LANES);
        let lanes: Vec<[f32; LANES]> = (0..passes * n_in)
            .map(|i| std::array::from_fn(|l| ((i * LANES + l) % 7) as f32 * 0.3 - 0.9))
            .collect();
        let mut y = vec![[0f32; LANES]; passes * n_out];
        let arch = Arch::new();
        plain.push(ns_per_item(b, secs, || {
            kernel.forward_many(arch, &lanes, &mut y, &mut scratch);
            std::hint::black_box(&y);
        }));
        burned.push(ns_per_item(b, secs, || {
            std::hint::black_box(burn.forward_normalized(&x));
        }));
    }
    (plain, burned)
}

/// Batch sizes of `bench-updaters`: one update, one observation across a work item of
/// particles, and a large batch.
pub const BATCHES: &[usize] = &[1, 64, 1000];

/// A whole run of `log` with `updater`: (wall s, step p50 ms, ns per update).
pub fn run_with(
    log: &Log,
    mut cfg: FilterConfig,
    updater: Arc<dyn LandmarkUpdater>,
) -> Result<RunOutput> {
    cfg.updater = updater.name().to_string();
    let mut slam = FastSlam::with_updater(cfg, updater)?;
    Ok(run_log(
        &mut slam,
        log,
        TrajectoryEstimate::Mean,
        |_, _| {},
    )?)
}

pub fn cmd_bench_updaters(a: BenchArgs) -> Result<()> {
    let models = a
        .models
        .iter()
        .map(|p| load_model(p))
        .collect::<Result<Vec<_>>>()?;
    let kind = models[0].kind;
    if let Some(m) = models.iter().find(|m| m.kind != kind) {
        bail!(
            "model {} is for {} landmarks, not {}",
            m.id,
            m.kind.as_str(),
            kind.as_str()
        );
    }
    let noise = models[0].noise;
    let inputs: Vec<UpdateInput> = synthetic_rows(kind, &noise, 10_000, 3)
        .iter()
        .map(TrainingRow::input)
        .collect();
    let mut updaters: Vec<(String, Arc<dyn LandmarkUpdater>)> =
        vec![("ekf".into(), Arc::new(EkfUpdater::new(kind, &noise)))];
    for m in &models {
        updaters.push((m.id.clone(), Arc::new(MlpUpdater::new(m.clone())?)));
        updaters.push((
            format!("{} (baseline SIMD)", m.id),
            Arc::new(MlpUpdater::new(m.clone())?.baseline_simd()),
        ));
    }
    let mut md = String::new();
    let _ = writeln!(
        md,
        "ns per landmark update ({} landmarks, one thread, {} generated updates cycled; \
         `posterior`: what FastSLAM 2.0 asks, `+ likelihood`: 1.0 or an outlier gate)\n",
        kind.as_str(),
        inputs.len()
    );
    let _ = writeln!(
        md,
        "| updater | needs | batch 1 | batch 64 | batch 1,000 | / EKF at 64 | / EKF at 1,000 |\n|---|---|---|---|---|---|---|"
    );
    for needs in [UpdateNeeds::Posterior, UpdateNeeds::PosteriorAndLikelihood] {
        let mut ekf_ns: Option<Vec<f64>> = None;
        for (name, u) in &updaters {
            let ns = bench_updater(u.as_ref(), needs, &inputs, a.seconds);
            let base = ekf_ns.get_or_insert_with(|| ns.clone()).clone();
            let _ = writeln!(
                md,
                "| {} | {} | {:.0} | {:.0} | {:.0} | {:.2} | {:.2} |",
                name,
                match needs {
                    UpdateNeeds::Posterior => "posterior",
                    UpdateNeeds::PosteriorAndLikelihood => "+ likelihood",
                },
                ns[0],
                ns[1],
                ns[2],
                ns[1] / base[1],
                ns[2] / base[2]
            );
        }
    }
    let _ = writeln!(
        md,
        "\nns per item of the network alone: the inference kernel (f32, {LANES} lanes, \
         normalisation folded, dispatched to AVX2 where the CPU has it) against burn's batched \
         forward (flex):\n"
    );
    let _ = writeln!(
        md,
        "| model | hidden | path | batch 1 | batch 64 | batch 1,000 |\n|---|---|---|---|---|---|"
    );
    for m in &models {
        let (plain, burn) = bench_forward(m, a.seconds);
        for (path, v) in [("kernel", plain), ("burn", burn)] {
            let _ = writeln!(
                md,
                "| {} | {:?} | {path} | {:.1} | {:.1} | {:.1} |",
                m.id,
                m.hidden(),
                v[0],
                v[1],
                v[2]
            );
        }
    }
    print!("{md}");
    if let Some(out) = &a.out {
        std::fs::write(out, &md).with_context(|| format!("writing {}", out.display()))?;
        println!("wrote {}", out.display());
    }
    if let Some(path) = &a.log {
        let log = Log::read_path(path).with_context(|| format!("reading {}", path.display()))?;
        let mut cfg = FilterConfig::from_header(&log.header);
        if cfg.landmark_kind != kind {
            bail!(
                "the log maps {} landmarks but the models are for {}",
                cfg.landmark_kind.as_str(),
                kind.as_str()
            );
        }
        cfg.particles = a.particles;
        println!(
            "\nwhole run of {} with {} particles, same log, same seed, one process:",
            path.display(),
            a.particles
        );
        println!(
            "| updater | wall time | step p50 | step p95 | ns per update (in filter) |\n|---|---|---|---|---|"
        );
        let ekf: Arc<dyn LandmarkUpdater> = Arc::new(EkfUpdater::new(kind, &cfg.sensor_noise));
        let mut list = vec![ekf];
        for m in &models {
            let mut c = cfg.clone();
            c.updater = m.id.clone();
            list.push(Arc::new(MlpUpdater::for_run(m.clone(), &c)?));
        }
        for u in list {
            let out = run_with(&log, cfg.clone(), u.clone())?;
            let m = &out.metrics;
            println!(
                "| {} | {:.2} s | {:.3} ms | {:.3} ms | {:.0} |",
                u.name(),
                m.wall_time_s,
                m.step_ms_p50,
                m.step_ms_p95,
                m.ns_per_landmark_update
            );
        }
    }
    Ok(())
}
