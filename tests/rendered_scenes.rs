//! The defaults on physically rendered recordings (bags/rendered, made by
//! scripts/render with Mitsuba 3 + mitransient: real light transport, not the
//! project's own model), and the audit's loop closed on one of them.
//!
//! Every figure asserted here is printed; `scripts/results` gives the whole set.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

fn exe() -> &'static str {
    env!("CARGO_BIN_EXE_translucent_tof")
}

fn rendered(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/rendered").join(name)
}

fn run(dir: &Path, args: &[&str]) -> Value {
    let json = dir.join("report.json");
    let out = Command::new(exe())
        .args(args)
        .arg("--json")
        .arg(&json)
        .current_dir(dir)
        .output()
        .expect("run translucent_tof");
    assert!(
        out.status.success(),
        "{args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(&std::fs::read_to_string(&json).expect("report")).expect("json")
}

fn replay(dir: &Path, bag: &str, extra: &[&str]) -> Value {
    let bag = rendered(bag);
    let mut args = vec!["replay", bag.to_str().expect("utf-8"), "--out", "out.mcap"];
    args.extend_from_slice(extra);
    run(dir, &args)
}

fn num(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or_else(|| panic!("{key} missing in {v}"))
}

/// The estimate of the material with the most evidence, its interval and the mean per-frame RMS.
fn summary(r: &Value) -> (f64, [f64; 2], f64) {
    let iv = |i: usize| r["xi_interval"][i].as_f64().expect("interval");
    (num(r, "xi"), [iv(0), iv(1)], num(r, "mean_frame_rmse_mm"))
}

#[test]
fn the_papers_file_box_with_the_defaults_beats_the_paper() {
    let dir = tempfile::tempdir().expect("temp dir");
    let r = replay(dir.path(), "paper_file_box.mcap", &[]);
    let (xi, iv, rms) = summary(&r);
    println!(
        "file box (xi 0.94): xi {xi:.3} [{:.3}, {:.3}], mean per-frame RMS {rms:.1} mm (paper 51.7)",
        iv[0], iv[1]
    );
    assert!(iv[0] <= 0.94 && 0.94 <= iv[1] && iv[1] - iv[0] <= 0.15, "{iv:?}");
    assert!(rms <= 51.7, "{rms} mm");
}

/// The document holder's first three distances recover to a few millimetres with the true ξ;
/// the last, 250 mm before the wall, is where the rendered light departs most from two
/// returns (the paper's errors jump there too): the mean stays within twice the paper's 10.6 mm.
#[test]
fn the_papers_document_holder_with_the_defaults() {
    let dir = tempfile::tempdir().expect("temp dir");
    let r = replay(dir.path(), "paper_document_holder.mcap", &[]);
    let (xi, iv, rms) = summary(&r);
    // (Its interval, about [0.67, 0.69], misses the true 0.65: the last distance pulls ξ up; README, Limits.)
    println!(
        "document holder (xi 0.65): xi {xi:.3} [{:.3}, {:.3}], mean per-frame RMS {rms:.1} mm (paper 10.6)",
        iv[0], iv[1]
    );
    assert!((xi - 0.65).abs() <= 0.05, "{xi}");
    assert!(rms <= 2.0 * 10.6, "{rms} mm");
    // The paper's model on the same recording does worse: the default is the better-supported one.
    let paper = replay(dir.path(), "paper_document_holder.mcap", &["--physics", "paper"]);
    let (_, _, paper_rms) = summary(&paper);
    println!("document holder with --physics paper: {paper_rms:.1} mm");
    assert!(rms < paper_rms, "default {rms} mm, paper {paper_rms} mm");
}

#[test]
fn a_tilted_sheet_before_a_gray_cluttered_background() {
    let dir = tempfile::tempdir().expect("temp dir");
    let r = replay(dir.path(), "tilted_gray.mcap", &[]);
    let (xi, iv, rms) = summary(&r);
    let truth = 0.5077;
    println!(
        "tilted sheet (xi {truth}): xi {xi:.3} [{:.3}, {:.3}], mean per-frame RMS {rms:.1} mm",
        iv[0], iv[1]
    );
    assert!(iv[0] <= truth && truth <= iv[1], "{iv:?}");
    assert!(rms <= 30.0, "{rms} mm");
}

/// The audit on a rendered calibration sequence: from the paper's model it names the
/// amplitude IR and claims nothing unphysical or worse on held-out frames; the physics file
/// it writes recovers that scene and another of the camera better than the paper's model.
/// From the default physics it finds nothing left out.
#[test]
fn the_audits_loop_closes_on_a_rendered_calibration_sequence() {
    let dir = tempfile::tempdir().expect("temp dir");
    let cal = rendered("calibration_sequence.mcap");
    let cal = cal.to_str().expect("utf-8");
    let a = run(
        dir.path(),
        &["audit", cal, "--physics", "paper", "--physics-out", "physics.toml"],
    );
    let effects: Vec<&str> = a["final"]["effects"]
        .as_array()
        .expect("effects")
        .iter()
        .filter_map(|e| e.as_str())
        .collect();
    println!(
        "audit from the paper's model: {effects:?}, held-out {} -> {} mm",
        a["baseline"]["heldout_rmse_mm"], a["final"]["heldout_rmse_mm"]
    );
    assert!(effects.contains(&"ir_amplitude"), "{effects:?}");
    assert!(num(&a["final"], "heldout_rmse_mm") < num(&a["baseline"], "heldout_rmse_mm"));
    for f in a["findings"].as_array().expect("findings") {
        if let Some(p) = f["params"]["transmission_albedo_power"].as_f64() {
            assert!((0.0..=2.0).contains(&p), "{f}");
        }
    }
    let physics = dir.path().join("physics.toml");
    let physics = physics.to_str().expect("utf-8");
    for bag in ["calibration_sequence.mcap", "paper_document_holder.mcap"] {
        let (_, _, with) = summary(&replay(dir.path(), bag, &["--physics", physics]));
        let (_, _, without) = summary(&replay(dir.path(), bag, &["--physics", "paper"]));
        println!("{bag}: {without:.1} mm with the paper's model, {with:.1} mm with the audit's physics file");
        assert!(with < without, "{bag}: {with} against {without}");
    }
    let d = run(dir.path(), &["audit", cal]);
    let left_out = d["final"]["effects"].as_array().expect("effects");
    println!("audit from the default physics: {left_out:?}");
    assert!(left_out.is_empty(), "{d}");
}
