"""ROS 2 wiring: the only code that imports rclpy or message packages."""
