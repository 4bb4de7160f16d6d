//! Estimating the translucency ξ that the data determine (physics.md §3).
//!
//! One frame's residuals alone do not pick ξ: every ξ fits each pixel. What
//! carries it, and what this module offers:
//! - [`calibrate`]: known foreground distances (the paper's Sec. V-A protocol);
//! - [`one_material`]: the ξ under which the albedo the inversion implies is
//!   the same over the object's pixels and over frames;
//! - [`eq12_residual`]: the paper's Eq. 12 residual sum, kept for comparison
//!   (its profile is flat: it reports how flat).
//!
//! Each works on per-frame [`FrameProfile`]s computed once on a fixed ξ grid,
//! so pooling a new frame costs one frame's work.

use std::borrow::Borrow;

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::buffer::{ImageBuf, Region, SparseImage};
use super::inversion::{albedo_cos_clamped, predicted_reading, InversionBounds, PixelObservation, PixelsOverXi};
use super::model::ForwardModel;
use super::stats::{median_and_sigma, student_t975};
use super::surface::{local_planes_adaptive, Plane};

/// How ξ was chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum XiMethod {
    /// Given by the user (`--xi`, parameter `xi`), e.g. from `calibrate-xi`.
    Fixed,
    /// Fitted to frames with known foreground distances (paper Sec. V-A).
    Calibrated,
    /// The ξ that makes the object one material (albedo constant over pixels and frames).
    OneMaterial,
    /// The paper's Eq. 12 residual sum (degenerate: for comparison only).
    Eq12Residual,
    /// Per pixel from several modulation frequencies' phasors (issue 35), a
    /// region's the median of its pixels'.
    MultiFrequency,
}

impl XiMethod {
    /// The name used in parameters and reports.
    pub fn as_str(&self) -> &'static str {
        match self {
            XiMethod::Fixed => "fixed",
            XiMethod::Calibrated => "calibrated",
            XiMethod::OneMaterial => "one_material",
            XiMethod::Eq12Residual => "eq12_residual",
            XiMethod::MultiFrequency => "multi_frequency",
        }
    }
}

/// An estimate of ξ with the interval the data support.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct XiEstimate {
    /// The estimate.
    pub xi: f64,
    /// Interval `[lo, hi]` (about 95 %) the data support.
    pub interval: [f64; 2],
    /// How it was chosen.
    pub method: XiMethod,
    /// Frames pooled.
    pub frames: usize,
    /// Pixels used (summed over frames).
    pub pixels: usize,
    /// The objective over the ξ grid, `(xi, value)`, lower is better.
    pub profile: Vec<(f64, f64)>,
    /// A sentence on what the data could and could not tell.
    pub note: String,
}

impl XiEstimate {
    /// A user-given ξ.
    pub fn fixed(xi: f64) -> Self {
        Self {
            xi,
            interval: [xi, xi],
            method: XiMethod::Fixed,
            frames: 0,
            pixels: 0,
            profile: vec![],
            note: "given by the user".into(),
        }
    }

    /// Half the interval's width.
    pub fn half_width(&self) -> f64 {
        0.5 * (self.interval[1] - self.interval[0])
    }

    /// Opaque, the null hypothesis (issue 31): the data do not reject a layer that passes
    /// less than [`OPAQUE_XI`], its interval reaches down to it. Such an object keeps its
    /// reading: a correction is applied only where the data support one.
    pub fn is_opaque(&self) -> bool {
        self.interval[0] <= OPAQUE_XI
    }
}

/// Largest ξ treated as opaque: a layer passing less light than this changes its
/// reading by under a few millimetres (the second return is `xi^2` of the background's).
pub const OPAQUE_XI: f64 = 0.1;

/// The ξ hypotheses every profile is evaluated on: 0.02 steps to 0.8, then
/// 0.01 steps to 0.99 (highly translucent materials need the finer steps).
pub fn xi_grid() -> Vec<f64> {
    let mut g: Vec<f64> = (0..40).map(|k| k as f64 * 0.02).collect();
    g.extend((80..=99).map(|k| k as f64 * 0.01));
    g
}

/// Settings of the ξ estimation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct XiSettings {
    /// Most pixels a frame contributes (a regular lattice over its objects, shared among
    /// the objects whose evidence it computes).
    pub max_pixels_per_frame: usize,
    /// Frames of evidence an object gathers at one pose while it stands still; after them its
    /// frames there add none (they repeat what it showed) and cost nothing.
    pub frames_per_pose: usize,
    /// Narrowest radius, in image pixels, of the local planes that give the normals
    /// (widened up to 6x where the recovered layer is too noisy for it).
    pub normal_radius_px: usize,
    /// The normals' windows are shared by square blocks of this many lattice
    /// steps a side, each pixel taking the fitted surface's tangent at its own
    /// ray (1: a window for every sampled pixel).
    pub normal_block_steps: usize,
    /// Groups (by measured distance) a frame is split into.
    pub groups_per_frame: usize,
    /// Fewest pixels in a group.
    pub min_group_pixels: usize,
    /// Most frames pooled: beyond it the oldest frame's evidence is dropped,
    /// so that a node running for hours keeps its memory and per-frame time
    /// bounded and follows a material that changes.
    pub max_frames_pooled: usize,
    /// Fastest an object moves along the camera's rays, m/s: a region farther from
    /// where an object was than this allows in the time between jumped (faster than a
    /// hand or a robot carries one: a cut).
    pub max_object_speed_m_s: f64,
    /// Largest change of an object's speed along the rays, m/s²: once its speed is known
    /// from two frames, a region farther from where that speed puts it jumped.
    pub max_object_acceleration_m_s2: f64,
    /// Longest 3-D step an object is followed through between two frames where it was put at
    /// another pose between captures (one frame a pose), mm; shared/design/objects.md
    /// "Stepped poses". Followed only where no other way of continuing the objects comes near.
    pub max_pose_step_mm: f64,
    /// Standard deviation of the one-material estimate's error that its own evidence cannot
    /// show: the model's misfit to a physical scene (light between a layer and a near wall,
    /// diffuse transmission, a hollow object's third return, mixed edges), measured on
    /// physically rendered recordings held out from the scenes it is used on
    /// (`scripts/xi_model_error.py`). Every interval short of [0, 1] takes it in quadrature
    /// ([`with_model_error`]). 0 (the default here: the model's own simulator) leaves the
    /// intervals as their evidence gives them; `replay` and the node take
    /// [`XI_MODEL_ERROR_SD`], measured on physical renders.
    pub xi_model_error_sd: f64,
}

impl Default for XiSettings {
    fn default() -> Self {
        Self {
            max_pixels_per_frame: 1500,
            frames_per_pose: 8,
            normal_radius_px: 3,
            normal_block_steps: 3,
            groups_per_frame: 3,
            min_group_pixels: 40,
            max_frames_pooled: 64,
            max_object_speed_m_s: 2.0,
            max_object_acceleration_m_s2: 10.0,
            max_pose_step_mm: 500.0,
            xi_model_error_sd: 0.0,
        }
    }
}

/// The pixels of one frame that ξ estimation uses: a lattice over the object.
#[derive(Debug, Clone)]
pub struct FrameSample {
    /// Observations on the lattice (None off the object).
    pub observations: ImageBuf<Option<PixelObservation>>,
    /// Unit rays of the lattice pixels.
    pub rays: ImageBuf<Vector3<f64>>,
    /// True foreground ray distance where known (calibration), mm.
    pub truth_mm: Option<ImageBuf<f64>>,
    /// Lattice stride in image pixels.
    pub stride: usize,
}

impl FrameSample {
    /// Takes every `stride`-th pixel in both directions, with the stride chosen
    /// so at most `max_pixels` observations remain.
    pub fn from_image(
        observations: &SparseImage<PixelObservation>,
        rays: &ImageBuf<Vector3<f64>>,
        truth_mm: Option<&ImageBuf<f64>>,
        max_pixels: usize,
    ) -> Self {
        let n = observations.count().max(1);
        let stride = ((n as f64 / max_pixels.max(1) as f64).sqrt().ceil() as usize).max(1);
        let (w, h) = (
            (observations.width).div_ceil(stride),
            (observations.height).div_ceil(stride),
        );
        let pick = |img_w: usize, k: usize| (k / w) * stride * img_w + (k % w) * stride;
        let obs = (0..w * h)
            .map(|k| observations.get(pick(observations.width, k)).copied())
            .collect();
        let ray = (0..w * h).map(|k| rays.data[pick(rays.width, k)]).collect();
        let truth = truth_mm.map(|t| ImageBuf {
            width: w,
            height: h,
            data: (0..w * h).map(|k| t.data[pick(t.width, k)]).collect(),
        });
        Self {
            observations: ImageBuf {
                width: w,
                height: h,
                data: obs,
            },
            rays: ImageBuf {
                width: w,
                height: h,
                data: ray,
            },
            truth_mm: truth,
            stride,
        }
    }

