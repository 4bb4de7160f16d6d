"""Core of the physically rendered CW-ToF set: a pinhole SR4000-like sensor
and a thin diffuse transmitter for Mitsuba 3 + mitransient, scene building,
transient rendering, the transient -> CW-ToF conversion, sensor noise and the
analytic ground truth.

Coordinates: the world frame IS the camera's optical frame (x right, y down,
z forward), metres. The camera and the emitter sit at the origin.

Pixel-centre convention (ROS / OpenCV): pixel (u, v) (column, row, integers
from 0) covers [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5] and its centre ray is
((u - cx) / fx, (v - cy) / fy, 1) with cx = (W - 1) / 2, cy = (H - 1) / 2,
fx = (W / 2) / tan(hfov / 2), fy = (H / 2) / tan(vfov / 2). The renderer
samples each pixel's square uniformly (box filter) with the same mapping.
"""

import math
import os

import numpy as np

os.environ.setdefault(
    "DRJIT_LIBLLVM_PATH", "/opt/llvm19/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_mono")
import mitransient  # noqa: E402,F401  (registers the transient plugins)

# ---------------------------------------------------------------- sensor ---
W, H = 176, 144
HFOV_DEG, VFOV_DEG = 44.0, 35.0
TX, TY = math.tan(math.radians(HFOV_DEG / 2)), math.tan(math.radians(VFOV_DEG / 2))
FX, FY = (W / 2) / TX, (H / 2) / TY
CX, CY = (W - 1) / 2, (H - 1) / 2
F_MOD = 30e6
C_LIGHT = 299_792_458.0
R_MM = C_LIGHT / (2 * F_MOD) * 1000.0  # unambiguous range, 4996.54 mm

# Transient binning (optical path length emitter -> scene -> sensor, metres).
BIN_M = 0.002
START_M = 0.5
BINS = 5750  # 0.5 .. 12.0 m of path (a direct return up to 6 m away)

# Emitter: a spot at the camera centre, flat within BEAM_DEG of the axis and
# falling off linearly in angle to 0 at CUTOFF_DEG (Mitsuba's `spot`); at the
# image corners (27.1 deg) it emits ~0.67 of the on-axis intensity.
EMIT_INTENSITY = 1.0
BEAM_DEG, CUTOFF_DEG = 2.0, 80.0

# IR gain and noise, fixed for the whole set (one calibration transfers).
# Reference: a white (albedo 1) Lambertian wall at 2000 mm, image centre:
# radiance L_ref = I * 1 / (pi * 2^2) -> IR_REF counts.
IR_REF_COUNTS = 10000.0
L_REF = EMIT_INTENSITY / (math.pi * 2.0 ** 2)
IR_GAIN = IR_REF_COUNTS / L_REF  # counts per unit of rendered radiance
# A and B (in counts) get independent Gaussian noise of variance
# NOISE_ALPHA * (S + NOISE_FLOOR), S = total collected light in counts
# (sum of the transient over all bins times IR_GAIN). NOISE_ALPHA is set so
# the reference wall has a depth standard deviation of REF_DEPTH_STD_MM.
REF_DEPTH_STD_MM = 10.0
NOISE_FLOOR = 100.0  # ambient / read floor, counts (1 % of the reference)
_sigma_ref = REF_DEPTH_STD_MM * 2 * math.pi / R_MM * IR_REF_COUNTS
NOISE_ALPHA = _sigma_ref ** 2 / (IR_REF_COUNTS + NOISE_FLOOR)
MIN_AMPLITUDE = 60.0  # counts (~5 sigma of the noise floor); below: depth 0 (invalid)

# Multi-frequency versions (issue 35, scenes.MF_FREQS_HZ): each frequency's
# phasor from the same transient, beside the 30 MHz depth and IR (phasor_frame).
PHASOR_STEP_COUNTS = 2.0  # phasor images are rounded to this (keeps the bags small; its std 0.58
# counts is < 5 % of the noise's at the floor, 12.5 counts)


