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
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence

from aefabmap_ros.verification.closures import Detection, Outcomes, Posterior

# Stamps remembered as asked for, per robot (a frame whose answer never came is not asked for twice).
ASKED_REMEMBERED = 5000


class FrameRequests:
    """The frames to ask each robot for, from the posteriors and candidates the base receives."""

    def __init__(self, robots: Sequence[str], outcomes: Outcomes) -> None:
        self.robots = tuple(robots)
        self.outcomes = outcomes
        self._asked: dict[str, OrderedDict[int, None]] = {robot: OrderedDict() for robot in self.robots}
        self._outgoing: dict[str, list[int]] = {robot: [] for robot in self.robots}
        self._newest_place_id = -1

    def after_posterior(self, posterior: Posterior, tracking: bool, stored: Callable[[int], bool]) -> None:
        """Ask for the posterior's frame when it made a place, has a candidate, or a loop of its robot is tracked."""
        made_place = posterior.query_id >= 0 and posterior.current_place_id > self._newest_place_id
        self._newest_place_id = max(self._newest_place_id, posterior.current_place_id)
        if posterior.query_id < 0:
            return  # a frame FAB-MAP dropped: nothing will be verified with it
        reason = ("place" if made_place else "query" if posterior.loop_closure_candidate
                  else "tracking" if tracking else None)
        if reason is not None:
            self.want(posterior.robot, posterior.query_ns, reason, stored)

    def after_detection(self, detection: Detection, stored: Callable[[int], bool]) -> None:
        """A candidate: its query (normally asked for with its posterior already) and a matched place not stored."""
        self.want(detection.query_robot, detection.query_ns, "query", stored)
        self.want(detection.matched_robot, detection.matched_ns, "matched_place", stored)

    def want(self, robot: str, stamp_ns: int, reason: str, stored: Callable[[int], bool]) -> None:
        """Ask ``robot`` for its frame at ``stamp_ns`` unless it is stored or was asked for already."""
        asked = self._asked.get(robot)
        if asked is None:
            self.outcomes.drop("request_for_unknown_robot", f"frame at stamp {stamp_ns} of robot {robot!r}, which "
                               f"is not one of this node's robots {list(self.robots)}")
            return
        if stamp_ns in asked or stored(stamp_ns):
            return
        asked[stamp_ns] = None
        while len(asked) > ASKED_REMEMBERED:
            asked.popitem(last=False)
        self._outgoing[robot].append(stamp_ns)
        self.outcomes.ok(f"requested_{reason}")

    def take(self) -> dict[str, list[int]]:
        """The stamps to ask each robot for now (robots with none left out); emptied."""
        taken = {robot: stamps for robot, stamps in self._outgoing.items() if stamps}
        self._outgoing = {robot: [] for robot in self.robots}
        return taken
