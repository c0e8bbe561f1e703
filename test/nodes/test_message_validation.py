"""Odometry and LoopClosure messages with any floats: the check answers every one with a verdict, and every
one it accepts goes through the pose graph and the odometry gate without an exception."""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

msg = pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402

from aefabmap_ros.backend.odometry import closure_in_base_frame  # noqa: E402
from aefabmap_ros.backend.odometry_gate import OdometryGate  # noqa: E402
from aefabmap_ros.backend.pose_graph import Closure, ClosureResult, PoseGraph, PoseGraphConfig  # noqa: E402
from aefabmap_ros.nodes.gtsam_poses import loop_closure_pose, pose_to_gtsam  # noqa: E402
from aefabmap_ros.nodes.messages import (  # noqa: E402
    loop_closure_pose_problem,
    loop_closure_stamp_problem,
    odometry_problem,
    posterior_problem,
)
from aefabmap_ros.stamps import stamp_to_ns  # noqa: E402

pytestmark = pytest.mark.ros

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)
# Near what a robot sends, where the interesting boundaries are: metres to Earth scale (tens of km apart are
# what Cholesky cannot factor), beyond it, zero, tiny.
PLAUSIBLE = st.one_of(st.floats(-1e3, 1e3), st.floats(1e4, 1e8), st.floats(-1e9, 1e9),
                      st.sampled_from([0.0, -0.0, 1e-300, 1.0]))
FLOAT = st.one_of(ANY_FLOAT, PLAUSIBLE)


@st.composite
def quaternions(draw: st.DrawFn, wild: bool) -> list[float]:
    """Unit quaternions (perturbed within or beyond the tolerance), or (``wild``) four of any floats."""
    if wild and draw(st.booleans()):
        return [draw(FLOAT) for _ in range(4)]
    vector = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(4)])
    norm = float(np.linalg.norm(vector))
    unit = vector / norm if norm > 1e-6 else np.array([0.0, 0.0, 0.0, 1.0])
    return [float(value) for value in unit * draw(st.sampled_from([1.0, 1.0 + 5e-4, 1.0 - 5e-4, 1.01, 0.0]))]


@st.composite
def covariances(draw: st.DrawFn, wild: bool) -> list[float]:
    """(``wild``) 36 of any floats or a diagonal of any floats; else a diagonal of plausible variances or
    L L^T of plausible L (positive semi-definite, up to its round-off)."""
    kind = draw(st.sampled_from(["any", "diagonal"] if wild else ["variances", "factor"]))
    if kind == "any":
        return [draw(FLOAT) for _ in range(36)]
    if kind in ("diagonal", "variances"):
        values = FLOAT if kind == "diagonal" else st.one_of(st.floats(0.0, 1e12), st.sampled_from([0.0, 1e6]))
        return [float(v) for v in np.diag([draw(values) for _ in range(6)]).reshape(36)]
    factor = np.array([[draw(st.floats(-1e3, 1e3)) for _ in range(6)] for _ in range(6)])
    return [float(v) for v in (factor @ factor.T).reshape(36)]


def _stamp(sec: int, nanosec: int) -> Any:
    stamp = Time()
    stamp.sec, stamp.nanosec = sec, nanosec  # unchecked on assignment beyond the field types
    return stamp


def _pose(message_pose: Any, position: list[float], quaternion: list[float]) -> None:
    message_pose.position.x, message_pose.position.y, message_pose.position.z = position
    orientation = message_pose.orientation
    orientation.x, orientation.y, orientation.z, orientation.w = quaternion


@st.composite
def odometry_messages(draw: st.DrawFn, sec: int) -> Any:
    """Half of them wild (any floats, any nanosec), the others plausible: both sides of every boundary."""
    wild = draw(st.booleans())
    message = Odometry()
    nanosec = st.integers(0, 2**32 - 1) if wild else st.integers(0, 999_999_999)
    message.header.stamp = _stamp(sec, draw(nanosec))
    _pose(message.pose.pose, [draw(FLOAT if wild else PLAUSIBLE) for _ in range(3)], draw(quaternions(wild)))
    return message


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), first_sec=st.sampled_from([0, 1_700_000_000, 2**31 - 8, -(2**31)]),
       count=st.integers(1, 5))
