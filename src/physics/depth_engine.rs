//! A multi-frequency camera's depth engine (issue 51): what a camera that
//! measures at several modulation frequencies hands its driver as one depth
//! image and one IR image.
//!
//! At each frequency `f_k` (unambiguous range `R_k = c / (2 f_k)`) the pixel's
//! returns mix into one phasor (Eq. 5 at `f_k`), which the waveform's decoder
//! turns into a wrapped distance `d_k` in `[0, R_k)`. The engine unwraps them
//! together within its own unambiguous range `R = c / (2 gcd f_k)`: a wrap
//! hypothesis `n = (n_1, ..., n_K)` gives the unwrapped distances
//! `D_k = d_k + n_k R_k`, and the engine keeps the hypothesis that minimises
//! their weighted disagreement
//!
//! ```text
//! E(n) = sum_k w_k (D_k - D)^2,   D = sum_k w_k D_k / sum_k w_k,
//! ```
//!
//! reports `D` (modulo `R`) as the depth and invalidates the pixel (no depth)
//! when the disagreement `sqrt(E / sum_k w_k)` exceeds its threshold. The IR
//! image is one frequency's demodulated amplitude or their mean.
//!
//! For one return every `d_k` is the same distance and some hypothesis makes
//! them agree exactly. A layer and the wall behind it mix at a different
//! angle at each frequency: the `d_k` disagree, and the depth is then no
//! single frequency's reading; it jumps where the best hypothesis changes.
//!
//! The minimum is found exactly, not by trying every hypothesis: `E` is
//! `min over D of sum_k w_k dist_k(D, d_k)^2`, with `dist_k` the distance to
//! the nearest `d_k + n R_k`. Between the points where one frequency's nearest
//! wrap changes (`d_k + (n + 1/2) R_k`, `sum_k R / R_k` of them around the
//! circle of length `R`) the wraps are fixed, so each such arc gives one
//! hypothesis, and the best of them is the best of all.

use std::f64::consts::TAU;

use serde::{Deserialize, Serialize};

use super::model::Return;
use super::sensor::{Buckets, Sensor, SPEED_OF_LIGHT_MM_PER_S};

/// Most frequencies an engine takes.
pub const MAX_ENGINE_FREQUENCIES: usize = 8;

/// Most wrap points around the engine's range (`sum_k R / R_k`): frequencies
/// whose greatest common divisor is too small for the scene make the range,
/// and the search, needlessly long.
pub const MAX_WRAP_POINTS: usize = 4096;

/// An engine the model cannot use.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DepthEngineError {
    /// Fewer than two frequencies, or more than [`MAX_ENGINE_FREQUENCIES`].
    #[error("a depth engine takes 2 to {MAX_ENGINE_FREQUENCIES} frequencies, got {0}")]
    FrequencyCount(usize),
    /// A frequency that is not a positive, finite number of hertz.
    #[error("depth engine frequency {0} Hz is not positive and finite")]
    BadFrequency(f64),
    /// Weights of the wrong length or not positive.
    #[error("depth engine weights: {0}")]
    BadWeights(String),
    /// A threshold that is not positive.
    #[error("depth engine max_disagreement_mm = {0} is not positive")]
    BadThreshold(f64),
    /// An IR frequency index past the frequencies.
    #[error("depth engine ir_frequency_index = {index} with {count} frequencies")]
    BadIrIndex {
        /// The index given.
        index: usize,
        /// How many frequencies there are.
        count: usize,
    },
    /// The frequencies' common range holds too many wraps.
    #[error("the depth engine's frequencies share a range of {range_mm:.0} mm holding {points} wraps (at most {MAX_WRAP_POINTS}): choose frequencies with a larger common divisor")]
    TooManyWraps {
        /// The common unambiguous range, mm.
        range_mm: f64,
        /// Wrap points around it.
        points: usize,
    },
    /// A named engine that is not a preset.
    #[error("depth engine {0:?}: the presets are kinect_v2")]
    UnknownPreset(String),
}

