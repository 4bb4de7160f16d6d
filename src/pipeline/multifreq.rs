//! The multi-frequency path (issue 35; docs/interfaces.md, "Multi-frequency
//! input"): a camera that gives one phasor per modulation frequency has each
//! pixel's layer determined by the pixel alone, against a latched background
//! ([`crate::physics::multifreq`]).
//!
//! Per frame, per pixel (in parallel):
//!
//! 1. the phasors `M_k` are compared with the latched background's `B_k`:
//!    a pixel whose `chi^2 = sum_k |M_k - B_k|^2 / sigma_k^2` stays below the
//!    change level is background (its reading is kept);
//! 2. a changed pixel is inverted for two returns, a layer before the
//!    background ([`MultiFrequencyInversion::invert`]); it is a layer when
//!    one return does not explain its phasors (the likelihood-ratio statistic
//!    above [`MultiFrequencyConfig::opacity_threshold`]), else opaque.
//!
//! Layer pixels in pieces of at least `min_region_pixels` form the mask; the
//! corrected depth is the layer's there and the reading elsewhere. Regions
//! (connected, without a step in depth) carry the median of their pixels' ξ
//! with an interval from their spread and stated σ; changed opaque pieces
//! are regions with ξ 0. Regions are per frame: no tracking between frames.
//!
//! The noise: each pixel's `sigma_k` (one component of `M_k`) is the spread
//! of its background phasors over the latch, grown with the latched mean's
//! own (`sqrt(1 + 1/n)` over `n` frames) and as shot noise with the light the
//! frame returns where that is more than the background's (`sqrt(|M| / |B|)`,
//! the largest amplitudes over the frequencies).

use std::sync::Arc;

use nalgebra::Vector3;
use rayon::prelude::*;
use thiserror::Error;

use super::{DepthFrame, FrameOutput, RegionOutput};
use crate::physics::coverage::{pooled_along_outline, Coverage, OutlinePixel};
use crate::physics::multifreq::{
    MultiFrequencyError, MultiFrequencyEstimate, MultiFrequencyInversion, MultiFrequencyModel, Phasor, PixelPhasors,
    ScanSettings, SingleReturn,
};
use crate::physics::segmentation::{
    enclosed_holes, label_regions, label_regions_by, open_mask, outline_pixels, remove_small_regions, step_allowed,
    wrapped_difference, EDGE_FLOOR_MM,
};
use crate::physics::stats::{median_select, quantile_select, sigma_about, student_t975};
use crate::physics::surface::{LocalSurfaces, Windows};
use crate::physics::{ForwardModel, ImageBuf, Intrinsics, XiEstimate, XiMethod};

/// Most modulation frequencies the path takes.
pub const MAX_FREQUENCIES: usize = 8;

/// The 99.9 % quantile of chi-square with one degree of freedom: the default
/// level at which a changed pixel is a layer rather than an opaque surface.
pub const CHI_SQUARE_1_999: f64 = 10.827_566_170_662_733;

/// The 99.9 % quantile of chi-square with two degrees of freedom (`-2 ln 0.001`): the
/// default level at which two free returns make a pixel a layer with no background latched.
pub const CHI_SQUARE_2_999: f64 = 13.815_510_557_964_274;

/// A background pixel whose phasors' distance, moved by a multiple of the frequencies'
/// common unambiguous range, agrees with the depth image within this (mm, wrapped at the
/// depth image's range) where as it is it does not, is aliased.
pub const ALIAS_TOLERANCE_MM: f64 = 100.0;

/// Share of the background's pixels allowed to disagree so before the
/// frequencies are refused for this scene.
pub const ALIAS_SHARE: f64 = 0.05;

/// The relative floor of a background pixel's noise: noise-free phasors
/// (simulated) still get a positive `sigma` (f32 rounding is about 6e-8).
const NOISE_FLOOR: f64 = 1e-6;

/// Pixels a rayon task takes at least.
const MIN_TASK_PIXELS: usize = 64;

/// Why the multi-frequency path cannot latch or process.
#[derive(Debug, Error)]
pub enum MultiFrequencyStageError {
    /// The frequencies or the inversion's settings.
    #[error(transparent)]
    Model(#[from] MultiFrequencyError),
    /// More frequencies than [`MAX_FREQUENCIES`].
    #[error("{0} modulation frequencies: at most {MAX_FREQUENCIES}")]
    TooManyFrequencies(usize),
    /// A frame with a phasor image per frequency missing or extra.
    #[error("{got} phasor images for {expected} modulation frequencies")]
    FrequencyCount {
        /// Frequencies.
        expected: usize,
        /// Images.
        got: usize,
    },
    /// An image of another size than the camera's.
    #[error("size mismatch: {what} is {got_w}x{got_h}, expected {want_w}x{want_h}")]
    SizeMismatch {
        /// Which image.
        what: String,
        /// Its width.
        got_w: usize,
        /// Its height.
        got_h: usize,
        /// The camera's width.
        want_w: usize,
        /// The camera's height.
        want_h: usize,
    },
    /// Nothing latched yet.
    #[error("no phasor background latched")]
    NoBackground,
    /// Too few frames to measure the background's noise. A recording with no frame of the
    /// empty scene (a moving camera, say) is recovered with no background latched.
    #[error("the phasor background needs at least 2 frames to measure its noise, got {0}; a recording with no frames of the empty scene (a moving camera) is recovered with no background latched: pass --no-latch (node parameter no_latch)")]
    TooFewFrames(usize),
    /// Too few pixels with usable background phasors.
    #[error("the phasor background has {valid} usable pixels of {total}: too few (no light returned?)")]
    BackgroundInvalid {
        /// Usable pixels.
        valid: usize,
        /// All pixels.
        total: usize,
    },
    /// The phasors put the background elsewhere than the depth image does:
    /// the frequencies' common unambiguous range is shorter than the scene.
    #[error(
        "the phasors put the background at {phasor_mm:.0} mm (median) where the depth image reads {depth_mm:.0} mm, at {share_percent:.0} % of its pixels: the frequencies' common unambiguous range {common_range_mm:.0} mm is shorter than the scene, whose distances alias; choose frequencies whose common range c / (2 gcd) covers it (20, 50 and 100 MHz: 14990 mm)"
    )]
    Aliased {
        /// The frequencies' common unambiguous range, mm.
        common_range_mm: f64,
        /// Median background distance the phasors give, mm, over the disagreeing pixels.
        phasor_mm: f64,
        /// Median the depth image gives there, mm.
        depth_mm: f64,
        /// Share of the compared pixels that disagree, %.
        share_percent: f64,
    },
}

/// One frame of a multi-frequency camera.
#[derive(Debug, Clone)]
pub struct PhasorFrame {
    /// Stamp, ns.
    pub stamp_ns: u64,
    /// One image per frequency, in the order of the frequencies: `[a, b]`
    /// (in-phase, quadrature) bucket differences, counts.
    pub phasors: Vec<ImageBuf<[f32; 2]>>,
}

/// Settings of the multi-frequency path.
#[derive(Debug, Clone)]
pub struct MultiFrequencyConfig {
    /// The modulation frequencies, Hz, in the order of the phasor images.
    pub frequencies_hz: Vec<f64>,
    /// The physics and waveform (its sensor's frequency is not used).
    pub model: ForwardModel,
    /// The inversion's search over the layer's distance.
    pub scan: ScanSettings,
    /// A pixel changed from the background when `chi^2` over its `2K` numbers
    /// exceeds chi-square's quantile this many standard normal deviations out
    /// (3.09: a tail of 0.001).
    pub change_sigmas: f64,
    /// A changed pixel is a layer when dropping the background term raises its
    /// `chi^2` by more than this ([`CHI_SQUARE_1_999`]).
    pub opacity_threshold: f64,
    /// With no background latched, a pixel is a layer when two free returns lower its
    /// `chi^2` by more than this below one return's (chi-square with 2 degrees of freedom
    /// at 99.9 %: the far return's distance and strength).
    pub two_return_threshold: f64,
    /// Pieces of the mask (and of the changed opaque pixels) smaller than this are dropped.
    pub min_region_pixels: usize,
    /// Radius (pixels) of the smooth-surface prior on each layer region (0: per pixel only),
    /// as on the single-frequency path.
    pub prior_radius_px: usize,
    /// The prior's windows are shared by square blocks of this many pixels a side.
    pub prior_stride_px: usize,
}

impl MultiFrequencyConfig {
    /// The defaults at `frequencies_hz` with `model`'s physics and waveform.
    pub fn new(frequencies_hz: Vec<f64>, model: ForwardModel) -> Self {
        Self {
            frequencies_hz,
            model,
            scan: ScanSettings::default(),
            change_sigmas: 3.09,
            opacity_threshold: CHI_SQUARE_1_999,
            two_return_threshold: CHI_SQUARE_2_999,
            min_region_pixels: 12,
            prior_radius_px: 4,
            prior_stride_px: 3,
        }
    }
}

/// The chi-square quantile with `dof` degrees of freedom `z` standard normal
/// deviations out (Wilson and Hilferty's cube-root approximation).
pub fn chi_square_quantile(dof: f64, z: f64) -> f64 {
    let a = 2.0 / (9.0 * dof);
    dof * (1.0 - a + z * a.sqrt()).powi(3)
}

/// Averages phasor frames into a background.
#[derive(Debug, Clone)]
pub struct PhasorLatch {
    width: usize,
    height: usize,
    frequencies: usize,
    frames: usize,
    /// Frames with every phasor finite, per pixel.
    n: Vec<u32>,
    /// `sum a`, `sum b` per pixel and frequency (pixel-major).
    sum: Vec<[f64; 2]>,
    /// `sum (a^2 + b^2)` per pixel and frequency.
    sum2: Vec<f64>,
    /// The first valid reading of the depth image, ray distance, mm.
    depth_mm: Vec<f64>,
}

/// One pixel of a latch: `B_k`, `sigma_k` and `db`.
type LatchedPixel = (Vec<Phasor>, Vec<f64>, f64);

/// A latched multi-frequency background.
#[derive(Debug, Clone)]
pub struct PhasorBackground {
    /// `B_k` per pixel, pixel-major (`[i * K + k]`).
    pub phasors: Vec<Phasor>,
    /// `sigma_k` of one frame's component per pixel, pixel-major.
    pub noise_sigma: Vec<f64>,
    /// `db` from one return fitted to `B_k`, ray distance, mm (NaN where unusable).
    pub distance_mm: ImageBuf<f64>,
    /// Frames averaged.
    pub frames: usize,
    /// Usable pixels.
    pub valid_pixels: usize,
    /// Pixels whose phasor distance was compared with the depth image's.
    pub compared_pixels: usize,
    /// Of those, how many disagree by more than [`ALIAS_TOLERANCE_MM`].
    pub aliased_pixels: usize,
    /// How far the phasors' distance of the background and the depth image's disagree, the
    /// magnitude of their median difference over the pixels compared (not aliased), mm: a
    /// systematic error that no distance from the phasors is free of (light along several
    /// paths moves each frequency's phase its own way; 0 before a plain wall). Every layer
    /// pixel's σ is at least this ([`MultiFrequencyStage::process`]).
    pub systematic_mm: f64,
}

impl PhasorLatch {
    /// An empty latch for `frequencies` phasor images of this size.
    pub fn new(width: usize, height: usize, frequencies: usize) -> Self {
        let n = width * height;
        Self {
            width,
            height,
            frequencies,
            frames: 0,
            n: vec![0; n],
            sum: vec![[0.0; 2]; n * frequencies],
            sum2: vec![0.0; n * frequencies],
            depth_mm: vec![f64::NAN; n],
        }
    }

    /// Frames added so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Adds a frame: its phasors, and its depth reading (`scale` turns z into ray distance).
    pub fn push(
        &mut self,
        frame: &PhasorFrame,
        depth: &DepthFrame,
        scale: &ImageBuf<f64>,
    ) -> Result<(), MultiFrequencyStageError> {
        check_frame(frame, self.frequencies, self.width, self.height)?;
        check_size(
            "depth image",
            depth.z_mm.width,
            depth.z_mm.height,
            self.width,
            self.height,
        )?;
        let k = self.frequencies;
        for i in 0..self.width * self.height {
            let d = f64::from(depth.z_mm.data[i]) * scale.data[i];
            if self.depth_mm[i].is_nan() && d.is_finite() && d > 0.0 {
                self.depth_mm[i] = d;
            }
            let finite = frame.phasors.iter().all(|p| p.data[i].iter().all(|v| v.is_finite()));
            if !finite {
                continue;
            }
            self.n[i] += 1;
            for (kk, p) in frame.phasors.iter().enumerate() {
                let [a, b] = p.data[i].map(f64::from);
                let s = &mut self.sum[i * k + kk];
                s[0] += a;
                s[1] += b;
                self.sum2[i * k + kk] += a * a + b * b;
            }
        }
        self.frames += 1;
        Ok(())
    }

    /// The averaged background: `B_k`, each pixel's noise from its spread,
    /// and `db` fitted to `B_k`, checked against the depth image's reading
    /// (`depth_range_mm`: its unambiguous range).
    pub fn finish(
        &self,
        inversion: &MultiFrequencyInversion,
        depth_range_mm: f64,
    ) -> Result<PhasorBackground, MultiFrequencyStageError> {
        if self.frames < 2 {
            return Err(MultiFrequencyStageError::TooFewFrames(self.frames));
        }
        let k = self.frequencies;
        let need = (self.frames as u32).div_ceil(2).max(2);
        let pixels: Vec<Option<LatchedPixel>> = (0..self.width * self.height)
            .into_par_iter()
            .with_min_len(MIN_TASK_PIXELS)
            .map(|i| self.pixel_background(i, need, inversion))
            .collect();
        let total = pixels.len();
        let mut bg = PhasorBackground {
            phasors: vec![Phasor::default(); total * k],
            noise_sigma: vec![f64::NAN; total * k],
            distance_mm: ImageBuf::filled(self.width, self.height, f64::NAN),
            frames: self.frames,
            valid_pixels: 0,
            compared_pixels: 0,
            aliased_pixels: 0,
            systematic_mm: 0.0,
        };
        let (mut phasor_aliased, mut depth_aliased) = (vec![], vec![]);
        let mut differences = vec![];
        let common_range = inversion.common_unambiguous_range_mm();
        for (i, p) in pixels.into_iter().enumerate() {
            let Some((b, s, db)) = p else { continue };
            bg.phasors[i * k..(i + 1) * k].copy_from_slice(&b);
            bg.noise_sigma[i * k..(i + 1) * k].copy_from_slice(&s);
            bg.distance_mm.data[i] = db;
            bg.valid_pixels += 1;
            let dd = self.depth_mm[i];
            if dd.is_finite() {
                bg.compared_pixels += 1;
                if aliased(db, dd, common_range, depth_range_mm) {
                    bg.aliased_pixels += 1;
                    phasor_aliased.push(db);
                    depth_aliased.push(dd);
                } else {
                    differences.push(db - dd);
                }
            }
        }
        if bg.valid_pixels < (total / 20).max(10) {
            return Err(MultiFrequencyStageError::BackgroundInvalid {
                valid: bg.valid_pixels,
                total,
            });
        }
        let offset = median_select(&mut differences);
        bg.systematic_mm = if offset.is_finite() { offset.abs() } else { 0.0 };
        let share = bg.aliased_pixels as f64 / bg.compared_pixels.max(1) as f64;
        if share > ALIAS_SHARE {
            return Err(MultiFrequencyStageError::Aliased {
                common_range_mm: inversion.common_unambiguous_range_mm(),
                phasor_mm: median_select(&mut phasor_aliased),
                depth_mm: median_select(&mut depth_aliased),
                share_percent: 100.0 * share,
            });
        }
        Ok(bg)
    }

    /// One pixel's `(B_k, sigma_k, db)`, or `None` if it has too few frames or no light.
    fn pixel_background(&self, i: usize, need: u32, inversion: &MultiFrequencyInversion) -> Option<LatchedPixel> {
        let n = self.n[i];
        if n < need {
            return None;
        }
        let k = self.frequencies;
        let nf = f64::from(n);
        let mut b = Vec::with_capacity(k);
        let mut sigma = Vec::with_capacity(k);
        for kk in 0..k {
            let [sa, sb] = self.sum[i * k + kk];
            let mean = Phasor { a: sa / nf, b: sb / nf };
            // Per component: half the variance of the complex value about its mean.
            let var = (self.sum2[i * k + kk] - nf * (mean.a * mean.a + mean.b * mean.b)).max(0.0) / (2.0 * (nf - 1.0));
            b.push(mean);
            sigma.push(var.sqrt());
        }
        let peak = peak_amplitude(&b);
        if !(peak > 0.0) {
            return None;
        }
        for s in &mut sigma {
            *s = s.max(NOISE_FLOOR * peak);
        }
        let fit = inversion.single_return(&b, &sigma).ok()?;
        Some((b, sigma, fit.distance_mm))
    }
}