def test_any_odometry_and_closure_get_a_verdict_and_the_accepted_go_through(data: st.DataObject, first_sec: int,
                                                                           count: int) -> None:
    graph = PoseGraph(PoseGraphConfig())
    gate = OdometryGate(PoseGraphConfig(), gtsam.Pose3())
    stamps, odometry = [], {}
    for index in range(count):
        message = data.draw(odometry_messages(first_sec + index))
        verdict = odometry_problem(message)
        assert verdict is None or (isinstance(verdict, str) and verdict)
        if verdict is None:
            stamp_ns, pose = stamp_to_ns(message.header.stamp), pose_to_gtsam(message.pose.pose)
            assert np.isfinite(pose.matrix()).all()
            graph.add_odometry(stamp_ns, pose)
            gate.add_odometry(stamp_ns, pose)
            stamps.append(message.header.stamp)
            odometry[stamp_ns] = pose
    closure = msg.LoopClosure(pose_available=True)
    endpoints = st.sampled_from(stamps) if stamps else st.just(_stamp(first_sec, 0))
    closure.header.stamp, closure.matched_stamp = data.draw(endpoints), data.draw(endpoints)
    query_ns, place_ns = stamp_to_ns(closure.header.stamp), stamp_to_ns(closure.matched_stamp)
    kind = data.draw(st.sampled_from(["wild", "plausible", "agrees with odometry"]))
    wild = kind == "wild"
    if kind == "agrees with odometry" and query_ns in odometry:  # the hardest for the solver: it is added
        relative = odometry[query_ns].between(odometry[place_ns])
        quaternion = Rotation.from_matrix(relative.rotation().matrix()).as_quat()
        _pose(closure.pose, [float(v) for v in relative.translation()], [float(v) for v in quaternion])
    else:
        _pose(closure.pose, [data.draw(FLOAT if wild else PLAUSIBLE) for _ in range(3)],
              data.draw(quaternions(wild)))
    closure.pose_covariance = data.draw(covariances(wild))
    verdict = loop_closure_stamp_problem(closure) or loop_closure_pose_problem(closure)
    assert verdict is None or (isinstance(verdict, str) and verdict)
    if verdict is not None:
        event("closure refused")
        return
    pose, covariance = closure_in_base_frame(*loop_closure_pose(closure), gtsam.Pose3())
    result = graph.add_closure(Closure(query_ns, place_ns, pose, covariance))
    assert isinstance(result, ClosureResult)
    event(f"closure {result.value}")
    gate.check(query_ns, place_ns, *loop_closure_pose(closure))
    for _, keyframe in graph.trajectory():
        assert np.isfinite(keyframe.matrix()).all()


def test_a_posterior_whose_candidate_arrays_differ_in_length_is_named() -> None:
    good = msg.PlacePosterior(place_ids=[1, 2], probabilities=[0.5, 0.25], log_likelihoods=[-1.0, -2.0])
    good.place_stamps = [Time(sec=1), Time(sec=2)]
    assert posterior_problem(good) is None
    bad = msg.PlacePosterior(query_id=7, place_ids=[1, 2], probabilities=[0.5], log_likelihoods=[-1.0, -2.0])
    bad.place_stamps = [Time(sec=1), Time(sec=2)]
    problem = posterior_problem(bad)
    assert problem is not None and "query 7" in problem and "'probabilities': 1" in problem


def test_a_zero_quaternion_and_a_nan_stamp_field_are_named() -> None:
    odometry = Odometry()
    odometry.pose.pose.orientation.w = 0.0
    assert "zero quaternion" in (odometry_problem(odometry) or "")
    odometry.pose.pose.orientation.w = math.nan
    assert "odometry pose orientation w = nan is not finite" in (odometry_problem(odometry) or "")
    odometry.pose.pose.orientation.w = 1.0
    odometry.header.stamp = _stamp(5, 1_500_000_000)
    assert "odometry stamp.nanosec = 1500000000" in (odometry_problem(odometry) or "")
