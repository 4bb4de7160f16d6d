//! Scene files (`SCENE.toml`): a camera, a background plane, and stages of
//! translucent objects, rendered by [`super::render`].

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::physics::camera::{Distortion, DistortionError};
use crate::physics::{DepthEngine, ModelOptions};

/// What is wrong with a scene file.
#[derive(Debug, Error)]
pub enum SceneError {
    /// The TOML did not parse into a scene.
    #[error("{path}")]
    Parse {
        /// The file.
        path: String,
        /// What the parser said.
        source: toml::de::Error,
    },
    /// A value is out of its range.
    #[error("{path}: {what}")]
    Invalid {
        /// The file.
        path: String,
        /// Which value and why.
        what: String,
    },
    /// The file could not be read.
    #[error("{path}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
}

/// A whole scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// A label.
    #[serde(default)]
    pub name: String,
    /// Seed of the noise.
    #[serde(default)]
    pub seed: u64,
    /// The camera.
    #[serde(default)]
    pub camera: CameraSpec,
    /// The illumination.
    #[serde(default)]
    pub emitter: EmitterSpec,
    /// The noise.
    #[serde(default)]
    pub noise: NoiseSpec,
    /// The physics that renders the truth (the forward model's options).
    #[serde(default)]
    pub physics: ModelOptions,
    /// The opaque background.
    pub background: BackgroundSpec,
    /// Object stages, rendered after the background frames, in order.
    #[serde(default, rename = "stage")]
    pub stages: Vec<StageSpec>,
}

/// The ToF camera (SR4000 by default).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraSpec {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
    /// Vertical field of view, degrees.
    pub vfov_deg: f64,
    /// Modulation frequency, Hz.
    pub modulation_frequency_hz: f64,
    /// A multi-frequency camera's modulation frequencies, Hz (empty: none).
    /// Each gets a `32FC2` phasor image `phasor_<k>/image_raw` beside the
    /// depth and IR (which stay at `modulation_frequency_hz`).
    pub modulation_frequencies_hz: Vec<f64>,
    /// A camera that unwraps its depth from several frequencies (issue 51):
    /// its depth engine, whose depth and IR the depth and IR images are
    /// (`[camera.depth_engine]`, as in a physics file; none by default).
    pub depth_engine: Option<DepthEngine>,
    /// `sinusoid`, `triangle` or `harmonics`.
    pub waveform: String,
    /// Relative 3rd and 5th harmonic amplitudes when `waveform = "harmonics"`.
    pub harmonics: [f64; 2],
    /// Frames per second.
    pub frame_rate_hz: f64,
    /// `16UC1` (mm) or `32FC1` (m).
    pub depth_encoding: String,
    /// `16UC1`, `mono16`, `mono8` or `32FC1`.
    pub ir_encoding: String,
    /// Frame id of the images.
    pub frame_id: String,
    /// Namespace of the topics.
    pub namespace: String,
    /// Stamp of the first frame, seconds.
    pub start_time_s: f64,
    /// Sub-rays per pixel side (1: one ray through the centre). More mix the
    /// returns of surfaces a pixel straddles at edges ("flying pixels").
    pub supersample: usize,
    /// Lens distortion model as camera_info names it: `plumb_bob`,
    /// `rational_polynomial` or `equidistant` ("": none). The fields of view
    /// set K as for a pinhole; the lens then bends each pixel's ray.
    pub distortion_model: String,
    /// Its coefficients in ROS's order (empty: none).
    pub distortion: Vec<f64>,
    /// Pixels farther from the image centre than this share of its half-diagonal read
    /// invalid (0 in `16UC1`, NaN in `32FC1`), as the corners a camera with a round or
    /// hexagonal illuminated field leaves (an Azure Kinect's); 0: none.
    pub invalid_beyond_radius: f64,
    /// The share of the other pixels read invalid in each frame, drawn at random (the
    /// pixels a camera invalidates for multipath or too little light); 0: none.
    pub invalid_share: f64,
    /// Sensor effects past the model (stray light, saturation, a nonlinear amplitude
    /// response, a drifting phase offset); all off by default.
    pub artefacts: super::artefacts::Artefacts,
}

