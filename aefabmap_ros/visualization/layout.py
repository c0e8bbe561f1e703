"""The Foxglove layout of the live view and of a run's recording (aefabmap_ros/config/foxglove_layout.json).

Built with the SDK's own layout types, so the file follows Foxglove's schema; the shipped JSON is this
function's output (test/visualization/test_layout.py keeps the two equal). Regenerate it with
``python -m aefabmap_ros.visualization.layout > aefabmap_ros/config/foxglove_layout.json``.
"""

from __future__ import annotations

import json

import foxglove.layouts as fl

CLOSURE_PICTURES = "/closure_view/closures"
REFUSED_PICTURES = "/closure_view/refused"
POSTERIORS = "/place_posteriors"
GRAPH_MARKERS = "/pose_graph/markers"
GRAPH_PATH = "/pose_graph/path"
TOP_PLACES = 3  # posterior series of the best-ranked places plotted beside the new-place probability


def view_layout() -> fl.Layout:
    """Left: the latest closure picture over the latest refused candidate. Right: the 3-D pose graph over a plot
    of the new-place probability and the top places' posteriors."""
    pictures = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=1, content=_image_panel("Verified closures (green: RANSAC inliers)", CLOSURE_PICTURES)),
        fl.SplitItem(proportion=1, content=_image_panel("Refused candidates", REFUSED_PICTURES)),
    ])
    series = [fl.PlotSeries(value=f"{POSTERIORS}.new_place_probability", label="p(new place)")]
    series += [fl.PlotSeries(value=f"{POSTERIORS}.probabilities[{rank}]", label=f"place ranked {rank + 1}")
               for rank in range(TOP_PLACES)]
    plot = fl.PlotPanel(title="Place posterior", config=fl.PlotConfig(paths=series, min_y_value=0, max_y_value=1))
    graph = fl.ThreeDeePanel(title="Pose graph (green: loops added, red: refused by the odometry gate)",
                             config=fl.ThreeDeeConfig(follow_tf="map", topics={
                                 GRAPH_MARKERS: fl.BaseRendererRosMarkerTopicSettings(visible=True),
                                 GRAPH_PATH: fl.BaseRendererPoseTopicSettings(visible=True),
                             }))
    right = fl.SplitContainer(direction="column", items=[fl.SplitItem(proportion=2, content=graph),
                                                         fl.SplitItem(proportion=1, content=plot)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[fl.SplitItem(proportion=1, content=pictures),
                                                                       fl.SplitItem(proportion=1, content=right)]))


def _image_panel(title: str, topic: str) -> fl.ImagePanel:
    return fl.ImagePanel(title=title, config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic=topic)))


def layout_json() -> str:
    """The layout as the shipped file holds it: indented, one trailing newline."""
    return json.dumps(json.loads(view_layout().to_json()), indent=2) + "\n"


if __name__ == "__main__":
    print(layout_json(), end="")
