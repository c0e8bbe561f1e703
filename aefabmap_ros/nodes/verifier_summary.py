"""verifier_node's reports: its start-up line, its shutdown summary, and how far behind the camera it is."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence

import numpy as np

from aefabmap_ros.nodes.sensor_inputs import SensorInput
from aefabmap_ros.nodes.verifier_parameters import VerifierParameters
from aefabmap_ros.verification.chain import POSTERIOR_HISTORY, LoopClosureChain


class FeatureClock:
    """When feature_node sent each recent frame's features (wall clock, as DDS stamps them): how far behind
    the camera the verifier is, the time they waited in its queue included (``max_lag_s``,
    ``drop_after_lag_s``), and each published closure's delay from its query's features."""

    def __init__(self, max_lag_s: float, drop_after_lag_s: float = 0.0) -> None:
        self.max_lag_s = max_lag_s
        self.drop_after_lag_s = drop_after_lag_s
        self._sent_ns: dict[int, int] = {}  # features stamp -> sent (wall clock ns)
        self.queue_wait_ns = 0  # of the newest features taken: how far behind the camera the verifier takes its input
        self.delays_s: deque[float] = deque(maxlen=10_000)

    def sent(self, stamp_ns: int, sent_ns: int | None) -> None:
        now_ns = time.time_ns()
        self._sent_ns[stamp_ns] = now_ns if sent_ns is None else sent_ns
        self.queue_wait_ns = max(0, now_ns - self._sent_ns[stamp_ns])
        while len(self._sent_ns) > POSTERIOR_HISTORY:
            del self._sent_ns[next(iter(self._sent_ns))]

    def behind(self, query_ns: int) -> bool:
        """More than max_lag_s since the query's features were sent: the verifier is behind the camera."""
        sent_ns = self._sent_ns.get(query_ns)
        return bool(self.max_lag_s) and sent_ns is not None and time.time_ns() - sent_ns > self.max_lag_s * 1e9

    def too_late(self, _query_ns: int) -> bool:
        """The newest features waited more than drop_after_lag_s in the queue: the verifier is that far behind
        the camera and drops detections until it catches up. Measured on its input, not on the query, so a query
        that waited for its depth image while the verifier kept up is still verified."""
        return bool(self.drop_after_lag_s) and self.queue_wait_ns > self.drop_after_lag_s * 1e9

    def published(self, query_ns: int) -> None:
        sent_ns = self._sent_ns.get(query_ns)
        if sent_ns is not None:
            self.delays_s.append((time.time_ns() - sent_ns) / 1e9)


def startup_summary(p: VerifierParameters) -> str:
    config = p.config
    metric_test = (f" or, with depth, >= {config.metric_min_inliers} PnP inliers (matches at ratio "
                   f"{config.metric_ratio:g}), {config.metric_min_view_overlap:.0%} view overlap and "
                   f"{config.metric_min_covisibility:.0%} covisibility"
                   if p.depth_topic and config.metric_min_inliers else "")
    fleet = (f"robots {', '.join(p.robots)}, each robot's frames asked for from its feature server, "
             if p.robots else "")
    return (f"verifying loop closures of {fleet}>= {config.min_inliers} fundamental-matrix inliers and "
            f"{config.min_inlier_ratio:.0%} of the keypoints{metric_test}, re-ranking the best {config.candidates} "
            "candidates, "
            f"tracking loops for {config.track_seconds:g} s, at most {p.max_frames} frames and "
            f"{p.max_store_bytes / 2**20:g} MiB kept, " + (f"closures checked against odometry on odom once it "
            f"arrives (waiting {p.odometry_wait_s:g} s for it)" if p.odometry_gate else "no odometry gate"))


def shutdown_summary(chain: LoopClosureChain, saved: bool, counters: str, delays_s: Sequence[float],
                     inputs: Sequence[SensorInput]) -> str:
    store = chain.store
    evicted = ", ".join(f"{count} {role.value}" for role, count in store.evicted.items())
    return (f"verifier_node: {len(store)} frames stored ({store.nbytes / 2**20:.1f} MiB"
            f"{'' if saved else ', NOT all saved'} of {store.max_bytes / 2**20:g} MiB; evicted {evicted}), "
            f"{len(chain.pending)} closures still waiting, {len(chain.odometry.waiting)} waiting for odometry; "
            f"{counters}; {delay_summary(delays_s)}; {chain.depth_wait.summary()}; "
            f"{chain.odometry.lateness_summary()}; "
            + ("; ".join(sensor_input.summary() for sensor_input in inputs) or "no sensor inputs"))


def delay_summary(delays_s: Sequence[float]) -> str:
    """From a query's features being sent to its closure going out: median, p95 and max."""
    if not delays_s:
        return "no closure published"
    p50, p95 = np.percentile(delays_s, [50, 95])
    return f"features -> published closure: median {p50:.3f} s, p95 {p95:.3f} s, max {max(delays_s):.3f} s"
