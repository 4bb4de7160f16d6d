//! Benchmarks of the real-time path (issue 5): the frames they run on, the
//! cases they time, and the plain 1 mm grid search the fast inversion is
//! measured against ([`reference`]). Used by the `bench` subcommand and by the
//! criterion benches in `benches/`; the pipeline itself never calls it.

pub mod reference;

use std::time::{Duration, Instant};

use serde::Serialize;

use crate::physics::translucency::{self, FrameSample, ProfileUse};
use crate::physics::{ImageBuf, XiEstimate, XiMethod};
use crate::pipeline::multifreq::{MultiFrequencyConfig, MultiFrequencyStage, PhasorFrame};
use crate::pipeline::{DepthFrame, Observed, Pipeline, PipelineConfig, XiChoice};
use crate::sim::render::{render_all, scene_intrinsics, scene_sensor};
use crate::sim::scene::{BackgroundSpec, CameraSpec, ObjectSpec, Scene, StageSpec};

/// The ξ of the benchmark's layer (the paper's document holder).
pub const BENCH_XI: f64 = 0.65;

/// Distances of the layer in the benchmark's frames, mm: the paper's Fig. 5 stages.
pub const STAGES_MM: [f64; 4] = [500.0, 750.0, 1000.0, 1750.0];

/// A document holder (the paper's Fig. 5a: ξ 0.65, albedo 0.6, 240 x 310 mm)
/// before a white wall at 2000 mm, one frame at each of [`STAGES_MM`], seen
/// by an SR4000-like camera (44 x 35 degrees, 30 MHz) of the given resolution.
/// At 500 mm the layer covers about half the image.
pub fn document_holder_scene(width: usize, height: usize, background_frames: usize, seed: u64) -> Scene {
    let plane = |z: f64, tilt: [f64; 2]| ObjectSpec {
        shape: "plane".into(),
        center_mm: [10.0, -8.0, z],
        size_mm: [240.0, 310.0],
        tilt_x_deg: tilt[0],
        tilt_y_deg: tilt[1],
        radius_mm: 0.0,
        height_mm: 0.0,
        xi: BENCH_XI,
        albedo: 0.6,
    };
    let tilts = [[2.0, -1.0], [-3.0, 2.0], [1.0, -2.0], [-2.0, 3.0]];
    Scene {
        name: format!("bench document holder {width}x{height}"),
        seed,
        camera: CameraSpec {
            width,
            height,
            ..CameraSpec::default()
        },
        emitter: Default::default(),
        noise: Default::default(),
        // The physics the pipeline assumes by default, so the bench times what users run.
        physics: crate::physics::ModelOptions::physical(),
        background: BackgroundSpec {
            distance_mm: 2000.0,
            albedo: 1.0,
            tilt_x_deg: 0.0,
            tilt_y_deg: 0.0,
            frames: background_frames,
        },
        stages: STAGES_MM
            .iter()
            .zip(tilts)
            .map(|(&z, t)| StageSpec {
                frames: 1,
                objects: vec![plane(z, t)],
            })
            .collect(),
    }
}

/// A latched pipeline and the object frames of [`document_holder_scene`].
pub struct BenchScene {
    /// Width x height.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// The pipeline, background latched, ξ fixed at [`BENCH_XI`], default settings otherwise.
    pub pipeline: Pipeline,
    /// One frame per stage of [`STAGES_MM`].
    pub frames: Vec<DepthFrame>,
    /// Ground-truth z, mm (NaN off the layer), per frame.
    pub truth_z_mm: Vec<ImageBuf<f32>>,
}

impl BenchScene {
    /// Renders and latches the scene (a few seconds at 640 x 480).
    pub fn new(width: usize, height: usize) -> Self {
        let scene = document_holder_scene(width, height, 5, 11);
        let frames = render_all(&scene);
        let k = scene_intrinsics(&scene);
        let config = PipelineConfig {
            xi: XiChoice::Fixed(BENCH_XI),
            ..PipelineConfig::default()
        };
        let as_frame = |f: &crate::sim::SimFrame| DepthFrame {
            stamp_ns: f.stamp_ns,
            z_mm: f.depth_z_mm.clone(),
            ir: f.ir.clone(),
        };
        let background: Vec<DepthFrame> = frames.iter().filter(|f| f.background_only).map(as_frame).collect();
        let pipeline = Pipeline::latched(config, k, &background)
            .expect("the bench wall latches: its frames match the camera and it is a plane");
        let objects: Vec<_> = frames.iter().filter(|f| !f.background_only).collect();
        Self {
            width,
            height,
            pipeline,
            frames: objects.iter().map(|f| as_frame(f)).collect(),
            truth_z_mm: objects.iter().map(|f| f.truth_z_mm.clone()).collect(),
        }
    }

