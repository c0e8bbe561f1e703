"""Image sequences for training and evaluation: a bag's image topic or a folder of image files.

Both yield ``(stamp_ns, gray)`` in sequence order. A folder is ordered by natural sort
(``2.jpg`` before ``10.jpg``), and its frames are stamped by index at ``folder_period_ns``;
an unreadable file is an ``ImageError`` naming it, never a silently shorter sequence, because
frame indices must line up with the ground truth.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aefabmap_ros.errors import DataError, ImageError
from aefabmap_ros.io import bags
from aefabmap_ros.io.image_messages import image_message_to_gray

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")
FOLDER_PERIOD_NS = 100_000_000  # folder frames are stamped at 10 Hz by index


def _natural_key(path: Path) -> list[int | str]:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def folder_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise DataError(f"image folder does not exist: {folder}")
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
    if not files:
        raise DataError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in folder {folder}")
    return files


def read_gray(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise ImageError(f"cannot read image file {path}")
    return image


@dataclass(frozen=True)
class ImageSource:
    """A bag topic (``bag`` + ``topic``) or a folder of images (``folder``)."""

    bag: Path | None = None
    topic: str = "/image"
    folder: Path | None = None
    folder_period_ns: int = FOLDER_PERIOD_NS  # a folder's frames are stamped index * this

    def __post_init__(self) -> None:
        if (self.bag is None) == (self.folder is None):
            raise DataError("an image source is either a bag (with a topic) or a folder, not both or neither")
        if self.folder_period_ns <= 0:
            raise DataError(f"folder_period_ns must be > 0, got {self.folder_period_ns}")

    @property
    def name(self) -> str:
        return f"{self.bag}:{self.topic}" if self.bag is not None else str(self.folder)

    def check(self) -> None:
        """Fail early, before any work, on a missing bag/topic/folder."""
        if self.bag is not None:
            bags.require_image_topic(self.bag, self.topic)
        else:
            assert self.folder is not None
            folder_images(self.folder)

    def fingerprint(self) -> str:
        """Changes whenever the source's content may have changed (names, sizes, modification times)."""
        digest = hashlib.sha256(self.name.encode())
        files = (sorted(p for p in self.bag.rglob("*") if p.is_file()) if self.bag is not None
                 else folder_images(self.folder) if self.folder is not None else [])
        for path in files:
            stat = path.stat()
            digest.update(f"{path.name}:{stat.st_size}:{stat.st_mtime_ns}".encode())
        return digest.hexdigest()[:16]

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        if self.bag is not None:
            for message in bags.read_messages(self.bag, [self.topic]):
                yield message.stamp_ns, image_message_to_gray(message.message)
        else:
            assert self.folder is not None
            for index, path in enumerate(folder_images(self.folder)):
                yield index * self.folder_period_ns, read_gray(path)

    def stamps_ns(self) -> np.ndarray:
        """(N,) int64 stamps of the frames, in sequence order (a bag's header stamps; no image decoded)."""
        if self.bag is not None:
            return np.array([m.stamp_ns for m in bags.read_messages(self.bag, [self.topic])], dtype=np.int64)
        assert self.folder is not None
        return np.arange(len(folder_images(self.folder)), dtype=np.int64) * self.folder_period_ns

    def __len__(self) -> int:
        if self.folder is not None:
            return len(folder_images(self.folder))
        assert self.bag is not None
        return bags.message_count(self.bag, self.topic)
