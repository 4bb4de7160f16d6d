//! The emitted-light map `Lin` (paper Eq. 13-14) from a white opaque plane.

use nalgebra::Vector3;
use thiserror::Error;

use super::buffer::ImageBuf;
use super::surface::{fit_plane_robust, Plane};

/// Why an emitted-light map could not be made.
#[derive(Debug, Error, PartialEq)]
pub enum EmittedLightError {
    /// Too few valid pixels to fit the calibration plane.
    #[error("only {valid} valid pixels of {total}: the calibration plane needs at least {needed}")]
    TooFewPixels {
        /// Valid pixels found.
        valid: usize,
        /// Pixels in the image.
        total: usize,
        /// Pixels needed.
        needed: usize,
    },
    /// The points do not form a plane.
    #[error("the calibration points do not form a plane")]
    NoPlane,
    /// The albedo is not in (0, 1].
    #[error("albedo {0} is not in (0, 1]")]
    BadAlbedo(f64),
}

/// `Lin` per pixel (Eq. 13): `Lin = I d^2 / (rho cos theta)`, `cos theta`
/// from a robust least-squares plane through the points, `rho` the plane's
/// albedo (1 for a white target). `ray_distance_mm` and `ir` are the plane's
/// readings (NaN where invalid); `unit_rays` the pixels' unit rays.
/// Pixels off the plane or invalid get NaN.
pub fn emitted_light_from_plane(
    ray_distance_mm: &ImageBuf<f64>,
    ir: &ImageBuf<f64>,
    unit_rays: &ImageBuf<Vector3<f64>>,
    albedo: f64,
) -> Result<(ImageBuf<f64>, Plane), EmittedLightError> {
    if !(albedo > 0.0 && albedo <= 1.0) {
        return Err(EmittedLightError::BadAlbedo(albedo));
    }
    let total = ray_distance_mm.len();
    let pts: Vec<Vector3<f64>> = ray_distance_mm
        .data
        .iter()
        .zip(&ir.data)
        .zip(&unit_rays.data)
        .filter(|((d, i), _)| d.is_finite() && **d > 0.0 && i.is_finite() && **i > 0.0)
        .map(|((d, _), u)| u * *d)
        .collect();
    let needed = (total / 10).max(10);
    if pts.len() < needed {
        return Err(EmittedLightError::TooFewPixels {
            valid: pts.len(),
            total,
            needed,
        });
    }
    let plane = fit_plane_robust(&pts, 3.0, 5.0, 3).ok_or(EmittedLightError::NoPlane)?;
    let cut = (4.0 * plane.rms_mm).max(20.0);
    let data = ray_distance_mm
        .data
        .iter()
        .zip(&ir.data)
        .zip(&unit_rays.data)
        .map(|((&d, &i), u)| {
            let on_plane = d.is_finite()
                && d > 0.0
                && i.is_finite()
                && i > 0.0
                && (plane.normal.dot(&(u * d)) - plane.offset).abs() <= cut;
            if on_plane {
                i * d * d / (albedo * plane.incidence_cos(u))
            } else {
                f64::NAN
            }
        })
        .collect();
    Ok((
        ImageBuf {
            width: ray_distance_mm.width,
            height: ray_distance_mm.height,
            data,
        },
        plane,
    ))
}

/// Fills the pixels of `lin` that are NaN (off the calibration plane: a box on
/// the wall, a corner) from a smooth fit of the rest: an emitter's light is a
/// smooth function of direction, so `ln Lin` is fitted by a quadratic in the
/// ray's slopes `(x/z, y/z)`, twice, the second time without the pixels beyond
/// three times the first fit's RMS. Returns the pixels filled; `lin` is left as
/// it is when fewer than 20 pixels are known.
pub fn fill_off_plane(lin: &mut ImageBuf<f64>, unit_rays: &ImageBuf<Vector3<f64>>) -> usize {
    let basis = |u: &Vector3<f64>| {
        let (x, y) = (u.x / u.z, u.y / u.z);
        nalgebra::SVector::<f64, 6>::new(1.0, x, y, x * x, x * y, y * y)
    };
    let known: Vec<(nalgebra::SVector<f64, 6>, f64)> = lin
        .data
        .iter()
        .zip(&unit_rays.data)
        .filter(|(v, u)| v.is_finite() && **v > 0.0 && u.z > 0.0)
        .map(|(v, u)| (basis(u), v.ln()))
        .collect();
    if known.len() < 20 || known.len() == lin.len() {
        return 0;
    }
    let fit = |keep: &dyn Fn(&nalgebra::SVector<f64, 6>, f64) -> bool| {
        let mut ata = nalgebra::SMatrix::<f64, 6, 6>::zeros();
        let mut atb = nalgebra::SVector::<f64, 6>::zeros();
        for (b, y) in known.iter().filter(|(b, y)| keep(b, *y)) {
            ata += b * b.transpose();
            atb += b * *y;
        }
        ata.cholesky().map(|c| c.solve(&atb))
    };
    let Some(first) = fit(&|_, _| true) else { return 0 };
    let rms = (known.iter().map(|(b, y)| (first.dot(b) - y).powi(2)).sum::<f64>() / known.len() as f64).sqrt();
    let cut = 3.0 * rms.max(1e-3);
    let coef = fit(&|b, y| (first.dot(b) - y).abs() <= cut).unwrap_or(first);
    let mut filled = 0;
    for (v, u) in lin.data.iter_mut().zip(&unit_rays.data) {
        if !(v.is_finite() && *v > 0.0) && u.z > 0.0 {
            *v = coef.dot(&basis(u)).exp();
            filled += 1;
        }
    }
    filled
}

