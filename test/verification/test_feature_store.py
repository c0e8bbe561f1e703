"""The bounded feature store and its folder of chunks on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.feature_store import FeatureStore, FeatureStoreFolder
from aefabmap_ros.verification.geometric import VerificationConfig, verify_pair
from test.verification.test_geometric import _features, _two_views


def test_store_is_bounded_and_forgets_the_oldest() -> None:
    store = FeatureStore(max_frames=2)
    query, place, _ = _two_views(seed=10, shared=20, clutter=0)
    store.add(100, query)
    store.add(200, place)
    store.add(300, query)
    assert len(store) == 2 and store.get(100) is None and store.get(999) is None
    assert 100 not in store and 200 in store and 300 in store
    restored = store.get(200)
    assert restored is not None and restored.descriptors.dtype == np.float32
    np.testing.assert_allclose(restored.descriptors, place.descriptors, rtol=1e-3, atol=0.2)  # float16
    np.testing.assert_array_equal(restored.keypoints, place.keypoints[:, :2])
    size = store.nbytes
    store.add(300, query)  # replacing a frame does not count it twice
    assert store.nbytes == size == 2 * (20 * 2 * 4 + 20 * 128 * 2)


def test_store_keeps_integer_sift_values_exactly() -> None:
    """OpenCV's SIFT descriptors are integers below 256, which float16 represents exactly."""
    _, place, _ = _two_views(seed=12, shared=20, clutter=0)
    integral = Features(keypoints=place.keypoints, descriptors=np.round(place.descriptors), descriptor_type="sift")
    store = FeatureStore(max_frames=1)
    store.add(1, integral)
    kept = store.get(1)
    assert kept is not None and np.array_equal(kept.descriptors, integral.descriptors)


def test_store_keeps_the_strongest_keypoints_and_verification_still_works() -> None:
    query, place, _ = _two_views(seed=11)
    store = FeatureStore(max_frames=10, max_features_per_frame=100)
    store.add(1, query)
    store.add(2, place)
    kept = store.get(1)
    assert kept is not None and len(kept) == 100
    strongest = np.argsort(-query.keypoints[:, 4], kind="stable")[:100]
    np.testing.assert_array_equal(kept.keypoints, query.keypoints[np.sort(strongest), :2])
    stored_query, stored_place = store.get(1), store.get(2)
    assert stored_query is not None and stored_place is not None
    assert verify_pair(stored_query, stored_place, VerificationConfig()).accepted
    with pytest.raises(ConfigError, match="max_frames >= 1"):
        FeatureStore(max_frames=0)




def test_store_folder_appends_only_new_frames_and_reloads_the_newest(tmp_path: Path) -> None:
    query, place, _ = _two_views(seed=13, shared=30, clutter=10)
    store = FeatureStore(max_frames=5, max_features_per_frame=25)
    folder = FeatureStoreFolder(tmp_path / "map.features")
    store.add(10, query)
    store.add(20, place)
    folder.save(store)
    store.add(30, query)
    folder.save(store)
    folder.save(store)  # nothing new: no chunk
    chunks = sorted(p.name for p in folder.folder.iterdir())
    assert chunks == ["chunk-000000000.npz", "chunk-000000001.npz"]  # no temporary file left either
    with np.load(folder.folder / chunks[1]) as second:
        assert second["stamps_ns"].tolist() == [30]  # the second save wrote only the new frame
    again = FeatureStore(max_frames=5)
    FeatureStoreFolder(folder.folder).load_into(again)
    assert len(again) == 3 and again.nbytes == store.nbytes and not again.unsaved()
    for stamp in (10, 20, 30):
        a, b = store.get(stamp), again.get(stamp)
        assert a is not None and b is not None and b.descriptor_type == "sift"
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
        np.testing.assert_array_equal(a.descriptors, b.descriptors)
    first_view, second_view = again.get(10), again.get(20)
    assert first_view is not None and second_view is not None
    assert verify_pair(first_view, second_view, VerificationConfig()).accepted
    newest = FeatureStore(max_frames=2)
    FeatureStoreFolder(folder.folder).load_into(newest)
    assert 10 not in newest and 20 in newest and 30 in newest


