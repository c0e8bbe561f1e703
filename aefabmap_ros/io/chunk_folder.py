"""Append-only folders of ``<prefix>-<n>.npz`` chunks: how the verifier's stores live on disk.

The feature store and the keypoint depths grow by frames and forget the oldest. Rewriting such a
store on every save would cost its whole size (a full store of 20,000 SIFT frames is ~2.5 GB), so
each save appends one chunk holding only the frames added since the last one, and deletes the
chunks whose frames have all been forgotten. Chunks are written atomically: a crash loses at most
the frames since the last save. What a chunk holds is the caller's (``encode`` / ``decode``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Generic, Protocol, TypeVar

import numpy as np

from aefabmap_ros.errors import ModelError
from aefabmap_ros.io.npz_files import write_npz_atomically

FrameT = TypeVar("FrameT")
Frames = list[tuple[int, FrameT]]  # (stamp in ns, what is kept of that frame), oldest first


class StampedFrames(Protocol[FrameT]):
    """What a store offers the folder that saves it."""

    def unsaved(self) -> list[tuple[int, FrameT]]: ...

    def mark_saved(self) -> None: ...

    def __contains__(self, stamp_ns: object) -> bool: ...

    def restore(self, frames: list[tuple[int, FrameT]]) -> None: ...


def chunk_pattern(prefix: str) -> str:
    """The glob of a chunk folder's chunk files (their temporaries are named from these too)."""
    return f"{prefix}-*.npz"


class ChunkFolder(Generic[FrameT]):
    """``folder/<prefix>-<n>.npz`` chunks, n counting up from 0 across saves and restarts."""

    def __init__(self, folder: Path, prefix: str, what: str,
                 encode: Callable[[Frames[FrameT]], Mapping[str, np.ndarray]],
                 decode: Callable[[Path], Frames[FrameT]]) -> None:
        self.folder = Path(folder)
        self._prefix = prefix
        self._what = what  # e.g. "feature store", for errors
        self._encode = encode
        self._decode = decode
        self._chunk_stamps: dict[Path, set[int]] = {}
        self._next_chunk = 0

    def read(self) -> Frames[FrameT]:
        """Every saved frame, chunk by chunk in order (a later copy of a frame comes later); ModelError
        naming a bad chunk, and then nothing about the saved chunks is remembered."""
        if self.folder.exists() and not self.folder.is_dir():
            raise ModelError(f"{self._what} {self.folder} is not a folder")
        chunks = sorted(self.folder.glob(chunk_pattern(self._prefix))) if self.folder.is_dir() else []
        numbers = [self._chunk_number(chunk) for chunk in chunks]
        frames: Frames[FrameT] = []
        chunk_stamps: dict[Path, set[int]] = {}
        for chunk in chunks:
            chunk_frames = self._decode(chunk)
            chunk_stamps[chunk] = {stamp for stamp, _ in chunk_frames}
            frames += chunk_frames
        self._chunk_stamps = chunk_stamps
        self._next_chunk = 1 + max(numbers, default=-1)
        return frames

    def load_into(self, store: StampedFrames[FrameT]) -> None:
        """Replace ``store``'s frames by the saved ones (``read``); ModelError naming a bad chunk, and then
        the store is unchanged."""
        store.restore(self.read())

    def save(self, store: StampedFrames[FrameT]) -> None:
        """Append the frames added since the last save as one chunk, then delete fully forgotten chunks."""
        frames = store.unsaved()
        if frames:
            self.folder.mkdir(parents=True, exist_ok=True)
            chunk = self.folder / f"{self._prefix}-{self._next_chunk:09d}.npz"
            write_npz_atomically(chunk, self._encode(frames))
            self._chunk_stamps[chunk] = {stamp for stamp, _ in frames}
            self._next_chunk += 1
            store.mark_saved()
        for chunk, stamps in list(self._chunk_stamps.items()):
            if not any(stamp in store for stamp in stamps):
                chunk.unlink(missing_ok=True)
                del self._chunk_stamps[chunk]

    def _chunk_number(self, chunk: Path) -> int:
        try:
            return int(chunk.stem.removeprefix(f"{self._prefix}-"))
        except ValueError as error:
            raise ModelError(f"{self._what} {chunk.parent} holds a chunk with an unexpected name: "
                             f"{chunk.name}") from error
