"""SynthConfig: bad values refused with the reason, ints taken for floats, every field documented, routes
checked."""


import pytest

from aefabmap_ros.datasets.synth import world as town_world
from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.errors import ConfigError


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"num_frames": 0}, "num_frames must be > 0, got 0"),
        ({"width": "640"}, "width must be int, got '640'"),
        ({"color": 1}, "color must be bool, got 1"),
        ({"fov_deg": 200.0}, r"fov_deg must be in \[10, 150\], got 200.0"),
        ({"blur_probability": 1.5}, r"blur_probability must be in \[0, 1\], got 1.5"),
        ({"lighting_variation": 1.0}, r"lighting_variation must be in \[0, 1\), got 1.0"),
        ({"noise_sigma": -1.0}, "noise_sigma must be >= 0, got -1.0"),
        ({"width": 8}, "width and height must be >= 16, got 8x480"),
        ({"lane_offset_m": 3.5}, "lane_offset_m 3.5 .* within 1 m of the walls"),
        ({"camera_height_m": 5.0}, "camera_height_m must be < 4"),
        ({"gt_max_angle_deg": 181.0}, r"gt_max_angle_deg must be in \[0, 180\]"),
        ({"gt_min_gap_s": -1.0}, "gt_min_gap_s must be >= 0, got -1.0"),
    ],
)
def test_config_errors(changes, match):
    with pytest.raises(ConfigError, match=match):
        SynthConfig(**changes)


def test_config_accepts_int_for_float_and_documents_fields():
    config = SynthConfig(fov_deg=70)
    assert config.fov_deg == 70.0 and isinstance(config.fov_deg, float)
    from dataclasses import fields

    assert all(item.metadata.get("description") for item in fields(SynthConfig))
    assert all(type(item.default) in (bool, int, float, str) for item in fields(SynthConfig))


def test_default_route_is_unchanged_and_routes_are_checked():
    assert SynthConfig().route == "figure-eight"
    assert town_world.route_nodes() == [(2, 1), (2, 2), (1, 2), (1, 1), (2, 1), (2, 2), (3, 2), (3, 1), (2, 1)]
    with pytest.raises(ConfigError, match=r"route must be one of \['dense-video', 'figure-eight'\], got 'spiral'"):
        SynthConfig(route="spiral")