    /// The frame at the nearest stage (500 mm, the largest translucent region).
    pub fn near_frame(&self) -> &DepthFrame {
        &self.frames[0]
    }

    /// Segments a frame.
    pub fn observe(&self, frame: &DepthFrame) -> Observed {
        self.pipeline.observe(frame).expect("bench frames match the camera")
    }

    /// ξ estimation by shape on one frame: the frame's profile over the ξ grid and
    /// the one-material estimate from it (what the node adds per frame).
    pub fn xi_by_shape(&self, obs: &Observed) -> Option<XiEstimate> {
        let p = &self.pipeline;
        let settings = &p.config.xi_settings;
        let sample = FrameSample::from_image(&obs.observations, p.rays(), None, settings.max_pixels_per_frame);
        let profile = translucency::frame_profile(
            &p.config.model,
            &p.config.bounds,
            &sample,
            settings,
            ProfileUse::Estimation,
        );
        translucency::one_material(&[profile])
    }

    /// The whole per-frame work of `replay` (estimating ξ online): a fresh
    /// pipeline on this background processes every object frame in turn.
    pub fn replay(&self) -> usize {
        let mut pipe = self.pipeline.clone();
        pipe.config.xi = XiChoice::Estimate(XiMethod::OneMaterial);
        let mut recovered = 0;
        for f in &self.frames {
            if let Some(out) = pipe.process(f).expect("bench frames match the camera") {
                recovered += out.recovered_pixels;
            }
        }
        recovered
    }
}

/// The modulation frequencies of the multi-frequency case, Hz.
pub const BENCH_FREQUENCIES_HZ: [f64; 3] = [20e6, 50e6, 100e6];

/// The document holder of [`document_holder_scene`] seen at
/// [`BENCH_FREQUENCIES_HZ`], latched on the multi-frequency path.
pub struct MultiFrequencyBench {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// The path, background latched, default settings.
    pub stage: MultiFrequencyStage,
    /// One frame per stage of [`STAGES_MM`]: phasors and depth.
    pub frames: Vec<(PhasorFrame, DepthFrame)>,
}

impl MultiFrequencyBench {
    /// Renders and latches the scene (several seconds at 640 x 480).
    pub fn new(width: usize, height: usize) -> Self {
        let mut scene = document_holder_scene(width, height, 5, 11);
        scene.camera.modulation_frequencies_hz = BENCH_FREQUENCIES_HZ.to_vec();
        let model = crate::physics::ForwardModel::physical(scene_sensor(&scene));
        let config = MultiFrequencyConfig::new(BENCH_FREQUENCIES_HZ.to_vec(), model);
        let mut stage =
            MultiFrequencyStage::new(config, scene_intrinsics(&scene)).expect("the bench frequencies are valid");
        let (background, objects): (Vec<_>, Vec<_>) = render_all(&scene)
            .into_iter()
            .map(|f| {
                let depth = DepthFrame {
                    stamp_ns: f.stamp_ns,
                    z_mm: f.depth_z_mm,
                    ir: f.ir,
                };
                let phasors = PhasorFrame {
                    stamp_ns: f.stamp_ns,
                    phasors: f.phasors,
                };
                (f.background_only, (phasors, depth))
            })
            .partition(|(bg, _)| *bg);
        let latch: Vec<_> = background.iter().map(|(_, (p, d))| (p, d)).collect();
        let range = scene_sensor(&scene).unambiguous_range_mm();
        stage.latch(&latch, range).expect("the bench wall latches");
        Self {
            width,
            height,
            stage,
            frames: objects.into_iter().map(|(_, f)| f).collect(),
        }
    }
}

