"""The offline chain (evaluation/online_chain.py) against a lockstep run of the nodes, closure for closure.

    PYTHONPATH=. .venv/bin/python scripts/compare_online_chain.py TEST_DIR RUN_DIR [--no-odometry]

TEST_DIR is an aefabmap_synth sequence (bag/ with /image, /depth, /camera_info, /odom); RUN_DIR an
``aefabmap_demo --online-only`` output (its online_recording and evaluation_online/closures.csv). The
chain gets the frames the nodes processed (the recorded place_posteriors' stamps: feature_node's
detection rate skips others), their features as the model extracts them, the bag's depth (as
verifier_node keeps it) for the frames the run kept a depth of (its store's depth chunks: a depth image
that waited too long for its features is not kept, which varies from run to run), intrinsics and odometry,
and the shipped configs; it prints how many closures each published and every one that differs.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from aefabmap_ros.cli.evaluate_depth import _camera_from_bag, _depth_from_bag, _odometry_from_bag, example_backend_gate
from aefabmap_ros.evaluation.online_chain import ChainInputs, run_online_chain
from aefabmap_ros.evaluation.protocol import model_tree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.features.extraction import extract_features
from aefabmap_ros.io import bags
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.model.training import count_bow
from aefabmap_ros.verification.feature_store import DEFAULT_MAX_STORED_FEATURES, stored_rows
from aefabmap_ros.verification.frame_depths import FrameDepths
from aefabmap_ros.verification.geometric import VerificationConfig


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("test", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--model", type=Path, default=Path("output/demo/models/autoencoder"),
                        help="model folder (default: the demo's, from the checkout's root)")
    parser.add_argument("--no-odometry", action="store_true", help="the chain without the odometry gate")
    args = parser.parse_args()
    bag = args.test / "bag"
    processed = {m.stamp_ns for m in bags.read_messages(args.run / "online_recording", ["/place_posteriors"])}
    model = load_model(args.model)
    stamps, features = [], []
    for stamp_ns, gray in ImageSource(bag=bag, topic="/image").frames():
        if stamp_ns in processed:
            stamps.append(stamp_ns)
            features.append(extract_features(gray, model.feature_config))
    stamps_ns = np.array(stamps, dtype=np.int64)
    camera, size = _camera_from_bag(bag, "/camera_info")
    depths: list[FrameDepths | None] = [None] * len(features)
    kept_depth = {int(stamp) for chunk in (args.run / "map.features").glob("depth-*.npz")
                  for stamp in np.load(chunk)["stamps_ns"]}
    for index, depth in _depth_from_bag(bag, "/depth", stamps_ns):
        if int(stamps_ns[index]) not in kept_depth:
            continue
        rows = stored_rows(features[index], DEFAULT_MAX_STORED_FEATURES)
        depths[index] = FrameDepths.sample(depth.astype(np.float16).astype(np.float32),
                                           features[index].keypoints[rows, :2].astype(np.float32))
    odometry = [] if args.no_odometry else _odometry_from_bag(bag, "/odom")
    inputs = ChainInputs(VerificationConfig(), features, depths, camera, size, odometry,
                         gate_factory=example_backend_gate)
    chain = run_online_chain(count_bow(model.quantizer, features), stamps_ns, model_tree(model),
                             model.new_place_samples, FabMapConfig(), inputs)
    offline = {(int(stamps_ns[c.query_frame]), int(stamps_ns[c.matched_frame])) for c in chain.published}
    nodes = set()
    with open(args.run / "evaluation_online" / "closures.csv") as file:
        for row in csv.DictReader(file):
            if row["topic"] == "loop_closures":
                nodes.add((_ns(row["query_stamp"]), _ns(row["matched_stamp"])))
    print(f"{len(stamps)} frames; offline chain published {len(chain.published)} ({len(offline)} distinct), nodes "
          f"{len(nodes)}; in both {len(offline & nodes)}, offline only {len(offline - nodes)}, nodes only "
          f"{len(nodes - offline)}; offline counters: {dict(sorted(chain.outcomes.items()))}")
    for name, pairs in (("offline only", offline - nodes), ("nodes only", nodes - offline)):
        for query_ns, place_ns in sorted(pairs):
            print(f"  {name}: query {query_ns / 1e9:.3f} s -> place {place_ns / 1e9:.3f} s")
    return 0 if offline == nodes else 1


def _ns(seconds: str) -> int:
    whole, _, fraction = seconds.partition(".")
    return int(whole) * 1_000_000_000 + int((fraction + "000000000")[:9])


if __name__ == "__main__":
    sys.exit(main())
