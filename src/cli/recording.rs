//! A recording read from a ROS 2 bag: paired depth + IR frames, intrinsics,
//! ground truth, and the choice of background frames.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};

use crate::bag::{phasor_topics, recorded_frequencies, select_topics, BagReader, SelectedTopics};
use crate::image::{depth_mm, ir_counts, phasor_samples};
use crate::msgs::{CameraInfo, Header, Image};
use crate::physics::{ImageBuf, Intrinsics};
use crate::pipeline::multifreq::PhasorFrame;
use crate::pipeline::{detect_scene_change, DepthFrame, Pipeline, PipelineConfig};

use super::common::{ModelArgs, PhysicsChoice, PhysicsFile, RecordedPhysics, TopicArgs};

/// Everything the pipeline needs from a bag.
pub struct Recording {
    /// Topics chosen and why.
    pub topics: SelectedTopics,
    /// Intrinsics from camera_info.
    pub intrinsics: Intrinsics,
    /// The camera_info they come from (the bag's first), as the node republishes it.
    pub camera_info: CameraInfo,
    /// Depth + IR pairs by exact stamp, in time order.
    pub frames: Vec<DepthFrame>,
    /// Header of each frame's depth image (for the outputs).
    pub headers: Vec<Header>,
    /// Encoding of the depth images (outputs keep it).
    pub depth_encoding: String,
    /// Ground-truth z-depth, mm, by stamp.
    pub truth: BTreeMap<u64, ImageBuf<f32>>,
    /// Depth messages with no IR at the same stamp, and IR with no depth.
    pub unpaired: (usize, usize),
    /// Where reading stopped short of a file's end (a recording cut short or
    /// damaged), in words; the frames before it are read. Empty for a whole bag.
    pub read_stops: Vec<String>,
    /// For a recording cut short: where, and what was read before the cut.
    pub cut: Option<String>,
    /// The physics the recording says it was made with (its
    /// [`PHYSICS_RECORD`](crate::bag::PHYSICS_RECORD), else a sidecar `BAG.toml`'s
    /// `physics = "PRESET"`); `Err` when what it says cannot be read.
    pub physics: Result<Option<RecordedPhysics>, String>,
    /// A multi-frequency camera's phasors, when asked for and the bag has them.
    pub multi_frequency: Option<PhasorRecording>,
}

/// The physics a bag names: its metadata record, else (a bag file) the
/// `physics = "PRESET"` of the sidecar `BAG.toml` beside it. A sidecar
/// without a `physics` string (a scene file's `[physics]` table, say) names none.
fn recorded_physics(path: &Path, reader: &BagReader) -> Result<Option<RecordedPhysics>, String> {
    use crate::bag::{PHYSICS_RECORD, PHYSICS_RECORD_KEY};
    if let Some(m) = reader.metadata().iter().rev().find(|m| m.name == PHYSICS_RECORD) {
        let from = format!("named by its metadata record {PHYSICS_RECORD}");
        let text = m.entries.get(PHYSICS_RECORD_KEY).ok_or_else(|| {
            format!(
                "bag {}: its {PHYSICS_RECORD} record has no {PHYSICS_RECORD_KEY:?} entry",
                path.display()
            )
        })?;
        let file = PhysicsFile::parse(text, &format!("bag {}: its {PHYSICS_RECORD} record", path.display()))
            .map_err(|e| format!("{e:#}"))?;
        return Ok(Some(RecordedPhysics {
            file,
            text: text.clone(),
            from,
        }));
    }
    if path.is_dir() {
        return Ok(None);
    }
    let sidecar = path.with_extension("toml");
    let Ok(text) = std::fs::read_to_string(&sidecar) else {
        return Ok(None);
    };
    let Ok(table) = text.parse::<toml::Table>() else {
        return Ok(None);
    };
    let Some(toml::Value::String(name)) = table.get("physics") else {
        return Ok(None);
    };
    let from = format!(
        "named by the sidecar {} (physics = {name:?}), the bag itself having no {PHYSICS_RECORD} record",
        sidecar.display()
    );
    let Some(preset) = crate::physics::Preset::from_name(name) else {
        let names: Vec<&str> = crate::physics::Preset::ALL.iter().map(|p| p.name()).collect();
        return Err(format!(
            "{}: physics = {name:?} is not a preset ({})",
            sidecar.display(),
            names.join(", ")
        ));
    };
    Ok(Some(RecordedPhysics {
        file: PhysicsFile {
            preset: Some(preset),
            ..PhysicsFile::default()
        },
        text: format!("preset = {name:?}\n"),
        from,
    }))
}

