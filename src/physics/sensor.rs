//! The continuous-wave ToF sensor: modulation, 4-bucket correlation and the
//! device's decoder (paper Sec. III, Eq. 4-6; physics.md §2).

use std::f64::consts::{PI, TAU};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::depth_engine::{DepthEngine, DepthEngineError, PreparedEngine};

/// Speed of light in millimetres per second.
pub const SPEED_OF_LIGHT_MM_PER_S: f64 = 299_792_458_000.0;

/// Shape of the correlation between the emitted signal and the bucket windows.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Waveform {
    /// Sinusoidal correlation `cos(phi)` (most devices).
    #[default]
    Sinusoid,
    /// Square emission with square windows: triangular correlation (paper Fig. 2).
    Triangle,
    /// `cos(phi) + third cos(3 phi) + fifth cos(5 phi)`: a sinusoid with
    /// harmonic content (a square-ish drive that the optics did not filter).
    Harmonics {
        /// Relative amplitude of the 3rd harmonic.
        third: f64,
        /// Relative amplitude of the 5th harmonic.
        fifth: f64,
    },
}

impl Waveform {
    /// The correlation waveform at phase `phi` (radians), peak 1 at `phi = 0`.
    pub fn correlation(&self, phi: f64) -> f64 {
        match *self {
            Waveform::Sinusoid => phi.cos(),
            Waveform::Triangle => {
                let p = wrap_phase(phi).abs();
                1.0 - 2.0 * p / PI
            }
            Waveform::Harmonics { third, fifth } => phi.cos() + third * (3.0 * phi).cos() + fifth * (5.0 * phi).cos(),
        }
    }
}

/// Wraps a phase into `(-pi, pi]`.
pub fn wrap_phase(phi: f64) -> f64 {
    // Already wrapped (the common case): no division.
    if phi > -PI && phi <= PI {
        return phi;
    }
    let mut p = phi.rem_euclid(TAU);
    if p > PI {
        p -= TAU;
    }
    p
}

/// The two bucket differences `(Q1 - Q2, Q3 - Q4)` of a pixel (Eq. 5).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Buckets {
    /// `Q1 - Q2`: the correlation sampled at `phi`.
    pub a: f64,
    /// `Q3 - Q4`: the correlation sampled at `phi - pi/2`.
    pub b: f64,
}

impl std::ops::AddAssign for Buckets {
    fn add_assign(&mut self, o: Self) {
        self.a += o.a;
        self.b += o.b;
    }
}

/// A continuous-wave ToF camera's measurement principle.
#[derive(Debug, Clone)]
pub struct Sensor {
    /// Modulation frequency in hertz (SR4000: 30 MHz).
    pub modulation_frequency_hz: f64,
    /// Correlation waveform.
    pub waveform: Waveform,
    range_mm: f64,
    /// For waveforms without a closed-form decoder: true phase at evenly
    /// spaced single-surface `atan2` angles over `[0, 2 pi]`.
    decode_table: Option<Arc<Vec<f64>>>,
    /// A multi-frequency camera's depth engine ([`super::depth_engine`]): the
    /// depth and IR the camera reports come from it, not from this frequency.
    depth_engine: Option<Arc<PreparedEngine>>,
}

const DECODE_TABLE_LEN: usize = 8192;

impl Sensor {
    /// A sensor at `modulation_frequency_hz` with the given waveform.
    pub fn new(modulation_frequency_hz: f64, waveform: Waveform) -> Self {
        Self::with_decode_table_len(modulation_frequency_hz, waveform, DECODE_TABLE_LEN)
    }

    /// As [`Sensor::new`] with a decoder table of `len` entries (at least 64) for
    /// harmonic waveforms: a coarser table is cheaper to build where many
    /// waveforms are tried (the audit's fits), at a decoding error that stays
    /// below half a millimetre for 512 entries (harmonics up to 0.15).
    pub fn with_decode_table_len(modulation_frequency_hz: f64, waveform: Waveform, len: usize) -> Self {
        let range_mm = SPEED_OF_LIGHT_MM_PER_S / (2.0 * modulation_frequency_hz);
        let decode_table = match waveform {
            Waveform::Harmonics { .. } => Some(Arc::new(build_decode_table(&waveform, len.max(64)))),
            _ => None,
        };
        Self {
            modulation_frequency_hz,
            waveform,
            range_mm,
            decode_table,
            depth_engine: None,
        }
    }

