"""quantizer_node: ``aefabmap/features`` -> ``aefabmap/words`` with the model's vocabulary.

With ``drop_when_busy`` (the default, for a live camera) quantization runs in a worker that takes the
newest features message: one that arrives while the previous one still waits replaces it (counted
as ``dropped_busy``). feature_node drops camera frames at its door too, but when quantization is
the slower stage (the paper's autoencoder network behind a fast feature extractor) the frames
feature_node passes would otherwise queue here and the delay from image to posterior would grow
without bound. With it off (bag replay without lockstep) every message is quantized, in order.

Quantizing is numpy (matrix products and an argmin, ``vocabulary/kmeans.py``, ``vocabulary/autoencoder.py``):
the node imports neither torch nor faiss nor scikit-learn, which only training needs (docs/runtime.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from aefabmap_msgs.msg import BagOfWords, Features
from rclpy.node import Node
from threadpoolctl import threadpool_limits

from aefabmap_ros.errors import AefabmapError, ConfigError
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.nodes.common import (
    DropCounter,
    counted_subscription,
    declare_parameter,
    node_callback,
    pipeline_qos,
    report_when_connected,
    run_node,
)
from aefabmap_ros.nodes.frame_gate import FrameHandOff
from aefabmap_ros.nodes.messages import bag_of_words_to_message, message_to_features
from aefabmap_ros.vocabulary.base import bag_of_words


class QuantizerNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("quantizer_node", **node_kwargs)
        model_dir = declare_parameter(self, "model_dir", "", "Model directory (from aefabmap_train). Required.")
        depth = declare_parameter(self, "queue_depth", 100, "Queue depth of subscriptions and publications.")
        blas_threads = declare_parameter(
            self, "blas_threads", 0,
            "Threads of the BLAS pool the quantizer's matrix products run on (0 = the library's default, which "
            "follows OPENBLAS_NUM_THREADS; aefabmap_launch sets that to this process's share of the cores).",
        )
        drop_when_busy = declare_parameter(
            self, "drop_when_busy", True,
            "Quantize only the newest features message: one arriving while quantization is busy replaces "
            "the one waiting (counted, never queued; a live camera). false: every message, in order (bag replay).",
        )
        if blas_threads < 0:
            raise ConfigError(f"quantizer_node: parameter blas_threads={blas_threads} must be >= 0")
        if blas_threads > 0:
            threadpool_limits(blas_threads, user_api="blas")  # for the process: the node's one pool
        if not model_dir:
            raise ConfigError("quantizer_node: parameter model_dir is required (a directory made by aefabmap_train)")
        model = load_model(model_dir)  # at start-up, never in a callback
        self.quantizer = model.quantizer
        self.vocabulary_id = model.vocabulary_id
        self.descriptor_type = model.feature_config.type
        self.counter = DropCounter(self)
        self.publisher = self.create_publisher(BagOfWords, "aefabmap/words", pipeline_qos(depth))
        self.frames: FrameHandOff[Any] = FrameHandOff(self._quantize, "quantizer_worker", newest_only=drop_when_busy)
        features = counted_subscription(self, Features, "aefabmap/features", self._on_features, pipeline_qos(depth),
                                        self.counter)
        report_when_connected(self, features, "features")
        self.get_logger().info(
            f"quantizing {self.descriptor_type} features into {self.quantizer.size} {self.quantizer.kind} words "
            f"(vocabulary {self.vocabulary_id})"
        )

    @node_callback
    def _on_features(self, message: Features) -> None:
        """Quantize now, or hand over to the worker, replacing -- and dropping -- a message still waiting."""
        if not self.frames.submit(message):
            self.counter.drop("busy", "a newer features message arrived before quantization took the previous one")

    @node_callback
    def _quantize(self, message: Features) -> None:
        if message.descriptor_type != self.descriptor_type:
            self.counter.drop(
                "wrong_descriptor_type",
                f"got {message.descriptor_type!r} features, the vocabulary is for {self.descriptor_type!r}",
            )
            return
        try:
            features = message_to_features(message)
            keypoint_words = self.quantizer.quantize(features.descriptors)
            word_ids, counts = bag_of_words(keypoint_words, self.quantizer.size)
        except AefabmapError as exc:
            self.counter.drop("bad_features", str(exc))
            return
        self.publisher.publish(bag_of_words_to_message(
            message.header, self.vocabulary_id, self.quantizer.size, word_ids, counts,
            keypoint_words.astype(np.int32),
        ))
        self.counter.ok()

    def destroy_node(self) -> None:
        self.frames.stop()
        super().destroy_node()

    def close(self) -> bool:
        self.frames.stop()  # the message in hand is finished first, so the counts are final
        self.get_logger().info(f"quantizer_node: {self.counter.summary()}")
        return True


def main(args: list[str] | None = None) -> int:
    return run_node(QuantizerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
