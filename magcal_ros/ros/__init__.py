"""ROS 2 layer: nodes and message conversions; the only package that imports rclpy."""
