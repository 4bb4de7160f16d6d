//! The bundled bags are what the simulator makes of their scene files: each
//! `bags/NAME.toml` rendered again gives `bags/NAME.mcap` message for message.

use std::path::Path;
use std::process::Command;

use translucent_tof::bag::BagReader;

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
