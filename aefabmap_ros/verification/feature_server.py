"""A robot's recent frames, kept on the robot for a base station that asks for some of them (docs/fleet.md).

With several robots and one base station, a robot sends the base only its words every frame; the features
a verification needs (keypoints, descriptors, and with a depth camera the keypoints' depths and a coarse
depth grid) cross the link only for the frames the base asks for. This is the robot's end: it keeps its
recent frames in the verifier's own :class:`FrameStore` (the same strongest keypoints, the same compact
descriptors, the same depths), bounded by a frame count and by bytes (frames are forgotten oldest first:
the robot has no posteriors to rank them by), and answers a request with the frames it still keeps.

A request for a frame is answered once, when the frame is ready:

- its features are kept and, when the robot has a depth camera, its depth has been sampled or will not come
  (verification/depth_wait.py: a later depth image came, or ``wait_s`` of newer frames passed): ``served``;
- its features have not come yet (the request overtook them: words and features leave feature_node on two
  paths): it waits, until they come or ``wait_s`` of newer frames passed (``never_came``);
- its features are no longer kept, or were never taken (a stamp older than the newest frame that is not
  stored): ``not_kept_any_more``, answered with nothing. The base decides without that frame.

Pure Python (no ROS): feature_server_node feeds it what arrives and publishes what it returns.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import NamedTuple

import numpy as np

from aefabmap_ros.errors import AefabmapError, ConfigError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.closures import Outcomes
from aefabmap_ros.verification.depth_wait import DepthWait
from aefabmap_ros.verification.frame_depths import FrameDepths
from aefabmap_ros.verification.frame_store import FrameStore

# Requests waiting for their frame, at most (the oldest is dropped as never_came).
MAX_WAITING_REQUESTS = 1000


class ServedFrame(NamedTuple):
    """One frame as the server sends it: its stored features and, with a depth camera, its depths."""

    stamp_ns: int
    features: Features  # as stored: (N, 2) keypoints, compact descriptors
    depths: FrameDepths | None
    image_size: tuple[int, int] | None  # (width, height) of its image


class FeatureServer:
    """The robot's recent frames and the requests waiting for theirs."""

    def __init__(self, store: FrameStore, outcomes: Outcomes, wait_s: float = 2.0) -> None:
        if not wait_s >= 0:
            raise ConfigError(f"the feature server's wait_s ({wait_s}) must be >= 0")
        self.store = store
        self.outcomes = outcomes
        self.wait_ns = round(wait_s * 1e9)
        self.depth_wait = DepthWait(wait_s)
        self.newest_ns: int | None = None  # newest frame whose features came
        self.waiting: OrderedDict[int, None] = OrderedDict()  # requested stamps not answered yet
        self._image_sizes: dict[int, tuple[int, int]] = {}

    def add_features(self, stamp_ns: int, features: Features, image_size: tuple[int, int] | None) -> list[ServedFrame]:
        """Keep a frame's features (AefabmapError when malformed); the waiting requests it makes ready."""
        stored = self.store.add_features(stamp_ns, features)
        if image_size is not None:
            self._image_sizes[stamp_ns] = image_size
        if self.store.depths is not None:
            try:
                self.store.depths.add_features(stamp_ns, stored.keypoints, image_size)
            except AefabmapError as exc:  # a depth image of another size: the frame goes without depth
                self.outcomes.drop("depth_size_mismatch", f"frame at stamp {stamp_ns}: {exc}")
            self.store.depths_changed(stamp_ns)
        if self.newest_ns is None or stamp_ns > self.newest_ns:
            self.newest_ns = stamp_ns
        self.depth_wait.frame_came(stamp_ns)
        self._forget_sizes()
        return self._ready()

    def add_depth(self, stamp_ns: int, depth_m: np.ndarray) -> list[ServedFrame]:
        """A frame's depth image in metres (AefabmapError when it cannot be kept); the requests it makes ready."""
        if self.store.depths is None:
            return []
        self.depth_wait.depth_came(stamp_ns)
        try:
            self.store.depths.add_depth(stamp_ns, depth_m)
            self.store.depths_changed(stamp_ns)
        finally:
            ready = self._ready()
        return ready

    def skip_frame(self, stamp_ns: int) -> None:
        """A frame feature_node will not process: its depth image is not kept."""
        if self.store.depths is not None:
            self.store.depths.skip_frame(stamp_ns)

    def request(self, stamps_ns: list[int]) -> list[ServedFrame]:
        """The base asks for these frames: those ready now; the ones still to come wait."""
        for stamp_ns in dict.fromkeys(stamps_ns):
            if stamp_ns in self.store or self.newest_ns is None or stamp_ns > self.newest_ns:
                self.waiting[stamp_ns] = None
                self.waiting.move_to_end(stamp_ns)
            else:
                self.outcomes.drop("not_kept_any_more", f"frame at stamp {stamp_ns} is not kept (any more)")
        while len(self.waiting) > MAX_WAITING_REQUESTS:
            oldest, _ = self.waiting.popitem(last=False)
            self.outcomes.drop("never_came", f"request for stamp {oldest} pushed out by newer ones")
        return self._ready()

    def _ready(self) -> list[ServedFrame]:
        """Answer the waiting requests whose frame is ready; drop those whose features will not come."""
        served = []
        for stamp_ns in list(self.waiting):
            if stamp_ns in self.store:
                has_depth = self.store.depths is None or stamp_ns in self.store.depths
                if not self.depth_wait.ready(stamp_ns, has_depth):
                    continue
                del self.waiting[stamp_ns]
                served.append(self._frame(stamp_ns))
            elif self.newest_ns is not None and self.newest_ns - stamp_ns > self.wait_ns:
                del self.waiting[stamp_ns]
                self.outcomes.drop("never_came", f"no features of the frame at stamp {stamp_ns} came")
        for _ in served:
            self.outcomes.ok("served")
        return served

    def _frame(self, stamp_ns: int) -> ServedFrame:
        features = self.store.get(stamp_ns)
        assert features is not None, "only stored frames are served"
        return ServedFrame(stamp_ns, features, self.store.depths_of(stamp_ns), self._image_sizes.get(stamp_ns))

    def _forget_sizes(self) -> None:
        """Image sizes only of the frames still kept (a bound as the store's)."""
        if len(self._image_sizes) > 2 * len(self.store) + 100:
            self._image_sizes = {stamp: size for stamp, size in self._image_sizes.items() if stamp in self.store}
