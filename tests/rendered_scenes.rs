//! The defaults on physically rendered recordings (bags/rendered, made by
//! scripts/render with Mitsuba 3 + mitransient: real light transport, not the
//! project's own model), and the audit's loop closed on one of them.
//!
//! Every figure asserted here is printed; `scripts/results` gives the whole set.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

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

/// The Python with the checkers (`TTOF_PYTHON`, else the project's `.venv`).
fn python() -> String {
    std::env::var("TTOF_PYTHON").unwrap_or_else(|_| {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join(".venv/bin/python")
            .display()
            .to_string()
    })
}

fn num(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or_else(|| panic!("{key} missing in {v}"))
}

/// The estimate of the material with the most evidence, its interval and the mean per-frame RMS.
fn summary(r: &Value) -> (f64, [f64; 2], f64) {
    let iv = |i: usize| r["xi_interval"][i].as_f64().expect("interval");
    (num(r, "xi"), [iv(0), iv(1)], num(r, "mean_frame_rmse_mm"))
}

/// The file box against the paper's figure and its truth: ξ 0.94 inside the interval the
/// defaults publish (the model's error on rendered scenes included), which its four poses'
/// own evidence (`--xi-model-error-sd 0`) bound to ±0.075.
#[test]
fn the_papers_file_box_with_the_defaults_is_under_the_papers_error() {
    let dir = tempfile::tempdir().expect("temp dir");
    let r = replay(dir.path(), "paper_file_box.mcap", &[]);
    let (xi, iv, rms) = summary(&r);
    let (_, own, _) = summary(&replay(
        dir.path(),
        "paper_file_box.mcap",
        &["--xi-model-error-sd", "0"],
    ));
    println!(
        "file box (xi 0.94): xi {xi:.3} [{:.3}, {:.3}] (its evidence's own [{:.3}, {:.3}]), mean per-frame RMS {rms:.1} mm (paper 51.7)",
        iv[0], iv[1], own[0], own[1]
    );
    assert!(iv[0] <= 0.94 && 0.94 <= iv[1], "{iv:?}");
    assert!(own[1] - own[0] <= 0.15, "{own:?}");
    assert!(rms <= 51.7, "{rms} mm");
}

/// The document holder against the paper's figure and its truth: ξ 0.65 inside the interval,
/// which four poses of one sheet bound to ±0.1, and the error under the paper's 10.6 mm.
#[test]
#[ignore = "issue 36: 18.6 mm and [0.652, 0.696] (misses 0.65) with the default physics, which leaves out the near wall's third return in the last pose; with the audit's file the setup is under the paper's figure (the_audit_names_the_near_wall_on_the_rendered_document_holder_and_its_file_recovers_it)"]
fn the_papers_document_holder_with_the_defaults_is_under_the_papers_error() {
    let dir = tempfile::tempdir().expect("temp dir");
    let r = replay(dir.path(), "paper_document_holder.mcap", &[]);
    let (xi, iv, rms) = summary(&r);
    println!(
        "document holder (xi 0.65): xi {xi:.3} [{:.3}, {:.3}], mean per-frame RMS {rms:.1} mm (paper 10.6)",
        iv[0], iv[1]
    );
    assert!(iv[0] <= 0.65 && 0.65 <= iv[1] && iv[1] - iv[0] <= 0.2, "{iv:?}");
    assert!(rms <= 10.6, "{rms} mm");
}

/// The paper's model on the same recording does worse than the default: the default is the
/// better-supported one (physics.md §6).
#[test]
fn the_papers_document_holder_recovers_better_with_the_defaults_than_with_the_papers_model() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_, _, rms) = summary(&replay(dir.path(), "paper_document_holder.mcap", &[]));
    let (_, _, paper_rms) = summary(&replay(
        dir.path(),
        "paper_document_holder.mcap",
        &["--physics", "paper"],
    ));
    println!("document holder: {rms:.1} mm with the defaults, {paper_rms:.1} mm with --physics paper");
    assert!(rms < paper_rms, "default {rms} mm, paper {paper_rms} mm");
}

