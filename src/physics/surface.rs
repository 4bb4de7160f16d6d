//! Plane fits over 3D points: the white calibration plane (Eq. 13), and the
//! smooth-surface prior on a recovered layer (local planes over a window).

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::buffer::ImageBuf;
use super::parallel::map_ordered;
use super::stats::{median_and_sigma_sorted, median_select, sigma_about};

mod columns;
use columns::Columns;

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
    let points: Vec<RayPoint> = points.iter().filter_map(RayPoint::new).collect();
    fit_inverse_depth::<3>(&points, (0.0, 0.0), 3, &robust)?.tangent_plane(&Vector3::new(0.0, 0.0, 1.0))
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
    let points: Vec<RayPoint> = points.iter().filter_map(RayPoint::new).collect();
    fit_quadric_along_rays(&points, center, k, floor_mm, passes)?.tangent_plane(center)
}

/// The quadric of [`fit_tangent_plane_along_rays`] itself, whose tangent
/// plane can be taken at any ray near its centre.
fn fit_quadric_along_rays(
    points: &[RayPoint],
    center: &Vector3<f64>,
    k: f64,
    floor_mm: f64,
    passes: usize,
) -> Option<InverseDepthFit<6>> {
    if center.z <= 0.0 {
        return None;
    }
    let robust = Robust { k, floor_mm, passes };
    fit_inverse_depth::<6>(points, (center.x / center.z, center.y / center.z), 10, &robust)
}

/// The first `N` monomials of [`MONOMIALS`] at `(a, b)` (N is 3, a plane:
/// `1, a, b`; or 6, a quadric: `1, a, b, a^2, a b, b^2`), dotted with `c`.
#[inline]
fn polynomial<const N: usize>(c: &[f64; N], a: f64, b: f64) -> f64 {
    let linear = c[0] + c[1] * a + c[2] * b;
    if N < 6 {
        return linear;
    }
    linear + a * (c[3] * a + c[4] * b) + c[5] * b * b
}

/// The derivatives in `a` and in `b` of the first `N` monomials at `(a, b)`
/// (N 3 or 6, as [`polynomial`]).
fn polynomial_slopes<const N: usize>(a: f64, b: f64) -> ([f64; N], [f64; N]) {
    let (mut d_a, mut d_b) = ([0.0; N], [0.0; N]);
    d_a[1] = 1.0;
    d_b[2] = 1.0;
    if N >= 6 {
        (d_a[3], d_a[4]) = (2.0 * a, b);
        (d_b[4], d_b[5]) = (a, 2.0 * b);
    }
    (d_a, d_b)
}

/// A symmetric positive definite matrix factored as `L D L^T` (`L` unit lower
/// triangular): the normal equations' solve, and the quadratic forms of their
/// inverse (the coefficients' covariance) without forming it.
#[derive(Debug, Clone, Copy)]
struct Ldl<const N: usize> {
    /// `l[i][j]`, `j < i`.
    l: [[f64; N]; N],
    /// `1 / D`.
    d_inv: [f64; N],
}

impl<const N: usize> Ldl<N> {
    /// Factors the matrix whose lower triangle is `a[i][j]`, `j <= i`. `None`
    /// when a pivot falls below `1e-10` of its diagonal entry: a column the
    /// others (nearly) span, as a quadric's on points in two rows.
    fn new(a: &[[f64; N]; N]) -> Option<Self> {
        let mut l = [[0.0; N]; N];
        let mut d = [0.0; N];
        let mut d_inv = [0.0; N];
        for j in 0..N {
            let mut dj = a[j][j];
            for k in 0..j {
                dj -= l[j][k] * l[j][k] * d[k];
            }
            if !(dj > 1e-10 * a[j][j]) {
                return None;
            }
            d[j] = dj;
            d_inv[j] = 1.0 / dj;
            for i in j + 1..N {
                let mut v = a[i][j];
                for k in 0..j {
                    v -= l[i][k] * l[j][k] * d[k];
                }
                l[i][j] = v * d_inv[j];
            }
        }
        Some(Self { l, d_inv })
    }

    /// `L y = v`.
    #[inline]
    fn forward(&self, v: &[f64; N]) -> [f64; N] {
        let mut y = *v;
        for i in 0..N {
            for k in 0..i {
                y[i] -= self.l[i][k] * y[k];
            }
        }
        y
    }

    /// `A x = b`.
    fn solve(&self, b: &[f64; N]) -> [f64; N] {
        let mut x = self.forward(b);
        for i in 0..N {
            x[i] *= self.d_inv[i];
        }
        for i in (0..N).rev() {
            for k in i + 1..N {
                x[i] -= self.l[k][i] * x[k];
            }
        }
        x
    }

    /// `v^T A^-1 v`.
    fn inverse_form(&self, v: &[f64; N]) -> f64 {
        let y = self.forward(v);
        (0..N).map(|i| y[i] * y[i] * self.d_inv[i]).sum()
    }
}

#[inline]
fn dot<const N: usize>(a: &[f64; N], b: &[f64; N]) -> f64 {
    let mut s = 0.0;
    for i in 0..N {
        s += a[i] * b[i];
    }
    s
}

