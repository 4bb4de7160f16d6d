//! The physics audit: fit the paper's model (Eq. 1-2, 5, 7) to a recording
//! whose foreground distances are known (the paper's Sec. V-A), find where it
//! disagrees with the readings, and test each effect the paper leaves out as
//! an option of the one forward model ([`ModelOptions`], [`Waveform`]).
//!
//! Numbers in, numbers out. Every hypothesis (the baseline or the baseline
//! plus a set of effects) is fitted with ξ and the material's albedo `rho_f`
//! refitted together with the effects' parameters (a missing effect is
//! otherwise absorbed into ξ), scored on frames left out of its fit, and
//! effects are added greedily while the held-out error improves by more than
//! the noise and a penalty per parameter allow.
//!
//! Per pixel the known foreground distance fixes `df`, its surface's normal
//! gives `cos(theta_f)`, and one material gives `X = rho_f cos(theta_f)`
//! (physics.md §3, "one material"): the model then predicts both the reading
//! `d` (Eq. 11) and the IR value `I` (Eq. 7), and both are compared with the
//! observation, each in units of its own noise.

use serde::Serialize;

use super::buffer::ImageBuf;
use super::inversion::{foreground_distance_without_slopes, InversionBounds, PixelObservation};
use super::model::{ForwardModel, IrMode, ModelOptions, MAX_BOUNCES};
use super::sensor::{Sensor, Waveform};

/// An effect past the paper's model, as `interfaces.md` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Effect {
    /// Eq. 3's terms past L2 (inter-reflections between the layers).
    HigherOrderBounces,
    /// Harmonic content of the correlation waveform (3rd and 5th).
    WaveformHarmonics,
    /// The IR image is the demodulated amplitude, not the sum of Eq. 7.
    IrAmplitude,
    /// An offset in the IR image.
    AmbientOffset,
    /// Extra path of the light the layer returns (subsurface scattering).
    SubsurfaceDelay,
    /// The second return's power of the layer's albedo (physics.md's note on Eq. 2).
    TransmissionLaw,
    /// The background seen through the layer displaced (refraction).
    RefractionShift,
    /// Light the layer's back and a near diffuse background exchange (a third return).
    WallInterreflection,
    /// Light crossing the layer diffusely (a frosted layer).
    DiffuseTransmission,
    /// A hollow object's back wall behind its front (three returns).
    ThreeReturns,
}

impl Effect {
    /// Every candidate, in a fixed order.
    pub const ALL: [Effect; 10] = [
        Effect::HigherOrderBounces,
        Effect::WaveformHarmonics,
        Effect::IrAmplitude,
        Effect::AmbientOffset,
        Effect::SubsurfaceDelay,
        Effect::TransmissionLaw,
        Effect::RefractionShift,
        Effect::WallInterreflection,
        Effect::DiffuseTransmission,
        Effect::ThreeReturns,
    ];

    /// The name in reports and physics files.
    pub fn name(&self) -> &'static str {
        match self {
            Effect::HigherOrderBounces => "higher_order_bounces",
            Effect::WaveformHarmonics => "waveform_harmonics",
            Effect::IrAmplitude => "ir_amplitude",
            Effect::AmbientOffset => "ambient_offset",
            Effect::SubsurfaceDelay => "subsurface_delay",
            Effect::TransmissionLaw => "transmission_law",
            Effect::RefractionShift => "refraction_shift",
            Effect::WallInterreflection => "wall_interreflection",
            Effect::DiffuseTransmission => "diffuse_transmission",
            Effect::ThreeReturns => "three_returns",
        }
    }

    /// Names of the continuous parameters fitted for this effect.
    pub fn param_names(&self) -> &'static [&'static str] {
        match self {
            Effect::HigherOrderBounces => &[],
            Effect::WaveformHarmonics => &["third", "fifth"],
            Effect::IrAmplitude => &[],
            Effect::AmbientOffset => &["ambient_offset"],
            Effect::SubsurfaceDelay => &["subsurface_delay_mm"],
            Effect::TransmissionLaw => &["transmission_albedo_power"],
            Effect::RefractionShift => &["shift_columns_px", "shift_rows_px"],
            Effect::WallInterreflection => &["wall_interreflection"],
            Effect::DiffuseTransmission => &["diffuse_transmission"],
            Effect::ThreeReturns => &["hollow_depth_mm"],
        }
    }

    /// The quantity the effect's misfit follows (its signature): where the model without
    /// it must leave a residual that varies along this, and the effect must take that away.
    pub fn signature(&self) -> Quantity {
        match self {
            // Eq. 3's terms grow as the layer nears the wall.
            Effect::HigherOrderBounces => Quantity::Separation,
            // A non-sinusoidal correlation bends the reading periodically in phase.
            Effect::WaveformHarmonics => Quantity::Phase,
            // Amplitude and sum part as the two returns' phases part: with the gap.
            Effect::IrAmplitude => Quantity::Separation,
            // An offset weighs most where the signal is faint.
            Effect::AmbientOffset => Quantity::IrLevel,
            // The delayed first return's share of the mix falls with distance.
            Effect::SubsurfaceDelay => Quantity::ForegroundDistance,
            // `X = rho_f cos(theta_f)` in L2: the law shows as X changes with the incidence.
            Effect::TransmissionLaw => Quantity::IncidenceAngle,
            // A displaced background shows along the image where the wall changes.
            Effect::RefractionShift => Quantity::ImageColumn,
            // The third return scales with the view factor from the wall to the layer.
            Effect::WallInterreflection => Quantity::ViewFactor,
            // The lobe's slanted paths lengthen with the gap.
            Effect::DiffuseTransmission => Quantity::Separation,
            // A back wall behind the layer: its return against the background's, with the gap.
            Effect::ThreeReturns => Quantity::Separation,
        }
    }

    /// Quantities besides [`Effect::signature`] the same misfit follows by the effect's
    /// geometry (a displacement along rows shows along rows).
    fn other_signatures(&self) -> &'static [Quantity] {
        match self {
            Effect::RefractionShift => &[Quantity::ImageRow],
            Effect::TransmissionLaw => &[Quantity::ForegroundDistance],
            Effect::SubsurfaceDelay => &[Quantity::IncidenceAngle],
            _ => &[],
        }
    }

    /// Parameters counted by the penalty: a discrete switch counts as one.
    pub fn penalty_params(&self) -> usize {
        self.param_names().len().max(1)
    }
}

/// One pixel of one frame with a known foreground distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AuditPixel {
    /// Index of the frame among the audited frames.
    pub frame: usize,
    /// Image column.
    pub col: usize,
    /// Image row.
    pub row: usize,
    /// What the pipeline knows at the pixel (reading, IR, its own background, `Lin`).
    pub obs: PixelObservation,
    /// True foreground ray distance, mm.
    pub truth_mm: f64,
    /// `cos(theta_f)` of the true surface at the pixel.
    pub incidence_cos: f64,
}

/// A recording prepared for the audit.
#[derive(Debug, Clone)]
pub struct AuditData {
    /// The pixels (a lattice over each frame's translucent pixels with truth).
    pub pixels: Vec<AuditPixel>,
    /// Frames the pixels come from.
    pub frames: usize,
    /// The latched background's ray distance, mm, smoothed over a few pixels:
    /// what every hypothesis sees behind the layer (smoothing keeps the latch's
    /// noise from making the fit rough in a displacement, and is the same for all).
    pub background_distance_mm: ImageBuf<f64>,
    /// The latched background's IR, counts, smoothed likewise.
    pub background_ir: ImageBuf<f64>,
    /// `Lin`, counts mm^2, smoothed likewise.
    pub emitted_light: ImageBuf<f64>,
    /// Depth noise of an opaque return times the square root of its IR, mm counts^(1/2)
    /// (shot noise: `sigma_d = k_d sqrt(total) / amplitude`), measured over the latch.
    pub depth_noise_coef: f64,
    /// IR noise over the square root of the IR, counts^(1/2), measured over the latch.
    pub ir_noise_coef: f64,
}

/// Why the audit cannot run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AuditError {
    /// Too few frames with known foreground distances to leave any out.
    #[error("{got} frame(s) show the layer with ground truth over its translucent pixels; the audit needs at least {need} (a calibration sequence: the layer at several known distances) to fit on some and test on the others")]
    TooFewFrames {
        /// Frames with usable pixels.
        got: usize,
        /// Frames needed.
        need: usize,
    },
    /// Too few pixels.
    #[error("{got} translucent pixel(s) with ground truth; the audit needs at least {need}")]
    TooFewPixels {
        /// Pixels.
        got: usize,
        /// Needed.
        need: usize,
    },
    /// The background's noise could not be measured.
    #[error("the background's noise is unknown (the latch needs at least 3 frames of a still background)")]
    NoNoise,
}

/// Least frames the audit works with (it leaves frames out in folds).
pub const MIN_FRAMES: usize = 4;
/// Least pixels.
pub const MIN_PIXELS: usize = 200;

/// A hypothesis: the baseline with these effects, and its fitted values.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Fit {
    /// Effects in the model.
    pub effects: Vec<Effect>,
    /// ξ.
    pub xi: f64,
    /// `rho_f`, the material's albedo (times whatever scale `Lin` carries).
    pub albedo: f64,
    /// The effects' parameters, by name, each inside its physical range ([`PHYSICAL_RANGES`]).
    pub params: Vec<(String, f64)>,
    /// The parameters that sit on a bound of their physical range (the unconstrained
    /// optimum lies outside it, or on it): the effect is scored at the bound.
    pub at_bound: Vec<String>,
    /// Bounces kept (when higher-order bounces are in).
    pub bounces: usize,
    /// RMS of the depth residual over every pixel, fitted on all of them, mm.
    pub rmse_mm: f64,
    /// RMS of the IR residual relative to the IR, fitted on all pixels.
    pub ir_rel_rmse: f64,
    /// RMS of the depth residual on frames left out of the fit, mm.
    pub heldout_rmse_mm: f64,
    /// Mean held-out loss per pixel (depth and IR, in units of their noise; Huber).
    pub heldout_score: f64,
    /// Held-out depth recovery: RMS over blocks ([`recovery_blocks`]) of the mean recovered
    /// minus true foreground (ray) distance, over the pixels of frames left out of the fit,
    /// each inverted per pixel with the model and ξ fitted without its frame; a pixel the
    /// model cannot invert counts as read. mm.
    pub heldout_recovery_rmse_mm: f64,
    /// Held-out recovery error per block ([`recovery_blocks`]), mm (for paired comparisons).
    #[serde(skip)]
    pub heldout_recovery_blocks_mm: Vec<f64>,
    /// Held-out loss per pixel (for paired comparisons).
    #[serde(skip)]
    pub heldout_loss: Vec<f64>,
    /// Held-out depth residual per pixel, mm (predicted minus read, wrapped).
    #[serde(skip)]
    pub heldout_residual_mm: Vec<f64>,
    /// Held-out IR residual per pixel, counts.
    #[serde(skip)]
    pub heldout_ir_residual: Vec<f64>,
    /// Parameter vector (internal coordinates) of the all-pixel fit.
    #[serde(skip)]
    theta: Vec<f64>,
}

impl Fit {
    /// The forward model this fit describes on top of `base`.
    pub fn model(&self, base: &ForwardModel) -> ForwardModel {
        build_model(base, &self.effects, &self.theta[2..], self.bounces)
    }
}

