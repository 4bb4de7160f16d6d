//! Inverting the two-layer model per translucent pixel (paper Eq. 8-11):
//! for a hypothesised translucency ξ, the foreground distance whose predicted
//! reading matches the observed one, within the physical bounds.

use serde::{Deserialize, Serialize};

use super::model::{ForwardModel, IrMode, LayerScene, ModelOptions};
use super::sensor::Waveform;
use super::trig::sin_cos;

mod lanes;
mod phasor;
pub use lanes::{foreground_distances, PixelsOverXi};
use phasor::PhasorModel;

/// What is known at one translucent pixel (physics.md §3).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelObservation {
    /// `d`: the reading with the object in place, ray distance, mm.
    pub distance_mm: f64,
    /// `I`: the IR value with the object in place, counts.
    pub ir: f64,
    /// `db`: the latched background's ray distance, mm.
    pub background_distance_mm: f64,
    /// `Ib`: the latched background's IR value, counts.
    pub background_ir: f64,
    /// `Lin`: emitted light toward this pixel (Eq. 13), counts mm^2.
    pub emitted_light: f64,
    /// `F`: the view factor from the background point to the layer, where the model's
    /// [`ModelOptions::wall_interreflection`] asks for it (0 until it is known).
    pub wall_view_factor: f64,
    /// What the pixel sees through a frosted layer's lobe, where the model's
    /// [`ModelOptions::diffuse_transmission`] asks for it and the layer's outline is known
    /// ([`super::diffuse::lobe_returns`]); `None`: the layer taken as filling the view.
    pub diffuse_lobe: Option<super::diffuse::LobeTable>,
}

impl PixelObservation {
    /// The scene along this pixel's ray for a hypothesis `(df, xi, X)`, with
    /// the background's `Xb` from its IR (less the model's IR offset).
    pub fn layer_scene(&self, df: f64, xi: f64, x: f64, ambient_offset: f64) -> LayerScene {
        LayerScene {
            foreground_distance_mm: df,
            background_distance_mm: self.background_distance_mm,
            translucency: xi,
            foreground_albedo_cos: x,
            background_albedo_cos: self.background_albedo_cos(ambient_offset),
            emitted_light: self.emitted_light,
            wall_view_factor: self.wall_view_factor,
            diffuse_lobe: self.diffuse_lobe.as_ref().map(|t| t.at(df)),
        }
    }

    /// `Xb = Ib db^2 / Lin`, the background's albedo times incidence cosine.
    pub fn background_albedo_cos(&self, ambient_offset: f64) -> f64 {
        let db = self.background_distance_mm;
        (self.background_ir - ambient_offset).max(0.0) * db * db / self.emitted_light
    }
}

/// Physical bounds of the search (physics.md §3).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct InversionBounds {
    /// `d_min`: nearest foreground distance considered, mm.
    pub min_distance_mm: f64,
    /// Upper bound of `X = rho_f cos(theta_f)` (1 for a physical albedo).
    pub max_albedo_cos: f64,
    /// Step of the scan that brackets roots before they are refined, mm.
    pub scan_step_mm: f64,
    /// Closest the foreground may come to the background, mm (`df < db`).
    pub min_separation_mm: f64,
}

impl Default for InversionBounds {
    fn default() -> Self {
        Self {
            min_distance_mm: 100.0,
            max_albedo_cos: 1.0,
            scan_step_mm: 60.0,
            min_separation_mm: 1.0,
        }
    }
}

/// The recovered layer at one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayerEstimate {
    /// `df`, ray distance, mm.
    pub foreground_distance_mm: f64,
    /// `X = rho_f cos(theta_f)` implied by the IR equation (Eq. 10).
    pub albedo_cos: f64,
    /// Predicted minus observed reading, wrapped, mm (0 for an exact root).
    pub residual_mm: f64,
    /// How many exact roots the bounds admit.
    pub roots: u8,
    /// No exact root within the bounds: the best fit is at a bound.
    pub pinned: bool,
    /// `d f / d df` at the estimate: how far the predicted reading moves per
    /// millimetre of layer (with the IR held). A reading noise `s` becomes a
    /// layer noise `s / |slope|`: a nearly invisible layer has a slope near 0.
    pub slope: f64,
    /// `d f / d I` at the estimate, the layer held: how far the predicted reading
    /// moves per count of IR ([`reading_sensitivity_to_ir`]). IR noise `s`
    /// becomes a layer noise `s |reading_per_ir| / |slope|`. In closed form on
    /// the sinusoid's fast path, by finite differences on the generic one.
    /// Like `slope`, NaN from [`foreground_distance_without_slopes`].
    pub reading_per_ir: f64,
}

/// `X` for a hypothesis `(df, xi)` from the IR equation (Eq. 7-10).
///
/// For the paper's model this is Eq. 10's non-negative root of
/// `xi^2 Ib X^2 + ((1-xi) Lin / df^2) X - I = 0` (closed forms too for other
/// transmission powers and an IR offset); with higher bounces or the
/// amplitude IR it is found numerically. `None` when no non-negative root exists
/// below `x_max` (the IR is too bright for any admissible albedo).
pub fn albedo_cos(model: &ForwardModel, obs: &PixelObservation, df: f64, xi: f64, x_max: f64) -> Option<f64> {
    let o = &model.options;
    let ir = obs.ir - o.ambient_offset;
    if ir <= 0.0 {
        return None;
    }
    if let Some(p) = PhasorModel::new(model) {
        return p.albedo_cos(obs, df, xi, x_max);
    }
    let one_layer = o.wall_interreflection == 0.0 && o.diffuse_transmission == 0.0 && o.hollow_depth_mm == 0.0;
    if o.bounces == 2 && o.ir_mode == IrMode::Sum && one_layer {
        // I = b X + a X^p with a = xi^2 Ib, b = (1 - xi) Lin / df^2 (Eq. 7).
        let a = xi * xi * (obs.background_ir - o.ambient_offset).max(0.0);
        let b = (1.0 - xi) * obs.emitted_light / (df * df);
        return albedo_closed_form(a, b, ir, o.transmission_albedo_power, x_max);
    }
    if let Some(x) = engine_albedo_cos(model, obs, df, xi, x_max) {
        return x;
    }
    if let Some(x) = affine_albedo_cos(model, obs, df, xi, x_max) {
        return x;
    }
    albedo_cos_scan(model, obs, df, xi, x_max)
}

/// [`albedo_cos`] on any model: the first crossing of the IR equation from `X = 0`,
/// bracketed on a coarse scan and bisected.
fn albedo_cos_scan(model: &ForwardModel, obs: &PixelObservation, df: f64, xi: f64, x_max: f64) -> Option<f64> {
    let o = &model.options;
    let g = |x: f64| model.layer_ir(&obs.layer_scene(df, xi, x, o.ambient_offset)) - obs.ir;
    // Bracket the first crossing on a coarse scan (the amplitude need not be monotone in X).
    const SCAN: usize = 16;
    let mut lo = 0.0;
    if g(lo) > 0.0 {
        return None;
    }
    for k in 1..=SCAN {
        let hi = x_max * k as f64 / SCAN as f64;
        let g_hi = g(hi);
        if g_hi >= 0.0 {
            let (mut a, mut b) = (lo, hi);
            for _ in 0..40 {
                let m = 0.5 * (a + b);
                if g(m) >= 0.0 {
                    b = m;
                } else {
                    a = m;
                }
            }
            return Some(0.5 * (a + b));
        }
        lo = hi;
    }
    None
}

/// The pixel's returns with the layer at `df`, translucency `xi` and albedo term `x`, and
/// how many there are.
pub(crate) fn returns_at_albedo(
    model: &ForwardModel,
    obs: &PixelObservation,
    df: f64,
    xi: f64,
    x: f64,
) -> ([super::model::Return; super::model::MAX_BOUNCES], usize) {
    let mut r = [super::model::Return::default(); super::model::MAX_BOUNCES];
    let n = model.layer_returns(&obs.layer_scene(df, xi, x, model.options.ambient_offset), &mut r);
    (r, n)
}

/// [`albedo_cos`] on the sensor's own frequency where the returns are affine in `X`
/// ([`ForwardModel::returns_affine_in_albedo`]; `C` and `A + C` the returns at `X = 0` and
/// `X = 1`): the IR is `X s + t` (the sum; `s > 0`) or `|X A + C|` (the amplitude; convex in
/// `X`), so from `g(0) <= 0` it is met once upward, the root [`albedo_cos_scan`] brackets and
/// bisects, here in closed form: `|A|^2 X^2 + 2 Re(A C*) X + |C|^2 - I^2 = 0`. The outer
/// `None`: not this case (a depth engine, another model, or `A = 0`).
fn affine_albedo_cos(
    model: &ForwardModel,
    obs: &PixelObservation,
    df: f64,
    xi: f64,
    x_max: f64,
) -> Option<Option<f64>> {
    if model.sensor.engine().is_some() || !model.returns_affine_in_albedo() {
        return None;
    }
    let o = &model.options;
    let ((zero, n0), (one, n1)) = (
        returns_at_albedo(model, obs, df, xi, 0.0),
        returns_at_albedo(model, obs, df, xi, 1.0),
    );
    let (zero, one) = (&zero[..n0], &one[..n1]);
    let ir = obs.ir - o.ambient_offset;
    let x = match o.ir_mode {
        IrMode::Sum => {
            let t: f64 = zero.iter().map(|r| r.strength).sum();
            let s = one.iter().map(|r| r.strength).sum::<f64>() - t;
            if !(s > 0.0) {
                return None;
            }
            if t > ir {
                return Some(None);
            }
            (ir - t) / s
        }
        IrMode::Amplitude => {
            let (c, p) = (model.own_phasor(zero), model.own_phasor(one));
            let a = [p[0] - c[0], p[1] - c[1]];
            let a2 = a[0] * a[0] + a[1] * a[1];
            if !(a2 > 0.0) {
                return None;
            }
            let c_len = c[0].hypot(c[1]);
            if c_len > ir {
                return Some(None);
            }
            let b = a[0] * c[0] + a[1] * c[1];
            (-b + (b * b + a2 * (ir - c_len) * (ir + c_len)).sqrt()) / a2
        }
    };
    Some((x.is_finite() && x <= x_max).then_some(x.max(0.0)))
}

