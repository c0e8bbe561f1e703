"""rosbag2 bags (mcap and sqlite3) through `rosbags`, with no ROS installation needed.

The suite's own message types are registered from the ``aefabmap_msgs/msg/*.msg`` files
(``bag_messages.get_typestore``), so bags holding ``Features``, ``BagOfWords``, ``LoopClosure`` or
``PlacePosterior`` read and write like any standard type. Every failure a user can cause becomes a
``BagError`` naming the bag.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg
from rosbags.typesys import get_typestore as _rosbags_typestore
from rosbags.typesys.store import Typestore

from aefabmap_ros.errors import BagError
from aefabmap_ros.io.bag_messages import (
    CAMERA_INFO_TYPE,
    IMAGE_TYPE,
    IMAGE_TYPES,
    MESSAGE_PACKAGE,
    ODOMETRY_TYPE,
    get_typestore,
    make_camera_info_message,
    make_image_message,
    make_odometry_message,
)
from aefabmap_ros.stamps import stamp_to_ns

STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


def _storage_plugin(storage: str) -> StoragePlugin:
    try:
        return STORAGES[storage]
    except KeyError:
        raise BagError(f"unknown bag storage {storage!r}; choose one of {sorted(STORAGES)}") from None


def _replace_path(tmp_path: Path, path: Path, overwrite: bool) -> None:
    if path.exists():
        if not overwrite:
            shutil.rmtree(tmp_path, ignore_errors=True)
            raise BagError(f"output bag already exists: {path} (remove it or pass overwrite)")
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    os.replace(tmp_path, path)


class BagWriter:
    """Writes messages to a new bag, atomically: it appears at ``path`` only once closed cleanly.

    Use as a context manager; ``write`` takes rosbags message objects or already serialized CDR.
    """

    def __init__(self, path: Path, storage: str = "mcap", overwrite: bool = False) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise BagError(f"output bag already exists: {self.path} (remove it or pass overwrite)")
        if not self.path.parent.is_dir():
            raise BagError(f"output folder does not exist: {self.path.parent}")
        self._overwrite = overwrite
        # rosbags names the data file after the bag folder (<folder>/<folder>.mcap) and writes that name
        # into metadata.yaml (and the mcap's own metadata record). Writing into a folder already named
        # as rosbag2 names the first split, "<name>_0", inside a hidden staging folder, gives the finished
        # bag rosbag2's layout (<name>/<name>_0.mcap) with every reference consistent, and nothing hidden.
        self._staging_dir = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
        self._tmp_path = self._staging_dir / f"{self.path.name}_0"
        self._writer = Writer(self._tmp_path, version=9, storage_plugin=_storage_plugin(storage))
        self._connections: dict[str, Any] = {}
        self._typestore = get_typestore()

    def __enter__(self) -> BagWriter:
        shutil.rmtree(self._staging_dir, ignore_errors=True)
        try:
            self._staging_dir.mkdir()
            self._writer.open()
        except Exception as exc:  # rosbags raises several unrelated types for unwritable paths
            shutil.rmtree(self._staging_dir, ignore_errors=True)
            raise BagError(f"cannot create bag {self.path}: {exc}") from exc
        return self

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=self._typestore)

    def write(self, topic: str, timestamp_ns: int, message: Any) -> None:
        connection = self._connections.get(topic)
        if connection is None:
            raise BagError(f"topic {topic!r} was not added to bag {self.path}")
        data = message if isinstance(message, bytes | memoryview) else self._typestore.serialize_cdr(
            message, connection.msgtype
        )
        self._writer.write(connection, int(timestamp_ns), data)

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            self._writer.close()
            if exc_type is None:
                _replace_path(self._tmp_path, self.path, self._overwrite)
        finally:
            shutil.rmtree(self._staging_dir, ignore_errors=True)


def write_image_bag(
    path: Path,
    topic: str,
    frames: Iterable[tuple[int, np.ndarray]],
    *,
    storage: str = "mcap",
    frame_id: str = "camera",
    overwrite: bool = False,
) -> int:
    """Write ``(stamp_ns, image)`` frames as ``sensor_msgs/Image``; returns the number written."""
    count = 0
    with BagWriter(path, storage=storage, overwrite=overwrite) as writer:
        writer.add_topic(topic, IMAGE_TYPE)
        for stamp_ns, image in frames:
            writer.write(topic, stamp_ns, make_image_message(image, stamp_ns, frame_id))
            count += 1
    return count


def sibling_topic(image_topic: str, name: str) -> str:
    """A topic in the image topic's namespace: ("/camera/image", "camera_info") -> "/camera/camera_info"."""
    namespace = image_topic.rsplit("/", 1)[0] if "/" in image_topic else ""
    return f"{namespace}/{name}"


