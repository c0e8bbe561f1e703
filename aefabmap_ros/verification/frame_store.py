"""Everything the verifier keeps of a past frame, by image stamp, in one store under one memory budget.

A loop closure is verified against the features of its query and of its matched place, its pose uses both
frames' keypoint depths, and loop tracking looks up the frames next to a verified place by their place in
the map (the timeline). One store holds the three, so a frame is added and forgotten in all of them at
once, and the whole is bounded twice: by a frame count and by the bytes of its arrays.

What is forgotten first when the budget is full. A frame that *created a place* of FAB-MAP's map can be
the matched place of any later revisit: forgetting it loses every closure to that place for the rest of
the run. A frame that joined an existing place (the scene had not changed) is needed only shortly: as a
query, and by loop tracking while a revisit of its stretch lasts. So the oldest frames known to have
joined a place go first; then the oldest of the rest -- places, and frames whose posterior has not come
yet (without posteriors every frame is of this kind, and the store forgets the oldest first). A frame
creates a place when its ``current_place_id`` is newer than every place seen before: places are numbered
in the order they are made (fabmap_node), which a reloaded timeline replays the same way.

Several robots (docs/fleet.md): frames are keyed by stamp, and a frame added with its robot's name keeps it
(``robot_of``), so a candidate naming a robot is never verified against another robot's frame of the same
stamp (the verification chain refuses it). Frames added without a robot, and frames reloaded from a folder
(the names are not saved), belong to any robot.

Not counted in the budget: the depth images waiting for their frame's features (``FrameDepthStore``'s
``max_waiting_bytes``, bounded on their own) and the timeline's 16 bytes a frame.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.io.atomic import remove_stale_temporaries
from aefabmap_ros.io.chunk_folder import chunk_pattern
from aefabmap_ros.verification.feature_store import FeatureStore, FeatureStoreFolder
from aefabmap_ros.verification.frame_depths import FrameDepthFolder, FrameDepths, FrameDepthStore
from aefabmap_ros.verification.loop_tracking import FrameTimeline, FrameTimelineFolder

# Posteriors that come before their frame's features: their roles wait this long (frames).
EARLY_ROLES_KEPT = 1000


class FrameRole(Enum):
    """What a stored frame is to the map: decides the order frames are forgotten in."""

    JOINED = "joined"  # joined an existing place: forgotten first
    UNKNOWN = "unknown"  # no posterior yet
    PLACE = "place"  # created a place: a revisit can match it


class FrameStore:
    """Features, keypoint depths and places of past frames, bounded by ``max_frames`` and ``max_bytes``."""

    def __init__(self, max_frames: int, max_bytes: int, max_features_per_frame: int = 0,
                 keep_depths: bool = False, folder: Path | None = None) -> None:
        if max_frames < 1 or max_bytes < 1:
            raise ConfigError(f"the frame store needs max_frames ({max_frames}) and max_bytes ({max_bytes}) >= 1")
        self.max_frames = max_frames
        self.max_bytes = max_bytes
        self.features = FeatureStore(max_frames, max_features_per_frame)
        self.depths = FrameDepthStore(max_frames) if keep_depths else None
        self.timeline = FrameTimeline(max_frames)
        self.evicted: dict[FrameRole, int] = dict.fromkeys(FrameRole, 0)
        # Stored stamps by role, oldest first (ordered sets).
        self._roles: dict[FrameRole, dict[int, None]] = {role: {} for role in FrameRole}
        self._early_roles: dict[int, FrameRole] = {}
        self._newest_place_id = -1
        self._robots: dict[int, str] = {}  # stamp -> robot of the frames added with one
        self.folder = folder  # saved to and reloaded from (``save``, ``load``); None: memory only
        self._feature_folder = None if folder is None else FeatureStoreFolder(folder)
        self._depth_folder = None if folder is None or self.depths is None else FrameDepthFolder(folder)
        self._timeline_folder = None if folder is None else FrameTimelineFolder(folder)

    def __len__(self) -> int:
        return len(self.features)

    def __contains__(self, stamp_ns: object) -> bool:
        return stamp_ns in self.features

    @property
    def nbytes(self) -> int:
        """Bytes of the kept arrays: features (keypoints, descriptors) and depths (keypoints, grids)."""
        return self.features.nbytes + (0 if self.depths is None else self.depths.nbytes)

    @property
    def has_unsaved(self) -> bool:
        """Frames (features, depths or places) added since the last save."""
        return bool(self.features.unsaved() or (self.depths is not None and self.depths.unsaved())
                    or self.timeline.unsaved())

    def get(self, stamp_ns: int) -> Features | None:
        return self.features.get(stamp_ns)

    def depths_of(self, stamp_ns: int) -> FrameDepths | None:
        return None if self.depths is None else self.depths.get(stamp_ns)

    def robot_of(self, stamp_ns: int) -> str | None:
        """The robot of a stored frame; None when it was stored without one (or is not stored)."""
        return self._robots.get(stamp_ns)

    def belongs(self, stamp_ns: int, robot: str) -> bool:
        """The frame at ``stamp_ns`` may be ``robot``'s: stored as its, or stored (or not) without a robot."""
        owner = self._robots.get(stamp_ns)
        return owner is None or owner == robot

    def add_features(self, stamp_ns: int, features: Features, robot: str | None = None) -> Features:
        """Store a frame's features (AefabmapError when malformed), of ``robot`` when given; the features as
        stored."""
        if stamp_ns not in self and len(self) >= self.max_frames:
            self._evict_one(keep=stamp_ns)
        self.features.add(stamp_ns, features)
        if robot is not None:
            self._robots[stamp_ns] = robot
        self._set_role(stamp_ns, self._early_roles.pop(stamp_ns, FrameRole.UNKNOWN))
        self._fit_budget(keep=stamp_ns)
        stored = self.features.get(stamp_ns)
        assert stored is not None, "the frame just added is never the one evicted"
        return stored

    def depths_changed(self, stamp_ns: int) -> None:
        """A frame's depths were sampled: they may take the store over its budget."""
        self._fit_budget(keep=stamp_ns)

    def add_place(self, stamp_ns: int, place_id: int) -> None:
        """The frame's place in the map, from its posterior: for loop tracking, and its role."""
        if not self.timeline.add(stamp_ns, place_id):
            return
        role = FrameRole.PLACE if place_id > self._newest_place_id else FrameRole.JOINED
        self._newest_place_id = max(self._newest_place_id, place_id)
        if stamp_ns in self:
            self._set_role(stamp_ns, role)
        else:
            self._early_roles[stamp_ns] = role
            while len(self._early_roles) > EARLY_ROLES_KEPT:
                del self._early_roles[next(iter(self._early_roles))]

    def role_of(self, stamp_ns: int) -> FrameRole | None:
        return next((role for role, stamps in self._roles.items() if stamp_ns in stamps), None)

    def _set_role(self, stamp_ns: int, role: FrameRole) -> None:
        for stamps in self._roles.values():
            stamps.pop(stamp_ns, None)
        self._roles[role][stamp_ns] = None

    def _fit_budget(self, keep: int) -> None:
        while self.nbytes > self.max_bytes and len(self) > 1:
            self._evict_one(keep)

    def _evict_one(self, keep: int) -> None:
        """Forget the oldest joined frame; else the oldest place or frame without a posterior (never ``keep``)."""
        joined = self._oldest(FrameRole.JOINED, keep)
        others = self._oldest(FrameRole.UNKNOWN, keep) + self._oldest(FrameRole.PLACE, keep)
        victim = joined[0] if joined else min(others)
        role = self.role_of(victim)
        assert role is not None
        self.evicted[role] += 1
        self.forget(victim)

    def _oldest(self, role: FrameRole, keep: int) -> list[int]:
        """The oldest stamp of that role other than ``keep`` (a list of at most one)."""
        for stamp_ns in self._roles[role]:
            if stamp_ns != keep:
                return [stamp_ns]
        return []

    def forget(self, stamp_ns: int) -> None:
        """Forget a frame's features and depths (its place stays in the timeline: 16 bytes)."""
        self.features.forget(stamp_ns)
        self._robots.pop(stamp_ns, None)
        if self.depths is not None:
            self.depths.forget(stamp_ns)
        for stamps in self._roles.values():
            stamps.pop(stamp_ns, None)

    # -------------------------------------------------------------------------------------- on disk

    def save(self, _folder: Path | None = None) -> None:
        """Append the frames added since the last save to the folder's chunk files (nothing without one)."""
        if self._feature_folder is not None:
            self._feature_folder.save(self.features)
        if self._depth_folder is not None and self.depths is not None:
            self._depth_folder.save(self.depths)
        if self._timeline_folder is not None:
            self._timeline_folder.save(self.timeline)

    def load(self) -> list[str]:
        """Replace the contents by what the folder holds (ModelError on a corrupt chunk: start-up stops, the
        file is kept); what was done, for the log."""
        if self.folder is None or self._feature_folder is None or self._timeline_folder is None:
            return []
        notes = []
        for chunk_folder in (FeatureStoreFolder, FrameDepthFolder, FrameTimelineFolder):
            for leftover in remove_stale_temporaries(self.folder, chunk_pattern(chunk_folder.PREFIX)):
                notes.append(f"deleted {leftover}, left by a save that was killed")
        self._feature_folder.load_into(self.features)
        if self._depth_folder is not None and self.depths is not None:
            self._depth_folder.load_into(self.depths)
        # Without it, loop tracking after a restart would never reach the frames stored before it.
        self._timeline_folder.load_into(self.timeline)
        self._roles_from_timeline()
        self._fit_budget(keep=max(self.features.stamps(), default=0))
        if len(self):
            notes.append(f"reloaded {len(self)} frames from {self.folder} (depths of "
                         f"{0 if self.depths is None else len(self.depths)}, places of {len(self.timeline)})")
        return notes

    def _roles_from_timeline(self) -> None:
        """The reloaded frames' roles, replayed from the timeline in stamp order."""
        for stamps in self._roles.values():
            stamps.clear()
        places = dict(self.timeline.frames())
        for stamp_ns in sorted(self.features.stamps()):
            place_id = places.get(stamp_ns)
            if place_id is None:
                role = FrameRole.UNKNOWN
            else:
                role = FrameRole.PLACE if place_id > self._newest_place_id else FrameRole.JOINED
                self._newest_place_id = max(self._newest_place_id, place_id)
            self._roles[role][stamp_ns] = None


def frame_bytes(features: Features, depths: FrameDepths | None) -> int:
    """A stored frame's bytes, as the budget counts them (an independent count for tests and sizing)."""
    total = features.keypoints.nbytes + features.descriptors.nbytes
    if depths is not None:
        total += depths.keypoints.nbytes + (0 if depths.grid is None else depths.grid.values.nbytes)
    return int(total)

