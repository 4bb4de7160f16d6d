//! The share of a pixel that a layer covers, on the layer's outline.
//!
//! A pixel that a layer of ξ covers by a share `c` collects the layer's returns over
//! `c` of its footprint and the background's own return over the rest. On a sinusoidal
//! sensor whose IR is the demodulated amplitude the reading and the IR are one measured
//! phasor `M`, and the returns add as phasors: `M = (1 - c) B + c (P0 + X P1)`, where `B`
//! is the latched background's phasor and `P0 + X P1` the one forward model's layer pixel
//! at the layer's distance (`P1` what scales with the layer's `X`, `P0` the rest: the
//! background through the layer). With the layer's distance from its surface and ξ from
//! its region, `M - B = c (P0 - B) + (c X) P1` is two equations in `c` and `c X`.
//!
//! The ground truth of a pixel is what its centre sees: the layer where `c >= 1/2`, the
//! background elsewhere. Where the layer's own return is under the noise (ξ near 1) the
//! dimming of the background still shows `c`.

use super::{ForwardModel, IrMode, PixelObservation, Return, Waveform};

/// A pixel's covered share and its standard deviation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coverage {
    /// `c`, the share of the pixel the layer covers (not clamped to `[0, 1]`).
    pub share: f64,
    /// Its standard deviation from the reading's and the IR's noise.
    pub share_sigma: f64,
}

impl Coverage {
    /// From the share `t` of the background's return left at a pixel (and its standard
    /// deviation) under a layer of `xi`: `t = 1 - c (1 - ξ^2)`. `None` where the layer dims
    /// nothing (ξ 1) or the inputs are not finite.
    pub fn from_background_share(t: f64, t_sigma: f64, xi: f64) -> Option<Self> {
        let dimming = 1.0 - xi * xi;
        let (share, share_sigma) = ((1.0 - t) / dimming, t_sigma / dimming);
        (dimming > 0.0 && share.is_finite() && share_sigma.is_finite()).then_some(Self { share, share_sigma })
    }

    /// Whether the pixel's centre sees the layer: it covers half of it or more (the ground
    /// truth of a pixel is what its centre sees).
    pub fn centre_covered(&self) -> bool {
        self.share >= 0.5
    }

    /// The least standard deviation a layer's depth published there may have: half the gap
    /// `gap_mm` between the layer and the background where the share's 95 % interval holds
    /// one half (the data cannot tell which its centre sees), 0 elsewhere.
    pub fn sigma_floor_mm(&self, gap_mm: f64) -> f64 {
        if (self.share - 1.96 * self.share_sigma..=self.share + 1.96 * self.share_sigma).contains(&0.5) {
            gap_mm.abs() / 2.0
        } else {
            0.0
        }
    }
}

impl Coverage {
    /// Whether the share's 95 % interval leaves one half out: the data say which side of
    /// the pixel's centre the outline passes.
    pub fn decided(&self) -> bool {
        (self.share - 0.5).abs() > 1.96 * self.share_sigma
    }
}

/// One pixel of a layer's outline (its own outline pixels and the pixels beside them): its
/// column, row and covered share.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutlinePixel {
    /// Column, pixels.
    pub x: f64,
    /// Row, pixels.
    pub y: f64,
    /// Its own covered share.
    pub coverage: Coverage,
}

/// Pixels either side of an outline pixel that [`pooled_along_outline`] fits, at most.
pub const OUTLINE_RADIUS_PX: f64 = 3.0;

/// How far a straight edge's share departs from the plane [`pooled_along_outline`] fits
/// (a standard deviation added to each pixel's own): the share of a pixel an edge cuts is
/// linear in the edge's offset only away from the pixel's corners.
const OUTLINE_MODEL_SIGMA: f64 = 0.15;

/// Each outline pixel's share, pooled where its own does not decide which side of its
/// centre the outline passes ([`Coverage::decided`]). A layer's edge is straight over a few
/// pixels, and the share a straight edge covers is about one half plus the centre's signed
/// distance to it (pixels), so the shares of the outline pixels within
/// [`OUTLINE_RADIUS_PX`] fit a plane `c - 1/2 = a dx + b dy + g` (weights `1 / sigma^2`,
/// the slopes held near 0 by a unit prior so that a short or straight run still fits),
/// and `1/2 + g` with its standard deviation is the pixel's pooled share. A faint layer
/// (ξ near 1) dims the background so little that one pixel's share is a coin's toss where
/// a run of them is not. `band` is one layer's outline; the result is in its order.
pub fn pooled_along_outline(band: &[OutlinePixel]) -> Vec<Coverage> {
    // The band by row, so that each pixel looks only at the rows within the radius.
    let mut by_row: Vec<OutlinePixel> = band.to_vec();
    by_row.sort_by(|a, b| a.y.total_cmp(&b.y));
    band.iter()
        .map(|p| {
            if p.coverage.decided() {
                return p.coverage;
            }
            let first = by_row.partition_point(|q| q.y < p.y - OUTLINE_RADIUS_PX);
            let last = by_row.partition_point(|q| q.y <= p.y + OUTLINE_RADIUS_PX);
            plane_at(p, &by_row[first..last]).unwrap_or(p.coverage)
        })
        .collect()
}

