"""The verifier's frame store: one memory budget over features and depths, which frames it forgets first,
and what a restart brings back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.frame_depths import FrameDepths, sample_depth_grid
from aefabmap_ros.verification.frame_store import FrameRole, FrameStore

SECOND = 1_000_000_000


def _frame(rng: np.random.Generator, count: int) -> Features:
    keypoints = np.column_stack([rng.uniform(0, 320, (count, 2)), np.ones(count), np.zeros(count),
                                 rng.uniform(0, 1, count)]).astype(np.float32)
    descriptors = rng.integers(0, 256, (count, 128)).astype(np.float32)
    return Features(keypoints, descriptors, "sift")


def _depths(rng: np.random.Generator, count: int) -> FrameDepths:
    return FrameDepths.sample(rng.uniform(0.5, 10.0, (240, 320)).astype(np.float32),
                              rng.uniform(0, 320, (count, 2)).astype(np.float32))


def _independent_bytes(store: FrameStore) -> int:
    """The kept arrays' bytes, counted from the arrays themselves (not the store's running total)."""
    total = 0
    for stamp_ns in store.features.stamps():
        stored = store.features._frames[stamp_ns]  # the compact arrays as kept (get() widens float16)
        total += stored.keypoints.nbytes + stored.descriptors.nbytes
        depths = store.depths_of(stamp_ns)
        if depths is not None:
            total += depths.keypoints.nbytes + (0 if depths.grid is None else depths.grid.values.nbytes)
    return total


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), budget_frames=st.integers(2, 40), place_every=st.integers(1, 6))
def test_a_long_stream_never_takes_the_store_over_its_budget(seed: int, budget_frames: int, place_every: int) -> None:
    """400 frames of 50-400 SIFT features with depths, posteriors coming for most: after every input the
    arrays' own bytes stay within max_bytes, the store's count agrees with them, and the newest frame is kept."""
    rng = np.random.default_rng(seed)
    grid = _depths(rng, 1).grid
    max_bytes = budget_frames * (400 * (2 * 4 + 128 * 2) + 300 * 4 + 80 * 60 * 2)
    store = FrameStore(10_000, max_bytes, 300, keep_depths=True)
    place_id = -1
    for index in range(400):
        stamp_ns = index * SECOND // 10
        features = _frame(rng, int(rng.integers(50, 400)))
        stored = store.add_features(stamp_ns, features)
        if rng.uniform() < 0.8:  # most frames' depth images come
            assert store.depths is not None
            store.depths.keep(stamp_ns, FrameDepths(rng.uniform(0.5, 10.0, len(stored)).astype(np.float32), grid))
            store.depths_changed(stamp_ns)
        if index % place_every == 0:
            place_id += 1
        if rng.uniform() < 0.9:  # most frames' posteriors come
            store.add_place(stamp_ns, max(place_id, 0))
        assert store.nbytes == _independent_bytes(store) <= max_bytes
        assert stamp_ns in store
    assert sum(store.evicted.values()) == 400 - len(store)


def test_frames_that_joined_a_place_are_forgotten_before_places() -> None:
    """Ten places of three frames each (the first creates the place, two join it), room for twelve frames: the
    ten place frames stay, with the two newest frames; every other frame that joined a place went first."""
    rng = np.random.default_rng(1)
    frame = _frame(rng, 100)
    frame_bytes = frame.keypoints[:, :2].nbytes + frame.descriptors.astype(np.float16).nbytes
    store = FrameStore(10_000, 12 * frame_bytes)
    for index in range(30):
        stamp_ns = (index + 1) * SECOND
        store.add_features(stamp_ns, frame)
        store.add_place(stamp_ns, index // 3)
    kept = sorted(stamp // SECOND for stamp in store.features.stamps())
    places = [3 * place + 1 for place in range(10)]
    assert kept == sorted(set(places) | {29, 30})
    assert store.evicted == {FrameRole.JOINED: 18, FrameRole.UNKNOWN: 0, FrameRole.PLACE: 0}
    assert all(store.role_of(place * SECOND) is FrameRole.PLACE for place in places)
    assert store.timeline.place_of(2 * SECOND) == 0  # a forgotten frame's place stays for loop tracking


def test_without_posteriors_the_oldest_frame_goes_first_and_the_frame_count_bounds_too() -> None:
    rng = np.random.default_rng(2)
    store = FrameStore(3, 2**40)
    for index in range(5):
        store.add_features(index * SECOND, _frame(rng, 20))
    assert store.features.stamps() == [2 * SECOND, 3 * SECOND, 4 * SECOND]
    assert store.evicted[FrameRole.UNKNOWN] == 2
    with pytest.raises(ConfigError):
        FrameStore(0, 10)
    with pytest.raises(ConfigError):
        FrameStore(10, 0)


def test_a_posterior_before_its_features_still_gives_the_frame_its_role() -> None:
    rng = np.random.default_rng(3)
    store = FrameStore(100, 2**40)
    store.add_place(SECOND, 0)  # the place's posterior came first
    store.add_place(2 * SECOND, 0)  # a frame that joined it
    store.add_features(SECOND, _frame(rng, 10))
    store.add_features(2 * SECOND, _frame(rng, 10))
    assert store.role_of(SECOND) is FrameRole.PLACE and store.role_of(2 * SECOND) is FrameRole.JOINED


def test_a_restart_brings_back_features_depths_places_and_roles(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    before = FrameStore(100, 2**40, keep_depths=True, folder=tmp_path)
    for index, place_id in enumerate([0, 0, 1, 1, 1]):
        stamp_ns = (index + 1) * SECOND
        stored = before.add_features(stamp_ns, _frame(rng, 30))
        assert before.depths is not None
        before.depths.keep(stamp_ns, FrameDepths(np.full(len(stored), 2.0, np.float32),
                                                 sample_depth_grid(np.full((240, 320), 2.0, np.float32))))
        before.add_place(stamp_ns, place_id)
    assert before.has_unsaved
    before.save()
    assert not before.has_unsaved
    after = FrameStore(100, 2**40, keep_depths=True, folder=tmp_path)
    assert any("reloaded 5 frames" in note for note in after.load())
    assert after.features.stamps() == before.features.stamps() and after.nbytes == before.nbytes
    assert [after.role_of(stamp) for stamp in after.features.stamps()] == [
        FrameRole.PLACE, FrameRole.JOINED, FrameRole.PLACE, FrameRole.JOINED, FrameRole.JOINED]
    # A smaller budget after the restart: the joined frames go first, oldest first.
    smaller = FrameStore(100, before.nbytes - 1, keep_depths=True, folder=tmp_path)
    smaller.load()
    assert smaller.features.stamps() == [SECOND, 3 * SECOND, 4 * SECOND, 5 * SECOND]
    assert smaller.evicted[FrameRole.JOINED] == 1
