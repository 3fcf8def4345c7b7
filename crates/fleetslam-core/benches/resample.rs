//! Resampling cost against the map size M, with N = 1000 particles. Copying a particle copies
//! one pointer to its persistent map, so the copy should not grow with M; what can grow is
//! freeing the discarded particles' own trie nodes (the paths their last step copied).
//!
//! A standing robot's particles all explain the observations about equally well, so before
//! the timed step the particles are given uneven log-weights `-4 z²`, `z ~ N(0, 1)` (ESS ≈
//! 0.46 N, a typical resampling trigger; about a third of the particles are not drawn).
//!
//! `resample_vs_landmarks/systematic_clone/<M>`: what `FastSlam::resample` does, from the
//! public pieces, on the particles after one step: normalise the log-weights, draw systematic
//! indices, clone the chosen particles and drop the old set. Here the old set is a copy that
//! shares everything with a set kept alive, so dropping it frees nothing: the pure copy cost.
//! `resample_vs_landmarks/systematic_clone_free/<M>`: the same on a particle set that solely
//! owns the trie paths its step copied, as in the filter: dropping the particles that were not
//! drawn frees those paths (about log₈ M nodes per updated landmark).
//! `resample_in_step/{always,never}/<M>`: the same full step (5 observations) with
//! `resample_threshold` 1.0 (resamples) and 0.0 (does not); the difference is the resampling
//! inside the filter. `resample_in_step/{always,never}_shared/<M>`: the same on particles whose
//! maps are one shared map (`common::shared_filter`), stepped once before so that each owns the
//! paths of the landmarks it observes, as after a run's resamplings.

mod common;

use common::{grow_map, new_filter, observe_five, shared_filter, with_config};
use criterion::{BatchSize, BenchmarkId, Criterion, SamplingMode, criterion_group, criterion_main};
use fleetslam_core::FastSlam;
use fleetslam_core::filter::Particle;
use fleetslam_core::math;
use fleetslam_core::resample::{normalize_log_weights, systematic};
use fleetslam_core::rng::StandardNormal;
use fleetslam_core::rng::{LANE_RESAMPLE, stream};
use rand::Rng;
use std::hint::black_box;
use std::time::{Duration, Instant};

const PARTICLES: usize = 1_000;
const LANDMARKS: [usize; 4] = [10, 100, 1_000, 10_000];

/// The body of `FastSlam::resample` for the particles (maps and weights; the robots' lists by
/// robot are gathered apart), plus the normalisation that precedes it in `step`.
fn resample(old: Vec<Particle>, mut log_w: Vec<f64>) -> Vec<Particle> {
    normalize_log_weights(&mut log_w);
    let mut rng = stream(0, 1, LANE_RESAMPLE);
    let idx = systematic(&log_w, &mut rng);
    let uniform = -math::ln(old.len() as f64);
    idx.into_iter()
        .map(|i| Particle {
            log_w: uniform,
            ..old[i].clone()
        })
        .collect()
}

/// The same filter with uneven (normalised) log-weights `-4 z²`.
fn uneven(slam: &FastSlam) -> FastSlam {
    let mut rng = stream(1, 2, 3);
    let mut w: Vec<f64> = (0..slam.particles().len())
        .map(|_| -4.0 * rng.sample::<f64, _>(StandardNormal).powi(2))
        .collect();
    normalize_log_weights(&mut w);
    let mut s = slam.snapshot();
    for (p, w) in s.particles.iter_mut().zip(w) {
        p.log_w = w;
    }
    FastSlam::from_snapshot(s, slam.updater().clone()).unwrap()
}

fn bench_resample(c: &mut Criterion) {
    let mut slam = new_filter(PARTICLES);
    for m in LANDMARKS {
        grow_map(&mut slam, m);
        let rec = observe_five(&slam, m);
        let never = uneven(&slam);
        let always = with_config(&never, |c| c.resample_threshold = 1.0);

        // Direct: the particles and weights after one step.
        let mut stepped = never.clone();
        let report = stepped.step(&rec).unwrap();
        assert!(!report.resampled && report.ess < 0.5 * PARTICLES as f64);
        let particles = stepped.particles().to_vec();
        let log_w: Vec<f64> = particles.iter().map(|p| p.log_w).collect();
        drop(stepped);
        {
            let mut g = c.benchmark_group("resample_vs_landmarks");
            g.sample_size(20)
                .warm_up_time(Duration::from_secs(1))
                .measurement_time(Duration::from_secs(2));
            g.bench_function(BenchmarkId::new("systematic_clone", m), |b| {
                b.iter_batched(
                    || (particles.clone(), log_w.clone()),
                    |(old, w)| resample(old, w),
                    BatchSize::PerIteration,
                )
            });
            // Each iteration needs a freshly stepped particle set (untimed, but a step is far
            // slower than the resample), so the measurement time is short.
            g.sample_size(20)
                .sampling_mode(SamplingMode::Flat)
                .warm_up_time(Duration::from_millis(300))
                .measurement_time(Duration::from_millis(if m >= 1_000 { 400 } else { 100 }));
            g.bench_function(BenchmarkId::new("systematic_clone_free", m), |b| {
                b.iter_custom(|iters| {
                    let mut total = Duration::ZERO;
                    for _ in 0..iters {
                        let mut s = never.clone();
                        s.step(&rec).unwrap();
                        let old = s.particles().to_vec();
                        drop(s);
                        let w = log_w.clone();
                        let t = Instant::now();
                        let new = resample(old, w);
                        total += t.elapsed();
                        drop(black_box(new));
                    }
                    total
                })
            });
            g.finish();
        }

        // In the filter: the same step, resampling or not, on the particles' own maps and on
        // one shared map (whose particles own their observed paths after a first step).
        let mut shared = shared_filter(PARTICLES, m);
        let shared_rec = observe_five(&shared, m);
        shared.step(&shared_rec).unwrap();
        let shared_rec = observe_five(&shared, m);
        let shared_never = uneven(&shared);
        let shared_always = with_config(&shared_never, |c| c.resample_threshold = 1.0);
        let mut g = c.benchmark_group("resample_in_step");
        g.sample_size(10)
            .sampling_mode(SamplingMode::Flat)
            .warm_up_time(Duration::from_secs(1))
            .measurement_time(Duration::from_secs(2));
        for (name, f, rec) in [
            ("always", &always, &rec),
            ("never", &never, &rec),
            ("always_shared", &shared_always, &shared_rec),
            ("never_shared", &shared_never, &shared_rec),
        ] {
            assert_eq!(
                f.clone().step(rec).unwrap().resampled,
                name.starts_with("always")
            );
            g.bench_function(BenchmarkId::new(name, m), |b| {
                b.iter_batched(
                    || f.clone(),
                    |mut s| {
                        s.step(rec).unwrap();
                        s
                    },
                    BatchSize::PerIteration,
                )
            });
        }
        g.finish();
    }
}

criterion_group!(benches, bench_resample);
criterion_main!(benches);
