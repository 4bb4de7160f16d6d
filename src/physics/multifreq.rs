//! Several modulation frequencies (issue 35, physics.md §7): the one forward
//! model's returns mixed into one phasor per frequency, and a per-pixel
//! inversion against a latched background that gives the layer's distance,
//! its return and ξ from one frame.
//!
//! At frequency `f_k` (unambiguous range `R_k = c / (2 f_k)`) a pixel's
//! phasor is its returns mixed in the buckets (Eq. 5 at each frequency):
//!
//! ```text
//! M_k = sum_j L_j u_k(d_j),   u_k(d) = (corr(2 pi d / R_k), corr(2 pi d / R_k - pi/2))
//! ```
//!
//! (`u_k(d) = e^{i 2 pi d / R_k}` for the sinusoid). With the default physics
//! (two returns, `L2 = Ib ξ²`) and the background latched as its phasor `B_k`
//! (the background alone: `Ib` at `db`) this is
//!
//! ```text
//! M_k = a u_k(d1) + ξ² B_k
//! ```
//!
//! with `a = L1` the layer's return (Eq. 1) at its distance `d1` (the
//! foreground distance `df`). One frequency gives two numbers for three
//! unknowns, so every ξ fits; K >= 2 frequencies give 2K >= 4 numbers
//! (objects.md's table).
//!
//! What the inversion does not model: under the paper's Eq. 2
//! (`L2 = Ib ξ² X²`) the fitted `ξ²` is `ξ² X²`; higher bounces (Eq. 3) and
//! diffuse transmission (physics.md §7) are model error, not noise; the
//! latched `B_k` is taken as exact (averaged over frames, its noise is small).

use nalgebra::{Matrix3, Matrix4};

use super::model::{ForwardModel, LayerScene, Measurement, Return, MAX_BOUNCES};
use super::sensor::{Buckets, Sensor, Waveform, SPEED_OF_LIGHT_MM_PER_S};
use super::trig;

/// A complex phasor at one frequency: in-phase `a = Q1 - Q2` and quadrature
/// `b = Q3 - Q4` (the bucket differences of Eq. 5).
pub type Phasor = Buckets;

/// The 95 % quantile of chi-square with one degree of freedom: the level of
/// the test of an opaque surface (ξ = 0) against a translucent layer.
pub const CHI_SQUARE_1_95: f64 = 3.841_458_820_694_124;

/// Invalid input to the multi-frequency model or inversion.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MultiFrequencyError {
    /// No modulation frequency.
    #[error("no modulation frequency given")]
    NoFrequencies,
    /// A frequency that is not a positive, finite number of hertz.
    #[error("modulation frequency {0} Hz is not positive and finite")]
    NonPositiveFrequency(f64),
    /// A per-frequency input of the wrong length.
    #[error("{what}: {got} values for {expected} modulation frequencies")]
    MismatchedLengths {
        /// Which input.
        what: &'static str,
        /// The number of frequencies.
        expected: usize,
        /// Its length.
        got: usize,
    },
    /// A phasor or distance that is not finite.
    #[error("{0} is not finite")]
    NotFinite(&'static str),
    /// A noise standard deviation that is not positive and finite.
    #[error("noise standard deviation {0} is not positive and finite")]
    NonPositiveNoise(f64),
    /// No room for a layer between the near limit and the background.
    #[error(
        "background at {background_distance_mm} mm leaves no layer distance beyond the near limit {min_distance_mm} mm"
    )]
    BackgroundTooNear {
        /// The latched background's distance, mm.
        background_distance_mm: f64,
        /// The near limit, mm.
        min_distance_mm: f64,
    },
    /// The scene is deeper than the frequencies' common unambiguous range:
    /// two layer distances in it give the same phasors (aliasing).
    #[error("the scene reaches {depth_mm} mm past the near limit, beyond the frequencies' common unambiguous range {common_range_mm} mm (layer distances alias)")]
    BeyondCommonRange {
        /// Background distance less the near limit, mm.
        depth_mm: f64,
        /// The common unambiguous range, mm.
        common_range_mm: f64,
    },
    /// The latched background's phasors are all zero: ξ has nothing to act on.
    #[error("the latched background returned no light")]
    NoBackgroundReturn,
    /// A translucency outside `[0, 1]`.
    #[error("translucency {0} is outside [0, 1]")]
    TranslucencyOutOfRange(f64),
    /// Scan settings that are not positive and finite.
    #[error("scan settings: {0}")]
    InvalidSettings(&'static str),
}

/// The frequency in whole hertz, or the error for a non-positive one.
fn whole_hertz(f: f64) -> Result<u64, MultiFrequencyError> {
    if !(f.is_finite() && f > 0.0) {
        return Err(MultiFrequencyError::NonPositiveFrequency(f));
    }
    Ok(rounded_hertz(f))
}

/// A positive frequency to the whole hertz, at least 1.
fn rounded_hertz(f: f64) -> u64 {
    (f.round() as u64).max(1)
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// The common unambiguous range of a set of modulation frequencies, mm:
/// `c / (2 gcd(f_1, ..., f_K))`, the shortest distance by which a return can
/// move and give the same phasor at every frequency (frequencies taken to
/// the whole hertz). A scene deeper than this aliases: 20, 50 and 100 MHz
/// give 14990 mm, 50 and 100 MHz only 2998 mm.
pub fn common_unambiguous_range_mm(frequencies_hz: &[f64]) -> Result<f64, MultiFrequencyError> {
    if frequencies_hz.is_empty() {
        return Err(MultiFrequencyError::NoFrequencies);
    }
    let mut g = 0;
    for &f in frequencies_hz {
        g = gcd(g, whole_hertz(f)?);
    }
    Ok(SPEED_OF_LIGHT_MM_PER_S / (2.0 * g as f64))
}

/// The one forward model ([`ForwardModel`]) at K modulation frequencies: the
/// same returns, each frequency's correlation and wrap.
#[derive(Debug, Clone)]
pub struct MultiFrequencyModel {
    /// One per frequency: the same options and waveform, its own sensor.
    models: Vec<ForwardModel>,
}

impl MultiFrequencyModel {
    /// `model`'s physics and waveform at each of `frequencies_hz`.
    pub fn new(model: &ForwardModel, frequencies_hz: &[f64]) -> Result<Self, MultiFrequencyError> {
        if frequencies_hz.is_empty() {
            return Err(MultiFrequencyError::NoFrequencies);
        }
        let models = frequencies_hz
            .iter()
            .map(|&f| {
                whole_hertz(f)?;
                Ok(ForwardModel {
                    sensor: Sensor::new(f, model.sensor.waveform),
                    options: model.options.clone(),
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { models })
    }

    /// The forward model at each frequency, in the order given.
    pub fn models(&self) -> &[ForwardModel] {
        &self.models
    }

    /// The number of frequencies K.
    pub fn len(&self) -> usize {
        self.models.len()
    }

    /// Never true (a model has at least one frequency); for clippy's `len` rule.
    pub fn is_empty(&self) -> bool {
        self.models.is_empty()
    }

    /// `c / (2 gcd(f_k))`: see [`common_unambiguous_range_mm`].
    pub fn common_unambiguous_range_mm(&self) -> f64 {
        let hertz = self
            .models
            .iter()
            .map(|m| rounded_hertz(m.sensor.modulation_frequency_hz));
        let g = hertz.fold(0, gcd);
        SPEED_OF_LIGHT_MM_PER_S / (2.0 * g as f64)
    }

    /// The returns mixed at each frequency (Eq. 5 with `R_k`), as
    /// [`ForwardModel::measure`] reads them: the phasor is each
    /// measurement's `buckets`.
    pub fn measure<'a>(&'a self, returns: &'a [Return]) -> impl ExactSizeIterator<Item = Measurement> + 'a {
        self.models.iter().map(move |m| m.measure(returns))
    }

    /// The measurements at each frequency of a pixel looking through a layer
    /// at a background: [`ForwardModel::layer_returns`] once, mixed per frequency.
    pub fn measure_layer(&self, scene: &LayerScene) -> impl ExactSizeIterator<Item = Measurement> + '_ {
        let mut r = [Return::default(); MAX_BOUNCES];
        let n = self.models[0].layer_returns(scene, &mut r);
        self.models.iter().map(move |m| m.measure(&r[..n]))
    }
}

/// The search over the layer's distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanSettings {
    /// `d_min`: nearest layer distance considered, mm.
    pub min_distance_mm: f64,
    /// Closest the layer may come to the background (`d1 < db`), mm.
    pub min_separation_mm: f64,
    /// Coarse grid cells per shortest unambiguous range `min R_k`.
    pub cells_per_range: f64,
    /// Width to which the best coarse cells are refined (Brent's search), mm.
    pub tolerance_mm: f64,
}

impl Default for ScanSettings {
    fn default() -> Self {
        Self {
            min_distance_mm: 100.0,
            min_separation_mm: 1.0,
            cells_per_range: 16.0,
            tolerance_mm: 0.05,
        }
    }
}

/// One pixel's measurements at the K frequencies, in the model's order.
#[derive(Debug, Clone, Copy)]
pub struct PixelPhasors<'a> {
    /// `M_k`: the phasors with the object in place.
    pub measured: &'a [Phasor],
    /// `B_k`: the latched background's phasors (taken as exact).
    pub background: &'a [Phasor],
    /// `db`: the latched background's distance, mm.
    pub background_distance_mm: f64,
    /// `sigma_k`: the noise standard deviation of each component of `M_k`.
    pub noise_sigma: &'a [f64],
}

/// The layer recovered at one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MultiFrequencyEstimate {
    /// `d1 = df`: the layer's distance (an opaque surface's if `opaque`), mm.
    pub foreground_distance_mm: f64,
    /// `a = L1`: the layer's return (Eq. 1), >= 0, counts.
    pub first_return: f64,
    /// `ξ` in `[0, 1]`; 0 when `opaque`.
    pub translucency: f64,
    /// `chi^2 = sum_k |M_k - model_k|^2 / sigma_k^2` of the reported fit.
    pub chi_square: f64,
    /// `chi^2` of one return alone less that of the layer before the
    /// background: the likelihood-ratio statistic of ξ = 0.
    pub opacity_statistic: f64,
    /// One return explains the phasors: `opacity_statistic <= `[`CHI_SQUARE_1_95`].
    pub opaque: bool,
    /// Standard deviation of `foreground_distance_mm` from the Fisher
    /// information at the estimate with the stated noise; infinite where the
    /// phasors do not determine it (one frequency, no layer return).
    pub foreground_distance_sigma_mm: f64,
    /// Standard deviation of ξ, `sigma(ξ²) / (2 ξ)`; for an opaque pixel
    /// `sqrt(sigma(ξ²))`, the ξ one standard deviation above 0 would give.
    /// Infinite where ξ is not determined.
    pub translucency_sigma: f64,
}

/// One opaque return fitted to a pixel's phasors ([`MultiFrequencyInversion::single_return`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SingleReturn {
    /// Its distance, mm, in `[d_min, d_min + common range)`.
    pub distance_mm: f64,
    /// Its strength `L`, >= 0, counts.
    pub strength: f64,
    /// `chi^2 = sum_k |M_k - L u_k(d)|^2 / sigma_k^2`.
    pub chi_square: f64,
}

/// The background with one return behind it changed ([`MultiFrequencyInversion::indirect_change`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndirectChange {
    /// The changed return's distance, mm, at or beyond the background's.
    pub distance_mm: f64,
    /// Its strength: > 0 added, < 0 blocked, counts.
    pub strength: f64,
    /// `chi^2 = sum_k |M_k - B_k - c u_k(d2)|^2 / sigma_k^2`.
    pub chi_square: f64,
}

/// The grid of [`MultiFrequencyInversion::indirect_change`] over `[db, hi]`: `D = M - B`
/// and the grid's minima of `chi^2`, with the largest `|<u, D>|` seen on it.
struct IndirectScan<'a> {
    p: Pixel<'a>,
    db: f64,
    hi: f64,
    h: f64,
    /// `<D, D>`.
    dd: f64,
    minima: GridMinima,
    lowest_on_grid: f64,
    largest_ud: f64,
    /// `<u, u>` (constant for the sinusoid).
    uu: f64,
}

impl<'a> IndirectScan<'a> {
    /// The grid over `[db, db + reach_mm]` (within the common range) of a validated pixel.
    fn new(inv: &MultiFrequencyInversion, p: Pixel<'a>, reach_mm: f64) -> Self {
        let db = p.px.background_distance_mm;
        let hi = (db + reach_mm.max(0.0))
            .min(inv.settings.min_distance_mm + inv.common_range_mm)
            .max(db);
        let f = &p.fixed;
        let dd = (f.mm - 2.0 * f.bm + f.bb).max(0.0);
        let (cells, h) = inv.grid(db, hi);
        let (mut minima, mut lowest_on_grid, mut largest_ud, mut uu) =
            (GridMinima::default(), f64::INFINITY, 0.0_f64, 0.0);
        inv.scan_grams(&p, db, h, cells, |d, g| {
            let chi = Self::fit_with(dd, g).1;
            minima.push(d, chi, None);
            lowest_on_grid = lowest_on_grid.min(chi);
            largest_ud = largest_ud.max((g.um - g.ub).abs());
            uu = g.uu;
        });
        Self {
            p,
            db,
            hi,
            h,
            dd,
            minima,
            lowest_on_grid,
            largest_ud,
            uu,
        }
    }

    /// `(c, chi^2)` at one `d2`: `c = <u, D> / <u, u>`, `chi^2 = <D, D> - c <u, D>`.
    fn fit(&self, g: Gram) -> (f64, f64) {
        Self::fit_with(self.dd, g)
    }

    fn fit_with(dd: f64, g: Gram) -> (f64, f64) {
        let ud = g.um - g.ub;
        let c = if g.uu > 0.0 { ud / g.uu } else { 0.0 };
        (c, (dd - c * ud).max(0.0))
    }

    /// A bound under `chi^2` everywhere on `[db, hi]` (the sinusoid only; `None` otherwise).
    fn lower_bound(&self, inv: &MultiFrequencyInversion) -> Option<f64> {
        if !(self.uu > 0.0 && inv.sinusoid()) {
            return None;
        }
        let slope: f64 = (0..inv.sensors.len())
            .map(|k| inv.sensors[k].phase(1.0).abs() * self.p.weight(k) * self.p.change_amplitude(k))
            .sum();
        let ud = self.largest_ud + slope * self.h / 2.0;
        Some((self.dd - ud * ud / self.uu).max(0.0))
    }
}

/// Two returns fitted to one pixel with no background ([`MultiFrequencyInversion::two_free_returns`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TwoReturns {
    /// The near return's distance (the layer's, or the one surface's), mm.
    pub near_distance_mm: f64,
    /// Its strength `a1 >= 0`, counts.
    pub near_strength: f64,
    /// The far return's distance (what the layer lets through), mm.
    pub far_distance_mm: f64,
    /// Its strength `a2 >= 0` (0: one return explains the pixel), counts.
    pub far_strength: f64,
    /// `chi^2 = sum_k |M_k - a1 u_k(d1) - a2 u_k(d2)|^2 / sigma_k^2`.
    pub chi_square: f64,
    /// The standard deviation of the near distance, mm (infinite where not determined).
    pub near_distance_sigma_mm: f64,
}

