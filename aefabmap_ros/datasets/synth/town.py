"""Synthetic town for loop-closure experiments: a textured 3-D world rendered along a looping route.

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
sequence reproduces it. ``gt_poses`` is the older pose rule: camera centres within
``gt_max_distance_m`` (2.5 m), optical axes within ``gt_max_angle_deg`` (30 deg) and
``j <= i - gt_min_gap_frames`` (10).

Poses follow KITTI's convention: camera-to-world ``[R | t]`` with camera axes x right, y down,
z forward (optical axis = third column of R); the world has x east, y north, z up, metres.
"""

from __future__ import annotations

import itertools
import string
from dataclasses import dataclass, field, fields, replace

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.evaluation.ground_truth import covisibility_loop_matrix, loop_matrix_from_poses
from aefabmap_ros.io.config_files import coerce_like

NUM_LEVELS = 5  # mip levels per texture: 1, 1/2, ..., 1/16
_ALIGN_PX = 1 << (NUM_LEVELS - 1)  # texture sizes are multiples of this, so every level halves exactly
_PAD_PX = 2  # replicated border around every atlas entry: bilinear taps never bleed into neighbours
_ATLAS_WIDTH_PX = 4096
_MAX_LAYERS = 4  # wall hits composited per image column
_NEAR_M = 0.05
_SKY_WIDTH_PX = 2048
_SKY_HEIGHT_PX = 256
_SKY_TOP_TAN = float(np.tan(np.deg2rad(60.0)))  # tan(elevation) of the sky panorama's top row
_FAR_TEXEL_DIVISOR = 4  # facades never seen up close get a quarter of the texel density
_GRID_COLUMNS, _GRID_ROWS = 4, 3  # city blocks


@dataclass(frozen=True)
class SynthConfig:
    """Parameters of one synthetic sequence (flat, so they can be ROS parameters or CLI flags)."""

    seed: int = field(default=0, metadata={"description": "Seed of the world, route jitter and camera noise."})
    num_frames: int = field(default=400, metadata={"description": "Frames over the whole route (all laps)."})
    width: int = field(default=640, metadata={"description": "Image width in pixels."})
    height: int = field(default=480, metadata={"description": "Image height in pixels."})
    fov_deg: float = field(default=60.0, metadata={"description": "Horizontal field of view in degrees."})
    color: bool = field(default=False, metadata={"description": "Render bgr8 instead of mono8 images."})
    laps: int = field(default=2, metadata={"description": "How many times the figure-eight route is driven."})
    block_size_m: float = field(default=12.0, metadata={"description": "Side of a city block in metres."})
    street_width_m: float = field(default=8.0, metadata={"description": "Street width, wall to wall, metres."})
    camera_height_m: float = field(default=1.6, metadata={"description": "Camera height above ground, metres."})
    lane_offset_m: float = field(
        default=1.0, metadata={"description": "Mean distance of the route right of the street centre line."}
    )
    lap_lateral_offset_m: float = field(
        default=0.6, metadata={"description": "Lateral distance between the paths of consecutive laps, metres."}
    )
    heading_jitter_deg: float = field(
        default=4.0, metadata={"description": "Std of the slowly varying heading jitter, degrees."}
    )
    speed_variation: float = field(default=0.2, metadata={"description": "Relative std of the slow speed changes."})
    texels_per_m: float = field(default=64.0, metadata={"description": "Texture resolution of route facades."})
    ground_texels_per_m: float = field(default=24.0, metadata={"description": "Texture resolution of the ground."})
    repeated_texture_fraction: float = field(
        default=0.2, metadata={"description": "Fraction of route facades reusing a shared texture (aliasing)."}
    )
    lighting_variation: float = field(
        default=0.25, metadata={"description": "Amplitude of global gain and gamma changes (0 = constant)."}
    )
    sun_drift_deg: float = field(default=120.0, metadata={"description": "Sun azimuth change over the sequence."})
    noise_sigma: float = field(default=3.0, metadata={"description": "Std of Gaussian pixel noise, grey levels."})
    blur_probability: float = field(
        default=0.1, metadata={"description": "Probability that a frame gets horizontal motion blur."}
    )
    max_blur_px: int = field(default=9, metadata={"description": "Longest motion-blur kernel, pixels."})
    fog_distance_m: float = field(
        default=150.0, metadata={"description": "Distance at which haze hides 63 % of a surface, metres."}
    )
    frame_rate_hz: float = field(default=10.0, metadata={"description": "Frame rate of the stamps."})
    start_stamp_ns: int = field(
        default=1_700_000_000_000_000_000, metadata={"description": "Stamp of the first frame, nanoseconds."}
    )
    gt_max_distance_m: float = field(
        default=2.5, metadata={"description": "Ground truth: largest camera-centre distance of a revisit."}
    )
    gt_max_angle_deg: float = field(
        default=30.0, metadata={"description": "Ground truth: largest optical-axis angle of a revisit."}
    )
    gt_min_gap_frames: int = field(
        default=10, metadata={"description": "Pose-rule ground truth: smallest frame gap of a revisit."}
    )
    gt_min_gap_s: float = field(
        default=5.0, metadata={"description": "Covisibility ground truth: smallest time gap of a revisit, s."}
    )
    route: str = field(
        default="figure-eight",
        metadata={"description": "figure-eight (driven `laps` times) or dense-video (one drive with a stop, "
                                 "revisits in both directions and a street never revisited; ignores laps)."},
    )

    def __post_init__(self) -> None:
        self._check_types()
        self._check_ranges()

    def _check_types(self) -> None:
        for item in fields(self):
            value = coerce_like(getattr(self, item.name), item.default)
            object.__setattr__(self, item.name, value)
            expected = type(item.default)
            if type(value) is not expected:
                raise ConfigError(f"{item.name} must be {expected.__name__}, got {value!r}")

    def _check_ranges(self) -> None:
        positive = ("num_frames", "width", "height", "laps", "block_size_m", "street_width_m", "camera_height_m",
                    "texels_per_m", "ground_texels_per_m", "fog_distance_m", "frame_rate_hz",
                    "gt_min_gap_frames", "max_blur_px")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)!r}")
        non_negative = ("noise_sigma", "heading_jitter_deg", "lap_lateral_offset_m", "gt_max_distance_m",
                        "sun_drift_deg", "start_stamp_ns", "gt_min_gap_s")
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("repeated_texture_fraction", "blur_probability"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        for name in ("lighting_variation", "speed_variation"):
            if not 0 <= getattr(self, name) < 1:
                raise ConfigError(f"{name} must be in [0, 1), got {getattr(self, name)!r}")
        if self.route not in ROUTES:
            raise ConfigError(f"route must be one of {sorted(ROUTES)}, got {self.route!r}")
        if not 10 <= self.fov_deg <= 150:
            raise ConfigError(f"fov_deg must be in [10, 150], got {self.fov_deg!r}")
        if not 0 <= self.gt_max_angle_deg <= 180:
            raise ConfigError(f"gt_max_angle_deg must be in [0, 180], got {self.gt_max_angle_deg!r}")
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"width and height must be >= 16, got {self.width}x{self.height}")
        if not self.camera_height_m < 4.0:
            raise ConfigError(f"camera_height_m must be < 4 (below the lowest facade), got {self.camera_height_m!r}")
        if not abs(self.lane_offset_m) + self.lap_lateral_offset_m / 2 < self.street_width_m / 2 - 1.0:
            raise ConfigError(
                f"lane_offset_m {self.lane_offset_m!r} with lap_lateral_offset_m {self.lap_lateral_offset_m!r} "
                f"puts the camera within 1 m of the walls of a street_width_m {self.street_width_m!r} street"
            )


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


