"""Screen vocabulary directions by tf-idf retrieval: train on one image folder, test on another.

    PYTHONPATH=. nice -n 10 .venv/bin/python scripts/screen_vocabulary.py \
        --train /work/shared/datasets/kitti00_first300/image_0 \
        --test /work/shared/datasets/rtabmap_samples/images --gt /work/shared/datasets/rtabmap_samples/loop_gt.npz

Every contender gets the same 1000 words from the same cheap k-means (10 Lloyd iterations on at most 64
rows per word, k-means++ on 10k rows), so the rows differ only in the space the words are found in:
raw SIFT; PCA-64 scaled to [0, 1] (the autoencoder's input); the match projection (``fit_match_projection``
on pairs matched between neighbouring training frames); and an MLP autoencoder (the distilled student's
shape, 64-256-64 with a mirror decoder, 4 epochs of BCE on 100k rows) on either input. Prints tf-idf
average precision and recall at 100 % precision (best earlier frame at least 10 back), the idf from the
training images, as aefabmap_eval's BoW rows do.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

import aefabmap_ros.vocabulary.kmeans as kmeans_module
from aefabmap_ros.evaluation.metrics import evaluate_scores
from aefabmap_ros.evaluation.tfidf import tfidf_score_matrix
from aefabmap_ros.features.extraction import FeatureConfig, Features, extract_features
from aefabmap_ros.model.training import binary_bow, count_bow, sequence_pairs
from aefabmap_ros.vocabulary.kmeans import kmeans, nearest
from aefabmap_ros.vocabulary.pca import PCA, fit_match_projection, fit_pca

Embed = Callable[[np.ndarray], np.ndarray]


class SpaceWords:
    """Nearest of ``centres`` in the space ``embed`` maps descriptors to."""

    def __init__(self, embed: Embed, centres: np.ndarray) -> None:
        self.embed, self.centres, self.size = embed, centres, len(centres)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        if len(descriptors) == 0:
            return np.zeros(0, np.int64)
        return nearest(self.centres, self.embed(descriptors.astype(np.float32)))[0]


def features_of(folder: Path) -> list[Features]:
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg"))
    paths.sort(key=lambda p: (len(p.stem), p.stem))  # 1.jpg, 2.jpg, ..., 10.jpg
    return [extract_features(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), FeatureConfig()) for p in paths]


def mlp_autoencoder(x: np.ndarray, seed: int, epochs: int = 4, hidden: int = 256, embedding: int = 64) -> Embed:
    torch.manual_seed(seed)
    encoder = nn.Sequential(nn.Linear(x.shape[1], hidden), nn.ReLU(), nn.Linear(hidden, embedding))
    decoder = nn.Sequential(nn.Linear(embedding, hidden), nn.ReLU(), nn.Linear(hidden, x.shape[1]))
    optimizer = torch.optim.Adam([*encoder.parameters(), *decoder.parameters()], lr=1e-3)
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(x), min(len(x), 100_000), replace=False)
    inputs, loss_of = torch.from_numpy(x), nn.BCEWithLogitsLoss()
    for _ in range(epochs):
        order = rows[rng.permutation(rows.size)]
        for start in range(0, order.size - 255, 256):
            batch = inputs[order[start:start + 256]]
            loss = loss_of(decoder(encoder(batch)), batch)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

    def embed(rows_in: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            result: np.ndarray = encoder(torch.from_numpy(rows_in)).numpy()
        return result
    return embed


def retrieval(words: SpaceWords, train: list[Features], test: list[Features], gt: np.ndarray) -> tuple[float, float]:
    scores = tfidf_score_matrix(count_bow(words, test), binary_bow(words, train))
    metrics = evaluate_scores(scores, gt, 10, 0.6)
    return metrics.average_precision, metrics.recall_at_100_precision


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=Path, required=True)
    parser.add_argument("--test", type=Path, required=True)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    kmeans_module.KMEANS_PLUSPLUS_MAX_POINTS = 10_000
    train, test = features_of(args.train), features_of(args.test)
    gt = np.load(args.gt)["gt"].astype(bool)
    x = np.concatenate([f.descriptors for f in train]).astype(np.float32)
    pairs = sequence_pairs(train, max_gap=1)
    print(f"{len(x)} training descriptors, {len(pairs)} matched pairs", flush=True)
    inputs: dict[str, PCA] = {"pca": fit_pca(x, 64), "matches": fit_match_projection(x, pairs, 64)}
    spaces: dict[str, Embed] = {"raw SIFT": lambda rows: rows}
    for name, projection in inputs.items():
        spaces[f"{name} projection"] = projection.transform_scaled
    for name, projection in inputs.items():
        network = mlp_autoencoder(projection.transform_scaled(x), args.seed)
        spaces[f"MLP autoencoder on {name}"] = lambda rows, p=projection, n=network: n(p.transform_scaled(rows))
    for name, embed in spaces.items():
        started = time.process_time()
        words = SpaceWords(embed, kmeans(embed(x), 1000, args.seed, 10, 64))
        ap, recall = retrieval(words, train, test, gt)
        print(f"{name}: AP {ap:.3f}, recall at 100 % precision {recall:.3f} "
              f"({time.process_time() - started:.0f} CPU s)", flush=True)


if __name__ == "__main__":
    main()