/// How far from its region's surface near it (a share of that distance) a pixel grown into
/// the region may have its layer ([`MultiFrequencyStage::grow_layers`]): the surface comes from
/// the region's pixels in windows up to 65 pixels wide, over which a tilted layer's distance
/// changes by this much.
const GROWTH_REACH: f64 = 0.15;

/// Least step of ξ between two neighbouring layer pixels that separates two regions (two
/// materials side by side): what the model's misfit moves one material's ξ by across a sheet.
const XI_STEP_FLOOR: f64 = 0.05;

/// Most multiples of the common range [`aliased`] tries.
const MAX_ALIAS_WRAPS: usize = 16;

/// Whether a background pixel's distance from its phasors, `db`, is the depth image's `dd`
/// less a multiple of the frequencies' common unambiguous range (both wrapped at the depth
/// image's range): aliased. A disagreement that no multiple explains is light the
/// frequencies see apart (a corner's or a table's several paths), which the latched
/// phasors hold as they are.
fn aliased(db: f64, dd: f64, common_range_mm: f64, depth_range_mm: f64) -> bool {
    let off = |k: usize| wrapped_difference(db + k as f64 * common_range_mm, dd, depth_range_mm).abs();
    if !(off(0) > ALIAS_TOLERANCE_MM) || !(common_range_mm > 0.0) {
        return false;
    }
    let wraps = ((depth_range_mm / common_range_mm).ceil() as usize + 1).min(MAX_ALIAS_WRAPS);
    (1..=wraps).any(|k| off(k) <= ALIAS_TOLERANCE_MM)
}

fn check_size(what: &str, w: usize, h: usize, want_w: usize, want_h: usize) -> Result<(), MultiFrequencyStageError> {
    if (w, h) != (want_w, want_h) {
        return Err(MultiFrequencyStageError::SizeMismatch {
            what: what.to_string(),
            got_w: w,
            got_h: h,
            want_w,
            want_h,
        });
    }
    Ok(())
}

fn check_frame(
    frame: &PhasorFrame,
    frequencies: usize,
    width: usize,
    height: usize,
) -> Result<(), MultiFrequencyStageError> {
    if frame.phasors.len() != frequencies {
        return Err(MultiFrequencyStageError::FrequencyCount {
            expected: frequencies,
            got: frame.phasors.len(),
        });
    }
    for (k, p) in frame.phasors.iter().enumerate() {
        check_size(&format!("phasor image {k}"), p.width, p.height, width, height)?;
        if p.data.len() != width * height {
            return Err(MultiFrequencyStageError::SizeMismatch {
                what: format!("phasor image {k}'s data"),
                got_w: p.data.len(),
                got_h: 1,
                want_w: width * height,
                want_h: 1,
            });
        }
    }
    Ok(())
}

/// One pixel's inputs to the inversion: its phasors, its noise and the background's.
#[derive(Debug, Clone, Copy)]
pub struct PixelInputs<'a> {
    /// `M_k` (the first `frequencies`).
    pub measured: [Phasor; MAX_FREQUENCIES],
    /// `sigma_k` of each component of `M_k` (the first `frequencies`).
    pub noise_sigma: [f64; MAX_FREQUENCIES],
    /// `K`.
    pub frequencies: usize,
    /// `B_k`.
    pub background: &'a [Phasor],
    /// `db`, mm.
    pub background_distance_mm: f64,
    /// `sum_k |M_k - B_k|^2 / sigma_k^2`.
    pub change_chi_square: f64,
}

impl PixelInputs<'_> {
    /// As the inversion takes them.
    pub fn phasors(&self) -> PixelPhasors<'_> {
        PixelPhasors {
            measured: &self.measured[..self.frequencies],
            background: self.background,
            background_distance_mm: self.background_distance_mm,
            noise_sigma: &self.noise_sigma[..self.frequencies],
        }
    }
}

/// What one pixel is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelClass {
    /// No usable background or phasors there: the reading is kept.
    Unusable,
    /// Unchanged from the background.
    Background,
    /// Changed, and one return explains it.
    Opaque,
    /// Changed: a layer before the background.
    Layer,
    /// Changed, but the inversion refused it: the reading is kept.
    Failed,
    /// Changed, but neither a layer nor an opaque surface can be claimed: a layer explains
    /// it better than one return, but not beyond the level; or one return at the background's
    /// own distance, weaker than the background, explains it (the background dimmed: seen
    /// through a layer whose own return is under the noise, or shadowed). The reading is kept
    /// and no region claims it: an opaque region's bound on ξ would not hold for it.
    Unclaimed,
}

/// A pixel with no background latched: its phasors, their noise's shape (the square root
/// of its light) and one return fitted with that noise.
#[derive(Debug, Clone, Copy)]
struct UnlatchedPixel {
    measured: [Phasor; MAX_FREQUENCIES],
    shape: f64,
    single: SingleReturn,
}

/// One pixel's result.
#[derive(Debug, Clone, Copy)]
struct PixelResult {
    class: PixelClass,
    /// The fitted distance (the layer's, or the one return's), mm.
    distance_mm: f64,
    /// Its standard deviation, mm.
    distance_sigma_mm: f64,
    /// ξ (0 when opaque).
    xi: f64,
    /// The standard deviation of ξ (layers).
    xi_sigma: f64,
    /// The standard deviation of ξ² (what bounds an opaque region's ξ).
    xi_squared_sigma: f64,
    /// The layer's own return against the background's, at equal distance:
    /// `(1 - ξ) X / Xb` (NaN where not a layer with a background).
    layer_to_background: f64,
    /// The background's distance beyond the layer, mm (NaN where not known).
    gap_mm: f64,
    /// The layer's own return (the one return's, when opaque), counts (NaN where not fitted).
    first_return: f64,
    /// The fit's `chi^2` against the background (NaN where not fitted against one).
    chi_square: f64,
}

impl PixelResult {
    /// The share of this layer pixel that a layer of `xi` covers, from its own `ξ_p^2`: the
    /// background's share left there.
    fn own_share(&self, xi: f64) -> Option<Coverage> {
        Coverage::from_background_share(self.xi * self.xi, 2.0 * self.xi * self.xi_sigma, xi)
    }

    fn only(class: PixelClass) -> Self {
        Self {
            class,
            distance_mm: f64::NAN,
            distance_sigma_mm: f64::NAN,
            xi: f64::NAN,
            xi_sigma: f64::NAN,
            xi_squared_sigma: f64::NAN,
            layer_to_background: f64::NAN,
            gap_mm: f64::NAN,
            first_return: f64::NAN,
            chi_square: f64::NAN,
        }
    }
}

/// The outputs of one frame on the multi-frequency path.
#[derive(Debug, Clone)]
pub struct MultiFrequencyOutput {
    /// What the single-frequency path publishes (corrected depth, σ, mask, regions).
    pub frame: FrameOutput,
    /// ξ per pixel where the mask is set, NaN elsewhere (`~/translucency_image`).
    pub translucency: ImageBuf<f32>,
    /// Each pixel's region (0 none, else 1 + its index in `frame.regions`).
    pub labels: ImageBuf<u32>,
    /// Pixels changed from the background (inverted).
    pub changed_pixels: usize,
    /// Changed pixels one return explains.
    pub opaque_pixels: usize,
    /// Changed pixels the inversion refused.
    pub failed_pixels: usize,
    /// Changed pixels neither a layer nor opaque can be claimed for ([`PixelClass::Unclaimed`]).
    pub unclaimed_pixels: usize,
    /// Pixels without a usable background or phasors.
    pub unusable_pixels: usize,
    /// Median ξ over the mask (NaN when empty).
    pub xi_pixel_median: f64,
}

/// The multi-frequency path's state: camera, inversion and background.
#[derive(Debug, Clone)]
pub struct MultiFrequencyStage {
    /// Settings.
    pub config: MultiFrequencyConfig,
    /// Camera.
    pub intrinsics: Intrinsics,
    inversion: MultiFrequencyInversion,
    /// With three frequencies or more, the inversion with each frequency left out in turn
    /// ([`MultiFrequencyStage::frequency_jackknife`]).
    left_out: Vec<MultiFrequencyInversion>,
    rays: Arc<ImageBuf<Vector3<f64>>>,
    scale: ImageBuf<f64>,
    change_chi_square: f64,
    background: Option<PhasorBackground>,
}

impl MultiFrequencyStage {
    /// The path for a camera at `config`'s frequencies; no background yet.
    pub fn new(config: MultiFrequencyConfig, intrinsics: Intrinsics) -> Result<Self, MultiFrequencyStageError> {
        let k = config.frequencies_hz.len();
        if k > MAX_FREQUENCIES {
            return Err(MultiFrequencyStageError::TooManyFrequencies(k));
        }
        let model = MultiFrequencyModel::new(&config.model, &config.frequencies_hz)?;
        let inversion = MultiFrequencyInversion::new(&model, config.scan)?;
        let left_out = if k >= 3 {
            (0..k)
                .map(|out| {
                    let kept: Vec<f64> = (0..k).filter(|&j| j != out).map(|j| config.frequencies_hz[j]).collect();
                    MultiFrequencyInversion::new(&MultiFrequencyModel::new(&config.model, &kept)?, config.scan)
                })
                .collect::<Result<Vec<_>, _>>()?
        } else {
            vec![]
        };
        let change_chi_square = chi_square_quantile(2.0 * k as f64, config.change_sigmas);
        Ok(Self {
            rays: Arc::new(intrinsics.unit_ray_map()),
            scale: intrinsics.ray_scale_map(),
            intrinsics,
            inversion,
            left_out,
            change_chi_square,
            config,
            background: None,
        })
    }

    /// The frequencies' common unambiguous range, mm.
    pub fn common_unambiguous_range_mm(&self) -> f64 {
        self.inversion.common_unambiguous_range_mm()
    }

    /// Latches `frames` (phasors with their depth images) as the background;
    /// `depth_range_mm` is the depth image's unambiguous range.
    pub fn latch(
        &mut self,
        frames: &[(&PhasorFrame, &DepthFrame)],
        depth_range_mm: f64,
    ) -> Result<&PhasorBackground, MultiFrequencyStageError> {
        let k = &self.intrinsics;
        let mut latch = PhasorLatch::new(k.width, k.height, self.config.frequencies_hz.len());
        for (p, d) in frames {
            latch.push(p, d, &self.scale)?;
        }
        let bg = latch.finish(&self.inversion, depth_range_mm)?;
        Ok(self.background.insert(bg))
    }

    /// The latched background's systematic error ([`PhasorBackground::systematic_mm`]), 0
    /// with none latched.
    fn systematic_mm(&self) -> f64 {
        self.background.as_ref().map_or(0.0, |b| b.systematic_mm)
    }

    /// The latched background.
    pub fn background(&self) -> Option<&PhasorBackground> {
        self.background.as_ref()
    }

    /// Unit rays of the camera's pixels.
    pub fn rays(&self) -> &ImageBuf<Vector3<f64>> {
        &self.rays
    }

    /// [`Self::rays`], shared.
    pub fn shared_rays(&self) -> Arc<ImageBuf<Vector3<f64>>> {
        Arc::clone(&self.rays)
    }

    /// One frame: every pixel tested and, where changed, inverted; the mask,
    /// regions and outputs. `depth` is the frame's depth image (its readings
    /// are kept where no layer is recovered).
    pub fn process(
        &self,
        frame: &PhasorFrame,
        depth: &DepthFrame,
    ) -> Result<MultiFrequencyOutput, MultiFrequencyStageError> {
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        check_frame(frame, self.config.frequencies_hz.len(), w, h)?;
        check_size("depth image", depth.z_mm.width, depth.z_mm.height, w, h)?;
        if self.background.is_none() {
            return Err(MultiFrequencyStageError::NoBackground);
        }
        let results: Vec<PixelResult> = (0..w * h)
            .into_par_iter()
            .with_min_len(MIN_TASK_PIXELS)
            .map(|i| self.pixel(frame, i))
            .collect();
        Ok(self.assemble(depth, frame.stamp_ns, &results, Some(frame)))
    }

    /// A frame with no background latched (a moving camera): every pixel's phasors fitted by
    /// one return and by two free returns (physics.md §7; objects.md: three frequencies, no
    /// background); a layer where two explain them better by more than
    /// [`MultiFrequencyConfig::two_return_threshold`], its near return the layer's distance;
    /// every other pixel keeps its reading. The noise is each pixel's light times one scale
    /// for the frame, the scale from the median of the one-return fits' `chi^2` (most pixels
    /// of a scene are one surface). ξ needs the background's own return, which nothing here
    /// measures: the ξ image is NaN and each layer region's interval is `[0, 1]`.
    pub fn process_unlatched(
        &self,
        frame: &PhasorFrame,
        depth: &DepthFrame,
    ) -> Result<MultiFrequencyOutput, MultiFrequencyStageError> {
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        let k = self.config.frequencies_hz.len();
        check_frame(frame, k, w, h)?;
        check_size("depth image", depth.z_mm.width, depth.z_mm.height, w, h)?;
        let pixels: Vec<Option<UnlatchedPixel>> = (0..w * h)
            .into_par_iter()
            .with_min_len(MIN_TASK_PIXELS)
            .map(|i| self.unlatched_pixel(frame, i))
            .collect();
        let mut chi: Vec<f64> = pixels.iter().flatten().map(|p| p.single.chi_square).collect();
        let mut far: Vec<f64> = pixels.iter().flatten().map(|p| p.single.distance_mm).collect();
        let dof = (2 * k - 2) as f64;
        let scale2 = (median_select(&mut chi) / (dof * (1.0 - 2.0 / (9.0 * dof)).powi(3))).max(f64::MIN_POSITIVE);
        let max_distance = 1.2 * quantile_select(&mut far, 0.99) + 300.0;
        let results: Vec<PixelResult> = pixels
            .par_iter()
            .with_min_len(MIN_TASK_PIXELS)
            .map(|p| match p {
                None => PixelResult::only(PixelClass::Unusable),
                Some(p) => self.unlatched_result(p, scale2, max_distance),
            })
            .collect();
        Ok(self.assemble(depth, frame.stamp_ns, &results, None))
    }

    /// Pixel `i`'s phasors, the shape of their noise and one return fitted to them.
    fn unlatched_pixel(&self, frame: &PhasorFrame, i: usize) -> Option<UnlatchedPixel> {
        let k = self.config.frequencies_hz.len();
        let mut measured = [Phasor::default(); MAX_FREQUENCIES];
        for (m, p) in measured.iter_mut().zip(&frame.phasors) {
            let [a, b] = p.data.get(i)?.map(f64::from);
            *m = Phasor { a, b };
        }
        let peak = peak_amplitude(&measured[..k]);
        if !(peak.is_finite() && peak > 0.0) {
            return None;
        }
        // Shot noise: a component's variance grows with the light collected.
        let shape = [peak.sqrt(); MAX_FREQUENCIES];
        let single = self.inversion.single_return(&measured[..k], &shape[..k]).ok()?;
        Some(UnlatchedPixel {
            measured,
            shape: peak.sqrt(),
            single,
        })
    }

    /// A layer where two free returns beat one beyond the threshold, else the reading kept.
    fn unlatched_result(&self, p: &UnlatchedPixel, scale2: f64, max_distance: f64) -> PixelResult {
        let k = self.config.frequencies_hz.len();
        if p.single.chi_square / scale2 <= self.config.two_return_threshold {
            // Two returns cannot lower chi^2 below 0: one explains the pixel within the level.
            return PixelResult::only(PixelClass::Background);
        }
        let sigma = [p.shape * scale2.sqrt(); MAX_FREQUENCIES];
        let Ok(two) = self.inversion.two_free_returns(
            &p.measured[..k],
            &sigma[..k],
            max_distance.max(p.single.distance_mm + 300.0),
        ) else {
            return PixelResult::only(PixelClass::Failed);
        };
        let statistic = (p.single.chi_square - two.chi_square * scale2) / scale2;
        let layer = statistic > self.config.two_return_threshold && two.near_strength > 0.0 && two.far_strength > 0.0;
        if !layer {
            return PixelResult::only(PixelClass::Background);
        }
        PixelResult {
            class: PixelClass::Layer,
            distance_mm: two.near_distance_mm,
            distance_sigma_mm: two.near_distance_sigma_mm,
            xi: f64::NAN,
            xi_sigma: f64::NAN,
            xi_squared_sigma: f64::NAN,
            layer_to_background: f64::NAN,
            gap_mm: f64::NAN,
            first_return: two.near_strength,
            chi_square: f64::NAN,
        }
    }

    /// The inversion this path runs per pixel.
    pub fn inversion(&self) -> &MultiFrequencyInversion {
        &self.inversion
    }