/// One candidate's score in one round of the greedy selection.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CandidateScore {
    /// Round (0 = the first effect added to the baseline).
    pub round: usize,
    /// The effect tried.
    pub effect: Effect,
    /// Held-out depth RMS with it, mm.
    pub heldout_rmse_mm: f64,
    /// Mean held-out loss per pixel with it.
    pub heldout_score: f64,
    /// Held-out depth recovery with it, mm ([`Fit::heldout_recovery_rmse_mm`]).
    pub heldout_recovery_rmse_mm: f64,
    /// Improvement of the summed held-out loss over the model of that round.
    pub gain: f64,
    /// What the gain had to exceed: the parameter penalty or the noise of the gain, whichever is larger.
    pub threshold: f64,
    /// The gain in units of its own standard error (pixel-paired).
    pub z: f64,
    /// Its fitted parameters (inside their physical ranges).
    pub params: Vec<(String, f64)>,
    /// The parameters that sit on a bound of their physical range.
    pub at_bound: Vec<String>,
    /// ξ refitted with it.
    pub xi: f64,
    /// Its signature test: the misfit it predicts against the observed one, and plausibility.
    pub signature: SignatureTest,
    /// Accepted.
    pub accepted: bool,
    /// Why it was not accepted though its loss gain passed (held-out depth error worse beyond noise);
    /// empty otherwise.
    pub rejected: String,
}

/// An effect's signature test ([`Effect::signature`]): the misfit it predicts along its
/// quantity set against the misfit observed there, and whether its parameters are plausible.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SignatureTest {
    /// The quantity the effect's misfit follows (the one of its signatures that shows most).
    pub quantity: Quantity,
    /// Trend of the model's held-out residual without the effect along the quantity, beyond
    /// noise: `(chi2 - dof) / sqrt(2 dof)` of the bin means, depth and IR in noise units.
    pub observed_z: f64,
    /// The same with the effect.
    pub left_z: f64,
    /// Share of the observed trend beyond noise that the effect's predicted change takes away.
    pub explained: f64,
    /// Correlation over the bins of the effect's predicted change with the observed residual.
    pub correlation: f64,
    /// The quantity the residual without the effect follows most, of its signatures and
    /// [`LOCATING`]: the misfit's dominant structure.
    pub dominant: Quantity,
    /// Its trend, z.
    pub dominant_z: f64,
    /// Share of that trend beyond noise the effect takes away: physics the recording holds
    /// takes away the misfit's main structure, not only a part along its own quantity.
    pub dominant_explained: f64,
    /// The parameters are physically plausible ([`plausibility`]).
    pub plausible: bool,
    /// Why the test fails, in words; empty where it passes.
    pub failed: String,
    /// The misfit follows the quantity, the effect takes most of that away, and its
    /// parameters are plausible.
    pub passed: bool,
}

/// Least trend (z) a residual must show along an effect's signature for the effect to be named.
pub const SIGNATURE_MIN_Z: f64 = 3.0;
/// Least share of that trend the effect must take away.
pub const SIGNATURE_MIN_EXPLAINED: f64 = 0.5;
/// Largest ambient offset that is plausible, as a share of the layer's median IR: an offset
/// is a small part of the signal (dark level, ambient light), not the signal itself.
pub const AMBIENT_MAX_SHARE: f64 = 0.25;
/// Parameters whose physical range ends at a limit of plausibility, not at a physical
/// state: a fit on that end is the effect stretched to take up a misfit of another kind.
const PLAUSIBLE_INSIDE: [&str; 5] = [
    "subsurface_delay_mm",
    "shift_columns_px",
    "shift_rows_px",
    "wall_interreflection",
    "hollow_depth_mm",
];

/// A quantity residuals are tested against.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Quantity {
    /// Layer-to-background gap `db - df`, mm.
    Separation,
    /// Foreground distance `df`, mm.
    ForegroundDistance,
    /// The reading's phase as a fraction of the unambiguous range.
    Phase,
    /// Brightness: the IR level, counts.
    IrLevel,
    /// Incidence angle on the layer (from the true surface's normal), degrees.
    IncidenceAngle,
    /// Image column.
    ImageColumn,
    /// Image row.
    ImageRow,
    /// Image position: distance from the image's centre, pixels.
    ImageRadius,
    /// Frame time: the frame's index in the recording's order.
    Frame,
    /// Pose: the index of the frame's pose (frames whose layer's median true distance
    /// agrees within [`POSE_TOLERANCE_MM`]), in order of distance.
    Pose,
    /// View factor from the pixel's background point to the layer (a near wall's third return).
    ViewFactor,
}

impl Quantity {
    /// Every quantity.
    pub const ALL: [Quantity; 11] = [
        Quantity::Separation,
        Quantity::ForegroundDistance,
        Quantity::Phase,
        Quantity::IrLevel,
        Quantity::IncidenceAngle,
        Quantity::ImageColumn,
        Quantity::ImageRow,
        Quantity::ImageRadius,
        Quantity::Frame,
        Quantity::Pose,
        Quantity::ViewFactor,
    ];

    /// Name in reports and file names.
    pub fn name(&self) -> &'static str {
        match self {
            Quantity::Separation => "separation_mm",
            Quantity::ForegroundDistance => "foreground_distance_mm",
            Quantity::Phase => "phase_fraction",
            Quantity::IrLevel => "ir_counts",
            Quantity::IncidenceAngle => "incidence_deg",
            Quantity::ImageColumn => "image_column",
            Quantity::ImageRow => "image_row",
            Quantity::ImageRadius => "image_radius_px",
            Quantity::Frame => "frame",
            Quantity::Pose => "pose",
            Quantity::ViewFactor => "wall_view_factor",
        }
    }

    /// The quantity in words, for the dependence the audit states.
    pub fn words(&self) -> &'static str {
        match self {
            Quantity::Separation => "the layer-to-background gap",
            Quantity::ForegroundDistance => "the layer's distance",
            Quantity::Phase => "the reading's phase",
            Quantity::IrLevel => "the brightness (IR level)",
            Quantity::IncidenceAngle => "the incidence angle on the layer",
            Quantity::ImageColumn => "the image column",
            Quantity::ImageRow => "the image row",
            Quantity::ImageRadius => "the image position (distance from the centre)",
            Quantity::Frame => "the frame time",
            Quantity::Pose => "the pose",
            Quantity::ViewFactor => "the view factor from the background to the layer",
        }
    }

    fn value(&self, p: &AuditPixel, ctx: &QuantityContext) -> f64 {
        match self {
            Quantity::Separation => p.obs.background_distance_mm - p.truth_mm,
            Quantity::ForegroundDistance => p.truth_mm,
            Quantity::Phase => (p.obs.distance_mm / ctx.range_mm).rem_euclid(1.0),
            Quantity::IrLevel => p.obs.ir,
            Quantity::IncidenceAngle => p.incidence_cos.clamp(-1.0, 1.0).acos().to_degrees(),
            Quantity::ImageColumn => p.col as f64,
            Quantity::ImageRow => p.row as f64,
            Quantity::ImageRadius => (p.col as f64 - ctx.centre[0]).hypot(p.row as f64 - ctx.centre[1]),
            Quantity::Frame => p.frame as f64,
            Quantity::Pose => ctx.pose_of_frame.get(p.frame).map_or(f64::NAN, |&k| k as f64),
            Quantity::ViewFactor => p.obs.wall_view_factor,
        }
    }
}

/// What the quantities need beyond a pixel: the unambiguous range, each frame's pose and
/// the image's centre.
#[derive(Debug, Clone)]
pub struct QuantityContext {
    range_mm: f64,
    pose_of_frame: Vec<usize>,
    centre: [f64; 2],
}

impl QuantityContext {
    /// The context of a recording read at unambiguous range `range_mm`.
    pub fn new(data: &AuditData, range_mm: f64) -> Self {
        let b = &data.background_distance_mm;
        Self {
            range_mm,
            pose_of_frame: frame_poses(data).0,
            centre: [(b.width as f64 - 1.0) / 2.0, (b.height as f64 - 1.0) / 2.0],
        }
    }
}

/// Residuals binned against one quantity (a plot's series).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Trend {
    /// The quantity.
    pub quantity: Quantity,
    /// Bin edges `[lo, hi]` in the quantity's unit.
    pub bins: Vec<[f64; 2]>,
    /// Pixels per bin.
    pub counts: Vec<usize>,
    /// Mean depth residual per bin, mm.
    pub mean_mm: Vec<f64>,
    /// Standard error of that mean, mm.
    pub se_mm: Vec<f64>,
    /// Mean IR residual per bin relative to the IR (percent).
    pub ir_mean_pct: Vec<f64>,
    /// Departure of the bin means from their overall mean, in units of the
    /// spread expected from noise: `(chi2 - dof) / sqrt(2 dof)` of depth and IR pooled.
    pub systematic_z: f64,
}

impl Trend {
    /// The bin whose mean depth residual is largest in magnitude, in words.
    pub fn worst_bin(&self) -> String {
        let Some(k) = (0..self.bins.len())
            .filter(|&k| self.counts[k] > 0)
            .max_by(|&a, &b| self.mean_mm[a].abs().total_cmp(&self.mean_mm[b].abs()))
        else {
            return String::new();
        };
        format!(
            "{} {}..{}: depth {:+.1} mm, IR {:+.2} % ({} px)",
            self.quantity.name(),
            short(self.bins[k][0]),
            short(self.bins[k][1]),
            self.mean_mm[k],
            self.ir_mean_pct[k],
            self.counts[k]
        )
    }
}

/// Where a step's model took the residual away: the quantities whose trend
/// fell most from `before` to `after`, each with the bin whose mean residual
/// shrank most, in words.
pub fn where_it_helped(before: &[Trend], after: &[Trend]) -> String {
    let mut drops: Vec<(f64, String)> = before
        .iter()
        .zip(after)
        .filter(|(b, a)| b.quantity == a.quantity && b.mean_mm.len() == a.mean_mm.len())
        .map(|(b, a)| {
            let k = (0..b.mean_mm.len())
                .max_by(|&i, &j| {
                    (b.mean_mm[i].abs() - a.mean_mm[i].abs()).total_cmp(&(b.mean_mm[j].abs() - a.mean_mm[j].abs()))
                })
                .unwrap_or(0);
            let text = if b.bins.is_empty() {
                String::new()
            } else {
                format!(
                    "{} {}..{}: depth {:+.1} -> {:+.1} mm, IR {:+.2} -> {:+.2} % (trend z {:.0} -> {:.0})",
                    b.quantity.name(),
                    short(b.bins[k][0]),
                    short(b.bins[k][1]),
                    b.mean_mm[k],
                    a.mean_mm[k],
                    b.ir_mean_pct[k],
                    a.ir_mean_pct[k],
                    b.systematic_z,
                    a.systematic_z
                )
            };
            (b.systematic_z - a.systematic_z, text)
        })
        .filter(|(d, t)| *d > 0.0 && !t.is_empty())
        .collect();
    drops.sort_by(|a, b| b.0.total_cmp(&a.0));
    drops.into_iter().take(2).map(|d| d.1).collect::<Vec<_>>().join("; ")
}

