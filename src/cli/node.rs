//! `node [--ros-args ...]`: the parameters of interfaces.md turned into the
//! node's settings, then the node.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;

use crate::node::ros_args::{NameResolver, ParamValue, RosArgs};
use crate::node::{NodeSettings, NodeStats, RuntimeSettings};
use crate::physics::XiMethod;
use crate::pipeline::multifreq::MAX_FREQUENCIES;
use crate::pipeline::XiChoice;
use crate::viz::RerunTarget;

use super::common::{parse_choice, DepthEngineArgs, ModelArgs, PipelineArgs, TopicArgs, WaveformArg};

/// Arguments of `node`.
#[derive(Debug, Args)]
pub struct NodeArgs {
    /// Write counters and timings (JSON) here on exit.
    #[arg(long)]
    pub stats_json: Option<PathBuf>,
    /// Exit after publishing this many frames (tests, benchmarks).
    #[arg(long, hide = true)]
    pub max_frames: Option<u64>,
    /// `--ros-args -r FROM:=TO -p NAME:=VALUE --log-level LEVEL ...`
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, num_args = 0.., value_name = "--ros-args ...")]
    pub ros_args: Vec<String>,
}

/// One of the node's parameters: its name, ROS type, default (`None`: not
/// set), whether it may change at run time, and what it means.
#[derive(Debug, Clone, Copy)]
pub struct ParamSpec {
    /// `-p NAME:=VALUE`.
    pub name: &'static str,
    /// `double`, `integer`, `string` or `bool`.
    pub kind: &'static str,
    /// The default as `-p` would spell it; `None`: unset.
    pub default: Option<&'static str>,
    /// Takes effect from the next frame when set at run time.
    pub runtime: bool,
    /// What it means.
    pub meaning: &'static str,
}

const fn spec(
    name: &'static str,
    kind: &'static str,
    default: Option<&'static str>,
    runtime: bool,
    meaning: &'static str,
) -> ParamSpec {
    ParamSpec {
        name,
        kind,
        default,
        runtime,
        meaning,
    }
}