/// The multi-frequency path on the frame of `settings.stage`: every pixel
/// tested against the background and the changed ones inverted, in a pool of
/// `settings.threads` threads; with `settings.reference`, the plain grid fit
/// of two returns ([`reference::multi_frequency_grid`]) on one thread.
pub fn run_multi_frequency(mf: &MultiFrequencyBench, settings: &RunSettings) -> Row {
    let pool = crate::affinity::thread_pool(settings.threads.max(1), settings.pin).expect("a thread pool");
    let stage = settings.stage.min(mf.frames.len() - 1);
    let (phasors, depth) = &mf.frames[stage];
    let process = || mf.stage.process(phasors, depth).expect("bench frames match the camera");
    let (median_ms, p95_ms, samples) = pool.install(|| {
        time_ms(settings.samples, settings.budget_s, settings.pause, || {
            std::hint::black_box(process());
        })
    });
    let out = process();
    let (mut reference_ms, mut agreement) = (None, None);
    if settings.reference {
        let start = Instant::now();
        let grid = reference::multi_frequency_grid(&mf.stage, phasors);
        reference_ms = Some(start.elapsed().as_secs_f64() * 1e3);
        let scale = mf.stage.intrinsics.ray_scale_map();
        let fast = ImageBuf {
            width: mf.width,
            height: mf.height,
            data: (0..scale.len())
                .map(|i| match out.frame.mask.data[i] {
                    true => f64::from(out.frame.corrected_z_mm.data[i]) * scale.data[i],
                    false => f64::NAN,
                })
                .collect(),
        };
        agreement = Some(reference::multi_frequency_agreement(&fast, &grid));
    }
    let case = Case::MultiFrequency;
    Row {
        name: case.name(),
        size: format!("{}x{}", mf.width, mf.height),
        threads: settings.threads.max(1),
        samples,
        pause_ms: settings.pause.as_secs_f64() * 1e3,
        pinned: settings.pin,
        stage_mm: STAGES_MM[stage],
        median_ms,
        p95_ms,
        reference_ms,
        speedup: reference_ms.map(|r| r / median_ms),
        target_ms: target_ms(case, mf.width, mf.height, settings.threads.max(1)),
        translucent_pixels: out.frame.translucent_pixels,
        translucent_fraction: out.frame.translucent_pixels as f64 / (mf.width * mf.height) as f64,
        agreement,
    }
}

/// How the multi-frequency path's per-pixel layer fit
/// ([`crate::physics::multifreq::MultiFrequencyInversion::layer`], before any spatial or
/// temporal prior) compares with the plain 1 mm grid's global optimum
/// ([`reference::multi_frequency_grid`]) on one frame's changed pixels.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SolverAgreement {
    /// Changed pixels the grid fitted.
    pub grid_pixels: usize,
    /// Of those, pixels both fitted: compared.
    pub compared: usize,
    /// Of those, pixels whose layer distances are at most [`SOLVER_TOLERANCE_MM`] apart.
    pub within: usize,
    /// Pixels farther apart where the fast fit's `chi^2` is below the grid's at the grid's
    /// own best point: the optimum lies between the grid's 1 mm steps (a well at the bound
    /// `db - separation`, which the grid's steps need not reach), and the fast fit found it.
    pub below_grid: usize,
    /// Changed pixels the fast fit refused (outside the common range, no background return):
    /// not compared.
    pub refused: usize,
    /// The largest difference, mm.
    pub max_diff_mm: f64,
    /// Up to ten pixels that miss the grid's optimum: `(pixel, fast mm, grid mm)`.
    pub worst: Vec<(usize, f64, f64)>,
}

/// How far the fast fit's layer distance may be from the grid's optimum, mm.
pub const SOLVER_TOLERANCE_MM: f64 = 1.0;

impl SolverAgreement {
    /// The share of compared pixels that reach the grid's optimum: within
    /// [`SOLVER_TOLERANCE_MM`] of it, or below it (1 with none compared).
    pub fn share_reached(&self) -> f64 {
        if self.compared == 0 {
            1.0
        } else {
            (self.within + self.below_grid) as f64 / self.compared as f64
        }
    }

    /// Adds another frame's counts.
    pub fn add(&mut self, other: &SolverAgreement) {
        self.grid_pixels += other.grid_pixels;
        self.compared += other.compared;
        self.within += other.within;
        self.below_grid += other.below_grid;
        self.refused += other.refused;
        self.max_diff_mm = self.max_diff_mm.max(other.max_diff_mm);
        let room = 10usize.saturating_sub(self.worst.len());
        self.worst.extend(other.worst.iter().take(room).copied());
    }
}

