//! Pinhole intrinsics: z-depth (REP 118) <-> distance along the pixel's ray.
//! The physics works in ray distances (the light's path); images carry z.

use nalgebra::Vector3;

use super::buffer::ImageBuf;

/// Pinhole intrinsics of an undistorted image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Focal length in x, pixels.
    pub fx: f64,
    /// Focal length in y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (pixel centres at integer coordinates).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// A centred pinhole with the given full fields of view in degrees.
    pub fn from_fov(width: usize, height: usize, hfov_deg: f64, vfov_deg: f64) -> Self {
        let fx = width as f64 / 2.0 / (hfov_deg.to_radians() / 2.0).tan();
        let fy = height as f64 / 2.0 / (vfov_deg.to_radians() / 2.0).tan();
        Self {
            width,
            height,
            fx,
            fy,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
        }
    }

    /// The SR4000 of the paper: 176 x 144 pixels, 44 x 35 degrees.
    pub fn sr4000() -> Self {
        Self::from_fov(176, 144, 44.0, 35.0)
    }

    /// From a row-major camera matrix `K` (sensor_msgs/CameraInfo `k`);
    /// `None` when the focal lengths are not positive and finite.
    pub fn from_k(width: usize, height: usize, k: &[f64; 9]) -> Option<Self> {
        let (fx, fy, cx, cy) = (k[0], k[4], k[2], k[5]);
        let ok = fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0 && cx.is_finite() && cy.is_finite();
        ok.then_some(Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
        })
    }

    /// Row-major `K`.
    pub fn k(&self) -> [f64; 9] {
        [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]
    }

    /// The ray through pixel `(col, row)` with z = 1 (optical frame: x right, y down, z forward).
    pub fn ray(&self, col: usize, row: usize) -> Vector3<f64> {
        Vector3::new((col as f64 - self.cx) / self.fx, (row as f64 - self.cy) / self.fy, 1.0)
    }

    /// The ray with z = 1 through the image point `(u, v)` (pixel units, centres at integers).
    pub fn ray_at(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }

    /// Unit ray through pixel `(col, row)`.
    pub fn unit_ray(&self, col: usize, row: usize) -> Vector3<f64> {
        self.ray(col, row).normalize()
    }

    /// `ray distance / z` at a pixel.
    pub fn ray_scale(&self, col: usize, row: usize) -> f64 {
        self.ray(col, row).norm()
    }

    /// `ray distance / z` for every pixel.
    pub fn ray_scale_map(&self) -> ImageBuf<f64> {
        self.per_pixel(|col, row| self.ray_scale(col, row))
    }

    /// Unit rays for every pixel.
    pub fn unit_ray_map(&self) -> ImageBuf<Vector3<f64>> {
        self.per_pixel(|col, row| self.unit_ray(col, row))
    }

    fn per_pixel<T>(&self, f: impl Fn(usize, usize) -> T) -> ImageBuf<T> {
        let data = (0..self.height)
            .flat_map(|row| (0..self.width).map(move |col| (col, row)))
            .map(|(c, r)| f(c, r))
            .collect();
        ImageBuf {
            width: self.width,
            height: self.height,
            data,
        }
    }
}

/// Converts a z-depth image (mm) to ray distances (mm); invalid readings
/// (non-finite or not positive) become NaN.
pub fn z_to_ray_distance(z_mm: &ImageBuf<f32>, scale: &ImageBuf<f64>) -> ImageBuf<f64> {
    let data = z_mm
        .data
        .iter()
        .zip(&scale.data)
        .map(|(&z, &s)| {
            if z.is_finite() && z > 0.0 {
                z as f64 * s
            } else {
                f64::NAN
            }
        })
        .collect();
    ImageBuf {
        width: z_mm.width,
        height: z_mm.height,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sr4000_fov_gives_the_edge_angles() {
        let k = Intrinsics::sr4000();
        let edge = ((k.width as f64 / 2.0) / k.fx).atan().to_degrees() * 2.0;
        assert!((edge - 44.0).abs() < 1e-9);
        let r = k.unit_ray(0, 0);
        assert!((r.norm() - 1.0).abs() < 1e-12 && r.x < 0.0 && r.y < 0.0);
    }

    #[test]
    fn z_and_ray_distance_round_trip() {
        let k = Intrinsics::sr4000();
        let s = k.ray_scale(10, 20);
        assert!(s > 1.0);
        let z = 1234.0;
        let d = z * s;
        let p = k.unit_ray(10, 20) * d;
        assert!((p.z - z).abs() < 1e-9);
        let back = Intrinsics::from_k(176, 144, &k.k()).unwrap();
        assert_eq!(back, k);
        assert!(Intrinsics::from_k(176, 144, &[0.0; 9]).is_none());
    }
}
