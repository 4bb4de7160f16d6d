//! The objects a scene shows, each with its own ξ (physics.md §3, "one
//! material"; shared/design/objects.md): every region of a frame brings its
//! evidence (a [`FrameProfile`]), which joins the object it continues, or
//! starts a new one. Evidence of different objects is never pooled.
//!
//! A region continues an object when it is where the object can be (issue 31):
//! it covers much of the image the object covered in an earlier frame, and its
//! measured distance is where the object's motion puts it. An object carried
//! through the scene moves smoothly: its distance changes by no more than
//! `max_object_speed_m_s` allows between two frames, and, once its speed is
//! known from two frames, departs from that speed by no more than
//! `max_object_acceleration_m_s2` allows. An object may also be put at another
//! pose between two captures (one frame a pose, the paper's own protocol): a
//! region within `max_pose_step_mm` of where the object stood, in 3-D
//! ([`Place`]: its pixels need not overlap the object's last ones, and a pose
//! nearer or farther scales its outline), continues it as a step. Moves and
//! steps are assigned one to one over all regions by least total step; one
//! stands only where no other identity for its object or its region comes
//! within [`STEP_DOUBT_MM`] (shared/design/objects.md, "Stepped poses"): with
//! two objects that could each have gone to either place, the data cannot
//! tell an object moved from one that took another's place, so each region
//! then starts a new object: an undetermined ξ is kept as read, a wrongly
//! pooled one would be corrected wrongly. A region farther off than any step
//! jumped: the scene was cut, and an object continues only where that is
//! beyond doubt: one object before it and one region after.
//!
//! A region whose median distance stays where a still object stood continues it only where
//! its pixels show the object's pattern of readings and IR within their noise, the shift and
//! ratio they share taken out: another object put down in the same place at about the same
//! distance (a swap) reads otherwise pixel by pixel, and is a jump. A moving object's pixels
//! change with its motion; the kinematic bounds alone judge it.
//!
//! Each object takes at most one region of a frame, and each region one
//! object: two regions seen at once are two objects. An object that reappears
//! farther than a step from where it was is a new one.

use super::stats::median_select;
use super::translucency::{self, FrameProfile, XiEstimate, XiMethod, XiSettings, OPAQUE_XI};

/// Least share of the smaller of two regions that the other must cover for the later to
/// continue the earlier's object: an object moves across the image by less than half
/// its size between two frames (a 300 mm object 2 m away carried at 1 m/s and seen at
/// 10 Hz moves by a third of its size; one that moved farther jumped: a cut).
const MIN_OVERLAP: f64 = 0.5;

/// Most a stepped object's size across the view may change between two poses, as a ratio
/// of its RMS radius: its tilt changes a little between poses, and a translucent layer's
/// measured distance (which places it) is pulled towards the background by a share that
/// changes with its distance from it.
const STEP_SIZE_RATIO: f64 = 2.5;

/// Farthest a stepped object moves across the view, in RMS radii of its footprint: its outline
/// projected to the new distance then still covers about half of the new one (a square's
/// half side is 1.2 of its RMS radius). Farther is another object's place (objects put down
/// elsewhere, exchanged), not a step.
const STEP_ACROSS_RADII: f64 = 1.5;

/// How much costlier, in mm of 3-D step, another way of continuing the objects must be for
/// a stepped object's identity to be beyond doubt: the measured distance of a translucent
/// layer places it off its true place by up to this much more in one pose than in another.
const STEP_DOUBT_MM: f64 = 150.0;

/// Most materials kept: past it the one seen longest ago is forgotten.
pub const MAX_MATERIALS: usize = 16;

/// Reading noise moves a region's median distance by this much between frames even when the
/// object stands still, mm. Its changing outline adds a quarter of the region's interquartile range:
/// a plane whose readings spread evenly, a quarter of it hidden or shown at one end, moves its
/// median by that much.
const DISTANCE_SLACK_MM: f64 = 20.0;

/// What an object's pixels show once the shift they share is taken out: over the pixels
/// two frames share, `z^2 = r_d^2 / var(Δd) + r_I^2 / var(ΔI)`, with `r_d` a pixel's change
/// of distance less the median change and `r_I` its IR less the median ratio's share, is
/// about chi-square with 2 degrees of freedom for one object (median 1.39), moved or not.
/// Above this median the pixels show another pattern: another object stands where this
/// one stood. It allows the noise to be underestimated threefold (a mixed pixel's phase
/// noise exceeds what its amplitude says); an object swapped for another reads off by
/// many times that (another tilt along its outline, another albedo or ξ in its IR).
pub const REPEAT_MEDIAN_Z2: f64 = 16.0;

/// Fewest shared pixels with readings in both frames that a comparison is made on.
const MIN_REPEAT_PIXELS: usize = 30;

/// Least shift of distance shared by an object's pixels that counts as moving, in standard
/// errors of the median change (with at least [`DISTANCE_FLOOR_MM`]).
const SHIFT_STANDARD_ERRORS: f64 = 4.0;

/// Least shared shift of distance that counts as moving, mm: light between objects changes
/// as others move about a still one (its reading by a few mm).
const DISTANCE_FLOOR_MM: f64 = 10.0;

/// One pixel's reading and IR with their noise variances, as the objects stage compares
/// them between frames (NaN where the pixel has none).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelReading {
    /// Measured distance, mm.
    pub distance_mm: f32,
    /// IR value, counts.
    pub ir: f32,
    /// Variance of the distance, mm^2.
    pub distance_var: f32,
    /// Variance of the IR value, counts^2 (0 where unknown: the IR is then not compared).
    pub ir_var: f32,
}

impl PixelReading {
    /// A pixel without a reading.
    pub const NONE: Self = Self {
        distance_mm: f32::NAN,
        ir: f32::NAN,
        distance_var: f32::NAN,
        ir_var: 0.0,
    };

    fn usable(&self) -> bool {
        self.distance_mm.is_finite() && self.distance_var > 0.0 && self.ir.is_finite()
    }
}

/// How a region's pixels compare with an object's earlier ones ([`Footprint::compare`]).
#[derive(Debug, Clone, Copy, PartialEq)]
struct PixelChange {
    /// Whether the median change of distance over the shared pixels exceeds noise
    /// ([`SHIFT_STANDARD_ERRORS`], [`DISTANCE_FLOOR_MM`]).
    shifted: bool,
    /// Whether, the shift taken out, the pixels show the same pattern ([`REPEAT_MEDIAN_Z2`]).
    same_pattern: bool,
}

/// The positions `(i, j)` in two ascending pixel lists where they hold the same pixel.
fn shared_positions<'a>(a: &'a [u32], b: &'a [u32]) -> impl Iterator<Item = (usize, usize)> + 'a {
    let (mut i, mut j) = (0, 0);
    std::iter::from_fn(move || {
        while i < a.len() && j < b.len() {
            match a[i].cmp(&b[j]) {
                std::cmp::Ordering::Less => i += 1,
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Equal => {
                    let at = (i, j);
                    i += 1;
                    j += 1;
                    return Some(at);
                }
            }
        }
        None
    })
}

/// Where an object's region was in one frame.
#[derive(Debug, Clone, Default)]
struct Footprint {
    frame: u64,
    /// The frame's stamp, ns.
    stamp_ns: u64,
    /// Median measured distance over the region, mm.
    distance_mm: f64,
    /// Interquartile range of the measured distances over the region, mm.
    spread_mm: f64,
    /// Pixel indices, ascending.
    pixels: Vec<u32>,
    /// Their readings (empty where the region brought none).
    readings: Vec<PixelReading>,
    /// Where it stood in 3-D and how large it was ([`RegionEvidence::place`]).
    place: Place,
}

/// Where a region stands in 3-D, camera frame, mm: the mean of its pixels' unit rays
/// (normalised) at its median measured distance, and the RMS lateral radius of its pixels'
/// rays at that distance (its size across the view). A stepped object is followed by these
/// (shared/design/objects.md, "Stepped poses"): its pixels need not overlap its last ones.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Place {
    /// The centre, mm.
    pub centre_mm: [f64; 3],
    /// The RMS lateral radius, mm (0 where unknown: no place).
    pub radius_mm: f64,
}

