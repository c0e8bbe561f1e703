"""What the decision chain asks of an odometry gate, so that verification needs no SLAM backend.

The chain (verification/chain.py) hands every verified closure with a relative pose to a gate before it is
published. The example backend's test against raw odometry (backend/odometry_gate.py) is the one the nodes
and the offline evaluation use; a robot's own backend can pass another.
"""

from __future__ import annotations

from enum import Enum
from typing import Protocol

import gtsam
import numpy as np


class GateResult(Enum):
    CONSISTENT = "consistent_with_odometry"
    INCONSISTENT = "inconsistent_with_odometry"  # further from odometry than its drift can explain
    NOT_YET = "waiting_for_odometry"  # a stamp after the newest odometry: ask again when more has come
    NO_ODOMETRY = "no_odometry_at_stamps"  # a stamp before the oldest odometry kept: it will never be covered


class ClosureGate(Protocol):
    """Odometry by stamp, and the test of a camera-frame closure against it."""

    @property
    def active(self) -> bool:
        """True once odometry has arrived: before that closures pass unchecked."""

    @property
    def threshold(self) -> float:
        """The Mahalanobis distance squared above which a closure is refused (for the log)."""

    def add_odometry(self, stamp_ns: int, pose: gtsam.Pose3) -> bool:
        """Keep ``T_odom_base`` at that stamp; False (ignored) unless it is after the last one."""

    def reaches(self, query_ns: int, place_ns: int) -> bool:
        """Whether odometry has come up to both stamps."""

    def check(self, query_ns: int, place_ns: int, query_to_place: gtsam.Pose3,
              covariance: np.ndarray) -> tuple[GateResult, float]:
        """The closure against odometry: the result and the Mahalanobis distance squared."""
