//! `sensor_msgs/msg/Image` and `PointCloud2` <-> physics buffers.
//!
//! As depth_image_proc's "depth traits": the encoding is branched on once
//! per image, then a plain loop converts samples. Depth is REP 118 z-depth:
//! `16UC1` millimetres with 0 invalid, `32FC1` metres with non-finite (or
//! non-positive) invalid; inside the crate it is `f32` millimetres with NaN
//! invalid.
#![deny(missing_docs)]

use crate::msgs::{CameraInfo, Header, Image, PointCloud2, PointField, RegionOfInterest};
use crate::physics::camera::{CameraError, Distortion, SensorWindow};
use crate::physics::{ImageBuf, Intrinsics};

/// Why an image could not be converted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    /// An encoding this role does not take.
    #[error("{role} image: unsupported encoding {encoding:?} (supported: {supported})")]
    UnsupportedEncoding {
        /// The encoding found or asked for.
        encoding: String,
        /// `depth`, `IR`, ...
        role: &'static str,
        /// What the role takes.
        supported: &'static str,
    },
    /// Buffers that should have one size do not.
    #[error("{what}: sizes differ: {expected_width}x{expected_height} vs {width}x{height}")]
    SizeMismatch {
        /// Which buffers.
        what: &'static str,
        /// Width of the first.
        expected_width: usize,
        /// Height of the first.
        expected_height: usize,
        /// Width of the second.
        width: usize,
        /// Height of the second.
        height: usize,
    },
    /// A row stride shorter than a row of samples.
    #[error("{role} image ({encoding}, {width} wide): step {step} is less than the {min} bytes of a row")]
    BadStep {
        /// `depth`, `IR`, ...
        role: &'static str,
        /// The image's encoding.
        encoding: String,
        /// Columns.
        width: u32,
        /// Bytes per row claimed.
        step: u32,
        /// Bytes per row needed.
        min: usize,
    },
    /// Fewer data bytes than `step * height`.
    #[error("{role} image: {found} data bytes, expected step x height = {expected}")]
    DataLength {
        /// `depth`, `IR`, ...
        role: &'static str,
        /// Bytes needed.
        expected: usize,
        /// Bytes present.
        found: usize,
    },
    /// A size that does not fit the message's `u32` fields.
    #[error("{what}: {width}x{height} is too large for a ROS image")]
    TooLarge {
        /// Which output.
        what: &'static str,
        /// Columns.
        width: usize,
        /// Rows.
        height: usize,
    },
}

/// The sample type behind an encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Sample {
    U8,
    U16,
    F32,
    /// Two `f32` per pixel (`32FC2`).
    F32x2,
}

impl Sample {
    fn size(self) -> usize {
        match self {
            Sample::U8 => 1,
            Sample::U16 => 2,
            Sample::F32 => 4,
            Sample::F32x2 => 8,
        }
    }
}

/// Checks the layout and decodes each pixel's bytes with `decode`, row-major.
fn samples<T>(
    img: &Image,
    sample: Sample,
    role: &'static str,
    decode: impl Fn(&[u8]) -> T,
) -> Result<Vec<T>, ImageError> {
    let size = sample.size();
    let width = img.width as usize;
    let height = img.height as usize;
    let step = img.step as usize;
    let min = width.saturating_mul(size);
    if step < min {
        return Err(ImageError::BadStep {
            role,
            encoding: img.encoding.clone(),
            width: img.width,
            step: img.step,
            min,
        });
    }
    let expected = step.saturating_mul(height);
    if img.data.len() < expected {
        return Err(ImageError::DataLength {
            role,
            expected,
            found: img.data.len(),
        });
    }
    // Row by row into a buffer of the image's size (one allocation; each row's pixels
    // an exact-size iterator).
    let mut out = Vec::with_capacity(width.saturating_mul(height));
    for row in img.data.chunks_exact(step.max(1)).take(height) {
        out.extend(row.get(..min).unwrap_or_default().chunks_exact(size).map(&decode));
    }
    Ok(out)
}

fn read_u16(b: &[u8], big: bool) -> f32 {
    let a = [b[0], b[1]];
    f32::from(if big {
        u16::from_be_bytes(a)
    } else {
        u16::from_le_bytes(a)
    })
}

