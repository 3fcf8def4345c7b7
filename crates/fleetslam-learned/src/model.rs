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
/// The widest hidden layer the inference kernel supports.
pub const MAX_WIDTH: usize = 256;
/// The most network inputs or outputs of any layout.
pub const MAX_IO: usize = 16;

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

impl DenseLayer {
    /// Layers of an untrained network with these widths (inputs, hidden layers, outputs):
    /// weights drawn uniformly from `(−weight, weight)` and biases from `(−bias, bias)`, for
    /// tests that need a network's arithmetic rather than a trained one.
    pub fn uniform_stack(
        widths: &[usize],
        weight: f32,
        bias: f32,
        rng: &mut impl rand::Rng,
    ) -> Vec<DenseLayer> {
        widths
            .windows(2)
            .map(|w| DenseLayer {
                inputs: w[0],
                outputs: w[1],
                weights: (0..w[0] * w[1])
                    .map(|_| rng.random_range(-weight..weight))
                    .collect(),
                bias: (0..w[1]).map(|_| rng.random_range(-bias..bias)).collect(),
            })
            .collect()
    }
}

/// Per-feature standardisation: `(v − mean) / std`, and the range the training data spanned.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Normalization {
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
    /// Smallest and largest value of each column in the training data. The inference kernel
    /// clamps the whitened layouts' inputs (`line_of_sight`, `gain`) to this range: a ReLU
    /// network extrapolates linearly, and a landmark observed far longer than any in the
    /// training runs (a prior much tighter than the noise) would otherwise get a gain or a
    /// covariance growth the network never learned, which repeated updates amplify. Empty:
    /// no clamping.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub min: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub max: Vec<f64>,
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
        let mut min = vec![f64::INFINITY; width];
        let mut max = vec![f64::NEG_INFINITY; width];
        for row in data.chunks_exact(width) {
            for ((lo, hi), v) in min.iter_mut().zip(max.iter_mut()).zip(row) {
                *lo = lo.min(*v);
                *hi = hi.max(*v);
            }
        }
        if data.len() < width {
            (min, max) = (Vec::new(), Vec::new());
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
        Self {
            mean,
            std,
            min,
            max,
        }
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
            let ranged = !norm.min.is_empty() || !norm.max.is_empty();
            if ranged
                && (norm.min.len() != w
                    || norm.max.len() != w
                    || norm
                        .min
                        .iter()
                        .zip(&norm.max)
                        .any(|(lo, hi)| !(lo.is_finite() && hi.is_finite() && lo <= hi)))
            {
                return bad(format!(
                    "{name}: min and max must both be empty or hold {w} finite values with min <= max"
                ));
            }
        }
        Ok(())
    }
}
