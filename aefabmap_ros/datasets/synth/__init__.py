"""The synthetic town: a textured 3-D world rendered along looping routes, with poses and ground truth."""

__all__ = ["town"]
