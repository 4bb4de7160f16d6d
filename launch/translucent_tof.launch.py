"""Starts translucent_tof's node in a sourced ROS 2 workspace.

    ros2 launch translucent_tof translucent_tof.launch.py \
        namespace:=/tof params_file:=/path/to/params.yaml \
        depth_topic:=/camera/depth/image_raw ir_topic:=/camera/ir/image_raw \
        info_topic:=/camera/depth/camera_info

Every argument is optional: by default the node runs in /tof with
config/translucent_tof.yaml (every parameter at its default) and subscribes
depth/image_raw, ir/image_raw and depth/camera_info in that namespace.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("translucent_tof"), "config", "translucent_tof.yaml")
    args = [
        DeclareLaunchArgument("namespace", default_value="/tof", description="the node's namespace"),
        DeclareLaunchArgument("node_name", default_value="translucent_tof", description="the node's name"),
        DeclareLaunchArgument("params_file", default_value=default_params, description="ROS 2 parameter YAML"),
        DeclareLaunchArgument("depth_topic", default_value="depth/image_raw", description="depth input"),
        DeclareLaunchArgument("ir_topic", default_value="ir/image_raw", description="IR input"),
        DeclareLaunchArgument("info_topic", default_value="depth/camera_info", description="camera_info input"),
        DeclareLaunchArgument("log_level", default_value="info", description="debug, info, warn or error"),
    ]
    node = Node(
        package="translucent_tof",
        executable="node",
        name=LaunchConfiguration("node_name"),
        namespace=LaunchConfiguration("namespace"),
        parameters=[LaunchConfiguration("params_file")],
        remappings=[
            ("depth/image_raw", LaunchConfiguration("depth_topic")),
            ("ir/image_raw", LaunchConfiguration("ir_topic")),
            ("depth/camera_info", LaunchConfiguration("info_topic")),
        ],
        arguments=["--ros-args", "--log-level", LaunchConfiguration("log_level")],
        output="screen",
        emulate_tty=True,
    )
    return LaunchDescription(args + [node])
