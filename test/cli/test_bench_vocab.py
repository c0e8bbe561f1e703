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
                 "ae_stage_pretrain_s", "ae_stage_distill_s", "train_kmeans_total_s", "student_word_agreement",
                 "quantize_1000_student_ms", "quantize_1000_network_ms", "quantize_1000_kmeans_ms",
                 "quantize_ratio_student_over_kmeans", "quantize_ratio_network_over_kmeans",
                 "quantize_ratio_network_over_student", "autoencoder_words_used"):
        assert f"{name}: " in out


def test_missing_folder_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--quick", "--images", str(tmp_path / "nope")]) == 1
    assert "ERROR: image folder" in capsys.readouterr().err
    assert main(["--quick", "--images", str(tmp_path)]) == 1
    assert "ERROR: no .png/.jpg images" in capsys.readouterr().err
