"""Sessions of a map: every place and candidate names its session and robot, a new session starts afresh
(uniform prior, a place at its first frame, earlier sessions never "too recent"), and sessions survive a
save and reload. Posteriors are checked against the offline oracle, which knows nothing of sessions."""

import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.fabmap.sessions import SessionTable
from test.fabmap.oracles import fabmap_score_matrices
from test.fabmap.test_recognizer import SAMPLES, _frames, _tree, openfabmap


def test_a_recognizer_starts_in_session_0_of_its_robot():
    recognizer = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "vocab-a", robot="r1")
    result = recognizer.process(_frames(1)[0], 0)
    assert (result.session, result.robot) == (0, "r1")
    assert recognizer.place_sessions.tolist() == [0]
    assert [(s.number, s.robot, s.first_query_id) for s in recognizer.sessions] == [(0, "r1", 0)]


def test_a_new_session_starts_from_the_motion_model_s_first_prior():
    """With the motion model on, the first frame of a new session gets the prior of a map's first frame (new:
    p_new, every place weight 1, as openFABMAP starts): the robot may have been carried anywhere. Reference:
    the oracle's log-likelihoods of that frame through that prior by hand."""
    frames = _frames(7)
    config = openfabmap(motion_model=True, top_k=100)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a")
    for i, words in enumerate(frames[:6]):
        recognizer.process(words, 1_000 * i)
    recognizer.start_session()
    first = recognizer.process(frames[6], 6_000)
    oracle = fabmap_score_matrices(frames, _tree(), SAMPLES, config)
    scores = np.concatenate([[oracle.log_likelihoods[6, 6] + np.log(config.p_new)], oracle.log_likelihoods[6, :6]])
    expected = np.exp(scores - scores.max())
    expected = config.smoothing * expected / expected.sum() + (1.0 - config.smoothing) / expected.size
    assert first.new_place_probability == pytest.approx(expected[0], abs=1e-12)
    for candidate in first.candidates:
        assert candidate.probability == pytest.approx(expected[1 + candidate.place_id], abs=1e-12)
    # The same frame without the new session continues the motion model: another posterior.
    assert abs(oracle.probabilities[6, 6] - expected[0]) > 1e-6


def test_earlier_sessions_are_never_too_recent_and_name_their_session():
    """A robot restarted where it stopped sees the last place of the earlier session: a hypothesis (it joins
    the two sessions' graphs), whereas the same view within one session is excluded as recent."""
    frames = _frames(6, seed=3)
    config = openfabmap(exclude_recent_frames=3, top_k=3)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a", robot="r1")
    for i, words in enumerate(frames):
        recognizer.process(words, 1_000 * i)
    within = recognizer.process(frames[5], 6_000)
    assert 5 not in [c.place_id for c in within.candidates]  # one frame ago: excluded in the same session
    recognizer.start_session("r2")
    revisit = recognizer.process(frames[5], 7_000, robot="r2")
    assert (revisit.session, revisit.robot) == (1, "r2")
    # Frames 5 and 6 (the same view, both places of session 0) share the posterior.
    assert {(c.place_id, c.session, c.robot) for c in revisit.candidates[:2]} == {(5, 0, "r1"), (6, 0, "r1")}


def test_a_session_s_first_informative_frame_makes_a_place():
    """Keyframing compares with the session's own last place: a new session's first frame is always one, even
    when it repeats the last place of the earlier session."""
    frames = _frames(3)
    config = openfabmap(keyframe_max_overlap=0.5, add_policy="all")
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a")
    recognizer.process(frames[0], 0)
    assert recognizer.process(frames[0], 1).added_place_id == -1  # same words, same session: no keyframe
    recognizer.start_session()
    added = recognizer.process(frames[0], 2)
    assert added.added_place_id == 1 and recognizer.place_sessions.tolist() == [0, 1]


