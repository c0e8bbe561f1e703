"""Geometric verification of loop-closure candidates (with depth, the metric and covisibility tests too), what is
kept of each frame's depth for them, loop tracking, and the relative pose of a closure."""

__all__ = ["frame_depths", "geometric", "loop_tracking", "metric", "relative_pose"]
