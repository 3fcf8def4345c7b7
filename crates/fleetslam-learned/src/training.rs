//! Training with burn (feature `train`): autodiff on the flex CPU backend.
//!
//! `train` splits the runs into training, validation and test runs (never rows: see
//! [`split_runs`]), encodes the rows for the preset's layout, standardises inputs and targets
//! on the training set, fits by mini-batch gradient descent on the mean squared error with
//! early stopping on the validation loss (the best epoch's weights are kept), and reports the
//! error of every network output and of the resulting updater against the EKF's logged
//! results on the test runs only, which played no part in training or stopping.

use crate::LearnedError;
use crate::dataset::{
    Encoded, RunSplit, TrainTarget, UpdaterError, encode, estimate_noise, split_runs, updater_error,
};
use crate::frame::InputLayout;
use crate::inference::MlpUpdater;
use crate::kernel::Kernel;
use crate::model::{
    Activation, CovarianceSource, DenseLayer, MAX_WIDTH, MODEL_FORMAT, MODEL_FORMAT_VERSION,
    MlpModel, Normalization,
};
use crate::row::TrainingRow;
use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamConfig, GradientsParams, SgdConfig};
use burn::tensor::{Device, Tensor, TensorData, activation};
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Gradient descent flavour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Optimizer {
    /// Plain back-propagation (no momentum), as in the paper.
    Sgd,
    Adam,
}

impl std::str::FromStr for Optimizer {
    type Err = LearnedError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "sgd" => Ok(Optimizer::Sgd),
            "adam" => Ok(Optimizer::Adam),
            o => Err(LearnedError::Config(format!(
                "unknown optimizer {o:?}: use sgd or adam"
            ))),
        }
    }
}

/// Everything a training run needs; saved beside the model as `config.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// The preset this configuration started from.
    pub preset: String,
    /// The model id (the updater name runs refer to).
    pub id: String,
    /// Landmark kind; `None`: the kind of the first row.
    pub kind: Option<LandmarkKind>,
    pub layout: InputLayout,
    /// Hidden layer widths (each 1..=256).
    pub hidden: Vec<usize>,
    pub activation: Activation,
    pub optimizer: Optimizer,
    pub lr: f64,
    pub epochs: usize,
    pub batch_size: usize,
    /// Runs held out for validation and early stopping.
    pub val_runs: usize,
    /// Runs held out for the test report (0: no test report).
    pub test_runs: usize,
    pub seed: u64,
    /// Stop after this many epochs without a better validation loss.
    pub patience: usize,
    /// Sensor noise; `None`: estimated from the rows.
    pub noise: Option<SensorNoise>,
    /// Where the `line_of_sight` updater's posterior covariance comes from.
    #[serde(default)]
    pub covariance: CovarianceSource,
    /// What the posterior-mean outputs learn: the EKF's posterior (default) or the
    /// landmark's true position (rows labelled with truth).
    #[serde(default)]
    pub target: TrainTarget,
}

impl TrainConfig {
    /// The paper's network (Vidal & Rosa 2015, Sec. 3): the raw inputs (landmark's previous
    /// coordinates, robot pose, observation), one hidden layer of two neurons, identity
    /// activation everywhere, back-propagation without momentum at learning rate 0.7 for
    /// 1000 epochs. Mini-batches of 64 stand in for the per-example updates of the original
    /// library (FANN), which would take hours here; inputs and targets are standardised.
    pub fn paper(id: &str) -> Self {
        Self {
            preset: "paper".into(),
            id: id.into(),
            kind: None,
            layout: InputLayout::Paper,
            hidden: vec![2],
            activation: Activation::Identity,
            optimizer: Optimizer::Sgd,
            lr: 0.7,
            epochs: 1000,
            batch_size: 64,
            val_runs: 1,
            test_runs: 1,
            seed: 1,
            patience: 50,
            noise: None,
            covariance: CovarianceSource::ClosedForm,
            target: TrainTarget::Ekf,
        }
    }

    /// Our design: the whitened measurement-frame layout, 2 × 32 ReLU, Adam.
    pub fn default_preset(id: &str) -> Self {
        Self {
            preset: "default".into(),
            id: id.into(),
            kind: None,
            layout: InputLayout::LineOfSight,
            hidden: vec![32, 32],
            activation: Activation::Relu,
            optimizer: Optimizer::Adam,
            lr: 3e-3,
            epochs: 500,
            batch_size: 256,
            val_runs: 1,
            test_runs: 1,
            seed: 1,
            patience: 50,
            noise: None,
            covariance: CovarianceSource::Network,
            target: TrainTarget::Ekf,
        }
    }

