//! The one forward model: the returns a pixel receives through a translucent
//! layer (paper Eq. 1-3), mixed in the buckets (Eq. 5) and read by the device
//! (Eq. 6, 11), with the IR image (Eq. 7). Every effect past the paper's
//! baseline is an option of [`ModelOptions`]; the simulator, the inversion
//! and the audit all call this one model.

use serde::{Deserialize, Serialize};

use super::diffuse::{diffuse_second_return, DiffuseLobe};
use super::near_wall::{third_return_distance, third_return_share};
use super::sensor::{Buckets, Sensor};

/// Most returns the model keeps (L1, L2 and six higher-order bounces).
pub const MAX_BOUNCES: usize = 8;

/// What the IR image reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum IrMode {
    /// The sum of the returns' strengths (the paper's Eq. 7).
    #[default]
    Sum,
    /// The demodulated amplitude `|sum_k L_k exp(i phi_k)|`, smaller when
    /// returns disagree in phase.
    Amplitude,
}

/// Options of the forward model. `Default` is the paper's model (what scene
/// files and the audit's effects are written against); [`ModelOptions::physical`]
/// is what the tools and the node use unless told otherwise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelOptions {
    /// Returns kept from Eq. 3: 2 keeps L1 and L2 (the paper); 3 adds the
    /// first inter-reflection term, and so on up to [`MAX_BOUNCES`] (values
    /// outside `2..=MAX_BOUNCES` are clamped).
    pub bounces: usize,
    /// What the IR image reports.
    pub ir_mode: IrMode,
    /// Power `p` of the layer's albedo term in the second return,
    /// `L2 = Ib xi^2 X^p`: 2 in the paper's Eq. 2, 0 for light that merely
    /// crosses the layer twice (physics.md's note on Eq. 2).
    pub transmission_albedo_power: f64,
    /// Offset in the IR image (ambient light, dark level), IR counts.
    pub ambient_offset: f64,
    /// Extra path of the light the layer returns (subsurface scattering), mm.
    pub subsurface_delay_mm: f64,
    /// Refraction by the layer (the paper's named limit, Sec. VI): the
    /// background reached through the layer (the second and later returns,
    /// Eq. 2-3) is the one a neighbouring ray would see, displaced by this
    /// many pixels `[columns, rows]` in the image. `[0, 0]` is no refraction.
    pub refraction_shift_px: [f64; 2],
    /// Gain on the light the layer's back and a diffuse background exchange
    /// ([`super::near_wall`]): a third return of `L2 F (1 - ξ) X Xb (ξ F + 1 - F) / ξ`
    /// at `db + sqrt(2) (db - df)`, with `F` the view factor from the background point to
    /// the layer ([`LayerScene::wall_view_factor`]). 0 leaves it out; 1 is its estimate.
    pub wall_interreflection: f64,
    /// Share (0..1) of the light crossing the layer that crosses diffusely, through a
    /// cosine lobe ([`super::diffuse`]; a frosted layer): that share of the second return
    /// (Eq. 2) comes back over slanted paths, fainter and farther; where the layer's outline
    /// is known ([`LayerScene::diffuse_lobe`]) the lobe sees the background outside the
    /// layer's shadow too, lit straight. 0 is a clear layer.
    pub diffuse_transmission: f64,
    /// Depth of a hollow object of the layer's material (a bin, a closed box), mm: a back
    /// wall this far behind the front along the ray, seen through it, and the background
    /// through both (three returns). 0 is one layer.
    pub hollow_depth_mm: f64,
}

impl Default for ModelOptions {
    fn default() -> Self {
        Self::paper()
    }
}

/// A named set of model options (`--physics NAME`, parameter `physics:=NAME`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// What physics and the evidence support (physics.md §5-6): the second
    /// return crosses the layer twice (`L2 = Ib xi^2`) and the IR image is the
    /// demodulated amplitude, as CW-ToF cameras report it.
    #[default]
    Physical,
    /// The paper's model as published: `L2 = Ib xi^2 X^2` (Eq. 2), IR the sum
    /// of the returns (Eq. 7). For replicating the paper.
    Paper,
}

impl Preset {
    /// Every preset, for help texts.
    pub const ALL: [Preset; 2] = [Preset::Physical, Preset::Paper];

