//! The paper's inversion written plainly (Eq. 8-11): for each translucent
//! pixel, the foreground distance on a 1 mm grid over `[d_min, db)` whose
//! predicted reading is nearest the observed one. The benchmarks time it
//! beside the pipeline's inversion and check that both give the same depths;
//! nothing else uses it. Likewise for the multi-frequency path: the plain
//! grid fit of two returns per pixel ([`multi_frequency_grid`]).

use serde::Serialize;

use crate::physics::inversion::{albedo_cos, predicted_reading};
use crate::physics::{ForwardModel, ImageBuf, InversionBounds, PixelObservation, Sensor};
use crate::pipeline::multifreq::{MultiFrequencyStage, PhasorFrame, PixelInputs};
use crate::pipeline::{Observed, Pipeline};

/// The grid's step, mm.
pub const GRID_STEP_MM: f64 = 1.0;

/// One pixel by the plain grid: `(df, |residual|)` of the grid point whose predicted
/// reading is nearest the observed one (wrapped), among those with `0 < X <= max`.
pub fn grid_search(
    model: &ForwardModel,
    obs: &PixelObservation,
    xi: f64,
    bounds: &InversionBounds,
) -> Option<(f64, f64)> {
    let lo = bounds.min_distance_mm;
    let hi = obs.background_distance_mm - bounds.min_separation_mm;
    if !(hi > lo) || !obs.distance_mm.is_finite() || !obs.ir.is_finite() {
        return None;
    }
    let mut best: Option<(f64, f64)> = None;
    let n = ((hi - lo) / GRID_STEP_MM).floor() as usize;
    for k in 0..=n {
        let df = lo + GRID_STEP_MM * k as f64;
        let Some(x) = albedo_cos(model, obs, df, xi, bounds.max_albedo_cos) else {
            continue;
        };
        if x <= 0.0 {
            continue;
        }
        let pred = predicted_reading(model, obs, df, xi, x);
        let r = model.sensor.wrapped_difference_mm(pred, obs.distance_mm).abs();
        if r.is_finite() && best.is_none_or(|(_, b)| r < b) {
            best = Some((df, r));
        }
    }
    best
}

/// The grid search over every translucent pixel of a frame: ray distances, mm
/// (NaN where no grid point is admissible), and the per-pixel residual, mm.
pub fn recover_per_pixel(pipeline: &Pipeline, obs: &Observed, xi: f64) -> (ImageBuf<f64>, ImageBuf<f64>) {
    let c = &pipeline.config;
    let mut df = ImageBuf::filled(obs.mask.width, obs.mask.height, f64::NAN);
    let mut res = df.clone();
    for (i, o) in obs.observations.iter() {
        if let Some((d, r)) = grid_search(&c.model, o, xi, &c.bounds) {
            df.data[i] = d;
            res.data[i] = r;
        }
    }
    (df, res)
}

/// How the fast path's per-pixel depths compare with the grid's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Agreement {
    /// Pixels compared: the fast path recovered one root, and the grid's
    /// best point fits to within its own resolution (`|residual| <= 1 mm`).
    pub compared: usize,
    /// Of those, pixels whose depths differ by more than `tolerance_mm`.
    pub disagree: usize,
    /// Largest difference, mm.
    pub max_diff_mm: f64,
    /// The tolerance, mm.
    pub tolerance_mm: f64,
    /// Pixels the fast path recovered that have several roots (the root rule,
    /// not the search, chooses there; not compared).
    pub several_roots: usize,
}

impl Agreement {
    /// Nothing compared yet, at `tolerance_mm`.
    fn within(tolerance_mm: f64) -> Self {
        Self {
            compared: 0,
            disagree: 0,
            max_diff_mm: 0.0,
            tolerance_mm,
            several_roots: 0,
        }
    }

    /// Counts one pixel whose depths differ by `diff_mm`.
    fn add(&mut self, diff_mm: f64) {
        self.compared += 1;
        self.max_diff_mm = self.max_diff_mm.max(diff_mm);
        self.disagree += usize::from(diff_mm > self.tolerance_mm);
    }
}

/// Compares per-pixel ray distances `fast` (NaN where none) with the grid's.
/// Pixels with several roots (`several[i]`) are left out: there the pipeline's
/// root rule (nearest the reading) and the grid's best residual may choose differently.
pub fn agreement(fast: &ImageBuf<f64>, several: &[bool], grid: &ImageBuf<f64>, grid_res: &ImageBuf<f64>) -> Agreement {
    let mut a = Agreement::within(1.0);
    for i in 0..fast.len() {
        if !fast.data[i].is_finite() {
            continue;
        }
        if several[i] {
            a.several_roots += 1;
            continue;
        }
        if !(grid_res.data[i] <= GRID_STEP_MM) {
            continue;
        }
        a.add((fast.data[i] - grid.data[i]).abs());
    }
    a
}

