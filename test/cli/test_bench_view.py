"""bench_view --picture-delays on a hand-made recording: delays by query stamp, closures without a picture left out."""

import numpy as np
import pytest

from aefabmap_ros.cli.bench_view import picture_delays_s
from aefabmap_ros.io import bags

pytest.importorskip("rclpy")


def test_each_closures_picture_delay_is_matched_by_query_stamp(tmp_path):
    from aefabmap_msgs.msg import LoopClosure
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage

    from aefabmap_ros.nodes.messages import time_from_ns

    def closure(stamp_ns: int) -> bytes:
        message = LoopClosure()
        message.header.stamp = time_from_ns(stamp_ns)
        return serialize_message(message)

    def picture(stamp_ns: int) -> bytes:
        message = CompressedImage(format="jpeg")
        message.header.stamp = time_from_ns(stamp_ns)
        return serialize_message(message)

    recording = tmp_path / "run"
    with bags.BagWriter(recording, storage="mcap") as writer:
        writer.add_topic("/loop_closures", "aefabmap_msgs/msg/LoopClosure")
        writer.add_topic("/closure_view/closures", "sensor_msgs/msg/CompressedImage")
        writer.write("/loop_closures", 10_000_000_000, closure(1_000))
        writer.write("/loop_closures", 11_000_000_000, closure(2_000))
        writer.write("/loop_closures", 12_000_000_000, closure(3_000))  # no picture
        writer.write("/closure_view/closures", 11_500_000_000, picture(2_000))  # out of order: by stamp, not order
        writer.write("/closure_view/closures", 10_250_000_000, picture(1_000))
    closures, delays = picture_delays_s(recording)
    assert closures == 3
    np.testing.assert_allclose(sorted(delays), [0.25, 0.5])
