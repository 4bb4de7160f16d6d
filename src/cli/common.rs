//! Options and plumbing shared by the subcommands.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde::{Deserialize, Serialize};

use crate::bag::TopicOverrides;
use crate::physics::{DepthEngine, ForwardModel, ImageBuf, IrMode, ModelOptions, Preset, Sensor, Waveform};
use crate::pipeline::PipelineConfig;

/// Topic overrides (`--depth-topic`, `--ir-topic`, `--info-topic`).
#[derive(Debug, Clone, Args, Default)]
pub struct TopicArgs {
    /// Depth image topic (default: found by type and name).
    #[arg(long)]
    pub depth_topic: Option<String>,
    /// IR image topic (default: found by type and name).
    #[arg(long)]
    pub ir_topic: Option<String>,
    /// CameraInfo topic (default: found by type and name).
    #[arg(long)]
    pub info_topic: Option<String>,
}

impl TopicArgs {
    /// As the bag layer's overrides.
    pub fn overrides(&self) -> TopicOverrides {
        TopicOverrides {
            depth: self.depth_topic.clone(),
            ir: self.ir_topic.clone(),
            info: self.info_topic.clone(),
        }
    }
}

/// What `replay` and `calibrate-xi` share: the background, the segmentation,
/// `Lin`, the model and the topics.
#[derive(Debug, Clone, Args)]
pub struct PipelineArgs {
    /// The first N paired frames are the background (default: detect where the scene changes).
    #[arg(long)]
    pub background_frames: Option<usize>,
    /// Segmentation threshold |d - db|, mm.
    #[arg(long, default_value_t = 30.0)]
    pub threshold_mm: f64,
    /// Albedo assumed for the background when Lin is derived from it.
    #[arg(long, default_value_t = 1.0)]
    pub background_albedo: f64,
    /// Emitted-light calibration from calibrate-lin.
    #[arg(long)]
    pub lin_calibration: Option<PathBuf>,
    /// Exposure of this recording, s, to scale the Lin calibration (Eq. 14).
    #[arg(long)]
    pub exposure_s: Option<f64>,
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub topics: TopicArgs,
}

impl PipelineArgs {
    /// The pipeline's settings these options give.
    pub fn config(&self) -> Result<PipelineConfig> {
        if !(self.threshold_mm.is_finite() && self.threshold_mm > 0.0) {
            bail!("--threshold-mm must be positive, got {}", self.threshold_mm);
        }
        if !(self.background_albedo > 0.0 && self.background_albedo <= 1.0) {
            bail!("--background-albedo must be in (0, 1], got {}", self.background_albedo);
        }
        let lin = self
            .lin_calibration
            .as_ref()
            .map(|p| LinFile::load(p, self.exposure_s))
            .transpose()?;
        Ok(PipelineConfig {
            threshold_mm: self.threshold_mm,
            background_albedo: self.background_albedo,
            lin_calibration: lin,
            model: self.model.model()?,
            ..PipelineConfig::default()
        })
    }
}

/// The sensor and the physics (`--physics`, `--waveform`, ...).
#[derive(Debug, Clone, Args)]
pub struct ModelArgs {
    /// The physics: a preset's name, or a physics TOML file (as `audit --physics-out` writes).
    #[arg(long, value_name = "physical|paper|FILE", value_parser = PhysicsParser)]
    pub physics: Option<PathBuf>,
    /// Modulation frequency, Hz.
    #[arg(long, default_value_t = 30.0e6)]
    pub modulation_frequency_hz: f64,
    /// Correlation waveform (a physics file may give harmonics).
    #[arg(long, value_enum, default_value_t = WaveformArg::Sinusoid)]
    pub waveform: WaveformArg,
    /// What the IR image reports (default: the physics' own).
    #[arg(long, value_enum)]
    pub ir_mode: Option<IrModeArg>,
    #[command(flatten)]
    pub depth_engine: DepthEngineArgs,
}

