"""The features of past frames by image stamp, in memory and on disk: what the online verifier checks a
loop closure against."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.features.descriptors import BINARY, FLOAT, kind_of
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.features.matching import check_features
from aefabmap_ros.io.chunk_folder import ChunkFolder
from aefabmap_ros.io.npz_files import read_versioned_npz

STORE_FORMAT_VERSION = 1
# Strongest keypoints kept per frame by default (verifier_node's max_stored_features): ~128 KiB a frame of SIFT.
DEFAULT_MAX_STORED_FEATURES = 500


class FeatureStore:
    """Features of past frames by image stamp, for verifying loop closures online.

    Bounded: at most ``max_frames`` frames (the oldest is forgotten first) and, when
    ``max_features_per_frame`` > 0, only each frame's strongest keypoints (by detector response).
    Float descriptors are kept as float16: half the memory, and exact for OpenCV's SIFT, whose
    values are integers below 256 (RootSIFT loses about 1e-4 of its unit-norm values); binary ones
    are kept as they are. About 128 KiB per frame of 500 SIFT features.
    """

    def __init__(self, max_frames: int, max_features_per_frame: int = 0) -> None:
        if max_frames < 1 or max_features_per_frame < 0:
            raise ConfigError(f"FeatureStore needs max_frames >= 1 (got {max_frames}) and "
                              f"max_features_per_frame >= 0 (got {max_features_per_frame})")
        self.max_frames = max_frames
        self.max_features_per_frame = max_features_per_frame
        self._frames: dict[int, Features] = {}  # insertion-ordered: the first key is the oldest
        self._unsaved: dict[int, None] = {}  # stamps added since the last save, in order (an ordered set)
        self._nbytes = 0

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, stamp_ns: object) -> bool:
        return stamp_ns in self._frames

    @property
    def nbytes(self) -> int:
        return self._nbytes

    def stamps(self) -> list[int]:
        """The stored frames' stamps, in the order they were added."""
        return list(self._frames)

    def add(self, stamp_ns: int, features: Features) -> np.ndarray:
        """Store (or replace) the features of the frame stamped ``stamp_ns``; the rows of ``features`` kept.

        DataError for malformed features and for a descriptor kind (type, dtype, length) other than
        that of the frames already stored: one store is saved as one kind, and a stray frame of
        another would make every later save fail.
        """
        check_features(features, "stored frame")
        kind = _kind(features.descriptor_type, features.descriptors)
        stored_kind = self.descriptor_kind
        if stored_kind is not None and kind != stored_kind:
            raise DataError(f"features of kind {kind} (type, dtype, length), but the store holds {stored_kind}")
        keep = stored_rows(features, self.max_features_per_frame)
        descriptors = features.descriptors[keep]
        descriptors = descriptors.astype(kind_of(descriptors).stored_dtype, copy=False)
        compact = Features(keypoints=np.ascontiguousarray(features.keypoints[keep, :2], dtype=np.float32),
                           descriptors=np.ascontiguousarray(descriptors), descriptor_type=features.descriptor_type)
        self.forget(stamp_ns)
        self._frames[stamp_ns] = compact
        self._unsaved[stamp_ns] = None
        self._nbytes += compact.keypoints.nbytes + compact.descriptors.nbytes
        while len(self._frames) > self.max_frames:
            self.forget(next(iter(self._frames)))
        return keep

    @property
    def descriptor_kind(self) -> tuple[str, str, int] | None:
        """(type, stored dtype, length) of the stored frames' descriptors; None when the store is empty."""
        if not self._frames:
            return None
        first = next(iter(self._frames.values()))
        return _kind(first.descriptor_type, first.descriptors)

    def get(self, stamp_ns: int) -> Features | None:
        """The stored features of that frame (float descriptors back as float32), None if unknown."""
        stored = self._frames.get(stamp_ns)
        if stored is None:
            return None
        descriptors = stored.descriptors
        if descriptors.dtype == np.float16:
            descriptors = descriptors.astype(np.float32)
        return Features(keypoints=stored.keypoints, descriptors=descriptors, descriptor_type=stored.descriptor_type)

    def unsaved(self) -> list[tuple[int, Features]]:
        """The frames added since the last ``mark_saved``, oldest first."""
        return [(stamp, self._frames[stamp]) for stamp in self._unsaved]

    def mark_saved(self) -> None:
        self._unsaved.clear()

    def restore(self, frames: list[tuple[int, Features]]) -> None:
        """Replace the contents by already compact frames (the newest ``max_frames``), all saved."""
        self._frames.clear()
        self._unsaved.clear()
        self._nbytes = 0
        for stamp_ns, features in frames:
            self.forget(stamp_ns)  # a later chunk's copy of a frame replaces the earlier one
            self._frames[stamp_ns] = features
            self._nbytes += features.keypoints.nbytes + features.descriptors.nbytes
        while len(self._frames) > self.max_frames:
            self.forget(next(iter(self._frames)))

    def forget(self, stamp_ns: int) -> None:
        """Drop that frame's features (nothing when they are not stored)."""
        stored = self._frames.pop(stamp_ns, None)
        self._unsaved.pop(stamp_ns, None)
        if stored is not None:
            self._nbytes -= stored.keypoints.nbytes + stored.descriptors.nbytes


