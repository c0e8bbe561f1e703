"""The town's world: train and test towns share no texture, and repeated textures are shared as configured."""

from dataclasses import replace

import numpy as np

from aefabmap_ros.datasets.synth import world as town_world
from aefabmap_ros.datasets.synth.config import SynthConfig, train_test_configs

TINY_CONFIG = SynthConfig(seed=3, num_frames=6, width=96, height=72, texels_per_m=16.0, ground_texels_per_m=8.0)


def test_train_and_test_worlds_differ():
    train, test = train_test_configs(TINY_CONFIG)
    assert train.seed != test.seed
    assert replace(train, seed=test.seed) == test
    train_world = town_world.build_world(train)
    test_world = town_world.build_world(test)
    # Same street grid and route, other facades and textures: no texture of one town is in the other.
    assert train_world.route_nodes == test_world.route_nodes and train_world.pitch_m == test_world.pitch_m
    train_textures = {_entry(train_world, t).tobytes() for t in range(train_world.entry_x.shape[0] - 2)}
    test_textures = {_entry(test_world, t).tobytes() for t in range(test_world.entry_x.shape[0] - 2)}
    assert not train_textures & test_textures


def _entry(world, texture_id: int) -> np.ndarray:
    x, y = int(world.entry_x[texture_id, 0]), int(world.entry_y[texture_id, 0])
    w, h = int(world.entry_w[texture_id, 0]), int(world.entry_h[texture_id, 0])
    return world.atlas[y : y + h, x : x + w]


def test_repeated_textures_are_shared():
    config = replace(TINY_CONFIG, repeated_texture_fraction=1.0)
    world = town_world.build_world(config)
    ids = world.facades.texture_id[world.facades.texels_per_m == config.texels_per_m]
    assert set(ids.tolist()) <= {0, 1, 2}  # every facade along the route shows one of the 3 shared textures
    world = town_world.build_world(replace(TINY_CONFIG, repeated_texture_fraction=0.0))
    near = world.facades.texels_per_m == TINY_CONFIG.texels_per_m
    assert np.unique(world.facades.texture_id[near]).size == near.sum()
