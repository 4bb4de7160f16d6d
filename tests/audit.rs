//! The physics audit (issue 6): on recordings with one concealed effect the
//! audit names it, on a clean control it claims nothing, and the physics file
//! it writes makes `replay` recover better. Also effects drawn at strengths
//! and scene settings other than the bundled ones (seeded draws).
//!
//! `cargo test --release --test audit -- --nocapture` prints the figures.

mod common;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use translucent_tof::audit::gather;
use translucent_tof::physics::audit::{run_audit, AuditSettings, Effect};
use translucent_tof::physics::{ForwardModel, IrMode};
use translucent_tof::pipeline::PipelineConfig;
use translucent_tof::sim::render::scene_sensor;
use translucent_tof::sim::scene::{BackgroundSpec, StageSpec};

fn bag(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("bags").join(name)
}

fn audit(bag: &Path, dir: &Path, extra: &[&str]) -> Value {
    let json = dir.join("audit.json");
    let mut args = vec![
        "audit".to_string(),
        bag.display().to_string(),
        "--json".into(),
        json.display().to_string(),
        // The concealed effects are effects past the paper's model, which the simulator speaks.
        "--physics".into(),
        "paper".into(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let out = Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
        .args(&args)
        .output()
        .expect("running translucent_tof");
    assert!(
        out.status.success(),
        "audit {} failed: {}",
        bag.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(&std::fs::read_to_string(&json).expect("the audit's JSON")).expect("JSON")
}

fn effects(v: &Value) -> BTreeSet<String> {
    v["final"]["effects"]
        .as_array()
        .expect("final.effects")
        .iter()
        .map(|e| e.as_str().expect("a name").to_string())
        .collect()
}

/// The bundled bags and what each conceals (the scene files are the recipe).
const BUNDLED: [(&str, &[&str]); 9] = [
    ("audit_a", &["transmission_law"]),
    ("audit_b", &["higher_order_bounces"]),
    ("audit_c", &["waveform_harmonics"]),
    ("audit_d", &["ir_amplitude"]),
    ("audit_e", &["ambient_offset"]),
    ("audit_f", &["subsurface_delay"]),
    ("audit_g", &["refraction_shift"]),
    ("audit_h", &["ambient_offset", "subsurface_delay"]),
    ("audit_control", &[]),
];

/// Every bundled audit bag: the concealed effects named, nothing on the control,
/// the keys interfaces.md fixes present, and the held-out error no worse after.
#[test]
fn bundled_audit_bags_name_their_concealed_effects() {
    let started = std::time::Instant::now();
    let physics_dir = tempfile::tempdir().expect("temp dir");
    let physics_dir = &physics_dir;
    let results: Vec<(String, Value)> = std::thread::scope(|s| {
        let chunks: Vec<Vec<(&str, &[&str])>> = vec![
            BUNDLED.iter().step_by(2).copied().collect(),
            BUNDLED.iter().skip(1).step_by(2).copied().collect(),
        ];
        let handles: Vec<_> = chunks
            .into_iter()
            .map(|chunk| {
                s.spawn(move || {
                    chunk
                        .iter()
                        .map(|(name, _)| {
                            let dir = tempfile::tempdir().expect("temp dir");
                            let v = if *name == "audit_b" {
                                // This one also writes its physics file and plots, for the replay check below.
                                let out = physics_dir.path();
                                audit(
                                    &bag("audit_b.mcap"),
                                    dir.path(),
                                    &[
                                        "--physics-out",
                                        out.join("physics.toml").to_str().expect("utf-8"),
                                        "--plots",
                                        out.join("plots").to_str().expect("utf-8"),
                                    ],
                                )
                            } else {
                                audit(&bag(&format!("{name}.mcap")), dir.path(), &[])
                            };
                            (name.to_string(), v)
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().expect("audit thread"))
            .collect()
    });
    let mut failures = vec![];
    for (name, want) in BUNDLED {
        let v = &results.iter().find(|(n, _)| n == name).expect("ran").1;
        let got = effects(v);
        let want: BTreeSet<String> = want.iter().map(|s| s.to_string()).collect();
        let (b, f) = (&v["baseline"], &v["final"]);
        println!(
            "{name}: named {:?}; held-out {:.1} -> {:.1} mm (score {:.3} -> {:.3}); xi {:.3} -> {:.3}; recovery {:.1} -> {:.1} mm",
            got,
            b["heldout_rmse_mm"].as_f64().unwrap_or(f64::NAN),
            f["heldout_rmse_mm"].as_f64().unwrap_or(f64::NAN),
            b["heldout_score"].as_f64().unwrap_or(f64::NAN),
            f["heldout_score"].as_f64().unwrap_or(f64::NAN),
            b["params"]["xi"].as_f64().unwrap_or(f64::NAN),
            f["params"]["xi"].as_f64().unwrap_or(f64::NAN),
            v["recovery_rmse_mm"]["before"].as_f64().unwrap_or(f64::NAN),
            v["recovery_rmse_mm"]["after"].as_f64().unwrap_or(f64::NAN),
        );
        for key in ["rmse_mm", "heldout_rmse_mm"] {
            assert!(b[key].is_number(), "{name}: baseline.{key}");
        }
        assert!(b["params"].is_object(), "{name}: baseline.params");
        assert!(f["heldout_rmse_mm"].is_number(), "{name}: final.heldout_rmse_mm");
        let findings = v["findings"].as_array().expect("findings");
        assert_eq!(findings.len(), got.len(), "{name}: one finding per effect");
        for fi in findings {
            for key in ["effect", "evidence", "where"] {
                assert!(fi[key].is_string(), "{name}: findings[].{key}");
            }
            assert!(fi["heldout_rmse_mm"].is_number() && fi["params"].is_object(), "{name}");
        }
        assert_eq!(
            v["candidates"].as_array().map(|c| c.len() >= 6),
            Some(true),
            "{name}: every candidate scored"
        );
        if got != want {
            failures.push(format!("{name}: named {got:?}, conceals {want:?}"));
        }
    }
    println!("bundled audits took {:.0} s", started.elapsed().as_secs_f64());
    assert!(failures.is_empty(), "{failures:#?}");
    let b = &results.iter().find(|(n, _)| n == "audit_b").expect("ran").1;
    replay_with_the_audit_physics(b, physics_dir.path());
}

/// The physics file the audit wrote for `audit_b` is one `replay --physics`
/// takes, and with it (and the ξ the audit fitted) recovery on the same
/// recording improves; the plots are there, one SVG per quantity.
fn replay_with_the_audit_physics(v: &Value, dir: &Path) {
    let physics = dir.join("physics.toml");
    let svgs = std::fs::read_dir(dir.join("plots")).expect("plots").count();
    assert!(svgs >= 8, "one SVG per quantity, got {svgs}");
    let b = bag("audit_b.mcap");

    let replay = |args: &[&str]| -> f64 {
        let (json, out) = (dir.join("replay.json"), dir.join("replay.mcap"));
        // (`--out` in the test's directory: the default is the working directory, the crate's.)
        let mut a = vec![
            "replay",
            b.to_str().expect("utf-8"),
            "--json",
            json.to_str().expect("utf-8"),
            "--out",
            out.to_str().expect("utf-8"),
        ];
        a.extend_from_slice(args);
        let out = Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
            .args(&a)
            .output()
            .expect("replay");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let r: Value = serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("json");
        r["rmse_mm"].as_f64().expect("rmse_mm")
    };
    let xi0 = format!("{:.3}", v["baseline"]["params"]["xi"].as_f64().expect("xi"));
    let xi1 = format!("{:.3}", v["final"]["params"]["xi"].as_f64().expect("xi"));
    let before = replay(&["--xi", &xi0, "--physics", "paper"]);
    let after = replay(&["--xi", &xi1, "--physics", physics.to_str().expect("utf-8")]);
    println!("audit_b replay: paper's model at xi {xi0}: {before:.1} mm; with the audit's physics file at xi {xi1}: {after:.1} mm");
    assert!(after < 0.7 * before, "{before} -> {after}");
}

// ---------------------------------------------------------------- seeded draws

/// A calibration sequence drawn from realistic ranges: wall distance and tilt,
/// modulation frequency, ξ, albedo, the layer's tilt and its distances.
fn drawn_scene(seed: u64, effect: Option<Effect>) -> translucent_tof::sim::Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let wall = rng.random_range(2600.0..3400.0);
    let xi = rng.random_range(0.55..0.85);
    let albedo = rng.random_range(0.35..0.8);
    let tilt = [rng.random_range(-8.0..8.0), rng.random_range(-8.0..8.0)];
    let near = rng.random_range(600.0..900.0);
    let frames = 12;
    let step = (wall - 250.0 - near) / (frames - 1) as f64;
    let stages = (0..frames)
        .map(|k| StageSpec {
            frames: 1,
            objects: vec![common::plane(
                [0.0, 0.0, near + step * k as f64],
                [700.0, 560.0],
                tilt,
                xi,
                albedo,
            )],
        })
        .collect();
    let mut scene = common::scene_with(format!("audit draw {seed}"), seed, wall, stages);
    scene.camera.width = 88;
    scene.camera.height = 72;
    scene.camera.modulation_frequency_hz = rng.random_range(20.0e6..32.0e6);
    scene.background = BackgroundSpec {
        frames: 8,
        ..scene.background
    };
    let p = &mut scene.physics;
    match effect {
        None => {}
        Some(Effect::HigherOrderBounces) => p.bounces = rng.random_range(3..=5),
        Some(Effect::WaveformHarmonics) => {
            scene.camera.waveform = "harmonics".into();
            let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            scene.camera.harmonics = [sign * rng.random_range(0.07..0.15), rng.random_range(0.0..0.04)];
        }
        Some(Effect::IrAmplitude) => p.ir_mode = IrMode::Amplitude,
        Some(Effect::AmbientOffset) => p.ambient_offset = rng.random_range(80.0..200.0),
        Some(Effect::SubsurfaceDelay) => p.subsurface_delay_mm = rng.random_range(12.0..35.0),
        Some(Effect::TransmissionLaw) => p.transmission_albedo_power = rng.random_range(0.0..1.0),
        Some(Effect::RefractionShift) => {
            // A displaced background shows only where the background changes along the
            // displacement: the wall is tilted about the axis across it.
            let tilt = rng.random_range(20.0..35.0);
            let s = rng.random_range(2.0..4.0);
            if rng.random_bool(0.5) {
                scene.background.tilt_y_deg = tilt;
                p.refraction_shift_px = [s, 0.0];
            } else {
                scene.background.tilt_x_deg = tilt;
                p.refraction_shift_px = [0.0, -s];
            }
        }
    }
    scene
}

/// Renders a drawn scene and audits it in memory; returns the effects named.
fn audit_draw(seed: u64, effect: Option<Effect>) -> (Vec<Effect>, String) {
    let scene = drawn_scene(seed, effect);
    let sensor = scene_sensor(&scene);
    // The audit's baseline: the device's own (sinusoidal) decoder, the paper's physics.
    let base = ForwardModel::paper(translucent_tof::physics::Sensor::new(
        sensor.modulation_frequency_hz,
        translucent_tof::physics::Waveform::Sinusoid,
    ));
    let config = PipelineConfig {
        model: base.clone(),
        ..PipelineConfig::default()
    };
    let (pipe, frames) = common::latched(&scene, config);
    let objects: Vec<_> = frames
        .iter()
        .filter(|f| !f.background_only)
        .map(|f| (common::df(f), f.truth_z_mm.clone()))
        .collect();
    let refs: Vec<_> = objects.iter().map(|(f, t)| (f, t)).collect();
    let (data, _) = gather(&pipe, &refs, 900).expect("gather");
    let r = run_audit(&data, &base, &AuditSettings::default()).expect("audit");
    let fin = r.final_fit();
    let text = format!(
        "seed {seed} {:?} (physics {:?}, camera {} {:?}): named {:?} xi {:.3} -> {:.3}, held-out {:.1} -> {:.1} mm, params {:?}",
        effect,
        scene.physics,
        scene.camera.waveform,
        scene.camera.harmonics,
        fin.effects,
        r.baseline.xi,
        fin.xi,
        r.baseline.heldout_rmse_mm,
        fin.heldout_rmse_mm,
        fin.params
    );
    let scores: Vec<String> = r
        .candidates
        .iter()
        .map(|c| {
            format!(
                "r{} {} gain {:.0}/{:.0} z {:.1}{}",
                c.round,
                c.effect.name(),
                c.gain,
                c.threshold,
                c.z,
                if c.accepted { " ACCEPTED" } else { "" }
            )
        })
        .collect();
    (
        fin.effects.clone(),
        format!("{text}\n    candidates: {}", scores.join("; ")),
    )
}

/// A draw: its seed and the effect it conceals.
type Job = (u64, Option<Effect>);
/// What the audit named, and the draw in words.
type Named = (Vec<Effect>, String);

fn draws(per_effect: usize, controls: usize, first_seed: u64, min_hit_rate: f64) {
    let started = std::time::Instant::now();
    let mut jobs: Vec<Job> = vec![];
    let mut seed = first_seed;
    for e in Effect::ALL {
        for _ in 0..per_effect {
            jobs.push((seed, Some(e)));
            seed += 1;
        }
    }
    for _ in 0..controls {
        jobs.push((seed, None));
        seed += 1;
    }
    let results: Vec<(Job, Named)> = std::thread::scope(|s| {
        let halves = [
            jobs.iter().step_by(2).collect::<Vec<_>>(),
            jobs.iter().skip(1).step_by(2).collect(),
        ];
        let hs: Vec<_> = halves
            .into_iter()
            .map(|h| {
                s.spawn(move || {
                    h.into_iter()
                        .map(|&(sd, e)| ((sd, e), audit_draw(sd, e)))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        hs.into_iter().flat_map(|h| h.join().expect("draw thread")).collect()
    });
    let (mut misses, mut wrong, mut hits_all, mut concealed) = (vec![], vec![], 0, 0);
    for e in Effect::ALL.iter().map(|e| Some(*e)).chain([None]) {
        let mine: Vec<_> = results.iter().filter(|((_, x), _)| *x == e).collect();
        let hits = mine
            .iter()
            .filter(|(_, (named, _))| named == &e.into_iter().collect::<Vec<_>>())
            .count();
        println!(
            "{}: {hits}/{} named right",
            e.map(|e| e.name()).unwrap_or("control"),
            mine.len()
        );
        for (_, (named, text)) in &mine {
            println!("  {text}");
            let want: Vec<Effect> = e.into_iter().collect();
            if named.iter().any(|n| !want.contains(n)) {
                wrong.push(text.clone());
            } else if named != &want {
                misses.push(text.clone());
            }
        }
        if e.is_some() {
            hits_all += hits;
            concealed += mine.len();
        }
    }
    println!(
        "{} draws took {:.0} s: {hits_all}/{concealed} concealed effects named right, {} draw(s) with a wrong name, {} missed",
        results.len(),
        started.elapsed().as_secs_f64(),
        wrong.len(),
        misses.len()
    );
    // Nothing the data do not hold is ever claimed (controls included); an effect too weak
    // to show in a draw may go unnamed, but most must be named.
    assert!(
        wrong.is_empty(),
        "effects named that the scene does not hold: {wrong:#?}"
    );
    assert!(
        hits_all as f64 >= min_hit_rate * concealed as f64,
        "{hits_all}/{concealed} named; missed: {misses:#?}"
    );
}

/// One seeded draw per effect and two clean controls: no wrong name, and at
/// least six of the seven concealed effects named.
#[test]
fn seeded_draws_are_named_right() {
    draws(1, 2, 6000, 6.0 / 7.0);
}

/// More draws (three per effect, four controls): the hit rates.
/// `cargo test --release --test audit -- --ignored --nocapture`
#[test]
#[ignore]
fn seeded_draws_hit_rates() {
    draws(3, 4, 7000, 0.8);
}
