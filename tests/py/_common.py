"""Helpers shared by the checker scripts: turn decoded ROS messages into
plain JSON values (NaN -> null) so the Rust tests can compare them."""

import math
import struct

FIRST_PIXELS = 4

_SAMPLES = {
    "16UC1": ("H", 2),
    "mono16": ("H", 2),
    "32FC1": ("f", 4),
    "mono8": ("B", 1),
}


def clean(v):
    """JSON-safe number: NaN and infinities become None."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def image_summary(msg):
    """width, height, encoding, step, stamp and the first pixels of row 0."""
    data = bytes(msg.data)
    fmt, size = _SAMPLES.get(msg.encoding, (None, None))
    pixels = []
    if fmt is not None:
        order = ">" if msg.is_bigendian else "<"
        n = min(FIRST_PIXELS, msg.width)
        pixels = [clean(x) for x in struct.unpack_from(f"{order}{n}{fmt}", data, 0)]
    return {
        "width": msg.width,
        "height": msg.height,
        "encoding": msg.encoding,
        "step": msg.step,
        "is_bigendian": int(msg.is_bigendian),
        "data_len": len(data),
        "first_pixels": pixels,
        "stamp": [msg.header.stamp.sec, msg.header.stamp.nanosec],
        "frame_id": msg.header.frame_id,
    }


def camera_info_summary(msg):
    return {
        "width": msg.width,
        "height": msg.height,
        "distortion_model": msg.distortion_model,
        "d": [float(x) for x in msg.d],
        "k": [float(x) for x in msg.k],
        "p": [float(x) for x in msg.p],
        "stamp": [msg.header.stamp.sec, msg.header.stamp.nanosec],
    }


_FIELD_FMT = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}


def cloud_summary(msg):
    data = bytes(msg.data)
    order = ">" if msg.is_bigendian else "<"
    first = {}
    if len(data) >= msg.point_step:
        for f in msg.fields:
            (v,) = struct.unpack_from(order + _FIELD_FMT[f.datatype], data, f.offset)
            first[f.name] = clean(v)
    return {
        "width": msg.width,
        "height": msg.height,
        "point_step": msg.point_step,
        "row_step": msg.row_step,
        "is_dense": bool(msg.is_dense),
        "fields": [[f.name, f.offset, f.datatype, f.count] for f in msg.fields],
        "first_point": first,
        "stamp": [msg.header.stamp.sec, msg.header.stamp.nanosec],
    }


def summarize(type_name, msg):
    """A summary for the types the tests check, else None."""
    short = type_name.replace("/msg/", "/")
    if short == "sensor_msgs/Image":
        return image_summary(msg)
    if short == "sensor_msgs/CameraInfo":
        return camera_info_summary(msg)
    if short == "sensor_msgs/PointCloud2":
        return cloud_summary(msg)
    return None


def check_schema_text(type_name, text):
    """rosbag2's ros2msg layout: separators of exactly 80 '=' each followed
    by a `MSG: pkg/Name` line. Returns the dependency names."""
    lines = text.split("\n")
    deps = []
    for i, line in enumerate(lines):
        if line and set(line) == {"="}:
            if len(line) != 80:
                raise SystemExit(f"{type_name}: separator of {len(line)} '=' (need 80)")
            nxt = lines[i + 1] if i + 1 < len(lines) else ""
            if not nxt.startswith("MSG: ") or "/msg/" in nxt:
                raise SystemExit(f"{type_name}: separator not followed by 'MSG: pkg/Name': {nxt!r}")
            deps.append(nxt[5:].strip())
    return deps


PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16",
    "uint16", "int32", "uint32", "int64", "uint64", "string", "wstring",
}


def check_dependencies_complete(type_name, text):
    """Every message type a ros2msg schema uses must be defined in it.

    rosbags' empty typestore already knows builtin_interfaces/Time, so its
    decoding alone would not notice a schema that leaves Time out; rosbag2
    always includes it."""
    sep = "=" * 80 + "\n"
    sections = text.split(sep)
    pkg = type_name.split("/")[0]
    names = [type_name.replace("/msg/", "/")]
    bodies = [(pkg, sections[0])]
    for sec in sections[1:]:
        head, _, body = sec.partition("\n")
        name = head[len("MSG: "):].strip()
        names.append(name)
        bodies.append((name.split("/")[0], body))
    defined = set(names)
    for owner_pkg, body in bodies:
        for line in body.split("\n"):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            ftype = line.split()[0]
            base = ftype.split("[", 1)[0].split("<=", 1)[0]
            if base in PRIMITIVES:
                continue
            if base == "Header":
                base = "std_msgs/Header"
            if "/" not in base:
                base = f"{owner_pkg}/{base}"
            base = base.replace("/msg/", "/")
            if base not in defined:
                raise SystemExit(f"{type_name}: schema uses {base} but does not define it")
