"""Measures `translucent_tof replay` on ground-truthed bags against their truth.

usage: results.py [--json OUT] [--check BASELINE] [--write-baseline OUT] [--markdown]
                  [--exe EXE] [--replay-arg ARG ...] [BAG...]

With no BAG, every rendered scene in bags/rendered, the videos (video_*) among
them (but the white wall, the calibration sequence and the per-material
calibrations calib_*, which hold no scene to recover, and the multi-frequency
versions mf_*, which are scored when named).

Each BAG is replayed with the given replay arguments (none: the defaults a user
gets); its sidecar `BAG.toml` names the materials (`[[materials]]`: id, xi,
opaque) and the bag carries `ground_truth/depth` (z, m) and
`ground_truth/material` (mono8: 0 background, else the material's id).

Per bag it reports:
- the mean over frames of the per-frame RMS z error (mm) over the pixels of
  translucent materials that are in the mask and have a recovered depth, the
  same for the raw reading over those pixels, and the share of the
  translucent materials' pixels that got a recovered depth;
- the same mean over frames of the per-frame RMS z error over *every* pixel
  of a translucent material with truth, and every pixel off them that was
  corrected (in the mask: on the background, whose truth is the median of
  the bag's background frames' readings, or on an opaque object)
  (`all_pixels_rms_mm`): the published depth where it was corrected, the
  reading where it was left as read (a frame the pipeline passed through
  counts at its reading), beside the raw reading's over the same pixels
  (`all_pixels_rms_raw_mm`): the figure that says whether a scene came out
  worse than raw;
- the corrections off every translucent object on their own (pixels in
  the mask, or published otherwise than read): pixels a frame, and the
  mean per-frame RMS error there, published and raw
  (`off_object_pixels`, `off_object_rms_mm`, `off_object_rms_raw_mm`): a
  mixed pixel on an object's outline whose centre sees the background is
  the background's;
- per translucent material: the ξ estimate of the region its pixels mostly
  fell in, its interval, whether the truth lies inside, the poses seen, and
  the every-pixel figure over its own pixels (`rms_mm` beside `rms_raw_mm`:
  whether that object came out worse than raw);
- per opaque material: the share of its pixels not in the mask, the
  median |z error| (mm) of the published depth there beside the reading's, and whether the
  interval of the region it fell in holds 0 (opaque);
- over those recovered pixels, the share whose error lies within twice the
  published standard deviation (`depth/corrected_sigma`), and pooled over
  every bag at the end.

Over the set: coverage (an interval holding the truth, no [0, 1] counted as
a hit), the determined share (of the translucent objects seen at two or more
distances 100 mm apart, those given an interval no wider than 0.3),
informative coverage (of those, the share that hold the truth) and their
median width, and the mean every-pixel error over the scenes against raw.

`--check BASELINE` compares the run with a committed baseline (the rows of an
earlier run and the failures known then) and exits 1 on a failure that is
not known: a scene or a translucent object worse than raw, an opaque object flagged or moved, a
paper setup above the paper's figure, coverage, the determined share,
informative coverage or σ below their stated levels, a scene or object
worse than the baseline beyond 1 % (replays are deterministic), a figure
the baseline had that this run gives as None, or (with no bag named) a
bag of the baseline missing from the run.
`--write-baseline OUT` writes this run as a baseline, its failures as the
known ones.
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
# The release binary cargo builds: under CARGO_TARGET_DIR when set (relative to the repository,
# where scripts/results runs cargo), else target/.
RELEASE_EXE = os.path.join(REPO, os.environ.get("CARGO_TARGET_DIR") or "target", "release", "translucent_tof")


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
        # a scene may need options of its own (a moving camera's bag: --no-latch)
        cmd = [exe, "replay", bag, "--out", out_bag, "--json", out_json, *replay_args, *side.get("replay_args", [])]
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode != 0:
            return {"bag": os.path.basename(bag), "error": run.stderr.strip()}
        report = json.load(open(out_json))
        inp = read(bag, ["ground_truth/depth", "ground_truth/material", "depth/image_raw"])
        res = read(out_bag, ["depth/corrected", "translucent_mask", "regions", "depth/corrected_sigma",
                             "translucency_image"])
    background = latched_background(side, inp, replay_args)
    multi = report.get("path") == "multi_frequency"
    # With no background latched (a moving camera's --no-latch) the path measures no xi.
    xi_measured = not multi or report.get("multi_frequency", {}).get("latched", True)
    # The multi-frequency path has no tracking: its regions (and their ids) are each frame's own.
    frame_regions = {round(f["stamp"] * 1e9): {g["id"]: g for g in f.get("regions", [])}
                     for f in report.get("per_frame", [])}
    frame_votes = defaultdict(lambda: defaultdict(Counter))  # stamp -> material -> region id -> pixels
    pixel_xi = defaultdict(list)  # material -> per frame the median of its pixels' xi (translucency_image)
    est = {m["id"]: m for m in report.get("materials", [])}
    frame_rms, frame_raw, covered, total = [], [], 0, 0
    every_rms, every_raw = [], []
    within_2sigma, with_sigma = 0, 0
    off_rms, off_raw, off_pixels = [], [], []
    region_votes = defaultdict(Counter)
    opaque_flagged, opaque_total, opaque_err = defaultdict(int), defaultdict(int), defaultdict(list)
    opaque_raw_err = defaultdict(list)
    # Each translucent material's per-frame RMS over its pixels with truth: published, raw.
    object_rms, object_raw = defaultdict(list), defaultdict(list)
    # The same away from the object's outline (no 8-neighbour of another material): what
    # is left where a pixel holds one object, not two.
    inner_rms, inner_raw = defaultdict(list), defaultdict(list)
    object_sigma = defaultdict(lambda: [0, 0])  # material -> [within 2 sigma, with a sigma]
    width = side.get("sensor", {}).get("width")
    stages = defaultdict(set)
    for stamp, truth_msg in sorted(inp["ground_truth/depth"].items()):
        if stamp not in inp["ground_truth/material"] or stamp not in inp["depth/image_raw"]:
            continue
        mat = image_values(inp["ground_truth/material"][stamp])
        if not any(m in materials for m in mat):
            continue  # background frames: nothing to recover
        truth = [x * 1000.0 if math.isfinite(x) else math.nan for x in image_values(truth_msg)]
        raw = z_mm(inp["depth/image_raw"][stamp])
        corr = res["depth/corrected"].get(stamp)
        # A frame with no output (no estimate yet) is published as read (the node passes it through).
        z = z_mm(corr) if corr is not None else raw
        mask = image_values(res["translucent_mask"][stamp]) if stamp in res["translucent_mask"] else [0] * len(z)
        regions = image_values(res["regions"][stamp]) if stamp in res["regions"] else [0] * len(z)
        sigma = z_mm(res["depth/corrected_sigma"][stamp]) if stamp in res["depth/corrected_sigma"] else [math.nan] * len(z)
        xi_img = image_values(res["translucency_image"][stamp]) if stamp in res["translucency_image"] else None
        frame_xi = defaultdict(list)
        obj_sq = defaultdict(lambda: [0.0, 0.0, 0])
        inner_sq = defaultdict(lambda: [0.0, 0.0, 0])
        e2, r2, n = 0.0, 0.0, 0
        a2, ar2, an = 0.0, 0.0, 0
        off = [0.0, 0.0, 0]
        for i, m in enumerate(mat):
            info = materials.get(m)
            if info is None or info.get("opaque"):
                # Off every translucent object: a correction here (a pixel in the mask, or
                # one published otherwise than read) is measured against the truth (an
                # opaque object's, or the latched background's reading).
                t = truth[i] if math.isfinite(truth[i]) else (background[i] if background else math.nan)
                finite = math.isfinite(t) and math.isfinite(z[i]) and math.isfinite(raw[i])
                if corr is not None and finite and (mask[i] or abs(z[i] - raw[i]) > 0.5):
                    off[0] += (z[i] - t) ** 2
                    off[1] += (raw[i] - t) ** 2
                    off[2] += 1
            if info is None or not math.isfinite(truth[i]):
                continue
            # A pixel published unmeasured (NaN) where the camera read it counts at its reading:
            # abstaining is no better than the raw reading, never left out of the figure.
            zi = z[i] if math.isfinite(z[i]) else raw[i]
            if regions[i]:
                region_votes[m][regions[i]] += 1
                frame_votes[stamp][m][regions[i]] += 1
            if xi_img is not None and math.isfinite(xi_img[i]):
                frame_xi[m].append(xi_img[i])
            if info.get("opaque"):
                opaque_total[m] += 1
                opaque_flagged[m] += mask[i] > 0
                if math.isfinite(z[i]):
                    opaque_err[m].append(abs(z[i] - truth[i]))
                if math.isfinite(raw[i]):
                    opaque_raw_err[m].append(abs(raw[i] - truth[i]))
                continue
            total += 1
            if math.isfinite(zi) and math.isfinite(raw[i]):
                a2 += (zi - truth[i]) ** 2
                ar2 += (raw[i] - truth[i]) ** 2
                an += 1
                inner = width and not on_outline(mat, i, width)
                for o in (obj_sq[m], inner_sq[m]) if inner else (obj_sq[m],):
                    o[0] += (zi - truth[i]) ** 2
                    o[1] += (raw[i] - truth[i]) ** 2
                    o[2] += 1
            if corr is not None and mask[i] and math.isfinite(z[i]):
                covered += 1
                if math.isfinite(sigma[i]):
                    with_sigma += 1
                    within_2sigma += abs(z[i] - truth[i]) <= 2.0 * sigma[i]
                    object_sigma[m][0] += abs(z[i] - truth[i]) <= 2.0 * sigma[i]
                    object_sigma[m][1] += 1
                e2 += (z[i] - truth[i]) ** 2
                r2 += (raw[i] - truth[i]) ** 2 if math.isfinite(raw[i]) else 0.0
                n += 1
        for m in set(mat):
            if m in materials and not materials[m].get("opaque"):
                ts = [t for t, k in zip(truth, mat) if k == m and math.isfinite(t)]
                if ts:
                    stages[m].add(round(statistics.median(ts), -1))
        for m, v in frame_xi.items():
            if not materials[m].get("opaque"):
                pixel_xi[m].append(statistics.median(v))
        for m, (e, r_, k) in obj_sq.items():
            object_rms[m].append(math.sqrt(e / k))
            object_raw[m].append(math.sqrt(r_ / k))
        for m, (e, r_, k) in inner_sq.items():
            inner_rms[m].append(math.sqrt(e / k))
            inner_raw[m].append(math.sqrt(r_ / k))
        if n:
            frame_rms.append(math.sqrt(e2 / n))
            frame_raw.append(math.sqrt(r2 / n))
        if off[2]:
            off_rms.append(math.sqrt(off[0] / off[2]))
            off_raw.append(math.sqrt(off[1] / off[2]))
        off_pixels.append(off[2])
        # Every pixel counts what was published wrongly off the objects too.
        a2, ar2, an = a2 + off[0], ar2 + off[1], an + off[2]
        if an:
            every_rms.append(math.sqrt(a2 / an))
            every_raw.append(math.sqrt(ar2 / an))
    out = {
        "bag": os.path.basename(bag),
        "description": side.get("description", ""),
        "frames": len(every_rms),
        "mean_frame_rms_mm": statistics.fmean(frame_rms) if frame_rms else None,
        "mean_frame_rms_raw_mm": statistics.fmean(frame_raw) if frame_raw else None,
        "all_pixels_rms_mm": statistics.fmean(every_rms) if every_rms else None,
        "all_pixels_rms_raw_mm": statistics.fmean(every_raw) if every_raw else None,
        "recovered_share": covered / total if total else None,
        # corrections off every translucent object: pixels per frame, and their mean per-frame RMS
        "off_object_pixels": statistics.fmean(off_pixels) if off_pixels else None,
        "off_object_rms_mm": statistics.fmean(off_rms) if off_rms else None,
        "off_object_rms_raw_mm": statistics.fmean(off_raw) if off_raw else None,
        "within_2sigma": [within_2sigma, with_sigma],
        "materials": [],
        "opaque": [],
    }
    if multi:
        out["path"] = "multi_frequency"
    for mid, info in sorted(materials.items()):
        votes = region_votes.get(mid)
        rid = votes.most_common(1)[0][0] if votes else None
        e = est.get(rid) if rid is not None else None
        per_frame = []
        if multi:
            # each frame: the region most of the object's pixels fell in, its xi and interval
            e, rid = None, None
            for stamp in sorted(frame_votes) if xi_measured else []:
                v = frame_votes[stamp].get(mid)
                g = frame_regions.get(stamp, {}).get(v.most_common(1)[0][0]) if v else None
                if g is None or not g.get("xi_interval") or g.get("xi") is None:
                    continue  # no region, or xi not measured (no background latched)
                lo, hi = g["xi_interval"]
                truth = 0.0 if info.get("opaque") else info["xi"]
                per_frame.append({"xi": g["xi"], "xi_interval": [lo, hi], "inside": lo <= truth <= hi,
                                  "width": hi - lo, "opaque_claimed": g.get("opaque", False)})
        if info.get("opaque"):
            if opaque_total[mid]:
                errs, raws = sorted(opaque_err[mid]), sorted(opaque_raw_err[mid])
                row = {
                    "id": mid,
                    "not_flagged": 1.0 - opaque_flagged[mid] / opaque_total[mid],
                    "median_error_mm": errs[len(errs) // 2] if errs else None,
                    "median_raw_error_mm": raws[len(raws) // 2] if raws else None,
                    "kept_share": len(errs) / opaque_total[mid],
                    "region": rid,
                }
                if e:
                    lo, hi = e["xi_interval"]
                    # Opaque is xi 0: the interval must hold it.
                    row.update({"xi": e["xi"], "xi_interval": [lo, hi], "inside": lo <= 0.0, "width": hi - lo})
                if per_frame:
                    row.update(frames_mf(per_frame))
                out["opaque"].append(row)
            continue
        row = {"id": mid, "xi_true": info["xi"], "poses": len(stages[mid]), "distances": distinct(stages[mid]),
               "region": rid}
        if object_rms.get(mid):
            # every pixel of the object with truth: the mean over frames of each frame's RMS
            row["rms_mm"] = statistics.fmean(object_rms[mid])
            row["rms_raw_mm"] = statistics.fmean(object_raw[mid])
        if object_sigma[mid][1]:
            row["within_2sigma"] = object_sigma[mid]
        if inner_rms.get(mid):
            row["rms_inner_mm"] = statistics.fmean(inner_rms[mid])
            row["rms_inner_raw_mm"] = statistics.fmean(inner_raw[mid])
        if not xi_measured:
            row["xi_not_measured"] = True
        if e:
            lo, hi = e["xi_interval"]
            row.update({"xi": e["xi"], "xi_interval": [lo, hi], "inside": lo <= info["xi"] <= hi, "width": hi - lo, "note": e.get("note"),
                        "opaque_claimed": e["opaque"]})
        if per_frame:
            row.update(frames_mf(per_frame))
        if pixel_xi.get(mid):
            row["xi_pixel_median"] = statistics.median(pixel_xi[mid])  # median over frames of each frame's median
            row["xi_pixel_frame_medians"] = [min(pixel_xi[mid]), max(pixel_xi[mid])]
        out["materials"].append(row)
    return out


def distinct(medians, apart_mm=100.0):
    """How many of an object's poses (median true depths) lie `apart_mm` or more from the
    nearer one kept: the distances it was seen at."""
    kept = []
    for d in sorted(medians):
        if not kept or d - kept[-1] >= apart_mm:
            kept.append(d)
    return len(kept)


def on_outline(mat, i, width):
    """Whether pixel `i` has an 8-neighbour of another material (or of none)."""
    r, c = divmod(i, width)
    height = len(mat) // width
    return any(0 <= r + dr < height and 0 <= c + dc < width and mat[(r + dr) * width + c + dc] != mat[i]
               for dr in (-1, 0, 1) for dc in (-1, 0, 1))


def latched_background(side, inp, replay_args):
    """The background's depth per pixel (mm), the median of the bag's background frames'
    readings: the truth behind the objects where the render gives none. None where the
    scene has no still background (a moving camera's replay takes no latch)."""
    n = side.get("background_frames", 0)
    if not n or "--no-latch" in [*replay_args, *side.get("replay_args", [])]:
        return None
    frames = [z_mm(inp["depth/image_raw"][st]) for st in sorted(inp["depth/image_raw"])[:n]]
    return [statistics.median(v) if all(math.isfinite(x) for x in v) else math.nan for v in zip(*frames)]


def frames_mf(per_frame):
    """A multi-frequency object's row: each frame's region (no tracking on that path) with its
    interval, the median of their xi, and how many of the intervals hold the truth."""
    return {"xi": statistics.median(f["xi"] for f in per_frame),
            "frames_inside": [sum(f["inside"] for f in per_frame), len(per_frame)],
            "per_frame": per_frame}


def fmt(v, spec=".1f"):
    return "-" if v is None else format(v, spec)


# What the README claims, as limits (the paper's figures, the stated levels; issue texts name them).
PAPER_MM = {"paper_document_holder.mcap": 10.6, "paper_file_box.mcap": 51.7}
COVERAGE_MIN = 0.90        # intervals stated at 95 %: at least 90 % over the set
SIGMA_BAND = (0.90, 0.98)  # +-2 sigma stated at 95 %
OPAQUE_NOT_FLAGGED_MIN = 0.90
OPAQUE_KEPT_MM = 1.0  # an opaque object keeps its reading: no worse than it by more than this
# Replays are deterministic up to the order of parallel sums: beyond 1 % is a change.
NOISE_REL, NOISE_MM = 0.01, 0.05
# An object seen at two or more distances determines its xi (objects.md): an interval no
# wider than this is informative, and its stated levels.
DETERMINED_WIDTH = 0.3
DETERMINED_SHARE_MIN = 0.90
INFORMATIVE_COVERAGE_MIN = 0.90
DETERMINED_MEDIAN_WIDTH_MAX = 0.15


def worse(now, before):
    return now is not None and before is not None and now > before * (1 + NOISE_REL) + NOISE_MM


def objects(rows):
    """The objects whose interval is scored: on the multi-frequency path each frame's (no tracking)."""
    out = []
    for r in rows:
        for o in r.get("materials", []) + r.get("opaque", []):
            if "per_frame" in o:
                out += o["per_frame"]
            elif "inside" in o:
                out.append(o)
    return out


def hit(o):
    """An interval that holds the truth and says something: [0, 1] holds every xi and is no hit."""
    return bool(o.get("inside")) and o.get("width", 1.0) < 1.0


def determinable(rows):
    """The translucent objects seen at two or more distances (single-frequency: tracked), each
    with its interval or none: those whose xi the data determine (objects.md)."""
    return [m for r in rows for m in r.get("materials", [])
            if m.get("distances", 0) >= 2 and "per_frame" not in m and not m.get("xi_not_measured")]


def determined(rows):
    """(determinable objects, those given an interval no wider than DETERMINED_WIDTH, those of
    them that hold the truth)."""
    d = determinable(rows)
    narrow = [m for m in d if "width" in m and m["width"] <= DETERMINED_WIDTH]
    return d, narrow, [m for m in narrow if m.get("inside")]


def pooled_sigma(rows):
    w = [r["within_2sigma"] for r in rows if r.get("within_2sigma", [0, 0])[1]]
    return (sum(a for a, _ in w) / sum(b for _, b in w), w) if w else (None, w)


def failures(rows):
    """Every way this run falls short of a stated claim: {key: figure}."""
    out = {}
    for r in rows:
        b = r["bag"]
        if "error" in r:
            out[f"{b}:replay"] = r["error"][:200]
            continue
        now, raw = r.get("all_pixels_rms_mm"), r.get("all_pixels_rms_raw_mm")
        if now is not None and raw is not None and now > raw * 1.01 + 0.5:
            out[f"{b}:worse_than_raw"] = f"{now:.1f} mm against raw {raw:.1f} mm over every pixel"
        if b in PAPER_MM and (r.get("mean_frame_rms_mm") or math.inf) > PAPER_MM[b]:
            out[f"{b}:paper"] = f"{fmt(r.get('mean_frame_rms_mm'))} mm against the paper's {PAPER_MM[b]}"
        for m in r.get("materials", []):
            now, raw = m.get("rms_mm"), m.get("rms_raw_mm")
            if now is not None and raw is not None and now > raw * 1.01 + 0.5:
                out[f"{b}:object_{m['id']}_worse_than_raw"] = f"{now:.1f} mm against raw {raw:.1f} mm over its pixels"
        for o in r.get("opaque", []):
            if o["not_flagged"] < OPAQUE_NOT_FLAGGED_MIN:
                out[f"{b}:opaque_{o['id']}_flagged"] = f"{100 * o['not_flagged']:.0f} % not flagged"
            now, raw = o.get("median_error_mm"), o.get("median_raw_error_mm")
            if now is not None and raw is not None and now > raw + OPAQUE_KEPT_MM:
                out[f"{b}:opaque_{o['id']}_moved"] = f"median {now:.1f} mm, the reading's {raw:.1f} mm"
    obj = objects(rows)
    if obj and sum(hit(o) for o in obj) / len(obj) < COVERAGE_MIN:
        out["set:coverage"] = f"{sum(hit(o) for o in obj)} of {len(obj)} (no [0, 1] counts)"
    d, narrow, held = determined(rows)
    if d and len(narrow) / len(d) < DETERMINED_SHARE_MIN:
        out["set:determined_share"] = f"{len(narrow)} of {len(d)} objects seen at two distances or more"
    if narrow and len(held) / len(narrow) < INFORMATIVE_COVERAGE_MIN:
        out["set:informative_coverage"] = f"{len(held)} of {len(narrow)} determined intervals hold the truth"
    if narrow and statistics.median(m["width"] for m in narrow) > DETERMINED_MEDIAN_WIDTH_MAX:
        out["set:determined_width"] = f"median {statistics.median(m['width'] for m in narrow):.3f}"
    share, _ = pooled_sigma(rows)
    if share is not None and not SIGMA_BAND[0] <= share <= SIGMA_BAND[1]:
        out["set:sigma"] = f"{100 * share:.1f} % within 2 sigma"
    return out


def vanished(now, before, where):
    """The figures the baseline had that this run gives as None (or not at all): {key: note}."""
    out = {}
    for k, v in before.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool) and now.get(k) is None:
            out[f"{where}:{k}_missing"] = f"None, baseline {v:.4g}"
    return out


