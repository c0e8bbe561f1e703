"""What every command-line tool shares: known errors become ``ERROR: ...`` on stderr and exit 1."""

from __future__ import annotations

import sys
from collections.abc import Callable

from aefabmap_ros.core.errors import AefabmapError

RESUME_HINT = "interrupted; rerun the same command to resume from the cached stages"


def report_errors(work: Callable[[], int], interrupted: str = "interrupted") -> int:
    """Run ``work``; an AefabmapError or Ctrl-C is printed as one ERROR line and gives exit 1."""
    try:
        return work()
    except AefabmapError as exc:
        print(f"ERROR: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"ERROR: {interrupted}", file=sys.stderr)
        return 1
