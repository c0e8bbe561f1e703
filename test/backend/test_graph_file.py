"""The pose graph saved and reloaded: the same sessions, keyframes, odometry and estimate, and a graph that goes
on optimising; broken files refused with one error naming them."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.graph_file import graph_arrays, load_graph, save_graph
from aefabmap_ros.backend.odometry import OdometryBuffer
from aefabmap_ros.backend.pose_graph import Closure, ClosureResult, PoseGraph, PoseGraphConfig
from aefabmap_ros.errors import ModelError
from aefabmap_ros.io.npz_files import write_npz_atomically
from test.backend.test_pose_graph import square_truth, stamp
from test.backend.test_sessions import (
    COVARIANCE,
    A,
    B,
    a_graph,
    assert_b_on_its_truth,
    b_odometry,
    b_stamp,
    b_to_a,
    b_truth,
    feed_b,
)


def two_sessions() -> PoseGraph:
    """A with a loop of its own; B with a loop of its own, then joined to A."""
    graph = a_graph()
    end = len(b_odometry()) - 1
    graph.add_closure(Closure(b_stamp(end), b_stamp(0), b_truth()[end].between(b_truth()[0]), COVARIANCE,
                              query_session=B, place_session=B))
    feed_b(graph)
    assert graph.add_closure(b_to_a(10, 31)) is ClosureResult.ADDED
    return graph


def test_a_saved_graph_reloads_the_same_and_goes_on(tmp_path: Path) -> None:
    graph = two_sessions()
    path = tmp_path / "office.graph.npz"
    save_graph(graph, path)
    loaded = load_graph(path, PoseGraphConfig())
    assert list(loaded.sessions) == [A, B] and loaded.anchor == A and loaded.current is None
    assert loaded.is_joined(*A) and loaded.is_joined(*B)
    for session_id, session in graph.sessions.items():
        again = loaded.sessions[session_id]
        assert [(k.stamp_ns, k.key, k.path_m) for k in again.keyframes] == \
            [(k.stamp_ns, k.key, k.path_m) for k in session.keyframes]
        for original, reloaded in zip(session.keyframes, again.keyframes, strict=True):
            assert reloaded.odometry.equals(original.odometry, 1e-12)
        stamps, poses, paths = session.odometry.samples()
        stamps_again, poses_again, paths_again = again.odometry.samples()
        assert stamps_again == stamps and np.allclose(paths_again, paths, atol=1e-12)
        assert all(p.equals(q, 1e-12) for p, q in zip(poses, poses_again, strict=True))
        assert loaded.map_to_odom(*session_id).equals(graph.map_to_odom(*session_id), 1e-6)
    for (stamp_ns, pose), (stamp_again, pose_again) in zip(graph.trajectory(), loaded.trajectory(), strict=True):
        assert stamp_again == stamp_ns and pose_again.equals(pose, 1e-6)
    def records(of: PoseGraph) -> list[tuple[int, int, int, np.ndarray, np.ndarray, float]]:
        return sorted(((r.kind.value, r.first, r.second, r.pose.matrix(), r.covariance, r.cauchy_scale)
                       for r in of.factors.values()), key=lambda record: record[:3])

    for record, record_again in zip(records(graph), records(loaded), strict=True):
        assert record[:3] == record_again[:3]
        assert np.allclose(record[3], record_again[3], atol=1e-12)
        assert np.allclose(record[4], record_again[4], rtol=1e-12)
        assert record[5] == pytest.approx(record_again[5], nan_ok=True)
    assert loaded.counts == graph.counts
    assert loaded.factorization == graph.factorization

    # It goes on: B's next closure (gated against the reloaded graph) and a third session joining through a
    # stamp of A that never was a keyframe (its odometry came back from the file).
    assert loaded.add_closure(b_to_a(30, 51)) is ClosureResult.ADDED
    assert_b_on_its_truth(loaded, 1e-3)
    third = ("", 2)
    loaded.start_session(third)
    truth = square_truth()
    for index in range(5):
        loaded.add_odometry(b_stamp(200 + index), truth[45].between(truth[45 + index]))  # from A's frame 45 on
    closure = Closure(b_stamp(202), stamp(45), truth[47].between(truth[45]), COVARIANCE,
                      query_session=third, place_session=A)
    assert loaded.add_closure(closure) is ClosureResult.ADDED
    assert loaded.is_joined(*third)
    assert loaded.map_to_odom(*third).equals(truth[45], 1e-4)


def test_a_graph_without_sessions_saves_and_reloads(tmp_path: Path) -> None:
    path = tmp_path / "empty.graph.npz"
    save_graph(PoseGraph(PoseGraphConfig()), path)
    loaded = load_graph(path, PoseGraphConfig())
    assert loaded.sessions == {} and loaded.trajectory() == []


def test_a_full_session_buffer_is_decimated_not_cut() -> None:
    """Past max_samples a decimating buffer halves its rate: it still spans the whole run, with each kept sample's
    distance travelled, so a closure into the start of an old session still finds its odometry."""
    buffer = OdometryBuffer(max_samples=10, decimate=True)
    for index in range(25):
        buffer.add(stamp(index), gtsam.Pose3(gtsam.Rot3(), np.array([float(index), 0.0, 0.0])))
    stamps, _, paths = buffer.samples()
    assert len(stamps) <= 10 and stamps[0] == stamp(0) and stamps[-1] == stamp(24)
    assert np.allclose(paths, [(stamp_ns // 1_000_000_000) - 1.0 for stamp_ns in stamps])
    found = buffer.pose_at(stamp(3))
    assert found is not None and found[1] == pytest.approx(3.0)
    cut = OdometryBuffer(max_samples=10)
    for index in range(25):
        cut.add(stamp(index), gtsam.Pose3())
    assert cut.first_ns == stamp(15)  # the gate's buffer forgets the oldest


def _broken(kind: str, good: Path, tmp_path: Path) -> Path:
    path = tmp_path / f"{kind}.graph.npz"
    content = good.read_bytes()
    if kind == "truncated":
        path.write_bytes(content[: len(content) // 2])
    elif kind == "garbage":
        path.write_bytes(b"this is no graph" * 100)
    elif kind == "empty":
        path.write_bytes(b"")
    else:
        arrays = dict(np.load(good, allow_pickle=False))
        if kind == "version":
            arrays["format_version"] = np.array(99)
        elif kind == "missing_key":
            arrays["factor_keys"] = arrays["factor_keys"] + 1000
        elif kind == "not_a_rotation":
            arrays["keyframe_pose"][1, :3, :3] *= 2.0
        elif kind == "nan_odometry":
            arrays["odometry_pose"][3, 0, 3] = np.nan
        elif kind == "missing_array":
            del arrays["odometry_path_m"]
        write_npz_atomically(path, arrays)
    return path


@pytest.mark.parametrize("kind", ["truncated", "garbage", "empty", "version", "missing_key", "not_a_rotation",
                                  "nan_odometry", "missing_array"])
def test_a_broken_graph_file_is_refused_naming_it(kind: str, tmp_path: Path) -> None:
    good = tmp_path / "good.graph.npz"
    save_graph(two_sessions(), good)
    path = _broken(kind, good, tmp_path)
    content = path.read_bytes()
    with pytest.raises(ModelError, match=str(path)):
        load_graph(path, PoseGraphConfig())
    assert path.read_bytes() == content


def test_the_arrays_hold_no_objects() -> None:
    """Numbers and strings only: np.load(allow_pickle=False) reads every one."""
    arrays = graph_arrays(two_sessions())
    assert all(array.dtype.kind in "biufU" for array in arrays.values())
