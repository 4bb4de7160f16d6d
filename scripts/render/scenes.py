"""The scenes of the rendered set, drawn from seeded ranges (one seed per
bag). Distances in mm, optical frame (x right, y down, z forward)."""

import math

import numpy as np

MODEL_NOTES = {
    "mask": "Mitsuba mask BSDF: each layer passes light straight through with probability xi "
            "(opacity 1 - xi) and otherwise reflects diffusely (two-sided diffuse, albedo rho): "
            "the paper's two-layer model, physically",
    "difftrans": "thin diffuse transmitter (scripts/render/tofcore.py ThinDiffTrans): each layer reflects "
                 "diffusely with albedo (1 - xi) * rho and transmits a fraction xi diffusely (cosine lobe) "
                 "to its other side; nothing passes straight through",
    "mixed": "per material, see [[materials]].model: mask (straight pass-through with probability xi) "
             "or difftrans (diffuse transmission xi, reflection (1 - xi) * rho)",
}
HIGH_SPP = 8192
COVERAGE_SPP = 2048
TAN_H, TAN_V = math.tan(math.radians(22)), math.tan(math.radians(17.5))


def mat(id_, name, xi, albedo, model):
    return {"id": id_, "name": name, "xi": round(float(xi), 4), "albedo": round(float(albedo), 4), "model": model}


def rect(center, size, tx=0.0, ty=0.0, tz=0.0, material="bg0"):
    return {"kind": "rect", "center_mm": [float(c) for c in center], "size_mm": [float(s) for s in size],
            "tilt_x_deg": float(tx), "tilt_y_deg": float(ty), "tilt_z_deg": float(tz), "material": material}


def box(center, size, tx=0.0, ty=0.0, tz=0.0, material="bg0"):
    o = rect(center, size, tx, ty, tz, material)
    o["kind"] = "box"
    return o


# ------------------------------------------------------------ backgrounds ---

def bg_wall(z, albedo, tilt_y=0.0):
    mats = {"bg0": {"albedo": round(float(albedo), 4), "model": "opaque", "xi": 0.0}}
    return [rect([0, 0, z], [9000, 9000], ty=tilt_y)], mats, \
        f"planar wall at {z:.0f} mm (tilt_y {tilt_y:.1f} deg), albedo {albedo:.3f}"


def bg_boxes_on_wall(rng, z, albedo_range=(0.3, 1.0), n_boxes=None):
    wall_alb = rng.uniform(*albedo_range)
    objs, mats, _ = bg_wall(z, wall_alb)
    n = int(rng.integers(1, 4)) if n_boxes is None else n_boxes
    slots = rng.permutation(4)[:n]
    for i, slot in enumerate(slots):
        w, h, d = rng.uniform(250, 600), rng.uniform(250, 600), rng.uniform(150, 400)
        # boxes stand against the wall, spread over the lower/side parts of the view
        x = (-0.75 + 0.5 * slot) * TAN_H * z + rng.uniform(-100, 100)
        y = rng.uniform(0.1, 0.6) * TAN_V * z
        key = f"bg{i + 1}"
        mats[key] = {"albedo": round(float(rng.uniform(*albedo_range)), 4), "model": "opaque", "xi": 0.0}
        objs.append(box([x, y, z - d / 2], [w, h, d], tz=rng.uniform(-10, 10), material=key))
    return objs, mats, f"wall at {z:.0f} mm (albedo {wall_alb:.3f}) with {n} box(es) standing against it"


def bg_corner(rng, albedo_range=(0.3, 1.0)):
    zc = rng.uniform(2600, 3400)
    xc = rng.uniform(-300, 300)
    a, b = rng.uniform(30, 50), rng.uniform(30, 50)
    al, ar = rng.uniform(*albedo_range), rng.uniform(*albedo_range)
    L = 7000
    dl = np.array([-math.cos(math.radians(a)), 0, -math.sin(math.radians(a))])
    dr_ = np.array([math.cos(math.radians(b)), 0, -math.sin(math.radians(b))])
    c = np.array([xc, 0, zc])
    mats = {"bg0": {"albedo": round(float(al), 4), "model": "opaque", "xi": 0.0},
            "bg1": {"albedo": round(float(ar), 4), "model": "opaque", "xi": 0.0}}
    objs = [rect(c + dl * L / 2, [L, 9000], ty=-a, material="bg0"),
            rect(c + dr_ * L / 2, [L, 9000], ty=b, material="bg1")]
    return objs, mats, (f"corner of two walls (vertical edge at x {xc:.0f}, z {zc:.0f} mm), walls "
                        f"{a:.1f} and {b:.1f} deg from fronto-parallel, albedo {al:.3f} / {ar:.3f}")


def bg_table(rng, albedo_range=(0.3, 1.0)):
    zw = rng.uniform(2600, 3400)
    yt = rng.uniform(300, 450)  # table top below the optical axis
    ze = rng.uniform(900, 1400)  # the table's front edge
    aw, at, af = (rng.uniform(*albedo_range) for _ in range(3))
    mats = {"bg0": {"albedo": round(float(aw), 4), "model": "opaque", "xi": 0.0},
            "bg1": {"albedo": round(float(at), 4), "model": "opaque", "xi": 0.0},
            "bg2": {"albedo": round(float(af), 4), "model": "opaque", "xi": 0.0}}
    objs = [rect([0, 0, zw], [9000, 9000], material="bg0"),
            rect([0, yt, (ze + zw) / 2], [4000, zw - ze], tx=90, material="bg1"),  # table top
            rect([0, yt + 700, zw / 2], [9000, zw], tx=90, material="bg2")]  # floor
    return objs, mats, (f"wall at {zw:.0f} mm, a table top {yt:.0f} mm below the axis from z {ze:.0f} mm "
                        f"(its front edge) to the wall, floor {yt + 700:.0f} mm below; albedo "
                        f"{aw:.3f} / {at:.3f} / {af:.3f}")


def near_wall(bg):
    """Smallest z of the background along the central part of the view."""
    zs = []
    for o in bg:
        if o["kind"] == "rect" and abs(o.get("tilt_x_deg", 0)) < 1:
            zs.append(o["center_mm"][2] - abs(math.sin(math.radians(o.get("tilt_y_deg", 0)))) * 1200)
        elif o["kind"] == "box":
            zs.append(o["center_mm"][2] - o["size_mm"][2] / 2)
    return min(zs)


