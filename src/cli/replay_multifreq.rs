//! `replay`'s multi-frequency path: a bag with `phasor_<k>/image_raw` topics
//! (docs/interfaces.md, "Multi-frequency input") is recovered pixel by pixel
//! from its phasors ([`crate::pipeline::multifreq`]), with the same outputs
//! as the single-frequency path plus `/translucent_tof/translucency_image`.

use anyhow::{anyhow, bail, Context, Result};
use serde_json::{json, Value};

use crate::bag::BagWriter;
use crate::image::{region_image, translucency_image};
use crate::msgs::Header;
use crate::outputs::output_messages;
use crate::pipeline::multifreq::{MultiFrequencyConfig, MultiFrequencyOutput, MultiFrequencyStage, PhasorFrame};
use crate::pipeline::{rmse_against_truth, DepthFrame, FrameOutput, Passthrough, PipelineConfig};

use super::recording::{PhasorRecording, Recording};
use super::replay::{finish_outputs, open_rerun, out_path, topics, write_published, ReplayArgs};

/// The frequencies: `--modulation-frequencies-hz`, else the bag's record; one per phasor topic.
fn frequencies(given: &[f64], mf: &PhasorRecording) -> Result<Vec<f64>> {
    let (f, source) = if !given.is_empty() {
        (given.to_vec(), "--modulation-frequencies-hz")
    } else {
        let recorded = mf.recorded_frequencies_hz.clone().ok_or_else(|| {
            anyhow!(
                "the bag has {} phasor topics ({}) but records no modulation frequencies (metadata translucent_tof.modulation_frequencies_hz): pass --modulation-frequencies-hz F0,F1,... (or --single-frequency to ignore the phasors)",
                mf.topics.len(),
                mf.topics.join(", ")
            )
        })?;
        (recorded, "the bag's metadata")
    };
    if f.len() != mf.topics.len() {
        bail!(
            "{} modulation frequencies from {source} ({}) for {} phasor topics ({}): one frequency per phasor_<k>/image_raw",
            f.len(),
            f.iter().map(|v| format!("{v}")).collect::<Vec<_>>().join(", "),
            mf.topics.len(),
            mf.topics.join(", ")
        );
    }
    if let Some(bad) = f.iter().find(|v| !(v.is_finite() && **v > 0.0)) {
        bail!("modulation frequency {bad} Hz from {source} is not positive");
    }
    Ok(f)
}

/// Running sums of the errors against ground truth.
#[derive(Default)]
struct Errors {
    sum_e2: f64,
    sum_raw2: f64,
    n: usize,
    segmented: usize,
    frame_rmse: Vec<(f64, f64)>,
}

