//! The objects stage: each segmented region followed as an object (`physics::materials`),
//! its evidence about ξ gathered frame by frame, its estimate, and its class among the known
//! materials.

use super::*;
use crate::physics::segmentation::Members;

/// The ξ a near wall's view factors are found at before any estimate.
const NOMINAL_XI: f64 = 0.5;

impl Pipeline {
    /// Adds a frame's evidence about ξ (no-op for a fixed ξ), region by region: the objects
    /// stage ([`Materials::add_frame`]) gives each region the object it continues, or starts
    /// one, and that object's estimate is renewed. Records the object in `obs.regions`.
    pub fn add_xi_evidence(&mut self, obs: &mut Observed) {
        let XiChoice::Estimate(method) = self.config.xi else {
            return;
        };
        self.evidence_frames += 1;
        let settings = self.config.xi_settings;
        let single = obs.regions.len() == 1;
        let members = Members::of(&obs.labels, obs.regions.len());
        let mut regions: Vec<RegionEvidence> = (1..=obs.regions.len())
            .map(|l| members.of_label(l))
            .map(|pixels| {
                let (distance_mm, spread_mm) = distance_quartiles(&obs.distance_mm, pixels);
                let rays = pixels
                    .iter()
                    .filter_map(|&p| self.rays.data.get(p as usize))
                    .map(|r| [r.x, r.y, r.z]);
                RegionEvidence {
                    pixels,
                    distance_mm,
                    spread_mm,
                    profile: None,
                    readings: self.pixel_readings(obs, pixels),
                    place: Place::of(rays, distance_mm),
                }
            })
            .collect();
        // Evidence only where it adds (an object standing still repeats itself), the frame's
        // lattice shared among those regions (each at least a fifth of it).
        let needed = self
            .materials
            .needs_evidence(&regions, self.evidence_frames, obs.stamp_ns, &settings);
        let count = needed.iter().filter(|&&n| n).count().max(1);
        let budget = (settings.max_pixels_per_frame / count).max(settings.max_pixels_per_frame / 5);
        // With a near wall's third return, each pixel's view factor from the layer at the ξ
        // known so far (the middle of the range before any).
        let wall_xi = self
            .needs_layer_geometry()
            .then(|| self.xi().map_or(NOMINAL_XI, |e| e.xi));
        for (k, region) in regions.iter_mut().enumerate().filter(|&(k, _)| needed[k]) {
            let observations = if single {
                Some(std::borrow::Cow::Borrowed(&obs.observations))
            } else {
                region_observations(obs, k as u32 + 1).map(std::borrow::Cow::Owned)
            };
            let observations = match (observations, wall_xi) {
                (Some(o), Some(xi)) => self
                    .with_wall_view_factors(&o, xi)
                    .map(std::borrow::Cow::Owned)
                    .or(Some(o)),
                (o, _) => o,
            };
            region.profile = observations.and_then(|observations| self.region_profile(&observations, budget));
        }
        let ids = self
            .materials
            .add_frame(regions, self.evidence_frames, obs.stamp_ns, method, &settings);
        for (region, id) in obs.regions.iter_mut().zip(ids) {
            region.material = id;
        }
    }

    /// The readings of a region's pixels with their noise ([`Self::reading_noise`]), for the
    /// objects stage to tell an object standing still from another put in its place.
    fn pixel_readings(&self, obs: &Observed, pixels: &[u32]) -> Vec<PixelReading> {
        pixels
            .iter()
            .map(|&p| {
                let i = p as usize;
                let Some(o) = obs.observations.get(i) else {
                    return PixelReading::NONE;
                };
                let noise = self.reading_noise(i, o);
                PixelReading {
                    distance_mm: o.distance_mm as f32,
                    ir: o.ir as f32,
                    distance_var: (noise.distance_mm * noise.distance_mm) as f32,
                    ir_var: (noise.ir * noise.ir) as f32,
                }
            })
            .collect()
    }

    /// The estimate ξ of the material with the most evidence, or the given ξ.
    /// `None` when ξ is to be estimated and no region has carried evidence yet.
    pub fn xi(&self) -> Option<XiEstimate> {
        match self.config.xi {
            XiChoice::Fixed(x) => Some(XiEstimate::fixed(x)),
            XiChoice::Estimate(_) => self.main_material().and_then(|m| m.estimate.clone()),
        }
    }

