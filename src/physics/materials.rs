//! The materials a scene shows, each with its own ξ (physics.md §3, "one
//! material"): every region of a frame brings its evidence (a [`FrameProfile`]),
//! which joins the material of the object it continues, or starts a new one.
//!
//! A region continues a material when it covers much of the image that the
//! material's region covered in an earlier frame: an object moves, it does not
//! jump. Regions are never joined on albedo alone: two objects seen in one pose
//! each can nearly always be given one ξ at which their albedos agree, and
//! pooling them would make an undetermined ξ look determined (and on rendered
//! scenes, the same object in two frames of one pose failed a chi-square test
//! of its albedos at high ξ, where the implied albedo is noisiest).

use super::translucency::{self, FrameProfile, XiEstimate, XiMethod, XiSettings};

/// Least share of the smaller of two regions that the other must cover for the later to
/// continue the earlier's object.
const MIN_OVERLAP: f64 = 0.3;

/// Most materials kept: past it the one seen longest ago is forgotten.
pub const MAX_MATERIALS: usize = 16;

/// The pixels a material's regions covered in one frame.
#[derive(Debug, Clone, Default)]
struct Footprint {
    frame: u64,
    /// Pixel indices, ascending.
    pixels: Vec<u32>,
}

impl Footprint {
    /// Pixels of `region` (ascending) that this footprint covers too.
    fn overlap(&self, region: &[u32]) -> usize {
        let (mut i, mut j, mut n) = (0, 0, 0);
        while i < self.pixels.len() && j < region.len() {
            match self.pixels[i].cmp(&region[j]) {
                std::cmp::Ordering::Less => i += 1,
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Equal => {
                    n += 1;
                    i += 1;
                    j += 1;
                }
            }
        }
        n
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

    fn record(&mut self, frame: u64, pixels: &[u32]) {
        if self.latest.frame == frame {
            self.latest.pixels.extend_from_slice(pixels);
            self.latest.pixels.sort_unstable();
        } else {
            self.before = std::mem::take(&mut self.latest);
            self.latest = Footprint {
                frame,
                pixels: pixels.to_vec(),
            };
        }
    }
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

    /// Adds a region of frame `frame` (a running count, from 1), its `pixels` ascending, with
    /// its evidence if it carries any: it joins the material of the object it continues, or
    /// (with evidence) starts one. Returns the material's id; `None` for a region without
    /// evidence that continues nothing.
    pub fn add(
        &mut self,
        pixels: &[u32],
        profile: Option<FrameProfile>,
        frame: u64,
        method: XiMethod,
        settings: &XiSettings,
    ) -> Option<u32> {
        let index = match (self.continued(pixels, frame), profile) {
            (Some(i), Some(p)) => {
                let m = &mut self.materials[i];
                if m.profiles.len() >= settings.max_frames_pooled.max(1) {
                    m.profiles.remove(0);
                }
                m.profiles.push(p);
                m.estimate = estimate(&m.profiles, method).or(m.estimate.take());
                i
            }
            (Some(i), None) => i,
            (None, Some(p)) => self.start(p, method),
            (None, None) => return None,
        };
        let m = &mut self.materials[index];
        m.record(frame, pixels);
        Some(m.id)
    }

    /// The material whose earlier region this one covers most (at least [`MIN_OVERLAP`] of
    /// the smaller of the two).
    fn continued(&self, pixels: &[u32], frame: u64) -> Option<usize> {
        self.materials
            .iter()
            .enumerate()
            .filter_map(|(i, m)| {
                let before = m.earlier_than(frame)?;
                let shared = before.overlap(pixels) as f64;
                let smaller = before.pixels.len().min(pixels.len()).max(1) as f64;
                (shared / smaller >= MIN_OVERLAP).then_some((i, shared))
            })
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(i, _)| i)
    }

    /// A new material of this evidence; the one seen longest ago goes if there are too many.
    fn start(&mut self, profile: FrameProfile, method: XiMethod) -> usize {
        if self.materials.len() >= MAX_MATERIALS {
            if let Some(oldest) = (0..self.materials.len()).min_by_key(|&i| self.materials[i].last_seen()) {
                self.materials.remove(oldest);
            }
        }
        self.next_id = self.next_id.wrapping_add(1).max(1);
        let profiles = vec![profile];
        self.materials.push(Material {
            id: self.next_id,
            estimate: estimate(&profiles, method),
            profiles,
            latest: Footprint::default(),
            before: Footprint::default(),
        });
        self.materials.len() - 1
    }
}

fn estimate(profiles: &[FrameProfile], method: XiMethod) -> Option<XiEstimate> {
    match method {
        XiMethod::Eq12Residual => translucency::eq12_residual(profiles),
        _ => translucency::one_material(profiles),
    }
}
