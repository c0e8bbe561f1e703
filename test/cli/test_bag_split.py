"""aefabmap_bag split / merge: a small RGB-D bag with odometry cut into two sessions, B's odometry restarted at the
identity; the ground truth cut to match; bad input is one ERROR line and leaves nothing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.cli.bag import main
from aefabmap_ros.io import bags

START = 1_700_000_000_000_000_000
PERIOD = 100_000_000
FRAMES = 12
TOPICS = ("/image", "/depth", "/camera_info", "/odom")


def _poses(count: int) -> np.ndarray:
    """Odometry T_odom_camera: a curving, climbing path with turns about every axis (not starting at identity)."""
    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i in range(count):
        poses[i, :3, :3] = Rotation.from_rotvec([0.1 * i, 0.3 + 0.2 * i, -0.05 * i]).as_matrix()
        poses[i, :3, 3] = [5.0 + np.cos(0.4 * i) * 3, 2.0 + 0.5 * i, 1.0 + rng.normal(0, 0.1)]
    return poses


def _sequence(root: Path, odometry: bool = True) -> Path:
    """A sequence folder as aefabmap_synth writes one: bag/, loop_gt.npz (gt, stamps_ns), groundtruth.tum."""
    folder = root / "seq"
    folder.mkdir()
    rng = np.random.default_rng(0)
    stamps = [START + i * PERIOD for i in range(FRAMES)]
    frames = [(stamp, rng.integers(0, 255, (12, 16), dtype=np.uint8), np.full((12, 16), 1000 + i, np.uint16))
              for i, stamp in enumerate(stamps)]
    camera = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    bags.write_rgbd_bag(folder / "bag", "/image", frames, camera, odometry=_poses(FRAMES) if odometry else None)
    gt = np.zeros((FRAMES, FRAMES), np.uint8)
    gt[8, 1] = gt[9, 2] = gt[10, 9] = 1
    np.savez(folder / "loop_gt.npz", gt=gt, stamps_ns=np.array(stamps, dtype=np.int64))
    (folder / "groundtruth.tum").write_text("# t x y z qx qy qz qw\n" + "".join(
        f"{stamp // 10**9}.{stamp % 10**9:09d} {i} 0 0 0 0 0 1\n" for i, stamp in enumerate(stamps)))
    return folder


def _odometry(bag: Path) -> list[tuple[int, np.ndarray]]:
    from aefabmap_ros.cli.bag_split import odometry_matrix

    return [(m.stamp_ns, odometry_matrix(m.message)) for m in bags.read_messages(bag, ["/odom"])]


def test_split_at_half_restarts_session_b_odometry(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sequence = _sequence(tmp_path)
    out = tmp_path / "cut"
    assert main(["split", str(sequence), "--at", "0.5", "--restart-odometry", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "session B's odometry (/odom) restarted at the identity" in printed
    # The span is 1.1 s: the cut at 0.55 s puts frames 0-5 in A, 6-11 in B.
    cut = START + 550_000_000
    counts = {}
    for name, frames in (("a", range(0, 6)), ("b", range(6, 12))):
        for topic in TOPICS:
            stamps = [m.stamp_ns for m in bags.read_messages(out / name / "bag", [topic])]
            assert stamps == [START + i * PERIOD for i in frames]
            assert all((stamp < cut) == (name == "a") for stamp in stamps)
            counts[(name, topic)] = len(stamps)
    assert all(counts[("a", t)] + counts[("b", t)] == FRAMES for t in TOPICS)
    original = _odometry(sequence / "bag")
    first, second = _odometry(out / "a" / "bag"), _odometry(out / "b" / "bag")
    for (_, pose), (_, kept) in zip(original[:6], first, strict=True):
        np.testing.assert_allclose(kept, pose, atol=1e-9)  # session A unchanged
    np.testing.assert_allclose(second[0][1], np.eye(4), atol=1e-9)
    for i in range(6):
        for j in range(6):
            before = np.linalg.inv(original[6 + i][1]) @ original[6 + j][1]
            after = np.linalg.inv(second[i][1]) @ second[j][1]
            np.testing.assert_allclose(after, before, atol=1e-9)
    # The ground truth cut to match: rows and columns by stamps_ns; B's gt keeps its own revisit (10 -> 9).
    for name, part in (("a", slice(0, 6)), ("b", slice(6, 12))):
        with np.load(out / name / "loop_gt.npz") as cut_gt, np.load(sequence / "loop_gt.npz") as full:
            np.testing.assert_array_equal(cut_gt["gt"], full["gt"][part, part])
            np.testing.assert_array_equal(cut_gt["stamps_ns"], full["stamps_ns"][part])
    assert [line.split()[1] for line in (out / "b" / "groundtruth.tum").read_text().splitlines()] == \
        [str(i) for i in range(6, 12)]
    tum = [line.split() for line in (out / "b" / "odometry.tum").read_text().splitlines()]
    assert len(tum) == 6 and [float(v) for v in tum[0][1:]] == [0, 0, 0, 0, 0, 0, 1]
    summary = json.loads((out / "split.json").read_text())
    assert summary["cut_ns"] == cut and summary["messages"]["b"]["/odom"] == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut", "seq"]  # no staging folder left


def test_split_at_a_stamp_without_restart_keeps_odometry(tmp_path: Path) -> None:
    sequence = _sequence(tmp_path)
    out = tmp_path / "cut"
    assert main(["split", str(sequence / "bag"), "--at-stamp", "1700000000.3", "--out", str(out)]) == 0
    assert [m.stamp_ns for m in bags.read_messages(out / "a" / "bag", ["/image"])] == \
        [START + i * PERIOD for i in range(3)]
    np.testing.assert_allclose(_odometry(out / "b" / "bag")[0][1], _odometry(sequence / "bag")[3][1], atol=1e-9)
    assert not (out / "a" / "loop_gt.npz").exists()  # a bare bag: no ground truth given


def test_merge_puts_recordings_back_together(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sequence = _sequence(tmp_path)
    cut = tmp_path / "cut"
    assert main(["split", str(sequence), "--at", "0.5", "--out", str(cut)]) == 0
    assert main(["merge", str(cut / "b" / "bag"), str(cut / "a" / "bag"), "--out", str(tmp_path / "both")]) == 0
    assert f"{4 * FRAMES} messages of 2 bags on 4 topics" in capsys.readouterr().out
    assert [m.stamp_ns for m in bags.read_messages(tmp_path / "both", ["/image"])] == \
        [START + i * PERIOD for i in range(FRAMES)]


@pytest.mark.parametrize(("arguments", "message"), [
    (["split", "{root}/nowhere", "--at", "0.5"], "bag does not exist"),
    (["split", "{seq}", "--at", "1.5"], "--at must be a fraction between 0 and 1"),
    (["split", "{seq}", "--at-stamp", "1600000000"], "leaves one session empty"),
    (["split", "{seq}", "--at-stamp", "1700000009"], "leaves one session empty"),
    (["split", "{seq}", "--at-stamp", "soon"], "--at-stamp must be a number of seconds"),
    (["split", "{seq}"], "one of the arguments --at --at-stamp is required"),
    (["split", "{seq}", "--at", "0.5", "--gt", "{root}/missing.npz"], "missing.npz"),
])
def test_bad_input_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: list[str],
                                     message: str) -> None:
    sequence = _sequence(tmp_path)
    argv = [a.format(root=tmp_path, seq=sequence) for a in arguments] + ["--out", str(tmp_path / "cut")]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR:") and message in err and len(err.strip().splitlines()) <= 2  # + usage line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_restart_needs_an_odometry_topic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sequence = _sequence(tmp_path, odometry=False)
    assert main(["split", str(sequence), "--at", "0.5", "--restart-odometry", "--out", str(tmp_path / "cut")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR:") and "no nav_msgs/msg/Odometry topic" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "cut").exists()


def test_an_existing_output_is_kept_unless_overwritten(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sequence = _sequence(tmp_path)
    (tmp_path / "cut").mkdir()
    assert main(["split", str(sequence), "--at", "0.5", "--out", str(tmp_path / "cut")]) == 1
    assert "already exists" in capsys.readouterr().err
    assert main(["split", str(sequence), "--at", "0.5", "--out", str(tmp_path / "cut"), "--overwrite"]) == 0
    assert (tmp_path / "cut" / "b" / "bag").is_dir()
