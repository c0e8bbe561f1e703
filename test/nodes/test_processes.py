"""The suite as users run it: separate OS processes, a bag replayed through rclpy, results recorded.

Every replay is in lockstep with ``place_posteriors``, so no image is dropped however loaded the
machine is, and the results are deterministic.
"""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.io.bags import read_messages
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.stamps import stamp_to_ns
from aefabmap_ros.verification.geometric import VerificationConfig
from test.reliability import Recorder
from test.revisit_fixture import FRAMES_PER_PASS, RevisitData
from test.ros_processes import LoggedProcess

pytestmark = [pytest.mark.ros, pytest.mark.slow]

PARAMS = """
fabmap_node:
  ros__parameters:
    save_period_s: 0.2
feature_node:
  ros__parameters:
    image_qos: reliable
    drop_when_busy: false
"""


def _params_file(tmp_path: Path) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(PARAMS)
    return path


def _replay(tmp_path: Path, bag: Path, name: str) -> None:
    with LoggedProcess(tmp_path / f"{name}.log", "aefabmap_ros.cli.replay", bag, "--topic", "/image",
                       "--lockstep", "place_posteriors", "--lockstep-timeout", "60", "--quiet",
                       "--wait-timeout", "60") as replay:  # generous: a loaded CI machine, first imports
        assert replay.wait(timeout_s=240) == 0, replay.log()
        assert "0 without an answer" in replay.log(), replay.log()


Closure = tuple[int, int, float, int]  # (query stamp, matched stamp, probability, inliers)


def _closures(recording: Path, topic: str) -> list[Closure]:
    return [(m.stamp_ns, stamp_to_ns(m.message.matched_stamp), float(m.message.probability), int(m.message.inliers))
            for m in read_messages(recording, [f"/{topic}"])]  # recorded under its full name


def _record_replay(tmp_path: Path, bag: Path, name: str, closure_topics: tuple[str, ...]) -> dict[str, list[Closure]]:
    """Replay ``bag`` with a recorder running; the loop closures recorded on each of ``closure_topics``."""
    recording = tmp_path / f"{name}_recording"
    with LoggedProcess(tmp_path / f"{name}_record.log", "aefabmap_ros.cli.record", recording, "--topics",
                       *closure_topics, "place_posteriors", "--wait-publishers", "60") as recorder:
        recorder.wait_for_log("[record] recording", timeout_s=90)
        _replay(tmp_path, bag, name)
        time.sleep(1.0)  # the last closure's verification runs after its posterior was answered
        assert recorder.stop(signal.SIGINT) == 0, recorder.log()
    posteriors = list(read_messages(recording, ["/place_posteriors"]))
    assert len(posteriors) > 0
    return {topic: _closures(recording, topic) for topic in closure_topics}


def _frame_of(data: RevisitData, stamp_ns: int) -> int:
    index = int(np.searchsorted(data.stamps_ns, stamp_ns))
    assert data.stamps_ns[index] == stamp_ns, f"stamp {stamp_ns} is no frame of the bag"
    return index


def _true_revisits(data: RevisitData, closures: list[Closure]) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(true, wrong) (query frame, matched frame) pairs; every closure's posterior passed the threshold."""
    assert all(probability > FabMapConfig().match_threshold for _, _, probability, _ in closures)
    pairs = [(_frame_of(data, query), _frame_of(data, matched)) for query, matched, *_ in closures]
    return [p for p in pairs if data.gt[p]], [p for p in pairs if not data.gt[p]]


def _run_suite(tmp_path: Path, data: RevisitData, pipeline: bool, verify: bool) -> dict[str, list[Closure]]:
    name = "pipeline" if pipeline else "nodes"
    launch_args: list[str | Path] = ["--model", data.model_dir, "--params", _params_file(tmp_path)]
    if pipeline:
        launch_args.append("--pipeline")
    if not verify:
        launch_args.append("--no-verify")
    # Without the verifier nothing publishes loop_closure_candidates (remapped onto loop_closures).
    topics = ("loop_closures", "loop_closure_candidates") if verify else ("loop_closures",)
    with LoggedProcess(tmp_path / f"{name}_launch.log", "aefabmap_ros.cli.launch", *launch_args) as suite:
        # Every link must be matched before the first image, or that image is lost on the way (and the
        # verifier cannot verify a place whose features it never heard).
        for link in ("quantizer_node]: receiving features", "fabmap_node]: receiving words",
                     *(("verifier_node]: receiving features",) if verify else ())):
            suite.wait_for_log(link, timeout_s=90)
        closures = _record_replay(tmp_path, data.bag, name, topics)
        assert suite.stop(signal.SIGINT) == 0, suite.log()
    assert "fabmap_node: 32 places" in suite.log(), suite.log()[-3000:]
    assert ("verifier_node:" in suite.log()) == verify, suite.log()[-3000:]
    return closures


