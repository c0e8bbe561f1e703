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


def _read_member_with_room(archive: zipfile.ZipFile, key: str, room: float) -> np.ndarray | None:
    """A 1-D array member ``key`` read straight into a buffer ``room`` times larger than it (its first values; the
    buffer is the array's ``base``), so an index that grows from it need not copy it; None when the member is
    not a plain 1-D array (then it is read as usual)."""
    with archive.open(f"{key}.npy") as member:
        version = np.lib.format.read_magic(member)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran_order, dtype = read_header(member)
        if len(shape) != 1 or fortran_order or dtype.hasobject:
            return None
        buffer = np.empty(shape[0] + int(shape[0] * room), dtype=dtype)
        target = memoryview(buffer[: shape[0]].view(np.uint8))  # type: ignore[arg-type]  # numpy arrays are buffers
        filled = 0
        while filled < target.nbytes:
            got = member.readinto(target[filled:])  # type: ignore[attr-defined]  # a ZipExtFile has it
            if not got:
                raise EOFError(f"{key}: the archive ends inside the array")
            filled += got
        member.read(1)  # at the end of the member: zipfile checks its CRC
        return buffer[: shape[0]]


def read_versioned_npz(path: Path, what: str, kind: str, required: Sequence[str],
                       version: int | Sequence[int], room: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
    """The arrays of a ``what`` file (e.g. "map file"), checked for the ``required`` keys (else it is
    "not a ``kind``") and a ``format_version`` this reader knows (``version``, or one of several);
    ModelError naming the file otherwise. The 1-D arrays named in ``room`` are read into buffers that many
    times larger than they are (see ``_read_member_with_room``)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files if key not in (room or {})}
        with zipfile.ZipFile(path) as archive:
            for key, fraction in (room or {}).items():
                if f"{key}.npy" in archive.namelist():
                    roomy = _read_member_with_room(archive, key, fraction)
                    arrays[key] = roomy if roomy is not None else np.load(archive.open(f"{key}.npy"))
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
