"""aefabmap_eval: the paper's comparison (FABMAP2, AE-FABMAP, BoW, AE-BoW) on a test sequence.

    # train both vocabularies on other images, then evaluate on the test folder
    aefabmap_eval --images test/images --gt test/loop_gt.npz --train-images train/images --out results/
    # a bag topic, ground truth from KITTI poses (10 m, 30 degrees, 10 frames apart)
    aefabmap_eval --bag test/bag --topic /image --poses test/poses.txt --max-distance 10 --max-angle 30 \\
        --train-bag train/bag --train-topic /image --out results/
    # models trained earlier (aefabmap_train); each gives its FAB-MAP and its BoW method
    aefabmap_eval --images test/images --gt test/loop_gt.npz --model models/ae --model models/kmeans --out r/
    # a recorded run of the nodes (aefabmap_record: loop_closures, loop_closure_candidates, place_posteriors)
    aefabmap_eval --recording run.mcap_dir --gt test/loop_gt.npz --out r/
    #   frames by stamp: the --gt file's stamps_ns, or --times FILE, or the images of --bag B --topic T
    aefabmap_eval --recording run.mcap_dir --poses poses.txt --max-distance 10 --max-angle 30 \\
        --times times.txt --pose-truth groundtruth.tum --out r/

Per method: precision-recall curve, average precision, max F1, recall at 100 % precision, and the
paper's accuracy (= precision) and recall at a fixed threshold: --threshold (FAB-MAP posterior,
default 0.99 as in the paper) and --bow-threshold (tf-idf cosine, default 0.6: near the best-F1
threshold of k-means BoW on the synthetic *training* sequence; the cosine is no calibrated
probability, so this default is a convention -- compare methods by AP and recall at 100 %
precision, which need no threshold).

Protocol: the best candidate of query i among frames j <= i - --min-gap. FAB-MAP's posterior is over
all earlier places (openFABMAP's run), unless the config's evaluation: fabmap_exclude_recent removes
the recent ones from it too (-1 = min gap - 1; see aefabmap_ros.evaluation.protocol for why this is
not the default). Vocabularies (one per
kind, shared by its FAB-MAP and BoW method), Chow-Liu trees and new-place samples come from the
training images (--train-images / --train-bag, as the paper does) or, with --train-on-test, from
the test sequence itself (each query is then left out of FAB-MAP's new-place sample mean). Trained
models and features are cached in --work-dir (default OUT/.cache), so a rerun is quick; the models
can be reused with --model.

With --verify every method gets a second row, "<method> + GV": each query's best candidates
(verification: candidates, default 5) are checked geometrically -- descriptor matches with the
ratio test, a fundamental matrix by MAGSAC++, at least verification: min_inliers (default 25)
inliers and min_inlier_ratio of the keypoints. Of the accepted ones, the candidate with the most
inliers is the query's match and it carries the score of the best-ranked accepted one; when none
is accepted, the next ones (evaluation: verify_more_candidates, default 5) are tried alike (none
accepted: no candidate). verifier_node does the same online for every published loop closure,
except that a refused best candidate refuses it (FAB-MAP's detection) and nothing deeper is tried.

Every FAB-MAP method also runs the nodes' decision chain on the sequence with its own stamps (--rate
for a folder): the config's fabmap section as fabmap_node uses it (places from dense video, recent
places excluded by time, temporal consistency), verified as verifier_node does when --verify is
given. Its table says what a backend would receive on /loop_closures: closures, false ones, revisit
events closed and recall over revisiting frames.

A recording is scored by stamp: a message's header stamp (its query image's) and matched_stamp /
place_stamps (the matched places' images) name ground-truth frames, never its query_id, which
counts only the frames that reached fabmap_node. Recall is given over all revisiting frames and
over those the detector processed (a place_posteriors message); OUT/closures.csv lists every
closure, its frames, truth and (--pose-truth) its relative pose's error. A recording of a map of several
sessions (its closures name more than one robot/session) is also scored per pair of sessions: closures, false
ones, the recall of the query session's frames that revisit the matched session, pose errors; with
--trajectory (the backend's trajectory_file) and --session-odometry (each session's odometry, TUM) the joined
trajectory's ATE is set beside each session's odometry aligned on its own (docs/sessions.md).

Writes OUT/results.md, OUT/results.json, OUT/pr_curves.png, OUT/reliability.png (reliability
diagram of the posterior the nodes publish: how often each frame's best place is right, per
posterior bin, in the online chain) and
OUT/scores_<method>.png (score matrix beside the ground truth). Config YAML sections: feature, vocabulary (both kinds),
vocabulary_kmeans, vocabulary_autoencoder (per-kind overrides), training, fabmap, evaluation,
verification.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from aefabmap_ros.cli.common import RESUME_HINT, ArgumentParser, deferred, run_cli
from aefabmap_ros.evaluation.methods import METHODS
from aefabmap_ros.features.kinds import FEATURE_TYPES

SECTIONS = ("feature", "vocabulary", "vocabulary_kmeans", "vocabulary_autoencoder", "training", "fabmap",
            "evaluation", "verification")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_eval", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_test_sequence_options(parser)
    _add_ground_truth_options(parser)
    _add_vocabulary_options(parser)
    _add_recording_options(parser)
    parser.add_argument("--methods", default=",".join(METHODS),
                        help=f"comma-separated subset of {', '.join(METHODS)} (default: all)")
    parser.add_argument("--verify", action="store_true",
                        help="also score every method after geometric verification of its candidates (+ GV rows)")
    parser.add_argument("--threshold", type=float, help="FAB-MAP posterior threshold (default 0.99)")
    parser.add_argument("--bow-threshold", type=float, help="tf-idf cosine threshold (default 0.6)")
    parser.add_argument("--config", type=Path, help=f"YAML with sections {', '.join(SECTIONS)}")
    parser.add_argument("--size", type=int, help="visual words of both vocabularies")
    parser.add_argument("--feature", choices=FEATURE_TYPES, help="feature type")
    parser.add_argument("--max-features", type=int, help="keypoints per image at most")
    parser.add_argument("--seed", type=int, help="random seed of the vocabularies")
    parser.add_argument("--out", type=Path, required=True, help="folder for results.md/json and the plots")
    parser.add_argument("--work-dir", type=Path, help="cache of features and trained models (default OUT/.cache)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    return parser




def _add_test_sequence_options(parser: argparse.ArgumentParser) -> None:
    test = parser.add_argument_group("test sequence (a folder, or a bag topic)")
    test.add_argument("--images", type=Path, help="folder of test images (natural sort order)")
    test.add_argument("--bag", type=Path,
                      help="rosbag2 bag holding the test images (with --recording: the frame stamps, read from it)")
    test.add_argument("--topic", default="/image", help="image topic of --bag (default: /image)")
    test.add_argument("--rate", type=float, default=10.0,
                      help="frame rate of --images in Hz: their stamps, which the online chain's time windows "
                      "use (default: 10; a bag has its own stamps)")
    test.add_argument("--depth", type=Path,
                      help="with --images: folder of 16-bit depth PNGs (mm), one per image in the same order, for "
                      "verification's metric test (with --verify; needs --camera-info)")
    test.add_argument("--depth-topic",
                      help="with --bag: its aligned depth topic (16UC1 mm or 32FC1 m), for verification's metric "
                      "test (with --verify; needs --camera-info-topic or --camera-info)")
    test.add_argument("--camera-info", type=Path,
                      help="ROS camera_info.yaml of the test camera, K and distortion (with --depth)")
    test.add_argument("--camera-info-topic", help="with --bag: its sensor_msgs/CameraInfo topic (with --depth-topic)")
    test.add_argument("--odometry-topic", help="with --bag: its nav_msgs/Odometry topic: the online chain checks its "
                      "verified closures against it, as verifier_node's odometry gate does (the odometry's child "
                      "frame is taken to be the camera's)")


def _add_ground_truth_options(parser: argparse.ArgumentParser) -> None:
    truth = parser.add_argument_group("ground truth (a loop matrix, or poses and a rule)")
    truth.add_argument("--gt", type=Path, help=".npz with key 'gt': (N, N) 0/1, gt[i, j] = 1: frame i revisits j")
    truth.add_argument("--poses", type=Path, help="KITTI pose file (one 3x4 camera-to-world matrix per line)")
    truth.add_argument("--max-distance", type=float, help="with --poses: camera centres within this many metres")
    truth.add_argument("--max-angle", type=float, help="with --poses: optical axes within this many degrees")
    truth.add_argument("--min-gap", type=int, help="frames j > i - G are never candidates of query i (default 10)")


def _add_vocabulary_options(parser: argparse.ArgumentParser) -> None:
    train = parser.add_argument_group("vocabularies (train on other images, on the test images, or load models)")
    train.add_argument("--train-images", type=Path, action="append", default=[], help="folder of training images")
    train.add_argument("--train-bag", type=Path, action="append", default=[], help="bag of training images")
    train.add_argument("--train-topic", default="/image", help="image topic of --train-bag (default: /image)")
    train.add_argument("--train-on-test", action="store_true", help="train on the test sequence itself")
    train.add_argument("--model", type=Path, action="append", default=[],
                       help="an already trained model directory (repeatable)")


def _add_recording_options(parser: argparse.ArgumentParser) -> None:
    recorded = parser.add_argument_group("a recorded run (--recording; frames found by image stamp)")
    recorded.add_argument("--recording", type=Path,
                          help="evaluate a recorded run instead (bag with place_posteriors, loop_closure_candidates, "
                          "loop_closures): each closure topic scored per closure and per revisit event, every "
                          "closure listed in OUT/closures.csv")
    recorded.add_argument("--times", type=Path,
                          help="the ground truth's frame stamps, one number of seconds per line (KITTI times.txt); "
                          "default: the --gt file's stamps_ns, else the images of --bag/--topic")
    recorded.add_argument("--pose-truth", type=Path,
                          help="TUM file of camera-to-world poses (t x y z qx qy qz qw, e.g. aefabmap_synth's "
                          "groundtruth.tum): each closure's relative pose scored against it")
    recorded.add_argument("--trajectory", type=Path,
                          help="with --pose-truth: the backend's keyframe trajectory (pose_graph_node's "
                          "trajectory_file, TUM), its ATE against the truth")
    recorded.add_argument("--session-odometry", type=Path, action="append", default=[],
                          help="with --trajectory: one session's odometry (TUM, e.g. aefabmap_bag split's "
                          "odometry.tum), aligned to the truth on its own at the trajectory's keyframes (repeatable)")
    recorded.add_argument("--frames-by-query-id", action="store_true",
                          help="map messages to frames by query_id instead of stamp: right only for a recording of a "
                          "lossless replay (every frame reached fabmap_node, in order)")


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, deferred("aefabmap_ros.cli.evaluate_run:run_evaluation"), RESUME_HINT)


if __name__ == "__main__":
    raise SystemExit(main())
