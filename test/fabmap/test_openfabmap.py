"""openFABMAP YAML files: golden files read with their shapes and types; written files open in OpenCV."""

import numpy as np
import pytest

from aefabmap_ros.errors import ModelError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.openfabmap import (
    read_bow,
    read_chow_liu_tree,
    read_opencv_matrix,
    read_vocabulary,
    write_bow,
    write_chow_liu_tree,
    write_opencv_matrices,
    write_vocabulary,
)

cv2 = pytest.importorskip("cv2")


def _cv2_read(path, node):
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return storage.getNode(node).mat()
    finally:
        storage.release()


def test_golden_files_read(golden_dir):
    for name, node, shape, dtype in [
        ("tree.yml", "ChowLiuTree", (4, 926), np.float64),
        ("bowtrain.yml", "BOWImageDescs", (300, 926), np.float32),
        ("bowtest.yml", "BOWImageDescs", (84, 926), np.float32),
        ("vocab.yml", "Vocabulary", (926, 128), np.float32),
    ]:
        matrix = read_opencv_matrix(golden_dir / name, node)
        assert matrix.shape == shape and matrix.dtype == dtype and np.isfinite(matrix).all()
    tree = read_chow_liu_tree(golden_dir / "tree.yml")
    assert tree.vocabulary_size == 926 and tree.roots.tolist() == [833]
    assert read_vocabulary(golden_dir / "vocab.yml").dtype == np.float32
    assert (read_bow(golden_dir / "bowtest.yml") > 0).sum(axis=1).tolist().count(0) == 2


def test_written_files_round_trip_through_opencv(tmp_path):
    rng = np.random.default_rng(0)
    centres = rng.random((5, 3)).astype(np.float32)
    bow = (rng.random((4, 5)) * (rng.random((4, 5)) < 0.5)).astype(np.float32)
    parent = np.array([0, 0, 1, 1, 0])
    tree = ChowLiuTree(parent, *rng.uniform(0.01, 0.99, size=(3, 5)))
    write_vocabulary(tmp_path / "vocab.yml", centres)
    write_bow(tmp_path / "bow.yml", bow)
    write_chow_liu_tree(tmp_path / "tree.yml", tree)
    np.testing.assert_array_equal(_cv2_read(tmp_path / "vocab.yml", "Vocabulary"), centres)
    np.testing.assert_array_equal(_cv2_read(tmp_path / "bow.yml", "BOWImageDescs"), bow)
    np.testing.assert_array_equal(_cv2_read(tmp_path / "tree.yml", "ChowLiuTree"), tree.to_matrix())
    np.testing.assert_array_equal(read_vocabulary(tmp_path / "vocab.yml"), centres)
    np.testing.assert_array_equal(read_bow(tmp_path / "bow.yml"), bow)
    np.testing.assert_array_equal(read_chow_liu_tree(tmp_path / "tree.yml").to_matrix(), tree.to_matrix())
    special = np.array([[np.nan, np.inf, -np.inf, 1.5]])
    write_opencv_matrices(tmp_path / "special.yml", {"S": special, "I": np.arange(4, dtype=np.int32).reshape(2, 2)})
    np.testing.assert_array_equal(read_opencv_matrix(tmp_path / "special.yml", "S"), special)
    np.testing.assert_array_equal(_cv2_read(tmp_path / "special.yml", "I"), [[0, 1], [2, 3]])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bow.yml", "special.yml", "tree.yml", "vocab.yml"]


def test_errors(tmp_path):
    with pytest.raises(ModelError, match="cannot read openFABMAP file"):
        read_opencv_matrix(tmp_path / "missing.yml", "X")
    (tmp_path / "plain.yml").write_text("hello: 1\n")
    with pytest.raises(ModelError, match="no %YAML header"):
        read_opencv_matrix(tmp_path / "plain.yml", "X")
    write_opencv_matrices(tmp_path / "a.yml", {"A": np.zeros((2, 2))})
    with pytest.raises(ModelError, match="has no matrix node 'ChowLiuTree'"):
        read_chow_liu_tree(tmp_path / "a.yml")
    text = (tmp_path / "a.yml").read_text().replace("rows: 2", "rows: 3")
    (tmp_path / "short.yml").write_text(text)
    with pytest.raises(ModelError, match="node 'A' is a malformed matrix"):
        read_opencv_matrix(tmp_path / "short.yml", "A")
    write_opencv_matrices(tmp_path / "badtree.yml", {"ChowLiuTree": np.zeros((4, 3))})
    with pytest.raises(ModelError, match=r"badtree.yml: .*not a probability"):
        read_chow_liu_tree(tmp_path / "badtree.yml")
    with pytest.raises(ModelError, match="only 2-D"):
        write_opencv_matrices(tmp_path / "b.yml", {"A": np.zeros(3)})