# ------------------------------------------------------------ foreground ---

def sheet(rng, z, xslot, mat_key, tilted, size=None, max_tilt=45.0, min_tilt=0.0):
    w, h = size if size is not None else (rng.uniform(250, 400), rng.uniform(300, 400))
    x = xslot * TAN_H * z + rng.uniform(-40, 40)
    y = rng.uniform(-0.25, 0.25) * TAN_V * z
    if tilted:
        t = rng.uniform(min_tilt, max_tilt) * rng.choice([-1, 1])
        if rng.uniform() < 0.6:
            tx, ty = rng.uniform(-5, 5), t
        else:
            tx, ty = t, rng.uniform(-5, 5)
    else:
        tx, ty = rng.uniform(-3, 3), rng.uniform(-3, 3)
    return rect([x, y, z], [w, h], tx=tx, ty=ty, tz=rng.uniform(-5, 5), material=mat_key)


def opaque_box(rng, z, xslot, mat_key):
    w, h, d = rng.uniform(150, 350), rng.uniform(150, 350), rng.uniform(150, 350)
    x = xslot * TAN_H * z + rng.uniform(-40, 40)
    y = rng.uniform(-0.2, 0.3) * TAN_V * z
    return box([x, y, z + d / 2], [w, h, d], tx=rng.uniform(-5, 5), ty=rng.uniform(-30, 30), material=mat_key)


# ------------------------------------------------------------ named bags ---

def paper(name, seed, xi, desc):
    rng = np.random.default_rng(seed)
    bg, bgm, bgd = bg_wall(2000, 1.0)
    mats = {"sheet": mat(1, "paper_sheet", xi, 0.6, "mask")}
    stages = []
    for z in (500, 750, 1000, 1750):
        o = rect([rng.uniform(-20, 20), rng.uniform(-20, 20), z], [240, 310],
                 tx=rng.uniform(-3, 3), ty=rng.uniform(-3, 3), material="sheet")
        stages.append({"frames": 2, "objects": [o]})
    return dict(name=name, seed=seed, description=desc, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages)


def tilted_gray(seed=31):
    rng = np.random.default_rng(seed)
    z = rng.uniform(2400, 3000)
    bg, bgm, bgd = bg_boxes_on_wall(rng, z, albedo_range=(0.3, 0.6), n_boxes=2)
    xi, rho = rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.7)
    mats = {"sheet": mat(1, "tilted_sheet", xi, rho, "mask")}
    stages = []
    for zs in sorted(rng.uniform(800, near_wall(bg) - 450, size=4)):
        stages.append({"frames": 2, "objects": [sheet(rng, zs, rng.uniform(-0.2, 0.2), "sheet", True,
                                                      min_tilt=20, max_tilt=45)]})
    return dict(name="tilted_gray", seed=seed, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                description=f"a sheet (xi {xi:.3f}, rho {rho:.3f}) tilted 20-45 deg before gray boxes on a gray wall, 4 poses")


def two_materials(seed=41):
    rng = np.random.default_rng(seed)
    z = rng.uniform(2400, 3200)
    bg, bgm, bgd = bg_wall(z, rng.uniform(0.5, 1.0))
    n = 3
    mats = {"m1": mat(1, "sheet_low_xi", rng.uniform(0.45, 0.65), rng.uniform(0.3, 0.7), "mask"),
            "m2": mat(2, "sheet_high_xi", rng.uniform(0.85, 0.95), rng.uniform(0.3, 0.7), "mask"),
            "m3": mat(3, "sheet_mid_xi", rng.uniform(0.3, 0.45), rng.uniform(0.3, 0.7), "mask")}
    stages = []
    for p in range(3):
        keys = ["m1", "m2", "m3"][: (2 if p == 0 else n)]
        rng.shuffle(keys)
        objs = []
        for i, k in enumerate(keys):
            zs = rng.uniform(1600 if len(keys) == 3 else 1200, z - 500)
            slot = (-0.55 + 1.1 * i / (len(keys) - 1)) if len(keys) > 1 else 0
            objs.append(sheet(rng, zs, slot, k, rng.uniform() < 0.5, size=(rng.uniform(250, 320), rng.uniform(300, 400)),
                              max_tilt=30))
        stages.append({"frames": 2, "objects": objs})
    return dict(name="two_materials", seed=seed, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                description="two (first pose) or three (later poses) sheets of different xi side by side, 3 poses")


def opaque_and_translucent(seed=51):
    rng = np.random.default_rng(seed)
    z = rng.uniform(2300, 3000)
    bg, bgm, bgd = bg_wall(z, rng.uniform(0.3, 1.0))
    mats = {"sheet": mat(1, "sheet", rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.7), "mask"),
            "box": mat(2, "opaque_box", 0.0, rng.uniform(0.3, 0.8), "opaque")}
    stages = []
    for p in range(3):
        zs = rng.uniform(1000, z - 600)
        zb = float(np.clip(zs + rng.uniform(-300, 300), 900, z - 600))
        side = rng.choice([-1, 1])
        objs = [sheet(rng, zs, side * 0.3, "sheet", p > 0, max_tilt=35),
                opaque_box(rng, zb, -side * 0.35, "box")]
        stages.append({"frames": 2, "objects": objs})
    return dict(name="opaque_and_translucent", seed=seed, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                description="an opaque box placed beside a translucent sheet, 3 poses")


def corner_background(seed=61):
    rng = np.random.default_rng(seed)
    bg, bgm, bgd = bg_corner(rng)
    mats = {"sheet": mat(1, "sheet", rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.7), "mask")}
    stages = []
    for p in range(3):
        zs = rng.uniform(900, 1800)
        stages.append({"frames": 2, "objects": [sheet(rng, zs, rng.uniform(-0.2, 0.2), "sheet", p == 2, max_tilt=35)]})
    return dict(name="corner_background", seed=seed, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                description="a translucent sheet before the corner of two walls, 3 poses")