/// Outlier rejection of the fits along the rays.
struct Robust {
    k: f64,
    floor_mm: f64,
    passes: usize,
}

/// A polynomial in inverse depth fitted over image coordinates relative to
/// `(a0, b0)`, with what its uncertainty needs.
#[derive(Clone, Copy)]
struct InverseDepthFit<const N: usize> {
    coef: [f64; N],
    a0: f64,
    b0: f64,
    rms: f64,
    sigma: f64,
    count: usize,
    /// `e_a^T (A^T W A)^-1 e_a + e_b^T (A^T W A)^-1 e_b`, `e_a`, `e_b` the slopes'
    /// coefficients (`c1`, `c2`): the tangent plane's normal variance, over
    /// `(sigma / v)^2`, where the slopes are those coefficients alone (a plane
    /// anywhere, a quadric at its centre). Kept instead of the factored matrix,
    /// whose 42 numbers every copy of the fit would carry.
    slope_var: f64,
}

impl<const N: usize> InverseDepthFit<N> {
    /// The fitted inverse depth `1/z` where the ray `u` (z > 0) meets it, if positive.
    #[inline]
    fn inverse_depth(&self, u: &Vector3<f64>) -> Option<f64> {
        if u.z <= 0.0 {
            return None;
        }
        let v = polynomial(&self.coef, u.x / u.z - self.a0, u.y / u.z - self.b0);
        (v > 0.0).then_some(v)
    }

    /// The distance along the unit ray `u` to the fitted surface: that of the
    /// tangent plane at `u` ([`Self::tangent_plane`]), `1 / (v u_z)`, without
    /// the plane.
    #[inline]
    fn ray_distance(&self, u: &Vector3<f64>) -> Option<f64> {
        self.inverse_depth(u).map(|v| 1.0 / (v * u.z))
    }

    /// The plane tangent to the fitted surface where the ray `u` (z > 0) meets
    /// it: `1/z = v + g_a (a - a1) + g_b (b - b1)` at `(a1, b1) = (x/z, y/z)`,
    /// i.e. `(g_a, g_b, v - g_a a1 - g_b b1) . p = 1`, its normal toward the
    /// camera; the normal's standard error from the coefficients' covariance
    /// for a plane, or at a quadric's centre (NaN elsewhere on a quadric).
    fn tangent_plane(&self, u: &Vector3<f64>) -> Option<Plane> {
        self.tangent_plane_with(u, true)
    }

    /// [`Self::tangent_plane`], its normal's standard error NaN unless `sigma`.
    fn tangent_plane_with(&self, u: &Vector3<f64>, sigma: bool) -> Option<Plane> {
        let v = self.inverse_depth(u)?;
        let (a1, b1) = (u.x / u.z, u.y / u.z);
        let (ra, rb) = (a1 - self.a0, b1 - self.b0);
        let (d_a, d_b) = polynomial_slopes::<N>(ra, rb);
        let (ga, gb) = (dot(&d_a, &self.coef), dot(&d_b, &self.coef));
        let coef = Vector3::new(ga, gb, v - ga * a1 - gb * b1);
        let norm = coef.norm();
        let (normal, offset) = if coef.z > 0.0 {
            (-coef / norm, -1.0 / norm)
        } else {
            (coef / norm, 1.0 / norm)
        };
        // Residuals are in z units under the z^4 weights, so Cov(c) = sigma^2 (A^T W A)^-1;
        // the normal turns by d(g_a, g_b) / v.
        let normal_sigma_rad = if sigma && (N < 6 || (ra == 0.0 && rb == 0.0)) {
            self.sigma * self.slope_var.max(0.0).sqrt() / v
        } else {
            f64::NAN
        };
        Some(Plane {
            normal,
            offset,
            rms_mm: self.rms,
            count: self.count,
            normal_sigma_rad,
        })
    }
}

/// A point as the fits along the rays see it: its image coordinates `(x/z,
/// y/z)`, its depth `z` and its distance from the camera. Made once per
/// point, not once per window that holds it.
#[derive(Debug, Clone, Copy)]
struct RayPoint {
    a: f64,
    b: f64,
    z: f64,
    distance: f64,
}

impl RayPoint {
    /// No point (off the mask, not finite or behind the camera) in an image of
    /// points ([`ray_points`]): NaN everywhere, so [`Self::is_point`] is false.
    const NONE: Self = Self {
        a: f64::NAN,
        b: f64::NAN,
        z: f64::NAN,
        distance: f64::NAN,
    };

    /// Whether this is a point, not [`Self::NONE`] (a point's distance is finite).
    #[inline]
    fn is_point(&self) -> bool {
        !self.distance.is_nan()
    }

    /// A pixel's entry in an image of points: its point ([`Self::new`]) where
    /// it is a `member` of the fitted pixels and has one, else [`Self::NONE`].
    #[inline]
    fn at(p: &Vector3<f64>, member: bool) -> Self {
        if member {
            Self::new(p).unwrap_or(Self::NONE)
        } else {
            Self::NONE
        }
    }

