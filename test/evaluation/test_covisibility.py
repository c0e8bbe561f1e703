"""Covisibility ground truth from depth, checked against closed forms (a plane seen shifted) and a per-pixel
brute force over a rendered room."""

import math

import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.evaluation.covisibility import covisibility_loop_matrix, covisibility_with_stats

WIDTH, HEIGHT, FOCAL, STEP = 100, 80, 50.0, 10  # grid columns 5, 15, ..., 95; rows 5, ..., 75
K = np.array([[FOCAL, 0.0, 49.5], [0.0, FOCAL, 39.5], [0.0, 0.0, 1.0]])
SECOND_NS = 1_000_000_000


def _pose(position=(0.0, 0.0, 0.0), yaw_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world [R | t]: the camera turned by yaw about its own y (down) axis."""
    angle = math.radians(yaw_deg)
    rotation = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    return np.hstack([rotation, np.reshape(position, (3, 1))])


def _plane_pair(shift_px: float, depth_m: float = 4.0, depth_j: np.ndarray | None = None, gap_s: float = 10.0):
    """Frame 0 = j, frame 1 = i: both see a fronto-parallel plane at depth_m; i sits shift_px * depth / f
    left of j, so i's pixel u lands at u - shift_px in j."""
    baseline_m = shift_px * depth_m / FOCAL
    poses = np.stack([_pose((baseline_m, 0.0, 0.0)), _pose()])
    depths = np.full((2, HEIGHT, WIDTH), depth_m)
    if depth_j is not None:
        depths[0] = depth_j
    stamps = np.array([0, int(gap_s * SECOND_NS)], dtype=np.int64)
    return depths, poses, stamps


def _closed_form_fraction(shift_px: float) -> float:
    """Share of grid columns u (every row has the same ones) with 0 <= u - shift <= W - 1."""
    columns = np.arange(STEP // 2, WIDTH, STEP)
    return float(np.mean((columns - shift_px >= 0) & (columns - shift_px <= WIDTH - 1)))


@pytest.mark.parametrize("shift_px", [0.0, 24.9, 44.9, 64.9, 74.9, 75.1, 80.0, 95.1, -74.9, -75.1, 120.0])
def test_plane_overlap_matches_closed_form(shift_px):
    depths, poses, stamps = _plane_pair(shift_px)
    expected = _closed_form_fraction(shift_px)
    for min_fraction in (0.3, 0.5, 0.7):
        gt = covisibility_loop_matrix(depths, poses, K, stamps, min_fraction=min_fraction, grid_step_px=STEP)
        assert gt[1, 0] == (expected >= min_fraction), (shift_px, expected, min_fraction)
        assert gt[0, 1] == 0  # lower-triangular: only later frames revisit earlier ones


def test_thirty_percent_boundary_on_both_sides():
    # Shift 74.9 px keeps columns 75, 85, 95 of 10: exactly 30 %; 75.1 px keeps 85, 95: 20 %.
    assert _closed_form_fraction(74.9) == 0.3 and _closed_form_fraction(75.1) == 0.2
    for shift_px, expected in ((74.9, 1), (75.1, 0)):
        depths, poses, stamps = _plane_pair(shift_px)
        assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP)[1, 0] == expected
    # The fraction's denominator is i's grid points with depth: hide 5 of i's 10 columns and the
    # 3 remaining visible columns of 5 are 60 %.
    depths, poses, stamps = _plane_pair(74.9)
    depths[1][:, :50] = 0.0
    assert covisibility_loop_matrix(depths, poses, K, stamps, min_fraction=0.6, grid_step_px=STEP)[1, 0] == 1
    assert covisibility_loop_matrix(depths, poses, K, stamps, min_fraction=0.61, grid_step_px=STEP)[1, 0] == 0


def test_far_plane_needs_the_relative_tolerance():
    """A plane at 40 m seen 0.3 m deeper by j: outside 5 cm, inside 5 cm + 1 % of 40 m."""
    depths, poses, stamps = _plane_pair(0.0, depth_m=40.0, depth_j=np.full((HEIGHT, WIDTH), 40.3))
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP)[1, 0] == 1
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP, relative_tolerance=0.0)[1, 0] == 0


