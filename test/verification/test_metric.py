"""The metric test (verification/metric.py) on scenes of known geometry: the view overlap against the share
built into the scene, PnP's inliers against the scene's correspondences, and what it accepts and refuses
beside the epipolar test."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.frame_depths import DepthGrid, sample_depth_grid
from aefabmap_ros.verification.geometric import VerificationConfig, verify_pair
from aefabmap_ros.verification.metric import KeypointDepths, covisibility, metric_check, view_overlap
from aefabmap_ros.verification.relative_pose import CameraModel, RelativePose
from aefabmap_ros.verification.reranking import SequenceDepths, cached_pair_verifier
from test.verification.test_geometric import FOCAL, HEIGHT, WIDTH, _features, _rotation_y

CAMERA = CameraModel(np.array([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]]))


def _pixels(points: np.ndarray) -> np.ndarray:
    return np.stack([FOCAL * points[:, 0] / points[:, 2] + WIDTH / 2,
                     FOCAL * points[:, 1] / points[:, 2] + HEIGHT / 2], axis=1)


def _in_image(points: np.ndarray, margin: float = 3.0) -> np.ndarray:
    """In front of the camera and ``margin`` pixels inside its image (a negative margin: as far outside)."""
    pixels = _pixels(points)
    return (points[:, 2] > 0) & (pixels[:, 0] >= margin) & (pixels[:, 0] <= WIDTH - 1 - margin) \
        & (pixels[:, 1] >= margin) & (pixels[:, 1] <= HEIGHT - 1 - margin)


def _out_of_image(points: np.ndarray) -> np.ndarray:
    """Clearly outside the view: pixel noise cannot carry it in."""
    return ~_in_image(points, margin=-3.0)


@dataclass(frozen=True)
class Scene:
    """Two views of one street, the query's camera further back: X_query = R X_place + t."""

    query: Features
    place: Features
    depths: KeypointDepths
    pose: RelativePose  # the place camera in the query's frame, exact
    overlap: float  # the share of the query's keypoints inside the place's view, by construction


def _scene(seed: int, shared: int, query_inside: int, query_outside: int, place_only: int) -> Scene:
    """``shared`` points both cameras see and match; ``query_inside`` more the query sees inside the place's
    view (unmatched: other detail), ``query_outside`` it sees outside it; ``place_only`` the place alone sees."""
    rng = np.random.default_rng(seed)
    rotation = _rotation_y(0.25)
    centre = np.array([0.6, 0.0, -8.0])  # the query camera in the place's frame: 8 m back, turned 14 degrees
    translation = -rotation @ centre

    def to_query(points: np.ndarray) -> np.ndarray:
        return points @ rotation.T + translation

    def draw(count: int, in_place: bool, in_query: bool) -> np.ndarray:
        """``count`` points in the place's frame, clearly inside or outside each camera's view."""
        found = np.zeros((0, 3))
        while found.shape[0] < count:
            points = np.column_stack([rng.uniform(-30, 30, 4000), rng.uniform(-6, 6, 4000), rng.uniform(-10, 40, 4000)])
            place_side = _in_image(points) if in_place else _out_of_image(points)
            query_side = _in_image(to_query(points)) if in_query else _out_of_image(to_query(points))
            found = np.vstack([found, points[place_side & query_side]])
        return found[:count]

    both = draw(shared + query_inside, in_place=True, in_query=True)
    outside = draw(query_outside, in_place=False, in_query=True)
    alone = draw(place_only, in_place=True, in_query=False)
    descriptors = rng.uniform(0, 255, (shared, 128)).astype(np.float32)

    def unrelated(count: int) -> np.ndarray:
        return rng.uniform(0, 255, (count, 128)).astype(np.float32)

    query_points = to_query(np.vstack([both, outside]))
    place_points = np.vstack([both[:shared], alone])
    noise = rng.normal(0.0, 0.3, (query_points.shape[0], 2))  # detector noise, well inside the 2 px threshold
    query = _features(_pixels(query_points) + noise, np.vstack([descriptors, unrelated(query_inside + query_outside)]))
    place = _features(_pixels(place_points), np.vstack([descriptors + rng.normal(0, 4, descriptors.shape).astype(
        np.float32), unrelated(place_only)]))
    depths = KeypointDepths(CAMERA, (WIDTH, HEIGHT), query_points[:, 2].astype(np.float32),
                            place_points[:, 2].astype(np.float32))
    pose = RelativePose(rotation, translation, np.eye(6), metric=True, inliers=shared)
    return Scene(query, place, depths, pose, (shared + query_inside) / query_points.shape[0])


