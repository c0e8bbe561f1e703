"""The dense-video drive: speeds, the stop, and revisits in both directions with a street left alone."""

import math
from dataclasses import replace

import numpy as np
import pytest

from aefabmap_ros.datasets.synth import trajectory
from aefabmap_ros.datasets.synth import world as town_world
from aefabmap_ros.datasets.synth.config import dense_video_config


@pytest.fixture(scope="module")
def dense_drive():
    config = dense_video_config()
    world = town_world.build_world(replace(config, texels_per_m=8.0, ground_texels_per_m=4.0))  # geometry only
    positions, headings = trajectory.drive_route(config, world, np.random.default_rng(0))
    return config, world, positions, headings


def test_dense_video_preset(dense_drive):
    config, _, positions, headings = dense_drive
    assert (config.num_frames, config.frame_rate_hz, config.route) == (3600, 30.0, "dense-video")
    assert positions.shape == (3600, 2) and headings.shape == (3600,)
    speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) * config.frame_rate_hz  # m/s
    # A stop of at least 4 s (standing still), slow and fast stretches.
    still = np.r_[0, (speed < 1e-9).astype(int), 0]
    runs = np.diff(np.nonzero(np.diff(still))[0])[::2]
    assert runs.max() >= 4 * 30
    moving = speed[speed > 0.1]
    assert np.percentile(moving, 90) > 2.0 * np.percentile(moving, 20)
    assert speed.max() < 12.0  # no teleporting


def test_dense_video_route_revisits_both_ways_and_leaves_a_street_alone(dense_drive):
    config, world, positions, headings = dense_drive
    pitch = world.pitch_m
    north = np.cos(headings - math.pi / 2) > 0.9
    south = np.cos(headings + math.pi / 2) > 0.9
    middle = np.abs(positions[:, 0] - 2 * pitch) < 3.0
    lower_half = middle & (positions[:, 1] > pitch + 5) & (positions[:, 1] < 2 * pitch - 5)
    upper_half = middle & (positions[:, 1] > 2 * pitch + 5) & (positions[:, 1] < 3 * pitch - 5)
    frames = np.arange(len(positions))
    # The lower half of the middle street southbound twice, far apart in time ...
    southbound = frames[lower_half & south]
    assert np.diff(southbound).max() > 20 * config.frame_rate_hz
    # ... the upper half southbound first, northbound at the end.
    upper_south, upper_north = frames[upper_half & south], frames[upper_half & north]
    assert upper_south.size > 30 and upper_north.size > 30 and upper_north.min() > southbound.max()
    assert upper_north.min() - upper_south.max() > 30 * config.frame_rate_hz
    # The west edge street (x = 0) is driven once, at the start, and never approached again (up to the
    # north edge, where the route turns east).
    west = frames[(positions[:, 0] < 3.0) & (positions[:, 1] < 2.5 * pitch)]
    assert west.size > 0 and west.max() < len(positions) // 2
    later = positions[np.argmax(positions[:, 0] > 15.0) :]  # from past the first corner on
    assert np.min(np.linalg.norm(later[:, None, :] - positions[west][None, ::10, :], axis=2)) > 10.0