/// Rounds of Brent's search on each distance in turn after the grid of pairs.
const FREE_REFINE_ROUNDS: usize = 2;

/// Gauss-Newton steps after them.
const FREE_NEWTON_STEPS: usize = 8;

/// The grid's lowest local minima of pairs that are refined.
const FREE_STARTS: usize = 6;

/// A pixel's fixed products for fits of two free returns: `w_k = 1 / sigma_k^2`, `<M, M>`.
struct FreeFit<'a> {
    measured: &'a [Phasor],
    weights: [f64; ROTATED_FREQUENCIES],
    mm: f64,
}

/// The strengths and `chi^2` of two returns at fixed distances.
#[derive(Debug, Clone, Copy)]
struct PairFit {
    near: f64,
    far: f64,
    chi_square: f64,
}

impl<'a> FreeFit<'a> {
    fn new(inv: &MultiFrequencyInversion, measured: &'a [Phasor], noise_sigma: &[f64]) -> Self {
        let mut weights = [0.0; ROTATED_FREQUENCIES];
        let mut mm = 0.0;
        for ((w, s), m) in weights
            .iter_mut()
            .zip(noise_sigma)
            .zip(measured)
            .take(inv.sensors.len())
        {
            *w = 1.0 / (s * s);
            mm += *w * dot(*m, *m);
        }
        Self { measured, weights, mm }
    }

    /// Non-negative least squares of the two strengths given their unit returns, in closed
    /// form: the normal equations where both come out >= 0, else the better single one.
    fn pair(&self, u1: &[Phasor], u2: &[Phasor]) -> PairFit {
        let (one, two) = (self.alone(u1), self.alone(u2));
        self.pair_of(one, two, self.cross(u1, u2))
    }

    /// `(<u, u>, <u, M>)` of one return's unit phasors `u`, weighted.
    fn alone(&self, u: &[Phasor]) -> (f64, f64) {
        let (mut g, mut p) = (0.0, 0.0);
        for ((a, m), w) in u.iter().zip(self.measured).zip(&self.weights) {
            g += w * dot(*a, *a);
            p += w * dot(*a, *m);
        }
        (g, p)
    }

    /// `<u1, u2>`, weighted.
    fn cross(&self, u1: &[Phasor], u2: &[Phasor]) -> f64 {
        u1.iter()
            .zip(u2)
            .zip(&self.weights)
            .fold(0.0, |g, ((a, b), w)| g + w * dot(*a, *b))
    }

    /// [`Self::pair`] from its inner products: each return's [`Self::alone`] and their
    /// [`Self::cross`] (a grid of pairs works each return's out once, not at every pair).
    fn pair_of(&self, (g11, p1): (f64, f64), (g22, p2): (f64, f64), g12: f64) -> PairFit {
        let det = g11 * g22 - g12 * g12;
        if det > 1e-12 * g11 * g22 {
            let (a1, a2) = ((p1 * g22 - p2 * g12) / det, (p2 * g11 - p1 * g12) / det);
            if a1 >= 0.0 && a2 >= 0.0 {
                return PairFit {
                    near: a1,
                    far: a2,
                    chi_square: (self.mm - a1 * p1 - a2 * p2).max(0.0),
                };
            }
        }
        let one = |p: f64, g: f64| if g > 0.0 { p.max(0.0) / g } else { 0.0 };
        let (a1, a2) = (one(p1, g11), one(p2, g22));
        let (c1, c2) = (self.mm - a1 * p1, self.mm - a2 * p2);
        if c1 <= c2 {
            PairFit {
                near: a1,
                far: 0.0,
                chi_square: c1.max(0.0),
            }
        } else {
            PairFit {
                near: 0.0,
                far: a2,
                chi_square: c2.max(0.0),
            }
        }
    }

    /// [`Self::pair`] at two distances.
    fn pair_at(&self, inv: &MultiFrequencyInversion, d1: f64, d2: f64) -> PairFit {
        let k = inv.sensors.len().min(ROTATED_FREQUENCIES);
        let mut u1 = [Phasor::default(); ROTATED_FREQUENCIES];
        let mut u2 = [Phasor::default(); ROTATED_FREQUENCIES];
        for ((a, b), s) in u1.iter_mut().zip(u2.iter_mut()).zip(&inv.sensors) {
            *a = inv.unit_return(s, d1);
            *b = inv.unit_return(s, d2);
        }
        self.pair(&u1[..k], &u2[..k])
    }
}

/// The best layer at one fixed ξ: a point of the profile over ξ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TranslucencyFit {
    /// The ξ held.
    pub translucency: f64,
    /// `d1`, mm.
    pub foreground_distance_mm: f64,
    /// `a = L1`, counts.
    pub first_return: f64,
    /// The weighted residual `chi^2`.
    pub chi_square: f64,
}

/// The per-pixel inversion at K frequencies against a latched background.
/// [`MultiFrequencyInversion::invert`] allocates nothing.
#[derive(Debug, Clone)]
pub struct MultiFrequencyInversion {
    sensors: Vec<Sensor>,
    /// The layer return's extra path (the model's subsurface delay), mm.
    delay_mm: f64,
    settings: ScanSettings,
    coarse_step_mm: f64,
    common_range_mm: f64,
    /// Per frequency, the unit return turned back by each of [`NEAR_BACKGROUND_MM`]:
    /// `e^{-i omega_k s}` (sinusoids; empty otherwise).
    near_turns: Vec<[Phasor; NEAR_BACKGROUND_POINTS]>,
}

/// The weighted inner products of one pixel that do not depend on `d1`:
/// `<B, B>`, `<B, M>`, `<M, M>` with weights `1 / sigma_k^2`.
#[derive(Debug, Clone, Copy)]
struct Fixed {
    bb: f64,
    bm: f64,
    mm: f64,
}

/// The inner products with the layer's unit phasor `u(d1)`: `<u, u>`, `<u, B>`, `<u, M>`.
#[derive(Debug, Clone, Copy, Default)]
struct Gram {
    uu: f64,
    ub: f64,
    um: f64,
}

/// A validated pixel: its inputs, the fixed products and the scan's range.
#[derive(Debug, Clone, Copy)]
struct Pixel<'a> {
    px: &'a PixelPhasors<'a>,
    fixed: Fixed,
    lo: f64,
    hi: f64,
    /// `1 / sigma_k^2` of the first [`HELD_WEIGHTS`] frequencies, worked out once.
    weights: [f64; HELD_WEIGHTS],
}

/// Frequencies whose weights `1 / sigma_k^2` a [`Pixel`] holds (more are worked out where used).
const HELD_WEIGHTS: usize = 8;

impl Pixel<'_> {
    /// `1 / sigma_k^2`, the weight of frequency `k`.
    fn weight(&self, k: usize) -> f64 {
        self.weights.get(k).copied().unwrap_or_else(|| {
            let sigma = self.px.noise_sigma[k];
            1.0 / (sigma * sigma)
        })
    }

    /// `|M_k - B_k|`: how far the phasor at frequency `k` moved from the background's.
    fn change_amplitude(&self, k: usize) -> f64 {
        let (m, b) = (self.px.measured[k], self.px.background[k]);
        (m.a - b.a).hypot(m.b - b.b)
    }

    /// The scan's range `[lo, hi]` narrowed to `[near, far]` where that lies inside it.
    fn within(&self, near: f64, far: f64) -> (f64, f64) {
        let hi = if far < self.hi { far.max(self.lo) } else { self.hi };
        let lo = if near > self.lo { near.min(hi) } else { self.lo };
        (lo, hi)
    }
}

/// `(a, t = ξ², chi^2)` at one `d1`.
#[derive(Debug, Clone, Copy)]
struct Amplitudes {
    a: f64,
    t: f64,
    chi_square: f64,
}

fn dot(p: Phasor, q: Phasor) -> f64 {
    p.a * q.a + p.b * q.b
}

impl Gram {
    /// `chi^2(a, t) = |M - a u - t B|^2`, expanded in the inner products.
    fn chi_square(&self, f: &Fixed, a: f64, t: f64) -> f64 {
        let q = f.mm - 2.0 * a * self.um - 2.0 * t * f.bm + a * a * self.uu + 2.0 * a * t * self.ub + t * t * f.bb;
        q.max(0.0)
    }

    /// The non-negative least squares `min_{a >= 0, 0 <= t <= 1} |M - a u - t B|^2`
    /// in closed form: the unconstrained normal equations if their solution is
    /// admissible, else the best of the box's edges (the problem is convex).
    fn two_returns(&self, f: &Fixed) -> Amplitudes {
        let det = self.uu * f.bb - self.ub * self.ub;
        if det > 1e-12 * self.uu * f.bb {
            let a = (self.um * f.bb - f.bm * self.ub) / det;
            let t = (f.bm * self.uu - self.um * self.ub) / det;
            if a >= 0.0 && (0.0..=1.0).contains(&t) {
                return self.amplitudes(f, a, t);
            }
        }
        let edges = [
            (0.0, (f.bm / f.bb).clamp(0.0, 1.0)),
            (self.return_at(0.0), 0.0),
            (self.return_at(1.0), 1.0),
        ];
        let mut best = self.amplitudes(f, edges[0].0, edges[0].1);
        for (a, t) in edges.into_iter().skip(1) {
            let c = self.amplitudes(f, a, t);
            if c.chi_square < best.chi_square {
                best = c;
            }
        }
        best
    }

    /// `a = max(0, <u, M - t B> / <u, u>)`: the layer's return with `ξ² = t` held.
    fn return_at(&self, t: f64) -> f64 {
        if self.uu > 0.0 {
            ((self.um - t * self.ub) / self.uu).max(0.0)
        } else {
            0.0
        }
    }

    fn amplitudes(&self, f: &Fixed, a: f64, t: f64) -> Amplitudes {
        Amplitudes {
            a,
            t,
            chi_square: self.chi_square(f, a, t),
        }
    }
}

impl MultiFrequencyInversion {
    /// The inversion for `model`'s frequencies and waveform.
    pub fn new(model: &MultiFrequencyModel, settings: ScanSettings) -> Result<Self, MultiFrequencyError> {
        let s = &settings;
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !(positive(s.cells_per_range) && positive(s.tolerance_mm)) {
            return Err(MultiFrequencyError::InvalidSettings(
                "cells_per_range and tolerance_mm must be > 0",
            ));
        }
        if !(s.min_distance_mm.is_finite() && s.min_separation_mm.is_finite() && s.min_separation_mm >= 0.0) {
            return Err(MultiFrequencyError::InvalidSettings(
                "distances must be finite, the separation >= 0",
            ));
        }
        let sensors: Vec<Sensor> = model.models().iter().map(|m| m.sensor.clone()).collect();
        let shortest = sensors
            .iter()
            .map(Sensor::unambiguous_range_mm)
            .fold(f64::INFINITY, f64::min);
        let near_turns = sensors
            .iter()
            .filter(|s| s.waveform == Waveform::Sinusoid)
            .map(|s| {
                NEAR_BACKGROUND_MM.map(|off| {
                    let (sin, cos) = s.phase(-off).sin_cos();
                    Phasor { a: cos, b: sin }
                })
            })
            .collect();
        Ok(Self {
            near_turns,
            sensors,
            delay_mm: model.models()[0].options.subsurface_delay_mm,
            settings,
            coarse_step_mm: shortest / settings.cells_per_range,
            common_range_mm: model.common_unambiguous_range_mm(),
        })
    }

    /// The layer at one pixel: `d1`, `a >= 0` and ξ in `[0, 1]` minimising
    ///
    /// ```text
    /// chi^2 = sum_k |M_k - a u_k(d1) - ξ² B_k|^2 / sigma_k^2
    /// ```
    ///
    /// `(a, ξ²)` in closed form at each `d1` (variable projection), `d1` by a
    /// coarse scan over `[d_min, db - separation]` refined by Newton's method
    /// ([`Self::layer_and_single`]). The pixel is opaque (ξ = 0, `d1` the single return's distance,
    /// searched up to `db`) when dropping the background term raises `chi^2`
    /// by at most [`CHI_SQUARE_1_95`].
    pub fn invert(&self, px: &PixelPhasors) -> Result<MultiFrequencyEstimate, MultiFrequencyError> {
        let p = self.pixel(px)?;
        let [(d1, _), (d0, single_chi_square)] = self.layer_and_single(&p);
        let layer = self.gram(&p, d1).two_returns(&p.fixed);
        let opacity_statistic = (single_chi_square - layer.chi_square).max(0.0);
        if opacity_statistic <= CHI_SQUARE_1_95 {
            return Ok(self.opaque_estimate(&p, d0, single_chi_square, opacity_statistic));
        }
        let [var_d, _, var_t] = Self::variances(&self.fisher(&p, d1, layer.a));
        let xi = layer.t.sqrt();
        Ok(MultiFrequencyEstimate {
            foreground_distance_mm: d1,
            first_return: layer.a,
            translucency: xi,
            chi_square: layer.chi_square,
            opacity_statistic,
            opaque: false,
            foreground_distance_sigma_mm: var_d.sqrt(),
            translucency_sigma: if xi > 0.0 {
                var_t.sqrt() / (2.0 * xi)
            } else {
                var_t.sqrt().sqrt()
            },
        })
    }

    /// The layer's per-pixel fit of [`Self::invert`] before the opacity test: `d1`, `a >= 0`
    /// and ξ of the global minimum of `chi^2` over `[d_min, db - separation]` (what the plain
    /// grid of `bench::reference` finds at its resolution).
    pub fn layer(&self, px: &PixelPhasors) -> Result<TranslucencyFit, MultiFrequencyError> {
        let p = self.pixel(px)?;
        let [(d1, _), _] = self.layer_and_single(&p);
        Ok(self.layer_fit(&p, d1))
    }

    /// The layer's fit with its distance held at `d1`: `a >= 0` and `ξ² = t` in `[0, 1]` by the
    /// closed-form least squares, and its `chi^2` (the projected objective at one point).
    pub fn layer_at(&self, px: &PixelPhasors, d1: f64) -> Result<TranslucencyFit, MultiFrequencyError> {
        Ok(self.layer_fit(&self.pixel(px)?, d1))
    }

    fn layer_fit(&self, p: &Pixel, d1: f64) -> TranslucencyFit {
        let layer = self.gram(p, d1).two_returns(&p.fixed);
        TranslucencyFit {
            translucency: layer.t.max(0.0).sqrt(),
            foreground_distance_mm: d1,
            first_return: layer.a,
            chi_square: layer.chi_square,
        }
    }

