"""Geometric verification benchmark: cost per verified candidate, and the verifier's memory per frame.

On synthetic 640 x 480 frames along a trajectory, for each feature type and keypoint budget: the
time to verify a candidate (descriptor matching, then the MAGSAC++ fundamental matrix) for pairs
of nearby frames (2 frames apart: mostly overlapping views, where the geometry should be found)
and of distant frames (camera centres more than --distance metres apart: it should not, except
where the town repeats a facade exactly, which fools geometry too), and the bytes verifier_node
keeps per frame. For scale,
the feature extraction of one frame is timed too: verification runs up to ``candidates`` times
per loop closure (re-ranking), extraction once per image. "per closure" is verifier_node's cost of
one closure on its stored features (the strongest 500 keypoints): the matched place, then, when
it is accepted, the other candidates (here the 4 frames before it). Also what a pair
costs with depth ("with depth": the same pairs verified with the rendered depth at their keypoints,
so the metric test tries a pair the epipolar test refused for its share and checks the view overlap
and covisibility of one it accepted), as a ratio to the same pairs without.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.town import generate_sequence
from aefabmap_ros.features.extraction import FeatureConfig, Features, extract_features
from aefabmap_ros.verification.feature_store import FeatureStore
from aefabmap_ros.verification.frame_depths import FrameDepths
from aefabmap_ros.verification.geometric import VerificationConfig, match_descriptors, verify_pair
from aefabmap_ros.verification.metric import KeypointDepths
from aefabmap_ros.verification.relative_pose import CameraModel
from aefabmap_ros.verification.reranking import rerank_by_inliers


def _ms(values_s: list[float]) -> str:
    values = np.asarray(values_s) * 1e3
    return f"median {np.median(values):7.2f} ms  p95 {np.percentile(values, 95):7.2f} ms"


def _timed_pairs(features: list[Features], pairs: list[tuple[int, int]],
                 config: VerificationConfig) -> tuple[list[float], list[float], list[int]]:
    """(matching seconds, whole-verification seconds, inliers) per pair."""
    matching, total, inliers = [], [], []
    for query, place in pairs:
        started = time.perf_counter()
        match_descriptors(features[query], features[place], config.ratio)
        matching.append(time.perf_counter() - started)
        started = time.perf_counter()
        result = verify_pair(features[query], features[place], config)
        total.append(time.perf_counter() - started)
        inliers.append(result.inliers)
    return matching, total, inliers


def _timed_closures(stored: list[Features], config: VerificationConfig) -> tuple[list[float], int]:
    """(seconds per closure, closures accepted) for queries matched to the frame 2 before them."""
    seconds, accepted = [], 0
    for query in range(config.candidates + 1, len(stored)):
        ranked = [stored[query - 2 - k] for k in range(config.candidates)]
        started = time.perf_counter()
        outcome = rerank_by_inliers(ranked, partial(verify_pair, stored[query], config=config), require_best=True)
        seconds.append(time.perf_counter() - started)
        accepted += outcome is not None
    return seconds, accepted


@dataclass(frozen=True)
class DepthTiming:
    """Verifying pairs with their keypoints' depth: the seconds of each, and what the metric test decided."""

    seconds: list[float]
    share_refused_tried: int  # pairs the epipolar test refused for their share that the metric test tried
    share_refused_accepted: int  # of those, accepted
    accepted_checked: int  # pairs the epipolar test accepted whose view overlap was measured
    accepted_refused: int  # of those, refused: no overlap under their motion