    /// `None` for a point that is not finite or not in front of the camera.
    #[inline]
    fn new(p: &Vector3<f64>) -> Option<Self> {
        (p.z > 0.0 && p.iter().all(|v| v.is_finite())).then(|| Self {
            a: p.x / p.z,
            b: p.y / p.z,
            z: p.z,
            distance: p.norm(),
        })
    }
}

/// The masked pixels' points as [`RayPoint`]s ([`RayPoint::NONE`] elsewhere:
/// a window's rows are then gathered without a branch per pixel).
fn ray_points(points: &ImageBuf<Vector3<f64>>, mask: &ImageBuf<bool>) -> Vec<RayPoint> {
    points
        .data
        .iter()
        .zip(&mask.data)
        .map(|(p, &m)| RayPoint::at(p, m))
        .collect()
}

/// Weighted moments of points over image coordinates: `sum w a^p b^q` for
/// `p + q <= 4` and `sum (w / z) a^p b^q` for `p + q <= 2`, monomials in
/// [`MONOMIALS`] order. The normal equations of any basis made of the first
/// monomials (the plane's three, the quadric's six) are read off them.
#[derive(Debug, Clone, Copy, Default)]
struct Moments {
    w: [f64; 15],
    rhs: [f64; 6],
}

/// The monomials `a^p b^q` by degree: `1, a, b, a^2, a b, b^2, a^3, ...`.
const MONOMIALS: [(u8, u8); 15] = [
    (0, 0),
    (1, 0),
    (0, 1),
    (2, 0),
    (1, 1),
    (0, 2),
    (3, 0),
    (2, 1),
    (1, 2),
    (0, 3),
    (4, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 4),
];

/// The index in [`MONOMIALS`] of the product of monomials `i` and `j`.
const fn product(i: usize, j: usize) -> usize {
    let (p, q) = (MONOMIALS[i].0 + MONOMIALS[j].0, MONOMIALS[i].1 + MONOMIALS[j].1);
    let mut k = 0;
    while k < MONOMIALS.len() {
        if MONOMIALS[k].0 == p && MONOMIALS[k].1 == q {
            return k;
        }
        k += 1;
    }
    panic!("degree above 4")
}

impl Moments {
    /// Takes out a point at `(a, b)` of weight `w` and right-hand side `rhs`
    /// (a robust pass's downdate; the sums themselves are made four points at a
    /// time, [`Columns::moments`]).
    #[inline]
    fn take_out(&mut self, a: f64, b: f64, w: f64, rhs: f64) {
        let w = -w;
        let (wa, wb) = (w * a, w * b);
        let (wa2, wab, wb2) = (wa * a, wa * b, wb * b);
        let (wa3, wa2b, wab2, wb3) = (wa2 * a, wa2 * b, wab * b, wb2 * b);
        let terms = [
            w,
            wa,
            wb,
            wa2,
            wab,
            wb2,
            wa3,
            wa2b,
            wab2,
            wb3,
            wa3 * a,
            wa3 * b,
            wa2b * b,
            wab2 * b,
            wb3 * b,
        ];
        for (m, t) in self.w.iter_mut().zip(terms) {
            *m += t;
        }
        let r = -rhs;
        let (ra, rb) = (r * a, r * b);
        for (m, t) in self.rhs.iter_mut().zip([r, ra, rb, ra * a, ra * b, rb * b]) {
            *m += t;
        }
    }

    /// The normal equations `(A^T W A, A^T W y)` of the first `N` monomials
    /// (the lower triangle of the matrix).
    fn normal_equations<const N: usize>(&self) -> ([[f64; N]; N], [f64; N]) {
        let mut m = [[0.0; N]; N];
        for (i, row) in m.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate().take(i + 1) {
                *v = self.w[product(i, j)];
            }
        }
        let mut r = [0.0; N];
        r.copy_from_slice(&self.rhs[..N]);
        (m, r)
    }
}

/// Weighted least squares of the inverse depth on the first `N` monomials of
/// [`MONOMIALS`] (3: `1, a, b`; 6: the quadric's) in
/// image coordinates `(a, b) = (x/z, y/z) - centre`, with weights `z^4` so
/// residuals are millimetres of z.
fn fit_inverse_depth<const N: usize>(
    points: &[RayPoint],
    centre: (f64, f64),
    min_points: usize,
    robust: &Robust,
) -> Option<InverseDepthFit<N>> {
    COLUMNS.with(|cols| fit_inverse_depth_in(&mut cols.borrow_mut(), points, centre, min_points, robust))
}

thread_local! {
    /// Each thread's columns for [`fit_inverse_depth`], kept between fits.
    static COLUMNS: std::cell::RefCell<Columns> = std::cell::RefCell::new(Columns::default());
}