    /// The materials seen since the latch, each with its pooled estimate.
    pub fn materials(&self) -> impl Iterator<Item = &Material> {
        self.materials.iter()
    }

    pub(super) fn main_material(&self) -> Option<&Material> {
        self.materials
            .iter()
            .filter(|m| m.estimate.is_some())
            .max_by_key(|m| m.pixels())
    }

    /// Each region's ξ: its material's estimate (the given ξ when fixed). A region that
    /// carried no evidence of its own (too small) takes the largest material's.
    /// `None` when ξ is to be estimated and there is no estimate at all yet.
    pub fn region_estimates(&self, obs: &Observed) -> Option<Vec<RegionOutput>> {
        Some(self.region_estimates_with(obs, &self.xi()?))
    }

    /// The albedo scale of this run: what `Lin` is (a calibration's, or the background's).
    pub fn albedo_scale(&self) -> AlbedoScale {
        AlbedoScale {
            reference: if self.background.as_ref().is_some_and(|b| b.lin_calibrated) {
                AlbedoReference::LinCalibration
            } else {
                AlbedoReference::Background
            },
            background_albedo: self.config.background_albedo,
        }
    }

    /// An object's class among the known materials, opaque and unknown, from its pooled
    /// evidence (`None` without a materials file).
    pub fn classify(&self, material: &Material) -> Option<Classification> {
        let catalog = self.config.materials.as_ref()?;
        let evidence = translucency::albedo_evidence(material.profiles());
        Some(catalog.classify(evidence.as_ref(), &self.albedo_scale()))
    }

    /// An object's ξ as it is published: its own estimate with its class applied
    /// ([`Self::with_class`]). `None` when ξ is given, or the object has no estimate and no
    /// class gives it one.
    pub fn published_estimate(&self, material: &Material) -> Option<XiEstimate> {
        let XiChoice::Estimate(method) = self.config.xi else {
            return None;
        };
        let (xi, class) = self.published_with_class(material, method);
        (material.estimate.is_some() || class.is_some()).then_some(xi)
    }

    /// An object's ξ as published, and its class: its own estimate (opaque with every ξ where
    /// it has none) with its class applied.
    fn published_with_class(&self, material: &Material, method: XiMethod) -> (XiEstimate, Option<Classification>) {
        let own = material.estimate.clone().unwrap_or_else(|| without_evidence(method));
        self.with_class(material, own)
    }

    /// An object's ξ as its class gives it: a known material's calibrated ξ and interval,
    /// opaque's 0 (its reading kept), or, unknown, `own` (its own estimate). `own` alone
    /// without a materials file.
    fn with_class(&self, material: &Material, own: XiEstimate) -> (XiEstimate, Option<Classification>) {
        let Some(catalog) = self.config.materials.as_deref() else {
            return (own, None);
        };
        let evidence = translucency::albedo_evidence(material.profiles());
        let class = catalog.classify(evidence.as_ref(), &self.albedo_scale());
        let xi = match class.class {
            Class::Known(i) if i < catalog.materials.len() => {
                let m = &catalog.materials[i];
                // The object's own most likely ξ within the material's, where its evidence
                // prefers one; the calibrated ξ where it does not (one pose, say).
                let best = evidence.as_ref().and_then(|e| catalog.best_xi(i, e));
                XiEstimate {
                    xi: best.unwrap_or(m.xi),
                    interval: m.classification_interval(),
                    method: XiMethod::Calibrated,
                    frames: material.frames(),
                    pixels: material.pixels(),
                    note: format!(
                        "material {:?} (probability {:.2}), calibrated from {}",
                        m.name, class.probability, m.recording
                    ),
                    ..own
                }
            }
            Class::Opaque => XiEstimate {
                xi: 0.0,
                interval: [0.0, own.interval[1].max(translucency::OPAQUE_XI)],
                note: format!("opaque (probability {:.2}): its reading is kept", class.probability),
                ..own
            },
            _ => own,
        };
        (xi, Some(class))
    }

