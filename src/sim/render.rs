//! Renders a [`Scene`] with the one forward model: ray casting for the
//! geometry, [`ForwardModel`] for the returns, [`ShotNoise`] in the buckets.

use nalgebra::{Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::scene::{ObjectSpec, Scene};
use crate::physics::diffuse::{layer_normal, DiffuseLobe, ImageLayer};
use crate::physics::model::MAX_BOUNCES;
use crate::physics::multifreq::MultiFrequencyModel;
use crate::physics::near_wall;
use crate::physics::noise::ShotNoise;
use crate::physics::{ForwardModel, ImageBuf, Intrinsics, IrMode, LayerScene, Return, Sensor, Waveform};

/// One rendered frame.
#[derive(Debug, Clone)]
pub struct SimFrame {
    /// Stamp, nanoseconds since the epoch.
    pub stamp_ns: u64,
    /// z-depth, mm (NaN where nothing decodes).
    pub depth_z_mm: ImageBuf<f32>,
    /// IR value, counts.
    pub ir: ImageBuf<f32>,
    /// True z-depth of the translucent foreground, mm (NaN where none).
    pub truth_z_mm: ImageBuf<f32>,
    /// Whether this frame shows the background alone.
    pub background_only: bool,
    /// One phasor image per `camera.modulation_frequencies_hz` (empty when
    /// none): in-phase and quadrature bucket differences, counts, noisy.
    pub phasors: Vec<ImageBuf<[f32; 2]>>,
}

/// The camera and physics a scene implies: its modulation and waveform, and
/// its depth engine where it has one (checked by [`Scene::validate`]; one
/// that does not check is left off).
pub fn scene_sensor(scene: &Scene) -> Sensor {
    let c = &scene.camera;
    let w = match c.waveform.as_str() {
        "triangle" => Waveform::Triangle,
        "harmonics" => Waveform::Harmonics {
            third: c.harmonics[0],
            fifth: c.harmonics[1],
        },
        _ => Waveform::Sinusoid,
    };
    let sensor = Sensor::new(c.modulation_frequency_hz, w);
    match &c.depth_engine {
        Some(e) => sensor.clone().with_depth_engine(e).unwrap_or(sensor),
        None => sensor,
    }
}

/// The scene's intrinsics: K from the fields of view, and the lens (a
/// pinhole when the scene's lens is not valid, which [`Scene::validate`] and
/// [`render`] refuse).
pub fn scene_intrinsics(scene: &Scene) -> Intrinsics {
    let c = &scene.camera;
    Intrinsics::from_fov(c.width, c.height, c.hfov_deg, c.vfov_deg).with_distortion(c.lens().unwrap_or_default())
}

/// `Lin` per pixel: the peak on the axis, falling quadratically to the corners.
pub fn emitted_light_map(scene: &Scene) -> ImageBuf<f64> {
    let k = scene_intrinsics(scene);
    let [cx, cy] = k.principal_point();
    let rmax2 = cx * cx + cy * cy;
    let mut data = Vec::with_capacity(k.width * k.height);
    for row in 0..k.height {
        for col in 0..k.width {
            let r2 = ((col as f64 - cx).powi(2) + (row as f64 - cy).powi(2)) / rmax2;
            data.push(scene.emitter.peak_emitted_light * (1.0 - scene.emitter.vignetting * r2));
        }
    }
    ImageBuf {
        width: k.width,
        height: k.height,
        data,
    }
}

/// A hit: distance along the unit ray and `|cos|` of incidence.
#[derive(Debug, Clone, Copy)]
struct Hit {
    t: f64,
    cos: f64,
}

fn tilt(x_deg: f64, y_deg: f64) -> Rotation3<f64> {
    Rotation3::from_euler_angles(x_deg.to_radians(), y_deg.to_radians(), 0.0)
}

fn hit_plane(u: &Vector3<f64>, center: Vector3<f64>, rot: &Rotation3<f64>, half: Option<[f64; 2]>) -> Option<Hit> {
    let n = rot * Vector3::new(0.0, 0.0, -1.0);
    let den = n.dot(u);
    if den.abs() < 1e-9 {
        return None;
    }
    let t = n.dot(&center) / den;
    if t <= 0.0 {
        return None;
    }
    if let Some([hw, hh]) = half {
        let local = rot.inverse() * (u * t - center);
        if local.x.abs() > hw || local.y.abs() > hh {
            return None;
        }
    }
    Some(Hit { t, cos: den.abs() })
}

fn hit_cylinder(u: &Vector3<f64>, o: &ObjectSpec) -> Option<Hit> {
    let c = Vector3::from(o.center_mm);
    // (t ux - cx)^2 + (t uz - cz)^2 = r^2, front root.
    let a = u.x * u.x + u.z * u.z;
    let b = -2.0 * (u.x * c.x + u.z * c.z);
    let cc = c.x * c.x + c.z * c.z - o.radius_mm * o.radius_mm;
    let disc = b * b - 4.0 * a * cc;
    if disc < 0.0 || a <= 0.0 {
        return None;
    }
    let t = (-b - disc.sqrt()) / (2.0 * a);
    if t <= 0.0 {
        return None;
    }
    let p = u * t;
    if (p.y - c.y).abs() > o.height_mm / 2.0 {
        return None;
    }
    let n = Vector3::new(p.x - c.x, 0.0, p.z - c.z) / o.radius_mm;
    Some(Hit { t, cos: n.dot(u).abs() })
}

fn hit_object(u: &Vector3<f64>, o: &ObjectSpec) -> Option<Hit> {
    match o.shape.as_str() {
        "plane" => hit_plane(
            u,
            Vector3::from(o.center_mm),
            &tilt(o.tilt_x_deg, o.tilt_y_deg),
            Some([o.size_mm[0] / 2.0, o.size_mm[1] / 2.0]),
        ),
        "cylinder" => hit_cylinder(u, o),
        _ => None,
    }
}

/// Patches per side of a plane object in its view factors.
const VIEW_FACTOR_GRID: usize = 16;

/// The view factor from a background point `wall` to a plane object (a grid of
/// [`VIEW_FACTOR_GRID`] patches a side, each given as the solid angle the camera sees it
/// fill, as [`near_wall::view_factor`] takes them); 0 for other shapes.
fn plane_view_factor(wall: &Vector3<f64>, o: &ObjectSpec) -> f64 {
    if o.shape != "plane" {
        return 0.0;
    }
    const N: usize = VIEW_FACTOR_GRID;
    let rot = tilt(o.tilt_x_deg, o.tilt_y_deg);
    let (c, [sx, sy]) = (Vector3::from(o.center_mm), o.size_mm);
    let area = sx * sy / (N * N) as f64;
    let patches: [near_wall::Patch; N * N] = std::array::from_fn(|k| {
        let (i, j) = ((k % N) as f64, (k / N) as f64);
        let local = Vector3::new(
            ((i + 0.5) / N as f64 - 0.5) * sx,
            ((j + 0.5) / N as f64 - 0.5) * sy,
            0.0,
        );
        let point = c + rot * local;
        let d = point.norm();
        near_wall::Patch {
            point,
            solid_angle: area * point.z / (d * d * d),
        }
    });
    near_wall::view_factor(wall, &patches)
}

/// The nearest object hit in front of the background along the unit ray `u`, and its index.
fn foreground_hit(u: &Vector3<f64>, objects: &[ObjectSpec], bg: Option<Hit>) -> Option<(Hit, usize)> {
    objects
        .iter()
        .enumerate()
        .filter_map(|(j, o)| hit_object(u, o).map(|h| (h, j)))
        .filter(|(h, _)| bg.is_none_or(|bh| h.t < bh.t))
        .min_by(|a, b| a.0.t.total_cmp(&b.0.t))
}

/// A frame's frosted layers as the lobe sees them ([`ImageLayer`]): the outline the pixels
/// any object covers (their shadow on the background), and each object's patches and normal
/// from its true ray distances, one patch per pixel.
struct FrostedLayers<'a> {
    intrinsics: &'a Intrinsics,
    emitted_light: &'a ImageBuf<f64>,
    mask: ImageBuf<bool>,
    patches: Vec<Vec<near_wall::Patch>>,
    normals: Vec<Vector3<f64>>,
    /// The sensor's radians per mm.
    k: f64,
}

