#!/usr/bin/env python3
"""Which class each object of a rendered scene is given with a materials file.

    .venv/bin/python scripts/classes.py --exe target/release/translucent_tof \\
        --materials FILE bags/rendered/two_materials.mcap [more bags] [-- replay options]

Replays each bag with `--materials FILE` and, for every object frame and every true
material in it (the bag's `ground_truth/material` image and its sidecar `.toml`), finds the
region that covers most of that material's pixels (replay's `regions` image) and the class
replay gave that region (its JSON `per_frame[].regions[]`). A frame's object is right when
the class is the material's name, or `opaque` for an opaque material. Prints one line per
frame and material, and a count; exits 1 when any is wrong or unclassified.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import tomllib
from collections import Counter

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from results import image_values, read  # noqa: E402


def classes(bag, exe, materials_file, replay_args):
    side = tomllib.load(open(os.path.splitext(bag)[0] + ".toml", "rb"))
    truth = {m["id"]: m for m in side.get("materials", [])}
    with tempfile.TemporaryDirectory() as tmp:
        out_bag, out_json = os.path.join(tmp, "out.mcap"), os.path.join(tmp, "report.json")
        cmd = [exe, "replay", bag, "--out", out_bag, "--json", out_json, "--materials", materials_file, *replay_args]
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)}: {run.stderr.strip()}")
        report = json.load(open(out_json))
        gt = read(bag, ["ground_truth/material"])["ground_truth/material"]
        regions = read(out_bag, ["regions"])["regions"]
    per_stamp = {round(r["stamp"] * 1e9): r for r in report["per_frame"]}
    rows = []
    for stamp, msg in sorted(gt.items()):
        if stamp not in regions:
            continue
        mat, reg = image_values(msg), image_values(regions[stamp])
        frame = per_stamp.get(stamp)
        for mid, info in sorted(truth.items()):
            votes = Counter(r for m, r in zip(mat, reg) if m == mid and r)
            pixels = sum(1 for m in mat if m == mid)
            if not pixels:
                continue
            want = "opaque" if info.get("opaque") else info["name"]
            row = {"bag": os.path.basename(bag), "stamp_s": stamp * 1e-9, "material": info["name"], "want": want,
                   "pixels": pixels, "object": None, "class": None, "probability": None, "xi": None}
            if votes and frame:
                rid, n = votes.most_common(1)[0]
                row.update({"object": rid, "covered": n / pixels})
                for r in frame.get("regions", []):
                    if r["id"] == rid:
                        row.update({"class": r.get("material"), "probability": r.get("class_probability"),
                                    "xi": r["xi"], "xi_interval": r["xi_interval"]})
                        break
            row["right"] = row["class"] == want
            rows.append(row)
    return report, rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exe", required=True)
    ap.add_argument("--materials", required=True)
    ap.add_argument("--json")
    ap.add_argument("bags", nargs="+")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args = ap.parse_args(argv[:cut])
    replay_args = argv[cut + 1:]
    everything, wrong = [], 0
    for bag in args.bags:
        report, rows = classes(bag, args.exe, args.materials, replay_args)
        for r in rows:
            p = "-" if r["probability"] is None else f"{r['probability']:.2f}"
            xi = "-" if r["xi"] is None else f"{r['xi']:.3f}"
            print(f"{r['bag']} t={r['stamp_s']:.1f}s {r['material']:>14}: object {r['object']}, class {r['class']} "
                  f"(p {p}), xi {xi}, want {r['want']}: {'right' if r['right'] else 'WRONG'}")
            wrong += not r["right"]
        for m in report.get("materials", []):
            c = m.get("class", {})
            print(f"  {os.path.basename(bag)} object {m['id']}: {m['frames']} frame(s), class {c.get('material')} "
                  f"(p {c.get('probability', float('nan')):.2f}) {c.get('note', '')}")
        print(f"  {os.path.basename(bag)}: {report.get('error_summary')}")
        everything += rows
    print(f"{len(everything) - wrong} of {len(everything)} object frames classified right")
    if args.json:
        json.dump(everything, open(args.json, "w"), indent=1)
    sys.exit(1 if wrong else 0)


if __name__ == "__main__":
    main()