    /// Pixel `i`'s inputs as [`Self::process`] forms them (`None` where it has no
    /// usable background or phasors, or no background is latched).
    pub fn pixel_inputs(&self, frame: &PhasorFrame, i: usize) -> Option<PixelInputs<'_>> {
        let bg = self.background.as_ref()?;
        let k = self.config.frequencies_hz.len();
        let db = bg.distance_mm.data[i];
        let mut measured = [Phasor::default(); MAX_FREQUENCIES];
        for (m, p) in measured.iter_mut().zip(&frame.phasors) {
            let [a, b] = p.data.get(i)?.map(f64::from);
            *m = Phasor { a, b };
        }
        let finite = measured[..k].iter().all(|m| m.a.is_finite() && m.b.is_finite());
        if !(db.is_finite() && finite) {
            return None;
        }
        let background = &bg.phasors[i * k..(i + 1) * k];
        let light = (peak_amplitude(&measured[..k]) / peak_amplitude(background)).max(1.0);
        let grow = (light * (1.0 + 1.0 / bg.frames as f64)).sqrt();
        let mut noise_sigma = [0.0; MAX_FREQUENCIES];
        for (s, s0) in noise_sigma.iter_mut().zip(&bg.noise_sigma[i * k..(i + 1) * k]) {
            *s = s0 * grow;
        }
        let change_chi_square = measured[..k]
            .iter()
            .zip(background)
            .zip(&noise_sigma[..k])
            .map(|((m, b), s)| ((m.a - b.a).powi(2) + (m.b - b.b).powi(2)) / (s * s))
            .sum();
        Some(PixelInputs {
            measured,
            noise_sigma,
            frequencies: k,
            background,
            background_distance_mm: db,
            change_chi_square,
        })
    }

    /// The pixel's phasors depart from the background's beyond the change level.
    pub fn changed(&self, inputs: &PixelInputs) -> bool {
        inputs.change_chi_square > self.change_chi_square
    }

    /// Tests and, where changed, inverts pixel `i`.
    fn pixel(&self, frame: &PhasorFrame, i: usize) -> PixelResult {
        let Some(inputs) = self.pixel_inputs(frame, i) else {
            return PixelResult::only(PixelClass::Unusable);
        };
        if !self.changed(&inputs) {
            return PixelResult::only(PixelClass::Background);
        }
        match self.inversion.invert(&inputs.phasors()) {
            Ok(est) if unclaimed(&est, &inputs, self.config.opacity_threshold) => {
                PixelResult::only(PixelClass::Unclaimed)
            }
            Ok(est) if self.indirect_explains(&est, &inputs) => PixelResult::only(PixelClass::Unclaimed),
            Ok(est) => self.classify(&est, &inputs),
            Err(_) => PixelResult::only(PixelClass::Failed),
        }
    }

    /// Whether a layer fitted at a pixel is explained as well (within the opacity level) by
    /// the background with light behind it blocked or added
    /// ([`MultiFrequencyInversion::indirect_change`]): an object that shades the light
    /// between a table and a wall changes the pixels beside it so, and a layer fits that
    /// change, before the wall, at a ξ near 1.
    fn indirect_explains(&self, est: &MultiFrequencyEstimate, inputs: &PixelInputs) -> bool {
        let level = self.config.opacity_threshold;
        if est.opaque || est.opacity_statistic <= level {
            return false;
        }
        self.inversion
            .indirect_change_within(&inputs.phasors(), INDIRECT_REACH_MM, est.chi_square + level)
            .unwrap_or(false)
    }

    /// A layer when its opacity statistic passes the configured level, else opaque.
    fn classify(&self, est: &MultiFrequencyEstimate, inputs: &PixelInputs) -> PixelResult {
        let layer = !est.opaque && est.opacity_statistic > self.config.opacity_threshold;
        // `translucency_sigma` is sigma(ξ²) / (2 ξ) for a layer, sqrt(sigma(ξ²)) when opaque.
        let xi_squared_sigma = if est.opaque {
            est.translucency_sigma.powi(2)
        } else {
            2.0 * est.translucency * est.translucency_sigma
        };
        PixelResult {
            class: if layer { PixelClass::Layer } else { PixelClass::Opaque },
            distance_mm: est.foreground_distance_mm,
            distance_sigma_mm: est.foreground_distance_sigma_mm,
            xi: if layer { est.translucency } else { 0.0 },
            xi_sigma: est.translucency_sigma,
            xi_squared_sigma,
            layer_to_background: layer_to_background(est, inputs),
            gap_mm: inputs.background_distance_mm - est.foreground_distance_mm,
            first_return: est.first_return,
            chi_square: est.chi_square,
        }
    }

    /// The frame's mask, regions and outputs from its pixels' results.
    /// `latched`: the frame, where a background is latched (its layers' ξ is known).
    fn assemble(
        &self,
        depth: &DepthFrame,
        stamp_ns: u64,
        results: &[PixelResult],
        latched: Option<&PhasorFrame>,
    ) -> MultiFrequencyOutput {
        let (mut mask, mut opaque) = self.masks(results, latched.is_none());
        let (mut labels, mut layers) = self.labels(results, &mask, &opaque);
        let misfit_classed: Vec<PixelResult>;
        let misfits = if latched.is_some() {
            let dof = (2 * self.config.frequencies_hz.len()).saturating_sub(3).max(1) as f64;
            region_misfits(&labels, layers, results, (dof, self.config.change_sigmas))
        } else {
            vec![]
        };
        let results = if misfits.is_empty() {
            results
        } else {
            let mut reclassed = results.to_vec();
            for &i in &misfits {
                reclassed[i] = PixelResult::only(PixelClass::Unclaimed);
            }
            misfit_classed = reclassed;
            (mask, opaque) = self.masks(&misfit_classed, false);
            (labels, layers) = self.labels(&misfit_classed, &mask, &opaque);
            &misfit_classed[..]
        };
        let pixel_sr = 1.0 / (self.intrinsics.fx * self.intrinsics.fy);
        let mut regions = regions(&labels, layers, results, pixel_sr);
        let (mut grown, mut edges, mut pooled_own) = (vec![], vec![], vec![]);
        let mut opaque_edges = vec![];
        if latched.is_some() {
            let dropped = self.opaque_edge_regions(&labels, layers, results);
            if !dropped.is_empty() {
                opaque_edges = (0..labels.len())
                    .filter(|&i| dropped.contains(&labels.data[i]))
                    .collect();
                for &i in &opaque_edges {
                    mask.data[i] = false;
                }
                (labels, layers) = drop_layer_regions(&labels, layers, &dropped);
                regions = self::regions(&labels, layers, results, pixel_sr);
            }
        }
        if latched.is_some() {
            let rims = self.opaque_edge_pixels(&labels, layers, results, &regions);
            if !rims.is_empty() {
                (labels, layers) = without_pixels(&labels, layers, &rims);
                for &i in &rims {
                    mask.data[i] = false;
                }
                opaque_edges.extend(rims);
                opaque_edges.sort_unstable();
                regions = self::regions(&labels, layers, results, pixel_sr);
            }
        }
        // An opaque edge's pixels are the object's: no layer grows into them.
        let edge_classed: Vec<PixelResult>;
        let results = if opaque_edges.is_empty() {
            results
        } else {
            edge_classed = (0..results.len())
                .map(|i| PixelResult {
                    class: if opaque_edges.binary_search(&i).is_ok() {
                        PixelClass::Opaque
                    } else {
                        results[i].class
                    },
                    ..results[i]
                })
                .collect();
            &edge_classed[..]
        };
        if let Some(frame) = latched {
            let growth = self.grow_layers(frame, &labels, layers, &regions, results);
            let (merged, new_ids, merged_layers) = merge_labels(&labels, layers, &growth.joined);
            if merged_layers < layers {
                (labels, layers) = (merged, merged_layers);
                regions = self::regions(&labels, layers, results, pixel_sr);
            }
            grown = growth.pixels.iter().map(|&(i, r)| (i, new_ids[r as usize])).collect();
            // The layer regions with what is grown into them, as the next steps see them.
            let mut with_grown = labels.clone();
            for &(i, r) in &grown {
                with_grown.data[i] = r;
            }
            let holes = self.holes(&with_grown, layers, results);
            for &(i, r) in &holes {
                with_grown.data[i] = r;
            }
            grown.extend(holes);
            let band = self.outline_band(frame, &labels, &with_grown, layers, &regions, results);
            (edges, pooled_own) = Self::covered_edges(&band, layers);
            pooled_own.sort_unstable_by_key(|&(i, _)| i);
            grown.extend(edges.iter().map(|e| (e.pixel, e.region)));
        }
        let mut layer = self.surface_prior(&labels, layers, results, &grown);
        if let Some(frame) = latched {
            // Each layer region's pixels, for both shares of σ.
            let members = label_members(&labels, layers, |_| true);
            self.add_translucency_share(frame, &members, &regions, &grown, &mut layer);
            self.add_misfit_share(&members, results, &grown, (&mut regions, &mut layer));
            self.widen_by_frequency_jackknife(frame, &labels, layers, results, &mut regions);
        }
        for e in &edges {
            layer.sigma_mm[e.pixel] = layer.sigma_mm[e.pixel].max(e.sigma_floor_mm);
        }
        let mut results = results.to_vec();
        for &(i, region) in &grown {
            if layer.distance_mm[i].is_finite() {
                labels.data[i] = region;
                mask.data[i] = true;
                results[i] = PixelResult {
                    class: PixelClass::Layer,
                    xi: regions[region as usize - 1].xi.xi,
                    ..PixelResult::only(PixelClass::Layer)
                };
            }
        }
        if latched.is_some() {
            let shares = OutlineShares {
                regions: &regions,
                pooled: &pooled_own,
            };
            self.keep_uncovered_outline(&mut mask, &mut labels, layers, &mut results, &mut layer, &shares);
        }
        let count = |c: PixelClass| results.iter().filter(|r| r.class == c).count();
        let mut filled = self.fill(depth, &mask, &results, &layer);
        self.resolve_opaque_edges(&opaque_edges, &results, &mut filled);
        let xi = frame_estimate(&regions, layers as usize);
        MultiFrequencyOutput {
            frame: FrameOutput {
                stamp_ns,
                mask,
                corrected_z_mm: filled.corrected_z_mm,
                corrected_sigma_mm: filled.sigma_mm,
                xi,
                regions,
                translucent_pixels: filled.pixels,
                recovered_pixels: filled.pixels,
                pinned_pixels: 0,
                unresolved_pixels: count(PixelClass::Failed),
                fit_residual_mm: f64::NAN,
                passthrough: None,
            },
            translucency: filled.translucency,
            labels,
            changed_pixels: count(PixelClass::Opaque)
                + count(PixelClass::Layer)
                + count(PixelClass::Failed)
                + count(PixelClass::Unclaimed),
            opaque_pixels: count(PixelClass::Opaque),
            failed_pixels: count(PixelClass::Failed),
            unclaimed_pixels: count(PixelClass::Unclaimed),
            unusable_pixels: count(PixelClass::Unusable),
            xi_pixel_median: filled.xi_median,
        }
    }

    /// The layer regions that are an opaque object's edge: no pixel of theirs has all eight
    /// neighbours in the region (a rim a pixel or two wide), half of their pixels or more
    /// touch an opaque region, and at half or more of those the fitted layer lies where the
    /// opaque neighbour is (within 3 σ of the two, or 2 % of the distance). A pixel that
    /// straddles an opaque edge mixes the object's return with the background's: with the
    /// background latched it fits a layer at the object's distance whose `ξ^2` is the share
    /// of the background it sees, which varies along the edge; a translucent layer has an
    /// interior.
    fn opaque_edge_regions(&self, labels: &ImageBuf<u32>, layers: u32, results: &[PixelResult]) -> Vec<u32> {
        let (w, h) = (labels.width, labels.height);
        let neighbours = |i: usize| neighbours_8(i, w, h);
        // Per layer region: pixels, interior pixels, pixels touching an opaque region, and
        // those of them at the opaque neighbour's distance.
        let mut tally = vec![[0usize; 4]; layers as usize + 1];
        for i in 0..labels.len() {
            let l = labels.data[i];
            if l == 0 || l > layers {
                continue;
            }
            let t = &mut tally[l as usize];
            t[0] += 1;
            let all_inside = neighbours(i).count() == 8 && neighbours(i).all(|n| labels.data[n] == l);
            t[1] += usize::from(all_inside);
            let (touching, beside) = beside_opaque(i, labels, layers, results);
            t[2] += usize::from(touching);
            t[3] += usize::from(beside);
        }
        (1..=layers)
            .filter(|&l| {
                let [n, inside, touching, beside] = tally[l as usize];
                n > 0 && inside == 0 && 2 * touching >= n && 2 * beside >= touching
            })
            .collect()
    }

    /// Where an opaque object's edge runs along a sheet and joins the sheet's region: the
    /// region's pixels beside the background (an 8-neighbour in no region) and beside an
    /// opaque region at that region's distance (as in [`Self::opaque_edge_regions`]), that
    /// hide more of the background than the region's material could over the whole pixel (a
    /// share of it beyond 1 by more than `change_sigmas` of its σ). Such a pixel's
    /// `1 - ξ_p^2` is the object's share of it; a pixel of the region's material hides at
    /// most `1 - ξ^2`, and one that the object partly covers has the sheet beside it.
    fn opaque_edge_pixels(
        &self,
        labels: &ImageBuf<u32>,
        layers: u32,
        results: &[PixelResult],
        regions: &[RegionOutput],
    ) -> Vec<usize> {
        let (w, h) = (labels.width, labels.height);
        let z = self.config.change_sigmas;
        (0..labels.len())
            .filter(|&i| {
                let l = labels.data[i];
                let Some(region) = (l >= 1 && l <= layers).then(|| regions.get(l as usize - 1)).flatten() else {
                    return false;
                };
                let beyond_whole = results[i]
                    .own_share(region.xi.xi)
                    .is_some_and(|c| c.share - 1.0 > z * c.share_sigma);
                let by_background = neighbours_8(i, w, h).any(|n| labels.data[n] == 0);
                by_background && beyond_whole && beside_opaque(i, labels, layers, results).1
            })
            .collect()
    }

    /// The pixels of an opaque object's edge ([`Self::opaque_edge_regions`]) published at
    /// what their centre sees: the object (its fitted distance) where it covers half of the
    /// pixel or more (`c = 1 - ξ_p^2`), else the latched background; σ at least half the gap
    /// where `c`'s 95 % interval holds a half. A reading there is a mix of the two, nearer
    /// neither.
    fn resolve_opaque_edges(&self, pixels: &[usize], results: &[PixelResult], filled: &mut Filled) {
        for &i in pixels {
            let (p, s) = (&results[i], self.scale.data[i]);
            let Some(cov) = Coverage::from_background_share(p.xi * p.xi, p.xi_squared_sigma, 0.0) else {
                continue;
            };
            let background = p.distance_mm + p.gap_mm;
            if !(p.distance_mm.is_finite() && background.is_finite()) {
                continue;
            }
            let distance = if cov.centre_covered() {
                p.distance_mm
            } else {
                background
            };
            let sigma = p
                .distance_sigma_mm
                .max(cov.sigma_floor_mm(p.gap_mm))
                .hypot(self.systematic_mm());
            filled.corrected_z_mm.data[i] = (distance / s) as f32;
            filled.sigma_mm.data[i] = (sigma / s) as f32;
        }
    }

    /// The mask (layer pixels in pieces of at least `min_region_pixels`; with `open`, first
    /// opened by a 3 x 3 square so that the mixed pixels along an opaque edge, two returns
    /// but no layer, drop out) and the changed opaque pixels (what the mask dropped among
    /// them), likewise cleaned. Only the unlatched path opens: with a background latched an
    /// edge's mix fits a layer whose ξ² is the share of background it sees, and thin
    /// parts of real layers (slivers between sheets) would go with it: on the rendered
    /// `mf_two_materials` opening took 5 % of the sheets' pixels back to their readings.
    fn masks(&self, results: &[PixelResult], open: bool) -> (ImageBuf<bool>, ImageBuf<bool>) {
        let min = self.config.min_region_pixels;
        let class_mask = |keep: &dyn Fn(&PixelResult) -> bool| ImageBuf {
            width: self.intrinsics.width,
            height: self.intrinsics.height,
            data: results.iter().map(keep).collect(),
        };
        let layers = class_mask(&|r| r.class == PixelClass::Layer);
        let (mask, _) = remove_small_regions(&if open { open_mask(&layers) } else { layers }, min);
        let mut opaque = class_mask(&|r| matches!(r.class, PixelClass::Opaque | PixelClass::Layer));
        for (o, &m) in opaque.data.iter_mut().zip(&mask.data) {
            *o &= !m;
        }
        (mask, remove_small_regions(&opaque, min).0)
    }

    /// Each pixel's region (layers first, then the opaque ones; 0 none), split
    /// where the fitted distance steps, and the number of layer regions.
    fn labels(&self, results: &[PixelResult], mask: &ImageBuf<bool>, opaque: &ImageBuf<bool>) -> (ImageBuf<u32>, u32) {
        let distance = ImageBuf {
            width: mask.width,
            height: mask.height,
            data: results.iter().map(|r| r.distance_mm).collect(),
        };
        let (range, min) = (self.common_unambiguous_range_mm(), self.config.min_region_pixels);
        let noise = |i: usize| results[i].distance_sigma_mm;
        // Layers: where the distance steps, or ξ does (two materials side by side).
        let scaled_steps = |i: usize, j: usize| {
            let (a, b) = (&results[i], &results[j]);
            let d = wrapped_difference(a.distance_mm, b.distance_mm, range).abs();
            let d_allowed = step_allowed(EDGE_FLOOR_MM, a.distance_sigma_mm, b.distance_sigma_mm);
            let xi_allowed = step_allowed(XI_STEP_FLOOR, a.xi_sigma, b.xi_sigma);
            // With no background latched no pixel has a ξ: the distance alone.
            let xi = (a.xi - b.xi).abs() / xi_allowed;
            (d / d_allowed, if xi.is_nan() { 0.0 } else { xi })
        };
        let joined = |i: usize, j: usize| {
            let (d, xi) = scaled_steps(i, j);
            d <= 1.0 && xi <= 1.0
        };
        let step = |i: usize, j: usize| {
            let (d, xi) = scaled_steps(i, j);
            d + xi
        };
        let (layer_labels, layer_sizes) = label_regions_by(mask, joined, step, min);
        let (opaque_labels, _) = label_regions(opaque, &distance, noise, range, min);
        let layers = layer_sizes.len() as u32;
        let data = layer_labels
            .data
            .iter()
            .zip(&opaque_labels.data)
            .map(|(&l, &o)| match (l, o) {
                (0, 0) => 0,
                (0, o) => o + layers,
                (l, _) => l,
            })
            .collect();
        let labels = ImageBuf {
            width: mask.width,
            height: mask.height,
            data,
        };
        (labels, layers)
    }

    /// Pixels of no region, unclaimed ([`PixelClass::Unclaimed`]) or layers in pieces too
    /// small for a region, that a layer region's ξ explains, reached from the region through
    /// such pixels (8-connected), and the layer regions that touch, directly or through them,
    /// with overlapping ξ intervals (one layer that the noise of its faint return split). A pixel
    /// is taken where the best layer at the region's ξ (its return free, its distance free
    /// up to halfway from the region's own pixels near it to the background) fits its
    /// phasors within chi-square's quantile with `2K - 2` degrees of freedom at the change
    /// level: the background behind it dimmed by ξ² as beside it, and a return of its own
    /// that the noise may hide (a faint layer, ξ near 1, far away), but not far under the
    /// returns of the region's own pixels near it ([`too_weak`]). A pixel that the layer
    /// only partly covers, or the background beside it, is not dimmed by ξ²: it fits only
    /// with a return at the background, which the search does not reach. Its distance is
    /// then the region's surface's ([`Self::surface_prior`]): the pixel's own phasors do not
    /// fix it.
    fn grow_layers(
        &self,
        frame: &PhasorFrame,
        labels: &ImageBuf<u32>,
        layers: u32,
        regions: &[RegionOutput],
        results: &[PixelResult],
    ) -> Growth {
        let (w, h) = (labels.width, labels.height);
        let k = self.config.frequencies_hz.len();
        let level = chi_square_quantile((2 * k).saturating_sub(2).max(1) as f64, self.config.change_sigmas);
        const TRIED: u32 = u32::MAX;
        let mut owner: Vec<u32> = labels.data.iter().map(|&l| if l <= layers { l } else { 0 }).collect();
        let mut queue: std::collections::VecDeque<usize> = (0..w * h).filter(|&i| owner[i] > 0).collect();
        let mut grown = Growth::default();
        let overlap = |a: u32, b: u32| {
            let (x, y) = (
                &regions[a as usize - 1].xi.interval,
                &regions[b as usize - 1].xi.interval,
            );
            x[0] <= y[1] && y[0] <= x[1]
        };
        while let Some(i) = queue.pop_front() {
            let region = owner[i];
            let Some(xi) = regions
                .get(region as usize - 1)
                .map(|r| r.xi.xi)
                .filter(|x| x.is_finite())
            else {
                continue;
            };
            let (c, r) = ((i % w) as isize, (i / w) as isize);
            for (dc, dr) in NEIGHBOURS_8 {
                let (cc, rr) = (c + dc, r + dr);
                if cc < 0 || rr < 0 || cc >= w as isize || rr >= h as isize {
                    continue;
                }
                let j = rr as usize * w + cc as usize;
                let other = owner[j];
                if other != 0 && other != TRIED && other != region && overlap(region, other) {
                    grown.joined.push((region.min(other), region.max(other)));
                }
                // Unclaimed, or a layer's pixel in a piece too small to be a region of its own.
                let open = matches!(results[j].class, PixelClass::Unclaimed | PixelClass::Layer);
                if owner[j] != 0 || labels.data[j] != 0 || !open {
                    continue;
                }
                // The layer must lie where the region's surface near the pixel is (within
                // GROWTH_REACH of it: a pixel whose own bright layer lies elsewhere is not
                // the region's, whatever ξ fits it) and stay clear of the background: halfway
                // from that surface to the background at most.
                let Some(local) = self.local_layer(j, region, labels, results) else {
                    continue;
                };
                let near = local.distance_mm;
                let fits = self.pixel_inputs(frame, j).is_some_and(|p| {
                    let clear = (near + p.background_distance_mm) / 2.0;
                    let window = (near * (1.0 - GROWTH_REACH), clear.min(near * (1.0 + GROWTH_REACH)));
                    self.inversion
                        .fit_at_translucency_within(&p.phasors(), xi, window)
                        .is_ok_and(|f| f.chi_square <= level && !too_weak(f.first_return, local.weak_return, &p))
                });
                owner[j] = if fits { region } else { TRIED };
                if fits {
                    grown.pixels.push((j, region));
                    queue.push_back(j);
                }
            }
        }
        grown.joined.sort_unstable();
        grown.joined.dedup();
        grown
    }

    /// Where `region`'s layer is near pixel `i`: its own pixels (its labels, not those grown)
    /// in the narrowest of the prior's windows about `i` that holds any ([`PRIOR_WIDENINGS`]),
    /// their median distance and the lower quartile of their returns. A faint layer's own
    /// pixels may be few and far between, and what is grown from them lies beyond the first
    /// window.
    fn local_layer(
        &self,
        i: usize,
        region: u32,
        labels: &ImageBuf<u32>,
        results: &[PixelResult],
    ) -> Option<LocalLayer> {
        let (w, h) = (labels.width as isize, labels.height as isize);
        let (c, row) = ((i as isize) % w, (i as isize) / w);
        (0..PRIOR_WIDENINGS).find_map(|k| {
            let r = (self.config.prior_radius_px.max(1) << k) as isize;
            let own: Vec<&PixelResult> = ((row - r).max(0)..=(row + r).min(h - 1))
                .flat_map(|y| ((c - r).max(0)..=(c + r).min(w - 1)).map(move |x| (y * w + x) as usize))
                .filter(|&j| labels.data[j] == region && results[j].distance_mm.is_finite())
                .map(|j| &results[j])
                .collect();
            let mut distances: Vec<f64> = own.iter().map(|p| p.distance_mm).collect();
            let mut returns: Vec<f64> = own.iter().map(|p| p.first_return).filter(|a| a.is_finite()).collect();
            let distance_mm = median_select(&mut distances);
            distance_mm.is_finite().then(|| LocalLayer {
                distance_mm,
                weak_return: quantile_select(&mut returns, 0.25),
            })
        })
    }

    /// The holes of the layer regions with what was grown into them: pieces of fewer than
    /// `min_region_pixels` that no region claims, each pixel unchanged from the background,
    /// unclaimed, failed or a layer's, and surrounded by one layer region alone. A layer
    /// whose own return is under the noise (ξ near 1) leaves such pixels in its midst: its
    /// phasors there fit the region's ξ a little beyond the level or not at all, while a
    /// sheet has no pinholes. Each takes its region's surface, as a grown pixel does.
    fn holes(&self, with_grown: &ImageBuf<u32>, layers: u32, results: &[PixelResult]) -> Vec<(usize, u32)> {
        let eligible = |i: usize| unclaimed_by_a_region(results[i].class);
        let max = self.config.min_region_pixels.saturating_sub(1);
        enclosed_holes(with_grown, max, eligible)
            .into_iter()
            .filter(|&(_, r)| r <= layers)
            .collect()
    }

    /// The pixels along a layer region's outline that the layer covers by half or more:
    /// of no region, unchanged, unclaimed, failed or a layer's, 8-adjacent to one layer region
    /// (with what was grown into it) alone. The share `c` the layer covers follows from the
    /// background left at the region's distance near the pixel, `t = 1 - c (1 - ξ^2)`
    /// ([`MultiFrequencyInversion::background_share_at`]): the mixed pixels of a layer whose
    /// own return is under the noise fit neither a layer nor the background. Where one
    /// pixel's share does not decide, the shares along the outline (these pixels and the
    /// region's own outline pixels) are pooled ([`pooled_along_outline`]). Where `c`'s 95 %
    /// interval still holds one half, the data cannot tell whether the pixel's centre sees
    /// the layer or the background: its σ is at least half the gap between them. `band` is
    /// [`Self::outline_band`]'s. Also returns the pooled shares of the regions' own outline
    /// pixels, for [`Self::keep_uncovered_outline`].
    fn covered_edges(band: &[BandPixel], layers: u32) -> (Vec<CoveredEdge>, Vec<(usize, Coverage)>) {
        let mut edges = vec![];
        let mut own = vec![];
        for region in 1..=layers {
            let members: Vec<&BandPixel> = band.iter().filter(|b| b.region == region).collect();
            let at: Vec<OutlinePixel> = members.iter().map(|b| b.at).collect();
            for (b, cov) in members.iter().zip(pooled_along_outline(&at)) {
                match b.gap_mm {
                    None => own.push((b.pixel, cov)),
                    Some(gap) if cov.centre_covered() => edges.push(CoveredEdge {
                        pixel: b.pixel,
                        region,
                        sigma_floor_mm: cov.sigma_floor_mm(gap),
                    }),
                    Some(_) => {}
                }
            }
        }
        edges.sort_unstable_by_key(|e| e.pixel);
        (edges, own)
    }

    /// The outline pixels of each layer region with their own covered shares: the pixels
    /// beside it ([`Self::covered_edges`]) and its own pixels with a neighbour outside it
    /// (their `ξ_p^2` is the background's share left, [`Self::keep_uncovered_outline`]).
    fn outline_band(
        &self,
        frame: &PhasorFrame,
        labels: &ImageBuf<u32>,
        with_grown: &ImageBuf<u32>,
        layers: u32,
        regions: &[RegionOutput],
        results: &[PixelResult],
    ) -> Vec<BandPixel> {
        let (w, h) = (labels.width, labels.height);
        let open = |i: usize| with_grown.data[i] == 0 && unclaimed_by_a_region(results[i].class);
        let neighbours = |i: usize| neighbours_8(i, w, h);
        let neighbour_region = |i: usize| {
            let mut seen = None;
            for n in neighbours(i) {
                match with_grown.data[n] {
                    0 => {}
                    l if l > layers || seen.is_some_and(|s| s != l) => return None,
                    l => seen = Some(l),
                }
            }
            seen
        };
        let at = |i: usize, coverage: Coverage| OutlinePixel {
            x: (i % w) as f64,
            y: (i / w) as f64,
            coverage,
        };
        let beside: Vec<BandPixel> = (0..w * h)
            .into_par_iter()
            .filter(|&i| open(i))
            .filter_map(|i| {
                let region = neighbour_region(i)?;
                let xi = regions.get(region as usize - 1)?.xi.xi;
                let near = self.local_layer(i, region, labels, results)?.distance_mm;
                let p = self.pixel_inputs(frame, i)?;
                let (t, sd) = self.inversion.background_share_at(&p.phasors(), near).ok()?;
                let cov = Coverage::from_background_share(t, sd, xi)?;
                Some(BandPixel {
                    pixel: i,
                    region,
                    at: at(i, cov),
                    gap_mm: Some(p.background_distance_mm - near),
                })
            })
            .collect();
        let inside = (0..w * h).filter_map(|i| {
            let region = labels.data[i];
            if region == 0 || region > layers || neighbours(i).all(|n| with_grown.data[n] == region) {
                return None;
            }
            let cov = results[i].own_share(regions.get(region as usize - 1)?.xi.xi)?;
            Some(BandPixel {
                pixel: i,
                region,
                at: at(i, cov),
                gap_mm: None,
            })
        });
        beside.into_iter().chain(inside).collect()
    }

    /// A layer region's own pixels on its outline (an 8-neighbour outside the mask) that the
    /// layer covers by less than half leave the mask and keep their readings; those it may
    /// cover by less than half take a σ of at least half the gap to the background. A pixel
    /// that a layer of `ξ` covers by a share `c` fits a layer at the layer's distance with
    /// `ξ_p^2 = 1 - c (1 - ξ^2)` ([`Self::covered_edges`] is the same from the other side):
    /// its centre sees the background where `c < 1/2`, and the reading is nearer the truth
    /// there than the layer's distance. Where the pixel's own share does not decide, the
    /// share pooled along the outline does ([`OutlineShares`]).
    fn keep_uncovered_outline(
        &self,
        mask: &mut ImageBuf<bool>,
        labels: &mut ImageBuf<u32>,
        layers: u32,
        results: &mut [PixelResult],
        layer: &mut Layer,
        shares: &OutlineShares,
    ) {
        let edge = outline_pixels(mask, false);
        let mut uncovered = vec![];
        for i in (0..edge.data.len()).filter(|&i| edge.data[i]) {
            let (l, p) = (labels.data[i], &results[i]);
            if l < 1 || l > layers {
                continue;
            }
            let Some(cov) = shares.of(i, p, l) else {
                continue;
            };
            if !cov.centre_covered() {
                uncovered.push(i);
            } else if p.gap_mm.is_finite() {
                layer.sigma_mm[i] = layer.sigma_mm[i].max(cov.sigma_floor_mm(p.gap_mm));
            }
        }
        for i in uncovered {
            mask.data[i] = false;
            labels.data[i] = 0;
            results[i] = PixelResult::only(PixelClass::Unclaimed);
        }
    }

    /// Each pixel's layer distance along its ray, mm: the pixel's own, or, with the prior,
    /// the local surface fitted over its region's pixels (robust planes in windows of
    /// `prior_radius_px`, one region at a time so that no window mixes two objects), where
    /// one fits; the window's size is each pixel's own ([`PRIOR_WIDENINGS`]). A pixel of
    /// `grown` takes its region's nearest plane of the widest windows within their radius,
    /// with the nearest region pixel's σ grown by the distance to it in `prior_radius_px`
    /// (in quadrature); NaN where none (it keeps its reading).
    fn surface_prior(
        &self,
        labels: &ImageBuf<u32>,
        layers: u32,
        results: &[PixelResult],
        grown: &[(usize, u32)],
    ) -> Layer {
        let roots: Vec<f64> = results.iter().map(|r| r.distance_mm).collect();
        let noise: Vec<f64> = results.iter().map(|r| r.distance_sigma_mm).collect();
        let mut out = roots.clone();
        if self.config.prior_radius_px == 0 || layers == 0 {
            return Layer {
                distance_mm: out,
                sigma_mm: noise,
            };
        }
        let (w, h) = (labels.width, labels.height);
        let nan = Vector3::new(f64::NAN, f64::NAN, f64::NAN);
        let mut sigma_mm = noise.clone();
        let mut chosen = vec![f64::INFINITY; w * h];
        let radii: Vec<usize> = (0..PRIOR_WIDENINGS).map(|k| self.config.prior_radius_px << k).collect();
        // A grown pixel takes the nearest plane as far as the widest window reaches.
        let reach = radii.last().copied().unwrap_or(1);
        for region in 1..=layers {
            let mask = ImageBuf {
                width: w,
                height: h,
                data: labels.data.iter().map(|&l| l == region).collect(),
            };
            let members: Vec<usize> = (0..mask.len()).filter(|&i| mask.data[i]).collect();
            let mut points = ImageBuf::filled(w, h, nan);
            for &i in &members {
                if results[i].distance_mm.is_finite() {
                    points.data[i] = self.rays.data[i] * results[i].distance_mm;
                }
            }
            let mut widest = None;
            for &radius in &radii {
                let windows = Windows {
                    radius,
                    min_points: 12,
                    stride: self.config.prior_stride_px.max(radius / 2).max(1),
                };
                let surfaces = LocalSurfaces::new(&points, &self.rays, &mask, &windows);
                let mut surface = vec![f64::NAN; w * h];
                for &i in &members {
                    if let Some(t) = surfaces
                        .ray_distance(i, &self.rays)
                        .filter(|t| t.is_finite() && *t > 0.0)
                    {
                        surface[i] = t;
                    }
                }
                // The roots' scatter about the surface near each pixel, averaged down by the
                // window (as on the single-frequency path); the window whose is least wins.
                let se = crate::pipeline::surface_standard_error(&roots, &surface, &noise, w, radius, f64::NAN);
                for &i in &members {
                    if surface[i].is_finite() && se[i] < chosen[i] {
                        (chosen[i], out[i], sigma_mm[i]) = (se[i], surface[i], se[i]);
                    }
                }
                widest = Some(surfaces);
                let mut now: Vec<f64> = members.iter().map(|&i| chosen[i]).filter(|s| s.is_finite()).collect();
                if median_select(&mut now) <= PRIOR_FINE_ENOUGH_MM {
                    break;
                }
            }
            let Some(surfaces) = widest else {
                continue;
            };
            for &(i, _) in grown.iter().filter(|g| g.1 == region) {
                out[i] = surfaces
                    .nearest_plane(i, reach, &self.rays)
                    .and_then(|p| p.ray_distance(&self.rays.data[i]))
                    .unwrap_or(f64::NAN);
            }
        }
        for &(i, region) in grown {
            sigma_mm[i] = self.grown_sigma(i, region, labels, &sigma_mm);
        }
        Layer {
            distance_mm: out,
            sigma_mm,
        }
    }

    /// Widens each layer region's ξ interval by what leaving one frequency out does to ξ
    /// ([`Self::frequency_jackknife`]): about ξ, to Student's t (K - 1 degrees of freedom)
    /// times the jackknife's standard error where that is wider. After σ has taken its share
    /// of the interval ([`Self::add_translucency_share`]): with the jackknife in σ too (at
    /// 1.96 standard errors) σ held the error for 98.1 % of two committed renders' recovered
    /// pixels (docs/multifrequency.md), beyond the 98 % that says σ is no wider than the
    /// errors ask; the floor under σ ([`PhasorBackground::systematic_mm`]) carries the same
    /// misfit in depth.
    fn widen_by_frequency_jackknife(
        &self,
        frame: &PhasorFrame,
        labels: &ImageBuf<u32>,
        layers: u32,
        results: &[PixelResult],
        regions: &mut [RegionOutput],
    ) {
        let members = label_members(labels, layers, |i| results[i].class == PixelClass::Layer);
        for (region, own) in regions.iter_mut().zip(&members) {
            let (xi, [lo, hi]) = (region.xi.xi, region.xi.interval);
            let jackknife = self.frequency_jackknife(frame, own, results);
            let Some((se, moved)) = jackknife.filter(|(se, _)| xi.is_finite() && *se > 0.0) else {
                continue;
            };
            let half = student_t975(self.left_out.len() - 1) * se;
            region.xi.interval = [lo.min(xi - half).max(0.0), hi.max(xi + half).min(1.0)];
            region.xi.note.push_str(&format!(
                "; with each frequency left out in turn the pixels' median xi is {moved}: a half width of {half:.4} from their scatter (jackknife)"
            ));
        }
    }

    /// The jackknife over the frequencies of a region's ξ: with each frequency left out in
    /// turn, the median ξ of up to [`SHARE_SAMPLES`] of the region's pixels, each refitted
    /// within [`GROWTH_REACH`] of its own layer (and clear of the background); the
    /// jackknife's standard error `sqrt((K - 1) / K sum (ξ_(k) - mean)^2)`. Each frequency
    /// measures the same layer; light along several paths (a table before a wall) turns each
    /// frequency's phasor its own way, and what that does to ξ shows as the estimates'
    /// disagreement, which one frame's residuals do not show. With the leave-one-out medians,
    /// as text. `None` with fewer than three frequencies or no pixel to refit.
    fn frequency_jackknife(
        &self,
        frame: &PhasorFrame,
        pixels: &[usize],
        results: &[PixelResult],
    ) -> Option<(f64, String)> {
        let k = self.left_out.len();
        if k < 3 || pixels.is_empty() {
            return None;
        }
        let step = pixels.len().div_ceil(SHARE_SAMPLES).max(1);
        let mut per_left_out: Vec<Vec<f64>> = vec![vec![]; k];
        for &i in pixels.iter().step_by(step) {
            let Some(p) = self.pixel_inputs(frame, i) else { continue };
            let d1 = results[i].distance_mm;
            let window = (
                d1 * (1.0 - GROWTH_REACH),
                (d1 * (1.0 + GROWTH_REACH)).min((d1 + p.background_distance_mm) / 2.0),
            );
            for (out, inversion) in self.left_out.iter().enumerate() {
                let mut measured = [Phasor::default(); MAX_FREQUENCIES];
                let mut background = [Phasor::default(); MAX_FREQUENCIES];
                let mut noise = [0.0; MAX_FREQUENCIES];
                for (j, kept) in (0..k).filter(|&j| j != out).enumerate() {
                    (measured[j], background[j], noise[j]) =
                        (p.measured[kept], p.background[kept], p.noise_sigma[kept]);
                }
                // The background enters as its phasors; its distance only bounds the search,
                // which the window bounds nearer (two frequencies' common range may be shorter
                // than the background's distance, not than the window's).
                let px = PixelPhasors {
                    measured: &measured[..k - 1],
                    background: &background[..k - 1],
                    background_distance_mm: p
                        .background_distance_mm
                        .min(window.1 + self.config.scan.min_separation_mm),
                    noise_sigma: &noise[..k - 1],
                };
                if let Ok(f) = inversion.layer_within(&px, window) {
                    per_left_out[out].push(f.translucency);
                }
            }
        }
        let medians: Vec<f64> = per_left_out.iter_mut().map(|v| median_select(v)).collect();
        if medians.iter().any(|m| !m.is_finite()) {
            return None;
        }
        let mean = medians.iter().sum::<f64>() / k as f64;
        let variance = (k - 1) as f64 / k as f64 * medians.iter().map(|m| (m - mean).powi(2)).sum::<f64>();
        let moved = medians.iter().map(|m| format!("{m:.4}")).collect::<Vec<_>>().join(", ");
        Some((variance.sqrt(), moved))
    }

    /// Adds ξ's share to each layer pixel's σ, in quadrature: the spread of the layer's
    /// distance over the region's ξ interval (whose lower end allows light between the layer
    /// and the background, shared by the region's pixels and not averaged down by the
    /// surface's window), as `|d(hi) - d(lo)| / (2 x 1.96)`, the median over up to
    /// [`SHARE_SAMPLES`] of the region's pixels. A faint layer's distance moves far with ξ.
    fn add_translucency_share(
        &self,
        frame: &PhasorFrame,
        members: &[Vec<usize>],
        regions: &[RegionOutput],
        grown: &[(usize, u32)],
        layer: &mut Layer,
    ) {
        for (r, px) in members.iter().enumerate() {
            let [lo, hi] = regions[r].xi.interval;
            if !(lo.is_finite() && hi.is_finite() && hi > lo) {
                continue;
            }
            let step = px.len().div_ceil(SHARE_SAMPLES).max(1);
            let mut spread: Vec<f64> = px
                .iter()
                .step_by(step)
                .filter_map(|&i| {
                    let p = self.pixel_inputs(frame, i)?;
                    let at = |xi: f64| self.inversion.fit_at_translucency(&p.phasors(), xi).ok();
                    let (a, b) = (at(lo)?, at(hi)?);
                    Some((a.foreground_distance_mm - b.foreground_distance_mm).abs() / (2.0 * 1.96))
                })
                .collect();
            let share = median_select(&mut spread);
            if !share.is_finite() {
                continue;
            }
            let region = r as u32 + 1;
            let grown_here = grown.iter().filter(|g| g.1 == region).map(|g| g.0);
            for i in px.iter().copied().chain(grown_here) {
                layer.sigma_mm[i] = layer.sigma_mm[i].hypot(share);
            }
        }
    }

    /// Adds the model's misfit to each layer pixel's σ, in quadrature: where a region's pixels
    /// misfit beyond the noise (their median `chi^2` `φ` times chi-square's median with
    /// `2K - 3` degrees of freedom), what the model leaves out (a layer that scatters what
    /// it passes, light between walls) moves each pixel's fit by about `sqrt(φ - 1)` times
    /// its noise, and neighbouring pixels share it, so the surface's window does not average
    /// it down (objects.md, "Intervals that hold": overdispersion from the object's own
    /// residuals). The share is that times the median of the region's pixels' own σ; the
    /// region's note says so.
    fn add_misfit_share(
        &self,
        members: &[Vec<usize>],
        results: &[PixelResult],
        grown: &[(usize, u32)],
        (regions, layer): (&mut [RegionOutput], &mut Layer),
    ) {
        let dof = (2 * self.config.frequencies_hz.len()).saturating_sub(3).max(1) as f64;
        for (r, px) in members.iter().enumerate() {
            let fitted = || px.iter().filter(|&&i| results[i].chi_square.is_finite());
            let mut chi: Vec<f64> = fitted().map(|&i| results[i].chi_square).collect();
            let phi = median_select(&mut chi) / chi_square_quantile(dof, 0.0);
            let mut noise: Vec<f64> = fitted().map(|&i| results[i].distance_sigma_mm).collect();
            let share = (phi - 1.0).max(0.0).sqrt() * median_select(&mut noise);
            if !(share.is_finite() && share > 0.0) {
                continue;
            }
            if let Some(output) = regions.get_mut(r) {
                output.xi.note.push_str(&format!(
                    "; its pixels misfit the two returns {phi:.1} times as much as the noise does (median chi^2), so each pixel's sigma takes {share:.1} mm more in quadrature"
                ));
            }
            let region = r as u32 + 1;
            let grown_here = grown.iter().filter(|g| g.1 == region).map(|g| g.0);
            for i in px.iter().copied().chain(grown_here) {
                layer.sigma_mm[i] = layer.sigma_mm[i].hypot(share);
            }
        }
    }

    /// A grown pixel's σ: the nearest pixel of its region's (within the widest window's
    /// radius), grown by the distance to it in `prior_radius_px`, in quadrature; NaN where none.
    fn grown_sigma(&self, i: usize, region: u32, labels: &ImageBuf<u32>, sigma_mm: &[f64]) -> f64 {
        let (w, h) = (labels.width as isize, labels.height as isize);
        let radius = self.config.prior_radius_px.max(1) as isize;
        let reach = radius << (PRIOR_WIDENINGS - 1);
        let (c, r) = ((i as isize) % w, (i as isize) / w);
        let mut best: Option<(isize, f64)> = None;
        for rr in (r - reach).max(0)..=(r + reach).min(h - 1) {
            for cc in (c - reach).max(0)..=(c + reach).min(w - 1) {
                let j = (rr * w + cc) as usize;
                let d2 = (rr - r).pow(2) + (cc - c).pow(2);
                if labels.data[j] == region && sigma_mm[j].is_finite() && best.is_none_or(|b| d2 < b.0) {
                    best = Some((d2, sigma_mm[j]));
                }
            }
        }
        best.map_or(f64::NAN, |(d2, s)| {
            s * (1.0 + d2 as f64 / (radius * radius) as f64).sqrt()
        })
    }

    /// The corrected depth (the layer's in the mask, the reading elsewhere),
    /// its σ and the ξ image.
    fn fill(&self, depth: &DepthFrame, mask: &ImageBuf<bool>, results: &[PixelResult], layer: &Layer) -> Filled {
        let (w, h) = (mask.width, mask.height);
        let mut f = Filled {
            corrected_z_mm: depth.z_mm.clone(),
            sigma_mm: ImageBuf::filled(w, h, f32::NAN),
            translucency: ImageBuf::filled(w, h, f32::NAN),
            pixels: 0,
            xi_median: f64::NAN,
        };
        let mut xis = vec![];
        let floor = self.systematic_mm();
        for i in (0..mask.len()).filter(|&i| mask.data[i]) {
            let (r, s) = (&results[i], self.scale.data[i]);
            f.corrected_z_mm.data[i] = (layer.distance_mm[i] / s) as f32;
            f.sigma_mm.data[i] = (layer.sigma_mm[i].hypot(floor) / s) as f32;
            f.translucency.data[i] = r.xi as f32;
            xis.push(r.xi);
        }
        f.pixels = xis.len();
        f.xi_median = median_select(&mut xis);
        f
    }
}

