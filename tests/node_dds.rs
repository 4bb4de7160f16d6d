//! The node over real DDS (RustDDS on loopback, in a private network
//! namespace): the demo end to end, faults, and a queue under overload.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::netns::isolated;
use common::published_width;
use translucent_tof::bag::BagReader;
use translucent_tof::image::{depth_mm, CLOUD_POINT_STEP};
use translucent_tof::msgs::{CameraInfo, Image, PointCloud2};
use translucent_tof::node::peer::{bag_frames, restamp, Peer};

fn exe() -> &'static str {
    env!("CARGO_BIN_EXE_translucent_tof")
}

fn bag(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("bags").join(name)
}

#[test]
fn demo_runs_the_graph_and_recovers_the_document_holder() {
    if !isolated("demo_runs_the_graph_and_recovers_the_document_holder") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(exe())
        .args(["demo", "--speed", "3", "--json", "-", "--out-dir"])
        .arg(dir.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "demo failed: {stderr}");
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).expect("demo --json - prints JSON");
    eprintln!("{}", serde_json::to_string_pretty(&r).unwrap());
    let played = r["object_frames_played"].as_u64().unwrap();
    let got = r["frames_received"].as_u64().unwrap();
    assert!(
        played > 0 && got * 10 >= played * 9,
        "{got} of {played} frames came back"
    );
    readme_demo_lines_are_these(&stderr, got == played);
    let (raw, rec) = (r["rmse_raw_mm"].as_f64().unwrap(), r["rmse_mm"].as_f64().unwrap());
    // The paper's 10.6 mm is over four poses offline; the node estimates online, as frames
    // arrive. Its claim here: recovered well under raw (the README's demo figures).
    assert!(rec < raw / 5.0, "recovered {rec} mm vs raw {raw} mm");
    // Against the truth the demo's bag was rendered with (its sidecar: xi 0.65), four poses
    // of one sheet: the data determine xi, so the interval is also bounded in width. The
    // estimate within 0.05 of the truth; whether the interval holds it is measured over the
    // rendered set (scripts/results), where this bag's, [0.652, 0.696] offline, is a known
    // miss (rendered_scenes' ignored document-holder test).
    let iv = r["xi_interval"].as_array().unwrap();
    let (lo, hi) = (iv[0].as_f64().unwrap(), iv[1].as_f64().unwrap());
    let xi = r["xi"].as_f64().unwrap();
    assert!((xi - 0.65).abs() <= 0.05, "xi {xi} [{lo}, {hi}] against the true 0.65");
    assert!(
        hi - lo <= published_width(0.1),
        "[{lo}, {hi}]: four poses of one sheet should pin xi to +-0.1, with the model's error"
    );
    let passed: u64 = r["node"]["passed_through"]
        .as_object()
        .map_or(0, |m| m.values().filter_map(|v| v.as_u64()).sum());
    assert!(r["node"]["published"].as_u64().unwrap() + passed >= got, "{r}");
    // The outputs kept as a bag: corrected depth as the input, an organized cloud.
    let reader = BagReader::open(&dir.path().join("demo.mcap")).unwrap();
    let (mut images, mut clouds) = (0, 0);
    let mut masks = std::collections::BTreeMap::new();
    let mut flags = std::collections::BTreeMap::new();
    for m in reader.messages() {
        let m = m.unwrap();
        if m.topic == "/tof/translucent_tof/depth/corrected" {
            let img: Image = BagReader::decode(&m).unwrap();
            assert_eq!((img.width, img.height, img.encoding.as_str()), (176, 144, "16UC1"));
            assert_eq!(img.header.stamp.as_log_time_ns(), m.log_time_ns);
            depth_mm(&img).unwrap();
            images += 1;
        } else if m.topic == "/tof/translucent_tof/points" {
            let c: PointCloud2 = BagReader::decode(&m).unwrap();
            assert_eq!((c.width, c.height, c.point_step), (176, 144, CLOUD_POINT_STEP));
            let names: Vec<&str> = c.fields.iter().map(|f| f.name.as_str()).collect();
            assert_eq!(names, ["x", "y", "z", "intensity", "translucent", "sigma"]);
            assert_eq!(c.data.len(), 176 * 144 * CLOUD_POINT_STEP as usize);
            let step = CLOUD_POINT_STEP as usize;
            let flagged = (0..176 * 144).filter(|k| c.data[k * step + 16] == 1).count();
            flags.insert(m.log_time_ns, flagged);
            // Valid points lie in front of the camera, metres.
            let z = |k: usize| f32::from_le_bytes(c.data[k * step + 8..k * step + 12].try_into().unwrap());
            let valid: Vec<f32> = (0..176 * 144).map(z).filter(|z| z.is_finite()).collect();
            assert!(valid.len() > 20_000 && valid.iter().all(|z| *z > 0.2 && *z < 5.0));
            clouds += 1;
        } else if m.topic == "/tof/translucent_tof/translucent_mask" {
            let img: Image = BagReader::decode(&m).unwrap();
            masks.insert(m.log_time_ns, img.data.iter().filter(|v| **v == 255).count());
        }
    }
    // The cloud's translucent flags are the mask's pixels, frame by frame.
    assert_eq!(flags, masks);
    // The sheet's first pose is kept as read (one pose does not reject opaque); from the
    // frame its object is determined on, every frame flags it.
    let flagged: Vec<usize> = flags.values().copied().collect();
    let first = flagged.iter().position(|n| *n > 0).unwrap_or(flagged.len());
    assert!(flagged[first..].iter().all(|n| *n > 500), "{flags:?}");
    assert!(flagged.len() - first >= flagged.len() / 2, "{flags:?}");
    assert_eq!(images as u64, got);
    assert_eq!(clouds as u64, got);
    let rrd = std::fs::metadata(dir.path().join("demo.rrd"))
        .map(|m| m.len())
        .unwrap_or(0);
    if cfg!(feature = "rerun") {
        assert!(rrd > 10_000, "demo.rrd is {rrd} bytes");
    }
}

