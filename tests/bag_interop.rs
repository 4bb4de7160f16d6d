//! Bags written by `BagWriter` read by independent Python readers
//! (`rosbags`, `mcap_ros2`), and a bag written by `mcap_ros2` read by
//! `BagReader`.
//!
//! Needs the Python venv: `bash scripts/setup-python.sh` (or point
//! `TTOF_PYTHON` at an interpreter that has `rosbags` and
//! `mcap-ros2-support`). Without it these tests fail, they do not skip.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;
use translucent_tof::bag::{select_topics, BagError, BagReader, BagWriter, TopicOverrides};
use translucent_tof::image::{depth_image, depth_mm, ir_counts, ir_image, organized_cloud};
use translucent_tof::msgs::{CameraInfo, Header, Image, PointCloud2, Time};
use translucent_tof::physics::ImageBuf;

const T0: u64 = 1_700_000_000_000_000_000;
const DT: u64 = 33_333_333;
const FRAMES: u64 = 2;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn python() -> PathBuf {
    let candidate = match std::env::var_os("TTOF_PYTHON") {
        Some(p) => PathBuf::from(p),
        None => repo().join(".venv/bin/python"),
    };
    assert!(
        candidate.exists(),
        "Python for the interop tests not found at {}: run `bash scripts/setup-python.sh` \
         (creates <repo>/.venv with rosbags and mcap-ros2-support) or set TTOF_PYTHON",
        candidate.display()
    );
    candidate
}