impl Place {
    /// A region's place from its pixels' unit rays and its median distance; the default (no
    /// place) without finite rays or distance.
    pub fn of(rays: impl Iterator<Item = [f64; 3]>, distance_mm: f64) -> Self {
        let (mut sum, mut sq, mut n) = ([0.0; 3], 0.0, 0usize);
        for r in rays.filter(|r| r.iter().all(|x| x.is_finite())) {
            for (s, x) in sum.iter_mut().zip(r) {
                *s += x;
            }
            sq += r.iter().map(|x| x * x).sum::<f64>();
            n += 1;
        }
        if n == 0 || !(distance_mm.is_finite() && distance_mm > 0.0) {
            return Self::default();
        }
        let mean = sum.map(|s| s / n as f64);
        let norm = mean.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(norm > 0.0) {
            return Self::default();
        }
        // Mean squared distance of the rays from their mean: sum |r|^2 / n - |mean|^2.
        let spread = (sq / n as f64 - norm * norm).max(0.0).sqrt();
        Self {
            centre_mm: mean.map(|x| x / norm * distance_mm),
            radius_mm: spread * distance_mm,
        }
    }

    fn known(&self) -> bool {
        self.radius_mm > 0.0
    }

    /// The 3-D step from `self` to `other`, mm.
    fn step_to(&self, other: &Place) -> f64 {
        self.centre_mm
            .iter()
            .zip(other.centre_mm)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt()
    }

    /// Whether `other` may be this object stepped to another pose: a step of at most
    /// `max_step_mm`, across the view by at most [`STEP_ACROSS_RADII`] of its size (its
    /// outline projected to the new distance still covers much of the new one), and a size
    /// within [`STEP_SIZE_RATIO`] of its own.
    fn may_step_to(&self, other: &Place, max_step_mm: f64) -> bool {
        let ratio = other.radius_mm / self.radius_mm;
        let [dx, dy, _] = [0, 1, 2].map(|k| other.centre_mm[k] - self.centre_mm[k]);
        let across = (dx * dx + dy * dy).sqrt();
        self.known()
            && other.known()
            && self.step_to(other) <= max_step_mm
            && across <= STEP_ACROSS_RADII * self.radius_mm.max(other.radius_mm)
            && (1.0 / STEP_SIZE_RATIO..=STEP_SIZE_RATIO).contains(&ratio)
    }
}

/// One region of a frame as the objects stage takes it.
#[derive(Debug, Clone)]
pub struct RegionEvidence<'a> {
    /// Its pixel indices, ascending.
    pub pixels: &'a [u32],
    /// Median measured distance over it, mm.
    pub distance_mm: f64,
    /// Interquartile range of the measured distances over it, mm (how far its median
    /// moves when its outline changes).
    pub spread_mm: f64,
    /// Its evidence about ξ (`None` when too small to carry any).
    pub profile: Option<FrameProfile>,
    /// Its pixels' readings, in the order of `pixels` (empty: not compared between frames).
    pub readings: Vec<PixelReading>,
    /// Where it stands in 3-D (the default: unknown, never followed through a step).
    pub place: Place,
}

impl Footprint {
    /// Pixels of `region` (ascending) that this footprint covers too.
    fn overlap(&self, region: &[u32]) -> usize {
        shared_positions(&self.pixels, region).count()
    }

    /// How `region`'s pixels compare with this footprint's over the pixels both hold with
    /// readings; `None` where fewer than [`MIN_REPEAT_PIXELS`].
    fn compare(&self, region: &RegionEvidence) -> Option<PixelChange> {
        if self.readings.len() != self.pixels.len() || region.readings.len() != region.pixels.len() {
            return None;
        }
        let pairs: Vec<(PixelReading, PixelReading)> = shared_positions(&self.pixels, region.pixels)
            .map(|(i, j)| (self.readings[i], region.readings[j]))
            .filter(|(a, b)| a.usable() && b.usable())
            .collect();
        if pairs.len() < MIN_REPEAT_PIXELS {
            return None;
        }
        let f = |x: f32| f64::from(x);
        let shift = median_select(
            &mut pairs
                .iter()
                .map(|(a, b)| f(b.distance_mm) - f(a.distance_mm))
                .collect::<Vec<_>>(),
        );
        let ratio = median_select(
            &mut pairs
                .iter()
                .filter(|(a, _)| a.ir > 0.0)
                .map(|(a, b)| f(b.ir) / f(a.ir))
                .collect::<Vec<_>>(),
        );
        let mut z2: Vec<f64> = pairs
            .iter()
            .map(|(a, b)| {
                let rd = f(b.distance_mm) - f(a.distance_mm) - shift;
                let d_term = rd * rd / (f(a.distance_var) + f(b.distance_var));
                let var_i = f(a.ir_var) * ratio * ratio + f(b.ir_var);
                let ri = f(b.ir) - ratio * f(a.ir);
                d_term
                    + if var_i > 0.0 && ri.is_finite() {
                        ri * ri / var_i
                    } else {
                        0.0
                    }
            })
            .collect();
        let mut var_d: Vec<f64> = pairs
            .iter()
            .map(|(a, b)| f(a.distance_var) + f(b.distance_var))
            .collect();
        // The median's standard error: 1.2533 sd / sqrt(n), with the pixels' typical variance.
        let standard_error = 1.2533 * (median_select(&mut var_d) / pairs.len() as f64).sqrt();
        Some(PixelChange {
            shifted: shift.abs() > (SHIFT_STANDARD_ERRORS * standard_error).max(DISTANCE_FLOOR_MM),
            same_pattern: median_select(&mut z2) <= REPEAT_MEDIAN_Z2,
        })
    }
}

/// One material: its pooled evidence and the estimate from it.
#[derive(Debug, Clone)]
pub struct Material {
    /// Its id, stable while it is kept (1, 2, ...).
    pub id: u32,
    profiles: Vec<FrameProfile>,
    /// The estimate from its pooled evidence (`None` until one exists).
    pub estimate: Option<XiEstimate>,
    /// Where its regions were in the latest frame that had one, and in the one before.
    latest: Footprint,
    before: Footprint,
    /// The interval of its last estimate that decided (a layer, or opaque short of 1).
    last_decided: Option<[f64; 2]>,
    /// Its estimates contradicted each other ([`Material::held_to_its_history`]).
    contradicted: bool,
}

impl Material {
    /// Frames of evidence pooled (a frame counts once for each of its regions).
    pub fn frames(&self) -> usize {
        self.profiles.len()
    }

    /// Its pooled evidence, oldest first.
    pub fn profiles(&self) -> &[FrameProfile] {
        &self.profiles
    }

    /// Pixels of evidence pooled.
    pub fn pixels(&self) -> usize {
        self.profiles.iter().map(|p| p.pixels).sum()
    }

    /// The frame count when a region last joined it.
    pub fn last_seen(&self) -> u64 {
        self.latest.frame
    }

    /// Its footprint from a frame before `frame`.
    fn earlier_than(&self, frame: u64) -> Option<&Footprint> {
        [&self.latest, &self.before]
            .into_iter()
            .find(|f| f.frame < frame && !f.pixels.is_empty())
    }

    /// Pools a frame's evidence and renews the estimate.
    fn pool(&mut self, profile: FrameProfile, method: XiMethod, settings: &XiSettings) {
        if self.profiles.len() >= settings.max_frames_pooled.max(1) {
            self.profiles.remove(0);
        }
        self.profiles.push(profile);
        self.estimate = match estimate(&self.profiles, method, settings) {
            Some(e) => Some(self.held_to_its_history(e)),
            None => self.estimate.take(),
        };
    }

