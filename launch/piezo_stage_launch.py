"""ros2 launch piezo_stage piezo_stage_launch.py  (full ROS 2 installs only).

The same node set as `piezo-stage launch`, from the same parameter file. Where the
launch tooling is not installable (wheels-only environments) use `piezo-stage launch`.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = ("stage_driver", "feedforward", "controller", "trajectory", "identifier")


def generate_launch_description():
    default_cfg = os.path.join(get_package_share_directory("piezo_stage"), "config",
                               "stage.yaml")
    cfg = LaunchConfiguration("config")
    ns = LaunchConfiguration("namespace")
    return LaunchDescription(
        [DeclareLaunchArgument("config", default_value=default_cfg),
         DeclareLaunchArgument("namespace", default_value="stage")]
        + [Node(package="piezo_stage", executable=n, name=n, namespace=ns,
                parameters=[cfg], output="screen") for n in NODES])
