//! What the node does with each paired frame, without DDS: validate, latch
//! the background on request, run the pipeline, build the output messages,
//! count what had to be dropped and why.

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::Vector3;

use crate::image::{depth_mm, ir_counts};
use crate::msgs::{CameraInfo, Image, TriggerResponse};
use crate::outputs::{companion_messages, corrected_message, Companions};
use crate::physics::{ImageBuf, Intrinsics};
use crate::pipeline::{Background, BackgroundLatch, DepthFrame, FrameOutput, Passthrough, Pipeline, PipelineConfig};

/// Why a frame was dropped (each logged once, then counted).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DropCause {
    /// Depth or IR in an encoding the node does not read, or a malformed buffer.
    BadImage,
    /// A sample whose CDR did not decode (truncated, a length past its end, an absurd size).
    Malformed,
    /// An image with more pixels than camera_info says, more data than its
    /// `step x height`, or more than the node takes at all.
    Oversized,
    /// Depth and IR, or images and camera_info, of different sizes.
    SizeMismatch,
    /// A depth or IR image whose partner with the same stamp never came.
    Unpaired,
    /// No camera_info received yet (the intrinsics are needed).
    NoCameraInfo,
    /// A camera_info that is not usable (focal length, distortion model, ROI, binning).
    BadCameraInfo,
    /// No background latched yet (call `~/latch_background`).
    NoBackground,
    /// Frames arrived faster than they were processed: the oldest was dropped.
    QueueFull,
    /// ξ not determined yet (too few translucent pixels so far).
    NoXiYet,
    /// The pipeline refused the frame.
    Pipeline,
    /// The camera moved after the latch (with `passthrough` off).
    CameraMoved,
}

impl DropCause {
    /// What to do about it, for the first log line of each cause.
    pub fn advice(self) -> &'static str {
        match self {
            DropCause::BadImage => "depth must be 16UC1/mono16 (mm) or 32FC1 (m); IR 16UC1, mono16, mono8 or 32FC1",
            DropCause::SizeMismatch => {
                "depth, IR and camera_info must come from the same sensor at the same resolution"
            }
            DropCause::Malformed => "the publisher sent a sample that is not a valid message of the topic's type",
            DropCause::Oversized => "images must be the size camera_info gives, with data of step x height bytes",
            DropCause::Unpaired => "depth and IR are paired by exact header stamp; check the driver stamps both alike",
            DropCause::NoCameraInfo => "waiting for depth/camera_info (remap it if the driver uses another name)",
            DropCause::BadCameraInfo => {
                "camera_info needs K with positive fx, fy; a distortion model of plumb_bob, rational_polynomial or equidistant with its coefficients (or none); ROI and binning within its width and height"
            }
            DropCause::NoBackground => "call ~/latch_background with the scene empty of the translucent object",
            DropCause::QueueFull => "frames arrive faster than they are processed; the oldest are dropped",
            DropCause::NoXiYet => "xi is estimated from the translucent pixels seen so far; set -p xi:=X to fix it",
            DropCause::Pipeline => "see the message",
            DropCause::CameraMoved => {
                "the view no longer lines up with the background: call ~/latch_background, or set relatch_on_move"
            }
        }
    }
}

/// Counters of dropped frames by cause; `record` says whether this is the first of its cause.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct DropCounters {
    /// Count per cause.
    pub by_cause: BTreeMap<DropCause, u64>,
}

impl DropCounters {
    /// Counts one drop; true the first time this cause is seen.
    pub fn record(&mut self, cause: DropCause) -> bool {
        let n = self.by_cause.entry(cause).or_insert(0);
        *n += 1;
        *n == 1
    }

    /// Count for a cause.
    pub fn get(&self, cause: DropCause) -> u64 {
        self.by_cause.get(&cause).copied().unwrap_or(0)
    }

    /// All drops.
    pub fn total(&self) -> u64 {
        self.by_cause.values().sum()
    }
}

/// A background latch in progress, on behalf of a service request.
#[derive(Debug)]
struct LatchInProgress<T> {
    /// The service call waiting for the reply; `None` for the node's own relatch.
    token: Option<T>,
    /// The frames so far and the camera they are of; `None` while waiting for
    /// the first camera_info.
    latch: Option<(BackgroundLatch, Intrinsics)>,
    started: std::time::Instant,
    /// Fails after `latch_timeout` (a latch on start-up waits as long as it takes).
    expires: bool,
}

impl<T> LatchInProgress<T> {
    fn frames(&self) -> usize {
        self.latch.as_ref().map_or(0, |(l, _)| l.frames())
    }
}

