"""What every command-line tool shares: known errors become ``ERROR: ...`` on stderr and exit 1."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

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


class UsageError(Exception):
    """Bad command-line arguments (reported as ERROR: ..., exit 1)."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose errors become ``UsageError`` instead of exit 2 with argparse's own message."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(message)


def parse_or_report(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace | None:
    """Parsed arguments, or None after printing ``ERROR: ...`` and the usage line (the caller exits 1)."""
    try:
        return parser.parse_args(argv)
    except UsageError as error:
        print(f"ERROR: {error}", file=sys.stderr)
        parser.print_usage(sys.stderr)
        return None
