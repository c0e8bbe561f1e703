"""io.rgbd's camera_info.yaml reader (K, distortion and size as ROS camera_calibration_parsers writes them) and
its pinhole check."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_ros.cli.synth import camera_info_yaml
from aefabmap_ros.errors import DataError
from aefabmap_ros.io.rgbd import check_camera_matrix, read_camera_info_yaml

K = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])

# As camera_calibration writes a calibrated, distorted camera (plumb_bob: k1 k2 p1 p2 k3).
DISTORTED = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [500.0, 0.0, 320.0, 0.0, 510.0, 240.0, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.28, 0.07, 0.0011, -0.0004, 0.0]
"""


def test_reads_matrix_distortion_and_size(tmp_path):
    path = tmp_path / "camera_info.yaml"
    path.write_text(DISTORTED)
    info = read_camera_info_yaml(path)
    np.testing.assert_array_equal(info.matrix, K)
    np.testing.assert_array_equal(info.distortion, [-0.28, 0.07, 0.0011, -0.0004, 0.0])
    assert (info.width, info.height) == (640, 480)


def test_synth_file_reads_back_as_written(tmp_path):
    path = tmp_path / "camera_info.yaml"
    path.write_text(camera_info_yaml(K, 64, 48))
    info = read_camera_info_yaml(path)
    np.testing.assert_array_equal(info.matrix, K)
    np.testing.assert_array_equal(info.distortion, np.zeros(5))
    assert (info.width, info.height) == (64, 48)


def test_no_distortion_given_is_none(tmp_path):
    path = tmp_path / "camera_info.yaml"
    path.write_text(DISTORTED.split("distortion_model")[0])
    assert read_camera_info_yaml(path).distortion.shape == (0,)


@pytest.mark.parametrize(("text", "message"), [
    (DISTORTED.replace("-0.28", "abc"), "cannot read camera info"),
    (DISTORTED.replace("-0.28", ".nan"), "must be finite"),
    (DISTORTED.replace("  data: [-0.28", "  datum: [-0.28"), "KeyError"),
    ("image_width: 3\n", "cannot read camera info"),
    (DISTORTED.replace("500.0, 0.0, 320.0", "-500.0, 0.0, 320.0"), "focal"),
])
def test_bad_files_are_refused_by_name(tmp_path, text, message):
    path = tmp_path / "camera_info.yaml"
    path.write_text(text)
    with pytest.raises(DataError, match=message) as error:
        read_camera_info_yaml(path)
    assert f"cannot read camera info {path}" in str(error.value)


def test_a_camera_matrix_is_a_pinhole_or_refused_by_name():
    pinhole = check_camera_matrix(np.array([[500, 0.5, 320], [0, 510, 240], [0, 0, 1]]))
    assert pinhole.dtype == np.float64 and pinhole[0, 1] == 0.5  # a skew is allowed
    for matrix, problem in (
        (np.eye(2), r"shape \(3, 3\), got \(2, 2\)"),
        (np.array([[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]]), "non-finite"),
        (np.array([[0.0, 0, 1], [0, 1, 1], [0, 0, 1]]), "focal lengths must be > 0"),
        (np.array([[1.0, 0, 1], [0.1, 1, 1], [0, 0, 1]]), r"must be \[\[fx, s, cx\]"),
        (np.array([[1.0, 0, 1], [0, 1, 1], [0, 0, 2]]), r"must be \[\[fx, s, cx\]"),
    ):
        with pytest.raises(DataError, match=problem):
            check_camera_matrix(matrix)
