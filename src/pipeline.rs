//! The processing pipeline shared by `replay` and the node: latch a
//! background, segment the pixels that changed, estimate ξ, invert the
//! two-layer model per pixel and apply the smooth-surface prior.
//!
//! Its stages, each a module with its own tests: `latch` (the background and
//! where a recording's scene changes), `segment` (the changed pixels, their
//! observations and regions), `objects` (each region followed as an object,
//! its evidence, ξ and class), `invert` (each pixel's layer, the surface
//! prior and σ); `truth` measures the outputs against ground truth;
//! [`multifreq`] is the multi-frequency path. This file holds the types they
//! share and [`Pipeline::process`], which runs them in order.
//!
//! Buffers in, buffers out: no ROS, no files.

mod invert;
mod latch;
pub mod multifreq;
mod objects;
mod segment;
mod truth;

pub(crate) use invert::surface_standard_error;
pub use latch::{detect_scene_change, Background, BackgroundLatch, SceneChange};
pub use truth::{rmse_against_truth, TruthError};

use std::sync::Arc;

use nalgebra::Vector3;
use serde::Serialize;
use thiserror::Error;

use crate::physics::camera::z_to_ray_distance;
use crate::physics::catalog::{AlbedoReference, AlbedoScale, Catalog, Class, Classification};
use crate::physics::emitted_light::EmittedLightError;
use crate::physics::materials::{Material, Materials, PixelReading, Place, RegionEvidence};
use crate::physics::segmentation::{
    change_threshold_mm, changed_pixels, label_regions, remove_small_regions, split_reading_modes, wrapped_difference,
    DEFAULT_THRESHOLD_MM, NOISE_SIGMAS,
};
use crate::physics::translucency::{self, FrameProfile, FrameSample, XiSettings};
use crate::physics::{
    ForwardModel, ImageBuf, Intrinsics, InversionBounds, PixelObservation, Sensor, SparseImage, XiEstimate, XiMethod,
};

/// Why a frame or a latch could not be processed.
#[derive(Debug, Error)]
pub enum PipelineError {
    /// Depth and IR images differ in size, or differ from the camera's.
    #[error("size mismatch: {what} is {got_w}x{got_h}, expected {want_w}x{want_h}")]
    SizeMismatch {
        /// Which image.
        what: &'static str,
        /// Its width.
        got_w: usize,
        /// Its height.
        got_h: usize,
        /// The expected width.
        want_w: usize,
        /// The expected height.
        want_h: usize,
    },
    /// No background has been latched.
    #[error("no background latched: latch one (the first frames of the recording, or the latch service) before the object is placed")]
    NoBackground,
    /// The background frames hold too few valid readings.
    #[error("the background has {valid} valid pixels of {total}: too few (NaN/0 depth everywhere?)")]
    BackgroundInvalid {
        /// Valid pixels.
        valid: usize,
        /// All pixels.
        total: usize,
    },
    /// The emitted-light map could not be derived.
    #[error("emitted light (Eq. 13)")]
    EmittedLight(#[from] EmittedLightError),
    /// The image has more pixels than a frame's per-pixel indices (`u32`) hold.
    #[error("the image is {width}x{height}: more pixels than this pipeline indexes (4,294,967,294)")]
    TooLarge {
        /// Its width.
        width: usize,
        /// Its height.
        height: usize,
    },
    /// A given Lin calibration does not match the camera.
    #[error("the Lin calibration is {got_w}x{got_h} but the camera is {want_w}x{want_h}")]
    LinSize {
        /// Calibration width.
        got_w: usize,
        /// Calibration height.
        got_h: usize,
        /// Camera width.
        want_w: usize,
        /// Camera height.
        want_h: usize,
    },
}

/// Darkest background assumed when `Lin` is derived from the background itself: the
/// albedo the inversion implies is then known only up to the background's albedo, so
/// `X` is bounded by `background_albedo / MIN_BACKGROUND_ALBEDO`, not by 1.
pub const MIN_BACKGROUND_ALBEDO: f64 = 0.3;

/// How ξ is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum XiChoice {
    /// A given ξ (parameter `xi`).
    Fixed(f64),
    /// Estimated from the data by this method.
    Estimate(XiMethod),
}

