"""The closure picture: matches found by the verifier's code, drawn where they are."""

import numpy as np

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.visualization.match_picture import (
    BANNER_HEIGHT_PX,
    INLIER_COLOUR,
    MAX_DRAWN_INLIERS,
    OUTLIER_COLOUR,
    PairMatches,
    decode_jpeg,
    draw_matches,
    make_thumbnail,
    pair_matches,
)


def _drawn_in(pixel: np.ndarray, colour: tuple[int, int, int]) -> bool:
    """The pixel is of that colour (lines are anti-aliased: its dominant channel, clearly lit)."""
    return int(np.argmax(pixel)) == int(np.argmax(colour)) and int(pixel.max()) > 120


def test_inliers_are_lines_and_outliers_dots_where_the_points_are():
    query, place = np.zeros((80, 100), np.uint8), np.zeros((60, 120), np.uint8)
    matches = PairMatches(query_points=np.array([[10, 20], [50, 40], [90, 70]], np.float32),
                          place_points=np.array([[30, 20], [70, 10], [5, 50]], np.float32),
                          inliers=np.array([True, True, False]))
    drawn = draw_matches(query, place, matches, 1.0, 1.0, "caption", refused=False)
    assert drawn.shape == (BANNER_HEIGHT_PX + 80, 100 + 120, 3)
    canvas = drawn[BANNER_HEIGHT_PX:]
    # An inlier's line passes through the midpoint of its query point and its place point (shifted right by 100).
    for (qx, qy), (px, py) in ((matches.query_points[0]), matches.place_points[0]), \
            (matches.query_points[1], matches.place_points[1]):
        mx, my = round((qx + px + 100) / 2), round((qy + py) / 2)
        assert _drawn_in(canvas[my, mx], INLIER_COLOUR)
    # The outlier: a dot at each end, no line between them.
    assert _drawn_in(canvas[70, 90], OUTLIER_COLOUR)
    assert _drawn_in(canvas[50, 105], OUTLIER_COLOUR)
    assert tuple(canvas[60, round((90 + 105) / 2)]) == (0, 0, 0)
    # Nothing drawn elsewhere: the coloured pixels lie near the three matches only.
    assert tuple(canvas[5, 200]) == (0, 0, 0)


def test_a_thumbnail_is_the_image_shrunk_to_its_width():
    image = np.zeros((480, 640), np.uint8)
    image[200:280, 300:340] = 255
    small = decode_jpeg(make_thumbnail(image, 320))
    assert small.shape[:2] == (240, 320)
    assert small[120, 160].mean() > 200 and small[20, 20].mean() < 30  # the bright block, halved


def test_at_most_max_drawn_inliers_lines_are_drawn():
    """Inliers on distinct rows, each a horizontal line: the rows lit in the gap between the two points count them."""
    rows = np.arange(5, 5 + 2 * 200, 2, dtype=np.float32)  # 200 inliers
    matches = PairMatches(query_points=np.stack([np.full(200, 10, np.float32), rows], axis=1),
                          place_points=np.stack([np.full(200, 10, np.float32), rows], axis=1),
                          inliers=np.ones(200, bool))
    image = np.zeros((420, 60), np.uint8)
    canvas = draw_matches(image, image, matches, 1.0, 1.0, "", refused=False)[BANNER_HEIGHT_PX:]
    lit_rows = np.flatnonzero(canvas[:, 40, 1] > 120)  # column 40: between x=10 and x=60+10
    assert len(lit_rows) == MAX_DRAWN_INLIERS


def _features(points: np.ndarray, descriptors: np.ndarray) -> Features:
    keypoints = np.zeros((len(points), 5), np.float32)
    keypoints[:, :2] = points
    keypoints[:, 2] = 5.0
    return Features(keypoints=keypoints, descriptors=descriptors, descriptor_type="sift")


def test_pair_matches_keeps_the_matches_of_one_geometry():
    """The place camera is the query camera moved sideways: each point keeps its row and moves along it by its
    disparity (its depth). Ten of the matches land elsewhere, off their row. The RANSAC inliers are exactly the 50
    that keep their row."""
    rng = np.random.default_rng(3)
    points = rng.uniform([20, 20], [600, 460], size=(60, 2)).astype(np.float32)
    descriptors = rng.integers(0, 255, size=(60, 128)).astype(np.float32)
    disparity = rng.uniform(5, 80, size=60).astype(np.float32)
    moved = points + np.stack([disparity, np.zeros(60, np.float32)], axis=1) \
        + rng.normal(0, 0.2, size=(60, 2)).astype(np.float32)
    moved[50:] = np.stack([rng.uniform(20, 600, 10), (points[50:, 1] + rng.uniform(40, 120, 10)) % 480], axis=1)
    order = rng.permutation(60)  # the place lists its keypoints in another order
    matches = pair_matches(_features(points, descriptors), _features(moved[order], descriptors[order]),
                           VerificationConfig())
    assert len(matches.inliers) == 60
    kept_rows = np.abs(matches.query_points[:, 1] - matches.place_points[:, 1]) < 1.0
    assert np.count_nonzero(kept_rows) == 50
    np.testing.assert_array_equal(matches.inliers, kept_rows)
