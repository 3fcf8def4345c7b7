//! Cost of one full `FastSlam::step`: one robot, 5 observations of known landmarks, no
//! resampling (see `resample.rs` for that).
//!
//! `step_vs_particles/v2/<N>`: FastSLAM 2.0, N particles, M = 100 landmarks.
//! `step_vs_landmarks/{v2,v1}/<M>`: FastSLAM 2.0 and 1.0, N = 1000 particles, M landmarks.
//!
//! `{v2,v1}`: every iteration steps a fresh clone of a pre-built filter. The clone shares its
//! maps, so the step copies the trie paths of the 5 landmarks it updates (as in the first step
//! after a resample) and finds them cold in the cache; cloning and dropping are untimed.
//! `v2_shared`: as `v2`, but the particles' maps are one shared map (see
//! `common::shared_filter`), so the step's working set is that map's nodes, not N maps'.
//! `v2_restep`: one filter steps the same record again and again, so its paths are already
//! its own (updated in place) and warm: the steady state of re-observing the same landmarks.

mod common;

use common::{grow_map, new_filter, observe_five, shared_filter, with_config};
use criterion::{BatchSize, BenchmarkId, Criterion, SamplingMode, criterion_group, criterion_main};
use fleetslam_core::FastSlam;
use fleetslam_core::config::FastSlamVersion;
use fleetslam_core::log::Record;
use std::time::Duration;

fn time_step(
    g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    id: BenchmarkId,
    slam: &FastSlam,
    rec: &Record,
) {
    let check = slam.clone().step(rec).unwrap();
    assert!(!check.resampled);
    g.bench_function(id, |b| {
        b.iter_batched(
            || slam.clone(),
            |mut s| {
                s.step(rec).unwrap();
                s
            },
            BatchSize::PerIteration,
        )
    });
}

fn time_restep(
    g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    id: BenchmarkId,
    slam: &FastSlam,
    rec: &Record,
) {
    let mut s = slam.clone();
    g.bench_function(id, |b| b.iter(|| s.step(rec).unwrap()));
}

fn bench_vs_particles(c: &mut Criterion) {
    let mut g = c.benchmark_group("step_vs_particles");
    g.sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(2));
    for n in [100usize, 1_000, 10_000] {
        let m = 100;
        let mut slam = new_filter(n);
        grow_map(&mut slam, m);
        let rec = observe_five(&slam, m);
        time_step(&mut g, BenchmarkId::new("v2", n), &slam, &rec);
        time_restep(&mut g, BenchmarkId::new("v2_restep", n), &slam, &rec);
    }
    g.finish();
}

fn bench_vs_landmarks(c: &mut Criterion) {
    let mut g = c.benchmark_group("step_vs_landmarks");
    g.sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(2));
    let mut slam = new_filter(1_000);
    for m in [10usize, 100, 1_000, 10_000] {
        grow_map(&mut slam, m);
        let rec = observe_five(&slam, m);
        time_step(&mut g, BenchmarkId::new("v2", m), &slam, &rec);
        time_restep(&mut g, BenchmarkId::new("v2_restep", m), &slam, &rec);
        let v1 = with_config(&slam, |c| c.version = FastSlamVersion::V1);
        time_step(&mut g, BenchmarkId::new("v1", m), &v1, &rec);
        let shared = shared_filter(1_000, m);
        let rec = observe_five(&shared, m);
        time_step(&mut g, BenchmarkId::new("v2_shared", m), &shared, &rec);
    }
    g.finish();
}

criterion_group!(benches, bench_vs_particles, bench_vs_landmarks);
criterion_main!(benches);
