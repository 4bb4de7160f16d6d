//! `simulate SCENE.toml -o BAG`: renders a scene into a ROS 2 bag.

use std::path::PathBuf;

use anyhow::{anyhow, Context, Result};
use clap::Args;
use serde_json::json;

use crate::bag::{frequencies_metadata, phasor_topic, BagWriter, METADATA_NAME};
use crate::image::{camera_info, depth_image, ir_image, phasor_image};
use crate::msgs::Header;
use crate::physics::ImageBuf;
use crate::sim::render::{render, scene_intrinsics, scene_sensor};
use crate::sim::Scene;

use super::common::{describe_model, DepthEngineArgs, OutputArgs, PhysicsFile};

/// Arguments of `simulate`.
#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// The scene file (TOML).
    pub scene: PathBuf,
    /// The bag to write (MCAP).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Override the scene's noise seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Render through a camera's depth engine (over the scene's `[camera.depth_engine]`).
    #[command(flatten)]
    pub depth_engine: DepthEngineArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// Runs `simulate`.
pub fn run(a: SimulateArgs) -> Result<()> {
    let mut scene = Scene::load(&a.scene)?;
    if let Some(s) = a.seed {
        scene.seed = s;
    }
    if let Some(e) = a.depth_engine.engine()? {
        scene.camera.depth_engine = Some(e);
    }
    let k = scene_intrinsics(&scene);
    let c = &scene.camera;
    let ns = c.namespace.trim_end_matches('/').to_string();
    let topic = |t: &str| format!("{ns}/{t}");
    let mut writer = BagWriter::create(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    // The physics the frames are made with, first in the bag: replay, calibrate-xi and audit
    // take it from there (a bag cut short keeps it).
    let sensor = scene_sensor(&scene);
    let physics = PhysicsFile::complete(&scene.physics, &sensor);
    let physics_toml = format!(
        "# The physics translucent_tof simulate rendered this bag with, from the scene {}.\n{}",
        a.scene
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        physics.to_toml()?
    );
    let model = crate::physics::ForwardModel {
        sensor,
        options: scene.physics.clone(),
    };
    writer
        .write_physics_record(physics_toml.clone())
        .with_context(|| format!("writing {}", a.out.display()))?;
    let frequencies = &c.modulation_frequencies_hz;
    if !frequencies.is_empty() {
        writer
            .write_metadata(METADATA_NAME, frequencies_metadata(frequencies))
            .with_context(|| format!("writing the modulation frequencies into {}", a.out.display()))?;
    }
    let phasor_topics: Vec<String> = (0..frequencies.len()).map(|k| phasor_topic(&ns, k)).collect();
    let pb = a.output.progress(scene.frame_count() as u64, "rendering");
    let mut background = 0;
    render(&scene, |_, f| {
        let h = Header::new(f.stamp_ns, c.frame_id.clone());
        let mut go = || -> Result<()> {
            writer.write(
                &topic("depth/image_raw"),
                f.stamp_ns,
                &depth_image(&h, &f.depth_z_mm, &c.depth_encoding)?,
            )?;
            writer.write(
                &topic("ir/image_raw"),
                f.stamp_ns,
                &ir_image(&h, &f.ir, &c.ir_encoding)?,
            )?;
            writer.write(&topic("depth/camera_info"), f.stamp_ns, &camera_info(&h, &k))?;
            for (t, p) in phasor_topics.iter().zip(&f.phasors) {
                writer.write(t, f.stamp_ns, &phasor_image(&h, p)?)?;
            }
            let truth_m = ImageBuf {
                width: f.truth_z_mm.width,
                height: f.truth_z_mm.height,
                data: f.truth_z_mm.data.clone(),
            };
            writer.write(
                &topic("ground_truth/depth"),
                f.stamp_ns,
                &depth_image(&h, &truth_m, "32FC1")?,
            )?;
            Ok(())
        };
        go().map_err(|e| format!("{e:#}"))?;
        if f.background_only {
            background += 1;
        }
        pb.inc(1);
        Ok(())
    })
    .map_err(|e| anyhow!(e))?;
    pb.finish_and_clear();
    writer
        .finish()
        .with_context(|| format!("finishing {}", a.out.display()))?;
    let mut topics = vec![
        topic("depth/image_raw"),
        topic("ir/image_raw"),
        topic("depth/camera_info"),
        topic("ground_truth/depth"),
    ];
    topics.extend(phasor_topics.iter().cloned());
    let mut report = json!({
        "scene": a.scene.display().to_string(),
        "out": a.out.display().to_string(),
        "frames": scene.frame_count(),
        "background_frames": background,
        "width": k.width,
        "height": k.height,
        "seed": scene.seed,
        "physics": describe_model(&model),
        "physics_toml": physics_toml,
        "topics": topics,
    });
    if !frequencies.is_empty() {
        report["modulation_frequencies_hz"] = json!(frequencies);
    }
    a.output.summary(&format!(
        "rendered {} frames ({} background) at {}x{} into {}\nphysics: {} (recorded in the bag as its {} metadata record; replay, calibrate-xi and audit use it)",
        scene.frame_count(),
        background,
        k.width,
        k.height,
        a.out.display(),
        describe_model(&model),
        crate::bag::PHYSICS_RECORD
    ));
    a.output.write_json(&report)
}
