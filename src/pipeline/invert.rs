//! The inversion stage: each segmented pixel's layer at the frame's ξ (Eq. 8-12, in
//! batches over the rayon pool), the smooth-surface prior over each region's roots, and
//! the standard deviation of what is published (the roots' scatter about the surface and
//! ξ's share of it).

use nalgebra::Vector3;

use super::{label_mask, restrict, DepthFrame, FrameOutput, Observed, Pipeline, RegionOutput};
use crate::physics::coverage::{layer_coverage, ReadingNoise};
use crate::physics::diffuse::{self, LobeTable};
use crate::physics::near_wall;
use crate::physics::parallel::{map_chunks_ordered, map_ordered};
use crate::physics::segmentation::outline_pixels;
use crate::physics::surface::{LocalSurfaces, Windows};
use crate::physics::{
    foreground_distance_without_slopes, foreground_distances, ImageBuf, PixelObservation, Region, SparseImage,
    XiEstimate,
};

/// Fewest pixels whose inversions are spread over the rayon pool: about half a
/// millisecond of one core's work (see [`map_ordered`]).
const MIN_PARALLEL_PIXELS: usize = 2048;

/// Pixels inverted together ([`foreground_distances`]): enough to fill the
/// vector loops, few enough to stay in cache and to share out over the pool.
const INVERSION_BATCH: usize = 256;

impl Pipeline {
    /// Recovery with each region's own ξ ([`Self::region_estimates`]): opaque regions keep
    /// their readings and leave the mask. `None` when there is no estimate yet.
    pub fn recover_regions(&self, frame: &DepthFrame, obs: &Observed) -> Option<FrameOutput> {
        let fallback = self.xi()?;
        let regions = self.region_estimates_with(obs, &fallback);
        Some(self.recover_with(frame, obs, regions, &fallback))
    }

    /// Per-pixel inversion at one given `xi` for every region, then the smooth-surface prior.
    pub fn recover(&self, frame: &DepthFrame, obs: &Observed, xi: &XiEstimate) -> FrameOutput {
        let regions = obs
            .regions
            .iter()
            .map(|r| RegionOutput {
                id: 0,
                xi: xi.clone(),
                pixels: r.pixels,
                opaque: xi.is_opaque(),
                class: None,
            })
            .collect();
        self.recover_with(frame, obs, regions, xi)
    }

    /// Recovery with each region's ξ: the regions of one material together (the prior's
    /// windows never mix two materials), opaque regions left as read and out of the mask.
    /// `fallback` is the frame's ξ when it has no region.
    fn recover_with(
        &self,
        frame: &DepthFrame,
        obs: &Observed,
        regions: Vec<RegionOutput>,
        fallback: &XiEstimate,
    ) -> FrameOutput {
        let main = regions
            .iter()
            .filter(|r| !r.opaque)
            .max_by_key(|r| r.pixels)
            .or_else(|| regions.iter().max_by_key(|r| r.pixels))
            .map_or_else(|| fallback.clone(), |r| r.xi.clone());
        let mut out = FrameOutput {
            stamp_ns: frame.stamp_ns,
            mask: obs.mask.clone(),
            corrected_z_mm: frame.z_mm.clone(),
            corrected_sigma_mm: ImageBuf::filled(frame.z_mm.width, frame.z_mm.height, f32::NAN),
            xi: main,
            regions,
            translucent_pixels: 0,
            recovered_pixels: 0,
            pinned_pixels: 0,
            unresolved_pixels: 0,
            fit_residual_mm: f64::NAN,
            passthrough: None,
        };
        // Groups of regions recovered together: one per material and ξ.
        let mut groups: Vec<(u32, XiEstimate, Vec<u32>)> = vec![];
        for (k, r) in out.regions.iter().enumerate() {
            let label = k as u32 + 1;
            if r.opaque {
                continue;
            }
            out.translucent_pixels += r.pixels;
            match groups.iter_mut().find(|g| g.0 == r.id && g.1 == r.xi) {
                Some(g) => g.2.push(label),
                None => groups.push((r.id, r.xi.clone(), vec![label])),
            }
        }
        for (k, r) in out.regions.iter().enumerate() {
            if r.opaque {
                let label = k as u32 + 1;
                for (m, l) in out.mask.data.iter_mut().zip(&obs.labels.data) {
                    if *l == label {
                        *m = false;
                    }
                }
            }
        }
        let mut tally = Tally::default();
        let mut uncovered = vec![];
        let frame_edge = outline_pixels(&out.mask, true);
        for (_, xi, labels) in &groups {
            let mut layer = Layer {
                z_mm: &mut out.corrected_z_mm,
                sigma_mm: &mut out.corrected_sigma_mm,
                tally: &mut tally,
                frame_edge: &frame_edge,
                uncovered: &mut uncovered,
            };
            if labels.len() == obs.regions.len() {
                // Every region: the frame's own mask and observations, no copy.
                self.recover_layer(&obs.mask, &obs.observations, xi, &mut layer);
            } else {
                let mask = label_mask(obs, |l| labels.contains(&l));
                let Some(observations) = restrict(&obs.observations, &mask) else {
                    continue;
                };
                self.recover_layer(&mask, &observations, xi, &mut layer);
            }
        }
        for fi in uncovered {
            out.mask.data[fi] = false;
        }
        out.recovered_pixels = tally.recovered;
        out.pinned_pixels = tally.pinned;
        out.unresolved_pixels = tally.unresolved;
        if tally.fitted > 0 {
            out.fit_residual_mm = (tally.res2 / tally.fitted as f64).sqrt();
        }
        out
    }