    /// The preset's name.
    pub fn name(&self) -> &'static str {
        match self {
            Preset::Physical => "physical",
            Preset::Paper => "paper",
        }
    }

    /// The preset named `name`, if any.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|p| p.name() == name)
    }

    /// Its model options.
    pub fn options(&self) -> ModelOptions {
        match self {
            Preset::Physical => ModelOptions::physical(),
            Preset::Paper => ModelOptions::paper(),
        }
    }
}

impl ModelOptions {
    /// The paper's model: L1 and L2 (Eq. 1-2), IR the sum of the returns (Eq. 7).
    pub fn paper() -> Self {
        Self {
            bounces: 2,
            ir_mode: IrMode::Sum,
            transmission_albedo_power: 2.0,
            ambient_offset: 0.0,
            subsurface_delay_mm: 0.0,
            refraction_shift_px: [0.0, 0.0],
            wall_interreflection: 0.0,
            diffuse_transmission: 0.0,
            hollow_depth_mm: 0.0,
        }
    }

    /// The default physics ([`Preset::Physical`]): the paper's returns with the
    /// second one crossing the layer twice (`L2 = Ib xi^2`) and IR the demodulated amplitude.
    pub fn physical() -> Self {
        Self {
            ir_mode: IrMode::Amplitude,
            transmission_albedo_power: 0.0,
            ..Self::paper()
        }
    }

    /// True for the paper's model, whose IR equation has a closed-form root (Eq. 10).
    pub fn is_paper_baseline(&self) -> bool {
        self.bounces == 2
            && self.ir_mode == IrMode::Sum
            && self.transmission_albedo_power == 2.0
            && self.ambient_offset == 0.0
            && self.wall_interreflection == 0.0
            && self.diffuse_transmission == 0.0
            && self.hollow_depth_mm == 0.0
    }

    /// True when the background behind the layer is displaced (refraction).
    pub fn refracts(&self) -> bool {
        self.refraction_shift_px != [0.0, 0.0]
    }

    /// What a pixel at `(col, row)` sees of the background through the layer:
    /// the background's distance (mm) and IR (counts) at the displaced image
    /// point (bilinear between the four pixels around it), with the IR scaled
    /// to this pixel's emitted light so that `Xb = Ib db^2 / Lin` (physics.md
    /// §1) holds with the pixel's own `Lin`. A displaced point past the image's
    /// border is moved onto it; `None` when it falls next to an invalid
    /// background pixel.
    pub fn background_through_layer(
        &self,
        background_distance_mm: &super::ImageBuf<f64>,
        background_ir: &super::ImageBuf<f64>,
        emitted_light: &super::ImageBuf<f64>,
        col: usize,
        row: usize,
    ) -> Option<(f64, f64)> {
        let i = row * background_distance_mm.width + col;
        if !self.refracts() {
            return Some((background_distance_mm.data[i], background_ir.data[i]));
        }
        let [dx, dy] = self.refraction_shift_px;
        // Past the image's border the nearest border pixel stands in (the camera sees no further).
        let u = (col as f64 + dx).clamp(0.0, (background_distance_mm.width - 1) as f64);
        let v = (row as f64 + dy).clamp(0.0, (background_distance_mm.height - 1) as f64);
        let d = bilinear(background_distance_mm, u, v)?;
        let ir = bilinear(background_ir, u, v)?;
        let lin = bilinear(emitted_light, u, v)?;
        let own = emitted_light.data[i];
        (d.is_finite() && ir.is_finite() && lin > 0.0 && own.is_finite()).then_some((d, ir * own / lin))
    }
}

/// Bilinear sample of an image at `(u, v)` (pixel centres at integers); `None`
/// outside the image or next to a non-finite sample.
pub fn bilinear(img: &super::ImageBuf<f64>, u: f64, v: f64) -> Option<f64> {
    if !(u >= 0.0 && v >= 0.0 && u <= (img.width - 1) as f64 && v <= (img.height - 1) as f64) {
        return None;
    }
    let (c0, r0) = (u.floor() as usize, v.floor() as usize);
    let (c1, r1) = ((c0 + 1).min(img.width - 1), (r0 + 1).min(img.height - 1));
    let (tu, tv) = (u - c0 as f64, v - r0 as f64);
    let at = |c: usize, r: usize| img.data[r * img.width + c];
    let top = at(c0, r0) * (1.0 - tu) + at(c1, r0) * tu;
    let bottom = at(c0, r1) * (1.0 - tu) + at(c1, r1) * tu;
    let v = top * (1.0 - tv) + bottom * tv;
    v.is_finite().then_some(v)
}

