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
    let data = (0..distance_mm.len())
        .map(|i| {
            let (d, db) = (distance_mm.data[i], background_mm.data[i]);
            let sigma = change_noise_mm
                .map(|n| n.data[i])
                .filter(|s| s.is_finite())
                .unwrap_or(0.0);
            let threshold = threshold_mm.max(NOISE_SIGMAS * sigma);
            valid(d) && valid(db) && wrapped_difference(d, db, range_mm).abs() > threshold
        })
        .collect();
    ImageBuf {
        width: distance_mm.width,
        height: distance_mm.height,
        data,
    }
}

fn valid(d: f64) -> bool {
    d.is_finite() && d > 0.0
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
        stack.push(start);
        seen[start] = true;
        while let Some(i) = stack.pop() {
            region.push(i);
            let (c, r) = (i % w, i / w);
            let mut visit = |j: usize| {
                if mask.data[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if c > 0 {
                visit(i - 1);
            }
            if c + 1 < w {
                visit(i + 1);
            }
            if r > 0 {
                visit(i - w);
            }
            if r + 1 < h {
                visit(i + w);
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
