"""closure_view_node: each loop closure as a picture, drawn only while someone watches.

Keeps every frame that got features as feature_node sends it on ``aefabmap/frame_views`` (its features and a
JPEG thumbnail, sent only while this node subscribes), serialized, by image stamp, bounded by bytes
(visualization/closure_album.py): a place seen before a client connected has its picture too, and a viewer
nobody watches decodes nothing. Publishes ``sensor_msgs/CompressedImage`` pictures of the query beside the
matched place with the verifier's matches (green lines: inliers of one fundamental matrix; red dots: matches
that do not fit):

- ``closure_view/closures``: every closure on ``loop_closures``;
- ``closure_view/refused``: FAB-MAP candidates on ``loop_closure_candidates`` the verifier refused (no closure
  of its query, while one of a later query came, or none at all within ``refused_timeout_s``:
  visualization/candidates.py), under a red banner, at most ``max_refused_pictures_per_s``: they are
  diagnostics, and drawing them (matching the pair again, RANSAC, a JPEG: ~5 ms each on an idle core, far
  more when the suite keeps both cores busy) must not take a core from the verifier.

Nothing is matched or drawn for a topic nobody subscribes to (its subscription count is looked at first).
Bad input (a frame whose features or thumbnail do not decode, any exception) is counted by name and dropped.
"""

from __future__ import annotations

import time
from typing import Any

from aefabmap_msgs.msg import FrameView, LoopClosure
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from aefabmap_ros.errors import DataError
from aefabmap_ros.nodes.common import (
    RESULT_QOS,
    DropCounter,
    declare_config,
    declare_parameter,
    node_callback,
    pipeline_qos,
    report_when_connected,
    run_node,
)
from aefabmap_ros.nodes.launch_table import CLOSURE_PICTURES_TOPIC, FRAME_VIEWS_TOPIC, REFUSED_PICTURES_TOPIC
from aefabmap_ros.nodes.messages import header_stamp_problem, message_to_features, time_from_ns
from aefabmap_ros.nodes.view_messages import jpeg_message
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.visualization.candidates import Candidate, CandidateWatch
from aefabmap_ros.visualization.closure_album import AlbumConfig, ClosureAlbum, ViewFrame

RETRY_PERIOD_S = 0.1
TIMEOUT_CHECK_PERIOD_S = 1.0  # refused by timeout: only when the verifier published nothing for refused_timeout_s
# A closure can arrive before its query's image reached this node (another process, another queue).
WAIT_FOR_FRAMES_S = 3.0
NO_PUBLISHER_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
NO_SUBSCRIPTION_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)


class ClosureViewNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        # Its parameters are read once, at start-up, so no parameter services (ros2 param does not reach it), and
        # no QoS-event handlers on its topics, all of which are the suite's own: each is one more entity for
        # rclpy's executor to gather before every wait, about a fifth of what this node costs nobody watching.
        super().__init__("closure_view_node", start_parameter_services=False, **node_kwargs)
        album_config = declare_config(self, AlbumConfig)
        self.album = ClosureAlbum(album_config, declare_config(self, VerificationConfig), load_frame)
        timeout_s = declare_parameter(
            self, "refused_timeout_s", 60.0,
            "A candidate whose query reached no closure, while no later query's closure came either, is taken as "
            "refused after this long (the verifier may run tens of seconds behind a lockstep replay).")
        self.watch = CandidateWatch(timeout_s)
        refused_rate = declare_parameter(
            self, "max_refused_pictures_per_s", 2.0,
            "Draw at most this many refused-candidate pictures a second (the others are counted, not drawn; 0 = "
            "none); closure pictures are never limited.")
        self.refused_interval_s = 1.0 / refused_rate if refused_rate > 0 else float("inf")
        self._last_refused_at = -float("inf")
        self.counter = DropCounter(self)
        self.closure_publisher = self.create_publisher(CompressedImage, CLOSURE_PICTURES_TOPIC, RESULT_QOS,
                                                       event_callbacks=NO_PUBLISHER_EVENTS)
        self.refused_publisher = self.create_publisher(CompressedImage, REFUSED_PICTURES_TOPIC, RESULT_QOS,
                                                       event_callbacks=NO_PUBLISHER_EVENTS)
        # Closures first: of the callbacks ready together, rclpy's executor runs the earliest created first, so a
        # closure's picture does not wait behind a queue of frames.
        self.create_subscription(LoopClosure, "loop_closures", self._on_closure, RESULT_QOS,
                                 event_callbacks=NO_SUBSCRIPTION_EVENTS)
        self.create_subscription(LoopClosure, "loop_closure_candidates", self._on_candidate, RESULT_QOS,
                                 event_callbacks=NO_SUBSCRIPTION_EVENTS)
        # Serialized: a frame is decoded only if a picture ever needs it.
        frames = self.create_subscription(FrameView, FRAME_VIEWS_TOPIC, self._on_frame, pipeline_qos(100), raw=True,
                                          event_callbacks=NO_SUBSCRIPTION_EVENTS)
        report_when_connected(self, frames, "frame views")
        self._waiting: list[tuple[Candidate, bool, float]] = []  # (what, refused, give up at) frames not yet here
        # Both timers run only while there is something to do: every wake-up of the executor costs.
        self.retry_timer = self.create_timer(RETRY_PERIOD_S, self._on_retry)
        self.retry_timer.cancel()
        self.timeout_timer = self.create_timer(TIMEOUT_CHECK_PERIOD_S, self._on_timeout_check)
        self.timeout_timer.cancel()
        self.get_logger().info(f"closure pictures on {CLOSURE_PICTURES_TOPIC} and {REFUSED_PICTURES_TOPIC} "
                               "(drawn only while subscribed)")

    @node_callback
    def _on_frame(self, serialized: bytes) -> None:
        # A message's CDR begins with its first field, here the features' header: read alone, it costs ~20 us.
        header = deserialize_message(serialized, Header)
        problem = header_stamp_problem(header, "frame view")
        if problem is not None:
            self.counter.drop("bad_stamp", problem)
            return
        self.album.add_frame(stamp_to_ns(header.stamp), serialized)

    @node_callback
    def _on_closure(self, message: LoopClosure) -> None:
        candidate = _candidate(message)
        self.watch.verified(candidate.query_ns)
        if self.closure_publisher.get_subscription_count() > 0:
            self._draw(candidate, refused=False, give_up_at=time.monotonic() + WAIT_FOR_FRAMES_S)
        self._draw_refused()

    @node_callback
    def _on_candidate(self, message: LoopClosure) -> None:
        self.watch.add(_candidate(message), time.monotonic())
        if self.timeout_timer.is_canceled():
            self.timeout_timer.reset()

    @node_callback
    def _on_timeout_check(self) -> None:
        self._draw_refused()
        if not len(self.watch):
            self.timeout_timer.cancel()

    @node_callback
    def _on_retry(self) -> None:
        waiting, self._waiting = self._waiting, []
        for candidate, was_refused, give_up_at in waiting:
            self._draw(candidate, was_refused, give_up_at)
        if not self._waiting:
            self.retry_timer.cancel()

    def _draw_refused(self) -> None:
        now = time.monotonic()
        refused = self.watch.refused(now)
        if not refused or self.refused_publisher.get_subscription_count() == 0:
            return
        for candidate in refused:
            if now - self._last_refused_at < self.refused_interval_s:
                self.counter.ok("refused_pictures_over_rate")
                continue
            self._last_refused_at = now
            self._draw(candidate, refused=True, give_up_at=now + WAIT_FOR_FRAMES_S)

    def _draw(self, candidate: Candidate, refused: bool, give_up_at: float) -> None:
        what = "REFUSED candidate" if refused else "closure"
        caption = (f"{what}: query {candidate.query_id} -> place {candidate.place_id}  "
                   f"p={candidate.probability:.3f}")
        try:
            picture = self.album.picture(candidate.query_ns, candidate.place_ns, caption, refused)
        except DataError as exc:  # a frame's features do not validate, or its thumbnail is not a JPEG
            self.counter.drop("bad_frame", f"no picture of query {candidate.query_id}: {exc}")
            return
        if picture is None:
            if time.monotonic() < give_up_at:
                self._waiting.append((candidate, refused, give_up_at))
                if self.retry_timer.is_canceled():
                    self.retry_timer.reset()
            else:
                self.counter.drop("frames_not_kept", f"query {candidate.query_id} or its place not kept: no picture "
                                  f"({FRAME_VIEWS_TOPIC} silent, or the frame evicted by the byte bound)")
            return
        message = jpeg_message(picture.jpeg, time_from_ns(candidate.query_ns), "closure_view")
        (self.refused_publisher if refused else self.closure_publisher).publish(message)
        self.counter.ok("refused_pictures" if refused else "closure_pictures")

    def close(self) -> bool:
        frames = self.album.frames
        self.get_logger().info(f"closure_view_node: {self.counter.summary()}; kept {len(frames)} frames "
                               f"({frames.nbytes / 2**20:.1f} of {frames.max_bytes / 2**20:.0f} MiB)")
        return True


def _candidate(message: LoopClosure) -> Candidate:
    return Candidate(stamp_to_ns(message.header.stamp), stamp_to_ns(message.matched_stamp), int(message.query_id),
                     int(message.matched_place_id), float(message.probability))


def load_frame(serialized: bytes) -> ViewFrame:
    """A frame as feature_node published it, its features validated."""
    message = deserialize_message(serialized, FrameView)
    return ViewFrame(message_to_features(message.features), int(message.features.image_width),
                     bytes(message.thumbnail_jpeg))


def main(args: list[str] | None = None) -> int:
    return run_node(ClosureViewNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
