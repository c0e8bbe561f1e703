"""Stamps: the raw/compressed de-duplication of feature_node, the ordering stamp of a reloaded map."""

from __future__ import annotations

from aefabmap_ros.stamps import TransportDeduplicator, newest_stamp_up_to


def test_a_frame_from_the_other_transport_is_a_duplicate_and_a_repeat_on_the_same_one_is_not() -> None:
    seen = TransportDeduplicator(remembered=2)
    assert not seen.is_duplicate(10, "raw")
    assert seen.is_duplicate(10, "compressed")
    assert not seen.is_duplicate(10, "raw")  # the sender's own repeat: not ours to hide
    assert not seen.is_duplicate(20, "compressed")
    assert not seen.is_duplicate(30, "compressed")  # 10 is forgotten now: memory stays bounded
    assert not seen.is_duplicate(10, "compressed")


def test_the_newest_stamp_up_to_a_limit_skips_and_names_the_ones_beyond_it() -> None:
    assert newest_stamp_up_to([10, 20, 2_000, 30], limit_ns=100) == (30, [2])
    assert newest_stamp_up_to([10, 20, 2_000], limit_ns=None) == (2_000, [])  # no clock: every stamp counts
    assert newest_stamp_up_to([2_000], limit_ns=100) == (-1, [0])
    assert newest_stamp_up_to([], limit_ns=100) == (-1, [])