#[test]
fn a_tilted_sheet_before_a_gray_cluttered_background() {
    let dir = tempfile::tempdir().expect("temp dir");
    let r = replay(dir.path(), "tilted_gray.mcap", &[]);
    let (xi, iv, rms) = summary(&r);
    let (_, own, _) = summary(&replay(dir.path(), "tilted_gray.mcap", &["--xi-model-error-sd", "0"]));
    let truth = 0.5077;
    println!(
        "tilted sheet (xi {truth}): xi {xi:.3} [{:.3}, {:.3}] (its evidence's own [{:.3}, {:.3}]), mean per-frame RMS {rms:.1} mm",
        iv[0], iv[1], own[0], own[1]
    );
    // Four poses of one sheet determine xi: the truth inside the published interval (the
    // model's error included), which the evidence alone bounds to +-0.1.
    assert!(iv[0] <= truth && truth <= iv[1], "{iv:?}");
    assert!(own[0] <= truth && truth <= own[1] && own[1] - own[0] <= 0.2, "{own:?}");
    // The paper's figure for its nearest setup (the document holder, 10.6 mm) is for a sheet
    // facing the camera before a white wall; tilted before gray boxes, under its file box's.
    assert!(rms <= 51.7, "{rms} mm");
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
    // The paper's protocol under each physics: the material calibrated once on the calibration
    // sequence (known distances, Sec. V-A), then the scenes recovered with it.
    let recovered = |bag: &str, physics: &str| -> f64 {
        let c = run(dir.path(), &["calibrate-xi", cal, "--physics", physics]);
        let xi = format!("{}", num(&c, "xi"));
        let (_, _, rms) = summary(&replay(dir.path(), bag, &["--physics", physics, "--xi", &xi]));
        rms
    };
    for bag in ["calibration_sequence.mcap", "paper_document_holder.mcap"] {
        let with = recovered(bag, physics);
        let without = recovered(bag, "paper");
        println!("{bag}: {without:.1} mm with the paper's model, {with:.1} mm with the audit's physics file");
        assert!(with < without, "{bag}: {with} against {without}");
    }
    let d = run(dir.path(), &["audit", cal]);
    let left_out = d["final"]["effects"].as_array().expect("effects");
    println!("audit from the default physics: {left_out:?}");
    assert!(left_out.is_empty(), "{d}");
}

/// The translucent material's true ξ in a rendered bag's sidecar (its first `[[materials]]`).
fn sidecar_xi(bag: &str) -> f64 {
    let path = rendered(bag).with_extension("toml");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let v: toml::Value = toml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    v["materials"][0]["xi"].as_float().expect("materials[0].xi")
}

/// The names of the effects a report's findings claim, and the law's fitted power if claimed.
fn named_effects(a: &Value) -> (Vec<String>, Option<f64>) {
    let findings = a["findings"].as_array().expect("findings");
    let names = findings
        .iter()
        .filter_map(|f| f["effect"].as_str().map(str::to_string))
        .collect();
    let power = findings
        .iter()
        .find(|f| f["effect"] == "transmission_law")
        .and_then(|f| f["params"]["transmission_albedo_power"].as_f64());
    (names, power)
}