/// A recovered frame's outputs: the corrected depth made, the rest made when
/// asked ([`NodeOutputs::companions`]), after the corrected depth is out.
#[derive(Debug)]
pub struct NodeOutputs {
    /// `~/depth/corrected`.
    pub corrected: Image,
    /// `~/depth/camera_info`: the camera's, with the corrected depth's header
    /// (none before the first camera_info).
    pub camera_info: Option<CameraInfo>,
    /// The recovery it was made from.
    pub frame: FrameOutput,
    header: crate::msgs::Header,
    /// The camera's rays (none before the first camera_info: no cloud then).
    rays: Option<Arc<ImageBuf<Vector3<f64>>>>,
    ir: ImageBuf<f32>,
}

impl NodeOutputs {
    /// The outputs of a frame recovered beside [`NodeCore`] (the multi-frequency
    /// path), made as the core makes its own: the corrected depth in `depth`'s
    /// encoding, camera_info with its header.
    pub fn recovered(
        depth: &Image,
        camera_info: Option<&CameraInfo>,
        frame: FrameOutput,
        rays: Option<Arc<ImageBuf<Vector3<f64>>>>,
        ir: ImageBuf<f32>,
    ) -> Result<Self, crate::image::ImageError> {
        Ok(Self {
            corrected: corrected_message(&depth.header, &frame, &depth.encoding)?,
            camera_info: camera_info.map(|ci| CameraInfo {
                header: depth.header.clone(),
                ..ci.clone()
            }),
            frame,
            header: depth.header.clone(),
            rays,
            ir,
        })
    }

    /// The sigma image, mask, cloud and estimates (the same as `replay` writes);
    /// before the first camera_info, no cloud.
    pub fn companions(&self) -> Result<Companions, crate::image::ImageError> {
        companion_messages(&self.header, self.rays.as_deref(), &self.frame, &self.ir)
    }
}

/// What a frame produced.
#[derive(Debug, Default)]
pub struct FrameResult<T> {
    /// What to publish (none when the frame was dropped or latched).
    pub outputs: Option<NodeOutputs>,
    /// A frame dropped, why, and a message when it is the first of its cause.
    pub dropped: Option<(DropCause, Option<String>)>,
    /// Service replies now due (a latch that completed or failed).
    pub replies: Vec<(T, TriggerResponse)>,
    /// What the node should log (a camera moved, a relatch), with its level.
    pub notes: Vec<(log::Level, String)>,
}

/// How long the view must hold still before a moved camera is relatched, frames.
pub const STEADY_FRAMES: usize = 3;
/// A view holds still while fewer than this share of its pixels change between frames.
const STEADY_CHANGED_SHARE: f64 = 0.02;

/// A camera seen to have moved after the latch.
#[derive(Debug)]
struct Moved {
    /// Consecutive frames the view has held still.
    steady: usize,
    /// The last frame's readings, z mm.
    last_z_mm: ImageBuf<f32>,
}

/// The node's state between frames. `T` identifies a pending service call.
#[derive(Debug)]
pub struct NodeCore<T> {
    config: PipelineConfig,
    background_frames: usize,
    latch_timeout: std::time::Duration,
    info: Option<(CameraInfo, Intrinsics)>,
    pipeline: Option<Pipeline>,
    latch: Option<LatchInProgress<T>>,
    /// Drops so far.
    pub drops: DropCounters,
    /// Frames that produced outputs.
    pub processed: u64,
    /// Frames passed through uncorrected, by reason.
    pub passed: BTreeMap<Passthrough, u64>,
    /// Times the camera was seen to move after a latch.
    pub moves: u64,
    /// Publish the input uncorrected while nothing can be recovered (`passthrough`).
    passthrough: bool,
    /// Latch again once a moved camera's view holds still (`relatch_on_move`).
    relatch_on_move: bool,
    moved: Option<Moved>,
}

impl<T> NodeCore<T> {
    /// A node that latches `background_frames` frames per request and gives
    /// up on a latch that has not completed in `latch_timeout`.
    pub fn new(config: PipelineConfig, background_frames: usize, latch_timeout: std::time::Duration) -> Self {
        Self {
            config,
            background_frames: background_frames.max(1),
            latch_timeout,
            info: None,
            pipeline: None,
            latch: None,
            drops: DropCounters::default(),
            processed: 0,
            passed: BTreeMap::new(),
            moves: 0,
            passthrough: true,
            relatch_on_move: false,
            moved: None,
        }
    }

    /// `passthrough`: publish the input while nothing can be recovered (else drop it);
    /// `relatch_on_move`: latch again once a moved camera's view holds still.
    pub fn with_watch(mut self, passthrough: bool, relatch_on_move: bool) -> Self {
        self.passthrough = passthrough;
        self.relatch_on_move = relatch_on_move;
        self
    }

    /// Whether the camera is taken to have moved since the latch.
    pub fn camera_moved(&self) -> bool {
        self.moved.is_some()
    }

    /// The latched background, if any.
    pub fn background(&self) -> Option<&Background> {
        self.pipeline.as_ref().and_then(|p| p.background())
    }

