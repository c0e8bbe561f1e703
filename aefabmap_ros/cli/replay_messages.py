"""What aefabmap_replay publishes, and in which order: the bag's image topic and its ``--with`` companions,
each companion message before the image of its log time, lap after lap with ``--loop`` (stamps moved on
past the previous lap), compressed images on image_transport's ``/compressed`` topic."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io import bag_messages, bags
from aefabmap_ros.nodes.launch_table import compressed_topic
from aefabmap_ros.stamps import stamp_to_ns


def publish_topic(out_topic: str, msgtype: str) -> str:
    """Where a bag topic of ``msgtype`` goes: raw images on ``out_topic``, compressed ones on
    ``out_topic/compressed`` (image_transport's convention), unless ``out_topic`` already names it."""
    if msgtype != bag_messages.COMPRESSED_IMAGE_TYPE or out_topic.rstrip("/").endswith("/compressed"):
        return out_topic
    return compressed_topic(out_topic)


def restamped(raw: bytes, msgtype: str, offset_ns: int) -> bytes:
    """The message with its header stamp moved by ``offset_ns`` (used for --loop laps after the first)."""
    if offset_ns == 0:
        return raw
    typestore = bag_messages.get_typestore()
    message: Any = typestore.deserialize_cdr(raw, msgtype)
    message.header.stamp = bag_messages.make_time(stamp_to_ns(message.header.stamp) + offset_ns)
    return bytes(typestore.serialize_cdr(message, msgtype))


def laps(bag: Path, topic: str, start_ns: int | None, loop: bool,
          companions: list[str] | None = None) -> Iterator[tuple[int, bags.BagMessage]]:
    """(lap index, message) for one pass over the bag, or forever with --loop; with ``companions``
    their messages too, each before the image of its log time."""
    lap = 0
    while True:
        yielded = False
        for message in companions_first(bags.read_messages(bag, [topic, *(companions or [])], start_ns=start_ns),
                                        topic):
            yielded = True
            yield lap, message
        if not loop or not yielded:
            return
        lap += 1


def companions_first(messages: Iterable[bags.BagMessage], image_topic: str) -> Iterator[bags.BagMessage]:
    """The bag's messages with each image held back until the other topics' messages of the same log
    time are out: a frame's depth, CameraInfo and odometry reach the nodes before its image does."""
    held: bags.BagMessage | None = None
    for message in messages:
        if message.topic == image_topic:
            if held is not None:
                yield held
            held = message
            continue
        if held is not None and message.log_time_ns > held.log_time_ns:
            yield held
            held = None
        yield message
    if held is not None:
        yield held


def companion_types(bag: Path, topics: list[str]) -> dict[str, str]:
    """Message type of each --with topic; ConfigError naming a topic the bag does not have."""
    if not topics:
        return {}
    available = bags.list_topics(bag)
    missing = [topic for topic in topics if topic not in available]
    if missing:
        raise ConfigError(f"--with {' '.join(missing)}: not in {bag} (it has {', '.join(sorted(available))})")
    return {topic: available[topic] for topic in topics}
