"""aefabmap_bag split / merge: a bag cut into two sessions, and recordings put back together.

    aefabmap_bag split bags/generated/test --at 0.5 --restart-odometry --out bags/two_sessions
    aefabmap_bag split run.mcap_dir --at-stamp 1700000015.0 --gt loop_gt.npz --pose-truth gt.tum --out cut
    aefabmap_bag merge output/session_a output/session_b --out output/both_sessions

split: every message whose header stamp (its log time when it has no header) is before the cut goes to
session A (``OUT/a/bag``), the others to session B (``OUT/b/bag``), with their stamps and log times kept.
``--at F`` cuts at the fraction F of the bag's span of stamps (0.5: half way from its first to its last);
``--at-stamp S`` at S seconds. With ``--restart-odometry`` session B's odometry (nav_msgs/Odometry, ``--odom-topic``
or the bag's only one) is re-expressed relative to its first pose, as a rebooted robot's odometry restarts at
the identity: pose' = pose0^-1 pose, the pose covariance turned into the new frame, the twist (in the child frame)
kept. Other topics, /tf included, are copied unchanged. Given BAG as a sequence folder (aefabmap_synth's:
``bag/`` beside ``loop_gt.npz`` and ``groundtruth.tum``) or ``--gt`` / ``--pose-truth``, the ground truth is cut to
match: loop_gt.npz's rows and columns by its ``stamps_ns``, the TUM lines by stamp (the truth's world frame is
kept). Each session gets ``odometry.tum``, its odometry as the robot would have logged it; ``OUT/split.json``
says where the cut was. OUT appears only when complete.

merge: the messages of several bags (e.g. one recording per session) in one bag, by log time, so that
``aefabmap_eval --recording`` scores the sessions together.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import shutil
from collections import Counter
from collections.abc import Iterator, Sequence
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.errors import BagError, ConfigError, DataError
from aefabmap_ros.evaluation.recordings import seconds_text
from aefabmap_ros.io.bag_messages import ODOMETRY_TYPE
from aefabmap_ros.io.bags import STORAGES, BagMessage, BagWriter, list_topics, read_messages

SESSIONS = ("a", "b")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bag", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    split = commands.add_parser("split", help="cut a bag into two sessions (A before the cut, B from it on)")
    split.add_argument("bag", type=Path, help="rosbag2 bag, or a sequence folder holding bag/ (aefabmap_synth's)")
    where = split.add_mutually_exclusive_group(required=True)
    where.add_argument("--at", type=float, help="cut at this fraction (0 < F < 1) of the bag's span of stamps")
    where.add_argument("--at-stamp", help="cut at this stamp, seconds (session B starts with it)")
    split.add_argument("--restart-odometry", action="store_true",
                       help="session B's odometry re-expressed relative to its first pose (starts at the identity)")
    split.add_argument("--odom-topic", help="the odometry topic (default: the bag's only nav_msgs/Odometry topic)")
    split.add_argument("--gt", type=Path, help="loop_gt.npz (gt, stamps_ns) to cut (default: the sequence folder's)")
    split.add_argument("--pose-truth", type=Path,
                       help="TUM ground truth to cut (default: the sequence folder's groundtruth.tum)")
    split.add_argument("--out", type=Path, required=True, help="folder to write: OUT/a, OUT/b, OUT/split.json")
    split.add_argument("--storage", choices=sorted(STORAGES), default="mcap", help="bag storage (default: mcap)")
    split.add_argument("--overwrite", action="store_true", help="replace an existing OUT")
    merge = commands.add_parser("merge", help="the messages of several bags in one, by log time")
    merge.add_argument("bags", type=Path, nargs="+", help="bags to merge (recordings of one map's sessions)")
    merge.add_argument("--out", type=Path, required=True, help="bag to write")
    merge.add_argument("--storage", choices=sorted(STORAGES), default="mcap", help="bag storage (default: mcap)")
    merge.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    return parser


# ------------------------------------------------------------------------------------------ inputs


def _inputs(args: argparse.Namespace) -> tuple[Path, Path | None, Path | None]:
    """(bag, loop ground truth, pose truth): a sequence folder's files unless given."""
    if not args.bag.exists():
        raise BagError(f"bag does not exist: {args.bag}")
    if (args.bag / "bag").is_dir():
        folder = args.bag
        gt = args.gt or (folder / "loop_gt.npz" if (folder / "loop_gt.npz").is_file() else None)
        truth = args.pose_truth or (folder / "groundtruth.tum" if (folder / "groundtruth.tum").is_file() else None)
        return folder / "bag", gt, truth
    return args.bag, args.gt, args.pose_truth


def parse_stamp(text: str) -> int:
    """Seconds as written (``1700000015.1``) -> integer nanoseconds, exactly."""
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise ConfigError(f"--at-stamp must be a number of seconds, got {text!r}") from None
    if not value.is_finite():
        raise ConfigError(f"--at-stamp must be a finite number of seconds, got {text!r}")
    return int((value * 1_000_000_000).to_integral_value())


