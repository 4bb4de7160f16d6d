//! `audit`: where the model and a ground-truthed recording disagree, which
//! effect the paper leaves out explains it, fitted and shown (physics::audit).

use std::path::PathBuf;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use serde_json::{json, Value};

use crate::audit::{gather, recovery_rmse, trend_svg};
use crate::physics::audit::{run_audit_with_progress, where_it_helped, AuditResult, AuditSettings, Effect, Fit};
use crate::physics::{IrMode, Waveform};
use crate::pipeline::{PipelineConfig, XiChoice};

use super::common::{describe_model, write_atomic, OutputArgs, PhysicsFile, PipelineArgs};
use super::recording::load;

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
    #[command(flatten)]
    pub pipeline: PipelineArgs,
    #[command(flatten)]
    pub output: OutputArgs,
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
    let settings = AuditSettings::default();
    // Baseline, then up to seven candidates per round.
    let pb = a.output.progress(1 + 7 * settings.max_effects as u64, "auditing");
    let result = run_audit_with_progress(&data, &config.model, &settings, &mut |what| {
        pb.set_message(what.to_string());
        pb.inc(1);
    })
    .map_err(|e| anyhow!("bag {}: {e}", a.bag.display()))?;
    pb.finish_and_clear();
    let base = &config.model;
    let fin = result.final_fit();
    // Recovery on the same recording, before and after.
    let recover_with = |fit: &Fit| -> Result<Option<(f64, usize)>> {
        let cfg = PipelineConfig {
            model: fit.model(base),
            xi: XiChoice::Fixed(fit.xi),
            ..config.clone()
        };
        let p = rec.latched_pipeline(cfg, bg.count)?;
        Ok(recovery_rmse(&p, &objects, fit.xi))
    };
    let before = recover_with(&result.baseline)?;
    let after = if result.steps.is_empty() {
        before
    } else {
        recover_with(fin)?
    };
    let physics = physics_file(&result, base);
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
    // A model that recovers this recording worse than its baseline is not written.
    let worse = match (before, after) {
        (Some(b), Some(f)) => f.0 > b.0 * (1.0 + WORSE_BY),
        _ => false,
    };
    let recovery_text = match (before, after) {
        (Some(b), Some(f)) => format!(
            "recovery on this recording at the fitted xi (RMS z error over every translucent pixel with truth, pooled over frames): {:.1} mm with the baseline -> {:.1} mm with the chosen model",
            b.0, f.0
        ),
        _ => String::new(),
    };
    let refusal = match &a.physics_out {
        Some(out) if worse => Some(format!(
            "--physics-out {} NOT WRITTEN: the chosen model ({}) recovers this recording worse than its baseline ({:.1} -> {:.1} mm RMS), though it fits the readings better: the inversion fails under it here (README, Limits: several roots). The baseline recovers it better: replay {}{} --xi {:.3}",
            out.display(),
            fin.effects.iter().map(|e| e.name()).collect::<Vec<_>>().join(", "),
            before.map_or(f64::NAN, |b| b.0),
            after.map_or(f64::NAN, |f| f.0),
            a.bag.display(),
            match &a.pipeline.model.physics {
                Some(p) => format!(" --physics {}", p.display()),
                None => String::new(),
            },
            result.baseline.xi
        )),
        _ => None,
    };
    if let (Some(out), None) = (&a.physics_out, &refusal) {
        let text = format!(
            "# Written by translucent_tof audit: the baseline's physics and the effects the recording supports past it.\n# Fitted with xi = {:.4}: replay --physics {} --xi {:.3}\n{}",
            fin.xi,
            out.display(),
            fin.xi,
            toml::to_string(&physics).context("writing the physics file")?
        );
        write_atomic(out, text.as_bytes())?;
    }
    let mut report = report(&a, &result, &physics, before, after, &plots, &bg.how, &stats);
    report["physics_used"] = physics_choice.json();
    report["warnings"] = json!(rec.cut.iter().chain(&physics_choice.warning).collect::<Vec<_>>());
    report["physics_out"] = json!({
        "path": a.physics_out.as_ref().map(|p| p.display().to_string()),
        "written": a.physics_out.is_some() && refusal.is_none(),
        "refused": refusal,
    });
    let mut summary = format!("physics: {}\n", physics_choice.text);
    for w in rec.cut.iter().chain(&physics_choice.warning) {
        summary += &format!("WARNING: {w}\n");
    }
    summary += &format!(
        "baseline ({}): xi {:.3}, depth RMSE {:.1} mm, held-out {:.1} mm ({} pixels, {} frames)\n",
        describe_model(base),
        result.baseline.xi,
        result.baseline.rmse_mm,
        result.baseline.heldout_rmse_mm,
        result.pixels,
        result.frames
    );
    if result.steps.is_empty() {
        summary += "no effect left out: no candidate improves the held-out error beyond the noise\n";
    }
    for s in &result.steps {
        let params = params_text(&s.params);
        summary += &format!(
            "+ {}: xi {:.3}, held-out {:.1} mm{}\n",
            s.effects.last().map(|e| e.name()).unwrap_or(""),
            s.xi,
            s.heldout_rmse_mm,
            if params.is_empty() {
                String::new()
            } else {
                format!(" ({params})")
            }
        );
    }
    if !recovery_text.is_empty() {
        summary += &recovery_text;
        summary += "\n";
    }
    match (&a.physics_out, &refusal) {
        (Some(_), Some(why)) => {
            // Loud, on the terminal whatever happens to the summary.
            eprintln!("\n{}\nWARNING: {why}\n{}\n", "!".repeat(72), "!".repeat(72));
            summary += &format!("WARNING: {why}");
        }
        (Some(out), None) => summary += &format!("wrote {}", out.display()),
        _ => {}
    }
    a.output.summary(summary.trim_end());
    a.output.write_json(&report)
}

