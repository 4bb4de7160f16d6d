//! The latch: the background averaged over frames of the empty scene (its distance, IR, noise
//! and `Lin`), and where a recording's scene first changes from it.

use serde::Serialize;

use super::{DepthFrame, PipelineConfig, PipelineError, MIN_BACKGROUND_ALBEDO};
use crate::physics::emitted_light::{emitted_light_from_plane, fill_off_plane};
use crate::physics::segmentation::{change_threshold_mm, remove_small_regions, wrapped_difference};
use crate::physics::stats::median_and_sigma;
use crate::physics::{ImageBuf, Intrinsics};

/// Averages frames into a background (the latch).
#[derive(Debug, Clone)]
pub struct BackgroundLatch {
    range_mm: f64,
    first: Vec<f64>,
    n: Vec<u32>,
    sum_d: Vec<f64>,
    sum_d2: Vec<f64>,
    sum_ir: Vec<f64>,
    sum_ir2: Vec<f64>,
    frames: usize,
    width: usize,
    height: usize,
    /// `ray distance / z` of the camera the frames so far were of (made at the first push).
    scale: Option<(Intrinsics, ImageBuf<f64>)>,
}

/// A latched background.
#[derive(Debug, Clone)]
pub struct Background {
    /// `db`: ray distance, mm (NaN invalid).
    pub distance_mm: ImageBuf<f64>,
    /// `Ib`, counts.
    pub ir: ImageBuf<f64>,
    /// Per-pixel standard deviation of the readings over the latch, mm.
    pub noise_mm: ImageBuf<f64>,
    /// Per-pixel standard deviation of the IR over the latch, counts.
    pub ir_noise: ImageBuf<f64>,
    /// `Lin`.
    pub emitted_light: ImageBuf<f64>,
    /// Where `Lin` came from, in words.
    pub lin_source: String,
    /// `Lin` is a calibration's (Eq. 13-14), not derived from this background.
    pub lin_calibrated: bool,
    /// What looks wrong with this background, in words (empty when nothing does).
    pub warnings: Vec<String>,
    /// Frames averaged.
    pub frames: usize,
    /// Valid pixels.
    pub valid_pixels: usize,
    /// Median per-pixel noise, mm.
    pub median_noise_mm: f64,
}

impl BackgroundLatch {
    /// An empty latch for images of this size.
    /// `range_mm` is the sensor's unambiguous range: readings are unwrapped
    /// against each pixel's first one before they are averaged.
    pub fn new(width: usize, height: usize, range_mm: f64) -> Self {
        let n = width * height;
        Self {
            range_mm,
            first: vec![f64::NAN; n],
            n: vec![0; n],
            sum_d: vec![0.0; n],
            sum_d2: vec![0.0; n],
            sum_ir: vec![0.0; n],
            sum_ir2: vec![0.0; n],
            frames: 0,
            width,
            height,
            scale: None,
        }
    }

    /// Frames added so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Adds a frame (ray distances via the camera's intrinsics).
    pub fn push(&mut self, frame: &DepthFrame, intrinsics: &Intrinsics) -> Result<(), PipelineError> {
        super::check_size(frame, intrinsics)?;
        if self.scale.as_ref().is_none_or(|(k, _)| k != intrinsics) {
            self.scale = Some((*intrinsics, intrinsics.ray_scale_map()));
        }
        let Some((_, scale)) = &self.scale else {
            return Ok(());
        };
        for i in 0..self.width * self.height {
            let z = frame.z_mm.data[i] as f64;
            let ir = frame.ir.data[i] as f64;
            let mut d = z * scale.data[i];
            if z > 0.0 && d.is_finite() && ir.is_finite() && ir > 0.0 {
                if self.first[i].is_nan() {
                    self.first[i] = d;
                }
                d = self.first[i] + wrapped_difference(d, self.first[i], self.range_mm);
                self.n[i] += 1;
                self.sum_d[i] += d;
                self.sum_d2[i] += d * d;
                self.sum_ir[i] += ir;
                self.sum_ir2[i] += ir * ir;
            }
        }
        self.frames += 1;
        Ok(())
    }

