"""The node in a ROS 2 graph as ROS users build one: rclpy on rmw_fastrtps_cpp
(ROS 2's default middleware, from the PyPI ros-* packages).

A driver node publishes a bag's depth, IR and camera_info; the latch is
called before the first frame and must succeed once frames flow; the object
frames are played at a fixed rate; every output is subscribed the two ways ROS
code subscribes (default QoS: reliable, keep last 10; sensor-data QoS: best
effort, keep last 5); the parameters are listed, read and set through rclpy's
parameter client; /diagnostics and /rosout are read. Prints one JSON object.

usage: rclpy_peer.py BAG NAMESPACE NODE_FQN [--rate HZ] [--frames N]
       [--params] [--timeout S] [--quiet S] [--drain S]
"""

import argparse
import json
import math
import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from mcap_ros2.reader import read_ros2_messages
from rcl_interfaces.msg import Log
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.utilities import get_rmw_implementation_identifier
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, RegionOfInterest
from std_srvs.srv import Trigger


def stamp_ns(h):
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def udp_counters():
    """The network namespace's UDP counters (Linux /proc/net/snmp), {} elsewhere."""
    try:
        lines = [l.split() for l in open("/proc/net/snmp") if l.startswith("Udp:")]
        return dict(zip(lines[0][1:], map(int, lines[1][1:])))
    except (OSError, IndexError, ValueError):
        return {}


def read_bag(path):
    depth, ir, truth, info = {}, {}, {}, None
    for m in read_ros2_messages(path):
        topic, msg = m.channel.topic, m.ros_msg
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        if topic.endswith("depth/image_raw"):
            depth[key] = msg
        elif topic.endswith("ir/image_raw"):
            ir[key] = msg
        elif topic.endswith("ground_truth/depth"):
            truth[key] = msg
        elif topic.endswith("camera_info") and info is None:
            info = msg
    keys = [k for k in sorted(depth) if k in ir]
    return info, [(depth[k], ir[k], truth.get(k)) for k in keys]


def as_image(m, ns):
    out = Image()
    out.header.stamp.sec, out.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    out.header.frame_id = m.header.frame_id
    out.height, out.width, out.encoding = m.height, m.width, m.encoding
    out.is_bigendian, out.step = m.is_bigendian, m.step
    out.data = bytes(m.data)
    return out


def as_info(m, ns):
    out = CameraInfo()
    out.header.stamp.sec, out.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    out.header.frame_id = m.header.frame_id
    out.height, out.width, out.distortion_model = m.height, m.width, m.distortion_model
    out.d, out.k, out.r, out.p = list(m.d), list(m.k), list(m.r), list(m.p)
    out.binning_x, out.binning_y = m.binning_x, m.binning_y
    out.roi = RegionOfInterest()
    return out


def depth_m(img):
    """z in metres, NaN invalid (16UC1 mm or 32FC1 m)."""
    if img.encoding == "32FC1":
        z = np.frombuffer(bytes(img.data), dtype="<f4").astype(np.float64)
    else:
        z = np.frombuffer(bytes(img.data), dtype="<u2").astype(np.float64) / 1000.0
        z[z == 0] = np.nan
    return z.reshape(img.height, img.width)


