//! `node [--ros-args ...]`: the parameters of interfaces.md turned into the
//! node's settings, then the node.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;

use crate::node::ros_args::{NameResolver, ParamValue, RosArgs};
use crate::node::{NodeSettings, NodeStats};
use crate::physics::XiMethod;
use crate::pipeline::XiChoice;
use crate::viz::RerunTarget;

use super::common::{ModelArgs, PipelineArgs, TopicArgs};

/// Arguments of `node`.
#[derive(Debug, Args)]
pub struct NodeArgs {
    /// Write counters and timings (JSON) here on exit.
    #[arg(long)]
    pub stats_json: Option<PathBuf>,
    /// Exit after publishing this many frames (tests, benchmarks).
    #[arg(long)]
    pub max_frames: Option<u64>,
    /// `--ros-args -r FROM:=TO -p NAME:=VALUE --log-level LEVEL ...`
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, num_args = 0.., value_name = "--ros-args ...")]
    pub ros_args: Vec<String>,
}

/// The parameters the node takes (`-p NAME:=VALUE`), with their defaults.
pub const PARAMETERS: &[(&str, &str)] = &[
    ("xi", "unset: estimate ξ; a number in [0, 1) fixes it"),
    ("xi_method", "one_material (default) or eq12_residual"),
    ("threshold_mm", "segmentation threshold |d - db|, mm (30)"),
    ("background_frames", "frames averaged per latch (10)"),
    ("modulation_frequency_hz", "sensor modulation frequency, Hz (30e6)"),
    ("waveform", "sinusoid (default) or triangle"),
    ("ir_mode", "what the IR image is: sum (paper Eq. 7) or amplitude"),
    ("lin_calibration", "emitted-light file from calibrate-lin"),
    ("exposure_s", "exposure now, s, to scale the Lin file (Eq. 14)"),
    (
        "background_albedo",
        "albedo assumed for the background without a Lin file (1.0)",
    ),
    (
        "physics",
        "physical (default: L2 = Ib xi^2, amplitude IR), paper (Eq. 2 and 7), or a physics TOML as audit writes",
    ),
    ("rerun", "off (default), a .rrd path, or a viewer address"),
    (
        "service_mapping",
        "enhanced (Fast DDS, ROS 2's default; default), cyclone (rmw_cyclonedds) or basic",
    ),
    (
        "queue_depth",
        "paired frames waiting; more and the oldest is dropped (2)",
    ),
    (
        "latch_timeout_s",
        "a latch that has not got its frames by then fails (10)",
    ),
    ("prior_radius_px", "smooth-surface prior radius, px (4; 0 = off)"),
    (
        "pin_threads",
        "pin the processing pool's workers one per CPU of the process's mask (false)",
    ),
];

fn number(params: &std::collections::BTreeMap<String, ParamValue>, name: &str) -> Result<Option<f64>> {
    match params.get(name) {
        None => Ok(None),
        Some(v) => v
            .as_f64()
            .map(Some)
            .ok_or_else(|| anyhow!("parameter {name}: expected a number, got {:?}", v.as_text())),
    }
}

fn count(params: &std::collections::BTreeMap<String, ParamValue>, name: &str, default: usize) -> Result<usize> {
    match number(params, name)? {
        None => Ok(default),
        Some(x) if x >= 0.0 && x.fract() == 0.0 && x <= 1e9 => Ok(x as usize),
        Some(x) => bail!("parameter {name}: expected a whole number >= 0, got {x}"),
    }
}

