"""Atomic file writes: a temporary file in the same folder, flushed to disk, then ``os.replace``.

A reader sees the old file or the new one, never half of one, even if the writer is killed.

The new file has the old one's permission bits, or, for a file that did not exist, what ``open()``
would have given it (0666 without the umask's bits): ``tempfile.mkstemp`` makes its file 0600, and
a map that another user or group was allowed to read must stay readable after a save.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


def _current_umask() -> int:
    """The process's umask: from /proc on Linux (a read that changes nothing), else by setting it and setting it
    straight back (for an instant another thread's new file would get 022)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _mode_for(path: Path) -> int:
    """The permission bits ``path``'s new content gets: the existing file's, else 0666 less the umask."""
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        return 0o666 & ~_current_umask()


@contextmanager
def atomic_open(path: Path) -> Iterator[BinaryIO]:
    """A binary file for ``path``'s new content, for writers that take a file (``np.savez``, ``savefig``):
    on a clean exit it is flushed to disk and replaces ``path``; on an error it is removed."""
    path = Path(path)
    handle, temp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(handle, _mode_for(path))
        with os.fdopen(handle, "wb") as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(temp_name, path)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path, data: bytes) -> None:
    with atomic_open(path) as file:
        file.write(data)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def remove_stale_temporaries(folder: Path, name_pattern: str) -> list[Path]:
    """Delete the temporaries :func:`atomic_write_bytes` left in ``folder`` for files named like
    ``name_pattern`` (a glob, e.g. ``map.npz`` or ``chunk-*.npz``) when a writer was killed mid-write.

    Call it at start-up, before this process writes there: a temporary being written by a live
    writer of the same file would go too (and two writers of one file are a mistake anyway).
    Returns the files removed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    for temporary in sorted(folder.glob(f".{name_pattern}.*.tmp")):
        if temporary.is_file():
            temporary.unlink(missing_ok=True)
            removed.append(temporary)
    return removed
