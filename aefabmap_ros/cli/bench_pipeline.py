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
import functools
import os
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

import numpy as np

from aefabmap_ros.cli.bench_nodes import Setup, camera_rate, load_average, print_ratios, through_nodes, throughput
from aefabmap_ros.cli.bench_stages import latency_summary, stage_latencies, thread_pools_of_a_node_process
from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.town import generate_sequence
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.io.bags import write_image_bag
from aefabmap_ros.model.directory import Model, load_model, save_model
from aefabmap_ros.model.training import sampled_centres_model


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bench pipeline", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200, help="synthetic frames (default 200)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--size", type=int, default=1000, help="words of the sampled vocabulary")
    parser.add_argument("--features", nargs="+", default=["sift", "orb"], choices=["sift", "rootsift", "orb"])
    parser.add_argument("--model", type=Path, help="use this trained model (its feature type) instead")
    parser.add_argument("--no-ros", action="store_true", help="per-stage latency only")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="source tree of the code to compare with (e.g. a worktree of an older commit): its "
                        "nodes run with this tree's messages, and images/s are given as ratios against it")
    parser.add_argument("--baseline-model", type=Path, default=None,
                        help="model directory the baseline's nodes load (default: --model); e.g. the same "
                        "vocabulary without its distilled encoder, for code that predates it")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each setup, interleaved (default 2)")
    parser.add_argument("--rate", type=float, default=0.0,
                        help="0 (default): replay as fast as possible, reliable QoS, images/s; > 0: a camera at "
                        "this many Hz with sensor-data QoS, latency image stamp -> posterior and drops")
    parser.add_argument("--no-pipeline", action="store_true",
                        help="only the three-process launch, not also the one-process --pipeline")
    parser.add_argument("--quick", action="store_true", help="seconds-long smoke run (small frames, no ROS)")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


def isolate_ros_domain(environment: MutableMapping[str, str], pid: int) -> str:
    """Give this run's nodes, recorder and replay a DDS domain of their own (unless the caller chose one), on
    this host only: two benchmarks on one machine, or a benchmark beside running nodes, would answer each
    other's images (a recording then holds more posteriors than images sent). Returns the domain id."""
    environment.setdefault("ROS_DOMAIN_ID", str(1 + pid % 100))  # 0-101: the ids ROS 2 documents as safe
    environment.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return environment["ROS_DOMAIN_ID"]


def _check_arguments(args: argparse.Namespace) -> None:
    if args.baseline is not None and not (args.baseline / "aefabmap_ros" / "cli" / "launch.py").is_file():
        raise ConfigError(f"--baseline {args.baseline} is not an aefabmap_ros source tree")
    if args.baseline_model is not None and (args.baseline is None or args.model is None):
        raise ConfigError("--baseline-model needs --baseline and --model")
    if args.baseline_model is not None and not (args.baseline_model / "metadata.json").is_file():
        raise ConfigError(f"--baseline-model {args.baseline_model} is not a model directory")
    if args.repeats < 1 or args.rate < 0:
        raise ConfigError("--repeats must be >= 1 and --rate >= 0")


def _model(name: str, model_dir: Path | None, images: list[np.ndarray], work: Path, size: int
           ) -> tuple[Model, Path]:
    """``model_dir``'s model, or (None) a vocabulary of ``size`` descriptors of ``name`` features sampled from the
    first half of the frames, saved under ``work``."""
    if model_dir is not None:
        return load_model(model_dir), model_dir
    config = FeatureConfig(type=name)
    training = [extract_features(image, config) for image in images[: len(images) // 2]]
    model = sampled_centres_model(training, config, size)
    save_model(work / f"model_{name}", model)
    return model, work / f"model_{name}"


def run(args: argparse.Namespace) -> int:
    _check_arguments(args)
    if args.quick:
        args.frames, args.width, args.height, args.size, args.no_ros = 24, 320, 240, 100, True

    domain = isolate_ros_domain(os.environ, os.getpid())  # inherited by every process the run starts
    sequence = generate_sequence(SynthConfig(num_frames=args.frames, width=args.width, height=args.height))
    images = sequence.images
    print(f"{len(images)} synthetic frames {args.width}x{args.height}; "
          f"{'model ' + str(args.model) if args.model else f'sampled {args.size}-word vocabulary'}; "
          f"{'baseline model ' + str(args.baseline_model) + '; ' if args.baseline_model else ''}"
          f"{os.cpu_count()} cores, load average {load_average()}, ROS domain {domain}")
    setups = [Setup("this", None, pipeline) for pipeline in ([False] if args.no_pipeline else [False, True])]
    if args.baseline is not None:
        setups += [Setup("baseline", args.baseline.resolve(), setup.pipeline, args.baseline_model)
                   for setup in setups]
    with tempfile.TemporaryDirectory(prefix="aefabmap_bench_") as tmp:
        work = Path(tmp)
        bag = work / "bag"
        write_image_bag(bag, "/image", zip(sequence.stamps_ns.tolist(), images, strict=True))
        runs = [("model", args.model)] if args.model else [(name, None) for name in args.features]
        for name, given_dir in runs:
            model, model_dir = _model(name, given_dir, images, work, args.size)
            label = f"{model.feature_config.type} / {model.quantizer.kind} {model.quantizer.size} words"
            with thread_pools_of_a_node_process() as threads:
                stages = stage_latencies(model, images)
            total = np.sum([stages[s] for s in ("decode", "features", "quantize", "fabmap")], axis=0)
            print(f"\n[{label}] per-stage latency, one process, {len(images)} images, "
                  f"{threads}-thread BLAS/torch pools (a node process's share under aefabmap_launch)")
            for stage, values in stages.items():
                print(f"  {stage:9s} {latency_summary(values)}")
            print(f"  {'total':9s} {latency_summary(list(total))}  "
                  f"-> {1e3 / np.median(total):.1f} images/s on one core")
            if args.no_ros:
                continue
            if args.rate > 0:
                print(f"\n[{label}] through the nodes: camera at {args.rate:g} Hz, sensor-data QoS, "
                      f"{len(images)} images")
                results = through_nodes(setups, args.repeats,
                                         functools.partial(camera_rate, model_dir=model_dir, images=images, work=work,
                                                           rate_hz=args.rate))
            else:
                print(f"\n[{label}] through the nodes: replay as fast as possible, reliable QoS, {len(images)} images")
                results = through_nodes(setups, args.repeats,
                                         functools.partial(throughput, model_dir=model_dir, bag=bag, work=work,
                                                           num_frames=len(images)))
            print_ratios(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
