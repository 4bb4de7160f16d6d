//! `audit`: where the model and a ground-truthed recording disagree, which
//! effect the paper leaves out explains it, fitted and shown (physics::audit).

use std::path::PathBuf;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use serde_json::{json, Value};

use crate::audit::{gather, recovery_rmse, trend_svg};
use crate::physics::audit::{
    run_audit_with_progress, where_it_helped, AuditResult, AuditSettings, CandidateScore, Dependence, Effect, Fit,
    SignatureTest, Trend,
};
use crate::physics::ImageBuf;
use crate::physics::{IrMode, Waveform};
use crate::pipeline::{DepthFrame, PipelineConfig, XiChoice};

use super::common::{write_atomic, OutputArgs, PhysicsFile, PipelineArgs};
use super::recording::{load, Recording};

/// Pixels the fits use at most (spread over the frames).
const MAX_PIXELS: usize = 1500;

/// Arguments of `audit`.
#[derive(Debug, Args)]
pub struct AuditArgs {
    /// A recording with ground truth for the foreground (`ground_truth/depth`): the layer at several known distances.
    pub bag: PathBuf,
    /// Write the residual plots (SVG) into this directory.
    #[arg(long, value_name = "DIR")]
    pub plots: Option<PathBuf>,
    /// Log the plot series to a Rerun recording (needs a build with Rerun).
    #[arg(long, value_name = "OUT.rrd")]
    pub rerun: Option<PathBuf>,
    /// Write the chosen effects and their fitted parameters as a physics file (TOML) for `replay --physics`.
    #[arg(long, value_name = "FILE")]
    pub physics_out: Option<PathBuf>,
    /// Other ground-truthed recordings of the same camera: each is replayed with the physics
    /// file the audit would write and with its baseline's, and the file is not written where it
    /// worsens any by more than 10 % (every-pixel error).
    #[arg(long = "check-on", value_name = "BAG", num_args = 1..)]
    pub check_on: Vec<PathBuf>,
    #[command(flatten)]
    pub pipeline: PipelineArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// Most a physics file may worsen another recording's every-pixel error (`--check-on`), as a share.
const CHECK_MAX_WORSENING: f64 = 0.10;

/// One `--check-on` recording replayed with the baseline's physics and with the file's.
#[derive(Debug, Clone)]
struct Check {
    /// The recording.
    bag: PathBuf,
    /// Every-pixel error with the baseline's physics, mm.
    baseline_mm: f64,
    /// Every-pixel error with the physics file, mm.
    file_mm: f64,
}

impl Check {
    /// The file worsens this recording by more than [`CHECK_MAX_WORSENING`].
    fn worsens(&self) -> bool {
        !(self.file_mm <= (1.0 + CHECK_MAX_WORSENING) * self.baseline_mm)
    }

