"""Depth images to metres (aefabmap_ros/io/image_messages.py): both ROS depth conventions (REP 118)
against hand-computed values, an unknown encoding refused."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.io.image_messages import depth_image_to_metres


def test_depth_images_in_both_encodings() -> None:
    millimetres = np.array([[0, 1500], [2000, 65535]], dtype=np.uint16)
    np.testing.assert_allclose(depth_image_to_metres(millimetres, "16UC1"), [[np.nan, 1.5], [2.0, 65.535]])
    metres = np.array([[np.nan, 1.5], [-1.0, np.inf]], dtype=np.float32)
    np.testing.assert_allclose(depth_image_to_metres(metres, "32FC1"), [[np.nan, 1.5], [np.nan, np.nan]])
    with pytest.raises(DataError):
        depth_image_to_metres(millimetres, "rgb8")