/// A depth engine's parameters: what a user copies from the camera's
/// documentation (a physics file's `[depth_engine]` table).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthEngine {
    /// The modulation frequencies, Hz (2 to [`MAX_ENGINE_FREQUENCIES`]).
    pub frequencies_hz: Vec<f64>,
    /// Each frequency's weight `w_k` in the disagreement and the mean (empty:
    /// `f_k^2`, the least-squares weights for the same phase noise at every
    /// frequency, under which `E` is the phase residuals' sum of squares).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub weights: Vec<f64>,
    /// The largest disagreement `sqrt(E / sum w)` a valid pixel has, mm;
    /// beyond it the pixel is invalid (depth 0). `None`: never invalid.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_disagreement_mm: Option<f64>,
    /// Which amplitude is the IR image: frequency `k`'s, or (`None`) the mean
    /// of every frequency's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ir_frequency_index: Option<usize>,
}

/// libfreenect2's `max_dealias_confidence` (0.6108653 rad, 35 degrees): the
/// largest norm of the phase residuals of a pixel it keeps.
const KINECT_V2_MAX_PHASE_RESIDUAL_RAD: f64 = 0.610_865_3;

impl DepthEngine {
    /// An engine at `frequencies_hz` with the default weights, no
    /// invalidation and the mean amplitude as the IR.
    pub fn at(frequencies_hz: &[f64]) -> Result<Self, DepthEngineError> {
        let e = Self {
            frequencies_hz: frequencies_hz.to_vec(),
            weights: vec![],
            max_disagreement_mm: None,
            ir_frequency_index: None,
        };
        e.check()?;
        Ok(e)
    }

    /// The Kinect v2 (Xbox One) depth engine from its openly published
    /// parameters, as the libfreenect2 project documents them
    /// (<https://github.com/OpenKinect/libfreenect2>, `depth_packet_processor.cpp`
    /// and `cpu_depth_packet_processor.cpp`):
    /// - three modulation frequencies, 80, 16 and 120 MHz, in the order the
    ///   sensor's packets carry them (common range `c / (2 * 8 MHz)` = 18.7 m);
    /// - the IR image is the mean of the three frequencies' amplitudes;
    /// - a pixel is invalid where the unwrapped phases disagree by more than
    ///   `max_dealias_confidence` = 0.6108653 rad, taken here as the norm of the
    ///   phase residuals `2 pi (D_k - D) / R_k`; with the weights `f_k^2` that is
    ///   a disagreement of [`Self::kinect_v2_max_disagreement_mm`] (100.4 mm).
    ///
    /// libfreenect2 also invalidates by amplitude (its thresholds on each
    /// frequency's amplitude and their sum) and by depth range (0.5-4.5 m), and
    /// filters across neighbouring pixels; none of those is modelled here.
    pub fn kinect_v2() -> Self {
        Self {
            frequencies_hz: vec![80.0e6, 16.0e6, 120.0e6],
            weights: vec![],
            max_disagreement_mm: Some(Self::kinect_v2_max_disagreement_mm()),
            ir_frequency_index: None,
        }
    }

    /// libfreenect2's phase threshold as a disagreement in mm under the
    /// weights `f_k^2`: `sum_k (2 pi (D_k - D) / R_k)^2 = (4 pi / c)^2 sum_k f_k^2
    /// (D_k - D)^2`, so a phase norm `theta` is `theta c / (4 pi sqrt(sum f_k^2))`.
    pub fn kinect_v2_max_disagreement_mm() -> f64 {
        let sum_f2: f64 = [80.0e6f64, 16.0e6, 120.0e6].iter().map(|f| f * f).sum();
        KINECT_V2_MAX_PHASE_RESIDUAL_RAD * SPEED_OF_LIGHT_MM_PER_S / (2.0 * TAU * sum_f2.sqrt())
    }

