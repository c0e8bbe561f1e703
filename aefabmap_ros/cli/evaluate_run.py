"""What aefabmap_eval does once its arguments are parsed (see ``evaluate.py``, which holds the options).

Imported only after parsing, so ``aefabmap_eval --help`` does not pay for torch, numba and OpenCV.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from aefabmap_ros.cli.common import no_empty_folders_left_on_error
from aefabmap_ros.cli.evaluate import SECTIONS
from aefabmap_ros.cli.evaluate_depth import chain_inputs, sequence_depths
from aefabmap_ros.cli.evaluate_outputs import prepare_output, write_report, write_results
from aefabmap_ros.cli.evaluate_recording import evaluate_recording, load_ground_truth
from aefabmap_ros.cli.train_run import extract_all, source_provenance
from aefabmap_ros.errors import ConfigError, ModelError
from aefabmap_ros.evaluation.ground_truth import check_gt_matches
from aefabmap_ros.evaluation.methods import METHODS, method_kinds, methods_of_kind, parse_methods
from aefabmap_ros.evaluation.online_chain import ChainInputs
from aefabmap_ros.evaluation.protocol import EvaluationConfig, MethodResult, evaluate_model, leave_one_out_samples
from aefabmap_ros.evaluation.reports import online_markdown, results_markdown
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.features.extraction import FeatureConfig, Features
from aefabmap_ros.io.config_files import build_config, read_sections
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.model.directory import Model, load_model, save_model
from aefabmap_ros.model.training import TrainingConfig, config_digest, evenly_spaced, train_model
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.reranking import PairVerifier, cached_pair_verifier
from aefabmap_ros.vocabulary.base import VocabularyConfig

# The FAB-MAP settings that shape the evaluation's scores (the others are fixed by the protocol).
REPORTED_FABMAP_SETTINGS = ("p_z_given_e", "p_z_given_not_e", "new_place_model", "motion_model", "smoothing",
                            "min_words")


# ------------------------------------------------------------------------------------------ configs


class Settings:
    """Every config the run uses, from the YAML sections and the command line."""

    def __init__(self, args: argparse.Namespace) -> None:
        sections = read_sections(args.config, set(SECTIONS))
        origin = str(args.config or "command line")

        def section(name: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
            extra = {k: v for k, v in (overrides or {}).items() if v is not None}
            return {**sections.get(name, {}), **extra}

        self.feature = build_config(FeatureConfig, section(
            "feature", {"type": args.feature, "max_features": args.max_features}), f"{origin} [feature]")
        self.training = build_config(TrainingConfig, section("training"), f"{origin} [training]")
        self.fabmap = build_config(FabMapConfig, section("fabmap"), f"{origin} [fabmap]")
        self.evaluation = build_config(EvaluationConfig, section("evaluation", {
            "min_gap": args.min_gap, "threshold": args.threshold, "bow_threshold": args.bow_threshold,
        }), f"{origin} [evaluation]")
        self.verification = build_config(VerificationConfig, section("verification"), f"{origin} [verification]")
        common = section("vocabulary", {"size": args.size, "seed": args.seed})
        common.pop("kind", None)  # the method decides the kind
        self.vocabulary = {
            kind: build_config(VocabularyConfig, {**common, **section(f"vocabulary_{kind}"), "kind": kind},
                               f"{origin} [vocabulary_{kind}]")
            for kind in method_kinds()
        }


# ------------------------------------------------------------------------------------------ outputs


# ------------------------------------------------------------------------------------------ inputs


def test_source(args: argparse.Namespace) -> ImageSource:
    if (args.images is None) == (args.bag is None):
        raise ConfigError("give the test sequence as --images DIR or as --bag BAG (with --topic), exactly one")
    if not (np.isfinite(args.rate) and args.rate > 0):
        raise ConfigError(f"--rate must be a positive frame rate in Hz, got {args.rate}")
    source = (ImageSource(folder=args.images, folder_period_ns=round(1e9 / args.rate)) if args.images is not None
              else ImageSource(bag=args.bag, topic=args.topic))
    source.check()
    return source


def report_source(args: argparse.Namespace) -> ImageSource | None:
    """The test images, for the report's image pairs: --images, or --bag (a recording's run was fed from it)."""
    if args.images is not None:
        return ImageSource(folder=args.images, folder_period_ns=round(1e9 / args.rate))
    return ImageSource(bag=args.bag, topic=args.topic) if args.bag is not None else None


def training_sources(args: argparse.Namespace) -> list[ImageSource]:
    sources = [ImageSource(folder=folder) for folder in args.train_images]
    sources += [ImageSource(bag=bag, topic=args.train_topic) for bag in args.train_bag]
    for source in sources:
        source.check()
    return sources


def check_training_choice(args: argparse.Namespace) -> None:
    chosen = [bool(args.train_images or args.train_bag), bool(args.train_on_test), bool(args.model)]
    if sum(chosen) != 1:
        raise ConfigError("choose where the vocabularies come from, exactly one of: --train-images/--train-bag, "
                          "--train-on-test, --model")


class Run:
    """State shared by the stages of one evaluation: settings, cache folder, logging."""

    def __init__(self, args: argparse.Namespace, settings: Settings) -> None:
        self.args = args
        self.settings = settings
        self.work_dir: Path = args.work_dir or args.out / ".cache"
        try:
            self.work_dir.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise ConfigError(f"--work-dir {self.work_dir} cannot be created: {error.strerror or error}") from error
        self.seconds: dict[str, float] = {}

    def log(self, message: str) -> None:
        if not self.args.quiet:
            print(f"[eval] {message}", file=sys.stderr)

    def features(self, source: ImageSource, feature_config: FeatureConfig) -> list[Features]:
        started = time.monotonic()
        sequence = extract_all([source], feature_config, self.work_dir, self.args.quiet)[0]
        self.seconds["features"] = self.seconds.get("features", 0.0) + time.monotonic() - started
        return sequence

    def trained_model(self, kind: str, sequences: list[list[Features]], provenance: dict[str, Any],
                      fingerprint: str) -> tuple[Model, Path]:
        """Train (or reuse from the cache) the model of one vocabulary kind."""
        settings = self.settings
        vocabulary = settings.vocabulary[kind]
        key = config_digest(settings.feature, vocabulary, settings.training)
        directory = self.work_dir / f"model-{kind}-{fingerprint}-{key}"
        if directory.is_dir():
            try:
                model = load_model(directory)
                self.log(f"reusing the cached {kind} model {directory}")
                return model, directory
            except ModelError as error:
                self.log(f"cached model unusable ({error}); training again")
        started = time.monotonic()
        model, _ = train_model(sequences, settings.feature, vocabulary, settings.training, provenance,
                               work_dir=self.work_dir, progress=not self.args.quiet, log=self.log)
        save_model(directory, model)
        self.seconds[f"train_{kind}"] = time.monotonic() - started
        return model, directory


class _ProgressFromFirstTick:
    """A progress bar that starts at its first tick, so the quantization before the first FAB-MAP
    query (seconds with the autoencoder) does not show up as the first query's time."""

    def __init__(self, total: int, description: str, quiet: bool) -> None:
        self._arguments = {"total": total, "desc": description, "unit": "img", "disable": quiet, "file": sys.stderr}
        self._bar: tqdm[Any] | None = None

    def tick(self, _frame: int) -> None:
        if self._bar is None:
            self._bar = tqdm(**self._arguments)
        self._bar.update()
        if self._bar.n >= self._bar.total:  # done: the bar's time must not run on through tf-idf and GV
            self._bar.close()

    def __enter__(self) -> _ProgressFromFirstTick:
        return self

    def __exit__(self, *_exc: object) -> None:
        if self._bar is not None:
            self._bar.close()


