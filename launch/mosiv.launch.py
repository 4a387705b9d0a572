"""Launch the mosiv_ros node graph on a ROS 2 Jazzy install.

    ros2 launch mosiv_ros mosiv.launch.py bag:=/path/to/recording rate:=1.0

Starts the four pipeline nodes and bag_replay_node with the parameters of
share/mosiv_ros/config/mosiv.yaml (or params_file:=...). Without a ``bag`` argument the replay
node is not started and the pipeline listens to live camera topics. The project's own runner
(mosiv_ros/graph.py, used by `mosiv graph` and the tests) starts the same executables with the
same parameters where `launch` is not installed.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

PIPELINE = ("reconstruction_node", "lifting_node", "identify_node", "prediction_node")


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("mosiv_ros"), "config", "mosiv.yaml")
    params_file = LaunchConfiguration("params_file")
    bag = LaunchConfiguration("bag")
    scene = LaunchConfiguration("scene")
    arguments = [
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS 2 params file for every node"),
        DeclareLaunchArgument("bag", default_value="",
                              description="rosbag2 directory to replay; empty = live topics"),
        DeclareLaunchArgument("rate", default_value="1.0", description="replay rate, 0 = fastest"),
        DeclareLaunchArgument("scene", default_value=bag,
                              description="scene declaration: bag directory, YAML file or text"),
    ]
    pipeline = [
        Node(package="mosiv_ros", executable=name, name=name, output="screen",
             parameters=[params_file, {"scene": scene}])
        for name in PIPELINE
    ]
    replay = Node(
        package="mosiv_ros", executable="bag_replay_node", name="bag_replay_node", output="screen",
        parameters=[params_file, {"bag": bag, "rate": LaunchConfiguration("rate"),
                                  "wait_for_subscribers": 1}],
        condition=IfCondition(PythonExpression(["'", bag, "' != ''"])),
    )
    return LaunchDescription(arguments + pipeline + [replay])
