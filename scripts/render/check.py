"""Numerical checks of rendered bags.

usage: check.py NAME [NAME ...]   (bags/rendered/NAME.mcap and the render cache)

Per bag: the background frames against the background's geometric z-depth
(noisy bag and, from the cached render, noise-free), the depth standard
deviation at the image centre over the background frames, and per stage and
material the mean raw error (reading - truth) on that material's pixels.
"""

import os
import sys
import tomllib

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import tofcore as tc  # noqa: E402
import scenes  # noqa: E402
import render_set  # noqa: E402
from mcap_ros2.reader import read_ros2_messages  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.normpath(os.path.join(HERE, "..", "..", "bags", "rendered"))
CACHE = os.environ.get("TTOF_RENDER_CACHE", "/work/render-cache")


def read_bag(path):
    frames = {}
    for m in read_ros2_messages(path):
        t = m.log_time_ns
        msg = m.ros_msg
        f = frames.setdefault(t, {})
        if m.channel.topic == "/tof/depth/camera_info":
            f["k"] = list(msg.k)
            continue
        dt = {"16UC1": "<u2", "32FC1": "<f4", "mono8": "u1"}[msg.encoding]
        f[m.channel.topic] = np.frombuffer(bytes(msg.data), dtype=dt).reshape(msg.height, msg.width)
    return [frames[t] for t in sorted(frames)]


def noise_free(objects, mats, spp):
    key = render_set.geometry_key(objects, mats, spp)
    p = os.path.join(CACHE, key + ".npz")
    if not os.path.exists(p):
        return None
    z = np.load(p)
    depth, _ = tc.tof_frame(z["a"], z["b"], z["s"], None)
    # unrounded z for mm-level checks
    d = np.mod(tc.R_MM / (2 * np.pi) * np.arctan2(z["b"], z["a"]), tc.R_MM)
    return d / np.linalg.norm(tc.pixel_rays(), axis=-1)


def check(name):
    spec = {s["name"]: s for s in scenes.all_specs()}[name]
    side = tomllib.load(open(os.path.join(OUT, name + ".toml"), "rb"))
    spec["spp"] = side["spp"]
    frames = read_bag(os.path.join(OUT, name + ".mcap"))
    mats = dict(spec["background_materials"])
    mats.update(spec["materials"])
    bg_truth, _ = tc.ground_truth(spec["background"], {k: 1 for k in spec["background_materials"]})
    bg_truth = bg_truth.astype(np.float64) * 1000.0
    print(f"== {name}: {len(frames)} frames, spp {side['spp']}, model {side['translucency_model']}")
    bgd = np.stack([f["/tof/depth/image_raw"] for f in frames[:10]]).astype(np.float64)
    valid = bgd > 0
    err = np.where(valid, bgd - bg_truth, np.nan)
    print(f"  background frames: valid {valid.mean() * 100:.2f} %, mean error {np.nanmean(err):+.2f} mm, "
          f"per-pixel mean over 10 frames |.| 95th pct {np.nanpercentile(np.abs(np.nanmean(err, axis=0)), 95):.2f} mm")
    c = bgd[:, 70:74, 86:90]
    print(f"  centre 4x4 depth std over frames {c.std(axis=0, ddof=1).mean():.2f} mm; "
          f"IR centre {np.mean([f['/tof/ir/image_raw'][70:74, 86:90].mean() for f in frames[:10]]):.1f} counts")
    nf = noise_free(spec["background"], mats, spec["spp"])
    if nf is not None:
        e = nf - bg_truth
        print(f"  noise-free background: mean {np.nanmean(e):+.3f} mm, max |err| {np.nanmax(np.abs(e)):.3f} mm, "
              f"99th pct {np.nanpercentile(np.abs(e), 99):.3f} mm")
    for si, st in enumerate(side.get("stages", [])):
        fs = [frames[i] for i in st["frames"]]
        gt = fs[0]["/tof/ground_truth/depth"].astype(np.float64) * 1000.0
        gm = fs[0]["/tof/ground_truth/material"]
        nf = noise_free(spec["background"] + spec["stages"][si]["objects"], mats, spec["spp"])
        parts = []
        for m in side["materials"]:
            px = gm == m["id"]
            if not px.any():
                continue
            d = np.stack([f["/tof/depth/image_raw"] for f in fs]).astype(np.float64)
            e = np.where(d > 0, d - gt, np.nan)[:, px]
            s = f"mat {m['id']} (xi {m['xi']}) {px.sum()} px: raw err {np.nanmean(e):+.1f} mm (mean |.| {np.nanmean(np.abs(e)):.1f})"
            if nf is not None:
                s += f", noise-free {np.nanmean(nf[px] - gt[px]):+.1f}"
            parts.append(s)
        zs = [o["center_mm"][2] for o in st.get("objects", [])]
        print(f"  stage {si} (z {', '.join(f'{z:.0f}' for z in zs)}): " + "; ".join(parts))


if __name__ == "__main__":
    for n in sys.argv[1:]:
        check(n)
