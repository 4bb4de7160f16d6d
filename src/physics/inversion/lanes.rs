//! Many pixels inverted at one ξ side by side (Eq. 8-12).
//!
//! Eight pixels at a time run the fast path's common case in straight-line
//! code over arrays of eight lanes, which the compiler turns into vector
//! instructions (AVX2 where the processor has it, chosen at run time). The
//! common case is a pixel whose search range meets at most two half-periods
//! of the closed root structure ([`HumpRoots`]) and finds exactly one root
//! there, from one end of its half-period (the other half-period has none).
//! Every lane does the same work: the pixel's constants, `e` at the ends of
//! both half-periods, Newton's method in lockstep until every lane has
//! stopped, the root's sample and its slopes. Any other pixel (no root,
//! several, a half-period that needs its maximum, an angle beyond the
//! polynomial's range, a residual off the small-angle series) is inverted on
//! its own afterwards, so the answer is [`foreground_distance`]'s for every
//! pixel, bit for bit (test `the_same_as_pixel_by_pixel`): each lane calls
//! the pixel's own pieces ([`search_range`], [`FastModel::angles`],
//! [`FastModel::pixel`], [`HumpRoots::of`], [`HumpRoots::holds`], [`HumpRoots::e_at`],
//! [`FastPixel::albedo_strengths_unchecked`], [`FastPixel::derivatives_at`],
//! ...) with the same `sin`/`cos` ([`sin_cos_reduced`]); what the lanes add
//! is the half-period walk and Newton's loop for the common case, written
//! over eight lanes, and their checks as masks.

use super::*;
use crate::physics::trig::{sin_cos_reduced, REDUCED_LIMIT};

/// Lanes of one pass.
const W: usize = 8;

/// One number per lane.
type V = [f64; W];

/// Largest angle, radians, a lane may meet: below [`REDUCED_LIMIT`], so the
/// per-pixel path's [`sin_cos`] takes the same polynomial.
const ANGLE_LIMIT: f64 = 1.0e6;
const _: () = assert!(ANGLE_LIMIT < REDUCED_LIMIT);

// Plain loops, not `std::array::from_fn`: the compiler does not always inline that, and
// what it leaves out of line is not built for the pass's target features.
#[inline(always)]
fn lanes(mut f: impl FnMut(usize) -> f64) -> V {
    let mut v = [0.0; W];
    for (l, v) in v.iter_mut().enumerate() {
        *v = f(l);
    }
    v
}

#[inline(always)]
fn masks(mut f: impl FnMut(usize) -> bool) -> [bool; W] {
    let mut m = [false; W];
    for (l, m) in m.iter_mut().enumerate() {
        *m = f(l);
    }
    m
}

/// Pixels to be inverted at many ξ (a profile over ξ): what does not change with ξ taken
/// once (the closed form's phases, [`PhasorModel`]); [`Self::at`] gives
/// [`foreground_distances`]'s estimates, bit for bit.
pub struct PixelsOverXi<'a> {
    model: &'a ForwardModel,
    obs: Vec<PixelObservation>,
    phasor: Option<(PhasorModel, Vec<phasor::PhaseTrig>)>,
}

impl<'a> PixelsOverXi<'a> {
    /// The pixels `obs` under `model`.
    pub fn new(model: &'a ForwardModel, obs: Vec<PixelObservation>) -> Self {
        let phasor = PhasorModel::new(model).map(|p| {
            let trig = obs.iter().map(|o| p.trig(o)).collect();
            (p, trig)
        });
        Self { model, obs, phasor }
    }

    /// Every pixel's estimate at `xi`, in order ([`foreground_distances`]).
    pub fn at(&self, xi: f64, bounds: &InversionBounds, slopes: bool) -> Vec<Option<LayerEstimate>> {
        let Some((p, trig)) = &self.phasor else {
            return foreground_distances(self.model, &self.obs, xi, bounds, slopes);
        };
        self.obs
            .iter()
            .zip(trig)
            .map(|(o, t)| {
                let (lo, hi) = search_range(o, bounds)?;
                p.invert_with(self.model, o, t, xi, bounds.max_albedo_cos, Search { lo, hi, slopes })
            })
            .collect()
    }
}

