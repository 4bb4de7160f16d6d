"""Checks or rewrites the README's generated figures from the commands that print them.

usage: readme_figures.py [--write] [--exe EXE] [--rows RUN=FILE ...] [--demo-log FILE]
                         [--skip RUN ...] [--readme FILE] [--list]

Every figure of the README's results, the demo's lines and the limits list stands
between `<!--f:KEY-->` and `<!--/f-->` (HTML comments: not shown on the rendered
page). KEY is `RUN:WHAT`; RUN names one of the commands below, WHAT what to print
of its rows (`--list` shows every key in the README with its value):

  default  scripts/results                                   (every rendered scene, the defaults)
  online   scripts/results --xi-mode online                  (the same, as the node estimates)
  mf       scripts/results bags/rendered/mf_two_materials.mcap bags/rendered/mf_opaque_and_translucent.mcap
  moving   scripts/results bags/rendered/mf_moving_camera.mcap
  demo     translucent_tof demo                              (its summary lines)

WHAT, for a results run (scripts/results.py says what each figure measures):
  table, summary          the README's table (`--markdown`) and the set's lines
  set:every               every pixel, mean over scenes against raw
  set:nothing_gained      scenes at or within 1 % of raw, of all
  set:determined          objects seen at two or more distances given an interval <= 0.3
  set:informative         of those, the ones whose interval holds the truth
  set:sigma               share of recovered pixels within 2 sigma
  BAG:every               every pixel, raw -> published
  BAG:recovered           recovered pixels, raw -> recovered (share)
  BAG:off                 corrections off the objects, pixels a frame (raw -> published)
  BAG:mN:xi               material N's (from 0) estimate [interval]
  BAG:mN:every            material N's own pixels, raw -> published
  BAG:mN:inner            the same away from its outline
  BAG:oN:unflagged        opaque object N's pixels left out of the mask
and for the demo: `demo:lines`.

With no --write, exits 1 naming each figure that differs from what its command
prints now. --write rewrites them in place. --rows RUN=FILE takes the run's rows
from a file `results.py --json` wrote (what tests/rendered_scenes.rs does, so the
check replays nothing); runs not given are replayed (minutes each), or skipped
with --skip RUN. --demo-log FILE takes the demo's summary from a file that holds
its output.
"""

import argparse
import contextlib
import difflib
import io
import json
import os
import re
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "scripts"))
import results  # noqa: E402  (the formatting of scripts/results itself)

RENDERED = os.path.join(REPO, "bags", "rendered")
RUNS = {
    "default": ([], []),
    "online": (["--replay-arg=--xi-mode", "--replay-arg=online"], []),
    "mf": ([], ["mf_two_materials.mcap", "mf_opaque_and_translucent.mcap"]),
    "moving": ([], ["mf_moving_camera.mcap"]),
}
DEMO_PREFIXES = ("demo over DDS on loopback:", "xi = ", "error against ground truth")
SPAN = re.compile(r"<!--f:([^>]*?)-->(.*?)<!--/f-->", re.S)


def run_results(name, exe):
    args, bags = RUNS[name]
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "rows.json")
        cmd = [sys.executable, os.path.join(REPO, "scripts", "results.py"), "--exe", exe, "--json", out,
               *args, *[os.path.join(RENDERED, b) for b in bags]]
        print(f"readme-figures: running {name}: {' '.join(cmd)}", file=sys.stderr)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        return json.load(open(out))


def run_demo(exe):
    with tempfile.TemporaryDirectory() as tmp:
        print("readme-figures: running the demo", file=sys.stderr)
        p = subprocess.run([exe, "demo", "--out-dir", tmp], cwd=REPO, check=True, capture_output=True, text=True)
        return p.stdout + p.stderr


def demo_lines(log):
    lines = [ln for ln in log.splitlines() if ln.startswith(DEMO_PREFIXES)]
    if len(lines) != len(DEMO_PREFIXES):
        raise SystemExit(f"the demo's output lacks its summary lines:\n{log}")
    return "```\n" + "\n".join(lines) + "\n```"


def f1(v):
    return results.fmt(v)


def pair(raw, now, unit=" mm"):
    return f"{f1(raw)} → {f1(now)}{unit}"


def captured(fn, rows):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        fn(rows)
    return buf.getvalue().rstrip("\n")


def set_figure(rows, what):
    if what == "every":
        every = [(r["all_pixels_rms_mm"], r["all_pixels_rms_raw_mm"]) for r in rows
                 if r.get("all_pixels_rms_mm") is not None and r.get("all_pixels_rms_raw_mm")]
        return f"{sum(a for a, _ in every) / len(every):.1f} mm against {sum(b for _, b in every) / len(every):.1f} mm raw"
    if what == "nothing_gained":
        every = [(r["all_pixels_rms_mm"], r["all_pixels_rms_raw_mm"]) for r in rows
                 if r.get("all_pixels_rms_mm") is not None and r.get("all_pixels_rms_raw_mm")]
        return f"{sum(a >= 0.99 * b for a, b in every)} of {len(every)}"
    if what in ("determined", "informative"):
        d, narrow, held = results.determined(rows)
        return f"{len(narrow)} of {len(d)}" if what == "determined" else f"{len(held)} of {len(narrow)}"
    if what == "sigma":
        share, _ = results.pooled_sigma(rows)
        return f"{100 * share:.1f} %"
    raise KeyError(what)