    /// The evidence about ξ of a frame's largest region, as [`Self::add_xi_evidence`] computes
    /// it (the same sample, bounds and groups), without pooling it: what a calibration
    /// measures the implied albedo of. `None` when the frame has no region with enough pixels.
    pub fn largest_region_profile(&self, obs: &Observed) -> Option<FrameProfile> {
        let (k, _) = obs.regions.iter().enumerate().max_by_key(|(_, r)| r.pixels)?;
        let observations = region_observations(obs, k as u32 + 1)?;
        self.region_profile(&observations, self.config.xi_settings.max_pixels_per_frame)
    }

    /// A region's evidence about ξ from a lattice of at most `budget` of its pixels; `None`
    /// when the lattice holds fewer than a group's pixels.
    fn region_profile(&self, observations: &SparseImage<PixelObservation>, budget: usize) -> Option<FrameProfile> {
        let settings = &self.config.xi_settings;
        let sample = FrameSample::from_image(observations, &self.rays, None, budget);
        (sample.pixel_count() >= settings.min_group_pixels).then(|| {
            translucency::frame_profile(
                &self.config.model,
                &self.bounds,
                &sample,
                settings,
                translucency::ProfileUse::Estimation,
            )
        })
    }

    /// [`Self::region_estimates`] with the frame's ξ already found. With ξ estimated, a
    /// region of no object with an estimate (too small to carry evidence) is kept as read:
    /// another object's evidence is not its own.
    pub(super) fn region_estimates_with(&self, obs: &Observed, fallback: &XiEstimate) -> Vec<RegionOutput> {
        obs.regions
            .iter()
            .map(|r| {
                let material = r.material.and_then(|id| self.materials.get(id));
                let (id, xi, class) = match (self.config.xi, material) {
                    (XiChoice::Fixed(_), _) => (0, fallback.clone(), None),
                    (XiChoice::Estimate(method), None) => (0, without_evidence(method), None),
                    (XiChoice::Estimate(method), Some(m)) => {
                        let (xi, class) = self.published_with_class(m, method);
                        (if m.estimate.is_some() { m.id } else { 0 }, xi, class)
                    }
                };
                RegionOutput {
                    id,
                    opaque: xi.is_opaque(),
                    xi,
                    pixels: r.pixels,
                    class,
                }
            })
            .collect()
    }
}

/// The estimate of a region that carries no evidence of its own: opaque, the null
/// hypothesis, with every ξ possible.
fn without_evidence(method: XiMethod) -> XiEstimate {
    XiEstimate {
        xi: 0.0,
        interval: [0.0, 1.0],
        method,
        frames: 0,
        pixels: 0,
        profile: vec![],
        note: "too small to carry evidence of its own: kept as read".into(),
    }
}

/// Median and interquartile range of the finite distances at `pixels` (NaN if none), mm.
fn distance_quartiles(distance_mm: &ImageBuf<f64>, pixels: &[u32]) -> (f64, f64) {
    let mut d: Vec<f64> = pixels
        .iter()
        .filter_map(|&i| distance_mm.data.get(i as usize).copied())
        .filter(|d| d.is_finite())
        .collect();
    if d.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    // Three order statistics, each found without sorting the rest.
    let n = d.len();
    let mut nth = |k: usize| *d.select_nth_unstable_by(k, f64::total_cmp).1;
    let (median, upper, lower) = (nth(n / 2), nth(3 * n / 4), nth(n / 4));
    (median, upper - lower)
}

/// The observations of the region labelled `label`.
fn region_observations(obs: &Observed, label: u32) -> Option<SparseImage<PixelObservation>> {
    restrict(&obs.observations, &label_mask(obs, |l| l == label))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_region_without_evidence_is_opaque_with_every_xi_possible() {
        let e = without_evidence(XiMethod::OneMaterial);
        assert_eq!((e.xi, e.interval), (0.0, [0.0, 1.0]));
        assert!(e.is_opaque());
    }

    #[test]
    fn distance_quartiles_give_the_median_and_the_spread_of_the_finite_readings() {
        let d = ImageBuf {
            width: 6,
            height: 1,
            data: vec![1000.0, 1010.0, 1020.0, 1030.0, f64::NAN, 5000.0],
        };
        let (median, iqr) = distance_quartiles(&d, &[0, 1, 2, 3, 4]);
        assert_eq!((median, iqr), (1020.0, 20.0));
        assert!(distance_quartiles(&d, &[4]).0.is_nan());
        // Indices past the image are not read.
        assert_eq!(distance_quartiles(&d, &[0, 99]).0, 1000.0);
    }
}