    /// An estimate checked against the object's last one that decided (a layer, or opaque
    /// with an interval short of 1). Where one of two in a row, from evidence a frame apart,
    /// is opaque and the other a layer, and their intervals do not meet, they contradict each
    /// other beyond what either allows: the object's evidence holds what one material does not
    /// explain (another object took over part of its regions, or the model misfits as it
    /// moves). Which holds the data cannot tell, so from then on the object is taken as
    /// opaque with every ξ allowed, as where its near and far poses part and one of them is
    /// opaque ([`translucency::one_material`]). Two layers a little apart are what narrow
    /// intervals of one material show as evidence grows: they are left as they are.
    fn held_to_its_history(&mut self, e: XiEstimate) -> XiEstimate {
        if e.interval != [0.0, 1.0] {
            let now = e.interval;
            if let Some(was) = self.last_decided.replace(now) {
                let apart = now[1] < was[0] || was[1] < now[0];
                let one_opaque = (now[0] <= OPAQUE_XI) != (was[0] <= OPAQUE_XI);
                self.contradicted |= apart && one_opaque;
            }
        }
        if !self.contradicted {
            return e;
        }
        XiEstimate {
            xi: 0.0,
            interval: [0.0, 1.0],
            note: format!(
                "taken as opaque, the data do not say otherwise: two of its estimates in a row, a frame of evidence apart, one opaque and one a layer, had intervals that do not meet: evidence one material does not explain, so no xi is excluded (now: xi {:.3} [{:.3}, {:.3}], {})",
                e.xi, e.interval[0], e.interval[1], e.note
            ),
            ..e
        }
    }

    /// Frames of evidence at the pose `distance_mm` (within the 5 % and 50 mm that separate
    /// poses).
    fn frames_near(&self, distance_mm: f64) -> usize {
        let gap = (0.05 * distance_mm).max(50.0);
        self.profiles
            .iter()
            .filter(|p| (p.median_distance_mm - distance_mm).abs() <= gap)
            .count()
    }

    /// Whether a region's evidence is what this object shows (the likelihood-ratio test of
    /// [`translucency::same_material_statistic`]): where its albedo fits the object's at no ξ,
    /// another object took its place. A region without evidence is not refused.
    fn same_material(&self, evidence: Option<&FrameProfile>) -> bool {
        evidence
            .and_then(|p| translucency::same_material_statistic(&self.profiles, p))
            .is_none_or(|q| q <= translucency::SAME_MATERIAL_LEVEL)
    }

    fn record(&mut self, footprint: Footprint) {
        self.before = std::mem::replace(&mut self.latest, footprint);
    }

    /// How a region at `distance_mm` (spread `spread_mm`) in a frame at `stamp_ns` follows
    /// this object's motion: still, moving as it can, or jumped. `None` without an earlier
    /// footprint.
    fn motion(&self, region: &RegionEvidence, frame: u64, stamp_ns: u64, limits: &Kinematics) -> Option<Motion> {
        let last = self.earlier_than(frame)?;
        let dt_s = stamp_ns.saturating_sub(last.stamp_ns) as f64 * 1e-9;
        let slack_of = |a: &Footprint, b: f64| {
            let spread = [a.spread_mm, b]
                .into_iter()
                .filter(|s| s.is_finite())
                .fold(0.0, f64::max);
            DISTANCE_SLACK_MM + 0.25 * spread
        };
        // The two footprints before, where there are two: the object's speed, and whether it
        // stood still between them.
        let earlier = (self.before.frame < last.frame && !self.before.pixels.is_empty()).then_some(&self.before);
        let speed_mm_s = earlier.and_then(|b| {
            let dt = last.stamp_ns.saturating_sub(b.stamp_ns) as f64 * 1e-9;
            (dt > 0.0).then(|| (last.distance_mm - b.distance_mm) / dt)
        });
        let stood_still =
            earlier.is_some_and(|b| (last.distance_mm - b.distance_mm).abs() <= slack_of(b, last.spread_mm));
        let slack = slack_of(last, region.spread_mm);
        let moved = (region.distance_mm - last.distance_mm).abs();
        if !(moved > slack) {
            // A moving object's pixels change with its motion (it turns, its outline slides
            // over what is behind): the kinematics alone judge it. Where one stood still,
            // its pixels tell whether it stayed.
            match stood_still.then(|| last.compare(region)).flatten() {
                // Where it stood, but its pixels show another pattern: another object took
                // its place.
                Some(c) if !c.same_pattern => return Some(Motion::Replaced),
                // Its pixels moved together by more than noise (the outline's change hides
                // that from the median): the kinematics judge the move.
                Some(c) if c.shifted => {}
                _ => return Some(Motion::Still),
            }
        }
        let off = match speed_mm_s {
            Some(v) => {
                let predicted = last.distance_mm + v * dt_s;
                (region.distance_mm - predicted).abs() - 0.5 * limits.acceleration_m_s2 * 1e3 * dt_s * dt_s
            }
            None => moved - limits.speed_m_s * 1e3 * dt_s,
        };
        Some(if off > slack { Motion::Jumped } else { Motion::Moving })
    }
}

/// How a region's distance follows an object's motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Motion {
    /// Within reading noise and outline of where it was.
    Still,
    /// As far as it can move between the frames.
    Moving,
    /// Farther than it can move between two frames, within a step of `max_pose_step_mm` in
    /// 3-D: put at another pose between captures (one frame a pose, the paper's protocol).
    Stepped,
    /// Farther than that: a cut.
    Jumped,
    /// Another object where it stood (its pixels read otherwise).
    Replaced,
}

/// How fast objects move, and how far they are stepped between captures.
#[derive(Debug, Clone, Copy)]
struct Kinematics {
    speed_m_s: f64,
    acceleration_m_s2: f64,
    max_pose_step_mm: f64,
}

impl Kinematics {
    fn of(settings: &XiSettings) -> Self {
        Self {
            speed_m_s: settings.max_object_speed_m_s,
            acceleration_m_s2: settings.max_object_acceleration_m_s2,
            max_pose_step_mm: settings.max_pose_step_mm,
        }
    }
}

/// A region and an object it may continue.
#[derive(Debug, Clone, Copy)]
struct Pair {
    /// Pixels the region shares with the object's earlier footprint.
    shared: usize,
    /// How far its median distance moved, mm.
    moved: f64,
    /// Its cost: the step from the object's earlier place (3-D where both places are known,
    /// else the change of median distance), mm, less the share of it that the pixels both
    /// hold make up for (the share of the smaller footprint the other covers).
    step_mm: f64,
    motion: Motion,
    /// Whether the region lies within a step of the object's place too (consecutive
    /// captures, [`Place::may_step_to`]): a move that a step would also explain.
    steps: bool,
    region: usize,
    object: usize,
}

/// The materials seen since the background was latched.
#[derive(Debug, Clone, Default)]
pub struct Materials {
    materials: Vec<Material>,
    next_id: u32,
}

impl Materials {
    /// Forgets every material.
    pub fn clear(&mut self) {
        self.materials.clear();
        self.next_id = 0;
    }

    /// The materials, oldest first.
    pub fn iter(&self) -> impl Iterator<Item = &Material> {
        self.materials.iter()
    }

    /// The material with this id.
    pub fn get(&self, id: u32) -> Option<&Material> {
        self.materials.iter().find(|m| m.id == id)
    }

    /// Adds the regions of frame `frame` (a running count, from 1, stamped `stamp_ns`): each
    /// joins the object it continues (one region an object), or, with evidence, starts one.
    /// Returns each region's object id; `None` for a region without evidence that continues
    /// nothing.
    pub fn add_frame(
        &mut self,
        regions: Vec<RegionEvidence>,
        frame: u64,
        stamp_ns: u64,
        method: XiMethod,
        settings: &XiSettings,
    ) -> Vec<Option<u32>> {
        let pairs = self.assignment(&regions, frame, stamp_ns, &Kinematics::of(settings));
        let mut ids = vec![None; regions.len()];
        let mut new = vec![];
        for (k, region) in regions.into_iter().enumerate() {
            let footprint = Footprint {
                frame,
                stamp_ns,
                distance_mm: region.distance_mm,
                spread_mm: region.spread_mm,
                pixels: region.pixels.to_vec(),
                readings: region.readings,
                place: region.place,
            };
            match (pairs[k], region.profile) {
                (Some(i), profile) => {
                    let m = &mut self.materials[i];
                    if let Some(p) = profile {
                        m.pool(p, method, settings);
                    }
                    m.record(footprint);
                    ids[k] = Some(m.id);
                }
                (None, Some(p)) => new.push((k, p, footprint)),
                (None, None) => {}
            }
        }
        // New objects last: starting one may forget the oldest, which moves the indices.
        for (k, p, footprint) in new {
            let i = self.start(p, method, settings);
            let m = &mut self.materials[i];
            m.record(footprint);
            ids[k] = Some(m.id);
        }
        ids
    }