    /// The averaged background, with `Lin` from the calibration if given,
    /// else from the background itself as a plane of `background_albedo`.
    pub fn finish(&self, intrinsics: &Intrinsics, config: &PipelineConfig) -> Result<Background, PipelineError> {
        let total = self.width * self.height;
        let Averages {
            d,
            ir,
            sd,
            ir_sd,
            valid,
        } = self.averages();
        if valid < (total / 20).max(10) {
            return Err(PipelineError::BackgroundInvalid { valid, total });
        }
        let mut noises: Vec<f64> = sd.data.iter().copied().filter(|v| v.is_finite()).collect();
        noises.sort_by(f64::total_cmp);
        let median_noise_mm = noises.get(noises.len() / 2).copied().unwrap_or(f64::NAN);
        let mut warnings = vec![];
        let lin_calibrated = config.lin_calibration.is_some();
        let (lin, lin_source) = match &config.lin_calibration {
            Some(lin) => {
                if lin.width != self.width || lin.height != self.height {
                    return Err(PipelineError::LinSize {
                        got_w: lin.width,
                        got_h: lin.height,
                        want_w: self.width,
                        want_h: self.height,
                    });
                }
                (lin.clone(), "calibration file (Eq. 13-14)".to_string())
            }
            None => lin_from_plane(&d, &ir, intrinsics, config, (valid, median_noise_mm), &mut warnings)?,
        };
        Ok(Background {
            distance_mm: d,
            ir,
            noise_mm: sd,
            ir_noise: ir_sd,
            emitted_light: lin,
            lin_source,
            lin_calibrated,
            warnings,
            frames: self.frames,
            valid_pixels: valid,
            median_noise_mm,
        })
    }

    /// Each pixel's mean reading and IR over the frames that saw it (at least half of them),
    /// and their standard deviations; NaN elsewhere.
    fn averages(&self) -> Averages {
        let need = (self.frames as u32).div_ceil(2).max(1);
        let filled = || ImageBuf::filled(self.width, self.height, f64::NAN);
        let mut a = Averages {
            d: filled(),
            ir: filled(),
            sd: filled(),
            ir_sd: filled(),
            valid: 0,
        };
        for i in 0..self.width * self.height {
            let n = self.n[i];
            if n < need {
                continue;
            }
            a.d.data[i] = (self.sum_d[i] / n as f64).rem_euclid(self.range_mm);
            a.ir.data[i] = self.sum_ir[i] / n as f64;
            if n > 1 {
                let sd = |s: f64, s2: f64| {
                    ((s2 / n as f64 - (s / n as f64).powi(2)).max(0.0) * n as f64 / (n - 1) as f64).sqrt()
                };
                a.sd.data[i] = sd(self.sum_d[i], self.sum_d2[i]);
                a.ir_sd.data[i] = sd(self.sum_ir[i], self.sum_ir2[i]);
            }
            a.valid += 1;
        }
        a
    }
}

