"""Atomic file writes: a temporary file in the same folder, flushed to disk, then ``os.replace``.

A reader sees the old file or the new one, never half of one, even if the writer is killed.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


@contextmanager
def atomic_open(path: Path) -> Iterator[BinaryIO]:
    """A binary file for ``path``'s new content, for writers that take a file (``np.savez``, ``savefig``):
    on a clean exit it is flushed to disk and replaces ``path``; on an error it is removed."""
    path = Path(path)
    handle, temp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
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
