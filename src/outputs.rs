//! The node's output messages for one recovered frame, shared by the node and
//! `replay` so that both publish exactly the same thing.
#![deny(missing_docs)]

use crate::image::{depth_image, mask_image, organized_cloud, sigma_image, ImageError};
use crate::msgs::translucent_tof::TranslucencyEstimate;
use crate::msgs::{CameraInfo, Header, Image, PointCloud2};
use nalgebra::Vector3;

use crate::physics::{ImageBuf, XiEstimate};
use crate::pipeline::FrameOutput;

/// What the node publishes for one frame.
#[derive(Debug, Clone)]
pub struct OutputMessages {
    /// `~/depth/corrected`: the input's size, stamp and encoding.
    pub corrected: Image,
    /// `~/depth/camera_info`: the camera's, with the corrected depth's header.
    pub camera_info: CameraInfo,
    /// `~/translucent_mask`: `mono8`, 255 where translucent.
    pub mask: Image,
    /// `~/depth/corrected_sigma`: `32FC1`, metres, NaN where nothing was recovered.
    pub sigma: Image,
    /// `~/points`: organized cloud of the corrected depth.
    pub points: PointCloud2,
    /// `~/translucency`: one per region (one for the frame when it has none).
    pub estimates: Vec<TranslucencyEstimate>,
}

/// Builds the outputs of `out` (recovered or passed through). `header` is the input depth
/// image's; `camera` the camera's camera_info and unit rays
/// ([`crate::pipeline::Pipeline::rays`]); `depth_encoding` the input's encoding (`32FC1` is
/// kept, anything else becomes `16UC1`).
pub fn output_messages(
    header: &Header,
    camera: (&CameraInfo, &ImageBuf<Vector3<f64>>),
    out: &FrameOutput,
    ir: &ImageBuf<f32>,
    depth_encoding: &str,
) -> Result<OutputMessages, ImageError> {
    let (info, rays) = camera;
    let corrected = corrected_message(header, out, depth_encoding)?;
    let Companions {
        mask, sigma, estimates, ..
    } = companion_messages(header, None, out, ir)?;
    let points = cloud_message(header, rays, out, ir);
    Ok(OutputMessages {
        corrected,
        camera_info: CameraInfo {
            header: header.clone(),
            ..info.clone()
        },
        mask,
        sigma,
        points,
        estimates,
    })
}

/// `~/depth/corrected` of [`output_messages`] alone: what most consumers wait
/// for, so the node publishes it before it builds the rest.
pub fn corrected_message(header: &Header, out: &FrameOutput, depth_encoding: &str) -> Result<Image, ImageError> {
    let enc = if depth_encoding == "32FC1" { "32FC1" } else { "16UC1" };
    depth_image(header, &out.corrected_z_mm, enc)
}

/// The outputs that follow the corrected depth.
#[derive(Debug, Clone)]
pub struct Companions {
    /// `~/translucent_mask`.
    pub mask: Image,
    /// `~/depth/corrected_sigma`.
    pub sigma: Image,
    /// `~/points` (none without the camera's rays).
    pub points: Option<PointCloud2>,
    /// `~/translucency`: one per region (one for the frame when it has none).
    pub estimates: Vec<TranslucencyEstimate>,
}

/// The mask, cloud and estimates of [`output_messages`].
pub fn companion_messages(
    header: &Header,
    rays: Option<&ImageBuf<Vector3<f64>>>,
    out: &FrameOutput,
    ir: &ImageBuf<f32>,
) -> Result<Companions, ImageError> {
    let count = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
    let estimate = |xi: &XiEstimate, region_id: u32, region_pixels: usize, opaque: bool| TranslucencyEstimate {
        material: String::new(),
        class_probability: f64::NAN,
        header: header.clone(),
        xi: xi.xi,
        xi_lower: xi.interval[0],
        xi_upper: xi.interval[1],
        method: xi.method.as_str().into(),
        translucent_pixels: count(out.translucent_pixels),
        fit_residual_mm: out.fit_residual_mm,
        frames_pooled: count(xi.frames),
        region_id,
        region_pixels: count(region_pixels),
        opaque,
    };
    let mut estimates: Vec<TranslucencyEstimate> = out
        .regions
        .iter()
        .map(|r| match &r.class {
            Some(c) => TranslucencyEstimate {
                material: c.name.clone(),
                class_probability: c.probability,
                ..estimate(&r.xi, r.id, r.pixels, r.opaque)
            },
            None => estimate(&r.xi, r.id, r.pixels, r.opaque),
        })
        .collect();
    if let Some(why) = out.passthrough {
        estimates = vec![TranslucencyEstimate {
            method: format!("passthrough: {}", why.as_str()),
            ..estimate(&out.xi, 0, 0, false)
        }];
    } else if estimates.is_empty() {
        estimates.push(estimate(&out.xi, 0, 0, out.xi.is_opaque()));
    }
    Ok(Companions {
        mask: mask_image(header, &out.mask),
        sigma: sigma_image(header, &out.corrected_sigma_mm)?,
        points: rays.map(|r| cloud_message(header, r, out, ir)),
        estimates,
    })
}

