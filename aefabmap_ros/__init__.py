"""aefabmap_ros: online visual loop-closure detection with AE-FABMAP for ROS 2."""

__version__ = "0.1.0"
