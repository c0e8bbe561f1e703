"""Fixtures for node tests: a small model and bags whose second half revisits the first.

The model is built without k-means training (centres are descriptors sampled from another
town), so the fixtures cost seconds; accuracy is the evaluation's job, these tests check that the
nodes deliver the right messages for an unambiguous revisit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.datasets.synth.config import SynthConfig, train_test_configs
from aefabmap_ros.datasets.synth.town import generate_sequence
from aefabmap_ros.evaluation.ground_truth import loop_matrix_from_poses
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.io.bags import write_image_bag
from aefabmap_ros.model.directory import Model, save_model
from aefabmap_ros.model.training import sampled_centres_model

FRAMES_PER_PASS = 16
FRAME_PERIOD_NS = 1_000_000_000  # one distinct place a second: the second pass is 16 s later
START_NS = 1_700_000_000_000_000_000


@dataclass(frozen=True)
class RevisitData:
    model_dir: Path
    vocabulary_id: str
    bag: Path  # both passes
    first_pass_bag: Path
    second_pass_bag: Path
    stamps_ns: np.ndarray  # (2 * FRAMES_PER_PASS,)
    gt: np.ndarray  # (2P, 2P) loop matrix from the poses


def _noisy(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    noise = rng.normal(0.0, 4.0, image.shape)
    return np.clip(image.astype(np.float64) * 0.9 + 12 + noise, 0, 255).astype(np.uint8)


def _make_model(train_images: list[np.ndarray], directory: Path) -> Model:
    feature_config = FeatureConfig(max_features=300)
    features = [extract_features(image, feature_config) for image in train_images]
    model = sampled_centres_model(features, feature_config, size=400)
    save_model(directory, model)
    return model


@pytest.fixture(scope="session")
def revisit_data(tmp_path_factory: pytest.TempPathFactory) -> RevisitData:
    root = tmp_path_factory.mktemp("revisit")
    base = SynthConfig(num_frames=120, width=320, height=240, laps=1, blur_probability=0.0)
    train_config, test_config = train_test_configs(base)
    train = generate_sequence(train_config)
    test = generate_sequence(test_config)
    model = _make_model(train.images[::2], root / "model")

    # Distinct places: every 4th frame of one lap; then the same places again, re-exposed and noisy.
    picks = np.arange(FRAMES_PER_PASS) * 4
    rng = np.random.default_rng(1)
    first = [test.images[i] for i in picks]
    second = [_noisy(image, rng) for image in first]
    stamps = START_NS + np.arange(2 * FRAMES_PER_PASS, dtype=np.int64) * FRAME_PERIOD_NS
    positions = np.concatenate([test.positions[picks]] * 2)
    axes = np.concatenate([test.optical_axes[picks]] * 2)
    gt = loop_matrix_from_poses(positions, axes, max_distance_m=2.5, max_angle_deg=30.0, min_gap_frames=5)

    def frames(images: list[np.ndarray], offset: int) -> list[tuple[int, np.ndarray]]:
        return [(int(stamps[offset + k]), image) for k, image in enumerate(images)]

    write_image_bag(root / "both", "/image", frames(first, 0) + frames(second, FRAMES_PER_PASS))
    write_image_bag(root / "first", "/image", frames(first, 0))
    write_image_bag(root / "second", "/image", frames(second, FRAMES_PER_PASS))
    return RevisitData(
        model_dir=root / "model", vocabulary_id=model.vocabulary_id, bag=root / "both", first_pass_bag=root / "first",
        second_pass_bag=root / "second", stamps_ns=stamps, gt=gt,
    )