class Peer:
    def __init__(self, node, ns, fqn):
        self.node = node
        reliable = QoSProfile(depth=10)
        self.pub_depth = node.create_publisher(Image, f"{ns}/depth/image_raw", reliable)
        self.pub_ir = node.create_publisher(Image, f"{ns}/ir/image_raw", reliable)
        self.pub_info = node.create_publisher(CameraInfo, f"{ns}/depth/camera_info", reliable)
        self.got = {}
        self.arrival = {}
        self.first_cloud = None
        outputs = [
            ("points", PointCloud2, f"{fqn}/points"),
            ("corrected", Image, f"{fqn}/depth/corrected"),
            ("camera_info", CameraInfo, f"{fqn}/depth/camera_info"),
            ("mask", Image, f"{fqn}/translucent_mask"),
            ("sigma", Image, f"{fqn}/depth/corrected_sigma"),
        ]
        for name, ty, topic in outputs:
            for qos_name, qos in [("default", reliable), ("sensor", qos_profile_sensor_data)]:
                key = f"{name}_{qos_name}"
                self.got[key] = {}
                node.create_subscription(ty, topic, self._keep(key), qos)
        self.diagnostics = []
        node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, reliable)
        self.rosout = []
        node.create_subscription(Log, "/rosout", self.rosout.append, QoSProfile(depth=100))
        self.latch = node.create_client(Trigger, f"{fqn}/latch_background")
        self.clear = node.create_client(Trigger, f"{fqn}/clear_background")
        self.params = AsyncParameterClient(node, fqn)

    def _keep(self, key):
        store = self.got[key]

        def cb(msg):
            s = stamp_ns(msg.header)
            # Keep only what the checks need: the messages of one subscriber of each
            # output, and of the clouds (up to 6 MB each) only the first.
            keep = key.endswith("_default") and not key.startswith("points")
            store[s] = msg if keep else True
            if key == "points_default" and self.first_cloud is None:
                self.first_cloud = msg
            self.arrival.setdefault(key, {})[s] = time.monotonic()

        return cb

    def spin_for(self, seconds):
        end = time.monotonic() + seconds
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return
            rclpy.spin_once(self.node, timeout_sec=min(left, 0.01))

    def spin_until(self, cond, timeout):
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                return False
            rclpy.spin_once(self.node, timeout_sec=0.01)
        return True

    def play(self, info, depth, ir, ns):
        self.pub_info.publish(as_info(info, ns))
        self.pub_depth.publish(as_image(depth, ns))
        self.pub_ir.publish(as_image(ir, ns))

    def wait_future(self, fut, timeout, what):
        if not self.spin_until(fut.done, timeout):
            raise SystemExit(f"rclpy peer: no answer to {what} in {timeout} s")
        return fut.result()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("bag")
    ap.add_argument("namespace")
    ap.add_argument("node")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--background", type=int, default=10)
    ap.add_argument("--params", action="store_true", help="also exercise the parameter services")
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--quiet", type=float, default=3.0,
                    help="after the last frame, stop waiting when no output arrived for this long")
    ap.add_argument("--drain", type=float, default=120.0,
                    help="after the last frame, wait at most this long in all")
    a = ap.parse_args()
    ns, fqn = a.namespace.rstrip("/"), a.node
    info, frames = read_bag(a.bag)
    background, objects = frames[: a.background], frames[a.background:]

    rclpy.init()
    node = rclpy.create_node("rclpy_peer")
    out = {"rmw": get_rmw_implementation_identifier()}
    peer = Peer(node, ns, fqn)

    # The node's services and parameter services are there before any frame flows.
    if not peer.latch.wait_for_service(timeout_sec=a.timeout):
        raise SystemExit("rclpy peer: latch service never appeared")
    if not peer.spin_until(lambda: peer.pub_depth.get_subscription_count() > 0, a.timeout):
        raise SystemExit("rclpy peer: the node never subscribed depth")
    # Let the outputs' readers match before anything is published.
    matched = peer.spin_until(
        lambda: len(node.get_publishers_info_by_topic(f"{fqn}/points")) > 0, a.timeout
    )
    out["points_publisher_seen"] = matched
    pubs = node.get_publishers_info_by_topic(f"{fqn}/points")
    if pubs:
        q = pubs[0].qos_profile
        out["points_qos"] = {"reliability": q.reliability.name, "durability": q.durability.name}
    est = node.get_publishers_info_by_topic(f"{fqn}/translucency")
    if est:
        out["estimate_type"] = est[0].topic_type
        out["estimate_durability"] = est[0].qos_profile.durability.name
    peer.spin_for(1.0)

    # 1. The latch, called before the first camera_info and frame.
    fut = peer.latch.call_async(Trigger.Request())
    peer.spin_for(0.5)
    out["latch_answered_before_frames"] = fut.done()
    t = 1_700_000_000_000_000_000
    period = 1.0 / a.rate
    k = 0
    end = time.monotonic() + a.timeout
    while not fut.done():
        if time.monotonic() > end:
            raise SystemExit("rclpy peer: the latch never answered")
        d, i, _ = background[k % len(background)]
        t += int(period * 1e9)
        peer.play(info, d, i, t)
        k += 1
        peer.spin_for(period)
    reply = fut.result()
    out["latch_success"], out["latch_message"] = bool(reply.success), reply.message

    # 2. The object frames at the rate, each once per cycle of the bag.
    udp_before = udp_counters()
    sent = []
    next_t = time.monotonic()
    truth_of = {}
    for j in range(a.frames):
        d, i, truth = objects[j % len(objects)]
        t += int(period * 1e9)
        peer.play(info, d, i, t)
        sent.append(t)
        truth_of[t] = truth
        next_t += period
        peer.spin_for(max(0.0, next_t - time.monotonic()))
    # Wait for what is in flight: a node slower than the rate (a debug build, a busy
    # machine) still works through its queue after the last frame was sent, so wait
    # while outputs keep arriving, until every output has the last frame or none has
    # arrived for --quiet seconds, at most --drain seconds in all.
    t_sent = time.monotonic()
    drain_end = t_sent + a.drain

    def last_arrival():
        return max((max(v.values()) for v in peer.arrival.values() if v), default=t_sent)

    while not all(sent[-1] in v for v in peer.got.values()):
        now = time.monotonic()
        if now > drain_end or now - max(last_arrival(), t_sent) > a.quiet:
            break
        rclpy.spin_once(node, timeout_sec=0.01)
    peer.spin_for(0.5)
    out["drain_s"] = round(time.monotonic() - t_sent, 2)
    out["drain_capped"] = time.monotonic() > drain_end
    out["last_output_after_s"] = round(last_arrival() - t_sent, 2)
    # Datagrams the kernel dropped on a full receive buffer while the frames played, on
    # any socket of the namespace (the tests run node and peer in one of their own).
    udp_after = udp_counters()
    out["udp_rcvbuf_errors"] = udp_after.get("RcvbufErrors", 0) - udp_before.get("RcvbufErrors", 0)
    out["sent"] = len(sent)
    out["received"] = {key: sum(1 for s in sent if s in v) for key, v in peer.got.items()}
    # Which frames (by index in the order sent) an output is missing for.
    out["missing"] = {key: [i for i, s in enumerate(sent) if s not in v] for key, v in peer.got.items()}
    out["missing"] = {k: v for k, v in out["missing"].items() if v}
    out["rate_hz"] = a.rate
    out["size"] = [objects[0][0].width, objects[0][0].height]

    # 3. The outputs against the input and the ground truth.
    raw_err, rec_err, info_ok, masks = [], [], 0, []
    within_2sigma, with_sigma = 0, 0
    for s in sent:
        c = peer.got["corrected_default"].get(s)
        ci = peer.got["camera_info_default"].get(s)
        m = peer.got["mask_default"].get(s)
        truth = truth_of[s]
        if ci is not None and list(ci.k) == list(info.k) and ci.header.frame_id == info.header.frame_id:
            info_ok += 1
        if c is None or m is None or truth is None:
            continue
        mask = np.frombuffer(bytes(m.data), dtype=np.uint8).reshape(m.height, m.width) == 255
        masks.append(int(mask.sum()))
        z_true = depth_m(truth)
        src = next(d for d, _, tr in objects if tr is truth)
        z_raw, z_rec = depth_m(src), depth_m(c)
        sel = mask & np.isfinite(z_true) & np.isfinite(z_rec) & np.isfinite(z_raw)
        if sel.sum() > 100:
            raw_err.append(float(np.sqrt(np.mean((z_raw[sel] - z_true[sel]) ** 2))) * 1000)
            rec_err.append(float(np.sqrt(np.mean((z_rec[sel] - z_true[sel]) ** 2))) * 1000)
        sg = peer.got["sigma_default"].get(s)
        if sg is not None and sg.encoding == "32FC1" and sel.sum() > 0:
            sigma = np.frombuffer(bytes(sg.data), dtype="<f4").reshape(sg.height, sg.width)
            with_sigma += int((sel & np.isfinite(sigma)).sum())
            within_2sigma += int((sel & (np.abs(z_rec - z_true) <= 2 * sigma)).sum())
    cloud = peer.first_cloud
    if cloud is not None:
        out["cloud"] = {
            "width": cloud.width, "height": cloud.height, "point_step": cloud.point_step,
            "fields": [f.name for f in cloud.fields],
        }
    out["camera_info_matching"] = info_ok
    out["sigma_pixels"], out["within_2sigma"] = with_sigma, within_2sigma
    out["mask_pixels_median"] = int(np.median(masks)) if masks else 0
    out["rmse_raw_mm"] = float(np.mean(raw_err)) if raw_err else None
    out["rmse_mm"] = float(np.mean(rec_err)) if rec_err else None

    # 4. Parameters through rclpy's parameter client, a change applying from the next frame.
    if a.params:
        p = peer.params
        if not p.wait_for_services(timeout_sec=a.timeout):
            raise SystemExit("rclpy peer: parameter services never appeared")
        names = peer.wait_future(p.list_parameters(), 10, "list_parameters").result.names
        out["parameters"] = sorted(names)
        got = peer.wait_future(p.get_parameters(["threshold_mm", "xi", "background_frames"]), 10, "get")
        out["get"] = [parameter_value_to_python(v) for v in got.values]
        # A parameter that cannot change at run time is refused with the reason.
        res = peer.wait_future(p.set_parameters([Parameter("queue_depth", value=7)]), 10, "set queue_depth")
        out["set_queue_depth"] = {"successful": res.results[0].successful, "reason": res.results[0].reason}
        res = peer.wait_future(p.set_parameters([Parameter("threshold_mm", value=-1.0)]), 10, "set bad")
        out["set_bad_threshold"] = {"successful": res.results[0].successful, "reason": res.results[0].reason}
        # threshold_mm far above any change: the very next frame segments nothing.
        d, i, _ = objects[0]
        t += int(period * 1e9)
        before = t
        peer.play(info, d, i, before)
        peer.spin_until(lambda: before in peer.got["mask_default"], 10.0)
        res = peer.wait_future(p.set_parameters([Parameter("threshold_mm", value=100000.0)]), 10, "set")
        out["set_threshold"] = {"successful": res.results[0].successful, "reason": res.results[0].reason}
        t += int(period * 1e9)
        after = t
        peer.play(info, d, i, after)
        peer.spin_until(lambda: after in peer.got["mask_default"], 10.0)
        count = lambda s: int((np.frombuffer(bytes(peer.got["mask_default"][s].data), np.uint8) == 255).sum()) \
            if s in peer.got["mask_default"] else None
        out["mask_before_set"], out["mask_after_set"] = count(before), count(after)
        got = peer.wait_future(p.get_parameters(["threshold_mm"]), 10, "get").values[0]
        out["threshold_after_set"] = got.double_value

    # 5. Clear; diagnostics and rosout seen on the way.
    fut = peer.clear.call_async(Trigger.Request())
    reply = peer.wait_future(fut, 10, "clear_background")
    out["clear_success"] = bool(reply.success)
    peer.spin_until(lambda: len(peer.diagnostics) > 0, 5.0)
    out["diagnostics_messages"] = len(peer.diagnostics)
    if peer.diagnostics:
        st = peer.diagnostics[-1].status[0]
        out["diagnostics"] = {"name": st.name, "level": int.from_bytes(st.level, "little")
                              if isinstance(st.level, bytes) else int(st.level),
                              "message": st.message, "values": {kv.key: kv.value for kv in st.values}}
    ours = [m for m in peer.rosout if m.name.endswith("translucent_tof")]
    out["rosout_lines"] = len(ours)
    out["rosout_sample"] = [m.msg for m in ours[:3]]
    node.destroy_node()
    rclpy.shutdown()
    print(json.dumps(out))


if __name__ == "__main__":
    sys.exit(main())