fn short(v: f64) -> String {
    if v.abs() >= 100.0 || v.fract() == 0.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.3}")
    }
}

/// Settings of the audit.
#[derive(Debug, Clone, PartialEq)]
pub struct AuditSettings {
    /// Folds of frames left out (whole poses, or frames interleaved: `frame_folds`).
    pub folds: usize,
    /// Huber threshold of the loss, in noise sigmas.
    pub huber_k: f64,
    /// Penalty per parameter in units of the loss (BIC-like: times `ln N`).
    pub penalty_per_param_ln_n: f64,
    /// Least pixel-paired z of an accepted gain.
    pub min_gain_z: f64,
    /// Least relative improvement of the held-out loss for an accepted effect.
    pub min_relative_gain: f64,
    /// Most effects added.
    pub max_effects: usize,
    /// Bins per trend.
    pub trend_bins: usize,
    /// Iterations of each Nelder-Mead fit.
    pub max_iterations: usize,
    /// Bounds of the per-pixel inversion that scores held-out recovery (the pipeline's).
    pub inversion: InversionBounds,
}

impl Default for AuditSettings {
    fn default() -> Self {
        Self {
            folds: 4,
            huber_k: 3.0,
            penalty_per_param_ln_n: 2.0,
            min_gain_z: 4.0,
            min_relative_gain: 0.02,
            max_effects: 3,
            trend_bins: 8,
            max_iterations: 260,
            inversion: InversionBounds::default(),
        }
    }
}

/// What the audit found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AuditResult {
    /// The paper's model fitted.
    pub baseline: Fit,
    /// Effects accepted, in order, each with the model up to it.
    pub steps: Vec<Fit>,
    /// How many of `steps` the model to use keeps: it stops at the last step whose held-out
    /// recovery is no worse than the one before beyond noise ([`steps_recovering_no_worse`]).
    pub kept_steps: usize,
    /// Every candidate's score in every round.
    pub candidates: Vec<CandidateScore>,
    /// The baseline's residual trends.
    pub trends_before: Vec<Trend>,
    /// The final model's residual trends.
    pub trends_after: Vec<Trend>,
    /// The residual trends of each accepted step's model (as `steps`).
    pub step_trends: Vec<Vec<Trend>>,
    /// Pixels used.
    pub pixels: usize,
    /// Frames used.
    pub frames: usize,
    /// RMS of the final model's held-out residuals in units of the noise (about 1 when
    /// the noise model and the physics are right).
    pub final_noise_ratio: f64,
    /// The one quantity the final model's residual follows most: what no effect named explains.
    pub dependence: Dependence,
}

/// The quantities a residual no effect explains is located by (issue 50: distance, incidence,
/// brightness, image position, pose, frame time, gap).
pub const LOCATING: [Quantity; 9] = [
    Quantity::ForegroundDistance,
    Quantity::IncidenceAngle,
    Quantity::IrLevel,
    Quantity::ImageRadius,
    Quantity::ImageColumn,
    Quantity::ImageRow,
    Quantity::Pose,
    Quantity::Frame,
    Quantity::Separation,
];

/// Least trend (z) of the final residual along a quantity for the audit to state it as a
/// dependence: below it the residual is noise along every quantity.
pub const DEPENDENCE_MIN_Z: f64 = 5.0;

/// Where the residual the final model leaves lies: the one strongest dependence, against the others.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Dependence {
    /// The quantity the residual follows most, where it follows one beyond
    /// [`DEPENDENCE_MIN_Z`]; `None` where it is noise along every one.
    pub quantity: Option<Quantity>,
    /// Its trend, z.
    pub z: f64,
    /// Every locating quantity's trend z, strongest first.
    pub against: Vec<(Quantity, f64)>,
    /// The dependence in words, with its strength against the next strongest.
    pub words: String,
}

/// The one strongest dependence of `trends` (a fit's residual trends) among [`LOCATING`].
pub fn strongest_dependence(trends: &[Trend]) -> Dependence {
    let mut against: Vec<(Quantity, f64)> = trends
        .iter()
        .filter(|t| LOCATING.contains(&t.quantity) && t.systematic_z.is_finite())
        .map(|t| (t.quantity, t.systematic_z))
        .collect();
    against.sort_by(|a, b| b.1.total_cmp(&a.1));
    let top = against.first().copied();
    let next = against
        .get(1)
        .map_or(String::new(), |(q, z)| format!("; next {} {z:.1}", q.name()));
    let (quantity, z, words) = match top {
        Some((q, z)) if z >= DEPENDENCE_MIN_Z => {
            let bin = trends
                .iter()
                .find(|t| t.quantity == q)
                .map(|t| t.worst_bin())
                .unwrap_or_default();
            (
                Some(q),
                z,
                format!(
                    "the residual no effect explains follows {} most (trend z {z:.1}{next}); largest at {bin}",
                    q.words()
                ),
            )
        }
        Some((q, z)) => (
            None,
            z,
            format!(
                "the residual follows no quantity beyond noise (strongest {} z {z:.1}, {DEPENDENCE_MIN_Z} needed)",
                q.name()
            ),
        ),
        None => (None, 0.0, "the residual could not be binned".to_string()),
    };
    Dependence {
        quantity,
        z,
        against,
        words,
    }
}

impl AuditResult {
    /// The final model's fit (every effect claimed).
    pub fn final_fit(&self) -> &Fit {
        self.steps.last().unwrap_or(&self.baseline)
    }

    /// The fit of the model to use: the claimed steps up to the last one that recovers
    /// no worse than the one before (the baseline when the first already recovers worse).
    pub fn kept_fit(&self) -> &Fit {
        self.kept_steps
            .checked_sub(1)
            .and_then(|k| self.steps.get(k))
            .unwrap_or(&self.baseline)
    }
}

// ---------------------------------------------------------------------------
// The model of a hypothesis.

const XI_MIN: f64 = 0.001;
const XI_MAX: f64 = 0.999;

fn logistic(u: f64) -> f64 {
    (1.0 / (1.0 + (-u).exp())).clamp(XI_MIN, XI_MAX)
}

fn logit(x: f64) -> f64 {
    let x = x.clamp(XI_MIN, XI_MAX);
    (x / (1.0 - x)).ln()
}

/// The forward model of `effects` with their parameters `p` (in order) on top of `base`.
fn build_model(base: &ForwardModel, effects: &[Effect], p: &[f64], bounces: usize) -> ForwardModel {
    let mut options = base.options.clone();
    let mut waveform = base.sensor.waveform;
    let mut k = 0;
    for e in effects {
        match e {
            Effect::HigherOrderBounces => options.bounces = bounces,
            Effect::WaveformHarmonics => {
                waveform = Waveform::Harmonics {
                    third: p[k],
                    fifth: p[k + 1],
                }
            }
            Effect::IrAmplitude => options.ir_mode = IrMode::Amplitude,
            Effect::AmbientOffset => options.ambient_offset = p[k],
            Effect::SubsurfaceDelay => options.subsurface_delay_mm = p[k],
            Effect::TransmissionLaw => options.transmission_albedo_power = p[k],
            Effect::RefractionShift => options.refraction_shift_px = [p[k], p[k + 1]],
            Effect::WallInterreflection => options.wall_interreflection = p[k],
            Effect::DiffuseTransmission => options.diffuse_transmission = p[k],
            Effect::ThreeReturns => options.hollow_depth_mm = p[k],
        }
        k += e.param_names().len();
    }
    let sensor = if waveform == base.sensor.waveform {
        base.sensor.clone()
    } else {
        Sensor::with_decode_table_len(base.sensor.modulation_frequency_hz, waveform, AUDIT_DECODE_TABLE_LEN)
    };
    ForwardModel { sensor, options }
}

/// Decoder table of the harmonic waveforms the fits try (sensor.rs): coarse, as it is rebuilt per trial.
const AUDIT_DECODE_TABLE_LEN: usize = 512;

/// The physical range of a named parameter ([`PHYSICAL_RANGES`]); unbounded when it has none.
fn range_of(name: &str) -> (f64, f64) {
    PHYSICAL_RANGES
        .iter()
        .find(|(n, _, _)| *n == name)
        .map_or((f64::NEG_INFINITY, f64::INFINITY), |&(_, lo, hi)| (lo, hi))
}

/// `theta` (`[logit xi, ln albedo, effect params...]`) with every effect parameter projected
/// onto its physical range, and how far outside the ranges it was, in simplex steps.
fn project(effects: &[Effect], theta: &[f64], steps: &[f64]) -> (Vec<f64>, f64) {
    let mut t = theta.to_vec();
    let mut outside = 0.0;
    for (k, name) in effect_param_names(effects).enumerate() {
        let j = k + 2;
        let (lo, hi) = range_of(name);
        let v = t[j].clamp(lo, hi);
        let step = steps.get(j).copied().filter(|s| *s > 0.0).unwrap_or(1.0);
        outside += (t[j] - v).abs() / step;
        t[j] = v;
    }
    (t, outside)
}

/// `f` of the parameters projected onto their ranges, plus how far outside they were (in
/// simplex steps): flat past a bound but for that small slope back toward it.
fn bounded<'a>(effects: &'a [Effect], steps: &'a [f64], f: impl Fn(&[f64]) -> f64 + 'a) -> impl Fn(&[f64]) -> f64 + 'a {
    move |t| {
        let (inside, outside) = project(effects, t, steps);
        f(&inside) + outside
    }
}

/// The names of the effects' continuous parameters, in `theta` order (after ξ and the albedo).
fn effect_param_names(effects: &[Effect]) -> impl Iterator<Item = &'static str> + '_ {
    effects.iter().flat_map(|e| e.param_names().iter().copied())
}

/// The parameters of `theta` (projected) that sit on a bound of their physical range.
fn at_bounds(effects: &[Effect], theta: &[f64]) -> Vec<String> {
    effect_param_names(effects)
        .zip(theta.iter().skip(2))
        .filter(|(name, v)| {
            let (lo, hi) = range_of(name);
            let tol = 1e-9 * (1.0 + v.abs());
            (**v - lo).abs() <= tol || (hi - **v).abs() <= tol
        })
        .map(|(name, _)| name.to_string())
        .collect()
}

/// Where each effect starts, and the simplex step, given a typical IR level.
fn param_starts(e: Effect, ir_level: f64) -> (Vec<Vec<f64>>, Vec<f64>) {
    match e {
        Effect::HigherOrderBounces | Effect::IrAmplitude => (vec![vec![]], vec![]),
        Effect::WaveformHarmonics => (
            vec![vec![0.0, 0.0], vec![-0.08, 0.0], vec![0.08, 0.0]],
            vec![0.03, 0.02],
        ),
        Effect::AmbientOffset => (vec![vec![0.0]], vec![0.03 * ir_level]),
        Effect::SubsurfaceDelay => (vec![vec![0.0], vec![25.0]], vec![8.0]),
        Effect::TransmissionLaw => (vec![vec![2.0], vec![1.0], vec![0.0]], vec![0.4]),
        Effect::WallInterreflection => (vec![vec![0.0], vec![1.0]], vec![0.3]),
        Effect::DiffuseTransmission => (vec![vec![0.0], vec![0.5], vec![1.0]], vec![0.2]),
        Effect::ThreeReturns => (vec![vec![0.0], vec![150.0], vec![350.0]], vec![50.0]),
        Effect::RefractionShift => (
            vec![
                vec![0.0, 0.0],
                vec![3.0, 0.0],
                vec![-3.0, 0.0],
                vec![0.0, 3.0],
                vec![0.0, -3.0],
            ],
            vec![1.0, 1.0],
        ),
    }
}

