//! The model file: a plain JSON document holding the weights, the normalisation and what the
//! model is for (landmark kind, input layout and its version, preset, sensor noise). The fast
//! inference path loads it without burn.

use crate::LearnedError;
use crate::frame::InputLayout;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use serde::{Deserialize, Serialize};

/// The `kind` a store keeps MLP updater models under (their `weights` are the model JSON).
pub const STORE_MODEL_KIND: &str = "mlp_updater";

/// The format tag every model file carries.
pub const MODEL_FORMAT: &str = "fleetslam-mlp";
/// The version of the model file format this build reads and writes.
pub const MODEL_FORMAT_VERSION: u32 = 1;
/// The widest hidden layer the plain forward pass supports.
pub const MAX_WIDTH: usize = 256;
/// The most network inputs or outputs of any layout.
pub const MAX_IO: usize = 16;

thread_local! {
    /// Two hidden-activation buffers per thread for the plain forward pass.
    static SCRATCH: std::cell::RefCell<Vec<f32>> = std::cell::RefCell::new(vec![0.0; 2 * MAX_WIDTH]);
}

/// Hidden-layer activation. The output layer is always linear.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    Relu,
    Tanh,
    /// No non-linearity (the paper's choice for every neuron).
    Identity,
}

impl Activation {
    pub fn as_str(self) -> &'static str {
        match self {
            Activation::Relu => "relu",
            Activation::Tanh => "tanh",
            Activation::Identity => "identity",
        }
    }

    #[inline]
    pub fn apply(self, v: f32) -> f32 {
        match self {
            Activation::Relu => v.max(0.0),
            Activation::Tanh => v.tanh(),
            Activation::Identity => v,
        }
    }
}

impl std::str::FromStr for Activation {
    type Err = LearnedError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "relu" => Ok(Activation::Relu),
            "tanh" => Ok(Activation::Tanh),
            "identity" => Ok(Activation::Identity),
            other => Err(LearnedError::Config(format!(
                "unknown activation {other:?}: use relu, tanh or identity"
            ))),
        }
    }
}

/// Where the `line_of_sight` updater takes the posterior covariance from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CovarianceSource {
    /// The network's Cholesky factor (always positive definite; its errors compound over
    /// repeated updates of the same landmark).
    #[default]
    Network,
    /// The EKF's closed form `Σ − Σ (Σ + Q)⁻¹ Σ` in the measurement frame, from the
    /// `(Σ + Q)⁻¹` the likelihood needs anyway: exact, and no error compounds.
    ClosedForm,
}

impl std::str::FromStr for CovarianceSource {
    type Err = LearnedError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "network" => Ok(CovarianceSource::Network),
            "closed_form" | "closed-form" => Ok(CovarianceSource::ClosedForm),
            o => Err(LearnedError::Config(format!(
                "unknown covariance source {o:?}: use network or closed-form"
            ))),
        }
    }
}

/// A dense layer: `y[o] = b[o] + Σᵢ x[i] W[i][o]`, `W` row-major `[inputs][outputs]`
/// (burn's `Linear` layout).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DenseLayer {
    pub inputs: usize,
    pub outputs: usize,
    pub weights: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Per-feature standardisation: `(v − mean) / std`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Normalization {
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
}

impl Normalization {
    /// Mean and standard deviation of each column of row-major `data` (`n × width`); a
    /// constant column gets std 1.
    pub fn fit(data: &[f64], width: usize) -> Self {
        let n = (data.len() / width.max(1)).max(1) as f64;
        let mut mean = vec![0.0; width];
        for row in data.chunks_exact(width) {
            for (m, v) in mean.iter_mut().zip(row) {
                *m += v;
            }
        }
        mean.iter_mut().for_each(|m| *m /= n);
        let mut var = vec![0.0; width];
        for row in data.chunks_exact(width) {
            for ((s, v), m) in var.iter_mut().zip(row).zip(&mean) {
                *s += (v - m) * (v - m);
            }
        }
        let std = var
            .iter()
            .map(|s| {
                let sd = (s / n).sqrt();
                if sd > 1e-12 && sd.is_finite() {
                    sd
                } else {
                    1.0
                }
            })
            .collect();
        Self { mean, std }
    }
}

