//! A layer that transmits diffusely (frosted, a thin diffuser): the light crossing it
//! leaves through a cosine lobe, not along the ray, so the background is reached, and
//! seen, over a spread of slanted paths.
//!
//! For a layer `g` before a plane background, a crossing at angle `θ` from the normal
//! travels `g / cos θ`. Over the cosine lobe (`u = cos θ` with density `2u`), the
//! crossing's phasor average at the equivalent distance (half the path) is
//!
//! `ψ(a) = ∫₀¹ 2u exp(i a / u) du`,  `a = k g / 2`
//!
//! and the second return crosses twice (in and back): `ψ²`. Of the light that crosses,
//! a share `f` does so diffusely: the second return (Eq. 2) keeps `(1 - f) L2` at the
//! background's distance, and the diffuse part, `f L2 ψ(k g / 2)²` at the layer's phase,
//! is a return of strength `f L2 |ψ²|` at `df + arg(ψ²) / k`. That is the limit of a
//! layer that fills the background's view: [`lobe_returns`] gives the finite layer's.
//!
//! **The finite layer** ([`lobe_returns`]). The camera and its emitter sit together, so the
//! layer's shadow on the background is, in the image, the layer's own outline. The lobe
//! behind a pixel's point `P` (its radiance toward the camera is `ξ` times the cosine-
//! weighted mean of the background's radiance over the lobe) falls on background points
//! `W` both inside and outside that shadow:
//!
//! - outside, the background is lit straight by the emitter: its radiance over the one
//!   behind the pixel `W0` is `b(W) = (cos α_W / cos α_0)³ Lin(W) / Lin(W0)` (`α` the angle
//!   off the optical axis; a background facing the camera), and the light crosses the
//!   layer once, on its way back:
//!   `Z_lit = Σ_{W outside} w b(W) exp(i k [(|P| + |W - P| + |W|) / 2 - df])`;
//! - inside, the background is lit only through the layer, diffusely, with
//!   `κ = E(W0) / (ξ E_direct(W0)) = |W0|² / cos α_0 Σ_q Ω_q cos β_q cos γ_q / (π r_q²)`
//!   over the layer's patches `q` (solid angle `Ω_q` from the emitter, `r_q` to `W0`,
//!   `β_q`, `γ_q` the angles to the layer's and the background's normals: each patch passes on
//!   what it intercepts, `ξ I Ω_q`, through a cosine lobe), and the light crosses twice:
//!   `Z_shadow = κ Σ_{W inside} w exp(i k [(|P| + |W - P| + l_in) / 2 - df])`, `l_in` the
//!   inward path (mean `|Q| + r_q`, weighted as `κ`).
//!
//! `w = 2u du dφ / 2π` are the lobe's weights. The second return is then
//! `(1 - f) L2` at `db` beside `f (L2 / (ξ X^{p/2})) Z_lit + f L2 Z_shadow` at the layer's
//! phase: one phasor. No parameter is added: the outline, the gap and the layer's normal
//! are the scene's. A background of infinite extent lit directly everywhere outside the
//! outline, a patch's light `Lin` taken as the pixel's (the emitter's falloff across the
//! layer left out) and the background's `Lin` beyond the image's border as at the border
//! are the approximations (`scripts/diffuse_return.py` measures what is left).

use nalgebra::Vector3;
use std::sync::OnceLock;

/// Entries of the table of `ψ` over `[0, TABLE_MAX]`.
const TABLE_LEN: usize = 4096;
/// Largest `a` the table holds: layers up to two unambiguous ranges before the background.
const TABLE_MAX: f64 = 2.0 * std::f64::consts::PI;
/// Midpoints of the quadrature in `u`.
const QUADRATURE: usize = 8192;

/// `ψ(a)` by the midpoint rule in `u` (real and imaginary parts).
fn lobe_average_direct(a: f64) -> (f64, f64) {
    let (mut re, mut im) = (0.0, 0.0);
    let du = 1.0 / QUADRATURE as f64;
    for j in 0..QUADRATURE {
        let u = (j as f64 + 0.5) * du;
        let (s, c) = (a / u).sin_cos();
        re += 2.0 * u * c * du;
        im += 2.0 * u * s * du;
    }
    (re, im)
}

