//! Known materials, calibrated once as a camera is (issue 31, item 3; the paper's Sec. V-A):
//! the data of a materials file, and the classification of an object's pooled evidence
//! among the known materials, opaque and unknown (shared/design/objects.md, "Deciding
//! opaque, known material, unknown").
//!
//! Each class is a hypothesis about the object's ξ and albedo, weighed by the likelihood
//! of its evidence ([`AlbedoEvidence`]: the one-material objective `Q(ξ)` as a chi-square,
//! and the pooled albedo the inversion implies at each ξ):
//! - opaque: ξ = 0, any albedo;
//! - a known material: ξ uniform over its calibrated interval, and the albedo implied
//!   there within its calibrated range (a constraint: a match is not counted as evidence
//!   for the material, a mismatch counts against it);
//! - unknown: ξ uniform over `[0, 1)`, any albedo.
//!
//! The posterior of each is its prior times that likelihood, normalised. Where the
//! evidence cannot tell classes apart (one fronto-parallel pose before a plain wall with
//! an albedo that fits), their likelihoods are equal and the priors decide: the
//! probability says so.
//!
//! Albedos are known up to the scale of `Lin` (Eq. 13-14): a material's range is
//! comparable with another recording's only under the same convention ([`AlbedoScale`]).
//! Text in, text out: reading and writing the file is the caller's.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::translucency::{interpolate, AlbedoEvidence};

/// The `format` a materials file names.
pub const FORMAT: &str = "translucent_tof.materials/1";

/// The name of the opaque class (not a material's name).
pub const OPAQUE: &str = "opaque";

/// The name of the unknown class (not a material's name).
pub const UNKNOWN: &str = "unknown";

/// How finely ξ is integrated over a class's interval.
const XI_STEP: f64 = 0.001;

/// A calibration's albedo range is widened by this much in `ln rho` each side when written:
/// what a calibration's poses show is not all a later scene's geometry gives (normals,
/// incidence, the wall's own light).
pub const ALBEDO_MARGIN_LN: f64 = 0.1;

/// What went wrong with a materials file's contents.
#[derive(Debug, Error, PartialEq)]
pub enum CatalogError {
    /// Not TOML, or a field missing or of the wrong type (the message names it and the line).
    #[error("{0}")]
    Syntax(String),
    /// A field whose value is not allowed.
    #[error("{field}: {why}")]
    Field {
        /// Where, e.g. `material[2].xi_interval` (`material[1]` is the first).
        field: String,
        /// Why not.
        why: String,
    },
}

fn field_error(field: impl Into<String>, why: impl Into<String>) -> CatalogError {
    CatalogError::Field {
        field: field.into(),
        why: why.into(),
    }
}

/// What a material's albedo is relative to: `Lin`'s scale.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AlbedoReference {
    /// `Lin` from a calibration file (`calibrate-lin`): albedos are absolute and compare
    /// across scenes.
    LinCalibration,
    /// `Lin` derived from the latched background as a plane of `background_albedo`: the
    /// albedos are relative to the background's, and compare only before a background of
    /// the same albedo (the same wall), or with `background_albedo` set to what it is.
    Background,
}

impl AlbedoReference {
    /// The name the file uses.
    pub fn as_str(self) -> &'static str {
        match self {
            AlbedoReference::LinCalibration => "lin_calibration",
            AlbedoReference::Background => "background",
        }
    }
}

/// The albedo scale of a run: where its `Lin` comes from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlbedoScale {
    /// What `Lin` is.
    pub reference: AlbedoReference,
    /// The background albedo assumed when `Lin` comes from the background.
    pub background_albedo: f64,
}

/// One known material, as a calibration found it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KnownMaterial {
    /// Its name (neither `opaque` nor `unknown`).
    pub name: String,
    /// Its translucency.
    pub xi: f64,
    /// The interval the calibration supports (about 95 %).
    pub xi_interval: [f64; 2],
    /// The albedo the inversion implies at its ξ, `[low, high]`, on the scale of
    /// `albedo_reference`: what the calibration's poses showed, widened by
    /// [`ALBEDO_MARGIN_LN`] each side.
    pub albedo_range: [f64; 2],
    /// What the albedos are relative to.
    pub albedo_reference: AlbedoReference,
    /// With `albedo_reference = "background"`: the background albedo the calibration assumed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub background_albedo: Option<f64>,
    /// Where the one-material objective (albedo consistency, what classifies a scene's
    /// objects) put ξ in the calibration recording itself, when it determined it: at high ξ
    /// it can differ from the fit to known distances by more than either's interval (the
    /// model's misfit). Classification takes ξ over the hull of this and `xi_interval`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub evidence_xi_interval: Option<[f64; 2]>,
    /// Its prior weight (relative to the other classes').
    #[serde(default = "one")]
    pub prior: f64,
    /// The recording it was calibrated from.
    pub recording: String,
    /// The physics its ξ is of (ξ is a model's: another physics gives another ξ).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub physics: Option<String>,
    /// Frames of the calibration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<usize>,
}

