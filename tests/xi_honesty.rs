//! ξ intervals that are honest about what the data carry (physics.md §3):
//! wide when one frame of one surface cannot tell, narrowing as frames with
//! new geometry arrive, covering the truth on scenes drawn from seeded ranges.

mod common;

use common::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use translucent_tof::physics::{ForwardModel, XiEstimate, XiMethod};
use translucent_tof::pipeline::{PipelineConfig, XiChoice};
use translucent_tof::sim::render::scene_sensor;
use translucent_tof::sim::scene::{ObjectSpec, Scene, StageSpec};

/// The pipeline as the node runs it: each frame pools the evidence so far.
/// Returns the estimate after each object frame.
fn online_estimates(s: &Scene) -> Vec<XiEstimate> {
    let config = PipelineConfig {
        xi: XiChoice::Estimate(XiMethod::OneMaterial),
        model: ForwardModel {
            sensor: scene_sensor(s),
            options: Default::default(),
        },
        ..PipelineConfig::default()
    };
    let (mut pipe, frames) = latched(s, config);
    frames
        .iter()
        .filter(|f| !f.background_only)
        .map(|f| pipe.process(&df(f)).unwrap().expect("an estimate").xi)
        .collect()
}

/// [`online_estimates`]' ξ and interval after each object frame.
fn online_intervals(s: &Scene) -> Vec<(f64, [f64; 2])> {
    online_estimates(s).into_iter().map(|e| (e.xi, e.interval)).collect()
}

#[test]
fn one_frame_of_one_tilted_plane_is_wide_and_frames_at_new_distances_narrow_it() {
    for seed in [1u64, 2] {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let xi = rng.random_range(0.5..0.8);
        let albedo = rng.random_range(0.5..0.8);
        let tilt = rng.random_range(20.0..35.0);
        let stages = [700.0, 1000.0, 1300.0, 1600.0]
            .iter()
            .map(|&z| StageSpec {
                frames: 1,
                objects: vec![plane([0.0, 0.0, z], [260.0, 320.0], [0.0, tilt], xi, albedo)],
            })
            .collect();
        let iv = online_intervals(&scene_with("tilted plane".into(), seed, 2200.0, stages));
        for (k, (x, i)) in iv.iter().enumerate() {
            println!(
                "seed {seed} xi {xi:.3}: after {} frame(s) {x:.3} [{:.3}, {:.3}]",
                k + 1,
                i[0],
                i[1]
            );
            assert!(i[0] <= xi && xi <= i[1], "seed {seed} frame {k}: {i:?} misses {xi}");
        }
        let width = |k: usize| iv[k].1[1] - iv[k].1[0];
        assert!(
            width(0) >= 0.15,
            "one frame of one plane cannot pin xi down: {:?}",
            iv[0]
        );
        assert!(width(3) < width(0), "new distances narrow the interval");
        assert!(width(3) <= 0.10, "{:?}", iv[3]);
    }
}

#[test]
fn cylinders_drawn_from_seeded_ranges_are_covered() {
    for seed in 0..4u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(1000 + seed);
        let xi = rng.random_range(0.2..0.8);
        let albedo = rng.random_range(0.5..0.9);
        let radius = rng.random_range(40.0..70.0);
        let wall = rng.random_range(1700.0..2300.0);
        let stages = (0..2)
            .map(|j| StageSpec {
                frames: 2,
                objects: vec![ObjectSpec {
                    shape: "cylinder".into(),
                    center_mm: [
                        rng.random_range(-150.0..150.0),
                        rng.random_range(-50.0..50.0),
                        rng.random_range(800.0..1000.0) + 400.0 * j as f64,
                    ],
                    size_mm: [0.0, 0.0],
                    tilt_x_deg: 0.0,
                    tilt_y_deg: 0.0,
                    radius_mm: radius,
                    height_mm: rng.random_range(150.0..250.0),
                    xi,
                    albedo,
                }],
            })
            .collect();
        let s = scene_with("cylinders".into(), seed, wall, stages);
        let r = run_scene(&s, XiChoice::Estimate(XiMethod::OneMaterial), 4);
        println!(
            "cylinder seed {seed}: truth xi {xi:.3} albedo {albedo:.2} r {radius:.0}: {}",
            r.describe()
        );
        assert!(r.covers(xi), "seed {seed}: {} misses {xi}", r.describe());
    }
}

