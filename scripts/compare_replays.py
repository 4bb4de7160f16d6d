"""Value-by-value comparison of two `replay` output bags (scripts/compare-replays):
the corrected depth images and the point clouds' bytes as float32."""

import math
import struct
import sys

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def load(path):
    out = {"depth": [], "points": []}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, msg in reader.iter_decoded_messages():
            if channel.topic.endswith("depth/corrected"):
                n = msg.width * msg.height
                fmt = "<%dH" % n if msg.encoding == "16UC1" else "<%df" % n
                out["depth"].append(struct.unpack(fmt, bytes(msg.data)))
            elif channel.topic.endswith("/points"):
                data = bytes(msg.data)
                out["points"].append(struct.unpack("<%df" % (len(data) // 4), data))
    return out


def same(u, v):
    if isinstance(u, float) and math.isnan(u):
        return isinstance(v, float) and math.isnan(v)
    return u == v


def main():
    old, new = load(sys.argv[1]), load(sys.argv[2])
    differ = 0
    parts = []
    for what in ("depth", "points"):
        if len(old[what]) != len(new[what]):
            print(f"{what}: {len(old[what])} messages against {len(new[what])}")
            sys.exit(1)
        values = sum(len(m) for m in old[what])
        pairs = [(u, v) for a, b in zip(old[what], new[what]) for u, v in zip(a, b) if not same(u, v)]
        # The largest difference between two finite values, and how many differ in finiteness.
        finite = [abs(u - v) for u, v in pairs if math.isfinite(u) and math.isfinite(v)]
        bad = len(pairs) + sum(abs(len(a) - len(b)) for a, b in zip(old[what], new[what]))
        differ += bad
        part = f"{what} {len(old[what])} messages, {values} values, {bad} differ"
        if pairs:
            part += f" (largest difference {max(finite, default=0.0):.3g}, {len(pairs) - len(finite)} finite in one only)"
        parts.append(part)
    print("; ".join(parts))
    sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
