"""rclpy shells over the core: the only place in the package that imports rclpy."""