    /// A preset by name (`kinect_v2`).
    pub fn preset(name: &str) -> Result<Self, DepthEngineError> {
        match name {
            "kinect_v2" => Ok(Self::kinect_v2()),
            other => Err(DepthEngineError::UnknownPreset(other.to_string())),
        }
    }

    /// Checks the parameters (what [`Sensor::with_depth_engine`] refuses).
    pub fn check(&self) -> Result<(), DepthEngineError> {
        self.prepare().map(|_| ())
    }

    /// The engine with its ranges, weights and common range worked out.
    pub(crate) fn prepare(&self) -> Result<PreparedEngine, DepthEngineError> {
        let f = &self.frequencies_hz;
        if !(2..=MAX_ENGINE_FREQUENCIES).contains(&f.len()) {
            return Err(DepthEngineError::FrequencyCount(f.len()));
        }
        if let Some(&bad) = f.iter().find(|f| !(f.is_finite() && **f > 0.0)) {
            return Err(DepthEngineError::BadFrequency(bad));
        }
        let weights: Vec<f64> = if self.weights.is_empty() {
            f.iter().map(|f| (f / 1e6) * (f / 1e6)).collect()
        } else if self.weights.len() != f.len() {
            return Err(DepthEngineError::BadWeights(format!(
                "{} weights for {} frequencies",
                self.weights.len(),
                f.len()
            )));
        } else {
            self.weights.clone()
        };
        if weights.iter().any(|w| !(w.is_finite() && *w > 0.0)) {
            return Err(DepthEngineError::BadWeights(format!(
                "{weights:?} are not all positive"
            )));
        }
        if let Some(t) = self.max_disagreement_mm.filter(|t| !(*t > 0.0)) {
            return Err(DepthEngineError::BadThreshold(t));
        }
        if let Some(index) = self.ir_frequency_index.filter(|i| *i >= f.len()) {
            return Err(DepthEngineError::BadIrIndex { index, count: f.len() });
        }
        let hertz: Vec<u64> = f.iter().map(|f| (f.round() as u64).max(1)).collect();
        let g = hertz.iter().fold(0, |a, &b| gcd(a, b));
        let range_mm = SPEED_OF_LIGHT_MM_PER_S / (2.0 * g as f64);
        let points: u64 = hertz.iter().map(|h| h / g).sum();
        if points > MAX_WRAP_POINTS as u64 {
            return Err(DepthEngineError::TooManyWraps {
                range_mm,
                points: points as usize,
            });
        }
        let total: f64 = weights.iter().sum();
        Ok(PreparedEngine {
            ranges_mm: f.iter().map(|f| SPEED_OF_LIGHT_MM_PER_S / (2.0 * f)).collect(),
            wraps: hertz.iter().map(|h| (h / g) as usize).collect(),
            weights: weights.iter().map(|w| w / total).collect(),
            range_mm,
            engine: self.clone(),
        })
    }
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// A checked engine with what every reading needs.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PreparedEngine {
    /// The parameters.
    pub engine: DepthEngine,
    /// `R_k`, mm.
    ranges_mm: Vec<f64>,
    /// `R / R_k`: each frequency's wraps in the engine's range.
    wraps: Vec<usize>,
    /// `w_k / sum w`.
    weights: Vec<f64>,
    /// `R = c / (2 gcd f_k)`, mm.
    pub range_mm: f64,
}

/// The phasors of a pixel at an engine's frequencies.
pub type EnginePhasors = [Buckets; MAX_ENGINE_FREQUENCIES];

/// What the engine makes of one pixel's phasors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EngineReading {
    /// The depth (ray distance) in `[0, R)`, mm; NaN where the engine
    /// invalidates the pixel (no light at a frequency, or a disagreement past
    /// the threshold).
    pub distance_mm: f64,
    /// `sqrt(E / sum w)` of the hypothesis kept, mm (NaN without light).
    pub disagreement_mm: f64,
    /// The IR image's amplitude (one frequency's or the mean), counts.
    pub ir_amplitude: f64,
    /// The wrap count `n_k` of each frequency in the hypothesis kept, relative
    /// to the depth's own period (the first `K` entries).
    pub wraps: [i64; MAX_ENGINE_FREQUENCIES],
}