    /// The camera_info in use, once one has come.
    pub fn camera_info(&self) -> Option<&CameraInfo> {
        self.info.as_ref().map(|(ci, _)| ci)
    }

    /// The camera, once camera_info has come.
    pub fn intrinsics(&self) -> Option<Intrinsics> {
        self.info.as_ref().map(|(_, k)| *k)
    }

    /// The camera's unit rays, once camera_info has come.
    pub fn shared_rays(&self) -> Option<Arc<ImageBuf<Vector3<f64>>>> {
        self.pipeline.as_ref().map(|p| p.shared_rays())
    }

    /// ξ frames pooled so far.
    pub fn xi_frames(&self) -> usize {
        self.pipeline.as_ref().map(|p| p.xi_frames()).unwrap_or(0)
    }

    /// Takes a camera_info. A change of size or intrinsics forgets the
    /// background (it no longer lines up) and starts a latch in progress over
    /// with the new camera (its frames so far were of the old one); returns a
    /// message when that happens.
    pub fn on_camera_info(&mut self, info: &CameraInfo) -> Result<Option<String>, (DropCause, String)> {
        let k = Intrinsics::from_camera_info(info).map_err(|e| (DropCause::BadCameraInfo, e.to_string()))?;
        if self.info.as_ref().is_some_and(|(_, old)| *old == k) {
            return Ok(None);
        }
        let had_background = self.background().is_some();
        let range_mm = self.config.model.sensor.unambiguous_range_mm();
        let restarted = self.latch.as_mut().and_then(|l| {
            let had = l.latch.is_some().then(|| l.frames());
            l.latch = Some((BackgroundLatch::new(k.width, k.height, range_mm), k));
            had
        });
        let note = self.info.as_ref().map(|(old, _)| {
            format!(
                "camera_info changed ({}x{} -> {}x{}){}{}",
                old.width,
                old.height,
                info.width,
                info.height,
                if had_background {
                    ": background forgotten, latch again"
                } else {
                    ""
                },
                restarted.map_or_else(String::new, |n| format!(
                    "; the latch in progress starts over with the new camera ({n} frames of the old one discarded)"
                ))
            )
        });
        self.info = Some((info.clone(), k));
        self.pipeline = Some(Pipeline::new(self.config.clone(), k));
        Ok(note)
    }

    /// Starts latching the next frames (waiting for camera_info first if none
    /// has come); replies at once if another latch is in progress. The latch
    /// fails if its frames have not come within `latch_timeout`.
    pub fn start_latch(&mut self, token: T) -> Result<(), (T, TriggerResponse)> {
        self.begin_latch(token, true)
    }

    /// [`Self::start_latch`] without the time limit (`latch_on_start`: the
    /// node latches as soon as frames flow, however late that is).
    pub fn start_latch_waiting(&mut self, token: T) -> Result<(), (T, TriggerResponse)> {
        self.begin_latch(token, false)
    }

    fn begin_latch(&mut self, token: T, expires: bool) -> Result<(), (T, TriggerResponse)> {
        if let Some(l) = &mut self.latch {
            if l.token.is_none() {
                // The node's own relatch: the caller takes it over and gets its reply.
                l.token = Some(token);
                l.expires = expires;
                l.started = std::time::Instant::now();
                return Ok(());
            }
            return Err((token, failure("a latch is already in progress; wait for its reply")));
        }
        let range_mm = self.config.model.sensor.unambiguous_range_mm();
        self.latch = Some(LatchInProgress {
            token: Some(token),
            latch: self
                .info
                .as_ref()
                .map(|(_, k)| (BackgroundLatch::new(k.width, k.height, range_mm), *k)),
            started: std::time::Instant::now(),
            expires,
        });
        Ok(())
    }

    /// Frames averaged per latch.
    pub fn background_frames(&self) -> usize {
        self.background_frames
    }