/// Pixel weights and per-pixel noise, fixed for every hypothesis.
#[derive(Debug, Clone)]
struct Prepared<'a> {
    data: &'a AuditData,
    base: ForwardModel,
    /// Depth noise per pixel, mm.
    sigma_d: Vec<f64>,
    /// IR noise per pixel, counts.
    sigma_i: Vec<f64>,
    huber_k: f64,
    /// Median IR of the pixels, counts (the scale of an IR offset's simplex step).
    ir_level: f64,
    /// Each pixel's fold of held-out poses ([`frame_folds`]), and the number of folds.
    fold: Vec<usize>,
    folds: usize,
}

/// What a hypothesis knows at a pixel: its observation with the background seen
/// through the layer from the smoothed latch. Every hypothesis sees the background
/// through the smoothed latch (undisplaced unless the hypothesis refracts), so none
/// gains merely from less noisy inputs.
fn observation(model: &ForwardModel, data: &AuditData, p: &AuditPixel, displaced: bool) -> Option<PixelObservation> {
    let mut obs = p.obs;
    let mut o = model.options.clone();
    if !displaced || !o.refracts() {
        o.refraction_shift_px = [1e-9, 0.0];
    }
    let (db, ib) = o.background_through_layer(
        &data.background_distance_mm,
        &data.background_ir,
        &data.emitted_light,
        p.col,
        p.row,
    )?;
    obs.background_distance_mm = db;
    obs.background_ir = ib;
    Some(obs)
}

/// Prediction of one pixel's `(reading, IR)` under a model, ξ and albedo.
fn predict(
    model: &ForwardModel,
    data: &AuditData,
    p: &AuditPixel,
    xi: f64,
    albedo: f64,
    displaced: bool,
) -> Option<(f64, f64, f64)> {
    let obs = observation(model, data, p, displaced)?;
    if !(p.truth_mm < obs.background_distance_mm) {
        return None;
    }
    let x = albedo * p.incidence_cos;
    let scene = obs.layer_scene(p.truth_mm, xi, x, model.options.ambient_offset);
    let m = model.measure_layer(&scene);
    let amp = m.buckets.a.hypot(m.buckets.b);
    Some((m.distance_mm, m.ir, amp / m.total_light.max(1e-12)))
}

fn huber(r: f64, k: f64) -> f64 {
    let a = r.abs();
    if a <= k {
        0.5 * a * a
    } else {
        k * (a - 0.5 * k)
    }
}

/// Per-pixel evaluation of one model.
struct Eval {
    loss: f64,
    res_mm: f64,
    res_ir: f64,
}

impl<'a> Prepared<'a> {
    fn new(data: &'a AuditData, base: &ForwardModel, settings: &AuditSettings) -> Self {
        let sigma_i = data
            .pixels
            .iter()
            .map(|p| (data.ir_noise_coef * p.obs.ir.max(1.0).sqrt()).max(0.5))
            .collect();
        let (frame_fold, folds) = frame_folds(data, settings.folds);
        Self {
            data,
            base: base.clone(),
            sigma_d: vec![f64::NAN; data.pixels.len()],
            sigma_i,
            huber_k: settings.huber_k,
            ir_level: median(data.pixels.iter().map(|p| p.obs.ir).collect()),
            fold: data
                .pixels
                .iter()
                .map(|p| frame_fold.get(p.frame).copied().unwrap_or(0))
                .collect(),
            folds,
        }
    }

    /// Depth noise from the shot noise of the light and the mix's amplitude
    /// (a mix of returns out of phase reads noisier), from a reference fit.
    fn set_depth_noise(&mut self, model: &ForwardModel, xi: f64, albedo: f64) {
        let d = self.data;
        self.sigma_d = d
            .pixels
            .iter()
            .map(|p| {
                let ratio = predict(model, d, p, xi, albedo, false)
                    .map(|(_, _, r)| r)
                    .filter(|r| r.is_finite() && *r > 0.0)
                    .unwrap_or(1.0)
                    .max(0.05);
                (d.depth_noise_coef / p.obs.ir.max(1.0).sqrt() / ratio).max(0.5)
            })
            .collect();
    }

    fn eval(&self, model: &ForwardModel, i: usize, xi: f64, albedo: f64, displaced: bool) -> Eval {
        let p = &self.data.pixels[i];
        let cap = 2.0 * huber(self.huber_k * 3.0, self.huber_k);
        match predict(model, self.data, p, xi, albedo, displaced) {
            Some((d, ir, _)) if d.is_finite() && ir.is_finite() => {
                let res_mm = model.sensor.wrapped_difference_mm(d, p.obs.distance_mm);
                let res_ir = ir - p.obs.ir;
                let loss =
                    huber(res_mm / self.sigma_d[i], self.huber_k) + huber(res_ir / self.sigma_i[i], self.huber_k);
                Eval {
                    loss: loss.min(cap),
                    res_mm,
                    res_ir,
                }
            }
            _ => Eval {
                loss: cap,
                res_mm: f64::NAN,
                res_ir: f64::NAN,
            },
        }
    }

    fn model_of(&self, effects: &[Effect], theta: &[f64], bounces: usize) -> ForwardModel {
        build_model(&self.base, effects, &theta[2..], bounces)
    }

    /// Recovered minus true foreground distance at pixel `i`, mm: the pixel inverted with
    /// `model` at `xi` as recovery does (Eq. 8-12, the root nearest the reading), the
    /// reading itself where the model admits no layer (the pixel is left as read).
    fn recovery_error_mm(
        &self,
        model: &ForwardModel,
        i: usize,
        xi: f64,
        displaced: bool,
        bounds: &InversionBounds,
    ) -> f64 {
        let p = &self.data.pixels[i];
        let recovered = observation(model, self.data, p, displaced)
            .and_then(|obs| foreground_distance_without_slopes(model, &obs, xi, bounds, None))
            .map(|e| e.foreground_distance_mm)
            .filter(|d| d.is_finite())
            .unwrap_or(p.obs.distance_mm);
        recovered - p.truth_mm
    }

    /// Summed loss over `pixels` of the hypothesis at `theta` (its parameters inside their ranges).
    fn objective(&self, effects: &[Effect], theta: &[f64], bounces: usize, pixels: &[usize]) -> f64 {
        if !theta.iter().all(|v| v.is_finite()) {
            return 1e12;
        }
        let model = self.model_of(effects, theta, bounces);
        let (xi, albedo) = (logistic(theta[0]), theta[1].exp());
        let displaced = effects.contains(&Effect::RefractionShift);
        pixels
            .iter()
            .map(|&i| self.eval(&model, i, xi, albedo, displaced).loss)
            .sum()
    }
}

// ---------------------------------------------------------------------------
// Optimisation.

/// Nelder-Mead minimisation from `x0` with initial steps `step`.
fn nelder_mead(f: &dyn Fn(&[f64]) -> f64, x0: &[f64], step: &[f64], max_iter: usize) -> (Vec<f64>, f64) {
    let n = x0.len();
    let mut simplex: Vec<(Vec<f64>, f64)> = Vec::with_capacity(n + 1);
    simplex.push((x0.to_vec(), f(x0)));
    for j in 0..n {
        let mut x = x0.to_vec();
        x[j] += step[j];
        let v = f(&x);
        simplex.push((x, v));
    }
    for _ in 0..max_iter {
        simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
        let (best, worst) = (simplex[0].1, simplex[n].1);
        if (worst - best).abs() <= 1e-7 * (best.abs() + 1e-9) + 1e-9 {
            break;
        }
        let mut c = vec![0.0; n];
        for s in &simplex[..n] {
            for j in 0..n {
                c[j] += s.0[j] / n as f64;
            }
        }
        let along = |t: f64| -> Vec<f64> { (0..n).map(|j| c[j] + t * (simplex[n].0[j] - c[j])).collect() };
        let xr = along(-1.0);
        let fr = f(&xr);
        if fr < simplex[0].1 {
            let xe = along(-2.0);
            let fe = f(&xe);
            simplex[n] = if fe < fr { (xe, fe) } else { (xr, fr) };
        } else if fr < simplex[n - 1].1 {
            simplex[n] = (xr, fr);
        } else {
            let (xc, fc) = if fr < simplex[n].1 {
                let x = along(-0.5);
                let v = f(&x);
                (x, v)
            } else {
                let x = along(0.5);
                let v = f(&x);
                (x, v)
            };
            if fc < simplex[n].1.min(fr) {
                simplex[n] = (xc, fc);
            } else {
                let b = simplex[0].0.clone();
                for s in simplex.iter_mut().skip(1) {
                    for j in 0..n {
                        s.0[j] = b[j] + 0.5 * (s.0[j] - b[j]);
                    }
                    s.1 = f(&s.0);
                }
            }
        }
    }
    simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
    let (x, v) = simplex.swap_remove(0);
    (x, v)
}

/// Golden-section search of a unimodal function on `[a, b]`.
fn golden(f: &dyn Fn(f64) -> f64, mut a: f64, mut b: f64, iters: usize) -> (f64, f64) {
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..iters {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = f(d);
        }
    }
    if fc < fd {
        (c, fc)
    } else {
        (d, fd)
    }
}

/// Where a hypothesis's fits start: every combination of its effects' starts, and the simplex steps.
fn starts_and_steps(effects: &[Effect], ir_level: f64) -> (Vec<Vec<f64>>, Vec<f64>) {
    let mut steps = vec![0.4, 0.15];
    // Cartesian product of each effect's starts (few: effects rarely exceed 2 with several starts).
    let mut starts: Vec<Vec<f64>> = vec![vec![]];
    for e in effects {
        let (s, st) = param_starts(*e, ir_level);
        steps.extend(st);
        starts = starts
            .iter()
            .flat_map(|a| {
                s.iter().map(move |b| {
                    let mut v = a.clone();
                    v.extend(b);
                    v
                })
            })
            .collect();
    }
    (starts, steps)
}

/// Fits a hypothesis on `pixels`: a coarse scan of ξ (albedo by golden
/// section) for each start of the effects' parameters, then Nelder-Mead from
/// the best starts. Returns `theta = [logit xi, ln albedo, effect params...]`.
///
/// Bounded: the effects' parameters are projected onto their physical ranges
/// before the model is evaluated (a step past a bound costs a little more
/// than the bound, so the simplex settles on it), and the `theta` returned is
/// projected: where the unconstrained optimum lies outside, the fit sits on
/// the bound, reachable exactly (the plain law's power 0 included).
fn fit_hypothesis(
    prep: &Prepared,
    effects: &[Effect],
    bounces: usize,
    pixels: &[usize],
    warm: Option<&[f64]>,
    settings: &AuditSettings,
) -> (Vec<f64>, f64) {
    let (starts, steps) = starts_and_steps(effects, prep.ir_level);
    let obj = bounded(effects, &steps, |t| prep.objective(effects, t, bounces, pixels));
    let (x, _) = match warm {
        Some(w) => nelder_mead(&obj, w, &steps, settings.max_iterations / 2),
        None => fit_from_starts(&obj, &starts, &steps, settings),
    };
    onto_range(&obj, effects, &x, &steps)
}