/// [`SolverAgreement`] of `stage`'s per-pixel layer fit against the plain grid on `frame`.
pub fn solver_agreement(stage: &MultiFrequencyStage, frame: &PhasorFrame) -> SolverAgreement {
    let grid = reference::multi_frequency_grid(stage, frame);
    let mut a = SolverAgreement::default();
    for (i, &g) in grid.data.iter().enumerate() {
        if !g.is_finite() {
            continue;
        }
        a.grid_pixels += 1;
        let Some(inputs) = stage.pixel_inputs(frame, i) else {
            continue;
        };
        let px = inputs.phasors();
        let (Ok(fit), Ok(at_grid)) = (stage.inversion().layer(&px), stage.inversion().layer_at(&px, g)) else {
            a.refused += 1;
            continue;
        };
        let (fast, diff) = (fit.foreground_distance_mm, (fit.foreground_distance_mm - g).abs());
        a.compared += 1;
        a.max_diff_mm = a.max_diff_mm.max(diff);
        // Rounding: the grid's unit returns and the fit's are a few ulp apart.
        let rounding = 1e-9 * at_grid.chi_square.abs().max(1.0);
        if diff <= SOLVER_TOLERANCE_MM {
            a.within += 1;
        } else if fit.chi_square < at_grid.chi_square - rounding {
            a.below_grid += 1;
        } else if a.worst.len() < 10 {
            a.worst.push((i, fast, g));
        }
    }
    a
}

/// A multi-frequency recording latched as `replay` latches it (the default settings, the
/// recorded frequencies, the background frames found where the scene changes): the stage
/// and the phasors of the frames after the background.
pub fn latched_recording(path: &std::path::Path) -> anyhow::Result<(MultiFrequencyStage, Vec<PhasorFrame>)> {
    use anyhow::Context;
    let rec = crate::cli::recording::load_with_phasors(path, &Default::default(), true)?;
    let mf = rec.multi_frequency.as_ref().context("no phasor topics")?;
    let frequencies = mf
        .recorded_frequencies_hz
        .clone()
        .context("no modulation frequencies recorded")?;
    let config = PipelineConfig::default();
    let mut stage = MultiFrequencyStage::new(
        MultiFrequencyConfig::new(frequencies, config.model.clone()),
        rec.intrinsics,
    )?;
    let background = rec.background_frames(None, &config)?.count;
    let latch: Vec<(&PhasorFrame, &DepthFrame)> = mf.frames.iter().zip(&rec.frames).take(background).collect();
    stage.latch(&latch, config.model.sensor.unambiguous_range_mm())?;
    Ok((stage, mf.frames[background..].to_vec()))
}

/// What one benchmark case measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Case {
    /// `Pipeline::recover` of one frame at a fixed ξ (per-pixel inversion,
    /// noise gate, smooth-surface prior), segmentation excluded.
    Recover,
    /// [`Case::Recover`] without the smooth-surface prior (`prior_radius_px`
    /// 0): the per-pixel inversion and the noise gate alone.
    RecoverPerPixel,
    /// [`Case::Recover`] at an estimated ξ with an interval (±0.05): the depth's standard
    /// deviation then also carries ξ's share (the layer inverted at the interval's ends).
    RecoverWithInterval,
    /// Segmentation (`Pipeline::observe`) of one frame.
    Observe,
    /// ξ estimation by shape on one frame: its profile over the ξ grid and the
    /// one-material estimate.
    XiEstimate,
    /// `Pipeline::process` over the four object frames, ξ estimated online; per frame.
    Replay,
    /// The multi-frequency path ([`MultiFrequencyStage::process`]) on one frame at
    /// [`BENCH_FREQUENCIES_HZ`]: every pixel tested, the changed ones inverted.
    MultiFrequency,
    // A `NodeLatency` case (the node's added latency over DDS on loopback) goes here.
}

impl Case {
    /// The case's name in tables and JSON.
    pub fn name(&self) -> &'static str {
        match self {
            Case::Recover => "recover",
            Case::RecoverPerPixel => "recover_per_pixel",
            Case::RecoverWithInterval => "recover_with_interval",
            Case::Observe => "observe",
            Case::XiEstimate => "xi_estimate",
            Case::Replay => "replay",
            Case::MultiFrequency => "multi_frequency",
        }
    }
}