def calibration_sequence(seed=71):
    rng = np.random.default_rng(seed)
    bg, bgm, bgd = bg_wall(3300, 1.0)
    xi = rng.uniform(0.6, 0.9)
    rho = rng.uniform(0.4, 0.7)
    mats = {"sheet": mat(1, "calibration_sheet", xi, rho, "mask")}
    stages = [{"frames": 2, "objects": [rect([0, 0, z], [400, 400], material="sheet")]}
              for z in range(700, 2601, 190)]
    return dict(name="calibration_sequence", seed=seed, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                description=(f"model-validation protocol (paper Sec. V-A): white wall at 3300 mm, a fronto-parallel "
                             f"400 x 400 mm sheet (xi {xi:.4f}, rho {rho:.4f}) centred on the axis at 11 known "
                             f"distances 700..2600 mm step 190"))


def white_wall_lin(seed=81):
    bg, bgm, bgd = bg_wall(2000, 1.0)
    return dict(name="white_wall_lin", seed=seed, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials={}, stages=[],
                description="empty white (albedo 1) fronto-parallel wall at 2000 mm, 10 frames, for calibrate-lin")


def difftrans_sheet(seed=91):
    rng = np.random.default_rng(seed)
    z = rng.uniform(2200, 2800)
    bg, bgm, bgd = bg_wall(z, rng.uniform(0.5, 1.0))
    mats = {"sheet": mat(1, "diffuse_transmitter", rng.uniform(0.5, 0.8), rng.uniform(0.4, 0.7), "difftrans")}
    stages = []
    for p, zs in enumerate(sorted(rng.uniform(700, z - 500, size=3))):
        stages.append({"frames": 2, "objects": [sheet(rng, zs, rng.uniform(-0.2, 0.2), "sheet", p == 1, max_tilt=40)]})
    return dict(name="difftrans_sheet", seed=seed, model="difftrans", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                description="translucency model (b): a thin diffuse transmitter (light crossing it is scattered, "
                            "not passed straight) before a wall, 3 poses")


HOLLOW_SEED = 96


def hollow_object():
    """One hollow bin (a box of a translucent material, open nowhere): its material and size."""
    rng = np.random.default_rng(HOLLOW_SEED)
    m = mat(1, "hollow_bin", rng.uniform(0.55, 0.8), rng.uniform(0.4, 0.7), "mask")
    return m, [float(rng.uniform(250, 350)), float(rng.uniform(220, 320)), float(rng.uniform(150, 300))]


def hollow_bin(name, seed, n_poses):
    """The hollow bin face-on at n_poses distances before a wall: three returns (its front wall,
    its back wall seen through the front, the wall through both)."""
    m, size = hollow_object()
    rng = np.random.default_rng(seed)
    zw = rng.uniform(2600, 3300)
    bg, bgm, bgd = bg_wall(zw, rng.uniform(0.6, 1.0))
    lo, hi = 800.0, zw - size[2] - 500.0
    stages = []
    for k in range(n_poses):
        zf = lo + (hi - lo) * (k + 0.5 + rng.uniform(-0.3, 0.3)) / n_poses
        o = box([rng.uniform(-60, 60), rng.uniform(-60, 60), zf + size[2] / 2], size,
                tx=rng.uniform(-3, 3), ty=rng.uniform(-3, 3), tz=rng.uniform(-3, 3), material="bin")
        stages.append({"frames": 2, "objects": [o]})
    zs = ", ".join(f"{st['objects'][0]['center_mm'][2] - size[2] / 2:.0f}" for st in stages)
    return dict(name=name, seed=seed, model="mask", spp=HIGH_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials={"bin": m}, stages=stages,
                description=(f"a hollow bin ({size[0]:.0f} x {size[1]:.0f} x {size[2]:.0f} mm, walls xi "
                             f"{m['xi']:.4f}, rho {m['albedo']:.4f}) face-on before {bgd}, its front at {zs} mm"))


# ---------------------------------------------------------- coverage set ---

def bg_depth(bg):
    import tofcore as tc
    z, _ = tc.ground_truth(bg, {o["material"]: 1 for o in bg})
    return z.astype(np.float64) * 1000.0


def fits(obj, bgz, margin=200.0):
    """The object is in view (>= 300 px), everywhere at least `margin` mm
    before the background and at least 500 mm from the camera."""
    import tofcore as tc
    z, m = tc.ground_truth([obj], {obj["material"]: 1})
    px = m > 0
    if px.sum() < 300:
        return False
    zz = z[px].astype(np.float64) * 1000.0
    return bool(zz.min() > 500 and np.all(bgz[px] - zz > margin))


def drawn_background(rng, wall_from_mm, boxes_from_mm):
    """A background of a drawn kind (wall, boxes on a wall, corner, table) and the
    farthest an object may stand before it: `(kind, bg, bgm, bgd, bgz, zmax)`."""
    kind = ["wall", "boxes_on_wall", "corner", "table"][int(rng.integers(4))]
    if kind == "wall":
        bg, bgm, bgd = bg_wall(rng.uniform(wall_from_mm, 3500), rng.uniform(0.3, 1.0), tilt_y=rng.uniform(-20, 20))
    elif kind == "boxes_on_wall":
        bg, bgm, bgd = bg_boxes_on_wall(rng, rng.uniform(boxes_from_mm, 3500))
    elif kind == "corner":
        bg, bgm, bgd = bg_corner(rng)
    else:
        bg, bgm, bgd = bg_table(rng)
    bgz = bg_depth(bg)
    zmax = float(np.nanmin(bgz[30:114, 35:141])) - 300
    return kind, bg, bgm, bgd, bgz, zmax


def drawn_sheets(rng, n_mat):
    """`n_mat` sheet materials (xi 0.3-0.95, albedo 0.3-0.7), the first a diffuse
    transmitter one time in five: `{"m1": ..., ...}`."""
    use_dt = rng.uniform() < 0.2
    mats = {}
    for m in range(n_mat):
        model = "difftrans" if (use_dt and m == 0) else "mask"
        mats[f"m{m + 1}"] = mat(m + 1, f"sheet_{m + 1}", rng.uniform(0.3, 0.95), rng.uniform(0.3, 0.7), model)
    return mats


