"""Geometric verification of loop-closure candidates, loop tracking, and the relative pose of a closure."""

__all__ = ["geometric", "loop_tracking", "relative_pose"]
