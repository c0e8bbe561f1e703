"""What aefabmap_eval does once its arguments are parsed (see ``evaluate.py``, which holds the options).

Imported only after parsing, so ``aefabmap_eval --help`` does not pay for torch, numba and OpenCV.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from aefabmap_ros.cli.common import no_empty_folders_left_on_error
from aefabmap_ros.cli.evaluate import SECTIONS
from aefabmap_ros.cli.evaluate_depth import chain_inputs, sequence_depths
from aefabmap_ros.cli.train_run import extract_all, source_provenance
from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.evaluation.ground_truth import check_gt_matches, load_gt_npz, load_gt_stamps, loop_matrix_from_kitti
from aefabmap_ros.evaluation.methods import METHODS, method_kinds, methods_of_kind, parse_methods
from aefabmap_ros.evaluation.metrics import DEFAULT_EVENT_GAP, evaluate_scores
from aefabmap_ros.evaluation.online_chain import ChainInputs
from aefabmap_ros.evaluation.plots import Curve, plot_pr_curves, plot_reliability, plot_score_matrix
from aefabmap_ros.evaluation.protocol import EvaluationConfig, MethodResult, evaluate_model, leave_one_out_samples
from aefabmap_ros.evaluation.recordings import (
    FLOAT_SECONDS_TOLERANCE_NS,
    FrameIndex,
    PoseTruth,
    closure_listing_markdown,
    closure_scores_markdown,
    closure_scores_to_dict,
    closures_csv,
    frames_by_query_id,
    read_pose_truth,
    score_recorded_closures,
    scores_from_recording,
)
from aefabmap_ros.evaluation.reports import online_markdown, result_to_dict, results_markdown, unique_slugs
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.features.extraction import FeatureConfig, Features
from aefabmap_ros.io import bags
from aefabmap_ros.io.atomic import atomic_write_text
from aefabmap_ros.io.config_files import build_config, read_sections
from aefabmap_ros.io.rgbd import read_times
from aefabmap_ros.io.sources import ImageSource
from aefabmap_ros.model.directory import Model, load_model, save_model
from aefabmap_ros.model.training import TrainingConfig, config_digest, evenly_spaced, train_model
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.reranking import PairVerifier, cached_pair_verifier
from aefabmap_ros.vocabulary.base import VocabularyConfig

RECORDING_TOPICS = {"place_posteriors": "aefabmap_msgs/msg/PlacePosterior",
                    "loop_closures": "aefabmap_msgs/msg/LoopClosure",
                    "loop_closure_candidates": "aefabmap_msgs/msg/LoopClosure",
                    # recordings made before loop_closures carried the verified closures:
                    "verified_loop_closures": "aefabmap_msgs/msg/LoopClosure"}


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


def prepare_output(out: Path) -> None:
    """Create the output folder and prove it writable now, not after the work."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(dir=out, prefix=".write-test-")
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        raise ConfigError(f"--out {out} is not a writable folder: {error.strerror or error}") from error


def write_results(out: Path, results: list[MethodResult], gt: np.ndarray, header: dict[str, Any],
                  extra_markdown: str = "", extra_json: dict[str, Any] | None = None,
                  extra_files: dict[str, str] | None = None) -> list[Path]:
    """results.md, results.json, pr_curves.png, scores_<method>.png and ``extra_files`` (name: text);
    returns the written paths."""
    min_gap = int(header["min_gap"])
    slugs = unique_slugs(results)
    written = []
    plot_pr_curves([Curve(r.title, r.metrics.pr_precision, r.metrics.pr_recall) for r in results],
                   out / "pr_curves.png", title=f"Precision-recall: {header['test']}")
    written.append(out / "pr_curves.png")
    for result, slug in zip(results, slugs, strict=True):
        path = out / f"scores_{slug}.png"
        plot_score_matrix(result.scores, gt, min_gap, path, f"{result.title} scores")
        written.append(path)
    diagrams = [(r.title, r.reliability) for r in results if r.reliability is not None]
    if diagrams:
        plot_reliability(diagrams, out / "reliability.png", title=f"Reliability: {header['test']}")
        written.append(out / "reliability.png")
    lines = [f"# Loop-closure evaluation: {header['test']}", ""]
    lines += [f"- {key}: {value}" for key, value in header.items() if key != "test"]
    lines += ["", results_markdown(results) + online_markdown(results)]
    if extra_markdown:
        lines += [extra_markdown]
    atomic_write_text(out / "results.md", "\n".join(lines))
    payload = {**header, "methods": [
        {**result_to_dict(r), "scores_plot": f"scores_{slug}.png"} for r, slug in zip(results, slugs, strict=True)
    ], **(extra_json or {})}
    atomic_write_text(out / "results.json", json.dumps(payload, indent=2, sort_keys=False) + "\n")
    written += [out / "results.md", out / "results.json"]
    for name, text in (extra_files or {}).items():
        atomic_write_text(out / name, text)
        written.append(out / name)
    return written


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