    /// The layer at the `mask` pixels at one ξ, written into `out` (z and its standard
    /// deviation, mm; NaN where nothing was recovered), with the counts added to its tally.
    fn recover_layer(
        &self,
        obs_mask: &ImageBuf<bool>,
        observations: &SparseImage<PixelObservation>,
        xi_estimate: &XiEstimate,
        out: &mut Layer,
    ) {
        let xi = xi_estimate.xi;
        // With a near wall's third return, each pixel's view factor to the layer first.
        let walled = self
            .needs_layer_geometry()
            .then(|| self.with_wall_view_factors(observations, xi))
            .flatten();
        let observations = walled.as_ref().unwrap_or(observations);
        // The work is done on the rectangle around the translucent pixels (on the prior's
        // block grid, so its windows are those of the whole image): often a small part of it.
        let Some(region) = Region::around(obs_mask, self.config.prior_stride_px) else {
            return;
        };
        let rays = region.crop(&self.rays);
        let mask = region.crop(obs_mask);
        let edge = region.crop(&outline_pixels(obs_mask, false));
        let observed = observed_in(&region, observations);
        // Every observation lies in the rectangle (both come from the frame's mask), so the
        // observations are the frame's own list, not a copy (unless that ever fails).
        let held: std::borrow::Cow<[PixelObservation]> = if observed.len() == observations.count() {
            std::borrow::Cow::Borrowed(observations.values())
        } else {
            observed
                .iter()
                .filter_map(|&(_, fi)| observations.get(fi).copied())
                .collect()
        };
        let roots = self.layer_roots(
            (&observed, &held, observations),
            (&rays, &mask, &edge),
            xi,
            region.width,
        );
        let xi_share = self.xi_share(&observed, &held, &roots.df, region.width, xi_estimate);
        for (i, fi) in region.pixels().filter(|&(i, _)| mask.data[i]) {
            // A pixel on the outline (the image's edge with it) that the layer covers less than
            // half keeps its reading. Beside a pixel off the mask, the layer's distance is the
            // interior's near it: the surface there is extrapolated past the interior's roots.
            let on_outline = out.frame_edge.data[fi];
            let df = if edge.data[i] {
                interior_distance(i, (&mask, &edge), &roots.df).unwrap_or(roots.df[i])
            } else {
                roots.df[i]
            };
            let coverage = observations
                .get(fi)
                .filter(|_| on_outline && df.is_finite())
                .and_then(|o| self.outline_coverage(fi, o, df, xi));
            if let Some((true, _)) = coverage {
                out.uncovered.push(fi);
                continue;
            }
            let floor = coverage.map_or(0.0, |c| c.1);
            let (z, sigma) = if df.is_finite() {
                out.tally.recovered += 1;
                let s = roots.noise[i].hypot(xi_share[i]).max(floor);
                ((df / self.scale.data[fi]) as f32, (s / self.scale.data[fi]) as f32)
            } else {
                (f32::NAN, f32::NAN)
            };
            out.z_mm.data[fi] = z;
            out.sigma_mm.data[fi] = sigma;
        }
        out.tally.pinned += roots.pinned;
        out.tally.unresolved += roots.unresolved;
        out.tally.res2 += roots.res2;
        out.tally.fitted += roots.fitted;
    }