/// [`albedo_cos`] for a depth engine's amplitude IR where the returns are linear in `X`
/// (two returns, `L2 = Ib xi^2` without `X`): at each frequency the phasor is
/// `X A_k + C_k` (`C_k` the background's share, `A_k` the layer's per unit `X`), so the
/// IR `mean_k |X A_k + C_k|` (or one frequency's) is convex in `X` and crosses the
/// observed IR at most once upward; Newton's method from `x_max` finds it. Where the IR
/// first falls with `X` and crosses twice, the upper root is taken (the generic search
/// gives none there): a layer on the lower branch is not found at its own distance.
/// The outer `None`: not this case (the generic search runs); the inner one: no
/// admissible root, as [`albedo_cos`] says it.
fn engine_albedo_cos(
    model: &ForwardModel,
    obs: &PixelObservation,
    df: f64,
    xi: f64,
    x_max: f64,
) -> Option<Option<f64>> {
    let o = &model.options;
    let e = model.sensor.engine()?;
    let linear = o.bounces == 2
        && o.transmission_albedo_power == 0.0
        && o.wall_interreflection == 0.0
        && o.diffuse_transmission == 0.0
        && o.hollow_depth_mm == 0.0;
    if !(linear && o.ir_mode == IrMode::Amplitude) {
        return None;
    }
    let k = e.len();
    let phasors_at = |x: f64| {
        let (r, n) = returns_at_albedo(model, obs, df, xi, x);
        e.phasors(&model.sensor, &r[..n])
    };
    let (c, one) = (phasors_at(0.0), phasors_at(1.0));
    let a: [(f64, f64); super::depth_engine::MAX_ENGINE_FREQUENCIES] =
        std::array::from_fn(|j| (one[j].a - c[j].a, one[j].b - c[j].b));
    let (first, last) = match e.ir_frequency_index() {
        Some(j) => (j, j + 1),
        None => (0, k),
    };
    let ir = obs.ir - o.ambient_offset;
    // g(X) = IR(X) - I and its derivative.
    let g = |x: f64| {
        let (mut v, mut dv) = (0.0, 0.0);
        for j in first..last {
            let (re, im) = (x * a[j].0 + c[j].a, x * a[j].1 + c[j].b);
            let len = re.hypot(im);
            v += len;
            if len > 0.0 {
                dv += (re * a[j].0 + im * a[j].1) / len;
            }
        }
        let n = (last - first) as f64;
        (v / n - ir, dv / n)
    };
    let (mut g_hi, mut dg_hi) = g(x_max);
    if g_hi < 0.0 {
        return Some(None);
    }
    // Where the layer's return first cancels the background's (g falls from X = 0), the
    // IR is met twice or not at all: the root on the rising side is taken, past g's minimum.
    let Some(mut lo) = rising_from(&g, x_max) else {
        return Some(None);
    };
    // Safeguarded Newton from the upper end of the bracket [lo, hi], g(lo) <= 0 <= g(hi).
    let mut hi = x_max;
    for _ in 0..100 {
        if g_hi == 0.0 || hi - lo <= 1e-13 * x_max {
            break;
        }
        let newton = hi - g_hi / dg_hi;
        let x = if dg_hi > 0.0 && newton > lo && newton < hi {
            newton
        } else {
            0.5 * (lo + hi)
        };
        let (gx, dgx) = g(x);
        if gx >= 0.0 {
            (hi, g_hi, dg_hi) = (x, gx, dgx);
        } else {
            lo = x;
        }
        if gx.abs() <= 1e-12 * ir.abs() {
            hi = x;
            break;
        }
    }
    Some((hi.is_finite() && hi >= 0.0 && hi <= x_max).then_some(hi))
}

/// For a convex `g` (value and slope) on `[0, x_max]`: 0 where `g(0) <= 0`, else the
/// point of its minimum (bisection on the slope) where `g` is not positive there; `None`
/// where `g` stays positive.
fn rising_from(g: &impl Fn(f64) -> (f64, f64), x_max: f64) -> Option<f64> {
    let (g0, dg0) = g(0.0);
    if g0 <= 0.0 {
        return Some(0.0);
    }
    if dg0 >= 0.0 {
        return None;
    }
    let (mut a, mut b) = (0.0, x_max);
    for _ in 0..60 {
        let m = 0.5 * (a + b);
        if g(m).1 < 0.0 {
            a = m
        } else {
            b = m
        }
    }
    (g(b).0 <= 0.0).then_some(b)
}

/// The non-negative root of `b X + a X^p = ir` (the IR equation of two
/// returns, Eq. 7-10) within `[0, x_max]`.
#[inline]
fn albedo_closed_form(a: f64, b: f64, ir: f64, p: f64, x_max: f64) -> Option<f64> {
    let x = if p == 2.0 {
        // Eq. 10; the rationalised form keeps precision when a -> 0 (a = 0 gives X = I / b).
        2.0 * ir / (b + (b * b + 4.0 * a * ir).sqrt())
    } else if p == 0.0 {
        (ir - a) / b
    } else if p == 1.0 {
        ir / (a + b)
    } else {
        // Monotone in X: Newton from the linear guess, kept in a bracket.
        let (mut lo, mut hi) = (0.0, x_max);
        let mut x = (ir / (a + b)).clamp(lo, hi);
        for _ in 0..60 {
            let g = b * x + a * x.powf(p) - ir;
            if g > 0.0 {
                hi = x
            } else {
                lo = x
            }
            let dg = b + a * p * x.powf(p - 1.0);
            let next = x - g / dg;
            x = if next.is_finite() && next > lo && next < hi {
                next
            } else {
                0.5 * (lo + hi)
            };
            if (hi - lo) < 1e-12 || g.abs() < 1e-12 * ir {
                break;
            }
        }
        x
    };
    (x.is_finite() && x >= 0.0 && x <= x_max).then_some(x)
}

/// [`albedo_cos`] kept within `[0, x_max]`: where noise puts the IR outside
/// what any admissible albedo explains at this `(df, xi)`, the nearer bound,
/// flagged `true` (pinned).
pub fn albedo_cos_clamped(model: &ForwardModel, obs: &PixelObservation, df: f64, xi: f64, x_max: f64) -> (f64, bool) {
    if let Some(x) = albedo_cos(model, obs, df, xi, x_max) {
        return (x, false);
    }
    if model.layer_ir(&obs.layer_scene(df, xi, x_max, model.options.ambient_offset)) < obs.ir {
        (x_max, true)
    } else {
        (0.0, true)
    }
}

/// The reading the model predicts for `(df, xi, X)` at this pixel (Eq. 11), mm.
pub fn predicted_reading(model: &ForwardModel, obs: &PixelObservation, df: f64, xi: f64, x: f64) -> f64 {
    model
        .measure_layer(&obs.layer_scene(df, xi, x, model.options.ambient_offset))
        .distance_mm
}

/// `d f / d I` at a fixed layer distance: how far the predicted reading
/// moves per count of IR (through the albedo the IR equation gives). With the
/// layer's [`LayerEstimate::slope`], IR noise `s` becomes a layer noise
/// `s |dF/dI| / |slope|`. NaN where the albedo is not admissible.
pub fn reading_sensitivity_to_ir(model: &ForwardModel, obs: &PixelObservation, df: f64, xi: f64, x_max: f64) -> f64 {
    if let Some(fast) = FastPixel::new(model, obs, xi, x_max) {
        return fast.derivatives(df).map_or(f64::NAN, |(_, per_ir)| per_ir);
    }
    let h = (obs.ir.abs() * 1e-3).max(1e-9);
    let at = |ir: f64| {
        let o = PixelObservation { ir, ..*obs };
        albedo_cos(model, &o, df, xi, x_max).map(|x| predicted_reading(model, &o, df, xi, x))
    };
    match (at(obs.ir - h), at(obs.ir + h)) {
        (Some(a), Some(b)) => model.sensor.wrapped_difference_mm(b, a) / (2.0 * h),
        _ => f64::NAN,
    }
}

/// One sample of the residual along `df`.
#[derive(Clone, Copy)]
struct Sample {
    df: f64,
    residual: f64,
    x: f64,
}

/// The roots a scan has found, and the one the root rule picks: the nearest
/// (wrapped) to the preference, a neighbourhood's surface, when given, else to
/// the reading itself (shared by the generic scan and the fast sinusoid path).
struct RootPick {
    anchor: f64,
    roots: u8,
    /// The root picked so far, with its distance to the anchor.
    chosen: Option<(Sample, f64)>,
}

impl RootPick {
    fn new(obs: &PixelObservation, prefer_mm: Option<f64>) -> Self {
        Self {
            anchor: prefer_mm.unwrap_or(obs.distance_mm),
            roots: 0,
            chosen: None,
        }
    }

    fn offer(&mut self, sensor: &crate::physics::Sensor, root: Sample) {
        self.roots = self.roots.saturating_add(1);
        let dist = sensor.wrapped_difference_mm(root.df, self.anchor).abs();
        if self.chosen.is_none_or(|(_, d)| dist < d) {
            self.chosen = Some((root, dist));
        }
    }
}

/// The generic path's estimate at the chosen sample `s`, with the residual's
/// slope there when `slopes`: a central difference where both sides are
/// admissible, else one-sided.
fn estimate_at(
    sensor: &crate::physics::Sensor,
    s: Sample,
    roots: u8,
    pinned: bool,
    slopes: bool,
    eval: impl Fn(f64) -> Option<Sample>,
) -> LayerEstimate {
    let h = 0.5;
    let sides = if slopes {
        (eval(s.df - h), eval(s.df + h))
    } else {
        (None, None)
    };
    let slope = match sides {
        (Some(a), Some(b)) => sensor.wrapped_difference_mm(b.residual, a.residual) / (2.0 * h),
        (Some(a), None) => sensor.wrapped_difference_mm(s.residual, a.residual) / h,
        (None, Some(b)) => sensor.wrapped_difference_mm(b.residual, s.residual) / h,
        (None, None) => f64::NAN,
    };
    LayerEstimate {
        foreground_distance_mm: s.df,
        albedo_cos: s.x,
        residual_mm: s.residual,
        roots,
        pinned,
        slope,
        reading_per_ir: f64::NAN,
    }
}