/// A camera that unwraps its depth from several frequencies (`--depth-engine`,
/// `--depth-engine-frequencies-hz`): the depth and IR are its engine's.
#[derive(Debug, Clone, Args, Default)]
pub struct DepthEngineArgs {
    /// The camera's depth engine by name: kinect_v2 (80, 16 and 120 MHz, libfreenect2's parameters).
    #[arg(long, value_name = "kinect_v2")]
    pub depth_engine: Option<String>,
    /// A depth engine at these frequencies, Hz, comma-separated (weights f^2, no invalidation,
    /// IR the mean amplitude); not --modulation-frequencies-hz, which reads phasor topics.
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "F0,F1,...",
        conflicts_with = "depth_engine"
    )]
    pub depth_engine_frequencies_hz: Vec<f64>,
    /// The depth engine's invalidation threshold: the largest disagreement of the
    /// unwrapped distances a valid pixel has, mm.
    #[arg(long)]
    pub depth_engine_max_disagreement_mm: Option<f64>,
}

impl DepthEngineArgs {
    /// The engine these options give, if any.
    pub fn engine(&self) -> Result<Option<DepthEngine>> {
        let mut engine = match (&self.depth_engine, self.depth_engine_frequencies_hz.as_slice()) {
            (Some(_), [_, ..]) => bail!("a depth engine by name or by its frequencies, not both"),
            (Some(name), []) => DepthEngine::preset(name)?,
            (None, []) => {
                if self.depth_engine_max_disagreement_mm.is_some() {
                    bail!("--depth-engine-max-disagreement-mm needs --depth-engine or --depth-engine-frequencies-hz");
                }
                return Ok(None);
            }
            (None, f) => DepthEngine::at(f)?,
        };
        if let Some(t) = self.depth_engine_max_disagreement_mm {
            engine.max_disagreement_mm = Some(t);
        }
        engine.check()?;
        Ok(Some(engine))
    }
}

/// `--waveform`: the camera's correlation waveform.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum WaveformArg {
    /// A pure sinusoid (the paper's model).
    Sinusoid,
    /// A triangle (square-wave emission and gating).
    Triangle,
}

impl WaveformArg {
    /// The name `--waveform` takes.
    pub fn name(self) -> &'static str {
        match self {
            WaveformArg::Sinusoid => "sinusoid",
            WaveformArg::Triangle => "triangle",
        }
    }
}

/// `--ir-mode`: what the IR image reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum IrModeArg {
    /// The sum of the returns' intensities (paper Eq. 7).
    Sum,
    /// The demodulated amplitude, as CW-ToF cameras report it.
    Amplitude,
}

impl From<IrModeArg> for IrMode {
    fn from(m: IrModeArg) -> Self {
        match m {
            IrModeArg::Sum => IrMode::Sum,
            IrModeArg::Amplitude => IrMode::Amplitude,
        }
    }
}

/// A value of a [`clap::ValueEnum`] given as text (a node parameter), or a
/// message naming the parameter and the values it takes.
pub fn parse_choice<T: clap::ValueEnum>(what: &str, text: &str) -> Result<T> {
    T::from_str(text, false).map_err(|_| {
        let names: Vec<String> = T::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value())
            .map(|p| p.get_name().to_string())
            .collect();
        anyhow::anyhow!("{what} {text:?}: expected one of {}", names.join(", "))
    })
}

/// `--physics`: a preset's name or a path. The presets are its possible
/// values in `--help`; any other value is taken as a physics file.
#[derive(Debug, Clone, Copy)]
pub struct PhysicsParser;

impl clap::builder::TypedValueParser for PhysicsParser {
    type Value = PathBuf;

    fn parse_ref(
        &self,
        cmd: &clap::Command,
        arg: Option<&clap::Arg>,
        value: &std::ffi::OsStr,
    ) -> std::result::Result<PathBuf, clap::Error> {
        clap::builder::PathBufValueParser::new().parse_ref(cmd, arg, value)
    }

