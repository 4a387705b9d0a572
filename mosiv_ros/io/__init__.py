"""ROS-free bag and message I/O: rosbag2 recordings, message <-> numpy conversions."""
