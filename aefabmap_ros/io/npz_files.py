"""Versioned .npz state files (the FAB-MAP map, the verifier's feature store): atomic write, checked read."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from aefabmap_ros.errors import ModelError
from aefabmap_ros.io.atomic import atomic_write_bytes


def npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """The content of an uncompressed .npz holding ``arrays``."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz (no pickles); ModelError naming the file when it cannot be read."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except Exception as error:  # numpy raises several types for corrupt archives
        raise ModelError(f"cannot read {path}: {error}") from error


def write_npz_atomically(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """All arrays into one .npz at ``path`` (folders created); readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, npz_bytes(arrays))


def read_versioned_npz(path: Path, what: str, kind: str, required: Sequence[str],
                       version: int | Sequence[int]) -> dict[str, np.ndarray]:
    """The arrays of a ``what`` file (e.g. "map file"), checked for the ``required`` keys (else it is
    "not a ``kind``") and a ``format_version`` this reader knows (``version``, or one of several);
    ModelError naming the file otherwise."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except FileNotFoundError as error:
        raise ModelError(f"{what} not found: {path}") from error
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise ModelError(f"cannot read {what} {path}: {error}") from error
    missing = [key for key in ("format_version", *required) if key not in arrays]
    if missing:
        raise ModelError(f"{what} {path} is not a {kind} (missing {missing})")
    known = (version,) if isinstance(version, int) else tuple(version)
    found = int(arrays["format_version"])
    if found not in known:
        expected = str(known[0]) if len(known) == 1 else " or ".join(map(str, known))
        raise ModelError(f"{what} {path} has format version {found}, expected {expected}")
    return arrays