def regressions(rows, base_rows, whole_set=True):
    """Where this run is worse than the baseline's rows beyond noise: {key: figure}. With
    `whole_set`, a bag of the baseline missing from the run is one."""
    out = {}
    before = {r["bag"]: r for r in base_rows}
    if whole_set:
        ran = {r["bag"] for r in rows}
        for b in sorted(set(before) - ran):
            out[f"{b}:dropped"] = "in the baseline, not in this run"
    for r in rows:
        b = before.get(r["bag"])
        if b is None or "error" in r:
            continue
        out.update(vanished(r, b, r["bag"]))
        now_objects = {(o["id"], "xi_true" in o): o for o in r.get("materials", []) + r.get("opaque", [])}
        for o in b.get("materials", []) + b.get("opaque", []):
            now = now_objects.get((o["id"], "xi_true" in o), {})
            out.update(vanished(now, o, f"{r['bag']}:object_{o['id']}"))
        for key in ("all_pixels_rms_mm", "mean_frame_rms_mm"):
            if worse(r.get(key), b.get(key)):
                out[f"{r['bag']}:{key}"] = f"{r[key]:.1f} mm, baseline {b[key]:.1f} mm"
        was = {(o["id"], "xi_true" in o): o.get("inside") for o in b.get("materials", []) + b.get("opaque", [])}
        for o in r.get("materials", []) + r.get("opaque", []):
            if was.get((o["id"], "xi_true" in o)) and not o.get("inside"):
                out[f"{r['bag']}:object_{o['id']}_interval"] = f"{o.get('xi_interval')} no longer holds the truth"
    now_in, base_in = sum(hit(o) for o in objects(rows)), sum(hit(o) for o in objects(base_rows))
    if now_in < base_in:
        out["set:coverage_fell"] = f"{now_in} objects inside, baseline {base_in}"
    now_s, base_s = pooled_sigma(rows)[0], pooled_sigma(base_rows)[0]
    if now_s is not None and base_s is not None and now_s < base_s - 0.02:
        out["set:sigma_fell"] = f"{100 * now_s:.1f} %, baseline {100 * base_s:.1f} %"
    return out