    /// `observations` with each pixel's view factor to the layer found at `xi`
    /// ([`Self::wall_view_factors`]; [`WALL_PASSES`] passes, each from the layer the last
    /// one's factors give), for recovery and ξ's evidence under a model with a near wall's
    /// third return. `None` when there is no layer.
    pub(crate) fn with_wall_view_factors(
        &self,
        observations: &SparseImage<PixelObservation>,
        xi: f64,
    ) -> Option<SparseImage<PixelObservation>> {
        let mut obs_mask = ImageBuf::filled(observations.width, observations.height, false);
        for fi in observations.pixels() {
            obs_mask.data[fi] = true;
        }
        let region = Region::around(&obs_mask, self.config.prior_stride_px)?;
        let rays = region.crop(&self.rays);
        let mask = region.crop(&obs_mask);
        let edge = region.crop(&outline_pixels(&obs_mask, false));
        let observed = observed_in(&region, observations);
        let mut held: Vec<PixelObservation> = observed
            .iter()
            .filter_map(|&(_, fi)| observations.get(fi).copied())
            .collect();
        let mut walled = None;
        // A frosted layer's lobes follow the hypothesised distance themselves (a table along
        // the ray): one pass gives the outline's patches and normal.
        let passes = if self.config.model.options.wall_interreflection > 0.0 {
            WALL_PASSES
        } else {
            1
        };
        for _ in 0..passes {
            let layer_of = walled.as_ref().unwrap_or(observations);
            let roots = self.layer_roots((&observed, &held, layer_of), (&rays, &mask, &edge), xi, region.width);
            let factors = self.wall_view_factors(&observed, &held, &roots.df, &rays, region.width);
            let lobes = self.diffuse_lobes(&observed, &held, &roots.df, &rays, (region.width, &obs_mask));
            walled = Some(with_view_factors(observations, &observed, &factors, &lobes)?);
            held = observed
                .iter()
                .filter_map(|&(_, fi)| walled.as_ref()?.get(fi).copied())
                .collect();
        }
        walled
    }

    /// Whether the model needs the layer's geometry beyond each pixel's ray: a near wall's
    /// view factors, a frosted layer's lobes.
    pub(crate) fn needs_layer_geometry(&self) -> bool {
        let o = &self.config.model.options;
        o.wall_interreflection > 0.0 || o.diffuse_transmission > 0.0
    }

    /// Each observed pixel's lobe through a frosted layer at `df` (by the rectangle's index,
    /// `width` wide; [`diffuse::ImageLayer`]), the layer's outline the frame's `mask` (whole
    /// image), its patches and normal from `df`: found at each `prior_stride_px` block's first
    /// observed pixel and taken by the block's others (relative to each one's own layer).
    /// Empty where the model has no diffuse transmission or there is no latched `Lin`.
    fn diffuse_lobes(
        &self,
        observed: &[(usize, usize)],
        held: &[PixelObservation],
        df: &[f64],
        rays: &ImageBuf<Vector3<f64>>,
        (width, mask): (usize, &ImageBuf<bool>),
    ) -> Vec<Option<LobeTable>> {
        let Some(bg) = self.background.as_ref() else {
            return vec![];
        };
        if !(self.config.model.options.diffuse_transmission > 0.0) {
            return vec![];
        }
        let (w, stride) = (width.max(1), self.config.prior_stride_px.max(1));
        let block = |i: usize| (i / w / stride) * w.div_ceil(stride) + (i % w) / stride;
        let patches = near_wall::layer_patches(df, rays, stride);
        let layer = diffuse::ImageLayer {
            intrinsics: &self.intrinsics,
            mask,
            emitted_light: &bg.emitted_light,
            patches: &patches,
            normal: diffuse::layer_normal(&patches),
        };
        let k = self.config.model.sensor.phase(1.0);
        let mut first_of_block = vec![usize::MAX; block(df.len().saturating_sub(1)) + 1];
        let mut items: Vec<(usize, Vector3<f64>, f64, f64)> = vec![];
        for (&(i, _), o) in observed.iter().zip(held) {
            if !df[i].is_finite() {
                continue;
            }
            if let Some(first) = first_of_block.get_mut(block(i)).filter(|f| **f == usize::MAX) {
                *first = i;
                items.push((i, rays.data[i], df[i], o.background_distance_mm));
            }
        }
        let near = self.bounds.min_distance_mm;
        let lobes = map_ordered(&items, 4, 8, |(_, ray, _, db)| layer.lobe_table(ray, near, *db, k));
        let mut by_index: Vec<Option<LobeTable>> = vec![None; df.len()];
        for (&(i, ..), l) in items.iter().zip(lobes) {
            by_index[i] = Some(l);
        }
        observed
            .iter()
            .map(|&(i, _)| {
                first_of_block
                    .get(block(i))
                    .and_then(|&first| by_index.get(first).copied().flatten())
            })
            .collect()
    }

    /// The layer's roots at ξ over a rectangle `width` wide (its `rays` and `mask`): each
    /// observed pixel inverted, then the smooth-surface prior.
    fn layer_roots(
        &self,
        (observed, held, observations): (&[(usize, usize)], &[PixelObservation], &SparseImage<PixelObservation>),
        (rays, mask, edge): (&ImageBuf<Vector3<f64>>, &ImageBuf<bool>, &ImageBuf<bool>),
        xi: f64,
        width: usize,
    ) -> Roots {
        let per_pixel = self.solve_pixels(observed, held, xi);
        let mut roots = Roots::of(
            rays.data.len(),
            observed,
            &per_pixel,
            rays,
            self.config.max_layer_sigma_mm,
        );
        if self.config.prior_radius_px > 0 {
            self.apply_surface_prior(
                &mut roots,
                (observed, held, observations),
                (rays, mask, edge),
                xi,
                width,
            );
        }
        roots
    }

