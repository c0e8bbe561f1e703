"""Synthetic town: geometry, ground truth, image statistics, determinism and disjoint worlds."""

import math
from dataclasses import replace
from typing import cast

import cv2
import numpy as np
import pytest

from aefabmap_ros.datasets.synth import renderer, trajectory
from aefabmap_ros.datasets.synth import world as town_world
from aefabmap_ros.datasets.synth.config import SynthConfig, dense_video_config, train_test_configs
from aefabmap_ros.datasets.synth.town import depth_to_16uc1, generate_sequence
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.evaluation.covisibility import covisibility_loop_matrix
from aefabmap_ros.evaluation.ground_truth import positions_and_axes

# 640x480 so that SIFT statistics mean what they mean at the default size; 120 frames over 2 laps.
SEQUENCE_CONFIG = SynthConfig(seed=5, num_frames=120)
TINY_CONFIG = SynthConfig(seed=3, num_frames=6, width=96, height=72, texels_per_m=16.0, ground_texels_per_m=8.0)


@pytest.fixture(scope="module")
def sequence():
    return generate_sequence(SEQUENCE_CONFIG)


class _LazySift:
    """SIFT of a frame computed on first use: the tests need only a few dozen of the frames."""

    def __init__(self, images):
        self.images = images
        self.sift = cv2.SIFT_create()  # type: ignore[attr-defined]
        self.cache = {}

    def __getitem__(self, index):
        if index not in self.cache:
            self.cache[index] = self.sift.detectAndCompute(self.images[index], None)
        return self.cache[index]


@pytest.fixture(scope="module")
def sift_features(sequence):
    return _LazySift(sequence.images)