/// Issue 36, item 1, on the per-material calibration renders (`calib_*`: one sheet at four
/// distances, one of them tilted 20-35 degrees, before a plain wall). The tilt spreads
/// `X = rho_f cos(theta_f)` over the layer, which is what carries the law's power (one
/// fronto-parallel sheet trades it with ξ and the albedo: docs/audit.md). From the paper's
/// model each names the amplitude IR and the transmission law with its power at or near 0
/// (the renders' own physics), nothing else, and ξ within 0.02 of the truth; from the default
/// physics (the renders' own) each finds nothing left out. Every physics file that keeps the
/// law replays the paper's two setups within 10 % of the default physics' figures.
#[test]
fn the_audit_names_the_plain_law_on_the_rendered_material_calibrations() {
    let bags = [
        "calib_opaque_and_translucent_sheet.mcap",
        "calib_two_materials_sheet_high_xi.mcap",
        "calib_two_materials_sheet_low_xi.mcap",
        "calib_two_materials_sheet_mid_xi.mcap",
    ];
    let dirs: Vec<tempfile::TempDir> = bags.iter().map(|_| tempfile::tempdir().expect("temp dir")).collect();
    let audits: Vec<(Value, Value)> = std::thread::scope(|s| {
        let hs: Vec<_> = [[0, 2], [1, 3]]
            .into_iter()
            .map(|pair| {
                let (bags, dirs) = (&bags, &dirs);
                s.spawn(move || {
                    pair.map(|i| {
                        let bag = rendered(bags[i]);
                        let bag = bag.to_str().expect("utf-8");
                        let dir = dirs[i].path();
                        let paper = run(
                            dir,
                            &["audit", bag, "--physics", "paper", "--physics-out", "physics.toml"],
                        );
                        std::fs::rename(dir.join("report.json"), dir.join("paper.json")).expect("keep the report");
                        (i, paper, run(dir, &["audit", bag]))
                    })
                })
            })
            .collect();
        let mut all: Vec<_> = hs.into_iter().flat_map(|h| h.join().expect("audit thread")).collect();
        all.sort_by_key(|(i, _, _)| *i);
        all.into_iter().map(|(_, p, d)| (p, d)).collect()
    });
    let mut files_with_law = vec![];
    for ((bag, (paper, default)), dir) in bags.iter().zip(&audits).zip(&dirs) {
        let (named, power) = named_effects(paper);
        let (xi, truth) = (num(&paper["final"]["params"], "xi"), sidecar_xi(bag));
        let kept: Vec<&str> = paper["physics_out"]["effects"]
            .as_array()
            .map(|a| a.iter().filter_map(|e| e.as_str()).collect())
            .unwrap_or_default();
        let (left_out, _) = named_effects(default);
        println!(
            "{bag}: from the paper's model {named:?}, power {power:?}, xi {xi:.3} (truth {truth:.3}), the file keeps {kept:?}; from the default physics {left_out:?}"
        );
        let mut want = vec!["ir_amplitude".to_string(), "transmission_law".to_string()];
        let mut got = named.clone();
        want.sort();
        got.sort();
        assert_eq!(got, want, "{bag}");
        let power = power.expect("the law's power");
        assert!((0.0..=0.1).contains(&power), "{bag}: power {power}");
        assert!((xi - truth).abs() <= 0.02, "{bag}: xi {xi} against {truth}");
        assert!(left_out.is_empty(), "{bag}: the default physics left out {left_out:?}");
        if kept.contains(&"transmission_law") {
            files_with_law.push(dir.path().join("physics.toml"));
        }
    }
    assert!(!files_with_law.is_empty(), "no physics file keeps the law");
    let dir = tempfile::tempdir().expect("temp dir");
    for bag in ["paper_document_holder.mcap", "paper_file_box.mcap"] {
        let (_, _, default) = summary(&replay(dir.path(), bag, &[]));
        for file in &files_with_law {
            let file = file.to_str().expect("utf-8");
            let (_, _, with) = summary(&replay(dir.path(), bag, &["--physics", file]));
            println!("{bag}: {with:.1} mm with {file}, {default:.1} mm with the default physics");
            assert!(
                (with - default).abs() <= 0.1 * default,
                "{bag}: {with} against {default}"
            );
        }
    }
}