/// [`fit_inverse_depth`] with its points held in `cols`.
fn fit_inverse_depth_in<const N: usize>(
    cols: &mut Columns,
    points: &[RayPoint],
    (a0, b0): (f64, f64),
    min_points: usize,
    robust: &Robust,
) -> Option<InverseDepthFit<N>> {
    // Each point's coordinates, weight and right-hand side once (the passes only drop points).
    cols.fill(points, (a0, b0));
    // The moments over every point, then each pass takes out the points it drops (a
    // downdate) instead of summing the kept ones again.
    let mut moments = cols.moments(N > 3);
    let mut n = points.len();
    let mut fit = None;
    for pass in 0..=robust.passes {
        if n < min_points {
            return fit;
        }
        let (ata, atb) = moments.normal_equations::<N>();
        let normal = Ldl::new(&ata)?;
        let c = normal.solve(&atb);
        if !c.iter().all(|v| v.is_finite()) || c[0] <= 0.0 {
            return fit;
        }
        let ss = cols.residuals(&c);
        let rms = (ss / n as f64).sqrt();
        let unit = |k: usize| {
            let mut e = [0.0; N];
            e[k] = 1.0;
            e
        };
        fit = Some(InverseDepthFit {
            coef: c,
            slope_var: normal.inverse_form(&unit(1)) + normal.inverse_form(&unit(2)),
            a0,
            b0,
            rms,
            sigma: (ss / n.saturating_sub(N).max(1) as f64).sqrt(), // residual scale, N terms fitted
            count: n,
        });
        if pass == robust.passes {
            break;
        }
        let cut = (robust.k * rms).max(robust.floor_mm);
        let dropped = cols.drop_beyond(cut, &mut moments);
        if dropped == 0 {
            break;
        }
        n -= dropped;
    }
    fit
}

/// Local planes whose window grows until the normal is known to
/// `max_normal_sigma_rad` (noisy layers need wide windows, curved ones narrow):
/// for each masked pixel with a finite point the first of `radii` (ascending)
/// that reaches it, else the widest. With `stride` above 1, one window per
/// block as in [`local_planes`], its radius chosen at the block's centre.
/// The planes carry no normal standard error (`normal_sigma_rad` NaN): it
/// chose the window and is not taken again at every pixel.
pub fn local_planes_adaptive(
    points: &ImageBuf<Vector3<f64>>,
    rays: &ImageBuf<Vector3<f64>>,
    mask: &ImageBuf<bool>,
    radii: &[usize],
    min_points: usize,
    max_normal_sigma_rad: f64,
    stride: usize,
) -> ImageBuf<Option<Plane>> {
    let with_point = ImageBuf {
        width: mask.width,
        height: mask.height,
        data: mask
            .data
            .iter()
            .zip(&points.data)
            .map(|(&m, p)| m && p.x.is_finite())
            .collect(),
    };
    let blocks = Blocks::new(&with_point, stride);
    let all: Vec<usize> = (0..blocks.centres.len()).collect();
    let ray_pts = ray_points(points, mask);
    let fits = blocks.fit(&all, |centre| {
        let mut out = None;
        for (k, &r) in radii.iter().enumerate() {
            if let Some(fit) = window_fit(&ray_pts, points.width, rays, centre, r, min_points) {
                let sigma = fit.tangent_plane(&rays.data[centre]).map(|p| p.normal_sigma_rad);
                let done = k + 1 == radii.len() || sigma.is_some_and(|s| s <= max_normal_sigma_rad);
                out = Some(fit);
                if done {
                    break;
                }
            }
        }
        out
    });
    LocalSurfaces {
        blocks,
        fits,
        points: ray_pts,
        members: with_point,
    }
    .planes(rays)
}

/// The windows of [`local_planes`]: `(2 radius + 1)^2` pixels, fitted when
/// they hold at least `min_points` points, one per `stride x stride` block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Windows {
    /// Half-width, pixels.
    pub radius: usize,
    /// Fewest points a window is fitted with.
    pub min_points: usize,
    /// Side of the blocks that share a window, pixels (1: every pixel its own).
    pub stride: usize,
}

/// Local planes over a `(2 radius + 1)^2` window: for every pixel where
/// `mask` holds, the robust tangent plane (fitted along the rays, see
/// [`fit_tangent_plane_along_rays`]) at the pixel's ray `rays` through the
/// masked neighbours' points (`None` with fewer than `windows.min_points`). The
/// smooth-surface prior: a noisy per-pixel depth is replaced by its
/// neighbourhood's plane. The planes of [`LocalSurfaces`], pixel by pixel,
/// without the normal's standard error (NaN).
pub fn local_planes(
    points: &ImageBuf<Vector3<f64>>,
    rays: &ImageBuf<Vector3<f64>>,
    mask: &ImageBuf<bool>,
    windows: &Windows,
) -> ImageBuf<Option<Plane>> {
    LocalSurfaces::new(points, rays, mask, windows).planes(rays)
}

