//! Shot noise in the buckets: depth noise that grows as the returned signal
//! weakens (the paper reports ~10 mm at a white wall at 2 m). Deterministic:
//! the caller draws the standard normals.

use super::model::Measurement;
use super::sensor::{Buckets, Sensor};

/// Bucket noise `sigma = k sqrt(total light + read^2)`, the same on both
/// bucket differences and on the IR value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShotNoise {
    /// `k`, counts^(1/2).
    pub coefficient: f64,
    /// Read noise, in counts of equivalent light (`read^2` adds to the variance).
    pub read_noise: f64,
}

impl ShotNoise {
    /// The `k` under which a single opaque return of `strength` reads with a
    /// distance noise of `sigma_mm` (sinusoidal phase noise `sigma / strength`).
    pub fn calibrated(sensor: &Sensor, strength: f64, sigma_mm: f64, read_noise: f64) -> Self {
        // At the sensor's own frequency (with a depth engine too: the buckets' noise is the light's).
        let sigma_phase = sigma_mm * sensor.phase(1.0);
        let sigma_bucket = sigma_phase * strength;
        Self {
            coefficient: sigma_bucket / (strength + read_noise * read_noise).sqrt(),
            read_noise,
        }
    }

    /// Standard deviation of each bucket difference for this much light.
    pub fn bucket_sigma(&self, total_light: f64) -> f64 {
        self.coefficient * (total_light.max(0.0) + self.read_noise * self.read_noise).sqrt()
    }

    /// A noisy reading `(distance_mm, ir)` of a measurement, given three
    /// standard normal draws `z`.
    pub fn apply(&self, sensor: &Sensor, m: &Measurement, z: [f64; 3]) -> (f64, f64) {
        let s = self.bucket_sigma(m.total_light);
        let b = Buckets {
            a: m.buckets.a + s * z[0],
            b: m.buckets.b + s * z[1],
        };
        let d = sensor.decode(b).unwrap_or(f64::NAN);
        (d, m.ir + s * z[2])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::model::ForwardModel;

    #[test]
    fn calibrated_noise_gives_the_asked_depth_sigma() {
        let sensor = Sensor::sr4000();
        let model = ForwardModel::paper(sensor.clone());
        let strength = 1.5e10 / 4.0e6;
        let noise = ShotNoise::calibrated(&sensor, strength, 10.0, 0.0);
        let m = model.measure(&[ForwardModel::opaque_return(2000.0, 1.0, 1.5e10)]);
        // Deterministic quadrature over a grid of normal pairs: small-angle sigma.
        let mut acc = 0.0;
        let mut n = 0.0;
        for i in -20..=20 {
            for j in -20..=20 {
                let (z0, z1) = (i as f64 * 0.15, j as f64 * 0.15);
                let w = (-(z0 * z0 + z1 * z1) / 2.0).exp();
                let (d, _) = noise.apply(&sensor, &m, [z0, z1, 0.0]);
                acc += w * (d - 2000.0).powi(2);
                n += w;
            }
        }
        let sigma = (acc / n).sqrt();
        assert!((sigma - 10.0).abs() < 0.2, "{sigma}");
        // Four times less light: twice the noise.
        assert!((noise.bucket_sigma(strength / 4.0) / strength * 4.0) > 1.9 * noise.bucket_sigma(strength) / strength);
    }
}