    /// The global minima `(d, chi^2)` of the layer's projected `chi^2` over `[d_min, db -
    /// separation]` and of the single return's over `[d_min, db]`, the amplitudes eliminated
    /// in closed form at each distance (variable projection). One coarse scan finds each
    /// objective's two lowest grid minima (tens of points, no trigonometry: the start); a
    /// second is dropped where a bound shows it cannot win; each kept one is refined within
    /// its cells by Newton's method on the projected objective (sinusoids), else by Brent's
    /// search.
    fn layer_and_single(&self, p: &Pixel) -> [(f64, f64); 2] {
        let db = p.px.background_distance_mm;
        let two = |g: Gram| g.two_returns(&p.fixed).chi_square;
        let one = |g: Gram| g.chi_square(&p.fixed, g.return_at(0.0), 0.0);
        // One scan serves both: the layer's objective up to `db - separation` (its last point
        // moved there: a layer at the background's return may fit best at the bound, in a
        // well narrower than a cell), the single return's up to `db`.
        let (cells, h) = self.grid(p.lo, db);
        let (mut layer_minima, mut single_minima) = (GridMinima::default(), GridMinima::default());
        self.scan_grams(p, p.lo, h, cells, |d, g| {
            if d <= p.hi {
                layer_minima.push(d, two(g), Some(g));
            } else if d - h < p.hi {
                let end = self.gram(p, p.hi);
                layer_minima.push(p.hi, two(end), Some(end));
            }
            single_minima.push(d, one(g), Some(g));
        });
        // A second minimum is searched only where it could beat the first.
        let slack = self.cell_slack(p, h);
        let layer_lowest = worth_refining(layer_minima.lowest(), slack.map(|s| s.layer), &p.fixed, two);
        let single_lowest = worth_refining(single_minima.lowest(), slack.map(|s| s.single), &p.fixed, one);
        if self.sinusoid() && self.sensors.len() <= ROTATED_FREQUENCIES {
            let tol = self.settings.tolerance_mm;
            let layer = layer_lowest.map(|m| newton_near(&m, (p.lo, p.hi), h, tol, |d| self.layer_projected(p, d)));
            let single = single_lowest.map(|m| newton_near(&m, (p.lo, db), h, tol, |d| self.single_projected(p, d)));
            let near = self.near_background(p, tol);
            return [lowest_of(&[layer[0], layer[1], near], p.lo), lowest_of(&single, p.lo)];
        }
        // Both objectives' searches stepped together (the same points as one after the other).
        let [l0, l1] = self.searches(layer_lowest, p.lo, p.hi, h);
        let [s0, s1] = self.searches(single_lowest, p.lo, db, h);
        let [l0, l1, s0, s1] = search_together([l0, l1, s0, s1], |i, d| {
            let g = self.gram(p, d);
            if i < 2 {
                two(g)
            } else {
                one(g)
            }
        });
        [lowest_found(&[l0, l1], p.lo), lowest_found(&[s0, s1], p.lo)]
    }

    /// The layer's lowest minimum within [`NEAR_BACKGROUND_MM`] of the bound `db - separation`
    /// (sinusoids), `(d1, chi^2)`: there the layer's return and the background's are nearly
    /// parallel, the two amplitudes ill-conditioned, and a well a few millimetres wide (the
    /// background's own return moved: `t = 0`, `a` its strength) hides between the coarse
    /// scan's points. Its points step away from the bound geometrically (each `u(d1)` the
    /// bound's turned by a fixed phasor); the lowest is refined by Newton's method between
    /// its neighbours.
    fn near_background(&self, p: &Pixel, tol: f64) -> (f64, f64) {
        let mut grams = [Gram::default(); NEAR_BACKGROUND_POINTS];
        let px = p.px;
        for (k, ((s, b), m)) in self.sensors.iter().zip(px.background).zip(px.measured).enumerate() {
            let (w, u) = (p.weight(k), self.unit_return(s, p.hi));
            for (g, t) in grams.iter_mut().zip(&self.near_turns[k]) {
                let v = Phasor {
                    a: u.a * t.a - u.b * t.b,
                    b: u.a * t.b + u.b * t.a,
                };
                g.uu += w * dot(v, v);
                g.ub += w * dot(v, *b);
                g.um += w * dot(v, *m);
            }
        }
        let at = |j: usize| p.hi - NEAR_BACKGROUND_MM[j];
        let mut best = (0, f64::INFINITY);
        for (j, g) in grams.iter().enumerate() {
            let chi = g.two_returns(&p.fixed).chi_square;
            if at(j) >= p.lo && chi < best.1 {
                best = (j, chi);
            }
        }
        let j = best.0;
        let bracket = (
            at((j + 1).min(NEAR_BACKGROUND_POINTS - 1)).max(p.lo),
            at(j.saturating_sub(1)),
        );
        newton_minimum(bracket, at(j), tol, |d| self.layer_projected(p, d))
    }

    /// The layer's projected `chi^2` at `d1` with its first two derivatives: `(a, ξ²)` of the
    /// closed-form least squares ([`Gram::two_returns`]), and the slopes of whichever piece
    /// of it is active there ([`Projection`]).
    fn layer_projected(&self, p: &Pixel, d1: f64) -> Projected {
        let s = self.gram_slopes(p, d1);
        let fit = s.gram.two_returns(&p.fixed);
        let piece = if fit.a > 0.0 && fit.t > 0.0 && fit.t < 1.0 {
            Projection::Both
        } else if fit.a > 0.0 {
            Projection::LayerAt(fit.t)
        } else {
            Projection::NoLayer
        };
        s.projected(&p.fixed, fit.chi_square, piece)
    }

    /// The single return's projected `chi^2` (`ξ = 0`, `a >= 0`) at `d` with its first two
    /// derivatives.
    fn single_projected(&self, p: &Pixel, d: f64) -> Projected {
        let s = self.gram_slopes(p, d);
        let a = s.gram.return_at(0.0);
        let piece = if a > 0.0 {
            Projection::LayerAt(0.0)
        } else {
            Projection::NoLayer
        };
        s.projected(&p.fixed, s.gram.chi_square(&p.fixed, a, 0.0), piece)
    }

    /// The Gram products at `d1` and the first two derivatives of `<u, B>` and `<u, M>` (the
    /// sinusoid: `u_k' = i omega_k u_k`, `u_k'' = -omega_k^2 u_k`, `<u, u>` constant): one
    /// sine and cosine per frequency give all three.
    fn gram_slopes(&self, p: &Pixel, d1: f64) -> GramSlopes {
        let mut s = GramSlopes::default();
        let px = p.px;
        for (k, ((sensor, b), m)) in self.sensors.iter().zip(px.background).zip(px.measured).enumerate() {
            let (w, omega) = (p.weight(k), sensor.phase(1.0));
            let u = self.unit_return(sensor, d1);
            let turned = Phasor { a: -u.b, b: u.a };
            let (ub, um) = (dot(u, *b), dot(u, *m));
            s.gram.uu += w * dot(u, u);
            s.gram.ub += w * ub;
            s.gram.um += w * um;
            s.ub1 += w * omega * dot(turned, *b);
            s.um1 += w * omega * dot(turned, *m);
            s.ub2 -= w * omega * omega * ub;
            s.um2 -= w * omega * omega * um;
        }
        s
    }

    /// The best layer with ξ held: `d1` scanned as in [`Self::invert`], `a`
    /// in closed form. Over several ξ this is the profile that shows whether
    /// the phasors determine ξ (with one frequency they do not).
    pub fn fit_at_translucency(&self, px: &PixelPhasors, xi: f64) -> Result<TranslucencyFit, MultiFrequencyError> {
        self.fit_at_translucency_within(px, xi, (f64::NEG_INFINITY, f64::INFINITY))
    }

    /// [`Self::fit_at_translucency`] with the layer's distance searched only within
    /// `[near, far]` (and the scan's own range): whether a layer where another layer's surface
    /// lies, and clear of the background, explains the phasors (with its distance free up to
    /// the background, a share of the background's own return left over, as a pixel partly
    /// covered shows, fits as a "layer" right at it).
    pub fn fit_at_translucency_within(
        &self,
        px: &PixelPhasors,
        xi: f64,
        (near, far): (f64, f64),
    ) -> Result<TranslucencyFit, MultiFrequencyError> {
        if !(0.0..=1.0).contains(&xi) {
            return Err(MultiFrequencyError::TranslucencyOutOfRange(xi));
        }
        let p = self.pixel(px)?;
        let t = xi * xi;
        let (lo, hi) = p.within(near, far);
        let (d1, chi_square) = self.minimise(lo, hi, |d| {
            let g = self.gram(&p, d);
            g.chi_square(&p.fixed, g.return_at(t), t)
        });
        Ok(TranslucencyFit {
            translucency: xi,
            foreground_distance_mm: d1,
            first_return: self.gram(&p, d1).return_at(t),
            chi_square,
        })
    }

    /// The best layer with ξ free and its distance searched only within `[near, far]` (and
    /// the scan's own range): `d1`, `a` and `ξ² = t` of `min |M - a u(d1) - t B|^2` as in
    /// [`Self::invert`]. With fewer frequencies than the camera's (one left out, to see how
    /// far ξ moves with it) the common range may be short, and the window keeps the layer
    /// where all of them put it.
    pub fn layer_within(
        &self,
        px: &PixelPhasors,
        (near, far): (f64, f64),
    ) -> Result<TranslucencyFit, MultiFrequencyError> {
        let p = self.pixel(px)?;
        let (lo, hi) = p.within(near, far);
        let (d1, chi_square) = self.minimise(lo, hi, |d| self.gram(&p, d).two_returns(&p.fixed).chi_square);
        let layer = self.gram(&p, d1).two_returns(&p.fixed);
        Ok(TranslucencyFit {
            translucency: layer.t.max(0.0).sqrt(),
            foreground_distance_mm: d1,
            first_return: layer.a,
            chi_square,
        })
    }

    /// The share of the background's return left at a pixel with a layer's return at
    /// `d1`: `t` of the least squares `min_{a >= 0, t} |M - a u(d1) - t B|^2` (`t` unbounded),
    /// and its standard deviation `sqrt(<u, u> / det)`. A pixel that a layer of `ξ` covers
    /// by a share `c` shows `t = 1 - c (1 - ξ^2)` (the one forward model: the covered part
    /// is the layer's two returns, the rest the background's), so `t` says how much of it
    /// the layer covers even where the layer's own return is under the noise.
    pub fn background_share_at(&self, px: &PixelPhasors, d1: f64) -> Result<(f64, f64), MultiFrequencyError> {
        let p = self.pixel(px)?;
        let (g, f) = (self.gram(&p, d1), &p.fixed);
        let det = g.uu * f.bb - g.ub * g.ub;
        if !(det > 1e-12 * g.uu * f.bb) {
            // No return at d1 to separate from the background's: t alone.
            return Ok((f.bm / f.bb, f.bb.recip().sqrt()));
        }
        let (a, t) = ((g.um * f.bb - f.bm * g.ub) / det, (f.bm * g.uu - g.um * g.ub) / det);
        if a >= 0.0 {
            Ok((t, (g.uu / det).sqrt()))
        } else {
            Ok((f.bm / f.bb, f.bb.recip().sqrt()))
        }
    }

    /// The background's phasors with one more return changed (added, `c > 0`, or blocked,
    /// `c < 0`) behind it: `min |M - B - c u(d2)|^2` over `db <= d2 <= db + reach_mm` (and
    /// the common unambiguous range), `c` in closed form at each `d2`. Light that reaches a
    /// surface by way of another (a table, a wall, an object beside it) travels at least
    /// the direct path (the triangle inequality), so an object that blocks or adds such
    /// light changes a pixel's phasors by a return at or beyond its background: no layer
    /// stands before it.
    pub fn indirect_change(&self, px: &PixelPhasors, reach_mm: f64) -> Result<IndirectChange, MultiFrequencyError> {
        Ok(self.refined(&IndirectScan::new(self, self.pixel(px)?, reach_mm)))
    }

    /// [`Self::indirect_change`] refined from its grid.
    fn refined(&self, scan: &IndirectScan) -> IndirectChange {
        let (d2, chi_square) = self.refine(scan.minima.lowest(), scan.db, scan.hi, scan.h, |d| {
            scan.fit(self.gram(&scan.p, d)).1
        });
        IndirectChange {
            distance_mm: d2,
            strength: scan.fit(self.gram(&scan.p, d2)).0,
            chi_square,
        }
    }

    /// Whether [`Self::indirect_change`]'s `chi^2` is at most `limit`, refining only where
    /// the grid cannot tell: a grid point at or under it says yes; for the sinusoid,
    /// `chi^2(d2) = <D, D> - <u, D>^2 / <u, u>` with `|d <u, D> / d d2| <= sum_k w_k omega_k
    /// |D_k|`, so no point within half a cell of the grid falls under a bound the grid
    /// gives, and a bound above `limit` says no; nor does [`Self::amplitude_spread`] above it.
    pub fn indirect_change_within(
        &self,
        px: &PixelPhasors,
        reach_mm: f64,
        limit: f64,
    ) -> Result<bool, MultiFrequencyError> {
        let p = self.pixel(px)?;
        if self.amplitude_spread(&p).is_some_and(|spread| spread > limit) {
            return Ok(false);
        }
        let scan = IndirectScan::new(self, p, reach_mm);
        if scan.lowest_on_grid <= limit {
            return Ok(true);
        }
        if scan.lower_bound(self).is_some_and(|bound| bound > limit) {
            return Ok(false);
        }
        Ok(self.refined(&scan).chi_square <= limit)
    }

    /// A bound under [`Self::indirect_change`]'s `chi^2` at every `d2`, for the sinusoid
    /// (`None` otherwise): one return has the same amplitude at every frequency (`|u_k| = 1`),
    /// so `|D_k - c u_k| >= | |D_k| - |c| |` with `D = M - B`, and `chi^2` is at least the
    /// weighted spread of the amplitudes `|D_k|` about their weighted mean. A layer's return
    /// and the background's dimming interfere differently at each frequency, which spreads
    /// them; a change one return behind the background makes does not.
    fn amplitude_spread(&self, p: &Pixel) -> Option<f64> {
        if !self.sinusoid() {
            return None;
        }
        let k = self.sensors.len();
        let total: f64 = (0..k).map(|j| p.weight(j)).sum();
        let mean = (0..k).map(|j| p.weight(j) * p.change_amplitude(j)).sum::<f64>() / total;
        Some(
            (0..k)
                .map(|j| p.weight(j) * (p.change_amplitude(j) - mean).powi(2))
                .sum(),
        )
    }

    /// Every frequency's correlation is the sinusoid (unit returns of one amplitude, turning
    /// at a constant rate): what the scans' rotation and their bounds rely on.
    fn sinusoid(&self) -> bool {
        self.sensors.iter().all(|s| s.waveform == Waveform::Sinusoid)
    }

    /// The frequencies' common unambiguous range, mm.
    pub fn common_unambiguous_range_mm(&self) -> f64 {
        self.common_range_mm
    }

