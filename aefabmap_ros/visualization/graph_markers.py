"""The pose graph as drawable primitives: keyframes, odometry edges, loop edges (accepted / refused by the
backend's gate) and the trajectory before (odometry) and after (optimised) the closures.

Pure data (points and colours); nodes/view_messages.py turns each :class:`MarkerSpec` into a
``visualization_msgs/Marker``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

Colour = tuple[float, float, float, float]  # RGBA, 0-1
KEYFRAME_COLOUR: Colour = (0.2, 0.5, 1.0, 1.0)
ODOMETRY_EDGE_COLOUR: Colour = (0.6, 0.6, 0.6, 1.0)
ACCEPTED_LOOP_COLOUR: Colour = (0.1, 0.85, 0.2, 1.0)
REFUSED_LOOP_COLOUR: Colour = (0.95, 0.15, 0.1, 1.0)
ODOMETRY_PATH_COLOUR: Colour = (0.9, 0.6, 0.1, 0.8)
OPTIMISED_PATH_COLOUR: Colour = (0.2, 0.5, 1.0, 0.9)


class Shape(Enum):
    """The visualization_msgs/Marker types used here."""

    SPHERE_LIST = "sphere_list"
    LINE_LIST = "line_list"  # pairs of points: one segment each
    LINE_STRIP = "line_strip"  # one polyline


@dataclass(frozen=True)
class MarkerSpec:
    namespace: str
    shape: Shape
    points: np.ndarray  # (N, 3) float64, metres in the map frame
    colours: np.ndarray  # (N, 4) RGBA per point (a LINE_LIST's segment takes its two points' colours)
    width_m: float


@dataclass
class GraphDrawing:
    """What the backend knows, in the map frame."""

    keyframes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3) optimised, by stamp
    odometry_path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (P, 3) odometry alone
    loops: list[tuple[np.ndarray, np.ndarray, bool]] = field(default_factory=list)  # (from, to, accepted)


def graph_markers(drawing: GraphDrawing, keyframe_size_m: float = 0.4, line_width_m: float = 0.08) -> list[MarkerSpec]:
    """One marker per namespace, every namespace always present (an empty one clears what a viewer showed)."""
    keyframes = np.asarray(drawing.keyframes, np.float64).reshape(-1, 3)
    consecutive = np.repeat(keyframes, 2, axis=0)[1:-1] if len(keyframes) > 1 else np.zeros((0, 3))
    loop_points = np.array([point for start, end, _ in drawing.loops for point in (start, end)],
                           np.float64).reshape(-1, 3)
    loop_colours = [ACCEPTED_LOOP_COLOUR if accepted else REFUSED_LOOP_COLOUR
                    for _, _, accepted in drawing.loops for _ in range(2)]
    return [
        _spec("keyframes", Shape.SPHERE_LIST, keyframes, KEYFRAME_COLOUR, keyframe_size_m),
        _spec("odometry_edges", Shape.LINE_LIST, consecutive, ODOMETRY_EDGE_COLOUR, line_width_m),
        MarkerSpec("loop_edges", Shape.LINE_LIST, loop_points, np.array(loop_colours, np.float64).reshape(-1, 4),
                   line_width_m * 1.5),
        _spec("trajectory_odometry", Shape.LINE_STRIP, np.asarray(drawing.odometry_path, np.float64).reshape(-1, 3),
              ODOMETRY_PATH_COLOUR, line_width_m),
        _spec("trajectory_optimised", Shape.LINE_STRIP, keyframes, OPTIMISED_PATH_COLOUR, line_width_m),
    ]


def _spec(namespace: str, shape: Shape, points: np.ndarray, colour: Colour, width_m: float) -> MarkerSpec:
    return MarkerSpec(namespace, shape, points, np.tile(np.array(colour, np.float64), (len(points), 1)), width_m)


class PathThinner:
    """Keeps a trajectory's points at least ``spacing_m`` apart: the odometry path drawn at a few points per metre,
    not at the odometry's rate."""

    def __init__(self, spacing_m: float, max_points: int = 20_000) -> None:
        self.spacing_m = spacing_m
        self.max_points = max_points
        self._points: list[np.ndarray] = []

    def add(self, point: np.ndarray) -> bool:
        if self._points and float(np.linalg.norm(point - self._points[-1])) < self.spacing_m:
            return False
        self._points.append(np.asarray(point, np.float64))
        if len(self._points) > self.max_points:  # a long run: keep every other point of the older half
            half = len(self._points) // 2
            self._points = self._points[:half:2] + self._points[half:]
        return True

    def points(self) -> np.ndarray:
        return np.array(self._points, np.float64).reshape(-1, 3)