def write_rgbd_bag(
    path: Path,
    image_topic: str,
    frames: Iterable[tuple[int, np.ndarray, np.ndarray]],
    camera_matrix: np.ndarray,
    *,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    storage: str = "mcap",
    frame_id: str = "camera",
    overwrite: bool = False,
    odometry: np.ndarray | None = None,
    odometry_topic: str = "/odom",
) -> int:
    """Write ``(stamp_ns, image, depth_mm)`` frames: the image, a 16UC1 depth image and a CameraInfo,
    all with the frame's stamp. Topics default to ``<namespace>/depth`` and ``<namespace>/camera_info``
    beside the image topic. With ``odometry`` ((N, 3|4, 4) camera-to-odom poses, one per frame) a
    ``nav_msgs/Odometry`` (frame ``odom``, child ``frame_id``) goes on ``odometry_topic`` with each
    frame's stamp, written before the frame's image: a backend has the odometry of a frame before any
    loop closure of that frame. Returns the number of frames written."""
    depth_topic = depth_topic or sibling_topic(image_topic, "depth")
    camera_info_topic = camera_info_topic or sibling_topic(image_topic, "camera_info")
    count = 0
    with BagWriter(path, storage=storage, overwrite=overwrite) as writer:
        writer.add_topic(image_topic, IMAGE_TYPE)
        writer.add_topic(depth_topic, IMAGE_TYPE)
        writer.add_topic(camera_info_topic, CAMERA_INFO_TYPE)
        if odometry is not None:
            writer.add_topic(odometry_topic, ODOMETRY_TYPE)
        for stamp_ns, image, depth_mm in frames:
            if depth_mm.dtype != np.uint16 or depth_mm.shape != image.shape[:2]:
                raise BagError(f"frame {count}: depth must be uint16 {image.shape[:2]}, "
                               f"got {depth_mm.dtype} {depth_mm.shape}")
            if odometry is not None:
                if count >= len(odometry):
                    raise BagError(f"{len(odometry)} odometry poses for more frames")
                writer.write(odometry_topic, stamp_ns,
                             make_odometry_message(odometry[count], stamp_ns, child_frame_id=frame_id))
            writer.write(image_topic, stamp_ns, make_image_message(image, stamp_ns, frame_id))
            writer.write(depth_topic, stamp_ns, make_image_message(depth_mm, stamp_ns, frame_id))
            info = make_camera_info_message(camera_matrix, image.shape[1], image.shape[0], stamp_ns, frame_id)
            writer.write(camera_info_topic, stamp_ns, info)
            count += 1
    if odometry is not None and count != len(odometry):
        raise BagError(f"{len(odometry)} odometry poses for {count} frames")
    return count


@dataclass(frozen=True)
class BagMessage:
    """One deserialized message: bag log time, header stamp (log time where there is none)."""

    topic: str
    msgtype: str
    log_time_ns: int
    stamp_ns: int
    message: Any
    raw: bytes


