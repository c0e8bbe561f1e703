"""The joined trajectory of two sessions against each session's odometry, on geometry with a closed-form answer.

Session B drives session A's path again, pose for pose. The joined trajectory holds A exactly and B shifted by
``offset`` along x: one SE(3) alignment can only split the difference (the cross-covariance of the two point sets
is the path's own scatter, symmetric, so the best rotation is the identity), so every keyframe is offset / 2 off.
Each session's odometry is the truth in a frame of its own (a rigid motion, as a restarted odometry's), each pose
of a stationary pair off by +-err along z: that error is uncorrelated with the path, so aligning the session on
its own leaves exactly err at every pose.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.evaluation.session_trajectory import joined_trajectory_error, unjoined_session_files
from aefabmap_ros.evaluation.trajectory_error import tum_text

START_S = 1_700_000_000.0
PERIOD_S = 0.1
PER_SESSION = 20


def _poses(positions: np.ndarray) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(positions), 1, 1))
    poses[:, :3, 3] = positions
    return poses


def _path() -> np.ndarray:
    """One session's camera centres: ten places on a circle, each held for two frames (a stationary pair)."""
    angles = 0.5 * np.arange(PER_SESSION // 2)
    places = np.column_stack([5 * np.cos(angles), 5 * np.sin(angles), np.zeros_like(angles)])
    return np.repeat(places, 2, axis=0)


def write_two_sessions(root: Path, offset_m: float, odometry_error_m: float) -> dict[str, Path]:
    """truth.tum, joined.tum (B shifted by ``offset_m`` along x) and each session's odometry (a.tum, b.tum)."""
    stamps = START_S + PERIOD_S * np.arange(2 * PER_SESSION)
    path = _path()
    truth = np.vstack([path, path])
    joined = truth.copy()
    joined[PER_SESSION:, 0] += offset_m
    files = {"truth": root / "truth.tum", "joined": root / "joined.tum"}
    files["truth"].write_text(tum_text(stamps, _poses(truth)))
    files["joined"].write_text(tum_text(stamps, _poses(joined)))
    alternate = np.where(np.arange(PER_SESSION) % 2 == 0, odometry_error_m, -odometry_error_m)
    for index, name in enumerate(("a", "b")):
        frame = np.eye(4)  # the session's odometry frame: turned and moved, as a restarted odometry's is
        frame[:3, :3] = Rotation.from_euler("z", 30 + 40 * index, degrees=True).as_matrix()
        frame[:3, 3] = [3.0, -2.0 * index, 0.5]
        noisy = path + alternate[:, None] * np.array([0.0, 0.0, 1.0])
        odometry = np.linalg.inv(frame) @ _poses(noisy)
        files[name] = root / f"{name}.tum"
        files[name].write_text(tum_text(stamps[index * PER_SESSION:(index + 1) * PER_SESSION], odometry))
    return files


def test_joined_error_against_each_sessions_own(tmp_path: Path) -> None:
    files = write_two_sessions(tmp_path, offset_m=0.4, odometry_error_m=0.5)
    error = joined_trajectory_error(files["truth"], files["joined"], [files["a"], files["b"]])
    assert error.keyframes == 2 * PER_SESSION
    assert error.rmse_m == pytest.approx(0.2, abs=1e-6)
    assert [s.keyframes for s in error.sessions] == [PER_SESSION, PER_SESSION]
    assert [s.rmse_m for s in error.sessions] == pytest.approx([0.5, 0.5], abs=1e-6)
    assert [s.all_frames_rmse_m for s in error.sessions] == pytest.approx([0.5, 0.5], abs=1e-6)
    assert error.odometry_rmse_m == pytest.approx(0.5, abs=1e-6)
    assert error.ratio == pytest.approx(0.4, abs=1e-5)
    assert error.unjoined == ()


def test_keyframes_are_those_of_the_joined_trajectory(tmp_path: Path) -> None:
    """Odometry is taken at the joined trajectory's keyframes only; a session with too few to align is nan."""
    files = write_two_sessions(tmp_path, offset_m=0.0, odometry_error_m=0.5)
    lines = files["joined"].read_text().splitlines()
    files["joined"].write_text("\n".join(lines[:PER_SESSION] + lines[PER_SESSION:PER_SESSION + 2]) + "\n")
    error = joined_trajectory_error(files["truth"], files["joined"], [files["a"], files["b"]])
    assert [s.keyframes for s in error.sessions] == [PER_SESSION, 2]
    assert error.sessions[0].rmse_m == pytest.approx(0.5, abs=1e-6) and math.isnan(error.sessions[1].rmse_m)
    assert error.odometry_rmse_m == pytest.approx(0.5, abs=1e-6)  # pooled over the sessions measured


def test_unjoined_sessions_beside_the_trajectory(tmp_path: Path) -> None:
    trajectory = tmp_path / "keyframes.tum"
    for name in ("keyframes.tum", "keyframes.session1.tum", "keyframes.rover.session2.tum", "other.session1.tum",
                 "keyframes_injected.tum"):
        (tmp_path / name).write_text("")
    assert [p.name for p in unjoined_session_files(trajectory)] == ["keyframes.rover.session2.tum",
                                                                     "keyframes.session1.tum"]