/// The foreground distance of one translucent pixel for a given ξ (Eq. 8-12).
///
/// Scans `df` over `[d_min, db)` in `scan_step_mm` steps, brackets every sign
/// change of the wrapped residual `f(df, xi) - d` (phase wraps are not roots),
/// and refines each to 0.01 mm. Several roots: the one nearest `prefer_mm`
/// when given (a neighbourhood's surface), else the one nearest the reading
/// itself (the smallest correction). No root: the admissible sample with the
/// smallest residual, flagged `pinned`. `None` when no `df` admits `0 < X <= max`.
pub fn foreground_distance(
    model: &ForwardModel,
    obs: &PixelObservation,
    xi: f64,
    bounds: &InversionBounds,
    prefer_mm: Option<f64>,
) -> Option<LayerEstimate> {
    invert(model, obs, xi, bounds, prefer_mm, true)
}

/// [`foreground_distance`] without the residual's slopes at the estimate
/// ([`LayerEstimate::slope`] and [`LayerEstimate::reading_per_ir`] NaN): the
/// same estimate, without the evaluations the slopes take, for callers that
/// do not gate on the layer's noise (ξ estimation's profile, recovery's
/// re-picks).
pub fn foreground_distance_without_slopes(
    model: &ForwardModel,
    obs: &PixelObservation,
    xi: f64,
    bounds: &InversionBounds,
    prefer_mm: Option<f64>,
) -> Option<LayerEstimate> {
    invert(model, obs, xi, bounds, prefer_mm, false)
}

/// Both of them: the search range from the bounds, then the sinusoid's fast
/// path where the model allows it, else the generic scan.
fn invert(
    model: &ForwardModel,
    obs: &PixelObservation,
    xi: f64,
    bounds: &InversionBounds,
    prefer_mm: Option<f64>,
    slopes: bool,
) -> Option<LayerEstimate> {
    let (lo, hi) = search_range(obs, bounds)?;
    let search = Search { lo, hi, slopes };
    if let Some(p) = PhasorModel::new(model) {
        return p.invert(model, obs, xi, bounds.max_albedo_cos, search);
    }
    match FastPixel::new(model, obs, xi, bounds.max_albedo_cos) {
        Some(fast) => foreground_distance_fast(&fast, model, obs, bounds, prefer_mm, search),
        None => foreground_distance_generic(model, obs, xi, bounds, prefer_mm, search),
    }
}

/// `[d_min, db - min_separation]`, where a pixel's layer is looked for; `None`
/// when it is empty or the reading or IR is not finite (nothing to invert).
#[inline(always)]
fn search_range(obs: &PixelObservation, bounds: &InversionBounds) -> Option<(f64, f64)> {
    let lo = bounds.min_distance_mm;
    let hi = obs.background_distance_mm - bounds.min_separation_mm;
    (hi > lo && obs.distance_mm.is_finite() && obs.ir.is_finite()).then_some((lo, hi))
}

/// Where an inversion looks for the layer, `df` in `[lo, hi]`, and whether
/// it finds the residual's slopes at its estimate.
#[derive(Debug, Clone, Copy)]
struct Search {
    lo: f64,
    hi: f64,
    slopes: bool,
}

/// [`foreground_distance`] on any forward model, one model evaluation per sample.
fn foreground_distance_generic(
    model: &ForwardModel,
    obs: &PixelObservation,
    xi: f64,
    bounds: &InversionBounds,
    prefer_mm: Option<f64>,
    Search { lo, hi, slopes }: Search,
) -> Option<LayerEstimate> {
    let sensor = &model.sensor;
    let eval = |df: f64| -> Option<Sample> {
        let x = albedo_cos(model, obs, df, xi, bounds.max_albedo_cos)?;
        if x <= 0.0 {
            return None;
        }
        let pred = predicted_reading(model, obs, df, xi, x);
        if !pred.is_finite() {
            return None;
        }
        Some(Sample {
            df,
            residual: sensor.wrapped_difference_mm(pred, obs.distance_mm),
            x,
        })
    };
    let mut samples = scan(&eval, lo, hi, bounds.scan_step_mm);
    if sensor.depth_engine().is_some() {
        samples = around_jumps(&eval, &samples);
    }
    let (pick, best) = roots_of(&samples, &eval, sensor, obs, prefer_mm);
    let (s, pinned) = match pick.chosen {
        Some((root, _)) => (root, false),
        None => (best?, true),
    };
    let reading_per_ir = if slopes {
        reading_sensitivity_to_ir(model, obs, s.df, xi, bounds.max_albedo_cos)
    } else {
        f64::NAN
    };
    Some(LayerEstimate {
        reading_per_ir,
        ..estimate_at(sensor, s, pick.roots, pinned, slopes, eval)
    })
}

/// The residual sampled from `lo` to `hi` in steps of about `step_mm`, with the edge of the
/// admissible region (where X reaches its bound) added as a sample wherever the scan crosses
/// it, so a root between the last admissible sample and that edge is bracketed too; a NaN
/// sample marks a gap between admissible stretches.
fn scan(eval: &impl Fn(f64) -> Option<Sample>, lo: f64, hi: f64, step_mm: f64) -> Vec<Sample> {
    let n = ((hi - lo) / step_mm).ceil().max(2.0) as usize;
    let step = (hi - lo) / n as f64;
    let mut samples: Vec<Sample> = Vec::with_capacity(n + 3);
    let mut prev: Option<(f64, bool)> = None;
    for k in 0..=n {
        let df = lo + step * k as f64;
        let cur = eval(df);
        if let Some((pdf, pok)) = prev {
            if pok != cur.is_some() {
                let (mut ok_df, mut bad_df) = if pok { (pdf, df) } else { (df, pdf) };
                for _ in 0..24 {
                    let m = 0.5 * (ok_df + bad_df);
                    if eval(m).is_some() {
                        ok_df = m;
                    } else {
                        bad_df = m;
                    }
                }
                // Leaving an admissible stretch the edge follows its samples; entering one it
                // precedes `cur`: either way it goes next, in df order.
                samples.extend(eval(ok_df));
                // Mark a gap between admissible stretches so no bracket spans it.
                if pok {
                    samples.push(Sample {
                        df: f64::NAN,
                        residual: f64::NAN,
                        x: f64::NAN,
                    });
                }
            }
        }
        if let Some(c) = cur {
            samples.push(c);
        }
        prev = Some((df, cur.is_some()));
    }
    samples
}

/// A refined sign change of the residual whose residual is still larger than this, mm,
/// is a depth engine's jump, not a root (a jump moves the engine's weighted mean by a
/// whole wrap of one frequency times its weight share: tens of mm).
const ENGINE_JUMP_MM: f64 = 1.0;

/// A step of the residual larger than this between neighbouring samples, mm, is looked
/// into for a depth engine's jump ([`around_jumps`]).
const ENGINE_STEP_MM: f64 = 50.0;

/// The scan's samples with more where the residual steps by over [`ENGINE_STEP_MM`]
/// between two of them: bisected down to 0.05 mm, so that a depth engine's jump (where
/// its wrap hypothesis changes) is pinned between two samples and a root on either side
/// of it, which a coarse step would straddle with the jump, is bracketed on its own.
fn around_jumps(eval: &impl Fn(f64) -> Option<Sample>, samples: &[Sample]) -> Vec<Sample> {
    fn split(eval: &impl Fn(f64) -> Option<Sample>, p: Sample, c: Sample, out: &mut Vec<Sample>, depth: u32) {
        if depth == 0 || c.df - p.df < 0.05 || (c.residual - p.residual).abs() <= ENGINE_STEP_MM {
            return;
        }
        let Some(m) = eval(0.5 * (p.df + c.df)) else {
            return;
        };
        split(eval, p, m, out, depth - 1);
        out.push(m);
        split(eval, m, c, out, depth - 1);
    }
    let mut out = Vec::with_capacity(samples.len() + 32);
    for (i, &p) in samples.iter().enumerate() {
        out.push(p);
        if let Some(&c) = samples.get(i + 1).filter(|c| !p.df.is_nan() && !c.df.is_nan()) {
            split(eval, p, c, &mut out, 16);
        }
    }
    out
}

/// The roots the scan brackets, refined and picked among; and the sample of least residual
/// (the pinned answer where there is no root).
fn roots_of(
    samples: &[Sample],
    eval: &impl Fn(f64) -> Option<Sample>,
    sensor: &crate::physics::Sensor,
    obs: &PixelObservation,
    prefer_mm: Option<f64>,
) -> (RootPick, Option<Sample>) {
    let range = sensor.unambiguous_range_mm();
    let mut best: Option<Sample> = None;
    let mut pick = RootPick::new(obs, prefer_mm);
    for w in samples.windows(2) {
        let (p, c) = (w[0], w[1]);
        if !p.df.is_nan() && best.is_none_or(|b| p.residual.abs() < b.residual.abs()) {
            best = Some(p);
        }
        if p.df.is_nan() || c.df.is_nan() || p.df == c.df {
            continue;
        }
        let crosses = (p.residual <= 0.0) != (c.residual <= 0.0);
        if crosses && (p.residual - c.residual).abs() < range / 4.0 {
            // A depth engine's reading jumps where its wrap hypothesis changes: a sign
            // change there is no root (the residual stays off zero on both sides).
            let jump = |root: &Sample| sensor.depth_engine().is_some() && root.residual.abs() > ENGINE_JUMP_MM;
            if let Some(root) = refine(eval, p, c).filter(|r| !jump(r)) {
                pick.offer(sensor, root);
            }
        }
    }
    if let Some(last) = samples.last().filter(|s| !s.df.is_nan()) {
        if best.is_none_or(|b| last.residual.abs() < b.residual.abs()) {
            best = Some(*last);
        }
    }
    (pick, best)
}

/// The inversion's evaluations for the paper's two returns on a sinusoidal
/// sensor (transmission power 0, 1 or 2, any IR offset and subsurface delay), with the
/// pixel's constants computed once: `X` in closed form (Eq. 10) and the mixed
/// phasor of Eq. 5 rotated by the reading's phase, whose angle is the wrapped
/// residual of Eq. 11. The same numbers as [`predicted_reading`] up to
/// rounding (test `fast_path_matches_the_forward_model`); [`FastPixel::new`]
/// declines (the generic path runs) for any model option it does not know.
#[derive(Debug, Clone, Copy)]
struct FastPixel {
    /// IR less the offset.
    ir: f64,
    /// `xi^2 (Ib - offset)`: the IR equation's `a`, and L2 per `X^p` (`Xb xi^2
    /// Lin / db^2` with `Xb = (Ib - offset) db^2 / Lin`).
    a: f64,
    /// `(1 - xi) Lin`: the IR equation's `b` times `df^2`, and L1's scale.
    l1: f64,
    /// Transmission power `p` (0, 1 or 2).
    p: f64,
    /// Largest admissible `X`.
    x_max: f64,
    /// `2 pi / R`, radians per mm.
    k: f64,
    /// `R / (2 pi)`, mm per radian.
    mm_per_rad: f64,
    /// The reading's phase less the subsurface delay's, radians.
    phi_d: f64,
    /// The background's phasor rotated by minus the reading's phase.
    bg: (f64, f64),
}