    /// Each observed pixel's view factor from its background point to the layer at `df`
    /// (by the rectangle's index, `width` wide; [`near_wall::view_factor`]): the layer as
    /// one patch per `prior_stride_px` square block, the factor found at each block's first
    /// observed pixel and taken by the block's others; 0 where the layer is not known.
    fn wall_view_factors(
        &self,
        observed: &[(usize, usize)],
        held: &[PixelObservation],
        df: &[f64],
        rays: &ImageBuf<Vector3<f64>>,
        width: usize,
    ) -> Vec<f64> {
        let (w, stride) = (width.max(1), self.config.prior_stride_px.max(1));
        let block = |i: usize| (i / w / stride) * w.div_ceil(stride) + (i % w) / stride;
        let patches = near_wall::layer_patches(df, rays, stride);
        let mut first_of_block = vec![usize::MAX; block(df.len().saturating_sub(1)) + 1];
        let mut items: Vec<(usize, Vector3<f64>)> = vec![];
        for (&(i, _), o) in observed.iter().zip(held) {
            if let Some(first) = first_of_block.get_mut(block(i)).filter(|f| **f == usize::MAX) {
                *first = i;
                items.push((i, rays.data[i] * o.background_distance_mm));
            }
        }
        let factors = map_ordered(&items, MIN_PARALLEL_PIXELS / 16, 8, |(_, wall)| {
            near_wall::view_factor(wall, &patches)
        });
        let mut by_index = vec![0.0; df.len()];
        for (&(i, _), f) in items.iter().zip(factors) {
            by_index[i] = f;
        }
        observed
            .iter()
            .map(|&(i, _)| {
                first_of_block
                    .get(block(i))
                    .map_or(0.0, |&first| by_index.get(first).copied().unwrap_or(0.0))
            })
            .collect()
    }

    /// Each observed pixel inverted at ξ (`None` where no root), with the layer's standard
    /// deviation from the reading and IR noise: inverted in batches, in parallel over the
    /// current rayon pool when there are enough of them, in pixel order.
    fn solve_pixels(&self, observed: &[(usize, usize)], held: &[PixelObservation], xi: f64) -> Vec<Option<PixelSolve>> {
        map_chunks_ordered(
            observed,
            INVERSION_BATCH,
            MIN_PARALLEL_PIXELS,
            |start: usize, batch: &[(usize, usize)]| {
                let observations = &held[start..start + batch.len()];
                let estimates = foreground_distances(&self.config.model, observations, xi, &self.bounds, true);
                batch
                    .iter()
                    .zip(observations.iter().zip(estimates))
                    .map(|(&(_, fi), (o, est))| {
                        let est = est?;
                        // The layer's noise follows from the reading's through the model's slopes
                        // (implicit function: d df = -(dF/dI dI - dd) / (dF/d df)).
                        let noise = self.reading_noise(fi, o);
                        let dfdi = est.reading_per_ir;
                        let ir_term = if dfdi.is_finite() { noise.ir * dfdi } else { 0.0 };
                        Some(PixelSolve {
                            foreground_distance_mm: est.foreground_distance_mm,
                            residual_mm: est.residual_mm,
                            layer_sigma_mm: noise.distance_mm.hypot(ir_term) / est.slope.abs(),
                            several_roots: est.roots > 1,
                            pinned: est.pinned,
                        })
                    })
                    .collect()
            },
        )
    }

    /// Pixel `fi`'s reading and IR noise: the background's, measured over the latch, scaled
    /// to the pixel's light as shot noise.
    pub(super) fn reading_noise(&self, fi: usize, o: &PixelObservation) -> ReadingNoise {
        let bg = self.background.as_ref();
        let light = (o.ir / o.background_ir).max(1e-9);
        let d_sigma = bg
            .map(|b| b.noise_mm.data[fi])
            .filter(|v| v.is_finite())
            .unwrap_or(self.config.threshold_mm / 3.0);
        let ir_sigma = bg.map(|b| b.ir_noise.data[fi]).filter(|v| v.is_finite()).unwrap_or(0.0);
        ReadingNoise {
            distance_mm: d_sigma / light.sqrt(),
            ir: ir_sigma * light.sqrt(),
        }
    }

    /// Whether a recovered pixel on the mask's outline (`fi`) is covered by the layer at ray
    /// distance `df` less than half, so that its centre sees the background
    /// ([`layer_coverage`]: the background's dimming and the layer's return against the share
    /// covered); `Some(true)` then, `Some(false)` where it is covered by half or more, with
    /// the least σ its depth may have (half the gap to the background where the share's 95 %
    /// interval holds a half, 0 elsewhere). `None` where the model's reading is no phasor.
    fn outline_coverage(&self, fi: usize, o: &PixelObservation, df: f64, xi: f64) -> Option<(bool, f64)> {
        let cov = layer_coverage(&self.config.model, o, df, xi, self.reading_noise(fi, o))?;
        Some(if cov.centre_covered() {
            (false, cov.sigma_floor_mm(o.background_distance_mm - df))
        } else {
            (true, 0.0)
        })
    }