fn run_py(script: &str, arg: &Path) -> String {
    let out = Command::new(python())
        .arg(repo().join("tests/py").join(script))
        .arg(arg)
        .output()
        .unwrap_or_else(|e| panic!("running {script}: {e}"));
    assert!(
        out.status.success(),
        "{script} {} failed ({}):\n{}\n{}",
        arg.display(),
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn read_json(script: &str, bag: &Path) -> Value {
    let text = run_py(script, bag);
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{script} printed bad JSON ({e}):\n{text}"))
}

fn header(frame: u64) -> Header {
    Header::new(T0 + frame * DT, "tof_optical_frame")
}

/// Depth in mm of frame `f` at (col, row) of a 3x2 image; (2, 1) invalid.
fn depth_value(f: u64, col: usize, row: usize) -> f32 {
    if (col, row) == (2, 1) {
        f32::NAN
    } else {
        (1000 + 100 * f as usize + 10 * row + col) as f32
    }
}

fn camera_info(frame: u64) -> CameraInfo {
    CameraInfo {
        header: header(frame),
        height: 2,
        width: 3,
        distortion_model: "plumb_bob".into(),
        d: vec![0.1, -0.2, 0.0, 0.0, 0.05],
        k: [500.0, 0.0, 1.0, 0.0, 501.0, 0.5, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [500.0, 0.0, 1.0, 0.0, 0.0, 501.0, 0.5, 0.0, 0.0, 0.0, 1.0, 0.0],
        ..Default::default()
    }
}

/// A bag with every encoding we write, two frames each.
fn write_test_bag(path: &Path) {
    let mut w = BagWriter::create(path).unwrap();
    for f in 0..FRAMES {
        let h = header(f);
        let t = h.stamp.as_log_time_ns();
        let z = ImageBuf::from_vec(3, 2, (0..6).map(|i| depth_value(f, i % 3, i / 3)).collect()).unwrap();
        w.write("/tof/depth/image_raw", t, &depth_image(&h, &z, "16UC1").unwrap())
            .unwrap();
        w.write("/tof/depth/image_m", t, &depth_image(&h, &z, "32FC1").unwrap())
            .unwrap();
        let ir = ImageBuf::from_vec(3, 2, (0..6).map(|i| (400 + 10 * f + i) as f32).collect()).unwrap();
        w.write("/tof/ir/image_raw", t, &ir_image(&h, &ir, "mono16").unwrap())
            .unwrap();
        w.write("/tof/ir/image_mono8", t, &ir_image(&h, &ir, "mono8").unwrap())
            .unwrap();
        // Row padding: 3 samples of 2 bytes, step 8.
        let mut padded = Vec::new();
        for row in 0..2u16 {
            for col in 0..3u16 {
                padded.extend_from_slice(&(2000 + row * 3 + col).to_le_bytes());
            }
            padded.extend_from_slice(&[0xEE, 0xEE]);
        }
        let padded = Image {
            header: h.clone(),
            height: 2,
            width: 3,
            encoding: "16UC1".into(),
            is_bigendian: 0,
            step: 8,
            data: padded,
        };
        w.write("/tof/depth/image_padded", t, &padded).unwrap();
        w.write("/tof/depth/camera_info", t, &camera_info(f)).unwrap();
        let xyz = ImageBuf::from_vec(3, 2, (0..6).map(|i| [i as f32 * 0.1, -0.5, 1.25]).collect()).unwrap();
        let translucent = ImageBuf::from_vec(3, 2, vec![true, false, false, false, false, true]).unwrap();
        let cloud: PointCloud2 = organized_cloud(&h, &xyz, &ir, &translucent, &ImageBuf::filled(3, 2, 0.004f32));
        w.write("/tof/points", t, &cloud).unwrap();
    }
    w.finish().unwrap();
}

const TOPICS: [(&str, &str); 7] = [
    ("/tof/depth/image_raw", "sensor_msgs/msg/Image"),
    ("/tof/depth/image_m", "sensor_msgs/msg/Image"),
    ("/tof/ir/image_raw", "sensor_msgs/msg/Image"),
    ("/tof/ir/image_mono8", "sensor_msgs/msg/Image"),
    ("/tof/depth/image_padded", "sensor_msgs/msg/Image"),
    ("/tof/depth/camera_info", "sensor_msgs/msg/CameraInfo"),
    ("/tof/points", "sensor_msgs/msg/PointCloud2"),
];

fn nums(v: &Value) -> Vec<Option<f64>> {
    v.as_array()
        .unwrap_or_else(|| panic!("not an array: {v}"))
        .iter()
        .map(Value::as_f64)
        .collect()
}

/// The checks both Python readers must pass on the bag of [`write_test_bag`].
fn check_python_view(json: &Value) {
    let reader = json["reader"].as_str().unwrap_or("?");
    let topics = &json["topics"];
    assert_eq!(
        topics.as_object().map(|o| o.len()),
        Some(TOPICS.len()),
        "{reader}: {topics}"
    );
    for (name, type_name) in TOPICS {
        let t = &topics[name];
        assert_eq!(t["type"], type_name, "{reader}: {name}");
        assert_eq!(t["count"], FRAMES, "{reader}: {name}");
        assert_eq!(t["message_encoding"], "cdr", "{reader}: {name}");
    }
    let deps: Vec<&str> = topics["/tof/depth/camera_info"]["dependencies"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect();
    assert_eq!(
        deps,
        [
            "std_msgs/Header",
            "builtin_interfaces/Time",
            "sensor_msgs/RegionOfInterest"
        ]
    );

    let first = &json["first"];
    let stamp = Time::from_nanos(T0);
    let want_stamp = serde_json::json!([stamp.sec, stamp.nanosec]);

    let d = &first["/tof/depth/image_raw"];
    assert_eq!(
        (d["width"].as_u64(), d["height"].as_u64()),
        (Some(3), Some(2)),
        "{reader}: {d}"
    );
    assert_eq!(d["encoding"], "16UC1");
    assert_eq!(d["step"], 6);
    assert_eq!(d["stamp"], want_stamp, "{reader}");
    assert_eq!(d["frame_id"], "tof_optical_frame");
    assert_eq!(nums(&d["first_pixels"]), [Some(1000.0), Some(1001.0), Some(1002.0)]);

    let m = &first["/tof/depth/image_m"];
    assert_eq!(m["encoding"], "32FC1");
    assert_eq!(m["step"], 12);
    let px = nums(&m["first_pixels"]);
    assert_eq!(px.len(), 3);
    for (got, want) in px.iter().zip([1.0, 1.001, 1.002]) {
        assert!((got.unwrap() - want).abs() < 1e-6, "{reader}: {px:?}");
    }

    let ir = &first["/tof/ir/image_raw"];
    assert_eq!(
        (ir["encoding"].as_str(), ir["step"].as_u64()),
        (Some("mono16"), Some(6))
    );
    assert_eq!(nums(&ir["first_pixels"]), [Some(400.0), Some(401.0), Some(402.0)]);
    let ir8 = &first["/tof/ir/image_mono8"];
    assert_eq!(
        (ir8["encoding"].as_str(), ir8["step"].as_u64()),
        (Some("mono8"), Some(3))
    );
    assert_eq!(nums(&ir8["first_pixels"]), [Some(255.0), Some(255.0), Some(255.0)]);

    let p = &first["/tof/depth/image_padded"];
    assert_eq!((p["step"].as_u64(), p["data_len"].as_u64()), (Some(8), Some(16)));
    assert_eq!(nums(&p["first_pixels"]), [Some(2000.0), Some(2001.0), Some(2002.0)]);

    let info = &first["/tof/depth/camera_info"];
    assert_eq!(nums(&info["k"]), camera_info(0).k.map(Some));
    assert_eq!(
        nums(&info["d"]),
        camera_info(0).d.iter().map(|&x| Some(x)).collect::<Vec<_>>()
    );
    assert_eq!(nums(&info["p"]), camera_info(0).p.map(Some));
    assert_eq!(info["distortion_model"], "plumb_bob");

    let c = &first["/tof/points"];
    assert_eq!(
        (c["width"].as_u64(), c["height"].as_u64()),
        (Some(3), Some(2)),
        "{reader}: {c}"
    );
    assert_eq!((c["point_step"].as_u64(), c["row_step"].as_u64()), (Some(24), Some(72)));
    assert_eq!(c["is_dense"], false);
    let fp = &c["first_point"];
    assert_eq!(
        (fp["x"].as_f64(), fp["y"].as_f64(), fp["z"].as_f64()),
        (Some(0.0), Some(-0.5), Some(1.25))
    );
    assert_eq!(
        (
            fp["intensity"].as_f64(),
            fp["translucent"].as_u64(),
            fp["sigma"].as_f64().map(|s| (s * 1e6).round())
        ),
        (Some(400.0), Some(1), Some(4000.0))
    );
}

#[test]
fn rosbags_reads_our_bag() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("ours.mcap");
    write_test_bag(&bag);
    check_python_view(&read_json("read_with_rosbags.py", &bag));
}

#[test]
fn mcap_ros2_reads_our_bag() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("ours.mcap");
    write_test_bag(&bag);
    let json = read_json("read_with_mcap_ros2.py", &bag);
    check_python_view(&json);
    let library = json["library"].as_str().unwrap_or_default();
    assert!(library.starts_with("translucent_tof"), "{library}");
    assert_eq!(json["first"]["/tof/points"]["log_time_ns"], T0);
}

#[test]
fn we_read_a_bag_written_by_mcap_ros2() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("theirs.mcap");
    run_py("write_with_mcap_ros2.py", &bag);
    let reader = BagReader::open(&bag).unwrap();
    let topics = reader.topics();
    assert_eq!(topics.len(), 3, "{topics:?}");
    assert!(topics.iter().all(|t| t.message_count == 3), "{topics:?}");

    let sel = select_topics(&topics, &TopicOverrides::default()).unwrap();
    assert_eq!(sel.depth, "/cam/depth/image_raw");
    assert_eq!(sel.ir, "/cam/ir/image_raw");
    assert_eq!(sel.info.as_deref(), Some("/cam/depth/camera_info"));
    assert_eq!(sel.ground_truth, None);

    let mut depth_frames = 0u64;
    let mut last_time = 0;
    for raw in reader.messages() {
        let raw = raw.unwrap();
        assert!(raw.log_time_ns >= last_time, "not in log-time order");
        last_time = raw.log_time_ns;
        if raw.topic == sel.depth {
            let img: Image = BagReader::decode(&raw).unwrap();
            let f = depth_frames;
            assert_eq!(img.header.stamp.as_log_time_ns(), 1_000_000_000 + f * 100_000_000);
            assert_eq!(raw.log_time_ns, img.header.stamp.as_log_time_ns());
            assert_eq!(img.step, 10);
            let z = depth_mm(&img).unwrap();
            for row in 0..3 {
                for col in 0..4 {
                    let v = *z.at(col, row);
                    if (col, row) == (3, 2) {
                        assert!(v.is_nan());
                    } else {
                        assert_eq!(v, (1000 + 100 * f as usize + 10 * row + col) as f32);
                    }
                }
            }
            depth_frames += 1;
        } else if raw.topic == sel.ir {
            let img: Image = BagReader::decode(&raw).unwrap();
            let ir = ir_counts(&img).unwrap();
            assert_eq!(*ir.at(1, 2), (500 + 9) as f32 + *ir.at(0, 0) - 500.0);
            assert!(BagReader::decode::<CameraInfo>(&raw).is_err());
        } else if Some(raw.topic) == sel.info.as_deref() {
            let info: CameraInfo = BagReader::decode(&raw).unwrap();
            assert_eq!(info.k, [500.0, 0.0, 2.0, 0.0, 501.0, 1.5, 0.0, 0.0, 1.0]);
            assert_eq!(info.d, [0.1, -0.2, 0.0, 0.0, 0.05]);
            assert_eq!(info.distortion_model, "plumb_bob");
        }
    }
    assert_eq!(depth_frames, 3);
}

#[test]
fn our_bag_round_trips_through_our_reader() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("ours.mcap");
    write_test_bag(&bag);
    let reader = BagReader::open(&bag).unwrap();
    let sel = select_topics(&reader.topics(), &TopicOverrides::default()).unwrap();
    assert_eq!(
        (sel.depth.as_str(), sel.ir.as_str()),
        ("/tof/depth/image_raw", "/tof/ir/image_raw")
    );
    let raw = reader
        .messages()
        .map(Result::unwrap)
        .find(|m| m.topic == "/tof/depth/image_m")
        .unwrap();
    let z = depth_mm(&BagReader::decode::<Image>(&raw).unwrap()).unwrap();
    assert!((z.at(1, 0) - depth_value(0, 1, 0)).abs() < 1e-3);
    assert!(z.at(2, 1).is_nan());
}