    fn possible_values(&self) -> Option<Box<dyn Iterator<Item = clap::builder::PossibleValue> + '_>> {
        Some(Box::new(Preset::ALL.into_iter().map(|p| {
            clap::builder::PossibleValue::new(p.name()).help(match p {
                Preset::Physical => {
                    "The default: the second return crosses the layer twice, IR is the demodulated amplitude"
                }
                Preset::Paper => "The paper's Eq. 2 and 7, for replication",
            })
        })))
    }
}

/// A physics file: the forward model's options on top of a preset.
/// Every key is optional; absent keys keep the preset's value.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsFile {
    /// The options the file starts from: `physical` (default) or `paper`.
    pub preset: Option<Preset>,
    /// Returns kept from Eq. 3 (2 = the paper).
    pub bounces: Option<usize>,
    /// `sum` or `amplitude`.
    pub ir_mode: Option<IrMode>,
    /// Power of X in the second return (2 = the paper, 0 = double pass).
    pub transmission_albedo_power: Option<f64>,
    /// IR offset, counts.
    pub ambient_offset: Option<f64>,
    /// Extra path of the layer's return, mm.
    pub subsurface_delay_mm: Option<f64>,
    /// `sinusoid`, `triangle` or `harmonics`.
    pub waveform: Option<String>,
    /// Relative 3rd and 5th harmonics when `waveform = "harmonics"`.
    pub harmonics: Option<[f64; 2]>,
    /// Displacement of the background seen through the layer, pixels `[columns, rows]`.
    pub refraction_shift_px: Option<[f64; 2]>,
    /// Gain on the third return of a layer near a diffuse background (0 = none, 1 = its estimate).
    pub wall_interreflection: Option<f64>,
    /// Share of the light crossing the layer that crosses diffusely (0 = a clear layer).
    pub diffuse_transmission: Option<f64>,
    /// Depth of a hollow object of the layer's material, mm (0 = one layer).
    pub hollow_depth_mm: Option<f64>,
    /// A camera that unwraps its depth from several frequencies: its engine.
    pub depth_engine: Option<DepthEngine>,
}