def test_sessions_survive_save_and_reload_and_a_reload_starts_a_new_one(tmp_path):
    frames = _frames(6)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "vocab-a", robot="r1")
    for i, words in enumerate(frames[:3]):
        recognizer.process(words, 1_000 * i)
    recognizer.start_session("r2")
    for i, words in enumerate(frames[3:5], start=3):
        recognizer.process(words, 1_000 * i, robot="r2")
    path = tmp_path / "map.npz"
    recognizer.save_map(path)
    reloaded = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "vocab-a", robot="r3")
    reloaded.load_map(path)
    assert [(s.number, s.robot, s.first_query_id) for s in reloaded.sessions] == [(0, "r1", 0), (1, "r2", 3),
                                                                                  (2, "r3", 5)]
    assert reloaded.place_sessions.tolist() == [0, 0, 0, 1, 1]
    result = reloaded.process(frames[5], 5_000)
    assert (result.session, result.robot, result.added_place_id) == (2, "r3", 5)
    continued = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "vocab-a")
    continued.load_map(path, new_session=False)
    assert len(continued.sessions) == 2 and continued.process(frames[5], 5_000).session == 1


def test_a_session_without_frames_is_reused():
    """A node restarted twice without an image adds one session, not an empty one per restart."""
    recognizer = PlaceRecognizer(_tree(), SAMPLES, openfabmap(), "vocab-a")
    recognizer.process(_frames(1)[0], 0)
    first = recognizer.start_session()
    assert recognizer.start_session() == first and len(recognizer.sessions) == 2


def test_session_table_round_trips_and_refuses_bad_columns():
    table = SessionTable()
    table.start("", 0)
    table.start("r2", 10)
    again = SessionTable.from_arrays(**{"robots": table.to_arrays()["session_robots"],
                                        "first_queries": table.to_arrays()["session_first_queries"]})
    assert [(s.number, s.robot, s.first_query_id) for s in again] == [(0, "", 0), (1, "r2", 10)]
    assert again.robots() == ["", "r2"]
    with pytest.raises(DataError, match="not increasing"):
        SessionTable.from_arrays(np.array(["a", "b"]), np.array([5, 1]))
    with pytest.raises(DataError, match="out of range"):
        again[2]
    with pytest.raises(DataError, match="one-line"):
        table.start("bad\nname", 20)


def test_two_robots_interleaved_score_every_place_as_the_oracle_does():
    """Two robots' frames interleaved on one map, with every place a hypothesis and a uniform prior: each
    frame's posterior is the offline run's over the frames in arrival order, whichever robot sent them."""
    frames = _frames(12, seed=5)
    config = openfabmap(top_k=100)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a", robot="r1")
    oracle = fabmap_score_matrices(frames, _tree(), SAMPLES, config)
    for i, words in enumerate(frames):
        robot = "r1" if i % 2 == 0 else "r2"
        result = recognizer.process(words, 1_000 * (i // 2), robot=robot)  # the two clocks run side by side
        assert (result.robot, result.session, result.added_place_id) == (robot, i % 2, i)
        assert result.new_place_probability == pytest.approx(oracle.probabilities[i, i], abs=1e-12)
        for candidate in result.candidates:
            assert candidate.probability == pytest.approx(oracle.probabilities[i, candidate.place_id], abs=1e-12)
            assert candidate.robot == ("r1" if candidate.place_id % 2 == 0 else "r2")
    assert [(s.number, s.robot) for s in recognizer.sessions] == [(0, "r1"), (1, "r2")]


def test_recent_places_are_each_robot_s_own():
    """A place robot r1 made a frame ago is too recent for r1 but a revisit for r2, which is elsewhere in
    its own session (the inter-robot closure); a robot's keyframing compares with its own last place."""
    frames = _frames(6, seed=6)
    config = openfabmap(exclude_recent_frames=2, top_k=10, keyframe_max_overlap=0.5)
    recognizer = PlaceRecognizer(_tree(), SAMPLES, config, "vocab-a", robot="r1")
    for i, words in enumerate(frames[:3]):
        recognizer.process(words, 1_000 * i, robot="r2")
    made = recognizer.process(frames[3], 5_000, robot="r1")
    assert made.added_place_id == 3
    other = recognizer.process(frames[3], 5_001, robot="r2")
    assert other.candidates[0].place_id == 3 and other.candidates[0].robot == "r1"
    assert other.added_place_id == 4  # r2's last place is place 2 (other words): a keyframe of r2
    same = recognizer.process(frames[3], 5_002, robot="r1")
    assert 3 not in [c.place_id for c in same.candidates]  # r1's own frame of one frame ago
    assert same.added_place_id == -1  # the same view as r1's last place: no keyframe
    assert same.current_place_id == 3