def stored_rows(features: Features, max_features: int) -> np.ndarray:
    """The rows of ``features`` a store keeps: the ``max_features`` strongest (0 = all), in their order."""
    if not max_features or len(features) <= max_features:
        return np.arange(len(features))
    if features.keypoints.shape[1] < 5:
        raise DataError(f"stored frame keypoints of shape {features.keypoints.shape} have no response "
                        "column (5th) to keep the strongest by")
    # Strongest first; a stable sort keeps the detector's order among equal responses.
    return np.sort(np.argsort(-features.keypoints[:, 4], kind="stable")[:max_features])


def _kind(descriptor_type: str, descriptors: np.ndarray) -> tuple[str, str, int]:
    """A descriptor kind as stored: float descriptors are kept as float16, so float32 and float16 agree."""
    dtype = np.dtype(kind_of(descriptors).stored_dtype)
    return descriptor_type, dtype.str, int(descriptors.shape[1])


_STORE_KEYS = ("descriptor_type", "stamps_ns", "counts", "keypoints", "descriptors")


class FeatureStoreFolder(ChunkFolder[Features]):
    """A FeatureStore on disk, as an append-only folder of chunk files (``chunk-<n>.npz``, see
    :mod:`aefabmap_ros.io.chunk_folder`): each ``save`` writes only the frames added since the last
    one. ``load_into`` reads the chunks in order (a later copy of a frame wins) and keeps the newest
    ``max_frames``.
    """

    PREFIX: ClassVar[str] = "chunk"  # its chunk files: chunk-<n>.npz

    def __init__(self, folder: Path) -> None:
        super().__init__(folder, self.PREFIX, "feature store", _frames_to_arrays, _read_chunk)


def _read_chunk(chunk: Path) -> list[tuple[int, Features]]:
    arrays = read_versioned_npz(chunk, "feature store chunk", "feature store chunk", _STORE_KEYS, STORE_FORMAT_VERSION)
    return _stored_frames(chunk, arrays)


def _frames_to_arrays(frames: list[tuple[int, Features]]) -> dict[str, np.ndarray]:
    kinds = {(f.descriptor_type, f.descriptors.dtype.str, f.descriptors.shape[1]) for _, f in frames}
    if len(kinds) > 1:
        raise DataError(f"the feature store mixes descriptor kinds {sorted(kinds)}; it cannot be saved as one")
    kind, dtype, width = kinds.pop() if kinds else ("", np.dtype(np.float16).str, 0)
    return {
        "format_version": np.array(STORE_FORMAT_VERSION, dtype=np.int64),
        "descriptor_type": np.array(kind),
        "stamps_ns": np.array([stamp for stamp, _ in frames], dtype=np.int64),
        "counts": np.array([len(f) for _, f in frames], dtype=np.int64),
        "keypoints": np.concatenate([f.keypoints for _, f in frames]) if frames else np.zeros((0, 2), np.float32),
        "descriptors": (np.concatenate([f.descriptors for _, f in frames]) if frames
                        else np.zeros((0, width), np.dtype(dtype))),
    }


def _stored_frames(path: Path, arrays: dict[str, np.ndarray]) -> list[tuple[int, Features]]:
    """The frames of a saved chunk (keys and version already checked); ModelError naming what is wrong."""
    stamps, counts = arrays["stamps_ns"], arrays["counts"]
    keypoints, descriptors = arrays["keypoints"], arrays["descriptors"]
    problems = []
    if stamps.ndim != 1 or counts.shape != stamps.shape or np.unique(stamps).size != stamps.size:
        problems.append("stamps and counts must be equally long, the stamps unique")
    if counts.size and counts.min() < 0:
        problems.append("negative keypoint counts")
    if keypoints.ndim != 2 or keypoints.shape[1] != 2 or keypoints.dtype != np.float32:
        problems.append(f"keypoints must be (K, 2) float32, got {keypoints.shape} {keypoints.dtype}")
    if descriptors.ndim != 2 or descriptors.dtype not in (BINARY.stored_dtype, FLOAT.stored_dtype):
        problems.append(f"descriptors must be (K, D) float16 or uint8, got {descriptors.shape} {descriptors.dtype}")
    if not problems and not (int(counts.sum()) == keypoints.shape[0] == descriptors.shape[0]):
        problems.append(f"{int(counts.sum())} keypoints counted, {keypoints.shape[0]} keypoints and "
                        f"{descriptors.shape[0]} descriptors stored")
    if problems:
        raise ModelError(f"feature store chunk {path} is corrupt: {'; '.join(problems)}")
    kind = str(arrays["descriptor_type"])
    ends = np.cumsum(counts)
    return [
        # Copies, not views of the file's arrays: forgetting a frame must free its memory.
        (int(stamp), Features(keypoints=keypoints[end - count : end].copy(),
                              descriptors=descriptors[end - count : end].copy(), descriptor_type=kind))
        for stamp, count, end in zip(stamps.tolist(), counts.tolist(), ends.tolist(), strict=True)
    ]
