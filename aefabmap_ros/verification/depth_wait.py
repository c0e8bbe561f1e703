"""Queries held until their own depth image has come (verification/chain.py).

A frame's depth image comes on its own topic, straight from the camera, while its features, posterior and
detection come through the detector's nodes; a verifier busy with a revisit takes its callbacks in turn, so
a query can be ready before its depth image has been taken. Verified then, a query gets no metric test, and
its pose is PnP's on the place's depth alone: for a facade seen again from far back, one of two solutions
that reproject almost equally well (relative_pose.py). On the dense synthetic video replayed in lockstep,
19 of the 21 closures published with a pose over 0.2 m off (all of them 15-28 m from their place) had been
verified so.

So a query waits for its depth image, and goes on without it only when that will not come:

- a depth image stamped after it has come (a stream in stamp order has lost the query's: best effort,
  or a depth image the verifier could not keep);
- the newest frame is ``wait_s`` newer than the query (stamp time, as the odometry wait: the depth
  stream has stopped, or trails further than the verifier should wait).

Before the first depth image nothing waits: a depth topic that is named but silent must not hold every
closure for ``wait_s``. How long the queries that waited were held (wall time) is summarised on shutdown
(``summary``), so the cost of the wait in latency is measured where it is paid.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable

import numpy as np

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.verification.closures import Outcomes

WAITS_KEPT = 10_000  # the newest waits the summary describes


class DepthWait:
    """Which queries may be verified now, as far as their depth image is concerned, and which wait."""

    def __init__(self, wait_s: float, outcomes: Outcomes | None = None) -> None:
        if not wait_s >= 0:
            raise ConfigError(f"depth_wait_s ({wait_s}) must be >= 0")
        self.wait_ns = round(wait_s * 1e9)
        self.outcomes = outcomes  # counts query_depth_missing
        self.newest_depth_ns: int | None = None  # of any depth image, kept or not
        self.newest_frame_ns: int | None = None
        # query stamp -> when its wait began (time.monotonic()), oldest first
        self.waiting: OrderedDict[int, float] = OrderedDict()
        self.waits_s: deque[float] = deque(maxlen=WAITS_KEPT)  # how long each query that waited was held

    def depth_came(self, stamp_ns: int) -> None:
        if self.newest_depth_ns is None or stamp_ns > self.newest_depth_ns:
            self.newest_depth_ns = stamp_ns

    def frame_came(self, stamp_ns: int) -> None:
        if self.newest_frame_ns is None or stamp_ns > self.newest_frame_ns:
            self.newest_frame_ns = stamp_ns

    def ready(self, query_ns: int, has_depth: bool) -> bool:
        """True: verify the query now (its depth is in, or will not come: counted as ``query_depth_missing`` once
        a depth stream exists); False: it waits (``waiting``)."""
        if has_depth or self.will_not_come(query_ns):
            began = self.waiting.pop(query_ns, None)
            if began is not None:
                self.waits_s.append(time.monotonic() - began)
            if not has_depth and self.newest_depth_ns is not None and self.outcomes is not None:
                self.outcomes.ok("query_depth_missing")
            return True
        self.waiting.setdefault(query_ns, time.monotonic())
        return False

    def will_not_come(self, query_ns: int) -> bool:
        """Nothing to wait for: no depth stream yet, a later depth image came, or the wait is over."""
        if self.newest_depth_ns is None or self.newest_depth_ns > query_ns:
            return True
        return self.newest_frame_ns is not None and self.newest_frame_ns - query_ns > self.wait_ns

    def waiting_among(self, alive: Callable[[int], bool]) -> list[int]:
        """The waiting queries ``alive`` still holds, oldest first; the others (dropped meanwhile by the chain's
        bounds) wait no longer."""
        for query_ns in [query_ns for query_ns in self.waiting if not alive(query_ns)]:
            del self.waiting[query_ns]
        return list(self.waiting)

    def summary(self) -> str:
        """How many queries waited for their depth image, and how long (wall time)."""
        if not self.waits_s:
            return "no query waited for its depth image"
        p50, p95 = np.percentile(self.waits_s, [50, 95])
        return (f"{len(self.waits_s)} queries waited for their depth image: median {p50:.3f} s, p95 {p95:.3f} s, "
                f"max {max(self.waits_s):.3f} s")