@pytest.mark.parametrize(("inside", "outside"), [(100, 0), (60, 40), (10, 150), (0, 300)])
def test_view_overlap_is_the_share_of_the_query_the_place_sees(inside: int, outside: int) -> None:
    scene = _scene(seed=inside + outside, shared=40, query_inside=inside, query_outside=outside, place_only=50)
    # Under the true motion: exactly the share built into the scene.
    assert view_overlap(scene.query.keypoints, scene.depths, scene.pose) == pytest.approx(scene.overlap, abs=1e-12)
    # Under PnP's motion from the matches: the scene's correspondences are its inliers, the share the same
    # but for a keypoint or two on the image's edge.
    rows = np.column_stack([np.arange(40), np.arange(40)])
    check = metric_check(scene.query.keypoints, scene.query.keypoints[:40, :2], scene.place.keypoints[:40, :2],
                         rows[:, 1], scene.depths, threshold_px=2.0, confidence=0.999, min_inliers=30)
    assert check.inliers >= 38
    assert check.view_overlap == pytest.approx(scene.overlap, abs=2.5 / len(scene.query))


def test_a_revisit_from_further_back_is_accepted_with_depth() -> None:
    """40 matches among 340 keypoints in each image: the epipolar test refuses them (12 % of the keypoints),
    though every query keypoint lies in the place's view. With depth, one motion explains the matches and the
    views overlap: accepted."""
    scene = _scene(seed=3, shared=40, query_inside=300, query_outside=0, place_only=300)
    without = verify_pair(scene.query, scene.place, VerificationConfig())
    assert not without.accepted and without.inliers >= 36 and without.metric is None
    result = verify_pair(scene.query, scene.place, VerificationConfig(), scene.depths)
    assert result.accepted and result.inliers == without.inliers
    assert result.metric is not None and result.metric.inliers >= 36 and result.metric.view_overlap > 0.99


def test_a_repeated_sign_in_another_street_stays_refused() -> None:
    """The same 40 consistent matches, but the query's other 410 keypoints lie outside the place's view: one
    motion fits the matches (a copied sign), the views do not overlap. The overlap refuses what PnP accepts."""
    scene = _scene(seed=4, shared=40, query_inside=0, query_outside=410, place_only=410)
    result = verify_pair(scene.query, scene.place, VerificationConfig(), scene.depths)
    assert result.metric is not None and result.metric.inliers >= 36
    assert result.metric.view_overlap == pytest.approx(40 / 450, abs=0.01)
    assert not result.accepted
    lenient = VerificationConfig(metric_min_view_overlap=0.05)
    assert verify_pair(scene.query, scene.place, lenient, scene.depths).accepted


def _ambiguous(scene: Scene, count: int, ratio: float) -> Scene:
    """``scene`` with its first ``count`` matches made ambiguous: the place gets a decoy keypoint for each, at
    ``1 / ratio`` times the true match's descriptor distance from the query's (Lowe's ratio exactly ``ratio``),
    as a facade's repeated windows give."""
    rng = np.random.default_rng(count)
    query_descriptors = scene.query.descriptors[:count].astype(np.float64)

    def at_distance(distance: float) -> np.ndarray:
        directions = rng.normal(size=query_descriptors.shape)
        return query_descriptors + distance * directions / np.linalg.norm(directions, axis=1, keepdims=True)

    place_descriptors = scene.place.descriptors.copy()
    place_descriptors[:count] = at_distance(40.0)
    decoys = at_distance(40.0 / ratio)
    decoy_pixels = rng.uniform([0.0, 0.0], [WIDTH - 1, HEIGHT - 1], (count, 2))
    place = _features(np.vstack([scene.place.keypoints[:, :2], decoy_pixels]),
                      np.vstack([place_descriptors, decoys]).astype(np.float32))
    depths = replace(scene.depths, place=np.concatenate([scene.depths.place, np.full(count, 10.0, np.float32)]))
    return replace(scene, place=place, depths=depths)