/// The README's demo lines (between `<!--f:demo:lines-->` and `<!--/f-->`, written by
/// `scripts/readme-figures --write` from the demo's output) are lines this demo printed, figure
/// for figure. Compared when every frame came back: a lost frame changes the figures.
fn readme_demo_lines_are_these(printed: &str, every_frame_back: bool) {
    let readme = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).expect("README.md");
    let block = readme
        .split_once("<!--f:demo:lines-->")
        .and_then(|(_, rest)| rest.split_once("<!--/f-->"))
        .map(|(block, _)| block)
        .expect("README.md has the demo's lines between <!--f:demo:lines--> and <!--/f-->");
    let lines: Vec<&str> = block
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with("```"))
        .collect();
    assert!(!lines.is_empty(), "README.md's demo block is empty");
    if !every_frame_back {
        println!("the README's demo lines not compared: not every frame came back");
        return;
    }
    for line in lines {
        assert!(
            printed.lines().any(|p| p.trim_end() == line.trim_end()),
            "README.md's demo line is not what the demo printed (scripts/readme-figures --write rewrites it):\n  README: {line}\n  demo printed:\n{printed}"
        );
    }
}

struct NodeChild {
    child: Child,
    stats: PathBuf,
    log: PathBuf,
    _dir: tempfile::TempDir,
}

impl NodeChild {
    fn start(params: &[&str]) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let stats = dir.path().join("stats.json");
        let log = dir.path().join("node.log");
        let mut cmd = Command::new(exe());
        cmd.arg("node").arg("--stats-json").arg(&stats);
        cmd.args(["--ros-args", "-r", "__ns:=/tof"]);
        for p in params {
            cmd.args(["-p", p]);
        }
        let child = cmd
            .stdin(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        NodeChild {
            child,
            stats,
            log,
            _dir: dir,
        }
    }

    fn stop(self) -> serde_json::Value {
        self.stop_with_log().0
    }

