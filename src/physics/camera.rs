//! Camera intrinsics as camera_info gives them (K, the lens distortion, ROI
//! and binning): each pixel's ray, and z-depth (REP 118) <-> distance along
//! it. The physics works in ray distances (the light's path); images carry z.

use nalgebra::Vector3;

use super::buffer::ImageBuf;
pub use super::distortion::{Distortion, DistortionError};
use super::parallel::map_chunks_ordered;

/// Most pixels a calibrated camera's image may have (a garbage size is refused
/// before the per-pixel maps are made).
pub const MAX_PIXELS: usize = 1 << 25;

/// What is wrong with a calibration (camera_info).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// K's focal lengths are not positive and finite (K[0] == 0: uncalibrated).
    #[error("camera_info K has fx = {fx}, fy = {fy}: focal lengths must be positive and finite (an all-zero K means an uncalibrated camera)")]
    FocalLength {
        /// K[0].
        fx: f64,
        /// K[4].
        fy: f64,
    },
    /// K's principal point is not finite.
    #[error("camera_info K has principal point ({cx}, {cy}): it must be finite")]
    PrincipalPoint {
        /// K[2].
        cx: f64,
        /// K[5].
        cy: f64,
    },
    /// The distortion model or its coefficients.
    #[error("camera_info distortion: {0}")]
    Distortion(#[from] DistortionError),
    /// ROI, binning and size leave no usable image.
    #[error("camera_info {0}")]
    Window(String),
}

/// Where an image's pixels lie on the calibrated sensor (REP 104): camera_info's
/// ROI cuts a window out of the full-resolution image, then binning merges
/// `binning` sensor pixels into each image pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SensorWindow {
    /// Calibrated (full-resolution) size, pixels: camera_info's width and height.
    pub full_size: [u32; 2],
    /// ROI offset on the sensor, pixels.
    pub offset: [u32; 2],
    /// ROI size on the sensor, pixels.
    pub size: [u32; 2],
    /// Binning in x and y (1: none).
    pub binning: [u32; 2],
}

impl SensorWindow {
    /// The whole sensor, unbinned.
    pub fn full(width: usize, height: usize) -> Self {
        let size = [width as u32, height as u32];
        Self {
            full_size: size,
            offset: [0, 0],
            size,
            binning: [1, 1],
        }
    }

    /// A ROI (`offset`, `size`; a zero size: the full extent) of the
    /// calibrated `full_size`, then binned (0 or 1: none); checked to lie on
    /// the sensor and to leave an image of 1 to [`MAX_PIXELS`] pixels.
    pub fn new(full_size: [u32; 2], offset: [u32; 2], size: [u32; 2], binning: [u32; 2]) -> Result<Self, CameraError> {
        let w = Self {
            full_size,
            offset,
            size: [0, 1].map(|a| if size[a] == 0 { full_size[a] } else { size[a] }),
            binning: binning.map(|b| b.max(1)),
        };
        let ends = [0, 1].map(|a| u64::from(w.offset[a]) + u64::from(w.size[a]));
        if ends[0] > u64::from(full_size[0]) || ends[1] > u64::from(full_size[1]) {
            return Err(CameraError::Window(format!(
                "ROI {}x{} at ({}, {}) does not lie within the calibrated {}x{} image",
                w.size[0], w.size[1], w.offset[0], w.offset[1], full_size[0], full_size[1]
            )));
        }
        let [iw, ih] = w.image_size();
        if iw == 0 || ih == 0 || iw.saturating_mul(ih) > MAX_PIXELS {
            return Err(CameraError::Window(format!(
                "size {}x{} with ROI {}x{} and binning {}x{} gives a {iw}x{ih} image (must have 1 to {MAX_PIXELS} pixels)",
                full_size[0], full_size[1], w.size[0], w.size[1], w.binning[0], w.binning[1]
            )));
        }
        Ok(w)
    }

    /// Columns and rows of the image: the ROI's size over the binning.
    pub fn image_size(&self) -> [usize; 2] {
        [0, 1].map(|a| (self.size[a] / self.binning[a]) as usize)
    }

    /// Whether the image is the whole sensor, unbinned.
    pub fn is_full(&self) -> bool {
        self.offset == [0, 0] && self.size == self.full_size && self.binning == [1, 1]
    }

    /// Sensor coordinates of the image point `(u, v)` (pixel centres at
    /// integers on both): image pixel `c` covers sensor pixels
    /// `x0 + b c ..= x0 + b c + b - 1`, its centre midway.
    pub fn to_sensor(&self, u: f64, v: f64) -> [f64; 2] {
        let at = |t: f64, a: usize| {
            let b = f64::from(self.binning[a]);
            f64::from(self.offset[a]) + b * t + (b - 1.0) / 2.0
        };
        [at(u, 0), at(v, 1)]
    }