impl KnownMaterial {
    /// The ξ a scene's object of this material may show: the hull of `xi_interval` and
    /// `evidence_xi_interval`.
    pub fn classification_interval(&self) -> [f64; 2] {
        match self.evidence_xi_interval {
            Some([lo, hi]) => [self.xi_interval[0].min(lo), self.xi_interval[1].max(hi)],
            None => self.xi_interval,
        }
    }
}

fn one() -> f64 {
    1.0
}

/// A materials file: the known materials and the priors of every class.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Catalog {
    /// [`FORMAT`].
    pub format: String,
    /// Prior weight of opaque (relative to the other classes').
    #[serde(default = "one")]
    pub opaque_prior: f64,
    /// Prior weight of an unknown material.
    #[serde(default = "one")]
    pub unknown_prior: f64,
    /// The known materials.
    #[serde(default, rename = "material")]
    pub materials: Vec<KnownMaterial>,
}

impl Default for Catalog {
    fn default() -> Self {
        Self {
            format: FORMAT.into(),
            opaque_prior: 1.0,
            unknown_prior: 1.0,
            materials: vec![],
        }
    }
}

/// The comment a new materials file starts with.
pub const HEADER: &str = "\
# translucent_tof materials file: known materials, calibrated once as a camera is.
# Written and appended to by `translucent_tof calibrate-xi BAG --name NAME -o FILE [--append]`;
# read by `replay --materials FILE` and the node's `materials` parameter.
# Priors are relative weights of the classes (normalised over opaque, unknown and every
# material): raise a material's `prior` where a cell only ever sees that material.
# albedo_range is the albedo the inversion implied at the material's xi over the
# calibration's poses, widened by 10 % each side, relative to `albedo_reference`:
# `lin_calibration` (absolute) or `background` (relative to the latched wall taken as
# `background_albedo`: compare only before a wall of the same albedo).
";

impl Catalog {
    /// Reads a materials file's text and checks every field.
    pub fn from_toml(text: &str) -> Result<Self, CatalogError> {
        let c: Catalog = toml::from_str(text).map_err(|e| CatalogError::Syntax(e.to_string().trim().to_string()))?;
        c.validate()?;
        Ok(c)
    }

    /// The file's text (with [`HEADER`]).
    pub fn to_toml(&self) -> Result<String, CatalogError> {
        self.validate()?;
        let body = toml::to_string(self).map_err(|e| CatalogError::Syntax(e.to_string()))?;
        Ok(format!("{HEADER}\n{body}"))
    }

    /// `text` (a materials file's) with `material` appended: the text is kept as it is
    /// (comments and all), the material's table added at its end. Refuses a name the
    /// file already holds.
    pub fn append_to(text: &str, material: &KnownMaterial) -> Result<String, CatalogError> {
        let mut c = Self::from_toml(text)?;
        c.materials.push(material.clone());
        c.validate()?;
        #[derive(Serialize)]
        struct One<'a> {
            material: [&'a KnownMaterial; 1],
        }
        let table = toml::to_string(&One { material: [material] }).map_err(|e| CatalogError::Syntax(e.to_string()))?;
        let mut out = text.to_string();
        if !out.ends_with('\n') {
            out.push('\n');
        }
        out.push('\n');
        out.push_str(&table);
        // What is written is what will be read.
        Self::from_toml(&out)?;
        Ok(out)
    }