/// The smooth-surface prior's fitted windows, one per block: with `stride`
/// above 1 the image is cut into `stride x stride` blocks and one window is
/// fitted per block, around the block's masked pixel nearest its middle;
/// every masked pixel of the block takes the fitted surface's tangent plane at
/// its own ray (`stride^2` times fewer fits; `stride` 1 fits every pixel's own
/// window). A pixel's plane is made only when asked for
/// ([`LocalSurfaces::plane`]); [`LocalSurfaces::ray_distance`] skips it.
pub struct LocalSurfaces {
    blocks: Blocks,
    fits: Vec<Option<WindowFit>>,
    /// The points fitted.
    points: Vec<RayPoint>,
    /// The pixels that take a plane.
    members: ImageBuf<bool>,
}

impl LocalSurfaces {
    /// Fits every block's window over the masked, finite `points`.
    pub fn new(
        points: &ImageBuf<Vector3<f64>>,
        rays: &ImageBuf<Vector3<f64>>,
        mask: &ImageBuf<bool>,
        windows: &Windows,
    ) -> Self {
        let blocks = Blocks::new(mask, windows.stride);
        let all: Vec<usize> = (0..blocks.centres.len()).collect();
        let ray_pts = ray_points(points, mask);
        let fits = blocks.fit(&all, |c| {
            window_fit(&ray_pts, points.width, rays, c, windows.radius, windows.min_points)
        });
        Self {
            blocks,
            fits,
            points: ray_pts,
            members: mask.clone(),
        }
    }

    /// Refits, after the points at `changed` moved, exactly the windows that
    /// hold one of them (the others are unchanged): the same surfaces as a
    /// full recomputation, at the cost of the windows touched. `windows` must
    /// be those the surfaces were made with.
    pub fn update(
        &mut self,
        points: &ImageBuf<Vector3<f64>>,
        rays: &ImageBuf<Vector3<f64>>,
        windows: &Windows,
        changed: &[usize],
    ) {
        let w = points.width;
        let r = windows.radius as isize;
        let redo: Vec<usize> = (0..self.blocks.centres.len())
            .filter(|&k| {
                let c = self.blocks.centres[k];
                let (cc, cr) = ((c % w) as isize, (c / w) as isize);
                changed
                    .iter()
                    .any(|&i| ((i % w) as isize - cc).abs() <= r && ((i / w) as isize - cr).abs() <= r)
            })
            .collect();
        for &i in changed {
            self.points[i] = RayPoint::at(&points.data[i], self.members.data[i]);
        }
        let ray_pts = &self.points;
        let fits = self.blocks.fit(&redo, |c| {
            window_fit(ray_pts, points.width, rays, c, windows.radius, windows.min_points)
        });
        for (k, f) in redo.into_iter().zip(fits) {
            self.fits[k] = f;
        }
    }

    /// The fitted surface of pixel `i`'s block, for a member pixel.
    #[inline]
    fn fit_of(&self, i: usize) -> Option<&WindowFit> {
        if !self.members.data[i] {
            return None;
        }
        self.fits.get(self.blocks.pixel_slot[i] as usize)?.as_ref()
    }

    /// The tangent plane at pixel `i`'s ray (`None` off the mask or without a
    /// fit), without the normal's standard error (NaN): the fits keep only
    /// what it takes at their centres.
    pub fn plane(&self, i: usize, rays: &ImageBuf<Vector3<f64>>) -> Option<Plane> {
        self.fit_of(i)?.tangent_plane_with(&rays.data[i], false)
    }

    /// `plane(i).ray_distance(rays[i])`, up to rounding, without making the plane.
    pub fn ray_distance(&self, i: usize, rays: &ImageBuf<Vector3<f64>>) -> Option<f64> {
        self.fit_of(i)?.ray_distance(&rays.data[i])
    }

    /// The plane of the pixel nearest `i` (within `radius`, in image distance) that has one.
    pub fn nearest_plane(&self, i: usize, radius: usize, rays: &ImageBuf<Vector3<f64>>) -> Option<Plane> {
        let (w, h) = (self.members.width, self.members.height);
        let (c, r) = ((i % w) as isize, (i / w) as isize);
        let rad = radius as isize;
        let mut best: Option<(isize, Plane)> = None;
        for dr in -rad..=rad {
            for dc in -rad..=rad {
                let (cc, rr) = (c + dc, r + dr);
                if cc < 0 || rr < 0 || cc >= w as isize || rr >= h as isize {
                    continue;
                }
                let d2 = dr * dr + dc * dc;
                if best.is_some_and(|(b, _)| d2 >= b) {
                    continue;
                }
                if let Some(p) = self.plane(rr as usize * w + cc as usize, rays) {
                    best = Some((d2, p));
                }
            }
        }
        best.map(|b| b.1)
    }

    /// Every pixel's plane ([`Self::plane`]).
    pub fn planes(&self, rays: &ImageBuf<Vector3<f64>>) -> ImageBuf<Option<Plane>> {
        let m = &self.members;
        ImageBuf {
            width: m.width,
            height: m.height,
            data: (0..m.data.len()).map(|i| self.plane(i, rays)).collect(),
        }
    }
}

/// The blocks of a strided [`LocalSurfaces`]: each block's window centre (its
/// masked pixel nearest the block's middle). Only blocks with a masked
/// pixel have a window: a small object in a large image has few.
struct Blocks {
    /// The windows' centres (pixel indices), in block order.
    centres: Vec<usize>,
    /// Per pixel, its block's `slot` (`u32::MAX` for none): found without a
    /// division at every pixel that asks for its surface.
    pixel_slot: Vec<u32>,
}

