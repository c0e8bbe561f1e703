"""What the place recognizer answers for one frame: its candidates among the known places, the match, the
loop closure, the place it made or belongs to, and the session and robot of each (fabmap/recognizer.py)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Candidate:
    """A known place as a hypothesis for the query."""

    place_id: int
    stamp_ns: int  # stamp of the frame the place was created from
    probability: float
    log_likelihood: float  # FAB-MAP 2 scale: relative to a place without words
    session: int = 0  # session the place was made in
    robot: str = ""  # robot of that session


@dataclass(frozen=True)
class Recognition:
    """The outcome of one frame."""

    query_id: int
    stamp_ns: int
    assigned_place_id: int  # matched place, else the place created from this frame, else -1
    is_new_place: bool  # no known place exceeded the match threshold
    new_place_probability: float
    candidates: tuple[Candidate, ...]  # top-K places by posterior, best first
    loop_closure: Candidate | None  # the match, once it is temporally consistent (see consistency_matches)
    added_place_id: int = -1  # place created from this frame, -1 if none (policy / keyframing)
    new_place_log_likelihood: float = 0.0
    # False: fewer than ``min_words`` words; nothing was decided (no candidates, no place, and
    # ``new_place_probability`` is nan).
    informative: bool = True
    match: Candidate | None = None  # best place above match_threshold, consistent or not
    # The place of the map this frame belongs to: the one it created, else the newest place of its robot's
    # session, which it joined because the scene had not changed; -1 before that session's first place.
    current_place_id: int = -1
    # Every hypothesis of the posterior: (H,) place ids (increasing) and their probabilities (arrays:
    # left out of ==, which compares the decision).
    hypothesis_place_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), compare=False)
    hypothesis_probabilities: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False)
    session: int = 0  # session of the query frame
    robot: str = ""  # robot of that session


def jaccard(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∩ b| / |a ∪ b| of two sorted unique word-id arrays; 1.0 for two empty sets."""
    union = a.size + b.size
    if union == 0:
        return 1.0
    common = np.intersect1d(a, b, assume_unique=True).size
    return common / (union - common)