    /// Checks every field: the error names it.
    pub fn validate(&self) -> Result<(), CatalogError> {
        if self.format != FORMAT {
            return Err(field_error("format", format!("{:?}: expected {FORMAT:?}", self.format)));
        }
        check_prior("opaque_prior", self.opaque_prior)?;
        check_prior("unknown_prior", self.unknown_prior)?;
        for (i, m) in self.materials.iter().enumerate() {
            let f = |name: &str| format!("material[{}].{name}", i + 1);
            let name = m.name.trim();
            if name.is_empty() {
                return Err(field_error(f("name"), "empty"));
            }
            if name == OPAQUE || name == UNKNOWN {
                return Err(field_error(
                    f("name"),
                    format!("{name:?} is a class of its own, not a material's name"),
                ));
            }
            if let Some(j) = self.materials[..i].iter().position(|o| o.name.trim() == name) {
                return Err(field_error(
                    f("name"),
                    format!("{name:?} is material[{}]'s name too: names must differ", j + 1),
                ));
            }
            if !(0.0..1.0).contains(&m.xi) {
                return Err(field_error(f("xi"), format!("{} is not in [0, 1)", m.xi)));
            }
            let [lo, hi] = m.xi_interval;
            if !(0.0 <= lo && lo <= m.xi && m.xi <= hi && hi <= 1.0) {
                return Err(field_error(
                    f("xi_interval"),
                    format!("[{lo}, {hi}] must lie in [0, 1] and hold xi {}", m.xi),
                ));
            }
            let [a, b] = m.albedo_range;
            if !(a > 0.0 && a <= b && b.is_finite()) {
                return Err(field_error(
                    f("albedo_range"),
                    format!("[{a}, {b}] must be positive and ordered"),
                ));
            }
            match (m.albedo_reference, m.background_albedo) {
                (AlbedoReference::Background, None) => {
                    return Err(field_error(
                        f("background_albedo"),
                        "missing: albedo_reference \"background\" needs the background albedo the calibration assumed",
                    ))
                }
                (_, Some(g)) if !(g > 0.0 && g <= 1.0) => {
                    return Err(field_error(f("background_albedo"), format!("{g} is not in (0, 1]")))
                }
                _ => {}
            }
            if let Some([lo, hi]) = m.evidence_xi_interval {
                if !(0.0 <= lo && lo <= hi && hi <= 1.0) {
                    return Err(field_error(
                        f("evidence_xi_interval"),
                        format!("[{lo}, {hi}] must be ordered within [0, 1]"),
                    ));
                }
            }
            check_prior(&f("prior"), m.prior)?;
        }
        let total = self.opaque_prior + self.unknown_prior + self.materials.iter().map(|m| m.prior).sum::<f64>();
        if !(total > 0.0) {
            return Err(field_error(
                "opaque_prior",
                "every class's prior is 0: at least one must be positive",
            ));
        }
        Ok(())
    }

    /// Sets priors from `NAME=WEIGHT` items (`opaque`, `unknown` or a material's name), as
    /// the `--material-prior` option and the node's `material_priors` parameter give them.
    pub fn set_priors<S: AsRef<str>>(&mut self, items: &[S]) -> Result<(), CatalogError> {
        for item in items {
            let item = item.as_ref().trim();
            if item.is_empty() {
                continue;
            }
            let Some((name, value)) = item.split_once('=') else {
                return Err(field_error(item, "expected NAME=WEIGHT, e.g. opaque=0.2"));
            };
            let (name, value) = (name.trim(), value.trim());
            let w: f64 = value
                .parse()
                .map_err(|_| field_error(name, format!("prior {value:?} is not a number")))?;
            check_prior(name, w)?;
            match name {
                OPAQUE => self.opaque_prior = w,
                UNKNOWN => self.unknown_prior = w,
                _ => match self.materials.iter_mut().find(|m| m.name == name) {
                    Some(m) => m.prior = w,
                    None => {
                        return Err(field_error(
                            name,
                            format!(
                                "no such class: opaque, unknown{}",
                                self.materials
                                    .iter()
                                    .map(|m| format!(", {}", m.name))
                                    .collect::<String>()
                            ),
                        ))
                    }
                },
            }
        }
        self.validate()
    }

