//! Cost of one EKF landmark update (`EkfUpdater`), alone and in batches.
//!
//! `ekf_update/<kind>`: one `update` call. `ekf_update_batch/<kind>/<needs>/<n>`: one
//! `update_batch` of `n` independent updates asking for the posterior only (`posterior`,
//! FastSLAM 2.0) or with the likelihood (`likelihood`); the throughput is in updates per
//! second, so criterion's time divided by `n` is the time per update.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use fleetslam_core::Pose2;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::math;
use fleetslam_core::rng::stream;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use fleetslam_core::updater::{LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput};
use rand::Rng;
use std::f64::consts::PI;
use std::hint::black_box;
use std::time::Duration;

const KINDS: [LandmarkKind; 2] = [LandmarkKind::RangeBearing2d, LandmarkKind::Point3d];

/// `n` varied updates: random poses, landmarks 1-20 m away initialised from a first
/// observation, and a second observation a little off it.
fn inputs(u: &EkfUpdater, n: usize) -> Vec<UpdateInput> {
    let mut rng = stream(7, 0, 0);
    (0..n)
        .map(|_| {
            let pose = Pose2::new(
                rng.random_range(-10.0..10.0),
                rng.random_range(-10.0..10.0),
                rng.random_range(-PI..PI),
            );
            let (r, b): (f64, f64) = (rng.random_range(1.0..20.0), rng.random_range(-1.5..1.5));
            let z0 = match u.kind() {
                LandmarkKind::RangeBearing2d => [r, b, 0.0],
                LandmarkKind::Point3d => [
                    r * math::cos(b),
                    r * math::sin(b),
                    rng.random_range(-2.0..2.0),
                ],
            };
            let prior = u.initialize(&pose, &z0);
            let mut z = z0;
            for v in z.iter_mut().take(u.kind().dim()) {
                *v += rng.random_range(-0.05..0.05);
            }
            UpdateInput { prior, pose, z }
        })
        .collect()
}

fn bench_single(c: &mut Criterion) {
    let mut g = c.benchmark_group("ekf_update");
    g.warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(2));
    for kind in KINDS {
        let u = EkfUpdater::new(kind, &SensorNoise::default());
        let inp = inputs(&u, 1)[0];
        g.bench_function(kind.as_str(), |b| b.iter(|| u.update(black_box(&inp))));
    }
    g.finish();
}

fn bench_batch(c: &mut Criterion) {
    let mut g = c.benchmark_group("ekf_update_batch");
    g.sample_size(50)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(2));
    for kind in KINDS {
        let u = EkfUpdater::new(kind, &SensorNoise::default());
        for (needs, name) in [
            (UpdateNeeds::Posterior, "posterior"),
            (UpdateNeeds::PosteriorAndLikelihood, "likelihood"),
        ] {
            for n in [1usize, 100, 10_000] {
                let inp = inputs(&u, n);
                let mut out = vec![UpdateOutput::default(); n];
                g.throughput(Throughput::Elements(n as u64));
                let id = BenchmarkId::new(format!("{}/{name}", kind.as_str()), n);
                g.bench_with_input(id, &inp, |b, inp| {
                    b.iter(|| {
                        u.update_batch(needs, black_box(inp), &mut out);
                        black_box(&out);
                    })
                });
            }
        }
    }
    g.finish();
}

criterion_group!(benches, bench_single, bench_batch);
criterion_main!(benches);
