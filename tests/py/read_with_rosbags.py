"""Reads a ROS 2 MCAP bag strictly with `rosbags` and prints a JSON summary.

usage: read_with_rosbags.py BAG

rosbags' own MCAP reader checks the header profile is `ros2`; AnyReader
builds its typestore only from the bag's own schemas (no default store);
on top, every connection is decoded with a typestore built from its own
schema text alone, so a schema missing a dependency fails even when another
topic's schema has it. Schema texts are checked
for rosbag2's separators. Output: {"reader", "topics": {name: {"type",
"count", "dependencies"}}, "first": {name: summary}}.
"""

import json
import sys
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from _common import check_dependencies_complete, check_schema_text, summarize


def main():
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    bag = Path(sys.argv[1])
    out = {"reader": "rosbags", "topics": {}, "first": {}}
    stores = {}
    with AnyReader([bag]) as reader:
        for conn in reader.connections:
            store = get_typestore(Stores.EMPTY)
            store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
            stores[conn.id] = store
            if conn.msgdef.format.name != "MSG":
                raise SystemExit(f"{conn.topic}: schema format {conn.msgdef.format}, want ros2msg")
            deps = check_schema_text(conn.msgtype, conn.msgdef.data)
            check_dependencies_complete(conn.msgtype, conn.msgdef.data)
            out["topics"][conn.topic] = {
                "type": conn.msgtype,
                "count": conn.msgcount,
                "dependencies": deps,
                "message_encoding": conn.ext.serialization_format,
            }
        counts = {}
        for conn, _t, raw in reader.messages():
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            msg = reader.deserialize(raw, conn.msgtype)
            alone = stores[conn.id].deserialize_cdr(raw, conn.msgtype)
            if summarize(conn.msgtype, alone) != summarize(conn.msgtype, msg):
                raise SystemExit(f"{conn.topic}: decodes differently with its own schema alone")
            if conn.topic not in out["first"]:
                out["first"][conn.topic] = summarize(conn.msgtype, msg)
        for topic, n in counts.items():
            if out["topics"][topic]["count"] != n:
                raise SystemExit(f"{topic}: summary says {out['topics'][topic]['count']}, read {n}")
    print(json.dumps(out, indent=1, allow_nan=False))


if __name__ == "__main__":
    main()
