//! Which pixels look through a translucent layer (paper Sec. V-C): those whose
//! reading moved by more than a threshold from the latched background.

use super::buffer::ImageBuf;
use super::parallel::map_chunks_ordered;

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
    // By rows over the pool; in each, the common case first, pixel by pixel without branches
    // (a loop the compiler vectorizes): a difference already within half the range is its
    // own wrapped difference. The few valid pixels beyond it are wrapped afterwards.
    let half = range_mm / 2.0;
    // (`move`: the constant copied in, so the loops do not read it back at every pixel.)
    let threshold = move |sigma: f64| change_threshold_mm(threshold_mm, sigma);
    let rows = ROWS_PER_TASK * distance_mm.width.max(1);
    let data = map_chunks_ordered(&distance_mm.data, rows, MIN_PARALLEL_PIXELS, |start, d| {
        let end = start + d.len();
        let mut out = vec![false; d.len()];
        // Readings without their background (an image of another size) stay unchanged.
        let Some(b) = background_mm.data.get(start..end) else {
            return out;
        };
        let noise = change_noise_mm.and_then(|n| n.data.get(start..end));
        let far = match noise {
            Some(n) => changed_within_half(&mut out, d, b, n.iter().map(|&s| threshold(s)), half),
            None => changed_within_half(&mut out, d, b, std::iter::repeat(threshold(0.0)), half),
        };
        if far > 0 {
            for (k, out) in out.iter_mut().enumerate() {
                let (d, db) = (d[k], b[k]);
                if valid(d) & valid(db) & !within_half(d, db, half) {
                    let sigma = noise.map_or(0.0, |n| n[k]);
                    *out = wrapped_difference(d, db, range_mm).abs() > threshold(sigma);
                }
            }
        }
        out
    });
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

/// The holes of labelled regions: each 4-connected piece of unlabelled pixels (label 0) of
/// at most `max_pixels`, off the image's border, every pixel of it `eligible`, whose
/// 8-neighbours outside it all carry one label; each of its pixels with that label. A hole
/// smaller than a region can be is no object of its own: it is the region that surrounds it.
pub fn enclosed_holes(
    labels: &ImageBuf<u32>,
    max_pixels: usize,
    eligible: impl Fn(usize) -> bool,
) -> Vec<(usize, u32)> {
    let (w, h) = (labels.width, labels.height);
    let mut seen = vec![false; w * h];
    let mut holes = Vec::new();
    let mut piece = Vec::new();
    for start in 0..w * h {
        if labels.data[start] != 0 || seen[start] {
            continue;
        }
        piece.clear();
        let mut stack = vec![start];
        seen[start] = true;
        // `None` until a neighbour's label is met; a second label, the border, an ineligible
        // pixel or too large a piece spoil it (the piece is still walked whole, so that none
        // of its pixels starts another).
        let (mut around, mut spoilt) = (None, false);
        while let Some(i) = stack.pop() {
            piece.push(i);
            spoilt |= !eligible(i) || piece.len() > max_pixels;
            let (c, r) = (i % w, i / w);
            if c == 0 || r == 0 || c + 1 == w || r + 1 == h {
                spoilt = true;
            }
            for (dc, dr) in [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)] {
                let (cc, rr) = (c as isize + dc, r as isize + dr);
                if cc < 0 || rr < 0 || cc >= w as isize || rr >= h as isize {
                    continue;
                }
                let j = rr as usize * w + cc as usize;
                match labels.data[j] {
                    0 if (dc == 0 || dr == 0) && !seen[j] => {
                        seen[j] = true;
                        stack.push(j);
                    }
                    0 => {}
                    l if around.is_none_or(|a| a == l) => around = Some(l),
                    _ => spoilt = true,
                }
            }
        }
        if let (Some(l), false) = (around, spoilt) {
            holes.extend(piece.iter().map(|&i| (i, l)));
        }
    }
    holes
}

