//! Which pixels look through a translucent layer (paper Sec. V-C): those whose
//! reading moved by more than a threshold from the latched background.

use super::buffer::ImageBuf;

/// Default threshold: 3x the SR4000's ~10 mm background noise (the paper's 30 mm).
pub const DEFAULT_THRESHOLD_MM: f64 = 30.0;

/// `|d - db| > threshold_mm` where both readings are valid (finite, > 0).
pub fn changed_pixels(distance_mm: &ImageBuf<f64>, background_mm: &ImageBuf<f64>, threshold_mm: f64) -> ImageBuf<bool> {
    let data = distance_mm
        .data
        .iter()
        .zip(&background_mm.data)
        .map(|(&d, &db)| valid(d) && valid(db) && (d - db).abs() > threshold_mm)
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
        let m = changed_pixels(&d, &b, 30.0);
        assert_eq!(m.data, vec![true, true, false, false]);
        let m = changed_pixels(&d, &b, 31.0);
        assert_eq!(m.data, vec![true, false, false, false]);
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
