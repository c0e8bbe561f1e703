"""Pipeline benchmark: per-stage latency in one process, and images/s through the ROS nodes.

For each feature type (SIFT, ORB) on synthetic 640 x 480 frames:
1. per-stage latency (median, p95) of decode, feature extraction, quantization and FAB-MAP 2,
   called directly (no ROS);
2. end-to-end throughput: the bag is replayed as fast as possible (--rate 0) into the three
   nodes as separate processes (aefabmap_launch), and the arrival times of the place posteriors
   give images/s. Every process shares this machine's cores, as on a robot's computer.

The model is a vocabulary of descriptors sampled from the first half of the frames (no
clustering: timing only) unless --model names a trained one.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from aefabmap_ros.core.chowliu import ChowLiuTree
from aefabmap_ros.core.detector import PlaceRecognizer
from aefabmap_ros.core.fabmap import FabMapConfig
from aefabmap_ros.core.features import FeatureConfig, extract_features
from aefabmap_ros.core.images import image_to_gray
from aefabmap_ros.core.model import Model, load_model, save_model
from aefabmap_ros.core.synth import SynthConfig, generate_sequence
from aefabmap_ros.core.training import sampled_centres_model
from aefabmap_ros.io.bags import read_messages, write_image_bag

PARAMS = """
feature_node:
  ros__parameters: {image_qos: reliable, queue_depth: 1000}
quantizer_node:
  ros__parameters: {queue_depth: 1000}
fabmap_node:
  ros__parameters: {queue_depth: 1000}
"""


def _ms_since(started: float) -> float:
    return (time.perf_counter() - started) * 1e3


def _summary(values_ms: list[float]) -> str:
    return f"median {np.median(values_ms):7.2f} ms  p95 {np.percentile(values_ms, 95):7.2f} ms"


def stage_latencies(model: Model, images: list[np.ndarray]) -> dict[str, list[float]]:
    assert model.tree_matrix is not None
    recognizer = PlaceRecognizer(ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples,
                                 FabMapConfig(), model.model_id)
    stages: dict[str, list[float]] = {"decode": [], "features": [], "quantize": [], "fabmap": []}
    for index, image in enumerate(images):
        height, width = image.shape[:2]
        raw = image.tobytes()
        started = time.perf_counter()
        gray = image_to_gray(raw, "mono8", height, width, width)
        stages["decode"].append(_ms_since(started))
        started = time.perf_counter()
        features = extract_features(gray, model.feature_config)
        stages["features"].append(_ms_since(started))
        started = time.perf_counter()
        words = np.unique(model.quantizer.quantize(features.descriptors))
        stages["quantize"].append(_ms_since(started))
        started = time.perf_counter()
        recognizer.process(words, index * 100_000_000)
        stages["fabmap"].append(_ms_since(started))
    return stages


def throughput(model_dir: Path, bag: Path, work: Path, num_frames: int) -> tuple[float, int]:
    """(images/s, posteriors received) through the three node processes."""
    params = work / "params.yaml"
    params.write_text(PARAMS)
    recording = work / "recording"
    shutil.rmtree(recording, ignore_errors=True)
    python = sys.executable
    logs = (work / "launch.log").open("w"), (work / "record.log").open("w")
    launch = subprocess.Popen([python, "-m", "aefabmap_ros.cli.launch", "--model", str(model_dir), "--params",
                               str(params)], stdout=logs[0], stderr=subprocess.STDOUT)
    record = subprocess.Popen([python, "-m", "aefabmap_ros.cli.record", str(recording), "--topics",
                               "place_posteriors", "--wait-publishers", "60", "--idle-timeout", "10"],
                              stdout=logs[1], stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while "[record] recording" not in (work / "record.log").read_text():
            if time.monotonic() > deadline or record.poll() is not None:
                raise RuntimeError(f"recorder did not start: {(work / 'record.log').read_text()[-2000:]}")
            time.sleep(0.2)
        subprocess.run([python, "-m", "aefabmap_ros.cli.replay", str(bag), "--topic", "/image", "--rate", "0",
                        "--queue-depth", str(num_frames + 10), "--quiet", "--wait-timeout", "60"], check=True)
        record.wait(timeout=600)
    finally:
        for process in (record, launch):
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
                process.wait(timeout=30)
        for log in logs:
            log.close()
    arrivals = np.array([m.log_time_ns for m in read_messages(recording, ["place_posteriors"])], dtype=np.float64)
    if arrivals.size < 2:
        return 0.0, int(arrivals.size)
    return (arrivals.size - 1) / ((arrivals[-1] - arrivals[0]) / 1e9), int(arrivals.size)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aefabmap_bench pipeline", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200, help="synthetic frames (default 200)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--size", type=int, default=1000, help="words of the sampled vocabulary")
    parser.add_argument("--features", nargs="+", default=["sift", "orb"], choices=["sift", "rootsift", "orb"])
    parser.add_argument("--model", type=Path, help="use this trained model (its feature type) instead")
    parser.add_argument("--no-ros", action="store_true", help="per-stage latency only")
    parser.add_argument("--quick", action="store_true", help="seconds-long smoke run (small frames, no ROS)")
    args = parser.parse_args(argv)
    if args.quick:
        args.frames, args.width, args.height, args.size, args.no_ros = 24, 320, 240, 100, True

    sequence = generate_sequence(SynthConfig(num_frames=args.frames, width=args.width, height=args.height))
    images = sequence.images
    print(f"{len(images)} synthetic frames {args.width}x{args.height}; "
          f"{'model ' + str(args.model) if args.model else f'sampled {args.size}-word vocabulary'}")
    with tempfile.TemporaryDirectory(prefix="aefabmap_bench_") as tmp:
        work = Path(tmp)
        bag = work / "bag"
        write_image_bag(bag, "/image", zip(sequence.stamps_ns.tolist(), images, strict=True))
        runs = [("model", args.model)] if args.model else [(name, None) for name in args.features]
        for name, model_dir in runs:
            if model_dir is None:
                config = FeatureConfig(type=name)
                training = [extract_features(image, config) for image in images[: len(images) // 2]]
                model = sampled_centres_model(training, config, args.size)
                model_dir = work / f"model_{name}"
                save_model(model_dir, model)
            else:
                model = load_model(model_dir)
            label = f"{model.feature_config.type} / {model.quantizer.kind} {model.quantizer.size} words"
            stages = stage_latencies(model, images)
            total = np.sum([stages[s] for s in stages], axis=0)
            print(f"\n[{label}] per-stage latency, one process, {len(images)} images")
            for stage, values in stages.items():
                print(f"  {stage:9s} {_summary(values)}")
            print(f"  {'total':9s} {_summary(list(total))}  -> {1e3 / np.median(total):.1f} images/s on one core")
            if not args.no_ros:
                rate, received = throughput(model_dir, bag, work, len(images))
                print(f"  ROS nodes (3 processes): {rate:.1f} images/s end to end "
                      f"({received}/{len(images)} posteriors received)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