/// One return: its strength and its equivalent distance.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Return {
    /// Strength in IR counts.
    pub strength: f64,
    /// Equivalent distance (half the travelled path) in mm.
    pub distance_mm: f64,
}

/// The scene along one pixel's ray (physics.md §1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayerScene {
    /// `df`: ray distance to the translucent foreground layer, mm.
    pub foreground_distance_mm: f64,
    /// `db`: ray distance to the opaque background, mm.
    pub background_distance_mm: f64,
    /// `xi`: translucency, 0 opaque .. 1 fully transmissive.
    pub translucency: f64,
    /// `X = rho_f cos(theta_f)`.
    pub foreground_albedo_cos: f64,
    /// `Xb = rho_b cos(theta_b)`.
    pub background_albedo_cos: f64,
    /// `Lin`: emitted light toward this pixel (Eq. 13), counts mm^2.
    pub emitted_light: f64,
    /// `F`: the view factor from the background point behind the pixel to the layer
    /// ([`super::near_wall::view_factor`]); 0 where it is not known or not wanted.
    pub wall_view_factor: f64,
    /// What the pixel sees through a frosted layer of finite extent
    /// ([`super::diffuse::lobe_returns`]); `None` takes the layer as filling the view
    /// (`ψ²`, [`super::diffuse::diffuse_second_return`]).
    pub diffuse_lobe: Option<DiffuseLobe>,
}

/// What the device reports for one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Decoded distance in `[0, R)`, mm; NaN when nothing returned.
    pub distance_mm: f64,
    /// IR value per [`IrMode`], counts.
    pub ir: f64,
    /// The mixed bucket differences (Eq. 5).
    pub buckets: Buckets,
    /// Total light collected (sum of strengths, no offset), counts: sets shot noise.
    pub total_light: f64,
}

/// The forward model: a sensor and the physics options.
#[derive(Debug, Clone)]
pub struct ForwardModel {
    /// The sensor's modulation, waveform and decoder.
    pub sensor: Sensor,
    /// Effects modelled beyond the paper's baseline.
    pub options: ModelOptions,
}

impl ForwardModel {
    /// The paper's model on the given sensor.
    pub fn paper(sensor: Sensor) -> Self {
        Self {
            sensor,
            options: ModelOptions::paper(),
        }
    }

    /// The default physics ([`ModelOptions::physical`]) on `sensor`.
    pub fn physical(sensor: Sensor) -> Self {
        Self {
            sensor,
            options: ModelOptions::physical(),
        }
    }