/// The constants of the fast path that one model and one ξ share over every
/// pixel, with the model's options checked once ([`FastPixel`]'s).
#[derive(Debug, Clone, Copy)]
struct FastModel {
    xi: f64,
    /// The IR offset (ambient), counts.
    offset: f64,
    /// The subsurface delay, mm.
    delay_mm: f64,
    /// Transmission power `p` (0, 1 or 2).
    p: f64,
    /// Largest admissible `X`.
    x_max: f64,
    /// `2 pi / R`, radians per mm.
    k: f64,
    /// `R / (2 pi)`, mm per radian.
    mm_per_rad: f64,
    /// `R`, the unambiguous range, mm.
    range_mm: f64,
}

impl FastModel {
    /// `None` for a model the fast path does not know (the generic path runs).
    fn new(model: &ForwardModel, xi: f64, x_max: f64) -> Option<Self> {
        let o = &model.options;
        // Only the options handled here may differ from the paper's; any other (an effect
        // added later) sends the pixel down the generic path.
        #[allow(clippy::needless_update)] // the update is for options added later
        let known = ModelOptions {
            bounces: 2,
            ir_mode: IrMode::Sum,
            transmission_albedo_power: o.transmission_albedo_power,
            ambient_offset: o.ambient_offset,
            subsurface_delay_mm: o.subsurface_delay_mm,
            ..ModelOptions::default()
        };
        // Powers with a closed-form albedo only (others iterate: the generic path).
        let closed = [0.0, 1.0, 2.0].contains(&o.transmission_albedo_power);
        let engine = model.sensor.depth_engine().is_some();
        if *o != known || !closed || model.sensor.waveform != Waveform::Sinusoid || engine {
            return None;
        }
        let range = model.sensor.unambiguous_range_mm();
        Some(Self {
            xi,
            offset: o.ambient_offset,
            delay_mm: o.subsurface_delay_mm,
            p: o.transmission_albedo_power,
            x_max,
            k: std::f64::consts::TAU / range,
            mm_per_rad: range / std::f64::consts::TAU,
            range_mm: range,
        })
    }

    /// The reading's phase `k d` and the background's angle from it, `k db - k d`.
    #[inline(always)]
    fn angles(&self, obs: &PixelObservation) -> (f64, f64) {
        let phi_d = self.k * obs.distance_mm;
        (phi_d, self.k * obs.background_distance_mm - phi_d)
    }

    /// One pixel's constants, given its [`Self::angles`] and the `(sin, cos)`
    /// of the background's angle.
    #[inline(always)]
    fn pixel(&self, obs: &PixelObservation, phi_d: f64, (s, c): (f64, f64)) -> FastPixel {
        FastPixel {
            ir: obs.ir - self.offset,
            a: self.xi * self.xi * (obs.background_ir - self.offset).max(0.0),
            l1: (1.0 - self.xi) * obs.emitted_light,
            p: self.p,
            x_max: self.x_max,
            k: self.k,
            mm_per_rad: self.mm_per_rad,
            phi_d: phi_d - self.k * self.delay_mm,
            bg: (c, s),
        }
    }
}

impl FastPixel {
    fn new(model: &ForwardModel, obs: &PixelObservation, xi: f64, x_max: f64) -> Option<Self> {
        let fm = FastModel::new(model, xi, x_max)?;
        let (phi_d, background) = fm.angles(obs);
        Some(fm.pixel(obs, phi_d, sin_cos(background)))
    }

    /// `X` at `df` (Eq. 10), if admissible (`0 < X <= x_max`).
    #[inline]
    fn albedo(&self, df: f64) -> Option<f64> {
        if self.ir <= 0.0 {
            return None;
        }
        let x = self.albedo_unchecked(df);
        self.admissible(x).then_some(x)
    }

    /// [`Self::albedo`]'s number before its checks.
    #[inline(always)]
    fn albedo_unchecked(&self, df: f64) -> f64 {
        // albedo_closed_form's closed forms, inlined.
        let (a, b, ir) = (self.a, self.l1 / (df * df), self.ir);
        if self.p == 2.0 {
            2.0 * ir / (b + (b * b + 4.0 * a * ir).sqrt())
        } else if self.p == 0.0 {
            (ir - a) / b
        } else {
            ir / (a + b)
        }
    }

    /// `0 < X <= x_max`.
    #[inline(always)]
    fn admissible(&self, x: f64) -> bool {
        x.is_finite() && x > 0.0 && x <= self.x_max
    }

    /// `X` at `df` with L1 and L2 there: [`Self::albedo`] and [`Self::strengths`]
    /// with one division and one square root for the transmission power 2.
    #[inline]
    fn albedo_strengths(&self, df: f64) -> Option<(f64, f64, f64)> {
        if self.ir <= 0.0 {
            return None;
        }
        let (x, l1, l2) = self.albedo_strengths_unchecked(df);
        self.admissible(x).then_some((x, l1, l2))
    }

    /// [`Self::albedo_strengths`]' numbers before its checks.
    #[inline(always)]
    fn albedo_strengths_unchecked(&self, df: f64) -> (f64, f64, f64) {
        if self.p != 2.0 {
            let x = self.albedo_unchecked(df);
            let (l1, l2) = self.strengths(df, x);
            return (x, l1, l2);
        }
        // With u = df^2: X = 2 I u / (l1 + sqrt(l1^2 + 4 a I u^2)), L1 = l1 X / u.
        let u = df * df;
        let r = 2.0 * self.ir / (self.l1 + (self.l1 * self.l1 + 4.0 * self.a * self.ir * u * u).sqrt());
        let x = r * u;
        (x, self.l1 * r, self.a * x * x)
    }

    /// L1 and L2 at `(df, X)`.
    #[inline]
    fn strengths(&self, df: f64, x: f64) -> (f64, f64) {
        let xp = if self.p == 2.0 {
            x * x
        } else if self.p == 0.0 {
            1.0
        } else {
            x
        };
        (self.l1 * x / (df * df), self.a * xp)
    }

    /// The mixed phasor, rotated by minus the reading's phase.
    #[inline]
    fn phasor(&self, df: f64, x: f64) -> (f64, f64) {
        let (l1, l2) = self.strengths(df, x);
        self.mix(l1, l2, sin_cos(self.k * df - self.phi_d))
    }

    /// The rotated phasor of returns `L1` and `L2`, the layer's turned by its
    /// `(sin, cos)`, the background's by [`Self::bg`](FastPixel::bg).
    #[inline]
    fn mix(&self, l1: f64, l2: f64, (s, c): (f64, f64)) -> (f64, f64) {
        (l1 * c + l2 * self.bg.0, l1 * s + l2 * self.bg.1)
    }

    /// The wrapped residual, mm, of a rotated phasor (NaN when it is zero: nothing decodes).
    #[inline]
    fn residual_mm(&self, re: f64, im: f64) -> f64 {
        if re == 0.0 && im == 0.0 {
            return f64::NAN;
        }
        if on_small_angle_series(re, im) {
            return self.small_angle_residual_mm(re, im);
        }
        im.atan2(re) * self.mm_per_rad
    }

    /// [`Self::residual_mm`] on its small-angle series ([`on_small_angle_series`]).
    #[inline(always)]
    fn small_angle_residual_mm(&self, re: f64, im: f64) -> f64 {
        let t = im / re;
        t * (1.0 - t * t / 3.0) * self.mm_per_rad
    }

    /// The residual's derivatives at `df`, mm per mm of layer and mm per count
    /// of IR, in closed form: with the rotated phasor `(Re, Im)`, `d angle =
    /// (Re dIm - Im dRe) / (Re^2 + Im^2)`, its parts through `L1 = l1 X / df^2`,
    /// `L2 = a X^p` and the IR equation's `dX` (implicit: `dX/dI = 1 / (b + a p
    /// X^(p-1))`, `dX/d df = 2 b X / df / (b + a p X^(p-1))`). `None` where `X`
    /// is not admissible.
    fn derivatives(&self, df: f64) -> Option<(f64, f64)> {
        let strengths = self.albedo_strengths(df)?;
        let (slope, per_ir) = self.derivatives_at(df, strengths, sin_cos(self.k * df - self.phi_d));
        (slope.is_finite() && per_ir.is_finite()).then_some((slope, per_ir))
    }

    /// [`Self::derivatives`] from `X`, L1 and L2 at `df` and the layer's
    /// `(sin, cos)` there, before the check that both are finite.
    #[inline(always)]
    fn derivatives_at(&self, df: f64, (x, l1, l2): (f64, f64, f64), (sn, cs): (f64, f64)) -> (f64, f64) {
        let (re, im) = self.mix(l1, l2, (sn, cs));
        let per_df = 1.0 / df;
        let b = self.l1 * per_df * per_df;
        // d L2 / d X.
        let dl2_dx = if self.p == 2.0 {
            2.0 * self.a * x
        } else if self.p == 0.0 {
            0.0
        } else {
            self.a
        };
        let dx_di = 1.0 / (b + dl2_dx);
        let dx_ddf = 2.0 * b * x * per_df * dx_di;
        let rate = self.mm_per_rad / (re * re + im * im);
        let angle_rate = |dre: f64, dim: f64| (re * dim - im * dre) * rate;
        // Along df: L1 changes through X and 1/df^2, and turns with the phase.
        let dl1 = b * dx_ddf - 2.0 * l1 * per_df;
        let dl2 = dl2_dx * dx_ddf;
        let slope = angle_rate(
            dl1 * cs - l1 * self.k * sn + dl2 * self.bg.0,
            dl1 * sn + l1 * self.k * cs + dl2 * self.bg.1,
        );
        // Along the IR at a fixed df.
        let (dl1, dl2) = (b * dx_di, dl2_dx * dx_di);
        let per_ir = angle_rate(dl1 * cs + dl2 * self.bg.0, dl1 * sn + dl2 * self.bg.1);
        (slope, per_ir)
    }