    /// Which object each region continues: among the pairs [`Self::candidates`] allows whose
    /// evidence is the object's, the pairs sharing most pixels first, each region and each
    /// object taken once.
    fn assignment(
        &self,
        regions: &[RegionEvidence],
        frame: u64,
        stamp_ns: u64,
        limits: &Kinematics,
    ) -> Vec<Option<usize>> {
        let mut pairs = self.candidates(regions, frame, stamp_ns, limits);
        pairs.retain(|p| self.materials[p.object].same_material(regions[p.region].profile.as_ref()));
        self.pick(pairs, regions.len())
            .into_iter()
            .map(|p| p.map(|p| p.object))
            .collect()
    }

    /// The pairs where the object's motion allows the region to continue it: a region that
    /// covers at least [`MIN_OVERLAP`] of the smaller of it and the object's earlier region,
    /// still or moving as it can; or one within a step of `max_pose_step_mm` of its earlier
    /// place in 3-D (its pixels need not overlap), stepped to another pose. Those that stand
    /// ([`Self::filter_candidates`]).
    fn candidates(&self, regions: &[RegionEvidence], frame: u64, stamp_ns: u64, limits: &Kinematics) -> Vec<Pair> {
        let pairs = self.candidates_raw(regions, frame, stamp_ns, limits);
        self.filter_candidates(pairs, regions, frame, limits)
    }

    fn candidates_raw(&self, regions: &[RegionEvidence], frame: u64, stamp_ns: u64, limits: &Kinematics) -> Vec<Pair> {
        let mut pairs = vec![];
        for (i, m) in self.materials.iter().enumerate() {
            let Some(before) = m.earlier_than(frame) else {
                continue;
            };
            for (k, r) in regions.iter().enumerate() {
                let shared = before.overlap(r.pixels);
                let smaller = before.pixels.len().min(r.pixels.len()).max(1);
                let overlaps = shared as f64 / smaller as f64 >= MIN_OVERLAP;
                // A step is between two captures in a row: an object unseen for a frame that
                // reappears a step away may as well be another put where it stood.
                let steps = before.frame + 1 == frame && before.place.may_step_to(&r.place, limits.max_pose_step_mm);
                if !overlaps && !steps {
                    continue;
                }
                let motion = match m.motion(r, frame, stamp_ns, limits) {
                    Some(Motion::Replaced) | None => continue,
                    Some(Motion::Jumped) if steps => Motion::Stepped,
                    // Without overlap only a step continues it.
                    Some(Motion::Still | Motion::Moving) if !overlaps => Motion::Stepped,
                    Some(motion) => motion,
                };
                let moved = (r.distance_mm - before.distance_mm).abs();
                // The pixels it shares with where the object was speak for it as much as
                // nearness: the cost of a pair is its step less that share of it.
                let share = shared as f64 / smaller as f64;
                let step_mm = if before.place.known() && r.place.known() {
                    before.place.step_to(&r.place)
                } else {
                    moved
                } * (1.0 - share.min(1.0));
                pairs.push(Pair {
                    shared,
                    moved,
                    step_mm,
                    motion,
                    steps,
                    region: k,
                    object: i,
                });
            }
        }
        pairs
    }

    /// The pairs that stand among `pairs` ([`Self::candidates`]): still ones; moving and
    /// stepped ones where the assignment takes them beyond doubt ([`Self::moves_that_stand`]);
    /// jumps only where one object and one region leave no doubt at all.
    fn filter_candidates(
        &self,
        pairs: Vec<Pair>,
        regions: &[RegionEvidence],
        frame: u64,
        limits: &Kinematics,
    ) -> Vec<Pair> {
        let beyond_doubt = regions.len() == 1 && self.seen_in_latest_frame(frame) == 1;
        let stands = self.moves_that_stand(&pairs, limits);
        // A cut: a region where objects were, each farther than it can have moved or stepped
        // (a step that does not stand counts), and at least one of them continued by no other
        // region (it may be that object, moved away): then an object that seems to have moved
        // may as well be another put in its place. A region beside an object that another
        // region continues is a new object entering its outline, not a cut.
        let jumped: Vec<bool> = pairs
            .iter()
            .zip(&stands)
            .map(|(p, &ok)| p.motion == Motion::Jumped || (p.motion == Motion::Stepped && !ok))
            .collect();
        let continued = |object: usize| pairs.iter().zip(&jumped).any(|(p, &j)| p.object == object && !j);
        let cut = (0..regions.len()).any(|k| {
            let of_region: Vec<(&Pair, bool)> = pairs
                .iter()
                .zip(jumped.iter().copied())
                .filter(|(p, _)| p.region == k)
                .collect();
            !of_region.is_empty()
                && of_region.iter().all(|&(_, j)| j)
                && of_region.iter().any(|(p, _)| !continued(p.object))
        });
        pairs
            .into_iter()
            .zip(stands)
            .filter(|(p, stands)| match p.motion {
                Motion::Still => true,
                // A cut elsewhere casts doubt on a move, not on one a step explains as well:
                // that stands as a step would.
                Motion::Moving => beyond_doubt || (*stands && (!cut || p.steps)),
                Motion::Stepped => beyond_doubt || *stands,
                Motion::Jumped => beyond_doubt,
                Motion::Replaced => false,
            })
            .map(|(p, _)| p)
            .collect()
    }

    /// Which moving and stepped pairs stand (objects.md, "Stepped poses"). Among the objects
    /// and regions no still pair holds, the one-to-one assignment of least total step (3-D
    /// where both places are known, else the change of median distance; an object left without
    /// a region costs `max_pose_step_mm`) is found. A pair stands where that assignment takes
    /// it and every other identity for its object or its region (the object to another region,
    /// or another object to this region, the rest assigned at least cost) costs at least
    /// [`STEP_DOUBT_MM`] more: else two objects could each have gone to either place, and the
    /// data cannot tell which. One flag a pair, false but for moving and stepped ones.
    fn moves_that_stand(&self, pairs: &[Pair], limits: &Kinematics) -> Vec<bool> {
        let moves = |p: &Pair| matches!(p.motion, Motion::Moving | Motion::Stepped);
        let held_region = |k: usize| pairs.iter().any(|p| p.region == k && p.motion == Motion::Still);
        let held_object = |i: usize| pairs.iter().any(|p| p.object == i && p.motion == Motion::Still);
        let open: Vec<&Pair> = pairs
            .iter()
            .filter(|p| moves(p) && !held_region(p.region) && !held_object(p.object))
            .filter(|p| p.step_mm.is_finite())
            .collect();
        let mut rows: Vec<usize> = open.iter().map(|p| p.object).collect();
        let mut cols: Vec<usize> = open.iter().map(|p| p.region).collect();
        for v in [&mut rows, &mut cols] {
            v.sort_unstable();
            v.dedup();
        }
        let step = |i: usize, k: usize| {
            open.iter()
                .find(|p| p.object == i && p.region == k)
                .map_or(f64::INFINITY, |p| p.step_mm)
        };
        let leave = limits.max_pose_step_mm.max(1.0);
        let cost = |forced: Option<(usize, usize)>| {
            let (r, c): (Vec<usize>, Vec<usize>) = match forced {
                Some((i, k)) => (
                    rows.iter().copied().filter(|&x| x != i).collect(),
                    cols.iter().copied().filter(|&x| x != k).collect(),
                ),
                None => (rows.clone(), cols.clone()),
            };
            let m: Vec<Vec<f64>> = r.iter().map(|&i| c.iter().map(|&k| step(i, k)).collect()).collect();
            let (total, assigned) = least_cost_assignment(&m, leave);
            let pairs: Vec<(usize, usize)> = assigned
                .iter()
                .enumerate()
                .filter_map(|(a, b)| Some((r[a], c[(*b)?])))
                .collect();
            (total + forced.map_or(0.0, |(i, k)| step(i, k)), pairs)
        };
        let (best, chosen) = cost(None);
        // Another identity for a pair's object or region: sharing one of the two, not both.
        let other = |(i, k): (usize, usize), q: (usize, usize)| (q.0 == i) != (q.1 == k);
        // The alternatives to the chosen pairs that come near, each assignment solved once.
        let near: Vec<(usize, usize)> = open
            .iter()
            .map(|q| (q.object, q.region))
            .filter(|&q| chosen.iter().any(|&c| other(c, q)))
            .filter(|&q| cost(Some(q)).0 < best + STEP_DOUBT_MM)
            .collect();
        pairs
            .iter()
            .map(|p| {
                let pair = (p.object, p.region);
                moves(p) && chosen.contains(&pair) && !near.iter().any(|&q| other(pair, q))
            })
            .collect()
    }

