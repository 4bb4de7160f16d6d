"""Makes docs/figure.png: raw and recovered depth of a physically rendered scene.

usage (from the repository's root, with the venv that scripts/test makes):

    cargo build --release
    .venv/bin/python docs/make_figure.py [--bin target/release/translucent_tof]
        [--bag bags/rendered/paper_document_holder.mcap] [--out docs/figure.png]

It replays the bag with the defaults (`translucent_tof replay BAG --out TMP`),
then draws, for the frames with the sheet at its nearest and at a middle
distance, three panels: the camera's raw depth, the node's corrected depth
(`/translucent_tof/depth/corrected`) and the ground truth of the sheet
(`/tof/ground_truth/depth`, dark grey where there is no sheet), all as z in
millimetres on one colour scale. The PNG is written with zlib alone.
"""

import argparse
import math
import os
import struct
import subprocess
import sys
import tempfile
import zlib

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Depth colour scale (z, mm) and a viridis-like ramp.
Z_MIN, Z_MAX = 400.0, 2100.0
RAMP = [(0.0, (68, 1, 84)), (0.25, (59, 82, 139)), (0.5, (33, 145, 140)),
        (0.75, (94, 201, 98)), (1.0, (253, 231, 37))]
NO_DATA = (40, 40, 40)
BACKDROP = (255, 255, 255)
INK = (20, 20, 20)

# A 5x7 font for the labels (rows top to bottom, 5 bits each, MSB left).
FONT = {
    " ": [0, 0, 0, 0, 0, 0, 0],
    "A": [14, 17, 17, 31, 17, 17, 17], "C": [14, 17, 16, 16, 16, 17, 14],
    "D": [30, 17, 17, 17, 17, 17, 30], "E": [31, 16, 16, 30, 16, 16, 31],
    "H": [17, 17, 17, 31, 17, 17, 17], "I": [14, 4, 4, 4, 4, 4, 14],
    "M": [17, 27, 21, 21, 17, 17, 17], "N": [17, 25, 21, 19, 17, 17, 17],
    "O": [14, 17, 17, 17, 17, 17, 14], "P": [30, 17, 17, 30, 16, 16, 16],
    "R": [30, 17, 17, 30, 20, 18, 17], "S": [15, 16, 16, 14, 1, 1, 30],
    "T": [31, 4, 4, 4, 4, 4, 4], "U": [17, 17, 17, 17, 17, 17, 14],
    "V": [17, 17, 17, 17, 17, 10, 4], "W": [17, 17, 17, 21, 21, 21, 10],
    "Z": [31, 1, 2, 4, 8, 16, 31], "F": [31, 16, 16, 30, 16, 16, 16],
    "L": [16, 16, 16, 16, 16, 16, 31], "G": [14, 17, 16, 23, 17, 17, 15],
    "0": [14, 17, 19, 21, 25, 17, 14], "1": [4, 12, 4, 4, 4, 4, 14],
    "2": [14, 17, 1, 2, 4, 8, 31], "3": [30, 1, 1, 14, 1, 1, 30],
    "4": [2, 6, 10, 18, 31, 2, 2], "5": [31, 16, 30, 1, 1, 17, 14],
    "6": [6, 8, 16, 30, 17, 17, 14], "7": [31, 1, 2, 4, 8, 8, 8],
    "8": [14, 17, 17, 14, 17, 17, 14], "9": [14, 17, 17, 15, 1, 2, 12],
    ",": [0, 0, 0, 0, 0, 4, 8], ".": [0, 0, 0, 0, 0, 0, 4],
    "-": [0, 0, 0, 31, 0, 0, 0], ":": [0, 4, 0, 0, 0, 4, 0],
    "(": [2, 4, 8, 8, 8, 4, 2], ")": [8, 4, 2, 2, 2, 4, 8],
}


def colour(z):
    if z is None or not math.isfinite(z):
        return NO_DATA
    t = min(1.0, max(0.0, (z - Z_MIN) / (Z_MAX - Z_MIN)))
    for (t0, c0), (t1, c1) in zip(RAMP, RAMP[1:]):
        if t <= t1:
            f = (t - t0) / (t1 - t0)
            return tuple(round(a + (b - a) * f) for a, b in zip(c0, c1))
    return RAMP[-1][1]


def z_mm(msg):
    """An Image as a list of rows of z in mm (None where invalid)."""
    fmt, size = {"16UC1": ("H", 2), "32FC1": ("f", 4)}[msg.encoding]
    end = ">" if msg.is_bigendian else "<"
    data, rows = bytes(msg.data), []
    for r in range(msg.height):
        row = struct.unpack(f"{end}{msg.width}{fmt}", data[r * msg.step: r * msg.step + msg.width * size])
        if msg.encoding == "32FC1":
            rows.append([x * 1000.0 if math.isfinite(x) and x > 0 else None for x in row])
        else:
            rows.append([float(x) if x > 0 else None for x in row])
    return rows