    /// Two returns fitted to a pixel's phasors with no background latched (physics.md §7,
    /// objects.md: three frequencies, no background): `M_k = a1 u_k(d1) + a2 u_k(d2)` with
    /// `d_min <= d1 < d2 <= max_distance_mm` (within the common unambiguous range) and
    /// `a1, a2 >= 0`. Both distances on a grid of the coarse step (pairs at least one cell
    /// apart), the strengths by non-negative least squares in closed form at each pair; the
    /// best pair refined by Brent's search on each distance in turn. The near return is the
    /// layer (or the one surface, where the far one comes out empty).
    pub fn two_free_returns(
        &self,
        measured: &[Phasor],
        noise_sigma: &[f64],
        max_distance_mm: f64,
    ) -> Result<TwoReturns, MultiFrequencyError> {
        self.check_measured(measured, noise_sigma)?;
        if self.sensors.len() > ROTATED_FREQUENCIES {
            return Err(MultiFrequencyError::InvalidSettings(
                "two free returns are fitted at up to 8 frequencies",
            ));
        }
        let lo = self.settings.min_distance_mm;
        let hi = max_distance_mm.min(lo + self.common_range_mm);
        if !(hi - lo > 2.0 * self.coarse_step_mm) {
            return Err(MultiFrequencyError::BackgroundTooNear {
                background_distance_mm: max_distance_mm,
                min_distance_mm: lo,
            });
        }
        let fit = FreeFit::new(self, measured, noise_sigma);
        let (cells, h) = self.grid(lo, hi);
        let sep = self.settings.min_separation_mm.max(0.5 * self.settings.tolerance_mm);
        let chi_at = |d1: f64, d2: f64| fit.pair_at(self, d1, d2).chi_square;
        let mut best = (f64::INFINITY, lo, hi);
        for (j1, j2) in self.pair_grid_starts(&fit, lo, h, cells) {
            let (mut d1, mut d2) = (lo + j1 as f64 * h, lo + j2 as f64 * h);
            for _ in 0..FREE_REFINE_ROUNDS {
                let near = ((d1 - h).max(lo), (d1 + h).min(d2 - sep));
                if near.1 > near.0 {
                    d1 = self.refine_alone(near, d1, |d| chi_at(d, d2)).0;
                }
                let far = ((d2 - h).max(d1 + sep), (d2 + h).min(hi));
                if far.1 > far.0 {
                    d2 = self.refine_alone(far, d2, |d| chi_at(d1, d)).0;
                }
            }
            (d1, d2) = self.free_gauss_newton(&fit, noise_sigma, (d1, d2), (lo, hi, sep));
            let c = chi_at(d1, d2);
            if c < best.0 {
                best = (c, d1, d2);
            }
        }
        let (_, d1, d2) = best;
        let pair = fit.pair_at(self, d1, d2);
        let sigma = self.free_distance_sigma(noise_sigma, (d1, pair.near), (d2, pair.far));
        Ok(TwoReturns {
            near_distance_mm: d1,
            near_strength: pair.near,
            far_distance_mm: d2,
            far_strength: pair.far,
            chi_square: pair.chi_square,
            near_distance_sigma_mm: sigma,
        })
    }

    /// The grid cells `(j1, j2)`, `j1 < j2`, of the [`FREE_STARTS`] lowest local minima of two
    /// free returns' `chi^2` over the pairs of the grid `lo + j h`, `j = 0..=cells`, lowest first.
    fn pair_grid_starts(&self, fit: &FreeFit, lo: f64, h: f64, cells: usize) -> Vec<(usize, usize)> {
        let units: Vec<Phasor> = (0..=cells)
            .flat_map(|j| self.sensors.iter().map(move |s| (s, lo + j as f64 * h)))
            .map(|(s, d)| self.unit_return(s, d))
            .collect();
        let k = self.sensors.len();
        let at = |j: usize| &units[j * k..(j + 1) * k];
        let n = cells + 1;
        let alone: Vec<(f64, f64)> = (0..n).map(|j| fit.alone(at(j))).collect();
        let mut chi = vec![f64::INFINITY; n * n];
        for j1 in 0..cells {
            for j2 in j1 + 1..n {
                chi[j1 * n + j2] = fit.pair_of(alone[j1], alone[j2], fit.cross(at(j1), at(j2))).chi_square;
            }
        }
        let mut starts: Vec<(f64, usize, usize)> = vec![];
        for j1 in 0..cells {
            for j2 in j1 + 1..n {
                let c = chi[j1 * n + j2];
                let neighbours = (j1.saturating_sub(1)..=(j1 + 1).min(cells))
                    .flat_map(|a| (j2.saturating_sub(1)..=(j2 + 1).min(cells)).map(move |b| (a, b)));
                if !neighbours
                    .into_iter()
                    .any(|(a, b)| (a, b) != (j1, j2) && chi[a * n + b] < c)
                {
                    starts.push((c, j1, j2));
                }
            }
        }
        starts.sort_by(|a, b| a.0.total_cmp(&b.0));
        starts
            .into_iter()
            .take(FREE_STARTS)
            .map(|(_, j1, j2)| (j1, j2))
            .collect()
    }

    /// The minimum of `f` on `bracket` near `x`, Brent's search seeded with `x` and the
    /// bracket's ends.
    fn refine_alone(&self, bracket: (f64, f64), x: f64, f: impl Fn(f64) -> f64) -> (f64, f64) {
        let (fx, fl, fh) = (f(x), f(bracket.0), f(bracket.1));
        let (l, r) = ((bracket.0, fl), (bracket.1, fh));
        let (near, far) = if fl <= fh { (l, r) } else { (r, l) };
        let mut seed = [(x, fx), near, far];
        seed.sort_by(|a, b| a.1.total_cmp(&b.1));
        brent_minimum(bracket, seed, self.settings.tolerance_mm, &f)
    }

    /// The Fisher information of two free returns' `(d1, a1, d2, a2)` (columns `a1 u'(d1)`,
    /// `u(d1)`, `a2 u'(d2)`, `u(d2)`, weighted by `1 / sigma_k^2`), and those columns.
    fn free_fisher(
        &self,
        noise_sigma: &[f64],
        near: (f64, f64),
        far: (f64, f64),
    ) -> (Matrix4<f64>, [[Phasor; 4]; ROTATED_FREQUENCIES]) {
        let mut f = Matrix4::<f64>::zeros();
        let mut columns = [[Phasor::default(); 4]; ROTATED_FREQUENCIES];
        for ((s, sigma), cols) in self.sensors.iter().zip(noise_sigma).zip(columns.iter_mut()) {
            let w = 1.0 / (sigma * sigma);
            let (u1, du1) = self.unit_return_and_slope(s, near.0);
            let (u2, du2) = self.unit_return_and_slope(s, far.0);
            let scaled = |p: Phasor, c: f64| Phasor { a: c * p.a, b: c * p.b };
            *cols = [scaled(du1, near.1), u1, scaled(du2, far.1), u2];
            for i in 0..4 {
                for j in 0..4 {
                    f[(i, j)] += w * dot(cols[i], cols[j]);
                }
            }
        }
        (f, columns)
    }

    /// The inverse of a Fisher information, `None` where it is singular.
    fn free_covariance(f: &Matrix4<f64>) -> Option<Matrix4<f64>> {
        let scale: f64 = (0..4).map(|i| f[(i, i)]).product();
        (scale > 0.0 && f.determinant() > 1e-12 * scale)
            .then(|| f.try_inverse())
            .flatten()
    }

    /// Gauss-Newton steps on two free returns from `(d1, d2)` (the strengths in closed form
    /// at each step's distances), each step halved until `chi^2` falls, the distances kept
    /// in `[lo, hi]` and `sep` apart.
    fn free_gauss_newton(
        &self,
        fit: &FreeFit,
        noise_sigma: &[f64],
        (mut d1, mut d2): (f64, f64),
        (lo, hi, sep): (f64, f64, f64),
    ) -> (f64, f64) {
        let mut pair = fit.pair_at(self, d1, d2);
        for _ in 0..FREE_NEWTON_STEPS {
            let (f, cols) = self.free_fisher(noise_sigma, (d1, pair.near), (d2, pair.far));
            let Some(c) = Self::free_covariance(&f) else { break };
            let mut g = nalgebra::Vector4::<f64>::zeros();
            for (((s, m), sigma), col) in self.sensors.iter().zip(fit.measured).zip(noise_sigma).zip(&cols) {
                let (u1, u2) = (self.unit_return(s, d1), self.unit_return(s, d2));
                let r = Phasor {
                    a: m.a - pair.near * u1.a - pair.far * u2.a,
                    b: m.b - pair.near * u1.b - pair.far * u2.b,
                };
                let w = 1.0 / (sigma * sigma);
                for i in 0..4 {
                    g[i] += w * dot(col[i], r);
                }
            }
            let step = c * g;
            let mut t = 1.0;
            let mut moved = false;
            for _ in 0..6 {
                let n1 = (d1 + t * step[0]).clamp(lo, hi - sep);
                let n2 = (d2 + t * step[2]).clamp(n1 + sep, hi);
                let trial = fit.pair_at(self, n1, n2);
                if trial.chi_square < pair.chi_square {
                    (d1, d2, pair, moved) = (n1, n2, trial, true);
                    break;
                }
                t *= 0.5;
            }
            if !moved || (t * step[0]).abs().max((t * step[2]).abs()) < self.settings.tolerance_mm {
                break;
            }
        }
        (d1, d2)
    }

    /// The standard deviation of the near distance of two free returns, from the inverse of
    /// their Fisher information; infinite where it is singular.
    fn free_distance_sigma(&self, noise_sigma: &[f64], near: (f64, f64), far: (f64, f64)) -> f64 {
        match Self::free_covariance(&self.free_fisher(noise_sigma, near, far).0) {
            Some(c) if c[(0, 0)] > 0.0 => c[(0, 0)].sqrt(),
            _ => f64::INFINITY,
        }
    }

    /// Checks a pixel's phasors and noise against the frequencies.
    fn check_measured(&self, measured: &[Phasor], noise_sigma: &[f64]) -> Result<(), MultiFrequencyError> {
        let k = self.sensors.len();
        for (what, got) in [
            ("measured phasors", measured.len()),
            ("noise sigmas", noise_sigma.len()),
        ] {
            if got != k {
                return Err(MultiFrequencyError::MismatchedLengths { what, expected: k, got });
            }
        }
        if !measured.iter().all(|p| p.a.is_finite() && p.b.is_finite()) {
            return Err(MultiFrequencyError::NotFinite("a measured phasor"));
        }
        if let Some(&s) = noise_sigma.iter().find(|s| !(s.is_finite() && **s > 0.0)) {
            return Err(MultiFrequencyError::NonPositiveNoise(s));
        }
        Ok(())
    }

    /// The one opaque return that best explains `measured` (a latched
    /// background's phasors, say): its distance over `[d_min, d_min + R)`
    /// with `R` the common unambiguous range (a surface farther than that
    /// aliases into it), its strength in closed form at each distance.
    pub fn single_return(&self, measured: &[Phasor], noise_sigma: &[f64]) -> Result<SingleReturn, MultiFrequencyError> {
        self.check_measured(measured, noise_sigma)?;
        let weights = || noise_sigma.iter().map(|s| 1.0 / (s * s));
        let mm: f64 = measured.iter().zip(weights()).map(|(m, w)| w * dot(*m, *m)).sum();
        // (<u, M>, <u, u>) at d, weighted.
        let products = |d: f64| {
            let (mut um, mut uu) = (0.0, 0.0);
            for ((s, m), w) in self.sensors.iter().zip(measured).zip(weights()) {
                let u = self.unit_return(s, d);
                um += w * dot(u, *m);
                uu += w * dot(u, u);
            }
            (um, uu)
        };
        let strength = |(um, uu): (f64, f64)| if uu > 0.0 { (um / uu).max(0.0) } else { 0.0 };
        let chi_square = |d: f64| {
            let (um, uu) = products(d);
            let l = strength((um, uu));
            (mm - 2.0 * l * um + l * l * uu).max(0.0)
        };
        let lo = self.settings.min_distance_mm;
        let (d, chi) = self.minimise(lo, lo + self.common_range_mm, chi_square);
        Ok(SingleReturn {
            distance_mm: d,
            strength: strength(products(d)),
            chi_square: chi,
        })
    }

    /// The estimate of a pixel that one return explains.
    fn opaque_estimate(&self, p: &Pixel, d0: f64, chi_square: f64, statistic: f64) -> MultiFrequencyEstimate {
        let a0 = self.gram(p, d0).return_at(0.0);
        let fisher = self.fisher(p, d0, a0);
        let [var_d, _] = Self::opaque_variances(&fisher);
        let [_, _, var_t] = Self::variances(&fisher);
        MultiFrequencyEstimate {
            foreground_distance_mm: d0,
            first_return: a0,
            translucency: 0.0,
            chi_square,
            opacity_statistic: statistic,
            opaque: true,
            foreground_distance_sigma_mm: var_d.sqrt(),
            translucency_sigma: var_t.sqrt().sqrt(),
        }
    }

    /// Checks one pixel's inputs and forms its fixed inner products.
    fn pixel<'a>(&self, px: &'a PixelPhasors<'a>) -> Result<Pixel<'a>, MultiFrequencyError> {
        let k = self.sensors.len();
        for (what, got) in [
            ("measured phasors", px.measured.len()),
            ("background phasors", px.background.len()),
            ("noise sigmas", px.noise_sigma.len()),
        ] {
            if got != k {
                return Err(MultiFrequencyError::MismatchedLengths { what, expected: k, got });
            }
        }
        let finite = |p: &Phasor| p.a.is_finite() && p.b.is_finite();
        if !px.measured.iter().all(finite) {
            return Err(MultiFrequencyError::NotFinite("a measured phasor"));
        }
        if !px.background.iter().all(finite) {
            return Err(MultiFrequencyError::NotFinite("a background phasor"));
        }
        if let Some(&s) = px.noise_sigma.iter().find(|s| !(s.is_finite() && **s > 0.0)) {
            return Err(MultiFrequencyError::NonPositiveNoise(s));
        }
        let (lo, hi) = self.scan_range(px.background_distance_mm)?;
        let fixed = self.fixed(px);
        if !(fixed.bb > 0.0) {
            return Err(MultiFrequencyError::NoBackgroundReturn);
        }
        let mut weights = [0.0; HELD_WEIGHTS];
        for (w, sigma) in weights.iter_mut().zip(px.noise_sigma) {
            *w = 1.0 / (sigma * sigma);
        }
        Ok(Pixel {
            px,
            fixed,
            lo,
            hi,
            weights,
        })
    }

    /// `[d_min, db - separation]`, checked against the common unambiguous range.
    fn scan_range(&self, db: f64) -> Result<(f64, f64), MultiFrequencyError> {
        if !db.is_finite() {
            return Err(MultiFrequencyError::NotFinite("the background distance"));
        }
        let (lo, hi) = (self.settings.min_distance_mm, db - self.settings.min_separation_mm);
        if !(hi > lo) {
            return Err(MultiFrequencyError::BackgroundTooNear {
                background_distance_mm: db,
                min_distance_mm: lo,
            });
        }
        if db - lo >= self.common_range_mm {
            return Err(MultiFrequencyError::BeyondCommonRange {
                depth_mm: db - lo,
                common_range_mm: self.common_range_mm,
            });
        }
        Ok((lo, hi))
    }