    /// The structured network: the `gain` layout (prior and noise in, gain and posterior
    /// factor out; the mean stays linear in the innovation), 2 × 16 ReLU, Adam.
    pub fn structured(id: &str) -> Self {
        Self {
            preset: "structured".into(),
            layout: InputLayout::Gain,
            hidden: vec![16, 16],
            ..Self::default_preset(id)
        }
    }

    /// Trained against ground truth: the `line_of_sight_range` layout (the default's inputs
    /// and the distance, on which a real sensor's error depends), the posterior mean learned
    /// from the landmarks' true positions, the covariance from the EKF's; 2 × 32 ReLU, Adam.
    /// Needs rows labelled with truth ([`crate::truth::label_rows`]).
    pub fn truth(id: &str) -> Self {
        Self {
            preset: "truth".into(),
            layout: InputLayout::LineOfSightRange,
            target: TrainTarget::Truth,
            ..Self::default_preset(id)
        }
    }

    /// The preset names [`TrainConfig::preset`] takes.
    pub const PRESETS: [&str; 4] = ["paper", "default", "structured", "truth"];

    /// A preset by name: `paper`, `default`, `structured` or `truth`.
    pub fn preset(name: &str, id: &str) -> Result<Self, LearnedError> {
        match name {
            "paper" => Ok(Self::paper(id)),
            "default" => Ok(Self::default_preset(id)),
            "structured" => Ok(Self::structured(id)),
            "truth" => Ok(Self::truth(id)),
            o => Err(LearnedError::Config(format!(
                "unknown preset {o:?}: use paper, default, structured or truth"
            ))),
        }
    }

    pub fn validate(&self) -> Result<(), LearnedError> {
        let bad = |m: String| Err(LearnedError::Config(m));
        if self.id.trim().is_empty() {
            return bad("the model id is empty".into());
        }
        if self.hidden.iter().any(|&w| w == 0 || w > MAX_WIDTH) {
            return bad(format!("hidden widths must be in 1..={MAX_WIDTH}"));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return bad(format!("lr must be > 0, got {}", self.lr));
        }
        if self.epochs == 0 || self.batch_size == 0 {
            return bad("epochs and batch size must be > 0".into());
        }
        if self.val_runs == 0 {
            return bad("at least one validation run is needed (val_runs >= 1)".into());
        }
        if self.target == TrainTarget::Truth && self.layout == InputLayout::Gain {
            return bad(
                "the gain layout cannot be trained against truth (one true position per row \
                 does not determine a gain): use line_of_sight or line_of_sight_range"
                    .into(),
            );
        }
        Ok(())
    }
}

/// The network as a burn module.
#[derive(Module, Debug)]
pub struct BurnMlp {
    layers: Vec<Linear>,
    #[module(skip)]
    activation: Activation,
}

impl BurnMlp {
    /// A freshly initialised network (seed the device first for repeatable weights).
    pub fn init(
        n_in: usize,
        hidden: &[usize],
        n_out: usize,
        activation: Activation,
        device: &Device,
    ) -> Self {
        let mut widths = vec![n_in];
        widths.extend_from_slice(hidden);
        widths.push(n_out);
        let layers = widths
            .windows(2)
            .map(|w| LinearConfig::new(w[0], w[1]).init(device))
            .collect();
        Self { layers, activation }
    }

    /// The network of a plain model file.
    pub fn from_model(model: &MlpModel, device: &Device) -> Self {
        let layers = model
            .layers
            .iter()
            .map(|l| {
                let w = l.weights.clone();
                Linear {
                    weight: Param::from_tensor(Tensor::from_data(
                        TensorData::new(w, [l.inputs, l.outputs]),
                        device,
                    )),
                    bias: Some(Param::from_tensor(Tensor::from_data(
                        TensorData::new(l.bias.clone(), [l.outputs]),
                        device,
                    ))),
                }
            })
            .collect();
        Self {
            layers,
            activation: model.activation,
        }
    }

    pub fn forward(&self, mut x: Tensor<2>) -> Tensor<2> {
        let last = self.layers.len() - 1;
        for (k, l) in self.layers.iter().enumerate() {
            x = l.forward(x);
            if k < last {
                x = match self.activation {
                    Activation::Relu => activation::relu(x),
                    Activation::Tanh => activation::tanh(x),
                    Activation::Identity => x,
                };
            }
        }
        x
    }