/// A bag cut short in words: where each file's reading stopped and what was
/// read before; `None` for a whole bag.
fn cut_text(
    path: &Path,
    stops: &[crate::bag::ReadStop],
    depth: &BTreeMap<u64, Image>,
    ir: &BTreeMap<u64, Image>,
    truth: usize,
    info: bool,
) -> Option<String> {
    if stops.is_empty() {
        return None;
    }
    let whys: Vec<String> = stops
        .iter()
        .map(|s| {
            let file = if s.file == path {
                String::new()
            } else {
                format!("{}: ", s.file.display())
            };
            match &s.source {
                crate::bag::McapProblem::Mcap(mcap::McapError::UnexpectedEof) => format!(
                    "{file}the file ends at byte {} in the middle of a record, after {} message(s)",
                    s.len, s.messages_kept
                ),
                e => format!(
                    "{file}reading stopped at byte {} of {} ({e}) after {} message(s)",
                    s.offset, s.len, s.messages_kept
                ),
            }
        })
        .collect();
    let paired: Vec<u64> = depth.keys().filter(|k| ir.contains_key(k)).copied().collect();
    let secs = |ns: u64| format!("{:.3}", ns as f64 * 1e-9);
    let span = match (paired.first(), paired.last()) {
        (Some(a), Some(b)) => format!(", stamps {} .. {} s", secs(*a), secs(*b)),
        _ => String::new(),
    };
    Some(format!(
        "bag {} is cut short: {}. Read before the cut: {} paired depth + IR frame(s){span} ({} depth, {} IR image(s)), {truth} ground-truth image(s), {}",
        path.display(),
        whys.join("; "),
        paired.len(),
        depth.len(),
        ir.len(),
        if info { "camera_info" } else { "no camera_info" }
    ))
}

/// The phasor images of a multi-frequency recording (docs/interfaces.md,
/// "Multi-frequency input").
pub struct PhasorRecording {
    /// `phasor_<k>/image_raw`, in the order of `k`.
    pub topics: Vec<String>,
    /// The frequencies the bag records (metadata `translucent_tof.modulation_frequencies_hz`), if any.
    pub recorded_frequencies_hz: Option<Vec<f64>>,
    /// One per frame of [`Recording::frames`], at the same stamp.
    pub frames: Vec<PhasorFrame>,
    /// Depth + IR pairs left out for want of a phasor image at their stamp.
    pub unpaired: usize,
}

/// Phasor images by topic index and stamp, as read.
type PhasorMessages = Vec<BTreeMap<u64, Image>>;

/// Reads a bag: picks topics, pairs depth and IR by exact stamp, decodes.
pub fn load(path: &Path, topics: &TopicArgs) -> Result<Recording> {
    load_with_phasors(path, topics, false)
}

