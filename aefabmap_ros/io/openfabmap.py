"""openFABMAP's files: OpenCV FileStorage YAML with ``!!opencv-matrix`` nodes.

openFABMAP (``openFABMAPcli``) keeps its vocabulary (node ``Vocabulary``, K x D float32),
Chow-Liu tree (node ``ChowLiuTree``, 4 x V float64 [parent; p(z); p(z|zp=1); p(z|zp=0)]) and
bags-of-words (node ``BOWImageDescs``, N x V float32, a word is present when its value is > 0)
in such files. This module reads and writes them without OpenCV (a small parser of the YAML
subset FileStorage writes); files written here open with ``cv2.FileStorage`` and openFABMAP.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from aefabmap_ros.core.atomic import atomic_write_text
from aefabmap_ros.core.chowliu import ChowLiuTree
from aefabmap_ros.core.errors import ModelError

VOCABULARY_NODE = "Vocabulary"
TREE_NODE = "ChowLiuTree"
BOW_NODE = "BOWImageDescs"

# OpenCV FileStorage element type codes.
_DTYPES: dict[str, np.dtype] = {
    "u": np.dtype(np.uint8),
    "c": np.dtype(np.int8),
    "w": np.dtype(np.uint16),
    "s": np.dtype(np.int16),
    "i": np.dtype(np.int32),
    "f": np.dtype(np.float32),
    "d": np.dtype(np.float64),
}
_CODES = {dtype: code for code, dtype in _DTYPES.items()}
_SPECIAL = {".nan": "nan", ".inf": "inf", "-.inf": "-inf", "+.inf": "inf"}
_NODE_RE = r"^{name}\s*:\s*!!opencv-matrix\s*$"


def read_opencv_matrix(path: Path | str, node: str) -> np.ndarray:
    """The matrix stored under top-level ``node`` of an OpenCV YAML file; ModelError naming file and node."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except (OSError, UnicodeDecodeError) as error:
        raise ModelError(f"cannot read openFABMAP file {path}: {error}") from error
    if not text.lstrip().startswith("%YAML"):
        raise ModelError(f"{path} is not an OpenCV YAML file (no %YAML header)")
    match = re.search(_NODE_RE.format(name=re.escape(node)), text, flags=re.MULTILINE)
    if match is None:
        raise ModelError(f"{path} has no matrix node {node!r}")
    body = text[match.end() :]
    fields = {}
    for key in ("rows", "cols", "dt"):
        found = re.search(rf"^\s+{key}\s*:\s*(\S+)\s*$", body, flags=re.MULTILINE)
        if found is None:
            raise ModelError(f"{path}: node {node!r} lacks '{key}'")
        fields[key] = found.group(1)
    data_match = re.search(r"^\s+data\s*:\s*\[(.*?)\]", body, flags=re.MULTILINE | re.DOTALL)
    if data_match is None:
        raise ModelError(f"{path}: node {node!r} lacks 'data: [...]'")
    try:
        rows, cols = int(fields["rows"]), int(fields["cols"])
    except ValueError as error:
        raise ModelError(f"{path}: node {node!r} has non-integer rows/cols {fields}") from error
    dtype = _DTYPES.get(fields["dt"])
    if dtype is None:
        raise ModelError(f"{path}: node {node!r} has unsupported dt {fields['dt']!r} (single-channel only)")
    tokens = data_match.group(1).replace(",", " ").split()
    try:
        values = np.array([_SPECIAL.get(t.lower(), t) for t in tokens], dtype=np.float64)
    except ValueError as error:
        raise ModelError(f"{path}: node {node!r} has a non-numeric value: {error}") from error
    if values.size != rows * cols:
        raise ModelError(f"{path}: node {node!r} has {values.size} values for {rows} x {cols}")
    return values.reshape(rows, cols).astype(dtype)


def _format_values(values: np.ndarray) -> list[str]:
    if values.dtype == np.float64:
        return [_float_token(repr(float(v))) for v in values]
    if values.dtype == np.float32:
        return [_float_token(f"{float(v):.9g}") for v in values]
    return [str(int(v)) for v in values]


def _float_token(token: str) -> str:
    lowered = token.lower()
    if lowered == "nan":
        return ".Nan"
    if lowered in ("inf", "-inf"):
        return ("-" if lowered.startswith("-") else "") + ".Inf"
    return token


def write_opencv_matrices(path: Path | str, nodes: Mapping[str, np.ndarray]) -> None:
    """Write 2-D single-channel matrices as an OpenCV YAML file, atomically (temp file + os.replace)."""
    path = Path(path)
    lines = ["%YAML:1.0", "---"]
    for name, matrix in nodes.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise ModelError(f"invalid OpenCV node name {name!r}")
        array = np.asarray(matrix)
        if array.ndim != 2:
            raise ModelError(f"node {name!r}: only 2-D matrices can be written, got shape {array.shape}")
        if array.dtype not in _CODES:
            array = array.astype(np.float64)
        tokens = _format_values(array.ravel())
        lines += [
            f"{name}: !!opencv-matrix",
            f"   rows: {array.shape[0]}",
            f"   cols: {array.shape[1]}",
            f"   dt: {_CODES[array.dtype]}",
        ]
        chunks = [", ".join(tokens[i : i + 8]) for i in range(0, len(tokens), 8)] or [""]
        lines.append("   data: [ " + (",\n       ".join(chunks)) + " ]")
    text = "\n".join(lines) + "\n"
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
