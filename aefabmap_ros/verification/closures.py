"""What the verification chain takes in and gives out, without ROS: FAB-MAP's detections and posteriors,
and the verified closures (verifier_node converts them to and from its messages)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Protocol

from aefabmap_ros.verification.relative_pose import PoseOutcome


@dataclass(frozen=True)
class Detection:
    """A loop-closure candidate: FAB-MAP's temporally consistent match of a query (or a tracked one)."""

    query_ns: int
    query_id: int
    query_place_id: int
    matched_place_id: int
    matched_ns: int  # stamp of the matched place's image
    probability: float  # FAB-MAP's posterior of the matched place
    log_likelihood: float
    frame_id: str = ""  # the query image's frame, carried through
    query_session: int = 0  # the map's session and robot of the query image (fabmap/sessions.py)
    query_robot: str = ""
    matched_session: int = 0  # ... and of the matched place's image
    matched_robot: str = ""


@dataclass(frozen=True)
class RankedPlace:
    """One of a query's top candidates in its posterior."""

    place_id: int
    stamp_ns: int
    probability: float
    log_likelihood: float
    session: int = 0  # session and robot the place was made in
    robot: str = ""


@dataclass(frozen=True)
class Posterior:
    """FAB-MAP's answer for one frame (a place_posteriors message)."""

    query_ns: int
    query_id: int  # -1: a frame FAB-MAP dropped
    assigned_place_id: int
    current_place_id: int  # the place of the map this frame belongs to, -1 while the map is empty
    loop_closure_candidate: bool  # a Detection of this frame comes too
    candidates: tuple[RankedPlace, ...]  # best first
    frame_id: str = ""
    session: int = 0  # session and robot of the query image
    robot: str = ""


@dataclass(frozen=True)
class Closure:
    """A verified loop closure: the detection (moved to the best-verified place), its inliers and pose."""

    detection: Detection
    inliers: int
    pose: PoseOutcome
    tracked: bool = False  # published by loop tracking (the frame had no detection of its own, or it failed)
    nearby_frame: bool = False  # tracked to one of the frames nearest the verified place, not a ranked candidate


class Outcomes(Protocol):
    """Where the chain counts what became of its inputs (verifier_node's DropCounter; a Counter offline)."""

    def ok(self, what: str = "processed") -> None: ...

    def drop(self, reason: str, detail: str, count: int = 1) -> None: ...


class CountedOutcomes:
    """Outcomes counted by name with no log: the offline chain's (the node's DropCounter logs them too)."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()

    def ok(self, what: str = "processed") -> None:
        self.counts[what] += 1

    def drop(self, reason: str, detail: str, count: int = 1) -> None:
        del detail
        self.counts[f"dropped_{reason}"] += count