/// `x` projected onto the ranges, each parameter within a hundredth of a step of a
/// bound moved onto it where that fits no worse (the simplex stops short of a bound
/// by its tolerance): `(theta, objective)`.
fn onto_range(obj: &dyn Fn(&[f64]) -> f64, effects: &[Effect], x: &[f64], steps: &[f64]) -> (Vec<f64>, f64) {
    let (mut t, _) = project(effects, x, steps);
    let mut v = obj(&t);
    for (k, name) in effect_param_names(effects).enumerate() {
        let j = k + 2;
        let (lo, hi) = range_of(name);
        let near = 0.01 * steps.get(j).copied().unwrap_or(1.0);
        for bound in [lo, hi] {
            if bound.is_finite() && t[j] != bound && (t[j] - bound).abs() < near {
                let mut trial = t.clone();
                trial[j] = bound;
                let tv = obj(&trial);
                if tv <= v {
                    (t, v) = (trial, tv);
                }
            }
        }
    }
    (t, v)
}

/// The coarse ξ scan from every start, the best few refined, the best of those polished.
fn fit_from_starts(
    obj: &dyn Fn(&[f64]) -> f64,
    starts: &[Vec<f64>],
    steps: &[f64],
    settings: &AuditSettings,
) -> (Vec<f64>, f64) {
    let mut seeds: Vec<(Vec<f64>, f64)> = vec![];
    for s in starts {
        for k in 0..10 {
            let xi = 0.05 + k as f64 * 0.1;
            let f1 = |la: f64| {
                let mut t = vec![logit(xi), la];
                t.extend(s);
                obj(&t)
            };
            let (la, v) = golden(&f1, (0.02f64).ln(), (3.0f64).ln(), 14);
            let mut t = vec![logit(xi), la];
            t.extend(s);
            seeds.push((t, v));
        }
    }
    seeds.sort_by(|a, b| a.1.total_cmp(&b.1));
    let mut best: Option<(Vec<f64>, f64)> = None;
    // The best few seeds, distinct in xi, each refined.
    let mut tried: Vec<f64> = vec![];
    for (t, _) in seeds {
        if tried.iter().any(|x| (x - t[0]).abs() < 0.5) {
            continue;
        }
        tried.push(t[0]);
        let r = nelder_mead(obj, &t, steps, settings.max_iterations);
        if best.as_ref().is_none_or(|b| r.1 < b.1) {
            best = Some(r);
        }
        if tried.len() >= 3 {
            break;
        }
    }
    let (x, _) = best.unwrap_or((vec![0.0, 0.0], f64::INFINITY));
    // Polish.
    nelder_mead(obj, &x, steps, settings.max_iterations)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    super::stats::median_sorted(&v)
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for x in v.filter(|x| x.is_finite()) {
        s += x * x;
        n += 1;
    }
    if n == 0 {
        f64::NAN
    } else {
        (s / n as f64).sqrt()
    }
}

/// Fits a hypothesis on all pixels and scores it on left-out frames.
fn score(prep: &Prepared, effects: &[Effect], settings: &AuditSettings) -> Fit {
    let data = prep.data;
    let all: Vec<usize> = (0..data.pixels.len()).collect();
    let (theta, bounces) = fit_all(prep, effects, &all, settings);
    let model = prep.model_of(effects, &theta, bounces);
    let (xi, albedo) = (logistic(theta[0]), theta[1].exp());
    let displaced = effects.contains(&Effect::RefractionShift);
    let evals: Vec<Eval> = all
        .iter()
        .map(|&i| prep.eval(&model, i, xi, albedo, displaced))
        .collect();
    let rmse_mm = rms(evals.iter().map(|e| e.res_mm));
    let ir_rel_rmse = rms(evals
        .iter()
        .zip(&data.pixels)
        .map(|(e, p)| e.res_ir / p.obs.ir.max(1.0)));
    let h = held_out(prep, effects, &theta, bounces, settings);
    let n = h.loss.iter().filter(|v| v.is_finite()).count().max(1);
    let blocks = recovery_blocks(data, &h.recovery_mm);
    Fit {
        effects: effects.to_vec(),
        xi,
        albedo,
        params: named_params(effects, &theta, bounces),
        at_bound: at_bounds(effects, &theta),
        bounces,
        rmse_mm,
        ir_rel_rmse,
        heldout_rmse_mm: rms(h.residual_mm.iter().copied()),
        heldout_score: h.loss.iter().filter(|v| v.is_finite()).sum::<f64>() / n as f64,
        heldout_recovery_rmse_mm: rms(blocks.iter().copied()),
        heldout_recovery_blocks_mm: blocks,
        heldout_loss: h.loss,
        heldout_residual_mm: h.residual_mm,
        heldout_ir_residual: h.ir_residual,
        theta,
    }
}

/// The hypothesis fitted on `pixels`, with the better of its bounce counts: `(theta, bounces)`.
fn fit_all(prep: &Prepared, effects: &[Effect], pixels: &[usize], settings: &AuditSettings) -> (Vec<f64>, usize) {
    let bounce_options: Vec<usize> = if effects.contains(&Effect::HigherOrderBounces) {
        vec![3, MAX_BOUNCES]
    } else {
        vec![prep.base.options.bounces]
    };
    let mut best: Option<(Vec<f64>, f64, usize)> = None;
    for &b in &bounce_options {
        let (t, v) = fit_hypothesis(prep, effects, b, pixels, None, settings);
        if best.as_ref().is_none_or(|x| v < x.1) {
            best = Some((t, v, b));
        }
    }
    let (theta, _, bounces) = best.unwrap_or((vec![0.0, 0.0], f64::INFINITY, 2));
    (theta, bounces)
}

/// The effects' parameters by name (and the bounces kept, where they are in).
fn named_params(effects: &[Effect], theta: &[f64], bounces: usize) -> Vec<(String, f64)> {
    let mut params = vec![];
    let mut k = 2;
    for e in effects {
        for name in e.param_names() {
            params.push((name.to_string(), theta[k]));
            k += 1;
        }
        if *e == Effect::HigherOrderBounces {
            params.push(("bounces".to_string(), bounces as f64));
        }
    }
    params
}

/// Per pixel, what a hypothesis refitted without the pixel's frame says of it.
struct HeldOut {
    /// Loss (depth and IR in units of their noise; Huber).
    loss: Vec<f64>,
    /// Depth residual, mm (predicted minus read, wrapped).
    residual_mm: Vec<f64>,
    /// IR residual, counts.
    ir_residual: Vec<f64>,
    /// Recovered minus true foreground distance, mm.
    recovery_mm: Vec<f64>,
}

/// Folds of frames, interleaved: each fold's pixels scored by the hypothesis refitted on the others.
fn held_out(prep: &Prepared, effects: &[Effect], theta: &[f64], bounces: usize, settings: &AuditSettings) -> HeldOut {
    let data = prep.data;
    let n = data.pixels.len();
    let mut h = HeldOut {
        loss: vec![f64::NAN; n],
        residual_mm: vec![f64::NAN; n],
        ir_residual: vec![f64::NAN; n],
        recovery_mm: vec![f64::NAN; n],
    };
    let displaced = effects.contains(&Effect::RefractionShift);
    for f in 0..prep.folds {
        let (test, train): (Vec<usize>, Vec<usize>) = (0..n).partition(|&i| prep.fold[i] == f);
        if test.is_empty() || train.is_empty() {
            continue;
        }
        let (t, _) = fit_hypothesis(prep, effects, bounces, &train, Some(theta), settings);
        let m = prep.model_of(effects, &t, bounces);
        let (x, a) = (logistic(t[0]), t[1].exp());
        for &i in &test {
            let e = prep.eval(&m, i, x, a, displaced);
            h.loss[i] = e.loss;
            h.residual_mm[i] = e.res_mm;
            h.ir_residual[i] = e.res_ir;
            h.recovery_mm[i] = prep.recovery_error_mm(&m, i, x, displaced, &settings.inversion);
        }
    }
    h
}

/// Two frames show the layer in one pose when their median true distances are this close, mm.
const POSE_TOLERANCE_MM: f64 = 10.0;

/// Each frame's fold, and the number of folds (at most `folds`, at least 2). With two poses or
/// more (frames whose layer's median true distance agrees within [`POSE_TOLERANCE_MM`]), whole
/// poses are left out, dealt to the folds in order of distance: an effect must predict a
/// distance it was not fitted at, not another frame of a pose it has seen (with frames
/// interleaved, a few parameters can follow each pose's own misfit). With one pose, frames
/// interleaved.
fn frame_folds(data: &AuditData, folds: usize) -> (Vec<usize>, usize) {
    let (pose, poses) = frame_poses(data);
    if poses >= 2 {
        let n = folds.clamp(2, poses);
        (pose.iter().map(|&p| p % n).collect(), n)
    } else {
        let n = folds.clamp(2, data.frames.max(2));
        ((0..data.frames).map(|f| f % n).collect(), n)
    }
}

/// Each frame's pose (frames whose layer's median true distance agrees within
/// [`POSE_TOLERANCE_MM`] show one pose), numbered in order of distance, and the number of poses.
fn frame_poses(data: &AuditData) -> (Vec<usize>, usize) {
    let mut per_frame: Vec<Vec<f64>> = vec![vec![]; data.frames];
    for p in &data.pixels {
        if let Some(v) = per_frame.get_mut(p.frame) {
            v.push(p.truth_mm);
        }
    }
    let mut order: Vec<(f64, usize)> = per_frame
        .iter_mut()
        .enumerate()
        .map(|(f, v)| (super::stats::median_select(v), f))
        .collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut pose = vec![0usize; data.frames];
    let mut poses = 0usize;
    let mut last = f64::NAN;
    for &(d, f) in &order {
        if !(d - last <= POSE_TOLERANCE_MM) {
            poses += 1;
            last = d;
        }
        pose[f] = poses.saturating_sub(1);
    }
    (pose, poses)
}

/// The folds ([`frame_folds`], as `prep` holds them) and the gain of `new` over `old` in held-out loss from all
/// but the fold where it gains most: what is left when the one pose (or set of poses) that
/// shows it best is set aside. A misfit of one pose that any flexible effect takes up gains
/// in that fold alone; physics shows in every pose.
fn gain_beyond_best_fold(prep: &Prepared, old: &Fit, new: &Fit) -> (usize, f64) {
    let mut per_fold = vec![0.0; prep.folds];
    for ((a, b), &f) in old.heldout_loss.iter().zip(&new.heldout_loss).zip(&prep.fold) {
        let d = a - b;
        if d.is_finite() {
            per_fold[f] += d;
        }
    }
    let total: f64 = per_fold.iter().sum();
    let best = per_fold.iter().copied().fold(0.0, f64::max);
    (prep.folds, total - best)
}

/// Gain of `new` over `old` in summed held-out loss, and its pixel-paired z.
fn paired_gain(old: &Fit, new: &Fit) -> (f64, f64, usize) {
    let d: Vec<f64> = old
        .heldout_loss
        .iter()
        .zip(&new.heldout_loss)
        .map(|(a, b)| a - b)
        .filter(|v| v.is_finite())
        .collect();
    let n = d.len();
    let Some((sum, var)) = sum_and_variance(&d) else {
        return (0.0, 0.0, n);
    };
    let se_sum = (var * n as f64).sqrt().max(1e-12);
    (sum, sum / se_sum, n)
}

