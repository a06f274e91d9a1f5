"""tal_core's ROS side: node utilities, message conversions and MCAP bag I/O. The rest of tal_core is pure
Python and never imports rclpy."""
