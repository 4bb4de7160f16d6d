//! `sin` and `cos` together, by a reduction to `[-pi/4, pi/4]` and two
//! polynomials, written in plain arithmetic (no calls, no branches on the
//! lane's value) so that a loop over many angles compiles to vector code.
//!
//! The polynomials are the classic minimax kernels of degree 13 (sine) and
//! 14 (cosine) on `[-pi/4, pi/4]`; the reduction subtracts `n pi/2` in three
//! parts (Cody and Waite), exact for `|n| <= 2^20`. Within 1 ulp of the
//! platform's `f64::sin_cos` for `|x| <= 1000` (the inversion's angles stay
//! below a few hundred radians), within 2 ulp up to `2^20 pi/2` (test
//! `within_an_ulp_of_the_platform`); beyond that it is the platform's. The
//! sine of `-0.0` comes out `+0.0`.

#![allow(clippy::excessive_precision)] // the kernels' coefficients as published

use std::f64::consts::FRAC_2_PI;

const S1: f64 = -1.666_666_666_666_663_243_48e-1;
const S2: f64 = 8.333_333_333_322_489_461_24e-3;
const S3: f64 = -1.984_126_982_985_794_931_34e-4;
const S4: f64 = 2.755_731_370_707_006_767_89e-6;
const S5: f64 = -2.505_076_025_340_686_341_95e-8;
const S6: f64 = 1.589_690_995_211_550_102_21e-10;

const C1: f64 = 4.166_666_666_666_660_190_37e-2;
const C2: f64 = -1.388_888_888_887_410_957_49e-3;
const C3: f64 = 2.480_158_728_947_672_941_78e-5;
const C4: f64 = -2.755_731_435_139_066_330_35e-7;
const C5: f64 = 2.087_572_321_298_174_827_90e-9;
const C6: f64 = -1.135_964_755_778_819_482_65e-11;

/// `pi/2` in three parts: the first two of 33 significant bits (so `n` times
/// either is exact for `|n| <= 2^20`), the third the rest.
const PIO2_1: f64 = 1.570_796_326_734_125_614_17;
const PIO2_2: f64 = 6.077_100_506_303_965_976_60e-11;
const PIO2_3: f64 = 2.022_266_248_795_950_631_54e-21;

/// `1.5 * 2^52`: adding it rounds a double of magnitude below `2^51` to an
/// integer held in the low bits of the sum's mantissa.
const ROUNDER: f64 = 6_755_399_441_055_744.0;

/// Largest `|x|` [`sin_cos_reduced`] takes: `|n| <= 2^20`.
pub const REDUCED_LIMIT: f64 = 1_647_099.0;

/// `(sin x, cos x)`: [`sin_cos_reduced`] within its range, else the platform's.
#[inline]
pub fn sin_cos(x: f64) -> (f64, f64) {
    if x.abs() <= REDUCED_LIMIT {
        sin_cos_reduced(x)
    } else {
        x.sin_cos()
    }
}

/// `(sin x, cos x)` for `|x| <= 2^20 pi/2` (NaN for NaN): branch-free, for
/// lanes of a vector loop; larger `|x|` loses accuracy.
#[inline(always)]
pub fn sin_cos_reduced(x: f64) -> (f64, f64) {
    // n = round(x 2/pi); its quadrant in the low bits of the rounded sum.
    let t = x * FRAC_2_PI + ROUNDER;
    let quadrant = t.to_bits();
    let n = t - ROUNDER;
    let r = (x - n * PIO2_1 - n * PIO2_2) - n * PIO2_3;
    let z = r * r;
    let sin_r = r + z * r * (S1 + z * (S2 + z * (S3 + z * (S4 + z * (S5 + z * S6)))));
    // cos r = 1 - z/2 + z^2 (...), the first subtraction's rounding carried (w's error).
    let tail = z * z * (C1 + z * (C2 + z * (C3 + z * (C4 + z * (C5 + z * C6)))));
    let half = 0.5 * z;
    let w = 1.0 - half;
    let cos_r = w + (((1.0 - w) - half) + tail);
    // Quadrant q: (sin, cos) = (s, c), (c, -s), (-s, -c), (-c, s).
    let odd = quadrant & 1 == 1;
    let (s, c) = if odd { (cos_r, sin_r) } else { (sin_r, cos_r) };
    let sin_sign = (quadrant & 2) << 62;
    let cos_sign = (quadrant.wrapping_add(1) & 2) << 62;
    (
        f64::from_bits(s.to_bits() ^ sin_sign),
        f64::from_bits(c.to_bits() ^ cos_sign),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f64, b: f64) -> u64 {
        if a == b {
            return 0;
        }
        (a.to_bits() as i64).wrapping_sub(b.to_bits() as i64).unsigned_abs()
    }

    /// The largest difference from the platform in ulp (where the value is
    /// above 1e-3: near a zero an ulp is tiny) and in absolute terms, over
    /// angles spread across `[-scale, scale]`.
    fn worst(scale: f64) -> (u64, f64) {
        let golden = 0.618_033_988_749_894_9;
        let (mut ulp, mut abs) = (0, 0.0_f64);
        for i in 0..200_000 {
            let x = (2.0 * (i as f64 * golden).fract() - 1.0) * scale;
            let (s, c) = sin_cos(x);
            let (s0, c0) = x.sin_cos();
            for (v, v0) in [(s, s0), (c, c0)] {
                abs = abs.max((v - v0).abs());
                if v0.abs() > 1e-3 {
                    ulp = ulp.max(ulps(v, v0));
                }
            }
        }
        (ulp, abs)
    }

    #[test]
    fn within_an_ulp_of_the_platform() {
        for scale in [1.0, 10.0, 1000.0] {
            let (ulp, abs) = worst(scale);
            assert!(ulp <= 1 && abs <= 2.3e-16, "|x| <= {scale}: {ulp} ulp, {abs:e}");
        }
        for scale in [1e4, REDUCED_LIMIT] {
            let (ulp, abs) = worst(scale);
            assert!(ulp <= 2 && abs <= 4.5e-16, "|x| <= {scale}: {ulp} ulp, {abs:e}");
        }
        // The quadrants' edges.
        for k in -8..=8 {
            let x = k as f64 * std::f64::consts::FRAC_PI_4;
            let (s, c) = sin_cos(x);
            let (s0, c0) = x.sin_cos();
            assert!(
                (s - s0).abs() <= 2.3e-16 && (c - c0).abs() <= 2.3e-16,
                "{x}: {s} {c} vs {s0} {c0}"
            );
        }
    }

    #[test]
    fn beyond_the_reduction_and_not_finite() {
        assert_eq!(sin_cos(1e9), 1e9_f64.sin_cos());
        assert!(sin_cos(f64::NAN).0.is_nan() && sin_cos(f64::NAN).1.is_nan());
        assert!(sin_cos(f64::INFINITY).0.is_nan());
        assert_eq!(sin_cos(0.0), (0.0, 1.0));
        assert_eq!(sin_cos(-0.0), (0.0, 1.0));
    }
}
