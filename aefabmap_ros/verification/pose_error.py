"""A measured relative pose against the ground truth's (the demo's and the recordings' pose scores)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class PoseError:
    """A measured relative pose against the ground truth's."""

    rotation_deg: float  # angle of R_true^T R_measured
    direction_deg: float  # angle between the translations (NaN when the true one is shorter than 1 mm)
    translation_m: float  # |t_measured - t_true| (meaningful for a metric pose only)


def relative_pose_error(query_to_world: np.ndarray, place_to_world: np.ndarray, measured: np.ndarray) -> PoseError:
    """Error of a measured place-in-query pose (4x4, ``X_query = R X_place + t``) given both cameras'
    ground-truth camera-to-world poses ((3|4, 4))."""
    def full(pose: np.ndarray) -> np.ndarray:
        matrix = np.eye(4)
        matrix[:3, :] = np.asarray(pose, dtype=np.float64)[:3, :]
        return matrix

    truth = np.linalg.inv(full(query_to_world)) @ full(place_to_world)
    estimate = full(measured)
    rotation = np.degrees(np.linalg.norm(Rotation.from_matrix(truth[:3, :3].T @ estimate[:3, :3]).as_rotvec()))
    true_t, measured_t = truth[:3, 3], estimate[:3, 3]
    lengths = np.linalg.norm(true_t) * np.linalg.norm(measured_t)
    direction = (float(np.degrees(np.arccos(np.clip(true_t @ measured_t / lengths, -1.0, 1.0))))
                 if np.linalg.norm(true_t) > 1e-3 and lengths > 0 else float("nan"))
    return PoseError(float(rotation), direction, float(np.linalg.norm(measured_t - true_t)))
