"""mosiv_ros: multi-object system identification from video, as a ROS 2 node suite.

The subpackages other than ``mosiv_ros.nodes`` form the ROS-free core: they never import rclpy.
"""

__version__ = "0.1.0"
