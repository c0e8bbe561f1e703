"""Which of FAB-MAP's candidates the verifier refused: those whose query never reached the closures topic."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass


@dataclass(frozen=True)
class Candidate:
    """What a picture of a candidate needs: both stamps and what the caption says."""

    query_ns: int
    place_ns: int
    query_id: int
    place_id: int
    probability: float


class CandidateWatch:
    """Candidates by query stamp until a closure of the same query arrives (verified), or a closure of a later
    query does (refused: the verifier takes candidates in the order of their queries), or ``timeout_s`` passes
    with neither (refused: the verifier published nothing since). A lockstep replay lets the verifier fall tens
    of seconds behind, so the order, not the clock, is what tells a refusal; a closure is keyed by its query's
    image stamp, whichever place the verifier settles on."""

    def __init__(self, timeout_s: float, max_pending: int = 1000) -> None:
        self.timeout_s = timeout_s
        self.max_pending = max_pending
        self._pending: OrderedDict[int, tuple[Candidate, float]] = OrderedDict()
        self._verified: OrderedDict[int, None] = OrderedDict()  # queries verified before their candidate arrived
        self._refused: list[Candidate] = []  # passed over by a later query's closure

    def __len__(self) -> int:
        return len(self._pending)

    def add(self, candidate: Candidate, now_s: float) -> None:
        if candidate.query_ns in self._verified:  # the verifier answered first
            del self._verified[candidate.query_ns]
            return
        self._pending[candidate.query_ns] = (candidate, now_s + self.timeout_s)
        while len(self._pending) > self.max_pending:
            self._pending.popitem(last=False)

    def verified(self, query_ns: int) -> None:
        if self._pending.pop(query_ns, None) is None:
            self._verified[query_ns] = None
            while len(self._verified) > self.max_pending:
                self._verified.popitem(last=False)
        passed_over = [stamp for stamp in self._pending if stamp < query_ns]
        self._refused += [self._pending.pop(stamp)[0] for stamp in passed_over]

    def refused(self, now_s: float) -> list[Candidate]:
        """The candidates refused since the last call (passed over, or their time ran out), by query stamp;
        they are forgotten."""
        timed_out = [query_ns for query_ns, (_, deadline) in self._pending.items() if deadline <= now_s]
        refused = self._refused + [self._pending.pop(query_ns)[0] for query_ns in timed_out]
        self._refused = []
        return sorted(refused, key=lambda candidate: candidate.query_ns)