/// A trained MLP landmark updater model. Serialised as JSON (`to_json` / `from_json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MlpModel {
    /// Always [`MODEL_FORMAT`].
    pub format: String,
    /// Always [`MODEL_FORMAT_VERSION`] for this build.
    pub format_version: u32,
    /// The model id: the updater's name, what a run's `updater` field names.
    pub id: String,
    /// The landmark kind it was trained for.
    pub kind: LandmarkKind,
    pub layout: InputLayout,
    /// [`InputLayout::VERSION`] at training time.
    pub layout_version: u32,
    /// The training preset (`paper`, `default`, ...).
    pub preset: String,
    /// Sensor noise (standard deviations) of the training data, estimated from the EKF
    /// updates themselves; used for the features, the likelihood and new landmarks.
    pub noise: SensorNoise,
    pub activation: Activation,
    /// Posterior covariance of the `line_of_sight` layout: the network's or the closed
    /// form (the `paper` layout always uses the closed form). Default `network`.
    #[serde(default)]
    pub covariance: CovarianceSource,
    pub input_norm: Normalization,
    pub output_norm: Normalization,
    pub layers: Vec<DenseLayer>,
    /// Training configuration and validation metrics, as written by `fleetslam train`.
    #[serde(default)]
    pub metadata: serde_json::Value,
}

