"""FAB-MAP's settings: every value is checked, the error names the setting."""

import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.fabmap.config import FabMapConfig

openfabmap = FabMapConfig.openfabmap


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"p_z_given_e": 1.0}, r"p_z_given_e = 1.0: must be in \(0, 1\)"),
        ({"p_z_given_not_e": 0.5}, "p_z_given_not_e = 0.5"),
        ({"new_place_model": "magic"}, "new_place_model = 'magic'"),
        ({"p_new": 0.0}, "p_new = 0.0"),
        ({"motion_bias": 1.5}, "motion_bias = 1.5"),
        ({"smoothing": 0.0}, "smoothing = 0.0"),
        ({"match_threshold": 2.0}, "match_threshold = 2.0"),
        ({"add_policy": "some"}, "add_policy = 'some'"),
        ({"exclude_recent_frames": -1}, "exclude_recent_frames = -1"),
        ({"exclude_recent_seconds": -0.5}, "exclude_recent_seconds = -0.5"),
        ({"keyframe_min_frames": 0}, "keyframe_min_frames = 0"),
        ({"keyframe_max_overlap": 1.1}, "keyframe_max_overlap = 1.1"),
        ({"keyframe_max_frames": -2}, "keyframe_max_frames = -2"),
        ({"top_k": -1}, "top_k = -1"),
        ({"top_k": 2.5}, "top_k = 2.5: must be of type int"),
        ({"motion_model": 1}, "motion_model = 1: must be of type bool"),
    ],
)
def test_config_validation(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        openfabmap(**kwargs)