fn read_f32(b: &[u8], big: bool) -> f32 {
    let a = [b[0], b[1], b[2], b[3]];
    if big {
        f32::from_be_bytes(a)
    } else {
        f32::from_le_bytes(a)
    }
}

fn to_buf<T>(img: &Image, data: Vec<T>, role: &'static str) -> Result<ImageBuf<T>, ImageError> {
    let (w, h) = (img.width as usize, img.height as usize);
    let found = data.len();
    ImageBuf::from_vec(w, h, data).ok_or(ImageError::DataLength {
        role,
        expected: w.saturating_mul(h),
        found,
    })
}

const DEPTH_ENCODINGS: &str = "16UC1 / mono16 (mm), 32FC1 (m)";
const IR_ENCODINGS: &str = "16UC1, mono16, mono8, 32FC1";

/// Depth (REP 118 z-depth) as millimetres in `f32`; invalid samples (0 in
/// `16UC1`/`mono16`; NaN, infinite or <= 0 in `32FC1`) become NaN.
/// Honours `step` (row padding) and `is_bigendian`.
pub fn depth_mm(img: &Image) -> Result<ImageBuf<f32>, ImageError> {
    const ROLE: &str = "depth";
    let big = img.is_bigendian != 0;
    let data: Vec<f32> = match img.encoding.as_str() {
        "16UC1" | "mono16" => samples(img, Sample::U16, ROLE, |b| {
            let mm = read_u16(b, big);
            if mm == 0.0 {
                f32::NAN
            } else {
                mm
            }
        })?,
        "32FC1" => samples(img, Sample::F32, ROLE, |b| {
            let m = read_f32(b, big);
            if m.is_finite() && m > 0.0 {
                m * 1000.0
            } else {
                f32::NAN
            }
        })?,
        other => {
            return Err(ImageError::UnsupportedEncoding {
                encoding: other.to_string(),
                role: ROLE,
                supported: DEPTH_ENCODINGS,
            })
        }
    };
    to_buf(img, data, ROLE)
}

/// IR / intensity as `f32` counts, from `16UC1`, `mono16`, `mono8` or `32FC1`.
/// Honours `step` and `is_bigendian`.
pub fn ir_counts(img: &Image) -> Result<ImageBuf<f32>, ImageError> {
    const ROLE: &str = "IR";
    let big = img.is_bigendian != 0;
    let data: Vec<f32> = match img.encoding.as_str() {
        "16UC1" | "mono16" => samples(img, Sample::U16, ROLE, |b| read_u16(b, big))?,
        "mono8" => samples(img, Sample::U8, ROLE, |b| f32::from(b[0]))?,
        "32FC1" => samples(img, Sample::F32, ROLE, |b| read_f32(b, big))?,
        other => {
            return Err(ImageError::UnsupportedEncoding {
                encoding: other.to_string(),
                role: ROLE,
                supported: IR_ENCODINGS,
            })
        }
    };
    to_buf(img, data, ROLE)
}

/// The encoding of a phasor image: in-phase and quadrature, `f32` each.
pub const PHASOR_ENCODING: &str = "32FC2";

/// A multi-frequency camera's phasor image (`32FC2`: in-phase `Q1 - Q2` and
/// quadrature `Q3 - Q4` per pixel, the bucket differences of Eq. 5, in
/// counts) as `[a, b]` pairs. Honours `step` and `is_bigendian`; non-finite
/// samples are kept (the pixel has no measurement).
pub fn phasor_samples(img: &Image) -> Result<ImageBuf<[f32; 2]>, ImageError> {
    const ROLE: &str = "phasor";
    if img.encoding != PHASOR_ENCODING {
        return Err(ImageError::UnsupportedEncoding {
            encoding: img.encoding.clone(),
            role: ROLE,
            supported: PHASOR_ENCODING,
        });
    }
    let big = img.is_bigendian != 0;
    let data = samples(img, Sample::F32x2, ROLE, |b| {
        [read_f32(&b[..4], big), read_f32(&b[4..], big)]
    })?;
    to_buf(img, data, ROLE)
}

