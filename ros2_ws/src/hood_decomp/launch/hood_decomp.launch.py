"""The three hood_decomp nodes, for cells with a full ROS 2 installation (launch_ros):

    ros2 launch hood_decomp hood_decomp.launch.py bases:=/path/to/bases.h5

Without launch_ros (the PyPI wheels), `hood-decomp launch --bases B` starts the same three processes.
"""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    params = str(Path(get_package_share_directory("hood_decomp")) / "config" / "hood_decomp.yaml")
    bases = LaunchConfiguration("bases")
    nodes = [
        # lifecycle nodes: autostart configures and activates each at start-up (a cell with its own lifecycle
        # manager sets autostart false and drives the transitions itself)
        Node(package="hood_decomp", executable=executable, output="screen",
             parameters=[params, {"bases": bases, "autostart": LaunchConfiguration("autostart")}])
        for executable in ("scan_node", "estimator_node", "decomposition_node")
    ]
    return LaunchDescription([DeclareLaunchArgument("bases", description="path of the bases file"),
                              DeclareLaunchArgument("autostart", default_value="true",
                                                    description="configure and activate the nodes at start-up"),
                              *nodes])
