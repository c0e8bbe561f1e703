"""Offline evaluation (DESIGN 6): the paper's four methods on a test sequence, scored against ground truth.

Methods (DESIGN 4.4), each a vocabulary kind and a scorer:

=========  ===========  =============================================================
FABMAP2    k-means      FAB-MAP 2 posterior p(place j | Z_0..Z_i)
AE-FABMAP  autoencoder  FAB-MAP 2 posterior
BoW        k-means      tf-idf cosine similarity (Sivic & Zisserman)
AE-BoW     autoencoder  tf-idf cosine similarity
=========  ===========  =============================================================

A vocabulary is trained (or loaded) once per kind and serves both its FAB-MAP and its BoW method.

**FAB-MAP score matrix.** The scores are produced by the online
:class:`~aefabmap_ros.fabmap.recognizer.PlaceRecognizer` itself (one code path with the nodes), run
frame by frame with add policy "all" and no keyframing (every informative frame is a place) and
every candidate reported (``top_k`` = all): ``scores[i, j]`` = posterior of frame j's place for
query i, ``new_place[i]`` = posterior of "new place". Frames with fewer than the config's
``min_words`` words are not recognised (a zero row) and are no places (a zero column). The
metrics then take each query's best candidate among ``j <= i - min_gap`` (``evaluation.metrics``).

Whether the recent frames are hypotheses of the posterior is ``fabmap_exclude_recent``
(the recognizer's ``exclude_recent_frames``). Default 0, none excluded, as openFABMAP: removing the
last ``min_gap - 1`` frames from the posterior (-1) takes from a query of an unvisited place the
look-alike predecessors that absorb the mass, and with a new-place model trained on other imagery
the mass lands on some older look-alike place, a confident false loop that lowers both AP and the
precision at the 0.99 threshold (figures: docs/measurements.md). On very dense video, where the
previous frames always win, set it to -1.

**tf-idf score matrix.** Cosine similarity of tf-idf vectors of word counts; the idf comes from
the model's new-place samples (the training images' binary bag-of-words: idf needs only which
images hold a word), so a loaded model and a freshly trained one score alike. A model without
samples falls back to the test sequence's own idf.

**Training on the test sequence.** The sampled new-place likelihood is a mean over training
images; when those are the test images, query i's own sample matches it perfectly and dominates
the mean, so it is left out of query i's mean (``exclude_samples``).

**Recordings.** :func:`scores_from_recording` rebuilds a score matrix from the ``place_posteriors``
(top-K candidates) and ``loop_closures`` of a recorded run of the nodes. Query ids are frame
indices (the detector numbers every frame it receives). A candidate place is mapped to a frame
by its stamp when that stamp is a query stamp of the recording (robust to keyframing and the
"new_only" policy); otherwise its place id is taken as the frame index, which holds under the
default policy "all" without keyframing. Places missing from a query's top-K score 0. The loop
closures of each recorded topic (FAB-MAP's candidates, the published and by default verified
closures) are scored on their own by :func:`score_recorded_closures`: precision, and per revisit
event and revisiting frame (``evaluation.metrics.event_scores``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from aefabmap_ros.errors import ConfigError, DataError, ModelError
from aefabmap_ros.evaluation.calibration import Reliability, reliability
from aefabmap_ros.evaluation.methods import METHODS
from aefabmap_ros.evaluation.metrics import (
    EventScores,
    LoopMetrics,
    evaluate_scores,
    event_scores,
    missed_with_a_true_place_ranked,
)
from aefabmap_ros.evaluation.online_chain import ChainInputs, run_online_chain
from aefabmap_ros.evaluation.tfidf import tfidf_score_matrix
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.recognizer import PlaceRecognizer
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.model.directory import Model
from aefabmap_ros.model.training import count_bow
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.verification.reranking import PairVerifier, verified_scores

# tf-idf cosine is not a calibrated probability: this default is near the best-F1 threshold (0.63) of
# k-means BoW on the synthetic *training* sequence (vocabulary from kitti00_first300). Compare methods by
# AP and recall at 100 % precision, which need no threshold.
DEFAULT_BOW_THRESHOLD = 0.6

FrameCallback = Callable[[int], None]


@dataclass(frozen=True)
class EvaluationConfig:
    """How the methods are scored (flat: one YAML key each)."""

    min_gap: int = field(
        default=10,
        metadata={"description": "Frames j > i - min_gap are not loop candidates of query i (in the metrics "
                  "and, for FAB-MAP, not hypotheses of its posterior)."},
    )
    threshold: float = field(
        default=0.99,
        metadata={"description": "FAB-MAP posterior threshold of the paper's accuracy and recall (0.99)."},
    )
    fabmap_exclude_recent: int = field(
        default=0,
        metadata={"description": "FAB-MAP: places of the last N frames are not hypotheses of the posterior "
                  "(0 = none excluded, as openFABMAP; -1 = min_gap - 1, exactly the protocol's "
                  "non-candidates)."},
    )
    bow_threshold: float = field(
        default=DEFAULT_BOW_THRESHOLD,
        metadata={"description": "tf-idf cosine threshold of the BoW methods' accuracy and recall."},
    )
    verify_more_candidates: int = field(
        default=5,
        metadata={"description": "The \"+ GV\" rows: when none of a query's best verification.candidates is "
                  "accepted, the next this many are verified and re-ranked alike (0 = off; their effect on AP: "
                  "docs/measurements.md)."},
    )

    def __post_init__(self) -> None:
        if isinstance(self.min_gap, bool) or not isinstance(self.min_gap, int) or self.min_gap < 1:
            raise ConfigError(f"EvaluationConfig.min_gap={self.min_gap!r} must be an integer >= 1")
        if isinstance(self.verify_more_candidates, bool) or not isinstance(self.verify_more_candidates, int) \
                or self.verify_more_candidates < 0:
            raise ConfigError(f"EvaluationConfig.verify_more_candidates={self.verify_more_candidates!r} must be an "
                              "integer >= 0")
        if isinstance(self.fabmap_exclude_recent, bool) or not isinstance(self.fabmap_exclude_recent, int) \
                or self.fabmap_exclude_recent < -1:
            raise ConfigError(f"EvaluationConfig.fabmap_exclude_recent={self.fabmap_exclude_recent!r} must be an "
                              "integer >= -1")
        for name in ("threshold", "bow_threshold"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
                raise ConfigError(f"EvaluationConfig.{name}={value!r} must be a number in [0, 1]")

    @property
    def fabmap_exclusion_frames(self) -> int:
        """The FAB-MAP posterior's exclusion window in frames (``fabmap_exclude_recent`` resolved)."""
        return self.min_gap - 1 if self.fabmap_exclude_recent < 0 else self.fabmap_exclude_recent


