"""redmax_ros: RedMax articulated-body simulation (Wang et al. 2019) on Pinocchio, served over ROS 2."""