    /// The sample cut to the rectangle around its observations, its edges on the grid of
    /// `align x align` blocks from the lattice's corner ([`Region::around`]): the same
    /// observations, rays and normals' blocks in a lattice without the empty rows and
    /// columns around the object (a small object far from the camera has a fine lattice
    /// over the whole image). `None` when it is already that rectangle or has no observation.
    pub fn around_observations(&self, align: usize) -> Option<Self> {
        let obs = &self.observations;
        let held = ImageBuf {
            width: obs.width,
            height: obs.height,
            data: obs.data.iter().map(Option::is_some).collect(),
        };
        let region = Region::around(&held, align)?;
        (region.len() < obs.len()).then(|| Self {
            observations: region.crop(obs),
            rays: region.crop(&self.rays),
            truth_mm: self.truth_mm.as_ref().map(|t| region.crop(t)),
            stride: self.stride,
        })
    }

    /// Observations present.
    pub fn pixel_count(&self) -> usize {
        self.observations.data.iter().filter(|o| o.is_some()).count()
    }
}

/// Pixels seen more obliquely than this (cos of incidence) carry no albedo:
/// near a silhouette the normal, so the albedo it implies, is least reliable.
const MIN_INCIDENCE_COS: f64 = 0.3;

/// Least scatter of `log rho` within a group of pixels.
const MIN_ALBEDO_SCATTER: f64 = 0.02;

/// The value a pixel that fits no physical albedo enters the statistics with,
/// relative to the largest albedo the bounds admit.
const CENSORED_ALBEDO: f64 = 2.0;

/// Largest albedo a surface can have, relative to the bound on `X`, with room for
/// the noise of one pixel's estimate.
const MAX_ALBEDO: f64 = 1.1;

/// The bound on `X` at ξ = 0 (opaque): none that a real surface reaches, so only
/// pixels without a usable normal are censored there.
const OPAQUE_ALBEDO_BOUND: f64 = 1e3;

/// Per pixel of the sample: whether the reading itself (the surface as measured) gives it a
/// usable normal, one seen at more than [`MIN_INCIDENCE_COS`]: not a face seen nearly
/// edge-on, a silhouette or a mixed edge, whose normal no ξ makes known.
fn readable_normals(sample: &FrameSample, planes: &ImageBuf<Option<Plane>>) -> Vec<bool> {
    let obs = &sample.observations;
    (0..obs.data.len())
        .map(|i| {
            planes.data[i]
                .map(|p| p.incidence_cos(&sample.rays.data[i]))
                .is_some_and(|c| c > MIN_INCIDENCE_COS)
        })
        .collect()
}

/// The local planes of the reading itself (the surface as measured: the layer at ξ = 0).
fn reading_planes(
    sample: &FrameSample,
    mask: &ImageBuf<bool>,
    radii: &[usize],
    block_steps: usize,
) -> ImageBuf<Option<Plane>> {
    let obs = &sample.observations;
    let mut points = ImageBuf::filled(obs.width, obs.height, Vector3::new(f64::NAN, f64::NAN, f64::NAN));
    for (i, o) in obs.data.iter().enumerate() {
        if let Some(o) = o {
            points.data[i] = sample.rays.data[i] * o.distance_mm;
        }
    }
    local_planes_adaptive(&points, &sample.rays, mask, radii, 12, 0.05, block_steps)
}

/// Robust summary of `log rho` in one group of pixels at one ξ.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GroupStat {
    /// Median of `log rho_f`.
    pub median: f64,
    /// Standard error of that median (from the MAD).
    pub std_error: f64,
    /// Pixels with a valid albedo.
    pub count: usize,
}

/// Error sums of the model's prediction at known foreground distances.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TruthFit {
    /// Noise-weighted sum of squared errors, mm^2.
    pub weighted_sse: f64,
    /// Sum of the weights.
    pub weight: f64,
    /// Plain sum of squared errors, mm^2.
    pub sse: f64,
    /// Pixels.
    pub count: usize,
}

/// What a frame's profile is computed for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProfileUse {
    /// Invert every pixel at every ξ: one-material and Eq. 12 statistics.
    Estimation,
    /// Only the prediction at the known distances (calibration; much cheaper).
    Calibration,
}

/// A frame's statistics at every ξ of [`xi_grid`].
#[derive(Debug, Clone, PartialEq)]
pub struct FrameProfile {
    /// Per ξ: the groups' albedo statistics (one-material objective).
    pub groups: Vec<Vec<GroupStat>>,
    /// Per ξ: share of pixels pinned at a bound or without any admissible root.
    pub pinned_fraction: Vec<f64>,
    /// Per ξ: Eq. 12's summed squared residual, mm^2.
    pub eq12: Vec<f64>,
    /// Per ξ: the error of the predicted reading at the known distances (calibration).
    pub truth: Vec<TruthFit>,
    /// Pixels in the sample.
    pub pixels: usize,
    /// The object's pose in this frame, as the median measured distance, mm.
    pub median_distance_mm: f64,
}

/// Computes one frame's profile on the grid (the expensive part, done once per frame).
pub fn frame_profile(
    model: &ForwardModel,
    bounds: &InversionBounds,
    sample: &FrameSample,
    settings: &XiSettings,
    usage: ProfileUse,
) -> FrameProfile {
    // Every stage below looks only at observed pixels and the windows around them, on the
    // normals' block grid: the lattice cut to its observations gives the same profile.
    let cropped = sample.around_observations(settings.normal_block_steps.max(1));
    let frame = ProfileFrame::new(model, bounds, cropped.as_ref().unwrap_or(sample), settings, usage);
    frame.profile()
}

/// What [`frame_profile`] holds fixed over the ξ grid for one frame's sample.
struct ProfileFrame<'a> {
    model: &'a ForwardModel,
    bounds: &'a InversionBounds,
    sample: &'a FrameSample,
    settings: &'a XiSettings,
    usage: ProfileUse,
    /// The sampled pixels with an observation, in grid order (inverted together at each ξ).
    observed: Vec<(usize, PixelObservation)>,
    observations: PixelsOverXi<'a>,
    mask: ImageBuf<bool>,
    /// The normals' windows: from `normal_radius_px` up to 6x that, in lattice steps.
    radii: Vec<usize>,
    /// The reading's own local planes (the layer at ξ = 0) and which pixels they give a
    /// usable normal ([`readable_normals`]).
    reading: ImageBuf<Option<Plane>>,
    readable: Vec<bool>,
    /// Each pixel's neighbourhood-mean distance and the groups' edges over it.
    smooth: Vec<f64>,
    edges: Vec<f64>,
    /// The finite neighbourhood-mean distances, sorted.
    distances: Vec<f64>,
}

impl<'a> ProfileFrame<'a> {
    fn new(
        model: &'a ForwardModel,
        bounds: &'a InversionBounds,
        sample: &'a FrameSample,
        settings: &'a XiSettings,
        usage: ProfileUse,
    ) -> Self {
        let obs = &sample.observations;
        let (w, h) = (obs.width, obs.height);
        // Groups: quantile bins of the measured distance averaged over a neighbourhood. Not
        // ξ's doing, and not the pixel's own noise either: bins of the raw reading would sort
        // pixels by their noise, and the recovered layer with them.
        let smooth = neighbourhood_mean_distance(obs, (6 / sample.stride).max(1));
        let mut distances: Vec<f64> = smooth.iter().copied().filter(|d| d.is_finite()).collect();
        distances.sort_by(f64::total_cmp);
        let n_groups = settings
            .groups_per_frame
            .min(distances.len() / settings.min_group_pixels.max(1))
            .max(1);
        let edges: Vec<f64> = (1..n_groups)
            .map(|k| distances[k * distances.len() / n_groups])
            .collect();
        // Each pixel takes the narrowest window whose normal is known to 0.05 rad (a
        // cos(theta) bias under 0.13 %).
        let mut radii: Vec<usize> = [1, 2, 4, 6]
            .iter()
            .map(|m| (m * settings.normal_radius_px / sample.stride).max(2))
            .collect();
        radii.dedup();
        let mask = ImageBuf {
            width: w,
            height: h,
            data: obs.data.iter().map(|o| o.is_some()).collect(),
        };
        let observed: Vec<(usize, PixelObservation)> = (0..w * h).filter_map(|i| obs.data[i].map(|o| (i, o))).collect();
        let observations = PixelsOverXi::new(model, observed.iter().map(|&(_, o)| o).collect());
        // Pixels whose reading gives no usable normal (a surface seen nearly edge-on, a
        // silhouette against the background, a mixed edge) carry no albedo at any ξ: left out
        // of the albedo statistics at every ξ alike (so no ξ wins by it), rather than censored
        // (a censored share that grows as an object turns a face edge-on moves its groups'
        // medians with its pose: an opaque box carried and turning through a video was taken
        // for a layer by it).
        let reading = reading_planes(sample, &mask, &radii, settings.normal_block_steps);
        let readable = readable_normals(sample, &reading);
        Self {
            model,
            bounds,
            sample,
            settings,
            usage,
            observed,
            observations,
            mask,
            radii,
            reading,
            readable,
            smooth,
            edges,
            distances,
        }
    }