def test_matches_the_ratio_test_finds_ambiguous_reach_the_metric_test_at_its_own_ratio() -> None:
    """40 shared points, 12 of them with a decoy at Lowe's ratio 0.85 (repeated windows): at 0.8 the pair has 28
    inliers, enough to be refused only for its share, and too few for the metric test; at metric_ratio 0.9 the
    12 come back, one motion explains all 40 and the pair is accepted, its pose fitted to those matches."""
    scene = _ambiguous(_scene(seed=10, shared=40, query_inside=300, query_outside=0, place_only=300), 12, 0.85)
    strict = verify_pair(scene.query, scene.place, VerificationConfig(metric_ratio=0.8), scene.depths)
    # Fewer matches fit one geometry than the metric test asks: not even tried.
    assert 25 <= strict.inliers <= 28 and strict.metric is None and not strict.accepted
    result = verify_pair(scene.query, scene.place, VerificationConfig(), scene.depths)
    assert result.accepted and result.inliers == strict.inliers  # the epipolar test's own count, at ratio 0.8
    assert result.metric is not None and result.metric.inliers >= 36 and result.metric.view_overlap > 0.99
    assert result.matched_rows is not None and result.matched_rows.shape[0] >= 38
    # A decoy is never the match of a shared point: its ratio is 1 / 0.85 the other way round.
    assert int(result.matched_rows[:, 1].max()) < len(scene.place) - 12


def test_a_pair_refused_for_too_few_inliers_gets_no_metric_test() -> None:
    """Half the shared points ambiguous: 20 inliers at ratio 0.8, under min_inliers. The metric test is for pairs
    refused for their share alone; this one is not tried, though at 0.9 its matches would pass."""
    scene = _ambiguous(_scene(seed=11, shared=40, query_inside=300, query_outside=0, place_only=300), 20, 0.85)
    result = verify_pair(scene.query, scene.place, VerificationConfig(), scene.depths)
    assert result.inliers < 25 and result.metric is None and not result.accepted
    tried = verify_pair(scene.query, scene.place, VerificationConfig(min_inliers=15, min_inlier_ratio=0.5),
                        scene.depths)
    assert tried.metric is not None and tried.metric.inliers >= 36 and tried.accepted


def test_wrong_depths_fit_no_motion() -> None:
    scene = _scene(seed=5, shared=40, query_inside=300, query_outside=0, place_only=300)
    shuffled = np.random.default_rng(5).permutation(scene.depths.place)
    result = verify_pair(scene.query, scene.place, VerificationConfig(), replace(scene.depths, place=shuffled))
    assert result.metric is not None and result.metric.inliers < 30 and not result.accepted


def test_an_accepted_pair_keeps_its_acceptance_where_the_views_overlap_and_the_test_can_be_turned_off() -> None:
    accepted = _scene(seed=6, shared=120, query_inside=0, query_outside=20, place_only=20)
    result = verify_pair(accepted.query, accepted.place, VerificationConfig(), accepted.depths)
    assert result.accepted and result.epipolar_accepted
    assert result.metric is not None and result.metric.view_overlap == pytest.approx(120 / 140, abs=0.02)
    far = _scene(seed=7, shared=40, query_inside=300, query_outside=0, place_only=300)
    off = verify_pair(far.query, far.place, VerificationConfig(metric_min_inliers=0), far.depths)
    assert not off.accepted and off.metric is None
    # More inliers asked than there are matches: not even tried.
    assert verify_pair(far.query, far.place, VerificationConfig(metric_min_inliers=60), far.depths).metric is None


