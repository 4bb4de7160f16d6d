//! Plane fits over 3D points: the white calibration plane (Eq. 13), and the
//! smooth-surface prior on a recovered layer (local planes over a window).

use nalgebra::{Matrix3, SMatrix, SVector, SymmetricEigen, Vector3};
use rayon::prelude::*;

use super::buffer::ImageBuf;
use super::stats::{median_select, sigma_about};

/// A plane `normal . p = offset`, with the fit's spread.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Unit normal, oriented toward the camera (negative z component).
    pub normal: Vector3<f64>,
    /// `normal . p` for points on the plane, mm.
    pub offset: f64,
    /// RMS of the orthogonal residuals of the points kept, mm.
    pub rms_mm: f64,
    /// Points kept by the fit.
    pub count: usize,
    /// Standard error of the normal's direction, radians (NaN when the fit does not say).
    pub normal_sigma_rad: f64,
}

impl Plane {
    /// Distance along the unit ray `u` to the plane, if it hits in front.
    pub fn ray_distance(&self, u: &Vector3<f64>) -> Option<f64> {
        let den = self.normal.dot(u);
        if den.abs() < 1e-9 {
            return None;
        }
        let t = self.offset / den;
        (t > 0.0).then_some(t)
    }

    /// `|cos|` of the angle between the plane's normal and the unit ray `u`.
    pub fn incidence_cos(&self, u: &Vector3<f64>) -> f64 {
        self.normal.dot(u).abs()
    }
}

/// Least-squares (orthogonal) plane through weighted points.
pub fn fit_plane_weighted(points: &[(Vector3<f64>, f64)]) -> Option<Plane> {
    let wsum: f64 = points.iter().map(|p| p.1).sum();
    if points.len() < 3 || wsum <= 0.0 {
        return None;
    }
    let c = points.iter().fold(Vector3::zeros(), |a, (p, w)| a + p * *w) / wsum;
    let mut cov = Matrix3::zeros();
    for (p, w) in points {
        let d = p - c;
        cov += d * d.transpose() * *w;
    }
    let eig = SymmetricEigen::new(cov / wsum);
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .fold((0, f64::INFINITY), |b, (i, &v)| if v < b.1 { (i, v) } else { b });
    let mut n: Vector3<f64> = eig.eigenvectors.column(imin).into_owned();
    // The two larger eigenvalues must span a plane, not a line.
    let mut ev: Vec<f64> = eig.eigenvalues.iter().copied().collect();
    ev.sort_by(f64::total_cmp);
    if !(ev[1] > 1e-12) || !n.iter().all(|v| v.is_finite()) {
        return None;
    }
    if n.z > 0.0 {
        n = -n;
    }
    let offset = n.dot(&c);
    let rms = (ev[0].max(0.0)).sqrt();
    Some(Plane {
        normal: n,
        offset,
        rms_mm: rms,
        count: points.len(),
        normal_sigma_rad: f64::NAN,
    })
}

/// A plane fit that drops points farther than `k` times the RMS (and at
/// least `floor_mm`) from the previous fit, `passes` times.
pub fn fit_plane_robust(points: &[Vector3<f64>], k: f64, floor_mm: f64, passes: usize) -> Option<Plane> {
    let mut kept: Vec<(Vector3<f64>, f64)> = points.iter().map(|p| (*p, 1.0)).collect();
    let mut plane = fit_plane_weighted(&kept)?;
    for _ in 0..passes {
        let cut = (k * plane.rms_mm).max(floor_mm);
        let next: Vec<(Vector3<f64>, f64)> = points
            .iter()
            .filter(|p| (plane.normal.dot(p) - plane.offset).abs() <= cut)
            .map(|p| (*p, 1.0))
            .collect();
        if next.len() == kept.len() || next.len() < 3 {
            break;
        }
        kept = next;
        plane = fit_plane_weighted(&kept)?;
    }
    Some(plane)
}

