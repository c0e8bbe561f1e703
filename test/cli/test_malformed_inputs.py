"""Every offline tool, given corrupt, truncated or mismatched inputs, prints one ``ERROR: ...`` line and exits 1.

Inputs: bags (mcap and sqlite3) corrupt, truncated, without the topic, not a bag; model folders with a file
missing, corrupt, or a Chow-Liu tree from another vocabulary (its checksum made to agree); ground-truth,
pose and times files with NaN, the wrong columns, stamps going back. Each tool's ``main`` is called as its
console script calls it: an exception escaping it is the traceback a user would see.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.io.bags import write_image_bag
from test.reliability import Recorder
from test.revisit_fixture import RevisitData

pytestmark = pytest.mark.reliability

RNG = np.random.default_rng(7)


@dataclass(frozen=True)
class Inputs:
    root: Path
    model: Path
    mcap_bag: Path
    sqlite_bag: Path


def _copy(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    return target


def _storage_file(bag: Path) -> Path:
    (path,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    return path


def _garbage(path: Path) -> None:
    path.write_bytes(RNG.integers(0, 256, 4096, np.uint8).tobytes())


def _truncate(path: Path, fraction: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


@pytest.fixture(scope="module")
def inputs(revisit_data: RevisitData, tmp_path_factory: pytest.TempPathFactory) -> Inputs:
    root = tmp_path_factory.mktemp("malformed")
    frames = [(stamp, RNG.integers(0, 256, (48, 64), np.uint8)) for stamp in range(1, 6)]
    write_image_bag(root / "sqlite", "/image", [(int(s) * 10**9, image) for s, image in frames], storage="sqlite3")
    return Inputs(root, revisit_data.model_dir, revisit_data.first_pass_bag, root / "sqlite")


# ------------------------------------------------------------------------------------ broken bags


def _bag_broken(inputs: Inputs, tmp: Path, how: str) -> Path:
    source = inputs.sqlite_bag if how.startswith("sqlite") else inputs.mcap_bag
    bag = _copy(source, tmp / "bag")
    if how.endswith("garbage"):
        _garbage(_storage_file(bag))
    elif how.endswith("truncated"):
        _truncate(_storage_file(bag))
    elif how == "metadata garbage":
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    elif how == "no metadata":
        (bag / "metadata.yaml").unlink()
    elif how == "empty folder":
        shutil.rmtree(bag)
        bag.mkdir()
    return bag


BAG_FAULTS = ["mcap garbage", "mcap truncated", "sqlite garbage", "sqlite truncated", "metadata garbage",
              "no metadata", "empty folder", "topic missing"]


def _bag_argv(tool: str, bag: Path, topic: str, inputs: Inputs, tmp: Path) -> list[str]:
    if tool == "train":
        return ["--bag", str(bag), "--topic", topic, "--vocabulary", "kmeans", "--size", "8", "--out",
                str(tmp / "model")]
    if tool == "evaluate":
        (tmp / "gt.npz").write_bytes(b"")
        np.savez(tmp / "gt.npz", gt=np.zeros((16, 16), np.uint8))
        return ["--bag", str(bag), "--topic", topic, "--gt", str(tmp / "gt.npz"), "--model", str(inputs.model),
                "--out", str(tmp / "eval"), "--quiet"]
    if tool == "words":
        return ["--model", str(inputs.model), "--bag", str(bag), "--topic", topic, "--quiet"]
    return [str(bag), "--topic", topic, "--quiet", "--wait-timeout", "0.1"]  # replay: fails before it publishes


@pytest.mark.parametrize("fault", BAG_FAULTS)
@pytest.mark.parametrize("tool", ["train", "evaluate", "replay", "words"])
def test_a_broken_bag_is_one_error_line(tool: str, fault: str, inputs: Inputs, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str], reliability: Recorder) -> None:
    bag = inputs.mcap_bag if fault == "topic missing" else _bag_broken(inputs, tmp_path, fault)
    topic = "/no_such_topic" if fault == "topic missing" else "/image"
    _assert_refused(tool, _bag_argv(tool, bag, topic, inputs, tmp_path), capsys, reliability, f"bag: {fault}")


# ------------------------------------------------------------------------------------ broken models


def _rehash(model: Path, name: str) -> None:
    """Make metadata.json's checksum of ``name`` agree with the file: only the content check can catch it."""
    metadata = json.loads((model / "metadata.json").read_text())
    metadata["files"][name] = hashlib.sha256((model / name).read_bytes()).hexdigest()
    (model / "metadata.json").write_text(json.dumps(metadata))


