"""aefabmap_eval --recording on a map of two sessions: the closures per pair of sessions against a hand-made
ground truth with a known answer, the pose errors per pair, the joined trajectory's error; a recording of one
session gives today's output."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.cli.evaluate import main
from aefabmap_ros.evaluation.trajectory_error import tum_text
from test.cli.test_evaluate import frame_stamp, save_gt, write_recording

FRAMES = 40
A, B = ("", 0), ("", 1)
SESSIONS = {frame: A if frame < 20 else B for frame in range(FRAMES)}


def _gt() -> np.ndarray:
    gt = np.zeros((FRAMES, FRAMES), np.uint8)
    for k in range(4):
        gt[20 + k, k] = 1  # session B's frames 20-23 revisit session A's 0-3
    gt[39, 25] = 1  # within B
    gt[15, 2] = 1  # within A
    return gt


def _translation(x: float, y: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, 3] = [x, y]
    return pose


def _recording(root: Path) -> Path:
    # The camera moves along x, 1 m a frame (pose truth below): frame m seen from frame q is (m - q) m along x.
    closures = [(20, 0, 0.999, 50, _translation(-20.0), True),  # true, exact pose
                (21, 1, 0.999, 40, _translation(-20.0, 0.5), True),  # true, pose 0.5 m off
                (22, 8, 0.999, 30),  # false (gt 0), no pose
                (39, 25, 0.999, 45, _translation(-14.0), True),  # within B
                (15, 2, 0.999, 45, _translation(-13.0), True)]  # within A
    closures.sort(key=lambda closure: closure[0])
    write_recording(root / "run", [(i, [], []) for i in range(FRAMES)], {"/loop_closures": closures},
                    sessions=SESSIONS)
    save_gt(root / "gt.npz", _gt())
    (root / "truth.tum").write_text(tum_text(np.array([frame_stamp(i) for i in range(FRAMES)]) / 1e9,
                                             np.stack([_translation(float(i)) for i in range(FRAMES)])))
    return root / "run"


def test_closures_per_pair_of_sessions(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _recording(tmp_path)
    assert main(["--recording", str(run), "--gt", str(tmp_path / "gt.npz"), "--pose-truth",
                 str(tmp_path / "truth.tum"), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "Loop closures per pair of sessions" in printed
    # 3 closures from B into A, 1 false; of B's 4 frames revisiting A, 2 closed; 1 of 2 poses checked is wrong.
    assert "| 1 -> 0 | 3 | 1 | 0 | 0.500 (2/4) | 1 / 2 | 0.000 | 0.250 |" in printed
    assert "| 0 -> 0 | 1 | 0 | 0 | 1.000 (1/1) | 0 / 1 | 0.000 | 0.000 |" in printed
    assert "| 1 -> 1 | 1 | 0 | 0 | 1.000 (1/1) | 0 / 1 | 0.000 | 0.000 |" in printed
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert results["sessions"] == ["0", "1"]
    pairs = {(p["query_session"], p["matched_session"]): p for p in results["session_pairs"]["pairs"]}
    assert list(pairs) == [(0, 0), (1, 0), (1, 1)]
    cross = pairs[(1, 0)]
    assert (cross["closures"], cross["false_closures"], cross["revisiting_frames_closed"],
            cross["revisiting_frames"], cross["wrong_poses"], cross["poses_checked"]) == (3, 1, 2, 4, 1, 2)
    assert cross["recall_revisiting_frames"] == 0.5
    assert cross["median_translation_error_m"] == pytest.approx(0.25, abs=1e-6)
    assert "Loop closures per pair of sessions" in (tmp_path / "out" / "results.md").read_text()


def test_a_recording_of_one_session_gives_todays_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    closures = [(20, 0, 0.999, 50), (21, 1, 0.999, 40), (22, 8, 0.999, 30)]
    write_recording(tmp_path / "run", [(i, [], []) for i in range(FRAMES)], {"/loop_closures": closures})
    save_gt(tmp_path / "gt.npz", _gt())
    assert main(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"), "--out",
                 str(tmp_path / "out"), "--quiet"]) == 0
    assert "pair of sessions" not in capsys.readouterr().out
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert not {"sessions", "session_pairs", "joined_trajectory"} & set(results)


def test_the_joined_trajectory_against_each_sessions_odometry(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Known answers (test/evaluation/test_session_trajectory.py derives them): the joined trajectory with session
    B 0.4 m off along x has an ATE of 0.2 m; each session's odometry, off by +-0.5 m in z on alternate stationary
    pairs, 0.5 m."""
    from test.evaluation.test_session_trajectory import write_two_sessions

    (tmp_path / "trajectories").mkdir()
    files = write_two_sessions(tmp_path / "trajectories", offset_m=0.4, odometry_error_m=0.5)
    run = _recording(tmp_path)
    assert main(["--recording", str(run), "--gt", str(tmp_path / "gt.npz"), "--pose-truth", str(files["truth"]),
                 "--trajectory", str(files["joined"]), "--session-odometry", str(files["a"]), "--session-odometry",
                 str(files["b"]), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "Joined trajectory error: 40.0 % of odometry's." in printed
    joined = json.loads((tmp_path / "out" / "results.json").read_text())["joined_trajectory"]
    assert joined["ate_rmse_m"] == pytest.approx(0.2, abs=1e-6)
    assert [s["ate_rmse_m"] for s in joined["session_odometry"]] == pytest.approx([0.5, 0.5], abs=1e-6)
    assert joined["unjoined_sessions"] == []


@pytest.mark.parametrize(("extra", "message"), [
    (["--trajectory", "t.tum"], "add --pose-truth"),
    (["--session-odometry", "o.tum"], "add --trajectory"),
])
def test_trajectory_options_that_do_not_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str],
                                            message: str) -> None:
    run = _recording(tmp_path)
    assert main(["--recording", str(run), "--gt", str(tmp_path / "gt.npz"), *extra, "--out",
                 str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR:") and message in err
