//! `through-engine` (issue 51, item 4): a multi-frequency recording's phasors read through a
//! camera's depth engine give the depth + IR bag that camera's driver publishes. Checked
//! against the simulator rendering the same noise-free scene through the same engine (one
//! forward model: both read the phasors with `PreparedEngine::read`), and its refusals.

use std::collections::BTreeMap;

use translucent_tof::image::{depth_mm, ir_counts};
use translucent_tof::msgs::Image;

mod common;
use common::cli::{assert_ok, describe, images, run};

/// A sheet over a box before a wall, noise-free; with `frequencies` the recording carries
/// phasors at them beside its 30 MHz depth and IR.
fn scene(frequencies: Option<&str>) -> String {
    let camera = frequencies.map_or(String::new(), |f| format!("modulation_frequencies_hz = {f}\n"));
    format!(
        r#"name = "a sheet over a box through a depth engine"
seed = 51
[camera]
{camera}
[physics]
transmission_albedo_power = 0.0
ir_mode = "amplitude"
[noise]
depth_noise_mm = 0.0
[background]
distance_mm = 2400
albedo = 0.7
frames = 3
[[stage]]
frames = 2
[[stage.objects]]
shape = "plane"
center_mm = [120, -10, 900]
size_mm = [320, 380]
tilt_y_deg = 25
xi = 0.7
albedo = 0.5
[[stage.objects]]
shape = "plane"
center_mm = [-320, 20, 1400]
size_mm = [260, 300]
xi = 0.0
albedo = 0.6
"#
    )
}

/// The largest difference between two bags' images on `topic`, per frame, over pixels both
/// hold (NaN in both counts as equal; NaN in one as infinitely apart), decoded by `decode`.
fn largest_difference(
    a: &BTreeMap<String, BTreeMap<u64, Image>>,
    b: &BTreeMap<String, BTreeMap<u64, Image>>,
    topic: &str,
    decode: impl Fn(&Image) -> Vec<f32>,
    relative: bool,
) -> f64 {
    let (ta, tb) = (&a[topic], &b[topic]);
    assert_eq!(
        ta.keys().collect::<Vec<_>>(),
        tb.keys().collect::<Vec<_>>(),
        "{topic}: other stamps"
    );
    let mut worst = 0.0f64;
    for (s, ia) in ta {
        for (x, y) in decode(ia).iter().zip(decode(&tb[s])) {
            let d = match (x.is_nan(), y.is_nan()) {
                (true, true) => 0.0,
                (false, false) => {
                    let d = f64::from((x - y).abs());
                    if relative {
                        d / f64::from(x.abs().max(y.abs())).max(1e-9)
                    } else {
                        d
                    }
                }
                _ => f64::INFINITY,
            };
            worst = worst.max(d);
        }
    }
    worst
}

#[test]
fn phasors_through_an_engine_read_as_the_simulator_renders_through_it() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let d = dir.path();
    std::fs::write(d.join("mf.toml"), scene(Some("[20e6, 50e6, 100e6]"))).expect("writing");
    std::fs::write(d.join("single.toml"), scene(None)).expect("writing");
    assert_ok(&run(d, &["simulate", "mf.toml", "-o", "mf.mcap"]));
    let engine = "--depth-engine-frequencies-hz=20e6,50e6,100e6";
    assert_ok(&run(d, &["simulate", "single.toml", engine, "-o", "direct.mcap"]));
    let out = run(
        d,
        &[
            "through-engine",
            "mf.mcap",
            engine,
            "-o",
            "conv.mcap",
            "--json",
            "conv.json",
        ],
    );
    assert_ok(&out);
    let (direct, conv) = (images(&d.join("direct.mcap")), images(&d.join("conv.mcap")));
    // The driver's bag: no phasors, the ground truth kept.
    assert!(conv.keys().all(|t| !t.contains("phasor")), "{:?}", conv.keys());
    assert!(conv.contains_key("/tof/ground_truth/depth"), "{:?}", conv.keys());
    let depth = largest_difference(
        &direct,
        &conv,
        "/tof/depth/image_raw",
        |m| depth_mm(m).expect("depth").data,
        false,
    );
    assert!(
        depth <= 0.5,
        "the engine's depth differs from the simulator's by up to {depth} mm"
    );
    let ir = largest_difference(
        &direct,
        &conv,
        "/tof/ir/image_raw",
        |m| ir_counts(m).expect("IR").data,
        true,
    );
    assert!(
        ir <= 1e-3,
        "the engine's IR differs from the simulator's by up to {:.3} %",
        ir * 100.0
    );
    // The truth moved: the sheet's pixels read otherwise through the engine than at 30 MHz.
    let mf = images(&d.join("mf.mcap"));
    let moved = largest_difference(
        &mf,
        &conv,
        "/tof/depth/image_raw",
        |m| depth_mm(m).expect("depth").data,
        false,
    );
    assert!(
        moved > 5.0,
        "the engine's depth is the 30 MHz depth ({moved} mm apart): not read through the engine"
    );
    // Replay reads the engine from the bag's physics record.
    let out = run(d, &["replay", "conv.mcap", "-o", "rec.mcap", "--json", "rec.json"]);
    assert_ok(&out);
    let report = std::fs::read_to_string(d.join("rec.json")).expect("the replay's JSON");
    assert!(
        report.contains("20000000"),
        "replay did not take the engine from the record: {report}"
    );
}

#[test]
fn through_engine_refuses_what_it_cannot_read() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let d = dir.path();
    std::fs::write(d.join("mf.toml"), scene(Some("[20e6, 50e6, 100e6]"))).expect("writing");
    std::fs::write(d.join("single.toml"), scene(None)).expect("writing");
    assert_ok(&run(d, &["simulate", "mf.toml", "-o", "mf.mcap"]));
    assert_ok(&run(d, &["simulate", "single.toml", "-o", "single.mcap"]));
    let cases: [(&[&str], &str); 3] = [
        (&["through-engine", "mf.mcap", "-o", "x.mcap"], "needs the engine"),
        (
            &[
                "through-engine",
                "mf.mcap",
                "--depth-engine",
                "kinect_v2",
                "-o",
                "x.mcap",
            ],
            "not among the recorded frequencies",
        ),
        (
            &[
                "through-engine",
                "single.mcap",
                "--depth-engine-frequencies-hz=20e6,50e6",
                "-o",
                "x.mcap",
            ],
            "phasor",
        ),
    ];
    for (args, says) in cases {
        let out = run(d, args);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {}", describe(&out));
        assert!(
            String::from_utf8_lossy(&out.stderr).contains(says),
            "{args:?} should say {says:?}: {}",
            describe(&out)
        );
        assert!(!d.join("x.mcap").exists(), "{args:?} left a bag behind");
    }
}
