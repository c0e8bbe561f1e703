"""feature_node: ``image`` (Image, optionally ``image/compressed``) -> ``aefabmap/features``."""

from __future__ import annotations

from typing import Any

from aefabmap_msgs.msg import Features
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from aefabmap_ros.core.errors import AefabmapError, ConfigError, ImageTooLargeError
from aefabmap_ros.core.features import FeatureConfig, extract_features
from aefabmap_ros.core.model import load_model
from aefabmap_ros.io.image_messages import image_message_to_gray
from aefabmap_ros.io.messages import features_to_message
from aefabmap_ros.nodes.common import (
    DropCounter,
    declare_config,
    declare_parameter,
    image_qos,
    node_callback,
    pipeline_qos,
    run_node,
)


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
            self, "subscribe_compressed", False, "Also subscribe to image/compressed (sensor_msgs/CompressedImage)."
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
        self.create_subscription(Image, "image", self._on_image, image_qos(qos_kind, depth))
        if subscribe_compressed:
            self.create_subscription(CompressedImage, "image/compressed", self._on_image, image_qos(qos_kind, depth))
        self.get_logger().info(f"extracting {self.config.type} features (max {self.config.max_features} per image)")

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
        self.get_logger().info(f"feature_node: {self.counter.summary()}")
        return True


def main(args: list[str] | None = None) -> int:
    return run_node(FeatureNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