impl CameraSpec {
    /// The lens the scene asks for.
    pub fn lens(&self) -> Result<Distortion, DistortionError> {
        Distortion::from_ros(&self.distortion_model, &self.distortion)
    }
}

impl Default for CameraSpec {
    fn default() -> Self {
        Self {
            width: 176,
            height: 144,
            hfov_deg: 44.0,
            vfov_deg: 35.0,
            modulation_frequency_hz: 30.0e6,
            modulation_frequencies_hz: vec![],
            depth_engine: None,
            waveform: "sinusoid".into(),
            harmonics: [0.0, 0.0],
            frame_rate_hz: 10.0,
            depth_encoding: "16UC1".into(),
            ir_encoding: "16UC1".into(),
            frame_id: "tof_optical_frame".into(),
            namespace: "/tof".into(),
            start_time_s: 1_700_000_000.0,
            supersample: 1,
            distortion_model: String::new(),
            distortion: vec![],
            invalid_beyond_radius: 0.0,
            invalid_share: 0.0,
            artefacts: super::artefacts::Artefacts::default(),
        }
    }
}

/// The emitted light `Lin`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EmitterSpec {
    /// `Lin` on the optical axis, counts mm^2 (a white wall at d reads `Lin / d^2`).
    pub peak_emitted_light: f64,
    /// Fraction by which `Lin` falls at the image corners (radial, quadratic).
    pub vignetting: f64,
}

impl Default for EmitterSpec {
    fn default() -> Self {
        Self {
            peak_emitted_light: 1.5e10,
            vignetting: 0.3,
        }
    }
}

/// Shot noise, set by the depth noise at a reference wall.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NoiseSpec {
    /// Depth noise (1 sigma, mm) of an opaque wall at the reference, on the axis.
    pub depth_noise_mm: f64,
    /// The reference wall's distance, mm.
    pub reference_distance_mm: f64,
    /// The reference wall's albedo.
    pub reference_albedo: f64,
    /// Read noise, counts of equivalent light.
    pub read_noise: f64,
}

impl Default for NoiseSpec {
    fn default() -> Self {
        Self {
            depth_noise_mm: 10.0,
            reference_distance_mm: 2000.0,
            reference_albedo: 1.0,
            read_noise: 0.0,
        }
    }
}

/// The opaque background plane.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundSpec {
    /// Distance along the optical axis, mm.
    pub distance_mm: f64,
    /// Albedo, 0..1.
    #[serde(default = "one")]
    pub albedo: f64,
    /// Rotation about the camera's x axis, degrees.
    #[serde(default)]
    pub tilt_x_deg: f64,
    /// Rotation about the camera's y axis, degrees.
    #[serde(default)]
    pub tilt_y_deg: f64,
    /// Frames of the background alone, before the objects.
    #[serde(default = "ten")]
    pub frames: usize,
}

fn one() -> f64 {
    1.0
}
fn ten() -> usize {
    10
}

/// A group of frames with the same objects in place.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageSpec {
    /// Frames in this stage.
    #[serde(default = "one_usize")]
    pub frames: usize,
    /// The translucent objects.
    #[serde(default)]
    pub objects: Vec<ObjectSpec>,
}

fn one_usize() -> usize {
    1
}