def print_row(r):
    if "error" in r:
        print(f"{r['bag']}: replay failed: {r['error']}")
        return
    mats = "; ".join(
        (f"xi {m['xi_true']:.2f}: {fmt(m.get('xi'), '.3f')} (median of frames), interval holds it in "
         f"{m['frames_inside'][0]} of {m['frames_inside'][1]} frames, per-pixel median {fmt(m.get('xi_pixel_median'), '.3f')}"
         if "frames_inside" in m else
         f"xi {m['xi_true']:.2f}: not measured (no background latched)" if m.get("xi_not_measured") else
         f"xi {m['xi_true']:.2f}: {fmt(m.get('xi'), '.3f')} [{fmt((m.get('xi_interval') or [None])[0], '.2f')}, "
         f"{fmt((m.get('xi_interval') or [None, None])[1], '.2f')}]{'' if m.get('inside') else ' MISS'}")
        + (f" ({fmt(m['rms_raw_mm'])} -> {fmt(m['rms_mm'])} mm" if "rms_mm" in m else "")
        + (f", off its outline {fmt(m['rms_inner_raw_mm'])} -> {fmt(m['rms_inner_mm'])} mm" if "rms_inner_mm" in m else "")
        + (")" if "rms_mm" in m else "")
        + (f", sigma holds {100 * m['within_2sigma'][0] / m['within_2sigma'][1]:.0f} %" if m.get("within_2sigma") else "")
        for m in r["materials"]
    )
    opq = "; ".join(
        f"opaque {o['id']}: {100 * o['not_flagged']:.0f} % unflagged, median {fmt(o['median_error_mm'])} mm "
        f"(reading {fmt(o.get('median_raw_error_mm'))} mm)"
        + (f", interval holds 0 in {o['frames_inside'][0]} of {o['frames_inside'][1]} frames" if "frames_inside" in o
           else f"{'' if o.get('inside', True) else ' (interval excludes 0)'}")
        for o in r["opaque"]
    )
    print(
        f"{r['bag']}: raw {fmt(r['mean_frame_rms_raw_mm'])} -> {fmt(r['mean_frame_rms_mm'])} mm over recovered pixels "
        f"(recovered {fmt(None if r['recovered_share'] is None else 100 * r['recovered_share'], '.0f')} %), "
        f"every pixel {fmt(r['all_pixels_rms_raw_mm'])} -> {fmt(r['all_pixels_rms_mm'])} mm; "
        f"{mats}{'; ' + opq if opq else ''}; "
        + (f"corrected off the objects {r['off_object_pixels']:.0f} px a frame ({fmt(r['off_object_rms_raw_mm'])} -> "
           f"{fmt(r['off_object_rms_mm'])} mm); " if r.get("off_object_pixels") else "")
        + f"within 2 sigma {fmt(100 * r['within_2sigma'][0] / r['within_2sigma'][1] if r['within_2sigma'][1] else None, '.0f')} %"
    )


