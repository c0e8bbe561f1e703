"""aefabmap_demo's two-session part: the single-session run's figure on the same frames, which closure joined the
sessions, and the figures printed against their targets (the run itself is ./scripts/demo.sh's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.cli.demo_sessions import (
    SessionRun,
    _first_cross_session,
    _joined_at,
    print_targets,
    single_session_recall,
)
from test.cli.test_evaluate import frame_stamp, save_gt, write_recording


def _gt() -> np.ndarray:
    gt = np.zeros((40, 40), np.uint8)
    for k in range(4):
        gt[20 + k, k] = 1  # the second half's frames 20-23 revisit the first half's 0-3
    gt[39, 25] = 1  # within the second half
    gt[35, 3] = gt[35, 24] = 1  # a frame revisiting both halves
    return gt


def test_single_session_recall_on_the_second_halfs_frames(tmp_path: Path) -> None:
    save_gt(tmp_path / "loop_gt.npz", _gt())
    closures = [(20, 0, 0.99, 40), (21, 1, 0.99, 40), (22, 8, 0.99, 40), (35, 24, 0.99, 40), (39, 25, 0.99, 40)]
    write_recording(tmp_path / "run", [(i, [], []) for i in range(40)], {"/loop_closures": closures})
    # Of the 5 frames revisiting the first half (20-23, 35), 20 and 21 closed into it; 22's closure is false;
    # 35's is true but into the second half; 39 revisits the second half only.
    assert single_session_recall(tmp_path / "run", tmp_path, cut_frame=20, min_gap=10) == (2, 5)


def test_the_first_cross_session_closure_and_whether_it_joined(tmp_path: Path) -> None:
    a, b = ("", 0), ("", 1)
    run = SessionRun("b", [(25, 22, True), (30, 3, True), (31, 4, True)], [(b, b), (b, a), (b, a)], "")
    stamps = np.array([frame_stamp(i) for i in range(40)])
    first = _first_cross_session(run, stamps)
    assert first is not None and first[:2] == (30, 3)
    trajectory = tmp_path / "keyframes.tum"
    trajectory.write_text(f"{frame_stamp(30) / 1e9:.9f} 0 0 0 0 0 0 1\n")
    assert _joined_at(trajectory, first[2]) and not _joined_at(trajectory, frame_stamp(31) / 1e9)
    assert not _joined_at(tmp_path / "missing.tum", first[2])
    assert _first_cross_session(SessionRun("b", [(25, 22, True)], [(b, b)], ""), stamps) is None


def test_the_figures_against_their_targets(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, b = ("", 0), ("", 1)
    stamps = np.array([frame_stamp(i) for i in range(40)])
    (tmp_path / "backend").mkdir()
    (tmp_path / "backend" / "keyframes.tum").write_text(f"{frame_stamp(30) / 1e9:.9f} 0 0 0 0 0 0 1\n")
    pair = {"query_session": 1, "matched_session": 0, "revisiting_frames": 4, "revisiting_frames_closed": 3,
            "wrong_poses": 0, "poses_checked": 3, "false_closures": 0}
    payload = {"session_pairs": {"pairs": [pair]},
               "joined_trajectory": {"ate_rmse_m": 0.2, "odometry_pooled_ate_rmse_m": 1.0, "joined_over_odometry": 0.2}}
    runs = [SessionRun("a", [], [], ""),
            SessionRun("b", [(30, 3, True)], [(b, a)], "[pose_graph_node]: pose_graph_node: 9 keyframes; added=3")]
    print_targets(payload, (4, 4), runs, stamps, tmp_path)
    printed = capsys.readouterr().out
    assert "3/4 (75.0 %): 75.0 % of the single-session figure (target >= 90 %)" in printed
    assert "0 of 3 checked (target 0)" in printed
    assert "frame 30 -> frame 3: session B joined to A there" in printed
    assert "0.200 m against the sessions' odometry 1.000 m (each aligned on its own): 20.0 % (target <= 15 %)" \
        in printed
    assert "backend after session B: 9 keyframes; added=3" in printed
