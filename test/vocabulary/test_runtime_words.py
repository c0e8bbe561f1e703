"""The numpy quantizers the nodes run give the words of the libraries the vocabularies were trained with: faiss'
nearest centre for k-means (SIFT and ORB), the torch encoders for the autoencoders (the MLP and the paper's
convolutional network), on every descriptor of the 300 KITTI images (../shared; skipped where absent).

Two computations of one nearest centre can differ only where two centres are equally near to float32
round-off: every row whose words differ must be such a near-tie, its two words' squared distances (in float64)
within ``TIE_TOLERANCE`` (relative) of the nearest. How many there were is printed (docs/runtime.md).
"""

from __future__ import annotations

import cv2
import faiss
import numpy as np
import pytest
import torch

from aefabmap_ros.features.descriptors import kind_of
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer
from aefabmap_ros.vocabulary.autoencoder_network import ConvAutoencoder
from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary
from aefabmap_ros.vocabulary.kmeans import KMeansQuantizer
from aefabmap_ros.vocabulary.mlp_encoder import mlp_network
from test.conftest import require_shared

TIE_TOLERANCE = 1e-4
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def descriptors() -> dict[str, np.ndarray]:
    """Every SIFT and ORB descriptor of the 300 images (about 220k and 300k)."""
    kitti_dir = require_shared("datasets", "kitti00_first300")
    images = [np.asarray(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
              for path in sorted((kitti_dir / "image_0").glob("*.png"))]
    assert len(images) == 300 and all(image.ndim == 2 for image in images)
    return {kind: np.concatenate([extract_features(image, FeatureConfig(type=kind)).descriptors for image in images])
            for kind in ("sift", "orb")}


def _squared_distances(vectors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    x, c = vectors.astype(np.float64), centres.astype(np.float64)
    return np.maximum((x * x).sum(1)[:, None] + (c * c).sum(1)[None, :] - 2.0 * x @ c.T, 0.0)


def _assert_equal_but_near_ties(name: str, ours: np.ndarray, theirs: np.ndarray, vectors: np.ndarray,
                                centres: np.ndarray) -> None:
    """``ours`` == ``theirs`` except on rows where both words are within TIE_TOLERANCE of the nearest centre."""
    differ = np.flatnonzero(ours != theirs)
    if differ.size:
        distances = _squared_distances(vectors[differ], centres)
        nearest = distances.min(axis=1)
        for words in (ours[differ], theirs[differ]):
            excess = distances[np.arange(differ.size), words] - nearest
            assert np.all(excess <= TIE_TOLERANCE * nearest), f"{name}: rows {differ[excess > TIE_TOLERANCE * nearest]}"
    print(f"{name}: {differ.size} of {ours.size} descriptors get another word, all near-ties")
    assert differ.size <= 1e-3 * ours.size


@pytest.mark.parametrize("feature", ["sift", "orb"])
def test_kmeans_words_are_faiss_words(descriptors: dict[str, np.ndarray], feature: str) -> None:
    rows = descriptors[feature]
    quantizer = train_vocabulary(rows[::10], VocabularyConfig(kind="kmeans", size=500), progress=False)
    assert isinstance(quantizer, KMeansQuantizer)
    vectors = kind_of(rows).vectors(rows)
    index = faiss.IndexFlatL2(quantizer.centres.shape[1])
    index.add(quantizer.centres)
    theirs = index.search(vectors, 1)[1][:, 0].astype(np.int64)
    _assert_equal_but_near_ties(f"k-means {feature}", quantizer.quantize(rows), theirs, vectors, quantizer.centres)


def _torch_encoder(quantizer: AutoencoderQuantizer) -> torch.nn.Module:
    """The torch module that computes the quantizer's embeddings, from the same weights."""
    if quantizer.encoder is None:
        assert quantizer.network is not None
        return ConvAutoencoder.from_numpy(quantizer.network).encoder
    encoder = quantizer.encoder
    network = mlp_network(encoder.input_dim, encoder.hidden_dim, encoder.embedding_dim).eval()
    network.load_state_dict({"0.weight": torch.from_numpy(encoder.w1.T.copy()), "0.bias": torch.from_numpy(encoder.b1),
                             "2.weight": torch.from_numpy(encoder.w2.T.copy()), "2.bias": torch.from_numpy(encoder.b2)})
    return network


def _torch_words(quantizer: AutoencoderQuantizer, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(words, embeddings) by torch: the encoder, then the argmin of |c|^2 - 2 z.c."""
    x = torch.from_numpy(quantizer.pca.transform_scaled(kind_of(rows).vectors(rows)))
    encoder, centres = _torch_encoder(quantizer), torch.from_numpy(quantizer.embedding_centres)
    with torch.inference_mode():
        z = torch.cat([encoder(x[start:start + 8192].unsqueeze(1) if quantizer.encoder is None else
                               x[start:start + 8192]) for start in range(0, x.shape[0], 8192)])
        words = (z @ centres.T * -2.0 + (centres * centres).sum(dim=1)).argmin(dim=1)
    return words.numpy().astype(np.int64), z.numpy()


@pytest.mark.parametrize("network", ["mlp", "conv"])
def test_autoencoder_words_are_the_torch_networks_words(descriptors: dict[str, np.ndarray], network: str) -> None:
    rows = descriptors["sift"]
    config = VocabularyConfig(size=300, ae_network=network, ae_student_hidden=0, ae_epochs=1, num_threads=1)
    quantizer = train_vocabulary(rows[::20], config, progress=False)
    assert isinstance(quantizer, AutoencoderQuantizer)
    assert (quantizer.network is None) == (network == "mlp") and (quantizer.encoder is None) == (network == "conv")
    theirs, embeddings = _torch_words(quantizer, rows)
    _assert_equal_but_near_ties(f"autoencoder {network}", quantizer.quantize(rows), theirs, embeddings,
                                quantizer.embedding_centres)