def print_summary(rows):
    obj = objects(rows)
    if obj:
        inside = sum(hit(o) for o in obj)
        print(f"coverage: {inside} of {len(obj)} objects' true xi inside an interval narrower than [0, 1] "
              f"({100 * inside / len(obj):.0f} %; opaque objects count when the interval holds 0; "
              f"on the multi-frequency path each frame's region counts); "
              f"median width {statistics.median(o['width'] for o in obj):.2f}")
    d, narrow, held = determined(rows)
    if d:
        widths = sorted(m["width"] for m in narrow)
        print(f"determined: {len(narrow)} of {len(d)} objects seen at two or more distances "
              f"({100 * len(narrow) / len(d):.0f} %) got an interval no wider than {DETERMINED_WIDTH}"
              + (f" (median width {statistics.median(widths):.3f}); informative coverage: {len(held)} of "
                 f"{len(narrow)} hold the truth ({100 * len(held) / len(narrow):.0f} %)" if narrow else ""))
    every = [(r["all_pixels_rms_mm"], r["all_pixels_rms_raw_mm"]) for r in rows
             if r.get("all_pixels_rms_mm") is not None and r.get("all_pixels_rms_raw_mm")]
    if every:
        print(f"every pixel: mean over scenes {statistics.fmean(a for a, _ in every):.1f} mm against raw "
              f"{statistics.fmean(b for _, b in every):.1f} mm; scenes at or within 1 % of raw (nothing gained): "
              f"{sum(a >= 0.99 * b for a, b in every)} of {len(every)}")
    share, w = pooled_sigma(rows)
    if share is not None:
        shares = [a / b for a, b in w]
        print(f"sigma: {100 * share:.1f} % of recovered pixels within 2 sigma "
              f"(pooled over {len(w)} bags; per bag median {100 * statistics.median(shares):.0f} %, "
              f"range {100 * min(shares):.0f}-{100 * max(shares):.0f} %)")


