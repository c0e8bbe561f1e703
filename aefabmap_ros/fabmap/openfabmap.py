"""openFABMAP's files: OpenCV FileStorage YAML with ``!!opencv-matrix`` nodes.

openFABMAP (``openFABMAPcli``) keeps its vocabulary (node ``Vocabulary``, K x D float32),
Chow-Liu tree (node ``ChowLiuTree``, 4 x V float64 [parent; p(z); p(z|zp=1); p(z|zp=0)]) and
bags-of-words (node ``BOWImageDescs``, N x V float32, a word is present when its value is > 0)
in such files. OpenCV's own ``cv2.FileStorage`` reads and writes them (in memory, so that the
file is read and written by us: errors name the file, writes are atomic).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from aefabmap_ros.errors import ModelError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.io.atomic import atomic_write_text

VOCABULARY_NODE = "Vocabulary"
TREE_NODE = "ChowLiuTree"
BOW_NODE = "BOWImageDescs"

# Element types FileStorage stores as single-channel matrices; anything else is written as float64.
_WRITABLE = {np.dtype(t) for t in (np.uint8, np.int8, np.uint16, np.int16, np.int32, np.float32, np.float64)}


def read_opencv_matrix(path: Path | str, node: str) -> np.ndarray:
    """The matrix stored under top-level ``node`` of an OpenCV YAML file; ModelError naming file and node."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except (OSError, UnicodeDecodeError) as error:
        raise ModelError(f"cannot read openFABMAP file {path}: {error}") from error
    if not text.lstrip().startswith("%YAML"):
        raise ModelError(f"{path} is not an OpenCV YAML file (no %YAML header)")
    try:
        storage = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except cv2.error as error:
        raise ModelError(f"{path} is not readable by OpenCV's FileStorage: {_first_line(error)}") from error
    try:
        found = storage.getNode(node)
        if found.empty() or found.isNone():
            raise ModelError(f"{path} has no matrix node {node!r}")
        try:
            matrix = found.mat()
        except cv2.error as error:
            raise ModelError(f"{path}: node {node!r} is a malformed matrix: {_first_line(error)}") from error
    finally:
        storage.release()
    if not isinstance(matrix, np.ndarray) or matrix.ndim != 2:
        raise ModelError(f"{path}: node {node!r} is not a single-channel matrix")
    return matrix


def _first_line(error: cv2.error) -> str:
    return str(error).strip().splitlines()[-1]


def write_opencv_matrices(path: Path | str, nodes: Mapping[str, np.ndarray]) -> None:
    """Write 2-D single-channel matrices as an OpenCV YAML file, atomically (temp file + os.replace)."""
    path = Path(path)
    storage = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    for name, matrix in nodes.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            storage.release()
            raise ModelError(f"invalid OpenCV node name {name!r}")
        array = np.asarray(matrix)
        if array.ndim != 2:
            storage.release()
            raise ModelError(f"node {name!r}: only 2-D matrices can be written, got shape {array.shape}")
        storage.write(name, np.ascontiguousarray(array if array.dtype in _WRITABLE else array.astype(np.float64)))
    text = storage.releaseAndGetString()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)


def read_vocabulary(path: Path | str) -> np.ndarray:
    """(K, D) float32 visual-word centres (node ``Vocabulary``)."""
    return read_opencv_matrix(path, VOCABULARY_NODE).astype(np.float32)


def read_chow_liu_tree(path: Path | str) -> ChowLiuTree:
    """Chow-Liu tree (node ``ChowLiuTree``, 4 x V); ModelError if malformed."""
    matrix = read_opencv_matrix(path, TREE_NODE)
    try:
        return ChowLiuTree.from_matrix(matrix.astype(np.float64))
    except ModelError as error:
        raise ModelError(f"{path}: {error}") from error


def read_bow(path: Path | str) -> np.ndarray:
    """(N, V) float32 bag-of-words (node ``BOWImageDescs``; present = value > 0)."""
    return read_opencv_matrix(path, BOW_NODE).astype(np.float32)


def write_vocabulary(path: Path | str, centres: np.ndarray) -> None:
    write_opencv_matrices(path, {VOCABULARY_NODE: np.asarray(centres, dtype=np.float32)})


def write_chow_liu_tree(path: Path | str, tree: ChowLiuTree) -> None:
    write_opencv_matrices(path, {TREE_NODE: tree.to_matrix()})


def write_bow(path: Path | str, bow: np.ndarray) -> None:
    write_opencv_matrices(path, {BOW_NODE: np.asarray(bow, dtype=np.float32)})