def _model_broken(inputs: Inputs, tmp: Path, how: str) -> Path:
    model = _copy(inputs.model, tmp / "model")
    if how == "metadata missing":
        (model / "metadata.json").unlink()
    elif how == "metadata not JSON":
        (model / "metadata.json").write_text("{ not json")
    elif how == "metadata wrong types":
        metadata = json.loads((model / "metadata.json").read_text())
        metadata["vocabulary"] = "kmeans"
        (model / "metadata.json").write_text(json.dumps(metadata))
    elif how == "vocabulary missing":
        (model / "vocabulary.npz").unlink()
    elif how == "vocabulary garbage":
        _garbage(model / "vocabulary.npz")
    elif how == "vocabulary garbage, checksum agreeing":
        _garbage(model / "vocabulary.npz")
        _rehash(model, "vocabulary.npz")
    elif how == "tree of another vocabulary, checksum agreeing":
        tree = np.load(model / "chow_liu_tree.npy")
        np.save(model / "chow_liu_tree.npy", tree[:, : tree.shape[1] // 2])
        _rehash(model, "chow_liu_tree.npy")
    elif how == "tree with NaN, checksum agreeing":
        tree = np.load(model / "chow_liu_tree.npy")
        tree[2, 3] = np.nan
        np.save(model / "chow_liu_tree.npy", tree)
        _rehash(model, "chow_liu_tree.npy")
    elif how == "new-place samples truncated, checksum agreeing":
        _truncate(model / "new_place_samples.npz")
        _rehash(model, "new_place_samples.npz")
    return model


MODEL_FAULTS = ["metadata missing", "metadata not JSON", "metadata wrong types", "vocabulary missing",
                "vocabulary garbage", "vocabulary garbage, checksum agreeing",
                "tree of another vocabulary, checksum agreeing", "tree with NaN, checksum agreeing",
                "new-place samples truncated, checksum agreeing"]


# aefabmap_launch checks the model's files before it starts a node; what only loading finds (contents whose
# checksums agree) each node refuses at its start-up, and the loader meets those through aefabmap_eval.
CASES = [(tool, fault) for tool in ("evaluate", "words") for fault in MODEL_FAULTS] + [
    ("launch", fault) for fault in MODEL_FAULTS if "checksum agreeing" not in fault]


@pytest.mark.parametrize(("tool", "fault"), CASES)
def test_a_broken_model_is_one_error_line(tool: str, fault: str, inputs: Inputs, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str], reliability: Recorder) -> None:
    model = _model_broken(inputs, tmp_path, fault)
    if tool == "launch":  # refused before a node starts
        argv = ["--model", str(model), "--map", str(tmp_path / "map.npz")]
    elif tool == "words":
        argv = ["--model", str(model), "--bag", str(inputs.mcap_bag), "--topic", "/image", "--quiet"]
    else:
        np.savez(tmp_path / "gt.npz", gt=np.zeros((16, 16), np.uint8))
        argv = ["--bag", str(inputs.mcap_bag), "--topic", "/image", "--gt", str(tmp_path / "gt.npz"), "--model",
                str(model), "--out", str(tmp_path / "eval"), "--quiet"]
    _assert_refused(tool, argv, capsys, reliability, f"model: {fault}")


# ------------------------------------------------------------------------ broken ground truth files

TUM_LINE = "{t} 1.0 2.0 0.5 0.0 0.0 0.0 1.0\n"


def _tum(path: Path, how: str) -> Path:
    lines = [TUM_LINE.format(t=float(t)) for t in range(10)]
    if how == "NaN":
        lines[4] = "4.0 nan 2.0 0.5 0.0 0.0 0.0 1.0\n"
    elif how == "wrong columns":
        lines[4] = "4.0 1.0 2.0 0.5\n"
    elif how == "stamps going back":
        lines[4], lines[6] = lines[6], lines[4]
    elif how == "not numbers":
        lines[4] = "four 1.0 2.0 0.5 0.0 0.0 0.0 1.0\n"
    elif how == "empty":
        lines = []
    path.write_text("".join(lines))
    return path


GT_FAULTS = ["NaN", "wrong columns", "stamps going back", "not numbers", "empty"]


@pytest.mark.parametrize("fault", GT_FAULTS)
def test_ate_refuses_a_broken_trajectory(fault: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         reliability: Recorder) -> None:
    good = _tum(tmp_path / "good.tum", "")
    bad = _tum(tmp_path / "bad.tum", fault)
    for argv in (["--reference", str(bad), "--estimate", f"run={good}"],
                 ["--reference", str(good), "--estimate", f"run={bad}"]):
        _assert_refused("ate", argv, capsys, reliability, f"trajectory: {fault}")


def _kitti_poses(path: Path, how: str, count: int) -> Path:
    rows = np.tile(np.hstack([np.eye(3), np.zeros((3, 1))]).reshape(1, 12), (count, 1))
    rows[:, 3] = np.arange(count)
    text = [" ".join(f"{v:.6e}" for v in row) for row in rows]
    if how == "NaN":
        text[2] = text[2].replace("0.000000e+00", "nan", 1)
    elif how == "wrong columns":
        text[2] = " ".join(text[2].split()[:7])
    elif how == "not numbers":
        text[2] = text[2].replace("0.000000e+00", "zero", 1)
    elif how == "empty":
        text = []
    path.write_text("\n".join(text) + "\n")
    return path


def _times(path: Path, how: str, count: int) -> Path:
    stamps = [f"{0.5 * i:.6f}" for i in range(count)]
    if how == "stamps going back":
        stamps[3], stamps[5] = stamps[5], stamps[3]
    elif how == "NaN":
        stamps[3] = "nan"
    path.write_text("\n".join(stamps) + "\n")
    return path


@pytest.mark.parametrize("fault", GT_FAULTS)
def test_gt_and_evaluate_refuse_broken_poses_and_times(fault: str, inputs: Inputs, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str],
                                                       reliability: Recorder) -> None:
    import cv2

    count = 6
    (tmp_path / "depth").mkdir()
    for index in range(count):
        cv2.imwrite(str(tmp_path / "depth" / f"{index:06d}.png"), np.full((24, 32), 1500, np.uint16))
    poses = _kitti_poses(tmp_path / "poses.txt", fault if fault != "stamps going back" else "", count)
    times = _times(tmp_path / "times.txt", fault if fault in ("stamps going back", "NaN") else "", count)
    _assert_refused("gt", ["--depth", str(tmp_path / "depth"), "--poses", str(poses), "--times", str(times),
                           "--intrinsics", "20", "20", "15.5", "11.5", "--out", str(tmp_path / "gt.npz")],
                    capsys, reliability, f"poses/times: {fault}")
    if fault != "stamps going back":  # evaluate's KITTI poses are per frame, without stamps
        poses16 = _kitti_poses(tmp_path / "poses16.txt", fault, 16)
        _assert_refused("evaluate", ["--bag", str(inputs.mcap_bag), "--topic", "/image", "--poses", str(poses16),
                                     "--model", str(inputs.model), "--out", str(tmp_path / "eval"), "--quiet"],
                        capsys, reliability, f"poses: {fault}")


