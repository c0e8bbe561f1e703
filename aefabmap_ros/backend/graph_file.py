"""The pose graph saved with the map: a versioned .npz (numpy arrays only, no pickle), written atomically.

What it holds, and why each part is needed to go on where the last run stopped:

* the session table: robot, session number, the session its graph is rooted at (joined ones: the anchor's);
* each session's keyframes: stamp, key, odometry pose, distance travelled and optimised pose;
* each session's odometry samples (stamp, pose, distance travelled): a closure from a later session may match
  any stamp of an earlier one, and its keyframe is made there by interpolation. At most ``max_odometry`` per
  session are kept, as the live buffer keeps them: a full buffer halves its sample rate (every second sample
  dropped, the first and the newest kept), so a long run stays covered end to end, more coarsely;
* every factor as the graph recorded it (``FactorRecord``): priors, odometry between-factors and loop factors
  with their measured pose, covariance (gtsam order) and Cauchy scale -- so a reload rebuilds the same graph
  even if the drift parameters changed since;
* the counts, the factorization (QR once Cholesky failed on this graph) and the anchor.

Not saved: the closures waiting for odometry (the next run's odometry restarts), the decided closures a
viewer draws, and per robot its current session and the odometry before one was named (backend/robot_feeds.py):
after a restart each robot's next posterior or closure names its session again. Sessions are saved whatever
their robot, so a base station's graph of several robots reloads as one of a single robot does. A reload
rebuilds iSAM2 from the saved factors at the saved estimate. A file that cannot be read, of another version,
or inconsistent (a factor naming a key no keyframe has, stamps out of order, a rotation that is not one) is
refused with one ModelError naming it.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import gtsam
import numpy as np

from aefabmap_ros.backend.factors import FactorKind, FactorRecord
from aefabmap_ros.backend.graph_types import Keyframe, PoseGraphConfig, SessionId
from aefabmap_ros.backend.pose_graph import PoseGraph
from aefabmap_ros.backend.sessions import Session, odometry_buffer
from aefabmap_ros.errors import ModelError
from aefabmap_ros.io.npz_files import read_versioned_npz, write_npz_atomically

GRAPH_FORMAT_VERSION = 1
WHAT = "graph file"
REQUIRED = (
    "session_robot", "session_number", "session_root", "anchor", "factorization", "count_names", "count_values",
    "keyframe_session", "keyframe_stamp_ns", "keyframe_key", "keyframe_odometry", "keyframe_path_m", "keyframe_pose",
    "odometry_session", "odometry_stamp_ns", "odometry_pose", "odometry_path_m",
    "factor_kind", "factor_keys", "factor_pose", "factor_covariance", "factor_cauchy_scale",
)


def graph_arrays(graph: PoseGraph) -> dict[str, np.ndarray]:
    """Everything ``load_graph`` needs, as arrays (module docstring)."""
    sessions = list(graph.sessions.values())
    index_of = {session.id: index for index, session in enumerate(sessions)}
    keyframes = [keyframe for session in sessions for keyframe in session.keyframes]
    odometry: list[tuple[int, int, gtsam.Pose3, float]] = []
    for index, session in enumerate(sessions):
        odometry += [(index, *sample) for sample in zip(*session.odometry.samples(), strict=True)]
    records = [graph.factors[index] for index in sorted(graph.factors)]
    counts = sorted(graph.counts.items())
    return {
        "format_version": np.array(GRAPH_FORMAT_VERSION),
        "session_robot": np.array([session.id[0] for session in sessions], dtype=str),
        "session_number": np.array([session.id[1] for session in sessions], dtype=np.int64),
        "session_root": np.array([index_of[session.root] for session in sessions], dtype=np.int64),
        "anchor": np.array(-1 if graph.anchor is None else index_of[graph.anchor], dtype=np.int64),
        "factorization": np.array(graph.factorization),
        "count_names": np.array([name for name, _ in counts], dtype=str),
        "count_values": np.array([value for _, value in counts], dtype=np.int64),
        "keyframe_session": np.array([index_of[keyframe.session] for keyframe in keyframes], dtype=np.int64),
        "keyframe_stamp_ns": np.array([keyframe.stamp_ns for keyframe in keyframes], dtype=np.int64),
        "keyframe_key": np.array([keyframe.key for keyframe in keyframes], dtype=np.int64),
        "keyframe_odometry": _matrices([keyframe.odometry for keyframe in keyframes], 4),
        "keyframe_path_m": np.array([keyframe.path_m for keyframe in keyframes], dtype=np.float64),
        "keyframe_pose": _matrices([graph.estimate_of(keyframe.key) for keyframe in keyframes], 4),
        "odometry_session": np.array([sample[0] for sample in odometry], dtype=np.int64),
        "odometry_stamp_ns": np.array([sample[1] for sample in odometry], dtype=np.int64),
        "odometry_pose": _matrices([sample[2] for sample in odometry], 3),  # the last row is always 0 0 0 1
        "odometry_path_m": np.array([sample[3] for sample in odometry], dtype=np.float64),
        "factor_kind": np.array([record.kind.value for record in records], dtype=np.int64),
        "factor_keys": np.array([(record.first, record.second) for record in records], dtype=np.int64).reshape(-1, 2),
        "factor_pose": _matrices([record.pose for record in records], 4),
        "factor_covariance": np.array([record.covariance for record in records], dtype=np.float64).reshape(-1, 6, 6),
        "factor_cauchy_scale": np.array([record.cauchy_scale for record in records], dtype=np.float64),
    }


def save_graph(graph: PoseGraph, path: Path) -> None:
    """The graph to ``path`` atomically (a temporary file, then os.replace): readers never see half a file."""
    write_npz_atomically(path, graph_arrays(graph))


def load_graph(path: Path, config: PoseGraphConfig, robot: str = "") -> PoseGraph:
    """A graph saved by ``save_graph``, its iSAM2 rebuilt; ModelError naming the file when it cannot be used."""
    try:
        arrays = read_versioned_npz(path, WHAT, "pose graph", REQUIRED, GRAPH_FORMAT_VERSION)
    except ModelError:
        raise
    except Exception as error:  # any other failure of a damaged archive is the same refusal
        raise ModelError(f"cannot read {WHAT} {path}: {type(error).__name__}: {error}") from error
    try:
        return graph_from_arrays(arrays, config, robot)
    except (ValueError, IndexError, KeyError, TypeError, RuntimeError) as error:  # RuntimeError: gtsam's
        raise ModelError(f"{WHAT} {path} is broken: {error}") from error


def graph_from_arrays(arrays: dict[str, np.ndarray], config: PoseGraphConfig, robot: str = "") -> PoseGraph:
    """The graph ``graph_arrays`` gave; ValueError (or gtsam's RuntimeError) naming what is inconsistent."""
    sessions, anchor = _sessions(arrays, config.max_odometry)
    estimate = _keyframes(arrays, sessions)
    _odometry(arrays, sessions)
    records = _records(arrays, {keyframe.key for session in sessions for keyframe in session.keyframes})
    factorization = str(_shaped(arrays, "factorization", ()))
    if factorization not in ("CHOLESKY", "QR"):
        raise ValueError(f"factorization {factorization!r} is neither CHOLESKY nor QR")
    names = [str(name) for name in _shaped(arrays, "count_names", (-1,))]
    values = _shaped(arrays, "count_values", (len(names),)).astype(np.int64)

    graph = PoseGraph(config, robot)
    graph.load(sessions, anchor, records, estimate, factorization)
    graph.counts = Counter({name: int(value) for name, value in zip(names, values, strict=True)})
    return graph


def _sessions(arrays: dict[str, np.ndarray], max_odometry: int) -> tuple[list[Session], SessionId | None]:
    """The session table, each session's keyframes and odometry still empty, and the anchor."""
    robots = [str(name) for name in _shaped(arrays, "session_robot", (-1,))]
    numbers = _shaped(arrays, "session_number", (len(robots),)).astype(np.int64)
    roots = _indices(arrays, "session_root", (len(robots),), len(robots))
    ids: list[SessionId] = [(name, int(number)) for name, number in zip(robots, numbers, strict=True)]
    if len(set(ids)) != len(ids):
        raise ValueError("a session is listed twice")
    anchor_index = int(_shaped(arrays, "anchor", ()))
    if not -1 <= anchor_index < len(ids):
        raise ValueError(f"anchor {anchor_index} is not a session")
    sessions = [Session(session_id, odometry_buffer(max_odometry), root=ids[int(root)])
                for session_id, root in zip(ids, roots, strict=True)]
    return sessions, None if anchor_index < 0 else ids[anchor_index]


def _keyframes(arrays: dict[str, np.ndarray], sessions: list[Session]) -> gtsam.Values:
    """Each session's keyframes, put into it in stamp order; their optimised poses by key."""
    count = len(_shaped(arrays, "keyframe_key", (-1,)))
    keyframe_session = _indices(arrays, "keyframe_session", (count,), len(sessions))
    stamps = _shaped(arrays, "keyframe_stamp_ns", (count,)).astype(np.int64)
    keys = _shaped(arrays, "keyframe_key", (count,)).astype(np.int64)
    odometry = _poses(arrays, "keyframe_odometry", count, 4)
    paths = _finite(arrays, "keyframe_path_m", (count,))
    poses = _poses(arrays, "keyframe_pose", count, 4)
    if len(set(keys.tolist())) != count or (count and keys.min() < 0):
        raise ValueError("keyframe keys are not distinct non-negative numbers")
    estimate = gtsam.Values()
    for index in range(count):
        session = sessions[int(keyframe_session[index])]
        if session.keyframes and session.keyframes[-1].stamp_ns >= stamps[index]:
            raise ValueError(f"keyframes of session {session.id} are not in stamp order")
        session.keyframes.append(Keyframe(int(stamps[index]), int(keys[index]), odometry[index], float(paths[index]),
                                          session.id))
        estimate.insert(int(keys[index]), poses[index])
    return estimate


def _odometry(arrays: dict[str, np.ndarray], sessions: list[Session]) -> None:
    """Each session's odometry samples, restored into its buffer."""
    samples = len(_shaped(arrays, "odometry_stamp_ns", (-1,)))
    sample_session = _indices(arrays, "odometry_session", (samples,), len(sessions))
    sample_stamps = _shaped(arrays, "odometry_stamp_ns", (samples,)).astype(np.int64)
    sample_poses = _poses(arrays, "odometry_pose", samples, 3)
    sample_paths = _finite(arrays, "odometry_path_m", (samples,))
    for index, session in enumerate(sessions):
        rows = np.flatnonzero(sample_session == index)
        session.odometry.restore([int(sample_stamps[row]) for row in rows], [sample_poses[row] for row in rows],
                                 [float(sample_paths[row]) for row in rows])


def _records(arrays: dict[str, np.ndarray], known: set[int]) -> list[FactorRecord]:
    """The factors, each checked to name keyframes in ``known`` and to have a usable covariance and scale."""
    factors = len(_shaped(arrays, "factor_kind", (-1,)))
    kinds = _shaped(arrays, "factor_kind", (factors,)).astype(np.int64)
    factor_keys = _shaped(arrays, "factor_keys", (factors, 2)).astype(np.int64)
    factor_poses = _poses(arrays, "factor_pose", factors, 4)
    covariances = _finite(arrays, "factor_covariance", (factors, 6, 6))
    scales = _shaped(arrays, "factor_cauchy_scale", (factors,)).astype(np.float64)
    records = []
    for index in range(factors):
        kind = FactorKind(int(kinds[index]))  # ValueError for a kind that is none
        first, second = (int(key) for key in factor_keys[index])
        if first not in known or second not in known:
            raise ValueError(f"factor {index} names keyframe key {first if first not in known else second}, "
                             "which no keyframe has")
        if not np.allclose(covariances[index], covariances[index].T) or np.linalg.eigvalsh(covariances[index])[0] <= 0:
            raise ValueError(f"factor {index}'s covariance is not symmetric positive definite")
        if kind is FactorKind.LOOP and not scales[index] > 0:
            raise ValueError(f"loop factor {index}'s Cauchy scale {scales[index]} is not > 0")
        records.append(FactorRecord(kind, first, second, factor_poses[index], covariances[index], float(scales[index])))
    return records


def _matrices(poses: list[gtsam.Pose3], rows: int) -> np.ndarray:
    return np.array([pose.matrix()[:rows] for pose in poses], dtype=np.float64).reshape(-1, rows, 4)


def _shaped(arrays: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray:
    """The array, checked for its shape (-1: any length) and for a kind of value it may hold (no objects)."""
    array = arrays[name]
    if array.dtype.kind not in "biufU":
        raise ValueError(f"{name} holds {array.dtype} values")
    if array.ndim != len(shape) or any(want not in (-1, got) for want, got in zip(shape, array.shape, strict=True)):
        raise ValueError(f"{name} has shape {array.shape}, expected {shape}")
    return array


def _finite(arrays: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray:
    array = _shaped(arrays, name, shape).astype(np.float64)
    if not np.isfinite(array).all():
        raise ValueError(f"{name} holds values that are not finite")
    return array


def _indices(arrays: dict[str, np.ndarray], name: str, shape: tuple[int, ...], size: int) -> np.ndarray:
    array = _shaped(arrays, name, shape).astype(np.int64)
    if array.size and not (array.min() >= 0 and array.max() < size):
        raise ValueError(f"{name} names a session that is not in the session table")
    return array


def _poses(arrays: dict[str, np.ndarray], name: str, count: int, rows: int) -> list[gtsam.Pose3]:
    """Poses from (count, rows, 4) matrices (rows 3: the last row left out); rotations checked to be ones."""
    matrices = _finite(arrays, name, (count, rows, 4))
    rotations = matrices[:, :3, :3]
    orthonormal = np.abs(np.einsum("nji,njk->nik", rotations, rotations) - np.eye(3)).max(axis=(1, 2)) <= 1e-6
    bad = np.flatnonzero(~orthonormal | (np.linalg.det(rotations) <= 0) if count else np.zeros(0, bool))
    if bad.size:
        raise ValueError(f"{name}[{int(bad[0])}] is not a rotation and translation")
    if rows == 4 and count and not np.array_equal(matrices[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (count, 1))):
        raise ValueError(f"{name} has a last row that is not 0 0 0 1")
    return [gtsam.Pose3(gtsam.Rot3(matrix[:3, :3]), matrix[:3, 3]) for matrix in matrices]