impl PhysicsFile {
    /// Reads and checks a physics file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading physics file {}", path.display()))?;
        Self::parse(&text, &format!("physics file {}", path.display()))
    }

    /// Parses and checks a physics file's text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self> {
        let f: PhysicsFile = toml::from_str(text).with_context(|| origin.to_string())?;
        let ranged = [
            ("hollow_depth_mm", f.hollow_depth_mm, 5000.0),
            ("diffuse_transmission", f.diffuse_transmission, 1.0),
            ("wall_interreflection", f.wall_interreflection, 10.0),
        ];
        for (name, value, most) in ranged {
            if let Some(v) = value.filter(|v| !(0.0..=most).contains(v)) {
                bail!("{origin}: {name} = {v} is not in 0..={most}");
            }
        }
        if let Some(e) = &f.depth_engine {
            e.check().with_context(|| format!("{origin}: depth_engine"))?;
        }
        if let Some(b) = f.bounces {
            if !(2..=crate::physics::model::MAX_BOUNCES).contains(&b) {
                bail!(
                    "{origin}: bounces = {b} is not in 2..={}",
                    crate::physics::model::MAX_BOUNCES
                );
            }
        }
        Ok(f)
    }

    /// The complete file of a model: its preset named (`physical` when the
    /// options are that preset's, else `paper`, the base scene files are
    /// written against) and every option written out, so that it reads the
    /// same whatever a preset's defaults become. The waveform is written when
    /// it is not a sinusoid, the sensor's depth engine when it has one.
    pub fn complete(options: &ModelOptions, sensor: &Sensor) -> Self {
        let waveform = &sensor.waveform;
        let preset = if *options == Preset::Physical.options() {
            Preset::Physical
        } else {
            Preset::Paper
        };
        let (waveform, harmonics) = match waveform {
            Waveform::Sinusoid => (None, None),
            Waveform::Triangle => (Some("triangle".to_string()), None),
            Waveform::Harmonics { third, fifth } => (Some("harmonics".to_string()), Some([*third, *fifth])),
        };
        PhysicsFile {
            preset: Some(preset),
            bounces: Some(options.bounces),
            ir_mode: Some(options.ir_mode),
            transmission_albedo_power: Some(options.transmission_albedo_power),
            ambient_offset: Some(options.ambient_offset),
            subsurface_delay_mm: Some(options.subsurface_delay_mm),
            waveform,
            harmonics,
            refraction_shift_px: Some(options.refraction_shift_px),
            wall_interreflection: Some(options.wall_interreflection),
            diffuse_transmission: Some(options.diffuse_transmission),
            hollow_depth_mm: Some(options.hollow_depth_mm),
            depth_engine: sensor.depth_engine().cloned(),
        }
    }

    /// The file as TOML (absent keys left out).
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string(self).context("writing a physics file as TOML")
    }

    /// The model options the file gives (absent keys: its preset's).
    pub fn options(&self) -> ModelOptions {
        let d = self.preset.unwrap_or_default().options();
        ModelOptions {
            bounces: self.bounces.unwrap_or(d.bounces),
            ir_mode: self.ir_mode.unwrap_or(d.ir_mode),
            transmission_albedo_power: self.transmission_albedo_power.unwrap_or(d.transmission_albedo_power),
            ambient_offset: self.ambient_offset.unwrap_or(d.ambient_offset),
            subsurface_delay_mm: self.subsurface_delay_mm.unwrap_or(d.subsurface_delay_mm),
            refraction_shift_px: self.refraction_shift_px.unwrap_or(d.refraction_shift_px),
            wall_interreflection: self.wall_interreflection.unwrap_or(d.wall_interreflection),
            diffuse_transmission: self.diffuse_transmission.unwrap_or(d.diffuse_transmission),
            hollow_depth_mm: self.hollow_depth_mm.unwrap_or(d.hollow_depth_mm),
        }
    }
}

/// The `--physics` value that gives `model` (a preset's name), if one does.
pub fn physics_option(model: &ForwardModel) -> Option<&'static str> {
    let plain = model.sensor.waveform == Waveform::Sinusoid && model.sensor.depth_engine().is_none();
    Preset::ALL
        .iter()
        .find(|p| plain && p.options() == model.options)
        .map(|p| p.name())
}

/// A model in words: the preset it is, or the nearer preset and the options
/// that depart from it (`paper` with `transmission_albedo_power = 0`).
pub fn describe_model(model: &ForwardModel) -> String {
    let o = &model.options;
    let wave = match model.sensor.waveform {
        Waveform::Sinusoid => String::new(),
        Waveform::Triangle => ", triangle waveform".to_string(),
        Waveform::Harmonics { third, fifth } => format!(", harmonics {third:.3} {fifth:.3}"),
    } + &model.sensor.depth_engine().map(describe_engine).unwrap_or_default();
    let departures = |p: &ModelOptions| {
        let mut d = vec![];
        if o.bounces != p.bounces {
            d.push(format!("bounces = {}", o.bounces));
        }
        if o.ir_mode != p.ir_mode {
            d.push(format!("ir_mode = {:?}", o.ir_mode).to_lowercase());
        }
        if o.transmission_albedo_power != p.transmission_albedo_power {
            d.push(format!("transmission_albedo_power = {}", o.transmission_albedo_power));
        }
        if o.ambient_offset != p.ambient_offset {
            d.push(format!("ambient_offset = {}", o.ambient_offset));
        }
        if o.subsurface_delay_mm != p.subsurface_delay_mm {
            d.push(format!("subsurface_delay_mm = {}", o.subsurface_delay_mm));
        }
        if o.refraction_shift_px != p.refraction_shift_px {
            d.push(format!(
                "refraction_shift_px = [{}, {}]",
                o.refraction_shift_px[0], o.refraction_shift_px[1]
            ));
        }
        let gains = [
            ("wall_interreflection", o.wall_interreflection, p.wall_interreflection),
            ("diffuse_transmission", o.diffuse_transmission, p.diffuse_transmission),
            ("hollow_depth_mm", o.hollow_depth_mm, p.hollow_depth_mm),
        ];
        for (name, mine, preset) in gains {
            if mine != preset {
                d.push(format!("{name} = {mine}"));
            }
        }
        d
    };
    // Ties go to the paper's model, the one scene files are written against.
    let (preset, d) = Preset::ALL
        .iter()
        .rev()
        .map(|p| (p.name(), departures(&p.options())))
        .min_by_key(|(_, d)| d.len())
        .unwrap_or(("physical", vec![]));
    if d.is_empty() {
        format!("{preset}{wave}")
    } else {
        format!("{preset} with {}{wave}", d.join(", "))
    }
}

