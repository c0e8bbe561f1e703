"""The town's geometry (city blocks cut into facades, the ring of far buildings, the routes through the
streets) and its texture atlas with mip levels."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from aefabmap_ros.datasets.synth.config import GRID_COLUMNS, GRID_ROWS, SynthConfig
from aefabmap_ros.datasets.synth.ground_and_sky import ground_texture, sky_texture
from aefabmap_ros.datasets.synth.textures import (
    NUM_LEVELS,
    PAD_PX,
    align_px,
    facade_texture,
    far_texture,
)

_ATLAS_WIDTH_PX = 4096
_FAR_TEXEL_DIVISOR = 4  # facades never seen up close get a quarter of the texel density


@dataclass
class _Facades:
    """Wall segments; the front side is to the right of p0 -> p1 (the outward normal)."""

    start: np.ndarray  # (S, 2) p0, metres
    direction: np.ndarray  # (S, 2) unit p1 - p0
    normal: np.ndarray  # (S, 2) unit outward normal
    length_m: np.ndarray  # (S,)
    height_m: np.ndarray  # (S,)
    texture_id: np.ndarray  # (S,) int64 atlas entry
    texels_per_m: np.ndarray  # (S,)


@dataclass
class World:
    """A town: its facades and one texture atlas with the mip levels of every texture."""

    facades: _Facades
    atlas: np.ndarray  # (A_h, A_w) or (A_h, A_w, 3) uint8
    entry_x: np.ndarray  # (T, L) float32 left of each texture's content per level, atlas pixels
    entry_y: np.ndarray  # (T, L) float32 top
    entry_w: np.ndarray  # (T, L) float32 content width
    entry_h: np.ndarray  # (T, L) float32 content height
    ground_id: int
    ground_origin: tuple[float, float]  # world (x, y) of the ground texture's top-left corner
    ground_texels_per_m: float
    sky_id: int
    fog_value: np.ndarray  # (C,) float32 haze colour
    route_nodes: list[tuple[int, int]]  # intersections (column, row) of the route
    pitch_m: float  # block + street


@dataclass
class _FacadeSpec:
    start: np.ndarray
    end: np.ndarray
    height_m: float
    near_route: bool


def route_nodes(route: str = "figure-eight") -> list[tuple[int, int]]:
    """The route through street intersections (column, row).

    figure-eight: closed, starting at (2, 1). dense-video: open; north up the west edge street (never
    driven again), east along the north edge, south down the middle street (rows 3 to 1), once around
    the right block and south down the middle street's lower half (rows 2 to 1) again: a revisit in
    the same direction; around the left block and north up the middle street's upper half (rows 2
    to 3): a revisit in the opposite direction.
    """
    if route == "dense-video":
        return [(0, 0), (0, 1), (0, 2), (0, 3), (1, 3), (2, 3), (2, 2), (2, 1), (3, 1), (3, 2), (2, 2), (2, 1),
                (1, 1), (1, 2), (2, 2), (2, 3)]
    return [(2, 1), (2, 2), (1, 2), (1, 1), (2, 1), (2, 2), (3, 2), (3, 1), (2, 1)]



def _near_route(point: np.ndarray, nodes: list[tuple[int, int]], pitch_m: float, tolerance_m: float) -> bool:
    """Is a world point within tolerance of a route street's centre line?"""
    for (c0, r0), (c1, r1) in itertools.pairwise(nodes):
        a = np.array([c0, r0], dtype=float) * pitch_m
        b = np.array([c1, r1], dtype=float) * pitch_m
        t = float(np.clip(np.dot(point - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0))
        if np.linalg.norm(point - (a + t * (b - a))) <= tolerance_m:
            return True
    return False


def _split_lengths(rng: np.random.Generator, total_m: float, low_m: float, high_m: float) -> list[float]:
    """Cut a length into pieces of about [low, high]."""
    pieces: list[float] = []
    remaining = total_m
    while remaining > high_m:
        piece = float(rng.uniform(low_m, high_m))
        if remaining - piece < low_m:
            piece = remaining / 2
        pieces.append(piece)
        remaining -= piece
    pieces.append(remaining)
    return pieces


def _block_facades(config: SynthConfig, rng: np.random.Generator, pitch_m: float) -> list[_FacadeSpec]:
    nodes = route_nodes(config.route)
    half_street = config.street_width_m / 2
    specs: list[_FacadeSpec] = []
    for column in range(GRID_COLUMNS):
        for row in range(GRID_ROWS):
            x0, y0 = column * pitch_m + half_street, row * pitch_m + half_street
            x1, y1 = x0 + config.block_size_m, y0 + config.block_size_m
            corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])  # counter-clockwise
            for a, b in itertools.pairwise(corners):
                unit = (b - a) / np.linalg.norm(b - a)
                normal = np.array([unit[1], -unit[0]])
                near = _near_route((a + b) / 2 + normal * half_street, nodes, pitch_m, 1.0)
                offset = 0.0
                for piece in _split_lengths(rng, float(np.linalg.norm(b - a)), 2.5, 6.5):
                    height = float(rng.uniform(4.0, 14.0))
                    specs.append(_FacadeSpec(a + unit * offset, a + unit * (offset + piece), height, near))
                    offset += piece
    return specs


def _ring_facades(rng: np.random.Generator, pitch_m: float) -> list[_FacadeSpec]:
    """Tall far buildings around the town, clockwise so that their fronts face inwards."""
    margin = pitch_m / 2
    x0, y0, x1, y1 = -margin, -margin, GRID_COLUMNS * pitch_m + margin, GRID_ROWS * pitch_m + margin
    corners = np.array([[x0, y0], [x0, y1], [x1, y1], [x1, y0], [x0, y0]])
    specs: list[_FacadeSpec] = []
    for a, b in itertools.pairwise(corners):
        unit = (b - a) / np.linalg.norm(b - a)
        offset = 0.0
        for piece in _split_lengths(rng, float(np.linalg.norm(b - a)), 6.0, 14.0):
            height = float(rng.uniform(12.0, 30.0))
            specs.append(_FacadeSpec(a + unit * offset, a + unit * (offset + piece), height, False))
            offset += piece
    return specs




