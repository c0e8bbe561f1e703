"""What every command-line tool shares: known errors become ``ERROR: ...`` on stderr and exit 1."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from aefabmap_ros.errors import AefabmapError

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


def _created_by(folder: Path) -> list[Path]:
    """The folders ``folder.mkdir(parents=True)`` would create, deepest first (empty if it exists)."""
    missing = []
    for path in (folder.absolute(), *folder.absolute().parents):
        if path.exists():
            break
        missing.append(path)
    return missing


@contextmanager
def no_empty_folders_left_on_error(*folders: Path) -> Iterator[None]:
    """Folders the body creates (with their missing parents) are removed again if it fails while they are
    still empty: a refused command leaves no trace, while cached work in them is kept for a rerun."""
    to_remove = sorted({path for folder in folders for path in _created_by(folder)},
                       key=lambda path: len(path.parts), reverse=True)
    try:
        yield
    except BaseException:
        for path in to_remove:
            with suppress(OSError):
                path.rmdir()  # only succeeds on an empty folder
        raise


def run_cli(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
            run: Callable[[argparse.Namespace], int], interrupted: str = "interrupted") -> int:
    """A CLI's main: parse (a usage error is one ERROR line, exit 1), then run with errors reported."""
    args = parse_or_report(parser, argv)
    if args is None:
        return 1
    return report_errors(lambda: run(args), interrupted)


def deferred(target: str) -> Callable[[argparse.Namespace], int]:
    """The CLI work ``"module:function"``, imported only when called: after ``--help`` and usage errors,
    so a tool whose work needs torch, numba or OpenCV still answers ``--help`` at once."""
    module_name, _, function_name = target.partition(":")

    def run(args: argparse.Namespace) -> int:
        work: Callable[[argparse.Namespace], int] = getattr(importlib.import_module(module_name), function_name)
        return work(args)

    return run


def with_ros(work: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``work`` inside an initialised ROS context, shut down however it ends (rclpy imported only then)."""

    def run(args: argparse.Namespace) -> int:
        import rclpy

        rclpy.init()
        try:
            return work(args)
        finally:
            rclpy.try_shutdown()

    return run


def ros_message_class(msgtype: str) -> Any:
    """The Python class of a ROS message type named as bags name it (``package/msg/Name``); the
    package is imported only now, so a CLI's ``--help`` does not load ROS."""
    package, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)