/// Where a layer region's layer is near a pixel ([`MultiFrequencyStage::local_layer`]).
#[derive(Debug, Clone, Copy)]
struct LocalLayer {
    /// The median distance of the region's own pixels there, mm.
    distance_mm: f64,
    /// The lower quartile of their returns, counts (NaN where none has one).
    weak_return: f64,
}

/// The covered shares of layer regions' own outline pixels: pooled along the outline
/// ([`MultiFrequencyStage::covered_edges`]), else the pixel's own.
struct OutlineShares<'a> {
    regions: &'a [RegionOutput],
    /// `(pixel, share)` sorted by pixel.
    pooled: &'a [(usize, Coverage)],
}

impl OutlineShares<'_> {
    /// Pixel `i`'s share of region `label`: the pooled one, else from its own `ξ_p^2`, the
    /// background's share left there.
    fn of(&self, i: usize, p: &PixelResult, label: u32) -> Option<Coverage> {
        if let Ok(k) = self.pooled.binary_search_by_key(&i, |&(j, _)| j) {
            return Some(self.pooled[k].1);
        }
        let region = self.regions.get(label as usize - 1)?;
        p.own_share(region.xi.xi)
    }
}

/// A pixel of a layer region's outline ([`MultiFrequencyStage::outline_band`]).
struct BandPixel {
    pixel: usize,
    region: u32,
    at: OutlinePixel,
    /// The gap from the layer to the background, mm, for a pixel beside the region; `None`
    /// for the region's own.
    gap_mm: Option<f64>,
}