/// Settings of the pipeline (the node's parameters).
#[derive(Debug, Clone)]
pub struct PipelineConfig {
    /// `threshold_mm`: segmentation threshold.
    pub threshold_mm: f64,
    /// Changed regions smaller than this are noise, not objects.
    pub min_region_pixels: usize,
    /// How ξ is chosen.
    pub xi: XiChoice,
    /// The forward model (sensor and physics options).
    pub model: ForwardModel,
    /// Bounds of the inversion.
    pub bounds: InversionBounds,
    /// Albedo assumed for the background when `Lin` is derived from it.
    pub background_albedo: f64,
    /// A calibrated `Lin` map (Eq. 13-14), if any.
    pub lin_calibration: Option<ImageBuf<f64>>,
    /// Radius (pixels) of the smooth-surface prior on the recovered layer; 0 = off.
    pub prior_radius_px: usize,
    /// The prior fits one window per `prior_stride_px` square block of pixels, each
    /// pixel taking the fitted surface's tangent at its own ray (1 = a window per pixel).
    pub prior_stride_px: usize,
    /// ξ estimation settings.
    pub xi_settings: XiSettings,
    /// A pixel whose layer the reading noise leaves more uncertain than this
    /// (1 sigma, mm) is not used: a nearly invisible layer is not guessed.
    pub max_layer_sigma_mm: f64,
    /// Known materials (a materials file, `--materials`): each object is classified among
    /// them, opaque and unknown, and a known material's ξ recovers it.
    pub materials: Option<Arc<Catalog>>,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self {
            threshold_mm: DEFAULT_THRESHOLD_MM,
            min_region_pixels: 12,
            xi: XiChoice::Estimate(XiMethod::OneMaterial),
            model: ForwardModel::physical(Sensor::sr4000()),
            bounds: InversionBounds::default(),
            background_albedo: 1.0,
            lin_calibration: None,
            prior_radius_px: 4,
            prior_stride_px: 3,
            xi_settings: XiSettings::default(),
            max_layer_sigma_mm: 300.0,
            materials: None,
        }
    }
}

/// An objective over the ξ grid: `(xi, value)` pairs.
pub type Profile = Vec<(f64, f64)>;

/// One depth + IR pair.
#[derive(Debug, Clone)]
pub struct DepthFrame {
    /// Stamp, ns.
    pub stamp_ns: u64,
    /// z-depth, mm, NaN invalid.
    pub z_mm: ImageBuf<f32>,
    /// IR, counts.
    pub ir: ImageBuf<f32>,
}

pub(crate) fn check_size(frame: &DepthFrame, k: &Intrinsics) -> Result<(), PipelineError> {
    for (what, w, h) in [
        ("depth", frame.z_mm.width, frame.z_mm.height),
        ("IR", frame.ir.width, frame.ir.height),
    ] {
        if w != k.width || h != k.height {
            return Err(PipelineError::SizeMismatch {
                what,
                got_w: w,
                got_h: h,
                want_w: k.width,
                want_h: k.height,
            });
        }
    }
    Ok(())
}

/// A frame's translucent pixels and what is known at each.
#[derive(Debug, Clone)]
pub struct Observed {
    /// Stamp, ns.
    pub stamp_ns: u64,
    /// Reading as ray distance, mm.
    pub distance_mm: ImageBuf<f64>,
    /// Pixels segmented as translucent.
    pub mask: ImageBuf<bool>,
    /// Observations at those pixels (none where `Lin` or the background is missing).
    pub observations: SparseImage<PixelObservation>,
    /// Segmented pixels.
    pub translucent_pixels: usize,
    /// Each pixel's region (0 off the mask, else 1 + its index in `regions`).
    pub labels: ImageBuf<u32>,
    /// The regions of the mask: connected, without a step in the readings between them.
    pub regions: Vec<ObservedRegion>,
}

/// One region of a frame's changed pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObservedRegion {
    /// Its pixels.
    pub pixels: usize,
    /// The material its evidence joined ([`Pipeline::add_xi_evidence`]), if it carried any.
    pub material: Option<u32>,
}

