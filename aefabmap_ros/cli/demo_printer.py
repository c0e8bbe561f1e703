"""aefabmap_demo's live report: each published loop closure printed as it arrives and judged against the
ground truth, FAB-MAP's raw candidates and the posteriors counted, the image-to-closure latency measured."""

from __future__ import annotations

import struct
import threading
import time
from typing import Any

import numpy as np

from aefabmap_ros.cli.demo_backend import BackendCheck
from aefabmap_ros.evaluation.metrics import event_scores
from aefabmap_ros.nodes.launch_table import CANDIDATES_TOPIC, CLOSURES_TOPIC, POSTERIORS_TOPIC
from aefabmap_ros.stamps import stamp_to_ns


class ClosurePrinter:
    """Prints the published (verified) loop closures as they arrive, counts FAB-MAP's raw candidates
    and the posteriors (spun in a thread)."""

    def __init__(self, stamps_ns: np.ndarray, gt: np.ndarray, poses: np.ndarray | None = None,
                 frames_to_process: int | None = None) -> None:
        import rclpy
        from aefabmap_msgs.msg import LoopClosure, PlacePosterior
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Image

        self._rclpy = rclpy
        self._stamps = stamps_ns
        self._gt = gt
        self.posteriors = 0
        self._frames_to_process = len(stamps_ns) if frames_to_process is None else frames_to_process
        self.closures: list[tuple[int, int, bool]] = []  # /loop_closures: what a backend gets
        # Each closure's (query, matched) sessions as (robot, session number), in the order of ``closures``.
        self.closure_sessions: list[tuple[tuple[str, int], tuple[str, int]]] = []
        self.candidates: list[tuple[int, int, bool]] = []  # /loop_closure_candidates: FAB-MAP's raw closures
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("aefabmap_demo_printer", context=self.context)
        self.node.create_subscription(LoopClosure, CLOSURES_TOPIC, self._on_closure, 100)
        self.node.create_subscription(LoopClosure, CANDIDATES_TOPIC, self._on_candidate, 100)
        self.node.create_subscription(PlacePosterior, POSTERIORS_TOPIC, self._on_posterior, 100)
        # When each image went out (its stamp read from the serialized message: nothing is deserialized), for the
        # latency from image to /loop_closures.
        self.image_arrivals_ns: dict[int, int] = {}
        self.closure_latencies_s: list[float] = []
        self.posterior_latencies_s: list[float] = []  # the detection alone (features, words, FAB-MAP)
        self.node.create_subscription(Image, "image", self._on_image, qos_profile_sensor_data, raw=True)
        self.backend = BackendCheck(self.node, stamps_ns, poses) if poses is not None else None
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="demo-printer")
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.1)

    def _frame(self, stamp: Any) -> int:
        return int(np.searchsorted(self._stamps, stamp_to_ns(stamp)))

    # The middleware's own times (the publisher's clock when it sent, ours when the sample arrived; one machine,
    # one clock), not this printer's callback times: a busy printer would add its own queue to the figures.
    def _on_image(self, data: bytes, info: Any) -> None:
        self.image_arrivals_ns[serialized_header_stamp_ns(data)] = int(info["source_timestamp"])

    def _latency_s(self, message: Any, info: Any) -> float | None:
        sent_ns = self.image_arrivals_ns.get(stamp_to_ns(message.header.stamp))
        return None if sent_ns is None else (int(info["received_timestamp"]) - sent_ns) / 1e9

    def _on_posterior(self, message: Any, info: Any) -> None:
        latency = self._latency_s(message, info)
        if latency is not None:
            self.posterior_latencies_s.append(latency)
        self.posteriors += 1
        if self.posteriors % 50 == 0:
            print(f"    ... {self.posteriors}/{self._frames_to_process} images processed", flush=True)

    def _judged(self, message: Any) -> tuple[int, int, bool]:
        query, matched = self._frame(message.header.stamp), self._frame(message.matched_stamp)
        true = bool(self._gt[query, matched]) if query < len(self._gt) and matched < len(self._gt) else False
        return query, matched, true

    def _on_candidate(self, message: Any) -> None:
        self.candidates.append(self._judged(message))

    def _on_closure(self, message: Any, info: Any) -> None:
        latency = self._latency_s(message, info)
        if latency is not None:
            self.closure_latencies_s.append(latency)
        query, matched, true = self._judged(message)
        self.closures.append((query, matched, true))
        sessions = ((str(message.query_robot), int(message.query_session)),
                    (str(message.matched_robot), int(message.matched_session)))
        self.closure_sessions.append(sessions)
        if self.backend is not None:
            self.backend.on_closure(message, query, matched)
        verdict = "true revisit" if true else "NOT a revisit in the ground truth"
        checked = f"{message.inliers} inliers" if message.inliers >= 0 else "not verified"
        pose = ("metric pose" if message.translation_metric else "monocular pose") if message.pose_available \
            else "no pose"
        print(f"    loop closure: frame {query:4d} -> frame {matched:4d}  p={message.probability:.4f}  {checked}, "
              f"{pose}  ({verdict}){session_tag(*sessions)}", flush=True)

    def wait_until_quiet(self, idle_s: float, at_most_s: float) -> None:
        """Give the nodes time to finish the last frames: until nothing arrived for ``idle_s``."""
        deadline = time.monotonic() + at_most_s
        seen: tuple[int, int, int] | None = None
        while time.monotonic() < deadline:
            now = (self.posteriors, len(self.closures), len(self.candidates))
            if now == seen:
                return
            seen = now
            time.sleep(idle_s)

    def summary(self, min_gap: int) -> str:
        """Published closures, false ones and revisit events closed; the raw candidates for comparison."""
        in_range = [(q, m) for q, m, _ in self.closures if q < len(self._gt) and m < len(self._gt)]
        events = event_scores(in_range, self._gt, min_gap)
        false = sum(1 for *_, ok in self.closures if not ok)
        false_candidates = sum(1 for *_, ok in self.candidates if not ok)
        return (f"    {len(self.closures)} loop closures published on /{CLOSURES_TOPIC} (verified), {false} false; "
                f"{events.num_events_closed} of {events.num_events} revisit events closed\n"
                f"    {len(self.candidates)} raw FAB-MAP candidates on /{CANDIDATES_TOPIC}, {false_candidates} false; "
                f"{self.posteriors} posteriors\n    {latency_summary(self.closure_latencies_s)}\n"
                f"    {latency_summary(self.posterior_latencies_s, 'place_posteriors', 'posterior')}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


def session_tag(query: tuple[str, int], matched: tuple[str, int]) -> str:
    """'' for a closure of a map's only session; else '  [session 1 -> 0]'."""
    if query == matched == ("", 0):
        return ""
    return f"  [session {'/'.join(filter(None, (query[0], str(query[1]))))} -> " \
           f"{'/'.join(filter(None, (matched[0], str(matched[1]))))}]"


def latency_summary(latencies_s: list[float], topic: str = "loop_closures", what: str = "closure") -> str:
    """Image to ``topic``: median, p95 and max over the messages whose image was seen going out."""
    if not latencies_s:
        return f"latency image -> /{topic}: no {what} to time"
    p50, p95 = np.percentile(latencies_s, [50, 95])
    return (f"latency image -> /{topic} over {len(latencies_s)} {what}s: median {p50:.3f} s, p95 {p95:.3f} s, "
            f"max {max(latencies_s):.3f} s")


def serialized_header_stamp_ns(data: bytes) -> int:
    """The header stamp of a serialized message that starts with a std_msgs/Header (CDR: 4 bytes of
    encapsulation, then int32 sec and uint32 nanosec, little-endian when the encapsulation says so)."""
    order = "<" if data[1] == 1 else ">"
    sec, nanosec = struct.unpack_from(f"{order}iI", data, 4)
    return int(sec) * 1_000_000_000 + int(nanosec)