/// The parameters the node takes (`-p NAME:=VALUE`, `--params-file`), with their defaults.
pub const PARAMETERS: &[ParamSpec] = &[
    spec(
        "xi",
        "double",
        None,
        true,
        "a number in [0, 1) fixes xi; unset: estimated (xi_method)",
    ),
    spec(
        "xi_method",
        "string",
        Some("one_material"),
        true,
        "one_material or eq12_residual",
    ),
    spec(
        "threshold_mm",
        "double",
        Some("30.0"),
        true,
        "segmentation threshold on |d - db|, mm",
    ),
    spec(
        "background_frames",
        "integer",
        Some("10"),
        true,
        "frames averaged per latch",
    ),
    spec(
        "modulation_frequency_hz",
        "double",
        Some("30000000.0"),
        false,
        "the camera's modulation frequency, Hz",
    ),
    spec(
        "modulation_frequencies_hz",
        "double_array",
        None,
        false,
        "a multi-frequency camera's frequencies, Hz, one per phasor_<k>/image_raw ([20e6, 50e6, 100e6]); unset: single frequency",
    ),
    spec(
        "depth_engine",
        "string",
        None,
        false,
        "a camera that unwraps its depth from several frequencies, by name: kinect_v2; unset: none",
    ),
    spec(
        "depth_engine_frequencies_hz",
        "double_array",
        None,
        false,
        "that camera's depth engine frequencies, Hz ([80e6, 16e6, 120e6]); depth and IR are the engine's (not modulation_frequencies_hz, which reads phasor topics)",
    ),
    spec(
        "depth_engine_max_disagreement_mm",
        "double",
        None,
        false,
        "the depth engine's invalidation threshold, mm; unset: the preset's, or none",
    ),
    spec(
        "no_latch",
        "bool",
        Some("false"),
        false,
        "with three or more modulation_frequencies_hz: latch nothing, correct every frame from two free returns per pixel (a moving camera); xi is not measured",
    ),
    spec("waveform", "string", Some("sinusoid"), false, "sinusoid or triangle"),
    spec(
        "ir_mode",
        "string",
        None,
        false,
        "what the IR image is: sum (paper Eq. 7) or amplitude; unset: the physics' own",
    ),
    spec(
        "lin_calibration",
        "string",
        Some(""),
        false,
        "emitted-light file from calibrate-lin ('': none)",
    ),
    spec(
        "exposure_s",
        "double",
        None,
        false,
        "exposure now, s, to scale the Lin file (Eq. 14)",
    ),
    spec(
        "background_albedo",
        "double",
        Some("1.0"),
        false,
        "albedo assumed for the background without a Lin file",
    ),
    spec(
        "physics",
        "string",
        Some(""),
        true,
        "physical (L2 = Ib xi^2, amplitude IR), paper (Eq. 2 and 7), or a physics TOML as audit writes ('': physical)",
    ),
    spec(
        "materials",
        "string",
        Some(""),
        false,
        "a materials file from calibrate-xi -o: objects classified among its materials, opaque and unknown ('': none)",
    ),
    spec(
        "material_priors",
        "string",
        Some(""),
        false,
        "class priors over the file's: NAME=WEIGHT,... (a material's name, opaque or unknown)",
    ),
    spec(
        "rerun",
        "string",
        Some("off"),
        false,
        "off, a .rrd path, or a viewer address",
    ),
    spec(
        "service_mapping",
        "string",
        Some("enhanced"),
        false,
        "enhanced (Fast DDS), cyclone (rmw_cyclonedds) or basic",
    ),
    spec(
        "queue_depth",
        "integer",
        Some("2"),
        false,
        "paired frames waiting; beyond it the oldest is dropped",
    ),
    spec(
        "latch_timeout_s",
        "double",
        Some("10.0"),
        true,
        "a latch waits this long for camera_info and frames",
    ),
    spec(
        "latch_on_start",
        "bool",
        Some("false"),
        false,
        "latch the background as soon as frames flow",
    ),
    spec(
        "passthrough",
        "bool",
        Some("true"),
        false,
        "publish the input uncorrected while nothing can be recovered (before camera_info or the latch, xi unknown, camera moved)",
    ),
    spec(
        "relatch_on_move",
        "bool",
        Some("false"),
        false,
        "latch again once a camera that moved after the latch holds still",
    ),
    spec(
        "prior_radius_px",
        "integer",
        Some("4"),
        true,
        "smooth-surface prior radius, px (0 = off)",
    ),
    spec(
        "pin_threads",
        "bool",
        Some("false"),
        false,
        "pin the processing pool's workers one per CPU",
    ),
    spec(
        "diagnostics_period_s",
        "double",
        Some("1.0"),
        false,
        "period of /diagnostics, s (0: none)",
    ),
    spec(
        "use_sim_time",
        "bool",
        Some("false"),
        true,
        "stamp the node's own messages with /clock",
    ),
];

/// The parameter table `node --help` prints.
pub fn parameters_help() -> String {
    let mut out = String::from(
        "Parameters (--ros-args -p NAME:=VALUE or --params-file FILE; `ros2 param` at run time, * = takes effect from the next frame):\n",
    );
    // Columns as wide as their longest entry and a space, so that none run together.
    let width =
        |f: fn(&ParamSpec) -> usize, header: &str| PARAMETERS.iter().map(f).max().unwrap_or(0).max(header.len()) + 1;
    let (wn, wk) = (width(|p| p.name.len(), "NAME"), width(|p| p.kind.len(), "TYPE"));
    out.push_str(&format!(
        "  {:<wn$}{:<wk$}{:<14}  {}\n",
        "NAME", "TYPE", "DEFAULT", "MEANING"
    ));
    for p in PARAMETERS {
        out.push_str(&format!(
            "  {:<wn$}{:<wk$}{:<14}{}{}\n",
            p.name,
            p.kind,
            p.default
                .map(|d| if d.is_empty() { "''" } else { d })
                .unwrap_or("unset"),
            if p.runtime { "* " } else { "  " },
            p.meaning
        ));
    }
    out.push_str(
        "  qos_overrides./TOPIC.publisher.{reliability,durability,history,depth}: QoS of each output (TOPIC fully qualified)\n",
    );
    out
}

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

