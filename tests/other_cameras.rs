//! Other cameras than the SR4000: resolution, field of view, modulation
//! frequency, waveform and noise drawn from seeded ranges; the pipeline is
//! told the camera's waveform and frequency, as a user would.

mod common;

use common::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use translucent_tof::physics::XiMethod;
use translucent_tof::pipeline::XiChoice;

#[test]
fn cameras_drawn_from_seeded_ranges() {
    for seed in 0..4u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(7000 + seed);
        let xi = rng.random_range(0.4..0.85);
        let mut s = fig5_scene(seed, xi, (0.5, 0.85), 1);
        let c = &mut s.camera;
        (c.width, c.height) = [(160, 120), (224, 172), (320, 240)][seed as usize % 3];
        c.hfov_deg = rng.random_range(40.0..70.0);
        c.vfov_deg = c.hfov_deg * c.height as f64 / c.width as f64;
        c.modulation_frequency_hz = rng.random_range(15.0e6..40.0e6);
        c.waveform = if seed % 2 == 0 { "triangle" } else { "sinusoid" }.into();
        s.noise.depth_noise_mm = rng.random_range(5.0..15.0);
        // Keep the layers under half the unambiguous range apart, as a user picks the frequency.
        let range = 299_792_458_000.0 / (2.0 * c.modulation_frequency_hz);
        s.background.distance_mm = (range * 0.45).clamp(1200.0, 2000.0);
        s.stages
            .retain(|st| st.objects[0].center_mm[2] < s.background.distance_mm - 300.0);
        let r = run_scene(&s, XiChoice::Estimate(XiMethod::OneMaterial), 4);
        println!(
            "seed {seed}: {}x{} {:.0} deg {:.1} MHz {} noise {:.1} mm, wall {:.0} mm, truth xi {xi:.3}: {}",
            s.camera.width,
            s.camera.height,
            s.camera.hfov_deg,
            s.camera.modulation_frequency_hz / 1e6,
            s.camera.waveform,
            s.noise.depth_noise_mm,
            s.background.distance_mm,
            r.describe()
        );
        assert!(r.covers(xi), "seed {seed}: {}", r.describe());
        assert!(r.mean_rmse() < 0.5 * r.mean_rmse_raw(), "seed {seed}");
    }
}

/// Edge pixels that straddle the layer and the wall (3x3 sub-rays per pixel,
/// the returns mixed as a real pixel mixes them): ξ still covered, and the
/// error still within the paper's figures.
#[test]
fn mixed_edge_pixels() {
    for (seed, xi, albedo, paper_mm) in [(31u64, 0.65, (0.45, 0.75), 10.6), (32, 0.94, (0.6, 0.9), 51.7)] {
        let mut s = fig5_scene(seed, xi, albedo, 1);
        s.camera.supersample = 3;
        let r = run_scene(&s, XiChoice::Estimate(XiMethod::OneMaterial), 4);
        println!("mixed edges, truth xi {xi}: {}", r.describe());
        assert!(r.covers(xi), "{}", r.describe());
        assert!(r.mean_rmse() <= paper_mm, "{:.1} mm", r.mean_rmse());
    }
}