    /// Classifies an object by its pooled evidence (`None`: it has none yet, the priors
    /// decide) under a run whose albedos are on `scale`.
    pub fn classify(&self, evidence: Option<&AlbedoEvidence>, scale: &AlbedoScale) -> Classification {
        let mut classes: Vec<(Class, f64)> =
            vec![(Class::Opaque, self.opaque_prior), (Class::Unknown, self.unknown_prior)];
        classes.extend(
            self.materials
                .iter()
                .enumerate()
                .map(|(i, m)| (Class::Known(i), m.prior)),
        );
        let mut notes = vec![];
        let likelihoods: Vec<f64> = match evidence {
            None => {
                notes.push("no evidence yet: the priors decide".to_string());
                vec![1.0; classes.len()]
            }
            Some(e) => classes
                .iter()
                .map(|(c, _)| self.likelihood(*c, e, scale, &mut notes))
                .collect(),
        };
        let weights: Vec<f64> = classes.iter().zip(&likelihoods).map(|((_, p), l)| p * l).collect();
        let total: f64 = weights.iter().sum();
        let posterior: Vec<f64> = if total > 0.0 && total.is_finite() {
            weights.iter().map(|w| w / total).collect()
        } else {
            notes.push("no class fits the evidence: the priors decide".to_string());
            let t: f64 = classes.iter().map(|c| c.1).sum();
            classes.iter().map(|c| c.1 / t).collect()
        };
        // The first of equals: opaque before unknown before the materials (a tie keeps the reading).
        let best = (1..classes.len()).fold(0, |b, k| if posterior[k] > posterior[b] { k } else { b });
        // The evidence told nothing when every class fits it alike: say that the prior decided.
        let spread = likelihoods
            .iter()
            .fold((f64::INFINITY, 0.0f64), |a, &l| (a.0.min(l), a.1.max(l)));
        if evidence.is_some() && spread.1 > 0.0 && spread.0 / spread.1 > 0.5 {
            notes.push("the evidence fits every class about alike: the priors decide".to_string());
        }
        notes.dedup();
        Classification {
            class: classes[best].0,
            name: self.class_name(classes[best].0).to_string(),
            probability: posterior[best],
            posterior: classes
                .iter()
                .zip(&posterior)
                .map(|((c, _), &p)| (self.class_name(*c).to_string(), p))
                .collect(),
            note: notes.join("; "),
        }
    }

    /// A class's name: `opaque`, `unknown` or the material's.
    pub fn class_name(&self, class: Class) -> &str {
        match class {
            Class::Opaque => OPAQUE,
            Class::Unknown => UNKNOWN,
            Class::Known(i) => self.materials.get(i).map_or(UNKNOWN, |m| m.name.as_str()),
        }
    }

    /// The likelihood of the evidence under a class, relative to that at the best ξ.
    fn likelihood(&self, class: Class, e: &AlbedoEvidence, scale: &AlbedoScale, notes: &mut Vec<String>) -> f64 {
        let top = e.xi.last().copied().unwrap_or(0.99);
        // The minimum between grid points too (the objective can be far sharper than the grid).
        let qmin = (0..=(top / XI_STEP).round() as usize)
            .filter_map(|j| quadratic(&e.xi, &e.q, j as f64 * XI_STEP))
            .chain(e.q.iter().copied().filter(|q| q.is_finite()))
            .fold(f64::INFINITY, f64::min);
        if !qmin.is_finite() {
            return 1.0;
        }
        let at = |xi: f64| -> f64 {
            quadratic(&e.xi, &e.q, xi.min(top))
                .map(|q| (-(q - qmin) / 2.0).exp())
                .unwrap_or(0.0)
        };
        match class {
            Class::Opaque => at(0.0),
            Class::Unknown => mean_over(0.0, top, at),
            Class::Known(i) => {
                let m = &self.materials[i];
                let albedo = match self.albedo_shift(m, scale) {
                    Ok(shift) => Some(((m.albedo_range[0].ln() + shift), (m.albedo_range[1].ln() + shift))),
                    Err(why) => {
                        notes.push(why);
                        None
                    }
                };
                let [lo, hi] = m.classification_interval();
                let integrand = |x: f64| {
                    let fit = at(x);
                    match albedo {
                        None => fit,
                        Some((lo, hi)) if fit > 0.0 => {
                            let m = interpolate(&e.xi, &e.log_albedo, x.min(top));
                            let s = interpolate(&e.xi, &e.log_albedo_se, x.min(top));
                            match (m, s) {
                                (Some(m), Some(s)) if s > 0.0 => {
                                    fit * (normal_cdf((hi - m) / s) - normal_cdf((lo - m) / s))
                                }
                                (Some(m), _) => fit * f64::from(u8::from(m >= lo && m <= hi)),
                                _ => 0.0,
                            }
                        }
                        _ => 0.0,
                    }
                };
                mean_over(lo, hi, integrand)
            }
        }
    }