def train_test_configs(config: SynthConfig) -> tuple[SynthConfig, SynthConfig]:
    """(train, test): the training town is another world (seed + 1000003), so the two are disjoint."""
    return replace(config, seed=config.seed + 1_000_003), config


# --------------------------------------------------------------------------------------------------
# World geometry


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


def _route_nodes(route: str = "figure-eight") -> list[tuple[int, int]]:
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


ROUTES = ("figure-eight", "dense-video")


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
    nodes = _route_nodes(config.route)
    half_street = config.street_width_m / 2
    specs: list[_FacadeSpec] = []
    for column in range(_GRID_COLUMNS):
        for row in range(_GRID_ROWS):
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
    x0, y0, x1, y1 = -margin, -margin, _GRID_COLUMNS * pitch_m + margin, _GRID_ROWS * pitch_m + margin
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


# --------------------------------------------------------------------------------------------------
# Procedural textures: BGR uint8, row 0 = top of the wall, bottom row = street level


def _align(pixels: float) -> int:
    return max(_ALIGN_PX, int(np.ceil(pixels / _ALIGN_PX)) * _ALIGN_PX)


def _smooth_noise(rng: np.random.Generator, height: int, width: int, cell_px: float) -> np.ndarray:
    """Band-limited noise in about [-1, 1]: random values on a coarse grid, bicubically upsampled."""
    rows = max(2, int(height / cell_px) + 2)
    cols = max(2, int(width / cell_px) + 2)
    coarse = rng.uniform(-1.0, 1.0, size=(rows, cols)).astype(np.float32)
    return cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)


def _colour(rng: np.random.Generator, low: int = 0, high: int = 255) -> tuple[int, int, int]:
    value = rng.integers(low, high + 1, size=3)
    return int(value[0]), int(value[1]), int(value[2])


def _tinted(rng: np.random.Generator, base: tuple[int, int, int], spread: int) -> tuple[int, int, int]:
    value = np.clip(np.array(base) + rng.integers(-spread, spread + 1, size=3), 0, 255)
    return int(value[0]), int(value[1]), int(value[2])


_LETTERS = list(string.ascii_uppercase + string.digits)
_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)


