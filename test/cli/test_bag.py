"""aefabmap_bag: image folders become bags with the stamps the user states; bad input is one ERROR line."""

import cv2
import numpy as np
import pytest

from aefabmap_ros.cli.bag import main
from aefabmap_ros.io import bags


def _folder(root, names, shape=(24, 32)):
    folder = root / "images"
    folder.mkdir()
    for index, name in enumerate(names):
        cv2.imwrite(str(folder / name), np.full(shape, 10 * index, np.uint8))
    return folder


def _read(bag):
    return [(m.stamp_ns, m.message.encoding, m.message.data[0]) for m in bags.read_messages(bag, ["/image"])]


def test_rate_stamps_in_natural_order(tmp_path, capsys):
    folder = _folder(tmp_path, ["1.jpg", "2.jpg", "10.jpg"][::-1])  # written 10, 2, 1; sorted 1, 2, 10
    assert main(["--images", str(folder), "--rate", "2", "--start", "5", "--out", str(tmp_path / "bag")]) == 0
    frames = _read(tmp_path / "bag")
    assert [f[0] for f in frames] == [5_000_000_000, 5_500_000_000, 6_000_000_000]
    assert [f[1] for f in frames] == ["mono8"] * 3 and [f[2] for f in frames] == [20, 10, 0]
    assert "3 images on /image, 1.00 s of stamps" in capsys.readouterr().out


def test_tum_names_and_times_file_and_color(tmp_path):
    folder = _folder(tmp_path, ["1305031102.160407.png", "1305031102.194330.png"])
    assert main(["--images", str(folder), "--out", str(tmp_path / "tum"), "--color"]) == 0
    assert [(f[0], f[1]) for f in _read(tmp_path / "tum")] == [(1305031102160407000, "bgr8"),
                                                                (1305031102194330000, "bgr8")]
    times = tmp_path / "times.txt"
    times.write_text("0.0\n0.1\n")
    assert main(["--images", str(folder), "--times", str(times), "--out", str(tmp_path / "kitti")]) == 0
    assert [f[0] for f in _read(tmp_path / "kitti")] == [0, 100_000_000]


@pytest.mark.parametrize(("extra", "message"), [
    (["--rate", "0"], "--rate must be a positive frame rate"),
    ([], "cannot read a stamp from file name 0.png"),
    (["--times", "missing.txt"], "missing.txt"),
    (["--rate", "1", "--times", "t.txt"], "not allowed with argument"),
])
def test_errors(tmp_path, capsys, extra, message):
    folder = _folder(tmp_path, ["0.png", "1.png"])
    assert main(["--images", str(folder), "--out", str(tmp_path / "bag"), *extra]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR:") and message in err
    assert not (tmp_path / "bag").exists()


def test_stamps_must_increase(tmp_path, capsys):
    folder = _folder(tmp_path, ["0.png", "1.png"])
    times = tmp_path / "times.txt"
    times.write_text("1.0\n0.5\n")
    assert main(["--images", str(folder), "--times", str(times), "--out", str(tmp_path / "bag")]) == 1
    assert "increase strictly" in capsys.readouterr().err
