"""PlaceRecognizer: golden posteriors online, policies, exclusion windows, map persistence."""

import numpy as np
import pytest
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError, ModelError, VocabularyMismatchError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer, jaccard
from test.fabmap.oracles import fabmap_score_matrices

openfabmap = FabMapConfig.openfabmap  # openFABMAP's semantics: the golden references' config


V = 40


def _tree(seed: int = 0) -> ChowLiuTree:
    rng = np.random.default_rng(seed)
    parent = np.array([0] + [int(rng.integers(0, q)) for q in range(1, V)])
    probs = rng.uniform(0.05, 0.6, size=(3, V))
    probs[1:, 0] = probs[0, 0]
    return ChowLiuTree(parent, probs[0], probs[1], probs[2])


def _frames(n: int, seed: int = 1) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.flatnonzero(rng.random(V) < 0.25) for _ in range(n)]


SAMPLES = sp.csr_matrix(np.random.default_rng(9).random((15, V)) < 0.25)


@pytest.mark.parametrize("motion", [False, True])
def test_online_matches_offline_all_policy(motion):
    config = openfabmap(motion_model=motion, top_k=100)
    frames = _frames(12)
    frames.append(frames[3])
    offline = fabmap_score_matrices(frames, _tree(), SAMPLES, config)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a")
    for i, words in enumerate(frames):
        result = recognizer.process(words, stamp_ns=1_000 * i)
        assert result.query_id == i and result.added_place_id == i
        assert result.new_place_probability == pytest.approx(offline.probabilities[i, i], abs=1e-12)
        for c in result.candidates:
            assert c.probability == pytest.approx(offline.probabilities[i, c.place_id], abs=1e-12)
            assert c.log_likelihood == pytest.approx(offline.log_likelihoods[i, c.place_id], abs=1e-9)
            assert c.stamp_ns == 1_000 * c.place_id
        assert len(result.candidates) == i
    assert result.candidates[0].place_id == 3


def test_golden_sequence_online(golden_dir):
    from aefabmap_ros.fabmap.openfabmap import read_bow, read_chow_liu_tree

    tree = read_chow_liu_tree(golden_dir / "tree.yml")
    train = sp.csr_matrix(read_bow(golden_dir / "bowtrain.yml"))
    test = read_bow(golden_dir / "bowtest.yml")
    golden_p = np.loadtxt(golden_dir / "fabmap2_sampled_motion.probabilities.txt")
    # openFABMAP recognises every frame, also its two blank ones (min_words=0).
    recognizer = PlaceRecognizer(tree, train, openfabmap(motion_model=True, top_k=3, min_words=0), "golden")
    for i, row in enumerate(test):
        result = recognizer.process(np.flatnonzero(row > 0).astype(np.uint32), stamp_ns=i)
        assert result.new_place_probability == pytest.approx(golden_p[i, i], abs=1e-5)
        for c in result.candidates:
            assert c.probability == pytest.approx(golden_p[i, c.place_id], abs=1e-5)
        if result.loop_closure is not None:
            assert result.loop_closure.probability > 0.99
            assert not result.is_new_place
            assert result.assigned_place_id == result.loop_closure.place_id
    assert recognizer.num_places == 84


def test_revisit_is_detected_and_new_only_policy_does_not_add_it():
    frames = _frames(10)
    config = openfabmap(add_policy="new_only", match_threshold=0.5)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "v")
    results = [recognizer.process(f, i) for i, f in enumerate(frames)]
    new = [r for r in results if r.is_new_place]
    assert recognizer.num_places == len(new) >= 2
    assert [r.added_place_id for r in new] == list(range(len(new)))
    assert all(r.added_place_id == -1 and r.assigned_place_id == r.loop_closure.place_id
               for r in results if r.loop_closure is not None)
    last = new[-1]
    revisit = recognizer.process(frames[last.query_id], 99)
    assert revisit.loop_closure is not None and revisit.loop_closure.place_id == last.added_place_id
    assert revisit.added_place_id == -1 and revisit.query_id == 10
    assert recognizer.num_places == len(new)
    assert sum(c.probability for c in revisit.candidates) + revisit.new_place_probability <= 1.0 + 1e-12


def test_recent_places_are_excluded_by_frames_and_seconds():
    frames = _frames(6)
    by_frames = PlaceRecognizer(_tree(), SAMPLES, openfabmap(exclude_recent_frames=2, top_k=10), "v")
    for i, f in enumerate(frames):
        r = by_frames.process(f, i * 10**9)
    assert [c.place_id for c in sorted(r.candidates, key=lambda c: c.place_id)] == [0, 1, 2]
    total = r.new_place_probability + sum(c.probability for c in r.candidates)
    assert total == pytest.approx(1.0)
    by_seconds = PlaceRecognizer(_tree(), SAMPLES, openfabmap(exclude_recent_seconds=2.5, top_k=10), "v")
    for i, f in enumerate(frames):
        r = by_seconds.process(f, i * 10**9)
    assert sorted(c.place_id for c in r.candidates) == [0, 1, 2]
    revisit = by_seconds.process(frames[5], 6 * 10**9)  # place 5 is only 1 s old: excluded
    assert 5 not in [c.place_id for c in revisit.candidates]


