"""The renderer against closed-form geometry: depth of a single wall and of the town's ground rows and sky,
one column's ray cast, and covisibility of a rendered revisit."""

import math
from dataclasses import replace
from typing import cast

import numpy as np
import pytest

from aefabmap_ros.datasets.synth import renderer, trajectory
from aefabmap_ros.datasets.synth import world as town_world
from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.evaluation.covisibility import covisibility_loop_matrix

TINY_CONFIG = SynthConfig(seed=3, num_frames=6, width=96, height=72, texels_per_m=16.0, ground_texels_per_m=8.0)


def _single_wall_world(config: SynthConfig) -> town_world.World:
    """The town's atlas with one facade: the wall y = 5.13 m from x = -10 to 10, 3 m high, facing south."""
    world = town_world.build_world(config)
    facades = town_world._Facades(
        start=np.array([[10.0, 5.13]]), direction=np.array([[-1.0, 0.0]]), normal=np.array([[0.0, -1.0]]),
        length_m=np.array([20.0]), height_m=np.array([3.0]), texture_id=np.array([3]),
        texels_per_m=np.array([config.texels_per_m]))
    return replace(world, facades=facades)


def _reference_depth(camera, origin_xy, heading, height_m):
    """Per-pixel 3-D ray casting against the ground z = 0 and the wall y = 5.13 (|x| <= 10, z <= 3)."""
    forward = np.array([math.cos(heading), math.sin(heading), 0.0])
    right = np.array([math.sin(heading), -math.cos(heading), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    origin = np.array([origin_xy[0], origin_xy[1], height_m])
    depth = np.zeros((camera.height, camera.width))
    for row in range(camera.height):
        for column in range(camera.width):
            ray = forward + (column - camera.cx) / camera.focal_px * right + (row - camera.cy) / camera.focal_px * down
            best = math.inf
            if ray[2] < 0:
                best = -origin[2] / ray[2]  # ground; the ray's forward component is 1: t is the depth
            if ray[1] > 0:
                t = (5.13 - origin[1]) / ray[1]
                hit = origin + t * ray
                if t > 0 and abs(hit[0]) <= 10 and 0 <= hit[2] <= 3 and t < best:
                    best = t
            depth[row, column] = 0.0 if math.isinf(best) else best
    return depth


@pytest.mark.parametrize(("origin_xy", "heading_deg"), [((0.3, 0.0), 90.0), ((-2.0, -1.0), 70.0), ((1.0, 2.0), 120.0)])
def test_rendered_depth_is_the_ray_plane_intersection(origin_xy, heading_deg):
    config = replace(TINY_CONFIG, width=64, height=48)
    world = _single_wall_world(config)
    camera = renderer.PinholeCamera.from_config(config)
    heading = math.radians(heading_deg)
    image, depth = renderer.render_view_and_depth(world, camera, np.array(origin_xy), heading, 1.6, 0.0, 150.0)
    assert image.shape == (48, 64) and depth.shape == (48, 64) and depth.dtype == np.float32
    reference = _reference_depth(camera, origin_xy, heading, 1.6)
    np.testing.assert_allclose(depth, reference, rtol=1e-5)
    assert (depth == 0).any() and (depth > 0).any()  # sky above the wall, wall and ground below
    x_col = (32 - camera.cx) / camera.focal_px  # column 32's ray meets the wall's plane at this depth
    wall_depth = (5.13 - origin_xy[1]) / (math.sin(heading) - x_col * math.cos(heading))
    assert (np.abs(depth[:, 32] - wall_depth) < 1e-3).sum() >= 5


def test_town_depth_ground_rows_and_sky():
    config = replace(TINY_CONFIG, width=80, height=60)
    world = town_world.build_world(config)
    camera = renderer.PinholeCamera.from_config(config)
    # In the middle street (x = 40 m), looking north along it: the bottom row sees the road 1.6 m below.
    _, depth = renderer.render_view_and_depth(world, camera, np.array([41.0, 25.0]), math.pi / 2, 1.6, 0.0, 150.0)
    rows = np.arange(config.height)
    ground = 1.6 * camera.focal_px / (rows - camera.cy)
    np.testing.assert_allclose(depth[-1], ground[-1], rtol=1e-5)
    np.testing.assert_allclose(depth[-5:, 40], ground[-5:], rtol=1e-5)
    assert (depth[0] == 0).any()  # sky between the facades at the top of the image
    assert np.isfinite(depth).all() and depth.max() < 200.0


def test_covisibility_of_a_rendered_revisit():
    """The same spot of the middle street seen again 10 s later a metre further on is a revisit; the same
    spot driven in the opposite direction, or from around the corner, is not."""
    config = replace(TINY_CONFIG, width=160, height=120)
    world = town_world.build_world(config)
    camera = renderer.PinholeCamera.from_config(config)
    views = [((41.0, 25.0), 90.0), ((41.2, 26.0), 93.0), ((41.0, 25.0), 270.0), ((50.0, 40.0), 0.0)]
    depths = np.stack([renderer.render_view_and_depth(world, camera, np.array(xy), math.radians(heading), 1.6, 0.0,
                                                   150.0)[1] for xy, heading in views])
    positions = np.array([[x, y, 1.6] for (x, y), _ in views])
    poses = trajectory.poses_from_headings(positions, np.radians([heading for _, heading in views]))
    stamps = np.arange(4, dtype=np.int64) * 10_000_000_000
    gt = covisibility_loop_matrix(depths, poses, camera.matrix(), stamps)
    assert gt[1, 0] == 1
    assert gt[2, 0] == 0 and gt[2, 1] == 0
    assert gt[3].sum() == 0


def test_column_ray_cast_against_a_single_wall():
    """Wall y = 5 from x = -10 to 10 facing south; camera at the origin looking north."""
    facades = town_world._Facades(
        start=np.array([[-10.0, 5.0]]),
        direction=np.array([[1.0, 0.0]]),
        normal=np.array([[0.0, -1.0]]),
        length_m=np.array([20.0]),
        height_m=np.array([6.0]),
        texture_id=np.array([0]),
        texels_per_m=np.array([64.0]),
    )
    world = cast(town_world.World, type("W", (), {"facades": facades})())
    camera = renderer.PinholeCamera(focal_px=100.0, cx=49.5, cy=39.5, width=100, height=80)
    heading = math.pi / 2
    forward = np.array([math.cos(heading), math.sin(heading)])
    right = np.array([math.sin(heading), -math.cos(heading)])
    np.testing.assert_allclose(right, [1.0, 0.0], atol=1e-12)
    hits = renderer._cast_columns(world, camera, np.zeros(2), forward, right)
    x_col = (np.arange(100) - 49.5) / 100.0
    np.testing.assert_allclose(hits.depth[0], 5.0)  # depth along the optical axis is constant on a facing wall
    np.testing.assert_allclose(hits.along_m[0], 10.0 + 5.0 * x_col)
    np.testing.assert_allclose(hits.slope_m[0], 5.0 / 100.0)
    # Seen from behind (camera north of the wall, looking south) the wall is culled.
    back = renderer._cast_columns(world, camera, np.array([0.0, 10.0]), -forward, -right)
    assert np.isinf(back.depth).all()