fn table() -> &'static [(f64, f64)] {
    static TABLE: OnceLock<Vec<(f64, f64)>> = OnceLock::new();
    TABLE.get_or_init(|| {
        (0..=TABLE_LEN)
            .map(|j| lobe_average_direct(TABLE_MAX * j as f64 / TABLE_LEN as f64))
            .collect()
    })
}

/// `ψ(a)`, one diffuse crossing's phasor average (real and imaginary parts); `a` at least 0.
pub fn lobe_average(a: f64) -> (f64, f64) {
    let a = a.max(0.0);
    if !(a < TABLE_MAX) {
        return if a.is_finite() {
            lobe_average_direct(a)
        } else {
            (0.0, 0.0)
        };
    }
    let t = table();
    let x = a / TABLE_MAX * TABLE_LEN as f64;
    let j = (x as usize).min(TABLE_LEN - 1);
    let w = x - j as f64;
    let (p, q) = (t[j], t[j + 1]);
    (p.0 + w * (q.0 - p.0), p.1 + w * (q.1 - p.1))
}

/// The diffuse part of the second return over `L2` for a layer `gap_mm` before the
/// background, `k` the sensor's radians per mm: its length `|ψ²|` and the extra
/// equivalent distance past the layer, `arg(ψ²) / k`, mm.
pub fn diffuse_second_return(gap_mm: f64, k: f64) -> (f64, f64) {
    let (re, im) = lobe_average(k * gap_mm.max(0.0) / 2.0);
    let (sq_re, sq_im) = (re * re - im * im, 2.0 * re * im);
    (sq_re.hypot(sq_im), sq_im.atan2(sq_re) / k)
}

/// Steps of the lobe's quadrature in `u = cos θ` (midpoints).
pub const LOBE_STEPS_U: usize = 16;
/// Steps of the lobe's quadrature in azimuth.
pub const LOBE_STEPS_PHI: usize = 32;

/// What a pixel sees through a frosted layer of finite extent, as two phasors relative to
/// the layer's own phase `exp(i k df)` ([`lobe_returns`]): the background outside the
/// layer's shadow (lit straight, one crossing) and inside it (lit through the layer).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct DiffuseLobe {
    /// `Z_lit`, relative to the background behind the pixel lit straight (real, imaginary).
    pub lit: [f64; 2],
    /// `Z_shadow`, relative to the straight second return (real, imaginary).
    pub shadow: [f64; 2],
}

/// Layer distances in a [`LobeTable`].
pub const LOBE_TABLE_LEN: usize = 16;

/// A pixel's lobe at layer distances along its ray ([`ImageLayer::lobe_table`]): the lobe
/// changes with the hypothesised layer's distance, the outline stays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LobeTable {
    /// The first layer distance, mm.
    pub first_mm: f64,
    /// The step between distances, mm.
    pub step_mm: f64,
    /// The lobe at each distance.
    pub lobes: [DiffuseLobe; LOBE_TABLE_LEN],
}

impl LobeTable {
    /// The lobe of a layer at `df`, mm (linear between the distances, held beyond them).
    pub fn at(&self, df: f64) -> DiffuseLobe {
        let x = ((df - self.first_mm) / self.step_mm).clamp(0.0, (LOBE_TABLE_LEN - 1) as f64);
        if !x.is_finite() {
            return self.lobes[0];
        }
        let j = (x as usize).min(LOBE_TABLE_LEN - 2);
        let t = x - j as f64;
        let (a, b) = (self.lobes[j], self.lobes[j + 1]);
        let mix = |p: [f64; 2], q: [f64; 2]| [p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])];
        DiffuseLobe {
            lit: mix(a.lit, b.lit),
            shadow: mix(a.shadow, b.shadow),
        }
    }
}