/// A translucent object.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectSpec {
    /// `plane` (a rectangle) or `cylinder` (axis along the camera's y).
    pub shape: String,
    /// Centre in the camera's optical frame (x right, y down, z forward), mm.
    pub center_mm: [f64; 3],
    /// Plane: width and height, mm.
    #[serde(default)]
    pub size_mm: [f64; 2],
    /// Plane: rotation about the camera's x axis, degrees.
    #[serde(default)]
    pub tilt_x_deg: f64,
    /// Plane: rotation about the camera's y axis, degrees.
    #[serde(default)]
    pub tilt_y_deg: f64,
    /// Cylinder: radius, mm.
    #[serde(default)]
    pub radius_mm: f64,
    /// Cylinder: height along y, mm.
    #[serde(default)]
    pub height_mm: f64,
    /// Translucency ξ.
    pub xi: f64,
    /// Albedo `rho_f`.
    pub albedo: f64,
}

impl Scene {
    /// Parses and validates a scene; `path` names the source in errors.
    pub fn from_toml(text: &str, path: &str) -> Result<Self, SceneError> {
        let scene: Scene = toml::from_str(text).map_err(|source| SceneError::Parse {
            path: path.into(),
            source,
        })?;
        scene.validate().map_err(|what| SceneError::Invalid {
            path: path.into(),
            what,
        })?;
        Ok(scene)
    }

    /// Reads a scene file.
    pub fn load(path: &std::path::Path) -> Result<Self, SceneError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: p.clone(),
            source,
        })?;
        Self::from_toml(&text, &p)
    }

    /// Checks every value's range; the error names the value.
    pub fn validate(&self) -> Result<(), String> {
        let c = &self.camera;
        let pos = |v: f64| v.is_finite() && v > 0.0;
        if c.width == 0 || c.height == 0 || c.width * c.height > 4096 * 4096 {
            return Err(format!("camera size {}x{} is not usable", c.width, c.height));
        }
        if !(c.hfov_deg > 0.0 && c.hfov_deg < 170.0 && c.vfov_deg > 0.0 && c.vfov_deg < 170.0) {
            return Err("camera field of view must be in (0, 170) degrees".into());
        }
        c.lens().map_err(|e| format!("camera: {e}"))?;
        if let Some((col, row)) = pixel_without_ray(&super::render::scene_intrinsics(self)) {
            return Err(format!(
                "camera: the lens model has no ray through pixel ({col}, {row}): its distortion folds back within the field of view"
            ));
        }
        if !(c.invalid_beyond_radius >= 0.0 && (0.0..1.0).contains(&c.invalid_share)) {
            return Err("camera: invalid_beyond_radius >= 0 and invalid_share in [0, 1) required".into());
        }
        c.artefacts.validate()?;
        if !(1..=8).contains(&c.supersample) {
            return Err(format!("camera.supersample {} must be in 1..=8", c.supersample));
        }
        if !pos(c.modulation_frequency_hz) || !pos(c.frame_rate_hz) {
            return Err("camera modulation_frequency_hz and frame_rate_hz must be positive".into());
        }
        check_frequencies(&c.modulation_frequencies_hz)?;
        if let Some(e) = &c.depth_engine {
            e.check().map_err(|e| format!("camera.depth_engine: {e}"))?;
            let a = &c.artefacts;
            if a.stray_light != 0.0 || a.saturation_ir != 0.0 || a.amplitude_power != 1.0 {
                return Err("camera.depth_engine: the artefacts that act on the single frequency's buckets (stray_light, saturation_ir, amplitude_power) do not apply to a depth engine; only phase_drift_mm_per_s does".into());
            }
        }
        if !["sinusoid", "triangle", "harmonics"].contains(&c.waveform.as_str()) {
            return Err(format!(
                "camera.waveform {:?}: expected sinusoid, triangle or harmonics",
                c.waveform
            ));
        }
        if !pos(self.emitter.peak_emitted_light) || !(0.0..1.0).contains(&self.emitter.vignetting) {
            return Err("emitter: peak_emitted_light > 0 and vignetting in [0, 1) required".into());
        }
        let n = &self.noise;
        if !(n.depth_noise_mm >= 0.0)
            || !pos(n.reference_distance_mm)
            || !pos(n.reference_albedo)
            || !(n.read_noise >= 0.0)
        {
            return Err(
                "noise: depth_noise_mm >= 0, reference_distance_mm > 0, reference_albedo > 0, read_noise >= 0 required"
                    .into(),
            );
        }
        let b = &self.background;
        if !(pos(b.distance_mm) && b.albedo > 0.0 && b.albedo <= 1.0) {
            return Err("background: distance_mm > 0 and albedo in (0, 1] required".into());
        }
        for (si, s) in self.stages.iter().enumerate() {
            for (oi, o) in s.objects.iter().enumerate() {
                let at = format!("stage {} object {}", si + 1, oi + 1);
                if !((0.0..=1.0).contains(&o.xi) && o.albedo > 0.0 && o.albedo <= 1.0) {
                    return Err(format!("{at}: xi in [0, 1] and albedo in (0, 1] required"));
                }
                match o.shape.as_str() {
                    "plane" if pos(o.size_mm[0]) && pos(o.size_mm[1]) => {}
                    "cylinder" if pos(o.radius_mm) && pos(o.height_mm) => {}
                    "plane" => return Err(format!("{at}: a plane needs size_mm = [w, h] > 0")),
                    "cylinder" => return Err(format!("{at}: a cylinder needs radius_mm and height_mm > 0")),
                    other => return Err(format!("{at}: shape {other:?}: expected plane or cylinder")),
                }
                if !(o.center_mm[2] > 0.0) {
                    return Err(format!("{at}: center_mm z must be in front of the camera"));
                }
            }
        }
        if !(2..=crate::physics::model::MAX_BOUNCES).contains(&self.physics.bounces) {
            return Err(format!(
                "physics.bounces must be in 2..={}",
                crate::physics::model::MAX_BOUNCES
            ));
        }
        Ok(())
    }

    /// Background frames plus every stage's frames.
    pub fn frame_count(&self) -> usize {
        self.background.frames + self.stages.iter().map(|s| s.frames).sum::<usize>()
    }
}