/// The node's settings from its command line and environment.
pub fn settings(a: &NodeArgs) -> Result<NodeSettings> {
    let (ros, rest) = RosArgs::parse(a.ros_args.iter().cloned())?;
    if !rest.is_empty() {
        bail!("node: unexpected arguments {rest:?} (node options go before --ros-args; ROS options after it)");
    }
    let p = &ros.params;
    for k in p.keys() {
        if !PARAMETERS.iter().any(|(n, _)| n == k) {
            let known: Vec<&str> = PARAMETERS.iter().map(|(n, _)| *n).collect();
            bail!("parameter {k:?} is not one of this node's: {}", known.join(", "));
        }
    }
    let text = |name: &str| p.get(name).map(|v| v.as_text());
    let xi = number(p, "xi")?;
    if let Some(x) = xi {
        if !(0.0..1.0).contains(&x) {
            bail!("parameter xi must be in [0, 1), got {x}");
        }
    }
    let method = match text("xi_method").as_deref() {
        None | Some("one_material") => XiMethod::OneMaterial,
        Some("eq12_residual") | Some("eq12") => XiMethod::Eq12Residual,
        Some(other) => bail!("parameter xi_method {other:?}: expected one_material or eq12_residual"),
    };
    let args = PipelineArgs {
        background_frames: None,
        threshold_mm: number(p, "threshold_mm")?.unwrap_or(crate::physics::segmentation::DEFAULT_THRESHOLD_MM),
        background_albedo: number(p, "background_albedo")?.unwrap_or(1.0),
        lin_calibration: text("lin_calibration").filter(|s| !s.is_empty()).map(PathBuf::from),
        exposure_s: number(p, "exposure_s")?,
        model: ModelArgs {
            physics: text("physics").filter(|s| !s.is_empty()).map(PathBuf::from),
            modulation_frequency_hz: number(p, "modulation_frequency_hz")?.unwrap_or(30.0e6),
            waveform: text("waveform").unwrap_or_else(|| "sinusoid".into()),
            ir_mode: text("ir_mode"),
        },
        topics: TopicArgs::default(),
    };
    let mut config = args.config().context("node parameters")?;
    config.prior_radius_px = count(p, "prior_radius_px", config.prior_radius_px)?;
    config.xi = match xi {
        Some(x) => XiChoice::Fixed(x),
        None => XiChoice::Estimate(method),
    };
    let background_frames = count(p, "background_frames", 10)?;
    if background_frames == 0 {
        bail!("parameter background_frames must be at least 1");
    }
    let service_mapping = match text("service_mapping").as_deref() {
        None | Some("enhanced") => ros2_client::ServiceMapping::Enhanced,
        Some("cyclone") => ros2_client::ServiceMapping::Cyclone,
        Some("basic") => ros2_client::ServiceMapping::Basic,
        Some(other) => bail!("parameter service_mapping {other:?}: expected enhanced, cyclone or basic"),
    };
    let pin_threads = match p.get("pin_threads") {
        None => false,
        Some(ParamValue::Bool(b)) => *b,
        Some(v) => bail!("parameter pin_threads: expected true or false, got {:?}", v.as_text()),
    };
    let latch_timeout_s = number(p, "latch_timeout_s")?.unwrap_or(10.0);
    if !(latch_timeout_s > 0.0 && latch_timeout_s < 1e6) {
        bail!("parameter latch_timeout_s must be positive, got {latch_timeout_s}");
    }
    let rerun = RerunTarget::parse(&text("rerun").unwrap_or_default()).map_err(|e| anyhow!("parameter {e}"))?;
    let domain_id = match std::env::var("ROS_DOMAIN_ID") {
        Ok(v) if !v.trim().is_empty() => v
            .trim()
            .parse::<u16>()
            .ok()
            .filter(|d| *d <= 232)
            .ok_or_else(|| anyhow!("ROS_DOMAIN_ID={v:?}: expected a whole number 0..=232"))?,
        _ => 0,
    };
    let localhost_only = std::env::var("ROS_LOCALHOST_ONLY").is_ok_and(|v| v.trim() == "1")
        || std::env::var("ROS_AUTOMATIC_DISCOVERY_RANGE").is_ok_and(|v| v.trim().eq_ignore_ascii_case("localhost"));
    let names = NameResolver::new("translucent_tof", &ros)?;
    crate::node::rlog::init(&names.node_fqn(), ros.log_level.as_deref().unwrap_or("info")).map_err(|e| anyhow!(e))?;
    Ok(NodeSettings {
        config,
        background_frames,
        latch_timeout: Duration::from_secs_f64(latch_timeout_s),
        queue_depth: count(p, "queue_depth", 2)?.max(1),
        pin_threads,
        service_mapping,
        names,
        domain_id,
        localhost_only,
        rerun,
        params: p.iter().map(|(k, v)| (k.clone(), v.clone())).collect(),
        stats_json: a.stats_json.clone(),
        max_frames: a.max_frames,
    })
}

/// Runs `node`.
pub fn run(a: NodeArgs) -> Result<NodeStats> {
    let s = settings(&a)?;
    crate::node::run(s)
}