def markdown(rows):
    print("| bag | true ξ: estimate [interval] (its pixels: raw → published, mm) | recovered pixels: raw → recovered, mm (share) | every pixel: raw → published, mm | corrected off the objects: pixels a frame (raw → published, mm) | opaque objects |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        if "error" in r:
            print(f"| `{r['bag']}` | replay failed | | | | |")
            continue
        mats = "; ".join(
            f"{m['xi_true']:.2f}: {fmt(m.get('xi'), '.3f')} [{fmt((m.get('xi_interval') or [None])[0], '.3f')}, "
            f"{fmt((m.get('xi_interval') or [None, None])[1], '.3f')}]{'' if m.get('inside') else ' ✗'}"
            + (f" ({fmt(m['rms_raw_mm'])} → {fmt(m['rms_mm'])})" if "rms_mm" in m else "")
            for m in r["materials"]) or "-"
        opq = "; ".join(f"{100 * o['not_flagged']:.0f} % not flagged, median error {fmt(o['median_error_mm'])} mm "
                        f"(reading {fmt(o.get('median_raw_error_mm'))})" for o in r["opaque"]) or "-"
        share = "-" if r["recovered_share"] is None else f"{100 * r['recovered_share']:.0f} %"
        off = (f"{r['off_object_pixels']:.0f} ({fmt(r.get('off_object_rms_raw_mm'))} → {fmt(r.get('off_object_rms_mm'))})"
               if r.get("off_object_pixels") else "0")
        print(f"| `{os.path.splitext(r['bag'])[0]}` | {mats} | {fmt(r['mean_frame_rms_raw_mm'])} → {fmt(r['mean_frame_rms_mm'])} ({share}) "
              f"| {fmt(r['all_pixels_rms_raw_mm'])} → {fmt(r['all_pixels_rms_mm'])} | {off} | {opq} |")


def default_bags():
    """Every rendered scene (the draws, the named scenes, the videos), but the
    recordings that hold no scene to recover: the empty wall (calibrate-lin's),
    the calibration sequence (the audit's) and the per-material calibrations
    (calib_*: calibrate-xi's). The multi-frequency versions (mf_*) are not among
    them: name them (`results.py bags/rendered/mf_*.mcap`)."""
    d = os.path.join(REPO, "bags", "rendered")
    skip = {"white_wall_lin.mcap", "calibration_sequence.mcap"}
    return [os.path.join(d, f) for f in sorted(os.listdir(d))
            if f.endswith(".mcap") and f not in skip and not f.startswith(("calib_", "mf_"))]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bags", nargs="*")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--check", help="a baseline to hold this run to (exit 1 on a failure not known there)")
    ap.add_argument("--write-baseline", help="write this run as a baseline, its failures as the known ones")
    ap.add_argument("--markdown", action="store_true", help="also print the rows as the README's table")
    ap.add_argument("--replay-arg", action="append", default=[], help="an argument for replay (repeat)")
    ap.add_argument("--exe", default=RELEASE_EXE)
    a = ap.parse_args()
    bags = a.bags or default_bags()
    rows = []
    for i, bag in enumerate(bags):
        if sys.stderr.isatty():
            print(f"[{i + 1}/{len(bags)}] {os.path.basename(bag)}", file=sys.stderr)
        r = evaluate(bag, a.replay_arg, a.exe)
        rows.append(r)
        print_row(r)
    print_summary(rows)
    if a.markdown:
        markdown(rows)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)
    fails = failures(rows)
    if a.write_baseline:
        with open(a.write_baseline, "w") as f:
            json.dump({"replay_args": a.replay_arg, "known_failures": fails, "rows": rows}, f, indent=1)
    if not a.check:
        for k, v in sorted(fails.items()):
            print(f"falls short: {k}: {v}")
        return 0
    base = json.load(open(a.check))
    known = base.get("known_failures", {})
    fails.update(regressions(rows, base.get("rows", []), whole_set=not a.bags))
    new = {k: v for k, v in fails.items() if k not in known}
    for k, v in sorted(fails.items()):
        print(f"{'known' if k in known else 'FAILED'}: {k}: {v}")
    for k in sorted(set(known) - set(fails)):
        print(f"no longer fails (remove from the baseline's known failures): {k}")
    print(f"check: {len(rows)} scenes, {len(new)} failed, {len(fails) - len(new)} known failures, "
          f"{len(set(known) - set(fails))} known failures that no longer occur")
    return 1 if new else 0


if __name__ == "__main__":
    sys.exit(main())
