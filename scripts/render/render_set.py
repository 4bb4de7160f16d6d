"""Renders the physically rendered CW-ToF validation set into bags/rendered/.

usage: render_set.py [--list] [--out DIR] [--cache DIR] [NAME ...]

A NAME beyond the set (draw_20, video_3, mf_draw_21, ...) is drawn from the same
seeded ranges: a scene nothing was tuned on. The stepped scenes (stepped_dev_<i>,
stepped_<i>, calib_stepped_dev_<i>_<material>; scenes.stepped) are rendered by
name only: a run with no NAME leaves them out.

Each bag: 10 background-only frames, then its stages (a few frames of one
geometry each). Each geometry is rendered once (cached by content in
--cache) and its noisy frames are drawn from that render with per-frame
seeds. Scene parameters are drawn from seeded ranges (scenes.py). A spec
with `frequencies_hz` (the mf_* bags) also writes each frequency's phasor
(`/tof/phasor_<k>/image_raw`, 32FC2) and the frequencies' metadata record.
"""

import argparse
import contextlib
import hashlib
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import tofcore as tc  # noqa: E402
import scenes  # noqa: E402
import mcap.writer  # noqa: E402
import zstandard  # noqa: E402
from mcap.writer import CompressionType  # noqa: E402
from mcap_ros2.writer import Writer  # noqa: E402

TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
SEP = "=" * 80 + "\n"
IMAGE = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
    "uint8 is_bigendian\nuint32 step\nuint8[] data\n"
    + SEP + "MSG: std_msgs/Header\n" + HEADER
    + SEP + "MSG: builtin_interfaces/Time\n" + TIME
)
ROI = "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
CAMERA_INFO = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
    "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
    "uint32 binning_y\nRegionOfInterest roi\n"
    + SEP + "MSG: std_msgs/Header\n" + HEADER
    + SEP + "MSG: builtin_interfaces/Time\n" + TIME
    + SEP + "MSG: sensor_msgs/RegionOfInterest\n" + ROI
)
FRAME_ID = "tof_optical_frame"
BACKGROUND_FRAMES = 10
# The model physics these renders match, named in every bag (an MCAP metadata record, read by
# replay, calibrate-xi and audit) and in its sidecar: IR the demodulated amplitude, light
# through a layer both ways (L2 = Ib xi^2), every option written out.
PHYSICS_RECORD = "translucent_tof.physics"
# Multi-frequency bags (issue 35): the frequencies of phasor_<k>/image_raw in this record
# (src/bag/phasors.rs METADATA_NAME / FREQUENCIES_KEY), Hz, comma-separated, in the order of k.
MF_RECORD = "translucent_tof"
MF_KEY = "modulation_frequencies_hz"
PHYSICS_PRESET = "physical"
PHYSICS_TOML = (
    "# The model physics this render matches (scripts/render/render_set.py).\n"
    f'preset = "{PHYSICS_PRESET}"\n'
    "bounces = 2\n"
    'ir_mode = "amplitude"\n'
    "transmission_albedo_power = 0.0\n"
    "ambient_offset = 0.0\n"
    "subsurface_delay_mm = 0.0\n"
    "refraction_shift_px = [0.0, 0.0]\n"
)


