"""Bridge plugins: ROS 2 topics in and out of a graph."""