/// [`load`], and with `phasors` a multi-frequency camera's phasor images
/// when the bag has them: the frames are then those with depth, IR and
/// every phasor image at one stamp.
pub fn load_with_phasors(path: &Path, topics: &TopicArgs, phasors: bool) -> Result<Recording> {
    let reader = BagReader::open(path).with_context(|| format!("opening bag {}", path.display()))?;
    let read_stops: Vec<String> = reader.stops().iter().map(|s| s.to_string()).collect();
    let physics = recorded_physics(path, &reader);
    let infos = reader.topics();
    let sel = select_topics(&infos, &topics.overrides()).with_context(|| format!("bag {}", path.display()))?;
    let phasor_names = if phasors {
        phasor_topics(&infos, &sel.depth).with_context(|| format!("bag {}", path.display()))?
    } else {
        vec![]
    };
    let mut phasor_msgs: PhasorMessages = vec![BTreeMap::new(); phasor_names.len()];
    let mut depth: BTreeMap<u64, Image> = BTreeMap::new();
    let mut ir: BTreeMap<u64, Image> = BTreeMap::new();
    let mut truth = BTreeMap::new();
    let mut info: Option<CameraInfo> = None;
    for raw in reader.messages() {
        let raw = raw.with_context(|| format!("reading {}", path.display()))?;
        let at = |what: &str| format!("{} message at log time {} ns on {}", what, raw.log_time_ns, raw.topic);
        if raw.topic == sel.depth {
            let img: Image = BagReader::decode(&raw).with_context(|| at("depth"))?;
            depth.insert(img.header.stamp.as_log_time_ns(), img);
        } else if raw.topic == sel.ir {
            let img: Image = BagReader::decode(&raw).with_context(|| at("IR"))?;
            ir.insert(img.header.stamp.as_log_time_ns(), img);
        } else if Some(raw.topic) == sel.info.as_deref() && info.is_none() {
            info = Some(BagReader::decode(&raw).with_context(|| at("camera_info"))?);
        } else if let Some(k) = phasor_names.iter().position(|t| t == raw.topic) {
            let img: Image = BagReader::decode(&raw).with_context(|| at("phasor"))?;
            phasor_msgs[k].insert(img.header.stamp.as_log_time_ns(), img);
        } else if Some(raw.topic) == sel.ground_truth.as_deref() {
            let img: Image = BagReader::decode(&raw).with_context(|| at("ground truth"))?;
            let stamp = img.header.stamp.as_log_time_ns();
            truth.insert(stamp, depth_mm(&img).with_context(|| at("ground truth"))?);
        }
    }
    // A recording cut short: where, and what was read before the cut, said now, before any
    // scene analysis; every error that may follow from it points back to it.
    let cut = cut_text(path, reader.stops(), &depth, &ir, truth.len(), info.is_some());
    if let Some(c) = &cut {
        eprintln!("WARNING: {c}");
    }
    let cut_suffix = if cut.is_some() {
        "; the bag is cut short (the warning above says where)"
    } else {
        ""
    };
    let info = info.ok_or_else(|| {
        anyhow!(
            "bag {}: no sensor_msgs/msg/CameraInfo message{}: the pipeline needs the intrinsics to turn z-depth into distance along each ray (pass --info-topic){cut_suffix}",
            path.display(),
            sel.info.as_deref().map(|t| format!(" on {t}")).unwrap_or_default()
        )
    })?;
    let intrinsics = Intrinsics::from_camera_info(&info)
        .with_context(|| format!("bag {}: camera_info not usable", path.display()))?;
    let mut paired: Vec<u64> = depth.keys().filter(|s| ir.contains_key(s)).copied().collect();
    let unpaired = (depth.len() - paired.len(), ir.len() - paired.len());
    let depth_ir_pairs = paired.len();
    if !phasor_names.is_empty() {
        paired.retain(|s| phasor_msgs.iter().all(|m| m.contains_key(s)));
        if paired.is_empty() && depth_ir_pairs > 0 {
            bail!(
                "bag {}: no depth + IR pair shares its stamp with an image on every phasor topic ({}): phasors must be paired by exact stamp with the depth",
                path.display(),
                phasor_names.join(", ")
            );
        }
    }
    if paired.is_empty() {
        let first = |m: &BTreeMap<u64, Image>| m.keys().next().map(|s| s.to_string()).unwrap_or_else(|| "none".into());
        bail!(
            "bag {}: no depth message on {} shares its header stamp with an IR message on {} ({} depth, {} IR; first stamps {} and {} ns): depth and IR must be paired by exact stamp{cut_suffix}",
            path.display(),
            sel.depth,
            sel.ir,
            depth.len(),
            ir.len(),
            first(&depth),
            first(&ir)
        );
    }
    let mut frames = Vec::with_capacity(paired.len());
    let mut headers = Vec::with_capacity(paired.len());
    let mut depth_encoding = String::new();
    for stamp in paired {
        let (d, i) = (&depth[&stamp], &ir[&stamp]);
        let z = depth_mm(d).with_context(|| format!("depth image at stamp {stamp} ns on {}", sel.depth))?;
        let v = ir_counts(i).with_context(|| format!("IR image at stamp {stamp} ns on {}", sel.ir))?;
        if !z.same_size(&v) {
            bail!(
                "bag {}: at stamp {stamp} ns the depth image is {}x{} but the IR image is {}x{}: they must come from the same sensor",
                path.display(),
                z.width,
                z.height,
                v.width,
                v.height
            );
        }
        if z.width != intrinsics.width || z.height != intrinsics.height {
            bail!(
                "bag {}: at stamp {stamp} ns the images are {}x{} but camera_info (with its ROI and binning) gives {}x{}",
                path.display(),
                z.width,
                z.height,
                intrinsics.width,
                intrinsics.height
            );
        }
        depth_encoding = d.encoding.clone();
        headers.push(d.header.clone());
        frames.push(DepthFrame {
            stamp_ns: stamp,
            z_mm: z,
            ir: v,
        });
    }
    let multi_frequency = if phasor_names.is_empty() {
        None
    } else {
        Some(PhasorRecording {
            frames: decode_phasors(path, &phasor_names, &phasor_msgs, &frames, &intrinsics)?,
            recorded_frequencies_hz: recorded_frequencies(reader.metadata())
                .with_context(|| format!("bag {}", path.display()))?,
            topics: phasor_names,
            unpaired: depth_ir_pairs - frames.len(),
        })
    };
    Ok(Recording {
        cut,
        topics: sel,
        intrinsics,
        camera_info: info,
        frames,
        headers,
        depth_encoding,
        truth,
        unpaired,
        read_stops,
        physics,
        multi_frequency,
    })
}