/// The plane of [`pooled_along_outline`] about `p`: its value and standard deviation there.
fn plane_at(p: &OutlinePixel, band: &[OutlinePixel]) -> Option<Coverage> {
    let mut normal = nalgebra::Matrix3::<f64>::zeros();
    let mut rhs = nalgebra::Vector3::<f64>::zeros();
    for q in band {
        let (dx, dy) = (q.x - p.x, q.y - p.y);
        let c = q.coverage;
        if dx.abs().max(dy.abs()) > OUTLINE_RADIUS_PX || !(c.share.is_finite() && c.share_sigma.is_finite()) {
            continue;
        }
        let w = 1.0 / (c.share_sigma.powi(2) + OUTLINE_MODEL_SIGMA.powi(2));
        let row = nalgebra::Vector3::new(dx, dy, 1.0);
        normal += w * row * row.transpose();
        rhs += w * (c.share - 0.5) * row;
    }
    normal[(0, 0)] += 1.0;
    normal[(1, 1)] += 1.0;
    let inverse = normal.try_inverse()?;
    let g = (inverse * rhs)[2];
    let variance = inverse[(2, 2)];
    (variance > 0.0 && g.is_finite()).then(|| Coverage {
        share: 0.5 + g,
        share_sigma: variance.sqrt(),
    })
}

/// The noise of one pixel's reading: its distance's and its IR's standard deviations.
#[derive(Debug, Clone, Copy)]
pub struct ReadingNoise {
    /// σ of the reading, mm.
    pub distance_mm: f64,
    /// σ of the IR value, counts.
    pub ir: f64,
}

/// A complex number as `(re, im)`.
type C = (f64, f64);

/// The phasor of a set of returns (the sinusoid's bucket pair, the amplitude IR's length).
fn phasor(model: &ForwardModel, returns: &[Return]) -> C {
    returns.iter().fold((0.0, 0.0), |(re, im), r| {
        let (s, c) = model.sensor.phase(r.distance_mm).sin_cos();
        (re + r.strength * c, im + r.strength * s)
    })
}

/// One return's phasor from a reading and its IR (less the model's IR offset).
fn reading_phasor(model: &ForwardModel, distance_mm: f64, ir: f64) -> C {
    let amplitude = ir - model.options.ambient_offset;
    let (s, c) = model.sensor.phase(distance_mm).sin_cos();
    (amplitude * c, amplitude * s)
}