    /// One full sample at `df`.
    #[inline]
    fn eval(&self, df: f64) -> Option<Sample> {
        let (x, l1, l2) = self.albedo_strengths(df)?;
        let (re, im) = self.mix(l1, l2, sin_cos(self.k * df - self.phi_d));
        let residual = self.residual_mm(re, im);
        residual.is_finite().then_some(Sample { df, residual, x })
    }
}

/// Whether a rotated phasor's angle is small enough for the residual's
/// series: near a root the angle is tiny, and `atan t = t - t^3/3 + t^5/5 -
/// ...` has its third term below the rounding of the first for `|t| <= 1e-4`.
#[inline(always)]
fn on_small_angle_series(re: f64, im: f64) -> bool {
    re > 0.0 && im.abs() <= 1e-4 * re
}

/// A scan sample of the fast path: the rotated phasor, its residual when needed.
#[derive(Clone, Copy)]
struct ScanSample {
    df: f64,
    x: f64,
    re: f64,
    im: f64,
}

impl ScanSample {
    /// `residual <= 0`, read from the phasor's sign (the angle in `(-pi, pi]`).
    #[inline]
    fn nonpositive(&self) -> bool {
        self.im < 0.0 || (self.im == 0.0 && self.re >= 0.0)
    }

    /// The sample with its residual.
    #[inline]
    fn sample(&self, fast: &FastPixel) -> Sample {
        Sample {
            df: self.df,
            residual: fast.residual_mm(self.re, self.im),
            x: self.x,
        }
    }
}

/// The scan of [`foreground_distance`] for a [`FastPixel`], streamed: every
/// admissible sample in `df` order to `visit`, with `None` between
/// admissible stretches (where `X` leaves its bounds; the edge itself, found
/// by bisection, is a sample). The phasors are stepped by rotation (no
/// trigonometry per sample).
fn scan_fast(fast: &FastPixel, lo: f64, hi: f64, step_mm: f64, mut visit: impl FnMut(Option<ScanSample>)) {
    let n = ((hi - lo) / step_mm).ceil().max(2.0) as usize;
    let step = (hi - lo) / n as f64;
    let (mut rs, mut rc) = sin_cos(fast.k * lo - fast.phi_d);
    let (ss, sc) = sin_cos(fast.k * step);
    let full = |df: f64| -> Option<ScanSample> {
        let x = fast.albedo(df)?;
        let (re, im) = fast.phasor(df, x);
        (re != 0.0 || im != 0.0).then_some(ScanSample { df, x, re, im })
    };
    let mut prev: Option<(f64, bool)> = None;
    for k in 0..=n {
        let df = lo + step * k as f64;
        if k > 0 {
            // e^{i (phi_k - phi_d)} by rotation; resynchronised every 64 steps.
            if k % 64 == 0 {
                (rs, rc) = sin_cos(fast.k * df - fast.phi_d);
            } else {
                (rs, rc) = (rs * sc + rc * ss, rc * sc - rs * ss);
            }
        }
        let cur = fast.albedo_strengths(df).and_then(|(x, l1, l2)| {
            let (re, im) = fast.mix(l1, l2, (rs, rc));
            (re != 0.0 || im != 0.0).then_some(ScanSample { df, x, re, im })
        });
        if let Some((pdf, pok)) = prev {
            if pok != cur.is_some() {
                let (mut ok_df, mut bad_df) = if pok { (pdf, df) } else { (df, pdf) };
                for _ in 0..24 {
                    let m = 0.5 * (ok_df + bad_df);
                    // Admissible where X is (a phasor of exactly zero has measure zero).
                    if fast.albedo(m).is_some() {
                        ok_df = m;
                    } else {
                        bad_df = m;
                    }
                }
                // Leaving an admissible stretch the edge follows its samples; entering one it
                // precedes `cur`: either way it goes next, in df order.
                if let Some(e) = full(ok_df) {
                    visit(Some(e));
                }
                if pok {
                    visit(None);
                }
            }
        }
        if let Some(c) = cur {
            visit(Some(c));
        }
        prev = Some((df, cur.is_some()));
    }
}

/// The roots of the fast path in closed structure, without a scan.
///
/// In the frame rotated by the reading's phase, a root is where the mixed
/// phasor's imaginary part `L1 sin(alpha) + L2 sin(beta)` vanishes with a
/// positive real part (`alpha = k df - phi_d`, `beta` the background's angle).
/// With `L1 + L2 = I` (Eq. 7) that is `lambda sin(alpha) + (1 - lambda) sin(beta)
/// = 0`, `lambda = L1 / I`, possible only where `sin(alpha)` has the sign
/// opposite to `sin(beta)`: half-periods of `alpha`. There the imaginary part
/// is `-sgn(sin beta) lambda e(df)` with
///
/// `e(df) = |sin(alpha)| - tau(df)`, `tau = |sin(beta)| L2 / L1`,
///
/// and `tau` has a closed form for each transmission power (`p` = 2:
/// `|sin beta| (sqrt(1 + c df^4) - 1) / 2`, `c = 4 a I / l1^2`; `p` = 1:
/// `|sin beta| a df^2 / l1`; `p` = 0: `|sin beta| a / (I - a)`), increasing and
/// convex in `df`. So `e` is concave on each half-period: it has at most two
/// roots there, found from the signs at the half-period's ends and at its
/// maximum, each then by Newton's method from the end where `e < 0` (on a
/// concave function Newton's steps stay on that side and converge
/// monotonically). The admissible albedo `X <= x_max` is `df <= df*` in
/// closed form (`X` grows with `df`).
#[derive(Clone, Copy)]
struct HumpRoots {
    /// `-sgn(sin beta)`: the sign `sin(alpha)` must have.
    sigma: f64,
    /// `|sin beta|`.
    s: f64,
    /// `k`, radians per mm, its inverse, and the reading's phase less the delay's.
    k: f64,
    mm_per_rad: f64,
    phi_d: f64,
    /// The transmission power and `tau`'s constant for it.
    p: f64,
    c: f64,
}

impl HumpRoots {
    /// `None` where the structure does not hold (no background angle, no layer
    /// light, no second return): the scan handles those pixels.
    fn new(fast: &FastPixel) -> Option<Self> {
        let hump = Self::of(fast);
        hump.holds(fast).then_some(hump)
    }

    /// The structure's constants for `fast`, whether or not it holds.
    #[inline(always)]
    fn of(fast: &FastPixel) -> Self {
        let sb = fast.bg.1;
        Self {
            sigma: -sb.signum(),
            s: sb.abs(),
            k: fast.k,
            mm_per_rad: fast.mm_per_rad,
            phi_d: fast.phi_d,
            p: fast.p,
            c: Self::tau_constant(fast),
        }
    }

    /// Whether the structure holds for `fast`, whose constants these are.
    #[inline(always)]
    fn holds(&self, fast: &FastPixel) -> bool {
        let sb = fast.bg.1;
        sb != 0.0 && fast.ir > 0.0 && fast.l1 > 0.0 && fast.a > 0.0 && sb.is_finite() && self.c.is_finite()
    }

    /// `tau`'s constant for the pixel's transmission power (NaN where the
    /// structure does not hold: `p` = 0 with `I <= a`).
    #[inline(always)]
    fn tau_constant(fast: &FastPixel) -> f64 {
        let s = fast.bg.1.abs();
        if fast.p == 2.0 {
            4.0 * fast.a * fast.ir / (fast.l1 * fast.l1)
        } else if fast.p == 1.0 {
            s * fast.a / fast.l1
        } else if fast.ir > fast.a {
            s * fast.a / (fast.ir - fast.a)
        } else {
            f64::NAN
        }
    }

    /// `tau` and `d tau / d df`.
    #[inline(always)]
    fn tau(&self, df: f64) -> (f64, f64) {
        if self.p == 2.0 {
            let d2 = df * df;
            let cd4 = self.c * d2 * d2;
            let q = (1.0 + cd4).sqrt();
            // q - 1 as c df^4 / (q + 1): no cancellation for a faint second return.
            (0.5 * self.s * cd4 / (q + 1.0), self.s * self.c * d2 * df / q)
        } else if self.p == 1.0 {
            (self.c * df * df, 2.0 * self.c * df)
        } else {
            (self.c, 0.0)
        }
    }

    /// `e` and `de / d df`.
    #[inline]
    fn e(&self, df: f64) -> (f64, f64) {
        self.e_at(df, sin_cos(self.k * df - self.phi_d))
    }

    /// [`Self::e`] given the layer's `(sin, cos)` at `df`.
    #[inline(always)]
    fn e_at(&self, df: f64, (sn, cs): (f64, f64)) -> (f64, f64) {
        let (t, dt) = self.tau(df);
        (self.sigma * sn - t, self.sigma * self.k * cs - dt)
    }

    /// Newton's method on the concave `e` from `x` (where `e <= 0`) toward the
    /// root between `x` and `toward`, kept within them.
    fn newton(&self, mut x: f64, toward: f64, start: Option<(f64, f64)>) -> f64 {
        let (lo, hi) = (x.min(toward), x.max(toward));
        let mut at = start;
        for _ in 0..50 {
            let (e, de) = at.take().unwrap_or_else(|| self.e(x));
            let step = -e / de;
            if !step.is_finite() {
                break;
            }
            let next = (x + step).clamp(lo, hi);
            let moved = (next - x).abs();
            x = next;
            if moved < 1e-3 || e == 0.0 {
                break;
            }
        }
        x
    }

