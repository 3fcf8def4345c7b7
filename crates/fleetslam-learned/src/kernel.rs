//! The network's forward pass for inference: f32, a batch of [`LANES`] items at a time laid
//! out as structure-of-arrays (`x[feature][lane]`), so that every multiply-add runs across the
//! lanes and the compiler turns the innermost loop into SIMD instructions (checked by the
//! `updaters` benchmark and `fleetslam bench-updaters`, which report ns per update at batch 1,
//! 64 and 1,000). The input standardisation is folded into the first layer and the output
//! de-standardisation into the last, so a forward pass is nothing but dense layers.
//!
//! Callers run passes inside [`Arch::dispatch`] (pulp) through a `WithSimd` operation whose
//! `with_simd` is `#[inline(always)]`, so that the passes are compiled for AVX2 when the CPU
//! has it (one 256-bit register holds the 8 lanes) and for the baseline otherwise. Rust
//! never fuses a multiply and an add on its own, so both give the same bits.

pub use pulp::Arch;

use crate::frame::InputLayout;
use crate::model::{Activation, DenseLayer, MAX_IO, MAX_WIDTH, MlpModel};

/// Items per forward pass: 8 f32 lanes (two SSE registers, one AVX register).
pub const LANES: usize = 8;

/// One value per lane.
pub type Lanes = [f32; LANES];

/// A dense layer with its weights transposed to `[outputs][inputs]`, so that one output's
/// weights are contiguous.
#[derive(Debug, Clone, PartialEq)]
struct Layer {
    inputs: usize,
    outputs: usize,
    w: Vec<f32>,
    b: Vec<f32>,
}

/// A model's network ready to run: normalisation folded in, weights transposed.
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel {
    layers: Vec<Layer>,
    activation: Activation,
    n_in: usize,
    n_out: usize,
    /// Each input's training range (`min`, `max`), for the whitened layouts; `None` for the
    /// paper layout (world coordinates, which no training range can cover) and for models
    /// without a recorded range. See [`crate::model::Normalization::min`].
    clamp: Option<(Vec<f32>, Vec<f32>)>,
}

/// Hidden activations of one forward pass (two buffers of the widest layer).
#[derive(Debug)]
pub struct Scratch {
    a: [Lanes; MAX_WIDTH],
    b: [Lanes; MAX_WIDTH],
}

impl Default for Scratch {
    fn default() -> Self {
        Self {
            a: [[0.0; LANES]; MAX_WIDTH],
            b: [[0.0; LANES]; MAX_WIDTH],
        }
    }
}

impl Kernel {
    /// Folds `(x − mean)/std` into the first layer (`w/std`, `b − Σ w·mean/std`) and
    /// `y·std + mean` into the last (`w·std`, `b·std + mean`), in f64 before rounding to f32.
    /// The model must be valid ([`MlpModel::validate`]).
    pub fn new(model: &MlpModel) -> Self {
        let last = model.layers.len() - 1;
        let layers = model
            .layers
            .iter()
            .enumerate()
            .map(|(k, l)| fold(l, k == 0, k == last, model))
            .collect();
        let n = &model.input_norm;
        let clamp = (model.layout != InputLayout::Paper && !n.min.is_empty()).then(|| {
            let f = |v: &[f64]| v.iter().map(|x| *x as f32).collect();
            (f(&n.min), f(&n.max))
        });
        Self {
            layers,
            activation: model.activation,
            n_in: model.input_norm.mean.len(),
            n_out: model.output_norm.mean.len(),
            clamp,
        }
    }

    pub fn n_in(&self) -> usize {
        self.n_in
    }

    pub fn n_out(&self) -> usize {
        self.n_out
    }

    /// Runs the network on `LANES` items: `x[..n_in]` raw features, `y[..n_out]` raw outputs.
    #[inline(always)]
    pub fn forward(&self, x: &[Lanes], y: &mut [Lanes], s: &mut Scratch) {
        let last = self.layers.len() - 1;
        let (mut cur, mut next) = (&mut s.a, &mut s.b);
        cur[..self.n_in].copy_from_slice(&x[..self.n_in]);
        if let Some((lo, hi)) = &self.clamp {
            for ((c, lo), hi) in cur[..self.n_in].iter_mut().zip(lo).zip(hi) {
                for v in c.iter_mut() {
                    *v = v.clamp(*lo, *hi);
                }
            }
        }
        for (k, l) in self.layers.iter().enumerate() {
            let act = if k == last {
                Activation::Identity
            } else {
                self.activation
            };
            dense(l, &cur[..l.inputs], &mut next[..l.outputs], act);
            std::mem::swap(&mut cur, &mut next);
        }
        y[..self.n_out].copy_from_slice(&cur[..self.n_out]);
    }

