//! The node against an independent DDS implementation: Eclipse Cyclone DDS
//! (Python `cyclonedds`, installed by scripts/setup-python.sh) as a ROS 2
//! peer over rmw_cyclonedds's service mapping, in a private network namespace.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::netns::isolated;
use common::published_width;

fn python() -> String {
    std::env::var("TTOF_PYTHON").unwrap_or_else(|_| format!("{}/.venv/bin/python", env!("CARGO_MANIFEST_DIR")))
}

#[test]
fn cyclone_peer_latches_and_receives_points_and_xi() {
    if !isolated("cyclone_peer_latches_and_receives_points_and_xi") {
        return;
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let py = python();
    let check = Command::new(&py).args(["-c", "import cyclonedds, mcap_ros2"]).output();
    assert!(
        check.as_ref().is_ok_and(|o| o.status.success()),
        "{py} lacks cyclonedds / mcap-ros2-support: run bash scripts/setup-python.sh (scripts/test does)"
    );
    let dir = tempfile::tempdir().unwrap();
    let stats = dir.path().join("stats.json");
    let mut node = Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
        .arg("node")
        .arg("--stats-json")
        .arg(&stats)
        .args([
            "--ros-args",
            "-r",
            "__ns:=/tof",
            "-p",
            "service_mapping:=cyclone",
            "-p",
            "background_frames:=4",
            // The bag is the simulator's, which speaks the paper's model.
            "-p",
            "physics:=paper",
        ])
        .stdin(Stdio::null())
        .spawn()
        .unwrap();
    let out = Command::new(&py)
        .arg(root.join("tests/py/cyclone_peer.py"))
        .arg(root.join("bags/document_holder.mcap"))
        .args(["/tof", "/tof/translucent_tof", "10"])
        .output()
        .unwrap();
    Command::new("kill")
        .args(["-INT", &node.id().to_string()])
        .status()
        .unwrap();
    let t0 = Instant::now();
    while node.try_wait().unwrap().is_none() {
        if t0.elapsed() > Duration::from_secs(20) {
            let _ = node.kill();
            panic!("node did not stop");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "cyclone peer failed: {stderr}");
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).expect("peer prints JSON");
    eprintln!("{}", serde_json::to_string_pretty(&r).unwrap());
    assert_eq!(r["latch_success"], true, "{r}");
    assert!(r["latch_message"].as_str().unwrap().contains("latched 4 frames"));
    let sent = r["object_frames_sent"].as_u64().unwrap();
    assert!(r["clouds_for_sent_stamps"].as_u64().unwrap() * 10 >= sent * 8, "{r}");
    let c = &r["cloud"];
    assert_eq!(
        (c["width"].as_u64(), c["height"].as_u64(), c["point_step"].as_u64()),
        (Some(176), Some(144), Some(24))
    );
    assert_eq!(
        c["fields"],
        serde_json::json!([
            ["x", 0, 7, 1],
            ["y", 4, 7, 1],
            ["z", 8, 7, 1],
            ["intensity", 12, 7, 1],
            ["translucent", 16, 2, 1],
            ["sigma", 20, 7, 1]
        ])
    );
    assert!(c["translucent_points"].as_u64().unwrap() > 100);
    let e = &r["estimate"];
    assert_eq!(e["method"], "one_material");
    // Against the truth the scene was simulated with (bags/document_holder.toml: xi 0.65),
    // for the object seen in most frames: several poses of one sheet determine xi.
    let (lo, hi) = (e["xi_lower"].as_f64().unwrap(), e["xi_upper"].as_f64().unwrap());
    assert!(e["frames_pooled"].as_u64().unwrap() >= 4, "{e}");
    assert!(
        lo <= 0.65 && 0.65 <= hi && hi - lo <= published_width(0.1),
        "[{lo}, {hi}] misses the true xi 0.65: {e}"
    );
    assert!(e["translucent_pixels"].as_u64().unwrap() > 100);
    // The fields appended for the materials file decode too: without one, no class.
    assert_eq!(e["material"], "", "{e}");
    assert!(e["class_probability"].is_null(), "{e}");
    let st: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
    assert_eq!(st["services"][0], 1);
}
