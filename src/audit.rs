//! The audit's glue between the pipeline and the physics: gathers a
//! recording's pixels with known foreground distances into
//! [`AuditData`], measures recovery with a model, and draws the residual
//! trends as SVG (plain strings: the caller writes the files).
//!
//! Buffers in, buffers out: no ROS, no files.

use nalgebra::Vector3;

use crate::physics::audit::{AuditData, AuditPixel, Trend};
use crate::physics::camera::z_to_ray_distance;
use crate::physics::camera::Intrinsics;
use crate::physics::stats::median_sorted;
use crate::physics::ImageBuf;
use crate::physics::{diffuse, near_wall};
use crate::pipeline::{rmse_against_truth, DepthFrame, Pipeline, PipelineError};

/// Frames with fewer usable pixels than this carry no weight in the audit.
pub const MIN_PIXELS_PER_FRAME: usize = 20;

/// What the gathering found, beside the data.
#[derive(Debug, Clone, Default)]
pub struct GatherStats {
    /// Object frames with a ground-truth image.
    pub frames_with_truth: usize,
    /// Translucent pixels (all frames) where the truth has a value.
    pub translucent_with_truth: usize,
    /// Translucent pixels (all frames).
    pub translucent: usize,
}

/// Gathers the translucent pixels of `frames` (each with its ground-truth
/// z-depth, mm, NaN where no foreground) that sit inside the layer (all
/// four neighbours on it, so the true surface's normal is known), at most
/// `max_pixels` in all, spread evenly over the frames.
pub fn gather(
    pipe: &Pipeline,
    frames: &[(&DepthFrame, &ImageBuf<f32>)],
    max_pixels: usize,
) -> Result<(AuditData, GatherStats), PipelineError> {
    let bg = pipe.background().ok_or(PipelineError::NoBackground)?;
    let k = &pipe.intrinsics;
    let (w, h) = (k.width, k.height);
    let scale = k.ray_scale_map();
    let rays = k.unit_ray_map();
    let mut stats = GatherStats::default();
    let mut per_frame: Vec<(Vec<AuditPixel>, ImageBuf<f64>)> = vec![];
    for (frame, truth_z) in frames {
        let obs = pipe.observe(frame)?;
        if !truth_z.same_size(&obs.mask) {
            return Err(PipelineError::SizeMismatch {
                what: "ground truth",
                got_w: truth_z.width,
                got_h: truth_z.height,
                want_w: w,
                want_h: h,
            });
        }
        stats.frames_with_truth += 1;
        let truth = z_to_ray_distance(truth_z, &scale);
        let point = |c: usize, r: usize| -> Option<Vector3<f64>> {
            let t = truth.data[r * w + c];
            t.is_finite().then(|| rays.data[r * w + c] * t)
        };
        let mut px = vec![];
        for r in 0..h {
            for c in 0..w {
                let i = r * w + c;
                if !obs.mask.data[i] {
                    continue;
                }
                stats.translucent += 1;
                if !truth.data[i].is_finite() {
                    continue;
                }
                stats.translucent_with_truth += 1;
                if c == 0 || r == 0 || c + 1 >= w || r + 1 >= h {
                    continue;
                }
                let Some(&o) = obs.observations.get(i) else {
                    continue;
                };
                // Inside the layer: the 3x3 neighbourhood on it and seen through it.
                let inside = (r - 1..=r + 1).all(|rr| {
                    (c - 1..=c + 1).all(|cc| obs.mask.data[rr * w + cc] && truth.data[rr * w + cc].is_finite())
                });
                if !inside {
                    continue;
                }
                let (Some(xl), Some(xr), Some(yu), Some(yd)) =
                    (point(c - 1, r), point(c + 1, r), point(c, r - 1), point(c, r + 1))
                else {
                    continue;
                };
                let n = (xr - xl).cross(&(yd - yu));
                let norm = n.norm();
                if !(norm > 0.0) {
                    continue;
                }
                let cos = (n / norm).dot(&rays.data[i]).abs();
                if !(cos > 0.2) || !(truth.data[i] < o.background_distance_mm) {
                    continue;
                }
                px.push(AuditPixel {
                    frame: 0,
                    col: c,
                    row: r,
                    obs: o,
                    truth_mm: truth.data[i],
                    incidence_cos: cos,
                });
            }
        }
        per_frame.push((px, truth));
    }
    per_frame.retain(|(p, _)| p.len() >= MIN_PIXELS_PER_FRAME);
    let nf = per_frame.len().max(1);
    let cap = (max_pixels / nf).max(MIN_PIXELS_PER_FRAME);
    let mut pixels = vec![];
    for (f, (px, truth)) in per_frame.iter().enumerate() {
        let step = px.len().div_ceil(cap).max(1);
        // An odd step over raster order spreads the pick over rows and columns.
        let step = if step > 1 && step % 2 == 0 { step + 1 } else { step };
        let mut picked: Vec<AuditPixel> = px.iter().step_by(step).map(|p| AuditPixel { frame: f, ..*p }).collect();
        set_wall_view_factors(&mut picked, truth, &rays);
        // Every candidate is fitted on these pixels: the lobes for diffuse transmission too.
        set_diffuse_lobes(
            &mut picked,
            truth,
            &rays,
            (k, &bg.emitted_light),
            (pipe.config.model.sensor.phase(1.0), pipe.bounds().min_distance_mm),
        );
        pixels.extend(picked);
    }
    let coef = |f: &dyn Fn(usize) -> f64| {
        let mut v: Vec<f64> = (0..w * h).map(f).filter(|v| v.is_finite() && *v > 0.0).collect();
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            f64::NAN
        } else {
            median_sorted(&v)
        }
    };
    let (depth_noise_coef, ir_noise_coef) = if bg.frames >= 3 {
        (
            coef(&|i| bg.noise_mm.data[i] * bg.ir.data[i].max(0.0).sqrt()),
            coef(&|i| bg.ir_noise.data[i] / bg.ir.data[i].max(0.0).sqrt()),
        )
    } else {
        (f64::NAN, f64::NAN)
    };
    Ok((
        AuditData {
            pixels,
            frames: per_frame.len(),
            background_distance_mm: box_mean(&bg.distance_mm, 2),
            background_ir: box_mean(&bg.ir, 2),
            emitted_light: box_mean(&bg.emitted_light, 2),
            depth_noise_coef,
            ir_noise_coef,
        },
        stats,
    ))
}

