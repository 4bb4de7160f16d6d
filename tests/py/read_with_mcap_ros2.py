"""Reads a ROS 2 MCAP bag with `mcap` + `mcap_ros2` and prints a JSON summary.

usage: read_with_mcap_ros2.py BAG

Messages are decoded by `mcap_ros2.reader.read_ros2_messages` from the
schema text in the file alone. Also checks the header profile and the
summary (which rosbag2 and seeking readers rely on). Output has the same
shape as read_with_rosbags.py.
"""

import json
import sys

from mcap.reader import make_reader
from mcap_ros2.reader import read_ros2_messages

from _common import check_dependencies_complete, check_schema_text, summarize


def main():
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    path = sys.argv[1]
    out = {"reader": "mcap_ros2", "topics": {}, "first": {}}
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        if header.profile != "ros2":
            raise SystemExit(f"MCAP profile {header.profile!r}, want 'ros2'")
        out["library"] = header.library
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            raise SystemExit("no summary section with statistics")
        if not summary.chunk_indexes:
            raise SystemExit("no chunk indexes")
        for cid, ch in summary.channels.items():
            schema = summary.schemas[ch.schema_id]
            if schema.encoding != "ros2msg" or ch.message_encoding != "cdr":
                raise SystemExit(f"{ch.topic}: {schema.encoding}/{ch.message_encoding}")
            if "offered_qos_profiles" not in ch.metadata:
                raise SystemExit(f"{ch.topic}: no offered_qos_profiles")
            deps = check_schema_text(schema.name, schema.data.decode())
            check_dependencies_complete(schema.name, schema.data.decode())
            out["topics"][ch.topic] = {
                "type": schema.name,
                "count": summary.statistics.channel_message_counts.get(cid, 0),
                "dependencies": deps,
                "message_encoding": ch.message_encoding,
            }
    last = {}
    for m in read_ros2_messages(path):
        topic = m.channel.topic
        if m.log_time_ns != m.publish_time_ns:
            raise SystemExit(f"{topic}: log time {m.log_time_ns} != publish time {m.publish_time_ns}")
        if topic in last and m.log_time_ns < last[topic]:
            raise SystemExit(f"{topic}: log times go backwards")
        last[topic] = m.log_time_ns
        if topic not in out["first"]:
            s = summarize(m.schema.name, m.ros_msg)
            if s is not None:
                s["log_time_ns"] = m.log_time_ns
            out["first"][topic] = s
    print(json.dumps(out, indent=1, allow_nan=False))


if __name__ == "__main__":
    main()