/// The sum of paired differences `d` and their sample variance; `None` with fewer than two.
fn sum_and_variance(d: &[f64]) -> Option<(f64, f64)> {
    let n = d.len();
    if n < 2 {
        return None;
    }
    let sum: f64 = d.iter().sum();
    let mean = sum / n as f64;
    let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    Some((sum, var))
}

/// Residual trends of a fit's held-out residuals against every quantity.
pub fn trends(
    data: &AuditData,
    fit: &Fit,
    range_mm: f64,
    sigma_ir_of: impl Fn(usize) -> f64,
    bins: usize,
) -> Vec<Trend> {
    let ctx = QuantityContext::new(data, range_mm);
    Quantity::ALL
        .iter()
        .map(|q| trend(data, fit, *q, &ctx, &sigma_ir_of, bins))
        .collect()
}

/// `(value, pixel)` pairs sorted by value in quantile groups of about `len / bins`, equal
/// values kept in one group (frames, columns); none where fewer than `2 bins` pairs.
fn quantile_groups(mut idx: Vec<(f64, usize)>, bins: usize) -> Vec<Vec<(f64, usize)>> {
    idx.sort_by(|a, b| a.0.total_cmp(&b.0));
    if idx.len() < 2 * bins || bins == 0 {
        return vec![];
    }
    let mut groups: Vec<Vec<(f64, usize)>> = vec![];
    let per = idx.len().div_ceil(bins);
    let mut cur: Vec<(f64, usize)> = vec![];
    for (k, item) in idx.iter().enumerate() {
        if cur.len() >= per && item.0 > cur.last().map(|c| c.0).unwrap_or(f64::NAN) && idx.len() - k >= per / 2 {
            groups.push(std::mem::take(&mut cur));
        }
        cur.push(*item);
    }
    if !cur.is_empty() {
        groups.push(cur);
    }
    groups
}

fn trend(
    data: &AuditData,
    fit: &Fit,
    q: Quantity,
    ctx: &QuantityContext,
    sigma_ir_of: &dyn Fn(usize) -> f64,
    bins: usize,
) -> Trend {
    let idx: Vec<(f64, usize)> = data
        .pixels
        .iter()
        .enumerate()
        .filter(|(i, _)| fit.heldout_residual_mm[*i].is_finite())
        .map(|(i, p)| (q.value(p, ctx), i))
        .filter(|(v, _)| v.is_finite())
        .collect();
    let mut t = Trend {
        quantity: q,
        bins: vec![],
        counts: vec![],
        mean_mm: vec![],
        se_mm: vec![],
        ir_mean_pct: vec![],
        systematic_z: 0.0,
    };
    let groups = quantile_groups(idx, bins);
    if groups.is_empty() {
        return t;
    }
    let idx: Vec<(f64, usize)> = groups.iter().flatten().copied().collect();
    let z_all: Vec<(f64, f64)> = idx
        .iter()
        .map(|&(_, i)| (fit.heldout_residual_mm[i], fit.heldout_ir_residual[i] / sigma_ir_of(i)))
        .collect();
    let mean_of = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let sd_d = robust_sd(z_all.iter().map(|z| z.0).collect()).max(1e-9);
    let sd_i = robust_sd(z_all.iter().map(|z| z.1).filter(|v| v.is_finite()).collect()).max(1e-9);
    let gd = mean_of(&z_all.iter().map(|z| z.0).collect::<Vec<_>>());
    let gi = mean_of(&z_all.iter().map(|z| z.1).filter(|v| v.is_finite()).collect::<Vec<_>>());
    let (mut chi2, mut dof) = (0.0, 0.0);
    for g in &groups {
        let d: Vec<f64> = g.iter().map(|&(_, i)| fit.heldout_residual_mm[i]).collect();
        let ir: Vec<f64> = g
            .iter()
            .map(|&(_, i)| fit.heldout_ir_residual[i] / sigma_ir_of(i))
            .filter(|v| v.is_finite())
            .collect();
        let ir_pct: Vec<f64> = g
            .iter()
            .map(|&(_, i)| 100.0 * fit.heldout_ir_residual[i] / data.pixels[i].obs.ir.max(1.0))
            .filter(|v| v.is_finite())
            .collect();
        let n = d.len() as f64;
        let md = mean_of(&d);
        let mi = mean_of(&ir);
        // Clipped means against outliers: trimmed to 4 sigma of the pooled spread.
        chi2 += n * ((md - gd) / sd_d).powi(2).min(1e6) + ir.len() as f64 * ((mi - gi) / sd_i).powi(2).min(1e6);
        dof += 2.0;
        t.bins.push([g[0].0, g[g.len() - 1].0]);
        t.counts.push(g.len());
        t.mean_mm.push(md);
        t.se_mm.push(robust_sd(d.clone()) / n.sqrt());
        t.ir_mean_pct.push(mean_of(&ir_pct));
    }
    dof -= 2.0;
    if dof > 0.0 {
        t.systematic_z = (chi2 - dof) / (2.0 * dof).sqrt();
    }
    t
}

/// Bin means of two fits' held-out residuals along `q`, depth and IR in noise units (each
/// pixel's clipped at 3 Huber thresholds), scaled by the spread of `before`'s: per bin and
/// channel `(pixels, mean before, mean after)`.
fn binned_pair(
    prep: &Prepared,
    ctx: &QuantityContext,
    q: Quantity,
    before: &Fit,
    after: &Fit,
    bins: usize,
) -> Vec<(f64, f64, f64)> {
    let clip = 3.0 * prep.huber_k;
    let z = |f: &Fit, i: usize| {
        [
            (f.heldout_residual_mm[i] / prep.sigma_d[i]).clamp(-clip, clip),
            (f.heldout_ir_residual[i] / prep.sigma_i[i]).clamp(-clip, clip),
        ]
    };
    let known = |f: &Fit, i: usize| z(f, i).iter().all(|v| v.is_finite());
    let idx: Vec<(f64, usize)> = prep
        .data
        .pixels
        .iter()
        .enumerate()
        .filter(|(i, _)| known(before, *i) && known(after, *i))
        .map(|(i, p)| (q.value(p, ctx), i))
        .filter(|(v, _)| v.is_finite())
        .collect();
    let groups = quantile_groups(idx, bins);
    let mut out = vec![];
    for c in 0..2 {
        let spread = robust_sd(groups.iter().flatten().map(|&(_, i)| z(before, i)[c]).collect()).max(1e-9);
        for g in &groups {
            let n = g.len() as f64;
            let (b, a) = g
                .iter()
                .fold((0.0, 0.0), |(b, a), &(_, i)| (b + z(before, i)[c], a + z(after, i)[c]));
            out.push((n, b / n / spread, a / n / spread));
        }
    }
    out
}

/// `(chi2 - dof) / sqrt(2 dof)` of bin means `(pixels, mean)` (in units of a pixel's spread)
/// about their pixel-weighted mean, `dof` the bins less one per channel (`channels`).
fn structure_z(bins: &[(f64, f64)], channels: usize) -> (f64, f64) {
    let n: f64 = bins.iter().map(|b| b.0).sum();
    if bins.len() <= channels || n <= 0.0 {
        return (0.0, 0.0);
    }
    let per = bins.len() / channels;
    let mut chi2 = 0.0;
    for ch in bins.chunks(per) {
        let m = ch.iter().map(|b| b.0 * b.1).sum::<f64>() / ch.iter().map(|b| b.0).sum::<f64>().max(1e-12);
        chi2 += ch.iter().map(|b| b.0 * (b.1 - m).powi(2)).sum::<f64>();
    }
    let dof = (bins.len() - channels) as f64;
    ((chi2 - dof) / (2.0 * dof).sqrt(), chi2)
}

/// The signature test of `effect`, `after` its fit added to `before`: along each of its
/// signature quantities the residual `before` leaves must vary beyond noise
/// ([`SIGNATURE_MIN_Z`]) and the effect must take at least [`SIGNATURE_MIN_EXPLAINED`] of
/// that away; its parameters must be plausible ([`plausibility`]). The quantity reported is
/// the signature along which the effect explains most.
fn signature_test(
    prep: &Prepared,
    ctx: &QuantityContext,
    effect: Effect,
    before: &Fit,
    after: &Fit,
    bins: usize,
) -> SignatureTest {
    let mut best: Option<SignatureTest> = None;
    let own: Vec<Quantity> = std::iter::once(effect.signature())
        .chain(effect.other_signatures().iter().copied())
        .collect();
    // The misfit's dominant structure: the quantity the residual without the effect follows most.
    let (mut dominant, mut dominant_z, mut dominant_explained) = (effect.signature(), f64::NEG_INFINITY, 0.0);
    for &q in own.iter().chain(LOCATING.iter()) {
        let (z, _, explained, _) = along(prep, ctx, q, before, after, bins);
        if z > dominant_z {
            (dominant, dominant_z, dominant_explained) = (q, z, explained);
        }
    }
    for q in own {
        let (observed_z, left_z, explained, correlation) = along(prep, ctx, q, before, after, bins);
        let t = SignatureTest {
            quantity: q,
            observed_z,
            left_z,
            explained,
            correlation,
            dominant,
            dominant_z,
            dominant_explained,
            plausible: true,
            failed: String::new(),
            passed: false,
        };
        if best
            .as_ref()
            .is_none_or(|b| t.explained * t.observed_z.max(0.0) > b.explained * b.observed_z.max(0.0))
        {
            best = Some(t);
        }
    }
    let mut t = best.unwrap_or(SignatureTest {
        quantity: effect.signature(),
        observed_z: 0.0,
        left_z: 0.0,
        explained: 0.0,
        correlation: 0.0,
        dominant,
        dominant_z,
        dominant_explained,
        plausible: true,
        failed: String::new(),
        passed: false,
    });
    let implausible = plausibility(effect, after, prep.data).err();
    t.plausible = implausible.is_none();
    t.failed = if t.observed_z < SIGNATURE_MIN_Z {
        format!(
            "no misfit along {} to explain (trend z {:.1}, {SIGNATURE_MIN_Z} needed)",
            t.quantity.name(),
            t.observed_z
        )
    } else if !(t.explained >= SIGNATURE_MIN_EXPLAINED) {
        format!(
            "its predicted misfit does not follow the observed one along {}: it takes {:.0} % of the trend away ({:.0} % needed; trend z {:.1} -> {:.1})",
            t.quantity.name(),
            100.0 * t.explained,
            100.0 * SIGNATURE_MIN_EXPLAINED,
            t.observed_z,
            t.left_z
        )
    } else if !(t.dominant_explained >= SIGNATURE_MIN_EXPLAINED) {
        format!(
            "the misfit follows {} most (trend z {:.1}) and it takes {:.0} % of that away ({:.0} % needed)",
            t.dominant.name(),
            t.dominant_z,
            100.0 * t.dominant_explained,
            100.0 * SIGNATURE_MIN_EXPLAINED
        )
    } else {
        implausible.unwrap_or_default()
    };
    t.passed = t.failed.is_empty();
    t
}