def test_an_accepted_pair_whose_views_do_not_overlap_is_refused_with_depth() -> None:
    """70 consistent matches, 14 % of the place's keypoints: the epipolar test accepts. But the query's other
    420 keypoints lie outside the place's view (the same corner seen from far round, or a copied facade in a
    new street): under the motion the matches fit, 14 % of the query overlaps the place. With depth: refused."""
    scene = _scene(seed=12, shared=70, query_inside=0, query_outside=420, place_only=300)
    without = verify_pair(scene.query, scene.place, VerificationConfig())
    assert without.accepted and without.epipolar_accepted and without.metric is None
    result = verify_pair(scene.query, scene.place, VerificationConfig(), scene.depths)
    assert result.epipolar_accepted and not result.accepted
    assert result.metric is not None and result.metric.inliers >= 60
    assert result.metric.view_overlap == pytest.approx(70 / 490, abs=0.01)
    # No motion to judge by (no place keypoint has depth): the epipolar decision stands.
    blind = replace(scene.depths, place=np.full_like(scene.depths.place, np.nan))
    assert verify_pair(scene.query, scene.place, VerificationConfig(), blind).accepted


def test_sequence_depths_give_the_metric_test_only_to_pairs_with_depth_on_both_sides() -> None:
    scene = _scene(seed=8, shared=40, query_inside=300, query_outside=0, place_only=300)
    features = [scene.place, scene.query]
    verify = cached_pair_verifier(features, VerificationConfig(),
                                  SequenceDepths(CAMERA, (WIDTH, HEIGHT), [scene.depths.place, scene.depths.query]))
    assert verify(1, 0).accepted
    no_place_depth = cached_pair_verifier(features, VerificationConfig(),
                                          SequenceDepths(CAMERA, (WIDTH, HEIGHT), [None, scene.depths.query]))
    assert not no_place_depth(1, 0).accepted and no_place_depth(1, 0).metric is None
    with pytest.raises(DataError, match="1 frames of keypoint depths for 2 frames"):
        cached_pair_verifier(features, VerificationConfig(), SequenceDepths(CAMERA, (WIDTH, HEIGHT), [None]))


def test_bad_depths_and_settings_are_refused() -> None:
    scene = _scene(seed=9, shared=40, query_inside=300, query_outside=0, place_only=300)
    config = VerificationConfig()
    with pytest.raises(DataError, match="query keypoint depths"):
        verify_pair(scene.query, scene.place, config, replace(scene.depths, query=scene.depths.query[:-1]))
    with pytest.raises(DataError, match="has no depth"):
        verify_pair(scene.query, scene.place, config, replace(scene.depths, place=scene.depths.place[:5]))
    with pytest.raises(DataError, match="image size"):
        KeypointDepths(CAMERA, (0, HEIGHT), scene.depths.query, scene.depths.place)
    with pytest.raises(DataError, match="one value per keypoint"):
        KeypointDepths(CAMERA, (WIDTH, HEIGHT), scene.depths.query.reshape(-1, 1), scene.depths.place)
    with pytest.raises(ConfigError, match="metric_min_inliers"):
        VerificationConfig(metric_min_inliers=5)
    with pytest.raises(ConfigError, match="metric_min_view_overlap"):
        VerificationConfig(metric_min_view_overlap=1.5)
    for ratio in (0.0, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="metric_ratio"):
            VerificationConfig(metric_ratio=ratio)
    # No keypoint with depth: no overlap to speak of.
    blind = replace(scene.depths, query=np.full_like(scene.depths.query, np.nan))
    assert view_overlap(scene.query.keypoints, blind, scene.pose) == 0.0


# Covisibility on scenes of known geometry: depth images ray-cast from planes, the share checked against a
# count made from the scene itself (which surface each camera's ray meets first), not from depth images.

@dataclass(frozen=True)
class Patch:
    """A wall facing the cameras: the plane z = ``z`` (place frame) for x in [x_min, x_max]."""

    z: float
    x_min: float = -np.inf
    x_max: float = np.inf