def test_loop_closures_are_verified_by_default_and_raw_with_no_verify(tmp_path: Path,
                                                                        revisit_data: RevisitData) -> None:
    """Default launch (separate processes): FAB-MAP's raw closures on loop_closure_candidates, and on
    loop_closures only those verifier_node passed, with their inliers. --no-verify (one-process
    pipeline): the raw candidates themselves on loop_closures, inliers -1 -- the same as the default
    run's candidates, so the pipeline agrees with the separate nodes."""
    (tmp_path / "separate").mkdir()
    (tmp_path / "together").mkdir()
    verified_run = _run_suite(tmp_path / "separate", revisit_data, pipeline=False, verify=True)
    candidates, published = verified_run["loop_closure_candidates"], verified_run["loop_closures"]
    # Candidates are FAB-MAP's consistent matches at a calibrated posterior of 0.1: most are revisits,
    # some first-pass look-alikes are not -- verification is what makes them trustworthy.
    true_candidates, _ = _true_revisits(revisit_data, candidates)
    assert len(true_candidates) >= FRAMES_PER_PASS // 2, candidates
    assert all(inliers == -1 for *_, inliers in candidates)
    min_inliers = VerificationConfig().min_inliers
    assert all(inliers >= min_inliers for *_, inliers in published), published
    true_published, wrong = _true_revisits(revisit_data, published)
    assert not wrong, f"published loop closures that are not revisits (query frame, matched frame): {wrong}"
    assert len(true_published) >= len(true_candidates) * 3 // 4, (published, candidates)
    by_query = {query: probability for query, _, probability, _ in candidates}
    # Each published closure is a candidate's (its matched place may move to a better-verified one).
    assert all(by_query.get(query) == probability for query, _, probability, _ in published), published

    raw_run = _run_suite(tmp_path / "together", revisit_data, pipeline=True, verify=False)
    raw = raw_run["loop_closures"]
    assert [(q, m, i) for q, m, _, i in raw] == [(q, m, i) for q, m, _, i in candidates]
    np.testing.assert_allclose([p for _, _, p, _ in raw], [p for _, _, p, _ in candidates], rtol=1e-12)


def _wait_until(condition: Callable[[], bool], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.1)


def _places_in(map_path: Path, data: RevisitData) -> int:
    model = load_model(data.model_dir)
    assert model.tree_matrix is not None
    recognizer = PlaceRecognizer(ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples,
                                 FabMapConfig(), model.vocabulary_id)
    recognizer.load_map(map_path)
    return recognizer.num_places


@pytest.mark.reliability
def test_fabmap_node_killed_and_restarted_keeps_its_saved_places(tmp_path: Path, revisit_data: RevisitData,
                                                                 reliability: Recorder) -> None:
    map_path = tmp_path / "map.npz"
    common: list[str | Path] = [
        "--ros-args", "--params-file", _params_file(tmp_path), "-p", f"model_dir:={revisit_data.model_dir}",
    ]
    fabmap_args = [*common, "-p", f"map_file:={map_path}"]
    with LoggedProcess(tmp_path / "feature.log", "aefabmap_ros.nodes.feature_node", *common) as features, \
            LoggedProcess(tmp_path / "quantizer.log", "aefabmap_ros.nodes.quantizer_node", *common) as quantizer:
        with LoggedProcess(tmp_path / "fabmap1.log", "aefabmap_ros.nodes.fabmap_node", *fabmap_args) as fabmap:
            fabmap.wait_for_log("receiving words", timeout_s=60)
            quantizer.wait_for_log("receiving features", timeout_s=60)
            _replay(tmp_path, revisit_data.first_pass_bag, "first")
            _wait_until(lambda: map_path.exists() and _places_in(map_path, revisit_data) == FRAMES_PER_PASS,
                        timeout_s=10)  # the periodic save (every 0.2 s) has caught up
            fabmap.stop(signal.SIGKILL)  # no shutdown hook: only what was saved survives
        assert _places_in(map_path, revisit_data) == FRAMES_PER_PASS
        reliability.fault("kill -9 of fabmap_node after its periodic save, then restart", injected=1, survived=1,
                          places_lost=FRAMES_PER_PASS - _places_in(map_path, revisit_data))

        with LoggedProcess(tmp_path / "fabmap2.log", "aefabmap_ros.nodes.fabmap_node", *fabmap_args) as fabmap:
            fabmap.wait_for_log(f"reloaded {FRAMES_PER_PASS} places", timeout_s=60)
            fabmap.wait_for_log("receiving words", timeout_s=60)
            closures = _record_replay(tmp_path, revisit_data.second_pass_bag, "second",
                                      ("loop_closure_candidates",))["loop_closure_candidates"]
            assert fabmap.stop(signal.SIGINT) == 0, fabmap.log()
        # The second pass closes loops with places made before the restart.
        true_closures, _ = _true_revisits(revisit_data, closures)
        assert len(true_closures) >= FRAMES_PER_PASS // 2, closures
        assert all(matched < FRAMES_PER_PASS for _, matched in true_closures)
        assert _places_in(map_path, revisit_data) == 2 * FRAMES_PER_PASS
        assert features.stop() == 0 and quantizer.stop() == 0
