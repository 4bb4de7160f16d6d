//! Sensor effects the model lacks, as options of the simulator: what real cameras show
//! beyond the forward model (lens stray light, saturation, a nonlinear amplitude response,
//! a phase offset that drifts as the camera warms). The audit has none of them in its
//! catalogue; scenes with them test what it says of physics it cannot name.
//!
//! Every one acts on the [`Measurement`] the one forward model makes of a pixel's returns
//! (or on the returns themselves): none is a model of its own.

use serde::{Deserialize, Serialize};

use crate::physics::sensor::Buckets;
use crate::physics::{Measurement, Return, Sensor};

/// The sensor effects past the model, each off at its default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Artefacts {
    /// Share of the frame's mean light (buckets and IR) the lens scatters onto every pixel:
    /// a bright object's signal spread over its neighbours. 0: none.
    pub stray_light: f64,
    /// Full well, IR counts: a pixel's raw buckets `(T +- A) / 2`, `(T +- B) / 2` and its IR
    /// clip at it (`T` the light collected). 0: none.
    pub saturation_ir: f64,
    /// Power of the amplitude response: the IR reads `R (I / R)^p`, `R` the
    /// [`Artefacts::amplitude_reference`]. 1: linear.
    pub amplitude_power: f64,
    /// The IR level the nonlinear response leaves as it is, counts.
    pub amplitude_reference: f64,
    /// Drift of the phase offset with the frame time, as a distance, mm per second (a
    /// camera warming up): every return reads this much farther per second since the first frame.
    pub phase_drift_mm_per_s: f64,
}

impl Default for Artefacts {
    fn default() -> Self {
        Self {
            stray_light: 0.0,
            saturation_ir: 0.0,
            amplitude_power: 1.0,
            amplitude_reference: 1000.0,
            phase_drift_mm_per_s: 0.0,
        }
    }
}

impl Artefacts {
    /// Whether every effect is off.
    pub fn none(&self) -> bool {
        self.stray_light == 0.0
            && self.saturation_ir == 0.0
            && self.amplitude_power == 1.0
            && self.phase_drift_mm_per_s == 0.0
    }

    /// Checks every value's range; the error names the value.
    pub fn validate(&self) -> Result<(), String> {
        let ok = (0.0..1.0).contains(&self.stray_light)
            && self.saturation_ir >= 0.0
            && self.amplitude_power > 0.0
            && self.amplitude_power.is_finite()
            && self.amplitude_reference > 0.0
            && self.amplitude_reference.is_finite()
            && self.phase_drift_mm_per_s.is_finite();
        if ok {
            Ok(())
        } else {
            Err("camera.artefacts: stray_light in [0, 1), saturation_ir >= 0, amplitude_power > 0, amplitude_reference > 0 and a finite phase_drift_mm_per_s required".into())
        }
    }

    /// The returns as the drifted phase offset reads them at frame time `t_s`, seconds.
    pub fn drift(&self, returns: &mut [Return], t_s: f64) {
        let shift = self.phase_drift_mm_per_s * t_s;
        if shift != 0.0 {
            for r in returns {
                r.distance_mm += shift;
            }
        }
    }

    /// The frame's mean light, what stray light spreads: `(buckets, total light, IR)` over
    /// the pixels that received any.
    pub fn frame_light(measurements: &[Option<Measurement>]) -> (Buckets, f64, f64) {
        let (mut b, mut t, mut ir, mut n) = (Buckets::default(), 0.0, 0.0, 0usize);
        for m in measurements.iter().flatten() {
            b += m.buckets;
            t += m.total_light;
            ir += m.ir;
            n += 1;
        }
        let k = 1.0 / n.max(1) as f64;
        (Buckets { a: b.a * k, b: b.b * k }, t * k, ir * k)
    }

