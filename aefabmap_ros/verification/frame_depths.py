"""What verification keeps of each frame's depth image: the depth at its keypoints and a coarse grid.

The metric test (``verification.metric``) needs two things of a frame's aligned depth image: the depth
at each stored keypoint (PnP's 3-D points, the keypoint view overlap) and the image itself, coarsely,
for the covisibility test (where the query's pixels land on the place's surface, occlusion included).
Both are small: ~2 KiB of keypoint depths for 500 keypoints and a float16 grid of about 80 columns
(``GRID_COLUMNS``; 80 x 60 = 9.6 KiB for a 4:3 image at any resolution), against the ~300 KiB of a
640 x 480 depth image.

``FrameDepthStore`` keeps them for the verifier's recent frames by image stamp (depth images and
features arrive on separate topics, in any order) and ``FrameDepthFolder`` saves them beside the
feature store, so the places seen before a restart keep their metric test.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.io.chunk_folder import ChunkFolder
from aefabmap_ros.io.npz_files import read_versioned_npz


def depth_size_problem(depth_size: tuple[int, int], image_size: tuple[int, int]) -> str | None:
    """Why a depth image of ``depth_size`` (width, height) cannot give the depths of an ``image_size`` image's
    keypoints: an aligned depth image has the image's pixels, and any other size would read each keypoint's
    depth at another point of the scene. None when the sizes agree."""
    if tuple(depth_size) == tuple(image_size):
        return None
    return (f"depth image {depth_size[0]}x{depth_size[1]} is not the size of its image {image_size[0]}x"
            f"{image_size[1]} (depth must be aligned to the image, pixel for pixel)")


# A keypoint's depth is read only where its four pixels agree within this share of the nearest: at a depth edge
# they hold two surfaces, and on a surface seen at a grazing angle a keypoint's sub-pixel error becomes a large
# depth error (a facade 50 m away seen at 80 degrees: about 1 m a pixel at 320 px wide). Chosen on the dense
# synthetic video, lockstep and live: metric poses over 0.2 m off 4 and 17 with the nearest pixel's depth,
# 2 and 3 with this rule (6 and 11 interpolating without it; 4 and 5 at 2 %, 6 and 4 at 5 %).
KEYPOINT_DEPTH_MAX_SPREAD = 0.03


def depth_at_pixels(depth_m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) float32 depth at each (x, y) point (pixel centres at whole coordinates): inverse depth interpolated
    bilinearly between its four pixels, exact on planes (1/z is affine in the pixel coordinates of a plane).
    NaN outside the image, where one of the four has no depth, or where they spread by more than
    ``KEYPOINT_DEPTH_MAX_SPREAD`` of the nearest of them."""
    height, width = depth_m.shape[:2]
    out = np.full(points.shape[0], np.nan, dtype=np.float32)
    x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
    inside = (x >= -0.5) & (y >= -0.5) & (x < width - 0.5) & (y < height - 0.5)
    if width < 2 or height < 2 or not inside.any():
        return out
    x, y = np.clip(x[inside], 0, width - 1), np.clip(y[inside], 0, height - 1)
    column0 = np.minimum(np.floor(x).astype(np.int64), width - 2)
    row0 = np.minimum(np.floor(y).astype(np.int64), height - 2)
    weight_x, weight_y = x - column0, y - row0
    corners = np.stack([depth_m[row0 + d_row, column0 + d_column].astype(np.float64)
                        for d_row, d_column in ((0, 0), (0, 1), (1, 0), (1, 1))])
    weights = np.stack([(1 - weight_y) * (1 - weight_x), (1 - weight_y) * weight_x, weight_y * (1 - weight_x),
                        weight_y * weight_x])
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = 1.0 / np.sum(weights / corners, axis=0)
        nearest = corners.min(axis=0)
        flat = np.all(np.isfinite(corners) & (corners > 0), axis=0) \
            & (corners.max(axis=0) - nearest <= KEYPOINT_DEPTH_MAX_SPREAD * nearest)
    out[inside] = np.where(flat, depth, np.nan)
    return out


