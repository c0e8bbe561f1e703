"""The factors of the pose graph and the iSAM2 that solves them: each factor recorded with its iSAM2 number,
the graph updated incrementally, and rebuilt from the records when it has to be.

iSAM2 numbers the factors in the order they are added. The numbers of the odometry factors are kept by the
pair of keyframes they tie, so that a keyframe inserted between two can remove the factor it splits; those of
the priors by the session whose graph they hold, so that a join can remove the moved graph's. A rebuilt
iSAM2 numbers the kept factors anew, and every number kept is translated.

iSAM2 factors by Cholesky, on the normal equations: fast, but it squares the system's condition
number, and a keyframe far from the anchor (30 km along a straight road, with the loop factors' 5 cm)
makes the system look singular to it (gtsam's "indeterminate linear system"). A closure whose update
fails so is added again by QR on a graph rebuilt from the factors kept before it (``factorization``
is then "QR" for good: slower per closure, and exact where Cholesky gave up); a closure QR
cannot take either is refused, the graph as it was (``_keep`` / ``_restore``). Either way no gtsam error
leaves the graph half updated.

The factors are kept as ``FactorRecord``s (backend/factors.py): iSAM2 is rebuilt from them, and graph_file.py
saves them and gives them back to ``load``.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from aefabmap_ros.backend.factors import FactorKind, FactorRecord
from aefabmap_ros.backend.graph_types import Keyframe, PoseGraphConfig, SessionId
from aefabmap_ros.backend.sessions import Session

# Extra iSAM2 iterations after a closure, and the largest keyframe move (m) at which they stop.
MAX_EXTRA_ITERATIONS = 20
SETTLED_M = 0.001


@dataclass(frozen=True)
class _Kept:
    """What a failed update must not leave changed (the estimate is replaced, never changed in place)."""

    sessions: dict[SessionId, tuple[list[Keyframe], SessionId]]
    chain_factors: dict[tuple[int, int], int]
    priors: dict[SessionId, int]
    factors: dict[int, FactorRecord]
    next_key: int
    estimate: gtsam.Values
    anchor: SessionId | None


def _isam_params(factorization: str) -> gtsam.ISAM2Params:
    params = gtsam.ISAM2Params()
    # Relinearise every step: the robust kernel's weights change as the graph moves (see _update).
    params.relinearizeSkip = 1
    params.setRelinearizeThreshold(0.01)
    params.setFactorization(factorization)
    return params


class FactorGraph:
    """Sessions with their keyframes, the factors recorded and the iSAM2 that solves them (module docstring).
    Keyframe poses are ``T_map_base``; a session not joined yet has them in its own graph's frame."""

    def __init__(self, config: PoseGraphConfig) -> None:
        self.config = config
        self.sessions: dict[SessionId, Session] = {}
        self.anchor: SessionId | None = None  # root of the joined graph: the first session given a keyframe
        self._chain_factors: dict[tuple[int, int], int] = {}  # (key before, key after) -> iSAM2 factor index
        self._priors: dict[SessionId, int] = {}  # root session -> iSAM2 index of the prior holding its graph
        self.factors: dict[int, FactorRecord] = {}  # iSAM2 factor index -> factor, the graph's own
        self._key_sessions: dict[int, SessionId] = {}
        self._next_key = 0
        self.factorization = "CHOLESKY"  # "QR" once Cholesky failed on this graph (module docstring)
        self.solver_error = ""  # gtsam's message of the last update that failed
        self._isam = gtsam.ISAM2(_isam_params(self.factorization))
        self._estimate = gtsam.Values()

    @property
    def keyframes(self) -> list[Keyframe]:
        """Every session's keyframes, session after session, each session's by stamp."""
        return [keyframe for session in self.sessions.values() for keyframe in session.keyframes]

    def estimate_of(self, key: int) -> gtsam.Pose3:
        """The optimised pose of a keyframe, by key."""
        return self._estimate.atPose3(key)

    def _session_of(self, key: int) -> Session:
        return self.sessions[self._key_sessions[key]]

    def _pose_of(self, key: int, pending: gtsam.Values) -> gtsam.Pose3:
        return pending.atPose3(key) if pending.exists(key) else self._estimate.atPose3(key)

    # -- iSAM2 --------------------------------------------------------------------------------------------

    def _update(self, records: list[FactorRecord], values: gtsam.Values, removed: list[int],
                start: gtsam.Values | None = None) -> None:
        """One iSAM2 update and its extra iterations; the factors are recorded once all of it succeeded.
        With ``start`` (a join's moved estimate), a new iSAM2 takes every factor kept and the new ones there."""
        graph = gtsam.NonlinearFactorGraph()
        for record in records:
            graph.add(record.factor())
        if start is None:
            result = self._isam.update(graph, values, removed)
            new_indices = [int(index) for index in result.getNewFactorsIndices()]
        else:
            dropped = set(removed)
            removed = []
            new_indices = self._restart([index for index in sorted(self.factors) if index not in dropped],
                                        self.factorization, start, graph, values)
        # The Cauchy kernel is re-weighted at each relinearisation (IRLS): a true closure far from the
        # drifted estimate starts with a small weight and gains it as the graph moves towards it; a wrong one
        # stays far and keeps a small weight. A few more iterations, until the estimate settles.
        keys = [keyframe.key for keyframe in self.keyframes]
        for _ in range(MAX_EXTRA_ITERATIONS):
            before = self._isam.calculateEstimate()
            self._isam.update()
            if _largest_change(before, self._isam.calculateEstimate(), keys) < SETTLED_M:
                break
        self._estimate = self._isam.calculateEstimate()
        # iSAM2 numbers the new factors in the order they were added: remember the odometry factors' numbers
        # so that a keyframe inserted later between two keyframes can remove the factor it splits, and the
        # priors' so that a join can remove its graph's.
        for record, index in zip(records, new_indices, strict=True):
            self._record(index, record)
        for index in removed:
            self.factors.pop(index, None)

    def _record(self, index: int, record: FactorRecord) -> None:
        self.factors[index] = record
        if record.kind is FactorKind.ODOMETRY:
            self._chain_factors[(record.first, record.second)] = index
        elif record.kind is FactorKind.PRIOR:
            self._priors[self._session_of(record.first).root] = index

    def _restart(self, kept: list[int], factorization: str, estimate: gtsam.Values,
                 graph: gtsam.NonlinearFactorGraph | None = None, values: gtsam.Values | None = None) -> list[int]:
        """A new iSAM2 (``factorization``) holding the recorded factors numbered ``kept`` (renumbered; the others
        forgotten) and ``graph``'s new ones, at ``estimate`` and ``values``; the new factors' numbers."""
        self.factorization = factorization
        self._isam = gtsam.ISAM2(_isam_params(factorization))
        full = gtsam.NonlinearFactorGraph()
        for index in kept:
            full.add(self.factors[index].factor())
        added = 0 if graph is None else graph.size()
        for position in range(added):
            assert graph is not None
            full.add(graph.at(position))
        initial = gtsam.Values(estimate)
        if values is not None:
            initial.insert(values)
        if full.size() == 0:
            self._estimate = gtsam.Values()
            self.factors, self._chain_factors, self._priors = {}, {}, {}
            return []
        result = self._isam.update(full, initial)
        indices = [int(index) for index in result.getNewFactorsIndices()]
        renumbered = dict(zip(kept, indices[:len(kept)], strict=True))
        self.factors = {renumbered[index]: self.factors[index] for index in kept}
        self._chain_factors = {pair: renumbered[index] for pair, index in self._chain_factors.items()
                               if index in renumbered}
        self._priors = {root: renumbered[index] for root, index in self._priors.items() if index in renumbered}
        self._estimate = self._isam.calculateEstimate()
        return indices[len(kept):]

    def _rebuild(self, factorization: str) -> None:
        """A new iSAM2 (``factorization``) holding the recorded factors at the last estimate."""
        self._restart(sorted(self.factors), factorization, self._estimate)

    def _keep(self) -> _Kept:
        sessions = {session_id: (list(session.keyframes), session.root)
                    for session_id, session in self.sessions.items()}
        return _Kept(sessions, dict(self._chain_factors), dict(self._priors), dict(self.factors), self._next_key,
                     self._estimate, self.anchor)

    def _restore(self, kept: _Kept) -> None:
        for session_id, (keyframes, root) in kept.sessions.items():
            self.sessions[session_id].keyframes, self.sessions[session_id].root = list(keyframes), root
        self._chain_factors, self._priors = dict(kept.chain_factors), dict(kept.priors)
        self.factors, self._next_key = dict(kept.factors), kept.next_key
        self._estimate, self.anchor = kept.estimate, kept.anchor

    # -- a saved graph (backend/graph_file.py) ------------------------------------------------------------

    def load(self, sessions: list[Session], anchor: SessionId | None, records: list[FactorRecord],
             estimate: gtsam.Values, factorization: str) -> None:
        """Take a saved graph into this empty one and rebuild iSAM2 from its factors at the saved estimate.

        No session is made current: PoseGraph's first closure of the next run names one (a reloaded session
        named again continues its odometry). RuntimeError (gtsam's) when the factors cannot be solved."""
        if self.sessions or self.factors:
            raise ValueError("a saved graph is loaded into an empty one only")
        self.sessions = {session.id: session for session in sessions}
        self.anchor = anchor
        self._key_sessions = {keyframe.key: session.id for session in sessions for keyframe in session.keyframes}
        self._next_key = max(self._key_sessions, default=-1) + 1
        self.factors, self._chain_factors, self._priors = {}, {}, {}
        for index, record in enumerate(records):
            self._record(index, record)
        self._estimate = estimate
        self._rebuild(factorization)


def _largest_change(before: gtsam.Values, after: gtsam.Values, keys: list[int]) -> float:
    return max((float(np.linalg.norm(before.atPose3(key).translation() - after.atPose3(key).translation()))
                for key in keys), default=0.0)

