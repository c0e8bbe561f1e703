"""The convolutional network's weights in model folders written before they were stored as numpy arrays:
a torch ``state_dict`` file (``autoencoder.AUTOENCODER``), read into the same arrays with torch.

Only a folder not yet converted comes here (``aefabmap_model convert`` rewrites it with the arrays, its
vocabulary id unchanged). Where torch is installed the folder is converted on load, in memory; where it is
not (a robot's runtime install), the ModelError names the command that converts it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from aefabmap_ros.errors import ModelError

CONVERT_COMMAND = "aefabmap_model convert"


def read_torch_weights(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a torch state_dict file by name (float32); ModelError if torch is missing, the file
    is corrupt or holds no state_dict."""
    try:
        import torch
    except ImportError as error:
        raise ModelError(
            f"{path} holds the autoencoder's weights in torch's format and torch is not installed here; convert "
            f"the model folder once where torch is (pip install -r requirements-train.txt): "
            f"{CONVERT_COMMAND} {path.parent}") from error
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a corrupt file
        raise ModelError(f"cannot load autoencoder weights {path}: corrupt file ({error})") from error
    if not isinstance(state, dict) or not all(isinstance(value, torch.Tensor) for value in state.values()):
        raise ModelError(f"{path} does not hold a state_dict")
    return {str(name): tensor.detach().cpu().numpy().astype(np.float32) for name, tensor in state.items()}


__all__ = ["CONVERT_COMMAND", "read_torch_weights"]
