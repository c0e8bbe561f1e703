"""aefabmap_eval's depth inputs (cli/evaluate_depth.py): the camera and keypoint depths the metric test gets."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import pytest

from aefabmap_ros.cli.evaluate_depth import sequence_depths
from aefabmap_ros.errors import DataError
from aefabmap_ros.features.extraction import Features
from test.io.test_rgbd import DISTORTED, K

WIDTH, HEIGHT = 640, 480


def _features(points: list[tuple[float, float]]) -> Features:
    keypoints = np.zeros((len(points), 5), np.float32)
    keypoints[:, :2] = points
    return Features(keypoints, np.zeros((len(points), 128), np.float32), "sift")


def _args(tmp_path, camera_text: str) -> argparse.Namespace:
    (tmp_path / "camera_info.yaml").write_text(camera_text)
    return argparse.Namespace(depth=tmp_path / "depth", depth_topic=None, camera_info=tmp_path / "camera_info.yaml",
                              camera_info_topic=None, images=tmp_path / "images", bag=None)


def _write_depth(folder, millimetres: list[int]) -> None:
    folder.mkdir()
    for index, value in enumerate(millimetres):
        image = np.full((HEIGHT, WIDTH), value, np.uint16)
        image[:10, :10] = 0  # no depth in the top-left corner
        assert cv2.imwrite(str(folder / f"{index:06d}.png"), image)


def test_folder_and_yaml_give_each_keypoint_its_depth_and_the_distorted_camera(tmp_path):
    _write_depth(tmp_path / "depth", [1500, 2750])
    features = [_features([(100.0, 200.0), (3.0, 4.0)]), _features([(639.0, 479.0)])]
    depths = sequence_depths(_args(tmp_path, DISTORTED), source=None, features=features)  # type: ignore[arg-type]
    assert depths is not None
    np.testing.assert_array_equal(depths.camera.matrix, K)
    # The distortion the file gives reaches the metric test's PnP and view overlap (as a bag's CameraInfo d does).
    np.testing.assert_array_equal(depths.camera.distortion, [-0.28, 0.07, 0.0011, -0.0004, 0.0])
    assert depths.image_size == (WIDTH, HEIGHT)
    np.testing.assert_array_equal(depths.keypoint_depths[0], [1.5, np.nan])  # 0 mm: no depth
    np.testing.assert_array_equal(depths.keypoint_depths[1], [2.75])


def test_depth_of_another_size_than_the_camera_is_refused(tmp_path):
    _write_depth(tmp_path / "depth", [1000])
    with pytest.raises(DataError, match="the camera's images 320x480"):
        sequence_depths(_args(tmp_path, DISTORTED.replace("640", "320")), source=None,  # type: ignore[arg-type]
                        features=[_features([(1.0, 1.0)])])
