//! The soak's CI version (issue 54): `scripts/soak` for a short time on both
//! paths, asserting the conditions the one-hour run is held to (memory flat,
//! p99 latency within 2x the median in every window, the output rate within
//! 5 % across windows, every fault counted and outputs back within 1 s, no
//! crash; scripts/soak.py). The single-frequency path at 640x480; the
//! multi-frequency path at 176x144, where it sustains a few frames a second
//! (at 640x480 it takes seconds a frame: too few outputs in CI's minutes to
//! fill the windows; docs/performance.md), without the moved camera, which
//! the node does not watch for on that path (docs/interfaces.md). Then the
//! same records checked again with limits they cannot meet, which must fail.
//!
//! Needs the release node (`TTOF_RELEASE_EXE`, set by `scripts/test`) and the
//! venv's rclpy; without either it says SKIPPED. 110 s a path (the first
//! 35 s a warm-up: resident memory is still settling before), about 4 minutes.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::netns::{isolated, skipped};
use serde_json::Value;

const TEST: &str = "the_node_stays_flat_under_load_and_faults_on_both_paths";

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn python() -> String {
    std::env::var("TTOF_PYTHON").unwrap_or_else(|_| format!("{}/.venv/bin/python", env!("CARGO_MANIFEST_DIR")))
}

/// `scripts/soak ARGS --json OUT/report.json`: its exit status, standard error and report.
fn soak(exe: &Path, out: &Path, args: &[&str]) -> (bool, String, Value) {
    let report = out.join("report.json");
    let o = Command::new(root().join("scripts/soak"))
        .arg("--node")
        .arg(exe)
        .arg("--out")
        .arg(out)
        .arg("--json")
        .arg(&report)
        .args(args)
        .env("TTOF_PYTHON", python())
        .output()
        .expect("running scripts/soak");
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    let r: Value = std::fs::read(&report)
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_else(|| panic!("scripts/soak wrote no report: {stderr}"));
    (o.status.success(), stderr, r)
}

/// One line per path: what the run measured.
fn summary(r: &Value) -> String {
    let mut lines = Vec::new();
    for p in r["paths"].as_array().into_iter().flatten() {
        lines.push(format!(
            "{} {}: {} outputs ({} /s), RSS {:.1} -> {:.1} MB, latency median {} ms p99 {} ms, faults {}, not injected {}",
            p["path"].as_str().unwrap_or("?"),
            p["size"].as_str().unwrap_or("?"),
            p["outputs"],
            p["output_rate_hz"],
            p["rss_kb_after_warmup"].as_f64().unwrap_or(f64::NAN) / 1024.0,
            p["rss_kb_at_end"].as_f64().unwrap_or(f64::NAN) / 1024.0,
            p["latency_ms_median"],
            p["latency_ms_p99"],
            p["faults"].as_array().map_or(0, Vec::len),
            p["faults_not_injected"],
        ));
    }
    lines.join("\n")
}

#[test]
#[ignore = "issue 54: the node does not meet the conditions yet (100 s a path on this 2-core machine: RSS +15.8 %, p99 2.29x the median on the single-frequency path; docs/performance.md, The soak); run with --ignored"]
fn the_node_stays_flat_under_load_and_faults_on_both_paths() {
    if !isolated(TEST) {
        return;
    }
    let Some(exe) = std::env::var_os("TTOF_RELEASE_EXE").map(PathBuf::from) else {
        skipped(
            TEST,
            false,
            "TTOF_RELEASE_EXE is not set: the soak measures the release node (scripts/test sets it)",
        );
        return;
    };
    assert!(exe.is_file(), "TTOF_RELEASE_EXE={} is not a file", exe.display());
    let py = python();
    let has_rclpy = Command::new(&py)
        .args([
            "-c",
            "import rclpy, sensor_msgs, std_srvs, diagnostic_msgs, mcap_ros2, numpy",
        ])
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_rclpy {
        skipped(
            TEST,
            false,
            &format!("{py} lacks rclpy or the ROS message packages (bash scripts/setup-python.sh)"),
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let runs: [(&str, &[&str]); 2] = [
        (
            "sf",
            &["--paths", "single_frequency", "--duration", "110s", "--warmup", "35s"],
        ),
        (
            "mf",
            &[
                "--paths",
                "multi_frequency",
                "--size",
                "176x144",
                "--duration",
                "110s",
                "--warmup",
                "35s",
                "--skip",
                "camera_moved",
            ],
        ),
    ];
    let mut failed = Vec::new();
    for (name, args) in runs {
        let out = dir.path().join(name);
        let (ok, stderr, r) = soak(&exe, &out, args);
        eprintln!("{}", summary(&r));
        if !ok {
            failed.push(stderr);
        }
        let paths = r["paths"].as_array().expect("paths");
        assert_eq!(paths.len(), 1, "{r}");
        // Every fault of the schedule was injected (one round in a short run).
        let want = if name == "mf" { 6 } else { 7 };
        assert_eq!(paths[0]["faults"].as_array().map_or(0, Vec::len), want, "{r}");
    }
    assert!(failed.is_empty(), "the soak failed a condition:\n{}", failed.join("\n"));
    // The same records with limits no run meets: the check must fail, naming them.
    let out = dir.path().join("sf");
    let (ok, stderr, _) = soak(
        &exe,
        &out,
        &[
            "--recheck",
            "--paths",
            "single_frequency",
            "--rss-tolerance",
            "0",
            "--p99-ratio",
            "1",
            "--resume-s",
            "0",
        ],
    );
    assert!(!ok, "a recheck with limits of 0 passed: {stderr}");
    for cond in ["FAIL latency:", "FAIL resumed:"] {
        assert!(stderr.contains(cond), "{cond} not reported: {stderr}");
    }
}