impl<'a> FrostedLayers<'a> {
    /// The layers of a frame whose pixels' rays (`rays`) hit `hits` (ray distance, object);
    /// `None` where the model has no diffuse transmission.
    fn of_frame(
        model: &ForwardModel,
        (intrinsics, rays, emitted_light): (&'a Intrinsics, &ImageBuf<Vector3<f64>>, &'a ImageBuf<f64>),
        hits: &[Option<(f64, usize)>],
        objects: usize,
    ) -> Option<Self> {
        if !(model.options.diffuse_transmission > 0.0) || objects == 0 {
            return None;
        }
        let patches: Vec<Vec<near_wall::Patch>> = (0..objects)
            .map(|j| {
                let df: Vec<f64> = hits
                    .iter()
                    .map(|h| h.filter(|&(_, o)| o == j).map_or(f64::NAN, |(t, _)| t))
                    .collect();
                near_wall::layer_patches(&df, rays, 1)
            })
            .collect();
        Some(Self {
            intrinsics,
            emitted_light,
            mask: ImageBuf {
                width: rays.width,
                height: rays.height,
                data: hits.iter().map(Option::is_some).collect(),
            },
            normals: patches.iter().map(|p| layer_normal(p)).collect(),
            patches,
            k: model.sensor.phase(1.0),
        })
    }

