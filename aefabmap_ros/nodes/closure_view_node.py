"""closure_view_node: each loop closure as a picture, drawn only while someone watches.

Keeps a small JPEG thumbnail and the features of every frame that got features (``image`` +
``aefabmap/features``, by image stamp, bounded by bytes: visualization/closure_album.py). Publishes
``sensor_msgs/CompressedImage`` pictures of the query beside the matched place with the verifier's
matches (green lines: inliers of one fundamental matrix; red dots: matches that do not fit):

- ``closure_view/closures``: every closure on ``loop_closures``;
- ``closure_view/refused``: every FAB-MAP candidate on ``loop_closure_candidates`` the verifier refused (no
  closure of its query, while one of a later query came, or none at all within ``refused_timeout_s``:
  visualization/candidates.py), under a red banner.

Nothing is matched or drawn for a topic nobody subscribes to (its subscription count is looked at first).
Bad input (an undecodable image, malformed features, any exception) is counted by name and dropped.
"""

from __future__ import annotations

import time
from typing import Any

from aefabmap_msgs.msg import Features, LoopClosure
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from aefabmap_ros.io.image_messages import image_message_to_gray
from aefabmap_ros.nodes.common import (
    RESULT_QOS,
    DropCounter,
    declare_config,
    declare_parameter,
    node_callback,
    pipeline_qos,
    run_node,
)
from aefabmap_ros.nodes.messages import message_to_features, time_from_ns
from aefabmap_ros.nodes.sensor_inputs import SensorInput
from aefabmap_ros.nodes.view_messages import jpeg_message
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.visualization.candidates import Candidate, CandidateWatch
from aefabmap_ros.visualization.closure_album import AlbumConfig, ClosureAlbum

CLOSURE_PICTURES_TOPIC = "closure_view/closures"
REFUSED_PICTURES_TOPIC = "closure_view/refused"
RETRY_PERIOD_S = 0.1
TIMEOUT_CHECK_PERIOD_S = 1.0  # refused by timeout: only when the verifier published nothing for refused_timeout_s
# A closure can arrive before its query's image reached this node (another process, another queue).
WAIT_FOR_FRAMES_S = 3.0
MAX_IMAGE_PIXELS = 25_000_000  # feature_node's default bound: larger images are refused before decoding


class ClosureViewNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("closure_view_node", **node_kwargs)
        album_config = declare_config(self, AlbumConfig)
        self.album = ClosureAlbum(album_config, declare_config(self, VerificationConfig))
        timeout_s = declare_parameter(
            self, "refused_timeout_s", 60.0,
            "A candidate whose query reached no closure, while no later query's closure came either, is taken as "
            "refused after this long (the verifier may run tens of seconds behind a lockstep replay).")
        self.watch = CandidateWatch(timeout_s)
        self.counter = DropCounter(self)
        self.closure_publisher = self.create_publisher(CompressedImage, CLOSURE_PICTURES_TOPIC, RESULT_QOS)
        self.refused_publisher = self.create_publisher(CompressedImage, REFUSED_PICTURES_TOPIC, RESULT_QOS)
        # Closures first: of the callbacks ready together, rclpy's executor runs the earliest created first, so a
        # closure's picture does not wait behind a queue of images. Plain subscriptions (no lost-message events):
        # each event is one more entity in every executor round's wait set, the node's main cost when idle.
        self.create_subscription(LoopClosure, "loop_closures", self._on_closure, RESULT_QOS)
        self.create_subscription(LoopClosure, "loop_closure_candidates", self._on_candidate, RESULT_QOS)
        self.create_subscription(Features, "aefabmap/features", self._on_features, pipeline_qos(100))
        self.image_input = SensorInput(self, Image, "image", self._on_image, policy="auto", depth=10,
                                       counter=self.counter, without_it="closures have no pictures")
        self._waiting: list[tuple[Candidate, bool, float]] = []  # (what, refused, give up at) frames not yet here
        # Both timers run only while there is something to do: every wake-up of the executor costs.
        self.retry_timer = self.create_timer(RETRY_PERIOD_S, self._on_retry)
        self.retry_timer.cancel()
        self.timeout_timer = self.create_timer(TIMEOUT_CHECK_PERIOD_S, self._on_timeout_check)
        self.timeout_timer.cancel()
        self.get_logger().info(f"closure pictures on {CLOSURE_PICTURES_TOPIC} and {REFUSED_PICTURES_TOPIC} "
                               "(drawn only while subscribed)")

    @node_callback
    def _on_image(self, message: Image) -> None:
        self.album.add_image(stamp_to_ns(message.header.stamp), image_message_to_gray(message, MAX_IMAGE_PIXELS))

    @node_callback
    def _on_features(self, message: Features) -> None:
        self.album.add_features(stamp_to_ns(message.header.stamp), message_to_features(message))

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
        if refused and self.refused_publisher.get_subscription_count() > 0:
            for candidate in refused:
                self._draw(candidate, refused=True, give_up_at=now + WAIT_FOR_FRAMES_S)

    def _draw(self, candidate: Candidate, refused: bool, give_up_at: float) -> None:
        what = "REFUSED candidate" if refused else "closure"
        caption = (f"{what}: query {candidate.query_id} -> place {candidate.place_id}  "
                   f"p={candidate.probability:.3f}")
        picture = self.album.picture(candidate.query_ns, candidate.place_ns, caption, refused)
        if picture is None:
            if time.monotonic() < give_up_at:
                self._waiting.append((candidate, refused, give_up_at))
                if self.retry_timer.is_canceled():
                    self.retry_timer.reset()
            else:
                self.counter.drop("frames_not_kept", f"no thumbnail or features of query {candidate.query_id} or "
                                  "its place: no picture (image topic silent, or evicted by the byte bounds)")
            return
        message = jpeg_message(picture.jpeg, time_from_ns(candidate.query_ns), "closure_view")
        (self.refused_publisher if refused else self.closure_publisher).publish(message)
        self.counter.ok("refused_pictures" if refused else "closure_pictures")

    def close(self) -> bool:
        self.get_logger().info(f"closure_view_node: {self.counter.summary()}; {self.image_input.summary()}")
        return True


def _candidate(message: LoopClosure) -> Candidate:
    return Candidate(stamp_to_ns(message.header.stamp), stamp_to_ns(message.matched_stamp), int(message.query_id),
                     int(message.matched_place_id), float(message.probability))


def main(args: list[str] | None = None) -> int:
    return run_node(ClosureViewNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
