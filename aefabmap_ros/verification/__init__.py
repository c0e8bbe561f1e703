"""Geometric verification of loop-closure candidates (with depth, the metric test too), loop tracking, and the
relative pose of a closure."""

__all__ = ["geometric", "loop_tracking", "metric", "relative_pose"]
