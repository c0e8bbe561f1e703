"""Model folders whose convolutional network is in torch's format (written before the weights were stored as
arrays): loaded by converting on load where torch is, refused with the command that converts them where it is
not, and converted in place, atomically, with the vocabulary id unchanged (model/convert.py, cli/model.py)."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from aefabmap_ros.cli.model import main as model_main
from aefabmap_ros.errors import ModelError
from aefabmap_ros.features.extraction import FeatureConfig
from aefabmap_ros.model import directory
from aefabmap_ros.model.convert import convert_model, needs_conversion
from aefabmap_ros.model.directory import METADATA, Model, load_model, save_model
from aefabmap_ros.vocabulary.autoencoder import AUTOENCODER, NETWORK_FILE, AutoencoderQuantizer
from aefabmap_ros.vocabulary.autoencoder_network import ConvAutoencoder
from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary
from aefabmap_ros.vocabulary.conv_encoder import ConvEncoder

V = 6


def as_torch_folder(source: Path, target: Path) -> Path:
    """A copy of model folder ``source`` as earlier versions wrote it: the network's state_dict saved by torch
    in ``AUTOENCODER``, no ``NETWORK_FILE``, the checksums listed accordingly."""
    shutil.copytree(source, target)
    network = ConvAutoencoder.from_numpy(ConvEncoder.from_arrays(dict(np.load(target / NETWORK_FILE))))
    torch.save(network.state_dict(), target / AUTOENCODER)  # as the torch module trained it
    (target / NETWORK_FILE).unlink()
    metadata = json.loads((target / METADATA).read_text())
    del metadata["files"][NETWORK_FILE]
    metadata["files"][AUTOENCODER] = hashlib.sha256((target / AUTOENCODER).read_bytes()).hexdigest()
    (target / METADATA).write_text(json.dumps(metadata, indent=2))
    return target


def _descriptors(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 100, (V, 128))
    return np.maximum(centres[rng.integers(0, V, 600)] + rng.normal(0, 4, (600, 128)), 0).astype(np.float32)


@pytest.fixture(scope="module", params=[0, 8], ids=["network", "network_and_student"])
def new_folder(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model of the paper's network (quantizing, or with an MLP encoder distilled from it), as saved now."""
    config = VocabularyConfig(size=V, pca_dim=8, ae_embedding_dim=4, ae_epochs=1, num_threads=1, ae_network="conv",
                              ae_student_hidden=request.param, ae_student_epochs=1, ae_student_noise_rows=0)
    quantizer = train_vocabulary(_descriptors(), config, progress=False)
    folder = tmp_path_factory.mktemp("convert") / "new"
    save_model(folder, Model.create(FeatureConfig(), config, quantizer, provenance={"bags": ["a.mcap"]}))
    return folder


@pytest.fixture
def old_folder(new_folder: Path, tmp_path: Path) -> Path:
    return as_torch_folder(new_folder, tmp_path / "old")


def test_an_old_folder_loads_with_torch_and_gives_the_same_words(new_folder: Path, old_folder: Path) -> None:
    new = load_model(new_folder)
    with pytest.warns(UserWarning, match=rf"aefabmap_model convert {old_folder}"):
        old = load_model(old_folder)
    assert old.vocabulary_id == new.vocabulary_id
    x = _descriptors(1)
    np.testing.assert_array_equal(old.quantizer.quantize(x), new.quantizer.quantize(x))
    assert isinstance(old.quantizer, AutoencoderQuantizer) and old.quantizer.network is not None
    assert isinstance(new.quantizer, AutoencoderQuantizer) and new.quantizer.network is not None
    for name, array in new.quantizer.network.to_arrays().items():
        np.testing.assert_array_equal(old.quantizer.network.arrays[name], array)


