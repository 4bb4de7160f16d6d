"""An independent ROS 2 peer on Eclipse Cyclone DDS (the `cyclonedds` Python
package): plays a bag's depth, IR and camera_info under ROS 2's topic and
type naming, calls ~/latch_background as an rmw_cyclonedds client would
(16-byte request header: client guid, sequence number), and receives the
node's PointCloud2 and TranslucencyEstimate. Prints a JSON summary.

usage: cyclone_peer.py BAG NAMESPACE NODE_FQN BACKGROUND_FRAMES
"""

import json
import struct
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.annotations import final
from cyclonedds.idl.types import array, float64, int32, int64, sequence, uint8, uint32, uint64
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from mcap_ros2.reader import read_ros2_messages


# Plain final structs: Cyclone writes them as XCDR1, which every ROS 2 DDS reads.
@final
@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@final
@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@final
@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: uint32
    width: uint32
    encoding: str
    is_bigendian: uint8
    step: uint32
    data: sequence[uint8]


@final
@dataclass
class RegionOfInterest(IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: uint32
    y_offset: uint32
    height: uint32
    width: uint32
    do_rectify: bool


@final
@dataclass
class CameraInfo(IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    header: Header
    height: uint32
    width: uint32
    distortion_model: str
    d: sequence[float64]
    k: array[float64, 9]
    r: array[float64, 9]
    p: array[float64, 12]
    binning_x: uint32
    binning_y: uint32
    roi: RegionOfInterest


@final
@dataclass
class PointField(IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    name: str
    offset: uint32
    datatype: uint8
    count: uint32


@final
@dataclass
class PointCloud2(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool


@final
@dataclass
class TranslucencyEstimate(IdlStruct, typename="translucent_tof_msgs::msg::dds_::TranslucencyEstimate_"):
    header: Header
    xi: float64
    xi_lower: float64
    xi_upper: float64
    method: str
    translucent_pixels: uint32
    fit_residual_mm: float64
    frames_pooled: uint32
    region_id: uint32
    region_pixels: uint32
    opaque: bool
    material: str
    class_probability: float64


# rmw_cyclonedds: every request and reply starts with the client's guid and a sequence number.
@final
@dataclass
class TriggerRequest(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    client_guid: uint64
    sequence_number: int64
    structure_needs_at_least_one_member: uint8


@final
@dataclass
class TriggerReply(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    client_guid: uint64
    sequence_number: int64
    success: bool
    message: str


XCDR1 = Policy.DataRepresentation(use_cdrv0_representation=True)
SENSOR = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), XCDR1)
RELIABLE = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(50), XCDR1)
LATCHED = Qos(
    Policy.Reliability.Reliable(duration(seconds=1)),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
    XCDR1,
)
SERVICE = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10), XCDR1)


def header(h, stamp_ns=None):
    if stamp_ns is None:
        return Header(Time(h.stamp.sec, h.stamp.nanosec), h.frame_id)
    return Header(Time(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000), h.frame_id)


def image(m, stamp_ns):
    return Image(header(m.header, stamp_ns), m.height, m.width, m.encoding, m.is_bigendian, m.step, list(bytes(m.data)))


def camera_info(m, stamp_ns):
    roi = m.roi
    return CameraInfo(
        header(m.header, stamp_ns), m.height, m.width, m.distortion_model, list(m.d), list(m.k), list(m.r), list(m.p),
        m.binning_x, m.binning_y,
        RegionOfInterest(roi.x_offset, roi.y_offset, roi.height, roi.width, bool(roi.do_rectify)),
    )


def read_bag(path):
    depth, ir, info = {}, {}, None
    for m in read_ros2_messages(path):
        topic = m.channel.topic
        msg = m.ros_msg
        if topic.endswith("depth/image_raw"):
            depth[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg
        elif topic.endswith("ir/image_raw"):
            ir[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg
        elif topic.endswith("camera_info") and info is None:
            info = msg
    pairs = [(depth[s], ir[s]) for s in sorted(depth) if s in ir]
    return info, pairs


def wait_matched(what, entity, method, timeout=30.0):
    t0 = time.time()
    while not getattr(entity, method)():
        if time.time() - t0 > timeout:
            raise SystemExit(f"cyclone peer: {what} never matched the node")
        time.sleep(0.02)


def main():
    bag, ns, node, background = sys.argv[1], sys.argv[2].rstrip("/"), sys.argv[3], int(sys.argv[4])
    info, pairs = read_bag(bag)
    dp = DomainParticipant(0)

    def writer(name, ty, qos):
        return DataWriter(dp, Topic(dp, name, ty, qos=qos), qos=qos)

    def reader(name, ty, qos):
        return DataReader(dp, Topic(dp, name, ty, qos=qos), qos=qos)

    w_depth = writer(f"rt{ns}/depth/image_raw", Image, SENSOR)
    w_ir = writer(f"rt{ns}/ir/image_raw", Image, SENSOR)
    w_info = writer(f"rt{ns}/depth/camera_info", CameraInfo, SENSOR)
    r_points = reader(f"rt{node}/points", PointCloud2, RELIABLE)
    r_est = reader(f"rt{node}/translucency", TranslucencyEstimate, LATCHED)
    w_req = writer(f"rq{node}/latch_backgroundRequest", TriggerRequest, SERVICE)
    r_rep = reader(f"rr{node}/latch_backgroundReply", TriggerReply, SERVICE)
    for what, ent, method in [
        ("depth writer", w_depth, "get_matched_subscriptions"),
        ("IR writer", w_ir, "get_matched_subscriptions"),
        ("camera_info writer", w_info, "get_matched_subscriptions"),
        ("points reader", r_points, "get_matched_publications"),
        ("estimate reader", r_est, "get_matched_publications"),
        ("request writer", w_req, "get_matched_subscriptions"),
        # The reply reader must have matched before the request goes out.
        ("reply reader", r_rep, "get_matched_publications"),
    ]:
        wait_matched(what, ent, method)

    stamp = [1_700_000_000_000_000_000]

    def play(pair):
        # The bag's own frame period (10 Hz): its sheet steps 250-750 mm between poses, which
        # 33 ms apart would be jumps no carried object makes (the node would start a new
        # object at every pose, each seen in one pose and kept as read).
        stamp[0] += 100_000_000
        d, i = pair
        w_info.write(camera_info(info, stamp[0]))
        w_depth.write(image(d, stamp[0]))
        w_ir.write(image(i, stamp[0]))
        return stamp[0]

    # A driver streams before anyone latches: the node has camera_info by then.
    k = 0
    for _ in range(3):
        play(pairs[k % background])
        k += 1
        time.sleep(0.1)
    guid = struct.unpack("<Q", b"pyclone1")[0]
    w_req.write(TriggerRequest(guid, 1, 0))
    reply = None
    t0 = time.time()
    while reply is None:
        if time.time() - t0 > 60:
            raise SystemExit("cyclone peer: no reply to latch_background")
        play(pairs[k % background])
        k += 1
        time.sleep(0.04)
        for r in r_rep.take(N=10):
            if r.client_guid == guid and r.sequence_number == 1:
                reply = r
    sent = []
    for pair in pairs[background:]:
        sent.append(play(pair))
        time.sleep(0.25)
    clouds, estimates = {}, []
    t0 = time.time()
    while time.time() - t0 < 120 and sent[-1] not in clouds:
        for c in r_points.take(N=10):
            s = c.header.stamp.sec * 1_000_000_000 + c.header.stamp.nanosec
            clouds[s] = c
        for e in r_est.take(N=10):
            estimates.append(e)
        time.sleep(0.02)
    for e in r_est.take(N=10):
        estimates.append(e)
    out = {
        "latch_success": bool(reply.success),
        "latch_message": reply.message,
        "background_frames_sent": k,
        "object_frames_sent": len(sent),
        "clouds": len(clouds),
        "clouds_for_sent_stamps": sum(1 for s in sent if s in clouds),
        "estimates": len(estimates),
    }
    if clouds:
        # The cloud with the most translucent points (a pose whose object the data determine).
        flagged = {s: sum(c.data[i + 16] for i in range(0, len(c.data), c.point_step)) for s, c in clouds.items()}
        c = clouds[max(flagged, key=flagged.get)]
        out["cloud"] = {
            "width": c.width, "height": c.height, "point_step": c.point_step,
            "fields": [[f.name, f.offset, f.datatype, f.count] for f in c.fields],
            "bytes": len(c.data),
            "translucent_points": max(flagged.values()),
        }
    if estimates:
        # The estimate pooled over the most frames (the latest of those).
        e = max(reversed(estimates), key=lambda e: e.frames_pooled)
        out["estimate"] = {"xi": e.xi, "xi_lower": e.xi_lower, "xi_upper": e.xi_upper, "method": e.method,
                           "translucent_pixels": e.translucent_pixels, "frames_pooled": e.frames_pooled,
                           "opaque": e.opaque, "material": e.material,
                           "class_probability": None if e.class_probability != e.class_probability else e.class_probability}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