def test_keyframe_policy():
    base = np.arange(10)
    config = openfabmap(keyframe_max_overlap=0.5, keyframe_max_frames=4)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "v")
    added = [recognizer.process(base, i).added_place_id for i in range(6)]
    assert added == [0, -1, -1, -1, 1, -1]  # same view: only forced every 4 frames
    changed = recognizer.process(np.arange(20, 30), 6)
    assert changed.added_place_id == 2
    spaced = PlaceRecognizer(_tree(), SAMPLES, openfabmap(keyframe_min_frames=3), "v")
    assert [spaced.process(np.array([i]), i).added_place_id for i in range(7)] == [0, -1, -1, 1, -1, -1, 2]
    assert jaccard(np.array([1, 2]), np.array([2, 3])) == pytest.approx(1 / 3)
    assert jaccard(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)) == 1.0


def test_empty_frames_keep_their_index_and_errors():
    recognizer = PlaceRecognizer(_tree(), SAMPLES, openfabmap(min_words=0), "v")
    assert recognizer.process(np.zeros(0, dtype=np.uint32), 0).added_place_id == 0
    assert recognizer.process(np.array([3, 1, 1]), 1).added_place_id == 1  # normalised to [1, 3]
    np.testing.assert_array_equal(recognizer.place_words(1), [1, 3])
    with pytest.raises(DataError, match=f"word id {V} out of range"):
        recognizer.process(np.array([V]), 2)
    with pytest.raises(DataError, match="stamp_ns must be an integer"):
        recognizer.process(np.array([1]), 2.5)  # type: ignore[arg-type]
    with pytest.raises(DataError, match="vocabulary_id"):
        PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "")
    with pytest.raises(DataError, match="place id 7 out of range"):
        recognizer.place_words(7)
    assert recognizer.num_queries == 2


def test_blank_frame_is_certain_to_match_a_blank_place_without_min_words():
    """Why min_words exists: FAB-MAP alone "recognises" an earlier blank frame with certainty."""
    frames = _frames(6)
    blank = np.zeros(0, dtype=np.int64)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, openfabmap(min_words=0), "v")
    for i, words in enumerate([blank, *frames]):
        recognizer.process(words, i)
    best, second = recognizer.process(blank, 10).candidates[:2]
    assert best.place_id == 0 and best.probability > 0.5 and best.probability > 5 * second.probability
    skipping = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "v")  # default min_words = 1
    for i, words in enumerate([blank, *frames]):
        skipping.process(words, i)
    assert skipping.process(blank, 10).candidates == () and skipping.num_places == len(frames)


@pytest.mark.parametrize("motion_model", [False, True])
def test_frames_below_min_words_are_skipped(motion_model):
    frames = _frames(8)
    config = openfabmap(min_words=3, motion_model=motion_model, top_k=100)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "v")
    reference = PlaceRecognizer(_tree(), SAMPLES, config, "v")  # never sees the sparse frames
    sparse = [np.zeros(0, dtype=np.int64), np.array([2, 5])]
    results = []
    for i, words in enumerate([sparse[0], *frames[:4], sparse[1], *frames[4:]]):
        results.append(recognizer.process(words, i))
    for result in (results[0], results[5]):
        assert not result.informative and result.candidates == () and result.loop_closure is None
        assert result.added_place_id == -1 and result.assigned_place_id == -1 and not result.is_new_place
        assert np.isnan(result.new_place_probability)
    assert recognizer.num_queries == 10 and recognizer.num_places == 8
    # The informative frames are recognised exactly as if the sparse ones had never arrived (the
    # motion model continues from the last informative posterior).
    informative = [r for r in results if r.informative]
    for words, result in zip(frames, informative, strict=True):
        expected = reference.process(words, result.stamp_ns)
        assert result.added_place_id == expected.added_place_id
        assert result.new_place_probability == pytest.approx(expected.new_place_probability, rel=1e-12)
        assert [(c.place_id, c.stamp_ns) for c in result.candidates] == \
            [(c.place_id, c.stamp_ns) for c in expected.candidates]
        np.testing.assert_allclose([c.probability for c in result.candidates],
                                   [c.probability for c in expected.candidates], rtol=1e-12)
    with pytest.raises(ConfigError, match="min_words"):
        openfabmap(min_words=-1)


