//! `replay BAG`: the node's pipeline over a recorded bag, offline.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use nalgebra::Vector3;
use serde_json::json;

use crate::bag::BagWriter;
use crate::msgs::{CameraInfo, Header};
use crate::outputs::{output_messages, OutputMessages};
use crate::physics::{ImageBuf, XiEstimate, XiMethod};
use crate::pipeline::{DepthFrame, FrameOutput, Passthrough, TruthError, XiChoice};

use super::common::{OutputArgs, PipelineArgs};
use super::recording::{load_with_phasors, Recording};

/// Arguments of `replay`.
#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// A ROS 2 bag (MCAP file, or a rosbag2 directory holding one).
    pub bag: PathBuf,
    /// A fixed ξ (e.g. from calibrate-xi); default: estimate it.
    #[arg(long)]
    pub xi: Option<f64>,
    /// How to estimate ξ.
    #[arg(long, value_enum, default_value_t = XiMethodArg::OneMaterial)]
    pub xi_method: XiMethodArg,
    /// The model's error in ξ (sd) that every estimated interval takes in quadrature: what a
    /// physical scene holds beyond the model (0: the evidence's own intervals).
    #[arg(long, default_value_t = crate::physics::translucency::XI_MODEL_ERROR_SD)]
    pub xi_model_error_sd: f64,
    /// Which frames' evidence each frame's ξ pools.
    #[arg(long, value_enum, default_value_t = XiMode::Pooled)]
    pub xi_mode: XiMode,
    /// Output bag, or an existing folder to write BAG's stem + `.recovered.mcap` into
    /// (default: that name in `out/` under the current directory).
    #[arg(short = 'o', long, value_name = "OUT.mcap|DIR")]
    pub out: Option<PathBuf>,
    /// Also log the raw and recovered depth, the mask, the points and ξ of every frame to a
    /// Rerun recording (needs a build with Rerun).
    #[arg(long, value_name = "OUT.rrd")]
    pub rerun: Option<PathBuf>,
    /// Radius (pixels) of the smooth-surface prior on the recovered layer (0: per-pixel inversion only).
    #[arg(long, default_value_t = 4)]
    pub prior_radius_px: usize,
    /// The prior fits one window per square block of this many pixels a side, each pixel taking
    /// the fitted surface's tangent at its own ray (1: a window for every pixel; slower).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..=16))]
    pub prior_stride_px: u64,
    /// A multi-frequency camera's modulation frequencies, Hz, comma-separated, one per
    /// `phasor_<k>/image_raw` topic (default: the bag's record of them).
    #[arg(long, value_delimiter = ',', value_name = "F0,F1,...")]
    pub modulation_frequencies_hz: Vec<f64>,
    /// Ignore phasor topics: recover from the depth and IR alone, as for a single-frequency camera.
    #[arg(long)]
    pub single_frequency: bool,
    /// Latch no background (a moving camera): every frame's layers from two free returns per
    /// pixel at three or more modulation frequencies (multi-frequency bags only); xi is not
    /// measured.
    #[arg(long, conflicts_with = "single_frequency")]
    pub no_latch: bool,
    /// Known materials (a materials file from `calibrate-xi -o`): each object is classified
    /// among them, opaque and unknown, and a known material's xi recovers it.
    #[arg(long, value_name = "FILE")]
    pub materials: Option<PathBuf>,
    /// A class's prior weight, over the file's: NAME=WEIGHT, NAME a material's, `opaque` or
    /// `unknown` (repeat, or separate by commas).
    #[arg(long, value_name = "NAME=WEIGHT", value_delimiter = ',', requires = "materials")]
    pub material_prior: Vec<String>,
    #[command(flatten)]
    pub pipeline: PipelineArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// `--xi-method`: how ξ is estimated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
#[value(rename_all = "snake_case")]
pub enum XiMethodArg {
    /// One material per region, pooled over frames (the default).
    OneMaterial,
    /// The paper's Eq. 12 residual (degenerate; for comparison).
    #[value(alias = "eq12")]
    Eq12Residual,
}

