//! The `translucent_tof` binary end to end: the offline subcommands on the
//! bundled bags and on scenes drawn here (happy paths), and bad input that
//! must fail with a message naming the cause and leave no output behind.
//!
//! Every run happens in its own temporary directory (the binary's working
//! directory), so anything it writes, wanted or not, is seen.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use tempfile::TempDir;
use translucent_tof::bag::{BagReader, BagWriter};
use translucent_tof::image::{depth_image, ir_image};
use translucent_tof::msgs::translucent_tof::TranslucencyEstimate;
use translucent_tof::msgs::{CameraInfo, Header, Image, PointCloud2, PointField};
use translucent_tof::physics::ImageBuf;
use translucent_tof::sim::render::scene_intrinsics;
use translucent_tof::sim::{render_all, Scene, SimFrame};

mod common;
use common::cli::{assert_ok, describe, run};

// ---------------------------------------------------------------- helpers

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn bundled(name: &str) -> PathBuf {
    repo().join("bags").join(name)
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn read_json(path: &Path) -> Value {
    let t = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    serde_json::from_str(&t).unwrap_or_else(|e| panic!("{} is not JSON ({e}):\n{t}", path.display()))
}

fn num(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("report key {key:?} is not a number: {}", v[key]))
}

fn interval(v: &Value) -> [f64; 2] {
    let iv = v["xi_interval"]
        .as_array()
        .unwrap_or_else(|| panic!("xi_interval is not an array: {}", v["xi_interval"]));
    assert_eq!(iv.len(), 2, "xi_interval {iv:?}");
    let lo = iv[0].as_f64().expect("xi_interval[0] a number");
    let hi = iv[1].as_f64().expect("xi_interval[1] a number");
    assert!(lo <= hi, "xi_interval [{lo}, {hi}] is reversed");
    [lo, hi]
}

fn assert_in_interval(v: &Value, xi: f64) {
    let [lo, hi] = interval(v);
    assert!(
        lo <= xi && xi <= hi,
        "true xi {xi} is outside the reported interval [{lo}, {hi}] (xi {})",
        v["xi"]
    );
}

/// Names of the entries of a directory.
fn entries(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir)
        .expect("listing the temp dir")
        .map(|e| e.expect("dir entry").file_name().to_string_lossy().into_owned())
        .collect()
}

/// A failure as a user should see it: a non-zero exit (not a panic), a
/// message on stderr holding every `needle` (case-insensitive), nothing on
/// stdout that looks like a success, and no file left in `dir` beyond `inputs`.
fn assert_clean_failure(out: &Output, needles: &[&str], dir: &Path, inputs: &[&str]) {
    let err = text(&out.stderr);
    assert!(
        !out.status.success(),
        "bad input was accepted (exit 0): {}",
        describe(out)
    );
    assert_ne!(out.status.code(), Some(101), "the program panicked: {}", describe(out));
    assert!(out.status.code().is_some(), "killed by a signal: {}", describe(out));
    assert!(!err.contains("panicked"), "the program panicked: {}", describe(out));
    let lower = err.to_lowercase();
    for n in needles {
        assert!(
            lower.contains(&n.to_lowercase()),
            "stderr does not name the cause (expected {n:?}): {}",
            describe(out)
        );
    }
    let left: BTreeSet<String> = entries(dir);
    let want: BTreeSet<String> = inputs.iter().map(|s| s.to_string()).collect();
    assert_eq!(
        left,
        want,
        "files left behind after a failure (besides the inputs): {:?}\n{}",
        left.difference(&want).collect::<Vec<_>>(),
        describe(out)
    );
}

/// `replay BAG --out out.mcap --json report.json` in `dir`, expecting failure.
fn replay_fails(dir: &Path, bag: &str, extra: &[&str], needles: &[&str], inputs: &[&str]) {
    let mut args = vec!["replay", bag, "--out", "out.mcap", "--json", "report.json"];
    args.extend_from_slice(extra);
    let out = run(dir, &args);
    assert_clean_failure(&out, needles, dir, inputs);
}

// ------------------------------------------------------- small bad bags

const NS: &str = "/tof";
const FRAME_ID: &str = "tof_optical_frame";

/// A 64x48 scene: `bg_frames` of a wall at 2000 mm, then (if `with_object`)
/// two frames of a translucent plane at 1000 mm.
fn small_scene(bg_frames: usize, with_object: bool) -> Scene {
    let mut toml = format!(
        "name = \"cli test\"\nseed = 7\n[camera]\nwidth = 64\nheight = 48\n[background]\ndistance_mm = 2000\nframes = {bg_frames}\n"
    );
    if with_object {
        toml.push_str(
            "[[stage]]\nframes = 2\n[[stage.objects]]\nshape = \"plane\"\ncenter_mm = [0, 0, 1000]\nsize_mm = [400, 300]\nxi = 0.6\nalbedo = 0.7\n",
        );
    }
    Scene::from_toml(&toml, "small_scene.toml").expect("the small scene parses")
}

fn camera_info(scene: &Scene, stamp_ns: u64) -> CameraInfo {
    translucent_tof::image::camera_info(&Header::new(stamp_ns, FRAME_ID), &scene_intrinsics(scene))
}

fn topic(t: &str) -> String {
    format!("{NS}/{t}")
}

/// Which topics a synthetic bag gets, and how each frame is encoded.
struct BagSpec<'a> {
    depth: bool,
    ir: bool,
    info: bool,
    truth: bool,
    /// Depth message of frame `i` (default: the rendered depth, 16UC1).
    depth_msg: &'a dyn Fn(usize, &SimFrame, &Header) -> Image,
    /// IR message of frame `i` (default: the rendered IR, 16UC1).
    ir_msg: &'a dyn Fn(usize, &SimFrame, &Header) -> Image,
    /// Stamp of the IR message of frame `i`, given the depth stamp.
    ir_stamp: &'a dyn Fn(u64) -> u64,
}

fn default_depth(_: usize, f: &SimFrame, h: &Header) -> Image {
    depth_image(h, &f.depth_z_mm, "16UC1").expect("encoding depth")
}

fn default_ir(_: usize, f: &SimFrame, h: &Header) -> Image {
    ir_image(h, &f.ir, "16UC1").expect("encoding IR")
}

fn same_stamp(t: u64) -> u64 {
    t
}

impl Default for BagSpec<'_> {
    fn default() -> Self {
        BagSpec {
            depth: true,
            ir: true,
            info: true,
            truth: false,
            depth_msg: &default_depth,
            ir_msg: &default_ir,
            ir_stamp: &same_stamp,
        }
    }
}

/// Renders `scene` and writes the topics `spec` asks for to `path`.
fn write_bag(path: &Path, scene: &Scene, spec: &BagSpec) {
    let frames = render_all(scene);
    assert_eq!(frames.len(), scene.frame_count());
    let mut w = BagWriter::create(path).expect("creating a test bag");
    for (i, f) in frames.iter().enumerate() {
        let h = Header::new(f.stamp_ns, FRAME_ID);
        if spec.depth {
            w.write(&topic("depth/image_raw"), f.stamp_ns, &(spec.depth_msg)(i, f, &h))
                .expect("writing depth");
        }
        if spec.ir {
            let t = (spec.ir_stamp)(f.stamp_ns);
            let hi = Header::new(t, FRAME_ID);
            w.write(&topic("ir/image_raw"), t, &(spec.ir_msg)(i, f, &hi))
                .expect("writing IR");
        }
        if spec.info {
            w.write(&topic("depth/camera_info"), f.stamp_ns, &camera_info(scene, f.stamp_ns))
                .expect("writing camera_info");
        }
        if spec.truth {
            w.write(
                &topic("ground_truth/depth"),
                f.stamp_ns,
                &depth_image(&h, &f.truth_z_mm, "32FC1").expect("encoding truth"),
            )
            .expect("writing truth");
        }
    }
    w.finish().expect("finishing a test bag");
}

fn temp() -> TempDir {
    tempfile::tempdir().expect("a temp dir")
}

// ------------------------------------------------------------ happy paths

fn messages_by_topic(bag: &Path) -> BTreeMap<String, Vec<(u64, Vec<u8>, String)>> {
    let r = BagReader::open(bag).unwrap_or_else(|e| panic!("reading {}: {e}", bag.display()));
    let mut m: BTreeMap<String, Vec<(u64, Vec<u8>, String)>> = BTreeMap::new();
    for raw in r.messages() {
        let raw = raw.expect("a message");
        m.entry(raw.topic.to_string()).or_default().push((
            raw.log_time_ns,
            raw.data.to_vec(),
            raw.type_name.to_string(),
        ));
    }
    m
}

fn decode<M: translucent_tof::msgs::RosMessage>(data: &[u8]) -> M {
    translucent_tof::msgs::from_cdr(data).expect("decoding a message")
}

fn f32_at(d: &[u8], off: usize) -> f32 {
    f32::from_le_bytes([d[off], d[off + 1], d[off + 2], d[off + 3]])
}

