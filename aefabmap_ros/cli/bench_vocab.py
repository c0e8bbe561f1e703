"""Benchmark of features and vocabularies: extraction per image, training per stage, quantization.

    bench_vocab                 # ~300k SIFT descriptors (kitti00_first300) -> 1000 words, AE and k-means
    bench_vocab --quick         # a seconds-long smoke run on a few images
    bench_vocab --images DIR    # your own images (png/jpg, searched recursively)
    bench_vocab --model M --kmeans-model K   # time trained vocabularies instead of training them

Prints one figure per line, ``name: value unit``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from aefabmap_ros.cli.common import ArgumentParser, run_cli
from aefabmap_ros.errors import AefabmapError
from aefabmap_ros.features.extraction import FeatureConfig, extract_features
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.vocabulary.autoencoder import AutoencoderQuantizer
from aefabmap_ros.vocabulary.base import Quantizer, VocabularyConfig, train_vocabulary, word_usage

DEFAULT_DATASETS = Path(__file__).resolve().parents[2].parent / "shared" / "datasets"


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_bench vocab", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="seconds-long smoke run (few images, small vocabulary)")
    parser.add_argument("--images", type=Path, action="append",
                        help="image folder to train on (repeatable); default: kitti00_first300 from ../shared")
    parser.add_argument("--size", type=int, default=None, help="vocabulary size (default 1000; --quick 50)")
    parser.add_argument("--epochs", type=int, default=None, help="autoencoder epochs (default: config default)")
    parser.add_argument("--max-images", type=int, default=None, help="use at most this many training images")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch default)")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")
    parser.add_argument("--model", type=Path, default=None,
                        help="a trained autoencoder model directory: time its quantization instead of training one")
    parser.add_argument("--kmeans-model", type=Path, default=None,
                        help="a trained k-means model directory: time it instead of training one")
    return parser


def _image_paths(folders: list[Path]) -> list[Path]:
    paths: list[Path] = []
    for folder in folders:
        if not folder.is_dir():
            raise AefabmapError(f"image folder {folder} does not exist")
        paths += sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not paths:
        raise AefabmapError(f"no .png/.jpg images in {', '.join(map(str, folders))}")
    return paths


def _synthetic_images(count: int, shape: tuple[int, int] = (480, 640)) -> list[np.ndarray]:
    """Textured test images for machines without the shared data."""
    rng = np.random.default_rng(0)
    images = []
    for _ in range(count):
        image = np.zeros(shape, np.uint8)
        for _ in range(150):
            x, y = int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0]))
            cv2.circle(image, (x, y), int(rng.integers(3, 25)), int(rng.integers(40, 255)), -1)
        images.append(cv2.GaussianBlur(image, (3, 3), 0))
    return images


def _load_gray(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise AefabmapError(f"cannot read image {path}")
    return image


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up (lazy init, caches)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1000.0)


def _report(name: str, value: float, unit: str) -> None:
    print(f"{name}: {value:.3f} {unit}", flush=True)


def _extraction(image: np.ndarray, config: FeatureConfig) -> Callable[[], object]:
    return lambda: extract_features(image, config)


def bench_extraction(images: list[np.ndarray], repeats: int) -> None:
    """Feature extraction per 640x480 image, SIFT and ORB."""
    resized = [cv2.resize(image, (640, 480), interpolation=cv2.INTER_AREA) for image in images]
    for kind in ("sift", "orb"):
        config = FeatureConfig(type=kind)
        per_image = [_median_ms(_extraction(image, config), repeats) for image in resized]
        count = np.mean([len(extract_features(im, config)) for im in resized])
        _report(f"extract_{kind}_640x480_ms", float(np.mean(per_image)), f"ms/image ({count:.0f} keypoints)")


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _run)


def _run(args: argparse.Namespace) -> int:
    size = args.size or (50 if args.quick else 1000)
    folders = args.images or [DEFAULT_DATASETS / "kitti00_first300" / "image_0"]
    max_images = args.max_images or (6 if args.quick else None)
    if args.images is None and not folders[0].is_dir():
        print(f"(no {folders[0]}: using synthetic images)", flush=True)
        images = _synthetic_images(max_images or 40)
    else:
        images = [_load_gray(p) for p in _image_paths(folders)[:max_images]]
    bench_extraction(images[:3] if args.quick else images[:10], repeats=1 if args.quick else 3)

    start = time.perf_counter()
    features = [extract_features(image, FeatureConfig()) for image in images]
    descriptors = np.concatenate([f.descriptors for f in features])
    _report("training_images", len(images), "images")
    _report("training_descriptors", descriptors.shape[0], "SIFT descriptors")
    _report("stage_extract_s", time.perf_counter() - start, "s")

    if args.model is not None:
        ae = _load_quantizer(args.model, "autoencoder")
    else:
        # The default vocabulary, with its distilled encoder, so that one run times it, the network and k-means.
        overrides: dict[str, object] = {"num_threads": args.threads}
        if args.epochs is not None:
            overrides["ae_epochs"] = args.epochs
        elif args.quick:
            overrides.update(ae_epochs=1, ae_max_train_descriptors=3000)
        ae_config = VocabularyConfig(kind="autoencoder", size=size, **overrides)  # type: ignore[arg-type]
        start, cpu_start = time.perf_counter(), time.process_time()
        ae = train_vocabulary(descriptors, ae_config, progress=not args.no_progress)
        _report("train_autoencoder_total_s", time.perf_counter() - start, f"s ({size} words)")
        # CPU seconds: on a machine shared with other jobs, wall time overstates the cost.
        _report("train_autoencoder_cpu_s", time.process_time() - cpu_start, "CPU s (all threads)")
        for stage, seconds in getattr(ae, "training_info", {}).items():
            if stage.endswith("_s"):
                _report(f"  ae_stage_{stage}", seconds, "s")
    if args.kmeans_model is not None:
        km = _load_quantizer(args.kmeans_model, "kmeans")
    else:
        start = time.perf_counter()
        km = train_vocabulary(descriptors, VocabularyConfig(kind="kmeans", size=size, seed=0))
        _report("train_kmeans_total_s", time.perf_counter() - start, f"s ({size} words)")

    for name, quantizer in (("autoencoder", ae), ("kmeans", km)):
        usage = word_usage(quantizer, descriptors)
        _report(f"{name}_words_used", float(np.mean(usage > 0) * 100), "%")
        _report(f"{name}_largest_word", float(usage.max() / usage.sum() * 100), "% of descriptors")

    bench_quantization(ae, km, descriptors, repeats=5 if args.quick else 100)
    return 0


def _load_quantizer(directory: Path, kind: str) -> Quantizer:
    quantizer = load_model(directory).quantizer
    if quantizer.kind != kind:
        raise AefabmapError(f"{directory} holds a vocabulary of kind {quantizer.kind}, not {kind}")
    return quantizer


def bench_quantization(ae: Quantizer, km: Quantizer, descriptors: np.ndarray, repeats: int) -> None:
    """Quantizing 1,000 descriptors: the vocabulary's MLP encoder and the paper's network (each when the
    vocabulary has one; the first quantizes), k-means."""
    if not isinstance(ae, AutoencoderQuantizer):
        raise AefabmapError(f"expected an autoencoder vocabulary, got {ae.kind!r}")
    info = ae.training_info
    if "student_word_agreement" in info:
        _report("student_word_agreement", info["student_word_agreement"] * 100,
                f"% of {info['student_held_out_descriptors']:.0f} held-out descriptors get the network's word")
    rows = np.random.default_rng(0).choice(descriptors.shape[0], 1000, replace=descriptors.shape[0] < 1000)
    batch = descriptors[rows]
    contenders: dict[str, Quantizer] = {}
    if ae.encoder is not None:
        contenders["encoder"] = ae
    if ae.network is not None:
        contenders["network"] = ae.with_encoder(None)
    contenders["kmeans"] = km
    times: dict[str, list[float]] = {name: [] for name in contenders}
    for quantizer in contenders.values():
        quantizer.quantize(batch)  # warm-up (lazy init, caches)
    # Round-robin, one call of each per round, so that a change in the machine's load falls on all alike.
    for _ in range(repeats):
        for name, quantizer in contenders.items():
            start = time.perf_counter()
            quantizer.quantize(batch)
            times[name].append(time.perf_counter() - start)
    timed = {name: float(np.median(values) * 1000.0) for name, values in times.items()}
    for name, ms in timed.items():
        _report(f"quantize_1000_{name}_ms", ms, "ms" + (" (the autoencoder's MLP encoder, which quantizes)"
                                                       if name == "encoder" else ""))
    for name in ("encoder", "network"):
        if name in timed:
            _report(f"quantize_ratio_{name}_over_kmeans", timed[name] / timed["kmeans"], "x")
    if "encoder" in timed and "network" in timed:
        _report("quantize_ratio_network_over_encoder", timed["network"] / timed["encoder"], "x")


if __name__ == "__main__":
    sys.exit(main())
