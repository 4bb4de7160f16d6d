//! Shared helpers for the integration tests: seeded scene draws and the
//! in-memory pipeline run.
#![allow(dead_code)]

pub mod cli;
pub mod netns;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use translucent_tof::physics::translucency;
use translucent_tof::physics::{ForwardModel, XiEstimate};
use translucent_tof::pipeline::{rmse_against_truth, BackgroundLatch, DepthFrame, Pipeline, PipelineConfig, XiChoice};
use translucent_tof::sim::render::{render_all, scene_intrinsics, scene_sensor};
use translucent_tof::sim::scene::{BackgroundSpec, ObjectSpec, Scene, StageSpec};
use translucent_tof::sim::SimFrame;

/// A scene with SR4000 defaults, a white wall at `wall_mm` seen for 10 frames, and the stages.
pub fn scene_with(name: String, seed: u64, wall_mm: f64, stages: Vec<StageSpec>) -> Scene {
    Scene {
        name,
        seed,
        camera: Default::default(),
        emitter: Default::default(),
        noise: Default::default(),
        physics: Default::default(),
        background: BackgroundSpec {
            distance_mm: wall_mm,
            albedo: 1.0,
            tilt_x_deg: 0.0,
            tilt_y_deg: 0.0,
            frames: 10,
        },
        stages,
    }
}

/// A translucent rectangle centred at `center_mm`.
pub fn plane(center_mm: [f64; 3], size_mm: [f64; 2], tilt_deg: [f64; 2], xi: f64, albedo: f64) -> ObjectSpec {
    ObjectSpec {
        shape: "plane".into(),
        center_mm,
        size_mm,
        tilt_x_deg: tilt_deg[0],
        tilt_y_deg: tilt_deg[1],
        radius_mm: 0.0,
        height_mm: 0.0,
        xi,
        albedo,
    }
}

/// The paper's Sec. V-B setting (document holder / file box): a plane at
/// 500/750/1000/1750 mm in front of a white wall at 2000 mm. Size, offset,
/// tilt and albedo are drawn from seeded ranges.
pub fn fig5_scene(seed: u64, xi: f64, albedo_range: (f64, f64), frames_per_stage: usize) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let albedo = rng.random_range(albedo_range.0..albedo_range.1);
    let w = rng.random_range(220.0..300.0);
    let h = rng.random_range(280.0..340.0);
    let stages = [500.0, 750.0, 1000.0, 1750.0]
        .iter()
        .map(|&z| StageSpec {
            frames: frames_per_stage,
            objects: vec![plane(
                [rng.random_range(-30.0..30.0), rng.random_range(-30.0..30.0), z],
                [w, h],
                [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0)],
                xi,
                albedo,
            )],
        })
        .collect();
    scene_with(format!("fig5 xi {xi} seed {seed}"), seed, 2000.0, stages)
}

/// A simulated frame as the pipeline takes it.
pub fn df(f: &SimFrame) -> DepthFrame {
    DepthFrame {
        stamp_ns: f.stamp_ns,
        z_mm: f.depth_z_mm.clone(),
        ir: f.ir.clone(),
    }
}

/// Renders a scene and latches its background frames into a new pipeline.
pub fn latched(scene: &Scene, config: PipelineConfig) -> (Pipeline, Vec<SimFrame>) {
    let frames = render_all(scene);
    let k = scene_intrinsics(scene);
    let mut latch = BackgroundLatch::new(k.width, k.height, config.model.sensor.unambiguous_range_mm());
    for f in frames.iter().filter(|f| f.background_only) {
        latch.push(&df(f), &k).unwrap();
    }
    let mut pipe = Pipeline::new(config.clone(), k);
    pipe.set_background(latch.finish(&k, &config).unwrap());
    (pipe, frames)
}

/// Figures of one in-memory run.
#[derive(Debug, Clone)]
pub struct RunFigures {
    pub xi: f64,
    pub interval: [f64; 2],
    pub frame_rmse_mm: Vec<f64>,
    pub frame_rmse_raw_mm: Vec<f64>,
}

impl RunFigures {
    /// Mean over frames of the per-frame RMS error, over frames where
    /// segmentation found the object (a layer reading within the threshold
    /// of the wall is not segmented, as in the paper).
    pub fn mean_rmse(&self) -> f64 {
        mean_finite(&self.frame_rmse_mm)
    }
    pub fn mean_rmse_raw(&self) -> f64 {
        mean_finite(&self.frame_rmse_raw_mm)
    }
    /// `xi 0.650 [0.630, 0.670], error 80.1 -> 2.7 mm` (mean of per-frame RMS, raw -> recovered).
    pub fn describe(&self) -> String {
        format!(
            "xi {:.3} [{:.3}, {:.3}], error {:.1} -> {:.1} mm",
            self.xi,
            self.interval[0],
            self.interval[1],
            self.mean_rmse_raw(),
            self.mean_rmse()
        )
    }

    /// Whether the reported interval covers `xi`.
    pub fn covers(&self, xi: f64) -> bool {
        self.interval[0] <= xi && xi <= self.interval[1]
    }

