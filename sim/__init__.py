"""A 2D multi-robot simulator: Gazebo worlds, diff drive, LIDAR, tag camera, ground truth."""