/// The share of pixel `obs` that a layer of `xi` at ray distance `df` covers, from
/// `M - B = c (P0 - B) + (c X) P1` (the module's doc), with `c X >= 0`. `None` where the
/// model's reading is not a phasor (a square-wave sensor, IR as the sum of the returns, a
/// depth engine),
/// the inputs are not finite, or the layer's return and the background's are parallel
/// (the layer a whole number of ranges before the background: `c` and `X` trade).
pub fn layer_coverage(
    model: &ForwardModel,
    obs: &PixelObservation,
    df: f64,
    xi: f64,
    noise: ReadingNoise,
) -> Option<Coverage> {
    let engine = model.sensor.depth_engine().is_some();
    if model.sensor.waveform != Waveform::Sinusoid || model.options.ir_mode != IrMode::Amplitude || engine {
        return None;
    }
    let at = |x: f64| {
        let (r, n) = super::inversion::returns_at_albedo(model, obs, df, xi, x);
        phasor(model, &r[..n])
    };
    let (p0, p_one) = (at(0.0), at(1.0));
    let p1 = (p_one.0 - p0.0, p_one.1 - p0.1);
    let m = reading_phasor(model, obs.distance_mm, obs.ir);
    let b = reading_phasor(model, obs.background_distance_mm, obs.background_ir);
    let (v, y) = ((p0.0 - b.0, p0.1 - b.1), (m.0 - b.0, m.1 - b.1));
    let det = v.0 * p1.1 - v.1 * p1.0;
    // c's gradient with respect to M: Cramer's rule, or with c X = 0 the projection on v.
    let mut g = (p1.1 / det, -p1.0 / det);
    let cx = (v.0 * y.1 - v.1 * y.0) / det;
    if !(det.abs() > 1e-12 * v.0.hypot(v.1) * p1.0.hypot(p1.1)) || cx < 0.0 {
        let vv = v.0 * v.0 + v.1 * v.1;
        g = (v.0 / vv, v.1 / vv);
    }
    let share = g.0 * y.0 + g.1 * y.1;
    // M's noise: along M (the IR's) and across it (the reading's, as phase times length).
    let len = m.0.hypot(m.1);
    let (r, t) = ((m.0 / len, m.1 / len), (-m.1 / len, m.0 / len));
    let across = len * model.sensor.phase(noise.distance_mm);
    let share_sigma = ((g.0 * r.0 + g.1 * r.1) * noise.ir).hypot((g.0 * t.0 + g.1 * t.1) * across);
    (share.is_finite() && share_sigma.is_finite()).then_some(Coverage { share, share_sigma })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::model::MAX_BOUNCES;
    use crate::physics::{LayerScene, Sensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    const LIN: f64 = 4e10;

    /// A pixel a share `c` of which a layer covers, as the one forward model makes it.
    fn mixed(model: &ForwardModel, df: f64, db: f64, xi: f64, x: f64, c: f64) -> PixelObservation {
        let s = LayerScene {
            foreground_distance_mm: df,
            background_distance_mm: db,
            translucency: xi,
            foreground_albedo_cos: x,
            background_albedo_cos: 0.8,
            emitted_light: LIN,
            wall_view_factor: 0.0,
            diffuse_lobe: None,
        };
        let mut r = [Return::default(); MAX_BOUNCES];
        let n = model.layer_returns(&s, &mut r);
        let behind = ForwardModel::opaque_return(db, 0.8, LIN);
        let mut all: Vec<Return> = r[..n]
            .iter()
            .map(|r| Return {
                strength: c * r.strength,
                ..*r
            })
            .collect();
        all.push(Return {
            strength: (1.0 - c) * behind.strength,
            ..behind
        });
        let (m, b) = (model.measure(&all), model.measure(&[behind]));
        PixelObservation {
            distance_mm: m.distance_mm,
            ir: m.ir,
            background_distance_mm: b.distance_mm,
            background_ir: b.ir,
            emitted_light: LIN,
            wall_view_factor: 0.0,
            diffuse_lobe: None,
        }
    }

    #[test]
    fn the_covered_share_of_the_forward_models_mixed_pixels_comes_back() {
        let model = ForwardModel::physical(Sensor::new(30e6, Waveform::Sinusoid));
        let quiet = ReadingNoise {
            distance_mm: 1.0,
            ir: 1.0,
        };
        for (df, db) in [(1500.0, 3000.0), (2250.0, 3150.0), (900.0, 1400.0)] {
            for xi in [0.4, 0.75, 0.93] {
                for c in [0.0, 0.2, 0.5, 0.8, 1.0] {
                    let o = mixed(&model, df, db, xi, 0.6, c);
                    let got = layer_coverage(&model, &o, df, xi, quiet).expect("coverage");
                    assert!((got.share - c).abs() < 1e-6, "{df} {db} {xi} {c}: {got:?}");
                }
            }
        }
    }

    #[test]
    fn its_sigma_holds_the_share_under_the_readings_noise() {
        let model = ForwardModel::physical(Sensor::new(30e6, Waveform::Sinusoid));
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        let (mut inside, mut draws) = (0, 0);
        for xi in [0.5, 0.93] {
            for c in [0.3, 0.7] {
                let clean = mixed(&model, 2250.0, 3150.0, xi, 0.6, c);
                // Noise as a ToF pixel's: the reading's and the IR's, independent.
                let noise = ReadingNoise {
                    distance_mm: 15.0,
                    ir: 0.01 * clean.ir,
                };
                for _ in 0..400 {
                    let mut o = clean;
                    o.distance_mm += noise.distance_mm * rng.sample::<f64, _>(StandardNormal);
                    o.ir += noise.ir * rng.sample::<f64, _>(StandardNormal);
                    let got = layer_coverage(&model, &o, 2250.0, xi, noise).expect("coverage");
                    inside += usize::from((got.share - c).abs() <= 1.96 * got.share_sigma);
                    draws += 1;
                }
            }
        }
        let share = inside as f64 / draws as f64;
        println!("covered share: {inside} of {draws} draws within 1.96 sigma ({share:.3})");
        assert!((0.93..=0.97).contains(&share), "{share}");
    }

    #[test]
    fn the_share_from_the_background_left_and_the_floor_where_a_half_is_possible() {
        // A layer of ξ 0.8 dims what it covers to 0.64: a pixel three quarters covered keeps 0.73.
        let c = Coverage::from_background_share(1.0 - 0.75 * 0.36, 0.01, 0.8).expect("share");
        assert!((c.share - 0.75).abs() < 1e-12 && (c.share_sigma - 0.01 / 0.36).abs() < 1e-12);
        assert!(c.centre_covered());
        assert_eq!(c.sigma_floor_mm(900.0), 0.0);
        // Its interval holds a half: the floor is half the gap.
        let loose = Coverage {
            share: 0.6,
            share_sigma: 0.1,
        };
        assert_eq!(loose.sigma_floor_mm(-900.0), 450.0);
        assert!(!Coverage {
            share: 0.4,
            share_sigma: 0.01
        }
        .centre_covered());
        // A layer that dims nothing says nothing of the share.
        assert_eq!(Coverage::from_background_share(0.9, 0.01, 1.0), None);
    }

    #[test]
    fn a_model_whose_reading_is_no_phasor_gives_none() {
        let model = ForwardModel::paper(Sensor::new(30e6, Waveform::Sinusoid));
        let o = mixed(&model, 1500.0, 3000.0, 0.5, 0.6, 0.5);
        let quiet = ReadingNoise {
            distance_mm: 1.0,
            ir: 1.0,
        };
        assert_eq!(layer_coverage(&model, &o, 1500.0, 0.5, quiet), None);
    }

    /// The share of the unit pixel about `(x, y)` on the near side of the line
    /// `n . p = offset` (`n . p >= offset` covered), by 64 x 64 sub-samples.
    fn share_of(x: f64, y: f64, n: (f64, f64), offset: f64) -> f64 {
        let steps = 64;
        let inside = (0..steps * steps)
            .filter(|k| {
                let (u, v) = ((k % steps) as f64 + 0.5, (k / steps) as f64 + 0.5);
                let (px, py) = (x - 0.5 + u / steps as f64, y - 0.5 + v / steps as f64);
                n.0 * px + n.1 * py >= offset
            })
            .count();
        inside as f64 / (steps * steps) as f64
    }

    /// Straight edges at seeded angles and offsets through a field of pixels, each pixel's
    /// share drawn with a standard deviation of 0.15 (a faint layer's): pooled along the
    /// outline, which side of its centre the edge passes is called right more often than
    /// from the pixel's own share (beyond chance), and 95 % of the calls it says are
    /// decided are right.
    #[test]
    fn shares_pooled_along_a_straight_outline_call_the_centres_right() {
        let mut rng = ChaCha8Rng::seed_from_u64(37);
        let (mut own_wrong, mut pooled_wrong, mut decided_wrong, mut decided, mut pixels) = (0, 0, 0, 0, 0);
        // Pixels only the pooled call gets right, and only the pixel's own.
        let (mut only_pooled, mut only_own) = (0, 0);
        for _ in 0..40 {
            let angle: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            let n = (angle.cos(), angle.sin());
            let offset: f64 = rng.random_range(-0.5..0.5);
            // The band: pixels within a pixel and a half of the edge, in a 21 x 21 field.
            let band: Vec<(OutlinePixel, bool)> = (-10..=10)
                .flat_map(|y| (-10..=10).map(move |x| (x as f64, y as f64)))
                .filter(|&(x, y)| (n.0 * x + n.1 * y - offset).abs() <= 1.5)
                .map(|(x, y)| {
                    let c = share_of(x, y, n, offset) + 0.15 * rng.sample::<f64, _>(StandardNormal);
                    let coverage = Coverage {
                        share: c,
                        share_sigma: 0.15,
                    };
                    (OutlinePixel { x, y, coverage }, n.0 * x + n.1 * y >= offset)
                })
                .collect();
            let at: Vec<OutlinePixel> = band.iter().map(|b| b.0).collect();
            for ((p, centre), pooled) in band.iter().zip(pooled_along_outline(&at)) {
                // Pixels the edge passes within a quarter pixel of the centre: the hard ones.
                if (n.0 * p.x + n.1 * p.y - offset).abs() > 0.25 {
                    continue;
                }
                pixels += 1;
                let (own_right, pooled_right) = (
                    p.coverage.centre_covered() == *centre,
                    pooled.centre_covered() == *centre,
                );
                own_wrong += usize::from(!own_right);
                pooled_wrong += usize::from(!pooled_right);
                only_pooled += usize::from(pooled_right && !own_right);
                only_own += usize::from(own_right && !pooled_right);
                if pooled.decided() {
                    decided += 1;
                    decided_wrong += usize::from(pooled.centre_covered() != *centre);
                }
            }
        }
        println!(
            "{pixels} pixels within a quarter pixel of the edge: own share wrong at {own_wrong}, pooled at \
             {pooled_wrong}; {decided} decided, {decided_wrong} of them wrong"
        );
        assert!(pixels > 200, "{pixels}");
        // McNemar's test: pooling is better beyond two standard deviations of chance.
        let (b, c) = (only_pooled as f64, only_own as f64);
        assert!(b - c > 2.0 * (b + c).sqrt(), "right only pooled {b}, only own {c}");
        assert!(
            decided_wrong * 20 <= decided.max(1),
            "{decided_wrong} of {decided} decided calls wrong"
        );
    }
}