def test_store_folder_deletes_chunks_whose_frames_were_all_forgotten(tmp_path: Path) -> None:
    query, place, _ = _two_views(seed=16, shared=10, clutter=0)
    store = FeatureStore(max_frames=2)
    folder = FeatureStoreFolder(tmp_path / "store")
    store.add(1, query)
    folder.save(store)  # chunk 0: frame 1
    store.add(2, place)
    store.add(1, place)  # frame 1 again, newer features: chunk 1 holds them
    folder.save(store)
    store.add(3, query)  # forgets frame 2 (the oldest now), frame 1 stays
    store.add(4, query)  # forgets frame 1
    folder.save(store)
    assert sorted(p.name for p in folder.folder.iterdir()) == ["chunk-000000002.npz"]
    reloaded = FeatureStore(max_frames=2)
    loader = FeatureStoreFolder(folder.folder)
    loader.load_into(reloaded)
    assert sorted(s for s in (1, 2, 3, 4) if s in reloaded) == [3, 4]
    replaced = FeatureStore(max_frames=5)
    two = FeatureStoreFolder(tmp_path / "replace")
    replaced.add(1, query)
    two.save(replaced)
    replaced.add(1, place)
    two.save(replaced)
    later = FeatureStore(max_frames=5)
    FeatureStoreFolder(two.folder).load_into(later)
    got = later.get(1)
    assert got is not None and np.array_equal(got.keypoints, place.keypoints[:, :2])  # the later copy wins


def test_binary_and_empty_stores_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(14)
    orb = _features(rng.uniform(0, 600, (12, 2)), rng.integers(0, 256, (12, 32), dtype=np.uint8))
    store = FeatureStore(max_frames=3)
    store.add(1, orb)
    FeatureStoreFolder(tmp_path / "orb").save(store)
    loaded = FeatureStore(max_frames=3)
    FeatureStoreFolder(tmp_path / "orb").load_into(loaded)
    got = loaded.get(1)
    assert got is not None and got.descriptors.dtype == np.uint8 and np.array_equal(got.descriptors, orb.descriptors)
    empty = FeatureStore(max_frames=3)
    FeatureStoreFolder(tmp_path / "never-saved").load_into(empty)  # no folder yet: an empty store
    FeatureStoreFolder(tmp_path / "never-saved").save(empty)  # nothing to write
    assert len(empty) == 0 and empty.nbytes == 0 and not (tmp_path / "never-saved").exists()


def test_store_folder_refuses_bad_chunks_and_mixed_kinds(tmp_path: Path) -> None:
    from aefabmap_ros.errors import ModelError

    store = FeatureStore(max_frames=3)
    query, _, _ = _two_views(seed=15, shared=10, clutter=0)
    store.add(1, query)
    (tmp_path / "a-file").write_bytes(b"")
    with pytest.raises(ModelError, match="is not a folder"):
        FeatureStoreFolder(tmp_path / "a-file").load_into(store)
    good = FeatureStoreFolder(tmp_path / "good")
    good.save(store)
    with np.load(good.folder / "chunk-000000000.npz") as data:
        arrays = {key: data[key] for key in data.files}
    cases = {
        "junk": (None, "cannot read feature store chunk"),
        "other": ({"weights": np.zeros(3), "format_version": np.array(1)}, "is not a feature store chunk"),
        "short": ({**arrays, "counts": arrays["counts"] + 1}, "corrupt: 11 keypoints counted, 10 keypoints"),
        "future": ({**arrays, "format_version": np.array(99)}, "format version 99"),
    }
    for name, (content, message) in cases.items():
        folder = tmp_path / name
        folder.mkdir()
        if content is None:
            (folder / "chunk-000000000.npz").write_bytes(b"not a zip file")
        else:
            np.savez(folder / "chunk-000000000.npz", **content)
        with pytest.raises(ModelError, match=message):
            FeatureStoreFolder(folder).load_into(store)
    assert len(store) == 1 and 1 in store  # every failed load left the store as it was
    mixed = FeatureStore(max_frames=3)
    mixed.add(1, query)
    with pytest.raises(DataError, match="the store holds"):  # one store (and chunk) holds one kind
        mixed.add(2, _features(np.zeros((4, 2)), np.zeros((4, 32), np.uint8)))
    FeatureStoreFolder(tmp_path / "mixed").save(mixed)  # the stray frame did not poison the save


def test_store_refuses_a_frame_of_another_descriptor_kind_so_saves_keep_working(tmp_path: Path) -> None:
    query, place, _ = _two_views(seed=41)
    store = FeatureStore(10, max_features_per_frame=50)
    store.add(1, place)
    short = Features(query.keypoints, np.ascontiguousarray(query.descriptors[:, :64]), query.descriptor_type)
    with pytest.raises(DataError, match="the store holds"):
        store.add(2, short)
    no_response = Features(query.keypoints[:, :2].copy(), query.descriptors, query.descriptor_type)
    with pytest.raises(DataError, match="no response column"):
        store.add(3, no_response)  # more than 50 keypoints to trim, nothing to rank them by
    folder = FeatureStoreFolder(tmp_path / "store")
    folder.save(store)
    assert len(store) == 1 and len(list((tmp_path / "store").glob("chunk-*.npz"))) == 1
