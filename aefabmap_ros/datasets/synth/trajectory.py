"""The camera's drive along the route: positions, headings and KITTI poses."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.ndimage import gaussian_filter1d

from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.world import World


def smooth_series(rng: np.random.Generator, count: int, correlation: float) -> np.ndarray:
    """Zero-mean, unit-std noise correlated over about `correlation` samples."""
    sigma = max(correlation, 1e-3)
    pad = int(3 * sigma) + 1
    noise = gaussian_filter1d(rng.normal(size=count + 2 * pad), sigma, mode="reflect")[pad : pad + count]
    std = float(noise.std())
    result: np.ndarray = noise / std if std > 0 else noise
    return result


# dense-video speed plan: (share of the drive's duration, relative speed); the stop lasts _STOP_S.
_DENSE_SPEED_PLAN = ((0.15, 1.0), (0.2, 2.6), (0.1, 1.0), (0.1, 0.5), (0.45, 1.8))
_STOP_S = 4.0
_STOP_AT = 0.45  # share of the duration after which the camera stands still


def _dense_speed(config: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """Relative speed per frame: slow, fast, slow, a stop of _STOP_S seconds, crawling, then brisk."""
    count = config.num_frames
    stop_frames = min(count // 4, round(_STOP_S * config.frame_rate_hz))
    moving = count - stop_frames
    shares = np.cumsum([share for share, _ in _DENSE_SPEED_PLAN])
    progress = (np.arange(moving) + 0.5) / moving
    speed = np.array([speed for _, speed in _DENSE_SPEED_PLAN])[np.minimum(np.searchsorted(shares, progress), 4)]
    # Speed changes take about a second (a car accelerates, a pedestrian starts walking).
    speed = gaussian_filter1d(speed, sigma=config.frame_rate_hz, mode="nearest")
    speed *= np.clip(1.0 + config.speed_variation * smooth_series(rng, moving, 2.0 * config.frame_rate_hz), 0.3, None)
    at = round(_STOP_AT * moving)
    ramp = np.minimum(1.0, np.abs(np.arange(moving) - at + 0.5) / config.frame_rate_hz)  # brake and start in 1 s
    return np.concatenate([(speed * ramp)[:at], np.zeros(stop_frames), (speed * ramp)[at:]])


def drive_route(config: SynthConfig, world: World, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Camera (x, y) positions (N, 2) and headings (N,) in radians over all laps."""
    if config.route == "dense-video":
        return _dense_trajectory(config, world, rng)
    step_m = 0.05
    nodes = np.array(world.route_nodes, dtype=np.float64) * world.pitch_m
    dense: list[np.ndarray] = []
    for lap in range(config.laps):
        offset = config.lane_offset_m + config.lap_lateral_offset_m * (0.5 if lap % 2 else -0.5)
        for a, b in itertools.pairwise(nodes):
            direction = (b - a) / np.linalg.norm(b - a)
            right = np.array([direction[1], -direction[0]])
            t = np.arange(0.0, np.linalg.norm(b - a), step_m)
            dense.append(a + t[:, None] * direction + offset * right)
    # Round the corners by low-passing the polyline (about 2.5 m); this also eases lap-to-lap offset changes.
    path = gaussian_filter1d(np.concatenate(dense), sigma=2.5 / step_m, axis=0, mode="nearest")
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    speed = np.clip(1.0 + config.speed_variation * smooth_series(rng, config.num_frames, 15.0), 0.3, None)
    target = np.r_[0.0, np.cumsum(speed[:-1])]
    target *= arc[-1] * (config.num_frames - 1) / config.num_frames / max(float(target[-1]), 1e-9)

    def at(distance: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(distance, arc, path[:, 0]), np.interp(distance, arc, path[:, 1])])

    positions = at(target)
    tangent = at(np.minimum(target + 0.5, arc[-1])) - at(np.maximum(target - 0.5, 0.0))
    heading = np.arctan2(tangent[:, 1], tangent[:, 0])
    heading += np.deg2rad(config.heading_jitter_deg) * smooth_series(rng, config.num_frames, 8.0)
    return positions, heading


def _dense_trajectory(
    config: SynthConfig, world: World, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """One drive along the dense-video route, at the speeds of ``_dense_speed``; heading jitter is
    correlated over seconds (not frames), so a 30 Hz camera sways like a real one."""
    step_m = 0.05
    nodes = np.array(world.route_nodes, dtype=np.float64) * world.pitch_m
    dense: list[np.ndarray] = []
    for a, b in itertools.pairwise(nodes):
        direction = (b - a) / np.linalg.norm(b - a)
        right = np.array([direction[1], -direction[0]])
        t = np.arange(0.0, np.linalg.norm(b - a), step_m)
        dense.append(a + t[:, None] * direction + config.lane_offset_m * right)
    path = gaussian_filter1d(np.concatenate(dense), sigma=2.5 / step_m, axis=0, mode="nearest")
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    speed = _dense_speed(config, rng)
    target = np.r_[0.0, np.cumsum(speed[:-1])]
    target *= arc[-1] / max(float(target[-1]), 1e-9)

    def at(distance: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(distance, arc, path[:, 0]), np.interp(distance, arc, path[:, 1])])

    positions = at(target)
    tangent = at(np.minimum(target + 0.5, arc[-1])) - at(np.maximum(target - 0.5, 0.0))
    heading = np.arctan2(tangent[:, 1], tangent[:, 0])
    jitter = smooth_series(rng, config.num_frames, 0.8 * config.frame_rate_hz)
    return positions, heading + np.deg2rad(config.heading_jitter_deg) * jitter




def poses_from_headings(positions: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """(N, 3, 4) camera-to-world [R | t], R columns = camera right, down, forward (KITTI convention)."""
    count = headings.shape[0]
    poses = np.zeros((count, 3, 4))
    poses[:, 0, 0], poses[:, 1, 0] = np.sin(headings), -np.cos(headings)  # right
    poses[:, 2, 1] = -1.0  # down
    poses[:, 0, 2], poses[:, 1, 2] = np.cos(headings), np.sin(headings)  # forward
    poses[:, :, 3] = positions
    return poses