    /// The smooth-surface prior on the roots: where a pixel fits several layers, the one its
    /// neighbourhood's surface is nearest (the first pass took the one nearest the reading);
    /// then every observed pixel inside the object takes the surface, and each its standard
    /// error about it.
    fn apply_surface_prior(
        &self,
        roots: &mut Roots,
        (observed, held, observations): (&[(usize, usize)], &[PixelObservation], &SparseImage<PixelObservation>),
        (rays, mask, edge): (&ImageBuf<Vector3<f64>>, &ImageBuf<bool>, &ImageBuf<bool>),
        xi: f64,
        width: usize,
    ) {
        let windows = Windows {
            radius: self.config.prior_radius_px,
            min_points: 12,
            stride: self.config.prior_stride_px,
        };
        // The surfaces are fitted to the interior's roots: an outline pixel's mixes the layer
        // with what lies beside it and pulls the windows at the edge far.
        let mut interior_points = roots.points.clone();
        for (i, p) in interior_points.data.iter_mut().enumerate() {
            if edge.data[i] {
                *p = Vector3::new(f64::NAN, f64::NAN, f64::NAN);
            }
        }
        let mut surfaces = LocalSurfaces::new(&interior_points, rays, mask, &windows);
        let df = &roots.df;
        let repicks: Vec<Option<f64>> = map_ordered(
            &roots.several_roots,
            MIN_PARALLEL_PIXELS,
            64,
            |&(i, fi): &(usize, usize)| {
                let o = *observations.get(fi)?;
                let t = surfaces.ray_distance(i, rays)?;
                let est = foreground_distance_without_slopes(&self.config.model, &o, xi, &self.bounds, Some(t))?;
                (!est.pinned && (est.foreground_distance_mm - df[i]).abs() > 0.5).then_some(est.foreground_distance_mm)
            },
        );
        let mut repicked = vec![];
        for (&(i, _), d) in roots.several_roots.iter().zip(repicks) {
            if let Some(d) = d {
                roots.df[i] = d;
                roots.points.data[i] = rays.data[i] * d;
                if !edge.data[i] {
                    interior_points.data[i] = roots.points.data[i];
                }
                repicked.push(i);
            }
        }
        // The windows those pixels are in, refitted (the same surfaces as refitting all).
        surfaces.update(&interior_points, rays, &windows, &repicked);
        let own = roots.df.clone();
        // Pixels without their own root but inside the object take the neighbourhood's surface too.
        for (&(i, _), o) in observed.iter().zip(held.iter()) {
            let t = surfaces.ray_distance(i, rays).or_else(|| {
                surfaces
                    .nearest_plane(i, self.config.prior_radius_px, rays)
                    .and_then(|p| p.ray_distance(&rays.data[i]))
            });
            if let Some(t) = t {
                if t > self.bounds.min_distance_mm && t < o.background_distance_mm {
                    roots.df[i] = t;
                }
            }
        }
        roots.noise = surface_standard_error(
            &own,
            &roots.df,
            &roots.noise,
            width,
            self.config.prior_radius_px,
            self.config.max_layer_sigma_mm,
        );
    }

    /// ξ's share of each recovered layer's standard deviation (ray distance, mm, by the
    /// index in the rectangle `width` wide): how far the layer moves between ξ and the ends
    /// of its 95 % interval, the farther end taken as 1.96 σ; 0 for a given ξ (no interval).
    /// Found at one pixel of each `prior_stride_px` square block (the layer moves with ξ as
    /// smoothly as the surface runs) and taken by the block's other pixels.
    fn xi_share(
        &self,
        observed: &[(usize, usize)],
        held: &[PixelObservation],
        df: &[f64],
        width: usize,
        xi: &XiEstimate,
    ) -> Vec<f64> {
        let mut share = vec![0.0; df.len()];
        let ends: Vec<f64> = xi
            .interval
            .iter()
            .copied()
            .filter(|e| (e - xi.xi).abs() > 1e-9)
            .collect();
        if ends.is_empty() {
            return share;
        }
        // An interval that runs on to 1 (past what the model admits) leaves the layer where
        // no reading places it: at ξ 1 it returns nothing, so the layer could be anywhere.
        if xi.interval[1] >= 1.0 {
            for &(i, _) in observed.iter().filter(|(i, _)| df[*i].is_finite()) {
                share[i] = self.config.max_layer_sigma_mm;
            }
            return share;
        }
        let (w, stride) = (width.max(1), self.config.prior_stride_px.max(1));
        let block = |i: usize| (i / w / stride) * w.div_ceil(stride) + (i % w) / stride;
        let recovered: Vec<(usize, &PixelObservation)> = observed
            .iter()
            .zip(held)
            .filter(|((i, _), _)| df[*i].is_finite())
            .map(|(&(i, _), o)| (i, o))
            .collect();
        // Each block's first recovered pixel stands for it.
        let mut first_of_block = vec![usize::MAX; block(df.len().saturating_sub(1)) + 1];
        let mut items: Vec<(usize, &PixelObservation)> = vec![];
        for &(i, o) in &recovered {
            if let Some(first) = first_of_block.get_mut(block(i)).filter(|f| **f == usize::MAX) {
                *first = i;
                items.push((i, o));
            }
        }
        let moves = map_ordered(&items, MIN_PARALLEL_PIXELS, 64, |&(i, o)| {
            let moved = ends.iter().filter_map(|&e| {
                let est = foreground_distance_without_slopes(&self.config.model, o, e, &self.bounds, Some(df[i]))?;
                (!est.pinned).then(|| (est.foreground_distance_mm - df[i]).abs())
            });
            moved.fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))))
        });
        for (&(i, _), m) in items.iter().zip(moves) {
            share[i] = m.map_or(self.config.max_layer_sigma_mm, |m| m / 1.96);
        }
        for &(i, _) in &recovered {
            if let Some(&first) = first_of_block.get(block(i)).filter(|f| **f != usize::MAX) {
                share[i] = share[first];
            }
        }
        share
    }
}