def draw(i):
    seed = 1000 + i
    rng = np.random.default_rng(seed)
    kind, bg, bgm, bgd, bgz, zmax = drawn_background(rng, 1800, 2200)
    n_mat = int(rng.integers(1, 4))
    mats = drawn_sheets(rng, n_mat)
    with_box = rng.uniform() < 0.4
    if with_box:
        mats["box"] = mat(n_mat + 1, "opaque_box", 0.0, rng.uniform(0.3, 0.8), "opaque")
    stages = []
    for s in range(int(rng.integers(2, 4))):
        keys = [f"m{m + 1}" for m in range(n_mat)]
        if n_mat > 1 and rng.uniform() < 0.3:
            keys = keys[:-1]
        if with_box and (s > 0 or rng.uniform() < 0.5):
            keys.append("box")
        rng.shuffle(keys)
        objs = []
        for j, k in enumerate(keys):
            zlo = min(700 + 400 * (len(keys) - 1), zmax - 200)
            for attempt in range(40):
                zs = rng.uniform(zlo, max(zlo + 50, zmax - 25 * attempt))
                slot = (-0.55 + 1.1 * j / (len(keys) - 1)) if len(keys) > 1 else rng.uniform(-0.2, 0.2)
                if k == "box":
                    o = opaque_box(rng, zs, slot, k)
                else:
                    o = sheet(rng, zs, slot, k, rng.uniform() < 0.5)
                if fits(o, bgz):
                    objs.append(o)
                    break
        stages.append({"frames": int(rng.integers(1, 3)), "objects": objs})
    model = "mixed" if any(m["model"] == "difftrans" for m in mats.values()) else "mask"
    return dict(name=f"draw_{i:02d}", seed=seed, model=model, spp=COVERAGE_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                spp_note=f"coverage set: {COVERAGE_SPP} spp (fewer than the named bags' {HIGH_SPP}) to keep render time manageable; "
                         "Monte Carlo noise of the render adds a little to the sensor noise, most on translucent pixels",
                description=f"coverage draw {i}: {kind} background, {n_mat} translucent material(s)"
                            f"{', an opaque box' if with_box else ''}, {len(stages)} stages")


# ------------------------------------------------- material calibration ---
# Paper Sec. V-A: a material is calibrated once, as a camera is: a sheet of
# only that material before a plain wall at several known distances. One
# bag per translucent material of two_materials and opaque_and_translucent,
# the same xi, albedo and BSDF model as in that scene. Every calib_* bag
# stands before the same wall (the rig, one seed), so its render is shared.

CALIB_SPP = 2048
CALIB_RIG_SEED = 300
CALIB_SHEET_MM = 400.0


def calib_rig():
    """The calibration wall: plain, fronto-parallel, drawn once."""
    rng = np.random.default_rng(CALIB_RIG_SEED)
    return bg_wall(rng.uniform(2800, 3400), rng.uniform(0.7, 1.0))


def calibration(scene, key, seed, n_stages=4):
    src = scene()
    m = dict(src["materials"][key])
    if m["model"] == "opaque":
        raise ValueError(f"{src['name']}: {key} is opaque")
    rng = np.random.default_rng(seed)
    bg, bgm, bgd = calib_rig()
    zw = bg[0]["center_mm"][2]
    lo, hi = 800.0, zw - 600.0
    tilted = int(rng.integers(n_stages))
    stages = []
    for k in range(n_stages):  # one distance in the middle 60 % of each of n bands of [lo, hi], nearest first
        z = lo + (hi - lo) * (k + 0.5 + rng.uniform(-0.3, 0.3)) / n_stages
        if k == tilted:
            t = rng.uniform(20, 35) * rng.choice([-1, 1])
            tx, ty = (0.0, t) if rng.uniform() < 0.5 else (t, 0.0)
        else:
            tx, ty = rng.uniform(-2, 2), rng.uniform(-2, 2)
        o = rect([rng.uniform(-50, 50), rng.uniform(-50, 50), z], [CALIB_SHEET_MM, CALIB_SHEET_MM],
                 tx=tx, ty=ty, tz=rng.uniform(-2, 2), material=key)
        stages.append({"frames": 2, "objects": [o]})
    t = stages[tilted]["objects"][0]
    tilt = t["tilt_x_deg"] if abs(t["tilt_x_deg"]) > abs(t["tilt_y_deg"]) else t["tilt_y_deg"]
    axis = "x" if abs(t["tilt_x_deg"]) > abs(t["tilt_y_deg"]) else "y"
    zs = ", ".join(f"{st['objects'][0]['center_mm'][2]:.0f}" for st in stages)
    return dict(name=f"calib_{src['name']}_{m['name']}", seed=seed, model=m["model"], spp=CALIB_SPP,
                background=bg, background_materials=bgm, background_description=bgd, materials={key: m},
                stages=stages,
                sidecar={"calibrates_scene": src["name"], "calibrates_material": m["name"],
                         "calibrates_material_id": m["id"]},
                spp_note=f"calibration set: {CALIB_SPP} spp; Monte Carlo noise of the render on the sheet is at most "
                         "about a fifth of one frame's sensor noise there (checked at 16384 spp)",
                description=(f"per-material calibration (paper Sec. V-A) for {src['name']}, material {m['id']} "
                             f"'{m['name']}' (xi {m['xi']:.4f}, rho {m['albedo']:.4f}, {m['model']}): only that "
                             f"material, a {CALIB_SHEET_MM:.0f} x {CALIB_SHEET_MM:.0f} mm sheet before {bgd}, "
                             f"at {n_stages} distances ({zs} mm), stage {tilted} tilted {tilt:.1f} deg about {axis}"))


def calibration_specs():
    return [calibration(two_materials, "m1", 301), calibration(two_materials, "m2", 302),
            calibration(two_materials, "m3", 303), calibration(opaque_and_translucent, "sheet", 304),
            calibration(difftrans_sheet, "sheet", 305)]


# ---------------------------------------------------------------- videos ---
# Continuous motion at the camera's rate: after the background frames every
# frame is a new pose of every object (one render each). Each object moves
# at a constant speed (20-50 mm per frame) along a straight or gently curved
# path and turns a little per frame; paths are drawn, and redrawn until the
# object stays in view, before the background and clear of the others.

VIDEO_SPP = 4096
VIDEO_RATE_HZ = 30


def surface_points(obj, n=12):
    """Points on an object's surface (mm), an n x n grid per face."""
    c = np.asarray(obj["center_mm"], dtype=np.float64)
    import tofcore as tc
    r = tc.rotation(obj["tilt_x_deg"], obj["tilt_y_deg"], obj["tilt_z_deg"])
    g = np.linspace(-0.5, 0.5, n)
    uu, vv = (a.ravel() for a in np.meshgrid(g, g))
    if obj["kind"] == "rect":
        local = np.stack([uu * obj["size_mm"][0], vv * obj["size_mm"][1], 0 * uu], axis=-1)
    else:
        w = np.asarray(obj["size_mm"], dtype=np.float64)
        faces = []
        for ax in range(3):
            for side in (-0.5, 0.5):
                f = np.zeros((uu.size, 3))
                a1, a2 = [i for i in range(3) if i != ax]
                f[:, ax], f[:, a1], f[:, a2] = side * w[ax], uu * w[a1], vv * w[a2]
                faces.append(f)
        local = np.concatenate(faces)
    return local @ r.T + c