    fn fixed(&self, px: &PixelPhasors) -> Fixed {
        let mut f = Fixed {
            bb: 0.0,
            bm: 0.0,
            mm: 0.0,
        };
        for ((b, m), s) in px.background.iter().zip(px.measured).zip(px.noise_sigma) {
            let w = 1.0 / (s * s);
            f.bb += w * dot(*b, *b);
            f.bm += w * dot(*b, *m);
            f.mm += w * dot(*m, *m);
        }
        f
    }

    /// `u_k(d1)`: the phasor of a unit return at `d1` (with the model's
    /// subsurface delay) at frequency `k`. For the sinusoid `(cos phi, sin phi)` by
    /// [`trig::sin_cos`] (within an ulp of the platform's, and inlined), else the
    /// sensor's buckets.
    fn unit_return(&self, sensor: &Sensor, d1: f64) -> Phasor {
        if sensor.waveform == Waveform::Sinusoid {
            let (sin, cos) = trig::sin_cos(sensor.phase(d1 + self.delay_mm));
            return Phasor { a: cos, b: sin };
        }
        sensor.buckets(1.0, d1 + self.delay_mm)
    }

    /// `u_k(d1)` and `d u_k / d d1`: for the sinusoid the unit return turned by a quarter
    /// and scaled by `2 pi / R_k`, for other waveforms by central differences (exact enough
    /// for every waveform).
    fn unit_return_and_slope(&self, sensor: &Sensor, d1: f64) -> (Phasor, Phasor) {
        let u = self.unit_return(sensor, d1);
        if sensor.waveform == Waveform::Sinusoid {
            let omega = sensor.phase(1.0);
            return (
                u,
                Phasor {
                    a: -omega * u.b,
                    b: omega * u.a,
                },
            );
        }
        const H: f64 = 0.01;
        let (p, m) = (self.unit_return(sensor, d1 + H), self.unit_return(sensor, d1 - H));
        let slope = Phasor {
            a: (p.a - m.a) / (2.0 * H),
            b: (p.b - m.b) / (2.0 * H),
        };
        (u, slope)
    }

    fn gram(&self, p: &Pixel, d1: f64) -> Gram {
        let mut g = Gram {
            uu: 0.0,
            ub: 0.0,
            um: 0.0,
        };
        let px = p.px;
        for (k, ((s, b), m)) in self.sensors.iter().zip(px.background).zip(px.measured).enumerate() {
            let w = p.weight(k);
            let u = self.unit_return(s, d1);
            g.uu += w * dot(u, u);
            g.ub += w * dot(u, *b);
            g.um += w * dot(u, *m);
        }
        g
    }

    /// The Fisher information of `(d1, a, ξ²)` at `(d1, a)` (it does not
    /// depend on ξ²): `F = J^T J` with the Jacobian columns `a u'_k(d1)`,
    /// `u_k(d1)` and `B_k`, weighted by `1 / sigma_k^2`.
    fn fisher(&self, p: &Pixel, d1: f64, a: f64) -> Matrix3<f64> {
        let mut f = Matrix3::zeros();
        let px = p.px;
        for ((s, b), sigma) in self.sensors.iter().zip(px.background).zip(px.noise_sigma) {
            let w = 1.0 / (sigma * sigma);
            let (u, du) = self.unit_return_and_slope(s, d1);
            let cols = [
                Phasor {
                    a: a * du.a,
                    b: a * du.b,
                },
                u,
                *b,
            ];
            for i in 0..3 {
                for j in 0..3 {
                    f[(i, j)] += w * dot(cols[i], cols[j]);
                }
            }
        }
        f
    }

    /// The variances of `(d1, a, ξ²)`: the diagonal of `F^-1`; infinite where
    /// `F` is singular (fewer observations than unknowns, or no layer return).
    fn variances(f: &Matrix3<f64>) -> [f64; 3] {
        let scale = f[(0, 0)] * f[(1, 1)] * f[(2, 2)];
        let inverse = (scale > 0.0 && f.determinant() > 1e-10 * scale)
            .then(|| f.try_inverse())
            .flatten();
        let Some(c) = inverse else {
            return [f64::INFINITY; 3];
        };
        [0, 1, 2].map(|i| if c[(i, i)] > 0.0 { c[(i, i)] } else { f64::INFINITY })
    }

    /// The variances of `(d, a)` for one return alone: the top-left 2 x 2 of `F`.
    fn opaque_variances(f: &Matrix3<f64>) -> [f64; 2] {
        let (fdd, fda, faa) = (f[(0, 0)], f[(0, 1)], f[(1, 1)]);
        let det = fdd * faa - fda * fda;
        if !(fdd * faa > 0.0 && det > 1e-10 * fdd * faa) {
            return [f64::INFINITY; 2];
        }
        [faa / det, fdd / det]
    }

    /// The grid of a scan over `[lo, hi]`: `cells` cells no wider than the coarse step, of
    /// width `h`; its points are `lo + j h`, `j = 0..=cells`.
    fn grid(&self, lo: f64, hi: f64) -> (usize, f64) {
        let cells = ((hi - lo) / self.coarse_step_mm).ceil().max(1.0);
        (cells as usize, (hi - lo) / cells)
    }

    /// The Gram products at every point `lo + j h` of a grid, `j = 0..=cells`, in order. For
    /// the sinusoid each frequency's unit return is turned by one fixed rotation per step
    /// (no trigonometry inside the scan); other waveforms are evaluated at each point.
    fn scan_grams(&self, p: &Pixel, lo: f64, h: f64, cells: usize, mut visit: impl FnMut(f64, Gram)) {
        let k = self.sensors.len();
        let sinusoid = k <= ROTATED_FREQUENCIES && self.sinusoid();
        if !sinusoid {
            for j in 0..=cells {
                let d = lo + j as f64 * h;
                visit(d, self.gram(p, d));
            }
            return;
        }
        let mut unit = [Phasor::default(); ROTATED_FREQUENCIES];
        let mut turn = [Phasor::default(); ROTATED_FREQUENCIES];
        for ((u, t), s) in unit.iter_mut().zip(turn.iter_mut()).zip(&self.sensors) {
            *u = self.unit_return(s, lo);
            let (sin, cos) = s.phase(h).sin_cos();
            *t = Phasor { a: cos, b: sin };
        }
        let px = p.px;
        for j in 0..=cells {
            let mut g = Gram {
                uu: 0.0,
                ub: 0.0,
                um: 0.0,
            };
            for (((u, b), m), &w) in unit[..k].iter().zip(px.background).zip(px.measured).zip(&p.weights) {
                g.uu += w * dot(*u, *u);
                g.ub += w * dot(*u, *b);
                g.um += w * dot(*u, *m);
            }
            visit(lo + j as f64 * h, g);
            for (u, t) in unit[..k].iter_mut().zip(&turn[..k]) {
                *u = Phasor {
                    a: u.a * t.a - u.b * t.b,
                    b: u.a * t.b + u.b * t.a,
                };
            }
        }
    }

    /// The minimum of `f` over `[lo, hi]`: a grid of cells no wider than the
    /// coarse step, then each of the grid's two lowest local minima refined
    /// ([`Self::refine`]).
    fn minimise(&self, lo: f64, hi: f64, f: impl Fn(f64) -> f64) -> (f64, f64) {
        let (cells, h) = self.grid(lo, hi);
        let mut minima = GridMinima::default();
        for j in 0..=cells {
            let x = lo + j as f64 * h;
            minima.push(x, f(x), None);
        }
        self.refine(minima.lowest(), lo, hi, h, f)
    }

    /// The lowest of the grid minima `lowest` (cells of width `h`), each refined by Brent's
    /// search over the cells either side of it within `[lo, hi]`, seeded with the grid's
    /// three points.
    fn refine(&self, lowest: [GridPoint; 2], lo: f64, hi: f64, h: f64, f: impl Fn(f64) -> f64) -> (f64, f64) {
        let found = search_together(self.searches(lowest, lo, hi, h), |_, x| f(x));
        lowest_found(&found, lo)
    }

    /// How far `<u(d), M - t B>` can rise between two grid points `h` apart above the larger
    /// of its values there, for `t` in `[0, 1]` (the layer's objective) and for `t = 0` (the
    /// single return's): `h^2 / 8` times a bound on its second derivative,
    /// `sum_k w_k omega_k^2 |M_k - t B_k|`. Sinusoids only (`None` otherwise): there
    /// `u_k(d)` turns at `omega_k = 2 pi / R_k` a millimetre and `<u, u>` is the same at every `d`.
    fn cell_slack(&self, p: &Pixel, h: f64) -> Option<CellSlack> {
        if !self.sinusoid() {
            return None;
        }
        let (mut layer, mut single) = (0.0, 0.0);
        for (k, ((s, m), b)) in self.sensors.iter().zip(p.px.measured).zip(p.px.background).enumerate() {
            let omega = s.phase(1.0);
            let curvature = p.weight(k) * omega * omega;
            // `sqrt` rather than `hypot`: the phasors are far from overflow, and the bound
            // carries a rounding margin (`worth_refining`).
            let (m, b) = ((m.a * m.a + m.b * m.b).sqrt(), (b.a * b.a + b.b * b.b).sqrt());
            single += curvature * m;
            layer += curvature * (m + b);
        }
        let q = h * h / 8.0;
        Some(CellSlack {
            layer: layer * q,
            single: single * q,
        })
    }

    /// Brent's searches of [`Self::refine`], not yet stepped: one over the cells either side
    /// of each finite grid minimum within `[lo, hi]`, seeded with the grid's three points.
    fn searches(&self, lowest: [GridPoint; 2], lo: f64, hi: f64, h: f64) -> [Option<BrentSearch>; 2] {
        let tol = self.settings.tolerance_mm;
        lowest.map(|m| {
            m.value
                .is_finite()
                .then(|| BrentSearch::new(((m.x - h).max(lo), (m.x + h).min(hi)), m.seed(h), tol))
        })
    }
}

/// The Gram products at one `d1` ([`Gram`]) and the first (`1`) and second (`2`)
/// derivatives in `d1` of `<u, B>` and `<u, M>`.
#[derive(Debug, Clone, Copy, Default)]
struct GramSlopes {
    gram: Gram,
    ub1: f64,
    um1: f64,
    ub2: f64,
    um2: f64,
}

/// Which piece of a projected objective is active at a distance: the least squares over
/// the amplitudes lands inside their bounds, on one bound of `t` (or `t` held), or at
/// `a = 0` (no return at `d1`: the objective does not depend on `d1` there).
#[derive(Debug, Clone, Copy)]
enum Projection {
    /// `a > 0`, `0 < t < 1`: `chi^2 = <M, M> - v^T G^-1 v`, `v = (<u, M>, <B, M>)`, `G`
    /// the 2 x 2 Gram matrix of `u` and `B`.
    Both,
    /// `a > 0` at this `t`: `chi^2 = |M - t B|^2 - <u, M - t B>^2 / <u, u>`.
    LayerAt(f64),
    /// `a = 0`.
    NoLayer,
}

/// A projected objective's value at one distance and its first two derivatives there.
#[derive(Debug, Clone, Copy)]
struct Projected {
    value: f64,
    slope: f64,
    curvature: f64,
}

impl GramSlopes {
    /// `value` with the slope and curvature of `piece` of the projected `chi^2` (the
    /// variable projection's closed form differentiated; `<u, u>` is constant).
    fn projected(&self, f: &Fixed, value: f64, piece: Projection) -> Projected {
        let g = &self.gram;
        let (slope, curvature) = match piece {
            Projection::Both => {
                // P = N / D is what the two amplitudes explain: chi^2 = <M, M> - P.
                let n = f.bb * g.um * g.um - 2.0 * f.bm * g.ub * g.um + g.uu * f.bm * f.bm;
                let n1 = 2.0 * f.bb * g.um * self.um1 - 2.0 * f.bm * (self.ub1 * g.um + g.ub * self.um1);
                let n2 = 2.0 * f.bb * (self.um1 * self.um1 + g.um * self.um2)
                    - 2.0 * f.bm * (self.ub2 * g.um + 2.0 * self.ub1 * self.um1 + g.ub * self.um2);
                let d = g.uu * f.bb - g.ub * g.ub;
                let d1 = -2.0 * g.ub * self.ub1;
                let d2 = -2.0 * (self.ub1 * self.ub1 + g.ub * self.ub2);
                let p = n / d;
                let p1 = (n1 - p * d1) / d;
                let p2 = (n2 - 2.0 * p1 * d1 - p * d2) / d;
                (-p1, -p2)
            }
            Projection::LayerAt(t) => {
                let r = g.um - t * g.ub;
                let r1 = self.um1 - t * self.ub1;
                let r2 = self.um2 - t * self.ub2;
                (-2.0 * r * r1 / g.uu, -2.0 * (r1 * r1 + r * r2) / g.uu)
            }
            Projection::NoLayer => (0.0, 0.0),
        };
        Projected {
            value,
            slope,
            curvature,
        }
    }
}

/// Distances before the layer's bound `db - separation` of the near-background scan
/// ([`MultiFrequencyInversion::near_background`]), mm: geometric, to about a coarse cell.
const NEAR_BACKGROUND_MM: [f64; NEAR_BACKGROUND_POINTS] = [0.0, 1.0, 2.0, 3.0, 5.0, 8.0, 13.0, 21.0, 34.0, 55.0, 90.0];

/// Points of the near-background scan.
const NEAR_BACKGROUND_POINTS: usize = 11;

/// Newton's steps at most per refinement (safeguarded: each one at least halves the bracket
/// when Newton's own step is not taken).
const NEWTON_STEPS: usize = 40;

/// The minimum of a projected objective `f` near grid minimum `m` (cells of width `h`, within
/// `[lo, hi]`), `(x, f(x))`: [`newton_minimum`] from `m`; `(lo, inf)` for no minimum.
fn newton_near(m: &GridPoint, (lo, hi): (f64, f64), h: f64, tol: f64, f: impl Fn(f64) -> Projected) -> (f64, f64) {
    if !m.value.is_finite() {
        return (lo, f64::INFINITY);
    }
    newton_minimum(((m.x - h).max(lo), (m.x + h).min(hi)), m.x, tol, f)
}

/// Newton's method for the minimum of `f` on `bracket` from `x0`, safeguarded: the bracket
/// narrows to the downhill side of each point taken; a step that leaves it, or taken where
/// `f` bends down, becomes a bisection; a point no lower than the best narrows the bracket
/// and is not taken. Stops once Newton's step or the bracket is under `tol`. The point
/// returned is never worse than `x0`.
fn newton_minimum(bracket: (f64, f64), x0: f64, tol: f64, f: impl Fn(f64) -> Projected) -> (f64, f64) {
    let (mut lo, mut hi) = bracket;
    let (mut x, mut p) = (x0, f(x0));
    for _ in 0..NEWTON_STEPS {
        if p.slope > 0.0 {
            hi = x;
        } else if p.slope < 0.0 {
            lo = x;
        } else {
            break;
        }
        if hi - lo <= tol {
            break;
        }
        let newton = x - p.slope / p.curvature;
        let u = if p.curvature > 0.0 && newton > lo && newton < hi {
            if (newton - x).abs() <= 0.5 * tol {
                // Newton's own step says the minimum is within half the tolerance.
                break;
            }
            newton
        } else {
            0.5 * (lo + hi)
        };
        let q = f(u);
        if q.value <= p.value {
            (x, p) = (u, q);
        } else if u > x {
            hi = u;
        } else {
            lo = u;
        }
    }
    (x, p.value)
}