/// Runs `replay` on the multi-frequency path.
pub fn run(a: &ReplayArgs, config: PipelineConfig, rec: Recording) -> Result<()> {
    if let Some(x) = a.xi {
        bail!("--xi {x}: the multi-frequency path determines xi per pixel from the phasors; pass --single-frequency to recover from the depth and IR with a given xi");
    }
    let mf = rec.multi_frequency.as_ref().context("no phasor topics")?;
    let f = frequencies(&a.modulation_frequencies_hz, mf)?;
    let mut settings = MultiFrequencyConfig::new(f.clone(), config.model.clone());
    settings.min_region_pixels = config.min_region_pixels;
    let mut stage = MultiFrequencyStage::new(settings, rec.intrinsics).context("the modulation frequencies")?;
    if a.no_latch && f.len() < 3 {
        bail!(
            "--no-latch: {} modulation frequencies; two free returns need at least three (six numbers for four unknowns)",
            f.len()
        );
    }
    let depth_range = config.model.sensor.unambiguous_range_mm();
    let (bg_count, bg_how, background) = if a.no_latch {
        (0, "none: --no-latch".to_string(), None)
    } else {
        let bg = rec.background_frames(a.pipeline.background_frames, &config)?;
        let latch: Vec<(&PhasorFrame, &DepthFrame)> = mf.frames.iter().zip(&rec.frames).take(bg.count).collect();
        let pb = a.output.progress(1, "latching the phasor background");
        let background = stage
            .latch(&latch, depth_range)
            .context("latching the phasor background")?
            .clone();
        pb.finish_and_clear();
        (bg.count, bg.how, Some(background))
    };
    let out_path = out_path(&a.bag, a.out.as_deref());
    super::common::create_parent(&out_path)?;
    let mut writer = BagWriter::create(&out_path).with_context(|| format!("creating {}", out_path.display()))?;
    if let Some(r) = &a.rerun {
        super::common::create_parent(r)?;
    }
    for (f, header) in rec.frames[..bg_count].iter().zip(&rec.headers) {
        // The node passes the frames it latches through.
        let out = FrameOutput::passed_through(f, Passthrough::Latching);
        let m = output_messages(
            header,
            (&rec.camera_info, stage.rays()),
            &out,
            &f.ir,
            &rec.depth_encoding,
        )?;
        write_published(&mut writer, &m)?;
        let none = crate::physics::ImageBuf::filled(f.z_mm.width, f.z_mm.height, 0u16);
        writer.write(topics::REGIONS, f.stamp_ns, &region_image(header, &none)?)?;
    }
    let viz = open_rerun(a)?;
    let objects = bg_count..rec.frames.len();
    let pb = a.output.progress(objects.len() as u64, "recovering");
    let (mut per_frame, mut errors, mut total_px, mut last) = (vec![], Errors::default(), 0, None);
    for j in objects {
        let (p, f) = (&mf.frames[j], &rec.frames[j]);
        let out = if a.no_latch {
            stage.process_unlatched(p, f)
        } else {
            stage.process(p, f)
        }
        .with_context(|| format!("frame at stamp {} ns", f.stamp_ns))?;
        write_outputs(&mut writer, &rec.headers[j], (&stage, &rec), &out, f)?;
        if let (Some(v), Some(r)) = (&viz, &a.rerun) {
            v.log(&crate::viz::FrameViz {
                stamp_ns: f.stamp_ns,
                frame: (j - bg_count) as u64,
                rays: stage.shared_rays(),
                raw_z_mm: f.z_mm.clone(),
                recovered_z_mm: out.frame.corrected_z_mm.clone(),
                mask: out.frame.mask.clone(),
                xi: Some((out.frame.xi.xi, out.frame.xi.interval)),
                objects: crate::viz::FrameViz::objects_of(&out.frame.regions),
            })
            .map_err(|e| anyhow!("--rerun {}: {e}", r.display()))?;
        }
        total_px += out.frame.translucent_pixels;
        per_frame.push(frame_row(&out, f, &rec, &mut errors));
        last = Some(out.frame.xi);
        pb.inc(1);
    }
    pb.finish_and_clear();
    finish_outputs(writer, &out_path, viz, a)?;
    let mut report = json!({
        "bag": a.bag.display().to_string(),
        "out": out_path.display().to_string(),
        "rerun": a.rerun.as_ref().map(|r| r.display().to_string()),
        "path": "multi_frequency",
        "frames": rec.frames.len(),
        "background_frames": bg_count,
        "background_choice": bg_how,
        "warnings": rec.read_stops,
        "read_stops": rec.read_stops,
        "multi_frequency": {
            "modulation_frequencies_hz": f,
            "common_unambiguous_range_mm": stage.common_unambiguous_range_mm(),
            "topics": mf.topics,
            "unpaired": mf.unpaired,
            "latched": background.is_some(),
            "background_valid_pixels": background.as_ref().map(|b| b.valid_pixels),
            "background_compared_with_depth": background.as_ref().map(|b| b.compared_pixels),
            "background_aliased_pixels": background.as_ref().map(|b| b.aliased_pixels),
            "background_systematic_mm": background.as_ref().map(|b| b.systematic_mm),
            "opacity_threshold": stage.config.opacity_threshold,
            "two_return_threshold": stage.config.two_return_threshold,
        },
        "sensor": {
            "modulation_frequency_hz": config.model.sensor.modulation_frequency_hz,
            "unambiguous_range_mm": depth_range,
            "waveform": format!("{:?}", config.model.sensor.waveform),
            "model_options": config.model.options,
        },
        "topics": {"depth": rec.topics.depth, "ir": rec.topics.ir, "info": rec.topics.info, "ground_truth": rec.topics.ground_truth, "notes": rec.topics.notes},
        "unpaired": {"depth": rec.unpaired.0, "ir": rec.unpaired.1},
        "xi": last.as_ref().map(|x| x.xi),
        "xi_interval": last.as_ref().map(|x| x.interval),
        "xi_method": last.as_ref().map(|x| x.method.as_str()),
        "xi_note": "the last frame's largest translucent region (per pixel on this path: see per_frame and translucency_image)",
        "translucent_pixels": total_px,
        "frames_written": rec.frames.len(),
        "passed_through": {"latching": bg_count},
        "per_frame": per_frame,
    });
    add_error_summary(&mut report, &errors);
    a.output.summary(&summary(&report, &rec));
    a.output.write_json(&report)
}

/// A frame's JSON row, its errors against ground truth added to `errors`.
fn frame_row(out: &MultiFrequencyOutput, f: &DepthFrame, rec: &Recording, errors: &mut Errors) -> Value {
    let o = &out.frame;
    let mut row = json!({
        "stamp": f.stamp_ns as f64 * 1e-9,
        "xi": o.xi.xi,
        "xi_interval": o.xi.interval,
        "xi_pixel_median": out.xi_pixel_median,
        "translucent_pixels": o.translucent_pixels,
        "recovered_pixels": o.recovered_pixels,
        "changed_pixels": out.changed_pixels,
        "opaque_pixels": out.opaque_pixels,
        "failed_pixels": out.failed_pixels,
        "unclaimed_pixels": out.unclaimed_pixels,
        "unusable_pixels": out.unusable_pixels,
        "regions": o.regions.iter().map(|r| json!({
            "id": r.id,
            "xi": r.xi.xi,
            "xi_interval": r.xi.interval,
            "pixels": r.pixels,
            "opaque": r.opaque,
            "note": r.xi.note,
        })).collect::<Vec<_>>(),
    });
    let Some(truth) = rec.truth.get(&f.stamp_ns) else {
        return row;
    };
    let segmented = (0..o.mask.len())
        .filter(|&i| o.mask.data[i] && truth.data[i].is_finite())
        .count();
    row["segmented_truth_pixels"] = json!(segmented);
    errors.segmented += segmented;
    let mut mask = o.mask.clone();
    for (m, z) in mask.data.iter_mut().zip(&o.corrected_z_mm.data) {
        *m &= z.is_finite();
    }
    if let (Some((e, n)), Some((raw, _))) = (
        rmse_against_truth(&o.corrected_z_mm, truth, &mask),
        rmse_against_truth(&f.z_mm, truth, &mask),
    ) {
        row["rmse_mm"] = json!(e);
        row["rmse_raw_mm"] = json!(raw);
        row["truth_pixels"] = json!(n);
        errors.sum_e2 += e * e * n as f64;
        errors.sum_raw2 += raw * raw * n as f64;
        errors.n += n;
        errors.frame_rmse.push((e, raw));
    }
    row
}