    /// The returns through a translucent layer (Eq. 1-3), strongest terms
    /// first; writes them into `out` and returns how many.
    pub fn layer_returns(&self, s: &LayerScene, out: &mut [Return; MAX_BOUNCES]) -> usize {
        let o = &self.options;
        let (df, db, xi) = (s.foreground_distance_mm, s.background_distance_mm, s.translucency);
        let (x, xb, lin) = (s.foreground_albedo_cos, s.background_albedo_cos, s.emitted_light);
        // Eq. 1: first bounce, off the layer.
        out[0] = Return {
            strength: (1.0 - xi) * x * lin / (df * df),
            distance_mm: df + o.subsurface_delay_mm,
        };
        // Eq. 2: through the layer, off the background, back through the layer; for a
        // hollow object, through its back wall too.
        let x_p = pow(x, o.transmission_albedo_power);
        let back = df + o.hollow_depth_mm;
        let hollow = o.hollow_depth_mm > 0.0 && back < db;
        let walls = if hollow { xi * xi * x_p } else { 1.0 };
        out[1] = Return {
            strength: xb * xi * xi * x_p * walls * lin / (db * db),
            distance_mm: db,
        };
        // Eq. 3, terms i = 0, 1, ...: inter-reflections between the layers.
        let n = o.bounces.clamp(2, MAX_BOUNCES);
        let sep = db - df;
        let mut fac = xi * xi * x_p * xb * xb * (1.0 - xi) * x;
        for (i, slot) in out.iter_mut().enumerate().take(n).skip(2) {
            let dist = db + (i - 1) as f64 * sep;
            *slot = Return {
                strength: fac * lin / (dist * dist),
                distance_mm: dist,
            };
            fac *= (1.0 - xi) * x * xb;
        }
        let mut n = n;
        let share = o.wall_interreflection * third_return_share(xi, x, xb, s.wall_view_factor);
        if share > 0.0 && n < MAX_BOUNCES {
            out[n] = Return {
                strength: share * out[1].strength,
                distance_mm: third_return_distance(df, db),
            };
            n += 1;
        }
        let diffuse = o.diffuse_transmission.clamp(0.0, 1.0);
        if diffuse > 0.0 && n < MAX_BOUNCES {
            let k = self.sensor.phase(1.0);
            out[n] = match s.diffuse_lobe {
                // The finite layer: `f (L2 / (ξ X^{p/2})) Z_lit + f L2 Z_shadow` at the layer's
                // phase, the background outside the shadow crossing the layer once.
                Some(lobe) => {
                    let once = xb * xi * pow(x, o.transmission_albedo_power / 2.0) * lin / (db * db);
                    let l2 = out[1].strength;
                    let re = once * lobe.lit[0] + l2 * lobe.shadow[0];
                    let im = once * lobe.lit[1] + l2 * lobe.shadow[1];
                    Return {
                        strength: diffuse * re.hypot(im),
                        distance_mm: df + im.atan2(re) / k,
                    }
                }
                None => {
                    let (length, extra_mm) = diffuse_second_return(db - df, k);
                    Return {
                        strength: diffuse * length * out[1].strength,
                        distance_mm: df + extra_mm,
                    }
                }
            };
            out[1].strength *= 1.0 - diffuse;
            n += 1;
        }
        // A hollow object's back wall, of the same material, seen through the front (Eq. 1
        // behind one crossing each way).
        if hollow && n < MAX_BOUNCES {
            out[n] = Return {
                strength: xi * xi * x_p * (1.0 - xi) * x * lin / (back * back),
                distance_mm: back + o.subsurface_delay_mm,
            };
            n += 1;
        }
        n
    }

    /// One opaque surface: `Lin rho cos(theta) / d^2` at `d` (Eq. 1 with xi = 0).
    pub fn opaque_return(distance_mm: f64, albedo_cos: f64, emitted_light: f64) -> Return {
        Return {
            strength: albedo_cos * emitted_light / (distance_mm * distance_mm),
            distance_mm,
        }
    }

    /// Mixes returns in the buckets (Eq. 5), decodes them (Eq. 6, 11) and forms
    /// the IR value (Eq. 7, or the amplitude). With a depth engine on the
    /// sensor the distance and the amplitude are the engine's, from the
    /// returns' phasors at its frequencies ([`super::depth_engine`]); the
    /// buckets stay the sensor's own frequency's.
    pub fn measure(&self, returns: &[Return]) -> Measurement {
        let mut buckets = Buckets::default();
        let mut total = 0.0;
        for r in returns {
            buckets += self.sensor.buckets(r.strength, r.distance_mm);
            total += r.strength;
        }
        let amplitude = self.options.ir_mode == IrMode::Amplitude;
        let (distance_mm, ir) = match self.sensor.engine() {
            Some(e) => {
                let p = e.phasors(&self.sensor, returns);
                let reading = e.read(&self.sensor, &p[..e.len()]);
                (
                    reading.distance_mm,
                    if amplitude { reading.ir_amplitude } else { total },
                )
            }
            None => (
                self.sensor.decode(buckets).unwrap_or(f64::NAN),
                if amplitude { self.own_amplitude(returns) } else { total },
            ),
        };
        let ir = ir + self.options.ambient_offset;
        Measurement {
            distance_mm,
            ir,
            buckets,
            total_light: total,
        }
    }

    /// The measurement of a pixel looking through a layer at a background.
    pub fn measure_layer(&self, s: &LayerScene) -> Measurement {
        let mut r = [Return::default(); MAX_BOUNCES];
        let n = self.layer_returns(s, &mut r);
        self.measure(&r[..n])
    }