/// Finds where the scene changes: the first frame whose readings (ray
/// distances, mm, NaN invalid) differ from the mean of the frames before it
/// by more than `threshold_mm`, compared as wrapped phases, over a region of
/// at least `min_region_pixels` (and 0.2 % of the image). `None` if never.
pub fn detect_scene_change(
    frames: &[ImageBuf<f64>],
    threshold_mm: f64,
    min_region_pixels: usize,
    range_mm: f64,
) -> Option<SceneChange> {
    let first = frames.first()?;
    let n = first.len();
    let mut anchor = vec![f64::NAN; n];
    let mut sum = vec![0.0f64; n];
    let mut sum2 = vec![0.0f64; n];
    let mut cnt = vec![0u32; n];
    let need = min_region_pixels.max(n / 500);
    let unwrap = |d: f64, a: f64| a + wrapped_difference(d, a, range_mm);
    for (k, f) in frames.iter().enumerate() {
        if f.len() != n {
            return None;
        }
        if k > 0 {
            // d - mean(before), with the noise it should have: the pixel's own spread once
            // three frames are in, before that the spread of this difference over the image.
            let diff: Vec<f64> = (0..n)
                .map(|i| {
                    let d = f.data[i];
                    if cnt[i] > 0 && d.is_finite() && d > 0.0 {
                        unwrap(d, anchor[i]) - sum[i] / cnt[i] as f64
                    } else {
                        f64::NAN
                    }
                })
                .collect();
            let mut finite: Vec<f64> = diff.iter().copied().filter(|v| v.is_finite()).collect();
            let global = median_and_sigma(&mut finite).map_or(0.0, |(_, s)| s);
            let mut changed = ImageBuf::filled(f.width, f.height, false);
            for i in 0..n {
                if !diff[i].is_finite() {
                    continue;
                }
                let c = cnt[i] as f64;
                let sigma = if cnt[i] >= 3 {
                    ((sum2[i] / c - (sum[i] / c).powi(2)).max(0.0) * c / (c - 1.0) * (1.0 + 1.0 / c)).sqrt()
                } else {
                    global
                };
                changed.data[i] = diff[i].abs() > change_threshold_mm(threshold_mm, sigma);
            }
            let (clean, _) = remove_small_regions(&changed, min_region_pixels);
            let count = clean.data.iter().filter(|&&c| c).count();
            if count >= need {
                return Some(SceneChange {
                    frame: k,
                    changed_pixels: count,
                });
            }
        }
        for i in 0..n {
            let d = f.data[i];
            if d.is_finite() && d > 0.0 {
                if anchor[i].is_nan() {
                    anchor[i] = d;
                }
                let u = unwrap(d, anchor[i]);
                sum[i] += u;
                sum2[i] += u * u;
                cnt[i] += 1;
            }
        }
    }
    None
}

/// Where the scene changed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SceneChange {
    /// Index of the first frame with the object.
    pub frame: usize,
    /// Pixels that changed in it.
    pub changed_pixels: usize,
}

/// The latch's per-pixel statistics ([`BackgroundLatch::averages`]).
struct Averages {
    d: ImageBuf<f64>,
    ir: ImageBuf<f64>,
    sd: ImageBuf<f64>,
    ir_sd: ImageBuf<f64>,
    valid: usize,
}

/// `Lin` from the latched background taken as a plane of the configured albedo, the emitter's
/// smooth fit off the plane; a warning where the background is no plane. `(valid, noise)`:
/// the latch's valid pixels and median noise, mm. Returns `Lin` and where it came from.
fn lin_from_plane(
    d: &ImageBuf<f64>,
    ir: &ImageBuf<f64>,
    intrinsics: &Intrinsics,
    config: &PipelineConfig,
    (valid, median_noise_mm): (usize, f64),
    warnings: &mut Vec<String>,
) -> Result<(ImageBuf<f64>, String), PipelineError> {
    let rays = intrinsics.unit_ray_map();
    let (mut lin, plane) = emitted_light_from_plane(d, ir, &rays, config.background_albedo)?;
    let on_plane = lin.data.iter().filter(|v| v.is_finite()).count();
    // Off the plane (a box on the wall, a corner) the emitter's smooth pattern stands in.
    let filled = fill_off_plane(&mut lin, &rays);
    // A plane fits a wall to about its noise; far worse, the background is no plane
    // (or the object was already there) and Lin from it is unreliable.
    let expected = (5.0 * median_noise_mm).max(20.0);
    if !(plane.rms_mm <= expected) || on_plane < valid / 2 {
        let noise = if median_noise_mm.is_finite() {
            format!("{median_noise_mm:.0} mm of noise")
        } else {
            "noise unknown from one frame".to_string()
        };
        warnings.push(format!(
            "the background is not a plane (fit RMS {:.0} mm against {noise}; {on_plane} of {valid} valid pixels on it): Lin derived from it is unreliable; give --lin-calibration (calibrate-lin), or check that the object was not in the background frames",
            plane.rms_mm
        ));
    }
    let src = format!(
        "derived from the latched background as a plane of albedo {} (no calibration file; plane fit RMS {:.1} mm; {filled} pixels off the plane from the emitter's smooth fit); albedos are bounded allowing for a background as dark as {MIN_BACKGROUND_ALBEDO}",
        config.background_albedo, plane.rms_mm
    );
    Ok((lin, src))
}