    /// Many passes in one dispatch (benchmarks): `x` holds `n_in` lane vectors per pass,
    /// `y` receives `n_out` per pass.
    pub fn forward_many(&self, arch: Arch, x: &[Lanes], y: &mut [Lanes], s: &mut Scratch) {
        arch.dispatch(ForwardMany {
            kernel: self,
            x,
            y,
            s,
        })
    }

    /// One item (lane 0 of a pass): raw features in, raw outputs out.
    pub fn predict(&self, features: &[f64], out: &mut [f64]) {
        let mut x = [[0f32; LANES]; MAX_IO];
        for (xi, f) in x.iter_mut().zip(features) {
            xi[0] = *f as f32;
        }
        let mut y = [[0f32; LANES]; MAX_IO];
        self.forward(&x, &mut y, &mut Scratch::default());
        for (o, yi) in out.iter_mut().zip(&y) {
            *o = yi[0] as f64;
        }
    }
}

/// [`Kernel::forward_many`] as one [`pulp::WithSimd`] operation, so that the passes are
/// compiled for the dispatched instruction set (a closure's body would not be).
struct ForwardMany<'a> {
    kernel: &'a Kernel,
    x: &'a [Lanes],
    y: &'a mut [Lanes],
    s: &'a mut Scratch,
}

impl pulp::WithSimd for ForwardMany<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let k = self.kernel;
        for (xp, yp) in self
            .x
            .chunks_exact(k.n_in)
            .zip(self.y.chunks_exact_mut(k.n_out))
        {
            k.forward(xp, yp, self.s);
        }
    }
}

fn fold(l: &DenseLayer, first: bool, last: bool, m: &MlpModel) -> Layer {
    let mut w = vec![0f32; l.inputs * l.outputs];
    let mut b = vec![0f32; l.outputs];
    for o in 0..l.outputs {
        let mut bias = l.bias[o] as f64;
        for i in 0..l.inputs {
            let mut wi = l.weights[i * l.outputs + o] as f64;
            if first {
                wi /= m.input_norm.std[i];
                bias -= wi * m.input_norm.mean[i];
            }
            w[o * l.inputs + i] = wi as f32;
        }
        if last {
            let s = m.output_norm.std[o];
            bias = bias * s + m.output_norm.mean[o];
            for i in 0..l.inputs {
                w[o * l.inputs + i] = (w[o * l.inputs + i] as f64 * s) as f32;
            }
        }
        b[o] = bias as f32;
    }
    Layer {
        inputs: l.inputs,
        outputs: l.outputs,
        w,
        b,
    }
}

/// Outputs computed together: independent accumulator chains, so that the adds do not wait
/// on each other's latency (one output at a time is latency-bound: every multiply-add of a
/// lane depends on the previous one).
const BLOCK: usize = 8;

/// `y[o] = act(b[o] + Σᵢ w[o][i] x[i])` for every lane, summed in input order (the same bits
/// whatever the blocking); the lane loop is what vectorises.
#[inline(always)]
fn dense(l: &Layer, x: &[Lanes], y: &mut [Lanes], act: Activation) {
    let n = l.inputs;
    let mut o = 0;
    while o + BLOCK <= l.outputs {
        let w = &l.w[o * n..(o + BLOCK) * n];
        let mut acc: [Lanes; BLOCK] = std::array::from_fn(|k| [l.b[o + k]; LANES]);
        for (i, xi) in x[..n].iter().enumerate() {
            for (k, a) in acc.iter_mut().enumerate() {
                let wk = w[k * n + i];
                for (a, v) in a.iter_mut().zip(xi) {
                    *a += wk * v;
                }
            }
        }
        for (yo, a) in y[o..o + BLOCK].iter_mut().zip(acc) {
            *yo = activate(a, act);
        }
        o += BLOCK;
    }
    for (o, yo) in y.iter_mut().enumerate().take(l.outputs).skip(o) {
        let w = &l.w[o * n..(o + 1) * n];
        let mut acc = [l.b[o]; LANES];
        for (wi, xi) in w.iter().zip(x) {
            for (a, v) in acc.iter_mut().zip(xi) {
                *a += wi * v;
            }
        }
        *yo = activate(acc, act);
    }
}