@pytest.mark.parametrize("fault", ["missing key", "not square", "NaN", "not npz", "other size"])
def test_evaluate_refuses_a_broken_loop_matrix(fault: str, inputs: Inputs, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str], reliability: Recorder) -> None:
    path = tmp_path / "gt.npz"
    if fault == "missing key":
        np.savez(path, loops=np.zeros((16, 16), np.uint8))
    elif fault == "not square":
        np.savez(path, gt=np.zeros((16, 15), np.uint8))
    elif fault == "NaN":
        np.savez(path, gt=np.full((16, 16), np.nan))
    elif fault == "not npz":
        path.write_bytes(b"PK\x03\x04 not really a zip")
    elif fault == "other size":
        np.savez(path, gt=np.zeros((40, 40), np.uint8))
    _assert_refused("evaluate", ["--bag", str(inputs.mcap_bag), "--topic", "/image", "--gt", str(path), "--model",
                                 str(inputs.model), "--out", str(tmp_path / "eval"), "--quiet"],
                    capsys, reliability, f"loop matrix: {fault}")


# --------------------------------------------------------------------------------------- the check

TOOLS: dict[str, str] = {"train": "aefabmap_ros.cli.train", "evaluate": "aefabmap_ros.cli.evaluate",
                         "replay": "aefabmap_ros.cli.replay", "gt": "aefabmap_ros.cli.gt",
                         "ate": "aefabmap_ros.cli.ate", "launch": "aefabmap_ros.cli.launch",
                         "words": "aefabmap_ros.cli.words"}


def _main(tool: str) -> Callable[[list[str]], int]:
    main: Callable[[list[str]], int] = importlib.import_module(TOOLS[tool]).main
    return main


def _assert_refused(tool: str, argv: list[str], capsys: pytest.CaptureFixture[str], reliability: Recorder,
                    what: str) -> None:
    capsys.readouterr()
    code = _main(tool)(argv)  # an exception here is a traceback for the user: the test fails with it
    error = capsys.readouterr().err
    reliability.bad_inputs(f"aefabmap_{tool}", tried=1, survived=int(code == 1 and "ERROR: " in error))
    assert code == 1, f"aefabmap_{tool} {what}: exit {code}\n{error}"
    assert "Traceback" not in error and error.lstrip().startswith("ERROR: "), f"aefabmap_{tool} {what}:\n{error}"