/// Each pixel's view factor from its background point to the frame's true layer
/// (`truth`: ray distances, NaN off it), for a near wall's third return.
fn set_wall_view_factors(px: &mut [AuditPixel], truth: &ImageBuf<f64>, rays: &ImageBuf<Vector3<f64>>) {
    let patches = near_wall::layer_patches(&truth.data, rays, WALL_PATCH_STRIDE);
    for p in px.iter_mut() {
        let wall = rays.data[p.row * truth.width + p.col] * p.obs.background_distance_mm;
        p.obs.wall_view_factor = near_wall::view_factor(&wall, &patches);
    }
}

/// Each pixel's lobe through the frame's true layer (`truth`: ray distances, NaN off it; its
/// outline the layer's shadow), for a frosted layer's diffuse transmission
/// ([`diffuse::ImageLayer`]), `k` the sensor's radians per mm.
fn set_diffuse_lobes(
    px: &mut [AuditPixel],
    truth: &ImageBuf<f64>,
    rays: &ImageBuf<Vector3<f64>>,
    (intrinsics, lin): (&Intrinsics, &ImageBuf<f64>),
    (k, near_mm): (f64, f64),
) {
    let patches = near_wall::layer_patches(&truth.data, rays, WALL_PATCH_STRIDE);
    let mask = ImageBuf {
        width: truth.width,
        height: truth.height,
        data: truth.data.iter().map(|t| t.is_finite()).collect(),
    };
    let layer = diffuse::ImageLayer {
        intrinsics,
        mask: &mask,
        emitted_light: lin,
        patches: &patches,
        normal: diffuse::layer_normal(&patches),
    };
    for p in px.iter_mut() {
        let ray = rays.data[p.row * truth.width + p.col];
        p.obs.diffuse_lobe = Some(layer.lobe_table(&ray, near_mm, p.obs.background_distance_mm, k));
    }
}

/// The layer as one patch per this many pixels square, for the view factors.
const WALL_PATCH_STRIDE: usize = 3;

/// Mean over the `(2 r + 1)^2` neighbourhood of each pixel, of its finite samples.
fn box_mean(img: &ImageBuf<f64>, r: usize) -> ImageBuf<f64> {
    let (w, h) = (img.width, img.height);
    let mut out = ImageBuf::filled(w, h, f64::NAN);
    for row in 0..h {
        for col in 0..w {
            if !img.data[row * w + col].is_finite() {
                continue;
            }
            let (mut s, mut n) = (0.0, 0usize);
            for rr in row.saturating_sub(r)..(row + r + 1).min(h) {
                for cc in col.saturating_sub(r)..(col + r + 1).min(w) {
                    let v = img.data[rr * w + cc];
                    if v.is_finite() {
                        s += v;
                        n += 1;
                    }
                }
            }
            out.data[row * w + col] = s / n as f64;
        }
    }
    out
}

/// RMS of the recovered z-depth's error over translucent pixels with truth,
/// pooled over frames, with the pipeline's ξ (its config's choice); mm, and the pixels counted.
pub fn recovery_rmse(pipe: &Pipeline, frames: &[(&DepthFrame, &ImageBuf<f32>)], xi: f64) -> Option<(f64, usize)> {
    let est = crate::physics::XiEstimate::fixed(xi);
    let (mut s2, mut n) = (0.0, 0usize);
    for (frame, truth) in frames {
        let Ok(obs) = pipe.observe(frame) else {
            continue;
        };
        let out = pipe.recover(frame, &obs, &est);
        if let Some((rmse, count)) = rmse_against_truth(&out.corrected_z_mm, truth, &out.mask) {
            s2 += rmse * rmse * count as f64;
            n += count;
        }
    }
    (n > 0).then(|| ((s2 / n as f64).sqrt(), n))
}