def fabmap_evaluation_config(base: FabMapConfig, exclude_recent_frames: int) -> FabMapConfig:
    """``base`` with what the evaluation fixes: the exclusion window, every frame a place, all candidates."""
    if exclude_recent_frames < 0:
        raise ConfigError(f"exclude_recent_frames={exclude_recent_frames} must be >= 0")
    return replace(
        base,
        exclude_recent_frames=exclude_recent_frames,  # the recognizer keeps places with query - frame > N
        exclude_recent_seconds=0.0,
        add_policy="all",
        keyframe_min_frames=1,
        keyframe_max_overlap=1.0,
        keyframe_max_frames=0,
        keyframe_max_seconds=0.0,
        exclude_linked_overlap=0.0,
        consistency_matches=1,  # the score matrix holds every frame's posterior; consistency is the online chain's
        top_k=1,  # the scores come from the full hypothesis arrays, not from the reported candidates
    )


# ------------------------------------------------------------------------------------------ scorers


def fabmap_posterior_matrix(
    observations: sp.csr_matrix,
    tree: ChowLiuTree,
    new_place_samples: sp.csr_matrix | None,
    config: FabMapConfig,
    exclude_recent_frames: int,
    exclude_samples: Sequence[int] | None = None,
    on_frame: FrameCallback | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """FAB-MAP 2 posteriors of a sequence, the places of the last ``exclude_recent_frames`` frames excluded.

    observations: (N, V) bag-of-words (value > 0 = word present). Returns ``scores`` (N, N) float64
    with ``[i, j]`` = p(place of frame j | query i) for ``j < i - exclude_recent_frames`` and 0 elsewhere
    (also 0 in the rows and columns of frames with fewer than ``config.min_words`` words: they are not
    recognised and are no places), and ``new_place`` (N,) float64 = p(new place | query i), nan for
    those frames.
    """
    matrix = sp.csr_matrix(observations)
    num_frames = matrix.shape[0]
    if matrix.shape[1] != tree.vocabulary_size:
        raise DataError(f"observations have {matrix.shape[1]} words, the Chow-Liu tree {tree.vocabulary_size}")
    if exclude_samples is not None and len(exclude_samples) != num_frames:
        raise DataError(f"exclude_samples has {len(exclude_samples)} entries for {num_frames} frames")
    matrix.sort_indices()
    recognizer = PlaceRecognizer(tree, new_place_samples, fabmap_evaluation_config(config, exclude_recent_frames),
                                 "evaluation")
    scores = np.zeros((num_frames, num_frames))
    new_place = np.zeros(num_frames)
    place_frames = np.zeros(num_frames, dtype=np.int64)  # place id -> frame (uninformative frames are no place)
    for i in range(num_frames):
        words = matrix.indices[matrix.indptr[i] : matrix.indptr[i + 1]].astype(np.int64)
        exclude = None if exclude_samples is None or exclude_samples[i] < 0 else int(exclude_samples[i])
        recognition = recognizer.process(words, i, exclude_sample=exclude)
        new_place[i] = recognition.new_place_probability
        # Every hypothesis, as arrays: one Python object per place and query would make a 5,000-frame
        # sequence take minutes.
        scores[i, place_frames[recognition.hypothesis_place_ids]] = recognition.hypothesis_probabilities
        if recognition.added_place_id >= 0:
            place_frames[recognition.added_place_id] = i
        if on_frame is not None:
            on_frame(i)
    return scores, new_place


def leave_one_out_samples(num_frames: int, sample_frames: np.ndarray) -> np.ndarray:
    """(N,) index of the new-place sample that is frame i, -1 where none (training on the test sequence).

    ``sample_frames``: (S,) frame index of each new-place sample, in sample order.
    """
    frames = np.asarray(sample_frames, dtype=np.int64)
    if frames.size and (frames.min() < 0 or frames.max() >= num_frames):
        raise DataError(f"sample frames must lie in [0, {num_frames}), got [{frames.min()}, {frames.max()}]")
    exclude = np.full(num_frames, -1, dtype=np.int64)
    exclude[frames] = np.arange(frames.size)
    return exclude


def tfidf_matrix(counts: sp.csr_matrix, idf_source: sp.csr_matrix | None) -> np.ndarray:
    """(N, N) tf-idf cosine similarity; idf from ``idf_source`` (training images) or the counts themselves."""
    return np.asarray(tfidf_score_matrix(counts, idf_source), dtype=np.float64)


# ------------------------------------------------------------------------------------------ methods


@dataclass(frozen=True)
class OnlineScores:
    """The nodes' decision chain run on the test sequence (``evaluation.online_chain``), scored per revisit event."""

    candidates: EventScores  # fabmap_node's loop_closure_candidates
    published: EventScores  # /loop_closures: verified (with --verify), else the candidates
    verified: bool
    num_places: int
    reliability: Reliability  # of each frame's best hypothesis, the posterior fabmap_node publishes
    num_tracked: int = 0  # published closures that loop tracking added (frames without a candidate of their own)
    # Revisiting frames each topic missed although their posterior ranked a true place (metrics.
    # missed_with_a_true_place_ranked): the decision's misses, not the ranking's.
    candidates_missed_ranked: int = 0
    published_missed_ranked: int = 0


@dataclass
class MethodResult:
    """One method's score matrix and metrics."""

    name: str
    vocabulary_kind: str
    vocabulary_size: int
    vocabulary_id: str
    scores: np.ndarray  # (N, N) float64, row i = query i
    metrics: LoopMetrics
    seconds: float
    new_place: np.ndarray | None = None  # (N,) FAB-MAP only
    model_path: str = ""
    label: str = ""  # distinguishes several models of one kind (their directory names)
    quantize_seconds: float = 0.0  # quantizing the test features (shared by the model's methods)
    verified: bool = False  # scores after geometric verification of the candidates
    # FAB-MAP with stamps only: the nodes' chain on the sequence, and the calibration of its posterior
    reliability: Reliability | None = None
    online: OnlineScores | None = None

    @property
    def title(self) -> str:
        name = f"{self.name} + GV" if self.verified else self.name
        return f"{name} ({self.label})" if self.label else name

    @property
    def false_positives_at_threshold(self) -> int:
        metrics = self.metrics
        if metrics.num_predictions_at_threshold == 0:
            return 0
        true = round(metrics.precision_at_threshold * metrics.num_predictions_at_threshold)
        return metrics.num_predictions_at_threshold - int(true)


def model_tree(model: Model) -> ChowLiuTree:
    if model.tree_matrix is None:
        raise ModelError(f"model {model.vocabulary_id} has no Chow-Liu tree: FAB-MAP needs one")
    return ChowLiuTree.from_matrix(model.tree_matrix)


def evaluate_model(
    model: Model,
    features: Sequence[Features],
    gt: np.ndarray,
    methods: Sequence[str],
    config: EvaluationConfig,
    fabmap_config: FabMapConfig,
    *,
    exclude_samples: Sequence[int] | None = None,
    on_frame: FrameCallback | None = None,
    label: str = "",
    model_path: str = "",
    verification: tuple[VerificationConfig, PairVerifier] | None = None,
    stamps_ns: np.ndarray | None = None,
    chain_inputs: ChainInputs | None = None,
) -> list[MethodResult]:
    """Run the ``methods`` (all of this model's vocabulary kind) on the test features and score them.

    With ``verification`` (a config and a verifier of the test features' pairs) every method also gets a
    "+ GV" result (``verification.geometric``). With ``stamps_ns`` every FAB-MAP method also runs the nodes'
    chain (``fabmap_config`` as the nodes use it; with ``verification``, verifier_node's chain on
    ``chain_inputs``: features, and depths and odometry where the evaluation has them): its ``online`` scores.
    """
    _check_methods(methods, model)
    if len(features) != gt.shape[0]:
        raise DataError(f"{len(features)} test frames but the ground truth is {gt.shape[0]}x{gt.shape[1]}")
    if verification is not None and chain_inputs is None:
        chain_inputs = ChainInputs(verification[0], features)
    started = time.monotonic()
    counts = count_bow(model.quantizer, features)
    quantize_seconds = time.monotonic() - started
    results = []
    for name in methods:
        started = time.monotonic()
        new_place = None
        online = None
        if METHODS[name][1] == "fabmap":
            scores, new_place = fabmap_posterior_matrix(
                counts, model_tree(model), model.new_place_samples, fabmap_config,
                config.fabmap_exclusion_frames, exclude_samples, on_frame,
            )
            threshold = config.threshold
            if stamps_ns is not None:
                online = online_scores(model, counts, stamps_ns, gt, config.min_gap, fabmap_config,
                                       chain_inputs if verification is not None else None)
        else:
            scores = tfidf_matrix(counts, model.new_place_samples)
            threshold = config.bow_threshold
        seconds = time.monotonic() - started
        results.append(MethodResult(
            name=name, vocabulary_kind=model.quantizer.kind, vocabulary_size=model.quantizer.size,
            scores=scores, metrics=evaluate_scores(scores, gt, config.min_gap, threshold), seconds=seconds,
            new_place=new_place, model_path=model_path, label=label, quantize_seconds=quantize_seconds,
            reliability=None if online is None else online.reliability,
            online=online, vocabulary_id=model.vocabulary_id,
        ))
        if verification is not None:
            results.append(verified_result(results[-1], verification, gt, config.min_gap,
                                           config.verify_more_candidates))
    return results


def _check_methods(methods: Sequence[str], model: Model) -> None:
    """ConfigError for a method that is unknown or needs another vocabulary kind than the model's."""
    for name in methods:
        if name not in METHODS:
            raise ConfigError(f"unknown method {name!r}; known: {', '.join(METHODS)}")
        if METHODS[name][0] != model.quantizer.kind:
            raise ConfigError(f"method {name} needs a {METHODS[name][0]} vocabulary, model {model.vocabulary_id} "
                              f"is {model.quantizer.kind}")


def online_scores(model: Model, counts: sp.csr_matrix, stamps_ns: np.ndarray, gt: np.ndarray, min_gap: int,
                  fabmap_config: FabMapConfig, verification: ChainInputs | None) -> OnlineScores:
    """The nodes' chain on the sequence (verified by verifier_node's chain with ``verification``), its
    candidates and published closures scored per revisit event."""
    chain = run_online_chain(counts, stamps_ns, model_tree(model), model.new_place_samples, fabmap_config,
                             verification)

    truth = np.asarray(gt).astype(bool)
    calibration = reliability(np.array([b.probability for b in chain.best]),
                              np.array([truth[b.query_frame, b.matched_frame] for b in chain.best], dtype=bool))
    candidates = [(c.query_frame, c.matched_frame) for c in chain.candidates]
    published = [(c.query_frame, c.matched_frame) for c in chain.published]
    return OnlineScores(event_scores(candidates, gt, min_gap), event_scores(published, gt, min_gap),
                        verification is not None, chain.num_places, calibration,
                        sum(c.tracked for c in chain.published),
                        missed_with_a_true_place_ranked(candidates, chain.ranked, gt, min_gap),
                        missed_with_a_true_place_ranked(published, chain.ranked, gt, min_gap))


def verified_result(result: MethodResult, verification: tuple[VerificationConfig, PairVerifier],
                    gt: np.ndarray, min_gap: int, more_candidates: int = 0) -> MethodResult:
    """``result`` after geometric verification of each query's best ``candidates`` candidates (and, when they
    all fail, the next ``more_candidates``)."""
    verification_config, verify = verification
    started = time.monotonic()
    scores = verified_scores(result.scores, verify, verification_config.candidates, min_gap, more_candidates)
    return replace(result, scores=scores, verified=True, seconds=result.seconds + time.monotonic() - started,
                   reliability=None, online=None,
                   metrics=evaluate_scores(scores, gt, min_gap, result.metrics.threshold))
