//! Counter-based random streams: every (seed, step, lane) gets its own generator.
//!
//! A particle's noise at a step depends only on the run's seed, the step number and the
//! particle's slot, never on which thread ran it or on what other particles drew. That makes
//! results bit-identical for any rayon pool size, and makes the random state of a whole
//! filter two integers (seed, step), which snapshots store for crash recovery.
//!
//! The filter's streams ([`stream`]) are Xoshiro256++ generators (Blackman and Vigna,
//! "Scrambled linear pseudorandom number generators", 2021) whose 256-bit state SplitMix64
//! fills from a hash of (seed, step, lane). A filter step sets up one stream per particle
//! and draws only a few normal variates from it (two on an odometry record with
//! calibration), so the cost of setting a stream up is what counts: a ChaCha8 stream, which
//! the filter used until session 17, computes four 64-byte blocks on its first draw, and
//! that was a quarter of the filter's instructions on MRCLAM Dataset 6. The localizer's
//! streams ([`chacha_stream`]) are still ChaCha8: its figures (docs/rtpf.md) were measured
//! with them.

use crate::math;
use rand::distr::Distribution;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_xoshiro::Xoshiro256PlusPlus;
use std::sync::LazyLock;

/// The generator of one (seed, step, lane) of the filter.
pub type Stream = Xoshiro256PlusPlus;

/// Lanes at and above this value are reserved for filter-wide draws (resampling, ...).
pub const LANE_RESAMPLE: u64 = u64::MAX;
/// Lane offset for drawing the start poses of a robot added to a running filter.
pub const LANE_ADD_ROBOT: u64 = 1 << 62;
/// Lane offset for drawing the odometry scales of a robot added to the filter.
pub const LANE_CALIBRATION: u64 = 1 << 61;

#[inline]
fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(SPLITMIX_GAMMA);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The key of (seed, step, lane): a SplitMix64 hash chain.
#[inline]
fn key(seed: u64, step: u64, lane: u64) -> [u64; 3] {
    let a = splitmix64(seed);
    let b = splitmix64(a ^ step);
    let c = splitmix64(b ^ lane);
    [a, b, c]
}

/// SplitMix64's increment, the golden ratio in 64-bit fixed point.
const SPLITMIX_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// The generator of `lane` (usually a particle slot) at `step` of a run seeded with `seed`:
/// Xoshiro256++ seeded through SplitMix64 (`seed_from_u64`) from the key's last word.
#[inline]
pub fn stream(seed: u64, step: u64, lane: u64) -> Stream {
    StepStreams::new(seed, step).lane(lane)
}

/// The streams of one step: the part of the key that (seed, step) fixes, hashed once, so
/// that each lane's stream costs one hash of its own and the four SplitMix64 words of its
/// state, which do not depend on each other. [`StepStreams::lane`] gives the generator
/// [`stream`] gives, bit for bit.
#[derive(Debug, Clone, Copy)]
pub struct StepStreams {
    /// The key's second word, `splitmix64(splitmix64(seed) ^ step)`.
    step_key: u64,
}

impl StepStreams {
    #[inline]
    pub fn new(seed: u64, step: u64) -> Self {
        Self {
            step_key: splitmix64(splitmix64(seed) ^ step),
        }
    }

    /// The generator of `lane` at this step.
    #[inline(always)]
    pub fn lane(&self, lane: u64) -> Stream {
        let c = splitmix64(self.step_key ^ lane);
        // `seed_from_u64(c)`: SplitMix64 from state `c` fills the 256-bit seed with its first
        // four outputs, the i-th being the mix of `c + (i + 1) · γ` (`splitmix64` adds γ
        // first), in little-endian order.
        let mut bytes = [0u8; 32];
        for (i, b) in bytes.chunks_exact_mut(8).enumerate() {
            let w = splitmix64(c.wrapping_add((i as u64).wrapping_mul(SPLITMIX_GAMMA)));
            b.copy_from_slice(&w.to_le_bytes());
        }
        Stream::from_seed(bytes)
    }
}

/// The ChaCha8 generator of (seed, step, lane), as every stream was before session 17; the
/// localizer draws from these.
#[inline]
pub fn chacha_stream(seed: u64, step: u64, lane: u64) -> ChaCha8Rng {
    let [a, b, c] = key(seed, step, lane);
    let d = splitmix64(c ^ 0x5EED);
    let mut bytes = [0u8; 32];
    for (i, w) in [a, b, c, d].iter().enumerate() {
        bytes[i * 8..i * 8 + 8].copy_from_slice(&w.to_le_bytes());
    }
    ChaCha8Rng::from_seed(bytes)
}