def _mip_chain(texture: np.ndarray) -> list[np.ndarray]:
    levels = [texture]
    for _ in range(1, NUM_LEVELS):
        height, width = levels[-1].shape[:2]
        size = (max(1, width // 2), max(1, height // 2))
        levels.append(cv2.resize(levels[-1], size, interpolation=cv2.INTER_AREA))
    return levels


def _build_atlas(
    textures: list[np.ndarray], color: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Shelf-pack every level of every texture (padded) into one image; return it and the entry tables."""
    converted = [t if color else cv2.cvtColor(t, cv2.COLOR_BGR2GRAY) for t in textures]
    entries = [(tid, level, image) for tid, t in enumerate(converted) for level, image in enumerate(_mip_chain(t))]
    entries.sort(key=lambda entry: -entry[2].shape[0])
    table = np.zeros((4, len(textures), NUM_LEVELS), dtype=np.float32)  # x, y, w, h
    placements = []
    cursor_x = cursor_y = shelf_h = 0
    for tid, level, image in entries:
        height, width = image.shape[0] + 2 * PAD_PX, image.shape[1] + 2 * PAD_PX
        if cursor_x + width > _ATLAS_WIDTH_PX:
            cursor_x, cursor_y, shelf_h = 0, cursor_y + shelf_h, 0
        placements.append((cursor_x, cursor_y, image))
        table[:, tid, level] = (cursor_x + PAD_PX, cursor_y + PAD_PX, image.shape[1], image.shape[0])
        cursor_x += width
        shelf_h = max(shelf_h, height)
    atlas = np.zeros((cursor_y + shelf_h, _ATLAS_WIDTH_PX) + ((3,) if color else ()), dtype=np.uint8)
    for x, y, image in placements:
        padded = cv2.copyMakeBorder(image, PAD_PX, PAD_PX, PAD_PX, PAD_PX, cv2.BORDER_REPLICATE)
        atlas[y : y + padded.shape[0], x : x + padded.shape[1]] = padded
    return atlas, table[0], table[1], table[2], table[3]


def _facade_textures(
    config: SynthConfig, rng: np.random.Generator, specs: list[_FacadeSpec], ring: list[_FacadeSpec]
) -> tuple[list[np.ndarray], list[int], list[float]]:
    """Textures of all facades (shared ones first), and each facade's texture id and texel density."""
    ppm = config.texels_per_m
    pool_size, pool_width_m, pool_height_m = 3, 6.5, 14.0
    textures = [facade_texture(rng, align_px(pool_width_m * ppm), align_px(pool_height_m * ppm), ppm)
                for _ in range(pool_size)]
    texture_id: list[int] = []
    texels: list[float] = []
    for spec in specs:
        if spec.near_route and rng.random() < config.repeated_texture_fraction:
            texture_id.append(int(rng.integers(0, pool_size)))  # a chain store: the same facade elsewhere
            texels.append(ppm)
            spec.height_m = min(spec.height_m, pool_height_m)
            continue
        facade_ppm = ppm if spec.near_route else ppm / _FAR_TEXEL_DIVISOR
        length_m = float(np.linalg.norm(spec.end - spec.start))
        size = (align_px(length_m * facade_ppm), align_px(spec.height_m * facade_ppm))
        textures.append(facade_texture(rng, size[0], size[1], facade_ppm))
        texture_id.append(len(textures) - 1)
        texels.append(facade_ppm)
    far_ppm = ppm / _FAR_TEXEL_DIVISOR
    for spec in ring:
        length_m = float(np.linalg.norm(spec.end - spec.start))
        textures.append(far_texture(rng, align_px(length_m * far_ppm), align_px(spec.height_m * far_ppm), far_ppm))
        texture_id.append(len(textures) - 1)
        texels.append(far_ppm)
    return textures, texture_id, texels


def build_world(config: SynthConfig) -> World:
    """Lay out the town and draw its textures (deterministic in ``config.seed``)."""
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, 1]))
    pitch_m = config.block_size_m + config.street_width_m
    specs = _block_facades(config, rng, pitch_m)
    ring = _ring_facades(rng, pitch_m)
    textures, texture_id, texels = _facade_textures(config, rng, specs, ring)
    ground, ground_origin = ground_texture(config, rng, pitch_m)
    textures.append(ground)
    textures.append(sky_texture(rng))
    atlas, entry_x, entry_y, entry_w, entry_h = _build_atlas(textures, config.color)

    all_specs = specs + ring
    start = np.array([s.start for s in all_specs])
    vector = np.array([s.end - s.start for s in all_specs])
    length_m = np.linalg.norm(vector, axis=1)
    direction = vector / length_m[:, None]
    facades = _Facades(
        start=start,
        direction=direction,
        normal=np.column_stack([direction[:, 1], -direction[:, 0]]),
        length_m=length_m,
        height_m=np.array([s.height_m for s in all_specs]),
        texture_id=np.array(texture_id, dtype=np.int64),
        texels_per_m=np.array(texels, dtype=np.float64),
    )
    fog = np.array([200.0, 190.0, 175.0] if config.color else [188.0], dtype=np.float32)
    return World(facades, atlas, entry_x, entry_y, entry_w, entry_h, len(textures) - 2, ground_origin,
                 config.ground_texels_per_m, len(textures) - 1, fog, route_nodes(config.route), pitch_m)