/// Encodes `[a, b]` phasors as a packed little-endian `32FC2` image.
pub fn phasor_image(header: &Header, phasors: &ImageBuf<[f32; 2]>) -> Result<Image, ImageError> {
    let mut data = Vec::with_capacity(8 * phasors.len());
    for p in &phasors.data {
        data.extend_from_slice(&p[0].to_le_bytes());
        data.extend_from_slice(&p[1].to_le_bytes());
    }
    image_msg(
        header,
        phasors.width,
        phasors.height,
        PHASOR_ENCODING,
        Sample::F32x2,
        data,
        "phasor image",
    )
}

/// A packed little-endian image message.
fn image_msg(
    header: &Header,
    width: usize,
    height: usize,
    encoding: &str,
    sample: Sample,
    data: Vec<u8>,
    what: &'static str,
) -> Result<Image, ImageError> {
    let too_large = || ImageError::TooLarge { what, width, height };
    let step = width.checked_mul(sample.size()).ok_or_else(too_large)?;
    Ok(Image {
        header: header.clone(),
        height: u32::try_from(height).map_err(|_| too_large())?,
        width: u32::try_from(width).map_err(|_| too_large())?,
        encoding: encoding.to_string(),
        is_bigendian: 0,
        step: u32::try_from(step).map_err(|_| too_large())?,
        data,
    })
}

// The encoders fill a buffer of the message's size (collecting a `flat_map` would grow
// it by doubling: its length is not known ahead).
fn u16_bytes<T: Copy>(values: &[T], map: impl Fn(T) -> u16) -> Vec<u8> {
    let mut out = Vec::with_capacity(2 * values.len());
    for &v in values {
        out.extend_from_slice(&map(v).to_le_bytes());
    }
    out
}

fn f32_bytes(values: &[f32], map: impl Fn(f32) -> f32) -> Vec<u8> {
    let mut out = Vec::with_capacity(4 * values.len());
    for &v in values {
        out.extend_from_slice(&map(v).to_le_bytes());
    }
    out
}

/// Encodes millimetre z-depth: `16UC1` (rounded mm; NaN, <= 0 or above
/// 65535 → 0, the invalid value) or `32FC1` (metres; invalid → NaN).
pub fn depth_image(header: &Header, z_mm: &ImageBuf<f32>, encoding: &str) -> Result<Image, ImageError> {
    let (w, h) = (z_mm.width, z_mm.height);
    match encoding {
        "16UC1" => {
            let data = u16_bytes(&z_mm.data, |mm| {
                let r = mm.round();
                if r.is_finite() && r >= 1.0 && r <= f32::from(u16::MAX) {
                    r as u16
                } else {
                    0
                }
            });
            image_msg(header, w, h, encoding, Sample::U16, data, "depth image")
        }
        "32FC1" => {
            let data = f32_bytes(&z_mm.data, |mm| {
                if mm.is_finite() && mm > 0.0 {
                    mm / 1000.0
                } else {
                    f32::NAN
                }
            });
            image_msg(header, w, h, encoding, Sample::F32, data, "depth image")
        }
        other => Err(ImageError::UnsupportedEncoding {
            encoding: other.to_string(),
            role: "depth",
            supported: "16UC1 (mm), 32FC1 (m)",
        }),
    }
}

/// Encodes IR counts: `16UC1` / `mono16` (rounded, clamped to 0..=65535,
/// NaN → 0), `mono8` (clamped to 0..=255) or `32FC1` (as is).
pub fn ir_image(header: &Header, counts: &ImageBuf<f32>, encoding: &str) -> Result<Image, ImageError> {
    let (w, h) = (counts.width, counts.height);
    // `as` saturates and maps NaN to 0.
    match encoding {
        "16UC1" | "mono16" => {
            let data = u16_bytes(&counts.data, |c| c.round() as u16);
            image_msg(header, w, h, encoding, Sample::U16, data, "IR image")
        }
        "mono8" => {
            let data = counts.data.iter().map(|&c| c.round() as u8).collect();
            image_msg(header, w, h, encoding, Sample::U8, data, "IR image")
        }
        "32FC1" => {
            let data = f32_bytes(&counts.data, |c| c);
            image_msg(header, w, h, encoding, Sample::F32, data, "IR image")
        }
        other => Err(ImageError::UnsupportedEncoding {
            encoding: other.to_string(),
            role: "IR",
            supported: IR_ENCODINGS,
        }),
    }
}