impl From<XiMethodArg> for XiMethod {
    fn from(m: XiMethodArg) -> Self {
        match m {
            XiMethodArg::OneMaterial => XiMethod::OneMaterial,
            XiMethodArg::Eq12Residual => XiMethod::Eq12Residual,
        }
    }
}

/// `--xi-mode`: which frames' evidence each frame's ξ pools.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
#[value(rename_all = "snake_case")]
pub enum XiMode {
    /// ξ estimated over all object frames, then each frame recovered (the offline default).
    Pooled,
    /// Each frame uses the estimate pooled up to it, as the node does.
    Online,
}

impl XiMode {
    /// The name `--xi-mode` takes (and the report gives).
    pub fn name(self) -> &'static str {
        match self {
            XiMode::Pooled => "pooled",
            XiMode::Online => "online",
        }
    }
}

/// Where replay writes its bag: `--out` if it names a file, `STEM.recovered.mcap` in
/// `--out` if that is a folder, else in `out/`.
pub(super) fn out_path(bag: &Path, out: Option<&Path>) -> PathBuf {
    let stem = bag
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "replay".into());
    let name = format!("{stem}.recovered.mcap");
    match out {
        Some(o) if o.is_dir() => o.join(name),
        Some(o) => o.to_path_buf(),
        None => Path::new(super::common::OUT_DIR).join(name),
    }
}

