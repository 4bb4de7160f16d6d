//! The inversion in closed form for the default physics ([`ModelOptions::physical`]):
//! two returns, the second crossing the layer twice (`L2 = Ib xi^2`, no `X`)
//! and the IR image the demodulated amplitude, on a sinusoidal sensor.
//!
//! There the reading and the IR together are the measured phasor
//! `M = I e^{i k d}` (`k = 2 pi / R`), and the second return's phasor
//! `xi^2 Ib e^{i k db}` is known for a hypothesised ξ. What is left is the
//! layer's own return (Eq. 1): `z = M - xi^2 Ib e^{i k db}`, whose phase is the
//! layer's distance and whose length gives `X` (Eq. 1 solved for `X`). One
//! exact root or none: no scan.

use super::*;
use crate::physics::near_wall::{third_return_distance, third_return_share};

/// The constants of the closed form for one model, or `None` when the model is not
/// the one it solves (the generic scan then runs).
#[derive(Debug, Clone, Copy)]
pub(super) struct PhasorModel {
    k: f64,
    range_mm: f64,
    offset: f64,
    delay_mm: f64,
    wall_gain: f64,
    hollow_mm: f64,
}

/// What the closed form needs of a pixel at every ξ: the sines and cosines of its
/// reading's and its background's phases.
#[derive(Debug, Clone, Copy)]
pub(super) struct PhaseTrig {
    sd: f64,
    cd: f64,
    sb: f64,
    cb: f64,
}

/// Fixed-point steps for the layer's distance with a near wall's third return or a hollow
/// object's back wall: each shrinks the error by about `(1 + sqrt 2) L3 / L1` (under 0.3
/// for any view factor) or `2 T / df` times the back wall's share.
const WALL_STEPS: usize = 12;

impl PhasorModel {
    /// `None` unless `model` is two returns, `L2 = Ib xi^2`, amplitude IR, a sinusoid without
    /// a depth engine and no refraction (an IR offset, a subsurface delay, a near wall's third return and a
    /// hollow object's back wall are allowed).
    pub(super) fn new(model: &ForwardModel) -> Option<Self> {
        let o = &model.options;
        let known = ModelOptions {
            ambient_offset: o.ambient_offset,
            subsurface_delay_mm: o.subsurface_delay_mm,
            wall_interreflection: o.wall_interreflection,
            hollow_depth_mm: o.hollow_depth_mm,
            ..ModelOptions::physical()
        };
        if *o != known || model.sensor.waveform != Waveform::Sinusoid || model.sensor.depth_engine().is_some() {
            return None;
        }
        let range_mm = model.sensor.unambiguous_range_mm();
        Some(Self {
            k: std::f64::consts::TAU / range_mm,
            range_mm,
            offset: o.ambient_offset,
            delay_mm: o.subsurface_delay_mm,
            wall_gain: o.wall_interreflection,
            hollow_mm: o.hollow_depth_mm,
        })
    }

    /// The returns that carry the layer's `X` beside its own, over its own (X cancels), at
    /// a layer `df`: `1 + sum_j (L_j / L1) e^{i theta_j}`, `theta_j` each one's phase past
    /// the layer's, for a near wall's third return and, with `walls`, a hollow object's back
    /// wall; as its phase and length, `(0, 1)` with neither.
    fn layer_factor(&self, obs: &PixelObservation, xi: f64, df: f64, walls: bool) -> (f64, f64) {
        let (mut wr, mut wi) = (1.0, 0.0);
        let mut add = |r: f64, theta: f64| {
            if r.is_finite() && r > 0.0 {
                let (s, c) = theta.sin_cos();
                wr += r * c;
                wi += r * s;
            }
        };
        if self.wall_gain > 0.0 && obs.wall_view_factor > 0.0 {
            let ib = (obs.background_ir - self.offset).max(0.0);
            let xb = obs.background_albedo_cos(self.offset);
            let third = self.wall_gain * third_return_share(xi, 1.0, xb, obs.wall_view_factor) * xi * xi * ib;
            let layer = (1.0 - xi) * obs.emitted_light / (df * df);
            let theta = self.k * (third_return_distance(df, obs.background_distance_mm) - df - self.delay_mm);
            add(third / layer, theta);
        }
        if walls {
            // The back wall: one crossing of the front each way, at T behind it.
            let back = df + self.hollow_mm;
            add(xi * xi * df * df / (back * back), self.k * self.hollow_mm);
        }
        if wr == 1.0 && wi == 0.0 {
            return (0.0, 1.0);
        }
        (wi.atan2(wr), wr.hypot(wi))
    }