/// The outline of `mask`: its pixels with an 8-neighbour in the image off it, and with
/// `image_edge` those on the image's own edge too. A layer that runs past the image's edge
/// is not mixed there with anything, but one whose edge runs along it shows no neighbour
/// off it: what a pixel's own evidence decides takes the edge, what trusts the interior
/// (a surface's fit) leaves it out.
pub fn outline_pixels(mask: &ImageBuf<bool>, image_edge: bool) -> ImageBuf<bool> {
    let (w, h) = (mask.width, mask.height);
    let n = mask.data.len();
    if w == 0 || h == 0 || n != w * h {
        return ImageBuf {
            width: w,
            height: h,
            data: vec![false; n],
        };
    }
    // Off the mask somewhere in each pixel's row of three (beyond the image: `image_edge`),
    // then in its column of three such rows: the 3 x 3 square, by rows over the pool.
    // Row `r`'s pixels off the mask or beside one off it; below the image, `image_edge`.
    let row_off = |r: usize, out: &mut [bool]| {
        if r < h {
            off_in_row(&mask.data[r * w..(r + 1) * w], image_edge, out)
        } else {
            out.fill(image_edge)
        }
    };
    // Whole rows per chunk, one result per pixel of the chunk.
    let data = map_chunks_ordered(&mask.data, ROWS_PER_TASK * w, MIN_PARALLEL_PIXELS, |start, chunk| {
        let mut out = vec![false; chunk.len()];
        let (mut up, mut here, mut down) = (vec![false; w], vec![false; w], vec![false; w]);
        for k in 0..chunk.len() / w {
            let r = start / w + k;
            if k == 0 {
                match r.checked_sub(1) {
                    Some(above) => row_off(above, &mut up),
                    None => up.fill(image_edge),
                }
                row_off(r, &mut here);
            } else {
                std::mem::swap(&mut up, &mut here);
                std::mem::swap(&mut here, &mut down);
            }
            row_off(r + 1, &mut down);
            let m = &mask.data[r * w..(r + 1) * w];
            for (c, o) in out[k * w..(k + 1) * w].iter_mut().enumerate() {
                *o = m[c] & (up[c] | here[c] | down[c]);
            }
        }
        out
    });
    ImageBuf {
        width: w,
        height: h,
        data,
    }
}

