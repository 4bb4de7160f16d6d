//! The paper's experiments, replicated in simulation (Shim & Lee Sec. V-A and
//! V-B): scenes made and inverted with this package's own model, so these check
//! the inversion's arithmetic against the paper's figures, not physics (the
//! physically rendered scenes are tests/rendered_scenes.rs). Scenes are drawn from seeded ranges (albedo, plane size, offset and
//! tilt), never one fixed setting; the noise is the paper's (~10 mm at a white
//! wall at 2 m). Figures print with `--nocapture`.

mod common;

use common::*;
use translucent_tof::physics::{ForwardModel, Sensor, XiMethod};
use translucent_tof::pipeline::XiChoice;

const SEEDS: [u64; 3] = [101, 202, 303];

/// Fig. 5a, document holder, ξ 0.65: the paper reports 195.3 mm raw -> 10.6 mm.
#[test]
fn simulated_document_holder_with_xi_given_is_under_the_papers_error() {
    for seed in SEEDS {
        let s = fig5_scene(seed, 0.65, (0.45, 0.75), 1);
        let per_pixel = run_scene(&s, XiChoice::Fixed(0.65), 0);
        let prior = run_scene(&s, XiChoice::Fixed(0.65), 4);
        println!(
            "document holder seed {seed}: raw {:.1} mm, per-pixel {:.1} mm, with surface prior {:.1} mm (per frame {:?})",
            prior.mean_rmse_raw(),
            per_pixel.mean_rmse(),
            prior.mean_rmse(),
            prior.frame_rmse_mm.iter().map(|e| format!("{e:.1}")).collect::<Vec<_>>()
        );
        assert!(prior.mean_rmse() <= 10.6, "seed {seed}: {:.2} mm", prior.mean_rmse());
        assert_eq!(prior.detected_frames(), 4);
        assert!(prior.mean_rmse_raw() > 5.0 * prior.mean_rmse());
    }
}

/// Fig. 5b, file box, ξ 0.94: the paper reports 725.6 mm raw -> 51.7 mm.
#[test]
fn simulated_file_box_with_xi_given_is_under_the_papers_error() {
    for seed in SEEDS {
        let s = fig5_scene(seed, 0.94, (0.6, 0.9), 1);
        let per_pixel = run_scene(&s, XiChoice::Fixed(0.94), 0);
        let prior = run_scene(&s, XiChoice::Fixed(0.94), 4);
        println!(
            "file box seed {seed}: raw {:.1} mm, per-pixel {:.1} mm, with surface prior {:.1} mm (per frame {:?})",
            prior.mean_rmse_raw(),
            per_pixel.mean_rmse(),
            prior.mean_rmse(),
            prior
                .frame_rmse_mm
                .iter()
                .map(|e| format!("{e:.1}"))
                .collect::<Vec<_>>()
        );
        assert!(prior.mean_rmse() <= 51.7, "seed {seed}: {:.2} mm", prior.mean_rmse());
        // At 1750 mm a ξ 0.94 layer may move the reading by less than the 30 mm threshold.
        assert!(
            prior.detected_frames() >= 3,
            "seed {seed}: found in {} of 4 frames",
            prior.detected_frames()
        );
        assert!(prior.mean_rmse_raw() > 5.0 * prior.mean_rmse());
    }
}

/// ξ estimated as one material over the four distances: the truth inside an
/// interval no wider than ±0.05.
#[test]
fn simulated_xi_estimated_over_four_distances_is_inside_a_tight_interval() {
    for (xi, albedo) in [(0.65, (0.45, 0.75)), (0.94, (0.6, 0.9))] {
        for seed in SEEDS {
            let s = fig5_scene(seed + 7, xi, albedo, 1);
            let r = run_scene(&s, XiChoice::Estimate(XiMethod::OneMaterial), 4);
            println!("truth xi {xi} seed {seed}: {}", r.describe());
            assert!(r.covers(xi), "xi {xi} seed {seed}: {}", r.describe());
            assert!(
                r.interval[1] - r.interval[0] <= 0.10,
                "xi {xi} seed {seed}: {:?}",
                r.interval
            );
        }
    }
}

/// Sec. V-A: ξ fitted to a plane at 20 known distances (0.72 and 0.91 in the
/// paper). The 0.91 folder shows the depth reversal, which the paper's Eq. 2
/// cannot produce (physics.md's note): the scene renders it with the
/// double-pass transmission law, and the fit uses the same law.
#[test]
fn simulated_model_validation_calibrates_xi_and_shows_the_depth_reversal() {
    let paper = ForwardModel::paper(Sensor::sr4000());
    for seed in [11, 12] {
        let s = fig4_scene(seed, 0.72, (0.5, 0.8));
        let est = calibrate_scene(&s, paper.clone());
        let rmse = est.profile.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
        println!(
            "xi 0.72 seed {seed}: calibrated {:.3} [{:.3}, {:.3}], model-vs-measurement RMS {rmse:.1} mm",
            est.xi, est.interval[0], est.interval[1]
        );
        assert!(est.interval[0] <= 0.72 && 0.72 <= est.interval[1], "{est:?}");
        assert!(est.half_width() <= 0.05);
    }
    let mut double = paper.clone();
    double.options.transmission_albedo_power = 0.0;
    for seed in [13, 14] {
        let mut s = fig4_scene(seed, 0.91, (0.25, 0.4));
        s.physics.transmission_albedo_power = 0.0;
        // The reversal: with the layers R/2 = 2498 mm apart or more, the folder reads behind the wall.
        let frames = translucent_tof::sim::render_all(&s);
        let objects: Vec<_> = frames.iter().filter(|f| !f.background_only).collect();
        let (at700, at800, at900) = (
            share_behind(objects[0], 3400.0),
            share_behind(objects[1], 3400.0),
            share_behind(objects[2], 3400.0),
        );
        println!("xi 0.91 seed {seed}: share of the folder reading over 100 mm behind the wall: {at700:.2} at 700 mm, {at800:.2} at 800 mm, {at900:.2} at 900 mm");
        let far = objects[5..].iter().map(|f| share_behind(f, 3400.0)).fold(0.0, f64::max);
        // At 800 mm the layers are 2500 mm apart on the axis, just past R/2: part of the folder reverses.
        assert!(at700 > 0.9 && at800 > 0.1, "depth reversal at 700 and (partly) 800 mm");
        assert!(
            far < 0.01,
            "no reversal from 1200 mm on, where the layers are well under R/2 apart: {far}"
        );
        let est = calibrate_scene(&s, double.clone());
        println!(
            "xi 0.91 seed {seed}: calibrated {:.3} [{:.3}, {:.3}]",
            est.xi, est.interval[0], est.interval[1]
        );
        assert!(est.interval[0] <= 0.91 && 0.91 <= est.interval[1], "{est:?}");
        assert!(est.half_width() <= 0.05);
    }
}