/// A `mono8` mask: 255 where true, 0 elsewhere. Sizes beyond `u32` are
/// clamped to an empty image.
pub fn mask_image(header: &Header, mask: &ImageBuf<bool>) -> Image {
    let data = mask.data.iter().map(|&m| if m { 255 } else { 0 }).collect();
    image_msg(header, mask.width, mask.height, "mono8", Sample::U8, data, "mask").unwrap_or_else(|_| Image {
        header: header.clone(),
        encoding: "mono8".into(),
        ..Image::default()
    })
}

/// A `mono16` image of each pixel's region: its material's id (0 where no region).
pub fn region_image(header: &Header, ids: &ImageBuf<u16>) -> Result<Image, ImageError> {
    let data = u16_bytes(&ids.data, |id| id);
    image_msg(
        header,
        ids.width,
        ids.height,
        "mono16",
        Sample::U16,
        data,
        "region image",
    )
}

/// Bytes per point of [`organized_cloud`]: x y z intensity (4 x float32),
/// translucent (uint8, padded to 4), sigma (float32).
pub const CLOUD_POINT_STEP: u32 = 24;

/// The point layout of [`organized_cloud`].
pub fn cloud_fields() -> Vec<PointField> {
    let field = |name: &str, offset, datatype| PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    };
    vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::FLOAT32),
        field("translucent", 16, PointField::UINT8),
        field("sigma", 20, PointField::FLOAT32),
    ]
}

/// A depth's standard deviation (mm) as a `32FC1` image in metres, NaN where there is none.
pub fn sigma_image(header: &Header, sigma_mm: &ImageBuf<f32>) -> Result<Image, ImageError> {
    let data = f32_bytes(&sigma_mm.data, |mm| if mm.is_finite() { mm / 1000.0 } else { f32::NAN });
    image_msg(
        header,
        sigma_mm.width,
        sigma_mm.height,
        "32FC1",
        Sample::F32,
        data,
        "sigma image",
    )
}

/// A per-pixel translucency ξ as a `32FC1` image, NaN where there is none
/// (`~/translucency_image`).
pub fn translucency_image(header: &Header, xi: &ImageBuf<f32>) -> Result<Image, ImageError> {
    let data = f32_bytes(&xi.data, |v| if v.is_finite() { v } else { f32::NAN });
    image_msg(
        header,
        xi.width,
        xi.height,
        "32FC1",
        Sample::F32,
        data,
        "translucency image",
    )
}