def load_ground_truth(args: argparse.Namespace, min_gap: int) -> np.ndarray:
    if (args.gt is None) == (args.poses is None):
        raise ConfigError("give the ground truth as --gt FILE.npz or as --poses FILE (with --max-distance "
                          "and --max-angle), exactly one")
    if args.gt is not None:
        return load_gt_npz(args.gt)
    if args.max_distance is None or args.max_angle is None:
        raise ConfigError("--poses needs --max-distance (metres) and --max-angle (degrees)")
    return loop_matrix_from_kitti(args.poses, args.max_distance, args.max_angle, min_gap)


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


def evaluate_images(run: Run, methods: tuple[str, ...]) -> tuple[list[MethodResult], np.ndarray, dict[str, Any]]:
    args, settings = run.args, run.settings
    if args.times is not None or args.pose_truth is not None or args.frames_by_query_id:
        raise ConfigError("--times, --pose-truth and --frames-by-query-id go with --recording")
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

    # (label, model, path, exclude_samples) per model to evaluate.
    entries: list[tuple[str, Model, Path, np.ndarray | None]] = []
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


@dataclass
class Recording:
    """A recording's messages, by what they are."""

    posteriors: list[Any]
    candidates: tuple[str, list[Any]] | None  # (topic, messages): FAB-MAP's raw closures
    published: tuple[str, list[Any]] | None  # (topic, messages): what a backend got on loop_closures
    note: str = ""


def read_recording(path: Path) -> Recording:
    """A recorded run's messages (``RECORDING_TOPICS``, with or without a leading '/': aefabmap_record
    stores the names it subscribed to, ros2 bag record absolute ones).

    Today's layout: ``loop_closure_candidates`` (FAB-MAP's raw closures) and ``loop_closures``
    (what was published: verified by default). Recordings made before verification moved onto
    ``loop_closures`` have ``verified_loop_closures``: their ``loop_closures`` are then read as the
    candidates and ``verified_loop_closures`` as the published, verified closures.
    """
    topics = bags.list_topics(path)
    found: dict[str, str] = {}
    for topic, msgtype in topics.items():
        name = topic.lstrip("/")
        if name in RECORDING_TOPICS:
            if msgtype != RECORDING_TOPICS[name]:
                raise DataError(f"topic {topic!r} in recording {path} is {msgtype}, expected {RECORDING_TOPICS[name]}")
            if name in found:  # 'loop_closures' (aefabmap_record's names) beside '/loop_closures' (ros2 bag record's)
                raise DataError(f"recording {path} has both {found[name]!r} and {topic!r}: one topic recorded twice; "
                                "record one run only")
            found[name] = topic
    if not found:
        raise DataError(f"recording {path} has none of place_posteriors, loop_closures, loop_closure_candidates; "
                        f"its topics: {sorted(topics) or 'none'}")
    if "verified_loop_closures" in found and "loop_closure_candidates" in found:
        raise DataError(f"recording {path} has both verified_loop_closures (recordings before loop_closures carried "
                        "the verified closures) and loop_closure_candidates (after): record one run only")
    messages: dict[str, list[Any]] = {name: [] for name in found}
    for message in bags.read_messages(path, list(found.values())):
        messages[message.topic.lstrip("/")].append(message.message)

    def closures_on(name: str) -> tuple[str, list[Any]] | None:
        return (name, messages[name]) if name in found else None

    if "verified_loop_closures" in found:
        return Recording(messages.get("place_posteriors", []), closures_on("loop_closures"),
                         closures_on("verified_loop_closures"),
                         note="An older recording: its loop_closures are read as FAB-MAP's candidates, its "
                              "verified_loop_closures as the published (verified) closures.\n")
    return Recording(messages.get("place_posteriors", []), closures_on("loop_closure_candidates"),
                     closures_on("loop_closures"))


def recording_frames(args: argparse.Namespace, num_frames: int, recording: Recording) -> FrameIndex:
    """Which ground-truth frame each recorded stamp is: the stamps of --times, else the --gt file's
    stamps_ns, else the image stamps of --bag; or, with --frames-by-query-id, the recording's query ids."""
    if args.frames_by_query_id:
        if args.times is not None or args.bag is not None:
            raise ConfigError("--frames-by-query-id maps frames by the recording's query ids: give no --times or "
                              "--bag with it")
        closure_lists = [topic[1] for topic in (recording.candidates, recording.published) if topic is not None]
        return frames_by_query_id(recording.posteriors, closure_lists, num_frames)
    if args.times is not None and args.bag is not None:
        raise ConfigError("give the frame stamps once: --times FILE or --bag BAG, not both")
    if args.times is not None:
        stamps = read_times(args.times, num_frames, frames_of="the ground truth")
        return FrameIndex(stamps, f"--times {args.times}", FLOAT_SECONDS_TOLERANCE_NS)
    gt_stamps = load_gt_stamps(args.gt) if args.gt is not None else None
    if gt_stamps is not None:
        if gt_stamps.size != num_frames:
            raise DataError(f"{args.gt} has {gt_stamps.size} stamps_ns for {num_frames} ground-truth frames")
        return FrameIndex(gt_stamps, f"the stamps_ns of {args.gt}")
    if args.bag is not None:
        source = ImageSource(bag=args.bag, topic=args.topic)
        source.check()
        stamps = source.stamps_ns()
        if stamps.size != num_frames:
            raise DataError(f"{source.name} has {stamps.size} images but the ground truth has {num_frames} frames")
        return FrameIndex(stamps, f"the {args.topic} images of {args.bag}")
    raise ConfigError(
        "the recording's messages are matched to ground-truth frames by their image stamps, and no frame stamps "
        f"were given ({'--poses' if args.gt is None else args.gt} has none): pass --times FILE (one line of "
        "seconds per frame), --bag BAG --topic TOPIC (the images the run was fed) or a --gt .npz with a stamps_ns "
        "array (aefabmap_gt, aefabmap_synth write one); --frames-by-query-id maps by the recording's query ids "
        "instead, right only for a lossless replay (every frame reached fabmap_node, in order)")


