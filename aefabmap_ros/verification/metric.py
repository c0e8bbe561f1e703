"""Metric verification: with depth, a candidate can be checked in 3-D instead of by its share of keypoints.

The epipolar test (``verification.geometric``) asks two things of a candidate: enough matches fit
one fundamental matrix, and they are a large enough share of the keypoints (the overlap proxy that
keeps repeated textures out). The share is what rejects most true revisits it misses: a street seen
again from 10-30 m further back, or 20-40 degrees turned, shares a small part of either image, so
its 25-40 inliers are 5-10 % of the keypoints (measured on the dense synthetic video, where 437
queries with a true place among their 5 verified candidates were rejected so).

With the depth at each keypoint and the camera intrinsics, both can be measured directly:

* **one rigid motion**: the place's keypoints with depth are 3-D points; PnP (RANSAC) finds the
  motion that projects them onto the query's matched pixels (the matches the epipolar test kept: a
  rigid motion's inliers fit its epipolar geometry too). A point-to-point reprojection test (2-D,
  within ``ransac_threshold_px``) is far stricter than a point-to-line epipolar one, so chance
  matches that fit a fundamental matrix rarely fit it;
* **the views overlap**: under that motion, the query's own keypoints with depth are carried into
  the place's camera. The share of them that land in front of it and inside its image is how much
  of what the query sees the place saw too. A loop on the edge of a revisit, the same corner seen
  from 45 degrees further round, gets its inliers but little overlap;
* **the views are covisible** (with both depth images, kept as coarse grids: ``frame_depths``): the
  query's pixels with depth, carried by the motion, land on the surface the place itself saw, within
  ``metric_depth_tolerance_m`` + ``metric_depth_relative_tolerance`` x depth -- the covisibility
  ground truth's own rule, occlusion included. A corner of the demo's town seen 31 degrees round, with
  its pose right, is refused by it: 62 % of the query's keypoints fall inside
  the place's image, but a building the place saw in front hides most of them, so 22 % of its
  surface is covisible, under the ground truth's 30 %.

With the query's depths the motion is also picked between PnP's two near-equal solutions for a far,
nearly planar facade (``relative_pose.pnp_pose``): measured on the dense synthetic video, PnP alone
gives streets seen again from 10-30 m further back poses 5-15 degrees and metres off, which the
covisibility test then refuses as not covisible; with the 3-D alignment they are within 0.4 degrees
and 0.4 m, and covisible.

The query's depths check the motion independently of the place's, which PnP used. A candidate is
accepted by this test when at least ``metric_min_inliers`` matches fit the motion and at least
``metric_min_view_overlap`` of the query's keypoints land in the place's view. It is asked of pairs the
epipolar test refused for their share alone (``min_inliers`` inliers, too few of the keypoints), and it
fits its motion to the matches under its own, looser Lowe's ratio (``metric_ratio``, 0.9) that lie
within ``ransac_threshold_px`` of the epipolar lines the epipolar test found: here the reprojection test
and the overlap keep chance matches out, and a far view's true matches are often ambiguous at 0.8 (a
facade's repeated windows, a smaller scale). Taking them by the geometry already fitted costs no second
robust fit (a refit gives the same closures: 1,692 against 1,687 on the dense video's offline chain). A pair the
epipolar test accepted is checked too, on its epipolar inliers: when they fit one motion under which the
views do not overlap, it is refused (e.g. the same corner seen 50 degrees and 2 m further round,
60 inliers and 13 % of the keypoints, is the ground truth's edge, not a revisit). Pairs with few
keypoint depths (a keypoint on a depth edge samples the background) keep the epipolar decision.

The default asks 30 inliers of the motion: with 25, PnP on all matches accepted a perpendicular view of the
demo's town under a wrong motion (26 inliers, 90 % overlap under its own motion). Figures:
docs/verification.md. What it does not stop: a look-alike built as a copy (the second synthetic town's
copied corners) fits one motion and overlaps as a true revisit does; odometry refuses those (``backend.odometry_gate``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aefabmap_ros.errors import DataError
from aefabmap_ros.verification.frame_depths import DepthGrid, agrees_with_surface
from aefabmap_ros.verification.relative_pose import (
    CameraModel,
    RelativePose,
    RelativePoseConfig,
    back_project,
    pnp_pose,
)

_EDGE = 1e-6  # grid units
QUERY_SUBSAMPLE = 2  # the covisibility test carries every this-many-th grid sample of the query, each way


@dataclass(frozen=True)
class KeypointDepths:
    """What the metric test needs beside the two frames' features."""

    camera: CameraModel
    image_size: tuple[int, int]  # (width, height) of the images, pixels
    query: np.ndarray  # (Nq,) metres at each query keypoint; NaN, 0 or negative = none
    place: np.ndarray  # (Np,) metres at each place keypoint
    # The two frames' depth images on their coarse grids, for the covisibility test (None: not kept).
    query_grid: DepthGrid | None = None
    place_grid: DepthGrid | None = None

    def __post_init__(self) -> None:
        width, height = self.image_size
        if width <= 0 or height <= 0:
            raise DataError(f"image size must be positive, got {self.image_size}")
        for name in ("query", "place"):
            if np.asarray(getattr(self, name)).ndim != 1:
                raise DataError(f"{name} keypoint depths must be one value per keypoint, got shape "
                                f"{np.asarray(getattr(self, name)).shape}")


