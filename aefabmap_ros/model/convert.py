"""Conversion of a model folder whose convolutional network is in torch's format (``autoencoder.pt``, written
before the weights were stored as arrays) into one the nodes load without torch (``network.npz``).

The folder is read with torch (``vocabulary/legacy_weights.py``), its vocabulary id checked as on every load,
and written again in place by ``save_model``: beside the old one, renamed over it once complete, so an
interrupted conversion leaves the old folder as it was. The arrays are the state_dict's own, under the same
names, so the vocabulary id, which the maps and messages made with the model carry, does not change; the
conversion checks that before and after it writes.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from aefabmap_ros.errors import ModelError
from aefabmap_ros.model.directory import Model, load_model, save_model
from aefabmap_ros.model.files import check_model_files
from aefabmap_ros.vocabulary.autoencoder import AUTOENCODER, NETWORK_FILE


@dataclass(frozen=True)
class Conversion:
    """What converting one folder did."""

    directory: Path
    converted: bool  # False: it held no torch weights, nothing was written
    vocabulary_id: str


def needs_conversion(directory: Path) -> bool:
    """Whether a model folder (its files checked) still holds the network in torch's format."""
    return AUTOENCODER in check_model_files(Path(directory))["files"]


def convert_model(directory: Path) -> Conversion:
    """Rewrite ``directory`` with the network's weights as arrays, in place and atomically; ModelError if it
    cannot be read (torch missing, corrupt) or its vocabulary id would change."""
    directory = Path(directory)
    if not needs_conversion(directory):
        return Conversion(directory, False, str(check_model_files(directory)["model_id"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the warning that asks for this very conversion
        model = load_model(directory)
    provenance = dict(model.provenance)
    provenance["converted"] = {"from": AUTOENCODER, "to": NETWORK_FILE,
                               "utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")}
    converted = Model(
        vocabulary_id=model.vocabulary_id, feature_config=model.feature_config,
        vocabulary_config=model.vocabulary_config, quantizer=model.quantizer, tree_matrix=model.tree_matrix,
        new_place_samples=model.new_place_samples, provenance=provenance, created_utc=model.created_utc,
    )
    save_model(directory, converted)  # refuses a vocabulary id that does not match the contents
    reloaded = load_model(directory)
    if reloaded.vocabulary_id != model.vocabulary_id or needs_conversion(directory):
        raise ModelError(f"converting {directory} changed its vocabulary id ({model.vocabulary_id} -> "
                         f"{reloaded.vocabulary_id})")
    return Conversion(directory, True, model.vocabulary_id)


__all__ = ["Conversion", "convert_model", "needs_conversion"]