    /// The plain layers (`[in][out]` row-major, as burn holds them).
    pub fn dense_layers(&self) -> Result<Vec<DenseLayer>, LearnedError> {
        self.layers
            .iter()
            .map(|l| {
                let w = l.weight.val();
                let [n_in, n_out] = w.dims();
                let wv: Vec<f32> = w
                    .into_data()
                    .try_to_vec::<f32>()
                    .map_err(|e| LearnedError::Burn(format!("{e:?}")))?;
                let bv: Vec<f32> = match &l.bias {
                    Some(b) => b
                        .val()
                        .into_data()
                        .try_to_vec::<f32>()
                        .map_err(|e| LearnedError::Burn(format!("{e:?}")))?,
                    None => vec![0.0; n_out],
                };
                let weights = wv;
                Ok(DenseLayer {
                    inputs: n_in,
                    outputs: n_out,
                    weights,
                    bias: bv,
                })
            })
            .collect()
    }

    /// Loads a burnpack record saved by [`save_model_dir`] into a network of `model`'s
    /// architecture.
    pub fn load_burnpack(
        model: &MlpModel,
        path: &Path,
        device: &Device,
    ) -> Result<Self, LearnedError> {
        let (n_in, n_out) = model.layout.dims(model.kind);
        let net = Self::init(n_in, &model.hidden(), n_out, model.activation, device);
        net.try_load_file(path)
            .map_err(|e| LearnedError::Burn(format!("loading {}: {e:?}", path.display())))
    }
}

/// burn's batched forward pass over a plain model (for measuring it against the plain path
/// and checking that both agree).
#[derive(Debug)]
pub struct BurnPredictor {
    net: BurnMlp,
    device: Device,
    n_in: usize,
    n_out: usize,
}

impl BurnPredictor {
    pub fn new(model: &MlpModel) -> Self {
        let device = Device::flex();
        let (n_in, n_out) = model.layout.dims(model.kind);
        Self {
            net: BurnMlp::from_model(model, &device),
            device,
            n_in,
            n_out,
        }
    }

    /// Standardised inputs (`n × n_in`, f32) → standardised outputs (`n × n_out`).
    pub fn forward_normalized(&self, x: &[f32]) -> Vec<f32> {
        let n = x.len() / self.n_in;
        let t = Tensor::<2>::from_data(TensorData::new(x.to_vec(), [n, self.n_in]), &self.device);
        let y = self.net.forward(t);
        y.into_data()
            .try_to_vec::<f32>()
            .unwrap_or_else(|_| vec![f32::NAN; n * self.n_out])
    }
}

/// Per-output validation error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutputError {
    pub name: String,
    /// RMSE in the output's own units.
    pub rmse: f64,
    /// RMSE over the output's standard deviation (1.0 = no better than its mean).
    pub normalized_rmse: f64,
}

/// What training reports; saved as `report.json` and into the model's metadata.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainReport {
    pub kind: LandmarkKind,
    pub train_rows: usize,
    pub val_rows: usize,
    pub test_rows: usize,
    /// Indices of the runs (files or store runs, in the order given) of each set.
    pub train_runs: Vec<usize>,
    pub val_runs: Vec<usize>,
    pub test_runs: Vec<usize>,
    pub skipped_rows: usize,
    pub noise: SensorNoise,
    pub epochs_run: usize,
    pub best_epoch: usize,
    /// Mean squared error on standardised targets.
    pub best_val_loss: f64,
    pub first_val_loss: f64,
    pub final_train_loss: f64,
    pub seconds: f64,
    /// What the posterior-mean outputs were trained against.
    #[serde(default)]
    pub target: TrainTarget,
    /// Each output's error on the test runs against the trained targets (empty without
    /// test runs).
    pub outputs: Vec<OutputError>,
    /// The updater's error against the EKF's logged results (and against truth, where the
    /// rows carry it) on the test runs.
    pub updater: Option<UpdaterError>,
}

/// The result of training.
#[derive(Debug)]
pub struct Trained {
    pub model: MlpModel,
    pub net: BurnMlp,
    pub config: TrainConfig,
    pub report: TrainReport,
}

fn standardize(data: &[f64], width: usize, norm: &Normalization) -> Vec<f32> {
    data.chunks_exact(width)
        .flat_map(|row| {
            row.iter()
                .enumerate()
                .map(|(k, v)| ((v - norm.mean[k]) / norm.std[k]) as f32)
        })
        .collect()
}

fn batch_tensor(src: &[f32], width: usize, idx: &[usize], device: &Device) -> Tensor<2> {
    let mut v = Vec::with_capacity(idx.len() * width);
    for &i in idx {
        v.extend_from_slice(&src[i * width..(i + 1) * width]);
    }
    Tensor::from_data(TensorData::new(v, [idx.len(), width]), device)
}

