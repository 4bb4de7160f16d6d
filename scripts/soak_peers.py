"""The soak's ROS 2 peers (rclpy on Fast DDS), one process each, driven by
scripts/soak.py over their standard input and output, one line per message:

  soak_peers.py player BAG NS [--rate HZ] [--mode objects|background|moved]
      the camera driver: plays BAG's frames in a loop at HZ (depth, IR,
      camera_info and, in a multi-frequency bag, every phasor_<k>), each
      stamped with the wall clock when published. Commands: `mode M`,
      `rate_factor F` (a burst), `malformed N` (N samples that do not decode
      and N images shorter than their size says, on depth and IR), `quit`.
      Prints `first NS N` after its first frame and after the first frame that
      follows N malformed samples, and `sent N` every second.
  soak_peers.py monitor NODE_FQN
      what a consumer sees: ~/depth/corrected (its arrival, for the latency),
      ~/translucent_mask (whether a frame was corrected: a frame passed
      through has an empty mask) and /diagnostics. Prints `c STAMP ARRIVAL`,
      `m STAMP CORRECTED`, `d JSON`; commands
      `latch`, `param NAME FLOAT` answered by `r latch|param OK MESSAGE`.
  soak_peers.py reader NODE_FQN
      a reliable reader of ~/depth/corrected that the soak stops (SIGSTOP)
      and lets go on (SIGCONT): a subscriber that stops reading, then returns.
"""

import argparse
import json
import select
import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from std_srvs.srv import Trigger


def say(*parts):
    sys.stdout.write(" ".join(str(p) for p in parts) + "\n")
    sys.stdout.flush()


def commands():
    """Lines waiting on standard input (none when nothing is there)."""
    out = []
    while select.select([sys.stdin], [], [], 0)[0]:
        line = sys.stdin.readline()
        if not line:
            out.append("quit")
            break
        out.append(line.strip())
    return out


def read_bag(path):
    """The bag's frames in stamp order: (depth, ir, [phasors]) as Image messages, and its camera_info."""
    from mcap_ros2.reader import read_ros2_messages

    by = {}
    info = None
    for m in read_ros2_messages(path):
        topic, msg = m.channel.topic, m.ros_msg
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        if topic.endswith("depth/image_raw"):
            by.setdefault(key, {})["depth"] = msg
        elif topic.endswith("ir/image_raw"):
            by.setdefault(key, {})["ir"] = msg
        elif "/phasor_" in topic and topic.endswith("/image_raw"):
            k = int(topic.rsplit("/phasor_", 1)[1].split("/")[0])
            by.setdefault(key, {})[f"phasor_{k}"] = msg
        elif topic.endswith("depth/camera_info") and info is None:
            info = msg
    frames = [by[k] for k in sorted(by) if "depth" in by[k] and "ir" in by[k]]
    return info, frames


def image(m, data=None):
    out = Image()
    out.header.frame_id = m.header.frame_id
    out.height, out.width, out.encoding = m.height, m.width, m.encoding
    out.is_bigendian, out.step = m.is_bigendian, m.step
    out.data = bytes(m.data) if data is None else data
    return out


def moved_depth(m):
    """The depth image of a camera stepped 0.5 m back: every valid pixel 500 mm farther."""
    if m.encoding == "32FC1":
        z = np.frombuffer(bytes(m.data), dtype="<f4").copy()
        z[np.isfinite(z) & (z > 0)] += 0.5
    else:
        z = np.frombuffer(bytes(m.data), dtype="<u2").copy()
        z[z > 0] += 500
    return image(m, z.tobytes())


def set_stamp(msg, ns):
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000


def player(a):
    info_msg, frames = read_bag(a.bag)
    background, objects = frames[: a.background], frames[a.background:]
    node = rclpy.create_node("soak_player")
    qos = QoSProfile(depth=10)
    ns = a.namespace.rstrip("/")
    topics = sorted(k for k in frames[0] if k.startswith("phasor_"))
    pubs = {k: node.create_publisher(Image, f"{ns}/{k}/image_raw", qos) for k in ["depth", "ir", *topics]}
    pub_info = node.create_publisher(CameraInfo, f"{ns}/depth/camera_info", qos)
    sets = {
        "background": [{k: image(v) for k, v in f.items()} for f in background],
        "objects": [{k: image(v) for k, v in f.items()} for f in objects],
    }
    sets["moved"] = [dict(f, depth=moved_depth(f["depth"])) for f in sets["objects"]]
    info = CameraInfo()
    info.header.frame_id = info_msg.header.frame_id
    info.height, info.width, info.distortion_model = info_msg.height, info_msg.width, info_msg.distortion_model
    info.d, info.k, info.r, info.p = list(info_msg.d), list(info_msg.k), list(info_msg.r), list(info_msg.p)
    info.roi = RegionOfInterest()
    # A frame published before the node's readers match is lost: wait for them.
    end = time.monotonic() + 60
    while pubs["depth"].get_subscription_count() == 0 or pubs["ir"].get_subscription_count() == 0:
        if time.monotonic() > end:
            raise SystemExit("soak player: the node never subscribed depth and IR")
        rclpy.spin_once(node, timeout_sec=0.05)
    mode, factor, k, sent, first, sent_bad = a.mode, 1.0, 0, 0, True, 0
    next_t, report_t = time.monotonic(), time.monotonic() + 1.0
    while True:
        for c in commands():
            word = c.split()
            if not word:
                continue
            if word[0] == "quit":
                node.destroy_node()
                return
            if word[0] == "mode":
                mode = word[1]
            elif word[0] == "rate_factor":
                factor = float(word[1])
            elif word[0] == "malformed":
                sent_bad = malformed(pubs, sets["objects"][0], int(word[1]))
                say("malformed_sent", sent_bad)
                first = True
            say("ack", c, time.time_ns(), sent)
        f = sets[mode][k % len(sets[mode])]
        k += 1
        t = time.time_ns()
        set_stamp(info, t)
        pub_info.publish(info)
        for key, msg in f.items():
            set_stamp(msg, t)
            pubs[key].publish(msg)
        sent += 1
        if first:
            # The first frame, and the first after malformed samples: the fault's end.
            say("first", t, sent_bad)
            first = False
        now = time.monotonic()
        if now >= report_t:
            say("sent", sent)
            report_t = now + 1.0
        next_t += 1.0 / (a.rate * factor)
        if next_t < now - 0.5:
            # Behind by more than half a second (a busy machine): do not catch up in a rush.
            next_t = now
        time.sleep(max(0.0, next_t - time.monotonic()))


