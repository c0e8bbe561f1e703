"""The renderer: one ray per image column against the facades, ground and sky ray-cast per pixel, trilinear
texture filtering from the atlas, then the camera's exposure, noise and blur."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.ground_and_sky import SKY_HEIGHT_PX, SKY_WIDTH_PX
from aefabmap_ros.datasets.synth.textures import NUM_LEVELS, PAD_PX
from aefabmap_ros.datasets.synth.world import World

_MAX_LAYERS = 4  # wall hits composited per image column
_NEAR_M = 0.05
_SKY_TOP_TAN = float(np.tan(np.deg2rad(60.0)))  # tan(elevation) of the sky panorama's top row


@dataclass(frozen=True)
class PinholeCamera:
    focal_px: float
    cx: float
    cy: float
    width: int
    height: int

    @staticmethod
    def from_config(config: SynthConfig) -> PinholeCamera:
        focal = (config.width / 2) / np.tan(np.deg2rad(config.fov_deg) / 2)
        return PinholeCamera(float(focal), (config.width - 1) / 2, (config.height - 1) / 2, config.width, config.height)

    def matrix(self) -> np.ndarray:
        return np.array([[self.focal_px, 0.0, self.cx], [0.0, self.focal_px, self.cy], [0.0, 0.0, 1.0]])


@dataclass
class _ColumnHits:
    depth: np.ndarray  # (K, W) distance along the optical axis, inf where no hit
    segment: np.ndarray  # (K, W) facade index
    along_m: np.ndarray  # (K, W) position of the hit along the facade
    slope_m: np.ndarray  # (K, W) |d along / d column|, metres of wall per image column


def _cast_columns(
    world: World, camera: PinholeCamera, origin: np.ndarray, forward: np.ndarray, right: np.ndarray
) -> _ColumnHits:
    """The nearest front-facing facade hits of each image column's ray."""
    facades = world.facades
    x_col = (np.arange(camera.width) - camera.cx) / camera.focal_px
    rays = forward[None, :] + x_col[:, None] * right[None, :]  # (W, 2); unit forward part: lambda = depth
    facing = facades.normal @ rays.T  # (S, W) n.d
    offset = np.einsum("sd,sd->s", facades.normal, facades.start) - facades.normal @ origin
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = offset[:, None] / facing
    start_along = np.einsum("sd,sd->s", facades.start, facades.direction)
    along_m = (facades.direction @ origin)[:, None] + depth * (facades.direction @ rays.T) - start_along[:, None]
    valid = (facing < -1e-9) & (depth > _NEAR_M) & (along_m >= 0) & (along_m <= facades.length_m[:, None])
    depth = np.where(valid, depth, np.inf)
    layers = min(_MAX_LAYERS, depth.shape[0])
    order = np.argsort(depth, axis=0)[:layers]  # (K, W)
    columns = np.arange(camera.width)[None, :]
    # d along / d column = lambda/f * (e.r - (e.d)(n.r)/(n.d)): the texel footprint for the mip level.
    e_dot_d = facades.direction @ rays.T
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = depth / camera.focal_px * (
            (facades.direction @ right)[:, None] - e_dot_d * (facades.normal @ right)[:, None] / facing
        )
    return _ColumnHits(
        depth=depth[order, columns],
        segment=order,
        along_m=along_m[order, columns],
        slope_m=np.nan_to_num(np.abs(slope[order, columns]), nan=0.0, posinf=1e6),
    )


def _level(footprint_texels: np.ndarray) -> np.ndarray:
    """Mip level of a pixel covering this many level-0 texels."""
    result: np.ndarray = np.clip(np.log2(np.maximum(footprint_texels, 1e-6)), 0.0, NUM_LEVELS - 1.0).astype(np.float32)
    return result


@dataclass
class _Maps:
    """Per-pixel sampling plan: atlas coordinates at two mip levels, their blend, then light and haze."""

    x_low: np.ndarray  # (H, W) float32 atlas x at the finer level
    y_low: np.ndarray
    x_high: np.ndarray  # at the coarser level
    y_high: np.ndarray
    blend: np.ndarray  # (H, W) float32 weight of the coarser level
    gain: np.ndarray  # (H, W) float32 light times (1 - haze)
    offset: np.ndarray  # (H, W) float32 haze colour times haze (grey; colour images scale it per channel)


