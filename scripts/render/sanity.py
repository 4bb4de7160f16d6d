"""The renderer's own checks, noise-free (no bag written):

1. an empty white wall at 2000 mm reads its geometric z-depth across the image;
2. a sheet of xi = 0 (opaque, mask model) at 1000 mm reads its own distance;
3. a sheet of xi = 0.65, rho 0.6 at 1000 mm before a white wall at 2000 mm
   reads in between, next to the two-return prediction with the plain
   transmission law L2 = Ib xi^2 (physics.md Sec. 6);
4. the same with the thin diffuse transmitter (model b);
5. the mask sheet of 3. at 20, 50 and 100 MHz (the multi-frequency
   versions' correlation, same transient): each frequency's phasor at the
   image centre against the two-return prediction at that frequency.

usage: sanity.py [SPP]   (default 2048)
"""

import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import tofcore as tc  # noqa: E402


def read(objs, mats, spp):
    a, b, s = tc.render_transient_ab(objs, mats, spp, seed=7, chunk_spp=2048, log=lambda m: None)
    d = np.mod(tc.R_MM / (2 * math.pi) * np.arctan2(b, a), tc.R_MM)
    return d / np.linalg.norm(tc.pixel_rays(), axis=-1), np.hypot(a, b) * tc.IR_GAIN, s * tc.IR_GAIN


def main():
    spp = int(sys.argv[1]) if len(sys.argv) > 1 else 2048
    wall = {"kind": "rect", "center_mm": [0, 0, 2000], "size_mm": [9000, 9000], "material": "wall"}
    sheet = {"kind": "rect", "center_mm": [0, 0, 1000], "size_mm": [240, 310], "material": "sheet"}
    gt, m = tc.ground_truth([sheet], {"sheet": 1})
    px = m > 0
    z, amp, s = read([wall], {"wall": {"model": "opaque", "albedo": 1.0, "xi": 0.0}}, spp)
    e = z - 2000.0
    print(f"1. white wall 2000 mm: z error mean {e.mean():+.3f} mm, max |err| {np.abs(e).max():.3f} mm; "
          f"IR centre {amp[70:74, 86:90].mean():.1f} counts (gain reference 10000)")
    for xi, model in ((0.0, "mask"), (0.65, "mask"), (0.65, "difftrans")):
        mats = {"wall": {"model": "opaque", "albedo": 1.0, "xi": 0.0},
                "sheet": {"model": model, "xi": xi, "albedo": 0.6}}
        z, amp, s = read([wall, sheet], mats, spp)
        err = z[px] - gt[px] * 1000.0
        line = (f"{model} xi {xi}: sheet at 1000 mm reads {z[px].mean():.1f} mm (error {err.mean():+.1f}, "
                f"std over its {px.sum()} px {err.std():.1f}); amplitude/total light {np.mean(amp[px] / s[px]):.3f}")
        if model == "mask":
            l1, l2 = (1 - xi) * 0.6 / 1.0 ** 2, 1.0 * xi ** 2 / 2.0 ** 2
            p1, p2 = 2 * math.pi * 1000 / tc.R_MM, 2 * math.pi * 2000 / tc.R_MM
            pred = tc.R_MM / (2 * math.pi) * math.atan2(l1 * math.sin(p1) + l2 * math.sin(p2),
                                                        l1 * math.cos(p1) + l2 * math.cos(p2))
            line += f"; two-return plain-law prediction on the axis {pred:.1f} mm"
        print(line)
    # 5. multi-frequency: the same mask scene, each frequency's own correlation and wrap
    freqs = [20e6, 50e6, 100e6]
    mats = {"wall": {"model": "opaque", "albedo": 1.0, "xi": 0.0}, "sheet": {"model": "mask", "xi": 0.65, "albedo": 0.6}}
    (pa, pb), _ = tc.render_transient_phasors([wall, sheet], mats, spp, 7, freqs, chunk_spp=2048, log=lambda m: None)
    l1, l2 = (1 - 0.65) * 0.6 / 1.0 ** 2, 1.0 * 0.65 ** 2 / 2.0 ** 2
    parts = []
    for k, f in enumerate(freqs):
        r = tc.C_LIGHT / (2 * f) * 1000.0
        a, b = pa[k][70:74, 86:90].mean(), pb[k][70:74, 86:90].mean()
        p1, p2 = 2 * math.pi * 1000 / r, 2 * math.pi * 2000 / r
        pred = math.atan2(l1 * math.sin(p1) + l2 * math.sin(p2), l1 * math.cos(p1) + l2 * math.cos(p2))
        got = math.atan2(b, a)
        dd = (got - pred + math.pi) % (2 * math.pi) - math.pi
        parts.append(f"{f / 1e6:g} MHz: phase {got:+.3f} rad, prediction {pred:+.3f} (difference {dd * r / (2 * math.pi):+.1f} mm)")
    print("5. mask xi 0.65 at 20/50/100 MHz, image centre: " + "; ".join(parts))


if __name__ == "__main__":
    main()
