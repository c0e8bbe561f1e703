"""aefabmap_pipeline: feature, quantizer and FAB-MAP nodes in one process (multi-threaded executor).

Same topics and parameters as the separate nodes (each keeps its own node name, so one YAML file
serves both ways of running), without three Python interpreters and model loads.
"""

from __future__ import annotations

from aefabmap_ros.nodes.common import run_nodes
from aefabmap_ros.nodes.fabmap_node import FabMapNode
from aefabmap_ros.nodes.feature_node import FeatureNode
from aefabmap_ros.nodes.quantizer_node import QuantizerNode


def main(args: list[str] | None = None) -> int:
    return run_nodes([FeatureNode, QuantizerNode, FabMapNode], args)


if __name__ == "__main__":
    raise SystemExit(main())