    /// The lobe of object `j` on the unit ray `u` at `df` before a background at `db` (ray
    /// distances, mm): [`ImageLayer::lobe`], as recovery and the audit take it.
    fn lobe(&self, j: usize, u: &Vector3<f64>, df: f64, db: f64) -> Option<DiffuseLobe> {
        let layer = ImageLayer {
            intrinsics: self.intrinsics,
            mask: &self.mask,
            emitted_light: self.emitted_light,
            patches: self.patches.get(j)?,
            normal: *self.normals.get(j)?,
        };
        Some(layer.lobe(u, df, db, self.k))
    }
}

/// Appends the returns along one ray carrying `lin` of emitted light: the
/// layer's (Eq. 1-3) in front of the background, or the background alone; a frosted
/// layer's lobe over the frame's `frosted` layers where the model has one.
fn ray_returns(
    (model, frosted): (&ForwardModel, Option<&FrostedLayers>),
    (u, u_behind): (&Vector3<f64>, &Vector3<f64>),
    objects: &[ObjectSpec],
    (bg_center, bg_rot, bg_albedo): (Vector3<f64>, &Rotation3<f64>, f64),
    lin: f64,
    out: &mut Vec<Return>,
) {
    let bg = hit_plane(u, bg_center, bg_rot, None);
    match (foreground_hit(u, objects, bg), bg) {
        (Some((h, j)), Some(bh)) => {
            let o = &objects[j];
            // Through the layer the background is the one the displaced ray meets (refraction).
            let bh = if u_behind == u {
                bh
            } else {
                match hit_plane(u_behind, bg_center, bg_rot, None) {
                    Some(b) => b,
                    None => bh,
                }
            };
            let mut r = [Return::default(); MAX_BOUNCES];
            let n = model.layer_returns(
                &LayerScene {
                    foreground_distance_mm: h.t,
                    background_distance_mm: bh.t,
                    translucency: o.xi,
                    foreground_albedo_cos: o.albedo * h.cos,
                    background_albedo_cos: bg_albedo * bh.cos,
                    emitted_light: lin,
                    wall_view_factor: if model.options.wall_interreflection > 0.0 {
                        plane_view_factor(&(u_behind * bh.t), o)
                    } else {
                        0.0
                    },
                    diffuse_lobe: frosted.and_then(|f| f.lobe(j, u, h.t, bh.t)),
                },
                &mut r,
            );
            out.extend_from_slice(&r[..n]);
        }
        (None, Some(bh)) => out.push(ForwardModel::opaque_return(bh.t, bg_albedo * bh.cos, lin)),
        // A layer with nothing behind it: its first return alone.
        (Some((h, j)), None) => {
            let o = &objects[j];
            out.push(ForwardModel::opaque_return(h.t, (1.0 - o.xi) * o.albedo * h.cos, lin))
        }
        (None, None) => {}
    }
}