impl PreparedEngine {
    /// The number of frequencies `K`.
    pub fn len(&self) -> usize {
        self.ranges_mm.len()
    }

    /// Which frequency's amplitude is the IR (`None`: the mean).
    pub fn ir_frequency_index(&self) -> Option<usize> {
        self.engine.ir_frequency_index
    }

    /// The noise-free phasor of `returns` at each frequency (Eq. 5 at `f_k`),
    /// with `sensor`'s correlation waveform; the first `K` entries.
    pub fn phasors(&self, sensor: &Sensor, returns: &[Return]) -> EnginePhasors {
        let mut out = [Buckets::default(); MAX_ENGINE_FREQUENCIES];
        for (p, r_k) in out.iter_mut().zip(&self.ranges_mm) {
            for r in returns {
                *p += sensor.buckets_at_phase(r.strength, TAU * r.distance_mm / r_k);
            }
        }
        out
    }

    /// The IR amplitude of a set of phasors: one frequency's length or the mean.
    pub fn ir_amplitude(&self, phasors: &[Buckets]) -> f64 {
        let len = |b: &Buckets| b.a.hypot(b.b);
        match self.engine.ir_frequency_index {
            Some(k) => phasors.get(k).map_or(0.0, len),
            None => phasors.iter().take(self.len()).map(len).sum::<f64>() / self.len() as f64,
        }
    }

    /// The engine's depth and IR from the phasors at its frequencies (noisy or
    /// not), the phases decoded with `sensor`'s waveform.
    pub fn read(&self, sensor: &Sensor, phasors: &[Buckets]) -> EngineReading {
        let ir_amplitude = self.ir_amplitude(phasors);
        let none = EngineReading {
            distance_mm: f64::NAN,
            disagreement_mm: f64::NAN,
            ir_amplitude,
            wraps: [0; MAX_ENGINE_FREQUENCIES],
        };
        let mut wrapped = [0.0; MAX_ENGINE_FREQUENCIES];
        for ((d, b), r_k) in wrapped.iter_mut().zip(phasors).zip(&self.ranges_mm) {
            match sensor.decode_phase(*b) {
                Some(phi) => *d = phi / TAU * r_k,
                None => return none,
            }
        }
        let Some((mean, cost)) = self.unwrap(&wrapped[..self.len()]) else {
            return none;
        };
        let disagreement_mm = cost.sqrt();
        let valid = self.engine.max_disagreement_mm.is_none_or(|t| disagreement_mm <= t);
        let distance_mm = mean.rem_euclid(self.range_mm);
        let mut wraps = [0; MAX_ENGINE_FREQUENCIES];
        for (k, n) in wraps.iter_mut().enumerate().take(self.len()) {
            *n = ((distance_mm - wrapped[k]) / self.ranges_mm[k]).round() as i64;
        }
        EngineReading {
            distance_mm: if valid { distance_mm } else { f64::NAN },
            disagreement_mm,
            ir_amplitude,
            wraps,
        }
    }