/// A depth engine in words: `, depth engine 80/16/120 MHz (invalid past 100.4 mm)`.
pub fn describe_engine(e: &DepthEngine) -> String {
    let f: Vec<String> = e.frequencies_hz.iter().map(|f| format!("{}", f / 1e6)).collect();
    let threshold = e
        .max_disagreement_mm
        .map(|t| format!(" (invalid past {t:.1} mm)"))
        .unwrap_or_default();
    format!(", depth engine {} MHz{threshold}", f.join("/"))
}

/// The physics a recording says it was made with.
#[derive(Debug, Clone)]
pub struct RecordedPhysics {
    /// The physics file it holds.
    pub file: PhysicsFile,
    /// That file's text.
    pub text: String,
    /// Where it was found, in words ("named by its metadata record ...").
    pub from: String,
}

/// What the physics of a run is, and where it came from.
#[derive(Debug, Clone)]
pub struct PhysicsChoice {
    /// The model.
    pub model: ForwardModel,
    /// `option`, `recording` or `default`.
    pub source: &'static str,
    /// What was used and why, in words.
    pub text: String,
    /// A given `--physics` that is not what the recording was made with (or a
    /// recorded physics that could not be read).
    pub warning: Option<String>,
    /// What `--physics` gives this model elsewhere: a preset's name, or the file
    /// given; `None` for recorded physics that is no preset.
    pub option: Option<String>,
}

impl PhysicsChoice {
    /// For a JSON report.
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "source": self.source,
            "model": describe_model(&self.model),
            "text": self.text,
            "model_options": self.model.options,
            "warning": self.warning,
            "option": self.option,
        })
    }
}

pub(crate) fn waveform(name: &str, harmonics: Option<[f64; 2]>) -> Result<Waveform> {
    Ok(match name {
        "sinusoid" => Waveform::Sinusoid,
        "triangle" => Waveform::Triangle,
        "harmonics" => {
            let [third, fifth] = harmonics.unwrap_or([0.0, 0.0]);
            Waveform::Harmonics { third, fifth }
        }
        other => bail!("waveform {other:?}: expected sinusoid, triangle or harmonics"),
    })
}

impl ModelArgs {
    /// The forward model these options describe (the default physics when
    /// `--physics` is not given; [`ModelArgs::choose`] for a recording).
    pub fn model(&self) -> Result<ForwardModel> {
        self.check_frequency()?;
        let file = self.given_file()?.unwrap_or_default();
        self.build(&file)
    }

    fn check_frequency(&self) -> Result<()> {
        if !(self.modulation_frequency_hz.is_finite() && self.modulation_frequency_hz > 0.0) {
            bail!(
                "--modulation-frequency-hz must be positive, got {}",
                self.modulation_frequency_hz
            );
        }
        Ok(())
    }

    /// The physics file `--physics` names, if given.
    fn given_file(&self) -> Result<Option<PhysicsFile>> {
        let Some(p) = &self.physics else { return Ok(None) };
        Ok(Some(match p.to_str().and_then(Preset::from_name) {
            Some(preset) => PhysicsFile {
                preset: Some(preset),
                ..PhysicsFile::default()
            },
            None if !p.exists() => {
                let names: Vec<&str> = Preset::ALL.iter().map(|p| p.name()).collect();
                bail!(
                    "physics {:?}: neither a preset ({}) nor an existing physics file",
                    p.display().to_string(),
                    names.join(", ")
                )
            }
            None => PhysicsFile::load(p)?,
        }))
    }