/// An organized `PointCloud2` (height x width of `xyz_m`): float32 `x y z`
/// in metres in the optical frame, float32 `intensity`, uint8 `translucent`
/// (1 or 0), float32 `sigma` (the depth's standard deviation, metres, NaN where
/// not recovered); `point_step` [`CLOUD_POINT_STEP`], little-endian,
/// `is_dense = false`. NaN coordinates mark invalid points. Pixels missing
/// from a smaller `intensity` / `translucent` / `sigma_m` get NaN / 0 / NaN.
pub fn organized_cloud(
    header: &Header,
    xyz_m: &ImageBuf<[f32; 3]>,
    intensity: &ImageBuf<f32>,
    translucent: &ImageBuf<bool>,
    sigma_m: &ImageBuf<f32>,
) -> PointCloud2 {
    let step = CLOUD_POINT_STEP as usize;
    let same = |w: usize, h: usize| w == xyz_m.width && h == xyz_m.height;
    let (inten_ok, flag_ok, sigma_ok) = (
        same(intensity.width, intensity.height),
        same(translucent.width, translucent.height),
        same(sigma_m.width, sigma_m.height),
    );
    let value = |ok: bool, buf: &ImageBuf<f32>, i: usize| {
        if ok {
            buf.data.get(i).copied().unwrap_or(f32::NAN)
        } else {
            f32::NAN
        }
    };
    let mut data = vec![0u8; xyz_m.len() * step];
    for (i, (p, out)) in xyz_m.data.iter().zip(data.chunks_exact_mut(step)).enumerate() {
        let inten = value(inten_ok, intensity, i);
        let flag = flag_ok && translucent.data.get(i).copied().unwrap_or(false);
        for (k, v) in [p[0], p[1], p[2], inten].into_iter().enumerate() {
            out[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
        }
        out[16] = u8::from(flag);
        out[20..24].copy_from_slice(&value(sigma_ok, sigma_m, i).to_le_bytes());
    }
    let dims = u32::try_from(xyz_m.width).ok().zip(u32::try_from(xyz_m.height).ok());
    let (width, height) = match dims {
        Some((w, h)) if xyz_m.len() == xyz_m.width.saturating_mul(xyz_m.height) => (w, h),
        // Inconsistent or oversized buffer: an empty cloud rather than a lie.
        _ => {
            data.clear();
            (0, 0)
        }
    };
    PointCloud2 {
        header: header.clone(),
        height,
        width,
        fields: cloud_fields(),
        is_bigendian: false,
        point_step: CLOUD_POINT_STEP,
        row_step: CLOUD_POINT_STEP.saturating_mul(width),
        data,
        is_dense: false,
    }
}

/// The CameraInfo of a camera: K, its distortion (`plumb_bob` with zero
/// coefficients when none), ROI and binning (zero when the whole sensor, as
/// drivers give them), identity rectification, `P = [K | 0]`.
pub fn camera_info(header: &Header, k: &Intrinsics) -> CameraInfo {
    let (model, d) = k.distortion.to_ros();
    let w = &k.window;
    let (roi, binning) = if w.is_full() {
        (RegionOfInterest::default(), [0, 0])
    } else {
        let roi = RegionOfInterest {
            x_offset: w.offset[0],
            y_offset: w.offset[1],
            width: w.size[0],
            height: w.size[1],
            do_rectify: false,
        };
        (roi, w.binning)
    };
    CameraInfo {
        header: header.clone(),
        height: w.full_size[1],
        width: w.full_size[0],
        distortion_model: model.into(),
        d,
        k: k.k(),
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x: binning[0],
        binning_y: binning[1],
        roi,
    }
}

impl Intrinsics {
    /// The camera a camera_info describes: K and D of the full-resolution
    /// sensor, the image cut by its ROI and then binned (REP 104); the
    /// image's size is what they leave. Errors say what is unusable.
    pub fn from_camera_info(info: &CameraInfo) -> Result<Self, CameraError> {
        let distortion = Distortion::from_ros(&info.distortion_model, &info.d)?;
        let roi = &info.roi;
        let window = SensorWindow::new(
            [info.width, info.height],
            [roi.x_offset, roi.y_offset],
            [roi.width, roi.height],
            [info.binning_x, info.binning_y],
        )?;
        Intrinsics::calibrated(&info.k, distortion, window)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msg(w: u32, h: u32, enc: &str, step: u32, big: bool, data: Vec<u8>) -> Image {
        Image {
            header: Header::new(7, "cam"),
            height: h,
            width: w,
            encoding: enc.into(),
            is_bigendian: u8::from(big),
            step,
            data,
        }
    }

    fn same(a: &[f32], b: &[f32]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x.is_nan() && y.is_nan()) || x == y)
    }

    #[test]
    fn depth_16uc1_with_row_padding() {
        // 2x2, step 6: two samples and 2 padding bytes per row.
        let data = vec![0xE8, 0x03, 0x00, 0x00, 0xAA, 0xBB, 0x01, 0x00, 0xFF, 0xFF, 0xCC, 0xDD];
        let d = depth_mm(&msg(2, 2, "16UC1", 6, false, data.clone())).unwrap();
        assert_eq!((d.width, d.height), (2, 2));
        assert!(same(&d.data, &[1000.0, f32::NAN, 1.0, 65535.0]));
        let m16 = depth_mm(&msg(2, 2, "mono16", 6, false, data)).unwrap();
        assert!(same(&m16.data, &d.data));
    }

    #[test]
    fn depth_big_endian() {
        let d = depth_mm(&msg(1, 1, "16UC1", 2, true, vec![0x03, 0xE8])).unwrap();
        assert_eq!(d.data, [1000.0]);
        let d = depth_mm(&msg(1, 1, "32FC1", 4, true, 1.5f32.to_be_bytes().to_vec())).unwrap();
        assert_eq!(d.data, [1500.0]);
    }

    #[test]
    fn depth_32fc1_invalid_values() {
        let vals = [1.25f32, 0.0, -1.0, f32::NAN, f32::INFINITY, 0.001];
        let data = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        let d = depth_mm(&msg(3, 2, "32FC1", 12, false, data)).unwrap();
        assert!(same(&d.data, &[1250.0, f32::NAN, f32::NAN, f32::NAN, f32::NAN, 1.0]));
    }

    #[test]
    fn depth_errors_say_what() {
        let err = depth_mm(&msg(1, 1, "rgb8", 3, false, vec![0; 3])).unwrap_err();
        assert!(matches!(&err, ImageError::UnsupportedEncoding { role: "depth", .. }));
        assert!(
            err.to_string().contains("rgb8") && err.to_string().contains("32FC1"),
            "{err}"
        );
        let err = depth_mm(&msg(4, 1, "16UC1", 6, false, vec![0; 8])).unwrap_err();
        assert!(matches!(err, ImageError::BadStep { step: 6, min: 8, .. }), "{err}");
        let err = depth_mm(&msg(2, 2, "16UC1", 4, false, vec![0; 7])).unwrap_err();
        assert!(
            matches!(
                err,
                ImageError::DataLength {
                    expected: 8,
                    found: 7,
                    ..
                }
            ),
            "{err}"
        );
        // Absurd sizes are errors, not panics or huge allocations.
        let err = depth_mm(&msg(u32::MAX, u32::MAX, "32FC1", u32::MAX, false, vec![])).unwrap_err();
        assert!(matches!(err, ImageError::BadStep { .. }), "{err}");
    }

    #[test]
    fn ir_encodings() {
        let d = ir_counts(&msg(2, 1, "mono8", 3, false, vec![10, 250, 99])).unwrap();
        assert_eq!(d.data, [10.0, 250.0]);
        let d = ir_counts(&msg(1, 1, "mono16", 2, false, vec![0x34, 0x12])).unwrap();
        assert_eq!(d.data, [4660.0]);
        let d = ir_counts(&msg(1, 1, "16UC1", 2, true, vec![0x12, 0x34])).unwrap();
        assert_eq!(d.data, [4660.0]);
        let d = ir_counts(&msg(1, 1, "32FC1", 4, false, 12.5f32.to_le_bytes().to_vec())).unwrap();
        assert_eq!(d.data, [12.5]);
        let err = ir_counts(&msg(1, 1, "bgr8", 3, false, vec![0; 3])).unwrap_err();
        assert!(
            matches!(err, ImageError::UnsupportedEncoding { role: "IR", .. }),
            "{err}"
        );
    }

    #[test]
    fn depth_encoding_round_trips() {
        let z = ImageBuf::from_vec(3, 2, vec![1000.4, f32::NAN, 70000.0, -5.0, 0.2, 1234.0]).unwrap();
        let h = Header::new(42, "cam");
        let img = depth_image(&h, &z, "16UC1").unwrap();
        assert_eq!((img.width, img.height, img.step, img.is_bigendian), (3, 2, 6, 0));
        assert_eq!(img.header, h);
        let back = depth_mm(&img).unwrap();
        assert!(same(
            &back.data,
            &[1000.0, f32::NAN, f32::NAN, f32::NAN, f32::NAN, 1234.0]
        ));

        let img = depth_image(&h, &z, "32FC1").unwrap();
        assert_eq!(img.step, 12);
        let back = depth_mm(&img).unwrap();
        assert!((back.data[0] - 1000.4).abs() < 1e-3);
        assert!(back.data[1].is_nan() && back.data[3].is_nan());
        assert!((back.data[4] - 0.2).abs() < 1e-5);

        let err = depth_image(&h, &z, "mono8").unwrap_err();
        assert!(matches!(err, ImageError::UnsupportedEncoding { .. }));
    }

    #[test]
    fn phasors_round_trip_and_bad_ones_are_errors() {
        let p = ImageBuf::from_vec(2, 1, vec![[1.5, -2.25], [f32::NAN, 3.0e4]]).unwrap();
        let h = Header::new(9, "cam");
        let img = phasor_image(&h, &p).unwrap();
        assert_eq!((img.encoding.as_str(), img.step, img.data.len()), ("32FC2", 16, 16));
        let back = phasor_samples(&img).unwrap();
        assert_eq!(back.data[0], [1.5, -2.25]);
        assert!(back.data[1][0].is_nan() && back.data[1][1] == 3.0e4);
        // Big-endian with row padding.
        let mut data: Vec<u8> = [1.0f32, 2.0].iter().flat_map(|v| v.to_be_bytes()).collect();
        data.extend([0, 0]);
        assert_eq!(
            phasor_samples(&msg(1, 1, "32FC2", 10, true, data)).unwrap().data,
            [[1.0, 2.0]]
        );
        let err = phasor_samples(&msg(1, 1, "32FC1", 4, false, vec![0; 4])).unwrap_err();
        assert!(
            matches!(err, ImageError::UnsupportedEncoding { role: "phasor", .. }),
            "{err}"
        );
        let err = phasor_samples(&msg(2, 1, "32FC2", 8, false, vec![0; 16])).unwrap_err();
        assert!(matches!(err, ImageError::BadStep { min: 16, .. }), "{err}");
        let err = phasor_samples(&msg(2, 2, "32FC2", 16, false, vec![0; 20])).unwrap_err();
        assert!(matches!(err, ImageError::DataLength { expected: 32, .. }), "{err}");
    }

    #[test]
    fn ir_encoding_clamps() {
        let c = ImageBuf::from_vec(4, 1, vec![-3.0, 300.4, f32::NAN, 70000.0]).unwrap();
        let h = Header::default();
        let img = ir_image(&h, &c, "mono8").unwrap();
        assert_eq!(img.data, [0, 255, 0, 255]);
        let img = ir_image(&h, &c, "16UC1").unwrap();
        assert_eq!(ir_counts(&img).unwrap().data, [0.0, 300.0, 0.0, 65535.0]);
        let img = ir_image(&h, &c, "mono16").unwrap();
        assert_eq!(img.encoding, "mono16");
        let img = ir_image(&h, &c, "32FC1").unwrap();
        assert!(same(&ir_counts(&img).unwrap().data, &c.data));
        assert!(ir_image(&h, &c, "rgb8").is_err());
    }

    #[test]
    fn mask() {
        let m = ImageBuf::from_vec(2, 2, vec![true, false, false, true]).unwrap();
        let img = mask_image(&Header::default(), &m);
        assert_eq!(
            (img.encoding.as_str(), img.step, img.data.as_slice()),
            ("mono8", 2, &[255, 0, 0, 255][..])
        );
    }

    #[test]
    fn cloud_layout() {
        let xyz = ImageBuf::from_vec(2, 1, vec![[1.0, 2.0, 3.0], [f32::NAN; 3]]).unwrap();
        let inten = ImageBuf::from_vec(2, 1, vec![10.0, 20.0]).unwrap();
        let tr = ImageBuf::from_vec(2, 1, vec![false, true]).unwrap();
        let sigma = ImageBuf::from_vec(2, 1, vec![0.004, f32::NAN]).unwrap();
        let c = organized_cloud(&Header::new(1, "cam"), &xyz, &inten, &tr, &sigma);
        assert_eq!((c.width, c.height, c.point_step, c.row_step), (2, 1, 24, 48));
        assert!(!c.is_dense && !c.is_bigendian);
        assert_eq!(c.data.len(), 48);
        let f = |off: usize| f32::from_le_bytes([c.data[off], c.data[off + 1], c.data[off + 2], c.data[off + 3]]);
        assert_eq!([f(0), f(4), f(8), f(12), f(20)], [1.0, 2.0, 3.0, 10.0, 0.004]);
        assert_eq!(c.data[16], 0);
        assert!(f(24).is_nan() && f(32).is_nan() && f(44).is_nan());
        assert_eq!((f(36), c.data[40]), (20.0, 1));
        let names: Vec<&str> = c.fields.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["x", "y", "z", "intensity", "translucent", "sigma"]);
        // Every field fits in the point.
        for f in &c.fields {
            let size = PointField::datatype_size(f.datatype).unwrap();
            assert!(f.offset as usize + size <= c.point_step as usize);
        }
        // A mismatched intensity buffer gives NaN intensity, not a panic.
        let small = ImageBuf::from_vec(1, 1, vec![5.0]).unwrap();
        let c = organized_cloud(&Header::default(), &xyz, &small, &tr, &sigma);
        assert!(f32::from_le_bytes([c.data[12], c.data[13], c.data[14], c.data[15]]).is_nan());
    }
}
