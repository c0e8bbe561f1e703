"""aefabmap_ros: online visual loop-closure detection with AE-FABMAP for ROS 2."""

__version__ = "0.1.0"

# The library by concern (each folder's docstring says what lives in it); errors and stamps serve all.
__all__ = ["__version__", "backend", "cli", "datasets", "errors", "evaluation", "fabmap", "features", "io", "model",
           "nodes", "stamps", "verification", "visualization",
           "vocabulary"]
