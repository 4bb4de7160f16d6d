//! A lens with strong distortion, end to end: the simulator renders through
//! it and writes it into the bag's camera_info; `replay` undoes it per pixel,
//! so the layer recovers as well in the image corners as in the centre. The
//! same bag with its camera_info's distortion dropped (pinhole rays) recovers
//! measurably worse in the corners.
//!
//! Every figure asserted is printed (`cargo test --test distorted_lens -- --nocapture`).

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use translucent_tof::bag::{BagReader, BagWriter};
use translucent_tof::image::{depth_mm, ir_counts};
use translucent_tof::msgs::{CameraInfo, Image};
use translucent_tof::physics::ImageBuf;

/// Barrel distortion as a cheap wide lens has it (plumb_bob k1 = -0.3, k2 = 0.1),
/// a white wall at 2 m and a translucent sheet filling the view at three distances.
const SCENE: &str = r#"
name = "barrel lens"
seed = 2701
[camera]
distortion_model = "plumb_bob"
distortion = [-0.3, 0.1, 0.0, 0.0, 0.0]
[emitter]
vignetting = 0.0
[noise]
depth_noise_mm = 2.0
[background]
distance_mm = 2000
frames = 10
[[stage]]
frames = 2
[[stage.objects]]
shape = "plane"
center_mm = [0, 0, 750]
size_mm = [1600, 1300]
xi = 0.65
albedo = 0.6
[[stage]]
frames = 2
[[stage.objects]]
shape = "plane"
center_mm = [0, 0, 1000]
size_mm = [1600, 1300]
tilt_y_deg = 5.0
xi = 0.65
albedo = 0.6
[[stage]]
frames = 2
[[stage.objects]]
shape = "plane"
center_mm = [0, 0, 1250]
size_mm = [1600, 1300]
tilt_x_deg = -4.0
xi = 0.65
albedo = 0.6
"#;

