"""verifier_node: ``loop_closures`` -> ``verified_loop_closures`` (geometric verification).

Keeps the features of recent frames (``aefabmap/features``, by image stamp). For every loop
closure from fabmap_node it matches the query image's features against the matched place's and
republishes the closure, with its ``inliers`` count filled in, when enough matches fit one
fundamental matrix (``min_inliers``); otherwise it is counted and logged as rejected. A SLAM
backend that cannot afford a false loop subscribes to ``verified_loop_closures`` instead of
``loop_closures``.

A closure can arrive before its query's features (separate topics): it waits, up to
``max_pending`` closures, until they come. A closure whose place is older than the store
(``max_stored_frames``) cannot be verified and is dropped. With ``store_dir`` the store is saved
to that folder (every ``save_period_s`` the frames added since the last save, as one more chunk
file, and on shutdown) and reloaded on start, so after a restart the places seen before it can
still be verified.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Any

from aefabmap_msgs.msg import Features, LoopClosure
from rclpy.node import Node

from aefabmap_ros.core.errors import AefabmapError, ConfigError
from aefabmap_ros.core.stamps import stamp_to_ns
from aefabmap_ros.core.verification import FeatureStore, FeatureStoreFolder, VerificationConfig, verify_pair
from aefabmap_ros.io.messages import message_to_features
from aefabmap_ros.nodes.common import (
    LOG_THROTTLE_S,
    RESULT_QOS,
    DropCounter,
    PeriodicSave,
    declare_config,
    declare_parameter,
    pipeline_qos,
    run_node,
)


class VerifierNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("verifier_node", **node_kwargs)
        depth = declare_parameter(self, "queue_depth", 100, "Queue depth of the features subscription.")
        max_frames = declare_parameter(
            self, "max_stored_frames", 20000,
            "Frames whose features are kept for verification (the oldest are forgotten first).",
        )
        max_features = declare_parameter(
            self, "max_stored_features", 500,
            "Strongest keypoints kept per frame (0 = all); ~128 KiB per frame of 500 SIFT features.",
        )
        self.max_pending = declare_parameter(
            self, "max_pending", 100, "Loop closures waiting for their query's features at most."
        )
        store_dir = declare_parameter(
            self, "store_dir", "", "Folder the feature store is saved to and reloaded from ('' = memory only)."
        )
        save_period_s = declare_parameter(
            self, "save_period_s", 10.0,
            "Save the frames added since the last save this often (seconds; 0 = only on shutdown).",
        )
        self.config = declare_config(self, VerificationConfig)
        if max_frames < 1 or max_features < 0 or self.max_pending < 1:
            raise ConfigError(f"verifier_node: max_stored_frames ({max_frames}) and max_pending "
                              f"({self.max_pending}) must be >= 1, max_stored_features ({max_features}) >= 0")
        self.store = FeatureStore(max_frames, max_features)
        self.store_folder = FeatureStoreFolder(Path(store_dir)) if store_dir else None
        if self.store_folder is not None:
            self.store_folder.load_into(self.store)  # a corrupt chunk stops start-up (ERROR), is not overwritten
            if len(self.store):
                self.get_logger().info(
                    f"reloaded the features of {len(self.store)} frames from {self.store_folder.folder}")
        self.pending: OrderedDict[int, LoopClosure] = OrderedDict()  # query stamp -> closure, oldest first
        self.counter = DropCounter(self)
        self.publisher = self.create_publisher(LoopClosure, "verified_loop_closures", RESULT_QOS)
        self.create_subscription(Features, "aefabmap/features", self._on_features, pipeline_qos(depth))
        self.create_subscription(LoopClosure, "loop_closures", self._on_loop_closure, RESULT_QOS)
        self.store_saver = PeriodicSave(
            self, None if self.store_folder is None else self.store_folder.folder, self._save_store,
            "the feature store", save_period_s,
        )
        self.get_logger().info(
            f"verifying loop closures: >= {self.config.min_inliers} fundamental-matrix inliers, "
            f"features of the last {max_frames} frames"
        )

    def _on_features(self, message: Features) -> None:
        stamp_ns = stamp_to_ns(message.header.stamp)
        try:
            self.store.add(stamp_ns, message_to_features(message))
        except AefabmapError as exc:
            self.counter.drop("bad_features", str(exc))
            return
        self.store_saver.mark_changed()
        waiting = self.pending.pop(stamp_ns, None)
        if waiting is not None:
            self._verify(waiting)

    def _on_loop_closure(self, message: LoopClosure) -> None:
        query_ns = stamp_to_ns(message.header.stamp)
        if query_ns not in self.store:
            self.pending[query_ns] = message
            while len(self.pending) > self.max_pending:
                _, oldest = self.pending.popitem(last=False)
                self.counter.drop("query_features_never_came",
                                  f"no features stamped like the closure of query {oldest.query_id}")
            return
        self._verify(message)

    def _verify(self, message: LoopClosure) -> None:
        query = self.store.get(stamp_to_ns(message.header.stamp))
        place = self.store.get(stamp_to_ns(message.matched_stamp))
        if query is None or place is None:
            self.counter.drop("place_features_unknown",
                              f"no stored features of place {message.matched_place_id} (before this node started, "
                              "or older than max_stored_frames)")
            return
        try:
            result = verify_pair(query, place, self.config)
        except AefabmapError as exc:
            self.counter.drop("unverifiable", str(exc))
            return
        outcome = "accepted" if result.accepted else "rejected"
        self.counter.ok(outcome)
        text = (f"loop closure query {message.query_id} -> place {message.matched_place_id} {outcome}: "
                f"{result.inliers} inliers of {result.matches} matches")
        if result.accepted:
            self.get_logger().info(text)
            message.inliers = result.inliers
            self.publisher.publish(message)
        else:  # a stream of aliased candidates must not flood the log
            self.get_logger().info(text, throttle_duration_sec=LOG_THROTTLE_S)

    def _save_store(self, _folder: Path) -> None:
        if self.store_folder is not None:
            self.store_folder.save(self.store)

    def close(self) -> None:
        self.store_saver.save_if_changed()
        self.get_logger().info(
            f"verifier_node: {len(self.store)} frames stored ({self.store.nbytes / 2**20:.1f} MiB), "
            f"{len(self.pending)} closures still waiting; {self.counter.summary()}"
        )


def main(args: list[str] | None = None) -> int:
    return run_node(VerifierNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
