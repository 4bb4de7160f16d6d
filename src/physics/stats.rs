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

/// The `q` quantile (`0 <= q <= 1`) of values in any order: the value at rank
/// `round(q (n - 1))`, by selection; reorders `v`. NaN for no values.
pub fn quantile_select(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let rank = ((q.clamp(0.0, 1.0) * (v.len() - 1) as f64).round() as usize).min(v.len() - 1);
    *v.select_nth_unstable_by(rank, f64::total_cmp).1
}

/// Median of values in any order (the mean of the middle two for an even
/// count), by selection; reorders `v`. The same value as [`median_sorted`] of
/// the sorted values. NaN for no values.
pub fn median_select(v: &mut [f64]) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    let (lower, mid, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let mid = *mid;
    if n % 2 == 1 {
        mid
    } else {
        let below = lower.iter().copied().max_by(f64::total_cmp).unwrap_or(mid);
        0.5 * (below + mid)
    }
}

/// `(median, 1.4826 MAD)`: a centre and a standard deviation that outliers
/// do not move; reorders `v`. `None` for no values.
pub fn median_and_sigma(v: &mut [f64]) -> Option<(f64, f64)> {
    if v.is_empty() {
        return None;
    }
    let med = median_select(v);
    Some((med, sigma_about(v, med)))
}

/// `1.4826 MAD` about a known median `med`: the robust standard deviation
/// of [`median_and_sigma`] when the median is already at hand. NaN for no values.
pub fn sigma_about(v: &[f64], med: f64) -> f64 {
    let mut dev: Vec<f64> = v.iter().map(|x| (x - med).abs()).collect();
    1.4826 * median_select(&mut dev)
}

/// `(median, 1.4826 MAD)` of values sorted ascending: the same pair as
/// [`median_and_sigma`] (NaN for no values), the deviations' median found by
/// walking the two runs of deviations either side of the median (each already
/// in order) as far as their middle, instead of a second selection.
pub fn median_and_sigma_sorted(v: &[f64]) -> (f64, f64) {
    let n = v.len();
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let med = median_sorted(v);
    // Below the split the deviations grow leftwards, from it rightwards.
    let split = v.partition_point(|&x| x < med);
    let (mut left, mut right) = (split, split);
    let mut next = || {
        let l = left.checked_sub(1).map(|i| (v[i] - med).abs());
        let r = v.get(right).map(|&x| (x - med).abs());
        match (l, r) {
            (Some(a), Some(b)) if a <= b => {
                left -= 1;
                a
            }
            (Some(a), None) => {
                left -= 1;
                a
            }
            (_, Some(b)) => {
                right += 1;
                b
            }
            (None, None) => f64::NAN,
        }
    };
    // The deviations in order up to rank n / 2 (and the one before it, for an even count).
    let mut below = f64::NAN;
    for _ in 0..n / 2 {
        below = next();
    }
    let mid = next();
    let mad = if n % 2 == 1 { mid } else { 0.5 * (below + mid) };
    (med, 1.4826 * mad)
}

/// Two-sided 97.5 % quantile of Student's t.
pub fn student_t975(dof: usize) -> f64 {
    const T: [f64; 10] = [12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228];
    match dof {
        0 => f64::INFINITY,
        1..=10 => T[dof - 1],
        11..=20 => 2.086 + (2.228 - 2.086) * (20 - dof) as f64 / 10.0,
        21..=30 => 2.042 + (2.086 - 2.042) * (30 - dof) as f64 / 10.0,
        _ => 1.96 + 0.08 * 30.0 / dof as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sorted_median_and_sigma_are_those_of_selection() {
        // Odd and even counts, ties at and around the median, negative values, one value.
        let mut rng: u64 = 0x9e37_79b9_7f4a_7c15;
        for n in 1..60usize {
            for round in 0..20 {
                let mut v: Vec<f64> = (0..n)
                    .map(|_| {
                        rng ^= rng << 13;
                        rng ^= rng >> 7;
                        rng ^= rng << 17;
                        let x = (rng % 1000) as f64 / 7.0 - 50.0;
                        if round % 3 == 0 {
                            x.round()
                        } else {
                            x
                        }
                    })
                    .collect();
                let (m, s) = median_and_sigma(&mut v.clone()).unwrap();
                v.sort_by(f64::total_cmp);
                let (ms, ss) = median_and_sigma_sorted(&v);
                assert_eq!((m.to_bits(), s.to_bits()), (ms.to_bits(), ss.to_bits()), "{v:?}");
            }
        }
        assert!(median_and_sigma_sorted(&[]).0.is_nan());
    }

    #[test]
    fn median_and_sigma_ignore_an_outlier() {
        let mut v: Vec<f64> = (0..100).map(|k| k as f64).collect();
        v.push(1e9);
        let (m, s) = median_and_sigma(&mut v).unwrap();
        assert_eq!(m, 50.0);
        assert!((s - 1.4826 * 25.0).abs() < 1e-9, "{s}");
        assert_eq!(median_sorted(&[1.0, 2.0]), 1.5);
        assert!(median_and_sigma(&mut []).is_none());
        // Selection gives the sorted median, odd and even counts, ties and all.
        for n in 1..40usize {
            let v: Vec<f64> = (0..n).map(|k| ((k * 7919) % 23) as f64 * 0.5 - 3.0).collect();
            let mut sorted = v.clone();
            sorted.sort_by(f64::total_cmp);
            assert_eq!(median_select(&mut v.clone()), median_sorted(&sorted), "n {n}");
        }
    }
}