    /// Whether a layer at `df` has a hollow object's back wall before the background.
    fn walls_at(&self, obs: &PixelObservation, df: f64) -> bool {
        self.hollow_mm > 0.0 && df + self.hollow_mm < obs.background_distance_mm
    }

    /// The layer's return `z` for a hypothesised ξ (its real and imaginary parts) and the
    /// measured amplitude `|M|`; `None` where the IR is not above the offset.
    fn layer_phasor(&self, obs: &PixelObservation, trig: &PhaseTrig, xi: f64, walls: bool) -> Option<(f64, f64, f64)> {
        let m = obs.ir - self.offset;
        let ib = (obs.background_ir - self.offset).max(0.0);
        if !(m > 0.0) {
            return None;
        }
        let PhaseTrig { sd, cd, sb, cb } = *trig;
        // Through a hollow object's back wall too, each way.
        let l2 = xi * xi * ib * if walls { xi * xi } else { 1.0 };
        Some((m * cd - l2 * cb, m * sd - l2 * sb, m))
    }

    /// `X` for a layer at `df` (the first crossing of the IR equation from `X = 0`, as
    /// the generic path finds it): the non-negative root of `|a X e^{i alpha} + c| = I`.
    pub(super) fn albedo_cos(&self, obs: &PixelObservation, df: f64, xi: f64, x_max: f64) -> Option<f64> {
        let m = obs.ir - self.offset;
        let walls = self.walls_at(obs, df);
        let c = xi * xi * (obs.background_ir - self.offset).max(0.0) * if walls { xi * xi } else { 1.0 };
        if !(m > 0.0) || c >= m {
            return None;
        }
        let (lead, length) = self.layer_factor(obs, xi, df, walls);
        let a = length * (1.0 - xi) * obs.emitted_light / (df * df);
        // a^2 X^2 + 2 a c cos(beta) X + c^2 - m^2 = 0, beta the angle between the layer's
        // return (with a near wall's third) and the background's.
        let cos_beta = (self.k * (df + self.delay_mm - obs.background_distance_mm) + lead).cos();
        let b = c * cos_beta;
        let x = (-b + (b * b + m * m - c * c).sqrt()) / a;
        (x.is_finite() && x >= 0.0 && x <= x_max).then_some(x)
    }

    /// The reading the model predicts for a layer at `df` of `X = x` (what
    /// [`predicted_reading`] decodes from the forward model's returns): the phase of the
    /// layer's return, with a near wall's third and a back wall by their lead and length, plus
    /// the background's share at its own phase.
    fn reading_at(&self, obs: &PixelObservation, (trig, walls): (&PhaseTrig, bool), df: f64, xi: f64, x: f64) -> f64 {
        let (lead, length) = self.layer_factor(obs, xi, df, walls);
        let a = x * length * (1.0 - xi) * obs.emitted_light / (df * df);
        let c = xi * xi * (obs.background_ir - self.offset).max(0.0) * if walls { xi * xi } else { 1.0 };
        let (s, co) = (self.k * (df + self.delay_mm) + lead).sin_cos();
        let (re, im) = (a * co + c * trig.cb, a * s + c * trig.sb);
        if re == 0.0 && im == 0.0 {
            return f64::NAN;
        }
        wrap(im.atan2(re) / self.k, self.range_mm)
    }

    /// The sines and cosines of a pixel's reading's and background's phases.
    pub(super) fn trig(&self, obs: &PixelObservation) -> PhaseTrig {
        let (sd, cd) = (self.k * obs.distance_mm).sin_cos();
        let (sb, cb) = (self.k * obs.background_distance_mm).sin_cos();
        PhaseTrig { sd, cd, sb, cb }
    }