/// Where a pixel's lobe starts and what it falls on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LobeGeometry {
    /// `P`: the layer's point on the pixel's ray (camera frame, mm).
    pub point: Vector3<f64>,
    /// The layer's unit normal, toward the background.
    pub normal: Vector3<f64>,
    /// `W0`: the background's point on the pixel's ray (the background is taken as the
    /// plane through it facing the camera).
    pub wall: Vector3<f64>,
}

/// The layer's light reaching the background behind the pixel, over what the emitter would
/// give it straight: `κ` and the inward path `l_in`, mm ([`lobe_returns`]); `(0, 0)` where no
/// patch lies before the background.
pub fn inward_light(wall: &Vector3<f64>, normal: &Vector3<f64>, patches: &[super::near_wall::Patch]) -> (f64, f64) {
    let (mut kappa, mut path) = (0.0, 0.0);
    for q in patches {
        let d = wall - q.point;
        let r2 = d.norm_squared();
        let (cos_layer, cos_wall) = (d.dot(normal), d.z);
        if !(r2 > 0.0 && cos_layer > 0.0 && cos_wall > 0.0) {
            continue;
        }
        let r = r2.sqrt();
        let e = q.solid_angle * cos_layer * cos_wall / (std::f64::consts::PI * r2 * r2);
        kappa += e;
        path += e * (q.point.norm() + r);
    }
    let (w0, cos0) = (wall.norm(), wall.z / wall.norm().max(f64::MIN_POSITIVE));
    if !(kappa > 0.0 && cos0 > 0.0) {
        return (0.0, 0.0);
    }
    (kappa * w0 * w0 / cos0, path / kappa)
}

/// The lobe behind `g.point` over a finite layer's shadow (module docs): `in_shadow(W)`
/// says whether the background point `W` lies in the layer's shadow (in the image, on the
/// layer's outline or inside it), `lin(W)` the emitted light toward it (its pixel's `Lin`),
/// `(kappa, inward_mm)` the layer's light on the background ([`inward_light`]); `k` the
/// sensor's radians per mm. Directions that do not reach the background add nothing.
pub fn lobe_returns(
    g: &LobeGeometry,
    k: f64,
    in_shadow: impl Fn(&Vector3<f64>) -> bool,
    lin: impl Fn(&Vector3<f64>) -> f64,
    (kappa, inward_mm): (f64, f64),
) -> DiffuseLobe {
    let n = g.normal.normalize();
    // Two directions across the normal.
    let helper = if n.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let e1 = n.cross(&helper).normalize();
    let e2 = n.cross(&e1);
    let (df, w0) = (g.point.norm(), g.wall.norm());
    let (cos0, lin0) = (g.wall.z / w0, lin(&g.wall));
    let mut out = DiffuseLobe::default();
    if !(cos0 > 0.0 && lin0 > 0.0 && df > 0.0 && g.wall.z > g.point.z) {
        return out;
    }
    let trig: Vec<(f64, f64)> = (0..LOBE_STEPS_PHI)
        .map(|j| ((j as f64 + 0.5) / LOBE_STEPS_PHI as f64 * std::f64::consts::TAU).sin_cos())
        .collect();
    for i in 0..LOBE_STEPS_U {
        let u = (i as f64 + 0.5) / LOBE_STEPS_U as f64;
        let weight = 2.0 * u / (LOBE_STEPS_U * LOBE_STEPS_PHI) as f64;
        let s = (1.0 - u * u).sqrt();
        for &(sp, cp) in &trig {
            let dir = n * u + (e1 * cp + e2 * sp) * s;
            if !(dir.z > 1e-9) {
                continue;
            }
            let t = (g.wall.z - g.point.z) / dir.z;
            let w = g.point + dir * t;
            let wn = w.norm();
            let (phase, strength, slot) = if in_shadow(&w) {
                (k * ((df + t + inward_mm) / 2.0 - df), weight * kappa, &mut out.shadow)
            } else {
                let cos = w.z / wn;
                let b = (cos / cos0).powi(3) * lin(&w) / lin0;
                (k * ((df + t + wn) / 2.0 - df), weight * b, &mut out.lit)
            };
            if strength > 0.0 && strength.is_finite() {
                let (ps, pc) = phase.sin_cos();
                slot[0] += strength * pc;
                slot[1] += strength * ps;
            }
        }
    }
    out
}