    /// This sensor reporting its depth and IR through `engine` (a camera that
    /// unwraps its depth from several frequencies); the waveform is the
    /// engine's at each of its frequencies.
    pub fn with_depth_engine(mut self, engine: &DepthEngine) -> Result<Self, DepthEngineError> {
        self.depth_engine = Some(Arc::new(engine.prepare()?));
        Ok(self)
    }

    /// The depth engine's parameters, if the camera has one.
    pub fn depth_engine(&self) -> Option<&DepthEngine> {
        self.depth_engine.as_deref().map(|e| &e.engine)
    }

    /// The prepared depth engine, if any.
    pub(crate) fn engine(&self) -> Option<&PreparedEngine> {
        self.depth_engine.as_deref()
    }

    /// The MESA SR4000 of the paper: 30 MHz, sinusoidal correlation.
    pub fn sr4000() -> Self {
        Self::new(30.0e6, Waveform::Sinusoid)
    }

    /// Unambiguous range of the depth the camera reports, mm: `R = c / (2 f)`,
    /// or with a depth engine its common range `c / (2 gcd f_k)`.
    pub fn unambiguous_range_mm(&self) -> f64 {
        self.engine().map_or(self.range_mm, |e| e.range_mm)
    }

    /// Phase of a return at `distance_mm`: `2 pi d / R` (not wrapped).
    pub fn phase(&self, distance_mm: f64) -> f64 {
        TAU * distance_mm / self.range_mm
    }

    /// Bucket differences of one return of `strength` at `distance_mm` (Eq. 5).
    pub fn buckets(&self, strength: f64, distance_mm: f64) -> Buckets {
        self.buckets_at_phase(strength, self.phase(distance_mm))
    }

    /// Bucket differences of one return of `strength` at phase `phi` (Eq. 5 at
    /// any frequency: the waveform's correlation sampled at `phi`, `phi - pi/2`).
    pub fn buckets_at_phase(&self, strength: f64, phi: f64) -> Buckets {
        match self.waveform {
            Waveform::Sinusoid => {
                let (s, c) = phi.sin_cos();
                Buckets {
                    a: strength * c,
                    b: strength * s,
                }
            }
            w => Buckets {
                a: strength * w.correlation(phi),
                b: strength * w.correlation(phi - PI / 2.0),
            },
        }
    }

    /// The device's decoder: the distance in `[0, R)` of the single opaque
    /// surface that gives this bucket ratio, at this sensor's own frequency.
    /// `None` when both buckets are 0.
    pub fn decode(&self, b: Buckets) -> Option<f64> {
        let phi = self.decode_phase(b)?;
        Some((phi / TAU * self.range_mm).rem_euclid(self.range_mm))
    }

    /// The decoder's phase in `[0, 2 pi)`: that of the single surface giving
    /// this bucket ratio (the same at every frequency for one waveform).
    pub fn decode_phase(&self, b: Buckets) -> Option<f64> {
        if b.a == 0.0 && b.b == 0.0 || !b.a.is_finite() || !b.b.is_finite() {
            return None;
        }
        let phi = match self.waveform {
            Waveform::Sinusoid => b.b.atan2(b.a),
            Waveform::Triangle => {
                // On a single surface |A| + |B| = strength; A = tri(phi) gives
                // |phi| = (1 - a) pi / 2 with a = A / (|A| + |B|), sign from B.
                let a = b.a / (b.a.abs() + b.b.abs());
                let mag = (1.0 - a) * PI / 2.0;
                if b.b >= 0.0 {
                    mag
                } else {
                    -mag
                }
            }
            Waveform::Harmonics { .. } => {
                let table = self.decode_table.as_ref()?;
                let psi = b.b.atan2(b.a).rem_euclid(TAU);
                let x = psi / TAU * (table.len() - 1) as f64;
                let i = (x.floor() as usize).min(table.len() - 2);
                let t = x - i as f64;
                table[i] * (1.0 - t) + table[i + 1] * t
            }
        };
        Some(phi.rem_euclid(TAU))
    }

    /// `d1 - d2` as a wrapped distance in `(-R/2, R/2]` (phases compared, not
    /// distances), `R` the reported depth's range ([`Self::unambiguous_range_mm`]).
    pub fn wrapped_difference_mm(&self, d1: f64, d2: f64) -> f64 {
        let range = self.unambiguous_range_mm();
        wrap_phase(TAU * (d1 - d2) / range) / TAU * range
    }
}

