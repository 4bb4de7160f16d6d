//! The node's multi-frequency path (`modulation_frequencies_hz` set): each
//! frame's `phasor_<k>/image_raw` images, paired by stamp with its depth and
//! IR, go through [`crate::pipeline::multifreq`] once the background is
//! latched, with the same outputs as the single-frequency path and
//! `~/translucency_image`.
//!
//! [`NodeCore`] keeps what it does for every camera: camera_info, the latch
//! service and its replies, the depth background, passing frames through
//! before a latch. This part latches the phasors of the same frames beside
//! it and recovers the frames after. A camera moved after the latch is not
//! watched for on this path. With `no_latch` (a moving camera, three
//! frequencies or more) nothing is latched: every frame is recovered on its
//! own from two free returns per pixel.

use crate::image::{depth_mm, ir_counts, phasor_samples, translucency_image};
use crate::msgs::{Image, TriggerResponse};
use crate::pipeline::multifreq::{MultiFrequencyConfig, MultiFrequencyStage, PhasorFrame};
use crate::pipeline::{DepthFrame, PipelineConfig};

use super::core::{DropCause, FrameResult, NodeCore, NodeOutputs};
use super::inbox::PairedFrame;

/// What a frame produced on this path.
#[derive(Debug)]
pub struct MultiFrequencyResult<T> {
    /// As the single-frequency path's.
    pub frame: FrameResult<T>,
    /// `~/translucency_image`, for a recovered frame.
    pub translucency: Option<Image>,
}

/// The multi-frequency path's state beside a [`NodeCore`].
#[derive(Debug)]
pub struct MultiFrequencyNode {
    config: MultiFrequencyConfig,
    depth_range_mm: f64,
    stage: Option<MultiFrequencyStage>,
    /// The frames of the latch in progress: phasors with their depth.
    pending: Vec<(PhasorFrame, DepthFrame)>,
    /// Latch nothing: every frame from two free returns per pixel (a moving camera).
    no_latch: bool,
}

impl MultiFrequencyNode {
    /// The path at `frequencies_hz` with `config`'s physics and waveform; with `no_latch`,
    /// every frame on its own (two free returns per pixel), whatever is latched.
    pub fn new(frequencies_hz: Vec<f64>, config: &PipelineConfig, no_latch: bool) -> Self {
        let mut mf = MultiFrequencyConfig::new(frequencies_hz, config.model.clone());
        mf.min_region_pixels = config.min_region_pixels;
        Self {
            config: mf,
            depth_range_mm: config.model.sensor.unambiguous_range_mm(),
            stage: None,
            pending: vec![],
            no_latch,
        }
    }

    /// After `core` took a camera_info: a new camera gets a new stage (its
    /// background, if any, forgotten, as the core forgets its own).
    pub fn on_camera_info<T>(&mut self, core: &NodeCore<T>) -> Result<(), String> {
        let Some(k) = core.intrinsics() else {
            return Ok(());
        };
        if self.stage.as_ref().is_some_and(|s| s.intrinsics == k) {
            return Ok(());
        }
        self.pending.clear();
        self.stage = None;
        let stage =
            MultiFrequencyStage::new(self.config.clone(), k).map_err(|e| format!("modulation_frequencies_hz: {e}"))?;
        self.stage = Some(stage);
        Ok(())
    }

    /// A latch has started: its frames are gathered from now.
    pub fn on_latch_started(&mut self) {
        self.pending.clear();
    }

    /// `~/clear_background`: the phasor background forgotten too.
    pub fn clear(&mut self) {
        self.pending.clear();
        if let Some(s) = &self.stage {
            self.stage = MultiFrequencyStage::new(self.config.clone(), s.intrinsics).ok();
        }
    }

    /// Whether a phasor background is latched.
    pub fn latched(&self) -> bool {
        self.stage.as_ref().is_some_and(|s| s.background().is_some())
    }

    /// One paired frame: latched beside the core's latch, recovered once
    /// latched, else handed to the core (passed through or dropped as it says).
    pub fn on_frame<T>(&mut self, core: &mut NodeCore<T>, f: &PairedFrame) -> MultiFrequencyResult<T> {
        let stamp = f.depth.header.stamp.as_log_time_ns();
        let phasors = match self.phasors(core, f, stamp) {
            Ok(p) => p,
            Err((cause, detail)) => return dropped(core, cause, detail),
        };
        if core.intrinsics().is_none() {
            return plain(core.on_frame(&f.depth, &f.ir));
        }
        if self.no_latch {
            return self
                .recover(core, f, &phasors)
                .unwrap_or_else(|(cause, detail)| dropped(core, cause, detail));
        }
        if core.latching() {
            return self.latch_frame(core, f, phasors);
        }
        if !self.latched() {
            return plain(core.on_frame(&f.depth, &f.ir));
        }
        match self.recover(core, f, &phasors) {
            Ok(r) => r,
            Err((cause, detail)) => dropped(core, cause, detail),
        }
    }

