"""Measures `translucent_tof replay` on ground-truthed bags against their truth.

usage: results.py [--json OUT] [--replay-arg ARG ...] BAG...

Each BAG is replayed with the given replay arguments (none: the defaults a user
gets); its sidecar `BAG.toml` names the materials (`[[materials]]`: id, xi,
opaque) and the bag carries `ground_truth/depth` (z, m) and
`ground_truth/material` (mono8: 0 background, else the material's id).

Per bag it reports:
- the mean over frames of the per-frame RMS z error (mm) over the pixels of
  translucent materials that are in the mask and have a recovered depth, the
  same for the raw reading over those pixels, and the share of the
  translucent materials' pixels that got a recovered depth;
- per translucent material: the ξ estimate of the region its pixels mostly
  fell in, its interval, whether the truth lies inside, and the poses seen;
- per opaque material: the share of its pixels not in the mask and the
  median |z error| (mm) of the published depth there;
- over those recovered pixels, the share whose error lies within twice the
  published standard deviation (`depth/corrected_sigma`), and pooled over
  every bag at the end.
"""

import argparse
import json
import math
import os
import statistics
import struct
import subprocess
import sys
import tempfile
import tomllib
from collections import Counter, defaultdict

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def image_values(msg):
    """An Image's samples as a flat list (row padding dropped)."""
    enc, w, h, step, data = msg.encoding, msg.width, msg.height, msg.step, bytes(msg.data)
    fmt, size = {"16UC1": ("H", 2), "mono16": ("H", 2), "32FC1": ("f", 4), "mono8": ("B", 1)}[enc]
    end = "<" if not msg.is_bigendian else ">"
    out = []
    for r in range(h):
        row = data[r * step: r * step + w * size]
        out.extend(struct.unpack(f"{end}{w}{fmt}", row))
    return out


def z_mm(msg):
    v = image_values(msg)
    if msg.encoding == "32FC1":
        return [x * 1000.0 if math.isfinite(x) and x > 0 else math.nan for x in v]
    return [float(x) if x > 0 else math.nan for x in v]


def read(path, wanted):
    """{topic suffix: {stamp_ns: msg}} for the topics ending in `wanted`."""
    out = defaultdict(dict)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, msg in reader.iter_decoded_messages():
            for w in wanted:
                if channel.topic.endswith(w):
                    st = msg.header.stamp
                    out[w][st.sec * 10**9 + st.nanosec] = msg
    return out


