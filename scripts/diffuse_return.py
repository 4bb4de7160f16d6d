"""A layer that transmits diffusely, against the straight second return: per pixel, with the truth.

usage: .venv/bin/python scripts/diffuse_return.py BAG [MATERIAL_ID]

For each stage of a rendered bag (sidecar `BAG.toml`: the materials' xi), over the pixels
of one translucent material (default 1), eroded by 3 pixels away from its edges, it
inverts each pixel's measured phasor M (amplitude from the IR image, phase from the depth)
for the layer's distance with the true xi, under two second returns:

- straight: xi^2 B, B the latched background's phasor (the default physics, Eq. 2);
- diffuse: light crossing the layer twice through a cosine lobe, each crossing's path
  g / cos(theta) for a layer g before the background, the lobe's phasor average
  psi(a) = E[exp(i a / c)] (c = cos(theta), density 2c) taken once per crossing:
  xi^2 |B| exp(i k df) psi(k g / 2)^2, on an infinite uniform background;

each by a fixed point on df (the layer's own return is what is left: its phase is
k df). It prints the RMS and median z error over the pixels for both. The diffuse
model leaves out the background outside the layer's shadow, lit directly and seen
through the layer at a slant, and the finite layer: what is left between them.
"""

import math
import os
import sys
import tomllib

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import results as R  # noqa: E402


def lobe_average(a, n=4000):
    """psi(a) = E[exp(i a / cos(theta))] over a cosine lobe (density 2 cos sin in theta)."""
    th = (np.arange(n) + 0.5) / n * (np.pi / 2)
    w = 2.0 * np.cos(th) * np.sin(th) * (np.pi / 2 / n)
    return np.sum(w * np.exp(1j * a / np.cos(th)))


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    bag = sys.argv[1]
    mid = int(sys.argv[2]) if len(sys.argv) > 2 else 1
    side = tomllib.load(open(os.path.splitext(bag)[0] + ".toml", "rb"))
    s = side["sensor"]
    w, h, fx, fy, cx, cy = s["width"], s["height"], s["fx"], s["fy"], s["cx"], s["cy"]
    rng = s["unambiguous_range_mm"]
    xi = next(m["xi"] for m in side["materials"] if m["id"] == mid)
    k = 2.0 * math.pi / rng
    inp = R.read(bag, ["ground_truth/depth", "ground_truth/material", "depth/image_raw", "ir/image_raw"])
    stamps = sorted(inp["depth/image_raw"])
    cc, rr = np.meshgrid(np.arange(w), np.arange(h))
    ray = np.sqrt(1.0 + ((cc - cx) / fx) ** 2 + ((rr - cy) / fy) ** 2)

    def arr(m):
        return np.array(R.image_values(m), float).reshape(h, w)

    def phasor(st):
        z = arr(inp["depth/image_raw"][st])
        z[z <= 0] = np.nan
        return arr(inp["ir/image_raw"][st]) * np.exp(1j * k * z * ray)

    # The lobe's average on a table over a = k g / 2 (g up to the unambiguous range).
    table_a = np.linspace(0.0, k * rng / 2.0, 2001)
    table = np.array([lobe_average(a) for a in table_a])

    def crossing(a):
        return np.interp(a, table_a, table.real) + 1j * np.interp(a, table_a, table.imag)

    nbg = side["background_frames"]
    background = np.mean([phasor(st) for st in stamps[:nbg]], 0)
    db = np.angle(background) % (2 * np.pi) / k
    for stage in side.get("stages", []):
        first = stage["frames"][0]
        st = stamps[first] if first < len(stamps) else None
        if st is None or st not in inp["ground_truth/depth"]:
            continue
        mat = arr(inp["ground_truth/material"][st])
        zt = arr(inp["ground_truth/depth"][st]) * 1000.0
        inside = (mat == mid) & np.isfinite(zt)
        for _ in range(3):
            e = inside.copy()
            e[1:] &= inside[:-1]
            e[:-1] &= inside[1:]
            e[:, 1:] &= inside[:, :-1]
            e[:, :-1] &= inside[:, 1:]
            inside = e
        ys, xs = np.nonzero(inside)
        if len(ys) == 0:
            continue
        # At most 400 pixels, spread over the layer.
        pick = slice(None, None, max(1, len(ys) // 400))
        ys, xs = ys[pick], xs[pick]
        m = phasor(st)
        rows = []
        for diffuse in (False, True):
            errs = []
            for y, x in zip(ys, xs):
                b = background[y, x]
                df = np.angle(m[y, x] - xi * xi * b) % (2 * np.pi) / k
                for _ in range(40 if diffuse else 0):
                    g = max(db[y, x] - df, 0.0)
                    second = xi * xi * abs(b) * np.exp(1j * k * df) * crossing(k * g / 2.0) ** 2
                    df = np.angle(m[y, x] - second) % (2 * np.pi) / k
                errs.append(df / ray[y, x] - zt[y, x])
            e = np.array(errs)
            rows.append(f"{'diffuse' if diffuse else 'straight'}: RMS {np.sqrt(np.mean(e ** 2)):.1f}, median {np.median(e):+.1f}")
        gap = np.median(db[ys, xs] - zt[ys, xs] * ray[ys, xs])
        print(f"stage {stage['index']} material {mid} (xi {xi:.3f}): {len(ys)} px of {int(inside.sum())}, gap {gap:.0f} mm; z error with the true xi, mm: {'; '.join(rows)}")


if __name__ == "__main__":
    main()