    /// How ξ is chosen now: `fixed` or the estimation method.
    pub fn xi_method(&self) -> &'static str {
        match self.config.xi {
            crate::pipeline::XiChoice::Fixed(_) => "fixed",
            crate::pipeline::XiChoice::Estimate(m) => m.as_str(),
        }
    }

    /// Whether a latch is in progress.
    pub fn latching(&self) -> bool {
        self.latch.is_some()
    }

    /// Takes the settings that may change at run time; they apply from the next
    /// frame. `forget_evidence`: the ξ evidence pooled so far was gathered under
    /// another model or method and is dropped (the background is kept).
    pub fn reconfigure(
        &mut self,
        config: PipelineConfig,
        background_frames: usize,
        latch_timeout: std::time::Duration,
        forget_evidence: bool,
    ) {
        self.background_frames = background_frames.max(1);
        self.latch_timeout = latch_timeout;
        if let Some(p) = &mut self.pipeline {
            p.config = config.clone();
            if forget_evidence {
                if let Some(bg) = p.background().cloned() {
                    p.set_background(bg);
                }
            }
        }
        self.config = config;
    }

    /// Forgets the background (and cancels a latch in progress).
    pub fn clear(&mut self) -> (TriggerResponse, Option<(T, TriggerResponse)>) {
        let cancelled = self
            .latch
            .take()
            .and_then(|l| l.token)
            .map(|t| (t, failure("cancelled by ~/clear_background")));
        self.moved = None;
        let had = self.background().is_some();
        if let Some(p) = &mut self.pipeline {
            p.clear_background();
        }
        let msg = if had {
            "background cleared; frames are passed through dropped until ~/latch_background is called"
        } else {
            "no background was latched"
        };
        (
            TriggerResponse {
                success: true,
                message: msg.into(),
            },
            cancelled,
        )
    }

    /// A latch that has waited too long for frames fails (called on every
    /// wake-up, with or without frames).
    pub fn check_latch_timeout(&mut self) -> Option<(T, TriggerResponse)> {
        let late = self
            .latch
            .as_ref()
            .is_some_and(|l| l.expires && l.started.elapsed() > self.latch_timeout);
        if !late {
            return None;
        }
        let mut l = self.latch.take()?;
        let token = l.token.take()?;
        let why = if l.latch.is_none() {
            format!(
                "no camera_info arrived in {:.1} s: cannot latch without the intrinsics (is depth/camera_info remapped right?)",
                self.latch_timeout.as_secs_f64()
            )
        } else {
            format!(
                "only {} of {} background frames arrived in {:.1} s (are depth and IR being published with equal stamps?)",
                l.frames(),
                self.background_frames,
                self.latch_timeout.as_secs_f64()
            )
        };
        Some((token, failure(&why)))
    }

    /// Handles one depth + IR pair (same stamp).
    pub fn on_frame(&mut self, depth: &Image, ir: &Image) -> FrameResult<T> {
        let mut result = FrameResult {
            outputs: None,
            dropped: None,
            replies: vec![],
            notes: vec![],
        };
        match self.frame(depth, ir, &mut result) {
            Ok(()) => {}
            Err((cause, detail)) => {
                let first = self.drops.record(cause);
                result.dropped = Some((cause, first.then(|| format!("{detail} ({})", cause.advice()))));
            }
        }
        result
    }

    fn frame(&mut self, depth: &Image, ir: &Image, result: &mut FrameResult<T>) -> Result<(), (DropCause, String)> {
        let frame = self.decode(depth, ir)?;
        let stamp = frame.stamp_ns;
        let Some((_, k)) = &self.info else {
            let why = (
                DropCause::NoCameraInfo,
                format!("frame at stamp {stamp} ns dropped: no camera_info yet"),
            );
            return self.pass_or_drop(Passthrough::NoCameraInfo, why, depth, frame, result);
        };
        let k = *k;
        if self.latch.is_some() {
            return self.latching_frame(depth, frame, result);
        }
        let Some(pipe) = &mut self.pipeline else {
            return Err((
                DropCause::NoCameraInfo,
                format!("frame at stamp {stamp} ns dropped: no camera_info yet"),
            ));
        };
        if pipe.background().is_none() {
            let why = (
                DropCause::NoBackground,
                format!("frame at stamp {stamp} ns dropped: no background latched"),
            );
            return self.pass_or_drop(Passthrough::NoBackground, why, depth, frame, result);
        }
        let mut obs = pipe
            .observe(&frame)
            .map_err(|e| (DropCause::Pipeline, format!("frame at stamp {stamp} ns dropped: {e}")))?;
        if let Some(d) = pipe.departure(&obs) {
            if self.watch_move(&d, &frame, k, result) {
                let why = (
                    DropCause::CameraMoved,
                    format!("frame at stamp {stamp} ns dropped: the camera moved after the latch"),
                );
                return self.pass_or_drop(Passthrough::CameraMoved, why, depth, frame, result);
            }
        }
        let Some(pipe) = &mut self.pipeline else {
            return Ok(());
        };
        pipe.add_xi_evidence(&mut obs);
        let Some(out) = pipe.recover_regions(&frame, &obs) else {
            let why = (
                DropCause::NoXiYet,
                format!(
                    "frame at stamp {stamp} ns not published: xi not determined yet ({} translucent pixels)",
                    obs.translucent_pixels
                ),
            );
            return self.pass_or_drop(Passthrough::NoXiYet, why, depth, frame, result);
        };
        self.publish(depth, out, frame, result)
    }

    /// The depth and IR images as a frame, both of the camera's size (before any
    /// camera_info, the depth's).
    fn decode(&self, depth: &Image, ir: &Image) -> Result<DepthFrame, (DropCause, String)> {
        let stamp = depth.header.stamp.as_log_time_ns();
        let z_mm =
            depth_mm(depth).map_err(|e| (DropCause::BadImage, format!("frame at stamp {stamp} ns dropped: {e}")))?;
        let ir_buf =
            ir_counts(ir).map_err(|e| (DropCause::BadImage, format!("frame at stamp {stamp} ns dropped: {e}")))?;
        let (want_w, want_h, by) = self
            .info
            .as_ref()
            .map_or((z_mm.width, z_mm.height, "the depth image"), |(_, k)| {
                (k.width, k.height, "camera_info (with its ROI and binning)")
            });
        for (what, w, h) in [("depth", z_mm.width, z_mm.height), ("IR", ir_buf.width, ir_buf.height)] {
            if (w, h) != (want_w, want_h) {
                return Err((
                    DropCause::SizeMismatch,
                    format!("frame at stamp {stamp} ns dropped: {what} is {w}x{h} but {by} gives {want_w}x{want_h}"),
                ));
            }
        }
        Ok(DepthFrame {
            stamp_ns: stamp,
            z_mm,
            ir: ir_buf,
        })
    }

    /// A frame while the background is latched: averaged into it, the latch finished once
    /// it has its frames, and the frame passed through if the node does that.
    fn latching_frame(
        &mut self,
        depth: &Image,
        frame: DepthFrame,
        result: &mut FrameResult<T>,
    ) -> Result<(), (DropCause, String)> {
        let Some(l) = &mut self.latch else {
            return Ok(());
        };
        if let Some((latch, k)) = &mut l.latch {
            latch.push(&frame, k).map_err(|e| {
                (
                    DropCause::Pipeline,
                    format!("background frame at stamp {} ns: {e}", frame.stamp_ns),
                )
            })?;
        }
        if l.frames() >= self.background_frames {
            if let Some(l) = self.latch.take() {
                let (reply, note) = self.finish_latch(l);
                result.replies.extend(reply);
                result.notes.extend(note.map(|n| (log::Level::Info, n)));
            }
        }
        if self.passthrough {
            self.publish(
                depth,
                FrameOutput::passed_through(&frame, Passthrough::Latching),
                frame,
                result,
            )?;
        }
        Ok(())
    }

    /// The outputs of `out` (recovered or passed through) into `result`.
    fn publish(
        &mut self,
        depth: &Image,
        out: FrameOutput,
        frame: DepthFrame,
        result: &mut FrameResult<T>,
    ) -> Result<(), (DropCause, String)> {
        let stamp = frame.stamp_ns;
        let corrected = corrected_message(&depth.header, &out, &depth.encoding)
            .map_err(|e| (DropCause::Pipeline, format!("frame at stamp {stamp} ns: {e}")))?;
        if let Some(why) = out.passthrough {
            *self.passed.entry(why).or_insert(0) += 1;
        } else {
            self.processed += 1;
        }
        let camera_info = self.info.as_ref().map(|(ci, _)| CameraInfo {
            header: depth.header.clone(),
            ..ci.clone()
        });
        let rays = self.pipeline.as_ref().map(|p| p.shared_rays());
        result.outputs = Some(NodeOutputs {
            corrected,
            camera_info,
            frame: out,
            header: depth.header.clone(),
            rays,
            ir: frame.ir,
        });
        Ok(())
    }

    /// The input passed through (`passthrough` on) or dropped for `why`.
    fn pass_or_drop(
        &mut self,
        reason: Passthrough,
        why: (DropCause, String),
        depth: &Image,
        frame: DepthFrame,
        result: &mut FrameResult<T>,
    ) -> Result<(), (DropCause, String)> {
        if !self.passthrough {
            return Err(why);
        }
        self.publish(depth, FrameOutput::passed_through(&frame, reason), frame, result)
    }

    /// Follows whether the camera moved after the latch; true while it is taken to have.
    /// With `relatch_on_move`, a latch starts once the view has held still for
    /// [`STEADY_FRAMES`] frames.
    fn watch_move(
        &mut self,
        d: &crate::pipeline::Departure,
        frame: &DepthFrame,
        k: Intrinsics,
        result: &mut FrameResult<T>,
    ) -> bool {
        if !d.camera_moved() {
            if self.moved.take().is_some() {
                result.notes.push((
                    log::Level::Info,
                    "the view lines up with the background again: correcting".into(),
                ));
            }
            return false;
        }
        let Some(m) = &mut self.moved else {
            self.moves += 1;
            let pct = |n: usize| 100.0 * n as f64 / d.valid.max(1) as f64;
            result.notes.push((log::Level::Warn, format!(
                "the camera moved after the latch: {:.0} % of the pixels read farther than the background, {:.0} % nearer; not correcting ({})",
                pct(d.farther),
                pct(d.nearer),
                if self.relatch_on_move {
                    "relatch_on_move: latching again once the view holds still"
                } else {
                    "call ~/latch_background to latch the new view, or set relatch_on_move"
                }
            )));
            self.moved = Some(Moved {
                steady: 0,
                last_z_mm: frame.z_mm.clone(),
            });
            return true;
        };
        let still = held_still(&m.last_z_mm, &frame.z_mm, self.config.threshold_mm);
        m.steady = if still { m.steady + 1 } else { 0 };
        m.last_z_mm = frame.z_mm.clone();
        if self.relatch_on_move && m.steady >= STEADY_FRAMES && self.latch.is_none() {
            let range_mm = self.config.model.sensor.unambiguous_range_mm();
            self.latch = Some(LatchInProgress {
                token: None,
                latch: Some((BackgroundLatch::new(k.width, k.height, range_mm), k)),
                started: std::time::Instant::now(),
                expires: false,
            });
            result.notes.push((
                log::Level::Info,
                format!(
                    "relatch_on_move: the view held still for {STEADY_FRAMES} frames; latching {} frames",
                    self.background_frames
                ),
            ));
        }
        true
    }

    /// The latch's reply to its caller, or for the node's own relatch a line to log.
    fn finish_latch(&mut self, l: LatchInProgress<T>) -> (Option<(T, TriggerResponse)>, Option<String>) {
        let Some((latch, intrinsics)) = l.latch else {
            let r = failure("no camera_info: nothing latched");
            return match l.token {
                Some(t) => (Some((t, r)), None),
                None => (None, Some(r.message)),
            };
        };
        let reply = match latch.finish(&intrinsics, &self.config) {
            Ok(bg) => {
                let msg = format!(
                    "latched {} frames: {} valid pixels of {}, median noise {:.1} mm; Lin {}{}",
                    bg.frames,
                    bg.valid_pixels,
                    intrinsics.width * intrinsics.height,
                    bg.median_noise_mm,
                    bg.lin_source,
                    bg.warnings
                        .iter()
                        .map(|w| format!("; WARNING: {w}"))
                        .collect::<String>()
                );
                let pipe = self
                    .pipeline
                    .get_or_insert_with(|| Pipeline::new(self.config.clone(), intrinsics));
                pipe.set_background(bg);
                self.moved = None;
                TriggerResponse {
                    success: true,
                    message: msg,
                }
            }
            Err(e) => failure(&format!("could not latch a background: {e}")),
        };
        match l.token {
            Some(t) => (Some((t, reply)), None),
            None => (None, Some(format!("relatch_on_move: {}", reply.message))),
        }
    }
}