/// Issue 36, item 3, on the rendered document holder: its last pose, 250 mm before the white
/// wall, holds light that the layer's back and the wall exchange (a third return the default
/// physics leaves out; docs/audit.md). From the default physics the audit names that effect
/// and nothing else (its renders hold no waveform harmonics and the plain law). Its physics
/// file recovers the setup at or under the paper's 10.6 mm with ξ 0.65 inside the interval,
/// and, with the true ξ, the near-wall pose at most 25 mm (the limits).
#[test]
fn the_audit_names_the_near_wall_on_the_rendered_document_holder_and_its_file_recovers_it() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bag = rendered("paper_document_holder.mcap");
    let a = run(
        dir.path(),
        &["audit", bag.to_str().expect("utf-8"), "--physics-out", "physics.toml"],
    );
    let (named, _) = named_effects(&a);
    println!("document holder, default physics: named {named:?}");
    assert_eq!(named, vec!["wall_interreflection".to_string()]);
    let file = dir.path().join("physics.toml");
    let file = file.to_str().expect("utf-8");
    let (xi, iv, rms) = summary(&replay(dir.path(), "paper_document_holder.mcap", &["--physics", file]));
    let (_, own, _) = summary(&replay(
        dir.path(),
        "paper_document_holder.mcap",
        &["--physics", file, "--xi-model-error-sd", "0"],
    ));
    println!(
        "with the audit's file: xi {xi:.3} [{:.3}, {:.3}] (its evidence's own [{:.3}, {:.3}]), mean per-frame RMS {rms:.1} mm (paper 10.6)",
        iv[0], iv[1], own[0], own[1]
    );
    assert!(iv[0] <= 0.65 && 0.65 <= iv[1], "{iv:?}");
    assert!(own[0] <= 0.65 && 0.65 <= own[1] && own[1] - own[0] <= 0.2, "{own:?}");
    assert!(rms <= 10.6, "{rms} mm");
    let given = replay(
        dir.path(),
        "paper_document_holder.mcap",
        &["--physics", file, "--xi", "0.65"],
    );
    // The near-wall pose: the last two frames (stamps 2.6 s and 2.7 s).
    let near: Vec<f64> = given["per_frame"]
        .as_array()
        .expect("per_frame")
        .iter()
        .filter(|f| f["stamp"].as_f64().is_some_and(|t| t > 2.55))
        .map(|f| num(f, "rmse_mm"))
        .collect();
    println!("near-wall pose with the true xi: {near:?} mm");
    assert_eq!(near.len(), 2, "{near:?}");
    assert!(near.iter().all(|r| *r <= 25.0), "{near:?}");
}

/// Issue 36, item 2, a frosted layer: the rendered calibration of the diffuse transmitter
/// (`calib_difftrans_sheet_diffuse_transmitter`: its material alone at four distances before
/// the calibration wall, one pose tilted) has the audit name diffuse transmission first,
/// from the default physics; the physics file it writes, given to `replay` on the other
/// recording of that material (`difftrans_sheet`: another wall, other poses), recovers it
/// at most 60 mm (the limit; 490 mm as read) with the truth inside ξ's interval.
#[test]
fn the_audit_names_diffuse_transmission_on_a_frosted_calibration_and_its_file_recovers_the_scene() {
    let (named, r) = audit_then_replay("calib_difftrans_sheet_diffuse_transmitter.mcap", "difftrans_sheet.mcap");
    assert_eq!(
        named.first().map(String::as_str),
        Some("diffuse_transmission"),
        "{named:?}"
    );
    let ((_, iv, rms), truth) = (summary(&r), sidecar_xi("difftrans_sheet.mcap"));
    assert!(iv[0] <= truth && truth <= iv[1], "{iv:?} against {truth}");
    assert!(rms <= 60.0, "{rms} mm");
    assert!(num(&r, "coverage") >= 0.9, "{r}");
}

/// The audit of `calibration` (from the default physics, `--physics-out`), then `replay` of
/// `scene` with the physics file it wrote: the effects it named and the replay's report.
fn audit_then_replay(calibration: &str, scene: &str) -> (Vec<String>, Value) {
    let dir = tempfile::tempdir().expect("temp dir");
    let bag = rendered(calibration);
    let a = run(
        dir.path(),
        &["audit", bag.to_str().expect("utf-8"), "--physics-out", "physics.toml"],
    );
    let (named, _) = named_effects(&a);
    let file = dir.path().join("physics.toml");
    let r = replay(dir.path(), scene, &["--physics", file.to_str().expect("utf-8")]);
    let (xi, iv, rms) = summary(&r);
    println!(
        "{calibration}, default physics: named {named:?}; {scene} with its file: xi {xi:.3} [{:.3}, {:.3}] (truth {:.3}), mean per-frame RMS {rms:.1} mm (raw {:.1})",
        iv[0],
        iv[1],
        sidecar_xi(scene),
        num(&r, "mean_frame_rmse_raw_mm")
    );
    (named, r)
}

