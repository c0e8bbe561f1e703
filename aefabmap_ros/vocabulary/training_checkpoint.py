"""Resumable training state of the autoencoder vocabulary: one file in the work directory, written
atomically after every epoch, picked up by the next run with the same settings and data."""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from aefabmap_ros.errors import ModelError
from aefabmap_ros.io.atomic import atomic_write_bytes
from aefabmap_ros.vocabulary.config import VocabularyConfig

CHECKPOINT_NAME = "ae_checkpoint.pt"
SKIP = 1 << 30  # an epoch number past any stage's end: the stage's loop runs no epoch


def fingerprint(options: VocabularyConfig, descriptors: np.ndarray, pairs: np.ndarray | None) -> str:
    digest = hashlib.sha256(json.dumps(options.to_dict(), sort_keys=True).encode())
    digest.update(str(descriptors.shape).encode() + str(descriptors.dtype).encode())
    step = max(1, descriptors.shape[0] // 1000)
    digest.update(np.ascontiguousarray(descriptors[::step]).tobytes())
    if pairs is not None:
        digest.update(np.ascontiguousarray(pairs).tobytes())
    return digest.hexdigest()[:16]


class Checkpoint:
    """Per-epoch training state in ``work_dir`` (atomic writes), resumed when the fingerprint matches."""

    def __init__(self, work_dir: Path | None, fingerprint: str) -> None:
        self.path = None if work_dir is None else Path(work_dir) / CHECKPOINT_NAME
        self.fingerprint = fingerprint
        self.state: dict[str, Any] | None = None
        if self.path is not None and self.path.exists():
            try:
                state = torch.load(self.path, map_location="cpu", weights_only=False)
            except Exception as error:  # a truncated or foreign file: say so and start afresh
                raise ModelError(
                    f"cannot read training checkpoint {self.path}: {error}; delete it to restart"
                ) from error
            if isinstance(state, dict) and state.get("fingerprint") == fingerprint:
                self.state = state

    def restore(self, stage: str, model: nn.Module, optimizer: torch.optim.Optimizer,
                centres: nn.Parameter | None = None) -> int:
        """Load the checkpoint's state if it is at or past ``stage``; the first epoch still to run."""
        if self.state is None:
            return 0
        stages = ("pretrain", "refine")
        saved_stage = self.state["stage"]
        if stages.index(saved_stage) < stages.index(stage):
            return 0
        model.load_state_dict(self.state["model"])
        if saved_stage != stage:  # past this stage: its result is in the model already
            return SKIP
        optimizer.load_state_dict(self.state["optimizer"])
        if centres is not None and self.state.get("centres") is not None:
            with torch.no_grad():
                centres.copy_(self.state["centres"])
        torch.set_rng_state(self.state["torch_rng"])
        return int(self.state["epoch"]) + 1

    def save(self, stage: str, epoch: int, model: nn.Module, optimizer: torch.optim.Optimizer,
             centres: nn.Parameter | None = None) -> None:
        if self.path is None:
            return
        state = {
            "fingerprint": self.fingerprint, "stage": stage, "epoch": epoch,
            "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "centres": None if centres is None else centres.detach().clone(),
            "torch_rng": torch.get_rng_state(),
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        torch.save(state, buffer)
        atomic_write_bytes(self.path, buffer.getvalue())

    def finish(self) -> None:
        """Training completed: the checkpoint has served its purpose."""
        if self.path is not None and self.path.exists():
            self.path.unlink()