/// For each pixel of a row: off the row's mask itself or beside a pixel off it (beyond the
/// row's ends: `image_edge`).
fn off_in_row(row: &[bool], image_edge: bool, out: &mut [bool]) {
    let w = row.len();
    for (c, o) in out.iter_mut().enumerate().take(w) {
        let left = if c == 0 { image_edge } else { !row[c - 1] };
        let right = if c + 1 == w { image_edge } else { !row[c + 1] };
        *o = left | !row[c] | right;
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
#[inline(never)] // a stage of its own in `scripts/frame-profile`
pub fn label_regions(
    mask: &ImageBuf<bool>,
    distance_mm: &ImageBuf<f64>,
    noise_mm: impl Fn(usize) -> f64 + Sync,
    range_mm: f64,
    min_pixels: usize,
) -> (ImageBuf<u32>, Vec<usize>) {
    // Each pixel's noise once (a pixel is compared with up to four neighbours).
    let noise: Vec<f64> = map_chunks_ordered(
        &mask.data,
        ROWS_PER_TASK * mask.width.max(1),
        MIN_PARALLEL_PIXELS,
        |start, m| {
            m.iter()
                .enumerate()
                .map(|(k, &on)| if on { noise_mm(start + k) } else { f64::NAN })
                .collect()
        },
    );
    let step = |i: usize, j: usize| wrapped_difference(distance_mm.data[i], distance_mm.data[j], range_mm).abs();
    let joined = |i: usize, j: usize| step(i, j) <= step_allowed(EDGE_FLOOR_MM, noise[i], noise[j]);
    label_regions_by(mask, joined, step, min_pixels)
}

/// The largest step between two neighbours' values (noise `a` and `b`, one standard
/// deviation each) that keeps them in one region: [`EDGE_SIGMAS`] times the noise of the
/// difference, at least `floor`.
pub fn step_allowed(floor: f64, a: f64, b: f64) -> f64 {
    // `a.hypot(b)` without its care for overflow: noise in mm is far from it.
    let sigma = (a * a + b * b).sqrt();
    floor.max(if sigma.is_finite() { EDGE_SIGMAS * sigma } else { 0.0 })
}

/// Rows of the image one task of the pool takes (per-pixel passes of segmentation).
const ROWS_PER_TASK: usize = 16;

/// Fewest pixels for which a per-pixel pass of segmentation is spread over the pool.
const MIN_PARALLEL_PIXELS: usize = 32 * 1024;

/// [`Links`]' link to the next pixel in the row.
const RIGHT: u8 = 1;
/// [`Links`]' link to the pixel below.
const DOWN: u8 = 2;

/// The regions of a mask as [`label_regions`] makes them, with any rule for which neighbours
/// belong together (`joined`, symmetric) and how far apart two neighbours are (`step`, what
/// an edge pixel's nearest region is chosen by).
pub fn label_regions_by(
    mask: &ImageBuf<bool>,
    joined: impl Fn(usize, usize) -> bool + Sync,
    step: impl Fn(usize, usize) -> f64,
    min_pixels: usize,
) -> (ImageBuf<u32>, Vec<usize>) {
    let grid = Links::new(mask, &joined);
    let n = mask.data.len();
    // Core pixels: joined to every neighbour on the mask. The pixels along an edge between two
    // objects mix both and their readings ramp from one to the other along a slanted edge, so
    // regions grow over core pixels only, and the edge's pixels join the region nearest in reading.
    let core: Vec<bool> = map_chunks_ordered(
        &mask.data,
        ROWS_PER_TASK * mask.width.max(1),
        MIN_PARALLEL_PIXELS,
        |start, m| {
            (start..start + m.len())
                .map(|i| {
                    let mut all = mask.data[i];
                    grid.each_neighbour(i, |_, linked| all &= linked);
                    all
                })
                .collect()
        },
    );
    let mut labels = ImageBuf::filled(mask.width, mask.height, 0u32);
    let mut sizes: Vec<usize> = vec![0];
    grid.grow(&mut labels, &mut sizes, |i| core[i]);
    // Edge pixels, ring by ring from the cores: the neighbouring region nearest in reading.
    let mut ring: Vec<usize> = (0..n)
        .filter(|&i| mask.data[i] && labels.data[i] == 0)
        .filter(|&i| {
            let mut beside = false;
            grid.each_neighbour(i, |j, _| beside |= labels.data[j] != 0);
            beside
        })
        .collect();
    while !ring.is_empty() {
        let assigned: Vec<(usize, u32)> = ring
            .iter()
            .filter_map(|&i| {
                let mut best: Option<(f64, usize)> = None;
                grid.each_neighbour(i, |j, _| {
                    if labels.data[j] != 0 {
                        let s = step(i, j);
                        // The first of equals, in the neighbours' order.
                        if best.is_none_or(|(b, _)| s.total_cmp(&b).is_lt()) {
                            best = Some((s, j));
                        }
                    }
                });
                best.map(|(_, j)| (i, labels.data[j]))
            })
            .collect();
        for &(i, l) in &assigned {
            labels.data[i] = l;
            sizes[l as usize] += 1;
        }
        // The next ring: the unlabelled pixels beside this one's, each once, in pixel order.
        ring.clear();
        for &(i, _) in &assigned {
            grid.each_neighbour(i, |j, _| {
                if labels.data[j] == 0 {
                    ring.push(j);
                }
            });
        }
        ring.sort_unstable();
        ring.dedup();
    }
    // Whatever touches no core (isolated noisy pixels): pieces of their own.
    grid.grow(&mut labels, &mut sizes, |i| mask.data[i]);
    merge_small_pieces(&mut labels, &mut sizes, min_pixels);
    renumber(labels, &sizes)
}

/// A mask with each pixel's links to its neighbours on it (which of them belong together).
struct Links<'a> {
    mask: &'a ImageBuf<bool>,
    /// Per pixel: [`RIGHT`] where it is joined to the next pixel of its row, [`DOWN`] to
    /// the one below.
    links: Vec<u8>,
}

impl<'a> Links<'a> {
    /// Every pair judged once by `joined` (symmetric), over the pool by rows.
    fn new(mask: &'a ImageBuf<bool>, joined: &(impl Fn(usize, usize) -> bool + Sync)) -> Self {
        let (w, n) = (mask.width, mask.data.len());
        let links = map_chunks_ordered(&mask.data, ROWS_PER_TASK * w.max(1), MIN_PARALLEL_PIXELS, |start, m| {
            m.iter()
                .enumerate()
                .map(|(k, &on)| {
                    let i = start + k;
                    let right = on && (i % w) + 1 < w && mask.data[i + 1] && joined(i, i + 1);
                    let down = on && i + w < n && mask.data[i + w] && joined(i, i + w);
                    (u8::from(right) * RIGHT) | (u8::from(down) * DOWN)
                })
                .collect()
        });
        Self { mask, links }
    }

    /// `f(j, linked)` for each 4-neighbour `j` of `i` on the mask (left, right, up, down).
    #[inline(always)]
    fn each_neighbour(&self, i: usize, mut f: impl FnMut(usize, bool)) {
        let (w, n, m) = (self.mask.width, self.mask.data.len(), &self.mask.data);
        let c = i % w;
        if c > 0 && m[i - 1] {
            f(i - 1, self.links[i - 1] & RIGHT != 0);
        }
        if c + 1 < w && m[i + 1] {
            f(i + 1, self.links[i] & RIGHT != 0);
        }
        if i >= w && m[i - w] {
            f(i - w, self.links[i - w] & DOWN != 0);
        }
        if i + w < n && m[i + w] {
            f(i + w, self.links[i] & DOWN != 0);
        }
    }

    /// New regions from each `eligible` pixel not yet labelled, grown over linked eligible
    /// neighbours; their sizes pushed onto `sizes`.
    fn grow(&self, labels: &mut ImageBuf<u32>, sizes: &mut Vec<usize>, eligible: impl Fn(usize) -> bool) {
        let mut stack = Vec::new();
        for start in 0..self.mask.data.len() {
            if labels.data[start] != 0 || !eligible(start) {
                continue;
            }
            let id = sizes.len() as u32;
            sizes.push(0);
            labels.data[start] = id;
            stack.push(start);
            while let Some(i) = stack.pop() {
                sizes[id as usize] += 1;
                self.each_neighbour(i, |j, linked| {
                    if linked && labels.data[j] == 0 && eligible(j) {
                        labels.data[j] = id;
                        stack.push(j);
                    }
                });
            }
        }
    }
}

/// Least gap between the readings of two objects that one region chained together, mm.
pub const SPLIT_GAP_FLOOR_MM: f64 = 150.0;

/// Largest share of a region's pixels whose readings lie in the middle third between two
/// modes, for the modes to be two objects: a tilted surface spreads its readings evenly.
pub const SPLIT_VALLEY_SHARE: f64 = 0.05;

/// Splits regions whose readings form two modes far apart while the background behind both
/// is at one distance: two objects at different depths whose edge pixels ramp from one to
/// the other chain into one region through [`label_regions`]' neighbour steps. A layer
/// before a background step (a table's edge behind a sheet) shows two modes too, but there
/// the background steps with the reading, and it stays whole. `background_mm`: the latched
/// background's distance per pixel. Returns the labels and sizes with the far modes as
/// regions of their own.
pub fn split_reading_modes(
    labels: ImageBuf<u32>,
    sizes: Vec<usize>,
    distance_mm: &ImageBuf<f64>,
    background_mm: &ImageBuf<f64>,
    range_mm: f64,
    min_pixels: usize,
) -> (ImageBuf<u32>, Vec<usize>) {
    let (mut labels, mut sizes) = (labels, sizes);
    // A region may chain more than two objects: split the pieces again, a few times.
    for _ in 0..3 {
        let members = Members::of(&labels, sizes.len());
        let mut split_any = false;
        for pixels in (1..=sizes.len()).map(|l| members.of_label(l)) {
            let Some(far) = far_mode(pixels, distance_mm, background_mm, range_mm, min_pixels) else {
                continue;
            };
            sizes.push(far.len());
            let id = sizes.len() as u32;
            let old = labels.data[pixels[0] as usize] as usize;
            sizes[old - 1] -= far.len();
            for i in far {
                labels.data[i as usize] = id;
            }
            split_any = true;
        }
        if !split_any {
            break;
        }
    }
    (labels, sizes)
}

/// Each region's pixels, ascending, the regions one after another in label order: laid
/// out at their counts in two passes over the labels (no list growing per region).
pub struct Members {
    /// The labelled pixels, grouped by label.
    pixels: Vec<u32>,
    /// Where each label's pixels start in `pixels` (label `l` at `start[l]..start[l + 1]`).
    start: Vec<usize>,
}

impl Members {
    /// The members of labels `1..=regions` (a pixel of a larger label is left out).
    pub fn of(labels: &ImageBuf<u32>, regions: usize) -> Self {
        let mut start = vec![0usize; regions + 2];
        for &l in &labels.data {
            if let Some(n) = start.get_mut(l as usize + 1) {
                *n += 1;
            }
        }
        start[1] = 0; // label 0: off the regions, not listed
        for l in 1..start.len() {
            start[l] += start[l - 1];
        }
        let mut next = start.clone();
        let mut pixels = vec![0u32; start[regions + 1]];
        for (i, &l) in labels.data.iter().enumerate() {
            if l != 0 && (l as usize) <= regions {
                // Images are indexed in u32 (`observe` refuses larger ones).
                pixels[next[l as usize]] = i as u32;
                next[l as usize] += 1;
            }
        }
        Self { pixels, start }
    }

    /// The pixels of label `l`, ascending.
    pub fn of_label(&self, l: usize) -> &[u32] {
        &self.pixels[self.start[l]..self.start[l + 1]]
    }
}

/// Width of the reading histogram's bins that [`far_mode`] splits, mm.
const SPLIT_BIN_MM: f64 = 5.0;

/// The pixels of a region's far reading mode, when its readings form two modes that are two
/// objects ([`split_reading_modes`]); `None` when they are one. The modes are found on a
/// histogram of the readings (Otsu's split), so a region costs one pass over its pixels.
fn far_mode(
    pixels: &[u32],
    distance_mm: &ImageBuf<f64>,
    background_mm: &ImageBuf<f64>,
    range_mm: f64,
    min_pixels: usize,
) -> Option<Vec<u32>> {
    let n = pixels.len();
    if n < 2 * min_pixels.max(2) {
        return None;
    }
    let centre = distance_mm.data[pixels[n / 2] as usize];
    let unwrapped = |i: u32| centre + wrapped_difference(distance_mm.data[i as usize], centre, range_mm);
    let (lo, hi) = pixels
        .iter()
        .map(|&i| unwrapped(i))
        .filter(|x| x.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |a, x| (a.0.min(x), a.1.max(x)));
    if hi - lo < SPLIT_GAP_FLOOR_MM {
        return None;
    }
    let bin = SPLIT_BIN_MM.max((hi - lo) / 4096.0);
    let mut hist = vec![0usize; ((hi - lo) / bin) as usize + 1];
    for &i in pixels {
        let x = unwrapped(i);
        if x.is_finite() {
            hist[((x - lo) / bin) as usize] += 1;
        }
    }
    let at = |k: f64| lo + (k + 0.5) * bin;
    let k = otsu_split(&hist)?;
    let (near, far) = hist.split_at(k);
    let (n_near, n_far) = (near.iter().sum::<usize>(), far.iter().sum::<usize>());
    let least = min_pixels.max((FRINGE_SHARE * n as f64).ceil() as usize);
    if n_near < least || n_far < least {
        return None;
    }
    let (m_near, s_near) = histogram_centre_spread(near)?;
    let (m_far, s_far) = histogram_centre_spread(far)?;
    let (m_near, m_far) = (at(m_near), at(k as f64 + m_far));
    let gap = m_far - m_near;
    if gap < SPLIT_GAP_FLOOR_MM.max(3.0 * bin * s_near.max(s_far)) {
        return None;
    }
    let (v_lo, v_hi) = (m_near + gap / 3.0, m_far - gap / 3.0);
    let valley: usize = (0..hist.len())
        .filter(|&j| at(j as f64) > v_lo && at(j as f64) < v_hi)
        .map(|j| hist[j])
        .sum();
    if valley as f64 > SPLIT_VALLEY_SHARE * n as f64 {
        return None;
    }
    let split = lo + k as f64 * bin;
    let (near_px, far_px): (Vec<u32>, Vec<u32>) = pixels.iter().partition(|&&i| !(unwrapped(i) >= split));
    let behind = |side: &[u32]| {
        let mut v: Vec<f64> = side
            .iter()
            .map(|&i| background_mm.data[i as usize])
            .filter(|d| d.is_finite())
            .collect();
        Some(crate::physics::stats::median_select(&mut v)).filter(|m| m.is_finite())
    };
    let (b_near, b_far) = (behind(&near_px)?, behind(&far_px)?);
    if wrapped_difference(b_far, b_near, range_mm).abs() > 0.5 * gap {
        return None;
    }
    Some(far_px)
}

/// Where a histogram splits best into two classes (Otsu: the largest between-class
/// variance); the first bin of the far class.
fn otsu_split(hist: &[usize]) -> Option<usize> {
    let total: f64 = hist.iter().map(|&c| c as f64).sum();
    let moment: f64 = hist.iter().enumerate().map(|(j, &c)| j as f64 * c as f64).sum();
    let (mut best, mut best_k, mut count, mut sum) = (0.0, None, 0.0, 0.0);
    for k in 1..hist.len() {
        count += hist[k - 1] as f64;
        sum += (k - 1) as f64 * hist[k - 1] as f64;
        let rest = total - count;
        if count == 0.0 || rest == 0.0 {
            continue;
        }
        let between = count * rest * (sum / count - (moment - sum) / rest).powi(2);
        if between > best {
            (best, best_k) = (between, Some(k));
        }
    }
    best_k
}

/// A histogram's median bin and its spread (the interquartile range as a normal sigma), in
/// bins.
fn histogram_centre_spread(hist: &[usize]) -> Option<(f64, f64)> {
    let total: usize = hist.iter().sum();
    if total == 0 {
        return None;
    }
    let quantile = |q: f64| {
        let target = q * total as f64;
        let mut seen = 0.0;
        for (j, &c) in hist.iter().enumerate() {
            seen += c as f64;
            if seen >= target {
                return j as f64;
            }
        }
        (hist.len() - 1) as f64
    };
    Some((quantile(0.5), (quantile(0.75) - quantile(0.25)) / 1.349))
}

/// A piece this small beside a region (a share of that region's pixels) is its fringe: the
/// pixels at a layer's edge mix the layer with what is behind it and step away from it.
pub const FRINGE_SHARE: f64 = 0.1;

/// Pieces under `min_pixels`, or under [`FRINGE_SHARE`] of the larger region they share most
/// borders with, take that region's label.
fn merge_small_pieces(labels: &mut ImageBuf<u32>, sizes: &mut [usize], min_pixels: usize) {
    // Repeated: a piece that touches only other small pieces joins once they have joined.
    for _ in 0..4 {
        // Each piece's borders with others, in pixel pairs: (piece, other, pairs).
        let borders = border_counts(labels);
        let small = |a: u32, b: u32| {
            let (sa, sb) = (sizes[a as usize], sizes[b as usize]);
            (sa, a) < (sb, b) && (sa < min_pixels || (sa as f64) < FRINGE_SHARE * sb as f64)
        };
        // Each piece's label after this round (itself where it stays).
        let mut target: Vec<u32> = (0..sizes.len() as u32).collect();
        let mut any = false;
        for piece in borders.chunk_by(|x, y| x.0 == y.0) {
            // The most shared border; of equals, the smaller label.
            let Some(&(a, b, _)) = piece.iter().max_by_key(|&&(_, b, n)| (n, std::cmp::Reverse(b))) else {
                continue;
            };
            if small(a, b) {
                target[a as usize] = b;
                any = true;
            }
        }
        if !any {
            return;
        }
        // A chain a -> b -> c ends where it ends: follow it (sizes strictly grow along it).
        let end = |mut a: u32| {
            while target[a as usize] != a {
                a = target[a as usize];
            }
            a
        };
        let ends: Vec<u32> = (0..sizes.len() as u32).map(end).collect();
        for l in labels.data.iter_mut() {
            let b = ends[*l as usize];
            if b != *l {
                sizes[b as usize] += 1;
                sizes[*l as usize] -= 1;
                *l = b;
            }
        }
    }
}

/// The borders between labelled pieces: for each ordered pair of labels (both non-zero) the
/// 4-neighbour pixel pairs between them, sorted by label pair.
fn border_counts(labels: &ImageBuf<u32>) -> Vec<(u32, u32, usize)> {
    let (w, n) = (labels.width, labels.data.len());
    let mut pairs: Vec<(u32, u32)> = vec![];
    for i in 0..n {
        let a = labels.data[i];
        if a == 0 {
            continue;
        }
        let right = ((i % w) + 1 < w).then(|| labels.data[i + 1]);
        let down = (i + w < n).then(|| labels.data[i + w]);
        for b in [right, down].into_iter().flatten() {
            if b != 0 && b != a {
                pairs.extend([(a, b), (b, a)]);
            }
        }
    }
    pairs.sort_unstable();
    let mut out: Vec<(u32, u32, usize)> = vec![];
    for (a, b) in pairs {
        match out.last_mut() {
            Some(last) if (last.0, last.1) == (a, b) => last.2 += 1,
            _ => out.push((a, b, 1)),
        }
    }
    out
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
    fn members_list_each_region_in_pixel_order() {
        let labels = ImageBuf::from_vec(4, 2, vec![0, 2, 1, 2, 1, 0, 3, 2]).unwrap();
        let m = super::Members::of(&labels, 3);
        assert_eq!(m.of_label(1), &[2, 4]);
        assert_eq!(m.of_label(2), &[1, 3, 7]);
        assert_eq!(m.of_label(3), &[6]);
        // Labels past the regions asked for are left out.
        let m = super::Members::of(&labels, 2);
        assert_eq!((m.of_label(1), m.of_label(2)), (&[2u32, 4][..], &[1u32, 3, 7][..]));
        assert_eq!(m.pixels.len(), 5);
    }

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
    fn the_outline_is_the_masks_pixels_beside_others_and_the_images_edge_when_asked() {
        let (w, h) = (6, 5);
        let mut m = ImageBuf::filled(w, h, false);
        for y in 0..4 {
            for x in 0..4 {
                m.data[y * w + x] = true; // a 4 x 4 block in the corner
            }
        }
        let (edge, with_image_edge) = (outline_pixels(&m, false), outline_pixels(&m, true));
        for y in 0..h {
            for x in 0..w {
                // Off the mask beside it: column 4 and row 4; the image's edge at column 0 and
                // row 0 only when asked for.
                let beside = m.data[y * w + x] && (x == 3 || y == 3);
                assert_eq!(edge.data[y * w + x], beside, "({x}, {y})");
                let at_edge = m.data[y * w + x] && (x == 0 || y == 0);
                assert_eq!(with_image_edge.data[y * w + x], beside || at_edge, "({x}, {y})");
            }
        }
    }

    #[test]
    fn holes_of_one_region_are_filled_and_nothing_else() {
        let (w, h) = (12, 10);
        let mut l = ImageBuf::filled(w, h, 0u32);
        for y in 1..8 {
            for x in 1..7 {
                l.data[y * w + x] = 1; // region 1, 6 x 7
            }
        }
        for y in 1..8 {
            for x in 7..11 {
                l.data[y * w + x] = 2; // region 2 beside it
            }
        }
        let (hole, big, seam, barred) = (3 * w + 3, [5 * w + 2, 5 * w + 3, 5 * w + 4], 6 * w + 7, 2 * w + 5);
        l.data[hole] = 0; // one pixel inside region 1
        for i in big {
            l.data[i] = 0; // three in a row inside region 1
        }
        l.data[seam] = 0; // on the seam of 1 and 2
        l.data[barred] = 0; // inside 1, but not eligible
        let holes = enclosed_holes(&l, 3, |i| i != barred);
        let mut want: Vec<(usize, u32)> = [hole].into_iter().chain(big).map(|i| (i, 1)).collect();
        want.sort_unstable();
        let mut got = holes.clone();
        got.sort_unstable();
        assert_eq!(got, want);
        // Too large a piece is no hole.
        let small = enclosed_holes(&l, 2, |i| i != barred);
        assert_eq!(small, vec![(hole, 1)]);
        // The background outside (touching the border) never is.
        assert!(holes.iter().all(|&(i, _)| l.data[i] == 0 && i != 0));
    }

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

    /// A 40 x 20 mask, all one region, with readings and background per column.
    fn one_region(reading: impl Fn(usize) -> f64, background: impl Fn(usize) -> f64) -> Vec<usize> {
        let (w, h) = (40, 20);
        let d = ImageBuf::from_vec(w, h, (0..w * h).map(|i| reading(i % w)).collect()).unwrap();
        let b = ImageBuf::from_vec(w, h, (0..w * h).map(|i| background(i % w)).collect()).unwrap();
        let labels = ImageBuf::filled(w, h, 1u32);
        let (labels, sizes) = split_reading_modes(labels, vec![w * h], &d, &b, 4996.5, 10);
        assert_eq!(sizes.iter().sum::<usize>(), w * h);
        assert_eq!(sizes.len(), labels.data.iter().copied().max().unwrap() as usize);
        sizes
    }

    #[test]
    fn two_objects_chained_by_a_ramp_split_and_one_surface_does_not() {
        // A near sheet (columns 0-27) and a far one (30-39) before one wall, their edge
        // pixels ramping between them: two objects.
        let ramp = |c: usize| match c {
            0..28 => 1030.0 + (c % 3) as f64 * 5.0,
            28 => 1200.0,
            29 => 1500.0,
            _ => 1800.0 + (c % 4) as f64 * 40.0,
        };
        assert_eq!(one_region(ramp, |_| 3390.0), vec![580, 220]);
        // A surface tilted steeply: its readings spread evenly, one object.
        assert_eq!(one_region(|c| 1000.0 + 25.0 * c as f64, |_| 3390.0), vec![800]);
        // A layer before a background step (a table's edge behind it): its reading steps with
        // the background, one object.
        let step = |c: usize| if c < 20 { 2000.0 } else { 3400.0 };
        assert_eq!(one_region(|c| 0.9 * step(c) + 100.0, step), vec![800]);
    }

    /// [`label_regions_by`] written plainly: every neighbour pair judged where it is met, and
    /// each ring of edge pixels found by a scan of the whole image.
    fn plain_label_regions_by(
        mask: &ImageBuf<bool>,
        joined: impl Fn(usize, usize) -> bool,
        step: impl Fn(usize, usize) -> f64,
        min_pixels: usize,
    ) -> (ImageBuf<u32>, Vec<usize>) {
        let (w, h) = (mask.width, mask.height);
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
        plain_merge_small_pieces(&mut labels, &mut sizes, min_pixels);
        renumber(labels, &sizes)
    }

    /// `merge_small_pieces` written plainly, with maps of votes.
    fn plain_merge_small_pieces(labels: &mut ImageBuf<u32>, sizes: &mut [usize], min_pixels: usize) {
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

    #[test]
    fn labels_are_those_of_the_plain_labelling() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for _ in 0..40 {
            let (w, h) = (rng.random_range(1..60), rng.random_range(1..50));
            let fill = rng.random_range(0.3..1.0);
            let m = ImageBuf::from_vec(w, h, (0..w * h).map(|_| rng.random_bool(fill)).collect()).unwrap();
            // Patches at a few depths, with noise and steps: cores, edges and small pieces.
            let base: Vec<f64> = (0..4).map(|_| rng.random_range(500.0..3000.0)).collect();
            let d = ImageBuf::from_vec(
                w,
                h,
                (0..w * h)
                    .map(|i| base[(i % w * 3 / w.max(1) + i / w * 2 / h.max(1)) % 4] + rng.random_range(-40.0..40.0))
                    .collect(),
            )
            .unwrap();
            let noise: Vec<f64> = (0..w * h).map(|_| rng.random_range(2.0..15.0)).collect();
            let min = rng.random_range(1..20);
            let step = |i: usize, j: usize| wrapped_difference(d.data[i], d.data[j], 4996.5).abs();
            let joined = |i: usize, j: usize| step(i, j) <= step_allowed(EDGE_FLOOR_MM, noise[i], noise[j]);
            let fast = label_regions_by(&m, joined, step, min);
            let plain = plain_label_regions_by(&m, joined, step, min);
            assert_eq!(fast.1, plain.1);
            assert_eq!(fast.0.data, plain.0.data);
        }
    }
}