def read(path, suffixes):
    out = {s: {} for s in suffixes}
    with open(path, "rb") as f:
        for _s, channel, _m, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            for s in suffixes:
                if channel.topic.endswith(s):
                    st = msg.header.stamp
                    out[s][st.sec * 10**9 + st.nanosec] = msg
    return out


class Canvas:
    def __init__(self, w, h):
        self.w, self.h = w, h
        self.px = [[BACKDROP] * w for _ in range(h)]

    def rect(self, x, y, w, h, c):
        for j in range(max(0, y), min(self.h, y + h)):
            row = self.px[j]
            for i in range(max(0, x), min(self.w, x + w)):
                row[i] = c

    def text(self, x, y, s, scale=2, c=INK):
        for ch in s.upper():
            for j, bits in enumerate(FONT.get(ch, FONT[" "])):
                for i in range(5):
                    if bits & (16 >> i):
                        self.rect(x + i * scale, y + j * scale, scale, scale, c)
            x += 6 * scale

    def image(self, x, y, rows, scale):
        for j, row in enumerate(rows):
            for i, z in enumerate(row):
                self.rect(x + i * scale, y + j * scale, scale, scale, colour(z))

    def png(self, path):
        raw = b"".join(b"\x00" + bytes(v for p in row for v in p) for row in self.px)
        def chunk(kind, data):
            return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        with open(path, "wb") as f:
            f.write(b"\x89PNG\r\n\x1a\n")
            f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", self.w, self.h, 8, 2, 0, 0, 0)))
            f.write(chunk(b"IDAT", zlib.compress(raw, 9)))
            f.write(chunk(b"IEND", b""))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", default=os.path.join(REPO, "target", "release", "translucent_tof"))
    ap.add_argument("--bag", default=os.path.join(REPO, "bags", "rendered", "paper_document_holder.mcap"))
    ap.add_argument("--out", default=os.path.join(REPO, "docs", "figure.png"))
    ap.add_argument("--scale", type=int, default=2, help="screen pixels per camera pixel")
    a = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        out_bag = os.path.join(tmp, "recovered.mcap")
        run = subprocess.run([a.bin, "replay", a.bag, "--out", out_bag, "--json", os.path.join(tmp, "r.json")],
                             capture_output=True, text=True)
        if run.returncode != 0:
            sys.exit(f"replay failed: {run.stderr.strip()}")
        rec = read(out_bag, ["depth/corrected"])["depth/corrected"]
    src = read(a.bag, ["depth/image_raw", "ground_truth/depth"])

    # Object frames (those the node published), grouped by the sheet's distance.
    frames = {}
    for stamp in sorted(rec):
        truth = z_mm(src["ground_truth/depth"][stamp])
        zs = sorted(z for row in truth for z in row if z is not None)
        if zs:
            frames.setdefault(round(zs[len(zs) // 2] / 50.0) * 50, (stamp, truth))
    distances = sorted(frames)
    picked = [distances[0], distances[len(distances) // 2]] if len(distances) > 1 else distances

    s, pad, top, label_h = a.scale, 16, 34, 22
    first = src["depth/image_raw"][frames[picked[0]][0]]
    pw, ph = first.width * s, first.height * s
    bar_h = 70
    cv = Canvas(3 * pw + 4 * pad, top + len(picked) * (ph + label_h + pad) + bar_h)
    for k, title in enumerate(["RAW DEPTH", "RECOVERED", "TRUTH (SHEET)"]):
        cv.text(pad + k * (pw + pad), 10, title)
    y = top
    for d in picked:
        stamp, truth = frames[d]
        panels = [z_mm(src["depth/image_raw"][stamp]), z_mm(rec[stamp]), truth]
        for k, rows in enumerate(panels):
            cv.image(pad + k * (pw + pad), y, rows, s)
        cv.text(pad, y + ph + 5, f"SHEET AT {int(d)} MM, WALL AT 2000 MM")
        y += ph + label_h + pad
    # Colour bar with ticks every 500 mm.
    bx, bw = pad, 3 * pw + 2 * pad
    for i in range(bw):
        cv.rect(bx + i, y, 1, 14, colour(Z_MIN + (Z_MAX - Z_MIN) * i / (bw - 1)))
    for z in range(500, int(Z_MAX) + 1, 500):
        x = bx + round((z - Z_MIN) / (Z_MAX - Z_MIN) * (bw - 1))
        cv.rect(x, y + 14, 2, 6, INK)
        cv.text(x - 12, y + 24, str(z))
    cv.text(bx + bw - 12 * 6 * 2 // 2, y + 44, "Z, MM")
    cv.png(a.out)
    print(f"wrote {a.out} ({cv.w}x{cv.h}; frames at {', '.join(str(int(d)) for d in picked)} mm)")


if __name__ == "__main__":
    main()