/// The trend of `before`'s residual along `q` and of `after`'s (z), the share of the
/// first beyond noise that `after` takes away, and the bins' correlation of the change
/// with the residual.
fn along(
    prep: &Prepared,
    ctx: &QuantityContext,
    q: Quantity,
    before: &Fit,
    after: &Fit,
    bins: usize,
) -> (f64, f64, f64, f64) {
    let pair = binned_pair(prep, ctx, q, before, after, bins);
    let obs: Vec<(f64, f64)> = pair.iter().map(|p| (p.0, p.1)).collect();
    let left: Vec<(f64, f64)> = pair.iter().map(|p| (p.0, p.2)).collect();
    let (observed_z, chi_obs) = structure_z(&obs, 2);
    let (left_z, chi_left) = structure_z(&left, 2);
    let dof = pair.len().saturating_sub(2) as f64;
    let explained = if chi_obs > dof {
        (chi_obs - chi_left) / (chi_obs - dof)
    } else {
        0.0
    };
    (observed_z, left_z, explained, bin_correlation(&pair))
}

/// Correlation over bins and channels of the predicted change (before minus after) with
/// the observed residual (before), each about its channel's pixel-weighted mean.
fn bin_correlation(pair: &[(f64, f64, f64)]) -> f64 {
    let per = (pair.len() / 2).max(1);
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for ch in pair.chunks(per) {
        let w: f64 = ch.iter().map(|p| p.0).sum::<f64>().max(1e-12);
        let mo = ch.iter().map(|p| p.0 * p.1).sum::<f64>() / w;
        let mp = ch.iter().map(|p| p.0 * (p.1 - p.2)).sum::<f64>() / w;
        for p in ch {
            let (o, d) = (p.1 - mo, p.1 - p.2 - mp);
            sxy += p.0 * o * d;
            sxx += p.0 * o * o;
            syy += p.0 * d * d;
        }
    }
    if sxx > 0.0 && syy > 0.0 {
        sxy / (sxx * syy).sqrt()
    } else {
        0.0
    }
}

/// Whether a fit's parameters are physically plausible: an ambient offset a small share of
/// the layer's IR ([`AMBIENT_MAX_SHARE`]), a hollow object's back wall before the
/// background, and no parameter of [`PLAUSIBLE_INSIDE`] on the far end of its range.
pub fn plausibility(effect: Effect, fit: &Fit, data: &AuditData) -> Result<(), String> {
    let param = |name: &str| fit.params.iter().find(|(n, _)| n == name).map(|p| p.1);
    match effect {
        Effect::AmbientOffset => {
            let ir = median(data.pixels.iter().map(|p| p.obs.ir).collect());
            let offset = param("ambient_offset").unwrap_or(0.0);
            if !(offset <= AMBIENT_MAX_SHARE * ir) {
                return Err(format!(
                    "an ambient offset of {offset:.0} counts is {:.0} % of the layer's median IR ({ir:.0} counts): more than a small part of the signal ({:.0} % at most)",
                    100.0 * offset / ir,
                    100.0 * AMBIENT_MAX_SHARE
                ));
            }
        }
        Effect::ThreeReturns => {
            let gap = median(
                data.pixels
                    .iter()
                    .map(|p| p.obs.background_distance_mm - p.truth_mm)
                    .collect(),
            );
            let t = param("hollow_depth_mm").unwrap_or(0.0);
            if !(t < gap) {
                return Err(format!(
                    "a back wall {t:.0} mm behind the layer lies behind the background for most pixels (median gap {gap:.0} mm)"
                ));
            }
        }
        _ => {}
    }
    for name in PLAUSIBLE_INSIDE {
        if let Some(v) = param(name) {
            let (lo, hi) = range_of(name);
            let far = if lo < 0.0 { v.abs() >= hi } else { v >= hi };
            if far {
                return Err(format!(
                    "{name} {v:.3} sits on the far end of its range: the effect stretched to take up another misfit"
                ));
            }
        }
    }
    Ok(())
}

/// The spread of `v`'s finite values from their median absolute deviation (a normal's sd); NaN when none.
fn robust_sd(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return f64::NAN;
    }
    let m = super::stats::median_sorted(&v);
    let mut dev: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
    dev.sort_by(f64::total_cmp);
    1.4826 * super::stats::median_sorted(&dev)
}

/// Runs the audit: baseline, greedy forward selection over [`Effect::ALL`],
/// trends before and after. `base` is the paper's model on the recording's
/// sensor (its options are the baseline: normally the paper's defaults).
pub fn run_audit(data: &AuditData, base: &ForwardModel, settings: &AuditSettings) -> Result<AuditResult, AuditError> {
    run_audit_with_progress(data, base, settings, &mut |_| {})
}

/// [`run_audit`], telling `progress` what it is fitting (one call per hypothesis).
pub fn run_audit_with_progress(
    data: &AuditData,
    base: &ForwardModel,
    settings: &AuditSettings,
    progress: &mut dyn FnMut(&str),
) -> Result<AuditResult, AuditError> {
    check_inputs(data)?;
    let range_mm = base.sensor.unambiguous_range_mm();
    let mut prep = Prepared::new(data, base, settings);
    // Noise weights from a first baseline fit with photon-limited depth noise, then refit.
    prep.sigma_d = data
        .pixels
        .iter()
        .map(|p| (data.depth_noise_coef / p.obs.ir.max(1.0).sqrt()).max(0.5))
        .collect();
    let first = score_full_only(&prep, settings);
    prep.set_depth_noise(&prep.model_of(&[], &first, 2), logistic(first[0]), first[1].exp());
    progress("baseline");
    let baseline = score(&prep, &[], settings);
    let mut current = baseline.clone();
    let mut steps: Vec<Fit> = vec![];
    let mut candidates = vec![];
    let mut remaining = candidate_effects(base);
    let ctx = QuantityContext::new(data, range_mm);
    for round in 0..settings.max_effects {
        let (scores, best) = run_round(&prep, &ctx, &current, &remaining, round, settings, progress);
        candidates.extend(scores);
        let Some((fit, ci)) = best else {
            break;
        };
        remaining.remove(ci);
        current = fit.clone();
        steps.push(fit);
        if remaining.is_empty() {
            break;
        }
    }
    let sig = |i: usize| prep.sigma_i[i];
    let trends_before = trends(data, &baseline, range_mm, sig, settings.trend_bins);
    let last = steps.last().unwrap_or(&baseline);
    let trends_after = trends(data, last, range_mm, sig, settings.trend_bins);
    let step_trends = steps
        .iter()
        .map(|s| trends(data, s, range_mm, sig, settings.trend_bins))
        .collect();
    let final_noise_ratio = {
        let v: Vec<f64> = last.heldout_loss.iter().copied().filter(|v| v.is_finite()).collect();
        // Mean Huber loss of two unit-noise residuals is about 1 (0.5 each).
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    let recovery: Vec<&[f64]> = steps.iter().map(|s| s.heldout_recovery_blocks_mm.as_slice()).collect();
    let kept_steps = steps_recovering_no_worse(&baseline.heldout_recovery_blocks_mm, &recovery);
    let dependence = strongest_dependence(&trends_after);
    Ok(AuditResult {
        baseline,
        steps,
        kept_steps,
        candidates,
        trends_before,
        trends_after,
        step_trends,
        pixels: data.pixels.len(),
        frames: data.frames,
        final_noise_ratio,
        dependence,
    })
}

/// The audit's inputs are enough to leave frames out and weigh residuals by their noise.
fn check_inputs(data: &AuditData) -> Result<(), AuditError> {
    if data.frames < MIN_FRAMES {
        return Err(AuditError::TooFewFrames {
            got: data.frames,
            need: MIN_FRAMES,
        });
    }
    if data.pixels.len() < MIN_PIXELS {
        return Err(AuditError::TooFewPixels {
            got: data.pixels.len(),
            need: MIN_PIXELS,
        });
    }
    let known = |v: f64| v.is_finite() && v > 0.0;
    if !(known(data.depth_noise_coef) && known(data.ir_noise_coef)) {
        return Err(AuditError::NoNoise);
    }
    Ok(())
}

/// The candidates past `base`: what the baseline already models is no candidate.
fn candidate_effects(base: &ForwardModel) -> Vec<Effect> {
    let mut remaining: Vec<Effect> = Effect::ALL.to_vec();
    if base.sensor.waveform != Waveform::Sinusoid {
        remaining.retain(|e| *e != Effect::WaveformHarmonics);
    }
    if base.options.ir_mode == IrMode::Amplitude {
        remaining.retain(|e| *e != Effect::IrAmplitude);
    }
    if base.options.bounces > 2 {
        remaining.retain(|e| *e != Effect::HigherOrderBounces);
    }
    remaining
}

/// One round of the greedy selection: every remaining effect added to `current`
/// and scored; the best one claimed (with its index in `remaining`), if any is.
fn run_round(
    prep: &Prepared,
    ctx: &QuantityContext,
    current: &Fit,
    remaining: &[Effect],
    round: usize,
    settings: &AuditSettings,
    progress: &mut dyn FnMut(&str),
) -> (Vec<CandidateScore>, Option<(Fit, usize)>) {
    let n = prep.data.pixels.len() as f64;
    let mut best: Option<(Fit, usize)> = None;
    let mut scores = vec![];
    for (ci, e) in remaining.iter().enumerate() {
        let mut effects = current.effects.clone();
        effects.push(*e);
        progress(e.name());
        let fit = score(prep, &effects, settings);
        let (gain, z, _) = paired_gain(current, &fit);
        let threshold = (settings.penalty_per_param_ln_n * e.penalty_params() as f64 * n.ln())
            .max(settings.min_relative_gain * current.heldout_score * n);
        let passes = gain > threshold && z > settings.min_gain_z;
        // An effect is claimed only where more than one fold of poses shows it, and where it
        // also predicts the held-out depths no worse beyond noise; otherwise the loss gain is
        // the fit bending to something else. Its parameters are inside their physical ranges
        // by construction (bounded fits).
        let (folds, one_fold) = gain_beyond_best_fold(prep, current, &fit);
        let rest_needed = threshold * (folds as f64 - 1.0) / folds as f64;
        let depth_worse = squared_increase_z(&current.heldout_residual_mm, &fit.heldout_residual_mm)
            .is_none_or(|z| z > WORSE_BEYOND_NOISE_Z);
        let signature = signature_test(prep, ctx, *e, current, &fit, settings.trend_bins);
        let rejected = if passes && one_fold < rest_needed {
            format!(
                "its held-out gain comes from one fold of poses: {one_fold:.0} from the others against {rest_needed:.0} needed"
            )
        } else if passes && depth_worse {
            format!(
                "held-out depth error {:.1} mm against {:.1} without it, worse beyond noise",
                fit.heldout_rmse_mm, current.heldout_rmse_mm
            )
        } else if passes && !signature.passed {
            format!("its signature test fails: {}", signature.failed)
        } else {
            String::new()
        };
        let ok = passes && rejected.is_empty();
        scores.push(CandidateScore {
            round,
            effect: *e,
            heldout_rmse_mm: fit.heldout_rmse_mm,
            heldout_score: fit.heldout_score,
            heldout_recovery_rmse_mm: fit.heldout_recovery_rmse_mm,
            gain,
            threshold,
            z,
            params: fit.params.clone(),
            at_bound: fit.at_bound.clone(),
            xi: fit.xi,
            signature,
            accepted: false,
            rejected,
        });
        if ok && best.as_ref().is_none_or(|(b, _)| fit.heldout_score < b.heldout_score) {
            best = Some((fit, ci));
        }
    }
    if let Some((_, ci)) = &best {
        for s in &mut scores {
            s.accepted = s.effect == remaining[*ci];
        }
    }
    (scores, best)
}

/// Side of the square blocks of one frame whose pixels' held-out recovery errors are
/// averaged, pixels: the smooth-surface prior's window (`prior_radius_px` 4). `replay`
/// recovers a pixel with its neighbourhood's surface, so a model's recovery is judged by
/// a neighbourhood's mean error, where a per-pixel inversion's noise averages out and a
/// bias or a wrong root stays.
pub const RECOVERY_BLOCK_PX: usize = 9;

/// A model predicts or recovers worse than another beyond noise when the mean increase of
/// the squared error, paired, exceeds this many of its standard errors ([`squared_increase_z`]).
pub const WORSE_BEYOND_NOISE_Z: f64 = 2.0;

/// The mean of `recovery_mm` (per pixel, NaN where unknown) over each block of
/// [`RECOVERY_BLOCK_PX`] pixels of a frame, in one order for every model (by frame, row
/// block, column block); NaN for a block with no known pixel.
pub fn recovery_blocks(data: &AuditData, recovery_mm: &[f64]) -> Vec<f64> {
    let mut sums: std::collections::BTreeMap<(usize, usize, usize), (f64, usize)> = Default::default();
    for (p, &e) in data.pixels.iter().zip(recovery_mm) {
        let key = (p.frame, p.row / RECOVERY_BLOCK_PX, p.col / RECOVERY_BLOCK_PX);
        let s = sums.entry(key).or_insert((0.0, 0));
        if e.is_finite() {
            s.0 += e;
            s.1 += 1;
        }
    }
    sums.values()
        .map(|&(s, n)| if n == 0 { f64::NAN } else { s / n as f64 })
        .collect()
}

/// The mean increase of the squared error from `old` to `new` (paired, entries both
/// know) in units of its standard error; `None` with fewer than two pairs or where the
/// two are not paired (lengths differ).
pub fn squared_increase_z(old: &[f64], new: &[f64]) -> Option<f64> {
    if old.len() != new.len() {
        return None;
    }
    let d: Vec<f64> = old
        .iter()
        .zip(new)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| b * b - a * a)
        .collect();
    let (sum, var) = sum_and_variance(&d)?;
    let n = d.len() as f64;
    Some(sum / n / (var / n).sqrt().max(1e-12))
}

