"""What runs on the robot imports no training library: each node, started on a model directory of every
vocabulary kind in a fresh interpreter, leaves torch, faiss, scikit-learn and pandas out of ``sys.modules``
(docs/runtime.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse

from aefabmap_ros.features.extraction import FeatureConfig
from aefabmap_ros.model.directory import Model, save_model
from aefabmap_ros.vocabulary.base import Quantizer, VocabularyConfig, train_vocabulary

TRAINING_LIBRARIES = ("torch", "faiss", "sklearn", "pandas")
# The robot's front end (feature and quantizer nodes) needs no compiled FAB-MAP kernels either: numba costs about
# 50 MiB in a process that imports it.
WATCHED = (*TRAINING_LIBRARIES, "numba")
FRONT_END = ("feature_node", "quantizer_node")
V = 12
# node module -> the parameters it is started with ("{model}": the model directory)
NODES = {
    "feature_node": {"model_dir": "{model}"},
    "quantizer_node": {"model_dir": "{model}"},
    "fabmap_node": {"model_dir": "{model}"},
    "verifier_node": {},
    "pose_graph_node": {},
}
# Starts the node on each model directory given (argv[3:]), quantizes with quantizer_node, prints the
# training libraries then in sys.modules.
PROBE = """
import importlib, json, sys
import numpy as np
import rclpy
from rclpy.parameter import Parameter
module = importlib.import_module("aefabmap_ros.nodes." + sys.argv[1])
node_class = next(value for name, value in vars(module).items()
                  if name.endswith("Node") and getattr(value, "__module__", "") == module.__name__)
rclpy.init()
for model in sys.argv[3:]:
    parameters = {name: value.replace("{model}", model) for name, value in json.loads(sys.argv[2]).items()}
    node = node_class(parameter_overrides=[Parameter(name, value=value) for name, value in parameters.items()])
    if hasattr(node, "quantizer"):
        words = node.quantizer.quantize(np.random.default_rng(0).uniform(0, 100, (500, 128)).astype(np.float32))
        assert words.shape == (500,)
    node.destroy_node()
rclpy.shutdown()
print("loaded:" + ",".join(name for name in TRAINING if name in sys.modules))
""".replace("TRAINING", repr(WATCHED))


def _descriptors(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 100, (V, 128))
    return np.maximum(centres[rng.integers(0, V, 1200)] + rng.normal(0, 4, (1200, 128)), 0).astype(np.float32)


def _save(quantizer: Quantizer, config: VocabularyConfig, directory: Path) -> Path:
    tree = np.vstack([np.arange(V) - 1.0, np.full((3, V), 0.2)])
    tree[0, 0] = 0
    samples = scipy.sparse.csr_matrix(np.random.default_rng(0).integers(0, 2, (5, V)))
    save_model(directory, Model.create(FeatureConfig(), config, quantizer, tree_matrix=tree,
                                       new_place_samples=samples))
    return directory


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """A model directory of each vocabulary kind and autoencoder: k-means, the MLP autoencoder, the paper's
    convolutional network quantizing, and the network with an MLP encoder distilled from it."""
    root = tmp_path_factory.mktemp("runtime_models")
    common = dict(size=V, pca_dim=8, ae_embedding_dim=4, ae_epochs=1, num_threads=1)
    configs = {
        "kmeans": VocabularyConfig(kind="kmeans", size=V),
        "mlp": VocabularyConfig(**common, ae_mlp_hidden=16),  # type: ignore[arg-type]
        "conv": VocabularyConfig(**common, ae_network="conv", ae_student_hidden=0),  # type: ignore[arg-type]
        "conv_student": VocabularyConfig(**common, ae_network="conv", ae_student_hidden=8,  # type: ignore[arg-type]
                                         ae_student_epochs=1, ae_student_noise_rows=0),
    }
    return [_save(train_vocabulary(_descriptors(), config, progress=False), config, root / name)
            for name, config in configs.items()]


def _loaded_after(node: str, parameters: dict[str, str], models: list[Path]) -> list[str]:
    """The training libraries in sys.modules once ``node`` was started on each of ``models``."""
    result = subprocess.run([sys.executable, "-c", PROBE, node, json.dumps(parameters), *map(str, models)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    line = result.stdout.strip().splitlines()[-1]
    assert line.startswith("loaded:"), result.stdout
    return [name for name in line.removeprefix("loaded:").split(",") if name]


@pytest.mark.ros
@pytest.mark.parametrize("node", sorted(NODES))
def test_a_node_started_on_every_kind_of_model_loads_no_training_library(node: str, models: list[Path]) -> None:
    pytest.importorskip("aefabmap_msgs.msg")
    loaded = _loaded_after(node, NODES[node], models)
    assert [name for name in loaded if name in TRAINING_LIBRARIES] == []
    if node in FRONT_END:
        assert "numba" not in loaded


@pytest.mark.ros
def test_the_probe_sees_a_training_library_that_a_node_loads(models: list[Path], tmp_path: Path) -> None:
    """The same probe on a quantizer_node that loads a folder whose network is still in torch's format (read by
    torch, converted in memory): torch is in sys.modules, so the check above can fail."""
    pytest.importorskip("aefabmap_msgs.msg")
    from test.model.test_convert import as_torch_folder

    old = as_torch_folder(models[2], tmp_path / "old")
    assert _loaded_after("quantizer_node", NODES["quantizer_node"], [old]) == ["torch"]
