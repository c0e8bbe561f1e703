"""aefabmap_bench: benchmarks that print figures (never timed assertions).

    aefabmap_bench fabmap [--quick]     FAB-MAP 2 query latency and memory vs. places; FAB-MAP 1 ratio
    aefabmap_bench vocab [--quick]      vocabulary training time per stage; AE vs k-means quantization
    aefabmap_bench pipeline [--quick]   per-stage latency and images/s through the ROS nodes
    aefabmap_bench verify [--quick]     geometric verification cost per candidate; verifier memory per frame
    aefabmap_bench backend [--quick]    pose-graph (iSAM2) update time per loop closure up to 1,000 keyframes
"""

from __future__ import annotations

import sys
from collections.abc import Callable

from aefabmap_ros.cli import bench_backend, bench_fabmap, bench_pipeline, bench_verify, bench_vocab

BENCHMARKS: dict[str, Callable[[list[str] | None], int]] = {
    "fabmap": bench_fabmap.main,
    "vocab": bench_vocab.main,
    "pipeline": bench_pipeline.main,
    "verify": bench_verify.main,
    "backend": bench_backend.main,
}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] not in BENCHMARKS:
        print(__doc__, file=sys.stderr)
        if args and args[0] not in ("-h", "--help"):
            print(f"ERROR: unknown benchmark {args[0]!r}; choose one of {', '.join(BENCHMARKS)}", file=sys.stderr)
            return 1
        return 0 if args else 1
    return BENCHMARKS[args[0]](args[1:])


if __name__ == "__main__":
    raise SystemExit(main())