def test_occluder_in_front_of_j_is_not_covisible():
    occluded = np.full((HEIGHT, WIDTH), 4.0)
    occluded[:, :] = 2.0  # a second plane 2 m in front of j hides the whole wall
    depths, poses, stamps = _plane_pair(10.0, depth_j=occluded)
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP)[1, 0] == 0
    # An occluder over j's left 60 columns: of i's points (landing at u - 10), those at j columns >= 61
    # (bilinear needs both neighbours on the wall) are 75, 85, 95 -> i columns 75..95: 3 of 10.
    partial = np.full((HEIGHT, WIDTH), 4.0)
    partial[:, :60] = 2.0
    depths, poses, stamps = _plane_pair(10.0, depth_j=partial)
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP, min_fraction=0.3)[1, 0] == 1
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP, min_fraction=0.31)[1, 0] == 0


def test_time_gap_rule():
    for gap_s, expected in ((4.999, 0), (5.0, 1), (60.0, 1)):
        depths, poses, stamps = _plane_pair(0.0, gap_s=gap_s)
        assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP)[1, 0] == expected
    depths, poses, stamps = _plane_pair(0.0, gap_s=1.0)
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP, min_gap_s=1.0)[1, 0] == 1
    # Same stamps with gap 0: still only earlier frames (lower triangle), never the frame itself.
    gt = covisibility_loop_matrix(depths, poses, K, np.zeros(2, np.int64), grid_step_px=STEP, min_gap_s=0.0)
    assert gt.tolist() == [[0, 0], [1, 0]]


@pytest.mark.parametrize("yaw_deg", [90.0, 180.0, -90.0])
def test_camera_looking_away_sees_nothing(yaw_deg):
    depths, _, stamps = _plane_pair(0.0)
    poses = np.stack([_pose(yaw_deg=yaw_deg), _pose()])
    depths[0] = 4.0  # j's depth map says there is a surface 4 m ahead of j too: still another surface
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP, prune_voxel_m=None)[1, 0] == 0
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP)[1, 0] == 0


# A room of 6 planes (n . p = d, normals pointing inside): every ray from inside hits a wall.
_ROOM = [((1, 0, 0), -5.0), ((-1, 0, 0), -5.0), ((0, 1, 0), -1.5), ((0, -1, 0), -1.5), ((0, 0, 1), -6.0),
         ((0, 0, -1), -6.0)]


def _room_depth(pose: np.ndarray, camera: np.ndarray, height: int, width: int) -> np.ndarray:
    """Depth along the optical axis of the nearest room plane at every pixel (ray-plane, per pixel)."""
    depth = np.full((height, width), np.inf)
    inverse = np.linalg.inv(camera)
    for row in range(height):
        for column in range(width):
            ray = pose[:, :3] @ (inverse @ [column, row, 1.0])
            for normal, offset in _ROOM:
                facing = float(np.dot(normal, ray))
                if facing < 0:
                    along = (offset - float(np.dot(normal, pose[:, 3]))) / facing
                    if along > 0:
                        depth[row, column] = min(depth[row, column], along)
    return depth