def _ray_hits(origin: np.ndarray, directions: np.ndarray, patch: Patch) -> np.ndarray:
    """(N,) ray parameter where each ray ``origin + s * direction`` meets ``patch`` (inf: it does not)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (patch.z - origin[2]) / directions[:, 2]
    x = origin[0] + s * directions[:, 0]
    hit = (s > 0) & (x >= patch.x_min) & (x <= patch.x_max)
    return np.where(hit, s, np.inf)


def _render_depth(centre: np.ndarray, patches: list[Patch]) -> np.ndarray:
    """Depth image (metres, NaN = nothing) of a camera at ``centre`` (place frame) looking along +z."""
    rows, columns = np.mgrid[0:HEIGHT, 0:WIDTH]
    directions = np.column_stack([(columns.ravel() - WIDTH / 2) / FOCAL, (rows.ravel() - HEIGHT / 2) / FOCAL,
                                  np.ones(rows.size)])  # z = 1: the ray parameter is the depth
    nearest = np.min([_ray_hits(centre, directions, patch) for patch in patches], axis=0)
    return np.where(np.isfinite(nearest), nearest, np.nan).reshape(HEIGHT, WIDTH).astype(np.float32)


def _visible_share(query_grid: DepthGrid, centre: np.ndarray, patches: list[Patch]) -> tuple[float, float]:
    """For the query's grid pixels with depth (camera at ``centre``), the share the place camera (at the origin)
    sees first along its own ray, inside its image; and the share merely inside its image (occlusion ignored)."""
    rows, columns = np.nonzero(np.isfinite(query_grid.values))
    u = query_grid.offset + columns * query_grid.step
    v = query_grid.offset + rows * query_grid.step
    depth = query_grid.values[rows, columns].astype(np.float64)
    points = centre + np.column_stack([(u - WIDTH / 2) / FOCAL * depth, (v - HEIGHT / 2) / FOCAL * depth, depth])
    in_image = _in_image(points, margin=0.0)
    towards = points / points[:, 2:3]  # the place's rays through them, z = 1
    first = np.min([_ray_hits(np.zeros(3), towards, patch) for patch in patches], axis=0)
    unoccluded = first >= points[:, 2] - 1e-6
    return float(np.mean(in_image & unoccluded)), float(np.mean(in_image))


def _moved_sideways(x: float) -> RelativePose:
    """The place camera in the frame of a query camera at (x, 0, 0), both looking along +z."""
    return RelativePose(np.eye(3), np.array([-x, 0.0, 0.0]), np.eye(6), metric=True, inliers=100)


def test_covisibility_of_a_wall_seen_from_the_side_is_the_shared_strip() -> None:
    """A wall 5 m away, the query 0.84 m to the side: 84 px of shift, 10.5 grid columns of 8 px. The query's
    every other grid column (0, 2, ..., 78) lands on the place's grid up to column 68: 35 of 40."""
    wall = [Patch(5.0)]
    query = sample_depth_grid(_render_depth(np.array([0.84, 0.0, 0.0]), wall))
    place = sample_depth_grid(_render_depth(np.zeros(3), wall))
    assert query.step == 8 and query.values.shape == (60, 80) and query.values.dtype == np.float16
    assert covisibility(query, place, _moved_sideways(0.84), CAMERA) == pytest.approx(35 / 40, abs=1e-12)
    # The same frame: everything; a wall the place saw 20 cm further back: nothing (beyond 5 cm + 1 %).
    assert covisibility(place, place, _moved_sideways(0.0), CAMERA) == 1.0
    behind = sample_depth_grid(_render_depth(np.zeros(3), [Patch(5.2)]))
    assert covisibility(query, behind, _moved_sideways(0.84), CAMERA) == 0.0


