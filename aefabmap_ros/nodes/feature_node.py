"""feature_node: ``image`` (Image) and ``<image>/compressed`` (CompressedImage) -> ``aefabmap/features``.

The compressed topic follows image_transport's convention: it is the *resolved* image topic plus
``/compressed``, so remapping ``image:=/camera/image_raw`` moves it to ``/camera/image_raw/compressed``;
a frame that arrives on both is processed once.

Which frames are processed: ``detection_rate_hz`` picks frames by their stamps (at most that many a
second; the others are skipped, counted as ``skipped_detection_rate``), the same frames in a replay as
live. With ``drop_when_busy`` (a live camera) a frame that arrives while the previous one still waits
for extraction replaces it (``dropped_busy``), so no queue builds up and the delay from image to
result stays bounded; without it (a lossless replay) every frame taken is processed, in order. Every
frame not processed is announced on ``aefabmap/skipped_frames`` (``std_msgs/Header``: the frame's
stamp, ``frame_id`` the reason), so a lockstep replay is answered for it and a recording accounts for
every frame. ``image_qos`` connects to the camera's publisher, best effort or reliable
(nodes/sensor_inputs.py).

While anyone subscribes to ``aefabmap/frame_views`` (closure_view_node), each frame that got features is also
published there (``aefabmap_msgs/FrameView``): its features and a small JPEG of it (``thumbnail_width``
pixels wide), made here where the image is decoded already, so a viewer takes one small message a frame and
never a camera image. Nobody subscribed, nothing is made.
"""

from __future__ import annotations

import time
from functools import partial
from typing import Any

from aefabmap_msgs.msg import Features, FrameView
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from aefabmap_ros.errors import AefabmapError, ConfigError, ImageTooLargeError
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.io.image_messages import image_message_to_gray
from aefabmap_ros.model.parts import load_feature_config
from aefabmap_ros.nodes.common import (
    DropCounter,
    declare_config,
    declare_parameter,
    node_callback,
    pipeline_qos,
    run_node,
)
from aefabmap_ros.nodes.frame_gate import DetectionRate, FrameHandOff
from aefabmap_ros.nodes.launch_table import FRAME_VIEWS_TOPIC, compressed_topic
from aefabmap_ros.nodes.messages import features_to_message, header_stamp_problem
from aefabmap_ros.nodes.sensor_inputs import SensorInput, check_sensor_qos
from aefabmap_ros.stamps import TransportDeduplicator, stamp_to_ns
from aefabmap_ros.visualization.match_picture import make_thumbnail


class FeatureNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("feature_node", **node_kwargs)
        model_dir = declare_parameter(
            self, "model_dir", "",
            "Model directory; when set, its feature settings are used so features match the vocabulary "
            "(the feature parameters below are then ignored).",
        )
        qos_kind = check_sensor_qos(declare_parameter(
            self, "image_qos", "auto",
            "QoS of the image subscriptions: auto (reliable, moving to best effort once a publisher offers only "
            "that, as camera drivers do), best_effort (= sensor_data) or reliable.",
        ), "image_qos")
        drop_when_busy = declare_parameter(
            self, "drop_when_busy", True,
            "A frame arriving while the previous one still waits for extraction replaces it (counted, never "
            "queued; a live camera). false: every frame taken is processed, in order (a lossless replay).",
        )
        detection_rate_hz = declare_parameter(
            self, "detection_rate_hz", 10.0,
            "Process at most about this many frames a second, chosen by their stamps (0 = every frame); the "
            "others are skipped and counted.",
        )
        if not detection_rate_hz >= 0:
            raise ConfigError(f"feature_node: parameter detection_rate_hz={detection_rate_hz} must be >= 0")
        depth = declare_parameter(self, "queue_depth", 10, "Queue depth of subscriptions and publications.")
        subscribe_compressed = declare_parameter(
            self, "subscribe_compressed", True,
            "Also subscribe to <image topic>/compressed (sensor_msgs/CompressedImage, image_transport's name); "
            "a frame arriving on both is processed once.",
        )
        self.max_image_pixels = declare_parameter(
            self, "max_image_pixels", 25_000_000,
            "Refuse images with more pixels than this, before decoding them (0 = no bound); 25 MP: above 4K.",
        )
        if self.max_image_pixels < 0:
            raise ConfigError(f"feature_node: parameter max_image_pixels={self.max_image_pixels} must be >= 0")
        self.thumbnail_width = _declare_thumbnail_width(self)
        self.frame_views_cpu_s = 0.0  # what the frame views cost this node: the live view's share of it
        parameter_config = declare_config(self, FeatureConfig)
        self.config = load_feature_config(model_dir) if model_dir else parameter_config  # not the vocabulary
        self.counter = DropCounter(self)
        self.publisher = self.create_publisher(Features, "aefabmap/features", pipeline_qos(depth))
        self.frame_view_publisher = self.create_publisher(FrameView, FRAME_VIEWS_TOPIC, pipeline_qos(depth))
        self.skipped_publisher = self.create_publisher(Header, "aefabmap/skipped_frames", pipeline_qos(max(depth, 100)))
        self.transports = TransportDeduplicator()
        self.detection_rate = DetectionRate(detection_rate_hz)
        # drop_when_busy: extraction in a worker that takes the newest frame; otherwise in the callback.
        self.frames: FrameHandOff[Any] = FrameHandOff(self._on_image, "feature_worker", newest_only=drop_when_busy,
                                                      on_replaced=partial(self._announce_skipped, reason="busy"))
        without = "no frame is processed"
        self.inputs = [SensorInput(self, Image, "image", partial(self._on_frame, transport="raw"), policy=qos_kind,
                                   depth=depth, counter=self.counter, without_it=without)]
        if subscribe_compressed:
            self.inputs.append(SensorInput(
                self, CompressedImage, compressed_topic(self.resolve_topic_name("image")),
                partial(self._on_frame, transport="compressed"), policy=qos_kind, depth=depth, counter=self.counter,
                without_it=without, silent_after_s=float("inf")))  # raw or compressed: one of them is enough
        rate = f"at most {detection_rate_hz:g} frames/s" if detection_rate_hz else "every frame"
        self.get_logger().info(f"extracting {self.config.type} features (max {self.config.max_features} per image), "
                               f"{rate}{', dropping frames while busy' if drop_when_busy else ''}")

    @node_callback
    def _on_frame(self, message: Any, transport: str = "raw") -> None:
        """A frame from one transport: skipped if the other brought it already; else extracted now (bag
        replay), or handed to the worker (live camera), replacing -- and dropping -- one still waiting."""
        problem = header_stamp_problem(message.header, "image")
        if problem is not None:  # its features would carry it on, to be refused downstream: refused at the door
            self.counter.drop("bad_stamp", problem)
            return
        stamp_ns = stamp_to_ns(message.header.stamp)
        if self.transports.is_duplicate(stamp_ns, transport):
            self.counter.ok(f"skipped_{transport}_copies")  # the other transport brought this frame already
            return
        if not self.detection_rate.take(stamp_ns):
            self.counter.ok("skipped_detection_rate")
            self._announce_skipped(message, reason="detection_rate")
            return
        if not self.frames.submit(message):
            self.counter.drop("busy", "a newer frame arrived before feature extraction took the previous one")

    def _announce_skipped(self, message: Any, reason: str) -> None:
        """The frame's stamp on aefabmap/skipped_frames: it will have no features, posterior or closure."""
        self.skipped_publisher.publish(Header(stamp=message.header.stamp, frame_id=reason))

    def destroy_node(self) -> None:
        self.frames.stop()
        super().destroy_node()

    @node_callback
    def _on_image(self, message: Any) -> None:
        try:
            gray = image_message_to_gray(message, self.max_image_pixels)
            features = extract_features(gray, self.config)
        except ImageTooLargeError as exc:
            self.counter.drop("image_too_large", str(exc))
            return
        except AefabmapError as exc:
            self.counter.drop("bad_image", str(exc))
            return
        if len(features.descriptors) == 0:
            self.counter.ok("images_without_features")  # still published: the frame keeps its place
        features_message = features_to_message(features, message.header, (gray.shape[1], gray.shape[0]))
        self.publisher.publish(features_message)
        self.counter.ok()
        if self.frame_view_publisher.get_subscription_count() > 0:
            self._publish_frame_view(features_message, gray)

    def _publish_frame_view(self, features: Features, gray: Any) -> None:
        started = time.thread_time()
        thumbnail = make_thumbnail(gray, self.thumbnail_width)
        self.frame_view_publisher.publish(FrameView(features=features, thumbnail_jpeg=thumbnail))
        self.frame_views_cpu_s += time.thread_time() - started
        self.counter.ok("frame_views")

    def close(self) -> bool:
        self.frames.stop()  # the frame in hand is finished first (one still waiting is not), so counts are final
        inputs = "; ".join(sensor_input.summary() for sensor_input in self.inputs)
        self.get_logger().info(f"feature_node: {self.counter.summary()}; {inputs}; frame views took "
                               f"{self.frame_views_cpu_s:.2f} s of CPU")
        return True


def _declare_thumbnail_width(node: Node) -> int:
    width: int = declare_parameter(
        node, "thumbnail_width", 320,
        f"Width in pixels of the JPEG thumbnails on {FRAME_VIEWS_TOPIC} (made only while subscribed).")
    if width <= 0:
        raise ConfigError(f"feature_node: parameter thumbnail_width={width} must be > 0")
    return width


def main(args: list[str] | None = None) -> int:
    return run_node(FeatureNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