def test_convert_rewrites_the_folder_in_place_with_the_same_id(new_folder: Path, old_folder: Path) -> None:
    with pytest.warns(UserWarning):
        before = load_model(old_folder)
    done = convert_model(old_folder)
    assert done.converted and done.vocabulary_id == before.vocabulary_id
    assert (old_folder / NETWORK_FILE).is_file() and not (old_folder / AUTOENCODER).exists()
    assert not needs_conversion(old_folder)
    after = load_model(old_folder)  # no warning: no torch needed any more
    assert after.vocabulary_id == before.vocabulary_id == load_model(new_folder).vocabulary_id
    assert after.created_utc == before.created_utc and after.provenance["bags"] == ["a.mcap"]
    converted = after.provenance["converted"]
    assert isinstance(converted, dict) and converted["from"] == AUTOENCODER
    x = _descriptors(2)
    np.testing.assert_array_equal(after.quantizer.quantize(x), before.quantizer.quantize(x))
    assert not convert_model(old_folder).converted  # a second run has nothing to do
    assert sorted(path.name for path in old_folder.parent.iterdir()) == ["old"]  # no temporary folder left


def test_a_failed_conversion_leaves_the_old_folder_as_it_was(old_folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    files = {path.name: path.read_bytes() for path in old_folder.iterdir()}

    def fail(path: Path, data: bytes) -> None:
        raise OSError(f"disk full writing {path.name}")

    monkeypatch.setattr(directory, "write_file", fail)
    with pytest.raises(OSError, match="disk full"):
        convert_model(old_folder)
    assert {path.name: path.read_bytes() for path in old_folder.iterdir()} == files
    assert sorted(path.name for path in old_folder.parent.iterdir()) == ["old"]


def test_the_command_converts_and_says_so(old_folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert model_main(["convert", str(old_folder)]) == 0
    assert f"{old_folder}: converted" in capsys.readouterr().out
    assert model_main(["convert", str(old_folder)]) == 0
    assert "nothing to convert" in capsys.readouterr().out
    assert model_main(["convert", str(old_folder.parent / "nowhere")]) == 1
    assert capsys.readouterr().err.startswith("ERROR: model directory")


# Runs with torch unimportable (a runtime install): argv[1] is "load" or "command", argv[2] the folder.
WITHOUT_TORCH = """
import sys
sys.modules["torch"] = None
from aefabmap_ros.errors import ModelError
if sys.argv[1] == "load":
    from aefabmap_ros.model.directory import load_model
    try:
        load_model(sys.argv[2])
    except ModelError as error:
        print("ModelError:", error)
else:
    from aefabmap_ros.cli.model import main
    print("exit", main(["convert", sys.argv[2]]))
"""


def test_without_torch_an_old_folder_is_refused_naming_the_command(old_folder: Path) -> None:
    for what in ("load", "command"):
        result = subprocess.run([sys.executable, "-c", WITHOUT_TORCH, what, str(old_folder)], capture_output=True,
                                text=True, timeout=120, check=True)
        expected = "torch is not installed here; convert the model folder once where torch is"
        if what == "load":
            assert result.stdout.startswith("ModelError: ") and expected in result.stdout
            assert f"aefabmap_model convert {old_folder}" in result.stdout
        else:
            assert result.stdout.strip() == "exit 1"
            assert result.stderr.startswith("ERROR: ") and f"aefabmap_model convert {old_folder}" in result.stderr
    assert needs_conversion(old_folder)


def test_a_corrupt_torch_file_is_named(old_folder: Path) -> None:
    (old_folder / AUTOENCODER).write_bytes(b"\x80\x02 definitely not torch")
    metadata = json.loads((old_folder / METADATA).read_text())
    metadata["files"][AUTOENCODER] = hashlib.sha256((old_folder / AUTOENCODER).read_bytes()).hexdigest()
    (old_folder / METADATA).write_text(json.dumps(metadata))
    with pytest.raises(ModelError, match=r"cannot load autoencoder weights .* corrupt"):
        load_model(old_folder)