    /// The most likely ξ of the evidence within a material's classification interval, when
    /// the evidence prefers part of it (the likelihood varies by more than a factor 2 over
    /// it); `None` when it is about flat there (the calibrated ξ stands).
    pub fn best_xi(&self, i: usize, e: &AlbedoEvidence) -> Option<f64> {
        let m = self.materials.get(i)?;
        let [lo, hi] = m.classification_interval();
        let top = e.xi.last().copied().unwrap_or(0.99);
        let n = ((hi - lo) / XI_STEP).ceil().max(1.0) as usize;
        let q: Vec<(f64, f64)> = (0..=n)
            .map(|j| lo + (hi - lo) * j as f64 / n as f64)
            .filter_map(|x| Some((x, quadratic(&e.xi, &e.q, x.min(top))?)))
            .collect();
        let best = q.iter().copied().min_by(|a, b| a.1.total_cmp(&b.1))?;
        let worst = q.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
        (worst - best.1 > 2.0 * std::f64::consts::LN_2).then_some(best.0)
    }

    /// What to add to a material's `ln rho` to put it on `scale`; why not, if it cannot be.
    fn albedo_shift(&self, m: &KnownMaterial, scale: &AlbedoScale) -> Result<f64, String> {
        match (m.albedo_reference, scale.reference) {
            (AlbedoReference::LinCalibration, AlbedoReference::LinCalibration) => Ok(0.0),
            (AlbedoReference::Background, AlbedoReference::Background) => {
                // Lin scales with the albedo assumed for the wall, the implied albedo with it.
                Ok((scale.background_albedo / m.background_albedo.unwrap_or(1.0)).ln())
            }
            (theirs, ours) => Err(format!(
                "material {:?}: its albedo is relative to {} and this run's to {}: not compared, its xi interval alone decides",
                m.name,
                theirs.as_str(),
                ours.as_str()
            )),
        }
    }
}

fn check_prior(field: &str, w: f64) -> Result<(), CatalogError> {
    if !(w >= 0.0 && w.is_finite()) {
        return Err(field_error(field, format!("prior {w} must be a number >= 0")));
    }
    Ok(())
}

/// `v` at `x` on `grid` by the parabola through the three grid points nearest `x` (all
/// finite; else linear between the two around it, if finite), never below 0: `Q` is about
/// quadratic near its minimum, and a sharp minimum between grid points is where a linear
/// interpolation fails most.
fn quadratic(grid: &[f64], v: &[f64], x: f64) -> Option<f64> {
    if grid.len() < 3 {
        return interpolate(grid, v, x);
    }
    let nearest = (0..grid.len()).min_by(|&a, &b| (grid[a] - x).abs().total_cmp(&(grid[b] - x).abs()))?;
    let j = nearest.clamp(1, grid.len() - 2);
    let (x0, x1, x2) = (grid[j - 1], grid[j], grid[j + 1]);
    let (y0, y1, y2) = (v[j - 1], v[j], v[j + 1]);
    if !(y0.is_finite() && y1.is_finite() && y2.is_finite()) || x < x0 || x > x2 {
        return interpolate(grid, v, x);
    }
    let l0 = (x - x1) * (x - x2) / ((x0 - x1) * (x0 - x2));
    let l1 = (x - x0) * (x - x2) / ((x1 - x0) * (x1 - x2));
    let l2 = (x - x0) * (x - x1) / ((x2 - x0) * (x2 - x1));
    Some((y0 * l0 + y1 * l1 + y2 * l2).max(0.0))
}

/// The mean of `f` over `[lo, hi]` (its value at `lo` when the interval is a point).
fn mean_over(lo: f64, hi: f64, f: impl Fn(f64) -> f64) -> f64 {
    let n = ((hi - lo) / XI_STEP).ceil().max(0.0) as usize;
    if n == 0 {
        return f(lo);
    }
    // Trapezoid rule over n equal steps.
    let h = (hi - lo) / n as f64;
    let sum: f64 = (0..=n)
        .map(|j| {
            let w = if j == 0 || j == n { 0.5 } else { 1.0 };
            w * f(lo + j as f64 * h)
        })
        .sum();
    sum / n as f64
}

