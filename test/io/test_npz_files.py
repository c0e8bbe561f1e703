"""Versioned .npz state files: atomic write, and every way a read is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.errors import ModelError
from aefabmap_ros.io.npz_files import read_versioned_npz, write_npz_atomically


def _read(path: Path) -> dict[str, np.ndarray]:
    return read_versioned_npz(path, "test file", "test state", ("values",), 3)


def test_round_trip_creates_folders_and_leaves_no_temporary_file(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "state.npz"
    write_npz_atomically(path, {"format_version": np.array(3), "values": np.arange(4.0)})
    assert sorted(p.name for p in path.parent.iterdir()) == ["state.npz"]
    np.testing.assert_array_equal(_read(path)["values"], np.arange(4.0))


def test_refusals_name_the_file_and_the_reason(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="test file not found"):
        _read(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ModelError, match=r"cannot read test file .*junk\.npz"):
        _read(tmp_path / "junk.npz")
    write_npz_atomically(tmp_path / "other.npz", {"format_version": np.array(3)})
    with pytest.raises(ModelError, match=r"is not a test state \(missing \['values'\]\)"):
        _read(tmp_path / "other.npz")
    write_npz_atomically(tmp_path / "old.npz", {"format_version": np.array(2), "values": np.zeros(1)})
    with pytest.raises(ModelError, match="format version 2, expected 3"):
        _read(tmp_path / "old.npz")
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, format_version=np.array(3), values=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ModelError, match="cannot read test file"):  # object arrays need pickle: refused
        _read(pickled)