    /// The layer at one pixel for a hypothesised ξ within `[lo, hi]`.
    pub(super) fn invert(
        &self,
        model: &ForwardModel,
        obs: &PixelObservation,
        xi: f64,
        x_max: f64,
        search: Search,
    ) -> Option<LayerEstimate> {
        self.invert_with(model, obs, &self.trig(obs), xi, x_max, search)
    }

    /// [`Self::invert`] with the pixel's [`Self::trig`] given (taken once for every ξ).
    /// With a hollow object, the layer with its back wall where that puts the back wall
    /// before the background, else the layer alone.
    pub(super) fn invert_with(
        &self,
        model: &ForwardModel,
        obs: &PixelObservation,
        trig: &PhaseTrig,
        xi: f64,
        x_max: f64,
        search: Search,
    ) -> Option<LayerEstimate> {
        if self.hollow_mm > 0.0 {
            let with_walls = self.solve(model, obs, (trig, true), xi, x_max, search);
            if with_walls.is_some_and(|e| self.walls_at(obs, e.foreground_distance_mm)) {
                return with_walls;
            }
        }
        self.solve(model, obs, (trig, false), xi, x_max, search)
    }

    /// [`Self::invert_with`] with or without a hollow object's back wall (`walls`).
    fn solve(
        &self,
        model: &ForwardModel,
        obs: &PixelObservation,
        (trig, walls): (&PhaseTrig, bool),
        xi: f64,
        x_max: f64,
        Search { lo, hi, slopes }: Search,
    ) -> Option<LayerEstimate> {
        let (re, im, m) = self.layer_phasor(obs, trig, xi, walls)?;
        // (Counts: no overflow for `hypot` to guard against, and the square root is cheaper.)
        let len = (re * re + im * im).sqrt();
        let x_scale = (1.0 - xi) * obs.emitted_light;
        if !(len > 0.0 && x_scale > 0.0) {
            return None;
        }
        // The layer's distance: the phase's, less the delay, in the search range if a period
        // allows; with a near wall's third return or a back wall, less their lead, found in turn.
        let phase = im.atan2(re);
        let from_phase = |lead: f64| lo + wrap((phase - lead) / self.k - self.delay_mm - lo, self.range_mm);
        let mut df = from_phase(0.0);
        let mut length = 1.0;
        if walls || (self.wall_gain > 0.0 && obs.wall_view_factor > 0.0) {
            for _ in 0..WALL_STEPS {
                let (lead, l) = self.layer_factor(obs, xi, df, walls);
                let next = from_phase(lead);
                length = l;
                let settled = (next - df).abs() < 1e-6;
                df = next;
                if settled {
                    break;
                }
            }
        }
        let x = len * df * df / (x_scale * length);
        let exact = df <= hi && x <= x_max;
        // The slopes as the generic path defines them (the predicted reading per mm of layer, the
        // IR held; per count of IR, the layer held), from the angle psi between M and z.
        let (slope, reading_per_ir) = if slopes {
            let (sd, cd) = (trig.sd, trig.cd);
            let (sin_psi, cos_psi) = ((cd * im - sd * re) / len, (cd * re + sd * im) / len);
            (len / (m * cos_psi), sin_psi / (self.k * m * cos_psi))
        } else {
            (f64::NAN, f64::NAN)
        };
        if exact {
            return Some(LayerEstimate {
                foreground_distance_mm: df,
                albedo_cos: x,
                residual_mm: 0.0,
                roots: 1,
                pinned: false,
                slope,
                reading_per_ir,
            });
        }
        // No admissible root: the nearest admissible layer, flagged pinned.
        let df = df.min(hi);
        let x = self.albedo_cos(obs, df, xi, x_max).unwrap_or(x_max);
        let pred = self.reading_at(obs, (trig, walls), df, xi, x);
        Some(LayerEstimate {
            foreground_distance_mm: df,
            albedo_cos: x,
            residual_mm: model.sensor.wrapped_difference_mm(pred, obs.distance_mm),
            roots: 0,
            pinned: true,
            slope,
            reading_per_ir,
        })
    }
}