/// Passes of a near wall's view factors and the layer found with them: the view factor
/// grows as the layer nears the wall, and the first layer (without the third return) is
/// too near it.
const WALL_PASSES: usize = 3;

/// The frame's observations with the `observed` pixels' view factors set (`factors` in
/// their order); `None` if the copy cannot be made.
fn with_view_factors(
    observations: &SparseImage<PixelObservation>,
    observed: &[(usize, usize)],
    factors: &[f64],
    lobes: &[Option<LobeTable>],
) -> Option<SparseImage<PixelObservation>> {
    let mut by_pixel: std::collections::HashMap<usize, (f64, Option<LobeTable>)> =
        std::collections::HashMap::with_capacity(observed.len());
    for (j, (&(_, fi), &f)) in observed.iter().zip(factors).enumerate() {
        by_pixel.insert(fi, (f, lobes.get(j).copied().flatten()));
    }
    let mask = ImageBuf {
        width: observations.width,
        height: observations.height,
        data: (0..observations.width * observations.height)
            .map(|fi| observations.get(fi).is_some())
            .collect(),
    };
    SparseImage::from_mask(&mask, |fi| {
        let o = *observations.get(fi)?;
        Some(PixelObservation {
            wall_view_factor: by_pixel.get(&fi).map_or(0.0, |p| p.0),
            diffuse_lobe: by_pixel.get(&fi).and_then(|p| p.1),
            ..o
        })
    })
}

/// Where a layer's recovery is written: z and its standard deviation (mm), and the counts.
struct Layer<'a> {
    z_mm: &'a mut ImageBuf<f32>,
    sigma_mm: &'a mut ImageBuf<f32>,
    tally: &'a mut Tally,
    /// The outline of the frame's mask (what is translucent), the image's edge with it: the
    /// pixels whose covered share is tested.
    frame_edge: &'a ImageBuf<bool>,
    /// Pixels on the outline that the layer covers less than half: they leave the mask.
    uncovered: &'a mut Vec<usize>,
}

/// How far about an outline pixel [`interior_distance`] looks, pixels.
const INTERIOR_REACH: isize = 3;

/// The median layer distance `df` (by the index in `mask`'s rectangle) of the interior
/// pixels (in `mask`, not on its outline `edge`) within [`INTERIOR_REACH`] of pixel `i`;
/// `None` where there are none.
fn interior_distance(i: usize, (mask, edge): (&ImageBuf<bool>, &ImageBuf<bool>), df: &[f64]) -> Option<f64> {
    let (w, h) = (mask.width as isize, mask.height as isize);
    let (c, r) = ((i as isize) % w, (i as isize) / w);
    let mut near: Vec<f64> = (-INTERIOR_REACH..=INTERIOR_REACH)
        .flat_map(|dr| (-INTERIOR_REACH..=INTERIOR_REACH).map(move |dc| (c + dc, r + dr)))
        .filter(|&(cc, rr)| cc >= 0 && rr >= 0 && cc < w && rr < h)
        .map(|(cc, rr)| (rr * w + cc) as usize)
        .filter(|&j| mask.data[j] && !edge.data[j])
        .map(|j| df[j])
        .filter(|d| d.is_finite())
        .collect();
    let d = crate::physics::stats::median_select(&mut near);
    d.is_finite().then_some(d)
}

/// Parameters a window's surface fits (a quadric's six): its value at a pixel averages the
/// noise of `n` roots down by `sqrt(SURFACE_PARAMETERS / n)`.
const SURFACE_PARAMETERS: f64 = 6.0;