    /// Each region's pair: the objects seen most recently first (an object lost for a frame
    /// does not take a region from one that continued it since), then most pixels shared,
    /// then least moved; each region and each object taken once.
    fn pick(&self, mut pairs: Vec<Pair>, regions: usize) -> Vec<Option<Pair>> {
        let seen = |p: &Pair| self.materials[p.object].latest.frame;
        let stepped = |p: &Pair| p.motion == Motion::Stepped;
        pairs.sort_by(|a, b| {
            seen(b)
                .cmp(&seen(a))
                .then(stepped(a).cmp(&stepped(b)))
                .then(b.shared.cmp(&a.shared))
                .then(a.step_mm.total_cmp(&b.step_mm))
                .then(a.moved.total_cmp(&b.moved))
        });
        let mut region_to = vec![None; regions];
        let mut taken = vec![false; self.materials.len()];
        for p in pairs {
            if region_to[p.region].is_none() && !taken[p.object] {
                region_to[p.region] = Some(p);
                taken[p.object] = true;
            }
        }
        region_to
    }

    /// Which regions of a frame bring evidence worth computing (their `profile` is not looked
    /// at): all but those standing still where their object has `frames_per_pose` frames of
    /// evidence already (a still object's next frame repeats what it showed).
    pub fn needs_evidence(
        &self,
        regions: &[RegionEvidence],
        frame: u64,
        stamp_ns: u64,
        settings: &XiSettings,
    ) -> Vec<bool> {
        let pairs = self.candidates(regions, frame, stamp_ns, &Kinematics::of(settings));
        self.pick(pairs, regions.len())
            .iter()
            .zip(regions)
            .map(|(p, r)| match p {
                Some(p) if p.motion == Motion::Still => {
                    self.materials[p.object].frames_near(r.distance_mm) < settings.frames_per_pose
                }
                _ => true,
            })
            .collect()
    }

    /// Objects seen in the latest frame before `frame` that had any.
    fn seen_in_latest_frame(&self, frame: u64) -> usize {
        let seen = |m: &Material| m.earlier_than(frame).map(|f| f.frame);
        let latest = self.materials.iter().filter_map(seen).max();
        self.materials
            .iter()
            .filter(|m| latest.is_some() && seen(m) == latest)
            .count()
    }

    /// A new material of this evidence; the one seen longest ago goes if there are too many.
    fn start(&mut self, profile: FrameProfile, method: XiMethod, settings: &XiSettings) -> usize {
        if self.materials.len() >= MAX_MATERIALS {
            if let Some(oldest) = (0..self.materials.len()).min_by_key(|&i| self.materials[i].last_seen()) {
                self.materials.remove(oldest);
            }
        }
        self.next_id = self.next_id.wrapping_add(1).max(1);
        let profiles = vec![profile];
        self.materials.push(Material {
            id: self.next_id,
            estimate: estimate(&profiles, method, settings),
            profiles,
            latest: Footprint::default(),
            before: Footprint::default(),
            last_decided: None,
            contradicted: false,
        });
        let i = self.materials.len() - 1;
        let m = &mut self.materials[i];
        m.estimate = m.estimate.take().map(|e| m.held_to_its_history(e));
        i
    }
}

/// The least-cost one-to-one assignment of rows to columns (the Hungarian method, Kuhn and
/// Munkres), each row left unassigned at cost `leave` if that is cheaper; an infinite cost
/// forbids a pair. Returns the total and each row's column.
fn least_cost_assignment(cost: &[Vec<f64>], leave: f64) -> (f64, Vec<Option<usize>>) {
    let n = cost.len();
    let m = cost.first().map_or(0, Vec::len);
    // Columns: the m real ones, then one "left" column a row (the others' forbidden).
    let forbidden = 1e3 * leave * (n + 1) as f64;
    let at = |i: usize, j: usize| -> f64 {
        if j < m {
            cost[i].get(j).copied().filter(|c| c.is_finite()).unwrap_or(forbidden)
        } else if j - m == i {
            leave
        } else {
            forbidden
        }
    };
    let cols = m + n;
    // Potentials and matching, 1-based with 0 as the free slot.
    let (mut u, mut v) = (vec![0.0; n + 1], vec![0.0; cols + 1]);
    let (mut row_of, mut way) = (vec![0usize; cols + 1], vec![0usize; cols + 1]);
    for i in 1..=n {
        row_of[0] = i;
        let mut j0 = 0;
        let mut min_v = vec![f64::INFINITY; cols + 1];
        let mut used = vec![false; cols + 1];
        loop {
            used[j0] = true;
            let i0 = row_of[j0];
            let (mut delta, mut j1) = (f64::INFINITY, 0);
            for j in 1..=cols {
                if used[j] {
                    continue;
                }
                let c = at(i0 - 1, j - 1) - u[i0] - v[j];
                if c < min_v[j] {
                    min_v[j] = c;
                    way[j] = j0;
                }
                if min_v[j] < delta {
                    delta = min_v[j];
                    j1 = j;
                }
            }
            for j in 0..=cols {
                if used[j] {
                    u[row_of[j]] += delta;
                    v[j] -= delta;
                } else {
                    min_v[j] -= delta;
                }
            }
            j0 = j1;
            if row_of[j0] == 0 {
                break;
            }
        }
        loop {
            let j1 = way[j0];
            row_of[j0] = row_of[j1];
            j0 = j1;
            if j0 == 0 {
                break;
            }
        }
    }
    let mut assigned = vec![None; n];
    let mut total = 0.0;
    for j in 1..=cols {
        let i = row_of[j];
        if i == 0 {
            continue;
        }
        total += at(i - 1, j - 1);
        if j <= m {
            assigned[i - 1] = Some(j - 1);
        }
    }
    (total, assigned)
}

