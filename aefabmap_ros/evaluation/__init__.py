"""Offline evaluation: the paper's methods and protocol, metrics, ground truth, calibration, trajectory
error, tf-idf baseline, the nodes' decision chain run offline, and the figures."""

__all__ = [
    "calibration",
    "ground_truth",
    "methods",
    "metrics",
    "online_chain",
    "plots",
    "protocol",
    "tfidf",
    "trajectory_error",
]
