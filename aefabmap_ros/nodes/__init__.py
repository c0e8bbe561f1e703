"""Everything ROS: the rclpy nodes, message conversion, the launch table. The only folder (with the
launchers in ``cli``) that imports rclpy or message types."""

__all__ = [
    "closure_messages",
    "closure_view_node",
    "common",
    "delivery",
    "fabmap_node",
    "feature_node",
    "frame_gate",
    "future_stamps",
    "graph_view",
    "gtsam_poses",
    "launch_table",
    "messages",
    "pipeline",
    "pose_graph_node",
    "quantizer_node",
    "sensor_inputs",
    "verifier_node",
    "verifier_parameters",
    "verifier_summary",
    "view_messages",
]
