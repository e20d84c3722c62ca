"""Recording of the node's topics (MCAP, ROS 2 conventions). No rclpy needed here."""
from .mcap_log import McapLogger, message_definition, qos_profiles_yaml, recover

__all__ = ["McapLogger", "message_definition", "qos_profiles_yaml", "recover"]