def _timed_with_depth(features: list[Features], depths: np.ndarray, camera: CameraModel,
                      pairs: list[tuple[int, int]], config: VerificationConfig) -> DepthTiming:
    """Verify each pair with its frames' depths (sampled beforehand as verifier_node keeps them: at the keypoints
    and on the coarse grid of the covisibility test)."""
    size = (depths.shape[2], depths.shape[1])
    seconds: list[float] = []
    tried = accepted = checked = refused = 0
    for query, place in pairs:
        kept = [FrameDepths.sample(depths[frame], features[frame].keypoints) for frame in (query, place)]
        keypoint_depths = KeypointDepths(camera, size, kept[0].keypoints, kept[1].keypoints, kept[0].grid,
                                         kept[1].grid)
        started = time.perf_counter()
        result = verify_pair(features[query], features[place], config, keypoint_depths)
        seconds.append(time.perf_counter() - started)
        ran = result.metric is not None
        tried += ran and not result.epipolar_accepted
        accepted += result.accepted and not result.epipolar_accepted
        checked += ran and result.epipolar_accepted
        refused += result.epipolar_accepted and not result.accepted
    return DepthTiming(seconds, tried, accepted, checked, refused)


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bench verify", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60, help="synthetic frames (default 60)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--features", nargs="+", default=["sift", "orb"], choices=["sift", "rootsift", "orb"])
    parser.add_argument("--max-features", nargs="+", type=int, default=[500, 1000],
                        help="keypoint budgets per image (default 500 1000)")
    parser.add_argument("--distance", type=float, default=25.0, help="distant pairs: metres apart at least")
    parser.add_argument("--quick", action="store_true", help="seconds-long smoke run (small frames)")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


def run(args: argparse.Namespace) -> int:
    if args.quick:
        args.frames, args.width, args.height, args.max_features = 12, 320, 240, [200]

    sequence = generate_sequence(SynthConfig(num_frames=args.frames, width=args.width, height=args.height))
    images = sequence.images
    near = [(i + 2, i) for i in range(len(images) - 2)]
    apart = np.linalg.norm(sequence.positions[:, None, :] - sequence.positions[None, :, :], axis=2)
    far = [(int(i), int(j)) for i, j in zip(*np.nonzero(np.tril(apart > args.distance)), strict=True)]
    far = far[:: max(1, len(far) // 60)]  # about 60 of them, spread over the sequence
    config = VerificationConfig()
    print(f"{len(images)} synthetic frames {args.width}x{args.height}; {len(near)} nearby pairs "
          f"(2 frames apart), {len(far)} distant pairs (> {args.distance:g} m); min_inliers {config.min_inliers}")
    for kind in args.features:
        for budget in args.max_features:
            feature_config = FeatureConfig(type=kind, max_features=budget)
            extraction, features = [], []
            for image in images:
                started = time.perf_counter()
                features.append(extract_features(image, feature_config))
                extraction.append(time.perf_counter() - started)
            store = FeatureStore(max_frames=len(features), max_features_per_frame=500)
            for stamp, frame in enumerate(features):
                store.add(stamp, frame)
            count = np.mean([len(f) for f in features])
            print(f"\n[{kind}, at most {budget} keypoints: {count:.0f} per frame on average]")
            print(f"  feature extraction     {_ms(extraction)}  (per image, for scale)")
            for name, pairs in (("nearby", near), ("distant", far)):
                matching, total, inliers = _timed_pairs(features, pairs, config)
                accepted = sum(1 for n in inliers if n >= config.min_inliers)
                print(f"  verify {name:12s}   {_ms(total)}  (matching {np.median(matching) * 1e3:.2f} ms); "
                      f"accepted {accepted}/{len(pairs)}, median inliers {np.median(inliers):.0f}")
                depth = _timed_with_depth(features, sequence.depths, CameraModel(sequence.camera_matrix), pairs,
                                          config)
                print(f"    with depth           {_ms(depth.seconds)}  "
                      f"({np.median(depth.seconds) / np.median(total):.2f}x without; the metric test ran on "
                      f"{depth.share_refused_tried} refused for their share, accepted {depth.share_refused_accepted}; "
                      f"on {depth.accepted_checked} accepted, refused {depth.accepted_refused})")
            stored = [kept for stamp in range(len(features)) if (kept := store.get(stamp)) is not None]
            closure_s, closures_accepted = _timed_closures(stored, config)
            print(f"  per closure, {config.candidates} cand. {_ms(closure_s)}  "
                  f"(accepted {closures_accepted}/{len(closure_s)})")
            print(f"  verifier_node memory   {store.nbytes / len(store) / 1024:.0f} KiB per frame "
                  f"(500 strongest keypoints kept)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