/// Whether fewer than [`STEADY_CHANGED_SHARE`] of the pixels valid in both frames moved by
/// more than `threshold_mm` between them.
fn held_still(before: &ImageBuf<f32>, now: &ImageBuf<f32>, threshold_mm: f64) -> bool {
    let (mut valid, mut changed) = (0usize, 0usize);
    for (&a, &b) in before.data.iter().zip(&now.data) {
        if a.is_finite() && a > 0.0 && b.is_finite() && b > 0.0 {
            valid += 1;
            changed += usize::from(f64::from((a - b).abs()) > threshold_mm);
        }
    }
    valid > 0 && (changed as f64) < STEADY_CHANGED_SHARE * valid as f64
}

fn failure(msg: &str) -> TriggerResponse {
    TriggerResponse {
        success: false,
        message: msg.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::{camera_info, depth_image, ir_image};
    use crate::msgs::Header;
    use crate::physics::{ImageBuf, Intrinsics};

    fn pair(k: &Intrinsics, stamp_ns: u64) -> (Image, Image) {
        let header = Header::new(stamp_ns, "tof_optical_frame");
        let z = ImageBuf::filled(k.width, k.height, 2000.0f32);
        let ir = ImageBuf::filled(k.width, k.height, 900.0f32);
        (
            depth_image(&header, &z, "16UC1").expect("encodes"),
            ir_image(&header, &ir, "16UC1").expect("encodes"),
        )
    }

    #[test]
    fn a_camera_change_during_a_latch_starts_it_over() {
        let mut core: NodeCore<u32> = NodeCore::new(PipelineConfig::default(), 3, std::time::Duration::from_secs(60));
        let (small, big) = (
            Intrinsics::from_fov(32, 24, 44.0, 35.0),
            Intrinsics::from_fov(48, 36, 44.0, 35.0),
        );
        let header = Header::new(0, "tof_optical_frame");
        assert_eq!(core.on_camera_info(&camera_info(&header, &small)), Ok(None));
        assert!(core.start_latch(7).is_ok());
        for stamp in 1..=2 {
            let (d, i) = pair(&small, stamp);
            let r = core.on_frame(&d, &i);
            assert!(r.dropped.is_none() && r.replies.is_empty());
        }
        // The camera changes with the latch two frames in: it starts over on the new camera.
        let note = core
            .on_camera_info(&camera_info(&header, &big))
            .expect("valid camera_info");
        assert!(note.is_some_and(|n| n.contains("starts over") && n.contains("2 frames")));
        // A late frame of the old size is dropped, not averaged into the new latch.
        let (d, i) = pair(&small, 3);
        assert_eq!(
            core.on_frame(&d, &i).dropped.map(|d| d.0),
            Some(DropCause::SizeMismatch)
        );
        // Three frames of the new camera complete the latch, with a success reply.
        let mut replies = vec![];
        for stamp in 4..=6 {
            let (d, i) = pair(&big, stamp);
            replies.extend(core.on_frame(&d, &i).replies);
        }
        assert_eq!(replies.len(), 1, "{replies:?}");
        assert_eq!(replies[0].0, 7);
        assert!(replies[0].1.success, "{}", replies[0].1.message);
        assert!(
            replies[0].1.message.contains("latched 3 frames"),
            "{}",
            replies[0].1.message
        );
        assert_eq!(core.intrinsics().map(|k| k.width), Some(48));
    }

    #[test]
    fn an_unusable_camera_info_is_refused_with_its_reason_and_the_camera_kept() {
        let mut core: NodeCore<u32> = NodeCore::new(PipelineConfig::default(), 3, std::time::Duration::from_secs(60));
        let k = Intrinsics::from_fov(32, 24, 44.0, 35.0);
        let good = camera_info(&Header::new(0, "tof_optical_frame"), &k);
        assert_eq!(core.on_camera_info(&good), Ok(None));
        for (model, d) in [
            ("kannala_brandt", vec![0.1; 4]),
            ("plumb_bob", vec![0.1; 3]),
            ("plumb_bob", vec![f64::NAN; 5]),
        ] {
            let bad = CameraInfo {
                distortion_model: model.into(),
                d,
                ..good.clone()
            };
            let (cause, why) = core.on_camera_info(&bad).unwrap_err();
            assert_eq!(cause, DropCause::BadCameraInfo);
            assert!(why.contains("distortion"), "{why}");
        }
        assert_eq!(core.intrinsics(), Some(k));
        // A new lens is a new camera: the rays change.
        let lens = CameraInfo {
            d: vec![-0.2, 0.05, 0.0, 0.0, 0.0],
            ..good
        };
        assert!(core.on_camera_info(&lens).expect("usable").is_some());
        assert_ne!(core.intrinsics(), Some(k));
    }

    /// A wall tilted about the vertical axis, seen `shift` columns turned.
    fn tilted_wall(k: &Intrinsics, stamp_ns: u64, shift: f32) -> (Image, Image) {
        let header = Header::new(stamp_ns, "tof_optical_frame");
        let mut z = ImageBuf::filled(k.width, k.height, 0.0f32);
        for (i, v) in z.data.iter_mut().enumerate() {
            *v = 1800.0 + 15.0 * ((i % k.width) as f32 + shift);
        }
        let ir = ImageBuf::filled(k.width, k.height, 900.0f32);
        (
            depth_image(&header, &z, "16UC1").expect("encodes"),
            ir_image(&header, &ir, "16UC1").expect("encodes"),
        )
    }

    fn latched_core(relatch_on_move: bool) -> (NodeCore<u32>, Intrinsics) {
        let k = Intrinsics::from_fov(32, 24, 44.0, 35.0);
        let mut core = NodeCore::new(PipelineConfig::default(), 3, std::time::Duration::from_secs(60))
            .with_watch(true, relatch_on_move);
        let header = Header::new(0, "tof_optical_frame");
        assert_eq!(core.on_camera_info(&camera_info(&header, &k)), Ok(None));
        assert!(core.start_latch(1).is_ok());
        let mut replies = vec![];
        for stamp in 1..=3 {
            let (d, i) = tilted_wall(&k, stamp, 0.0);
            replies.extend(core.on_frame(&d, &i).replies);
        }
        assert!(replies.len() == 1 && replies[0].1.success, "{replies:?}");
        (core, k)
    }

    fn passed(r: &FrameResult<u32>) -> Option<Passthrough> {
        r.outputs.as_ref().and_then(|o| o.frame.passthrough)
    }

    #[test]
    fn before_the_latch_the_input_passes_through_and_says_why() {
        let k = Intrinsics::from_fov(32, 24, 44.0, 35.0);
        let header = Header::new(0, "tof_optical_frame");
        for passthrough in [true, false] {
            let mut core: NodeCore<u32> =
                NodeCore::new(PipelineConfig::default(), 3, std::time::Duration::from_secs(60))
                    .with_watch(passthrough, false);
            // Before camera_info: the depth alone, no camera_info, no cloud.
            let (d, i) = tilted_wall(&k, 0, 0.0);
            let r = core.on_frame(&d, &i);
            if passthrough {
                let o = r.outputs.expect("the input published before camera_info");
                assert_eq!(o.frame.passthrough, Some(Passthrough::NoCameraInfo));
                assert_eq!(o.corrected.data, d.data);
                assert!(o.camera_info.is_none());
                let c = o.companions().expect("messages");
                assert!(c.points.is_none(), "no cloud without rays");
                assert_eq!(c.estimates[0].method, "passthrough: no camera_info yet");
            } else {
                assert_eq!(r.dropped.map(|d| d.0), Some(DropCause::NoCameraInfo));
            }
            assert_eq!(core.on_camera_info(&camera_info(&header, &k)), Ok(None));
            let (d, i) = tilted_wall(&k, 1, 0.0);
            let r = core.on_frame(&d, &i);
            if !passthrough {
                assert_eq!(r.dropped.map(|d| d.0), Some(DropCause::NoBackground));
                assert!(r.outputs.is_none());
                continue;
            }
            assert!(r.dropped.is_none());
            let o = r.outputs.expect("the input published");
            assert_eq!(o.frame.passthrough, Some(Passthrough::NoBackground));
            assert_eq!(o.corrected.data, d.data, "the depth as it came");
            let c = o.companions().expect("messages");
            assert_eq!(c.estimates.len(), 1);
            assert_eq!(c.estimates[0].method, "passthrough: no background latched");
            assert!(c.mask.data.iter().all(|&m| m == 0));
            assert_eq!(core.passed.get(&Passthrough::NoBackground), Some(&1));
            // While latching, too.
            assert!(core.start_latch(1).is_ok());
            let (d, i) = tilted_wall(&k, 2, 0.0);
            assert_eq!(passed(&core.on_frame(&d, &i)), Some(Passthrough::Latching));
        }
    }

    #[test]
    fn a_camera_turned_after_the_latch_is_detected_and_lines_up_again_when_turned_back() {
        let (mut core, k) = latched_core(false);
        // The view as latched: nothing moved.
        let (d, i) = tilted_wall(&k, 10, 0.0);
        let r = core.on_frame(&d, &i);
        assert_ne!(passed(&r), Some(Passthrough::CameraMoved));
        assert!(!core.camera_moved());
        // Turned by 5 columns: every pixel reads 75 mm farther than the background.
        let mut notes = vec![];
        for stamp in 11..=15 {
            let (d, i) = tilted_wall(&k, stamp, 5.0);
            let r = core.on_frame(&d, &i);
            assert_eq!(passed(&r), Some(Passthrough::CameraMoved), "frame {stamp}");
            notes.extend(r.notes);
        }
        assert!(core.camera_moved());
        assert_eq!(core.moves, 1);
        assert_eq!(notes.len(), 1, "logged once: {notes:?}");
        assert!(
            notes[0].1.contains("moved after the latch") && notes[0].1.contains("100 % of the pixels read farther")
        );
        assert!(!core.latching(), "no relatch unless asked");
        // Turned back: it lines up with the background again.
        let (d, i) = tilted_wall(&k, 16, 0.0);
        let r = core.on_frame(&d, &i);
        assert_ne!(passed(&r), Some(Passthrough::CameraMoved));
        assert!(!core.camera_moved());
    }

    #[test]
    fn with_relatch_on_move_a_moved_camera_is_latched_again_once_still() {
        let (mut core, k) = latched_core(true);
        let mut notes = vec![];
        let mut stamp = 10;
        let mut frame = |core: &mut NodeCore<u32>, shift: f32| {
            stamp += 1;
            let (d, i) = tilted_wall(&k, stamp, shift);
            let r = core.on_frame(&d, &i);
            notes.extend(r.notes.iter().map(|n| n.1.clone()));
            passed(&r)
        };
        // Moving: each frame differs from the last, so no relatch yet.
        for shift in [5.0, 8.0, 11.0] {
            assert_eq!(frame(&mut core, shift), Some(Passthrough::CameraMoved));
        }
        assert!(!core.latching());
        // Still at 11 columns: after STEADY_FRAMES still frames the latch starts...
        for _ in 0..STEADY_FRAMES {
            assert_eq!(frame(&mut core, 11.0), Some(Passthrough::CameraMoved));
        }
        assert!(core.latching());
        // ...takes background_frames frames, and the new view is the background.
        for _ in 0..3 {
            assert_eq!(frame(&mut core, 11.0), Some(Passthrough::Latching));
        }
        assert!(!core.latching() && !core.camera_moved());
        assert_ne!(frame(&mut core, 11.0), Some(Passthrough::CameraMoved));
        assert!(
            notes.iter().any(|n| n.starts_with("relatch_on_move: latched 3 frames")),
            "{notes:?}"
        );
        assert_eq!(core.moves, 1);
    }
}
