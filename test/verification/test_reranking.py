"""Re-ranking by inliers: the candidate walk against brute force and a scripted verifier."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.verification.geometric import Verification
from aefabmap_ros.verification.reranking import Reranked, rerank_by_inliers, verified_scores


class FakeVerifier:
    """Gives each listed (query, place) pair its inlier count (accepted at >= 20) and records the calls."""

    def __init__(self, inliers: dict[tuple[int, int], int] | set[tuple[int, int]]) -> None:
        self.inliers = inliers if isinstance(inliers, dict) else dict.fromkeys(inliers, 40)
        self.calls: list[tuple[int, int]] = []

    def __call__(self, query: int, place: int) -> Verification:
        self.calls.append((query, place))
        inliers = self.inliers.get((query, place), 3)
        return Verification(matches=50, inliers=inliers, accepted=inliers >= 20)


def test_the_accepted_candidate_with_most_inliers_gets_the_best_accepted_score() -> None:
    scores = np.zeros((6, 6))
    scores[5, :4] = [0.1, 0.6, 0.3, 0.0]
    scores[4, :3] = [0.5, 0.4, 0.05]
    verify = FakeVerifier({(5, 2): 25, (5, 0): 60, (4, 0): 30, (4, 2): 25})
    out = verified_scores(scores, verify, candidates=5, min_gap=2)
    expected = np.zeros((6, 6))
    expected[5, 0] = 0.3  # place 0 has the most inliers; 0.3 is the best accepted place's (2) score
    expected[4, 0] = 0.5  # the best candidate is also the best verified one
    np.testing.assert_array_equal(out, expected)
    # Every positive candidate among the best 5 is verified, best first; zero scores never are.
    assert verify.calls == [(4, 0), (4, 1), (4, 2), (5, 1), (5, 2), (5, 0)]


def test_rerank_ties_go_to_the_better_ranked_and_require_best_stops_at_a_rejected_best() -> None:
    results = {"a": Verification(50, 30, True), "b": Verification(50, 30, True), "c": Verification(50, 5, False)}
    calls: list[str] = []

    def verify(name: str) -> Verification:
        calls.append(name)
        return results[name]

    outcome = rerank_by_inliers(["c", "a", "b"], verify)
    assert outcome == Reranked(winner=1, verification=results["a"], best_accepted=1)
    assert calls == ["c", "a", "b"]
    calls.clear()
    assert rerank_by_inliers(["c", "a", "b"], verify, require_best=True) is None and calls == ["c"]
    assert rerank_by_inliers(["c"], verify) is None and rerank_by_inliers([], verify) is None


def test_rerank_searches_deeper_only_when_every_best_candidate_fails() -> None:
    results = {"refused": Verification(50, 5, False), "weak": Verification(50, 30, True),
               "strong": Verification(50, 90, True), "deep": Verification(50, 60, True)}
    calls: list[str] = []

    def verify(name: str) -> Verification:
        calls.append(name)
        return results[name]

    # The best two hold a match: the deeper candidates are never verified, however many inliers they have.
    outcome = rerank_by_inliers(["refused", "weak", "strong", "deep"], verify, first=2)
    assert outcome == Reranked(winner=1, verification=results["weak"], best_accepted=1) and len(calls) == 2
    calls.clear()
    # Both best refused: the rest are verified and re-ranked among themselves, ranks still index the whole list.
    outcome = rerank_by_inliers(["refused", "refused", "deep", "strong"], verify, first=2)
    assert outcome == Reranked(winner=3, verification=results["strong"], best_accepted=2) and len(calls) == 4
    calls.clear()
    # A loop closure's own verification (require_best) never goes deeper than a refused best.
    assert rerank_by_inliers(["refused", "strong"], verify, require_best=True, first=1) is None and calls == ["refused"]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 6), st.integers(1, 4), st.integers(0, 4))
def test_verified_scores_equal_a_brute_force_reranking(seed: int, candidates: int, min_gap: int,
                                                       more_candidates: int) -> None:
    """Reference: sort each row's eligible places in plain Python (score, then recency), verify the
    best K with a positive score, keep the accepted one with most inliers (first on ties); when none is
    accepted, the same with the next ``more_candidates``."""
    rng = np.random.default_rng(seed)
    size = 9
    scores = np.round(rng.random((size, size)), 1) * (rng.random((size, size)) < 0.7)  # ties and zeros
    inliers = {(q, p): int(rng.integers(0, 60)) for q in range(size) for p in range(size)}
    out = verified_scores(scores, FakeVerifier(inliers), candidates, min_gap, more_candidates)
    expected = np.zeros((size, size))
    for query in range(min_gap, size):
        eligible = sorted(range(query - min_gap + 1), key=lambda p: (-scores[query, p], -p))
        for tried in (eligible[:candidates], eligible[candidates : candidates + more_candidates]):
            tried = [p for p in tried if scores[query, p] > 0]
            accepted = [p for p in tried if inliers[query, p] >= 20]
            if accepted:
                best = max(accepted, key=lambda p: (inliers[query, p], -tried.index(p)))
                expected[query, best] = scores[query, accepted[0]]
                break
    np.testing.assert_array_equal(out, expected)


def test_only_the_best_candidates_are_tried_and_never_ineligible_or_zero_ones() -> None:
    scores = np.zeros((8, 8))
    scores[7, :7] = [0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.7]  # 5 and 6 are within the gap
    verify = FakeVerifier({(7, 0)})
    out = verified_scores(scores, verify, candidates=3, min_gap=3)
    assert not out.any()  # place 0 is the 5th eligible candidate: not tried
    assert verify.calls == [(7, 4), (7, 3), (7, 2)]
    zero_row = np.zeros((8, 8))
    assert not verified_scores(zero_row, verify, candidates=3, min_gap=3).any() and len(verify.calls) == 3


def test_ties_try_the_most_recent_place_first() -> None:
    scores = np.zeros((5, 5))
    scores[4, :3] = [0.4, 0.4, 0.2]
    verify = FakeVerifier({(4, 0), (4, 1)})
    out = verified_scores(scores, verify, candidates=2, min_gap=2)
    assert out[4, 1] == 0.4 and out[4, 0] == 0.0


def test_walk_rejects_bad_arguments() -> None:
    with pytest.raises(DataError, match="square"):
        verified_scores(np.zeros((3, 4)), FakeVerifier(set()), 1, 1)
    with pytest.raises(ConfigError, match="must be >= 1"):
        verified_scores(np.zeros((3, 3)), FakeVerifier(set()), 0, 1)
    with pytest.raises(ConfigError, match="more_candidates"):
        verified_scores(np.zeros((3, 3)), FakeVerifier(set()), 1, 1, -1)