def _put_text_in_box(
    rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int], colour: tuple[int, int, int]
) -> None:
    """A random word scaled to fill most of the box (x, y, w, h)."""
    x, y, w, h = box
    if w < 8 or h < 6:
        return
    word = "".join(rng.choice(_LETTERS, size=int(rng.integers(3, 9))).tolist())
    font = int(rng.choice(_FONTS))
    thickness = max(1, int(h / 12))
    (text_w, text_h), _ = cv2.getTextSize(word, font, 1.0, thickness)
    scale = min(0.9 * w / max(text_w, 1), 0.75 * h / max(text_h, 1))
    if scale <= 0.05:
        return
    (text_w, text_h), _ = cv2.getTextSize(word, font, scale, thickness)
    cv2.putText(image, word, (x + (w - text_w) // 2, y + (h + text_h) // 2), font, scale, colour, thickness,
                cv2.LINE_AA)


def _draw_shapes(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int], count: int) -> None:
    """Circles, rectangles, triangles and thick strokes: the blobs and corners SIFT feeds on."""
    x, y, w, h = box
    if w < 6 or h < 6:
        return
    for _ in range(count):
        colour = _colour(rng)
        cx, cy = int(x + rng.uniform(0, w)), int(y + rng.uniform(0, h))
        size = max(2, int(rng.uniform(0.08, 0.35) * min(w, h)))
        kind = int(rng.integers(0, 4))
        if kind == 0:
            cv2.circle(image, (cx, cy), size, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(image, (cx - size, cy - size // 2), (cx + size, cy + size // 2), colour, -1)
        elif kind == 2:
            points = np.array([[cx, cy - size], [cx - size, cy + size], [cx + size, cy + size]], dtype=np.int32)
            cv2.fillPoly(image, [points], colour, cv2.LINE_AA)
        else:
            end = (int(cx + rng.uniform(-2, 2) * size), int(cy + rng.uniform(-2, 2) * size))
            cv2.line(image, (cx, cy), end, colour, max(1, size // 4), cv2.LINE_AA)


def _material_shade(rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray, ppm: float) -> np.ndarray:
    """Relative brightness pattern of a wall material: brick, plaster, panels, siding or stone."""
    kind = int(rng.integers(0, 5))
    if kind == 0:  # brick in running bond
        brick_h, brick_w, mortar = 0.075 * ppm, 0.24 * ppm, max(1.0, 0.012 * ppm)
        course = np.floor(rows / brick_h)
        shifted = cols + (course % 2) * brick_w / 2
        brick = np.floor(shifted / brick_w)
        jitter = rng.uniform(-0.18, 0.18, size=(int(course.max()) + 1, int(brick.max()) + 2)).astype(np.float32)
        shade = 1.0 + jitter[course.astype(np.int64), brick.astype(np.int64)]
        return np.where(((rows % brick_h) < mortar) | ((shifted % brick_w) < mortar), 1.35, shade)
    if kind == 1:  # plaster
        return 1.0 + 0.08 * _smooth_noise(rng, rows.shape[0], rows.shape[1], 0.6 * ppm)
    if kind == 2:  # concrete panels with seams
        panel_w, panel_h = rng.uniform(0.9, 1.6) * ppm, rng.uniform(0.5, 1.2) * ppm
        seam = max(1.0, 0.02 * ppm)
        panels = rng.uniform(-0.1, 0.1, size=(int(rows.max() / panel_h) + 2, int(cols.max() / panel_w) + 2))
        panel = panels.astype(np.float32)[(rows / panel_h).astype(np.int64), (cols / panel_w).astype(np.int64)]
        return np.where(((rows % panel_h) < seam) | ((cols % panel_w) < seam), 0.6, 1.0 + panel)
    if kind == 3:  # horizontal siding boards
        board = rng.uniform(0.12, 0.22) * ppm
        return 0.85 + 0.25 * (rows % board) / board
    stone_h = rng.uniform(0.25, 0.45) * ppm  # irregular stone courses
    course = np.floor(rows / stone_h).astype(np.int64)
    widths = (rng.uniform(0.3, 0.8, size=int(course.max()) + 1) * ppm).astype(np.float32)
    offsets = (rng.uniform(0, 1, size=int(course.max()) + 1) * ppm).astype(np.float32)
    shifted = cols + offsets[course]
    step = widths[course]
    stone = np.floor(shifted / step).astype(np.int64)
    jitter = rng.uniform(-0.2, 0.2, size=(int(course.max()) + 1, int(stone.max()) + 2)).astype(np.float32)
    joint_px = max(1.0, 0.02 * ppm)
    joint = ((rows % stone_h) < joint_px) | ((shifted % step) < joint_px)
    return np.where(joint, 0.55, 1.0 + jitter[course, stone])


def _material(rng: np.random.Generator, height: int, width: int, ppm: float) -> np.ndarray:
    """Wall material: a colour times a pattern, large stains and fine grain. BGR uint8."""
    base = np.array(_colour(rng, 60, 220), dtype=np.float32)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    shade = _material_shade(rng, rows, cols, ppm)
    stains = 1.0 + 0.12 * _smooth_noise(rng, height, width, 1.5 * ppm)
    grain = 1.0 + rng.normal(0.0, 0.03, size=(height, width)).astype(np.float32)
    image = base[None, None, :] * (shade * stains * grain)[:, :, None]
    return np.clip(image, 0, 255).astype(np.uint8)


def _draw_window(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int], ppm: float) -> None:
    """Window with frame, sill and one of: reflection, curtains, blinds, lit room; maybe shutters."""
    x, y, w, h = box
    frame = max(1, int(0.06 * ppm))
    frame_colour = _colour(rng, 150, 255) if rng.random() < 0.6 else _colour(rng, 20, 90)
    cv2.rectangle(image, (x - frame, y - frame), (x + w + frame, y + h + frame), frame_colour, -1)
    cv2.rectangle(image, (x, y), (x + w, y + h), _colour(rng, 15, 70), -1)
    variant = int(rng.integers(0, 5))
    if variant == 0:  # sky reflection band
        shift = int(rng.uniform(0.2, 0.6) * w)
        band = np.array([[x, y + h], [x + shift, y], [x + min(w, shift + w // 3), y], [x + w // 3, y + h]])
        cv2.fillPoly(image, [band.astype(np.int32)], _tinted(rng, (150, 140, 130), 40), cv2.LINE_AA)
    elif variant == 1:  # curtains
        colour = _colour(rng, 80, 240)
        curtain = max(2, int(w * rng.uniform(0.2, 0.45)))
        cv2.rectangle(image, (x, y), (x + curtain, y + h), colour, -1)
        cv2.rectangle(image, (x + w - curtain, y), (x + w, y + h), colour, -1)
    elif variant == 2:  # blinds
        slat = max(2, int(0.05 * ppm))
        for row in range(y, y + int(rng.uniform(0.2, 1.0) * h), slat):
            cv2.line(image, (x, row), (x + w, row), _tinted(rng, (200, 200, 200), 20), max(1, slat // 2))
    elif variant == 3:  # lit room
        cv2.rectangle(image, (x, y), (x + w, y + h), _tinted(rng, (120, 200, 230), 25), -1)
        _draw_shapes(rng, image, (x, y, w, h), 2)
    if rng.random() < 0.7:  # mullions
        cv2.line(image, (x + w // 2, y), (x + w // 2, y + h), frame_colour, frame)
        if rng.random() < 0.5:
            cv2.line(image, (x, y + h // 3), (x + w, y + h // 3), frame_colour, frame)
    sill = max(2, int(0.07 * ppm))
    cv2.rectangle(image, (x - 2 * frame, y + h + frame), (x + w + 2 * frame, y + h + frame + sill),
                  _colour(rng, 150, 240), -1)
    if rng.random() < 0.2:  # shutters
        shutter_colour = _colour(rng, 30, 200)
        for left in (x - frame - w // 2, x + w + frame):
            cv2.rectangle(image, (left, y), (left + w // 2, y + h), shutter_colour, -1)
            for row in range(y, y + h, max(3, int(0.06 * ppm))):
                cv2.line(image, (left, row), (left + w // 2, row), (20, 20, 20), 1)


def _draw_poster(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int]) -> None:
    x, y, w, h = box
    cv2.rectangle(image, (x, y), (x + w, y + h), _colour(rng), -1)
    _draw_shapes(rng, image, box, int(rng.integers(3, 8)))
    _put_text_in_box(rng, image, (x, y + int(0.05 * h), w, int(0.25 * h)), _colour(rng))
    cv2.rectangle(image, (x, y), (x + w, y + h), _colour(rng, 0, 60), 2)


def _draw_shop(rng: np.random.Generator, image: np.ndarray, top: int, door: tuple[int, int], ppm: float) -> None:
    """Sign band with a name above display windows with posters; maybe a striped awning."""
    height, width = image.shape[:2]
    door_x, door_w = door
    sign_h = int(rng.uniform(0.5, 0.9) * ppm)
    sign_y = max(0, top + int(0.2 * ppm))
    cv2.rectangle(image, (0, sign_y), (width, sign_y + sign_h), _colour(rng), -1)
    _put_text_in_box(rng, image, (int(0.05 * width), sign_y, int(0.9 * width), sign_h), _colour(rng))
    pane_top = sign_y + sign_h + int(0.2 * ppm)
    for left, right in ((0, door_x - int(0.2 * ppm)), (door_x + door_w + int(0.2 * ppm), width)):
        if right - left < int(0.8 * ppm):
            continue
        box = (left + int(0.15 * ppm), pane_top, right - left - int(0.3 * ppm), height - pane_top - int(0.5 * ppm))
        cv2.rectangle(image, (box[0], box[1]), (box[0] + box[2], box[1] + box[3]), _colour(rng, 10, 60), -1)
        poster_w, poster_h = int(box[2] * rng.uniform(0.3, 0.6)), int(box[3] * rng.uniform(0.4, 0.8))
        px = box[0] + int(rng.uniform(0, max(1, box[2] - poster_w)))
        py = box[1] + int(rng.uniform(0, max(1, box[3] - poster_h)))
        _draw_poster(rng, image, (px, py, poster_w, poster_h))
    if rng.random() < 0.5:
        stripe = max(2, int(0.25 * ppm))
        colours = (_colour(rng), _colour(rng))
        for index, left in enumerate(range(0, width, stripe)):
            cv2.rectangle(image, (left, sign_y - int(0.1 * ppm)), (left + stripe, sign_y), colours[index % 2], -1)


def _draw_ground_floor(rng: np.random.Generator, image: np.ndarray, top: int, ppm: float) -> None:
    """A door, then a shop front or an entrance with a number plate and small windows."""
    height, width = image.shape[:2]
    door_w, door_h = int(rng.uniform(0.9, 1.4) * ppm), int(rng.uniform(2.1, 2.5) * ppm)
    door_x = int(rng.uniform(0.1, 0.8) * max(1, width - door_w))
    cv2.rectangle(image, (door_x, height - door_h), (door_x + door_w, height), _colour(rng, 20, 160), -1)
    cv2.rectangle(image, (door_x + door_w // 6, height - door_h + door_h // 8),
                  (door_x + door_w - door_w // 6, height - door_h // 2), _colour(rng, 20, 90), -1)
    cv2.circle(image, (door_x + door_w - door_w // 8, height - door_h // 2), max(2, int(0.04 * ppm)),
               (200, 210, 220), -1, cv2.LINE_AA)
    if rng.random() < 0.6:
        _draw_shop(rng, image, top, (door_x, door_w), ppm)
        return
    plate = int(0.3 * ppm)
    px, py = door_x + door_w + int(0.2 * ppm), height - door_h
    cv2.rectangle(image, (px, py), (px + plate, py + plate), (40, 90, 160), -1)
    _put_text_in_box(rng, image, (px, py, plate, plate), (255, 255, 255))
    for _ in range(int(rng.integers(1, 3))):
        w, h = int(0.8 * ppm), int(1.2 * ppm)
        wx = int(rng.uniform(0, max(1, width - w)))
        if abs(wx - door_x) >= door_w + w:
            _draw_window(rng, image, (wx, height - int(2.3 * ppm), w, h), ppm)


def _draw_decals(rng: np.random.Generator, image: np.ndarray, ppm: float) -> None:
    """Pasted posters, graffiti, a drainpipe, air conditioners and small blobs."""
    height, width = image.shape[:2]
    for _ in range(int(rng.integers(0, 3))):
        w, h = int(rng.uniform(0.5, 1.0) * ppm), int(rng.uniform(0.7, 1.3) * ppm)
        x = int(rng.uniform(0, max(1, width - w)))
        y = height - int(rng.uniform(1.0, 2.2) * ppm) - h // 2
        _draw_poster(rng, image, (x, max(0, y), w, h))
    if rng.random() < 0.35:
        colour = _colour(rng)
        for _ in range(int(rng.integers(2, 6))):
            points = np.column_stack([rng.uniform(0, width, 5), height - rng.uniform(0.2, 1.6, 5) * ppm])
            cv2.polylines(image, [points.astype(np.int32)], False, colour, max(2, int(0.05 * ppm)), cv2.LINE_AA)
    if rng.random() < 0.5:
        x = int(rng.choice([int(0.1 * ppm), width - int(0.15 * ppm)]))
        cv2.line(image, (x, 0), (x, height), _colour(rng, 30, 120), max(2, int(0.08 * ppm)))
        for y in range(0, height, max(1, int(1.5 * ppm))):
            cv2.line(image, (x - int(0.06 * ppm), y), (x + int(0.06 * ppm), y), (40, 40, 40), 2)
    for _ in range(int(rng.integers(0, 3))):
        w, h = int(0.8 * ppm), int(0.5 * ppm)
        x, y = int(rng.uniform(0, max(1, width - w))), int(rng.uniform(0, max(1, height - 4 * ppm)))
        cv2.rectangle(image, (x, y), (x + w, y + h), (210, 210, 205), -1)
        cv2.circle(image, (x + w // 3, y + h // 2), max(1, int(0.18 * ppm)), (90, 90, 90), -1, cv2.LINE_AA)
        for gx in range(x + 2 * w // 3, x + w - 2, max(2, int(0.05 * ppm))):
            cv2.line(image, (gx, y + 3), (gx, y + h - 3), (120, 120, 120), 1)
    for _ in range(int(rng.integers(5, 25))):
        centre = (int(rng.uniform(0, width)), int(rng.uniform(0, height)))
        cv2.circle(image, centre, max(2, int(rng.uniform(0.02, 0.15) * ppm)), _colour(rng), -1, cv2.LINE_AA)


def _facade_texture(rng: np.random.Generator, width_px: int, height_px: int, ppm: float) -> np.ndarray:
    """A building facade: material, storeys of windows, a ground floor, decals. BGR uint8."""
    image = _material(rng, height_px, width_px, ppm)
    ground_floor_px = int(rng.uniform(3.2, 4.2) * ppm)
    storey_px = int(rng.uniform(2.8, 3.4) * ppm)
    window_w, window_h = int(rng.uniform(0.7, 1.5) * ppm), int(rng.uniform(1.1, 1.7) * ppm)
    count = max(1, int(width_px / (window_w + rng.uniform(0.5, 1.4) * ppm)))
    spacing = width_px / count
    storey_bottom = height_px - ground_floor_px
    while storey_bottom - storey_px >= int(0.5 * ppm):
        window_y = storey_bottom - int(0.9 * ppm) - window_h
        if window_y > 0:
            for index in range(count):
                _draw_window(rng, image, (int((index + 0.5) * spacing - window_w / 2), window_y, window_w, window_h),
                             ppm)
        if rng.random() < 0.3:  # cornice between storeys
            cv2.rectangle(image, (0, storey_bottom - int(0.1 * ppm)), (width_px, storey_bottom),
                          _colour(rng, 100, 230), -1)
        storey_bottom -= storey_px
    _draw_ground_floor(rng, image, height_px - ground_floor_px, ppm)
    _draw_decals(rng, image, ppm)
    return image


def _far_texture(rng: np.random.Generator, width_px: int, height_px: int, ppm: float) -> np.ndarray:
    """Distant tall building: material and a regular grid of windows, some lit."""
    image = _material(rng, height_px, width_px, ppm)
    cell_w, cell_h = rng.uniform(1.5, 3.0) * ppm, rng.uniform(2.8, 3.5) * ppm
    dark, lit = _colour(rng, 10, 90), _tinted(rng, (140, 210, 235), 20)
    for top in np.arange(0.5 * ppm, height_px - 2 * ppm, cell_h):
        for left in np.arange(0.3 * ppm, width_px - cell_w / 2, cell_w):
            colour = lit if rng.random() < 0.15 else dark
            cv2.rectangle(image, (int(left), int(top)), (int(left + 0.6 * cell_w), int(top + 0.5 * cell_h)),
                          colour, -1)
    return image


def _ground_texture(
    config: SynthConfig, rng: np.random.Generator, pitch_m: float
) -> tuple[np.ndarray, tuple[float, float]]:
    """Asphalt with lane markings and zebra crossings, paved sidewalks, over the whole town."""
    ppm = config.ground_texels_per_m
    margin = pitch_m / 2
    x_min, y_max = -margin, _GRID_ROWS * pitch_m + margin
    width_px = _align((_GRID_COLUMNS * pitch_m + 2 * margin) * ppm)
    height_px = _align((_GRID_ROWS * pitch_m + 2 * margin) * ppm)

    def px(x: float, y: float) -> tuple[int, int]:
        return int((x - x_min) * ppm), int((y_max - y) * ppm)

    asphalt = 85.0 + 12.0 * _smooth_noise(rng, height_px, width_px, 3 * ppm)
    asphalt += rng.normal(0, 9.0, size=(height_px, width_px)).astype(np.float32)
    image = np.repeat(np.clip(asphalt, 0, 255)[:, :, None], 3, axis=2).astype(np.uint8)
    half_street, sidewalk = config.street_width_m / 2, min(2.0, config.street_width_m / 4)
    grey = int(rng.integers(130, 171))
    paving = _tinted(rng, (grey, grey, grey), 6)  # concrete: grey with a faint tint
    for column in range(_GRID_COLUMNS):
        for row in range(_GRID_ROWS):
            x0, y0 = column * pitch_m + half_street - sidewalk, row * pitch_m + half_street - sidewalk
            x1, y1 = x0 + config.block_size_m + 2 * sidewalk, y0 + config.block_size_m + 2 * sidewalk
            cv2.rectangle(image, px(x0, y1), px(x1, y0), paving, -1)
            for gx in np.arange(x0, x1, 0.6):
                cv2.line(image, px(gx, y0), px(gx, y1), (110, 110, 110), 1)
            for gy in np.arange(y0, y1, 0.6):
                cv2.line(image, px(x0, gy), px(x1, gy), (110, 110, 110), 1)
            cv2.rectangle(image, px(x0, y1), px(x1, y0), (60, 60, 60), max(1, int(0.15 * ppm)))
    mark, line_px = (215, 215, 215), max(1, int(0.12 * ppm))
    # Dashed centre lines between intersections (dashes 2 m long every 4 m), clear of the zebra crossings.
    dashes = list(np.arange(half_street + 3.0, pitch_m - half_street - 4.99, 4.0))
    for k in range(_GRID_COLUMNS + 1):
        for block in range(_GRID_ROWS):
            for d in dashes:
                y = block * pitch_m + d
                cv2.line(image, px(k * pitch_m, y), px(k * pitch_m, y + 2.0), mark, line_px)
    for k in range(_GRID_ROWS + 1):
        for block in range(_GRID_COLUMNS):
            for d in dashes:
                x = block * pitch_m + d
                cv2.line(image, px(x, k * pitch_m), px(x + 2.0, k * pitch_m), mark, line_px)
    road = half_street - sidewalk
    for cx in range(_GRID_COLUMNS + 1):  # zebra crossings on every approach of every intersection
        for cy in range(_GRID_ROWS + 1):
            ox, oy = cx * pitch_m, cy * pitch_m
            for sign in (-1, 1):
                edge = sign * (half_street + 0.3)
                for stripe in np.arange(-road + 0.2, road - 0.2, 0.8):
                    cv2.rectangle(image, px(ox + stripe, oy + edge), px(ox + stripe + 0.4, oy + edge + sign * 2.0),
                                  mark, -1)
                    cv2.rectangle(image, px(ox + edge, oy + stripe), px(ox + edge + sign * 2.0, oy + stripe + 0.4),
                                  mark, -1)
    for _ in range(int(2 * pitch_m)):  # manholes, patches and oil stains
        x = rng.uniform(-margin, _GRID_COLUMNS * pitch_m + margin)
        y = rng.uniform(-margin, _GRID_ROWS * pitch_m + margin)
        kind = rng.random()
        if kind < 0.4:
            cv2.circle(image, px(x, y), int(0.35 * ppm), (55, 55, 55), -1, cv2.LINE_AA)
            cv2.circle(image, px(x, y), int(0.35 * ppm), (120, 120, 120), max(1, int(0.04 * ppm)), cv2.LINE_AA)
        elif kind < 0.7:
            size = rng.uniform(0.5, 2.0, size=2)
            cv2.rectangle(image, px(x, y), px(x + size[0], y + size[1]), _tinted(rng, (70, 70, 70), 10), -1)
        else:
            axes = (int(rng.uniform(0.2, 0.6) * ppm), int(rng.uniform(0.1, 0.4) * ppm))
            cv2.ellipse(image, px(x, y), axes, float(rng.uniform(0, 180)), 0, 360, (45, 45, 45), -1, cv2.LINE_AA)
    return image, (x_min, y_max)


def _sky_texture(rng: np.random.Generator) -> np.ndarray:
    """Sky panorama, periodic in azimuth: bright hazy horizon, darker zenith, soft clouds."""
    azimuth = np.linspace(0, 2 * np.pi, _SKY_WIDTH_PX, endpoint=False, dtype=np.float32)
    elevation = np.linspace(1.0, 0.0, _SKY_HEIGHT_PX, dtype=np.float32)  # 1 = top row
    clouds = np.zeros((_SKY_HEIGHT_PX, _SKY_WIDTH_PX), dtype=np.float32)
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
    return np.concatenate([sky[:, -_PAD_PX:], sky, sky[:, :_PAD_PX]], axis=1)


# --------------------------------------------------------------------------------------------------
# Texture atlas with mip levels


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
        height, width = image.shape[0] + 2 * _PAD_PX, image.shape[1] + 2 * _PAD_PX
        if cursor_x + width > _ATLAS_WIDTH_PX:
            cursor_x, cursor_y, shelf_h = 0, cursor_y + shelf_h, 0
        placements.append((cursor_x, cursor_y, image))
        table[:, tid, level] = (cursor_x + _PAD_PX, cursor_y + _PAD_PX, image.shape[1], image.shape[0])
        cursor_x += width
        shelf_h = max(shelf_h, height)
    atlas = np.zeros((cursor_y + shelf_h, _ATLAS_WIDTH_PX) + ((3,) if color else ()), dtype=np.uint8)
    for x, y, image in placements:
        padded = cv2.copyMakeBorder(image, _PAD_PX, _PAD_PX, _PAD_PX, _PAD_PX, cv2.BORDER_REPLICATE)
        atlas[y : y + padded.shape[0], x : x + padded.shape[1]] = padded
    return atlas, table[0], table[1], table[2], table[3]


def _facade_textures(
    config: SynthConfig, rng: np.random.Generator, specs: list[_FacadeSpec], ring: list[_FacadeSpec]
) -> tuple[list[np.ndarray], list[int], list[float]]:
    """Textures of all facades (shared ones first), and each facade's texture id and texel density."""
    ppm = config.texels_per_m
    pool_size, pool_width_m, pool_height_m = 3, 6.5, 14.0
    textures = [_facade_texture(rng, _align(pool_width_m * ppm), _align(pool_height_m * ppm), ppm)
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
        size = (_align(length_m * facade_ppm), _align(spec.height_m * facade_ppm))
        textures.append(_facade_texture(rng, size[0], size[1], facade_ppm))
        texture_id.append(len(textures) - 1)
        texels.append(facade_ppm)
    far_ppm = ppm / _FAR_TEXEL_DIVISOR
    for spec in ring:
        length_m = float(np.linalg.norm(spec.end - spec.start))
        textures.append(_far_texture(rng, _align(length_m * far_ppm), _align(spec.height_m * far_ppm), far_ppm))
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
    ground, ground_origin = _ground_texture(config, rng, pitch_m)
    textures.append(ground)
    textures.append(_sky_texture(rng))
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
                 config.ground_texels_per_m, len(textures) - 1, fog, _route_nodes(config.route), pitch_m)


# --------------------------------------------------------------------------------------------------
# Trajectory


def _smooth_series(rng: np.random.Generator, count: int, correlation: float) -> np.ndarray:
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
    speed *= np.clip(1.0 + config.speed_variation * _smooth_series(rng, moving, 2.0 * config.frame_rate_hz), 0.3, None)
    at = round(_STOP_AT * moving)
    ramp = np.minimum(1.0, np.abs(np.arange(moving) - at + 0.5) / config.frame_rate_hz)  # brake and start in 1 s
    return np.concatenate([(speed * ramp)[:at], np.zeros(stop_frames), (speed * ramp)[at:]])


def _trajectory(config: SynthConfig, world: World, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
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
    speed = np.clip(1.0 + config.speed_variation * _smooth_series(rng, config.num_frames, 15.0), 0.3, None)
    target = np.r_[0.0, np.cumsum(speed[:-1])]
    target *= arc[-1] * (config.num_frames - 1) / config.num_frames / max(float(target[-1]), 1e-9)

    def at(distance: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(distance, arc, path[:, 0]), np.interp(distance, arc, path[:, 1])])

    positions = at(target)
    tangent = at(np.minimum(target + 0.5, arc[-1])) - at(np.maximum(target - 0.5, 0.0))
    heading = np.arctan2(tangent[:, 1], tangent[:, 0])
    heading += np.deg2rad(config.heading_jitter_deg) * _smooth_series(rng, config.num_frames, 8.0)
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
    jitter = _smooth_series(rng, config.num_frames, 0.8 * config.frame_rate_hz)
    return positions, heading + np.deg2rad(config.heading_jitter_deg) * jitter


def dense_video_config(*, seed: int = 0, width: int = 320, height: int = 240, num_frames: int = 3600) -> SynthConfig:
    """The dense-video preset: 2 minutes of 30 Hz video along the dense-video route (about 315 m: slow,
    fast, a 4 s stop, a revisit in the same and one in the opposite direction, a street never
    revisited). 320x240 by default: see aefabmap_synth's docstring for the render times."""
    return SynthConfig(seed=seed, num_frames=num_frames, width=width, height=height, route="dense-video",
                       frame_rate_hz=30.0, laps=1, gt_min_gap_frames=150, blur_probability=0.05)


# --------------------------------------------------------------------------------------------------
# Renderer


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
    sky_u = azimuth / (2 * np.pi) * _SKY_WIDTH_PX + _PAD_PX
    tan_elevation = -y_row[:horizon, None] / lateral[None, :]
    sky_v = (1.0 - np.clip(tan_elevation / _SKY_TOP_TAN, 0.0, 1.0)) * (_SKY_HEIGHT_PX - 1) + 0.5
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


def _camera_effects(
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


def poses_from_headings(positions: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """(N, 3, 4) camera-to-world [R | t], R columns = camera right, down, forward (KITTI convention)."""
    count = headings.shape[0]
    poses = np.zeros((count, 3, 4))
    poses[:, 0, 0], poses[:, 1, 0] = np.sin(headings), -np.cos(headings)  # right
    poses[:, 2, 1] = -1.0  # down
    poses[:, 0, 2], poses[:, 1, 2] = np.cos(headings), np.sin(headings)  # forward
    poses[:, :, 3] = positions
    return poses


def generate_sequence(config: SynthConfig) -> SyntheticSequence:
    """Build the town of ``config.seed`` and render ``config.num_frames`` frames along its route."""
    world = build_world(config)
    motion_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 2]))
    camera_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 3]))
    count = config.num_frames
    positions_xy, headings = _trajectory(config, world, motion_rng)
    camera_heights = config.camera_height_m + 0.05 * _smooth_series(motion_rng, count, 20.0)
    progress = np.arange(count) / max(count - 1, 1)
    sun_azimuth = motion_rng.uniform(0, 2 * np.pi) + np.deg2rad(config.sun_drift_deg) * progress
    variation = config.lighting_variation
    gains = 1.0 + variation * np.tanh(_smooth_series(motion_rng, count, count / 6))
    gains *= 1.0 + 0.02 * variation * motion_rng.normal(size=count)  # auto-exposure flicker
    gammas = 1.0 + 0.5 * variation * np.tanh(_smooth_series(motion_rng, count, count / 5))
    camera = PinholeCamera.from_config(config)
    noise_shape = (2 * config.height, 2 * config.width) + ((3,) if config.color else ())
    noise = camera_rng.normal(0.0, config.noise_sigma, size=noise_shape).astype(np.float32)
    images = []
    depths = np.empty((count, config.height, config.width), dtype=np.float32)
    for index in range(count):
        radiance, depths[index] = render_view_and_depth(
            world, camera, positions_xy[index], float(headings[index]), float(camera_heights[index]),
            float(sun_azimuth[index]), config.fog_distance_m)
        images.append(_camera_effects(radiance, camera_rng, noise, float(gains[index]), float(gammas[index]), config))
    positions = np.column_stack([positions_xy, camera_heights])
    axes = np.column_stack([np.cos(headings), np.sin(headings), np.zeros(count)])
    gt_poses = loop_matrix_from_poses(positions, axes, config.gt_max_distance_m, config.gt_max_angle_deg,
                                      config.gt_min_gap_frames)
    stamps = config.start_stamp_ns + np.rint(np.arange(count) * (1e9 / config.frame_rate_hz)).astype(np.int64)
    poses = poses_from_headings(positions, headings)
    gt = covisibility_loop_matrix(depth_to_16uc1(depths), poses, camera.matrix(), stamps,
                                  min_gap_s=config.gt_min_gap_s, depth_scale=1000.0)
    return SyntheticSequence(images, stamps, positions, axes, gt, poses, camera.matrix(), depths, gt_poses)
