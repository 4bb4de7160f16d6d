//! `calibrate-xi` (paper Sec. V-A) and `calibrate-lin` (Eq. 13-14).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;

use crate::physics::catalog::{AlbedoReference, Catalog, KnownMaterial, ALBEDO_MARGIN_LN};
use crate::physics::emitted_light::emitted_light_from_plane;
use crate::physics::translucency;
use crate::pipeline::{BackgroundLatch, PipelineConfig};

use super::common::{
    describe_model, write_atomic, LinFile, ModelArgs, OutputArgs, PhysicsFile, PipelineArgs, TopicArgs, LIN_FORMAT,
};
use super::recording::load;
use crate::physics::Preset;

/// Arguments of `calibrate-xi`.
#[derive(Debug, Args)]
pub struct CalibrateXiArgs {
    /// A recording of the material at known distances, with `ground_truth/depth`.
    pub bag: PathBuf,
    /// Write the material (its xi, interval, albedo range and this recording) to a materials
    /// file, for `replay --materials` and the node's `materials` parameter.
    #[arg(short = 'o', long = "out", value_name = "MATERIALS.toml")]
    pub out: Option<PathBuf>,
    /// Add the material to the existing file `--out` (without it an existing file is refused).
    #[arg(long, requires = "out")]
    pub append: bool,
    /// The material's name in the file (default: the bag's file stem).
    #[arg(long, requires = "out")]
    pub name: Option<String>,
    /// The material's prior weight in the file (relative to opaque's, unknown's and the
    /// other materials'; 1 each unless set).
    #[arg(long, default_value_t = 1.0, requires = "out")]
    pub prior: f64,
    #[command(flatten)]
    pub pipeline: PipelineArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// Runs `calibrate-xi`.
pub fn run_xi(a: CalibrateXiArgs) -> Result<()> {
    let mut config = a.pipeline.config()?;
    let rec = load(&a.bag, &a.pipeline.topics)?;
    let physics = rec.physics_choice(&a.pipeline.model)?;
    config.model = physics.model.clone();
    if rec.topics.ground_truth.is_none() || rec.truth.is_empty() {
        bail!(
            "bag {}: calibrate-xi needs known foreground distances, and the bag has no ground_truth/depth images (sensor_msgs/Image, 32FC1 z in metres)",
            a.bag.display()
        );
    }
    let bg = rec.background_frames(a.pipeline.background_frames, &config)?;
    let pipe = rec.latched_pipeline(config, bg.count)?;
    let objects = &rec.frames[bg.count..];
    if let Some(out) = &a.out {
        // Refused before the work, not after it.
        materials_target(out, a.append)?;
    }
    let pb = a.output.progress(objects.len() as u64, "fitting xi");
    let mut profiles = vec![];
    let mut used = vec![];
    let mut albedo_evidence = vec![];
    for f in objects {
        pb.inc(1);
        let Some(truth) = rec.truth.get(&f.stamp_ns) else {
            continue;
        };
        if let Some(profile) = pipe.calibration_profile(f, truth)? {
            profiles.push(profile);
            used.push(f.stamp_ns);
            if a.out.is_some() {
                // The albedo the estimation implies, as replay computes it: one frame at a time.
                let obs = pipe.observe(f)?;
                albedo_evidence.push(pipe.largest_region_profile(&obs));
            }
        }
    }
    pb.finish_and_clear();
    if profiles.is_empty() {
        bail!(
            "bag {}: no frame has translucent pixels with ground truth (the truth must overlap the pixels that moved by more than {} mm)",
            a.bag.display(),
            pipe.config.threshold_mm
        );
    }
    let est = translucency::calibrate(&profiles).context("no pixel carried a usable error against the truth")?;
    let written = match &a.out {
        Some(out) => {
            let albedos: Vec<f64> = albedo_evidence
                .iter()
                .flatten()
                .filter_map(|p| translucency::albedo_evidence(std::slice::from_ref(p))?.albedo_at(est.xi))
                .map(|(albedo, _)| albedo)
                .filter(|v| v.is_finite() && *v > 0.0)
                .collect();
            let (lo, hi) = albedos
                .iter()
                .fold((f64::INFINITY, 0.0f64), |r, &v| (r.0.min(v), r.1.max(v)));
            if albedos.is_empty() {
                bail!(
                    "bag {}: no frame gave an albedo at xi {:.3} (too few pixels in the largest region, or every pixel pinned there): no material written",
                    a.bag.display(),
                    est.xi
                );
            }
            let bg = pipe.background().context("background")?;
            // Where albedo consistency (what classifies objects) puts this material's ξ in its
            // own recording, when the poses determine it.
            let own: Vec<_> = albedo_evidence.iter().flatten().cloned().collect();
            let one_material_interval = translucency::one_material(&own)
                .filter(|e| !e.is_opaque())
                .map(|e| e.interval);
            let name = match &a.name {
                Some(n) => n.clone(),
                None => a
                    .bag
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_else(|| "material".into()),
            };
            let material = KnownMaterial {
                name,
                xi: est.xi,
                xi_interval: est.interval,
                albedo_range: [lo * (-ALBEDO_MARGIN_LN).exp(), hi * ALBEDO_MARGIN_LN.exp()],
                albedo_reference: if bg.lin_calibrated {
                    AlbedoReference::LinCalibration
                } else {
                    AlbedoReference::Background
                },
                background_albedo: (!bg.lin_calibrated).then_some(pipe.config.background_albedo),
                evidence_xi_interval: one_material_interval,
                prior: a.prior,
                recording: a.bag.display().to_string(),
                physics: Some(physics.option.clone().unwrap_or_else(|| describe_model(&physics.model))),
                frames: Some(used.len()),
            };
            write_material(out, a.append, &material)?;
            Some((material, albedos.len(), [lo, hi]))
        }
        None => None,
    };
    let report = json!({
        "bag": a.bag.display().to_string(),
        "xi": est.xi,
        "xi_interval": est.interval,
        "xi_method": est.method.as_str(),
        "frames": used.len(),
        "background_frames": bg.count,
        "background_choice": bg.how,
        "lin_source": pipe.background().map(|b| b.lin_source.clone()),
        "pixels": est.pixels,
        "profile": est.profile,
        "note": est.note,
        "physics": physics.json(),
        "warnings": rec.cut.iter().chain(&physics.warning).collect::<Vec<_>>(),
        "materials_file": written.as_ref().map(|(m, n, measured)| json!({
            "path": a.out.as_ref().map(|p| p.display().to_string()),
            "appended": a.append,
            "name": m.name,
            "albedo_range": m.albedo_range,
            "albedo_measured": measured,
            "albedo_frames": n,
            "albedo_reference": m.albedo_reference.as_str(),
        })),
    });
    // ξ is that of a model: say which, and how to give the same one elsewhere.
    let (replay_physics, node_physics) = match physics.option.as_deref() {
        Some(name) if name == Preset::Physical.name() => (String::new(), String::new()),
        Some(name) => (format!(" --physics {name}"), format!(" -p physics:={name}")),
        None => (" --physics FILE".to_string(), " -p physics:=FILE".to_string()),
    };
    let mut summary = format!("physics: {}\n", physics.text);
    for w in rec.cut.iter().chain(&physics.warning) {
        summary += &format!("WARNING: {w}\n");
    }
    summary += &format!(
        "xi = {:.3} [{:.3}, {:.3}] fitted to {} frame(s) with known distances ({} pixels)\nuse it with: replay --xi {:.3}{replay_physics}   (node: -p xi:={:.3}{node_physics})",
        est.xi, est.interval[0], est.interval[1], used.len(), est.pixels, est.xi, est.xi
    );
    if physics.option.is_none() {
        summary += &format!(
            "\n  FILE: a physics file holding {}, e.g.\n{}",
            describe_model(&physics.model),
            PhysicsFile::complete(&physics.model.options, &physics.model.sensor)
                .to_toml()?
                .lines()
                .map(|l| format!("    {l}"))
                .collect::<Vec<_>>()
                .join("\n")
        );
    }
    if let (Some((m, n, measured)), Some(out)) = (&written, &a.out) {
        summary += &format!(
            "\n{} material {:?} to {}: xi {:.3} [{:.3}, {:.3}], implied albedo {:.3}-{:.3} over {n} frame(s) (range {:.3}-{:.3} with the margin), relative to {}",
            if a.append { "appended" } else { "wrote" },
            m.name,
            out.display(),
            m.xi,
            m.xi_interval[0],
            m.xi_interval[1],
            measured[0],
            measured[1],
            m.albedo_range[0],
            m.albedo_range[1],
            match m.background_albedo {
                Some(g) => format!("the background taken as albedo {g} (Lin from the latched wall: compare before a wall of the same albedo)"),
                None => "the Lin calibration (absolute)".to_string(),
            }
        );
    }
    a.output.summary(&summary);
    a.output.write_json(&report)
}

/// Checks that a materials file may be written at `out`: new, or `append`ed to.
fn materials_target(out: &std::path::Path, append: bool) -> Result<()> {
    if out.exists() && !append {
        bail!(
            "materials file {} exists: give --append to add the material to it, or another path",
            out.display()
        );
    }
    Ok(())
}

/// Writes `material` to a new materials file at `out`, or appends it to the existing one.
fn write_material(out: &std::path::Path, append: bool, material: &KnownMaterial) -> Result<()> {
    materials_target(out, append)?;
    let text = if out.exists() {
        let old = std::fs::read_to_string(out).with_context(|| format!("reading materials file {}", out.display()))?;
        Catalog::append_to(&old, material).map_err(|e| anyhow::anyhow!("materials file {}: {e}", out.display()))?
    } else {
        let catalog = Catalog {
            materials: vec![material.clone()],
            ..Catalog::default()
        };
        catalog
            .to_toml()
            .map_err(|e| anyhow::anyhow!("materials file {}: {e}", out.display()))?
    };
    super::common::create_parent(out)?;
    write_atomic(out, text.as_bytes())?;
    Ok(())
}

/// Arguments of `calibrate-lin`.
#[derive(Debug, Args)]
pub struct CalibrateLinArgs {
    /// A recording of a white (or known-albedo) opaque plane filling the view.
    pub bag: PathBuf,
    /// Where to write the calibration (JSON).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Albedo of the plane.
    #[arg(long, default_value_t = 1.0)]
    pub albedo: f64,
    /// Exposure of the recording, s (kept for Eq. 14 scaling).
    #[arg(long)]
    pub exposure_s: Option<f64>,
    /// Average only the first N frames (default: all); `--background-frames N` says the same.
    #[arg(long, alias = "background-frames")]
    pub frames: Option<usize>,
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub topics: TopicArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// Runs `calibrate-lin`.
pub fn run_lin(a: CalibrateLinArgs) -> Result<()> {
    let rec = load(&a.bag, &a.topics)?;
    let k = rec.intrinsics;
    let n = a.frames.unwrap_or(rec.frames.len()).min(rec.frames.len());
    if n == 0 {
        bail!("--frames must be at least 1");
    }
    let range = a.model.model()?.sensor.unambiguous_range_mm();
    let mut latch = BackgroundLatch::new(k.width, k.height, range);
    for f in &rec.frames[..n] {
        latch.push(f, &k)?;
    }
    // The plane is averaged like a background; Lin comes from it as a plane of the given albedo.
    let config = PipelineConfig {
        background_albedo: a.albedo,
        ..PipelineConfig::default()
    };
    let bg = latch.finish(&k, &config).context("averaging the calibration plane")?;
    let (lin, plane) = emitted_light_from_plane(&bg.distance_mm, &bg.ir, &k.unit_ray_map(), a.albedo)
        .context("fitting the calibration plane")?;
    let seen = lin.data.iter().filter(|v| v.is_finite()).count();
    let file = LinFile {
        format: LIN_FORMAT.into(),
        width: lin.width,
        height: lin.height,
        albedo: a.albedo,
        exposure_s: a.exposure_s,
        plane_rms_mm: plane.rms_mm,
        lin: lin.data.iter().map(|v| v.is_finite().then_some(*v)).collect(),
    };
    write_atomic(&a.out, serde_json::to_string(&file)?.as_bytes())?;
    let report = json!({
        "bag": a.bag.display().to_string(),
        "out": a.out.display().to_string(),
        "frames": n,
        "pixels": seen,
        "plane_rms_mm": plane.rms_mm,
        "plane_normal": [plane.normal.x, plane.normal.y, plane.normal.z],
        "plane_distance_mm": plane.offset.abs(),
    });
    a.output.summary(&format!(
        "Lin from {n} frame(s) of a plane {:.0} mm away (fit RMS {:.1} mm): {seen} of {} pixels; wrote {}",
        plane.offset.abs(),
        plane.rms_mm,
        lin.len(),
        a.out.display()
    ));
    a.output.write_json(&report)
}