/// The standard error of the surface prior's layer at each pixel (mm, by the rectangle's
/// index, `width` wide): the roots' scatter about the surface within `radius` (at least their
/// reading noise, `noise`), averaged down by the window's count. A pixel with no root near
/// gets `unknown_mm`.
pub(crate) fn surface_standard_error(
    roots: &[f64],
    surface: &[f64],
    noise: &[f64],
    width: usize,
    radius: usize,
    unknown_mm: f64,
) -> Vec<f64> {
    let w = width.max(1);
    let h = roots.len() / w;
    // Summed-area tables of (residual^2, noise^2, count) over the pixels with both.
    let mut table = vec![[0.0f64; 3]; (w + 1) * (h + 1)];
    for r in 0..h {
        for c in 0..w {
            let i = r * w + c;
            let e = roots[i] - surface[i];
            let v = if e.is_finite() && noise[i].is_finite() {
                [e * e, noise[i] * noise[i], 1.0]
            } else {
                [0.0; 3]
            };
            let (up, left, diag) = (
                table[r * (w + 1) + c + 1],
                table[(r + 1) * (w + 1) + c],
                table[r * (w + 1) + c],
            );
            table[(r + 1) * (w + 1) + c + 1] = std::array::from_fn(|k| v[k] + up[k] + left[k] - diag[k]);
        }
    }
    (0..roots.len())
        .map(|i| {
            if !surface[i].is_finite() {
                return f64::NAN;
            }
            let (r, c) = (i / w, i % w);
            let (r0, r1, c0, c1) = (
                r.saturating_sub(radius),
                (r + radius + 1).min(h),
                c.saturating_sub(radius),
                (c + radius + 1).min(w),
            );
            let at = |rr: usize, cc: usize| table[rr * (w + 1) + cc];
            let (a, b, cc, d) = (at(r1, c1), at(r0, c1), at(r1, c0), at(r0, c0));
            let sum: [f64; 3] = std::array::from_fn(|k| a[k] - b[k] - cc[k] + d[k]);
            let n = sum[2];
            if n < 1.0 {
                return unknown_mm;
            }
            let scatter2 = (sum[0] / n).max(sum[1] / n);
            (scatter2 * (SURFACE_PARAMETERS / n).min(1.0)).sqrt()
        })
        .collect()
}

/// The observed pixels inside `region`, in pixel order, each as its index in the rectangle
/// and in the image (walking the rectangle's rows: no division per pixel).
fn observed_in(region: &Region, observations: &SparseImage<PixelObservation>) -> Vec<(usize, usize)> {
    let mut observed: Vec<(usize, usize)> = Vec::with_capacity(observations.count());
    let (mut row, mut row_start) = (0, 0);
    let full = region.full_width.max(1);
    for fi in observations.pixels() {
        while fi >= row_start + full {
            (row, row_start) = (row + 1, row_start + full);
        }
        let col = fi - row_start;
        if (region.row0..region.row0 + region.height).contains(&row)
            && (region.col0..region.col0 + region.width).contains(&col)
        {
            observed.push(((row - region.row0) * region.width + col - region.col0, fi));
        }
    }
    observed
}

/// The pixels' own roots in a rectangle (by its index): the layer's distance and standard
/// deviation (NaN where pinned, without a root or too noisy), its points, the pixels with
/// several roots, and the counts.
struct Roots {
    df: Vec<f64>,
    noise: Vec<f64>,
    points: ImageBuf<Vector3<f64>>,
    several_roots: Vec<(usize, usize)>,
    pinned: usize,
    unresolved: usize,
    res2: f64,
    fitted: usize,
}

impl Roots {
    /// The solves of the `observed` pixels of a rectangle of `n` pixels (its `rays`), a layer
    /// kept where its standard deviation is at most `max_sigma_mm`.
    fn of(
        n: usize,
        observed: &[(usize, usize)],
        solves: &[Option<PixelSolve>],
        rays: &ImageBuf<Vector3<f64>>,
        max_sigma_mm: f64,
    ) -> Self {
        let nan = Vector3::new(f64::NAN, f64::NAN, f64::NAN);
        let mut r = Roots {
            df: vec![f64::NAN; n],
            noise: vec![f64::NAN; n],
            points: ImageBuf::filled(rays.width, rays.height, nan),
            several_roots: vec![],
            pinned: 0,
            unresolved: 0,
            res2: 0.0,
            fitted: 0,
        };
        for (&(i, fi), solve) in observed.iter().zip(solves) {
            let Some(est) = *solve else {
                r.pinned += 1;
                continue;
            };
            r.res2 += est.residual_mm * est.residual_mm;
            r.fitted += 1;
            if est.several_roots {
                r.several_roots.push((i, fi));
            }
            if est.pinned {
                r.pinned += 1;
            } else if !(est.layer_sigma_mm <= max_sigma_mm) {
                r.unresolved += 1;
            } else {
                r.df[i] = est.foreground_distance_mm;
                r.noise[i] = est.layer_sigma_mm;
                r.points.data[i] = rays.data[i] * est.foreground_distance_mm;
            }
        }
        r
    }
}

