"""The trajectory of several sessions joined by a backend, against each session's odometry
(``aefabmap_eval --recording ... --trajectory keyframes.tum --session-odometry a.tum --session-odometry b.tum``).

The joined trajectory (pose_graph_node's ``trajectory_file``: every joined session's keyframes in one map frame)
is aligned to the pose truth once, SE(3) by evo, so its error includes where each session was placed relative to
the others. Each session's odometry has its own frame (a rebooted robot's odometry restarts): it is taken at the
keyframes of the joined trajectory that fall in its span of stamps and aligned to the truth on its own, which
is the most odometry alone can give. The odometry figure to compare with is those sessions' errors pooled
(the RMSE over all their keyframes, each session aligned on its own).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.evaluation.reports import fmt, jsonable_float


@dataclass(frozen=True)
class SessionOdometryError:
    source: str  # the odometry file
    keyframes: int  # keyframes of the joined trajectory in its span (and with an odometry pose)
    rmse_m: float  # its odometry at them, aligned on its own (nan: too few to align)
    all_frames_rmse_m: float  # its odometry over every pose, aligned on its own


@dataclass(frozen=True)
class JoinedTrajectoryError:
    trajectory: str
    keyframes: int
    rmse_m: float  # the joined trajectory, one SE(3) alignment
    sessions: tuple[SessionOdometryError, ...]
    unjoined: tuple[str, ...]  # files the backend wrote beside it for sessions it never joined

    @property
    def odometry_rmse_m(self) -> float:
        """The sessions' odometry errors pooled: RMSE over all their keyframes, each session aligned on its own."""
        measured = [s for s in self.sessions if not math.isnan(s.rmse_m)]
        count = sum(s.keyframes for s in measured)
        return math.sqrt(sum(s.keyframes * s.rmse_m ** 2 for s in measured) / count) if count else float("nan")

    @property
    def ratio(self) -> float:
        odometry = self.odometry_rmse_m
        return self.rmse_m / odometry if odometry > 0 else float("nan")


def unjoined_session_files(trajectory: Path) -> list[Path]:
    """``<stem>.session<k><suffix>`` and ``<stem>.<robot>.session<k><suffix>`` beside the trajectory file."""
    return sorted(path for path in trajectory.parent.glob(f"{trajectory.stem}.*{trajectory.suffix}")
                  if ".session" in path.name[len(trajectory.stem):])


def joined_trajectory_error(truth: Path, trajectory: Path, odometry_files: Sequence[Path]) -> JoinedTrajectoryError:
    """ATE of the joined keyframe trajectory, and of each session's odometry at its keyframes (module docstring)."""
    from aefabmap_ros.evaluation.trajectory_error import absolute_trajectory_error, at_stamps, read_tum

    reference = read_tum(truth)
    joined = read_tum(trajectory)
    stamps = np.asarray(joined.timestamps, dtype=np.float64)
    sessions = []
    for path in odometry_files:
        odometry = read_tum(path)
        span = np.asarray(odometry.timestamps, dtype=np.float64)
        inside = stamps[(stamps >= span[0] - 0.01) & (stamps <= span[-1] + 0.01)]
        keyframes, rmse = 0, float("nan")
        if inside.size:
            at_keyframes = at_stamps(odometry, inside)
            keyframes = int(at_keyframes.num_poses)
            with suppress(DataError):  # fewer than 3 keyframes in this session: nothing to align
                rmse = absolute_trajectory_error(reference, at_keyframes).rmse_m
        sessions.append(SessionOdometryError(str(path), keyframes, rmse,
                                             absolute_trajectory_error(reference, odometry).rmse_m))
    return JoinedTrajectoryError(str(trajectory), int(stamps.size), absolute_trajectory_error(reference, joined).rmse_m,
                                 tuple(sessions), tuple(str(p) for p in unjoined_session_files(trajectory)))


def joined_trajectory_markdown(error: JoinedTrajectoryError) -> str:
    lines = ["\nThe joined trajectory (the backend's keyframes of every joined session in one map frame, one SE(3) "
             "alignment to the pose truth, evo) against each session's odometry at the same keyframes, aligned on "
             "its own:\n",
             "| trajectory | keyframes | ATE RMSE (m) | every odometry pose (m) |", "|---|---|---|---|",
             f"| joined: `{error.trajectory}` | {error.keyframes} | {fmt(error.rmse_m)} | |"]
    lines += [f"| odometry `{s.source}`, aligned on its own | {s.keyframes} | {fmt(s.rmse_m)} "
              f"| {fmt(s.all_frames_rmse_m)} |" for s in error.sessions]
    if error.sessions:
        lines.append(f"| odometry, the sessions pooled | {sum(s.keyframes for s in error.sessions)} "
                     f"| {fmt(error.odometry_rmse_m)} | |")
        lines.append(f"\nJoined trajectory error: {100 * error.ratio:.1f} % of odometry's.")
    lines.append("Sessions left unjoined (not in the joined trajectory): "
                 + (", ".join(f"`{path}`" for path in error.unjoined) if error.unjoined else "none") + ".")
    return "\n".join(lines) + "\n"


def joined_trajectory_to_dict(error: JoinedTrajectoryError) -> dict[str, Any]:
    return {"trajectory": error.trajectory, "keyframes": error.keyframes, "ate_rmse_m": jsonable_float(error.rmse_m),
            "session_odometry": [{"source": s.source, "keyframes": s.keyframes, "ate_rmse_m": jsonable_float(s.rmse_m),
                                  "all_poses_ate_rmse_m": jsonable_float(s.all_frames_rmse_m)}
                                 for s in error.sessions],
            "odometry_pooled_ate_rmse_m": jsonable_float(error.odometry_rmse_m),
            "joined_over_odometry": jsonable_float(error.ratio), "unjoined_sessions": list(error.unjoined)}
