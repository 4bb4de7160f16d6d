//! The error of a published depth against ground truth: one definition for every report.

use crate::physics::ImageBuf;

/// RMS z error (mm) of `z` against `truth` over `mask` pixels with finite truth
/// and a finite estimate; `(rmse, pixels)`.
pub fn rmse_against_truth(z: &ImageBuf<f32>, truth: &ImageBuf<f32>, mask: &ImageBuf<bool>) -> Option<(f64, usize)> {
    let mut s = 0.0;
    let mut n = 0;
    for i in 0..z.len() {
        if mask.data[i] && truth.data[i].is_finite() && z.data[i].is_finite() {
            let e = (z.data[i] - truth.data[i]) as f64;
            s += e * e;
            n += 1;
        }
    }
    (n > 0).then(|| ((s / n as f64).sqrt(), n))
}

/// What [`TruthError::mean_frame_rmse_mm`] is, in words: the error every report
/// (replay, the demo, the README's tables) leads with.
pub const TRUTH_ERROR_METRIC: &str = "mean over frames of the per-frame RMS z error, over the pixels in the mask with ground truth and a recovered depth (raw: the reading over the same pixels)";

/// What [`TruthError::pooled_rmse_mm`] is, in words.
pub const TRUTH_ERROR_POOLED: &str =
    "one RMS z error over those pixels of every frame together (frames weigh by their pixel count)";

/// The error against ground truth, frame by frame: one definition for every report.
#[derive(Debug, Clone, Default)]
pub struct TruthError {
    /// Per frame with pixels to compare: (recovered RMS mm, raw RMS mm, pixels).
    pub frames: Vec<(f64, f64, usize)>,
    /// Pixels in the mask with ground truth, whether recovered or not.
    pub segmented_with_truth: usize,
    /// Pixels with ground truth, in the mask or not.
    pub with_truth: usize,
    /// Per frame with truth: the RMS z error over every pixel with truth and a reading,
    /// published (the reading where nothing was recovered) and raw, mm ([`TRUTH_ERROR_EVERY`]).
    pub every: Vec<(f64, f64)>,
}

/// What [`TruthError::every_pixel_rmse_mm`] is, in words: the figure where abstaining counts.
pub const TRUTH_ERROR_EVERY: &str = "mean over frames of the per-frame RMS z error over every pixel with ground truth and a reading, the published depth where one was recovered and the reading where not (raw: the reading over the same pixels)";

impl TruthError {
    /// Adds one frame: the corrected and raw z (mm), the truth (mm, NaN where
    /// none) and the mask. Returns the frame's (recovered, raw, pixels), if any
    /// pixel counts.
    pub fn add(
        &mut self,
        corrected: &ImageBuf<f32>,
        raw: &ImageBuf<f32>,
        truth: &ImageBuf<f32>,
        mask: &ImageBuf<bool>,
    ) -> Option<(f64, f64, usize)> {
        self.add_every(corrected, raw, truth);
        let n = mask.len().min(truth.len()).min(corrected.len());
        let mut recovered = ImageBuf::filled(mask.width, mask.height, false);
        for i in 0..n {
            let t = truth.data[i].is_finite();
            self.with_truth += t as usize;
            if mask.data[i] && t {
                self.segmented_with_truth += 1;
                recovered.data[i] = corrected.data[i].is_finite();
            }
        }
        let (e, k) = rmse_against_truth(corrected, truth, &recovered)?;
        let (r, _) = rmse_against_truth(raw, truth, &recovered)?;
        self.frames.push((e, r, k));
        Some((e, r, k))
    }

    /// Adds one frame's every-pixel error ([`TRUTH_ERROR_EVERY`]): `published` is the depth
    /// as published (the reading itself for a frame passed through).
    pub fn add_every(&mut self, published: &ImageBuf<f32>, raw: &ImageBuf<f32>, truth: &ImageBuf<f32>) {
        let (mut e, mut r, mut n) = (0.0, 0.0, 0usize);
        for ((p, w), t) in published.data.iter().zip(&raw.data).zip(&truth.data) {
            if t.is_finite() && w.is_finite() {
                let p = if p.is_finite() { *p } else { *w };
                e += f64::from(p - t).powi(2);
                r += f64::from(w - t).powi(2);
                n += 1;
            }
        }
        if n > 0 {
            self.every.push(((e / n as f64).sqrt(), (r / n as f64).sqrt()));
        }
    }

    /// [`TRUTH_ERROR_EVERY`], published and raw (mm).
    pub fn every_pixel_rmse_mm(&self) -> Option<(f64, f64)> {
        mean_over_frames(self.every.iter().copied())
    }

    /// Pixels compared, all frames.
    pub fn pixels(&self) -> usize {
        self.frames.iter().map(|f| f.2).sum()
    }

    /// [`TRUTH_ERROR_METRIC`], recovered and raw (mm).
    pub fn mean_frame_rmse_mm(&self) -> Option<(f64, f64)> {
        mean_over_frames(self.frames.iter().map(|&(e, r, _)| (e, r)))
    }

