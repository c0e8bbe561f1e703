"""feature_node's frames for a viewer: made only while someone subscribes, the frame's own features with a
thumbnail of its image."""

from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from aefabmap_ros.io.sources import ImageSource  # noqa: E402
from aefabmap_ros.nodes.common import pipeline_qos  # noqa: E402
from aefabmap_ros.nodes.feature_node import FeatureNode  # noqa: E402
from aefabmap_ros.nodes.launch_table import FRAME_VIEWS_TOPIC  # noqa: E402
from aefabmap_ros.visualization.match_picture import decode_jpeg  # noqa: E402
from test.nodes.captured import Captured  # noqa: E402
from test.revisit_fixture import RevisitData  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]


def _image(gray: np.ndarray, sec: int) -> Image:
    image = Image(height=gray.shape[0], width=gray.shape[1], encoding="mono8", step=gray.shape[1],
                  data=gray.tobytes())
    image.header.stamp = Time(sec=sec)
    return image


def test_frame_views_only_while_subscribed_with_the_frames_features_and_a_thumbnail(
        revisit_data: RevisitData) -> None:
    node = FeatureNode(parameter_overrides=[Parameter("model_dir", value=str(revisit_data.model_dir)),
                                            Parameter("thumbnail_width", value=160)])
    try:
        features, views = Captured(node.publisher), Captured(node.frame_view_publisher)
        _, gray = next(iter(ImageSource(bag=revisit_data.bag, topic="/image").frames()))
        node._on_image(_image(gray, sec=1))
        assert len(features.messages) == 1 and views.messages == []  # nobody watches: no thumbnail made

        viewer = node.create_subscription(msg.FrameView, FRAME_VIEWS_TOPIC, lambda _message: None, pipeline_qos(10))
        deadline = time.monotonic() + 10
        while node.frame_view_publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        node._on_image(_image(gray, sec=2))
        assert len(features.messages) == 2 and len(views.messages) == 1
        view = views.messages[0]
        assert view.features is features.messages[1]  # the features the detector got, not a second extraction
        assert view.features.header.stamp.sec == 2 and view.features.image_width == gray.shape[1]
        thumbnail = decode_jpeg(bytes(view.thumbnail_jpeg))
        assert thumbnail.shape[1] == 160
        assert thumbnail.shape[0] == round(gray.shape[0] * 160 / gray.shape[1])
        node.destroy_subscription(viewer)
    finally:
        node.destroy_node()