/// Runs `replay`.
pub fn run(a: ReplayArgs) -> Result<()> {
    let method = XiMethod::from(a.xi_method);
    let online = a.xi_mode == XiMode::Online;
    if let Some(r) = &a.rerun {
        if !cfg!(feature = "rerun") {
            bail!(
                "--rerun {}: this build has no Rerun logging (rebuild with the default `rerun` feature); the outputs are in the bag (--out)",
                r.display()
            );
        }
        if r.extension().and_then(|e| e.to_str()) != Some("rrd") {
            bail!("--rerun {}: expected a path ending in .rrd", r.display());
        }
    }
    if let Some(x) = a.xi {
        if !(0.0..1.0).contains(&x) {
            bail!("--xi must be in [0, 1), got {x}");
        }
    }
    let mut config = a.pipeline.config()?;
    if !(a.xi_model_error_sd.is_finite() && (0.0..=1.0).contains(&a.xi_model_error_sd)) {
        bail!("--xi-model-error-sd must be in [0, 1], got {}", a.xi_model_error_sd);
    }
    config.xi_settings.xi_model_error_sd = a.xi_model_error_sd;
    config.prior_radius_px = a.prior_radius_px;
    config.prior_stride_px = a.prior_stride_px as usize;
    config.xi = match a.xi {
        Some(x) => XiChoice::Fixed(x),
        None => XiChoice::Estimate(method),
    };
    if let Some(path) = &a.materials {
        if a.xi.is_some() {
            bail!("--materials and --xi: a given xi leaves nothing to classify; give one of them");
        }
        config.materials = Some(std::sync::Arc::new(super::common::load_materials(
            path,
            &a.material_prior,
        )?));
    }
    let rec = load_with_phasors(&a.bag, &a.pipeline.topics, !a.single_frequency)?;
    let physics = rec.physics_choice(&a.pipeline.model)?;
    config.model = physics.model.clone();
    let materials_warnings = materials_physics_warnings(&config, &physics);
    if rec.multi_frequency.is_some() {
        return super::replay_multifreq::run(&a, config, rec);
    }
    if a.no_latch {
        bail!(
            "--no-latch: the bag {} has no phasor_<k>/image_raw topics; with one modulation frequency a layer needs the background latched",
            a.bag.display()
        );
    }
    if !a.modulation_frequencies_hz.is_empty() {
        bail!(
            "--modulation-frequencies-hz: {}",
            if a.single_frequency {
                "not with --single-frequency".to_string()
            } else {
                format!("the bag {} has no phasor_<k>/image_raw topics", a.bag.display())
            }
        );
    }
    let bg = rec.background_frames(a.pipeline.background_frames, &config)?;
    let mut pipe = rec.latched_pipeline(config, bg.count)?;
    let objects = &rec.frames[bg.count..];
    let out_path = out_path(&a.bag, a.out.as_deref());
    super::common::create_parent(&out_path)?;
    if let Some(r) = &a.rerun {
        super::common::create_parent(r)?;
    }

    // Pass 1 (pooled): the evidence of every object frame, before any is recovered. The
    // camera is taken to be still: unlike the node, replay does not watch for a moved one.
    let mut observed = Vec::with_capacity(objects.len());
    let pb = a.output.progress(objects.len() as u64, "segmenting");
    for f in objects {
        let mut obs = pipe.observe(f)?;
        if !online {
            pipe.add_xi_evidence(&mut obs);
        }
        observed.push(obs);
        pb.inc(1);
    }
    pb.finish_and_clear();

    // Pass 2: recover and write, every frame as the node publishes it.
    let mut writer = BagWriter::create(&out_path).with_context(|| format!("creating {}", out_path.display()))?;
    let rays = pipe.shared_rays();
    let camera = (&rec.camera_info, &*rays);
    for (f, header) in rec.frames[..bg.count].iter().zip(&rec.headers) {
        // The node passes the frames it latches through.
        let out = FrameOutput::passed_through(f, Passthrough::Latching);
        write_frame(&mut writer, header, camera, (&out, None), (f, &rec.depth_encoding))?;
    }
    let viz = open_rerun(&a)?;
    let pb = a.output.progress(objects.len() as u64, "recovering");
    let mut per_frame = vec![];
    let mut last: Option<XiEstimate> = None;
    let mut errors = TruthError::default();
    let (mut total_px, mut total_unmeasured) = (0usize, 0usize);
    let mut passed = std::collections::BTreeMap::from([(Passthrough::Latching, bg.count)]);
    for (j, (f, obs)) in objects.iter().zip(&mut observed).enumerate() {
        let header = &rec.headers[bg.count + j];
        let unmeasured = pipe.unmeasured_pixels(f);
        total_unmeasured += unmeasured;
        if online {
            pipe.add_xi_evidence(obs);
        }
        let Some(out) = pipe.recover_regions(f, obs) else {
            // Passed through, as the node does: published as read.
            let why = Passthrough::NoXiYet;
            let out = FrameOutput::passed_through(f, why);
            write_frame(&mut writer, header, camera, (&out, None), (f, &rec.depth_encoding))?;
            *passed.entry(why).or_insert(0) += 1;
            if let Some(truth) = rec.truth.get(&f.stamp_ns) {
                // Published as read: every pixel counts at its reading.
                errors.add_every(&f.z_mm, &f.z_mm, truth);
            }
            per_frame.push(json!({"stamp": f.stamp_ns as f64 * 1e-9, "xi": null, "translucent_pixels": obs.translucent_pixels, "note": passthrough_note(why), "passthrough": why}));
            pb.inc(1);
            continue;
        };
        let xi = out.xi.clone();
        total_px += out.translucent_pixels;
        write_frame(
            &mut writer,
            header,
            camera,
            (&out, Some(&obs.labels)),
            (f, &rec.depth_encoding),
        )?;
        if let (Some(v), Some(r)) = (&viz, &a.rerun) {
            v.log(&crate::viz::FrameViz {
                stamp_ns: out.stamp_ns,
                frame: j as u64,
                rays: pipe.shared_rays(),
                raw_z_mm: f.z_mm.clone(),
                recovered_z_mm: out.corrected_z_mm.clone(),
                mask: out.mask.clone(),
                xi: Some((xi.xi, xi.interval)),
                objects: crate::viz::FrameViz::objects_of(&out.regions),
            })
            .map_err(|e| anyhow!("--rerun {}: {e}", r.display()))?;
        }
        let mut row = json!({
            "stamp": f.stamp_ns as f64 * 1e-9,
            "xi": xi.xi,
            "xi_interval": xi.interval,
            "translucent_pixels": out.translucent_pixels,
            "unmeasured_pixels": unmeasured,
            "recovered_pixels": out.recovered_pixels,
            "pinned_pixels": out.pinned_pixels,
            "unresolved_pixels": out.unresolved_pixels,
            "fit_residual_mm": out.fit_residual_mm,
            "regions": out.regions.iter().map(|r| {
                let mut region = json!({
                    "id": r.id,
                    "xi": r.xi.xi,
                    "xi_interval": r.xi.interval,
                    "pixels": r.pixels,
                    "opaque": r.opaque,
                });
                if let Some(c) = &r.class {
                    region["material"] = json!(c.name);
                    region["class_probability"] = json!(c.probability);
                }
                region
            }).collect::<Vec<_>>(),
        });
        if let Some(truth) = rec.truth.get(&f.stamp_ns) {
            // Raw and recovered over the same pixels: segmented, with truth, recovered.
            let segmented_before = errors.segmented_with_truth;
            let got = errors.add(&out.corrected_z_mm, &f.z_mm, truth, &out.mask);
            row["segmented_truth_pixels"] = json!(errors.segmented_with_truth - segmented_before);
            if let Some((e, raw, n)) = got {
                row["rmse_mm"] = json!(e);
                row["rmse_raw_mm"] = json!(raw);
                row["truth_pixels"] = json!(n);
            }
        }
        per_frame.push(row);
        last = Some(xi);
        pb.inc(1);
    }
    pb.finish_and_clear();
    finish_outputs(writer, &out_path, viz, &a)?;

    let bgd = pipe.background().context("background")?;
    // The material with the most evidence (the last frame's when ξ is given or nothing pooled).
    let xi = pipe.xi().filter(|_| pipe.xi_frames() > 0).or(last);
    let mut report = json!({
        "bag": a.bag.display().to_string(),
        "out": out_path.display().to_string(),
        "rerun": a.rerun.as_ref().map(|r| r.display().to_string()),
        "frames": rec.frames.len(),
        "background_frames": bg.count,
        "background_choice": bg.how,
        "background_noise_mm": bgd.median_noise_mm,
        "lin_source": bgd.lin_source,
        "warnings": rec.cut.iter().chain(&physics.warning).chain(&bgd.warnings).chain(&materials_warnings).collect::<Vec<_>>(),
        "read_stops": rec.read_stops,
        "physics": physics.json(),
        "sensor": {
            "modulation_frequency_hz": pipe.config.model.sensor.modulation_frequency_hz,
            "unambiguous_range_mm": pipe.config.model.sensor.unambiguous_range_mm(),
            "waveform": format!("{:?}", pipe.config.model.sensor.waveform),
            "model_options": pipe.config.model.options,
        },
        "topics": {"depth": rec.topics.depth, "ir": rec.topics.ir, "info": rec.topics.info, "ground_truth": rec.topics.ground_truth, "notes": rec.topics.notes},
        "unpaired": {"depth": rec.unpaired.0, "ir": rec.unpaired.1},
        "xi": xi.as_ref().map(|x| x.xi),
        "xi_interval": xi.as_ref().map(|x| x.interval),
        "xi_method": xi.as_ref().map(|x| x.method.as_str()),
        "xi_mode": a.xi_mode.name(),
        "xi_frames_pooled": pipe.xi_frames(),
        "xi_note": xi.as_ref().map(|x| {
            if pipe.config.lin_calibration.is_none() && x.method != XiMethod::Fixed {
                // Lin's scale and xi trade off: the pair recovers depth, but xi alone is
                // conditional on the assumed background albedo.
                format!("{}; xi is conditional on the assumed background albedo {} (Lin from the background): depth recovery is not, a wrong albedo shifts xi instead", x.note, pipe.config.background_albedo)
            } else {
                x.note.clone()
            }
        }),
        "xi_profile": xi.as_ref().map(|x| x.profile.clone()),
        "translucent_pixels": total_px,
        "unmeasured_pixels": total_unmeasured,
        "frames_written": rec.frames.len(),
        "passed_through": passed,
        "materials": pipe.materials().filter_map(|m| {
            // What is published for it: its own estimate with its class applied.
            let e = pipe.published_estimate(m)?;
            let mut object = json!({
                "id": m.id,
                "xi": e.xi,
                "xi_interval": e.interval,
                "opaque": e.is_opaque(),
                "frames": m.frames(),
                "pixels": m.pixels(),
                "note": e.note,
            });
            if let Some(own) = m.estimate.as_ref().filter(|own| own.interval != e.interval || own.xi != e.xi) {
                object["own_xi"] = json!(own.xi);
                object["own_xi_interval"] = json!(own.interval);
            }
            if let Some(c) = pipe.classify(m) {
                object["class"] = json!({
                    "material": c.name,
                    "probability": c.probability,
                    "posterior": c.posterior.iter().map(|(n, p)| json!({"class": n, "probability": p})).collect::<Vec<_>>(),
                    "note": c.note,
                });
            }
            Some(object)
        }).collect::<Vec<_>>(),
        "materials_file": a.materials.as_ref().map(|p| p.display().to_string()),
        "per_frame": per_frame,
    });
    if let Some((profile, flat)) = pipe.eq12_comparison() {
        // The paper's criterion beside ours: where it would put ξ, and how flat it is.
        let best = profile
            .iter()
            .copied()
            .filter(|p| p.1.is_finite())
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let at = |x: f64| {
            profile
                .iter()
                .min_by(|a, b| (a.0 - x).abs().total_cmp(&(b.0 - x).abs()))
                .map(|p| p.1)
        };
        report["eq12"] = json!({
            "xi": best.map(|b| b.0),
            "rms_mm_at_its_xi": best.map(|b| b.1),
            "rms_mm_at_estimate": xi.as_ref().and_then(|x| at(x.xi)),
            "flat_range": flat,
        });
        report["eq12_profile"] = json!(profile);
    }
    if !errors.every.is_empty() {
        if let serde_json::Value::Object(m) = errors.json() {
            for (k, v) in m {
                report[k] = v;
            }
        }
    }
    report["error_summary"] = json!(errors.summary_line());
    a.output.summary(&summary(&report, &rec));
    a.output.write_json(&report)
}