def _open_reader(path: Path) -> Reader:
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag does not exist: {path}")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags' errors for corrupt metadata/storage vary by plugin
        raise BagError(f"cannot open bag {path}: {exc}") from exc
    return reader


def list_topics(path: Path) -> dict[str, str]:
    """Topic name -> message type of every connection in the bag."""
    reader = _open_reader(path)
    try:
        return {connection.topic: connection.msgtype for connection in reader.connections}
    finally:
        reader.close()


def message_count(path: Path, topic: str) -> int:
    """Number of messages on ``topic``, from the bag's metadata (nothing is deserialized)."""
    reader = _open_reader(path)
    try:
        return sum(connection.msgcount for connection in reader.connections if connection.topic == topic)
    finally:
        reader.close()


def _connection_typestore(connection: Any, ours: Typestore) -> Typestore:
    """Our type store, unless the bag recorded one of our message types with another definition (a
    recording made before a field was added, e.g. LoopClosure's relative pose): then a store built from
    the bag's own definition, so older recordings stay readable."""
    if not connection.msgtype.startswith(f"{MESSAGE_PACKAGE}/"):
        return ours
    definition = getattr(getattr(connection, "msgdef", None), "data", "")
    if not definition:
        return ours
    try:
        recorded = get_types_from_msg(definition, connection.msgtype)
    except Exception:  # an unparsable definition: try ours, which reports a bad message as corrupt
        return ours
    if recorded[connection.msgtype][1] == ours.fielddefs.get(connection.msgtype, (None, None))[1]:
        return ours
    store = _rosbags_typestore(Stores.ROS2_JAZZY)
    store.register({name: fields for name, fields in recorded.items() if name.startswith(f"{MESSAGE_PACKAGE}/")})
    return store


def read_messages(
    path: Path, topics: Iterable[str], start_ns: int | None = None, stop_ns: int | None = None
) -> Iterator[BagMessage]:
    """Deserialized messages of ``topics`` in log-time order; a missing topic is a ``BagError``."""
    wanted = list(topics)
    reader = _open_reader(path)
    typestore = get_typestore()
    try:
        available = {connection.topic for connection in reader.connections}
        missing = [topic for topic in wanted if topic not in available]
        if missing:
            raise BagError(
                f"topic(s) {missing} not in bag {path}; it has: {sorted(available) or 'no topics'}"
            )
        connections = [c for c in reader.connections if c.topic in wanted]
        stores = {connection.id: _connection_typestore(connection, typestore) for connection in connections}
        try:
            for connection, log_time_ns, raw in reader.messages(connections, start=start_ns, stop=stop_ns):
                message = stores[connection.id].deserialize_cdr(raw, connection.msgtype)
                header = getattr(message, "header", None)
                stamp_ns = stamp_to_ns(header.stamp) if header is not None else 0
                yield BagMessage(
                    topic=connection.topic,
                    msgtype=connection.msgtype,
                    log_time_ns=int(log_time_ns),
                    stamp_ns=stamp_ns or int(log_time_ns),
                    message=message,
                    raw=bytes(raw),
                )
        except BagError:
            raise
        except Exception as exc:  # truncated chunks, bad CDR: name the bag, never a bare traceback
            raise BagError(f"bag {path} is corrupt or unreadable: {exc}") from exc
    finally:
        reader.close()


def require_image_topic(path: Path, topic: str) -> str:
    """The message type of ``topic``, which must be an Image or CompressedImage topic of the bag."""
    topics = list_topics(path)
    if topic not in topics:
        image_topics = sorted(t for t, kind in topics.items() if kind in IMAGE_TYPES)
        raise BagError(f"topic {topic!r} not in bag {path}; its image topics: {image_topics or 'none'}")
    if topics[topic] not in IMAGE_TYPES:
        raise BagError(f"topic {topic!r} in bag {path} is {topics[topic]}, not an image type {IMAGE_TYPES}")
    return topics[topic]