    /// Frames where the object was segmented.
    pub fn detected_frames(&self) -> usize {
        self.frame_rmse_mm.iter().filter(|e| e.is_finite()).count()
    }
}

/// Renders the scene and runs the pipeline: background latched from the
/// background frames, ξ pooled over all object frames (or fixed), then each
/// object frame recovered.
pub fn run_scene(scene: &Scene, xi: XiChoice, prior_radius_px: usize) -> RunFigures {
    run_scene_with(scene, xi, prior_radius_px, 1.0)
}

/// [`run_scene`] with the background's albedo (for `Lin`) given.
pub fn run_scene_with(scene: &Scene, xi: XiChoice, prior_radius_px: usize, background_albedo: f64) -> RunFigures {
    let config = PipelineConfig {
        xi,
        model: ForwardModel {
            sensor: scene_sensor(scene),
            options: Default::default(),
        },
        prior_radius_px,
        background_albedo,
        ..PipelineConfig::default()
    };
    let (mut pipe, frames) = latched(scene, config);
    let objects: Vec<_> = frames.iter().filter(|f| !f.background_only).collect();
    let mut observed: Vec<_> = objects.iter().map(|f| pipe.observe(&df(f)).unwrap()).collect();
    for o in &mut observed {
        pipe.add_xi_evidence(o);
    }
    let est = pipe.xi().expect("an estimate");
    let mut fr = vec![];
    let mut fr_raw = vec![];
    for (f, o) in objects.iter().zip(&observed) {
        let out = pipe.recover(&df(f), o, &est);
        // Same pixels for both: translucent, with truth, with a recovered depth.
        let mut mask = out.mask.clone();
        for i in 0..mask.len() {
            mask.data[i] &= out.corrected_z_mm.data[i].is_finite();
        }
        fr.push(
            rmse_against_truth(&out.corrected_z_mm, &f.truth_z_mm, &mask)
                .map(|r| r.0)
                .unwrap_or(f64::NAN),
        );
        fr_raw.push(
            rmse_against_truth(&f.depth_z_mm, &f.truth_z_mm, &mask)
                .map(|r| r.0)
                .unwrap_or(f64::NAN),
        );
    }
    RunFigures {
        xi: est.xi,
        interval: est.interval,
        frame_rmse_mm: fr,
        frame_rmse_raw_mm: fr_raw,
    }
}

/// The paper's Sec. V-A setting: a plane at 700..2600 mm (step 100) before a
/// wall at 3300 mm, one frame each; albedo and plane pose drawn from seeded ranges.
pub fn fig4_scene(seed: u64, xi: f64, albedo_range: (f64, f64)) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let albedo = rng.random_range(albedo_range.0..albedo_range.1);
    let stages = (7..=26)
        .map(|k| StageSpec {
            frames: 1,
            objects: vec![plane(
                [
                    rng.random_range(-20.0..20.0),
                    rng.random_range(-20.0..20.0),
                    k as f64 * 100.0,
                ],
                [300.0, 380.0],
                [rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)],
                xi,
                albedo,
            )],
        })
        .collect();
    scene_with(format!("fig4 xi {xi} seed {seed}"), seed, 3300.0, stages)
}

/// The paper's Sec. V-A protocol in memory: ξ fitted to the object frames'
/// known distances, with the given model.
pub fn calibrate_scene(scene: &Scene, model: ForwardModel) -> XiEstimate {
    let (pipe, frames) = latched(
        scene,
        PipelineConfig {
            model,
            ..PipelineConfig::default()
        },
    );
    let profiles: Vec<_> = frames
        .iter()
        .filter(|f| !f.background_only)
        .filter_map(|f| pipe.calibration_profile(&df(f), &f.truth_z_mm).unwrap())
        .collect();
    translucency::calibrate(&profiles).expect("a calibration")
}

/// Share of the object's pixels (with truth) that read behind the wall at `wall_mm` (z).
pub fn share_behind(f: &translucent_tof::sim::SimFrame, wall_mm: f32) -> f64 {
    let (mut n, mut b) = (0, 0);
    for (z, t) in f.depth_z_mm.data.iter().zip(&f.truth_z_mm.data) {
        if t.is_finite() {
            n += 1;
            if *z > wall_mm {
                b += 1;
            }
        }
    }
    b as f64 / n.max(1) as f64
}

fn mean_finite(v: &[f64]) -> f64 {
    let f: Vec<f64> = v.iter().copied().filter(|e| e.is_finite()).collect();
    f.iter().sum::<f64>() / f.len() as f64
}

/// Widest interval a node publishes where its evidence pins ξ to `half` either side: the
/// evidence's half width and the model's error on physical scenes
/// (`XI_MODEL_ERROR_SD`, which every published interval includes) in quadrature, each side.
#[allow(dead_code)]
pub fn published_width(half: f64) -> f64 {
    let pad = 1.96 * translucent_tof::physics::translucency::XI_MODEL_ERROR_SD;
    2.0 * (half * half + pad * pad).sqrt()
}
