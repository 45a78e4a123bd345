"""ros2 launch piezo_stage piezo_stage_launch.py [config:=FILE] [namespace:=stage]
[record:=BAG_DIR] [arm:=true] [foxglove:=8765]   (full ROS 2 installs only).

The same node set as `piezo-stage launch`, built by the same code: the nodes the
parameter file configures (recorder when ``record`` is given, identifier and gap
included), each with the parameters our launcher gives it (start-up gating, the
recorder's bag, one clock in lockstep, auto-arming). Where the launch tooling is not
installable (wheels-only environments) use `piezo-stage launch`.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription
from piezo_stage.launcher.launcher import Launch, LaunchOptions


def _nodes(context):
    cfg = LaunchConfiguration("config").perform(context)
    ns = "/" + LaunchConfiguration("namespace").perform(context).strip("/")
    record = LaunchConfiguration("record").perform(context) or None
    arm = LaunchConfiguration("arm").perform(context).lower() in ("true", "1", "yes")
    port = LaunchConfiguration("foxglove").perform(context)
    launch = Launch(cfg, LaunchOptions(record=record, namespace=ns, arm=arm,
        foxglove_port=int(port) if port else None))
    return [Node(package="piezo_stage", executable=n, name=n, namespace=ns,
                 parameters=[cfg, launch.node_params(n)], output="screen",
                 additional_env=launch.node_env)
            for n in launch.nodes]


def generate_launch_description():
    default_cfg = os.path.join(get_package_share_directory("piezo_stage"), "config",
                               "stage.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=default_cfg),
        DeclareLaunchArgument("namespace", default_value="stage"),
        DeclareLaunchArgument("record", default_value="",
                              description="bag directory ('' = no recorder)"),
        DeclareLaunchArgument("arm", default_value="true"),
        DeclareLaunchArgument("foxglove", default_value="",
                              description="live view WebSocket port ('' = none)"),
        OpaqueFunction(function=_nodes)])