    fn build(&self, file: &PhysicsFile) -> Result<ForwardModel> {
        let mut options = file.options();
        if let Some(m) = self.ir_mode {
            options.ir_mode = m.into();
        }
        let wf = waveform(file.waveform.as_deref().unwrap_or(self.waveform.name()), file.harmonics)?;
        let mut sensor = Sensor::new(self.modulation_frequency_hz, wf);
        // The engine given on the command line, else the file's.
        if let Some(engine) = self.depth_engine.engine()?.or_else(|| file.depth_engine.clone()) {
            sensor = sensor.with_depth_engine(&engine)?;
        }
        Ok(ForwardModel { sensor, options })
    }

    /// The model for a recording: `--physics` when given (with a warning when
    /// the recording says it was made with other physics), else the physics
    /// the recording names, else the default.
    pub fn choose(&self, recorded: Result<Option<&RecordedPhysics>, &str>) -> Result<PhysicsChoice> {
        self.check_frequency()?;
        let given = self.given_file()?;
        let given_name = self
            .physics
            .as_ref()
            .map(|p| p.display().to_string())
            .unwrap_or_default();
        match (given, recorded) {
            (Some(g), Ok(Some(r))) => {
                let model = self.build(&g)?;
                let theirs = self.build(&r.file)?;
                let same = model.options == theirs.options
                    && model.sensor.waveform == theirs.sensor.waveform
                    && model.sensor.depth_engine() == theirs.sensor.depth_engine();
                let (text, warning) = if same {
                    (
                        format!(
                            "{} (--physics {given_name}; the recording was made with the same, {})",
                            describe_model(&model),
                            r.from
                        ),
                        None,
                    )
                } else {
                    (
                        format!("{} (--physics {given_name})", describe_model(&model)),
                        Some(format!(
                            "--physics {given_name}{} differs from the physics the recording was made with ({}, {}): xi and the recovered depth are those of another model; leave --physics out to use the recording's",
                            if describe_model(&model) == given_name {
                                String::new()
                            } else {
                                format!(" ({})", describe_model(&model))
                            },
                            describe_model(&theirs),
                            r.from
                        )),
                    )
                };
                Ok(PhysicsChoice {
                    option: physics_option(&model).map(str::to_string).or(Some(given_name)),
                    model,
                    source: "option",
                    text,
                    warning,
                })
            }
            (Some(g), recorded) => {
                let model = self.build(&g)?;
                Ok(PhysicsChoice {
                    text: format!("{} (--physics {given_name})", describe_model(&model)),
                    option: physics_option(&model).map(str::to_string).or(Some(given_name.clone())),
                    model,
                    source: "option",
                    warning: recorded
                        .err()
                        .map(|e| format!("{e}; the recording's physics is unknown, --physics {given_name} is used")),
                })
            }
            (None, Ok(Some(r))) => {
                let model = self.build(&r.file)?;
                Ok(PhysicsChoice {
                    text: format!(
                        "{}, the recording's own, {}; --physics overrides",
                        describe_model(&model),
                        r.from
                    ),
                    option: physics_option(&model).map(str::to_string),
                    model,
                    source: "recording",
                    warning: None,
                })
            }
            (None, Ok(None)) => {
                let model = self.build(&PhysicsFile::default())?;
                Ok(PhysicsChoice {
                    text: format!(
                        "{}, the default (the recording does not say which physics it was made with; --physics paper for the paper's model)",
                        describe_model(&model)
                    ),
                    option: physics_option(&model).map(str::to_string),
                    model,
                    source: "default",
                    warning: None,
                })
            }
            (None, Err(e)) => bail!("{e}; pass --physics physical, paper or a physics file"),
        }
    }
}

