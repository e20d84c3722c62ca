"""The ROS 2 node (rclpy): main.py (node), engine.py (simulation thread), convert.py, pacing.py."""