    /// The hypothesis of least weighted disagreement for the wrapped distances
    /// `d_k`: its weighted mean `D` (not reduced modulo `R`) and `E / sum w`.
    fn unwrap(&self, wrapped: &[f64]) -> Option<(f64, f64)> {
        let r = self.range_mm;
        // Where each frequency's nearest wrap changes, around the circle [0, R).
        let mut points: Vec<f64> = Vec::with_capacity(self.wraps.iter().sum());
        for ((d, r_k), n_k) in wrapped.iter().zip(&self.ranges_mm).zip(&self.wraps) {
            points.extend((0..*n_k).map(|n| (d + (n as f64 + 0.5) * r_k).rem_euclid(r)));
        }
        points.sort_by(f64::total_cmp);
        let mut best: Option<(f64, f64)> = None;
        for (i, &a) in points.iter().enumerate() {
            let b = points.get(i + 1).copied().unwrap_or(points[0] + r);
            let mid = 0.5 * (a + b);
            let hypothesis = |k: usize| {
                let (d, r_k) = (wrapped[k], self.ranges_mm[k]);
                d + r_k * ((mid - d) / r_k).round()
            };
            let mean: f64 = (0..self.len()).map(|k| self.weights[k] * hypothesis(k)).sum();
            let cost: f64 = (0..self.len())
                .map(|k| self.weights[k] * (hypothesis(k) - mean).powi(2))
                .sum();
            if best.is_none_or(|(_, c)| cost < c) {
                best = Some((mean, cost));
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::model::ForwardModel;
    use crate::physics::sensor::Waveform;

    fn engine(frequencies: &[f64]) -> PreparedEngine {
        DepthEngine::at(frequencies).unwrap().prepare().unwrap()
    }

    fn reading(e: &PreparedEngine, sensor: &Sensor, returns: &[Return]) -> EngineReading {
        let p = e.phasors(sensor, returns);
        e.read(sensor, &p[..e.len()])
    }

    fn one(distance_mm: f64) -> Return {
        Return {
            strength: 100.0,
            distance_mm,
        }
    }

    #[test]
    fn kinect_v2_shares_8_mhz_and_its_threshold_is_100_mm() {
        let e = DepthEngine::kinect_v2().prepare().unwrap();
        assert!((e.range_mm - 18_737.0).abs() < 1.0, "{}", e.range_mm);
        assert_eq!(e.wraps, vec![10, 2, 15]);
        let t = DepthEngine::kinect_v2_max_disagreement_mm();
        assert!((t - 100.4).abs() < 0.1, "{t}");
    }

    #[test]
    fn a_single_return_reads_its_distance_up_to_the_unambiguous_range() {
        for waveform in [Waveform::Sinusoid, Waveform::Triangle] {
            let sensor = Sensor::new(30e6, waveform);
            for freqs in [vec![80e6, 16e6, 120e6], vec![20e6, 50e6, 100e6], vec![20e6, 100e6]] {
                let e = engine(&freqs);
                for i in 0..2000 {
                    let d = e.range_mm * i as f64 / 2000.0;
                    let r = reading(&e, &sensor, &[one(d)]);
                    let err = (r.distance_mm - d).abs().min(e.range_mm - (r.distance_mm - d).abs());
                    assert!(err < 1e-6, "{freqs:?} {waveform:?} d {d} read {}", r.distance_mm);
                    assert!(r.disagreement_mm < 1e-6);
                    assert!((r.ir_amplitude - 100.0).abs() < 1e-9 || waveform != Waveform::Sinusoid);
                }
            }
        }
    }

    /// The engine's depth of a layer at `df` before a wall at 2500 mm, returns as
    /// the default physics makes them.
    fn mix(e: &PreparedEngine, df: f64) -> (EngineReading, [f64; 3]) {
        let sensor = Sensor::sr4000();
        let returns = [
            ForwardModel::opaque_return(df, 0.35 * 0.6, 4e10),
            ForwardModel::opaque_return(2500.0, 0.65 * 0.65, 4e10),
        ];
        // Each frequency's own reading: the single surface its phase alone gives.
        let p = e.phasors(&sensor, &returns);
        let own = std::array::from_fn(|k| sensor.decode_phase(p[k]).unwrap_or(f64::NAN) / TAU * e.ranges_mm[k]);
        (reading(e, &sensor, &returns), own)
    }

    #[test]
    fn a_layer_before_a_wall_reads_no_single_frequencys_depth_and_jumps_where_the_wraps_change() {
        let e = engine(&[80e6, 16e6, 120e6]);
        let mut jumps = 0;
        let mut apart = 0;
        let mut prev: Option<EngineReading> = None;
        for i in 0..=1400 {
            let df = 600.0 + i as f64;
            let (r, own) = mix(&e, df);
            assert!(r.distance_mm.is_finite(), "no threshold: always valid");
            // No frequency's own phase (at any of its wraps) gives the engine's depth.
            let nearest = (0..3)
                .map(|k| {
                    let d = r.distance_mm - own[k];
                    (d - e.ranges_mm[k] * (d / e.ranges_mm[k]).round()).abs()
                })
                .fold(f64::INFINITY, f64::min);
            if nearest > 5.0 {
                apart += 1;
            }
            if let Some(p) = prev {
                let step = (r.distance_mm - p.distance_mm).abs();
                if step > 30.0 {
                    jumps += 1;
                    assert_ne!(r.wraps[..3], p.wraps[..3], "a jump at {df} without a new hypothesis");
                }
            }
            prev = Some(r);
        }
        assert!(
            apart > 1000,
            "the engine's depth is a single frequency's at {} of 1401",
            1401 - apart
        );
        assert!(jumps >= 1, "the depth never jumps");
    }

    #[test]
    fn the_threshold_invalidates_large_disagreements_only() {
        let mut strict = DepthEngine::at(&[80e6, 16e6, 120e6]).unwrap();
        strict.max_disagreement_mm = Some(20.0);
        let strict = strict.prepare().unwrap();
        let free = engine(&[80e6, 16e6, 120e6]);
        let (mut kept, mut dropped) = (0, 0);
        for i in 0..=140 {
            let df = 600.0 + 10.0 * i as f64;
            let (r, _) = mix(&free, df);
            let (s, _) = mix(&strict, df);
            if r.disagreement_mm > 20.0 {
                assert!(
                    s.distance_mm.is_nan(),
                    "kept a disagreement of {} mm",
                    r.disagreement_mm
                );
                dropped += 1;
            } else {
                assert_eq!(s.distance_mm, r.distance_mm);
                kept += 1;
            }
        }
        assert!(kept > 0 && dropped > 0, "kept {kept} dropped {dropped}");
        // A single return is never invalid.
        let sensor = Sensor::sr4000();
        assert!(reading(&strict, &sensor, &[one(1234.0)]).distance_mm.is_finite());
    }

    #[test]
    fn no_light_is_no_depth_and_bad_parameters_are_refused() {
        let e = engine(&[20e6, 100e6]);
        assert!(reading(&e, &Sensor::sr4000(), &[]).distance_mm.is_nan());
        assert!(matches!(
            DepthEngine::at(&[20e6]),
            Err(DepthEngineError::FrequencyCount(1))
        ));
        assert!(DepthEngine::at(&[20e6, -1.0]).is_err());
        assert!(DepthEngine::at(&[20_000_001.0, 100e6]).is_err(), "a 1 Hz divisor");
        let mut w = DepthEngine::at(&[20e6, 100e6]).unwrap();
        w.weights = vec![1.0];
        assert!(w.check().is_err());
        w.weights = vec![];
        w.ir_frequency_index = Some(2);
        assert!(w.check().is_err());
        assert!(DepthEngine::preset("kinect_v2").unwrap().check().is_ok());
        assert!(DepthEngine::preset("kinect").is_err());
    }

    #[test]
    fn the_ir_is_the_named_amplitude() {
        let mut e = DepthEngine::at(&[20e6, 100e6]).unwrap();
        let sensor = Sensor::sr4000();
        let returns = [one(1000.0), one(1500.0)];
        let mean = reading(&e.prepare().unwrap(), &sensor, &returns).ir_amplitude;
        e.ir_frequency_index = Some(0);
        let p = e.prepare().unwrap();
        let first = reading(&p, &sensor, &returns).ir_amplitude;
        let ph = p.phasors(&sensor, &returns);
        assert!((first - ph[0].a.hypot(ph[0].b)).abs() < 1e-9);
        assert!((mean - 0.5 * (ph[0].a.hypot(ph[0].b) + ph[1].a.hypot(ph[1].b))).abs() < 1e-9);
    }
}
