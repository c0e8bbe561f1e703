"""aefabmap_ate: absolute trajectory error (evo) of trajectories against ground truth, and a plot.

    aefabmap_ate --reference test/groundtruth.tum --estimate odometry=test/odometry.tum \
        --estimate "odometry + closures=keyframes.tum" --plot ate.png
    aefabmap_ate --reference gt.tum --estimate mono=orb_mono.tum --sim3   # monocular: scale unknown

Every file is TUM (``timestamp tx ty tz qx qy qz qw``). Each estimate is associated to the reference
by stamp (within --max-diff seconds), aligned by SE(3) (--sim3: Sim(3), for monocular
trajectories), and its ATE RMSE printed in metres. --plot writes a top view of the aligned
trajectories over the reference (PNG).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.evaluation.trajectory_error import DEFAULT_MAX_DIFF_S, absolute_trajectory_error, read_tum


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_ate", description=__doc__.split("\n\n")[0],
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reference", type=Path, required=True, help="ground-truth TUM file")
    parser.add_argument("--estimate", action="append", required=True, metavar="LABEL=FILE",
                        help="an estimated trajectory (TUM), repeatable")
    parser.add_argument("--sim3", action="store_true", help="align by Sim(3) (monocular: scale unknown)")
    parser.add_argument("--max-diff", type=float, default=DEFAULT_MAX_DIFF_S,
                        help=f"stamp association tolerance, seconds (default {DEFAULT_MAX_DIFF_S})")
    parser.add_argument("--plot", type=Path, default=None, help="PNG of the aligned trajectories")
    return parser


def _labelled(values: list[str]) -> list[tuple[str, Path]]:
    pairs = []
    for value in values:
        label, sep, file = value.partition("=")
        if not sep or not label or not file:
            raise ConfigError(f"--estimate {value!r} must be LABEL=FILE")
        pairs.append((label, Path(file)))
    return pairs


def run(args: argparse.Namespace) -> int:
    if args.max_diff <= 0:
        raise ConfigError(f"--max-diff must be > 0, got {args.max_diff}")
    reference = read_tum(args.reference)
    alignment = "Sim(3)" if args.sim3 else "SE(3)"
    plotted = []
    for label, path in _labelled(args.estimate):
        result = absolute_trajectory_error(reference, read_tum(path), correct_scale=args.sim3,
                                           max_diff_s=args.max_diff)
        print(f"ATE RMSE {label}: {result.rmse_m:.4f} m ({result.matched} poses, {alignment} alignment)")
        plotted.append((label, result.aligned.positions_xyz))
    if args.plot is not None:
        from aefabmap_ros.evaluation.plots import plot_trajectories

        plot_trajectories(reference.positions_xyz, plotted, args.plot)
        print(f"plot: {args.plot}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


if __name__ == "__main__":
    sys.exit(main())
