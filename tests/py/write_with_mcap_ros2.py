"""Writes a small ROS 2 MCAP bag with `mcap_ros2.writer.Writer`, for the
Rust reader to decode.

usage: write_with_mcap_ros2.py OUT.mcap

Three frames on /cam/depth/image_raw (16UC1, mm), /cam/ir/image_raw
(mono16) and /cam/depth/camera_info, stamped 1.000000000 s + frame * 0.1 s.
Frame f, pixel (col, row) of a 4x3 image: depth = 1000 + 100*f + 10*row +
col (0 at col 3 row 2: invalid); IR = 500 + f + row*4 + col. The depth rows
are padded: step 10 (8 bytes of samples + 2 of 0xEE). k = [500, 0, 2, 0,
501, 1.5, 0, 0, 1].
"""

import struct
import sys

from mcap_ros2.writer import Writer

TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
SEP = "=" * 80 + "\n"
IMAGE = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
    "uint8 is_bigendian\nuint32 step\nuint8[] data\n"
    + SEP + "MSG: std_msgs/Header\n" + HEADER
    + SEP + "MSG: builtin_interfaces/Time\n" + TIME
)
ROI = "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
CAMERA_INFO = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
    "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
    "uint32 binning_y\nRegionOfInterest roi\n"
    + SEP + "MSG: std_msgs/Header\n" + HEADER
    + SEP + "MSG: builtin_interfaces/Time\n" + TIME
    + SEP + "MSG: sensor_msgs/RegionOfInterest\n" + ROI
)
W, H = 4, 3
K = [500.0, 0.0, 2.0, 0.0, 501.0, 1.5, 0.0, 0.0, 1.0]


def header(f):
    ns = 1_000_000_000 + f * 100_000_000
    return {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": "cam_optical_frame"}, ns


def depth(f):
    rows = []
    for row in range(H):
        vals = [0 if (col, row) == (3, 2) else 1000 + 100 * f + 10 * row + col for col in range(W)]
        rows.append(struct.pack("<4H", *vals) + b"\xee\xee")
    return b"".join(rows)


def ir(f):
    return b"".join(struct.pack("<H", 500 + f + row * 4 + col) for row in range(H) for col in range(W))


def main():
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    with open(sys.argv[1], "wb") as out:
        writer = Writer(out)
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO)
        for f in range(3):
            hdr, ns = header(f)
            writer.write_message(
                "/cam/depth/image_raw", image_schema,
                {"header": hdr, "height": H, "width": W, "encoding": "16UC1",
                 "is_bigendian": 0, "step": 10, "data": depth(f)},
                log_time=ns, publish_time=ns, sequence=f,
            )
            writer.write_message(
                "/cam/ir/image_raw", image_schema,
                {"header": hdr, "height": H, "width": W, "encoding": "mono16",
                 "is_bigendian": 0, "step": 2 * W, "data": ir(f)},
                log_time=ns, publish_time=ns, sequence=f,
            )
            writer.write_message(
                "/cam/depth/camera_info", info_schema,
                {"header": hdr, "height": H, "width": W, "distortion_model": "plumb_bob",
                 "d": [0.1, -0.2, 0.0, 0.0, 0.05], "k": K,
                 "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                 "p": [500.0, 0, 2.0, 0, 0, 501.0, 1.5, 0, 0, 0, 1.0, 0],
                 "binning_x": 0, "binning_y": 0,
                 "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}},
                log_time=ns, publish_time=ns, sequence=f,
            )
        writer.finish()


if __name__ == "__main__":
    main()