fn estimate(profiles: &[FrameProfile], method: XiMethod, settings: &XiSettings) -> Option<XiEstimate> {
    match method {
        XiMethod::Eq12Residual => translucency::eq12_residual(profiles),
        _ => {
            translucency::one_material(profiles).map(|e| translucency::with_model_error(e, settings.xi_model_error_sd))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::translucency::xi_grid;

    /// Evidence that carries no estimate: identity is what these tests look at.
    fn evidence() -> FrameProfile {
        let n = xi_grid().len();
        FrameProfile {
            groups: vec![vec![]; n],
            pinned_fraction: vec![0.0; n],
            eq12: vec![0.0; n],
            truth: vec![Default::default(); n],
            pixels: 100,
            median_distance_mm: f64::NAN,
        }
    }

    fn region(pixels: &[u32], distance_mm: f64) -> RegionEvidence<'_> {
        RegionEvidence {
            pixels,
            distance_mm,
            spread_mm: 0.0,
            profile: Some(evidence()),
            readings: vec![],
            place: Place::default(),
        }
    }

    /// A region placed in 3-D: centred at `(x, y, z)` mm with an RMS radius of 100 mm.
    fn placed(pixels: &[u32], x: f64, y: f64, z: f64) -> RegionEvidence<'_> {
        RegionEvidence {
            place: Place {
                centre_mm: [x, y, z],
                radius_mm: 100.0,
            },
            ..region(pixels, (x * x + y * y + z * z).sqrt())
        }
    }

    const FRAME_NS: u64 = 100_000_000; // 10 Hz

    fn estimate_at(xi: f64, interval: [f64; 2]) -> XiEstimate {
        XiEstimate {
            xi,
            interval,
            method: XiMethod::OneMaterial,
            frames: 0,
            pixels: 0,
            profile: vec![],
            note: String::new(),
        }
    }

    /// The estimates an object's growing evidence gave, frame by frame, as it holds them.
    fn held(estimates: &[(f64, [f64; 2])]) -> Vec<(f64, [f64; 2])> {
        let mut objects = Materials::default();
        let i = objects.start(evidence(), XiMethod::OneMaterial, &XiSettings::default());
        let m = &mut objects.materials[i];
        estimates
            .iter()
            .map(|&(xi, iv)| {
                let e = m.held_to_its_history(estimate_at(xi, iv));
                (e.xi, e.interval)
            })
            .collect()
    }

    #[test]
    fn an_object_whose_estimates_turn_from_a_layer_to_opaque_beyond_their_intervals_is_kept_as_read() {
        // A region that followed a sheet and then a box that took its place (rendered
        // video_05's, online): a layer twice, then opaque with an interval that does not reach
        // it, then a layer again. From the contradiction on, every ξ is allowed and none applied.
        let got = held(&[
            (0.716, [0.696, 0.737]),
            (0.713, [0.673, 0.740]),
            (0.0, [0.0, 0.304]),
            (0.714, [0.676, 0.747]),
        ]);
        assert_eq!(got[..2], [(0.716, [0.696, 0.737]), (0.713, [0.673, 0.740])]);
        assert!(got[2..].iter().all(|&e| e == (0.0, [0.0, 1.0])), "{got:?}");
        // One material's evidence near the test's edge (rendered video_00's ξ 0.57 sheet):
        // opaque with an interval that reaches the layer's, then the layer; and two layers a
        // little apart as the intervals narrow. Nothing is changed.
        let steady = [
            (0.0, [0.0, 0.770]),
            (0.573, [0.445, 0.682]),
            (0.0, [0.0, 0.770]),
            (0.551, [0.417, 0.669]),
            (0.879, [0.858, 0.893]),
            (0.914, [0.898, 0.927]),
            (0.0, [0.0, 1.0]),
        ];
        assert_eq!(held(&steady), steady);
    }

    fn add(objects: &mut Materials, frame: u64, regions: Vec<RegionEvidence>) -> Vec<Option<u32>> {
        objects.add_frame(
            regions,
            frame,
            frame * FRAME_NS,
            XiMethod::OneMaterial,
            &XiSettings::default(),
        )
    }

    #[test]
    fn an_object_that_moves_a_little_keeps_its_identity() {
        let mut objects = Materials::default();
        let a: Vec<u32> = (0..400).collect();
        let b: Vec<u32> = (40..440).collect();
        let first = add(&mut objects, 1, vec![region(&a, 1000.0)]);
        let second = add(&mut objects, 2, vec![region(&b, 1040.0)]);
        assert_eq!(first, second);
        assert_eq!(objects.get(first[0].unwrap()).unwrap().frames(), 2);
    }

    #[test]
    fn two_regions_seen_at_once_are_two_objects() {
        let mut objects = Materials::default();
        let whole: Vec<u32> = (0..800).collect();
        let left: Vec<u32> = (0..400).collect();
        let right: Vec<u32> = (400..800).collect();
        let first = add(&mut objects, 1, vec![region(&whole, 1000.0)]);
        let ids = add(&mut objects, 2, vec![region(&left, 1000.0), region(&right, 1500.0)]);
        assert_ne!(ids[0], ids[1]);
        // The one object continues into one of them only, the other is new.
        assert_eq!(ids.iter().filter(|&&id| id == first[0]).count(), 1);
        assert_eq!(objects.iter().count(), 2);
    }

    #[test]
    fn an_object_entering_another_ones_outline_is_no_cut() {
        let mut objects = Materials::default();
        let (a, b): (Vec<u32>, Vec<u32>) = ((0..400).collect(), (1000..1400).collect());
        let first = add(&mut objects, 1, vec![region(&a, 1000.0), region(&b, 2000.0)]);
        // `a` is carried 100 mm nearer; a box enters at 2500 mm over part of `b`'s outline
        // while `b` stays: the box is a new object, and `a` and `b` continue.
        let (b_now, entering): (Vec<u32>, Vec<u32>) = ((1000..1300).collect(), (1300..1400).collect());
        let second = add(
            &mut objects,
            2,
            vec![region(&a, 1100.0), region(&b_now, 2000.0), region(&entering, 2500.0)],
        );
        assert_eq!(second[..2], first[..]);
        assert!(second[2].is_some() && !first.contains(&second[2]));
    }

    #[test]
    fn an_object_lost_for_a_frame_does_not_take_a_region_from_the_one_that_continued_it() {
        let mut objects = Materials::default();
        let all: Vec<u32> = (0..400).collect();
        let part: Vec<u32> = (100..400).collect();
        let other: Vec<u32> = (1000..1400).collect();
        let first = add(&mut objects, 1, vec![region(&all, 1000.0)]);
        // A jump of 300 mm in 0.1 s with another object in view: a cut, a new object.
        let second = add(&mut objects, 2, vec![region(&part, 1300.0), region(&other, 2000.0)]);
        assert_ne!(first[0], second[0]);
        // The region grows back over the first object's old outline: it shares more pixels
        // with that object, seen two frames ago, but continues the one seen in the last.
        let third = add(&mut objects, 3, vec![region(&all, 1310.0), region(&other, 2000.0)]);
        assert_eq!(third, second);
    }

    #[test]
    fn a_jump_with_several_objects_in_view_starts_new_objects() {
        let mut objects = Materials::default();
        let (a, b): (Vec<u32>, Vec<u32>) = ((0..400).collect(), (1000..1400).collect());
        let first = add(&mut objects, 1, vec![region(&a, 1000.0), region(&b, 2000.0)]);
        // 2 m/s for 0.1 s is 200 mm (with 20 mm slack): 300 mm is a cut, and with two
        // objects in view either may have taken the other's place.
        let second = add(&mut objects, 2, vec![region(&a, 1300.0), region(&b, 2300.0)]);
        for (f, s) in first.iter().zip(&second) {
            assert_ne!(f, s);
        }
        // Standing still after it, each continues its new object.
        let third = add(&mut objects, 3, vec![region(&a, 1305.0), region(&b, 2295.0)]);
        assert_eq!(second, third);
    }

    #[test]
    fn one_object_moved_to_another_distance_continues() {
        // The paper's calibration: one object, shown at several distances.
        let mut objects = Materials::default();
        let a: Vec<u32> = (0..400).collect();
        let first = add(&mut objects, 1, vec![region(&a, 600.0)]);
        let second = add(&mut objects, 2, vec![region(&a, 600.0)]);
        let third = add(&mut objects, 3, vec![region(&a, 1300.0)]);
        assert_eq!(first, second);
        assert_eq!(second, third);
        assert_eq!(objects.get(first[0].unwrap()).unwrap().frames(), 3);
    }

    #[test]
    fn objects_carried_through_the_scene_keep_their_identity() {
        // 30 Hz, 50 and 30 mm a frame (1.5 and 0.9 m/s), the second speeding up.
        let mut objects = Materials::default();
        let (a, b): (Vec<u32>, Vec<u32>) = ((0..400).collect(), (1000..1400).collect());
        let frame_ns = 33_333_333;
        let mut ids = vec![];
        for f in 1..=12u64 {
            let t = f as f64 * frame_ns as f64 * 1e-9;
            let regions = vec![
                region(&a, 1000.0 + 50.0 * f as f64),
                region(&b, 2500.0 - 30.0 * f as f64 - 2.0 * t * t * 1e3),
            ];
            ids.push(objects.add_frame(regions, f, f * frame_ns, XiMethod::OneMaterial, &XiSettings::default()));
        }
        assert!(ids.iter().all(|f| *f == ids[0]), "{ids:?}");
        // A still object that jumps by 100 mm in 0.1 s (10 m/s^2 allows 50) with another
        // object in view is a cut.
        let mut objects = Materials::default();
        let first = add(&mut objects, 1, vec![region(&a, 1000.0), region(&b, 2000.0)]);
        add(&mut objects, 2, vec![region(&a, 1000.0), region(&b, 2000.0)]);
        let jumped = add(&mut objects, 3, vec![region(&a, 1100.0), region(&b, 2000.0)]);
        assert_ne!(jumped[0], first[0]);
    }

    #[test]
    fn a_still_object_needs_no_more_evidence_once_it_has_enough() {
        let mut objects = Materials::default();
        let a: Vec<u32> = (0..400).collect();
        let settings = XiSettings::default();
        let needs = |objects: &Materials, frame: u64, d: f64| {
            objects.needs_evidence(&[region(&a, d)], frame, frame * FRAME_NS, &settings)[0]
        };
        let at = |d: f64| FrameProfile {
            median_distance_mm: d,
            ..evidence()
        };
        for frame in 1..=settings.frames_per_pose as u64 {
            assert!(needs(&objects, frame, 1000.0), "frame {frame}");
            let r = RegionEvidence {
                profile: Some(at(1000.0)),
                ..region(&a, 1000.0)
            };
            add(&mut objects, frame, vec![r]);
        }
        let next = settings.frames_per_pose as u64 + 1;
        assert!(!needs(&objects, next, 1005.0));
        // Moved to another pose, or a new object elsewhere: evidence again.
        assert!(needs(&objects, next, 1150.0));
        let far: Vec<u32> = (5000..5400).collect();
        assert!(objects.needs_evidence(&[region(&far, 1000.0)], next, next * FRAME_NS, &settings)[0]);
    }

    #[test]
    fn an_object_that_reappears_elsewhere_after_a_cut_is_a_new_one() {
        let mut objects = Materials::default();
        let here: Vec<u32> = (0..400).collect();
        let there: Vec<u32> = (5000..5400).collect();
        let first = add(&mut objects, 1, vec![region(&here, 1000.0)]);
        let second = add(&mut objects, 2, vec![region(&there, 1000.0)]);
        assert_ne!(first, second);
        // Evidence never pooled across them.
        for id in first.iter().chain(&second) {
            assert_eq!(objects.get(id.unwrap()).unwrap().frames(), 1);
        }
    }

    /// Readings of `pixels` (a 20-pixel-wide patch): distance `d + slope * column` and IR
    /// `ir`, each with its noise (σ 20 mm, 1 % of the IR) drawn from `seed`.
    fn readings(pixels: &[u32], d: f64, slope: f64, ir: f64, seed: u64) -> Vec<PixelReading> {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let unit = Normal::new(0.0, 1.0).expect("unit normal");
        pixels
            .iter()
            .map(|&p| PixelReading {
                distance_mm: (d + slope * f64::from(p % 20) + 20.0 * unit.sample(&mut rng)) as f32,
                ir: (ir * (1.0 + 0.01 * unit.sample(&mut rng))) as f32,
                distance_var: 400.0,
                ir_var: (0.01 * ir * 0.01 * ir) as f32,
            })
            .collect()
    }

    fn with_readings<'a>(pixels: &'a [u32], d: f64, slope: f64, ir: f64, seed: u64) -> RegionEvidence<'a> {
        RegionEvidence {
            readings: readings(pixels, d, slope, ir, seed),
            ..region(pixels, d + slope * 9.5)
        }
    }

    #[test]
    fn an_object_standing_still_repeats_its_pixels_within_noise() {
        let mut objects = Materials::default();
        let (a, b): (Vec<u32>, Vec<u32>) = ((0..400).collect(), (1000..1400).collect());
        let first = add(
            &mut objects,
            1,
            vec![
                with_readings(&a, 1000.0, 5.0, 800.0, 1),
                with_readings(&b, 2000.0, 0.0, 300.0, 2),
            ],
        );
        let second = add(
            &mut objects,
            2,
            vec![
                with_readings(&a, 1000.0, 5.0, 800.0, 3),
                with_readings(&b, 2000.0, 0.0, 300.0, 4),
            ],
        );
        assert_eq!(first, second);
    }

    #[test]
    fn another_object_put_where_one_stood_is_a_new_one() {
        // Two objects in view. Where a box stood, showing two faces (one lit at 900 counts,
        // one turned from the emitter at 400), a flat sheet (500 counts) now stands at the
        // box's median distance: its IR follows no one ratio of the box's.
        let mut objects = Materials::default();
        let (a, b): (Vec<u32>, Vec<u32>) = ((0..400).collect(), (1000..1400).collect());
        let faces = |seed| {
            let mut r = readings(&a, 1000.0, 0.0, 900.0, seed);
            for (p, x) in a.iter().zip(r.iter_mut()).filter(|(p, _)| *p % 20 >= 10) {
                x.ir *= 4.0 / 9.0;
                x.ir_var *= 16.0 / 81.0;
                x.distance_mm += 5.0 * (*p % 20 - 10) as f32;
            }
            RegionEvidence {
                readings: r,
                ..region(&a, 1000.0)
            }
        };
        let first = add(
            &mut objects,
            1,
            vec![faces(1), with_readings(&b, 2000.0, 0.0, 300.0, 2)],
        );
        let box_again = add(
            &mut objects,
            2,
            vec![faces(3), with_readings(&b, 2000.0, 0.0, 300.0, 4)],
        );
        assert_eq!(box_again, first);
        let swapped = add(
            &mut objects,
            3,
            vec![
                with_readings(&a, 1010.0, 0.0, 500.0, 5),
                with_readings(&b, 2000.0, 0.0, 300.0, 6),
            ],
        );
        assert_ne!(swapped[0], first[0]);
        assert_eq!(swapped[1], first[1]);
        // Its median distance alone would have continued the box.
        let mut objects = Materials::default();
        let first = add(&mut objects, 1, vec![region(&a, 1000.0), region(&b, 2000.0)]);
        let bare = add(&mut objects, 2, vec![region(&a, 1010.0), region(&b, 2000.0)]);
        assert_eq!(bare, first);
    }

    #[test]
    fn an_object_creeping_nearer_within_the_outline_slack_moves() {
        // 15 mm a frame at 10 Hz (0.15 m/s), under the slack the median is allowed: its
        // pixels' shared shift says it moves, and a move this slow continues the object.
        let mut objects = Materials::default();
        let (a, b): (Vec<u32>, Vec<u32>) = ((0..400).collect(), (1000..1400).collect());
        let mut ids = vec![];
        for f in 1..=6u64 {
            let d = 1000.0 - 15.0 * f as f64;
            ids.push(add(
                &mut objects,
                f,
                vec![
                    with_readings(&a, d, 5.0, 800.0, 2 * f),
                    with_readings(&b, 2000.0, 0.0, 300.0, 2 * f + 1),
                ],
            ));
        }
        assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");
        let m = objects.get(ids[0][0].expect("an id")).expect("the object");
        let c = m
            .before
            .compare(&with_readings(&a, 900.0, 5.0, 800.0, 99))
            .expect("comparable");
        assert!(c.shifted && c.same_pattern, "{c:?}");
    }

    #[test]
    fn a_carried_object_that_turns_as_it_slows_keeps_its_identity() {
        // Carried 50 mm a frame at 10 Hz, then slowing to 10 mm while it turns (its pixels'
        // tilt reverses) beside another object: a moving object's pixels change with its
        // motion, so the kinematics alone judge it.
        let mut objects = Materials::default();
        let (a, b): (Vec<u32>, Vec<u32>) = ((0..400).collect(), (1000..1400).collect());
        let other = |f: u64| with_readings(&b, 2000.0, 0.0, 300.0, 100 + f);
        let mut ids = vec![];
        for f in 1..=3u64 {
            let d = 1000.0 + 50.0 * f as f64;
            ids.push(add(
                &mut objects,
                f,
                vec![with_readings(&a, d, 20.0, 800.0, f), other(f)],
            ));
        }
        // Its median 10 mm beyond the last frame's (1340 mm).
        let turned = with_readings(&a, 1540.0, -20.0, 800.0, 4);
        ids.push(add(&mut objects, 4, vec![turned, other(4)]));
        assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");
    }

    #[test]
    fn a_region_without_evidence_continues_an_object_but_starts_none() {
        let mut objects = Materials::default();
        let a: Vec<u32> = (0..400).collect();
        let far: Vec<u32> = (9000..9010).collect();
        let first = add(&mut objects, 1, vec![region(&a, 1000.0)]);
        let bare = |pixels| RegionEvidence {
            pixels,
            distance_mm: 1000.0,
            spread_mm: 0.0,
            profile: None,
            readings: vec![],
            place: Place::default(),
        };
        let ids = add(&mut objects, 2, vec![bare(&a), bare(&far)]);
        assert_eq!(ids, vec![first[0], None]);
        assert_eq!(objects.get(first[0].unwrap()).unwrap().frames(), 1);
    }

    #[test]
    fn a_place_is_the_mean_ray_at_the_median_distance_and_the_rays_spread() {
        // Four rays at +-0.1 in x and y about the axis, at 2000 mm.
        let rays = [[0.1, 0.0, 1.0], [-0.1, 0.0, 1.0], [0.0, 0.1, 1.0], [0.0, -0.1, 1.0]];
        let p = Place::of(rays.into_iter(), 2000.0);
        assert!((p.centre_mm[2] - 2000.0).abs() < 1e-9 && p.centre_mm[0].abs() < 1e-9);
        assert!((p.radius_mm - 200.0).abs() < 1e-9, "{p:?}");
        assert!(!Place::of(rays.into_iter(), f64::NAN).known());
        assert!(!Place::of(std::iter::empty(), 2000.0).known());
    }

    #[test]
    fn a_step_across_the_view_beyond_its_size_or_after_a_frame_unseen_is_no_step() {
        // Another object put down where one stood, 250 mm across (2.5 radii): not a step.
        let mut objects = Materials::default();
        let px: Vec<Vec<u32>> = (0..4).map(|k| (k * 1000..k * 1000 + 400).collect()).collect();
        let first = add(
            &mut objects,
            1,
            vec![placed(&px[0], -500.0, 0.0, 1000.0), placed(&px[1], 500.0, 0.0, 1000.0)],
        );
        let second = add(
            &mut objects,
            2,
            vec![placed(&px[2], -250.0, 0.0, 1200.0), placed(&px[3], 500.0, 0.0, 1200.0)],
        );
        assert_ne!(second[0], first[0]);
        assert_eq!(second[1], first[1]);
        // Unseen for a frame (another object alone in view), then a step from where it stood.
        let mut objects = Materials::default();
        let first = add(
            &mut objects,
            1,
            vec![placed(&px[0], -500.0, 0.0, 1000.0), placed(&px[1], 500.0, 0.0, 1000.0)],
        );
        add(&mut objects, 2, vec![placed(&px[1], 500.0, 0.0, 1000.0)]);
        let third = add(
            &mut objects,
            3,
            vec![placed(&px[2], -500.0, 0.0, 1300.0), placed(&px[1], 500.0, 0.0, 1000.0)],
        );
        assert_ne!(third[0], first[0]);
        assert_eq!(third[1], first[1]);
    }

    #[test]
    fn objects_stepped_between_poses_keep_their_identity_with_others_in_view() {
        // Two sheets 500 mm apart across the view, each stepped 250-300 mm in depth with a
        // lateral move of 100 mm between frames at 10 Hz (2.5-3 m/s: beyond the speed
        // limit), their pixels no longer overlapping: one frame a pose.
        let mut objects = Materials::default();
        let px: Vec<Vec<u32>> = (0..8).map(|k| (k * 1000..k * 1000 + 400).collect()).collect();
        let mut ids = vec![];
        for pose in 0..4u64 {
            let f = pose as f64;
            let regions = vec![
                placed(&px[2 * pose as usize], -250.0 + 100.0 * f, 0.0, 1000.0 + 250.0 * f),
                placed(&px[2 * pose as usize + 1], 250.0 + 100.0 * f, 0.0, 2000.0 - 300.0 * f),
            ];
            ids.push(add(&mut objects, pose + 1, regions));
        }
        assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");
        for id in &ids[0] {
            assert_eq!(objects.get(id.expect("an id")).expect("the object").frames(), 4);
        }
    }

    #[test]
    fn objects_that_could_each_have_stepped_to_either_place_start_new_ones() {
        // Two sheets one behind the other, 100 mm apart across the view, each stepped 300 mm:
        // each new region is as near one as the other (within the doubt), so neither identity
        // is kept.
        let mut objects = Materials::default();
        let px: Vec<Vec<u32>> = (0..4).map(|k| (k * 1000..k * 1000 + 400).collect()).collect();
        let first = add(
            &mut objects,
            1,
            vec![placed(&px[0], -50.0, 0.0, 1000.0), placed(&px[1], 50.0, 0.0, 1000.0)],
        );
        let second = add(
            &mut objects,
            2,
            vec![placed(&px[2], -50.0, 0.0, 1300.0), placed(&px[3], 50.0, 0.0, 1300.0)],
        );
        for s in &second {
            assert!(!first.contains(s), "{first:?} {second:?}");
        }
        // A step beyond max_pose_step_mm with another object in view is a cut too.
        let mut objects = Materials::default();
        let first = add(
            &mut objects,
            1,
            vec![placed(&px[0], -600.0, 0.0, 1000.0), placed(&px[1], 600.0, 0.0, 1000.0)],
        );
        let second = add(
            &mut objects,
            2,
            vec![placed(&px[2], -600.0, 0.0, 1700.0), placed(&px[3], 600.0, 0.0, 1000.0)],
        );
        assert_ne!(second[0], first[0]);
        assert_eq!(second[1], first[1]);
    }

    #[test]
    fn a_move_a_step_explains_too_keeps_its_identity_when_another_object_jumps() {
        // A sheet carried 150 mm away over the same pixels (a move within the speed limit,
        // and a step), while another object in view, over its own earlier pixels, reads 700 mm
        // farther, beyond any step: that one is a cut, and casts no doubt on the sheet's move.
        let mut objects = Materials::default();
        let px: Vec<Vec<u32>> = (0..2).map(|k| (k * 1000..k * 1000 + 400).collect()).collect();
        let first = add(
            &mut objects,
            1,
            vec![placed(&px[0], -600.0, 0.0, 2000.0), placed(&px[1], 600.0, 0.0, 1000.0)],
        );
        let second = add(
            &mut objects,
            2,
            vec![placed(&px[0], -600.0, 0.0, 2150.0), placed(&px[1], 600.0, 0.0, 1700.0)],
        );
        assert_eq!(second[0], first[0], "{first:?} {second:?}");
        assert_ne!(second[1], first[1], "{first:?} {second:?}");
    }

    #[test]
    fn the_least_cost_assignment_takes_the_cheapest_total_and_leaves_what_costs_more() {
        let inf = f64::INFINITY;
        // Greedy would take (0, 0) at 1 and leave row 1 at 10: the least total is 2 + 2.
        let (total, a) = least_cost_assignment(&[vec![1.0, 2.0], vec![2.0, inf]], 10.0);
        assert_eq!((total, a), (4.0, vec![Some(1), Some(0)]));
        // A row whose only pairs cost more than leaving is left.
        let (total, a) = least_cost_assignment(&[vec![1.0], vec![20.0]], 10.0);
        assert_eq!((total, a), (11.0, vec![Some(0), None]));
        assert_eq!(least_cost_assignment(&[], 10.0), (0.0, vec![]));
        assert_eq!(least_cost_assignment(&[vec![], vec![]], 10.0), (20.0, vec![None, None]));
    }
}
