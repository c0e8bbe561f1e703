"""Relative pose of a verified loop closure: the matched place's camera in the query camera's frame.

``(R, t)`` maps a point from the place camera's frame into the query camera's:
``X_query = R @ X_place + t``, so ``t`` is the place camera's centre and ``R`` its orientation, both
in the query camera's frame (the ``geometry_msgs/Pose`` of the place camera there). Two ways to get
it from the verified matches:

* monocular (no depth): essential matrix (RANSAC) -> ``cv2.recoverPose`` -> rotation and the
  direction of translation; its length is unknown (``metric`` False, ``t`` has unit norm);
* with the depth of the place's keypoints: the place's 3-D points and the query's pixels ->
  ``cv2.solvePnPRansac`` -> rotation and metric translation (``metric`` True).

The covariance (``verification/pose_covariance.py``) is the Gauss-Newton one of the inliers' residuals
(reprojection error for PnP, Sampson error for the essential matrix), over errors along and about the
query camera's axes, with the keypoints' error at least ``min_pixel_sigma_px``. For the monocular pose
the variance along the translation direction is ``UNKNOWN_SCALE_VARIANCE``: the scale is unobserved,
and a backend must not treat the unit length as a measurement.

Degenerate geometry gives no pose, never a wrong one: too few matches (or too few with depth), too
few RANSAC inliers, or too little parallax for the essential matrix (a pure rotation leaves the
translation direction undefined). The reason is returned so that a node can count it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.verification.pose_covariance import (
    cross_matrices,
    gauss_newton_covariance,
    numeric_jacobian,
    pnp_covariance,
    to_ros_order,
)
from aefabmap_ros.verification.rigid_alignment import misfit, rigid_alignment

# Below this many correspondences RANSAC has no redundancy (5-point essential, 4-point PnP + checks).
MIN_POSE_POINTS = 8
# Variance (m^2, for a unit vector) given along the monocular translation direction: "not observed".
UNKNOWN_SCALE_VARIANCE = 1.0e6


class PoseStatus(IntEnum):
    """Why a relative pose is or is not available; the values are LoopClosure.POSE_* constants."""

    OK = 0
    NO_CAMERA_INFO = 1  # no intrinsics yet: nothing to compute with
    TOO_FEW_POINTS = 2  # fewer than MIN_POSE_POINTS matches (with depth, for PnP) or too few inliers
    PURE_ROTATION = 3  # the essential matrix's parallax is too small to give a translation direction
    ESTIMATION_FAILED = 4  # OpenCV found no model (degenerate configuration)


@dataclass(frozen=True)
class RelativePoseConfig:
    """Thresholds of the relative pose (declared by verifier_node with the prefix ``pose_``)."""

    ransac_threshold_px: float = field(default=1.0, metadata={
        "description": "RANSAC inlier threshold of the essential matrix / PnP, pixels."})
    confidence: float = field(default=0.999, metadata={"description": "RANSAC confidence of the relative pose."})
    min_inliers: int = field(default=15, metadata={
        "description": "Fewer RANSAC inliers than this: no relative pose (the closure is still published, "
                       "unless verifier_node's odometry gate is active)."})
    min_parallax_deg: float = field(default=1.0, metadata={
        "description": "Median parallax below which a monocular pose is refused (pure rotation), degrees."})
    min_pixel_sigma_px: float = field(default=0.8, metadata={
        "description": "Least standard deviation of a keypoint match (pixels) the pose covariance assumes: the "
                       "inliers' own scatter under-states it (chosen on the dense synthetic video so that 95 % "
                       "of the poses' errors lie in their covariance's 95 % region)."})

    def __post_init__(self) -> None:
        if self.ransac_threshold_px <= 0 or not 0 < self.confidence < 1:
            raise ConfigError(f"pose ransac_threshold_px ({self.ransac_threshold_px}) must be > 0 and "
                              f"confidence ({self.confidence}) in (0, 1)")
        if self.min_inliers < MIN_POSE_POINTS or self.min_parallax_deg < 0 or not self.min_pixel_sigma_px >= 0:
            raise ConfigError(f"pose min_inliers ({self.min_inliers}) must be >= {MIN_POSE_POINTS}, "
                              f"min_parallax_deg ({self.min_parallax_deg}) >= 0 and "
                              f"min_pixel_sigma_px ({self.min_pixel_sigma_px}) >= 0")


@dataclass(frozen=True)
class CameraModel:
    """Pinhole intrinsics (3x3 ``K``) and OpenCV distortion coefficients (plumb_bob / rational_polynomial)."""

    matrix: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        if self.matrix.shape != (3, 3) or not np.isfinite(self.matrix).all() or self.matrix[0, 0] <= 0 \
                or self.matrix[1, 1] <= 0:
            raise DataError(f"camera matrix must be a finite 3x3 with positive focal lengths, got {self.matrix}")
        if not np.isfinite(self.distortion).all():
            raise DataError(f"distortion coefficients must be finite, got {self.distortion}")


def camera_info_to_model(message: Any) -> CameraModel | None:
    """``sensor_msgs/CameraInfo`` (a ROS message or a rosbags one: its ``k`` and ``d``) -> intrinsics; None for
    an uncalibrated camera (K all zero; taken to be one whenever fx is 0). DataError for a K of another size,
    non-finite or non-positive focal lengths, non-finite values or distortion coefficients."""
    values = np.asarray(message.k, dtype=np.float64).reshape(-1)
    if values.size != 9:
        raise DataError(f"CameraInfo K has {values.size} values, not 9")
    matrix = values.reshape(3, 3)
    if matrix[0, 0] == 0.0:
        return None
    return CameraModel(matrix, np.asarray(message.d, dtype=np.float64))


@dataclass(frozen=True)
class RelativePose:
    """The matched place's camera in the query camera's frame."""

    rotation: np.ndarray  # (3, 3) R: X_query = R X_place + t
    translation: np.ndarray  # (3,) t; unit norm when not metric
    covariance: np.ndarray  # (6, 6) over (x, y, z, rot x, rot y, rot z)
    metric: bool  # translation in metres (PnP on depth) or a direction only (essential matrix)
    inliers: int


@dataclass(frozen=True)
class PoseOutcome:
    pose: RelativePose | None
    status: PoseStatus


def _no_pose(status: PoseStatus) -> PoseOutcome:
    return PoseOutcome(None, status)


def _check_points(query_points: np.ndarray, place_points: np.ndarray) -> None:
    if query_points.shape != place_points.shape or query_points.ndim != 2 or query_points.shape[1] != 2:
        raise DataError(f"point arrays must both be (M, 2), got {query_points.shape} and {place_points.shape}")


def _undistorted_pixels(points: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Pixels as a distortion-free camera with the same ``K`` would see them, (M, 2) float64."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 2)
    if camera.distortion.size == 0 or not np.any(camera.distortion):
        return points.reshape(-1, 2)
    return cv2.undistortPoints(points, camera.matrix, camera.distortion, P=camera.matrix).reshape(-1, 2)


def _rotation_matrix(rotation_vector: np.ndarray) -> np.ndarray:
    matrix, _ = cv2.Rodrigues(np.asarray(rotation_vector, dtype=np.float64).reshape(3, 1))
    return matrix


def _rotation_vector(rotation: np.ndarray) -> np.ndarray:
    vector, _ = cv2.Rodrigues(np.asarray(rotation, dtype=np.float64))
    return vector.reshape(3)


def _sampson_errors(rotation: np.ndarray, translation: np.ndarray, query_normalized: np.ndarray,
                    place_normalized: np.ndarray) -> np.ndarray:
    """Sampson distances (normalised image units) of x_query^T E x_place = 0, E = [t]x R."""
    t = translation / max(float(np.linalg.norm(translation)), 1e-12)
    essential = cross_matrices(t.reshape(1, 3))[0] @ rotation
    place_h = np.column_stack([place_normalized, np.ones(len(place_normalized))])
    query_h = np.column_stack([query_normalized, np.ones(len(query_normalized))])
    e_place = place_h @ essential.T  # rows: E x_place
    e_query = query_h @ essential  # rows: E^T x_query
    algebraic = np.einsum("ij,ij->i", query_h, e_place)
    scale = np.sqrt(e_place[:, 0] ** 2 + e_place[:, 1] ** 2 + e_query[:, 0] ** 2 + e_query[:, 1] ** 2)
    result: np.ndarray = algebraic / np.maximum(scale, 1e-12)
    return result


def _parallax_deg(rotation: np.ndarray, query_normalized: np.ndarray, place_normalized: np.ndarray) -> float:
    """Median angle between each query ray and its place ray rotated into the query frame."""
    query_rays = np.column_stack([query_normalized, np.ones(len(query_normalized))])
    place_rays = np.column_stack([place_normalized, np.ones(len(place_normalized))]) @ rotation.T
    cosines = np.einsum("ij,ij->i", query_rays, place_rays) / (
        np.linalg.norm(query_rays, axis=1) * np.linalg.norm(place_rays, axis=1))
    return float(np.degrees(np.median(np.arccos(np.clip(cosines, -1.0, 1.0)))))


def _is_pure_rotation(query_px: np.ndarray, place_px: np.ndarray, camera: CameraModel, config: RelativePoseConfig,
                      essential_inliers: int) -> bool:
    """True when one homography of the form K R K^-1 explains (nearly) every match the essential matrix
    does: the views differ by a rotation only, and any translation direction would be noise. An essential
    matrix fitted to such data is arbitrary, so this is tested before trusting ``recoverPose``."""
    try:
        homography, mask = cv2.findHomography(place_px, query_px, cv2.USAC_MAGSAC, config.ransac_threshold_px,
                                              confidence=config.confidence)
    except cv2.error:
        return False
    if homography is None or mask is None or np.count_nonzero(mask) < 0.9 * essential_inliers:
        return False
    normalized = np.linalg.inv(camera.matrix) @ homography @ camera.matrix
    singular = np.linalg.svd(normalized, compute_uv=False)
    # A rotation's singular values are all equal; a plane seen with parallax stretches one of them.
    return bool(singular[0] / singular[2] < 1.0 + np.radians(config.min_parallax_deg))


def essential_pose(query_points: np.ndarray, place_points: np.ndarray, camera: CameraModel,
                   config: RelativePoseConfig) -> PoseOutcome:
    """Monocular relative pose: rotation and translation direction from the essential matrix."""
    _check_points(query_points, place_points)
    if query_points.shape[0] < MIN_POSE_POINTS:
        return _no_pose(PoseStatus.TOO_FEW_POINTS)
    query_px = _undistorted_pixels(query_points, camera)
    place_px = _undistorted_pixels(place_points, camera)
    try:
        # points1 = place, points2 = query: recoverPose's (R, t) then map place-frame points to the query frame.
        essential, mask = cv2.findEssentialMat(place_px, query_px, camera.matrix, cv2.USAC_MAGSAC,
                                               config.confidence, config.ransac_threshold_px)
        if essential is None or essential.shape != (3, 3) or mask is None:
            return _no_pose(PoseStatus.ESTIMATION_FAILED)
        inliers, rotation, translation, mask = cv2.recoverPose(essential, place_px, query_px, camera.matrix,
                                                               mask=mask.copy())
    except cv2.error:
        return _no_pose(PoseStatus.ESTIMATION_FAILED)
    if _is_pure_rotation(query_px, place_px, camera, config, essential_inliers=int(np.count_nonzero(mask))):
        return _no_pose(PoseStatus.PURE_ROTATION)
    keep = mask.reshape(-1).astype(bool)
    if int(inliers) < config.min_inliers or np.count_nonzero(keep) < config.min_inliers:
        return _no_pose(PoseStatus.TOO_FEW_POINTS)
    inverse_k = np.linalg.inv(camera.matrix)
    query_n = (np.column_stack([query_px[keep], np.ones(np.count_nonzero(keep))]) @ inverse_k.T)[:, :2]
    place_n = (np.column_stack([place_px[keep], np.ones(np.count_nonzero(keep))]) @ inverse_k.T)[:, :2]
    if _parallax_deg(rotation, query_n, place_n) < config.min_parallax_deg:
        return _no_pose(PoseStatus.PURE_ROTATION)
    translation = translation.reshape(3) / np.linalg.norm(translation)

    def sampson(parameters: np.ndarray) -> np.ndarray:  # parameters: dtheta (applied as Exp(dtheta) R), t
        return _sampson_errors(_rotation_matrix(parameters[:3]) @ rotation, parameters[3:], query_n, place_n)

    parameters = np.concatenate([np.zeros(3), translation])
    # The Sampson error is in normalised image units: the pixel floor over the focal length.
    min_sigma = config.min_pixel_sigma_px / float(np.mean(np.diag(camera.matrix)[:2]))
    covariance = to_ros_order(gauss_newton_covariance(numeric_jacobian(sampson, parameters),
                                                        sampson(parameters), 5, min_sigma))
    # The Sampson error ignores the length of t: put "unobserved" along its direction.
    direction = np.outer(translation, translation)
    covariance[:3, :3] += UNKNOWN_SCALE_VARIANCE * direction
    return PoseOutcome(RelativePose(rotation, translation, covariance, metric=False, inliers=int(inliers)),
                       PoseStatus.OK)


def back_project(points: np.ndarray, depths_m: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(M, 3) camera-frame points of pixels with depth (z along the optical axis, metres)."""
    pixels = _undistorted_pixels(points, camera)
    rays = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(camera.matrix).T
    return rays * np.asarray(depths_m, dtype=np.float64).reshape(-1, 1)