/// The standard normal distribution function (erfc by a Chebyshev-fitted exponential,
/// relative error under 1.2e-7).
pub fn normal_cdf(x: f64) -> f64 {
    let z = (-x / std::f64::consts::SQRT_2).abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * poly.exp();
    if x >= 0.0 {
        1.0 - 0.5 * erfc
    } else {
        0.5 * erfc
    }
}

/// One of the classes an object can be.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Class {
    /// Opaque: ξ = 0.
    Opaque,
    /// None of the known materials: ξ estimated from its own evidence.
    Unknown,
    /// The known material of this index in the catalog.
    Known(usize),
}

/// An object's class and how sure.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Classification {
    /// The most probable class.
    #[serde(skip)]
    pub class: Class,
    /// Its name: `opaque`, `unknown` or the material's.
    pub name: String,
    /// Its posterior probability.
    pub probability: f64,
    /// Every class's posterior probability, opaque and unknown first.
    pub posterior: Vec<(String, f64)>,
    /// What decided, in words (empty when the evidence did).
    pub note: String,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::translucency::xi_grid;

    fn material(name: &str, xi: f64, albedo: f64) -> KnownMaterial {
        KnownMaterial {
            name: name.into(),
            xi,
            xi_interval: [xi - 0.02, xi + 0.02],
            albedo_range: [albedo * 0.9, albedo * 1.1],
            albedo_reference: AlbedoReference::Background,
            background_albedo: Some(1.0),
            evidence_xi_interval: None,
            prior: 1.0,
            recording: format!("calib_{name}.mcap"),
            physics: Some("physical".into()),
            frames: Some(10),
        }
    }

    fn catalog() -> Catalog {
        Catalog {
            materials: vec![material("folder", 0.6, 0.5), material("box", 0.9, 0.3)],
            ..Catalog::default()
        }
    }

    const SCALE: AlbedoScale = AlbedoScale {
        reference: AlbedoReference::Background,
        background_albedo: 1.0,
    };

    /// Evidence whose objective is a parabola about `best` (`curvature` per unit ξ squared;
    /// 0: flat) and whose implied albedo is `albedo(xi)`.
    fn evidence(best: f64, curvature: f64, albedo: impl Fn(f64) -> f64) -> AlbedoEvidence {
        let xi = xi_grid();
        AlbedoEvidence {
            q: xi.iter().map(|x| 2.0 + curvature * (x - best).powi(2)).collect(),
            log_albedo: xi.iter().map(|&x| albedo(x).ln()).collect(),
            log_albedo_se: vec![0.01; xi.len()],
            poses: 2,
            xi,
        }
    }

    fn probability(c: &Classification, name: &str) -> f64 {
        c.posterior.iter().find(|p| p.0 == name).map(|p| p.1).unwrap()
    }

    #[test]
    fn the_file_round_trips_and_appends_keep_the_text() {
        let c = catalog();
        let text = c.to_toml().unwrap();
        assert!(text.starts_with("# translucent_tof materials file"));
        assert_eq!(Catalog::from_toml(&text).unwrap(), c);
        let extra = material("bottle", 0.8, 0.7);
        let with = Catalog::append_to(&format!("{text}# kept\n"), &extra).unwrap();
        assert!(with.contains("# kept"));
        let back = Catalog::from_toml(&with).unwrap();
        assert_eq!(back.materials.len(), 3);
        assert_eq!(back.materials[2], extra);
        // The same name twice is refused.
        let err = Catalog::append_to(&with, &extra).unwrap_err();
        assert!(err.to_string().contains("material[4].name"), "{err}");
    }

    #[test]
    fn bad_files_name_the_field() {
        let text = catalog().to_toml().unwrap();
        let cases = [
            (text.replacen("xi = 0.6", "xi = 1.5", 1), "material[1].xi"),
            (text.replacen("xi = 0.6", "xi = 0.2", 1), "material[1].xi_interval"),
            (
                text.replacen("name = \"box\"", "name = \"opaque\"", 1),
                "material[2].name",
            ),
            (
                text.replacen("opaque_prior = 1.0", "opaque_prior = -1.0", 1),
                "opaque_prior",
            ),
            (text.replacen(FORMAT, "something/2", 1), "format"),
            (
                text.replacen("background_albedo = 1.0\n", "", 1),
                "material[1].background_albedo",
            ),
            (text.replacen("xi = 0.6\n", "", 1), "missing field `xi`"),
            (text.replacen("xi = 0.6", "xi = \"high\"", 1), "xi"),
            (text.replacen("[[material]]", "[[material]]\ncolour = 3", 1), "colour"),
            ("this is not toml".to_string(), "TOML parse error"),
        ];
        for (bad, field) in cases {
            let err = Catalog::from_toml(&bad).expect_err(field).to_string();
            assert!(err.contains(field), "{field}: {err}");
        }
        let mut c = catalog();
        assert!(c.set_priors(&["box=3", " opaque = 0.5 "]).is_ok());
        assert_eq!((c.materials[1].prior, c.opaque_prior), (3.0, 0.5));
        for bad in ["glass=1", "box", "box=x", "box=-1"] {
            assert!(c.set_priors(&[bad]).is_err(), "{bad}");
        }
    }

    #[test]
    fn a_material_is_told_from_opaque_and_unknown_by_xi_and_albedo() {
        let c = catalog();
        // Sharp at 0.6 with the folder's albedo there: the folder.
        let folder = c.classify(Some(&evidence(0.6, 4000.0, |x| 0.2 + 0.5 * x)), &SCALE);
        assert_eq!(folder.name, "folder", "{folder:?}");
        assert!(folder.probability > 0.9, "{folder:?}");
        // Sharp at 0.6 but the albedo there is the box's range, not the folder's: neither
        // material (the box's ξ does not fit), an unknown one.
        let other = c.classify(Some(&evidence(0.6, 4000.0, |_| 0.3)), &SCALE);
        assert_eq!(other.name, UNKNOWN, "{other:?}");
        // Sharp at 0: opaque.
        let opaque = c.classify(Some(&evidence(0.0, 4000.0, |_| 0.5)), &SCALE);
        assert_eq!(opaque.name, OPAQUE, "{opaque:?}");
        assert!(opaque.probability > 0.9);
        // Sharp at 0.3, where no material is: unknown.
        let unknown = c.classify(Some(&evidence(0.3, 4000.0, |_| 0.5)), &SCALE);
        assert_eq!(unknown.name, UNKNOWN, "{unknown:?}");
    }

    #[test]
    fn where_the_evidence_cannot_tell_the_priors_decide() {
        let mut c = catalog();
        // Flat in ξ, and the implied albedo fits each material at its ξ: every class alike.
        let flat = evidence(0.5, 0.0, |x| if x > 0.75 { 0.3 } else { 0.5 });
        let even = c.classify(Some(&flat), &SCALE);
        for (_, p) in &even.posterior {
            assert!((p - 0.25).abs() < 0.01, "{even:?}");
        }
        assert!(even.note.contains("priors decide"), "{even:?}");
        // A cell that only sees boxes says so.
        c.set_priors(&["box=8", "opaque=1", "unknown=0.5", "folder=0.5"])
            .unwrap();
        let boxes = c.classify(Some(&flat), &SCALE);
        assert_eq!(boxes.name, "box");
        assert!((boxes.probability - 0.8).abs() < 0.01, "{boxes:?}");
        // No evidence at all: the priors.
        let none = c.classify(None, &SCALE);
        assert_eq!(none.name, "box");
        assert!((probability(&none, OPAQUE) - 0.1).abs() < 1e-9);
    }

    #[test]
    fn albedos_on_another_scale_are_rescaled_or_left_out() {
        let c = catalog();
        let e = evidence(0.6, 4000.0, |x| 0.5 * (0.2 + 0.5 * x));
        // The same wall assumed half as bright: every implied albedo halves, and so the range.
        let half = AlbedoScale {
            background_albedo: 0.5,
            ..SCALE
        };
        assert_eq!(c.classify(Some(&e), &half).name, "folder");
        assert_eq!(c.classify(Some(&e), &SCALE).name, UNKNOWN);
        // A calibrated Lin: not comparable, the interval alone decides, and the note says so.
        let lin = AlbedoScale {
            reference: AlbedoReference::LinCalibration,
            background_albedo: 1.0,
        };
        let r = c.classify(Some(&e), &lin);
        assert_eq!(r.name, "folder");
        assert!(r.note.contains("not compared"), "{r:?}");
    }

    #[test]
    fn normal_cdf_is_accurate() {
        for (x, p) in [
            (0.0, 0.5),
            (1.0, 0.841_344_746),
            (-1.96, 0.024_997_895),
            (3.0, 0.998_650_102),
        ] {
            assert!((normal_cdf(x) - p).abs() < 1e-7, "{x}");
        }
    }
}