/// Whether `new`'s block recovery errors are worse than `old`'s (as [`recovery_blocks`]
/// orders them) beyond noise ([`WORSE_BEYOND_NOISE_Z`]); unpaired counts as worse.
pub fn recovers_worse(old: &[f64], new: &[f64]) -> bool {
    squared_increase_z(old, new).is_none_or(|z| z > WORSE_BEYOND_NOISE_Z)
}

/// How many of the claimed steps a model keeps when it stops at the last step that
/// recovers no worse than the one before beyond noise ([`recovers_worse`]): `steps[k]`
/// is step `k + 1`'s held-out block recovery errors, `baseline` the baseline's.
pub fn steps_recovering_no_worse(baseline: &[f64], steps: &[&[f64]]) -> usize {
    let mut prev = baseline;
    let mut kept = 0;
    for &r in steps {
        if recovers_worse(prev, r) {
            break;
        }
        prev = r;
        kept += 1;
    }
    kept
}

/// Physical ranges of the effects' parameters: every fit is bounded to them.
/// The harmonics' bounds are a square wave's (1/3 and 1/5 of the fundamental: square
/// emission read through short windows), the richest correlation a CW sensor has;
/// `L2 = Ib xi^2 X^p` with `p` from 0 (light crossing the layer) to 2 (the paper's Eq. 2);
/// a delay and an offset are not negative.
pub const PHYSICAL_RANGES: &[(&str, f64, f64)] = &[
    ("third", -1.0 / 3.0, 1.0 / 3.0),
    ("fifth", -1.0 / 5.0, 1.0 / 5.0),
    ("transmission_albedo_power", 0.0, 2.0),
    ("subsurface_delay_mm", 0.0, 200.0),
    ("ambient_offset", 0.0, f64::INFINITY),
    ("shift_columns_px", -20.0, 20.0),
    ("shift_rows_px", -20.0, 20.0),
    ("wall_interreflection", 0.0, 3.0),
    ("diffuse_transmission", 0.0, 1.0),
    ("hollow_depth_mm", 0.0, 1500.0),
];

/// The baseline fitted on all pixels (internal coordinates), for the noise weights.
fn score_full_only(prep: &Prepared, settings: &AuditSettings) -> Vec<f64> {
    let all: Vec<usize> = (0..prep.data.pixels.len()).collect();
    fit_hypothesis(prep, &[], prep.base.options.bounces, &all, None, settings).0
}

/// The model options a set of fitted effects gives, on top of `base` (for a physics file).
pub fn fitted_options(base: &ForwardModel, fit: &Fit) -> (ModelOptions, Waveform) {
    let m = fit.model(base);
    (m.options, m.sensor.waveform)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nelder_mead_finds_a_quadratic_minimum() {
        let f = |x: &[f64]| (x[0] - 1.0).powi(2) + 3.0 * (x[1] + 2.0).powi(2);
        let (x, v) = nelder_mead(&f, &[0.0, 0.0], &[0.5, 0.5], 400);
        assert!(
            (x[0] - 1.0).abs() < 1e-3 && (x[1] + 2.0).abs() < 1e-3 && v < 1e-6,
            "{x:?}"
        );
    }

    #[test]
    fn a_bounded_fit_reaches_the_bound_where_the_optimum_lies_past_it() {
        // The plain law (power 0) with the unconstrained optimum at -0.04, as measured on a
        // rendered sequence: the bounded fit sits exactly on 0 and says so.
        let effects = [Effect::TransmissionLaw];
        let steps = [0.4, 0.15, 0.4];
        let f = |t: &[f64]| (t[0] - 0.5).powi(2) + (t[1] + 0.2).powi(2) + 50.0 * (t[2] + 0.04).powi(2);
        let obj = bounded(&effects, &steps, f);
        for start in [2.0, 1.0, 0.0] {
            let (x, _) = nelder_mead(&obj, &[0.0, 0.0, start], &steps, 400);
            let (x, _) = onto_range(&obj, &effects, &x, &steps);
            assert_eq!(x[2], 0.0, "start {start}: {x:?}");
            assert!((x[0] - 0.5).abs() < 1e-3 && (x[1] + 0.2).abs() < 1e-3, "{x:?}");
            assert_eq!(at_bounds(&effects, &x), vec!["transmission_albedo_power".to_string()]);
        }
        // Inside the range the optimum is found where it is, on no bound.
        let g = |t: &[f64]| t[0].powi(2) + t[1].powi(2) + (t[2] - 0.7).powi(2);
        let obj = bounded(&effects, &steps, g);
        let (x, _) = nelder_mead(&obj, &[0.0, 0.0, 2.0], &steps, 400);
        let (x, _) = onto_range(&obj, &effects, &x, &steps);
        assert!((x[2] - 0.7).abs() < 1e-3, "{x:?}");
        assert!(at_bounds(&effects, &x).is_empty());
    }

    #[test]
    fn projection_keeps_every_parameter_in_its_physical_range() {
        let effects = [
            Effect::WaveformHarmonics,
            Effect::AmbientOffset,
            Effect::SubsurfaceDelay,
            Effect::TransmissionLaw,
            Effect::RefractionShift,
        ];
        let theta = [9.0, -9.0, 0.5, -0.3, -40.0, 250.0, -1.0, 30.0, 0.0];
        let steps = vec![1.0; theta.len()];
        let (t, outside) = project(&effects, &theta, &steps);
        assert_eq!(t, vec![9.0, -9.0, 1.0 / 3.0, -0.2, 0.0, 200.0, 0.0, 20.0, 0.0]);
        assert!((outside - (0.5 - 1.0 / 3.0 + 0.1 + 40.0 + 50.0 + 1.0 + 10.0)).abs() < 1e-9);
        assert_eq!(
            at_bounds(&effects, &t),
            [
                "third",
                "fifth",
                "ambient_offset",
                "subsurface_delay_mm",
                "transmission_albedo_power",
                "shift_columns_px"
            ]
        );
    }

    #[test]
    fn the_model_kept_stops_at_the_last_step_that_recovers_worse_beyond_noise() {
        let base = [20.0, -21.0, 19.0, -20.0, 22.0];
        let better = [10.0, -11.0, 9.0, -10.0, 12.0];
        let within_noise = [20.5, -20.0, 19.5, -21.0, 21.0];
        let worse = [30.0, -31.0, 29.0, -30.0, 32.0];
        assert_eq!(steps_recovering_no_worse(&base, &[]), 0);
        assert_eq!(steps_recovering_no_worse(&base, &[&better, &better]), 2);
        assert_eq!(steps_recovering_no_worse(&base, &[&within_noise, &better]), 2);
        assert_eq!(steps_recovering_no_worse(&base, &[&better, &base, &better]), 1);
        assert_eq!(steps_recovering_no_worse(&base, &[&worse, &better]), 0);
        let unknown = [f64::NAN; 5];
        assert_eq!(steps_recovering_no_worse(&base, &[&unknown, &better]), 0);
        assert_eq!(steps_recovering_no_worse(&unknown, &[&better]), 0);
        assert_eq!(steps_recovering_no_worse(&base, &[&better[..4]]), 0);
    }

    #[test]
    fn golden_section_finds_a_minimum() {
        let (x, _) = golden(&|x| (x - 0.3).powi(2), -1.0, 2.0, 40);
        assert!((x - 0.3).abs() < 1e-4);
    }

    #[test]
    fn the_audits_coarse_decoder_reads_single_surfaces_within_half_a_millimetre() {
        let w = Waveform::Harmonics {
            third: 0.15,
            fifth: -0.04,
        };
        let s = Sensor::with_decode_table_len(30e6, w, AUDIT_DECODE_TABLE_LEN);
        let r = s.unambiguous_range_mm();
        for k in 0..1009 {
            let d = r * k as f64 / 1009.0;
            let got = s.decode(s.buckets(2.0, d)).unwrap_or(f64::NAN);
            assert!(s.wrapped_difference_mm(got, d).abs() < 0.5, "d {d} read {got}");
        }
    }

    #[test]
    fn effects_map_to_model_options() {
        let base = ForwardModel::paper(Sensor::sr4000());
        let m = build_model(
            &base,
            &[
                Effect::TransmissionLaw,
                Effect::RefractionShift,
                Effect::WaveformHarmonics,
            ],
            &[0.0, 2.0, -1.0, -0.1, 0.02],
            2,
        );
        assert_eq!(m.options.transmission_albedo_power, 0.0);
        assert_eq!(m.options.refraction_shift_px, [2.0, -1.0]);
        assert_eq!(
            m.sensor.waveform,
            Waveform::Harmonics {
                third: -0.1,
                fifth: 0.02
            }
        );
    }
}