def apart(a, b, clearance=80.0):
    pa, pb = surface_points(a), surface_points(b)
    d2 = ((pa[:, None, :] - pb[None, :, :]) ** 2).sum(-1)
    return bool(d2.min() > clearance ** 2)


def path(rng, n, mid, speed, tilts0):
    """n poses (centre, tilts) centred on `mid`: constant speed, direction
    turning at a constant rate about the vertical, tilts at constant rates."""
    az, el = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(-25, 25))
    turn = math.radians(rng.uniform(-2.0, 2.0))  # deg per frame: straight to gently curved
    rates = [rng.uniform(-1.5, 1.5), rng.uniform(-2.0, 2.0), rng.uniform(-1.0, 1.0)]  # tilt x, y, z per frame
    pts = [np.zeros(3)]
    for k in range(1, n):
        a = az + turn * (k - 0.5)
        pts.append(pts[-1] + speed * np.array([math.cos(a) * math.cos(el), math.sin(el), math.sin(a) * math.cos(el)]))
    pts = np.array(pts)
    pts += np.asarray(mid) - pts[(n - 1) // 2]
    k0 = (n - 1) // 2
    poses = [(pts[k], [t + r * (k - k0) for t, r in zip(tilts0, rates)]) for k in range(n)]
    info = {"speed_mm_per_frame": round(float(speed), 2), "heading_deg": round(math.degrees(az), 2),
            "elevation_deg": round(math.degrees(el), 2), "turn_deg_per_frame": round(math.degrees(turn), 3),
            "tilt_rates_deg_per_frame": [round(float(r), 3) for r in rates]}
    return poses, info


def video(i, n_tries=400):
    seed = 2000 + i
    rng = np.random.default_rng(seed)
    kind, bg, bgm, bgd, bgz, zmax = drawn_background(rng, 2200, 2400)
    n_mat = int(rng.integers(2, 4))
    mats = drawn_sheets(rng, n_mat)
    mats["box"] = mat(n_mat + 1, "opaque_box", 0.0, rng.uniform(0.3, 0.8), "opaque")
    n = int(rng.integers(20, 26))  # moving frames (at most 35 frames: a bag stays under ~4 MB)
    keys = [f"m{m + 1}" for m in range(n_mat)] + ["box"]
    rng.shuffle(keys)
    tracks, placed = [], []  # placed: per object, its n poses as objects
    for j, k in enumerate(keys):
        slot = -0.5 + 1.0 * j / (len(keys) - 1)
        for attempt in range(n_tries):
            zm = rng.uniform(900, zmax)
            mid = [slot * TAN_H * zm + rng.uniform(-80, 80), rng.uniform(-0.25, 0.25) * TAN_V * zm, zm]
            if k == "box":
                size = [rng.uniform(150, 350), rng.uniform(150, 350), rng.uniform(150, 350)]
                tilts0 = [rng.uniform(-5, 5), rng.uniform(-30, 30), 0.0]
            else:
                size = [rng.uniform(250, 400), rng.uniform(300, 400)]
                if rng.uniform() < 0.5:
                    t = rng.uniform(0, 40) * rng.choice([-1, 1])
                    tilts0 = [rng.uniform(-5, 5), t, rng.uniform(-5, 5)] if rng.uniform() < 0.6 else \
                        [t, rng.uniform(-5, 5), rng.uniform(-5, 5)]
                else:
                    tilts0 = [rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-5, 5)]
            poses, info = path(rng, n, mid, rng.uniform(20, 50), tilts0)
            make = box if k == "box" else rect
            objs = [make(c, size, tx=t[0], ty=t[1], tz=t[2], material=k) for c, t in poses]
            for o in objs:
                o["object"] = mats[k]["name"]
            if k != "box" and any(max(abs(o["tilt_x_deg"]), abs(o["tilt_y_deg"])) > 50 for o in objs):
                continue
            if not all(fits(o, bgz) for o in objs):
                continue
            if not all(apart(o, other[f]) for other in placed for f, o in enumerate(objs)):
                continue
            placed.append(objs)
            m = mats[k]
            tracks.append({"object": objs[0]["object"], "material": m["id"], "kind": objs[0]["kind"],
                           "size_mm": [round(float(x), 1) for x in size], "attempts": attempt + 1, **info,
                           "first_center_mm": [round(float(x), 1) for x in objs[0]["center_mm"]],
                           "last_center_mm": [round(float(x), 1) for x in objs[-1]["center_mm"]]})
            break
        else:
            raise RuntimeError(f"video_{i:02d}: no path for {k} in {n_tries} draws")
    stages = [{"frames": 1, "objects": [p[f] for p in placed]} for f in range(n)]
    model = "mixed" if any(m["model"] == "difftrans" for m in mats.values()) else "mask"
    return dict(name=f"video_{i:02d}", seed=seed, model=model, spp=VIDEO_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                tracks=tracks, frame_rate_hz=VIDEO_RATE_HZ, zstd_level=19,
                sidecar={"moving_frames": n, "motion_note": (
                    "every frame after the background frames is its own pose (one stage per frame, one render each); "
                    "[[tracks]] gives each object's path: constant speed, heading turning at a constant rate about "
                    "the vertical, tilts changing at constant rates, centred on the middle frame; "
                    "stages.objects.object names the object")},
                spp_note=f"videos: {VIDEO_SPP} spp per frame (every frame is its own render)",
                description=f"video {i}: {kind} background, {n_mat} translucent sheet(s) and an opaque box, each "
                            f"moving on its own smooth path at {VIDEO_RATE_HZ} Hz, {n} moving frames")


# ------------------------------------------------ multi-frequency versions ---
MF_FREQS_HZ = [20e6, 50e6, 100e6]
# draws whose scenes hold several translucent materials and an opaque box (draw_03: three mask
# sheets and a box, draw_06: two and a box, draw_11: three and a box)
MF_DRAWS = [3, 6, 11]


