"""Stamps: the raw/compressed de-duplication of feature_node."""

from __future__ import annotations

from aefabmap_ros.stamps import TransportDeduplicator


def test_a_frame_from_the_other_transport_is_a_duplicate_and_a_repeat_on_the_same_one_is_not() -> None:
    seen = TransportDeduplicator(remembered=2)
    assert not seen.is_duplicate(10, "raw")
    assert seen.is_duplicate(10, "compressed")
    assert not seen.is_duplicate(10, "raw")  # the sender's own repeat: not ours to hide
    assert not seen.is_duplicate(20, "compressed")
    assert not seen.is_duplicate(30, "compressed")  # 10 is forgotten now: memory stays bounded
    assert not seen.is_duplicate(10, "compressed")
