"""Synthetic town for loop-closure experiments: a textured 3-D world rendered along a looping route.

``generate_sequence`` here puts the parts together: ``config`` (parameters, routes, presets), ``world``
(geometry, texture atlas), ``textures`` and ``ground_and_sky``, ``trajectory`` (the drive) and ``renderer``.

World. A grid of 4 x 3 city blocks separated by streets, inside a ring of tall far buildings so
every view ends in a skyline. Each block side is cut into facades (vertical wall segments) of
random width and height. Every facade has its own procedurally drawn texture (brick, plaster,
concrete panels, siding or stone; windows with curtains, blinds and reflections; shop fronts with
posters, signs with text, doors, graffiti, stains). A fraction ``repeated_texture_fraction`` of
the facades along the route reuse one of a few shared textures (the chain shops of a town): the
perceptual aliasing that fools appearance-only place recognition. The ground is one large texture
(asphalt, sidewalks with paving, dashed lane markings, zebra crossings, manholes, patches); the
sky a smooth periodic panorama with clouds.

Route. A figure-eight around the two central blocks: north up the middle street, around the left
block counter-clockwise, north up the middle street again, around the right block clockwise.
The middle street is driven twice per lap in the same direction, and every lap revisits the whole
route, each lap with a different lateral offset, speed profile and heading jitter. Lighting changes
over the sequence (sun direction drift, global gain and gamma), the camera adds noise and some
frames get motion blur.

Renderer. The camera is upright (no pitch or roll), so the image is separable: one ray per image
column is intersected with all facade segments (vectorised), the nearest 4 front-facing hits per
column are composited (farther, taller buildings show above nearer ones), ground and sky are
ray-cast per pixel. All textures live in one atlas holding 5 mip levels each; each pixel gets
texture coordinates and a level of detail from its footprint, and two ``cv2.remap`` calls with a
blend give trilinear filtering (no aliasing shimmer, so SIFT features are stable across views).

Depth. Every frame also has its depth map (``render_view_and_depth``): metres along the optical axis
of the surface drawn at each pixel, 0 where only sky is drawn.

Ground truth. ``gt`` is covisibility (DESIGN section 9.2, ``covisibility_loop_matrix``): frame i
revisits frame j, at least ``gt_min_gap_s`` (5 s) earlier, when at least 30 % of i's depth pixels
(every 8th) land on the surfaces j saw. It is computed from the depth as a 16UC1 depth image holds
it (``depth_to_16uc1``: millimetres, nothing beyond 65.535 m), so ``aefabmap_gt`` run on a written
sequence reproduces it. ``gt_poses`` is the pose rule: camera centres within
``gt_max_distance_m`` (2.5 m), optical axes within ``gt_max_angle_deg`` (30 deg) and
``j <= i - gt_min_gap_frames`` (10).

Poses follow KITTI's convention: camera-to-world ``[R | t]`` with camera axes x right, y down,
z forward (optical axis = third column of R); the world has x east, y north, z up, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.renderer import PinholeCamera, camera_effects, render_view_and_depth
from aefabmap_ros.datasets.synth.trajectory import drive_route, poses_from_headings, smooth_series
from aefabmap_ros.datasets.synth.world import build_world
from aefabmap_ros.evaluation.covisibility import covisibility_loop_matrix
from aefabmap_ros.evaluation.ground_truth import loop_matrix_from_poses


@dataclass
class SyntheticSequence:
    """Rendered frames with their depth, poses and ground-truth loop matrices."""

    images: list[np.ndarray]  # N x (H, W) uint8 mono8, or (H, W, 3) uint8 bgr8
    stamps_ns: np.ndarray  # (N,) int64
    positions: np.ndarray  # (N, 3) float64 camera centres, metres (world x east, y north, z up)
    optical_axes: np.ndarray  # (N, 3) float64 unit viewing directions
    gt: np.ndarray  # (N, N) uint8 covisibility, gt[i, j] = 1: frame i revisits earlier frame j
    poses: np.ndarray  # (N, 3, 4) float64 KITTI camera-to-world [R | t]
    camera_matrix: np.ndarray  # (3, 3) float64 pinhole intrinsics
    depths: np.ndarray  # (N, H, W) float32 metres along the optical axis, 0 = sky (no depth)
    gt_poses: np.ndarray  # (N, N) uint8 loop matrix of the pose rule (distance, angle, frame gap)


def depth_to_16uc1(depth_m: np.ndarray) -> np.ndarray:
    """uint16 millimetres as in a ROS 16UC1 depth image: 0 = no depth, and so is anything beyond 65.535 m."""
    millimetres = np.rint(np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0) * 1000.0)
    return np.where((millimetres > 0) & (millimetres <= np.iinfo(np.uint16).max), millimetres, 0).astype(np.uint16)



def generate_sequence(config: SynthConfig) -> SyntheticSequence:
    """Build the town of ``config.seed`` and render ``config.num_frames`` frames along its route."""
    world = build_world(config)
    motion_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 2]))
    camera_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 3]))
    count = config.num_frames
    positions_xy, headings = drive_route(config, world, motion_rng)
    camera_heights = config.camera_height_m + 0.05 * smooth_series(motion_rng, count, 20.0)
    progress = np.arange(count) / max(count - 1, 1)
    sun_azimuth = motion_rng.uniform(0, 2 * np.pi) + np.deg2rad(config.sun_drift_deg) * progress
    variation = config.lighting_variation
    gains = 1.0 + variation * np.tanh(smooth_series(motion_rng, count, count / 6))
    gains *= 1.0 + 0.02 * variation * motion_rng.normal(size=count)  # auto-exposure flicker
    gammas = 1.0 + 0.5 * variation * np.tanh(smooth_series(motion_rng, count, count / 5))
    camera = PinholeCamera.from_config(config)
    noise_shape = (2 * config.height, 2 * config.width) + ((3,) if config.color else ())
    noise = camera_rng.normal(0.0, config.noise_sigma, size=noise_shape).astype(np.float32)
    images = []
    depths = np.empty((count, config.height, config.width), dtype=np.float32)
    for index in range(count):
        radiance, depths[index] = render_view_and_depth(
            world, camera, positions_xy[index], float(headings[index]), float(camera_heights[index]),
            float(sun_azimuth[index]), config.fog_distance_m)
        images.append(camera_effects(radiance, camera_rng, noise, float(gains[index]), float(gammas[index]), config))
    positions = np.column_stack([positions_xy, camera_heights])
    axes = np.column_stack([np.cos(headings), np.sin(headings), np.zeros(count)])
    gt_poses = loop_matrix_from_poses(positions, axes, config.gt_max_distance_m, config.gt_max_angle_deg,
                                      config.gt_min_gap_frames)
    stamps = config.start_stamp_ns + np.rint(np.arange(count) * (1e9 / config.frame_rate_hz)).astype(np.int64)
    poses = poses_from_headings(positions, headings)
    gt = covisibility_loop_matrix(depth_to_16uc1(depths), poses, camera.matrix(), stamps,
                                  min_gap_s=config.gt_min_gap_s, depth_scale=1000.0)
    return SyntheticSequence(images, stamps, positions, axes, gt, poses, camera.matrix(), depths, gt_poses)