/// A pixel on a layer region's outline that the layer covers by half or more
/// ([`MultiFrequencyStage::covered_edges`]).
#[derive(Debug, Clone, Copy)]
struct CoveredEdge {
    pixel: usize,
    region: u32,
    /// The least σ its depth may have, mm (half the gap to the background where the layer
    /// may cover less than half of it).
    sigma_floor_mm: f64,
}

/// What [`MultiFrequencyStage::grow_layers`] finds.
#[derive(Debug, Default)]
struct Growth {
    /// `(pixel, layer region)` taken into the region.
    pixels: Vec<(usize, u32)>,
    /// Layer regions to join, `(a, b)` with `a < b`.
    joined: Vec<(u32, u32)>,
}

/// Whether layer pixel `i` touches an opaque region (one of the 8 neighbours labelled past
/// `layers`), and whether its fitted distance is that neighbour's (within 3 σ of the two, or
/// 2 % of the distance).
fn beside_opaque(i: usize, labels: &ImageBuf<u32>, layers: u32, results: &[PixelResult]) -> (bool, bool) {
    let (p, d) = (&results[i], results[i].distance_mm);
    let (mut touching, mut beside) = (false, false);
    for n in neighbours_8(i, labels.width, labels.height).filter(|&n| labels.data[n] > layers) {
        let q = &results[n];
        let tol = (3.0 * p.distance_sigma_mm.hypot(q.distance_sigma_mm)).max(0.02 * d);
        touching = true;
        beside |= (d - q.distance_mm).abs() <= tol;
    }
    (touching, beside)
}

/// `labels` with `pixels` taken off their regions, and the layer regions left empty dropped.
fn without_pixels(labels: &ImageBuf<u32>, layers: u32, pixels: &[usize]) -> (ImageBuf<u32>, u32) {
    let mut out = labels.clone();
    for &i in pixels {
        out.data[i] = 0;
    }
    let mut left = vec![false; layers as usize + 1];
    for &l in &out.data {
        if l >= 1 && l <= layers {
            left[l as usize] = true;
        }
    }
    let empty: Vec<u32> = (1..=layers).filter(|&l| !left[l as usize]).collect();
    if empty.is_empty() {
        (out, layers)
    } else {
        drop_layer_regions(&out, layers, &empty)
    }
}

/// `labels` without the layer regions `dropped` (their pixels 0), the others numbered again
/// from 1 in order, the opaque regions after them; and the new layer count.
fn drop_layer_regions(labels: &ImageBuf<u32>, layers: u32, dropped: &[u32]) -> (ImageBuf<u32>, u32) {
    let mut new_id = vec![0u32; layers as usize + 1];
    let mut next = 0;
    for l in 1..=layers {
        if !dropped.contains(&l) {
            next += 1;
            new_id[l as usize] = next;
        }
    }
    (renumbered(labels, layers, &new_id, next), next)
}

/// `labels` with each layer label `l` made `new_ids[l]` (0 for a region dropped) and the
/// opaque regions after the `new_layers` layer regions.
fn renumbered(labels: &ImageBuf<u32>, layers: u32, new_ids: &[u32], new_layers: u32) -> ImageBuf<u32> {
    let data = labels
        .data
        .iter()
        .map(|&l| match l {
            0 => 0,
            l if l <= layers => new_ids[l as usize],
            o => o - layers + new_layers,
        })
        .collect();
    ImageBuf {
        width: labels.width,
        height: labels.height,
        data,
    }
}

