"""Faults around fabmap_node's map file: kill -9 in the middle of a save, a full disk, a corrupt map.

Each keeps the places saved before the fault: the map on disk is always a whole earlier save (the
writes are atomic), a failed save says so, and a damaged map is refused without being overwritten.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from aefabmap_ros.errors import ModelError  # noqa: E402
from aefabmap_ros.fabmap.chowliu import ChowLiuTree  # noqa: E402
from aefabmap_ros.fabmap.config import FabMapConfig  # noqa: E402
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer  # noqa: E402
from aefabmap_ros.io.atomic import remove_stale_temporaries  # noqa: E402
from aefabmap_ros.model.directory import load_model  # noqa: E402
from aefabmap_ros.nodes.fabmap_node import FabMapNode  # noqa: E402
from test.reliability import Recorder  # noqa: E402
from test.revisit_fixture import RevisitData  # noqa: E402
from test.ros_processes import write_script  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.reliability]

# Saves a map that grows by 2,000 places (240,000 words: saves of several MB) before every save,
# announcing each save; killed from outside.
SAVER = """
import sys
import numpy as np
import scipy.sparse as sp
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.model.directory import load_model

model = load_model(sys.argv[1])
recognizer = PlaceRecognizer(ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples,
                             FabMapConfig(), model.vocabulary_id)
rng = np.random.default_rng(0)
stamp = 1
while True:
    places = sp.csr_matrix(rng.random((2000, model.quantizer.size)) < 0.3)
    recognizer.add_places(places, np.arange(stamp, stamp + 2000, dtype=np.int64))
    stamp += 2000
    print("saving", flush=True)
    recognizer.save_map(sys.argv[2])
    print("saved", recognizer.num_places, flush=True)