/// A layer seen in the image, for its pixels' lobes: its outline (`mask`, the whole image's),
/// its patches and normal, and the emitted light `Lin` per pixel.
pub struct ImageLayer<'a> {
    /// The camera.
    pub intrinsics: &'a super::camera::Intrinsics,
    /// The layer's pixels (its outline is its shadow's).
    pub mask: &'a super::ImageBuf<bool>,
    /// `Lin` per pixel (Eq. 13).
    pub emitted_light: &'a super::ImageBuf<f64>,
    /// The layer as patches ([`super::near_wall::layer_patches`]).
    pub patches: &'a [super::near_wall::Patch],
    /// The layer's unit normal toward the background ([`layer_normal`]).
    pub normal: Vector3<f64>,
}

impl ImageLayer<'_> {
    /// The pixel on `ray` (unit) at `df` before a background at `db` (ray distances, mm):
    /// its lobe ([`lobe_returns`]), `k` the sensor's radians per mm.
    pub fn lobe(&self, ray: &Vector3<f64>, df: f64, db: f64, k: f64) -> DiffuseLobe {
        self.lobe_with(ray, df, db, k, self.inward_light(ray, db))
    }

    /// The layer's light on the background at `db` along `ray` ([`inward_light`]): what the
    /// pixel's lobes share at every layer distance.
    fn inward_light(&self, ray: &Vector3<f64>, db: f64) -> (f64, f64) {
        inward_light(&(ray * db), &self.normal, self.patches)
    }

    /// [`Self::lobe`] with the layer's light on the background, `inward`, already found.
    fn lobe_with(&self, ray: &Vector3<f64>, df: f64, db: f64, k: f64, inward: (f64, f64)) -> DiffuseLobe {
        let (point, wall) = (ray * df, ray * db);
        let lin0 = self.lin_at(&wall);
        let lin = |w: &Vector3<f64>| self.lin_at(w).or(lin0).unwrap_or(0.0);
        lobe_returns(
            &LobeGeometry {
                point,
                normal: self.normal,
                wall,
            },
            k,
            |w| {
                self.pixel(w)
                    .is_some_and(|(c, r)| self.mask.data[r * self.mask.width + c])
            },
            lin,
            inward,
        )
    }

    /// The pixel on `ray` before a background at `db`: its lobe at [`LOBE_TABLE_LEN`] layer
    /// distances from `near_mm` to just before the background.
    pub fn lobe_table(&self, ray: &Vector3<f64>, near_mm: f64, db: f64, k: f64) -> LobeTable {
        let near = near_mm.min(0.9 * db).max(0.0);
        let step_mm = (0.98 * db - near) / (LOBE_TABLE_LEN - 1) as f64;
        let inward = self.inward_light(ray, db);
        LobeTable {
            first_mm: near,
            step_mm,
            lobes: std::array::from_fn(|j| self.lobe_with(ray, near + step_mm * j as f64, db, k, inward)),
        }
    }

    /// The pixel where `w` is seen, `None` outside the image.
    fn pixel(&self, w: &Vector3<f64>) -> Option<(usize, usize)> {
        let [u, v] = self.intrinsics.project(w)?;
        let (c, r) = (u.round(), v.round());
        (c >= 0.0 && r >= 0.0 && (c as usize) < self.mask.width && (r as usize) < self.mask.height)
            .then_some((c as usize, r as usize))
    }

    /// `Lin` toward `w`: its pixel's, or beyond the image the nearest border pixel's (the
    /// pinhole's image point held to the image); `None` where not finite.
    fn lin_at(&self, w: &Vector3<f64>) -> Option<f64> {
        let k = self.intrinsics;
        if !(w.z > 0.0) {
            return None;
        }
        let [u, v] = k
            .project(w)
            .unwrap_or([k.cx + k.fx * w.x / w.z, k.cy + k.fy * w.y / w.z]);
        let (wd, ht) = (self.emitted_light.width, self.emitted_light.height);
        let c = u.round().clamp(0.0, wd.saturating_sub(1) as f64) as usize;
        let r = v.round().clamp(0.0, ht.saturating_sub(1) as f64) as usize;
        self.emitted_light
            .data
            .get(r * wd + c)
            .copied()
            .filter(|l| l.is_finite() && *l > 0.0)
    }
}

