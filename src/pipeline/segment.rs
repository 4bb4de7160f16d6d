//! The segmentation stage: the pixels that changed from the latched background, their
//! observations and regions, and whether the camera moved after the latch.

use super::*;
use crate::physics::parallel::filter_map_parts;

/// Fewest segmented pixels whose observations are gathered over the pool.
const PARALLEL_PIXELS: usize = 16 * 1024;

impl Pipeline {
    /// Segments a frame and gathers what the inversion needs.
    pub fn observe(&self, frame: &DepthFrame) -> Result<Observed, PipelineError> {
        check_size(frame, &self.intrinsics)?;
        let bg = self.background.as_ref().ok_or(PipelineError::NoBackground)?;
        let k = &self.intrinsics;
        let d = z_to_ray_distance(&frame.z_mm, &self.scale);
        let range = self.config.model.sensor.unambiguous_range_mm();
        let raw = changed_pixels(
            &d,
            &bg.distance_mm,
            self.config.threshold_mm,
            range,
            self.change_noise.as_ref(),
        );
        let (mask, _) = remove_small_regions(&raw, self.config.min_region_pixels);
        let observation = |i: usize| {
            let ir = frame.ir.data[i] as f64;
            // The background behind the layer (displaced when the model refracts).
            let (db, ib) = if self.config.model.options.refracts() {
                self.config
                    .model
                    .options
                    .background_through_layer(&bg.distance_mm, &bg.ir, &bg.emitted_light, i % k.width, i / k.width)
                    .unwrap_or((f64::NAN, f64::NAN))
            } else {
                (bg.distance_mm.data[i], bg.ir.data[i])
            };
            let o = PixelObservation {
                distance_mm: d.data[i],
                ir,
                background_distance_mm: db,
                background_ir: ib,
                emitted_light: bg.emitted_light.data[i],
                wall_view_factor: 0.0,
                diffuse_lobe: None,
            };
            let ok = ir.is_finite()
                && ir > 0.0
                && o.background_ir > 0.0
                && o.emitted_light.is_finite()
                && o.emitted_light > 0.0;
            ok.then_some(o)
        };
        let too_large = || PipelineError::TooLarge {
            width: k.width,
            height: k.height,
        };
        let pixels = u32::try_from(mask.data.len()).map_err(|_| too_large())?;
        let mut segmented: Vec<u32> = Vec::with_capacity(mask.data.iter().filter(|&&m| m).count());
        segmented.extend((0..pixels).filter(|&i| mask.data[i as usize]));
        let observations = gather_observations(&segmented, k, observation).ok_or_else(too_large)?;
        let translucent_pixels = segmented.len();
        // A pixel's reading noise: the latch's, grown as shot noise where less light returns.
        let fallback = self.config.threshold_mm / NOISE_SIGMAS;
        let noise = |i: usize| {
            let latch = self.change_noise.as_ref().map_or(fallback, |n| n.data[i]);
            let light = frame.ir.data[i] as f64 / bg.ir.data[i];
            if light > 0.0 && latch.is_finite() {
                latch / light.min(1.0).sqrt()
            } else {
                fallback
            }
        };
        let (labels, sizes) = label_regions(&mask, &d, noise, range, self.config.min_region_pixels);
        let (labels, sizes) =
            split_reading_modes(labels, sizes, &d, &bg.distance_mm, range, self.config.min_region_pixels);
        let regions = sizes
            .into_iter()
            .map(|pixels| ObservedRegion { pixels, material: None })
            .collect();
        Ok(Observed {
            stamp_ns: frame.stamp_ns,
            distance_mm: d,
            mask,
            observations,
            translucent_pixels,
            labels,
            regions,
        })
    }

    /// The pixels a frame reads invalid (0 or NaN) where the latched background is valid:
    /// a camera's depth engine invalidates a layer's pixels whose frequencies disagree
    /// beyond its threshold. They stay unmeasured in the outputs (never a distance); this
    /// counts them (0 without a background).
    pub fn unmeasured_pixels(&self, frame: &DepthFrame) -> usize {
        let Some(bg) = self.background.as_ref() else { return 0 };
        let valid = |v: f64| v.is_finite() && v > 0.0;
        frame
            .z_mm
            .data
            .iter()
            .zip(&bg.distance_mm.data)
            .filter(|(&z, &db)| !valid(f64::from(z)) && valid(db))
            .count()
    }

