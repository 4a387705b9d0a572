"""Launch the mosiv_ros node graph on a ROS 2 Jazzy install.

    ros2 launch mosiv_ros mosiv.launch.py bag:=/path/to/recording rate:=1.0

Starts the graph that ``mosiv_ros.graph.graph_nodes`` describes (the four pipeline nodes, then
bag_replay_node) with the parameters of share/mosiv_ros/config/mosiv.yaml (or params_file:=...).
Without a ``bag`` argument the replay node is not started and the pipeline listens to live camera
topics. The project's own runner (``mosiv graph``, used where `launch` is not installed) starts
the same description.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

from mosiv_ros.graph import PACKAGE, REPLAY_NODE, graph_nodes


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory(PACKAGE), "config", "mosiv.yaml")
    params_file = LaunchConfiguration("params_file")
    bag = LaunchConfiguration("bag")
    arguments = [
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS 2 params file for every node"),
        DeclareLaunchArgument("bag", default_value="",
                              description="rosbag2 directory to replay; empty = live topics"),
        DeclareLaunchArgument("rate", default_value="1.0", description="replay rate, 0 = fastest"),
        DeclareLaunchArgument("scene", default_value=bag,
                              description="scene declaration: bag directory, YAML file or text"),
    ]
    with_bag = IfCondition(PythonExpression(["'", bag, "' != ''"]))
    nodes = [
        Node(package=PACKAGE, executable=spec.executable, name=spec.executable, output="screen",
             parameters=[params_file, spec.parameters],
             condition=with_bag if spec.executable == REPLAY_NODE else None)
        for spec in graph_nodes(bag, LaunchConfiguration("rate"), LaunchConfiguration("scene"))
    ]
    return LaunchDescription(arguments + nodes)