/// An SVG plot of the mean depth residual (mm) in each bin of a quantity,
/// before (the baseline) and after (the chosen model), with standard errors.
pub fn trend_svg(before: &Trend, after: &Trend, title: &str) -> String {
    let (w, h) = (640.0, 400.0);
    let (ml, mr, mt, mb) = (70.0, 20.0, 40.0, 50.0);
    let xs = |t: &Trend| -> Vec<f64> { t.bins.iter().map(|b| 0.5 * (b[0] + b[1])).collect() };
    let all_x: Vec<f64> = xs(before)
        .into_iter()
        .chain(xs(after))
        .filter(|v| v.is_finite())
        .collect();
    let all_y: Vec<f64> = before
        .mean_mm
        .iter()
        .zip(&before.se_mm)
        .chain(after.mean_mm.iter().zip(&after.se_mm))
        .flat_map(|(m, s)| [m + s.max(0.0), m - s.max(0.0)])
        .chain([0.0])
        .filter(|v| v.is_finite())
        .collect();
    let (x0, x1) = min_max(&all_x).unwrap_or((0.0, 1.0));
    let (y0, y1) = min_max(&all_y).unwrap_or((-1.0, 1.0));
    let (x1, y1) = (if x1 > x0 { x1 } else { x0 + 1.0 }, if y1 > y0 { y1 } else { y0 + 1.0 });
    let px = |x: f64| ml + (x - x0) / (x1 - x0) * (w - ml - mr);
    let py = |y: f64| mt + (y1 - y) / (y1 - y0) * (h - mt - mb);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n<text x=\"{}\" y=\"20\" text-anchor=\"middle\" font-size=\"14\">{}</text>\n",
        w / 2.0,
        escape(title)
    );
    // Axes, zero line and ticks.
    s += &format!(
        "<line x1=\"{ml}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"black\"/>\n<line x1=\"{ml}\" y1=\"{mt}\" x2=\"{ml}\" y2=\"{}\" stroke=\"black\"/>\n",
        h - mb,
        w - mr,
        h - mb,
        h - mb
    );
    s += &format!(
        "<line x1=\"{ml}\" y1=\"{0:.1}\" x2=\"{1}\" y2=\"{0:.1}\" stroke=\"#999\" stroke-dasharray=\"4 3\"/>\n",
        py(0.0),
        w - mr
    );
    for k in 0..=4 {
        let xv = x0 + (x1 - x0) * k as f64 / 4.0;
        let yv = y0 + (y1 - y0) * k as f64 / 4.0;
        s += &format!(
            "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{}</text>\n<text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{:.1}</text>\n",
            px(xv),
            h - mb + 18.0,
            tick(xv),
            ml - 6.0,
            py(yv) + 4.0,
            yv
        );
    }
    s += &format!(
        "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{}</text>\n<text x=\"16\" y=\"{}\" text-anchor=\"middle\" transform=\"rotate(-90 16 {})\">held-out depth residual, mm (predicted - read)</text>\n",
        (ml + w - mr) / 2.0,
        h - 10.0,
        escape(before.quantity.name()),
        (mt + h - mb) / 2.0,
        (mt + h - mb) / 2.0
    );
    for (t, colour, label, dy) in [
        (before, "#d62728", "before (paper's model)", 0.0),
        (after, "#1f77b4", "after (chosen effects)", 16.0),
    ] {
        let pts: Vec<(f64, f64, f64)> = xs(t)
            .into_iter()
            .zip(&t.mean_mm)
            .zip(&t.se_mm)
            .map(|((x, m), s)| (x, *m, *s))
            .filter(|(x, m, _)| x.is_finite() && m.is_finite())
            .collect();
        let path: Vec<String> = pts
            .iter()
            .map(|(x, m, _)| format!("{:.1},{:.1}", px(*x), py(*m)))
            .collect();
        s += &format!(
            "<polyline fill=\"none\" stroke=\"{colour}\" stroke-width=\"2\" points=\"{}\"/>\n",
            path.join(" ")
        );
        for (x, m, se) in &pts {
            let se = if se.is_finite() { *se } else { 0.0 };
            s += &format!(
                "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"{colour}\"/>\n<line x1=\"{0:.1}\" y1=\"{2:.1}\" x2=\"{0:.1}\" y2=\"{3:.1}\" stroke=\"{colour}\"/>\n",
                px(*x),
                py(*m),
                py(m + se),
                py(m - se)
            );
        }
        s += &format!(
            "<text x=\"{}\" y=\"{}\" fill=\"{colour}\">{} (trend z {:.1})</text>\n",
            ml + 10.0,
            mt + 12.0 + dy,
            label,
            t.systematic_z
        );
    }
    s += "</svg>\n";
    s
}

fn min_max(v: &[f64]) -> Option<(f64, f64)> {
    let lo = v.iter().copied().reduce(f64::min)?;
    let hi = v.iter().copied().reduce(f64::max)?;
    Some((lo, hi))
}

fn tick(v: f64) -> String {
    if v.abs() >= 100.0 {
        format!("{v:.0}")
    } else if v.abs() >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}