/// One row of the `bench` table.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// The case's name.
    pub name: &'static str,
    /// `WIDTHxHEIGHT`.
    pub size: String,
    /// Worker threads.
    pub threads: usize,
    /// Timed repetitions.
    pub samples: usize,
    /// Idle time before each of them, ms.
    pub pause_ms: f64,
    /// Workers pinned one per CPU.
    pub pinned: bool,
    /// Distance of the layer in the frame timed, mm (`replay`: the first of all it runs).
    pub stage_mm: f64,
    /// Median time per frame, ms.
    pub median_ms: f64,
    /// 95th percentile per frame, ms.
    pub p95_ms: f64,
    /// The plain reference on the same frame in the same run, ms (where there is one).
    pub reference_ms: Option<f64>,
    /// `reference_ms / median_ms`.
    pub speedup: Option<f64>,
    /// The target, ms, where the issue sets one.
    pub target_ms: Option<f64>,
    /// Translucent pixels in the frame, and their share of the image.
    pub translucent_pixels: usize,
    /// Share of the image segmented as translucent.
    pub translucent_fraction: f64,
    /// Fast against reference depths, where compared.
    pub agreement: Option<reference::Agreement>,
}

/// The machine a benchmark ran on: timings mean little without it (the same
/// commit has timed 20-25 % apart on two machines of the same kind).
#[derive(Debug, Clone, Serialize)]
pub struct Machine {
    /// The processor's model name with its family, model, stepping and clock
    /// (`/proc/cpuinfo`), or `unknown`.
    pub cpu: String,
    /// Logical cores this process may use.
    pub cores: usize,
    /// The vector instruction sets the processor offers, of those that matter
    /// to the numerics (the build itself targets baseline x86-64).
    pub features: Vec<&'static str>,
    /// Which build of the hand-vectorised loops ran: `avx2`, or `portable`
    /// (no AVX2, or `TTOF_PORTABLE=1`; see [`crate::physics::vector`]).
    pub vector_code: &'static str,
}

impl Machine {
    /// Reads the processor's description; never fails (fields say `unknown`).
    pub fn this() -> Self {
        // The first processor's fields; a virtual machine often names only a family, so
        // the model numbers and clock go with it.
        let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
        let field = |key: &str| {
            info.lines()
                .take_while(|l| !l.trim().is_empty())
                .filter_map(|l| l.split_once(':'))
                .find(|(k, _)| k.trim() == key)
                .map(|(_, v)| v.trim().to_string())
        };
        let cpu = match field("model name") {
            Some(name) => {
                let ids: Vec<String> = ["cpu family", "model", "stepping", "cpu MHz"]
                    .iter()
                    .filter_map(|&k| field(k).map(|v| format!("{} {v}", k.trim_start_matches("cpu "))))
                    .collect();
                if ids.is_empty() {
                    name
                } else {
                    format!("{name} ({})", ids.join(", "))
                }
            }
            None => "unknown".into(),
        };
        #[allow(unused_mut)]
        let mut features = vec![];
        #[cfg(target_arch = "x86_64")]
        {
            for (name, has) in [
                ("avx2", std::arch::is_x86_feature_detected!("avx2")),
                ("fma", std::arch::is_x86_feature_detected!("fma")),
                ("avx512f", std::arch::is_x86_feature_detected!("avx512f")),
            ] {
                if has {
                    features.push(name);
                }
            }
        }
        Self {
            cpu,
            cores: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
            features,
            vector_code: crate::physics::vector::name(),
        }
    }

    /// One line for a table's header.
    pub fn describe(&self) -> String {
        format!(
            "{}, {} cores, {}, {} code",
            self.cpu,
            self.cores,
            if self.features.is_empty() {
                "no AVX2/FMA".into()
            } else {
                self.features.join("+")
            },
            self.vector_code
        )
    }
}