def as_metres(values: np.ndarray, depth_scale: float = 1.0, dtype: type = np.float64) -> np.ndarray:
    """Depth values divided by ``depth_scale`` (units per metre); no depth (0, negative, NaN, inf) becomes NaN."""
    metres = values.astype(dtype) / dtype(depth_scale)
    result: np.ndarray = np.where(np.isfinite(metres) & (metres > 0), metres, dtype(np.nan))
    return result


def agrees_with_surface(sample_metres: Callable[[np.ndarray, np.ndarray], np.ndarray], x: np.ndarray, y: np.ndarray,
                        size: tuple[int, int], z: np.ndarray, tolerance_m: float,
                        relative_tolerance: float) -> np.ndarray:
    """(M,) bool: the points at sample coordinates (x, y) (columns, rows, within [0, width - 1] x
    [0, height - 1] of a ``size`` = (width, height) array of depth samples) with depth ``z`` lie on the
    sampled surface, within ``tolerance_m + relative_tolerance * z``. ``sample_metres(rows, columns)`` gives
    the samples' depths (metres, NaN = none).

    Inverse depth is interpolated bilinearly between the four samples around each point: exact on planes
    (1/z is affine in the pixel coordinates of a plane), so oblique ground and walls agree at any distance;
    across a depth edge the mix lands between the two surfaces and agrees with neither. All four samples
    must have depth. The covisibility ground truth (on every pixel) and the metric test (on a grid) share it.
    """
    width, height = size
    column0 = np.minimum(np.floor(x).astype(np.int64), width - 2)
    row0 = np.minimum(np.floor(y).astype(np.int64), height - 2)
    weight_x, weight_y = x - column0, y - row0
    inverse = np.zeros(x.size)
    for d_row, d_column, weight in ((0, 0, (1 - weight_y) * (1 - weight_x)), (0, 1, (1 - weight_y) * weight_x),
                                    (1, 0, weight_y * (1 - weight_x)), (1, 1, weight_y * weight_x)):
        inverse += weight / sample_metres(row0 + d_row, column0 + d_column)  # NaN (no depth) poisons the sum
    with np.errstate(divide="ignore", invalid="ignore"):
        agree: np.ndarray = np.abs(1.0 / inverse - z) < tolerance_m + relative_tolerance * z
    return agree


@dataclass(frozen=True)
class DepthGrid:
    """A frame's depth image sampled on a coarse grid.

    ``values[r, c]`` is the depth (metres, NaN = none) at pixel (x, y) = (offset + c * step,
    offset + r * step), offset = step // 2: the ground truth's sampling grid (``evaluation.ground_truth``).
    """

    values: np.ndarray  # (rows, columns) float16 or float32
    step: int

    def __post_init__(self) -> None:
        if isinstance(self.step, bool) or not isinstance(self.step, int | np.integer) or self.step < 1 \
                or np.asarray(self.values).ndim != 2:
            raise DataError(f"a depth grid is a 2-D array with an integer step >= 1, got shape "
                            f"{np.asarray(self.values).shape} and step {self.step!r}")

    @property
    def offset(self) -> int:
        return self.step // 2


GRID_COLUMNS = 80


def grid_step_for(width: int) -> int:
    """The grid step giving about ``GRID_COLUMNS`` columns across an image ``width`` pixels wide."""
    return max(1, round(width / GRID_COLUMNS))