/// Most modulation frequencies a scene's camera may have.
pub const MAX_FREQUENCIES: usize = 8;

/// `camera.modulation_frequencies_hz`: up to [`MAX_FREQUENCIES`] distinct,
/// positive, finite frequencies.
fn check_frequencies(f: &[f64]) -> Result<(), String> {
    if f.len() > MAX_FREQUENCIES {
        return Err(format!(
            "camera.modulation_frequencies_hz has {} frequencies; at most {MAX_FREQUENCIES}",
            f.len()
        ));
    }
    for (k, &v) in f.iter().enumerate() {
        if !(v.is_finite() && v > 0.0) {
            return Err(format!(
                "camera.modulation_frequencies_hz[{k}] = {v}: frequencies must be positive, in Hz"
            ));
        }
        if f[..k].contains(&v) {
            return Err(format!("camera.modulation_frequencies_hz lists {v} Hz twice"));
        }
    }
    Ok(())
}

/// A pixel on the image's border whose ray the lens model cannot give
/// (distortion folds back first at the border).
fn pixel_without_ray(k: &crate::physics::Intrinsics) -> Option<(usize, usize)> {
    let (w, h) = (k.width, k.height);
    let border = (0..w)
        .flat_map(|c| [(c, 0), (c, h - 1)])
        .chain((0..h).flat_map(|r| [(0, r), (w - 1, r)]));
    border.into_iter().find(|&(c, r)| !k.ray(c, r).x.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minimal_scene_parses_with_sr4000_defaults() {
        let s = Scene::from_toml(
            "[background]\ndistance_mm = 2000\n[[stage]]\nframes = 2\n[[stage.objects]]\nshape = \"plane\"\ncenter_mm = [0, 0, 1000]\nsize_mm = [300, 200]\nxi = 0.65\nalbedo = 0.6\n",
            "t.toml",
        )
        .unwrap();
        assert_eq!((s.camera.width, s.camera.height), (176, 144));
        assert_eq!(s.frame_count(), 12);
        assert_eq!(s.physics, ModelOptions::default());
    }

    #[test]
    fn the_camera_lens_is_optional_and_checked() {
        let with = |lens: &str| {
            Scene::from_toml(
                &format!("[camera]\n{lens}\n[background]\ndistance_mm = 2000\n"),
                "l.toml",
            )
        };
        assert_eq!(with("").unwrap().camera.lens(), Ok(Distortion::None));
        let s = with("distortion_model = \"equidistant\"\ndistortion = [0.05, -0.01, 0, 0]").unwrap();
        assert_eq!(s.camera.lens(), Ok(Distortion::Equidistant([0.05, -0.01, 0.0, 0.0])));
        let e = chain(&with("distortion_model = \"fisheye\"\ndistortion = [0.1, 0, 0, 0]").unwrap_err());
        assert!(
            e.contains("l.toml") && e.contains("\"fisheye\" is not supported"),
            "{e}"
        );
        // Barrel distortion this strong folds back before the image's corners.
        let e = chain(&with("distortion_model = \"plumb_bob\"\ndistortion = [-2.5, 0, 0, 0, 0]").unwrap_err());
        assert!(e.contains("no ray through pixel"), "{e}");
    }

    /// The error and its causes, as `main` prints them.
    fn chain(e: &dyn std::error::Error) -> String {
        let mut s = e.to_string();
        let mut cur = e.source();
        while let Some(c) = cur {
            s.push_str(&format!(": {c}"));
            cur = c.source();
        }
        s
    }

    #[test]
    fn modulation_frequencies_are_optional_and_checked() {
        let with = |f: &str| Scene::from_toml(&format!("[camera]\n{f}\n[background]\ndistance_mm = 2000\n"), "f.toml");
        assert!(with("").unwrap().camera.modulation_frequencies_hz.is_empty());
        let s = with("modulation_frequencies_hz = [20e6, 50e6, 100e6]").unwrap();
        assert_eq!(s.camera.modulation_frequencies_hz, [20e6, 50e6, 100e6]);
        for (bad, says) in [
            ("[20e6, -5]", "must be positive"),
            ("[20e6, 20e6]", "twice"),
            ("[1, 2, 3, 4, 5, 6, 7, 8, 9]", "at most 8"),
        ] {
            let e = chain(&with(&format!("modulation_frequencies_hz = {bad}")).unwrap_err());
            assert!(e.contains("f.toml") && e.contains(says), "{e}");
        }
    }

    #[test]
    fn bad_values_are_named() {
        let e = Scene::from_toml("[background]\ndistance_mm = -5\n", "x.toml").unwrap_err();
        let e = chain(&e);
        assert!(e.contains("x.toml") && e.contains("background"), "{e}");
        let e = Scene::from_toml("[background]\ndistance_mm = 5\n[[stage]]\n[[stage.objects]]\nshape = \"cone\"\ncenter_mm = [0,0,1]\nxi = 0.5\nalbedo = 0.5\n", "x.toml")
            .unwrap_err();
        let e = chain(&e);
        assert!(e.contains("cone"), "{e}");
        let e = Scene::from_toml("[background]\ndistance_mm = 5\ncolour = 3\n", "x.toml").unwrap_err();
        let e = chain(&e);
        assert!(e.contains("colour"), "{e}");
        let e = Scene::from_toml(
            "[background]\ndistance_mm = 2000\n[camera.depth_engine]\nfrequencies_hz = [16e6, 80e6, 120e6]\n[camera.artefacts]\nstray_light = 0.01\n",
            "x.toml",
        )
        .unwrap_err();
        let e = chain(&e);
        assert!(e.contains("depth_engine") && e.contains("stray_light"), "{e}");
    }
}