    /// The frame's statistics at every ξ of the grid (in parallel over the current rayon
    /// pool, gathered in grid order).
    fn profile(&self) -> FrameProfile {
        let mut out = FrameProfile {
            groups: vec![],
            pinned_fraction: vec![],
            eq12: vec![],
            truth: vec![],
            pixels: self.distances.len(),
            median_distance_mm: self
                .distances
                .get(self.distances.len() / 2)
                .copied()
                .unwrap_or(f64::NAN),
        };
        let rows: Vec<_> = xi_grid().par_iter().map(|&xi| self.at(xi)).collect();
        for (stats, pinned_fraction, eq12, fit) in rows {
            out.groups.push(stats);
            out.pinned_fraction.push(pinned_fraction);
            out.eq12.push(eq12);
            out.truth.push(fit);
        }
        out
    }

    fn group_of(&self, i: usize) -> usize {
        self.edges.iter().filter(|&&e| self.smooth[i] >= e).count()
    }

    /// The frame's statistics at one ξ: the groups' albedos, the share pinned, Eq. 12's
    /// residual and the error at the known distances.
    fn at(&self, xi: f64) -> (Vec<GroupStat>, f64, f64, TruthFit) {
        // Albedos are known up to Lin's scale: the bound on X (1 with a calibrated Lin) sets
        // both. Opaque (xi 0) is judged by its albedos' consistency alone: the bound on X
        // comes from `Lin`, which rests on an assumed background albedo, and an opaque object
        // brighter than its background exceeds it (such an object is not a layer, whatever the
        // bound).
        let unbounded = InversionBounds {
            max_albedo_cos: OPAQUE_ALBEDO_BOUND,
            ..*self.bounds
        };
        let bounds = if xi == 0.0 { &unbounded } else { self.bounds };
        let layer = self.layer_at(xi, bounds);
        let (stats, pinned) = self.albedo_groups(xi, bounds.max_albedo_cos, &layer);
        (
            stats,
            pinned as f64 / self.distances.len().max(1) as f64,
            layer.eq12,
            layer.fit,
        )
    }

    /// Every observed pixel inverted at ξ: its layer's point and `X` (NaN where pinned or
    /// without a root), with the pinned count, Eq. 12's residual and the truth's error.
    fn layer_at(&self, xi: f64, bounds: &InversionBounds) -> LayerAt {
        let obs = &self.sample.observations;
        let (w, h) = (obs.width, obs.height);
        let mut layer = LayerAt {
            points: ImageBuf::filled(w, h, Vector3::new(f64::NAN, f64::NAN, f64::NAN)),
            xs: vec![f64::NAN; w * h],
            pinned: 0,
            eq12: 0.0,
            fit: TruthFit::default(),
        };
        let calibration = self.usage == ProfileUse::Calibration;
        let estimates = if calibration {
            vec![]
        } else {
            self.observations.at(xi, bounds, false)
        };
        for (k, &(i, o)) in self.observed.iter().enumerate() {
            if let Some(t) = self
                .sample
                .truth_mm
                .as_ref()
                .map(|t| t.data[i])
                .filter(|t| t.is_finite())
            {
                add_truth_error(self.model, &o, t, xi, bounds, &mut layer.fit);
            }
            if calibration {
                continue;
            }
            match estimates[k] {
                Some(est) => {
                    layer.eq12 += est.residual_mm * est.residual_mm;
                    if est.pinned {
                        layer.pinned += 1;
                    } else {
                        layer.points.data[i] = self.sample.rays.data[i] * est.foreground_distance_mm;
                        layer.xs[i] = est.albedo_cos;
                    }
                }
                None => {
                    layer.pinned += 1;
                    layer.eq12 += self
                        .model
                        .sensor
                        .wrapped_difference_mm(o.distance_mm, o.background_distance_mm)
                        .powi(2);
                }
            }
        }
        layer
    }

    /// The groups' albedo statistics at ξ (the bound on `X` `x_bound`) from the layer's `X`
    /// and the normals of its local planes, and the pixels pinned in all.
    fn albedo_groups(&self, xi: f64, x_bound: f64, layer: &LayerAt) -> (Vec<GroupStat>, usize) {
        let (max_albedo, censored_albedo) = (MAX_ALBEDO * x_bound, CENSORED_ALBEDO * x_bound);
        let rays = &self.sample.rays;
        // Normals from the smooth-surface prior: local planes over the recovered layer (at
        // ξ = 0 the layer is the reading, whose planes are known).
        let computed;
        let planes = if xi == 0.0 {
            &self.reading
        } else {
            computed = local_planes_adaptive(
                &layer.points,
                rays,
                &self.mask,
                &self.radii,
                12,
                0.05,
                self.settings.normal_block_steps,
            );
            &computed
        };
        let mut pinned = layer.pinned;
        let mut per_group: Vec<Vec<f64>> = vec![vec![]; self.edges.len() + 1];
        for (i, o) in self.sample.observations.data.iter().enumerate() {
            if o.is_none() || !self.readable[i] {
                continue;
            }
            if !layer.xs[i].is_finite() {
                // Pinned by the inversion (counted already): censored too.
                per_group[self.group_of(i)].push(censored_albedo.ln());
                continue;
            }
            // Every pixel stays in its group at every ξ (so no ξ wins by dropping pixels): one
            // without a usable normal, seen too obliquely or implying an albedo above 1 enters
            // as a censored value above any physical albedo. Above 1 also counts as pinned.
            let cos = planes.data[i].map(|p| p.incidence_cos(&rays.data[i])).unwrap_or(0.0);
            let rho = if cos > MIN_INCIDENCE_COS {
                layer.xs[i] / cos
            } else {
                censored_albedo
            };
            if rho > max_albedo && cos > MIN_INCIDENCE_COS {
                pinned += 1;
            }
            per_group[self.group_of(i)].push(rho.min(censored_albedo).ln());
        }
        // A group whose median is censored carries no albedo at this ξ: out of the objective
        // (with its pixels counted as pinned, so such a ξ cannot win by it).
        let stats = per_group
            .into_iter()
            .map(|v| {
                let g = group_stat(v, self.settings.min_group_pixels);
                if g.median >= max_albedo.ln() {
                    pinned += g.count;
                    GroupStat {
                        median: f64::NAN,
                        std_error: f64::NAN,
                        count: g.count,
                    }
                } else {
                    g
                }
            })
            .collect();
        (stats, pinned)
    }
}

/// One frame's layer at one ξ ([`ProfileFrame::layer_at`]).
struct LayerAt {
    points: ImageBuf<Vector3<f64>>,
    xs: Vec<f64>,
    pinned: usize,
    eq12: f64,
    fit: TruthFit,
}

/// Mean reading over the observed pixels within `radius` (lattice steps) of each pixel.
fn neighbourhood_mean_distance(obs: &ImageBuf<Option<PixelObservation>>, radius: usize) -> Vec<f64> {
    let (w, h) = (obs.width, obs.height);
    (0..w * h)
        .map(|i| {
            if obs.data[i].is_none() {
                return f64::NAN;
            }
            let (col, row) = (i % w, i / w);
            let (mut sum, mut n) = (0.0, 0);
            for r in row.saturating_sub(radius)..(row + radius + 1).min(h) {
                for c in col.saturating_sub(radius)..(col + radius + 1).min(w) {
                    if let Some(o) = obs.data[r * w + c] {
                        sum += o.distance_mm;
                        n += 1;
                    }
                }
            }
            sum / n as f64
        })
        .collect()
}

/// Adds one pixel's noise-weighted error against a known foreground distance.
fn add_truth_error(
    model: &ForwardModel,
    o: &PixelObservation,
    truth: f64,
    xi: f64,
    bounds: &InversionBounds,
    acc: &mut TruthFit,
) {
    if !(truth > bounds.min_distance_mm && truth < o.background_distance_mm) {
        return;
    }
    // Noise can put the IR outside what any admissible albedo explains: the bound, not a penalty
    // (a penalty would push ξ toward values where fewer pixels leave the range).
    let (x, _) = albedo_cos_clamped(model, o, truth, xi, bounds.max_albedo_cos);
    let pred = predicted_reading(model, o, truth, xi, x);
    let r = model.sensor.wrapped_difference_mm(pred, o.distance_mm);
    // Shot-noise weight: phase noise ~ sqrt(total light) / |mixed amplitude|.
    let w = noise_weight(model, o, truth, xi, x);
    let w = if w.is_finite() && w > 0.0 {
        w
    } else if acc.count > 0 {
        acc.weight / acc.count as f64
    } else {
        1.0
    };
    acc.weighted_sse += w * r * r;
    acc.weight += w;
    acc.sse += r * r;
    acc.count += 1;
}

/// `1 / var(d)` up to a constant, for shot noise: `|A + iB|^2 / total light`.
fn noise_weight(model: &ForwardModel, o: &PixelObservation, df: f64, xi: f64, x: f64) -> f64 {
    let m = model.measure_layer(&o.layer_scene(df, xi, x, model.options.ambient_offset));
    let amp2 = m.buckets.a * m.buckets.a + m.buckets.b * m.buckets.b;
    if m.total_light > 0.0 {
        amp2 / m.total_light
    } else {
        0.0
    }
}