def multi_frequency(spec):
    """The same scene (seed, geometry, spp, so the same render and the same 30 MHz depth and IR)
    with the phasors at MF_FREQS_HZ written beside them (issue 35)."""
    out = dict(spec)
    out["name"] = "mf_" + spec["name"]
    out["frequencies_hz"] = list(MF_FREQS_HZ)
    out["description"] = (spec["description"] + "; multi-frequency: phasors at "
                          + ", ".join(f"{f / 1e6:g}" for f in MF_FREQS_HZ) + " MHz beside the 30 MHz depth and IR")
    out["sidecar"] = dict(spec.get("sidecar", {}), single_frequency_version=spec["name"])
    return out


def mf_specs():
    return [multi_frequency(s) for s in [two_materials(), opaque_and_translucent()] + [draw(i) for i in MF_DRAWS]
            + [video(i) for i in range(3)]]


# ------------------------------------------------ a moving camera (no latch) ---

def translated(o, offset):
    """Object `o` as seen from a camera moved by `offset` (mm, optical frame): its centre shifted
    by -offset (the camera translates; it does not turn)."""
    out = dict(o)
    out["center_mm"] = [float(c - d) for c, d in zip(o["center_mm"], offset)]
    return out


def mf_moving_camera(seed=3100, n=8):
    """Issue 35: a camera carried by a robot (translating sideways and forward, 10 Hz) past a
    tilted sheet and an opaque box before boxes on a wall, phasors at MF_FREQS_HZ. No background
    is ever seen alone from a still camera, so nothing can be latched: each frame's objects,
    background included, are those seen from where the camera is then (the toml's stage objects
    are in that frame's camera coordinates)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(2800, 3300)
    bg, bgm, bgd = bg_boxes_on_wall(rng, z, n_boxes=2)
    bgz = bg_depth(bg)
    zmax = float(np.nanmin(bgz[30:114, 35:141])) - 300
    mats = {"m1": mat(1, "sheet_1", rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.7), "mask"),
            "box": mat(2, "opaque_box", 0.0, rng.uniform(0.3, 0.8), "opaque")}
    step = np.array([rng.uniform(20, 35), 0.0, rng.uniform(10, 25)])  # mm a frame
    for attempt in range(200):
        sh = sheet(rng, rng.uniform(1100, min(1600, zmax)), -0.3, "m1", True, min_tilt=15, max_tilt=35)
        bx = opaque_box(rng, rng.uniform(1200, min(1900, zmax)), 0.35, "box")
        views = [[translated(o, step * f) for o in (sh, bx)] for f in range(n)]
        if all(fits(o, bgz) for v in views for o in v):
            break
    stages = [{"frames": 1, "objects": v, "background": [translated(o, step * f) for o in bg],
               "camera_mm": [round(float(c), 1) for c in step * f]} for f, v in enumerate(views)]
    return dict(name="mf_moving_camera", seed=seed, model="mask", spp=COVERAGE_SPP, background=bg,
                background_materials=bgm, background_description=bgd, materials=mats, stages=stages,
                frequencies_hz=list(MF_FREQS_HZ), background_frames=0,
                sidecar={"replay_args": ["--no-latch"],
                         "camera_motion": f"the camera translates by {step.round(1).tolist()} mm a frame "
                                          "(x right, z forward), no rotation; stage k's objects are in its camera's coordinates"},
                spp_note=f"{COVERAGE_SPP} spp per frame (every frame is its own render)",
                description=f"a moving camera (no background latch): a tilted sheet and an opaque box before "
                            f"boxes on a wall, {n} frames, phasors at "
                            + ", ".join(f"{f / 1e6:g}" for f in MF_FREQS_HZ) + " MHz")


def all_specs():
    return [
        white_wall_lin(),
        paper("paper_document_holder", 11, 0.65,
              "paper Fig. 5a: white wall (albedo 1) at 2000 mm, a 24 x 31 cm sheet xi 0.65 rho 0.6 at 500/750/1000/1750 mm"),
        paper("paper_file_box", 12, 0.94,
              "paper Fig. 5b: white wall (albedo 1) at 2000 mm, a 24 x 31 cm sheet xi 0.94 rho 0.6 at 500/750/1000/1750 mm"),
        calibration_sequence(),
        tilted_gray(),
        two_materials(),
        opaque_and_translucent(),
        corner_background(),
        difftrans_sheet(),
        hollow_bin("calib_hollow_bin", 97, 4),
        hollow_bin("hollow_bin", 98, 3),
    ] + [draw(i) for i in range(20)] + calibration_specs() + [video(i) for i in range(3)] + mf_specs() + [mf_moving_camera()]


# ------------------------------------------------ objects in stepped poses ---
# Objects followed through stepped poses: after the background frames, ONE
# frame per pose, 3-5 poses at a drawn frame rate (10-30 Hz). Between
# consecutive poses every object (translucent or opaque) steps 150-350 mm in
# depth (sign drawn), 0-150 mm sideways and turns a little; each keeps its
# identity (`object`) and its own material across the poses. A pose is drawn
# again until every object is in view, within [700 mm, background - 250 mm]
# and clear of the others (`apart`). `stepped(i, "stepped_dev")` (seed
# 5000 + i) is the committed development set, `stepped(i, "stepped")` (seed
# 6000 + i) the fresh one, rendered outside the repository.

STEPPED_SEEDS = {"stepped_dev": 5000, "stepped": 6000}
STEPPED_SETS = {"stepped_dev": 8, "stepped": 12}  # the registered names: stepped_dev_00..07, stepped_00..11
STEPPED_KINDS = ["two_sheets", "two_sheets_box", "sheet_over_box", "frosted", "hollow_bin_sheet"]
STEP_MM = (150.0, 350.0)  # depth step of every object between consecutive poses
STEP_LATERAL_MM = 150.0  # at most, in a drawn direction in the image plane
STEP_TILT_DEG = 2.5  # per axis (x, y, z), so under 5 deg in all
STEP_NEAR_MM = 700.0  # every point of an object at least this far from the camera
STEP_BG_MARGIN_MM = 250.0  # every pixel of an object at least this far before the background
STEP_SHEET_MAX_TILT = 35.0
STEP_BOX_MAX_TILT = 35.0
STEP_BIN_MAX_TILT = 10.0  # the hollow bin stays near face-on
STEP_MIN_VISIBLE_PX = 150  # every object, as the nearest surface among the others
STEP_OVER_SHARE = 0.25  # sheet_over_box: the front sheet covers at least this share of the box's pixels
STEPPED_CALIB_SEED = 5500  # calib_stepped_dev_XX_<material>: seed 5500 + 10 i + material id


def in_step_range(o, bgz):
    """In view (>= 300 px), every pixel at least STEP_BG_MARGIN_MM before the background and
    every point of it at least STEP_NEAR_MM from the camera."""
    return fits(o, bgz, margin=STEP_BG_MARGIN_MM) and surface_points(o, 2)[:, 2].min() >= STEP_NEAR_MM


def _stepped_pose_ok(objs, keys, ids, kind):
    """Each object seen as the nearest surface on >= STEP_MIN_VISIBLE_PX pixels; sheet_over_box:
    the front sheet (m1) before the box on at least STEP_OVER_SHARE of the box's own pixels."""
    import tofcore as tc
    _, m = tc.ground_truth(objs, ids)
    if any((m == ids[k]).sum() < STEP_MIN_VISIBLE_PX for k in keys):
        return False
    if kind == "sheet_over_box":
        by = dict(zip(keys, objs))
        zb, mb = tc.ground_truth([by["box"]], {"box": 1})
        zs, ms = tc.ground_truth([by["m1"]], {"m1": 1})
        own = mb > 0
        over = own & (ms > 0) & (zs < zb)
        if over.sum() < STEP_OVER_SHARE * own.sum():
            return False
    return True