def evaluate(bag, replay_args, exe):
    side = tomllib.load(open(os.path.splitext(bag)[0] + ".toml", "rb"))
    materials = {m["id"]: m for m in side.get("materials", [])}
    with tempfile.TemporaryDirectory() as tmp:
        out_bag, out_json = os.path.join(tmp, "out.mcap"), os.path.join(tmp, "report.json")
        cmd = [exe, "replay", bag, "--out", out_bag, "--json", out_json, *replay_args]
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode != 0:
            return {"bag": bag, "error": run.stderr.strip()}
        report = json.load(open(out_json))
        inp = read(bag, ["ground_truth/depth", "ground_truth/material", "depth/image_raw"])
        res = read(out_bag, ["depth/corrected", "translucent_mask", "regions", "depth/corrected_sigma"])
    est = {m["id"]: m for m in report.get("materials", [])}
    frame_rms, frame_raw, covered, total = [], [], 0, 0
    within_2sigma, with_sigma = 0, 0
    region_votes = defaultdict(Counter)
    opaque_flagged, opaque_total, opaque_err = defaultdict(int), defaultdict(int), defaultdict(list)
    stages = defaultdict(set)
    for stamp, corr in sorted(res["depth/corrected"].items()):
        if stamp not in inp["ground_truth/depth"]:
            continue
        truth = [x * 1000.0 if math.isfinite(x) else math.nan for x in image_values(inp["ground_truth/depth"][stamp])]
        mat = image_values(inp["ground_truth/material"][stamp])
        raw = z_mm(inp["depth/image_raw"][stamp])
        z = z_mm(corr)
        mask = image_values(res["translucent_mask"][stamp])
        regions = image_values(res["regions"][stamp]) if stamp in res["regions"] else [0] * len(z)
        sigma = z_mm(res["depth/corrected_sigma"][stamp]) if stamp in res["depth/corrected_sigma"] else [math.nan] * len(z)
        e2, r2, n = 0.0, 0.0, 0
        for i, m in enumerate(mat):
            info = materials.get(m)
            if info is None or not math.isfinite(truth[i]):
                continue
            if info.get("opaque"):
                opaque_total[m] += 1
                opaque_flagged[m] += mask[i] > 0
                if math.isfinite(z[i]):
                    opaque_err[m].append(abs(z[i] - truth[i]))
                continue
            total += 1
            if regions[i]:
                region_votes[m][regions[i]] += 1
            if mask[i] and math.isfinite(z[i]):
                covered += 1
                if math.isfinite(sigma[i]):
                    with_sigma += 1
                    within_2sigma += abs(z[i] - truth[i]) <= 2.0 * sigma[i]
                e2 += (z[i] - truth[i]) ** 2
                r2 += (raw[i] - truth[i]) ** 2 if math.isfinite(raw[i]) else 0.0
                n += 1
        for m in set(mat):
            if m in materials and not materials[m].get("opaque"):
                stages[m].add(round(statistics.median(t for t, k in zip(truth, mat) if k == m and math.isfinite(t)), -1))
        if n:
            frame_rms.append(math.sqrt(e2 / n))
            frame_raw.append(math.sqrt(r2 / n))
    out = {
        "bag": os.path.basename(bag),
        "description": side.get("description", ""),
        "frames": len(frame_rms),
        "mean_frame_rms_mm": statistics.fmean(frame_rms) if frame_rms else None,
        "mean_frame_rms_raw_mm": statistics.fmean(frame_raw) if frame_raw else None,
        "recovered_share": covered / total if total else None,
        "within_2sigma": [within_2sigma, with_sigma],
        "materials": [],
        "opaque": [],
    }
    for mid, info in sorted(materials.items()):
        if info.get("opaque"):
            if opaque_total[mid]:
                errs = sorted(opaque_err[mid])
                out["opaque"].append({
                    "id": mid,
                    "not_flagged": 1.0 - opaque_flagged[mid] / opaque_total[mid],
                    "median_error_mm": errs[len(errs) // 2] if errs else None,
                    "kept_share": len(errs) / opaque_total[mid],
                })
            continue
        votes = region_votes.get(mid)
        rid = votes.most_common(1)[0][0] if votes else None
        e = est.get(rid) if rid is not None else None
        row = {"id": mid, "xi_true": info["xi"], "poses": len(stages[mid]), "region": rid}
        if e:
            lo, hi = e["xi_interval"]
            row.update({"xi": e["xi"], "xi_interval": [lo, hi], "inside": lo <= info["xi"] <= hi, "width": hi - lo,
                        "opaque_claimed": e["opaque"]})
        out["materials"].append(row)
    return out


def fmt(v, spec=".1f"):
    return "-" if v is None else format(v, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bags", nargs="+")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--replay-arg", action="append", default=[], help="an argument for replay (repeat)")
    ap.add_argument("--exe", default=os.path.join(REPO, "target", "release", "translucent_tof"))
    a = ap.parse_args()
    rows = []
    for i, bag in enumerate(a.bags):
        if sys.stderr.isatty():
            print(f"[{i + 1}/{len(a.bags)}] {os.path.basename(bag)}", file=sys.stderr)
        r = evaluate(bag, a.replay_arg, a.exe)
        rows.append(r)
        if "error" in r:
            print(f"{r['bag']}: replay failed: {r['error']}")
            continue
        mats = "; ".join(
            f"xi {m['xi_true']:.2f}: {fmt(m.get('xi'), '.3f')} [{fmt((m.get('xi_interval') or [None])[0], '.2f')}, "
            f"{fmt((m.get('xi_interval') or [None, None])[1], '.2f')}]{'' if m.get('inside') else ' MISS'}"
            for m in r["materials"]
        )
        opq = "; ".join(
            f"opaque {o['id']}: {100 * o['not_flagged']:.0f} % unflagged, median {fmt(o['median_error_mm'])} mm"
            for o in r["opaque"]
        )
        print(
            f"{r['bag']}: raw {fmt(r['mean_frame_rms_raw_mm'])} -> {fmt(r['mean_frame_rms_mm'])} mm "
            f"(recovered {fmt(None if r['recovered_share'] is None else 100 * r['recovered_share'], '.0f')} %); "
            f"{mats}{'; ' + opq if opq else ''}; "
            f"within 2 sigma {fmt(100 * r['within_2sigma'][0] / r['within_2sigma'][1] if r['within_2sigma'][1] else None, '.0f')} %"
        )
    ok = [m for r in rows for m in r.get("materials", []) if "inside" in m]
    if ok:
        inside = sum(m["inside"] for m in ok)
        print(f"coverage: {inside} of {len(ok)} materials' true xi inside their interval "
              f"({100 * inside / len(ok):.0f} %); median width {statistics.median(m['width'] for m in ok):.2f}")
    w = [r["within_2sigma"] for r in rows if r.get("within_2sigma", [0, 0])[1]]
    if w:
        shares = [a / b for a, b in w]
        print(f"sigma: {100 * sum(a for a, _ in w) / sum(b for _, b in w):.1f} % of recovered pixels within 2 sigma "
              f"(pooled over {len(w)} bags; per bag median {100 * statistics.median(shares):.0f} %, "
              f"range {100 * min(shares):.0f}-{100 * max(shares):.0f} %)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