def evaluate_recording(run: Run) -> tuple[list[MethodResult], np.ndarray, dict[str, Any], str, dict[str, Any],
                                          dict[str, str]]:
    args, settings = run.args, run.settings
    depth_given = any(value is not None for value in (args.depth, args.depth_topic, args.camera_info,
                                                      args.camera_info_topic))
    if args.images is not None or args.model or args.train_images or args.train_bag \
            or args.train_on_test or args.verify or depth_given:
        raise ConfigError("--recording takes only the ground truth (--gt or --poses) and the frame stamps (--times, "
                          "--bag); it evaluates recorded outputs, no images, depth, models or --verify")
    min_gap = settings.evaluation.min_gap
    gt = load_ground_truth(args, min_gap)
    pose_truth: PoseTruth | None = read_pose_truth(args.pose_truth) if args.pose_truth is not None else None
    started = time.monotonic()
    recording = read_recording(args.recording)
    frames = recording_frames(args, gt.shape[0], recording)
    # The score matrix: the posteriors and FAB-MAP's own decisions (verified closures may have moved).
    raw = recording.candidates[1] if recording.candidates is not None else []
    recorded = scores_from_recording(recording.posteriors, raw, frames)
    metrics = evaluate_scores(recorded.scores, gt, min_gap, settings.evaluation.threshold)
    result = MethodResult(name="recording", vocabulary_kind="recorded", vocabulary_size=0, vocabulary_id="",
                          scores=recorded.scores, metrics=metrics, seconds=time.monotonic() - started,
                          model_path=str(args.recording))
    rows = [score_recorded_closures(role, *topic_messages, recording.posteriors, gt, frames, min_gap,
                                    pose_truth=pose_truth)
            for role, topic_messages in (("FAB-MAP candidates", recording.candidates),
                                         ("published", recording.published)) if topic_messages is not None]
    run.log(f"frames: {frames.describe()}")
    header = {
        "test": str(args.recording),
        "frames": int(gt.shape[0]),
        "frame_stamps": frames.describe(),
        "frames_processed": int(recorded.processed.sum()),
        "positive_queries": metrics.num_positive_queries,
        "min_gap": min_gap,
        "place_posteriors": recorded.num_posteriors,
        "place_posteriors_dropped": recorded.num_dropped_posteriors,
        "event_gap_frames": DEFAULT_EVENT_GAP,
    }
    if pose_truth is not None:
        header["pose_truth"] = pose_truth.source
    listing = [closure for row in rows for closure in row.rows]
    extra = ("\nLoop closures per topic, each message mapped to its ground-truth frames by stamp (the query "
             "image's, the matched place's). A closure (i, j) is false when gt[i, j] = 0. A revisit event is a run "
             "of revisiting frames (a ground-truth loop at least min_gap frames back), gaps of up to "
             f"{DEFAULT_EVENT_GAP} frames bridged; it is closed by one true closure from one of its frames. Recall "
             "is over all revisiting frames, and over those the detector processed (a place_posteriors message: a "
             "live detector may skip frames by design). Of the revisiting frames a topic missed, the 'missed' "
             "column counts those whose recorded posterior ranked a true place (temporal consistency or "
             "verification missed them); the rest were never ranked right (the vocabulary and FAB-MAP).\n\n"
             + (closure_scores_markdown(rows) + closure_listing_markdown(listing, pose_truth is not None)
                if rows else "No loop-closure topic in the recording.\n")
             + recording.note)
    files = {"closures.csv": closures_csv(listing)} if rows else {}
    return [result], gt, header, extra, {"closures": [closure_scores_to_dict(row) for row in rows]}, files


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
    print(results_markdown(results) + online_markdown(results), end="")
    if extra:
        print(extra, end="")
    print(f"wall time {header['wall_seconds']:.1f} s; written: " + ", ".join(str(p) for p in written))
    return 0