/// The Rerun recording `--rerun` asks for, opened (its directory made before).
pub(super) fn open_rerun(a: &ReplayArgs) -> Result<Option<crate::viz::Recorder>> {
    let Some(r) = &a.rerun else { return Ok(None) };
    crate::viz::Recorder::open(&crate::viz::RerunTarget::File(r.clone()), "translucent_tof_replay")
        .map(Some)
        .map_err(|e| anyhow!("--rerun {}: {e}", r.display()))
}

/// Finishes the output bag and the Rerun recording.
pub(super) fn finish_outputs(
    writer: BagWriter,
    out_path: &Path,
    viz: Option<crate::viz::Recorder>,
    a: &ReplayArgs,
) -> Result<()> {
    writer
        .finish()
        .with_context(|| format!("finishing {}", out_path.display()))?;
    if let (Some(v), Some(r)) = (viz, &a.rerun) {
        v.finish().map_err(|e| anyhow!("--rerun {}: {e}", r.display()))?;
    }
    Ok(())
}

/// The topics replay writes, as the node publishes them under `~/` (docs/interfaces.md).
pub(super) mod topics {
    /// `~/depth/corrected`.
    pub const CORRECTED: &str = "/translucent_tof/depth/corrected";
    /// `~/depth/camera_info`.
    pub const CAMERA_INFO: &str = "/translucent_tof/depth/camera_info";
    /// `~/depth/corrected_sigma`.
    pub const SIGMA: &str = "/translucent_tof/depth/corrected_sigma";
    /// `~/translucent_mask`.
    pub const MASK: &str = "/translucent_tof/translucent_mask";
    /// `~/points`.
    pub const POINTS: &str = "/translucent_tof/points";
    /// `~/translucency`.
    pub const TRANSLUCENCY: &str = "/translucent_tof/translucency";
    /// Offline only: which material each pixel's region joined.
    pub const REGIONS: &str = "/translucent_tof/regions";
}

