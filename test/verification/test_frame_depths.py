"""What verification keeps of each frame's depth (verification/frame_depths.py): keypoint
depths and grids against hand-computed values, the store's bounds and order, and its folder across a restart."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.errors import DataError, ModelError
from aefabmap_ros.io.npz_files import write_npz_atomically
from aefabmap_ros.verification.frame_depths import (
    DEPTH_FORMAT_VERSION,
    DepthGrid,
    FrameDepthFolder,
    FrameDepthStore,
    depth_at_pixels,
    depth_size_problem,
    grid_step_for,
    sample_depth_grid,
)


def test_the_grid_samples_every_step_th_pixel_half_a_step_in() -> None:
    """A 40 x 24 image whose depth encodes its pixel (row * 100 + column, cm): the grid of step 4 holds the
    pixels at rows and columns 2, 6, 10, ..., NaN where the image has none, in float16."""
    rows, columns = np.mgrid[0:24, 0:40]
    depth = ((rows * 100 + columns) / 100.0).astype(np.float32)
    depth[6, 10] = 0.0  # a dropout
    grid = sample_depth_grid(depth, step=4)
    assert grid.values.shape == (6, 10) and grid.values.dtype == np.float16 and grid.offset == 2
    assert float(grid.values[0, 0]) == pytest.approx(2.02, rel=1e-3)  # pixel (row 2, column 2)
    assert float(grid.values[5, 9]) == pytest.approx(22.38, rel=1e-3)  # pixel (row 22, column 38)
    # Pixel (row 6, column 10) has none: its 3 x 3 neighbours' median, 6.10 (they are symmetric about it).
    assert float(grid.values[1, 2]) == pytest.approx(6.10, rel=1e-3)
    # The step gives about 80 columns whatever the resolution.
    assert [grid_step_for(width) for width in (80, 320, 640, 1280, 1920)] == [1, 4, 8, 16, 24]
    assert sample_depth_grid(np.ones((480, 640), np.float32)).values.shape == (60, 80)
    with pytest.raises(DataError, match="step"):
        DepthGrid(np.ones((2, 2)), 0)
    with pytest.raises(DataError, match="single-channel"):
        sample_depth_grid(np.ones((4, 4, 3)))


def test_frame_depths_arrive_in_either_order_and_stay_bounded() -> None:
    depth = (10.0 + 0.01 * np.arange(12)).reshape(3, 4).astype(np.float32)  # 1 cm more each pixel: flat
    depth[0, 0] = 0.0  # a dropout
    keypoints = np.array([[1.0, 2.0], [3.2, 0.4], [9.0, 9.0]], dtype=np.float32)
    store = FrameDepthStore(max_frames=2)
    store.add_depth(10, depth)
    store.add_features(10, keypoints)
    store.add_features(20, keypoints)
    assert store.get(20) is None
    store.add_depth(20, depth + 100)
    first, second = store.get(10), store.get(20)
    assert first is not None and second is not None
    # (row 2, column 1); between rows 0 and 1 of column 3 (x 3.2 is still that pixel's), 1/z interpolated; outside.
    # Of the images as kept, in float16.
    for kept, image in ((first, depth), (second, depth + 100)):
        as_kept = image.astype(np.float16).astype(np.float64)
        between = 1 / (0.6 / as_kept[0, 3] + 0.4 / as_kept[1, 3])
        np.testing.assert_allclose(kept.keypoints, [as_kept[2, 1], between, np.nan], rtol=1e-6)
    # A 4-pixel-wide image: step 1 (~80 columns at most), the whole image; its one dropout (0 at the corner)
    # takes the median of its three neighbours 10.01, 10.04 and 10.05.
    assert first.grid is not None and first.grid.step == 1
    np.testing.assert_allclose(first.grid.values.astype(np.float32), np.where(depth > 0, depth, 10.04), rtol=1e-3)
    store.add_depth(30, depth)
    store.add_features(30, keypoints)
    assert len(store) == 2 and store.get(10) is None


def test_a_keypoint_depth_is_exact_on_a_plane_and_none_across_an_edge_or_a_grazing_surface() -> None:
    """Against closed forms: a plane's depth at sub-pixel points (1/z affine in the pixel coordinates), NaN where
    the four pixels hold two surfaces, where the surface is seen so obliquely that they spread over 3 %, where one
    has no depth, and outside the image."""
    rows, columns = np.mgrid[0:30, 0:40].astype(np.float64)
    inverse = 0.1 + 0.0004 * columns - 0.0002 * rows  # a plane: 1/z affine in (x, y); 5.9-11.4 m, < 1 % a pixel
    plane = (1 / inverse).astype(np.float32)
    points = np.array([[3.25, 7.5], [20.9, 0.1], [39.4, 29.4], [-0.2, 5.0], [-0.6, 5.0], [12.0, 30.6]])
    expected = 1 / (0.1 + 0.0004 * np.clip(points[:, 0], 0, 39) - 0.0002 * np.clip(points[:, 1], 0, 29))
    expected[4:] = np.nan  # outside
    np.testing.assert_allclose(depth_at_pixels(plane, points), expected, rtol=1e-5)
    edge = plane.copy()
    edge[:, 20:] += 3.0  # a step of 3 m between columns 19 and 20
    steep = (5.0 + 0.2 * columns).astype(np.float32)  # 20 cm a pixel at 5-13 m: a grazing surface
    holed = plane.copy()
    holed[8, 4] = np.nan
    assert np.isnan(depth_at_pixels(edge, np.array([[19.5, 3.0]])))[0]
    assert depth_at_pixels(edge, np.array([[18.5, 3.0]]))[0] == pytest.approx(plane[3, 18:20].mean(), rel=1e-3)
    assert np.isnan(depth_at_pixels(steep, np.array([[3.5, 3.0]])))[0]
    assert np.isnan(depth_at_pixels(holed, np.array([[3.25, 7.5]])))[0]


def test_the_depth_of_a_skipped_frame_is_not_kept_whether_it_came_before_or_after_the_skip() -> None:
    """A 30 Hz depth stream beside a 10 Hz detector: the images waiting must be those of frames to come."""
    depth = np.ones((3, 4), dtype=np.float32)
    keypoints = np.array([[1.0, 1.0]], dtype=np.float32)
    store = FrameDepthStore(max_frames=10, max_waiting_bytes=2 * depth.astype(np.float16).nbytes)  # two images
    store.add_depth(30, depth)  # a frame to be processed, its features late
    store.add_depth(10, depth)
    store.skip_frame(10)  # announced after its depth came: dropped, so it pushes nothing out
    store.add_depth(20, depth)
    store.skip_frame(20)
    store.skip_frame(50)  # announced before its depth comes: never kept
    store.add_depth(50, depth)
    store.add_depth(40, depth)
    store.add_features(30, keypoints)
    assert 30 in store  # without the skips, 10, 20, 50 and 40 would have pushed it out of the two waiting
    for stamp in (10, 20, 50):
        store.add_features(stamp, keypoints)
        assert stamp not in store


def test_a_depth_image_of_another_size_than_its_image_is_not_sampled() -> None:
    """A 4 x 3 depth image for a frame whose image is 8 x 6: its pixels are not the keypoints'. Refused when
    the keypoints come (DataError naming both sizes); they wait for a depth image that fits."""
    depth = np.arange(12, dtype=np.float32).reshape(3, 4)
    keypoints = np.array([[1.0, 2.0]], dtype=np.float32)
    assert depth_size_problem((4, 3), (4, 3)) is None
    store = FrameDepthStore(max_frames=2)
    store.add_depth(10, depth)
    with pytest.raises(DataError, match="depth image 4x3 is not the size of its image 8x6"):
        store.add_features(10, keypoints, image_size=(8, 6))
    assert store.get(10) is None
    store.add_depth(10, np.ones((6, 8), np.float32))
    kept = store.get(10)
    assert kept is not None and kept.keypoints.tolist() == [1.0]
    store.add_depth(20, depth)
    store.add_features(20, keypoints, image_size=(4, 3))  # the right size
    assert store.get(20) is not None


def test_frame_depths_survive_a_restart_through_the_folder(tmp_path: Path) -> None:
    store = FrameDepthStore(max_frames=2)
    folder = FrameDepthFolder(tmp_path)
    depth_image = (50.0 + 0.01 * np.arange(100)).reshape(10, 10).astype(np.float32)  # flat: 1 cm a pixel
    store.add_features(1, np.array([[1.0, 2.0], [3.0, 4.0]], np.float32))
    store.add_depth(1, depth_image)
    folder.save(store)
    store.add_depth(2, depth_image * 2)
    store.add_features(2, np.array([[5.0, 5.0]], np.float32))
    folder.save(store)
    folder.save(store)  # nothing new: no empty chunk
    assert sorted(p.name for p in tmp_path.glob("depth-*.npz")) == ["depth-000000000.npz", "depth-000000001.npz"]

    reloaded = FrameDepthStore(max_frames=2)
    FrameDepthFolder(tmp_path).load_into(reloaded)
    first, second = reloaded.get(1), reloaded.get(2)
    assert first is not None and second is not None
    as_kept = [float(np.float16(value)) for value in (depth_image[2, 1], depth_image[4, 3], 2 * depth_image[5, 5])]
    assert first.keypoints.tolist() == as_kept[:2] and second.keypoints.tolist() == as_kept[2:]
    for kept, image in ((first, depth_image), (second, depth_image * 2)):
        assert kept.grid is not None and kept.grid.step == 1
        np.testing.assert_array_equal(kept.grid.values, image.astype(np.float16))
    assert reloaded.unsaved() == []  # reloaded frames count as saved

    # Two more frames push frames 1 and 2 out: their chunks are deleted at the next save.
    later = FrameDepthFolder(tmp_path)
    later.load_into(reloaded)
    for stamp in (3, 4):
        reloaded.add_depth(stamp, depth_image)
        reloaded.add_features(stamp, np.array([[0.0, 0.0]], np.float32))
    later.save(reloaded)
    assert sorted(p.name for p in tmp_path.glob("depth-*.npz")) == ["depth-000000002.npz"]


def test_a_chunk_saved_before_grids_were_kept_loads_without_them(tmp_path: Path) -> None:
    write_npz_atomically(tmp_path / "depth-000000000.npz", {
        "format_version": np.array(DEPTH_FORMAT_VERSION), "stamps_ns": np.array([1, 2]),
        "counts": np.array([2, 1]), "depths": np.array([1.0, 2.0, 3.0], np.float32)})
    store = FrameDepthStore(max_frames=2)
    FrameDepthFolder(tmp_path).load_into(store)
    first, second = store.get(1), store.get(2)
    assert first is not None and second is not None
    assert first.keypoints.tolist() == [1.0, 2.0] and second.keypoints.tolist() == [3.0]
    assert first.grid is None and second.grid is None


def test_a_corrupt_depth_chunk_is_named(tmp_path: Path) -> None:
    write_npz_atomically(tmp_path / "depth-000000000.npz", {
        "format_version": np.array(DEPTH_FORMAT_VERSION), "stamps_ns": np.array([1, 2]),
        "counts": np.array([2, 2]), "depths": np.zeros(3, np.float32)})
    with pytest.raises(ModelError, match=r"depth-000000000\.npz"):
        FrameDepthFolder(tmp_path).load_into(FrameDepthStore(max_frames=2))
    # Grids whose shapes do not add up to their values.
    write_npz_atomically(tmp_path / "depth-000000000.npz", {
        "format_version": np.array(DEPTH_FORMAT_VERSION), "stamps_ns": np.array([1]),
        "counts": np.array([1]), "depths": np.zeros(1, np.float32), "grid_shapes": np.array([[2, 3]]),
        "grid_steps": np.array([4]), "grid_values": np.zeros(5, np.float16)})
    with pytest.raises(ModelError, match=r"depth-000000000\.npz: the depth grids"):
        FrameDepthFolder(tmp_path).load_into(FrameDepthStore(max_frames=2))


def test_a_grid_pixel_in_a_dropout_takes_its_neighbours_median_and_a_large_hole_stays_one() -> None:
    """A wall at 4 m with a sensor's scattered dropouts: a grid pixel that lost its depth gets its 3 x 3
    neighbours' median; a hole of 5 x 5 pixels around a grid pixel stays a hole."""
    depth = np.full((24, 40), 4.0, np.float32)
    depth[2:4, 6:8] = 3.0  # neighbours of the grid pixel (row 2, column 6) at another depth
    depth[2, 6] = 0.0  # the grid pixel itself dropped out: its 8 neighbours are 3, 3, 3 and five 4 s
    depth[8:13, 12:17] = 0.0  # a hole around the grid pixel (row 10, column 14)
    grid = sample_depth_grid(depth, step=4)
    assert float(grid.values[0, 1]) == pytest.approx(4.0)  # median of (3, 3, 3, 4, 4, 4, 4, 4)
    assert np.isnan(grid.values[2, 3])
    assert np.count_nonzero(np.isnan(grid.values)) == 1


def test_depth_images_wait_for_late_features_up_to_their_byte_bound() -> None:
    """A verifier seconds behind on features: 300 depth images of a 320x240 camera (10 s at 30 Hz) come before
    the first one's features and it is still there; a bound of three images keeps only the newest three."""
    depth = np.full((240, 320), 2.0, dtype=np.float32)
    keypoints = np.array([[5.0, 7.0]], dtype=np.float32)
    store = FrameDepthStore(max_frames=10)
    for stamp in range(300):
        store.add_depth(stamp, depth)
    store.add_features(0, keypoints)
    first = store.get(0)
    assert first is not None and first.keypoints.tolist() == [2.0]
    small = FrameDepthStore(max_frames=10, max_waiting_bytes=3 * depth.astype(np.float16).nbytes)
    for stamp in range(5):
        small.add_depth(stamp, depth)
    for stamp in range(5):
        small.add_features(stamp, keypoints)
    assert [stamp for stamp in range(5) if stamp in small] == [2, 3, 4]