/// How much worse (relative) recovery with the chosen model may be than with the
/// baseline before `--physics-out` is refused.
const WORSE_BY: f64 = 0.01;

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

/// The physics file of the final model: only the chosen effects' keys.
fn physics_file(result: &AuditResult, base: &crate::physics::ForwardModel) -> PhysicsFile {
    let fin = result.final_fit();
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
        }
    }
    f
}

#[allow(clippy::too_many_arguments)]
fn report(
    a: &AuditArgs,
    r: &AuditResult,
    physics: &PhysicsFile,
    before: Option<(f64, usize)>,
    after: Option<(f64, usize)>,
    plots: &[String],
    background: &str,
    stats: &crate::audit::GatherStats,
) -> Value {
    let fin = r.final_fit();
    let strongest = |trends: &[crate::physics::audit::Trend]| -> Vec<Value> {
        let mut t: Vec<_> = trends.iter().filter(|t| t.systematic_z > 5.0).collect();
        t.sort_by(|a, b| b.systematic_z.total_cmp(&a.systematic_z));
        t.iter()
            .map(|t| json!({"quantity": t.quantity.name(), "z": t.systematic_z, "where": t.worst_bin()}))
            .collect()
    };
    let mut prev = &r.baseline;
    let mut prev_trends = &r.trends_before;
    let mut findings = vec![];
    for (s, trends) in r.steps.iter().zip(&r.step_trends) {
        let effect = s.effects.last().map(|e| e.name()).unwrap_or("");
        let cand = r
            .candidates
            .iter()
            .find(|c| c.accepted && c.effect.name() == effect)
            .cloned();
        let where_ = where_it_helped(prev_trends, trends);
        findings.push(json!({
            "effect": effect,
            "evidence": format!(
                "held-out loss per pixel {:.3} -> {:.3} (gain {:.0}, {:.1} standard errors, needed {:.0}); held-out depth RMSE {:.1} -> {:.1} mm; xi refitted {:.3} -> {:.3}",
                prev.heldout_score,
                s.heldout_score,
                cand.as_ref().map(|c| c.gain).unwrap_or(f64::NAN),
                cand.as_ref().map(|c| c.z).unwrap_or(f64::NAN),
                cand.as_ref().map(|c| c.threshold).unwrap_or(f64::NAN),
                prev.heldout_rmse_mm,
                s.heldout_rmse_mm,
                prev.xi,
                s.xi
            ),
            "where": if where_.is_empty() { "no single quantity carries the residual".to_string() } else { where_ },
            "heldout_rmse_mm": s.heldout_rmse_mm,
            "heldout_score": s.heldout_score,
            "params": params_json(s, true),
        }));
        prev = s;
        prev_trends = trends;
    }
    let trend_json = |t: &crate::physics::audit::Trend| {
        json!({
            "quantity": t.quantity.name(),
            "bins": t.bins,
            "counts": t.counts,
            "mean_mm": t.mean_mm,
            "se_mm": t.se_mm,
            "ir_mean_pct": t.ir_mean_pct,
            "systematic_z": t.systematic_z,
        })
    };
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
            "ir_rel_rmse": r.baseline.ir_rel_rmse,
            "params": params_json(&r.baseline, true),
            "systematic": strongest(&r.trends_before),
        },
        "findings": findings,
        "final": {
            "effects": fin.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
            "heldout_rmse_mm": fin.heldout_rmse_mm,
            "heldout_score": fin.heldout_score,
            "rmse_mm": fin.rmse_mm,
            "params": params_json(fin, true),
            "physics": serde_json::to_value(physics).unwrap_or(Value::Null),
            "noise_ratio": r.final_noise_ratio,
            "systematic": strongest(&r.trends_after),
        },
        "candidates": r.candidates.iter().map(|c| json!({
            "round": c.round,
            "effect": c.effect.name(),
            "heldout_rmse_mm": c.heldout_rmse_mm,
            "heldout_score": c.heldout_score,
            "gain": c.gain,
            "threshold": c.threshold,
            "z": c.z,
            "xi": c.xi,
            "params": c.params.iter().map(|(k, v)| (k.clone(), json!(v))).collect::<serde_json::Map<_, _>>(),
            "accepted": c.accepted,
        })).collect::<Vec<_>>(),
        "recovery_rmse_mm": {
            "before": before.map(|b| b.0),
            "after": after.map(|b| b.0),
            "pixels": before.map(|b| b.1),
            "metric": "RMS z error over every translucent pixel with ground truth, pooled over the object frames, at the fitted xi",
            "note": match (before, after) {
                (Some(b), Some(f)) if f.0 > b.0 => "recovery with the chosen model is worse than with the baseline's, though the model fits the readings better: the inversion's choice among several roots (README, Limits) fails on this recording under the chosen physics",
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