type Params = std::collections::BTreeMap<String, ParamValue>;

fn flag(p: &Params, name: &str) -> Result<bool> {
    flag_or(p, name, false)
}

fn flag_or(p: &Params, name: &str, default: bool) -> Result<bool> {
    match p.get(name) {
        None => Ok(default),
        Some(ParamValue::Bool(b)) => Ok(*b),
        Some(v) => bail!("parameter {name}: expected true or false, got {:?}", v.as_text()),
    }
}

/// `no_latch`: only with three or more `modulation_frequencies_hz` (six numbers a pixel for
/// two free returns' four unknowns).
fn no_latch(p: &Params) -> Result<bool> {
    let on = flag(p, "no_latch")?;
    let k = frequencies(p)?.map_or(0, |f| f.len());
    if on && k < 3 {
        bail!(
            "parameter no_latch: needs three or more modulation_frequencies_hz (two free returns per pixel), got {k}"
        );
    }
    Ok(on)
}

/// `depth_engine_frequencies_hz`: empty when unset.
fn engine_frequencies(p: &Params) -> Result<Vec<f64>> {
    const NAME: &str = "depth_engine_frequencies_hz";
    match p.get(NAME) {
        None => Ok(vec![]),
        Some(ParamValue::DoubleArray(v)) => Ok(v.clone()),
        Some(other) => bail!(
            "parameter {NAME}: expected an array of frequencies in Hz such as [80e6, 16e6, 120e6], got {:?}",
            other.as_text()
        ),
    }
}

/// `modulation_frequencies_hz`: `None` unset (or empty), else at least two
/// positive frequencies, at most [`MAX_FREQUENCIES`].
fn frequencies(p: &Params) -> Result<Option<Vec<f64>>> {
    const NAME: &str = "modulation_frequencies_hz";
    let v = match p.get(NAME) {
        None => return Ok(None),
        Some(ParamValue::DoubleArray(v)) if v.is_empty() => return Ok(None),
        Some(ParamValue::DoubleArray(v)) => v.clone(),
        Some(other) => bail!(
            "parameter {NAME}: expected an array of frequencies in Hz such as [20e6, 50e6, 100e6], got {:?}",
            other.as_text()
        ),
    };
    if !(2..=MAX_FREQUENCIES).contains(&v.len()) {
        bail!(
            "parameter {NAME}: {} frequencies; the multi-frequency path takes 2 to {MAX_FREQUENCIES}",
            v.len()
        );
    }
    crate::physics::multifreq::common_unambiguous_range_mm(&v).map_err(|e| anyhow!("parameter {NAME}: {e}"))?;
    Ok(Some(v))
}