/// [`foreground_distance`] (`slopes`) or [`foreground_distance_without_slopes`]
/// of every pixel in `obs` at one ξ, in order, the root nearest each reading
/// (no preference): the same estimates, bit for bit.
pub fn foreground_distances(
    model: &ForwardModel,
    obs: &[PixelObservation],
    xi: f64,
    bounds: &InversionBounds,
    slopes: bool,
) -> Vec<Option<LayerEstimate>> {
    let mut out = Vec::with_capacity(obs.len());
    let Some(fm) = FastModel::new(model, xi, bounds.max_albedo_cos) else {
        out.extend(obs.iter().map(|o| invert(model, o, xi, bounds, None, slopes)));
        return out;
    };
    let mut chunks = obs.chunks_exact(W);
    for chunk in &mut chunks {
        let chunk: &[PixelObservation; W] = chunk.try_into().expect("chunks_exact gives W");
        let lanes = pass(&fm, bounds, chunk, slopes);
        for (o, lane) in chunk.iter().zip(lanes) {
            out.push(match lane {
                Lane::Done(est) => Some(est),
                Lane::Alone => invert(model, o, xi, bounds, None, slopes),
            });
        }
    }
    out.extend(
        chunks
            .remainder()
            .iter()
            .map(|o| invert(model, o, xi, bounds, None, slopes)),
    );
    out
}

/// What one lane of a pass gave.
#[derive(Clone, Copy)]
enum Lane {
    /// The pixel's estimate.
    Done(LayerEstimate),
    /// Not the common case: the pixel is inverted on its own.
    Alone,
}

