"""The decision between FAB-MAP's candidates and /loop_closures, without ROS: geometric verification (with
depth, the metric and covisibility tests too), re-ranking, loop tracking, the odometry gate's interface, one
frame store bounded by bytes, and the relative pose of a closure (chain.py ties them together)."""

__all__ = [
    "chain",
    "closures",
    "depth_wait",
    "feature_server",
    "feature_store",
    "frame_depths",
    "frame_requests",
    "frame_store",
    "gate",
    "geometric",
    "loop_tracking",
    "metric",
    "odometry_wait",
    "pair_check",
    "places",
    "pose_covariance",
    "pose_error",
    "relative_pose",
    "reranking",
    "rigid_alignment",
    "tracking_search",
]