    /// Image coordinates of the sensor point `(x, y)` (inverse of [`Self::to_sensor`]).
    pub fn to_image(&self, x: f64, y: f64) -> [f64; 2] {
        let at = |s: f64, a: usize| {
            let b = f64::from(self.binning[a]);
            (s - f64::from(self.offset[a]) - (b - 1.0) / 2.0) / b
        };
        [at(x, 0), at(y, 1)]
    }
}

/// A camera: full-resolution K, lens distortion, and where the image lies on the sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Columns of the image.
    pub width: usize,
    /// Rows of the image.
    pub height: usize,
    /// Focal length in x, sensor pixels.
    pub fx: f64,
    /// Focal length in y, sensor pixels.
    pub fy: f64,
    /// Principal point x, sensor pixels (pixel centres at integer coordinates).
    pub cx: f64,
    /// Principal point y, sensor pixels.
    pub cy: f64,
    /// The lens distortion.
    pub distortion: Distortion,
    /// ROI and binning.
    pub window: SensorWindow,
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
            distortion: Distortion::None,
            window: SensorWindow::full(width, height),
        }
    }

    /// The SR4000 of the paper: 176 x 144 pixels, 44 x 35 degrees.
    pub fn sr4000() -> Self {
        Self::from_fov(176, 144, 44.0, 35.0)
    }

    /// A pinhole from a row-major camera matrix `K`, the whole sensor;
    /// `None` when the focal lengths are not positive and finite.
    pub fn from_k(width: usize, height: usize, k: &[f64; 9]) -> Option<Self> {
        Self::calibrated(k, Distortion::None, SensorWindow::full(width, height)).ok()
    }

    /// A calibrated camera: full-resolution row-major `K`, the lens, and
    /// where the image lies on the sensor (which gives the image's size).
    /// camera_info's is `Intrinsics::from_camera_info` (in `crate::image`).
    pub fn calibrated(k: &[f64; 9], distortion: Distortion, window: SensorWindow) -> Result<Self, CameraError> {
        check_k(k)?;
        let [width, height] = window.image_size();
        Ok(Self {
            width,
            height,
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
            distortion,
            window,
        })
    }

    /// This camera with another lens.
    pub fn with_distortion(self, distortion: Distortion) -> Self {
        Self { distortion, ..self }
    }

    /// Row-major `K` (full resolution).
    pub fn k(&self) -> [f64; 9] {
        [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]
    }

    /// The principal point in image coordinates.
    pub fn principal_point(&self) -> [f64; 2] {
        self.window.to_image(self.cx, self.cy)
    }

    /// The ray through pixel `(col, row)` with z = 1 (optical frame: x right, y down, z forward).
    pub fn ray(&self, col: usize, row: usize) -> Vector3<f64> {
        self.ray_at(col as f64, row as f64)
    }

    /// The ray with z = 1 through the image point `(u, v)` (pixel units,
    /// centres at integers), the lens's distortion undone; NaN where the
    /// lens model has no ray.
    pub fn ray_at(&self, u: f64, v: f64) -> Vector3<f64> {
        let [x, y] = self.window.to_sensor(u, v);
        let distorted = [(x - self.cx) / self.fx, (y - self.cy) / self.fy];
        match self.distortion.undistort(distorted) {
            Some([x, y]) => Vector3::new(x, y, 1.0),
            None => Vector3::from_element(f64::NAN),
        }
    }

    /// Image coordinates `(u, v)` where the point `p` (optical frame) is
    /// seen; `None` behind the camera or where the lens model has no image.
    pub fn project(&self, p: &Vector3<f64>) -> Option<[f64; 2]> {
        if !(p.z > 0.0) {
            return None;
        }
        let [x, y] = self.distortion.distort([p.x / p.z, p.y / p.z])?;
        Some(self.window.to_image(self.cx + self.fx * x, self.cy + self.fy * y))
    }

    /// Unit ray through pixel `(col, row)`.
    pub fn unit_ray(&self, col: usize, row: usize) -> Vector3<f64> {
        self.ray(col, row).normalize()
    }

    /// `ray distance / z` at a pixel.
    pub fn ray_scale(&self, col: usize, row: usize) -> f64 {
        self.ray(col, row).norm()
    }

    /// `ray distance / z` for every pixel (compute once per camera: each
    /// pixel's distortion is undone by iteration).
    pub fn ray_scale_map(&self) -> ImageBuf<f64> {
        self.per_pixel(|col, row| self.ray_scale(col, row))
    }

    /// Unit rays for every pixel (compute once per camera, as [`Self::ray_scale_map`]).
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

