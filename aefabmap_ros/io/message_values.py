"""Whether a stamp, a pose or a covariance read from a message can be used: the one check shared by the
example backend (pose_graph_node), the odometry gate (verifier_node) and the pose graph itself. It sits in
io/ with the other message readers so that the message conversions (nodes/messages.py) need no backend.

Each ``*_problem`` function returns None for a usable value, else one sentence naming the value and why
it cannot be used (for a node's drop log). It never raises, whatever the floats: NaN, inf, 1e308, a zero
quaternion. Pure numpy: the nodes convert their messages to sequences first (nodes/messages.py).

What is refused, and why:

* a non-finite number anywhere: scipy refuses to build a rotation from it, and one NaN in the pose graph
  spreads to every keyframe at the next optimisation;
* a quaternion whose norm is off 1 by more than ``QUATERNION_NORM_TOLERANCE``: a driver's quaternion is
  normalised to float precision (1e-7), so a norm of 0 (an unset orientation) or of 1.5 is a broken
  message, not one to normalise and trust;
* a position beyond ``MAX_POSITION_M``: farther than any Earth-bound frame reaches (ECEF coordinates
  stay below 6.4e6 m), so a corrupt value; the drift model's arithmetic stays finite below it;
* a covariance entry beyond ``MAX_VARIANCE`` (a standard deviation of 1e6 m or rad: no information),
  one that is not symmetric, or one with a negative eigenvalue, each beyond the round-off of a
  covariance computed in single precision (``COVARIANCE_RELATIVE_TOLERANCE`` of its largest entry).
  What is accepted may still be a hair off positive semi-definite: its user takes ``psd_part``;
* a stamp whose ``nanosec`` is not below 1e9 (or whose ``sec`` leaves int32): not a ROS time.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

QUATERNION_NORM_TOLERANCE = 1e-3
MAX_POSITION_M = 1e8
MAX_VARIANCE = 1e12
COVARIANCE_RELATIVE_TOLERANCE = 1e-6
NANOSECONDS_PER_SECOND = 1_000_000_000


def _floats(values: Any, what: str, size: int) -> tuple[np.ndarray | None, str | None]:
    """``values`` as a flat float64 array of ``size`` numbers, or why not."""
    try:
        array = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError) as exc:
        return None, f"{what} is not a sequence of numbers ({exc})"
    if array.size != size:
        return None, f"{what} has {array.size} values, not {size}"
    return array, None


def _first_non_finite(array: np.ndarray, what: str, names: Sequence[str] | None = None) -> str | None:
    bad = np.flatnonzero(~np.isfinite(array))
    if not bad.size:
        return None
    index = int(bad[0])
    label = names[index] if names is not None else f"[{index}]"
    return f"{what} {label} = {array[index]} is not finite"


def stamp_problem(sec: Any, nanosec: Any, what: str = "stamp") -> str | None:
    """Why ``builtin_interfaces/Time`` fields cannot be a ROS time (None: they can)."""
    try:
        seconds, nanoseconds = int(sec), int(nanosec)
    except (TypeError, ValueError, OverflowError):
        return f"{what} ({sec!r}, {nanosec!r}) is not a pair of integers"
    if not 0 <= nanoseconds < NANOSECONDS_PER_SECOND:
        return f"{what}.nanosec = {nanoseconds} is not in [0, 1e9)"
    if not -(2**31) <= seconds < 2**31:
        return f"{what}.sec = {seconds} is outside int32"
    return None


def pose_problem(position: Any, quaternion: Any, what: str = "pose") -> str | None:
    """Why a position (x, y, z, metres) and an orientation quaternion (x, y, z, w) are not a usable pose."""
    point, problem = _floats(position, f"{what} position", 3)
    if point is None:
        return problem
    rotation, problem = _floats(quaternion, f"{what} orientation", 4)
    if rotation is None:
        return problem
    problem = (_first_non_finite(point, f"{what} position", ("x", "y", "z"))
               or _first_non_finite(rotation, f"{what} orientation", ("x", "y", "z", "w")))
    if problem is not None:
        return problem
    far = np.flatnonzero(np.abs(point) > MAX_POSITION_M)
    if far.size:
        axis = int(far[0])
        return (f"{what} position {'xyz'[axis]} = {point[axis]:g} m is beyond {MAX_POSITION_M:g} m "
                "(no Earth-bound frame reaches it)")
    with np.errstate(over="ignore"):
        norm = float(np.linalg.norm(rotation))
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        kind = " (a zero quaternion: no orientation)" if norm == 0.0 else ""
        return (f"{what} orientation {rotation.tolist()} has norm {norm:.6g}{kind}, not 1 within "
                f"{QUATERNION_NORM_TOLERANCE:g}")
    return None


def covariance_problem(covariance: Any, size: int = 6, what: str = "covariance") -> str | None:
    """Why ``covariance`` (``size`` x ``size``, row-major or 2-D) is not a usable covariance matrix."""
    values, problem = _floats(covariance, what, size * size)
    if values is None:
        return problem
    problem = _first_non_finite(values, what)
    if problem is not None:
        return problem
    matrix = values.reshape(size, size)
    largest = float(np.abs(matrix).max())
    if largest > MAX_VARIANCE:
        row, column = np.unravel_index(int(np.abs(matrix).argmax()), matrix.shape)
        return (f"{what} [{row}, {column}] = {matrix[row, column]:g} is beyond {MAX_VARIANCE:g} "
                "(a standard deviation of 1e6: no information)")
    tolerance = COVARIANCE_RELATIVE_TOLERANCE * largest
    asymmetry = np.abs(matrix - matrix.T)
    if asymmetry.max() > tolerance:
        row, column = np.unravel_index(int(asymmetry.argmax()), matrix.shape)
        return (f"{what} is not symmetric: [{row}, {column}] = {matrix[row, column]:g} but "
                f"[{column}, {row}] = {matrix[column, row]:g}")
    try:
        smallest = float(np.linalg.eigvalsh((matrix + matrix.T) / 2)[0])
    except np.linalg.LinAlgError as exc:
        return f"{what}: its eigenvalues cannot be computed ({exc})"
    if not smallest >= -tolerance:
        return f"{what} is not positive semi-definite: eigenvalue {smallest:g} (largest entry {largest:g})"
    return None


def psd_part(covariance: np.ndarray) -> np.ndarray:
    """A covariance ``covariance_problem`` accepted, made exactly symmetric and its round-off's negative
    eigenvalues set to 0: a floor added to it then gives a positive-definite matrix."""
    matrix = np.asarray(covariance, dtype=np.float64)
    symmetric: np.ndarray = (matrix + matrix.T) / 2
    eigenvalues, eigenvectors = np.linalg.eigh(symmetric)
    if eigenvalues[0] >= 0:
        return symmetric
    clipped: np.ndarray = (eigenvectors * np.maximum(eigenvalues, 0.0)) @ eigenvectors.T
    result: np.ndarray = (clipped + clipped.T) / 2
    return result