def _atlas_coordinates(
    world: World, texture: np.ndarray, level: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Atlas x, y of a texture's level-0 origin at a mip level, and that level's scale (entry tables)."""
    scale = np.exp2(-level.astype(np.float32))
    # Pixel centres: texel coordinate u (level-0 units) sits at u * scale - 0.5 at the level.
    return world.entry_x[texture, level] - 0.5, world.entry_y[texture, level] - 0.5, scale


def _haze(distance_m: np.ndarray, fog_distance_m: float) -> np.ndarray:
    return (1.0 - np.exp(-distance_m / fog_distance_m)).astype(np.float32)


def _ground_and_sky_maps(
    world: World, camera: PinholeCamera, origin: np.ndarray, heading: float, camera_height: float,
    fog_distance_m: float,
) -> _Maps:
    """Maps of the ground (rows below the horizon) and the sky (rows above), separably where possible."""
    forward = np.array([np.cos(heading), np.sin(heading)])
    right = np.array([np.sin(heading), -np.cos(heading)])
    y_row = ((np.arange(camera.height) - camera.cy) / camera.focal_px).astype(np.float32)
    x_col = ((np.arange(camera.width) - camera.cx) / camera.focal_px).astype(np.float32)
    lateral = np.sqrt(1.0 + x_col**2)
    horizon = int(np.searchsorted(y_row, 1e-6, side="right"))  # first ground row
    shape = (camera.height, camera.width)
    maps = _Maps(*(np.empty(shape, dtype=np.float32) for _ in range(7)))

    # Ground: depth per row, direction per column; texel footprint across (lambda/f) and along (lambda^2/(h f)).
    depth = (camera_height / y_row[horizon:])[:, None]
    ppm = world.ground_texels_per_m
    u = (origin[0] - world.ground_origin[0]) * ppm + depth * ((forward[0] + x_col * right[0]) * ppm)[None, :]
    v = (world.ground_origin[1] - origin[1]) * ppm - depth * ((forward[1] + x_col * right[1]) * ppm)[None, :]
    level_row = np.log2(depth[:, 0] * np.maximum(1.0, depth[:, 0] / camera_height) * ppm / camera.focal_px)
    level = np.clip(level_row[:, None] + np.log2(lateral)[None, :], 0.0, NUM_LEVELS - 1.0)
    low = np.floor(level).astype(np.int64)
    high = np.minimum(low + 1, NUM_LEVELS - 1)
    for level_index, (x_map, y_map) in ((low, (maps.x_low, maps.y_low)), (high, (maps.x_high, maps.y_high))):
        scale = np.exp2(-level_index.astype(np.float32))
        x0 = world.entry_x[world.ground_id][level_index] - 0.5
        y0 = world.entry_y[world.ground_id][level_index] - 0.5
        x_map[horizon:] = x0 + u * scale
        y_map[horizon:] = y0 + v * scale
    maps.blend[horizon:] = level - low
    haze = _haze(depth * lateral[None, :], fog_distance_m)
    maps.gain[horizon:] = 1.0 - haze
    maps.offset[horizon:] = haze

    # Sky: azimuth per column, tan(elevation) = -y / lateral; no level of detail needed (it is smooth).
    azimuth = (heading - np.arctan(x_col)) % (2 * np.pi)
    sky_u = azimuth / (2 * np.pi) * SKY_WIDTH_PX + PAD_PX
    tan_elevation = -y_row[:horizon, None] / lateral[None, :]
    sky_v = (1.0 - np.clip(tan_elevation / _SKY_TOP_TAN, 0.0, 1.0)) * (SKY_HEIGHT_PX - 1) + 0.5
    x0 = float(world.entry_x[world.sky_id, 0]) - 0.5
    y0 = float(world.entry_y[world.sky_id, 0]) - 0.5
    for x_map, y_map in ((maps.x_low, maps.y_low), (maps.x_high, maps.y_high)):
        x_map[:horizon] = (x0 + sky_u)[None, :]
        y_map[:horizon] = y0 + sky_v
    maps.blend[:horizon] = 0.0
    maps.gain[:horizon] = 1.0
    maps.offset[:horizon] = 0.0
    return maps


def _wall_maps(
    world: World, camera: PinholeCamera, hits: _ColumnHits, camera_height: float, sun_azimuth: float,
    fog_distance_m: float, maps: _Maps,
) -> np.ndarray:
    """Paint the facades into the maps: per column and layer everything but the row is known.

    Returns the depth along the optical axis of the facade drawn at each pixel, (H, W) float32, inf
    where no facade is drawn.
    """
    facades = world.facades
    finite = np.isfinite(hits.depth)
    depth = np.where(finite, hits.depth, 1.0)  # (K, W)
    segment = hits.segment
    texture = facades.texture_id[segment]
    ppm = facades.texels_per_m[segment]
    # Rows covered: wall height h - y * depth within [0, facade height].
    row_top = np.where(finite, camera.cy + camera.focal_px * (camera_height - facades.height_m[segment]) / depth,
                       np.inf)
    row_bottom = np.where(finite, camera.cy + camera.focal_px * camera_height / depth, -np.inf)
    rows = np.arange(camera.height, dtype=np.float64)[:, None]
    layer = np.full((camera.height, camera.width), -1, dtype=np.int32)
    for k in range(depth.shape[0] - 1, -1, -1):  # the nearest covering facade wins
        np.copyto(layer, k, where=(rows >= row_top[k][None, :]) & (rows <= row_bottom[k][None, :]))
    wall = layer >= 0
    flat = np.maximum(layer, 0) * camera.width + np.arange(camera.width, dtype=np.int32)[None, :]

    level = _level(np.maximum(hits.slope_m, depth / camera.focal_px) * ppm)
    low = np.floor(level).astype(np.int64)
    high = np.minimum(low + 1, NUM_LEVELS - 1)
    u = hits.along_m * ppm
    # v (texels down from the texture's top row; textures are anchored at street level) = a + y * b.
    texture_top_m = world.entry_h[texture, 0] / ppm
    v_a = (texture_top_m - camera_height) * ppm
    v_b = depth * ppm
    y_row = ((np.arange(camera.height) - camera.cy) / camera.focal_px).astype(np.float32)[:, None]
    for level_index, x_map, y_map in ((low, maps.x_low, maps.y_low), (high, maps.x_high, maps.y_high)):
        x0, y0, scale = _atlas_coordinates(world, texture, level_index)
        column_x = (x0 + u * scale).astype(np.float32).ravel()
        column_a = (y0 + v_a * scale).astype(np.float32).ravel()
        column_b = (v_b * scale).astype(np.float32).ravel()
        np.copyto(x_map, column_x.take(flat), where=wall)
        np.copyto(y_map, column_a.take(flat) + y_row * column_b.take(flat), where=wall)
    np.copyto(maps.blend, (level - low).astype(np.float32).ravel().take(flat), where=wall)
    sun = np.array([np.cos(sun_azimuth), np.sin(sun_azimuth)])
    light = 0.65 + 0.45 * np.clip(facades.normal[segment] @ sun, 0.0, 1.0)
    x_col = (np.arange(camera.width) - camera.cx) / camera.focal_px
    haze = _haze(depth * np.sqrt(1.0 + x_col**2)[None, :], fog_distance_m)
    np.copyto(maps.gain, (light * (1.0 - haze)).astype(np.float32).ravel().take(flat), where=wall)
    np.copyto(maps.offset, haze.ravel().take(flat), where=wall)
    # The same front-most layer that was painted: the camera is upright, so a column's hit depth along
    # the horizontal forward axis is its depth along the optical axis at every row.
    return np.where(wall, hits.depth.astype(np.float32).ravel().take(flat), np.float32(np.inf))


def _ground_depth(camera: PinholeCamera, camera_height: float) -> np.ndarray:
    """(H, W) float32 depth along the optical axis of the ground plane (ray-plane), 0 above the horizon."""
    y_row = ((np.arange(camera.height) - camera.cy) / camera.focal_px).astype(np.float32)
    horizon = int(np.searchsorted(y_row, 1e-6, side="right"))  # first ground row, as in _ground_and_sky_maps
    depth = np.zeros((camera.height, camera.width), dtype=np.float32)
    depth[horizon:] = (camera_height / y_row[horizon:])[:, None]
    return depth


def render_view(
    world: World,
    camera: PinholeCamera,
    position_xy: np.ndarray,
    heading_rad: float,
    camera_height_m: float,
    sun_azimuth_rad: float,
    fog_distance_m: float,
) -> np.ndarray:
    """Noise-free image of the town, float32 (H, W) or (H, W, 3) in grey levels (about 0..255)."""
    image, _ = render_view_and_depth(world, camera, position_xy, heading_rad, camera_height_m, sun_azimuth_rad,
                                     fog_distance_m)
    return image


def render_view_and_depth(
    world: World,
    camera: PinholeCamera,
    position_xy: np.ndarray,
    heading_rad: float,
    camera_height_m: float,
    sun_azimuth_rad: float,
    fog_distance_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The image of ``render_view`` and its depth map.

    Depth: (H, W) float32 metres along the optical axis (camera z) of exactly the surface drawn at
    each pixel: the front-most facade layer where a facade is drawn, else the ground (ray-plane)
    below the horizon; 0 where only sky is drawn (0 = no depth, as in ROS 16UC1 depth images).
    """
    origin = np.asarray(position_xy, dtype=np.float64)
    forward = np.array([np.cos(heading_rad), np.sin(heading_rad)])
    right = np.array([np.sin(heading_rad), -np.cos(heading_rad)])
    maps = _ground_and_sky_maps(world, camera, origin, heading_rad, camera_height_m, fog_distance_m)
    hits = _cast_columns(world, camera, origin, forward, right)
    wall_depth = _wall_maps(world, camera, hits, camera_height_m, sun_azimuth_rad, fog_distance_m, maps)
    depth = np.where(np.isfinite(wall_depth), wall_depth, _ground_depth(camera, camera_height_m))
    return _shade(world, maps), depth


def _shade(world: World, maps: _Maps) -> np.ndarray:
    """Sample the atlas with the maps: trilinear texture times light plus haze."""
    low = cv2.remap(world.atlas, maps.x_low, maps.y_low, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    high = cv2.remap(world.atlas, maps.x_high, maps.y_high, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    low = low.astype(np.float32)
    if low.ndim == 3:
        blend, gain, offset = maps.blend[:, :, None], maps.gain[:, :, None], maps.offset[:, :, None]
        shaded: np.ndarray = (low + (high - low) * blend) * gain + offset * world.fog_value
        return shaded
    result: np.ndarray = (low + (high - low) * maps.blend) * maps.gain + maps.offset * float(world.fog_value[0])
    return result


def camera_effects(
    image: np.ndarray, rng: np.random.Generator, noise: np.ndarray, gain: float, gamma: float, config: SynthConfig
) -> np.ndarray:
    """Lens blur, exposure (gain, gamma), maybe motion blur, sensor noise, 8-bit quantisation.

    ``noise`` is a bank of Gaussian noise twice the image size; each frame takes a random window of it
    (drawing fresh normal deviates for every pixel of every frame would dominate the render time).
    """
    image = cv2.GaussianBlur(image, (0, 0), 0.6)  # lens PSF; also softens pixel-stair silhouettes
    levels = np.arange(256, dtype=np.float32)
    curve = (255.0 * np.power(np.clip(gain * levels / 255.0, 0.0, 1.0), gamma)).astype(np.float32)
    quantised = np.clip(image + 0.5, 0, 255).astype(np.uint8)
    image = curve[quantised]
    if rng.random() < config.blur_probability and config.max_blur_px >= 3:
        length = int(rng.integers(3, config.max_blur_px + 1))
        kernel = np.full((1, length), 1.0 / length, dtype=np.float32)
        image = cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if config.noise_sigma > 0:
        top = int(rng.integers(0, noise.shape[0] - image.shape[0] + 1))
        left = int(rng.integers(0, noise.shape[1] - image.shape[1] + 1))
        image = image + noise[top : top + image.shape[0], left : left + image.shape[1]]
    return np.clip(image + 0.5, 0, 255).astype(np.uint8)