fn mse(net: &BurnMlp, x: &[f32], y: &[f32], n_in: usize, n_out: usize, device: &Device) -> f64 {
    let n = x.len() / n_in;
    let xt = Tensor::<2>::from_data(TensorData::new(x.to_vec(), [n, n_in]), device);
    let yt = Tensor::<2>::from_data(TensorData::new(y.to_vec(), [n, n_out]), device);
    let loss = (net.forward(xt) - yt).powf_scalar(2.0).mean();
    loss.into_scalar::<f32>() as f64
}

/// Trains a model on `runs` (each the rows of one run), split by run ([`split_runs`] with
/// the configuration's `val_runs`, `test_runs` and seed). `progress(epoch, epochs,
/// train_loss, val_loss)` is called after every epoch.
pub fn train(
    runs: &[Vec<TrainingRow>],
    cfg: &TrainConfig,
    progress: impl FnMut(usize, usize, f64, f64),
) -> Result<Trained, LearnedError> {
    cfg.validate()?;
    let kind = match cfg
        .kind
        .or_else(|| runs.iter().flatten().next().map(|r| r.kind))
    {
        Some(k) => k,
        None => return Err(LearnedError::Data("no training rows".into())),
    };
    let runs: Vec<Vec<TrainingRow>> = runs
        .iter()
        .map(|r| r.iter().filter(|r| r.kind == kind).copied().collect())
        .collect();
    let sets = split_runs(&runs, cfg.val_runs, cfg.test_runs, cfg.seed)?;
    train_split(
        sets,
        &TrainConfig {
            kind: Some(kind),
            ..cfg.clone()
        },
        progress,
    )
}