    /// A pixel's measurement with the stray light of the frame's mean light `frame`
    /// ([`Artefacts::frame_light`]), the saturation and the amplitude response, read again.
    pub fn apply(&self, sensor: &Sensor, m: &Measurement, frame: (Buckets, f64, f64)) -> Measurement {
        let mut out = *m;
        let s = self.stray_light;
        if s > 0.0 {
            out.buckets = Buckets {
                a: out.buckets.a + s * frame.0.a,
                b: out.buckets.b + s * frame.0.b,
            };
            out.total_light += s * frame.1;
            out.ir += s * frame.2;
        }
        let w = self.saturation_ir;
        if w > 0.0 {
            let clip = |q: f64| q.clamp(0.0, w);
            let t = out.total_light;
            let (a, b) = (out.buckets.a, out.buckets.b);
            out.buckets = Buckets {
                a: clip(0.5 * (t + a)) - clip(0.5 * (t - a)),
                b: clip(0.5 * (t + b)) - clip(0.5 * (t - b)),
            };
            out.ir = out.ir.min(w);
        }
        if self.amplitude_power != 1.0 && out.ir > 0.0 {
            let r = self.amplitude_reference;
            out.ir = r * (out.ir / r).powf(self.amplitude_power);
        }
        out.distance_mm = sensor.decode(out.buckets).unwrap_or(f64::NAN);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::ForwardModel;

    fn reading(a: &Artefacts, strength: f64, d: f64) -> Measurement {
        let model = ForwardModel::paper(Sensor::sr4000());
        let m = model.measure(&[ForwardModel::opaque_return(d, 1.0, strength * d * d)]);
        a.apply(&model.sensor, &m, (Buckets::default(), 0.0, 0.0))
    }

    #[test]
    fn off_leaves_the_reading_as_the_model_makes_it() {
        let a = Artefacts::default();
        assert!(a.none());
        let m = reading(&a, 500.0, 1800.0);
        assert!(
            (m.distance_mm - 1800.0).abs() < 1e-6 && (m.ir - 500.0).abs() < 1e-6,
            "{m:?}"
        );
    }

    #[test]
    fn saturation_clips_the_ir_and_moves_the_bright_pixels_reading() {
        let a = Artefacts {
            saturation_ir: 400.0,
            ..Artefacts::default()
        };
        let faint = reading(&a, 300.0, 1800.0);
        assert!((faint.distance_mm - 1800.0).abs() < 1e-6 && (faint.ir - 300.0).abs() < 1e-6);
        let bright = reading(&a, 500.0, 1800.0);
        assert_eq!(bright.ir, 400.0);
        assert!((bright.distance_mm - 1800.0).abs() > 5.0, "{bright:?}");
    }

    #[test]
    fn the_amplitude_response_bends_the_ir_about_its_reference_only() {
        let a = Artefacts {
            amplitude_power: 0.8,
            amplitude_reference: 400.0,
            ..Artefacts::default()
        };
        assert!((reading(&a, 400.0, 1500.0).ir - 400.0).abs() < 1e-6);
        let m = reading(&a, 1600.0, 1500.0);
        assert!((m.ir - 400.0 * 4f64.powf(0.8)).abs() < 1e-6 && (m.distance_mm - 1500.0).abs() < 1e-6);
    }

    #[test]
    fn drift_moves_every_return_with_the_frame_time() {
        let a = Artefacts {
            phase_drift_mm_per_s: 2.0,
            ..Artefacts::default()
        };
        let mut r = [
            ForwardModel::opaque_return(1000.0, 1.0, 1e9),
            ForwardModel::opaque_return(2000.0, 1.0, 1e9),
        ];
        a.drift(&mut r, 5.0);
        assert_eq!([r[0].distance_mm, r[1].distance_mm], [1010.0, 2010.0]);
    }

    #[test]
    fn stray_light_adds_the_frames_mean_light() {
        let a = Artefacts {
            stray_light: 0.1,
            ..Artefacts::default()
        };
        let model = ForwardModel::paper(Sensor::sr4000());
        let near = model.measure(&[ForwardModel::opaque_return(1000.0, 1.0, 1e9)]);
        let far = model.measure(&[ForwardModel::opaque_return(2500.0, 1.0, 1e8)]);
        let frame = Artefacts::frame_light(&[Some(near), Some(far), None]);
        let m = a.apply(&model.sensor, &far, frame);
        assert!((m.ir - (far.ir + 0.05 * (near.ir + far.ir))).abs() < 1e-6);
        assert!(m.distance_mm < 2400.0, "the near return pulls the far pixel: {m:?}");
    }
}