impl MlpModel {
    /// Parses and validates a model file.
    pub fn from_json(bytes: &[u8]) -> Result<Self, LearnedError> {
        let m: Self =
            serde_json::from_slice(bytes).map_err(|e| LearnedError::Model(e.to_string()))?;
        m.validate()?;
        Ok(m)
    }

    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec_pretty(self).expect("a model always serialises")
    }

    pub fn read_path(path: &std::path::Path) -> Result<Self, LearnedError> {
        let bytes = std::fs::read(path).map_err(|e| LearnedError::io(path, e))?;
        Self::from_json(&bytes).map_err(|e| match e {
            LearnedError::Model(m) => LearnedError::Model(format!("{}: {m}", path.display())),
            other => other,
        })
    }

    /// The hidden widths.
    pub fn hidden(&self) -> Vec<usize> {
        self.layers[..self.layers.len().saturating_sub(1)]
            .iter()
            .map(|l| l.outputs)
            .collect()
    }

    /// Checks that the file is one this build can run and that it is self-consistent.
    pub fn validate(&self) -> Result<(), LearnedError> {
        let bad = |m: String| Err(LearnedError::Model(m));
        if self.format != MODEL_FORMAT {
            return bad(format!("format {:?} is not {MODEL_FORMAT:?}", self.format));
        }
        if self.format_version != MODEL_FORMAT_VERSION {
            return bad(format!(
                "format version {} is not supported (this build reads {MODEL_FORMAT_VERSION})",
                self.format_version
            ));
        }
        if self.layout_version != InputLayout::VERSION {
            return Err(LearnedError::LayoutMismatch {
                model: format!("{} v{}", self.layout.as_str(), self.layout_version),
                expected: format!("{} v{}", self.layout.as_str(), InputLayout::VERSION),
            });
        }
        if self.id.trim().is_empty() {
            return bad("the model id is empty".into());
        }
        self.noise.validate("noise").map_err(LearnedError::Model)?;
        let (n_in, n_out) = self.layout.dims(self.kind);
        if self.layers.is_empty() {
            return bad("the model has no layers".into());
        }
        let mut width = n_in;
        for (k, l) in self.layers.iter().enumerate() {
            if l.inputs != width {
                return Err(LearnedError::LayoutMismatch {
                    model: format!("layer {k} takes {} inputs", l.inputs),
                    expected: format!(
                        "{width} ({} layout for {} has {n_in} inputs)",
                        self.layout.as_str(),
                        self.kind.as_str()
                    ),
                });
            }
            if l.outputs == 0 || l.outputs > MAX_WIDTH {
                return bad(format!(
                    "layer {k} has {} outputs (1..={MAX_WIDTH} supported)",
                    l.outputs
                ));
            }
            if l.weights.len() != l.inputs * l.outputs || l.bias.len() != l.outputs {
                return bad(format!("layer {k}: weights or bias have the wrong length"));
            }
            if !l.weights.iter().chain(&l.bias).all(|v| v.is_finite()) {
                return bad(format!("layer {k} has a non-finite weight"));
            }
            width = l.outputs;
        }
        if width != n_out {
            return Err(LearnedError::LayoutMismatch {
                model: format!("{width} outputs"),
                expected: format!(
                    "{n_out} ({} layout for {})",
                    self.layout.as_str(),
                    self.kind.as_str()
                ),
            });
        }
        for (name, norm, w) in [
            ("input_norm", &self.input_norm, n_in),
            ("output_norm", &self.output_norm, n_out),
        ] {
            if norm.mean.len() != w || norm.std.len() != w {
                return bad(format!("{name} has the wrong length (want {w})"));
            }
            if !norm.mean.iter().all(|v| v.is_finite())
                || !norm.std.iter().all(|v| v.is_finite() && *v > 0.0)
            {
                return bad(format!("{name} has a non-finite value or a std <= 0"));
            }
        }
        Ok(())
    }

    /// The network on one standardised input (plain Rust, f32). `x` holds `n_in` values and
    /// `y` receives `n_out`. Hidden activations live in a per-thread scratch buffer, so a
    /// call neither allocates nor clears memory.
    #[inline]
    pub fn forward_normalized(&self, x: &[f32], y: &mut [f32]) {
        SCRATCH.with(|s| {
            let mut s = s.borrow_mut();
            let (a, b) = s.split_at_mut(MAX_WIDTH);
            self.forward_in(x, y, a, b);
        })
    }

    #[inline]
    fn forward_in(&self, x: &[f32], y: &mut [f32], a: &mut [f32], b: &mut [f32]) {
        let (mut cur, mut next) = (a, b);
        cur[..x.len()].copy_from_slice(x);
        let last = self.layers.len() - 1;
        for (k, l) in self.layers.iter().enumerate() {
            // Output-major accumulation: each input adds its row of weights to every
            // output at once, a loop without a reduction that the compiler vectorises.
            let out = &mut next[..l.outputs];
            out.copy_from_slice(&l.bias);
            for (i, xi) in cur[..l.inputs].iter().enumerate() {
                let w = &l.weights[i * l.outputs..(i + 1) * l.outputs];
                for (o, wi) in out.iter_mut().zip(w) {
                    *o += xi * wi;
                }
            }
            if k != last && self.activation != Activation::Identity {
                for o in out.iter_mut() {
                    *o = self.activation.apply(*o);
                }
            }
            std::mem::swap(&mut cur, &mut next);
        }
        y.copy_from_slice(&cur[..y.len()]);
    }

    /// The network on raw features: standardises, runs, de-standardises.
    #[inline]
    pub fn predict(&self, features: &[f64], out: &mut [f64]) {
        let mut x = [0f32; MAX_IO];
        let n_in = features.len();
        let norm = &self.input_norm;
        for (((xi, f), m), s) in x.iter_mut().zip(features).zip(&norm.mean).zip(&norm.std) {
            *xi = ((f - m) / s) as f32;
        }
        let mut y = [0f32; MAX_IO];
        let n_out = out.len();
        self.forward_normalized(&x[..n_in], &mut y[..n_out]);
        let norm = &self.output_norm;
        for (((o, yi), m), s) in out.iter_mut().zip(&y).zip(&norm.mean).zip(&norm.std) {
            *o = *yi as f64 * s + m;
        }
    }
}
