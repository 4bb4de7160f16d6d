//! `calibrate-xi` (paper Sec. V-A) and `calibrate-lin` (Eq. 13-14).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;

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
    let pb = a.output.progress(objects.len() as u64, "fitting xi");
    let mut profiles = vec![];
    let mut used = vec![];
    for f in objects {
        pb.inc(1);
        let Some(truth) = rec.truth.get(&f.stamp_ns) else {
            continue;
        };
        if let Some(profile) = pipe.calibration_profile(f, truth)? {
            profiles.push(profile);
            used.push(f.stamp_ns);
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
            PhysicsFile::complete(&physics.model.options, &physics.model.sensor.waveform)
                .to_toml()?
                .lines()
                .map(|l| format!("    {l}"))
                .collect::<Vec<_>>()
                .join("\n")
        );
    }
    a.output.summary(&summary);
    a.output.write_json(&report)
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