def sample_depth_grid(depth_m: np.ndarray, step: int | None = None) -> DepthGrid:
    """The depth image (metres, H x W; 0, negative, NaN = none) on its coarse grid, as float16 (a relative
    precision of 0.05 %, far inside any depth tolerance; up to 65 km).

    A grid pixel without depth takes the median of its 3 x 3 neighbours that have one, when at least
    ``MIN_NEIGHBOURS_WITH_DEPTH`` do: a real sensor's scattered dropouts (edges, speckle) would otherwise
    leave holes that void every interpolation cell around them (the covisibility test needs all four
    corners), while a hole larger than a few pixels (out of range, a window) stays one.
    """
    if depth_m.ndim != 2:
        raise DataError(f"depth image must be single-channel, got shape {depth_m.shape}")
    step = grid_step_for(depth_m.shape[1]) if step is None else step
    height, width = depth_m.shape
    rows, columns = np.arange(step // 2, height, step), np.arange(step // 2, width, step)
    around = np.stack([as_metres(depth_m[np.ix_(np.clip(rows + d_row, 0, height - 1),
                                                np.clip(columns + d_column, 0, width - 1))], dtype=np.float32)
                       for d_row in (0, -1, 1) for d_column in (0, -1, 1)])  # the grid pixel itself first
    samples = around[0]
    missing = ~np.isfinite(samples) & (np.isfinite(around).sum(axis=0) >= MIN_NEIGHBOURS_WITH_DEPTH)
    if missing.any():
        samples[missing] = np.nanmedian(around[:, missing], axis=0)
    return DepthGrid(samples.astype(np.float16), step)


MIN_NEIGHBOURS_WITH_DEPTH = 3



@dataclass(frozen=True)
class FrameDepths:
    """What is kept of one frame's depth image."""

    keypoints: np.ndarray  # (N,) float32 metres at each stored keypoint, NaN = none
    grid: DepthGrid | None  # None: saved by a version that kept no grid

    @staticmethod
    def sample(depth_m: np.ndarray, keypoints: np.ndarray) -> FrameDepths:
        return FrameDepths(depth_at_pixels(depth_m, keypoints), sample_depth_grid(depth_m))


# Skipped frames remembered, for a depth image that arrives after its frame's skip was announced: at 30 Hz about
# ten seconds.
SKIPPED_REMEMBERED = 300
# Depth images waiting for their frame's features, bytes at most (float16; see FrameDepthStore).
WAITING_DEPTH_BYTES = 128 * 2**20
# Frames whose features wait for their depth image, at most (their keypoints only: a few KiB each).
WAITING_KEYPOINT_FRAMES = 1000


class FrameDepthStore:
    """The FrameDepths of recent frames, by image stamp.

    Bounded like the feature store it complements (``max_frames``, oldest first; ~12 KiB per frame).
    Depth images and features arrive on separate topics: depth images wait for their frame's features, and
    features whose depth image has not come yet are sampled when it comes (``add_features`` / ``add_depth``
    in any order). Features reach the verifier through feature_node and the depth images straight from the
    camera, and a verifier busy with a revisit takes its features seconds late (lockstep replay: up to 6 s
    on the dense synthetic video), so the images wait as float16 (the precision the grid keeps) up to
    ``max_waiting_bytes`` (``WAITING_DEPTH_BYTES``: 128 MiB, 28 s of a 30 Hz 320x240 camera, 7 s of a
    640x480 one); an image pushed out before its features came leaves that frame without depth, and the
    query verified without it (verification/depth_wait.py).
    """

    def __init__(self, max_frames: int, max_waiting_bytes: int = WAITING_DEPTH_BYTES) -> None:
        if max_frames < 1 or max_waiting_bytes < 1:
            raise ConfigError(f"FrameDepthStore needs max_frames ({max_frames}) and max_waiting_bytes "
                              f"({max_waiting_bytes}) >= 1")
        self.max_frames = max_frames
        self.max_waiting_bytes = max_waiting_bytes
        self._depths: dict[int, FrameDepths] = {}
        self._images: dict[int, np.ndarray] = {}
        self._images_nbytes = 0
        self._waiting_keypoints: dict[int, np.ndarray] = {}
        self._unsaved: dict[int, None] = {}  # stamps sampled since the last save, in order (an ordered set)
        self._skipped: dict[int, None] = {}  # recent frames announced as skipped (an ordered set)
        self._nbytes = 0  # of the kept FrameDepths' arrays

    def __len__(self) -> int:
        return len(self._depths)

    @property
    def nbytes(self) -> int:
        """Bytes of the kept frames' arrays (keypoint depths and grids; not the images waiting for features)."""
        return self._nbytes

    def forget(self, stamp_ns: int) -> None:
        """Drop that frame's depths (and anything of it still waiting)."""
        dropped = self._depths.pop(stamp_ns, None)
        if dropped is not None:
            self._nbytes -= _frame_nbytes(dropped)
        self._unsaved.pop(stamp_ns, None)
        self._pop_image(stamp_ns)
        self._waiting_keypoints.pop(stamp_ns, None)

    def __contains__(self, stamp_ns: object) -> bool:
        return stamp_ns in self._depths

    def get(self, stamp_ns: int) -> FrameDepths | None:
        return self._depths.get(stamp_ns)

    def unsaved(self) -> list[tuple[int, FrameDepths]]:
        """The frames sampled since ``mark_saved`` and still kept, oldest first (what a save appends)."""
        return [(stamp, self._depths[stamp]) for stamp in self._unsaved if stamp in self._depths]

    def mark_saved(self) -> None:
        self._unsaved.clear()

    def restore(self, frames: list[tuple[int, FrameDepths]]) -> None:
        """Replace the kept depths by saved ones (oldest first; the newest ``max_frames`` stay); they count as saved."""
        self._depths.clear()
        self._unsaved.clear()
        self._nbytes = 0
        for stamp, depths in frames:
            self.forget(stamp)
            self._depths[stamp] = depths
            self._nbytes += _frame_nbytes(depths)
        self._trim_depths()

    def skip_frame(self, stamp_ns: int) -> None:
        """A frame the detector will not process (feature_node's detection rate): its depth image, come or to
        come, is not kept, so the images waiting are those of frames whose features are on their way."""
        self._pop_image(stamp_ns)
        self._skipped[stamp_ns] = None
        _trim(self._skipped, SKIPPED_REMEMBERED)

    def add_depth(self, stamp_ns: int, depth_m: np.ndarray) -> None:
        if stamp_ns in self._skipped:
            return
        depth_m = depth_m.astype(np.float16)  # kept so, whichever comes first: the same depths in either order
        keypoints = self._waiting_keypoints.pop(stamp_ns, None)
        if keypoints is not None:
            self.keep(stamp_ns, FrameDepths.sample(depth_m.astype(np.float32), keypoints))
            return
        self._pop_image(stamp_ns)  # the same stamp twice: the newer image waits, counted once
        self._images[stamp_ns] = depth_m
        self._images_nbytes += depth_m.nbytes
        while self._images_nbytes > self.max_waiting_bytes:
            self._pop_image(next(iter(self._images)))

    def add_features(self, stamp_ns: int, keypoints: np.ndarray, image_size: tuple[int, int] | None = None) -> None:
        """The keypoints as stored for this frame (the feature store's, so the depths align with them).

        ``image_size`` (width, height) is the frame's image: a depth image of another size waiting for these
        keypoints is discarded and DataError names both sizes; the keypoints then wait for a depth image that fits."""
        image = self._pop_image(stamp_ns)
        problem = None
        if image is not None:
            problem = None if image_size is None else depth_size_problem((image.shape[1], image.shape[0]), image_size)
            if problem is None:
                self.keep(stamp_ns, FrameDepths.sample(image.astype(np.float32), keypoints))
                return
        self._waiting_keypoints[stamp_ns] = keypoints
        _trim(self._waiting_keypoints, WAITING_KEYPOINT_FRAMES)
        if problem is not None:
            raise DataError(problem)

    def _pop_image(self, stamp_ns: int) -> np.ndarray | None:
        image = self._images.pop(stamp_ns, None)
        if image is not None:
            self._images_nbytes -= image.nbytes
        return image

    def keep(self, stamp_ns: int, depths: FrameDepths) -> None:
        """Keep a frame's depths as sampled (the nodes sample them here; the offline chain brings its own)."""
        self.forget(stamp_ns)
        self._depths[stamp_ns] = depths
        self._nbytes += _frame_nbytes(depths)
        self._unsaved[stamp_ns] = None
        self._trim_depths()

    def _trim_depths(self) -> None:
        while len(self._depths) > self.max_frames:
            self.forget(next(iter(self._depths)))


DEPTH_FORMAT_VERSION = 1


class FrameDepthFolder(ChunkFolder[FrameDepths]):
    """A FrameDepthStore on disk beside the feature store's chunks (verifier_node's ``store_dir``),
    so that after a restart the places seen before it still get the metric test.

    Append-only like FeatureStoreFolder (:mod:`aefabmap_ros.io.chunk_folder`): each ``save`` writes the
    frames sampled since the last one as ``depth-<n>.npz``: stamps, per-frame counts and the keypoint
    depths concatenated (float32, NaN = none), and each frame's grid (shape, step; 0 rows = none) with
    the grids' values concatenated (float16). Chunks written before grids were kept (no grid arrays)
    still load, without grids: those places get the keypoint overlap test alone.
    """

    PREFIX: ClassVar[str] = "depth"  # its chunk files: depth-<n>.npz

    def __init__(self, folder: Path) -> None:
        super().__init__(folder, self.PREFIX, "frame depth store", _depth_arrays, _read_depth_chunk)


def _depth_arrays(frames: list[tuple[int, FrameDepths]]) -> dict[str, np.ndarray]:
    grids = [depths.grid for _, depths in frames]
    return {
        "format_version": np.array(DEPTH_FORMAT_VERSION, dtype=np.int64),
        "stamps_ns": np.array([stamp for stamp, _ in frames], dtype=np.int64),
        "counts": np.array([len(depths.keypoints) for _, depths in frames], dtype=np.int64),
        "depths": np.concatenate([depths.keypoints for _, depths in frames]).astype(np.float32),
        "grid_shapes": np.array([(0, 0) if grid is None else grid.values.shape for grid in grids],
                                dtype=np.int64).reshape(-1, 2),
        "grid_steps": np.array([0 if grid is None else grid.step for grid in grids], dtype=np.int64),
        "grid_values": np.concatenate([np.zeros(0, np.float16)] + [grid.values.astype(np.float16).ravel()
                                                                   for grid in grids if grid is not None]),
    }


def _read_depth_chunk(chunk: Path) -> list[tuple[int, FrameDepths]]:
    arrays = read_versioned_npz(chunk, "keypoint depth chunk", "keypoint depth chunk",
                                ("stamps_ns", "counts", "depths"), DEPTH_FORMAT_VERSION)
    stamps, counts, depths = arrays["stamps_ns"], arrays["counts"], arrays["depths"]
    if stamps.ndim != 1 or counts.shape != stamps.shape or depths.ndim != 1 \
            or (counts.size and counts.min() < 0) or int(counts.sum()) != depths.size:
        raise ModelError(f"keypoint depth chunk {chunk}: stamps, counts and depths do not agree")
    split = np.split(depths.astype(np.float32), np.cumsum(counts)[:-1]) if counts.size else []
    grids = _read_grids(chunk, arrays, len(stamps))
    return [(int(stamp), FrameDepths(keypoints, grid))
            for stamp, keypoints, grid in zip(stamps, split, grids, strict=True)]


def _read_grids(chunk: Path, arrays: dict[str, np.ndarray], num_frames: int) -> list[DepthGrid | None]:
    if "grid_values" not in arrays:  # written before grids were kept
        return [None] * num_frames
    shapes, steps, values = arrays.get("grid_shapes"), arrays.get("grid_steps"), arrays["grid_values"]
    if shapes is None or steps is None or shapes.shape != (num_frames, 2) or steps.shape != (num_frames,) \
            or values.ndim != 1 or (shapes.size and shapes.min() < 0) \
            or int(np.prod(shapes, axis=1).sum()) != values.size:
        raise ModelError(f"keypoint depth chunk {chunk}: the depth grids' shapes and values do not agree")
    grids: list[DepthGrid | None] = []
    start = 0
    for (rows, columns), step in zip(shapes.tolist(), steps.tolist(), strict=True):
        if rows == 0 or columns == 0:
            grids.append(None)
            continue
        size = rows * columns
        try:
            grids.append(DepthGrid(values[start:start + size].reshape(rows, columns), int(step)))
        except DataError as error:
            raise ModelError(f"keypoint depth chunk {chunk}: {error}") from error
        start += size
    return grids


def _frame_nbytes(depths: FrameDepths) -> int:
    return depths.keypoints.nbytes + (0 if depths.grid is None else depths.grid.values.nbytes)


def _trim(frames: dict[int, FrameDepths] | dict[int, np.ndarray] | dict[int, None], limit: int) -> None:
    while len(frames) > limit:
        del frames[next(iter(frames))]
