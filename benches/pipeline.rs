//! Criterion benches of the real-time path (issue 5); `translucent_tof bench`
//! prints the same cases as a table. `cargo bench --bench pipeline`.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use translucent_tof::bench::{reference, BenchScene, BENCH_XI};
use translucent_tof::physics::{foreground_distance, PixelObservation, XiEstimate};

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap()
}

/// The fast inversion against the plain 1 mm grid, on the same pixels.
fn inversion(c: &mut Criterion) {
    let scene = BenchScene::new(176, 144);
    let obs = scene.observe(scene.near_frame());
    let pixels: Vec<PixelObservation> = obs.observations.iter().map(|(_, o)| *o).step_by(50).collect();
    let cfg = &scene.pipeline.config;
    let mut g = c.benchmark_group(format!("inversion_{}px", pixels.len()));
    g.sample_size(10);
    g.bench_function("fast", |b| {
        b.iter(|| {
            for o in &pixels {
                black_box(foreground_distance(&cfg.model, o, BENCH_XI, &cfg.bounds, None));
            }
        })
    });
    g.bench_function("grid_1mm", |b| {
        b.iter(|| {
            for o in &pixels {
                black_box(reference::grid_search(&cfg.model, o, BENCH_XI, &cfg.bounds));
            }
        })
    });
    g.finish();
}

/// `Pipeline::recover` of one frame at a fixed ξ, one and two threads.
fn recover(c: &mut Criterion) {
    let mut g = c.benchmark_group("recover");
    g.sample_size(10);
    for (w, h) in [(176, 144), (640, 480)] {
        let scene = BenchScene::new(w, h);
        let frame = scene.near_frame();
        let obs = scene.observe(frame);
        let xi = XiEstimate::fixed(BENCH_XI);
        for threads in [1, 2] {
            let p = pool(threads);
            g.bench_with_input(BenchmarkId::new(format!("{w}x{h}"), threads), &threads, |b, _| {
                p.install(|| b.iter(|| black_box(scene.pipeline.recover(frame, &obs, &xi))))
            });
        }
    }
    g.finish();
}

/// ξ estimation by shape on one frame, and the whole replay per frame, at 176x144.
fn xi_and_replay(c: &mut Criterion) {
    let scene = BenchScene::new(176, 144);
    let obs = scene.observe(scene.near_frame());
    let mut g = c.benchmark_group("per_frame_176x144");
    g.sample_size(10);
    for threads in [1, 2] {
        let p = pool(threads);
        g.bench_with_input(BenchmarkId::new("xi_estimate", threads), &threads, |b, _| {
            p.install(|| b.iter(|| black_box(scene.xi_by_shape(&obs))))
        });
        g.bench_with_input(BenchmarkId::new("replay_4_frames", threads), &threads, |b, _| {
            p.install(|| b.iter(|| black_box(scene.replay())))
        });
    }
    g.finish();
}

criterion_group!(benches, inversion, recover, xi_and_replay);
criterion_main!(benches);