    /// The IR value the model predicts for the layer (Eq. 7), without decoding.
    pub fn layer_ir(&self, s: &LayerScene) -> f64 {
        let mut r = [Return::default(); MAX_BOUNCES];
        let n = self.layer_returns(s, &mut r);
        let r = &r[..n];
        let ir = match (self.options.ir_mode, self.sensor.engine()) {
            (IrMode::Sum, _) => r.iter().map(|r| r.strength).sum(),
            (IrMode::Amplitude, None) => self.own_amplitude(r),
            (IrMode::Amplitude, Some(e)) => {
                let p = e.phasors(&self.sensor, r);
                e.ir_amplitude(&p[..e.len()])
            }
        };
        ir + self.options.ambient_offset
    }

    /// The demodulated amplitude `|sum_k L_k exp(i phi_k)|` at the sensor's own frequency.
    fn own_amplitude(&self, returns: &[Return]) -> f64 {
        let [re, im] = self.own_phasor(returns);
        re.hypot(im)
    }

    /// `sum_k L_k exp(i phi_k)` at the sensor's own frequency (real and imaginary parts).
    pub fn own_phasor(&self, returns: &[Return]) -> [f64; 2] {
        let (mut re, mut im) = (0.0, 0.0);
        for r in returns {
            let (s, c) = self.sensor.phase(r.distance_mm).sin_cos();
            re += r.strength * c;
            im += r.strength * s;
        }
        [re, im]
    }

    /// Whether, in any scene, every return's strength is affine in the layer's albedo-cosine
    /// `X` and its distance free of it ([`Self::layer_returns`]): the transmission law's power
    /// 0 (no return through the layer carries `X`) and at most one inter-reflection (Eq. 3's
    /// first term, linear in `X`); a near wall's third return, a frosted layer's diffuse part
    /// and a hollow object's back wall stay so. The returns' phasor is then `X A + C`.
    pub fn returns_affine_in_albedo(&self) -> bool {
        self.options.transmission_albedo_power == 0.0 && self.options.bounces <= 3
    }
}