/// Issue 36, item 4, three returns: a hollow bin of one translucent material (front wall, back
/// wall, the wall behind). The audit of its recording face-on at four distances
/// (`calib_hollow_bin`) names a back wall (`three_returns`) and nothing else, from the default
/// physics; the physics file it writes, given to `replay` on another recording of the bin
/// (`hollow_bin`: another wall, other distances), recovers it at most 40 mm (the issue's
/// limit) with the truth inside ξ's interval.
#[test]
fn the_audit_names_three_returns_on_a_hollow_bin_and_its_file_recovers_another_recording() {
    let (named, r) = audit_then_replay("calib_hollow_bin.mcap", "hollow_bin.mcap");
    assert_eq!(named, vec!["three_returns".to_string()]);
    let ((_, iv, rms), truth) = (summary(&r), sidecar_xi("hollow_bin.mcap"));
    assert!(iv[0] <= truth && truth <= iv[1], "{iv:?} against {truth}");
    assert!(rms <= 40.0, "{rms} mm");
}

/// A camera carried past a tilted sheet and an opaque box before boxes on a wall
/// (`bags/rendered/mf_moving_camera`: 8 frames, phasors at 20, 50 and 100 MHz, no frame of the
/// background alone): `replay --no-latch` (the bag's sidecar asks for it) corrects every frame
/// from two free returns per pixel. Limits from issue 35's for the multi-frequency path: every
/// sheet pixel's mean per-frame RMS at most 20 mm, the box at least 95 % unflagged with its
/// reading kept; ξ is reported as not measured, not guessed.
#[test]
fn a_moving_camera_is_corrected_with_no_latch() {
    let run = shared_run(Run::Moving);
    println!("{}", run.stdout());
    let rows = run.rows();
    let row = &rows[0];
    assert!(row.get("error").is_none(), "{row}");
    let (every, raw) = (num(row, "all_pixels_rms_mm"), num(row, "all_pixels_rms_raw_mm"));
    assert!(
        every <= 20.0 && every < raw,
        "every sheet pixel {every:.1} mm (raw {raw:.1})"
    );
    assert!(num(row, "recovered_share") >= 0.9, "{row}");
    let sheet = &row["materials"][0];
    assert_eq!(sheet["xi_not_measured"], Value::Bool(true), "{sheet}");
    let boxed = &row["opaque"][0];
    assert!(num(boxed, "not_flagged") >= 0.95, "{boxed}");
    assert!(
        num(boxed, "median_error_mm") <= num(boxed, "median_raw_error_mm") + 1.0,
        "{boxed}"
    );
}

/// `scripts/results.py --exe EXE ARGS...` run to its end (its output printed by the caller).
fn results_py(args: &[std::ffi::OsString]) -> std::process::Output {
    let python = python();
    Command::new(&python)
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/results.py"))
        .args(["--exe", exe()])
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("running {python} scripts/results.py: {e} (scripts/setup-python.sh makes .venv)"))
}

/// The `scripts/results.py` runs that several tests share: each runs once per test binary,
/// whichever test asks first, and the README's figures are checked against the same rows
/// ([`the_readmes_figures_are_what_their_commands_print`]), so the check replays nothing.
#[derive(Clone, Copy, Debug)]
enum Run {
    /// Every rendered scene with the defaults, checked against the committed baseline.
    Default,
    /// The same scenes recovered as the node recovers them (`--xi-mode online`).
    Online,
    /// The multi-frequency renders of two scenes.
    MultiFrequency,
    /// The moving camera's render (`--no-latch`, as its sidecar asks).
    Moving,
}

impl Run {
    /// Its name in `scripts/readme_figures.py` (`--rows NAME=FILE`).
    fn name(self) -> &'static str {
        match self {
            Run::Default => "default",
            Run::Online => "online",
            Run::MultiFrequency => "mf",
            Run::Moving => "moving",
        }
    }

    /// `scripts/results.py` arguments (besides `--exe` and `--json`).
    fn args(self) -> Vec<std::ffi::OsString> {
        match self {
            Run::Default => vec!["--check".into(), rendered("baseline.json").into()],
            Run::Online => {
                let mut args: Vec<std::ffi::OsString> =
                    vec!["--replay-arg=--xi-mode".into(), "--replay-arg=online".into()];
                args.extend(single_frequency_scenes().into_iter().map(Into::into));
                args
            }
            Run::MultiFrequency => vec![
                rendered("mf_two_materials.mcap").into(),
                rendered("mf_opaque_and_translucent.mcap").into(),
            ],
            Run::Moving => vec![rendered("mf_moving_camera.mcap").into()],
        }
    }
}

