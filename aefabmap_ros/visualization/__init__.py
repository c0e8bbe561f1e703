"""Pictures of what the detector did, for people: closure images with their matches, pose-graph markers, the
Foxglove layout and the evaluation's HTML page. Pure: no ROS imports (nodes/ turns these into messages)."""

__all__ = ["candidates", "closure_album", "graph_markers", "html_report", "layout", "match_picture", "stores"]
