"""aefabmap_bench: benchmarks that print figures (never timed assertions).

    aefabmap_bench fabmap [--quick]     FAB-MAP 2 query latency and memory vs. places; FAB-MAP 1 ratio
    aefabmap_bench vocab [--quick]      vocabulary training time per stage; AE vs k-means quantization
    aefabmap_bench pipeline [--quick]   per-stage latency and images/s through the ROS nodes
    aefabmap_bench verify [--quick]     geometric verification cost per candidate; verifier memory per frame
    aefabmap_bench backend [--quick]    pose-graph (iSAM2) update time per loop closure up to 1,000 keyframes
"""

from __future__ import annotations

import importlib
import sys

# Benchmark name -> its module (imported only when chosen: each pulls in what it measures).
BENCHMARKS = {
    "fabmap": "aefabmap_ros.cli.bench_fabmap",
    "vocab": "aefabmap_ros.cli.bench_vocab",
    "pipeline": "aefabmap_ros.cli.bench_pipeline",
    "verify": "aefabmap_ros.cli.bench_verify",
    "backend": "aefabmap_ros.cli.bench_backend",
}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] not in BENCHMARKS:
        print(__doc__, file=sys.stderr)
        if args and args[0] not in ("-h", "--help"):
            print(f"ERROR: unknown benchmark {args[0]!r}; choose one of {', '.join(BENCHMARKS)}", file=sys.stderr)
            return 1
        return 0 if args else 1
    status: int = importlib.import_module(BENCHMARKS[args[0]]).main(args[1:])
    return status


if __name__ == "__main__":
    raise SystemExit(main())