/// A finished `scripts/results.py` run: its output and the rows it wrote (`--json`).
struct SharedRun {
    out: std::process::Output,
    rows: Option<Vec<Value>>,
}

impl SharedRun {
    fn stdout(&self) -> String {
        String::from_utf8_lossy(&self.out.stdout).into_owned()
    }

    fn rows(&self) -> Vec<Value> {
        self.rows.clone().unwrap_or_else(|| {
            panic!(
                "scripts/results.py wrote no rows:\n{}\n{}",
                self.stdout(),
                String::from_utf8_lossy(&self.out.stderr)
            )
        })
    }
}

/// `run`, made once per test binary (a second caller waits for the first).
fn shared_run(run: Run) -> &'static SharedRun {
    static RUNS: [OnceLock<SharedRun>; 4] = [const { OnceLock::new() }; 4];
    RUNS[run as usize].get_or_init(|| {
        let dir = tempfile::tempdir().expect("temp dir");
        let json = dir.path().join("rows.json");
        let mut args: Vec<std::ffi::OsString> = vec!["--json".into(), json.clone().into()];
        args.extend(run.args());
        let out = results_py(&args);
        let rows = std::fs::read_to_string(&json)
            .ok()
            .and_then(|t| serde_json::from_str::<Value>(&t).ok())
            .and_then(|v| v.as_array().cloned());
        SharedRun { out, rows }
    })
}

/// The single-frequency rendered scenes (`scripts/results`' default set): not the
/// multi-frequency bags (their own path, no online ξ), the calibrations or the white wall
/// (inputs of other tests, with nothing to recover).
fn single_frequency_scenes() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/rendered");
    let mut bags: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("bags/rendered")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
        .filter(|p| {
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            !(name.starts_with("mf_") || name.starts_with("calib") || name.starts_with("white_wall"))
        })
        .collect();
    bags.sort();
    bags
}

/// `scripts/results` rows of `bags`, each replayed with `replay_args` too.
fn results_rows_with(bags: &[&str], replay_args: &[&str]) -> Vec<Value> {
    let dir = tempfile::tempdir().expect("temp dir");
    let json = dir.path().join("rows.json");
    let mut args: Vec<std::ffi::OsString> = vec!["--json".into(), json.clone().into()];
    args.extend(replay_args.iter().map(|a| format!("--replay-arg={a}").into()));
    args.extend(bags.iter().map(|b| rendered(b).into()));
    let out = results_py(&args);
    println!("{}", String::from_utf8_lossy(&out.stdout));
    let rows: Value = serde_json::from_str(&std::fs::read_to_string(&json).expect("rows")).expect("json");
    rows.as_array().expect("rows").clone()
}

/// Issue 31, item 3, as a camera is calibrated: `Lin` once from a white wall
/// (`calibrate-lin`), the sheet's material from its own calibration render at that scale
/// (`calibrate-xi --lin-calibration`), then `opaque_and_translucent` (a sheet and a box
/// re-arranged between three poses, each pose a new object) replayed with both. The box
/// stays opaque (at least 90 % unflagged, its median error at most 10 mm: the issue's
/// figures) and the sheet, which the defaults keep as read, comes out better than read
/// over its own pixels. Its error against the 30 mm is printed: not met (README,
/// Known materials).
#[test]
fn a_materials_file_on_the_calibrated_scale_keeps_the_box_and_corrects_the_sheet() {
    let dir = tempfile::tempdir().expect("temp dir");
    let lin = dir.path().join("lin.toml");
    let materials = dir.path().join("materials.toml");
    let (lin, materials) = (lin.to_str().expect("utf-8"), materials.to_str().expect("utf-8"));
    let wall = rendered("white_wall_lin.mcap");
    run(dir.path(), &["calibrate-lin", wall.to_str().expect("utf-8"), "-o", lin]);
    let calibration = rendered("calib_opaque_and_translucent_sheet.mcap");
    let args = [
        "calibrate-xi",
        calibration.to_str().expect("utf-8"),
        "--lin-calibration",
        lin,
        "--name",
        "sheet",
        "-o",
        materials,
    ];
    run(dir.path(), &args);
    let rows = results_rows_with(
        &["opaque_and_translucent.mcap"],
        &["--materials", materials, "--lin-calibration", lin],
    );
    let row = rows.first().expect("one row");
    assert!(row.get("error").is_none(), "{row}");
    let sheet = &row["materials"][0];
    let (rms, raw) = (num(sheet, "rms_mm"), num(sheet, "rms_raw_mm"));
    println!("the sheet over its own pixels: {raw:.1} mm read, {rms:.1} mm published (the issue's limit 30 mm)");
    assert!(rms < raw, "{sheet}");
    let boxes = row["opaque"].as_array().expect("the box is scored");
    assert!(!boxes.is_empty(), "{row}");
    for o in boxes {
        assert!(num(o, "not_flagged") >= 0.9, "{o}");
        assert!(num(o, "median_error_mm") <= 10.0, "{o}");
    }
}

