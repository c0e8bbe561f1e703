"""The example backend on a hand-made square loop with drifting odometry."""

from __future__ import annotations

import itertools
from typing import Any

import gtsam
import numpy as np
import pytest

from aefabmap_ros.backend.odometry import interpolate
from aefabmap_ros.backend.pose_graph import (
    Closure,
    ClosureResult,
    PoseGraph,
    PoseGraphConfig,
    trajectory_arrays,
)
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.evaluation.trajectory_error import tum_text

SECOND = 1_000_000_000
STEP_M = 0.5
SIDE_STEPS = 20  # a 10 m square


def square_truth() -> list[gtsam.Pose3]:
    """Ground truth: 4 sides of 10 m, turning left 90 degrees at each corner, back at the start."""
    poses, pose = [], gtsam.Pose3()
    for _side in range(4):
        for _ in range(SIDE_STEPS):
            poses.append(pose)
            pose = pose.compose(gtsam.Pose3(gtsam.Rot3(), np.array([STEP_M, 0.0, 0.0])))
        pose = pose.compose(gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.zeros(3)))
    poses.append(pose)
    return poses


def drifting_odometry(truth: list[gtsam.Pose3]) -> list[gtsam.Pose3]:
    """Each step's motion 2 % too long and turned 0.15 degrees further left: the loop does not close."""
    odometry = [truth[0]]
    for before, after in itertools.pairwise(truth):
        step = before.between(after)
        drifted = gtsam.Pose3(step.rotation().compose(gtsam.Rot3.Yaw(np.radians(0.15))), 1.02 * step.translation())
        odometry.append(odometry[-1].compose(drifted))
    return odometry


def stamp(index: int) -> int:
    return (index + 1) * SECOND


def closure(truth: list[gtsam.Pose3], query: int, place: int, wrong_place: int | None = None) -> Closure:
    """The true T_query_place of two frames (with wrong_place: the pose of that other place instead)."""
    relative = truth[query].between(truth[place if wrong_place is None else wrong_place])
    return Closure(stamp(query), stamp(place), relative, np.diag([0.02**2] * 3 + [0.005**2] * 3))


def graph_with_odometry(odometry: list[gtsam.Pose3]) -> PoseGraph:
    graph = PoseGraph(PoseGraphConfig())
    for index, pose in enumerate(odometry):
        graph.add_odometry(stamp(index), pose)
    return graph


def position_error(graph: PoseGraph, truth: list[gtsam.Pose3], index: int) -> float:
    poses = dict(graph.trajectory())
    return float(np.linalg.norm(poses[stamp(index)].translation() - truth[index].translation()))


def test_a_closure_pulls_the_end_of_the_loop_back() -> None:
    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    odometry_error = float(np.linalg.norm(odometry[end].translation() - truth[end].translation()))
    assert odometry_error > 1.0  # the drift this test corrects
    graph = graph_with_odometry(odometry)
    assert graph.add_closure(closure(truth, end, 0)) is ClosureResult.ADDED
    assert position_error(graph, truth, end) < 0.1 * odometry_error
    # A second closure at a corner inserts keyframes between the first two (splitting their odometry factor).
    assert graph.add_closure(closure(truth, 2 * SIDE_STEPS, SIDE_STEPS)) is ClosureResult.ADDED
    assert [stamp_ns for stamp_ns, _ in graph.trajectory()] == [stamp(0), stamp(SIDE_STEPS), stamp(2 * SIDE_STEPS),
                                                               stamp(end)]
    assert position_error(graph, truth, end) < 0.1 * odometry_error
    # map -> odom moves the drifted odometry of the newest keyframe onto its optimised pose.
    newest_stamp, newest = graph.trajectory()[-1]
    assert newest_stamp == stamp(end)
    corrected = graph.map_to_odom().compose(odometry[end])
    np.testing.assert_allclose(corrected.translation(), newest.translation(), atol=1e-6)


def test_a_wrong_closure_far_from_odometry_is_refused() -> None:
    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    graph = graph_with_odometry(odometry)
    graph.add_closure(closure(truth, end, 0))
    right = position_error(graph, truth, end)
    # The end claims to see the far corner as if it were at its start: 14 m off, drift explains < 2 m.
    wrong = closure(truth, end - 1, 2 * SIDE_STEPS, wrong_place=0)
    assert graph.add_closure(wrong) is ClosureResult.INCONSISTENT
    assert graph.counts["inconsistent_with_odometry"] == 1
    assert position_error(graph, truth, end) == pytest.approx(right)