/// An emitted-light calibration file, as `calibrate-lin` writes it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LinFile {
    /// Format tag.
    pub format: String,
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Albedo of the calibration plane.
    pub albedo: f64,
    /// Exposure of the calibration recording, s (Eq. 14), if known.
    pub exposure_s: Option<f64>,
    /// RMS of the calibration plane fit, mm.
    pub plane_rms_mm: f64,
    /// `Lin` per pixel, row-major, counts mm^2 (null where the plane was not seen).
    pub lin: Vec<Option<f64>>,
}

/// The format tag of [`LinFile`].
pub const LIN_FORMAT: &str = "translucent_tof.lin.v1";

impl LinFile {
    /// Reads a calibration and scales it to `exposure_s` (Eq. 14) when both exposures are known.
    pub fn load(path: &Path, exposure_s: Option<f64>) -> Result<ImageBuf<f64>> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading Lin calibration {}", path.display()))?;
        let f: LinFile = serde_json::from_str(&text).with_context(|| format!("Lin calibration {}", path.display()))?;
        if f.format != LIN_FORMAT {
            bail!(
                "Lin calibration {}: format {:?}, expected {LIN_FORMAT:?}",
                path.display(),
                f.format
            );
        }
        let data: Vec<f64> = f.lin.iter().map(|v| v.unwrap_or(f64::NAN)).collect();
        let lin = ImageBuf::from_vec(f.width, f.height, data).with_context(|| {
            format!(
                "Lin calibration {}: {} values for {}x{}",
                path.display(),
                f.lin.len(),
                f.width,
                f.height
            )
        })?;
        Ok(match (f.exposure_s, exposure_s) {
            (Some(cal), Some(now)) if cal > 0.0 && now > 0.0 => {
                crate::physics::emitted_light::scale_for_exposure(&lin, cal, now)
            }
            _ => lin,
        })
    }
}

/// Where the human summary and the JSON report go.
#[derive(Debug, Clone, Args, Default)]
pub struct OutputArgs {
    /// Write a machine-readable JSON report to FILE (`-` for standard output; the summary then goes to standard error).
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

impl OutputArgs {
    /// JSON goes to stdout: keep stdout clean and progress quiet.
    pub fn json_on_stdout(&self) -> bool {
        self.json.as_deref() == Some(Path::new("-"))
    }

    /// Prints the human summary (to stderr when stdout carries JSON).
    /// A closed pipe (`| head`) is not an error worth a panic: the summary is dropped.
    pub fn summary(&self, text: &str) {
        use std::io::Write;
        let _ = if self.json_on_stdout() {
            writeln!(std::io::stderr(), "{text}")
        } else {
            writeln!(std::io::stdout(), "{text}")
        };
    }

    /// Writes the JSON report, if asked.
    pub fn write_json(&self, value: &serde_json::Value) -> Result<()> {
        let Some(path) = &self.json else { return Ok(()) };
        let text = serde_json::to_string_pretty(value)?;
        if self.json_on_stdout() {
            use std::io::Write;
            writeln!(std::io::stdout(), "{text}").context("writing the JSON report to standard output")?;
        } else {
            write_atomic(path, text.as_bytes())?;
        }
        Ok(())
    }

    /// A progress bar on an interactive terminal; hidden in pipelines and with `--json -`.
    pub fn progress(&self, len: u64, label: &str) -> ProgressBar {
        let show = std::io::stderr().is_terminal() && !self.json_on_stdout();
        let pb = ProgressBar::with_draw_target(
            Some(len),
            if show {
                ProgressDrawTarget::stderr()
            } else {
                ProgressDrawTarget::hidden()
            },
        );
        if let Ok(style) = ProgressStyle::with_template("{prefix:>12} [{bar:30}] {pos}/{len} {msg}") {
            pb.set_style(style.progress_chars("=> "));
        }
        pb.set_prefix(label.to_string());
        pb
    }
}

/// Where outputs go when their option is not given: relative to the working directory.
pub const OUT_DIR: &str = "out";

/// Creates the folder a file is to be written in, if it has one and it is missing.
pub fn create_parent(path: &Path) -> Result<()> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() && !dir.is_dir() => {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))
        }
        _ => Ok(()),
    }
}