def bag_stamp_span(bag: Path) -> tuple[int, int]:
    """First and last header stamp of the bag's messages."""
    first, last = None, None
    for message in read_messages(bag, list(list_topics(bag))):
        first = message.stamp_ns if first is None else min(first, message.stamp_ns)
        last = message.stamp_ns if last is None else max(last, message.stamp_ns)
    if first is None or last is None:
        raise BagError(f"bag {bag} holds no messages")
    return first, last


def cut_stamp(bag: Path, fraction: float | None, stamp_text: str | None) -> int:
    """The cut: session B holds the messages stamped at or after it; each side must hold some."""
    first, last = bag_stamp_span(bag)
    span = f"the bag's stamps run from {seconds_text(first)} to {seconds_text(last)} s"
    if fraction is not None:
        if not (np.isfinite(fraction) and 0.0 < fraction < 1.0):
            raise ConfigError(f"--at must be a fraction between 0 and 1 (exclusive), got {fraction}")
        cut = first + round(fraction * (last - first))
    else:
        assert stamp_text is not None
        cut = parse_stamp(stamp_text)
    if not first < cut <= last:
        raise ConfigError(f"the cut at {seconds_text(cut)} s leaves one session empty: {span}")
    return cut


def odometry_topic(bag: Path, wanted: str | None) -> str:
    topics = list_topics(bag)
    odometry = sorted(topic for topic, kind in topics.items() if kind == ODOMETRY_TYPE)
    if wanted is not None:
        if topics.get(wanted) != ODOMETRY_TYPE:
            raise BagError(f"--odom-topic {wanted!r} is not a {ODOMETRY_TYPE} topic of bag {bag}; its odometry "
                           f"topics: {odometry or 'none'}")
        return wanted
    if len(odometry) != 1:
        raise BagError(f"--restart-odometry needs the bag's odometry topic: bag {bag} has "
                       + (f"several ({odometry}): choose one with --odom-topic" if odometry
                          else f"no {ODOMETRY_TYPE} topic"))
    return odometry[0]


# ------------------------------------------------------------------------------------------ odometry


def odometry_matrix(message: Any) -> np.ndarray:
    """T_odom_child of a nav_msgs/Odometry."""
    pose = message.pose.pose
    q = pose.orientation
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    matrix[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return matrix


def restart_odometry(message: Any, origin: np.ndarray) -> Any:
    """The message re-expressed relative to ``origin`` (the session's first T_odom_child), in place:
    pose' = origin^-1 pose; the covariance's position and rotation blocks turned into the new frame."""
    relative = np.linalg.inv(origin) @ odometry_matrix(message)
    pose = message.pose.pose
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in relative[:3, 3])
    x, y, z, w = Rotation.from_matrix(relative[:3, :3]).as_quat()
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in (x, y, z, w))
    turn = np.kron(np.eye(2), origin[:3, :3].T)
    covariance = np.asarray(message.pose.covariance, dtype=np.float64).reshape(6, 6)
    message.pose.covariance = (turn @ covariance @ turn.T).reshape(36)
    return message


# ------------------------------------------------------------------------------------------ the split


def write_sessions(bag: Path, folders: Sequence[Path], cut_ns: int, odom_topic: str | None, restart: bool,
                   storage: str) -> tuple[dict[str, Counter[str]], list[list[tuple[int, np.ndarray]]], list[float]]:
    """Both sessions' bags (``folder/bag``): per session the messages per topic, its odometry (stamp, pose) and,
    restarted, B's first odometry pose as x y z qx qy qz qw of the original frame."""
    topics = list_topics(bag)
    counts: dict[str, Counter[str]] = {name: Counter() for name in SESSIONS}
    odometry: list[list[tuple[int, np.ndarray]]] = [[], []]
    origin: np.ndarray | None = None
    writers = [BagWriter(folder / "bag", storage=storage) for folder in folders]
    with writers[0] as first, writers[1] as second:
        for writer in (first, second):
            for topic, msgtype in topics.items():
                writer.add_topic(topic, msgtype)
        for message in read_messages(bag, list(topics)):
            side = int(message.stamp_ns >= cut_ns)
            data: Any = message.raw
            if message.topic == odom_topic:
                if side == 1 and restart:
                    origin = odometry_matrix(message.message) if origin is None else origin
                    data = restart_odometry(message.message, origin)
                odometry[side].append((message.stamp_ns, odometry_matrix(message.message)))
            (first, second)[side].write(message.topic, message.log_time_ns, data)
            counts[SESSIONS[side]][message.topic] += 1
    if restart and origin is None:
        raise DataError(f"session B of bag {bag} has no message on {odom_topic}: no odometry to restart")
    origin_pose = [] if origin is None else [*origin[:3, 3].tolist(),
                                             *Rotation.from_matrix(origin[:3, :3]).as_quat().tolist()]
    return counts, odometry, origin_pose