/// What may change while the node runs (the parameters marked so in
/// [`PARAMETERS`]), read from the whole parameter set.
pub fn runtime_settings(p: &Params) -> Result<RuntimeSettings> {
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
            waveform: text("waveform")
                .map(|w| parse_choice("parameter waveform", &w))
                .transpose()?
                .unwrap_or(WaveformArg::Sinusoid),
            ir_mode: text("ir_mode")
                .map(|m| parse_choice("parameter ir_mode", &m))
                .transpose()?,
            depth_engine: DepthEngineArgs {
                depth_engine: text("depth_engine").filter(|s| !s.is_empty()),
                depth_engine_frequencies_hz: engine_frequencies(p)?,
                depth_engine_max_disagreement_mm: number(p, "depth_engine_max_disagreement_mm")?,
            },
        },
        topics: TopicArgs::default(),
    };
    let mut config = args.config().context("node parameters")?;
    if let Some(path) = text("materials").filter(|s| !s.is_empty()) {
        let priors = text("material_priors").unwrap_or_default();
        let priors: Vec<&str> = priors.split(',').collect();
        let catalog =
            super::common::load_materials(std::path::Path::new(&path), &priors).context("parameter materials")?;
        config.materials = Some(std::sync::Arc::new(catalog));
    } else if text("material_priors").is_some_and(|p| !p.trim().is_empty()) {
        bail!("parameter material_priors: needs a materials file (parameter materials)");
    }
    config.prior_radius_px = count(p, "prior_radius_px", config.prior_radius_px)?;
    // The model's error on physical scenes in every estimated interval, as `replay`'s default.
    config.xi_settings.xi_model_error_sd = crate::physics::translucency::XI_MODEL_ERROR_SD;
    config.xi = match xi {
        Some(x) => XiChoice::Fixed(x),
        None => XiChoice::Estimate(method),
    };
    let background_frames = count(p, "background_frames", 10)?;
    if background_frames == 0 {
        bail!("parameter background_frames must be at least 1");
    }
    let latch_timeout_s = number(p, "latch_timeout_s")?.unwrap_or(10.0);
    if !(latch_timeout_s > 0.0 && latch_timeout_s < 1e6) {
        bail!("parameter latch_timeout_s must be positive, got {latch_timeout_s}");
    }
    flag(p, "use_sim_time")?;
    Ok(RuntimeSettings {
        config,
        background_frames,
        latch_timeout: Duration::from_secs_f64(latch_timeout_s),
    })
}

fn runtime_settings_or_reason(p: &Params) -> Result<RuntimeSettings, String> {
    runtime_settings(p).map_err(|e| format!("{e:#}"))
}

