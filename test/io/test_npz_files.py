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


def test_an_array_read_with_room_is_the_start_of_a_larger_buffer(tmp_path):
    """Read with room, a 1-D array equals the saved one and sits at the start of a buffer an eighth larger, which
    a growable array adopts as its capacity: the index grows into it without copying the loaded map."""
    from aefabmap_ros.fabmap.index import GrowableArray

    path = tmp_path / "state.npz"
    values = np.arange(800, dtype=np.uint16)
    write_npz_atomically(path, {"format_version": np.array(3), "values": values, "other": np.eye(2)})
    arrays = read_versioned_npz(path, "test file", "test state", ("values",), 3, room={"values": 0.125})
    np.testing.assert_array_equal(arrays["values"], values)
    np.testing.assert_array_equal(arrays["other"], np.eye(2))
    assert arrays["values"].base is not None and arrays["values"].base.size == 900
    grown = GrowableArray(np.uint16)
    grown.adopt(arrays["values"])
    grown.extend(np.array([7, 8], dtype=np.uint16))
    assert grown.nbytes == 900 * 2  # grew into the room, no new buffer
    np.testing.assert_array_equal(grown.view(), np.concatenate([values, [7, 8]]))


def test_a_truncated_array_read_with_room_is_refused_by_name(tmp_path):
    path = tmp_path / "state.npz"
    write_npz_atomically(path, {"format_version": np.array(3), "values": np.arange(5000, dtype=np.int32)})
    path.write_bytes(path.read_bytes()[:-3000])
    with pytest.raises(ModelError, match="cannot read test file"):
        read_versioned_npz(path, "test file", "test state", ("values",), 3, room={"values": 0.125})
