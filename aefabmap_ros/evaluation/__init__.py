"""Offline evaluation: the paper's methods and protocol, metrics, ground truth (from poses, from depth),
calibration, trajectory error, tf-idf baseline, the nodes' decision chain run offline, recorded runs, and the
reports and figures."""

__all__ = [
    "calibration",
    "closure_listing",
    "closure_scores",
    "covisibility",
    "ground_truth",
    "methods",
    "metrics",
    "online_chain",
    "plots",
    "protocol",
    "recordings",
    "reports",
    "session_scores",
    "session_trajectory",
    "tfidf",
    "trajectory_error",
    "word_statistics",
]