impl Blocks {
    fn new(mask: &ImageBuf<bool>, stride: usize) -> Self {
        let s = stride.max(1);
        let (w, h) = (mask.width, mask.height);
        let (across, down) = (w.div_ceil(s), h.div_ceil(s));
        let mut slot = vec![usize::MAX; across * down];
        let mut centres = vec![];
        for (b, slot) in slot.iter_mut().enumerate() {
            let centre = {
                let (c0, r0) = ((b % across) * s, (b / across) * s);
                let (c1, r1) = ((c0 + s).min(w), (r0 + s).min(h));
                // Twice the offset from the block's middle, so odd and even strides stay exact.
                let (mc, mr) = ((c0 + c1 - 1) as isize, (r0 + r1 - 1) as isize);
                // A masked pixel at the very middle (a block of odd sides) is the nearest.
                let middle = (mr as usize / 2) * w + mc as usize / 2;
                if mc % 2 == 0 && mr % 2 == 0 && mask.data[middle] {
                    Some(middle)
                } else {
                    (r0..r1)
                        .flat_map(|r| (c0..c1).map(move |c| (r, c)))
                        .filter(|&(r, c)| mask.data[r * w + c])
                        .min_by_key(|&(r, c)| (2 * r as isize - mr).pow(2) + (2 * c as isize - mc).pow(2))
                        .map(|(r, c)| r * w + c)
                }
            };
            if let Some(c) = centre {
                *slot = centres.len();
                centres.push(c);
            }
        }
        // Each row of blocks' slots, repeated `s` times across, then copied to its `s` rows.
        let mut pixel_slot = Vec::with_capacity(w * h);
        let mut row_slots = Vec::with_capacity(across * s);
        for (br, blocks) in slot.chunks(across.max(1)).enumerate() {
            row_slots.clear();
            for &k in blocks {
                row_slots.extend(std::iter::repeat_n(u32::try_from(k).unwrap_or(u32::MAX), s));
            }
            row_slots.truncate(w);
            for _ in br * s..((br + 1) * s).min(h) {
                pixel_slot.extend_from_slice(&row_slots);
            }
        }
        Self { centres, pixel_slot }
    }

    /// Fits the windows `windows` (indices into `centres`) with `fit` (given the
    /// centre; in parallel over the current rayon pool when there are enough of them).
    fn fit(&self, windows: &[usize], fit: impl Fn(usize) -> Option<WindowFit> + Sync + Send) -> Vec<Option<WindowFit>> {
        map_ordered(windows, MIN_PARALLEL_WINDOWS, 8, |&k| fit(self.centres[k]))
    }
}

/// Fewest windows whose fits are spread over the rayon pool: about half a
/// millisecond of one core's work (see [`map_ordered`]).
const MIN_PARALLEL_WINDOWS: usize = 256;

/// Keeps the points whose distance from the camera lies within `k` robust
/// standard deviations (1.4826 MAD, at least `floor_mm`) of the median.
fn keep_near_median(points: &mut Vec<RayPoint>, k: f64, floor_mm: f64) {
    if points.len() < 3 {
        return;
    }
    // Every point within the floor of the median is kept whatever the spread: no need
    // to measure it (the common case on a smooth layer). Within the floor of each other,
    // they are within it of the median too.
    // (Comparisons, not `f64::min`: the distances are finite, so no NaN to order.)
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in points.iter() {
        let d = p.distance;
        lo = if d < lo { d } else { lo };
        hi = if d > hi { d } else { hi };
    }
    if hi - lo <= floor_mm {
        return;
    }
    // The same when the median lies within the floor of both ends, which counts can show
    // without finding it: fewer than half the points more than the floor above the lowest
    // (and below the highest) put the middle one, or both middle ones, within it.
    let half = (points.len() - 1) / 2;
    let (far_above, far_below) = points.iter().fold((0, 0), |(a, b), p| {
        (
            a + usize::from(p.distance - lo > floor_mm),
            b + usize::from(hi - p.distance > floor_mm),
        )
    });
    if far_above <= half && far_below <= half {
        return;
    }
    let mut norms: Vec<f64> = points.iter().map(|p| p.distance).collect();
    let (med, cut) = if norms.len() <= SMALL_WINDOW {
        // A few dozen distances: sorted in place, they give the median and its spread at once.
        insertion_sort(&mut norms);
        let (med, sigma) = median_and_sigma_sorted(&norms);
        if med - lo <= floor_mm && hi - med <= floor_mm {
            return;
        }
        (med, (k * sigma).max(floor_mm))
    } else {
        let med = median_select(&mut norms);
        if med - lo <= floor_mm && hi - med <= floor_mm {
            return;
        }
        (med, (k * sigma_about(&norms, med)).max(floor_mm))
    };
    points.retain(|p| (p.distance - med).abs() <= cut);
}