fn group_stat(mut v: Vec<f64>, min_count: usize) -> GroupStat {
    let count = v.len();
    let stats = if count >= min_count.max(3) {
        median_and_sigma(&mut v)
    } else {
        None
    };
    let Some((median, spread)) = stats else {
        return GroupStat {
            median: f64::NAN,
            std_error: f64::NAN,
            count,
        };
    };
    // No group of real pixels is more uniform than 2 % in albedo (noise, texture): the floor
    // keeps a group of identical (censored) values from taking all the weight.
    let sigma = spread.max(MIN_ALBEDO_SCATTER);
    GroupStat {
        median,
        std_error: 1.2533 * sigma / (count as f64).sqrt(),
        count,
    }
}

/// ξ values a method may pick: those at which no more pixels are pinned at a
/// bound than at the best ξ, give or take sampling noise (pinned pixels drop
/// out of the albedo statistics, so a ξ that pins many must not win by it).
///
/// ξ = 0 (opaque, no layer to invert) is always eligible, and does not set the best
/// share: it is evaluated without the albedo bound (see [`frame_profile`]).
fn eligible<P: Borrow<FrameProfile>>(profiles: &[P]) -> Vec<bool> {
    let frac = pooled_pinned_fraction(profiles);
    let total: usize = profiles.iter().map(|p| p.borrow().pixels).sum();
    let best = frac.iter().skip(1).copied().fold(f64::INFINITY, f64::min);
    let tol = 0.05f64.max(3.0 * (best * (1.0 - best) / total.max(1) as f64).sqrt());
    frac.iter()
        .enumerate()
        .map(|(k, &f)| k == 0 || f <= best + tol)
        .collect()
}

/// Per ξ of the grid: the share of the pooled pixels pinned at a bound or without a root.
fn pooled_pinned_fraction<P: Borrow<FrameProfile>>(profiles: &[P]) -> Vec<f64> {
    let total: usize = profiles.iter().map(|p| p.borrow().pixels).sum();
    (0..xi_grid().len())
        .map(|k| {
            profiles
                .iter()
                .map(|p| p.borrow().pinned_fraction[k] * p.borrow().pixels as f64)
                .sum::<f64>()
                / total.max(1) as f64
        })
        .collect()
}

/// The groups' log-albedo sums of each pose at one ξ: `(S, T, U, groups)` with
/// `S = sum w`, `T = sum w m`, `U = sum w m^2` over the groups, `w = 1 / se^2`.
type PoseSums = (f64, f64, f64, usize);

fn pose_sums<P: Borrow<FrameProfile>>(profiles: &[P], pose: &[usize], poses: usize, k: usize) -> Vec<PoseSums> {
    let mut sums = vec![(0.0, 0.0, 0.0, 0); poses];
    for (p, &j) in profiles.iter().zip(pose) {
        let Some(s) = sums.get_mut(j) else { continue };
        for g in p.borrow().groups[k].iter().filter(|g| g.median.is_finite()) {
            let w = 1.0 / (g.std_error * g.std_error);
            *s = (s.0 + w, s.1 + w * g.median, s.2 + w * g.median * g.median, s.3 + 1);
        }
    }
    sums
}

/// The one-material objective at one ξ: the groups' median log-albedos fitted by one mean,
/// the groups of each pose sharing an offset of variance `tau2` (the model's misfit between
/// poses, a random effect) besides their own standard errors: generalised least squares,
/// `Q = sum_p (U_p - tau2 T_p^2 a_p) - B^2 / A` with `a_p = 1 / (1 + tau2 S_p)`,
/// `A = sum S_p a_p`, `B = sum T_p a_p`. With `tau2 = 0` it is `sum_g (m_g - m)^2 / se_g^2`,
/// about chi-square with G - 1 degrees of freedom at the true ξ. NaN with fewer than 2 groups.
fn objective_at(sums: &[PoseSums], tau2: f64) -> f64 {
    if sums.iter().map(|s| s.3).sum::<usize>() < 2 {
        return f64::NAN;
    }
    let (mut a, mut b, mut u) = (0.0, 0.0, 0.0);
    for &(s, t, uu, _) in sums {
        let ap = 1.0 / (1.0 + tau2 * s);
        a += s * ap;
        b += t * ap;
        u += uu - tau2 * t * t * ap;
    }
    (u - b * b / a).max(0.0)
}

/// The groups' scatter about their own pose's mean beyond their standard errors: the
/// overdispersion within poses, `max(1, Q_within / (G - P))` (1 when it cannot be told).
/// A group's standard error comes from its pixels' spread over the square root of their
/// number, which neighbouring pixels' shared normals make too small.
fn within_pose_overdispersion(sums: &[PoseSums]) -> f64 {
    let seen: Vec<&PoseSums> = sums.iter().filter(|s| s.3 > 0).collect();
    let groups: usize = seen.iter().map(|s| s.3).sum();
    if groups <= seen.len() {
        return 1.0;
    }
    let q_within: f64 = seen.iter().map(|s| (s.2 - s.1 * s.1 / s.0).max(0.0)).sum();
    (q_within / (groups - seen.len()) as f64).max(1.0)
}

/// The sums with every group's variance scaled by `phi`.
fn scaled(sums: &[PoseSums], phi: f64) -> Vec<PoseSums> {
    sums.iter()
        .map(|&(s, t, u, n)| (s / phi, t / phi, u / phi, n))
        .collect()
}

/// The variance of the poses' offsets (DerSimonian-Laird from the spread of the poses' mean
/// log-albedos beyond their errors), 0 with fewer than two poses.
fn pose_variance(sums: &[PoseSums]) -> f64 {
    let seen: Vec<&PoseSums> = sums.iter().filter(|s| s.3 > 0).collect();
    if seen.len() < 2 {
        return 0.0;
    }
    let (sw, sw2, st) = seen
        .iter()
        .fold((0.0, 0.0, 0.0), |a, s| (a.0 + s.0, a.1 + s.0 * s.0, a.2 + s.1));
    let mean = st / sw;
    let q_between: f64 = seen.iter().map(|s| s.0 * (s.1 / s.0 - mean).powi(2)).sum();
    ((q_between - (seen.len() - 1) as f64) / (sw - sw2 / sw)).max(0.0)
}

/// The one-material objective at each ξ of the grid, the groups' variances scaled by `phi`
/// and the poses' offsets of variance `tau2`. Returns `(Q, groups)` per ξ.
fn one_material_objective<P: Borrow<FrameProfile>>(
    profiles: &[P],
    pose: &[usize],
    poses: usize,
    (phi, tau2): (f64, f64),
) -> Vec<(f64, usize)> {
    (0..xi_grid().len())
        .map(|k| {
            let sums = scaled(&pose_sums(profiles, pose, poses, k), phi);
            (objective_at(&sums, tau2), sums.iter().map(|s| s.3).sum())
        })
        .collect()
}

/// The groups' scatter within poses, the poses' misfit and a floor for it,
/// `(phi_within, tau2, tau2_floor)`, from the ξ the plain objective prefers (among the `ok`
/// ones), then held over the grid.
///
/// The floor, for two poses, is the variance the groups show within a pose: with
/// two poses the spread between them is not measurable at the ξ that makes them agree (it
/// is what picks that ξ), and what the model cannot explain between two distances along a
/// tilted object it does not explain better between two poses (objects.md, "Intervals that
/// hold": overdispersion from the object's own residuals).
fn misfit_scales<P: Borrow<FrameProfile>>(
    profiles: &[P],
    pose: &[usize],
    poses: usize,
    ok: &[bool],
) -> Option<(f64, f64, f64)> {
    let plain: Vec<f64> = one_material_objective(profiles, pose, poses, (1.0, 0.0))
        .iter()
        .zip(ok)
        .map(|(&(q, _), &e)| if e { q } else { f64::NAN })
        .collect();
    let (k0, _) = argmin(&plain)?;
    let at_k0 = pose_sums(profiles, pose, poses, k0);
    let phi_within = within_pose_overdispersion(&at_k0);
    let sums = scaled(&at_k0, phi_within);
    Some((phi_within, pose_variance(&sums), group_variance(&sums)))
}

/// The groups' variance (their harmonic mean), in log albedo squared, where there are exactly
/// two poses; 0 otherwise (one pose has no offset to bound; from three on, the poses' spread
/// about the ξ that fits them all is measured).
fn group_variance(sums: &[PoseSums]) -> f64 {
    let seen: Vec<&PoseSums> = sums.iter().filter(|s| s.3 > 0).collect();
    if seen.len() != 2 {
        return 0.0;
    }
    let (w, n) = seen.iter().fold((0.0, 0usize), |a, s| (a.0 + s.0, a.1 + s.3));
    n as f64 / w
}

/// Poses among the frames: their median distances, nearest first, each pose spanning at most
/// 5 % (and 50 mm) from its nearest frame, so that an object carried continuously through
/// the scene shows a pose every 5 % of distance it travels, as one moved in steps does at
/// each step. Returns each frame's pose (`usize::MAX` without a distance) and the number of
/// poses.
fn pose_labels<P: Borrow<FrameProfile>>(profiles: &[P]) -> (Vec<usize>, usize) {
    let mut order: Vec<(f64, usize)> = profiles
        .iter()
        .enumerate()
        .map(|(i, p)| (p.borrow().median_distance_mm, i))
        .filter(|(d, _)| d.is_finite())
        .collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut labels = vec![usize::MAX; profiles.len()];
    let mut pose = 0;
    let mut first = order.first().map_or(0.0, |o| o.0);
    for &(d, i) in &order {
        if d - first > (0.05 * first).max(50.0) {
            pose += 1;
            first = d;
        }
        labels[i] = pose;
    }
    (labels, if order.is_empty() { 0 } else { pose + 1 })
}

