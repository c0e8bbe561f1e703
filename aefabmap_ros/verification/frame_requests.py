"""Which robot frames a base station asks for (several robots, docs/fleet.md), without ROS.

The base gets every robot's words, not its features: the verifier asks each robot's feature server for the
frames it will verify, and only those cross the link. From FAB-MAP's answer for a frame (its posterior,
published before its candidate) the base knows which it will need:

- a frame that **made a place** (its ``current_place_id`` is newer than every place seen): any later revisit
  by any robot may match it, so it is asked for at once and kept (``requested_place``);
- the **query of a candidate** (the posterior says a candidate follows): verified as soon as it comes
  (``requested_query``);
- while a loop is **tracked** for the frame's robot (verification/loop_tracking.py): each of that robot's
  frames, which tracking verifies against the places near the tracked one (``requested_tracking``);
- a candidate's **matched place** that is not stored (the base restarted, or its store forgot it): asked for
  in case the robot still keeps it (``requested_matched_place``); the candidate does not wait for it.

A frame already stored, or already asked for, is not asked for again; a frame of a robot the base does not
serve is not asked for (``request_for_unknown_robot``). Requests are collected per robot and sent together
(``take``), one message per robot and callback.

**The link's budget** (``requests_per_frame``, as Swarm-SLAM bounds the candidates it verifies). During a
revisit nearly every frame is a candidate, and its features (20-35 KiB) dwarf its words (1-2 KiB). Each robot
earns ``requests_per_frame`` requests with every frame FAB-MAP answers (at most ``BURST_REQUESTS`` saved up);
a place is always asked for and spends one (a place missed is a revisit lost for good), a query or a tracked
frame is asked for only while one is left (else ``request_over_budget_<reason>``, and the candidate is
decided without it). So a robot's link carries on average its words and at most ``requests_per_frame``
answers per frame, or its places where they are more. 0: no budget.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.verification.closures import Detection, Outcomes, Posterior

# Stamps remembered as asked for, per robot (a frame whose answer never came is not asked for twice).
ASKED_REMEMBERED = 5000
BURST_REQUESTS = 10.0  # requests a robot may save up, with a budget: a revisit's first frames are all verified


class FrameRequests:
    """The frames to ask each robot for, from the posteriors and candidates the base receives."""

    def __init__(self, robots: Sequence[str], outcomes: Outcomes, requests_per_frame: float = 0.0) -> None:
        if not requests_per_frame >= 0:
            raise ConfigError(f"requests_per_frame ({requests_per_frame}) must be >= 0 (0 = no budget)")
        self.robots = tuple(robots)
        self.outcomes = outcomes
        self.requests_per_frame = requests_per_frame
        self._budget = dict.fromkeys(self.robots, BURST_REQUESTS)
        self._refused: OrderedDict[int, None] = OrderedDict()  # queries and tracked frames not asked for: budget
        self._asked: dict[str, OrderedDict[int, None]] = {robot: OrderedDict() for robot in self.robots}
        self._outgoing: dict[str, list[int]] = {robot: [] for robot in self.robots}
        self._newest_place_id = -1

    def after_posterior(self, posterior: Posterior, tracking: bool, stored: Callable[[int], bool]) -> None:
        """Ask for the posterior's frame when it made a place, has a candidate, or a loop of its robot is tracked."""
        made_place = posterior.query_id >= 0 and posterior.current_place_id > self._newest_place_id
        self._newest_place_id = max(self._newest_place_id, posterior.current_place_id)
        if posterior.query_id < 0:
            return  # a frame FAB-MAP dropped: nothing will be verified with it
        if posterior.robot in self._budget:
            self._budget[posterior.robot] = min(BURST_REQUESTS, self._budget[posterior.robot] + self.requests_per_frame)
        reason = ("place" if made_place else "query" if posterior.loop_closure_candidate
                  else "tracking" if tracking else None)
        if reason is not None:
            self.want(posterior.robot, posterior.query_ns, reason, stored)

    def after_detection(self, detection: Detection, stored: Callable[[int], bool]) -> bool:
        """A candidate: its query (normally asked for with its posterior already) and a matched place not stored.
        False: its query will not come (over the link's budget, or of a robot not served)."""
        query = self.want(detection.query_robot, detection.query_ns, "query", stored)
        self.want(detection.matched_robot, detection.matched_ns, "matched_place", stored)
        return query

    def want(self, robot: str, stamp_ns: int, reason: str, stored: Callable[[int], bool]) -> bool:
        """Ask ``robot`` for its frame at ``stamp_ns`` unless it is stored or was asked for already (within the
        link's budget); False when it is neither stored nor asked for."""
        asked = self._asked.get(robot)
        if asked is None:
            self.outcomes.drop("request_for_unknown_robot", f"frame at stamp {stamp_ns} of robot {robot!r}, which "
                               f"is not one of this node's robots {list(self.robots)}")
            return False
        if stamp_ns in asked or stored(stamp_ns):
            return True
        if stamp_ns in self._refused:
            return False
        if self.requests_per_frame and reason not in ("place", "matched_place") and self._budget[robot] < 1.0:
            self.outcomes.ok(f"request_over_budget_{reason}")
            self._refused[stamp_ns] = None
            while len(self._refused) > ASKED_REMEMBERED:
                self._refused.popitem(last=False)
            return False
        self._budget[robot] -= 1.0 if self.requests_per_frame else 0.0
        asked[stamp_ns] = None
        while len(asked) > ASKED_REMEMBERED:
            asked.popitem(last=False)
        self._outgoing[robot].append(stamp_ns)
        self.outcomes.ok(f"requested_{reason}")
        return True

    def take(self) -> dict[str, list[int]]:
        """The stamps to ask each robot for now (robots with none left out); emptied."""
        taken = {robot: stamps for robot, stamps in self._outgoing.items() if stamps}
        self._outgoing = {robot: [] for robot in self.robots}
        return taken