"""


def _recognizer(data: RevisitData) -> PlaceRecognizer:
    model = load_model(data.model_dir)
    assert model.tree_matrix is not None
    return PlaceRecognizer(ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples, FabMapConfig(),
                           model.vocabulary_id)


def _words(word_ids: list[int], sec: int, vocabulary_id: str) -> object:
    from aefabmap_msgs.msg import BagOfWords
    from builtin_interfaces.msg import Time

    message = BagOfWords(vocabulary_id=vocabulary_id, vocabulary_size=400, word_ids=word_ids,
                         counts=[1] * len(word_ids))
    message.header.stamp = Time(sec=sec)
    return message


def test_kill_9_in_the_middle_of_saves_keeps_the_last_whole_map(tmp_path: Path, revisit_data: RevisitData,
                                                                 reliability: Recorder) -> None:
    saver = write_script(tmp_path, "saver.py", SAVER)
    map_path = tmp_path / "map.npz"
    kills, whole, lost, mid_save = 5, 0, 0, 0
    for kill in range(kills):
        map_path.unlink(missing_ok=True)
        process = subprocess.Popen([sys.executable, str(saver), str(revisit_data.model_dir), str(map_path)],
                                   stdout=subprocess.PIPE, text=True)
        assert process.stdout is not None
        saved, saving = 0, 0
        for line in process.stdout:  # let it save a few times, then kill it as save number `kill + 2` starts
            if line.startswith("saved"):
                saved = int(line.split()[1])
            elif line.startswith("saving"):
                saving += 1
                if saving == kill + 2:
                    break
        deadline = time.monotonic() + 10  # kill while the temporary is being written, before the rename
        while not list(tmp_path.glob(".map.npz.*.tmp")) and time.monotonic() < deadline:
            pass
        process.send_signal(signal.SIGKILL)
        process.wait()
        process.stdout.close()
        leftovers = remove_stale_temporaries(tmp_path, "map.npz")  # what fabmap_node does at start
        mid_save += bool(leftovers)
        recognizer = _recognizer(revisit_data)
        recognizer.load_map(map_path)  # whole: it loads (a half-written map would raise ModelError)
        whole += 1
        lost += max(0, saved - recognizer.num_places)
        assert recognizer.num_places >= saved
    assert not list(tmp_path.glob(".map.npz.*.tmp"))
    reliability.fault(f"kill -9 during map saves ({mid_save} of {kills} left a half-written temporary)",
                      injected=kills, survived=whole, places_lost=lost)


def _tmpfs_available() -> bool:
    if shutil.which("unshare") is None:
        return False
    with tempfile.TemporaryDirectory() as folder:
        result = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {folder}"],
                                capture_output=True, check=False)
    return result.returncode == 0


# In its own mount namespace: a 40 KiB disk holds the first save of the map; later ones fill it.
FULL_DISK = """
import sys
from test.nodes.test_faults import disk_full_run
disk_full_run(sys.argv[1], sys.argv[2])
"""


def disk_full_run(model_dir: str, folder: str) -> None:
    """Runs inside the small tmpfs: periodic saves that start failing, then the final save; prints results."""
    import rclpy as ros

    ros.init()
    map_path = Path(folder) / "map.npz"
    node = FabMapNode(parameter_overrides=[rclpy.parameter.Parameter("model_dir", value=model_dir),
                                           rclpy.parameter.Parameter("map_file", value=str(map_path)),
                                           rclpy.parameter.Parameter("save_period_s", value=0.0)])
    model_id = node.vocabulary_id
    rng = np.random.default_rng(1)
    saved_places = 0
    sec = 1
    failures = 0
    while failures == 0:
        for _ in range(20):
            node._on_words(_words(sorted(rng.choice(400, 60, replace=False).tolist()), sec, model_id))
            sec += 1
        node.map_saver.mark_changed()
        before = node.map_saver.unsaved_changes
        node.map_saver.save_if_changed()
        if before and node.map_saver.unsaved_changes:
            failures += 1
        else:
            saved_places = node.recognizer.num_places
    final_ok = node.close()
    node.destroy_node()
    ros.try_shutdown()
    print("RESULT", saved_places, node.recognizer.num_places, int(final_ok), flush=True)


@pytest.mark.skipif(not _tmpfs_available(), reason="cannot mount a small tmpfs here (needs unshare -m and mount)")
def test_disk_full_during_saves_keeps_the_last_whole_map(tmp_path: Path, revisit_data: RevisitData,
                                                         reliability: Recorder) -> None:
    folder = tmp_path / "disk"
    folder.mkdir()
    script = write_script(tmp_path, "full_disk.py", FULL_DISK)
    repo = Path(__file__).resolve().parents[2]
    command = (f"mount -t tmpfs -o size=40k tmpfs {folder} && cd {repo} && PYTHONPATH={repo} "
               f"{sys.executable} {script} {revisit_data.model_dir} {folder} && cp {folder}/map.npz {tmp_path}/")
    result = subprocess.run(["unshare", "-m", "sh", "-c", command], capture_output=True, text=True, check=False,
                            timeout=240)
    assert result.returncode == 0, result.stderr[-3000:]
    line = next(line for line in result.stdout.splitlines() if line.startswith("RESULT"))
    saved_places, total_places, final_ok = (int(value) for value in line.split()[1:])
    assert saved_places > 0 and total_places > saved_places and final_ok == 0  # the final save failed, and said so
    assert "FINAL SAVE FAILED" in result.stderr
    recognizer = _recognizer(revisit_data)
    recognizer.load_map(tmp_path / "map.npz")  # the last whole save survived the full disk
    assert recognizer.num_places == saved_places
    reliability.fault("disk full during a periodic and the final save", injected=2, survived=2,
                      places_lost=max(0, saved_places - recognizer.num_places))


def test_a_corrupt_map_is_refused_and_left_untouched(tmp_path: Path, revisit_data: RevisitData,
                                                     reliability: Recorder) -> None:
    rclpy.init()
    try:
        map_path = tmp_path / "map.npz"
        parameters = [rclpy.parameter.Parameter("model_dir", value=str(revisit_data.model_dir)),
                      rclpy.parameter.Parameter("map_file", value=str(map_path))]
        node = FabMapNode(parameter_overrides=parameters)
        node._on_words(_words([1, 5, 9], 10, revisit_data.vocabulary_id))
        assert node.close()
        node.destroy_node()
        damaged = map_path.read_bytes()[: map_path.stat().st_size // 2]  # a torn copy, say
        map_path.write_bytes(damaged)
        with pytest.raises(ModelError, match="map"):
            FabMapNode(parameter_overrides=parameters)
        assert map_path.read_bytes() == damaged  # refused, not overwritten by an empty map
    finally:
        rclpy.try_shutdown()
    reliability.fault("corrupt map file at start (fabmap)", injected=1, survived=1, places_lost=0)