/// Most distances [`keep_near_median`] sorts by insertion (fewer moves than a selection's
/// partitions there); above it, two selections.
const SMALL_WINDOW: usize = 48;

/// Sorts finite values ascending by insertion.
fn insertion_sort(v: &mut [f64]) {
    for i in 1..v.len() {
        let x = v[i];
        let mut j = i;
        while j > 0 && v[j - 1] > x {
            v[j] = v[j - 1];
            j -= 1;
        }
        v[j] = x;
    }
}

/// A window's fitted surface: the quadric, or a plane where the quadric failed.
#[allow(clippy::large_enum_variant)] // short-lived, one per window; boxing would allocate per fit
enum WindowFit {
    Quadric(InverseDepthFit<6>),
    Plane(InverseDepthFit<3>),
}

impl WindowFit {
    fn tangent_plane(&self, u: &Vector3<f64>) -> Option<Plane> {
        self.tangent_plane_with(u, true)
    }

    fn tangent_plane_with(&self, u: &Vector3<f64>, sigma: bool) -> Option<Plane> {
        match self {
            WindowFit::Quadric(f) => f.tangent_plane_with(u, sigma),
            WindowFit::Plane(f) => f.tangent_plane_with(u, sigma),
        }
    }

    #[inline]
    fn ray_distance(&self, u: &Vector3<f64>) -> Option<f64> {
        match self {
            WindowFit::Quadric(f) => f.ray_distance(u),
            WindowFit::Plane(f) => f.ray_distance(u),
        }
    }
}

/// The surface through the masked, finite points in the window around pixel `i`.
fn window_fit(
    points: &[RayPoint],
    width: usize,
    rays: &ImageBuf<Vector3<f64>>,
    i: usize,
    radius: usize,
    min_points: usize,
) -> Option<WindowFit> {
    WINDOW.with(|window| {
        // The window's points, gathered into the thread's buffer.
        let window = &mut *window.borrow_mut();
        let h = points.len() / width.max(1);
        let (col, row) = (i % width, i / width);
        // Each pixel is written at the end and counted only if it is a point: no branch per
        // pixel (the buffer is first made as long as the window).
        let rows = row.saturating_sub(radius)..(row + radius + 1).min(h);
        let cols = col.saturating_sub(radius)..(col + radius + 1).min(width);
        let most = rows.len() * cols.len();
        if window.len() < most {
            window.resize(most, RayPoint::NONE);
        }
        let mut len = 0;
        for r in rows {
            for p in &points[r * width + cols.start..r * width + cols.end] {
                window[len] = *p;
                len += usize::from(p.is_point());
            }
        }
        window.truncate(len);
        // A least-squares start is only as good as its worst points: drop those far from the
        // window's median distance first (pixels of another surface that joined the region).
        keep_near_median(window, 4.0, 20.0);
        if window.len() < min_points.max(3) {
            return None;
        }
        // The quadric where the window allows it (curved layers), else a plane.
        let (k, floor_mm, passes) = (2.5, 1.0, 2);
        if let Some(q) = fit_quadric_along_rays(window, &rays.data[i], k, floor_mm, passes) {
            return Some(WindowFit::Quadric(q));
        }
        let robust = Robust { k, floor_mm, passes };
        fit_inverse_depth::<3>(window, (0.0, 0.0), 3, &robust).map(WindowFit::Plane)
    })
}