fn check_k(k: &[f64; 9]) -> Result<(), CameraError> {
    let (fx, fy, cx, cy) = (k[0], k[4], k[2], k[5]);
    if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
        return Err(CameraError::FocalLength { fx, fy });
    }
    if !(cx.is_finite() && cy.is_finite()) {
        return Err(CameraError::PrincipalPoint { cx, cy });
    }
    Ok(())
}

/// Converts a z-depth image (mm) to ray distances (mm); invalid readings
/// (non-finite or not positive) become NaN.
pub fn z_to_ray_distance(z_mm: &ImageBuf<f32>, scale: &ImageBuf<f64>) -> ImageBuf<f64> {
    // By rows over the pool (a frame's first pass, at camera rate).
    let data = map_chunks_ordered(&z_mm.data, 16 * z_mm.width.max(1), 32 * 1024, |start, zs| {
        zs.iter()
            .enumerate()
            .map(|(k, &z)| match scale.data.get(start + k) {
                Some(&s) if z.is_finite() && z > 0.0 => z as f64 * s,
                _ => f64::NAN,
            })
            .collect()
    });
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

    use crate::msgs::{CameraInfo, RegionOfInterest};

    /// A 176 x 144 camera_info with K of the SR4000 and the given lens.
    fn info(model: &str, d: &[f64]) -> CameraInfo {
        CameraInfo {
            width: 176,
            height: 144,
            distortion_model: model.into(),
            d: d.to_vec(),
            k: Intrinsics::sr4000().k(),
            ..CameraInfo::default()
        }
    }

    fn lenses() -> Vec<(&'static str, Vec<f64>)> {
        vec![
            ("plumb_bob", vec![-0.3, 0.1, 0.002, -0.001, 0.0]),
            ("plumb_bob", vec![0.25, -0.2, -0.003, 0.002, 0.15]),
            (
                "rational_polynomial",
                vec![0.3, -0.05, 0.001, 0.001, 0.0, 0.5, 0.02, 0.0],
            ),
            ("equidistant", vec![0.06, -0.02, 0.004, -0.001]),
        ]
    }

    #[test]
    fn every_pixel_centre_round_trips_through_each_lens() {
        for (model, d) in lenses() {
            let k = Intrinsics::from_camera_info(&info(model, &d)).unwrap();
            assert!(!matches!(k.distortion, Distortion::None), "{model}");
            let mut worst: f64 = 0.0;
            for row in 0..k.height {
                for col in 0..k.width {
                    let [u, v] = k.project(&k.ray(col, row)).unwrap_or([f64::NAN; 2]);
                    // Image error in normalized units (pixels over the focal length).
                    let e = ((u - col as f64) / k.fx).hypot((v - row as f64) / k.fy);
                    worst = worst.max(if e.is_nan() { f64::INFINITY } else { e });
                }
            }
            assert!(worst < 1e-9, "{model} {d:?}: worst round trip {worst:e}");
        }
    }

    #[test]
    fn plumb_bob_pixel_matches_a_hand_computation() {
        // K: fx 200, fy 210, cx 87.5, cy 71.5. The point (0.2, -0.1, 1) distorts to
        // (0.19925125, -0.098625625) (distortion.rs works it through): pixel
        // u = 87.5 + 200 * 0.19925125 = 127.35025, v = 71.5 - 210 * 0.098625625 = 50.78861875.
        let mut ci = info("plumb_bob", &[-0.3, 0.1, 0.01, 0.02, 0.05]);
        ci.k = [200.0, 0.0, 87.5, 0.0, 210.0, 71.5, 0.0, 0.0, 1.0];
        let k = Intrinsics::from_camera_info(&ci).unwrap();
        let [u, v] = k.project(&Vector3::new(0.4, -0.2, 2.0)).unwrap();
        assert!(
            (u - 127.35025).abs() < 1e-11 && (v - 50.78861875).abs() < 1e-11,
            "{u} {v}"
        );
        let r = k.ray_at(127.35025, 50.78861875);
        assert!(
            (r.x - 0.2).abs() < 1e-12 && (r.y + 0.1).abs() < 1e-12 && r.z == 1.0,
            "{r:?}"
        );
        // The pinhole would have put the ray elsewhere: the lens matters at this pixel.
        let pinhole = Intrinsics::from_k(176, 144, &ci.k)
            .unwrap()
            .ray_at(127.35025, 50.78861875);
        assert!((pinhole.x - 0.2).abs() > 5e-4, "{pinhole:?}");
    }

    #[test]
    fn zero_coefficients_are_the_pinhole() {
        let pinhole = Intrinsics::sr4000();
        for (model, n) in [
            ("plumb_bob", 5),
            ("rational_polynomial", 8),
            ("equidistant", 4),
            ("", 0),
        ] {
            let k = Intrinsics::from_camera_info(&info(model, &vec![0.0; n])).unwrap();
            assert_eq!(k, pinhole, "{model}");
            assert_eq!(k.unit_ray_map().data, pinhole.unit_ray_map().data);
        }
    }

    #[test]
    fn roi_then_binning_places_each_pixel_on_the_sensor() {
        // A 64 x 48 image: the 128 x 96 window at (16, 8) of the sensor, binned 2 x 2.
        let mut ci = info("plumb_bob", &[-0.3, 0.1, 0.0, 0.0, 0.0]);
        ci.binning_x = 2;
        ci.binning_y = 2;
        ci.roi = RegionOfInterest {
            x_offset: 16,
            y_offset: 8,
            width: 128,
            height: 96,
            do_rectify: false,
        };
        let binned = Intrinsics::from_camera_info(&ci).unwrap();
        assert_eq!((binned.width, binned.height), (64, 48));
        let full = Intrinsics::from_camera_info(&info("plumb_bob", &ci.d)).unwrap();
        assert_eq!((full.width, full.height), (176, 144));
        for (c, r) in [(0, 0), (63, 47), (10, 30)] {
            // Binned pixel (c, r) covers sensor pixels 16 + 2c, 16 + 2c + 1 (and rows alike): its centre is midway.
            let (x, y) = (16.0 + 2.0 * c as f64 + 0.5, 8.0 + 2.0 * r as f64 + 0.5);
            assert_eq!(binned.ray(c, r), full.ray_at(x, y), "pixel ({c}, {r})");
            let [u, v] = binned.project(&full.ray_at(x, y)).unwrap();
            assert!((u - c as f64).abs() < 1e-9 && (v - r as f64).abs() < 1e-9);
        }
        // Without distortion a binned pixel's ray (z = 1) is the mean of its sensor pixels' rays.
        let (mut pb, mut pf) = (ci.clone(), info("plumb_bob", &[]));
        pb.d.clear();
        pf.d.clear();
        let (pb, pf) = (
            Intrinsics::from_camera_info(&pb).unwrap(),
            Intrinsics::from_camera_info(&pf).unwrap(),
        );
        let mean = (pf.ray(36, 28) + pf.ray(37, 28) + pf.ray(36, 29) + pf.ray(37, 29)) / 4.0;
        assert!((pb.ray(10, 10) - mean).norm() < 1e-15);
        // Written back, the camera_info says the same.
        let again = crate::image::camera_info(&Default::default(), &binned);
        assert_eq!(Intrinsics::from_camera_info(&again), Ok(binned));
        assert_eq!((again.binning_x, again.roi.x_offset, again.roi.width), (2, 16, 128));
    }

    #[test]
    fn unusable_camera_infos_say_what_is_wrong() {
        let err = |ci: CameraInfo| Intrinsics::from_camera_info(&ci).unwrap_err().to_string();
        let mut ci = info("plumb_bob", &[]);
        ci.k = [0.0; 9];
        assert!(err(ci).contains("focal length"));
        let mut ci = info("plumb_bob", &[]);
        ci.k[2] = f64::NAN;
        assert!(err(ci).contains("principal point"));
        assert!(err(info("fisheye62", &[0.1; 4])).contains("\"fisheye62\" is not supported"));
        assert!(err(info("plumb_bob", &[0.1; 8])).contains("needs 5 coefficients in D, got 8"));
        assert!(err(info("equidistant", &[0.1, f64::INFINITY, 0.0, 0.0])).contains("D[1] is inf"));
        let mut ci = info("", &[]);
        ci.roi = RegionOfInterest {
            x_offset: 100,
            y_offset: 0,
            width: 100,
            height: 10,
            do_rectify: false,
        };
        assert!(err(ci).contains("does not lie within"));
        let mut ci = info("", &[]);
        ci.binning_x = 200;
        assert!(err(ci).contains("gives a 0x144 image"));
        let mut ci = info("", &[]);
        (ci.width, ci.height) = (u32::MAX, u32::MAX);
        assert!(err(ci).contains("pixels"));
        let mut ci = info("", &[]);
        ci.width = 0;
        assert!(err(ci).contains("0x144"));
    }
}
