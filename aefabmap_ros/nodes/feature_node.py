"""feature_node: ``image`` (Image) and ``<image>/compressed`` (CompressedImage) -> ``aefabmap/features``.

The compressed topic follows image_transport's convention: it is the *resolved* image topic plus
``/compressed``, so remapping ``image:=/camera/image_raw`` moves it to ``/camera/image_raw/compressed``;
a frame that arrives on both is processed once.

With ``image_qos`` sensor_data (a live camera) frames are dropped at the door: the subscription
only hands the newest frame to a worker thread through a one-frame gate, a frame that arrives while
the previous one still waits replaces it (counted as ``dropped_busy``), so no queue builds up and
the delay from image to result stays bounded. With reliable QoS (bag replay) every frame is
processed, in order.
"""

from __future__ import annotations

from functools import partial
from typing import Any

from aefabmap_msgs.msg import Features
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from aefabmap_ros.errors import AefabmapError, ConfigError, ImageTooLargeError
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.io.image_messages import image_message_to_gray
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.nodes.common import (
    DropCounter,
    counted_subscription,
    declare_config,
    declare_parameter,
    image_qos,
    node_callback,
    pipeline_qos,
    run_node,
)
from aefabmap_ros.nodes.frame_gate import FrameHandOff
from aefabmap_ros.nodes.launch_table import compressed_topic
from aefabmap_ros.nodes.messages import features_to_message
from aefabmap_ros.stamps import TransportDeduplicator, stamp_to_ns


class FeatureNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("feature_node", **node_kwargs)
        model_dir = declare_parameter(
            self, "model_dir", "",
            "Model directory; when set, its feature settings are used so features match the vocabulary "
            "(the feature parameters below are then ignored).",
        )
        qos_kind = declare_parameter(
            self, "image_qos", "sensor_data",
            "QoS of the image subscription: sensor_data (cameras; frames arriving while busy are "
            "dropped, counted, never queued) or reliable (bag replay; every frame is processed).",
        )
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
        parameter_config = declare_config(self, FeatureConfig)
        self.config = load_model(model_dir).feature_config if model_dir else parameter_config
        self.counter = DropCounter(self)
        self.publisher = self.create_publisher(Features, "aefabmap/features", pipeline_qos(depth))
        self.transports = TransportDeduplicator()
        # sensor_data: extraction in a worker that takes the newest frame; reliable: in the callback.
        self.frames: FrameHandOff[Any] = FrameHandOff(self._on_image, "feature_worker",
                                                      newest_only=qos_kind == "sensor_data")
        counted_subscription(self, Image, "image", partial(self._on_frame, transport="raw"), image_qos(qos_kind, depth),
                             self.counter)
        if subscribe_compressed:
            counted_subscription(self, CompressedImage, compressed_topic(self.resolve_topic_name("image")),
                                 partial(self._on_frame, transport="compressed"), image_qos(qos_kind, depth),
                                 self.counter)
        self.get_logger().info(f"extracting {self.config.type} features (max {self.config.max_features} per image)")

    @node_callback
    def _on_frame(self, message: Any, transport: str = "raw") -> None:
        """A frame from one transport: skipped if the other brought it already; else extracted now (bag
        replay), or handed to the worker (live camera), replacing -- and dropping -- one still waiting."""
        if self.transports.is_duplicate(stamp_to_ns(message.header.stamp), transport):
            self.counter.ok(f"skipped_{transport}_copies")  # the other transport brought this frame already
            return
        if not self.frames.submit(message):
            self.counter.drop("busy", "a newer frame arrived before feature extraction took the previous one")

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
        self.publisher.publish(features_to_message(features, message.header, (gray.shape[1], gray.shape[0])))
        self.counter.ok()

    def close(self) -> bool:
        self.frames.stop()  # the frame in hand is finished first (one still waiting is not), so counts are final
        self.get_logger().info(f"feature_node: {self.counter.summary()}")
        return True


def main(args: list[str] | None = None) -> int:
    return run_node(FeatureNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