/// Without a Lin calibration, `Lin` comes from the background taken as white.
/// On a grey wall that scale is wrong; ξ and `Lin`'s scale trade off, so the
/// estimate is an effective ξ under that assumption, while the recovered
/// depth stays right. With the wall's albedo given, ξ is the material's.
#[test]
fn unknown_background_albedo_shifts_xi_not_depth() {
    for seed in [5u64, 6] {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let grey = rng.random_range(0.35..0.7);
        let mut s = fig5_scene(seed, 0.65, (0.45, 0.75), 1);
        s.background.albedo = grey;
        let assumed_white = run_scene(&s, XiChoice::Estimate(XiMethod::OneMaterial), 4);
        let known = run_scene_with(&s, XiChoice::Estimate(XiMethod::OneMaterial), 4, grey);
        println!(
            "wall albedo {grey:.2}: assumed white -> {}; given -> {}",
            assumed_white.describe(),
            known.describe()
        );
        assert!(known.covers(0.65), "{}", known.describe());
        assert!(known.mean_rmse() <= 10.6 && assumed_white.mean_rmse() <= 10.6);
        assert!(
            assumed_white.xi < 0.6,
            "a grey wall taken as white lowers the effective xi"
        );
    }
}

/// A tilted plane of seeded ξ, albedo and tilt shown at six distances from 500 to 1950 mm
/// before a wall at 2200 mm, with an IR offset of `offset` counts that the model does not
/// have; ξ's estimate online and its truth.
fn tilted_plane_with_an_ir_offset(seed: u64, offset: f64) -> (XiEstimate, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let xi = rng.random_range(0.5..0.8);
    let albedo = rng.random_range(0.5..0.8);
    let tilt = rng.random_range(20.0..35.0);
    let stages = [500.0, 800.0, 1100.0, 1400.0, 1700.0, 1950.0]
        .iter()
        .map(|&z| StageSpec {
            frames: 1,
            objects: vec![plane([0.0, 0.0, z], [260.0, 320.0], [0.0, tilt], xi, albedo)],
        })
        .collect();
    let mut s = scene_with(format!("tilted plane, IR offset {offset}"), seed, 2200.0, stages);
    s.physics.ambient_offset = offset;
    let est = online_estimates(&s).pop().expect("an estimate");
    println!("xi {xi:.3}: {:.3} {:?} ({})", est.xi, est.interval, est.note);
    (est, xi)
}

/// A misfit that grows with distance (an IR offset the model does not have: the
/// farther poses' weaker returns carry more of it) is not a random offset per pose: the
/// near poses and the far ones, each estimated alone, part, and the interval spans both.
/// With the pooled interval alone this draw gives 0.662 [0.575, 0.760] for ξ 0.560.
#[test]
fn a_misfit_that_grows_with_distance_widens_the_interval_to_both_sides() {
    let (est, xi) = tilted_plane_with_an_ir_offset(5, 600.0);
    assert!(est.note.contains("the near poses alone give"), "{}", est.note);
    assert!(
        est.interval[0] <= xi && xi <= est.interval[1],
        "{:?} misses {xi}",
        est.interval
    );
}

/// Where the near poses find a layer and the far ones do not reject opaque (a larger IR
/// offset than above: the far poses' weak returns are mostly offset), the misfit is as large
/// as the layer's effect: the object is kept as read and its interval is every ξ. Spanning the
/// two sides' intervals gives [0, 0.849] here, where a diffuse transmitter's sides both fall
/// short of its ξ (`video_02`: 0 and 0.51 for 0.88).
#[test]
fn sides_that_part_into_opaque_and_a_layer_exclude_no_xi() {
    let (est, _) = tilted_plane_with_an_ir_offset(5, 1200.0);
    assert!(est.note.contains("the near poses alone give"), "{}", est.note);
    assert_eq!((est.xi, est.interval), (0.0, [0.0, 1.0]), "{}", est.note);
}