/// `x` wrapped into `[0, r)` (`rem_euclid`, without its division's remainder call: `x` is
/// within a few ranges of 0 here).
fn wrap(x: f64, r: f64) -> f64 {
    let w = x - r * (x / r).floor();
    if w >= r {
        w - r
    } else {
        w
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::Sensor;

    use super::super::tests::observe as obs_of;

    #[test]
    fn recovers_the_layer_of_the_forward_model_exactly() {
        let model = ForwardModel::physical(Sensor::sr4000());
        let p = PhasorModel::new(&model).expect("the default physics has the closed form");
        let bounds = InversionBounds::default();
        let mut compared = 0;
        for &(df, db, xi, x, xb) in &[
            (1000.0, 2000.0, 0.65, 0.6, 1.0),
            (500.0, 2000.0, 0.94, 0.5, 0.4),
            (800.0, 3300.0, 0.91, 0.3, 1.0),
            (1750.0, 2000.0, 0.3, 0.7, 0.6),
            (2600.0, 3300.0, 0.8, 0.4, 0.9),
        ] {
            let o = obs_of(&model, df, db, xi, x, xb);
            let (lo, hi) = search_range(&o, &bounds).expect("range");
            let est = p
                .invert(&model, &o, xi, 1.0, Search { lo, hi, slopes: true })
                .expect("estimate");
            assert!(!est.pinned, "{df} {db} {xi}");
            assert!((est.foreground_distance_mm - df).abs() < 1e-6, "{df}: {est:?}");
            assert!((est.albedo_cos - x).abs() < 1e-9, "{x}: {est:?}");
            // The same layer as the generic scan finds, and the same X from the IR equation, where
            // those exist: both take the IR equation's first root from X = 0, which there is none
            // of when the background's return alone is brighter than the mix (they interfere).
            let background_return = xi * xi * o.background_ir;
            let Some(generic) =
                foreground_distance_generic(&model, &o, xi, &bounds, None, Search { lo, hi, slopes: true })
            else {
                assert!(
                    background_return >= o.ir,
                    "{df} {db} {xi}: the generic scan finds no layer"
                );
                assert!(p.albedo_cos(&o, df, xi, 1.0).is_none());
                continue;
            };
            compared += 1;
            assert!((generic.foreground_distance_mm - df).abs() < 0.05, "{generic:?}");
            assert!(
                (generic.slope.abs() - est.slope.abs()).abs() < 0.02 * est.slope.abs(),
                "{generic:?} {est:?}"
            );
            let ax = p.albedo_cos(&o, df, xi, 1.0).expect("albedo");
            assert!((ax - x).abs() < 1e-9);
        }
        assert!(compared >= 3, "{compared}");
    }

    #[test]
    fn a_layer_too_bright_for_any_albedo_is_pinned() {
        let model = ForwardModel::physical(Sensor::sr4000());
        let p = PhasorModel::new(&model).expect("closed form");
        // At a much smaller ξ than the truth the layer must be brighter than X = 1 allows.
        let o = obs_of(&model, 1000.0, 2000.0, 0.9, 0.9, 1.0);
        let (lo, hi) = search_range(&o, &InversionBounds::default()).expect("range");
        let est = p
            .invert(&model, &o, 0.0, 0.05, Search { lo, hi, slopes: false })
            .expect("estimate");
        assert!(est.pinned && est.albedo_cos <= 0.05);
    }

    #[test]
    fn its_predicted_reading_is_the_forward_models() {
        let mut worst = 0.0f64;
        for (delay, gain, hollow) in [(0.0, 0.0, 0.0), (12.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 150.0)] {
            let mut model = ForwardModel::physical(Sensor::sr4000());
            model.options.subsurface_delay_mm = delay;
            model.options.wall_interreflection = gain;
            model.options.hollow_depth_mm = hollow;
            let p = PhasorModel::new(&model).expect("closed form");
            let mut o = obs_of(&model, 900.0, 2000.0, 0.7, 0.6, 1.0);
            o.wall_view_factor = 0.2 * gain;
            for (df, xi, x) in [(900.0, 0.7, 0.6), (600.0, 0.4, 0.9), (1500.0, 0.9, 0.2)] {
                let walls = p.walls_at(&o, df);
                let want = predicted_reading(&model, &o, df, xi, x);
                let got = p.reading_at(&o, (&p.trig(&o), walls), df, xi, x);
                let diff = model.sensor.wrapped_difference_mm(got, want).abs();
                assert!(
                    diff < 1e-6,
                    "{delay} {gain} {hollow} {df} {xi} {x}: {got} against {want}"
                );
                worst = worst.max(diff);
            }
        }
        println!("closed-form predicted reading: worst difference {worst:.1e} mm");
    }

    #[test]
    fn only_the_model_it_solves() {
        assert!(PhasorModel::new(&ForwardModel::paper(Sensor::sr4000())).is_none());
        let mut m = ForwardModel::physical(Sensor::sr4000());
        m.options.bounces = 3;
        assert!(PhasorModel::new(&m).is_none());
        let t = ForwardModel::physical(Sensor::new(30e6, Waveform::Triangle));
        assert!(PhasorModel::new(&t).is_none());
    }

    #[test]
    fn recovers_the_layer_of_the_forward_model_with_a_near_walls_third_return() {
        let mut model = ForwardModel::physical(Sensor::sr4000());
        model.options.wall_interreflection = 1.0;
        let p = PhasorModel::new(&model).expect("the closed form takes the near wall");
        for &(df, db, xi, x, xb, f) in &[
            (1750.0, 2000.0, 0.65, 0.6, 1.0, 0.27),
            (2700.0, 3000.0, 0.8, 0.4, 0.5, 0.4),
            (1000.0, 2000.0, 0.3, 0.7, 0.9, 0.05),
        ] {
            let o = super::super::tests::observe_near_wall(&model, [df, db], xi, x, xb, f);
            let est = inverted(&p, &model, &o, xi);
            assert!(!est.pinned, "{df} {xi}: {est:?}");
            assert!((est.foreground_distance_mm - df).abs() < 1e-3, "{df}: {est:?}");
            assert!((est.albedo_cos - x).abs() < 1e-6, "{x}: {est:?}");
            assert!((p.albedo_cos(&o, df, xi, 1.0).expect("albedo") - x).abs() < 1e-9);
            // Without the third return the same reading puts the layer elsewhere (by a quarter
            // of a millimetre for the weakest view here).
            let plain = PixelObservation {
                wall_view_factor: 0.0,
                diffuse_lobe: None,
                ..o
            };
            let off = inverted(&p, &model, &plain, xi);
            assert!((off.foreground_distance_mm - df).abs() > 0.2, "{df}: {off:?}");
        }
    }

    #[test]
    fn recovers_the_front_of_a_hollow_object_of_the_forward_model() {
        let mut model = ForwardModel::physical(Sensor::sr4000());
        model.options.hollow_depth_mm = 220.0;
        let p = PhasorModel::new(&model).expect("the closed form takes a back wall");
        for &(df, db, xi, x, xb) in &[
            (1000.0, 2600.0, 0.65, 0.6, 1.0),
            (1800.0, 3000.0, 0.8, 0.4, 0.5),
            // The back wall would lie behind the background: one layer.
            (2500.0, 2650.0, 0.6, 0.5, 0.8),
        ] {
            let est = inverted(&p, &model, &obs_of(&model, df, db, xi, x, xb), xi);
            assert!(!est.pinned, "{df} {xi}: {est:?}");
            assert!((est.foreground_distance_mm - df).abs() < 1e-3, "{df}: {est:?}");
            assert!((est.albedo_cos - x).abs() < 1e-6, "{x}: {est:?}");
        }
    }

    /// A pixel inverted by the closed form over the default search range, without slopes.
    fn inverted(p: &PhasorModel, model: &ForwardModel, o: &PixelObservation, xi: f64) -> LayerEstimate {
        let (lo, hi) = search_range(o, &InversionBounds::default()).expect("range");
        p.invert(model, o, xi, 1.0, Search { lo, hi, slopes: false })
            .expect("estimate")
    }
}