/// A plane through points whose noise lies along the camera's rays (depth
/// noise): ordinary least squares of the inverse depth `1/z = alpha x/z +
/// beta y/z + gamma`, exact for a plane (`(alpha, beta, gamma) . p = 1`), with
/// residuals weighted to millimetres of z. Unlike an orthogonal fit it stays
/// right when the depth noise is as large as the window (a small window on a
/// noisy layer). Points farther than `k` times the RMS (at least `floor_mm`)
/// are dropped and the fit repeated, `passes` times.
pub fn fit_plane_along_rays(points: &[Vector3<f64>], k: f64, floor_mm: f64, passes: usize) -> Option<Plane> {
    let robust = Robust { k, floor_mm, passes };
    fit_inverse_depth(
        points,
        (0.0, 0.0),
        |a, b| SVector::<f64, 3>::from([1.0, a, b]),
        3,
        &robust,
    )
}

/// The plane tangent, at the ray `center` (a unit or z = 1 ray), to a smooth
/// surface through points with depth noise along the rays: a quadric in
/// inverse depth, `1/z = c0 + c1 a + c2 b + c3 a^2 + c4 a b + c5 b^2` with
/// `(a, b)` the image coordinates relative to the centre ray, fitted like
/// [`fit_plane_along_rays`]. Unbiased on curved layers (a cylinder) where a
/// plane over the same window is not; `None` with fewer than 10 points or a
/// degenerate window.
pub fn fit_tangent_plane_along_rays(
    points: &[Vector3<f64>],
    center: &Vector3<f64>,
    k: f64,
    floor_mm: f64,
    passes: usize,
) -> Option<Plane> {
    if center.z <= 0.0 {
        return None;
    }
    let robust = Robust { k, floor_mm, passes };
    let quadric = |a: f64, b: f64| SVector::<f64, 6>::from([1.0, a, b, a * a, a * b, b * b]);
    fit_inverse_depth(points, (center.x / center.z, center.y / center.z), quadric, 10, &robust)
}

/// Outlier rejection of the fits along the rays.
struct Robust {
    k: f64,
    floor_mm: f64,
    passes: usize,
}