/// The lowest of `found`, in order (the first of equals).
fn lowest_of(found: &[(f64, f64)], lo: f64) -> (f64, f64) {
    let mut best = (lo, f64::INFINITY);
    for &(x, fx) in found {
        if fx < best.1 {
            best = (x, fx);
        }
    }
    best
}

/// [`MultiFrequencyInversion::cell_slack`]: how far `<u(d), M - t B>` can rise within a
/// grid cell above its values at the cell's ends, for either objective.
#[derive(Debug, Clone, Copy)]
struct CellSlack {
    layer: f64,
    single: f64,
}

/// `lowest` with the second minimum dropped where no point of its cells can come below the
/// first's grid value (which the first's search only lowers, so the second's search could
/// not win): where [`cells_lower_bound`] exceeds it by more than the arithmetic's rounding.
fn worth_refining(
    [first, second]: [GridPoint; 2],
    slack: Option<f64>,
    fixed: &Fixed,
    objective: impl Fn(Gram) -> f64,
) -> [GridPoint; 2] {
    let Some(slack) = slack else {
        return [first, second];
    };
    if !(first.value.is_finite() && second.value.is_finite()) {
        return [first, second];
    }
    // Rounding: the scan's turned phasors and the search's own are a few ulp apart.
    let rounding = 1e-9 * fixed.mm;
    match cells_lower_bound(&second, slack, fixed, objective) {
        Some(bound) if bound > first.value + rounding => [first, GridPoint::NONE],
        _ => [first, second],
    }
}

/// A lower bound of `objective` (the layer's or the single return's chi^2, each the least
/// squares over `a >= 0` and `t`) on the cells either side of grid minimum `m`: its value
/// at each grid point there with `<u, M>` raised by `slack`, the lowest. Within a cell
/// `<u(d), M - t B>` stays below the larger of its ends' values plus `slack` for every `t`,
/// and `<u, u>` is the same, so the least squares at `d` is no lower than at one of the
/// ends with that raised correlation. `None` (no bound) where a point's Gram is missing or
/// `u` is nearly parallel to `B` (the closed form then leaves the interior out).
fn cells_lower_bound(m: &GridPoint, slack: f64, f: &Fixed, objective: impl Fn(Gram) -> f64) -> Option<f64> {
    m.grams[1]?;
    let mut bound = f64::INFINITY;
    for g in m.grams.iter().flatten() {
        let det = g.uu * f.bb - g.ub * g.ub;
        if !(det > 1e-6 * g.uu * f.bb) {
            return None;
        }
        bound = bound.min(objective(Gram { um: g.um + slack, ..*g }));
    }
    Some(bound)
}

/// The lowest point the searches found, in order (the first of equals), or `(lo, inf)`
/// where there were none.
fn lowest_found(found: &[Option<BrentSearch>], lo: f64) -> (f64, f64) {
    let mut best = (lo, f64::INFINITY);
    for refined in found.iter().flatten().map(BrentSearch::best) {
        if refined.1 < best.1 {
            best = refined;
        }
    }
    best
}

/// Brent's searches stepped together to their ends: in each round every unfinished search
/// names its next point, all of them are evaluated (`f(i, u)` for search `i`), then each
/// takes its value. Each search follows the same points as alone; a round's evaluations
/// do not depend on one another, so the core overlaps them where a search alone waits on
/// each of its own.
fn search_together<const N: usize>(
    mut searches: [Option<BrentSearch>; N],
    f: impl Fn(usize, f64) -> f64,
) -> [Option<BrentSearch>; N] {
    loop {
        let points = searches.each_mut().map(|s| s.as_mut().and_then(BrentSearch::next));
        if points.iter().all(Option::is_none) {
            return searches;
        }
        let values: [Option<f64>; N] = std::array::from_fn(|i| points[i].map(|u| f(i, u)));
        for ((s, u), fu) in searches.iter_mut().zip(points).zip(values) {
            if let (Some(s), Some(u), Some(fu)) = (s, u, fu) {
                s.take(u, fu);
            }
        }
    }
}

/// Frequencies up to which a scan turns the unit returns in place (more are evaluated).
const ROTATED_FREQUENCIES: usize = 8;

/// A local minimum of a grid: its point, value and its neighbours' values (infinite past
/// an end), and the Gram products at the three points where the scan gave them (`None`
/// past an end).
#[derive(Debug, Clone, Copy)]
struct GridPoint {
    x: f64,
    value: f64,
    left: f64,
    right: f64,
    grams: [Option<Gram>; 3],
}

impl GridPoint {
    const NONE: Self = Self {
        x: 0.0,
        value: f64::INFINITY,
        left: f64::INFINITY,
        right: f64::INFINITY,
        grams: [None; 3],
    };

    /// The three points known about the minimum, best first, for [`brent_minimum`].
    fn seed(&self, h: f64) -> [(f64, f64); 3] {
        let (l, r) = ((self.x - h, self.left), (self.x + h, self.right));
        let (near, far) = if self.left <= self.right { (l, r) } else { (r, l) };
        [(self.x, self.value), near, far]
    }
}

/// The two lowest local minima of a function sampled along a grid, fed point by point in
/// order (the ends count when no neighbour is lower).
#[derive(Debug, Clone, Copy)]
struct GridMinima {
    before: (f64, Option<Gram>),
    last: Option<(f64, f64, Option<Gram>)>,
    lowest: [GridPoint; 2],
}

impl Default for GridMinima {
    fn default() -> Self {
        Self {
            before: (f64::INFINITY, None),
            last: None,
            lowest: [GridPoint::NONE; 2],
        }
    }
}

impl GridMinima {
    /// The next grid point `(x, f(x))` and its Gram products, where known.
    fn push(&mut self, x: f64, fx: f64, gram: Option<Gram>) {
        if let Some((xl, fl, gl)) = self.last {
            if fl <= self.before.0 && fl <= fx {
                self.keep(GridPoint {
                    x: xl,
                    value: fl,
                    left: self.before.0,
                    right: fx,
                    grams: [self.before.1, gl, gram],
                });
            }
            self.before = (fl, gl);
        }
        self.last = Some((x, fx, gram));
    }

    /// Keeps the two lowest, lowest first.
    fn keep(&mut self, m: GridPoint) {
        if m.value < self.lowest[0].value {
            self.lowest[1] = self.lowest[0];
            self.lowest[0] = m;
        } else if m.value < self.lowest[1].value {
            self.lowest[1] = m;
        }
    }

    /// The two lowest local minima, lowest first (the last point taken with nothing after it).
    fn lowest(mut self) -> [GridPoint; 2] {
        self.push(f64::NAN, f64::INFINITY, None);
        self.lowest
    }
}

/// Brent's search for the minimum of `f` on `[lo, hi]` to a bracket about `tol` wide
/// ([`BrentSearch`]): a smooth minimum takes a handful of evaluations where golden section
/// alone takes one per factor 1.618 of narrowing. `seed` holds the three best points known,
/// best first; the point returned is never worse than the first (the search moves only to
/// lower values).
fn brent_minimum(bracket: (f64, f64), seed: [(f64, f64); 3], tol: f64, f: &impl Fn(f64) -> f64) -> (f64, f64) {
    let mut search = BrentSearch::new(bracket, seed, tol);
    while let Some(u) = search.next() {
        search.take(u, f(u));
    }
    search.best()
}

/// Brent's search for a minimum on a bracket (golden section with parabolic steps where
/// the parabola through the last three points is trustworthy), one evaluation at a time:
/// [`BrentSearch::next`] names the point to evaluate, [`BrentSearch::take`] takes its
/// value, so that several searches can be stepped together ([`search_together`]).
#[derive(Debug, Clone, Copy)]
struct BrentSearch {
    /// The bracket's ends.
    lo: f64,
    hi: f64,
    /// The best point so far and the second and third best, with their values.
    x: f64,
    fx: f64,
    w: f64,
    fw: f64,
    v: f64,
    fv: f64,
    /// This step and the one before the last (a parabolic step must halve it).
    step: f64,
    older: f64,
    /// The shortest step: a quarter of the tolerance.
    step_min: f64,
    /// Evaluations taken so far.
    evaluations: usize,
}

impl BrentSearch {
    /// Evaluations after which the search stops wherever it is.
    const MAX_EVALUATIONS: usize = 100;
    /// `(3 - sqrt 5) / 2`: golden section's share of the longer side.
    const GOLDEN: f64 = 0.381_966_011_250_105_1;

    /// A search of `[lo, hi]` to about `tol` from `seed`, the three best points known, best
    /// first (a first parabolic step may use them).
    fn new((lo, hi): (f64, f64), seed: [(f64, f64); 3], tol: f64) -> Self {
        let [(x, fx), (w, fw), (v, fv)] = seed;
        Self {
            lo,
            hi,
            x,
            fx,
            w,
            fw,
            v,
            fv,
            step: hi - lo,
            older: hi - lo,
            step_min: 0.25 * tol,
            evaluations: 0,
        }
    }

    /// The best point so far and its value.
    fn best(&self) -> (f64, f64) {
        (self.x, self.fx)
    }

    /// The next point to evaluate, to be answered by [`Self::take`]; `None` (and nothing
    /// changed) once the bracket is about `tol` wide or the evaluations are spent.
    fn next(&mut self) -> Option<f64> {
        let (lo, hi, x, step_min) = (self.lo, self.hi, self.x, self.step_min);
        let mid = 0.5 * (lo + hi);
        if self.evaluations >= Self::MAX_EVALUATIONS || (x - mid).abs() <= 2.0 * step_min - 0.5 * (hi - lo) {
            return None;
        }
        let last = self.older;
        self.older = self.step;
        let parabolic = (last.abs() > step_min)
            .then(|| parabola_step(x, self.fx, self.w, self.fw, self.v, self.fv))
            .flatten()
            .filter(|&p| p.abs() < 0.5 * last.abs() && x + p > lo && x + p < hi);
        self.step = match parabolic {
            Some(p) if x + p - lo < 2.0 * step_min || hi - (x + p) < 2.0 * step_min => step_min.copysign(mid - x),
            Some(p) => p,
            None => {
                self.older = if x >= mid { lo - x } else { hi - x };
                Self::GOLDEN * self.older
            }
        };
        let step = self.step;
        Some(
            x + if step.abs() >= step_min {
                step
            } else {
                step_min.copysign(step)
            },
        )
    }

    /// The value `fu` at `u`, the point [`Self::next`] named: the bracket narrowed and the
    /// three best points kept.
    fn take(&mut self, u: f64, fu: f64) {
        self.evaluations += 1;
        if fu <= self.fx {
            if u >= self.x {
                self.lo = self.x;
            } else {
                self.hi = self.x;
            }
            ((self.v, self.fv), (self.w, self.fw), (self.x, self.fx)) = ((self.w, self.fw), (self.x, self.fx), (u, fu));
        } else {
            if u < self.x {
                self.lo = u;
            } else {
                self.hi = u;
            }
            if fu <= self.fw || self.w == self.x {
                ((self.v, self.fv), (self.w, self.fw)) = ((self.w, self.fw), (u, fu));
            } else if fu <= self.fv || self.v == self.x || self.v == self.w {
                (self.v, self.fv) = (u, fu);
            }
        }
    }
}