    /// Every root of `e` on `[lo, hi]`, in increasing `df`, to `found`.
    fn roots(&self, lo: f64, hi: f64, mut found: impl FnMut(f64)) {
        use std::f64::consts::{FRAC_1_PI, FRAC_PI_2, PI, TAU};
        // Half-periods where sgn(sin alpha) = sigma: alpha in (a0 + 2 pi m, a0 + 2 pi m + pi).
        let a0 = if self.sigma > 0.0 { 0.0 } else { PI };
        let to_df = |alpha: f64| (alpha + self.phi_d) * self.mm_per_rad;
        let mut m = ((self.k * lo - self.phi_d - a0) * (0.5 * FRAC_1_PI)).floor();
        loop {
            let start = to_df(a0 + TAU * m);
            if !(start < hi) {
                break;
            }
            let (l, u) = (start.max(lo), to_df(a0 + TAU * m + PI).min(hi));
            let peak = to_df(a0 + TAU * m + FRAC_PI_2);
            m += 1.0;
            if !(l < u) {
                continue;
            }
            let (el, dl) = self.e(l);
            let (eu, du) = self.e(u);
            match (el > 0.0, eu > 0.0) {
                (true, true) => {}
                (false, true) => found(self.newton(l, u, Some((el, dl)))),
                (true, false) => found(self.newton(u, l, Some((eu, du)))),
                (false, false) => {
                    // Two roots or none: around the maximum, which lies before the peak of
                    // |sin alpha| (e' = -tau' <= 0 there).
                    let top = if peak > l && peak < u && self.e(peak).0 > 0.0 {
                        Some(peak)
                    } else if dl > 0.0 && peak.min(u) > l {
                        self.maximum(l, peak.min(u)).filter(|&x| self.e(x).0 > 0.0)
                    } else {
                        None
                    };
                    if let Some(top) = top {
                        found(self.newton(l, top, Some((el, dl))));
                        found(self.newton(u, top, Some((eu, du))));
                    }
                }
            }
        }
    }

    /// Where the concave `e` peaks on `[l, u]` (`e'(l) > 0`), by bisection on
    /// `e'`; `None` when it peaks at `u`.
    fn maximum(&self, mut l: f64, mut u: f64) -> Option<f64> {
        if self.e(u).1 >= 0.0 {
            return None;
        }
        while u - l > 0.05 {
            let m = 0.5 * (l + u);
            if self.e(m).1 > 0.0 {
                l = m;
            } else {
                u = m;
            }
        }
        Some(0.5 * (l + u))
    }
}

/// The largest `df` whose albedo is admissible (`X <= x_max`; `X` grows with
/// `df`): `b = (I - a x_max^p) / x_max` in the IR equation. Infinite when no
/// `df` reaches the bound.
#[inline(always)]
fn admissible_limit(fast: &FastPixel) -> f64 {
    let xp = if fast.p == 2.0 {
        fast.x_max * fast.x_max
    } else if fast.p == 0.0 {
        1.0
    } else {
        fast.x_max
    };
    let rest = fast.ir - fast.a * xp;
    if rest > 0.0 {
        (fast.l1 * fast.x_max / rest).sqrt()
    } else {
        f64::INFINITY
    }
}

/// [`foreground_distance`] for a [`FastPixel`]: every root from its closed
/// structure ([`HumpRoots`]; the scan where that does not apply), the same
/// root rule, and a pixel without a root scanned for its best sample.
fn foreground_distance_fast(
    fast: &FastPixel,
    model: &ForwardModel,
    obs: &PixelObservation,
    bounds: &InversionBounds,
    prefer_mm: Option<f64>,
    Search { lo, hi, slopes }: Search,
) -> Option<LayerEstimate> {
    let sensor = &model.sensor;
    let range = sensor.unambiguous_range_mm();
    let eval = |df: f64| fast.eval(df);
    let mut pick = RootPick::new(obs, prefer_mm);
    if let Some(hump) = HumpRoots::new(fast) {
        // The roots in closed structure; a root whose phasor points away from the reading
        // (the reading's phase plus pi) is a wrap, not a root.
        hump.roots(lo, hi.min(admissible_limit(fast)), |df| {
            if let Some(root) = eval(df).filter(|s| s.residual.abs() < range / 4.0) {
                pick.offer(sensor, root);
            }
        });
    } else {
        scan_roots(fast, lo, hi, bounds, &mut pick, sensor, range);
    }
    let (s, pinned) = match pick.chosen {
        Some((root, _)) => (root, false),
        None => {
            // No root: the admissible sample with the smallest residual (the first of equals).
            let mut best: Option<Sample> = None;
            scan_fast(fast, lo, hi, bounds.scan_step_mm, |cur| {
                if let Some(s) = cur.map(|c| c.sample(fast)) {
                    if best.is_none_or(|b| s.residual.abs() < b.residual.abs()) {
                        best = Some(s);
                    }
                }
            });
            (best?, true)
        }
    };
    let (slope, reading_per_ir) = if slopes {
        fast.derivatives(s.df).unwrap_or((f64::NAN, f64::NAN))
    } else {
        (f64::NAN, f64::NAN)
    };
    Some(LayerEstimate {
        foreground_distance_mm: s.df,
        albedo_cos: s.x,
        residual_mm: s.residual,
        roots: pick.roots,
        pinned,
        slope,
        reading_per_ir,
    })
}

/// The roots of [`foreground_distance_fast`] by the scan: every sign change of
/// the wrapped residual between admissible samples (not a phase wrap), refined.
fn scan_roots(
    fast: &FastPixel,
    lo: f64,
    hi: f64,
    bounds: &InversionBounds,
    pick: &mut RootPick,
    sensor: &crate::physics::Sensor,
    range: f64,
) {
    let eval = |df: f64| fast.eval(df);
    let mut last: Option<ScanSample> = None;
    scan_fast(fast, lo, hi, bounds.scan_step_mm, |cur| {
        if let (Some(p), Some(c)) = (&last, &cur) {
            if p.df != c.df && p.nonpositive() != c.nonpositive() {
                let (p, c) = (p.sample(fast), c.sample(fast));
                if (p.residual - c.residual).abs() < range / 4.0 {
                    if let Some(root) = refine(&eval, p, c) {
                        pick.offer(sensor, root);
                    }
                }
            }
        }
        last = cur;
    });
}