/// The node's settings from its command line and environment.
pub fn settings(a: &NodeArgs) -> Result<NodeSettings> {
    let (ros, rest) = RosArgs::parse(a.ros_args.iter().cloned())?;
    if !rest.is_empty() {
        bail!("node: unexpected arguments {rest:?} (node options go before --ros-args; ROS options after it)");
    }
    let names = NameResolver::new("translucent_tof", &ros)?;
    let given = ros.resolved_params(&names.node_fqn())?;
    let p = &given;
    for k in p.keys() {
        if !PARAMETERS.iter().any(|s| s.name == k) && !crate::node::qos_overrides::is_override(k) {
            let known: Vec<&str> = PARAMETERS.iter().map(|s| s.name).collect();
            bail!("parameter {k:?} is not one of this node's: {}", known.join(", "));
        }
    }
    let text = |name: &str| p.get(name).map(|v| v.as_text());
    let runtime = runtime_settings(p)?;
    let service_mapping = match text("service_mapping").as_deref() {
        None | Some("enhanced") => ros2_client::ServiceMapping::Enhanced,
        Some("cyclone") => ros2_client::ServiceMapping::Cyclone,
        Some("basic") => ros2_client::ServiceMapping::Basic,
        Some(other) => bail!("parameter service_mapping {other:?}: expected enhanced, cyclone or basic"),
    };
    let diagnostics_period_s = number(p, "diagnostics_period_s")?.unwrap_or(1.0);
    if !(0.0..1e6).contains(&diagnostics_period_s) {
        bail!("parameter diagnostics_period_s must be >= 0, got {diagnostics_period_s}");
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
    crate::node::rlog::init(&names.node_fqn(), ros.log_level.as_deref().unwrap_or("info")).map_err(|e| anyhow!(e))?;
    // Every parameter declared on the node: the value given, else its default, else unset.
    let declared = PARAMETERS
        .iter()
        .map(|s| {
            let v = p
                .get(s.name)
                .map(|v| typed(s.kind, v.clone()))
                .or_else(|| s.default.map(|d| typed(s.kind, ParamValue::parse(d))));
            (s.name.to_string(), v)
        })
        .collect();
    Ok(NodeSettings {
        config: runtime.config,
        background_frames: runtime.background_frames,
        latch_timeout: runtime.latch_timeout,
        latch_on_start: flag(p, "latch_on_start")?,
        passthrough: flag_or(p, "passthrough", true)?,
        relatch_on_move: flag(p, "relatch_on_move")?,
        queue_depth: count(p, "queue_depth", 2)?.max(1),
        pin_threads: flag(p, "pin_threads")?,
        service_mapping,
        names,
        domain_id,
        localhost_only,
        rerun,
        params: p.iter().map(|(k, v)| (k.clone(), v.clone())).collect(),
        declared,
        runtime_params: PARAMETERS.iter().filter(|s| s.runtime).map(|s| s.name).collect(),
        reconfigure: runtime_settings_or_reason,
        diagnostics_period: Duration::from_secs_f64(diagnostics_period_s),
        stats_json: a.stats_json.clone(),
        max_frames: a.max_frames,
        multi_frequency: frequencies(p)?,
        no_latch: no_latch(p)?,
    })
}

/// A value as its parameter's declared type (`-p threshold_mm:=25` is a double
/// of 25, `-p physics:=''` an empty text), so that `ros2 param set` with the
/// declared type is accepted later.
fn typed(kind: &str, v: ParamValue) -> ParamValue {
    match (kind, v) {
        ("double", ParamValue::Integer(i)) => ParamValue::Double(i as f64),
        ("string", v) => ParamValue::String(v.as_text()),
        (_, v) => v,
    }
}

/// Runs `node`.
pub fn run(a: NodeArgs) -> Result<NodeStats> {
    let s = settings(&a)?;
    crate::node::run(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with(v: &str) -> Params {
        Params::from([("modulation_frequencies_hz".to_string(), ParamValue::parse(v))])
    }

    #[test]
    fn modulation_frequencies_are_an_array_of_two_or_more() {
        assert_eq!(frequencies(&Params::new()).unwrap(), None);
        assert_eq!(frequencies(&with("[]")).unwrap(), None);
        assert_eq!(
            frequencies(&with("[20e6, 50e6, 100000000]")).unwrap(),
            Some(vec![20e6, 50e6, 1e8])
        );
        for (bad, says) in [
            ("20e6", "expected an array of frequencies"),
            ("[20e6]", "1 frequencies"),
            ("[20e6, -5]", "not positive"),
            ("[a, b]", "expected an array"),
        ] {
            let e = format!("{:#}", frequencies(&with(bad)).unwrap_err());
            assert!(
                e.contains("modulation_frequencies_hz") && e.contains(says),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn the_depth_engine_is_a_parameter_of_its_own() {
        let engine = |params: &[(&str, &str)]| {
            let p: Params = params
                .iter()
                .map(|(k, v)| (k.to_string(), ParamValue::parse(v)))
                .collect();
            runtime_settings(&p).map(|s| s.config.model.sensor.depth_engine().cloned())
        };
        assert_eq!(engine(&[]).unwrap(), None);
        let e = engine(&[("depth_engine_frequencies_hz", "[16e6, 80e6, 120e6]")])
            .unwrap()
            .expect("an engine");
        assert_eq!(e.frequencies_hz, [16e6, 80e6, 120e6]);
        // Not the phasor path's parameter.
        assert_eq!(
            engine(&[("modulation_frequencies_hz", "[16e6, 80e6, 120e6]")]).unwrap(),
            None
        );
        let k = engine(&[
            ("depth_engine", "kinect_v2"),
            ("depth_engine_max_disagreement_mm", "50.0"),
        ])
        .unwrap()
        .expect("the preset");
        assert_eq!(k.max_disagreement_mm, Some(50.0));
        for bad in [
            vec![("depth_engine", "kinect")],
            vec![("depth_engine_frequencies_hz", "[16e6]")],
            vec![
                ("depth_engine", "kinect_v2"),
                ("depth_engine_frequencies_hz", "[16e6, 80e6]"),
            ],
        ] {
            assert!(engine(&bad).is_err(), "{bad:?}");
        }
    }
}