/// `x^p` with `0^0 = 1` and integer powers fast.
fn pow(x: f64, p: f64) -> f64 {
    if p == 2.0 {
        x * x
    } else if p == 0.0 {
        1.0
    } else if p == 1.0 {
        x
    } else {
        x.powf(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(df: f64, db: f64, xi: f64, x: f64) -> LayerScene {
        LayerScene {
            foreground_distance_mm: df,
            background_distance_mm: db,
            translucency: xi,
            foreground_albedo_cos: x,
            background_albedo_cos: 1.0,
            emitted_light: 1.0e10,
            wall_view_factor: 0.0,
            diffuse_lobe: None,
        }
    }

    /// A frosted layer's lobe with a shadowed and a lit part.
    fn lobe() -> Option<DiffuseLobe> {
        Some(DiffuseLobe {
            lit: [0.21, 0.13],
            shadow: [0.55, 0.31],
        })
    }

    #[test]
    fn returns_said_affine_in_the_albedo_are_and_others_are_not() {
        // The returns' phasor and strengths at X = 0.5 against the mean of those at 0 and 1.
        let off_affine = |m: &ForwardModel, s: &LayerScene| {
            let at = |x: f64| {
                let mut r = [Return::default(); MAX_BOUNCES];
                let n = m.layer_returns(
                    &LayerScene {
                        foreground_albedo_cos: x,
                        ..*s
                    },
                    &mut r,
                );
                let p = m.own_phasor(&r[..n]);
                [p[0], p[1], r[..n].iter().map(|r| r.strength).sum()]
            };
            let (a, b, c) = (at(0.0), at(0.5), at(1.0));
            (0..3)
                .map(|j| (b[j] - 0.5 * (a[j] + c[j])).abs() / c[j].abs().max(b[j].abs()))
                .fold(0.0, f64::max)
        };
        let s = LayerScene {
            wall_view_factor: 0.3,
            diffuse_lobe: lobe(),
            ..scene(1400.0, 2100.0, 0.6, 0.5)
        };
        let mut m = ForwardModel::physical(Sensor::sr4000());
        for (bounces, wall, diffuse, hollow, delay) in [
            (2, 0.0, 0.0, 0.0, 0.0),
            (3, 0.0, 0.8, 0.0, 0.0),
            (3, 1.0, 0.6, 150.0, 12.0),
            (2, 0.0, 0.7, 0.0, 0.0),
        ] {
            m.options.bounces = bounces;
            m.options.wall_interreflection = wall;
            m.options.diffuse_transmission = diffuse;
            m.options.hollow_depth_mm = hollow;
            m.options.subsurface_delay_mm = delay;
            for lobe in [lobe(), None] {
                let s = LayerScene {
                    diffuse_lobe: lobe,
                    ..s
                };
                assert!(m.returns_affine_in_albedo());
                assert!(off_affine(&m, &s) < 1e-12, "{:?}: {}", m.options, off_affine(&m, &s));
            }
        }
        // A second inter-reflection (X^2) or a transmission law with a power is not affine.
        m.options.bounces = 4;
        assert!(!m.returns_affine_in_albedo() && off_affine(&m, &s) > 1e-6);
        m.options.bounces = 3;
        m.options.transmission_albedo_power = 1.0;
        assert!(!m.returns_affine_in_albedo() && off_affine(&m, &s) > 1e-6);
    }

    #[test]
    fn paper_returns_match_eq1_and_eq2() {
        let m = ForwardModel::paper(Sensor::sr4000());
        let s = scene(1000.0, 2000.0, 0.65, 0.6);
        let mut r = [Return::default(); MAX_BOUNCES];
        assert_eq!(m.layer_returns(&s, &mut r), 2);
        let l1 = (1.0 - 0.65) * 0.6 * 1e10 / 1e6;
        let ib = 1e10 / 4e6;
        let l2 = ib * 0.65 * 0.65 * 0.36;
        assert!((r[0].strength - l1).abs() < 1e-9 && r[0].distance_mm == 1000.0);
        assert!((r[1].strength - l2).abs() < 1e-9 && r[1].distance_mm == 2000.0);
        let meas = m.measure_layer(&s);
        assert!((meas.ir - (l1 + l2)).abs() < 1e-9, "Eq. 7: I = L1 + L2");
        assert!(meas.distance_mm > 1000.0 && meas.distance_mm < 2000.0);
    }

    #[test]
    fn higher_bounces_follow_eq3() {
        let mut m = ForwardModel::paper(Sensor::sr4000());
        m.options.bounces = 4;
        let s = LayerScene {
            background_albedo_cos: 0.8,
            ..scene(1500.0, 2000.0, 0.5, 0.7)
        };
        let mut r = [Return::default(); MAX_BOUNCES];
        assert_eq!(m.layer_returns(&s, &mut r), 4);
        for i in 0..2 {
            let dist = 2000.0 + (i + 1) as f64 * 500.0;
            let want = 0.25 * 0.5f64.powi(i + 1) * 0.7f64.powi(i + 3) * 0.8f64.powi(i + 2) * 1e10 / (dist * dist);
            let got = r[2 + i as usize];
            assert!((got.strength - want).abs() < 1e-9 * want, "term {i}");
            assert_eq!(got.distance_mm, dist);
        }
    }

    #[test]
    fn a_near_wall_adds_a_third_return_past_the_background() {
        let mut m = ForwardModel::physical(Sensor::sr4000());
        let s = LayerScene {
            wall_view_factor: 0.27,
            diffuse_lobe: None,
            ..scene(1750.0, 2000.0, 0.65, 0.6)
        };
        let mut r = [Return::default(); MAX_BOUNCES];
        assert_eq!(m.layer_returns(&s, &mut r), 2, "off unless asked for");
        m.options.wall_interreflection = 1.0;
        assert_eq!(m.layer_returns(&s, &mut r), 3);
        let share = 0.27 * 0.35 * 0.6 * (0.65 * 0.27 + 0.73) / 0.65;
        assert!((r[2].strength - share * r[1].strength).abs() < 1e-9 * r[1].strength);
        assert!((r[2].distance_mm - (2000.0 + 250.0 * std::f64::consts::SQRT_2)).abs() < 1e-9);
        let none = LayerScene {
            wall_view_factor: 0.0,
            diffuse_lobe: None,
            ..s
        };
        assert_eq!(m.layer_returns(&none, &mut r), 2, "no view, no third return");
    }

    #[test]
    fn a_hollow_object_adds_its_back_wall_and_dims_the_background() {
        let mut m = ForwardModel::physical(Sensor::sr4000());
        let s = scene(1000.0, 2500.0, 0.6, 0.5);
        let mut one = [Return::default(); MAX_BOUNCES];
        assert_eq!(m.layer_returns(&s, &mut one), 2);
        m.options.hollow_depth_mm = 300.0;
        let mut r = [Return::default(); MAX_BOUNCES];
        assert_eq!(m.layer_returns(&s, &mut r), 3);
        assert_eq!(r[0], one[0], "the front wall is the layer");
        assert!(
            (r[1].strength - 0.36 * one[1].strength).abs() < 1e-9 * one[1].strength,
            "xi^2 once more"
        );
        let back = 0.36 * 0.4 * 0.5 * 1e10 / (1300.0 * 1300.0);
        assert!((r[2].strength - back).abs() < 1e-9 * back && r[2].distance_mm == 1300.0);
        // A back wall behind the background is none.
        let near = scene(2300.0, 2500.0, 0.6, 0.5);
        assert_eq!(m.layer_returns(&near, &mut r), 2);
    }

    #[test]
    fn opaque_pixel_reads_its_distance() {
        let m = ForwardModel::paper(Sensor::sr4000());
        let meas = m.measure(&[ForwardModel::opaque_return(2345.0, 0.5, 1e10)]);
        assert!((meas.distance_mm - 2345.0).abs() < 1e-6);
        let s = scene(1000.0, 2000.0, 0.0, 0.6);
        assert!(
            (m.measure_layer(&s).distance_mm - 1000.0).abs() < 1e-6,
            "xi = 0 is opaque"
        );
    }

    #[test]
    fn paper_law_cannot_reverse_but_double_pass_can() {
        // physics.md's note on Eq. 2: df 800, db 3300, xi 0.91.
        let mut m = ForwardModel::paper(Sensor::sr4000());
        let s = scene(800.0, 3300.0, 0.91, 0.9);
        let paper = m.measure_layer(&s).distance_mm;
        assert!(paper < 3300.0, "paper's Eq. 2 reads {paper}");
        m.options.transmission_albedo_power = 0.0;
        let s = scene(800.0, 3300.0, 0.91, 0.3);
        let double = m.measure_layer(&s).distance_mm;
        assert!(double > 3300.0, "double pass reads {double}");
    }

    #[test]
    fn amplitude_is_smaller_than_sum_when_phases_differ() {
        let mut m = ForwardModel::paper(Sensor::sr4000());
        let s = scene(1000.0, 3000.0, 0.8, 0.8);
        let sum = m.measure_layer(&s).ir;
        m.options.ir_mode = IrMode::Amplitude;
        let amp = m.measure_layer(&s).ir;
        assert!(amp < sum);
        assert!((m.layer_ir(&s) - amp).abs() < 1e-9);
    }

    #[test]
    fn refraction_samples_the_displaced_background() {
        use crate::physics::ImageBuf;
        // A background whose distance grows by 10 mm per column; IR and Lin flat.
        let (w, h) = (8, 4);
        let d = ImageBuf {
            width: w,
            height: h,
            data: (0..w * h).map(|i| 2000.0 + 10.0 * (i % w) as f64).collect(),
        };
        let ir = ImageBuf::filled(w, h, 500.0);
        let lin = ImageBuf::filled(w, h, 1e10);
        let mut o = ModelOptions::default();
        assert_eq!(o.background_through_layer(&d, &ir, &lin, 3, 1), Some((2030.0, 500.0)));
        o.refraction_shift_px = [1.5, 0.0];
        let (db, ib) = o.background_through_layer(&d, &ir, &lin, 3, 1).unwrap();
        assert!((db - 2045.0).abs() < 1e-9 && (ib - 500.0).abs() < 1e-9, "{db} {ib}");
        // Past the border the border stands in.
        o.refraction_shift_px = [5.0, 0.0];
        assert_eq!(
            o.background_through_layer(&d, &ir, &lin, 6, 1).map(|v| v.0),
            Some(2070.0)
        );
    }

    #[test]
    fn subsurface_delay_and_ambient_shift_the_readings() {
        let mut m = ForwardModel::paper(Sensor::sr4000());
        let s = scene(1000.0, 2000.0, 0.0, 0.6);
        m.options.subsurface_delay_mm = 12.0;
        m.options.ambient_offset = 50.0;
        let meas = m.measure_layer(&s);
        assert!((meas.distance_mm - 1012.0).abs() < 1e-6);
        assert!((meas.ir - meas.total_light - 50.0).abs() < 1e-9);
    }
}
