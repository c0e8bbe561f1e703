"""How a closure goes into the pose graph: keyframes at its endpoints, in their sessions' chains, the factors
that tie them, and, for a closure between two graphs, the join. The factors and iSAM2 are FactorGraph's
(backend/factor_graph.py); which closures come here is PoseGraph's (backend/pose_graph.py).

* every closure endpoint becomes a keyframe at its image stamp, its odometry pose interpolated between the
  two nearest odometry samples (SE(3) geodesic); a keyframe inserted between two existing ones splits their
  odometry factor in two;
* consecutive keyframes of a session are tied by odometry ``BetweenFactor``s whose noise grows with the
  distance travelled; a graph's first keyframe has a tight prior;
* a closure adds a ``BetweenFactor`` from the query keyframe to the matched place's, behind a Cauchy kernel;
* the first closure between two graphs joins them: the moved graph loses its prior and all its keyframes are
  moved, rigidly, onto the other's frame through the closure (query keyframe = place keyframe * closure^-1)
  before iSAM2 sees them. The anchored graph (the map frame) never moves: it is the first graph given a
  keyframe that ``_may_anchor`` allows (the place's of a closure before the query's), and the graph a closure
  joins to it is the one moved.
"""

from __future__ import annotations

import gtsam

from aefabmap_ros.backend.factor_graph import FactorGraph
from aefabmap_ros.backend.factors import FactorKind, FactorRecord, odometry_record, prior_record
from aefabmap_ros.backend.graph_types import Keyframe, SessionId
from aefabmap_ros.backend.sessions import Session

Endpoints = tuple[tuple[Session, int], tuple[Session, int]]  # (session, stamp) of a closure's query and place