def pnp_pose(query_points: np.ndarray, place_points: np.ndarray, place_depths_m: np.ndarray, camera: CameraModel,
             config: RelativePoseConfig, query_depths_m: np.ndarray | None = None) -> PoseOutcome:
    """Metric relative pose: PnP (RANSAC) of the place's 3-D points (its pixels and depth) on the query's pixels.

    ``place_depths_m`` holds each place point's depth; NaN, 0 or negative means none (that match is
    not used). With the query's depths too (``query_depths_m``, same convention), the pose is the rigid
    alignment of the inliers' two 3-D point sets (:func:`rigid_alignment`) where it fits them better than
    PnP's own solution and still reprojects them (:func:`_depth_consistent`): a far facade is nearly
    planar, and PnP of a plane seen from afar has two solutions that reproject almost equally well
    (measured on the dense synthetic video: 5-15 degrees and 5-15 m apart for streets seen again from 10-30
    m further back); the depths tell them apart.
    """
    _check_points(query_points, place_points)
    depths = np.asarray(place_depths_m, dtype=np.float64).reshape(-1)
    if depths.size != query_points.shape[0]:
        raise DataError(f"{depths.size} depths for {query_points.shape[0]} matches")
    valid = np.isfinite(depths) & (depths > 0)
    if np.count_nonzero(valid) < MIN_POSE_POINTS:
        return _no_pose(PoseStatus.TOO_FEW_POINTS)
    objects = back_project(place_points[valid], depths[valid], camera)
    images = np.ascontiguousarray(query_points[valid], dtype=np.float64)
    distortion = camera.distortion if camera.distortion.size else None
    try:
        found, rvec, tvec, inlier_index = cv2.solvePnPRansac(
            objects, images, camera.matrix, distortion, reprojectionError=config.ransac_threshold_px,
            confidence=config.confidence, iterationsCount=1000, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return _no_pose(PoseStatus.ESTIMATION_FAILED)
    if not found or inlier_index is None:
        return _no_pose(PoseStatus.ESTIMATION_FAILED)
    inlier_index = inlier_index.reshape(-1)
    if inlier_index.size < config.min_inliers:
        return _no_pose(PoseStatus.TOO_FEW_POINTS)
    objects, images = objects[inlier_index], images[inlier_index]
    rvec, tvec = cv2.solvePnPRefineLM(objects, images, camera.matrix, distortion, rvec, tvec)
    if query_depths_m is not None:
        query_depths = np.asarray(query_depths_m, dtype=np.float64).reshape(-1)
        if query_depths.size != valid.size:
            raise DataError(f"{query_depths.size} query depths for {valid.size} matches")
        rvec, tvec = _depth_consistent(rvec, tvec, objects, images, query_depths[valid][inlier_index], camera,
                                       config.ransac_threshold_px)
    covariance = pnp_covariance(objects, images, rvec, tvec, camera.matrix, distortion, config.min_pixel_sigma_px)
    return PoseOutcome(RelativePose(_rotation_matrix(rvec), tvec.reshape(3), covariance, metric=True,
                                    inliers=int(inlier_index.size)), PoseStatus.OK)


# The rigid alignment replaces PnP's pose only when it still explains the image:
RIGID_MIN_REPROJECTED = 0.9  # share of PnP's inliers the alignment must reproject within its threshold ...
# ... or within this many pixels, if more: the alignment is not fitted to the image, and at the published pose's
# 1 px the far views it is for failed (dense video: 94-97 % of their inliers within 2 px, 85-89 % within 1 px).
RIGID_CHECK_MIN_PX = 2.0


def _depth_consistent(rvec: np.ndarray, tvec: np.ndarray, objects: np.ndarray, images: np.ndarray,
                      query_depths: np.ndarray, camera: CameraModel,
                      threshold_px: float) -> tuple[np.ndarray, np.ndarray]:
    """PnP's refined pose (rvec, tvec), or the rigid alignment of its inliers' two 3-D point sets (place points
    ``objects``, query pixels ``images`` with ``query_depths``) when that alignment fits them better in 3-D
    (:func:`_misfit`) and still explains the image: ``RIGID_MIN_REPROJECTED`` of PnP's inliers reproject
    within ``threshold_px`` (at least ``RIGID_CHECK_MIN_PX``) under it. Asked only when at least eight of
    the inliers have a query depth and agree on one motion.

    Why not refine the reprojection from the alignment instead: on a far facade the reprojection error is
    nearly flat between the two solutions, and the refinement slides back to the wrong one (measured).
    """
    has_depth = np.isfinite(query_depths) & (query_depths > 0)
    if np.count_nonzero(has_depth) < MIN_POSE_POINTS:
        return rvec, tvec
    place_xyz = objects[has_depth]
    query_xyz = back_project(images[has_depth], query_depths[has_depth], camera)
    alignment = rigid_alignment(place_xyz, query_xyz)
    if alignment is None:
        return rvec, tvec
    rotation, translation, _ = alignment
    if misfit(_rotation_matrix(rvec), tvec.reshape(3), place_xyz, query_xyz) \
            <= misfit(rotation, translation, place_xyz, query_xyz):
        return rvec, tvec
    aligned = _rotation_vector(rotation).reshape(3, 1), translation.reshape(3, 1)
    distortion = camera.distortion if camera.distortion.size else None
    projected, _ = cv2.projectPoints(objects, aligned[0], aligned[1], camera.matrix, distortion)
    check_px = max(threshold_px, RIGID_CHECK_MIN_PX)
    reprojected = np.linalg.norm(projected.reshape(-1, 2) - images, axis=1) <= check_px
    if np.count_nonzero(reprojected) < RIGID_MIN_REPROJECTED * objects.shape[0]:
        return rvec, tvec
    return aligned


def relative_pose(query_points: np.ndarray, place_points: np.ndarray, camera: CameraModel | None,
                  config: RelativePoseConfig, place_depths_m: np.ndarray | None = None,
                  query_depths_m: np.ndarray | None = None) -> PoseOutcome:
    """PnP when the place's depths are known (metric; started from the 3-D alignment when the query's are
    known too), else -- or when PnP finds no pose, e.g. too few points with depth -- the essential matrix
    (direction only)."""
    if camera is None:
        return _no_pose(PoseStatus.NO_CAMERA_INFO)
    if place_depths_m is not None:
        metric = pnp_pose(query_points, place_points, place_depths_m, camera, config, query_depths_m)
        if metric.pose is not None:
            return metric
    return essential_pose(query_points, place_points, camera, config)


def pose_message_to_matrix(pose: Any) -> np.ndarray:
    """A geometry_msgs/Pose (any object with ``position`` x y z and ``orientation`` x y z w) as a 4x4 matrix."""
    q = pose.orientation
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    matrix[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return matrix
