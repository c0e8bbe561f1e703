"""aefabmap_map: look into, merge and cut FAB-MAP map files (the .npz a fabmap_node saves).

    aefabmap_map info maps/office.npz
    aefabmap_map info maps/office.npz --json office.json
    aefabmap_map merge maps/robot1.npz maps/robot2.npz --out maps/both.npz --model models/office
    aefabmap_map remove-session maps/both.npz 1 --out maps/robot1_again.npz

merge appends the second map's places and sessions after the first's (query ids shifted so they stay
unique); remove-session drops one session and its places. Both write a new file atomically and refuse to
write over an input. A map file that cannot be read, or maps of different vocabularies, are refused with one
ERROR line, and nothing is written.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from aefabmap_ros.cli.common import ArgumentParser, run_cli

if TYPE_CHECKING:
    from aefabmap_ros.fabmap.map_tools import MapArrays, MapSummary


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_map", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    # Shared by the subcommands that write a map (evo-style parent parser).
    writes = ArgumentParser(add_help=False)
    writes.add_argument("--out", type=Path, required=True, help="map file to write (must not be an input)")
    commands = parser.add_subparsers(dest="command", required=True, metavar="{info,merge,remove-session}")

    info = commands.add_parser("info", help="sessions, robots, places and vocabulary of a map")
    info.add_argument("map", type=Path, help="map file (.npz)")
    info.add_argument("--json", type=Path, help="also write the summary to this JSON file")

    merge = commands.add_parser("merge", parents=[writes], help="one map of A's places followed by B's")
    merge.add_argument("first", type=Path, metavar="A", help="map whose places come first (its settings are kept)")
    merge.add_argument("second", type=Path, metavar="B", help="map whose places and sessions follow A's")
    merge.add_argument("--model", type=Path, help="model directory: also refuse maps of another vocabulary")

    remove = commands.add_parser("remove-session", parents=[writes], help="drop one session and its places")
    remove.add_argument("map", type=Path, help="map file (.npz)")
    remove.add_argument("session", type=int, help="session number (see info)")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, run)


def run(args: argparse.Namespace) -> int:
    if args.command == "info":
        return run_info(args.map, args.json)
    if args.command == "merge":
        return run_merge(args.first, args.second, args.out, args.model)
    return run_remove_session(args.map, args.session, args.out)


def run_info(path: Path, json_path: Path | None) -> int:
    import json

    from aefabmap_ros.fabmap.map_tools import map_summary
    from aefabmap_ros.io.atomic import atomic_write_text

    summary = map_summary(read_map_file(path), file_bytes=path.stat().st_size)
    print(format_summary(path, summary))
    if json_path is not None:
        atomic_write_text(json_path, json.dumps({"map": str(path), **summary.to_json()}, indent=2) + "\n")
    return 0


def run_merge(first: Path, second: Path, out: Path, model: Path | None) -> int:
    from aefabmap_ros.fabmap.map_file import write_map
    from aefabmap_ros.fabmap.map_tools import map_summary, merge_maps

    check_output(out, first, second)
    a, b = read_map_file(first), read_map_file(second)
    if model is not None:
        check_model_vocabulary(model, {first: a, second: b})
    merged = merge_maps(a, b, names=(f"map file {first}", f"map file {second}"))
    write_map(out, merged)
    summary = map_summary(merged)
    print(f"{out}: {summary.places} places in {_count(len(summary.sessions), 'session')} "
          f"({first}: {_places(a)}, {second}: {_places(b)})")
    return 0


def run_remove_session(path: Path, number: int, out: Path) -> int:
    from aefabmap_ros.fabmap.map_file import write_map
    from aefabmap_ros.fabmap.map_tools import map_summary, remove_session

    check_output(out, path)
    arrays = read_map_file(path)
    kept = remove_session(arrays, number)
    write_map(out, kept)
    print(f"{out}: {map_summary(kept).places} places in {_count(len(kept['session_robots']), 'session')} "
          f"({_places(arrays) - _places(kept)} places of session {number} removed)")
    return 0


def read_map_file(path: Path) -> MapArrays:
    """A map file's arrays, checked against the vocabulary it names; ModelError naming the file for one that
    cannot be read as a map (also for contents the checks do not expect, e.g. arrays of the wrong rank)."""
    from aefabmap_ros.errors import AefabmapError, ModelError
    from aefabmap_ros.fabmap.map_file import read_map_unchecked_vocabulary

    try:
        return read_map_unchecked_vocabulary(path)
    except AefabmapError:
        raise
    except (ValueError, TypeError, IndexError, KeyError, OSError) as error:
        raise ModelError(f"corrupt map file {path}: {error}") from error


def check_output(out: Path, *inputs: Path) -> None:
    """ConfigError when ``out`` is one of the ``inputs`` (also by another name or a hard link): the inputs are
    read whole before writing, but a refused or interrupted merge must never cost the map it came from."""
    from aefabmap_ros.errors import ConfigError

    for path in inputs:
        same = out.resolve() == path.resolve()
        if not same and out.exists() and path.exists():
            same = os.path.samefile(out, path)
        if same:
            raise ConfigError(f"--out {out} is the input map {path}: write the result to a new file")


def check_model_vocabulary(model: Path, maps: dict[Path, MapArrays]) -> None:
    """VocabularyMismatchError naming the map and both ids when a map is not of ``model``'s vocabulary. Reads
    the model's metadata with its files' checksums checked (no vocabulary is loaded)."""
    from aefabmap_ros.errors import ModelError, VocabularyMismatchError
    from aefabmap_ros.model.directory import check_model_files

    metadata = check_model_files(model)
    try:
        model_id, model_size = str(metadata["model_id"]), int(metadata["vocabulary"]["size"])
    except (TypeError, ValueError) as error:
        raise ModelError(f"model directory {model}: unreadable vocabulary id or size: {error}") from error
    for path, arrays in maps.items():
        map_id, map_size = str(arrays["vocabulary_id"]), int(arrays["vocabulary_size"])
        if (map_id, map_size) != (model_id, model_size):
            raise VocabularyMismatchError(
                f"map file {path} belongs to vocabulary {map_id!r} ({map_size} words), but the model {model} is "
                f"vocabulary {model_id!r} ({model_size} words)"
            )


def format_summary(path: Path, summary: MapSummary) -> str:
    """The summary as a plain-text table."""
    size = "" if summary.file_bytes is None else f"{summary.file_bytes / 1e6:.1f} MB, "
    lines = [
        f"map         {path} ({size}format {summary.format_version})",
        f"vocabulary  {summary.vocabulary_id} ({summary.vocabulary_size} words)",
        f"places      {summary.places} ({summary.words_stored} words stored, "
        f"{summary.words_stored / max(summary.places, 1):.1f} a place)",
        f"queries     {summary.next_query_id} (next query id)",
        f"robots      {', '.join(repr(robot) for robot in summary.robots) or '-'}",
        f"sessions    {len(summary.sessions)}",
    ]
    header = ("session", "robot", "places", "first query", "first stamp [s]", "last stamp [s]")
    rows = [header] + [
        (str(s.number), repr(s.robot), str(s.places), str(s.first_query_id), _seconds(s.first_stamp_ns),
         _seconds(s.last_stamp_ns))
        for s in summary.sessions
    ]
    widths = [max(len(row[column]) for row in rows) for column in range(len(header))]
    lines += ["  " + "  ".join(cell.rjust(width) if column != 1 else cell.ljust(width)
                                for column, (cell, width) in enumerate(zip(row, widths, strict=True)))
              for row in rows]
    return "\n".join(lines)


def _seconds(stamp_ns: int | None) -> str:
    return "-" if stamp_ns is None else f"{stamp_ns / 1e9:.3f}"


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def _places(arrays: MapArrays) -> int:
    return int(len(arrays["word_indptr"]) - 1)


if __name__ == "__main__":
    sys.exit(main())
