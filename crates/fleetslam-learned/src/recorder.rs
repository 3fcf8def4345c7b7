//! [`RecordingUpdater`]: logs a deterministic sample of another updater's landmark updates
//! as [`TrainingRow`]s.
//!
//! Which updates are kept depends only on the updates themselves, never on call order or
//! threads: each update gets a 64-bit hash of its inputs' bits and the seed; it is sampled
//! when the hash falls in the lowest `rate` fraction of the hash range, and when more than
//! `cap` sampled rows are held, the ones with the largest hashes are dropped (a bottom-k
//! sample). Rows are drained sorted by hash, so the same run gives the same rows in the same
//! order, whatever the rayon pool does.

use crate::LearnedError;
use crate::row::TrainingRow;
use fleetslam_core::pose::Pose2;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_core::updater::{
    LandmarkGaussian, LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput,
};
use std::collections::BinaryHeap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// What to log.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecordingConfig {
    /// Fraction of updates sampled, in `[0, 1]`. Default 0.05. Higher gives more rows per
    /// run (memory: ~250 bytes per held row).
    pub rate: f64,
    /// Most rows held until drained. Default 200,000. When more are sampled, the rows with
    /// the largest hashes are dropped, deterministically.
    pub cap: usize,
    /// Seed of the sampling hash. Default 0. Another seed samples other updates.
    pub seed: u64,
}

impl Default for RecordingConfig {
    fn default() -> Self {
        Self {
            rate: 0.05,
            cap: 200_000,
            seed: 0,
        }
    }
}

impl RecordingConfig {
    pub fn validate(&self) -> Result<(), LearnedError> {
        if !(self.rate.is_finite() && (0.0..=1.0).contains(&self.rate)) {
            return Err(LearnedError::Config(format!(
                "training rate must be in [0, 1], got {}",
                self.rate
            )));
        }
        Ok(())
    }
}

/// The bits of an update's inputs, in a fixed order (also the tie-break between equal
/// hashes).
type InputBits = [u64; 15];

fn input_bits(i: &UpdateInput) -> InputBits {
    let p = &i.prior;
    let v = [
        p.mean[0],
        p.mean[1],
        p.mean[2],
        p.cov[0],
        p.cov[1],
        p.cov[2],
        p.cov[3],
        p.cov[4],
        p.cov[5],
        i.pose.x,
        i.pose.y,
        i.pose.theta,
        i.z[0],
        i.z[1],
        i.z[2],
    ];
    v.map(f64::to_bits)
}

/// splitmix64's finaliser.
#[inline]
fn mix(mut x: u64) -> u64 {
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

fn hash_bits(bits: &InputBits, seed: u64) -> u64 {
    let mut h = mix(seed ^ 0x9e37_79b9_7f4a_7c15);
    for b in bits {
        h = mix(h ^ b);
    }
    h
}

#[derive(Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Key {
    hash: u64,
    bits: InputBits,
}

#[derive(Debug)]
struct Held {
    key: Key,
    row: TrainingRow,
}

impl PartialEq for Held {
    fn eq(&self, o: &Self) -> bool {
        self.key == o.key
    }
}
impl Eq for Held {}
impl PartialOrd for Held {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Held {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.key.cmp(&o.key)
    }
}

/// A decorator over any updater: same name, kind and results, and a sample of the updates
/// kept as training rows. Thread-safe: the filter calls it from rayon workers.
#[derive(Debug)]
pub struct RecordingUpdater {
    inner: Arc<dyn LandmarkUpdater>,
    config: RecordingConfig,
    /// Hashes at or below this are sampled.
    threshold: u64,
    /// When the held set is full, its largest hash: larger hashes are refused without the
    /// lock. `u64::MAX` while not full.
    full_max: AtomicU64,
    held: Mutex<BinaryHeap<Held>>,
    seen: AtomicU64,
}

impl RecordingUpdater {
    pub fn new(
        inner: Arc<dyn LandmarkUpdater>,
        config: RecordingConfig,
    ) -> Result<Self, LearnedError> {
        config.validate()?;
        let threshold = if config.rate >= 1.0 {
            u64::MAX
        } else {
            (config.rate * u64::MAX as f64) as u64
        };
        Ok(Self {
            inner,
            config,
            threshold,
            full_max: AtomicU64::new(u64::MAX),
            held: Mutex::new(BinaryHeap::new()),
            seen: AtomicU64::new(0),
        })
    }

    pub fn config(&self) -> &RecordingConfig {
        &self.config
    }

    pub fn inner(&self) -> &Arc<dyn LandmarkUpdater> {
        &self.inner
    }

    /// Updates seen since construction (sampled or not).
    pub fn seen(&self) -> u64 {
        self.seen.load(Ordering::Relaxed)
    }

    /// Rows held now.
    pub fn held(&self) -> usize {
        self.lock().len()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BinaryHeap<Held>> {
        // A panic while holding the lock can only leave a complete heap behind.
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Takes the held rows, sorted by their sampling hash (a deterministic order).
    pub fn drain_rows(&self) -> Vec<TrainingRow> {
        let heap = std::mem::take(&mut *self.lock());
        self.full_max.store(u64::MAX, Ordering::Relaxed);
        heap.into_sorted_vec().into_iter().map(|h| h.row).collect()
    }

    fn record(&self, inputs: &[UpdateInput], outputs: &[UpdateOutput]) {
        if self.config.cap == 0 || self.threshold == 0 {
            return;
        }
        let kind = self.inner.kind();
        let mut picked: Vec<Held> = Vec::new();
        for (i, o) in inputs.iter().zip(outputs) {
            let bits = input_bits(i);
            let hash = hash_bits(&bits, self.config.seed);
            if hash > self.threshold || hash > self.full_max.load(Ordering::Relaxed) {
                continue;
            }
            if let Some(row) = TrainingRow::new(kind, i, o) {
                picked.push(Held {
                    key: Key { hash, bits },
                    row,
                });
            }
        }
        if picked.is_empty() {
            return;
        }
        let mut heap = self.lock();
        for h in picked {
            heap.push(h);
            if heap.len() > self.config.cap {
                heap.pop();
            }
        }
        if heap.len() >= self.config.cap
            && let Some(top) = heap.peek()
        {
            self.full_max.store(top.key.hash, Ordering::Relaxed);
        }
    }
}

impl LandmarkUpdater for RecordingUpdater {
    fn name(&self) -> &str {
        self.inner.name()
    }

    fn kind(&self) -> LandmarkKind {
        self.inner.kind()
    }

    fn initialize(&self, pose: &Pose2, z: &[f64; 3]) -> LandmarkGaussian {
        self.inner.initialize(pose, z)
    }

    /// Always asks the wrapped updater for the likelihood too: a training row holds the
    /// whole update.
    fn update_batch(
        &self,
        _needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
    ) {
        self.inner
            .update_batch(UpdateNeeds::PosteriorAndLikelihood, inputs, outputs);
        self.seen.fetch_add(inputs.len() as u64, Ordering::Relaxed);
        self.record(inputs, outputs);
    }
}
