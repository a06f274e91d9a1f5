"""tal_core: robot model, leg/frame conventions, terrain description and shared math for tal.

This package never imports rclpy; nodes in the other packages adapt it to ROS 2.
"""