    fn json(&self) -> Value {
        json!({
            "bag": self.bag.display().to_string(),
            "baseline_every_pixel_rmse_mm": self.baseline_mm,
            "file_every_pixel_rmse_mm": self.file_mm,
            "ratio": self.file_mm / self.baseline_mm,
            "worsens": self.worsens(),
        })
    }
}

/// Replays each of `bags` with `baseline` and with `file` (physics files) by this program's
/// own `replay`, ξ estimated as for any scene: the every-pixel errors.
fn check_on(bags: &[PathBuf], baseline: &PhysicsFile, file: &PhysicsFile) -> Result<Vec<Check>> {
    let exe = std::env::current_exe().context("finding this program to replay the --check-on recordings")?;
    let dir = std::env::temp_dir().join(format!("translucent_tof_audit_check_{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let result = (|| {
        let mut paths = vec![];
        for (name, f) in [("baseline.toml", baseline), ("file.toml", file)] {
            let path = dir.join(name);
            let text = toml::to_string(f).context("writing a physics file to check")?;
            write_atomic(&path, text.as_bytes())?;
            paths.push(path);
        }
        bags.iter()
            .map(|bag| {
                Ok(Check {
                    bag: bag.clone(),
                    baseline_mm: replay_every_pixel(&exe, bag, &paths[0], &dir)?,
                    file_mm: replay_every_pixel(&exe, bag, &paths[1], &dir)?,
                })
            })
            .collect::<Result<Vec<_>>>()
    })();
    // Best effort: a leftover temporary folder is no error of the audit's.
    let _ = std::fs::remove_dir_all(&dir);
    result
}

/// `replay BAG --physics PHYSICS`: its every-pixel error, mm.
fn replay_every_pixel(
    exe: &std::path::Path,
    bag: &std::path::Path,
    physics: &std::path::Path,
    dir: &std::path::Path,
) -> Result<f64> {
    let json_path = dir.join("replay.json");
    let out = std::process::Command::new(exe)
        .arg("replay")
        .arg(bag)
        .arg("--physics")
        .arg(physics)
        .arg("--json")
        .arg(&json_path)
        .arg("--out")
        .arg(dir.join("replay.mcap"))
        .output()
        .with_context(|| format!("--check-on {}: running replay", bag.display()))?;
    if !out.status.success() {
        bail!(
            "--check-on {}: replay failed: {}",
            bag.display(),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    let text = std::fs::read_to_string(&json_path).with_context(|| format!("reading {}", json_path.display()))?;
    let v: Value =
        serde_json::from_str(&text).with_context(|| format!("--check-on {}: replay's report", bag.display()))?;
    v["every_pixel_rmse_mm"]
        .as_f64()
        .filter(|e| e.is_finite())
        .ok_or_else(|| {
            anyhow!(
                "--check-on {}: the recording has no ground truth (ground_truth/depth) to measure the file against",
                bag.display()
            )
        })
}

/// Runs `audit`.
pub fn run(a: AuditArgs) -> Result<()> {
    if let Some(r) = &a.rerun {
        if !cfg!(feature = "rerun") {
            bail!(
                "--rerun {}: this build has no Rerun logging (rebuild with the default `rerun` feature); the audit's plot series are in the JSON report (\"plots\") and the SVG files of --plots",
                r.display()
            );
        }
    }
    let mut config = a.pipeline.config()?;
    let rec = load(&a.bag, &a.pipeline.topics)?;
    // The physics the recording says it was made with, unless --physics says otherwise.
    let physics_choice = rec.physics_choice(&a.pipeline.model)?;
    config.model = physics_choice.model.clone();
    if rec.topics.ground_truth.is_none() || rec.truth.is_empty() {
        bail!(
            "bag {}: the audit compares the model with known foreground distances, and the bag has no ground_truth/depth images (sensor_msgs/Image, 32FC1 z in metres, NaN where no foreground): record a calibration sequence with ground truth (paper Sec. V-A)",
            a.bag.display()
        );
    }
    let bg = rec.background_frames(a.pipeline.background_frames, &config)?;
    let pipe = rec.latched_pipeline(config.clone(), bg.count)?;
    let objects: Vec<_> = rec.frames[bg.count..]
        .iter()
        .filter_map(|f| rec.truth.get(&f.stamp_ns).map(|t| (f, t)))
        .collect();
    let (data, stats) = gather(&pipe, &objects, MAX_PIXELS).context("gathering the translucent pixels")?;
    if stats.translucent_with_truth == 0 {
        bail!(
            "bag {}: the ground truth does not overlap the translucent pixels ({} frame(s) with truth, {} translucent pixel(s), none with a true foreground distance): the audit needs the layer's true distance where the readings moved by more than {} mm",
            a.bag.display(),
            stats.frames_with_truth,
            stats.translucent,
            config.threshold_mm
        );
    }
    // Held-out recovery is scored with the pipeline's inversion bounds.
    let settings = AuditSettings {
        inversion: config.bounds,
        ..AuditSettings::default()
    };
    // Baseline, then up to seven candidates per round.
    let pb = a.output.progress(1 + 7 * settings.max_effects as u64, "auditing");
    let result = run_audit_with_progress(&data, &config.model, &settings, &mut |what| {
        pb.set_message(what.to_string());
        pb.inc(1);
    })
    .map_err(|e| anyhow!("bag {}: {e}", a.bag.display()))?;
    pb.finish_and_clear();
    let base = &config.model;
    let replayed = Replayed {
        rec: &rec,
        config: &config,
        background: bg.count,
        objects: &objects,
    };
    let [before, after, kept] = replayed.recoveries(&result)?;
    let mut choice = ModelChoice::new(&result, base, before, kept, a.physics_out.as_deref());
    let checks = if a.check_on.is_empty() || result.kept_fit().effects.is_empty() || !choice.written {
        vec![]
    } else {
        check_on(&a.check_on, &physics_file(&result.baseline, base), &choice.physics)?
    };
    choice.checked(&result, &a.check_on, &checks, a.physics_out.as_deref());
    let plots = write_plots(&a, &result)?;
    if let (Some(out), true) = (&a.physics_out, choice.written) {
        write_physics_file(out, &result, &choice)?;
    }
    let mut report = report(&a, &result, base, &choice, before, after, &plots, &bg.how, &stats);
    report["physics_used"] = physics_choice.json();
    report["warnings"] = json!(rec.cut.iter().chain(&physics_choice.warning).collect::<Vec<_>>());
    let mut head = format!("physics: {}\n", physics_choice.text);
    for w in rec.cut.iter().chain(&physics_choice.warning) {
        head += &format!("WARNING: {w}\n");
    }
    let body = summary(&result, base, &choice, before, after, a.physics_out.as_deref());
    a.output.summary(format!("{head}{body}").trim_end());
    if !choice.written && a.physics_out.is_some() {
        // Loud: on the terminal whatever the summary's stream, and in the JSON.
        eprintln!("WARNING: {}", choice.note);
    }
    a.output.write_json(&report)
}

/// The recording replayed with a fitted model, for its recovery.
struct Replayed<'a> {
    rec: &'a Recording,
    config: &'a PipelineConfig,
    background: usize,
    objects: &'a [(&'a DepthFrame, &'a ImageBuf<f32>)],
}

impl Replayed<'_> {
    /// Recovery (mm RMS, pixels) at the fit's ξ with its model.
    fn recovery(&self, fit: &Fit) -> Result<Option<(f64, usize)>> {
        let cfg = PipelineConfig {
            model: fit.model(&self.config.model),
            xi: XiChoice::Fixed(fit.xi),
            ..self.config.clone()
        };
        let p = self.rec.latched_pipeline(cfg, self.background)?;
        Ok(recovery_rmse(&p, self.objects, fit.xi))
    }

    /// Recovery with the baseline, the final (claimed) model and the model to use.
    fn recoveries(&self, result: &AuditResult) -> Result<[Option<(f64, usize)>; 3]> {
        let before = self.recovery(&result.baseline)?;
        let after = if result.steps.is_empty() {
            before
        } else {
            self.recovery(result.final_fit())?
        };
        let kept = if result.kept_steps == result.steps.len() {
            after
        } else if result.kept_steps == 0 {
            before
        } else {
            self.recovery(result.kept_fit())?
        };
        Ok([before, after, kept])
    }
}

/// Writes the model to use as a physics file, the ξ it was fitted with in its comments.
fn write_physics_file(out: &std::path::Path, result: &AuditResult, choice: &ModelChoice) -> Result<()> {
    let xi = result.kept_fit().xi;
    let text = format!(
        "# Written by translucent_tof audit: {}.\n# Fitted with xi = {xi:.4}: replay --physics {} --xi {xi:.3}\n{}",
        file_header(result),
        out.display(),
        toml::to_string(&choice.physics).context("writing the physics file")?
    );
    Ok(write_atomic(out, text.as_bytes())?)
}

/// The model the audit stands by and writes with `--physics-out`: the claimed steps up
/// to the last one that recovers held-out frames no worse than the one before, and
/// written only where it recovers the recording no worse than the baseline.
struct ModelChoice {
    /// Its physics file.
    physics: PhysicsFile,
    /// The claimed effect it stops before (whose held-out recovery is worse), if any.
    stopped_before: Option<Effect>,
    /// Recovery of the recording with it, mm RMS and pixels.
    recovery: Option<(f64, usize)>,
    /// The file was written (or would be, where no `--physics-out` was given).
    written: bool,
    /// Why it stops where it does, or why nothing was written; empty when all is well.
    note: String,
    /// Where it was checked, in words.
    checked_on: String,
    /// The `--check-on` recordings replayed with it.
    checks: Vec<Value>,
}

impl ModelChoice {
    fn new(
        result: &AuditResult,
        base: &crate::physics::ForwardModel,
        before: Option<(f64, usize)>,
        recovery: Option<(f64, usize)>,
        out: Option<&std::path::Path>,
    ) -> Self {
        let fit = result.kept_fit();
        let stopped_before = result
            .steps
            .get(result.kept_steps)
            .and_then(|s| s.effects.last().copied());
        let mut note = match stopped_before {
            Some(e) => format!(
                "the model stops before {}: held-out recovery {:.1} mm with it against {:.1} mm without",
                e.name(),
                result.steps[result.kept_steps].heldout_recovery_rmse_mm,
                fit.heldout_recovery_rmse_mm
            ),
            None => String::new(),
        };
        let refused = refusal(&effects_text(&fit.effects), before, recovery, out);
        let written = refused.is_none();
        if let Some(r) = refused {
            note = if note.is_empty() { r } else { format!("{r}; {note}") };
        }
        Self {
            physics: physics_file(fit, base),
            stopped_before,
            recovery,
            written,
            note,
            checked_on: String::new(),
            checks: vec![],
        }
    }
}

impl ModelChoice {
    /// Where the file was checked, and refused where it worsens a `--check-on` recording by
    /// more than [`CHECK_MAX_WORSENING`].
    fn checked(&mut self, result: &AuditResult, bags: &[PathBuf], checks: &[Check], out: Option<&std::path::Path>) {
        self.checks = checks.iter().map(Check::json).collect();
        self.checked_on = if result.kept_fit().effects.is_empty() {
            "the file is the baseline's physics: nothing to check".to_string()
        } else if !self.written {
            "not checked on other recordings: it is not written".to_string()
        } else if bags.is_empty() {
            "checked on its own recording only (give other ground-truthed recordings of the camera with --check-on)"
                .to_string()
        } else {
            let figures: Vec<String> = checks
                .iter()
                .map(|c| {
                    format!(
                        "{} {:.1} -> {:.1} mm",
                        c.bag
                            .file_name()
                            .map_or(c.bag.display().to_string(), |n| n.to_string_lossy().into_owned()),
                        c.baseline_mm,
                        c.file_mm
                    )
                })
                .collect();
            format!(
                "checked on {} other recording(s), every-pixel error with the baseline's physics -> with the file: {}",
                checks.len(),
                figures.join(", ")
            )
        };
        if let Some(c) = checks.iter().find(|c| c.worsens()) {
            let what = out.map_or("no physics file would be written".to_string(), |p| {
                format!(
                    "--physics-out {} NOT WRITTEN (a file already there is from before)",
                    p.display()
                )
            });
            let r = format!(
                "{what}: it worsens {} by more than {:.0} % (every-pixel error {:.1} mm against {:.1} with the baseline's physics)",
                c.bag.display(),
                100.0 * CHECK_MAX_WORSENING,
                c.file_mm,
                c.baseline_mm
            );
            self.note = if self.note.is_empty() {
                r
            } else {
                format!("{r}; {}", self.note)
            };
            self.written = false;
        }
    }
}

/// What the physics file holds, in words (its first comment line).
fn file_header(result: &AuditResult) -> String {
    match (result.kept_steps, result.steps.get(result.kept_steps)) {
        (_, None) => "the baseline's physics and the effects the recording supports past it".to_string(),
        (0, Some(s)) => format!(
            "the baseline's physics only: the first effect claimed ({}) recovers held-out frames worse",
            effects_text(&s.effects)
        ),
        (_, Some(s)) => format!(
            "the baseline's physics and the effects claimed up to the last that recovers no worse (not {})",
            s.effects.last().map_or("", |e| e.name())
        ),
    }
}

/// Why the model to use (`model`, in words) is not written, if it is not: it must recover
/// the recording no worse than the baseline (`before`; `kept` its own recovery), and both
/// must be measured.
fn refusal(
    model: &str,
    before: Option<(f64, usize)>,
    kept: Option<(f64, usize)>,
    out: Option<&std::path::Path>,
) -> Option<String> {
    let what = out.map_or("no physics file would be written".to_string(), |p| {
        format!(
            "--physics-out {} NOT WRITTEN (a file already there is from before)",
            p.display()
        )
    });
    match (before, kept) {
        (Some(b), Some(k)) if k.0 <= b.0 => None,
        (Some(b), Some(k)) => Some(format!(
            "{what}: the model to use ({model}) recovers this recording worse than its baseline: {:.1} mm RMS against {:.1} mm",
            k.0, b.0
        )),
        _ => Some(format!(
            "{what}: the recovery of the model to use ({model}) or of its baseline could not be measured on this recording, so it is not shown to recover no worse"
        )),
    }
}

fn effects_text(effects: &[Effect]) -> String {
    if effects.is_empty() {
        "the baseline".to_string()
    } else {
        effects.iter().map(|e| e.name()).collect::<Vec<_>>().join(" + ")
    }
}

/// Writes the residual plots (SVG) and the Rerun recording, as asked; their paths.
fn write_plots(a: &AuditArgs, result: &AuditResult) -> Result<Vec<String>> {
    let mut plots = vec![];
    if let Some(dir) = &a.plots {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for (b, f) in result.trends_before.iter().zip(&result.trends_after) {
            let name = format!("residual_vs_{}.svg", b.quantity.name());
            let path = dir.join(&name);
            let title = format!(
                "{}: held-out depth residual vs {}",
                a.bag.file_name().and_then(|n| n.to_str()).unwrap_or("bag"),
                b.quantity.name()
            );
            write_atomic(&path, trend_svg(b, f, &title).as_bytes())?;
            plots.push(path.display().to_string());
        }
    }
    if let Some(r) = &a.rerun {
        let mut curves = vec![];
        for (b, f) in result.trends_before.iter().zip(&result.trends_after) {
            for (t, when, color) in [(b, "before", [230, 80, 60]), (f, "after", [40, 170, 230])] {
                let points = t
                    .bins
                    .iter()
                    .zip(&t.mean_mm)
                    .filter(|(_, m)| m.is_finite())
                    .map(|(bin, m)| [(0.5 * (bin[0] + bin[1])) as f32, *m as f32])
                    .collect();
                curves.push(crate::viz::Curve {
                    entity: format!("audit/residual_vs_{}/{when}", t.quantity.name()),
                    points,
                    color,
                });
            }
        }
        let target = crate::viz::RerunTarget::File(r.clone());
        crate::viz::write_curves(&target, "translucent_tof_audit", &curves).map_err(|e| anyhow::anyhow!(e))?;
        plots.push(r.display().to_string());
    }
    Ok(plots)
}

/// The human summary: the baseline, each effect claimed, recovery, and the model written.
fn summary(
    result: &AuditResult,
    base: &crate::physics::ForwardModel,
    choice: &ModelChoice,
    before: Option<(f64, usize)>,
    after: Option<(f64, usize)>,
    out: Option<&std::path::Path>,
) -> String {
    let mut summary = format!(
        "baseline ({} physics): xi {:.3}, depth RMSE {:.1} mm, held-out {:.1} mm, held-out recovery {:.1} mm ({} pixels, {} frames)\n",
        if base.options == crate::physics::ModelOptions::paper() {
            "the paper's"
        } else if base.options == crate::physics::ModelOptions::physical() {
            "the default"
        } else {
            "the given"
        },
        result.baseline.xi,
        result.baseline.rmse_mm,
        result.baseline.heldout_rmse_mm,
        result.baseline.heldout_recovery_rmse_mm,
        result.pixels,
        result.frames
    );
    if result.steps.is_empty() {
        summary += "no effect left out: no candidate improves the held-out error beyond the noise\n";
    }
    for s in &result.steps {
        summary += &format!(
            "+ {}: xi {:.3}, held-out {:.1} mm, held-out recovery {:.1} mm{}{}\n",
            s.effects.last().map(|e| e.name()).unwrap_or(""),
            s.xi,
            s.heldout_rmse_mm,
            s.heldout_recovery_rmse_mm,
            match params_text(&s.params) {
                p if p.is_empty() => p,
                p => format!(" ({p})"),
            },
            bound_text(&s.at_bound)
        );
    }
    summary += &format!("left unexplained: {}\n", result.dependence.words);
    if let (Some(b), Some(f)) = (before, after) {
        summary += &format!("recovery on this recording: {:.1} -> {:.1} mm RMS\n", b.0, f.0);
    }
    if choice.stopped_before.is_some() {
        if let Some(k) = choice.recovery {
            summary += &format!(
                "model kept: {}, recovery {:.1} mm RMS\n",
                effects_text(&result.kept_fit().effects),
                k.0
            );
        }
    }
    // Not written where asked: the warning goes to standard error, after this.
    let warned_apart = out.is_some() && !choice.written;
    if !choice.note.is_empty() && !warned_apart {
        summary += &format!("{}{}\n", if choice.written { "" } else { "WARNING: " }, choice.note);
    }
    if !choice.checked_on.is_empty() {
        summary += &format!("{}\n", choice.checked_on);
    }
    if let (true, Some(out)) = (choice.written, out) {
        summary += &format!("wrote {}\n", out.display());
    }
    summary
}

fn bound_text(at_bound: &[String]) -> String {
    if at_bound.is_empty() {
        String::new()
    } else {
        format!(" [at the bound of its physical range: {}]", at_bound.join(", "))
    }
}

fn params_text(p: &[(String, f64)]) -> String {
    p.iter()
        .map(|(k, v)| format!("{k} {v:.4}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn params_json(fit: &Fit, with_xi: bool) -> Value {
    let mut m = serde_json::Map::new();
    if with_xi {
        m.insert("xi".into(), json!(fit.xi));
        m.insert("albedo".into(), json!(fit.albedo));
    }
    for (k, v) in &fit.params {
        m.insert(k.clone(), json!(v));
    }
    Value::Object(m)
}

/// The physics file of a fitted model: the baseline's keys and the fit's effects'.
fn physics_file(fin: &Fit, base: &crate::physics::ForwardModel) -> PhysicsFile {
    let m = fin.model(base);
    // Written against the paper's model, whatever the baseline: every key that departs from
    // it is in the file, so the file reads the same whatever the tools' default becomes.
    let mut f = PhysicsFile {
        preset: Some(crate::physics::Preset::Paper),
        ..PhysicsFile::default()
    };
    // What the baseline already modelled (the default physics, or a --physics given to the audit) stays.
    let d = crate::physics::ModelOptions::paper();
    let o = &base.options;
    f.bounces = (o.bounces != d.bounces).then_some(o.bounces);
    f.ir_mode = (o.ir_mode != d.ir_mode).then_some(o.ir_mode);
    f.transmission_albedo_power =
        (o.transmission_albedo_power != d.transmission_albedo_power).then_some(o.transmission_albedo_power);
    f.ambient_offset = (o.ambient_offset != d.ambient_offset).then_some(o.ambient_offset);
    f.subsurface_delay_mm = (o.subsurface_delay_mm != d.subsurface_delay_mm).then_some(o.subsurface_delay_mm);
    f.refraction_shift_px = (o.refraction_shift_px != d.refraction_shift_px).then_some(o.refraction_shift_px);
    match base.sensor.waveform {
        Waveform::Harmonics { third, fifth } => {
            f.waveform = Some("harmonics".into());
            f.harmonics = Some([third, fifth]);
        }
        Waveform::Triangle => f.waveform = Some("triangle".into()),
        Waveform::Sinusoid => {}
    }
    for e in &fin.effects {
        match e {
            Effect::HigherOrderBounces => f.bounces = Some(m.options.bounces),
            Effect::WaveformHarmonics => {
                if let Waveform::Harmonics { third, fifth } = m.sensor.waveform {
                    f.waveform = Some("harmonics".into());
                    f.harmonics = Some([third, fifth]);
                }
            }
            Effect::IrAmplitude => f.ir_mode = Some(IrMode::Amplitude),
            Effect::AmbientOffset => f.ambient_offset = Some(m.options.ambient_offset),
            Effect::SubsurfaceDelay => f.subsurface_delay_mm = Some(m.options.subsurface_delay_mm),
            Effect::TransmissionLaw => f.transmission_albedo_power = Some(m.options.transmission_albedo_power),
            Effect::RefractionShift => f.refraction_shift_px = Some(m.options.refraction_shift_px),
            Effect::WallInterreflection => f.wall_interreflection = Some(m.options.wall_interreflection),
            Effect::DiffuseTransmission => f.diffuse_transmission = Some(m.options.diffuse_transmission),
            Effect::ThreeReturns => f.hollow_depth_mm = Some(m.options.hollow_depth_mm),
        }
    }
    f
}

#[allow(clippy::too_many_arguments)]
fn report(
    a: &AuditArgs,
    r: &AuditResult,
    base: &crate::physics::ForwardModel,
    choice: &ModelChoice,
    before: Option<(f64, usize)>,
    after: Option<(f64, usize)>,
    plots: &[String],
    background: &str,
    stats: &crate::audit::GatherStats,
) -> Value {
    let fin = r.final_fit();
    json!({
        "bag": a.bag.display().to_string(),
        "frames": r.frames,
        "pixels": r.pixels,
        "background_choice": background,
        "translucent_pixels": stats.translucent,
        "translucent_pixels_with_truth": stats.translucent_with_truth,
        "baseline": {
            "rmse_mm": r.baseline.rmse_mm,
            "heldout_rmse_mm": r.baseline.heldout_rmse_mm,
            "heldout_score": r.baseline.heldout_score,
            "heldout_recovery_rmse_mm": r.baseline.heldout_recovery_rmse_mm,
            "ir_rel_rmse": r.baseline.ir_rel_rmse,
            "params": params_json(&r.baseline, true),
            "systematic": strongest(&r.trends_before),
        },
        "findings": findings_json(r),
        "final": {
            "effects": fin.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
            "heldout_rmse_mm": fin.heldout_rmse_mm,
            "heldout_score": fin.heldout_score,
            "heldout_recovery_rmse_mm": fin.heldout_recovery_rmse_mm,
            "rmse_mm": fin.rmse_mm,
            "params": params_json(fin, true),
            "at_bound": fin.at_bound,
            "physics": serde_json::to_value(physics_file(fin, base)).unwrap_or(Value::Null),
            "noise_ratio": r.final_noise_ratio,
            "systematic": strongest(&r.trends_after),
        },
        "physics_out": physics_out_json(a, r, choice, before),
        "candidates": r.candidates.iter().map(candidate_json).collect::<Vec<_>>(),
        "dependence": dependence_json(&r.dependence),
        "recovery_rmse_mm": {
            "before": before.map(|b| b.0),
            "after": after.map(|b| b.0),
            "pixels": before.map(|b| b.1),
            "note": match (before, after) {
                (Some(b), Some(f)) if f.0 > b.0 => "recovery with the chosen model is worse than with the baseline, though the model fits the readings better: the inversion's choice among several roots (README, Limits) fails on this recording under the chosen physics; the physics file stops before it (physics_out)",
                _ => "",
            },
        },
        "plots": {
            "files": plots,
            "before": r.trends_before.iter().map(trend_json).collect::<Vec<_>>(),
            "after": r.trends_after.iter().map(trend_json).collect::<Vec<_>>(),
        },
    })
}

/// The strongest systematic trends (z over 5), strongest first.
fn strongest(trends: &[Trend]) -> Vec<Value> {
    let mut t: Vec<_> = trends.iter().filter(|t| t.systematic_z > 5.0).collect();
    t.sort_by(|a, b| b.systematic_z.total_cmp(&a.systematic_z));
    t.iter()
        .map(|t| json!({"quantity": t.quantity.name(), "z": t.systematic_z, "where": t.worst_bin()}))
        .collect()
}

/// The one strongest dependence of the residual left, against the others.
fn dependence_json(d: &Dependence) -> Value {
    json!({
        "quantity": d.quantity.map(|q| q.name()),
        "z": d.z,
        "against": d.against.iter().map(|(q, z)| json!({"quantity": q.name(), "z": z})).collect::<Vec<_>>(),
        "words": d.words,
    })
}

fn trend_json(t: &Trend) -> Value {
    json!({
        "quantity": t.quantity.name(),
        "bins": t.bins,
        "counts": t.counts,
        "mean_mm": t.mean_mm,
        "se_mm": t.se_mm,
        "ir_mean_pct": t.ir_mean_pct,
        "systematic_z": t.systematic_z,
    })
}

/// One finding per claimed effect, with its evidence and where it helped.
fn findings_json(r: &AuditResult) -> Vec<Value> {
    let mut prev = &r.baseline;
    let mut prev_trends = &r.trends_before;
    let mut findings = vec![];
    for (k, (s, trends)) in r.steps.iter().zip(&r.step_trends).enumerate() {
        let effect = s.effects.last().map(|e| e.name()).unwrap_or("");
        let cand = r.candidates.iter().find(|c| c.accepted && c.effect.name() == effect);
        let where_ = where_it_helped(prev_trends, trends);
        findings.push(json!({
            "effect": effect,
            "evidence": format!(
                "held-out loss per pixel {:.3} -> {:.3} (gain {:.0}, {:.1} standard errors, needed {:.0}); held-out depth RMSE {:.1} -> {:.1} mm; held-out recovery {:.1} -> {:.1} mm; xi refitted {:.3} -> {:.3}",
                prev.heldout_score,
                s.heldout_score,
                cand.map(|c| c.gain).unwrap_or(f64::NAN),
                cand.map(|c| c.z).unwrap_or(f64::NAN),
                cand.map(|c| c.threshold).unwrap_or(f64::NAN),
                prev.heldout_rmse_mm,
                s.heldout_rmse_mm,
                prev.heldout_recovery_rmse_mm,
                s.heldout_recovery_rmse_mm,
                prev.xi,
                s.xi
            ),
            "where": if where_.is_empty() { "no single quantity carries the residual".to_string() } else { where_ },
            "heldout_rmse_mm": s.heldout_rmse_mm,
            "heldout_score": s.heldout_score,
            "heldout_recovery_rmse_mm": s.heldout_recovery_rmse_mm,
            "params": params_json(s, true),
            "at_bound": s.at_bound,
            "in_physics_out": k < r.kept_steps,
        }));
        prev = s;
        prev_trends = trends;
    }
    findings
}

fn candidate_json(c: &CandidateScore) -> Value {
    json!({
        "round": c.round,
        "effect": c.effect.name(),
        "heldout_rmse_mm": c.heldout_rmse_mm,
        "heldout_score": c.heldout_score,
        "heldout_recovery_rmse_mm": c.heldout_recovery_rmse_mm,
        "gain": c.gain,
        "threshold": c.threshold,
        "z": c.z,
        "xi": c.xi,
        "params": c.params.iter().map(|(k, v)| (k.clone(), json!(v))).collect::<serde_json::Map<_, _>>(),
        "at_bound": c.at_bound,
        "signature": signature_json(&c.signature),
        "accepted": c.accepted,
        "rejected": c.rejected,
    })
}

/// A candidate's signature test: what its misfit follows and whether the residual shows it.
fn signature_json(t: &SignatureTest) -> Value {
    json!({
        "quantity": t.quantity.name(),
        "observed_z": t.observed_z,
        "left_z": t.left_z,
        "explained": t.explained,
        "correlation": t.correlation,
        "dominant": t.dominant.name(),
        "dominant_z": t.dominant_z,
        "dominant_explained": t.dominant_explained,
        "plausible": t.plausible,
        "passed": t.passed,
        "failed": t.failed,
    })
}

/// The model the audit stands by (and writes with `--physics-out`), and whether it was written.
fn physics_out_json(a: &AuditArgs, r: &AuditResult, choice: &ModelChoice, before: Option<(f64, usize)>) -> Value {
    let fit = r.kept_fit();
    json!({
        "file": a.physics_out.as_ref().map(|p| p.display().to_string()),
        "path": a.physics_out.as_ref().map(|p| p.display().to_string()),
        "written": choice.written && a.physics_out.is_some(),
        "refused": (!choice.written).then_some(&choice.note),
        "recovers_no_worse_than_baseline": choice.written,
        "effects": fit.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
        "steps_kept": r.kept_steps,
        "steps_claimed": r.steps.len(),
        "stopped_before": choice.stopped_before.map(|e| e.name()),
        "xi": fit.xi,
        "heldout_recovery_rmse_mm": fit.heldout_recovery_rmse_mm,
        "recovery_rmse_mm": choice.recovery.map(|k| k.0),
        "baseline_recovery_rmse_mm": before.map(|b| b.0),
        "physics": serde_json::to_value(&choice.physics).unwrap_or(Value::Null),
        "note": choice.note,
        "checked_on": choice.checked_on,
        "check_on": choice.checks,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_model_that_recovers_worse_than_its_baseline_is_refused_with_its_figures() {
        let out = std::path::Path::new("physics.toml");
        assert_eq!(
            refusal("ir_amplitude", Some((27.6, 10)), Some((11.6, 10)), Some(out)),
            None
        );
        assert_eq!(
            refusal("ir_amplitude", Some((11.6, 10)), Some((11.6, 10)), Some(out)),
            None
        );
        let worse = refusal("transmission_law", Some((23.9, 10)), Some((647.9, 10)), Some(out)).unwrap_or_default();
        assert!(
            worse.contains("--physics-out physics.toml NOT WRITTEN")
                && worse.contains("647.9")
                && worse.contains("23.9"),
            "{worse}"
        );
        let unknown = refusal("transmission_law", Some((23.9, 10)), None, None).unwrap_or_default();
        assert!(unknown.contains("could not be measured"), "{unknown}");
    }
}
