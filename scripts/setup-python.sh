#!/usr/bin/env bash
# Creates the Python virtual environment used by the bag interoperability
# tests (tests/bag_interop.rs): independent ROS 2 MCAP readers and writers;
# by the DDS peer tests (tests/cyclone_peer.rs, tests/rclpy_graph.rs); and by
# the Rerun recording checks of tests/cli.rs (`rerun rrd verify`); and by
# the soak's plot (scripts/soak).
#
#   bash scripts/setup-python.sh          # venv at <repo>/.venv
#   TTOF_VENV=/some/dir bash scripts/setup-python.sh
#
# Then `cargo test --test bag_interop` finds <repo>/.venv/bin/python, or the
# interpreter named by TTOF_PYTHON.
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${TTOF_VENV:-$repo/.venv}"
python="${PYTHON:-python3}"

# Versions checked to work with the interop tests.
ROSBAGS_VERSION="0.11.9"
MCAP_VERSION="1.6.0"
MCAP_ROS2_VERSION="0.6.0"
# Eclipse Cyclone DDS: the independent DDS peer of tests/dds_peer.rs.
CYCLONEDDS_VERSION="11.0.1"
# rclpy on Fast DDS (rmw_fastrtps_cpp) without a ROS installation: the peer of
# tests/rclpy_graph.rs (PyPI ros-* wheels, ROS 2 Kilted builds).
RCLPY_VERSION="9.1.2"
RMW_FASTRTPS_VERSION="9.3.3"
ROS_MSGS_VERSION="5.5.1"       # sensor_msgs, std_srvs, diagnostic_msgs
RCL_INTERFACES_VERSION="2.3.0"
# The Rerun CLI (`rerun rrd verify`) of the same version as the Rust crate
# `rerun` in Cargo.lock: a recording is checked by the reader of its own version.
RERUN_SDK_VERSION="0.36.3"
# The soak's plot of memory and latency over time (scripts/soak).
MATPLOTLIB_VERSION="3.10.9"

if [ ! -x "$venv/bin/python" ]; then
    echo "creating venv at $venv"
    "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    "rosbags==$ROSBAGS_VERSION" \
    "mcap==$MCAP_VERSION" \
    "mcap-ros2-support==$MCAP_ROS2_VERSION" \
    "cyclonedds==$CYCLONEDDS_VERSION" \
    "ros-rclpy==$RCLPY_VERSION" \
    "ros-rmw-fastrtps-cpp==$RMW_FASTRTPS_VERSION" \
    "ros-sensor-msgs==$ROS_MSGS_VERSION" \
    "ros-std-srvs==$ROS_MSGS_VERSION" \
    "ros-diagnostic-msgs==$ROS_MSGS_VERSION" \
    "ros-rcl-interfaces==$RCL_INTERFACES_VERSION" \
    "rerun-sdk==$RERUN_SDK_VERSION" \
    "matplotlib==$MATPLOTLIB_VERSION"
"$venv/bin/python" - <<'PY'
import importlib.metadata as md
for name in ("rosbags", "mcap", "mcap-ros2-support", "cyclonedds", "ros-rclpy", "ros-rmw-fastrtps-cpp", "rerun-sdk", "matplotlib"):
    print(f"{name}=={md.version(name)}")
PY
echo "ok: run the interop tests with: cargo test --test bag_interop"
