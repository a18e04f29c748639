"""The type table (one row per ROS type) and the host configuration resolved against it."""