    /// Waits until the node's log holds `line` (false after `timeout`): the node has acted on
    /// what was sent, however long DDS took to deliver it.
    async fn logged(&self, line: &str, timeout: Duration) -> bool {
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            if std::fs::read_to_string(&self.log).is_ok_and(|l| l.contains(line)) {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        false
    }

    /// Stops the node; its counters and its log (also shown on stderr).
    fn stop_with_log(mut self) -> (serde_json::Value, String) {
        let pid = self.child.id().to_string();
        Command::new("kill").args(["-INT", &pid]).status().unwrap();
        let t0 = Instant::now();
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            if t0.elapsed() > Duration::from_secs(20) {
                let log = std::fs::read_to_string(&self.log).unwrap_or_default();
                panic!("node did not stop within 20 s of SIGINT; its log:\n{log}");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let log = std::fs::read_to_string(&self.log).unwrap_or_default();
        eprint!("{log}");
        assert!(status.success(), "node exited with {status}");
        let stats = serde_json::from_str(&std::fs::read_to_string(&self.stats).unwrap()).unwrap();
        (stats, log)
    }
}

impl Drop for NodeChild {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The bundled document holder's frames: camera_info and depth + IR pairs.
fn frames() -> (CameraInfo, Vec<(Image, Image)>, usize) {
    let (info, pairs) = bag_frames(&bag("document_holder.mcap")).unwrap();
    // The bundled scene's background lasts 10 frames.
    (info, pairs, 10)
}

fn stamped(img: &Image, ns: u64) -> Image {
    restamp(img, ns)
}

/// A driver, client and listener of the node at `/tof/translucent_tof`, once the node is up.
async fn driver(ctx: &ros2_client::Context, name: &str) -> Peer {
    let peer = Peer::new(
        ctx,
        name,
        "/tof",
        "/tof/translucent_tof",
        ros2_client::ServiceMapping::Enhanced,
    )
    .unwrap();
    peer.wait_for_node(Duration::from_secs(30)).await.unwrap();
    peer
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap()
}

/// A sample's CDR body sent as it is (RustDDS puts the `CDR_LE` header in front).
#[derive(Debug)]
struct RawCdr(Vec<u8>);

struct RawCdrAdapter;

impl rustdds::no_key::SerializerAdapter<RawCdr> for RawCdrAdapter {
    type Error = std::io::Error;
    fn output_encoding() -> rustdds::RepresentationIdentifier {
        rustdds::RepresentationIdentifier::CDR_LE
    }
    fn to_bytes(value: &RawCdr) -> Result<rustdds::bytes::Bytes, Self::Error> {
        Ok(rustdds::bytes::Bytes::copy_from_slice(&value.0))
    }
}

type RawWriter = rustdds::no_key::DataWriter<RawCdr, RawCdrAdapter>;

/// A writer of arbitrary bytes on one of the node's input topics (`rt/tof/...`).
fn raw_writer(ctx: &ros2_client::Context, topic: &str, ty: &str) -> RawWriter {
    let qos = rustdds::QosPolicies::from(
        &ros2_client::QosProfile::publisher_default().history(ros2_client::qos::History::KeepLast { depth: 64 }),
    );
    let dp = ctx.domain_participant();
    let t = dp
        .create_topic(
            format!("rt/tof/{topic}"),
            format!("sensor_msgs::msg::dds_::{ty}_"),
            &qos,
            rustdds::TopicKind::NoKey,
        )
        .unwrap();
    dp.create_publisher(&qos)
        .unwrap()
        .create_datawriter_no_key::<RawCdr, RawCdrAdapter>(&t, None)
        .unwrap()
}

/// Malformed CDR bodies made from a real message's: cut short, a sequence
/// length past the end, absurd lengths, nothing at all.
fn malformed_bodies(body: &[u8], data_len: usize) -> Vec<Vec<u8>> {
    // The last field of an Image is `data`: its u32 length, then the bytes.
    let len_at = body.len() - data_len - 4;
    let with_len = |v: u32| {
        let mut b = body.to_vec();
        b[len_at..len_at + 4].copy_from_slice(&v.to_le_bytes());
        b
    };
    let mut frame_id_len = body.to_vec();
    frame_id_len[8..12].copy_from_slice(&0x7fff_fff0u32.to_le_bytes());
    vec![
        body[..body.len() / 2].to_vec(),
        body[..6].to_vec(),
        with_len(data_len as u32 + 1000),
        with_len(u32::MAX),
        frame_id_len,
        Vec::new(),
    ]
}

#[test]
fn faults_are_dropped_counted_and_the_node_keeps_running() {
    if !isolated("faults_are_dropped_counted_and_the_node_keeps_running") {
        return;
    }
    let node = NodeChild::start(&["background_frames:=3", "xi:=0.65", "latch_timeout_s:=2"]);
    let (info, pairs, bg) = frames();
    let rt = rt();
    let clock = std::cell::Cell::new(1_000_000_000u64);
    let next = || {
        clock.set(clock.get() + 33_000_000);
        clock.get()
    };
    let pause = || std::thread::sleep(Duration::from_millis(60));
    rt.block_on(async {
        let ctx = translucent_tof::node::context(0, false).unwrap();
        let mut peer = driver(&ctx, "fault_peer").await;
        let (d0, i0) = &pairs[0];
        // 1. Frames before any camera_info: the depth is passed on as it came,
        //    with no cloud (no rays without the intrinsics).
        let mut early = vec![];
        for _ in 0..2 {
            let s = next();
            peer.publish_one(true, &stamped(d0, s)).unwrap();
            peer.publish_one(false, &stamped(i0, s)).unwrap();
            early.push(s);
            pause();
        }
        assert!(
            peer.wait_for(early[1], Duration::from_secs(10)).await,
            "no corrected depth before camera_info"
        );
        for s in &early {
            if let Some(c) = peer.received.corrected.get(s) {
                assert_eq!(c.data, stamped(d0, *s).data, "a frame before camera_info was changed");
            }
            assert!(!peer.received.points.contains_key(s), "a cloud without intrinsics");
        }
        // 2. A latch before camera_info waits for it, then (none coming) fails with the reason.
        let r = peer.call(true, Duration::from_secs(10)).await.unwrap();
        assert!(!r.success && r.message.contains("camera_info"), "{r:?}");
        peer.publish_info(&info).unwrap();
        pause();
        // 3. Frames before a background.
        for _ in 0..2 {
            let s = next();
            peer.publish(&info, &stamped(d0, s), &stamped(i0, s)).unwrap();
            pause();
        }
        // 4. Wrong encoding.
        let s = next();
        let mut bad = stamped(d0, s);
        bad.encoding = "rgb8".into();
        peer.publish(&info, &bad, &stamped(i0, s)).unwrap();
        pause();
        // 5. Depth and IR of different sizes.
        let s = next();
        let mut small = stamped(i0, s);
        small.width /= 2;
        small.step /= 2;
        small.data.truncate(small.data.len() / 2);
        peer.publish(&info, &stamped(d0, s), &small).unwrap();
        pause();
        // 6. Depth without IR, then a pair (the unpaired ones expire).
        for _ in 0..3 {
            peer.publish_one(true, &stamped(d0, next())).unwrap();
        }
        let s = next();
        peer.publish(&info, &stamped(d0, s), &stamped(i0, s)).unwrap();
        pause();
        // 7. Latch over background frames, streaming until the reply.
        let mut s7 = next();
        let reply = peer
            .latch_while_streaming(&info, &pairs[..bg], Duration::from_millis(40), &mut s7, 1_000)
            .await
            .unwrap();
        clock.set(s7);
        assert!(reply.success, "{reply:?}");
        assert!(reply.message.contains("latched 3 frames"), "{}", reply.message);
        // 8. Object frames come back recovered.
        let mut last = 0;
        for (d, i) in pairs.iter().skip(bg).take(4) {
            last = next();
            peer.publish(&info, &stamped(d, last), &stamped(i, last)).unwrap();
            pause();
        }
        assert!(
            peer.wait_for(last, Duration::from_secs(20)).await,
            "no output for the last frame"
        );
        // 9. A burst of malformed samples (raw bytes on the inputs' topics), and images
        //    larger than the camera, each dropped and counted; then frames come back again.
        let raw_ctx = translucent_tof::node::context(0, false).unwrap();
        let raw_depth = raw_writer(&raw_ctx, "depth/image_raw", "Image");
        let raw_info = raw_writer(&raw_ctx, "depth/camera_info", "CameraInfo");
        // Discovery of the new writers.
        tokio::time::sleep(Duration::from_secs(2)).await;
        let image_cdr = translucent_tof::msgs::to_cdr(d0).unwrap();
        let image_body = &image_cdr[4..];
        let info_body = translucent_tof::msgs::to_cdr(&info).unwrap()[4..].to_vec();
        let mut sent_malformed = 0;
        for _ in 0..4 {
            for body in malformed_bodies(image_body, d0.data.len()) {
                raw_depth.write(RawCdr(body), None).unwrap();
                sent_malformed += 1;
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            raw_info
                .write(RawCdr(info_body[..info_body.len() / 3].to_vec()), None)
                .unwrap();
            sent_malformed += 1;
        }
        let s = next();
        let mut wide = stamped(d0, s);
        wide.width *= 2;
        wide.height *= 2;
        wide.step *= 2;
        wide.data = vec![0; wide.data.len() * 4];
        peer.publish_one(true, &wide).unwrap();
        let mut padded = stamped(i0, s);
        padded.data.extend(std::iter::repeat_n(0, 100_000));
        peer.publish_one(false, &padded).unwrap();
        let mut absurd = stamped(d0, next());
        (absurd.width, absurd.height, absurd.step) = (u32::MAX, u32::MAX, u32::MAX);
        absurd.data.truncate(10);
        peer.publish_one(true, &absurd).unwrap();
        let mut vast_camera = info.clone();
        (vast_camera.width, vast_camera.height) = (100_000, 100_000);
        peer.publish_info(&vast_camera).unwrap();
        pause();
        for (d, i) in pairs.iter().skip(bg).take(4) {
            last = next();
            peer.publish(&info, &stamped(d, last), &stamped(i, last)).unwrap();
            pause();
        }
        assert!(
            peer.wait_for(last, Duration::from_secs(20)).await,
            "no output after the malformed burst"
        );
        eprintln!("sent {sent_malformed} malformed samples");
        // 10. Clear: frames are passed through uncorrected again, and a second clear says so.
        let r = peer.call(false, Duration::from_secs(10)).await.unwrap();
        assert!(r.success && r.message.contains("cleared"), "{r:?}");
        let s = next();
        peer.publish(&info, &stamped(d0, s), &stamped(i0, s)).unwrap();
        pause();
        let r = peer.call(false, Duration::from_secs(10)).await.unwrap();
        assert!(r.message.contains("no background"), "{r:?}");
    });
    let (st, log) = node.stop_with_log();
    eprintln!("{}", serde_json::to_string_pretty(&st).unwrap());
    let dropped = &st["dropped"];
    for cause in ["bad_image", "size_mismatch", "unpaired", "malformed", "oversized"] {
        assert!(
            dropped[cause].as_u64().unwrap_or(0) >= 1,
            "no {cause} drop counted: {dropped}"
        );
    }
    // Frames without a background are published as they came (`passthrough`), not dropped.
    assert_eq!(dropped["no_background"].as_u64(), None, "{dropped}");
    assert!(st["passed_through"]["no_background"].as_u64().unwrap() >= 3, "{st}");
    assert!(st["passed_through"]["no_camera_info"].as_u64().unwrap() >= 1, "{st}");
    assert_eq!(dropped["no_camera_info"].as_u64(), None, "{dropped}");
    assert!(dropped["unpaired"].as_u64().unwrap() >= 3);
    // 28 malformed samples went out best-effort on loopback; the oversized: a wide image, a
    // padded one, an absurd one and a camera_info of a 100000 x 100000 camera.
    let malformed = dropped["malformed"].as_u64().unwrap();
    assert!((14..=28).contains(&malformed), "{malformed} malformed of 28 sent");
    assert_eq!(dropped["oversized"].as_u64(), Some(4), "{dropped}");
    // Logged once per cause.
    for cause in ["Malformed", "Oversized"] {
        let lines = log
            .lines()
            .filter(|l| l.contains(&format!("further {cause} drops")))
            .count();
        assert_eq!(lines, 1, "{cause} logged {lines} times");
    }
    assert!(st["published"].as_u64().unwrap() >= 8);
    assert_eq!(st["services"], serde_json::json!([2, 2]));
}

/// `depth` as a camera pulled back by `mm` would read it (every valid pixel farther).
fn pulled_back(depth: &Image, mm: f32) -> Image {
    let mut d = depth.clone();
    match d.encoding.as_str() {
        "32FC1" => d.data.chunks_exact_mut(4).for_each(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v.is_finite() && v > 0.0 {
                c.copy_from_slice(&(v + mm / 1000.0).to_le_bytes());
            }
        }),
        _ => d.data.chunks_exact_mut(2).for_each(|c| {
            let v = u16::from_le_bytes([c[0], c[1]]);
            if v > 0 {
                c.copy_from_slice(&v.saturating_add(mm as u16).to_le_bytes());
            }
        }),
    }
    d
}

#[test]
fn a_camera_moved_after_the_latch_is_reported_passed_through_and_relatched() {
    if !isolated("a_camera_moved_after_the_latch_is_reported_passed_through_and_relatched") {
        return;
    }
    let node = NodeChild::start(&["background_frames:=3", "xi:=0.65", "relatch_on_move:=true"]);
    let (info, pairs, bg) = frames();
    let rt = rt();
    rt.block_on(async {
        let ctx = translucent_tof::node::context(0, false).unwrap();
        let mut peer = driver(&ctx, "moving_peer").await;
        let mut t = 7_000_000_000u64;
        let reply = peer
            .latch_while_streaming(&info, &pairs[..bg], Duration::from_millis(40), &mut t, 33_000_000)
            .await
            .unwrap();
        assert!(reply.success, "{reply:?}");
        // The camera is bumped 300 mm back and stays there: the empty scene, read farther.
        let (d0, i0) = &pairs[0];
        let moved = pulled_back(d0, 300.0);
        for _ in 0..20 {
            t += 33_000_000;
            peer.publish(&info, &stamped(&moved, t), &stamped(i0, t)).unwrap();
            tokio::time::sleep(Duration::from_millis(60)).await;
            peer.drain();
        }
        assert!(
            peer.wait_for_every(t, Duration::from_secs(20)).await,
            "no corrected depth, mask, sigma or camera_info for the last frame"
        );
        let c = &peer.received.corrected[&t];
        assert_eq!(c.data, stamped(&moved, t).data, "the relatched view was corrected");
        let m = &peer.received.mask[&t];
        assert!(m.data.iter().all(|&v| v == 0), "the relatched empty view is masked");
    });
    let (st, log) = node.stop_with_log();
    let passed = &st["passed_through"];
    assert!(passed["camera_moved"].as_u64().unwrap_or(0) >= 1, "{st}");
    // Relatched: the first latch's 3 frames and the second's.
    assert!(st["latched_frames"].as_u64().unwrap() >= 6, "{st}");
    let moved_lines = log
        .lines()
        .filter(|l| l.contains("the camera moved after the latch"))
        .count();
    assert_eq!(moved_lines, 1, "the move logged once:\n{log}");
    assert!(log.contains("relatch_on_move"), "{log}");
    assert!(!log.contains("[ERROR]"), "{log}");
}

/// `materials:=FILE` over DDS: the node reads a materials file written by `calibrate-xi`
/// (here from the rendered document holder's own frames, so the class is known) and every
/// `~/translucency` estimate carries a class among the file's materials, `opaque` and
/// `unknown`, with a probability; once the sheet's evidence is in, it is classed as the
/// file's material and recovered with its xi.
#[test]
fn the_node_classifies_objects_with_a_materials_file() {
    if !isolated("the_node_classifies_objects_with_a_materials_file") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("materials.toml");
    let rendered = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/rendered/paper_document_holder.mcap");
    let out = Command::new(exe())
        .arg("calibrate-xi")
        .arg(&rendered)
        .args(["--name", "holder", "-o"])
        .arg(&file)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let node = NodeChild::start(&["background_frames:=10", &format!("materials:={}", file.display())]);
    let (info, pairs) = bag_frames(&rendered).unwrap();
    let estimates = rt().block_on(async {
        let ctx = translucent_tof::node::context(0, false).unwrap();
        let mut peer = driver(&ctx, "materials_peer").await;
        latch_then_play(&mut peer, &info, &pairs, 10, Duration::from_secs(20)).await;
        tokio::time::sleep(Duration::from_millis(300)).await;
        peer.drain();
        peer.received.estimates.clone()
    });
    let (_, log) = node.stop_with_log();
    // Frames passed through before the latch carry no class (and say why in `method`).
    let estimates: Vec<_> = estimates
        .iter()
        .filter(|e| !e.method.starts_with("passthrough"))
        .collect();
    assert!(!estimates.is_empty(), "no estimate of a recovered frame");
    for e in &estimates {
        println!(
            "xi {:.3} [{:.3}, {:.3}] class {:?} p {:.3}",
            e.xi, e.xi_lower, e.xi_upper, e.material, e.class_probability
        );
        assert!(["holder", "opaque", "unknown"].contains(&e.material.as_str()), "{e:?}");
        assert!((0.0..=1.0).contains(&e.class_probability), "{e:?}");
    }
    let last = estimates.last().expect("an estimate");
    assert_eq!(last.material, "holder", "{last:?}");
    assert!(last.class_probability > 0.5, "{last:?}");
    assert!(!log.contains("[ERROR]"), "{log}");
}

#[test]
fn overload_drops_the_oldest_frames_and_memory_stays_bounded() {
    if !isolated("overload_drops_the_oldest_frames_and_memory_stays_bounded") {
        return;
    }
    // ξ estimated per frame: slower than the burst below.
    let node = NodeChild::start(&["background_frames:=3", "queue_depth:=2"]);
    let (info, pairs, bg) = frames();
    let rt = rt();
    let n_burst = 300u64;
    rt.block_on(async {
        let ctx = translucent_tof::node::context(0, false).unwrap();
        let mut peer = driver(&ctx, "load_peer").await;
        let mut t = 5_000_000_000u64;
        let reply = peer
            .latch_while_streaming(&info, &pairs[..bg], Duration::from_millis(40), &mut t, 1_000_000)
            .await
            .unwrap();
        assert!(reply.success, "{reply:?}");
        let objects = &pairs[bg..];
        for j in 0..n_burst {
            let (d, i) = &objects[j as usize % objects.len()];
            t += 1_000_000;
            peer.publish(&info, &stamped(d, t), &stamped(i, t)).unwrap();
            // Paced at ~1 ms: far above what the node processes per frame.
            tokio::time::sleep(Duration::from_millis(1)).await;
            peer.drain();
        }
        assert!(
            peer.wait_for(t, Duration::from_secs(30)).await,
            "the newest frame was not processed"
        );
    });
    let st = node.stop();
    eprintln!("{}", serde_json::to_string_pretty(&st).unwrap());
    let queue_full = st["dropped"]["queue_full"].as_u64().unwrap_or(0);
    let published = st["published"].as_u64().unwrap();
    assert!(queue_full > 0, "no frame dropped under overload: {st}");
    assert!(
        published < n_burst,
        "published {published} of a {n_burst} burst: no overload?"
    );
    assert!(published + queue_full <= st["pairs"].as_u64().unwrap());
}

#[test]
fn latency_bench_times_every_frame_of_the_bag_through_echo_and_node() {
    if !isolated("latency_bench_times_every_frame_of_the_bag_through_echo_and_node") {
        return;
    }
    let out = Command::new(exe())
        .args([
            "bench",
            "--cases",
            "node_latency",
            "--node-frames",
            "24",
            "--node-rate-hz",
            "20",
            // The node with its pool pinned (the default, unpinned, runs in the tests above).
            "--pin-threads",
            "--json",
            "-",
        ])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "bench failed: {stderr}");
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).expect("bench --json - prints JSON");
    let n = &r["node_latency"];
    eprintln!("{}", serde_json::to_string_pretty(n).unwrap());
    for side in ["bare", "node"] {
        assert_eq!(n[side]["sent"].as_u64(), Some(24), "{side}");
        assert!(n[side]["received"].as_u64().unwrap() >= 22, "{side}: {}", n[side]);
    }
    let pinned = n["node_stats"]["pinned_cpus"].as_array().expect("pinned_cpus");
    assert!(
        !pinned.is_empty(),
        "pin_threads left the pool unpinned: {}",
        n["node_stats"]
    );
    // The bundled document holder: two frames at each of 500, 750, 1000 and 1750 mm, so
    // the translucent share falls frame by frame pair, and 24 frames time each of them.
    let frames = n["frames"].as_array().expect("per-frame latencies");
    assert_eq!(frames.len(), 8);
    let shares: Vec<f64> = frames
        .iter()
        .map(|f| f["translucent_fraction"].as_f64().unwrap())
        .collect();
    assert!(shares[0] > 0.4 && shares[7] < 0.1, "{shares:?}");
    assert!(shares.windows(3).step_by(2).all(|w| w[2] < w[0]), "{shares:?}");
    for f in frames {
        let (b, t, a) = (
            f["bare_median_ms"].as_f64().unwrap(),
            f["node_median_ms"].as_f64().unwrap(),
            f["added_median_ms"].as_f64().unwrap(),
        );
        assert!(b > 0.0 && t > 0.0 && (t - b - a).abs() < 1e-9, "{f}");
    }
}

/// One frame's outputs, each message as its CDR bytes (NaN compared bit for bit).
#[derive(Debug, Default, PartialEq)]
struct Published {
    corrected: Option<Vec<u8>>,
    camera_info: Option<Vec<u8>>,
    sigma: Option<Vec<u8>>,
    mask: Option<Vec<u8>>,
    points: Option<Vec<u8>>,
    translucency: Vec<Vec<u8>>,
}

fn cdr<M: translucent_tof::msgs::RosMessage>(m: &M) -> Vec<u8> {
    translucent_tof::msgs::to_cdr(m).unwrap()
}

/// What replay's output bag holds, by input stamp (its `regions`, replay's own, left out).
fn replayed(out_bag: &Path) -> std::collections::BTreeMap<u64, Published> {
    use translucent_tof::msgs::translucent_tof::TranslucencyEstimate;
    let mut by_stamp: std::collections::BTreeMap<u64, Published> = Default::default();
    for raw in BagReader::open(out_bag).unwrap().messages() {
        let raw = raw.unwrap();
        let p = by_stamp.entry(raw.log_time_ns).or_default();
        match raw.topic {
            "/translucent_tof/depth/corrected" => p.corrected = Some(cdr(&BagReader::decode::<Image>(&raw).unwrap())),
            "/translucent_tof/depth/camera_info" => {
                p.camera_info = Some(cdr(&BagReader::decode::<CameraInfo>(&raw).unwrap()))
            }
            "/translucent_tof/depth/corrected_sigma" => p.sigma = Some(cdr(&BagReader::decode::<Image>(&raw).unwrap())),
            "/translucent_tof/translucent_mask" => p.mask = Some(cdr(&BagReader::decode::<Image>(&raw).unwrap())),
            "/translucent_tof/points" => p.points = Some(cdr(&BagReader::decode::<PointCloud2>(&raw).unwrap())),
            "/translucent_tof/translucency" => p
                .translucency
                .push(cdr(&BagReader::decode::<TranslucencyEstimate>(&raw).unwrap())),
            "/translucent_tof/regions" => {}
            other => panic!("replay wrote an unexpected topic {other}"),
        }
    }
    by_stamp
}

/// What the node published for the frame at `stamp`, as the peer received it.
fn node_published(r: &translucent_tof::node::peer::Received, stamp: u64) -> Published {
    Published {
        corrected: r.corrected.get(&stamp).map(cdr),
        camera_info: r.camera_info.get(&stamp).map(cdr),
        sigma: r.sigma.get(&stamp).map(cdr),
        mask: r.mask.get(&stamp).map(cdr),
        points: r.points.get(&stamp).map(cdr),
        translucency: r
            .estimates
            .iter()
            .filter(|e| e.header.stamp.as_log_time_ns() == stamp)
            .map(cdr)
            .collect(),
    }
}

/// Where two frames' outputs differ, topic by topic (empty when they are the same).
fn differences(node: &Published, replay: &Published) -> Vec<String> {
    let mut out = vec![];
    let mut topic = |name: &str, a: &Option<Vec<u8>>, b: &Option<Vec<u8>>| {
        if a != b {
            let bytes = |v: &Option<Vec<u8>>| v.as_ref().map(|v| v.len());
            let first = a
                .iter()
                .zip(b)
                .find_map(|(a, b)| a.iter().zip(b).position(|(x, y)| x != y));
            out.push(format!(
                "{name}: node {:?} bytes, replay {:?} bytes, first differing byte {first:?}",
                bytes(a),
                bytes(b)
            ));
        }
    };
    topic("depth/corrected", &node.corrected, &replay.corrected);
    topic("depth/camera_info", &node.camera_info, &replay.camera_info);
    topic("depth/corrected_sigma", &node.sigma, &replay.sigma);
    topic("translucent_mask", &node.mask, &replay.mask);
    topic("points", &node.points, &replay.points);
    if node.translucency != replay.translucency {
        out.push(format!(
            "translucency: node {} estimates, replay {}",
            node.translucency.len(),
            replay.translucency.len()
        ));
    }
    out
}

/// The pixels an input depth image marks invalid (0 in 16UC1, NaN in 32FC1).
fn invalid_pixels(depth: &Image) -> Vec<usize> {
    let z = depth_mm(depth).unwrap();
    (0..z.len()).filter(|&i| !z.data[i].is_finite()).collect()
}

/// None of `invalid` is published as a distance: the corrected depth invalid there, the
/// cloud's point NaN.
fn invalid_kept_invalid(corrected: &Image, points: &PointCloud2, invalid: &[usize]) -> Result<(), String> {
    let z = depth_mm(corrected).unwrap();
    let step = points.point_step as usize;
    let cloud_z = |k: usize| f32::from_le_bytes(points.data[k * step + 8..k * step + 12].try_into().unwrap());
    match invalid
        .iter()
        .find(|&&k| z.data[k].is_finite() || cloud_z(k).is_finite())
    {
        Some(&k) => Err(format!(
            "invalid input pixel {k} published as {} mm, cloud z {} m",
            z.data[k],
            cloud_z(k)
        )),
        None => Ok(()),
    }
}

/// Issue 53: replay's output bag holds what the node publishes, frame by frame. A committed
/// Azure-Kinect-like bag (a static stretch, a translucent sheet at two distances, the wall
/// again; invalid (0) pixels in every frame) goes through `replay --xi-mode online` (the
/// node's way of estimating xi) and through the node over DDS, whose latch takes the frames
/// replay latched. The outputs are paired by input stamp: a frame the node did not publish is
/// counted, not compared (and, its xi evidence missing from the node, neither is any after
/// it); every other frame's every topic the node publishes is compared byte for byte.
#[test]
fn replay_writes_what_the_node_publishes_frame_by_frame() {
    if !isolated("replay_writes_what_the_node_publishes_frame_by_frame") {
        return;
    }
    let input = bag("azure_like_object.mcap");
    let dir = tempfile::tempdir().unwrap();
    let out_bag = dir.path().join("replay.mcap");
    let out = Command::new(exe())
        .arg("replay")
        .arg(&input)
        .args(["--xi-mode", "online", "--physics", "physical", "--json", "-", "-o"])
        .arg(&out_bag)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let latched = report["background_frames"].as_u64().unwrap() as usize;
    let replay = replayed(&out_bag);
    let (info, pairs) = bag_frames(&input).unwrap();
    assert_eq!(
        replay.len(),
        pairs.len(),
        "replay wrote {} of {} frames",
        replay.len(),
        pairs.len()
    );

    let background_frames = format!("background_frames:={latched}");
    let node = NodeChild::start(&[&background_frames, "queue_depth:=64", "latch_timeout_s:=60"]);
    let with_header = |d: &Image| CameraInfo {
        header: d.header.clone(),
        ..info.clone()
    };
    let (received, missing) = rt().block_on(async {
        let ctx = translucent_tof::node::context(0, false).unwrap();
        let mut peer = driver(&ctx, "replay_peer").await;
        peer.wait_for_every_output(Duration::from_secs(30)).await.unwrap();
        peer.publish_info(&info).unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        // The latch asked for first; the frames replay latched stream once the node has
        // taken the request (a request that comes after them would latch none of them).
        let stream = async {
            assert!(
                node.logged("latch requested", Duration::from_secs(60)).await,
                "the node did not log the latch request within 60 s"
            );
            for (d, i) in &pairs[..latched] {
                peer.publish(&with_header(d), d, i).unwrap();
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        };
        let (reply, ()) = tokio::join!(peer.call(true, Duration::from_secs(60)), stream);
        // The latch itself is what this test needs; a reply lost on DDS (the node's reply
        // writer not yet matched with this client's reader) is said, not failed on.
        let done = format!("latched {latched} frames");
        match reply {
            Ok(reply) => assert!(reply.success && reply.message.contains(&done), "{reply:?}"),
            Err(e) => {
                assert!(
                    node.logged(&done, Duration::from_secs(1)).await,
                    "no latch reply ({e}) and the node's log does not say {done:?}"
                );
                eprintln!("the latch's reply did not arrive ({e}); the node's log says {done:?}");
            }
        }
        // Each object frame once the last has come back: no queue to overflow.
        let mut missing = vec![];
        for (d, i) in &pairs[latched..] {
            peer.publish(&with_header(d), d, i).unwrap();
            let stamp = d.header.stamp.as_log_time_ns();
            if !peer.wait_for(stamp, Duration::from_secs(20)).await {
                missing.push(stamp);
            }
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        peer.drain();
        (std::mem::take(&mut peer.received), missing)
    });
    let stats = node.stop();
    eprintln!("node: {}", serde_json::to_string(&stats).unwrap());

    let (mut compared, mut dropped, mut after_drop, mut recovered) = (0, 0, 0, 0);
    let mut mismatches = vec![];
    for (d, _) in &pairs {
        let stamp = d.header.stamp.as_log_time_ns();
        let from_node = node_published(&received, stamp);
        if from_node.corrected.is_none() {
            dropped += 1;
            continue;
        }
        if dropped > 0 {
            after_drop += 1;
            continue;
        }
        let from_replay = replay.get(&stamp).expect("replay wrote every frame");
        for diff in differences(&from_node, from_replay) {
            mismatches.push(format!("frame at {stamp}: {diff}"));
        }
        // Neither publishes an invalid input pixel as a distance.
        let invalid = invalid_pixels(d);
        assert!(
            !invalid.is_empty(),
            "the bag's frame at {stamp} has no invalid pixel to check"
        );
        let corrected = &received.corrected[&stamp];
        let points = received.points.get(&stamp).expect("a cloud beside the corrected depth");
        if let Err(e) = invalid_kept_invalid(corrected, points, &invalid) {
            mismatches.push(format!("frame at {stamp}, node: {e}"));
        }
        let (c, p) = (from_replay.corrected.as_ref(), from_replay.points.as_ref());
        let (c, p): (Image, PointCloud2) = (
            translucent_tof::msgs::from_cdr(c.unwrap()).unwrap(),
            translucent_tof::msgs::from_cdr(p.unwrap()).unwrap(),
        );
        if let Err(e) = invalid_kept_invalid(&c, &p, &invalid) {
            mismatches.push(format!("frame at {stamp}, replay: {e}"));
        }
        recovered += usize::from(received.mask[&stamp].data.contains(&255));
        compared += 1;
    }
    eprintln!(
        "{compared} frames compared ({recovered} with translucent pixels), {dropped} not published by the node (stamps {missing:?}), {after_drop} after a drop not compared"
    );
    assert!(
        mismatches.is_empty(),
        "{} differences:\n{}",
        mismatches.len(),
        mismatches.join("\n")
    );
    // Enough compared to say something: every latched frame and the sheet recovered.
    assert!(
        compared >= latched + 4 && recovered >= 3,
        "{compared} compared, {recovered} recovered"
    );
    assert!(
        dropped * 10 <= pairs.len(),
        "the node dropped {dropped} of {} frames",
        pairs.len()
    );
}

/// The document holder through a Kinect v2 depth engine (`simulate --depth-engine
/// kinect_v2`, the default physics), played to a node told the same engine by its
/// parameters: it names the engine at start-up, publishes every frame, and recovers the
/// layer. Over the pixels in its mask with a true depth, the corrected depth's RMS error
/// is at most a quarter of the reading's (issue 47's every-pixel target; replay recovers
/// this scene at about 1 mm against 63 raw: `scripts/depth-engine`).
#[test]
fn the_node_recovers_through_a_depth_engine_given_by_its_parameters() {
    if !isolated("the_node_recovers_through_a_depth_engine_given_by_its_parameters") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = std::fs::read_to_string(bag("document_holder.toml")).unwrap().replacen(
        "[background]",
        "[physics]\nir_mode = \"amplitude\"\ntransmission_albedo_power = 0.0\n\n[background]",
        1,
    );
    let (toml, recording) = (dir.path().join("scene.toml"), dir.path().join("engine.mcap"));
    std::fs::write(&toml, scene).unwrap();
    let out = Command::new(exe())
        .arg("simulate")
        .arg(&toml)
        .args(["--depth-engine", "kinect_v2", "-o"])
        .arg(&recording)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let truth = ground_truth_mm(&recording);
    let (info, pairs) = bag_frames(&recording).unwrap();
    let node = NodeChild::start(&["depth_engine:=kinect_v2", "xi:=0.65", "background_frames:=10"]);
    let frames = 4;
    let received = rt().block_on(async {
        let ctx = translucent_tof::node::context(0, false).unwrap();
        let mut peer = driver(&ctx, "engine_peer").await;
        let sent = latch_then_play(&mut peer, &info, &pairs[..10 + frames], 10, Duration::from_secs(60)).await;
        peer.drain();
        (sent, peer.received.corrected.clone(), peer.received.mask.clone())
    });
    let (_, log) = node.stop_with_log();
    assert!(
        log.contains("depth engine: depth and IR unwrapped from [80000000.0, 16000000.0, 120000000.0] Hz"),
        "{log}"
    );
    assert!(!log.contains("[ERROR]"), "{log}");
    let (sent, corrected, mask) = received;
    let (mut sq, mut sq_raw, mut n) = (0.0f64, 0.0f64, 0usize);
    for (t, (raw, _)) in sent.iter().zip(&pairs[10..]) {
        let original = raw.header.stamp.as_log_time_ns();
        let (Some(c), Some(m), Some(z)) = (corrected.get(t), mask.get(t), truth.get(&original)) else {
            panic!("frame {t}: an output or the truth missing");
        };
        let (c, r) = (depth_mm(c).unwrap(), depth_mm(raw).unwrap());
        for (k, &on) in m.data.iter().enumerate() {
            let (zc, zr, zt) = (c.data[k], r.data[k], z[k]);
            if on != 0 && zt.is_finite() && zc.is_finite() && zr.is_finite() {
                sq += f64::from(zc - zt).powi(2);
                sq_raw += f64::from(zr - zt).powi(2);
                n += 1;
            }
        }
    }
    assert!(n > 1000, "only {n} pixels in the mask with a true depth");
    let (rms, rms_raw) = ((sq / n as f64).sqrt(), (sq_raw / n as f64).sqrt());
    println!("{n} pixels: raw {rms_raw:.1} mm -> corrected {rms:.1} mm");
    assert!(
        rms <= 0.25 * rms_raw,
        "corrected {rms:.1} mm against raw {rms_raw:.1} mm"
    );
}

/// Latches the first `background` of `pairs` while streaming them, then plays the rest one
/// at a time, 100 ms apart, each waited for (up to `wait`) before the next: the stamps sent.
async fn latch_then_play(
    peer: &mut Peer,
    info: &CameraInfo,
    pairs: &[(Image, Image)],
    background: usize,
    wait: Duration,
) -> Vec<u64> {
    // The mask and sigma are read beside the corrected depth: their readers must have
    // matched the node's writers before the first frame, or a loaded machine loses its mask.
    peer.wait_for_every_output(Duration::from_secs(30)).await.unwrap();
    let mut t = 3_000_000_000u64;
    let reply = peer
        .latch_while_streaming(
            info,
            &pairs[..background],
            Duration::from_millis(40),
            &mut t,
            33_000_000,
        )
        .await
        .unwrap();
    assert!(reply.success, "{reply:?}");
    let mut sent = vec![];
    for (d, i) in &pairs[background..] {
        t += 100_000_000;
        peer.publish(info, &stamped(d, t), &stamped(i, t)).unwrap();
        assert!(
            peer.wait_for_every(t, wait).await,
            "no corrected depth, mask, sigma or camera_info at {t}"
        );
        sent.push(t);
    }
    sent
}

/// A simulated bag's `ground_truth/depth` (z, mm; NaN where there is none) by the stamp of
/// the depth image it belongs to.
fn ground_truth_mm(path: &Path) -> std::collections::BTreeMap<u64, Vec<f32>> {
    let reader = BagReader::open(path).unwrap();
    let mut out = std::collections::BTreeMap::new();
    for raw in reader.messages() {
        let raw = raw.unwrap();
        if raw.topic.ends_with("ground_truth/depth") {
            let m: Image = BagReader::decode(&raw).unwrap();
            let z = depth_mm(&m).unwrap();
            out.insert(m.header.stamp.as_log_time_ns(), z.data);
        }
    }
    out
}
