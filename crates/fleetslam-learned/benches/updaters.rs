//! ns per landmark update: the EKF against the MLP updaters (paper, default and structured
//! presets), asking for the posterior only (FastSLAM 2.0) and for the likelihood too, and the
//! network alone (the inference kernel against burn's batched forward pass), at batch sizes
//! 1, 64 and 1,000.
//!
//! Run with `cargo bench -p fleetslam-learned --bench updaters`. The models are trained
//! here on generated updates for a few epochs: speed depends on the architecture, not on
//! how well the weights are trained. Set `FLEETSLAM_BENCH_MODELS=dir1,dir2` to bench
//! trained models instead.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use fleetslam_core::updater::{LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput};
use fleetslam_learned::dataset::synthetic_rows;
use fleetslam_learned::kernel::{Arch, Kernel, LANES, Scratch};
use fleetslam_learned::training::{BurnPredictor, TrainConfig, train};
use fleetslam_learned::{MlpModel, MlpUpdater, TrainingRow};
use std::hint::black_box;
use std::sync::Arc;

const BATCHES: [usize; 3] = [1, 64, 1000];

fn models(kind: LandmarkKind, noise: &SensorNoise) -> Vec<MlpModel> {
    if let Ok(dirs) = std::env::var("FLEETSLAM_BENCH_MODELS") {
        return dirs
            .split(',')
            .map(|d| {
                let p = std::path::Path::new(d);
                let f = if p.is_dir() {
                    p.join("model.json")
                } else {
                    p.to_path_buf()
                };
                MlpModel::read_path(&f).expect("a model file")
            })
            .filter(|m| m.kind == kind)
            .collect();
    }
    let runs: Vec<_> = (1..=3)
        .map(|seed| synthetic_rows(kind, noise, 1000, seed))
        .collect();
    TrainConfig::PRESETS
        .iter()
        .map(|p| {
            let mut c = TrainConfig::preset(p, &format!("mlp-{p}")).unwrap();
            c.epochs = 3;
            train(&runs, &c, |_, _, _, _| {}).unwrap().model
        })
        .collect()
}

fn bench_kind(c: &mut Criterion, kind: LandmarkKind) {
    let noise = SensorNoise::default();
    let inputs: Vec<UpdateInput> = synthetic_rows(kind, &noise, 10_000, 7)
        .iter()
        .map(TrainingRow::input)
        .collect();
    let models = models(kind, &noise);
    let mut updaters: Vec<Arc<dyn LandmarkUpdater>> = vec![Arc::new(EkfUpdater::new(kind, &noise))];
    for m in &models {
        updaters.push(Arc::new(MlpUpdater::new(m.clone()).unwrap()));
    }
    let mut g = c.benchmark_group(format!("update_{}", kind.as_str()));
    g.sample_size(20);
    for u in &updaters {
        for (needs, tag) in [
            (UpdateNeeds::Posterior, "posterior"),
            (UpdateNeeds::PosteriorAndLikelihood, "likelihood"),
        ] {
            for &b in &BATCHES {
                let batch = &inputs[..b];
                let mut out = vec![UpdateOutput::default(); b];
                g.throughput(Throughput::Elements(b as u64));
                g.bench_with_input(
                    BenchmarkId::new(format!("{}/{tag}", u.name()), b),
                    &b,
                    |bch, _| {
                        bch.iter(|| {
                            u.update_batch(needs, black_box(batch), &mut out);
                            black_box(&out);
                        })
                    },
                );
            }
        }
    }
    g.finish();
    let mut g = c.benchmark_group(format!("forward_{}", kind.as_str()));
    g.sample_size(20);
    for m in &models {
        let (n_in, n_out) = m.layout.dims(kind);
        let burn = BurnPredictor::new(m);
        let kernel = Kernel::new(m);
        for &b in &BATCHES {
            let x: Vec<f32> = (0..b * n_in)
                .map(|i| ((i % 7) as f32 - 3.0) * 0.3)
                .collect();
            let lanes: Vec<[f32; LANES]> = (0..b.div_ceil(LANES) * n_in)
                .map(|i| std::array::from_fn(|l| ((i * LANES + l) % 7) as f32 * 0.3 - 0.9))
                .collect();
            let mut y = vec![[0f32; LANES]; b.div_ceil(LANES) * n_out];
            let arch = Arch::new();
            let mut scratch = Box::<Scratch>::default();
            g.throughput(Throughput::Elements(b as u64));
            g.bench_with_input(
                BenchmarkId::new(format!("{}/kernel", m.id), b),
                &b,
                |bch, _| {
                    bch.iter(|| {
                        kernel.forward_many(arch, black_box(&lanes), &mut y, &mut scratch);
                        black_box(&y);
                    })
                },
            );
            g.bench_with_input(
                BenchmarkId::new(format!("{}/burn", m.id), b),
                &b,
                |bch, _| bch.iter(|| black_box(burn.forward_normalized(black_box(&x)))),
            );
        }
    }
    g.finish();
}

fn benches(c: &mut Criterion) {
    bench_kind(c, LandmarkKind::RangeBearing2d);
    bench_kind(c, LandmarkKind::Point3d);
}

criterion_group!(updater_benches, benches);
criterion_main!(updater_benches);