/// Writes what the node publishes for one frame (recovered or passed through), in the order
/// it publishes it, at the input's stamp.
pub(super) fn write_published(writer: &mut BagWriter, m: &OutputMessages) -> Result<()> {
    let t = m.corrected.header.stamp.as_log_time_ns();
    writer.write(topics::CORRECTED, t, &m.corrected)?;
    writer.write(topics::CAMERA_INFO, t, &m.camera_info)?;
    writer.write(topics::SIGMA, t, &m.sigma)?;
    writer.write(topics::MASK, t, &m.mask)?;
    writer.write(topics::POINTS, t, &m.points)?;
    for e in &m.estimates {
        writer.write(topics::TRANSLUCENCY, t, e)?;
    }
    Ok(())
}

/// One frame's outputs and, offline only, its regions: each pixel's material id where `labels`
/// (the frame's segmentation) puts it in a region, 0 elsewhere and in a frame passed through.
fn write_frame(
    writer: &mut BagWriter,
    header: &Header,
    camera: (&CameraInfo, &ImageBuf<Vector3<f64>>),
    (out, labels): (&FrameOutput, Option<&ImageBuf<u32>>),
    (frame, depth_encoding): (&DepthFrame, &str),
) -> Result<()> {
    let m = output_messages(header, camera, out, &frame.ir, depth_encoding)?;
    write_published(writer, &m)?;
    let region_id = |l: u32| match l {
        0 => 0,
        l => out
            .regions
            .get(l as usize - 1)
            .map_or(0, |r| u16::try_from(r.id).unwrap_or(u16::MAX)),
    };
    let (w, h) = (frame.z_mm.width, frame.z_mm.height);
    let ids = ImageBuf {
        width: w,
        height: h,
        data: match labels {
            Some(l) => l.data.iter().map(|&l| region_id(l)).collect(),
            None => vec![0; w * h],
        },
    };
    writer.write(
        topics::REGIONS,
        m.corrected.header.stamp.as_log_time_ns(),
        &crate::image::region_image(header, &ids)?,
    )?;
    Ok(())
}