/// The standard normal distribution N(0, 1), with the same bits on every CPU.
///
/// `rand_distr`'s `StandardNormal` tests its candidates against `exp` and `ln` from the C
/// library, whose bits depend on the CPU ([`crate::math`]): a draw that glibc's FMA
/// variant accepts the other may reject, and the stream goes on differently from there.
/// This is the same method, the ziggurat of Marsaglia and Tsang ("The Ziggurat Method for
/// Generating Random Variables", J. Stat. Software 5(8), 2000), with [`crate::math`]'s
/// functions, in tables built once from the paper's `r` for 256 layers. One 64-bit draw
/// decides most variates: its low 8 bits pick a layer, its top 53 a point across it, and
/// the point is taken when it lies inside the layer's rectangle below the next layer
/// (98.5 % of draws: the mean of the ratios `x[i+1] / x[i]`); otherwise it is tested
/// against the density (a layer's wedge) or, in the base layer, replaced by a draw from
/// the tail beyond `r` (Marsaglia 1964).
#[derive(Debug, Clone, Copy, Default)]
pub struct StandardNormal;

/// The ziggurat's number of layers (a power of two: the layer is a draw's low bits).
const ZIGGURAT_LAYERS: usize = 256;

/// Where the tail begins for 256 layers (Marsaglia and Tsang 2000, Table 1).
const ZIGGURAT_R: f64 = 3.654_152_885_361_009;

/// The ziggurat's tables: `x[i]` the half-width of layer `i`'s rectangle (`x[0]` the base
/// layer's width were its tail a rectangle, `x[1] = r`, `x[256] = 0`) and `f[i]` the
/// unnormalised density `exp(−x[i]²/2)` there.
struct Ziggurat {
    x: [f64; ZIGGURAT_LAYERS + 1],
    f: [f64; ZIGGURAT_LAYERS + 1],
}

impl Ziggurat {
    /// The paper's recursion: the base layer (the rectangle up to `r` and the tail beyond)
    /// has area `v = r f(r) + ∫ᵣ^∞ f`, and each layer above it has the same area, which
    /// places its top at `f(x[i+1]) = v / x[i] + f(x[i])`.
    fn new() -> Self {
        let pdf = |x: f64| math::exp(-0.5 * x * x);
        let r = ZIGGURAT_R;
        let tail = (std::f64::consts::PI / 2.0).sqrt() * libm::erfc(r / std::f64::consts::SQRT_2);
        let area = r * pdf(r) + tail;
        let mut x = [0.0; ZIGGURAT_LAYERS + 1];
        x[0] = area / pdf(r);
        x[1] = r;
        for i in 2..ZIGGURAT_LAYERS {
            x[i] = (-2.0 * math::ln(area / x[i - 1] + pdf(x[i - 1]))).sqrt();
        }
        Self { x, f: x.map(pdf) }
    }

    fn get() -> &'static Self {
        static TABLES: LazyLock<Ziggurat> = LazyLock::new(Ziggurat::new);
        &TABLES
    }
}

impl Distribution<f64> for StandardNormal {
    #[inline]
    fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        let z = Ziggurat::get();
        loop {
            let bits = rng.next_u64();
            let i = (bits as usize) % ZIGGURAT_LAYERS;
            // Uniform on [−1, 1) in steps of 2^−52, from the 53 bits above the layer's.
            let u = (bits >> 11) as f64 * (1.0 / (1u64 << 52) as f64) - 1.0;
            let x = u * z.x[i];
            if x.abs() < z.x[i + 1] {
                return x;
            }
            if i == 0 {
                return normal_tail(rng, u < 0.0);
            }
            let y = z.f[i + 1] + (z.f[i] - z.f[i + 1]) * rng.random::<f64>();
            if y < math::exp(-0.5 * x * x) {
                return x;
            }
        }
    }
}

