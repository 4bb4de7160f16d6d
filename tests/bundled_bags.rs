//! The bundled bags are what the simulator makes of their scene files: each
//! `bags/NAME.toml` rendered again gives `bags/NAME.mcap` message for message,
//! the physics it was made with recorded in it. The physically rendered bags
//! name their physics too, and the shipped physics files name their preset.

use std::path::Path;
use std::process::Command;

use translucent_tof::bag::{BagReader, PHYSICS_RECORD, PHYSICS_RECORD_KEY};

#[test]
fn every_bundled_bag_is_remade_by_the_simulator() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags");
    let tmp = tempfile::tempdir().unwrap();
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let scene = entry.unwrap().path();
        if scene.extension().and_then(|e| e.to_str()) != Some("toml") {
            continue;
        }
        let bundled = scene.with_extension("mcap");
        assert!(
            bundled.exists(),
            "{} has no bag beside it (bags/make.sh)",
            scene.display()
        );
        let fresh = tmp.path().join(bundled.file_name().unwrap());
        let out = Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
            .args(["simulate", scene.to_str().unwrap(), "-o", fresh.to_str().unwrap()])
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let (a, b) = (BagReader::open(&bundled).unwrap(), BagReader::open(&fresh).unwrap());
        // The physics it was made with, as the simulator records it now.
        let physics = |r: &BagReader| {
            r.metadata()
                .iter()
                .find(|m| m.name == PHYSICS_RECORD)
                .and_then(|m| m.entries.get(PHYSICS_RECORD_KEY).cloned())
        };
        let recorded = physics(&b).unwrap_or_else(|| panic!("simulate wrote no {PHYSICS_RECORD} record"));
        assert!(recorded.contains("preset = "), "{recorded}");
        assert_eq!(
            physics(&a).as_deref(),
            Some(recorded.as_str()),
            "{}: the bundled bag does not record the physics its scene renders with: remake with bags/make.sh",
            scene.display()
        );
        let (ta, tb) = (a.topics(), b.topics());
        assert_eq!(
            ta.iter()
                .map(|t| (&t.name, &t.type_name, t.message_count))
                .collect::<Vec<_>>(),
            tb.iter()
                .map(|t| (&t.name, &t.type_name, t.message_count))
                .collect::<Vec<_>>(),
            "{}",
            scene.display()
        );
        for (ma, mb) in a.messages().zip(b.messages()) {
            let (ma, mb) = (ma.unwrap(), mb.unwrap());
            assert_eq!((ma.topic, ma.log_time_ns), (mb.topic, mb.log_time_ns));
            assert!(
                ma.data == mb.data,
                "{}: {} at {} differs: remake with bags/make.sh",
                scene.display(),
                ma.topic,
                ma.log_time_ns
            );
        }
        checked += 1;
    }
    assert!(checked >= 6, "found {checked} scenes");
}

/// Each physically rendered bag says which physics to replay it with: its own
/// record, or (bags rendered before the record) its sidecar's `physics`; and
/// the tools take it from there when no `--physics` is given.
#[test]
fn every_rendered_bag_names_its_physics() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/rendered");
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let bag = entry.unwrap().path();
        if bag.extension().and_then(|e| e.to_str()) != Some("mcap") {
            continue;
        }
        let recorded = BagReader::open(&bag)
            .unwrap()
            .metadata()
            .iter()
            .any(|m| m.name == PHYSICS_RECORD);
        let sidecar: toml::Table = std::fs::read_to_string(bag.with_extension("toml"))
            .unwrap()
            .parse()
            .unwrap();
        let named = sidecar.get("physics").and_then(|v| v.as_str());
        assert!(
            recorded || named == Some("physical"),
            "{}: neither a {PHYSICS_RECORD} record nor physics = \"physical\" in its sidecar",
            bag.display()
        );
        checked += 1;
    }
    assert!(checked >= 20, "found {checked} rendered bags");

    // As a user runs it: calibrate-xi on the rendered calibration sequence says where its physics came from.
    let bag = dir.join("calibration_sequence.mcap");
    let out = Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
        .args(["calibrate-xi", bag.to_str().unwrap()])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        stdout.contains("physics: physical, the recording's own, named by the sidecar")
            && stdout.contains("calibration_sequence.toml"),
        "{stdout}"
    );
}

/// A shipped physics file names its preset and every option: what it says does
/// not hang on a preset's defaults.
#[test]
fn shipped_physics_files_are_complete() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/physics");
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let file: toml::Table = std::fs::read_to_string(&path).unwrap().parse().unwrap();
        for key in [
            "preset",
            "bounces",
            "ir_mode",
            "transmission_albedo_power",
            "ambient_offset",
            "subsurface_delay_mm",
            "refraction_shift_px",
            "wall_interreflection",
            "diffuse_transmission",
            "hollow_depth_mm",
        ] {
            assert!(file.contains_key(key), "{}: no {key}", path.display());
        }
        checked += 1;
    }
    assert!(checked >= 1);
}
