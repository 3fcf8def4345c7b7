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

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_xoshiro::Xoshiro256PlusPlus;

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
}