def test_map_round_trip_and_refusals(tmp_path):
    config = openfabmap(motion_model=True, top_k=4)
    frames = _frames(8)
    first = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a")
    for i, f in enumerate(frames[:5]):
        first.process(f, 10 * i)
    path = tmp_path / "maps" / "map.npz"
    first.save_map(path)
    assert [p.name for p in path.parent.iterdir()] == ["map.npz"]  # no temp file left behind
    second = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a")
    second.load_map(path, new_session=False)  # the same session goes on: as if never stopped
    assert second.num_places == 5 and second.num_queries == 5
    for i, f in enumerate(frames[5:], start=5):
        a, b = first.process(f, 10 * i), second.process(f, 10 * i)
        assert a == b
    other = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-b")
    with pytest.raises(VocabularyMismatchError, match=r"'vocab-a'.*'vocab-b'"):
        other.load_map(path)
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ModelError, match="cannot read map file"):
        second.load_map(corrupt)
    with pytest.raises(ModelError, match="map file not found"):
        second.load_map(tmp_path / "missing.npz")
    np.savez(tmp_path / "foreign.npz", x=np.zeros(3))
    with pytest.raises(ModelError, match="not a place map"):
        second.load_map(tmp_path / "foreign.npz")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["word_indices"] = arrays["word_indices"].copy()
    arrays["word_indices"][0] = V + 5
    np.savez(tmp_path / "bad_ids.npz", **arrays)
    with pytest.raises(ModelError, match="word ids out of range"):
        second.load_map(tmp_path / "bad_ids.npz")
    assert second.num_places == 8  # a refused map leaves the current one untouched


def test_bulk_added_places_equal_processed_ones():
    frames = _frames(6)
    processed = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "v")
    for i, f in enumerate(frames[:5]):
        processed.process(f, i)
    bulk = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "v")
    rows = np.zeros((5, V), dtype=bool)
    for i, f in enumerate(frames[:5]):
        rows[i, f] = True
    bulk.add_places(sp.csr_matrix(rows), np.arange(5, dtype=np.int64))
    a, b = processed.process(frames[5], 5), bulk.process(frames[5], 5)
    assert a.candidates == b.candidates and a.query_id == b.query_id == 5
    with pytest.raises(DataError, match="expected"):
        bulk.add_places(sp.csr_matrix((2, V + 1)), np.arange(2))
    with pytest.raises(DataError, match="stamps_ns"):
        bulk.add_places(sp.csr_matrix((2, V)), np.arange(3))


def _place_recognizer(**overrides) -> PlaceRecognizer:
    return PlaceRecognizer(_tree(), SAMPLES, openfabmap(**overrides), "v")


def test_consistency_holds_back_a_single_match():
    """A revisit of places 0..2 by frames 4..6: with consistency_matches 2 the first match is no closure."""
    frames = [np.arange(0, 10), np.arange(10, 20), np.arange(20, 30), np.arange(30, 40)]
    for required, closures in ((1, [True, True, True]), (2, [False, True, True]), (4, [False, False, False])):
        recognizer = _place_recognizer(consistency_matches=required, island_seconds=1.5, match_threshold=0.5)
        for i, words in enumerate(frames):
            recognizer.process(words, i * 10**9)
        results = [recognizer.process(frames[k], (4 + k) * 10**9) for k in range(3)]
        assert [r.match.place_id if r.match else -1 for r in results] == [0, 1, 2]  # every frame matches ...
        assert [r.loop_closure is not None for r in results] == closures  # ... but only consistent ones close


def test_consistency_skips_a_frame_that_flickers():
    """Revisit frames 0, (a frame matching nothing), 1: the chain of two matches survives the skipped frame."""
    frames = [np.arange(0, 10), np.arange(10, 20), np.arange(20, 30), np.arange(30, 40)]
    flicker = np.r_[0:40:4]  # a few words of every place: no place stands out
    for skips, closures in ((0, [False, False, False]), (1, [False, False, True])):
        recognizer = _place_recognizer(consistency_matches=2, consistency_skips=skips, island_seconds=1.5,
                                       match_threshold=0.5, add_policy="new_only")
        for i, words in enumerate(frames):
            recognizer.process(words, i * 10**9)
        revisit = (frames[0], flicker, frames[1])
        results = [recognizer.process(words, (5 + k) * 10**9) for k, words in enumerate(revisit)]
        assert [r.match.place_id if r.match else -1 for r in results] == [0, -1, 1]
        assert [r.loop_closure is not None for r in results] == closures


