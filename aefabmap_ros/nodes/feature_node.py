"""feature_node: ``image`` (Image) and ``<image>/compressed`` (CompressedImage) -> ``aefabmap/features``.

The compressed topic follows image_transport's convention: it is the *resolved* image topic plus
``/compressed``, so remapping ``image:=/camera/image_raw`` moves it to ``/camera/image_raw/compressed``.
"""

from __future__ import annotations

from functools import partial
from typing import Any

from aefabmap_msgs.msg import Features
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from aefabmap_ros.core.errors import AefabmapError
from aefabmap_ros.core.features import FeatureConfig, extract_features
from aefabmap_ros.core.model import load_model
from aefabmap_ros.core.stamps import TransportDeduplicator, stamp_to_ns
from aefabmap_ros.io.image_messages import image_message_to_gray
from aefabmap_ros.io.messages import features_to_message
from aefabmap_ros.nodes.common import DropCounter, declare_config, declare_parameter, image_qos, pipeline_qos, run_node


class FeatureNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("feature_node", **node_kwargs)
        model_dir = declare_parameter(
            self, "model_dir", "",
            "Model directory; when set, its feature settings are used so features match the vocabulary "
            "(the feature parameters below are then ignored).",
        )
        qos_kind = declare_parameter(self, "image_qos", "sensor_data",
                                     "QoS of the image subscription: sensor_data (cameras) or reliable (bag replay).")
        depth = declare_parameter(self, "queue_depth", 10, "Queue depth of subscriptions and publications.")
        subscribe_compressed = declare_parameter(
            self, "subscribe_compressed", True,
            "Also subscribe to <image topic>/compressed (sensor_msgs/CompressedImage, image_transport's name); "
            "a frame arriving on both is processed once.",
        )
        parameter_config = declare_config(self, FeatureConfig)
        self.config = load_model(model_dir).feature_config if model_dir else parameter_config
        self.counter = DropCounter(self)
        self.publisher = self.create_publisher(Features, "aefabmap/features", pipeline_qos(depth))
        self.transports = TransportDeduplicator()
        self.create_subscription(Image, "image", partial(self._on_image, transport="raw"), image_qos(qos_kind, depth))
        if subscribe_compressed:
            self.create_subscription(CompressedImage, compressed_topic(self.resolve_topic_name("image")),
                                     partial(self._on_image, transport="compressed"), image_qos(qos_kind, depth))
        self.get_logger().info(f"extracting {self.config.type} features (max {self.config.max_features} per image)")

    def _on_image(self, message: Any, transport: str = "raw") -> None:
        if self.transports.is_duplicate(stamp_to_ns(message.header.stamp), transport):
            self.counter.ok(f"skipped_{transport}_copies")  # the other transport brought this frame already
            return
        try:
            gray = image_message_to_gray(message)
            features = extract_features(gray, self.config)
        except AefabmapError as exc:
            self.counter.drop("bad_image", str(exc))
            return
        if len(features.descriptors) == 0:
            self.counter.ok("images_without_features")  # still published: the frame keeps its place
        self.publisher.publish(features_to_message(features, message.header, (gray.shape[1], gray.shape[0])))
        self.counter.ok()

    def close(self) -> None:
        self.get_logger().info(f"feature_node: {self.counter.summary()}")


def compressed_topic(image_topic: str) -> str:
    """image_transport's compressed topic of a resolved image topic: ``/cam/image`` -> ``/cam/image/compressed``."""
    return f"{image_topic.rstrip('/')}/compressed"


def main(args: list[str] | None = None) -> int:
    return run_node(FeatureNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
