//! Which pixels look through a translucent layer (paper Sec. V-C): those whose
//! reading moved by more than a threshold from the latched background.

use super::buffer::ImageBuf;

/// Default threshold: 3x the SR4000's ~10 mm background noise (the paper's 30 mm).
pub const DEFAULT_THRESHOLD_MM: f64 = 30.0;

/// `a - b` as a phase difference in distance units, in `[-R/2, R/2)`: readings
/// of a CW ToF camera are known modulo its unambiguous range `R`.
pub fn wrapped_difference(a: f64, b: f64, range_mm: f64) -> f64 {
    let (d, half) = (a - b, range_mm / 2.0);
    // Already within the range (the common case): no division.
    if d >= -half && d < half {
        return d;
    }
    (d + half).rem_euclid(range_mm) - half
}

/// How many standard deviations of a pixel's own noise a change must exceed.
pub const NOISE_SIGMAS: f64 = 3.0;

/// `|d - db| > threshold_mm`, compared as wrapped phases (range `range_mm`),
/// where both readings are valid (finite, > 0). With `change_noise_mm` (the
/// standard deviation of `d - db` per pixel, where known), the threshold is
/// at least [`NOISE_SIGMAS`] of it: the paper's 30 mm is 3x the ~10 mm noise
/// of its wall, and a farther or darker background is noisier.
pub fn changed_pixels(
    distance_mm: &ImageBuf<f64>,
    background_mm: &ImageBuf<f64>,
    threshold_mm: f64,
    range_mm: f64,
    change_noise_mm: Option<&ImageBuf<f64>>,
) -> ImageBuf<bool> {
    // The common case first, pixel by pixel without branches (a loop the compiler
    // vectorizes): a difference already within half the range is its own wrapped
    // difference. The few valid pixels beyond it are wrapped afterwards.
    let half = range_mm / 2.0;
    // (`move`: the constant copied in, so the loops do not read it back at every pixel.)
    let threshold = move |sigma: f64| threshold_mm.max(NOISE_SIGMAS * if sigma.is_finite() { sigma } else { 0.0 });
    let (d, b) = (&distance_mm.data, &background_mm.data);
    let mut data = vec![false; d.len()];
    let far = match change_noise_mm {
        Some(n) => changed_within_half(&mut data, d, b, n.data.iter().map(|&s| threshold(s)), half),
        None => changed_within_half(&mut data, d, b, std::iter::repeat(threshold(0.0)), half),
    };
    if far > 0 {
        for (i, out) in data.iter_mut().enumerate() {
            let (d, db) = (d[i], b[i]);
            if valid(d) & valid(db) & !within_half(d, db, half) {
                let sigma = change_noise_mm.map_or(0.0, |n| n.data[i]);
                *out = wrapped_difference(d, db, range_mm).abs() > threshold(sigma);
            }
        }
    }
    ImageBuf {
        width: distance_mm.width,
        height: distance_mm.height,
        data,
    }
}

/// [`changed_pixels`]'s common case at every pixel: `out` marks the valid
/// pairs whose difference, within half the range, exceeds the pixel's
/// threshold (one per pixel, in order); how many valid pairs lie beyond half
/// the range (left unmarked, to be wrapped).
#[inline(always)]
fn changed_within_half(
    out: &mut [bool],
    d: &[f64],
    b: &[f64],
    thresholds: impl Iterator<Item = f64>,
    half: f64,
) -> usize {
    let mut far = 0usize;
    for (((out, &d), &db), t) in out.iter_mut().zip(d).zip(b).zip(thresholds) {
        let (both, near) = (valid(d) & valid(db), within_half(d, db, half));
        *out = both & near & ((d - db).abs() > t);
        far += usize::from(both & !near);
    }
    far
}

/// `d - db` in `[-half, half)`: its own wrapped difference.
#[inline(always)]
fn within_half(d: f64, db: f64, half: f64) -> bool {
    let diff = d - db;
    (diff >= -half) & (diff < half)
}

#[inline(always)]
fn valid(d: f64) -> bool {
    // `d.is_finite() && d > 0.0`, without a branch.
    (d > 0.0) & (d < f64::INFINITY)
}