/// Illinois (modified regula falsi) refinement of a bracketed root to 0.01 mm.
fn refine(eval: &impl Fn(f64) -> Option<Sample>, mut a: Sample, mut b: Sample) -> Option<Sample> {
    let mut side = 0i8;
    let (mut fa, mut fb) = (a.residual, b.residual);
    for _ in 0..40 {
        let t = if (fb - fa).abs() > 0.0 { fb / (fb - fa) } else { 0.5 };
        let df = (b.df - t * (b.df - a.df)).clamp(a.df.min(b.df), a.df.max(b.df));
        let c = eval(df)?;
        if c.residual.abs() < 1e-6 || (b.df - a.df).abs() < 0.01 {
            return Some(c);
        }
        if (c.residual <= 0.0) == (fb <= 0.0) {
            b = c;
            fb = c.residual;
            if side == 1 {
                fa *= 0.5;
            }
            side = 1;
        } else {
            a = c;
            fa = c.residual;
            if side == -1 {
                fb *= 0.5;
            }
            side = -1;
        }
    }
    Some(if a.residual.abs() < b.residual.abs() { a } else { b })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::model::{IrMode, ModelOptions};
    use crate::physics::sensor::{Sensor, Waveform};

    /// A pixel's observation of a layer as `model` renders it (shared with the phasor path's tests).
    pub(super) fn observe(model: &ForwardModel, df: f64, db: f64, xi: f64, x: f64, xb: f64) -> PixelObservation {
        observe_near_wall(model, [df, db], xi, x, xb, 0.0)
    }

    /// [`observe`] with the view factor `f` from the background point to the layer.
    pub(super) fn observe_near_wall(
        model: &ForwardModel,
        [df, db]: [f64; 2],
        xi: f64,
        x: f64,
        xb: f64,
        f: f64,
    ) -> PixelObservation {
        let lin = 1.5e10;
        let s = LayerScene {
            foreground_distance_mm: df,
            background_distance_mm: db,
            translucency: xi,
            foreground_albedo_cos: x,
            background_albedo_cos: xb,
            emitted_light: lin,
            wall_view_factor: f,
            diffuse_lobe: None,
        };
        let m = model.measure_layer(&s);
        let bg = model.measure(&[ForwardModel::opaque_return(db, xb, lin)]);
        PixelObservation {
            distance_mm: m.distance_mm,
            ir: m.ir,
            background_distance_mm: db,
            background_ir: bg.ir,
            emitted_light: lin,
            wall_view_factor: f,
            diffuse_lobe: None,
        }
    }

    /// Where the returns are affine in `X`, the closed form gives the root the scan brackets
    /// and bisects (or none where the scan finds none): a frosted layer's lobe (a table along
    /// the ray) and the filled view, with one inter-reflection, a near wall, a hollow object,
    /// a delay and an IR offset, the amplitude IR and the sum, at hypothesised layers before,
    /// at and past the pixel's own. A model that is not affine is left to the scan.
    #[test]
    fn the_affine_albedo_is_the_root_the_scan_finds() {
        let table = crate::physics::diffuse::LobeTable {
            first_mm: 500.0,
            step_mm: 120.0,
            lobes: std::array::from_fn(|j| crate::physics::diffuse::DiffuseLobe {
                lit: [0.3 - 0.01 * j as f64, 0.1 + 0.005 * j as f64],
                shadow: [0.5 - 0.02 * j as f64, 0.2 + 0.01 * j as f64],
            }),
        };
        let x_max = InversionBounds::default().max_albedo_cos;
        let (mut found, mut none) = (0, 0);
        let mut m = ForwardModel::physical(Sensor::sr4000());
        for (ir_mode, bounces, wall, hollow, delay, offset) in [
            (IrMode::Amplitude, 3, 0.0, 0.0, 0.0, 0.0),
            (IrMode::Amplitude, 2, 1.0, 150.0, 12.0, 40.0),
            (IrMode::Sum, 3, 0.0, 0.0, 0.0, 0.0),
            (IrMode::Sum, 2, 1.0, 150.0, 12.0, 40.0),
        ] {
            m.options.ir_mode = ir_mode;
            m.options.bounces = bounces;
            m.options.wall_interreflection = wall;
            m.options.hollow_depth_mm = hollow;
            m.options.subsurface_delay_mm = delay;
            m.options.ambient_offset = offset;
            m.options.diffuse_transmission = 0.8;
            for lobe in [Some(table), None] {
                for (df, xi, x) in [(800.0, 0.4, 0.3), (1300.0, 0.7, 0.6), (1900.0, 0.85, 0.9)] {
                    let s = LayerScene {
                        diffuse_lobe: lobe.map(|t| t.at(df)),
                        ..LayerScene {
                            foreground_distance_mm: df,
                            background_distance_mm: 2600.0,
                            translucency: xi,
                            foreground_albedo_cos: x,
                            background_albedo_cos: 0.8,
                            emitted_light: 1.5e10,
                            wall_view_factor: 0.25,
                            diffuse_lobe: None,
                        }
                    };
                    let me = m.measure_layer(&s);
                    let bg = m.measure(&[ForwardModel::opaque_return(2600.0, 0.8, 1.5e10)]);
                    let obs = PixelObservation {
                        distance_mm: me.distance_mm,
                        ir: me.ir,
                        background_distance_mm: 2600.0,
                        background_ir: bg.ir,
                        emitted_light: 1.5e10,
                        wall_view_factor: 0.25,
                        diffuse_lobe: lobe,
                    };
                    let truth = affine_albedo_cos(&m, &obs, df, xi, x_max).expect("affine");
                    assert!(truth.is_some_and(|got| (got - x).abs() < 1e-9), "{truth:?} against {x}");
                    for h in [df - 450.0, df - 60.0, df, df + 140.0, df + 500.0] {
                        let closed = affine_albedo_cos(&m, &obs, h, xi, x_max).expect("affine");
                        let scan = albedo_cos_scan(&m, &obs, h, xi, x_max);
                        match (closed, scan) {
                            (Some(a), Some(b)) => {
                                assert!((a - b).abs() < 1e-9 * x_max, "{:?} {h}: {a} against {b}", m.options);
                                found += 1;
                            }
                            (None, None) => none += 1,
                            _ => panic!("{:?} {h}: {closed:?} against the scan's {scan:?}", m.options),
                        }
                    }
                }
            }
        }
        println!("{found} roots alike, {none} with none");
        assert!(found >= 60 && none >= 5, "{found} {none}");
        m.options.transmission_albedo_power = 1.0;
        let obs = observe(&m, 1200.0, 2600.0, 0.6, 0.5, 0.8);
        assert!(affine_albedo_cos(&m, &obs, 1200.0, 0.6, x_max).is_none());
    }

    /// The default physics read through a 16/80/120 MHz depth engine.
    fn engine_model(ir_mode: IrMode) -> ForwardModel {
        let engine = crate::physics::DepthEngine::at(&[16e6, 80e6, 120e6]).expect("an engine");
        let mut m = ForwardModel::physical(Sensor::sr4000().with_depth_engine(&engine).expect("an engine"));
        m.options.ir_mode = ir_mode;
        m
    }

    #[test]
    fn a_pixel_read_through_a_depth_engine_inverts_to_its_layer() {
        let bounds = InversionBounds::default();
        let (mut found, mut lost) = (0, 0);
        for ir_mode in [IrMode::Amplitude, IrMode::Sum] {
            let m = engine_model(ir_mode);
            for db in [2000.0, 3300.0] {
                for df in (5..db as usize / 100 - 1).map(|k| 100.0 * k as f64 + 17.0) {
                    let obs = observe(&m, df, db, 0.65, 0.6, 0.9);
                    // Where the IR is met twice the lower albedo is lost (albedo_cos' doc); where
                    // the residual only touches zero at the layer (a double root) it is pinned.
                    if albedo_cos(&m, &obs, df, 0.65, 1.0).is_none_or(|x| (x - 0.6).abs() > 1e-6) {
                        lost += 1;
                        continue;
                    }
                    // Alone where it has one root; where the engine's jumps leave several, with
                    // a neighbourhood's surface to pick by (as recovery gives one).
                    let alone = foreground_distance(&m, &obs, 0.65, &bounds, None)
                        .unwrap_or_else(|| panic!("{ir_mode:?} db {db} df {df}: no layer, {obs:?}"));
                    let prefer = (alone.roots > 1).then_some(df + 30.0);
                    let e = foreground_distance(&m, &obs, 0.65, &bounds, prefer).expect("a layer");
                    if e.pinned {
                        lost += 1;
                        continue;
                    }
                    assert!(
                        (e.foreground_distance_mm - df).abs() < 0.5 && !e.pinned,
                        "{ir_mode:?} db {db} df {df}: {e:?} (reading {})",
                        obs.distance_mm
                    );
                    // The albedo the engine's IR implies is the true one.
                    assert!(
                        (e.albedo_cos - 0.6).abs() < 1e-6,
                        "{ir_mode:?} df {df}: X {}",
                        e.albedo_cos
                    );
                    found += 1;
                }
            }
        }
        assert!(found >= 6 * lost && found > 60, "found {found}, lost {lost}");
    }

    #[test]
    fn the_engine_albedo_solves_the_ir_equation() {
        let m = engine_model(IrMode::Amplitude);
        for df in [600.0, 1111.0, 1800.0] {
            let obs = observe(&m, df, 2000.0, 0.5, 0.45, 1.0);
            for xi in [0.3, 0.5, 0.7] {
                let Some(x) = albedo_cos(&m, &obs, df, xi, 1.0) else {
                    continue;
                };
                let ir = m.layer_ir(&obs.layer_scene(df, xi, x, 0.0));
                assert!(
                    (ir - obs.ir).abs() < 1e-9 * obs.ir,
                    "df {df} xi {xi}: {ir} vs {}",
                    obs.ir
                );
            }
        }
    }

    #[test]
    fn eq10_root_satisfies_the_ir_equation() {
        let m = ForwardModel::paper(Sensor::sr4000());
        let obs = observe(&m, 1000.0, 2000.0, 0.65, 0.6, 1.0);
        let x = albedo_cos(&m, &obs, 1000.0, 0.65, 1.0).unwrap();
        assert!((x - 0.6).abs() < 1e-12);
        // xi = 0: X = I / b exactly.
        let x0 = albedo_cos(&m, &obs, 1000.0, 0.0, 10.0).unwrap();
        assert!((x0 - obs.ir * 1e6 / obs.emitted_light).abs() < 1e-12);
    }

    #[test]
    fn albedo_solves_every_ir_equation() {
        let paper = ForwardModel::paper(Sensor::sr4000());
        let mut amp = paper.clone();
        amp.options.bounces = 3; // forces the numeric path; the third return is tiny here
        let obs = observe(&paper, 1200.0, 2500.0, 0.5, 0.7, 0.9);
        let a = albedo_cos(&paper, &obs, 1200.0, 0.5, 1.0).unwrap();
        assert!((a - 0.7).abs() < 1e-9);
        let obs3 = observe(&amp, 1200.0, 2500.0, 0.5, 0.7, 0.9);
        let b = albedo_cos(&amp, &obs3, 1200.0, 0.5, 1.0).unwrap();
        assert!((b - 0.7).abs() < 1e-9, "{b}");
        let mut p15 = paper.clone();
        p15.options.transmission_albedo_power = 1.5;
        let obs = observe(&p15, 1200.0, 2500.0, 0.5, 0.7, 0.9);
        assert!((albedo_cos(&p15, &obs, 1200.0, 0.5, 1.0).unwrap() - 0.7).abs() < 1e-9);
    }

    #[test]
    fn recovers_the_true_layer_at_the_true_xi() {
        let cases = [
            (Waveform::Sinusoid, 1000.0, 2000.0, 0.65, 0.6),
            (Waveform::Sinusoid, 500.0, 2000.0, 0.94, 0.8),
            (Waveform::Sinusoid, 1750.0, 2000.0, 0.94, 0.8),
            (Waveform::Triangle, 900.0, 3300.0, 0.72, 0.5),
            (Waveform::Sinusoid, 700.0, 3300.0, 0.91, 0.9),
        ];
        for (w, df, db, xi, x) in cases {
            let m = ForwardModel::paper(Sensor::new(30e6, w));
            let obs = observe(&m, df, db, xi, x, 1.0);
            let est = foreground_distance(&m, &obs, xi, &InversionBounds::default(), None).unwrap();
            assert!(!est.pinned, "{w:?} {df}");
            // The slope against a finite difference of the forward model.
            let f = |d: f64| predicted_reading(&m, &obs, d, xi, albedo_cos(&m, &obs, d, xi, 1.0).unwrap());
            let fd = (f(df + 0.01) - f(df - 0.01)) / 0.02;
            assert!(
                (est.slope - fd).abs() < 1e-3 * fd.abs().max(1.0),
                "{w:?} {df}: {} vs {fd}",
                est.slope
            );
            assert!((est.foreground_distance_mm - df).abs() < 0.05, "{w:?} df {df}: {est:?}");
            assert!((est.albedo_cos - x).abs() < 1e-3);
        }
    }

    #[test]
    fn recovers_with_model_options() {
        let opts = ModelOptions {
            bounces: 4,
            ir_mode: IrMode::Amplitude,
            transmission_albedo_power: 0.0,
            ambient_offset: 30.0,
            subsurface_delay_mm: 5.0,
            refraction_shift_px: [0.0, 0.0],
            wall_interreflection: 0.0,
            diffuse_transmission: 0.0,
            hollow_depth_mm: 0.0,
        };
        let m = ForwardModel {
            sensor: Sensor::sr4000(),
            options: opts,
        };
        let obs = observe(&m, 1300.0, 2600.0, 0.6, 0.5, 0.9);
        let est = foreground_distance(&m, &obs, 0.6, &InversionBounds::default(), None).unwrap();
        assert!((est.foreground_distance_mm - 1300.0).abs() < 0.05, "{est:?}");
    }

    #[test]
    fn every_xi_fits_one_pixel_exactly() {
        // physics.md §3: one frame's residuals alone do not determine xi.
        let m = ForwardModel::paper(Sensor::sr4000());
        let obs = observe(&m, 1000.0, 2000.0, 0.65, 0.6, 1.0);
        let mut depths = vec![];
        for xi in [0.0, 0.3, 0.5, 0.65, 0.8] {
            let est = foreground_distance(&m, &obs, xi, &InversionBounds::default(), None).unwrap();
            assert!(est.residual_mm.abs() < 0.05 && !est.pinned, "xi {xi}: {est:?}");
            depths.push(est.foreground_distance_mm);
        }
        assert!((depths[3] - 1000.0).abs() < 0.05);
        assert!((depths[0] - 1000.0).abs() > 15.0, "a wrong xi recovers another depth");
    }

    #[test]
    fn without_slopes_the_estimate_is_the_same() {
        // On the fast path and the generic one (a third bounce), with and without a preference.
        let mut generic = ForwardModel::paper(Sensor::sr4000());
        generic.options.bounces = 3;
        for m in [ForwardModel::paper(Sensor::sr4000()), generic] {
            for (df, xi, prefer) in [(600.0, 0.65, None), (1400.0, 0.3, Some(1300.0)), (900.0, 0.94, None)] {
                let obs = observe(&m, df, 2000.0, xi, 0.6, 1.0);
                let b = InversionBounds::default();
                let with = foreground_distance(&m, &obs, xi, &b, prefer).expect("an estimate");
                let without = foreground_distance_without_slopes(&m, &obs, xi, &b, prefer).expect("an estimate");
                assert!(with.slope.is_finite() && with.reading_per_ir.is_finite());
                assert!(without.slope.is_nan() && without.reading_per_ir.is_nan());
                let same =
                    |e: &LayerEstimate| (e.foreground_distance_mm, e.albedo_cos, e.residual_mm, e.roots, e.pinned);
                assert_eq!(same(&with), same(&without));
            }
        }
    }

    #[test]
    fn no_admissible_root_is_pinned_or_none() {
        let m = ForwardModel::paper(Sensor::sr4000());
        let mut obs = observe(&m, 1000.0, 2000.0, 0.65, 0.6, 1.0);
        obs.distance_mm = 2300.0; // behind the background: no two-layer mix reads there
        if let Some(est) = foreground_distance(&m, &obs, 0.3, &InversionBounds::default(), None) {
            assert!(est.pinned);
        }
        obs.ir = -1.0;
        assert!(foreground_distance(&m, &obs, 0.3, &InversionBounds::default(), None).is_none());
    }

    #[test]
    fn a_root_next_to_the_albedo_bound_is_found() {
        // A bright layer close to the camera: the root lies just below the df where X reaches 1.
        for w in [Waveform::Sinusoid, Waveform::Triangle] {
            let m = ForwardModel::paper(Sensor::new(30e6, w));
            let obs = observe(&m, 184.0, 1500.0, 0.5, 0.9, 1.0);
            let est = foreground_distance(&m, &obs, 0.5, &InversionBounds::default(), None).unwrap();
            assert!(
                !est.pinned && (est.foreground_distance_mm - 184.0).abs() < 0.05,
                "{w:?}: {est:?}"
            );
        }
    }

    /// The root rule (nearest the reading) against the alternative (nearest the
    /// camera) on a noise-free grid of layers: how often each picks a wrong root.
    #[test]
    fn nearest_reading_rule_picks_the_true_root_most_often() {
        for (power, max_wrong) in [(2.0, 0.02), (0.0, 0.05)] {
            let mut m = ForwardModel::paper(Sensor::sr4000());
            m.options.transmission_albedo_power = power;
            let (mut n, mut several, mut wrong_near, mut wrong_camera) = (0, 0, 0, 0);
            for db in [1500.0, 2000.0, 2500.0, 3300.0, 4000.0] {
                for frac in [0.1, 0.2, 0.35, 0.5, 0.65, 0.8, 0.9, 0.95] {
                    let df = 150.0 + frac * (db - 200.0);
                    for xi in [0.2, 0.4, 0.6, 0.8, 0.9, 0.95] {
                        for x in [0.2, 0.4, 0.6, 0.8, 0.95] {
                            let obs = observe(&m, df, db, xi, x, 1.0);
                            let b = InversionBounds::default();
                            let Some(near) = foreground_distance(&m, &obs, xi, &b, None) else {
                                continue;
                            };
                            let camera = foreground_distance(&m, &obs, xi, &b, Some(0.0)).unwrap();
                            n += 1;
                            several += (near.roots > 1) as usize;
                            wrong_near += ((near.foreground_distance_mm - df).abs() > 1.0) as usize;
                            wrong_camera += ((camera.foreground_distance_mm - df).abs() > 1.0) as usize;
                        }
                    }
                }
            }
            println!("L2 ~ X^{power}: {n} layers, {several} with several roots; wrong: nearest the reading {wrong_near}, nearest the camera {wrong_camera}");
            assert!(wrong_near <= wrong_camera);
            assert!((wrong_near as f64) <= max_wrong * n as f64, "{wrong_near} of {n}");
        }
    }

    /// `d f / d df` of the forward model by a difference of 1e-4 mm, one-sided where
    /// the other side is not admissible.
    fn fine_slope(m: &ForwardModel, obs: &PixelObservation, xi: f64, df: f64) -> f64 {
        let f = |d: f64| albedo_cos(m, obs, d, xi, 1.0).map(|x| predicted_reading(m, obs, d, xi, x));
        let (h, w) = (1e-4, |a: f64, b: f64| m.sensor.wrapped_difference_mm(a, b));
        match (f(df - h), f(df), f(df + h)) {
            (Some(a), _, Some(b)) => w(b, a) / (2.0 * h),
            (Some(a), Some(c), None) => w(c, a) / h,
            (None, Some(c), Some(b)) => w(b, c) / h,
            _ => f64::NAN,
        }
    }

    /// The fast path (paper's returns on a sinusoid, roots from their closed structure)
    /// against the generic one (a scan of the forward model at 2 mm, fine enough not to
    /// step over a pair of roots or a steep one) on a grid of layers.
    #[test]
    fn fast_path_matches_the_forward_model() {
        let b = InversionBounds::default();
        let fine = InversionBounds { scan_step_mm: 2.0, ..b };
        let mut checked = 0;
        for (power, offset, delay) in [(2.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 20.0, 4.0), (2.0, 20.0, 4.0)] {
            let mut m = ForwardModel::paper(Sensor::sr4000());
            m.options.transmission_albedo_power = power;
            m.options.ambient_offset = offset;
            m.options.subsurface_delay_mm = delay;
            for db in [1500.0, 2500.0, 4000.0] {
                for frac in [0.05, 0.3, 0.6, 0.9] {
                    let df = 150.0 + frac * (db - 200.0);
                    for xi in [0.2, 0.65, 0.94] {
                        for x in [0.3, 0.9] {
                            let mut obs = observe(&m, df, db, xi, x, 1.0);
                            for (dd, di) in [(0.0, 1.0), (25.0, 1.03), (-40.0, 0.9)] {
                                obs.distance_mm += dd;
                                obs.ir *= di;
                                for prefer in [None, Some(0.0)] {
                                    let fast = FastPixel::new(&m, &obs, xi, b.max_albedo_cos).expect("fast path");
                                    let search = Search {
                                        lo: b.min_distance_mm,
                                        hi: db - b.min_separation_mm,
                                        slopes: true,
                                    };
                                    let f = foreground_distance_fast(&fast, &m, &obs, &b, prefer, search);
                                    // Roots against the fine scan; a pixel without one against the
                                    // same coarse scan for its best sample.
                                    let fine_or_same = if f.is_some_and(|f| f.pinned) { &b } else { &fine };
                                    let g = foreground_distance_generic(&m, &obs, xi, fine_or_same, prefer, search);
                                    if f.is_some_and(|f| f.pinned) {
                                        let g = foreground_distance_generic(&m, &obs, xi, &fine, prefer, search);
                                        assert!(g.is_none_or(|g| g.roots == 0), "a root missed: {g:?}");
                                    }
                                    let case = format!("p {power} off {offset} db {db} df {df} xi {xi} x {x} dd {dd} di {di} {prefer:?}");
                                    match (f, g) {
                                        (Some(f), Some(g)) => {
                                            assert_eq!((f.roots, f.pinned), (g.roots, g.pinned), "{case}: {f:?} {g:?}");
                                            let tol = if f.pinned { 1e-6 } else { 0.02 };
                                            assert!(
                                                (f.foreground_distance_mm - g.foreground_distance_mm).abs() < tol,
                                                "{case}: {f:?} {g:?}"
                                            );
                                            assert!(
                                                (f.residual_mm - g.residual_mm).abs() < 0.02,
                                                "{case}: {f:?} {g:?}"
                                            );
                                            // The closed-form slope against a fine difference of the
                                            // forward model (one-sided at the albedo's bound).
                                            let fd = fine_slope(&m, &obs, xi, f.foreground_distance_mm);
                                            assert!(
                                                (f.slope - fd).abs() < 1e-3 * fd.abs().max(1.0),
                                                "{case}: {} vs {fd}",
                                                f.slope
                                            );
                                            let per_ir =
                                                reading_sensitivity_to_ir(&m, &obs, f.foreground_distance_mm, xi, 1.0);
                                            let h = obs.ir * 1e-6;
                                            let at = |ir: f64| {
                                                let o = PixelObservation { ir, ..obs };
                                                let d = f.foreground_distance_mm;
                                                albedo_cos(&m, &o, d, xi, 1.0)
                                                    .map(|x| predicted_reading(&m, &o, d, xi, x))
                                            };
                                            if let (Some(a), Some(c)) = (at(obs.ir - h), at(obs.ir + h)) {
                                                let fd = m.sensor.wrapped_difference_mm(c, a) / (2.0 * h);
                                                // (a floor of 1e-3 mm per IR of the pixel for a derivative near zero)
                                                assert!(
                                                    (per_ir - fd).abs() < 1e-3 * fd.abs().max(1.0 / obs.ir),
                                                    "{case}: {per_ir} vs {fd}"
                                                );
                                            }
                                            checked += 1;
                                        }
                                        (None, None) => {}
                                        other => panic!("{case}: {other:?}"),
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(checked > 800, "{checked}");
        // Options the fast path does not know go the generic way.
        let mut m = ForwardModel::paper(Sensor::sr4000());
        m.options.bounces = 3;
        assert!(FastPixel::new(&m, &observe(&m, 900.0, 2000.0, 0.5, 0.5, 1.0), 0.5, 1.0).is_none());
        m.options.bounces = 2;
        m.options.transmission_albedo_power = 1.5;
        assert!(FastPixel::new(&m, &observe(&m, 900.0, 2000.0, 0.5, 0.5, 1.0), 0.5, 1.0).is_none());
        let t = ForwardModel::paper(Sensor::new(30e6, Waveform::Triangle));
        assert!(FastPixel::new(&t, &observe(&t, 900.0, 2000.0, 0.5, 0.5, 1.0), 0.5, 1.0).is_none());
    }

    #[test]
    fn depth_reversal_inverts_with_double_pass_law() {
        let mut m = ForwardModel::paper(Sensor::sr4000());
        m.options.transmission_albedo_power = 0.0;
        let obs = observe(&m, 800.0, 3300.0, 0.91, 0.3, 1.0);
        assert!(obs.distance_mm > 3300.0);
        let est = foreground_distance(&m, &obs, 0.91, &InversionBounds::default(), None).unwrap();
        assert!((est.foreground_distance_mm - 800.0).abs() < 0.05, "{est:?}");
    }
}