/// The scene's forward model at each of `camera.modulation_frequencies_hz`
/// (`None` when it lists none): the same physics and waveform.
pub fn scene_frequencies(scene: &Scene, model: &ForwardModel) -> Result<Option<MultiFrequencyModel>, String> {
    let f = &scene.camera.modulation_frequencies_hz;
    if f.is_empty() {
        return Ok(None);
    }
    MultiFrequencyModel::new(model, f)
        .map(Some)
        .map_err(|e| format!("camera.modulation_frequencies_hz: {e}"))
}

/// The noisy phasor of `returns` at each frequency (Eq. 5 at `f_k`), with the
/// same shot noise as the depth image: the bucket noise follows the light
/// received, which is the same at every frequency. Pushes one per frequency.
fn push_phasors(
    mf: &MultiFrequencyModel,
    returns: &[Return],
    noise: &ShotNoise,
    rng: &mut ChaCha8Rng,
    out: &mut [Vec<[f32; 2]>],
) {
    for (m, image) in mf.measure(returns).zip(out.iter_mut()) {
        let s = noise.bucket_sigma(m.total_light);
        let (za, zb): (f64, f64) = (rng.sample(StandardNormal), rng.sample(StandardNormal));
        image.push([(m.buckets.a + s * za) as f32, (m.buckets.b + s * zb) as f32]);
    }
}

/// A noisy reading `(distance_mm, ir)` of `returns` through the sensor's depth
/// engine: the phasor at each of its frequencies (Eq. 5 at `f_k`) with the bucket
/// noise of the light received (the same at every frequency), read by the engine
/// as the camera does (NaN where it invalidates the pixel). The IR is the
/// engine's amplitude, or the sum of the returns (with its noise) for `IrMode::Sum`.
fn engine_reading(model: &ForwardModel, returns: &[Return], noise: &ShotNoise, rng: &mut ChaCha8Rng) -> (f64, f64) {
    let Some(e) = model.sensor.engine() else {
        return (f64::NAN, 0.0);
    };
    let total: f64 = returns.iter().map(|r| r.strength).sum();
    let s = noise.bucket_sigma(total);
    let mut p = e.phasors(&model.sensor, returns);
    for b in p.iter_mut().take(e.len()) {
        let (za, zb): (f64, f64) = (rng.sample(StandardNormal), rng.sample(StandardNormal));
        b.a += s * za;
        b.b += s * zb;
    }
    let reading = e.read(&model.sensor, &p[..e.len()]);
    let ir = match model.options.ir_mode {
        IrMode::Amplitude => reading.ir_amplitude,
        IrMode::Sum => total + s * rng.sample::<f64, _>(StandardNormal),
    };
    (reading.distance_mm, ir + model.options.ambient_offset)
}

/// What a pixel received before the sensor's effects and noise: nothing, the single
/// frequency's measurement (Eq. 5), or the returns a depth engine reads.
enum Pixel {
    Empty,
    Measured(crate::physics::Measurement),
    Engine(Vec<Return>),
}

impl Pixel {
    /// The single frequency's measurement, where the pixel has one.
    fn measurement(&self) -> Option<crate::physics::Measurement> {
        match self {
            Pixel::Measured(m) => Some(*m),
            _ => None,
        }
    }
}