/// The step from `x` to the vertex of the parabola through `(x, fx)`, `(w, fw)`, `(v, fv)`;
/// `None` where the three points do not bend upwards.
fn parabola_step(x: f64, fx: f64, w: f64, fw: f64, v: f64, fv: f64) -> Option<f64> {
    let r = (x - w) * (fx - fv);
    let q = (x - v) * (fx - fw);
    let p = (x - v) * q - (x - w) * r;
    let q = 2.0 * (q - r);
    let (p, q) = if q > 0.0 { (-p, q) } else { (p, -q) };
    (q > 0.0 && p.is_finite()).then(|| p / q)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    const MHZ: f64 = 1e6;
    const THREE: [f64; 3] = [20.0 * MHZ, 50.0 * MHZ, 100.0 * MHZ];
    /// `Lin`, the layer's `X = rho_f cos(theta_f)` and the background's `Xb`.
    const LIN: f64 = 1e10;
    const X_LAYER: f64 = 0.6;
    const X_BACKGROUND: f64 = 0.8;
    /// The noise stated with noise-free phasors, and the noise drawn, as fractions of `L1`.
    const NOISE_FREE: f64 = 1e-4;
    const NOISE: f64 = 0.01;

    fn scene(df: f64, db: f64, xi: f64) -> LayerScene {
        LayerScene {
            foreground_distance_mm: df,
            background_distance_mm: db,
            translucency: xi,
            foreground_albedo_cos: X_LAYER,
            background_albedo_cos: X_BACKGROUND,
            emitted_light: LIN,
            wall_view_factor: 0.0,
            diffuse_lobe: None,
        }
    }

    /// A pixel of `scene` as the one forward model makes it, with the background
    /// latched alone and a noise of `noise` times the layer's return stated.
    struct Observed {
        measured: Vec<Phasor>,
        background: Vec<Phasor>,
        db: f64,
        sigma: Vec<f64>,
    }

    impl Observed {
        fn new(mf: &MultiFrequencyModel, s: &LayerScene, noise: f64) -> Self {
            let db = s.background_distance_mm;
            let mut r = [Return::default(); MAX_BOUNCES];
            mf.models()[0].layer_returns(s, &mut r);
            let behind = [ForwardModel::opaque_return(db, X_BACKGROUND, LIN)];
            Self {
                measured: mf.measure_layer(s).map(|m| m.buckets).collect(),
                background: mf.measure(&behind).map(|m| m.buckets).collect(),
                db,
                sigma: vec![noise * r[0].strength; mf.len()],
            }
        }

        fn phasors(&self) -> PixelPhasors<'_> {
            PixelPhasors {
                measured: &self.measured,
                background: &self.background,
                background_distance_mm: self.db,
                noise_sigma: &self.sigma,
            }
        }

        /// The stated noise drawn onto every component of `M_k`.
        fn add_noise(&mut self, rng: &mut ChaCha8Rng) {
            for (m, s) in self.measured.iter_mut().zip(&self.sigma) {
                m.a += s * rng.sample::<f64, _>(StandardNormal);
                m.b += s * rng.sample::<f64, _>(StandardNormal);
            }
        }
    }

    fn model(waveform: Waveform, frequencies_hz: &[f64]) -> (MultiFrequencyModel, MultiFrequencyInversion) {
        let one = ForwardModel::physical(Sensor::new(30.0 * MHZ, waveform));
        let mf = MultiFrequencyModel::new(&one, frequencies_hz).expect("model");
        let inv = MultiFrequencyInversion::new(&mf, ScanSettings::default()).expect("inversion");
        (mf, inv)
    }

    /// The value below which a fraction `q` of `v` lies (nearest rank).
    fn quantile(v: &mut [f64], q: f64) -> f64 {
        v.sort_by(f64::total_cmp);
        let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
        v[i]
    }

    #[test]
    fn common_range_is_c_over_2_gcd() {
        let range = |f: &[f64]| common_unambiguous_range_mm(f).expect("range");
        assert!((range(&THREE) - 14_989.6).abs() < 0.1, "{}", range(&THREE));
        assert!((range(&[50.0 * MHZ, 100.0 * MHZ]) - 2_997.9).abs() < 0.1);
        assert!((range(&[20.0 * MHZ, 100.0 * MHZ]) - 7_494.8).abs() < 0.1);
        assert!((range(&[30.0 * MHZ]) - Sensor::sr4000().unambiguous_range_mm()).abs() < 1e-6);
        assert_eq!(
            common_unambiguous_range_mm(&[]),
            Err(MultiFrequencyError::NoFrequencies)
        );
        for bad in [0.0, -20.0 * MHZ, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                common_unambiguous_range_mm(&[20.0 * MHZ, bad]),
                Err(MultiFrequencyError::NonPositiveFrequency(_))
            ));
        }
    }

    #[test]
    fn a_pair_shorter_than_the_scene_aliases_and_is_refused() {
        // 50 and 100 MHz repeat every 2998 mm: a layer there and 2998 mm further give the same phasors.
        let (mf, inv) = model(Waveform::Sinusoid, &[50.0 * MHZ, 100.0 * MHZ]);
        let r = mf.common_unambiguous_range_mm();
        let at = |d: f64| -> Vec<Phasor> {
            let one = Return {
                strength: 1000.0,
                distance_mm: d,
            };
            mf.measure(&[one]).map(|m| m.buckets).collect()
        };
        for (n, f) in at(800.0).iter().zip(&at(800.0 + r)) {
            assert!((n.a - f.a).abs() < 1e-6 && (n.b - f.b).abs() < 1e-6, "{n:?} {f:?}");
        }
        // A background beyond it is refused; 20, 50 and 100 MHz take it.
        let o = Observed::new(&mf, &scene(1000.0, 4000.0, 0.5), NOISE_FREE);
        assert!(matches!(
            inv.invert(&o.phasors()),
            Err(MultiFrequencyError::BeyondCommonRange { .. })
        ));
        let (mf3, inv3) = model(Waveform::Sinusoid, &THREE);
        let o = Observed::new(&mf3, &scene(1000.0, 4000.0, 0.5), NOISE_FREE);
        let est = inv3.invert(&o.phasors()).expect("three frequencies reach 4 m");
        assert!((est.foreground_distance_mm - 1000.0).abs() < 0.5, "{est:?}");
    }

    #[test]
    fn a_single_return_is_found_over_the_common_range() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        for d in [150.0, 2000.0, 3300.0, 9000.0, 14_000.0] {
            let wall = [ForwardModel::opaque_return(d, X_BACKGROUND, LIN)];
            let m: Vec<Phasor> = mf.measure(&wall).map(|m| m.buckets).collect();
            let fit = inv.single_return(&m, &[1e-4 * wall[0].strength; 3]).expect("fit");
            assert!((fit.distance_mm - d).abs() < 0.01, "{d}: {fit:?}");
            assert!((fit.strength / wall[0].strength - 1.0).abs() < 1e-6, "{d}: {fit:?}");
        }
        // 50 and 100 MHz: 3300 mm aliases to 3300 - 2998 mm.
        let (mf2, inv2) = model(Waveform::Sinusoid, &[50.0 * MHZ, 100.0 * MHZ]);
        let wall = [ForwardModel::opaque_return(3300.0, X_BACKGROUND, LIN)];
        let m: Vec<Phasor> = mf2.measure(&wall).map(|m| m.buckets).collect();
        let fit = inv2.single_return(&m, &[1.0; 2]).expect("fit");
        assert!(
            (fit.distance_mm - (3300.0 - mf2.common_unambiguous_range_mm())).abs() < 0.01,
            "{fit:?}"
        );
        assert!(matches!(
            inv.single_return(&m, &[1.0; 2]),
            Err(MultiFrequencyError::MismatchedLengths { .. })
        ));
    }

    #[test]
    fn recovers_layers_noise_free() {
        let mut worst = (0.0f64, 0.0f64);
        let sets: [&[f64]; 2] = [&THREE, &[20.0 * MHZ, 100.0 * MHZ]];
        for waveform in [Waveform::Sinusoid, Waveform::Triangle] {
            for freqs in sets {
                let (mf, inv) = model(waveform, freqs);
                for &(df, db) in &[
                    (500.0, 2000.0),
                    (1000.0, 2000.0),
                    (1750.0, 2000.0),
                    (800.0, 3300.0),
                    (2600.0, 3300.0),
                ] {
                    for xi in [0.3, 0.65, 0.9] {
                        let o = Observed::new(&mf, &scene(df, db, xi), NOISE_FREE);
                        let est = inv.invert(&o.phasors()).expect("estimate");
                        let (ed, ex) = ((est.foreground_distance_mm - df).abs(), (est.translucency - xi).abs());
                        assert!(
                            !est.opaque && ed < 0.5 && ex < 0.005,
                            "{waveform:?} {freqs:?} {df} {db} {xi}: {est:?}"
                        );
                        worst = (worst.0.max(ed), worst.1.max(ex));
                    }
                }
            }
        }
        println!(
            "noise-free layers: worst |d1 error| {:.2e} mm, worst |xi error| {:.2e}",
            worst.0, worst.1
        );
    }

    #[test]
    fn a_partly_covered_pixel_shows_its_share_in_the_background_left() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let mut rng = ChaCha8Rng::seed_from_u64(35);
        let (mut inside, mut draws) = (0, 0);
        for xi in [0.5, 0.93] {
            for c in [0.0, 0.3, 0.7, 1.0] {
                let (df, db) = (2250.0, 3150.0);
                let full = Observed::new(&mf, &scene(df, db, xi), NOISE);
                // A share c of the pixel sees the layer's returns, the rest the background.
                let mix = |m: &Phasor, b: &Phasor| Phasor {
                    a: c * m.a + (1.0 - c) * b.a,
                    b: c * m.b + (1.0 - c) * b.b,
                };
                let clean: Vec<Phasor> = full
                    .measured
                    .iter()
                    .zip(&full.background)
                    .map(|(m, b)| mix(m, b))
                    .collect();
                let want = 1.0 - c * (1.0 - xi * xi);
                let mut o = Observed {
                    measured: clean.clone(),
                    background: full.background.clone(),
                    db,
                    sigma: vec![NOISE_FREE * full.sigma[0] / NOISE; mf.len()],
                };
                let (t, _) = inv.background_share_at(&o.phasors(), df).expect("share");
                assert!((t - want).abs() < 1e-4, "noise-free xi {xi} c {c}: t {t} want {want}");
                o.sigma = full.sigma.clone();
                for _ in 0..200 {
                    o.measured = clean.clone();
                    o.add_noise(&mut rng);
                    let (t, sd) = inv.background_share_at(&o.phasors(), df).expect("share");
                    inside += usize::from((t - want).abs() <= 1.96 * sd);
                    draws += 1;
                }
            }
        }
        let share = inside as f64 / draws as f64;
        println!("background share: {inside} of {draws} draws within 1.96 sd ({share:.3})");
        assert!((0.93..=0.97).contains(&share), "{share}");
    }

    /// Light blocked behind the background (`M = B - c u(d2)`, `d2 > db`: what an object
    /// shading the light between a table and a wall leaves) fits a layer before the
    /// background far better than one return, and `indirect_change` finds it within the
    /// opacity level of that layer; a real layer it does not explain.
    #[test]
    fn light_changed_behind_the_background_is_told_from_a_layer() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let mut rng = ChaCha8Rng::seed_from_u64(36);
        let db = 3150.0;
        let background: Vec<Phasor> = mf
            .measure(&[ForwardModel::opaque_return(db, X_BACKGROUND, LIN)])
            .map(|m| m.buckets)
            .collect();
        let sigma = vec![NOISE * background[0].a.hypot(background[0].b); mf.len()];
        // The level the pipeline uses: chi-square with one degree of freedom at 99.9 %.
        const LEVEL: f64 = 10.827_566_170_662_733;
        let (mut layers, mut explained, mut draws) = (0, 0, 0);
        for (share, beyond) in [(0.1_f64, 300.0), (0.2, 700.0), (-0.15, 1200.0)] {
            let changed = ForwardModel::opaque_return(db + beyond, X_BACKGROUND * share.abs(), LIN);
            let sign = f64::signum(share);
            let clean: Vec<Phasor> = background
                .iter()
                .zip(mf.measure(&[changed]))
                .map(|(b, c)| Phasor {
                    a: b.a - sign * c.buckets.a,
                    b: b.b - sign * c.buckets.b,
                })
                .collect();
            for _ in 0..100 {
                let mut o = Observed {
                    measured: clean.clone(),
                    background: background.clone(),
                    db,
                    sigma: sigma.clone(),
                };
                o.add_noise(&mut rng);
                let est = inv.invert(&o.phasors()).expect("invert");
                let indirect = inv.indirect_change(&o.phasors(), 3000.0).expect("indirect");
                layers += usize::from(!est.opaque && est.opacity_statistic > LEVEL);
                explained += usize::from(indirect.chi_square - est.chi_square <= LEVEL);
                let within = inv.indirect_change_within(&o.phasors(), 3000.0, est.chi_square + LEVEL);
                assert_eq!(within.ok(), Some(indirect.chi_square <= est.chi_square + LEVEL));
                let px = o.phasors();
                let spread = inv.amplitude_spread(&inv.pixel(&px).expect("pixel")).expect("sinusoid");
                assert!(
                    spread <= indirect.chi_square * (1.0 + 1e-12),
                    "{spread} over {indirect:?}"
                );
                draws += 1;
            }
        }
        println!("light changed behind the background: {layers} of {draws} fit as layers, {explained} explained");
        assert!(
            layers * 2 >= draws,
            "the premise: such pixels fit layers ({layers} of {draws})"
        );
        assert!(explained * 100 >= draws * 99, "{explained} of {draws}");
        for xi in [0.5, 0.75, 0.9] {
            for df in [900.0, 2250.0] {
                let mut o = Observed::new(&mf, &scene(df, db, xi), NOISE);
                for _ in 0..50 {
                    o.measured = Observed::new(&mf, &scene(df, db, xi), NOISE).measured;
                    o.add_noise(&mut rng);
                    let est = inv.invert(&o.phasors()).expect("invert");
                    let indirect = inv.indirect_change(&o.phasors(), 3000.0).expect("indirect");
                    let within = inv.indirect_change_within(&o.phasors(), 3000.0, est.chi_square + LEVEL);
                    assert_eq!(within.ok(), Some(false), "the grid's bound and the refined fit differ");
                    let px = o.phasors();
                    let spread = inv.amplitude_spread(&inv.pixel(&px).expect("pixel")).expect("sinusoid");
                    assert!(
                        spread <= indirect.chi_square * (1.0 + 1e-12),
                        "{spread} over {indirect:?}"
                    );
                    assert!(
                        indirect.chi_square - est.chi_square > LEVEL,
                        "a layer of xi {xi} at {df} mm explained: {indirect:?} against {est:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_layer_searched_within_a_window_is_found_only_there() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let xi = 0.4;
        let o = Observed::new(&mf, &scene(900.0, 3300.0, xi), NOISE);
        let px = o.phasors();
        let free = inv.fit_at_translucency(&px, xi).expect("fit");
        assert!((free.foreground_distance_mm - 900.0).abs() < 1.0, "{free:?}");
        let near = inv.fit_at_translucency_within(&px, xi, (850.0, 950.0)).expect("fit");
        assert!(
            (near.foreground_distance_mm - 900.0).abs() < 1.0 && near.chi_square < 1e-6,
            "{near:?}"
        );
        // Where another layer's surface lies, 2 m behind it, no layer of this ξ explains it.
        let far = inv.fit_at_translucency_within(&px, xi, (2500.0, 3000.0)).expect("fit");
        assert!((2500.0..=3000.0).contains(&far.foreground_distance_mm), "{far:?}");
        // Far beyond chi-square's 99.9 % quantile for its few degrees of freedom (under 20).
        assert!(far.chi_square > 100.0, "{far:?}");
    }

    #[test]
    fn the_scan_turns_unit_returns_as_they_are_evaluated() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let o = Observed::new(&mf, &scene(800.0, 3300.0, 0.65), NOISE_FREE);
        let px = o.phasors();
        let p = inv.pixel(&px).expect("a valid pixel");
        let (cells, h) = inv.grid(p.lo, px.background_distance_mm);
        let mut seen = 0;
        inv.scan_grams(&p, p.lo, h, cells, |d, g| {
            let direct = inv.gram(&p, d);
            for (turned, evaluated) in [(g.uu, direct.uu), (g.ub, direct.ub), (g.um, direct.um)] {
                assert!(
                    (turned - evaluated).abs() <= 1e-9 * direct.uu.abs().max(direct.um.abs()),
                    "{d}: {g:?} against {direct:?}"
                );
            }
            seen += 1;
        });
        assert_eq!(seen, cells + 1);
    }

    #[test]
    fn a_cells_lower_bound_is_below_its_objective_across_the_cells() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut bounded = 0;
        for &(df, db, xi) in &[(800.0, 3300.0, 0.65), (500.0, 2000.0, 0.9), (1500.0, 4000.0, 0.3)] {
            for noise in [NOISE_FREE, NOISE] {
                let mut o = Observed::new(&mf, &scene(df, db, xi), noise);
                o.add_noise(&mut rng);
                let px = o.phasors();
                let p = inv.pixel(&px).expect("a valid pixel");
                let (cells, h) = inv.grid(p.lo, db);
                let mut grams = vec![];
                inv.scan_grams(&p, p.lo, h, cells, |d, g| grams.push((d, g)));
                let slack = inv.cell_slack(&p, h).expect("sinusoids");
                let two = |g: Gram| g.two_returns(&p.fixed).chi_square;
                let one = |g: Gram| g.chi_square(&p.fixed, g.return_at(0.0), 0.0);
                for j in 0..grams.len() {
                    let m = GridPoint {
                        x: grams[j].0,
                        grams: [
                            j.checked_sub(1).map(|i| grams[i].1),
                            Some(grams[j].1),
                            grams.get(j + 1).map(|g| g.1),
                        ],
                        ..GridPoint::NONE
                    };
                    let (lo, hi) = ((m.x - h).max(p.lo), (m.x + h).min(db));
                    for (objective, s) in [(&two as &dyn Fn(Gram) -> f64, slack.layer), (&one, slack.single)] {
                        let Some(bound) = cells_lower_bound(&m, s, &p.fixed, objective) else {
                            continue;
                        };
                        bounded += 1;
                        for i in 0..=200 {
                            let d = lo + (hi - lo) * i as f64 / 200.0;
                            let f = objective(inv.gram(&p, d));
                            assert!(bound <= f, "{df} {db} {xi}: bound {bound} above {f} at {d}");
                        }
                    }
                }
            }
        }
        assert!(bounded > 100, "{bounded} cells bounded");
    }

    #[test]
    fn brents_search_finds_a_smooth_minimum_in_fewer_steps_than_golden_section() {
        use std::cell::Cell;
        let calls = Cell::new(0);
        let f = |x: f64| {
            calls.set(calls.get() + 1);
            1.0 - (std::f64::consts::TAU * (x - 1234.567) / 1499.0).cos()
        };
        let (lo, hi, tol) = (1150.0, 1340.0, 0.05);
        let seed = [(1245.0, f(1245.0)), (1150.0, f(1150.0)), (1340.0, f(1340.0))];
        calls.set(0);
        let (x, fx) = brent_minimum((lo, hi), seed, tol, &f);
        assert!((x - 1234.567).abs() < tol, "{x}");
        assert!(fx <= 1e-6, "{fx}");
        let golden_steps = ((hi - lo) / tol).ln() / (1.0 / 0.618_033_988_749_894_9_f64).ln();
        assert!((calls.get() as f64) < golden_steps, "{} evaluations", calls.get());
        // Neighbours past the ends of a grid (infinite) leave it to golden steps.
        let seed = [(1150.0, f(1150.0)), (1055.0, f64::INFINITY), (1245.0, f(1245.0))];
        let (x, _) = brent_minimum((1150.0, 1245.0), seed, tol, &f);
        assert!((x - 1234.567).abs() < tol, "{x}");
    }

    #[test]
    fn two_free_returns_find_the_layer_with_no_background_latched() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        for &(df, db) in &[(500.0, 2000.0), (1200.0, 3300.0), (2600.0, 3300.0)] {
            for xi in [0.4, 0.75, 0.9] {
                let o = Observed::new(&mf, &scene(df, db, xi), NOISE_FREE);
                let fit = inv.two_free_returns(&o.measured, &o.sigma, 5000.0).expect("a fit");
                assert!(
                    (fit.near_distance_mm - df).abs() < 0.5 && (fit.far_distance_mm - db).abs() < 0.5,
                    "{df} {db} {xi}: {fit:?}"
                );
                // The far return is the background dimmed by xi squared (the physical default).
                let behind = [ForwardModel::opaque_return(db, X_BACKGROUND, LIN)];
                let alone: f64 = mf
                    .measure(&behind)
                    .map(|m| m.buckets.a.hypot(m.buckets.b))
                    .next()
                    .unwrap_or(0.0);
                assert!(
                    (fit.far_strength / alone - xi * xi).abs() < 0.01,
                    "{df} {db} {xi}: {fit:?}"
                );
                assert!(fit.near_distance_sigma_mm.is_finite());
            }
        }
        // One surface: the far return comes out empty or at the same place, and a single
        // return explains it as well.
        let o = Observed::new(&mf, &scene(1500.0, 3000.0, 0.0), NOISE_FREE);
        let fit = inv.two_free_returns(&o.measured, &o.sigma, 5000.0).expect("a fit");
        let one = inv.single_return(&o.measured, &o.sigma).expect("a fit");
        assert!((one.distance_mm - 1500.0).abs() < 0.5, "{one:?}");
        assert!(one.chi_square - fit.chi_square < 1.0, "{one:?} against {fit:?}");
    }

    #[test]
    fn noisy_layers_are_told_from_one_return_without_a_background() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let level = 13.82; // chi-square, two more parameters, 99.9 %
        let (mut layers, mut surfaces, mut worst) = (0, 0, 0.0f64);
        for trial in 0..40 {
            let xi = if trial % 2 == 0 { 0.75 } else { 0.0 };
            let mut o = Observed::new(&mf, &scene(1000.0 + 20.0 * trial as f64, 3000.0, xi), NOISE);
            o.add_noise(&mut rng);
            let two = inv.two_free_returns(&o.measured, &o.sigma, 5000.0).expect("a fit");
            let one = inv.single_return(&o.measured, &o.sigma).expect("a fit");
            let layer = one.chi_square - two.chi_square > level;
            if xi > 0.0 {
                layers += usize::from(layer);
                worst = worst.max((two.near_distance_mm - (1000.0 + 20.0 * trial as f64)).abs());
            } else {
                surfaces += usize::from(!layer);
            }
        }
        assert_eq!(layers, 20, "every xi 0.75 layer told from one return");
        assert!(surfaces >= 19, "{surfaces} of 20 surfaces kept as one return");
        assert!(worst < 30.0, "worst layer distance error {worst} mm");
    }

    #[test]
    fn an_opaque_surface_comes_out_opaque_with_its_depth() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        // Before the background, and the background itself (nothing placed).
        for d in [300.0, 1000.0, 1950.0, 2000.0] {
            let o = Observed::new(&mf, &scene(d, 2000.0, 0.0), NOISE_FREE);
            let est = inv.invert(&o.phasors()).expect("estimate");
            assert!(est.opaque && est.translucency == 0.0, "{d}: {est:?}");
            assert!((est.foreground_distance_mm - d).abs() < 0.5, "{d}: {est:?}");
        }
    }

    #[test]
    fn opaque_means_one_return_within_the_stated_noise() {
        // A ξ 0.3 layer at 500 mm: the background's return through it (ξ² Ib = 180) is about
        // 1 % of the layer's (16800). At a stated noise of 0.01 % it is a layer; at 1 % one
        // return explains the same phasors within the test's level, and the pixel is opaque.
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let s = scene(500.0, 2000.0, 0.3);
        let layer = inv
            .invert(&Observed::new(&mf, &s, NOISE_FREE).phasors())
            .expect("estimate");
        assert!(!layer.opaque && (layer.translucency - 0.3).abs() < 0.005, "{layer:?}");
        let opaque = inv.invert(&Observed::new(&mf, &s, NOISE).phasors()).expect("estimate");
        assert!(
            opaque.opaque && opaque.opacity_statistic <= CHI_SQUARE_1_95,
            "{opaque:?}"
        );
        assert!((opaque.foreground_distance_mm - 500.0).abs() < 2.0 * opaque.foreground_distance_sigma_mm);
    }

    #[test]
    fn one_frequency_cannot_tell_a_layer_from_an_opaque_surface() {
        let (mf, inv) = model(Waveform::Sinusoid, &[20.0 * MHZ]);
        let o = Observed::new(&mf, &scene(1000.0, 2000.0, 0.65), NOISE);
        // Every ξ fits the two numbers exactly, each at its own depth.
        let fits: Vec<TranslucencyFit> = [0.0, 0.2, 0.4, 0.65, 0.8]
            .into_iter()
            .map(|xi| inv.fit_at_translucency(&o.phasors(), xi).expect("fit"))
            .collect();
        for f in &fits {
            assert!(f.chi_square < 1e-4, "{f:?}");
        }
        let spread = fits.iter().map(|f| f.foreground_distance_mm).fold(f64::NAN, f64::max)
            - fits.iter().map(|f| f.foreground_distance_mm).fold(f64::NAN, f64::min);
        assert!(spread > 100.0, "depths spread {spread} mm");
        // So the test of ξ = 0 cannot reject it, and ξ has no finite uncertainty.
        let est = inv.invert(&o.phasors()).expect("estimate");
        assert!(est.opaque && est.opacity_statistic < 1e-4, "{est:?}");
        assert!(est.translucency_sigma.is_infinite(), "{est:?}");
        // An opaque surface at the ξ = 0 depth gives the same phasor: the same answer.
        let d0 = fits[0].foreground_distance_mm;
        let same = Observed {
            measured: mf
                .measure(&[Return {
                    strength: fits[0].first_return,
                    distance_mm: d0,
                }])
                .map(|m| m.buckets)
                .collect(),
            ..Observed::new(&mf, &scene(d0, 2000.0, 0.0), NOISE)
        };
        let twin = inv.invert(&same.phasors()).expect("estimate");
        assert!(
            (twin.foreground_distance_mm - est.foreground_distance_mm).abs() < 0.01,
            "{twin:?} {est:?}"
        );
        println!("one frequency: xi 0..0.8 all fit (chi^2 < 1e-4), depths spread {spread:.0} mm");
    }

    /// What [`noisy_layers`] measured.
    #[derive(Debug)]
    struct NoisySummary {
        xi_median: f64,
        xi_95: f64,
        d_median: f64,
        d_95: f64,
        xi_coverage: f64,
        d_coverage: f64,
        opaque: usize,
    }

    /// `draws` seeded layers (`df`, ξ uniform over the ranges) before a background at
    /// 2000 mm, noise 1 % of the layer's return on every component: the errors against
    /// the truth and how often `1.96 sigma` covers it.
    fn noisy_layers(seed: u64, draws: usize, df: std::ops::Range<f64>, xi: std::ops::Range<f64>) -> NoisySummary {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (mut xi_err, mut d_err) = (Vec::new(), Vec::new());
        let (mut xi_covered, mut d_covered, mut opaque) = (0, 0, 0);
        for _ in 0..draws {
            let (d_true, xi_true) = (rng.random_range(df.clone()), rng.random_range(xi.clone()));
            let mut o = Observed::new(&mf, &scene(d_true, 2000.0, xi_true), NOISE);
            o.add_noise(&mut rng);
            let est = inv.invert(&o.phasors()).expect("estimate");
            opaque += usize::from(est.opaque);
            let (ed, ex) = (
                (est.foreground_distance_mm - d_true).abs(),
                (est.translucency - xi_true).abs(),
            );
            xi_err.push(ex);
            d_err.push(ed);
            xi_covered += usize::from(ex <= 1.96 * est.translucency_sigma);
            d_covered += usize::from(ed <= 1.96 * est.foreground_distance_sigma_mm);
        }
        let s = NoisySummary {
            xi_median: quantile(&mut xi_err, 0.5),
            xi_95: quantile(&mut xi_err, 0.95),
            d_median: quantile(&mut d_err, 0.5),
            d_95: quantile(&mut d_err, 0.95),
            xi_coverage: xi_covered as f64 / draws as f64,
            d_coverage: d_covered as f64 / draws as f64,
            opaque,
        };
        println!(
            "df {df:?} mm, xi {xi:?}, noise 1 % of L1, {draws} draws: |xi error| median {:.4} p95 {:.4}; \
             |d1 error| median {:.2} mm p95 {:.2} mm; 1.96 sigma covers xi {:.3}, d1 {:.3}; flagged opaque {}",
            s.xi_median, s.xi_95, s.d_median, s.d_95, s.xi_coverage, s.d_coverage, s.opaque
        );
        s
    }

    #[test]
    fn noisy_layers_give_xi_per_pixel_and_intervals_that_cover() {
        // A sheet 250-1250 mm before the wall, as in the issue's render (ξ 0.75) and around it;
        // depth to 15 mm (the issue asks 20 mm of `two_materials`).
        let s = noisy_layers(35, 200, 750.0..1750.0, 0.5..0.9);
        assert_eq!(s.opaque, 0, "{s:?}");
        assert!(s.xi_95 < 0.02, "{s:?}");
        assert!(s.d_95 < 15.0, "{s:?}");
        assert!((0.85..=0.99).contains(&s.xi_coverage), "{s:?}");
        assert!((0.85..=0.99).contains(&s.d_coverage), "{s:?}");
    }

    #[test]
    fn a_strong_near_layer_leaves_xi_loose_and_says_so() {
        // Noise 1 % of a layer return 24 times the background's through it (df 500 mm, ξ 0.5):
        // ξ is loose (its error's p95 is several times 0.02), and the stated sigma says so.
        let s = noisy_layers(37, 200, 500.0..550.0, 0.5..0.55);
        assert!(s.xi_95 > 0.02, "{s:?}");
        assert!((0.85..=0.99).contains(&s.xi_coverage), "{s:?}");
        assert!((0.85..=0.99).contains(&s.d_coverage), "{s:?}");
    }

    #[test]
    fn noisy_opaque_surfaces_stay_opaque() {
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let mut rng = ChaCha8Rng::seed_from_u64(36);
        let (mut kept, mut d_err, mut covered) = (0, Vec::new(), 0);
        let draws = 200;
        for _ in 0..draws {
            let d = rng.random_range(300.0..1950.0);
            let mut o = Observed::new(&mf, &scene(d, 2000.0, 0.0), NOISE);
            o.add_noise(&mut rng);
            let est = inv.invert(&o.phasors()).expect("estimate");
            if est.opaque {
                kept += 1;
                let e = (est.foreground_distance_mm - d).abs();
                d_err.push(e);
                covered += usize::from(e <= 1.96 * est.foreground_distance_sigma_mm);
            }
        }
        let rate = kept as f64 / draws as f64;
        let cov = covered as f64 / kept.max(1) as f64;
        let d_95 = quantile(&mut d_err, 0.95);
        println!("opaque, noise 1 % of its return, {draws} draws: {rate:.3} flagged opaque; |d error| p95 {d_95:.2} mm; 1.96 sigma covers d {cov:.3}");
        // The test's level is 95 % (97.5 % with ξ² >= 0, a one-sided alternative).
        assert!(rate >= 0.9, "{rate}");
        assert!((0.85..=0.99).contains(&cov), "{cov}");
    }

    #[test]
    fn invalid_input_is_an_error() {
        let one = ForwardModel::physical(Sensor::sr4000());
        assert_eq!(
            MultiFrequencyModel::new(&one, &[]).err(),
            Some(MultiFrequencyError::NoFrequencies)
        );
        assert!(matches!(
            MultiFrequencyModel::new(&one, &[20.0 * MHZ, -1.0]),
            Err(MultiFrequencyError::NonPositiveFrequency(_))
        ));
        let (mf, inv) = model(Waveform::Sinusoid, &THREE);
        let o = Observed::new(&mf, &scene(1000.0, 2000.0, 0.5), NOISE_FREE);
        let short = PixelPhasors {
            measured: &o.measured[..2],
            ..o.phasors()
        };
        assert!(matches!(
            inv.invert(&short),
            Err(MultiFrequencyError::MismatchedLengths {
                what: "measured phasors",
                expected: 3,
                got: 2
            })
        ));
        let zero = [0.0; 3];
        assert!(matches!(
            inv.invert(&PixelPhasors {
                noise_sigma: &zero,
                ..o.phasors()
            }),
            Err(MultiFrequencyError::NonPositiveNoise(_))
        ));
        let dark = [Phasor::default(); 3];
        assert_eq!(
            inv.invert(&PixelPhasors {
                background: &dark,
                ..o.phasors()
            })
            .err(),
            Some(MultiFrequencyError::NoBackgroundReturn)
        );
        assert!(matches!(
            inv.invert(&PixelPhasors {
                background_distance_mm: 50.0,
                ..o.phasors()
            }),
            Err(MultiFrequencyError::BackgroundTooNear { .. })
        ));
        assert!(matches!(
            inv.fit_at_translucency(&o.phasors(), 1.5),
            Err(MultiFrequencyError::TranslucencyOutOfRange(_))
        ));
        let bad = ScanSettings {
            cells_per_range: 0.0,
            ..ScanSettings::default()
        };
        assert!(matches!(
            MultiFrequencyInversion::new(&mf, bad),
            Err(MultiFrequencyError::InvalidSettings(_))
        ));
    }
}