    /// [`TRUTH_ERROR_POOLED`], recovered and raw (mm).
    pub fn pooled_rmse_mm(&self) -> Option<(f64, f64)> {
        let n = self.pixels() as f64;
        (n > 0.0).then(|| {
            let s = |g: fn(&(f64, f64, usize)) -> f64| {
                (self.frames.iter().map(|f| g(f) * g(f) * f.2 as f64).sum::<f64>() / n).sqrt()
            };
            (s(|f| f.0), s(|f| f.1))
        })
    }

    /// Share of the pixels in the mask with truth that got a recovered depth.
    pub fn recovered_of_segmented(&self) -> Option<f64> {
        (self.segmented_with_truth > 0).then(|| self.pixels() as f64 / self.segmented_with_truth as f64)
    }

    /// Share of the pixels with truth (in the mask or not) that got a recovered depth.
    pub fn recovered_of_truth(&self) -> Option<f64> {
        (self.with_truth > 0).then(|| self.pixels() as f64 / self.with_truth as f64)
    }

    /// The summary line: the metric named, raw and recovered, and the shares.
    /// Every frame with truth says something: where nothing was recovered, the raw error
    /// and a recovered share of 0.
    pub fn summary_line(&self) -> Option<String> {
        let (every, every_raw) = self.every_pixel_rmse_mm()?;
        let every = format!(
            "every pixel with truth (mean over {} frame(s) of the per-frame RMS z error, a pixel kept as read counting at its reading): raw {every_raw:.1} mm -> published {every:.1} mm",
            self.every.len()
        );
        let recovered = match self.mean_frame_rmse_mm() {
            Some((e, raw)) => format!(
                "over the pixels in the mask with truth and a recovered depth ({} frame(s)): raw {raw:.1} mm -> recovered {e:.1} mm",
                self.frames.len()
            ),
            None => "nothing recovered".to_string(),
        };
        Some(format!(
            "error against ground truth: {every}; {recovered}; recovered depth for {:.1} % of the pixels with truth ({:.1} % of those in the mask)",
            100.0 * self.recovered_of_truth().unwrap_or(0.0),
            100.0 * self.recovered_of_segmented().unwrap_or(0.0),
        ))
    }

    /// The report's keys: `mean_frame_rmse_mm` (and `_raw_`), `rmse_mm` (and
    /// `_raw_`, pooled), the shares, and `error_metric` saying which is which.
    pub fn json(&self) -> serde_json::Value {
        let mean = self.mean_frame_rmse_mm();
        let pooled = self.pooled_rmse_mm();
        serde_json::json!({
            "every_pixel_rmse_mm": self.every_pixel_rmse_mm().map(|m| m.0),
            "every_pixel_rmse_raw_mm": self.every_pixel_rmse_mm().map(|m| m.1),
            "mean_frame_rmse_mm": mean.map(|m| m.0),
            "mean_frame_rmse_raw_mm": mean.map(|m| m.1),
            "rmse_mm": pooled.map(|p| p.0),
            "rmse_raw_mm": pooled.map(|p| p.1),
            "truth_pixels": self.pixels(),
            "coverage": self.recovered_of_segmented(),
            "recovered_of_truth": self.recovered_of_truth(),
            "error_metric": {
                "mean_frame_rmse_mm": TRUTH_ERROR_METRIC,
                "rmse_mm": TRUTH_ERROR_POOLED,
                "every_pixel_rmse_mm": TRUTH_ERROR_EVERY,
                "coverage": "share of the pixels in the mask with truth that got a recovered depth",
                "recovered_of_truth": "share of the pixels with truth (in the mask or not) that got a recovered depth",
            },
        })
    }
}

/// The mean of per-frame (published, raw) figures; `None` without a frame.
fn mean_over_frames(frames: impl Iterator<Item = (f64, f64)>) -> Option<(f64, f64)> {
    let (mut e, mut r, mut k) = (0.0, 0.0, 0usize);
    for (a, b) in frames {
        e += a;
        r += b;
        k += 1;
    }
    (k > 0).then(|| (e / k as f64, r / k as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_error_counts_masked_pixels_with_truth_and_an_estimate() {
        let img = |v: Vec<f32>| ImageBuf {
            width: 4,
            height: 1,
            data: v,
        };
        let z = img(vec![1003.0, 996.0, f32::NAN, 2000.0]);
        let truth = img(vec![1000.0, 1000.0, 1000.0, f32::NAN]);
        let mask = ImageBuf {
            width: 4,
            height: 1,
            data: vec![true, true, true, true],
        };
        let (rmse, n) = rmse_against_truth(&z, &truth, &mask).expect("two pixels");
        assert_eq!(n, 2);
        assert!((rmse - (12.5f64).sqrt()).abs() < 1e-9, "{rmse}");
        let none = ImageBuf {
            width: 4,
            height: 1,
            data: vec![false; 4],
        };
        assert!(rmse_against_truth(&z, &truth, &none).is_none());
    }
}