#[test]
fn a_truncated_file_is_read_to_its_cut_or_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("ours.mcap");
    write_test_bag(&bag);
    let bytes = std::fs::read(&bag).unwrap();
    let whole = BagReader::open(&bag).unwrap().messages().count();
    let cut = dir.path().join("cut.mcap");
    let (mut refused, mut partial) = (0, 0);
    for eighth in 1..8 {
        let len = bytes.len() * eighth / 8;
        std::fs::write(&cut, &bytes[..len]).unwrap();
        match BagReader::open(&cut) {
            // Cut before its first message: nothing to read.
            Err(err) => {
                assert!(matches!(err, BagError::Truncated { .. }), "{err}");
                let msg = err.to_string();
                assert!(msg.contains("cut.mcap") && msg.contains("truncated"), "{msg}");
                refused += 1;
            }
            // Cut later: the messages before the cut, and where it is.
            Ok(r) => {
                let [stop] = r.stops() else {
                    panic!("cut at {len} of {} read without a stop", bytes.len())
                };
                assert_eq!((stop.len, stop.offset), (len as u64, len as u64), "{stop}");
                let n = r.messages().count();
                assert!(n > 0 && n <= whole && stop.messages_kept == n as u64, "{stop}");
                let msg = stop.to_string();
                assert!(msg.contains("cut.mcap") && msg.contains("cut short"), "{msg}");
                partial += 1;
            }
        }
    }
    assert_eq!(refused + partial, 7);
    assert!(refused > 0, "every cut read something");
}

#[test]
fn non_mcap_file_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("notes.mcap");
    std::fs::write(&path, b"just some text, no MCAP here\n").unwrap();
    let err = BagReader::open(&path).err().expect("a text file must not open");
    assert!(matches!(err, BagError::NotMcap { .. }), "{err}");
    assert!(
        err.to_string().contains("notes.mcap") && err.to_string().contains("not an MCAP"),
        "{err}"
    );
}

#[test]
fn partial_file_removed_when_writer_dropped() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("out.mcap");
    {
        let mut w = BagWriter::create(&bag).unwrap();
        w.write("/tof/depth/camera_info", T0, &camera_info(0)).unwrap();
        assert!(dir.path().join("out.mcap.partial").exists());
        assert!(!bag.exists());
    }
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}
