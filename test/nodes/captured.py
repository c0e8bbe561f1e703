"""Stands in for a node's publisher in in-process tests."""

from __future__ import annotations

from typing import Any


class Captured:
    """Replaces a publisher's publish() to keep what the node sends."""

    def __init__(self, publisher: Any) -> None:
        self.messages: list[Any] = []
        publisher.publish = self.messages.append
