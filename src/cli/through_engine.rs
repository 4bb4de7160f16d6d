//! `through-engine BAG -o OUT --depth-engine ...`: a multi-frequency recording's phasor images
//! read through a camera's depth engine, as that camera's driver would publish them: one
//! unwrapped depth image and one IR image a frame, no phasors (issue 51, item 4).

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use serde_json::json;

use crate::bag::{BagReader, BagWriter, METADATA_NAME};
use crate::image::{depth_image, ir_image};
use crate::msgs::{CameraInfo, Image};
use crate::physics::depth_engine::PreparedEngine;
use crate::physics::sensor::{Buckets, Sensor};
use crate::physics::stats::median_select;
use crate::physics::ImageBuf;
use crate::pipeline::multifreq::PhasorFrame;

use super::common::{waveform, DepthEngineArgs, OutputArgs, PhysicsFile, TopicArgs};
use super::recording::{load_with_phasors, Recording};

/// Arguments of `through-engine`.
#[derive(Debug, Args)]
pub struct ThroughEngineArgs {
    /// A recording with `phasor_<k>/image_raw` topics and their frequencies' record (a
    /// multi-frequency render).
    pub bag: PathBuf,
    /// The bag to write (MCAP): depth and IR through the engine, every other topic as read.
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// The engine (its frequencies must be among the recording's).
    #[command(flatten)]
    pub depth_engine: DepthEngineArgs,
    #[command(flatten)]
    pub topics: TopicArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// One frame through the engine: z-depth (mm, NaN where it invalidates the pixel) and its
/// amplitude (the phasors' counts).
struct EngineFrame {
    z_mm: ImageBuf<f32>,
    amplitude: ImageBuf<f32>,
}

/// Runs `through-engine`.
pub fn run(a: ThroughEngineArgs) -> Result<()> {
    let engine = a.depth_engine.engine()?.ok_or_else(|| {
        anyhow!("through-engine needs the engine: --depth-engine NAME or --depth-engine-frequencies-hz F0,F1,...")
    })?;
    let rec = load_with_phasors(&a.bag, &a.topics, true)?;
    let physics = recorded_physics_file(&rec, &a.bag)?;
    let wf = waveform(physics.waveform.as_deref().unwrap_or("sinusoid"), physics.harmonics)?;
    // The frequency is the engine's business: the sensor only decodes each phasor's phase.
    let sensor = Sensor::new(engine.frequencies_hz[0], wf)
        .with_depth_engine(&engine)
        .with_context(|| format!("the engine {:?}", engine.frequencies_hz))?;
    let prepared = sensor.engine().ok_or_else(|| anyhow!("the engine was not prepared"))?;
    let order = engine_order(&rec, &engine.frequencies_hz, &a.bag)?;
    let phasors = &rec
        .multi_frequency
        .as_ref()
        .ok_or_else(|| anyhow!("no phasors read"))?
        .frames;
    let scale = rec.intrinsics.ray_scale_map();
    let pb = a.output.progress(phasors.len() as u64, "through the engine");
    let mut frames = BTreeMap::new();
    for p in phasors {
        frames.insert(p.stamp_ns, read_frame(&sensor, prepared, p, &order, &scale)?);
        pb.inc(1);
    }
    pb.finish_and_clear();
    let gain = ir_gain(&rec, &frames).ok_or_else(|| {
        anyhow!(
            "bag {}: no pixel of the first frame has both a recorded IR and a phasor amplitude: the IR's scale cannot be carried over",
            a.bag.display()
        )
    })?;
    let mut with_engine = physics;
    with_engine.depth_engine = Some(engine.clone());
    let written = write_bag(&a, &rec, &frames, gain, &with_engine)?;
    let invalid: usize = frames
        .values()
        .map(|f| f.z_mm.data.iter().filter(|z| z.is_nan()).count())
        .sum();
    let summary = json!({
        "bag": a.bag.display().to_string(),
        "out": a.out.display().to_string(),
        "frequencies_hz": engine.frequencies_hz,
        "frames": frames.len(),
        "invalid_pixels": invalid,
        "ir_gain": gain,
        "messages_copied": written.copied,
        "messages_left_out": written.left_out,
    });
    a.output.write_json(&summary)?;
    a.output.summary(&format!(
            "{} frames of {} through the engine at {:?} Hz into {} ({} pixels invalidated; the IR is the engine's amplitude times {:.4}, the recording's IR over the amplitude on its first frame; {} other messages copied, {} left out: phasors and depth or IR without phasors)",
            frames.len(),
            a.bag.display(),
            engine.frequencies_hz,
            a.out.display(),
            invalid,
            gain,
            written.copied,
            written.left_out
    ));
    Ok(())
}

/// The physics the recording names (its record, else the defaults), to be written again
/// with the engine in it.
fn recorded_physics_file(rec: &Recording, bag: &std::path::Path) -> Result<PhysicsFile> {
    match &rec.physics {
        Ok(Some(r)) => Ok(r.file.clone()),
        Ok(None) => Ok(PhysicsFile::default()),
        Err(e) => bail!("bag {}: its physics cannot be read: {e}", bag.display()),
    }
}

/// For each of the engine's frequencies, the index of the recording's phasor image at it.
fn engine_order(rec: &Recording, engine_hz: &[f64], bag: &std::path::Path) -> Result<Vec<usize>> {
    let recorded = rec
        .multi_frequency
        .as_ref()
        .and_then(|m| m.recorded_frequencies_hz.clone())
        .ok_or_else(|| {
            anyhow!(
                "bag {}: no phasor topics with a {METADATA_NAME} record of their frequencies: nothing to read through an engine",
                bag.display()
            )
        })?;
    engine_hz
        .iter()
        .map(|f| {
            recorded.iter().position(|r| (r - f).abs() <= 1.0).ok_or_else(|| {
                anyhow!(
                    "bag {}: the engine's {f} Hz is not among the recorded frequencies {recorded:?}",
                    bag.display()
                )
            })
        })
        .collect()
}

/// One frame's phasors through the engine: each pixel's distance along its ray as z.
fn read_frame(
    sensor: &Sensor,
    engine: &PreparedEngine,
    frame: &PhasorFrame,
    order: &[usize],
    scale: &ImageBuf<f64>,
) -> Result<EngineFrame> {
    let images: Vec<&ImageBuf<[f32; 2]>> = order
        .iter()
        .map(|&k| frame.phasors.get(k).ok_or_else(|| anyhow!("phasor image {k} missing")))
        .collect::<Result<_>>()?;
    let (w, h) = (scale.width, scale.height);
    if images.iter().any(|im| im.width != w || im.height != h) {
        bail!(
            "frame at {} ns: a phasor image is not {w}x{h}, the camera_info's size",
            frame.stamp_ns
        );
    }
    let mut z_mm = ImageBuf::filled(w, h, f32::NAN);
    let mut amplitude = ImageBuf::filled(w, h, f32::NAN);
    let mut pixel = vec![Buckets::default(); images.len()];
    for i in 0..w * h {
        for (b, im) in pixel.iter_mut().zip(&images) {
            let [pa, pb] = im.data[i];
            *b = Buckets {
                a: f64::from(pa),
                b: f64::from(pb),
            };
        }
        let r = engine.read(sensor, &pixel);
        z_mm.data[i] = (r.distance_mm / scale.data[i]) as f32;
        amplitude.data[i] = r.ir_amplitude as f32;
    }
    Ok(EngineFrame { z_mm, amplitude })
}

/// The recording's IR counts per unit of phasor amplitude: the median ratio over the first
/// frame's pixels (a single return's amplitude is the same at every frequency).
fn ir_gain(rec: &Recording, frames: &BTreeMap<u64, EngineFrame>) -> Option<f64> {
    let first = rec.frames.first()?;
    let f = frames.get(&first.stamp_ns)?;
    let mut ratios: Vec<f64> = first
        .ir
        .data
        .iter()
        .zip(&f.amplitude.data)
        .filter(|(ir, amp)| ir.is_finite() && **ir > 0.0 && amp.is_finite() && **amp > 0.0)
        .map(|(ir, amp)| f64::from(*ir) / f64::from(*amp))
        .collect();
    (!ratios.is_empty()).then(|| median_select(&mut ratios))
}

struct Written {
    copied: usize,
    left_out: usize,
}

/// The bag: the physics record with the engine, then every message in log-time order, the
/// depth and IR of each engine frame replaced by the engine's, phasors left out.
fn write_bag(
    a: &ThroughEngineArgs,
    rec: &Recording,
    frames: &BTreeMap<u64, EngineFrame>,
    gain: f64,
    physics: &PhysicsFile,
) -> Result<Written> {
    let reader = BagReader::open(&a.bag).with_context(|| format!("opening bag {}", a.bag.display()))?;
    let phasor_topics = rec
        .multi_frequency
        .as_ref()
        .map(|m| m.topics.clone())
        .unwrap_or_default();
    let mut writer = BagWriter::create(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let text = format!(
        "# The physics of {}, read through a depth engine by translucent_tof through-engine.\n{}",
        a.bag
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        physics.to_toml()?
    );
    writer.write_physics_record(text)?;
    let (mut copied, mut left_out) = (0, 0);
    for raw in reader.messages() {
        let raw = raw.with_context(|| format!("reading {}", a.bag.display()))?;
        let at = || format!("message at log time {} ns on {}", raw.log_time_ns, raw.topic);
        let (depth, ir) = (raw.topic == rec.topics.depth, raw.topic == rec.topics.ir);
        if depth || ir {
            let img: Image = BagReader::decode(&raw).with_context(at)?;
            let Some(f) = frames.get(&img.header.stamp.as_log_time_ns()) else {
                left_out += 1;
                continue;
            };
            let out = if depth {
                depth_image(&img.header, &f.z_mm, &img.encoding)
            } else {
                let mut counts = f.amplitude.clone();
                counts.data.iter_mut().for_each(|x| *x = (f64::from(*x) * gain) as f32);
                ir_image(&img.header, &counts, &img.encoding)
            }
            .with_context(at)?;
            writer.write(raw.topic, raw.log_time_ns, &out)?;
        } else if phasor_topics.iter().any(|t| t == raw.topic) {
            left_out += 1;
        } else if raw.type_name.ends_with("CameraInfo") {
            let m: CameraInfo = BagReader::decode(&raw).with_context(at)?;
            writer.write(raw.topic, raw.log_time_ns, &m)?;
            copied += 1;
        } else if raw.type_name.ends_with("Image") {
            let m: Image = BagReader::decode(&raw).with_context(at)?;
            writer.write(raw.topic, raw.log_time_ns, &m)?;
            copied += 1;
        } else {
            left_out += 1;
        }
    }
    writer
        .finish()
        .with_context(|| format!("writing {}", a.out.display()))?;
    Ok(Written { copied, left_out })
}