def geometry_key(objects, materials, spp):
    used = {o["material"] for o in objects}
    blob = json.dumps({"objects": objects, "materials": {k: materials[k] for k in sorted(used)},
                       "spp": spp, "bins": [tc.START_M, tc.BIN_M, tc.BINS],
                       "emitter": [tc.EMIT_INTENSITY, tc.BEAM_DEG, tc.CUTOFF_DEG], "v": 1},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def rendered(objects, materials, spp, cache, freqs_hz=()):
    """(A, B, S, render_seconds, cached?, phasors) of one geometry. The
    render's seed comes from the geometry's content, so a geometry shared by
    several bags (e.g. the white wall at 2000 mm) is rendered once. With
    `freqs_hz` the same transient is also correlated at those frequencies
    (`phasors` = (A_k, B_k) arrays (K, H, W), else None), cached apart under
    the same seed: its 30 MHz A, B are those of the single-frequency render."""
    key = geometry_key(objects, materials, spp)
    seed = int(key[:7], 16)
    freqs = [float(f) for f in freqs_hz]
    if freqs:
        tag = hashlib.sha256(json.dumps(freqs).encode()).hexdigest()[:8]
        path = os.path.join(cache, f"{key}_mf_{tag}.npz")
    else:
        path = os.path.join(cache, key + ".npz")
    if os.path.exists(path):
        z = np.load(path)
        ph = (z["pa"], z["pb"]) if freqs else None
        return z["a"], z["b"], z["s"], float(z["seconds"]), True, ph
    t0 = time.time()
    (pa, pb), s = tc.render_transient_phasors(objects, materials, spp, seed, [tc.F_MOD] + freqs,
                                             chunk_spp=2048, log=lambda m: print(m, flush=True))
    secs = time.time() - t0
    a, b = pa[0], pb[0]
    extra = {"pa": pa[1:], "pb": pb[1:], "freqs_hz": np.array(freqs)} if freqs else {}
    np.savez(path + ".tmp.npz", a=a, b=b, s=s, seconds=secs, **extra)
    os.replace(path + ".tmp.npz", path)
    return a, b, s, secs, False, ((pa[1:], pb[1:]) if freqs else None)


@contextlib.contextmanager
def _zstd_level(level):
    """The mcap writer compresses each chunk with zstandard.compress (level 3); this swaps in
    a compressor at `level` while a bag is written."""
    import mcap.writer as mw
    real = mw.zstandard

    class Shim:
        @staticmethod
        def compress(data):
            return real.ZstdCompressor(level=level).compress(data)
    mw.zstandard = Shim
    try:
        yield
    finally:
        mw.zstandard = real


@contextlib.contextmanager
def _nothing():
    yield


def image_msg(hdr, encoding, arr):
    arr = np.ascontiguousarray(arr)
    return {"header": hdr, "height": tc.H, "width": tc.W, "encoding": encoding, "is_bigendian": 0,
            "step": arr.nbytes // tc.H, "data": arr.tobytes()}


def info_msg(hdr):
    k = tc.camera_info_k()
    return {"header": hdr, "height": tc.H, "width": tc.W, "distortion_model": "plumb_bob",
            "d": [0.0] * 5, "k": k, "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
            "p": [k[0], 0.0, k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0],
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


def toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(round(float(v), 6))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def obj_toml(prefix, obj, materials):
    mat = materials[obj["material"]]
    lines = [f"[[{prefix}]]", f'kind = "{obj["kind"]}"']
    if "object" in obj:  # a moving object's name (videos): the same name in every frame it is in
        lines.append(f"object = {toml_value(obj['object'])}")
    if "id" in mat:
        lines.append(f"material = {mat['id']}")
    else:
        lines.append(f"albedo = {toml_value(mat['albedo'])}")
    lines += [f"center_mm = {toml_value([round(float(x), 1) for x in obj['center_mm']])}",
              f"size_mm = {toml_value([round(float(x), 1) for x in obj['size_mm']])}"]
    for k in ("tilt_x_deg", "tilt_y_deg", "tilt_z_deg"):
        lines.append(f"{k} = {toml_value(round(float(obj.get(k, 0.0)), 3))}")
    return lines


class ZstdAtLevel:
    """Stands in for the zstandard module in mcap.writer (which compresses
    each chunk with zstandard.compress at its default level 3) to compress at
    another level: a spec's `zstd_level` (the videos: smaller bags, the same
    messages)."""

    def __init__(self, level):
        self.compressor = zstandard.ZstdCompressor(level=level)

    def compress(self, data):
        return self.compressor.compress(data)


def write_bag(spec, out_dir, cache):
    level = spec.get("zstd_level")
    saved = mcap.writer.zstandard
    if level is not None:
        mcap.writer.zstandard = ZstdAtLevel(level)
    try:
        _write_bag(spec, out_dir, cache)
    finally:
        mcap.writer.zstandard = saved


def _write_bag(spec, out_dir, cache):
    name = spec["name"]
    mats = dict(spec["background_materials"])
    mats.update(spec["materials"])
    ids = {k: m["id"] for k, m in spec["materials"].items()}
    freqs = [float(f) for f in spec.get("frequencies_hz", [])]
    n_background = spec.get("background_frames", BACKGROUND_FRAMES)  # 0: nothing to latch
    geoms = [(spec["background"], [], n_background, None)] if n_background else []
    for st in spec["stages"]:  # a stage may see the background from elsewhere (a moving camera)
        geoms.append((st.get("background", spec["background"]) + st["objects"], st["objects"], st["frames"],
                      st.get("camera_mm")))
    total_secs = 0.0
    frame = 0
    rate_hz = spec.get("frame_rate_hz", 10)  # stamps 1 s + floor(frame * 1e9 / rate) ns
    stage_rows = []
    os.makedirs(out_dir, exist_ok=True)
    tmp = os.path.join(cache, name + ".mcap.tmp")  # moved into out_dir when complete
    with open(tmp, "wb") as out, (_zstd_level(19) if freqs and spec.get("zstd_level") is None else _nothing()):
        # multi-frequency bags: zstd level 19 (the phasor images are noisy floats; level 3,
        # the writer's default, would put a 16-frame bag above 5 MB); the content is the same
        w = Writer(out, compression=CompressionType.ZSTD)
        w.add_metadata(PHYSICS_RECORD, {"physics_toml": PHYSICS_TOML})  # first: a bag cut short keeps it
        if freqs:  # the phasor topics' frequencies, in the order of k (docs/interfaces.md)
            w.add_metadata(MF_RECORD, {MF_KEY: ",".join(str(int(round(f))) for f in freqs)})
        img_s = w.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        info_s = w.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO)
        for gi, (objects, fg, nframes, camera) in enumerate(geoms):
            print(f"{name}: geometry {gi}/{len(geoms) - 1} ({len(objects)} objects, {nframes} frames)", flush=True)
            a, b, s, secs, cached, ph = rendered(objects, mats, spec["spp"], cache, freqs)
            print(f"  {'cached' if cached else 'rendered'} {secs:.1f} s", flush=True)
            total_secs += secs
            gt_depth, gt_mat = tc.ground_truth(fg, ids)
            first = frame
            for _ in range(nframes):
                rng = np.random.default_rng([spec["seed"], frame])
                depth, ir = tc.tof_frame(a, b, s, rng)
                ir = np.round(ir * 16.0) / 16.0  # 1/16 count: keeps the bags small
                ns = 1_000_000_000 + frame * 1_000_000_000 // rate_hz
                hdr = {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": FRAME_ID}
                for topic, schema, msg in (
                        ("/tof/depth/image_raw", img_s, image_msg(hdr, "16UC1", depth.astype("<u2"))),
                        ("/tof/ir/image_raw", img_s, image_msg(hdr, "32FC1", ir.astype("<f4"))),
                        ("/tof/depth/camera_info", info_s, info_msg(hdr)),
                        ("/tof/ground_truth/depth", img_s, image_msg(hdr, "32FC1", gt_depth.astype("<f4"))),
                        ("/tof/ground_truth/material", img_s, image_msg(hdr, "mono8", gt_mat))):
                    w.write_message(topic, schema, msg, log_time=ns, publish_time=ns, sequence=frame)
                for k in range(len(freqs)):
                    # each frequency's noise from its own stream: depth and IR above are
                    # drawn exactly as in the single-frequency bag of the same render
                    prng = np.random.default_rng([spec["seed"], frame, 1 + k])
                    p = tc.phasor_frame(ph[0][k], ph[1][k], s, prng)
                    w.write_message(f"/tof/phasor_{k}/image_raw", img_s, image_msg(hdr, "32FC2", p.astype("<f4")),
                                    log_time=ns, publish_time=ns, sequence=frame)
                frame += 1
            if gi > 0 or not n_background:
                stage_rows.append((first, frame - 1, fg, secs, camera))
        w.finish()
    os.replace(tmp, os.path.join(out_dir, name + ".mcap"))

    lines = [f"# Physically rendered CW-ToF bag (Mitsuba 3 + mitransient); made by scripts/render/render_set.py {name}",
             f"name = {toml_value(name)}", f"description = {toml_value(spec['description'])}",
             f"seed = {spec['seed']}", f"translucency_model = {toml_value(spec['model'])}",
             f"translucency_model_note = {toml_value(scenes.MODEL_NOTES[spec['model']])}",
             f"spp = {spec['spp']}",
             f"spp_note = {toml_value(spec.get('spp_note', 'high sample count: one render per geometry'))}",
             f"render_seconds = {round(total_secs, 1)}",
             f"background_frames = {n_background}", f"frames = {frame}",
             f"frame_period_s = {toml_value(round(1.0 / rate_hz, 9))}", 'first_stamp_s = 1.0',
             "# the model physics this render matches (also the bag's translucent_tof.physics record)",
             f"physics = {toml_value(PHYSICS_PRESET)}",
             *([f"frame_rate_hz = {rate_hz}",
                "stamps_note = \"frame k is stamped 1 s + floor(k * 1e9 / frame_rate_hz) ns\""]
               if rate_hz != 10 or "frame_rate_hz" in spec else []),  # a drawn rate: stated even at 10 Hz
             *[f"{k} = {toml_value(v)}" for k, v in spec.get("sidecar", {}).items()],
             "", "[sensor]", f"width = {tc.W}", f"height = {tc.H}", f"hfov_deg = {tc.HFOV_DEG}",
             f"vfov_deg = {tc.VFOV_DEG}", f"fx = {tc.FX!r}", f"fy = {tc.FY!r}", f"cx = {tc.CX!r}", f"cy = {tc.CY!r}",
             'pixel_centre = "pixel (u, v) centre ray ((u - cx)/fx, (v - cy)/fy, 1); cx = (W-1)/2, cy = (H-1)/2"',
             f"modulation_hz = {tc.F_MOD!r}", f"unambiguous_range_mm = {round(tc.R_MM, 4)}",
             'correlation = "sinusoidal: A = sum L cos(2 pi (p/2)/R), B = sum L sin(...); depth = R/(2 pi) atan2(B, A) mod R, as z"',
             f"transient_bin_mm = {tc.BIN_M * 1000}", f"transient_path_range_mm = [{tc.START_M * 1000}, {(tc.START_M + tc.BINS * tc.BIN_M) * 1000}]",
             f'emitter = "spot at the camera centre, flat to {tc.BEAM_DEG} deg off axis, linear falloff in angle to 0 at {tc.CUTOFF_DEG} deg"',
             f"ir = {toml_value('demodulated amplitude sqrt(A^2 + B^2) times ir_gain, counts, rounded to 1/16')}",
             f"ir_gain = {tc.IR_GAIN!r}",
             f"ir_reference = {toml_value('white (albedo 1) wall at 2000 mm, image centre = %g counts' % tc.IR_REF_COUNTS)}",
             "", "[noise]",
             'model = "A, B (counts) += N(0, alpha * (S + floor)) each, S = total collected light (sum of all bins) in counts; per-frame seed [seed, frame]"',
             f"alpha = {tc.NOISE_ALPHA!r}", f"floor_counts = {tc.NOISE_FLOOR!r}",
             f"reference_depth_std_mm = {tc.REF_DEPTH_STD_MM} # white wall, 2000 mm, image centre",
             f"min_amplitude_counts = {tc.MIN_AMPLITUDE} # below: depth 0 (invalid)",
             ]
    if freqs:
        lines += ["", "[multi_frequency]",
                  f"modulation_frequencies_hz = {toml_value(freqs)}",
                  f"topics = {toml_value([f'/tof/phasor_{k}/image_raw' for k in range(len(freqs))])}",
                  f"unambiguous_range_mm = {toml_value([round(tc.C_LIGHT / (2 * f) * 1000.0, 4) for f in freqs])}",
                  f"record = {toml_value(f'MCAP metadata {MF_RECORD}, key {MF_KEY}: the frequencies in Hz in the order of k')}",
                  'encoding = "32FC2: per pixel (in-phase A, quadrature B) in counts (ir_gain), rounded to step_counts"',
                  'correlation = "from the same transient as the 30 MHz depth and IR: per frequency f_k, R_k = c/(2 f_k), '
                  'A_k = sum L cos(2 pi (p/2)/R_k), B_k = sum L sin(...), each divided by its bin sinc(pi w / 2R_k); '
                  'a return at distance d (along the ray) has phase 2 pi d / R_k (wraps at R_k), as the 30 MHz depth"',
                  f"step_counts = {tc.PHASOR_STEP_COUNTS!r}",
                  "depth_and_ir_note = \"depth and IR are the 30 MHz readings drawn exactly as a single-frequency bag's "
                  "(seed [seed, frame]); the phasors do not change them\"",
                  "", "[multi_frequency.noise]",
                  'model = "per frequency k: A_k, B_k (counts) += N(0, alpha * (S + floor)) each, the [noise] model with the same alpha, '
                  'floor and S (total collected light, the same at every frequency); independent per frequency and of the '
                  '30 MHz reading: per-frame seed [seed, frame, 1 + k]"',
                  f"alpha = {tc.NOISE_ALPHA!r}", f"floor_counts = {tc.NOISE_FLOOR!r}",
                  "reference_note = \"the same A, B noise at every frequency: the reference wall's depth std is "
                  "10 mm * 30 MHz / f_k (15, 6, 3 mm at 20, 50, 100 MHz)\""]
    lines += ["", "[background]", f"description = {toml_value(spec['background_description'])}"]
    for o in spec["background"]:
        lines += [""] + obj_toml("background.objects", o, mats)
    for key in sorted(spec["materials"], key=lambda k: spec["materials"][k]["id"]):
        m = spec["materials"][key]
        lines += ["", "[[materials]]", f"id = {m['id']}", f"name = {toml_value(m['name'])}",
                  f"xi = {toml_value(m['xi'])}", f"albedo = {toml_value(m['albedo'])}",
                  f"opaque = {toml_value(m['model'] == 'opaque')}", f"model = {toml_value(m['model'])}"]
    for t in spec.get("tracks", []):  # a video's moving objects: material and path, per object
        lines += ["", "[[tracks]]"] + [f"{k} = {toml_value(v)}" for k, v in t.items()]
    for i, (f0, f1, fg, secs, camera) in enumerate(stage_rows):
        lines += ["", "[[stages]]", f"index = {i}", f"frames = {toml_value(list(range(f0, f1 + 1)))}",
                  f"render_seconds = {round(secs, 1)}"]
        if camera is not None:
            lines += [f"camera_mm = {toml_value(camera)}"]
        for o in fg:
            lines += [""] + obj_toml("stages.objects", o, mats)
    with open(os.path.join(out_dir, name + ".toml"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"{name}: {frame} frames, render {total_secs:.1f} s", flush=True)


def find_spec(name, specs=None):
    """The spec of `name`: a stepped scene or its calibration (scenes.stepped_spec, drawn alone:
    no need to draw the whole set), one of `specs` (by name; scenes.all_specs() if None), or a
    fresh draw (fresh_spec)."""
    spec = scenes.stepped_spec(name)
    if spec is not None:
        return spec
    if specs is None:
        specs = {s["name"]: s for s in scenes.all_specs()}
    return specs[name] if name in specs else fresh_spec(name)


def fresh_spec(name):
    """The spec of `draw_<i>`, `video_<i>` or either with `mf_` before it, for any `i`."""
    mf = name.startswith("mf_")
    kind, _, index = name.removeprefix("mf_").rpartition("_")
    make = {"draw": scenes.draw, "video": scenes.video}.get(kind)
    if make is None or not index.isdigit():
        raise SystemExit(f"{name}: no such scene (see --list; draw_<i>, video_<i> and mf_ before either are drawn fresh)")
    spec = make(int(index))
    return scenes.multi_frequency(spec) if mf else spec


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("names", nargs="*")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "bags", "rendered"))
    ap.add_argument("--cache", default=os.environ.get("TTOF_RENDER_CACHE", "/work/render-cache"))
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--spp", type=int, default=0, help="override every bag's spp (quick tests)")
    args = ap.parse_args()
    if args.list:
        for s in scenes.all_specs():
            print(s["name"], s["spp"], len(s["stages"]))
        # the stepped scenes and their calibrations: rendered by name only (not in the default run)
        for s in [scenes.stepped(i, "stepped_dev") for i in range(scenes.STEPPED_SETS["stepped_dev"])] \
                + scenes.stepped_calibration_specs() \
                + [scenes.stepped(i, "stepped") for i in range(scenes.STEPPED_SETS["stepped"])]:
            print(s["name"], s["spp"], len(s["stages"]), "(by name)")
        return
    # A stepped name (scenes.stepped_spec) is drawn alone; any other needs the set.
    specs = None if args.names and all(scenes.stepped_spec_name(n) for n in args.names) else scenes.all_specs()
    names = args.names or [s["name"] for s in specs]
    by = {s["name"]: s for s in specs} if specs is not None else {}
    # Fresh scenes from the same seeded ranges, beyond the committed set (draw_20,
    # mf_draw_20, video_3, stepped_12, ...): scenes nothing was tuned on.
    for n in names:
        if n not in by:
            by[n] = find_spec(n, by)
    os.makedirs(args.cache, exist_ok=True)
    for n in names:
        if args.spp:
            by[n]["spp"] = args.spp
        write_bag(by[n], os.path.normpath(args.out), args.cache)


if __name__ == "__main__":
    main()