    /// How a frame's readings depart from the background (`None` without one).
    pub fn departure(&self, obs: &Observed) -> Option<Departure> {
        let bg = self.background.as_ref()?;
        let range = self.config.model.sensor.unambiguous_range_mm();
        let mut out = Departure::default();
        for (i, (&d, &db)) in obs.distance_mm.data.iter().zip(&bg.distance_mm.data).enumerate() {
            if !(d.is_finite() && d > 0.0 && db.is_finite() && db > 0.0) {
                continue;
            }
            out.valid += 1;
            let sigma = self.change_noise.as_ref().map_or(0.0, |n| n.data[i]);
            let threshold = change_threshold_mm(self.config.threshold_mm, sigma);
            let diff = wrapped_difference(d, db, range);
            out.nearer += usize::from(diff < -threshold);
            out.farther += usize::from(diff > threshold);
        }
        Some(out)
    }
}

/// The observations `observation` gives at the `segmented` pixels (ascending), over the pool
/// in chunks, laid out once in pixel order; `None` for an image too large to index.
fn gather_observations(
    segmented: &[u32],
    k: &Intrinsics,
    observation: impl Fn(usize) -> Option<PixelObservation> + Sync + Send,
) -> Option<SparseImage<PixelObservation>> {
    let parts = filter_map_parts(segmented, PARALLEL_PIXELS, 1024, |&i| {
        observation(i as usize).map(|o| (i, o))
    });
    let count = parts.iter().map(Vec::len).sum();
    let (mut pixels, mut values) = (Vec::with_capacity(count), Vec::with_capacity(count));
    for (i, o) in parts.into_iter().flatten() {
        pixels.push(i);
        values.push(o);
    }
    SparseImage::from_pixels(k.width, k.height, pixels, values)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(k: &Intrinsics, z: impl Fn(usize, usize) -> f32) -> DepthFrame {
        DepthFrame {
            stamp_ns: 0,
            z_mm: ImageBuf {
                width: k.width,
                height: k.height,
                data: (0..k.width * k.height).map(|i| z(i % k.width, i / k.width)).collect(),
            },
            ir: ImageBuf::filled(k.width, k.height, 1000.0),
        }
    }

    #[test]
    fn the_pixels_that_changed_form_one_region_and_the_camera_has_not_moved() {
        let k = Intrinsics::from_fov(40, 30, 44.0, 35.0);
        let wall: Vec<DepthFrame> = [1999.0, 2000.0, 2001.0]
            .iter()
            .map(|&z| frame(&k, move |_, _| z))
            .collect();
        let pipe = Pipeline::latched(PipelineConfig::default(), k, &wall).expect("a latched wall");
        // A 12 x 10 patch read 500 mm nearer.
        let patch = |c: usize, r: usize| (10..22).contains(&c) && (8..18).contains(&r);
        let obs = pipe
            .observe(&frame(&k, |c, r| if patch(c, r) { 1500.0 } else { 2000.0 }))
            .expect("an observation");
        assert_eq!(obs.translucent_pixels, 120);
        // A pixel read invalid over the valid wall is unmeasured, and counted.
        let mut holed = frame(&k, |c, r| if patch(c, r) { 1500.0 } else { 2000.0 });
        holed.z_mm.data[12 * k.width + 15] = 0.0;
        holed.z_mm.data[13 * k.width + 15] = f32::NAN;
        assert_eq!(pipe.unmeasured_pixels(&holed), 2);
        assert_eq!(pipe.observe(&holed).expect("an observation").translucent_pixels, 118);
        assert_eq!(obs.regions.len(), 1);
        assert_eq!(obs.regions[0].pixels, 120);
        assert!((0..k.width * k.height).all(|i| obs.mask.data[i] == patch(i % k.width, i / k.width)));
        assert!(pipe.departure(&obs).is_none_or(|d| !d.camera_moved()));
        // A frame of the wall as latched changes nothing.
        let still = pipe.observe(&frame(&k, |_, _| 2000.0)).expect("an observation");
        assert_eq!((still.translucent_pixels, still.regions.len()), (0, 0));
    }
}