/// `labels` with the layer regions of `joined` made one (each the smallest label of its
/// group, then numbered again from 1 in order, the opaque regions after them): the new
/// labels, each old layer label's new one (`new_ids[l]`, 0 for 0) and the new layer count.
fn merge_labels(labels: &ImageBuf<u32>, layers: u32, joined: &[(u32, u32)]) -> (ImageBuf<u32>, Vec<u32>, u32) {
    let mut parent: Vec<u32> = (0..=layers).collect();
    fn root(parent: &mut [u32], mut a: u32) -> u32 {
        while parent[a as usize] != a {
            parent[a as usize] = parent[parent[a as usize] as usize];
            a = parent[a as usize];
        }
        a
    }
    for &(a, b) in joined {
        let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
        parent[ra.max(rb) as usize] = ra.min(rb);
    }
    let mut new_ids = vec![0u32; layers as usize + 1];
    let mut next = 0;
    for l in 1..=layers {
        let r = root(&mut parent, l);
        if r == l {
            next += 1;
            new_ids[l as usize] = next;
        } else {
            new_ids[l as usize] = new_ids[r as usize];
        }
    }
    (renumbered(labels, layers, &new_ids, next), new_ids, next)
}

/// The pixels of a region [`MultiFrequencyStage::add_translucency_share`] samples.
const SHARE_SAMPLES: usize = 64;

/// A region's windows stop widening once the median of its pixels' standard errors is at
/// most this, mm: below a millimetre a wider window buys nothing that a depth image in
/// millimetres shows.
const PRIOR_FINE_ENOUGH_MM: f64 = 1.0;

/// The smooth-surface prior tries windows of `prior_radius_px` doubled up to this many
/// times less one (4, 8, 16, 32 pixels), and each pixel takes the one whose surface has the
/// least standard error there (until the region's are fine enough, [`PRIOR_FINE_ENOUGH_MM`]): a faint layer (ξ near 1, far away), whose roots scatter by
/// hundreds of millimetres, needs wide windows; a curved one, whose scatter about a wide
/// window's surface grows, keeps a narrow one.
const PRIOR_WIDENINGS: u32 = 4;

/// The 8 neighbours of a pixel, `(column, row)` steps.
const NEIGHBOURS_8: [(isize, isize); 8] = [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)];

/// The largest amplitude among a pixel's phasors (one return's strength, for the sinusoid).
fn peak_amplitude(phasors: &[Phasor]) -> f64 {
    phasors.iter().map(|p| p.a.hypot(p.b)).fold(0.0, f64::max)
}

/// Whether a pixel of no region may still be a layer region's (a hole in it, or on its
/// outline): unchanged, unclaimed, failed, or a layer's in a piece too small; not opaque,
/// not unusable.
fn unclaimed_by_a_region(class: PixelClass) -> bool {
    matches!(
        class,
        PixelClass::Background | PixelClass::Unclaimed | PixelClass::Failed | PixelClass::Layer
    )
}

/// The share of a layer region's weak returns near a pixel (their lower quartile) that a
/// pixel grown into it must reach, less three of its own return's standard deviations.
const GROWTH_RETURN_SHARE: f64 = 0.5;

/// Whether a return `a` fitted at a region's ξ is too weak to be the region's layer: under
/// [`GROWTH_RETURN_SHARE`] of `weak_return` (the region's own pixels' returns near it) beyond
/// three of its standard deviations. One material at one distance returns alike, so a pixel
/// of a bright layer returns brightly; a background that something else dimmed (an object's
/// shadow in the light between a table and a wall) fits the region's ξ² only with a return
/// of its own far under the layer's. A faint layer's returns are under the noise, and so is
/// the bound.
fn too_weak(a: f64, weak_return: f64, inputs: &PixelInputs) -> bool {
    let information: f64 = inputs.noise_sigma[..inputs.frequencies]
        .iter()
        .map(|s| s.powi(-2))
        .sum();
    let sigma = information.recip().sqrt();
    a < GROWTH_RETURN_SHARE * weak_return - 3.0 * sigma
}

/// How far beyond the background [`MultiFrequencyStage::indirect_explains`] looks for the
/// light an object blocks or adds (half the extra path of a bounce off a table or a wall
/// beside the surface a pixel sees), mm.
const INDIRECT_REACH_MM: f64 = 3000.0;

/// Farthest from the background's distance, beyond three of its own standard deviations,
/// that one return still counts as the background's ([`PixelClass::Unclaimed`]), mm.
const DIMMED_TOLERANCE_MM: f64 = 30.0;

/// Whether a changed pixel's fit claims nothing ([`PixelClass::Unclaimed`]): a layer preferred
/// to one return (at 95 %) but not beyond `level`; a layer at the background's own distance
/// (within three of its standard deviations, or [`DIMMED_TOLERANCE_MM`]); or one return there
/// and weaker than the background's. A layer whose own return is under the noise shows the
/// last, its ξ² that return over the background's; so does a shadow. Light between two
/// surfaces (a table and a wall) changes where an object elsewhere blocks or adds to it: the
/// background dims and turns a little, which fits a layer of weak return at the background.
/// A layer or an opaque surface there cannot be told from the background itself.
fn unclaimed(est: &MultiFrequencyEstimate, inputs: &PixelInputs, level: f64) -> bool {
    let tolerance = (3.0 * est.foreground_distance_sigma_mm).max(DIMMED_TOLERANCE_MM);
    let at_background = (est.foreground_distance_mm - inputs.background_distance_mm).abs() <= tolerance;
    if !est.opaque {
        return est.opacity_statistic <= level || at_background;
    }
    at_background && est.first_return < peak_amplitude(inputs.background)
}

/// Each pixel's layer distance along its ray and its σ, mm (what [`MultiFrequencyStage::fill`]
/// publishes in the mask).
struct Layer {
    distance_mm: Vec<f64>,
    sigma_mm: Vec<f64>,
}

/// What [`MultiFrequencyStage::fill`] makes.
struct Filled {
    corrected_z_mm: ImageBuf<f32>,
    sigma_mm: ImageBuf<f32>,
    translucency: ImageBuf<f32>,
    pixels: usize,
    xi_median: f64,
}

/// The layer pixels that misfit their region: `chi^2` over the quantile of chi-square with
/// `2K - 3` degrees of freedom `sigmas` standard deviations out, scaled by how far the
/// region's median `chi^2` exceeds chi-square's median (at least 1). A model misfit that
/// every pixel of a region shares (a diffuse transmitter, light between walls) scales its
/// level with it; a surface of another kind among its pixels (an opaque box beside a sheet,
/// whose light on it fits a layer better than one return, and neither well) stands out.
fn region_misfits(
    labels: &ImageBuf<u32>,
    layers: u32,
    results: &[PixelResult],
    (dof, sigmas): (f64, f64),
) -> Vec<usize> {
    let mut misfits = vec![];
    for pixels in label_members(labels, layers, |i| results[i].chi_square.is_finite()) {
        if pixels.is_empty() {
            continue;
        }
        let mut chi: Vec<f64> = pixels.iter().map(|&i| results[i].chi_square).collect();
        let scale = (median_select(&mut chi) / chi_square_quantile(dof, 0.0)).max(1.0);
        let level = scale * chi_square_quantile(dof, sigmas);
        misfits.extend(pixels.iter().copied().filter(|&i| results[i].chi_square > level));
    }
    misfits.sort_unstable();
    misfits
}

/// The 8-neighbours of pixel `i` inside a `w` x `h` image.
fn neighbours_8(i: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (c, r) = ((i % w) as isize, (i / w) as isize);
    NEIGHBOURS_8.iter().filter_map(move |(dc, dr)| {
        let (cc, rr) = (c + dc, r + dr);
        (cc >= 0 && rr >= 0 && cc < w as isize && rr < h as isize).then(|| rr as usize * w + cc as usize)
    })
}

/// The pixels of each of the labels `1..=count`, those `keep` takes, in image order.
fn label_members(labels: &ImageBuf<u32>, count: u32, keep: impl Fn(usize) -> bool) -> Vec<Vec<usize>> {
    let mut members: Vec<Vec<usize>> = vec![vec![]; count as usize];
    for (i, &l) in labels.data.iter().enumerate() {
        if l > 0 && l <= count && keep(i) {
            members[l as usize - 1].push(i);
        }
    }
    members
}

/// Every region's estimate, in the order of their labels (`layers` layer regions first).
fn regions(labels: &ImageBuf<u32>, layers: u32, results: &[PixelResult], pixel_sr: f64) -> Vec<RegionOutput> {
    let count = labels.data.iter().copied().max().unwrap_or(0);
    label_members(labels, count, |_| true)
        .iter()
        .enumerate()
        .map(|(r, px)| {
            let id = r as u32 + 1;
            if id <= layers {
                layer_region(id, px, (labels.width, pixel_sr), results)
            } else {
                opaque_region(id, px, results)
            }
        })
        .collect()
}

/// A region's estimate on this path.
fn region_estimate(xi: f64, interval: [f64; 2], pixels: usize, note: String) -> XiEstimate {
    XiEstimate {
        xi,
        interval,
        method: XiMethod::MultiFrequency,
        frames: 1,
        pixels,
        profile: vec![],
        note,
    }
}

/// A layer region: the median of its pixels' ξ, and an interval (about 95 %)
/// of `1.96` standard errors of a median (`1.2533 s / sqrt(n)`), `s` the
/// larger of the pixels' robust spread and their stated σ (overdispersion
/// widens it, never narrows it), or, where wider, Student's t times the
/// scatter of the medians of the region's square blocks of [`BLOCK_PX`]
/// pixels over the square root of their number: what the model leaves out
/// (light between the layer and a near wall, a mixed edge) is shared by
/// neighbouring pixels and does not average out over them.
fn layer_region(id: u32, pixels: &[usize], (width, pixel_sr): (usize, f64), results: &[PixelResult]) -> RegionOutput {
    if pixels.iter().all(|&i| results[i].xi.is_nan()) {
        let note = format!(
            "{} pixels, each two returns; no background latched, so xi (the far return against the background's own) is not measured",
            pixels.len()
        );
        return RegionOutput {
            id,
            xi: region_estimate(f64::NAN, [0.0, 1.0], pixels.len(), note),
            pixels: pixels.len(),
            opaque: false,
            class: None,
        };
    }
    let mut xi: Vec<f64> = pixels.iter().map(|&i| results[i].xi).collect();
    let mut stated: Vec<f64> = pixels.iter().map(|&i| results[i].xi_sigma).collect();
    let median = median_select(&mut xi);
    let spread = sigma_about(&xi, median);
    let stated = median_select(&mut stated);
    let s = spread.max(stated);
    let pixel_half = 1.96 * 1.2533 * s / (pixels.len() as f64).sqrt();
    let blocks = block_medians(pixels, width, results);
    let block_half = if blocks.len() >= 3 {
        let m = blocks.iter().sum::<f64>() / blocks.len() as f64;
        let sd = (blocks.iter().map(|b| (b - m).powi(2)).sum::<f64>() / (blocks.len() - 1) as f64).sqrt();
        student_t975(blocks.len() - 1) * sd / (blocks.len() as f64).sqrt()
    } else {
        0.0
    };
    let half = pixel_half.max(block_half);
    // Light between the layer's back and the background (not in the model) only adds to the
    // far return: ξ² comes out up to a factor 1 + gain too high.
    let gain = interreflection_bound(pixels, results, pixel_sr);
    let lower = (median - half) / (1.0 + gain.max(0.0)).sqrt();
    let interval = [lower.max(0.0), (median + half).min(1.0)];
    let note = format!(
        "median of {} pixels' xi, each from its own phasors; spread {spread:.4}, stated sigma {stated:.4} per pixel; {} blocks, half width {block_half:.4} from their scatter; the lower end allows light between the layer and the background to raise xi^2 by up to {:.1} %",
        pixels.len(),
        blocks.len(),
        100.0 * gain.max(0.0)
    );
    RegionOutput {
        id,
        xi: region_estimate(median, interval, pixels.len(), note),
        pixels: pixels.len(),
        opaque: false,
        class: None,
    }
}

/// An upper bound on the share that light between a layer's back and the background adds
/// to the far return (Eq. 3's first inter-reflection, weighted by the background's view of
/// the layer): `(1 - ξ) X Xb F <= (1 - ξ) X / Xb · F` (`Xb <= 1`), with `F` the view factor
/// of the region, taken as a square of its area at its median distance, from the background
/// point behind its centre at the median gap (physics.md §5, "What a sheet lets through").
/// NaN where the region's pixels do not say.
fn interreflection_bound(pixels: &[usize], results: &[PixelResult], pixel_sr: f64) -> f64 {
    let median_of = |f: &dyn Fn(&PixelResult) -> f64| {
        let mut v: Vec<f64> = pixels
            .iter()
            .map(|&i| f(&results[i]))
            .filter(|v| v.is_finite())
            .collect();
        median_select(&mut v)
    };
    let ratio = median_of(&|r| r.layer_to_background);
    let gap = median_of(&|r| r.gap_mm);
    let distance = median_of(&|r| r.distance_mm);
    let half_side = 0.5 * distance * (pixels.len() as f64 * pixel_sr).sqrt();
    ratio * 4.0 * corner_view_factor(half_side, half_side, gap)
}

