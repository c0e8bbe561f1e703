"""Smoke test of the vocabulary benchmark CLI (aefabmap_ros/cli/bench_vocab.py)."""

from pathlib import Path

import cv2
import pytest

from aefabmap_ros.cli.bench_vocab import _synthetic_images, main


def test_quick_run_prints_every_figure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for i, image in enumerate(_synthetic_images(3, (240, 320))):
        cv2.imwrite(str(tmp_path / f"{i}.png"), image)
    assert main(["--quick", "--no-progress", "--images", str(tmp_path), "--size", "10", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    for name in ("extract_sift_640x480_ms", "extract_orb_640x480_ms", "train_autoencoder_total_s",
                 "ae_stage_pretrain_s", "train_kmeans_total_s", "quantize_1000_encoder_ms",
                 "quantize_1000_kmeans_ms", "quantize_ratio_encoder_over_kmeans", "autoencoder_words_used"):
        assert f"{name}: " in out
    # The default MLP autoencoder quantizes with its own encoder: no network, no distillation to report.
    for name in ("ae_stage_distill_s", "student_word_agreement", "quantize_1000_network_ms"):
        assert f"{name}: " not in out


def test_missing_folder_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--quick", "--images", str(tmp_path / "nope")]) == 1
    assert "ERROR: image folder" in capsys.readouterr().err
    assert main(["--quick", "--images", str(tmp_path)]) == 1
    assert "ERROR: no .png/.jpg images" in capsys.readouterr().err


def test_trained_models_are_timed_without_training(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np

    from aefabmap_ros.features.extraction import FeatureConfig, extract_features
    from aefabmap_ros.model.directory import Model, save_model
    from aefabmap_ros.vocabulary.base import VocabularyConfig, train_vocabulary

    images = _synthetic_images(3, (240, 320))
    for i, image in enumerate(images):
        cv2.imwrite(str(tmp_path / f"{i}.png"), image)
    descriptors = np.concatenate([extract_features(image, FeatureConfig()).descriptors for image in images])
    for kind, extra in (("autoencoder", {"pca_dim": 8, "ae_embedding_dim": 4, "ae_epochs": 1, "num_threads": 1,
                                         "ae_network": "conv", "ae_student_hidden": 8}),
                        ("kmeans", {})):
        config = VocabularyConfig(kind=kind, size=10, **extra)  # type: ignore[arg-type]
        save_model(tmp_path / kind, Model.create(FeatureConfig(), config,
                                                 train_vocabulary(descriptors, config, progress=False)))
    arguments = ["--quick", "--no-progress", "--images", str(tmp_path), "--model", str(tmp_path / "autoencoder"),
                 "--kmeans-model", str(tmp_path / "kmeans")]
    assert main(arguments) == 0
    out = capsys.readouterr().out
    assert "train_autoencoder_total_s" not in out and "train_kmeans_total_s" not in out
    for name in ("quantize_1000_encoder_ms", "quantize_1000_network_ms", "quantize_1000_kmeans_ms",
                 "quantize_ratio_network_over_encoder"):  # the distilled encoder beside the paper's network
        assert f"{name}: " in out
    assert main([*arguments[:-1], str(tmp_path / "autoencoder")]) == 1
    assert "holds a vocabulary of kind autoencoder, not kmeans" in capsys.readouterr().err
