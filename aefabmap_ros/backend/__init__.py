"""An example SLAM backend on /loop_closures: an iSAM2 pose graph (what pose_graph_node runs)."""

__all__ = ["pose_graph"]