/// The view factor from a point to an `a` x `b` rectangle parallel to it at distance `c`,
/// the point on the normal through one of its corners.
fn corner_view_factor(a: f64, b: f64, c: f64) -> f64 {
    let (x, y) = (a / c, b / c);
    let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
    (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / std::f64::consts::TAU
}

/// The layer's own return against the background's at equal distance, `(1 - ξ) X / Xb`:
/// the returns' strengths scaled by the square of their distances.
fn layer_to_background(est: &MultiFrequencyEstimate, inputs: &PixelInputs) -> f64 {
    let background = peak_amplitude(inputs.background);
    let (d1, db) = (est.foreground_distance_mm, inputs.background_distance_mm);
    if est.opaque || !(background > 0.0 && d1 > 0.0 && db > 0.0) {
        return f64::NAN;
    }
    est.first_return / background * (d1 / db).powi(2)
}

/// Side of the square blocks whose medians measure a region's shared error, pixels.
const BLOCK_PX: usize = 8;

/// The median ξ of each [`BLOCK_PX`]-square block holding at least a quarter of its pixels.
fn block_medians(pixels: &[usize], width: usize, results: &[PixelResult]) -> Vec<f64> {
    let width = width.max(1);
    let mut by_block: std::collections::BTreeMap<(usize, usize), Vec<f64>> = Default::default();
    for &i in pixels {
        by_block
            .entry(((i / width) / BLOCK_PX, (i % width) / BLOCK_PX))
            .or_default()
            .push(results[i].xi);
    }
    by_block
        .into_values()
        .filter(|v| v.len() * 4 >= BLOCK_PX * BLOCK_PX)
        .map(|mut v| median_select(&mut v))
        .collect()
}

/// A changed region one return explains at every pixel: ξ 0, bounded above by
/// the ξ whose ξ² is `1.96` standard errors (of a mean over its pixels) above 0.
fn opaque_region(id: u32, pixels: &[usize], results: &[PixelResult]) -> RegionOutput {
    let mut s: Vec<f64> = pixels.iter().map(|&i| results[i].xi_squared_sigma).collect();
    let s = median_select(&mut s);
    let upper = (1.96 * s / (pixels.len() as f64).sqrt()).sqrt().min(1.0);
    let note = format!(
        "one return explains each of its {} pixels: opaque, readings kept",
        pixels.len()
    );
    RegionOutput {
        id,
        xi: region_estimate(
            0.0,
            [0.0, if upper.is_finite() { upper } else { 1.0 }],
            pixels.len(),
            note,
        ),
        pixels: pixels.len(),
        opaque: true,
        class: None,
    }
}

/// The frame's estimate: its largest layer region's, else its largest region's.
fn frame_estimate(regions: &[RegionOutput], layers: usize) -> XiEstimate {
    let largest = |r: &[RegionOutput]| r.iter().max_by_key(|r| r.pixels).map(|r| r.xi.clone());
    largest(&regions[..layers])
        .or_else(|| largest(regions))
        .unwrap_or_else(|| region_estimate(f64::NAN, [0.0, 1.0], 0, "nothing changed from the background".into()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::Sensor;
    use crate::sim::render::{render_all, scene_intrinsics};
    use crate::sim::Scene;

    const SCENE: &str = r#"
seed = 3
[camera]
width = 48
height = 40
modulation_frequencies_hz = [20e6, 50e6, 100e6]
[physics]
transmission_albedo_power = 0.0
ir_mode = "amplitude"
[background]
distance_mm = 2000
frames = 6
[[stage]]
frames = 1
[[stage.objects]]
shape = "plane"
center_mm = [120, 0, 900]
size_mm = [300, 400]
tilt_y_deg = 25
xi = 0.75
albedo = 0.6
[[stage.objects]]
shape = "plane"
center_mm = [-250, 0, 1300]
size_mm = [200, 300]
xi = 0.0
albedo = 0.7
"#;

    fn frames(scene: &Scene) -> Vec<(PhasorFrame, DepthFrame, ImageBuf<f32>)> {
        render_all(scene)
            .into_iter()
            .map(|f| {
                let p = PhasorFrame {
                    stamp_ns: f.stamp_ns,
                    phasors: f.phasors,
                };
                let d = DepthFrame {
                    stamp_ns: f.stamp_ns,
                    z_mm: f.depth_z_mm,
                    ir: f.ir,
                };
                (p, d, f.truth_z_mm)
            })
            .collect()
    }

    fn stage(scene: &Scene) -> MultiFrequencyStage {
        let model = ForwardModel::physical(Sensor::sr4000());
        let config = MultiFrequencyConfig::new(scene.camera.modulation_frequencies_hz.clone(), model);
        MultiFrequencyStage::new(config, scene_intrinsics(scene)).expect("stage")
    }

    /// The scene of `toml` rendered, and the stage with its background latched.
    fn latched_on(toml: &str) -> (MultiFrequencyStage, Vec<(PhasorFrame, DepthFrame, ImageBuf<f32>)>) {
        let scene = Scene::from_toml(toml, "t.toml").expect("scene");
        let all = frames(&scene);
        (latched_stage(&scene, &all), all)
    }

    /// The stage with the background latched from the scene's first six frames.
    fn latched_stage(scene: &Scene, all: &[(PhasorFrame, DepthFrame, ImageBuf<f32>)]) -> MultiFrequencyStage {
        let mut s = stage(scene);
        let latch: Vec<_> = all[..6].iter().map(|(p, d, _)| (p, d)).collect();
        s.latch(&latch, Sensor::sr4000().unambiguous_range_mm()).expect("latch");
        s
    }

    /// What a frame of the test scene shows: the sheet's pixels (truth nearer than 1150 mm),
    /// those in the mask, their RMS error and ξ; the box's pixels and those in the mask (every
    /// other box pixel keeps its reading); whether the background stayed out of the mask.
    #[derive(Debug)]
    struct SheetAndBox {
        sheet: usize,
        in_mask: usize,
        rms_mm: f64,
        sheet_xi: Vec<f32>,
        box_px: usize,
        box_masked: usize,
        elsewhere_clean: bool,
    }

    impl SheetAndBox {
        fn of(out: &MultiFrequencyOutput, depth: &DepthFrame, truth: &ImageBuf<f32>) -> Self {
            let o = &out.frame;
            let mut c = SheetAndBox {
                sheet: 0,
                in_mask: 0,
                rms_mm: 0.0,
                sheet_xi: vec![],
                box_px: 0,
                box_masked: 0,
                elsewhere_clean: true,
            };
            let mut err2 = 0.0;
            for (i, &t) in truth.data.iter().enumerate() {
                if t < 1150.0 {
                    c.sheet += 1;
                    if o.mask.data[i] {
                        c.in_mask += 1;
                        err2 += f64::from(o.corrected_z_mm.data[i] - t).powi(2);
                        c.sheet_xi.push(out.translucency.data[i]);
                    }
                } else if t.is_finite() {
                    c.box_px += 1;
                    c.box_masked += usize::from(o.mask.data[i]);
                    assert!(o.corrected_z_mm.data[i] == depth.z_mm.data[i] || o.mask.data[i]);
                } else {
                    c.elsewhere_clean &= !o.mask.data[i] && out.translucency.data[i].is_nan();
                }
            }
            c.rms_mm = (err2 / c.in_mask.max(1) as f64).sqrt();
            c
        }
    }

    #[test]
    fn view_factors_of_a_rectangle() {
        // An infinite plane: a quarter from each corner's rectangle.
        assert!((corner_view_factor(1e9, 1e9, 1.0) - 0.25).abs() < 1e-6);
        // The paper's 24 x 31 cm sheet 250 mm before the wall, seen from behind its centre:
        // about 0.27 (physics.md §5).
        let f = 4.0 * corner_view_factor(120.0, 155.0, 250.0);
        assert!((f - 0.27).abs() < 0.005, "{f}");
        // Far away, the solid angle over pi: a / c * b / c / pi per corner.
        let far = corner_view_factor(1.0, 1.0, 1000.0);
        assert!((far - 1e-6 / std::f64::consts::PI).abs() < 1e-9, "{far}");
    }

    #[test]
    fn layer_regions_joined_are_one_and_the_opaque_ones_follow() {
        let labels = ImageBuf {
            width: 6,
            height: 1,
            data: vec![0, 1, 2, 3, 4, 5],
        };
        // Layers 1-4; 5 opaque. 1 and 3 joined, then 3 and 4: layers {1, 3, 4} and {2}.
        let (merged, ids, layers) = merge_labels(&labels, 4, &[(1, 3), (3, 4)]);
        assert_eq!(layers, 2);
        assert_eq!(ids, vec![0, 1, 2, 1, 1]);
        assert_eq!(merged.data, vec![0, 1, 2, 1, 1, 3]);
        let (same, _, layers) = merge_labels(&labels, 4, &[]);
        assert_eq!((same.data, layers), (labels.data.clone(), 4));
    }

    /// A faint layer as the rendered `mf_two_materials`' ξ 0.93 sheet's far pose (albedo 0.44,
    /// tilted 25 degrees, 2.3 m away and 0.85 m before the wall: its own return about a tenth of
    /// the background's), whose pixels one at a time often do not show a layer beyond the level
    /// (a third of them here): they join the layer the others show, at its ξ. At least 99 % of
    /// its pixels in the mask (a pixel whose phasors the layer's ξ does not fit at 99.9 % keeps
    /// its reading), recovered better than read.
    #[test]
    fn a_faint_layer_is_recovered_whole() {
        let (s, all) = latched_on(
            &SCENE
                .replace("distance_mm = 2000", "distance_mm = 3160")
                .replace("center_mm = [120, 0, 900]", "center_mm = [0, 0, 2320]")
                .replace("albedo = 0.6", "albedo = 0.44")
                .replace("size_mm = [300, 400]", "size_mm = [700, 800]")
                .replace("xi = 0.75", "xi = 0.935")
                .replace("center_mm = [-250, 0, 1300]", "center_mm = [-2500, 0, 1300]"),
        );
        let (p, d, truth) = &all[6];
        let out = s.process(p, d).expect("frame");
        let (mut sheet, mut in_mask, mut err2, mut raw2) = (0, 0, 0.0, 0.0);
        for (i, &t) in truth.data.iter().enumerate() {
            if t.is_finite() && t < 3000.0 {
                sheet += 1;
                if out.frame.mask.data[i] {
                    in_mask += 1;
                    err2 += f64::from(out.frame.corrected_z_mm.data[i] - t).powi(2);
                    raw2 += f64::from(d.z_mm.data[i] - t).powi(2);
                }
            }
        }
        let (rms, raw) = (
            (err2 / in_mask.max(1) as f64).sqrt(),
            (raw2 / in_mask.max(1) as f64).sqrt(),
        );
        println!("faint layer: {in_mask} of {sheet} sheet pixels in the mask, RMS {rms:.1} mm there (read {raw:.1})");
        assert!(sheet > 100, "{sheet} sheet pixels");
        assert!(
            in_mask as f64 >= 0.99 * sheet as f64,
            "{in_mask} of {sheet} in the mask"
        );
        assert!(rms < raw, "RMS {rms:.1} mm against {raw:.1} read");
    }

    #[test]
    fn the_change_level_is_chi_squares_quantile() {
        // Tables: chi-square 0.999 quantiles 13.82 (2 dof), 22.46 (6), 26.12 (8).
        for (dof, q) in [(2.0, 13.82), (6.0, 22.46), (8.0, 26.12)] {
            let got = chi_square_quantile(dof, 3.09);
            assert!((got - q).abs() < 0.03 * q, "{dof}: {got}");
        }
    }

    #[test]
    fn a_layer_is_recovered_and_an_opaque_box_kept() {
        let (s, all) = latched_on(SCENE);
        let (p, d, truth) = &all[6];
        let out = s.process(p, d).expect("frame");
        let o = &out.frame;
        // Sheet pixels (truth nearer than 1150 mm) in the mask with xi and depth; box pixels not.
        let c = SheetAndBox::of(&out, d, truth);
        assert!(c.sheet_xi.iter().all(|x| (x - 0.75).abs() < 0.05), "{:?}", c.sheet_xi);
        assert!(c.elsewhere_clean);
        assert!(c.in_mask * 100 >= c.sheet * 95 && c.rms_mm < 15.0, "{c:?}");
        assert!(c.box_px > 50 && c.box_masked * 20 <= c.box_px, "{c:?}");
        assert!(o.regions.iter().any(|r| r.opaque) && o.regions.iter().any(|r| !r.opaque));
        assert_eq!(o.xi.method, XiMethod::MultiFrequency);
    }

    /// Beside a bright layer (ξ 0.75, albedo 0.6), the background dimmed by ξ² with no return
    /// of its own, as when an object blocks the light that reached a wall from a table: the
    /// region's ξ fits those pixels with a return near zero, where the layer's own pixels
    /// return brightly. They are not grown into the layer and keep their readings; the layer is
    /// recovered as without them.
    /// Of `pixels`, how many are in the mask and how many are published otherwise than read.
    fn masked_and_moved(out: &MultiFrequencyOutput, depth: &DepthFrame, pixels: &[usize]) -> (usize, usize) {
        let masked = pixels.iter().filter(|&&i| out.frame.mask.data[i]).count();
        let moved = pixels
            .iter()
            .filter(|&&i| out.frame.corrected_z_mm.data[i] != depth.z_mm.data[i])
            .count();
        (masked, moved)
    }

    #[test]
    fn a_background_dimmed_beside_a_bright_layer_is_not_grown_into_it() {
        let (s, all) = latched_on(SCENE);
        let (p, d, truth) = &all[6];
        let w = truth.width;
        // The six pixels to the right of the sheet's last column, in each of its rows, dimmed;
        // the first of them, on the sheet's outline, mixes its return and is not counted.
        let (mut dimmed, mut outline) = (vec![], vec![]);
        for row in 0..truth.height {
            let sheet_cols = (0..w).filter(|&c| truth.data[row * w + c] < 1150.0);
            if let Some(last) = sheet_cols.max() {
                outline.push(row * w + last + 1);
                dimmed.extend((last + 2..(last + 7).min(w)).map(|c| row * w + c));
            }
        }
        let mut p = p.clone();
        for img in &mut p.phasors {
            for &i in dimmed.iter().chain(&outline) {
                img.data[i] = img.data[i].map(|v| v * 0.5625);
            }
        }
        let out = s.process(&p, d).expect("frame");
        let (grown, moved) = masked_and_moved(&out, d, &dimmed);
        let c = SheetAndBox::of(&out, d, truth);
        println!(
            "dimmed {} pixels: {grown} in the mask, {moved} moved; sheet {} of {} in the mask, RMS {:.1} mm",
            dimmed.len(),
            c.in_mask,
            c.sheet,
            c.rms_mm
        );
        assert!(dimmed.len() > 60, "{} dimmed pixels", dimmed.len());
        assert_eq!((grown, moved), (0, 0));
        assert!(c.in_mask * 100 >= c.sheet * 95 && c.rms_mm < 15.0, "{c:?}");
    }

    /// An object that shades the light a wall gets by way of something beside it (a table)
    /// takes a return from beyond the wall out of the pixels near it: `M = B - c u(d2)`,
    /// `d2` past the background. A layer before the wall fits that change (without
    /// [`MultiFrequencyStage::indirect_explains`] every such pixel was a layer, published
    /// hundreds of mm before the wall); the background with a return behind it changed fits
    /// it as well, so none of them is claimed, and the sheet is still recovered.
    #[test]
    fn light_blocked_from_behind_the_wall_is_no_layer() {
        let (s, all) = latched_on(SCENE);
        let (p, d, truth) = &all[6];
        let w = truth.width;
        let db = s.background().expect("latched").distance_mm.clone();
        let shaded: Vec<usize> = (2..12)
            .flat_map(|row| (36..46).map(move |col| row * w + col))
            .filter(|&i| !(truth.data[i] < 1900.0))
            .collect();
        let mut p = p.clone();
        for (img, f) in p.phasors.iter_mut().zip(&s.config.frequencies_hz) {
            let sensor = Sensor::new(*f, crate::physics::Waveform::Sinusoid);
            for &i in &shaded {
                let [a, b] = img.data[i].map(f64::from);
                let blocked = sensor.buckets(0.2 * a.hypot(b), db.data[i] + 1300.0);
                img.data[i] = [(a - blocked.a) as f32, (b - blocked.b) as f32];
            }
        }
        let out = s.process(&p, d).expect("frame");
        let (claimed, moved) = masked_and_moved(&out, d, &shaded);
        let c = SheetAndBox::of(&out, d, truth);
        println!(
            "shaded {} pixels: {claimed} in the mask, {moved} moved; sheet {} of {} in the mask, RMS {:.1} mm",
            shaded.len(),
            c.in_mask,
            c.sheet,
            c.rms_mm
        );
        assert!(shaded.len() >= 50, "{} shaded pixels", shaded.len());
        assert_eq!((claimed, moved), (0, 0));
        assert!(c.in_mask * 100 >= c.sheet * 95 && c.rms_mm < 15.0, "{c:?}");
    }

    /// A region of 400 layer pixels whose `chi^2` follow chi-square with 3 degrees of
    /// freedom, scaled by 1 or by 6 (a misfit every pixel shares), with 20 pixels of an
    /// opaque box among them fitting 15 times worse than the region's median: the box's are
    /// the misfits in both, and of the others no more than chance at the level flags.
    #[test]
    fn pixels_that_misfit_their_region_are_told_from_a_misfit_the_region_shares() {
        use rand::{Rng, SeedableRng};
        use rand_chacha::ChaCha8Rng;
        use rand_distr::StandardNormal;
        let mut rng = ChaCha8Rng::seed_from_u64(38);
        let (w, h) = (21, 20);
        let labels = ImageBuf {
            width: w,
            height: h,
            data: vec![1u32; w * h],
        };
        let level = (3.0, 3.09);
        for scale in [1.0, 6.0] {
            let mut results: Vec<PixelResult> = (0..w * h)
                .map(|_| {
                    let chi: f64 = (0..3).map(|_| rng.sample::<f64, _>(StandardNormal).powi(2)).sum();
                    PixelResult {
                        chi_square: scale * chi,
                        ..PixelResult::only(PixelClass::Layer)
                    }
                })
                .collect();
            let boxed: Vec<usize> = (0..20).map(|k| 5 * w + k).collect();
            for &i in &boxed {
                results[i].chi_square = 15.0 * scale * 2.37;
            }
            let misfits = region_misfits(&labels, 1, &results, level);
            let others = misfits.iter().filter(|i| !boxed.contains(i)).count();
            println!(
                "scale {scale}: {} misfits, {others} of them not the box's",
                misfits.len()
            );
            assert!(boxed.iter().all(|i| misfits.contains(i)), "scale {scale}: {misfits:?}");
            assert!(
                others <= 3,
                "scale {scale}: {others} of the region's own pixels flagged"
            );
        }
    }

    /// Two sheets side by side at one distance, ξ 0.5 and 0.8: one region by their
    /// distances, two by their pixels' ξ. Each comes out a region of its own whose interval
    /// holds its ξ; pooled they give one ξ between the two.
    #[test]
    fn two_materials_side_by_side_are_two_regions() {
        let (s, all) = latched_on(
            &SCENE
                .replace("center_mm = [120, 0, 900]", "center_mm = [150, 0, 1000]")
                .replace("tilt_y_deg = 25\n", "")
                .replace("xi = 0.75", "xi = 0.8")
                .replace("center_mm = [-250, 0, 1300]", "center_mm = [-150, 0, 1000]")
                .replace("size_mm = [200, 300]", "size_mm = [300, 400]")
                .replace("xi = 0.0", "xi = 0.5"),
        );
        let (p, d, _) = &all[6];
        let out = s.process(p, d).expect("frame");
        let layers: Vec<&RegionOutput> = out
            .frame
            .regions
            .iter()
            .filter(|r| !r.opaque && r.pixels > 100)
            .collect();
        for r in &layers {
            println!(
                "region {}: {} pixels, xi {:.3} {:?}",
                r.id, r.pixels, r.xi.xi, r.xi.interval
            );
        }
        let holds = |xi: f64| layers.iter().any(|r| r.xi.interval[0] <= xi && xi <= r.xi.interval[1]);
        assert_eq!(layers.len(), 2);
        assert!(holds(0.5) && holds(0.8));
    }

    /// Where the depth image reads the background 25 mm nearer than its phasors do (a
    /// systematic that light along several paths makes, each frequency's phase moved its own
    /// way), the latch measures it, and no layer pixel's σ is under it; with the two agreeing,
    /// σ is the fit's own.
    #[test]
    fn a_background_the_frequencies_disagree_on_sets_a_floor_under_sigma() {
        let scene = Scene::from_toml(SCENE, "t.toml").expect("scene");
        let all = frames(&scene);
        let sigmas = |offset_mm: f32| {
            let mut s = stage(&scene);
            let shifted: Vec<DepthFrame> = all[..6]
                .iter()
                .map(|(_, d, _)| DepthFrame {
                    z_mm: ImageBuf {
                        data: d.z_mm.data.iter().map(|z| z - offset_mm).collect(),
                        ..d.z_mm.clone()
                    },
                    ..d.clone()
                })
                .collect();
            let latch: Vec<_> = all[..6].iter().map(|(p, _, _)| p).zip(&shifted).collect();
            let systematic = s
                .latch(&latch, Sensor::sr4000().unambiguous_range_mm())
                .expect("latch")
                .systematic_mm;
            let (p, d, _) = &all[6];
            let out = s.process(p, d).expect("frame");
            let mut sigma: Vec<f64> = (0..out.frame.mask.len())
                .filter(|&i| out.frame.mask.data[i])
                .map(|i| f64::from(out.frame.corrected_sigma_mm.data[i]))
                .collect();
            let least = sigma.iter().copied().fold(f64::INFINITY, f64::min);
            (systematic, least, median_select(&mut sigma))
        };
        let (plain, _, plain_median) = sigmas(0.0);
        let (shifted, least, _) = sigmas(25.0);
        println!("systematic {plain:.2} mm, sigma median {plain_median:.2}; shifted 25 mm: {shifted:.2}, least sigma {least:.2}");
        assert!(plain < 2.0 && plain_median < 10.0, "{plain} {plain_median}");
        // Ray distance: z times up to 1.07 in this field of view.
        assert!((25.0..27.5).contains(&shifted), "{shifted}");
        assert!(least >= 23.0, "{least}");
    }

    /// Light along several paths turns each frequency's phasor its own way; here the sheet's
    /// 100 MHz phasors turned by 4 degrees. Every pixel still fits a layer, and the region's
    /// interval from its pixels' scatter misses ξ; with each frequency left out in turn ξ
    /// moves, and the interval widened by that holds it. Unturned, the widening is small.
    #[test]
    fn a_frequency_the_model_misfits_widens_the_interval_by_the_jackknife() {
        let (s, all) = latched_on(SCENE);
        let (p, d, truth) = &all[6];
        let sheet_region = |p: &PhasorFrame| {
            let out = s.process(p, d).expect("frame");
            out.frame
                .regions
                .iter()
                .filter(|r| !r.opaque)
                .max_by_key(|r| r.pixels)
                .map(|r| r.xi.clone())
                .expect("a layer region")
        };
        let plain = sheet_region(p);
        let mut turned = p.clone();
        let (c, s4) = (4f32.to_radians().cos(), 4f32.to_radians().sin());
        for (i, &t) in truth.data.iter().enumerate() {
            if t < 1150.0 {
                let [a, b] = turned.phasors[2].data[i];
                turned.phasors[2].data[i] = [a * c - b * s4, a * s4 + b * c];
            }
        }
        let misfit = sheet_region(&turned);
        println!(
            "plain {:.4} {:?}; turned {:.4} {:?} ({})",
            plain.xi, plain.interval, misfit.xi, misfit.interval, misfit.note
        );
        let holds = |e: &XiEstimate| e.interval[0] <= 0.75 && 0.75 <= e.interval[1];
        assert!(
            holds(&plain) && plain.interval[1] - plain.interval[0] < 0.03,
            "{:?}",
            plain.interval
        );
        assert!(holds(&misfit), "{:?}", misfit.interval);
        assert!(misfit.note.contains("left out"), "{}", misfit.note);
    }

    /// A changed pixel whose best layer lies at the background's own distance claims nothing:
    /// light between two surfaces that an object elsewhere blocks dims the background and turns
    /// it a little, which a layer of weak return at the background fits. A layer well before
    /// the background is claimed.
    #[test]
    fn a_layer_at_the_background_claims_nothing() {
        let background = [Phasor { a: 1000.0, b: 0.0 }; 3];
        let inputs = PixelInputs {
            measured: [Phasor { a: 850.0, b: 20.0 }; MAX_FREQUENCIES],
            noise_sigma: [5.0; MAX_FREQUENCIES],
            frequencies: 3,
            background: &background,
            background_distance_mm: 2700.0,
            change_chi_square: 1e4,
        };
        let layer_at = |d: f64| MultiFrequencyEstimate {
            foreground_distance_mm: d,
            first_return: 120.0,
            translucency: 0.9,
            chi_square: 3.0,
            opacity_statistic: 60.0,
            opaque: false,
            foreground_distance_sigma_mm: 40.0,
            translucency_sigma: 0.02,
        };
        let level = CHI_SQUARE_1_999;
        // Within three of its standard deviations (120 mm) of the background: nothing claimed.
        assert!(unclaimed(&layer_at(2700.0 - 100.0), &inputs, level));
        assert!(unclaimed(&layer_at(2700.0 + 20.0), &inputs, level));
        // Beyond them: a layer.
        assert!(!unclaimed(&layer_at(2700.0 - 400.0), &inputs, level));
    }

    #[test]
    fn an_opaque_edge_is_no_layer_and_its_pixels_take_what_their_centre_sees() {
        // Four by four rays a pixel: the box's outline (1300 mm, before the wall at 2000)
        // mixes the two; with the background latched such a pixel fits a layer at the box's
        // distance whose ξ^2 is the wall's share.
        let text = SCENE.replace("[camera]\n", "[camera]\nsupersample = 4\n");
        let (s, all) = latched_on(&text);
        let (p, d, truth) = &all[6];
        let out = s.process(p, d).expect("frame");
        let o = &out.frame;
        // The pixels read between the two beside the box and away from the sheet: the box's
        // outline. Their truth is the box's, or the wall's (2000 mm) where no object is hit
        // at the centre.
        let w = truth.width;
        let near = |i: usize, what: &dyn Fn(f32) -> bool| {
            let (c, r) = ((i % w) as isize, (i / w) as isize);
            (-2..=2isize).any(|dr| {
                (-2..=2isize).any(|dc| {
                    let (cc, rr) = (c + dc, r + dr);
                    cc >= 0
                        && rr >= 0
                        && (cc as usize) < w
                        && (rr as usize) < truth.height
                        && what(truth.data[rr as usize * w + cc as usize])
                })
            })
        };
        let (mut flagged, mut n, mut raw2, mut pub2) = (0, 0, 0.0, 0.0);
        for i in 0..truth.data.len() {
            let (t, z) = (f64::from(truth.data[i]), f64::from(d.z_mm.data[i]));
            let beside_box = near(i, &|t| (1150.0..1900.0).contains(&t)) && !near(i, &|t| t < 1150.0);
            if !beside_box || !(1400.0..1900.0).contains(&z) {
                continue;
            }
            let t = if t.is_finite() { t } else { 2000.0 };
            n += 1;
            flagged += usize::from(o.mask.data[i]);
            raw2 += (z - t).powi(2);
            pub2 += (f64::from(o.corrected_z_mm.data[i]) - t).powi(2);
        }
        let (raw, published) = ((raw2 / n.max(1) as f64).sqrt(), (pub2 / n.max(1) as f64).sqrt());
        assert!(n >= 20, "{n} mixed pixels");
        assert_eq!(flagged, 0, "of {n}");
        assert!(
            published < 0.5 * raw,
            "{published:.1} against {raw:.1} mm read over {n} pixels"
        );
        // The sheet is still a layer.
        let c = SheetAndBox::of(&out, d, truth);
        assert!(c.in_mask * 100 >= c.sheet * 90, "{c:?}");
    }

    #[test]
    fn an_opaque_edge_that_runs_into_a_sheet_takes_what_its_centre_sees() {
        // A faint sheet (ξ 0.9, 1280 mm) taller than the box (1300 mm) it touches: the box's
        // top and bottom outlines run into the sheet, and their mixed pixels (a layer at the
        // box's distance hiding the wall's share 1 - ξ_p^2) join the sheet's region. The
        // sheet hides at most 1 - 0.81 of the wall; where an outline pixel hides more, the
        // rest is the box's, and its centre sees the box or the wall as that share says.
        let text = SCENE
            .replace("[camera]\n", "[camera]\nsupersample = 4\n")
            .replace("center_mm = [120, 0, 900]", "center_mm = [150, 0, 1280]")
            .replace("tilt_y_deg = 25\nxi = 0.75", "tilt_y_deg = 0\nxi = 0.9")
            .replace("center_mm = [-250, 0, 1300]", "center_mm = [-100, 0, 1300]");
        let (s, all) = latched_on(&text);
        let (p, d, truth) = &all[6];
        let out = s.process(p, d).expect("frame");
        let (w, h) = (truth.width, truth.height);
        // The wall's pixels beside the box's top and bottom (the box's pixel above or below),
        // away from the sheet (no sheet pixel within two columns).
        let at = |r: isize, c: isize| {
            (r >= 0 && c >= 0 && (r as usize) < h && (c as usize) < w)
                .then(|| f64::from(truth.data[r as usize * w + c as usize]))
        };
        let is_box = |t: Option<f64>| t.is_some_and(|t| (t - 1300.0).abs() < 5.0);
        let is_sheet = |t: Option<f64>| t.is_some_and(|t| (t - 1280.0).abs() < 5.0);
        let (mut n, mut raw2, mut pub2) = (0, 0.0, 0.0);
        for i in 0..truth.data.len() {
            let (r, c) = ((i / w) as isize, (i % w) as isize);
            let wall = !truth.data[i].is_finite() || truth.data[i] > 1900.0;
            let rim = is_box(at(r - 1, c)) || is_box(at(r + 1, c));
            let by_sheet = (-2..=2).any(|dc| (-1..=1).any(|dr| is_sheet(at(r + dr, c + dc))));
            if !wall || !rim || by_sheet {
                continue;
            }
            n += 1;
            raw2 += (f64::from(d.z_mm.data[i]) - 2000.0).powi(2);
            pub2 += (f64::from(out.frame.corrected_z_mm.data[i]) - 2000.0).powi(2);
        }
        let (raw, published) = ((raw2 / n.max(1) as f64).sqrt(), (pub2 / n.max(1) as f64).sqrt());
        assert!(n >= 10, "{n} outline pixels");
        assert!(
            published < raw,
            "{published:.1} against {raw:.1} mm read over {n} pixels whose centre sees the wall"
        );
        // The sheet stays a layer.
        let sheet = (0..truth.data.len()).filter(|&i| is_sheet(Some(f64::from(truth.data[i]))));
        let (count, masked) = sheet.fold((0, 0), |a, i| (a.0 + 1, a.1 + usize::from(out.frame.mask.data[i])));
        assert!(
            masked * 100 >= count * 90,
            "{masked} of {count} sheet pixels in the mask"
        );
    }

    #[test]
    fn where_the_model_misfits_a_region_its_pixels_sigma_holds_their_error() {
        // A frosted sheet: most of the light it passes crosses diffusely (physics.md: a
        // share of the second return comes back over slanted paths), which the path's two
        // returns leave out. Its pixels' fits are biased alike, and the surface's window does
        // not average that down; their chi^2 says how far they misfit.
        let text = SCENE.replace("[physics]\n", "[physics]\ndiffuse_transmission = 0.8\n");
        let (s, all) = latched_on(&text);
        let (mut n, mut held, mut sheet) = (0, 0, 0);
        let (mut errs, mut sigmas) = (vec![], vec![]);
        for (p, d, truth) in &all[6..] {
            let out = s.process(p, d).expect("frame");
            let o = &out.frame;
            for (i, &t) in truth.data.iter().enumerate() {
                let (z, sigma) = (o.corrected_z_mm.data[i], o.corrected_sigma_mm.data[i]);
                sheet += usize::from(t < 1150.0);
                if t < 1150.0 && o.mask.data[i] && sigma.is_finite() {
                    n += 1;
                    held += usize::from((z - t).abs() <= 2.0 * sigma);
                    errs.push(f64::from((z - t).abs()));
                    sigmas.push(f64::from(sigma));
                }
            }
        }
        eprintln!(
            "{held} of {n} of {sheet}; median error {:.1} sigma {:.1}",
            median_select(&mut errs),
            median_select(&mut sigmas)
        );
        assert!(n * 10 >= sheet * 9, "{n} of {sheet} sheet pixels recovered");
        assert!(held * 100 >= n * 90, "σ holds the error at {held} of {n} sheet pixels");
    }

    #[test]
    fn with_no_latch_the_layer_comes_from_two_free_returns_and_the_box_is_kept() {
        let scene = Scene::from_toml(SCENE, "t.toml").expect("scene");
        let all = frames(&scene);
        let s = stage(&scene); // nothing latched
        let (p, d, truth) = &all[6];
        assert!(matches!(s.process(p, d), Err(MultiFrequencyStageError::NoBackground)));
        let out = s.process_unlatched(p, d).expect("frame");
        let o = &out.frame;
        let c = SheetAndBox::of(&out, d, truth);
        // xi is not measured without the background's own return.
        assert!(out.translucency.data.iter().all(|x| x.is_nan()));
        assert!(c.in_mask * 100 >= c.sheet * 90 && c.rms_mm < 15.0, "{c:?}");
        assert!(c.box_px > 50 && c.box_masked * 20 <= c.box_px, "{c:?}");
        assert!(o
            .regions
            .iter()
            .all(|r| r.opaque || (r.xi.xi.is_nan() && r.xi.interval == [0.0, 1.0])));
    }

    #[test]
    fn bad_frames_are_errors() {
        let scene = Scene::from_toml(SCENE, "t.toml").expect("scene");
        let all = frames(&scene);
        let mut s = stage(&scene);
        let (p, d, _) = &all[0];
        assert!(matches!(s.process(p, d), Err(MultiFrequencyStageError::NoBackground)));
        let range = Sensor::sr4000().unambiguous_range_mm();
        let one = s.latch(&[(p, d)], range).unwrap_err();
        assert!(matches!(one, MultiFrequencyStageError::TooFewFrames(1)), "{one}");
        // A recording with no empty frames is told the way for a moving camera (issue 48, item 5).
        let said = one.to_string();
        assert!(
            said.contains("--no-latch") && said.contains("node parameter no_latch"),
            "{said}"
        );
        let two = PhasorFrame {
            phasors: p.phasors[..2].to_vec(),
            ..p.clone()
        };
        let e = s.latch(&[(&two, d), (&two, d)], range).unwrap_err();
        assert!(
            matches!(e, MultiFrequencyStageError::FrequencyCount { expected: 3, got: 2 }),
            "{e}"
        );
        let mut small = p.clone();
        small.phasors[1] = ImageBuf::filled(10, 10, [0.0; 2]);
        let e = s.latch(&[(&small, d), (&small, d)], range).unwrap_err();
        assert!(e.to_string().contains("phasor image 1 is 10x10, expected 48x40"), "{e}");
        let dark = PhasorFrame {
            phasors: vec![ImageBuf::filled(48, 40, [0.0; 2]); 3],
            ..p.clone()
        };
        let e = s.latch(&[(&dark, d), (&dark, d)], range).unwrap_err();
        assert!(
            matches!(e, MultiFrequencyStageError::BackgroundInvalid { valid: 0, .. }),
            "{e}"
        );
    }

    #[test]
    fn a_background_pixel_is_aliased_only_where_a_multiple_of_the_common_range_explains_it() {
        let depth_range = Sensor::sr4000().unambiguous_range_mm();
        // 50 and 100 MHz (2998 mm) before a wall at 3300 mm: the phasors put it at 302.
        assert!(aliased(302.0, 3300.0, 2998.0, depth_range));
        // Light along several paths (a table's, a corner's): 221 mm apart, no multiple of
        // 14990 mm (20, 50 and 100 MHz) explains it.
        assert!(!aliased(2066.0, 2287.0, 14990.0, depth_range));
        assert!(!aliased(2000.0, 2040.0, 2998.0, depth_range));
    }

    #[test]
    fn frequencies_whose_common_range_is_shorter_than_the_scene_are_refused() {
        // 50 and 100 MHz repeat every 2998 mm; the wall is at 3300 mm.
        let text = SCENE
            .replace("[20e6, 50e6, 100e6]", "[50e6, 100e6]")
            .replace("distance_mm = 2000", "distance_mm = 3300");
        let scene = Scene::from_toml(&text, "t.toml").expect("scene");
        let all = frames(&scene);
        let mut s = stage(&scene);
        let latch: Vec<_> = all[..6].iter().map(|(p, d, _)| (p, d)).collect();
        let e = s.latch(&latch, Sensor::sr4000().unambiguous_range_mm()).unwrap_err();
        let text = e.to_string();
        assert!(
            matches!(e, MultiFrequencyStageError::Aliased { .. }) && text.contains("common unambiguous range 2998 mm"),
            "{text}"
        );
    }
}