/// Weighted least squares of the inverse depth on `terms(a, b)` (whose first
/// three are `1, a, b`) in image coordinates `(a, b) = (x/z, y/z) - centre`,
/// with weights `z^4` so residuals are millimetres of z; returns the tangent
/// plane at the centre, `1/z = c0 + c1 (a - a0) + c2 (b - b0)`.
fn fit_inverse_depth<const N: usize>(
    points: &[Vector3<f64>],
    (a0, b0): (f64, f64),
    terms: impl Fn(f64, f64) -> SVector<f64, N>,
    min_points: usize,
    robust: &Robust,
) -> Option<Plane> {
    // Each point's row, weight and right-hand side once (the passes only drop points).
    struct Term<const N: usize> {
        row: SVector<f64, N>,
        z: f64,
        w: f64,
        rhs: f64,
        keep: bool,
        resid: f64,
    }
    let mut t: Vec<Term<N>> = points
        .iter()
        .map(|p| {
            let z2 = p.z * p.z;
            let w = z2 * z2; // d(1/z) = dz / z^2
            Term {
                row: terms(p.x / p.z - a0, p.y / p.z - b0),
                z: p.z,
                w,
                rhs: w / p.z,
                keep: p.z > 0.0 && p.iter().all(|v| v.is_finite()),
                resid: 0.0,
            }
        })
        .collect();
    // The normal equations, upper triangle only (the matrix is symmetric), in plain arrays:
    // built once over every point, then each pass takes out the points it drops (a
    // downdate) instead of summing the kept ones again.
    let mut acc = [[0.0f64; N]; N];
    let mut atb = SVector::<f64, N>::zeros();
    let mut n = 0;
    let add = |acc: &mut [[f64; N]; N], atb: &mut SVector<f64, N>, p: &Term<N>, sign: f64| {
        let r: [f64; N] = p.row.into();
        let w = sign * p.w;
        for (j, col) in acc.iter_mut().enumerate() {
            let rw = r[j] * w;
            for (i, a) in col.iter_mut().enumerate().take(j + 1) {
                *a += r[i] * rw;
            }
        }
        *atb += p.row * (sign * p.rhs);
    };
    for p in t.iter().filter(|p| p.keep) {
        add(&mut acc, &mut atb, p, 1.0);
        n += 1;
    }
    let mut plane = None;
    for pass in 0..=robust.passes {
        let ata = SMatrix::<f64, N, N>::from_fn(|i, j| if i <= j { acc[j][i] } else { acc[i][j] });
        if n < min_points {
            return plane;
        }
        let inv = ata.try_inverse()?;
        let c = inv * atb;
        if !c.iter().all(|v| v.is_finite()) || c[0] <= 0.0 {
            return plane;
        }
        let mut ss = 0.0;
        for p in t.iter_mut().filter(|p| p.keep) {
            p.resid = (p.z - 1.0 / p.row.dot(&c)).abs();
            ss += p.resid.powi(2);
        }
        let rms = (ss / n as f64).sqrt();
        // The tangent plane coef . p = 1, its unit normal toward the camera.
        let coef = Vector3::new(c[1], c[2], c[0] - c[1] * a0 - c[2] * b0);
        let norm = coef.norm();
        let (normal, offset) = if coef.z > 0.0 {
            (-coef / norm, -1.0 / norm)
        } else {
            (coef / norm, 1.0 / norm)
        };
        // Residuals are in z units under the z^4 weights, so Cov(c) = sigma^2 (A^T W A)^-1;
        // the normal turns by d(c1, c2) / c0.
        let sigma = (ss / n.saturating_sub(N).max(1) as f64).sqrt(); // residual scale, N terms fitted
        let normal_sigma_rad = sigma * (inv[(1, 1)] + inv[(2, 2)]).max(0.0).sqrt() / c[0];
        plane = Some(Plane {
            normal,
            offset,
            rms_mm: rms,
            count: n,
            normal_sigma_rad,
        });
        if pass == robust.passes {
            break;
        }
        let cut = (robust.k * rms).max(robust.floor_mm);
        let mut changed = false;
        for p in t.iter_mut() {
            if p.keep && p.resid > cut {
                p.keep = false;
                add(&mut acc, &mut atb, p, -1.0);
                n -= 1;
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    plane
}

/// Local planes whose window grows until the normal is known to
/// `max_normal_sigma_rad` (noisy layers need wide windows, curved ones narrow):
/// for each pixel the first of `radii` (ascending) that reaches it, else the widest.
pub fn local_planes_adaptive(
    points: &ImageBuf<Vector3<f64>>,
    rays: &ImageBuf<Vector3<f64>>,
    mask: &ImageBuf<bool>,
    radii: &[usize],
    min_points: usize,
    max_normal_sigma_rad: f64,
) -> ImageBuf<Option<Plane>> {
    let plane_at = |i: usize| {
        if !mask.data[i] || !points.data[i].x.is_finite() {
            return None;
        }
        let mut out = None;
        for (k, &r) in radii.iter().enumerate() {
            if let Some(p) = local_plane_at(points, rays, mask, i, r, min_points) {
                out = Some(p);
                if k + 1 == radii.len() || p.normal_sigma_rad <= max_normal_sigma_rad {
                    break;
                }
            }
        }
        out
    };
    ImageBuf {
        width: points.width,
        height: points.height,
        data: (0..points.len())
            .into_par_iter()
            .with_min_len(64)
            .map(plane_at)
            .collect(),
    }
}

/// Local planes over a `(2 radius + 1)^2` window: for every pixel where
/// `mask` holds, the robust tangent plane (fitted along the rays, see
/// [`fit_tangent_plane_along_rays`]) at the pixel's ray `rays`
/// through the masked neighbours' points (`None` with fewer than
/// `min_points`). The smooth-surface prior: a noisy per-pixel depth is
/// replaced by its neighbourhood's plane.
pub fn local_planes(
    points: &ImageBuf<Vector3<f64>>,
    rays: &ImageBuf<Vector3<f64>>,
    mask: &ImageBuf<bool>,
    radius: usize,
    min_points: usize,
) -> ImageBuf<Option<Plane>> {
    // Pixels in parallel over the current rayon pool.
    let data = (0..points.len())
        .into_par_iter()
        .with_min_len(64)
        .map(|i| {
            if mask.data[i] {
                local_plane_at(points, rays, mask, i, radius, min_points)
            } else {
                None
            }
        })
        .collect();
    ImageBuf {
        width: points.width,
        height: points.height,
        data,
    }
}

/// Refits, after the points at `changed` moved, exactly the planes of
/// [`local_planes`] whose window holds one of them (the others' windows are
/// unchanged): the same planes as a full recomputation, at the cost of the
/// windows touched.
pub fn update_local_planes(
    planes: &mut ImageBuf<Option<Plane>>,
    points: &ImageBuf<Vector3<f64>>,
    rays: &ImageBuf<Vector3<f64>>,
    mask: &ImageBuf<bool>,
    radius: usize,
    min_points: usize,
    changed: &[usize],
) {
    let (w, h) = (points.width, points.height);
    let mut touched = vec![false; points.len()];
    for &i in changed {
        let (col, row) = (i % w, i / w);
        for r in row.saturating_sub(radius)..(row + radius + 1).min(h) {
            for c in col.saturating_sub(radius)..(col + radius + 1).min(w) {
                touched[r * w + c] = mask.data[r * w + c];
            }
        }
    }
    let redo: Vec<usize> = (0..points.len()).filter(|&i| touched[i]).collect();
    let fits: Vec<Option<Plane>> = redo
        .par_iter()
        .with_min_len(64)
        .map(|&i| local_plane_at(points, rays, mask, i, radius, min_points))
        .collect();
    for (i, p) in redo.into_iter().zip(fits) {
        planes.data[i] = p;
    }
}

/// Keeps the points whose distance from the camera lies within `k` robust
/// standard deviations (1.4826 MAD, at least `floor_mm`) of the median.
fn keep_near_median(points: &mut Vec<Vector3<f64>>, k: f64, floor_mm: f64) {
    if points.len() < 3 {
        return;
    }
    let norms: Vec<f64> = points.iter().map(|p| p.norm()).collect();
    let med = median_select(&mut norms.clone());
    // Every point within the floor of the median is kept whatever the spread: no need
    // to measure it (the common case on a smooth layer).
    let (lo, hi) = norms
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
    if med - lo <= floor_mm && hi - med <= floor_mm {
        return;
    }
    let cut = (k * sigma_about(&norms, med)).max(floor_mm);
    let mut i = 0;
    points.retain(|_| {
        i += 1;
        (norms[i - 1] - med).abs() <= cut
    });
}

/// The plane through the masked, finite points in the window around pixel `i`.
fn local_plane_at(
    points: &ImageBuf<Vector3<f64>>,
    rays: &ImageBuf<Vector3<f64>>,
    mask: &ImageBuf<bool>,
    i: usize,
    radius: usize,
    min_points: usize,
) -> Option<Plane> {
    let (w, h) = (points.width, points.height);
    let (col, row) = (i % w, i / w);
    let mut window = Vec::with_capacity((2 * radius + 1).pow(2));
    for r in row.saturating_sub(radius)..(row + radius + 1).min(h) {
        for c in col.saturating_sub(radius)..(col + radius + 1).min(w) {
            let j = r * w + c;
            if mask.data[j] && points.data[j].x.is_finite() {
                window.push(points.data[j]);
            }
        }
    }
    // A least-squares start is only as good as its worst points: drop those far from the
    // window's median distance first (pixels of another surface that joined the region).
    keep_near_median(&mut window, 4.0, 20.0);
    if window.len() < min_points.max(3) {
        return None;
    }
    // The tangent to a quadric where the window allows it (curved layers), else a plane.
    fit_tangent_plane_along_rays(&window, &rays.data[i], 2.5, 1.0, 2)
        .or_else(|| fit_plane_along_rays(&window, 2.5, 1.0, 2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fits_a_tilted_plane_and_rejects_an_outlier() {
        let n = Vector3::new(0.2, -0.1, -1.0).normalize();
        let mut pts = vec![];
        for i in 0..10 {
            for j in 0..10 {
                let (x, y) = (i as f64 * 10.0 - 50.0, j as f64 * 10.0 - 50.0);
                // n . p = -1000 -> z from x, y
                let z = (-1000.0 - n.x * x - n.y * y) / n.z;
                pts.push(Vector3::new(x, y, z));
            }
        }
        pts[17].z += 300.0;
        let p = fit_plane_robust(&pts, 3.0, 1.0, 3).unwrap();
        assert!((p.normal - n).norm() < 1e-6, "{:?}", p.normal);
        assert!((p.offset + 1000.0).abs() < 1e-6);
        assert_eq!(p.count, 99);
        let u = Vector3::new(0.0, 0.0, 1.0);
        assert!((p.ray_distance(&u).unwrap() - 1000.0 / n.z.abs()).abs() < 1e-6);
    }

    #[test]
    fn fit_along_rays_survives_depth_noise_larger_than_the_window() {
        // A 20 mm wide patch at 500 mm with +-15 mm depth noise along the rays:
        // an orthogonal fit tips over, the inverse-depth fit does not.
        let n_true = Vector3::new(0.1, 0.0, -1.0).normalize();
        let offset = n_true.dot(&Vector3::new(0.0, 0.0, 500.0));
        let mut pts = vec![];
        let mut k = 0u32;
        for i in -4..=4 {
            for j in -4..=4 {
                let u = Vector3::new(i as f64 * 0.005, j as f64 * 0.005, 1.0).normalize();
                let t = offset / n_true.dot(&u);
                k = k.wrapping_mul(1103515245).wrapping_add(12345);
                let noise = ((k >> 16) % 31) as f64 - 15.0;
                pts.push(u * (t + noise));
            }
        }
        let p = fit_plane_along_rays(&pts, 3.0, 1.0, 2).unwrap();
        let centre = Vector3::new(0.0, 0.0, 1.0);
        assert!((p.ray_distance(&centre).unwrap() - offset / n_true.dot(&centre)).abs() < 4.0);
        assert!(p.normal.z < -0.9, "{:?}", p.normal);
    }

    #[test]
    fn updating_moved_windows_equals_refitting_all() {
        // A noisy tilted plane under a masked region; move a few points, then compare the
        // windowed update with a full recomputation, plane for plane.
        let (w, h) = (40usize, 30usize);
        let rays = ImageBuf {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| Vector3::new((i % w) as f64 * 0.004 - 0.08, (i / w) as f64 * 0.004 - 0.06, 1.0).normalize())
                .collect(),
        };
        let mask = ImageBuf {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| (3..37).contains(&(i % w)) && (2..27).contains(&(i / w)))
                .collect(),
        };
        let mut k = 7u32;
        let mut points = ImageBuf {
            width: w,
            height: h,
            data: rays
                .data
                .iter()
                .map(|u| {
                    k = k.wrapping_mul(1103515245).wrapping_add(12345);
                    u * (800.0 + 300.0 * u.x + ((k >> 16) % 21) as f64 - 10.0)
                })
                .collect(),
        };
        let mut planes = local_planes(&points, &rays, &mask, 3, 12);
        let moved = [5 * w + 6, 15 * w + 20, 16 * w + 20, 26 * w + 36];
        for &i in &moved {
            points.data[i] *= 1.2;
        }
        update_local_planes(&mut planes, &points, &rays, &mask, 3, 12, &moved);
        let full = local_planes(&points, &rays, &mask, 3, 12);
        assert_eq!(planes.data, full.data);
        // The update did refit: the planes before the move differ somewhere.
        let before = local_planes(
            &ImageBuf {
                width: w,
                height: h,
                data: points
                    .data
                    .iter()
                    .enumerate()
                    .map(|(i, p)| if moved.contains(&i) { p / 1.2 } else { *p })
                    .collect(),
            },
            &rays,
            &mask,
            3,
            12,
        );
        assert_ne!(before.data, full.data);
    }

    #[test]
    fn collinear_points_have_no_plane() {
        let pts: Vec<_> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 1000.0)).collect();
        assert!(fit_plane_robust(&pts, 3.0, 1.0, 1).is_none());
    }
}