fn run(dir: &Path, args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("running translucent_tof");
    assert!(
        out.status.success(),
        "{args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Images of a topic by log time.
fn images(bag: &Path, topic: &str) -> BTreeMap<u64, Image> {
    let r = BagReader::open(bag).expect("bag");
    r.messages()
        .map(|m| m.expect("message"))
        .filter(|m| m.topic == topic)
        .map(|m| (m.log_time_ns, BagReader::decode(&m).expect("image")))
        .collect()
}

fn camera_info(bag: &Path) -> CameraInfo {
    let r = BagReader::open(bag).expect("bag");
    let m = r
        .messages()
        .map(|m| m.expect("message"))
        .find(|m| m.topic == "/tof/depth/camera_info");
    BagReader::decode(&m.expect("a camera_info")).expect("camera_info")
}

/// The bag with its camera_info's distortion dropped (all else as it was).
fn without_distortion(bag: &Path, out: &Path) {
    let r = BagReader::open(bag).expect("bag");
    let mut w = BagWriter::create(out).expect("bag");
    for m in r.messages() {
        let m = m.expect("message");
        if m.topic.ends_with("camera_info") {
            let mut ci: CameraInfo = BagReader::decode(&m).expect("camera_info");
            ci.d = vec![0.0; 5];
            w.write(m.topic, m.log_time_ns, &ci).expect("write");
        } else {
            let img: Image = BagReader::decode(&m).expect("image");
            w.write(m.topic, m.log_time_ns, &img).expect("write");
        }
    }
    w.finish().expect("finish");
}

/// RMS error (mm, z) of the recovered layer over its translucent pixels with
/// truth, in the corners (beyond 80 % of the half-diagonal) and the centre
/// (within 30 %), over every recovered frame; with the pixel counts.
fn corner_and_centre_rms(input: &Path, recovered: &Path) -> ([f64; 2], [usize; 2]) {
    let truth = images(input, "/tof/ground_truth/depth");
    let corrected = images(recovered, "/translucent_tof/depth/corrected");
    let masks = images(recovered, "/translucent_tof/translucent_mask");
    assert!(!corrected.is_empty(), "nothing recovered");
    let (mut sum, mut n) = ([0.0; 2], [0usize; 2]);
    for (t, img) in &corrected {
        let z = depth_mm(img).expect("depth");
        let truth = depth_mm(&truth[t]).expect("truth");
        let mask: ImageBuf<f32> = ir_counts(&masks[t]).expect("mask");
        let (cx, cy) = ((z.width as f64 - 1.0) / 2.0, (z.height as f64 - 1.0) / 2.0);
        for (i, (&zr, &zt)) in z.data.iter().zip(&truth.data).enumerate() {
            if !(mask.data[i] > 0.0 && zr.is_finite() && zt.is_finite()) {
                continue;
            }
            let (c, r) = ((i % z.width) as f64, (i / z.width) as f64);
            let rho = ((c - cx) / cx).hypot((r - cy) / cy) / 2f64.sqrt();
            let e2 = f64::from(zr - zt).powi(2);
            let region = if rho > 0.8 {
                0
            } else if rho < 0.3 {
                1
            } else {
                continue;
            };
            sum[region] += e2;
            n[region] += 1;
        }
    }
    ([0, 1].map(|k| (sum[k] / n[k] as f64).sqrt()), n)
}

#[test]
fn a_distorted_lens_recovers_in_the_corners_as_in_the_centre() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    std::fs::write(d.join("scene.toml"), SCENE).expect("scene");
    run(d, &["simulate", "scene.toml", "-o", "lens.mcap"]);
    let ci = camera_info(&d.join("lens.mcap"));
    assert_eq!(
        (ci.distortion_model.as_str(), ci.d.as_slice()),
        ("plumb_bob", &[-0.3, 0.1, 0.0, 0.0, 0.0][..]),
        "the bag's camera_info must carry the lens"
    );
    without_distortion(&d.join("lens.mcap"), &d.join("pinhole.mcap"));
    for (bag, out) in [("lens.mcap", "lens.rec.mcap"), ("pinhole.mcap", "pinhole.rec.mcap")] {
        run(d, &["replay", bag, "--physics", "paper", "--out", out]);
    }
    let ([corner, centre], n) = corner_and_centre_rms(&d.join("lens.mcap"), &d.join("lens.rec.mcap"));
    let ([pin_corner, pin_centre], pn) = corner_and_centre_rms(&d.join("pinhole.mcap"), &d.join("pinhole.rec.mcap"));
    println!(
        "barrel lens (plumb_bob k1 -0.3, k2 0.1), RMS of the recovered layer's z:\n  \
         distortion undone:  corners {corner:.2} mm ({} px), centre {centre:.2} mm ({} px)\n  \
         distortion ignored: corners {pin_corner:.2} mm ({} px), centre {pin_centre:.2} mm ({} px)",
        n[0], n[1], pn[0], pn[1]
    );
    assert!(n[0] > 500 && n[1] > 500, "too few pixels: {n:?}");
    assert!(
        corner <= 1.5 * centre,
        "with the lens undone the corners ({corner:.2} mm) should recover about as well as the centre ({centre:.2} mm)"
    );
    assert!(
        pin_corner > 3.0 * corner,
        "pinhole rays should be measurably worse in the corners: {pin_corner:.2} vs {corner:.2} mm"
    );
}

/// A camera_info whose lens folds back inside the image (barrel k1 = -2.5:
/// the outer pixels have no ray) is usable where it has rays: the pipeline
/// runs over it without a panic, and the pixels without a ray are never
/// taken as translucent.
#[test]
fn pixels_without_a_ray_are_left_alone() {
    use translucent_tof::physics::camera::Distortion;
    use translucent_tof::physics::Intrinsics;
    use translucent_tof::pipeline::{DepthFrame, Pipeline, PipelineConfig};
    use translucent_tof::sim::{render_all, Scene};

    let pinhole = SCENE
        .replace("distortion_model = \"plumb_bob\"\n", "")
        .replace("distortion = [-0.3, 0.1, 0.0, 0.0, 0.0]\n", "");
    let scene = Scene::from_toml(&pinhole, "pinhole");
    let frames = render_all(&scene.expect("scene"));
    let k = Intrinsics::sr4000().with_distortion(Distortion::PlumbBob([-2.5, 0.0, 0.0, 0.0, 0.0]));
    let rayless: Vec<usize> = (0..k.width * k.height)
        .filter(|&i| !k.ray(i % k.width, i / k.width).x.is_finite())
        .collect();
    assert!(rayless.len() > 1000, "{} pixels without a ray", rayless.len());
    let df = |f: &translucent_tof::sim::SimFrame| DepthFrame {
        stamp_ns: f.stamp_ns,
        z_mm: f.depth_z_mm.clone(),
        ir: f.ir.clone(),
    };
    let background: Vec<DepthFrame> = frames.iter().filter(|f| f.background_only).map(df).collect();
    let mut pipe = Pipeline::latched(PipelineConfig::default(), k, &background).expect("latched");
    let mut recovered = 0;
    for f in frames.iter().filter(|f| !f.background_only) {
        let mut obs = pipe.observe(&df(f)).expect("observed");
        assert!(rayless.iter().all(|&i| !obs.mask.data[i]));
        pipe.add_xi_evidence(&mut obs);
        if let Some(out) = pipe.recover_regions(&df(f), &obs) {
            assert!(rayless.iter().all(|&i| !out.mask.data[i]));
            recovered += 1;
        }
    }
    println!(
        "{} pixels without a ray; {recovered} frames recovered around them",
        rayless.len()
    );
    assert!(recovered > 0);
}
