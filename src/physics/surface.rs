//! Plane fits over 3D points: the white calibration plane (Eq. 13), and the
//! smooth-surface prior on a recovered layer (local planes over a window).

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::buffer::ImageBuf;

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
    let (imin, _) = eig.eigenvalues.iter().enumerate().fold((0, f64::INFINITY), |b, (i, &v)| if v < b.1 { (i, v) } else { b });
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
    Some(Plane { normal: n, offset, rms_mm: rms, count: points.len() })
}

/// A plane fit that drops points farther than `k` times the RMS (and at
/// least `floor_mm`) from the previous fit, `passes` times.
pub fn fit_plane_robust(points: &[Vector3<f64>], k: f64, floor_mm: f64, passes: usize) -> Option<Plane> {
    let mut kept: Vec<(Vector3<f64>, f64)> = points.iter().map(|p| (*p, 1.0)).collect();
    let mut plane = fit_plane_weighted(&kept)?;
    for _ in 0..passes {
        let cut = (k * plane.rms_mm).max(floor_mm);
        let next: Vec<(Vector3<f64>, f64)> =
            points.iter().filter(|p| (plane.normal.dot(p) - plane.offset).abs() <= cut).map(|p| (*p, 1.0)).collect();
        if next.len() == kept.len() || next.len() < 3 {
            break;
        }
        kept = next;
        plane = fit_plane_weighted(&kept)?;
    }
    Some(plane)
}

/// Local planes over a `(2 radius + 1)^2` window: for every pixel where
/// `points` is finite and `mask` holds, a robust plane through the masked
/// neighbours' points (`None` with fewer than `min_points`). The smooth-surface
/// prior: replace a noisy per-pixel depth by its neighbourhood's plane.
pub fn local_planes(points: &ImageBuf<Vector3<f64>>, mask: &ImageBuf<bool>, radius: usize, min_points: usize) -> ImageBuf<Option<Plane>> {
    let (w, h) = (points.width, points.height);
    let mut out = ImageBuf::filled(w, h, None);
    let mut window = Vec::with_capacity((2 * radius + 1).pow(2));
    for row in 0..h {
        for col in 0..w {
            let i = row * w + col;
            if !mask.data[i] || !points.data[i].x.is_finite() {
                continue;
            }
            window.clear();
            for r in row.saturating_sub(radius)..(row + radius + 1).min(h) {
                for c in col.saturating_sub(radius)..(col + radius + 1).min(w) {
                    let j = r * w + c;
                    if mask.data[j] && points.data[j].x.is_finite() {
                        window.push(points.data[j]);
                    }
                }
            }
            if window.len() >= min_points.max(3) {
                out.data[i] = fit_plane_robust(&window, 2.5, 1.0, 2);
            }
        }
    }
    out
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
    fn collinear_points_have_no_plane() {
        let pts: Vec<_> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 1000.0)).collect();
        assert!(fit_plane_robust(&pts, 3.0, 1.0, 1).is_none());
    }
}
