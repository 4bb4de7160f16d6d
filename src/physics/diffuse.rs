//! A layer that transmits diffusely (frosted, a thin diffuser): the light crossing it
//! leaves through a cosine lobe, not along the ray, so the background is reached, and
//! seen, over a spread of slanted paths.
//!
//! For a layer `g` before a plane background, a crossing at angle `θ` from the normal
//! travels `g / cos θ`. Over the cosine lobe (`u = cos θ` with density `2u`), the
//! crossing's phasor average at the equivalent distance (half the path) is
//!
//! `ψ(a) = ∫₀¹ 2u exp(i a / u) du`,  `a = k g / 2`
//!
//! and the second return crosses twice (in and back): `ψ²`. Of the light that crosses,
//! a share `f` does so diffusely: the second return (Eq. 2) keeps `(1 - f) L2` at the
//! background's distance, and the diffuse part, `f L2 ψ(k g / 2)²` at the layer's phase,
//! is a return of strength `f L2 |ψ²|` at `df + arg(ψ²) / k`. The background is taken as
//! an infinite uniform plane: its parts outside the layer's shadow (lit directly and seen
//! through the layer at a slant) and the layer's extent are left out
//! (`scripts/diffuse_return.py` measures what that leaves).

use std::sync::OnceLock;

/// Entries of the table of `ψ` over `[0, TABLE_MAX]`.
const TABLE_LEN: usize = 4096;
/// Largest `a` the table holds: layers up to two unambiguous ranges before the background.
const TABLE_MAX: f64 = 2.0 * std::f64::consts::PI;
/// Midpoints of the quadrature in `u`.
const QUADRATURE: usize = 8192;

/// `ψ(a)` by the midpoint rule in `u` (real and imaginary parts).
fn lobe_average_direct(a: f64) -> (f64, f64) {
    let (mut re, mut im) = (0.0, 0.0);
    let du = 1.0 / QUADRATURE as f64;
    for j in 0..QUADRATURE {
        let u = (j as f64 + 0.5) * du;
        let (s, c) = (a / u).sin_cos();
        re += 2.0 * u * c * du;
        im += 2.0 * u * s * du;
    }
    (re, im)
}

fn table() -> &'static [(f64, f64)] {
    static TABLE: OnceLock<Vec<(f64, f64)>> = OnceLock::new();
    TABLE.get_or_init(|| {
        (0..=TABLE_LEN)
            .map(|j| lobe_average_direct(TABLE_MAX * j as f64 / TABLE_LEN as f64))
            .collect()
    })
}

/// `ψ(a)`, one diffuse crossing's phasor average (real and imaginary parts); `a` at least 0.
pub fn lobe_average(a: f64) -> (f64, f64) {
    let a = a.max(0.0);
    if !(a < TABLE_MAX) {
        return if a.is_finite() {
            lobe_average_direct(a)
        } else {
            (0.0, 0.0)
        };
    }
    let t = table();
    let x = a / TABLE_MAX * TABLE_LEN as f64;
    let j = (x as usize).min(TABLE_LEN - 1);
    let w = x - j as f64;
    let (p, q) = (t[j], t[j + 1]);
    (p.0 + w * (q.0 - p.0), p.1 + w * (q.1 - p.1))
}

/// The diffuse part of the second return over `L2` for a layer `gap_mm` before the
/// background, `k` the sensor's radians per mm: its length `|ψ²|` and the extra
/// equivalent distance past the layer, `arg(ψ²) / k`, mm.
pub fn diffuse_second_return(gap_mm: f64, k: f64) -> (f64, f64) {
    let (re, im) = lobe_average(k * gap_mm.max(0.0) / 2.0);
    let (sq_re, sq_im) = (re * re - im * im, 2.0 * re * im);
    (sq_re.hypot(sq_im), sq_im.atan2(sq_re) / k)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lobe_average_is_one_at_no_gap_and_shrinks_and_turns_with_it() {
        let (re, im) = lobe_average(0.0);
        assert!((re - 1.0).abs() < 1e-6 && im.abs() < 1e-9, "{re} {im}");
        // Small a: psi ~ 1 + i a E[1/u] = 1 + 2 i a.
        let (re, im) = lobe_average(1e-3);
        assert!((re - 1.0).abs() < 1e-4 && (im - 2e-3).abs() < 2e-5, "{re} {im}");
        let mut last = 1.0;
        for a in [0.2, 0.5, 1.0, 1.5] {
            let (re, im) = lobe_average(a);
            let len = re.hypot(im);
            assert!(len < last && im > 0.0, "{a}: {re} {im}");
            last = len;
        }
        // The table agrees with the quadrature between its entries.
        let a = 0.123_456 * TABLE_MAX;
        let (t, d) = (lobe_average(a), lobe_average_direct(a));
        assert!((t.0 - d.0).abs() < 1e-5 && (t.1 - d.1).abs() < 1e-5, "{t:?} {d:?}");
    }

    #[test]
    fn the_diffuse_return_lies_past_the_layer_by_more_than_the_gap_and_fades() {
        // 30 MHz: k = 2 pi / 4996.5 mm. A crossing's mean path over the lobe is twice the gap.
        let k = std::f64::consts::TAU / 4996.5;
        let (len, extra) = diffuse_second_return(100.0, k);
        assert!(len < 1.0 && len > 0.9, "{len}");
        assert!(extra > 100.0 && extra < 400.0, "{extra}");
        let (far, _) = diffuse_second_return(1000.0, k);
        assert!(far < len, "{far} {len}");
        let (len0, extra0) = diffuse_second_return(0.0, k);
        assert!((len0 - 1.0).abs() < 1e-6 && extra0.abs() < 1e-6, "{len0} {extra0}");
    }
}
