"""The one table both launchers render: what each node gets beyond the parameter file."""

from __future__ import annotations

import pytest

from aefabmap_ros.nodes.launch_table import SuiteOptions, suite_nodes


def _parameters(options: SuiteOptions, node: str) -> dict[str, str]:
    return next(launch.parameters for launch in suite_nodes(options) if launch.name == node)


@pytest.mark.parametrize(("image_qos", "drop_when_busy"), [("sensor_data", "true"), ("reliable", "false")])
def test_the_quantizer_drops_frames_exactly_when_the_camera_subscription_does(image_qos: str,
                                                                             drop_when_busy: str) -> None:
    """A live camera's frames may be dropped at every stage; a lossless replay must lose none at any."""
    options = SuiteOptions(model_dir="/m", image_qos=image_qos)
    assert _parameters(options, "feature_node")["image_qos"] == image_qos
    assert _parameters(options, "quantizer_node")["drop_when_busy"] == drop_when_busy


def test_without_an_image_qos_choice_both_nodes_keep_the_parameter_files_values() -> None:
    options = SuiteOptions(model_dir="/m")
    assert "image_qos" not in _parameters(options, "feature_node")
    assert _parameters(options, "quantizer_node") == {"model_dir": "/m"}