/// A draw from the normal's tail beyond `r` (Marsaglia 1964): `r + a` for `a = −ln(U₁)/r`,
/// accepted when `−2 ln(U₂) >= a²`; negative when `negative`.
#[cold]
fn normal_tail<R: Rng + ?Sized>(rng: &mut R, negative: bool) -> f64 {
    loop {
        // 1 − U on (0, 1]: the logarithm stays finite.
        let a = -math::ln(1.0 - rng.random::<f64>()) / ZIGGURAT_R;
        let b = -math::ln(1.0 - rng.random::<f64>());
        if 2.0 * b >= a * a {
            return if negative {
                -(ZIGGURAT_R + a)
            } else {
                ZIGGURAT_R + a
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    /// A step's streams are the ones `seed_from_u64` of the key's last word gives (the
    /// streams of sessions 17-18), state for state.
    #[test]
    fn step_streams_are_seed_from_u64_of_the_key() {
        for (seed, step) in [(0, 0), (1, 2), (u64::MAX, 7), (42, u64::MAX)] {
            let streams = StepStreams::new(seed, step);
            for lane in [0, 1, 2, 999, LANE_CALIBRATION + 3, LANE_RESAMPLE] {
                let mut old = Stream::seed_from_u64(key(seed, step, lane)[2]);
                let mut new = streams.lane(lane);
                for _ in 0..8 {
                    assert_eq!(old.random::<u64>(), new.random::<u64>());
                }
            }
        }
    }

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let a: u64 = stream(1, 2, 3).random();
        assert_eq!(a, stream(1, 2, 3).random::<u64>());
        assert_ne!(a, stream(1, 2, 4).random::<u64>());
        assert_ne!(a, stream(1, 3, 3).random::<u64>());
        assert_ne!(a, stream(2, 2, 3).random::<u64>());
        let c: u64 = chacha_stream(1, 2, 3).random();
        assert_eq!(c, chacha_stream(1, 2, 3).random::<u64>());
        assert_ne!(c, chacha_stream(1, 2, 4).random::<u64>());
        assert_ne!(c, chacha_stream(1, 3, 3).random::<u64>());
        assert_ne!(c, chacha_stream(2, 2, 3).random::<u64>());
    }

    /// Neighbouring lanes and steps are independent: the first uniform draws of 4,096
    /// particles' streams at one step, and of one lane over 4,096 steps, have the mean and
    /// variance of U(0, 1), and consecutive lanes' draws are uncorrelated (each within 4
    /// standard errors).
    #[test]
    fn neighbouring_streams_are_independent() {
        let n = 4096;
        let check = |u: &[f64]| {
            let m = u.iter().sum::<f64>() / n as f64;
            let v = u.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n as f64;
            let c = u.windows(2).map(|w| (w[0] - m) * (w[1] - m)).sum::<f64>() / n as f64 / v;
            let se = (1.0 / 12.0 / n as f64).sqrt();
            // The sample variance's standard error: √((μ₄ − σ⁴) / n), μ₄ = 1/80 for U(0, 1).
            let se_var = ((1.0 / 80.0 - 1.0 / 144.0) / n as f64).sqrt();
            assert!((m - 0.5).abs() < 4.0 * se, "mean {m}");
            assert!((v - 1.0 / 12.0).abs() < 4.0 * se_var, "variance {v}");
            assert!(c.abs() < 4.0 / (n as f64).sqrt(), "lag-1 correlation {c}");
        };
        let lanes: Vec<f64> = (0..n).map(|i| stream(7, 11, i).random()).collect();
        check(&lanes);
        let steps: Vec<f64> = (0..n).map(|t| stream(7, t, 5).random()).collect();
        check(&steps);
    }

    /// Every layer of the ziggurat has the base layer's area `v = x[0] f(r)`, to within
    /// 2e-13 of it (measured 9.7e-14; the top layer closes the recursion: its area was not
    /// imposed).
    #[test]
    fn the_ziggurat_layers_have_one_area() {
        let z = Ziggurat::get();
        let area = z.x[0] * z.f[1];
        assert_eq!((z.x[1], z.x[ZIGGURAT_LAYERS]), (ZIGGURAT_R, 0.0));
        let worst = (1..ZIGGURAT_LAYERS)
            .map(|i| (z.x[i] * (z.f[i + 1] - z.f[i]) / area - 1.0).abs())
            .fold(0.0, f64::max);
        println!("the worst layer's area is off by {worst:e} of v");
        assert!(worst < 2e-13, "a layer's area is off by {worst:e} of v");
        assert!(z.x.windows(2).all(|w| w[0] > w[1]));
    }

    /// A million draws are N(0, 1): their counts in 42 bins (edges −4 to 4 in steps of
    /// 0.2, and the two tails) against Φ's, by Pearson's χ² test at the 0.1 % level, and the
    /// count beyond the tail's start `r` (|x| > 3.654, probability 2.58e-4) within four
    /// standard deviations of its expectation: a wrong tail or wedge fails either.
    #[test]
    fn standard_normal_draws_are_standard_normal() {
        let n = 1_000_000;
        let phi = |x: f64| 0.5 * libm::erfc(-x / std::f64::consts::SQRT_2);
        let edges: Vec<f64> = (-20..=20).map(|k| k as f64 * 0.2).collect();
        let mut counts = vec![0u64; edges.len() + 1];
        let mut beyond_r = 0u64;
        let mut rng = stream(3, 5, 7);
        for _ in 0..n {
            let x: f64 = rng.sample(StandardNormal);
            counts[edges.partition_point(|&e| e <= x)] += 1;
            beyond_r += u64::from(x.abs() > ZIGGURAT_R);
        }
        let mut cdf = vec![0.0];
        cdf.extend(edges.iter().map(|&e| phi(e)));
        cdf.push(1.0);
        let chi2: f64 = counts
            .iter()
            .zip(cdf.windows(2))
            .map(|(&c, p)| {
                let e = n as f64 * (p[1] - p[0]);
                (c as f64 - e).powi(2) / e
            })
            .sum();
        let bound = crate::stats::chi2_quantile(0.999, counts.len() as u32 - 1);
        println!("χ² {chi2:.1} (bound {bound:.1}), {beyond_r} beyond r");
        assert!(chi2 < bound, "χ² {chi2:.1} against {bound:.1}");
        let p_r = 2.0 * phi(-ZIGGURAT_R);
        let (e, sd) = (n as f64 * p_r, (n as f64 * p_r * (1.0 - p_r)).sqrt());
        assert!(
            (beyond_r as f64 - e).abs() < 4.0 * sd,
            "{beyond_r} beyond r, expected {e:.0}"
        );
    }
}