/// Renders every frame of the scene: background frames, then each stage's.
/// `on_frame` receives each frame as it is made (for progress and writing).
pub fn render(scene: &Scene, mut on_frame: impl FnMut(usize, SimFrame) -> Result<(), String>) -> Result<(), String> {
    scene.camera.lens().map_err(|e| format!("camera: {e}"))?;
    let k = scene_intrinsics(scene);
    let sensor = scene_sensor(scene);
    let model = ForwardModel {
        sensor: sensor.clone(),
        options: scene.physics.clone(),
    };
    let lin = emitted_light_map(scene);
    let n = &scene.noise;
    let ref_strength = n.reference_albedo * scene.emitter.peak_emitted_light / n.reference_distance_mm.powi(2);
    let noise = ShotNoise::calibrated(&sensor, ref_strength, n.depth_noise_mm, n.read_noise);
    let mut rng = ChaCha8Rng::seed_from_u64(scene.seed);
    let multi = scene_frequencies(scene, &model)?;
    // The phasors' noise from a stream of its own: depth and IR are those of the same
    // scene without the extra frequencies.
    let mut phasor_rng = ChaCha8Rng::seed_from_u64(scene.seed);
    phasor_rng.set_stream(1);
    // Which pixels read invalid, from a stream of its own: a scene without any reads as before.
    let mut invalid_rng = ChaCha8Rng::seed_from_u64(scene.seed);
    invalid_rng.set_stream(2);
    let outside = outside_field(&k, scene.camera.invalid_beyond_radius);
    let rays = k.unit_ray_map();
    let scale = k.ray_scale_map();
    let b = &scene.background;
    let bg_rot = tilt(b.tilt_x_deg, b.tilt_y_deg);
    let bg_center = Vector3::new(0.0, 0.0, b.distance_mm);
    let ss = scene.camera.supersample.max(1);
    let mut returns: Vec<Return> = Vec::with_capacity(ss * ss * MAX_BOUNCES);
    let period_ns = 1e9 / scene.camera.frame_rate_hz;
    let start_ns = (scene.camera.start_time_s * 1e9) as u64;
    let mut stages: Vec<(&[ObjectSpec], bool)> = vec![(&[], true); b.frames];
    for s in &scene.stages {
        stages.extend(std::iter::repeat_n((s.objects.as_slice(), false), s.frames));
    }
    let artefacts = &scene.camera.artefacts;
    for (index, (objects, background_only)) in stages.into_iter().enumerate() {
        let npx = k.width * k.height;
        let mut depth = Vec::with_capacity(npx);
        let mut ir = Vec::with_capacity(npx);
        let mut truth = Vec::with_capacity(npx);
        let mut phasors: Vec<Vec<[f32; 2]>> = vec![Vec::with_capacity(npx); multi.as_ref().map_or(0, |m| m.len())];
        let frame_time_s = index as f64 / scene.camera.frame_rate_hz;
        let mut measurements: Vec<Pixel> = Vec::with_capacity(npx);
        // What each pixel's central ray hits before the background: the truth, and the
        // outline and layers a frosted layer's lobes fall over.
        let hits: Vec<Option<(f64, usize)>> = rays
            .data
            .iter()
            .map(|u| foreground_hit(u, objects, hit_plane(u, bg_center, &bg_rot, None)).map(|(h, j)| (h.t, j)))
            .collect();
        let frosted = FrostedLayers::of_frame(&model, (&k, &rays, &lin), &hits, objects.len());
        for i in 0..npx {
            let (col, row) = ((i % k.width) as f64, (i / k.width) as f64);
            // Sub-rays on a regular grid within the pixel, each with its share of the light:
            // edges mix the surfaces they straddle, as on a real sensor.
            returns.clear();
            for sy in 0..ss {
                for sx in 0..ss {
                    let (du, dv) = ((sx as f64 + 0.5) / ss as f64 - 0.5, (sy as f64 + 0.5) / ss as f64 - 0.5);
                    let u = if ss == 1 {
                        rays.data[i]
                    } else {
                        k.ray_at(col + du, row + dv).normalize()
                    };
                    let behind = if model.options.refracts() {
                        let [dx, dy] = model.options.refraction_shift_px;
                        k.ray_at(col + du + dx, row + dv + dy).normalize()
                    } else {
                        u
                    };
                    ray_returns(
                        (&model, frosted.as_ref()),
                        (&u, &behind),
                        objects,
                        (bg_center, &bg_rot, b.albedo),
                        lin.data[i] / (ss * ss) as f64,
                        &mut returns,
                    );
                }
            }
            artefacts.drift(&mut returns, frame_time_s);
            if let Some(mf) = &multi {
                push_phasors(mf, &returns, &noise, &mut phasor_rng, &mut phasors);
            }
            // A depth engine reads the returns themselves (several frequencies); the single
            // frequency's measurement is made here and read after the frame's stray light.
            if model.sensor.engine().is_some() && !returns.is_empty() {
                measurements.push(Pixel::Engine(returns.clone()));
            } else {
                measurements.push(if returns.is_empty() {
                    Pixel::Empty
                } else {
                    Pixel::Measured(model.measure(&returns))
                });
            }
        }
        // The sensor's effects past the model, on the whole frame's measurements (stray light
        // spreads the frame's light); none leaves each measurement as the model made it.
        let single: Vec<Option<crate::physics::Measurement>> = measurements.iter().map(Pixel::measurement).collect();
        let frame_light = crate::sim::Artefacts::frame_light(&single);
        for (i, pixel) in measurements.into_iter().enumerate() {
            let z: [f64; 3] = [
                rng.sample(StandardNormal),
                rng.sample(StandardNormal),
                rng.sample(StandardNormal),
            ];
            let (d, v) = match pixel {
                Pixel::Engine(returns) => engine_reading(&model, &returns, &noise, &mut rng),
                Pixel::Measured(m) if !artefacts.none() => {
                    noise.apply(&sensor, &artefacts.apply(&sensor, &m, frame_light), z)
                }
                Pixel::Measured(m) => noise.apply(&sensor, &m, z),
                Pixel::Empty => (f64::NAN, 0.0),
            };
            let share = scene.camera.invalid_share;
            let invalid = outside.get(i).copied().unwrap_or(false) || (share > 0.0 && invalid_rng.random_bool(share));
            depth.push(if invalid { f32::NAN } else { (d / scale.data[i]) as f32 });
            ir.push(v.max(0.0) as f32);
            truth.push(hits[i].map_or(f32::NAN, |(t, _)| (t / scale.data[i]) as f32));
        }
        let frame = SimFrame {
            stamp_ns: start_ns + (index as f64 * period_ns).round() as u64,
            depth_z_mm: ImageBuf {
                width: k.width,
                height: k.height,
                data: depth,
            },
            ir: ImageBuf {
                width: k.width,
                height: k.height,
                data: ir,
            },
            truth_z_mm: ImageBuf {
                width: k.width,
                height: k.height,
                data: truth,
            },
            background_only,
            phasors: phasors
                .into_iter()
                .map(|data| ImageBuf {
                    width: k.width,
                    height: k.height,
                    data,
                })
                .collect(),
        };
        on_frame(index, frame)?;
    }
    Ok(())
}