/// Median and 95th percentile, ms, and the runs timed: up to `samples` runs of `f`
/// after one warm-up run, stopping early (after at least 3) once `budget_s` seconds are spent.
/// `pause`: idle time before each timed run (not timed), as between a camera's frames.
pub fn time_ms(samples: usize, budget_s: f64, pause: Duration, mut f: impl FnMut()) -> (f64, f64, usize) {
    f();
    let started = Instant::now();
    let mut t: Vec<f64> = vec![];
    while t.len() < samples.max(1) && (t.len() < 3 || started.elapsed().as_secs_f64() < budget_s) {
        if !pause.is_zero() {
            std::thread::sleep(pause);
        }
        let start = Instant::now();
        f();
        t.push(start.elapsed().as_secs_f64() * 1e3);
    }
    t.sort_by(f64::total_cmp);
    let q = |p: f64| t[((t.len() - 1) as f64 * p).round() as usize];
    (q(0.5), q(0.95), t.len())
}

/// The pipeline's per-pixel inversion ([`crate::physics::foreground_distance`])
/// over a frame: ray distances, mm (NaN where pinned or none), and where a
/// pixel fits several roots.
pub fn fast_per_pixel(pipeline: &Pipeline, obs: &Observed, xi: f64) -> (ImageBuf<f64>, Vec<bool>) {
    let c = &pipeline.config;
    let mut df = ImageBuf::filled(obs.mask.width, obs.mask.height, f64::NAN);
    let mut several = vec![false; df.len()];
    for (i, o) in obs.observations.iter() {
        if let Some(est) = crate::physics::foreground_distance(&c.model, o, xi, &c.bounds, None) {
            if !est.pinned {
                df.data[i] = est.foreground_distance_mm;
                several[i] = est.roots > 1;
            }
        }
    }
    (df, several)
}

/// Settings of a benchmark run.
#[derive(Debug, Clone, Copy)]
pub struct RunSettings {
    /// Timed repetitions per case (after one warm-up).
    pub samples: usize,
    /// Seconds a case may spend on its repetitions (at least 3 are timed).
    pub budget_s: f64,
    /// Worker threads (1: one core).
    pub threads: usize,
    /// Time the plain reference too, and compare depths.
    pub reference: bool,
    /// Idle time before each timed repetition (0: back to back). A camera's
    /// frame period shows what a node pays when its cores idle between frames.
    pub pause: Duration,
    /// The frame timed (but by `replay`): an index into [`STAGES_MM`].
    pub stage: usize,
    /// Pin the pool's workers one per CPU ([`crate::affinity`]).
    pub pin: bool,
}

/// The target for a case at a size, ms, where it sets one.
pub fn target_ms(case: Case, width: usize, height: usize, threads: usize) -> Option<f64> {
    match (case, width * height, threads) {
        (Case::Recover, 25_344, 1) => Some(1.0),
        (Case::Recover, 307_200, 1) => Some(10.0),
        (Case::XiEstimate, 25_344, _) => Some(1000.0 / 30.0),
        (Case::MultiFrequency, 307_200, 2) => Some(1000.0 / 30.0),
        _ => None,
    }
}