/// Removes 4-connected regions smaller than `min_pixels` (isolated noise
/// crossing the threshold); returns the cleaned mask and the region count kept.
pub fn remove_small_regions(mask: &ImageBuf<bool>, min_pixels: usize) -> (ImageBuf<bool>, usize) {
    let (w, h) = (mask.width, mask.height);
    let mut out = ImageBuf::filled(w, h, false);
    let mut seen = vec![false; w * h];
    let mut stack = Vec::new();
    let mut region = Vec::new();
    let mut kept = 0;
    for start in 0..w * h {
        if !mask.data[start] || seen[start] {
            continue;
        }
        region.clear();
        // Each pixel with its column: its neighbours are found without a division.
        stack.push((start, start % w));
        seen[start] = true;
        while let Some((i, c)) = stack.pop() {
            region.push(i);
            let mut visit = |j: usize, cj: usize| {
                if mask.data[j] && !seen[j] {
                    seen[j] = true;
                    stack.push((j, cj));
                }
            };
            if c > 0 {
                visit(i - 1, c - 1);
            }
            if c + 1 < w {
                visit(i + 1, c + 1);
            }
            if i >= w {
                visit(i - w, c);
            }
            if i + w < w * h {
                visit(i + w, c);
            }
        }
        if region.len() >= min_pixels {
            kept += 1;
            for &i in &region {
                out.data[i] = true;
            }
        }
    }
    (out, kept)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threshold_and_validity() {
        let d = ImageBuf::from_vec(4, 1, vec![1000.0, 1969.0, f64::NAN, 0.0]).unwrap();
        let b = ImageBuf::from_vec(4, 1, vec![2000.0, 2000.0, 2000.0, 2000.0]).unwrap();
        let m = changed_pixels(&d, &b, 30.0, 4996.5, None);
        assert_eq!(m.data, vec![true, true, false, false]);
        let m = changed_pixels(&d, &b, 31.0, 4996.5, None);
        assert_eq!(m.data, vec![true, false, false, false]);
        // A wall just past the range reads near 0: the same wall, not a change.
        let d = ImageBuf::from_vec(2, 1, vec![10.0, 4990.0]).unwrap();
        let b = ImageBuf::from_vec(2, 1, vec![4990.0, 10.0]).unwrap();
        assert_eq!(changed_pixels(&d, &b, 30.0, 4996.5, None).data, vec![false, false]);
    }

    #[test]
    fn the_same_as_the_test_written_plainly() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let range = 4996.5;
        let mut checked = [0usize; 3];
        for round in 0..40 {
            let (w, h) = (rng.random_range(1..40), rng.random_range(1..30));
            let pick = |rng: &mut rand_chacha::ChaCha8Rng| match rng.random_range(0..20) {
                0 => f64::NAN,
                1 => 0.0,
                2 => -5.0,
                3 => f64::INFINITY,
                4 => rng.random_range(4000.0..9000.0),
                _ => rng.random_range(300.0..4900.0),
            };
            let d: Vec<f64> = (0..w * h).map(|_| pick(&mut rng)).collect();
            let b: Vec<f64> = (0..w * h).map(|_| pick(&mut rng)).collect();
            let noise: Vec<f64> = (0..w * h)
                .map(|_| {
                    if rng.random_range(0..8) == 0 {
                        f64::NAN
                    } else {
                        rng.random_range(0.0..40.0)
                    }
                })
                .collect();
            let threshold = rng.random_range(5.0..60.0);
            let (d, b, noise) = (
                ImageBuf::from_vec(w, h, d).unwrap(),
                ImageBuf::from_vec(w, h, b).unwrap(),
                ImageBuf::from_vec(w, h, noise).unwrap(),
            );
            let with_noise = round % 2 == 0;
            let got = changed_pixels(&d, &b, threshold, range, with_noise.then_some(&noise));
            for i in 0..w * h {
                let (x, y) = (d.data[i], b.data[i]);
                let sigma = if with_noise && noise.data[i].is_finite() {
                    noise.data[i]
                } else {
                    0.0
                };
                let plain = x.is_finite()
                    && x > 0.0
                    && y.is_finite()
                    && y > 0.0
                    && wrapped_difference(x, y, range).abs() > threshold.max(NOISE_SIGMAS * sigma);
                assert_eq!(got.data[i], plain, "pixel {i}: {x} against {y}");
                checked[usize::from(plain)] += 1;
                if plain && (x - y).abs() >= range / 2.0 {
                    checked[2] += 1;
                }
            }
        }
        // Changed and unchanged pixels, and changes seen only once wrapped.
        assert!(checked.iter().all(|&c| c > 20), "{checked:?}");
    }

    #[test]
    fn regions_kept_are_those_of_a_plain_labelling() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for _ in 0..30 {
            let (w, h) = (rng.random_range(1..50), rng.random_range(1..40));
            let fill = rng.random_range(0.2..0.7);
            let m = ImageBuf::from_vec(w, h, (0..w * h).map(|_| rng.random_bool(fill)).collect()).unwrap();
            let min = rng.random_range(1..12);
            let (out, kept) = remove_small_regions(&m, min);
            // Labels by repeated relaxation to the smallest index among 4-neighbours.
            let mut label: Vec<usize> = (0..w * h).collect();
            loop {
                let mut moved = false;
                for i in 0..w * h {
                    if !m.data[i] {
                        continue;
                    }
                    let (c, r) = (i % w, i / w);
                    let mut n = vec![];
                    if c > 0 {
                        n.push(i - 1);
                    }
                    if c + 1 < w {
                        n.push(i + 1);
                    }
                    if r > 0 {
                        n.push(i - w);
                    }
                    if r + 1 < h {
                        n.push(i + w);
                    }
                    for j in n {
                        if m.data[j] && label[j] < label[i] {
                            label[i] = label[j];
                            moved = true;
                        }
                    }
                }
                if !moved {
                    break;
                }
            }
            let mut size = std::collections::HashMap::new();
            for i in (0..w * h).filter(|&i| m.data[i]) {
                *size.entry(label[i]).or_insert(0usize) += 1;
            }
            for i in 0..w * h {
                assert_eq!(out.data[i], m.data[i] && size[&label[i]] >= min, "pixel {i}");
            }
            assert_eq!(kept, size.values().filter(|&&s| s >= min).count());
        }
    }

    #[test]
    fn small_regions_go_large_stay() {
        let mut m = ImageBuf::filled(10, 10, false);
        for r in 2..6 {
            for c in 2..6 {
                m.data[r * 10 + c] = true;
            }
        }
        m.data[9 * 10 + 9] = true;
        let (out, kept) = remove_small_regions(&m, 5);
        assert_eq!(kept, 1);
        assert_eq!(out.data.iter().filter(|&&x| x).count(), 16);
        assert!(!out.data[99]);
    }
}