/// Counts of a frame's recovery, summed over its materials.
#[derive(Debug, Clone, Copy, Default)]
struct Tally {
    recovered: usize,
    pinned: usize,
    unresolved: usize,
    res2: f64,
    fitted: usize,
}

/// What recovery keeps of a pixel's inversion ([`crate::physics::LayerEstimate`]'s fields it
/// reads, and the layer's noise).
#[derive(Debug, Clone, Copy)]
struct PixelSolve {
    foreground_distance_mm: f64,
    residual_mm: f64,
    /// The layer's standard deviation from the reading and IR noise, mm.
    layer_sigma_mm: f64,
    several_roots: bool,
    pinned: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn observation(d: f64) -> PixelObservation {
        PixelObservation {
            distance_mm: d,
            ir: 1000.0,
            background_distance_mm: 2000.0,
            background_ir: 800.0,
            emitted_light: 1e10,
            wall_view_factor: 0.0,
            diffuse_lobe: None,
        }
    }

    #[test]
    fn the_observed_pixels_map_into_their_rectangle() {
        let (w, h) = (10, 8);
        let mut mask = ImageBuf::filled(w, h, false);
        for (c, r) in [(3, 2), (4, 2), (6, 5)] {
            mask.data[r * w + c] = true;
        }
        let region = Region::around(&mask, 1).expect("a rectangle");
        let obs = SparseImage::from_mask(&mask, |i| Some(observation(i as f64))).expect("observations");
        let got = observed_in(&region, &obs);
        // The rectangle spans columns 3..=6 and rows 2..=5: 4 wide.
        assert_eq!((region.col0, region.row0, region.width, region.height), (3, 2, 4, 4));
        assert_eq!(got, vec![(0, 23), (1, 24), (3 * 4 + 3, 56)]);
    }

    #[test]
    fn roots_keep_resolved_layers_and_count_the_rest() {
        let (w, h) = (4, 1);
        let rays = ImageBuf {
            width: w,
            height: h,
            data: vec![Vector3::new(0.0, 0.0, 1.0); w * h],
        };
        let solve = |d: f64, sigma: f64, pinned: bool, several: bool| {
            Some(PixelSolve {
                foreground_distance_mm: d,
                residual_mm: 1.0,
                layer_sigma_mm: sigma,
                several_roots: several,
                pinned,
            })
        };
        let observed = [(0, 0), (1, 1), (2, 2), (3, 3)];
        let solves = [
            solve(1000.0, 5.0, false, true),
            solve(1100.0, 500.0, false, false),
            solve(1200.0, 5.0, true, false),
            None,
        ];
        let r = Roots::of(w * h, &observed, &solves, &rays, 100.0);
        assert_eq!(r.df[0], 1000.0);
        assert!(r.df[1..].iter().all(|d| d.is_nan()));
        assert_eq!((r.pinned, r.unresolved, r.fitted), (2, 1, 3));
        assert_eq!(r.several_roots, vec![(0, 0)]);
        assert_eq!(r.points.data[0], Vector3::new(0.0, 0.0, 1000.0));
    }

    #[test]
    fn the_surface_error_averages_the_scatter_down_and_keeps_the_reading_noise() {
        // A 9 x 9 patch, roots scattered +-3 mm about a flat surface, reading noise 1 mm.
        let (w, n) = (9, 81);
        let surface = vec![1000.0; n];
        let roots: Vec<f64> = (0..n).map(|i| 1000.0 + if i % 2 == 0 { 3.0 } else { -3.0 }).collect();
        let noise = vec![1.0; n];
        let se = surface_standard_error(&roots, &surface, &noise, w, 4, f64::NAN);
        // The centre's window holds all 81: sqrt(9 * 6 / 81).
        assert!((se[40] - (9.0f64 * 6.0 / 81.0).sqrt()).abs() < 1e-9, "{}", se[40]);
        // Where the reading noise exceeds the scatter, it is the noise that is averaged.
        let quiet: Vec<f64> = vec![1000.0; n];
        let se = surface_standard_error(&quiet, &surface, &vec![2.0; n], w, 4, f64::NAN);
        assert!((se[40] - (4.0f64 * 6.0 / 81.0).sqrt()).abs() < 1e-9, "{}", se[40]);
        // No surface, no error; no root near, the stated unknown.
        let mut none = surface.clone();
        none[0] = f64::NAN;
        assert!(surface_standard_error(&roots, &none, &noise, w, 4, 7.0)[0].is_nan());
        let empty = vec![f64::NAN; n];
        assert_eq!(surface_standard_error(&empty, &surface, &noise, w, 1, 7.0)[40], 7.0);
    }
}