def test_consistency_window_reaches_over_a_30hz_flicker():
    """At 30 Hz a revisit matched place 0, flickered for 10 frames (1/3 s), then matched place 1: the
    time window chains the two matches where a frame count of skips does not."""
    frames = [np.arange(0, 10), np.arange(10, 20), np.arange(20, 30), np.arange(30, 40)]
    flicker = np.r_[0:40:4]
    revisit = (frames[0], *[flicker] * 10, frames[1])
    for window, closes in ((0.0, False), (0.5, True)):
        recognizer = _place_recognizer(consistency_matches=2, consistency_skips=1, consistency_window_seconds=window,
                                       island_seconds=1.5, match_threshold=0.5, add_policy="new_only",
                                       exclude_recent_seconds=1.0)  # the flicker's own new place is no hypothesis
        for i, words in enumerate(frames):
            recognizer.process(words, i * 10**9)
        results = [recognizer.process(words, 5 * 10**9 + k * 10**9 // 30) for k, words in enumerate(revisit)]
        assert [r.match.place_id if r.match else -1 for r in results] == [0] + [-1] * 10 + [1]
        assert [r.loop_closure is not None for r in results] == [False] * 11 + [closes]


def test_linked_overlap_excludes_the_stretch_still_in_view():
    """Frames that share words with the query back to the last break are no hypotheses, older ones are."""
    view = np.arange(0, 10)
    frames = [view, np.arange(10, 20), view[:8], np.r_[view[:6], 30, 31], np.r_[view[:7], 32]]
    recognizer = _place_recognizer(exclude_linked_overlap=0.3)
    for i, words in enumerate(frames):
        recognizer.process(words, i)
    query = recognizer.process(view, 5)
    # Places 2..4 overlap the query by >= 0.3 (0.8, 0.5, 0.64) up to place 1 (overlap 0): excluded.
    # Place 0 lies beyond that break: it is a hypothesis although it overlaps fully.
    np.testing.assert_array_equal(query.hypothesis_place_ids, [0, 1])
    assert query.candidates[0].place_id == 0
    assert query.hypothesis_probabilities.shape == (2,)


def test_keyframe_max_seconds_splits_a_long_stay_and_maps_frames_to_places():
    recognizer = _place_recognizer(keyframe_max_overlap=0.5, keyframe_max_seconds=2.0)
    still = np.arange(10)
    results = [recognizer.process(still, int(t * 10**9)) for t in (0.0, 0.5, 1.0, 1.9, 2.0, 2.5, 4.1)]
    assert [r.added_place_id for r in results] == [0, -1, -1, -1, 1, -1, 2]
    assert [r.current_place_id for r in results] == [0, 0, 0, 0, 1, 1, 2]


def test_likelihood_temperature_is_a_softmax_of_scaled_log_likelihoods():
    """Closed form: p = s * softmax([new_ll, place_ll] / T) + (1 - s) / n, from the reported log-likelihoods."""
    frames = _frames(8)
    recognizer = _place_recognizer(likelihood_temperature=3.0, top_k=100)
    for i, words in enumerate(frames[:-1]):
        recognizer.process(words, i)
    result = recognizer.process(frames[2], 7)
    lls = np.r_[result.new_place_log_likelihood, [c.log_likelihood for c in result.candidates]]
    expected = np.exp((lls - lls.max()) / 3.0)
    expected = 0.99 * expected / expected.sum() + 0.01 / lls.size
    actual = np.r_[result.new_place_probability, [c.probability for c in result.candidates]]
    np.testing.assert_allclose(actual, expected, rtol=1e-12)
    assert result.candidates[0].place_id == 2
    with pytest.raises(ConfigError, match=r"likelihood_temperature = 0\.0"):
        openfabmap(likelihood_temperature=0.0)


def test_a_map_reports_the_settings_it_was_made_with_that_differ(tmp_path):
    path = tmp_path / "map.npz"
    maker = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "v")
    maker.process(_frames(1)[0], 0)
    maker.save_map(path)
    assert PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "v").load_map(path) == {}
    other = PlaceRecognizer(_tree(), SAMPLES, openfabmap(match_threshold=0.5, top_k=3), "v")
    assert other.load_map(path) == {"match_threshold": (openfabmap().match_threshold, 0.5),
                                    "top_k": (openfabmap().top_k, 3)}
    assert other.num_places == 1  # used as it is
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    del arrays["config_json"]
    np.savez(tmp_path / "old.npz", **arrays)
    assert set(other.load_map(tmp_path / "old.npz")) == {"config_json"}


def test_runtime_settings_change_from_the_next_frame_and_the_rest_are_refused():
    recognizer = _place_recognizer()
    recognizer.reconfigure({"match_threshold": 0.5, "top_k": 2})
    assert recognizer.config.match_threshold == 0.5 and recognizer.config.top_k == 2
    with pytest.raises(ConfigError, match="p_z_given_e cannot change"):
        recognizer.reconfigure({"p_z_given_e": 0.5, "match_threshold": 0.2})
    with pytest.raises(ConfigError, match="match_threshold"):
        recognizer.reconfigure({"match_threshold": 1.5})
    assert recognizer.config.match_threshold == 0.5  # a refused change changes nothing
