"""Differentiable multi-object MLS-MPM simulator (Warp), ROS-free."""
