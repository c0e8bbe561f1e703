"""The rigid motion two sets of matched 3-D points agree on (query = R place + t), robust to outliers.

With both frames' depths, PnP's pose can slide to a wrong solution on a far facade, where the reprojection
error is nearly flat between two motions; the 3-D points themselves tell them apart
(verification/relative_pose.py asks for this alignment).
"""

from __future__ import annotations

import numpy as np

# Below this many correspondences RANSAC has no redundancy (as relative_pose's MIN_POSE_POINTS).
MIN_ALIGNMENT_POINTS = 8

# The rigid alignment's RANSAC: a 3-D match fits when the place's point, moved, lies within this distance of the
# query's (metres, plus a share of the query point's depth: depth noise grows with range).
RIGID_TOLERANCE_M = 0.05
RIGID_RELATIVE_TOLERANCE = 0.05
# Minimal triplets drawn, all at once (fixed seed: the same pair gives the same pose). PnP's inliers are mostly
# consistent: at half of them outliers, 64 triplets miss an all-inlier one with probability 2e-4.
RIGID_HYPOTHESES = 64


def _kabsch(place_xyz: np.ndarray, query_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotations and translations (batched: (..., N, 3) point sets) with query = R place + t."""
    place_centre = place_xyz.mean(axis=-2, keepdims=True)
    query_centre = query_xyz.mean(axis=-2, keepdims=True)
    covariance = np.swapaxes(place_xyz - place_centre, -1, -2) @ (query_xyz - query_centre)
    u, _, vt = np.linalg.svd(covariance)
    v, ut = np.swapaxes(vt, -1, -2), np.swapaxes(u, -1, -2)
    reflection = np.sign(np.linalg.det(v @ ut))  # a proper rotation: no mirror image
    fix = np.broadcast_to(np.eye(3), covariance.shape).copy()
    fix[..., 2, 2] = reflection
    rotation = v @ fix @ ut
    translation = query_centre[..., 0, :] - (rotation @ place_centre[..., 0, :, None])[..., 0]
    return rotation, translation


def _scaled_distances(rotation: np.ndarray, translation: np.ndarray, place_xyz: np.ndarray,
                      query_xyz: np.ndarray) -> np.ndarray:
    """Each 3-D match's distance under the motion(s) (R: (..., 3, 3), t: (..., 3)) in units of its tolerance:
    (..., N); below 1 it agrees."""
    moved = place_xyz @ np.swapaxes(rotation, -1, -2) + translation[..., None, :]
    tolerance = RIGID_TOLERANCE_M + RIGID_RELATIVE_TOLERANCE * query_xyz[:, 2]
    scaled: np.ndarray = np.linalg.norm(moved - query_xyz, axis=-1) / tolerance
    return scaled


def misfit(rotation: np.ndarray, translation: np.ndarray, place_xyz: np.ndarray, query_xyz: np.ndarray) -> float:
    """A motion's truncated 3-D misfit (MSAC): the sum of each match's squared scaled distance, at most 1 each."""
    return float(np.minimum(_scaled_distances(rotation, translation, place_xyz, query_xyz) ** 2, 1.0).sum())


def rigid_alignment(place_xyz: np.ndarray, query_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The rigid motion (R, t; query = R place + t) most 3-D matches agree on, and its (N,) bool inliers.

    RANSAC over minimal triplets (Kabsch), refitted on the inliers; None with fewer than
    ``MIN_ALIGNMENT_POINTS`` matches or inliers."""
    count = place_xyz.shape[0]
    if count < MIN_ALIGNMENT_POINTS:
        return None
    # A triplet drawing one match twice is degenerate and simply loses.
    triplets = np.random.default_rng(0).integers(0, count, (RIGID_HYPOTHESES, 3))
    rotations, translations = _kabsch(place_xyz[triplets], query_xyz[triplets])
    fits = _scaled_distances(rotations, translations, place_xyz, query_xyz) < 1.0
    inliers = fits[int(np.argmax(fits.sum(axis=1)))]
    if np.count_nonzero(inliers) < MIN_ALIGNMENT_POINTS:
        return None
    rotation, translation = _kabsch(place_xyz[inliers], query_xyz[inliers])
    return rotation, translation, inliers