/// ξ as one material (physics.md §3, item 2), pooled over the frames given.
///
/// Opaque is the null hypothesis: an object is a layer only where its evidence rejects
/// ξ = 0. Otherwise the estimate is ξ 0 with an interval from 0 to what the data allow.
///
/// Where the data determine ξ (three groups or more, two poses or more, an interior
/// minimum), the interval is where `Q` rises by less than 3.84 times the overdispersion
/// `max(1, Q_min / (G - 2))` above its minimum (a profile-likelihood interval that widens
/// when the groups scatter more than their errors say), widened by half a grid step, and
/// `Q` carries the model's misfit between poses as a random offset per pose (issue 31,
/// item 4: what the model cannot explain between poses widens the interval), and
/// opaque is rejected when `Q(0)` lies above that level. Where they do not (physics.md §3
/// measured one frame of one tilted plane: a profile that falls through the truth), the
/// interval is every ξ.
pub fn one_material(profiles: &[FrameProfile]) -> Option<XiEstimate> {
    let pooled = one_material_pooled(profiles)?;
    Some(across_distance(profiles, pooled))
}

/// [`XiSettings::xi_model_error_sd`]'s default: `.venv/bin/python scripts/xi_model_error.py`
/// over every rendered scene `scripts/results` scores (the stepped_dev set among them).
pub const XI_MODEL_ERROR_SD: f64 = 0.082;

/// An estimate's interval with the model's error `sd` in quadrature on each side, about the
/// estimate (z 1.96): what a physical scene holds beyond the model, which the evidence of a
/// few poses cannot show. The model's error moves where ξ lies, not whether the pixels show
/// a second return at all: a layer whose own evidence rejects opaque stays a layer (its lower
/// end held just above [`OPAQUE_XI`]), an opaque one widens upwards only. [0, 1] and a given
/// ξ stay as they are.
pub fn with_model_error(e: XiEstimate, sd: f64) -> XiEstimate {
    if !(sd > 0.0) || e.interval == [0.0, 1.0] || e.method == XiMethod::Fixed {
        return e;
    }
    let pad = 1.96 * sd;
    let widen = |half: f64| (half * half + pad * pad).sqrt();
    let [lo, hi] = e.interval;
    let hi = (e.xi + widen(hi - e.xi)).min(1.0);
    let lo = if e.is_opaque() {
        lo
    } else {
        (e.xi - widen(e.xi - lo)).max(lo.min(OPAQUE_XI + XI_STEP_ABOVE_OPAQUE))
    };
    XiEstimate {
        interval: [lo, hi],
        note: format!(
            "{}; the model's error on rendered scenes (sd {sd:.3} in xi) included",
            e.note
        ),
        ..e
    }
}

/// How far above [`OPAQUE_XI`] a layer's widened interval stops ([`with_model_error`]).
const XI_STEP_ABOVE_OPAQUE: f64 = 0.01;

/// Fewest poses an object needs before its near and far poses are compared
/// ([`across_distance`]): two on each side, as each side must determine ξ by itself.
pub const POSES_TO_COMPARE: usize = 4;

/// The pooled estimate checked against the object's near poses and its far poses, each
/// estimated alone. The model's misfit between poses enters the pooled interval as a random
/// offset per pose; a misfit that grows with distance (light between a layer and a near wall,
/// a layer that scatters what it passes) is not random, and there the two sides' intervals
/// part. Then what the data cannot tell is which side is right: the interval spans both
/// sides' and the pooled one (objects.md, "Intervals that hold"); where one side is opaque
/// and the other a layer, the interval is every ξ.
fn across_distance(profiles: &[FrameProfile], pooled: XiEstimate) -> XiEstimate {
    let (pose, poses) = pose_labels(profiles);
    let determined = pooled.interval != [0.0, 1.0];
    if poses < POSES_TO_COMPARE || !determined {
        return pooled;
    }
    let frames = |far: bool| -> Vec<&FrameProfile> {
        profiles
            .iter()
            .zip(&pose)
            .filter(|(_, &k)| k != usize::MAX && (k >= poses / 2) == far)
            .map(|(p, _)| p)
            .collect()
    };
    let (near_frames, far_frames) = (frames(false), frames(true));
    let statistic = match split_statistic(&near_frames, &far_frames) {
        Some(q) if q > SIDES_PART_LEVEL => q,
        _ => return pooled,
    };
    // A side that alone leaves ξ open widens nothing beyond what the pooled interval says.
    let side = |f: &[&FrameProfile]| one_material_pooled(f).filter(|e| e.interval != [0.0, 1.0]);
    let (Some(near), Some(far)) = (side(&near_frames), side(&far_frames)) else {
        return pooled;
    };
    let lo = pooled.interval[0].min(near.interval[0]).min(far.interval[0]);
    let hi = pooled.interval[1].max(near.interval[1]).max(far.interval[1]);
    let disagreement = format!(
        "the near poses alone give xi {:.3} [{:.3}, {:.3}] and the far ones {:.3} [{:.3}, {:.3}], apart beyond chance (statistic {:.1} > {SIDES_PART_LEVEL:.2}): a misfit that changes with distance, so the interval spans both",
        near.xi, near.interval[0], near.interval[1], far.xi, far.interval[0], far.interval[1], statistic
    );
    if lo <= OPAQUE_XI {
        // One side does not reject opaque where the other finds a layer: the misfit is as
        // large as the layer's own effect, and where it puts ξ says nothing of where ξ is
        // (a diffuse transmitter's sides both fall short of it). No ξ is excluded.
        return XiEstimate {
            xi: 0.0,
            interval: [0.0, 1.0],
            note: format!(
                "taken as opaque, the data do not say otherwise: {disagreement}, one of them opaque: a misfit as large as the layer's effect, so no xi is excluded ({})",
                pooled.note
            ),
            ..pooled
        };
    }
    XiEstimate {
        interval: [lo, hi],
        note: format!("{}; {disagreement}", pooled.note),
        ..pooled
    }
}

/// The level of the near-and-far statistic ([`split_statistic`]) above which the two sides
/// part: chi-square with 2 degrees of freedom at 95 %. A side's own interval, from two poses,
/// can be narrow and off where its layer is faint; the statistic weighs each side by what its
/// evidence holds. Parting widens the interval, so a false alarm costs width, not coverage.
pub const SIDES_PART_LEVEL: f64 = 5.991_464_547_107_979;

/// [`one_material`] over the frames given, without the near-and-far check.
fn one_material_pooled<P: Borrow<FrameProfile>>(profiles: &[P]) -> Option<XiEstimate> {
    let grid = xi_grid();
    let ok = eligible(profiles);
    let (pose, poses) = pose_labels(profiles);
    let admissible = |obj: &[(f64, usize)]| -> Vec<f64> {
        obj.iter()
            .zip(&ok)
            .map(|(&(q, _), &e)| if e { q } else { f64::NAN })
            .collect()
    };
    let (phi_within, tau2, tau2_floor) = misfit_scales(profiles, &pose, poses, &ok)?;
    let obj = one_material_objective(profiles, &pose, poses, (phi_within, tau2));
    let q = admissible(&obj);
    let (kmin, _) = argmin(&q)?;
    let groups = obj[kmin].1;
    let estimate = |xi: f64, interval: [f64; 2], note: String| XiEstimate {
        xi,
        interval,
        method: XiMethod::OneMaterial,
        frames: profiles.len(),
        pixels: profiles.iter().map(|p| p.borrow().pixels).sum(),
        profile: grid.iter().copied().zip(q.iter().copied()).collect(),
        note,
    };
    if let Some(why) = undetermined(groups, poses) {
        // Every ξ: even the albedo bound that pins pixels at high ξ rests on the background
        // albedo `Lin` assumes, so it does not exclude them either.
        return Some(estimate(
            0.0,
            [0.0, 1.0],
            format!("taken as opaque, the data do not say otherwise: {why}"),
        ));
    }
    let xi = refine_minimum(&grid, &q, kmin);
    // The interval with the poses' misfit at least the groups' (`group_variance`): the
    // estimate stays where the measured misfit puts it, the interval says what the poses
    // cannot show.
    let wide = admissible(&one_material_objective(
        profiles,
        &pose,
        poses,
        (phi_within, tau2.max(tau2_floor)),
    ));
    let (kwide, qwide) = argmin(&wide)?;
    let phi = (qwide / (groups as f64 - 2.0)).max(1.0);
    let level = qwide + 3.84 * phi;
    let interval = cover(admissible_interval(&grid, &wide, kwide, level), xi);
    let edge = if at_admissible_edge(&q, kmin) {
        format!(
            "; the objective falls to xi {:.2}, the edge of what the model admits, so the interval runs on past it",
            grid[kmin]
        )
    } else {
        String::new()
    };
    let evidence = format!(
        "albedo consistency over {groups} groups in {} frame(s), {poses} poses; overdispersion {phi_within:.2} within poses and {phi:.2} left, pose misfit sd {:.3} in log albedo (at least {:.3}, the groups'){edge}",
        profiles.len(),
        tau2.sqrt(),
        tau2_floor.sqrt()
    );
    if wide[0] <= level || interval[0] <= OPAQUE_XI {
        return Some(estimate(
            0.0,
            [0.0, interval[1]],
            format!("taken as opaque: the evidence does not reject xi 0 ({evidence})"),
        ));
    }
    Some(estimate(xi, interval, evidence))
}

