"""What aefabmap_train does once its arguments are parsed (see ``train.py``, which holds the options).

Imported only after parsing, so ``aefabmap_train --help`` does not pay for torch, numba and OpenCV.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from aefabmap_ros.cli.common import no_empty_folders_left_on_error
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.features.extraction import FeatureConfig, Features
from aefabmap_ros.io.config_files import build_config, read_sections
from aefabmap_ros.io.digests import file_sha256
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.model.directory import save_model
from aefabmap_ros.model.training import TrainingConfig, config_digest, extract_sequence_features, train_model
from aefabmap_ros.vocabulary.base import VocabularyConfig

SECTIONS = {"feature": FeatureConfig, "vocabulary": VocabularyConfig, "training": TrainingConfig}


def load_configs(args: argparse.Namespace) -> tuple[FeatureConfig, VocabularyConfig, TrainingConfig]:
    sections = read_sections(args.config, set(SECTIONS))
    overrides: dict[str, dict[str, Any]] = {
        "feature": {"type": args.feature, "max_features": args.max_features},
        "vocabulary": {"kind": args.vocabulary, "size": args.size, "seed": args.seed, "ae_input": args.ae_input},
        "training": {},
    }
    built: list[Any] = []
    for name, config_type in SECTIONS.items():
        values = {**sections.get(name, {}), **{k: v for k, v in overrides[name].items() if v is not None}}
        built.append(build_config(config_type, values, f"{args.config or 'command line'} [{name}]"))
    feature, vocabulary, training = built
    assert isinstance(feature, FeatureConfig) and isinstance(vocabulary, VocabularyConfig)
    assert isinstance(training, TrainingConfig)
    return feature, vocabulary, training


def gather_sources(args: argparse.Namespace) -> list[ImageSource]:
    sources = [ImageSource(bag=bag, topic=args.topic) for bag in args.bag]
    sources += [ImageSource(folder=folder) for folder in args.images]
    if not sources:
        raise ConfigError("no training images: give --bag (with --topic) or --images")
    for source in sources:
        source.check()  # a missing topic or folder fails now, not after an hour of work
    return sources


def check_output(out: Path, overwrite: bool) -> None:
    if out.exists() and not overwrite:
        raise ConfigError(f"--out {out} already exists (pass --overwrite to replace it)")
    parent = out.resolve().parent
    if not parent.is_dir():
        raise ConfigError(f"--out {out}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise ConfigError(f"--out {out}: folder {parent} is not writable")


def source_provenance(source: ImageSource) -> dict[str, Any]:
    entry: dict[str, Any] = {"source": source.name, "fingerprint": source.fingerprint()}
    if source.bag is not None:
        entry["files"] = {p.name: file_sha256(p) for p in sorted(source.bag.iterdir()) if p.is_file()}
    return entry


def extract_all(sources: list[ImageSource], feature_config: FeatureConfig, work_dir: Path,
                quiet: bool) -> list[list[Features]]:
    return [source_features(source, feature_config, work_dir, quiet) for source in sources]


def source_features(source: ImageSource, feature_config: FeatureConfig, work_dir: Path | None, quiet: bool,
                    stride: int = 1) -> list[Features]:
    """Every ``stride``-th frame's features, cached in ``work_dir`` (None: not cached) per source, feature settings
    and stride; aefabmap_train's cache serves any tool that reads the same source with the same settings."""
    cache = None
    if work_dir is not None:
        work_dir.mkdir(parents=True, exist_ok=True)
        strided = "" if stride == 1 else f"-s{stride}"
        cache = work_dir / f"features-{source.fingerprint()}{strided}-{config_digest(feature_config)}.npz"
    frames = (gray for index, (_, gray) in enumerate(source.frames()) if index % stride == 0)
    with tqdm(total=-(-len(source) // stride), desc=f"features {source.name}", unit="img", disable=quiet,
              file=sys.stderr) as bar:
        sequence = extract_sequence_features(frames, feature_config, cache_path=cache,
                                             on_frame=lambda _: bar.update())
        bar.update(bar.total - bar.n)
    return sequence


def run_training(args: argparse.Namespace) -> int:
    feature_config, vocabulary_config, training_config = load_configs(args)
    check_output(args.out, args.overwrite)
    sources = gather_sources(args)
    work_dir = args.work_dir or args.out.resolve().parent / f".{args.out.name}.work"
    with no_empty_folders_left_on_error(work_dir):  # a failure before any cached stage leaves nothing behind
        work_dir.mkdir(parents=True, exist_ok=True)
        return train_in(work_dir, args, sources, feature_config, vocabulary_config, training_config)


def train_in(work_dir: Path, args: argparse.Namespace, sources: list[ImageSource], feature_config: FeatureConfig,
             vocabulary_config: VocabularyConfig, training_config: TrainingConfig) -> int:
    started = time.monotonic()
    sequences = extract_all(sources, feature_config, work_dir, args.quiet)
    feature_seconds = time.monotonic() - started

    def log(message: str) -> None:
        if not args.quiet:
            print(f"[train] {message}", file=sys.stderr)

    provenance = {"sources": [source_provenance(s) for s in sources]}
    model, report = train_model(sequences, feature_config, vocabulary_config, training_config, provenance,
                                work_dir=work_dir, progress=not args.quiet, log=log)
    save_model(args.out, model)
    seconds = {"features": feature_seconds, **report.seconds}
    print(f"model {model.vocabulary_id} written to {args.out}")
    print(f"  images: {report.num_images} ({report.images_without_features} without features), "
          f"descriptors: {report.num_descriptors}, self-supervision pairs: {report.num_pairs}")
    print(f"  vocabulary: {vocabulary_config.kind}, {model.quantizer.size} words, {report.words_used} used "
          f"by the training images; Chow-Liu tree: {report.tree_edges} edges")
    info: dict[str, float] = getattr(model.quantizer, "training_info", {})  # autoencoder vocabularies
    agreement = info.get("student_word_agreement")
    if agreement is not None:  # how faithfully the distilled encoder that quantizes reproduces the network
        print(f"  distilled encoder ({int(info['student_hidden'])} hidden units) gives the network's word to "
              f"{agreement * 100:.1f} % of {int(info['student_held_out_descriptors'])} held-out descriptors")
    print("  time: " + ", ".join(f"{stage} {value:.1f} s" for stage, value in seconds.items()))
    return 0
