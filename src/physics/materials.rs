//! The materials a scene shows, each with its own ξ (physics.md §3, "one
//! material"): every region of a frame brings its evidence (a [`FrameProfile`]),
//! which joins the material it is consistent with or starts a new one.
//!
//! A region joins a material when one ξ and one albedo explain both: the
//! one-material objective of the pooled evidence rises above the two apart by
//! no more than chance allows (chi-square with two degrees of freedom, one ξ
//! and one albedo fewer, scaled by the overdispersion). A region with too
//! little evidence to tell starts its own material rather than bias another's.

use super::translucency::{self, FrameProfile, Misfit, XiEstimate, XiMethod, XiSettings};

/// 95 % quantile of chi-square with two degrees of freedom.
const JOIN_CHI2: f64 = 5.99;

/// How far in albedo (log) two groups of one material may differ beyond their noise in the
/// test that joins them: texture and what the model leaves out vary a material's albedo
/// by a few per cent from place to place, while thousands of pixels make the noise tiny.
const MATERIAL_SPREAD: f64 = 0.03;

/// Most materials kept: past it the one seen longest ago is forgotten.
pub const MAX_MATERIALS: usize = 16;

/// One material: its pooled evidence and the estimate from it.
#[derive(Debug, Clone)]
pub struct Material {
    /// Its id, stable while it is kept (1, 2, ...).
    pub id: u32,
    profiles: Vec<FrameProfile>,
    misfit: Misfit,
    /// The estimate from its pooled evidence (`None` until one exists).
    pub estimate: Option<XiEstimate>,
    /// The frame count when a region last joined it.
    pub last_seen: u64,
}

impl Material {
    /// Frames of evidence pooled.
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

    /// Adds a region's evidence of frame `frame` (a running count): it joins the
    /// material it is consistent with, or starts one. Returns the material's id.
    pub fn add(&mut self, profile: FrameProfile, frame: u64, method: XiMethod, settings: &XiSettings) -> u32 {
        // A region of fewer than two groups is one group's albedo: no spread of its own.
        let own = translucency::one_material_misfit(std::slice::from_ref(&profile), MATERIAL_SPREAD)
            .unwrap_or(Misfit { q_min: 0.0, groups: 1 });
        let joined = self.best_match(&profile, own);
        let index = match joined {
            Some((i, misfit)) => {
                let m = &mut self.materials[i];
                if m.profiles.len() >= settings.max_frames_pooled.max(1) {
                    m.profiles.remove(0);
                }
                m.profiles.push(profile);
                m.misfit = misfit;
                i
            }
            None => self.start(profile, own),
        };
        let m = &mut self.materials[index];
        m.last_seen = frame;
        let est = match method {
            XiMethod::Eq12Residual => translucency::eq12_residual(&m.profiles),
            _ => translucency::one_material(&m.profiles),
        };
        if est.is_some() {
            m.estimate = est;
        }
        m.id
    }

    /// The material `profile` fits best, if one fits within chance, with the pooled misfit.
    fn best_match(&self, profile: &FrameProfile, own: Misfit) -> Option<(usize, Misfit)> {
        let mut best: Option<(usize, Misfit, f64)> = None;
        for (i, m) in self.materials.iter().enumerate() {
            let alone = m.misfit;
            let mut pooled = m.profiles.clone();
            pooled.push(profile.clone());
            let Some(joint) = translucency::one_material_misfit(&pooled, MATERIAL_SPREAD) else {
                continue;
            };
            // Apart, each has its own ξ and albedo: the joint fit has two parameters fewer.
            let apart = Misfit {
                q_min: alone.q_min + own.q_min,
                groups: alone.groups + own.groups,
            };
            let phi = if apart.groups > 4 {
                (apart.q_min / (apart.groups as f64 - 4.0)).max(1.0)
            } else {
                1.0
            };
            let rise = (joint.q_min - apart.q_min).max(0.0) / phi;
            if rise <= JOIN_CHI2 && best.is_none_or(|(_, _, r)| rise < r) {
                best = Some((i, joint, rise));
            }
        }
        best.map(|(i, joint, _)| (i, joint))
    }

    /// A new material of this evidence; the one seen longest ago goes if there are too many.
    fn start(&mut self, profile: FrameProfile, misfit: Misfit) -> usize {
        if self.materials.len() >= MAX_MATERIALS {
            if let Some(oldest) = (0..self.materials.len()).min_by_key(|&i| self.materials[i].last_seen) {
                self.materials.remove(oldest);
            }
        }
        self.next_id = self.next_id.wrapping_add(1).max(1);
        self.materials.push(Material {
            id: self.next_id,
            profiles: vec![profile],
            misfit,
            estimate: None,
            last_seen: 0,
        });
        self.materials.len() - 1
    }
}