    /// The frame's phasor images decoded and checked against the camera's size.
    fn phasors<T>(&self, core: &NodeCore<T>, f: &PairedFrame, stamp: u64) -> Result<PhasorFrame, (DropCause, String)> {
        if f.phasors.len() != self.config.frequencies_hz.len() {
            return Err((
                DropCause::Pipeline,
                format!(
                    "frame at stamp {stamp} ns dropped: {} phasor images for {} modulation frequencies",
                    f.phasors.len(),
                    self.config.frequencies_hz.len()
                ),
            ));
        }
        let mut images = Vec::with_capacity(f.phasors.len());
        for (k, img) in f.phasors.iter().enumerate() {
            let p = phasor_samples(img).map_err(|e| {
                (
                    DropCause::BadImage,
                    format!("frame at stamp {stamp} ns dropped: phasor_{k}: {e}"),
                )
            })?;
            if let Some(c) = core.intrinsics().filter(|c| (c.width, c.height) != (p.width, p.height)) {
                return Err((
                    DropCause::SizeMismatch,
                    format!(
                        "frame at stamp {stamp} ns dropped: phasor_{k} is {}x{} but camera_info gives {}x{}",
                        p.width, p.height, c.width, c.height
                    ),
                ));
            }
            images.push(p);
        }
        Ok(PhasorFrame {
            stamp_ns: stamp,
            phasors: images,
        })
    }

    /// A frame of the latch in progress: the core latches its depth (and passes
    /// it through), its phasors are kept; when the core's latch completes the
    /// phasors are latched too, and the reply says how it went.
    fn latch_frame<T>(
        &mut self,
        core: &mut NodeCore<T>,
        f: &PairedFrame,
        phasors: PhasorFrame,
    ) -> MultiFrequencyResult<T> {
        let mut r = core.on_frame(&f.depth, &f.ir);
        if r.dropped.is_none() {
            if let Ok(depth) = depth_frame(f) {
                self.pending.push((phasors, depth));
            }
        }
        if !core.latching() {
            self.finish_latch(core, &mut r);
        }
        plain(r)
    }

    /// The core's latch has completed: the phasors of its frames latched, or
    /// the whole latch failed with the reason (and the core's background cleared).
    fn finish_latch<T>(&mut self, core: &mut NodeCore<T>, r: &mut FrameResult<T>) {
        let pending = std::mem::take(&mut self.pending);
        if core.background().is_none() {
            return;
        }
        let frames: Vec<_> = pending.iter().map(|(p, d)| (p, d)).collect();
        let outcome = match &mut self.stage {
            Some(stage) => {
                let range = stage.common_unambiguous_range_mm();
                stage
                    .latch(&frames, self.depth_range_mm)
                    .map(|bg| {
                        format!(
                            "; phasors at {} frequencies (common range {range:.0} mm) latched: {} usable pixels, the phasors and the depth image {:.1} mm apart on the background (no layer's sigma is less)",
                            self.config.frequencies_hz.len(),
                            bg.valid_pixels,
                            bg.systematic_mm
                        )
                    })
                    .map_err(|e| format!("could not latch the phasor background: {e}"))
            }
            None => Err("could not latch the phasor background: no camera".to_string()),
        };
        match outcome {
            Ok(extra) => {
                for (_, reply) in &mut r.replies {
                    reply.message.push_str(&extra);
                }
            }
            Err(why) => {
                core.clear();
                self.clear();
                for (_, reply) in &mut r.replies {
                    *reply = TriggerResponse {
                        success: false,
                        message: why.clone(),
                    };
                }
                r.notes.push((log::Level::Warn, why));
            }
        }
    }

    /// A frame after the latch, recovered pixel by pixel.
    fn recover<T>(
        &self,
        core: &mut NodeCore<T>,
        f: &PairedFrame,
        phasors: &PhasorFrame,
    ) -> Result<MultiFrequencyResult<T>, (DropCause, String)> {
        let stamp = phasors.stamp_ns;
        let stage = self.stage.as_ref().ok_or((
            DropCause::NoBackground,
            format!("frame at stamp {stamp} ns dropped: no phasor background"),
        ))?;
        let depth = depth_frame(f)?;
        let out = if self.no_latch {
            stage.process_unlatched(phasors, &depth)
        } else {
            stage.process(phasors, &depth)
        }
        .map_err(|e| (DropCause::Pipeline, format!("frame at stamp {stamp} ns dropped: {e}")))?;
        let image = |e: crate::image::ImageError| (DropCause::Pipeline, format!("frame at stamp {stamp} ns: {e}"));
        let translucency = translucency_image(&f.depth.header, &out.translucency).map_err(image)?;
        let outputs = NodeOutputs::recovered(
            &f.depth,
            core.camera_info(),
            out.frame,
            Some(stage.shared_rays()),
            depth.ir,
        )
        .map_err(image)?;
        core.processed += 1;
        Ok(MultiFrequencyResult {
            frame: FrameResult {
                outputs: Some(outputs),
                dropped: None,
                replies: vec![],
                notes: vec![],
            },
            translucency: Some(translucency),
        })
    }
}

/// The frame's depth and IR, decoded.
fn depth_frame(f: &PairedFrame) -> Result<DepthFrame, (DropCause, String)> {
    let stamp = f.depth.header.stamp.as_log_time_ns();
    let bad = |e: crate::image::ImageError| (DropCause::BadImage, format!("frame at stamp {stamp} ns dropped: {e}"));
    Ok(DepthFrame {
        stamp_ns: stamp,
        z_mm: depth_mm(&f.depth).map_err(bad)?,
        ir: ir_counts(&f.ir).map_err(bad)?,
    })
}

fn plain<T>(frame: FrameResult<T>) -> MultiFrequencyResult<T> {
    MultiFrequencyResult {
        frame,
        translucency: None,
    }
}

/// A frame dropped for `cause`, counted on the core; the message the first time.
fn dropped<T>(core: &mut NodeCore<T>, cause: DropCause, detail: String) -> MultiFrequencyResult<T> {
    let first = core.drops.record(cause);
    plain(FrameResult {
        outputs: None,
        dropped: Some((cause, first.then(|| format!("{detail} ({})", cause.advice())))),
        replies: vec![],
        notes: vec![],
    })
}
