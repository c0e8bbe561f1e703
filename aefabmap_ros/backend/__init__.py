"""An example SLAM backend on /loop_closures: an iSAM2 pose graph (what pose_graph_node runs), and the
odometry test of a closure it shares with verifier_node's odometry gate."""

__all__ = [
    "factor_graph",
    "factors",
    "graph_file",
    "graph_types",
    "keyframe_graph",
    "odometry",
    "odometry_gate",
    "pose_graph",
    "robot_feeds",
    "sessions",
]