/// The level of [`same_material_statistic`] above which a frame's region is not the object
/// it would continue: chi-square with 2 degrees of freedom (one ξ and one albedo shared) at
/// 99.9 %, so that one object in a thousand frames is split, never pooled wrongly more often.
pub const SAME_MATERIAL_LEVEL: f64 = 13.82;

/// How much worse one material explains an object's evidence and a new frame's together than
/// each on its own: `min Q(joint) - min Q(object) - min Q(frame)`, the objectives with the
/// joint's overdispersion and pose misfit, over the ξ the joint admits. A likelihood-ratio
/// statistic, about chi-square with 2 degrees of freedom when the frame shows the object:
/// a region that takes another object's place (a swap between poses) exceeds
/// [`SAME_MATERIAL_LEVEL`] unless some ξ makes both albedos agree (then the data cannot tell).
/// `None` when the evidence holds too few groups to say.
pub fn same_material_statistic(object: &[FrameProfile], frame: &FrameProfile) -> Option<f64> {
    // The evidence by reference: an object pools up to `max_frames_pooled` frames, and this
    // runs for every region that may continue it, every frame.
    let object: Vec<&FrameProfile> = object.iter().collect();
    split_statistic(&object, &[frame])
}

/// How much worse one material explains two sets of frames together than each on its own:
/// `min Q(joint) - min Q(a) - min Q(b)`, the objectives with the joint's overdispersion and
/// pose misfit, over the ξ the joint admits; about chi-square with 2 degrees of freedom
/// where both show one material under the model. `None` when the evidence holds too few
/// groups to say.
fn split_statistic(a: &[&FrameProfile], b: &[&FrameProfile]) -> Option<f64> {
    let joint: Vec<&FrameProfile> = a.iter().chain(b).copied().collect();
    let ok = eligible(&joint);
    let (pose, poses) = pose_labels(&joint);
    let (phi, tau2, _) = misfit_scales(&joint, &pose, poses, &ok)?;
    let scales = (phi, tau2);
    let least = |profiles: &[&FrameProfile], pose: &[usize], poses: usize| -> Option<f64> {
        let q: Vec<f64> = one_material_objective(profiles, pose, poses, scales)
            .iter()
            .zip(&ok)
            .map(|(&(q, _), &e)| if e { q } else { f64::NAN })
            .collect();
        argmin(&q).map(|(_, v)| v)
    };
    let n = a.len();
    let q_joint = least(&joint, &pose, poses)?;
    let q_a = least(&joint[..n], &pose[..n], poses).unwrap_or(0.0);
    let q_b = least(&joint[n..], &pose[n..], poses).unwrap_or(0.0);
    Some((q_joint - q_a - q_b).max(0.0))
}

/// Why the albedo-consistency objective does not determine ξ, if it does not. A minimum at
/// the edge of the admissible range is an estimate like any other: the data prefer as
/// high a ξ as the model admits ([`at_admissible_edge`]), and the interval runs on to 1.
fn undetermined(groups: usize, poses: usize) -> Option<String> {
    if groups < 3 {
        Some(format!("{groups} pixel group(s): too few to compare albedos"))
    } else if poses < 2 {
        Some("the object has been seen in one pose only: one view of one surface does not determine xi (physics.md §3); move it to another distance or give xi".to_string())
    } else {
        None
    }
}

/// Whether the objective's least value `q[k]` lies next to an inadmissible ξ (not finite):
/// beyond it the model explains fewer of the object's pixels ([`admissible_interval`]).
/// ξ 0 is the physical end of the range, not an edge of what the data admit.
fn at_admissible_edge(q: &[f64], k: usize) -> bool {
    let inadmissible = |j: usize| q.get(j).is_none_or(|v| !v.is_finite());
    (k > 0 && inadmissible(k - 1)) || inadmissible(k + 1)
}

/// ξ fitted to frames with known foreground distances (paper Sec. V-A):
/// the noise-weighted squared error between predicted and observed readings
/// at the true distances, summed over frames. The interval is the larger of
/// the profile interval (`Δ SSE <= 3.84 σ²`) and the scatter of the frames'
/// own best ξ (`t · sd / sqrt(frames)`), so frame-to-frame systematics widen it.
pub fn calibrate(profiles: &[FrameProfile]) -> Option<XiEstimate> {
    let grid = xi_grid();
    let sse: Vec<f64> = (0..grid.len())
        .map(|k| {
            profiles
                .iter()
                .map(|p| p.truth[k].weighted_sse / p.truth[k].weight.max(1e-300) * p.truth[k].count as f64)
                .sum::<f64>()
        })
        .collect();
    let count: usize = profiles.iter().map(|p| p.truth[0].count).sum();
    if count == 0 {
        return None;
    }
    let (kmin, smin) = argmin(&sse)?;
    let xi = refine_minimum(&grid, &sse, kmin);
    let n = count.max(2);
    let sigma2 = smin / (n as f64 - 1.0);
    let mut interval = cover(threshold_interval(&grid, &sse, kmin, smin + 3.84 * sigma2), xi);
    let per_frame: Vec<f64> = profiles
        .iter()
        .filter_map(|p| {
            let s: Vec<f64> = p.truth.iter().map(|t| t.weighted_sse / t.weight.max(1e-300)).collect();
            let (k, _) = argmin(&s)?;
            (p.truth[k].count > 0).then(|| refine_minimum(&grid, &s, k))
        })
        .collect();
    if per_frame.len() >= 2 {
        let m = per_frame.iter().sum::<f64>() / per_frame.len() as f64;
        let sd = (per_frame.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (per_frame.len() - 1) as f64).sqrt();
        let half = student_t975(per_frame.len() - 1) * sd / (per_frame.len() as f64).sqrt();
        interval = [interval[0].min(xi - half).max(0.0), interval[1].max(xi + half).min(1.0)];
    }
    Some(XiEstimate {
        xi,
        interval,
        method: XiMethod::Calibrated,
        frames: profiles.len(),
        pixels: n,
        profile: grid
            .iter()
            .enumerate()
            .map(|(k, &x)| {
                let (s, c) = profiles
                    .iter()
                    .fold((0.0, 0usize), |a, p| (a.0 + p.truth[k].sse, a.1 + p.truth[k].count));
                (x, (s / c.max(1) as f64).sqrt())
            })
            .collect(),
        note: format!(
            "fitted to known foreground distances in {} frame(s); the profile is the model-vs-measurement RMS (mm)",
            profiles.len()
        ),
    })
}

/// The paper's Eq. 12: per ξ, the summed squared residual of the per-pixel
/// best fits. Degenerate (every ξ fits each pixel): the interval is every ξ
/// within 5 % of the minimum, and the note reports the profile's relative range.
pub fn eq12_residual(profiles: &[FrameProfile]) -> Option<XiEstimate> {
    if profiles.is_empty() {
        return None;
    }
    let grid = xi_grid();
    let r: Vec<f64> = (0..grid.len())
        .map(|k| profiles.iter().map(|p| p.eq12[k]).sum())
        .collect();
    let (kmin, rmin) = argmin(&r)?;
    let pixels = profiles.iter().map(|p| p.pixels).sum::<usize>().max(1);
    let level = (rmin.sqrt() + (pixels as f64).sqrt()).powi(2); // RMS within 1 mm of its minimum
    let interval = threshold_interval(&grid, &r, kmin, level);
    let flat = eq12_flat_range(&r, pixels);
    Some(XiEstimate {
        xi: grid[kmin],
        interval,
        method: XiMethod::Eq12Residual,
        frames: profiles.len(),
        pixels,
        profile: grid.iter().copied().zip(r.iter().map(|v| (v / pixels as f64).sqrt())).collect(),
        note: format!("Eq. 12 residual RMS is within 1 mm of its minimum for every xi in [{:.2}, {:.2}]: it cannot pick xi (physics.md §3)", flat[0], flat[1]),
    })
}

/// The ξ range over which the Eq. 12 residual RMS (over `pixels`) stays
/// within 1 mm of its minimum: how flat, and so how uninformative, it is.
pub fn eq12_flat_range(r: &[f64], pixels: usize) -> [f64; 2] {
    let grid = xi_grid();
    let n = pixels.max(1) as f64;
    let rms: Vec<f64> = r.iter().map(|v| (v / n).sqrt()).collect();
    let Some((k, m)) = argmin(&rms) else { return [0.0, 1.0] };
    let iv = threshold_interval(&grid, &rms, k, m + 1.0);
    [iv[0], iv[1]]
}

