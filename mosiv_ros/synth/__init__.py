"""Synthetic recordings with known ground truth, ROS-free."""