def end_error_after_wrong_then_true_closures(config: PoseGraphConfig) -> float:
    """A closure 2 m wrong (within what 80 m of drift explains, so accepted), then five true ones that contradict it."""
    truth = square_truth()
    end = len(truth) - 1
    graph = PoseGraph(config)
    for index, pose in enumerate(drifting_odometry(truth)):
        graph.add_odometry(stamp(index), pose)
    start_shifted = [truth[0].compose(gtsam.Pose3(gtsam.Rot3(), np.array([2.0, 0.0, 0.0]))), *truth[1:]]
    assert graph.add_closure(closure(start_shifted, end, 0)) is ClosureResult.ADDED
    for step in range(1, 6):
        assert graph.add_closure(closure(truth, end - step, step)) is ClosureResult.ADDED
    return position_error(graph, truth, end)


def test_a_wrong_closure_within_drift_is_down_weighted() -> None:
    robust = end_error_after_wrong_then_true_closures(PoseGraphConfig())
    plain = end_error_after_wrong_then_true_closures(PoseGraphConfig(cauchy_scale=1e6))  # ~ no kernel
    assert robust < 0.15
    assert plain > 2 * robust  # what the kernel saves: the wrong closure keeps pulling a Gaussian graph


def test_bad_input_is_counted_and_dropped() -> None:
    truth = square_truth()
    graph = graph_with_odometry(drifting_odometry(truth))
    graph.add_odometry(stamp(3), gtsam.Pose3())  # out of order
    assert graph.counts["odometry_out_of_order"] == 1
    unknown = Closure(stamp(10), 0, gtsam.Pose3(), np.eye(6))  # a place before the first odometry
    assert graph.add_closure(unknown) is ClosureResult.UNKNOWN_STAMP
    bad = Closure(stamp(10), stamp(0), gtsam.Pose3(), np.full((6, 6), np.nan))
    assert graph.add_closure(bad) is ClosureResult.BAD_COVARIANCE
    assert graph.counts["unknown_stamp"] == 1 and graph.counts["bad_covariance"] == 1
    assert graph.trajectory() == []


def test_a_closure_waits_for_odometry_to_reach_its_query() -> None:
    truth = square_truth()
    odometry = drifting_odometry(truth)
    graph = PoseGraph(PoseGraphConfig())
    for index in range(30):
        graph.add_odometry(stamp(index), odometry[index])
    assert graph.add_closure(closure(truth, 40, 0)) is ClosureResult.WAITING
    results = []
    for index in range(30, 41):
        results += graph.add_odometry(stamp(index), odometry[index])
    assert results == [ClosureResult.ADDED]
    assert len(graph.trajectory()) == 2  # the anchor at the first odometry is also the place


def test_tum_lines() -> None:
    trajectory = [(1_500_000_000, gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 2.0, 3.0])))]
    (line,) = tum_text(*trajectory_arrays(trajectory)).splitlines()
    assert line.split() == ["1.500000000", "1.000000", "2.000000", "3.000000",
                            "0.000000000", "0.000000000", "0.000000000", "1.000000000"]


def test_config_is_checked() -> None:
    with pytest.raises(ConfigError):
        PoseGraphConfig(cauchy_scale=0.0)


def test_a_closure_before_any_odometry_waits_for_it() -> None:
    """A node may take a closure off its queue before the odometry that came first: it waits, not dropped."""
    truth = square_truth()
    odometry = drifting_odometry(truth)
    graph = PoseGraph(PoseGraphConfig())
    assert graph.add_closure(closure(truth, 40, 0)) is ClosureResult.WAITING
    results = []
    for index in range(41):
        results += graph.add_odometry(stamp(index), odometry[index])
    assert results == [ClosureResult.ADDED]


def test_a_graph_cholesky_cannot_factor_is_solved_by_qr() -> None:
    """A keyframe 30 km from the anchor along a straight road, tied by a loop factor of 5 cm: the normal
    equations look singular to Cholesky (gtsam's indeterminate system). The closure is added by QR on the
    graph rebuilt without it, and later closures use QR too."""
    graph = PoseGraph(PoseGraphConfig())
    poses = [gtsam.Pose3(gtsam.Rot3(), np.array([x, 0.0, 0.0])) for x in (0.0, 1000.0, 2000.0, 30_000.0)]
    for index, pose in enumerate(poses):
        graph.add_odometry(index * SECOND, pose)
    covariance = np.diag([0.02**2] * 3 + [0.005**2] * 3)
    assert graph.add_closure(Closure(2 * SECOND, SECOND, poses[2].between(poses[1]), covariance)) \
        is ClosureResult.ADDED
    assert graph.factorization == "CHOLESKY"  # 2 km: still fine
    assert graph.add_closure(Closure(3 * SECOND, 0, poses[3].between(poses[0]), covariance)) is ClosureResult.ADDED
    assert graph.factorization == "QR" and "Indeterminate" in graph.solver_error
    estimated = dict(graph.trajectory())
    assert sorted(estimated) == [0, SECOND, 2 * SECOND, 3 * SECOND]
    for index, pose in enumerate(poses):
        assert np.linalg.norm(estimated[index * SECOND].translation() - pose.translation()) < 1e-3
    assert graph.add_closure(Closure(3 * SECOND, 2 * SECOND, poses[3].between(poses[2]), covariance)) \
        is ClosureResult.ADDED