def pixel_rays():
    """Unnormalised centre rays (x, y, 1), shape (H, W, 3)."""
    u = np.arange(W, dtype=np.float64)
    v = np.arange(H, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    return np.stack([(uu - CX) / FX, (vv - CY) / FY, np.ones_like(uu)], axis=-1)


def camera_info_k():
    return [FX, 0.0, CX, 0.0, FY, CY, 0.0, 0.0, 1.0]


class SR4000Sensor(mi.Sensor):
    """Pinhole at the origin looking down +z (optical frame), anisotropic
    focal lengths so the image spans exactly 44 x 35 degrees."""

    def __init__(self, props):
        super().__init__(props)

    def _ray(self, time, sample2):
        d = dr.normalize(mi.Vector3f((2 * sample2.x - 1) * TX, (2 * sample2.y - 1) * TY, 1.0))
        return mi.RayDifferential3f(mi.Point3f(0.0), d, time, [])

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        return self._ray(time, sample2), mi.Spectrum(1.0)

    def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
        return self._ray(time, sample2), mi.Spectrum(1.0)

    def bbox(self):
        return mi.ScalarBoundingBox3f(mi.ScalarPoint3f(0.0))

    def to_string(self):
        return "SR4000Sensor[]"


mi.register_sensor("sr4000", lambda props: SR4000Sensor(props))


class ThinDiffTrans(mi.BSDF):
    """Thin two-sided sheet: diffuse reflection of albedo `reflectance` and
    diffuse (cosine) transmission of albedo `transmittance` to the other side."""

    def __init__(self, props):
        super().__init__(props)
        self.r = float(props.get("reflectance", 0.5))
        self.t = float(props.get("transmittance", 0.5))
        refl = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
        tran = mi.BSDFFlags.DiffuseTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
        self.m_components = [refl, tran]
        self.m_flags = refl | tran

    def sample(self, ctx, si, sample1, sample2, active=True):
        cos_i = mi.Frame3f.cos_theta(si.wi)
        p_r = self.r / (self.r + self.t)
        reflect = sample1 < p_r
        wo = mi.warp.square_to_cosine_hemisphere(sample2)
        pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
        side = dr.select(cos_i >= 0, 1.0, -1.0)
        wo.z = wo.z * dr.select(reflect, side, -side)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = wo
        bs.pdf = pdf * dr.select(reflect, p_r, 1.0 - p_r)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(dr.select(
            reflect, mi.UInt32(int(mi.BSDFFlags.DiffuseReflection)),
            mi.UInt32(int(mi.BSDFFlags.DiffuseTransmission))))
        bs.sampled_component = dr.select(reflect, mi.UInt32(0), mi.UInt32(1))
        return bs, mi.Spectrum(self.r + self.t)

    def _value_pdf(self, si, wo):
        ci, co = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
        same = ci * co > 0
        p_r = self.r / (self.r + self.t)
        a = dr.abs(co) * dr.inv_pi
        return (dr.select(same, self.r, self.t) * a, dr.select(same, p_r, 1.0 - p_r) * a)

    def eval(self, ctx, si, wo, active=True):
        return mi.Spectrum(self._value_pdf(si, wo)[0])

    def pdf(self, ctx, si, wo, active=True):
        return self._value_pdf(si, wo)[1]

    def eval_pdf(self, ctx, si, wo, active=True):
        v, p = self._value_pdf(si, wo)
        return mi.Spectrum(v), p

    def to_string(self):
        return f"ThinDiffTrans[r={self.r}, t={self.t}]"


mi.register_bsdf("thin_difftrans", lambda props: ThinDiffTrans(props))

# ------------------------------------------------------------- geometry ---


def rotation(tilt_x_deg=0.0, tilt_y_deg=0.0, tilt_z_deg=0.0):
    """R = Rz @ Ry @ Rx (about the optical frame's axes)."""
    ax, ay, az = (math.radians(a) for a in (tilt_x_deg, tilt_y_deg, tilt_z_deg))
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def obj_frame(obj):
    """(centre m, rotation, half sizes m) of a scene object. Objects are
    dicts: kind 'rect' (size_mm [w, h], local normal +z) or 'box' (size_mm
    [w, h, d]); center_mm; tilt_x/y/z_deg."""
    c = np.asarray(obj["center_mm"], dtype=np.float64) / 1000.0
    r = rotation(obj.get("tilt_x_deg", 0.0), obj.get("tilt_y_deg", 0.0), obj.get("tilt_z_deg", 0.0))
    half = np.asarray(obj["size_mm"], dtype=np.float64) / 2000.0
    return c, r, half


def to_world(obj):
    c, r, half = obj_frame(obj)
    s = np.diag(list(half) + ([1.0] if obj["kind"] == "rect" else []) + [1.0])
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = c
    return mi.ScalarTransform4f((m @ s).tolist())


def bsdf_dict(mat):
    """Mitsuba BSDF of a material dict {model, xi, albedo}."""
    diffuse = {"type": "diffuse", "reflectance": {"type": "spectrum", "value": float(mat["albedo"])}}
    model = mat["model"]
    if model == "opaque":
        return {"type": "twosided", "bsdf": diffuse}
    if model == "mask":
        # passes light straight through with probability xi, else reflects
        # diffusely with albedo rho: the two-layer model physically
        return {"type": "mask", "opacity": {"type": "spectrum", "value": 1.0 - float(mat["xi"])},
                "bsdf": {"type": "twosided", "bsdf": diffuse}}
    if model == "difftrans":
        # thin diffuse transmitter: reflects (1 - xi) * rho, transmits xi
        # diffusely (cosine lobe) to the other side
        return {"type": "thin_difftrans", "reflectance": (1.0 - float(mat["xi"])) * float(mat["albedo"]),
                "transmittance": float(mat["xi"])}
    raise ValueError(model)


def build_scene(objects, materials):
    """objects: list of object dicts with 'material' (a key of materials)."""
    scene = {
        "type": "scene",
        "integrator": {"type": "transient_prbvolpath", "max_depth": 8, "rr_depth": 8},
        "sensor": {
            "type": "sr4000",
            "film": {"type": "transient_hdr_film", "width": W, "height": H,
                     "temporal_bins": BINS, "bin_width_opl": BIN_M, "start_opl": START_M,
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": 256},
        },
        "emitter": {
            "type": "spot", "intensity": {"type": "spectrum", "value": EMIT_INTENSITY},
            "cutoff_angle": CUTOFF_DEG, "beam_width": BEAM_DEG,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
        },
    }
    for i, obj in enumerate(objects):
        scene[f"obj{i:02d}"] = {
            "type": "rectangle" if obj["kind"] == "rect" else "cube",
            "to_world": to_world(obj),
            "bsdf": bsdf_dict(materials[obj["material"]]),
        }
    return mi.load_dict(scene)


def render_transient_ab(objects, materials, spp, seed, chunk_spp=1024, log=print):
    """Renders the scene and correlates its transient with the modulation.
    Returns float64 arrays (H, W): A, B (radiance units) and S = the total
    light collected (sum of the transient over all bins)."""
    (a, b), s = render_transient_phasors(objects, materials, spp, seed, [F_MOD], chunk_spp, log)
    return a[0], b[0], s


def correlation_weights(freqs_hz):
    """(BINS, 2K) weights: per frequency f_k (unambiguous range R_k = c/2f_k)
    the columns cos and sin of 2 pi (p/2)/R_k at each bin's centre p (path,
    mm), divided by the bin's sinc(pi w / 2R_k) (a return spread uniformly
    over a bin of width w correlates to that fraction of its centre value;
    dividing it out makes a bin stand for the path lengths inside it). Each
    frequency's phase wraps on its own (cos/sin are periodic in R_k)."""
    centres_mm = (START_M + (np.arange(BINS) + 0.5) * BIN_M) * 1000.0
    cols = []
    for f in freqs_hz:
        r_mm = C_LIGHT / (2 * f) * 1000.0
        phase = 2 * math.pi * (centres_mm / 2.0) / r_mm
        half = math.pi * (BIN_M * 1000.0) / (2 * r_mm)
        sinc = math.sin(half) / half
        cols += [np.cos(phase) / sinc, np.sin(phase) / sinc]
    return np.stack(cols, axis=1)


def render_transient_phasors(objects, materials, spp, seed, freqs_hz, chunk_spp=1024, log=print):
    """Renders the scene once and correlates its transient at every frequency
    of `freqs_hz`. Returns ((A, B), S): A and B float64 arrays (K, H, W), the
    in-phase and quadrature correlations (radiance units) at each frequency,
    and S (H, W) the total light collected (sum of the transient over all
    bins). The render's samples do not depend on the frequencies: the same
    seed gives the same A, B at 30 MHz whatever else is asked for."""
    scene = build_scene(objects, materials)
    integ = scene.integrator()
    k_f = len(freqs_hz)
    wts = np.concatenate([correlation_weights(freqs_hz), np.ones((BINS, 1))], axis=1)
    acc = np.zeros((H * W, 2 * k_f + 1))
    done = 0
    k = 0
    while done < spp:
        n = min(chunk_spp, spp - done)
        _, transient = integ.render(scene, seed=(seed * 1009 + k) % 2**32, spp=n)
        t = np.asarray(transient).reshape(H * W, BINS)
        acc += n * (t @ wts)
        del t, transient
        done += n
        k += 1
        log(f"    {done}/{spp} spp")
    acc = (acc / spp).T.reshape(2 * k_f + 1, H, W)
    return (acc[0:2 * k_f:2], acc[1:2 * k_f:2]), acc[2 * k_f]


# ----------------------------------------------------- CW-ToF readings ---


def tof_frame(a, b, s, rng):
    """Noisy CW-ToF readings from the rendered correlations.
    Returns (depth uint16 mm z, ir float32 counts)."""
    ac, bc, sc = a * IR_GAIN, b * IR_GAIN, s * IR_GAIN
    sigma = np.sqrt(NOISE_ALPHA * (np.maximum(sc, 0.0) + NOISE_FLOOR))
    if rng is not None:
        ac = ac + rng.standard_normal(ac.shape) * sigma
        bc = bc + rng.standard_normal(bc.shape) * sigma
    amp = np.hypot(ac, bc)
    d = np.mod(R_MM / (2 * math.pi) * np.arctan2(bc, ac), R_MM)
    z = d / np.linalg.norm(pixel_rays(), axis=-1)
    depth = np.round(z)
    depth[(amp < MIN_AMPLITUDE) | ~np.isfinite(depth)] = 0
    return depth.astype(np.uint16), amp.astype(np.float32)


def phasor_frame(a, b, s, rng):
    """One noisy phasor (in-phase, quadrature) at one frequency from its
    rendered correlations a, b and the total light s (H, W each), in counts,
    with the same noise model as tof_frame's A and B: N(0, alpha (S + floor))
    each, S = total collected light in counts (the same at every frequency:
    the buckets collect the same light). Returns float32 (H, W, 2), rounded to
    PHASOR_STEP_COUNTS (well below the noise: its floor's std is ~12.5 counts)."""
    ac, bc, sc = a * IR_GAIN, b * IR_GAIN, s * IR_GAIN
    sigma = np.sqrt(NOISE_ALPHA * (np.maximum(sc, 0.0) + NOISE_FLOOR))
    if rng is not None:
        ac = ac + rng.standard_normal(ac.shape) * sigma
        bc = bc + rng.standard_normal(bc.shape) * sigma
    out = np.stack([ac, bc], axis=-1)
    return (np.round(out / PHASOR_STEP_COUNTS) * PHASOR_STEP_COUNTS).astype(np.float32)


# --------------------------------------------------------- ground truth ---


def _hit_rect(rays, c, r, half):
    n = r[:, 2]
    dn = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (c @ n) / dn
    p = rays * t[..., None] - c
    ok = (t > 0) & (np.abs(p @ r[:, 0]) <= half[0]) & (np.abs(p @ r[:, 1]) <= half[1])
    return np.where(ok, t, np.inf)


def _hit_box(rays, c, r, half):
    # slab test in the box's frame; the ray starts at the origin
    o = r.T @ (-c)
    d = rays @ r  # (H, W, 3): local directions
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) / d
        t2 = (half - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    ok = (tmax >= tmin) & (tmax > 0)
    t = np.where(tmin > 0, tmin, tmax)
    return np.where(ok, t, np.inf)


def ground_truth(foreground, material_ids):
    """z-depth (m, NaN where only background) and material id (0 background)
    of the nearest foreground object along each pixel's centre ray.
    Rays are (x, y, 1), so the ray parameter IS the z-depth."""
    rays = pixel_rays()
    best = np.full((H, W), np.inf)
    mat = np.zeros((H, W), dtype=np.uint8)
    for obj in foreground:
        c, r, half = obj_frame(obj)
        t = (_hit_rect if obj["kind"] == "rect" else _hit_box)(rays, c, r, half)
        closer = t < best
        best[closer] = t[closer]
        mat[closer] = material_ids[obj["material"]]
    depth = np.where(np.isfinite(best), best, np.nan).astype(np.float32)
    return depth, mat
