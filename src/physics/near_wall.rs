//! Light that a translucent layer's back and a diffuse background exchange: the third
//! return of a layer near a wall (not along one ray, as Eq. 3's terms are, but over the
//! wall around the pixel's point).
//!
//! The pixel's ray crosses the layer (ξ) and lights the wall at `p`. The wall's diffuse
//! light reaches the layer's back over the view factor `F` from `p` to the layer; the back
//! returns `(1 - ξ) X` of it; that light reaches the wall again, near `p`, and the camera
//! sees it through the layer (ξ) as it sees the second return. The layer's back is lit
//! too by the wall outside its own shadow, unattenuated (a share `1 - F` of what it sees,
//! against `ξ F` in the shadow). Relative to the second return's strength (Eq. 2):
//!
//! `L3 / L2 = F (1 - ξ) X Xb (ξ F + 1 - F) / ξ`
//!
//! at an equivalent distance `db + sqrt(2) (db - df)`: the diffuse exchange between two
//! parallel planes `g` apart travels about `sqrt(2) g` each way, on average.

use nalgebra::Vector3;

use super::ImageBuf;

/// Extra equivalent distance of the third return per mm between layer and background.
pub const PATH_PER_GAP: f64 = std::f64::consts::SQRT_2;

/// `L3 / L2` for a layer of translucency `xi` and albedo-cosine `x` before a background of
/// albedo-cosine `xb`, with `f` the view factor from the background point to the layer.
pub fn third_return_share(xi: f64, x: f64, xb: f64, f: f64) -> f64 {
    if !(xi > 0.0 && f > 0.0) {
        return 0.0;
    }
    f * (1.0 - xi) * x * xb * (xi * f + 1.0 - f) / xi
}

/// The third return's equivalent distance (mm) for a layer at `df` before a background at `db`.
pub fn third_return_distance(df: f64, db: f64) -> f64 {
    db + PATH_PER_GAP * (db - df).max(0.0)
}

/// A patch of the layer: its point (camera frame, mm) and the solid angle it fills, sr.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Patch {
    /// The patch's centre.
    pub point: Vector3<f64>,
    /// The solid angle of the pixels it stands for.
    pub solid_angle: f64,
}

/// The view factor from a background point `wall` to the layer's `patches`: the sum of
/// `cos(a) cos(b) A / (pi r^2)` over them, both surfaces taken as facing the camera (their
/// normals along its axis), each patch's area `A` its solid angle seen from the camera at
/// its distance. Patches not in front of the point add nothing; the sum is held to 1.
pub fn view_factor(wall: &Vector3<f64>, patches: &[Patch]) -> f64 {
    let mut sum = 0.0;
    for q in patches {
        let depth = q.point.norm();
        let gap = wall.z - q.point.z;
        if !(gap > 0.0 && depth > 0.0 && q.point.z > 0.0) {
            continue;
        }
        let area = q.solid_angle * depth * depth * depth / q.point.z;
        let r2 = (wall - q.point).norm_squared();
        sum += gap * gap * area / (std::f64::consts::PI * r2 * r2);
    }
    sum.min(1.0)
}

/// The solid angle a pixel's ray stands for (sr), from its neighbours' unit `rays`.
pub fn pixel_solid_angle(rays: &ImageBuf<Vector3<f64>>, i: usize) -> f64 {
    let w = rays.width.max(1);
    let h = rays.data.len() / w;
    let (r, c) = (i / w, i % w);
    let across = if c + 1 < w { i + 1 } else { i.saturating_sub(1) };
    let down = if r + 1 < h { i + w } else { i.saturating_sub(w) };
    let (a, b) = (rays.data[across] - rays.data[i], rays.data[down] - rays.data[i]);
    a.cross(&b).norm()
}

/// A layer given as its pixels' ray distances (`df`, mm; not finite off it) on `rays`, as
/// patches for [`view_factor`]: one per `stride` square block, at the block's first pixel.
pub fn layer_patches(df: &[f64], rays: &ImageBuf<Vector3<f64>>, stride: usize) -> Vec<Patch> {
    let (w, stride) = (rays.width.max(1), stride.max(1));
    df.iter()
        .enumerate()
        .filter(|&(i, d)| (i / w) % stride == 0 && (i % w) % stride == 0 && d.is_finite())
        .map(|(i, &d)| Patch {
            point: rays.data[i] * d,
            solid_angle: pixel_solid_angle(rays, i) * (stride * stride) as f64,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The view factor from a point to a parallel rectangle `2a x 2b` centred before it at
    /// `h` (four corner rectangles, the standard closed form).
    fn rectangle_view_factor(a: f64, b: f64, h: f64) -> f64 {
        let (x, y) = (a / h, b / h);
        let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
        let quarter = (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / (2.0 * std::f64::consts::PI);
        4.0 * quarter
    }

    #[test]
    fn the_sum_over_patches_is_the_rectangles_view_factor() {
        // A 240 x 310 mm sheet at 1750 mm, 1 mm patches, the wall point on the axis at 2000 mm.
        let z = 1750.0;
        let mut patches = vec![];
        for i in 0..240 {
            for j in 0..310 {
                let point = Vector3::new(i as f64 - 119.5, j as f64 - 154.5, z);
                // The solid angle of a 1 mm^2 patch facing the camera at that point.
                let solid_angle = point.z / point.norm().powi(3);
                patches.push(Patch { point, solid_angle });
            }
        }
        let f = view_factor(&Vector3::new(0.0, 0.0, 2000.0), &patches);
        let want = rectangle_view_factor(120.0, 155.0, 250.0);
        assert!((want - 0.271).abs() < 0.002, "{want}");
        assert!((f - want).abs() < 0.002 * want.max(1.0), "{f} against {want}");
        // Behind the layer, or with the layer beyond the point, nothing.
        assert_eq!(view_factor(&Vector3::new(0.0, 0.0, 1500.0), &patches), 0.0);
    }

    #[test]
    fn the_share_vanishes_without_a_view_or_a_layer_and_grows_with_the_view() {
        assert_eq!(third_return_share(0.65, 0.6, 1.0, 0.0), 0.0);
        assert_eq!(third_return_share(0.0, 0.6, 1.0, 0.3), 0.0);
        // The paper's document holder 250 mm before its white wall: F 0.27 at the centre.
        let s = third_return_share(0.65, 0.6, 1.0, 0.27);
        assert!((s - 0.27 * 0.35 * 0.6 * (0.65 * 0.27 + 0.73) / 0.65).abs() < 1e-12);
        assert!(s > third_return_share(0.65, 0.6, 1.0, 0.1));
        assert_eq!(
            third_return_distance(1750.0, 2000.0),
            2000.0 + 250.0 * std::f64::consts::SQRT_2
        );
    }
}
