"""ROS-free numerical core (numpy/scipy only); never import rclpy or *_msgs here."""