/// `~/points`: the corrected depth along the camera's unit `rays`, with IR,
/// mask and sigma (m) per point.
fn cloud_message(header: &Header, rays: &ImageBuf<Vector3<f64>>, out: &FrameOutput, ir: &ImageBuf<f32>) -> PointCloud2 {
    let sigma_m = ImageBuf {
        width: out.corrected_sigma_mm.width,
        height: out.corrected_sigma_mm.height,
        data: out.corrected_sigma_mm.data.iter().map(|s| s / 1000.0).collect(),
    };
    organized_cloud(header, &points_m(rays, &out.corrected_z_mm), ir, &out.mask, &sigma_m)
}

/// Points in the optical frame (REP 103: x right, y down, z forward), metres,
/// along each pixel's unit ray `rays` (the camera's, lens distortion undone);
/// NaN where the depth is invalid.
pub fn points_m(rays: &ImageBuf<Vector3<f64>>, z_mm: &ImageBuf<f32>) -> ImageBuf<[f32; 3]> {
    let data = rays
        .data
        .iter()
        .enumerate()
        .map(|(i, u)| {
            let z = z_mm.data.get(i).copied().unwrap_or(f32::NAN) as f64 / 1000.0;
            let p = u * (z / u.z);
            if z > 0.0 && p.iter().all(|v| v.is_finite()) {
                [p.x as f32, p.y as f32, p.z as f32]
            } else {
                [f32::NAN; 3]
            }
        })
        .collect();
    ImageBuf {
        width: rays.width,
        height: rays.height,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::{camera_info, depth_image, depth_mm};
    use crate::physics::Intrinsics;
    use crate::pipeline::{DepthFrame, Passthrough};

    /// An invalid input pixel (0 in `16UC1`, NaN in `32FC1`) of a frame passed through is
    /// published as no distance: invalid in the corrected depth, no point in the cloud.
    #[test]
    fn invalid_pixels_are_published_as_no_distance_in_either_encoding() {
        let k = Intrinsics::from_fov(8, 6, 44.0, 35.0);
        let header = Header::new(5, "tof_optical_frame");
        let mut z = ImageBuf::filled(8, 6, 1500.0f32);
        z.data[3] = f32::NAN;
        for encoding in ["16UC1", "32FC1"] {
            let input = depth_image(&header, &z, encoding).expect("encodes");
            let frame = DepthFrame {
                stamp_ns: 5,
                z_mm: depth_mm(&input).expect("decodes"),
                ir: ImageBuf::filled(8, 6, 900.0),
            };
            let out = FrameOutput::passed_through(&frame, Passthrough::NoXiYet);
            let camera = (&camera_info(&header, &k), &k.unit_ray_map());
            let m = output_messages(&header, camera, &out, &frame.ir, encoding).expect("messages");
            assert_eq!(m.corrected.data, input.data, "{encoding}: not the input as read");
            let published = depth_mm(&m.corrected).expect("decodes");
            assert!(published.data[3].is_nan() && published.data[4] == 1500.0, "{encoding}");
            let step = m.points.point_step as usize;
            let cloud_z = |i: usize| f32::from_le_bytes([8, 9, 10, 11].map(|b| m.points.data[i * step + b]));
            assert!(cloud_z(3).is_nan() && (cloud_z(4) - 1.5).abs() < 1e-6, "{encoding}");
        }
    }
}