fn add_error_summary(report: &mut Value, e: &Errors) {
    if e.n == 0 {
        return;
    }
    let k = e.frame_rmse.len() as f64;
    report["rmse_mm"] = json!((e.sum_e2 / e.n as f64).sqrt());
    report["rmse_raw_mm"] = json!((e.sum_raw2 / e.n as f64).sqrt());
    report["coverage"] = json!(e.n as f64 / e.segmented.max(1) as f64);
    report["mean_frame_rmse_mm"] = json!(e.frame_rmse.iter().map(|r| r.0).sum::<f64>() / k);
    report["mean_frame_rmse_raw_mm"] = json!(e.frame_rmse.iter().map(|r| r.1).sum::<f64>() / k);
}

/// The node's outputs, the per-pixel ξ image and the regions image.
fn write_outputs(
    writer: &mut BagWriter,
    header: &Header,
    (stage, rec): (&MultiFrequencyStage, &Recording),
    out: &MultiFrequencyOutput,
    f: &DepthFrame,
) -> Result<()> {
    let t = out.frame.stamp_ns;
    let m = output_messages(
        header,
        (&rec.camera_info, stage.rays()),
        &out.frame,
        &f.ir,
        &rec.depth_encoding,
    )?;
    write_published(writer, &m)?;
    writer.write(
        "/translucent_tof/translucency_image",
        t,
        &translucency_image(header, &out.translucency)?,
    )?;
    let ids = crate::physics::ImageBuf {
        width: out.labels.width,
        height: out.labels.height,
        data: out
            .labels
            .data
            .iter()
            .map(|&l| u16::try_from(l).unwrap_or(u16::MAX))
            .collect(),
    };
    writer.write(topics::REGIONS, t, &region_image(header, &ids)?)?;
    Ok(())
}

fn summary(r: &Value, rec: &Recording) -> String {
    let mut s = String::new();
    for n in &rec.topics.notes {
        s.push_str(&format!("topics: {n}\n"));
    }
    let m = &r["multi_frequency"];
    let freqs: Vec<String> = m["modulation_frequencies_hz"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|v| format!("{:.1}", v.as_f64().unwrap_or(f64::NAN) / 1e6))
        .collect();
    s.push_str(&format!(
        "multi-frequency path: phasors at {} MHz (common unambiguous range {:.0} mm), each pixel inverted on its own\n",
        freqs.join(", "),
        m["common_unambiguous_range_mm"].as_f64().unwrap_or(f64::NAN)
    ));
    s.push_str(&format!(
        "background: {}\n",
        r["background_choice"].as_str().unwrap_or("")
    ));
    for w in r["warnings"].as_array().into_iter().flatten() {
        s.push_str(&format!("WARNING: {}\n", w.as_str().unwrap_or("")));
    }
    let frames = r["per_frame"].as_array().map(|v| v.as_slice()).unwrap_or(&[]);
    let mut medians: Vec<f64> = frames.iter().filter_map(|f| f["xi_pixel_median"].as_f64()).collect();
    medians.sort_by(f64::total_cmp);
    if let (Some(lo), Some(hi)) = (medians.first(), medians.last()) {
        s.push_str(&format!("per-pixel xi, median of each frame: {lo:.3} to {hi:.3}\n"));
    } else {
        s.push_str("xi: no translucent pixels\n");
    }
    s.push_str(&format!(
        "{} object frames, {} translucent pixels in all\n",
        frames.len(),
        r["translucent_pixels"]
    ));
    if let (Some(e), Some(raw)) = (r["mean_frame_rmse_mm"].as_f64(), r["mean_frame_rmse_raw_mm"].as_f64()) {
        s.push_str(&format!(
            "error against ground truth (mean of per-frame RMS over the mask): raw {raw:.1} mm -> recovered {e:.1} mm\n"
        ));
    }
    s.push_str(&format!("wrote {}", r["out"].as_str().unwrap_or("")));
    if let Some(rrd) = r["rerun"].as_str() {
        s.push_str(&format!(" and {rrd}"));
    }
    s
}