/// The inversions of ξ estimation written plainly: the grid search at every ξ
/// of [`crate::physics::translucency::xi_grid`] over the pixels ξ estimation
/// samples (the plane fits that follow are not included). Returns the pixels inverted.
pub fn xi_grid_inversions(pipeline: &Pipeline, obs: &Observed) -> usize {
    let c = &pipeline.config;
    let sample = crate::physics::translucency::FrameSample::from_image(
        &obs.observations,
        pipeline.rays(),
        None,
        c.xi_settings.max_pixels_per_frame,
    );
    let mut n = 0;
    for xi in crate::physics::translucency::xi_grid() {
        for o in sample.observations.data.iter().flatten() {
            n += grid_search(&c.model, o, xi, &c.bounds).is_some() as usize;
        }
    }
    n
}

/// The plain per-pixel fit of two returns against the latched background
/// (physics.md §7) over every pixel the multi-frequency path inverts: the
/// layer's distance on a 1 mm grid over `[d_min, db - separation]`, its
/// return `a >= 0` and `t = ξ²` in `[0, 1]` by least squares in closed form
/// at each point. Returns each pixel's `d1`, mm (NaN where not changed).
pub fn multi_frequency_grid(stage: &MultiFrequencyStage, frame: &PhasorFrame) -> ImageBuf<f64> {
    let k = &stage.intrinsics;
    let sensors: Vec<Sensor> = stage
        .config
        .frequencies_hz
        .iter()
        .map(|&f| Sensor::new(f, stage.config.model.sensor.waveform))
        .collect();
    let delay = stage.config.model.options.subsurface_delay_mm;
    let scan = &stage.config.scan;
    let mut d1 = ImageBuf::filled(k.width, k.height, f64::NAN);
    for i in 0..d1.len() {
        let Some(inputs) = stage.pixel_inputs(frame, i) else {
            continue;
        };
        if !stage.changed(&inputs) {
            continue;
        }
        let (lo, hi) = (
            scan.min_distance_mm,
            inputs.background_distance_mm - scan.min_separation_mm,
        );
        let n = ((hi - lo) / GRID_STEP_MM).floor().max(0.0) as usize;
        let mut best = (f64::NAN, f64::INFINITY);
        for step in 0..=n {
            let d = lo + GRID_STEP_MM * step as f64;
            let chi = two_returns_at(&sensors, delay, &inputs, d);
            if chi < best.1 {
                best = (d, chi);
            }
        }
        d1.data[i] = best.0;
    }
    d1
}

/// `min_{a >= 0, 0 <= t <= 1} sum_k |M_k - a u_k(d) - t B_k|^2 / sigma_k^2`: the
/// normal equations' solution where it is admissible, else the best edge.
fn two_returns_at(sensors: &[Sensor], delay_mm: f64, p: &PixelInputs, d: f64) -> f64 {
    let (mut uu, mut ub, mut um, mut bb, mut bm, mut mm) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for (kk, s) in sensors.iter().enumerate() {
        let w = 1.0 / p.noise_sigma[kk].powi(2);
        let u = s.buckets(1.0, d + delay_mm);
        let (b, m) = (p.background[kk], p.measured[kk]);
        uu += w * (u.a * u.a + u.b * u.b);
        ub += w * (u.a * b.a + u.b * b.b);
        um += w * (u.a * m.a + u.b * m.b);
        bb += w * (b.a * b.a + b.b * b.b);
        bm += w * (b.a * m.a + b.b * m.b);
        mm += w * (m.a * m.a + m.b * m.b);
    }
    let chi = |a: f64, t: f64| mm - 2.0 * a * um - 2.0 * t * bm + a * a * uu + 2.0 * a * t * ub + t * t * bb;
    let det = uu * bb - ub * ub;
    if det > 0.0 {
        let (a, t) = ((um * bb - bm * ub) / det, (bm * uu - um * ub) / det);
        if a >= 0.0 && (0.0..=1.0).contains(&t) {
            return chi(a, t);
        }
    }
    let a_at = |t: f64| if uu > 0.0 { ((um - t * ub) / uu).max(0.0) } else { 0.0 };
    let t_alone = if bb > 0.0 { (bm / bb).clamp(0.0, 1.0) } else { 0.0 };
    [chi(0.0, t_alone), chi(a_at(0.0), 0.0), chi(a_at(1.0), 1.0)]
        .into_iter()
        .fold(f64::INFINITY, f64::min)
}

/// How the multi-frequency path's layer distances (`fast`, ray distance, mm, NaN
/// off the mask) compare with the grid's.
pub fn multi_frequency_agreement(fast: &ImageBuf<f64>, grid: &ImageBuf<f64>) -> Agreement {
    let mut a = Agreement::within(1.0);
    for (f, g) in fast.data.iter().zip(&grid.data) {
        if !(f.is_finite() && g.is_finite()) {
            continue;
        }
        a.add((f - g).abs());
    }
    a
}