/// Runs one case on the frame of `settings.stage` (all frames for `replay`)
/// in a pool of `settings.threads` threads.
/// [`Case::MultiFrequency`] renders its own scene at this size ([`MultiFrequencyBench`];
/// [`run_multi_frequency`] runs one already made).
pub fn run_case(scene: &BenchScene, case: Case, settings: &RunSettings) -> Row {
    if case == Case::MultiFrequency {
        return run_multi_frequency(&MultiFrequencyBench::new(scene.width, scene.height), settings);
    }
    let pool = crate::affinity::thread_pool(settings.threads.max(1), settings.pin).expect("a thread pool");
    let stage = settings.stage.min(scene.frames.len() - 1);
    let frame = &scene.frames[stage];
    let obs = scene.observe(frame);
    let xi = XiEstimate::fixed(BENCH_XI);
    let (samples, budget, pause) = (settings.samples, settings.budget_s, settings.pause);
    let (median_ms, p95_ms, samples) = pool.install(|| match case {
        Case::Recover => time_ms(samples, budget, pause, || {
            std::hint::black_box(scene.pipeline.recover(frame, &obs, &xi));
        }),
        Case::RecoverPerPixel => {
            let mut per_pixel = scene.pipeline.clone();
            per_pixel.config.prior_radius_px = 0;
            time_ms(samples, budget, pause, || {
                std::hint::black_box(per_pixel.recover(frame, &obs, &xi));
            })
        }
        Case::RecoverWithInterval => {
            let mut estimated = xi.clone();
            estimated.interval = [BENCH_XI - 0.05, BENCH_XI + 0.05];
            time_ms(samples, budget, pause, || {
                std::hint::black_box(scene.pipeline.recover(frame, &obs, &estimated));
            })
        }
        Case::Observe => time_ms(samples, budget, pause, || {
            std::hint::black_box(scene.observe(frame));
        }),
        Case::XiEstimate => time_ms(samples, budget, pause, || {
            std::hint::black_box(scene.xi_by_shape(&obs));
        }),
        Case::Replay => {
            let (m, p, k) = time_ms(samples, budget, pause, || {
                std::hint::black_box(scene.replay());
            });
            let n = scene.frames.len() as f64;
            (m / n, p / n, k)
        }
        // Run above, on its own scene.
        Case::MultiFrequency => (f64::NAN, f64::NAN, 0),
    });
    let (mut reference_ms, mut agreement) = (None, None);
    if settings.reference {
        match case {
            Case::Recover => {
                let start = Instant::now();
                let (grid, res) = reference::recover_per_pixel(&scene.pipeline, &obs, BENCH_XI);
                reference_ms = Some(start.elapsed().as_secs_f64() * 1e3);
                let (fast, several) = fast_per_pixel(&scene.pipeline, &obs, BENCH_XI);
                agreement = Some(reference::agreement(&fast, &several, &grid, &res));
            }
            Case::XiEstimate => {
                let start = Instant::now();
                std::hint::black_box(reference::xi_grid_inversions(&scene.pipeline, &obs));
                reference_ms = Some(start.elapsed().as_secs_f64() * 1e3);
            }
            _ => {}
        }
    }
    let pixels = scene.width * scene.height;
    Row {
        name: case.name(),
        size: format!("{}x{}", scene.width, scene.height),
        threads: settings.threads.max(1),
        samples,
        pause_ms: pause.as_secs_f64() * 1e3,
        pinned: settings.pin,
        stage_mm: STAGES_MM[stage],
        median_ms,
        p95_ms,
        reference_ms,
        speedup: reference_ms.map(|r| r / median_ms),
        target_ms: target_ms(case, scene.width, scene.height, settings.threads.max(1)),
        translucent_pixels: obs.translucent_pixels,
        translucent_fraction: obs.translucent_pixels as f64 / pixels as f64,
        agreement,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pipeline's inversion and the plain 1 mm grid give the same layer
    /// wherever the pixel has one root (speed is measured by `bench`, not here).
    #[test]
    fn fast_inversion_agrees_with_the_1mm_grid() {
        let scene = BenchScene::new(64, 52);
        for (k, frame) in scene.frames.iter().enumerate() {
            let obs = scene.observe(frame);
            assert!(obs.translucent_pixels > 100, "stage {k}: {}", obs.translucent_pixels);
            let (grid, res) = reference::recover_per_pixel(&scene.pipeline, &obs, BENCH_XI);
            let (fast, several) = fast_per_pixel(&scene.pipeline, &obs, BENCH_XI);
            let a = reference::agreement(&fast, &several, &grid, &res);
            assert!(a.compared * 10 >= obs.translucent_pixels * 8, "stage {k}: {a:?}");
            assert_eq!(a.disagree, 0, "stage {k}: {a:?}");
        }
    }

    /// The per-pixel layer fit of the multi-frequency path reaches the plain 1 mm grid's
    /// global optimum (within 1 mm, or below the grid's best point) on 99.9 % of the changed
    /// pixels or more, on fresh draws (the document holder at its four distances, with the
    /// sensor's noise).
    #[test]
    fn the_multi_frequency_fit_reaches_the_grids_optimum_on_fresh_draws() {
        let mf = MultiFrequencyBench::new(96, 72);
        let mut total = SolverAgreement::default();
        for (k, (phasors, _)) in mf.frames.iter().enumerate() {
            let a = solver_agreement(&mf.stage, phasors);
            assert!(a.compared > 300, "stage {k}: {a:?}");
            total.add(&a);
        }
        eprintln!(
            "fresh draws: {} of {} within 1 mm, {} below the grid's best point, {} refused",
            total.within, total.compared, total.below_grid, total.refused
        );
        assert!(total.share_reached() >= 0.999, "{total:?}");
    }
}