@dataclass(frozen=True)
class MetricCheck:
    """Outcome of the metric test of one pair."""

    inliers: int  # matches that fit the rigid motion (0: no motion found)
    view_overlap: float  # share of the query's keypoints with depth inside the place's view under it
    # share of the query's grid pixels with depth that land on the place's own surface under it (NaN: no grids)
    covisibility: float = float("nan")


NO_MOTION = MetricCheck(0, 0.0)


def metric_check(query_keypoints: np.ndarray, query_points: np.ndarray, place_points: np.ndarray,
                 place_rows: np.ndarray, depths: KeypointDepths, threshold_px: float, confidence: float,
                 min_inliers: int, depth_tolerance: tuple[float, float] = (0.05, 0.05),
                 query_rows: np.ndarray | None = None) -> MetricCheck:
    """PnP of the place's matched keypoints (with depth) on the query's, and the view overlap under it.

    query_keypoints: (Nq, >= 2) all the query's keypoints (x, y first), aligned with ``depths.query``.
    query_points, place_points: (M, 2) the matches' pixels; place_rows: (M,) each match's place
    keypoint row (into ``depths.place``). No motion with fewer than ``min_inliers`` inliers. With each match's
    query keypoint row (``query_rows``, into ``depths.query``) the query's depths pick PnP's solution
    (``relative_pose.pnp_pose``). With both depth grids, the covisibility under the motion too, with
    ``depth_tolerance`` (metres, relative).
    """
    if query_keypoints.shape[0] != depths.query.shape[0]:
        raise DataError(f"{depths.query.shape[0]} query keypoint depths for {query_keypoints.shape[0]} keypoints")
    if place_rows.size and int(place_rows.max()) >= depths.place.shape[0]:
        raise DataError(f"place keypoint row {int(place_rows.max())} has no depth ({depths.place.shape[0]} depths)")
    query_depths = None if query_rows is None else depths.query[query_rows].astype(np.float64)
    outcome = pnp_pose(query_points, place_points, depths.place[place_rows].astype(np.float64), depths.camera,
                       RelativePoseConfig(ransac_threshold_px=threshold_px, confidence=confidence,
                                          min_inliers=min_inliers), query_depths)
    if outcome.pose is None:
        return NO_MOTION
    covisible = (float("nan") if depths.query_grid is None or depths.place_grid is None
                 else covisibility(depths.query_grid, depths.place_grid, outcome.pose, depths.camera, *depth_tolerance))
    return MetricCheck(outcome.pose.inliers, view_overlap(query_keypoints, depths, outcome.pose), covisible)