pub use crate::files::write_atomic;

/// Reads a materials file (`calibrate-xi -o`) and sets the priors given as `NAME=WEIGHT`
/// items: every error names the file and the field.
pub fn load_materials<S: AsRef<str>>(path: &Path, priors: &[S]) -> Result<crate::physics::catalog::Catalog> {
    use crate::physics::catalog::Catalog;
    let text = std::fs::read_to_string(path).with_context(|| format!("reading materials file {}", path.display()))?;
    let mut catalog = Catalog::from_toml(&text).map_err(|e| anyhow!("materials file {}: {e}", path.display()))?;
    catalog
        .set_priors(priors)
        .map_err(|e| anyhow!("materials file {}: prior {e}", path.display()))?;
    Ok(catalog)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(engine: DepthEngineArgs, physics: Option<&str>) -> ModelArgs {
        ModelArgs {
            physics: physics.map(PathBuf::from),
            modulation_frequency_hz: 30e6,
            waveform: WaveformArg::Sinusoid,
            ir_mode: None,
            depth_engine: engine,
        }
    }

    #[test]
    fn a_depth_engine_goes_through_the_physics_file_and_the_options() {
        let declared = DepthEngineArgs {
            depth_engine_frequencies_hz: vec![16e6, 80e6, 120e6],
            ..DepthEngineArgs::default()
        };
        let model = args(declared.clone(), None).model().expect("a model");
        let engine = model.sensor.depth_engine().cloned().expect("the engine");
        assert_eq!(engine.frequencies_hz, [16e6, 80e6, 120e6]);
        assert!(engine.max_disagreement_mm.is_none());
        assert_eq!(physics_option(&model), None, "no preset is an engine");
        assert!(describe_model(&model).ends_with("depth engine 16/80/120 MHz"));
        // The complete file carries it, and reads back to the same sensor.
        let text = PhysicsFile::complete(&model.options, &model.sensor)
            .to_toml()
            .expect("toml");
        assert!(text.contains("[depth_engine]"), "{text}");
        let file = PhysicsFile::parse(&text, "test").expect("parses");
        let back = args(DepthEngineArgs::default(), None).build(&file).expect("a model");
        assert_eq!(back.sensor.depth_engine(), Some(&engine));
        // A recording made through it is replayed through it; --physics physical drops it.
        let recorded = RecordedPhysics {
            file,
            text,
            from: "a test".into(),
        };
        let own = args(DepthEngineArgs::default(), None)
            .choose(Ok(Some(&recorded)))
            .unwrap();
        assert_eq!(own.model.sensor.depth_engine(), Some(&engine));
        let single = args(DepthEngineArgs::default(), Some("physical"))
            .choose(Ok(Some(&recorded)))
            .unwrap();
        assert!(single.model.sensor.depth_engine().is_none() && single.warning.is_some());
        let same = args(declared, Some("physical")).choose(Ok(Some(&recorded))).unwrap();
        assert!(same.warning.is_none(), "{:?}", same.warning);
        // The preset, and what is refused.
        let kinect = DepthEngineArgs {
            depth_engine: Some("kinect_v2".into()),
            ..DepthEngineArgs::default()
        };
        let k = args(kinect, None).model().unwrap();
        assert_eq!(k.sensor.depth_engine(), Some(&DepthEngine::kinect_v2()));
        let bad = DepthEngineArgs {
            depth_engine_frequencies_hz: vec![20e6],
            ..DepthEngineArgs::default()
        };
        assert!(args(bad, None).model().is_err());
        assert!(PhysicsFile::parse("[depth_engine]\nfrequencies_hz = [20e6, -1]\n", "t").is_err());
    }
}
