# Included by scripts/setup.sh into each msg_defs/ package (cmake -DCMAKE_PROJECT_INCLUDE=this file, run right
# after the package's project() call): keep only the rosidl generators a Python node needs (type description,
# C, the C typesupports, Python) and drop the four C++ ones (rosidl_generator_cpp, rosidl_typesupport_cpp,
# _fastrtps_cpp, _introspection_cpp). rclpy reaches messages through the C typesupports only, so nothing in
# this project uses the C++ bindings, and skipping them halves the colcon build (2026-12-05, quiet 2-core
# machine: 166 s wall / 238 s CPU for all generators, 76 s / 112 s without the C++ ones).
#
# ament configs guard against a second inclusion, so the generators registered here are the ones
# rosidl_generate_interfaces() runs later; the packages' own CMakeLists.txt are those of a normal colcon build
# (an apt ROS user's `colcon build` without this file generates every binding).
find_package(rosidl_default_generators REQUIRED)
list(FILTER AMENT_EXTENSIONS_rosidl_generate_idl_interfaces EXCLUDE REGEX "_cpp:")
message(STATUS "redmax_ros: rosidl generators for C and Python only: ${AMENT_EXTENSIONS_rosidl_generate_idl_interfaces}")