def test_shapes_and_types(sequence):
    n = SEQUENCE_CONFIG.num_frames
    assert len(sequence.images) == n
    assert all(image.shape == (480, 640) and image.dtype == np.uint8 for image in sequence.images)
    assert sequence.stamps_ns.dtype == np.int64 and sequence.stamps_ns.shape == (n,)
    np.testing.assert_array_equal(np.diff(sequence.stamps_ns), 100_000_000)  # 10 Hz
    assert sequence.positions.shape == (n, 3) and sequence.optical_axes.shape == (n, 3)
    assert sequence.gt.shape == (n, n) and sequence.gt.dtype == np.uint8
    assert sequence.poses.shape == (n, 3, 4)
    focal = 320 / math.tan(math.radians(30))
    expected = np.array([[focal, 0, 319.5], [0, focal, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(sequence.camera_matrix, expected)


def test_images_are_not_flat_or_saturated(sequence):
    for image in sequence.images[::10]:
        assert 40 < image.mean() < 215
        assert image.std() > 20
        assert (image == 255).mean() < 0.05 and (image == 0).mean() < 0.05


def test_poses_are_rotations_consistent_with_axes(sequence):
    rotations = sequence.poses[:, :, :3]
    identity = np.einsum("nji,njk->nik", rotations, rotations)
    np.testing.assert_allclose(identity, np.broadcast_to(np.eye(3), identity.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0)
    positions, axes = positions_and_axes(sequence.poses)
    np.testing.assert_allclose(positions, sequence.positions)
    np.testing.assert_allclose(axes, sequence.optical_axes)
    np.testing.assert_allclose(rotations[:, :, 1], np.tile([0, 0, -1.0], (len(rotations), 1)))  # y down


def test_speed_is_plausible(sequence):
    steps = np.linalg.norm(np.diff(sequence.positions[:, :2], axis=0), axis=1)
    assert 0.5 < np.median(steps) < 3.0
    assert steps.max() < 3 * np.median(steps)


def test_gt_poses_agrees_with_poses(sequence):
    """Recompute the pose-rule loop matrix with a plain double loop over the published poses."""
    cfg = SEQUENCE_CONFIG
    n = cfg.num_frames
    expected = np.zeros((n, n), dtype=np.uint8)
    for i in range(n):
        for j in range(i - cfg.gt_min_gap_frames + 1):
            close = np.linalg.norm(sequence.positions[i] - sequence.positions[j]) <= cfg.gt_max_distance_m
            cosine = float(np.dot(sequence.optical_axes[i], sequence.optical_axes[j]))
            if close and math.degrees(math.acos(min(1.0, cosine))) <= cfg.gt_max_angle_deg:
                expected[i, j] = 1
    np.testing.assert_array_equal(sequence.gt_poses, expected)
    # Two laps of a figure-eight: the second lap revisits the first, and the middle street is driven twice a lap.
    assert sequence.gt_poses.any(axis=1).sum() >= n // 3


def test_gt_is_covisibility_of_the_written_depth(sequence):
    n = SEQUENCE_CONFIG.num_frames
    assert sequence.depths.shape == (n, 480, 640) and sequence.depths.dtype == np.float32
    expected = covisibility_loop_matrix(depth_to_16uc1(sequence.depths), sequence.poses, sequence.camera_matrix,
                                        sequence.stamps_ns, min_gap_s=SEQUENCE_CONFIG.gt_min_gap_s, depth_scale=1000.0)
    np.testing.assert_array_equal(sequence.gt, expected)
    # 60 frames (6 s) a lap: the second lap revisits the first, beyond the 5 s gap.
    assert sequence.gt[70:].any(axis=1).sum() >= 25
    assert not sequence.gt[:50].any()
    # Most revisits are close in space too (the same street, the same direction).
    i, j = np.nonzero(sequence.gt)
    distance = np.linalg.norm(sequence.positions[i] - sequence.positions[j], axis=1)
    assert np.median(distance) < 5.0


def test_depth_to_16uc1():
    depth = np.array([[0.0, 0.0004, 0.0006, 1.2344], [65.535, 65.536, np.inf, np.nan]], dtype=np.float32)
    millimetres = depth_to_16uc1(depth)
    assert millimetres.dtype == np.uint16
    assert millimetres.tolist() == [[0, 0, 1, 1234], [65535, 0, 0, 0]]


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


def test_sift_finds_plenty_of_keypoints(sift_features):
    counts = np.array([len(sift_features[index][0]) for index in range(0, SEQUENCE_CONFIG.num_frames, 4)])
    assert np.median(counts) >= 300
    assert np.percentile(counts, 10) >= 150  # even the motion-blurred frames keep texture


def _ratio_matches(first, second) -> int:
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(first, second, k=2)
    return sum(1 for pair in matches if len(pair) == 2 and pair[0].distance < 0.75 * pair[1].distance)


def test_revisits_look_alike(sequence, sift_features):
    rng = np.random.default_rng(0)
    loop_i, loop_j = np.nonzero(sequence.gt)
    picks = rng.choice(loop_i.size, size=min(15, loop_i.size), replace=False)
    revisit = [_ratio_matches(sift_features[loop_i[p]][1], sift_features[loop_j[p]][1]) for p in picks]
    others: list[int] = []
    while len(others) < 15:
        i, j = (int(v) for v in rng.integers(0, len(sequence.images), size=2))
        far = np.linalg.norm(sequence.positions[i] - sequence.positions[j]) > 10.0
        if i - j >= 10 and far:
            others.append(_ratio_matches(sift_features[i][1], sift_features[j][1]))
    assert np.mean(revisit) > 3 * np.mean(others)
    assert np.median(revisit) > 60


def test_deterministic_given_seed():
    first = generate_sequence(TINY_CONFIG)
    second = generate_sequence(TINY_CONFIG)
    for a, b in zip(first.images, second.images, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first.positions, second.positions)
    other = generate_sequence(replace(TINY_CONFIG, seed=4))
    assert not np.array_equal(first.images[0], other.images[0])


def test_color_images():
    sequence = generate_sequence(replace(TINY_CONFIG, color=True, num_frames=2))
    assert sequence.images[0].shape == (72, 96, 3)
    channels = sequence.images[0].reshape(-1, 3).mean(axis=0)
    assert channels.max() - channels.min() > 1.0  # bluish sky, coloured facades: not grey


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
