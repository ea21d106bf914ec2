"""ROS-free readers and writers: wide CSV, rosbag2 (via rosbags), calibration YAML."""