#[inline(always)]
fn activate(mut a: Lanes, act: Activation) -> Lanes {
    match act {
        Activation::Relu => {
            for v in a.iter_mut() {
                *v = if *v > 0.0 { *v } else { 0.0 };
            }
        }
        Activation::Tanh => {
            for v in a.iter_mut() {
                *v = v.tanh();
            }
        }
        Activation::Identity => {}
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{MODEL_FORMAT, MODEL_FORMAT_VERSION, Normalization};
    use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
    use rand::{Rng, SeedableRng};

    fn random_model(rng: &mut impl Rng, activation: Activation) -> MlpModel {
        let kind = LandmarkKind::RangeBearing2d;
        let layout = InputLayout::LineOfSight;
        let (n_in, n_out) = layout.dims(kind);
        let layers = DenseLayer::uniform_stack(&[n_in, 19, 16, n_out], 1.0, 0.5, rng);
        let norm = |n: usize, rng: &mut dyn rand::RngCore| Normalization {
            mean: (0..n).map(|_| rng.random_range(-3.0..3.0)).collect(),
            std: (0..n).map(|_| rng.random_range(0.2..4.0)).collect(),
            min: Vec::new(),
            max: Vec::new(),
        };
        MlpModel {
            format: MODEL_FORMAT.into(),
            format_version: MODEL_FORMAT_VERSION,
            id: "k".into(),
            kind,
            layout,
            layout_version: InputLayout::VERSION,
            preset: "test".into(),
            noise: SensorNoise::default(),
            activation,
            covariance: Default::default(),
            input_norm: norm(n_in, rng),
            output_norm: norm(n_out, rng),
            layers,
            metadata: serde_json::Value::Null,
        }
    }

    /// The folded, lane-parallel kernel computes the model's definition: standardise, dense
    /// layers with the activation between them, de-standardise (evaluated here in f64), and
    /// every lane is independent of the others.
    #[test]
    fn folded_kernel_matches_the_definition() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for act in [Activation::Relu, Activation::Tanh, Activation::Identity] {
            let m = random_model(&mut rng, act);
            let k = Kernel::new(&m);
            let (n_in, n_out) = (k.n_in(), k.n_out());
            let mut x = [[0f32; LANES]; MAX_IO];
            let feats: Vec<Vec<f64>> = (0..LANES)
                .map(|_| (0..n_in).map(|_| rng.random_range(-5.0..5.0)).collect())
                .collect();
            for (l, f) in feats.iter().enumerate() {
                for i in 0..n_in {
                    x[i][l] = f[i] as f32;
                }
            }
            let mut y = [[0f32; LANES]; MAX_IO];
            k.forward(&x, &mut y, &mut Scratch::default());
            for (l, f) in feats.iter().enumerate() {
                let mut v: Vec<f64> = (0..n_in)
                    .map(|i| (f[i] - m.input_norm.mean[i]) / m.input_norm.std[i])
                    .collect();
                for (li, layer) in m.layers.iter().enumerate() {
                    let mut nv = vec![0.0; layer.outputs];
                    for (o, out) in nv.iter_mut().enumerate() {
                        *out = layer.bias[o] as f64
                            + (0..layer.inputs)
                                .map(|i| layer.weights[i * layer.outputs + o] as f64 * v[i])
                                .sum::<f64>();
                        if li + 1 < m.layers.len() {
                            *out = match act {
                                Activation::Relu => out.max(0.0),
                                Activation::Tanh => libm::tanh(*out),
                                Activation::Identity => *out,
                            };
                        }
                    }
                    v = nv;
                }
                for o in 0..n_out {
                    let want = v[o] * m.output_norm.std[o] + m.output_norm.mean[o];
                    let got = y[o][l] as f64;
                    assert!(
                        (got - want).abs() < 1e-4 * (1.0 + want.abs()),
                        "{act:?} lane {l} output {o}: {got} vs {want}"
                    );
                }
                // The same item alone in lane 0 gives the same bits.
                let mut single = vec![0.0; n_out];
                k.predict(f, &mut single);
                for o in 0..n_out {
                    assert_eq!(single[o], y[o][l] as f64);
                }
            }
        }
    }

    /// A whitened layout's inputs outside the training range count as its nearest end; the
    /// paper layout's are never clamped.
    #[test]
    fn inputs_are_clamped_to_the_training_range() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut m = random_model(&mut rng, Activation::Tanh);
        let n_in = m.input_norm.mean.len();
        m.input_norm.min = vec![-1.0; n_in];
        m.input_norm.max = vec![2.0; n_in];
        let k = Kernel::new(&m);
        let run = |f: &[f64]| {
            let mut y = vec![0.0; k.n_out()];
            k.predict(f, &mut y);
            y
        };
        let wild: Vec<f64> = (0..n_in)
            .map(|i| if i % 2 == 0 { -7.0 } else { 9.0 })
            .collect();
        let ends: Vec<f64> = (0..n_in)
            .map(|i| if i % 2 == 0 { -1.0 } else { 2.0 })
            .collect();
        let inside: Vec<f64> = (0..n_in).map(|i| 0.1 * i as f64).collect();
        assert_eq!(run(&wild), run(&ends));
        assert_ne!(run(&wild), run(&inside));
        m.layout = InputLayout::Paper;
        let paper = Kernel::new(&m);
        let mut a = vec![0.0; k.n_out()];
        let mut b = a.clone();
        paper.predict(&wild, &mut a);
        paper.predict(&ends, &mut b);
        assert_ne!(a, b);
    }
}
