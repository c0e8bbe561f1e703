"""The one check of stamps, poses and covariances: what it refuses is named, what it accepts the graph takes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aefabmap_ros.io.message_values import (
    MAX_POSITION_M,
    MAX_VARIANCE,
    covariance_problem,
    pose_problem,
    psd_part,
    stamp_problem,
)

IDENTITY = (0.0, 0.0, 0.0, 1.0)
NAN, INF = float("nan"), float("inf")


def test_a_usable_pose_passes_and_each_broken_one_is_named() -> None:
    assert pose_problem((1.0, -2.0, 3.0), IDENTITY) is None
    assert pose_problem((0.0, 0.0, 0.0), (0.0, 0.0, math.sin(0.3), math.cos(0.3))) is None
    assert pose_problem((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0 + 9e-4)) is None  # a float32 driver's rounding
    cases = [
        (((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, NAN)), "orientation w = nan is not finite"),
        (((NAN, 0.0, 0.0), IDENTITY), "position x = nan is not finite"),
        (((0.0, 0.0, -INF), IDENTITY), "position z = -inf is not finite"),
        (((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)), "norm 0 (a zero quaternion"),
        (((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.5)), "norm 1.5"),
        (((0.0, 0.0, 0.0), (1e308, 1e308, 0.0, 0.0)), "norm inf"),
        (((0.0, 2 * MAX_POSITION_M, 0.0), IDENTITY), "position y = 2e+08 m is beyond"),
        (((0.0, 0.0), IDENTITY), "position has 2 values, not 3"),
        (((0.0, 0.0, 0.0), ("a", "b", "c", "d")), "orientation is not a sequence of numbers"),
    ]
    for (position, quaternion), expected in cases:
        problem = pose_problem(position, quaternion, "odometry pose")
        assert problem is not None and expected in problem and problem.startswith("odometry pose"), problem


def test_a_covariance_must_be_finite_symmetric_and_positive_semi_definite() -> None:
    assert covariance_problem(np.diag([0.02**2] * 3 + [0.005**2] * 3)) is None
    assert covariance_problem(np.zeros(36)) is None  # "exact": the graph's floor still applies
    monocular = np.diag([1e-4] * 6)
    monocular[:3, :3] += 1e6 * np.outer([0.6, 0.8, 0.0], [0.6, 0.8, 0.0])  # the unknown scale's variance
    assert covariance_problem(monocular) is None
    rounded = monocular.astype(np.float32).astype(np.float64)  # computed in single precision
    assert covariance_problem(rounded) is None
    not_psd = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, -0.5])
    asymmetric = np.eye(6)
    asymmetric[0, 1] = 0.5
    with_nan = np.eye(6)
    with_nan[2, 2] = NAN
    cases = [
        (with_nan, "covariance [14] = nan is not finite"),
        (not_psd, "not positive semi-definite: eigenvalue -0.5"),
        (asymmetric, "not symmetric: [0, 1] = 0.5 but [1, 0] = 0"),
        (np.eye(6) * 10 * MAX_VARIANCE, "is beyond 1e+12"),
        (np.eye(5), "has 25 values, not 36"),
    ]
    for covariance, expected in cases:
        problem = covariance_problem(covariance)
        assert problem is not None and expected in problem, problem


def test_the_psd_part_of_an_accepted_covariance_takes_a_floor_to_positive_definite() -> None:
    rng = np.random.default_rng(3)
    basis = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    covariance = (basis * np.array([-1e-9, 0.0, 1e-6, 1.0, 10.0, 1e3])) @ basis.T  # round-off below zero
    assert covariance_problem(covariance) is None
    part = psd_part(covariance)
    # Reassembled from its eigenvectors, the clipped matrix's smallest eigenvalue is 0 up to round-off (of the
    # order of 1e-16 times its largest, 1e3, whatever the BLAS): far above the -1e-9 it clipped.
    assert np.array_equal(part, part.T) and np.linalg.eigvalsh(part)[0] >= -1e-11
    assert np.allclose(part, covariance, atol=1e-8)
    np.linalg.cholesky(part + 1e-4 * np.eye(6))  # positive definite with the graph's smallest default floor


def test_stamps() -> None:
    assert stamp_problem(2**31 - 1, 999_999_999) is None and stamp_problem(-(2**31), 0) is None
    assert "nanosec = 1000000000 is not in [0, 1e9)" in (stamp_problem(5, 1_000_000_000, "odometry stamp") or "")
    assert "sec = 2147483648 is outside int32" in (stamp_problem(2**31, 0) or "")
    assert "is not a pair of integers" in (stamp_problem(None, 0) or "")


ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=300, deadline=None)
@given(position=st.lists(ANY_FLOAT, min_size=0, max_size=4), quaternion=st.lists(ANY_FLOAT, min_size=0, max_size=5),
       covariance=st.lists(ANY_FLOAT, min_size=35, max_size=37), sec=st.integers(-(2**40), 2**40),
       nanosec=st.integers(-(2**33), 2**33))
def test_the_checks_answer_every_input_with_a_verdict(position: list[float], quaternion: list[float],
                                                      covariance: list[float], sec: int, nanosec: int) -> None:
    for verdict in (pose_problem(position, quaternion), covariance_problem(covariance), stamp_problem(sec, nanosec)):
        assert verdict is None or (isinstance(verdict, str) and verdict)
    if covariance_problem(covariance) is None:
        part = psd_part(np.asarray(covariance).reshape(6, 6))
        assert np.isfinite(part).all() and np.linalg.eigvalsh(part)[0] >= -1e-9 * max(1.0, np.abs(part).max())


@pytest.mark.parametrize("diagonal", [[0.0] * 6, [MAX_VARIANCE] * 6, [1e-300] * 6])
def test_extreme_but_valid_diagonals_pass(diagonal: list[float]) -> None:
    assert covariance_problem(np.diag(diagonal)) is None