def test_a_closure_the_solver_refuses_leaves_the_graph_as_it_was(monkeypatch: pytest.MonkeyPatch) -> None:
    truth = square_truth()
    graph = graph_with_odometry(drifting_odometry(truth))
    assert graph.add_closure(closure(truth, 40, 0)) is ClosureResult.ADDED
    before = [(stamp_ns, pose.translation().tolist()) for stamp_ns, pose in graph.trajectory()]
    real_update = PoseGraph._update
    calls = []

    def failing_update(self: PoseGraph, *args: Any) -> None:
        calls.append(self.factorization)
        real_update(self, *args)  # the factors go into iSAM2, as when gtsam fails half way through
        raise RuntimeError("Indeterminate linear system detected while working near variable 3")

    monkeypatch.setattr(PoseGraph, "_update", failing_update)
    assert graph.add_closure(closure(truth, 60, 20)) is ClosureResult.SOLVER_FAILED
    assert calls == ["CHOLESKY", "QR"] and graph.counts["solver_failed"] == 1
    after = [(stamp_ns, pose.translation().tolist()) for stamp_ns, pose in graph.trajectory()]
    assert [s for s, _ in after] == [s for s, _ in before]  # no keyframe of the refused closure left behind
    assert np.allclose([p for _, p in after], [p for _, p in before], atol=1e-6)
    monkeypatch.setattr(PoseGraph, "_update", real_update)
    assert graph.add_closure(closure(truth, 60, 20)) is ClosureResult.ADDED  # the rebuilt graph goes on
    assert len(graph.trajectory()) == len(before) + 2 and graph.add_closure(closure(truth, 70, 30)) \
        is ClosureResult.ADDED


def test_a_covariance_a_hair_off_positive_semi_definite_is_added() -> None:
    """A covariance computed in single precision: a rank-deficient one has eigenvalues of -1e-7 of its
    largest. Accepted (within round-off) and cut to positive semi-definite before the floor is added."""
    truth = square_truth()
    graph = graph_with_odometry(drifting_odometry(truth))
    direction = np.array([0.6, 0.8, 0.0])
    covariance = np.diag([0.02**2] * 3 + [0.005**2] * 3)
    covariance[:3, :3] += 1e6 * np.outer(direction, direction)
    rng = np.random.default_rng(0)
    basis = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    covariance += (basis * np.array([-1e-1, 0, 0, 0, 0, 0])) @ basis.T  # -1e-7 of the largest eigenvalue
    covariance = (covariance + covariance.T) / 2
    assert np.linalg.eigvalsh(covariance)[0] < 0
    end = len(truth) - 1
    result = graph.add_closure(Closure(stamp(end), stamp(0), truth[end].between(truth[0]), covariance))
    assert result is ClosureResult.ADDED
    assert all(np.isfinite(pose.matrix()).all() for _, pose in graph.trajectory())


def test_stamps_at_the_int32_limit_interpolate() -> None:
    """The last stamp a ROS time holds (sec 2**31 - 1, nanosec 999999999): odometry around it interpolates,
    a closure to it is added, and a sample out of order there is refused."""
    last_ns = (2**31 - 1) * SECOND + 999_999_999
    truth = square_truth()
    odometry = drifting_odometry(truth)
    start = last_ns - (len(truth) - 1) * SECOND
    graph = PoseGraph(PoseGraphConfig())
    for index, pose in enumerate(odometry):
        graph.add_odometry(start + index * SECOND, pose)
    graph.add_odometry(last_ns, odometry[-1])  # the same stamp again
    assert graph.odometry.last_ns == last_ns and graph.counts["odometry_out_of_order"] == 1
    middle = graph.odometry.pose_at(last_ns - SECOND // 2)
    assert middle is not None
    assert middle[0].equals(interpolate(odometry[-2], odometry[-1], 0.5), 1e-9)
    end = len(truth) - 1
    relative = truth[end].between(truth[0])
    assert graph.add_closure(Closure(last_ns, start, relative, np.diag([0.02**2] * 3 + [0.005**2] * 3))) \
        is ClosureResult.ADDED
    stamps_s, _ = trajectory_arrays(graph.trajectory())
    assert stamps_s[-1] == pytest.approx(last_ns / 1e9)
    assert graph.odometry.pose_at(last_ns + 1) is None
