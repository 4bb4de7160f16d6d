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

/// The change a pixel must exceed to count as changed: `threshold_mm`, or
/// [`NOISE_SIGMAS`] times the pixel's change noise `sigma_mm` where that is larger.
#[inline(always)]
pub fn change_threshold_mm(threshold_mm: f64, sigma_mm: f64) -> f64 {
    threshold_mm.max(NOISE_SIGMAS * if sigma_mm.is_finite() { sigma_mm } else { 0.0 })
}

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
    let threshold = move |sigma: f64| change_threshold_mm(threshold_mm, sigma);
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

/// The mask opened by a 3 x 3 square: what an erosion (a pixel whose eight neighbours are
/// all set) leaves, grown back by one pixel within the mask. Lines and rims under three
/// pixels wide (the mixed pixels along an opaque edge) go; a region's interior and its own
/// rim stay.
pub fn open_mask(mask: &ImageBuf<bool>) -> ImageBuf<bool> {
    let (w, h) = (mask.width, mask.height);
    let at = |x: isize, y: isize| {
        x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h && mask.data[y as usize * w + x as usize]
    };
    let square =
        |x: usize, y: usize| (-1..=1).flat_map(move |dy| (-1..=1).map(move |dx| (x as isize + dx, y as isize + dy)));
    let core: Vec<bool> = (0..w * h)
        .map(|i| square(i % w, i / w).all(|(x, y)| at(x, y)))
        .collect();
    let core_at = |x: isize, y: isize| {
        x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h && core[y as usize * w + x as usize]
    };
    ImageBuf {
        width: w,
        height: h,
        data: (0..w * h)
            .map(|i| mask.data[i] && square(i % w, i / w).any(|(x, y)| core_at(x, y)))
            .collect(),
    }
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

/// Neighbours whose readings differ by more than this many noise sigmas (and
/// [`EDGE_FLOOR_MM`]) belong to different objects: a layer's readings are smooth.
pub const EDGE_SIGMAS: f64 = 3.0;

/// Least reading step between neighbours that separates two regions, mm: what a
/// surface tilted by 60 degrees steps over one pixel at 3 m.
pub const EDGE_FLOOR_MM: f64 = 25.0;

/// The regions of a mask: 4-connected pixels whose readings do not step by more
/// than their noise allows (two objects side by side touch in the image but not
/// in depth). `noise_mm` gives each pixel's reading noise (1 sigma, mm).
///
/// Returns each pixel's region (0 off the mask, else 1-based) and each region's
/// pixel count. Pieces smaller than `min_pixels` join the region they touch most
/// (a noisy pixel must not cut a layer in two); pieces that touch none keep their own label.
pub fn label_regions(
    mask: &ImageBuf<bool>,
    distance_mm: &ImageBuf<f64>,
    noise_mm: impl Fn(usize) -> f64,
    range_mm: f64,
    min_pixels: usize,
) -> (ImageBuf<u32>, Vec<usize>) {
    let (w, h) = (mask.width, mask.height);
    let step = |i: usize, j: usize| wrapped_difference(distance_mm.data[i], distance_mm.data[j], range_mm).abs();
    let joined = |i: usize, j: usize| {
        let (a, b) = (noise_mm(i), noise_mm(j));
        let sigma = (a * a + b * b).sqrt();
        step(i, j) <= EDGE_FLOOR_MM.max(if sigma.is_finite() { EDGE_SIGMAS * sigma } else { 0.0 })
    };
    let neighbours = |i: usize| {
        let c = i % w;
        [
            (c > 0).then(|| i - 1),
            (c + 1 < w).then(|| i + 1),
            (i >= w).then(|| i - w),
            (i + w < w * h).then(|| i + w),
        ]
        .into_iter()
        .flatten()
        .filter(|&j| mask.data[j])
    };
    // Core pixels: joined to every neighbour on the mask. The pixels along an edge between two
    // objects mix both and their readings ramp from one to the other along a slanted edge, so
    // regions grow over core pixels only, and the edge's pixels join the region nearest in reading.
    let core: Vec<bool> = (0..w * h)
        .map(|i| mask.data[i] && neighbours(i).all(|j| joined(i, j)))
        .collect();
    let mut labels = ImageBuf::filled(w, h, 0u32);
    let mut sizes: Vec<usize> = vec![0];
    let mut stack = Vec::new();
    let mut grow = |labels: &mut ImageBuf<u32>, sizes: &mut Vec<usize>, eligible: &dyn Fn(usize) -> bool| {
        for start in 0..w * h {
            if !eligible(start) || labels.data[start] != 0 {
                continue;
            }
            let id = sizes.len() as u32;
            sizes.push(0);
            labels.data[start] = id;
            stack.push(start);
            while let Some(i) = stack.pop() {
                sizes[id as usize] += 1;
                for j in neighbours(i) {
                    if eligible(j) && labels.data[j] == 0 && joined(i, j) {
                        labels.data[j] = id;
                        stack.push(j);
                    }
                }
            }
        }
    };
    grow(&mut labels, &mut sizes, &|i| core[i]);
    // Edge pixels, ring by ring from the cores: the neighbouring region nearest in reading.
    loop {
        let mut assigned = vec![];
        for i in 0..w * h {
            if !mask.data[i] || labels.data[i] != 0 {
                continue;
            }
            let best = neighbours(i)
                .filter(|&j| labels.data[j] != 0)
                .min_by(|&a, &b| step(i, a).total_cmp(&step(i, b)));
            if let Some(j) = best {
                assigned.push((i, labels.data[j]));
            }
        }
        if assigned.is_empty() {
            break;
        }
        for (i, l) in assigned {
            labels.data[i] = l;
            sizes[l as usize] += 1;
        }
    }
    // Whatever touches no core (isolated noisy pixels): pieces of their own.
    grow(&mut labels, &mut sizes, &|i| mask.data[i]);
    merge_small_pieces(&mut labels, &mut sizes, min_pixels);
    renumber(labels, &sizes)
}

/// A piece this small beside a region (a share of that region's pixels) is its fringe: the
/// pixels at a layer's edge mix the layer with what is behind it and step away from it.
pub const FRINGE_SHARE: f64 = 0.1;

/// Pieces under `min_pixels`, or under [`FRINGE_SHARE`] of the larger region they share most
/// borders with, take that region's label.
fn merge_small_pieces(labels: &mut ImageBuf<u32>, sizes: &mut [usize], min_pixels: usize) {
    let (w, h) = (labels.width, labels.height);
    // Repeated: a piece that touches only other small pieces joins once they have joined.
    for _ in 0..4 {
        let mut votes: std::collections::HashMap<u32, std::collections::HashMap<u32, usize>> = Default::default();
        for i in 0..w * h {
            let a = labels.data[i];
            if a == 0 {
                continue;
            }
            let c = i % w;
            let neighbours = [
                (c > 0).then(|| i - 1),
                (c + 1 < w).then(|| i + 1),
                (i >= w).then(|| i - w),
                (i + w < w * h).then(|| i + w),
            ];
            for j in neighbours.into_iter().flatten() {
                let b = labels.data[j];
                if b != 0 && b != a {
                    *votes.entry(a).or_default().entry(b).or_default() += 1;
                }
            }
        }
        let small = |a: u32, b: u32| {
            let (sa, sb) = (sizes[a as usize], sizes[b as usize]);
            (sa, a) < (sb, b) && (sa < min_pixels || (sa as f64) < FRINGE_SHARE * sb as f64)
        };
        let target: std::collections::HashMap<u32, u32> = votes
            .into_iter()
            .filter_map(|(a, v)| {
                let (b, _) = v.into_iter().max_by_key(|&(b, n)| (n, std::cmp::Reverse(b)))?;
                small(a, b).then_some((a, b))
            })
            .collect();
        if target.is_empty() {
            return;
        }
        // A chain a -> b -> c ends where it ends: follow it (sizes strictly grow along it).
        let end = |mut a: u32| {
            while let Some(&b) = target.get(&a) {
                a = b;
            }
            a
        };
        for l in labels.data.iter_mut() {
            if target.contains_key(l) {
                let b = end(*l);
                sizes[b as usize] += 1;
                sizes[*l as usize] -= 1;
                *l = b;
            }
        }
    }
}

/// Labels 1.. in order of first appearance, empty labels dropped; the sizes with them.
fn renumber(mut labels: ImageBuf<u32>, sizes: &[usize]) -> (ImageBuf<u32>, Vec<usize>) {
    let mut new_id = vec![0u32; sizes.len()];
    let mut out_sizes = vec![];
    for l in labels.data.iter_mut() {
        if *l == 0 {
            continue;
        }
        let old = *l as usize;
        if new_id[old] == 0 {
            out_sizes.push(sizes[old]);
            new_id[old] = out_sizes.len() as u32;
        }
        *l = new_id[old];
    }
    (labels, out_sizes)
}

#[cfg(test)]
mod tests {
    #[test]
    fn opening_drops_thin_lines_and_keeps_a_region_with_its_rim() {
        let (w, h) = (20, 12);
        let mut m = ImageBuf::filled(w, h, false);
        for y in 2..8 {
            for x in 2..9 {
                m.data[y * w + x] = true; // a 7 x 6 block
            }
        }
        for x in 11..19 {
            m.data[5 * w + x] = true; // a line one pixel wide
            m.data[6 * w + x] = true; // ... two
        }
        let opened = open_mask(&m);
        for y in 0..h {
            for x in 0..w {
                let block = (2..9).contains(&x) && (2..8).contains(&y);
                assert_eq!(opened.data[y * w + x], block, "({x}, {y})");
            }
        }
    }

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

    #[test]
    fn regions_split_where_the_readings_step_and_small_pieces_join() {
        // Two touching 20x10 patches at 1000 and 1500 mm, and one noisy pixel inside the first.
        let (w, h) = (40, 10);
        let mut d = ImageBuf::filled(w, h, 1000.0);
        for r in 0..h {
            for c in 20..w {
                d.data[r * w + c] = 1500.0 + c as f64;
            }
        }
        d.data[4 * w + 7] = 1100.0;
        let mask = ImageBuf::filled(w, h, true);
        let (labels, sizes) = label_regions(&mask, &d, |_| 5.0, 4996.5, 3);
        assert_eq!(sizes, vec![200, 200]);
        assert!((0..h).all(|r| labels.data[r * w] == 1 && labels.data[r * w + 19] == 1));
        assert_eq!(labels.data[4 * w + 7], 1, "the noisy pixel joins its region");
        assert!((0..h).all(|r| labels.data[r * w + 20] == 2 && labels.data[r * w + w - 1] == 2));
        // A ramp of mixed pixels along the edge does not bridge the two.
        for r in 0..h {
            d.data[r * w + 19] = 1000.0 + 50.0 * r as f64;
            d.data[r * w + 20] = 1050.0 + 50.0 * r as f64;
        }
        let (_, sizes) = label_regions(&mask, &d, |_| 5.0, 4996.5, 3);
        assert_eq!(sizes.len(), 2, "{sizes:?}");
        // With a noise that allows the step, one region.
        let (_, sizes) = label_regions(&mask, &d, |_| 200.0, 4996.5, 3);
        assert_eq!(sizes, vec![400]);
        // Off the mask: 0.
        let mut m = mask.clone();
        m.data[0] = false;
        let (labels, _) = label_regions(&m, &d, |_| 5.0, 4996.5, 3);
        assert_eq!(labels.data[0], 0);
    }
}