def _brute_force_covisibility(depths, poses, camera, stamps, min_fraction, gap_s, step, tol, rel, max_angle=None):
    """The rule of DESIGN 9.2 one pixel at a time, in plain Python floats."""
    n, height, width = depths.shape
    fx, fy, cx, cy = camera[0, 0], camera[1, 1], camera[0, 2], camera[1, 2]
    gt = np.zeros((n, n), np.uint8)

    def has_depth(value):
        return math.isfinite(value) and value > 0

    for i in range(n):
        for j in range(i):
            if stamps[i] - stamps[j] < gap_s * 1e9:
                continue
            total = agree = 0
            for row in range(step // 2, height, step):
                for column in range(step // 2, width, step):
                    d = float(depths[i, row, column])
                    if not has_depth(d):
                        continue
                    total += 1
                    camera_point = [(column - cx) / fx * d, (row - cy) / fy * d, d]
                    world = [sum(poses[i][a][b] * camera_point[b] for b in range(3)) + poses[i][a][3] for a in range(3)]
                    local = [sum(poses[j][b][a] * (world[b] - poses[j][b][3]) for b in range(3)) for a in range(3)]
                    z = local[2]
                    if z <= 0:
                        continue
                    u, v = fx * local[0] / z + cx, fy * local[1] / z + cy
                    if not (0 <= u <= width - 1 and 0 <= v <= height - 1):
                        continue
                    c0, r0 = min(math.floor(u), width - 2), min(math.floor(v), height - 2)
                    corners = [float(depths[j, r0 + a, c0 + b]) for a in (0, 1) for b in (0, 1)]
                    if not all(has_depth(value) for value in corners):
                        continue
                    wu, wv = u - c0, v - r0
                    inverse = ((1 - wv) * ((1 - wu) / corners[0] + wu / corners[1])
                               + wv * ((1 - wu) / corners[2] + wu / corners[3]))
                    if abs(1 / inverse - z) < tol + rel * z:
                        from_i = [world[a] - poses[i][a][3] for a in range(3)]
                        from_j = [world[a] - poses[j][a][3] for a in range(3)]
                        cosine = sum(a * b for a, b in zip(from_i, from_j, strict=True)) / (
                            math.hypot(*from_i) * math.hypot(*from_j))
                        if max_angle is None or math.degrees(math.acos(max(-1.0, min(1.0, cosine)))) <= max_angle:
                            agree += 1
            if total and agree / total >= min_fraction:
                gt[i, j] = 1
    return gt


@pytest.fixture(scope="module")
def room_sequence():
    """Eight 32x24 views in a room, with holes in the depth, and some turned away from the others."""
    rng = np.random.default_rng(7)
    height, width = 24, 32
    camera = np.array([[20.0, 0.0, 15.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]])
    poses = np.stack([_pose((rng.uniform(-2, 2), rng.uniform(-0.3, 0.3), rng.uniform(-3, 3)),
                            float(rng.choice([0.0, 20.0, 40.0, 180.0, 200.0]) + rng.uniform(-10, 10)))
                      for _ in range(8)])
    depths = np.stack([_room_depth(pose, camera, height, width) for pose in poses])
    depths[rng.random(depths.shape) < 0.1] = 0.0  # sensor holes
    depths[:, :3, :3] = np.nan
    stamps = (np.arange(8) * 3 * SECOND_NS).astype(np.int64)
    return depths, poses, camera, stamps


@pytest.mark.parametrize(("min_fraction", "gap_s", "step", "tol", "angle"),
                         [(0.3, 5.0, 4, 0.05, None), (0.5, 0.0, 3, 0.01, None), (0.1, 2.0, 5, 0.2, None),
                          (0.2, 0.0, 4, 0.05, 30.0)])
def test_matches_per_pixel_brute_force(room_sequence, min_fraction, gap_s, step, tol, angle):
    depths, poses, camera, stamps = room_sequence
    reference = _brute_force_covisibility(depths, poses, camera, stamps, min_fraction, gap_s, step, tol, 0.01, angle)
    assert 0 < reference.sum() < np.tril(np.ones_like(reference), -1).sum()  # a mix of revisits and not
    for voxel in (None, 2.0, 1.0, 0.5):
        gt = covisibility_loop_matrix(depths, poses, camera, stamps, min_fraction=min_fraction, min_gap_s=gap_s,
                                      grid_step_px=step, tolerance_m=tol, prune_voxel_m=voxel,
                                      max_view_angle_deg=angle)
        np.testing.assert_array_equal(gt, reference, err_msg=f"prune_voxel_m={voxel}")


def test_cameras_facing_each_other_share_the_room_but_not_the_view():
    """Two cameras 6 m apart look at each other in the room: the floor, ceiling and side walls between
    them are covisible by depth, but each sees them from the opposite side."""
    camera = np.array([[20.0, 0.0, 15.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]])
    poses = np.stack([_pose((0.0, 0.0, 3.0), 180.0), _pose((0.0, 0.0, -3.0), 0.0)])
    depths = np.stack([_room_depth(pose, camera, 24, 32) for pose in poses])
    stamps = np.array([0, 10 * SECOND_NS])
    plain = _brute_force_covisibility(depths, poses, camera, stamps, 0.3, 5.0, 4, 0.05, 0.01)
    assert plain[1, 0] == 1
    assert covisibility_loop_matrix(depths, poses, camera, stamps, grid_step_px=4)[1, 0] == 1
    assert covisibility_loop_matrix(depths, poses, camera, stamps, grid_step_px=4, max_view_angle_deg=90.0)[1, 0] == 0


def test_integer_millimetre_depths_and_stats(room_sequence):
    depths, poses, camera, stamps = room_sequence
    millimetres = np.where(np.isfinite(depths), np.round(depths * 1000), 0).astype(np.uint16)
    metres = covisibility_loop_matrix(millimetres / 1000.0, poses, camera, stamps, min_fraction=0.2)
    gt, stats = covisibility_with_stats(millimetres, poses, camera, stamps, min_fraction=0.2, depth_scale=1000.0)
    np.testing.assert_array_equal(gt, metres)
    assert stats.num_frames == 8 and stats.revisit_pairs == int(gt.sum()) > 0
    assert stats.revisiting_frames == int(gt.any(axis=1).sum())
    assert stats.revisit_pairs <= stats.candidate_pairs <= 8 * 7 // 2


def test_empty_and_depthless_sequences():
    gt = covisibility_loop_matrix(np.zeros((0, 4, 4)), np.zeros((0, 3, 4)), K, np.zeros(0, np.int64))
    assert gt.shape == (0, 0)
    depths, poses, stamps = _plane_pair(0.0)
    depths[:] = 0.0
    assert covisibility_loop_matrix(depths, poses, K, stamps, grid_step_px=STEP).sum() == 0


def _bad(**changes):
    depths, poses, stamps = _plane_pair(0.0)
    arguments = {"depths": depths, "poses": poses, "camera_matrix": K, "stamps_ns": stamps}
    arguments.update(changes)
    return arguments


@pytest.mark.parametrize(
    ("changes", "error", "match"),
    [
        ({"depths": np.ones((HEIGHT, WIDTH))}, DataError, r"depths must have shape \(N, H, W\), got \(80, 100\)"),
        ({"depths": np.ones((2, 1, 5))}, DataError, "at least 2x2 pixels, got 1x5"),
        ({"depths": np.full((2, 4, 4), "a")}, DataError, "real number array"),
        ({"poses": np.zeros((3, 3, 4))}, DataError, "poses has 3 entries but depths has 2 frames"),
        ({"poses": np.zeros((2, 4, 4))}, DataError, r"poses must have shape \(N, 3, 4\), got \(2, 4, 4\)"),
        ({"poses": np.stack([_pose(), _pose((np.nan, 0, 0))])}, DataError, "pose 1 contains non-finite"),
        ({"poses": np.stack([_pose(), 2 * _pose()])}, DataError, "pose 1 is not a rotation"),
        ({"camera_matrix": np.eye(2)}, DataError, r"camera_matrix must have shape \(3, 3\)"),
        ({"camera_matrix": np.diag([-1.0, 1.0, 1.0])}, DataError, "focal lengths must be > 0, got fx=-1.0"),
        ({"camera_matrix": np.array([[1.0, 0, 0], [0, 1, 0], [0, 1, 1]])}, DataError, r"must be \[\[fx, s, cx\]"),
        ({"camera_matrix": np.full((3, 3), np.inf)}, DataError, "camera_matrix contains non-finite"),
        ({"stamps_ns": np.array([5, 4])}, DataError, r"must not decrease: frame 1 \(4\) is before frame 0 \(5\)"),
        ({"stamps_ns": np.array([0.0, 1.0])}, DataError, "integer nanoseconds, got dtype float64"),
        ({"stamps_ns": np.array([0, 1, 2])}, DataError, r"stamps_ns must have shape \(2,\), got \(3,\)"),
        ({"min_fraction": 0.0}, ConfigError, r"min_fraction must be in \(0, 1\], got 0.0"),
        ({"min_gap_s": -1.0}, ConfigError, "min_gap_s must be >= 0, got -1.0"),
        ({"grid_step_px": 0}, ConfigError, "grid_step_px must be an integer >= 1, got 0"),
        ({"grid_step_px": 2.5}, ConfigError, "grid_step_px must be an integer >= 1, got 2.5"),
        ({"tolerance_m": -0.01}, ConfigError, "tolerance_m must be >= 0, got -0.01"),
        ({"relative_tolerance": float("nan")}, ConfigError, "relative_tolerance must be >= 0, got nan"),
        ({"prune_voxel_m": 0.0}, ConfigError, r"prune_voxel_m must be > 0 \(or None: no pruning\), got 0.0"),
        ({"depth_scale": 0}, ConfigError, "depth_scale must be > 0, got 0"),
        ({"max_view_angle_deg": 0.0}, ConfigError, r"max_view_angle_deg must be in \(0, 180\] \(or None"),
    ],
)
def test_covisibility_bad_inputs(changes, error, match):
    with pytest.raises(error, match=match):
        covisibility_loop_matrix(**_bad(**changes))