thread_local! {
    /// Each thread's window of points for [`window_fit`], kept between windows.
    static WINDOW: std::cell::RefCell<Vec<RayPoint>> = const { std::cell::RefCell::new(Vec::new()) };
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

    /// Unit rays of a `w x h` pinhole image, `step` apart in `x/z` and `y/z` from `origin`.
    fn ray_grid(w: usize, h: usize, step: f64, origin: (f64, f64)) -> ImageBuf<Vector3<f64>> {
        ImageBuf {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| {
                    Vector3::new(origin.0 + (i % w) as f64 * step, origin.1 + (i / w) as f64 * step, 1.0).normalize()
                })
                .collect(),
        }
    }

    #[test]
    fn updating_moved_windows_equals_refitting_all() {
        // A noisy tilted plane under a masked region; move a few points, then compare the
        // windowed update with a full recomputation, plane for plane.
        let (w, h) = (40usize, 30usize);
        let rays = ray_grid(w, h, 0.004, (-0.08, -0.06));
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
        let moved = [5 * w + 6, 15 * w + 20, 16 * w + 20, 26 * w + 36];
        let before_move = points.clone();
        for &i in &moved {
            points.data[i] *= 1.2;
        }
        // Every window on its own, and one window per 3 x 3 block.
        for stride in [1, 3] {
            let windows = Windows {
                radius: 3,
                min_points: 12,
                stride,
            };
            let mut surfaces = LocalSurfaces::new(&before_move, &rays, &mask, &windows);
            surfaces.update(&points, &rays, &windows, &moved);
            // Plane for plane, bit for bit (the prior's planes carry no standard error).
            let bits = |planes: &ImageBuf<Option<Plane>>| -> Vec<Option<([u64; 5], usize)>> {
                let key = |p: &Plane| {
                    assert!(p.normal_sigma_rad.is_nan());
                    let v = [p.normal.x, p.normal.y, p.normal.z, p.offset, p.rms_mm];
                    (v.map(f64::to_bits), p.count)
                };
                planes.data.iter().map(|p| p.as_ref().map(key)).collect()
            };
            let planes = bits(&surfaces.planes(&rays));
            let full = local_planes(&points, &rays, &mask, &windows);
            assert_eq!(planes, bits(&full), "stride {stride}");
            // The update did refit: the planes before the move differ somewhere.
            let before = local_planes(&before_move, &rays, &mask, &windows);
            assert_ne!(bits(&before), bits(&full), "stride {stride}");
            // Every masked pixel has a plane (the windows hold enough points everywhere).
            let masked = mask.data.iter().filter(|&&m| m).count();
            assert_eq!(
                full.data.iter().filter(|p| p.is_some()).count(),
                masked,
                "stride {stride}"
            );
        }
    }

    #[test]
    fn strided_planes_follow_a_curved_layer() {
        // A cylinder-like layer (inverse depth quadratic across the image) without noise:
        // each pixel's tangent plane from its block's window is the exact one at its ray,
        // as with a window of its own.
        let (w, h) = (30usize, 24usize);
        let rays = ray_grid(w, h, 0.005, (-0.07, -0.06));
        let inv_z = |a: f64, b: f64| 1e-3 * (1.0 + 0.3 * a - 0.2 * b + 4.0 * a * a + 1.5 * b * b);
        let points = ImageBuf {
            width: w,
            height: h,
            data: rays
                .data
                .iter()
                .map(|u| u * (1.0 / inv_z(u.x / u.z, u.y / u.z)) / u.z)
                .collect(),
        };
        let mask = ImageBuf::filled(w, h, true);
        let windows = |stride| Windows {
            radius: 4,
            min_points: 12,
            stride,
        };
        let own = local_planes(&points, &rays, &mask, &windows(1));
        let strided = local_planes(&points, &rays, &mask, &windows(3));
        for i in 0..w * h {
            let (p, q) = (own.data[i].unwrap(), strided.data[i].unwrap());
            let t = points.data[i].norm();
            assert!((p.ray_distance(&rays.data[i]).unwrap() - t).abs() < 1e-6, "pixel {i}");
            assert!((q.ray_distance(&rays.data[i]).unwrap() - t).abs() < 1e-6, "pixel {i}");
            assert!(
                (p.normal - q.normal).norm() < 1e-6,
                "pixel {i}: {:?} {:?}",
                p.normal,
                q.normal
            );
        }
    }

    #[test]
    fn block_centres_are_the_masked_pixels_nearest_the_middles() {
        // Seeded masks, odd and even strides, blocks cut by the image's edges: each block's
        // centre is its masked pixel nearest the block's middle (the first in row order of
        // those as near), found by looking at every pixel.
        let mut k = 11u32;
        for stride in 1..=5usize {
            for fill in [0.3, 0.8, 1.0] {
                let (w, h) = (23usize, 17usize);
                let mask = ImageBuf {
                    width: w,
                    height: h,
                    data: (0..w * h)
                        .map(|_| {
                            k = k.wrapping_mul(1103515245).wrapping_add(12345);
                            ((k >> 16) % 1000) as f64 / 1000.0 < fill
                        })
                        .collect(),
                };
                let blocks = Blocks::new(&mask, stride);
                let across = w.div_ceil(stride);
                for b in 0..across * h.div_ceil(stride) {
                    let (c0, r0) = ((b % across) * stride, (b / across) * stride);
                    // The block's window, as its first pixel knows it.
                    let slot = blocks.pixel_slot[r0 * w + c0];
                    let (c1, r1) = ((c0 + stride).min(w), (r0 + stride).min(h));
                    let mut best: Option<(f64, usize)> = None;
                    for r in r0..r1 {
                        for c in c0..c1 {
                            let d = (r as f64 - (r0 + r1 - 1) as f64 / 2.0).powi(2)
                                + (c as f64 - (c0 + c1 - 1) as f64 / 2.0).powi(2);
                            if mask.data[r * w + c] && best.is_none_or(|(bd, _)| d < bd) {
                                best = Some((d, r * w + c));
                            }
                        }
                    }
                    let got = (slot != u32::MAX).then(|| blocks.centres[slot as usize]);
                    assert_eq!(got, best.map(|b| b.1), "stride {stride}, fill {fill}, block {b}");
                    // Every pixel of the block knows the same window.
                    for r in r0..r1 {
                        for c in c0..c1 {
                            assert_eq!(blocks.pixel_slot[r * w + c], slot, "pixel ({c}, {r})");
                        }
                    }
                }
                assert_eq!(blocks.pixel_slot.len(), w * h);
            }
        }
    }

    #[test]
    fn collinear_points_have_no_plane() {
        let pts: Vec<_> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 1000.0)).collect();
        assert!(fit_plane_robust(&pts, 3.0, 1.0, 1).is_none());
    }
}