def _fingerprint(sources: list[ImageSource]) -> str:
    """Identifies the training images (their sources' fingerprints, in order)."""
    return hashlib.sha256("\n".join(s.fingerprint() for s in sources).encode()).hexdigest()[:12]


# ------------------------------------------------------------------------------------------ modes


ModelEntry = tuple[str, Model, Path, np.ndarray | None]  # (label, model, its path, samples to exclude)


def model_entries(run: Run, methods: tuple[str, ...], source: ImageSource,
                  train: list[ImageSource]) -> tuple[list[ModelEntry], tuple[str, ...]]:
    """The models to evaluate -- given (--model), or trained on the training sources or the test sequence -- and
    the methods they can run."""
    args, settings = run.args, run.settings
    num_frames = len(source)
    entries: list[ModelEntry] = []
    if args.model:
        loaded = [(path, load_model(path)) for path in args.model]
        by_kind: dict[str, int] = {}
        for _, model in loaded:
            by_kind[model.quantizer.kind] = by_kind.get(model.quantizer.kind, 0) + 1
        for path, model in loaded:
            label = path.name if by_kind[model.quantizer.kind] > 1 else ""
            entries.append((label, model, path, None))
        kinds_given = {model.quantizer.kind for _, model in loaded}
        methods = tuple(name for name in methods if METHODS[name][0] in kinds_given)
        if not methods:
            raise ConfigError(f"none of the selected methods can run with the given models "
                              f"(vocabulary kinds {sorted(kinds_given)})")
    else:
        kinds = [kind for kind in method_kinds() if methods_of_kind(kind, methods)]
        if args.train_on_test:
            sequences = [run.features(source, settings.feature)]
            fingerprint = _fingerprint([source])
            provenance: dict[str, Any] = {"sources": [source_provenance(source)], "train_on_test": True}
            samples = evenly_spaced(num_frames, settings.training.max_new_place_samples)
            exclude: np.ndarray | None = leave_one_out_samples(num_frames, samples)
        else:
            sequences = [run.features(s, settings.feature) for s in train]
            fingerprint = _fingerprint(train)
            provenance = {"sources": [source_provenance(s) for s in train]}
            exclude = None
        for kind in kinds:
            model, directory = run.trained_model(kind, sequences, provenance, fingerprint)
            entries.append(("", model, directory, exclude))
    return entries, methods