/// What a frame's region was recovered with.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RegionOutput {
    /// The material's id (stable over frames while it is kept); 0 for a region of a frame
    /// recovered with one given ξ, or of no material.
    pub id: u32,
    /// Its ξ estimate.
    pub xi: XiEstimate,
    /// Its pixels.
    pub pixels: usize,
    /// The data say it is opaque ([`XiEstimate::is_opaque`]): its readings are kept and
    /// it is not in the mask.
    pub opaque: bool,
    /// Its object's class among the known materials, opaque and unknown (with a materials
    /// file; `None` without one, or for a region of no object).
    pub class: Option<Classification>,
}

/// The outputs of one frame.
#[derive(Debug, Clone)]
pub struct FrameOutput {
    /// Stamp, ns.
    pub stamp_ns: u64,
    /// Translucent mask.
    pub mask: ImageBuf<bool>,
    /// Corrected z-depth, mm: recovered at translucent pixels (NaN where recovery
    /// failed), the input elsewhere.
    pub corrected_z_mm: ImageBuf<f32>,
    /// Standard deviation of the recovered z-depth, mm ([`Pipeline::recover`]); NaN where
    /// nothing was recovered.
    pub corrected_sigma_mm: ImageBuf<f32>,
    /// ξ of the frame's largest translucent region (of its largest region when none is).
    pub xi: XiEstimate,
    /// Every region's estimate, in the order of [`Observed::regions`].
    pub regions: Vec<RegionOutput>,
    /// Segmented pixels, opaque regions not counted.
    pub translucent_pixels: usize,
    /// Pixels with a recovered depth.
    pub recovered_pixels: usize,
    /// Pixels whose per-pixel inversion had no exact root (before the prior).
    pub pinned_pixels: usize,
    /// Pixels whose layer the reading noise leaves too uncertain to use
    /// (`max_layer_sigma_mm`); they get the neighbourhood's surface, if any.
    pub unresolved_pixels: usize,
    /// RMS of the per-pixel model residual, mm.
    pub fit_residual_mm: f64,
    /// Why the input was passed through uncorrected, if it was.
    pub passthrough: Option<Passthrough>,
}

/// How a frame's readings depart from the latched background, over the pixels valid in both.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Departure {
    /// Pixels valid in the frame and the background.
    pub valid: usize,
    /// Read nearer than the background, beyond the change threshold.
    pub nearer: usize,
    /// Read farther than the background, beyond the change threshold.
    pub farther: usize,
}

impl Departure {
    /// A share of the valid pixels read farther than the background beyond which the camera
    /// moved: a layer's return mixes with the background's and reads between the two (Eq. 3),
    /// never farther, so objects placed in the scene give none.
    pub const MOVED_FARTHER_SHARE: f64 = 0.2;
    /// A share of the valid pixels changed beyond which the camera moved (a move toward the
    /// scene brings every pixel nearer; objects leave most of the background in view).
    pub const MOVED_CHANGED_SHARE: f64 = 0.8;

    /// The frame is not of the camera the background was latched from.
    pub fn camera_moved(&self) -> bool {
        let share = |n: usize| n as f64 / self.valid.max(1) as f64;
        self.valid > 0
            && (share(self.farther) > Self::MOVED_FARTHER_SHARE
                || share(self.farther + self.nearer) > Self::MOVED_CHANGED_SHARE)
    }
}

/// Why a frame's input is passed through uncorrected (the node's output never goes silent).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Passthrough {
    /// No camera_info received yet: the depth alone is passed on (no cloud, no camera_info).
    NoCameraInfo,
    /// No background latched yet.
    NoBackground,
    /// A background latch is in progress.
    Latching,
    /// ξ is not determined yet (too few translucent pixels so far).
    NoXiYet,
    /// The camera moved after the latch: the background no longer lines up.
    CameraMoved,
}

impl Passthrough {
    /// Why, in words (the estimate's `method` says `passthrough: <this>`).
    pub fn as_str(self) -> &'static str {
        match self {
            Passthrough::NoCameraInfo => "no camera_info yet",
            Passthrough::NoBackground => "no background latched",
            Passthrough::Latching => "latching the background",
            Passthrough::NoXiYet => "xi not determined yet",
            Passthrough::CameraMoved => "the camera moved after the latch",
        }
    }
}