/// The unit normal of the plane through the patches' points (least squares), toward the
/// background (positive z); the optical axis for fewer than three.
pub fn layer_normal(patches: &[super::near_wall::Patch]) -> Vector3<f64> {
    if patches.len() < 3 {
        return Vector3::z();
    }
    let mean = patches.iter().map(|p| p.point).sum::<Vector3<f64>>() / patches.len() as f64;
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    for p in patches {
        let d = p.point - mean;
        cov += d * d.transpose();
    }
    let eig = nalgebra::SymmetricEigen::new(cov);
    let (mut j, mut least) = (0, f64::INFINITY);
    for (i, &v) in eig.eigenvalues.iter().enumerate() {
        if v < least {
            (j, least) = (i, v);
        }
    }
    let n: Vector3<f64> = eig.eigenvectors.column(j).into_owned();
    if !n.iter().all(|v| v.is_finite()) || n.norm() == 0.0 {
        return Vector3::z();
    }
    let n = n.normalize();
    if n.z < 0.0 {
        -n
    } else {
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lobe_average_is_one_at_no_gap_and_shrinks_and_turns_with_it() {
        let (re, im) = lobe_average(0.0);
        assert!((re - 1.0).abs() < 1e-6 && im.abs() < 1e-9, "{re} {im}");
        // Small a: psi ~ 1 + i a E[1/u] = 1 + 2 i a.
        let (re, im) = lobe_average(1e-3);
        assert!((re - 1.0).abs() < 1e-4 && (im - 2e-3).abs() < 2e-5, "{re} {im}");
        let mut last = 1.0;
        for a in [0.2, 0.5, 1.0, 1.5] {
            let (re, im) = lobe_average(a);
            let len = re.hypot(im);
            assert!(len < last && im > 0.0, "{a}: {re} {im}");
            last = len;
        }
        // The table agrees with the quadrature between its entries.
        let a = 0.123_456 * TABLE_MAX;
        let (t, d) = (lobe_average(a), lobe_average_direct(a));
        assert!((t.0 - d.0).abs() < 1e-5 && (t.1 - d.1).abs() < 1e-5, "{t:?} {d:?}");
    }

    #[test]
    fn the_diffuse_return_lies_past_the_layer_by_more_than_the_gap_and_fades() {
        // 30 MHz: k = 2 pi / 4996.5 mm. A crossing's mean path over the lobe is twice the gap.
        let k = std::f64::consts::TAU / 4996.5;
        let (len, extra) = diffuse_second_return(100.0, k);
        assert!(len < 1.0 && len > 0.9, "{len}");
        assert!(extra > 100.0 && extra < 400.0, "{extra}");
        let (far, _) = diffuse_second_return(1000.0, k);
        assert!(far < len, "{far} {len}");
        let (len0, extra0) = diffuse_second_return(0.0, k);
        assert!((len0 - 1.0).abs() < 1e-6 && extra0.abs() < 1e-6, "{len0} {extra0}");
    }
    /// The lobe's phasor outside any shadow for a pixel on the axis, a layer and a background
    /// facing the camera, `Lin` flat: by an independent quadrature in the angle from the normal.
    fn unshadowed_by_angle(df: f64, db: f64, k: f64) -> (f64, f64) {
        let (g, steps) = (db - df, 200_000);
        let (mut re, mut im) = (0.0, 0.0);
        let dt = std::f64::consts::FRAC_PI_2 / steps as f64;
        for j in 0..steps {
            let th = (j as f64 + 0.5) * dt;
            let lateral = g * th.tan();
            let wn = db.hypot(lateral);
            let b = (db / wn).powi(3);
            let phase = k * ((df + g / th.cos() + wn) / 2.0 - df);
            let w = 2.0 * th.cos() * th.sin() * dt * b;
            re += w * phase.cos();
            im += w * phase.sin();
        }
        (re, im)
    }

    #[test]
    fn the_lobe_outside_any_shadow_matches_the_integral_over_its_angle() {
        let k = std::f64::consts::TAU / 4996.5;
        for (df, db) in [(1000.0, 1300.0), (1500.0, 3200.0), (700.0, 2400.0)] {
            let g = LobeGeometry {
                point: Vector3::new(0.0, 0.0, df),
                normal: Vector3::z(),
                wall: Vector3::new(0.0, 0.0, db),
            };
            let l = lobe_returns(&g, k, |_| false, |_| 1.0, (0.0, 0.0));
            let (re, im) = unshadowed_by_angle(df, db, k);
            assert!(
                (l.lit[0] - re).abs() < 5e-3 && (l.lit[1] - im).abs() < 5e-3,
                "{df} {db}: {:?} against ({re}, {im})",
                l.lit
            );
            assert_eq!(l.shadow, [0.0, 0.0]);
        }
    }

    #[test]
    fn a_lobe_all_in_shadow_is_the_filled_views_crossing_with_the_inward_path() {
        // Inward path |Q| + r = df + g: the shadowed phasor is exp(i k g / 2) psi(k g / 2).
        let k = std::f64::consts::TAU / 4996.5;
        let (df, db) = (1200.0, 2000.0);
        let gap = db - df;
        let g = LobeGeometry {
            point: Vector3::new(0.0, 0.0, df),
            normal: Vector3::z(),
            wall: Vector3::new(0.0, 0.0, db),
        };
        let l = lobe_returns(&g, k, |_| true, |_| 1.0, (1.0, df + gap));
        let (pr, pi) = lobe_average(k * gap / 2.0);
        let (s, c) = (k * gap / 2.0).sin_cos();
        let (re, im) = (pr * c - pi * s, pr * s + pi * c);
        assert!(
            (l.shadow[0] - re).abs() < 5e-3 && (l.shadow[1] - im).abs() < 5e-3,
            "{:?} against ({re}, {im})",
            l.shadow
        );
        assert_eq!(l.lit, [0.0, 0.0]);
    }

    #[test]
    fn the_layers_light_on_the_background_matches_the_integral_over_a_disc() {
        // A disc of the layer facing the camera, as patches, against the integral over its
        // radius of what each ring intercepts (`I df / |Q|^3` per area) passed on through a
        // cosine lobe (`g^2 / (pi r^4)` per area).
        let (df, db, radius, step) = (1000.0, 1300.0, 800.0, 5.0);
        let g = db - df;
        let mut patches = vec![];
        let n = (radius / step) as i32;
        for i in -n..=n {
            for j in -n..=n {
                let p = Vector3::new(i as f64 * step, j as f64 * step, df);
                if p.x.hypot(p.y) > radius {
                    continue;
                }
                let d = p.norm();
                patches.push(crate::physics::near_wall::Patch {
                    point: p,
                    solid_angle: step * step * df / (d * d * d),
                });
            }
        }
        let (kappa, path) = inward_light(&Vector3::new(0.0, 0.0, db), &Vector3::z(), &patches);
        let (mut want, mut want_path, steps) = (0.0, 0.0, 100_000);
        let dr = radius / steps as f64;
        for j in 0..steps {
            let rho = (j as f64 + 0.5) * dr;
            let (q, r2) = ((df * df + rho * rho).sqrt(), g * g + rho * rho);
            let e = std::f64::consts::TAU * rho * dr * df / (q * q * q) * g * g / (std::f64::consts::PI * r2 * r2);
            want += e;
            want_path += e * (q + r2.sqrt());
        }
        let (want, want_path) = (want * db * db, want_path / want);
        assert!((kappa / want - 1.0).abs() < 0.01, "{kappa} against {want}");
        assert!((path - want_path).abs() < 2.0, "{path} against {want_path}");
        // Below the unbounded layer's (db / df)^2: the disc ends 2.7 gaps from the centre.
        assert!(kappa > 0.5 * (db / df).powi(2) && kappa < (db / df).powi(2), "{kappa}");
    }
}
