"""ChunkFolder with a hand-made store: what each save writes, what it deletes, and how it reads back."""

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.errors import ModelError
from aefabmap_ros.io.chunk_folder import ChunkFolder


class _Store:
    """Frames by stamp, the oldest forgotten beyond ``limit``; remembers which are not saved yet."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.frames: dict[int, float] = {}
        self._unsaved: list[int] = []

    def add(self, stamp: int) -> None:
        self.frames[stamp] = float(stamp) / 10
        self._unsaved.append(stamp)
        while len(self.frames) > self.limit:
            del self.frames[min(self.frames)]

    def unsaved(self) -> list[tuple[int, float]]:
        return [(stamp, self.frames[stamp]) for stamp in self._unsaved if stamp in self.frames]

    def mark_saved(self) -> None:
        self._unsaved = []

    def __contains__(self, stamp: object) -> bool:
        return stamp in self.frames

    def restore(self, frames: list[tuple[int, float]]) -> None:
        self.frames, self._unsaved = dict(frames), []


def _folder(path: Path) -> ChunkFolder[float]:
    def encode(frames):
        return {"stamps": np.array([s for s, _ in frames]), "values": np.array([v for _, v in frames])}

    def decode(chunk):
        with np.load(chunk) as arrays:
            return list(zip(arrays["stamps"].tolist(), arrays["values"].tolist(), strict=True))

    return ChunkFolder(path, "part", "test store", encode, decode)


def test_each_save_appends_only_new_frames_and_forgotten_chunks_go(tmp_path):
    store, folder = _Store(limit=3), _folder(tmp_path)
    for stamp in (1, 2):
        store.add(stamp)
    folder.save(store)
    folder.save(store)  # nothing new: no empty chunk
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part-000000000.npz"]
    for stamp in (3, 4, 5):  # 1 and 2 are forgotten: the first chunk holds nothing the store still has
        store.add(stamp)
    folder.save(store)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part-000000001.npz"]
    assert _folder(tmp_path).read() == [(3, 0.3), (4, 0.4), (5, 0.5)]


def test_numbering_goes_on_after_a_restart(tmp_path):
    store = _Store(limit=10)
    store.add(1)
    _folder(tmp_path).save(store)
    restarted, reloaded = _folder(tmp_path), _Store(limit=10)
    reloaded.add(7)  # replaced by what was saved
    restarted.load_into(reloaded)
    assert reloaded.frames == {1: 0.1} and reloaded.unsaved() == []
    store.add(2)
    restarted.save(store)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part-000000000.npz", "part-000000001.npz"]
    assert _folder(tmp_path).read() == [(1, 0.1), (2, 0.2)]


def test_a_missing_folder_reads_as_empty_and_bad_ones_are_named(tmp_path):
    assert _folder(tmp_path / "none").read() == []
    (tmp_path / "part-x.npz").write_bytes(b"")
    with pytest.raises(ModelError, match=r"test store .* unexpected name: part-x\.npz"):
        _folder(tmp_path).read()
    file = tmp_path / "file"
    file.write_text("")
    with pytest.raises(ModelError, match="is not a folder"):
        _folder(file).read()
