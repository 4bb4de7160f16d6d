"""What a rendered sheet lets through, measured against the two-layer model.

usage: .venv/bin/python scripts/background_return.py BAG

For each stage of a rendered bag (its sidecar `BAG.toml`: the stages' objects, the
materials' xi and albedo, the background's albedo), over the pixels of each
translucent sheet (eroded by 3 pixels, away from its edges):

  G = M - L1

where M is the measured phasor (amplitude from the IR image, phase from the depth) and
L1 the sheet's own return the model predicts from the truth (its distance from
ground_truth/depth, its albedo (1 - xi) rho and its tilt's cosine, scaled from the
latched background's return: a fronto-parallel wall of the sidecar's first albedo).
It prints |G| against the latched background's |B| and against the model's xi^2 |B|,
and the distance G's phase puts it at against the background's. A straight second
return (the mask model) gives |G| / |B| = xi^2 at the background's distance; light
between the sheet and a near wall adds a little, farther; a diffuse transmitter gives
a weaker, farther return.
"""

import math
import os
import sys
import tomllib

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def read(path):
    out = {}
    with open(path, "rb") as f:
        for _, ch, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            out.setdefault(ch.topic.split("/tof/", 1)[-1], []).append(msg)
    return out


def image(m, dtype):
    return np.frombuffer(bytes(m.data), dtype=dtype).reshape(m.height, m.width).astype(np.float64)


def rotation(tx, ty, tz):
    """R = Rz Ry Rx (scripts/render/tofcore.py rotation), degrees."""
    ax, ay, az = (math.radians(a) for a in (tx, ty, tz))
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def erode(mask, n):
    for _ in range(n):
        m = mask.copy()
        m[1:] &= mask[:-1]
        m[:-1] &= mask[1:]
        m[:, 1:] &= mask[:, :-1]
        m[:, :-1] &= mask[:, 1:]
        mask = m
    return mask


def main(bag):
    meta = tomllib.load(open(os.path.splitext(bag)[0] + ".toml", "rb"))
    s = meta["sensor"]
    rng = s["unambiguous_range_mm"]
    d = read(bag)
    u, v = np.meshgrid(np.arange(s["width"]), np.arange(s["height"]))
    x, y = (u - s["cx"]) / s["fx"], (v - s["cy"]) / s["fy"]
    ray = np.sqrt(1 + x * x + y * y)
    rays = np.stack([x, y, np.ones_like(x)], -1) / ray[..., None]

    def phasor(z, ir):
        return ir * np.exp(1j * 2 * np.pi * z * ray / rng)

    nb = meta["background_frames"]
    back = np.mean([phasor(image(d["depth/image_raw"][i], "<u2"), image(d["ir/image_raw"][i], "<f4"))
                    for i in range(nb)], axis=0)
    rb = np.angle(back) % (2 * np.pi) * rng / (2 * np.pi)
    wall = meta["background"]["objects"][0]["albedo"]
    mats = {m["id"]: m for m in meta["materials"]}
    for st in meta["stages"]:
        f = st["frames"][0]
        z, ir = image(d["depth/image_raw"][f], "<u2"), image(d["ir/image_raw"][f], "<f4")
        truth, mat = image(d["ground_truth/depth"][f], "<f4") * 1000, image(d["ground_truth/material"][f], "u1")
        m_phasor = phasor(z, ir)
        for o in st["objects"]:
            m = mats[o["material"]]
            if m.get("opaque"):
                continue
            sel = erode(mat == m["id"], 3)
            if sel.sum() < 20:
                continue
            normal = rotation(o.get("tilt_x_deg", 0), o.get("tilt_y_deg", 0), o.get("tilt_z_deg", 0)) @ [0, 0, 1]
            cos_f = np.abs(rays @ normal)
            rf = truth * ray
            l1 = np.abs(back) * ((1 - m["xi"]) * m["albedo"] / wall) * (rb / rf) ** 2 * cos_f * ray
            g = m_phasor - l1 * np.exp(1j * 2 * np.pi * rf / rng)
            rg = np.angle(g) % (2 * np.pi) * rng / (2 * np.pi)
            ratio = np.abs(g[sel]) / np.abs(back[sel])
            print(f"stage {st['index']} material {m['id']} ({m['model']}, xi {m['xi']:.3f}): {int(sel.sum())} px, "
                  f"sheet {np.median(rf[sel]):.0f} mm, background {np.median(rb[sel]):.0f} mm, gap {np.median((rb - rf)[sel]):.0f} mm; "
                  f"|G|/|B| {np.median(ratio):.3f} (p10 {np.percentile(ratio, 10):.3f}, p90 {np.percentile(ratio, 90):.3f}; "
                  f"xi^2 {m['xi'] ** 2:.3f}); G at {np.median(rg[sel]):.0f} mm, "
                  f"{np.median((rg - rb)[sel]):+.0f} mm from the background")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
