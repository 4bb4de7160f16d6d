"""Numerical checks of rendered bags.

usage: check.py NAME [NAME ...]   (bags/rendered/NAME.mcap and the render cache)

Per bag: the background frames against the background's geometric z-depth
(noisy bag and, from the cached render, noise-free), the depth standard
deviation at the image centre over the background frames, and per stage and
material the mean raw error (reading - truth) on that material's pixels.
Multi-frequency bags (mf_*) also: per frequency the background's phasor
distance against the geometry (wrapped at that frequency's range) and the
opaque objects', the phasors' spread, and whether the 30 MHz depth and IR
are the single-frequency bag's. Every bag: its stamps against the sidecar's rate; with
[[tracks]] (videos, stepped scenes) whether every stage names each tracked object and
(stepped) the ground truth per pose against the sidecar's. TTOF_RENDER_OUT: another bag directory.
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
OUT = os.path.normpath(os.environ.get("TTOF_RENDER_OUT", os.path.join(HERE, "..", "..", "bags", "rendered")))
CACHE = os.environ.get("TTOF_RENDER_CACHE", "/work/render-cache")


def read_bag(path):
    frames = {}
    for m in read_ros2_messages(path):
        t = m.log_time_ns
        msg = m.ros_msg
        f = frames.setdefault(t, {"t": t})
        if m.channel.topic == "/tof/depth/camera_info":
            f["k"] = list(msg.k)
            continue
        dt = {"16UC1": "<u2", "32FC1": "<f4", "32FC2": "<f4", "mono8": "u1"}[msg.encoding]
        shape = (msg.height, msg.width, 2) if msg.encoding == "32FC2" else (msg.height, msg.width)
        f[m.channel.topic] = np.frombuffer(bytes(msg.data), dtype=dt).reshape(shape)
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


def wrapped(d, r):
    """d wrapped into [-r/2, r/2)."""
    return np.mod(d + r / 2, r) - r / 2


def check_phasors(name, side, spec, frames, bg_truth):
    """Multi-frequency bags: each frequency's phasor against the geometry (the distance along the
    ray, wrapped at that frequency's range), its noise against the stated model, and the 30 MHz
    depth against the single-frequency bag's."""
    mf = side["multi_frequency"]
    norm = np.linalg.norm(tc.pixel_rays(), axis=-1)
    for k, (f, r) in enumerate(zip(mf["modulation_frequencies_hz"], mf["unambiguous_range_mm"])):
        ph = np.stack([fr[f"/tof/phasor_{k}/image_raw"] for fr in frames[:10]]).astype(np.float64)
        m = ph.mean(axis=0)
        d = np.mod(r / (2 * np.pi) * np.arctan2(m[..., 1], m[..., 0]), r)
        e = wrapped(d - bg_truth * norm, r)
        # the noise: per pixel std of A over the background frames against alpha (S + floor),
        # S from the 30 MHz IR would be the amplitude, not the total light: compare at the centre
        sd = ph[:, 70:74, 86:90, :].std(axis=0, ddof=1).mean()
        print(f"  phasor_{k} {f / 1e6:g} MHz (R {r:.0f} mm): background (mean of 10 frames) distance - truth, wrapped: "
              f"median {np.nanmedian(e):+.2f} mm, |.| 95th pct {np.nanpercentile(np.abs(e), 95):.2f} mm; "
              f"amplitude centre {np.hypot(m[70:74, 86:90, 0], m[70:74, 86:90, 1]).mean():.1f} counts, "
              f"A/B std over frames {sd:.1f} counts")
        for si, st in enumerate(side.get("stages", [])):
            fs = [frames[i] for i in st["frames"]]
            gt = fs[0]["/tof/ground_truth/depth"].astype(np.float64) * 1000.0
            gm = fs[0]["/tof/ground_truth/material"]
            for mat in side["materials"]:
                px = gm == mat["id"]
                if not mat["opaque"] or not px.any():
                    continue
                p = np.stack([fr[f"/tof/phasor_{k}/image_raw"] for fr in fs]).astype(np.float64)[:, px]
                dd = np.mod(r / (2 * np.pi) * np.arctan2(p[..., 1], p[..., 0]), r)
                ee = wrapped(dd - gt[px] * norm[px], r)
                print(f"    stage {si} opaque mat {mat['id']} {px.sum()} px: distance - truth median {np.median(ee):+.1f} mm")
    single = side.get("single_frequency_version")
    sp = os.path.join(OUT, f"{single}.mcap") if single else None
    if sp and os.path.exists(sp):
        other = read_bag(sp)
        same = [np.array_equal(a["/tof/depth/image_raw"], b["/tof/depth/image_raw"])
                and np.array_equal(a["/tof/ir/image_raw"], b["/tof/ir/image_raw"]) for a, b in zip(frames, other)]
        diff = np.concatenate([(a["/tof/depth/image_raw"].astype(float) - b["/tof/depth/image_raw"]).ravel()
                               for a, b in zip(frames, other)])
        print(f"  30 MHz depth and IR identical to {single}'s in {sum(same)} of {len(frames)} frames "
              f"(depth differs at {np.mean(diff != 0) * 100:.3f} % of pixels, max |.| {np.abs(diff).max():.0f} mm)")


def check_stamps(side, frames):
    """Frame k stamped 1 s + floor(k 1e9 / rate) ns (rate: the sidecar's frame_rate_hz, else 10 Hz)."""
    rate = side.get("frame_rate_hz", 10)
    want = [1_000_000_000 + k * 1_000_000_000 // rate for k in range(len(frames))]
    got = [f["t"] for f in frames]
    bad = sum(a != b for a, b in zip(got, want))
    print(f"  stamps: {len(frames)} frames at {rate} Hz (period {side['frame_period_s']} s), "
          f"{'all as stated' if not bad and len(got) == side['frames'] else f'{bad} differ from 1 s + floor(k 1e9 / rate)'}"
          f"; first {got[0] / 1e9:.6f} s, last {got[-1] / 1e9:.6f} s")


def check_tracks(side, frames):
    """Moving objects ([[tracks]], stages.objects.object): each stage names every tracked object;
    where a track gives per-pose truth (stepped scenes: truth_median_z_mm), the bag's ground truth
    on the object's material agrees."""
    names = [t["object"] for t in side["tracks"]]
    stages = side.get("stages", [])
    named = all(sorted(o.get("object", "") for o in st["objects"]) == sorted(names) for st in stages)
    print(f"  tracks: {', '.join(names)}; every stage lists each once: {named}")
    for t in side["tracks"]:
        if "truth_median_z_mm" not in t:
            continue
        meds, counts = [], []
        for st in stages:
            f = frames[st["frames"][0]]
            px = f["/tof/ground_truth/material"] == t["material"]
            counts.append(int(px.sum()))
            meds.append(float(np.median(f["/tof/ground_truth/depth"][px])) * 1000.0 if px.any() else float("nan"))
        diff = np.nanmax(np.abs(np.array(meds) - np.array(t["truth_median_z_mm"])))
        print(f"    {t['object']} (mat {t['material']}): truth median z per pose "
              f"{', '.join(f'{m:.0f}' for m in meds)} mm ({', '.join(map(str, counts))} px), "
              f"sidecar's within {diff:.2f} mm; depth steps {t['depth_step_mm']} mm")


def check(name):
    spec = render_set.find_spec(name)
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
    if "multi_frequency" in side:
        check_phasors(name, side, spec, frames, bg_truth)
    check_stamps(side, frames)
    if side.get("tracks"):
        check_tracks(side, frames)
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