/// Inverts `phi -> atan2(corr(phi - pi/2), corr(phi))` on a fine grid so a
/// harmonic waveform decodes single surfaces exactly (to table resolution).
fn build_decode_table(w: &Waveform, len: usize) -> Vec<f64> {
    // Forward samples of the (unwrapped, monotone for modest harmonics) angle.
    let n_fwd = len * 4;
    let mut fwd = Vec::with_capacity(n_fwd + 1);
    let mut prev = 0.0;
    let mut offset = 0.0;
    for k in 0..=n_fwd {
        let phi = TAU * k as f64 / n_fwd as f64;
        let mut psi = w.correlation(phi - PI / 2.0).atan2(w.correlation(phi));
        if k == 0 {
            prev = psi;
        }
        psi += offset;
        if psi - prev < -PI {
            offset += TAU;
            psi += TAU;
        }
        prev = psi;
        fwd.push((psi, phi));
    }
    // psi(0) = 0 for every even waveform, so index 0 is psi = 0.
    let psi0 = fwd[0].0;
    let mut table = Vec::with_capacity(len);
    let mut j = 0;
    for i in 0..len {
        let target = psi0 + TAU * i as f64 / (len - 1) as f64;
        while j + 1 < fwd.len() - 1 && fwd[j + 1].0 < target {
            j += 1;
        }
        let (p0, f0) = fwd[j];
        let (p1, f1) = fwd[j + 1];
        let t = if p1 > p0 {
            ((target - p0) / (p1 - p0)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        table.push(f0 + t * (f1 - f0));
    }
    table
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sensors() -> Vec<Sensor> {
        vec![
            Sensor::sr4000(),
            Sensor::new(30e6, Waveform::Triangle),
            Sensor::new(
                30e6,
                Waveform::Harmonics {
                    third: -0.08,
                    fifth: 0.02,
                },
            ),
            Sensor::new(20e6, Waveform::Sinusoid),
        ]
    }

    #[test]
    fn sr4000_range_is_c_over_2f() {
        let r = Sensor::sr4000().unambiguous_range_mm();
        assert!((r - 4996.54).abs() < 0.01, "{r}");
    }

    #[test]
    fn single_opaque_surface_decodes_exactly_for_every_waveform() {
        for s in sensors() {
            let r = s.unambiguous_range_mm();
            for k in 0..997 {
                let d = r * k as f64 / 997.0;
                let got = s.decode(s.buckets(3.7, d)).unwrap();
                let err = s.wrapped_difference_mm(got, d).abs();
                assert!(err < 0.01, "{:?} d={d} got={got}", s.waveform);
            }
        }
    }

    #[test]
    fn triangle_correlation_matches_definition() {
        let w = Waveform::Triangle;
        assert!((w.correlation(0.0) - 1.0).abs() < 1e-12);
        assert!((w.correlation(PI / 2.0)).abs() < 1e-12);
        assert!((w.correlation(PI) + 1.0).abs() < 1e-12);
        assert!((w.correlation(-PI / 4.0) - 0.5).abs() < 1e-12);
        assert!((w.correlation(TAU + PI / 4.0) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn two_returns_read_between_them_and_wrap_past_half_range() {
        let s = Sensor::sr4000();
        // Equal returns at 1000 and 2000 mm read 1500 mm.
        let mut b = s.buckets(1.0, 1000.0);
        b += s.buckets(1.0, 2000.0);
        assert!((s.decode(b).unwrap() - 1500.0).abs() < 1e-6);
        // Layers more than R/2 apart with the far one stronger read behind it
        // (the paper's depth reversal).
        let mut b = s.buckets(0.4, 800.0);
        b += s.buckets(1.0, 3300.0);
        let d = s.decode(b).unwrap();
        assert!(d > 3300.0, "reads {d}");
    }

    #[test]
    fn wrapped_difference_is_within_half_range() {
        let s = Sensor::sr4000();
        let r = s.unambiguous_range_mm();
        assert!((s.wrapped_difference_mm(10.0, r - 10.0) - 20.0).abs() < 1e-9);
        assert!((s.wrapped_difference_mm(100.0, 50.0) - 50.0).abs() < 1e-9);
    }

    #[test]
    fn zero_buckets_do_not_decode() {
        assert!(Sensor::sr4000().decode(Buckets::default()).is_none());
    }
}