@pytest.mark.parametrize("side", [1.0, 2.0, 3.0])
def test_covisibility_counts_what_a_pillar_hides_from_the_place(side: float) -> None:
    """A pillar 4 m away in front of a wall 12 m away; the query camera stands ``side`` m to the side, so it
    sees wall the pillar hides from the place. The estimate follows the count made from the scene's geometry,
    never above it: across a depth edge the interpolated depth agrees with neither surface, so each of the
    pillar's two edges, in either grid, costs at most one grid column (1 / 80). It is clearly below the share
    that merely lands in the place's image."""
    scene = [Patch(12.0), Patch(4.0, -1.5, 1.5)]
    centre = np.array([side, 0.0, 0.0])
    query = sample_depth_grid(_render_depth(centre, scene))
    place = sample_depth_grid(_render_depth(np.zeros(3), scene))
    visible, in_image = _visible_share(query, centre, scene)
    estimate = covisibility(query, place, _moved_sideways(side), CAMERA)
    assert visible - 4 / 80 <= estimate <= visible + 1e-12
    assert in_image - visible > 0.1  # occlusion matters in this scene: the test is not the frustum share


def test_the_covisibility_test_refuses_a_pair_whose_surfaces_the_place_did_not_see() -> None:
    """The accepted street scene (120 consistent matches, the views overlapping) with depth grids: where the place's
    grid agrees with the query's surface the pair stays accepted; where the place saw something 1 m in front of
    all of it (the same corner with a wall between) it is refused; without grids, or with the test off, the
    keypoint overlap decides alone."""
    scene = _scene(seed=6, shared=120, query_inside=0, query_outside=20, place_only=20)
    # The query sees a wall 20 m ahead: z_query = 20, i.e. r3 . X_place + t_z = 20 in the place's frame. The
    # place's grid holds the depth along its own rays to that plane (the wall seen obliquely).
    wall_in_query = sample_depth_grid(np.full((HEIGHT, WIDTH), 20.0, np.float32))
    rows, columns = np.mgrid[0:60, 0:80]
    rays = np.stack([(4 + 8 * columns - WIDTH / 2) / FOCAL, (4 + 8 * rows - HEIGHT / 2) / FOCAL,
                     np.ones((60, 80))], axis=-1)
    with np.errstate(divide="ignore"):
        place_values = (20.0 - scene.pose.translation[2]) / (rays @ scene.pose.rotation[2])
    place_values = np.where(place_values > 0, place_values, np.nan)
    seen = DepthGrid(place_values.astype(np.float16), 8)
    blocked = DepthGrid((place_values - 1.0).astype(np.float16), 8)
    config = VerificationConfig()

    def verified(place_grid: DepthGrid | None, settings: VerificationConfig = config) -> bool:
        depths = replace(scene.depths, query_grid=wall_in_query, place_grid=place_grid)
        result = verify_pair(scene.query, scene.place, settings, depths)
        assert result.metric is not None and result.metric.inliers >= 110
        return result.accepted

    assert covisibility(wall_in_query, seen, scene.pose, CAMERA, 0.05, 0.05) > 0.3
    assert covisibility(wall_in_query, blocked, scene.pose, CAMERA, 0.05, 0.05) == 0.0
    assert verified(seen) and not verified(blocked)
    assert verified(None)  # no grids: the keypoint overlap alone
    assert verified(blocked, VerificationConfig(metric_min_covisibility=0.0))
    with pytest.raises(ConfigError, match="metric_min_covisibility"):
        VerificationConfig(metric_min_covisibility=1.5)
    with pytest.raises(ConfigError, match="metric_depth_relative_tolerance"):
        VerificationConfig(metric_depth_relative_tolerance=-0.1)


def test_sequence_depths_hand_each_pair_its_two_grids() -> None:
    scene = _scene(seed=8, shared=40, query_inside=300, query_outside=0, place_only=300)
    grids = [DepthGrid(np.full((2, 2), value, np.float16), 4) for value in (1.0, 2.0)]
    depths = SequenceDepths(CAMERA, (WIDTH, HEIGHT), [scene.depths.place, scene.depths.query], grids)
    pair = depths.pair(1, 0)
    assert pair is not None and pair.query_grid is grids[1] and pair.place_grid is grids[0]
    no_grids = SequenceDepths(CAMERA, (WIDTH, HEIGHT), [scene.depths.place, scene.depths.query]).pair(1, 0)
    assert no_grids is not None and no_grids.query_grid is None and no_grids.place_grid is None