#[cfg(test)]
mod tests {
    use super::*;

    const RANGE_MM: f64 = 5000.0;

    fn frame(k: &Intrinsics, z: impl Fn(usize) -> f32) -> DepthFrame {
        DepthFrame {
            stamp_ns: 0,
            z_mm: ImageBuf {
                width: k.width,
                height: k.height,
                data: (0..k.width * k.height).map(z).collect(),
            },
            ir: ImageBuf::filled(k.width, k.height, 1000.0),
        }
    }

    #[test]
    fn the_latch_averages_its_frames_and_measures_their_noise() {
        let k = Intrinsics::from_fov(32, 24, 44.0, 35.0);
        let mut latch = BackgroundLatch::new(k.width, k.height, RANGE_MM);
        for z in [1999.0, 2000.0, 2001.0] {
            latch.push(&frame(&k, |_| z), &k).expect("a frame of the camera's size");
        }
        let bg = latch.finish(&k, &PipelineConfig::default()).expect("a background");
        assert_eq!((bg.frames, bg.valid_pixels), (3, k.width * k.height));
        let scale = k.ray_scale_map();
        for i in 0..k.width * k.height {
            assert!((bg.distance_mm.data[i] - 2000.0 * scale.data[i]).abs() < 1e-6 * 2000.0);
            // The sample standard deviation of -1, 0, +1 mm, along the ray.
            assert!(
                (bg.noise_mm.data[i] - scale.data[i]).abs() < 1e-6,
                "{}",
                bg.noise_mm.data[i]
            );
        }
        assert!(!bg.lin_calibrated && bg.warnings.is_empty(), "{:?}", bg.warnings);
    }

    #[test]
    fn readings_either_side_of_the_wrap_average_at_the_wrap() {
        let k = Intrinsics::from_fov(32, 24, 44.0, 35.0);
        let mut latch = BackgroundLatch::new(k.width, k.height, RANGE_MM);
        // The centre pixels' rays are nearly along the axis: 4990 and 4 mm straddle the wrap.
        for z in [4990.0, 4.0] {
            latch.push(&frame(&k, |_| z), &k).expect("a frame");
        }
        let bg = latch.finish(&k, &PipelineConfig::default()).expect("a background");
        let centre = 12 * k.width + 16;
        let d = bg.distance_mm.data[centre];
        let off = wrapped_difference(d, 0.0, RANGE_MM).abs();
        assert!(
            off < 10.0,
            "{d} mm: the mean of two readings 14 mm apart across the wrap"
        );
    }

    #[test]
    fn a_latch_without_valid_readings_is_refused_and_a_wrong_size_too() {
        let k = Intrinsics::from_fov(32, 24, 44.0, 35.0);
        let mut latch = BackgroundLatch::new(k.width, k.height, RANGE_MM);
        latch.push(&frame(&k, |_| 0.0), &k).expect("a frame");
        assert!(matches!(
            latch.finish(&k, &PipelineConfig::default()),
            Err(PipelineError::BackgroundInvalid { valid: 0, .. })
        ));
        let other = Intrinsics::from_fov(48, 36, 44.0, 35.0);
        assert!(matches!(
            latch.push(&frame(&other, |_| 2000.0), &k),
            Err(PipelineError::SizeMismatch { .. })
        ));
    }

    #[test]
    fn the_scene_change_is_the_first_frame_that_departs() {
        let (w, h) = (40, 30);
        let wall = |patch: bool| ImageBuf {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| {
                    if patch && (i % w) < 12 && (i / w) < 12 {
                        1500.0
                    } else {
                        2000.0
                    }
                })
                .collect::<Vec<f64>>(),
        };
        let frames: Vec<ImageBuf<f64>> = (0..8).map(|f| wall(f >= 5)).collect();
        let change = detect_scene_change(&frames, 30.0, 12, RANGE_MM).expect("a change");
        assert_eq!(change.frame, 5);
        assert_eq!(change.changed_pixels, 144);
        assert!(detect_scene_change(&frames[..5], 30.0, 12, RANGE_MM).is_none());
    }
}