def row_figure(rows, bag, what):
    row = next((r for r in rows if os.path.splitext(r["bag"])[0] == bag), None)
    if row is None:
        raise KeyError(f"no row for {bag}")
    if what == ["every"]:
        return pair(row["all_pixels_rms_raw_mm"], row["all_pixels_rms_mm"])
    if what == ["recovered"]:
        share = row["recovered_share"]
        return (pair(row["mean_frame_rms_raw_mm"], row["mean_frame_rms_mm"])
                + f" ({'-' if share is None else f'{100 * share:.0f} %'})")
    if what == ["off"]:
        return (f"{row.get('off_object_pixels') or 0:.0f} pixels a frame "
                f"({pair(row.get('off_object_rms_raw_mm'), row.get('off_object_rms_mm'))})")
    kind, n = what[0][0], int(what[0][1:])
    item = row["materials" if kind == "m" else "opaque"][n]
    if what[1:] == ["xi"]:
        lo, hi = item["xi_interval"]
        return f"{results.fmt(item['xi'], '.3f')} [{results.fmt(lo, '.3f')}, {results.fmt(hi, '.3f')}]"
    if what[1:] == ["every"]:
        return pair(item["rms_raw_mm"], item["rms_mm"])
    if what[1:] == ["inner"]:
        return pair(item["rms_inner_raw_mm"], item["rms_inner_mm"])
    if what[1:] == ["unflagged"]:
        return f"{100 * item['not_flagged']:.0f} %"
    raise KeyError(":".join(what))


def figure(key, runs):
    run, _, what = key.partition(":")
    data = runs[run]
    if run == "demo":
        if what != "lines":
            raise KeyError(key)
        return demo_lines(data)
    if what == "table":
        return captured(results.markdown, data)
    if what == "summary":
        return "```\n" + captured(results.print_summary, data) + "\n```"
    parts = what.split(":")
    if parts[0] == "set":
        return set_figure(data, parts[1])
    return row_figure(data, parts[0], parts[1:])


def rendered_value(value):
    """A block (several lines) stands on lines of its own between its markers."""
    return f"\n\n{value}\n\n" if "\n" in value else value


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--write", action="store_true", help="rewrite the figures in place")
    ap.add_argument("--exe", default=results.RELEASE_EXE)
    ap.add_argument("--rows", action="append", default=[], help="RUN=FILE: that run's rows (results.py --json)")
    ap.add_argument("--demo-log", help="a file holding the demo's output")
    ap.add_argument("--skip", action="append", default=[], help="a run not to check")
    ap.add_argument("--readme", default=os.path.join(REPO, "README.md"))
    ap.add_argument("--list", action="store_true", help="print each key and its value")
    a = ap.parse_args()
    text = open(a.readme, encoding="utf-8").read()
    spans = list(SPAN.finditer(text))
    if not spans:
        raise SystemExit(f"{a.readme}: no generated figures (<!--f:KEY-->...<!--/f-->)")
    needed = {m.group(1).partition(":")[0] for m in spans} - set(a.skip)
    unknown = needed - set(RUNS) - {"demo"}
    if unknown:
        raise SystemExit(f"{a.readme}: unknown runs {sorted(unknown)} (known: {sorted(RUNS)}, demo)")
    runs = {}
    for spec in a.rows:
        name, _, path = spec.partition("=")
        runs[name] = json.load(open(path))
    if a.demo_log:
        runs["demo"] = open(a.demo_log, encoding="utf-8").read()
    for name in sorted(needed - set(runs)):
        runs[name] = run_demo(a.exe) if name == "demo" else run_results(name, a.exe)
    for m in spans:
        line_start = text.rfind("\n", 0, m.start()) + 1
        if "\n" not in m.group(2) and not text[line_start:m.start()].strip():
            raise SystemExit(f"{a.readme}: figure {m.group(1)} begins a line: Markdown takes a line that begins "
                             "with <!-- for an HTML block; move a word before it")
    wrong, out, at = [], [], 0
    for m in spans:
        key, was = m.group(1), m.group(2)
        out.append(text[at:m.start(2)])
        at = m.end(2)
        if key.partition(":")[0] in a.skip:
            out.append(was)
            continue
        try:
            now = rendered_value(figure(key, runs))
        except (KeyError, IndexError, TypeError) as e:
            raise SystemExit(f"{a.readme}: figure {key}: {e!r}")
        if a.list:
            print(f"{key}: {now.strip()}")
        if now != was:
            wrong.append((key, was, now))
        out.append(now)
    out.append(text[at:])
    if a.write:
        if wrong:
            with open(a.readme, "w", encoding="utf-8") as f:
                f.write("".join(out))
        print(f"readme-figures: {len(spans)} figures, {len(wrong)} rewritten in {a.readme}")
        return 0
    for key, was, now in wrong:
        if "\n" in now.strip():
            diff = difflib.unified_diff(was.strip().splitlines(), now.strip().splitlines(), "README", "command",
                                        lineterm="", n=0)
            print(f"README figure {key}:\n" + "\n".join(diff) + "\n")
        else:
            print(f"README figure {key}: README has {was.strip()!r}, its command prints {now.strip()!r}")
    print(f"readme-figures: {len(spans)} figures, {len(wrong)} differ from their commands"
          + (" (scripts/readme-figures --write rewrites them)" if wrong else ""))
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())