/// The multi-frequency renders (`mf_two_materials`, `mf_opaque_and_translucent`: the
/// scenes of those names with phasors at 20, 50 and 100 MHz) against issue 35's claims that
/// they meet: the recovered pixels of `two_materials` at most 20 mm; every translucent object
/// better than read over its own pixels; the opaque box at least 95 % unflagged with its
/// reading kept; the regions' intervals holding ξ in at least 90 % of the frame-objects (stated
/// 95 %); σ holding the error for 90-98 % of the recovered pixels. Every pixel of
/// `two_materials` at 20 mm, the other target, is printed, not asserted: it is not met
/// (README, Multi-frequency cameras).
#[test]
fn the_multi_frequency_renders_hold_their_claims() {
    let run = shared_run(Run::MultiFrequency);
    println!("{}", run.stdout());
    let rows = run.rows();
    let (mut inside, mut frame_objects) = (0.0, 0.0);
    for row in &rows {
        let bag = row["bag"].as_str().unwrap_or("?");
        assert!(row.get("error").is_none(), "{row}");
        assert_eq!(row["path"], "multi_frequency", "{bag}");
        println!(
            "{bag}: recovered {:.1} mm, every pixel {:.1} mm (raw {:.1})",
            num(row, "mean_frame_rms_mm"),
            num(row, "all_pixels_rms_mm"),
            num(row, "all_pixels_rms_raw_mm")
        );
        for m in row["materials"].as_array().expect("materials") {
            let (rms, raw) = (num(m, "rms_mm"), num(m, "rms_raw_mm"));
            assert!(
                rms < raw,
                "{bag}: material {} {rms:.1} mm against {raw:.1} read",
                m["id"]
            );
            let f = m["frames_inside"].as_array().expect("frames_inside");
            inside += f[0].as_f64().unwrap_or(0.0);
            frame_objects += f[1].as_f64().unwrap_or(0.0);
        }
        for o in row["opaque"].as_array().into_iter().flatten() {
            assert!(num(o, "not_flagged") >= 0.95, "{bag}: {o}");
            assert!(
                num(o, "median_error_mm") <= num(o, "median_raw_error_mm") + 1.0,
                "{bag}: {o}"
            );
        }
    }
    let (within, with_sigma) = rows.iter().fold((0.0, 0.0), |(a, b), r| {
        let w = &r["within_2sigma"];
        (a + w[0].as_f64().unwrap_or(0.0), b + w[1].as_f64().unwrap_or(0.0))
    });
    let sigma = within / with_sigma.max(1.0);
    println!(
        "sigma holds the error for {:.1} % of {with_sigma} recovered pixels",
        100.0 * sigma
    );
    assert!((0.90..=0.98).contains(&sigma), "{sigma}");
    let two = rows
        .iter()
        .find(|r| r["bag"] == "mf_two_materials.mcap")
        .expect("two_materials row");
    assert!(num(two, "mean_frame_rms_mm") <= 20.0, "{two}");
    assert!(
        rows.iter()
            .any(|r| r["bag"] == "mf_opaque_and_translucent.mcap"
                && r["opaque"].as_array().is_some_and(|o| !o.is_empty())),
        "the opaque box is scored"
    );
    assert!(
        frame_objects >= 20.0 && inside >= 0.9 * frame_objects,
        "{inside} of {frame_objects}"
    );
}