/// A frame passed through, in the report's words (`no xi yet` as before the node's reasons).
fn passthrough_note(why: Passthrough) -> &'static str {
    match why {
        Passthrough::NoXiYet => "no xi yet",
        other => other.as_str(),
    }
}

fn summary(r: &serde_json::Value, rec: &Recording) -> String {
    let mut s = String::new();
    for n in &rec.topics.notes {
        s.push_str(&format!("topics: {n}\n"));
    }
    s.push_str(&format!(
        "background: {}\n",
        r["background_choice"].as_str().unwrap_or("")
    ));
    s.push_str(&format!("Lin: {}\n", r["lin_source"].as_str().unwrap_or("")));
    let sensor = &r["sensor"];
    s.push_str(&format!(
        "sensor assumed: {:.1} MHz, {} correlation (--modulation-frequency-hz, --waveform)\n",
        sensor["modulation_frequency_hz"].as_f64().unwrap_or(f64::NAN) / 1e6,
        sensor["waveform"].as_str().unwrap_or("?").to_lowercase()
    ));
    s.push_str(&format!("physics: {}\n", r["physics"]["text"].as_str().unwrap_or("")));
    for w in r["warnings"].as_array().into_iter().flatten() {
        s.push_str(&format!("WARNING: {}\n", w.as_str().unwrap_or("")));
    }
    if let (Some(x), Some(iv)) = (r["xi"].as_f64(), r["xi_interval"].as_array()) {
        s.push_str(&format!(
            "xi = {x:.3} [{:.3}, {:.3}] by {} over {} frame(s) ({})\n",
            iv[0].as_f64().unwrap_or(f64::NAN),
            iv[1].as_f64().unwrap_or(f64::NAN),
            r["xi_method"].as_str().unwrap_or("?"),
            r["xi_frames_pooled"],
            match (r["xi_method"].as_str(), r["xi_mode"].as_str()) {
                (Some("fixed"), _) => "given",
                (_, Some("online")) => "--xi-mode online: each frame with the evidence up to it, as the node",
                _ => "--xi-mode pooled: every frame with the evidence of all; the node estimates online",
            }
        ));
    } else {
        s.push_str("xi: not determined (no translucent pixels)\n");
    }
    let materials = r["materials"].as_array().map(|v| v.as_slice()).unwrap_or(&[]);
    if materials.len() > 1
        || materials.iter().any(|m| m["opaque"].as_bool() == Some(true))
        || r["materials_file"].is_string()
    {
        for m in materials {
            let iv = |i: usize| m["xi_interval"][i].as_f64().unwrap_or(f64::NAN);
            s.push_str(&format!(
                "  material {}: xi = {:.3} [{:.3}, {:.3}]{} over {} frame(s)",
                m["id"],
                m["xi"].as_f64().unwrap_or(f64::NAN),
                iv(0),
                iv(1),
                if m["opaque"].as_bool() == Some(true) {
                    ", opaque: depth kept"
                } else {
                    ""
                },
                m["frames"]
            ));
            let c = &m["class"];
            if let Some(name) = c["material"].as_str() {
                s.push_str(&format!(
                    "; class {name} (probability {:.2}){}",
                    c["probability"].as_f64().unwrap_or(f64::NAN),
                    c["note"]
                        .as_str()
                        .filter(|n| !n.is_empty())
                        .map(|n| format!(": {n}"))
                        .unwrap_or_default()
                ));
            }
            s.push('\n');
        }
    }
    let e = &r["eq12"];
    if let (Some(x), Some(rms), Some(flat)) = (
        e["xi"].as_f64(),
        e["rms_mm_at_its_xi"].as_f64(),
        e["flat_range"].as_array(),
    ) {
        let g = |i: usize| flat.get(i).and_then(|v| v.as_f64()).unwrap_or(f64::NAN);
        s.push_str(&format!(
            "Eq. 12 (the paper's residual) would pick xi = {x:.2} (RMS {rms:.2} mm; within 1 mm of that for xi in [{:.2}, {:.2}], {:.2} mm at the estimate): residuals alone do not determine xi\n",
            g(0),
            g(1),
            e["rms_mm_at_estimate"].as_f64().unwrap_or(f64::NAN)
        ));
    }
    s.push_str(&format!(
        "{} object frames, {} translucent pixels in all\n",
        r["per_frame"].as_array().map(|v| v.len()).unwrap_or(0),
        r["translucent_pixels"]
    ));
    if let Some(n) = r["unmeasured_pixels"].as_u64().filter(|n| *n > 0) {
        s.push_str(&format!(
            "{n} pixels read invalid over the valid background (a depth engine's invalidated pixels): published unmeasured\n"
        ));
    }
    s.push_str(&format!("{}\n", written_line(r)));
    if let Some(line) = r["error_summary"].as_str() {
        s.push_str(line);
        s.push('\n');
    }
    s.push_str(&format!("wrote {}", r["out"].as_str().unwrap_or("")));
    if let Some(rrd) = r["rerun"].as_str() {
        s.push_str(&format!(" and {rrd}"));
    }
    s
}