impl FrameOutput {
    /// The input as it is: nothing in the mask, nothing recovered.
    pub fn passed_through(frame: &DepthFrame, why: Passthrough) -> Self {
        let (w, h) = (frame.z_mm.width, frame.z_mm.height);
        let mut xi = XiEstimate::fixed(f64::NAN);
        xi.interval = [0.0, 1.0];
        xi.note = why.as_str().into();
        Self {
            stamp_ns: frame.stamp_ns,
            mask: ImageBuf::filled(w, h, false),
            corrected_z_mm: frame.z_mm.clone(),
            corrected_sigma_mm: ImageBuf::filled(w, h, f32::NAN),
            xi,
            regions: vec![],
            translucent_pixels: 0,
            recovered_pixels: 0,
            pinned_pixels: 0,
            unresolved_pixels: 0,
            fit_residual_mm: f64::NAN,
            passthrough: Some(why),
        }
    }
}

/// The pipeline's state: camera, background and the pooled ξ evidence.
#[derive(Debug, Clone)]
pub struct Pipeline {
    /// Settings.
    pub config: PipelineConfig,
    /// Camera.
    pub intrinsics: Intrinsics,
    /// Unit rays per pixel, shared with the outputs of each frame.
    rays: Arc<ImageBuf<Vector3<f64>>>,
    /// `ray distance / z` per pixel.
    scale: ImageBuf<f64>,
    background: Option<Background>,
    /// The noise of `d - db` per pixel, mm: the pixel's own (measured over the latch) and
    /// the latched mean's. `None` without a background or with fewer than 3 frames latched.
    change_noise: Option<ImageBuf<f64>>,
    /// The inversion's bounds for this background ([`Pipeline::bounds`]).
    bounds: InversionBounds,
    materials: Materials,
    /// Frames whose ξ evidence was added since the latch.
    evidence_frames: u64,
}

impl Pipeline {
    /// A pipeline for a camera; no background yet.
    pub fn new(config: PipelineConfig, intrinsics: Intrinsics) -> Self {
        let rays = Arc::new(intrinsics.unit_ray_map());
        let scale = intrinsics.ray_scale_map();
        Self {
            intrinsics,
            rays,
            scale,
            bounds: config.bounds,
            config,
            background: None,
            change_noise: None,
            materials: Materials::default(),
            evidence_frames: 0,
        }
    }

    /// A pipeline for a camera with the frames `background` averaged as its
    /// background (the latch).
    pub fn latched(
        config: PipelineConfig,
        intrinsics: Intrinsics,
        background: &[DepthFrame],
    ) -> Result<Self, PipelineError> {
        let k = intrinsics;
        let mut latch = BackgroundLatch::new(k.width, k.height, config.model.sensor.unambiguous_range_mm());
        for f in background {
            latch.push(f, &k)?;
        }
        let bg = latch.finish(&k, &config)?;
        let mut pipe = Self::new(config, k);
        pipe.set_background(bg);
        Ok(pipe)
    }

    /// Sets the latched background (and forgets ξ evidence tied to the old one).
    pub fn set_background(&mut self, bg: Background) {
        // The pixel's own noise, and the latched mean's (its noise over the frames averaged).
        let with_mean = (1.0 + 1.0 / bg.frames as f64).sqrt();
        self.change_noise = (bg.frames >= 3).then(|| ImageBuf {
            width: bg.noise_mm.width,
            height: bg.noise_mm.height,
            data: bg.noise_mm.data.iter().map(|s| s * with_mean).collect(),
        });
        // Without a calibrated Lin the albedo is known up to the background's: bounded allowing
        // for one as dark as MIN_BACKGROUND_ALBEDO.
        self.bounds = self.config.bounds;
        if !bg.lin_calibrated {
            self.bounds.max_albedo_cos *=
                self.config.background_albedo.max(MIN_BACKGROUND_ALBEDO) / MIN_BACKGROUND_ALBEDO;
        }
        self.background = Some(bg);
        self.materials.clear();
        self.evidence_frames = 0;
    }

    /// The inversion's bounds: the configured ones, with the bound on `X` widened when
    /// `Lin` was derived from the background ([`MIN_BACKGROUND_ALBEDO`]).
    pub fn bounds(&self) -> &InversionBounds {
        &self.bounds
    }