/// Eq. 14: `Lin` scales linearly with exposure time.
pub fn scale_for_exposure(lin: &ImageBuf<f64>, calibrated_exposure_s: f64, exposure_s: f64) -> ImageBuf<f64> {
    let k = exposure_s / calibrated_exposure_s;
    ImageBuf {
        width: lin.width,
        height: lin.height,
        data: lin.data.iter().map(|v| v * k).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::camera::Intrinsics;

    #[test]
    fn recovers_lin_of_a_tilted_white_plane() {
        let k = Intrinsics::from_fov(40, 30, 44.0, 35.0);
        let rays = k.unit_ray_map();
        let n = Vector3::new(0.3, 0.0, -1.0).normalize();
        let offset = n.dot(&Vector3::new(0.0, 0.0, 2000.0));
        let lin_true = |i: usize| 1e10 * (1.0 + 0.001 * i as f64);
        let mut d = vec![];
        let mut ir = vec![];
        for (i, u) in rays.data.iter().enumerate() {
            let t = offset / n.dot(u);
            d.push(t);
            ir.push(lin_true(i) * n.dot(u).abs() / (t * t));
        }
        let d = ImageBuf::from_vec(40, 30, d).unwrap();
        let ir = ImageBuf::from_vec(40, 30, ir).unwrap();
        let (lin, plane) = emitted_light_from_plane(&d, &ir, &rays, 1.0).unwrap();
        assert!(plane.rms_mm < 1e-3, "{}", plane.rms_mm);
        for (i, v) in lin.data.iter().enumerate() {
            assert!((v / lin_true(i) - 1.0).abs() < 1e-9);
        }
        let half = emitted_light_from_plane(&d, &ir, &rays, 0.5).unwrap().0;
        assert!((half.data[0] / lin.data[0] - 2.0).abs() < 1e-12);
        let doubled = scale_for_exposure(&lin, 1.5e-3, 3.0e-3);
        assert!((doubled.data[5] / lin.data[5] - 2.0).abs() < 1e-12);
    }

    #[test]
    fn off_plane_pixels_are_filled_from_the_emitters_smooth_pattern() {
        let k = Intrinsics::from_fov(40, 30, 44.0, 35.0);
        let rays = k.unit_ray_map();
        // A spot-like emitter: brightest on the axis, falling off with the angle.
        let truth: Vec<f64> = rays.data.iter().map(|u| 1e10 * (1.0 - 0.8 * (1.0 - u.z))).collect();
        let mut lin = ImageBuf::from_vec(40, 30, truth.clone()).unwrap();
        // A box on the wall: its pixels are off the plane.
        for r in 5..15 {
            for c in 20..32 {
                lin.data[r * 40 + c] = f64::NAN;
            }
        }
        assert_eq!(fill_off_plane(&mut lin, &rays), 120);
        for (v, t) in lin.data.iter().zip(&truth) {
            assert!((v / t - 1.0).abs() < 2e-3, "{v} {t}");
        }
    }

    #[test]
    fn too_few_pixels_is_an_error() {
        let k = Intrinsics::from_fov(40, 30, 44.0, 35.0);
        let d = ImageBuf::filled(40, 30, f64::NAN);
        let ir = ImageBuf::filled(40, 30, 1.0);
        let e = emitted_light_from_plane(&d, &ir, &k.unit_ray_map(), 1.0).unwrap_err();
        assert!(matches!(e, EmittedLightError::TooFewPixels { valid: 0, .. }));
    }
}