/// What the output bag holds: every frame, and those passed through as read, by reason.
fn written_line(r: &serde_json::Value) -> String {
    let passed: Vec<String> = r["passed_through"]
        .as_object()
        .into_iter()
        .flatten()
        .filter(|(_, n)| n.as_u64().unwrap_or(0) > 0)
        .map(|(why, n)| format!("{n} {why}"))
        .collect();
    format!(
        "output: all {} frames as the node publishes them; passed through as read: {}",
        r["frames_written"],
        if passed.is_empty() {
            "none".to_string()
        } else {
            passed.join(", ")
        }
    )
}

/// Warnings about the materials file against this run: a material's ξ is that of the physics
/// it was calibrated under.
fn materials_physics_warnings(
    config: &crate::pipeline::PipelineConfig,
    physics: &super::common::PhysicsChoice,
) -> Vec<String> {
    let Some(catalog) = &config.materials else {
        return vec![];
    };
    let ours = physics
        .option
        .clone()
        .unwrap_or_else(|| super::common::describe_model(&physics.model));
    catalog
        .materials
        .iter()
        .filter_map(|m| {
            let theirs = m.physics.as_deref()?;
            (theirs != ours).then(|| {
                format!(
                    "material {:?} was calibrated under the physics {theirs:?}, this run uses {ours:?}: its xi is that model's",
                    m.name
                )
            })
        })
        .collect()
}