def malformed(pubs, f, n):
    """`n` samples that do not decode (a serialized image cut in half) and `n` images whose
    data is shorter than `step x height`, alternately on depth and IR, each at a stamp of
    its own (so that no partner waits for them). Returns how many were sent."""
    sent = 0
    for j in range(n):
        key = "depth" if j % 2 == 0 else "ir"
        msg = image(f[key])
        set_stamp(msg, time.time_ns())
        raw = serialize_message(msg)
        pubs[key].publish(raw[: len(raw) // 2])
        short = image(f[key], bytes(f[key].data)[: len(f[key].data) // 3])
        set_stamp(short, time.time_ns())
        pubs[key].publish(short)
        sent += 2
        time.sleep(0.005)
    return sent


def stamp_ns(h):
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def monitor_main(a):
    node = rclpy.create_node("soak_monitor")
    fqn = a.node
    qos = QoSProfile(depth=10)

    def on_corrected(msg):
        say("c", stamp_ns(msg.header), time.time_ns())

    node.create_subscription(Image, f"{fqn}/depth/corrected", on_corrected, qos)

    def on_diag(msg):
        for st in msg.status:
            if st.name.endswith("pipeline"):
                say("d", json.dumps({"t": time.time_ns(), "values": {kv.key: kv.value for kv in st.values}}))

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos)

    def on_mask(msg):
        translucent = np.count_nonzero(np.frombuffer(bytes(msg.data), dtype=np.uint8))
        say("m", stamp_ns(msg.header), int(translucent > 0))

    node.create_subscription(Image, f"{fqn}/translucent_mask", on_mask, qos)
    latch = node.create_client(Trigger, f"{fqn}/latch_background")
    params = AsyncParameterClient(node, fqn)
    pending = []
    if not latch.wait_for_service(timeout_sec=60):
        raise SystemExit("soak monitor: the latch service never appeared")
    say("ready", time.time_ns())
    while True:
        rclpy.spin_once(node, timeout_sec=0.01)
        for c in commands():
            word = c.split()
            if not word:
                continue
            if word[0] == "quit":
                node.destroy_node()
                return
            if word[0] == "latch":
                pending.append(("latch", latch.call_async(Trigger.Request())))
            elif word[0] == "param":
                value = Parameter(word[1], value=float(word[2]))
                pending.append(("param", params.set_parameters([value])))
        for item in list(pending):
            what, fut = item
            if not fut.done():
                continue
            pending.remove(item)
            r = fut.result()
            if what == "latch":
                say("r", "latch", int(bool(r.success)), r.message.replace("\n", " "))
            else:
                say("r", "param", int(all(x.successful for x in r.results)), ";".join(x.reason for x in r.results))


def reader(a):
    node = rclpy.create_node("soak_reader")
    got = [0]

    def on_msg(_raw):
        got[0] += 1

    node.create_subscription(Image, f"{a.node}/depth/corrected", on_msg, QoSProfile(depth=10), raw=True)
    say("ready", time.time_ns())
    report = time.monotonic() + 1.0
    while True:
        rclpy.spin_once(node, timeout_sec=0.05)
        if time.monotonic() >= report:
            say("got", got[0])
            report = time.monotonic() + 1.0
        if "quit" in commands():
            node.destroy_node()
            return


def main():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="role", required=True)
    p = sub.add_parser("player")
    p.add_argument("bag")
    p.add_argument("namespace")
    p.add_argument("--rate", type=float, default=30.0)
    p.add_argument("--background", type=int, default=10)
    p.add_argument("--mode", default="background", choices=["background", "objects", "moved"])
    m = sub.add_parser("monitor")
    m.add_argument("node")
    r = sub.add_parser("reader")
    r.add_argument("node")
    a = ap.parse_args()
    rclpy.init()
    try:
        {"player": player, "monitor": monitor_main, "reader": reader}[a.role](a)
    except KeyboardInterrupt:
        pass
    finally:
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(main())