/// One pass over eight pixels, the power's code chosen for the processor.
fn pass(fm: &FastModel, bounds: &InversionBounds, obs: &[PixelObservation; W], slopes: bool) -> [Lane; W] {
    #[cfg(target_arch = "x86_64")]
    {
        if crate::physics::vector::avx2() {
            // SAFETY: the processor has AVX2 (`avx2` checks it).
            return unsafe {
                match fm.p {
                    2.0 => pass_avx2::<2>(fm, bounds, obs, slopes),
                    1.0 => pass_avx2::<1>(fm, bounds, obs, slopes),
                    _ => pass_avx2::<0>(fm, bounds, obs, slopes),
                }
            };
        }
    }
    match fm.p {
        2.0 => pass_lanes::<2>(fm, bounds, obs, slopes),
        1.0 => pass_lanes::<1>(fm, bounds, obs, slopes),
        _ => pass_lanes::<0>(fm, bounds, obs, slopes),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn pass_avx2<const P: u8>(
    fm: &FastModel,
    bounds: &InversionBounds,
    obs: &[PixelObservation; W],
    slopes: bool,
) -> [Lane; W] {
    pass_lanes::<P>(fm, bounds, obs, slopes)
}

/// The lanes' pixels, field by field (so the per-lane loops stay in vector
/// registers): each lane's [`FastPixel`] and [`HumpRoots`] are made from
/// them where used, their `p` the constant `P`.
struct Pixels<const P: u8> {
    k: f64,
    mm_per_rad: f64,
    x_max: f64,
    ir: V,
    a: V,
    l1: V,
    phi_d: V,
    /// The background's `(sin, cos)`.
    sb: V,
    cb: V,
    /// `HumpRoots`' sign, `|sin beta|` and `tau`'s constant.
    sigma: V,
    s: V,
    c: V,
}

impl<const P: u8> Pixels<P> {
    #[inline(always)]
    fn fast(&self, l: usize) -> FastPixel {
        FastPixel {
            ir: self.ir[l],
            a: self.a[l],
            l1: self.l1[l],
            p: f64::from(P),
            x_max: self.x_max,
            k: self.k,
            mm_per_rad: self.mm_per_rad,
            phi_d: self.phi_d[l],
            bg: (self.cb[l], self.sb[l]),
        }
    }

    #[inline(always)]
    fn hump(&self, l: usize) -> HumpRoots {
        HumpRoots {
            sigma: self.sigma[l],
            s: self.s[l],
            k: self.k,
            mm_per_rad: self.mm_per_rad,
            phi_d: self.phi_d[l],
            p: f64::from(P),
            c: self.c[l],
        }
    }
}

/// [`HumpRoots::e`] in every lane.
#[inline(always)]
fn e_lanes<const P: u8>(px: &Pixels<P>, df: &V) -> (V, V) {
    let mut e = [0.0; W];
    let mut de = [0.0; W];
    for l in 0..W {
        let h = px.hump(l);
        (e[l], de[l]) = h.e_at(df[l], sin_cos_reduced(h.k * df[l] - h.phi_d));
    }
    (e, de)
}

/// `e` and `de / d df` at both ends of a half-period in every lane (zeros
/// when no lane `needed` it).
#[inline(always)]
fn ends_lanes<const P: u8>(needed: bool, px: &Pixels<P>, lower: &V, upper: &V) -> (V, V, V, V) {
    if needed {
        let (el, dl) = e_lanes(px, lower);
        let (eu, du) = e_lanes(px, upper);
        (el, dl, eu, du)
    } else {
        ([0.0; W], [0.0; W], [0.0; W], [0.0; W])
    }
}

/// The lanes' pass: see the module's text. Each expression is the per-pixel
/// path's, in its order.
#[inline(always)]
fn pass_lanes<const P: u8>(
    fm: &FastModel,
    bounds: &InversionBounds,
    obs: &[PixelObservation; W],
    slopes: bool,
) -> [Lane; W] {
    let (px, mut ok, hi_e) = lane_pixels::<P>(fm, bounds, obs);
    let h = half_periods(fm, bounds, &px, &hi_e, &mut ok);
    let mut start = root_starts(&h, &mut ok);
    newton_lanes(&px, &mut start, ok);
    lane_results(fm, &px, &start.x, ok, slopes)
}

/// Each lane's FastPixel and HumpRoots constants, whether its checks (and its range's)
/// hold, and the upper end of its admissible range.
#[inline(always)]
fn lane_pixels<const P: u8>(
    fm: &FastModel,
    bounds: &InversionBounds,
    obs: &[PixelObservation; W],
) -> (Pixels<P>, [bool; W], V) {
    let lo = bounds.min_distance_mm;
    // invert's range (where there is none the lane is not ok: its upper end NaN).
    let mut hi = [f64::NAN; W];
    // FastPixel: the constants.
    let mut phi0 = [0.0; W];
    let mut angle = [0.0; W];
    for l in 0..W {
        if let Some((_, h)) = search_range(&obs[l], bounds) {
            hi[l] = h;
        }
        (phi0[l], angle[l]) = fm.angles(&obs[l]);
    }
    let mut sb = [0.0; W];
    let mut cb = [0.0; W];
    for l in 0..W {
        (sb[l], cb[l]) = sin_cos_reduced(angle[l]);
    }
    let mut px = Pixels::<P> {
        k: fm.k,
        mm_per_rad: fm.mm_per_rad,
        x_max: fm.x_max,
        ir: [0.0; W],
        a: [0.0; W],
        l1: [0.0; W],
        phi_d: [0.0; W],
        sb,
        cb,
        sigma: [0.0; W],
        s: [0.0; W],
        c: [0.0; W],
    };
    for l in 0..W {
        let f = fm.pixel(&obs[l], phi0[l], (sb[l], cb[l]));
        (px.ir[l], px.a[l], px.l1[l], px.phi_d[l]) = (f.ir, f.a, f.l1, f.phi_d);
    }
    // HumpRoots::new, its checks (and the range's) as a mask.
    let mut ok = [false; W];
    for l in 0..W {
        let f = px.fast(l);
        let hump = HumpRoots::of(&f);
        (px.sigma[l], px.s[l], px.c[l]) = (hump.sigma, hump.s, hump.c);
        ok[l] = hi[l] > lo && angle[l].abs() <= ANGLE_LIMIT && hump.holds(&f);
    }
    let hi_e = lanes(|l| hi[l].min(admissible_limit(&px.fast(l))));
    (px, ok, hi_e)
}

/// The two half-periods a lane's root may lie in: their ends in the range, whether each is
/// active, and e (with its slope) at the ends.
struct HalfPeriods {
    l0: V,
    u0: V,
    lb1: V,
    u1: V,
    act0: [bool; W],
    act1: [bool; W],
    ends0: (V, V, V, V),
    ends1: (V, V, V, V),
}

/// HumpRoots::roots: the half-periods m and m + 1 (m + 2 must lie beyond the range; a lane
/// where it does not, or whose ends leave the small-angle series, is not ok).
#[inline(always)]
fn half_periods<const P: u8>(
    fm: &FastModel,
    bounds: &InversionBounds,
    px: &Pixels<P>,
    hi_e: &V,
    ok: &mut [bool; W],
) -> HalfPeriods {
    use std::f64::consts::{FRAC_1_PI, PI, TAU};
    let (k, lo) = (fm.k, bounds.min_distance_mm);
    let (phi_d, sigma) = (px.phi_d, px.sigma);
    let a0 = lanes(|l| if sigma[l] > 0.0 { 0.0 } else { PI });
    let m0 = lanes(|l| ((k * lo - phi_d[l] - a0[l]) * (0.5 * FRAC_1_PI)).floor());
    let m1 = lanes(|l| m0[l] + 1.0);
    let to_df = |alpha: f64, l: usize| (alpha + phi_d[l]) * fm.mm_per_rad;
    let start0 = lanes(|l| to_df(a0[l] + TAU * m0[l], l));
    let start1 = lanes(|l| to_df(a0[l] + TAU * m1[l], l));
    let l0 = lanes(|l| start0[l].max(lo));
    let u0 = lanes(|l| to_df(a0[l] + TAU * m0[l] + PI, l).min(hi_e[l]));
    let lb1 = lanes(|l| start1[l].max(lo));
    let u1 = lanes(|l| to_df(a0[l] + TAU * m1[l] + PI, l).min(hi_e[l]));
    let act0 = masks(|l| start0[l] < hi_e[l] && l0[l] < u0[l]);
    let act1 = masks(|l| start1[l] < hi_e[l] && lb1[l] < u1[l]);
    for l in 0..W {
        let start2 = to_df(a0[l] + TAU * (m1[l] + 1.0), l);
        let ends = [l0[l], u0[l], lb1[l], u1[l]];
        ok[l] &= !(start2 < hi_e[l]) && ends.iter().all(|&x| (k * x - phi_d[l]).abs() <= ANGLE_LIMIT);
    }
    // e at the half-periods' ends (a half-period no lane needs is skipped).
    // (Plain calls: a closure the compiler does not inline is not built for the pass's
    // target features.)
    let needed0 = act0.iter().zip(ok.iter()).any(|(&a, &o)| a & o);
    let needed1 = act1.iter().zip(ok.iter()).any(|(&a, &o)| a & o);
    let ends0 = ends_lanes(needed0, px, &l0, &u0);
    let ends1 = ends_lanes(needed1, px, &lb1, &u1);
    HalfPeriods {
        l0,
        u0,
        lb1,
        u1,
        act0,
        act1,
        ends0,
        ends1,
    }
}

/// Where each lane's Newton iteration starts and what bounds it.
struct RootStart {
    x: V,
    toward: V,
    e: V,
    de: V,
}

/// Each lane's one root: from the end of its half-period where e <= 0 (a lane with none, or
/// two, is not ok).
#[inline(always)]
fn root_starts(h: &HalfPeriods, ok: &mut [bool; W]) -> RootStart {
    let (el0, dl0, eu0, du0) = h.ends0;
    let (el1, dl1, eu1, du1) = h.ends1;
    let mut r = RootStart {
        x: [0.0; W],
        toward: [0.0; W],
        e: [0.0; W],
        de: [0.0; W],
    };
    for l in 0..W {
        // 0: no root; 1: from the lower end; 2: from the upper; 3: two or none (the maximum).
        let kind = |act: bool, el: f64, eu: f64| -> u8 {
            match (act, el > 0.0, eu > 0.0) {
                (false, _, _) | (true, true, true) => 0,
                (true, false, true) => 1,
                (true, true, false) => 2,
                (true, false, false) => 3,
            }
        };
        let k0 = kind(h.act0[l], el0[l], eu0[l]);
        let k1 = kind(h.act1[l], el1[l], eu1[l]);
        ok[l] &= (k0 == 0) != (k1 == 0) && k0 != 3 && k1 != 3;
        (r.x[l], r.toward[l], r.e[l], r.de[l]) = match (k0, k1) {
            (1, _) => (h.l0[l], h.u0[l], el0[l], dl0[l]),
            (2, _) => (h.u0[l], h.l0[l], eu0[l], du0[l]),
            (_, 1) => (h.lb1[l], h.u1[l], el1[l], dl1[l]),
            _ => (h.u1[l], h.lb1[l], eu1[l], du1[l]),
        };
    }
    r
}

/// HumpRoots::newton in lockstep: each running lane's root to 1 µm, within its bracket.
#[inline(always)]
fn newton_lanes<const P: u8>(px: &Pixels<P>, r: &mut RootStart, ok: [bool; W]) {
    let nlo = lanes(|l| r.x[l].min(r.toward[l]));
    let nhi = lanes(|l| r.x[l].max(r.toward[l]));
    let mut running = ok;
    let (mut e, mut de) = (r.e, r.de);
    for iteration in 0..50 {
        if iteration > 0 {
            (e, de) = e_lanes(px, &r.x);
        }
        // Selects, not branches, so the lanes stay in vector registers.
        for l in 0..W {
            let step = -e[l] / de[l];
            // f64::clamp's result without its check (a lane not running may hold NaN).
            let v = r.x[l] + step;
            let next = if v < nlo[l] {
                nlo[l]
            } else if v > nhi[l] {
                nhi[l]
            } else {
                v
            };
            let moved = (next - r.x[l]).abs();
            let go = running[l] & (step.abs() < f64::INFINITY);
            r.x[l] = if go { next } else { r.x[l] };
            running[l] = go & !((moved < 1e-3) | (e[l] == 0.0));
        }
        if !running.iter().any(|&r| r) {
            break;
        }
    }
}

/// The roots' samples (FastPixel::eval) and slopes (FastPixel::derivatives): a lane done
/// where it is the common case, alone (for the scalar path) otherwise.
#[inline(always)]
fn lane_results<const P: u8>(fm: &FastModel, px: &Pixels<P>, x: &V, ok: [bool; W], slopes: bool) -> [Lane; W] {
    let (k, phi_d) = (fm.k, px.phi_d);
    let mut sn = [0.0; W];
    let mut cs = [0.0; W];
    for l in 0..W {
        (sn[l], cs[l]) = sin_cos_reduced(k * x[l] - phi_d[l]);
    }
    // Every lane computed, then kept where it is the common case (selects, not branches).
    let mut strengths = [(0.0, 0.0, 0.0); W];
    let mut re = [0.0; W];
    let mut im = [0.0; W];
    let mut residual = [0.0; W];
    for l in 0..W {
        let f = px.fast(l);
        strengths[l] = f.albedo_strengths_unchecked(x[l]);
        let (_, s1, s2) = strengths[l];
        (re[l], im[l]) = f.mix(s1, s2, (sn[l], cs[l]));
        residual[l] = f.small_angle_residual_mm(re[l], im[l]);
    }
    let range = fm.range_mm;
    let done = masks(|l| {
        let f = px.fast(l);
        ok[l]
            & f.admissible(strengths[l].0)
            & on_small_angle_series(re[l], im[l])
            & (residual[l].abs() < f64::INFINITY)
            & (residual[l].abs() < range / 4.0)
    });
    let mut slope = [f64::NAN; W];
    let mut per_ir = [f64::NAN; W];
    if slopes {
        for l in 0..W {
            let f = px.fast(l);
            let (along, across) = f.derivatives_at(x[l], strengths[l], (sn[l], cs[l]));
            let finite = (along.abs() < f64::INFINITY) & (across.abs() < f64::INFINITY);
            slope[l] = if finite { along } else { f64::NAN };
            per_ir[l] = if finite { across } else { f64::NAN };
        }
    }
    let mut out = [Lane::Alone; W];
    for (l, out) in out.iter_mut().enumerate() {
        *out = if done[l] {
            Lane::Done(LayerEstimate {
                foreground_distance_mm: x[l],
                albedo_cos: strengths[l].0,
                residual_mm: residual[l],
                roots: 1,
                pinned: false,
                slope: slope[l],
                reading_per_ir: per_ir[l],
            })
        } else {
            Lane::Alone
        };
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::model::{IrMode, ModelOptions};
    use crate::physics::sensor::{Sensor, Waveform};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Pixels drawn from seeded ranges: the layer anywhere before the background, any
    /// translucency and albedo, noise on the reading and the IR, some with the IR or
    /// reading far off (no root, several roots, nothing admissible).
    fn pixels(model: &ForwardModel, seed: u64, n: usize) -> Vec<PixelObservation> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let lin = 1.5e10;
        (0..n)
            .map(|_| {
                let db = rng.random_range(600.0..4500.0);
                let df = rng.random_range(150.0..db - 20.0);
                let xb = rng.random_range(0.2..1.0);
                let s = LayerScene {
                    foreground_distance_mm: df,
                    background_distance_mm: db,
                    translucency: rng.random_range(0.05..0.97),
                    foreground_albedo_cos: rng.random_range(0.05..1.0),
                    background_albedo_cos: xb,
                    emitted_light: lin,
                    wall_view_factor: 0.0,
                    diffuse_lobe: None,
                };
                let m = model.measure_layer(&s);
                let bg = model.measure(&[ForwardModel::opaque_return(db, xb, lin)]);
                let wild = rng.random_range(0.0..1.0) < 0.1;
                PixelObservation {
                    distance_mm: m.distance_mm + rng.random_range(-15.0..15.0) + if wild { 900.0 } else { 0.0 },
                    ir: m.ir * rng.random_range(0.97..1.03) * if wild { 3.0 } else { 1.0 },
                    background_distance_mm: db,
                    background_ir: bg.ir,
                    emitted_light: lin,
                    wall_view_factor: 0.0,
                    diffuse_lobe: None,
                }
            })
            .collect()
    }

    fn bits(e: &Option<LayerEstimate>) -> Option<[u64; 7]> {
        e.map(|e| {
            [
                e.foreground_distance_mm.to_bits(),
                e.albedo_cos.to_bits(),
                e.residual_mm.to_bits(),
                u64::from(e.roots),
                u64::from(e.pinned),
                e.slope.to_bits(),
                e.reading_per_ir.to_bits(),
            ]
        })
    }

    #[test]
    fn the_same_as_pixel_by_pixel() {
        let sr4000 = Sensor::sr4000();
        let paper = ForwardModel::paper(sr4000.clone());
        let with = |options: ModelOptions| ForwardModel {
            options,
            ..paper.clone()
        };
        let models = [
            paper.clone(),
            with(ModelOptions {
                transmission_albedo_power: 1.0,
                ..paper.options.clone()
            }),
            with(ModelOptions {
                transmission_albedo_power: 0.0,
                ..paper.options.clone()
            }),
            with(ModelOptions {
                ambient_offset: 40.0,
                subsurface_delay_mm: 6.0,
                ..paper.options.clone()
            }),
            // Not on the fast path: every pixel is inverted on its own.
            with(ModelOptions {
                ir_mode: IrMode::Amplitude,
                ..paper.options.clone()
            }),
            ForwardModel::paper(Sensor::new(30e6, Waveform::Triangle)),
        ];
        let bounds = InversionBounds::default();
        let mut checked = [0usize; 4];
        let mut laned = 0;
        for (seed, model) in models.iter().enumerate() {
            let obs = pixels(model, 7 + seed as u64, 600);
            for xi in [0.3, 0.65, 0.9] {
                for slopes in [true, false] {
                    let batch = foreground_distances(model, &obs, xi, &bounds, slopes);
                    if let Some(fm) = FastModel::new(model, xi, bounds.max_albedo_cos) {
                        for chunk in obs.chunks_exact(W) {
                            let chunk: &[PixelObservation; W] = chunk.try_into().expect("W");
                            let dispatched = pass(&fm, &bounds, chunk, slopes);
                            laned += dispatched.iter().filter(|l| matches!(l, Lane::Done(_))).count();
                            // The code for any processor (built for the base target here) gives
                            // what the dispatched one gives.
                            let portable = match fm.p {
                                2.0 => pass_lanes::<2>(&fm, &bounds, chunk, slopes),
                                1.0 => pass_lanes::<1>(&fm, &bounds, chunk, slopes),
                                _ => pass_lanes::<0>(&fm, &bounds, chunk, slopes),
                            };
                            for (a, b) in dispatched.iter().zip(&portable) {
                                let done = |l: &Lane| match l {
                                    Lane::Done(e) => bits(&Some(*e)),
                                    Lane::Alone => None,
                                };
                                assert_eq!(done(a), done(b));
                            }
                        }
                    }
                    assert_eq!(batch.len(), obs.len());
                    for (o, b) in obs.iter().zip(&batch) {
                        let one = invert(model, o, xi, &bounds, None, slopes);
                        assert_eq!(bits(b), bits(&one), "{o:?} at xi {xi}: {b:?} vs {one:?}");
                        match one {
                            None => checked[0] += 1,
                            Some(e) if e.pinned => checked[1] += 1,
                            Some(e) if e.roots > 1 => checked[2] += 1,
                            Some(_) => checked[3] += 1,
                        }
                    }
                }
            }
        }
        // Every kind of outcome was compared, and most single roots came from the lanes.
        assert!(checked.iter().all(|&c| c > 50), "{checked:?}");
        assert!(
            laned * 2 > checked[3],
            "{laned} of {} single roots from the lanes",
            checked[3]
        );
    }

    #[test]
    fn empty_and_degenerate_input() {
        let model = ForwardModel::paper(Sensor::sr4000());
        let bounds = InversionBounds::default();
        assert!(foreground_distances(&model, &[], 0.65, &bounds, true).is_empty());
        let bad = PixelObservation {
            distance_mm: f64::NAN,
            ir: 100.0,
            background_distance_mm: 2000.0,
            background_ir: 200.0,
            emitted_light: 1.5e10,
            wall_view_factor: 0.0,
            diffuse_lobe: None,
        };
        let beyond = PixelObservation {
            distance_mm: 1e12,
            background_distance_mm: 1e13,
            ..bad
        };
        // A pass of lanes (W) and a remainder, both kinds in each.
        let input: Vec<PixelObservation> = (0..W + 3).map(|i| if i % 2 == 0 { bad } else { beyond }).collect();
        let out = foreground_distances(&model, &input, 0.65, &bounds, true);
        assert_eq!(out.len(), input.len());
        for (o, e) in input.iter().zip(&out) {
            assert_eq!(bits(e), bits(&invert(&model, o, 0.65, &bounds, None, true)));
        }
        assert!(out[0].is_none());
    }

    #[test]
    fn pixels_over_xi_give_each_xi_what_the_batch_gives() {
        let sr4000 = Sensor::sr4000();
        let mut near_wall = ForwardModel::physical(sr4000.clone());
        near_wall.options.wall_interreflection = 1.0;
        let bounds = InversionBounds::default();
        for (seed, model) in [
            ForwardModel::physical(sr4000.clone()),
            near_wall,
            ForwardModel::paper(sr4000),
        ]
        .iter()
        .enumerate()
        {
            let mut obs = pixels(model, 40 + seed as u64, 300);
            for (k, o) in obs.iter_mut().enumerate() {
                o.wall_view_factor = (k % 4) as f64 * 0.1;
            }
            let over = PixelsOverXi::new(model, obs.clone());
            for xi in [0.0, 0.3, 0.65, 0.9] {
                for slopes in [true, false] {
                    let batch = foreground_distances(model, &obs, xi, &bounds, slopes);
                    let each = over.at(xi, &bounds, slopes);
                    assert_eq!(batch.len(), each.len());
                    for (a, b) in batch.iter().zip(&each) {
                        assert_eq!(bits(a), bits(b), "model {seed}, xi {xi}");
                    }
                }
            }
        }
    }
}