def evaluate_images(run: Run, methods: tuple[str, ...]) -> tuple[list[MethodResult], np.ndarray, dict[str, Any]]:
    args, settings = run.args, run.settings
    if args.times is not None or args.pose_truth is not None or args.frames_by_query_id \
            or args.trajectory is not None or args.session_odometry:
        raise ConfigError("--times, --pose-truth, --trajectory, --session-odometry and --frames-by-query-id go "
                          "with --recording")
    check_training_choice(args)
    depth_given = args.depth is not None or args.depth_topic is not None
    if depth_given and not args.verify:
        raise ConfigError("--depth/--depth-topic feed verification's metric test: add --verify")
    min_gap = settings.evaluation.min_gap
    gt = load_ground_truth(args, min_gap)
    source = test_source(args)
    num_frames = len(source)
    check_gt_matches(gt, num_frames, source.name)
    train = [] if args.train_on_test or args.model else training_sources(args)

    entries, methods = model_entries(run, methods, source, train)

    stamps_ns = source.stamps_ns()
    results: list[MethodResult] = []
    features_by_config: dict[str, list[Features]] = {}
    verifiers: dict[str, PairVerifier] = {}  # one per feature config: methods share the pairs they verify
    chains: dict[str, ChainInputs] = {}  # one per feature config: what verifier_node's chain verifies with
    for label, model, path, exclude in entries:
        key = config_digest(model.feature_config)
        if key not in features_by_config:
            features_by_config[key] = run.features(source, model.feature_config)
            depths = sequence_depths(args, source, features_by_config[key]) if args.verify else None
            verifiers[key] = cached_pair_verifier(features_by_config[key], settings.verification, depths)
            chains[key] = chain_inputs(args, features_by_config[key], settings.verification, depths)
        test_features = features_by_config[key]
        verification = (settings.verification, verifiers[key]) if args.verify else None
        wanted = methods_of_kind(model.quantizer.kind, methods)
        fabmap_count = sum(1 for name in wanted if METHODS[name][1] == "fabmap")
        run.log(f"quantizing the {num_frames} test images, then scoring {', '.join(wanted)} with "
                f"{model.quantizer.kind} model {model.vocabulary_id}")
        with _ProgressFromFirstTick(num_frames * fabmap_count, "FAB-MAP queries", args.quiet) as progress:
            results += evaluate_model(model, test_features, gt, wanted, settings.evaluation, settings.fabmap,
                                      exclude_samples=None if exclude is None else exclude.tolist(),
                                      on_frame=progress.tick, label=label, model_path=str(path),
                                      verification=verification, stamps_ns=stamps_ns, chain_inputs=chains[key])
    order = {name: index for index, name in enumerate(METHODS)}
    results.sort(key=lambda r: (order[r.name], r.label, r.verified))
    header = {
        "test": source.name,
        "frames": num_frames,
        "positive_queries": results[0].metrics.num_positive_queries if results else 0,
        "min_gap": min_gap,
        "training": ("test sequence (--train-on-test)" if args.train_on_test else
                     "models " + ", ".join(str(p) for p in args.model) if args.model else
                     ", ".join(s.name for s in train)),
        "features": f"{settings.feature.type}, at most {settings.feature.max_features} per image"
                    if not args.model else "from the models",
        "fabmap": {k: v for k, v in asdict(settings.fabmap).items() if k in REPORTED_FABMAP_SETTINGS},
    }
    if args.verify:
        header["geometric_verification"] = asdict(settings.verification)
        header["depth"] = f"{args.depth or args.depth_topic} (the metric test)" if depth_given else "none"
    return results, gt, header


def run_evaluation(args: argparse.Namespace) -> int:
    started = time.monotonic()
    settings = Settings(args)
    methods = parse_methods(args.methods.split(","))
    extra = ""
    extra_json: dict[str, Any] = {}
    extra_files: dict[str, str] = {}
    # Some arguments are validated only by the stage that uses them: a refusal must not leave OUT/.cache.
    with no_empty_folders_left_on_error(args.out, args.work_dir or args.out / ".cache"):
        prepare_output(args.out)
        run = Run(args, settings)
        if args.recording is not None:
            results, gt, header, extra, extra_json, extra_files = evaluate_recording(run)
        else:
            results, gt, header = evaluate_images(run, methods)
    header["wall_seconds"] = round(time.monotonic() - started, 1)
    header["stage_seconds"] = {k: round(v, 1) for k, v in run.seconds.items()}
    written = write_results(args.out, results, gt, header, extra, extra_json, extra_files)
    written.append(write_report(args.out, f"Loop-closure evaluation: {header['test']}", results, gt,
                                int(header["min_gap"]), settings.evaluation, report_source(args)))
    print(results_markdown(results) + online_markdown(results), end="")
    if extra:
        print(extra, end="")
    print(f"wall time {header['wall_seconds']:.1f} s; written: " + ", ".join(str(p) for p in written))
    return 0