/// Trains a model on a split made by the caller (for example by robot and time span, so that
/// the test set holds robots and times the model never saw). The configuration's
/// `val_runs` and `test_runs` are not used.
pub fn train_split(
    sets: RunSplit,
    cfg: &TrainConfig,
    mut progress: impl FnMut(usize, usize, f64, f64),
) -> Result<Trained, LearnedError> {
    cfg.validate()?;
    let started = std::time::Instant::now();
    let Some(kind) = cfg.kind.or_else(|| sets.train.first().map(|r| r.kind)) else {
        return Err(LearnedError::Data("no training rows".into()));
    };
    if cfg.target == TrainTarget::Truth {
        let unlabelled = sets
            .train
            .iter()
            .chain(&sets.val)
            .filter(|r| r.truth.is_none())
            .count();
        if unlabelled > 0 {
            return Err(LearnedError::Data(format!(
                "target truth: {unlabelled} of {} training and validation rows carry no truth \
                 position (label them against the data set's landmark truth first)",
                sets.train.len() + sets.val.len()
            )));
        }
    }
    let noise = match cfg.noise {
        Some(n) => n,
        None => estimate_noise(&sets.train, kind)?,
    };
    let (tr, skip_t) = encode(&sets.train, kind, cfg.layout, cfg.target, &noise);
    let (va, skip_v) = encode(&sets.val, kind, cfg.layout, cfg.target, &noise);
    let (te, skip_e) = encode(&sets.test, kind, cfg.layout, cfg.target, &noise);
    if tr.len() < 2 || va.is_empty() {
        return Err(LearnedError::Data(format!(
            "too few usable rows ({} train, {} validation) of kind {}",
            tr.len(),
            va.len(),
            kind.as_str()
        )));
    }
    let Encoded { n_in, n_out, .. } = tr;
    let in_norm = Normalization::fit(&tr.x, n_in);
    let out_norm = Normalization::fit(&tr.y, n_out);
    let xt = standardize(&tr.x, n_in, &in_norm);
    let yt = standardize(&tr.y, n_out, &out_norm);
    let xv = standardize(&va.x, n_in, &in_norm);
    let yv = standardize(&va.y, n_out, &out_norm);

    let device = Device::flex().autodiff();
    device.seed(cfg.seed);
    let mut net = BurnMlp::init(n_in, &cfg.hidden, n_out, cfg.activation, &device);
    let mut optim = match cfg.optimizer {
        Optimizer::Sgd => SgdConfig::new().init(),
        Optimizer::Adam => AdamConfig::new().init(),
    };
    let plain = Device::flex();
    let mut best = net.valid();
    let first_val = mse(&best, &xv, &yv, n_in, n_out, &plain);
    let mut best_val = first_val;
    let mut best_epoch = 0;
    let mut train_loss = f64::NAN;
    let mut epochs_run = 0;
    let mut order: Vec<usize> = (0..tr.len()).collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(cfg.seed ^ 0x5eed);
    for epoch in 1..=cfg.epochs {
        epochs_run = epoch;
        order.shuffle(&mut rng);
        let (mut sum, mut count) = (0.0f64, 0usize);
        for idx in order.chunks(cfg.batch_size) {
            let x = batch_tensor(&xt, n_in, idx, &device);
            let y = batch_tensor(&yt, n_out, idx, &device);
            let loss = (net.forward(x) - y).powf_scalar(2.0).mean();
            let l = loss.clone().into_scalar::<f32>() as f64;
            let grads = GradientsParams::from_grads(loss.backward(), &net);
            net = optim.step(cfg.lr, net, grads);
            sum += l * idx.len() as f64;
            count += idx.len();
        }
        train_loss = sum / count.max(1) as f64;
        let candidate = net.valid();
        let val = mse(&candidate, &xv, &yv, n_in, n_out, &plain);
        progress(epoch, cfg.epochs, train_loss, val);
        if val.is_finite() && val < best_val {
            best_val = val;
            best_epoch = epoch;
            best = candidate;
        } else if !train_loss.is_finite() || epoch - best_epoch >= cfg.patience {
            break;
        }
    }

    let layers = best.dense_layers()?;
    let mut model = MlpModel {
        format: MODEL_FORMAT.into(),
        format_version: MODEL_FORMAT_VERSION,
        id: cfg.id.clone(),
        kind,
        layout: cfg.layout,
        layout_version: InputLayout::VERSION,
        preset: cfg.preset.clone(),
        noise,
        activation: cfg.activation,
        covariance: cfg.covariance,
        input_norm: in_norm,
        output_norm: out_norm,
        layers,
        metadata: serde_json::Value::Null,
    };
    model.validate()?;

    // Per-output errors on the test runs, through the inference kernel.
    let names = cfg.layout.output_names(kind);
    let kernel = Kernel::new(&model);
    let mut sq = vec![0.0; n_out];
    let mut pred = vec![0.0; n_out];
    for (x, y) in te.x.chunks_exact(n_in).zip(te.y.chunks_exact(n_out)) {
        kernel.predict(x, &mut pred);
        for ((s, p), t) in sq.iter_mut().zip(&pred).zip(y) {
            *s += (p - t).powi(2);
        }
    }
    let nt = te.len() as f64;
    let outputs = if te.is_empty() {
        Vec::new()
    } else {
        (0..n_out)
            .map(|k| {
                let rmse = (sq[k] / nt).sqrt();
                OutputError {
                    name: names[k].clone(),
                    rmse,
                    normalized_rmse: rmse / model.output_norm.std[k],
                }
            })
            .collect()
    };
    let updater = MlpUpdater::new(model.clone())?;
    let report = TrainReport {
        kind,
        train_rows: tr.len(),
        val_rows: va.len(),
        test_rows: te.len(),
        train_runs: sets.train_runs.clone(),
        val_runs: sets.val_runs.clone(),
        test_runs: sets.test_runs.clone(),
        skipped_rows: skip_t + skip_v + skip_e,
        noise,
        epochs_run,
        best_epoch,
        best_val_loss: best_val,
        first_val_loss: first_val,
        final_train_loss: train_loss,
        seconds: started.elapsed().as_secs_f64(),
        target: cfg.target,
        outputs,
        updater: (!sets.test.is_empty()).then(|| updater_error(&updater, &sets.test)),
    };
    model.metadata = serde_json::json!({ "config": cfg, "report": report });
    Ok(Trained {
        model,
        net: best,
        config: cfg.clone(),
        report,
    })
}

/// Writes `model.json` (the plain model the updater loads), `model.bpk` (burn's burnpack
/// record), `config.json` and `report.json` into `dir`.
pub fn save_model_dir(dir: &Path, t: &Trained) -> Result<(), LearnedError> {
    std::fs::create_dir_all(dir).map_err(|e| LearnedError::io(dir, e))?;
    let write = |name: &str, bytes: Vec<u8>| -> Result<(), LearnedError> {
        let p = dir.join(name);
        std::fs::write(&p, bytes).map_err(|e| LearnedError::io(&p, e))
    };
    write("model.json", t.model.to_json())?;
    write(
        "config.json",
        serde_json::to_vec_pretty(&t.config).expect("config serialises"),
    )?;
    write(
        "report.json",
        serde_json::to_vec_pretty(&t.report).expect("report serialises"),
    )?;
    let bpk = dir.join("model.bpk");
    t.net
        .clone()
        .save_file(&bpk)
        .map_err(|e| LearnedError::Burn(format!("saving {}: {e:?}", bpk.display())))
}