/// A1: the paper's document holder, ξ estimated, background detected, the
/// output bag read back.
#[test]
fn replay_document_holder_estimates_xi_and_writes_outputs() {
    let dir = temp();
    let input = bundled("document_holder.mcap");
    let out = run(
        dir.path(),
        &[
            "replay",
            input.to_str().unwrap(),
            // The bundled bags are the simulator's, which speaks the paper's model.
            "--physics",
            "paper",
            "--out",
            "out.mcap",
            "--json",
            "report.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("report.json"));
    assert_eq!(r["frames"].as_u64(), Some(18), "frames: {}", r["frames"]);
    assert_eq!(
        r["background_frames"].as_u64(),
        Some(10),
        "background_frames: {}",
        r["background_frames"]
    );
    assert_eq!(r["xi_method"].as_str(), Some("one_material"));
    assert_in_interval(&r, 0.65);
    let mean = num(&r, "mean_frame_rmse_mm");
    let mean_raw = num(&r, "mean_frame_rmse_raw_mm");
    assert!(
        mean <= 10.6,
        "mean per-frame RMSE {mean} mm is worse than the paper's 10.6 mm"
    );
    assert!(
        mean < mean_raw,
        "recovery did not improve the depth: {mean} vs raw {mean_raw} mm"
    );
    assert!(num(&r, "rmse_mm") < num(&r, "rmse_raw_mm"));
    assert!(r["translucent_pixels"].as_u64().unwrap_or(0) > 0);
    let per_frame = r["per_frame"].as_array().expect("per_frame array");
    assert_eq!(per_frame.len(), 8, "one row per object frame");
    for row in per_frame {
        for key in ["stamp", "xi", "rmse_raw_mm", "rmse_mm", "translucent_pixels"] {
            assert!(!row[key].is_null(), "per_frame row lacks {key}: {row}");
        }
    }

    // The output bag, read back.
    let out_bag = dir.path().join("out.mcap");
    assert!(out_bag.is_file(), "no output bag");
    assert!(
        !dir.path().join("out.mcap.partial").exists(),
        "a .partial file was left"
    );
    let outs = messages_by_topic(&out_bag);
    let ins = messages_by_topic(&input);
    // Every frame, as the node publishes it: the 10 it latches passed through, then the 8 object frames.
    let want_topics = [
        "/translucent_tof/depth/corrected",
        "/translucent_tof/depth/camera_info",
        "/translucent_tof/depth/corrected_sigma",
        "/translucent_tof/points",
        "/translucent_tof/translucent_mask",
        "/translucent_tof/translucency",
        "/translucent_tof/regions",
    ];
    for t in want_topics {
        let n = outs.get(t).map(|v| v.len()).unwrap_or(0);
        assert_eq!(
            n,
            18,
            "{t}: {n} messages, expected one per frame; topics: {:?}",
            outs.keys()
        );
    }
    let input_depth: BTreeMap<u64, Image> = ins["/tof/depth/image_raw"]
        .iter()
        .map(|(_, d, _)| {
            let img: Image = decode(d);
            (img.header.stamp.as_log_time_ns(), img)
        })
        .collect();
    let latched: BTreeSet<u64> = input_depth.keys().take(10).copied().collect();
    let report_stamps: Vec<u64> = per_frame
        .iter()
        .map(|row| (row["stamp"].as_f64().unwrap() * 1e9).round() as u64)
        .collect();
    for (i, (log_time, data, ty)) in outs["/translucent_tof/depth/corrected"].iter().enumerate() {
        assert_eq!(ty, "sensor_msgs/msg/Image");
        let img: Image = decode(data);
        let stamp = img.header.stamp.as_log_time_ns();
        assert_eq!(*log_time, stamp, "log time differs from the header stamp");
        let src = input_depth
            .get(&stamp)
            .unwrap_or_else(|| panic!("corrected depth at stamp {stamp} has no input depth frame"));
        assert_eq!((img.width, img.height), (src.width, src.height), "size at {stamp}");
        assert_eq!(img.encoding, src.encoding, "encoding at {stamp}");
        assert_eq!(img.header, src.header, "header at {stamp}");
        if latched.contains(&stamp) {
            assert_eq!(
                img.data, src.data,
                "a latched frame is passed through as read ({stamp})"
            );
        } else {
            assert!(
                report_stamps.iter().any(|s| s.abs_diff(stamp) < 1000),
                "stamp {stamp} not in the report's per_frame stamps {report_stamps:?} (row {i})"
            );
        }
    }
    for (_, data, ty) in &outs["/translucent_tof/depth/camera_info"] {
        assert_eq!(ty, "sensor_msgs/msg/CameraInfo");
        let ci: CameraInfo = decode(data);
        assert!(input_depth
            .get(&ci.header.stamp.as_log_time_ns())
            .is_some_and(|d| d.header == ci.header));
    }
    let (w, h) = {
        let any = input_depth.values().next().unwrap();
        (any.width, any.height)
    };
    for (_, data, ty) in &outs["/translucent_tof/points"] {
        assert_eq!(ty, "sensor_msgs/msg/PointCloud2");
        let pc: PointCloud2 = decode(data);
        assert_eq!((pc.width, pc.height), (w, h), "cloud not organized like the image");
        assert!(
            !pc.is_dense,
            "an organized cloud with NaN points must have is_dense = false"
        );
        assert_eq!(pc.row_step, pc.point_step * pc.width);
        assert_eq!(pc.data.len(), (pc.row_step * pc.height) as usize);
        let field = |n: &str| {
            pc.fields
                .iter()
                .find(|f| f.name == n)
                .unwrap_or_else(|| panic!("no field {n}"))
        };
        for n in ["x", "y", "z"] {
            assert_eq!(field(n).datatype, PointField::FLOAT32, "{n} is not float32");
        }
        let zoff = field("z").offset as usize;
        let zs: Vec<f32> = (0..(w * h) as usize)
            .map(|i| f32_at(&pc.data, i * pc.point_step as usize + zoff))
            .filter(|z| z.is_finite())
            .collect();
        assert!(zs.len() > (w * h) as usize / 2, "too few valid points: {}", zs.len());
        assert!(
            zs.iter().all(|&z| z > 0.2 && z < 3.0),
            "points outside 0.2..3 m (metres expected)"
        );
    }
    let [lo, hi] = interval(&r);
    for (t, data, ty) in &outs["/translucent_tof/translucency"] {
        assert_eq!(ty, "translucent_tof_msgs/msg/TranslucencyEstimate");
        let e: TranslucencyEstimate = decode(data);
        if latched.contains(t) {
            assert_eq!(e.method, "passthrough: latching the background");
            continue;
        }
        assert_eq!(e.method, "one_material");
        assert!(
            (e.xi_lower - lo).abs() < 1e-9 && (e.xi_upper - hi).abs() < 1e-9,
            "estimate message interval [{}, {}] differs from the report's [{lo}, {hi}]",
            e.xi_lower,
            e.xi_upper
        );
    }
    for (t, data, _) in &outs["/translucent_tof/translucent_mask"] {
        let m: Image = decode(data);
        assert_eq!((m.width, m.height, m.encoding.as_str()), (w, h, "mono8"));
        assert_eq!(
            m.data.contains(&255),
            !latched.contains(t),
            "at {t}: an empty mask on an object frame, or a flagged one on a latched frame"
        );
    }
}

/// Issue 53: a user's own recording of a static scene, laid out as an Azure Kinect's driver
/// publishes it (reduced in size: 16UC1 depth in mm with 0 where invalid, 16UC1 IR, a
/// rational_polynomial lens, topics at the root; bags/azure_like_static.toml). Replayed with
/// `--background-frames 10`, the output holds all 14 frames as the node publishes them: every
/// one the input as read, nothing flagged, no invalid pixel published as a distance.
#[test]
fn replay_of_a_static_scene_writes_every_frame_as_read_with_nothing_flagged() {
    let dir = temp();
    let input = bundled("azure_like_static.mcap");
    let args = ["replay", input.to_str().unwrap(), "--background-frames", "10"];
    let out = run(
        dir.path(),
        &[&args[..], &["-o", "out.mcap", "--json", "report.json"]].concat(),
    );
    assert_ok(&out);
    assert!(
        text(&out.stdout).contains("output: all 14 frames as the node publishes them"),
        "{}",
        describe(&out)
    );
    let r = read_json(&dir.path().join("report.json"));
    assert_eq!(
        (r["frames"].as_u64(), r["frames_written"].as_u64()),
        (Some(14), Some(14)),
        "{r}"
    );
    assert_eq!(r["translucent_pixels"].as_u64(), Some(0), "{r}");
    let ins = messages_by_topic(&input);
    let outs = messages_by_topic(&dir.path().join("out.mcap"));
    let input_depth: BTreeMap<u64, Image> = ins["/depth/image_raw"]
        .iter()
        .map(|(t, d, _)| (*t, decode::<Image>(d)))
        .collect();
    assert_eq!(input_depth.len(), 14);
    let latched: BTreeSet<u64> = input_depth.keys().take(10).copied().collect();
    let by_stamp = |topic: &str| -> BTreeMap<u64, Vec<u8>> {
        let msgs = outs
            .get(topic)
            .unwrap_or_else(|| panic!("no {topic}: {:?}", outs.keys()));
        assert_eq!(msgs.len(), 14, "{topic}: one message per frame");
        msgs.iter().map(|(t, d, _)| (*t, d.clone())).collect()
    };
    let (corrected, masks, clouds, sigmas, infos) = (
        by_stamp("/translucent_tof/depth/corrected"),
        by_stamp("/translucent_tof/translucent_mask"),
        by_stamp("/translucent_tof/points"),
        by_stamp("/translucent_tof/depth/corrected_sigma"),
        by_stamp("/translucent_tof/depth/camera_info"),
    );
    let estimates = by_stamp("/translucent_tof/translucency");
    for (stamp, src) in &input_depth {
        let img: Image = decode(&corrected[stamp]);
        assert_eq!(img.header, src.header, "at {stamp}");
        assert_eq!(
            (img.encoding.as_str(), &img.data),
            ("16UC1", &src.data),
            "at {stamp}: not the input as read"
        );
        let invalid: Vec<usize> = (0..src.data.len() / 2)
            .filter(|k| src.data[2 * k] == 0 && src.data[2 * k + 1] == 0)
            .collect();
        assert!(!invalid.is_empty(), "the frame at {stamp} has no invalid (0) pixel");
        let mask: Image = decode(&masks[stamp]);
        assert!(
            mask.data.iter().all(|&m| m == 0),
            "at {stamp}: pixels flagged translucent"
        );
        let pc: PointCloud2 = decode(&clouds[stamp]);
        let step = pc.point_step as usize;
        assert!(
            (0..mask.data.len()).all(|k| pc.data[k * step + 16] == 0),
            "at {stamp}: points flagged"
        );
        for k in &invalid {
            assert!(
                f32_at(&pc.data, k * step + 8).is_nan(),
                "at {stamp}: invalid pixel {k} has a point"
            );
        }
        let sigma: Image = decode(&sigmas[stamp]);
        assert!(
            (0..sigma.data.len() / 4).all(|k| f32_at(&sigma.data, 4 * k).is_nan()),
            "at {stamp}: a sigma"
        );
        assert_eq!(decode::<CameraInfo>(&infos[stamp]).header, src.header, "at {stamp}");
        let e: TranslucencyEstimate = decode(&estimates[stamp]);
        let why = if latched.contains(stamp) {
            "passthrough: latching the background"
        } else {
            "passthrough: xi not determined yet"
        };
        assert_eq!(e.method, why, "at {stamp}");
    }
}

/// A2: a fixed ξ is reported as such, with a degenerate interval.
#[test]
fn replay_with_fixed_xi_reports_fixed() {
    let dir = temp();
    let input = bundled("document_holder.mcap");
    let out = run(
        dir.path(),
        &[
            "replay",
            input.to_str().unwrap(),
            // The bundled bags are the simulator's, which speaks the paper's model.
            "--physics",
            "paper",
            "--xi",
            "0.65",
            "--out",
            "out.mcap",
            "--json",
            "report.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("report.json"));
    assert_eq!(r["xi_method"].as_str(), Some("fixed"), "xi_method {}", r["xi_method"]);
    assert_eq!(interval(&r), [0.65, 0.65]);
    assert_eq!(r["xi"].as_f64(), Some(0.65));
    assert_eq!(r["background_frames"].as_u64(), Some(10));
}

/// The loops built for any processor (`TTOF_PORTABLE=1`) give what the AVX2
/// builds give (where the processor has AVX2): every message of `replay`'s
/// output bag, byte for byte, ξ estimated (the lanes, the ξ profile's fits and
/// the prior's all run).
#[test]
fn replay_with_the_portable_code_gives_the_same_bag() {
    let dir = temp();
    let input = bundled("document_holder.mcap");
    for (out, portable) in [("vector.mcap", "0"), ("portable.mcap", "1")] {
        let o = Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
            .args(["replay", input.to_str().unwrap(), "--physics", "paper", "--out", out])
            .env("TTOF_PORTABLE", portable)
            .current_dir(dir.path())
            .output()
            .expect("running the translucent_tof binary");
        assert_ok(&o);
        // The binary says when it took the portable code (and only then).
        assert_eq!(
            text(&o.stderr).contains("TTOF_PORTABLE"),
            portable == "1",
            "{}",
            describe(&o)
        );
    }
    if !translucent_tof::physics::vector::avx2() {
        eprintln!("no AVX2 here: the portable code is compared with itself");
    }
    let vector = messages_by_topic(&dir.path().join("vector.mcap"));
    let portable = messages_by_topic(&dir.path().join("portable.mcap"));
    assert_eq!(vector.keys().collect::<Vec<_>>(), portable.keys().collect::<Vec<_>>());
    let mut compared = 0;
    for (topic, msgs) in &vector {
        assert_eq!(msgs.len(), portable[topic].len(), "{topic}");
        for (k, (a, b)) in msgs.iter().zip(&portable[topic]).enumerate() {
            assert!(a == b, "{topic}: message {k} differs");
            compared += 1;
        }
    }
    assert!(
        vector.keys().any(|t| t.ends_with("depth/corrected")) && compared > 20,
        "{compared} messages"
    );
}

/// A3: `--json -` puts the report alone on stdout; the summary goes to stderr.
/// (`--xi` keeps this run short; the stdout/stderr split does not depend on it.)
#[test]
fn replay_json_to_stdout_is_pure_json() {
    let dir = temp();
    let input = bundled("document_holder.mcap");
    let out = run(
        dir.path(),
        &[
            "replay",
            input.to_str().unwrap(),
            // The bundled bags are the simulator's, which speaks the paper's model.
            "--physics",
            "paper",
            "--xi",
            "0.65",
            "--out",
            "out.mcap",
            "--json",
            "-",
        ],
    );
    assert_ok(&out);
    let stdout = text(&out.stdout);
    let v: Value =
        serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("stdout is not (only) JSON: {e}\n{}", describe(&out)));
    assert_eq!(v["frames"].as_u64(), Some(18));
    assert!(v["per_frame"].is_array());
    let err = text(&out.stderr);
    assert!(
        err.contains("xi"),
        "the human summary is not on stderr: {}",
        describe(&out)
    );
    assert!(
        err.contains("out.mcap"),
        "the summary does not say what it wrote: {err}"
    );
    assert!(!dir.path().join("-").exists(), "wrote the report to a file named '-'");
}

/// A4: a scene drawn from a seeded RNG, simulated, then replayed: the true ξ
/// lies in the reported interval.
#[test]
fn simulate_random_scene_then_replay_recovers_xi() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x7f0f_2024);
    let xi: f64 = rng.random_range(0.4..0.8);
    let albedo: f64 = rng.random_range(0.5..0.8);
    let wall: f64 = rng.random_range(1800.0..2500.0);
    let z1: f64 = rng.random_range(500.0..900.0);
    let z2: f64 = rng.random_range(1000.0..wall - 500.0);
    let n1: usize = rng.random_range(1..=2);
    let n2: usize = rng.random_range(1..=2);
    let seed: u64 = rng.random_range(0..1_000_000);
    let mut toml = format!(
        "name = \"random cli scene\"\nseed = {seed}\n[background]\ndistance_mm = {wall:.1}\nalbedo = 1.0\nframes = 10\n"
    );
    for (z, n) in [(z1, n1), (z2, n2)] {
        let (x, y): (f64, f64) = (rng.random_range(-30.0..30.0), rng.random_range(-30.0..30.0));
        let (tx, ty): (f64, f64) = (rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0));
        toml.push_str(&format!(
            "[[stage]]\nframes = {n}\n[[stage.objects]]\nshape = \"plane\"\ncenter_mm = [{x:.1}, {y:.1}, {z:.1}]\nsize_mm = [260, 320]\ntilt_x_deg = {tx:.2}\ntilt_y_deg = {ty:.2}\nxi = {xi}\nalbedo = {albedo}\n"
        ));
    }
    let dir = temp();
    std::fs::write(dir.path().join("scene.toml"), &toml).unwrap();
    let out = run(
        dir.path(),
        &["simulate", "scene.toml", "-o", "scene.mcap", "--json", "sim.json"],
    );
    assert_ok(&out);
    let sim = read_json(&dir.path().join("sim.json"));
    assert_eq!(sim["frames"].as_u64(), Some((10 + n1 + n2) as u64), "{sim}");
    assert_eq!(sim["background_frames"].as_u64(), Some(10));
    assert!(dir.path().join("scene.mcap").is_file());

    let out = run(
        dir.path(),
        &[
            "replay",
            "scene.mcap",
            "--physics",
            "paper",
            "--out",
            "rec.mcap",
            "--json",
            "report.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("report.json"));
    assert_eq!(r["background_frames"].as_u64(), Some(10), "scene:\n{toml}");
    assert_eq!(r["per_frame"].as_array().map(|v| v.len()), Some(n1 + n2));
    assert_in_interval(&r, xi);
    assert!(
        num(&r, "rmse_mm") < num(&r, "rmse_raw_mm"),
        "no improvement on the drawn scene:\n{toml}\n{r}"
    );
}

/// A5: Lin from a white wall, then used for the candle.
#[test]
fn calibrate_lin_then_replay_candle_with_it() {
    let dir = temp();
    let wall = bundled("white_wall.mcap");
    let out = run(dir.path(), &["calibrate-lin", wall.to_str().unwrap(), "-o", "lin.json"]);
    assert_ok(&out);
    let lin = read_json(&dir.path().join("lin.json"));
    assert_eq!(lin["format"].as_str(), Some("translucent_tof.lin.v1"));
    assert_eq!(
        lin["lin"].as_array().map(|v| v.len() as u64),
        Some(lin["width"].as_u64().unwrap() * lin["height"].as_u64().unwrap())
    );
    let candle = bundled("candle.mcap");
    let out = run(
        dir.path(),
        &[
            "replay",
            candle.to_str().unwrap(),
            "--physics",
            "paper",
            "--lin-calibration",
            "lin.json",
            "--out",
            "out.mcap",
            "--json",
            "report.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("report.json"));
    let src = r["lin_source"]
        .as_str()
        .unwrap_or_else(|| panic!("lin_source: {}", r["lin_source"]));
    assert!(
        src.contains("calibration file") && !src.contains("no calibration file"),
        "lin_source does not say the calibration file was used: {src:?}"
    );
    assert_in_interval(&r, 0.3);
}

/// A6: calibrate-xi on the model-validation recording (paper Sec. V-A).
#[test]
fn calibrate_xi_on_model_validation_bag() {
    let dir = temp();
    let bag = bundled("model_validation_xi072.mcap");
    let out = run(
        dir.path(),
        &[
            "calibrate-xi",
            bag.to_str().unwrap(),
            "--physics",
            "paper",
            "--json",
            "xi.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("xi.json"));
    assert_in_interval(&r, 0.72);
    let [lo, hi] = interval(&r);
    assert!((hi - lo) / 2.0 <= 0.05, "interval [{lo}, {hi}] is too wide");
}

/// A7: `--help` lists the subcommands.
#[test]
fn help_lists_subcommands() {
    let dir = temp();
    let out = run(dir.path(), &["--help"]);
    assert_ok(&out);
    let s = text(&out.stdout);
    for sub in ["replay", "simulate", "calibrate-xi", "calibrate-lin"] {
        assert!(s.contains(sub), "--help does not list {sub}:\n{s}");
    }
}

/// The options that take one of a few names show them in `--help` (clap's
/// "possible values"), `--physics` its presets beside FILE; a name not among
/// them is refused naming the option and the values.
#[test]
fn help_shows_possible_values() {
    let dir = temp();
    let help = |args: &[&str]| {
        let out = run(dir.path(), args);
        assert_ok(&out);
        text(&out.stdout)
    };
    let replay = help(&["replay", "--help"]);
    for (option, values) in [
        ("--xi-method", &["one_material", "eq12_residual"][..]),
        ("--xi-mode", &["pooled", "online"]),
        ("--physics", &["physical", "paper"]),
        ("--waveform", &["sinusoid", "triangle"]),
        ("--ir-mode", &["sum", "amplitude"]),
    ] {
        let at = replay
            .find(&format!("{option} <"))
            .unwrap_or_else(|| panic!("replay --help has no {option}:\n{replay}"));
        let section = &replay[at..];
        let end = section[2..].find("\n      --").map_or(section.len(), |e| e + 2);
        let section = &section[..end];
        assert!(
            section.contains("Possible values:"),
            "{option} lists no values:\n{section}"
        );
        for v in values {
            assert!(
                section.contains(&format!("- {v}")),
                "{option} does not list {v}:\n{section}"
            );
        }
    }
    assert!(replay.contains("--physics <physical|paper|FILE>"), "{replay}");
    let short = help(&["replay", "-h"]);
    assert!(
        short.contains("[possible values: physical, paper]"),
        "replay -h: --physics\n{short}"
    );
    let calibrate = help(&["calibrate-lin", "-h"]);
    assert!(
        calibrate.contains("[possible values: sinusoid, triangle]"),
        "{calibrate}"
    );
    let bench = help(&["bench", "-h"]);
    assert!(
        bench.contains("[possible values: recover, recover_per_pixel, recover_with_interval, observe, xi_estimate, replay, multi_frequency, node_latency]"),
        "{bench}"
    );
    let bad = run(dir.path(), &["replay", "x.mcap", "--xi-mode", "offline"]);
    assert_clean_failure(&bad, &["--xi-mode", "offline", "pooled", "online"], dir.path(), &[]);
    let bad = run(dir.path(), &["bench", "--cases", "recover,fast"]);
    assert_clean_failure(&bad, &["--cases", "fast", "node_latency"], dir.path(), &[]);
    // A --physics that is no preset and no file says both.
    let bad = run(
        dir.path(),
        &[
            "replay",
            bundled("document_holder.mcap").to_str().unwrap(),
            "--physics",
            "papr",
        ],
    );
    assert_clean_failure(&bad, &["papr", "physical, paper", "physics file"], dir.path(), &[]);
}

/// Flags that exist for tests and benchmarks are accepted but not shown.
#[test]
fn help_hides_test_only_flags() {
    let dir = temp();
    let out = run(dir.path(), &["node", "--help"]);
    assert_ok(&out);
    let help = text(&out.stdout);
    assert!(!help.contains("--max-frames"), "{help}");
    assert!(help.contains("--stats-json"), "{help}");
    let top = run(dir.path(), &["--help"]);
    assert!(!text(&top.stdout).contains("dds-echo"), "{}", text(&top.stdout));
    // Still accepted: the parse fails later, on the parameter, not on the flag.
    let out = run(
        dir.path(),
        &["node", "--max-frames", "1", "--ros-args", "-p", "pin_threads:=2"],
    );
    assert_clean_failure(&out, &["pin_threads"], dir.path(), &[]);
}

/// `node --help` gives every parameter of the README's table with its type and
/// default, under a header naming the columns.
#[test]
fn node_help_lists_parameters_with_type_and_default() {
    let dir = temp();
    let out = run(dir.path(), &["node", "--help"]);
    assert_ok(&out);
    let help = text(&out.stdout);
    let header = help
        .lines()
        .find(|l| l.trim_start().starts_with("NAME"))
        .unwrap_or_else(|| panic!("no header line:\n{help}"));
    let words: Vec<&str> = header.split_whitespace().collect();
    assert_eq!(words, ["NAME", "TYPE", "DEFAULT", "MEANING"], "{header}");
    let readme = std::fs::read_to_string(repo().join("README.md")).expect("README.md");
    let mut rows = 0;
    for line in readme.lines() {
        // | `name` | type | default | run time | meaning |
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() < 7 || !cells[1].starts_with('`') || !["double", "integer", "string", "bool"].contains(&cells[2])
        {
            continue;
        }
        let name = cells[1].trim_matches('`');
        let default = cells[3].split_whitespace().next().unwrap_or("").trim_matches('`');
        let row = help
            .lines()
            .find(|l| l.split_whitespace().next() == Some(name))
            .unwrap_or_else(|| panic!("node --help does not list {name}:\n{help}"));
        let got: Vec<&str> = row.split_whitespace().collect();
        assert_eq!(got[1], cells[2], "type of {name}: {row}");
        assert_eq!(got[2], default, "default of {name}: {row}");
        assert!(got.len() > 3, "no meaning for {name}: {row}");
        rows += 1;
    }
    assert!(rows >= 15, "only {rows} parameters found in README's table");
}

/// `replay -o` is `--out`: a file name, or a folder to write the default name
/// into; nothing is written anywhere else.
#[test]
fn replay_o_writes_there() {
    let dir = temp();
    let input = bundled("document_holder.mcap");
    let bag = input.to_str().unwrap();
    std::fs::create_dir(dir.path().join("results")).unwrap();
    let out = run(dir.path(), &["replay", bag, "--physics", "paper", "-o", "results"]);
    assert_ok(&out);
    let written = dir.path().join("results/document_holder.recovered.mcap");
    let outs = messages_by_topic(&written);
    assert!(
        outs.contains_key("/translucent_tof/depth/corrected"),
        "{:?}",
        outs.keys()
    );
    assert_eq!(entries(dir.path()), BTreeSet::from(["results".to_string()]));
    assert_eq!(entries(&dir.path().join("results")).len(), 1);
    let out = run(
        dir.path(),
        &["replay", bag, "--physics", "paper", "-o", "results/named.mcap"],
    );
    assert_ok(&out);
    assert!(
        text(&out.stdout).contains("wrote results/named.mcap"),
        "{}",
        describe(&out)
    );
    assert!(messages_by_topic(&dir.path().join("results/named.mcap")).contains_key("/translucent_tof/translucency"));
    assert_eq!(entries(dir.path()), BTreeSet::from(["results".to_string()]));
}

/// Without `--out`, replay's bag lands in `out/` under the working directory
/// (created), never beside the input or in the working directory itself.
#[test]
fn default_outputs_land_under_out() {
    let dir = temp();
    let input = dir.path().join("in").join("document_holder.mcap");
    std::fs::create_dir(input.parent().unwrap()).unwrap();
    std::fs::copy(bundled("document_holder.mcap"), &input).unwrap();
    let out = run(dir.path(), &["replay", "in/document_holder.mcap", "--physics", "paper"]);
    assert_ok(&out);
    assert_eq!(
        entries(dir.path()),
        BTreeSet::from(["in".to_string(), "out".to_string()])
    );
    assert_eq!(
        entries(&dir.path().join("in")),
        BTreeSet::from(["document_holder.mcap".to_string()])
    );
    assert_eq!(
        entries(&dir.path().join("out")),
        BTreeSet::from(["document_holder.recovered.mcap".to_string()])
    );
    assert!(
        messages_by_topic(&dir.path().join("out/document_holder.recovered.mcap"))
            .contains_key("/translucent_tof/depth/corrected")
    );
    // The other subcommands write nothing unless asked (demo's default, out/demo, needs DDS: tests/node_dds.rs).
    let out = run(
        dir.path(),
        &[
            "calibrate-xi",
            bundled("model_validation_xi072.mcap").to_str().unwrap(),
            "--physics",
            "paper",
        ],
    );
    assert_ok(&out);
    assert_eq!(
        entries(dir.path()),
        BTreeSet::from(["in".to_string(), "out".to_string()])
    );
    let out = run(dir.path(), &["demo", "--help"]);
    assert!(text(&out.stdout).contains("[default: out/demo]"), "{}", describe(&out));
}

/// The Python interpreter of the venv `scripts/setup-python.sh` builds (or `TTOF_PYTHON`).
fn python() -> PathBuf {
    let p = std::env::var_os("TTOF_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo().join(".venv/bin/python"));
    assert!(
        p.exists(),
        "Python with rerun-sdk not found at {}: run `bash scripts/setup-python.sh` or set TTOF_PYTHON",
        p.display()
    );
    p
}

/// The version of a package in Cargo.lock.
fn locked_version(name: &str) -> String {
    let lock = std::fs::read_to_string(repo().join("Cargo.lock")).expect("Cargo.lock");
    let at = lock
        .find(&format!("name = \"{name}\"\nversion = \""))
        .unwrap_or_else(|| panic!("{name} is not in Cargo.lock"));
    let rest = &lock[at..];
    let v = &rest[rest.find("version = \"").unwrap() + 11..];
    v[..v.find('"').unwrap()].to_string()
}

/// The Rerun CLI of rerun-sdk with `args` (its `rerun` command; `python -m
/// rerun_cli` would drop the exit code).
fn rerun_cli(args: &[&str]) -> Output {
    Command::new(python())
        .args([
            "-c",
            "import sys; from rerun_cli.__main__ import main; sys.exit(main())",
        ])
        .args(args)
        .output()
        .expect("running the Rerun CLI of rerun-sdk")
}

/// `rerun rrd verify FILE` by the Rerun CLI of rerun-sdk, which must be the
/// version of the `rerun` crate this binary logs with. Returns its output.
fn rerun_verify(file: &Path) -> Output {
    let cli = rerun_cli;
    let version = cli(&["--version"]);
    assert!(version.status.success(), "rerun_cli --version: {}", describe(&version));
    let want = format!("rerun-cli {} ", locked_version("rerun"));
    assert!(
        text(&version.stdout).starts_with(&want),
        "the Rerun CLI is not the crate's version ({want:?}): {} (scripts/setup-python.sh pins rerun-sdk)",
        text(&version.stdout)
    );
    cli(&["rrd", "verify", file.to_str().unwrap()])
}

/// `rerun rrd verify` exits 0 for a file it could not read at all ("0 files
/// verified"): success is that exit with the file counted.
fn assert_rerun_verifies(file: &Path) {
    let out = rerun_verify(file);
    let all = format!("{}{}", text(&out.stdout), text(&out.stderr));
    assert!(
        out.status.success() && all.contains("1 file verified without error"),
        "rerun rrd verify {}: {}",
        file.display(),
        describe(&out)
    );
}

/// `replay --rerun OUT.rrd` writes a recording that the Rerun CLI of the same
/// version verifies (a cut copy of it does not pass, so the check reads it),
/// with the recovered depth of every recovered frame; a path not ending in
/// `.rrd` is refused, and a build without Rerun refuses the flag.
#[test]
fn replay_rerun_writes_a_recording_rerun_verifies() {
    let dir = temp();
    let input = bundled("document_holder.mcap");
    let out = run(
        dir.path(),
        &[
            "replay",
            input.to_str().unwrap(),
            "--physics",
            "paper",
            "--rerun",
            "viz/replay.rrd",
            "--json",
            "r.json",
        ],
    );
    if !cfg!(feature = "rerun") {
        assert_clean_failure(&out, &["--rerun", "rerun"], dir.path(), &[]);
        return;
    }
    assert_ok(&out);
    let rrd = dir.path().join("viz/replay.rrd");
    assert_rerun_verifies(&rrd);
    let bytes = std::fs::read(&rrd).unwrap();
    let cut = dir.path().join("cut.rrd");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let refused = rerun_verify(&cut);
    assert!(
        !refused.status.success(),
        "a cut recording passed: {}",
        describe(&refused)
    );
    let r = read_json(&dir.path().join("r.json"));
    assert_eq!(r["rerun"], "viz/replay.rrd", "{}", r["rerun"]);
    // Every recovered frame is in it: the rows of the recovered depth, over its chunks.
    let print = rerun_cli(&["rrd", "print", "-v", rrd.to_str().unwrap()]);
    assert!(print.status.success(), "{}", describe(&print));
    let rows: usize = text(&print.stdout)
        .lines()
        .filter(|l| l.contains(" - /camera/depth/recovered - "))
        .filter_map(|l| l.split(" with ").nth(1)?.split(' ').next()?.parse::<usize>().ok())
        .sum();
    let recovered = r["per_frame"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| f["xi"].is_number())
        .count();
    assert!(recovered > 0, "{r}");
    assert_eq!(rows, recovered, "{}", text(&print.stdout));
    // Each object is an entity over time: its xi has a row in every frame it is in.
    let rows_of = |entity: &str| -> usize {
        text(&print.stdout)
            .lines()
            .filter(|l| l.contains(&format!(" - {entity} - ")))
            .filter_map(|l| l.split(" with ").nth(1)?.split(' ').next()?.parse::<usize>().ok())
            .sum()
    };
    for m in r["materials"].as_array().unwrap() {
        let id = m["id"].as_u64().unwrap();
        let frames = r["per_frame"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|f| f["xi"].is_number())
            .filter(|f| {
                f["regions"]
                    .as_array()
                    .is_some_and(|rs| rs.iter().any(|g| g["id"] == id))
            })
            .count();
        assert!(frames > 0, "object {id} in no frame: {r}");
        for entity in ["xi", "xi_lower", "xi_upper"] {
            assert_eq!(
                rows_of(&format!("/objects/{id}/{entity}")),
                frames,
                "object {id} {entity}"
            );
        }
    }
    let bad = run(
        dir.path(),
        &[
            "replay",
            input.to_str().unwrap(),
            "--physics",
            "paper",
            "--rerun",
            "viz/replay.txt",
            "-o",
            "x.mcap",
        ],
    );
    assert_clean_failure(
        &bad,
        &["--rerun", "viz/replay.txt", ".rrd"],
        dir.path(),
        &["cut.rrd", "out", "r.json", "viz"],
    );
}

/// `bench` on a small image at two layer distances: one row per case and
/// distance, the farther layer covering less of the image and taking less
/// time to recover (the work follows the translucent pixels), `replay` once;
/// a distance the bench has no frame for is refused.
#[test]
fn bench_rows_per_layer_distance() {
    let dir = temp();
    let args = [
        "bench",
        "--cases",
        "recover,replay",
        "--sizes",
        "96x80",
        "--threads",
        "1",
        "--no-reference",
        "--frames",
        "5",
        "--stage-mm",
        "500,1750",
        "--pin-threads",
        "--json",
        "-",
    ];
    let out = run(dir.path(), &args);
    assert_ok(&out);
    let report: Value =
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("not JSON ({e}): {}", describe(&out)));
    let rows = report["rows"].as_array().expect("rows");
    let row = |name: &str, mm: f64| {
        rows.iter()
            .find(|r| r["name"] == name && r["stage_mm"].as_f64() == Some(mm))
            .unwrap_or_else(|| panic!("no {name} row at {mm} mm: {rows:?}"))
    };
    let (near, far) = (row("recover", 500.0), row("recover", 1750.0));
    assert!(
        num(near, "translucent_fraction") > 5.0 * num(far, "translucent_fraction"),
        "{near} {far}"
    );
    assert!(
        num(far, "median_ms") > 0.0 && num(far, "median_ms") < num(near, "median_ms"),
        "{near} {far}"
    );
    assert_eq!(rows.iter().filter(|r| r["name"] == "replay").count(), 1, "{rows:?}");
    assert!(rows.iter().all(|r| r["pinned"] == true), "{rows:?}");
    // The machine the figures were measured on goes with them.
    let machine = &report["machine"];
    assert!(machine["cpu"].as_str().is_some_and(|c| !c.is_empty()), "{machine}");
    assert!(machine["cores"].as_u64().is_some_and(|c| c >= 1), "{machine}");
    assert!(machine["features"].is_array(), "{machine}");
    let bad = run(dir.path(), &["bench", "--stage-mm", "600", "--no-reference"]);
    assert!(!bad.status.success(), "{}", describe(&bad));
    assert!(text(&bad.stderr).contains("--stage-mm 600"), "{}", describe(&bad));
}

/// The node's `pin_threads` takes a boolean; anything else is refused before
/// the node joins DDS.
#[test]
fn node_pin_threads_wants_a_boolean() {
    let dir = temp();
    let out = run(dir.path(), &["node", "--ros-args", "-p", "pin_threads:=2"]);
    assert_clean_failure(&out, &["pin_threads", "true or false"], dir.path(), &[]);
}

// -------------------------------------------------------------- bad input

/// B1
#[test]
fn bad_nonexistent_bag() {
    let dir = temp();
    replay_fails(
        dir.path(),
        "no_such_bag.mcap",
        &[],
        &["no_such_bag.mcap", "no such file"],
        &[],
    );
}

/// B1c: a prior stride of 0 is refused before the bag is read.
#[test]
fn bad_prior_stride() {
    let dir = temp();
    let bag = bundled("document_holder.mcap");
    replay_fails(
        dir.path(),
        bag.to_str().expect("a UTF-8 path"),
        &["--prior-stride-px", "0"],
        &["--prior-stride-px", "0"],
        &[],
    );
}

/// B1b: the OS error is said once (a repeated cause reads as two failures).
#[test]
fn bad_nonexistent_bag_says_the_cause_once() {
    let dir = temp();
    let out = run(dir.path(), &["replay", "no_such_bag.mcap", "--out", "out.mcap"]);
    assert_clean_failure(&out, &["no such file"], dir.path(), &[]);
    let err = text(&out.stderr);
    assert_eq!(
        err.matches("No such file or directory").count(),
        1,
        "the OS error is repeated: {err}"
    );
}

/// B2
#[test]
fn bad_not_mcap() {
    let dir = temp();
    std::fs::write(
        dir.path().join("notes.mcap"),
        "this is a text file, not a recording\n".repeat(20),
    )
    .unwrap();
    replay_fails(
        dir.path(),
        "notes.mcap",
        &[],
        &["notes.mcap", "not an MCAP file"],
        &["notes.mcap"],
    );
}

/// B3a: a bag with camera_info only.
#[test]
fn bad_only_camera_info_topic() {
    let dir = temp();
    let scene = small_scene(3, false);
    let spec = BagSpec {
        depth: false,
        ir: false,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("info_only.mcap"), &scene, &spec);
    replay_fails(
        dir.path(),
        "info_only.mcap",
        &[],
        &["no depth topic", "/tof/depth/camera_info", "--depth-topic"],
        &["info_only.mcap"],
    );
}

/// B3b: depth and camera_info but no IR.
#[test]
fn bad_only_depth_topic() {
    let dir = temp();
    let scene = small_scene(3, true);
    let spec = BagSpec {
        ir: false,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("depth_only.mcap"), &scene, &spec);
    replay_fails(
        dir.path(),
        "depth_only.mcap",
        &[],
        &["no IR topic", "--ir-topic"],
        &["depth_only.mcap"],
    );
}

/// B4: depth 64x48, IR 32x24 at the same stamps.
#[test]
fn bad_depth_ir_size_mismatch() {
    let dir = temp();
    let scene = small_scene(3, true);
    let small_ir = |_: usize, f: &SimFrame, h: &Header| {
        let (w, hh) = (f.ir.width / 2, f.ir.height / 2);
        let mut data = Vec::with_capacity(w * hh);
        for r in 0..hh {
            for c in 0..w {
                data.push(f.ir.data[(2 * r) * f.ir.width + 2 * c]);
            }
        }
        ir_image(
            h,
            &ImageBuf {
                width: w,
                height: hh,
                data,
            },
            "16UC1",
        )
        .unwrap()
    };
    let spec = BagSpec {
        ir_msg: &small_ir,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("sizes.mcap"), &scene, &spec);
    replay_fails(
        dir.path(),
        "sizes.mcap",
        &[],
        &["64x48", "32x24", "IR"],
        &["sizes.mcap"],
    );
}

/// B5: IR stamped 1 ms after depth: no pairs.
#[test]
fn bad_no_shared_stamps() {
    let dir = temp();
    let scene = small_scene(3, true);
    let later = |t: u64| t + 1_000_000;
    let spec = BagSpec {
        ir_stamp: &later,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("stamps.mcap"), &scene, &spec);
    replay_fails(
        dir.path(),
        "stamps.mcap",
        &[],
        &["shares its header stamp", "paired by exact stamp"],
        &["stamps.mcap"],
    );
}

/// B6: a depth image in rgb8.
#[test]
fn bad_unsupported_depth_encoding() {
    let dir = temp();
    let scene = small_scene(3, true);
    let rgb = |_: usize, f: &SimFrame, h: &Header| Image {
        header: h.clone(),
        height: f.depth_z_mm.height as u32,
        width: f.depth_z_mm.width as u32,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: 3 * f.depth_z_mm.width as u32,
        data: vec![128; 3 * f.depth_z_mm.len()],
    };
    let spec = BagSpec {
        depth_msg: &rgb,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("rgb.mcap"), &scene, &spec);
    replay_fails(
        dir.path(),
        "rgb.mcap",
        &[],
        &["unsupported encoding", "rgb8", "depth"],
        &["rgb.mcap"],
    );
}

fn nan_depth(_: usize, f: &SimFrame, h: &Header) -> Image {
    let z = ImageBuf {
        width: f.depth_z_mm.width,
        height: f.depth_z_mm.height,
        data: vec![f32::NAN; f.depth_z_mm.len()],
    };
    depth_image(h, &z, "32FC1").unwrap()
}

fn zero_depth(_: usize, f: &SimFrame, h: &Header) -> Image {
    Image {
        header: h.clone(),
        height: f.depth_z_mm.height as u32,
        width: f.depth_z_mm.width as u32,
        encoding: "16UC1".into(),
        is_bigendian: 0,
        step: 2 * f.depth_z_mm.width as u32,
        data: vec![0; 2 * f.depth_z_mm.len()],
    }
}

/// A 5-frame bag (valid IR) whose depth is invalid everywhere.
fn invalid_depth_bag(dir: &Path, name: &str, depth: &dyn Fn(usize, &SimFrame, &Header) -> Image) {
    let spec = BagSpec {
        depth_msg: depth,
        ..BagSpec::default()
    };
    write_bag(&dir.join(name), &small_scene(3, true), &spec);
}

/// The error for depth that is invalid everywhere: it must name invalid
/// depth / valid pixels, and must not claim the scene never changes (the
/// scene is not the problem, the readings are).
fn assert_invalid_depth_failure(dir: &Path, name: &str, extra: &[&str]) {
    let mut args = vec!["replay", name, "--out", "out.mcap", "--json", "report.json"];
    args.extend_from_slice(extra);
    let out = run(dir, &args);
    assert!(
        !text(&out.stderr).contains("never changes"),
        "depth invalid everywhere is reported as a scene that never changes (misleading): {}",
        describe(&out)
    );
    assert_clean_failure(&out, &["valid"], dir, &[name]);
}

/// B7a: 32FC1 depth, NaN everywhere, background detected: no usable background.
#[test]
fn bad_all_nan_depth_32fc1() {
    let dir = temp();
    invalid_depth_bag(dir.path(), "nan.mcap", &nan_depth);
    assert_invalid_depth_failure(dir.path(), "nan.mcap", &[]);
}

/// B7b: as B7a with `--background-frames 3`.
#[test]
fn bad_all_nan_depth_32fc1_given_background_frames() {
    let dir = temp();
    invalid_depth_bag(dir.path(), "nan.mcap", &nan_depth);
    assert_invalid_depth_failure(dir.path(), "nan.mcap", &["--background-frames", "3"]);
}

/// B7c: 16UC1 depth, 0 (invalid) everywhere, background detected.
#[test]
fn bad_all_zero_depth_16uc1() {
    let dir = temp();
    invalid_depth_bag(dir.path(), "zeros.mcap", &zero_depth);
    assert_invalid_depth_failure(dir.path(), "zeros.mcap", &[]);
}

/// B7d: as B7c with `--background-frames 3`.
#[test]
fn bad_all_zero_depth_16uc1_given_background_frames() {
    let dir = temp();
    invalid_depth_bag(dir.path(), "zeros.mcap", &zero_depth);
    assert_invalid_depth_failure(dir.path(), "zeros.mcap", &["--background-frames", "3"]);
}

/// B8: the wall alone, never an object.
#[test]
fn bad_scene_never_changes() {
    let dir = temp();
    let scene = small_scene(6, false);
    write_bag(&dir.path().join("wall.mcap"), &scene, &BagSpec::default());
    replay_fails(
        dir.path(),
        "wall.mcap",
        &[],
        &["no background", "never changes", "--background-frames"],
        &["wall.mcap"],
    );
}

/// B9: `--background-frames N` with N >= the number of frames.
#[test]
fn bad_background_frames_too_many() {
    let dir = temp();
    let scene = small_scene(3, true); // 5 frames
    write_bag(&dir.path().join("five.mcap"), &scene, &BagSpec::default());
    for n in ["5", "9"] {
        replay_fails(
            dir.path(),
            "five.mcap",
            &["--background-frames", n],
            &[&format!("--background-frames {n}"), "5 paired frames"],
            &["five.mcap"],
        );
    }
}

/// B10: no camera_info.
#[test]
fn bad_no_camera_info() {
    let dir = temp();
    let scene = small_scene(3, true);
    let spec = BagSpec {
        info: false,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("noinfo.mcap"), &scene, &spec);
    replay_fails(
        dir.path(),
        "noinfo.mcap",
        &[],
        &["CameraInfo", "intrinsics", "--info-topic"],
        &["noinfo.mcap"],
    );
}

/// B11: calibrate-xi needs ground truth.
#[test]
fn bad_calibrate_xi_without_ground_truth() {
    let dir = temp();
    let scene = small_scene(3, true);
    write_bag(&dir.path().join("notruth.mcap"), &scene, &BagSpec::default());
    let out = run(dir.path(), &["calibrate-xi", "notruth.mcap", "--json", "xi.json"]);
    assert_clean_failure(
        &out,
        &["ground_truth/depth", "calibrate-xi"],
        dir.path(),
        &["notruth.mcap"],
    );
    // The same scene with truth calibrates (the failure is the missing truth).
    let dir2 = temp();
    let spec = BagSpec {
        truth: true,
        ..BagSpec::default()
    };
    write_bag(&dir2.path().join("truth.mcap"), &scene, &spec);
    let out = run(dir2.path(), &["calibrate-xi", "truth.mcap", "--json", "xi.json"]);
    assert_ok(&out);
}

/// B12a: a negative background distance.
#[test]
fn bad_scene_negative_distance() {
    let dir = temp();
    std::fs::write(
        dir.path().join("neg.toml"),
        "[background]\ndistance_mm = -2000\n[[stage]]\n[[stage.objects]]\nshape = \"plane\"\ncenter_mm = [0, 0, 1000]\nsize_mm = [300, 300]\nxi = 0.5\nalbedo = 0.6\n",
    )
    .unwrap();
    let out = run(
        dir.path(),
        &["simulate", "neg.toml", "-o", "out.mcap", "--json", "sim.json"],
    );
    assert_clean_failure(
        &out,
        &["neg.toml", "background", "distance_mm"],
        dir.path(),
        &["neg.toml"],
    );
}

/// B12b: an unknown key.
#[test]
fn bad_scene_unknown_key() {
    let dir = temp();
    std::fs::write(
        dir.path().join("typo.toml"),
        "[background]\ndistance_mm = 2000\ncolour = \"white\"\n",
    )
    .unwrap();
    let out = run(
        dir.path(),
        &["simulate", "typo.toml", "-o", "out.mcap", "--json", "sim.json"],
    );
    assert_clean_failure(&out, &["typo.toml", "colour"], dir.path(), &["typo.toml"]);
}

// ------------------------------------------------------------------ audit

/// The audit needs ground truth: without it, a clear error and no output.
#[test]
fn bad_audit_without_ground_truth() {
    let dir = temp();
    let scene = small_scene(3, true);
    write_bag(&dir.path().join("notruth.mcap"), &scene, &BagSpec::default());
    let out = run(
        dir.path(),
        &[
            "audit",
            "notruth.mcap",
            "--json",
            "audit.json",
            "--physics-out",
            "physics.toml",
            "--plots",
            "plots",
        ],
    );
    assert_clean_failure(&out, &["ground_truth/depth", "audit"], dir.path(), &["notruth.mcap"]);
}

/// Two frames of the layer are too few to leave frames out.
#[test]
fn bad_audit_too_few_frames() {
    let dir = temp();
    let scene = small_scene(3, true);
    let spec = BagSpec {
        truth: true,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("short.mcap"), &scene, &spec);
    let out = run(
        dir.path(),
        &[
            "audit",
            "short.mcap",
            "--json",
            "audit.json",
            "--physics-out",
            "physics.toml",
        ],
    );
    assert_clean_failure(&out, &["frame", "at least 4"], dir.path(), &["short.mcap"]);
}

fn truth_off_the_layer(_: usize, f: &SimFrame, h: &Header) -> Image {
    // Truth only in the top-left corner, where the layer is not.
    let mut t = f.truth_z_mm.clone();
    for (i, v) in t.data.iter_mut().enumerate() {
        let (c, r) = (i % t.width, i / t.width);
        *v = if c < 4 && r < 4 { 500.0 } else { f32::NAN };
    }
    depth_image(h, &t, "32FC1").expect("encoding truth")
}

/// Ground truth that does not overlap the translucent pixels says so.
#[test]
fn bad_audit_truth_not_on_the_layer() {
    let dir = temp();
    let scene = small_scene(3, true);
    let frames = render_all(&scene);
    let mut w = BagWriter::create(&dir.path().join("offset.mcap")).expect("bag");
    for f in &frames {
        let h = Header::new(f.stamp_ns, FRAME_ID);
        w.write(&topic("depth/image_raw"), f.stamp_ns, &default_depth(0, f, &h))
            .expect("depth");
        w.write(&topic("ir/image_raw"), f.stamp_ns, &default_ir(0, f, &h))
            .expect("ir");
        w.write(
            &topic("depth/camera_info"),
            f.stamp_ns,
            &camera_info(&scene, f.stamp_ns),
        )
        .expect("info");
        w.write(&topic("ground_truth/depth"), f.stamp_ns, &truth_off_the_layer(0, f, &h))
            .expect("truth");
    }
    w.finish().expect("finish");
    let out = run(
        dir.path(),
        &[
            "audit",
            "offset.mcap",
            "--json",
            "audit.json",
            "--physics-out",
            "physics.toml",
        ],
    );
    assert_clean_failure(&out, &["does not overlap", "translucent"], dir.path(), &["offset.mcap"]);
}

/// `--rerun` writes the residual plots as a Rerun recording; a build without
/// Rerun refuses it rather than ignoring it.
#[test]
fn audit_rerun_writes_a_recording_or_is_refused() {
    let dir = temp();
    let out = run(
        dir.path(),
        &[
            "audit",
            bundled("audit_control.mcap").to_str().unwrap(),
            "--rerun",
            "out.rrd",
            "--json",
            "a.json",
        ],
    );
    if cfg!(feature = "rerun") {
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let size = std::fs::metadata(dir.path().join("out.rrd"))
            .map(|m| m.len())
            .unwrap_or(0);
        assert!(size > 1000, "out.rrd is {size} bytes");
        assert_rerun_verifies(&dir.path().join("out.rrd"));
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.path().join("a.json")).unwrap()).unwrap();
        assert!(r["plots"]["files"].to_string().contains("out.rrd"), "{}", r["plots"]);
    } else {
        assert_clean_failure(&out, &["rerun"], dir.path(), &[]);
    }
}

// ------------------------------------------------- the first hour (issue 34)

fn stdout_of(out: &Output) -> String {
    text(&out.stdout)
}

/// A recording says the physics it was made with: `simulate` records it in
/// the bag, and replay and calibrate-xi use it when no `--physics` is given,
/// say so, and warn when a given one differs.
#[test]
fn bags_say_their_physics_and_the_tools_use_it() {
    let dir = temp();
    let scene = repo().join("bags/model_validation_xi072.toml");
    let out = run(dir.path(), &["simulate", scene.to_str().unwrap(), "-o", "mv.mcap"]);
    assert_ok(&out);
    assert!(
        stdout_of(&out).contains("physics: paper (recorded in the bag"),
        "{}",
        describe(&out)
    );
    let r = BagReader::open(&dir.path().join("mv.mcap")).expect("the simulated bag");
    let record = r
        .metadata()
        .iter()
        .find(|m| m.name == translucent_tof::bag::PHYSICS_RECORD)
        .expect("simulate records the physics");
    assert!(
        record.entries[translucent_tof::bag::PHYSICS_RECORD_KEY].contains("preset = \"paper\""),
        "{record:?}"
    );

    // calibrate-xi on the bundled bag, as the issue ran it: the 0.72 material, not 0.565.
    let bag = bundled("model_validation_xi072.mcap");
    let out = run(
        dir.path(),
        &["calibrate-xi", bag.to_str().unwrap(), "--json", "xi.json"],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("xi.json"));
    assert_in_interval(&r, 0.72);
    assert_eq!(r["physics"]["source"], "recording", "{}", r["physics"]);
    let s = stdout_of(&out);
    assert!(
        s.contains("physics: paper, the recording's own, named by its metadata record")
            && s.contains("--physics paper")
            && !s.contains("WARNING"),
        "{s}"
    );
    // A --physics that is not the recording's: used, with a warning.
    let out = run(
        dir.path(),
        &[
            "calibrate-xi",
            bag.to_str().unwrap(),
            "--physics",
            "physical",
            "--json",
            "xi.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("xi.json"));
    assert_eq!(r["physics"]["source"], "option");
    assert!(
        stdout_of(&out).contains("WARNING: --physics physical differs from the physics the recording was made with"),
        "{}",
        describe(&out)
    );
    // The shipped double-pass file is the physics model_validation_xi091 was made with.
    let out = run(
        dir.path(),
        &[
            "calibrate-xi",
            bundled("model_validation_xi091.mcap").to_str().unwrap(),
            "--physics",
            repo().join("bags/physics/double_pass.toml").to_str().unwrap(),
            "--json",
            "xi.json",
        ],
    );
    assert_ok(&out);
    assert_in_interval(&read_json(&dir.path().join("xi.json")), 0.91);
    assert!(!stdout_of(&out).contains("WARNING"), "{}", describe(&out));

    // replay as the issue ran it: the 0.65 document holder, not 0.370.
    let out = run(
        dir.path(),
        &[
            "replay",
            bundled("document_holder.mcap").to_str().unwrap(),
            "--out",
            "out.mcap",
            "--json",
            "report.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("report.json"));
    assert_in_interval(&r, 0.65);
    assert_eq!(r["physics"]["source"], "recording");
    assert!(
        stdout_of(&out).contains("physics: paper, the recording's own"),
        "{}",
        describe(&out)
    );
}

/// A bag with no physics record takes it from its sidecar `BAG.toml`
/// (`physics = "PRESET"`), says so, and refuses a sidecar naming no preset;
/// with neither, the default, said to be one.
#[test]
fn a_sidecar_names_the_physics_of_a_bag_without_a_record() {
    let dir = temp();
    let spec = BagSpec {
        truth: true,
        ..BagSpec::default()
    };
    write_bag(&dir.path().join("scene.mcap"), &small_scene(3, true), &spec);
    let replay = |dir: &Path| run(dir, &["replay", "scene.mcap", "--out", "out.mcap", "--json", "r.json"]);
    let out = replay(dir.path());
    assert_ok(&out);
    assert!(
        stdout_of(&out).contains("physics: physical, the default (the recording does not say"),
        "{}",
        describe(&out)
    );
    assert_eq!(read_json(&dir.path().join("r.json"))["physics"]["source"], "default");

    std::fs::write(dir.path().join("scene.toml"), "name = \"x\"\nphysics = \"paper\"\n").unwrap();
    let out = replay(dir.path());
    assert_ok(&out);
    assert!(
        stdout_of(&out).contains("physics: paper, the recording's own, named by the sidecar scene.toml"),
        "{}",
        describe(&out)
    );
    let r = read_json(&dir.path().join("r.json"));
    assert_eq!(r["physics"]["source"], "recording");
    assert_eq!(r["physics"]["model_options"]["ir_mode"], "sum", "{}", r["physics"]);

    let bad = temp();
    write_bag(&bad.path().join("scene.mcap"), &small_scene(3, true), &spec);
    std::fs::write(bad.path().join("scene.toml"), "physics = \"phyiscal\"\n").unwrap();
    let out = replay(bad.path());
    assert_clean_failure(
        &out,
        &["scene.toml", "phyiscal", "not a preset", "--physics"],
        bad.path(),
        &["scene.mcap", "scene.toml"],
    );
}

/// A bag cut short says where, and what was read, before any scene analysis,
/// even when too little is left for a background; it is not sent the wrong way.
#[test]
fn a_bag_cut_short_says_so_before_the_scene_analysis() {
    let dir = temp();
    let bytes = std::fs::read(bundled("document_holder.mcap")).unwrap();
    std::fs::write(dir.path().join("half.mcap"), &bytes[..bytes.len() / 2]).unwrap();
    let out = run(
        dir.path(),
        &["replay", "half.mcap", "--out", "out.mcap", "--json", "r.json"],
    );
    assert_clean_failure(
        &out,
        &[
            "half.mcap is cut short",
            &format!("the file ends at byte {}", bytes.len() / 2),
            "read before the cut:",
            "paired depth + IR frame(s)",
            "a whole recording is needed",
        ],
        dir.path(),
        &["half.mcap"],
    );
    let err = text(&out.stderr);
    assert!(!err.contains("pass --background-frames"), "{err}");
    assert!(err.starts_with("WARNING: bag half.mcap is cut short"), "{err}");

    // At three quarters it replays, the cut said first, then in the summary and the report.
    std::fs::write(dir.path().join("q3.mcap"), &bytes[..bytes.len() * 3 / 4]).unwrap();
    let out = run(
        dir.path(),
        &["replay", "q3.mcap", "--out", "out.mcap", "--json", "r.json"],
    );
    assert_ok(&out);
    assert!(
        text(&out.stderr).starts_with("WARNING: bag q3.mcap is cut short"),
        "{}",
        describe(&out)
    );
    assert!(
        stdout_of(&out).contains("WARNING: bag q3.mcap is cut short"),
        "{}",
        describe(&out)
    );
    let r = read_json(&dir.path().join("r.json"));
    assert!(r["warnings"].to_string().contains("cut short"), "{}", r["warnings"]);
}

/// One error metric, named: replay's summary prints the mean of per-frame RMS
/// its report names (`error_metric`), and the report's pooled `rmse_mm` is
/// what its name says.
#[test]
fn replay_names_its_error_metric() {
    let dir = temp();
    let out = run(
        dir.path(),
        &[
            "replay",
            bundled("document_holder.mcap").to_str().unwrap(),
            "--out",
            "out.mcap",
            "--json",
            "r.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("r.json"));
    let rows: Vec<(f64, f64, f64)> = r["per_frame"]
        .as_array()
        .expect("per_frame")
        .iter()
        .filter_map(|f| {
            Some((
                f["rmse_mm"].as_f64()?,
                f["rmse_raw_mm"].as_f64()?,
                f["truth_pixels"].as_f64()?,
            ))
        })
        .collect();
    assert_eq!(rows.len(), 8);
    let k = rows.len() as f64;
    let mean = rows.iter().map(|f| f.0).sum::<f64>() / k;
    let mean_raw = rows.iter().map(|f| f.1).sum::<f64>() / k;
    let n: f64 = rows.iter().map(|f| f.2).sum();
    let pooled = (rows.iter().map(|f| f.0 * f.0 * f.2).sum::<f64>() / n).sqrt();
    assert!((num(&r, "mean_frame_rmse_mm") - mean).abs() < 1e-9);
    assert!((num(&r, "mean_frame_rmse_raw_mm") - mean_raw).abs() < 1e-9);
    assert!((num(&r, "rmse_mm") - pooled).abs() < 1e-9);
    for key in ["mean_frame_rmse_mm", "rmse_mm", "coverage", "recovered_of_truth"] {
        assert!(
            r["error_metric"][key].is_string(),
            "error_metric.{key}: {}",
            r["error_metric"]
        );
    }
    assert!(r["error_metric"]["mean_frame_rmse_mm"]
        .as_str()
        .unwrap()
        .starts_with("mean over frames"));
    let line = format!(
        "over the pixels in the mask with truth and a recovered depth (8 frame(s)): raw {mean_raw:.1} mm -> recovered {mean:.1} mm"
    );
    // Every pixel with truth, a pixel kept as read at its reading: never better than the
    // recovered pixels' figure would allow, and said in the same line.
    let every = num(&r, "every_pixel_rmse_mm");
    let every_raw = num(&r, "every_pixel_rmse_raw_mm");
    assert!(
        every.is_finite() && every_raw.is_finite() && every <= every_raw,
        "{every} {every_raw}"
    );
    assert!(stdout_of(&out).contains(&format!("raw {every_raw:.1} mm -> published {every:.1} mm")));
    assert!(stdout_of(&out).contains(&line), "{line}\n{}", describe(&out));
}

/// The audit does not write a physics file that recovers the recording worse
/// than its baseline: where the claimed effect recovers worse, the model it
/// writes stops before it (here: the baseline's own physics), and the report
/// and the summary say so; a step without parameters prints none (no empty
/// parentheses).
#[test]
fn audit_refuses_a_physics_file_that_recovers_worse() {
    let dir = temp();
    let out = run(
        dir.path(),
        &[
            "audit",
            bundled("audit_a.mcap").to_str().unwrap(),
            "--physics",
            "paper",
            "--physics-out",
            "p.toml",
            "--json",
            "a.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("a.json"));
    let po = &r["physics_out"];
    let rec = &r["recovery_rmse_mm"];
    // The claimed model recovers worse: what is written stops before its effect.
    assert!(num(rec, "after") > num(rec, "before"), "{rec}");
    assert_eq!(po["stopped_before"], "transmission_law", "{po}");
    assert_eq!(po["effects"], serde_json::json!([]), "{po}");
    assert!(
        num(po, "recovery_rmse_mm") <= num(po, "baseline_recovery_rmse_mm"),
        "{po}"
    );
    let written = std::fs::read_to_string(dir.path().join("p.toml")).expect("p.toml");
    assert!(!written.contains("transmission_albedo_power = 0.0"), "{written}");
    let s = stdout_of(&out);
    assert!(s.contains("model kept: the baseline"), "{s}");

    // A model that recovers no worse is written; its one step has no parameters.
    let out = run(
        dir.path(),
        &[
            "audit",
            bundled("audit_d.mcap").to_str().unwrap(),
            "--physics",
            "paper",
            "--physics-out",
            "d.toml",
            "--json",
            "d.json",
        ],
    );
    assert_ok(&out);
    assert!(dir.path().join("d.toml").exists(), "{}", describe(&out));
    assert_eq!(read_json(&dir.path().join("d.json"))["physics_out"]["written"], true);
    let s = stdout_of(&out);
    assert!(s.contains("+ ir_amplitude") && !s.contains("()"), "{s}");
}

/// The README says where the binary is, how to install it, and what each
/// `--xi-mode` that `replay -h` offers does.
#[test]
fn readme_says_where_the_binary_is_and_what_xi_mode_does() {
    let readme = std::fs::read_to_string(repo().join("README.md")).expect("README.md");
    for needle in ["target/release/translucent_tof", "cargo install --path ."] {
        assert!(readme.contains(needle), "README.md does not say {needle:?}");
    }
    let dir = temp();
    let out = run(dir.path(), &["replay", "-h"]);
    assert_ok(&out);
    let help = stdout_of(&out);
    let modes = help
        .split_once("--xi-mode")
        .and_then(|(_, after)| after.split_once("[possible values: "))
        .and_then(|(_, values)| values.split_once(']'))
        .map(|(v, _)| v.split(", ").map(str::to_string).collect::<Vec<_>>())
        .unwrap_or_else(|| panic!("no --xi-mode values in replay -h:\n{help}"));
    assert!(modes.len() >= 2, "{modes:?}");
    for m in modes {
        assert!(
            readme.contains(&format!("--xi-mode {m}")),
            "README.md does not explain --xi-mode {m}"
        );
    }
}

/// Issue 31 item 3: `calibrate-xi -o` writes a materials file and appends to it; `replay
/// --materials` reads it and classifies each object among its materials, opaque and unknown
/// (JSON and the estimate message), and a bad file fails naming the file and the field.
#[test]
fn calibrate_xi_writes_a_materials_file_that_replay_classifies_with() {
    let dir = temp();
    let rendered = |name: &str| bundled("rendered").join(name).to_str().unwrap().to_string();
    let calibrate = |bag: &str, name: &str, append: bool| {
        let mut args = vec!["calibrate-xi", bag, "-o", "materials.toml", "--name", name];
        if append {
            args.push("--append");
        }
        run(dir.path(), &args)
    };
    // The calibration sheet (xi 0.676, rho 0.558) and the paper's file box (xi 0.94), each
    // from its own recording with known distances.
    assert_ok(&calibrate(&rendered("calibration_sequence.mcap"), "sheet", false));
    let again = calibrate(&rendered("paper_file_box.mcap"), "file_box", false);
    assert!(
        !again.status.success() && text(&again.stderr).contains("--append"),
        "{}",
        describe(&again)
    );
    assert_ok(&calibrate(&rendered("paper_file_box.mcap"), "file_box", true));
    let file = std::fs::read_to_string(dir.path().join("materials.toml")).unwrap();
    let catalog = translucent_tof::physics::catalog::Catalog::from_toml(&file).unwrap();
    let names: Vec<&str> = catalog.materials.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["sheet", "file_box"]);
    let sheet = &catalog.materials[0];
    assert!(
        sheet.xi_interval[0] <= 0.676 + 0.01 && 0.676 - 0.01 <= sheet.xi_interval[1],
        "{sheet:?}"
    );
    // The implied albedo on the background's scale (wall albedo 1): the sheet's 0.558.
    assert!(
        sheet.albedo_range[0] < 0.558 && 0.558 < sheet.albedo_range[1],
        "{sheet:?}"
    );
    assert!(sheet.recording.ends_with("calibration_sequence.mcap"));

    // The paper's document holder (xi 0.65, rho 0.6 before a white wall) is a sheet of
    // nearly the calibrated one's material: classified as it, and recovered.
    let out = run(
        dir.path(),
        &[
            "replay",
            &rendered("paper_document_holder.mcap"),
            "--materials",
            "materials.toml",
            "-o",
            "holder.mcap",
            "--json",
            "holder.json",
        ],
    );
    assert_ok(&out);
    let r = read_json(&dir.path().join("holder.json"));
    let objects = r["materials"].as_array().unwrap();
    assert_eq!(objects.len(), 1, "{objects:?}");
    let class = &objects[0]["class"];
    assert_eq!(class["material"], "sheet", "{class}");
    assert!(num(class, "probability") > 0.8, "{class}");
    assert!(text(&out.stdout).contains("class sheet"), "{}", describe(&out));
    let regions: Vec<&Value> = r["per_frame"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|f| f["regions"].as_array().into_iter().flatten())
        .collect();
    assert!(!regions.is_empty());
    for region in &regions {
        assert_eq!(region["material"], "sheet", "{region}");
        assert!(num(region, "class_probability") > 0.5, "{region}");
    }
    assert!(num(&r, "rmse_mm") < 30.0, "{}", r["error_summary"]);
    // The estimate message carries the class.
    let outs = messages_by_topic(&dir.path().join("holder.mcap"));
    // Those of the frames passed through while the background was latched carry no class.
    let estimates: Vec<TranslucencyEstimate> = outs["/translucent_tof/translucency"]
        .iter()
        .map(|(_, data, _)| decode::<TranslucencyEstimate>(data))
        .filter(|e| !e.method.starts_with("passthrough"))
        .collect();
    assert!(!estimates.is_empty());
    for e in &estimates {
        assert_eq!(e.material, "sheet", "{e:?}");
        assert!(e.class_probability > 0.5 && e.class_probability <= 1.0, "{e:?}");
        assert_eq!(e.method, "calibrated");
    }

    // Priors over the file's weigh classes, they do not overrule evidence that excludes one:
    // the holder's xi is far from the file box's, however probable a file box was.
    let out = run(
        dir.path(),
        &[
            "replay",
            &rendered("paper_document_holder.mcap"),
            "--materials",
            "materials.toml",
            "--material-prior",
            "file_box=100,opaque=0.01",
            "-o",
            "holder2.mcap",
            "--json",
            "holder2.json",
        ],
    );
    assert_ok(&out);
    let r2 = read_json(&dir.path().join("holder2.json"));
    assert_eq!(r2["materials"][0]["class"]["material"], "sheet", "{}", r2["materials"]);

    // Bad files and priors: the file and the field named, no output written.
    let bad_dir = dir.path().join("bad");
    std::fs::create_dir(&bad_dir).unwrap();
    std::fs::write(bad_dir.join("materials.toml"), &file).unwrap();
    let bad = file.replacen("name = \"file_box\"", "name = \"sheet\"", 1);
    std::fs::write(bad_dir.join("bad.toml"), bad).unwrap();
    replay_fails(
        &bad_dir,
        &rendered("paper_document_holder.mcap"),
        &["--materials", "bad.toml"],
        &["materials file bad.toml", "material[2].name"],
        &["materials.toml", "bad.toml"],
    );
    replay_fails(
        &bad_dir,
        &rendered("paper_document_holder.mcap"),
        &["--materials", "materials.toml", "--material-prior", "glass=2"],
        &["materials file materials.toml", "glass"],
        &["materials.toml", "bad.toml"],
    );
}