def _stepped_move(rng, o, zlo, zhi, max_tilt):
    """`o` one step on: depth +-150..350 mm (sign drawn; turned back if the centre would leave
    [zlo, zhi]), 0..150 mm sideways in a drawn direction, each tilt +-2.5 deg."""
    c = list(o["center_mm"])
    dz = rng.uniform(*STEP_MM) * rng.choice([-1, 1])
    if not zlo <= c[2] + dz <= zhi:
        dz = -dz
    a, r = rng.uniform(0, 2 * math.pi), rng.uniform(0, STEP_LATERAL_MM)
    dt = rng.uniform(-STEP_TILT_DEG, STEP_TILT_DEG, size=3)
    out = dict(o)
    out["center_mm"] = [c[0] + r * math.cos(a), c[1] + r * math.sin(a), c[2] + dz]
    for k, d in zip(("tilt_x_deg", "tilt_y_deg", "tilt_z_deg"), dt):
        out[k] = float(o[k] + d)
    if max(abs(out["tilt_x_deg"]), abs(out["tilt_y_deg"])) > max_tilt:
        return None
    return out


def stepped(i, prefix="stepped_dev", n_scene_tries=40, n_pose_tries=200, n_obj_tries=60):
    """Objects followed through stepped poses (see above); the kind cycles with i
    (STEPPED_KINDS), so every kind appears in any 5 consecutive indices."""
    seed = STEPPED_SEEDS[prefix] + i
    name = f"{prefix}_{i:02d}"
    rng = np.random.default_rng(seed)
    kind = STEPPED_KINDS[i % len(STEPPED_KINDS)]
    bkind, bg, bgm, bgd, bgz, _ = drawn_background(rng, 2400, 2600)
    # the farthest a centre is drawn: the background's middle part less the margin (fits decides per pixel)
    zhi = float(np.nanmedian(bgz[30:114, 35:141])) - STEP_BG_MARGIN_MM - 100.0
    zlo = STEP_NEAR_MM + 150.0
    bin_size = None
    if kind in ("two_sheets", "two_sheets_box", "sheet_over_box"):
        mats = drawn_sheets(rng, 2)
        if kind != "two_sheets":
            mats["box"] = mat(3, "opaque_box", 0.0, rng.uniform(0.3, 0.8), "opaque")
    elif kind == "frosted":
        mats = {"m1": mat(1, "frosted_slab", rng.uniform(0.3, 0.95), rng.uniform(0.3, 0.7), "difftrans")}
        if rng.uniform() < 0.5:
            mats["m2"] = mat(2, "sheet_2", rng.uniform(0.3, 0.95), rng.uniform(0.3, 0.7), "mask")
    else:
        bin_mat, bin_size = hollow_object()
        mats = {"bin": bin_mat, "m2": mat(2, "sheet_2", rng.uniform(0.3, 0.95), rng.uniform(0.3, 0.7), "mask")}
    ids = {k: m["id"] for k, m in mats.items()}
    n = int(rng.integers(3, 6))
    rate = int(rng.integers(10, 31))
    keys = sorted(mats, key=lambda k: mats[k]["id"])
    if kind == "sheet_over_box":
        keys = ["box", "m1", "m2"]  # the box first, the sheet before it next
    max_tilt = {k: STEP_BIN_MAX_TILT if k == "bin" else STEP_BOX_MAX_TILT if k == "box" else STEP_SHEET_MAX_TILT
                for k in keys}

    def first_pose():
        side = rng.choice([-1, 1])
        if kind == "sheet_over_box":
            slots = {"box": side * 0.3, "m1": side * 0.3, "m2": -side * 0.35}
        else:
            order = list(keys)
            rng.shuffle(order)
            slots = {k: (-0.45 + 0.9 * j / (len(order) - 1)) if len(order) > 1 else rng.uniform(-0.2, 0.2)
                     for j, k in enumerate(order)}
        objs = []
        for k in keys:
            for _ in range(n_obj_tries):
                if kind == "sheet_over_box" and k == "m1":
                    zbox = objs[0]["center_mm"][2] - objs[0]["size_mm"][2] / 2
                    if zbox - 250 < zlo:
                        return None
                    z = rng.uniform(zlo, zbox - 250)
                else:
                    z = rng.uniform(zlo, max(zlo + 50, zhi))
                if k == "box":
                    o = opaque_box(rng, z, slots[k], k)
                elif k == "bin":
                    x = slots[k] * TAN_H * z + rng.uniform(-40, 40)
                    o = box([x, rng.uniform(-0.2, 0.2) * TAN_V * z, z + bin_size[2] / 2], bin_size,
                            tx=rng.uniform(-3, 3), ty=rng.uniform(-3, 3), tz=rng.uniform(-3, 3), material=k)
                else:
                    o = sheet(rng, z, slots[k], k, rng.uniform() < 0.5, max_tilt=STEP_SHEET_MAX_TILT)
                if kind == "sheet_over_box" and k == "m1":  # straight before the box, a little off its centre
                    b = objs[0]["center_mm"]
                    o["center_mm"] = [b[0] + rng.uniform(-60, 60), b[1] + rng.uniform(-60, 60), o["center_mm"][2]]
                o["object"] = mats[k]["name"]
                if in_step_range(o, bgz) and all(apart(o, p) for p in objs):
                    objs.append(o)
                    break
            else:
                return None
        return objs if _stepped_pose_ok(objs, keys, ids, kind) else None

    def next_pose(prev):
        objs = []
        for k, p in zip(keys, prev):
            for _ in range(n_obj_tries):
                o = _stepped_move(rng, p, zlo, zhi, max_tilt[k])
                if o is not None and in_step_range(o, bgz) and all(apart(o, q) for q in objs):
                    objs.append(o)
                    break
            else:
                return None
        return objs if _stepped_pose_ok(objs, keys, ids, kind) else None

    for scene_try in range(n_scene_tries):
        poses, tries = [first_pose()], [1]
        if poses[0] is None:
            continue
        for _ in range(1, n):
            for t in range(n_pose_tries):
                nxt = next_pose(poses[-1])
                if nxt is not None:
                    poses.append(nxt)
                    tries.append(t + 1)
                    break
            else:
                break
        if len(poses) == n:
            break
    else:
        raise RuntimeError(f"{name}: no {n} stepped poses in {n_scene_tries} scenes")

    import tofcore as tc
    truths = [tc.ground_truth(p, ids) for p in poses]
    tracks = []
    for j, k in enumerate(keys):
        seq = [p[j] for p in poses]
        cs = [o["center_mm"] for o in seq]
        med = [round(float(np.median(z[m == ids[k]])) * 1000.0, 1) for z, m in truths]
        tracks.append({
            "object": mats[k]["name"], "material": mats[k]["id"], "kind": seq[0]["kind"],
            "model": mats[k]["model"], "size_mm": [round(float(x), 1) for x in seq[0]["size_mm"]],
            "depth_mm": [round(float(c[2]), 1) for c in cs],
            "truth_median_z_mm": med,
            "depth_step_mm": [round(float(b[2] - a[2]), 1) for a, b in zip(cs, cs[1:])],
            "lateral_step_mm": [round(float(math.hypot(b[0] - a[0], b[1] - a[1])), 1) for a, b in zip(cs, cs[1:])],
            "center_mm": [[round(float(x), 1) for x in c] for c in cs],
            "tilt_deg": [[round(float(o[t]), 2) for t in ("tilt_x_deg", "tilt_y_deg", "tilt_z_deg")] for o in seq]})
    stages = [{"frames": 1, "objects": p} for p in poses]
    model = "mixed" if any(m["model"] == "difftrans" for m in mats.values()) else "mask"
    what = ", ".join(f"{mats[k]['name']} ({'opaque' if mats[k]['model'] == 'opaque' else mats[k]['model'] + ' xi %.2f' % mats[k]['xi']})"
                     for k in keys)
    return dict(name=name, seed=seed, model=model, spp=COVERAGE_SPP, background=bg, background_materials=bgm,
                background_description=bgd, materials=mats, stages=stages, tracks=tracks, frame_rate_hz=rate,
                zstd_level=19,
                sidecar={"kind": kind, "poses": n, "moving_frames": n, "pose_draws": tries,
                         "motion_note": (
                             "stepped poses: one frame per pose after the background frames (one stage per frame, "
                             "one render each); between consecutive poses every object steps 150-350 mm in depth "
                             "(sign drawn), 0-150 mm in the image plane and each tilt by up to 2.5 deg; "
                             "stages.objects.object names the object; [[tracks]] give each object's material and, per "
                             "pose, its centre (depth_mm = centre z; truth_median_z_mm = the median ground-truth z of "
                             "the pixels it is the nearest surface on) and tilts")},
                spp_note=f"stepped poses: {COVERAGE_SPP} spp per pose (every pose is its own render)",
                description=f"stepped {prefix} {i}: {kind}: {what} before a {bkind} background, {n} poses, one frame "
                            f"each at {rate} Hz")


