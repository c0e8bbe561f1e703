"""The ground texture of the whole town (asphalt, lane markings, zebra crossings, paved sidewalks, manholes)
and the sky panorama, BGR uint8."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from aefabmap_ros.datasets.synth.config import GRID_COLUMNS, GRID_ROWS, SynthConfig
from aefabmap_ros.datasets.synth.textures import PAD_PX, align_px, smooth_noise, tinted

SKY_WIDTH_PX = 2048
SKY_HEIGHT_PX = 256


def ground_texture(
    config: SynthConfig, rng: np.random.Generator, pitch_m: float
) -> tuple[np.ndarray, tuple[float, float]]:
    """Asphalt with lane markings and zebra crossings, paved sidewalks, over the whole town."""
    ppm = config.ground_texels_per_m
    margin = pitch_m / 2
    x_min, y_max = -margin, GRID_ROWS * pitch_m + margin
    width_px = align_px((GRID_COLUMNS * pitch_m + 2 * margin) * ppm)
    height_px = align_px((GRID_ROWS * pitch_m + 2 * margin) * ppm)

    def px(x: float, y: float) -> tuple[int, int]:
        return int((x - x_min) * ppm), int((y_max - y) * ppm)

    asphalt = 85.0 + 12.0 * smooth_noise(rng, height_px, width_px, 3 * ppm)
    asphalt += rng.normal(0, 9.0, size=(height_px, width_px)).astype(np.float32)
    image = np.repeat(np.clip(asphalt, 0, 255)[:, :, None], 3, axis=2).astype(np.uint8)
    half_street, sidewalk = config.street_width_m / 2, min(2.0, config.street_width_m / 4)
    _draw_sidewalks(image, px, rng, config, pitch_m, sidewalk)
    line_px = max(1, int(0.12 * ppm))
    _draw_lane_markings(image, px, pitch_m, half_street, line_px)
    _draw_zebra_crossings(image, px, pitch_m, half_street, half_street - sidewalk)
    _draw_road_blemishes(image, px, rng, pitch_m, ppm)
    return image, (x_min, y_max)


_Pixel = Callable[[float, float], tuple[int, int]]  # world (x, y) in metres -> ground texture pixel
_MARK = (215, 215, 215)  # road paint


def _draw_sidewalks(image: np.ndarray, px: _Pixel, rng: np.random.Generator, config: SynthConfig, pitch_m: float,
                    sidewalk: float) -> None:
    """Paved sidewalks around every block, in one concrete colour, with a kerb."""
    half_street, ppm = config.street_width_m / 2, config.ground_texels_per_m
    grey = int(rng.integers(130, 171))
    paving = tinted(rng, (grey, grey, grey), 6)  # concrete: grey with a faint tint
    for column in range(GRID_COLUMNS):
        for row in range(GRID_ROWS):
            x0, y0 = column * pitch_m + half_street - sidewalk, row * pitch_m + half_street - sidewalk
            x1, y1 = x0 + config.block_size_m + 2 * sidewalk, y0 + config.block_size_m + 2 * sidewalk
            cv2.rectangle(image, px(x0, y1), px(x1, y0), paving, -1)
            for gx in np.arange(x0, x1, 0.6):
                cv2.line(image, px(gx, y0), px(gx, y1), (110, 110, 110), 1)
            for gy in np.arange(y0, y1, 0.6):
                cv2.line(image, px(x0, gy), px(x1, gy), (110, 110, 110), 1)
            cv2.rectangle(image, px(x0, y1), px(x1, y0), (60, 60, 60), max(1, int(0.15 * ppm)))


def _draw_lane_markings(image: np.ndarray, px: _Pixel, pitch_m: float, half_street: float, line_px: int) -> None:
    """Dashed centre lines between intersections (dashes 2 m long every 4 m), clear of the zebra crossings."""
    dashes = list(np.arange(half_street + 3.0, pitch_m - half_street - 4.99, 4.0))
    for k in range(GRID_COLUMNS + 1):
        for block in range(GRID_ROWS):
            for d in dashes:
                y = block * pitch_m + d
                cv2.line(image, px(k * pitch_m, y), px(k * pitch_m, y + 2.0), _MARK, line_px)
    for k in range(GRID_ROWS + 1):
        for block in range(GRID_COLUMNS):
            for d in dashes:
                x = block * pitch_m + d
                cv2.line(image, px(x, k * pitch_m), px(x + 2.0, k * pitch_m), _MARK, line_px)


def _draw_zebra_crossings(image: np.ndarray, px: _Pixel, pitch_m: float, half_street: float, road: float) -> None:
    """Zebra crossings on every approach of every intersection."""
    for cx in range(GRID_COLUMNS + 1):
        for cy in range(GRID_ROWS + 1):
            ox, oy = cx * pitch_m, cy * pitch_m
            for sign in (-1, 1):
                edge = sign * (half_street + 0.3)
                for stripe in np.arange(-road + 0.2, road - 0.2, 0.8):
                    cv2.rectangle(image, px(ox + stripe, oy + edge), px(ox + stripe + 0.4, oy + edge + sign * 2.0),
                                  _MARK, -1)
                    cv2.rectangle(image, px(ox + edge, oy + stripe), px(ox + edge + sign * 2.0, oy + stripe + 0.4),
                                  _MARK, -1)


def _draw_road_blemishes(image: np.ndarray, px: _Pixel, rng: np.random.Generator, pitch_m: float, ppm: float) -> None:
    """Manholes, patches and oil stains anywhere on the ground."""
    margin = pitch_m / 2
    for _ in range(int(2 * pitch_m)):
        x = rng.uniform(-margin, GRID_COLUMNS * pitch_m + margin)
        y = rng.uniform(-margin, GRID_ROWS * pitch_m + margin)
        kind = rng.random()
        if kind < 0.4:
            cv2.circle(image, px(x, y), int(0.35 * ppm), (55, 55, 55), -1, cv2.LINE_AA)
            cv2.circle(image, px(x, y), int(0.35 * ppm), (120, 120, 120), max(1, int(0.04 * ppm)), cv2.LINE_AA)
        elif kind < 0.7:
            size = rng.uniform(0.5, 2.0, size=2)
            cv2.rectangle(image, px(x, y), px(x + size[0], y + size[1]), tinted(rng, (70, 70, 70), 10), -1)
        else:
            axes = (int(rng.uniform(0.2, 0.6) * ppm), int(rng.uniform(0.1, 0.4) * ppm))
            cv2.ellipse(image, px(x, y), axes, float(rng.uniform(0, 180)), 0, 360, (45, 45, 45), -1, cv2.LINE_AA)


def sky_texture(rng: np.random.Generator) -> np.ndarray:
    """Sky panorama, periodic in azimuth: bright hazy horizon, darker zenith, soft clouds."""
    azimuth = np.linspace(0, 2 * np.pi, SKY_WIDTH_PX, endpoint=False, dtype=np.float32)
    elevation = np.linspace(1.0, 0.0, SKY_HEIGHT_PX, dtype=np.float32)  # 1 = top row
    clouds = np.zeros((SKY_HEIGHT_PX, SKY_WIDTH_PX), dtype=np.float32)
    for _ in range(12):
        frequency = int(rng.integers(1, 9))
        phase = rng.uniform(0, 2 * np.pi)
        tilt = rng.uniform(3.0, 18.0)
        clouds += np.sin(frequency * azimuth[None, :] + phase + tilt * elevation[:, None]) / 12
    clouds = np.clip(3.0 * clouds, 0.0, 1.0)
    gradient = 235.0 - 70.0 * elevation[:, None]
    tint = np.array([1.0, 0.9, 0.75], dtype=np.float32)  # BGR: bluish
    sky = np.clip(gradient[:, :, None] * tint + clouds[:, :, None] * 35.0, 0, 255).astype(np.uint8)
    # Wrap columns on both sides so bilinear taps at the azimuth seam see the other end.
    return np.concatenate([sky[:, -PAD_PX:], sky, sky[:, :PAD_PX]], axis=1)