def view_overlap(query_keypoints: np.ndarray, depths: KeypointDepths, pose: RelativePose) -> float:
    """Share of the query's keypoints with depth that land in front of the place's camera and inside its
    image, carried there by ``pose`` (X_query = R X_place + t); 0 when no query keypoint has depth."""
    values = np.asarray(depths.query, dtype=np.float64)
    valid = np.isfinite(values) & (values > 0)
    if not valid.any():
        return 0.0
    pixels, _ = _carried_into_place(query_keypoints[valid, :2], values[valid], pose, depths.camera)
    width, height = depths.image_size
    inside = (pixels[:, 0] >= 0) & (pixels[:, 0] <= width - 1) & (pixels[:, 1] >= 0) & (pixels[:, 1] <= height - 1)
    return float(np.count_nonzero(inside)) / float(np.count_nonzero(valid))


def covisibility(query: DepthGrid, place: DepthGrid, pose: RelativePose, camera: CameraModel,
                 tolerance_m: float = 0.05, relative_tolerance: float = 0.01) -> float:
    """Share of the query's grid pixels with depth that, carried by ``pose`` (X_query = R X_place + t) into
    the place's camera, land on the surface the place saw: in front of it, inside its grid, and within
    ``tolerance_m + relative_tolerance * z`` of its depth there (the covisibility ground truth's rule and
    tolerances, with the estimated motion for the true poses). Unlike :func:`view_overlap` it knows about
    occlusion: a facade the query sees behind a corner the place saw in front of it does not count.
    0 when the query grid has no depth. The query's side takes every other grid sample each way (40 x 30:
    the ground truth's own count on a 320 x 240 image), a quarter of the cost on a busy verifier."""
    step = QUERY_SUBSAMPLE * query.step
    rows, columns = np.nonzero(np.isfinite(query.values[::QUERY_SUBSAMPLE, ::QUERY_SUBSAMPLE]))
    if rows.size == 0:
        return 0.0
    values = query.values[rows * QUERY_SUBSAMPLE, columns * QUERY_SUBSAMPLE]
    pixels = np.column_stack([query.offset + columns * step, query.offset + rows * step])
    projected, depths = _carried_into_place(pixels.astype(np.float64), values.astype(np.float64), pose, camera)
    agreeing = _agrees_with_grid(place, projected, depths, tolerance_m, relative_tolerance)
    return float(np.count_nonzero(agreeing)) / float(rows.size)


def _carried_into_place(pixels: np.ndarray, depths_m: np.ndarray, pose: RelativePose,
                        camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """The query's ``pixels`` (M, 2) with depth, carried by ``pose`` into the place's camera: the (K, 2) pixels
    and (K,) depths there of those that land in front of it."""
    in_query = back_project(pixels, depths_m, camera)
    in_place = (in_query - pose.translation) @ pose.rotation  # R^T (X - t), row by row
    in_front = in_place[:, 2] > 0
    if not in_front.any():
        return np.zeros((0, 2)), np.zeros(0)
    distortion = camera.distortion if camera.distortion.size else None
    projected, _ = cv2.projectPoints(in_place[in_front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                     camera.matrix, distortion)
    return projected.reshape(-1, 2), in_place[in_front, 2]


def _agrees_with_grid(grid: DepthGrid, pixels: np.ndarray, depths_m: np.ndarray, tolerance_m: float,
                      relative_tolerance: float) -> np.ndarray:
    """(M,) bool: the points at ``pixels`` with depth ``depths_m`` lie on the grid's surface there
    (``frame_depths.agrees_with_surface``, the ground truth's interpolation, between grid samples)."""
    height, width = grid.values.shape
    # Rounding in the round trip through 3-D must not move a point on the grid's last row off it.
    grid_x = (pixels[:, 0] - grid.offset) / grid.step
    grid_y = (pixels[:, 1] - grid.offset) / grid.step
    inside = (grid_x >= -_EDGE) & (grid_x <= width - 1 + _EDGE) & (grid_y >= -_EDGE) & (grid_y <= height - 1 + _EDGE)
    agree = np.zeros(len(pixels), bool)
    if width < 2 or height < 2 or not inside.any():
        return agree
    values = grid.values.astype(np.float64)
    agree[inside] = agrees_with_surface(lambda rows, columns: values[rows, columns],
                                        np.clip(grid_x[inside], 0, width - 1), np.clip(grid_y[inside], 0, height - 1),
                                        (width, height), depths_m[inside], tolerance_m, relative_tolerance)
    return agree
