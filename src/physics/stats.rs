//! Robust statistics shared by the ξ estimation, the surface fits and the
//! scene-change detection.

/// Median of sorted values (the mean of the middle two for an even count).
pub fn median_sorted(v: &[f64]) -> f64 {
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// `(median, 1.4826 MAD)`: a centre and a standard deviation that outliers
/// do not move; sorts `v`. `None` for no values.
pub fn median_and_sigma(v: &mut [f64]) -> Option<(f64, f64)> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let med = median_sorted(v);
    let mut dev: Vec<f64> = v.iter().map(|x| (x - med).abs()).collect();
    dev.sort_by(f64::total_cmp);
    Some((med, 1.4826 * median_sorted(&dev)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_and_sigma_ignore_an_outlier() {
        let mut v: Vec<f64> = (0..100).map(|k| k as f64).collect();
        v.push(1e9);
        let (m, s) = median_and_sigma(&mut v).unwrap();
        assert_eq!(m, 50.0);
        assert!((s - 1.4826 * 25.0).abs() < 1e-9, "{s}");
        assert_eq!(median_sorted(&[1.0, 2.0]), 1.5);
        assert!(median_and_sigma(&mut []).is_none());
    }
}