def cut_loop_truth(path: Path, cut_ns: int) -> list[dict[str, np.ndarray]]:
    """loop_gt.npz's rows and columns before the cut, and from it on (by its stamps_ns)."""
    from aefabmap_ros.evaluation.ground_truth import load_gt_npz, load_gt_stamps

    gt = load_gt_npz(path)
    stamps = load_gt_stamps(path)
    if stamps is None:
        raise DataError(f"{path} has no stamps_ns: its frames cannot be cut by stamp")
    if stamps.size != gt.shape[0]:
        raise DataError(f"{path} has {stamps.size} stamps_ns for {gt.shape[0]} frames")
    sides = [stamps < cut_ns, stamps >= cut_ns]
    return [{"gt": gt[np.ix_(side, side)], "stamps_ns": stamps[side]} for side in sides]


def cut_tum(path: Path, cut_ns: int) -> list[str]:
    """A TUM file's lines before the cut and from it on (comments and blank lines dropped)."""
    if not path.is_file():
        raise DataError(f"pose truth does not exist: {path}")
    sides: list[list[str]] = [[], []]
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            stamp = parse_stamp(line.split()[0])
        except ConfigError:
            raise DataError(f"{path} line {number}: no stamp in {line!r}") from None
        sides[int(stamp >= cut_ns)].append(line + "\n")
    return ["".join(side) for side in sides]


def _staging(out: Path, overwrite: bool) -> Path:
    if out.exists() and not overwrite:
        raise ConfigError(f"--out {out} already exists (remove it or pass --overwrite)")
    if not out.parent.is_dir():
        raise ConfigError(f"--out {out}: folder {out.parent} does not exist")
    staging = out.with_name(f".{out.name}.partial-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    return staging


def run_split(args: argparse.Namespace) -> int:
    bag, gt_path, truth_path = _inputs(args)
    odom = odometry_topic(bag, args.odom_topic) if args.restart_odometry or args.odom_topic else None
    if odom is None:
        odometry = sorted(t for t, kind in list_topics(bag).items() if kind == ODOMETRY_TYPE)
        odom = odometry[0] if len(odometry) == 1 else None
    cut = cut_stamp(bag, args.at, args.at_stamp)
    loop_truth = cut_loop_truth(gt_path, cut) if gt_path is not None else None
    pose_truth = cut_tum(truth_path, cut) if truth_path is not None else None
    staging = _staging(args.out, args.overwrite)
    try:
        from aefabmap_ros.evaluation.trajectory_error import tum_text

        folders = [staging / name for name in SESSIONS]
        for folder in folders:
            folder.mkdir()
        counts, odometry_poses, origin = write_sessions(bag, folders, cut, odom, args.restart_odometry,
                                                        args.storage)
        for index, folder in enumerate(folders):
            if loop_truth is not None:
                np.savez(folder / "loop_gt.npz", gt=loop_truth[index]["gt"], stamps_ns=loop_truth[index]["stamps_ns"])
            if pose_truth is not None:
                (folder / "groundtruth.tum").write_text(pose_truth[index])
            if odometry_poses[index]:
                stamps, poses = zip(*odometry_poses[index], strict=True)
                (folder / "odometry.tum").write_text(tum_text(np.array(stamps) / 1e9, np.stack(poses)))
        summary = {"source": str(bag), "cut_ns": cut, "odometry_topic": odom,
                   "odometry_restarted": bool(args.restart_odometry), "session_b_odometry_origin": origin,
                   "messages": {name: dict(sorted(counts[name].items())) for name in SESSIONS},
                   "ground_truth_frames": None if loop_truth is None else
                   {name: int(side["stamps_ns"].size) for name, side in zip(SESSIONS, loop_truth, strict=True)}}
        (staging / "split.json").write_text(json.dumps(summary, indent=2) + "\n")
        if args.out.exists():
            shutil.rmtree(args.out)
        os.replace(staging, args.out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    for name in SESSIONS:
        listing = ", ".join(f"{count} {topic}" for topic, count in sorted(counts[name].items()))
        print(f"session {name.upper()}: {listing} -> {args.out / name}")
    restarted = f"; session B's odometry ({odom}) restarted at the identity" if args.restart_odometry else ""
    print(f"cut at {seconds_text(cut)} s{restarted}")
    return 0


# ------------------------------------------------------------------------------------------ merge


def _merged(paths: Sequence[Path]) -> Iterator[BagMessage]:
    streams = [read_messages(path, list(list_topics(path))) for path in paths]
    return heapq.merge(*streams, key=lambda message: message.log_time_ns)


def run_merge(args: argparse.Namespace) -> int:
    types: dict[str, str] = {}
    for path in args.bags:
        for topic, msgtype in list_topics(path).items():
            if types.setdefault(topic, msgtype) != msgtype:
                raise BagError(f"topic {topic!r} is {types[topic]} in one bag and {msgtype} in {path}")
    count = 0
    with BagWriter(args.out, storage=args.storage, overwrite=args.overwrite) as writer:
        for topic, msgtype in types.items():
            writer.add_topic(topic, msgtype)
        for message in _merged(args.bags):
            writer.write(message.topic, message.log_time_ns, message.raw)
            count += 1
    print(f"{count} messages of {len(args.bags)} bags on {len(types)} topics -> {args.out}")
    return 0


def run(args: argparse.Namespace) -> int:
    return run_split(args) if args.command == "split" else run_merge(args)


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)