    /// Forgets the background.
    pub fn clear_background(&mut self) {
        self.background = None;
        self.change_noise = None;
        self.materials.clear();
        self.evidence_frames = 0;
    }

    /// Unit rays of the camera's pixels.
    pub fn rays(&self) -> &ImageBuf<Vector3<f64>> {
        &self.rays
    }

    /// [`Self::rays`], shared (for outputs made after the frame).
    pub fn shared_rays(&self) -> Arc<ImageBuf<Vector3<f64>>> {
        Arc::clone(&self.rays)
    }

    /// The latched background.
    pub fn background(&self) -> Option<&Background> {
        self.background.as_ref()
    }

    /// Online processing (the node): observe, add ξ evidence, recover with the pooled ξ.
    /// `None` for ξ when it is to be estimated and no frame has carried evidence yet.
    pub fn process(&mut self, frame: &DepthFrame) -> Result<Option<FrameOutput>, PipelineError> {
        let mut obs = self.observe(frame)?;
        self.add_xi_evidence(&mut obs);
        Ok(self.recover_regions(frame, &obs))
    }

    /// A frame's calibration evidence (paper Sec. V-A): the model's error at the
    /// known foreground distances `truth_z_mm` over ξ. `None` when fewer than
    /// 10 sampled translucent pixels have a known distance.
    pub fn calibration_profile(
        &self,
        frame: &DepthFrame,
        truth_z_mm: &ImageBuf<f32>,
    ) -> Result<Option<FrameProfile>, PipelineError> {
        let obs = self.observe(frame)?;
        let k = &self.intrinsics;
        if !truth_z_mm.same_size(&obs.mask) {
            return Err(PipelineError::SizeMismatch {
                what: "ground truth",
                got_w: truth_z_mm.width,
                got_h: truth_z_mm.height,
                want_w: k.width,
                want_h: k.height,
            });
        }
        let truth = z_to_ray_distance(truth_z_mm, &self.scale);
        let settings = &self.config.xi_settings;
        let sample = FrameSample::from_image(
            &obs.observations,
            &self.rays,
            Some(&truth),
            settings.max_pixels_per_frame,
        );
        let with_truth = match &sample.truth_mm {
            Some(t) => sample
                .observations
                .data
                .iter()
                .zip(&t.data)
                .filter(|(o, t)| o.is_some() && t.is_finite())
                .count(),
            None => 0,
        };
        if with_truth < 10 {
            return Ok(None);
        }
        Ok(Some(translucency::frame_profile(
            &self.config.model,
            &self.config.bounds,
            &sample,
            settings,
            translucency::ProfileUse::Calibration,
        )))
    }

    /// Frames of ξ evidence pooled.
    pub fn xi_frames(&self) -> usize {
        self.main_material().map_or(0, |m| m.frames())
    }

    /// The Eq. 12 comparison over the pooled frames: its RMS profile (mm) and
    /// the ξ range over which it stays within 1 mm of its minimum.
    pub fn eq12_comparison(&self) -> Option<(Profile, [f64; 2])> {
        let profiles = self.main_material()?.profiles();
        let est = translucency::eq12_residual(profiles)?;
        let r: Vec<f64> = (0..translucency::xi_grid().len())
            .map(|k| profiles.iter().map(|p| p.eq12[k]).sum())
            .collect();
        Some((est.profile, translucency::eq12_flat_range(&r, est.pixels)))
    }
}

/// The observations of `all` at the `mask` pixels (`None` only for an image too large
/// to index, which `observe` has already refused).
fn restrict(all: &SparseImage<PixelObservation>, mask: &ImageBuf<bool>) -> Option<SparseImage<PixelObservation>> {
    SparseImage::from_mask(mask, |i| all.get(i).copied())
}

/// The pixels whose region label passes `keep`.
fn label_mask(obs: &Observed, keep: impl Fn(u32) -> bool) -> ImageBuf<bool> {
    ImageBuf {
        width: obs.labels.width,
        height: obs.labels.height,
        data: obs.labels.data.iter().map(|&l| keep(l)).collect(),
    }
}