class KeyframeGraph(FactorGraph):
    """A closure's keyframes and factors into the graph, in one iSAM2 update (module docstring)."""

    def _may_anchor(self, root: SessionId) -> bool:
        """Whether the graph rooted at that session may become the anchored one (the map frame): any may here;
        the pose graph keeps the map frame for its own robot's sessions."""
        return True

    def _add_loop(self, endpoints: Endpoints, loop: FactorRecord) -> bool:
        """A loop factor with ``loop``'s pose, covariance and Cauchy scale between the endpoints' keyframes (made
        where missing), by one iSAM2 update; when that fails, by QR on the graph kept before it
        (backend/factor_graph.py). False when QR fails too (``solver_error`` has gtsam's message): the graph is
        then as it was."""
        kept = self._keep()
        while True:
            try:
                self._insert_closure(endpoints, loop)
                return True
            except RuntimeError as exc:  # gtsam's IndeterminantLinearSystemException and kin
                self.solver_error = " ".join(str(exc).split())
                retry = self.factorization != "QR"
                # The failed update left its factors inside iSAM2: start again from the graph kept before it.
                self._restore(kept)
                self._rebuild("QR")
                if not retry:
                    return False

    def _insert_closure(self, endpoints: Endpoints, loop: FactorRecord) -> None:
        """Keyframes at both endpoints (made where missing), the loop factor between them and, when it joins two
        graphs, the moved graph; one iSAM2 update. A gtsam error leaves keyframes and iSAM2 half updated: the
        caller restores and rebuilds them."""
        records: list[FactorRecord] = []
        values = gtsam.Values()
        removed: list[int] = []
        (query, _), (place, _) = endpoints
        if self.anchor is None:  # the place's graph, else the query's, if it may hold the map frame
            self.anchor = next((root for root in (place.root, query.root) if self._may_anchor(root)), None)
        moving = None  # the root of the graph this closure moves onto the other's, when it joins two
        if query.root != place.root:
            moving = place.root if query.root == self.anchor else query.root
        for session in (query,) if query is place else (query, place):
            if not session.keyframes and session.odometry.first_ns is not None:
                # A session's first keyframe, at its first odometry pose; a prior there holds its graph (map ==
                # odom for the first session). One that joins another graph needs none: the closure places it.
                self._new_keyframe(session, session.odometry.first_ns, records, values, removed,
                                   prior=session.id != moving)
        keys = []
        for session, stamp_ns in endpoints:
            keyframe = (session.find_keyframe(stamp_ns)
                        or self._new_keyframe(session, stamp_ns, records, values, removed, prior=False))
            assert keyframe is not None  # resolvable, checked above
            keys.append(keyframe.key)
        records.append(FactorRecord(FactorKind.LOOP, keys[0], keys[1], loop.pose, loop.covariance, loop.cauchy_scale))
        start = None
        if moving is not None:
            start = self._join(moving, query, keys, loop.pose, values, removed)
        self._update(records, values, removed, start)

    def _join(self, moving: SessionId, query: Session, keys: list[int], query_to_place: gtsam.Pose3,
              values: gtsam.Values, removed: list[int]) -> gtsam.Values | None:
        """Move the graph rooted at ``moving`` onto the other's frame through the joining closure (keys: its query
        and place keyframes), rigidly, and drop its prior; the moved poses of new keyframes go into ``values``.

        Returns None when that graph had no keyframe in iSAM2 yet (an ordinary update then starts at the answer),
        else the whole estimate, moved: iSAM2 keeps a variable's linearisation point once it has it, so only a
        new iSAM2 starts near the answer, and ``_update`` builds one (a join happens once per session)."""
        query_pose, place_pose = (self._pose_of(key, values) for key in keys)
        if query.root == moving:  # the query keyframe, seen from the place: place * closure^-1
            offset = place_pose.compose(query_to_place.inverse()).compose(query_pose.inverse())
            stay = self._session_of(keys[1]).root
        else:
            offset = query_pose.compose(query_to_place).compose(place_pose.inverse())
            stay = query.root
        members = [session for session in self.sessions.values() if session.root == moving]
        moved = {keyframe.key for session in members for keyframe in session.keyframes}
        for key in moved:
            if values.exists(key):
                values.update(key, offset.compose(values.atPose3(key)))
        for session in members:
            session.root = stay
        if moving in self._priors:
            removed.append(self._priors.pop(moving))
        if not any(self._estimate.exists(key) for key in moved):
            return None
        estimate = gtsam.Values()
        keys = [int(key) for key in self._estimate.keys()]  # noqa: SIM118 - gtsam.Values is no dict
        for key in keys:
            pose = self._estimate.atPose3(key)
            estimate.insert(key, offset.compose(pose) if key in moved else pose)
        return estimate

    def _new_keyframe(self, session: Session, stamp_ns: int, records: list[FactorRecord], values: gtsam.Values,
                      removed: list[int], prior: bool) -> Keyframe | None:
        """A keyframe of ``session`` at ``stamp_ns``, its pose interpolated in the session's odometry, inserted in
        its chain (the odometry factor it splits removed, its own one or two added, a prior if ``prior`` and it
        is the session's first); None for a stamp outside the odometry."""
        found = session.odometry.pose_at(stamp_ns)
        if found is None:
            return None
        odometry, path_m = found
        keyframe = Keyframe(stamp_ns, self._next_key, odometry, path_m, session.id)
        self._next_key += 1
        self._key_sessions[keyframe.key] = session.id
        index = session.index_of(stamp_ns)
        before = session.keyframes[index - 1] if index > 0 else None
        after = session.keyframes[index] if index < len(session.keyframes) else None
        if before is None and after is None:
            values.insert(keyframe.key, odometry)  # the session's first keyframe: its odom frame is its graph's
            if prior:
                records.append(prior_record(keyframe.key, odometry))
        else:
            anchor = before if before is not None else after
            assert anchor is not None
            anchor_pose = self._pose_of(anchor.key, values)
            values.insert(keyframe.key, anchor_pose.compose(anchor.odometry.between(odometry)))
        if before is not None and after is not None and (before.key, after.key) in self._chain_factors:
            removed.append(self._chain_factors.pop((before.key, after.key)))  # split the factor it interrupts
        for first, second in ((before, keyframe), (keyframe, after)):
            if first is not None and second is not None:
                records.append(odometry_record(self.config, first, second))
        session.keyframes.insert(index, keyframe)
        return keyframe

