//! The recovered depth's standard deviation (`~/depth/corrected_sigma`) is
//! calibrated: over scenes drawn from seeded ranges and run as the node runs
//! them (ξ pooled online), the share of recovered pixels whose error lies
//! within ±2σ is that of a normal error, between 90 and 98 %.

mod common;

use common::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use translucent_tof::physics::{ForwardModel, XiMethod};
use translucent_tof::pipeline::{FrameOutput, PipelineConfig, XiChoice};
use translucent_tof::sim::render::scene_sensor;
use translucent_tof::sim::scene::{Scene, StageSpec};
use translucent_tof::sim::SimFrame;

/// A plane of one material at three or four distances before a wall; size,
/// pose, ξ, albedo and the wall drawn from seeded ranges.
fn drawn_scene(seed: u64) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let xi = rng.random_range(0.3..0.95);
    let albedo = rng.random_range(0.3..0.7);
    let wall = rng.random_range(1800.0..2600.0);
    let tilt = [rng.random_range(-30.0..30.0), rng.random_range(-30.0..30.0)];
    let (w, h) = (rng.random_range(200.0..320.0), rng.random_range(220.0..340.0));
    let stages = (0..rng.random_range(3..=4))
        .map(|_| StageSpec {
            frames: 1,
            objects: vec![plane(
                [
                    rng.random_range(-80.0..80.0),
                    rng.random_range(-60.0..60.0),
                    rng.random_range(500.0..wall - 400.0),
                ],
                [w, h],
                tilt,
                xi,
                albedo,
            )],
        })
        .collect();
    let mut s = scene_with(
        format!("draw {seed}: xi {xi:.2} albedo {albedo:.2}"),
        seed,
        wall,
        stages,
    );
    s.background.albedo = rng.random_range(0.5..1.0);
    s
}

/// (within 2σ, with σ) over a frame's recovered pixels with truth.
fn within_two_sigma(out: &FrameOutput, f: &SimFrame) -> (usize, usize) {
    let mut n = (0, 0);
    for i in 0..out.mask.len() {
        let (z, s, t) = (
            out.corrected_z_mm.data[i],
            out.corrected_sigma_mm.data[i],
            f.truth_z_mm.data[i],
        );
        if out.mask.data[i] && z.is_finite() && t.is_finite() {
            assert!(s.is_finite() && s >= 0.0, "a recovered pixel without a sigma: {s}");
            n.1 += 1;
            n.0 += usize::from((z - t).abs() <= 2.0 * s);
        }
    }
    n
}

/// Simulated with the pipeline's own model: σ's own arithmetic, not a claim about
/// physical scenes (scripts/results measures σ on the rendered set).
#[test]
#[ignore = "issue 31: 99.8 % within 2 sigma (too wide): with opaque the null hypothesis the single-pose frames are kept as read, and the determined objects' sigma is conservative (cargo test --test depth_sigma -- --ignored)"]
fn simulated_two_sigma_holds_90_to_98_percent_of_the_errors_on_seeded_scenes() {
    let mut pooled = (0, 0);
    for seed in 0..8u64 {
        let scene = drawn_scene(500 + seed);
        let config = PipelineConfig {
            xi: XiChoice::Estimate(XiMethod::OneMaterial),
            model: ForwardModel {
                sensor: scene_sensor(&scene),
                options: Default::default(),
            },
            ..PipelineConfig::default()
        };
        let (mut pipe, frames) = latched(&scene, config);
        let mut scene_n = (0, 0);
        for f in frames.iter().filter(|f| !f.background_only) {
            let Some(out) = pipe.process(&df(f)).expect("a valid frame") else {
                continue;
            };
            let n = within_two_sigma(&out, f);
            scene_n = (scene_n.0 + n.0, scene_n.1 + n.1);
        }
        println!(
            "{}: {} of {} recovered pixels within 2 sigma ({:.1} %)",
            scene.name,
            scene_n.0,
            scene_n.1,
            100.0 * scene_n.0 as f64 / scene_n.1.max(1) as f64
        );
        pooled = (pooled.0 + scene_n.0, pooled.1 + scene_n.1);
    }
    let share = pooled.0 as f64 / pooled.1.max(1) as f64;
    println!(
        "pooled: {} of {} within 2 sigma ({:.1} %)",
        pooled.0,
        pooled.1,
        100.0 * share
    );
    assert!(pooled.1 > 10_000, "too few recovered pixels to judge: {}", pooled.1);
    assert!(
        (0.90..=0.98).contains(&share),
        "2-sigma share {:.3} outside 0.90-0.98",
        share
    );
}
