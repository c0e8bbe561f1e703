"""aefabmap_robot_pipeline: a robot's side of a base station (docs/fleet.md) in one process.

feature_node, quantizer_node and feature_server_node with a multi-threaded executor, as aefabmap_pipeline
runs the single host's detection nodes: one Python interpreter and one model load on the robot instead of
three. Start it in the robot's namespace (``-r __ns:=/robot1``) with quantizer_node's words remapped onto
the feature server's input (``-r quantizer_node:aefabmap/words:=aefabmap/robot_words``), as
``aefabmap_launch --robot-side --pipeline`` does.
"""

from __future__ import annotations

from aefabmap_ros.nodes.common import run_nodes
from aefabmap_ros.nodes.feature_node import FeatureNode
from aefabmap_ros.nodes.feature_server_node import FeatureServerNode
from aefabmap_ros.nodes.quantizer_node import QuantizerNode


def main(args: list[str] | None = None) -> int:
    return run_nodes([FeatureNode, QuantizerNode, FeatureServerNode], args)


if __name__ == "__main__":
    raise SystemExit(main())