/// The rendered single-frequency scenes recovered as the node recovers them (`--xi-mode
/// online`: each frame with the evidence up to it) fall short of no claim of a scene or an
/// object: none worse than raw over every pixel or over its own, no opaque object flagged or
/// moved, the paper's setups at or under the paper's figures. A shortfall the committed
/// baseline lists as known, with its reason (`known_failures`; docs/results.md, Reading the
/// table), is printed, not failed: the default run holds it there. The set's coverage and σ
/// are held by [`the_rendered_set_holds_its_baseline`] over every scene.
#[test]
fn the_rendered_scenes_recovered_online_as_the_node_does_fall_short_of_no_claim() {
    let bags = single_frequency_scenes();
    assert!(bags.len() >= 25, "{bags:?}");
    let out = &shared_run(Run::Online).out;
    let stdout = String::from_utf8_lossy(&out.stdout);
    println!("{stdout}");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let known = known_failures();
    let (known_short, short): (Vec<&str>, Vec<&str>) = stdout
        .lines()
        .filter(|l| l.starts_with("falls short:") && !l.starts_with("falls short: set:"))
        .partition(|l| {
            let key = l.trim_start_matches("falls short: ").split(": ").next().unwrap_or("");
            known.iter().any(|k| k == key)
        });
    println!("known in the baseline: {known_short:?}");
    assert!(short.is_empty(), "recovered online:\n{}", short.join("\n"));
}

/// The keys of the committed baseline's known failures (`bags/rendered/baseline.json`).
fn known_failures() -> Vec<String> {
    let text = std::fs::read_to_string(rendered("baseline.json")).expect("baseline");
    let v: Value = serde_json::from_str(&text).expect("baseline json");
    v["known_failures"]
        .as_object()
        .map(|o| o.keys().cloned().collect())
        .unwrap_or_default()
}

/// The whole rendered set against its committed baseline (`bags/rendered/baseline.json`,
/// written by `scripts/results --write-baseline`): fails on a scene worse than raw, an opaque
/// object flagged or moved, a paper setup above the paper's figure, interval coverage or σ
/// below their stated levels, or a scene or object worse than the baseline beyond noise,
/// unless the baseline lists that failure as known. The README's tables come from the same
/// script (`scripts/results --markdown`).
#[test]
fn the_rendered_set_holds_its_baseline() {
    let out = &shared_run(Run::Default).out;
    let stdout = String::from_utf8_lossy(&out.stdout);
    println!("{stdout}");
    assert!(
        out.status.success(),
        "the rendered set fell below its baseline:\n{}\n{}",
        stdout
            .lines()
            .filter(|l| l.starts_with("FAILED") || l.starts_with("check:"))
            .collect::<Vec<_>>()
            .join("\n"),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The README's generated figures (every `<!--f:KEY-->...<!--/f-->`: the results table and
/// the set's lines, the figures of Replay, Modes and Limits) are what their commands print on
/// the committed bags. `scripts/readme_figures.py` formats them from the rows of the runs the
/// tests above make (`--rows`), so this replays nothing; the demo's lines are compared by
/// `tests/node_dds.rs`, which runs the demo. `scripts/readme-figures --write` rewrites them.
#[test]
fn the_readmes_figures_are_what_their_commands_print() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut args: Vec<std::ffi::OsString> = vec![
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scripts/readme_figures.py")
            .into(),
        "--skip".into(),
        "demo".into(),
    ];
    for run in [Run::Default, Run::Online, Run::MultiFrequency, Run::Moving] {
        let file = dir.path().join(format!("{}.json", run.name()));
        let rows = Value::Array(shared_run(run).rows());
        std::fs::write(&file, rows.to_string()).expect("write rows");
        args.push("--rows".into());
        args.push(format!("{}={}", run.name(), file.display()).into());
    }
    let python = python();
    let out = Command::new(&python)
        .args(&args)
        .output()
        .unwrap_or_else(|e| panic!("running {python} scripts/readme_figures.py: {e}"));
    let stdout = String::from_utf8_lossy(&out.stdout);
    println!("{stdout}");
    assert!(
        out.status.success(),
        "the README's figures differ from their commands' (scripts/readme-figures --write rewrites them):\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