/// The pixels beyond `radius` of the half-diagonal from the image centre (none for 0).
fn outside_field(k: &Intrinsics, radius: f64) -> Vec<bool> {
    if radius <= 0.0 {
        return vec![];
    }
    let (cx, cy) = ((k.width as f64 - 1.0) / 2.0, (k.height as f64 - 1.0) / 2.0);
    let half_diagonal = cx.hypot(cy).max(f64::MIN_POSITIVE);
    (0..k.width * k.height)
        .map(|i| ((i % k.width) as f64 - cx).hypot((i / k.width) as f64 - cy) > radius * half_diagonal)
        .collect()
}

/// Renders into memory.
pub fn render_all(scene: &Scene) -> Vec<SimFrame> {
    let mut v = Vec::with_capacity(scene.frame_count());
    let _ = render(scene, |_, f| {
        v.push(f);
        Ok(())
    });
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(noise: f64) -> Scene {
        let mut s = Scene::from_toml(
            "[background]\ndistance_mm = 2000\nframes = 2\n[[stage]]\nframes = 1\n[[stage.objects]]\nshape = \"plane\"\ncenter_mm = [0, 0, 1000]\nsize_mm = [300, 200]\nxi = 0.65\nalbedo = 0.6\n[[stage.objects]]\nshape = \"cylinder\"\ncenter_mm = [-250, 0, 1200]\nradius_mm = 50\nheight_mm = 300\nxi = 0.3\nalbedo = 0.8\n",
            "t",
        )
        .unwrap();
        s.noise.depth_noise_mm = noise;
        s
    }

    #[test]
    fn noise_free_background_reads_the_plane_and_truth_marks_objects() {
        let frames = render_all(&scene(0.0));
        assert_eq!(frames.len(), 3);
        let k = Intrinsics::sr4000();
        let c = k.width / 2 + (k.height / 2) * k.width;
        assert!((frames[0].depth_z_mm.data[c] - 2000.0).abs() < 0.01);
        assert!(frames[0].truth_z_mm.data.iter().all(|t| t.is_nan()));
        let f = &frames[2];
        assert!((f.truth_z_mm.data[c] - 1000.0).abs() < 0.01);
        assert!(f.depth_z_mm.data[c] > 1000.0 && f.depth_z_mm.data[c] < 2000.0);
        let n_truth = f.truth_z_mm.data.iter().filter(|t| t.is_finite()).count();
        assert!(n_truth > 2000, "{n_truth}");
        assert!(frames[2].stamp_ns > frames[1].stamp_ns);
    }

    #[test]
    fn phasors_come_from_the_one_model_and_leave_depth_and_ir_alone() {
        let single = render_all(&scene(10.0));
        let mut s = scene(10.0);
        s.camera.modulation_frequencies_hz = vec![20e6, 50e6, 100e6];
        let multi = render_all(&s);
        for (a, b) in single.iter().zip(&multi) {
            assert!(a.phasors.is_empty() && b.phasors.len() == 3);
            assert_eq!(
                a.depth_z_mm.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                b.depth_z_mm.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
            assert_eq!(a.ir.data, b.ir.data);
        }
        // Noise-free: the wall's phasor at each frequency is the forward model's.
        let mut quiet = s.clone();
        quiet.noise.depth_noise_mm = 0.0;
        let f = &render_all(&quiet)[0];
        let k = Intrinsics::sr4000();
        let c = k.width / 2 + (k.height / 2) * k.width;
        let lin = emitted_light_map(&quiet).data[c];
        let wall = [ForwardModel::opaque_return(
            2000.0 * k.ray_scale(k.width / 2, k.height / 2),
            1.0,
            lin,
        )];
        let model = ForwardModel {
            sensor: scene_sensor(&quiet),
            options: quiet.physics.clone(),
        };
        let mf = scene_frequencies(&quiet, &model).unwrap().unwrap();
        for (m, image) in mf.measure(&wall).zip(&f.phasors) {
            let [a, b] = image.data[c];
            let scale = m.buckets.a.hypot(m.buckets.b);
            assert!((f64::from(a) - m.buckets.a).abs() < 1e-5 * scale, "{a} {:?}", m.buckets);
            assert!((f64::from(b) - m.buckets.b).abs() < 1e-5 * scale, "{b} {:?}", m.buckets);
        }
    }

    #[test]
    fn a_depth_engine_renders_the_models_depth_and_invalidates_past_its_threshold() {
        let mut s = scene(0.0);
        s.camera.depth_engine = Some(crate::physics::DepthEngine::at(&[16e6, 80e6, 120e6]).unwrap());
        let frames = render_all(&s);
        let k = Intrinsics::sr4000();
        let c = k.width / 2 + (k.height / 2) * k.width;
        assert!(
            (frames[0].depth_z_mm.data[c] - 2000.0).abs() < 0.01,
            "the wall reads its distance"
        );
        // The layer's pixel reads the engine's depth of its returns, not the single frequency's.
        let model = ForwardModel {
            sensor: scene_sensor(&s),
            options: s.physics.clone(),
        };
        let single = render_all(&scene(0.0));
        let (got, one) = (frames[2].depth_z_mm.data[c], single[2].depth_z_mm.data[c]);
        let scale = k.ray_scale(k.width / 2, k.height / 2);
        let lin = emitted_light_map(&s).data[c];
        let want = model
            .measure_layer(&LayerScene {
                foreground_distance_mm: 1000.0 * scale,
                background_distance_mm: 2000.0 * scale,
                translucency: 0.65,
                foreground_albedo_cos: 0.6 / scale,
                background_albedo_cos: 1.0 / scale,
                emitted_light: lin,
                wall_view_factor: 0.0,
                diffuse_lobe: None,
            })
            .distance_mm
            / scale;
        assert!((f64::from(got) - want).abs() < 0.5, "engine {got}, model {want}");
        assert!((got - one).abs() > 5.0, "engine {got}, single frequency {one}");
        // A tight threshold leaves the layer's pixels unmeasured and the wall's valid.
        if let Some(e) = s.camera.depth_engine.as_mut() {
            e.max_disagreement_mm = Some(1.0);
        }
        let strict = render_all(&s);
        assert!(
            strict[2].depth_z_mm.data[c].is_nan(),
            "{}",
            strict[2].depth_z_mm.data[c]
        );
        assert!((strict[0].depth_z_mm.data[c] - 2000.0).abs() < 0.01);
    }

    /// A frosted sheet's pixels read the finite layer's lobe over the frame's outline (the
    /// outline, patches and normal from the truth, [`ImageLayer::lobe`] as recovery and the
    /// audit take it), not the filled view's, which lies more than 5 mm from it.
    #[test]
    fn a_frosted_layer_renders_its_lobe_over_its_outline() {
        let mut s = scene(0.0);
        s.stages[0].objects.truncate(1);
        s.physics.diffuse_transmission = 0.8;
        let f = &render_all(&s)[2];
        let k = scene_intrinsics(&s);
        let (rays, scale, lin) = (k.unit_ray_map(), k.ray_scale_map(), emitted_light_map(&s));
        let df: Vec<f64> = f
            .truth_z_mm
            .data
            .iter()
            .zip(&scale.data)
            .map(|(z, sc)| f64::from(*z) * sc)
            .collect();
        let patches = near_wall::layer_patches(&df, &rays, 1);
        let mask = ImageBuf {
            width: k.width,
            height: k.height,
            data: df.iter().map(|d| d.is_finite()).collect(),
        };
        let layer = ImageLayer {
            intrinsics: &k,
            mask: &mask,
            emitted_light: &lin,
            patches: &patches,
            normal: layer_normal(&patches),
        };
        let model = ForwardModel {
            sensor: scene_sensor(&s),
            options: s.physics.clone(),
        };
        let (c, r) = (k.width / 2 + 20, k.height / 2 - 10);
        let i = r * k.width + c;
        let (sc, u) = (scale.data[i], rays.data[i]);
        let scene_at = |lobe: Option<DiffuseLobe>| LayerScene {
            foreground_distance_mm: df[i],
            background_distance_mm: 2000.0 * sc,
            translucency: 0.65,
            foreground_albedo_cos: 0.6 / sc,
            background_albedo_cos: 1.0 / sc,
            emitted_light: lin.data[i],
            wall_view_factor: 0.0,
            diffuse_lobe: lobe,
        };
        let lobe = layer.lobe(&u, df[i], 2000.0 * sc, model.sensor.phase(1.0));
        let want = model.measure_layer(&scene_at(Some(lobe))).distance_mm / sc;
        let filled = model.measure_layer(&scene_at(None)).distance_mm / sc;
        let got = f64::from(f.depth_z_mm.data[i]);
        assert!((got - want).abs() < 0.5, "rendered {got}, the lobe's {want}");
        assert!(
            (want - filled).abs() > 5.0,
            "the lobe's {want}, the filled view's {filled}"
        );
    }

    #[test]
    fn wall_noise_is_about_the_asked_sigma() {
        let mut s = scene(10.0);
        s.background.frames = 1;
        s.stages.clear();
        let f = &render_all(&s)[0];
        let k = Intrinsics::sr4000();
        // Central 20x20 patch: Lin within ~1 % of the peak.
        let mut v = vec![];
        for r in 62..82 {
            for c in 78..98 {
                v.push(f.depth_z_mm.data[r * k.width + c] as f64 * k.ray_scale(c, r) - 2000.0 * k.ray_scale(c, r));
            }
        }
        let sd = (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        assert!(sd > 9.0 && sd < 11.5, "wall noise {sd}");
    }
}