fn argmin(v: &[f64]) -> Option<(usize, f64)> {
    v.iter()
        .copied()
        .enumerate()
        .filter(|(_, x)| x.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// Parabolic interpolation of the minimum between the grid's neighbours.
fn refine_minimum(grid: &[f64], v: &[f64], k: usize) -> f64 {
    if k == 0 || k + 1 >= grid.len() || !v[k - 1].is_finite() || !v[k + 1].is_finite() {
        return grid[k];
    }
    let (x0, x1, x2) = (grid[k - 1], grid[k], grid[k + 1]);
    let (y0, y1, y2) = (v[k - 1], v[k], v[k + 1]);
    let den = (x0 - x1) * (x0 - x2) * (x1 - x2);
    let a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den;
    let b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den;
    if a <= 0.0 {
        return x1;
    }
    (-b / (2.0 * a)).clamp(x0, x2)
}

/// [`threshold_interval`] over an objective that is not finite where ξ is inadmissible
/// ([`eligible`]): a run that reaches an inadmissible ξ does not end there. There the model
/// explains fewer of the object's pixels (no root, or an albedo beyond the bound), which is
/// what an object it does not describe shows too (a box between a layer and the latched
/// wall, a frosted layer): the albedo consistency has not rejected those ξ, so the interval
/// runs on to that end of the range.
fn admissible_interval(grid: &[f64], v: &[f64], k: usize, level: f64) -> [f64; 2] {
    let [mut lo, mut hi] = threshold_interval(grid, v, k, level);
    let (run_lo, run_hi) = run_below(v, k, level);
    if run_lo > 0 && !v[run_lo - 1].is_finite() {
        lo = 0.0;
    }
    if run_hi + 1 < v.len() && !v[run_hi + 1].is_finite() {
        hi = 1.0;
    }
    [lo, hi]
}

/// The first and last index of the connected run of finite values `<= level` around `k`.
fn run_below(v: &[f64], k: usize, level: f64) -> (usize, usize) {
    let below = |j: usize| v[j].is_finite() && v[j] <= level;
    let mut lo = k;
    while lo > 0 && below(lo - 1) {
        lo -= 1;
    }
    let mut hi = k;
    while hi + 1 < v.len() && below(hi + 1) {
        hi += 1;
    }
    (lo, hi)
}

/// The connected run of grid points around `k` with value `<= level`, extended
/// by linear interpolation to the crossing and by half a grid step.
fn threshold_interval(grid: &[f64], v: &[f64], k: usize, level: f64) -> [f64; 2] {
    let (lo, hi) = run_below(v, k, level);
    let cross = |a: usize, b: usize| -> f64 {
        if !v[b].is_finite() {
            return grid[a];
        }
        let t = ((level - v[a]) / (v[b] - v[a])).clamp(0.0, 1.0);
        grid[a] + t * (grid[b] - grid[a])
    };
    // Widened by half the local grid step: the grid resolves no finer.
    let lo_x = if lo > 0 {
        cross(lo, lo - 1) - 0.5 * (grid[lo] - grid[lo - 1])
    } else {
        0.0
    };
    let hi_x = if hi + 1 < grid.len() {
        cross(hi, hi + 1) + 0.5 * (grid[hi + 1] - grid[hi])
    } else {
        1.0
    };
    [lo_x.max(0.0), hi_x.min(1.0)]
}

/// The interval widened, if need be, to contain the estimate (a parabolic
/// minimum can sit between grid points outside a coarse crossing).
fn cover(iv: [f64; 2], xi: f64) -> [f64; 2] {
    [iv[0].min(xi), iv[1].max(xi)]
}

/// What an object's pooled evidence says at every ξ of [`xi_grid`], for weighing hypotheses
/// about it against each other (known materials, opaque, unknown: `catalog`): the
/// one-material objective as a chi-square and the pooled albedo it implies.
#[derive(Debug, Clone, PartialEq)]
pub struct AlbedoEvidence {
    /// The ξ grid ([`xi_grid`]).
    pub xi: Vec<f64>,
    /// The one-material objective `Q` (the groups' scatter within poses and the poses'
    /// misfit carried as in [`one_material`]), divided by the overdispersion left at its
    /// minimum: about chi-square, so `exp(-Q / 2)` is a likelihood up to a constant. NaN
    /// where the ξ is not admissible (more pixels pinned at a bound than at the best ξ).
    pub q: Vec<f64>,
    /// The pooled mean of the groups' median `ln rho_f` (the generalised least-squares mean
    /// that `Q` is the scatter about), NaN where no group has one.
    pub log_albedo: Vec<f64>,
    /// Its standard error (with the same overdispersion and pose misfit).
    pub log_albedo_se: Vec<f64>,
    /// Poses among the frames.
    pub poses: usize,
}

impl AlbedoEvidence {
    /// The albedo the evidence implies at `xi` (linear between grid points), with the
    /// standard error of its log: `None` where the grid has none there.
    pub fn albedo_at(&self, xi: f64) -> Option<(f64, f64)> {
        let (m, s) = (
            interpolate(&self.xi, &self.log_albedo, xi)?,
            interpolate(&self.xi, &self.log_albedo_se, xi)?,
        );
        Some((m.exp(), s))
    }
}

/// `v` at `x` on `grid`, linear between its two neighbours (both finite), `None` outside.
pub fn interpolate(grid: &[f64], v: &[f64], x: f64) -> Option<f64> {
    let j = grid.iter().position(|&g| g >= x)?;
    if grid[j] == x || j == 0 {
        return (grid[j] == x && v[j].is_finite()).then_some(v[j]);
    }
    let (x0, x1, y0, y1) = (grid[j - 1], grid[j], v[j - 1], v[j]);
    if !(y0.is_finite() && y1.is_finite()) {
        return None;
    }
    Some(y0 + (y1 - y0) * (x - x0) / (x1 - x0))
}

/// The evidence of `profiles` at every ξ ([`AlbedoEvidence`]); `None` without a group to
/// compare at any ξ.
pub fn albedo_evidence(profiles: &[FrameProfile]) -> Option<AlbedoEvidence> {
    let grid = xi_grid();
    let ok = eligible(profiles);
    let (pose, poses) = pose_labels(profiles);
    let plain = one_material_objective(profiles, &pose, poses, (1.0, 0.0));
    let plain: Vec<f64> = plain
        .iter()
        .zip(&ok)
        .map(|(&(q, _), &e)| if e { q } else { f64::NAN })
        .collect();
    let (k0, _) = argmin(&plain)?;
    let at_k0 = pose_sums(profiles, &pose, poses, k0);
    let phi_within = within_pose_overdispersion(&at_k0);
    let tau2 = pose_variance(&scaled(&at_k0, phi_within));
    let (mut q, mut mean, mut var, mut groups) = (vec![], vec![], vec![], vec![]);
    for (k, &admissible) in ok.iter().enumerate() {
        let sums = scaled(&pose_sums(profiles, &pose, poses, k), phi_within);
        let (mut a, mut b) = (0.0, 0.0);
        for &(s, t, _, _) in &sums {
            let ap = 1.0 / (1.0 + tau2 * s);
            a += s * ap;
            b += t * ap;
        }
        let g: usize = sums.iter().map(|s| s.3).sum();
        q.push(if admissible {
            objective_at(&sums, tau2)
        } else {
            f64::NAN
        });
        mean.push(if g > 0 { b / a } else { f64::NAN });
        var.push(if g > 0 { 1.0 / a } else { f64::NAN });
        groups.push(g);
    }
    let (kmin, qmin) = argmin(&q)?;
    // The scatter left at the best ξ beyond what the groups' errors and the poses' misfit
    // explain (one degree of freedom for the mean, one for ξ).
    let phi = if groups[kmin] > 2 {
        (qmin / (groups[kmin] as f64 - 2.0)).max(1.0)
    } else {
        1.0
    };
    Some(AlbedoEvidence {
        xi: grid,
        q: q.iter().map(|v| v / phi).collect(),
        log_albedo: mean,
        log_albedo_se: var.iter().map(|v| (v * phi).sqrt()).collect(),
        poses,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_model_error_widens_an_interval_about_its_estimate_and_keeps_a_layer_a_layer() {
        let e = |xi: f64, interval: [f64; 2]| XiEstimate {
            xi,
            interval,
            method: XiMethod::OneMaterial,
            frames: 3,
            pixels: 100,
            profile: vec![],
            note: String::new(),
        };
        // 0.03 on each side and 1.96 * 0.1 of model error: sqrt(0.03^2 + 0.196^2) = 0.198.
        let w = with_model_error(e(0.6, [0.57, 0.63]), 0.1);
        assert!((w.interval[0] - (0.6 - 0.198_282)).abs() < 1e-5, "{:?}", w.interval);
        assert!((w.interval[1] - (0.6 + 0.198_282)).abs() < 1e-5, "{:?}", w.interval);
        assert!(!w.is_opaque() && w.xi == 0.6);
        // A layer near opaque stays a layer; an opaque one widens upwards only.
        let low = with_model_error(e(0.2, [0.15, 0.25]), 0.1);
        assert!(!low.is_opaque() && (low.interval[0] - 0.11).abs() < 1e-12);
        let opaque = with_model_error(e(0.0, [0.0, 0.3]), 0.1);
        assert_eq!(opaque.interval[0], 0.0);
        assert!(opaque.interval[1] > 0.3 && opaque.is_opaque());
        // Nothing to widen: every xi, a given xi, or no model error.
        assert_eq!(with_model_error(e(0.0, [0.0, 1.0]), 0.1).interval, [0.0, 1.0]);
        assert_eq!(with_model_error(XiEstimate::fixed(0.5), 0.1).interval, [0.5, 0.5]);
        assert_eq!(with_model_error(e(0.6, [0.57, 0.63]), 0.0).interval, [0.57, 0.63]);
    }

    #[test]
    fn parabola_minimum_is_found_between_grid_points() {
        let grid = xi_grid();
        let v: Vec<f64> = grid.iter().map(|x| (x - 0.437).powi(2)).collect();
        let (k, _) = argmin(&v).unwrap();
        assert!((refine_minimum(&grid, &v, k) - 0.437).abs() < 1e-9);
        // The crossings at 0.337 and 0.537 (linear interpolation errs by < 0.003 here),
        // widened by half the 0.02 grid step.
        let iv = threshold_interval(&grid, &v, k, 0.01);
        assert!(
            (iv[0] - (0.337 - 0.01)).abs() < 0.003 && (iv[1] - (0.537 + 0.01)).abs() < 0.003,
            "{iv:?}"
        );
        assert_eq!(cover([0.4, 0.5], 0.52), [0.4, 0.52]);
    }

    /// An objective inadmissible (NaN) above ξ 0.55, where the model would explain fewer
    /// pixels: a run that reaches it does not end there (the albedo consistency has not
    /// rejected those ξ), one that ends before it by the data does.
    #[test]
    fn an_interval_that_reaches_the_inadmissible_range_runs_on_to_its_end() {
        let grid = xi_grid();
        let v: Vec<f64> = grid
            .iter()
            .map(|&x| if x > 0.55 { f64::NAN } else { (x / 0.1).powi(2) })
            .collect();
        let (k, _) = argmin(&v).unwrap();
        // Rising to the edge: the data end the run at ξ 0.3 (level 9), before the edge.
        assert!(admissible_interval(&grid, &v, k, 9.0)[1] < 0.35);
        // Still under the level at the edge: every ξ above it stays possible.
        assert_eq!(admissible_interval(&grid, &v, k, 40.0), [0.0, 1.0]);
        assert!(threshold_interval(&grid, &v, k, 40.0)[1] < 0.6);
    }

    /// An objective that falls all the way to where the model stops admitting ξ (a faint,
    /// high-ξ layer whose physics the model misses a little) is an estimate at that edge,
    /// its interval from where the data rise above the level on to 1; an interior minimum
    /// is no edge, and ξ 0 is the range's physical end, not an edge.
    #[test]
    fn a_minimum_at_the_admissible_edge_is_an_estimate_whose_interval_runs_on() {
        let grid = xi_grid();
        let v: Vec<f64> = grid
            .iter()
            .map(|&x| if x > 0.9 { f64::NAN } else { ((0.9 - x) / 0.05).powi(2) })
            .collect();
        let (k, _) = argmin(&v).unwrap();
        assert!(at_admissible_edge(&v, k));
        assert!((grid[k] - 0.9).abs() < 0.03, "{}", grid[k]);
        let [lo, hi] = admissible_interval(&grid, &v, k, v[k] + 3.84);
        assert_eq!(hi, 1.0);
        assert!((0.78..0.85).contains(&lo), "{lo}");
        let interior: Vec<f64> = grid.iter().map(|&x| ((x - 0.5) / 0.05).powi(2)).collect();
        let (k, _) = argmin(&interior).unwrap();
        assert!(!at_admissible_edge(&interior, k));
        // Rising from ξ 0: opaque, its minimum at the range's physical end.
        assert!(!at_admissible_edge(&grid, 0));
        assert_eq!(undetermined(9, 2), None);
        assert!(undetermined(9, 1).is_some() && undetermined(2, 3).is_some());
    }

    /// Unit rays of a `w x h` pinhole camera of focal length `f` pixels, its principal point
    /// at the image's centre.
    fn centred_rays(w: usize, h: usize, f: f64) -> ImageBuf<Vector3<f64>> {
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        ImageBuf {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| Vector3::new(((i % w) as f64 - cx) / f, ((i / w) as f64 - cy) / f, 1.0).normalize())
                .collect(),
        }
    }

    /// A box's corner, one face seen face-on and the other nearly edge-on (80° from the view):
    /// the first face's pixels read a usable normal at every ξ alike, the grazing face's do not
    /// (cos of incidence under 0.3), and are left out of the albedo statistics.
    #[test]
    fn a_face_seen_edge_on_is_not_readable_and_one_seen_face_on_is() {
        let (w, h, f) = (48usize, 32usize, 60.0);
        let rays = centred_rays(w, h, f);
        // Left: z = 2000; right of x = 0: z = 2000 + x tan(80°), a face receding steeply.
        let steep = 80f64.to_radians().tan();
        let observations = ImageBuf {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| {
                    let r = rays.data[i];
                    let t = if r.x < 0.0 {
                        2000.0 / r.z
                    } else {
                        2000.0 / (r.z - steep * r.x)
                    };
                    (t > 0.0 && t < 1e5).then_some(PixelObservation {
                        distance_mm: t,
                        ir: 1000.0,
                        background_distance_mm: 3000.0,
                        background_ir: 800.0,
                        emitted_light: 1e10,
                        wall_view_factor: 0.0,
                        diffuse_lobe: None,
                    })
                })
                .collect(),
        };
        let mask = ImageBuf {
            width: w,
            height: h,
            data: observations.data.iter().map(Option::is_some).collect(),
        };
        let sample = FrameSample {
            observations,
            rays,
            truth_mm: None,
            stride: 1,
        };
        let readable = readable_normals(&sample, &reading_planes(&sample, &mask, &[3, 6, 12, 18], 1));
        let rows = 6..h - 6;
        assert!(
            rows.clone().all(|v| (4..16).all(|u| readable[v * w + u])),
            "the face seen face-on"
        );
        // Beyond the narrowest window's reach of the corner (3 pixels): windows there hold only
        // the edge-on face.
        let edge_on: Vec<usize> = (0..w)
            .filter(|&u| sample.rays.data[16 * w + u].x > 4.0 / f && mask.data[16 * w + u])
            .collect();
        assert!(!edge_on.is_empty());
        assert!(
            rows.clone().all(|v| edge_on.iter().all(|&u| !readable[v * w + u])),
            "the face seen edge-on"
        );
    }

    /// The profile of a sample cut to its observations is the profile of the whole lattice:
    /// a tilted patch in the middle of an empty lattice.
    #[test]
    fn a_lattice_cut_to_its_observations_gives_the_same_profile() {
        let (w, h, f) = (40usize, 30usize, 50.0);
        let rays = centred_rays(w, h, f);
        let patch = |i: usize| (7..23).contains(&(i / w)) && (8..31).contains(&(i % w));
        let observations = ImageBuf {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| {
                    let r = rays.data[i];
                    // A layer at z = 1200 + 0.3 x, reading farther by a ξ-dependent share.
                    let t = 1200.0 / (r.z - 0.3 * r.x) + 40.0 + (i % 7) as f64;
                    patch(i).then_some(PixelObservation {
                        distance_mm: t,
                        ir: 900.0 + (i % 5) as f64 * 10.0,
                        background_distance_mm: 2500.0,
                        background_ir: 700.0,
                        emitted_light: 3e9,
                        wall_view_factor: 0.0,
                        diffuse_lobe: None,
                    })
                })
                .collect(),
        };
        let sample = FrameSample {
            observations,
            rays,
            truth_mm: None,
            stride: 1,
        };
        let settings = XiSettings::default();
        let cut = sample
            .around_observations(settings.normal_block_steps)
            .expect("a smaller lattice");
        assert_eq!((cut.observations.width, cut.observations.height), (27, 18));
        assert_eq!(cut.observations.data.iter().flatten().count(), 16 * 23);
        let model = ForwardModel::physical(crate::physics::sensor::Sensor::sr4000());
        let bounds = InversionBounds::default();
        let whole = ProfileFrame::new(&model, &bounds, &sample, &settings, ProfileUse::Estimation).profile();
        let profile = frame_profile(&model, &bounds, &sample, &settings, ProfileUse::Estimation);
        assert!(whole.groups.iter().flatten().any(|g| g.count > 0));
        assert_eq!(format!("{whole:?}"), format!("{profile:?}"));
    }

    #[test]
    fn t_quantiles() {
        assert!((student_t975(1) - 12.706).abs() < 1e-9);
        assert!((student_t975(1000) - 1.96).abs() < 0.01);
    }

    #[test]
    fn group_stats_are_robust() {
        let mut v: Vec<f64> = (0..100).map(|k| (k as f64 - 49.5) * 0.001).collect();
        v.push(50.0);
        let g = group_stat(v, 10);
        assert!(g.median.abs() < 0.001 && g.std_error < 0.01 && g.count == 101);
        assert!(group_stat(vec![1.0, 2.0], 10).median.is_nan());
    }
}