/// The phasor images at each frame's stamp, decoded and checked against the camera's size.
fn decode_phasors(
    path: &Path,
    topics: &[String],
    msgs: &PhasorMessages,
    frames: &[DepthFrame],
    k: &Intrinsics,
) -> Result<Vec<PhasorFrame>> {
    frames
        .iter()
        .map(|f| {
            let phasors = topics
                .iter()
                .zip(msgs)
                .map(|(topic, by_stamp)| {
                    let at = || {
                        format!(
                            "bag {}: phasor image at stamp {} ns on {topic}",
                            path.display(),
                            f.stamp_ns
                        )
                    };
                    let img = by_stamp.get(&f.stamp_ns).ok_or_else(|| anyhow!("{}: missing", at()))?;
                    let p = phasor_samples(img).with_context(at)?;
                    if (p.width, p.height) != (k.width, k.height) {
                        bail!(
                            "{}: {}x{}, but camera_info (with its ROI and binning) gives {}x{}",
                            at(),
                            p.width,
                            p.height,
                            k.width,
                            k.height
                        );
                    }
                    Ok(p)
                })
                .collect::<Result<Vec<_>>>()?;
            Ok(PhasorFrame {
                stamp_ns: f.stamp_ns,
                phasors,
            })
        })
        .collect()
}

/// How the background frames were chosen.
pub struct BackgroundChoice {
    /// Frames `0..count` are the background.
    pub count: usize,
    /// In words.
    pub how: String,
}

impl Recording {
    /// The physics for this recording: `--physics`, else the recording's own, else the default.
    pub fn physics_choice(&self, args: &ModelArgs) -> Result<PhysicsChoice> {
        args.choose(self.physics.as_ref().map(Option::as_ref).map_err(String::as_str))
    }

    /// `; ` and the cut, for errors that may follow from a recording cut short.
    fn cut_suffix(&self) -> &'static str {
        if self.cut.is_some() {
            "; the bag is cut short (the warning above says where)"
        } else {
            ""
        }
    }

    /// A pipeline with the first `background` frames latched as the background.
    pub fn latched_pipeline(&self, config: PipelineConfig, background: usize) -> Result<Pipeline> {
        Pipeline::latched(config, self.intrinsics, &self.frames[..background]).context("latching the background")
    }

    /// `--background-frames N`, else the first frame where the scene changes.
    pub fn background_frames(&self, given: Option<usize>, config: &PipelineConfig) -> Result<BackgroundChoice> {
        let n = self.frames.len();
        let (threshold_mm, min_region) = (config.threshold_mm, config.min_region_pixels);
        let range_mm = config.model.sensor.unambiguous_range_mm();
        match given {
            Some(0) => bail!("--background-frames must be at least 1"),
            Some(k) if k >= n => {
                bail!(
                    "--background-frames {k}: the recording has {n} paired frames, leaving none with the object{}",
                    self.cut_suffix()
                )
            }
            Some(k) => Ok(BackgroundChoice {
                count: k,
                how: format!("first {k} frames (--background-frames)"),
            }),
            None => {
                // A background needs valid readings before a change can be looked for.
                let first = &self.frames[0].z_mm;
                let valid = first.data.iter().filter(|z| z.is_finite() && **z > 0.0).count();
                if valid < (first.len() / 20).max(10) {
                    bail!(
                        "no background: the first frame has {valid} valid depth pixels of {} (NaN/0 depth everywhere?){}",
                        first.len(),
                        self.cut_suffix()
                    );
                }
                let scale = self.intrinsics.ray_scale_map();
                let distances: Vec<ImageBuf<f64>> = self
                    .frames
                    .iter()
                    .map(|f| crate::physics::camera::z_to_ray_distance(&f.z_mm, &scale))
                    .collect();
                let change = detect_scene_change(&distances, threshold_mm, min_region, range_mm).ok_or_else(|| match &self.cut {
                    Some(_) => anyhow!(
                        "no scene change: the bag is cut short (the warning above says where), and the {n} frame(s) read before the cut show one unchanging scene; the frames with the object were probably past the cut: a whole recording is needed"
                    ),
                    None => anyhow!("no background: the scene never changes over {n} frames (no object appears in front of the first frame's background); pass --background-frames N if the object is there from the start"),
                })?;
                Ok(BackgroundChoice {
                    count: change.frame,
                    how: format!(
                        "scene changes at frame {} (stamp {} ns: {} pixels moved by more than {threshold_mm} mm and 3 sigma of their noise); frames 0..{} are the background",
                        change.frame,
                        self.frames[change.frame].stamp_ns,
                        change.changed_pixels,
                        change.frame - 1
                    ),
                })
            }
        }
    }
}
