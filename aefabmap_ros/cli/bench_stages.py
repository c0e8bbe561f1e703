"""Per-stage latency of the pipeline in one process (decode, features, quantization, FAB-MAP 2), with the
thread pools a node process gets under aefabmap_launch; for ``aefabmap_bench pipeline``."""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Iterator

import numpy as np
from threadpoolctl import threadpool_limits

from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.features.extraction import extract_features
from aefabmap_ros.io.image_encodings import image_to_gray
from aefabmap_ros.model.directory import Model
from aefabmap_ros.nodes.launch_table import DETECTION_NODES, threads_per_process


def _ms_since(started: float) -> float:
    return (time.perf_counter() - started) * 1e3


def latency_summary(values_ms: list[float]) -> str:
    return f"median {np.median(values_ms):7.2f} ms  p95 {np.percentile(values_ms, 95):7.2f} ms"


@contextlib.contextmanager
def thread_pools_of_a_node_process() -> Iterator[int]:
    """Cap BLAS/OpenMP pools (numpy, scipy, faiss) and torch's to what each node process gets under
    aefabmap_launch (its share of the cores), so the one-process stage timings are the nodes' own:
    uncapped, torch's pool spins against everything else on a shared machine and inflates them."""
    share = threads_per_process(len(DETECTION_NODES))
    torch = sys.modules.get("torch")  # only an autoencoder model has imported it
    torch_threads = torch.get_num_threads() if torch is not None else 0
    with threadpool_limits(limits=share):
        if torch is not None:
            torch.set_num_threads(share)
        try:
            yield share
        finally:
            if torch is not None:
                torch.set_num_threads(torch_threads)


def stage_latencies(model: Model, images: list[np.ndarray]) -> dict[str, list[float]]:
    assert model.tree_matrix is not None
    recognizer = PlaceRecognizer(ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples,
                                 FabMapConfig(), model.vocabulary_id)
    stages: dict[str, list[float]] = {"decode": [], "features": [], "quantize": [], "fabmap": []}
    # An autoencoder vocabulary with the paper's network and an MLP encoder distilled from it (which
    # quantizes): time the network too.
    network = None
    if getattr(model.quantizer, "encoder", None) is not None and getattr(model.quantizer, "network", None) is not None:
        from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer  # torch: only for this kind

        assert isinstance(model.quantizer, AutoencoderQuantizer)
        network = model.quantizer.with_encoder(None)
        stages["quantize (paper's network)"] = []
    for index, image in enumerate(images):
        height, width = image.shape[:2]
        raw = image.tobytes()
        started = time.perf_counter()
        gray = image_to_gray(raw, "mono8", height, width, width)
        stages["decode"].append(_ms_since(started))
        started = time.perf_counter()
        features = extract_features(gray, model.feature_config)
        stages["features"].append(_ms_since(started))
        started = time.perf_counter()
        words = np.unique(model.quantizer.quantize(features.descriptors))
        stages["quantize"].append(_ms_since(started))
        if network is not None:  # the reference setting on the same descriptors, for the ratio
            started = time.perf_counter()
            network.quantize(features.descriptors)
            stages["quantize (paper's network)"].append(_ms_since(started))
        started = time.perf_counter()
        recognizer.process(words, index * 100_000_000)
        stages["fabmap"].append(_ms_since(started))
    return stages