def stepped_calibration_specs(n=STEPPED_SETS["stepped_dev"]):
    """Per-material calibrations (calibration(), the shared calibration wall) for every
    translucent material of stepped_dev_00 .. n-1: calib_stepped_dev_XX_<material>."""
    out = []
    for i in range(n):
        spec = stepped(i, "stepped_dev")
        for key in sorted(spec["materials"], key=lambda k: spec["materials"][k]["id"]):
            if spec["materials"][key]["model"] != "opaque":
                out.append(_stepped_calibration(i, spec, key))
    return out


def _stepped_calibration(i, spec, key):
    """calibration() of material `key` of stepped_dev_<i> (`spec`), written at zstd level 19."""
    c = calibration(lambda: spec, key, STEPPED_CALIB_SEED + 10 * i + spec["materials"][key]["id"])
    c["zstd_level"] = 19
    return c


STEPPED_NAME = r"(stepped_dev|stepped)_(\d+)"
STEPPED_CALIB_NAME = r"calib_stepped_dev_(\d+)_(.+)"


def stepped_spec_name(name):
    """Whether `name` is a stepped scene's (stepped_dev_<i>, stepped_<i>) or a stepped_dev
    calibration's (calib_stepped_dev_<i>_<material>)."""
    import re
    return bool(re.fullmatch(STEPPED_NAME, name) or re.fullmatch(STEPPED_CALIB_NAME, name))


def stepped_spec(name):
    """The spec of stepped_dev_<i>, stepped_<i> (any i) or calib_stepped_dev_<i>_<material>;
    None for another name."""
    import re
    m = re.fullmatch(STEPPED_CALIB_NAME, name)
    if m:
        spec = stepped(int(m.group(1)), "stepped_dev")
        for key, mm in spec["materials"].items():
            if mm["name"] == m.group(2) and mm["model"] != "opaque":
                return _stepped_calibration(int(m.group(1)), spec, key)
        raise SystemExit(f"{name}: stepped_dev_{m.group(1)} has no translucent material {m.group(2)!r}")
    m = re.fullmatch(STEPPED_NAME, name)
    return stepped(int(m.group(2)), m.group(1)) if m else None
